"""Event simulation: static scenes, changing scenes, and a noise stream for other simulators.

Fidelity tiers ("model only what a scene needs"):

``renewal``
    A pixel whose illuminance never changes fires in i.i.d. trials with probabilities
    ``p_on``, ``p_off`` (the closed form), so its events are a renewal process: the gap to
    the next event is geometric in eligible trials. Cost O(events).
``trials``
    The full per-trial model: ``n ~ Poisson(lam(t))``, ``n0 ~ Poisson(lam_ref)``, threshold
    comparison, signal crossings of the mean level, refractory period. Cost O(pixels x trials).

``method="auto"`` uses the renewal tier for every pixel that is static over the whole run and
the trial tier for the others (with reset memory whose chains are too many for tables: the trial tier for every
pixel, each chain's start computed on its own). Randomness: each pixel has its own stream (xoshiro256++ keyed
by the caller's generator and the pixel index), so the output does not depend on the number
of threads, the chunking of pixels, or the windows in which time is generated (whose length depends on the
number of pixels), for a still scene and a video alike (the trial tier's runs at one light are the trials', their
probabilities evaluated value by value).
"""

from __future__ import annotations

import collections
import math
from typing import Iterator

import numpy as np

from . import terms
from ._budget import human_bytes
from ._checks import check_lux, duration_to_us, resolve_threads
from ._engine import (
    Collector,
    PixelState,
    check_event_memory,
    check_span,
    check_t_start,
    memory_step,
    progress_bar,
    renewal_step,
    select_background,
    sorted_window,
    static_inputs,
    trial_step,
)
from ._memory_chains import RENEWAL_NEEDS_TABLES, memory_chains
from ._run import run_setup
from .errors import InputError, ParameterError
from .events import empty_events
from .params import NoiseParams
from .rates import trial_probabilities
from .terms.memory import memory_on

__all__ = [
    "simulate_events",
    "iter_events",
    "EventWindows",
    "estimate_file_size",
    "check_disk_space",
    "simulate_video",
    "iter_video",
    "sample_counts",
    "NoiseStream",
]

TARGET_EVENTS_PER_WINDOW = 1_000_000
#: Every window advances every static pixel (a pass over their state, ~30 ns a pixel on one core here, whatever
#: their events): a static scene's windows hold at least this many events per pixel, so that pass stays a small part
#: of a window's cost (a 1280x720 scene at 2 lux, 1.2-20 M events, 2 threads: 5-30 % less time per event in one
#: process than in windows of 1 M events, the same events bit for bit; benchmarks/bench_windows.py), up to
#: :data:`MAX_EVENTS_PER_WINDOW` (a window's working memory is about
#: :data:`evnoise._engine.WINDOW_BYTES_PER_EVENT` per event).
EVENTS_PER_PIXEL_PER_WINDOW = 8
MAX_EVENTS_PER_WINDOW = 8_000_000
TARGET_PIXEL_TRIALS_PER_WINDOW = 40_000_000
#: the trial tier's windows at most this long (a changing pixel's events are not bounded by events_per_window)
MAX_WINDOW_US = 1 << 22
#: a static scene's windows (bounded by events_per_window) at most this long (~67 s): at a low event rate a long
#: window saves passes over the pixels' state (~0.6 events per pixel in a 4 s window of a 1280x720 scene at 0.01 or
#: 300 lux); the window sort takes up to ~268 s (evnoise._kernels.simulate.SORT_COARSE_MAX)
MAX_STATIC_WINDOW_US = 1 << 26
# Trial tier: pixels static within a window (lam = lam_ref) jump between events with geometric
# gaps (O(events)); False keeps the per-trial reference algorithm (tests compare the two).
TRIAL_FAST_STATIC = True
METHODS = ("auto", "renewal", "trials")


class EventWindows:
    """The windows of a simulation, produced lazily (what :func:`iter_events` and :func:`iter_video` return).

    An iterator of time-sorted event arrays (memory stays bounded by one window whatever the
    duration) that also says what to expect before the first window is made:

    ``expected_events``
        expected number of events (float): exact in expectation for a static scene; for a video
        the noise events of its first frame over the whole run (signal events come on top).
    ``noise_only``
        True for a video: ``expected_events`` then counts the noise at the first frame's light, not the total.
    ``t_start_us``, ``duration_us``
        the span of the recording in microseconds.
    """

    def __init__(self, windows, *, expected_events, t_start_us: int, duration_us: int, noise_only: bool = False):
        self._windows = windows
        self.noise_only = bool(noise_only)
        self._expected = expected_events  # a number, or a function computing it when first asked
        self.t_start_us = int(t_start_us)
        self.duration_us = int(duration_us)

    @property
    def expected_events(self) -> float:
        if callable(self._expected):
            self._expected = self._expected()
        return float(self._expected)

    def __iter__(self):
        return self

    def __next__(self):
        return next(self._windows)

    def close(self) -> None:
        """Stop early (closes the progress bar; nothing more is simulated)."""
        self._windows.close()


def _check_memory(expected_events: float, what: str = "simulate_events", window_events: float = 0.0) -> None:
    """Refuse to hold an event array that cannot fit in memory (before allocating it); ``window_events``: the
    events of a window made while the array fills (its working memory counts too)."""
    check_event_memory(expected_events, f"{what} would return about {expected_events:,.0f} events; they",
                       window_events=window_events,
                       hint="shorten the duration, or stream the windows (iter_events, iter_video) into a file "
                            "(EventWriter)")


# Bytes per event of each output format (measured on `simulate --example`, 1 M events in 2 s), and
# events.h5's bytes per millisecond of its ms_to_idx index. Typical values, not bounds: a file can
# come out somewhat larger or smaller.
BYTES_PER_EVENT = {"h5": 4.0, "h5-lzf": 5.0, "h5-none": 14.0, "aedat4": 9.5, "evt3": 6.0, "dat": 8.0, "es": 5.5,
                   "csv": 13.0}
H5_BYTES_PER_MS = {"gzip": 2.0, "lzf": 3.0, None: 8.0}


def estimate_file_size(expected_events: float, duration_us: int, fmt: str = "h5", *, compression="gzip",
                       t_end_us: int | None = None) -> float:
    """Typical size in bytes of an event file of ``expected_events`` events over ``duration_us``.

    ``fmt`` is the output format (``"h5"``, ``"aedat4"``, ``"evt3"``, ``"dat"``, ``"es"``, ``"csv"``);
    ``compression`` applies to ``"h5"``. A CSV row grows with the digits of its timestamps (``t_end_us``).
    """
    events = max(float(expected_events), 0.0)
    if fmt == "h5":
        key = "h5" if compression == "gzip" else f"h5-{compression or 'none'}"
        per_ms = H5_BYTES_PER_MS.get(compression, 8.0)
        return events * BYTES_PER_EVENT[key] + (duration_us / 1000.0) * per_ms + 4096.0
    per_event = BYTES_PER_EVENT.get(fmt, 16.0)
    if fmt == "csv":
        per_event += len(str(int(t_end_us if t_end_us is not None else duration_us)))
    return events * per_event + 4096.0


def check_disk_space(windows, path, fmt: str = "h5", *, compression="gzip") -> str:
    """One line with the expected events and file size of a simulation; refuses what cannot fit on the disk.

    ``windows`` is what :func:`iter_events` / :func:`iter_video` returned. Raises
    :class:`~evnoise.OutputError` when the typical file size exceeds the free space of ``path``'s
    file system (:func:`shutil.disk_usage`), before anything is simulated or written.
    """
    import shutil
    from pathlib import Path

    from .errors import OutputError

    expected = windows.expected_events
    size = estimate_file_size(expected, windows.duration_us, fmt, compression=compression,
                              t_end_us=windows.t_start_us + windows.duration_us)
    folder = Path(path).parent if str(Path(path).parent) else Path(".")
    if getattr(windows, "noise_only", False):  # a video: its signal events come on top of the noise
        line = (f"expecting about {expected:,.0f} noise events at the first frame's light (the scene's changes add "
                f"more), a file of about {human_bytes(size)} for those")
    else:
        line = f"expecting about {expected:,.0f} events, a file of about {human_bytes(size)}"
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return line
    if size > free:
        raise OutputError(f"{path} would be about {human_bytes(size)} ({expected:,.0f} events expected), more "
                          f"than the {human_bytes(free)} free on its disk; shorten the duration or choose "
                          f"another disk")
    return f"{line} ({human_bytes(free)} free)"


# --------------------------------------------------------------------------------------
# static scenes
# --------------------------------------------------------------------------------------
def iter_events(
    lux,
    params: NoiseParams,
    duration_s: float,
    rng=None,
    method: str = "auto",
    *,
    thresholds=None,
    background=None,
    t_start_us: int = 0,
    threads: int | None = None,
    progress: bool = False,
) -> Iterator[np.ndarray]:
    """Simulate a static scene, yielding time-sorted event arrays window by window.

    The concatenation of the yielded arrays is the full, sorted event stream of :func:`simulate_events`, and
    memory stays bounded by one window (about a million events or 8 per pixel of the scene, whichever is more, at
    most eight million). Validation happens at the call, before the first window.

    Parameters
    ----------
    lux : array_like, shape (H, W)
        Illuminance at the sensor in lux (finite, ``>= 0``).
    params : NoiseParams
        Model parameters.
    duration_s : float
        Length of the recording in seconds (``> 0``), as in :func:`simulate_events`.
    rng : numpy.random.Generator, int or None
        Randomness; the same seed gives the same events as :func:`simulate_events`.
    method : {"auto", "renewal", "trials"}
        Fidelity tier, as in :func:`simulate_events`.
    thresholds : array_like, optional
        Per-pixel thresholds ``(2, H, W)``, as in :func:`simulate_events`.
    background : array_like, optional
        Per-pixel background maps ``(2, H, W)``, as in :func:`simulate_events`.
    t_start_us : int
        Timestamp of the start of the recording in microseconds.
    threads : int, optional
        Worker threads (default ``NUMBA_NUM_THREADS`` or the CPU count).
    progress : bool
        Show a progress bar (tqdm) in simulated seconds while the windows are made.

    Returns
    -------
    EventWindows
        An iterator of event arrays (:data:`evnoise.EVENT_DTYPE`), each sorted by time, that also gives the
        expected number of events before the first window is made.
    """
    return _iter_events(lux, params, duration_s, rng, method, thresholds, t_start_us, threads, progress,
                        background=background)


def _iter_events(lux, params, duration_s, rng, method, thresholds, t_start_us, threads, progress, sink=None,
                 background=None):
    """:func:`iter_events`; with ``sink`` (static scenes) each window is sorted straight into it."""
    lux = check_lux(lux)
    duration_us = duration_to_us(duration_s)
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    t_start_us = check_t_start(t_start_us)
    threads = resolve_threads(threads)
    run = run_setup(lux.shape, params, rng, thresholds=thresholds, background=background,  # before any draw:
                    before_draws=lambda p: check_span(t_start_us, duration_us, p.trial_us, "duration"))
    params, key, (eps_on, eps_off), bg = run.params, run.key, run.thresholds, run.background
    if memory_on(params) and method != "trials":
        return _still_memory_windows(lux, params, key, t_start_us, duration_us, threads, progress, sink, bg,
                                     (eps_on, eps_off), method)
    if method == "trials":
        return _still_trial_windows(lux, params, key, t_start_us, duration_us, threads, progress, sink, bg,
                                    (eps_on, eps_off))
    return _iter_static(lux, params, key, eps_on, eps_off, t_start_us, duration_us, threads, progress, sink, bg)


def _still_trial_windows(lux, params, key, t_start_us, duration_us, threads, progress, sink, bg, thresholds,
                         memory_plan=None):
    """The windows of a still scene in the trial tier (``memory_plan``: as :func:`_iter_dynamic`'s)."""
    windows = _iter_dynamic(_FrameSource([lux], name="lux"), np.array([0.0, float(duration_us)]), params, key,
                            *thresholds, np.zeros(lux.size, dtype=bool), t_start_us, duration_us, threads, progress,
                            bg=bg, memory_plan=memory_plan)
    if sink is not None:
        _check_memory(windows.expected_events)
        windows = _into_sink(windows, sink)
    return windows


def _still_memory_windows(lux, params, key, t_start_us, duration_us, threads, progress, sink, bg, thresholds,
                          method="auto"):
    """The windows of a still scene with reset memory: the renewal tier over its chains' tables
    (:func:`_iter_memory`) or, where the chains are too many for tables (:data:`~evnoise.terms.memory.MAX_TABLE_STATES`)
    and ``method`` is ``"auto"``, the trial tier, each chain's start computed on its own (:class:`OwnChainStarts`)."""
    from .terms.memory import MAX_TABLE_STATES, chain_plan, too_many_states

    plan = chain_plan(params.photons_per_trial(lux).ravel(), params, bg, thresholds)
    if plan[2] <= MAX_TABLE_STATES:
        return _iter_memory(lux, params, key, t_start_us, duration_us, threads, progress, sink, bg=bg,
                            thresholds=thresholds, plan=plan)
    if method == "renewal":
        raise too_many_states(len(plan[0][0]), plan[2], RENEWAL_NEEDS_TABLES)
    return _still_trial_windows(lux, params, key, t_start_us, duration_us, threads, progress, sink, bg, thresholds,
                                plan)


def _into_sink(windows: "EventWindows", sink) -> "EventWindows":
    """``windows`` (the trial tier's, sorted on their own) copied one by one into ``sink``, sized for the expected
    events first; each window yielded is the sink's view of it."""
    total = windows.expected_events
    sink.__init__(int(math.ceil(total + 8.0 * math.sqrt(total) + 4096)))

    def gen():
        for window in windows:
            view = sink.reserve(window.size)
            view[...] = window
            del window
            yield view

    return EventWindows(gen(), expected_events=total, t_start_us=windows.t_start_us,
                        duration_us=windows.duration_us)


def events_per_window(n_pixels: int) -> int:
    """Events a static scene's window of ``n_pixels`` pixels aims at: :data:`TARGET_EVENTS_PER_WINDOW`, or
    :data:`EVENTS_PER_PIXEL_PER_WINDOW` per pixel where that is more, at most :data:`MAX_EVENTS_PER_WINDOW`
    (the output is the same for any window length)."""
    return max(TARGET_EVENTS_PER_WINDOW, min(MAX_EVENTS_PER_WINDOW, EVENTS_PER_PIXEL_PER_WINDOW * n_pixels))


def _static_windows(n_pixels, key, threads, total, t_start_us, duration_us, progress, sink, reserve, step):
    """The windows of a static scene, whatever advances its pixels (the body :func:`_iter_static` and
    :func:`_iter_memory` share).

    ``total`` is the expected number of events; the run is cut into windows of about
    :func:`events_per_window` events (and at most :data:`MAX_STATIC_WINDOW_US` long), their ends whole
    microseconds made one at a time, so any duration streams in bounded memory. ``reserve``: the events a
    ``sink`` is sized for. ``step(state, t_prev_us, w_end_us)`` advances every pixel (``state``: their
    :class:`PixelState`) to ``w_end_us`` and returns the window's unsorted parts.
    """
    n_win = max(1, math.ceil(total / events_per_window(n_pixels)), -(-duration_us // MAX_STATIC_WINDOW_US))
    if sink is not None:
        _check_memory(total, window_events=events_per_window(n_pixels))
        sink.__init__(int(math.ceil(reserve)))

    def gen():
        state = PixelState(np.arange(n_pixels), key, threads)
        bar = _time_bar(duration_us, progress)
        t_prev = 0
        for k in range(n_win):
            w_end = duration_us * (k + 1) // n_win
            parts = step(state, t_prev, w_end)
            window = sorted_window(parts, t_start_us + t_prev, t_start_us + w_end, sink=sink, state=state)
            del parts  # not held while the caller has the window
            yield window
            del window
            if bar is not None:
                bar.update(w_end - t_prev)  # whole microseconds: the steps add up to the total exactly
            t_prev = w_end
        if bar is not None:
            bar.close()

    return EventWindows(gen(), expected_events=total, t_start_us=t_start_us, duration_us=duration_us)


def _iter_static(lux, params, key, eps_on, eps_off, t_start_us, duration_us, threads, progress, sink=None,
                 bg=None):
    width = lux.shape[1]
    lam = params.photons_per_trial(lux).ravel()
    log1m_p, q_on, timer, nu = static_inputs(lam, params, eps_on, eps_off, bg)
    dt = params.trial_us
    refr = params.refractory_us
    del lam  # not needed while the windows run: keep the per-pixel memory small
    total = float(nu.sum()) * duration_us * 1e-6

    def step(state, t_prev, w_end):
        return renewal_step(state, width, log1m_p, q_on, dt, refr, 0, w_end, math.inf, t_start_us, threads,
                            expected=nu * (w_end - t_prev) * 1e-6, timer=timer)

    # counts are under-dispersed against Poisson (renewal with dead time): 8 sigma is ample
    return _static_windows(lux.size, key, threads, total, t_start_us, duration_us, progress, sink,
                           total + 8.0 * math.sqrt(total) + 4096, step)


def _iter_memory(lux, params, key, t_start_us, duration_us, threads, progress, sink=None, bg=None, thresholds=None,
                 plan=None):
    """The windows of a static scene with reset memory (:mod:`evnoise.terms.memory`): pixels grouped by light
    level, background and thresholds (``bg``: the run's flat maps or None; ``thresholds``: its flat per-pixel
    ``(eps_on, eps_off)`` or None), each advanced event by event over its group's state tables
    (:mod:`evnoise._kernels.memory`)."""
    from .terms.memory import EXACT_RATE_LEVELS, chain_plan, still_chains

    width = lux.shape[1]
    lam = params.photons_per_trial(lux).ravel()
    plan = chain_plan(lam, params, bg, thresholds) if plan is None else plan
    n_chains = len(plan[0][0])
    # many chains (threshold mismatch: about one per pixel) take about 0.5 ms each before the first event
    bar = progress_bar(n_chains, progress and n_chains > EXACT_RATE_LEVELS, "memory tables", unit="chains")
    try:
        _, group, tables, level_rates, timer = still_chains(lam, params, bg, thresholds, plan,
                                                            done=None if bar is None else bar.update)
    finally:
        if bar is not None:
            bar.close()
    nu = level_rates[group]
    dt = params.trial_us
    refr = float(params.refractory_us)
    total = float(nu.sum()) * duration_us * 1e-6
    mem = np.full(lux.size, math.nan)  # each pixel's stored state (NaN: drawn at its first window)

    def step(state, t_prev, w_end):
        return memory_step(state, mem, width, group, tables, dt, refr, 0.0, float(w_end), math.inf,
                           np.int64(t_start_us), threads, nu * ((w_end - t_prev) * 1e-6), timer)

    return _static_windows(lux.size, key, threads, total, t_start_us, duration_us, progress, sink,
                           1.2 * total + 8.0 * math.sqrt(total) + 4096, step)


def _time_bar(duration_us: int, enabled: bool):
    """Progress in simulated seconds, counted in whole microseconds (no float drift past the total)."""
    return progress_bar(duration_us, enabled, "simulate", scale=1e-6)


def simulate_events(
    lux,
    params: NoiseParams,
    duration_s: float,
    rng=None,
    method: str = "auto",
    *,
    thresholds=None,
    background=None,
    t_start_us: int = 0,
    threads: int | None = None,
    progress: bool = False,
) -> np.ndarray:
    """Noise events of a static scene.

    Parameters
    ----------
    lux : array_like, shape (H, W)
        Illuminance at the sensor in lux (finite, ``>= 0``).
    params : NoiseParams
        Model parameters.
    duration_s : float
        Length of the recording in seconds (``> 0``); events have
        ``t_start_us <= t < t_start_us + round(duration_s * 1e6)``.
    rng : numpy.random.Generator, int or None
        Randomness; the same seed gives the same events whatever the number of threads.
    method : {"auto", "renewal", "trials"}
        Fidelity tier; for a static scene ``"auto"`` is the renewal tier (exact, O(events)),
        ``"trials"`` runs the full per-trial model (statistically identical, slower). With reset memory whose chains
        are too many for tables (``evnoise.terms.memory.MAX_TABLE_STATES``) ``"auto"`` runs the trial tier and
        ``"renewal"`` is refused.
    thresholds : array_like, optional
        Per-pixel thresholds ``(2, H, W)``; drawn from ``rng`` when ``params.eps_sigma > 0``.
    background : array_like, optional
        Per-pixel background maps ``(2, H, W)`` (``[spread factor, hot rate]``, see
        :func:`evnoise.draw_background`); drawn from ``rng`` (after the thresholds) when
        ``params.leak_sigma > 0`` or hot pixels are on.
    t_start_us : int
        Timestamp of the start of the recording in microseconds.
    threads : int, optional
        Worker threads (default ``NUMBA_NUM_THREADS`` or the CPU count).
    progress : bool
        Show a progress bar (tqdm) in simulated seconds while the events are made.

    Returns
    -------
    numpy.ndarray
        Events (:data:`evnoise.EVENT_DTYPE`), sorted by time.
    """
    # one output array, each window sorted straight into it (the trial tier: copied into it), so the peak memory
    # is about the output plus one window, instead of twice the output for a final concatenation
    sink = Collector(0)
    # windows consumed and dropped (none held: the last is a view of the sink's array, which shrinks in place)
    collections.deque(_iter_events(lux, params, duration_s, rng, method, thresholds, t_start_us, threads, progress,
                                   sink, background), maxlen=0)
    return sink.result()


# --------------------------------------------------------------------------------------
# changing scenes
# --------------------------------------------------------------------------------------
class _FrameSource:
    """Validated, lazily read frames of illuminance (any sequence of 2-D arrays)."""

    def __init__(self, frames, name: str = "frames_lux"):
        if isinstance(frames, np.ndarray):
            if frames.ndim != 3 and not (name == "lux" and frames.ndim == 2):
                raise InputError(f"{name} must have shape (F, H, W), got {frames.shape}")
        try:
            self.n = len(frames)
        except TypeError:
            raise InputError(f"{name} must be a sequence of 2-D arrays (or an (F, H, W) array)") from None
        if self.n == 0:
            raise InputError(f"{name} is empty")
        self.frames = frames
        self.name = name
        self.shape = None
        first = self.get(0)
        self.shape = first.shape

    def get(self, i: int) -> np.ndarray:
        label = f"{self.name}[{i}]"
        frame = self.frames[i]
        arr = check_lux(frame, name=label)
        if self.shape is not None and arr.shape != self.shape:
            raise InputError(f"{label} has shape {arr.shape}, but the first frame has shape {self.shape}")
        return arr


def _check_timestamps(timestamps_s, n_frames: int) -> np.ndarray:
    try:
        ts = np.asarray(timestamps_s, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("timestamps_s must be a 1-D array of seconds") from None
    if ts.ndim != 1 or ts.size != n_frames:
        raise InputError(f"timestamps_s must have one entry per frame ({n_frames}), got shape {ts.shape}")
    if n_frames < 2:
        raise InputError("a video needs at least 2 frames (use simulate_events for a static scene)")
    if not np.isfinite(ts).all():
        raise InputError("timestamps_s contains NaN or Inf")
    if np.any(np.diff(ts) <= 0):
        i = int(np.flatnonzero(np.diff(ts) <= 0)[0])
        raise InputError(f"timestamps_s must be strictly increasing; timestamps_s[{i + 1}] = {ts[i + 1]} "
                         f"<= timestamps_s[{i}] = {ts[i]}")
    return ts


#: a video of more frames shows a progress bar while they are first read (``progress=True``)
FRAMES_WITHOUT_BAR = 100


def iter_video(
    frames_lux,
    timestamps_s,
    params: NoiseParams,
    rng=None,
    method: str = "auto",
    *,
    thresholds=None,
    background=None,
    threads: int | None = None,
    progress: bool = False,
    return_labels: bool = False,
) -> Iterator[np.ndarray]:
    """Simulate a changing scene, yielding time-sorted event arrays window by window.

    See :func:`simulate_video`. Frames may be any sequence of ``(H, W)`` arrays (read
    lazily, two passes: one to find the static pixels, one to simulate). With
    ``return_labels`` each item is ``(events, is_signal)``.

    Parameters
    ----------
    frames_lux : array_like (F, H, W) or sequence of (H, W) arrays
        Illuminance in lux of each frame (finite, ``>= 0``, all the same shape), at least two frames.
    timestamps_s : array_like (F,)
        Time of each frame in seconds, strictly increasing, as in :func:`simulate_video`.
    params : NoiseParams
        Model parameters.
    rng : numpy.random.Generator, int or None
        Randomness, as in :func:`simulate_events`.
    method : {"auto", "renewal", "trials"}
        Fidelity tier, as in :func:`simulate_video`.
    thresholds : array_like, optional
        Per-pixel thresholds ``(2, H, W)``, as in :func:`simulate_events`.
    background : array_like, optional
        Per-pixel background maps ``(2, H, W)``, as in :func:`simulate_events`.
    threads : int, optional
        Worker threads (default ``NUMBA_NUM_THREADS`` or the CPU count).
    progress : bool
        Show progress bars (tqdm): while the frames are first read (videos of more than
        :data:`FRAMES_WITHOUT_BAR` frames) and in simulated seconds while the windows are made.
    return_labels : bool
        Yield ``(events, is_signal)`` pairs: a bool array, True for signal events, as in :func:`simulate_video`.

    Returns
    -------
    EventWindows
        An iterator of event arrays (:data:`evnoise.EVENT_DTYPE`) sorted by time (or of ``(events, is_signal)``
        pairs with ``return_labels``); its ``expected_events`` counts the noise at the first frame's light.
    """
    frames = _FrameSource(frames_lux)
    ts = _check_timestamps(timestamps_s, frames.n)
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    threads = resolve_threads(threads)
    t0_us = check_t_start(round(ts[0] * 1e6), "the first frame's time (us)")
    frame_us = (ts - ts[0]) * 1e6
    duration_us = int(round(frame_us[-1]))
    if duration_us < 1:
        raise InputError("the video is shorter than one microsecond")
    def span_check(p):
        check_span(t0_us, duration_us, p.trial_us, "video")

    if isinstance(params, NoiseParams):
        span_check(params)  # before the frames are read (a preset name is loaded, once, by run_setup)
    shape = frames.shape
    static = np.ones(shape, dtype=bool)
    first = frames.get(0)
    # every frame is read once here (which pixels never change): 100,000 frames of a folder take minutes
    reading = progress_bar(frames.n - 1, progress and frames.n > FRAMES_WITHOUT_BAR, "reading frames", unit="frames")
    try:
        for i in range(1, frames.n):
            static &= frames.get(i) == first
            if reading is not None:
                reading.update(1)
    finally:
        if reading is not None:
            reading.close()
    if method == "trials":
        static[:] = False
    elif method == "renewal" and not static.all():
        raise ParameterError("method='renewal' needs a static scene, but some pixels change between frames")
    run = run_setup(shape, params, rng, thresholds=thresholds, background=background, before_draws=span_check)
    params, key, (eps_on, eps_off), bg = run.params, run.key, run.thresholds, run.background
    return _iter_dynamic(frames, frame_us, params, key, eps_on, eps_off, static.ravel(), t0_us,
                         duration_us, threads, progress, labels=return_labels, bg=bg, renewal=method == "renewal")


def simulate_video(
    frames_lux,
    timestamps_s,
    params: NoiseParams,
    rng=None,
    method: str = "auto",
    *,
    thresholds=None,
    background=None,
    threads: int | None = None,
    progress: bool = False,
    return_labels: bool = False,
):
    """Signal and noise events of a changing scene.

    Parameters
    ----------
    frames_lux : array_like (F, H, W) or sequence of (H, W) arrays
        Illuminance in lux of each frame (finite, ``>= 0``, all the same shape).
    timestamps_s : array_like (F,)
        Time of each frame in seconds, strictly increasing. The recording spans
        ``[timestamps_s[0], timestamps_s[-1])``; event timestamps are absolute microseconds.
    params : NoiseParams
        Model parameters.
    rng : numpy.random.Generator, int or None
        Randomness, as in :func:`simulate_events`.
    method : {"auto", "renewal", "trials"}
        ``"auto"``: renewal tier for pixels that never change, trial tier for the rest;
        ``"trials"``: trial tier everywhere; ``"renewal"``: only valid if nothing changes (and, with reset
        memory whose chains are too many for tables, refused: ``"auto"`` then runs every pixel trial by trial).
    thresholds : array_like, optional
        Per-pixel thresholds ``(2, H, W)``, as in :func:`simulate_events`.
    background : array_like, optional
        Per-pixel background maps ``(2, H, W)``, as in :func:`simulate_events`.
    threads : int, optional
        Worker threads (default ``NUMBA_NUM_THREADS`` or the CPU count).
    progress : bool
        Show progress bars (tqdm): while the frames are first read (videos of more than
        :data:`FRAMES_WITHOUT_BAR` frames) and in simulated seconds while the events are made.
    return_labels : bool
        Also return a bool array, True for *signal* events (threshold crossings of the mean
        level) and False for *noise* events (the photon-count comparison): the ground truth
        for signal/noise separation.

    Returns
    -------
    numpy.ndarray or (numpy.ndarray, numpy.ndarray)
        Events sorted by time, and with ``return_labels`` the labels.

    Notes
    -----
    The illuminance of a trial is the linear interpolation between the frames at the trial's
    centre. Signal events appear where the mean log-level ``log(lam + b)`` crosses whole
    thresholds away from the pixel's reference (about ``|delta log(lam + b)| / eps`` events per
    step change); noise events everywhere, from the per-trial photon-count comparison.
    """
    windows = iter_video(frames_lux, timestamps_s, params, rng, method, thresholds=thresholds, background=background,
                         threads=threads, progress=progress, return_labels=return_labels)
    _check_memory(windows.expected_events, "simulate_video")  # before anything runs (iter_video streams)
    parts = list(windows)
    if return_labels:
        if not parts:
            return empty_events(0), np.zeros(0, dtype=bool)
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    return np.concatenate(parts) if parts else empty_events(0)


def _fill_static_cache(state: PixelState, frames_lam: np.ndarray, params: NoiseParams, eps_on, eps_off, bg=None):
    """Closed-form probabilities of the pixels the trial tier will jump through in this window.

    Those whose ``lam`` is the same in every frame ``frames_lam`` (F, all pixels) of the window
    and equals their ``lam_ref`` and ``lam_prev`` (see :func:`evnoise._kernels.simulate.trial_window`),
    and whose cache does not already hold that ``lam``. Vectorised here (the grouped closed
    form) so that the kernel does not evaluate the exact sum pixel by pixel.
    """
    from ._kernels.simulate import PEND_TAU, static_in_window

    need = np.empty(state.pix.size, dtype=np.bool_)
    static_in_window(frames_lam, state.pix, state.fstate, need)
    sel = np.flatnonzero(need)
    if sel.size == 0:
        return
    lam0 = frames_lam[0, state.pix[sel]]
    state.cache_log1m_p[sel], state.cache_q_on[sel] = _jump_inputs(lam0, params, eps_on[sel], eps_off[sel],
                                                                   select_background(bg, sel))
    state.cache_lam[sel] = lam0
    state.fstate[sel, PEND_TAU] = np.nan  # a pending jump's event was drawn with the old probabilities


def _jump_inputs(lam, params: NoiseParams, eps_on, eps_off, bg, alone=False):
    """``(log1p(-(p_on + p_off)), p_on / (p_on + p_off))`` of the trial tier's jumps at ``lam`` (the kernel's cache);
    ``alone`` as :func:`evnoise.rates.trial_probabilities`'."""
    p_on, p_off = trial_probabilities(lam, params, (eps_on, eps_off), background=bg, alone=alone)
    p_all = p_on + p_off
    with np.errstate(divide="ignore", invalid="ignore"):
        log1m_p = np.where(p_all < 1.0, np.log1p(-np.minimum(p_all, 1.0)), -np.inf)
        q_on = np.where(p_all > 0.0, p_on / np.where(p_all > 0.0, p_all, 1.0), 0.0)
    return log1m_p, q_on


class _RunProbabilities:
    """A video's changing pixels' jump probabilities (the trial kernel's ``run_*`` arguments), the same bits however
    time is cut into windows.

    A pixel whose light is the same in frames ``i`` and ``i + 1`` may jump through the trials between them at that
    light. Only pairs with a trial's centre between their frames count (so the set does not depend on the windows),
    in increasing order, each once. A pixel's probabilities are evaluated once per *stretch* (pairs in a row at one
    light: :func:`evnoise._kernels.simulate.run_stretches`), each value alone
    (:func:`evnoise.model.log_event_probability_alone`: the closed form's faster paths depend on the batch).
    """

    def __init__(self, params: NoiseParams, eps_on, eps_off, bg):
        n = eps_on.size
        # one threshold for every changing pixel: passed as a scalar (the table, fast for any lam), else per pixel
        eps_on, eps_off = (float(e[0]) if e.size and np.all(e == e[0]) else e for e in (eps_on, eps_off))
        self.params, self.eps_on, self.eps_off, self.bg = params, eps_on, eps_off, bg
        self.last = -1  # the last pair evaluated
        self.valid = np.zeros(n, dtype=np.bool_)  # pixels in a stretch through pair `last`
        self.carry = np.full((n, 2), np.nan)  # its values

    def window(self, idx, segments, frames_lam, pix):
        """The kernel's ``(run_ptr, run_seg, run_val, run_carry)`` for a window whose frames are ``idx`` (increasing)
        and whose trials' centres lie between frames ``segments`` and ``segments + 1``, with photons per trial
        ``frames_lam`` ``(F, all pixels)`` of which the changing pixels are ``pix``."""
        from ._kernels.simulate import run_stretches

        idx = np.asarray(idx, dtype=np.int64)
        pairs = np.ascontiguousarray(np.sort(np.asarray(segments, dtype=np.int64)))
        segs = np.searchsorted(idx, pairs).astype(np.int64)
        n = pix.size
        count = np.empty(n, dtype=np.int64)
        none_i, none_f = np.empty(0, dtype=np.int64), np.empty(0)
        run_stretches(frames_lam, pix, segs, pairs, self.last, self.valid, count, none_i, none_i, none_f)
        ptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(count, out=ptr[1:])
        m = int(ptr[n])
        # (one slot more: a fill call also updates `valid`)
        seg_out, lam_out = np.empty(m + 1, dtype=np.int64), np.empty(m + 1)
        before = self.carry.copy()
        run_stretches(frames_lam, pix, segs, pairs, self.last, self.valid, count, ptr, seg_out, lam_out)
        seg_out, lam_out = seg_out[:m], lam_out[:m]
        values = np.empty((m, 2))
        if m:
            k = np.repeat(np.arange(n), np.diff(ptr))
            eps = [e if np.ndim(e) == 0 else e[k] for e in (self.eps_on, self.eps_off)]
            values[:, 0], values[:, 1] = _jump_inputs(lam_out, self.params, *eps, select_background(self.bg, k),
                                                      alone=True)
            # the stretch each pixel is in at the window's last pair: its last start here, or the one carried
            ends = ptr[1:][np.diff(ptr) > 0] - 1
            self.carry[k[ends]] = values[ends]
        self.carry[~self.valid] = np.nan
        self.last = max(self.last, int(pairs[-1]))
        return ptr, seg_out, values, before


def _iter_dynamic(frames, frame_us, params, key, eps_on, eps_off, static, t0_us, duration_us, threads,
                  progress, labels=False, bg=None, memory_plan=None, renewal=False):
    """Generator over windows of a changing scene (renewal for ``static`` pixels, trials for the rest; with reset
    memory whose chains are too many for tables, trials for every pixel, unless ``renewal``: the caller asked for the
    renewal tier, refused then). ``memory_plan``: :func:`~evnoise.terms.memory.chain_plan`'s at the first frame's
    light, when the caller has it."""
    width = frames.shape[1]

    def lam_of(i):
        return params.photons_per_trial(frames.get(i)).ravel()

    mem = None
    if memory_on(params):
        mem = memory_chains(lam_of(0), params, bg, eps_on, eps_off, threads, memory_plan, renewal)
        if mem.tables is None:
            static = np.zeros_like(static)
    dt = params.trial_us
    refr = params.refractory_us
    n_trials = math.ceil(duration_us / dt - 1e-12)
    stat_pix = np.flatnonzero(static)
    dyn_pix = np.flatnonzero(~static)
    c_on = np.expm1(eps_on)
    c_off = np.expm1(eps_off)

    def lam_first_trial():
        """The changing pixels' photons per trial at the first trial's centre (their reference at the start)."""
        idx = frame_indices(0, 1)
        lams = np.stack([lam_of(int(i))[dyn_pix] for i in idx])
        if idx.size == 1:
            return lams[0]
        a = min(max((0.5 * dt - frame_us[idx[0]]) / (frame_us[idx[1]] - frame_us[idx[0]]), 0.0), 1.0)
        return lams[0] + a * (lams[1] - lams[0])

    def segments(j_a, j_b):
        """Indices ``i`` of the pairs of frames ``(i, i + 1)`` whose times bracket the centres of trials j_a .. j_b - 1
        (clamped at the ends)."""
        centres = np.arange(j_a, j_b) * dt + 0.5 * dt  # as the kernel computes them, to the bit
        return np.unique(np.clip(np.searchsorted(frame_us, centres, side="right") - 1, 0, frames.n - 2))

    def frame_indices(j_a, j_b):
        """Indices of the frames bracketing the centres of trials j_a .. j_b - 1."""
        if frames.n == 1:
            return np.array([0])
        seg = segments(j_a, j_b)
        return np.unique(np.concatenate([seg, seg + 1]))

    # static pixels: closed-form probabilities once (with reset memory: their chains' tables)
    stat_timer = None
    if stat_pix.size and mem is not None:
        nu = mem.rates[mem.group[stat_pix]]
    elif stat_pix.size:
        lam0 = lam_of(0)[stat_pix]
        log1m_p, q_on, stat_timer, nu = static_inputs(lam0, params, eps_on[stat_pix], eps_off[stat_pix],
                                                       select_background(bg, stat_pix))

    def expected_events():
        """The static pixels' events, and the changing ones' noise at their first frame (asked for only)."""
        rate = float(nu.sum()) if stat_pix.size else 0.0
        if dyn_pix.size and mem is not None:
            rate += float(mem.rates[mem.group[dyn_pix]].sum())
        elif dyn_pix.size:
            *_, dyn_nu = static_inputs(lam_of(0)[dyn_pix], params, eps_on[dyn_pix], eps_off[dyn_pix],
                                       select_background(bg, dyn_pix))
            rate += float(dyn_nu.sum())
        return rate * duration_us * 1e-6
    dyn_bg = terms.kernel_coefficients(params, bg, dyn_pix)
    model = terms.kernel_model(params)  # what each noise term feeds the trial kernel
    regularity = model[terms.MODEL.index("regularity")]
    # the regular timer and reset memory are not memoryless
    fast_static = TRIAL_FAST_STATIC and regularity == 0.0 and mem is None
    per_window = max(1, TARGET_PIXEL_TRIALS_PER_WINDOW // max(1, dyn_pix.size))
    per_window = min(per_window, max(1, int(MAX_WINDOW_US // dt)))
    if stat_pix.size:
        stat_rate = float(nu.sum())
        if stat_rate > 0:
            per_window = min(per_window, max(1, int(events_per_window(stat_pix.size) / (stat_rate * dt * 1e-6))))
    n_windows = -(-n_trials // per_window)  # windows of per_window trials, made one at a time

    def gen():
        stat_state = PixelState(stat_pix, key, threads) if stat_pix.size else None
        dyn_state = PixelState(dyn_pix, key, threads) if dyn_pix.size else None
        cache: dict[int, np.ndarray] = {}
        if dyn_state is not None:
            lam_first = lam_first_trial()
            dyn_state.lam_ref[:] = lam_first
            dyn_state.lam_prev[:] = lam_first
            if mem is not None:
                mem.start_trials(dyn_state, mem.group[dyn_pix], dt, refr, threads, dyn_bg, lam_first, model,
                                 progress)
        stat_mem = np.full(stat_pix.size, math.nan) if mem is not None else None  # stored states, drawn at first
        dyn_e_on, dyn_e_off = eps_on[dyn_pix], eps_off[dyn_pix]
        dyn_thr = np.stack([c_on[dyn_pix], c_off[dyn_pix], dyn_e_on, dyn_e_off])
        runs = _RunProbabilities(params, dyn_e_on, dyn_e_off, None if bg is None else select_background(bg, dyn_pix))
        bar = _time_bar(duration_us, progress)
        for w in range(n_windows):
            j_a, j_b = w * per_window, min((w + 1) * per_window, n_trials)
            w_lo = 0 if j_a == 0 else int(math.floor(j_a * dt))
            w_hi = duration_us if j_b == n_trials else int(math.floor(j_b * dt))
            parts = []
            if stat_state is not None:
                expected = nu * (j_b - j_a) * dt * 1e-6
                w_end = min(j_b * dt, float(duration_us))
                if mem is not None:
                    parts += memory_step(stat_state, stat_mem, width, mem.group[stat_pix], mem.tables, dt, float(refr),
                                         0.0, float(w_end), math.inf, np.int64(t0_us), threads, expected, mem.timer)
                else:
                    parts += renewal_step(stat_state, width, log1m_p, q_on, dt, refr, 0, w_end, math.inf,
                                          t0_us, threads, expected=expected, timer=stat_timer)
            if dyn_state is not None:
                idx = frame_indices(j_a, j_b)
                for i in list(cache):
                    if i not in idx:
                        del cache[i]
                for i in idx:
                    if int(i) not in cache:
                        cache[int(i)] = lam_of(int(i))
                stack = np.stack([cache[int(i)] for i in idx])
                f_us = np.ascontiguousarray(frame_us[idx]) if frames.n > 1 else np.zeros(1)
                run_p = None  # the trial kernel's probabilities of a video's runs
                if fast_static and frames.n == 1:  # a still scene: each pixel's one light, vectorised, filled once
                    _fill_static_cache(dyn_state, stack, params, dyn_e_on, dyn_e_off,
                                       None if bg is None else select_background(bg, dyn_pix))
                elif fast_static:  # a video: per pair of frames, the same bits however windows cut them
                    run_p = runs.window(idx, segments(j_a, j_b), stack, dyn_pix)
                parts += trial_step(dyn_state, width, stack, f_us, j_a, j_b, dyn_thr, dyn_bg, model, duration_us,
                                    t0_us, threads, fast_static, run_p)
            yield sorted_window([p[:4] for p in parts], t0_us + w_lo, t0_us + w_hi, labels=labels,
                                state=stat_state if stat_state is not None else dyn_state)
            if bar is not None:
                bar.update(w_hi - w_lo)
        if bar is not None:
            bar.close()

    return EventWindows(gen(), expected_events=expected_events, t_start_us=t0_us, duration_us=duration_us,
                        noise_only=True)


# --------------------------------------------------------------------------------------
# counts only
# --------------------------------------------------------------------------------------
DISTRIBUTIONS = ("exact", "poisson", "negative-binomial")
#: Most events the exact count sampler draws (about 5-10 ns each on 2 cores: hours beyond) ...
MAX_EXACT_COUNT_EVENTS = 1e12
#: ... in windows of about this many (each one call of the kernel, which Ctrl-C cannot stop midway).
EXACT_COUNT_WINDOW_EVENTS = 2e8
#: Largest mean count the Poisson and gamma-Poisson draws take (NumPy's Poisson sampler stops near 9.2e18).
MAX_COUNT_MEAN = 1e18


def _check_count_means(mean) -> None:
    top = float(np.max(mean)) if np.size(mean) else 0.0
    if top > MAX_COUNT_MEAN:
        raise ParameterError(f"a pixel's expected count is {top:.3g}, beyond the {MAX_COUNT_MEAN:.0e} the count "
                             f"samplers take; use a shorter duration_s")


def sample_counts(
    lux,
    params: NoiseParams,
    duration_s: float,
    rng=None,
    *,
    distribution: str = "exact",
    nb_shape=None,
    thresholds=None,
    background=None,
    threads: int | None = None,
) -> np.ndarray:
    """Noise-event counts ``(2, H, W)`` ``[ON, OFF]`` of a static scene over ``duration_s``.

    Parameters
    ----------
    lux : array_like, shape (H, W)
        Illuminance at the sensor in lux (finite, ``>= 0``).
    params : NoiseParams
        Model parameters.
    duration_s : float
        Length of the recording in seconds (``> 0``), as in :func:`simulate_events`.
    rng : numpy.random.Generator, int or None
        Randomness, as in :func:`simulate_events`.
    distribution : {"exact", "poisson", "negative-binomial"}
        ``"exact"`` (default): the count distribution of the event process itself (trials
        with dead time; counts equal :func:`count_events` of :func:`simulate_events` in
        distribution), sampled in O(events) without storing events. ``"poisson"``: Poisson
        with the expected count (the paper's synthetic data). ``"negative-binomial"``:
        gamma-Poisson with the expected count as mean and shape ``nb_shape`` (the paper's
        over-dispersed variant; variance ``mu + mu^2 / r``).
    nb_shape : float or array_like, optional
        Shape ``r > 0`` for ``"negative-binomial"``, broadcastable to ``(2, H, W)``; required there and
        refused with the other distributions. ``inf`` (where :func:`evnoise.calibration.nb_shape` finds no
        over-dispersion) is the Poisson limit.
    thresholds : array_like, optional
        Per-pixel thresholds ``(2, H, W)``, as in :func:`simulate_events`.
    background : array_like, optional
        Per-pixel background maps ``(2, H, W)``, as in :func:`simulate_events`.
    threads : int, optional
        Worker threads (default ``NUMBA_NUM_THREADS`` or the CPU count).

    Returns
    -------
    numpy.ndarray
        int64 array of shape ``(2, H, W)``.
    """
    lux = check_lux(lux)
    duration_us = duration_to_us(duration_s)
    if distribution not in DISTRIBUTIONS:
        raise ParameterError(f"distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
    if distribution == "negative-binomial":
        if nb_shape is None:
            raise ParameterError("distribution='negative-binomial' needs nb_shape (r > 0)")
        r = np.asarray(nb_shape, dtype=np.float64)
        if not (~np.isnan(r) & (r > 0)).all():  # inf: the Poisson limit, as calibration.nb_shape gives it
            raise ParameterError(f"nb_shape must be > 0 (inf for Poisson), got {nb_shape!r}")
        try:
            r = np.broadcast_to(r, (2, *lux.shape))
        except ValueError:
            raise ParameterError(f"nb_shape does not broadcast to (2, H, W) = {(2, *lux.shape)}") from None
    elif nb_shape is not None:
        raise ParameterError("nb_shape is only used with distribution='negative-binomial'")
    threads = resolve_threads(threads)
    # the exact sampler draws the kernel key after the maps; the others draw counts from the generator
    run = run_setup(lux.shape, params, rng, thresholds=thresholds, background=background,
                    draw_key=distribution == "exact")
    params, gen, key, (eps_on, eps_off), bg = run.params, run.gen, run.key, run.thresholds, run.background
    if memory_on(params):
        return _memory_counts(lux, params, key, duration_us, threads, distribution, gen, r if
                              distribution == "negative-binomial" else None, bg, (eps_on, eps_off), thresholds)
    lam = params.photons_per_trial(lux).ravel()
    if distribution == "exact":
        from ._bracket import applies, bracketed_counts

        if applies(lam, params, (eps_on, eps_off), bg):  # per-pixel thresholds: counts decided by brackets
            found = bracketed_counts(lam, params, (eps_on, eps_off), key, duration_us, lux.shape[1], threads)
            if found is not None:
                return np.stack(found[:2]).reshape(2, *lux.shape)
        log1m_p, q_on, timer, nu = static_inputs(lam, params, eps_on, eps_off, bg)
        expected = float(nu.sum()) * duration_us * 1e-6
        if expected > MAX_EXACT_COUNT_EVENTS:
            raise ParameterError(f"distribution='exact' draws every event, and this scene expects {expected:.3g} "
                                 f"(more than {MAX_EXACT_COUNT_EVENTS:.0e}: hours of work); use "
                                 f"distribution='poisson' or a shorter duration_s")
        state = PixelState(np.arange(lux.size), key, threads)
        on = np.zeros(lux.size, dtype=np.int64)
        off = np.zeros(lux.size, dtype=np.int64)
        # in windows of a bounded number of events: Ctrl-C stops the run between two (the kernel's stream goes on
        # from one window to the next: the counts of one window, bit for bit)
        n_windows = max(1, math.ceil(expected / EXACT_COUNT_WINDOW_EVENTS))
        for w in range(1, n_windows + 1):
            w_end = duration_us if w == n_windows else duration_us * w // n_windows
            parts = renewal_step(state, lux.shape[1], log1m_p, q_on, params.trial_us, params.refractory_us, 0,
                                  float(w_end), math.inf, 0, threads, store=False, timer=timer)
            on += np.concatenate([p[4] for p in parts])
            off += np.concatenate([p[5] for p in parts])
        return np.stack([on, off]).reshape(2, *lux.shape)
    from .rates import pixel_rates  # the one home of the rate formula (dead time, background)

    mean = np.stack(pixel_rates(lam, params, (eps_on, eps_off), bg)).reshape(2, *lux.shape) * (duration_us * 1e-6)
    _check_count_means(mean)
    if distribution == "poisson":
        return gen.poisson(mean).astype(np.int64)
    return _gamma_poisson(gen, mean, r)


def _gamma_poisson(gen, mean, r):
    """Negative-binomial counts of mean ``mean`` and shape ``r`` (gamma-Poisson); ``r = inf`` is the Poisson
    limit (where a placeholder shape keeps the gamma draw finite)."""
    limit = np.isinf(r)
    shape = np.where(limit, 1.0, r)
    rate = gen.gamma(shape, mean / shape)
    return gen.poisson(np.where(limit, mean, rate)).astype(np.int64)


def _memory_counts(lux, params, key, duration_us, threads, distribution, gen, nb_shape, bg=None, eps=None,
                   given_thresholds=None):
    """:func:`sample_counts` with reset memory. ``"exact"``: the counts of the reset-memory tier's own events
    (the stream :func:`simulate_events` makes with the same seed, counted window by window: memory stays that
    of one window; the trial tier's where the chains are too many for tables); ``"poisson"`` /
    ``"negative-binomial"``: about the stationary rate of :func:`~evnoise.terms.memory.memory_statistics` (the memory
    model's closed form, the nominal pixel's: not with a background or thresholds that differ between pixels)."""
    height, width = lux.shape
    if distribution == "exact":
        counts = np.zeros(2 * lux.size, dtype=np.int64)
        for window in _still_memory_windows(lux, params, key, 0, duration_us, threads, False, None, bg, eps):
            cell = window["y"].astype(np.int64) * width + window["x"]
            counts += np.bincount(np.where(window["p"] == 1, cell, lux.size + cell), minlength=2 * lux.size)
        return counts.reshape(2, height, width)
    if bg is not None or params.eps_sigma > 0 or given_thresholds is not None:
        raise ParameterError(f"distribution={distribution!r} with reset_memory > 0 is known for the nominal pixel "
                             f"only, not with a background or thresholds that differ between pixels (hot pixels, "
                             f"leak_sigma > 0, eps_sigma > 0, given maps); use distribution='exact'")
    from .terms.memory import memory_statistics

    mean = memory_statistics(lux, params).rate_hz * (duration_us * 1e-6)
    _check_count_means(mean)
    if distribution == "poisson":
        return gen.poisson(mean).astype(np.int64)
    return _gamma_poisson(gen, mean, nb_shape)


# --------------------------------------------------------------------------------------
# streaming interface for other simulators
# --------------------------------------------------------------------------------------


from .stream import NoiseStream  # noqa: E402  (public here too; it uses the engine, not this module)
