"""Certified Chebyshev panels of the event probability in ``lam`` (not ``log lam``), for large ``lam``.

Above about ``lam = 2e4`` (``eps <= 2``) the threshold lattice makes ``log p`` ripple on a ``lam`` scale of
``sqrt(lam)``, finer than the log-spaced panels of :mod:`evnoise._kernels.chebyshev` can follow. Here the
range is cut into panels ``[lo, hi]`` of width a few ``sqrt(lam)``, and on each one the rescaled

    q(lam) = p(lam) exp(-(A + B (lam - mid)))        (A, B: the chord of log p through the end nodes)

which is of order one on the panel, is interpolated at the ``n + 1`` Chebyshev points of the first kind
(degree :data:`DEGREE`). Evaluation returns ``A + B (lam - mid) + log q_n(t)`` (log space throughout, so
``p`` far below 1e-300 is no harder than ``p = 0.1``).

What is proven (for the panel's double values ``A``, ``B``, ``mid``, ``half``):

1. ``p(z) = sum_{(n, n0) in E} e^{-2z} z^{n + n0} / (n! n0!)`` is entire (``E``: the event set of the
   integer thresholds, a subset of ``{n - (1 + c) n0 > c b}``, see :func:`evnoise._kernels.poisson.threshold_count`),
   and ``|p(z)| <= e^{2(|z| - Re z)} p(|z|)`` term by term. The Chernoff bound gives
   ``p(r) <= exp(r g(theta) - theta c b)`` for every ``theta >= 0``, ``g = expm1(theta) + expm1(-(1 + c) theta) > -2``.
2. On the Bernstein ellipse ``E_rho`` of the panel (``z = mid + half (w + 1/w) / 2``, ``|w| = rho``), write
   ``z = x + i y``: ``|z| - x = y^2 / (|z| + x) <= y^2 / (2 x)``. So ``log |q(z)|`` is below
   ``(2 + g) y^2 / (2 x) + (g - B) x + B mid - theta c b - A``; the boundary is cut into cells of
   ``cos(phi)``, each with its own ``theta`` (any ``theta`` is valid), and each term is bounded over the
   cell by monotonicity. Their maximum (plus a margin for rounding) is ``log M``: ``|q| <= M`` on ``E_rho``
   (maximum modulus principle: ``q`` is entire).
3. Interpolation in the first-kind Chebyshev points of a function analytic in ``E_rho`` and bounded by ``M``
   there: the Chebyshev coefficients obey ``|a_k| <= 2 M rho^-k``, ``T_k`` (``k > n``) interpolates to a
   polynomial of sup norm ``<= 1``, so ``|q - q_n| <= 4 M rho^-n / (rho - 1)`` on ``[-1, 1]`` (the ``rho``
   of a panel is the best of :data:`RHOS`).
4. Errors ``d_k`` of the node values propagate by at most ``Lambda_n max |d_k|`` with the Lebesgue constant
   of the Chebyshev zeros, ``Lambda_n <= (2 / pi) log(n + 1) + 1``.
5. ``q >= min q_n - |q - q_n|`` on the panel, and ``min q_n`` is bounded below from 2049 equispaced samples
   and ``|q_n''| <= sum_j |a_j| j^2 (j^2 - 1) / 3`` (so the bound need not trust the samples alone).

The panel's certified relative error of ``p`` is ``(truncation + Lambda_n node error + evaluation rounding)
/ lower bound of q``; a panel is accepted when it is at most :data:`CERT_TOL` and otherwise halved, down to
a minimum width below which the panel is evaluated with the exact sum. What is *not* proven: the node values
come from :func:`evnoise._kernels.poisson.log_event_probability_exact`, whose error is taken as
:data:`NODE_REL_ERR` plus the rounding of its double result ``u |log p|`` (``u = 2^-53``) -- measured against
mpmath, not proven -- and the floating-point rounding of the build and of Clenshaw's recurrence is bounded by
standard estimates with explicit constants. The rounding of ``log p`` itself to a double is not part of the
bound: a panel's value carries, in addition, at most ``(Lambda_n + 2) u |log p|`` of it (the exact sum's own
result carries ``u |log p|``); it matters only where ``|log p| > 1e5``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ._jit import kernel
from .bounds import chernoff_bracket
from .poisson import log_event_probability_exact

DEGREE = 40
#: certified panels cover lam from here up (below, the log-spaced panels are kept as they are)
LAM_MIN = 1e4
#: largest certified relative error of p accepted for a panel
CERT_TOL = 1e-10
#: assumed error of the exact sum: ``|log p_sum - log p| <= NODE_REL_ERR + NODE_ULPS u |log p|`` (measured
#: against mpmath: at most ~1e-15 + 44 u |log p|; tests/test_certified_large_lambda.py checks it)
NODE_REL_ERR = 1e-12
NODE_ULPS = 128.0
#: ellipse parameters tried for each panel
RHOS = np.array([2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0])
N_CELLS = 256  # cells of cos(phi) on the ellipse boundary
N_SAMPLES = 2048  # intervals of the sampling of q_n for its minimum
#: half-width of a panel, in units of sqrt(lam): first try, growth after a success, cap and floor
HALF_START = 2.5
HALF_MAX = 2.5
HALF_MIN = 0.05
_U = 2.0**-53
#: a panel's parameters: lo, hi, mid, half, A, B, bound, inherited. The certified relative error of p is at most
#: ``bound + inherited``: ``bound`` (<= CERT_TOL) is truncation, NODE_REL_ERR propagated, and rounding;
#: ``inherited`` is the exact sum's own ``NODE_ULPS u |log p|`` propagated, plus the rounding of the result.
N_PAR = 8


@kernel(parallel=True)
def _node_values(mid, half, c, b, n):
    """``log p`` at the ``n + 1`` first-kind Chebyshev points of ``[mid - half, mid + half]``, and those points."""
    lam = np.empty(n + 1)
    v = np.empty(n + 1)
    for k in prange(n + 1):
        x = math.cos(math.pi * (k + 0.5) / (n + 1))
        lam[k] = mid + half * x
        v[k] = log_event_probability_exact(lam[k], c, b)
    return lam, v


@kernel
def dct(values):
    """Chebyshev coefficients of the values at the first-kind points ``cos(pi (k + 1/2) / n)`` (also the
    log-spaced table's, :mod:`.chebyshev`)."""
    n = values.shape[0]
    a = np.zeros(n)
    for j in range(n):
        s = 0.0
        for k in range(n):
            s += values[k] * math.cos(math.pi * j * (k + 0.5) / n)
        a[j] = 2.0 * s / n
    a[0] *= 0.5
    return a


@kernel
def clenshaw(coef, t):
    """The Chebyshev series ``coef`` at ``t`` in [-1, 1] (Clenshaw's recurrence; also :mod:`.chebyshev`'s)."""
    b1 = 0.0
    b2 = 0.0
    for j in range(coef.shape[0] - 1, 0, -1):
        b0 = coef[j] + 2.0 * t * b1 - b2
        b2 = b1
        b1 = b0
    return coef[0] + t * b1 - b2


@kernel
def log_majorant(mid, half, rho, c, b, A, B, n_cells):
    """An upper bound of ``log |q(z)|`` on the Bernstein ellipse ``E_rho`` of the panel (see the module text).

    ``+inf`` when the ellipse reaches ``Re z <= 0``.
    """
    a_e = 0.5 * half * (rho + 1.0 / rho)
    b_e = 0.5 * half * (rho - 1.0 / rho)
    if not a_e < mid:
        return math.inf
    T = c * b
    a = 1.0 + c
    best = -math.inf
    for i in range(n_cells):
        c1 = -1.0 + 2.0 * i / n_cells
        c2 = -1.0 + 2.0 * (i + 1) / n_cells
        x_lo = mid + a_e * c1
        x_hi = mid + a_e * c2
        if c1 <= 0.0 <= c2:
            cmin2 = 0.0
        else:
            cmin2 = min(c1 * c1, c2 * c2)
        y2 = b_e * b_e * (1.0 - cmin2)
        r_c = math.sqrt(0.25 * (x_lo + x_hi) ** 2 + y2)  # where theta is optimised (any theta is valid)
        theta, _ = chernoff_bracket(r_c, c, b, 40)
        g = math.expm1(theta) + math.expm1(-a * theta)
        lin = max((g - B) * x_lo, (g - B) * x_hi)
        val = (2.0 + g) * y2 / (2.0 * x_lo) + lin + B * mid - theta * T - A
        scale = abs((2.0 + g) * y2 / (2.0 * x_lo)) + abs(g - B) * x_hi + abs(B) * mid + theta * T + abs(A)
        val += 1e-6 + 1e-12 * scale
        if val > best:
            best = val
    return best


@kernel
def certify_panel(lo, hi, c, b, n):
    """Interpolate ``q`` on ``[lo, hi]`` and bound its error. Returns ``(coef, par)`` (see :data:`N_PAR`);
    ``par[6] = inf`` when nothing could be certified."""
    mid = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    lam, v = _node_values(mid, half, c, b, n)
    par = np.empty(N_PAR)
    par[0] = lo
    par[1] = hi
    par[2] = mid
    par[3] = half
    par[4] = 0.0
    par[5] = 0.0
    par[6] = math.inf
    par[7] = math.inf
    for k in range(n + 1):
        if not (v[k] > -math.inf and v[k] < math.inf):
            return np.full(n + 1, math.nan), par
    B = (v[0] - v[n]) / (lam[0] - lam[n])
    A = 0.5 * (v[0] + v[n])
    par[4] = A
    par[5] = B
    q = np.empty(n + 1)
    eta = 0.0  # relative error of the node values q_k, besides the exact sum's NODE_ULPS u |log p|
    vmax = 0.0
    for k in range(n + 1):
        d = v[k] - A
        e = B * (lam[k] - mid)
        q[k] = math.exp(d - e)
        eta = max(eta, NODE_REL_ERR + 2.0 * _U * (abs(d) + abs(e)) + 2.0 * _U * abs(d - e) + 4.0 * _U)
        vmax = max(vmax, abs(v[k]))
    coef = dct(q)
    qmax = 0.0
    for k in range(n + 1):
        qmax = max(qmax, q[k])
    # truncation: the best ellipse
    log_trunc = math.inf
    log_m_best = math.inf
    rho_best = 0.0
    for i in range(RHOS.shape[0]):
        rho = RHOS[i]
        lm = log_majorant(mid, half, rho, c, b, A, B, N_CELLS)
        lt = math.log(4.0) + lm - n * math.log(rho) - math.log(rho - 1.0)
        if lt < log_trunc:
            log_trunc = lt
            log_m_best = lm
            rho_best = rho
    if not log_trunc < -10.0:
        return coef, par
    trunc = math.exp(log_trunc)
    lebesgue = 2.0 / math.pi * math.log(n + 1.0) + 1.0
    inherited = qmax * NODE_ULPS * _U * vmax  # the exact sum's own error at the nodes
    # node positions: the computed lam_k differ from mid + half x_k by <= 2u hi; x_k (a computed cosine) by 4u
    dt = 2.0 * _U * hi / half + 4.0 * _U
    s1 = 0.0
    s2 = 0.0
    sabs = 0.0
    for j in range(n + 1):
        s1 += j * j * abs(coef[j])
        s2 += abs(coef[j]) * j * j * (j * j - 1.0) / 3.0
        sabs += abs(coef[j])
    # |q'| on [-1, 1]: the interpolant's, the aliased tail's, and that of the interpolated node errors
    tail = 0.0
    m_best = math.exp(log_m_best)
    for k in range(n + 1, 100 * (n + 1)):
        term = 2.0 * m_best * (k * k + n * n) * math.exp(-k * math.log(rho_best))
        tail += term
        if k > n + 10 and term < 1e-30 * tail:
            break
    node_guess = qmax * eta * 1.0000001 + 2.0 * (n + 1.0) * (n + 4.0) * _U * qmax + 1e-9 + inherited
    d1 = s1 + tail + n * n * lebesgue * node_guess
    node_abs = qmax * eta * 1.0000001 + d1 * dt
    node_abs += 2.0 * (n + 1.0) * (n + 4.0) * _U * qmax  # rounding of the DCT
    if not node_abs <= 1e-9:
        return coef, par
    eval_abs = 2.0 * (n + 1.0) ** 2 * _U * sabs  # rounding of Clenshaw's recurrence
    # lower bound of q on [-1, 1]
    qn_min = math.inf
    for i in range(N_SAMPLES + 1):
        t = -1.0 + 2.0 * i / N_SAMPLES
        qn_min = min(qn_min, clenshaw(coef, t))
    h = 2.0 / N_SAMPLES
    qn_min -= h * h / 8.0 * s2 + eval_abs
    q_lo = qn_min - trunc - lebesgue * (node_abs + inherited)
    if not q_lo > 0.0:
        return coef, par
    par[6] = (trunc + lebesgue * node_abs + eval_abs) / q_lo
    # the exact sum's inherited error, and the rounding of A + B d + log q_n (the last: 4 u |log p|)
    par[7] = lebesgue * inherited / q_lo + 4.0 * _U * (vmax + abs(B) * half + 1.0)
    return coef, par


def build_unit(unit: int, c: float, b: float, n: int = DEGREE):
    """Certified panels covering ``lam`` in ``[max(e^unit, LAM_MIN), e^(unit + 1)]`` (slightly widened at both
    ends): a list of ``(coef | None, par)``; ``None``: a panel left to the exact sum."""
    lam_lo = max(math.exp(unit), LAM_MIN) * (1.0 - 1e-12)
    lam_hi = math.exp(unit + 1) * (1.0 + 1e-12)
    out = []
    s = HALF_START
    lo = lam_lo
    while lo < lam_hi:
        root = math.sqrt(lo)
        half = s * root
        hi = lo + 2.0 * half
        if hi > lam_hi or lam_hi - hi < 0.5 * half:  # no sliver at the end
            hi = lam_hi
        coef, par = certify_panel(lo, hi, c, b, n)
        if par[6] <= CERT_TOL:
            out.append((coef, par))
            lo = hi
            s = min(s * 1.25, HALF_MAX)
        elif s * 0.5 >= HALF_MIN:
            s *= 0.5
        else:
            par = par.copy()
            par[6] = math.inf
            out.append((None, par))
            lo = hi
    return out


def units_to_arrays(units: dict, n: int = DEGREE) -> dict:
    """``{unit: [(coef | None, par), ...]}`` as flat arrays (a panel left to the exact sum: a row of NaN)."""
    keys = sorted(units)
    start = np.zeros(len(keys) + 1, dtype=np.int64)
    pars, coefs = [], []
    for i, u in enumerate(keys):
        start[i + 1] = start[i] + len(units[u])
        for coef, par in units[u]:
            pars.append(par)
            coefs.append(np.full(n + 1, np.nan) if coef is None else coef)
    return {"units": np.array(keys, dtype=np.int64), "unit_start": start,
            "par": np.array(pars, dtype=np.float64).reshape(-1, N_PAR),
            "coef": np.array(coefs, dtype=np.float64).reshape(-1, n + 1)}


CACHED = ("units", "unit_start", "par", "coef")


def arrays_to_units(arrays: dict, first_unit: int, last_unit: int, n: int = DEGREE) -> dict | None:
    """:func:`units_to_arrays` undone, or None when the arrays are not well formed: panels contiguous and
    increasing, finite coefficients with a bound <= CERT_TOL, or a row of NaN (exact sum)."""
    units, start, par, coef = (arrays[k] for k in CACHED)
    if not (units.dtype == np.int64 and start.dtype == np.int64 and par.dtype == np.float64
            and coef.dtype == np.float64 and units.ndim == 1 and start.shape == (units.size + 1,)
            and par.ndim == 2 and par.shape[1] == N_PAR and coef.shape == (par.shape[0], n + 1)):
        return None
    if units.size and not (units[0] >= first_unit and units[-1] <= last_unit and (np.diff(units) > 0).all()):
        return None
    if not (start[0] == 0 and start[-1] == par.shape[0] and (np.diff(start) > 0).all()
            and np.isfinite(par[:, :6]).all()):
        return None
    out = {}
    for i, u in enumerate(units.tolist()):
        lo, hi = int(start[i]), int(start[i + 1])
        p = par[lo:hi]
        if not ((p[:, 0] < p[:, 1]).all() and (p[1:, 0] == p[:-1, 1]).all()):
            return None
        panels = []
        for j in range(lo, hi):
            if np.isnan(coef[j]).all():
                panels.append((None, par[j].copy()))
            elif np.isfinite(coef[j]).all() and par[j, 6] <= CERT_TOL:
                panels.append((coef[j].copy(), par[j].copy()))
            else:
                return None
        out[u] = panels
    return out


@kernel(inline=True)
def evaluate_one(x, start, end, par, coef):
    """``log p`` at ``x`` from the certified panels ``[start, end)`` of its unit; NaN where ``x`` is outside
    them or in a panel left to the exact sum."""
    if end <= start or x < par[start, 0] or x > par[end - 1, 1]:
        return math.nan
    lo = start
    hi = end - 1
    while lo < hi:  # last panel with lo <= x
        m = (lo + hi + 1) // 2
        if par[m, 0] <= x:
            lo = m
        else:
            hi = m - 1
    if math.isnan(coef[lo, 0]):
        return math.nan
    d = x - par[lo, 2]
    t = d / par[lo, 3]
    return par[lo, 4] + par[lo, 5] * d + math.log(clenshaw(coef[lo], t))
