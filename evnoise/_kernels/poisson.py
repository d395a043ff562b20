"""Unit-free Poisson kernels: log pmf, tail sums and the exact noise-event probability.

All functions take plain floats (photon counts are integer-valued floats) and do no
checking. The public, checked entry points live in :mod:`evnoise.model`.

The exact probability of one polarity is, for ``n, n0 ~ Poisson(lam)`` i.i.d.,

    p = P(n + b > e^eps (n0 + b)) = sum_m pmf(m) * P(N > k(m)),
    k(m) = m + floor(c (m + b)),  c = expm1(eps),

(the threshold ``e^eps (m + b) - b`` is written as ``m + c (m + b)`` so that its integer
part ``m`` is exact). The sum is evaluated in scaled linear arithmetic over a window of
``m`` around the summand's mode, sweeping ``m`` downwards so that the tail sums
``P(N > k(m))`` only ever *grow* by adding positive terms (no cancellation). All terms
are positive, so the relative error is a few ulps times the number of terms.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ._jit import kernel
from .bounds import chernoff_bracket

_LOG_2PI = math.log(2.0 * math.pi)

# stirlerr(n) = log(n!) - log(sqrt(2 pi n) (n/e)^n) for n = 0..15, computed with mpmath
# at 40 digits (n = 0 is unused: pmf(0) is handled exactly).
_STIRLERR = np.array(
    [
        0.0,
        0.08106146679532725822,
        0.041340695955409294094,
        0.027677925684998339149,
        0.020790672103765093112,
        0.016644691189821192163,
        0.013876128823070747999,
        0.011896709945891770095,
        0.010411265261972096497,
        0.0092554621827127329177,
        0.0083305634333628712565,
        0.007573675487951840795,
        0.0069428401072095298657,
        0.0064089941880042070684,
        0.0059513701127588477356,
        0.005554733551962801371,
    ]
)
# Stirling series coefficients B_{2k} / (2k (2k-1)): 1/12, 1/360, 1/1260, 1/1680, 1/1188.
_S0 = 1.0 / 12.0
_S1 = 1.0 / 360.0
_S2 = 1.0 / 1260.0
_S3 = 1.0 / 1680.0
_S4 = 1.0 / 1188.0

# Relative size below which a term or a tail is negligible (well under one ulp).
_TINY_REL = 1e-18
# Log-distance from the summand's maximum beyond which terms are dropped (e^-50 ~ 2e-22).
_LOG_WINDOW = 50.0
_SQRT1_2 = math.sqrt(0.5)
# Photons per trial above which the exact sum gives way to its saddle-point form (the sum costs
# about 3 s per value here, and grows like sqrt(lam); see log_event_probability_exact).
LAM_EXACT_MAX = 1e12


@kernel
def stirlerr(n):
    """Error of Stirling's formula for ``log(n!)``; ``n >= 1`` integer-valued."""
    if n <= 15.0:
        return _STIRLERR[min(max(int(n), 0), 15)]  # clamped: an index out of the table would read any memory
    nn = n * n
    if n > 500.0:
        return (_S0 - _S1 / nn) / n
    if n > 80.0:
        return (_S0 - (_S1 - _S2 / nn) / nn) / n
    if n > 35.0:
        return (_S0 - (_S1 - (_S2 - _S3 / nn) / nn) / nn) / n
    return (_S0 - (_S1 - (_S2 - (_S3 - _S4 / nn) / nn) / nn) / nn) / n


@kernel
def bd0(x, mu):
    """Deviance term ``x log(x/mu) + mu - x``, accurate also when ``x ~ mu`` (x > 0, mu > 0)."""
    if abs(x - mu) < 0.1 * (x + mu):
        v = (x - mu) / (x + mu)
        s = (x - mu) * v
        ej = 2.0 * x * v
        v2 = v * v
        for j in range(1, 1000):
            ej *= v2
            s1 = s + ej / (2 * j + 1)
            if s1 == s:
                return s1
            s = s1
        return s
    return x * (math.log(x) - math.log(mu)) + mu - x


@kernel
def log_pmf(n, lam):
    """``log P(N = n)`` for ``N ~ Poisson(lam)``; full relative accuracy of the pmf (Loader's method)."""
    if n == 0.0:
        return -lam
    return -stirlerr(n) - bd0(n, lam) - 0.5 * (_LOG_2PI + math.log(n))


@kernel
def approx_log_sf(k, lam):
    """Cheap approximation of ``log P(N > k)``, within about one unit; used only to place windows."""
    if k == math.inf:
        return -math.inf
    a = k + 1.0
    if a > lam:
        # P(N >= a) <= pmf(a) / (1 - lam / (a + 1))
        v = log_pmf(a, lam) - math.log1p(-lam / (a + 1.0))
        return min(v, 0.0)
    # P(N <= k) <= pmf(k) / (1 - k / lam)  (k < lam here)
    cdf = math.exp(log_pmf(k, lam)) / (1.0 - k / lam)
    return math.log1p(-min(cdf, 0.5))


@kernel
def log_sf(k, lam):
    """Accurate ``log P(N > k)`` for ``N ~ Poisson(lam)``, finite far below 1e-300 (``-inf`` at ``k = inf``)."""
    if k == math.inf:
        return -math.inf
    a = k + 1.0
    if a >= lam:
        # upward series: P(N >= a) = pmf(a) * (1 + lam/(a+1) + lam^2/((a+1)(a+2)) + ...)
        t = 1.0
        s = 1.0
        n = a
        while True:
            n += 1.0
            r = lam / n
            t *= r
            s += t
            rn = lam / (n + 1.0)
            if rn < 1.0 and t * rn / (1.0 - rn) < _TINY_REL * s:
                break
        return log_pmf(a, lam) + math.log(s)
    # a < lam: P(N > k) = 1 - P(N <= k), P(N <= k) summed downwards from k (it is <~ 0.5)
    t = 1.0
    s = 1.0
    n = k
    while n > 0.0:
        t *= n / lam
        n -= 1.0
        s += t
        r = n / lam
        if t * r / (1.0 - r) < _TINY_REL * s:
            break
    cdf = s * math.exp(log_pmf(k, lam))
    return math.log1p(-cdf)


@kernel
def threshold_count(m, c, b):
    """``k(m) = m + floor(c (m + b))``: an event needs ``n > k(m)`` when ``n0 = m``.

    A float throughout (``inf`` when ``c`` is): Numba's ``math.floor`` returns an int64, which wraps
    to a negative count once ``c (m + b)`` passes 2^63 (thresholds ``eps >= 43``). ``m + b = 0`` gives
    ``k = 0`` for every ``c`` (any photon beats a dark reference without bias).
    """
    if m + b == 0.0:
        return m
    return m + np.floor(c * (m + b))


@kernel
def _approx_log_term(m, lam, c, b):
    return log_pmf(m, lam) + approx_log_sf(threshold_count(m, c, b), lam)


@kernel
def _log_block_sum(n_low, n_high, lam):
    """``log sum_{n=n_low}^{n_high} pmf(n)``, summed outwards from the block's largest term."""
    n_pk = min(max(np.floor(lam), n_low), n_high)
    bs = 1.0
    t = 1.0
    n = n_pk
    while n < n_high:
        n += 1.0
        t *= lam / n
        bs += t
        if t < _TINY_REL * bs:
            break
    t = 1.0
    n = n_pk
    while n > n_low:
        t *= n / lam
        n -= 1.0
        bs += t
        if t < _TINY_REL * bs:
            break
    return log_pmf(n_pk, lam) + math.log(bs)


@kernel
def logaddexp(x, y):
    """``log(exp(x) + exp(y))`` of two floats (``-inf`` allowed), without overflow."""
    if x < y:
        x, y = y, x
    if y == -math.inf:
        return x
    return x + math.log1p(math.exp(y - x))


@kernel
def _sweep(m_hi, m_star, lam, c, b, ref):
    """Sum ``pmf(m) P(N > k(m))`` for m = m_hi, m_hi - 1, ... while terms matter.

    Returns ``(log_total, log_first_term)``. The tail ``P(N > k(m))`` is carried in log form
    and only grows (blocks of positive pmf terms are added), so nothing cancels. ``ref`` is
    an estimate of the largest log term, used as the accumulator's scale.
    """
    k_m = threshold_count(m_hi, c, b)
    s_log = log_sf(k_m, lam)
    acc = 0.0
    first = -math.inf
    n_small = 0
    m = m_hi
    while True:
        t_log = log_pmf(m, lam) + s_log
        if m == m_hi:
            first = t_log
        acc += math.exp(t_log - ref)
        if acc > 1e280:  # the reference was far too low; rescale
            ref += math.log(acc)
            acc = 1.0
        if m < m_star and t_log < ref + math.log(acc) - _LOG_WINDOW:
            n_small += 1
            if n_small >= 4:
                break
        else:
            n_small = 0
        if m <= 0.0:
            break
        k_new = threshold_count(m - 1.0, c, b)
        if k_new < k_m:
            s_log = logaddexp(s_log, _log_block_sum(k_new + 1.0, k_m, lam))
        k_m = k_new
        m -= 1.0
    return ref + math.log(acc), first


@kernel
def _log_upper_normal(w):
    """``log P(Z > w)`` for a standard normal ``Z`` and ``w >= 0``, finite for every finite ``w``."""
    if w < 30.0:
        return math.log(0.5 * math.erfc(w * _SQRT1_2))
    w2 = w * w
    return -0.5 * w2 - math.log(w) - 0.5 * _LOG_2PI + math.log1p(-1.0 / w2 + 3.0 / (w2 * w2) - 15.0 / (w2 * w2 * w2))


@kernel
def _cgf_terms(theta, c):
    """``(f, f')`` of ``f(theta) = expm1(theta) + expm1(-(1 + c) theta)``, without cancellation.

    Small ``theta``: the series ``sum_k theta^k (1 + (-a)^k) / k!`` with ``1 - a^k = -expm1(k log1p(c))``,
    so that ``f ~ -c theta`` keeps its digits when ``c`` is tiny (a direct sum would lose ``log10(1/c)``).
    """
    a = 1.0 + c
    if a * theta > 0.5:
        return math.expm1(theta) + math.expm1(-a * theta), math.expm1(theta) - a * math.expm1(-a * theta) - c
    lc = math.log1p(c)
    f = 0.0
    d = 0.0
    pw = 1.0  # theta^(k-1) / (k-1)!
    for k in range(1, 80):
        coef = -math.expm1(k * lc) if k % 2 == 1 else 1.0 + math.exp(k * lc)
        d += pw * coef
        pw_next = pw * theta / k
        f += pw_next * coef
        if abs(pw_next * coef) <= 1e-17 * abs(f) and abs(pw * coef) <= 1e-17 * abs(d):
            break
        pw = pw_next
    return f, d


@kernel
def log_event_probability_saddlepoint(lam, c, b):
    """Saddle-point (Lugannani-Rice) form of :func:`log_event_probability_exact`, for huge ``lam``.

    ``S = n - (1 + c) n0`` has cumulant generating function ``K(theta) = lam f(theta)``,
    ``f = (e^theta - 1) + (e^{-(1 + c) theta} - 1)``; the event is ``S > T = c b``. With
    ``K'(theta) = T``, ``w = sqrt(2 (theta T - K))`` and ``u = theta sqrt(K''(theta))``,
    ``P(S > T) ~ Q(w) + phi(w) (1/u - 1/w)``. Its exponent ``-w^2 / 2`` is the exact large-deviation
    rate: against the exact sum ``log p`` agrees to a relative 2e-8 at ``lam = 1e11`` (3e-5 at
    ``1e8``), and the gap shrinks like ``1 / lam``.
    """
    a = 1.0 + c
    target = c * b / lam
    hi = 1.0
    for _ in range(1100):
        if _cgf_terms(hi, c)[1] >= target:
            break
        hi *= 2.0
    lo = 0.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid <= lo or mid >= hi:
            break
        if _cgf_terms(mid, c)[1] < target:
            lo = mid
        else:
            hi = mid
    theta = 0.5 * (lo + hi)
    f, _ = _cgf_terms(theta, c)
    k2 = lam * (math.exp(theta) + a * a * math.exp(-a * theta))
    w2 = 2.0 * (theta * (c * b) - lam * f)
    if not w2 > 1e-12 or not theta > 0.0:  # at the mean: the plain normal form
        return _log_upper_normal((c * b + lam * c) / math.sqrt(lam * (1.0 + a * a)))
    w = math.sqrt(w2)
    u = theta * math.sqrt(k2)
    if w < 30.0:
        mills = 0.5 * math.erfc(w * _SQRT1_2) * math.exp(0.5 * w2) * math.sqrt(2.0 * math.pi)
        bracket = mills - 1.0 / w + 1.0 / u
    else:
        iw2 = 1.0 / w2
        bracket = 1.0 / u - iw2 / w * (1.0 - 3.0 * iw2 + 15.0 * iw2 * iw2 - 105.0 * iw2 * iw2 * iw2)
    if not bracket > 0.0:  # rounding at the crossover: the leading (Bahadur-Rao) term
        bracket = 1.0 / u
    return -0.5 * w2 - 0.5 * _LOG_2PI + math.log(bracket)


@kernel
def log_event_probability_exact(lam, c, b):
    """Exact ``log P(n + b > (1 + c)(n0 + b))`` for ``n, n0 ~ Poisson(lam)`` i.i.d.

    ``lam >= 0`` (``inf`` allowed), ``c = expm1(eps) > 0``, ``b >= 0``. Returns ``-inf`` at
    ``lam = 0`` (no photons, no event) and ``lam = inf``. Above :data:`LAM_EXACT_MAX` photons per
    trial the sum (whose cost grows like ``sqrt(lam)`` and whose counts lose unit resolution at
    2^53) is replaced by :func:`log_event_probability_saddlepoint`.
    """
    if not lam > 0.0 or lam == math.inf:
        return -math.inf
    if lam > LAM_EXACT_MAX:
        return log_event_probability_saddlepoint(lam, c, b)
    # The summand is non-increasing beyond the pmf mode, so its maximum lies in [0, floor(lam)].
    lo = 0.0
    hi = np.floor(lam)
    while hi - lo > 2.0:
        third = np.floor((hi - lo) / 3.0)
        m1 = lo + third
        m2 = hi - third
        if _approx_log_term(m1, lam, c, b) < _approx_log_term(m2, lam, c, b):
            lo = m1 + 1.0
        else:
            hi = m2 - 1.0
    m_star = lo
    g_star = _approx_log_term(lo, lam, c, b)
    m = lo + 1.0
    while m <= hi:
        g = _approx_log_term(m, lam, c, b)
        if g > g_star:
            g_star = g
            m_star = m
        m += 1.0
    if g_star == -math.inf:
        return -math.inf  # every threshold is infinite (c = inf, m + b > 0): no event, ever
    # Right edge: step out until the (approximate) terms are far below the maximum.
    # Above m_star the tails P(N > k(m)) do not grow, so term(m) / term(m_star) <= pmf(m) / pmf(m_star):
    # that ratio also bounds the step, where log p is too large for a difference of _LOG_WINDOW to show
    # in a double (a bias of 1e100 photons: log p ~ -5e101).
    lp_star = log_pmf(m_star, lam)
    step = 1.0
    while True:
        g = _approx_log_term(m_star + step, lam, c, b)
        if g > g_star:
            g_star = g
        if g < g_star - _LOG_WINDOW - 10.0:
            break
        if m_star + step > lam and log_pmf(m_star + step, lam) < lp_star - _LOG_WINDOW - 10.0:
            break
        step *= 2.0
    m_hi = m_star + step
    # Sweep down; verify that the first term is negligible, otherwise widen and redo.
    for _ in range(60):
        total, first = _sweep(m_hi, m_star, lam, c, b, g_star)
        if first < total - _LOG_WINDOW + 5.0:
            return total
        if m_hi > lam and log_pmf(m_hi, lam) < lp_star - _LOG_WINDOW + 5.0:
            return total  # the first term is negligible next to term(m_star) <= total
        m_hi = m_hi + 2.0 * (m_hi - m_star) + 16.0
    return total


@kernel
def log_event_probability_exact_serial(lam, c, b, out):
    """Elementwise :func:`log_event_probability_exact` over equal-length 1-D arrays, in one thread.

    For small arrays (the calibration's inner loops), where starting threads costs more than the
    work; :func:`log_event_probability_exact_array` runs it on blocks in parallel.
    """
    for i in range(lam.shape[0]):
        out[i] = log_event_probability_exact(lam[i], c[i], b[i])


_PARALLEL_BLOCKS = 256  # fine enough to share the work evenly, few enough to cost nothing


@kernel(parallel=True)
def log_event_probability_exact_array(lam, c, b, out):
    """Elementwise :func:`log_event_probability_exact` over equal-length 1-D arrays, in parallel:
    :func:`log_event_probability_exact_serial` on at most :data:`_PARALLEL_BLOCKS` contiguous blocks
    (the threads share them out as they did the elements)."""
    n = lam.shape[0]
    size = max(1, -(-n // _PARALLEL_BLOCKS))
    for k in prange((n + size - 1) // size):
        lo = k * size
        hi = min(lo + size, n)
        log_event_probability_exact_serial(lam[lo:hi], c[lo:hi], b[lo:hi], out[lo:hi])


GROUPED_MAX_LAM = 1e6  # above this a level's table (~ (c_max - c_min) lam entries) grows too large
GROUPED_MAX_TABLE = 1 << 20  # entries of one level's pmf / tail tables (16 MiB)
GROUPED_TOL = 1e-17  # the neglected terms of each pixel's sum are at most this fraction of the sum kept


@kernel
def _peak_m(lam, c, b):
    """Where ``pmf(m) P(N > k(m))`` peaks, roughly: the mean of ``n0`` under the exponential tilt
    that makes the event typical (the Chernoff point of :func:`evnoise._kernels.bounds.log_chernoff_bound`).
    Only a starting point and a table extent: every sum is stopped by a rigorous bound."""
    lo, hi = chernoff_bracket(lam, c, b, 60)
    return lam * math.exp(-(1.0 + c) * 0.5 * (lo + hi))


@kernel
def _grouped_pixel(lam, ci, b, j0, j1, pmf, sf, m_start, tol):
    """``p = sum_m pmf(m) P(N > k(m))`` for one pixel from a level's tables (``pmf[j - j0]``, ``sf[j - j0]``).

    Summed outwards from ``m_start``; each side stops once a rigorous bound on all its remaining
    terms is below ``tol`` times the sum so far. The bound: ``pmf(m') <= pmf(m) (m / lam)^j``
    for ``m' = m - j`` (and ``(lam / (m + 1))^j`` for ``m' = m + j``); ``k(m) - k(m')`` lies within
    ``j (1 + c) +- 1``; and the Poisson law is log-concave, so ``log P(N > k)`` is concave in ``k``
    and ``P(N > k - x) <= P(N > k) r^x`` with ``r = P(N > k - 1) / P(N > k)`` (``P(N > k + x) <=
    P(N > k) q^x``, ``q = P(N > k + 1) / P(N > k)``). The rest is then below a geometric series,
    ``t(m) r^2 rho / (1 - rho)`` with ``rho = (m / lam) r^(1 + c)`` downwards and
    ``t(m) q^-1 rho / (1 - rho)`` with ``rho = lam / (m + 1) q^(1 + c)`` upwards. Returns NaN
    where the terms run past the tables (the caller falls back to the windowed sum).
    """
    a_hi = 1.0 + ci * (1.0 + 1e-8)  # margins for the rounding of c (m + b)
    a_lo = 1.0 + ci * (1.0 - 1e-8)
    s = 0.0
    # upwards from m_start
    m = m_start
    n_step = 0
    while True:
        k = threshold_count(m, ci, b)
        if not (k + 1.0 <= j1 and m <= j1):
            return math.nan
        sk = sf[int(k) - j0]
        t = pmf[int(m) - j0] * sk
        s += t
        n_step += 1
        if sk == 0.0:
            break  # every later term is below the smallest double: nothing left that counts
        if n_step % 8 == 0:
            q = sf[int(k) + 1 - j0] / sk
            rho = lam / (m + 1.0) * math.exp(a_lo * math.log(q)) if q > 0.0 else 0.0
            if rho < 1.0 and t * rho <= tol * s * q * (1.0 - rho):
                break
        m += 1.0
    # downwards from m_start - 1
    m = m_start - 1.0
    n_step = 0
    while m >= 0.0:
        if m < j0:
            return math.nan
        k = threshold_count(m, ci, b)
        if not j0 <= k <= j1:
            return math.nan
        sk = sf[int(k) - j0]
        t = pmf[int(m) - j0] * sk
        s += t
        n_step += 1
        if n_step % 8 == 0 and sk > 0.0:
            if k - 1.0 < j0:
                if j0 > 0:
                    return math.nan
                r = 1.0 / sk  # P(N > -1) = 1
            else:
                r = sf[int(k) - 1 - j0] / sk
            rho = m / lam * math.exp(a_hi * math.log(r))
            if rho < 1.0 and t * r * r * rho <= tol * s * (1.0 - rho):
                break
        m -= 1.0
    return s


@kernel
def pmf_run(lam, j0, pmf):
    """``pmf[j] = P(N = j0 + j)``: exact ``log_pmf`` at every 32nd entry, the ratio recurrence
    ``pmf(j + 1) = pmf(j) lam / (j + 1)`` in between (relative error below ~32 ulps; values that
    underflow are recomputed from the anchors, never carried as 0)."""
    n = pmf.shape[0]
    for a in range(0, n, 32):
        v = math.exp(log_pmf(float(j0 + a), lam))
        pmf[a] = v
        top = min(a + 32, n)
        if v < 1e-290:
            for j in range(a + 1, top):
                pmf[j] = math.exp(log_pmf(float(j0 + j), lam))
            continue
        for j in range(a + 1, top):
            v *= lam / float(j0 + j)
            pmf[j] = v


@kernel(parallel=True)
def event_probability_grouped(lam_levels, starts, order, c, b, out, c_range):
    """``p`` for pixels that share a few ``lam`` levels but each have their own threshold.

    Pixels ``order[starts[g]:starts[g + 1]]`` all have ``lam = lam_levels[g]`` (``0 < lam <=``
    :data:`GROUPED_MAX_LAM`) and thresholds ``c[i] = expm1(eps_i)``. Per level, ``pmf(j)`` and
    ``P(N > j)`` are tabulated once over the ``j`` that the level's pixels need (the tails summed
    downwards, so they only grow); per pixel ``p = sum_m pmf(m) P(N > m + floor(c_i (m + b)))``
    is summed outwards from its peak until a rigorous bound on the remaining terms (see
    :func:`_grouped_pixel`) is below :data:`GROUPED_TOL` of the sum. Linear arithmetic: results
    below about 1e-280 lose relative accuracy, and NaN marks a pixel whose terms ran past the
    table; both should be recomputed with the windowed sum.

    A level's tables span the thresholds of its pixels, so a pixel's bits depend on the others at its level;
    ``c_range = (c_lo, c_hi)`` (containing every ``c``; ``(NaN, NaN)``: each level's own) fixes the span
    instead: each pixel's result is then a function of its own ``lam``, ``c`` and ``b`` alone, whatever else
    the call holds.
    """
    for g in prange(lam_levels.shape[0]):
        lam = lam_levels[g]
        lo = starts[g]
        hi = starts[g + 1]
        c_min = math.inf
        c_max = 0.0
        if math.isnan(c_range[0]):
            for q in range(lo, hi):
                c_min = min(c_min, c[order[q]])
                c_max = max(c_max, c[order[q]])
        else:
            c_min = c_range[0]
            c_max = c_range[1]
        if not c_max <= GROUPED_MAX_LAM:  # huge thresholds: the tables would be far too wide
            for q in range(lo, hi):
                out[order[q]] = math.nan
            continue
        width = 12.0 * math.sqrt(lam) + 40.0
        peak_lo = _peak_m(lam, c_max, b)  # the peak moves down as the threshold grows
        peak_hi = _peak_m(lam, c_min, b)
        m_a = max(0.0, np.floor(peak_lo - width))
        m_b = np.ceil(peak_hi + width)
        k_a = m_a + np.floor(c_min * (m_a + b)) - 3.0 - np.floor(c_max)
        k_b = m_b + np.floor(c_max * (m_b + b)) + 1.0 + np.floor(c_max)
        j0f = max(0.0, min(m_a, k_a))
        j1f = max(m_b, k_b) + 1.0
        if not j1f - j0f + 1.0 <= GROUPED_MAX_TABLE:  # (also NaN) checked as floats, before any int conversion
            for q in range(lo, hi):
                out[order[q]] = math.nan
            continue
        j0 = int(j0f)
        j1 = int(j1f)
        n = j1 - j0 + 1
        if n > GROUPED_MAX_TABLE:  # widely spread or large thresholds: leave the level to the windowed sum
            for q in range(lo, hi):
                out[order[q]] = math.nan
            continue
        pmf = np.empty(n + 1)
        pmf_run(lam, j0, pmf)
        sf = np.empty(n)
        sf[n - 1] = math.exp(log_sf(float(j1), lam))
        for j in range(n - 2, -1, -1):
            sf[j] = sf[j + 1] + pmf[j + 1]
        for q in range(lo, hi):
            i = order[q]
            ci = c[i]
            f = (ci - c_min) / (c_max - c_min) if c_max > c_min else 0.0
            m_start = min(max(np.floor(peak_hi + f * (peak_lo - peak_hi)), float(j0)), float(j1))
            out[i] = _grouped_pixel(lam, ci, b, j0, j1, pmf, sf, m_start, GROUPED_TOL)
