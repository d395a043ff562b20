"""Event-generation kernels: renewal tier (static pixels) and trial tier (changing pixels).

Time is kept per pixel in float64 microseconds relative to the start of the run; trial ``j``
covers ``[j dt, (j + 1) dt)``. A noise event of trial ``j`` happens at ``tau = (j + u) dt`` with
``u ~ U[0, 1)`` (so timestamps are not a comb) and is emitted as ``t0 + floor(tau)``.
Refractory period ``R`` (whole microseconds): after an event at ``tau`` in trial ``j`` the next
trial that may fire is the first ``j' > j`` with ``j' dt >= tau + R``; emitted timestamps of
one pixel are therefore at least ``R`` apart, and since ``u`` is uniform the mean number of
skipped trials is exactly ``R / dt``, giving the non-paralyzable dead-time rate
``nu = nu0 / (1 + nu0 R)``.

All kernels work on a contiguous range of pixels ``[lo, hi)`` and on that range's slice of
the per-pixel state only, so chunks can run in parallel threads.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ._jit import kernel
from .poisson import log_event_probability_exact
from .background import draw_timer, draw_timer_stationary, timer_shape
from .rng import geometric, poisson_emlam, seed_state, uniform

NO_EVENT = math.nan


@kernel
def seed_streams(key, pix, states):
    """Seed row ``i`` of ``states`` with the stream of flat pixel index ``pix[i]``."""
    for i in range(pix.shape[0]):
        seed_state(key, pix[i], states[i])


@kernel
def _first_eligible(last_trial, tau, refr_us, dt):
    """First trial ``j > last_trial`` whose start ``j dt`` is at or after ``tau + refr_us``."""
    j = math.ceil((tau + refr_us) / dt)
    while j * dt < tau + refr_us:
        j += 1.0
    while j > last_trial + 1.0 and (j - 1.0) * dt >= tau + refr_us:
        j -= 1.0
    return max(j, last_trial + 1.0)


@kernel
def _grow(arr, n):
    out = np.empty(max(2 * arr.shape[0], 1024), dtype=arr.dtype)
    out[:n] = arr[:n]
    return out


@kernel(inline=True)
def _push(t_out, x_out, y_out, p_out, n, t, flat, width, pol):
    """Append one event, growing the buffers when full; returns the (possibly new) buffers."""
    if n == t_out.shape[0]:
        t_out = _grow(t_out, n)
        x_out = _grow(x_out, n)
        y_out = _grow(y_out, n)
        p_out = _grow(p_out, n)
    t_out[n] = t
    x_out[n] = flat % width
    y_out[n] = flat // width
    p_out[n] = pol
    return t_out, x_out, y_out, p_out


@kernel
def renewal_window(
    lo, hi, width, pix, log1m_p, q_on, states, last_trial, last_tau, pend_trial, pend_tau,
    dt, refr_us, j_min, w_end, discard_from_trial, t0_us, capacity, store
):
    """Advance pixels ``pix[lo:hi]`` whose probabilities are constant up to time ``w_end`` (µs).

    Per pixel (chunk slices, index ``k = i - lo``): ``log1m_p = log1p(-(p_on + p_off))`` and
    ``q_on = p_on / (p_on + p_off)``. The gap to the next event is geometric in eligible
    trials; no trial before ``j_min`` is drawn. A drawn event beyond ``w_end`` stays pending
    (``pend_trial``, ``pend_tau``; ``pend_tau`` NaN when none) so that the random stream does
    not depend on how time is cut into windows - unless its trial starts at or after
    ``discard_from_trial``: then it is dropped and redrawn next time, which is exact because
    the geometric gap is memoryless (used when the probabilities change between windows).

    Returns ``(t, x, y, p, on_counts, off_counts)``; with ``store`` false only the counts
    (length ``hi - lo``) are filled.
    """
    cap = capacity if store else 0
    t_out = np.empty(cap, dtype=np.int64)
    x_out = np.empty(cap, dtype=np.uint16)
    y_out = np.empty(cap, dtype=np.uint16)
    p_out = np.empty(cap, dtype=np.uint8)
    on_counts = np.zeros(hi - lo, dtype=np.int64)
    off_counts = np.zeros(hi - lo, dtype=np.int64)
    n = 0
    for i in range(lo, hi):
        k = i - lo
        tau = pend_tau[k]
        if tau >= w_end:  # (NaN compares false) an event pending beyond the window: nothing to draw
            if pend_trial[k] >= discard_from_trial:
                pend_tau[k] = NO_EVENT
            continue
        s = states[k]
        jp = pend_trial[k]
        flat = pix[i]
        xk = np.uint16(flat % width)
        yk = np.uint16(flat // width)
        # the pixel's state in locals and x, y once per pixel (not per event): same draws, same bits
        lt = last_trial[k]
        lta = last_tau[k]
        l1p = log1m_p[k]
        qk = q_on[k]
        n_on = 0
        n_off = 0
        while True:
            if math.isnan(tau):
                if lta == -math.inf:
                    j_e = lt + 1.0
                else:
                    j_e = _first_eligible(lt, lta, refr_us, dt)
                j_e = max(j_e, j_min)
                g = geometric(s, l1p)
                if g == math.inf:
                    tau = math.inf
                    jp = math.inf
                    break
                jp = j_e + g - 1.0
                tau = (jp + uniform(s)) * dt
            if tau >= w_end:
                break
            on = uniform(s) < qk
            if on:
                n_on += 1
            else:
                n_off += 1
            if store:
                if n == t_out.shape[0]:
                    t_out = _grow(t_out, n)
                    x_out = _grow(x_out, n)
                    y_out = _grow(y_out, n)
                    p_out = _grow(p_out, n)
                t_out[n] = t0_us + np.int64(math.floor(tau))
                x_out[n] = xk
                y_out[n] = yk
                p_out[n] = 1 if on else 0
                n += 1
            lta = tau
            lt = jp
            tau = NO_EVENT
        on_counts[k] = n_on
        off_counts[k] = n_off
        last_tau[k] = lta
        last_trial[k] = lt
        if jp >= discard_from_trial:
            tau = NO_EVENT
        pend_tau[k] = tau
        pend_trial[k] = jp
    return t_out[:n], x_out[:n], y_out[:n], p_out[:n], on_counts, off_counts


@kernel
def renewal_window_timer(
    lo, hi, width, pix, log1m_p, q_on, timer, states, last_trial, last_tau, pend_trial, pend_tau, pend_on,
    bg_next, dt, refr_us, j_min, w_end, discard_from_trial, t0_us, capacity, store
):
    """:func:`evnoise._kernels.simulate.renewal_window` with a regular background timer.

    ``log1m_p``, ``q_on`` are the *photon-noise* ``log1p(-(p_on + p_off))`` and ON share; ``timer``
    ``(3, hi - lo)`` per pixel ``[d, log1p(-a2), background ON share]`` (:func:`timer_shape`).
    ``bg_next`` (state) is the trial of the pixel's next background arrival (NaN: to be drawn when
    the pixel is next eligible; the stationary draw for a pixel that has had no event). ``pend_on``
    holds a pending event's polarity. A pending event beyond the window is dropped at or after
    ``discard_from_trial`` (the photon gap is memoryless and ``bg_next`` is kept, so this is exact).
    """
    cap = capacity if store else 0
    t_out = np.empty(cap, dtype=np.int64)
    x_out = np.empty(cap, dtype=np.uint16)
    y_out = np.empty(cap, dtype=np.uint16)
    p_out = np.empty(cap, dtype=np.uint8)
    on_counts = np.zeros(hi - lo, dtype=np.int64)
    off_counts = np.zeros(hi - lo, dtype=np.int64)
    n = 0
    for i in range(lo, hi):
        k = i - lo
        tau = pend_tau[k]
        if tau >= w_end:
            if pend_trial[k] >= discard_from_trial:
                pend_tau[k] = NO_EVENT
            continue
        s = states[k]
        jp = pend_trial[k]
        on = pend_on[k] == 1.0
        flat = pix[i]
        lt = last_trial[k]
        lta = last_tau[k]
        nxt = bg_next[k]
        n_on = 0
        n_off = 0
        while True:
            if math.isnan(tau):
                if lta == -math.inf:
                    j_e = lt + 1.0
                else:
                    j_e = _first_eligible(lt, lta, refr_us, dt)
                j_e = max(j_e, j_min)
                if math.isnan(nxt):
                    if lta == -math.inf:
                        nxt = j_e + draw_timer_stationary(s, timer[0, k], timer[1, k], log1m_p[k]) - 1.0
                    else:
                        nxt = j_e + draw_timer(s, timer[0, k], timer[1, k]) - 1.0
                nxt = max(nxt, j_e)
                g = geometric(s, log1m_p[k])
                j_ph = j_e + g - 1.0
                if nxt < j_ph:
                    jp = nxt
                    on = uniform(s) < timer[2, k]
                else:
                    jp = j_ph
                    on = uniform(s) < q_on[k]
                if jp == math.inf:
                    tau = math.inf
                    break
                tau = (jp + uniform(s)) * dt
            if tau >= w_end:
                break
            if on:
                n_on += 1
            else:
                n_off += 1
            if store:
                t_out, x_out, y_out, p_out = _push(t_out, x_out, y_out, p_out, n, t0_us + np.int64(math.floor(tau)),
                                                   flat, width, 1 if on else 0)
                n += 1
            lta = tau
            lt = jp
            tau = NO_EVENT
            nxt = NO_EVENT  # every event restarts the timer
        on_counts[k] = n_on
        off_counts[k] = n_off
        last_tau[k] = lta
        last_trial[k] = lt
        bg_next[k] = nxt
        if jp >= discard_from_trial:
            tau = NO_EVENT
        pend_tau[k] = tau
        pend_trial[k] = jp
        pend_on[k] = 1.0 if on else 0.0
    return t_out[:n], x_out[:n], y_out[:n], p_out[:n], on_counts, off_counts


SIGNAL_FLAG = 2  # or-ed into a kernel's polarity output for signal (threshold-crossing) events


@kernel(parallel=True)
def sort_into_events(t, x, y, p, t_lo, t_hi, out, labels):
    """Scatter the columns into the event array ``out`` sorted stably by ``t`` (in ``[t_lo, t_hi)``).

    A two-pass (MSD) counting sort, O(n + t_hi - t_lo): the events are first scattered into
    at most 256 coarse time buckets (few write streams, so the writes stay in cache), then
    each bucket is counting-sorted by the remaining low bits of ``t`` in parallel (a bucket's
    histogram and output fit in cache). Both passes are stable: ties keep the input order
    (pixel order, then time order within a pixel), so the result does not depend on how the
    work was split. The kernels mark signal events with :data:`SIGNAL_FLAG` in ``p``; the
    flag is removed from ``out.p`` and, if ``labels`` has room for every event, written there
    (1 = signal).
    """
    n = t.shape[0]
    span = t_hi - t_lo
    shift = 0
    while (span >> shift) >= 256:
        shift += 1
    n_coarse = (span >> shift) + 1
    starts = np.zeros(n_coarse + 1, dtype=np.int64)
    for i in range(n):
        starts[((t[i] - t_lo) >> shift) + 1] += 1
    for c in range(n_coarse):
        starts[c + 1] += starts[c]
    tt = np.empty(n, dtype=np.int64)
    xx = np.empty(n, dtype=np.uint16)
    yy = np.empty(n, dtype=np.uint16)
    pp = np.empty(n, dtype=np.uint8)
    fill = starts.copy()
    for i in range(n):
        c = (t[i] - t_lo) >> shift
        j = fill[c]
        fill[c] = j + 1
        tt[j] = t[i]
        xx[j] = x[i]
        yy[j] = y[i]
        pp[j] = p[i]
    fine = np.int64(1) << shift
    mask = fine - 1
    want_labels = labels.shape[0] == n
    for c in prange(n_coarse):
        lo = starts[c]
        hi = starts[c + 1]
        if hi - lo == 0:
            continue
        counts = np.zeros(fine + 1, dtype=np.int64)
        for i in range(lo, hi):
            counts[((tt[i] - t_lo) & mask) + 1] += 1
        for f in range(fine):
            counts[f + 1] += counts[f]
        for i in range(lo, hi):
            f = (tt[i] - t_lo) & mask
            j = lo + counts[f]
            counts[f] += 1
            out[j].t = tt[i]
            out[j].x = xx[i]
            out[j].y = yy[i]
            out[j].p = pp[i] & 1
            if want_labels:
                labels[j] = pp[i] >> 1


@kernel
def _add_background(p_on, p_off, l_on, l_off, dt_s):
    """Per-trial probabilities with background intensities ``l_on``, ``l_off`` (events/s) added."""
    l_all = l_on + l_off
    if l_all <= 0.0:
        return p_on, p_off
    g = -math.expm1(-l_all * dt_s) / l_all
    quiet = 1.0 - p_on - p_off
    return p_on + quiet * g * l_on, p_off + quiet * g * l_off


_LEVEL_FLOOR = 1e-6  # photons per trial; log-levels below log(1e-6) are clamped in signal crossings


@kernel
def _level(lam, b):
    return math.log(max(lam + b, _LEVEL_FLOOR))


@kernel
def trial_window(
    lo, hi, width, pix, frames_lam, frame_us, j_start, j_end, c_on, c_off, eps_on, eps_off, b,
    states, last_trial, last_tau, lam_ref, lam_prev, dt, refr_us, tau_limit, t0_us, capacity,
    fast_static, cache_lam, cache_log1m_p, cache_q_on, bg, lux_per_photon, dark_lux, pr_alpha, regularity, bg_next,
    bg_l
):
    """Trial-by-trial simulation of pixels ``pix[lo:hi]`` for trials ``j_start .. j_end - 1``.

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

    Per-pixel arrays (``states``, ``last_*``, ``lam_ref``, ``lam_prev``, ``c_*``, ``eps_*``) are
    indexed by ``k = i - lo`` (pass the chunk's slices); ``pix`` maps to flat pixel indices.
    Events at or after ``tau_limit`` (µs) are not emitted (the end of the recording).

    With ``fast_static`` a pixel whose ``lam`` is the same in every frame of the window and
    equals both ``lam_ref`` and ``lam_prev`` skips the trial-by-trial loop: no signal
    crossing can happen (``lam = lam_ref``), a noise event resets ``lam_ref`` to the same
    ``lam``, so every eligible trial fires independently with the same probabilities
    ``p_on``, ``p_off`` of the static model, and the gap to the next event is geometric in
    eligible trials (as in :func:`renewal_window`): O(events) instead of O(trials). A gap
    that ends beyond the window is dropped and redrawn in the next window (exact: the
    geometric gap is memoryless). ``p_on``, ``p_off`` come from the exact closed form and are
    cached per pixel (``cache_lam`` is the ``lam`` they belong to, NaN for none;
    ``cache_log1m_p = log1p(-(p_on + p_off))``, ``cache_q_on = p_on / (p_on + p_off)``). The
    random stream is consumed differently from the per-trial path, so the output differs in
    its bits, not in its law; ``fast_static=False`` keeps the per-trial path (the reference).

    Background activity (:mod:`evnoise.background`): ``bg`` is ``(4, hi - lo)`` per pixel
    ``[l0_on, l1_on, l0_off, l1_off]`` with intensities ``l = l0 + l1 * lux`` (events/s) at the
    trial's input ``lux = max(lam * lux_per_photon - dark_lux, 0)``, or ``(4, 0)`` for none. An
    eligible trial whose photon comparison fired nothing fires a background event with
    probability ``1 - exp(-l dt)``, ON with probability ``l_on / l`` (one more uniform draw, only
    when ``bg`` is given), and, like every event, resets ``lam_ref``. With ``regularity > 0`` the
    background follows the regular timer of :mod:`evnoise._kernels.background` instead: ``bg_next``
    (state) is the trial of the next arrival, drawn in the first quiet eligible trial after an event
    from the intensity of that trial (the stationary draw before a pixel's first event); every event
    restarts it; when the intensity changes, the rest of a pending interval scales with old / new
    intensity (``bg_l`` holds the intensity it belongs to). (Pass ``fast_static`` false then: the
    timer is not memoryless.)

    Photoreceptor bandwidth: with ``pr_alpha > 0`` the mean photon count a pixel compares
    (``lam_prev`` holds it between trials) follows the input through a first-order low-pass
    filter on the level ``log(lam + b)`` with step ``1 - exp(-lam * pr_alpha)`` per trial (time
    constant inversely proportional to the input photocurrent); once within ``1e-9`` of the input
    level it is snapped to it, so a settled pixel is exactly static again.
    """
    t_out = np.empty(capacity, dtype=np.int64)
    x_out = np.empty(capacity, dtype=np.uint16)
    y_out = np.empty(capacity, dtype=np.uint16)
    p_out = np.empty(capacity, dtype=np.uint8)
    n = 0
    n_frames = frames_lam.shape[0]
    max_signal = 1 << 20
    has_bg = bg.shape[1] > 0
    dt_s = dt * 1e-6
    for i in range(lo, hi):
        k = i - lo
        flat = pix[i]
        s = states[k]
        seg = 0
        e_on = math.exp(eps_on[k])
        e_off = math.exp(eps_off[k])
        ref = lam_ref[k]
        if fast_static:
            lam0 = frames_lam[0, flat]
            const = lam0 == ref and lam_prev[k] == ref
            for f in range(1, n_frames):
                if frames_lam[f, flat] != lam0:
                    const = False
                    break
            if const:
                if cache_lam[k] != lam0:
                    p_on = math.exp(log_event_probability_exact(lam0, c_on[k], b))
                    p_off = math.exp(log_event_probability_exact(lam0, c_off[k], b))
                    if has_bg:
                        lux0 = max(lam0 * lux_per_photon - dark_lux, 0.0)
                        p_on, p_off = _add_background(p_on, p_off, bg[0, k] + bg[1, k] * lux0,
                                                      bg[2, k] + bg[3, k] * lux0, dt_s)
                    p_all = p_on + p_off
                    cache_lam[k] = lam0
                    cache_log1m_p[k] = math.log1p(-p_all) if p_all < 1.0 else -math.inf
                    cache_q_on[k] = p_on / p_all if p_all > 0.0 else 0.0
                log1m_p = cache_log1m_p[k]
                q_on = cache_q_on[k]
                while True:
                    if last_tau[k] == -math.inf:
                        j_e = last_trial[k] + 1.0
                    else:
                        j_e = _first_eligible(last_trial[k], last_tau[k], refr_us, dt)
                    j_e = max(j_e, float(j_start))
                    if j_e >= j_end:
                        break
                    g = geometric(s, log1m_p)
                    jp = j_e + g - 1.0
                    if jp >= j_end:
                        break  # dropped; redrawn from the next window on (memoryless)
                    u_t = uniform(s)
                    on = uniform(s) < q_on
                    tau = (jp + u_t) * dt
                    if tau >= tau_limit:
                        break
                    t_out, x_out, y_out, p_out = _push(
                        t_out, x_out, y_out, p_out, n, t0_us + np.int64(math.floor(tau)), flat, width,
                        1 if on else 0,
                    )
                    n += 1
                    last_tau[k] = tau
                    last_trial[k] = jp
                continue
        # cached exp(-lam) of the last Poisson means (most trials repeat them)
        lam_c = -1.0
        em_c = 1.0
        ref_c = -1.0
        emr_c = 1.0
        for j in range(j_start, j_end):
            s_j = j * dt
            if n_frames == 1:
                lam = frames_lam[0, flat]
            else:
                centre = s_j + 0.5 * dt
                while seg < n_frames - 2 and frame_us[seg + 1] <= centre:
                    seg += 1
                f0 = frames_lam[seg, flat]
                f1 = frames_lam[seg + 1, flat]
                a = (centre - frame_us[seg]) / (frame_us[seg + 1] - frame_us[seg])
                a = min(max(a, 0.0), 1.0)
                lam = f0 + a * (f1 - f0)
            lam_in = lam
            if pr_alpha > 0.0 and lam != lam_prev[k]:
                lev_in = _level(lam, b)
                lev_f = _level(lam_prev[k], b)
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
                lev_prev = _level(lam_prev[k], b)
                sign = 0 if up else 1
                eps = eps_on[k] if up else eps_off[k]
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
                    if last_tau[k] + refr_us > tau:
                        tau = last_tau[k] + refr_us
                    if tau >= s_j + dt or tau >= tau_limit:
                        break  # does not fit in this trial: left for the next one
                    t_out, x_out, y_out, p_out = _push(
                        t_out, x_out, y_out, p_out, n, t0_us + np.int64(math.floor(tau)), flat, width,
                        (1 if sign == 0 else 0) | SIGNAL_FLAG,
                    )
                    n += 1
                    emitted += 1
                    fired = True
                    lev_ref = target
                    last_tau[k] = tau
                    last_trial[k] = j
                    if regularity > 0.0:
                        bg_next[k] = math.nan
                if fired:
                    ref = max(math.exp(lev_ref) - b, 0.0)
            if not fired and j > last_trial[k] and s_j >= last_tau[k] + refr_us:
                if lam != lam_c:
                    lam_c = lam
                    em_c = math.exp(-lam)
                if ref != ref_c:
                    ref_c = ref
                    emr_c = math.exp(-ref)
                n_sig = poisson_emlam(s, lam, em_c)
                n_ref = poisson_emlam(s, ref, emr_c)
                pol = -1
                if n_sig > n_ref + math.floor(c_on[k] * (n_ref + b)):
                    pol = 1
                elif n_ref > n_sig + math.floor(c_off[k] * (n_sig + b)):
                    pol = 0
                elif has_bg:
                    lux_j = max(lam_in * lux_per_photon - dark_lux, 0.0)
                    l_on = bg[0, k] + bg[1, k] * lux_j
                    l_all = l_on + bg[2, k] + bg[3, k] * lux_j
                    if regularity > 0.0:
                        if not bg_next[k] < math.inf and l_all > 0.0:  # none pending (NaN, or inf in the dark)
                            d_t, l1m_t = timer_shape(l_all, dt_s, regularity)
                            if last_tau[k] == -math.inf:
                                p_st = (math.exp(log_event_probability_exact(lam, c_on[k], b))
                                        + math.exp(log_event_probability_exact(lam, c_off[k], b)))
                                bg_next[k] = j + draw_timer_stationary(s, d_t, l1m_t, math.log1p(-min(p_st, 1.0))) - 1.0
                            else:
                                bg_next[k] = j + draw_timer(s, d_t, l1m_t) - 1.0
                            bg_l[k] = l_all
                        elif l_all != bg_l[k] and bg_l[k] > 0.0 and bg_next[k] > j:
                            if l_all > 0.0:
                                bg_next[k] = j + math.floor((bg_next[k] - j) * (bg_l[k] / l_all))
                            else:
                                bg_next[k] = math.inf
                            bg_l[k] = l_all
                        if j >= bg_next[k]:
                            pol = 1 if uniform(s) * l_all < l_on else 0
                    elif l_all > 0.0:
                        u_bg = uniform(s)
                        a_bg = -math.expm1(-l_all * dt_s)
                        if u_bg < a_bg:
                            pol = 1 if u_bg < a_bg * (l_on / l_all) else 0
                tau = (j + uniform(s)) * dt if pol >= 0 else math.inf
                if tau < tau_limit:
                    t_out, x_out, y_out, p_out = _push(
                        t_out, x_out, y_out, p_out, n, t0_us + np.int64(math.floor(tau)), flat, width, pol
                    )
                    n += 1
                    last_tau[k] = tau
                    last_trial[k] = j
                    ref = lam
                    if regularity > 0.0:
                        bg_next[k] = math.nan
            lam_prev[k] = lam
        lam_ref[k] = ref
    return t_out[:n], x_out[:n], y_out[:n], p_out[:n]
