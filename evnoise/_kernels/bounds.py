"""Rigorous upper bounds on the event probability (used to skip work that underflows)."""

from __future__ import annotations

import math

from numba import prange

from ._jit import kernel


@kernel
def chernoff_bracket(lam, c, b, iterations):
    """Bracket ``(lo, hi)`` of the tilt ``theta`` solving ``K'(theta) = T`` (see
    :func:`log_chernoff_bound`) after ``iterations`` bisection steps; ``lam > 0``.

    ``K'(0) = lam (1 - a) < 0 <= T`` and ``K'`` increases, so the root lies in ``[0, hi]``.
    """
    a = 1.0 + c
    T = c * b
    hi = 1.0
    for _ in range(200):
        if lam * (math.exp(hi) - a * math.exp(-a * hi)) >= T:
            break
        hi *= 2.0
    lo = 0.0
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if lam * (math.exp(mid) - a * math.exp(-a * mid)) < T:
            lo = mid
        else:
            hi = mid
    return lo, hi


@kernel
def log_chernoff_bound(lam, c, b):
    """Upper bound on ``log P(n - a n0 > (a - 1) b)`` for ``n, n0 ~ Poisson(lam)``, ``a = 1 + c``.

    ``P(S > T) <= exp(K(theta) - theta T)`` for every ``theta >= 0``, with the cumulant
    generating function ``K(theta) = lam (e^theta - 1) + lam (e^{-a theta} - 1)`` of
    ``S = n - a n0``. The optimal ``theta`` solves ``K'(theta) = T``; any ``theta`` found by the
    bisection below gives a valid bound, so inexact solving only loosens it.
    """
    if not lam > 0.0:
        return -math.inf if lam == 0.0 else 0.0
    a = 1.0 + c
    theta, _ = chernoff_bracket(lam, c, b, 80)
    return lam * (math.expm1(theta) + math.expm1(-a * theta)) - theta * (c * b)


@kernel(parallel=True)
def log_chernoff_bound_array(lam, c, b, out):
    for i in prange(lam.shape[0]):
        out[i] = log_chernoff_bound(lam[i], c[i], b[i])
