"""Expected event rates and per-pixel threshold maps.

Dead-time convention (see :mod:`evnoise._kernels.simulate`): after an event at time ``tau``
the pixel skips every trial that starts before ``tau + R``; event times are uniform within
their trial, so the mean number of skipped trials is exactly ``R * trial_rate_hz`` and the
rate of a pixel is the non-paralyzable dead-time formula

    nu = nu0 / (1 + nu0 R),   nu0 = trial_rate_hz * (p_on + p_off),

split between the polarities in proportion ``p_on : p_off``. ``R`` is the refractory period
rounded up to whole microseconds.
"""

from __future__ import annotations

import numpy as np

from . import terms
from ._checks import as_generator, check_lux, check_map_shape, check_params, check_thresholds
from .errors import ParameterError
from .model import event_probability, log_event_probability_alone

__all__ = ["expected_rate", "draw_thresholds", "trial_probabilities"]


def draw_thresholds(shape, params, rng=None) -> np.ndarray:
    """Per-pixel thresholds ``(2, H, W)`` = ``[eps_pos, eps_neg]`` with mismatch ``eps_sigma``.

    Each pixel's two thresholds are drawn independently from normal distributions with means
    ``eps_pos`` / ``eps_neg`` and standard deviation ``eps_sigma``, truncated to ``> 0``
    (values ``<= 0`` are redrawn). With ``eps_sigma = 0`` the maps are constant.

    Parameters
    ----------
    shape : (H, W)
        Sensor size in pixels.
    params : NoiseParams or str
        Parameters (``eps_pos``, ``eps_neg``, ``eps_sigma``) or a preset name.
    rng : numpy.random.Generator, int or None
        Randomness: a generator (drawn from in place), a seed, or None for fresh entropy; nothing is drawn
        when ``eps_sigma = 0``.

    Returns
    -------
    numpy.ndarray
        float64 array of shape ``(2, H, W)``: the ON thresholds, then the OFF thresholds.
    """
    params = check_params(params)
    gen = as_generator(rng)
    return terms.draw_map("thresholds", check_map_shape(shape, "thresholds"), params, gen)


def trial_probabilities(lam, params, thresholds=None, *, background=None, skip_below=None, photon_only=False,
                        alone=False):
    """Per-trial ``(P_on, P_off)`` at mean photon counts ``lam`` (nominal or per-pixel thresholds).

    The photon-noise probabilities, with the background activity of :mod:`evnoise.background`
    added when ``params`` has any (each pixel at the nominal spread factor and no hot pixel unless
    ``background = (scale, hot)``, arrays matching ``lam``, is given). ``photon_only``: without it.
    With a regular background (``leak_regularity > 0``) trials are no longer i.i.d.: use
    :func:`pixel_rates` for rates. ``alone``: each value from its own inputs alone, the same bits whatever else the
    call holds (:func:`evnoise.model.log_event_probability_alone`; 1-D ``lam``).
    """
    eps_on = params.eps_pos if thresholds is None else thresholds[0]
    eps_off = params.eps_neg if thresholds is None else thresholds[1]
    if alone:
        p_on = np.exp(log_event_probability_alone(lam, eps_on, params.bias_pr))
        p_off = np.exp(log_event_probability_alone(lam, eps_off, params.bias_pr))
    else:
        p_on = event_probability(lam, eps_on, params.bias_pr)
        p_off = event_probability(lam, eps_off, params.bias_pr)
    if terms.background_on(params) and not photon_only:
        from .background import lux_of_photons, with_background

        scale, hot = (None, None) if background is None else background
        p_on, p_off = with_background(p_on, p_off, lux_of_photons(lam, params), params, scale, hot)
    return p_on, p_off


def expected_rate(lux, params, *, thresholds=None, background=None, mismatch: str = "nominal") -> np.ndarray:
    """Expected noise-event rate of a static pixel, events per second, ``[ON, OFF]``.

    Parameters
    ----------
    lux : array_like
        Illuminance at the sensor in lux (any shape, ``>= 0``).
    params : NoiseParams
        Model parameters (refractory period included as non-paralyzable dead time).
    thresholds : array_like, optional
        Per-pixel thresholds ``(2, *lux.shape)`` (e.g. from :func:`draw_thresholds`). Without it
        the nominal thresholds are used; with ``eps_sigma > 0`` the result is then the rate
        of a pixel whose thresholds equal the nominal values, not the population mean.
    background : array_like, optional
        Per-pixel background maps ``(2, *lux.shape)`` (``[spread factor, hot rate]``, from
        :func:`evnoise.draw_background`); without it each pixel has the nominal background
        (spread factor 1, not hot). The background (leak) adds events as described in
        :mod:`evnoise.background`.
    mismatch : {"nominal", "mean"}
        ``"nominal"`` (default): the rate of a pixel at the nominal (or the given) thresholds.
        ``"mean"``: the mean rate over the population of pixels whose thresholds are spread by
        ``params.eps_sigma`` (:func:`evnoise.mismatch.population_rate`; exact up to about 1e5 photons per
        trial, beyond within about 1e-10 without dead time and 1e-5 with it: :mod:`evnoise.mismatch`): what a
        measurement averaged over many pixels sees (threshold mismatch, background spread and
        hot pixels). The two agree when ``eps_sigma``, ``leak_sigma`` and ``hot_pixel_fraction`` are 0.

    Returns
    -------
    numpy.ndarray
        float64 array of shape ``(2, *lux.shape)``.
    """
    params = check_params(params)
    lux = check_lux(lux, ndim=None)
    if mismatch not in ("nominal", "mean"):
        raise ParameterError(f"mismatch must be 'nominal' or 'mean', got {mismatch!r}")
    if params.reset_memory > 0:
        # a pixel with memory is not a sequence of independent trials: its rate is the Markov renewal closed form
        # (nominal thresholds, a uniform Poisson background: what that form and its simulator cover so far)
        from .terms.memory import memory_statistics, unsupported

        # nominal: the nominal pixel (nominal thresholds, spread factor 1, not hot); mean: the population, which
        # needs what differs between pixels; given maps: per-pixel rates, which the closed form does not give
        nominal = mismatch == "nominal"
        missing = unsupported(params.replace(eps_sigma=0.0) if nominal else params, thresholds, background,
                              per_pixel=nominal and background is None and thresholds is None)
        if missing:
            raise ParameterError(f"the rate with reset_memory > 0 is known for the nominal pixel (nominal thresholds, "
                                 f"a Poisson background) only, not for {', '.join(missing)} "
                                 f"(evnoise.terms.memory.memory_statistics)")

        return memory_statistics(lux, params).rate_hz
    if mismatch == "mean":
        if thresholds is not None or background is not None:
            raise ParameterError("mismatch='mean' averages over the pixel population; do not pass thresholds "
                                 "or background maps too")
        from .mismatch import population_rate

        return population_rate(lux, params)
    if thresholds is not None:
        thresholds = check_thresholds(thresholds, lux.shape)
    if background is not None:
        from .background import check_background

        background = check_background(background, lux.shape)
    lam = params.photons_per_trial(lux)
    bg = None if background is None else (background[0], background[1])
    return np.stack(pixel_rates(lam, params, thresholds, bg))


def pixel_rates(lam, params, thresholds=None, background=None):
    """``(nu_on, nu_off)`` events/s of static pixels at mean photon counts ``lam`` (any shape).

    Dead time included; background as in :func:`trial_probabilities` (``background = (scale, hot)``
    arrays matching ``lam``, or None for the nominal pixel), regular or not.
    """
    if terms.regular_timer(params):
        from .background import lux_of_photons

        p_on, p_off = trial_probabilities(lam, params, thresholds, photon_only=True)
        scale, hot = (None, None) if background is None else background
        l_on, l_off = terms.intensities(lux_of_photons(lam, params), params, scale, hot)
        return terms.TIMER.rates(p_on, p_off, l_on, l_off, params, hot)
    p_on, p_off = trial_probabilities(lam, params, thresholds, background=background)
    nu_on = params.trial_rate_hz * p_on
    nu_off = params.trial_rate_hz * p_off
    dead = 1.0 + (nu_on + nu_off) * (params.refractory_us * 1e-6)
    return nu_on / dead, nu_off / dead
