"""Numba kernels of the calibration: the exact distribution of the event probability across pixels.

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
took 2.1 GB at ``lam ~ 2e5``, evk4 at 3000 lux, and failed at 10,000 lux).

Everything is in scaled arithmetic (values relative to ``exp(ref)``), so tiny probabilities
do not underflow. Unit-free, no checking: the checked entry points are in
:mod:`evnoise.mismatch`.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import kernel
from .poisson import log_event_probability_exact, log_pmf

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
