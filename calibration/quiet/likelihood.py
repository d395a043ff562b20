"""The likelihood of quiet windows (the model of :mod:`evnoise.calibration.quiet`'s docstring).

Per-pixel count vectors over a recording's windows, integrated over the spread of the rates (and the
hot pixels) on a fixed grid of the standard normal; the maximisation and the numerical Hessian.
Part of :mod:`evnoise.calibration.quiet`; used by :mod:`.fit` and :mod:`.goodness`.
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


@dataclass
class _Group:
    """The pixels of one recording: unique count vectors over its windows and their multiplicities."""

    windows: list
    vectors: np.ndarray  # (U, n_windows, 2) counts
    weight: np.ndarray   # (U,) number of pixels with that vector
    log_binom: np.ndarray  # (U,) sum over windows of log C(k_on + k_off, k_on)


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
        out.append(_Group(ws, vec, mult.astype(np.float64), log_binom))
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
    v["rate_on_hz"], v["rate_off_hz"] = _exp(v.pop("log_on")), _exp(v.pop("log_off"))
    return v


def component_rates(v, group_index, model: Model, grp: _Group):
    """Per component: total rates (M, W) events/s and ON shares (M, W) over its grid."""
    T = np.array([w.duration_s for w in grp.windows])
    shot = model.shot[group_index]
    lux = model.lux[group_index] if model.growth else np.zeros(len(T))
    base = np.stack([v["rate_on_hz"] + v["growth_on"] * lux, v["rate_off_hz"] + v["growth_off"] * lux], axis=1)
    sigma = v["sigma"]
    s = np.exp(-0.5 * sigma * sigma + sigma * _Z) if sigma > 0 else np.ones(1)
    per_pol = s[:, None, None] * base[None] + shot[None]  # (M, W, 2)
    comps = [(per_pol.sum(axis=2), per_pol[..., 0] / np.maximum(per_pol.sum(axis=2), 1e-300),
              _WZ if sigma > 0 else np.ones(1))]
    if v["hot_fraction"] > 0:
        sh = v["hot_sigma"]
        h = v["hot_rate_hz"] * np.exp(-0.5 * sh * sh + sh * _Z)
        q = v["hot_on_fraction"]
        hot = h[:, None, None] * np.array([q, 1.0 - q])[None, None, :] + base[None] + shot[None]
        comps.append((hot.sum(axis=2), hot[..., 0] / np.maximum(hot.sum(axis=2), 1e-300), _WZ))
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
    lh = _log_component(vec, *comps[1], grp, regularity)
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


def mixture_log_likelihood(theta, model: Model, groups) -> float:
    """Log-likelihood of every group's count vectors at ``theta`` (-inf where a rate is beyond :data:`RATE_MAX_HZ`)."""
    v = unpack(theta, model)
    if not _rates_in_range(v, model):
        return -math.inf
    total = 0.0
    for gi, grp in enumerate(groups):
        comps = component_rates(v, gi, model, grp)
        ll = _log_mix(grp.vectors, comps, v, grp, v["regularity"]) + grp.log_binom
        total += float(np.dot(grp.weight, ll))
    return total


def maximise(model, groups, start):
    """BFGS from every start (numerical gradients of a smooth likelihood), a Nelder-Mead polish of the best."""
    from scipy.optimize import minimize

    def nll(theta):
        val = -mixture_log_likelihood(theta, model, groups)
        return val if math.isfinite(val) else 1e300

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
