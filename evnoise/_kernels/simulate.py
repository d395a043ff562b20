"""Event-generation kernels: renewal tier (static pixels) and trial tier (changing pixels).

Time is kept per pixel in float64 microseconds relative to the start of the run; trial ``j``
covers ``[j dt, (j + 1) dt)``. A noise event of trial ``j`` happens at ``tau = (j + u) dt`` with
``u ~ U[0, 1)`` (so timestamps are not a comb) and is emitted as ``t0 + floor(tau)``.
Refractory period ``R`` (whole microseconds): after an event at ``tau`` in trial ``j`` the next
trial that may fire is the first ``j' > j`` with ``j' dt >= tau + R``; emitted timestamps of
one pixel are therefore at least ``R`` apart, and since ``u`` is uniform the mean number of
skipped trials is exactly ``R / dt``, giving the non-paralyzable dead-time rate
``nu = nu0 / (1 + nu0 R)``.

The window kernels take a chunk of pixels as slices (flat indices ``pix``, random streams
``states``, the float state ``fstate`` with one row per pixel and the columns named below, and
per-pixel parameters) and touch nothing else, so chunks can run in parallel threads.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ._jit import kernel
from .background import draw_timer, draw_timer_stationary, timer_shape
from .poisson import log_event_probability_exact, threshold_count
from .rng import geometric, geometric_of, geometric_x, poisson_emlam, seed_state, uniform, unit, xoshiro_step

NO_EVENT = math.nan


@kernel
def seed_streams(key, pix, states):
    """Seed row ``i`` of ``states`` with the stream of flat pixel index ``pix[i]``."""
    for i in range(pix.shape[0]):
        seed_state(key, pix[i], states[i])


@kernel
def first_eligible_trial(last_trial, tau, refr_us, dt):
    """First trial ``j > last_trial`` whose start ``j dt`` is at or after ``tau + refr_us``."""
    j = np.ceil((tau + refr_us) / dt)  # a float: math.ceil is an int64 in Numba and wraps for huge values
    while j * dt < tau + refr_us:
        j += 1.0
    while j > last_trial + 1.0 and (j - 1.0) * dt >= tau + refr_us:
        j -= 1.0
    return max(j, last_trial + 1.0)


@kernel(inline=True)
def _first_centre_at(edge_us, dt, j):
    """The first trial after ``j`` whose centre ``i dt + dt / 2`` (as the trial kernel computes it) is at or
    after ``edge_us``."""
    i = max(float(j) + 1.0, np.floor(edge_us / dt - 0.5))
    while i * dt + 0.5 * dt < edge_us:
        i += 1.0
    while i - 1.0 > float(j) and (i - 1.0) * dt + 0.5 * dt >= edge_us:
        i -= 1.0
    return int(i)


@kernel(inline=True)
def put_event(out, n, t, x, y, pol):
    """Write one event into slot ``n`` of the event columns ``out = (t, x, y, p)`` (room checked by the caller)."""
    out[0][n] = t
    out[1][n] = x
    out[2][n] = y
    out[3][n] = pol


@kernel(inline=True)
def emit(out, store, n, t0_us, tau, x, y, pol):
    """The next free slot after an event at ``tau`` µs after ``t0_us`` (floored to whole µs): with ``store`` it goes
    into slot ``n`` of ``out`` (:func:`put_event`), else only counted by the caller."""
    if store:
        put_event(out, n, t0_us + np.int64(math.floor(tau)), x, y, pol)
        return n + 1
    return n


@kernel
def _restore(states, fstate, k, snap_s, snap_f):
    """Put pixel ``k``'s stream and state back to the snapshot taken before it ran."""
    for w in range(4):
        states[k, w] = snap_s[w]
    for w in range(snap_f.shape[0]):
        fstate[k, w] = snap_f[w]


#: Columns of the per-pixel float state ``fstate`` ``(n, N_STATE)`` that the window kernels advance
#: (one row per pixel, so a pixel's state is contiguous): the last event's trial and time (µs),
#: a pending event's trial, time (NaN: none) and polarity (1.0 ON), the reference and previous mean
#: photon counts of the trial tier, its cached static probabilities (``CACHE_LAM`` the ``lam`` they
#: belong to, NaN for none), the regular timer's next arrival (trial) and its intensity (events/s), and the
#: trial tier's stored count of the reset-memory term (the photon count the pixel reset at).
(LAST_TRIAL, LAST_TAU, PEND_TRIAL, PEND_TAU, PEND_ON, LAM_REF, LAM_PREV, CACHE_LAM, CACHE_LOG1M_P, CACHE_Q_ON,
 BG_NEXT, BG_L, STORED) = range(13)
N_STATE = 13


#: The renewal kernel's loop without branches for the limits takes pixels with ``log1p(-p) < -PLAIN_LOG1M_P``: there
#: every geometric gap is finite (``|log u| <= 53 log 2`` for the smallest uniform ``u = 2**-53``)
PLAIN_LOG1M_P = 1e-300


@kernel
def renewal_window(width, pix, log1m_p, q_on, timer, states, fstate, dt, refr_us, j_min, w_end, discard_from_trial,
                   t0_us, out, n, k_start, on_counts, off_counts, store):
    """Advance pixels ``pix`` whose probabilities are constant up to time ``w_end`` (µs).

    Per pixel ``k`` (all arrays are the chunk's slices): ``log1m_p = log1p(-(p_on + p_off))`` and
    ``q_on = p_on / (p_on + p_off)``; ``states[k]`` its random stream, ``fstate[k]`` its state
    (columns :data:`LAST_TRIAL` ...). The gap to the next event is geometric in eligible trials; no
    trial before ``j_min`` is drawn. A drawn event beyond ``w_end`` stays pending (``PEND_TRIAL``,
    ``PEND_TAU``; NaN when none) so that the random stream does not depend on how time is cut into
    windows - unless its trial starts at or after ``discard_from_trial``: then it is dropped and
    redrawn next time, which is exact because the geometric gap is memoryless (used when the
    probabilities change between windows).

    With a regular background timer, ``timer`` is ``(3, n)`` per pixel ``[d, log1p(-a2), background
    ON share]`` (:func:`timer_shape`; ``(3, 0)`` for none) and ``log1m_p``, ``q_on`` are the
    *photon-noise* ones: the next event is the earlier of the photon gap and the timer's arrival
    ``BG_NEXT`` (NaN: drawn when the pixel is next eligible, the stationary draw for a pixel that
    has had no event), every event restarts the timer, and a pending event keeps its polarity in
    ``PEND_ON`` (dropping it at ``discard_from_trial`` stays exact: the timer is kept).

    Events go to the caller's buffers ``out = (t, x, y, p)`` from slot ``n`` on, and each pixel's
    counts are added to ``on_counts[k]``, ``off_counts[k]`` (with ``store`` false only the counts).
    The kernel starts at pixel ``k_start`` and returns ``(n, k)``: ``k = len(pix)`` when every pixel
    is done, else the buffers are full and pixel ``k`` stopped with its next event (inside the
    window) saved as pending - drawn but not stored; its polarity is drawn when it is stored, or, with a
    timer, was drawn with it and kept in ``PEND_ON``: grow the buffers and call again from ``k``;
    the draws, and so the events, are the same as in one call. (The buffers are never replaced inside
    the kernel: an array reassigned in the event loop costs Numba reference counting per event.)
    """
    has_timer = timer.shape[1] > 0
    cap = out[0].shape[0] if store else 0
    n_pix = pix.shape[0]
    # the pixel's stream in four scalars (registers: :func:`xoshiro_step`), copied into ``s`` around the timer's
    # draws, which take an array
    s = np.empty(4, dtype=np.uint64)
    plain = not has_timer and refr_us == 0.0
    for k in range(k_start, n_pix):
        tau = fstate[k, PEND_TAU]
        if tau >= w_end:  # (NaN compares false) an event pending beyond the window: nothing to draw
            if fstate[k, PEND_TRIAL] >= discard_from_trial:
                fstate[k, PEND_TAU] = NO_EVENT
            continue
        s0, s1, s2, s3 = states[k, 0], states[k, 1], states[k, 2], states[k, 3]
        jp = fstate[k, PEND_TRIAL]
        on = fstate[k, PEND_ON] == 1.0
        y_pix = pix[k] // width  # one division (pixel indices are >= 0)
        x_pix = pix[k] - y_pix * width
        # the pixel's state in locals (not per event): same draws, same bits
        lt = fstate[k, LAST_TRIAL]
        lta = fstate[k, LAST_TAU]
        nxt = fstate[k, BG_NEXT]
        l1p = log1m_p[k]
        qk = q_on[k]
        n_on = 0
        n_off = 0
        full = False
        if plain and -math.inf < l1p < -PLAIN_LOG1M_P:
            # The common case (no timer, no refractory period, 0 < p < 1 with every gap finite): the loop below with
            # the branches it does not take left out - the same draws and arithmetic, so the same bits. It stops at
            # the first event beyond the window or a full buffer, which the loop below then sees first.
            if math.isnan(tau):
                r, s0, s1, s2, s3 = xoshiro_step(s0, s1, s2, s3)
                jp = max(lt + 1.0, j_min) + geometric_of(r, l1p) - 1.0
                r, s0, s1, s2, s3 = xoshiro_step(s0, s1, s2, s3)
                tau = (jp + unit(r)) * dt
            while tau < w_end and not (store and n == cap):
                r, s0, s1, s2, s3 = xoshiro_step(s0, s1, s2, s3)
                pol = np.uint8(unit(r) < qk)
                n_on += pol
                n_off += 1 - pol
                n = emit(out, store, n, t0_us, tau, x_pix, y_pix, pol)
                lta = tau
                lt = jp
                r, s0, s1, s2, s3 = xoshiro_step(s0, s1, s2, s3)
                jp = max(lt + 1.0, j_min) + geometric_of(r, l1p) - 1.0
                r, s0, s1, s2, s3 = xoshiro_step(s0, s1, s2, s3)
                tau = (jp + unit(r)) * dt
        while True:
            if math.isnan(tau):
                if lta == -math.inf or refr_us == 0.0:
                    # what first_eligible_trial gives without a refractory period, since this kernel's own
                    # tau = (lt + u) dt rounds to at most (lt + 1) dt (state written by another kernel may not)
                    j_e = lt + 1.0
                else:
                    j_e = first_eligible_trial(lt, lta, refr_us, dt)
                j_e = max(j_e, j_min)
                if has_timer:
                    s[0], s[1], s[2], s[3] = s0, s1, s2, s3
                    if math.isnan(nxt):
                        if lta == -math.inf:
                            nxt = j_e + draw_timer_stationary(s, timer[0, k], timer[1, k], l1p) - 1.0
                        else:
                            nxt = j_e + draw_timer(s, timer[0, k], timer[1, k]) - 1.0
                    nxt = max(nxt, j_e)
                    j_ph = j_e + geometric(s, l1p) - 1.0
                    if nxt < j_ph:
                        jp = nxt
                        on = uniform(s) < timer[2, k]
                    else:
                        jp = j_ph
                        on = uniform(s) < qk
                    s0, s1, s2, s3 = s[0], s[1], s[2], s[3]
                    if jp == math.inf:
                        tau = math.inf
                        break
                else:
                    g, s0, s1, s2, s3 = geometric_x(s0, s1, s2, s3, l1p)
                    if g == math.inf:
                        tau = math.inf
                        jp = math.inf
                        break
                    jp = j_e + g - 1.0
                r, s0, s1, s2, s3 = xoshiro_step(s0, s1, s2, s3)
                tau = (jp + unit(r)) * dt
            if tau >= w_end:
                break
            if store and n == cap:
                full = True  # the event stays pending (polarity drawn when it is stored; with a timer kept in PEND_ON)
                break
            if not has_timer:  # the Poisson path draws the polarity of an event inside the window only
                r, s0, s1, s2, s3 = xoshiro_step(s0, s1, s2, s3)
                on = unit(r) < qk
            pol = np.uint8(on)  # counted without a branch on the polarity (it is a coin flip)
            n_on += pol
            n_off += 1 - pol
            n = emit(out, store, n, t0_us, tau, x_pix, y_pix, pol)
            lta = tau
            lt = jp
            tau = NO_EVENT
            nxt = NO_EVENT  # every event restarts the timer
        on_counts[k] += n_on
        off_counts[k] += n_off
        fstate[k, LAST_TAU] = lta
        fstate[k, LAST_TRIAL] = lt
        if jp >= discard_from_trial and not full:
            tau = NO_EVENT
        fstate[k, PEND_TAU] = tau
        fstate[k, PEND_TRIAL] = jp
        if has_timer:
            fstate[k, BG_NEXT] = nxt
            fstate[k, PEND_ON] = 1.0 if on else 0.0
        states[k, 0], states[k, 1], states[k, 2], states[k, 3] = s0, s1, s2, s3
        if full:
            return n, k
    return n, n_pix


SIGNAL_FLAG = 2  # or-ed into a kernel's polarity output for signal (threshold-crossing) events
#: :func:`sort_into_events`' first pass runs over blocks of its segments, a segment of more than SORT_BLOCK_MIN events
#: cut into up to SORT_BLOCKS blocks (the result is the same for any blocks: the pass is stable)
SORT_BLOCKS = 8
SORT_BLOCK_MIN = 1 << 17
#: the first pass's coarse time buckets: up to SORT_COARSE, more (up to SORT_COARSE_MAX) where a window is so long
#: that each would span more than ``2**SORT_FINE_BITS`` µs (the second pass's histogram per bucket: 32 k entries,
#: 256 kB); a window longer than ``SORT_COARSE_MAX * 2**SORT_FINE_BITS`` µs (~268 s) is sorted another way
#: (:func:`evnoise._engine.sorted_window`)
SORT_COARSE = 256
SORT_FINE_BITS = 15
SORT_COARSE_MAX = 1 << 13
_X_SHIFT = 18  # a packed event: fine time bits << 34 | x << 18 | y << 2 | p (p: polarity bit and SIGNAL_FLAG)
_FINE_SHIFT = 34


@kernel
def _sort_blocks(segments):
    """``(first, end)`` rows: the blocks of the first pass, in input order (segments in order, a segment of more
    than SORT_BLOCK_MIN events cut into up to SORT_BLOCKS blocks)."""
    n_blocks = 0
    for s in range(segments.shape[0]):
        n_blocks += max(1, min(SORT_BLOCKS, (segments[s, 1] - segments[s, 0]) // SORT_BLOCK_MIN))
    blocks = np.empty((n_blocks, 2), dtype=np.int64)
    r = 0
    for s in range(segments.shape[0]):
        lo = segments[s, 0]
        m = segments[s, 1] - lo
        k = max(1, min(SORT_BLOCKS, m // SORT_BLOCK_MIN))
        size = (m + k - 1) // k
        for b in range(k):
            blocks[r, 0] = lo + min(m, b * size)
            blocks[r, 1] = lo + min(m, (b + 1) * size)
            r += 1
    return blocks


@kernel(parallel=True)
def sort_into_events(t, x, y, p, segments, t_lo, t_hi, out, labels, keys):
    """Sort the events of the columns ``(t, x, y, p)`` in the ``segments`` ``(first, end)`` rows (in order) into
    the event array ``out``, stably by ``t`` (in ``[t_lo, t_hi)``, shorter than ``SORT_COARSE_MAX << SORT_FINE_BITS``).

    A two-pass (MSD) counting sort, O(n + t_hi - t_lo), that reads the segments where they are: the first pass packs
    each event into one 64-bit word (the low bits of its time, x, y, p) and scatters it into one of
    :data:`SORT_COARSE` coarse time buckets (more for very long windows; one write stream per bucket, so the writes
    stay in cache), in parallel over blocks of the input, each block's share of a bucket after the earlier blocks'
    (offsets bucket by bucket, block by block); the second counting-sorts each bucket by the low bits in parallel (a
    bucket's histogram and output fit in cache) and unpacks it into ``out``. Both passes are stable: ties keep the
    input order (segment order, then each segment's own order), so the result does not depend on how the work was
    split. The kernels mark signal events with :data:`SIGNAL_FLAG` in ``p``; the flag is removed from ``out.p``
    and, if ``labels`` has room for every event, written there (1 = signal). ``keys``: working memory for the packed
    events (a new array is taken if it has room for fewer than all of them).
    """
    span = t_hi - t_lo
    shift = 0
    while (span >> shift) >= SORT_COARSE and shift < SORT_FINE_BITS:
        shift += 1
    n_coarse = (span >> shift) + 1
    blocks = _sort_blocks(segments)
    n_blocks = blocks.shape[0]
    hist = np.zeros((n_blocks, n_coarse), dtype=np.int64)
    for b in prange(n_blocks):
        for i in range(blocks[b, 0], blocks[b, 1]):
            hist[b, (t[i] - t_lo) >> shift] += 1
    starts = np.zeros(n_coarse + 1, dtype=np.int64)
    fill = np.empty((n_blocks, n_coarse), dtype=np.int64)
    acc = 0
    for c in range(n_coarse):
        starts[c] = acc
        for b in range(n_blocks):
            fill[b, c] = acc
            acc += hist[b, c]
    starts[n_coarse] = acc
    fine = np.int64(1) << shift
    mask = fine - 1
    if keys.shape[0] < acc:
        keys = np.empty(acc, dtype=np.uint64)
    for b in prange(n_blocks):
        for i in range(blocks[b, 0], blocks[b, 1]):
            d = t[i] - t_lo
            c = d >> shift
            j = fill[b, c]
            fill[b, c] = j + 1
            keys[j] = ((np.uint64(d & mask) << np.uint64(_FINE_SHIFT)) | (np.uint64(x[i]) << np.uint64(_X_SHIFT))
                       | (np.uint64(y[i]) << np.uint64(2)) | np.uint64(p[i] & 3))
    want_labels = labels.shape[0] == acc
    for c in prange(n_coarse):
        lo = starts[c]
        hi = starts[c + 1]
        if hi - lo == 0:
            continue
        counts = np.zeros(fine + 1, dtype=np.int64)
        for i in range(lo, hi):
            counts[np.int64(keys[i] >> np.uint64(_FINE_SHIFT)) + 1] += 1
        for f in range(fine):
            counts[f + 1] += counts[f]
        base = t_lo + (np.int64(c) << shift)
        for i in range(lo, hi):
            key = keys[i]
            f = np.int64(key >> np.uint64(_FINE_SHIFT))
            j = lo + counts[f]
            counts[f] += 1
            out[j].t = base + f
            out[j].x = np.uint16((key >> np.uint64(_X_SHIFT)) & np.uint64(0xFFFF))
            out[j].y = np.uint16((key >> np.uint64(2)) & np.uint64(0xFFFF))
            out[j].p = np.uint8(key & np.uint64(1))
            if want_labels:
                labels[j] = np.uint8((key >> np.uint64(1)) & np.uint64(1))


@kernel
def static_in_window(frames_lam, pix, fstate, out):
    """``out[k]``: pixel ``pix[k]`` has the same ``lam`` in every frame of ``frames_lam`` (F, all pixels),
    equal to its ``LAM_REF`` and ``LAM_PREV``, and its cached probabilities belong to another ``lam``
    (the pixels whose cache :func:`trial_window`'s jump needs filled)."""
    for k in range(pix.shape[0]):
        lam0 = frames_lam[0, pix[k]]
        ok = lam0 == fstate[k, LAM_REF] and lam0 == fstate[k, LAM_PREV] and not fstate[k, CACHE_LAM] == lam0
        f = 1
        while ok and f < frames_lam.shape[0]:
            ok = frames_lam[f, pix[k]] == lam0
            f += 1
        out[k] = ok


@kernel
def _add_background(p_on, p_off, l_on, l_off, dt_s):
    """Per-trial probabilities with background intensities ``l_on``, ``l_off`` (events/s) added."""
    l_all = l_on + l_off
    if l_all <= 0.0:
        return p_on, p_off
    g = -math.expm1(-l_all * dt_s) / l_all
    quiet = 1.0 - p_on - p_off
    return p_on + quiet * g * l_on, p_off + quiet * g * l_off


@kernel(inline=True)
def background_intensity(bg, k, lam_in, lux_per_photon, dark_lux):
    """``(l_on, l_all)``, pixel ``k``'s background intensities (events/s) at ``lam_in`` photons per trial from its
    rows ``bg`` of :func:`trial_window` (also what :func:`evnoise._kernels.memory.initial_stored` stores, the same
    arithmetic, so a timer it starts is not rescaled at the first trial)."""
    lux = max(lam_in * lux_per_photon - dark_lux, 0.0)
    l_on = bg[0, k] + bg[1, k] * lux
    return l_on, l_on + bg[2, k] + bg[3, k] * lux


_LEVEL_FLOOR = 1e-6  # photons per trial; log-levels below log(1e-6) are clamped in signal crossings


@kernel
def _level(lam, b):
    return math.log(max(lam + b, _LEVEL_FLOOR))


@kernel(inline=True)
def run_entry(run_ptr, run_seg, k, seg):
    """Index of pixel ``k``'s last stretch starting at a frame ``<= seg`` of this window (see
    :func:`run_stretches`), -1 for none (its stretch began before the window: the carried values)."""
    e = -1
    for q in range(run_ptr[k], run_ptr[k + 1]):
        if run_seg[q] <= seg:
            e = q
    return e


_STRETCH_BLOCK = 4096  # run_stretches: pixels per block (the threads share the blocks)


@kernel(parallel=True)
def run_stretches(frames_lam, pix, segs, pairs, last, valid, count, ptr, seg_out, lam_out):
    """Where a video's changing pixels start *stretches* of one light in a window (the trial tier's runs).

    ``frames_lam`` ``(F, all pixels)``: photons per trial at the window's frames, of which pixels ``pix`` (``n``)
    count; ``segs``: the frames ``f`` (indices into ``frames_lam``, increasing) whose pair ``(f, f + 1)``
    brackets some trial's centre, ``pairs`` their indices in the video. A pixel at the same light in both frames
    of pair ``i`` continues the stretch it had at pair ``i - 1`` (``valid``: it had one through pair ``last``,
    the last pair of the windows before) when that pair was evaluated too, or else starts one. With ``seg_out``
    empty: counts each pixel's starts into ``count``. Else, with ``ptr`` ``(n + 1)`` the offsets of those
    counts: fills per pixel, in order, ``seg_out`` (the frame ``f``) and ``lam_out`` of each start, and updates
    ``valid`` to the window's last pair. The starts depend on the frames and the trials alone.
    """
    n = pix.shape[0]
    fill = seg_out.shape[0] > 0
    for blk in prange((n + _STRETCH_BLOCK - 1) // _STRETCH_BLOCK):
        lo = blk * _STRETCH_BLOCK
        hi = min(lo + _STRETCH_BLOCK, n)
        ok = valid[lo:hi].copy()
        m = np.zeros(hi - lo, dtype=np.int64)
        prev = last
        for q in range(segs.shape[0]):
            i = pairs[q]
            if i <= last:
                continue  # evaluated with the windows before
            f = segs[q]
            cont = prev == i - 1
            for k in range(lo, hi):
                lam = frames_lam[f, pix[k]]
                same = lam == frames_lam[f + 1, pix[k]]
                if same and not (ok[k - lo] and cont):
                    if fill:
                        e = ptr[k] + m[k - lo]
                        seg_out[e] = f
                        lam_out[e] = lam
                    m[k - lo] += 1
                ok[k - lo] = same
            prev = i
        for k in range(lo, hi):
            if fill:
                valid[k] = ok[k - lo] and prev == pairs[segs.shape[0] - 1]
            else:
                count[k] = m[k - lo]


@kernel
def trial_window(width, pix, frames_lam, frame_us, j_start, j_end, thr, bg, states, fstate, model, tau_limit, t0_us,
                 out, n, k_start, fast_static, run_ptr, run_seg, run_val, run_carry):
    """Trial-by-trial simulation of pixels ``pix`` for trials ``j_start .. j_end - 1``.

    ``frames_lam`` (F, P) holds the mean photon counts per trial of the frames at times
    ``frame_us`` (µs, increasing; trials whose centre lies outside are clamped to the end
    frames); ``lam`` of a trial is the linear interpolation at the trial's centre.

    Per trial: *signal* events first - the mean level ``L = log(lam + b)`` is compared with
    the reference ``L_ref = log(lam_ref + b)``; every whole threshold crossed gives one event,
    timed where the level crosses it (linear in ``L`` between the previous trial's level and
    this one), at least the refractory period after the previous event, and moves ``L_ref``
    by one threshold; what does not fit in the trial is left for the next one. Then, if no
    signal event fired and the trial is eligible, the *noise* comparison of the paper's
    model: ``n ~ Poisson(lam)``, ``n0 ~ Poisson(lam_ref)``, ON if ``n > n0 + floor(c_on (n0 + b))``,
    OFF if ``n0 > n + floor(c_off (n + b))``; a noise event resets ``lam_ref`` to ``lam``. For a
    static pixel (``lam_ref = lam``) this is exactly the static model.

    Per-pixel arrays are the chunk's slices, indexed by ``k``: ``pix`` the flat pixel indices,
    ``thr`` ``(4, n)`` ``[c_on, c_off, eps_on, eps_off]``, ``states`` the random streams and
    ``fstate`` the state (columns :data:`LAST_TRIAL` ...; the reference ``LAM_REF``, the previous
    trial's mean ``LAM_PREV``). ``model`` is ``(b, dt, refr_us, lux_per_photon, dark_lux, pr_alpha,
    regularity, memory)``: the bias in photons per trial, the trial length and refractory period (µs) and the
    terms below. Events at or after ``tau_limit`` (µs) are not emitted (the end of the recording).

    With ``fast_static`` a *run* of trials jumps: from a trial whose centre lies between two frames of the
    same ``lam``, equal to the pixel's ``lam_ref`` and ``lam_prev``, to the first trial whose centre does not
    (between frames of another light, or of two lights). No signal crossing can happen there
    (``lam = lam_ref``), a noise event resets ``lam_ref`` to the same ``lam``, so every eligible trial fires
    independently with the same probabilities ``p_on``, ``p_off`` of the static model, and the gap to the next
    event is geometric in eligible trials (as in :func:`renewal_window`): O(events) instead of O(trials).
    Each gap is drawn with its event's time and polarity. An event beyond a run that ends inside the window
    is dropped (exact: the geometric gap is memoryless) and the next trials go one by one; beyond a run that
    reaches the window's end it stays pending (``PEND_TRIAL``, ``PEND_TAU``, ``PEND_ON``) and is taken if
    the next window's first trial goes on with the run. Runs are defined by the trials and frames alone, so
    the events do not depend on how time is cut into windows. ``p_on``, ``p_off`` come from the exact
    closed form and are cached per pixel (``CACHE_LAM`` is the ``lam`` they belong to, NaN for none;
    ``CACHE_LOG1M_P = log1p(-(p_on + p_off))``, ``CACHE_Q_ON = p_on / (p_on + p_off)``), set when a run
    begins at a ``lam`` other than the cached one: from the caller's values of :func:`run_stretches` where given
    (``run_ptr``, ``run_seg``, ``run_val``, ``run_carry``; ``run_carry`` with no rows: none), or else from the
    exact sum here. Bits that do not depend on the windows need the caller's values to be the same bits whichever
    window asks (:mod:`evnoise.simulate` evaluates each value on its own,
    :func:`evnoise.model.log_event_probability_alone`); a caller may also fill the cache beforehand
    (:func:`static_in_window`) where it computes the same bits for every window (a still scene: every pixel's one
    ``lam``, filled before the first window). The random stream is consumed differently from the per-trial path,
    so the output differs in its bits, not in its law;
    ``fast_static=False`` keeps the per-trial path (the reference).

    Background activity (:mod:`evnoise.background`): ``bg`` is ``(4, n)`` per pixel
    ``[l0_on, l1_on, l0_off, l1_off]`` with intensities ``l = l0 + l1 * lux`` (events/s) at the
    trial's input ``lux = max(lam * lux_per_photon - dark_lux, 0)``, or ``(4, 0)`` for none. An
    eligible trial whose photon comparison fired nothing fires a background event with
    probability ``1 - exp(-l dt)``, ON with probability ``l_on / l`` (one more uniform draw, only
    when ``bg`` is given), and, like every event, resets ``lam_ref``. With ``regularity > 0`` the
    background follows the regular timer of :mod:`evnoise._kernels.background` instead: ``BG_NEXT``
    (state) is the trial of the next arrival, drawn in the first quiet eligible trial after an event
    from the intensity of that trial (the stationary draw before a pixel's first event); every event
    restarts it; when the intensity changes, the rest of a pending interval scales with old / new
    intensity (``BG_L`` holds the intensity it belongs to). (Pass ``fast_static`` false then: the
    timer is not memoryless.) A fifth row of ``bg``, where given, is each pixel's own regularity (hot
    pixels with one of their own; ``regularity`` is then the largest, which turns the timer on).

    Photoreceptor bandwidth: with ``pr_alpha > 0`` the mean photon count a pixel compares
    (``LAM_PREV`` holds it between trials) follows the input through a first-order low-pass
    filter on the level ``log(lam + b)`` with step ``1 - exp(-lam * pr_alpha)`` per trial (time
    constant inversely proportional to the input photocurrent); once within ``1e-9`` of the input
    level it is snapped to it, so a settled pixel is exactly static again.

    Reset memory (:mod:`evnoise.terms.memory`): with ``memory = k > 0`` the noise comparison of an eligible
    trial takes, with probability ``k`` (one more uniform, drawn before the reference; none when ``k = 0``), the
    pixel's stored count ``STORED`` as its reference instead of a fresh ``n0 ~ Poisson(lam_ref)``. A noise or
    background event stores the trial's count ``n``; a trial with signal events stores a count drawn around the
    new reference, ``Poisson(lam_ref)`` (the level the pixel reset at, with its photon noise). For a still pixel
    this is the module's model trial by trial; the caller draws ``STORED`` (and a timer's first arrival) at the
    start from the steady state (:func:`evnoise._kernels.memory.initial_stored`). ``fast_static`` is ignored then
    (the stored count makes a still pixel's trials dependent).

    Events go to the caller's buffers ``out = (t, x, y, p)`` from slot ``n`` on, starting at pixel
    ``k_start``; returns ``(n, k)``, ``k = len(pix)`` when every pixel is done. When the buffers fill
    up, pixel ``k``'s stream and state are put back as they were before it and its events dropped:
    grow the buffers and call again from ``k`` (same draws, same events as one call; the buffers are
    never replaced inside the kernel, where Numba would count references on every trial).
    """
    cap = out[0].shape[0]
    snap_s = np.empty(4, dtype=np.uint64)
    snap_f = np.empty(fstate.shape[1])
    n_frames = frames_lam.shape[0]
    max_signal = 1 << 20
    b, dt, refr_us, lux_per_photon, dark_lux, pr_alpha, regularity, memory = model
    has_bg = bg.shape[1] > 0
    own_reg = bg.shape[0] > 4  # a regularity per pixel (hot pixels with their own), row 4
    dt_s = dt * 1e-6
    for k in range(k_start, pix.shape[0]):
        n_before = n
        for w in range(4):
            snap_s[w] = states[k, w]
        for w in range(snap_f.shape[0]):
            snap_f[w] = fstate[k, w]
        full = False
        flat = pix[k]
        x_pix = flat % width
        y_pix = flat // width
        s = states[k]
        seg = 0
        e_on = math.exp(thr[2, k])
        e_off = math.exp(thr[3, k])
        ref = fstate[k, LAM_REF]
        fast = fast_static and memory == 0.0
        # an event a jump drew in the last window: kept if this window's first trial goes on with its run (below)
        pend_ok = fast and not math.isnan(fstate[k, PEND_TAU])
        fstate[k, PEND_TAU] = NO_EVENT  # (put back by a jump that leaves one pending)
        p_trial = snap_f[PEND_TRIAL]
        p_tau = snap_f[PEND_TAU]
        p_on = snap_f[PEND_ON] == 1.0
        # cached exp(-lam) of the last Poisson means (most trials repeat them)
        lam_c = -1.0
        em_c = 1.0
        ref_c = -1.0
        emr_c = 1.0
        j = j_start
        while j < j_end:
            s_j = j * dt
            const = True  # the trial's centre lies between two frames of the same light
            if n_frames == 1:
                lam = frames_lam[0, flat]
            else:
                centre = s_j + 0.5 * dt
                while seg < n_frames - 2 and frame_us[seg + 1] <= centre:
                    seg += 1
                f0 = frames_lam[seg, flat]
                f1 = frames_lam[seg + 1, flat]
                const = f0 == f1
                a = (centre - frame_us[seg]) / (frame_us[seg + 1] - frame_us[seg])
                a = min(max(a, 0.0), 1.0)
                lam = f0 + a * (f1 - f0)
            if fast and const and lam == ref and fstate[k, LAM_PREV] == lam:
                # a run of trials at this light, settled: to the first trial whose centre lies between frames that
                # are not both at it (the same run however the windows cut it); within it every eligible trial
                # fires independently, so the gap to the next event is geometric (the module's static model)
                r = j_end
                sr = seg
                while n_frames > 1 and sr < n_frames - 2:
                    jr = _first_centre_at(frame_us[sr + 1], dt, j)
                    if jr >= j_end:
                        break
                    c_r = jr * dt + 0.5 * dt
                    sn = sr + 1
                    while sn < n_frames - 2 and frame_us[sn + 1] <= c_r:
                        sn += 1
                    if frames_lam[sn, flat] == lam and frames_lam[sn + 1, flat] == lam:
                        sr = sn
                    else:
                        r = jr
                        break
                if fstate[k, CACHE_LAM] != lam:
                    e = run_entry(run_ptr, run_seg, k, seg)
                    if run_carry.shape[0] > 0 and (e >= 0 or not math.isnan(run_carry[k, 0])):  # the caller's
                        fstate[k, CACHE_LOG1M_P] = run_val[e, 0] if e >= 0 else run_carry[k, 0]
                        fstate[k, CACHE_Q_ON] = run_val[e, 1] if e >= 0 else run_carry[k, 1]
                    else:
                        p1 = math.exp(log_event_probability_exact(lam, thr[0, k], b))
                        p0 = math.exp(log_event_probability_exact(lam, thr[1, k], b))
                        if has_bg:
                            lux0 = max(lam * lux_per_photon - dark_lux, 0.0)
                            p1, p0 = _add_background(p1, p0, bg[0, k] + bg[1, k] * lux0,
                                                     bg[2, k] + bg[3, k] * lux0, dt_s)
                        p_all = p1 + p0
                        fstate[k, CACHE_LOG1M_P] = math.log1p(-p_all) if p_all < 1.0 else -math.inf
                        fstate[k, CACHE_Q_ON] = p1 / p_all if p_all > 0.0 else 0.0
                    fstate[k, CACHE_LAM] = lam
                    pend_ok = False  # drawn with other probabilities
                if j != j_start:
                    pend_ok = False
                log1m_p = fstate[k, CACHE_LOG1M_P]
                q_on = fstate[k, CACHE_Q_ON]
                while True:
                    if pend_ok:  # (its time may be inf: never)
                        jp = p_trial
                        tau = p_tau
                        on = p_on
                        pend_ok = False
                    else:
                        if fstate[k, LAST_TAU] == -math.inf:
                            j_e = fstate[k, LAST_TRIAL] + 1.0
                        else:
                            j_e = first_eligible_trial(fstate[k, LAST_TRIAL], fstate[k, LAST_TAU], refr_us, dt)
                        j_e = max(j_e, float(j))
                        if j_e >= r:
                            break
                        g = geometric(s, log1m_p)
                        jp = j_e + g - 1.0
                        u_t = uniform(s)
                        on = uniform(s) < q_on
                        tau = (jp + u_t) * dt
                    if jp >= r:
                        if r == j_end:  # the run may go on in the next window
                            fstate[k, PEND_TRIAL] = jp
                            fstate[k, PEND_TAU] = tau
                            fstate[k, PEND_ON] = 1.0 if on else 0.0
                        break  # else the run ends here: dropped (memoryless), the next trials go one by one
                    if tau >= tau_limit:
                        break
                    if n == cap:
                        full = True
                        break
                    put_event(out, n, t0_us + np.int64(math.floor(tau)), x_pix, y_pix, 1 if on else 0)
                    n += 1
                    fstate[k, LAST_TAU] = tau
                    fstate[k, LAST_TRIAL] = jp
                if full:
                    break
                j = r
                continue
            pend_ok = False  # trial by trial: a pending jump's event is dropped (memoryless)
            lam_in = lam
            if pr_alpha > 0.0 and lam != fstate[k, LAM_PREV]:
                lev_in = _level(lam, b)
                lev_f = _level(fstate[k, LAM_PREV], b)
                lev_f += -math.expm1(-lam * pr_alpha) * (lev_in - lev_f)
                if abs(lev_f - lev_in) <= 1e-9:
                    lam = lam_in
                else:
                    lam = max(math.exp(lev_f) - b, 0.0)
            fired = False
            # signal crossings (rare): compare levels multiplicatively, take logs only if needed
            up = lam + b >= (ref + b) * e_on
            down = (lam + b) * e_off <= ref + b
            if up or down:
                lev = _level(lam, b)
                lev_ref = _level(ref, b)
                lev_prev = _level(fstate[k, LAM_PREV], b)
                sign = 0 if up else 1
                eps = thr[2, k] if up else thr[3, k]
                emitted = 0
                while emitted < max_signal:
                    gap = (lev - lev_ref) if sign == 0 else (lev_ref - lev)
                    if gap < eps:
                        break
                    target = lev_ref + eps if sign == 0 else lev_ref - eps
                    span = lev - lev_prev
                    phi = (target - lev_prev) / span if span != 0.0 else 0.0
                    phi = min(max(phi, 0.0), 1.0)
                    tau = s_j + phi * dt
                    if fstate[k, LAST_TAU] + refr_us > tau:
                        tau = fstate[k, LAST_TAU] + refr_us
                    if tau >= s_j + dt or tau >= tau_limit:
                        break  # does not fit in this trial: left for the next one
                    if n == cap:
                        full = True
                        break
                    put_event(out, n, t0_us + np.int64(math.floor(tau)), x_pix, y_pix,
                              (1 if sign == 0 else 0) | SIGNAL_FLAG)
                    n += 1
                    emitted += 1
                    fired = True
                    lev_ref = target
                    fstate[k, LAST_TAU] = tau
                    fstate[k, LAST_TRIAL] = j
                    if regularity > 0.0:
                        fstate[k, BG_NEXT] = math.nan
                if full:
                    break
                if fired:
                    ref = max(math.exp(lev_ref) - b, 0.0)
                    if memory > 0.0:
                        fstate[k, STORED] = poisson_emlam(s, ref, math.exp(-ref))
            if not fired and j > fstate[k, LAST_TRIAL] and s_j >= fstate[k, LAST_TAU] + refr_us:
                if lam != lam_c:
                    lam_c = lam
                    em_c = math.exp(-lam)
                if ref != ref_c:
                    ref_c = ref
                    emr_c = math.exp(-ref)
                n_sig = poisson_emlam(s, lam, em_c)
                if memory > 0.0 and uniform(s) < memory:
                    n_ref = fstate[k, STORED]
                else:
                    n_ref = poisson_emlam(s, ref, emr_c)
                pol = -1
                if n_sig > threshold_count(n_ref, thr[0, k], b):  # a float: no int64 wrap for large thresholds
                    pol = 1
                elif n_ref > threshold_count(n_sig, thr[1, k], b):
                    pol = 0
                elif has_bg:
                    l_on, l_all = background_intensity(bg, k, lam_in, lux_per_photon, dark_lux)
                    if regularity > 0.0:
                        if not fstate[k, BG_NEXT] < math.inf and l_all > 0.0:  # none pending (NaN, or inf in the dark)
                            d_t, l1m_t = timer_shape(l_all, dt_s, bg[4, k] if own_reg else regularity)
                            if fstate[k, LAST_TAU] == -math.inf:
                                p_st = (math.exp(log_event_probability_exact(lam, thr[0, k], b))
                                        + math.exp(log_event_probability_exact(lam, thr[1, k], b)))
                                fstate[k, BG_NEXT] = j + draw_timer_stationary(s, d_t, l1m_t,
                                                                               math.log1p(-min(p_st, 1.0))) - 1.0
                            else:
                                fstate[k, BG_NEXT] = j + draw_timer(s, d_t, l1m_t) - 1.0
                            fstate[k, BG_L] = l_all
                        elif l_all != fstate[k, BG_L] and fstate[k, BG_L] > 0.0 and fstate[k, BG_NEXT] > j:
                            if l_all > 0.0:
                                fstate[k, BG_NEXT] = j + np.floor((fstate[k, BG_NEXT] - j)
                                                                    * (fstate[k, BG_L] / l_all))
                            else:
                                fstate[k, BG_NEXT] = math.inf
                            fstate[k, BG_L] = l_all
                        if j >= fstate[k, BG_NEXT]:
                            pol = 1 if uniform(s) * l_all < l_on else 0
                    elif l_all > 0.0:
                        u_bg = uniform(s)
                        a_bg = -math.expm1(-l_all * dt_s)
                        if u_bg < a_bg:
                            pol = 1 if u_bg < a_bg * (l_on / l_all) else 0
                tau = (j + uniform(s)) * dt if pol >= 0 else math.inf
                if tau < tau_limit:
                    if n == cap:
                        full = True
                        break
                    put_event(out, n, t0_us + np.int64(math.floor(tau)), x_pix, y_pix, pol)
                    n += 1
                    fstate[k, LAST_TAU] = tau
                    fstate[k, LAST_TRIAL] = j
                    ref = lam
                    if memory > 0.0:
                        fstate[k, STORED] = n_sig
                    if regularity > 0.0:
                        fstate[k, BG_NEXT] = math.nan
            fstate[k, LAM_PREV] = lam
            j += 1
        if full:
            _restore(states, fstate, k, snap_s, snap_f)
            return n_before, k
        fstate[k, LAM_REF] = ref
    return n, pix.shape[0]
