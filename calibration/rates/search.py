"""The search for the maximum: stand-in pre-fits from quasi-random seeds, Levenberg-Marquardt Fisher
scoring, the ridge walk, the continuation for step-like likelihoods and the profile of
photons_per_lux. Internal.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from evnoise import terms
from evnoise.params import NoiseParams

from .likelihood import Prepared, Problem
from .spec import (
    FIT_NAMES,
    FLOORS,
    GROWTH,
    N_CONVERGED,
    PROFILE_MAX_STEP,
    PROFILE_ROUGH,
    PROFILE_STEP,
    PROFILE_STOP,
    SMOOTHING,
    SPREAD,
    FitSpec,
    data_bounds,
)
from .uncertainty import covariance, information, is_step_like, rejected, steps

log = logging.getLogger("evnoise.calibration")


class _MeanProxy:
    """Cheap stand-in objective for the global search: mean-rate deviance without mismatch.

    Uses the exact closed form at the nominal thresholds (no threshold distribution) and
    profiles ``trial_rate_hz`` out (the rate is proportional to it, so its best value is
    closed-form), which leaves the shape parameters to search.
    """

    SEED_BOX = {"eps_pos": (0.02, 3.0), "eps_neg": (0.02, 3.0), "bias_pr": (1e-3, 1e3), "eps_sigma": (0.01, 0.3)}
    SEED_LAM_MAX = 1e4  # photons per trial at the brightest level, most of the seeds
    MIN_SIGMA = 0.02  # smoothing used when the mismatch is fixed below it (or at 0) ...
    MIN_REL_SIGMA = 0.1  # ... or below this fraction of the threshold, if that is smaller
    N_NODES = 9

    def __init__(self, problem: Problem):
        self.pr = problem
        # the spread and hot-pixel terms barely change the mean: held at their values in the stand-in;
        # the floors are profiled out with trial_rate_hz (the mean is linear in them), so the seeds
        # search the same shape parameters as without them
        self.names = [n for n in problem.free if n not in ("refractory_s", "trial_rate_hz") + SPREAD + FLOORS]
        self.floors = [k for k, n in enumerate(FLOORS) if n in problem.free]
        nodes, weights = np.polynomial.hermite.hermgauss(self.N_NODES)
        self.nodes, self.weights = math.sqrt(2.0) * nodes, weights / math.sqrt(math.pi)
        self.profile_n = "trial_rate_hz" in problem.free
        lux = problem.lux
        lux_max = float(max(lux.max(), 1e-6))
        pos = lux[lux > 0]
        lux_min = float(pos.min()) if pos.size else lux_max
        box = dict(self.SEED_BOX)
        # seeds up to a few thousand photons per trial; the profile of rate tables walks further
        box["photons_per_lux"] = (0.3 / lux_max, min(0.5 * problem.bounds["photons_per_lux"][1],
                                                     self.SEED_LAM_MAX / lux_max))
        box["dark_lux"] = (min(1e-3 * lux_min, 1e-4 * lux_max), lux_max)
        rate_max = float(max(problem.meas.rate_hz.max(), 1e-9))
        for n in GROWTH:
            box[n] = (1e-4 * rate_max / lux_max, rate_max / lux_max)
        self.lo = np.array([math.log(max(box[n][0], problem.bounds[n][0])) for n in self.names])
        self.hi = np.array([math.log(min(box[n][1], problem.bounds[n][1])) for n in self.names])
        self.blo = np.array([math.log(problem.bounds[n][0]) for n in self.names])
        self.bhi = np.array([math.log(problem.bounds[n][1]) for n in self.names])

    def _values(self, x):
        """Columns of parameter values for a (S, len(names)) array of log values."""
        s = x.shape[0]
        vals = {n: np.full(s, self.pr.values[n], dtype=np.float64) for n in FIT_NAMES}
        for i, n in enumerate(self.names):
            vals[n] = np.exp(x[:, i])
        return vals

    def deviance(self, x) -> np.ndarray:
        """Profiled Poisson deviance of the level means for log-parameter rows ``x`` (S, d)."""
        from evnoise.model import event_probability

        x = np.atleast_2d(x)
        vals = self._values(x)
        pr = self.pr
        lam = vals["photons_per_lux"][:, None] * (pr.lux[None, :] + vals["dark_lux"][:, None])
        # mismatch smooths the mean curve (without it, it is a step function of eps and bias_pr,
        # which direct search handles badly): average over Gauss-Hermite nodes of eps
        # (relative to small thresholds, so that the smoothing is the same along the many-photon
        # ridge, where eps scales like 1/sqrt(photons_per_lux))
        sigma = {e: np.maximum(vals["eps_sigma"], np.minimum(self.MIN_SIGMA, self.MIN_REL_SIGMA * vals[e]))[:, None]
                 for e in ("eps_pos", "eps_neg")}
        if x.shape[0] == 1:
            from evnoise._kernels.poisson import log_event_probability_exact_serial

            j = lam.shape[1]
            k = self.nodes.size
            eps = np.concatenate([np.maximum(vals[e][0] + sigma[e][0] * self.nodes, 1e-4)
                                  for e in ("eps_pos", "eps_neg")])  # (2K,)
            lam2 = np.ascontiguousarray(np.tile(lam[0], 2 * k))
            c2 = np.repeat(np.expm1(eps), j)
            out = np.empty(lam2.size)
            log_event_probability_exact_serial(lam2, c2, np.full(lam2.size, vals["bias_pr"][0]), out)
            p = (np.exp(out).reshape(2, k, j) * self.weights[None, :, None]).sum(axis=1)[None]
        else:
            p = np.stack([
                np.einsum("skj,k->sj", event_probability(
                    lam[:, None, :], np.maximum(vals[e][:, None] + sigma[e] * self.nodes[None, :], 1e-4)[:, :, None],
                    vals["bias_pr"][:, None, None]), self.weights)
                for e in ("eps_pos", "eps_neg")], axis=1)  # (S, 2, J)
        base = p * pr.exposure[None, None, :]
        y = pr.y[None]
        # background: additive in the stand-in (nu ~ N p + l for l << N), the population mean of every
        # background term of the registry
        bg = np.stack(terms.mean_intensities(pr.lux[None, :], {k: v[:, None] for k, v in vals.items()}),
                      axis=1) * pr.exposure[None, None, :]  # (S, 2, J)
        if self.profile_n:
            lo, hi = pr.bounds["trial_rate_hz"]
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                n = np.clip((y.sum(axis=(1, 2)) - bg.sum(axis=(1, 2))) / base.sum(axis=(1, 2)), lo, hi)
            n = np.where(np.isfinite(n), n, hi)
        else:
            n = vals["trial_rate_hz"]
        if self.floors:
            n, bg = self._profile_floors(base, bg, n, y)
        mu = base * n[:, None, None] + bg
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            dev = 2.0 * (np.where(y > 0, y * np.log(np.where(y > 0, y, 1.0) / mu), 0.0) - (y - mu))
        out = np.sum(dev, axis=(1, 2))
        self.last_n = n
        return np.where(np.isfinite(out), out, np.inf)

    FLOOR_ITERATIONS = 40

    def _profile_floors(self, base, bg, n, y):
        """Maximise the stand-in's Poisson likelihood over the free floors (and N if profiled).

        The mean is ``N base + bg + f_k E`` (``E`` the exposure), linear in ``N`` and the floors
        ``f_k``: EM (multiplicative) updates, which keep them >= 0 and raise the likelihood each step.
        """
        pr = self.pr
        e = np.broadcast_to(pr.exposure[None, :], y.shape[1:])  # (2, J)
        f = np.zeros((base.shape[0], 2))
        lo_f = np.array([pr.bounds[m][0] for m in FLOORS])
        hi_f = np.array([pr.bounds[m][1] for m in FLOORS])
        mean_rate = np.sum(y[0], axis=1) / np.sum(e, axis=1)
        for k in self.floors:
            f[:, k] = 0.1 * mean_rate[k]
        n = np.array(n, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for _ in range(self.FLOOR_ITERATIONS):
                mu = base * n[:, None, None] + bg + f[:, :, None] * e[None]
                ratio = np.where(mu > 0, y / np.where(mu > 0, mu, 1.0), 0.0)
                if self.profile_n:
                    n = n * np.sum(ratio * base, axis=(1, 2)) / np.sum(base, axis=(1, 2))
                    n = np.where(np.isfinite(n), n, pr.bounds["trial_rate_hz"][1])
                for k in self.floors:
                    f[:, k] = f[:, k] * np.sum(ratio[:, k] * e[k], axis=1) / np.sum(e[k])
            if self.profile_n:
                n = np.clip(n, *pr.bounds["trial_rate_hz"])
        f = np.where(np.isfinite(f), f, 0.0)
        for k in self.floors:
            f[:, k] = np.clip(f[:, k], lo_f[k], hi_f[k])
        self.last_floors = f
        return n, bg + f[:, :, None] * e[None]

    def full_theta(self, x) -> np.ndarray:
        """The problem's log-parameter vector for proxy coordinates ``x`` (profiled N and floors filled in)."""
        self.deviance(x[None, :])
        vals = dict(self.pr.values)
        for i, n in enumerate(self.names):
            vals[n] = float(math.exp(x[i]))
        if self.profile_n:
            vals["trial_rate_hz"] = float(self.last_n[0])
        for k in self.floors:
            vals[FLOORS[k]] = float(self.last_floors[0, k])
        t = np.array([math.log(vals[n]) for n in self.pr.free])
        return np.clip(t, self.pr.lo, self.pr.hi)

    def local(self, x0, maxfev, lo=None, hi=None):
        from scipy.optimize import minimize

        lo = self.blo if lo is None else lo
        hi = self.bhi if hi is None else hi
        f = lambda x: float(self.deviance(np.clip(x, lo, hi)[None, :])[0])  # noqa: E731
        res = minimize(f, x0, method="Nelder-Mead",
                       options={"maxfev": maxfev, "xatol": 1e-5, "fatol": 1e-9, "adaptive": True,
                                "initial_simplex": _simplex(x0, lo, hi, size=0.2)})
        x = np.clip(res.x, lo, hi)
        return x, f(x)


def local_fit(problem: Problem, theta0, *, max_iter: int = 80, polish: bool = True, central: bool = True):
    """Levenberg-Marquardt-damped Fisher scoring in log space, within the bounds.

    Each iteration needs the score and expected information (central differences, ``2 p``
    model evaluations); steps that do not increase the likelihood raise the damping. For the
    mismatch-free model (a step function of ``eps`` and ``bias_pr``) a Nelder-Mead polish
    follows, as derivatives there only see the large-scale slope.
    """
    lo, hi = problem.lo, problem.hi
    theta = np.clip(np.asarray(theta0, dtype=np.float64), lo, hi)
    if not problem.in_domain(theta):  # a non-finite start: nothing to fit from
        return theta, math.inf
    ll = problem.loglik(theta)
    damping = 1e-3
    h = steps(problem, 1e-4)
    for _ in range(max_iter):
        info, _, extras = information(problem, theta, h, want_meat=False, central=central)
        score = extras["score"]
        free_dir = ~(((theta <= lo + 1e-12) & (score < 0)) | ((theta >= hi - 1e-12) & (score > 0)))
        if not free_dir.any():
            break
        improved = False
        for _ in range(30):
            a = info[np.ix_(free_dir, free_dir)]
            a = a + damping * np.diag(np.diag(a) + 1e-12 * max(np.max(np.diag(a)), 1e-300))
            try:
                step_f = np.linalg.solve(a, score[free_dir])
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            step = np.zeros_like(theta)
            step[free_dir] = step_f
            big = np.max(np.abs(step))
            if big > 1.0:  # at most a factor e per step on any parameter
                step /= big
            # a degenerate information (e.g. where no count has a finite probability) can give a
            # non-finite step: the candidate is then outside the domain, its log-likelihood -inf, and it
            # is rejected like any worse point (more damping, then the next start)
            cand = np.clip(theta + step, lo, hi)
            ll_c = problem.loglik(cand)
            if ll_c > ll:
                gain = ll_c - ll
                theta, ll = cand, ll_c
                damping = max(damping / 3.0, 1e-9)
                improved = True
                break
            damping *= 4.0
            if damping > 1e12:
                break
        log.debug("LM: log-likelihood %.12g (damping %.3g)", ll, damping)
        if not improved or gain < 1e-10 * (1.0 + abs(ll)):
            break
    if polish and "eps_sigma" not in problem.free and problem.values["eps_sigma"] == 0 \
            and problem.meas.kind == "table":
        from scipy.optimize import minimize

        nm = minimize(problem.objective, theta, method="Nelder-Mead",
                      options={"maxfev": 300 * len(theta), "xatol": 1e-6, "fatol": 1e-13, "adaptive": True,
                               "initial_simplex": _simplex(theta, lo, hi)})
        t_nm = np.clip(nm.x, lo, hi)
        if problem.loglik(t_nm) > ll:
            theta = t_nm
    return theta, problem.objective(theta)


def _simplex(t, lo, hi, size=0.05):
    pts = [t]
    for i in range(t.size):
        q = t.copy()
        q[i] = q[i] + size if q[i] + size <= hi[i] else q[i] - size
        pts.append(q)
    return np.array(pts)


def run_search(meas, method, distribution, free, values, *, assumed, gen, n_starts, n_seeds, progress, have_initial,
         dispersion, bounds):
    """Build the problem and find its best optimum; ``(problem, theta)`` (the problem of the last
    stage: with rescaled block weights where the noise scale is unknown)."""
    values = dict(values)
    fit_bounds = data_bounds(meas, free, values, bounds)  # moves starting values inside the bounds
    prepared = Prepared(meas)
    fit_shape = prepared.use_shape and dispersion == "fit"
    quasi = prepared.quasi_counts or (fit_shape and prepared.quasi_shape)
    # measured shapes only reported, or unknown scales (then the mean curve is fitted first): no shape term
    shape_weight = 0.0 if prepared.use_shape and (not fit_shape or quasi) else 1.0
    spec = FitSpec(method, distribution, free, values, fit_bounds, weights={"counts": 1.0, "shape": shape_weight},
                   fit_shape=fit_shape, assumed_sigma=assumed)
    problem = Problem.from_spec(meas, spec, prepared)
    step_like = problem.values["eps_sigma"] == 0.0 and "eps_sigma" not in free and method == "poisson"
    if step_like and meas.kind == "flat-field":
        theta = _continuation(problem, gen, n_starts, n_seeds, progress, have_initial)
    elif step_like:
        # Rate tables: first a direct search (its starts come from a smoothed stand-in, and the exact
        # mismatch statistics of the continuation cost O(lam) per level at the large photon counts a
        # table may need); the continuation, within the bounds of a fit with mismatch, only when the
        # direct fit is rejected (few photons, where the steps of the likelihood are coarse).
        theta = _optimise(problem, problem.values, gen, n_starts, n_seeds, progress, have_initial)
        if rejected(problem, theta):
            log.info("direct fit rejected; fitting the mismatch-free model by continuation")
            smooth = problem.derive(dataclasses.replace(
                problem.spec, bounds=data_bounds(meas, free, dict(problem.values, eps_sigma=SMOOTHING[0]), bounds)))
            theta2 = np.clip(_continuation(smooth, gen, n_starts, n_seeds, progress, have_initial),
                             problem.lo, problem.hi)
            theta2, _ = local_fit(problem, theta2)
            if problem.objective(theta2) < problem.objective(theta):
                theta = theta2
    else:
        theta = _optimise(problem, problem.values, gen, n_starts, n_seeds, progress, have_initial)
        if _looks_bad(problem, theta):
            # the level means are not matched: a missed optimum is likely; search again, wider
            log.info("fit does not match the level means; searching again with %d strata", 2 * n_starts)
            theta2 = _optimise(problem, problem.values, gen, 2 * n_starts, 2 * n_seeds, progress, False)
            if problem.objective(theta2) < problem.objective(theta):
                theta = theta2
    if quasi:
        # blocks with unknown noise scale: weight each by its residual dispersion, refit
        for _ in range(3):
            problem = reweighted(problem, theta)
            theta, _ = local_fit(problem, theta)
    return problem, theta


def _continuation(problem: Problem, gen, n_starts, n_seeds, progress, have_initial):
    """Fit the mismatch-free (step-like) model by continuation: optimise with a little mismatch
    (:data:`SMOOTHING`) and follow the optimum as the mismatch goes to 0 (each stage a problem of its
    own; ``problem`` itself is left as it is). Returns the optimum of the last stage (``eps_sigma = 0``)."""
    stage = problem.with_value("eps_sigma", SMOOTHING[0])
    theta = _optimise(stage, stage.values, gen, n_starts, n_seeds, progress, have_initial)
    for s_c in SMOOTHING[1:] + (0.0,):
        stage = problem.with_value("eps_sigma", s_c)
        theta, _ = local_fit(stage, theta)
    return theta


def comparable_loglik(problem: Problem, theta) -> float:
    """Log-likelihood of the level totals with unit weights (profiled scale for rates without exposure)."""
    mu = problem.model_counts(problem.stats(theta))
    if problem.quasi_counts:
        used = problem.y > 0
        rss = float(np.sum(problem.log_residuals(mu)[used] ** 2))
        n = int(np.count_nonzero(used))
        return -0.5 * n * math.log(max(rss / n, 1e-300))
    return float(np.sum(problem.count_terms(mu)))


def fixed_problem(problem: Problem, name: str, value: float):
    """A copy of ``problem`` with ``name`` held at ``value``; returns it and the indices of the others."""
    keep = [i for i, n in enumerate(problem.free) if n != name]
    return problem.derive(problem.spec.with_fixed(name, value)), keep


def profile_likelihood(problem: Problem, theta, name: str, *, max_steps: int = 30):
    """Profile likelihood of ``name`` (log steps of :data:`PROFILE_STEP`), the others refitted.

    Walks out from ``theta`` both ways until twice the log-likelihood has dropped by
    :data:`PROFILE_STOP` (at two points in a row) or the bound is reached, each point started
    from the previous one moved along the path; while the profile stays flat the steps grow
    (up to :data:`PROFILE_MAX_STEP`). If a point is better than ``theta``, the full fit is resumed from it.
    Returns ``(theta, profile)`` with ``profile = {"name", "points": [(t, loglik, theta)],
    "lo_bound", "hi_bound"}`` (points sorted by ``t``, the log of the value).
    """
    i = problem.free.index(name)
    ll0 = problem.loglik(theta)
    stop = PROFILE_STOP + (PROFILE_ROUGH if is_step_like(problem) else 0.0)
    points = [(float(theta[i]), ll0, np.array(theta, dtype=np.float64))]
    reached = {1: False, -1: False}
    ridge = np.zeros(len(problem.free))
    for j, n in enumerate(problem.free):
        ridge[j] = {name: 1.0, "eps_pos": -0.5, "eps_neg": -0.5, "bias_pr": 1.0}.get(n, 0.0)
    for sign in (1, -1):
        path = [np.array(theta, dtype=np.float64)]
        best = ll0
        beyond = 0
        step = PROFILE_STEP
        for _ in range(max_steps):
            edge = float(problem.hi[i] if sign > 0 else problem.lo[i])
            t = float(path[-1][i] + sign * step)
            if sign * (t - edge) >= 0:
                t = edge
            if abs(t - path[-1][i]) < 1e-9:
                reached[sign] = True
                break
            # starts: the last point moved along the many-photon ridge (thresholds ~ 1/sqrt,
            # bias ~ photons_per_lux), and the path extrapolated linearly
            last = path[-1]
            starts = [last + (t - last[i]) * ridge]
            if len(path) >= 2 and path[-1][i] != path[-2][i]:
                starts.append(last + (last - path[-2]) * ((t - last[i]) / (path[-1][i] - path[-2][i])))
            sub, keep = fixed_problem(problem, name, math.exp(t))
            ll, full = -math.inf, None
            for start in starts:
                x, _ = local_fit(sub, np.clip(start[keep], sub.lo, sub.hi), max_iter=40, polish=False,
                                  central=False)
                cand = start.copy()
                cand[keep] = x
                cand[i] = t
                ll_c = problem.loglik(cand)
                if ll_c > ll:
                    ll, full = ll_c, cand
            points.append((t, ll, full))
            path.append(full)
            best = max(best, ll)
            log.info("profile %s = %.4g: log-likelihood %.6f", name, math.exp(t), ll)
            if t == edge:
                reached[sign] = True
                break
            if 2.0 * (best - ll) > stop:
                beyond += 1
                if beyond >= 2:
                    break
            else:
                beyond = 0
            # where the profile is flat (within the interval's tolerance), walk faster
            flat = 2.0 * (best - ll) <= 1.0 + (PROFILE_ROUGH if is_step_like(problem) else 0.0)
            step = min(step * 1.5, PROFILE_MAX_STEP) if flat else PROFILE_STEP
    points.sort(key=lambda q: q[0])
    k_best = int(np.argmax([q[1] for q in points]))
    if points[k_best][1] > ll0 + 1e-9 * (1.0 + abs(ll0)):
        # a better optimum along the profile: resume the full fit from it
        cand, _ = local_fit(problem, points[k_best][2])
        theta = cand if problem.loglik(cand) >= points[k_best][1] else points[k_best][2]
        log.info("profile of %s found a better optimum: %.4g", name, math.exp(theta[i]))
        points.append((float(theta[i]), problem.loglik(theta), np.array(theta)))
        points.sort(key=lambda q: q[0])
    return theta, {"name": name, "points": points, "lo_bound": reached[-1], "hi_bound": reached[1]}


def _optimise(problem: Problem, values, gen, n_starts, n_seeds, progress, have_initial):
    """Global search: quasi-random seeds -> cheap mean-curve fits -> full fits from the best."""
    from scipy.stats import qmc

    proxy = _MeanProxy(problem)
    d = len(proxy.names)
    starts = []
    if have_initial:
        starts.append(problem.theta(NoiseParams(**values)))
    if d:
        sob = qmc.Sobol(d=d, scramble=True, seed=gen)
        u = sob.random(1 << int(math.ceil(math.log2(max(n_seeds, 2)))))[:n_seeds]
        seeds = proxy.lo + u * (proxy.hi - proxy.lo)
        x_init = np.array([math.log(min(max(values[n], problem.bounds[n][0]), problem.bounds[n][1]))
                           for n in proxy.names])
        seeds = np.vstack([x_init[None, :], seeds])
        scores = proxy.deviance(seeds)
        # the rate curve is nearly unchanged along a ridge in (photons_per_lux, bias_pr, eps):
        # stratify the starts along bias_pr (a profile over it) so that the ridge is explored
        if "bias_pr" in proxy.names:
            ib = proxy.names.index("bias_pr")
            edges = np.linspace(proxy.lo[ib], proxy.hi[ib], n_starts + 1)
            bins = np.clip(np.searchsorted(edges, seeds[:, ib], side="right") - 1, 0, n_starts - 1)
        else:
            ib, edges, bins = None, None, np.zeros(seeds.shape[0], dtype=int)
        kept = []
        for b_ in range(int(bins.max()) + 1):
            members = np.flatnonzero(bins == b_)
            members = members[np.argsort(scores[members])]
            lo_b, hi_b = proxy.blo.copy(), proxy.bhi.copy()
            if ib is not None:
                lo_b[ib], hi_b[ib] = edges[b_], edges[b_ + 1]
            chosen = []
            for m_ in members:  # the four best distinct seeds of each stratum, refined on the stand-in
                if len(chosen) >= 4:
                    break
                if all(np.max(np.abs(seeds[m_] - seeds[c])) > 0.5 for c in chosen):
                    chosen.append(m_)
            refined = sorted((proxy.local(seeds[m_], maxfev=150 * d, lo=lo_b, hi=hi_b) for m_ in chosen),
                             key=lambda r: r[1])
            kept += refined[:2]  # the best two of each stratum go on to the full likelihood
        kept.sort(key=lambda r: r[1])
        fitted = kept
        starts += [proxy.full_theta(x) for x, _ in kept]
        log.info("mean-curve pre-fits: deviances %s", ", ".join(f"{f:.6g}" for _, f in fitted))
    else:
        starts.append(problem.theta(NoiseParams(**values)))
    best = (None, math.inf)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(starts), desc="calibrate", unit="start", leave=False)
    # a few iterations from every start, then the best N_CONVERGED to convergence
    trial = []
    for k, s0 in enumerate(starts):
        t, f = local_fit(problem, s0, max_iter=10, polish=False, central=False) if len(starts) > 2 \
            else (s0, math.inf)
        trial.append((f, k, t))
        if bar is not None:
            bar.update(1)
    trial.sort(key=lambda r: r[0])
    for _, k, t0 in trial[:N_CONVERGED]:
        t, f = local_fit(problem, t0)
        log.info("start %d/%d: objective %.10g", k + 1, len(starts), f)
        if f < best[1] or (best[0] is None and problem.in_domain(t)):
            best = (t, f)
    if best[0] is None:
        raise RuntimeError("calibration: no start of the search is a finite point within the bounds")
    if bar is not None:
        bar.close()
    return _ridge_walk(problem, best[0], best[1])


def _ridge_walk(problem: Problem, theta, f, *, rounds: int = 2, n_directions: int = 3):
    """Look for better optima along the least-constrained directions of the best fit.

    The rate curve hardly changes along ridges (photons_per_lux and bias_pr up, thresholds
    down, ...), and the exact model has several local optima on them, often far apart compared
    with the local standard errors (tens of them): from the best fit, fits are started at
    +-0.5 and +-1 log units along each of the ``n_directions`` directions of largest variance,
    and the best result is kept; repeated while it improves.
    """
    if len(problem.free) < 2:
        return theta
    # flat fields: every direction, each start fitted to convergence (a short fit from a
    # displaced start is often still above the optimum it would reach); rate tables (a few
    # dozen numbers, slow at large photon counts): one round on the weakest direction, short fits
    thorough = problem.meas.kind == "flat-field"
    for _ in range(rounds if thorough else 1):
        info, _, _ = information(problem, theta, steps(problem, 1e-4), want_meat=False)
        cov, _ = covariance(info, info)
        w, v = np.linalg.eigh(cov)
        improved = False
        base = theta
        for k in range(1, (min(n_directions, len(w)) if thorough else 1) + 1):
            direction = v[:, -k]
            scale = max(0.5, 1.5 * math.sqrt(max(w[-k], 0.0)))
            for t in (-2.0, -1.0, 1.0, 2.0):
                start = np.clip(base + t * scale * direction, problem.lo, problem.hi)
                cand, fc = (local_fit(problem, start, central=False) if thorough else
                            local_fit(problem, start, max_iter=12, polish=False, central=False))
                if fc < f - 1e-9 * (1 + abs(f)):
                    cand, fc = local_fit(problem, cand)
                    if fc < f:
                        log.info("ridge walk: objective %.10g -> %.10g", f, fc)
                        theta, f, improved = cand, fc, True
        if not improved:
            break
    return theta


def _looks_bad(problem: Problem, theta) -> bool:
    """Whether the fitted level means miss the measured ones by far more than their noise."""
    meas = problem.meas
    stats = problem.stats(theta)
    rate = stats.mean_rate()
    if meas.kind == "flat-field":
        for j, counts in enumerate(meas.pixel_counts):
            n = counts.shape[1]
            if n < 2:
                continue
            se = counts.std(axis=1, ddof=1) / math.sqrt(n)
            z = (counts.mean(axis=1) - rate[:, j] * meas.duration_s[j]) / np.maximum(se, 1e-12)
            if np.any(np.abs(z) > 6.0):
                return True
        return False
    if problem.quasi_counts:
        return False
    mu = problem.model_counts(stats)
    with np.errstate(divide="ignore", invalid="ignore"):
        pearson = float(np.sum((problem.y - mu) ** 2 / mu))
    return not pearson <= 5.0 * max(problem.y.size - len(problem.free), 1)


def reweighted(problem: Problem, theta) -> Problem:
    """The problem with each block of unknown noise scale weighted by its residual dispersion at ``theta``."""
    stats = problem.stats(theta)
    n_free = len(problem.free)
    n_c = problem.y.size
    n_s = problem.k_obs.size if problem.fit_shape else 0
    dof_share = lambda n: max(n - n_free * n / (n_c + n_s), 1.0)  # noqa: E731
    weights = {}
    if problem.quasi_counts:
        r = problem.log_residuals(problem.model_counts(stats))
        n_c = int(np.count_nonzero(problem.y > 0))
        weights["counts"] = 1.0 / max(float(np.sum(r**2)) / dof_share(n_c), 1e-300)
    if problem.fit_shape and problem.quasi_shape:
        e = problem.shape_residuals(stats)
        weights["shape"] = 1.0 / max(float(np.sum(e**2)) / dof_share(n_s), 1e-300)
    return problem.derive(problem.spec.with_weights(**weights))
