"""Slow, obviously-correct reference implementations, for tests and benchmarks.

Nothing here is used by evnoise itself. Each function computes the same quantity as a fast
path of the library by the most direct route available, so the two can be compared:

- :func:`reference_log_event_probability`: the exact probability with mpmath at high
  precision (independent special functions: ``gammainc`` and ``hyp1f1``);
- :func:`double_sum_event_probability`: the plain double sum over both photon counts in
  float64 (small ``lam`` only);
- :func:`naive_static_events`: a straightforward vectorised-NumPy per-trial simulation of a
  static scene (draw both photon counts of every eligible pixel in every trial).
"""

from __future__ import annotations

import math

import numpy as np

from .events import EVENT_DTYPE
from .params import NoiseParams


def reference_log_event_probability(lam: float, eps: float, bias: float, *, dps: int = 40) -> float:
    """``log P(n + b > e^eps (n0 + b))``, ``n, n0 ~ Poisson(lam)`` i.i.d., with mpmath.

    Sums ``Pois(m) * P(N > floor(e^eps (m + b) - b))`` over every ``m`` whose term is above
    ``1e-30`` of the total (found by scanning outwards from the largest term). The tail
    ``P(N > k)`` is ``pmf(k + 1) * 1F1(1; k + 2; lam)`` above the mean (all terms positive) and
    ``1 - pmf(k) 2F0(1, -k; ; -1/lam)`` (a terminating series of positive terms) below it. Slow: meant for a few points.
    """
    import mpmath as mp

    with mp.workdps(dps):
        lam_m = mp.mpf(lam)
        if lam == 0:
            return -math.inf
        a = mp.e ** mp.mpf(eps)
        b = mp.mpf(bias)

        def log_term(m: int):
            k = int(mp.floor(a * (m + b) - b))  # n > a (m + b) - b  <=>  n > floor(...)
            log_pmf_m = -lam_m + m * mp.log(lam_m) - mp.loggamma(m + 1)
            if k + 1 > lam:
                log_sf = (-lam_m + (k + 1) * mp.log(lam_m) - mp.loggamma(k + 2)
                          + mp.log(mp.hyp1f1(1, k + 2, lam_m, maxterms=10**7)))
            else:
                # P(N <= k) = pmf(k) * sum_j k!/(k-j)! / lam^j, a terminating series
                log_pmf_k = -lam_m + k * mp.log(lam_m) - mp.loggamma(k + 1)
                cdf = mp.e ** log_pmf_k * mp.hyp2f0(1, -k, -1 / lam_m, maxterms=10**7)
                log_sf = mp.log(1 - cdf)
            return log_pmf_m + log_sf

        # the largest term lies in [0, floor(lam)]: coarse scan, then refine
        top = int(math.floor(lam))
        step = max(1, top // 64)
        grid = list(range(0, top + 1, step))
        vals = [log_term(m) for m in grid]
        best = grid[int(np.argmax([float(v) for v in vals]))]
        lo, hi = max(0, best - step), min(top, best + step)
        best_v = max((log_term(m), m) for m in range(lo, hi + 1))[1]
        terms = {best_v: log_term(best_v)}
        total = mp.e ** terms[best_v]
        for direction in (1, -1):
            m = best_v + direction
            small = 0
            while m >= 0 and small < 3:
                t = mp.e ** log_term(m)
                total += t
                small = small + 1 if t < total * mp.mpf(10) ** -30 else 0
                m += direction
        return float(mp.log(total))


def double_sum_event_probability(lam: float, eps: float, bias: float) -> float:
    """``sum_{n0} sum_{n} Pois(n0) Pois(n) [n + b > e^eps (n0 + b)]`` in float64 (``lam`` <~ 100)."""
    from scipy.stats import poisson

    top = int(lam + 40 * math.sqrt(lam) + 40)
    k = np.arange(top + 1)
    pmf = poisson.pmf(k, lam)
    fires = (k[None, :] + bias) > math.exp(eps) * (k[:, None] + bias)  # rows n0, columns n
    return float(np.sum(pmf[:, None] * pmf[None, :] * fires))


def naive_static_events(lux, params: NoiseParams, duration_s: float, rng=None, *, background=None) -> np.ndarray:
    """Static-scene events by brute force: every trial, every eligible pixel draws ``n, n0``.

    Same conventions as the library (event time uniform within its trial, refractory period
    as non-paralyzable dead time on trial starts); per-pixel thresholds follow
    ``params.eps_sigma`` with :func:`evnoise.rates.draw_thresholds`. Background activity
    (:mod:`evnoise.background`): a pixel whose comparison fired nothing draws the number of
    background arrivals in the trial, ``Poisson(l dt)``, and fires if it is at least one, ON with
    probability ``l_on / l`` (``background``: per-pixel ``[spread, hot rate]`` maps, default
    the nominal pixel). Cost O(pixels x trials).
    """
    from .rates import draw_thresholds

    rng = np.random.default_rng(rng)
    lux = np.asarray(lux, dtype=np.float64)
    height, width = lux.shape
    lam = params.photons_per_trial(lux).ravel()
    thr = draw_thresholds(lux.shape, params, rng)
    c_on, c_off = np.expm1(thr[0].ravel()), np.expm1(thr[1].ravel())
    bg = np.stack([np.ones(lux.shape), np.zeros(lux.shape)]) if background is None else np.asarray(background)
    q_hot = params.hot_pixel_on_fraction
    l_on = bg[0].ravel() * (params.leak_on_hz + params.leak_on_hz_per_lux * lux.ravel()) + bg[1].ravel() * q_hot
    l_off = (bg[0].ravel() * (params.leak_off_hz + params.leak_off_hz_per_lux * lux.ravel())
             + bg[1].ravel() * (1 - q_hot))
    has_bg = bool(np.any(l_on + l_off > 0))
    b = params.bias_pr
    dt = params.trial_us
    refr = params.refractory_us
    duration_us = int(round(duration_s * 1e6))
    n_trials = math.ceil(duration_us / dt)
    free_at = np.full(lam.size, -np.inf)  # time from which the pixel may fire again
    last_trial = np.full(lam.size, -1)
    chunks = []
    for j in range(n_trials):
        eligible = (j * dt >= free_at) & (j > last_trial)
        idx = np.flatnonzero(eligible)
        n = rng.poisson(lam[idx])
        n0 = rng.poisson(lam[idx])
        on = n > n0 + np.floor(c_on[idx] * (n0 + b))
        off = n0 > n + np.floor(c_off[idx] * (n + b))
        if has_bg:
            quiet = ~(on | off)
            l_all = l_on[idx] + l_off[idx]
            arrivals = rng.poisson(l_all * dt * 1e-6)
            bg_fire = quiet & (arrivals > 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                bg_on = rng.random(idx.size) * l_all < l_on[idx]
            on = on | (bg_fire & bg_on)
            off = off | (bg_fire & ~bg_on)
        fired = idx[on | off]
        if fired.size == 0:
            continue
        tau = (j + rng.random(fired.size)) * dt
        keep = tau < duration_us
        fired, tau = fired[keep], tau[keep]
        free_at[fired] = tau + refr
        last_trial[fired] = j
        ev = np.empty(fired.size, dtype=EVENT_DTYPE)
        ev["t"] = np.floor(tau).astype(np.int64)
        ev["x"] = fired % width
        ev["y"] = fired // width
        ev["p"] = on[on | off][keep].astype(np.uint8)
        chunks.append(ev)
    out = np.concatenate(chunks) if chunks else np.empty(0, dtype=EVENT_DTYPE)
    return out[np.argsort(out["t"], kind="stable")]
