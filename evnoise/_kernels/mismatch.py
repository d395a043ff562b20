"""Numba kernels of threshold mismatch: the exact distribution of the event probability across pixels (calibration),
and the counts of pixels with their own thresholds decided by brackets (:mod:`evnoise._bracket`, the second part
of this module: level tables, lattice sums, and the pass over the pixels that runs the renewal kernel's draws at
both ends of each pixel's bracket).

With a per-pixel threshold ``eps ~ N(mu, s)`` truncated to ``eps > 0`` (the model of
:func:`evnoise.draw_thresholds`), the per-trial probability of a pixel,

    p(eps) = sum_{n, m} Pois(n; lam) Pois(m; lam) [eps < L_nm],   L_nm = log1p((n - m) / (m + b)),

is a *step function* of ``eps``: it only changes where ``eps`` crosses one of the breakpoints
``L_nm`` (the event condition ``n + b > e^eps (m + b)`` written for ``eps``). Its distribution
across pixels is therefore discrete and can be computed exactly: sort the breakpoints, and
between two consecutive ones ``p`` is constant and has the normal probability of that
interval. Nothing is approximated except dropping pairs ``(n, m)`` whose largest possible
contribution ``w_nm P(eps < L_nm)`` is below ``e^-50`` of a lower bound on the mean (their total
is far below 1e-16 of it), and lumping pairs whose breakpoint lies more than ``9 s`` above
``mu`` into a constant (their indicator is 1 for all but a ``1e-19`` fraction of pixels). With
more than ``_BIN_ABOVE`` steps (``lam`` of a few hundred and more) the mean is still summed
exactly pair by pair, but for the rest of the distribution the steps are gathered into bins
``s / 1024`` wide instead of sorted (each step moves by less than ``s / 2048``). The cost grows
like ``lam``: about 0.1 ms at ``lam ~ 1``, 1 ms at ``lam ~ 20``, a few ms at ``lam ~ 1000``. The
pairs are not stored: they are visited once to count them and find their range, then again to store
the few or bin the many, so memory stays at the photon-count window and the bins (storing every pair
took 2.1 GB at ``lam ~ 2e5``, evk4 at 3000 lux, and failed at 10,000 lux). The number of pairs grows like
``s lam^1.5`` (1e8 .. 1e9 at ``lam ~ 1e5 .. 1e6``: 50 s and 280 s with evk4 at 3000 and 10,000 lux), so at large
``lam`` :func:`threshold_atoms_grid` brackets ``p`` on a grid of thresholds instead (the middle part of this module;
the choice is :func:`evnoise.mismatch.uses_threshold_grid`).

Everything is in scaled arithmetic (values relative to ``exp(ref)``), so tiny probabilities
do not underflow. Unit-free, no checking: the checked entry points are in
:mod:`evnoise.mismatch`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ._jit import kernel
from .bounds import chernoff_bracket
from .poisson import log_event_probability_exact, log_pmf, log_sf, logaddexp, pmf_run, threshold_count
from .rng import seed_state, uniform, uniform_pos
from .simulate import first_eligible_trial

_SQRT1_2 = 1.0 / math.sqrt(2.0)
_LUMP_X = 9.0  # breakpoints more than this many sigma above mu count as +inf
_CUT = 50.0  # pairs with weight below exp(-_CUT) of the lower bound on the mean are dropped
LOG_ZERO = -1.0e4  # stands for log(0) in atom tables (exp underflows to exactly 0)
_BIN_ABOVE = 20000  # more steps than this: gather them into bins instead of sorting
_BIN_PER_SIGMA = 1024.0


@kernel
def phi_interval(xa, xb):
    """``P(xa < Z < xb)`` for a standard normal ``Z``, without cancellation (``xa <= xb``)."""
    if xa >= 0.0:
        return 0.5 * (math.erfc(xa * _SQRT1_2) - math.erfc(xb * _SQRT1_2))
    if xb <= 0.0:
        return 0.5 * (math.erfc(-xb * _SQRT1_2) - math.erfc(-xa * _SQRT1_2))
    return 1.0 - 0.5 * math.erfc(-xa * _SQRT1_2) - 0.5 * math.erfc(xb * _SQRT1_2)


@kernel
def _window(lam, thr):
    """Integer range ``[lo, hi]`` of counts ``k`` with ``log Pois(k; lam) >= thr``."""
    mode = math.floor(lam)
    lo = mode
    while lo > 0.0 and log_pmf(lo - 1.0, lam) >= thr:
        lo -= 1.0
    hi = mode
    while log_pmf(hi + 1.0, lam) >= thr:
        hi += 1.0
    return lo, hi


@kernel
def _pair_pass(mode, lpmf, first, lo, size, lam, b, mu, s, cut, lp_max, ref, x0, brk, wts, acc, lo_l, width, m1):
    """One visit of the pairs ``(n, m)`` that can matter (:func:`threshold_atoms`), in one fixed order.

    ``mode`` 0 counts the breakpoints kept and returns their range and the lumped weight; 1 stores them
    in ``brk``, ``wts``; 2 adds each weight to its bin of ``acc`` (``width`` wide from ``lo_l``) and to
    ``m1`` (started at the lumped weight) times the probability of a threshold below the breakpoint.
    Returns ``(count, lumped, smallest, largest breakpoint, m1)``.
    """
    count = 0
    lumped = 0.0
    lmin = math.inf
    lmax = -math.inf
    for i in range(size):
        m = lo + i
        if lpmf[i] + lp_max < cut:
            continue
        for j in range(first[i], size):
            lw = lpmf[i] + lpmf[j]
            if lw < cut:
                if lo + j > lam:
                    break
                continue
            n = lo + j
            if m + b > 0.0:
                L = math.log1p((n - m) / (m + b))
            else:
                L = math.inf
            if (L - mu) / s > _LUMP_X:
                if mode == 0:
                    lumped += math.exp(lw - ref)
                continue
            if mode == 0:
                lmin = min(lmin, L)
                lmax = max(lmax, L)
            elif mode == 1:
                brk[count] = L
                wts[count] = math.exp(lw - ref)
            else:
                w = math.exp(lw - ref)
                m1 += w * phi_interval(x0, (L - mu) / s)
                acc[int((L - lo_l) / width)] += w
            count += 1
    return count, lumped, lmin, lmax, m1


@kernel
def threshold_atoms(lam, b, mu, s, delta):
    """Distribution of ``log p`` across pixels for ``eps ~ N(mu, s)`` truncated to ``eps > 0``.

    Parameters are plain floats: ``lam > 0`` photons per trial, ``b >= 0`` bias, ``mu > 0``
    mean threshold, ``s > 0`` its standard deviation, ``delta > 0`` the width in ``log p`` of
    the bins the atoms are merged into (mass-weighted means, so the mean of ``p`` is kept
    exactly).

    Returns
    -------
    (log_p, mass, log_m1, log_m2)
        Merged atoms (``log_p`` decreasing, ``LOG_ZERO`` for ``p = 0``) with their
        probabilities (summing to 1), and the exact ``log E[p]`` and ``log E[p^2]``.
    """
    x0 = -mu / s
    q_norm = phi_interval(x0, math.inf)  # P(eps > 0)
    # lower bound on E[p]: p(e) P(eps < e) for thresholds e from mu down to mu - 12 s, since p
    # does not increase with eps; pairs contributing far below it are negligible
    log_lb = -math.inf
    for i in range(13):
        e = mu - i * s
        if e <= 0.0:
            break
        lf = math.log(phi_interval(x0, (e - mu) / s) / q_norm)
        v = log_event_probability_exact(lam, math.expm1(e), b) + lf
        if v > log_lb:
            log_lb = v
    if log_lb < -750.0:  # E[p] is far below the smallest double: no events, ever
        out_lp = np.full(1, LOG_ZERO)
        out_mass = np.ones(1)
        return out_lp, out_mass, log_lb, 2.0 * log_lb
    # scaled arithmetic: weights (<= 1) stay below exp(700) relative to ref
    ref = max(log_lb, -700.0)
    cut = log_lb - _CUT
    lp_max = log_pmf(math.floor(lam), lam)
    lo, hi = _window(lam, cut - lp_max)
    size = int(hi - lo) + 1
    lpmf = np.empty(size)
    for i in range(size):
        lpmf[i] = log_pmf(lo + i, lam)
    log_q = math.log(q_norm)
    # first n (index) for each m whose pair can matter: w * P(eps < L_nm) >= exp(cut), with
    # P(eps < L) <= Phi((L - mu) / s) / q_norm increasing in n (binary search)
    first = np.empty(size, dtype=np.int64)
    for i in range(size):
        m = lo + i
        need = cut - lpmf[i] - lp_max + log_q
        a = i + 1
        z = size
        while a < z:
            mid = (a + z) // 2
            n = lo + mid
            if m + b > 0.0:
                x = (math.log1p((n - m) / (m + b)) - mu) / s
                phi = 0.5 * math.erfc(-x * _SQRT1_2)
                ok = phi > 0.0 and math.log(phi) >= need
            else:
                ok = True
            if ok:
                z = mid
            else:
                a = mid + 1
        first[i] = a
    # the pairs are visited twice instead of stored: once to count them (and find their range), then to
    # store them (few) or gather them into bins (many); storing every pair took 2 GB at lam ~ 2e5
    none = np.empty(0)
    count, lumped, lo_l, hi_l, _ = _pair_pass(0, lpmf, first, lo, size, lam, b, mu, s, cut, lp_max, ref, x0,
                                              none, none, none, 0.0, 1.0, 0.0)
    exact_m1 = math.nan
    if count > _BIN_ABOVE:
        # many steps (large lam): the mean is summed exactly, pair by pair; for the rest the
        # breakpoints are gathered into bins s / _BIN_PER_SIGMA wide (each moved by at most half
        # a bin), which replaces a sort of all pairs by a histogram
        width = s / _BIN_PER_SIGMA
        nb = int((hi_l - lo_l) / width) + 1
        acc = np.zeros(nb)
        exact_m1 = _pair_pass(2, lpmf, first, lo, size, lam, b, mu, s, cut, lp_max, ref, x0, none, none, acc,
                              lo_l, width, lumped)[4]
        exact_m1 /= q_norm
        nz = 0
        for i in range(nb):
            if acc[i] > 0.0:
                nz += 1
        brk = np.empty(nz)
        wts = np.empty(nz)
        k = 0
        for i in range(nb):
            if acc[i] > 0.0:
                brk[k] = lo_l + (i + 0.5) * width
                wts[k] = acc[i]
                k += 1
        count = nz
    else:
        brk = np.empty(count)
        wts = np.empty(count)
        _pair_pass(1, lpmf, first, lo, size, lam, b, mu, s, cut, lp_max, ref, x0, brk, wts, none, 0.0, 1.0, 0.0)
    order = np.argsort(brk)
    brk = brk[order]
    wts = wts[order]
    # suffix sums: value of p on [brk[k-1], brk[k]) is lumped + sum_{j >= k} wts[j]
    val = np.empty(count + 1)
    val[count] = lumped
    for k in range(count - 1, -1, -1):
        val[k] = val[k + 1] + wts[k]
    mass = np.empty(count + 1)
    xa = x0
    for k in range(count + 1):
        xb = (brk[k] - mu) / s if k < count else math.inf
        mass[k] = phi_interval(xa, xb) / q_norm
        xa = xb
    vmax = val[0]
    m1 = 0.0
    m2 = 0.0
    if vmax > 0.0:
        for k in range(count + 1):
            m1 += val[k] * mass[k]
            v = val[k] / vmax
            m2 += v * v * mass[k]
    if exact_m1 == exact_m1:  # not NaN: binned steps, exact mean from the pairs
        m1 = exact_m1
    log_m1 = ref + math.log(m1) if m1 > 0.0 else -math.inf
    log_m2 = 2.0 * (ref + math.log(vmax)) + math.log(m2) if m2 > 0.0 else -math.inf
    # merge consecutive atoms (val is non-increasing in k) into bins of width delta in log p
    out_lp = np.empty(count + 1)
    out_mass = np.empty(count + 1)
    n_out = 0
    k = 0
    while k <= count:
        if mass[k] <= 0.0:
            k += 1
            continue
        if val[k] <= 0.0:  # p = 0 from here on (eps above every breakpoint)
            acc_m = 0.0
            while k <= count:
                acc_m += mass[k]
                k += 1
            out_lp[n_out] = LOG_ZERO
            out_mass[n_out] = acc_m
            n_out += 1
            break
        top = math.log(val[k])
        acc_m = mass[k]
        acc_v = mass[k] * val[k]
        k += 1
        while k <= count and val[k] > 0.0 and top - math.log(val[k]) < delta:
            acc_m += mass[k]
            acc_v += mass[k] * val[k]
            k += 1
        out_lp[n_out] = ref + math.log(acc_v / acc_m)
        out_mass[n_out] = acc_m
        n_out += 1
    total = 0.0
    for i in range(n_out):
        total += out_mass[i]
    for i in range(n_out):
        out_mass[i] /= total
    return out_lp[:n_out].copy(), out_mass[:n_out].copy(), log_m1, log_m2


@kernel
def mean_probability_double_sum(lam, b, mu, s, n_max):
    """``E[p]`` by the plain double sum ``sum_{n > m} Pois(n) Pois(m) P(0 < eps < L_nm)``.

    An independent, obviously-correct route to the mean (no sorting, no lumping); linear
    arithmetic over ``0 <= m < n <= n_max``, so only for moderate ``lam`` and ``p`` not tiny.
    """
    x0 = -mu / s
    q_norm = phi_interval(x0, math.inf)
    total = 0.0
    for m in range(int(n_max) + 1):
        wm = math.exp(log_pmf(float(m), lam))
        for n in range(m + 1, int(n_max) + 1):
            w = wm * math.exp(log_pmf(float(n), lam))
            if m + b > 0.0:
                xb = (math.log1p((n - m) / (m + b)) - mu) / s
            else:
                xb = math.inf
            total += w * phi_interval(x0, xb)
    return total / q_norm


# --------------------------------------------------------------------------------------
# the same distribution at large lam, from p on a grid of thresholds (issue 33)
#
# Enumerating the breakpoints costs about s lam^1.5 pairs (1e8 .. 1e9 at lam ~ 1e5 .. 1e6). p is non-increasing in
# the threshold (each k(m) = m + floor(c (m + b)) grows with c = expm1(eps)), so the pixels whose threshold lies in
# a cell (t_i, t_i+1] of a grid have p in [p(t_i+1), p(t_i)]: the grid gives two-sided brackets of E[p] and E[p^2]
# and an atom per cell, from one sum per grid point (tables of log pmf and log P(N > k) shared by the grid).
# --------------------------------------------------------------------------------------
#: grid step in units of the threshold's standard deviation (the resolution of the binned breakpoints above)
GRID_PER_SIGMA = 1024.0
#: bracket ends of the grid are widened by this (relative) for the rounding of the sums at the grid points
GRID_WIDEN = 1e-9
#: the grid's lowest threshold leaves out pixels whose share of E[p] and E[p^2] is below exp(-GRID_CUT)
GRID_CUT = 40.0
#: a table sum stops once a bound on the terms left is below exp(-GRID_TOL_LOG) of the sum
GRID_TOL_LOG = 41.0
#: tables longer than this are not built (each grid point then takes the exact windowed sum)
GRID_MAX_TABLE = 1 << 23
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
# 6-point Gauss-Legendre nodes and weights on [0, 1]
_GL_U = np.array([0.033765242898423975, 0.16939530676686776, 0.3806904069584015, 0.6193095930415985,
                  0.8306046932331322, 0.966234757101576])
_GL_W = np.array([0.08566224618958517, 0.1803807865240693, 0.23395696728634552, 0.23395696728634552,
                  0.1803807865240693, 0.08566224618958517])


@kernel
def _peak(lam, c, b):
    """Roughly where ``pmf(m) P(N > k(m))`` peaks in ``m``: the mean of ``n0`` under the Chernoff tilt."""
    lo, hi = chernoff_bracket(lam, c, b, 40)
    return lam * math.exp(-(1.0 + c) * 0.5 * (lo + hi))


@kernel
def grid_tables(lam, b, c_min, c_max):
    """``(j0, lpmf, lsf)``: ``lpmf[i] = log P(M = j0 + i)``, ``lsf[i] = log P(M > j0 + i)`` for ``M ~ Poisson(lam)``
    over the counts that the sums of :func:`log_p_table` visit for ``c_min <= c <= c_max`` (empty when too long).

    The tails are summed downwards from an exact last one in scaled linear arithmetic (they only grow: relative
    error at most a few ulps per entry), so only ``log`` of each stored value is rounded."""
    width = 14.0 * math.sqrt(lam) + 64.0
    m_a = max(0.0, np.floor(_peak(lam, c_max, b) - width))
    m_b = np.ceil(_peak(lam, c_min, b) + width)
    k_b = m_b + np.floor(c_max * (m_b + b)) + width
    if not k_b - m_a + 1.0 <= GRID_MAX_TABLE:
        return 0, np.empty(0), np.empty(0)
    j0 = int(m_a)
    n = int(k_b - m_a) + 1
    lpmf = np.empty(n)
    for i in range(n):
        lpmf[i] = log_pmf(float(j0 + i), lam)
    lsf = np.empty(n)
    top = log_sf(float(j0 + n - 1), lam)
    lsf[n - 1] = top
    scale = top  # P(M > j) = v exp(scale)
    v = 1.0
    for i in range(n - 2, -1, -1):
        v += math.exp(lpmf[i + 1] - scale)
        if v > 1e100:
            scale += math.log(v)
            v = 1.0
        lsf[i] = scale + math.log(v)
    return j0, lpmf, lsf


@kernel
def scaled_add(acc, ref, lt):
    """``acc e^ref + e^lt`` kept as ``(acc, ref)``: the reference follows a term ``e^300`` larger (no overflow);
    a term ``e^-inf`` adds nothing (also before the first finite one)."""
    if lt == -math.inf:
        return acc, ref
    if ref == -math.inf:
        ref = lt
    if lt - ref > 300.0:
        acc *= math.exp(ref - lt)
        ref = lt
    return acc + math.exp(lt - ref), ref


@kernel
def log_p_table(lam, c, b, j0, lpmf, lsf):
    """``log p`` at ``c = expm1(eps)`` from the tables of :func:`grid_tables`: ``sum_m pmf(m) P(N > k(m))`` summed
    outwards from the peak until a bound on the rest is below ``exp(-GRID_TOL_LOG)`` of the sum (NaN where the
    terms run past the tables).

    The bound (as :func:`evnoise._kernels.poisson.event_probability_grouped` uses it): ``pmf(m + j) <= pmf(m)
    (lam / (m + 1))^j``, ``pmf(m - j) <= pmf(m) (m / lam)^j``; ``k(m +- j) - k(m)`` lies within ``j (1 + c) -+ 1``;
    the Poisson law is log-concave, so ``P(N > k + x) <= P(N > k) q^x`` and ``P(N > k - x) <= P(N > k) r^x``
    (``q``, ``r`` the ratios of neighbouring tails at ``k``): the rest is below a geometric series."""
    n = lpmf.shape[0]
    j1 = j0 + n - 1
    a_hi = 1.0 + c * (1.0 + 1e-8)
    a_lo = 1.0 + c * (1.0 - 1e-8)
    m0 = min(max(np.floor(_peak(lam, c, b)), float(j0)), float(j1))
    ref = -math.inf
    acc = 0.0
    m = m0
    steps = 0
    while True:  # upwards from the peak
        k = threshold_count(m, c, b)
        if not (k + 1.0 <= j1 and m <= j1):
            return math.nan
        ik = int(k) - j0
        lt = lpmf[int(m) - j0] + lsf[ik]
        acc, ref = scaled_add(acc, ref, lt)
        steps += 1
        if steps % 8 == 0:
            lq = lsf[ik + 1] - lsf[ik]
            lrho = math.log(lam / (m + 1.0)) + a_lo * lq
            if lrho < 0.0 and lt - lq + lrho - math.log(-math.expm1(lrho)) <= ref + math.log(acc) - GRID_TOL_LOG:
                break
        m += 1.0
    m = m0 - 1.0
    steps = 0
    while m >= 0.0:  # downwards
        if m < j0:
            return math.nan
        k = threshold_count(m, c, b)
        if k < j0 or k > j1:
            return math.nan
        ik = int(k) - j0
        lt = lpmf[int(m) - j0] + lsf[ik]
        acc, ref = scaled_add(acc, ref, lt)
        steps += 1
        if steps % 8 == 0 and m > 0.0:
            if ik == 0:
                if j0 > 0:
                    return math.nan
                lr = -lsf[0]  # P(N > -1) = 1
            else:
                lr = lsf[ik - 1] - lsf[ik]
            lrho = math.log(m / lam) + a_hi * lr
            if lrho < 0.0 and lt + 2.0 * lr + lrho - math.log(-math.expm1(lrho)) <= ref + math.log(acc) - GRID_TOL_LOG:
                break
        m -= 1.0
    return ref + math.log(acc)


@kernel
def log_p_thresholds(lam, b, eps, out):
    """``out[i] = log p`` at threshold ``eps[i] >= 0`` (``lam > 0``): :func:`log_p_table` on tables shared by all
    thresholds, the exact windowed sum (:func:`evnoise._kernels.poisson.log_event_probability_exact`) where the
    tables do not reach. Returns how many thresholds took the windowed sum."""
    n = eps.shape[0]
    e_min = math.inf
    e_max = 0.0
    for i in range(n):
        e_min = min(e_min, eps[i])
        e_max = max(e_max, eps[i])
    j0, lpmf, lsf = grid_tables(lam, b, math.expm1(e_min), math.expm1(e_max))
    n_exact = 0
    for i in range(n):
        c = math.expm1(eps[i])
        v = log_p_table(lam, c, b, j0, lpmf, lsf) if lpmf.shape[0] > 0 else math.nan
        if v != v:
            v = log_event_probability_exact(lam, c, b)
            n_exact += 1
        out[i] = v
    return n_exact


@kernel(parallel=True)
def _grid_log_p(lam, b, theta, j0, lpmf, lsf, out):
    """``out[i] = log p`` at threshold ``theta[i]``: :func:`log_p_table`, else the exact windowed sum (each value on
    its own, so the same whatever the number of threads)."""
    for i in prange(theta.shape[0]):
        c = math.expm1(theta[i])
        v = log_p_table(lam, c, b, j0, lpmf, lsf) if lpmf.shape[0] > 0 else math.nan
        if v != v:
            v = log_event_probability_exact(lam, c, b)
        out[i] = v


@kernel
def _log_cell(x, dx, dl):
    """``log`` of ``int_0^1 exp(dl u - x dx u - dx^2 u^2 / 2) du`` (6-point Gauss-Legendre on pieces where the
    exponent changes by at most 1/2): the Gaussian density's shape over a cell ``dx`` wide (in sigmas) from ``x``,
    times ``p`` log-linear across it (``log p`` changes by ``dl``)."""
    g = dl - x * dx
    pieces = 1 + int(abs(g) / 0.5)
    top = max(0.0, g)
    acc = 0.0
    for j in range(pieces):
        for q in range(6):
            u = (j + _GL_U[q]) / pieces
            acc += _GL_W[q] * math.exp(g * u - 0.5 * dx * dx * u * u - top)
    return top + math.log(acc / pieces)


@kernel
def threshold_atoms_grid(lam, b, mu, s, delta):
    """:func:`threshold_atoms` from ``p`` on a grid of thresholds, for large ``lam`` (cost independent of ``lam``
    but for the ``sqrt(lam)`` terms of each sum).

    The grid runs in steps of ``s / GRID_PER_SIGMA`` (the resolution of :func:`threshold_atoms`' binned
    breakpoints) from ``t_0`` to ``mu + 9 s``; ``t_0`` is 0 or the threshold below which the pixels' share of
    ``E[p]`` and ``E[p^2]`` is at most ``exp(-GRID_CUT)`` (``P(eps < t_0) <= exp(-GRID_CUT)`` times a lower bound
    on each moment, as ``p <= 1``). A cell's pixels have ``p`` between its ends' values, so

        sum_i P(cell i) p(t_i+1)  <=  E[p]  <=  sum_i P(cell i) p(t_i) + P(eps < t_0) + P(eps > mu + 9 s) p(mu + 9 s)

    (and the same for ``p^2``), each end widened by :data:`GRID_WIDEN` for the rounding of the sums (the
    bracket's width is about ``|d log p / d eps| s / GRID_PER_SIGMA`` of the moment where it is dominated: 7e-4 to
    2e-2 with ``evk4`` from 30 to 10,000 lux). Inside it, the grid's estimates take ``log p`` linear across each
    cell (integrated against the normal density by Gauss-Legendre): ``E[p^2]`` is that estimate (measured within
    about 1e-4 of the enumeration: the staircase of ``p`` between grid points limits it, not the grid step);
    ``E[p]`` is :func:`mean_probability_smooth` where that is defined and inside the bracket (measured within 1e-11
    of the enumeration at ``lam <= 6.4e4``, 1.3e-10 at ``6.4e5``), else the grid's (about 1e-4). Each cell is an
    atom (``E[p | cell]``, scaled to the mean taken), merged into bins ``delta`` wide in ``log p`` as in
    :func:`threshold_atoms`; atoms below ``LOG_ZERO`` are set to it. A pixel's ``p`` is thus represented by a
    value within its cell's bracket, a cell ``s / 1024`` wide as the binned breakpoints of :func:`threshold_atoms`.

    Returns
    -------
    (log_p, mass, log_m1, log_m2, info, n_grid)
        As :func:`threshold_atoms`, then ``info = [lo_m1, hi_m1, lo_m2, hi_m2, grid_m1, smooth_m1]``: the logs of
        the brackets' ends, the grid's estimate of ``log E[p]`` and :func:`mean_probability_smooth`'s (NaN where
        it is not defined); and the number of grid points.
    """
    x0 = -mu / s
    q_norm = phi_interval(x0, math.inf)
    log_q = math.log(q_norm)
    h = s / GRID_PER_SIGMA
    t_hi = mu + 9.0 * s
    j0, lpmf, lsf = grid_tables(lam, b, 0.0, math.expm1(t_hi + h))
    # lower bounds on E[p] and E[p^2]: p(e)^k P(0 < eps < e), p non-increasing, at e = mu, mu - s, ...
    log_lb = -math.inf
    i = 0
    while True:
        e = mu - i * s
        if e <= 0.0:
            break
        lf = math.log(phi_interval(x0, (e - mu) / s) / q_norm)
        c = math.expm1(e)
        lp_e = log_p_table(lam, c, b, j0, lpmf, lsf) if lpmf.shape[0] > 0 else math.nan
        if lp_e != lp_e:
            lp_e = log_event_probability_exact(lam, c, b)
        log_lb = max(log_lb, 2.0 * lp_e + lf)  # a lower bound on E[p^2], so also on E[p]
        i += 1
    need = log_lb - GRID_CUT
    t_lo = 0.0
    xi = 0.0
    while True:
        x = -xi
        if mu + x * s <= 0.0:
            break
        if log_ndtr(x) - log_q <= need:
            t_lo = mu + x * s
            break
        xi += 1.0
    n_cell = int(math.ceil((t_hi - t_lo) / h))
    theta = np.empty(n_cell + 1)
    for i in range(n_cell + 1):
        theta[i] = t_lo + i * h
    lp = np.empty(n_cell + 1)
    _grid_log_p(lam, b, theta, j0, lpmf, lsf, lp)
    # cells: log mass, log E[p 1_cell], log E[p^2 1_cell] (all relative to P(eps > 0))
    lmass = np.empty(n_cell + 1)
    lc1 = np.empty(n_cell + 1)
    lc2 = np.empty(n_cell + 1)
    dx = h / s
    lo1 = -math.inf
    hi1 = -math.inf
    lo2 = -math.inf
    hi2 = -math.inf
    for i in range(n_cell):
        x = (theta[i] - mu) / s
        base = math.log(dx) - 0.5 * x * x - _LOG_SQRT_2PI - log_q
        lmass[i] = base + _log_cell(x, dx, 0.0)
        dl = lp[i + 1] - lp[i]
        lc1[i] = base + lp[i] + _log_cell(x, dx, dl)
        lc2[i] = base + 2.0 * lp[i] + _log_cell(x, dx, 2.0 * dl)
        lo1 = logaddexp(lo1, lmass[i] + lp[i + 1])
        hi1 = logaddexp(hi1, lmass[i] + lp[i])
        lo2 = logaddexp(lo2, lmass[i] + 2.0 * lp[i + 1])
        hi2 = logaddexp(hi2, lmass[i] + 2.0 * lp[i])
    # above the grid: P(eps > t_hi) (below 1e-19), p at most p(t_hi)
    x = (theta[n_cell] - mu) / s
    l_top = math.log(0.5 * math.erfc(x * _SQRT1_2)) - log_q
    lmass[n_cell] = l_top
    lc1[n_cell] = l_top + lp[n_cell]
    lc2[n_cell] = l_top + 2.0 * lp[n_cell]
    hi1 = logaddexp(hi1, lc1[n_cell])
    hi2 = logaddexp(hi2, lc2[n_cell])
    # below the grid: P(0 < eps < t_lo), p at most 1 (its mass joins the first cell, at that cell's p)
    l_bot = -math.inf
    if t_lo > 0.0:
        l_bot = math.log(phi_interval(x0, (t_lo - mu) / s)) - log_q
        hi1 = logaddexp(hi1, l_bot)
        hi2 = logaddexp(hi2, l_bot)
    r1 = lc1[0] - lmass[0]
    r2 = lc2[0] - lmass[0]
    lmass[0] = logaddexp(lmass[0], l_bot)
    lc1[0] = lmass[0] + r1
    lc2[0] = lmass[0] + r2
    widen = math.log1p(GRID_WIDEN)
    lo1 -= widen
    hi1 += widen
    # the estimates; the atoms E[p | cell], merged into bins delta wide in log p (log p non-increasing)
    n_all = n_cell + 1
    m1 = -math.inf
    m2 = -math.inf
    i_peak = 0
    for i in range(n_all):
        m1 = logaddexp(m1, lc1[i])
        m2 = logaddexp(m2, lc2[i])
        if lc1[i] > lc1[i_peak]:
            i_peak = i
    m1_grid = m1
    # E[p] by the smooth double sum where it lies inside the bracket: the atoms are scaled to it
    m1_smooth = mean_probability_smooth(lam, b, mu, s, theta[min(i_peak, n_cell)])
    if lo1 <= m1_smooth <= hi1:
        m1 = m1_smooth
        for i in range(n_all):
            lc1[i] += m1_smooth - m1_grid
    info = np.array([lo1, hi1, lo2 - widen, hi2 + widen, m1_grid, m1_smooth])
    out_lp = np.empty(n_all)
    out_mass = np.empty(n_all)
    n_out = 0
    k = 0
    while k < n_all:
        top = lc1[k] - lmass[k]
        am = lmass[k]
        av = lc1[k]
        k += 1
        while k < n_all and top - (lc1[k] - lmass[k]) < delta:
            am = logaddexp(am, lmass[k])
            av = logaddexp(av, lc1[k])
            k += 1
        out_lp[n_out] = max(av - am, LOG_ZERO)
        out_mass[n_out] = am
        n_out += 1
    big = -math.inf
    for i in range(n_out):
        big = max(big, out_mass[i])
    total = 0.0
    n_keep = 0
    for i in range(n_out):  # atoms of mass below 1e-300 are left out (threshold_atoms: those that underflow)
        w = math.exp(out_mass[i] - big)
        if w > 1e-300:
            out_lp[n_keep] = out_lp[i]
            out_mass[n_keep] = w
            total += w
            n_keep += 1
    for i in range(n_keep):
        out_mass[i] /= total
    return out_lp[:n_keep].copy(), out_mass[:n_keep].copy(), m1, m2, info, n_cell + 1


@kernel
def log_ndtr(z):
    """``log Phi(z)`` for a standard normal, full relative accuracy for every finite ``z`` (``erfc`` down to
    ``z = -37``, below it the asymptotic series to ``z^-14``, whose next term is below 1e-18)."""
    if z > 0.0:
        return math.log1p(-0.5 * math.erfc(z * _SQRT1_2))
    if z > -37.0:
        return math.log(0.5 * math.erfc(-z * _SQRT1_2))
    iz2 = 1.0 / (z * z)
    ser = 1.0 + iz2 * (-1.0 + iz2 * (3.0 + iz2 * (-15.0 + iz2 * (105.0 + iz2 * (-945.0 + iz2 * (
        10395.0 - iz2 * 135135.0))))))
    return -0.5 * z * z - math.log(-z) - _LOG_SQRT_2PI + math.log(ser)


@kernel
def _log_f_inner(x, m, lam, b, mu, s, l0):
    """``log[pmf(m + x) P(0 < eps < log1p(x / (m + b)))]`` for real ``x > 0`` (the pmf extended by the gamma
    function; ``l0 = log Phi(-mu / s)``), relative to ``P(eps > 0)``."""
    z = (math.log1p(x / (m + b)) - mu) / s
    lz = log_ndtr(z)
    if not lz > l0:
        return -math.inf
    return log_pmf(m + x, lam) + lz + math.log(-math.expm1(l0 - lz))


#: :func:`mean_probability_smooth` needs its summands smooth on this many counts at least (``s (m + b)``, and a
#: quarter of it for the width of each inner integrand); below, it returns NaN
EM_MIN_SCALE = 30.0
#: Gauss-Legendre nodes and weights on [0, 1] for the inner integrals of :func:`mean_probability_smooth`
_EM_NODES = 24
_EM_PANELS = 6
_EM_HALF = 15.0  # the inner integral covers the mode +- this many widths (log-concave: the rest is below e^-100)
_GL24_U = 0.5 * (np.polynomial.legendre.leggauss(_EM_NODES)[0] + 1.0)
_GL24_W = 0.5 * np.polynomial.legendre.leggauss(_EM_NODES)[1]


@kernel
def mean_probability_smooth(lam, b, mu, s, eps_peak):
    """``log E[p]`` by the double sum ``sum_m pmf(m) sum_{j >= 1} pmf(m + j) P(0 < eps < log1p(j / (m + b)))`` with
    each inner sum over ``j`` replaced by its Euler-Maclaurin form (``lam`` large, ``m >= 16``): the integral over
    a real ``j`` (the pmf extended by the gamma function), minus ``g'(0) / 12`` at the end ``j = 0`` where the
    summand ``g`` vanishes. The summand is smooth on the scale of ``min(sqrt(lam), s (m + b))`` counts, so the
    sum and the integral differ by far less than the next term (about ``g'''(0) / 720``, a relative
    ``(s (m + b))^-2`` of the first, itself only there when the truncation at ``eps = 0`` matters). The integrand
    is log-concave in ``j`` (log-concave pmf, and the normal's ``log Phi`` of a concave argument), so each integral
    is taken by Gauss-Legendre over its mode +- ``_EM_HALF`` widths. The outer sum runs outwards from the ``m`` that
    dominates at threshold ``eps_peak`` until its terms fall below ``exp(-45)`` of the largest for 16 steps.

    Not a bound: an estimate whose error is far below the grid's bracket (tested against the enumeration);
    :func:`threshold_atoms_grid` uses it only inside its rigorous bracket. Returns NaN where ``m`` would go below
    16 (small ``lam``).
    """
    x0 = -mu / s
    l0 = log_ndtr(x0)
    log_q = math.log1p(-math.exp(l0))
    # d/dj P(0 < eps < log1p(j / (m + b))) at j = 0 is phi(x0) / (s (m + b))
    log_dens0 = -0.5 * x0 * x0 - _LOG_SQRT_2PI - math.log(s)
    m_start = np.floor(_peak(lam, math.expm1(eps_peak), b))
    best = -math.inf
    total_ref = -math.inf
    acc = 0.0
    x_first = -1.0
    for direction in range(2):
        m = m_start if direction == 0 else m_start - 1.0
        xm = max(1.0, (m_start + b) * math.expm1(eps_peak)) if direction == 0 else x_first
        small = 0
        while True:
            if m < 16.0 or s * (m + b) < EM_MIN_SCALE:
                return math.nan
            # the inner integrand's mode: Newton on central differences, kept inside a bracket of the mode
            lo = 0.0
            hi = math.inf
            for _ in range(200):
                d = 1.0 if xm > 4.0 else 0.25 * xm
                f0 = _log_f_inner(xm, m, lam, b, mu, s, l0)
                fp = _log_f_inner(xm + d, m, lam, b, mu, s, l0)
                fm = _log_f_inner(xm - d, m, lam, b, mu, s, l0)
                if fm == -math.inf or fp > fm:
                    lo = xm
                else:
                    hi = xm
                g1 = (fp - fm) / (2.0 * d)
                g2 = (fp - 2.0 * f0 + fm) / (d * d)
                xn = xm - g1 / g2 if (g2 < 0.0 and fm > -math.inf) else math.nan
                if not (lo < xn < hi):
                    xn = 0.5 * (lo + hi) if hi < math.inf else 2.0 * xm + 1.0
                if abs(xn - xm) < 0.01:
                    xm = xn
                    break
                xm = xn
            f0 = _log_f_inner(xm, m, lam, b, mu, s, l0)
            d = 1.0 if xm > 4.0 else 0.25 * xm
            g2 = (_log_f_inner(xm + d, m, lam, b, mu, s, l0) - 2.0 * f0
                  + _log_f_inner(xm - d, m, lam, b, mu, s, l0)) / (d * d)
            w = 1.0 / math.sqrt(-g2) if g2 < 0.0 else 0.25 * xm
            if not w >= EM_MIN_SCALE / 4.0:
                return math.nan
            a = max(0.0, xm - _EM_HALF * w)
            z = xm + _EM_HALF * w
            pw = (z - a) / _EM_PANELS
            inner = 0.0
            for panel in range(_EM_PANELS):
                pa = a + pw * panel
                for q in range(_EM_NODES):
                    inner += _GL24_W[q] * pw * math.exp(_log_f_inner(pa + pw * _GL24_U[q], m, lam, b, mu, s, l0) - f0)
            # Euler-Maclaurin at j = 0: sum_{j >= 1} g(j) = int_0^inf g - g'(0) / 12 + ...
            corr = math.exp(log_pmf(m, lam) + log_dens0 - math.log(m + b) - f0) / 12.0 if a == 0.0 else 0.0
            lt = log_pmf(m, lam) + f0 + math.log(inner - corr) if inner > corr else -math.inf
            if x_first < 0.0:
                x_first = xm
            acc, total_ref = scaled_add(acc, total_ref, lt)
            best = max(best, lt)
            if lt < best - 45.0:
                small += 1
                if small >= 16:
                    break
            else:
                small = 0
            m += 1.0 if direction == 0 else -1.0
            if direction == 0 and m > lam + 60.0 * math.sqrt(lam) + 100.0:
                break
    return total_ref + math.log(acc) - log_q

@kernel
def enumeration_size(lam, b, mu, s):
    """``(pairs, grid)``: about how many breakpoints :func:`threshold_atoms` visits (the pairs ``n > m`` of its
    photon-count window whose breakpoint lies between the lowest threshold that can matter and ``mu + 9 s``),
    and about how many grid points :func:`threshold_atoms_grid` takes; ``(0, 0)`` where the mean is far below
    the smallest double (:func:`threshold_atoms` then returns at once)."""
    x0 = -mu / s
    q_norm = phi_interval(x0, math.inf)
    # threshold_atoms' lower bound on the mean, with p from the paper's Gaussian form (an estimate is enough here,
    # and it costs no sum): p ~ Phi(-(lam + b) c / sqrt(lam (1 + (1 + c)^2)))
    log_lb = -math.inf
    for i in range(13):
        e = mu - i * s
        if e <= 0.0:
            break
        lf = math.log(phi_interval(x0, (e - mu) / s) / q_norm)
        c = math.expm1(e)
        log_lb = max(log_lb, log_ndtr(-(lam + b) * c / math.sqrt(lam * (1.0 + (1.0 + c) ** 2))) + lf)
    if log_lb < -750.0:
        return 0.0, 0.0
    lp_max = log_pmf(math.floor(lam), lam)
    cut = log_lb - _CUT
    lo, hi = _window(lam, cut - 2.0 * lp_max)
    c_top = math.expm1(mu + _LUMP_X * s)
    # P(eps < L) >= exp(cut - 2 lp_max) P(eps > 0) is needed, and P(eps < L) <= phi(x) / |x| below x = -1
    x_low = -math.sqrt(max(2.0 * (2.0 * lp_max - cut), 1.0))
    c_low = math.expm1(max(mu + x_low * s, 0.0))
    total = 0.0
    m = lo
    while m < hi:
        n_top = min(hi, np.floor(m + c_top * (m + b)))
        n_low = max(m, np.floor(m + c_low * (m + b)))
        if n_top > n_low:
            total += n_top - n_low
        m += 1.0
    return total, (_LUMP_X + min(-x_low, mu / s)) * GRID_PER_SIGMA

# --------------------------------------------------------------------------------------
# counts of pixels with their own thresholds, decided by brackets (evnoise._bracket)
#
# p = sum_m pmf(m) P(N > k(m)), k(m) = m + floor(c (m + b)), c = expm1(eps), as the closed form sums it
# (evnoise._kernels.poisson); each k(m) is monotone in c bit for bit (a product and a floor), so sums at two
# thresholds bracket the closed form's p at every threshold between them, up to the rounding of two separately
# computed sums (BRACKET_WIDEN) and the photon counts left out of the window (bounded, added to the upper end).
# --------------------------------------------------------------------------------------
#: bracket ends are widened by this (relative) for the rounding of two separately computed sums
BRACKET_WIDEN = 1e-9
#: bracket upper ends also get this (absolute) for terms that underflow in the sums
BRACKET_ABS = 1e-290
#: relative margin on each end of a bracket of ``log1p(-p)`` (a few ulps of any libm's log1p, and more)
LOG_MARGIN = 1e-14
#: a lattice point's threshold ``c = expm1(e)`` is moved by this (relative) either way: covers two libm's expm1
C_MARGIN = 1e-13
#: the photon-count window of a sum leaves out at most this much probability on either side (added to the upper
#: ends: the width it adds to a bracket, times the trials, is the chance it leaves a pixel undecided)
WINDOW_ATOL = 1e-12
#: a level's pmf / tail table longer than this is not built (its pixels take the closed form)
BRACKET_MAX_TABLE = 1 << 20
#: pixels whose lattice brackets are looked up together (:func:`bracket_counts`)
_BLOCK = 64
#: status of a pixel: decided by the lattice bracket, by its own sums, or left to the closed form
DECIDED_LATTICE, DECIDED_OWN, UNDECIDED = 0, 1, 2
#: a level's kind: photon counts tabulated, no photons (p = 0 exactly), or not handled here
LEVEL_TABLE, LEVEL_DARK, LEVEL_NONE = 0, 1, 2


@kernel
def lattice_cell(e, h, inv_h):
    """``j`` (a float) with ``j h <= e <= (j + 1) h`` as computed in floating point (``e >= 0``, ``h > 0``,
    ``inv_h`` about ``1 / h``)."""
    j = np.floor(e * inv_h)
    for _ in range(8):  # the division may round across a lattice point: step back inside
        if j * h > e:
            j -= 1.0
        elif (j + 1.0) * h < e:
            j += 1.0
        else:
            break
    return j


@kernel
def _log_lower_tail(m, lam):
    """Bound on ``log P(M < m)`` for ``M ~ Poisson(lam)``, ``m <= lam`` (``-inf`` at ``m = 0``): the pmf
    ratio ``pmf(k - 1) / pmf(k) = k / lam <= (m - 1) / lam`` below ``m``, a geometric series."""
    if m <= 0.0:
        return -math.inf
    return log_pmf(m - 1.0, lam) - math.log1p(-(m - 1.0) / lam)


@kernel
def _log_upper_tail(m, lam):
    """Bound on ``log P(M > m)`` for ``M ~ Poisson(lam)``: ``pmf(m + 1) / (1 - lam / (m + 2))`` where the
    ratio is below 1, else 0 (the trivial bound)."""
    r = lam / (m + 2.0)
    if r >= 1.0:
        return 0.0
    return min(log_pmf(m + 1.0, lam) - math.log1p(-r), 0.0)


@kernel
def level_geometry(lam, b, c_min, c_max, atol, out_int, out_t):
    """The photon-count window and table of one light level for both polarities.

    ``c_min[q]``, ``c_max[q]`` (``q`` = 0 ON, 1 OFF) are the smallest and largest ``c = expm1(eps)`` the
    level's sums are taken at (already widened). Fills ``out_int = [kind, m_lo, m_hi_on, m_hi_off, j1]`` and
    ``out_t = [T, T]``: the sums (:func:`window_sums`) start at ``m_lo``, leaving out at most ``T = P(M < m_lo)
    <= atol`` of ``p``; they stop by ``m_hi_q``, where the terms above, at most ``P(M > m_hi) P(N > k(m_hi + 1))``
    at the smallest ``c``, are below ``atol``; the table covers the counts ``m_lo .. j1``. ``kind``:
    :data:`LEVEL_DARK` at ``lam = 0`` (``p = 0``), :data:`LEVEL_NONE` where the table would be too long.
    """
    out_t[0] = 0.0
    out_t[1] = 0.0
    if lam == 0.0:
        out_int[0] = LEVEL_DARK
        return
    if not (lam > 0.0 and lam < 1e12):
        out_int[0] = LEVEL_NONE
        return
    log_atol = math.log(atol)
    mode = np.floor(lam)
    # m_lo: the largest m <= mode with P(M < m) <= atol (the bound grows with m: bisection, bound(0) = 0)
    if _log_lower_tail(mode, lam) <= log_atol:
        m_lo = mode
    else:
        a = 0.0
        z = mode
        while z - a > 1.0:
            mid = np.floor(0.5 * (a + z))
            if _log_lower_tail(mid, lam) <= log_atol:
                a = mid
            else:
                z = mid
        m_lo = a
    t_lo = math.exp(_log_lower_tail(m_lo, lam)) * (1.0 + 1e-6)
    j1 = m_lo
    for q in range(2):
        c = c_min[q]
        # m_hi: the smallest m >= mode with P(M > m) P(N > k(m + 1)) <= atol (falls as m grows)
        lo_m = mode
        step = max(1.0, np.floor(math.sqrt(lam)))
        hi_m = mode + step
        for _ in range(200):
            k = threshold_count(hi_m + 1.0, c, b)
            if _log_upper_tail(hi_m, lam) + _log_upper_tail(k, lam) <= log_atol:
                break
            lo_m = hi_m
            step *= 2.0
            hi_m = mode + step
        while hi_m - lo_m > 1.0:
            mid = np.floor(0.5 * (lo_m + hi_m))
            k = threshold_count(mid + 1.0, c, b)
            if _log_upper_tail(mid, lam) + _log_upper_tail(k, lam) <= log_atol:
                hi_m = mid
            else:
                lo_m = mid
        m_hi = hi_m
        out_t[q] = t_lo
        out_int[2 + q] = int(m_hi)
        j1 = max(j1, threshold_count(m_hi, c_max[q], b) + 2.0)
    if not (j1 - m_lo + 1.0 <= BRACKET_MAX_TABLE):
        out_int[0] = LEVEL_NONE
        return
    out_int[0] = LEVEL_TABLE
    out_int[1] = int(m_lo)
    out_int[4] = int(j1)


@kernel
def fill_level_table(lam, j0, pmf, sf):
    """``pmf[i] = P(M = j0 + i)`` and ``sf[i] = P(M > j0 + i)`` for ``M ~ Poisson(lam)``: the pmf as
    :func:`.poisson.pmf_run` makes it (exact ``log_pmf`` at every 32nd entry, the ratio recurrence between);
    the tails summed downwards from an exact last one, so they only grow (no cancellation)."""
    n = pmf.shape[0]
    pmf_run(lam, j0, pmf)
    sf[n - 1] = math.exp(log_sf(float(j0 + n - 1), lam))
    for j in range(n - 2, -1, -1):
        sf[j] = sf[j + 1] + pmf[j + 1]


@kernel
def window_sums(c_up, c_dn, b, m_lo, m_hi, pmf, sf, atol):
    """Bracket ends of ``p = sum_m pmf(m) P(N > k(m, c))`` for ``c_up <= c <= c_dn`` from a level's table (which
    starts at ``m_lo``): ``(upper, lower)``, the sums over ``m >= m_lo`` at ``c_up`` plus a bound on the terms
    left out above, and at ``c_dn``; ``k(m, c) = m + floor(c (m + b))`` is computed as the closed form computes
    it (:func:`evnoise._kernels.poisson.threshold_count`), so that ``k`` is monotone in ``c`` bit for bit.

    The sum stops past ``m`` once the terms above it, at most ``P(M > m) P(N > k(m, c_up))`` (``k`` grows with
    ``m``), are below ``atol`` (both factors from the table), and at ``m_hi`` at the latest. A term whose ``k``
    is the same at both ends (all but those whose ``c (m + b)`` lies within the two ends of an integer) is added
    once, to a sum both ends share."""
    common = 0.0
    d_up = 0.0
    d_dn = 0.0
    n = m_hi - m_lo + 1
    i = 0
    k = 0
    while i < n:
        top = min(i + 8, n)
        for ii in range(i, top):
            x = float(m_lo + ii) + b
            f = np.floor(c_up * x)
            k = ii + int(f)
            t = pmf[ii] * sf[k]
            if c_dn * x < f + 1.0:  # the same floor at c_dn (which is >= c_up: never below it)
                common += t
            else:
                d_up += t
                d_dn += pmf[ii] * sf[ii + int(np.floor(c_dn * x))]
        i = top
        tail = sf[i - 1] * sf[k]
        if tail <= atol:
            break
    return (common + d_up) + tail * 1.01, common + d_dn


@kernel
def level_sums(g_lo, g_hi, levels, b, kind, geo, tab_off, pmf, sf, h, j_first, n_cells, atol, s_up, s_dn):
    """Tables and lattice sums of levels ``g_lo <= g < g_hi``.

    Fills each level's ``pmf``, ``sf`` (from ``tab_off[g]``, :func:`fill_level_table`) and, for polarity ``q``
    (lattice step ``h[q]``) and its lattice points ``j = j_first[q] + i``, ``0 <= i <= n_cells[q]``:
    ``s_up[q, g, i]`` the upper end of :func:`window_sums` at ``expm1(j h) (1 - C_MARGIN)`` (the upper end of the
    cell that starts there, but for the level's lower tail) and ``s_dn[q, g, i]`` its lower end at
    ``expm1(j h) (1 + C_MARGIN)`` (the lower end of the cell that ends there); zeros for a level without table."""
    for g in range(g_lo, g_hi):
        if kind[g] != LEVEL_TABLE:
            s_up[:, g, :] = 0.0
            s_dn[:, g, :] = 0.0
            continue
        m_lo = geo[g, 1]
        lo = tab_off[g]
        hi = tab_off[g + 1]
        tp = pmf[lo:hi]
        ts = sf[lo:hi]
        fill_level_table(levels[g], m_lo, tp, ts)
        for q in range(2):
            m_hi = geo[g, 2 + q]
            for i in range(n_cells[q] + 1):
                c = math.expm1((j_first[q] + i) * h[q])
                s_up[q, g, i], s_dn[q, g, i] = window_sums(c * (1.0 - C_MARGIN), c * (1.0 + C_MARGIN), b, m_lo,
                                                           m_hi, tp, ts, atol)


@kernel
def _log1m_low(p, exact):
    """``l >= log1p(-p')`` for every ``p' >= p`` as any libm computes it (within a few ulps): ``log1p`` moved by
    :data:`LOG_MARGIN`, or (``exact`` false, ``p <= 0.1``) the series bound ``log1p(-p) <= -p - p^2/2``, which
    costs no logarithm and is wider by a relative ``p^2 / 3`` at most. ``p = 0`` gives 0 (no event, no draw)."""
    if exact or p > 0.1:
        return math.log1p(-p) * (1.0 - LOG_MARGIN)
    return -(p + 0.5 * p * p) * (1.0 - LOG_MARGIN)


@kernel
def _log1m_high(p, exact):
    """``l <= log1p(-p')`` for every ``p' <= p < 1``, as :func:`_log1m_low` (the series bound
    ``log1p(-p) >= -p - p^2/2 - p^3 / (3 (1 - p))``, and ``1 / (3 (1 - p)) <= 0.375`` for ``p <= 0.1``)."""
    if exact or p > 0.1:
        return math.log1p(-p) * (1.0 + LOG_MARGIN)
    return -(p + p * p * (0.5 + 0.375 * p)) * (1.0 + LOG_MARGIN)


@kernel
def _with_background(p_on, p_off, a_on, a_off):
    """``(P_on, P_off)``: :func:`evnoise.background.with_background` at arrival shares ``a_on``, ``a_off``."""
    quiet = 1.0 - p_on - p_off
    return p_on + quiet * a_on, p_off + quiet * a_off


@kernel
def _on_share(p_on, p_off, a_on, a_off):
    """The ON share ``P_on / (P_on + P_off)`` of :func:`_with_background` (0.5 where both are 0)."""
    a, c = _with_background(p_on, p_off, a_on, a_off)
    return a / (a + c) if a + c > 0.0 else 0.5


@kernel
def _first_trial(lt, lta, refr_us, dt):
    """The renewal kernel's first eligible trial after an event at trial ``lt``, time ``lta`` (``j_min = 0``)."""
    if lta == -math.inf or refr_us == 0.0:
        j_e = lt + 1.0
    else:
        j_e = first_eligible_trial(lt, lta, refr_us, dt)
    return max(j_e, 0.0)


#: what :func:`dual_counts` found: the two ends part, give the same counts, or the upper end is ``p = 1``
DUAL_PARTED, DUAL_SAME, DUAL_SURE = 0, 1, 2


@kernel(inline=True)
def dual_counts(s, lo_on, hi_on, lo_off, hi_off, a_on, a_off, exact, dt, refr_us, w_end):
    """ON and OFF counts that the renewal kernel (:func:`evnoise._kernels.simulate.renewal_window`, counts only,
    one window from 0 to ``w_end``, no timer) draws on the stream ``s`` for every ``(p_on, p_off)`` in the bracket
    ``lo_* <= p_* <= hi_*``: ``(on, off, DUAL_SAME)`` when they are the same all over the bracket, else
    :data:`DUAL_PARTED` (or :data:`DUAL_SURE` where the upper end reaches ``p = 1``, whose draws differ in kind).

    The renewal inputs at the bracket's two ends ``a`` (lower ``p``) and ``b`` (higher): with background each
    polarity's total is ``p + (1 - p_on - p_off) a`` (arrival shares ``a_on``, ``a_off``, zero without), so the
    total ``P`` grows with both ``p`` (``a_on + a_off <= 1``) and the ON share ``P_on / P`` grows with ``p_on`` and
    falls with ``p_off``: their extremes lie at the corners ``(lo, lo)``, ``(hi, hi)`` and ``(lo_on, hi_off)``,
    ``(hi_on, lo_off)``; each is widened by :data:`BRACKET_WIDEN`, and ``log1p(-P)`` bounded by :func:`_log1m_low`,
    :func:`_log1m_high` (``exact``: by ``log1p`` itself). Both ends are run in lockstep, stopping as soon as they
    part: while both have their events inside the window they take the same draws (one ``uniform_pos`` for the
    gap, one ``uniform`` for the time in the trial and one for the polarity), and every event of ``b`` comes at or
    before ``a``'s (gaps shrink as ``p`` grows, the first eligible trial follows the last event), so ``b``'s next
    event beyond the window ends both. The lower end and the ON shares are only worked out once ``b`` has an
    event in the window (most pixels have none)."""
    p_on, p_off = _with_background(hi_on, hi_off, a_on, a_off)
    p_hi = (p_on + p_off) * (1.0 + BRACKET_WIDEN)
    if p_hi >= 1.0:
        return 0, 0, DUAL_SURE
    l_b = _log1m_high(p_hi, exact)
    if l_b == 0.0:  # p = 0 at the upper end: no draw, no event, at every p in between
        return 0, 0, DUAL_SAME
    la = math.log(uniform_pos(s))
    g_b = np.floor(la / l_b) + 1.0
    if g_b == math.inf:
        return 0, 0, DUAL_SAME
    jp_b = g_b - 1.0  # the first eligible trial is 0
    u = uniform(s)
    tau_b = (jp_b + u) * dt
    if tau_b >= w_end:
        return 0, 0, DUAL_SAME
    p_on, p_off = _with_background(lo_on, lo_off, a_on, a_off)
    l_a = _log1m_low(max((p_on + p_off) * (1.0 - BRACKET_WIDEN), 0.0), exact)
    q_a = min(max(_on_share(lo_on, hi_off, a_on, a_off) * (1.0 - BRACKET_WIDEN), 0.0), 1.0)
    q_b = min(max(_on_share(hi_on, lo_off, a_on, a_off) * (1.0 + BRACKET_WIDEN), 0.0), 1.0)
    j_a = 0.0
    n_on = 0
    n_off = 0
    while True:  # b's event of this step (its gap from la, its time from u) is inside the window
        if l_a == 0.0:  # p = 0 at the lower end: no draw, no event
            return n_on, n_off, DUAL_PARTED
        g_a = np.floor(la / l_a) + 1.0
        if g_a == math.inf:
            return n_on, n_off, DUAL_PARTED
        jp_a = j_a + g_a - 1.0
        tau_a = (jp_a + u) * dt
        if tau_a >= w_end:
            return n_on, n_off, DUAL_PARTED
        u = uniform(s)
        on_a = u < q_a
        if on_a != (u < q_b):
            return n_on, n_off, DUAL_PARTED
        if on_a:
            n_on += 1
        else:
            n_off += 1
        j_a = _first_trial(jp_a, tau_a, refr_us, dt)
        j_b = _first_trial(jp_b, tau_b, refr_us, dt)
        la = math.log(uniform_pos(s))
        g_b = np.floor(la / l_b) + 1.0
        if g_b == math.inf:  # then g_a is too: neither draws again
            return n_on, n_off, DUAL_SAME
        jp_b = j_b + g_b - 1.0
        u = uniform(s)
        tau_b = (jp_b + u) * dt
        if tau_b >= w_end:
            return n_on, n_off, DUAL_SAME


@kernel
def _own_bracket(e, g, q, b, geo, t_tail, tab_off, pmf, sf, atol):
    """``(ok, upper, lower)``: the bracket of one polarity's ``p`` of a pixel at threshold ``e`` from its level's
    table (:func:`window_sums` at its own ``c = expm1(e)``, moved by :data:`C_MARGIN` either way); ``ok`` false
    where the sums would run past the table (not for thresholds inside the level's lattice)."""
    m_lo = geo[g, 1]
    m_hi = geo[g, 2 + q]
    lo = tab_off[g]
    hi = tab_off[g + 1]
    c = math.expm1(e)
    if threshold_count(float(m_hi), c * (1.0 + C_MARGIN), b) > m_lo + (hi - lo) - 1:
        return False, 0.0, 0.0
    up, dn = window_sums(c * (1.0 - C_MARGIN), c * (1.0 + C_MARGIN), b, m_lo, m_hi, pmf[lo:hi], sf[lo:hi], atol)
    return True, (up + t_tail[g, q]) * (1.0 + BRACKET_WIDEN) + BRACKET_ABS, (
        dn * (1.0 - BRACKET_WIDEN) if dn > 1e-280 else 0.0)


@kernel
def bracket_counts(first, group, eps_on, eps_off, key, inv_h, h, j_first, n_cells, cells, kind, geo, t_tail, tab_off,
                   pmf, sf, b, a_on, a_off, dt, refr_us, w_end, atol, on_counts, off_counts, status):
    """Counts of the pixels ``first, first + 1, ...`` (flat indices; their level ``group``, thresholds ``eps_on``,
    ``eps_off``), each decided by its lattice bracket, else by brackets of its own sums (the polarity whose
    lattice bracket is wider first), else marked :data:`UNDECIDED` (counts left 0) for the closed form.

    ``cells[q, g, j - j_first[q]] = (upper, lower)`` is the bracket of polarity ``q``'s ``p`` over lattice cell
    ``j`` (step ``h[q]``, ``inv_h[q] = 1 / h[q]``, ``0 <= j - j_first[q] < n_cells[q]``; a threshold outside the
    lattice takes its own sums at once) of level ``g``; ``geo``, ``t_tail``, ``tab_off``, ``pmf``, ``sf``
    the level windows and tables (:func:`level_geometry`, :func:`level_sums`); ``a_on``, ``a_off`` the levels'
    background arrival shares (zeros without background); ``status`` says how each pixel was decided. Returns how
    many pixels the lattice left undecided, and how many of those their own sums did not decide either."""
    s = np.empty(4, dtype=np.uint64)
    ends = np.empty((_BLOCK, 4))
    n_pix = group.shape[0]
    n_own = 0
    n_left = 0
    for i0 in range(0, n_pix, _BLOCK):
        i1 = min(i0 + _BLOCK, n_pix)
        # the lattice brackets of a block first, in a loop of their own (measured faster than pixel by pixel)
        for i in range(i0, i1):
            k = i - i0
            g = group[i]
            ends[k, 0] = 1.0  # beyond the lattice: a bracket that decides nothing
            ends[k, 1] = 0.0
            ends[k, 2] = 1.0
            ends[k, 3] = 0.0
            if kind[g] == LEVEL_DARK:  # no photons: p = 0 exactly at every threshold
                ends[k, 0] = 0.0
                ends[k, 2] = 0.0
            elif kind[g] == LEVEL_TABLE:
                jf = lattice_cell(eps_on[i], h[0], inv_h[0]) - j_first[0]
                if 0.0 <= jf < n_cells[0]:
                    ends[k, 0] = cells[0, g, int(jf), 0]
                    ends[k, 1] = cells[0, g, int(jf), 1]
                jf = lattice_cell(eps_off[i], h[1], inv_h[1]) - j_first[1]
                if 0.0 <= jf < n_cells[1]:
                    ends[k, 2] = cells[1, g, int(jf), 0]
                    ends[k, 3] = cells[1, g, int(jf), 1]
        for i in range(i0, i1):
            k = i - i0
            g = group[i]
            on_counts[i] = 0
            off_counts[i] = 0
            status[i] = UNDECIDED
            if kind[g] == LEVEL_NONE:
                n_left += 1
                continue
            seed_state(key, np.int64(first + i), s)
            n_on, n_off, found = dual_counts(s, ends[k, 1], ends[k, 0], ends[k, 3], ends[k, 2], a_on[g], a_off[g],
                                             False, dt, refr_us, w_end)
            if found == DUAL_SAME:
                on_counts[i] = n_on
                off_counts[i] = n_off
                status[i] = DECIDED_LATTICE
                continue
            n_own += 1
            if kind[g] == LEVEL_TABLE:
                status[i], on_counts[i], off_counts[i] = _own_counts(
                    np.int64(first + i), g, eps_on[i], eps_off[i], ends[k, 0], ends[k, 1], ends[k, 2], ends[k, 3],
                    key, s, geo, t_tail, tab_off, pmf, sf, b, a_on[g], a_off[g], dt, refr_us, w_end, atol)
            if status[i] == UNDECIDED:
                n_left += 1
    return n_own, n_left


@kernel
def _own_counts(pix, g, e_on, e_off, hi_on, lo_on, hi_off, lo_off, key, s, geo, t_tail, tab_off, pmf, sf, b, a_on,
                a_off, dt, refr_us, w_end, atol):
    """A pixel that its lattice brackets (``hi_on``, ``lo_on``, ``hi_off``, ``lo_off``) left undecided, decided by
    the brackets of its own sums (the polarity whose lattice bracket is wider first): ``(status, on, off)``, the
    counts 0 unless decided."""
    first_q = 0 if hi_on - lo_on >= hi_off - lo_off else 1
    for step in range(2):
        q = first_q if step == 0 else 1 - first_q
        ok, up, dn = _own_bracket(e_on if q == 0 else e_off, g, q, b, geo, t_tail, tab_off, pmf, sf, atol)
        if not ok:
            break
        if q == 0:
            hi_on = up
            lo_on = dn
        else:
            hi_off = up
            lo_off = dn
        seed_state(key, pix, s)
        n_on, n_off, found = dual_counts(s, lo_on, hi_on, lo_off, hi_off, a_on, a_off, True, dt, refr_us, w_end)
        if found == DUAL_SAME:
            return DECIDED_OWN, n_on, n_off
    return UNDECIDED, 0, 0


@kernel
def levels_geometry(levels, b, c_min, c_max, atol, geo, t_tail):
    """:func:`level_geometry` of every level: ``geo[g] = [kind, m_lo, m_hi_on, m_hi_off, j1]``, ``t_tail[g]``."""
    for g in range(levels.shape[0]):
        level_geometry(levels[g], b, c_min[g], c_max[g], atol, geo[g], t_tail[g])
