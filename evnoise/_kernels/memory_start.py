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
from .memory import _search_up, fill_counts
from .poisson import threshold_count
from .rng import uniform, uniform_pos
from .simulate import LAST_TAU, LAST_TRIAL, STORED

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


@kernel
def start_law(pmf_level, lo, n_s, c_on, c_off, b, k, a_on, a_off, steps, dt_s, refr_s, cum, dead):
    """A chain's start at a trial start: ``cum`` the cumulative time-stationary law of its state (unnormalised,
    as ``ROW_CUM_INIT``) and ``dead`` the probability, per state, that ``t = 0`` is in the dead time (``ROW_DEAD``)
    (:func:`evnoise.terms.memory.initial_law` of the law after ``steps`` embedded steps from ``Poisson(lam)``;
    arguments as :func:`chain_arrays`')."""
    arr = np.empty((N_ARRAYS, n_s))
    idx_on = np.empty(n_s, dtype=np.int64)
    idx_off = np.empty(n_s, dtype=np.int64)
    chain_arrays(pmf_level, lo, n_s, c_on, c_off, b, k, a_on, a_off, arr, idx_on, idx_off)
    pmf = arr[A_PMF]
    # for each j: first m past its ON prefix (idx_on(m) <= j) and its OFF suffix (idx_off(m) >= j)
    a = np.empty(n_s, dtype=np.int64)
    bb = np.empty(n_s, dtype=np.int64)
    i_a = 0
    i_b = 0
    for j in range(n_s):
        while i_a < n_s and idx_on[i_a] <= j:
            i_a += 1
        a[j] = i_a
        while i_b < n_s and idx_off[i_b] < j:
            i_b += 1
        bb[j] = i_b
    p = np.empty(n_s)
    inv_p = np.empty(n_s)
    for s in range(n_s):
        p[s] = arr[A_P_ON, s] + arr[A_P_OFF, s]
        inv_p[s] = 1.0 / p[s] if p[s] > 0.0 else 0.0
    # one step x -> x T, _after's ON and OFF laws added: per j, the fresh branches and the background's fresh-quiet
    # trials times the total weight W, the stored branches over the m whose ranges reach j, the background's
    # stored-quiet trials over the m in [a, b)
    a_all = a_on + a_off
    fk = np.empty((n_s, 4))  # a row per state: the four weights one j reads
    for j in range(n_s):
        fk[j, 0] = arr[A_FRESH_ON, j] + arr[A_FRESH_OFF, j] + a_all * arr[A_NONE, j]
        fk[j, 1] = k * pmf[j]
        fk[j, 2] = a_all * k * pmf[j] if bb[j] > a[j] else 0.0
        fk[j, 3] = 0.0 if p[j] > 0.0 else 1.0  # a state that never fires keeps its mass
    total_pmf = 0.0
    for s in range(n_s):
        total_pmf += pmf[s]
    x = np.empty(n_s)
    c = np.empty(n_s + 1)  # c[i]: the weights x / P of the states below i
    c[0] = 0.0
    for s in range(n_s):
        x[s] = pmf[s] / total_pmf
        c[s + 1] = c[s] + x[s] * inv_p[s]
    x_new = np.empty(n_s)
    for _ in range(steps):
        w_all = c[n_s]
        total = 0.0
        for j in range(n_s):
            ca = c[a[j]]
            cb = c[bb[j]]
            # ca + (W - cb), not (ca + W) - cb: W can be 1e11 times ca (states with P(m) ~ 1e-11)
            v = fk[j, 0] * w_all + fk[j, 1] * (ca + (w_all - cb)) + fk[j, 2] * (cb - ca) + fk[j, 3] * x[j]
            x_new[j] = v
            total += v
        if not total > 0.0:  # the law vanished: Poisson(lam), as it started (and stays)
            for s in range(n_s):
                x[s] = pmf[s] / total_pmf
            break
        same = True
        inv_total = 1.0 / total
        for s in range(n_s):  # normalised, and the next step's sums
            v = x_new[s] * inv_total
            same = same and v == x[s]
            x[s] = v
            c[s + 1] = c[s] + v * inv_p[s]
        if same:  # a fixed point in floating point: every further step gives this law again
            break
    # the time-stationary law at a trial start (initial_law): pi E[T_m], or pi on absorbing states
    absorbed = False
    pi_total = 0.0
    for s in range(n_s):
        x[s] = max(x[s], 0.0)
        pi_total += x[s]
    if not pi_total > 0.0:
        for s in range(n_s):
            x[s] = pmf[s]
    for s in range(n_s):
        if x[s] > 0.0 and not p[s] > 0.0:
            absorbed = True
    weight_total = 0.0
    for s in range(n_s):
        if absorbed:
            wt = x[s] if not p[s] > 0.0 else 0.0
        else:
            wt = x[s] * (refr_s / dt_s + 1.0 / p[s]) if p[s] > 0.0 else 0.0
        x_new[s] = wt
        weight_total += wt
        dead[s] = refr_s * p[s] / (refr_s * p[s] + dt_s) if p[s] > 0.0 else 0.0
    acc = 0.0
    for s in range(n_s):
        acc += x_new[s] / weight_total
        cum[s] = acc


@kernel
def chain_rates(pmf, level, lo, n_s, at, c_on, c_off, a_on, a_off, b, k, dt_s, refr_s, out):
    """Each chain's rate estimate (events/s; :func:`evnoise.terms.memory.kernel_tables`' for many chains: the
    states weighted by ``Poisson(lam)``), which sizes windows and buffers, into ``out``.

    Chain ``g`` is at light level ``level[g]``, whose states are ``lo[l] ..`` (``n_s[l]`` of them) and whose
    :func:`level_pmf` is ``pmf[at[l]:at[l] + n_s[l]]``; ``c_*``, ``a_*``: per chain, as :func:`chain_arrays`'."""
    for g in range(level.size):
        lv = level[g]
        n = n_s[lv]
        arr = np.empty((N_ARRAYS, n))
        idx_on = np.empty(n, dtype=np.int64)
        idx_off = np.empty(n, dtype=np.int64)
        chain_arrays(pmf[at[lv]:at[lv] + n], lo[lv], n, c_on[g], c_off[g], b, k, a_on[g], a_off[g], arr, idx_on,
                     idx_off)
        mean_p = 0.0
        for s in range(n):
            mean_p += arr[A_PMF, s] * min(arr[A_P_ON, s] + arr[A_P_OFF, s], 1.0)
        out[g] = mean_p / (dt_s + mean_p * refr_s)


@kernel
def start_pixels(pmf, level, lo, n_s, at, c_on, c_off, a_on, a_off, b, k, steps, dt_s, refr_s, dt_us, refr_us, chains,
                 first, members, states, fstate):
    """Start the pixels of the chains ``chains`` (indices into the per-chain arrays) in their steady state.

    The pixels of ``chains[i]`` are ``members[first[i]:first[i + 1]]`` (rows of ``states`` and ``fstate``); the
    chains' arrays as :func:`chain_rates`'. Each
    draws its state and dead time from its own stream as :func:`evnoise._kernels.memory.draw_initial` does, and
    stores them as :func:`evnoise._kernels.memory.initial_stored` does (no regular timer: the caller refuses it).
    ``dt_s``, ``refr_s``: the trial and the refractory period for the law (as the tables'), ``dt_us``, ``refr_us``:
    for the draws (as the trial kernel's).
    """
    for i in range(chains.size):
        g = chains[i]
        lv = level[g]
        n = n_s[lv]
        cum = np.empty(n)
        dead = np.empty(n)
        start_law(pmf[at[lv]:at[lv] + n], lo[lv], n, c_on[g], c_off[g], b, k, a_on[g], a_off[g], steps, dt_s, refr_s,
                  cum, dead)
        s = np.empty(4, dtype=np.uint64)
        for q in range(first[i], first[i + 1]):
            r = members[q]
            for w in range(4):
                s[w] = states[r, w]
            st = _search_up(cum, 0, n - 1, uniform_pos(s) * cum[n - 1])
            fstate[r, STORED] = lo[lv] + st
            if uniform(s) < dead[st]:
                elapsed = uniform_pos(s) * refr_us
                if elapsed > 0.0:
                    fstate[r, LAST_TAU] = -elapsed
                    fstate[r, LAST_TRIAL] = np.floor(-elapsed / dt_us)
            for w in range(4):
                states[r, w] = s[w]
