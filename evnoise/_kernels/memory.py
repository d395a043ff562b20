"""Kernels of the reset-memory term (``reset_memory > 0``): state tables and the event-by-event simulator.

A static pixel with reset memory is a Markov renewal process over its *stored count* ``m`` (the photon
count of the trial of its last event; module doc of :mod:`evnoise.terms.memory`). The states are the
counts ``lo .. lo + S - 1`` of one light level (a *group* of pixels sharing ``lam`` and thresholds); per
state the tables hold the per-trial event probability and what the next state is drawn from. The
window kernel advances pixels event by event: a geometric gap in eligible trials from the state's
probability, a uniform time within the trial, the refractory period as in
:func:`evnoise._kernels.simulate.renewal_window`, then the branch and polarity, then the new state. All
draws of one event are made when the event is drawn (an event beyond the window stays pending with its
polarity and new state), so a pixel's stream, and the output, do not depend on windows, chunks or threads.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import kernel
from .background import draw_timer, draw_timer_stationary, timer_shape
from .poisson import log_pmf, threshold_count
from .rng import geometric, uniform, uniform_pos
from .simulate import (
    BG_L,
    BG_NEXT,
    LAST_TAU,
    LAST_TRIAL,
    PEND_ON,
    PEND_TAU,
    PEND_TRIAL,
    STORED,
    background_intensity,
    emit,
    first_eligible_trial,
)

NO_EVENT = math.nan

#: Rows of the per-state float table ``(N_ROWS, total states)`` of :func:`memory_window`.
#: ``ROW_CUM_INIT``: cumulative (unnormalised) time-stationary law of the state at ``t = 0``; ``ROW_DEAD``: the
#: probability, given the state, that ``t = 0`` falls in the refractory period after the last event
#: (:func:`evnoise.terms.memory.initial_law`).
#: ``ROW_BG_ON``, ``ROW_BG_OFF``: per-trial probability of a background event (a trial without photon event);
#: ``ROW_CUM_NONE``: cumulative ``(1 - k) Poisson(j) P(no fresh event | j)``; ``ROW_K_HEAD``: ``k P(lo <= N <= j)``
#: (the two laws a background event's stored count is drawn from, :func:`draw_event`).
(ROW_LOG1M_P, ROW_FRESH_ON, ROW_FRESH_OFF, ROW_STORED_ON, ROW_STORED_OFF, ROW_CUM_FRESH_ON, ROW_CUM_FRESH_OFF,
 ROW_TAIL, ROW_HEAD, ROW_CUM_INIT, ROW_DEAD, ROW_BG_ON, ROW_BG_OFF, ROW_CUM_NONE, ROW_K_HEAD) = range(15)
N_ROWS = 15
#: Rows of the per-state integer table ``(2, total states)``: first state above the ON threshold, last state
#: below the OFF threshold (local indices; ``S`` and ``-1`` for none).
ROW_IDX_ON, ROW_IDX_OFF = range(2)


@kernel
def fill_counts(lam, lo, n_states, c_on, c_off, b, log_pmf_out, k_on_out, k_off_out):
    """Per state ``m = lo + s``: ``log P(N = m)`` for ``N ~ Poisson(lam)`` and the threshold counts
    ``k(m) = m + floor(c (m + b))`` of both polarities (:func:`~evnoise._kernels.poisson.threshold_count`)."""
    for s in range(n_states):
        m = lo + s
        if lam > 0.0:
            log_pmf_out[s] = log_pmf(m, lam)
        else:
            log_pmf_out[s] = 0.0 if m == 0.0 else -math.inf
        k_on_out[s] = threshold_count(m, c_on, b)
        k_off_out[s] = threshold_count(m, c_off, b)


@kernel
def search_up(cum, a, b, target):
    """Smallest index ``i`` in ``[a, b]`` with ``cum[i] >= target`` (``cum`` nondecreasing; ``b`` if none)."""
    while a < b:
        mid = (a + b) // 2
        if cum[mid] >= target:
            b = mid
        else:
            a = mid + 1
    return a


@kernel
def _search_down(tail, a, b, target):
    """Largest index ``i`` in ``[a, b]`` with ``tail[i] >= target`` (``tail`` nonincreasing; ``a`` if none)."""
    while a < b:
        mid = (a + b + 1) // 2
        if tail[mid] >= target:
            a = mid
        else:
            b = mid - 1
    return a


@kernel
def draw_initial(s, table, o, n_s, refr_us):
    """A pixel's state at ``t = 0`` (a trial start) in its steady state: ``(state, elapsed_us)``.

    The state (local index) is drawn from the time-stationary law ``ROW_CUM_INIT`` (``pi_m E[T_m]``, see
    :func:`evnoise.terms.memory.initial_law`); then, with probability ``ROW_DEAD`` of that state, ``t = 0`` is
    in the refractory period after the pixel's last event, which was ``elapsed_us`` ago, uniform on
    ``(0, refr_us]``; else ``elapsed_us`` is ``-1`` (eligible: the next event's trial is geometric from trial 0,
    memoryless). Always two uniforms, three when dead.
    """
    return draw_start(s, table[ROW_CUM_INIT, o:o + n_s], table[ROW_DEAD, o:o + n_s], n_s, refr_us)


@kernel
def draw_start(s, cum, dead, n_s, refr_us):
    """:func:`draw_initial` from a chain's rows themselves: ``cum`` its ``ROW_CUM_INIT``, ``dead`` its ``ROW_DEAD``
    (also for chains without tables, :mod:`evnoise._kernels.memory_start`)."""
    st = float(search_up(cum, 0, n_s - 1, uniform_pos(s) * cum[n_s - 1]))
    if uniform(s) < dead[int(st)]:
        return st, uniform_pos(s) * refr_us
    return st, -1.0


@kernel
def store_start(fstate, k, stored, elapsed, dt):
    """Pixel ``k``'s start in the trial kernel's state: its stored count, and, where ``t = 0`` is in its dead time
    (``elapsed > 0`` µs since its last event), that event's time and trial (``dt``: the trial, µs)."""
    fstate[k, STORED] = stored
    if elapsed > 0.0:
        fstate[k, LAST_TAU] = -elapsed
        fstate[k, LAST_TRIAL] = np.floor(-elapsed / dt)


@kernel
def initial_stored(states, fstate, group, offsets, sizes, lo, table, dt, refr_us, timer, bg, lam_first,
                   lux_per_photon, dark_lux, regularity):
    """The trial tier's start in the steady state (:func:`evnoise._kernels.simulate.trial_window` with reset
    memory): per pixel ``k`` of the chunk a state of its level ``group[k]`` drawn by :func:`draw_initial` from
    its stream ``states[k]``, stored as the count ``lo[g] + state`` in ``fstate[k, STORED]``, and the last event's
    time and trial when ``t = 0`` falls in its dead time (as :func:`memory_window` does).

    With the regular timer (``timer`` ``(3, groups)`` as in :func:`memory_window`; ``(3, 0)``: none) a pixel of a
    group with one, outside its dead time, also gets its timer's first arrival from the steady-state age given its
    state (:func:`draw_timer_stationary` with the state's photon probability), as the trial kernel's ``BG_NEXT``
    (trial) and ``BG_L`` (the intensity it belongs to: :func:`~evnoise._kernels.simulate.background_intensity` at
    trial 0 from the pixel's background rows ``bg`` and its photons per trial ``lam_first`` there; ``regularity``:
    the trial kernel's, where ``bg`` has no row of its own)."""
    s = np.empty(4, dtype=np.uint64)
    has_timer = timer.shape[1] > 0
    own_reg = bg.shape[0] > 4
    for k in range(states.shape[0]):
        for w in range(4):
            s[w] = states[k, w]
        g = group[k]
        st, elapsed = draw_initial(s, table, offsets[g], sizes[g], refr_us)
        store_start(fstate, k, lo[g] + st, elapsed, dt)
        if not elapsed > 0.0 and has_timer and timer[0, g] < math.inf and bg.shape[1] > 0:
            l_all = background_intensity(bg, k, lam_first[k], lux_per_photon, dark_lux)[1]
            if l_all > 0.0:
                d_t, l1m_t = timer_shape(l_all, dt * 1e-6, bg[4, k] if own_reg else regularity)
                log1m_p = table[ROW_LOG1M_P, offsets[g] + int(st)]
                fstate[k, BG_NEXT] = draw_timer_stationary(s, d_t, l1m_t, log1m_p) - 1.0
                fstate[k, BG_L] = l_all
        for w in range(4):
            states[k, w] = s[w]


@kernel
def _quiet_count(table, itable, o, n_s, i, w):
    """The count (local index) a background event stores from state ``i`` (global column): the trial's count
    given no photon event, by inversion of ``F(j) = CUM_NONE(j) + k (HEAD(min(j, a - 1)) - HEAD(b))`` for
    ``j > b`` (``a``, ``b``: the state's ``ROW_IDX_ON``, ``ROW_IDX_OFF``; the stored branch not beaten
    between them), nondecreasing in ``j``, at ``w`` times its total."""
    a = itable[ROW_IDX_ON, i]
    b = itable[ROW_IDX_OFF, i]
    cum = table[ROW_CUM_NONE, o:o + n_s]
    khead = table[ROW_K_HEAD, o:o + n_s]
    base = khead[b] if b >= 0 else 0.0

    def f(j):
        top = min(j, a - 1)
        return cum[j] + (khead[top] - base if top > b else 0.0)

    target = w * f(n_s - 1)
    lo_j = 0
    hi_j = n_s - 1
    while lo_j < hi_j:
        mid = (lo_j + hi_j) // 2
        if f(mid) >= target:
            hi_j = mid
        else:
            lo_j = mid + 1
    return float(lo_j)


@kernel
def draw_event(s, table, itable, o, n_s, st):
    """Branch, polarity and new state of an event from state ``st`` (local index) of the group at offset ``o``.

    Returns ``(on, new_state)``. One uniform picks the branch and polarity in proportion to the six
    per-trial probabilities (fresh ON, fresh OFF, stored ON, stored OFF, then background ON and OFF, which
    are 0 without background), one more the new state by inversion of that branch's table.
    """
    i = o + int(st)
    f_on = table[ROW_FRESH_ON, i]
    f_off = table[ROW_FRESH_OFF, i]
    s_on = table[ROW_STORED_ON, i]
    s_off = table[ROW_STORED_OFF, i]
    g_on = table[ROW_BG_ON, i]
    g_off = table[ROW_BG_OFF, i]
    v = uniform(s) * (f_on + f_off + s_on + s_off + g_on + g_off)
    w = uniform_pos(s)
    # the first branch whose cumulative weight passes v (a branch of weight 0 is never chosen, also
    # when rounding puts v at the total: then the last branch of positive weight)
    branch = -1
    acc = 0.0
    for c in range(6):
        wt = f_on if c == 0 else (f_off if c == 1 else (s_on if c == 2 else (s_off if c == 3 else (
            g_on if c == 4 else g_off))))
        if wt > 0.0:
            acc += wt
            branch = c
            if v < acc:
                break
    if branch >= 4:
        return branch == 4, _quiet_count(table, itable, o, n_s, i, w)
    if branch == 0:
        cum = table[ROW_CUM_FRESH_ON, o:o + n_s]
        return True, float(search_up(cum, 0, n_s - 1, w * cum[n_s - 1]))
    if branch == 1:
        cum = table[ROW_CUM_FRESH_OFF, o:o + n_s]
        return False, float(search_up(cum, 0, n_s - 1, w * cum[n_s - 1]))
    if branch == 2:
        a = itable[ROW_IDX_ON, i]  # Poisson restricted to states a .. S - 1: invert its upper tail
        tail = table[ROW_TAIL, o:o + n_s]
        return True, float(_search_down(tail, a, n_s - 1, w * tail[a]))
    b = itable[ROW_IDX_OFF, i]  # Poisson restricted to states 0 .. b: invert its cumulative sum
    head = table[ROW_HEAD, o:o + n_s]
    return False, float(search_up(head, 0, b, w * head[b]))


@kernel
def memory_window(width, pix, group, offsets, sizes, table, itable, timer, states, fstate, mem, dt, refr_us, j_min,
                  w_end, discard_from_trial, t0_us, out, n, k_start, on_counts, off_counts, store):
    """Advance static pixels with reset memory up to time ``w_end`` (µs); the memory twin of ``renewal_window``.

    No trial before ``j_min`` is drawn, and a drawn event beyond ``w_end`` whose trial starts at or after
    ``discard_from_trial`` is dropped (with its polarity and new state) and redrawn next time, from the stored
    state, which is exact because the gap in one state is geometric (used by :class:`evnoise.NoiseStream` when
    the light changes between intervals; ``0`` and ``inf`` for one static run).

    Per pixel ``k`` of the chunk: ``group[k]`` its light level, whose states are the columns
    ``offsets[g] .. offsets[g] + sizes[g] - 1`` of ``table`` (rows ``ROW_*``) and ``itable``;
    ``states[k]`` its random stream; ``fstate[k]`` its state (columns of :mod:`evnoise._kernels.simulate`:
    last event's trial and time, a pending event's trial and time; ``PEND_ON`` holds the pending event's
    code ``on + 2 * (new state + 1)``); ``mem[k]`` its stored state (local index; NaN before its first window,
    then drawn, with its last event's time when ``t = 0`` is in its dead time, from the steady state:
    :func:`draw_initial`).

    The regular background timer (:mod:`evnoise._kernels.background`): ``timer`` is ``(3, groups)``, per group
    the timer's fixed part ``d`` (trials; ``inf``: none, the background is Poisson and in the tables' rows), its
    ``log1p(-a2)`` and the share of ON arrivals, or ``(3, 0)`` for no group. A group with a timer has tables of
    photon noise alone (``ROW_LOG1M_P``, and ``ROW_BG_*`` 0): from the first eligible trial the photon event comes
    after ``G`` trials (geometric), the timer's after ``L`` (:func:`draw_timer`; at a pixel's start outside its
    dead time :func:`draw_timer_stationary` with its state's photon probability), the photon event first when
    ``G <= L`` (the trial kernel compares photons first); a timer event's polarity is ON with its share, and it
    stores the count of a trial without photon event (:func:`_quiet_count`). The timer's arrival (trial) is kept in
    ``fstate[k, BG_NEXT]`` until an event restarts it, so a pending event dropped at ``discard_from_trial`` is
    redrawn with a fresh photon gap (memoryless) and the same timer (as ``renewal_window`` does; a change of its
    intensity between intervals: :meth:`evnoise._engine.PixelState.rescale_timers`). With a refractory period only
    a pixel's first event is approximate there (as for memoryless pixels with the timer).

    Events go to ``out = (t, x, y, p)`` from slot ``n``; counts to ``on_counts``, ``off_counts``. Returns
    ``(n, k)`` like ``renewal_window`` (``k = len(pix)``: done; else the buffers are full and pixel ``k``
    keeps its next event pending: grow them and call again from ``k``).
    """
    t_out, x_out, y_out, p_out = out
    has_timer = timer.shape[1] > 0
    cap = t_out.shape[0] if store else 0
    n_pix = pix.shape[0]
    s = np.empty(4, dtype=np.uint64)
    for k in range(k_start, n_pix):
        tau = fstate[k, PEND_TAU]
        if tau >= w_end:  # (NaN compares false) an event pending beyond the window: nothing to draw
            if fstate[k, PEND_TRIAL] >= discard_from_trial:
                fstate[k, PEND_TAU] = NO_EVENT
            continue
        for w in range(4):
            s[w] = states[k, w]
        g = group[k]
        o = offsets[g]
        n_s = sizes[g]
        st = mem[k]
        d_timer = timer[0, g] if has_timer else math.inf
        nxt = fstate[k, BG_NEXT]  # the timer's pending arrival (trial; NaN: none drawn since the last event)
        stationary_timer = False
        if math.isnan(st):
            st, elapsed = draw_initial(s, table, o, n_s, refr_us)
            if elapsed > 0.0:  # in the dead time of an event at -elapsed µs (in trial floor(-elapsed / dt) < 0)
                fstate[k, LAST_TAU] = -elapsed
                fstate[k, LAST_TRIAL] = np.floor(-elapsed / dt)
            else:
                stationary_timer = True
        jp = fstate[k, PEND_TRIAL]
        code = fstate[k, PEND_ON]  # pending event: on + 2 * (new state + 1)
        x_pix = pix[k] % width
        y_pix = pix[k] // width
        lt = fstate[k, LAST_TRIAL]
        lta = fstate[k, LAST_TAU]
        n_on = 0
        n_off = 0
        full = False
        while True:
            if math.isnan(tau):
                if lta == -math.inf or refr_us == 0.0:
                    j_e = lt + 1.0
                else:
                    j_e = first_eligible_trial(lt, lta, refr_us, dt)
                j_e = max(j_e, j_min)
                log1m_p = table[ROW_LOG1M_P, o + int(st)]
                from_timer = False
                if d_timer < math.inf:
                    if math.isnan(nxt):
                        if stationary_timer:
                            nxt = j_e + draw_timer_stationary(s, d_timer, timer[1, g], log1m_p) - 1.0
                        else:
                            nxt = j_e + draw_timer(s, d_timer, timer[1, g]) - 1.0
                    nxt = max(nxt, j_e)
                    jp = j_e + geometric(s, log1m_p) - 1.0
                    from_timer = nxt < jp  # photons first on a tie
                    if from_timer:
                        jp = nxt
                else:
                    jp = j_e + geometric(s, log1m_p) - 1.0
                stationary_timer = False
                if jp == math.inf:
                    tau = math.inf
                    break
                tau = (jp + uniform(s)) * dt
                if from_timer:
                    on = uniform(s) < timer[2, g]
                    new_st = _quiet_count(table, itable, o, n_s, o + int(st), uniform_pos(s))
                else:
                    on, new_st = draw_event(s, table, itable, o, n_s, st)
                code = (1.0 if on else 0.0) + 2.0 * (new_st + 1.0)
            if tau >= w_end:
                break
            if store and n == cap:
                full = True
                break
            pol = np.uint8(int(code) % 2)
            n_on += pol
            n_off += 1 - pol
            n = emit(out, store, n, t0_us, tau, x_pix, y_pix, pol)
            st = float(int(code) // 2 - 1)
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
        fstate[k, PEND_ON] = code
        if d_timer < math.inf:
            fstate[k, BG_NEXT] = nxt  # kept when the pending event is dropped (the photon gap is redrawn)
        mem[k] = st
        for w in range(4):
            states[k, w] = s[w]
        if full:
            return n, k
    return n, n_pix
