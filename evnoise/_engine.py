"""The simulators' engine: per-pixel state, chunked threads, window collection (internal).

Shared by :mod:`evnoise.simulate` (static and changing scenes, counts) and :mod:`evnoise.stream`
(:class:`~evnoise.stream.NoiseStream`): the per-pixel state the kernels of
:mod:`evnoise._kernels.simulate` advance, the fixed-size pixel chunks that threads share (chunking
never changes the output), the renewal tier's inputs and step, and the collection of each
window's events in time order. A run's per-pixel maps and key come from :mod:`evnoise._run`; what each
noise term feeds the kernels comes from :mod:`evnoise.terms`.
"""

from __future__ import annotations

import contextlib
import math
import weakref

import numpy as np

from . import model, terms
from ._pool import map_in_threads
from .errors import ParameterError
from .events import EVENT_DTYPE, empty_events
from .model import same_path_values
from .params import NoiseParams
from .rates import trial_probabilities

CHUNK_PIXELS = 1 << 14
#: event buffers of a chunk larger than this are not kept between windows (13 bytes per event: 3.4 MB per chunk,
#: ~190 MB at 1280x720; a static scene's window of 8 events per pixel needs ~131 k per chunk, 1.7 MB)
KEEP_EVENTS_PER_CHUNK = 1 << 18


def pixel_chunks(n: int):
    return [(lo, min(lo + CHUNK_PIXELS, n)) for lo in range(0, n, CHUNK_PIXELS)]


def map_chunks(fn, n: int, threads: int):
    """``fn(lo, hi)`` for every fixed-size chunk, in chunk order (threads only change speed)."""
    return map_in_threads(fn, pixel_chunks(n), threads)


def select_background(bg, sel):
    return None if bg is None else (bg[0][sel], bg[1][sel])


class PixelState:
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
        row = np.zeros(k.N_STATE)
        initial = {k.LAST_TRIAL: -1.0, k.LAST_TAU: -math.inf, k.PEND_TRIAL: math.nan, k.PEND_TAU: math.nan,
                   k.PEND_ON: math.nan, k.CACHE_LAM: math.nan, k.BG_NEXT: math.nan}
        for col, value in initial.items():
            row[col] = value
        self.fstate = np.empty((n, k.N_STATE))

        def init(lo, hi):
            # each pixel's stream is keyed by its flat index, not by its position in this set
            k.seed_streams(key, self.pix[lo:hi], self.states[lo:hi])
            # one pass over the chunk's rows (column by column is a strided pass each), in the chunk's thread:
            # the fresh pages of this ~100 bytes-per-pixel state are faulted in by both threads
            self.fstate[lo:hi] = row

        map_chunks(init, n, threads)
        self._row, self._threads = row, threads
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
        # each chunk's event buffers, reused window after window (fresh pages cost page faults per event);
        # what a window kernel returns are views of them, valid until the next window
        self._buffers: dict[int, tuple] = {}
        # or, inside shared(), each chunk's region of the window's columns (kept in _shared unless large)
        self._shared = None
        self._regions: dict[int, tuple] = {}
        self._window = None  # a weak reference to the columns of the window being made
        self._outgrown: dict[int, int] = {}  # what a chunk needed when it outgrew its region
        self._sort_keys = np.empty(0, dtype=np.uint64)  # the window sort's packed keys, reused (sort_keys)

    def restart(self, streams: np.ndarray) -> None:
        """Back to the state of a fresh :class:`PixelState` whose random streams are ``streams`` (a copy of
        ``states`` taken before a run): a second run on the same draws without seeding the streams again."""
        def reset(lo, hi):
            self.states[lo:hi] = streams[lo:hi]
            self.fstate[lo:hi] = self._row

        map_chunks(reset, self.pix.size, self._threads)

    @contextlib.contextmanager
    def shared(self, capacities):
        """For one window's kernels: each chunk's :meth:`buffers` returns its region of one set of event columns,
        with room for ``capacities[c]`` events (chunks in :func:`pixel_chunks` order), or for what the chunk needed
        when it outgrew its region (:meth:`keep`). The window's parts are then views of the same columns, which
        :func:`sorted_window` sorts where they are (no concatenation). The columns are kept for the next window
        unless large (as :meth:`keep`); the regions end with the block (the parts stay valid until the next window).
        """
        chunks = pixel_chunks(self.pix.size)
        caps = [max(int(cap), self._outgrown.get(lo, 0)) for (lo, _), cap in zip(chunks, capacities)]
        total = sum(caps)
        buf = self._shared
        if buf is None or buf[0].size < total:
            self._shared = buf = None
            buf = event_buffers(total)
        if total <= KEEP_EVENTS_PER_CHUNK * len(chunks):
            self._shared = buf
        self._window = weakref.ref(buf[0])
        off = 0
        for (lo, _), cap in zip(chunks, caps):
            self._regions[lo] = tuple(c[off:off + cap] for c in buf)
            off += cap
        del buf
        try:
            yield
        finally:
            self._regions = {}
            self._window = None

    def buffers(self, lo: int, capacity: int):
        """Event buffers of the chunk starting at pixel ``lo`` with room for at least ``capacity`` events (its region
        of the window's columns inside :meth:`shared`)."""
        out = self._regions.pop(lo, None)
        if out is not None and out[0].size >= capacity:
            return out
        out = self._buffers.get(lo)
        if out is None or out[0].size < capacity:
            out = event_buffers(capacity)
        return out

    def sort_keys(self, n: int) -> np.ndarray:
        """Room for the window sort's ``n`` packed keys (:func:`sorted_window`), reused window after window as the
        event columns are (a fresh array's pages cost a fault each, every window), unless large (as :meth:`keep`)."""
        keys = self._sort_keys
        if keys.size < n:
            keys = np.empty(n, dtype=np.uint64)
            self._sort_keys = keys if n <= KEEP_EVENTS_PER_CHUNK * len(pixel_chunks(self.pix.size)) else self._sort_keys
        return keys

    def keep(self, lo: int, out) -> None:
        """Keep ``out`` (perhaps grown) as the buffers of chunk ``lo``, unless it is large (one long window, e.g.
        a long ``NoiseStream.advance``, must not pin its memory for the life of the state). Inside :meth:`shared`
        a region stays where it is, and a chunk that outgrew its region gets a region of that size in later windows,
        unless that is large (its grown buffer is not kept)."""
        window = self._window() if self._window is not None else None
        if window is not None:
            if out[0].base is not window and out[0].size <= KEEP_EVENTS_PER_CHUNK:
                self._outgrown[lo] = out[0].size
            return
        if out[0].size <= KEEP_EVENTS_PER_CHUNK:
            self._buffers[lo] = out
        else:
            self._buffers.pop(lo, None)

    def rescale_timers(self, l_all: np.ndarray, j_now: float):
        """Pending background arrivals at or after trial ``j_now`` move to a new intensity ``l_all``.

        The remaining interval scales with ``old / new`` intensity (a leak drifting at a new speed covers
        the rest of its way in proportionally more or less time): exact for a periodic timer, the natural
        continuation otherwise. Pixels whose intensity is unchanged are left alone (bit for bit). A timer that
        had no intensity (its arrival at infinity) is drawn afresh when its pixel has one again, as the trial
        kernel does (before, such a pixel's background stayed silent until its next photon event).
        """
        # a timer that never fires (no intensity: arrival inf) is drawn afresh once its pixel has an intensity
        revive = (self.bg_next == math.inf) & (l_all > 0)
        if revive.any():
            self.bg_next[revive] = math.nan
            idx = np.flatnonzero(revive)
            self.pend_tau[idx[self.pend_trial[idx] >= j_now]] = math.nan
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


class Collector:
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


def sorted_window(parts, t_lo: int, t_hi: int, labels: bool = False, sink: Collector | None = None,
                  state: PixelState | None = None):
    """The events of ``(t, x, y, p)`` parts (in a fixed order) in one event array sorted stably by time.

    With ``labels`` also returns a bool array, True for signal events. With ``sink`` the window
    is sorted straight into the sink's next slots (and that view is returned). With ``state`` (the pixels' state
    of a run that sorts window after window) the sort's working memory is reused (:meth:`PixelState.sort_keys`).
    """
    from ._kernels import simulate as k

    parts = [p for p in parts if p[0].size]
    n = sum(p[0].size for p in parts)
    if not parts:
        return (empty_events(0), np.zeros(0, dtype=bool)) if labels else empty_events(0)
    out = np.empty(n, dtype=EVENT_DTYPE) if sink is None else sink.reserve(n)
    # touch its fresh pages in order, from this thread: the sort's parallel scatter faulting them in
    # costs ~14 ns per event (measured: 21 ms per million events into fresh memory, 8.7 touched first)
    out.view(np.uint8)[::4096] = 0
    lab = np.empty(n if labels else 0, dtype=np.uint8)
    if (t_hi - t_lo) >> k.SORT_FINE_BITS >= k.SORT_COARSE_MAX:  # a window too long for the counting sort's histograms
        _sort_long_window(parts, out, lab)
    else:
        cols, segments = _in_place(parts)
        del parts
        keys = state.sort_keys(n) if state is not None else np.empty(n, dtype=np.uint64)
        k.sort_into_events(*cols, segments, np.int64(t_lo), np.int64(t_hi), out, lab, keys)
    return (out, lab.astype(bool)) if labels else out


_COLUMN_TYPES = (np.int64, np.uint16, np.uint16, np.uint8)


def _in_place(parts):
    """``(columns, segments)``: four columns and the ``(first, end)`` rows that hold the parts' events in order.

    Parts that are views of the same columns (:meth:`PixelState.shared`) are read where they are; otherwise they
    are concatenated into new columns (one segment).
    """
    segments = _segments_of(parts)
    if segments is not None:
        return [c.base for c in parts[0][:4]], segments
    cols = [np.ascontiguousarray(parts[0][i] if len(parts) == 1 else np.concatenate([p[i] for p in parts]), dtype=d)
            for i, d in enumerate(_COLUMN_TYPES)]
    return cols, np.array([[0, cols[0].size]], dtype=np.int64)


def _segments_of(parts):
    """Where the parts lie in the columns their first part is a view of, or None if they are not all views of them
    (in :data:`_COLUMN_TYPES`, contiguous, each part at one offset in every column)."""
    bases = [c.base for c in parts[0][:4]]
    if not all(isinstance(b, np.ndarray) and b.ndim == 1 and b.dtype == d and b.flags.c_contiguous
               for b, d in zip(bases, _COLUMN_TYPES)):
        return None
    address = [b.__array_interface__["data"][0] for b in bases]
    segments = np.empty((len(parts), 2), dtype=np.int64)
    for j, part in enumerate(parts):
        first = {(a.__array_interface__["data"][0] - at) // a.itemsize if a.base is b and a.flags.c_contiguous
                 else -1 for a, b, at in zip(part[:4], bases, address)}
        if len(first) != 1 or -1 in first:
            return None
        segments[j, 0] = first.pop()
        segments[j, 1] = segments[j, 0] + part[0].size
    return segments


def _sort_long_window(parts, out, lab):
    """The counting sort's result for a window whose span would need too large a histogram: NumPy's stable sort."""
    t, x, y, p = (np.concatenate([part[i] for part in parts]) for i in range(4))
    order = np.argsort(t, kind="stable")
    out["t"], out["x"], out["y"] = t[order], x[order], y[order]
    out["p"] = p[order] & 1
    if lab.size:
        lab[:] = (p[order] >> 1) & 1


def renewal_inputs(p_on: np.ndarray, p_off: np.ndarray):
    """``(log(1 - p), ON share)`` of the per-trial event probability ``p = p_on + p_off``, capped at 1.

    ``p`` reaches 1 when a rate reaches the trial rate (a background of 1e6 Hz at 1000 trials/s:
    ``1 - exp(-1000)`` is 1.0 in floating point): ``log(1 - p)`` is then ``-inf``, explicitly, and the
    renewal kernel's geometric gap ``floor(log(u) / log(1 - p))`` is 0: an event at every trial.
    """
    p = np.minimum(p_on + p_off, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        q_on = np.where(p > 0, p_on / np.where(p > 0, p_on + p_off, 1.0), 0.5)
    sure = p >= 1.0
    log1m_p = np.log1p(-np.where(sure, 0.0, p))
    return np.where(sure, -np.inf, log1m_p), q_on


def timer_arrays(lam, params: NoiseParams, bg):
    """``(3, n)`` ``[d, log1p(-a2), ON share]`` of the regular background timer (:mod:`evnoise._kernels.background`)."""
    from .background import lux_of_photons
    from .terms.timer import pixel_regularity, timer_shape

    scale, hot = (None, None) if bg is None else bg
    l_on, l_off = terms.intensities(lux_of_photons(lam, params), params, scale, hot)
    l_on = np.broadcast_to(l_on, np.shape(lam))
    l_all = l_on + np.broadcast_to(l_off, np.shape(lam))
    d, log1m_a2 = timer_shape(l_all, params.trial_us * 1e-6, pixel_regularity(params, hot))
    has = l_all > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(has, l_on / np.where(has, l_all, 1.0), 0.0)
    return np.ascontiguousarray(np.stack([d, log1m_a2, share]))


def static_inputs(lam, params: NoiseParams, eps_on, eps_off, bg):
    """Renewal-kernel inputs of static pixels at ``lam``: ``(log1m_p, q_on, timer or None, total rate)``.

    Every input is a function of the pixel's ``(lam, eps_on, eps_off)`` alone when no pixel has a background
    map of its own (``bg`` None), evaluated element by element: a field with one threshold pair and few
    distinct ``lam`` (a flat field: one; an 8-bit image: at most 256) is then evaluated once per distinct
    ``lam`` and scattered, through the closed form's path for the whole field
    (:func:`evnoise.model.same_path_values`), so the arrays are bit for bit those of a per-pixel evaluation.
    """
    found = _scene_levels(lam, eps_on, eps_off, bg)
    if found is None:
        return _static_inputs(lam, params, eps_on, eps_off, bg)
    levels, inverse = found
    n, k = lam.size, levels.size
    values = same_path_values(levels, n)
    m = values.size
    log1m_p, q_on, timer, nu = _static_inputs(values, params, np.full(m, eps_on.flat[0]),
                                              np.full(m, eps_off.flat[0]), None)

    def scatter(a):
        return np.full(n, a[0]) if k == 1 else a[:k][inverse]

    if timer is not None:
        timer = np.ascontiguousarray(timer[:, :1].repeat(n, axis=1) if k == 1 else timer[:, :k][:, inverse])
    return scatter(log1m_p), scatter(q_on), timer, scatter(nu)


def _scene_levels(lam, eps_on, eps_off, bg):
    """``(levels, inverse)`` of a flat ``lam`` with few distinct values and one threshold pair, else None."""
    lam = np.asarray(lam)
    if bg is not None or lam.ndim != 1 or lam.size < 2 or lam.dtype != np.float64:
        return None
    eps_on, eps_off = np.asarray(eps_on), np.asarray(eps_off)
    for eps in (eps_on, eps_off):
        if eps.size not in (1, lam.size) or eps.min() != eps.max():
            return None
    cap = min(model.MAX_LEVELS, lam.size // 2)
    if cap < 1:
        return None
    from ._kernels.levels import find_levels

    return find_levels(lam, cap)


def _static_inputs(lam, params: NoiseParams, eps_on, eps_off, bg):
    """:func:`static_inputs` element by element."""
    if terms.regular_timer(params):
        from .rates import pixel_rates

        p_on, p_off = trial_probabilities(lam, params, (eps_on, eps_off), photon_only=True)
        log1m_p, q_on = renewal_inputs(p_on, p_off)
        nu_on, nu_off = pixel_rates(lam, params, (eps_on, eps_off), bg)
        return log1m_p, q_on, timer_arrays(lam, params, bg), nu_on + nu_off
    p_on, p_off = trial_probabilities(lam, params, (eps_on, eps_off), background=bg)
    log1m_p, q_on = renewal_inputs(p_on, p_off)
    nu = params.trial_rate_hz * (p_on + p_off)
    nu = nu / (1.0 + nu * params.refractory_us * 1e-6)
    return log1m_p, q_on, None, nu


def event_buffers(capacity: int):
    """Empty event columns ``(t, x, y, p)`` with room for ``capacity`` events (the window kernels fill them)."""
    return (np.empty(capacity, dtype=np.int64), np.empty(capacity, dtype=np.uint16),
            np.empty(capacity, dtype=np.uint16), np.empty(capacity, dtype=np.uint8))


def grown(out, n: int):
    """Event columns with twice the room (at least 1024), the first ``n`` events copied over."""
    bigger = event_buffers(max(2 * out[0].size, 1024))
    for new, old in zip(bigger, out):
        new[:n] = old[:n]
    return bigger


def run_to_end(call, out, n_pixels: int):
    """Run a window kernel over a chunk of ``n_pixels`` pixels, ``call(out, n, k) -> (n, k)``, until it reports
    every pixel done; when it stops with ``out`` full, ``out`` is :func:`grown` and the kernel called again from
    where it stopped (its draws, and so its events, are those of one call). Returns ``(out, n)``."""
    n = k = 0
    while True:
        n, k = call(out, n, k)
        if k == n_pixels:
            return out, n
        out = grown(out, n)


def renewal_step(state: PixelState, width, log1m_p, q_on, dt, refr_us, j_min, w_end, discard_from,
                  t0_us, threads, store=True, expected=None, timer=None):
    """Run the renewal kernel over all pixels of ``state`` up to ``w_end``; returns chunk parts.

    The parts' event columns are views of ``state``'s buffers: use them before the next window.
    """
    from ._kernels.simulate import renewal_window

    no_timer = np.zeros((3, 0))
    caps = {lo: int(1.2 * expected[lo:hi].sum() + 64) if expected is not None else 1024
            for lo, hi in pixel_chunks(state.pix.size)}

    def run(lo, hi):
        out = state.buffers(lo, caps[lo]) if store else event_buffers(0)
        on = np.zeros(hi - lo, dtype=np.int64)
        off = np.zeros(hi - lo, dtype=np.int64)
        out, n = run_to_end(lambda buf, n, k: renewal_window(
            width, state.pix[lo:hi], log1m_p[lo:hi], q_on[lo:hi], no_timer if timer is None else timer[:, lo:hi],
            state.states[lo:hi], state.fstate[lo:hi], dt, float(refr_us), float(j_min), float(w_end),
            float(discard_from), np.int64(t0_us), buf, n, k, on, off, store,
        ), out, hi - lo)
        if store:
            state.keep(lo, out)
        return (*(a[:n] for a in out), on, off)

    with state.shared(list(caps.values())) if store else contextlib.nullcontext():
        return map_chunks(run, state.pix.size, threads)


def memory_step(state: PixelState, mem, width, group, tables, dt, refr_us, j_min, w_end, discard_from, t0_us,
                threads, expected, timer=None):
    """Run the reset-memory kernel (:func:`evnoise._kernels.memory.memory_window`) over all pixels of ``state``
    up to ``w_end``; returns chunk parts ``(t, x, y, p)`` (views of ``state``'s buffers: use them before the
    next window). ``mem``: each pixel's stored state (local index in its level ``group``; NaN before its first
    window), updated in place; ``tables``: ``(table, itable, offsets, sizes)`` of
    :func:`evnoise.terms.memory.kernel_tables`; ``expected``: each pixel's expected events in the window;
    ``timer``: its groups' regular timer ``(3, groups)`` (None: none)."""
    from ._kernels.memory import memory_window

    table, itable, offsets, sizes = tables
    timer = np.zeros((3, 0)) if timer is None else timer
    caps = {lo: int(1.2 * expected[lo:hi].sum() + 64) for lo, hi in pixel_chunks(state.pix.size)}

    def run(lo, hi):
        out = state.buffers(lo, caps[lo])
        on = np.zeros(hi - lo, dtype=np.int64)
        off = np.zeros(hi - lo, dtype=np.int64)
        out, n = run_to_end(lambda buf, n, k: memory_window(
            width, state.pix[lo:hi], group[lo:hi], offsets, sizes, table, itable, timer, state.states[lo:hi],
            state.fstate[lo:hi], mem[lo:hi], dt, float(refr_us), float(j_min), float(w_end), float(discard_from),
            np.int64(t0_us), buf, n, k, on, off, True), out, hi - lo)
        state.keep(lo, out)
        return tuple(a[:n] for a in out)

    with state.shared(list(caps.values())):
        return map_chunks(run, state.pix.size, threads)


def trial_step(state: PixelState, width, frames_lam, frame_us, j_start: int, j_end: int, thr, bg_rows, model,
               tau_limit_us, t0_us, threads, fast_static=False, runs=None):
    """Run the trial kernel (:func:`evnoise._kernels.simulate.trial_window`) over all pixels of ``state`` for trials
    ``j_start .. j_end - 1``; returns chunk parts ``(t, x, y, p)`` (views of ``state``'s buffers: use them before the
    next window). ``thr`` ``(4, n)`` and ``bg_rows`` (the background rows, ``(4 or 5, n)`` or ``(4, 0)``) are per
    pixel of ``state``; ``frames_lam``, ``frame_us``, ``model``, ``fast_static`` as the kernel's; events at or after
    ``tau_limit_us`` (µs from ``t0_us``) are not emitted. ``runs``: the kernel's ``(run_ptr, run_seg, run_val,
    run_carry)`` (the probabilities of runs at one light of a video's pixels; default none)."""
    from ._kernels.simulate import trial_window

    if runs is None:
        runs = (np.zeros(state.pix.size + 1, dtype=np.int64), np.empty(0, dtype=np.int64), np.empty((0, 2)),
                np.empty((0, 2)))
    run_ptr, run_seg, run_val, run_carry = runs

    def run(lo, hi):
        out, n = run_to_end(lambda buf, n, k: trial_window(
            width, state.pix[lo:hi], frames_lam, frame_us, j_start, j_end, thr[:, lo:hi], bg_rows[:, lo:hi],
            state.states[lo:hi], state.fstate[lo:hi], model, float(tau_limit_us), np.int64(t0_us), buf, n, k,
            fast_static, run_ptr[lo:hi + 1], run_seg, run_val, run_carry[lo:hi]), state.buffers(lo, 256), hi - lo)
        state.keep(lo, out)
        return tuple(a[:n] for a in out)

    return map_chunks(run, state.pix.size, threads)


def progress_bar(total, enabled, desc, unit="s", scale=None):
    """A tqdm bar (None unless ``enabled``); with ``scale`` the counts are shown multiplied by it.

    Count in integers where the steps are fractions (microseconds with ``scale=1e-6`` for seconds):
    float steps can add up past ``total`` (tqdm then warns and shows a negative time left).
    """
    if not enabled:
        return None
    from tqdm.auto import tqdm

    counts = "{n:.1f}/{total:.1f} " if scale else "{n}/{total} "  # scaled counts are fractions (seconds)
    return tqdm(total=total, desc=desc, unit=unit, leave=False, unit_scale=scale or False,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| " + counts + unit + " [{elapsed}<{remaining}]")


INT64_MIN, INT64_MAX = -(1 << 63), (1 << 63) - 1
#: the kernels count trials in float64 from a run's (or a stream's) start: whole numbers are exact up to 2**53, so a
#: run may span at most 2**52 trials (142 years at the highest trial rate, 1 MHz; past any 64-bit time at the presets')
MAX_TRIALS = 1 << 52
#: working memory per event of a window being made (the kernel's columns, their sort keys), besides the events
WINDOW_BYTES_PER_EVENT = 40


def check_t_start(t_start_us, name: str = "t_start_us") -> int:
    """``t_start_us`` as an int: a whole number of microseconds that a 64-bit timestamp holds."""
    try:
        if isinstance(t_start_us, (bool, np.bool_)):  # int(True) is 1: a flag passed for a time
            raise TypeError
        t = int(t_start_us)
    except (TypeError, ValueError, OverflowError):
        raise ParameterError(f"{name} must be an integer number of microseconds, got {t_start_us!r}") from None
    if t != t_start_us:
        raise ParameterError(f"{name} must be an integer number of microseconds, got {t_start_us!r}")
    if not INT64_MIN <= t <= INT64_MAX:
        raise ParameterError(f"{name} must be a 64-bit timestamp, within +-{INT64_MAX} us (about 292,000 years), "
                             f"got {t_start_us!r}")
    return t


def check_trial_span(span_us: int, trial_us: float, what: str = "duration") -> None:
    """Refuse a run (or a stream's time since its start) longer than :data:`MAX_TRIALS` trials of ``trial_us``."""
    if span_us / trial_us >= MAX_TRIALS:
        years = MAX_TRIALS * trial_us * 1e-6 / 3.15576e7
        raise ParameterError(f"the {what} ({span_us} us) spans {span_us / trial_us:.3g} trials of {trial_us:.6g} us, "
                             f"more than the 2**52 the simulator counts exactly ({years:.3g} years at this trial rate)")


def check_span(t_start_us: int, span_us: int, trial_us: float, what: str) -> None:
    """Refuse ``span_us`` microseconds from ``t_start_us`` that no 64-bit time holds (the kernels count times from a
    run's or a stream's start in int64: the span and its end must both fit) or that is more than :data:`MAX_TRIALS`
    trials of ``trial_us``; ``what`` names the span (``"duration"``)."""
    if span_us > INT64_MAX:
        raise ParameterError(f"the {what} ({span_us} us) is more than 2**63 us, longer than a 64-bit time holds "
                             f"(about 292,000 years)")
    if t_start_us + span_us > INT64_MAX:
        raise ParameterError(f"the {what} ({span_us} us from t = {t_start_us} us) ends beyond the largest 64-bit "
                             f"timestamp ({INT64_MAX} us, about 292,000 years)")
    check_trial_span(span_us, trial_us, what)


def check_event_memory(expected_events: float, what: str, *, window_events: float = 0.0, hint: str = "") -> None:
    """Refuse to hold ``expected_events`` events (with 8 sigma to spare) before allocating them; ``window_events``:
    the events of a window made while they are held (its working memory, :data:`WINDOW_BYTES_PER_EVENT` each,
    counts too). ``what`` names who would return them (``"simulate_events would return about N events; they"``)."""
    from ._budget import check_allocation

    need = (expected_events + 8.0 * math.sqrt(max(expected_events, 0.0))) * EVENT_DTYPE.itemsize
    need += min(window_events, expected_events) * WINDOW_BYTES_PER_EVENT
    check_allocation(need, what, hint=hint, error=ParameterError)
