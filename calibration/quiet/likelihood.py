"""The likelihood of quiet windows (the model of :mod:`evnoise.calibration.quiet`'s docstring).

Per-pixel count vectors over a recording's windows, integrated over the spread of the rates (and the
hot pixels) on a fixed grid of the standard normal; the maximisation and the numerical Hessian.
Part of :mod:`evnoise.calibration.quiet`; used by :mod:`.fit` and :mod:`.goodness`.

Timing likelihood (``Model.timing``, windows read with their events): each pixel's event *times* in
the window, not only its counts. A pixel's events are a stationary renewal process with gaps
``d + Exp(theta)``, ``d = r mu``, ``theta = (1 - r) mu``, ``mu = 1 / rate`` (the simulator's regular
timer, Poisson at ``r = 0``). With survival ``S(x) = exp(-max(x - d, 0) / theta)`` and gap density
``g(x) = exp(-(x - d) / theta) / theta`` for ``x > d`` (0 below), events at ``t_1 < ... < t_k`` in
``[0, T)`` have density ``rate S(t_1) * prod g(t_(i+1) - t_i) * S(T - t_k)`` (the first from the
stationary forward-recurrence law, the last interval censored by the window's end), and no event has
probability ``rate int_T^inf S = 1 - rate T`` for ``T <= d``, ``(1 - r) exp(-(T - d) / theta)`` beyond.
Each event is ON with the pixel's ON share. This density integrated over the count of the window is the
count likelihood, so the timing likelihood holds all of it and more. The ordinary pixels and the hot
pixels may have their own regularity (``Model.hot_regular``: ``hot_regularity``). The density depends on a
pixel's times only through its first event, its last, its shortest gap and its counts, and each pixel's
integral over the spread is taken on nodes of its own (:mod:`.timing`): with many gaps and a regular timer
the integrand is a spike far narrower than any fixed grid over the spread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from evnoise.errors import InputError

from .counts import count_log_pmf
from .timing import log_point_density, log_spread_integral, timing_statistics

#: Grid points of the standard normal (over +-7 sd) for the integrals over the spread.
GRID = 241
_Z = np.linspace(-7.0, 7.0, GRID)
_WZ = np.exp(-0.5 * _Z * _Z)
_WZ /= _WZ.sum()
_LOG_WZ = np.log(_WZ)
_Z_MAX = float(_Z[-1])
#: Hot pixels: at most this fraction of the pixels, at least this many times the ordinary mean rate.
HOT_MAX_FRACTION = 0.05
HOT_MIN_RATIO = 5.0
#: Largest per-pixel rate (events/s) the likelihood evaluates. Only an optimiser's trial point far from
#: any sensor gets there (a long step in a log rate, a hot-pixel rate that overflows); the log-likelihood
#: is -inf there, where the arithmetic would overflow to inf and NaN.
RATE_MAX_HZ = 1e300

@dataclass
class _Group:
    """The pixels of one recording: unique count vectors over its windows and their multiplicities."""

    windows: list
    vectors: np.ndarray  # (U, n_windows, 2) counts
    weight: np.ndarray   # (U,) number of pixels with that vector
    log_binom: np.ndarray  # (U,) sum over windows of log C(k_on + k_off, k_on)
    #: the timing likelihood's per-pixel statistics (:func:`.timing.timing_statistics`), or None (counts only)
    timing: dict | None = None


def window_groups(windows) -> list:
    from scipy.special import gammaln

    by = {}
    for w in windows:
        by.setdefault(w.group, []).append(w)
    out = []
    for name, ws in by.items():
        shapes = {w.shape for w in ws}
        if len(shapes) > 1:
            raise InputError(f"windows of {name} have different sensor sizes: {sorted(shapes)}")
        if len({w.excluded.tobytes() for w in ws}) > 1:
            raise InputError(f"windows of {name} exclude different pixels (use window.same_exclusions)")
        stack = np.stack([w.pixel_counts().T for w in ws], axis=1)  # (P, n_windows, 2), the kept pixels
        flat = stack.reshape(stack.shape[0], -1)
        uniq, mult = np.unique(flat, axis=0, return_counts=True)
        vec = uniq.reshape(-1, len(ws), 2)
        tot = vec.sum(axis=2)
        log_binom = (gammaln(tot + 1.0) - gammaln(vec[..., 0] + 1.0) - gammaln(vec[..., 1] + 1.0)).sum(axis=1)
        timing = None
        if all(w.events is not None for w in ws):
            timing = timing_statistics([w.events for w in ws], [w.duration_s for w in ws], stack.shape[0])
        out.append(_Group(ws, vec, mult.astype(np.float64), log_binom, timing))
    return out


@dataclass
class Model:
    """What is free and the fixed shot-noise rates of each window (``shot``: (n_windows, 2) per group)."""

    spread: bool
    hot: bool
    shot: list  # per group, (n_windows, 2) events/s added to every pixel (0 without lux)
    growth: bool = False  # background grows with lux: rate = r + g * lux
    lux: list = field(default_factory=list)
    regular: bool = False  # fit the regularity of the arrivals (else Poisson, r = 0)
    timing: bool = False  # the likelihood of the event times (module doc), else of the counts
    hot_regular: bool = False  # the hot pixels have their own regularity (else the ordinary pixels')


def _exp(x):
    return math.exp(min(x, 700.0))


def _sigmoid(x):
    return 1.0 / (1.0 + math.exp(-x)) if x >= 0 else math.exp(x) / (1.0 + math.exp(x))


def unpack(theta, model: Model):
    v = dict(zip(("log_on", "log_off"), theta[:2]))
    i = 2
    v["sigma"] = _exp(theta[i]) if model.spread else 0.0
    i += model.spread
    if model.hot:
        # hot pixels are a minority (f < HOT_MAX_FRACTION) far above the ordinary rate (> HOT_MIN_RATIO times it):
        # without these bounds the second component can take over the role of the spread
        f = HOT_MAX_FRACTION * _sigmoid(theta[i])
        ordinary = _exp(theta[0]) + _exp(theta[1])
        v.update(hot_fraction=f, hot_rate_hz=ordinary * (HOT_MIN_RATIO + _exp(theta[i + 1])),
                 hot_sigma=_exp(theta[i + 2]), hot_on_fraction=_sigmoid(theta[i + 3]))
        i += 4
    else:
        v.update(hot_fraction=0.0, hot_rate_hz=0.0, hot_sigma=0.0, hot_on_fraction=0.5)
    if model.growth:
        v["growth_on"], v["growth_off"] = _exp(theta[i]), _exp(theta[i + 1])
        i += 2
    else:
        v["growth_on"] = v["growth_off"] = 0.0
    v["regularity"] = _sigmoid(theta[i]) if model.regular else 0.0
    i += model.regular
    v["hot_regularity"] = _sigmoid(theta[i]) if (model.hot and model.hot_regular) else v["regularity"]
    v["rate_on_hz"], v["rate_off_hz"] = _exp(v.pop("log_on")), _exp(v.pop("log_off"))
    return v


def component_rates(v, group_index, model: Model, grp: _Group):
    """Per component: total rates (M, W) events/s and ON shares (M, W) over its grid."""
    z, wz = _Z, _WZ
    T = np.array([w.duration_s for w in grp.windows])
    shot = model.shot[group_index]
    lux = model.lux[group_index] if model.growth else np.zeros(len(T))
    base = np.stack([v["rate_on_hz"] + v["growth_on"] * lux, v["rate_off_hz"] + v["growth_off"] * lux], axis=1)
    sigma = v["sigma"]
    s = np.exp(-0.5 * sigma * sigma + sigma * z) if sigma > 0 else np.ones(1)
    per_pol = s[:, None, None] * base[None] + shot[None]  # (M, W, 2)
    comps = [(per_pol.sum(axis=2), per_pol[..., 0] / np.maximum(per_pol.sum(axis=2), 1e-300),
              wz if sigma > 0 else np.ones(1))]
    if v["hot_fraction"] > 0:
        sh = v["hot_sigma"]
        h = v["hot_rate_hz"] * np.exp(-0.5 * sh * sh + sh * z) if sh > 0 else np.full(1, v["hot_rate_hz"])
        q = v["hot_on_fraction"]
        hot = h[:, None, None] * np.array([q, 1.0 - q])[None, None, :] + base[None] + shot[None]
        comps.append((hot.sum(axis=2), hot[..., 0] / np.maximum(hot.sum(axis=2), 1e-300),
                      wz if sh > 0 else np.ones(1)))
    return comps


def _log_component(vec, rates, share_on, weights, grp: _Group, regularity):
    """log of sum over nodes of weight * prod over windows P(counts) for vectors (U, W, 2) -> (U,)."""
    from scipy.special import logsumexp

    n_tot = vec.sum(axis=2)  # (U, W)
    acc = np.zeros((vec.shape[0], rates.shape[0]))
    for wi, w in enumerate(grp.windows):
        needed, where = np.unique(n_tot[:, wi], return_inverse=True)
        log_pmf = count_log_pmf(needed[None, :].astype(np.float64), rates[:, wi, None], w.duration_s,
                                regularity)[:, where]  # (M, U)
        with np.errstate(divide="ignore"):
            lq = np.log(np.maximum(share_on[:, wi], 1e-300))
            l1q = np.log(np.maximum(1.0 - share_on[:, wi], 1e-300))
        k_on = vec[:, wi, 0].astype(np.float64)
        k_off = vec[:, wi, 1].astype(np.float64)
        acc += log_pmf.T + np.outer(k_on, lq) + np.outer(k_off, l1q)
    return logsumexp(acc + np.log(weights)[None, :], axis=1)


def _log_mix(vec, comps, v, grp, regularity):
    """log-likelihood (U,) of each count vector under the mixture (binomial-split constants excluded)."""
    lo = _log_component(vec, *comps[0], grp, regularity)
    if len(comps) == 1:
        return lo
    lh = _log_component(vec, *comps[1], grp, v.get("hot_regularity", regularity))
    f = min(max(v["hot_fraction"], 1e-300), 0.5)
    return np.logaddexp(math.log1p(-f) + lo, math.log(f) + lh)


def _log_peak_rate(rate_hz, sigma):
    """log of the largest of ``rate_hz * exp(-sigma^2 / 2 + sigma z)`` over the grid (``-inf`` for 0)."""
    if not rate_hz > 0.0:
        return -math.inf
    if not math.isfinite(rate_hz):
        return math.inf
    return math.log(rate_hz) + sigma * (_Z_MAX - 0.5 * sigma)  # -inf where sigma * sigma overflows


def _rates_in_range(v, model: Model) -> bool:
    """Whether every rate of the model (each component on its whole grid, every window) is at most
    :data:`RATE_MAX_HZ`, so that sums and shares of the rates stay finite."""
    lux_max = max((float(np.max(x, initial=0.0)) for x in model.lux), default=0.0) if model.growth else 0.0
    shot_max = max((float(np.max(x, initial=0.0)) for x in model.shot), default=0.0)
    top = max(v["rate_on_hz"] + v["growth_on"] * lux_max, v["rate_off_hz"] + v["growth_off"] * lux_max)
    log_max = math.log(RATE_MAX_HZ)
    if _log_peak_rate(top, v["sigma"]) > log_max or not top + shot_max <= RATE_MAX_HZ:
        return False
    return v["hot_fraction"] == 0.0 or _log_peak_rate(v["hot_rate_hz"], v["hot_sigma"]) <= log_max


def timing_components(v, group_index, model: Model, grp: _Group):
    """Per component (ordinary, then hot pixels if any): its rates per window and polarity as ``a exp(sigma z) +
    c`` (``a_on``, ``a_off``, ``c_on``, ``c_off`` (W,) events/s, ``sigma``; ``z`` standard normal) and its
    regularity, for :func:`.timing.log_spread_integral` (``sigma`` 0: the rates are ``c``)."""
    shot = np.asarray(model.shot[group_index], dtype=np.float64)
    lux = model.lux[group_index] if model.growth else np.zeros(shot.shape[0])
    base_on = v["rate_on_hz"] + v["growth_on"] * lux
    base_off = v["rate_off_hz"] + v["growth_off"] * lux
    sigma = v["sigma"]
    scale = math.exp(-0.5 * sigma * sigma) if sigma > 0 else 0.0
    comps = [dict(a_on=scale * base_on, a_off=scale * base_off, c_on=shot[:, 0] + (sigma <= 0) * base_on,
                  c_off=shot[:, 1] + (sigma <= 0) * base_off, sigma=sigma, regularity=v["regularity"])]
    if v["hot_fraction"] > 0:
        sh = v["hot_sigma"]
        h = v["hot_rate_hz"] * (math.exp(-0.5 * sh * sh) if sh > 0 else 1.0)
        q = v["hot_on_fraction"]
        c_on, c_off = base_on + shot[:, 0], base_off + shot[:, 1]
        hot_on, hot_off = np.full(c_on.shape, h * q), np.full(c_on.shape, h * (1.0 - q))
        comps.append(dict(a_on=hot_on if sh > 0 else 0.0 * hot_on, a_off=hot_off if sh > 0 else 0.0 * hot_off,
                          c_on=c_on + (sh <= 0) * hot_on, c_off=c_off + (sh <= 0) * hot_off, sigma=sh,
                          regularity=v["hot_regularity"]))
    return comps


def _log_timing_component(comp, st):
    """log-likelihood of each pixel column's event times under one component (its spread integrated)."""
    if comp["sigma"] > 0:
        return log_spread_integral(comp, st, comp["regularity"])
    return log_point_density(comp["c_on"], comp["c_off"], st, comp["regularity"])


def _log_timing(v, model, gi, grp):
    """Timing log-likelihood of one group (module doc), the hot pixels mixed in."""
    st = grp.timing
    parts = [_log_timing_component(c, st) for c in timing_components(v, gi, model, grp)]
    if len(parts) == 1:
        act = parts[0]
    else:
        f = min(max(v["hot_fraction"], 1e-300), 0.5)
        act = np.logaddexp(math.log1p(-f) + parts[0], math.log(f) + parts[1])
    # a column of weight 0 is never there (timing_statistics leaves the silent column out when none is silent)
    return float(np.dot(st["weight"], act)) if np.all(np.isfinite(act)) else -math.inf


def timing_available(groups) -> bool:
    """Whether every group's windows carry their events (the timing likelihood can be evaluated)."""
    return all(g.timing is not None for g in groups)


def mixture_log_likelihood(theta, model: Model, groups) -> float:
    """Log-likelihood of every group's count vectors at ``theta`` (-inf where a rate is beyond :data:`RATE_MAX_HZ`);
    with ``model.timing``, of their event times (module doc)."""
    v = unpack(theta, model)
    if not _rates_in_range(v, model):
        return -math.inf
    total = 0.0
    for gi, grp in enumerate(groups):
        if model.timing:
            total += _log_timing(v, model, gi, grp)
            continue
        comps = component_rates(v, gi, model, grp)
        ll = _log_mix(grp.vectors, comps, v, grp, v["regularity"]) + grp.log_binom
        total += float(np.dot(grp.weight, ll))
    return total


#: What the optimiser sees where the likelihood is 0 (a regular timer's gap shorter than any pixel allows): large
#: beside any log-likelihood of a window, finite so that its difference quotients stay numbers.
INFEASIBLE_NLL = 1e12


#: BFGS's gradient tolerance for a timing model: the timing likelihood's gradients are finite differences of a
#: quadrature (its nodes found to a tolerance), good to about 1e-2 near the maximum; a gradient of 0.1 leaves the
#: maximum by ``0.1 / information``, far below a standard error (``information^-1/2``) wherever the information
#: exceeds 1.
TIMING_GTOL = 0.1
#: A timing model runs BFGS from this many of its starts, the best first (each run costs as much as a whole count
#: fit): one from the count fit's maximum, one near Poisson (a real sensor's times can disagree with its counts).
TIMING_STARTS = 2
#: ... and from this many of its *screened* starts, the best first: points spread over the spread, regularities and
#: hot fraction (:func:`.fit._screen`), each scored by one evaluation. A real window's timing likelihood has
#: maxima far apart (a near-periodic leak with little spread, or a Poisson one with much spread and regular hot
#: pixels: 6.7 log-units apart in a 1 s DVS128 window), which the two starts above alone need not reach.
SCREEN_STARTS = 2


def maximise(model, groups, start, screen=(), always=()):
    """BFGS from every start (numerical gradients of a smooth likelihood), a Nelder-Mead polish of the best.

    A timing model (``model.timing``) runs BFGS from its :data:`TIMING_STARTS` best starts, its
    :data:`SCREEN_STARTS` best ``screen`` starts and every ``always`` start, and is not polished: its likelihood is
    smooth (:mod:`.timing`) and each evaluation integrates every pixel, where the counts' takes the few distinct
    count vectors. The best of the runs is returned (the first on a tie): never below the runs from ``start``
    alone, nor below any ``always`` start's value (BFGS does not descend). A count model runs every start.
    """
    from scipy.optimize import minimize

    def nll(theta):
        val = -mixture_log_likelihood(theta, model, groups)
        return val if math.isfinite(val) else INFEASIBLE_NLL

    always = [np.asarray(x0, dtype=np.float64) for x0 in always]
    if not model.timing:
        start = list(start) + always
    start = [np.asarray(x0, dtype=np.float64) for x0 in start]
    if model.timing:
        # the TIMING_STARTS best starts, BFGS's first steps scaled by the curvature there: the identity of a plain
        # BFGS start sends the first step far beyond the sensor (the gradients are of the order of the events' number)
        values = [nll(x0) for x0 in start]
        picked = [(start[i], values[i]) for i in np.argsort(values, kind="stable")[:TIMING_STARTS]]
        screen = [np.asarray(x0, dtype=np.float64) for x0 in screen]
        screened = [nll(x0) for x0 in screen]
        picked += [(screen[i], screened[i]) for i in np.argsort(screened, kind="stable")[:SCREEN_STARTS]
                   if screened[i] < INFEASIBLE_NLL]
        picked += [(x0, nll(x0)) for x0 in always]
        best = None
        for x0, f0 in picked:
            if f0 >= INFEASIBLE_NLL and best is not None:
                continue
            res = minimize(nll, x0, method="BFGS",
                           options=dict(gtol=TIMING_GTOL, maxiter=150, hess_inv0=_diagonal_scale(nll, x0, f0)))
            if best is None or res.fun < best.fun:
                best = res
        return best
    best = None
    for x0 in start:
        res = minimize(nll, x0, method="BFGS", options=dict(gtol=1e-3, maxiter=150))
        if best is None or res.fun < best.fun:
            best = res
    polished = minimize(nll, best.x, method="Nelder-Mead", options=dict(xatol=1e-5, fatol=1e-6, maxfev=400,
                                                                       adaptive=True))
    return polished if polished.fun < best.fun else best


def _diagonal_scale(fun, x, f0, step=1e-3):
    """A diagonal inverse Hessian of ``fun`` at ``x`` (``f0 = fun(x)``) from second differences (1 where one is not
    positive)."""
    d = np.ones(x.size)
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = step
        curv = (fun(x + e) - 2.0 * f0 + fun(x - e)) / (step * step)
        if math.isfinite(curv) and curv > 0:
            d[i] = 1.0 / curv
    return np.diag(d)


def hessian(fun, x, step=1e-3):
    n = x.size
    h = np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            e_i = np.zeros(n)
            e_j = np.zeros(n)
            e_i[i] = step
            e_j[j] = step
            val = (fun(x + e_i + e_j) - fun(x + e_i - e_j) - fun(x - e_i + e_j)
                   + fun(x - e_i - e_j)) / (4 * step * step)
            h[i, j] = h[j, i] = val
    return h
