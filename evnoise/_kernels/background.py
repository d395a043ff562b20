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
def draw_timer(s, d, log1m_a2):
    """Trials ``L >= 1`` from the first eligible trial to the next background arrival."""
    if d == math.inf:
        return math.inf
    d0 = math.floor(d)
    if uniform(s) < d - d0:
        d0 += 1.0
    return d0 + geometric(s, log1m_a2)


@kernel
def draw_timer_stationary(s, d, log1m_a2):
    """The first arrival of a timer that has been running forever: a uniform point of a length-biased ``L``.

    Length-biased ``D + G`` is, with probability ``E[D] / E[L]``, length-biased ``D`` plus ``G``, else ``D``
    plus length-biased ``G`` (``G1 + G2 - 1``); the arrival is uniform on ``1 .. L*``.
    """
    if d == math.inf:
        return math.inf
    d0 = math.floor(d)
    phi = d - d0
    a2 = -math.expm1(log1m_a2) if log1m_a2 > -math.inf else 1.0
    e_g = 1.0 / a2
    if uniform(s) * (d + e_g) < d:
        dd = d0 + 1.0 if uniform(s) * d < (d0 + 1.0) * phi else d0
        length = dd + geometric(s, log1m_a2)
    else:
        dd = d0 + 1.0 if uniform(s) < phi else d0
        length = dd + geometric(s, log1m_a2) + geometric(s, log1m_a2) - 1.0
    return 1.0 + math.floor(uniform(s) * length)
