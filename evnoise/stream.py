"""A noise stream for other simulators: advance a sensor's noise step by step (:class:`NoiseStream`)."""

from __future__ import annotations

import math

import numpy as np

from . import terms
from ._checks import check_lux, resolve_threads
from ._engine import (
    WINDOW_BYTES_PER_EVENT,
    PixelState,
    check_event_memory,
    check_span,
    check_t_start,
    memory_step,
    renewal_step,
    sorted_window,
    static_inputs,
)
from ._run import run_setup
from .errors import InputError, ParameterError
from .events import EVENT_DTYPE, empty_events
from .params import NoiseParams
from .terms.memory import memory_on

__all__ = ["NoiseStream"]

#: light levels at which an interval run trial by trial evaluates its rate estimate (NoiseStream._trial_rate_hz)
RATE_GRID_LEVELS = 32


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
    threads : int, optional
        Worker threads (default ``NUMBA_NUM_THREADS`` or the CPU count); the events are the same for any number.

    Notes
    -----
    With reset memory (``params.reset_memory > 0``, :mod:`evnoise.terms.memory`) each pixel keeps its stored
    level between intervals, so polarities alternate across interval boundaries as within one; the first
    interval starts in the steady state of its light. When a pixel's light changes, its stored photon count
    is kept (clamped into the new light's state range, which spans the new ``lam`` ± many standard
    deviations: only a jump of the light beyond that range moves it). A Poisson background (hot pixels and a
    spread leak included), the regular background timer (its pending arrival kept across intervals and moved
    with a change of its intensity, as without memory) and threshold mismatch are part of the memory model.
    With mismatch or a spread leak most
    pixels have a chain of their own, and after a change of light each chain's tables widen to hold the counts
    stored under the old light. Where the tables would pass the table budget
    (``evnoise.terms.memory.MAX_TABLE_STATES``: a large sensor with mismatch, at the first interval or at a change
    of light) the stream goes on trial by trial for the rest of its life, as ``simulate_events`` runs such a scene:
    from the first interval its events are ``simulate_events``' with the same seed, event for event; from a later
    interval each pixel keeps its stored count (unclamped from then on) and an event pending from the last
    interval. The regular background timer is not covered there (a :class:`~evnoise.ParameterError`).
    """

    def __init__(self, shape, params: NoiseParams, rng=None, *, t_start_us: int = 0, thresholds=None,
                 background=None, threads: int | None = None):
        from .events import check_shape

        self.shape = check_shape(shape)
        self.threads = resolve_threads(threads)
        run = run_setup(self.shape, params, rng, thresholds=thresholds, background=background)
        self.params = run.params
        self._eps_on, self._eps_off = run.thresholds
        # thresholds that differ between pixels (drawn or given): the memory chains depend on them
        self._mismatch = bool(np.any(self._eps_on != self._eps_on[0]) or np.any(self._eps_off != self._eps_off[0]))
        self._bg = run.background
        self._state = PixelState(np.arange(self.shape[0] * self.shape[1]), run.key, self.threads)
        self._t0 = check_t_start(t_start_us)
        self._t_rel = 0  # µs since t_start_us
        self._inputs = None  # (lam, renewal inputs) of the last interval
        self._memory = None  # reset memory: (levels, tables, each level's lowest count) of the last interval
        self._grouping = None  # reset memory: (class spans, lam, pixel_groups) of the last interval
        self._stored = np.full(self.shape[0] * self.shape[1], np.nan)  # stored photon counts (NaN: none yet)
        self._pending_count = np.full(self.shape[0] * self.shape[1], np.nan)  # new state of a pending event
        self._trials = None  # reset memory beyond the table budget: the trial kernel's (thresholds, background, model)
        self._carry = None  # ... and the events of the last interval's last trial at or after its end

    @property
    def t_start_us(self) -> int:
        """Time of the start of the stream, microseconds."""
        return self._t0

    @property
    def t_us(self) -> int:
        """Current time of the stream (end of the last interval), microseconds."""
        return self._t0 + self._t_rel

    def advance(self, lux, t_end_us: int) -> np.ndarray:
        """Noise events with ``t_us <= t < t_end_us`` under illuminance ``lux`` (H, W), sorted by time.

        Parameters
        ----------
        lux : array_like, shape (H, W)
            Illuminance at the sensor in lux (finite, ``>= 0``), held over the trials that start in the
            interval; the shape must be the stream's.
        t_end_us : int
            End of the interval (excluded), an absolute time in whole microseconds, not before the stream's
            current time :attr:`t_us` (equal to it: no events, the stream unchanged).

        Returns
        -------
        numpy.ndarray
            Events (:data:`evnoise.EVENT_DTYPE`) of the interval, sorted by time; the stream's current time
            is then ``t_end_us``.

        Notes
        -----
        An interval whose events would not fit in memory (``t_end_us`` in another unit than microseconds,
        say) is a :class:`~evnoise.ParameterError` before anything is drawn, and so is a time more than 2**52
        trials after ``t_start_us`` (143 years at the highest trial rate); the stream is then unchanged.
        """
        lux = check_lux(lux)
        if lux.shape != self.shape:
            raise InputError(f"lux has shape {lux.shape}, but the stream was made for {self.shape}")
        t_end = check_t_start(t_end_us, "t_end_us") - self._t0
        if t_end < self._t_rel:
            raise ParameterError(f"t_end_us={t_end_us} is before the stream's current time {self.t_us}")
        if t_end == self._t_rel:
            return empty_events(0)
        p = self.params
        dt = p.trial_us
        check_span(self._t0, t_end, dt, "time since the stream's start")
        lam = p.photons_per_trial(lux).ravel()
        if memory_on(p):
            return self._advance_memory(lam, t_end)
        if self._inputs is not None and np.array_equal(lam, self._inputs[0]):
            log1m_p, q_on, timer, nu = self._inputs[1]  # the same light as the last interval: same closed form
        else:
            log1m_p, q_on, timer, nu = static_inputs(lam, p, self._eps_on, self._eps_off, self._bg)
            self._inputs = (lam, (log1m_p, q_on, timer, nu))
        self._check_memory(float(nu.sum()), t_end)
        j_min = _first_trial_at_or_after(self._t_rel, dt)
        discard = _first_trial_at_or_after(t_end, dt)
        if timer is not None:
            self._state.rescale_timers(self._timer_intensity(lam), j_min)
        parts = renewal_step(self._state, self.shape[1], log1m_p, q_on, dt, p.refractory_us, j_min,
                              float(t_end), discard, self._t0, self.threads,
                              expected=nu * (t_end - self._t_rel) * 1e-6, timer=timer)
        out = sorted_window(parts, self._t0 + self._t_rel, self._t0 + t_end, state=self._state)
        self._t_rel = t_end
        return out


    def _check_memory(self, rate_hz: float, t_end: int) -> None:
        """Refuse an interval whose events (``rate_hz`` over the sensor, events/s) cannot fit in memory, before the
        kernel allocates their columns (the interval is one window: its working memory counts too)."""
        expected = rate_hz * (t_end - self._t_rel) * 1e-6
        check_event_memory(expected, f"advance() to t_end_us={self._t0 + t_end} would return about {expected:,.0f} "
                                     f"events ({(t_end - self._t_rel) * 1e-6:.6g} s of noise); they",
                           window_events=expected, hint="advance in shorter intervals")

    def _timer_intensity(self, lam) -> np.ndarray:
        """Each pixel's background intensity (events/s) at ``lam`` photons per trial: what its timer runs at."""
        from .background import lux_of_photons

        scale, hot = (None, None) if self._bg is None else self._bg
        l_on, l_off = terms.intensities(lux_of_photons(lam, self.params), self.params, scale, hot)
        return np.broadcast_to(l_on + l_off, lam.shape)

    def _advance_memory(self, lam, t_end: int) -> np.ndarray:
        """:meth:`advance` with reset memory: the memory kernel over the interval's light levels. A pixel's
        stored state is kept as a photon count between intervals (a level's tables index counts from its
        lowest one), and so is the new state of an event pending in a trial that started in the last interval."""
        from ._kernels.simulate import PEND_ON, PEND_TAU
        from .terms.memory import MAX_TABLE_STATES, chain_timer, kernel_tables, pixel_groups

        if self._trials is not None:
            return self._advance_trials(lam, t_end)
        p = self.params
        dt = p.trial_us
        thresholds = (self._eps_on, self._eps_off)
        class_spans = None
        if self._mismatch:
            # pixels share a chain when their thresholds agree over the states their light's tables will hold
            lam_levels, lam_group = np.unique(lam, return_inverse=True)
            level_spans = _memory_spans(lam_levels, lam_group.ravel(), self._stored, self._pending_count)
            class_spans = dict(zip(lam_levels.tolist(), map(tuple, level_spans.tolist())))
        grouping = self._grouping
        if grouping is None or grouping[0] != class_spans or not np.array_equal(grouping[1], lam):
            # the pixels' chains: the same while the light and the states compared over are (most intervals)
            grouping = self._grouping = (class_spans, lam.copy(), pixel_groups(lam, p, self._bg, thresholds,
                                                                               class_spans))
        levels, a_on, a_off, reg, group, eps = grouping[2]
        spans = _memory_spans(levels, group, self._stored, self._pending_count)
        if class_spans is not None:  # within the states its thresholds were compared over (counts beyond: clamped)
            spans = _inside(spans, level_spans[np.searchsorted(lam_levels, levels)])
        key = np.stack([levels, a_on, a_off, reg, *eps])
        if (self._memory is None or not np.array_equal(key, self._memory[0])
                or not np.array_equal(spans, self._memory[4])):
            timer = chain_timer(a_on, a_off, reg, p)
            if int(spans[:, 1].sum()) > MAX_TABLE_STATES:  # what kernel_tables would refuse: trial by trial from now
                # the interval's memory checked first: a refused call leaves the stream as it was
                self._check_memory(self._trial_rate_hz(lam, t_end - self._t_rel), t_end)
                self._to_trials(lam, len(levels), int(spans[:, 1].sum()), timer is not None)
                return self._advance_trials(lam, t_end)
            table, itable, offsets, sizes, rates = kernel_tables(levels, p, spans.tolist(), background=(a_on, a_off),
                                                                 thresholds=eps, timer=timer)
            lowest = spans[:, 0].astype(np.float64)
            self._memory = (key, (table, itable, offsets, sizes), lowest, rates, spans, timer)
        _, tables, lowest, rates, _, timer = self._memory
        self._check_memory(float(rates[group].sum()), t_end)
        sizes = tables[3]
        lo, top = lowest[group], (sizes[group] - 1).astype(np.float64)
        mem = np.clip(self._stored - lo, 0.0, top)  # NaN stays NaN: drawn from the steady state
        fstate = self._state.fstate
        pend = np.flatnonzero(np.isfinite(fstate[:, PEND_TAU]))
        if pend.size:  # an event pending from the last interval keeps its new state as a count
            code = fstate[pend, PEND_ON]
            new = np.clip(self._pending_count[pend] - lo[pend], 0.0, top[pend])
            fstate[pend, PEND_ON] = code % 2.0 + 2.0 * (new + 1.0)
        j_min = _first_trial_at_or_after(self._t_rel, dt)
        discard = _first_trial_at_or_after(t_end, dt)
        if timer is not None:  # a pending timer arrival moves with a change of its intensity (as without memory)
            self._state.rescale_timers(self._timer_intensity(lam), j_min)
        parts = memory_step(self._state, mem, self.shape[1], group, tables, dt, p.refractory_us, j_min, float(t_end),
                            discard, self._t0, self.threads, rates[group] * ((t_end - self._t_rel) * 1e-6), timer)
        out = sorted_window(parts, self._t0 + self._t_rel, self._t0 + t_end, state=self._state)
        self._stored = mem + lo
        code = fstate[:, PEND_ON]
        self._pending_count = np.where(np.isfinite(fstate[:, PEND_TAU]), code // 2.0 - 1.0 + lo, np.nan)
        self._t_rel = t_end
        return out

    def _to_trials(self, lam, n_chains: int, n_states: int, timer: bool):
        """From now on every pixel trial by trial (the trial kernel): the chains' tables would pass
        :data:`~evnoise.terms.memory.MAX_TABLE_STATES` (``n_chains`` chains, ``n_states`` states; ``timer``: they
        have the regular background timer, which this does not cover: refused). Before the first interval each
        pixel starts in its steady state (:class:`evnoise._memory_chains.OwnChainStarts`, as ``simulate_events``);
        later its stored count carries over, and an event pending from the last interval (its trial started
        there) is kept as that interval's last event: given its stored count a pixel's trials are independent
        until its next event, so going on trial by trial from here is exact."""
        from ._kernels import simulate as ks
        from ._memory_chains import TIMER_NEEDS_TABLES, memory_chains
        from .terms.memory import too_many_states

        if timer:
            raise too_many_states(n_chains, n_states, TIMER_NEEDS_TABLES)
        p = self.params
        state = self._state
        bg_rows = terms.kernel_coefficients(p, self._bg, state.pix)
        model = terms.kernel_model(p)
        thr = np.stack([np.expm1(self._eps_on), np.expm1(self._eps_off), self._eps_on, self._eps_off])
        state.lam_ref[:] = lam
        state.lam_prev[:] = lam
        fstate = state.fstate
        carry = None
        if np.isnan(self._stored).all():  # nothing run yet: each pixel's steady state at this light
            chains = memory_chains(lam, p, self._bg, self._eps_on, self._eps_off, self.threads)
            chains.start_trials(state, chains.group, p.trial_us, p.refractory_us, self.threads, bg_rows, lam, model)
        else:
            pend = np.flatnonzero(np.isfinite(fstate[:, ks.PEND_TAU]))
            tau = fstate[pend, ks.PEND_TAU]
            width = self.shape[1]
            polarity = (fstate[pend, ks.PEND_ON].astype(np.int64) % 2).astype(np.uint8)  # code: on + 2 (state + 1)
            carry = (self._t0 + np.floor(tau).astype(np.int64), (pend % width).astype(np.uint16),
                     (pend // width).astype(np.uint16), polarity)
            stored = self._stored.copy()
            stored[pend] = self._pending_count[pend]
            fstate[pend, ks.LAST_TRIAL] = fstate[pend, ks.PEND_TRIAL]
            fstate[pend, ks.LAST_TAU] = tau
            fstate[:, ks.STORED] = stored
            for col in (ks.PEND_TRIAL, ks.PEND_TAU, ks.PEND_ON):
                fstate[:, col] = np.nan
        self._trials = (thr, bg_rows, model)
        self._carry = carry
        self._memory = self._grouping = None  # the tables are not needed again

    def _advance_trials(self, lam, t_end: int) -> np.ndarray:
        """:meth:`advance` trial by trial (reset memory beyond the table budget, :meth:`_to_trials`): the trials that
        start in the interval, at its light; an event of its last trial that falls at or after ``t_end`` is kept for
        the next interval (as the renewal kernels keep a pending event)."""
        from ._engine import trial_step

        p = self.params
        dt = p.trial_us
        thr, bg_rows, model = self._trials
        state = self._state
        state.lam_ref[:] = lam  # the host's light: no signal crossings here, noise only
        state.lam_prev[:] = lam
        j_a = int(_first_trial_at_or_after(self._t_rel, dt))
        j_b = int(_first_trial_at_or_after(t_end, dt))
        self._check_memory(self._trial_rate_hz(lam, t_end - self._t_rel), t_end)
        parts = [self._carry] if self._carry is not None else []
        if j_b > j_a:
            parts += trial_step(state, self.shape[1], lam[None, :], np.zeros(1), j_a, j_b, thr, bg_rows, model,
                                math.inf, self._t0, self.threads)
        cols = [np.concatenate([c[i] for c in parts]) for i in range(4)] if parts else None
        if cols is None:
            self._t_rel = t_end
            return empty_events(0)
        late = cols[0] >= self._t0 + t_end
        self._carry = tuple(c[late] for c in cols)
        out = sorted_window([tuple(c[~late] for c in cols)], self._t0 + self._t_rel, self._t0 + t_end)
        self._t_rel = t_end
        return out


    def _trial_rate_hz(self, lam, span_us: float) -> float:
        """The sensor's event rate (events/s) to size an interval of ``span_us`` run trial by trial: a bound (a
        pixel's trial gives at most one event, and the background its own), or where that bound would not fit in
        memory, twice the mean rate of a population of pixels without memory at each one's light (no tables give each
        pixel's rate here; run trial by trial over the presets, reset_memory 0.5-1, mismatch 0-0.08 and 0.01-3000
        lux, memory changed that mean by 0.07-1.65x: tests/test_stream_limits.py holds the worst cases),
        interpolated in log lux from :data:`RATE_GRID_LEVELS` light levels where the scene has more (a smooth
        function of the light; each level's population mean takes 25-270 ms)."""
        from ._budget import memory_budget
        from ._checks import MAX_LUX
        from .background import lux_of_photons
        from .rates import expected_rate

        bound = lam.size / (self.params.trial_us * 1e-6) + float(self._timer_intensity(lam).sum())
        budget = memory_budget()
        if budget is None or bound * span_us * 1e-6 * (EVENT_DTYPE.itemsize + WINDOW_BYTES_PER_EVENT) <= budget:
            return bound
        levels, count = np.unique(lam, return_counts=True)
        lux = np.minimum(lux_of_photons(levels, self.params), MAX_LUX)  # the round trip may land a hair above
        grid = lux  # sorted, distinct: lux[1] > 0
        if lux.size > RATE_GRID_LEVELS:
            grid = np.unique(np.concatenate([lux[:1], np.geomspace(lux[1], lux[-1], RATE_GRID_LEVELS - 1)]))
        memoryless = self.params.replace(reset_memory=0.0)
        mean_hz = expected_rate(grid, memoryless, mismatch="mean").sum(axis=0)
        if grid is not lux:
            mean_hz = np.interp(np.log(lux + 1e-6), np.log(grid + 1e-6), mean_hz)
        return 2.0 * float(mean_hz @ count)


def _memory_spans(levels, group, stored, pending) -> np.ndarray:
    """Per light level, the states ``(lo, n_states)`` (rows of an ``(n, 2)`` int64 array) its tables need:
    :func:`~evnoise.terms.memory.state_range`'s, widened to hold the stored counts (and pending events' new counts)
    its pixels bring from another light,
    up to :data:`~evnoise.terms.memory.MAX_STATES` states (counts beyond are clamped into the range: only a
    step of the light by many times its own photon noise at hundreds of photons per trial goes that far)."""
    from .terms.memory import MAX_STATES, level_spans

    low = np.full(len(levels), np.inf)
    high = np.full(len(levels), -np.inf)
    for counts in (stored, pending):  # each level's lowest and highest count brought (NaN: none)
        known = np.isfinite(counts)
        np.minimum.at(low, group[known], counts[known])
        np.maximum.at(high, group[known], counts[known])
    which, _, lo_level, n_level = level_spans(levels)
    lo, n = lo_level[which], n_level[which]
    hi = lo + n - 1
    brought = np.isfinite(low)
    room = np.maximum(0, MAX_STATES - n)
    low_i = np.where(brought, low, 0.0).astype(np.int64)  # whole counts
    high_i = np.where(brought, high, 0.0).astype(np.int64)
    new_lo = np.where(brought, np.minimum(lo, np.maximum(low_i, lo - room)), lo)
    new_hi = np.where(brought, np.maximum(hi, np.minimum(high_i, hi + room)), hi)
    cap = np.maximum(MAX_STATES, n)
    new_hi = np.where(brought & (new_hi - new_lo + 1 > cap), new_lo + cap - 1, new_hi)
    return np.stack([new_lo, new_hi - new_lo + 1], axis=1).astype(np.int64)


def _inside(spans, outer) -> np.ndarray:
    """The states of each of ``spans`` (``(n, 2)``: ``lo, n_states``) within the matching row of ``outer``."""
    lo = np.maximum(spans[:, 0], outer[:, 0])
    hi = np.minimum(spans[:, 0] + spans[:, 1], outer[:, 0] + outer[:, 1]) - 1
    return np.stack([lo, hi - lo + 1], axis=1)


def _first_trial_at_or_after(t_us: float, dt: float) -> float:
    """Index of the first trial starting at or after ``t_us`` (``t_us >= 0``): the kernels' eligibility rule
    with no previous event and no refractory period (one home for the rounding of trial starts)."""
    from ._kernels.simulate import first_eligible_trial

    return float(first_eligible_trial(-1.0, float(t_us), 0.0, float(dt)))
