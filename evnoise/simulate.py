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
the trial tier for the others. Randomness: each pixel has its own stream (xoshiro256++ keyed
by the caller's generator and the pixel index), so the output does not depend on the number
of threads, the chunking of pixels, or the windows in which time is generated.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Iterator

import numpy as np

from ._checks import (
    as_generator,
    check_lux,
    check_params,
    check_thresholds,
    duration_to_us,
)
from .errors import InputError, ParameterError
from .events import EVENT_DTYPE, empty_events
from .params import NoiseParams
from .rates import draw_thresholds, trial_probabilities

__all__ = [
    "simulate_events",
    "iter_events",
    "simulate_video",
    "iter_video",
    "sample_counts",
    "NoiseStream",
]

CHUNK_PIXELS = 1 << 14
TARGET_EVENTS_PER_WINDOW = 1_000_000
TARGET_PIXEL_TRIALS_PER_WINDOW = 40_000_000
MAX_WINDOW_US = 1 << 22  # bounds the counting sort's histogram
# Trial tier: pixels static within a window (lam = lam_ref) jump between events with geometric
# gaps (O(events)); False keeps the per-trial reference algorithm (tests compare the two).
TRIAL_FAST_STATIC = True
METHODS = ("auto", "renewal", "trials")


def default_threads() -> int:
    """Threads used by the simulators: ``NUMBA_NUM_THREADS`` if set, else the CPU count."""
    env = os.environ.get("NUMBA_NUM_THREADS")
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            pass
    return max(1, os.cpu_count() or 1)


def _chunks(n: int):
    return [(lo, min(lo + CHUNK_PIXELS, n)) for lo in range(0, n, CHUNK_PIXELS)]


def _map_chunks(fn, n: int, threads: int):
    """``fn(lo, hi)`` for every fixed-size chunk, in chunk order (threads only change speed)."""
    chunks = _chunks(n)
    if threads <= 1 or len(chunks) <= 1:
        return [fn(lo, hi) for lo, hi in chunks]
    with ThreadPoolExecutor(max_workers=threads) as pool:
        return list(pool.map(lambda c: fn(*c), chunks))


def _resolve_thresholds(shape, params: NoiseParams, gen, thresholds):
    """Per-pixel ``(eps_on, eps_off)`` flat arrays (drawn when ``eps_sigma > 0``)."""
    n = int(np.prod(shape))
    if thresholds is not None:
        thr = check_thresholds(thresholds, shape)
    elif params.eps_sigma > 0:
        thr = draw_thresholds(shape, params, gen)
    else:
        return np.full(n, params.eps_pos), np.full(n, params.eps_neg)
    return np.ascontiguousarray(thr[0].ravel()), np.ascontiguousarray(thr[1].ravel())


def _resolve_background(shape, params: NoiseParams, gen, background):
    """Per-pixel ``(scale, hot)`` flat arrays of the background, or None when it needs none.

    Drawn (after the thresholds) when ``leak_sigma`` or hot pixels are on and no maps are given;
    None when every pixel has the nominal background (or there is none).
    """
    from .background import check_background, draw_background

    if background is not None:
        arr = check_background(background, shape)
    elif params.has_background and (params.leak_sigma > 0 or params.hot_pixel_fraction > 0):
        arr = draw_background(shape, params, gen)
    else:
        return None
    return np.ascontiguousarray(arr[0].ravel()), np.ascontiguousarray(arr[1].ravel())


def _background_coefficients(params: NoiseParams, bg, sel) -> np.ndarray:
    """``(4, n)`` ``[l0_on, l1_on, l0_off, l1_off]`` of the trial kernel for pixels ``sel`` (``(4, 0)`` without
    background)."""
    if not params.has_background:
        return np.zeros((4, 0))
    if bg is None:
        scale, hot = np.ones(sel.size), np.zeros(sel.size)
    else:
        scale, hot = bg[0][sel], bg[1][sel]
    q = params.hot_pixel_on_fraction
    out = np.stack([scale * params.leak_on_hz + hot * q, scale * params.leak_on_hz_per_lux,
                    scale * params.leak_off_hz + hot * (1.0 - q), scale * params.leak_off_hz_per_lux])
    return np.ascontiguousarray(out)


def _select(bg, sel):
    return None if bg is None else (bg[0][sel], bg[1][sel])


class _PixelState:
    """Per-pixel simulation state of a set of pixels (flat indices ``pix``).

    The float state is one array ``fstate`` ``(n, N_STATE)``, a row per pixel (the columns of
    :mod:`evnoise._kernels.simulate`); the attributes ``last_trial``, ``lam_ref``, ... are views of
    its columns, for the vectorised code here.
    """

    def __init__(self, pix: np.ndarray, key: np.ndarray, threads: int):
        from ._kernels import simulate as k

        self.pix = np.ascontiguousarray(pix, dtype=np.int64)
        n = self.pix.size
        self.states = np.empty((n, 4), dtype=np.uint64)
        # each pixel's stream is keyed by its flat index, not by its position in this set
        _map_chunks(lambda lo, hi: k.seed_streams(key, self.pix[lo:hi], self.states[lo:hi]), n, threads)
        self.fstate = np.zeros((n, k.N_STATE))
        initial = {k.LAST_TRIAL: -1.0, k.LAST_TAU: -math.inf, k.PEND_TRIAL: math.nan, k.PEND_TAU: math.nan,
                   k.PEND_ON: math.nan, k.CACHE_LAM: math.nan, k.BG_NEXT: math.nan}
        for col, value in initial.items():
            self.fstate[:, col] = value
        self.last_trial = self.fstate[:, k.LAST_TRIAL]
        self.last_tau = self.fstate[:, k.LAST_TAU]
        self.pend_trial = self.fstate[:, k.PEND_TRIAL]
        self.pend_tau = self.fstate[:, k.PEND_TAU]
        self.pend_on = self.fstate[:, k.PEND_ON]
        self.lam_ref = self.fstate[:, k.LAM_REF]
        self.lam_prev = self.fstate[:, k.LAM_PREV]
        # trial tier: closed-form probabilities of pixels that are static within a window
        self.cache_lam = self.fstate[:, k.CACHE_LAM]
        self.cache_log1m_p = self.fstate[:, k.CACHE_LOG1M_P]
        self.cache_q_on = self.fstate[:, k.CACHE_Q_ON]
        # regular background (leak_regularity > 0): trial of the next background arrival, its intensity (events/s)
        self.bg_next = self.fstate[:, k.BG_NEXT]
        self.bg_l = self.fstate[:, k.BG_L]

    def rescale_timers(self, l_all: np.ndarray, j_now: float):
        """Pending background arrivals at or after trial ``j_now`` move to a new intensity ``l_all``.

        The remaining interval scales with ``old / new`` intensity (a leak drifting at a new speed covers
        the rest of its way in proportionally more or less time): exact for a periodic timer, the natural
        continuation otherwise. Pixels whose intensity is unchanged are left alone (bit for bit).
        """
        pend = np.isfinite(self.bg_next) & (self.bg_next >= j_now) & (l_all != self.bg_l) & (self.bg_l > 0)
        if pend.any():
            ratio = np.where(l_all[pend] > 0, self.bg_l[pend] / np.where(l_all[pend] > 0, l_all[pend], 1.0), np.inf)
            with np.errstate(invalid="ignore"):
                self.bg_next[pend] = j_now + np.floor((self.bg_next[pend] - j_now) * ratio)
            # a pending event in a trial not yet begun is redrawn (the photon gap is memoryless; the
            # background arrival comes from the moved timer); one in a trial already begun stays
            idx = np.flatnonzero(pend)
            redraw = idx[self.pend_trial[idx] >= j_now]
            self.pend_tau[redraw] = math.nan
        self.bg_l[:] = l_all


class _Collector:
    """One output array that windows are sorted straight into (no final concatenation).

    ``capacity`` is the expected number of events plus a margin of many standard deviations;
    should a run still produce more, the array grows (a copy, correct but no longer in place).
    """

    def __init__(self, capacity: int):
        self.buf = np.empty(max(0, int(capacity)), dtype=EVENT_DTYPE)
        self.n = 0

    def reserve(self, n: int) -> np.ndarray:
        """The next ``n`` slots of the output (a contiguous view)."""
        if self.n + n > self.buf.size:
            grown = np.empty(max(self.n + n, int(1.25 * self.buf.size) + 1024), dtype=EVENT_DTYPE)
            grown[:self.n] = self.buf[:self.n]
            self.buf = grown
        view = self.buf[self.n:self.n + n]
        self.n += n
        return view

    def result(self) -> np.ndarray:
        buf, self.buf = self.buf, None
        try:
            buf.resize((self.n,), refcheck=True)  # gives back the unused margin, in place
        except ValueError:  # a view of it is still referenced somewhere: return a view instead
            return buf[:self.n]
        return buf


def _sorted_window(parts, t_lo: int, t_hi: int, labels: bool = False, sink: _Collector | None = None):
    """Concatenate ``(t, x, y, p)`` parts (in a fixed order) into one event array sorted stably by time.

    With ``labels`` also returns a bool array, True for signal events. With ``sink`` the window
    is sorted straight into the sink's next slots (and that view is returned).
    """
    from ._kernels.simulate import sort_into_events

    parts = [p for p in parts if p[0].size]
    if not parts:
        return (empty_events(0), np.zeros(0, dtype=bool)) if labels else empty_events(0)
    cols = [np.concatenate([p[i] for p in parts]) if len(parts) > 1 else parts[0][i] for i in range(4)]
    del parts
    out = np.empty(cols[0].size, dtype=EVENT_DTYPE) if sink is None else sink.reserve(cols[0].size)
    lab = np.empty(cols[0].size if labels else 0, dtype=np.uint8)
    sort_into_events(*cols, np.int64(t_lo), np.int64(t_hi), out, lab)
    return (out, lab.astype(bool)) if labels else out


def _renewal_inputs(p_on: np.ndarray, p_off: np.ndarray):
    p = p_on + p_off
    with np.errstate(divide="ignore", invalid="ignore"):
        q_on = np.where(p > 0, p_on / np.where(p > 0, p, 1.0), 0.5)
    return np.log1p(-np.minimum(p, 1.0)), q_on


def _timer_arrays(lam, params: NoiseParams, bg):
    """``(3, n)`` ``[d, log1p(-a2), ON share]`` of the regular background timer (:mod:`evnoise._kernels.background`)."""
    from .background import _intensities, lux_of_photons, timer_shape

    scale, hot = (None, None) if bg is None else bg
    l_on, l_off = _intensities(lux_of_photons(lam, params), params, scale, hot)
    l_on = np.broadcast_to(l_on, np.shape(lam))
    l_all = l_on + np.broadcast_to(l_off, np.shape(lam))
    d, log1m_a2 = timer_shape(l_all, params.trial_us * 1e-6, params.leak_regularity)
    has = l_all > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(has, l_on / np.where(has, l_all, 1.0), 0.0)
    return np.ascontiguousarray(np.stack([d, log1m_a2, share]))


def _static_inputs(lam, params: NoiseParams, eps_on, eps_off, bg):
    """Renewal-kernel inputs of static pixels at ``lam``: ``(log1m_p, q_on, timer or None, total rate)``."""
    if params.regular_background:
        from .rates import pixel_rates

        p_on, p_off = trial_probabilities(lam, params, (eps_on, eps_off), photon_only=True)
        log1m_p, q_on = _renewal_inputs(p_on, p_off)
        nu_on, nu_off = pixel_rates(lam, params, (eps_on, eps_off), bg)
        return log1m_p, q_on, _timer_arrays(lam, params, bg), nu_on + nu_off
    p_on, p_off = trial_probabilities(lam, params, (eps_on, eps_off), background=bg)
    log1m_p, q_on = _renewal_inputs(p_on, p_off)
    nu = params.trial_rate_hz * (p_on + p_off)
    nu = nu / (1.0 + nu * params.refractory_us * 1e-6)
    return log1m_p, q_on, None, nu


def _renewal_step(state: _PixelState, width, log1m_p, q_on, dt, refr_us, j_min, w_end, discard_from,
                  t0_us, threads, store=True, expected=None, timer=None):
    """Run the renewal kernel over all pixels of ``state`` up to ``w_end``; returns chunk parts."""
    from ._kernels.simulate import renewal_window

    no_timer = np.zeros((3, 0))

    def run(lo, hi):
        cap = 0
        if store:
            cap = int(1.2 * expected[lo:hi].sum() + 64) if expected is not None else 1024
        return renewal_window(
            width, state.pix[lo:hi], log1m_p[lo:hi], q_on[lo:hi], no_timer if timer is None else timer[:, lo:hi],
            state.states[lo:hi], state.fstate[lo:hi], dt, float(refr_us), float(j_min), float(w_end),
            float(discard_from), np.int64(t0_us), cap, store,
        )

    return _map_chunks(run, state.pix.size, threads)


def _progress(total, enabled, desc, unit="s"):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit, leave=False,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} " + unit + " [{elapsed}<{remaining}]")


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

    Same parameters as :func:`simulate_events`; the concatenation of the yielded arrays is
    the full, sorted event stream, and memory stays bounded by one window (a few million
    events). Validation happens at the call, before the first window.
    """
    return _iter_events(lux, params, duration_s, rng, method, thresholds, t_start_us, threads, progress,
                        background=background)


def _iter_events(lux, params, duration_s, rng, method, thresholds, t_start_us, threads, progress, sink=None,
                 background=None):
    """:func:`iter_events`; with ``sink`` (static scenes) each window is sorted straight into it."""
    params = check_params(params)
    lux = check_lux(lux)
    duration_us = duration_to_us(duration_s)
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    t_start_us = _check_t_start(t_start_us)
    threads = default_threads() if threads is None else max(1, int(threads))
    gen = as_generator(rng)
    eps_on, eps_off = _resolve_thresholds(lux.shape, params, gen, thresholds)
    bg = _resolve_background(lux.shape, params, gen, background)
    key = _key(gen)
    if method == "trials":
        frames = _FrameSource([lux], name="lux")
        return _iter_dynamic(frames, np.array([0.0, float(duration_us)]), params, key, eps_on, eps_off,
                             np.zeros(lux.size, dtype=bool), t_start_us, duration_us, threads, progress, bg=bg)
    return _iter_static(lux, params, key, eps_on, eps_off, t_start_us, duration_us, threads, progress, sink, bg)


def _check_t_start(t_start_us) -> int:
    try:
        t = int(t_start_us)
    except (TypeError, ValueError):
        raise ParameterError(f"t_start_us must be an integer number of microseconds, got {t_start_us!r}") from None
    if t != t_start_us:
        raise ParameterError(f"t_start_us must be an integer number of microseconds, got {t_start_us!r}")
    return t


def _key(gen):
    from ._checks import kernel_key

    return kernel_key(gen)  # the one home of seed -> kernel key (issue 13)


def _iter_static(lux, params, key, eps_on, eps_off, t_start_us, duration_us, threads, progress, sink=None,
                 bg=None):
    height, width = lux.shape
    lam = params.photons_per_trial(lux).ravel()
    log1m_p, q_on, timer, nu = _static_inputs(lam, params, eps_on, eps_off, bg)
    dt = params.trial_us
    refr = params.refractory_us
    del lam  # not needed while the windows run: keep the per-pixel memory small
    total = float(nu.sum()) * duration_us * 1e-6
    n_win = max(1, math.ceil(total / TARGET_EVENTS_PER_WINDOW), math.ceil(duration_us / MAX_WINDOW_US))
    ends = [duration_us * (k + 1) // n_win for k in range(n_win)]
    if sink is not None:
        # counts are under-dispersed against Poisson (renewal with dead time): 8 sigma is ample
        sink.__init__(int(math.ceil(total + 8.0 * math.sqrt(total) + 4096)))

    def gen():
        state = _PixelState(np.arange(lux.size), key, threads)
        bar = _progress(duration_us * 1e-6, progress, "simulate")
        t_prev = 0
        for w_end in ends:
            expected = nu * (w_end - t_prev) * 1e-6
            parts = _renewal_step(state, width, log1m_p, q_on, dt, refr, 0, w_end, math.inf,
                                  t_start_us, threads, expected=expected, timer=timer)
            del expected
            window = _sorted_window(parts, t_start_us + t_prev, t_start_us + w_end, sink=sink)
            del parts  # not held while the caller has the window
            yield window
            del window
            if bar is not None:
                bar.update((w_end - t_prev) * 1e-6)
            t_prev = w_end
        if bar is not None:
            bar.close()

    return gen()


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
        ``"trials"`` runs the full per-trial model (statistically identical, slower).
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

    Returns
    -------
    numpy.ndarray
        Events (:data:`evnoise.EVENT_DTYPE`), sorted by time.
    """
    # static scenes: one output array, each window sorted straight into it (peak memory about the
    # output plus one window, instead of twice the output for a final concatenation)
    sink = _Collector(0)
    parts = []
    for window in _iter_events(lux, params, duration_s, rng, method, thresholds, t_start_us, threads, progress,
                               sink, background):
        if method == "trials":
            parts.append(window)
    window = None  # the last window is a view of the sink's array: let it shrink in place
    if method == "trials":
        return np.concatenate(parts) if parts else empty_events(0)
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
    """
    params = check_params(params)
    frames = _FrameSource(frames_lux)
    ts = _check_timestamps(timestamps_s, frames.n)
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    threads = default_threads() if threads is None else max(1, int(threads))
    shape = frames.shape
    static = np.ones(shape, dtype=bool)
    first = frames.get(0)
    for i in range(1, frames.n):
        static &= frames.get(i) == first
    if method == "trials":
        static[:] = False
    elif method == "renewal" and not static.all():
        raise ParameterError("method='renewal' needs a static scene, but some pixels change between frames")
    gen = as_generator(rng)
    eps_on, eps_off = _resolve_thresholds(shape, params, gen, thresholds)
    bg = _resolve_background(shape, params, gen, background)
    key = _key(gen)
    t0_us = int(round(ts[0] * 1e6))
    frame_us = (ts - ts[0]) * 1e6
    duration_us = int(round(frame_us[-1]))
    if duration_us < 1:
        raise InputError("the video is shorter than one microsecond")
    return _iter_dynamic(frames, frame_us, params, key, eps_on, eps_off, static.ravel(), t0_us,
                         duration_us, threads, progress, labels=return_labels, bg=bg)


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
    params, rng, thresholds, background, threads
        As in :func:`simulate_events`.
    method : {"auto", "renewal", "trials"}
        ``"auto"``: renewal tier for pixels that never change, trial tier for the rest;
        ``"trials"``: trial tier everywhere; ``"renewal"``: only valid if nothing changes.
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
    parts = list(iter_video(frames_lux, timestamps_s, params, rng, method, thresholds=thresholds,
                            background=background, threads=threads, progress=progress, return_labels=return_labels))
    if return_labels:
        if not parts:
            return empty_events(0), np.zeros(0, dtype=bool)
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    return np.concatenate(parts) if parts else empty_events(0)


def _fill_static_cache(state: _PixelState, lams: np.ndarray, params: NoiseParams, eps_on, eps_off, bg=None):
    """Closed-form probabilities of the pixels the trial tier will jump through in this window.

    Those whose ``lam`` is the same in every frame ``lams`` (F, n) of the window and equals
    their ``lam_ref`` and ``lam_prev`` (see :func:`evnoise._kernels.simulate.trial_window`),
    and whose cache does not already hold that ``lam``. Vectorised here (the grouped closed
    form) so that the kernel does not evaluate the exact sum pixel by pixel.
    """
    lam0 = lams[0]
    need = (lam0 == state.lam_ref) & (lam0 == state.lam_prev) & ~(state.cache_lam == lam0)
    for row in lams[1:]:
        need &= row == lam0
    sel = np.flatnonzero(need)
    if sel.size == 0:
        return
    p_on, p_off = trial_probabilities(lam0[sel], params, (eps_on[sel], eps_off[sel]), background=_select(bg, sel))
    p_all = p_on + p_off
    with np.errstate(divide="ignore", invalid="ignore"):
        state.cache_log1m_p[sel] = np.where(p_all < 1.0, np.log1p(-np.minimum(p_all, 1.0)), -np.inf)
        state.cache_q_on[sel] = np.where(p_all > 0.0, p_on / np.where(p_all > 0.0, p_all, 1.0), 0.0)
    state.cache_lam[sel] = lam0[sel]


def _iter_dynamic(frames, frame_us, params, key, eps_on, eps_off, static, t0_us, duration_us, threads,
                  progress, labels=False, bg=None):
    """Generator over windows of a changing scene (renewal for ``static`` pixels, trials for the rest)."""
    from ._kernels.simulate import trial_window

    width = frames.shape[1]
    dt = params.trial_us
    refr = params.refractory_us
    b = params.bias_pr
    n_trials = math.ceil(duration_us / dt - 1e-12)
    stat_pix = np.flatnonzero(static)
    dyn_pix = np.flatnonzero(~static)
    c_on = np.expm1(eps_on)
    c_off = np.expm1(eps_off)

    def lam_of(i):
        return params.photons_per_trial(frames.get(i)).ravel()

    # static pixels: closed-form probabilities once
    stat_timer = None
    if stat_pix.size:
        lam0 = lam_of(0)[stat_pix]
        log1m_p, q_on, stat_timer, nu = _static_inputs(lam0, params, eps_on[stat_pix], eps_off[stat_pix],
                                                       _select(bg, stat_pix))
    dyn_bg = _background_coefficients(params, bg, dyn_pix)
    from .background import pr_alpha_per_photon

    pr_alpha = pr_alpha_per_photon(params)
    regularity = params.leak_regularity if params.regular_background else 0.0
    fast_static = TRIAL_FAST_STATIC and regularity == 0.0  # the regular timer is not memoryless
    model = (float(b), float(dt), float(refr), 1.0 / params.photons_per_lux, float(params.dark_lux), float(pr_alpha),
             float(regularity))
    per_window = max(1, TARGET_PIXEL_TRIALS_PER_WINDOW // max(1, dyn_pix.size))
    per_window = min(per_window, max(1, int(MAX_WINDOW_US // dt)))
    if stat_pix.size:
        stat_rate = float(nu.sum())
        if stat_rate > 0:
            per_window = min(per_window, max(1, int(TARGET_EVENTS_PER_WINDOW / (stat_rate * dt * 1e-6))))
    trial_edges = list(range(0, n_trials, per_window)) + [n_trials]

    def frame_indices(j_a, j_b):
        """Indices of the frames bracketing the centres of trials j_a .. j_b - 1."""
        if frames.n == 1:
            return np.array([0])
        centres = (np.arange(j_a, j_b) + 0.5) * dt
        seg = np.clip(np.searchsorted(frame_us, centres, side="right") - 1, 0, frames.n - 2)
        return np.unique(np.concatenate([seg, seg + 1]))

    def gen():
        stat_state = _PixelState(stat_pix, key, threads) if stat_pix.size else None
        dyn_state = _PixelState(dyn_pix, key, threads) if dyn_pix.size else None
        cache: dict[int, np.ndarray] = {}
        if dyn_state is not None:
            idx = frame_indices(0, 1)
            lams = np.stack([lam_of(int(i))[dyn_pix] for i in idx])
            if idx.size == 1:
                lam_first = lams[0]
            else:
                a = min(max((0.5 * dt - frame_us[idx[0]]) / (frame_us[idx[1]] - frame_us[idx[0]]), 0.0), 1.0)
                lam_first = lams[0] + a * (lams[1] - lams[0])
            dyn_state.lam_ref[:] = lam_first
            dyn_state.lam_prev[:] = lam_first
        dyn_e_on, dyn_e_off = eps_on[dyn_pix], eps_off[dyn_pix]
        dyn_thr = np.stack([c_on[dyn_pix], c_off[dyn_pix], dyn_e_on, dyn_e_off])
        bar = _progress(duration_us * 1e-6, progress, "simulate")
        for j_a, j_b in zip(trial_edges[:-1], trial_edges[1:]):
            w_lo = 0 if j_a == 0 else int(math.floor(j_a * dt))
            w_hi = duration_us if j_b == n_trials else int(math.floor(j_b * dt))
            parts = []
            if stat_state is not None:
                expected = nu * (j_b - j_a) * dt * 1e-6
                w_end = min(j_b * dt, float(duration_us))
                parts += _renewal_step(stat_state, width, log1m_p, q_on, dt, refr, 0, w_end, math.inf,
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
                if fast_static:
                    _fill_static_cache(dyn_state, stack[:, dyn_pix], params, dyn_e_on, dyn_e_off,
                                       None if bg is None else _select(bg, dyn_pix))

                def run(lo, hi, stack=stack, f_us=f_us, j_a=j_a, j_b=j_b):
                    s = dyn_state
                    return trial_window(
                        width, s.pix[lo:hi], stack, f_us, j_a, j_b, dyn_thr[:, lo:hi], dyn_bg[:, lo:hi],
                        s.states[lo:hi], s.fstate[lo:hi], model, float(duration_us), np.int64(t0_us), 256,
                        fast_static,
                    )

                parts += _map_chunks(run, dyn_pix.size, threads)
            yield _sorted_window([p[:4] for p in parts], t0_us + w_lo, t0_us + w_hi, labels=labels)
            if bar is not None:
                bar.update((w_hi - w_lo) * 1e-6)
        if bar is not None:
            bar.close()

    return gen()


# --------------------------------------------------------------------------------------
# counts only
# --------------------------------------------------------------------------------------
DISTRIBUTIONS = ("exact", "poisson", "negative-binomial")


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
    lux, params, duration_s, rng, thresholds, background, threads
        As in :func:`simulate_events`.
    distribution : {"exact", "poisson", "negative-binomial"}
        ``"exact"`` (default): the count distribution of the event process itself (trials
        with dead time; counts equal :func:`count_events` of :func:`simulate_events` in
        distribution), sampled in O(events) without storing events. ``"poisson"``: Poisson
        with the expected count (the paper's synthetic data). ``"negative-binomial"``:
        gamma-Poisson with the expected count as mean and shape ``nb_shape`` (the paper's
        over-dispersed variant; variance ``mu + mu^2 / r``).
    nb_shape : float or array_like, optional
        Shape ``r > 0`` for ``"negative-binomial"``, broadcastable to ``(2, H, W)``.

    Returns
    -------
    numpy.ndarray
        int64 array of shape ``(2, H, W)``.
    """
    params = check_params(params)
    lux = check_lux(lux)
    duration_us = duration_to_us(duration_s)
    if distribution not in DISTRIBUTIONS:
        raise ParameterError(f"distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
    if distribution == "negative-binomial":
        if nb_shape is None:
            raise ParameterError("distribution='negative-binomial' needs nb_shape (r > 0)")
        r = np.asarray(nb_shape, dtype=np.float64)
        if not (np.isfinite(r).all() and (r > 0).all()):
            raise ParameterError(f"nb_shape must be finite and > 0, got {nb_shape!r}")
        try:
            r = np.broadcast_to(r, (2, *lux.shape))
        except ValueError:
            raise ParameterError(f"nb_shape does not broadcast to (2, H, W) = {(2, *lux.shape)}") from None
    elif nb_shape is not None:
        raise ParameterError("nb_shape is only used with distribution='negative-binomial'")
    threads = default_threads() if threads is None else max(1, int(threads))
    gen = as_generator(rng)
    eps_on, eps_off = _resolve_thresholds(lux.shape, params, gen, thresholds)
    bg = _resolve_background(lux.shape, params, gen, background)
    lam = params.photons_per_trial(lux).ravel()
    if distribution == "exact":
        key = _key(gen)
        log1m_p, q_on, timer, _ = _static_inputs(lam, params, eps_on, eps_off, bg)
        state = _PixelState(np.arange(lux.size), key, threads)
        parts = _renewal_step(state, lux.shape[1], log1m_p, q_on, params.trial_us, params.refractory_us, 0,
                              float(duration_us), math.inf, 0, threads, store=False, timer=timer)
        on = np.concatenate([p[4] for p in parts])
        off = np.concatenate([p[5] for p in parts])
        return np.stack([on, off]).reshape(2, *lux.shape)
    from .rates import pixel_rates  # the one home of the rate formula (dead time, background)

    mean = np.stack(pixel_rates(lam, params, (eps_on, eps_off), bg)).reshape(2, *lux.shape) * (duration_us * 1e-6)
    if distribution == "poisson":
        return gen.poisson(mean).astype(np.int64)
    rate = gen.gamma(r, mean / r)
    return gen.poisson(rate).astype(np.int64)


# --------------------------------------------------------------------------------------
# streaming interface for other simulators
# --------------------------------------------------------------------------------------
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
        self.params = check_params(params)
        self.threads = default_threads() if threads is None else max(1, int(threads))
        gen = as_generator(rng)
        self._eps_on, self._eps_off = _resolve_thresholds(self.shape, self.params, gen, thresholds)
        self._bg = _resolve_background(self.shape, self.params, gen, background)
        self._state = _PixelState(np.arange(self.shape[0] * self.shape[1]), _key(gen), self.threads)
        self._t0 = _check_t_start(t_start_us)
        self._t_rel = 0  # µs since t_start_us

    @property
    def t_us(self) -> int:
        """Current time of the stream (end of the last interval), microseconds."""
        return self._t0 + self._t_rel

    def advance(self, lux, t_end_us: int) -> np.ndarray:
        """Noise events with ``t_us <= t < t_end_us`` under illuminance ``lux`` (H, W), sorted by time."""
        lux = check_lux(lux)
        if lux.shape != self.shape:
            raise InputError(f"lux has shape {lux.shape}, but the stream was made for {self.shape}")
        t_end = _check_t_start(t_end_us) - self._t0
        if t_end < self._t_rel:
            raise ParameterError(f"t_end_us={t_end_us} is before the stream's current time {self.t_us}")
        if t_end == self._t_rel:
            return empty_events(0)
        p = self.params
        dt = p.trial_us
        lam = p.photons_per_trial(lux).ravel()
        log1m_p, q_on, timer, nu = _static_inputs(lam, p, self._eps_on, self._eps_off, self._bg)
        j_min = _first_trial_at_or_after(self._t_rel, dt)
        discard = _first_trial_at_or_after(t_end, dt)
        if timer is not None:
            from .background import _intensities, lux_of_photons

            scale, hot = (None, None) if self._bg is None else self._bg
            l_on, l_off = _intensities(lux_of_photons(lam, p), p, scale, hot)
            self._state.rescale_timers(np.broadcast_to(l_on + l_off, lam.shape), j_min)
        parts = _renewal_step(self._state, self.shape[1], log1m_p, q_on, dt, p.refractory_us, j_min,
                              float(t_end), discard, self._t0, self.threads,
                              expected=nu * (t_end - self._t_rel) * 1e-6, timer=timer)
        out = _sorted_window(parts, self._t0 + self._t_rel, self._t0 + t_end)
        self._t_rel = t_end
        return out


def _first_trial_at_or_after(t_us: float, dt: float) -> float:
    """Index of the first trial starting at or after ``t_us`` (``t_us >= 0``): the kernels' eligibility rule
    with no previous event and no refractory period (one home for the rounding of trial starts)."""
    from ._kernels.simulate import _first_eligible

    return float(_first_eligible(-1.0, float(t_us), 0.0, float(dt)))
