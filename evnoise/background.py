"""Background activity (leak) and hot pixels: events that are not photon-noise threshold crossings.

Model (one home of the concept; the simulators and the closed forms use these functions):

- A pixel's background intensity at illuminance ``lux`` is, per polarity,

      l_on  = s * (leak_on_hz  + leak_on_hz_per_lux  * lux) + h * hot_pixel_on_fraction
      l_off = s * (leak_off_hz + leak_off_hz_per_lux * lux) + h * (1 - hot_pixel_on_fraction)

  in events/s, where ``s`` is the pixel's spread factor (log-normal, mean 1, ``sigma = leak_sigma``)
  and ``h`` its hot-pixel rate (0 for ordinary pixels; for a fraction ``hot_pixel_fraction`` of
  them log-normal with mean ``hot_pixel_rate_hz`` and ``sigma = hot_pixel_sigma``). Both are drawn
  once per run (:func:`draw_background`). A pixel at the nominal values has ``s = 1, h = 0``.
- Background events are a Poisson process of intensity ``l = l_on + l_off`` that shares the
  pixel's trials with the photon-noise comparison: in an eligible trial (not in the refractory
  period) that the comparison leaves without an event, a background event happens with
  probability ``a = 1 - exp(-l / N)`` (``N = trial_rate_hz``; at least one background arrival in the
  trial), ON with probability ``l_on / l``. The per-trial probabilities become

      P_on  = p_on  + (1 - p_on - p_off) * a * l_on  / l
      P_off = p_off + (1 - p_on - p_off) * a * l_off / l

  so every tier keeps its exact form (i.i.d. trials, renewal gaps geometric in eligible trials,
  dead time ``nu = N P / (1 + N P R)``). For ``l << N`` the rates add (``nu ~ N p + l``, the
  additive floors of published fits); a pixel fires at most once per trial, so the background
  rate saturates at ``trial_rate_hz`` (hot pixels faster than that need a larger trial rate).
- Regular background (``leak_regularity = r > 0``): leak events are close to periodic in real
  sensors (the memorised level drifts at a steady rate until it crosses a threshold). Then each
  event restarts a timer, and the next background arrival comes ``L`` eligible trials later,
  ``L = D + G`` with ``D`` whole trials of mean ``r (M - 1)`` and ``G`` geometric of mean
  ``1 + (1 - r)(M - 1)``, ``M = 1 / a`` (so ``r = 0`` is the Poisson case above and ``r = 1`` is
  periodic up to one trial). With the photon noise ``G_p`` (geometric, ``p = p_on + p_off``) the
  gap in trials after an event is ``R N + min(G_p, L)`` on average, and

      E[min(G_p, L)] = sum_m (1 - p)^m P(L > m),    nu = N / (R N + E[min]),
      nu_on = nu (p_on E[min] + (1 - p E[min]) l_on / l)

  (``p E[min]`` is the share of photon events), exact in closed form (:func:`regular_rates`).
  A pixel's first background arrival comes from the timer's stationary (length-biased)
  distribution, so the record starts in the steady state (exact without photon noise).
- The growing term follows the photocurrent of the scene (parasitic junction leakage grows
  with light, so ON background rises at high illuminance while OFF does not); ``dark_lux`` is not
  added to it: its share is part of the constant ``leak_*_hz``.
"""

from __future__ import annotations

import math

import numpy as np

from ._checks import as_generator, check_lux, check_params
from .errors import InputError

__all__ = ["draw_background", "background_rate", "with_background", "regular_rates"]


def _lognormal_mean_one(gen, sigma: float, size):
    """Log-normal factors of mean 1 (``log`` has standard deviation ``sigma``)."""
    return np.exp(gen.normal(-0.5 * sigma * sigma, sigma, size=size))


def draw_background(shape, params, rng=None) -> np.ndarray:
    """Per-pixel background maps ``(2, H, W)``: ``[spread factor s, hot-pixel rate h in events/s]``.

    ``s`` is 1 everywhere when ``leak_sigma`` is 0; ``h`` is 0 except for the hot pixels (a
    uniformly random ``round(hot_pixel_fraction * H * W)`` of them, chosen without replacement).
    Draws from ``rng`` only for the terms that are on (spread first, then hot pixels), so turning
    them off leaves every other draw of a run unchanged.
    """
    params = check_params(params)
    gen = as_generator(rng)
    shape = tuple(int(s) for s in shape)
    n = int(np.prod(shape))
    out = np.zeros((2, n))
    out[0] = 1.0
    if params.leak_sigma > 0:
        out[0] = _lognormal_mean_one(gen, params.leak_sigma, n)
    if params.hot_pixel_fraction > 0 and params.hot_pixel_rate_hz > 0:
        n_hot = int(round(params.hot_pixel_fraction * n))
        if n_hot:
            idx = gen.choice(n, size=n_hot, replace=False)
            rates = np.full(n_hot, params.hot_pixel_rate_hz)
            if params.hot_pixel_sigma > 0:
                rates *= _lognormal_mean_one(gen, params.hot_pixel_sigma, n_hot)
            out[1, idx] = rates
    return out.reshape(2, *shape)


def check_background(background, shape) -> np.ndarray:
    arr = np.asarray(background, dtype=np.float64)
    if arr.shape != (2, *shape):
        raise InputError(f"background must have shape (2, H, W) = {(2, *shape)}, got {arr.shape}")
    if not (np.isfinite(arr).all() and (arr >= 0).all()):
        raise InputError("background must be finite and >= 0")
    return arr


def background_rate(lux, params, *, background=None) -> np.ndarray:
    """Background intensities ``(2, *lux.shape)`` ``[l_on, l_off]`` in events/s (before sharing trials).

    ``background`` (from :func:`draw_background`) gives each pixel's spread factor and hot rate;
    without it every pixel is at the nominal values (``s = 1``, no hot pixel).
    """
    params = check_params(params)
    lux = check_lux(lux, ndim=None)
    if background is not None:
        background = check_background(background, lux.shape)
        scale, hot = background[0], background[1]
    else:
        scale, hot = None, None
    return np.stack(_intensities(lux, params, scale, hot))


def _intensities(lux, params, scale=None, hot=None):
    """``(l_on, l_off)`` arrays at ``lux`` for flat (or matching) ``scale``, ``hot`` arrays or None."""
    l_on = params.leak_on_hz + params.leak_on_hz_per_lux * lux
    l_off = params.leak_off_hz + params.leak_off_hz_per_lux * lux
    if scale is not None:
        l_on = l_on * scale
        l_off = l_off * scale
    if hot is not None:
        q = params.hot_pixel_on_fraction
        l_on = l_on + hot * q
        l_off = l_off + hot * (1.0 - q)
    return np.asarray(l_on, dtype=np.float64), np.asarray(l_off, dtype=np.float64)


def arrival_shares(l_on, l_off, trial_rate_hz: float):
    """Per-trial background probabilities ``(a_on, a_off)``: ``a * l_on / l`` and ``a * l_off / l``."""
    l_all = l_on + l_off
    with np.errstate(divide="ignore", invalid="ignore"):
        # (1 - exp(-l / N)) / l, with its limit 1 / N at l = 0
        g = np.where(l_all > 0, -np.expm1(-l_all / trial_rate_hz) / np.where(l_all > 0, l_all, 1.0),
                     1.0 / trial_rate_hz)
    return g * l_on, g * l_off


def with_background(p_on, p_off, lux, params, scale=None, hot=None):
    """Per-trial ``(P_on, P_off)``: photon-noise probabilities with the background added (module doc)."""
    l_on, l_off = _intensities(lux, params, scale, hot)
    a_on, a_off = arrival_shares(l_on, l_off, params.trial_rate_hz)
    quiet = 1.0 - p_on - p_off
    return p_on + quiet * a_on, p_off + quiet * a_off


def lux_of_photons(lam, params):
    """Illuminance ``lux`` back from mean photons per trial (``>= 0``)."""
    return np.maximum(np.asarray(lam, dtype=np.float64) / params.photons_per_lux - params.dark_lux, 0.0)


def pr_alpha_per_photon(params) -> float:
    """``dt / (tau(lam) lam)``: the filter's step is ``1 - exp(-lam * this)`` (0 when the filter is off)."""
    if params.pr_tau_s_at_1lux <= 0:
        return 0.0
    # tau = pr_tau_s_at_1lux / (lux + dark_lux) = pr_tau_s_at_1lux * photons_per_lux / lam
    return (1.0 / params.trial_rate_hz) / (params.pr_tau_s_at_1lux * params.photons_per_lux)


def pr_tau_s(lux, params) -> np.ndarray:
    """Photoreceptor time constant in seconds at ``lux`` (``inf`` in total darkness, 0 when off)."""
    params = check_params(params)
    lux = check_lux(lux, ndim=None)
    if params.pr_tau_s_at_1lux <= 0:
        return np.zeros_like(lux)
    total = lux + params.dark_lux
    with np.errstate(divide="ignore"):
        return np.where(total > 0, params.pr_tau_s_at_1lux / np.where(total > 0, total, 1.0), math.inf)


def _timer_mean_min(log1m_p, p, d, log1m_a2):
    """``E[min(G_p, D + G)]`` for a whole ``d`` (arrays).

    ``(1 - q^(d+1)) / p + q^(d+1) (1 - a2) / (1 - q (1 - a2))``; the last denominator is
    ``-expm1(log q + log(1 - a2))`` (no cancellation when ``p`` and ``a2`` are both small).
    """
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        qd = np.exp((d + 1.0) * log1m_p)
        head = np.where(p > 0, -np.expm1((d + 1.0) * log1m_p) / np.where(p > 0, p, 1.0), d + 1.0)
        tail = np.where(qd > 0, qd * np.exp(log1m_a2) / -np.expm1(log1m_p + log1m_a2), 0.0)
    return head + tail


def timer_shape(l_all_hz, trial_s: float, regularity: float):
    """``(d, log1p(-a2))`` of the regular timer for background intensities ``l_all_hz`` (events/s).

    The one home of the timer's shape (module doc; :func:`evnoise._kernels.background.timer_shape`
    element by element): ``d`` the mean fixed part in trials (``inf`` where there is no background),
    ``a2`` the per-trial probability of the geometric rest (``log1p(-a2)`` is 0 where there is none).
    """
    from ._kernels.background import timer_shapes

    l_all = np.asarray(l_all_hz, dtype=np.float64)
    flat = np.ascontiguousarray(l_all.ravel())
    d = np.empty_like(flat)
    log1m_a2 = np.empty_like(flat)
    timer_shapes(flat, float(trial_s), float(regularity), d, log1m_a2)
    return d.reshape(l_all.shape), log1m_a2.reshape(l_all.shape)


def regular_rates(p_on, p_off, l_on, l_off, trial_rate_hz: float, refractory_s: float, regularity: float):
    """Rates ``(nu_on, nu_off)`` events/s of a pixel with photon noise and a regular background timer.

    ``p_on``, ``p_off``: the photon-noise per-trial probabilities; ``l_on``, ``l_off``: background
    intensities (events/s); see the module doc for the formula. Arrays broadcast.
    """
    p_on, p_off, l_on, l_off = (np.asarray(x, dtype=np.float64) for x in (p_on, p_off, l_on, l_off))
    n = float(trial_rate_hz)
    p = np.minimum(p_on + p_off, 1.0)
    with np.errstate(divide="ignore"):
        log1m_p = np.log1p(-p)  # -inf where a trial always fires
    l_all = l_on + l_off
    has = l_all > 0
    d, log1m_a2 = timer_shape(l_all, 1.0 / n, regularity)
    has = has & np.isfinite(d)  # an intensity too small to ever fire (1 / (1 - exp(-l / N)) overflows)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        d0 = np.floor(np.where(has, d, 0.0))
        phi = np.where(has, d, 0.0) - d0
        e_min = ((1.0 - phi) * _timer_mean_min(log1m_p, p, d0, log1m_a2)
                 + phi * _timer_mean_min(log1m_p, p, d0 + 1.0, log1m_a2))
        e_min = np.where(has, e_min, np.where(p > 0, 1.0 / np.where(p > 0, p, 1.0), np.inf))
        gap = refractory_s * n + e_min
        nu = np.where(np.isfinite(gap), n / gap, 0.0)
        photon = np.where(np.isfinite(e_min), np.minimum(p * e_min, 1.0), 1.0)  # a share: <= 1 after rounding
        share_on = np.where(has, l_on / np.where(has, l_all, 1.0), 0.0)
        share_p = np.where(p > 0, p_on / np.where(p > 0, p, 1.0), 0.0)
        nu_on = nu * (photon * share_p + (1.0 - photon) * share_on)
        nu_off = nu * (photon * (1.0 - share_p) + (1.0 - photon) * (1.0 - share_on))
    return nu_on, nu_off
