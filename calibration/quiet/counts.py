"""The count of a stationary renewal process in a window: the quiet-scene model's count distribution.

Part of :mod:`evnoise.calibration.quiet` (which uses it for the likelihood of quiet windows).

Both tails of the count law are kept to full relative precision: ``P(N >= k)`` from the regularised lower incomplete
gamma function where it is small, ``P(N < k)`` from the upper one where that is small, and ``P(N = k)`` as the
difference of whichever pair is the smaller tail (:func:`count_log_pmf`). A difference of two survival values near 1
would leave rounding noise (a pixel with no event where the model expects 60 has ``P = 8.8e-27``, which the difference
``P(N >= 0) - P(N >= 1)`` gives as 0).
"""

from __future__ import annotations

import numpy as np

__all__ = ["count_survival", "count_pmf", "count_log_pmf"]

#: Rates (events/s) at or below which the process counts as never firing (as at rate 0): ``P(N >= 1)``
#: is below ``RATE_TINY_HZ * duration_s`` there, and ``k / rate`` would overflow.
RATE_TINY_HZ = 1e-300
#: ``log P(N = k)`` of a regular timer (``regularity > 0``) where the probability is 0 in double precision: beyond
#: ``1e-300`` below the double range's end, or exactly 0 (a count a timer of that rate cannot reach, its gaps being
#: at least ``regularity / rate``). A finite floor keeps an optimiser's difference quotients numbers; at
#: ``regularity = 0`` (Poisson) the log-probability is exact at every count and there is no floor.
LOG_PMF_FLOOR = float(np.log(1e-300))


def _tails(k, rate_hz, duration_s, regularity, upper=True, lower=True):
    """``(P(N >= k), P(N < k))`` (either ``None`` when not asked for), each accurate in its own small tail.

    Gaps are ``d + Exp(theta)``, ``d = r mu``, ``theta = (1 - r) mu``, ``mu = 1 / rate``; the first arrival is the
    stationary forward recurrence time (uniform on ``[0, d)`` with probability ``r``, else ``d + Exp(theta)``), so
    ``P(N >= k) = r A + (1 - r) B`` with ``B = P(Gamma_k <= T - k d)`` and ``A`` the mean over the phase ``u`` of
    ``P(Gamma_(k-1) <= x0 - u d)``, ``x0 = T - (k - 1) d`` (``Gamma_n`` of scale ``theta``). ``A`` in closed form
    through ``int_0^y P(Gamma_n <= t) dt = theta (x P(n, x) - n P(n + 1, x))``, ``1 - A`` through the tail integral
    ``int_y^inf P(Gamma_n > t) dt = theta (n Q(n + 1, x) - x Q(n, x))`` (``x = y / theta``; ``P``, ``Q`` the
    regularised incomplete gamma functions).
    """
    from scipy.special import gammainc, gammaincc

    k = np.asarray(k, dtype=np.float64)
    rate = np.asarray(rate_hz, dtype=np.float64)
    r = float(regularity)
    T = float(duration_s)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        never = ~(rate > RATE_TINY_HZ)  # rate 0: no event in the window
        always = rate == np.inf  # events beyond any count
        mu = 1.0 / np.where(never | always, 1.0, rate)
        theta = (1.0 - r) * mu
        d = r * mu

        def p_le(n, y):  # P(Gamma_n <= y), y >= 0 (Gamma_0 = 0; r = 1: every Gamma is 0)
            if r >= 1.0:
                return np.ones(np.broadcast(n, y).shape)
            return np.where(n == 0, 1.0, gammainc(np.maximum(n, 1e-300), y / theta))

        def q_gt(n, y):  # P(Gamma_n > y), any y
            if r >= 1.0:
                return np.where(y < 0, 1.0, 0.0)
            q = np.where(n == 0, 0.0, gammaincc(np.maximum(n, 1e-300), np.maximum(y, 0.0) / theta))
            return np.where(y < 0, 1.0, q)

        def head(n, y):  # int_0^y P(Gamma_n <= t) dt (0 for y <= 0)
            y = np.maximum(y, 0.0)
            if r >= 1.0:
                return y
            x = y / theta
            return np.where(n == 0, y, y * gammainc(np.maximum(n, 1e-300), x) - n * theta * gammainc(n + 1.0, x))

        def tail(n, y):  # int_y^inf P(Gamma_n > t) dt (y < 0 adds the |y| where Gamma_n > t surely)
            if r >= 1.0:
                return np.maximum(-y, 0.0)
            x = np.maximum(y, 0.0) / theta
            at = n * theta * gammaincc(n + 1.0, x) - np.maximum(y, 0.0) * gammaincc(np.maximum(n, 1e-300), x)
            return np.where(n == 0, 0.0, np.maximum(at, 0.0)) + np.maximum(-y, 0.0)

        n = k - 1.0
        x0 = T - n * d
        y_b = T - k * d
        upper_out = lower_out = None
        if upper:
            b = 0.0 if r >= 1.0 else np.where(y_b < 0, 0.0, p_le(k, np.maximum(y_b, 0.0)))
            a = 0.0
            if r > 0:
                a = (head(n, x0) - head(n, x0 - d)) / d
                # d below the smallest double (r tiny, or a huge rate): A is its limit, not the 0 / 0 of the difference
                a = np.where(d == 0.0, np.where(x0 < 0, 0.0, p_le(n, np.maximum(x0, 0.0))), a)
            s = r * a + (1.0 - r) * b
            s = np.where(never, k <= 0, np.where(always, 1.0, s))
            upper_out = np.clip(np.where(k <= 0, 1.0, s), 0.0, 1.0)
        if lower:
            b_c = 0.0 if r >= 1.0 else q_gt(k, y_b)
            a_c = 0.0
            if r > 0:
                a_c = (tail(n, x0 - d) - tail(n, x0)) / d
                a_c = np.where(d == 0.0, q_gt(n, x0), a_c)
            f = r * a_c + (1.0 - r) * b_c
            f = np.where(never, k > 0, np.where(always, 0.0, f))
            lower_out = np.clip(np.where(k <= 0, 0.0, f), 0.0, 1.0)
    return upper_out, lower_out


def count_survival(k, rate_hz, duration_s, regularity):
    """``P(N >= k)`` of the count ``N`` in a window of a stationary renewal process (arrays broadcast).

    Gaps are ``r mu + Exp((1 - r) mu)`` with ``mu = 1 / rate_hz`` (``r`` = ``regularity``: 0 Poisson, 1
    periodic), the continuous-time form of evnoise's background timer; the closed form is :func:`_tails`'.
    Accurate relative to itself where it is small; where it is near 1, ``1 - P(N >= k)`` is
    :func:`count_log_pmf`'s business. Rates up to :data:`RATE_TINY_HZ` count as 0 (no events), an infinite rate
    as events beyond any ``k``.
    """
    return _tails(k, rate_hz, duration_s, regularity, lower=False)[0]


def count_log_pmf(k, rate_hz, duration_s, regularity):
    """``log P(N = k)`` (arrays broadcast; ``k`` whole numbers >= 0), accurate in both tails (module doc).

    Poisson (``regularity = 0``): the exact ``k log(rate T) - rate T - log k!``, finite at every count of a positive
    rate. A regular timer: the difference of the smaller tail's values at ``k`` and ``k + 1`` (:func:`_tails`),
    :data:`LOG_PMF_FLOOR` where that is 0 in double precision.
    """
    from scipy.special import gammaln, xlogy

    k = np.asarray(k, dtype=np.float64)
    rate = np.asarray(rate_hz, dtype=np.float64)
    r = float(regularity)
    if r == 0.0:
        with np.errstate(over="ignore", invalid="ignore"):
            m = np.maximum(rate, 0.0) * float(duration_s)  # a subnormal rate is still a rate: xlogy takes m = 0
            out = xlogy(k, m) - m - gammaln(k + 1.0)
            return np.where((m == np.inf) | (rate == np.inf), -np.inf, out)
    k, rate = np.broadcast_arrays(k, rate)
    pmf = np.empty(k.shape)
    # below the mean count P(N <= k) is the smaller tail (near the mean both are about 1/2 and either is accurate)
    low = k < rate * float(duration_s)
    for side, upper in ((~low, True), (low, False)):
        if np.any(side):
            at, after = (_tails(j, rate[side], duration_s, r, upper=upper, lower=not upper)[0 if upper else 1]
                         for j in (k[side], k[side] + 1.0))
            pmf[side] = at - after if upper else after - at
    with np.errstate(divide="ignore"):  # below the floor counts as the floor: never below an impossible count
        return np.where(pmf > 0.0, np.maximum(np.log(np.maximum(pmf, 1e-320)), LOG_PMF_FLOOR), LOG_PMF_FLOOR)


def count_pmf(n_max: int, rate_hz, duration_s, regularity) -> np.ndarray:
    """``P(N = n)`` for ``n = 0 .. n_max`` (last axis) at each rate (``rate_hz`` any shape)."""
    rate = np.asarray(rate_hz, dtype=np.float64)[..., None]
    k = np.arange(n_max + 1, dtype=np.float64)
    log_pmf = count_log_pmf(k, rate, duration_s, regularity)
    return np.where(log_pmf > LOG_PMF_FLOOR, np.exp(log_pmf), 0.0) if regularity > 0 else np.exp(log_pmf)
