"""A noise stream for other simulators: advance a sensor's noise step by step (:class:`NoiseStream`)."""

from __future__ import annotations

import numpy as np

from . import terms
from ._checks import check_lux, resolve_threads
from ._engine import PixelState, check_t_start, renewal_step, sorted_window, static_inputs
from ._run import run_setup
from .errors import InputError, ParameterError
from .events import empty_events
from .params import NoiseParams
from .terms.memory import refuse

__all__ = ["NoiseStream"]


class NoiseStream:
    """Photon-noise events for another simulator's loop, interval by interval.

    Keeps per-pixel state (random streams, refractory, pending events) between calls. Each
    call :meth:`advance` gives the noise events of ``[t_now, t_end_us)`` for an illuminance
    held constant over the trials that *start* in that interval (sample-and-hold per trial),
    which is exact for piecewise-constant illuminance. Signal events are the host
    simulator's business: merge them with :func:`evnoise.merge_events`.

    Parameters
    ----------
    shape : (H, W)
        Sensor size.
    params : NoiseParams
        Model parameters.
    rng : numpy.random.Generator, int or None
        Randomness (per-pixel streams; results do not depend on the number of threads).
    t_start_us : int
        Time of the start of the stream in microseconds.
    thresholds : array_like, optional
        Per-pixel thresholds ``(2, H, W)``; drawn when ``params.eps_sigma > 0``.
    background : array_like, optional
        Per-pixel background maps ``(2, H, W)``; drawn when ``params.leak_sigma > 0`` or hot
        pixels are on (see :func:`simulate_events`).
    """

    def __init__(self, shape, params: NoiseParams, rng=None, *, t_start_us: int = 0, thresholds=None,
                 background=None, threads: int | None = None):
        from .events import check_shape

        self.shape = check_shape(shape)
        self.threads = resolve_threads(threads)
        run = run_setup(self.shape, params, rng, thresholds=thresholds, background=background)
        refuse(run.params, "NoiseStream")
        self.params = run.params
        self._eps_on, self._eps_off = run.thresholds
        self._bg = run.background
        self._state = PixelState(np.arange(self.shape[0] * self.shape[1]), run.key, self.threads)
        self._t0 = check_t_start(t_start_us)
        self._t_rel = 0  # µs since t_start_us
        self._inputs = None  # (lam, renewal inputs) of the last interval

    @property
    def t_us(self) -> int:
        """Current time of the stream (end of the last interval), microseconds."""
        return self._t0 + self._t_rel

    def advance(self, lux, t_end_us: int) -> np.ndarray:
        """Noise events with ``t_us <= t < t_end_us`` under illuminance ``lux`` (H, W), sorted by time."""
        lux = check_lux(lux)
        if lux.shape != self.shape:
            raise InputError(f"lux has shape {lux.shape}, but the stream was made for {self.shape}")
        t_end = check_t_start(t_end_us) - self._t0
        if t_end < self._t_rel:
            raise ParameterError(f"t_end_us={t_end_us} is before the stream's current time {self.t_us}")
        if t_end == self._t_rel:
            return empty_events(0)
        p = self.params
        dt = p.trial_us
        lam = p.photons_per_trial(lux).ravel()
        if self._inputs is not None and np.array_equal(lam, self._inputs[0]):
            log1m_p, q_on, timer, nu = self._inputs[1]  # the same light as the last interval: same closed form
        else:
            log1m_p, q_on, timer, nu = static_inputs(lam, p, self._eps_on, self._eps_off, self._bg)
            self._inputs = (lam, (log1m_p, q_on, timer, nu))
        j_min = _first_trial_at_or_after(self._t_rel, dt)
        discard = _first_trial_at_or_after(t_end, dt)
        if timer is not None:
            from .background import lux_of_photons

            scale, hot = (None, None) if self._bg is None else self._bg
            l_on, l_off = terms.intensities(lux_of_photons(lam, p), p, scale, hot)
            self._state.rescale_timers(np.broadcast_to(l_on + l_off, lam.shape), j_min)
        parts = renewal_step(self._state, self.shape[1], log1m_p, q_on, dt, p.refractory_us, j_min,
                              float(t_end), discard, self._t0, self.threads,
                              expected=nu * (t_end - self._t_rel) * 1e-6, timer=timer)
        out = sorted_window(parts, self._t0 + self._t_rel, self._t0 + t_end)
        self._t_rel = t_end
        return out


def _first_trial_at_or_after(t_us: float, dt: float) -> float:
    """Index of the first trial starting at or after ``t_us`` (``t_us >= 0``): the kernels' eligibility rule
    with no previous event and no refractory period (one home for the rounding of trial starts)."""
    from ._kernels.simulate import first_eligible_trial

    return float(first_eligible_trial(-1.0, float(t_us), 0.0, float(dt)))
