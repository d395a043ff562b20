"""Background activity (leak) and hot pixels: events that are not photon-noise threshold crossings.

Model (the simulators and the closed forms use these functions; each term's own part -- its parameters,
per-pixel map, intensity and kernel coefficients -- lives in its module of :mod:`evnoise.terms`, and the
intensity is the sum over the registered background terms, :func:`evnoise.terms.intensities`):

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
  Hot pixels may have a regularity of their own (``hot_pixel_regularity``; -1, the default, is
  ``leak_regularity``'s): a hot pixel's whole background then runs on a timer of that regularity.
  A pixel's first background arrival comes from the timer's stationary (length-biased)
  distribution, so the record starts in the steady state (exact without photon noise).
- The growing term follows the photocurrent of the scene (parasitic junction leakage grows
  with light, so ON background rises at high illuminance while OFF does not); ``dark_lux`` is not
  added to it: its share is part of the constant ``leak_*_hz``.
"""

from __future__ import annotations

import math

import numpy as np

from . import terms
from ._checks import as_generator, check_lux, check_map_shape, check_params, real_array
from .errors import InputError
from .terms.arrivals import arrival_shares, lux_of_photons  # noqa: F401  (their home; imported from here too)
from .terms.bandwidth import alpha_per_photon as pr_alpha_per_photon
from .terms.timer import regular_rates, timer_shape

__all__ = ["draw_background", "background_rate", "with_background", "regular_rates", "timer_shape",
           "pr_alpha_per_photon"]


def draw_background(shape, params, rng=None) -> np.ndarray:
    """Per-pixel background maps ``(2, H, W)``: ``[spread factor s, hot-pixel rate h in events/s]``.

    ``s`` is 1 everywhere when ``leak_sigma`` is 0; ``h`` is 0 except for the hot pixels (a
    uniformly random ``round(hot_pixel_fraction * H * W)`` of them, chosen without replacement; a rate
    spread by ``hot_pixel_sigma`` past 1e9 events/s, ``hot_pixel_rate_hz``'s own limit, is capped there).
    Draws from ``rng`` only for the terms that are on (spread first, then hot pixels), so turning
    them off leaves every other draw of a run unchanged.

    Parameters
    ----------
    shape : (H, W)
        Sensor size in pixels.
    params : NoiseParams
        Model parameters (``leak_sigma``, ``hot_pixel_fraction``, ``hot_pixel_rate_hz``, ``hot_pixel_sigma``),
        or the name of a preset.
    rng : numpy.random.Generator, int or None
        Randomness: a generator (drawn from in place), a seed, or None for fresh entropy.

    Returns
    -------
    numpy.ndarray
        float64 array of shape ``(2, H, W)``: the spread factors, then the hot-pixel rates in events/s.
    """
    params = check_params(params)
    gen = as_generator(rng)
    return terms.draw_map("background", check_map_shape(shape, "background"), params, gen)


def check_background(background, shape) -> np.ndarray:
    """Background maps ``(2, H, W)`` ``[spread factor, hot rate]``: finite, >= 0, hot rates at most
    ``hot_pixel_rate_hz``'s limit (1e9 events/s)."""
    from .params import PARAM_LIMITS

    arr = real_array(background, "background")
    if arr.shape != (2, *shape):
        raise InputError(f"background must have shape (2, H, W) = {(2, *shape)}, got {arr.shape}")
    if not (np.isfinite(arr).all() and (arr >= 0).all()):
        raise InputError("background must be finite and >= 0")
    top = PARAM_LIMITS["hot_pixel_rate_hz"]
    if (arr[1] > top).any():
        raise InputError(f"background hot rates (row 1) must be at most {top:g} events/s (as hot_pixel_rate_hz), "
                         f"got {arr[1].max():g}")
    return arr


def background_rate(lux, params, *, background=None) -> np.ndarray:
    """Background intensities ``(2, *lux.shape)`` ``[l_on, l_off]`` in events/s (before sharing trials).

    Parameters
    ----------
    lux : array_like
        Illuminance at the sensor in lux (finite, ``>= 0``), of any shape.
    params : NoiseParams
        Model parameters, or the name of a preset.
    background : array_like, optional
        Per-pixel maps ``(2, *lux.shape)`` from :func:`draw_background`: each pixel's spread factor and hot
        rate; without it every pixel is at the nominal values (``s = 1``, no hot pixel).

    Returns
    -------
    numpy.ndarray
        float64 array of shape ``(2, *lux.shape)``: ``l_on`` then ``l_off``, in events/s.
    """
    params = check_params(params)
    lux = check_lux(lux, ndim=None)
    if background is not None:
        background = check_background(background, lux.shape)
        scale, hot = background[0], background[1]
    else:
        scale, hot = None, None
    return np.stack(terms.intensities(lux, params, scale, hot))


def with_background(p_on, p_off, lux, params, scale=None, hot=None):
    """Per-trial ``(P_on, P_off)``: photon-noise probabilities with the background added (module doc)."""
    l_on, l_off = terms.intensities(lux, params, scale, hot)
    a_on, a_off = arrival_shares(l_on, l_off, params.trial_rate_hz)
    quiet = 1.0 - p_on - p_off
    return p_on + quiet * a_on, p_off + quiet * a_off


def pr_tau_s(lux, params) -> np.ndarray:
    """Photoreceptor time constant in seconds at ``lux`` (``inf`` in total darkness, 0 when off)."""
    params = check_params(params)
    lux = check_lux(lux, ndim=None)
    if params.pr_tau_s_at_1lux <= 0:
        return np.zeros_like(lux)
    total = lux + params.dark_lux
    with np.errstate(divide="ignore"):
        return np.where(total > 0, params.pr_tau_s_at_1lux / np.where(total > 0, total, 1.0), math.inf)
