"""Reset memory fitted to a quiet window's event times: the exact likelihood of the memory chain.

Part of :mod:`evnoise.calibration.quiet`. The reset-memory model (:mod:`evnoise.terms.memory`) makes a pixel a
Markov chain over its stored photon count ``m``: in each trial it has an ON event and moves to state ``j`` with
probability ``E_on(m, j)``, an OFF event with ``E_off(m, j)``, else nothing (state kept). Those are the chain's
tables (:func:`transition_matrices`; their row sums are the per-trial probabilities ``P_on(m)``, ``P_off(m)``
of :class:`~evnoise.terms.memory.LevelTables`). So a pixel's events, as trial indices and polarities, have the
likelihood of a hidden Markov model, computed exactly by the forward recursion over ``m``
(:func:`window_log_likelihood`): from the steady state at the window's start
(:func:`~evnoise.terms.memory.initial_law`), ``(1 - P(m))`` per quiet trial, ``E_pol(m, .)`` per event, and the
quiet trials after the last event. It is the simulator's own model on its trial grid (an event's trial is
``floor(t / dt)`` of its time from the window's start), without dead time (refused) and with nominal thresholds
(the fit's photon noise is the base preset's ``eps_pos``, ``eps_neg``, ``bias_pr`` and ``trial_rate_hz``).

Parameters fitted (:func:`fit_memory`): the photon noise level ``lam`` (photons per trial: a quiet recording's
light is unknown), ``k = reset_memory``, the leak rates ``leak_on_hz``, ``leak_off_hz`` (a Poisson background,
per pixel scaled by a log-normal factor of mean 1 and log-sd ``sigma``, integrated over by Gauss-Hermite
quadrature, :data:`SPREAD_NODES` nodes). The memoryless model is ``k = 0`` (photon noise and leak are then both
independent per trial); the likelihood-ratio test of ``k`` has the boundary's null law, half a chi-square with
one degree of freedom.

The photon noise matters only where it is a share of the events: with the DVS128 presets' bias of 64 photons
per trial it is 0.24 events/s at 5 photons per trial, 19 at 50, falling again beyond (the bright branch, not
searched: its state ranges are hundreds of counts).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from evnoise.errors import InputError, ParameterError

__all__ = ["transition_matrices", "window_log_likelihood", "fit_memory", "MemoryFit", "SPREAD_NODES"]

#: Gauss-Hermite nodes of the leak's log-normal spread.
SPREAD_NODES = 16
#: Starting points of the photon noise level (photons per trial) and of ``k``.
LAM_STARTS = (1.0, 3.0, 8.0)
K_STARTS = (0.05, 0.5)
NAMES = ("lam", "k", "leak_on_hz", "leak_off_hz", "sigma")


def transition_matrices(t):
    """``(E_on, E_off)``, ``(S, S)``: per trial from state ``m`` (row) an ON / OFF event that leaves the pixel in
    state ``j`` (column), for the tables ``t`` of :func:`evnoise.terms.memory.level_tables` (module doc there:
    the fresh branch, the stored branch beaten when ``j >= idx_on(m)`` / ``j <= idx_off(m)``, and a background
    event in a trial without photon event, which stores that trial's count)."""
    j = np.arange(t.n_states)[None, :]
    pmf = t.pmf[None, :]
    quiet = t.none_fresh[None, :] + t.k * pmf * ((j > t.idx_off[:, None]) & (j < t.idx_on[:, None]))
    e_on = t.fresh_on[None, :] + t.k * pmf * (j >= t.idx_on[:, None]) + t.a_on * quiet
    e_off = t.fresh_off[None, :] + t.k * pmf * (j <= t.idx_off[:, None]) + t.a_off * quiet
    return e_on, e_off


def _trials(window, dt_s: float):
    """The window's events by rank: ``(trials, polarities, n_trials, n_silent)``. Pixels with events are ordered
    by their number of events (most first), so the pixels with an ``i``-th event are a prefix: ``trials[i]`` and
    ``polarities[i]`` hold their ``i``-th event's trial index and polarity (as many entries as events in all:
    one pixel with many events costs no padding). A pixel's trials strictly increase (two events of a pixel in
    one trial, which the model cannot make, are moved to consecutive trials); ``n_trials``: the window's."""
    ev = window.events
    if ev is None:
        raise InputError(f"{window.describe()}: no events (read the window with quiet_window)")
    n_trials = int(math.floor(window.duration_s / dt_s))
    pix = np.asarray(ev["pixel"], dtype=np.int64)
    order = np.lexsort((ev["t_s"], pix))
    pix, t, on = pix[order], np.asarray(ev["t_s"])[order], np.asarray(ev["on"])[order]
    active, first, inverse, count = np.unique(pix, return_index=True, return_inverse=True, return_counts=True)
    rank = np.arange(pix.size) - first[inverse]  # the event's number within its pixel
    idx = np.clip(np.floor(t / dt_s).astype(np.int64), 0, n_trials - 1) - rank
    # strictly increasing within each pixel: a running maximum per pixel (pixels' blocks are contiguous)
    idx = np.maximum.accumulate(idx + inverse * (n_trials + pix.size)) - inverse * (n_trials + pix.size) + rank
    most = np.empty(active.size, dtype=np.int64)
    most[np.argsort(-count, kind="stable")] = np.arange(active.size)  # each pixel's place, most events first
    by_rank = np.lexsort((most[inverse], rank))
    bounds = np.searchsorted(rank[by_rank], np.arange(int(count.max(initial=0)) + 1))
    trials = [idx[by_rank][a:b] for a, b in zip(bounds[:-1], bounds[1:])]
    polarities = [on[by_rank][a:b] for a, b in zip(bounds[:-1], bounds[1:])]
    return trials, polarities, n_trials, window.n_pixels - active.size


def window_log_likelihood(values: dict, window, base, nodes: int = SPREAD_NODES, data=None) -> float:
    """Log-likelihood of a window's events (trial indices and polarities of every pixel) under the memory chain
    with ``values`` (``lam``, ``k``, ``leak_on_hz``, ``leak_off_hz``, ``sigma``) and ``base``'s photon noise
    (module doc). ``data``: :func:`_trials` of the window, to reuse."""
    from scipy.special import logsumexp

    from evnoise.terms import memory
    from evnoise.terms.arrivals import arrival_shares

    dt_s = 1.0 / base.trial_rate_hz
    trials, polarities, n_trials, n_silent = _trials(window, dt_s) if data is None else data
    z, w = np.polynomial.hermite_e.hermegauss(nodes if values["sigma"] > 0 else 1)
    w = w / w.sum()
    base_tables = memory.level_tables(values["lam"], base.eps_pos, base.eps_neg, base.bias_pr, values["k"])
    n_act = trials[0].size if trials else 0
    per_node = np.empty((z.size, n_act))
    silent = np.empty(z.size)
    for iz, zz in enumerate(z):
        scale = math.exp(values["sigma"] * zz - 0.5 * values["sigma"] ** 2)
        a_on, a_off = arrival_shares(np.float64(values["leak_on_hz"] * scale),
                                     np.float64(values["leak_off_hz"] * scale), base.trial_rate_hz)
        t = dataclasses.replace(base_tables, a_on=float(a_on), a_off=float(a_off))
        e_on, e_off = transition_matrices(t)
        p = np.minimum(e_on.sum(axis=1) + e_off.sum(axis=1), 1.0)
        with np.errstate(divide="ignore"):
            log_q = np.log1p(-p)
        pi, _ = memory._stationary(t)
        start, _ = memory.initial_law(t, pi, dt_s, 0.0)
        with np.errstate(invalid="ignore"):
            silent[iz] = logsumexp(np.where(np.isfinite(log_q), n_trials * log_q, -np.inf), b=start)
        alpha = np.broadcast_to(start, (n_act, start.size)).copy()
        log_l = np.zeros(n_act)
        prev = np.full(n_act, -1, dtype=np.int64)
        for trial, pol in zip(trials, polarities):
            n = trial.size  # pixels sorted by their number of events: the first n have this event
            a = _quiet_trials(alpha[:n], trial - prev[:n] - 1, log_q)
            a = np.where(pol[:, None], a @ e_on, a @ e_off)
            total = a.sum(axis=1)
            with np.errstate(divide="ignore"):
                log_l[:n] += np.log(total)
            alpha[:n] = a / np.where(total > 0, total, 1.0)[:, None]
            prev[:n] = trial
        with np.errstate(divide="ignore"):
            log_l += np.log(_quiet_trials(alpha, n_trials - 1 - prev, log_q).sum(axis=1))
        per_node[iz] = log_l
    log_w = np.log(w)[:, None]
    active = np.logaddexp.reduce(log_w + per_node, axis=0)
    quiet = np.logaddexp.reduce(np.log(w) + silent)
    return float(active.sum() + n_silent * quiet)


def _quiet_trials(alpha, gaps, log_q):
    """``alpha (1 - P(m))^gap`` per row (a state with ``P = 1`` stays only through 0 quiet trials)."""
    with np.errstate(invalid="ignore"):
        factor = np.exp(gaps[:, None] * log_q[None, :])
    return alpha * np.where(gaps[:, None] == 0, 1.0, factor)


@dataclasses.dataclass
class MemoryFit:
    """A memory fit of quiet windows (:func:`fit_memory`): the fitted ``values`` (:data:`NAMES`) and their
    standard errors (None where the information is not positive definite), the log-likelihood, the memoryless
    fit (``k = 0``) and the likelihood-ratio test of ``k``."""

    values: dict
    std_error: dict | None
    log_likelihood: float
    memoryless: dict
    memoryless_log_likelihood: float
    lr: float
    p_value: float
    windows: list

    def to_params(self, base, memoryless: bool = False):
        """``base`` with the fit's photon noise level, memory and leak: ``NoiseParams`` for a sensor at the lux
        that gives ``lam`` photons per trial (:meth:`lux`)."""
        v = self.memoryless if memoryless else self.values
        return base.replace(reset_memory=v["k"], leak_on_hz=v["leak_on_hz"], leak_off_hz=v["leak_off_hz"],
                            leak_sigma=v["sigma"], leak_regularity=0.0, hot_pixel_fraction=0.0,
                            leak_on_hz_per_lux=0.0, leak_off_hz_per_lux=0.0, eps_sigma=0.0, refractory_s=0.0)

    def lux(self, base, memoryless: bool = False) -> float:
        """The illuminance at which ``base`` has the fitted photon noise level ``lam`` (photons per trial)."""
        from evnoise.terms.arrivals import lux_of_photons

        v = self.memoryless if memoryless else self.values
        return float(lux_of_photons(v["lam"], base))

    def summary(self) -> str:
        rows = [f"memory fit of {', '.join(self.windows)}: log L {self.log_likelihood:.2f}, memoryless "
                f"{self.memoryless_log_likelihood:.2f}; LR {self.lr:.2f}, p = {self.p_value:.3g}"]
        for name in NAMES:
            se = "" if not self.std_error or self.std_error.get(name) is None else f" +- {self.std_error[name]:.3g}"
            bound = " (at its bound 0: no memory)" if name == "k" and self.values[name] < 1e-9 else ""
            rows.append(f"  {name:12s} {self.values[name]:.4g}{se}{bound}   (memoryless {self.memoryless[name]:.4g})")
        return "\n".join(rows)


def _unpack(theta, free):
    """The values of the fit's coordinates (logs, the logit of ``k``; clipped where ``exp`` would overflow)."""
    th = np.clip(np.asarray(theta, dtype=np.float64), -700.0, 700.0)
    v = dict(lam=math.exp(th[0]), k=0.0, leak_on_hz=math.exp(th[2]), leak_off_hz=math.exp(th[3]),
             sigma=math.exp(th[4]))
    if free:
        v["k"] = 1.0 / (1.0 + math.exp(-th[1]))
    return v


def fit_memory(windows, base="dvs128", *, nodes: int = SPREAD_NODES) -> MemoryFit:
    """Fit the reset-memory chain to quiet windows' event times (module doc), and the memoryless chain.

    Parameters
    ----------
    windows : sequence of QuietWindow
        Windows read with their events (:func:`~evnoise.calibration.quiet_window`); each window's pixels are
        independent of the others' (windows of one recording are not tied).
    base : NoiseParams or str
        Preset of the photon noise (thresholds, bias, trial rate); it must have no dead time.
    nodes : int
        Gauss-Hermite nodes of the leak's spread.
    """
    from scipy.optimize import minimize
    from scipy.stats import chi2

    import evnoise as ev

    base = ev.load_preset(base) if isinstance(base, str) else base
    if base.refractory_s > 0:
        raise ParameterError("the memory fit's likelihood has no dead time: use a base preset with refractory_s = 0")
    windows = list(windows)
    if not windows:
        raise InputError("no quiet windows to fit")
    dt_s = 1.0 / base.trial_rate_hz
    data = [_trials(w, dt_s) for w in windows]
    exposure = sum(w.duration_s * w.n_pixels for w in windows)
    rate_on = max(sum(int(w.counts[0].sum()) for w in windows), 1) / exposure
    rate_off = max(sum(int(w.counts[1].sum()) for w in windows), 1) / exposure

    def nll(theta, free):
        values = _unpack(theta, free)
        try:
            val = -sum(window_log_likelihood(values, w, base, nodes, d) for w, d in zip(windows, data))
        except (FloatingPointError, ValueError, OverflowError, np.linalg.LinAlgError, MemoryError):
            return 1e300
        return val if math.isfinite(val) else 1e300

    def best_of(starts, free, runs=2):
        """Nelder-Mead from the ``runs`` best of ``starts``."""
        values = [nll(x0, free) for x0 in starts]
        best = None
        for x0 in [starts[i] for i in np.argsort(values, kind="stable")[:runs]]:
            res = minimize(nll, x0, args=(free,), method="Nelder-Mead",
                           options=dict(xatol=1e-4, fatol=1e-4, maxfev=1500, adaptive=True))
            if best is None or res.fun < best.fun:
                best = res
        return best

    def start(lam, k):
        return np.array([math.log(lam), math.log(k / (1.0 - k)), math.log(rate_on), math.log(rate_off),
                         math.log(0.5)])

    null = best_of([start(lam, 0.5) for lam in LAM_STARTS], free=False)
    full = best_of([start(lam, k) for lam in LAM_STARTS for k in K_STARTS] + [np.array(null.x)], free=True)
    lr = max(0.0, 2.0 * (null.fun - full.fun))
    se = _standard_errors(lambda th: nll(th, True), full.x)
    return MemoryFit(values=_unpack(full.x, True), std_error=se, log_likelihood=-full.fun,
                     memoryless=_unpack(null.x, False), memoryless_log_likelihood=-null.fun, lr=lr,
                     p_value=float(0.5 * chi2.sf(lr, 1)) if lr > 0 else 1.0,
                     windows=[w.describe() for w in windows])


def _standard_errors(nll, theta):
    """Standard errors of :data:`NAMES` from the numerical Hessian of ``nll`` in the fit's coordinates (logs,
    the logit of ``k``), carried to the values by the delta method; None if it is not positive definite."""
    from .likelihood import hessian

    h = hessian(nll, theta)
    if not np.all(np.linalg.eigvalsh(h) > 0):
        return None
    cov = np.linalg.inv(h)
    v = _unpack(theta, True)
    grad = [v["lam"], v["k"] * (1.0 - v["k"]), v["leak_on_hz"], v["leak_off_hz"], v["sigma"]]
    return {name: float(abs(g) * math.sqrt(cov[i, i])) for i, (name, g) in enumerate(zip(NAMES, grad))}
