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
pixels may have their own regularity (``Model.hot_regular``: ``hot_regularity``). The rate spread is
integrated on a finer grid (:data:`GRID_TIMING`), since a pixel's gaps make its integrand narrower.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from evnoise.errors import InputError

from .counts import count_survival

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
#: Grid points of the standard normal for the timing likelihood (over +-7 sd).
GRID_TIMING = 241
_ZT = np.linspace(-7.0, 7.0, GRID_TIMING)
_WZT = np.exp(-0.5 * _ZT * _ZT)
_WZT /= _WZT.sum()


@dataclass
class _Group:
    """The pixels of one recording: unique count vectors over its windows and their multiplicities."""

    windows: list
    vectors: np.ndarray  # (U, n_windows, 2) counts
    weight: np.ndarray   # (U,) number of pixels with that vector
    log_binom: np.ndarray  # (U,) sum over windows of log C(k_on + k_off, k_on)
    #: per window, the event times of the pixels with events (:func:`_timing_data`), or None (counts only)
    timing: list | None = None
    n_silent: int = 0  # pixels without an event in any window of the group


def _timing_data(ws, n_pix):
    """Per window: the pixels with events in any window (``active``), their counts, first times, censored
    tails and gaps (with each gap's pixel), for :func:`_log_timing`. None if a window has no events kept."""
    if any(w.events is None for w in ws):
        return None, 0
    active = np.unique(np.concatenate([w.events["pixel"] for w in ws]))
    out = []
    for w in ws:
        ev = w.events
        a = np.searchsorted(active, ev["pixel"])
        k = np.bincount(a, minlength=active.size)
        k_on = np.bincount(a, weights=ev["on"].astype(np.float64), minlength=active.size)
        first = np.zeros(active.size)
        last = np.zeros(active.size)
        if ev["pixel"].size:
            start = np.r_[True, ev["pixel"][1:] != ev["pixel"][:-1]]
            stop = np.r_[ev["pixel"][1:] != ev["pixel"][:-1], True]
            first[a[start]] = ev["t_s"][start]
            last[a[stop]] = ev["t_s"][stop]
        same = ev["pixel"][1:] == ev["pixel"][:-1]
        gaps = np.maximum(np.diff(ev["t_s"])[same], 0.0)
        gap_pix = a[1:][same]
        gap_start = np.flatnonzero(np.r_[True, gap_pix[1:] != gap_pix[:-1]]) if gap_pix.size else gap_pix
        T = float(w.duration_s)
        out.append({"k": k.astype(np.float64), "k_on": k_on, "k_off": k - k_on, "first": first,
                    "tail": np.maximum(T - last, 0.0), "gaps": gaps, "gap_pix": gap_pix, "T": T,
                    "gap_start": gap_start, "gap_owner": gap_pix[gap_start] if gap_pix.size else gap_pix,
                    "has": k > 0})
    return out, int(n_pix - active.size)


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
        stack = np.stack([w.counts.reshape(2, -1).T for w in ws], axis=1)  # (P, n_windows, 2)
        flat = stack.reshape(stack.shape[0], -1)
        uniq, mult = np.unique(flat, axis=0, return_counts=True)
        vec = uniq.reshape(-1, len(ws), 2)
        tot = vec.sum(axis=2)
        log_binom = (gammaln(tot + 1.0) - gammaln(vec[..., 0] + 1.0) - gammaln(vec[..., 1] + 1.0)).sum(axis=1)
        timing, silent = _timing_data(ws, stack.shape[0])
        out.append(_Group(ws, vec, mult.astype(np.float64), log_binom, timing, silent))
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


def component_rates(v, group_index, model: Model, grp: _Group, fine: bool = False):
    """Per component: total rates (M, W) events/s and ON shares (M, W) over its grid (``fine``: the timing
    likelihood's :data:`GRID_TIMING` nodes)."""
    z, wz = (_ZT, _WZT) if fine else (_Z, _WZ)
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
        k = np.concatenate([needed, needed + 1]).astype(np.float64)
        surv = count_survival(k[None, :], rates[:, wi, None], w.duration_s, regularity)  # (M, 2 n)
        pmf = np.maximum(surv[:, :needed.size] - surv[:, needed.size:], 0.0)
        with np.errstate(divide="ignore"):
            log_pmf = np.log(np.maximum(pmf, 1e-300))[:, where]  # (M, U)
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


def _renewal_logs(rate, r):
    """``(log rate, d, theta, log theta)`` of the renewal gaps ``d + Exp(theta)`` at rates ``rate``."""
    with np.errstate(divide="ignore"):
        mu = 1.0 / np.maximum(rate, 1e-300)
        d = r * mu
        theta = np.maximum((1.0 - r) * mu, 1e-300)
        return np.log(np.maximum(rate, 1e-300)), d, theta, np.log(theta)


def _log_surv(x, d, theta):
    """``log S(x) = -max(x - d, 0) / theta`` (broadcast)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return -np.maximum(x - d, 0.0) / theta


def _log_timing_component(rates, share_on, weights, grp: _Group, r):
    """Per pixel with events (A,) and for a silent pixel (scalar): log of the mean over the component's grid
    of the event-time density (module doc) over every window of the group."""
    from scipy.special import logsumexp

    n_act = grp.timing[0]["k"].size
    acc = np.zeros((rates.shape[0], n_act))
    silent = np.zeros(rates.shape[0])
    for wi, td in enumerate(grp.timing):
        lam = rates[:, wi]
        log_lam, d, theta, log_theta = _renewal_logs(lam, r)
        T = td["T"]
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            p0 = np.where(T <= d, -np.expm1(np.log(np.maximum(lam, 1e-300)) + math.log(T)) if T > 0 else 1.0,
                          (1.0 - r) * np.exp(_log_surv(T, d, theta)))
            log_p0 = np.log(np.maximum(p0, 0.0))
            lq = np.log(np.maximum(share_on[:, wi], 1e-300))
            l1q = np.log(np.maximum(1.0 - share_on[:, wi], 1e-300))
        silent += log_p0
        has = td["has"]
        dd, th = d[:, None], theta[:, None]
        ev = (log_lam[:, None] + _log_surv(td["first"][None, :], dd, th) + _log_surv(td["tail"][None, :], dd, th)
              + np.outer(lq, td["k_on"]) + np.outer(l1q, td["k_off"]))
        if td["gaps"].size:
            x = td["gaps"][None, :]
            with np.errstate(over="ignore", invalid="ignore"):
                lg = np.where(x > dd, -log_theta[:, None] - (x - dd) / th, -np.inf)
            # the gaps are sorted by pixel: sum each pixel's run
            ev[:, td["gap_owner"]] += np.add.reduceat(lg, td["gap_start"], axis=1)
        acc += np.where(has[None, :], ev, log_p0[:, None])
    lw = np.log(weights)
    return _logsumexp0(acc + lw[:, None]), float(logsumexp(silent + lw))


def _logsumexp0(a):
    """``log(sum(exp(a), axis=0))`` of a (M, A) array, columns all ``-inf`` giving ``-inf`` (no warnings)."""
    top = a.max(axis=0)
    safe = np.where(np.isfinite(top), top, 0.0)
    with np.errstate(divide="ignore"):
        return np.log(np.exp(a - safe[None, :]).sum(axis=0)) + safe


def _log_timing(v, model, gi, grp):
    """Timing log-likelihood of one group (module doc), the hot pixels mixed in."""
    comps = component_rates(v, gi, model, grp, fine=True)
    regs = (v["regularity"], v["hot_regularity"])
    parts = [_log_timing_component(*c, grp, r) for c, r in zip(comps, regs)]
    if len(parts) == 1:
        act, sil = parts[0]
    else:
        f = min(max(v["hot_fraction"], 1e-300), 0.5)
        act = np.logaddexp(math.log1p(-f) + parts[0][0], math.log(f) + parts[1][0])
        sil = float(np.logaddexp(math.log1p(-f) + parts[0][1], math.log(f) + parts[1][1]))
    return float(np.sum(act)) + grp.n_silent * sil


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


def maximise(model, groups, start):
    """BFGS from every start (numerical gradients of a smooth likelihood), a Nelder-Mead polish of the best."""
    from scipy.optimize import minimize

    def nll(theta):
        val = -mixture_log_likelihood(theta, model, groups)
        return val if math.isfinite(val) else INFEASIBLE_NLL

    best = None
    for x0 in start:
        res = minimize(nll, np.asarray(x0, dtype=np.float64), method="BFGS", options=dict(gtol=1e-3, maxiter=150))
        if best is None or res.fun < best.fun:
            best = res
    polished = minimize(nll, best.x, method="Nelder-Mead", options=dict(xatol=1e-5, fatol=1e-6, maxfev=400,
                                                                       adaptive=True))
    return polished if polished.fun < best.fun else best


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
