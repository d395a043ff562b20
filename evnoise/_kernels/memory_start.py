"""Steady-state starts of reset-memory pixels computed chain by chain, without keeping the chains' tables.

The trial tier (:func:`evnoise._kernels.simulate.trial_window`) reads of a reset-memory pixel's chain only its
start: the stored count at ``t = 0`` and whether ``t = 0`` falls in the dead time after its last event
(:func:`evnoise._kernels.memory.initial_stored` draws them from the tables of
:func:`evnoise.terms.memory.kernel_tables`). A scene whose tables would pass
:data:`evnoise.terms.memory.MAX_TABLE_STATES` (a megapixel sensor with threshold mismatch: nearly a chain per pixel)
runs in the trial tier with its starts from here. Per chain this computes what the table path computes for a run
of many chains, in the same order of operations: the chain's arrays of :func:`evnoise.terms.memory.level_tables`
(:func:`chain_arrays`), ``steps`` steps of the embedded chain from ``Poisson(lam)``
(:func:`evnoise.terms.memory._embedded_iterate`), the time-stationary law and dead-time probability of
:func:`evnoise.terms.memory.initial_law`; then each of the chain's pixels draws its start as
:func:`evnoise._kernels.memory.draw_initial` does, from its own stream (so the starts do not depend on how the
chains are cut into chunks for threads). Sums are sequential here where NumPy's are pairwise (and one step's two laws
are added as they are made), so laws agree with the table path's to rounding (~1e-16), not bit for bit. Memory: a
few arrays of the chain's states per thread; nothing is kept but the pixels' starts.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import kernel
from .memory import draw_start, fill_counts, store_start
from .poisson import threshold_count

#: Arrays of one chain in :func:`chain_arrays`' scratch ``(N_ARRAYS, S)``.
(A_PMF, A_HEAD, A_TAIL, A_FRESH_ON, A_FRESH_OFF, A_NONE, A_P_ON, A_P_OFF) = range(8)
N_ARRAYS = 8


@kernel
def _count_le(x, lo, n_s):
    """How many of the states ``lo .. lo + n_s - 1`` are ``<= x`` (``x`` a count, or ``inf``)."""
    if x < lo:
        return 0
    if x >= lo + n_s - 1:
        return n_s
    return int(np.floor(x) - lo) + 1


@kernel
def level_pmf(lam, lo, n_s, out):
    """``P(N = m)`` for ``N ~ Poisson(lam)`` at the states ``m = lo .. lo + n_s - 1`` (as the tables':
    ``exp`` of :func:`evnoise._kernels.memory.fill_counts`' log), into ``out``."""
    log_p = np.empty(n_s)
    scratch = np.empty(n_s)
    fill_counts(lam, lo, n_s, 0.0, 0.0, 0.0, log_p, scratch, scratch)
    for s in range(n_s):
        out[s] = math.exp(log_p[s])


@kernel
def chain_arrays(pmf_level, lo, n_s, c_on, c_off, b, k, a_on, a_off, arr, idx_on, idx_off):
    """One chain's arrays (:func:`evnoise.terms.memory.level_tables` and ``LevelTables.probabilities``): rows
    ``A_*`` of ``arr`` ``(N_ARRAYS, >= n_s)`` and the indices ``idx_on``, ``idx_off``; ``pmf_level`` is its light
    level's :func:`level_pmf`, ``c_*`` are ``expm1(eps_*)``, ``b`` the bias, ``k`` the reset memory, ``a_*`` the
    per-trial background probabilities."""
    k_on = np.empty(n_s)
    k_off = np.empty(n_s)
    for s in range(n_s):
        k_on[s] = threshold_count(lo + s, c_on, b)
        k_off[s] = threshold_count(lo + s, c_off, b)
    pmf = arr[A_PMF]
    head = arr[A_HEAD]
    tail = arr[A_TAIL]
    acc = 0.0
    for s in range(n_s):
        pmf[s] = pmf_level[s]
        acc += pmf[s]
        head[s] = acc
    acc = 0.0
    for s in range(n_s - 1, -1, -1):
        acc += pmf[s]
        tail[s] = acc
    i_off = 0
    i_on = 0
    for s in range(n_s):
        m = lo + s
        idx_on[s] = _count_le(k_on[s], lo, n_s)  # first state above m's ON threshold
        while i_off < n_s and k_off[i_off] < m:  # k_off nondecreasing: last j with k_off(j) < m
            i_off += 1
        idx_off[s] = i_off - 1
        while i_on < n_s and k_on[i_on] < m:  # P(k_on(N0) < m): the fresh reference beaten upwards
            i_on += 1
        beaten_on = head[i_on - 1] if i_on > 0 else 0.0
        c = _count_le(k_off[s], lo, n_s)  # P(N0 > k_off(m))
        beaten_off = tail[c] if c < n_s else 0.0
        arr[A_FRESH_ON, s] = (1.0 - k) * pmf[s] * beaten_on
        arr[A_FRESH_OFF, s] = (1.0 - k) * pmf[s] * beaten_off
        arr[A_NONE, s] = (1.0 - k) * pmf[s] * max(head[n_s - 1] - beaten_on - beaten_off, 0.0)
    p_fresh_on = 0.0
    p_fresh_off = 0.0
    for s in range(n_s):
        p_fresh_on += arr[A_FRESH_ON, s]
        p_fresh_off += arr[A_FRESH_OFF, s]
    background = a_on != 0.0 or a_off != 0.0
    for s in range(n_s):
        stored_on = k * (tail[idx_on[s]] if idx_on[s] < n_s else 0.0)
        stored_off = k * (head[idx_off[s]] if idx_off[s] >= 0 else 0.0)
        photon_on = p_fresh_on + stored_on
        photon_off = p_fresh_off + stored_off
        if background:
            quiet = 1.0 - min(p_fresh_on + stored_on + p_fresh_off + stored_off, 1.0)
            photon_on += quiet * a_on
            photon_off += quiet * a_off
        arr[A_P_ON, s] = photon_on
        arr[A_P_OFF, s] = photon_off


#: Chains of one light level iterated together (interleaved: their sums' dependency chains overlap).
INTERLEAVE = 4


@kernel
def _prepare(pmf_level, lo, n_s, c_on, c_off, b, k, a_on, a_off, fk, a, bb, p, inv_p):
    """What one step of a chain's embedded law reads (:func:`_iterate`): per state ``j`` the four weights ``fk[j]``,
    the first ``m`` past ``j``'s ON prefix (``a``: ``idx_on(m) <= j``) and OFF suffix (``bb``: ``idx_off(m) >= j``),
    and the event probabilities ``p`` and ``1 / p`` (0 where ``p = 0``). Arguments as :func:`chain_arrays`'."""
    arr = np.empty((N_ARRAYS, n_s))
    idx_on = np.empty(n_s, dtype=np.int64)
    idx_off = np.empty(n_s, dtype=np.int64)
    chain_arrays(pmf_level, lo, n_s, c_on, c_off, b, k, a_on, a_off, arr, idx_on, idx_off)
    i_a = 0
    i_b = 0
    for j in range(n_s):
        while i_a < n_s and idx_on[i_a] <= j:
            i_a += 1
        a[j] = i_a
        while i_b < n_s and idx_off[i_b] < j:
            i_b += 1
        bb[j] = i_b
    for s in range(n_s):
        p[s] = arr[A_P_ON, s] + arr[A_P_OFF, s]
        inv_p[s] = 1.0 / p[s] if p[s] > 0.0 else 0.0
    # one step x -> x T, _after's ON and OFF laws added: per j, the fresh branches and the background's fresh-quiet
    # trials times the total weight W, the stored branches over the m whose ranges reach j, the background's
    # stored-quiet trials over the m in [a, b)
    a_all = a_on + a_off
    for j in range(n_s):
        fk[j, 0] = arr[A_FRESH_ON, j] + arr[A_FRESH_OFF, j] + a_all * arr[A_NONE, j]
        fk[j, 1] = k * pmf_level[j]
        fk[j, 2] = a_all * k * pmf_level[j] if bb[j] > a[j] else 0.0
        fk[j, 3] = 0.0 if p[j] > 0.0 else 1.0  # a state that never fires keeps its mass


@kernel
def _iterate(pmf_level, n_s, fk, a, bb, inv_p, steps, x, from_x=False):
    """``steps`` steps of the embedded laws of ``G`` chains of one level (``fk`` ``(n_s, G, 4)``, ``a``, ``bb``,
    ``inv_p`` ``(n_s, G)``: :func:`_prepare`'s), each from ``Poisson(lam)`` (``from_x``: from the normalised laws in
    ``x``), into ``x`` ``(n_s, G)`` (normalised).

    The chains are interleaved, each computed exactly as alone: a chain whose law vanished takes ``Poisson(lam)``
    and stays there, one at a fixed point in floating point (a step that changes nothing) stops there (every further
    step gives it again); the others go on."""
    g_n = x.shape[1]
    total_pmf = 0.0
    for s in range(n_s):
        total_pmf += pmf_level[s]
    c = np.empty((n_s + 1, g_n))  # c[i, g]: chain g's weights x / P of the states below i
    x_new = np.empty((n_s, g_n))
    w_all = np.empty(g_n)
    total = np.empty(g_n)
    inv_total = np.empty(g_n)
    live = np.ones(g_n, dtype=np.bool_)
    changed = np.empty(g_n, dtype=np.bool_)
    for g in range(g_n):
        c[0, g] = 0.0
    for s in range(n_s):
        for g in range(g_n):
            if not from_x:
                x[s, g] = pmf_level[s] / total_pmf
            c[s + 1, g] = c[s, g] + x[s, g] * inv_p[s, g]
    for _ in range(steps):
        for g in range(g_n):
            w_all[g] = c[n_s, g]
            total[g] = 0.0
        for j in range(n_s):
            for g in range(g_n):
                ca = c[a[j, g], g]
                cb = c[bb[j, g], g]
                # ca + (W - cb), not (ca + W) - cb: W can be 1e11 times ca (states with P(m) ~ 1e-11)
                v = (fk[j, g, 0] * w_all[g] + fk[j, g, 1] * (ca + (w_all[g] - cb)) + fk[j, g, 2] * (cb - ca)
                     + fk[j, g, 3] * x[j, g])
                x_new[j, g] = v
                total[g] += v
        for g in range(g_n):
            changed[g] = False
            if live[g]:
                if not total[g] > 0.0:  # the law vanished: Poisson(lam), as it started (and stays)
                    live[g] = False
                    for s in range(n_s):
                        x[s, g] = pmf_level[s] / total_pmf
                inv_total[g] = 1.0 / total[g]
        for s in range(n_s):  # normalised, and the next step's sums
            for g in range(g_n):
                if live[g]:
                    v = x_new[s, g] * inv_total[g]
                    if v != x[s, g]:
                        changed[g] = True
                    x[s, g] = v
                    c[s + 1, g] = c[s, g] + v * inv_p[s, g]
        any_live = False
        for g in range(g_n):
            live[g] = live[g] and changed[g]  # a fixed point: every further step gives this law again
            any_live = any_live or live[g]
        if not any_live:
            break


@kernel
def _finish(x, p, pmf_level, n_s, dt_s, refr_s, cum, dead):
    """:func:`evnoise.terms.memory.initial_law` of an embedded law ``x`` (changed in place): ``cum`` the cumulative
    time-stationary law of the state at a trial start (unnormalised, as ``ROW_CUM_INIT``), ``dead`` the probability,
    per state, that ``t = 0`` is in the dead time (``ROW_DEAD``)."""
    absorbed = False
    pi_total = 0.0
    for s in range(n_s):
        x[s] = max(x[s], 0.0)
        pi_total += x[s]
    if not pi_total > 0.0:
        for s in range(n_s):
            x[s] = pmf_level[s]
    for s in range(n_s):
        if x[s] > 0.0 and not p[s] > 0.0:
            absorbed = True
    weight = np.empty(n_s)
    weight_total = 0.0
    for s in range(n_s):
        if absorbed:
            wt = x[s] if not p[s] > 0.0 else 0.0
        else:
            wt = x[s] * (refr_s / dt_s + 1.0 / p[s]) if p[s] > 0.0 else 0.0
        weight[s] = wt
        weight_total += wt
        dead[s] = refr_s * p[s] / (refr_s * p[s] + dt_s) if p[s] > 0.0 else 0.0
    acc = 0.0
    for s in range(n_s):
        acc += weight[s] / weight_total
        cum[s] = acc


@kernel
def _block(pmf, level, lo, n_s, at, c_on, c_off, a_on, a_off, b, k, steps, chains, i, rate_tol=0.0, max_steps=0):
    """The chains ``chains[i:]`` of ``chains[i]``'s light level, at most :data:`INTERLEAVE` of them: their embedded
    laws after ``steps`` steps from ``Poisson(lam)`` (:func:`_iterate`), ``(g_n, x (n_s, g_n), p (g_n, n_s), lv)``
    (``p``: per-trial event probabilities; the arguments as :func:`start_pixels`'); with ``rate_tol`` more steps as
    :func:`chain_rates` says."""
    lv = level[chains[i]]
    g_n = 1
    while g_n < INTERLEAVE and i + g_n < chains.size and level[chains[i + g_n]] == lv:
        g_n += 1
    n = n_s[lv]
    pmf_level = pmf[at[lv]:at[lv] + n]
    fk = np.empty((n, g_n, 4))
    a = np.empty((n, g_n), dtype=np.int64)
    bb = np.empty((n, g_n), dtype=np.int64)
    p = np.empty((g_n, n))
    inv_p = np.empty((n, g_n))
    fk_q = np.empty((n, 4))
    a_q = np.empty(n, dtype=np.int64)
    bb_q = np.empty(n, dtype=np.int64)
    one = np.empty(n)
    for q in range(g_n):
        g = chains[i + q]
        _prepare(pmf_level, lo[lv], n, c_on[g], c_off[g], b, k, a_on[g], a_off[g], fk_q, a_q, bb_q, p[q], one)
        for j in range(n):
            for col in range(4):
                fk[j, q, col] = fk_q[j, col]
            a[j, q] = a_q[j]
            bb[j, q] = bb_q[j]
            inv_p[j, q] = one[j]
    x = np.empty((n, g_n))
    _iterate(pmf_level, n, fk, a, bb, inv_p, steps, x)
    if rate_tol > 0.0:  # more steps, RATE_STEPS at a time, until every chain's trials per event settle
        done = steps
        before = _trials_per_event(x, p)
        while done < max_steps:
            _iterate(pmf_level, n, fk, a, bb, inv_p, RATE_STEPS, x, True)
            done += RATE_STEPS
            after = _trials_per_event(x, p)
            settled = True
            for q in range(g_n):
                settled = settled and abs(after[q] - before[q]) <= rate_tol * after[q]
            before = after
            if settled:
                break
    return g_n, x, p, lv


@kernel
def _trials_per_event(x, p):
    """``sum x / P`` of each chain's embedded law (columns of ``x``; states that never fire left out)."""
    out = np.zeros(x.shape[1])
    for q in range(x.shape[1]):
        for j in range(x.shape[0]):
            if p[q, j] > 0.0:
                out[q] += x[j, q] / p[q, j]
    return out


#: Embedded steps between two looks at a chain's rate estimate (:func:`chain_rates`) ...
RATE_STEPS = 5
#: ... which stops when the mean trials per event moved by less than this share over those steps.
RATE_TOL = 1e-3


@kernel
def chain_rates(pmf, level, lo, n_s, at, c_on, c_off, a_on, a_off, b, k, dt_s, refr_s, max_steps, chains, out):
    """The rate estimates (events/s) of the chains ``chains`` into ``out[chains]``: ``1 / (R + dt sum x / P)`` (the
    stationary rate's formula, :func:`evnoise.terms.memory.level_statistics`; absorbing states left out) of the
    embedded law ``x`` after :data:`RATE_STEPS` steps from ``Poisson(lam)`` and as many more as it takes the mean
    trials per event to move by less than :data:`RATE_TOL` over :data:`RATE_STEPS` steps, at most ``max_steps`` (the
    starts' law). An estimate (a slow-mixing chain can still be moving): it sizes windows and buffers and is what a
    run says it expects. Arguments as :func:`start_pixels`'."""
    i = 0
    while i < chains.size:
        g_n, x, p, lv = _block(pmf, level, lo, n_s, at, c_on, c_off, a_on, a_off, b, k, RATE_STEPS, chains, i,
                               RATE_TOL, max_steps)
        trials = _trials_per_event(x, p)
        for q in range(g_n):
            out[chains[i + q]] = 1.0 / (refr_s + dt_s * trials[q]) if trials[q] > 0.0 else 0.0
        i += g_n


@kernel
def start_pixels(pmf, level, lo, n_s, at, c_on, c_off, a_on, a_off, b, k, steps, dt_s, refr_s, dt_us, refr_us, chains,
                 first, members, states, fstate):
    """Start the pixels of the chains ``chains`` (indices into the per-chain arrays) in their steady state.

    Chain ``g`` is at light level ``level[g]``, whose states are ``lo[l] ..`` (``n_s[l]`` of them) and whose
    :func:`level_pmf` is ``pmf[at[l]:at[l] + n_s[l]]``; ``c_*``, ``a_*``: per chain, as :func:`chain_arrays`'. The
    chains of a level are adjacent in ``chains`` (they are iterated together, :func:`_block`). The pixels of
    ``chains[i]`` are ``members[first[i]:first[i + 1]]`` (rows of ``states`` and ``fstate``). Each draws its state
    and dead time from its own stream as :func:`evnoise._kernels.memory.draw_initial` does, and stores them as
    :func:`evnoise._kernels.memory.initial_stored` does (no regular timer: the caller refuses it).
    ``dt_s``, ``refr_s``: the trial and the refractory period for the law (as the tables'), ``dt_us``, ``refr_us``:
    for the draws (as the trial kernel's).
    """
    s = np.empty(4, dtype=np.uint64)
    i = 0
    while i < chains.size:
        g_n, x, p, lv = _block(pmf, level, lo, n_s, at, c_on, c_off, a_on, a_off, b, k, steps, chains, i)
        n = n_s[lv]
        pmf_level = pmf[at[lv]:at[lv] + n]
        one = np.empty(n)
        cum = np.empty(n)
        dead = np.empty(n)
        for q in range(g_n):
            for j in range(n):
                one[j] = x[j, q]
            _finish(one, p[q], pmf_level, n, dt_s, refr_s, cum, dead)
            for r_i in range(first[i + q], first[i + q + 1]):
                r = members[r_i]
                for w in range(4):
                    s[w] = states[r, w]
                st, elapsed = draw_start(s, cum, dead, n, refr_us)
                store_start(fstate, r, lo[lv] + st, elapsed, dt_us)
                for w in range(4):
                    states[r, w] = s[w]
        i += g_n
