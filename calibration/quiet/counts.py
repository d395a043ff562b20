"""The count of a stationary renewal process in a window: the quiet-scene model's count distribution.

Part of :mod:`evnoise.calibration.quiet` (which uses it for the likelihood of quiet windows).
"""

from __future__ import annotations

import numpy as np

__all__ = ["count_survival", "count_pmf"]

#: Rates (events/s) at or below which the process counts as never firing (as at rate 0): ``P(N >= 1)``
#: is below ``RATE_TINY_HZ * duration_s`` there, and ``k / rate`` would overflow.
RATE_TINY_HZ = 1e-300


def count_survival(k, rate_hz, duration_s, regularity):
    """``P(N >= k)`` of the count ``N`` in a window of a stationary renewal process (arrays broadcast).

    Gaps are ``r mu + Exp((1 - r) mu)`` with ``mu = 1 / rate_hz`` (``r`` = ``regularity``: 0 Poisson, 1
    periodic), the continuous-time form of evnoise's background timer. The first arrival is the
    stationary forward recurrence time: with probability ``r`` uniform on ``[0, r mu)``, else
    ``r mu + Exp((1 - r) mu)``, so ``P(N >= k) = r A + (1 - r) P(Gamma_k <= T - k r mu)`` with
    ``A = mean over u of P(Gamma_{k-1} <= T - (k - 1 + u) r mu)`` (Gamma of scale ``(1 - r) mu``), in
    closed form through ``int_0^Y P(Gamma_n <= y) dy = Y P(n, Y/theta) - n theta P(n + 1, Y/theta)``.
    Rates up to :data:`RATE_TINY_HZ` count as 0 (no events), an infinite rate as events beyond any ``k``.
    """
    from scipy.special import gammainc

    k = np.asarray(k, dtype=np.float64)
    rate = np.asarray(rate_hz, dtype=np.float64)
    r = float(regularity)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        live = rate > RATE_TINY_HZ
        mu = np.where(live, 1.0 / np.where(live, rate, 1.0), np.inf)
        theta = (1.0 - r) * mu
        T = float(duration_s)

        def p_gamma(n, y):  # P(Gamma_n(theta) <= y), Gamma_0 = 0
            y = np.maximum(y, 0.0)
            if r >= 1.0:
                return np.where(y > 0, 1.0, np.where(n == 0, 1.0, 0.0)) * 1.0
            val = gammainc(np.maximum(n, 1e-300), y / theta)
            return np.where(n == 0, 1.0, val)

        def integral(n, y):  # int_0^y P(Gamma_n <= t) dt
            y = np.maximum(y, 0.0)
            if r >= 1.0:
                return y
            x = y / theta
            val = y * gammainc(np.maximum(n, 1e-300), x) - n * theta * gammainc(n + 1.0, x)
            return np.where(n == 0, y, val)

        b = p_gamma(k, T - k * r * mu) if r < 1.0 else 0.0
        if r > 0:
            x0 = T - (k - 1.0) * r * mu
            step = r * mu  # the range of the uniform phase
            a = (integral(k - 1.0, x0) - integral(k - 1.0, x0 - step)) / step
            if np.any(step == 0.0):
                # r mu below the smallest double (r tiny, or a huge rate): A is its limit, P(Gamma_{k-1} <= x0),
                # not the 0 / 0 of the difference
                a = np.where(step == 0.0, p_gamma(k - 1.0, x0), a)
        else:
            a = 0.0
        out = r * a + (1.0 - r) * b
        out = np.where(k <= 0, 1.0, out)
        out = np.where(np.isfinite(mu), out, np.where(k <= 0, 1.0, 0.0))
    return np.clip(out, 0.0, 1.0)


def count_pmf(n_max: int, rate_hz, duration_s, regularity) -> np.ndarray:
    """``P(N = n)`` for ``n = 0 .. n_max`` (last axis) at each rate (``rate_hz`` any shape)."""
    rate = np.asarray(rate_hz, dtype=np.float64)[..., None]
    k = np.arange(n_max + 2, dtype=np.float64)
    surv = count_survival(k, rate, duration_s, regularity)
    return np.maximum(surv[..., :-1] - surv[..., 1:], 0.0)
