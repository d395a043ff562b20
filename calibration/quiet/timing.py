"""The timing likelihood of quiet windows: each pixel's event times, integrated over the spread of its rate.

Part of :mod:`evnoise.calibration.quiet` (:mod:`.likelihood` builds the components and mixes them).

A pixel's events in a window of ``T`` seconds are a stationary renewal process of rate ``lam`` with gaps
``d + Exp(theta)``, ``d = r / lam``, ``theta = (1 - r) / lam`` (the module doc of :mod:`.likelihood`). Its
density depends on the event times only through a few numbers per window (:func:`timing_statistics`): the
count ``k`` (``k_on``, ``k_off``), the first time ``f``, the censored tail ``t = T - last`` and the shortest gap
``m``. With ON and OFF rates ``n_on + n_off = lam`` and ``k >= 1``,

    log density = k_on log n_on + k_off log n_off - (k - 1) log(1 - r) - E,
    E = [lam (T - f - t) - (k - 1) r + max(lam f - r, 0) + max(lam t - r, 0)] / (1 - r),

for ``lam m >= r`` (a gap shorter than ``d`` has density 0), and a window without events has probability
``1 - lam T`` for ``lam T <= r``, ``(1 - r) exp(-(lam T - r) / (1 - r))`` beyond. (At ``r = 0``:
``k_on log n_on + k_off log n_off - lam T`` and ``exp(-lam T)``.)

The spread: a component's rates are ``n = a exp(sigma z) + c`` per window and polarity (``a``: the spread
part, ``c``: what does not spread, e.g. the shot noise or a hot pixel's ordinary rate), ``z`` standard normal;
the pixel's likelihood is ``int phi(z) exp(sum over windows of the log density) dz``. With many gaps and a
regular timer this integrand is a spike: it is 0 below the ``z`` where ``lam m = r`` and falls by ``e`` within
about ``(1 - r) / (k r sigma)`` above it, far narrower than any fixed grid over ``z`` (on the old 241-node grid
a pixel's integral was off by factors 0.002 to 3 depending on where the cut fell between two nodes, which
biased the fit and left the numerical Hessian without a positive-definite information). So each pixel is
integrated on its own nodes (:func:`log_spread_integral`): the integrand's mode (at the support's lower end
``z_c`` or at a kink where the one-sided derivatives change sign, else a Newton root of the derivative between
two kinks: the log-integrand is concave between its kinks where ``c = 0``), the two points where it has
fallen by :data:`DROP` (Newton on the log of the fall, or the support's ends) and Gauss-Legendre panels
between them, graded away from the mode, whose edges include every kink (where ``lam f``, ``lam t`` or
``lam T`` passes ``r``). A pixel's integral agrees with adaptive quadrature to about 1e-11 (measured in
tests/test_quiet_timing_selfconsistency.py), so where the nodes fall matters only at that level: the
likelihood is smooth in the parameters and its numerical Hessian gives the standard errors.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["timing_statistics", "log_spread_integral", "log_point_density", "DROP", "SIDE_PANELS", "NODES",
           "Z_LIMIT", "R_MAX"]

#: The integration range of a pixel ends where the log-integrand is this far below its maximum (e^-40 ~ 4e-18).
DROP = 40.0
#: Gauss-Legendre panels on each side of the mode (edges at ``(j / SIDE_PANELS)^2`` of the way to the range's end;
#: the kinks add theirs) and nodes per panel. On model integrands (a normal, an exponential, a double-exponential
#: wall, a log-gamma tail) 4 x 8 has relative error at most 2e-9;
#: tests/test_quiet_timing_selfconsistency.py measures it on the likelihood's own integrands against adaptive
#: quadrature.
SIDE_PANELS = 4
NODES = 8
#: ``z`` beyond +-Z_LIMIT (prior density below e^-800) is not integrated.
Z_LIMIT = 40.0
#: Largest argument of ``exp`` in a rate (beyond it the rate is inf in float64).
_EXP_MAX = 700.0
#: A regularity of 1 (a logit beyond ~37 rounds to it) is taken as this: a periodic timer's gaps are all ``1 / lam``,
#: a density 0 for any other gap; just below 1 the likelihood is finite and falls steeply towards 1.
R_MAX = 1.0 - 1e-12
_GL_X, _GL_W = np.polynomial.legendre.leggauss(NODES)
_NEWTON_STEPS = 100
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def timing_statistics(windows_events, durations, n_pix):
    """Per-pixel numbers of the timing likelihood: ``dict`` of arrays ``(W, P)`` ``k``, ``k_on``, ``k_off``,
    ``first``, ``tail``, ``min_gap`` (``inf`` below two events), ``T`` ``(W, 1)`` and ``weight`` ``(P,)``.

    ``windows_events``: per window the events as :func:`.window.window_events` gives them (``pixel``, ``t_s``,
    ``on``; sorted by pixel, then time); columns are the pixels with an event in any window, then (weight: the
    number of pixels without any event, left out when there are none) one column of those silent pixels.
    """
    active = np.unique(np.concatenate([ev["pixel"] for ev in windows_events]))
    n_silent = int(n_pix - active.size)
    n_col = active.size + (n_silent > 0)
    W = len(windows_events)
    out = {name: np.zeros((W, n_col)) for name in ("k", "k_on", "k_off", "first", "tail")}
    out["min_gap"] = np.full((W, n_col), np.inf)
    out["T"] = np.asarray(durations, dtype=np.float64).reshape(W, 1)
    for wi, ev in enumerate(windows_events):
        T = float(durations[wi])
        a = np.searchsorted(active, ev["pixel"])
        k = np.bincount(a, minlength=n_col).astype(np.float64)
        k_on = np.bincount(a, weights=ev["on"].astype(np.float64), minlength=n_col)
        out["k"][wi], out["k_on"][wi], out["k_off"][wi] = k, k_on, k - k_on
        if not ev["pixel"].size:
            continue
        t = np.clip(ev["t_s"], 0.0, T)
        start = np.r_[True, ev["pixel"][1:] != ev["pixel"][:-1]]
        stop = np.r_[ev["pixel"][1:] != ev["pixel"][:-1], True]
        out["first"][wi, a[start]] = t[start]
        out["tail"][wi, a[stop]] = T - t[stop]
        same = ~start[1:]
        if np.any(same):
            gaps = np.diff(t)[same]
            np.minimum.at(out["min_gap"][wi], a[1:][same], gaps)
    out["weight"] = np.r_[np.ones(active.size), [float(n_silent)] * (n_silent > 0)]
    return out


def _xlogy(k, x):
    """``k log x`` with ``0 log 0 = 0`` (``-inf`` for ``k > 0``, ``x = 0``), without warnings."""
    with np.errstate(divide="ignore"):
        return np.where(k > 0, k * np.log(np.where(k > 0, x, 1.0)), 0.0)


def _prepare(comp, st, r):
    """The pixel columns' constants of one component's log-integrand (``(W, P)`` arrays, ``st``'s columns)."""
    k, k_on, k_off = st["k"], st["k_on"], st["k_off"]
    f, tl = st["first"], st["tail"]
    pre = {"k": k, "k_on": k_on, "k_off": k_off, "first": f, "tail": tl, "span": st["T"] - f - tl,
           "has": k > 0, "T": st["T"]}
    no_shot = (np.all(np.asarray(comp["c_on"]) == 0) and np.all(np.asarray(comp["c_off"]) == 0)
               and np.all(np.asarray(comp["a_on"]) > 0) and np.all(np.asarray(comp["a_off"]) > 0))
    const = np.where(k > 0, (k - 1.0) * (r / (1.0 - r) - math.log1p(-r)), 0.0)
    if no_shot:  # k_on log n_on + k_off log n_off = k sigma z + (k_on log a_on + k_off log a_off)
        const = const + k_on * np.log(comp["a_on"])[:, None] + k_off * np.log(comp["a_off"])[:, None]
    pre["const"] = const
    pre["no_shot"] = no_shot
    return pre


def _columns(st, keep):
    """The pixel columns ``keep`` of the per-column arrays ``st`` (``(W, P)``; ``T`` and flags stay)."""
    return {name: (val[:, keep] if name != "T" and isinstance(val, np.ndarray) and val.ndim == 2 else val)
            for name, val in st.items()}


def _psi(z, comp, pre, r, order=0):
    """The log-integrand over ``z`` (without ``log sqrt(2 pi)``) of the pixel columns of ``pre`` (:func:`_prepare`;
    ``z`` ``(P,)`` or ``(P, N)``): ``-z^2 / 2`` plus each window's log density (module doc) at the component's
    rates ``a exp(sigma z) + c``; with ``order`` 2 also its first two derivatives in ``z``."""
    sigma = comp["sigma"]
    one_m_r = 1.0 - r
    two = z.ndim == 2
    e = np.exp(np.minimum(sigma * z, _EXP_MAX))
    val = -0.5 * z * z
    if order:
        d1 = -z
        d2 = -np.ones_like(z)
    for wi in range(pre["k"].shape[0]):

        def col(name):
            x = pre[name][wi]
            return x[:, None] if two else x

        a_on, a_off = comp["a_on"][wi], comp["a_off"][wi]
        c_on, c_off = comp["c_on"][wi], comp["c_off"][wi]
        u = (a_on + a_off) * e
        lam = u + (c_on + c_off)
        k, k_on, k_off, f, tl = col("k"), col("k_on"), col("k_off"), col("first"), col("tail")
        over_f = np.maximum(lam * f - r, 0.0)
        over_t = np.maximum(lam * tl - r, 0.0)
        if pre["no_shot"]:
            pol = (sigma * k) * z
        else:
            pol = _xlogy(k_on, a_on * e + c_on) + _xlogy(k_off, a_off * e + c_off)
        v = col("const") + pol - (lam * col("span") + over_f + over_t) / one_m_r
        has = pre["has"][wi]
        everyone = bool(np.all(has))
        T = float(pre["T"][wi, 0])
        if not everyone:
            lt = lam * T
            early = lt <= r
            silent = np.where(early, np.log1p(-np.minimum(lt, r)), math.log1p(-r) - (lt - r) / one_m_r)
            v = np.where(col("has"), v, silent)
        val = val + v
        if not order:
            continue
        beta = col("span") + np.where(over_f > 0, f, 0.0) + np.where(over_t > 0, tl, 0.0)
        if pre["no_shot"]:
            g1 = sigma * k
            g2 = 0.0
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                x_on = np.where(k_on > 0, a_on * e / (a_on * e + c_on), 0.0)
                x_off = np.where(k_off > 0, a_off * e / (a_off * e + c_off), 0.0)
            g1 = sigma * (k_on * x_on + k_off * x_off)
            g2 = sigma * sigma * (k_on * x_on * (1.0 - x_on) + k_off * x_off * (1.0 - x_off))
        e1 = g1 - sigma * u * beta / one_m_r
        e2 = g2 - sigma * sigma * u * beta / one_m_r
        if not everyone:
            one_m = np.where(early, 1.0 - np.minimum(lt, r), 1.0)
            h1 = np.where(early, -T / one_m, -T / one_m_r)
            h2 = np.where(early, -(T / one_m) ** 2, 0.0)
            e1 = np.where(col("has"), e1, sigma * u * h1)
            e2 = np.where(col("has"), e2, sigma * sigma * (u * h1 + u * u * h2))
        d1 = d1 + e1
        d2 = d2 + e2
    if not order:
        return val
    return val, d1, d2


def _node_values(nodes, mid, comp, pre, r):
    """:func:`_psi` at the quadrature nodes ``(P, panels * NODES)`` of panels with midpoints ``mid`` ``(P, panels)``.

    Between two kinks each window's log density is ``C + k sigma z - B exp(sigma z)`` where the rates are
    ``a exp(sigma z)`` (no ``c``) and the pixel has events in every window: those columns are summed that way,
    with ``C`` and ``B`` taken per panel (a kink is a panel edge, so a panel's midpoint says which side of it the
    whole panel lies on); the others go through :func:`_psi`.
    """
    def generic(z, cols):
        return _psi(z.reshape(z.shape[0], -1), comp, cols, r).reshape(z.shape)

    if not pre["no_shot"]:
        return generic(nodes, pre)
    fast = np.all(pre["has"], axis=0)
    out = np.empty(nodes.shape)
    if not np.all(fast):
        out[~fast] = generic(nodes[~fast], _columns(pre, ~fast))
    if not np.any(fast):
        return out
    sub = _columns(pre, fast)
    sigma = comp["sigma"]
    one_m_r = 1.0 - r
    with np.errstate(over="ignore"):
        e_mid = np.exp(sigma * mid[fast])
    C = np.zeros(e_mid.shape)
    B = np.zeros(e_mid.shape)
    K = np.zeros(e_mid.shape[0])
    for wi in range(sub["k"].shape[0]):
        a = comp["a_on"][wi] + comp["a_off"][wi]
        f, tl = sub["first"][wi][:, None], sub["tail"][wi][:, None]
        past_f = a * e_mid * f > r
        past_t = a * e_mid * tl > r
        beta = sub["span"][wi][:, None] + np.where(past_f, f, 0.0) + np.where(past_t, tl, 0.0)
        C += sub["const"][wi][:, None] + (r / one_m_r) * (past_f.astype(np.float64) + past_t)
        B += (a / one_m_r) * beta
        K += sigma * sub["k"][wi]
    z = nodes[fast]
    with np.errstate(over="ignore", invalid="ignore"):
        e = np.exp(sigma * z)
        vals = C[:, :, None] + (K[:, None, None] - 0.5 * z) * z - B[:, :, None] * e
    out[fast] = np.where(np.isnan(vals), -np.inf, vals)
    return out


def _z_of_rate(level, comp, wi):
    """``z`` where the component's total rate in window ``wi`` reaches ``level`` (``-inf`` if it is always above,
    ``inf`` if never; arrays)."""
    a = comp["a_on"][wi] + comp["a_off"][wi]
    c = comp["c_on"][wi] + comp["c_off"][wi]
    sigma = comp["sigma"]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        excess = np.asarray(level, dtype=np.float64) - c
        if a > 0:
            z = np.where(excess > 0, (np.log(np.where(excess > 0, excess, 1.0)) - math.log(a)) / sigma, -np.inf)
        else:
            z = np.where(excess > 0, np.inf, -np.inf)
    return np.where(np.isnan(z), np.inf, z)


def _solve(fun, lo, hi, x0, decreasing, close):
    """A root of the monotone ``fun(x, idx) -> (g, g')`` (columns ``idx``) in each bracket ``[lo, hi]``: Newton steps
    kept inside the bracket, bisection otherwise, until ``close(g, g', width)`` (vectorised)."""
    a, b = lo.copy(), hi.copy()
    x = np.clip(x0, a, b)
    idx = np.arange(x.size)
    for _ in range(_NEWTON_STEPS):
        g, dg = fun(x[idx], idx)
        done = close(g, dg, b[idx] - a[idx], idx)
        above = (g > 0) if decreasing else (g < 0)  # the root lies above x
        a[idx] = np.where(above, x[idx], a[idx])
        b[idx] = np.where(above, b[idx], x[idx])
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            xn = x[idx] - g / dg
        bad = ~((xn > a[idx]) & (xn < b[idx]))
        xn = np.where(bad, 0.5 * (a[idx] + b[idx]), xn)
        x[idx] = np.where(done, x[idx], xn)
        idx = idx[~done]
        if not idx.size:
            break
    return x


def log_spread_integral(comp, st, r):
    """``log int phi(z) exp(sum over windows of log density) dz`` per pixel column of ``st`` (module doc).

    ``comp``: ``a_on``, ``a_off``, ``c_on``, ``c_off`` (per window, events/s) and ``sigma`` > 0; ``r`` the
    regularity. ``-inf`` where no ``z`` within :data:`Z_LIMIT` allows the pixel's shortest gaps.
    """
    # an optimiser's trial point far from any sensor (a rate that underflows to 0 or overflows) gives inf and nan
    # on the way: they end as a log-integrand of -inf (see the end), never as a warning
    with np.errstate(all="ignore"):
        return _log_spread_integral(comp, st, min(float(r), R_MAX))


def _log_spread_integral(comp, st, r):
    """:func:`log_spread_integral`'s work (floating-point errors ignored there: they end as ``-inf``)."""
    n_col = st["k"].shape[1]
    z_c = np.full(n_col, -Z_LIMIT)
    kinks = []
    if r > 0:
        with np.errstate(divide="ignore"):
            for wi in range(st["k"].shape[0]):
                z_c = np.maximum(z_c, _z_of_rate(r / st["min_gap"][wi], comp, wi))
                has = st["k"][wi] > 0
                kinks.append(_z_of_rate(np.where(has, r / np.where(has, st["first"][wi], 1.0), r / st["T"][wi, 0]),
                                        comp, wi))
                kinks.append(np.where(has, _z_of_rate(r / st["tail"][wi], comp, wi), -np.inf))
    out = np.full(n_col, -np.inf)
    ok = z_c < Z_LIMIT
    if not np.any(ok):
        return out
    pre = _columns(_prepare(comp, st, r), ok)
    lo = z_c[ok]
    hi = np.full(lo.shape, Z_LIMIT)
    kinks = [np.clip(kk[ok], lo, hi) for kk in kinks]
    n = lo.size

    def at(x, idx, order=0):
        return _psi(x, comp, pre if idx is None else _columns(pre, idx), r, order)

    # the mode: psi is concave between its kinks and its derivative falls at each (where c = 0): the kinks (and the
    # support's lower end) whose one-sided derivatives have opposite signs hold it; else it is the root of psi'
    # between the last kink where psi still rises and the first where it falls
    a, b = lo.copy(), hi.copy()
    x_star = np.full(n, np.nan)
    for kk in [lo] + kinks:
        step = 1e-9 * (1.0 + np.abs(kk))
        below = at(np.maximum(kk - step, lo), None, 2)[1]
        above = at(np.minimum(kk + step, hi), None, 2)[1]
        inside = (kk > lo) & (kk < hi)
        x_star = np.where(np.isnan(x_star) & (above <= 0) & ((below >= 0) | ~inside) & (kk < hi), kk, x_star)
        a = np.where(above > 0, np.maximum(a, kk), a)
        b = np.where(inside & (below < 0), np.minimum(b, kk), b)
    todo = np.flatnonzero(np.isnan(x_star))
    if todo.size:

        def slope(x, idx):
            return at(x, todo[idx], 2)[1:]

        def flat(g, dg, width, idx):  # within 1e-4 of the maximum of psi
            return (g * g <= 2e-4 * np.abs(dg)) | (np.abs(g) * width <= 1e-4)

        x_star[todo] = _solve(slope, a[todo], b[todo], 0.5 * (a[todo] + b[todo]), True, flat)
    psi_star, _, curv = at(x_star, None, 2)
    live = np.isfinite(psi_star) & np.isfinite(x_star)
    if not np.all(live):  # the integrand is 0 (or not a number) at its mode: -inf
        keep = np.flatnonzero(ok)[live]
        ok[:] = False
        ok[keep] = True
        pre, lo, hi, x_star, psi_star, curv = (_columns(pre, live), lo[live], hi[live], x_star[live], psi_star[live],
                                               curv[live])
        kinks = [kk[live] for kk in kinks]
        n = lo.size
        if not n:
            return out
    target = psi_star - DROP

    # the range: where psi has fallen by DROP on each side (Newton on log(psi* - psi), nearly linear in z for
    # normal, exponential and double-exponential tails alike), or the support's ends
    def log_fall(x, idx):
        val, d1, _ = at(x, idx, 2)
        fall = np.maximum(psi_star[idx] - val, 1e-300)
        return np.log(fall) - math.log(DROP), -d1 / fall

    def near(g, dg, width, idx):  # the fall within DROP * (1 +- 5 %)
        return np.abs(g) <= 0.05

    reach = math.sqrt(2.0 * DROP) / np.sqrt(np.maximum(-curv, 1e-12))
    left, right = lo.copy(), hi.copy()
    for end, side, sign in ((lo, left, -1.0), (hi, right, 1.0)):
        cut = np.flatnonzero(at(end, None) < target)
        if cut.size:
            lo_b, hi_b = (end[cut], x_star[cut]) if sign < 0 else (x_star[cut], end[cut])
            side[cut] = _solve(lambda x, idx, cut=cut: log_fall(x, cut[idx]), lo_b, hi_b,
                               x_star[cut] + sign * reach[cut], sign < 0, near)
    # panels graded away from the mode on each side (widths growing like j^2: fine where the integrand is large,
    # wide in its tails), the kinks added as edges
    grade = (np.arange(SIDE_PANELS + 1) / SIDE_PANELS) ** 2
    edges = [x_star[:, None] - (x_star - left)[:, None] * grade[None, ::-1],
             x_star[:, None] + (right - x_star)[:, None] * grade[None, 1:]]
    edges += [np.clip(kk, left, right)[:, None] for kk in kinks]
    edges = np.sort(np.concatenate(edges, axis=1), axis=1)
    half = 0.5 * np.diff(edges, axis=1)  # (A, panels)
    mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
    nodes = mid[:, :, None] + half[:, :, None] * _GL_X
    vals = _node_values(nodes, mid, comp, pre, r)  # (A, panels, NODES), at most psi_star (+ the mode's tolerance)
    vals = np.where(np.isnan(vals), -np.inf, vals)
    total = np.einsum("apn,ap,n->a", np.exp(vals - psi_star[:, None, None]), half, _GL_W)
    out[ok] = np.where(np.isfinite(total), np.log(total) + psi_star - _LOG_SQRT_2PI, -np.inf)
    return out


def log_point_density(rates_on, rates_off, st, r):
    """log density of each pixel column's event times at fixed rates (no spread): ``rates_on``, ``rates_off``
    per window (events/s); ``-inf`` where a gap is shorter than ``r / rate``."""
    r = min(float(r), R_MAX)
    comp = dict(a_on=np.zeros(len(rates_on)), a_off=np.zeros(len(rates_on)), c_on=np.asarray(rates_on, float),
                c_off=np.asarray(rates_off, float), sigma=0.0)
    with np.errstate(all="ignore"):
        val = _psi(np.zeros(st["k"].shape[1]), comp, _prepare(comp, st, r), r)
        lam = (comp["c_on"] + comp["c_off"])[:, None]
        feasible = np.all(lam * st["min_gap"] >= r, axis=0) & ~np.isnan(val)
    return np.where(feasible, val, -np.inf)
