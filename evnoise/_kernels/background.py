"""Kernels of the regular background timer (``leak_regularity > 0``, see :mod:`evnoise.background`).

After every event of a pixel its background timer restarts: the next background arrival comes
``L`` eligible trials after the first eligible one (``L >= 1``), with ``L = D + G``: ``D`` a whole
number of trials, ``floor(d) or floor(d) + 1`` with mean ``d = r (M - 1)``, and ``G`` geometric on
``1, 2, ...`` with mean ``1 + (1 - r)(M - 1)``. ``M = 1 / (1 - exp(-l dt))`` is the mean of the
memoryless case ``r = 0`` (where ``L`` is geometric and the timer is the per-trial probability of
the Poisson background), so the mean interval in quiet trials is ``M`` for every ``r``; ``r = 1``
is periodic up to a one-trial jitter. The photon comparison wins a tie (the background fires only
in a trial the comparison leaves quiet).
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ._jit import kernel
from .rng import geometric, uniform


@kernel
def timer_shape(l_all, dt_s, regularity):
    """``(d, log1p(-a2))`` of the timer for background intensity ``l_all`` (events/s); ``d = inf`` for none."""
    if not l_all > 0.0:
        return math.inf, 0.0
    a = -math.expm1(-l_all * dt_s)
    m = 1.0 / a
    d = regularity * (m - 1.0)
    g_mean = 1.0 + (1.0 - regularity) * (m - 1.0)
    a2 = 1.0 / g_mean
    return d, (math.log1p(-a2) if a2 < 1.0 else -math.inf)


@kernel
def timer_shapes(l_all, dt_s, regularity, d, log1m_a2):
    """:func:`timer_shape` of every intensity of the 1-D array ``l_all`` with its ``regularity`` (1-D, same
    size), into ``d`` and ``log1m_a2``."""
    for i in range(l_all.size):
        d[i], log1m_a2[i] = timer_shape(l_all[i], dt_s, regularity[i])


@kernel
def draw_timer(s, d, log1m_a2):
    """Trials ``L >= 1`` from the first eligible trial to the next background arrival."""
    if d == math.inf:
        return math.inf
    d0 = np.floor(d)  # a float: math.floor is an int64 in Numba and overflows beyond 9.2e18
    if uniform(s) < d - d0:
        d0 += 1.0
    return d0 + geometric(s, log1m_a2)


@kernel
def draw_timer_stationary(s, d, log1m_a2, log1m_p):
    """The first background arrival (trials ``>= 1`` from the first trial) of a pixel in its steady state.

    A pixel whose events (photon noise of per-trial probability ``p``, ``log1m_p = log1p(-p)``, and the
    timer ``L = D + G``) have been running forever: its age ``A`` (trials since its last event) has
    ``P(A = a) ~ (1 - p)^a P(L > a)`` (the steady-state age of a discrete renewal process whose gap is
    ``min(G_p, L)``), drawn jointly with ``D``; given ``A = a`` the timer is ``L`` conditioned on
    ``L > a`` (memoryless beyond ``D``), and the arrival comes ``L - a`` trials on. Exact without a
    refractory period (with one, only the first event of a pixel is approximate).
    """
    if d == math.inf:
        return math.inf
    d0 = np.floor(d)  # a float: math.floor is an int64 in Numba and overflows beyond 9.2e18
    phi = d - d0
    q = math.exp(log1m_p)  # 1 - p
    p = -math.expm1(log1m_p)
    one_m_a2 = math.exp(log1m_a2)
    # masses of the ages a <= dd (geometric q^a) and a > dd (ratio q (1 - a2)) for dd = d0 and d0 + 1
    best = 0.0
    dd = d0
    head = 0.0
    w0 = 0.0
    for k in range(2):
        dk = d0 + k
        qd = math.exp((dk + 1.0) * log1m_p)
        h = -math.expm1((dk + 1.0) * log1m_p) / p if p > 0.0 else dk + 1.0
        t = qd * one_m_a2 / (1.0 - q * one_m_a2) if one_m_a2 > 0.0 else 0.0
        z = ((1.0 - phi) if k == 0 else phi) * (h + t)
        if k == 0:
            w0 = z
            head = h
        else:
            best = z
            if uniform(s) * (w0 + best) >= w0:
                dd = dk
                head = h
    total = head + (math.exp((dd + 1.0) * log1m_p) * one_m_a2 / (1.0 - q * one_m_a2) if one_m_a2 > 0.0 else 0.0)
    if uniform(s) * total < head:
        # age a in 0..dd with weights q^a: inverse of the truncated geometric
        if p > 0.0:
            u = uniform(s)
            a = np.floor(math.log1p(u * math.expm1((dd + 1.0) * log1m_p)) / log1m_p)
            a = min(max(a, 0.0), dd)
        else:
            a = np.floor(uniform(s) * (dd + 1.0))
        return (dd - a) + geometric(s, log1m_a2)
    # age a > dd: a = dd + 1 + (failures of ratio q (1 - a2)); the rest of the timer is memoryless
    return geometric(s, log1m_a2)


@kernel(parallel=True)
def regular_mean_rate(p_own, mass, p_other, l_own, l_other, weight, trial_rate_hz, refractory_s, regularity,
                      own_is_on):
    """Population mean rate (events/s) of one polarity with the regular timer, summed in one pass.

    ``sum_b weight[b] sum_a mass[a] nu_own(p_own[a], p_other, l_own[b], l_other[b])`` with ``nu_own``
    the rate of :func:`evnoise.background.regular_rates` (its module doc's formula): threshold atoms
    ``a`` (``p_own``, ``mass``), background nodes ``b`` (``l_own``, ``l_other`` events/s, ``weight``,
    the timer's ``regularity``).
    The two whole parts of the timer share their powers: ``E[min]`` at ``D = d0 + 1`` is
    ``head + q^(d0+1) + q tail`` of the one at ``d0``. Where ``p_own + p_other > 1`` the total is
    clipped to 1 and, as in ``regular_rates``, ON keeps ``p_on / p`` of the photon events and OFF the
    rest (``own_is_on`` says which one ``p_own`` is). Each node's sum is its own (thread-count
    independent), the nodes are added in order.
    """
    n = trial_rate_hz
    n_atoms = p_own.size
    p = np.empty(n_atoms)
    q = np.empty(n_atoms)
    log1m_p = np.empty(n_atoms)
    share_p = np.empty(n_atoms)
    for a in range(n_atoms):
        pa = min(p_own[a] + p_other, 1.0)
        p[a] = pa
        log1m_p[a] = math.log1p(-pa)
        q[a] = math.exp(log1m_p[a])
        if pa > 0.0:
            share_p[a] = p_own[a] / pa if own_is_on else 1.0 - p_other / pa
        else:
            share_p[a] = 0.0
    dead = refractory_s * n
    per_node = np.zeros(l_own.size)
    for b in prange(l_own.size):
        l_all = l_own[b] + l_other[b]
        d, log1m_a2 = timer_shape(l_all, 1.0 / n, regularity[b])
        acc = 0.0
        if d < math.inf:
            d0 = np.floor(d)  # a float: math.floor is an int64 in Numba and overflows beyond 9.2e18
            phi = d - d0
            one_m_a2 = math.exp(log1m_a2)
            a2 = -math.expm1(log1m_a2)
            share_l = l_own[b] / l_all
            for a in range(n_atoms):
                pa = p[a]
                x = (d0 + 1.0) * log1m_p[a]
                if x < -0.5:  # 1 - q^(d0+1) without cancellation: no expm1 needed
                    qd = math.exp(x)
                    head = (1.0 - qd) / pa
                else:  # one expm1 gives both (q^(d0+1) = 1 + expm1 to a rounding: it is near 1 here)
                    em1 = math.expm1(x)
                    qd = 1.0 + em1
                    # divided by p, not times 1 / p: that overflows for a subnormal p (the rate came out 0)
                    head = -em1 / pa if pa > 0.0 else d0 + 1.0
                e_min = head + phi * qd
                if qd > 0.0:  # the geometric rest after the whole part; nothing left once q^(d0+1) underflows
                    # 1 - q (1 - a2) = p + q a2: a sum of two non-negative terms, no cancellation when both are small
                    e_min += qd * one_m_a2 / (pa + q[a] * a2) * (1.0 - phi + phi * q[a])
                if e_min < math.inf:  # else the pixel never fires: rate 0
                    photon = min(pa * e_min, 1.0)  # the photon events' share: <= 1 after rounding
                    acc += mass[a] * n / (dead + e_min) * (photon * share_p[a] + (1.0 - photon) * share_l)
        else:  # no background: photon noise alone, nu = N p / (1 + N p R)
            for a in range(n_atoms):
                if p[a] > 0.0:
                    acc += mass[a] * n * p[a] / (1.0 + dead * p[a]) * share_p[a]
        per_node[b] = acc
    total = 0.0
    for b in range(l_own.size):
        total += weight[b] * per_node[b]
    return total
