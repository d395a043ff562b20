"""The regular background timer (``leak_regularity > 0``): background arrivals close to periodic.

Each event restarts a timer; the next background arrival comes ``D + G`` eligible trials later (module doc
of :mod:`evnoise.background`). The closed form is :func:`regular_rates`; the kernels draw the timer
(:mod:`evnoise._kernels.background`) from :func:`timer_shape`'s arrays and the ``regularity`` entry of the
trial kernel's model.
"""

from __future__ import annotations

import numpy as np

from .base import NoiseTerm


class RegularTimer(NoiseTerm):
    """``leak_regularity``: how regular the background arrivals are (0 Poisson, 1 periodic);
    ``hot_pixel_regularity``: the same for hot pixels (``-1``: ``leak_regularity``'s)."""

    name = "timer"
    fields = ("leak_regularity", "hot_pixel_regularity")
    modifies_background = True

    def is_on(self, params) -> bool:
        return params.regular_background

    def kernel_model(self, params) -> dict:
        # the trial kernel runs the timer wherever this is > 0; with hot pixels of a regularity of their own each
        # pixel reads its own from the coefficients (:func:`pixel_regularity`, row 4 of ``kernel_coefficients``)
        return {"regularity": largest_regularity(params)}

    def rates(self, p_on, p_off, l_on, l_off, params, hot=None):
        """Closed-form rates ``(nu_on, nu_off)`` events/s with the timer on (:func:`regular_rates`) of pixels
        with hot-pixel map ``hot`` (None: the nominal pixel, which is not hot)."""
        return regular_rates(p_on, p_off, l_on, l_off, params.trial_rate_hz, params.refractory_us * 1e-6,
                             pixel_regularity(params, hot))


def own_hot_regularity(params) -> bool:
    """True when hot pixels have a regularity that differs from the ordinary pixels'. Decided by the parameters
    alone: a hot-pixel map given by the caller (``background=``) has it too, whatever ``hot_pixel_fraction``."""
    return params.hot_regularity != params.leak_regularity


def largest_regularity(params) -> float:
    """The largest regularity any pixel's timer has: ``leak_regularity``, or ``hot_pixel_regularity`` where hot
    pixels have their own (the trial kernel's switch for the timer; each pixel then reads its own)."""
    if own_hot_regularity(params):
        return max(float(params.leak_regularity), float(params.hot_regularity))
    return float(params.leak_regularity)


def pixel_regularity(params, hot=None):
    """The timer's regularity of pixels with hot-pixel map ``hot`` (events/s, 0 for an ordinary pixel): the
    scalar ``leak_regularity`` where every pixel has it (no map, or hot pixels tied to it), else an array
    (``hot_regularity`` where ``hot > 0``)."""
    if hot is None or not own_hot_regularity(params):
        return float(params.leak_regularity)
    return np.where(np.asarray(hot) > 0, params.hot_regularity, params.leak_regularity)


def timer_mean_min(log1m_p, p, d, log1m_a2):
    """``E[min(G_p, D + G)]`` for a whole ``d`` (arrays).

    ``(1 - q^(d+1)) / p + q^(d+1) (1 - a2) / (1 - q (1 - a2))``; the last denominator is
    ``-expm1(log q + log(1 - a2))`` (no cancellation when ``p`` and ``a2`` are both small).
    """
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        qd = np.exp((d + 1.0) * log1m_p)
        head = np.where(p > 0, -np.expm1((d + 1.0) * log1m_p) / np.where(p > 0, p, 1.0), d + 1.0)
        tail = np.where(qd > 0, qd * np.exp(log1m_a2) / -np.expm1(log1m_p + log1m_a2), 0.0)
    return head + tail


def timer_shape(l_all_hz, trial_s: float, regularity):
    """``(d, log1p(-a2))`` of the regular timer for background intensities ``l_all_hz`` (events/s).

    The one home of the timer's shape (module doc; :func:`evnoise._kernels.background.timer_shape`
    element by element): ``d`` the mean fixed part in trials (``inf`` where there is no background),
    ``a2`` the per-trial probability of the geometric rest (``log1p(-a2)`` is 0 where there is none).
    ``regularity``: a scalar or an array that broadcasts with ``l_all_hz`` (per pixel).
    """
    from .._kernels.background import timer_shapes

    l_all = np.asarray(l_all_hz, dtype=np.float64)
    flat = np.ascontiguousarray(l_all.ravel())
    reg = np.empty_like(flat)
    reg.reshape(l_all.shape)[...] = regularity  # a fresh array (a broadcast view is read-only for Numba)
    d = np.empty_like(flat)
    log1m_a2 = np.empty_like(flat)
    timer_shapes(flat, float(trial_s), reg, d, log1m_a2)
    return d.reshape(l_all.shape), log1m_a2.reshape(l_all.shape)


def regular_rates(p_on, p_off, l_on, l_off, trial_rate_hz: float, refractory_s: float, regularity):
    """Rates ``(nu_on, nu_off)`` events/s of a pixel with photon noise and a regular background timer.

    ``p_on``, ``p_off``: the photon-noise per-trial probabilities; ``l_on``, ``l_off``: background
    intensities (events/s); ``regularity`` a scalar or per pixel; see the module doc for the formula. Arrays
    broadcast.
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
        e_min = ((1.0 - phi) * timer_mean_min(log1m_p, p, d0, log1m_a2)
                 + phi * timer_mean_min(log1m_p, p, d0 + 1.0, log1m_a2))
        e_min = np.where(has, e_min, np.where(p > 0, 1.0 / np.where(p > 0, p, 1.0), np.inf))
        gap = refractory_s * n + e_min
        nu = np.where(np.isfinite(gap), n / gap, 0.0)
        photon = np.where(np.isfinite(e_min), np.minimum(p * e_min, 1.0), 1.0)  # a share: <= 1 after rounding
        share_on = np.where(has, l_on / np.where(has, l_all, 1.0), 0.0)
        share_p = np.where(p > 0, p_on / np.where(p > 0, p, 1.0), 0.0)
        nu_on = nu * (photon * share_p + (1.0 - photon) * share_on)
        nu_off = nu * (photon * (1.0 - share_p) + (1.0 - photon) * (1.0 - share_on))
    return nu_on, nu_off


TIMER = RegularTimer()
