"""Approximations of the event probability that evnoise does *not* use, measured for comparison.

Both treat ``S = n - e^eps n0`` (``n, n0 ~ Poisson(lam)``) as if it were continuous; the event is
``S > (e^eps - 1) b``. They are cheap and accurate only when ``lam`` is large and the
probability is not deep in the tail; the benchmark report shows how far they are from the
exact form, which is why evnoise evaluates the exact windowed sum everywhere.
"""

from __future__ import annotations

import numpy as np
from scipy.special import log_ndtr, ndtr


def continuity_corrected_normal(lam, eps, bias):
    """Normal approximation of ``S`` with a half-photon continuity correction on ``n``."""
    lam = np.asarray(lam, dtype=np.float64)
    a = np.exp(eps)
    mean = lam * (1.0 - a)
    sd = np.sqrt(lam * (1.0 + a * a))
    threshold = (a - 1.0) * bias + 0.5  # n > x  ->  n >= floor(x) + 1 ~ n > x + 1/2 on average
    return ndtr((mean - threshold) / sd)


def saddle_point(lam, eps, bias, iterations: int = 60):
    """Lugannani-Rice saddle-point tail of ``S`` (continuous form, no lattice correction)."""
    lam = np.asarray(lam, dtype=np.float64)
    a = float(np.exp(eps))
    t = (a - 1.0) * bias
    # K(th) = lam (e^th - 1) + lam (e^{-a th} - 1);  K'(th) = lam (e^th - a e^{-a th}) = t
    lo = np.zeros_like(lam)
    hi = np.ones_like(lam)
    for _ in range(200):
        short = lam * (np.exp(hi) - a * np.exp(-a * hi)) < t
        if not short.any():
            break
        hi = np.where(short, 2 * hi, hi)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        below = lam * (np.exp(mid) - a * np.exp(-a * mid)) < t
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    th = 0.5 * (lo + hi)
    k = lam * (np.expm1(th) + np.expm1(-a * th))
    k2 = lam * (np.exp(th) + a * a * np.exp(-a * th))
    w = np.sqrt(np.maximum(2.0 * (th * t - k), 0.0))
    u = th * np.sqrt(k2)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_phi = -0.5 * w * w - 0.5 * np.log(2 * np.pi)
        p = np.exp(log_ndtr(-w)) + np.exp(log_phi) * (1.0 / u - 1.0 / w)
    return np.clip(p, 0.0, 1.0)
