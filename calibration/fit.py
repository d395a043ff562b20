"""Maximum-likelihood calibration of :class:`evnoise.NoiseParams` to measurements.

Model
    At illuminance ``lux`` a pixel with thresholds ``(eps_on, eps_off)`` fires per trial with the
    exact probabilities of :mod:`evnoise.model` at ``lam = photons_per_lux (lux + dark_lux)``;
    thresholds vary across pixels as ``N(eps_pos|eps_neg, eps_sigma)`` truncated to ``> 0``
    (:mod:`evnoise.calibration.model` gives the exact distribution across pixels).

Likelihoods
    *Flat fields* (per-pixel counts): the composite likelihood of every pixel's count at every
    level, each the exact mixture over the threshold distribution of ``Binomial(M, q)``
    (``M = trial_rate_hz * duration_s`` trials; ``distribution="poisson"``: ``Poisson(M q)``).
    A pixel keeps its thresholds at all levels, so its counts are correlated; the
    uncertainties are the cluster-robust (sandwich) ones with pixels as clusters.
    *Rate tables*: Poisson likelihood of the total counts (negative binomial with the measured
    shape when ``r_on, r_off`` and ``n_pixels`` are given), plus, with measured shapes, a
    normal likelihood for the excess dispersion ``1/r``. When the absolute counts are unknown
    (no ``n_pixels, duration_s``) or the residuals scatter more than the count noise, the
    covariance is scaled by the residual dispersion (quasi-likelihood).

Fit
    All parameters are fitted on a log scale within data-scaled bounds (:data:`BOUNDS`). Global
    search: quasi-random seeds scored by a cheap stand-in (mean-rate deviance without mismatch,
    ``trial_rate_hz`` profiled out), stratified along ``bias_pr`` because the rate curve hardly
    changes along a ridge of (``photons_per_lux``, ``bias_pr``, thresholds) that carries several
    local optima of the exact model; two seeds per stratum are refined on the stand-in, a few
    Levenberg-Marquardt-damped Fisher-scoring steps of the full likelihood screen them, the
    best :data:`N_CONVERGED` are run to convergence, and short fits along the least-constrained
    direction look for a better optimum on the ridge. For the mismatch-free model (a step
    function of ``eps`` and ``bias_pr``) a Nelder-Mead polish follows. Uncertainties come from
    the expected information (or the sandwich) computed by central differences in
    log-parameter space; each step is checked against half of it, because without mismatch the
    likelihood is step-like.

Rate tables: profile of ``photons_per_lux``
    Along the ridge (``photons_per_lux`` up, thresholds down like its inverse square root,
    ``bias_pr`` up in proportion) the rate curve approaches the many-photon limit, where it no
    longer changes; the exact likelihood is rough there (a step function of the thresholds), so
    its local curvature says nothing about how far the ridge extends. The fit therefore profiles
    ``photons_per_lux`` (steps of :data:`PROFILE_STEP` in log, the others refitted at each) out
    to where the log-likelihood has dropped by 4.5 or to the bound: its standard error is the
    half-width of the interval where it is within 0.5 of the maximum (0.5 plus half of
    :data:`PROFILE_ROUGH` for the step-like mismatch-free likelihood), and the others'
    uncertainties add their movement along the profile to the conditional ones; a profile
    sharper than its steps falls back to the local information. An interval that reaches a
    bound means *not identified*, and so are the parameters that move with it.

Fit status
    :attr:`CalibrationResult.fit_status` is ``"accepted"``, ``"rejected"`` (goodness-of-fit
    p-value below :data:`REJECT_P`, or for rates without exposure an rms relative residual above
    :data:`REJECT_RMS`; the parameters are then marked ``"fitted (fit rejected)"``) and
    :attr:`CalibrationResult.warnings` says so, and names every parameter that sits on a bound.

Identifiability
    A parameter whose relative standard error exceeds ``max_rel_se`` is reported as *not
    identified*, together with the products/ratios of parameters that the data do constrain;
    parameters that sit on a bound (``bias_pr``, ``dark_lux``, ``eps_sigma`` -> 0) are reported
    as such and treated as fixed there for the uncertainties of the others.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math

import numpy as np

from evnoise.errors import InputError, ParameterError
from evnoise.params import NoiseParams

from .measurements import Measurements
from .model import METHODS, LevelStats

__all__ = ["calibrate", "CalibrationResult", "FIT_NAMES"]

log = logging.getLogger("evnoise.calibration")

#: Every parameter of :class:`NoiseParams`, in its order.
FIT_NAMES = tuple(f.name for f in dataclasses.fields(NoiseParams))
CORE = FIT_NAMES[:6]
DISTRIBUTIONS = ("binomial", "poisson")
#: Bounds of the fit (natural units). ``None`` entries are set from the data: ``trial_rate_hz``
#: from the highest rate (p < 1/2), ``photons_per_lux`` so that the brightest level has 1e-3 to
#: :data:`LAM_MAX` photons per trial (:data:`LAM_MAX_MISMATCH` with threshold mismatch),
#: ``dark_lux`` from 1e-6 to 10 times the brightest level, ``refractory_s`` below half the
#: shortest mean interval between events. ``calibrate(bounds=...)`` overrides any of them.
BOUNDS = {
    "eps_pos": (1e-3, 5.0),
    "eps_neg": (1e-3, 5.0),
    "bias_pr": (1e-6, 1e4),
    "trial_rate_hz": (None, 5e5),
    "photons_per_lux": (None, None),
    "dark_lux": (None, None),
    "refractory_s": (1e-8, None),
    "eps_sigma": (1e-3, 1.5),
}
#: Most photons per trial at the brightest level that the fit explores without threshold
#: mismatch: the range over which :mod:`evnoise.model`'s exact probability is verified (its cost
#: grows like ``sqrt(lam)``: about 10 ms for a 15-level table at 1e4 photons per trial). Real
#: sensors (the shipped EVK3-HD preset has 3200 at 50 lux) are far in this range; a fit that
#: runs into it is in the many-photon limit, where ``photons_per_lux`` is not identified.
LAM_MAX = 1e6
#: The same with threshold mismatch (``eps_sigma > 0``): the exact distribution of ``p`` across
#: pixels (:func:`evnoise.calibration.threshold_distribution`) costs O(lam) per level and
#: polarity (about 0.1 s at 3000 photons per trial, 30 s at 3e5), so the search stops here; the
#: mismatch-free alternative of a mean-rate table (see :data:`TABLE_SIGMA`) is not limited by it.
LAM_MAX_MISMATCH = 3000.0
_DEFAULTS = dict(eps_pos=0.5, eps_neg=0.5, bias_pr=1.0, trial_rate_hz=100.0, photons_per_lux=1.0, dark_lux=0.1,
                 refractory_s=0.0, eps_sigma=0.0)
#: Threshold mismatch assumed when the measurements carry no dispersion (mean rates only), unless
#: it is fixed explicitly or given by ``initial``: it is not determined by mean rates, mismatch
#: is always present in real sensors, and without it the exact likelihood is a step function of
#: the thresholds and the bias (see ``SMOOTHING``).
TABLE_SIGMA = 0.05
#: Mismatch levels of the continuation used to fit the mismatch-free (step-like) model to flat
#: fields (rate tables are fitted directly: their stand-in search is already smoothed).
SMOOTHING = (0.05, 0.02, 0.008)
#: Starts fitted to convergence after the short screening fits (optima are close in likelihood).
N_CONVERGED = 4
#: Goodness-of-fit p-value below which a fit is rejected (tables with counts, flat fields).
REJECT_P = 1e-4
#: Rates without exposure (no absolute noise scale): rms relative residual above which a fit is rejected.
REJECT_RMS = 0.25
#: Step of the profile of ``photons_per_lux`` (rate tables), in log units.
PROFILE_STEP = 0.35
#: Largest profile step (steps grow by half while the profile stays within its interval).
PROFILE_MAX_STEP = 1.5
#: The profile stops where twice the log-likelihood has dropped by this much from its maximum
#: (plus :data:`PROFILE_ROUGH` for step-like likelihoods).
PROFILE_STOP = 9.0
#: Without threshold mismatch the exact likelihood is a step function of the thresholds and the
#: bias, and fits along the profile land a few log-likelihood units apart by chance (up to about
#: 4 on tables simulated from the EVK3-HD preset, where the smooth profile is flat): a profile
#: point counts as inside the interval when twice its log-likelihood is within 1 + this of the
#: maximum, so that such jitter is not mistaken for information (it errs towards "not identified").
PROFILE_ROUGH = 10.0
_AT_BOUND_OK = ("bias_pr", "dark_lux", "eps_sigma", "refractory_s")  # a lower bound standing for 0


# --------------------------------------------------------------------------------------
# the problem: parameters <-> log vector, objective
# --------------------------------------------------------------------------------------
class _Problem:
    def __init__(self, meas: Measurements, method, distribution, free, values, bounds):
        self.meas = meas
        self.method = method
        self.distribution = distribution
        self.free = list(free)
        self.values = dict(values)  # every field of NoiseParams: current value
        self.bounds = bounds  # name -> (lo, hi), natural units
        self.lo = np.log([bounds[n][0] for n in self.free])
        self.hi = np.log([bounds[n][1] for n in self.free])
        self.lux = meas.lux
        self.weights = {"counts": 1.0, "shape": 1.0}
        self.fit_shape = False
        self.assumed_sigma = False
        self._cache_key = None
        self._cache_val = None
        self.n_eval = 0
        if meas.kind == "flat-field":
            self._prepare_histograms()
        self._prepare_table()

    # -- parameters --------------------------------------------------------------------
    def params(self, theta) -> NoiseParams:
        vals = dict(self.values)
        for name, t in zip(self.free, theta, strict=True):
            vals[name] = float(math.exp(t))
        return NoiseParams(**vals)

    def theta(self, params: NoiseParams) -> np.ndarray:
        return np.array([math.log(getattr(params, n)) for n in self.free])

    def set_value(self, name, value):
        """Change a fixed parameter (invalidates the cached model statistics)."""
        self.values[name] = float(value)
        self._cache_key = None

    def stats(self, theta) -> LevelStats:
        key = tuple(np.asarray(theta, dtype=np.float64).tolist())
        if key != self._cache_key:
            p = self.params(theta)
            self._cache_val = LevelStats(p.photons_per_trial(self.lux), p, self.method)
            self._cache_key = key
            self.n_eval += 1
        return self._cache_val

    # -- data preparation ----------------------------------------------------------------
    def _prepare_histograms(self):
        """Unique counts and multiplicities of every (polarity, level)."""
        m = self.meas
        self.hist = {}
        self.max_count = 0
        for j, c in enumerate(m.pixel_counts):
            for k in range(2):
                vals, mult = np.unique(c[k], return_counts=True)
                self.hist[k, j] = (vals.astype(np.float64), mult.astype(np.float64))
                self.max_count = max(self.max_count, int(vals[-1]))

    def _prepare_table(self):
        m = self.meas
        self.exposure = (m.duration_s * m.n_pixels) if m.exposure_known else np.ones(m.n_levels)
        self.y = m.rate_hz * self.exposure  # (2, J) counts (or rates with unit exposure)
        self.quasi_counts = not m.exposure_known
        self.use_shape = m.kind == "table" and m.nb_shape is not None
        if m.nb_shape is not None and m.exposure_known:
            self.nb_total_shape = m.nb_shape * m.n_pixels  # shape of the sum over n pixels
        else:
            self.nb_total_shape = None
        if self.use_shape:
            k_obs = 1.0 / m.nb_shape  # 0 where inf
            self.k_obs = k_obs
            if m.n_pixels is not None:
                se = _nb_log_shape_se(m.rate_hz * m.duration_s, m.nb_shape, m.n_pixels)
                self.k_sd = np.maximum(k_obs * se, 1e-6)
                self.quasi_shape = False
            else:
                self.k_sd = np.maximum(k_obs, 1e-3)
                self.quasi_shape = True

    # -- objective -------------------------------------------------------------------------
    def model_counts(self, stats: LevelStats) -> np.ndarray:
        return stats.mean_rate() * self.exposure

    def count_terms(self, mu):
        """Per-(polarity, level) log-likelihood of the level totals (up to constants).

        Unknown exposure (rates only): a normal likelihood of ``log rate`` with a common, unknown
        variance (relative errors), levels with zero rate left out.
        """
        y = self.y
        if self.quasi_counts:
            r = self.log_residuals(mu)
            return np.where(np.isfinite(r), -0.5 * r**2, -1e300)
        # y log(mu) only where y > 0 (elsewhere 0, also for mu = 0: no 0 * -inf)
        with np.errstate(divide="ignore"):
            log_mu = np.log(np.where(y > 0, mu, 1.0))
        y_log_mu = np.where(y > 0, y * log_mu, 0.0)
        if self.nb_total_shape is None:
            out = y_log_mu - mu
        else:
            R = self.nb_total_shape
            finite = np.isfinite(R)
            Rf = np.where(finite, R, 1.0)
            log_mu_r = np.log(mu + Rf)
            nb = y_log_mu - np.where(y > 0, y * log_mu_r, 0.0) + Rf * (np.log(Rf) - log_mu_r)
            out = np.where(finite, nb, y_log_mu - mu)
        return np.where(np.isfinite(out), out, -1e300)

    def log_residuals(self, mu) -> np.ndarray:
        """``log y - log mu`` where ``y > 0`` (0 elsewhere): the quasi block of rate tables."""
        y = self.y
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.log(np.where(y > 0, y, 1.0)) - np.log(mu)
        return np.where(y > 0, r, 0.0)

    def shape_residuals(self, stats: LevelStats) -> np.ndarray:
        k_model = stats.inverse_shape(self.meas.duration_s)
        return (k_model - self.k_obs) / self.k_sd

    def hist_tables(self, stats: LevelStats, k, j, counts):
        """``log P(c)`` of the mixture count distribution at ``counts`` for polarity k, level j."""
        from scipy.special import gammaln

        lq, mass = stats.atom_q(k, j)
        lq = np.asarray(lq)
        trials = stats.trial_rate_hz * self.meas.duration_s[j]
        c = np.asarray(counts, dtype=np.float64)
        q = np.exp(lq)
        log_mass = np.log(mass)[:, None]
        if self.distribution == "binomial":
            log1mq = np.log1p(-np.minimum(q, 1.0 - 1e-16))
            term = (gammaln(trials + 1.0) - gammaln(c + 1.0) - gammaln(np.maximum(trials - c, 0.0) + 1.0))[None, :]
            term = term + c[None, :] * lq[:, None] + (trials - c)[None, :] * log1mq[:, None]
            if np.any(c > trials):
                term[:, c > trials] = -np.inf
        else:
            lm = lq + math.log(trials)
            term = c[None, :] * lm[:, None] - np.exp(lm)[:, None] - gammaln(c + 1.0)[None, :]
        z = term + log_mass
        top = np.max(z, axis=0)
        out = np.full(c.size, -np.inf)
        ok = np.isfinite(top)
        out[ok] = top[ok] + np.log(np.sum(np.exp(z[:, ok] - top[ok]), axis=0))
        return out

    def loglik(self, theta) -> float:
        stats = self.stats(theta)
        if self.meas.kind == "flat-field":
            total = 0.0
            for (k, j), (vals, mult) in self.hist.items():
                lp = self.hist_tables(stats, k, j, vals)
                if not np.all(np.isfinite(lp)):
                    return -1e300
                total += float(np.dot(mult, lp))
            return total
        mu = self.model_counts(stats)
        total = self.weights["counts"] * float(np.sum(self.count_terms(mu)))
        if self.use_shape:
            e = self.shape_residuals(stats)
            total -= 0.5 * self.weights["shape"] * float(np.sum(e**2))
        return total

    def objective(self, theta) -> float:
        """Negative log-likelihood, scaled per data point (for the optimisers)."""
        theta = np.clip(theta, self.lo, self.hi)
        return -self.loglik(theta) / self.n_data

    @property
    def n_data(self) -> int:
        j = self.meas.n_levels
        return 2 * j * (2 if self.meas.has_dispersion else 1)


def _nb_log_shape_se(mean_count, r, n_pixels):
    """Standard error of ``log r`` estimated by maximum likelihood from ``n_pixels`` NB counts."""
    from scipy.stats import nbinom

    mean_count = np.asarray(mean_count, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    n = np.broadcast_to(np.asarray(n_pixels, dtype=np.float64), r.shape[-1:])
    out = np.full(r.shape, np.inf)
    for idx in np.ndindex(r.shape):
        mu, rr = mean_count[idx], r[idx]
        if not (np.isfinite(rr) and rr > 0 and mu > 0):
            continue
        prob = rr / (rr + mu)
        hi = int(nbinom.ppf(1 - 1e-12, rr, prob)) + 2
        j = np.arange(hi)
        info = float(np.sum(nbinom.sf(j, rr, prob) / (rr + j) ** 2) - mu / (rr * (rr + mu)))
        if info > 0:
            out[idx] = math.sqrt(1.0 / (n[idx[-1]] * info)) / rr
    return out


# --------------------------------------------------------------------------------------
# derivatives and information
# --------------------------------------------------------------------------------------
def _steps(problem: _Problem, base: float = 1e-3) -> np.ndarray:
    """Central-difference steps in log space (larger for step-like parameters without mismatch)."""
    coarse = problem.values.get("eps_sigma", 0.0) == 0.0 and "eps_sigma" not in problem.free
    h = np.full(len(problem.free), base)
    if coarse:
        for i, n in enumerate(problem.free):
            if n in ("eps_pos", "eps_neg", "bias_pr"):
                h[i] = max(base, 0.02)
    return h


def _shifted(theta, i, d):
    t = np.array(theta, dtype=np.float64)
    t[i] += d
    return t


def _information(problem: _Problem, theta, h, *, want_meat: bool = True, central: bool = True):
    """``(info, meat, extras)`` in log space: expected information and the robust meat.

    ``extras["score"]`` is the gradient of the log-likelihood (for Fisher scoring).
    """
    p = len(theta)
    m = problem.meas
    if m.kind == "flat-field":
        # per (k, j): log P(c) for c in the support, differentiated by central differences
        base = problem.stats(theta)
        ranges = {}
        for (k, j), (vals, _) in problem.hist.items():
            trials = base.trial_rate_hz * m.duration_s[j]
            hi = int(max(vals[-1], min(trials, 10.0 * base.mean_rate()[k, j] * m.duration_s[j] + 50.0)))
            ranges[k, j] = np.arange(hi + 1, dtype=np.float64)
        lp0 = {kj: problem.hist_tables(base, *kj, c) for kj, c in ranges.items()}
        deriv = {kj: np.zeros((c.size, p)) for kj, c in ranges.items()}
        for i in range(p):
            sp = problem.stats(_shifted(theta, i, h[i]))
            tables_p = {kj: problem.hist_tables(sp, *kj, c) for kj, c in ranges.items()}
            if central:
                sm = problem.stats(_shifted(theta, i, -h[i]))
            for kj, c in ranges.items():
                tm = problem.hist_tables(sm, *kj, c) if central else lp0[kj]
                with np.errstate(invalid="ignore"):
                    d = (tables_p[kj] - tm) / ((2 if central else 1) * h[i])
                deriv[kj][:, i] = np.where(np.isfinite(d), d, 0.0)
        problem.stats(theta)
        info = np.zeros((p, p))
        score = np.zeros(p)
        for (k, j) in ranges:
            prob = np.exp(lp0[k, j])
            d = deriv[k, j]
            info += m.n_pixels[j] * (d * prob[:, None]).T @ d
            vals, mult = problem.hist[k, j]
            score += mult @ d[vals.astype(np.int64)]
        if not want_meat:
            return info, None, {"deriv": deriv, "ranges": ranges, "score": score}
        # meat: per-pixel scores summed over levels and polarities, clustered by pixel id
        ids_all = np.concatenate(m.pixel_ids)
        uniq, inv_all = np.unique(ids_all, return_inverse=True)
        scores = np.zeros((uniq.size, p))
        start = 0
        for j, counts in enumerate(m.pixel_counts):
            n = counts.shape[1]
            inv = inv_all[start:start + n]
            start += n
            for k in range(2):
                s = deriv[k, j][counts[k]]
                np.add.at(scores, inv, s)
        g = uniq.size
        meat = scores.T @ scores * (g / max(g - 1, 1))
        return info, meat, {"deriv": deriv, "ranges": ranges, "score": score}
    # tables: Jacobians of the model means (and shapes) by central differences
    base = problem.stats(theta)
    mu0 = problem.model_counts(base)
    jac_mu = np.zeros((*mu0.shape, p))
    jac_e = None
    if problem.use_shape:
        e0 = problem.shape_residuals(base)
        jac_e = np.zeros((*e0.shape, p))
    for i in range(p):
        sp = problem.stats(_shifted(theta, i, h[i]))
        mup = problem.model_counts(sp)
        ep = problem.shape_residuals(sp) if jac_e is not None else None
        if central:
            sm = problem.stats(_shifted(theta, i, -h[i]))
            jac_mu[..., i] = (mup - problem.model_counts(sm)) / (2 * h[i])
            if jac_e is not None:
                jac_e[..., i] = (ep - problem.shape_residuals(sm)) / (2 * h[i])
        else:
            jac_mu[..., i] = (mup - mu0) / h[i]
            if jac_e is not None:
                jac_e[..., i] = (ep - e0) / h[i]
    problem.stats(theta)
    var = mu0.copy()
    if problem.nb_total_shape is not None:
        R = problem.nb_total_shape
        var = np.where(np.isfinite(R), mu0 + mu0**2 / np.where(np.isfinite(R), R, 1.0), mu0)
    jm = jac_mu.reshape(-1, p)
    if problem.quasi_counts:  # normal in log rate: d log mu = d mu / mu
        used = (problem.y > 0).ravel()
        with np.errstate(invalid="ignore", over="ignore"):
            jl = jm / np.maximum(mu0.ravel(), 1e-300)[:, None]
        jl = np.where(used[:, None] & np.isfinite(jl), jl, 0.0)
        info = problem.weights["counts"] * jl.T @ jl
        res = problem.log_residuals(mu0).ravel()
        score = problem.weights["counts"] * jl.T @ np.where(np.isfinite(res), res, 0.0)
    else:
        w = problem.weights["counts"] / np.maximum(var.ravel(), 1e-300)
        info = (jm * w[:, None]).T @ jm
        score = jm.T @ (w * (problem.y - mu0).ravel())
    if jac_e is not None:
        je = jac_e.reshape(-1, p)
        info += problem.weights["shape"] * je.T @ je
        score -= problem.weights["shape"] * je.T @ e0.ravel()
    return info, info.copy(), {"jac_mu": jac_mu, "jac_e": jac_e, "score": score}


def _covariance(info, meat):
    """Sandwich ``info^-1 meat info^-1`` by a scaled pseudo-inverse (rank-deficient safe)."""
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    scaled = info / np.outer(d, d)
    w, v = np.linalg.eigh(scaled)
    tol = max(w.max(), 0.0) * 1e-12
    inv_w = np.where(w > tol, 1.0 / np.where(w > tol, w, 1.0), 0.0)
    pinv = (v * inv_w) @ v.T / np.outer(d, d)
    cov = pinv @ meat @ pinv
    singular = np.where(w <= tol)[0]
    null_dirs = [v[:, i] / d for i in singular]
    return 0.5 * (cov + cov.T), null_dirs


# --------------------------------------------------------------------------------------
# optimisation
# --------------------------------------------------------------------------------------
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

    def __init__(self, problem: _Problem):
        self.pr = problem
        self.names = [n for n in problem.free if n not in ("refractory_s", "trial_rate_hz")]
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
            from ._kernels import log_probability_serial

            j = lam.shape[1]
            k = self.nodes.size
            eps = np.concatenate([np.maximum(vals[e][0] + sigma[e][0] * self.nodes, 1e-4)
                                  for e in ("eps_pos", "eps_neg")])  # (2K,)
            lam2 = np.ascontiguousarray(np.tile(lam[0], 2 * k))
            c2 = np.repeat(np.expm1(eps), j)
            out = np.empty(lam2.size)
            log_probability_serial(lam2, c2, np.full(lam2.size, vals["bias_pr"][0]), out)
            p = (np.exp(out).reshape(2, k, j) * self.weights[None, :, None]).sum(axis=1)[None]
        else:
            p = np.stack([
                np.einsum("skj,k->sj", event_probability(
                    lam[:, None, :], np.maximum(vals[e][:, None] + sigma[e] * self.nodes[None, :], 1e-4)[:, :, None],
                    vals["bias_pr"][:, None, None]), self.weights)
                for e in ("eps_pos", "eps_neg")], axis=1)  # (S, 2, J)
        base = p * pr.exposure[None, None, :]
        y = pr.y[None]
        if self.profile_n:
            lo, hi = pr.bounds["trial_rate_hz"]
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                n = np.clip(y.sum(axis=(1, 2)) / base.sum(axis=(1, 2)), lo, hi)
            n = np.where(np.isfinite(n), n, hi)
        else:
            n = vals["trial_rate_hz"]
        mu = base * n[:, None, None]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            dev = 2.0 * (np.where(y > 0, y * np.log(np.where(y > 0, y, 1.0) / mu), 0.0) - (y - mu))
        out = np.sum(dev, axis=(1, 2))
        self.last_n = n
        return np.where(np.isfinite(out), out, np.inf)

    def full_theta(self, x) -> np.ndarray:
        """The problem's log-parameter vector for proxy coordinates ``x`` (profiled N filled in)."""
        self.deviance(x[None, :])
        vals = dict(self.pr.values)
        for i, n in enumerate(self.names):
            vals[n] = float(math.exp(x[i]))
        if self.profile_n:
            vals["trial_rate_hz"] = float(self.last_n[0])
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


def _local_fit(problem: _Problem, theta0, *, max_iter: int = 80, polish: bool = True, central: bool = True):
    """Levenberg-Marquardt-damped Fisher scoring in log space, within the bounds.

    Each iteration needs the score and expected information (central differences, ``2 p``
    model evaluations); steps that do not increase the likelihood raise the damping. For the
    mismatch-free model (a step function of ``eps`` and ``bias_pr``) a Nelder-Mead polish
    follows, as derivatives there only see the large-scale slope.
    """
    lo, hi = problem.lo, problem.hi
    theta = np.clip(np.asarray(theta0, dtype=np.float64), lo, hi)
    ll = problem.loglik(theta)
    damping = 1e-3
    h = _steps(problem, 1e-4)
    for _ in range(max_iter):
        info, _, extras = _information(problem, theta, h, want_meat=False, central=central)
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


# --------------------------------------------------------------------------------------
# result
# --------------------------------------------------------------------------------------
@dataclasses.dataclass(eq=False)
class CalibrationResult:
    """Fitted parameters with uncertainties, identifiability and goodness of fit.

    Attributes
    ----------
    params : NoiseParams
        The fitted parameters (fixed ones at their given values).
    method : str
        Closed form used (``"poisson"`` exact or ``"gaussian"`` eq. 3).
    free : tuple of str
        Parameters that were fitted.
    status : dict
        Per parameter: ``"fitted"``, ``"fitted (fit rejected)"``, ``"fixed"``, ``"fixed (assumed)"``,
        ``"not identified"`` or ``"at lower bound"``.
    std_error : dict
        Standard errors in the parameters' units (NaN where not available).
    rel_error : dict
        Standard errors of ``log(value)`` (relative uncertainties).
    cov_log : numpy.ndarray
        Covariance of the log-parameters of ``free`` (in that order).
    correlation : numpy.ndarray
        The corresponding correlation matrix.
    identifiability : list of str
        Findings in words (what is and is not constrained).
    gof : dict
        Goodness of fit (see :meth:`summary`).
    dispersion : dict
        Measured vs predicted NB shape per level (``r_measured``, ``r_model``, ``(2, J)``).
    measurements : Measurements
    fit_status : str
        ``"accepted"`` or ``"rejected"`` (the goodness of fit says the model does not describe
        the data; see :data:`REJECT_P`).
    warnings : list of str
        What a user must not miss: a rejected fit, parameters on a bound.
    at_bound : dict
        Parameters that ended on a bound: name -> ``"lower"`` or ``"upper"``.
    bounds : dict
        The bounds of the free parameters (natural units).
    profile : dict
        Rate tables with ``photons_per_lux`` free: its profile-likelihood range (``name``,
        ``best``, ``low``, ``high``, ``closed_low``, ``closed_high``: whether the likelihood falls
        by more than ``loglik_tolerance`` on that side; an open side means not identified).
    """

    params: NoiseParams
    method: str
    distribution: str
    free: tuple
    status: dict
    std_error: dict
    rel_error: dict
    cov_log: np.ndarray
    correlation: np.ndarray
    identifiability: list
    gof: dict
    dispersion: dict
    measurements: Measurements
    loglik: float
    notes: list = dataclasses.field(default_factory=list)
    seed: object = None
    fit_status: str = "accepted"
    warnings: list = dataclasses.field(default_factory=list)
    at_bound: dict = dataclasses.field(default_factory=dict)
    bounds: dict = dataclasses.field(default_factory=dict)
    profile: dict = dataclasses.field(default_factory=dict)

    def population_rate(self, lux) -> np.ndarray:
        """Fitted mean rate over pixels, events/s, ``(2, *lux.shape)``."""
        from .model import population_rate

        return population_rate(lux, self.params, method=self.method)

    def rate_band(self, lux, *, n_sigma: float = 1.0):
        """``(rate, rel_sd)``: fitted population rate and its relative standard deviation (delta method)."""
        lux = np.asarray(lux, dtype=np.float64)
        rate = self.population_rate(lux)
        # parameters with an uncertainty (not those held on a bound, or not identified by a profile)
        idx = [i for i in range(len(self.free)) if np.isfinite(self.cov_log[i, i])]
        names = [self.free[i] for i in idx]
        if not names:
            return rate, np.zeros_like(rate)
        cov = self.cov_log[np.ix_(idx, idx)]
        jac = np.zeros((*rate.shape, len(names)))
        h = 1e-3
        for i, n in enumerate(names):
            v = getattr(self.params, n)
            up = self.params.replace(**{n: v * math.exp(h)})
            dn = self.params.replace(**{n: v * math.exp(-h)})
            from .model import population_rate

            with np.errstate(divide="ignore", invalid="ignore"):
                jac[..., i] = (np.log(population_rate(lux, up, method=self.method))
                               - np.log(population_rate(lux, dn, method=self.method))) / (2 * h)
        jac = np.where(np.isfinite(jac), jac, 0.0)
        var = np.einsum("...i,ij,...j->...", jac, cov, jac)
        return rate, n_sigma * np.sqrt(np.maximum(var, 0.0))

    def summary(self) -> str:
        """A readable report: parameters, uncertainties, identifiability, fit quality, dispersion."""
        lines = [f"evnoise calibration ({self.method} closed form, {self.measurements.kind}: "
                 f"{self.measurements.n_levels} levels from {self.measurements.source})"]
        lines.append(f"fit status: {self.fit_status.upper()}")
        lines += [f"WARNING: {t}" for t in self.warnings]
        lines.append(f"{'parameter':<16} {'value':>13} {'std error':>11} {'rel':>7}  status")
        for n in FIT_NAMES:
            v = getattr(self.params, n)
            se = self.std_error.get(n, math.nan)
            rel = self.rel_error.get(n, math.nan)
            se_t = "" if not np.isfinite(se) else f"{se:11.4g}"
            rel_t = "" if not np.isfinite(rel) else f"{100 * rel:6.1f}%"
            lines.append(f"{n:<16} {v:13.6g} {se_t:>11} {rel_t:>7}  {self.status.get(n, 'fixed')}")
        if self.identifiability:
            lines.append("identifiability:")
            lines += [f"  - {t}" for t in self.identifiability]
        lines.append("goodness of fit:")
        for k, v in self.gof.items():
            lines.append(f"  {k}: {_fmt(v)}")
        if self.dispersion.get("summary"):
            lines.append("over-dispersion (NB shape r, measured vs threshold mismatch):")
            lines.append(f"  {self.dispersion['summary']}")
        lines += [f"note: {t}" for t in self.notes]
        return "\n".join(lines)

    def to_toml(self, *, extra_provenance: dict | None = None) -> str:
        """The preset document: ``[params]``, ``[provenance]``, ``[fit]`` tables."""
        from .preset import result_to_toml

        return result_to_toml(self, extra_provenance=extra_provenance)

    def write_preset(self, path, *, overwrite: bool = False, extra_provenance: dict | None = None):
        """Write the preset TOML atomically; returns the path."""
        from .preset import write_text_atomic

        return write_text_atomic(path, self.to_toml(extra_provenance=extra_provenance), overwrite=overwrite)

    def plot(self, path, *, title: str | None = None, overwrite: bool = False, extra_curves=None,
             extra_r_curves=None):
        """Save a PNG of the data and the fitted curves (see :func:`evnoise.calibration.plot_fit`)."""
        from .plot import plot_fit

        return plot_fit(self, path, title=title, overwrite=overwrite, extra_curves=extra_curves,
                        extra_r_curves=extra_r_curves)


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


# --------------------------------------------------------------------------------------
# main entry point
# --------------------------------------------------------------------------------------
def _resolve(meas: Measurements, free, fixed, initial, fit_dispersion: bool = True):
    fixed = dict(fixed or {})
    for n in fixed:
        if n not in FIT_NAMES:
            raise ParameterError(f"unknown parameter {n!r} to fix; parameters: {', '.join(FIT_NAMES)}")
    if free is None:
        free = list(CORE)
        if meas.has_dispersion and fit_dispersion:
            free.append("eps_sigma")
    else:
        free = list(free)
        for n in free:
            if n not in FIT_NAMES:
                raise ParameterError(f"unknown parameter {n!r} to fit; parameters: {', '.join(FIT_NAMES)}")
        if len(set(free)) != len(free):
            raise ParameterError("a parameter is listed twice in free")
    free = [n for n in FIT_NAMES if n in free and n not in fixed]
    if not free:
        raise ParameterError("nothing to fit: every parameter is fixed")
    if "eps_sigma" in free and not (meas.has_dispersion and fit_dispersion):
        raise InputError("eps_sigma cannot be fitted from mean rates alone: give per-pixel counts (flat fields) "
                         "or measured NB shapes (r_on, r_off columns), or fix it")
    values = dict(_DEFAULTS)
    if not (meas.has_dispersion and fit_dispersion) and "eps_sigma" not in fixed and initial is None:
        values["eps_sigma"] = TABLE_SIGMA
    if initial is not None:
        if not isinstance(initial, NoiseParams):
            raise ParameterError(f"initial must be a NoiseParams, got {type(initial).__name__}")
        values.update(initial.to_dict())
    values.update({n: float(v) for n, v in fixed.items()})
    NoiseParams(**values)  # validates the fixed values
    return free, fixed, values


def _bounds(meas: Measurements, free, values, override=None):
    b = dict(BOUNDS)
    lux_ref = float(max(meas.lux.max(), 1e-6))
    rate_max = float(meas.rate_hz.max())
    n_lo = 2.0 * rate_max
    if meas.kind == "flat-field":
        n_lo = max(n_lo, max(float(c.max()) / d for c, d in zip(meas.pixel_counts, meas.duration_s)))
    b["trial_rate_hz"] = (max(n_lo * (1 + 1e-6), 1e-3), 5e5)
    mismatch = "eps_sigma" in free or values["eps_sigma"] > 0
    b["photons_per_lux"] = (1e-3 / lux_ref, (LAM_MAX_MISMATCH if mismatch else LAM_MAX) / lux_ref)
    b["dark_lux"] = (1e-6 * lux_ref, 10.0 * lux_ref)
    # the bias moves with photons_per_lux along the many-photon ridge: allow it as many photons
    b["bias_pr"] = (BOUNDS["bias_pr"][0], max(BOUNDS["bias_pr"][1], 10.0 * b["photons_per_lux"][1] * lux_ref))
    b["refractory_s"] = (1e-8, min(1.0, 0.5 / max(rate_max, 1e-9)))
    for n, (lo, hi) in (override or {}).items():
        b[n] = (float(lo), float(hi))
    for n in free:
        lo, hi = b[n]
        v = values[n]
        if not (lo < v < hi):
            values[n] = float(min(max(v, lo * 1.5), hi / 1.5))
    return b


def calibrate(measurements: Measurements, *, method: str = "poisson", distribution: str = "binomial",
              free=None, fixed: dict | None = None, initial: NoiseParams | None = None, n_starts: int = 4,
              n_seeds: int = 2048, rng=None, unidentified: str = "report", max_rel_se: float = 0.5,
              dispersion: str = "fit", bounds: dict | None = None, progress: bool = False) -> CalibrationResult:
    """Fit the noise model to measurements by maximum likelihood.

    Parameters
    ----------
    measurements : Measurements
        From :func:`read_measurements`, :func:`rate_table`, :func:`flat_field`, ...
    method : {"poisson", "gaussian"}
        Closed form of the per-trial probability: exact (default) or the paper's eq. 3.
    distribution : {"binomial", "poisson"}
        Flat fields: count distribution of one pixel given its thresholds (binomial in
        ``trial_rate_hz * duration_s`` trials, as the model; or Poisson, as the paper).
    free : sequence of str, optional
        Parameters to fit (default: the six core parameters, plus ``eps_sigma`` when the
        measurements carry dispersion). ``refractory_s`` is only fitted when listed.
    fixed : dict, optional
        Values of parameters held fixed (removed from ``free``).
    initial : NoiseParams, optional
        Starting point and values of parameters neither free nor fixed (default: zeros for
        ``refractory_s`` and ``eps_sigma``).
    n_starts : int
        Strata of starting points along ``bias_pr`` (two starts each are screened, the best
        :data:`N_CONVERGED` fitted to convergence): the rate curve is not monotonic and the
        likelihood has several local optima. More strata are slower and safer.
    n_seeds : int
        Quasi-random parameter vectors scored to choose the starts.
    rng : int, Generator or None
        Scrambling of the quasi-random seeds (None: fresh entropy; pass a seed for a
        reproducible fit).
    unidentified : {"report", "fix"}
        What to do with parameters the data do not constrain: keep the fitted value and report
        them (default), or fix them (at ``fixed``/``initial`` values if given, else at the
        fitted value) and refit the rest, so the others' uncertainties are conditional on them.
    max_rel_se : float
        Relative standard error above which a parameter counts as not identified.
    dispersion : {"fit", "report"}
        Rate tables with measured NB shapes: fit them (default; determines ``eps_sigma``) or
        only compare them with the model (``eps_sigma`` then fixed, at 0 unless given).
    bounds : dict, optional
        ``{name: (low, high)}`` in natural units, replacing the default bounds of those
        parameters (see :data:`BOUNDS`); a parameter that ends on one is flagged.
    progress : bool
        Show a progress bar over the starts.

    Returns
    -------
    CalibrationResult
    """
    from evnoise._checks import as_generator

    if not isinstance(measurements, Measurements):
        raise InputError(f"measurements must be a Measurements object, got {type(measurements).__name__}")
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    if distribution not in DISTRIBUTIONS:
        raise ParameterError(f"distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
    if unidentified not in ("report", "fix"):
        raise ParameterError(f"unidentified must be 'report' or 'fix', got {unidentified!r}")
    if dispersion not in ("fit", "report"):
        raise ParameterError(f"dispersion must be 'fit' or 'report', got {dispersion!r}")
    if dispersion == "report" and measurements.kind == "flat-field":
        raise ParameterError("dispersion='report' applies to rate tables; the flat-field likelihood always uses "
                             "the per-pixel counts")
    if not (isinstance(n_starts, int) and n_starts >= 1):
        raise ParameterError(f"n_starts must be an integer >= 1, got {n_starts!r}")
    if not (isinstance(n_seeds, int) and n_seeds >= n_starts):
        raise ParameterError(f"n_seeds must be an integer >= n_starts, got {n_seeds!r}")
    if not (isinstance(max_rel_se, (int, float)) and max_rel_se > 0):
        raise ParameterError(f"max_rel_se must be > 0, got {max_rel_se!r}")
    gen = as_generator(rng)
    meas = measurements
    free, fixed, values = _resolve(meas, free, fixed, initial, fit_dispersion=dispersion == "fit")
    n_points = 2 * meas.n_levels
    needed = len([n for n in free if n != "eps_sigma"]) + 1
    if n_points < needed:
        raise InputError(
            f"{meas.n_levels} illuminance levels give {n_points} rates, too few to fit {needed - 1} parameters "
            f"({', '.join(n for n in free if n != 'eps_sigma')}); measure more levels or fix some parameters"
        )
    bounds = _check_bounds(bounds)
    assumed = ("eps_sigma" not in free and "eps_sigma" not in fixed and initial is None
               and values["eps_sigma"] == TABLE_SIGMA)
    fit_args = dict(gen=gen, n_starts=n_starts, n_seeds=n_seeds, progress=progress, have_initial=initial is not None,
                    dispersion=dispersion, bounds=bounds)
    problem, theta = _fit(meas, method, distribution, free, values, assumed=assumed, **fit_args)
    want_profile = meas.kind == "table" and "photons_per_lux" in free and len(free) >= 2
    profile = sigma_note = None
    if assumed and TABLE_SIGMA > 0 and _rejected(problem, theta):
        # The assumed mismatch changes the shape of the mean curve where photons are many (its
        # bright tail no longer falls as fast), and the data reject it: fit without mismatch as
        # well and keep that when the data clearly prefer it (twice the log-likelihood ratio above 4).
        problem0, theta0 = _fit(meas, method, distribution, free, dict(values, eps_sigma=0.0), assumed=True,
                                **fit_args)
        profile0 = None
        if want_profile:
            theta0, profile0 = _profile(problem0, theta0, "photons_per_lux")
        ll_a, ll_0 = _comparable_loglik(problem, theta), _comparable_loglik(problem0, theta0)
        if 2.0 * (ll_0 - ll_a) > 4.0:
            problem, theta, profile = problem0, theta0, profile0
        sigma_note = (f"the fit with the assumed {TABLE_SIGMA:g} is rejected; of it and 0 the data prefer "
                      f"{problem.values['eps_sigma']:g} (twice the log-likelihood ratio {2.0 * (ll_0 - ll_a):+.3g} "
                      f"for 0; 0 is kept when above 4)")
    if want_profile and profile is None:
        theta, profile = _profile(problem, theta, "photons_per_lux")
    result = _finish(problem, theta, max_rel_se, profile=profile, sigma_note=sigma_note)
    if unidentified == "fix":
        flagged = [n for n in result.free if result.status[n] == "not identified"]
        if flagged:
            fit_vals = result.params.to_dict()
            new_fixed = dict(fixed)
            for n in flagged:
                new_fixed[n] = fixed.get(n, getattr(initial, n) if initial is not None else fit_vals[n])
            rest = [n for n in free if n not in flagged]
            if rest:
                init2 = result.params.replace(**{n: new_fixed[n] for n in flagged})
                result2 = calibrate(meas, method=method, distribution=distribution, free=rest, fixed=new_fixed,
                                    initial=init2, n_starts=1, n_seeds=max(n_starts, 1), rng=gen,
                                    unidentified="report", max_rel_se=max_rel_se, dispersion=dispersion,
                                    bounds=bounds, progress=False)
                for n in flagged:
                    result2.status[n] = "fixed (not identified)"
                result2.identifiability = result.identifiability + [
                    f"fixed (not identified): {', '.join(flagged)}; the other uncertainties are conditional on "
                    f"these values"] + [t for t in result2.identifiability if t not in result.identifiability]
                return result2
    return result


def _check_bounds(bounds):
    if bounds is None:
        return None
    if not isinstance(bounds, dict):
        raise ParameterError(f"bounds must be a dict name -> (low, high), got {type(bounds).__name__}")
    out = {}
    for n, v in bounds.items():
        if n not in FIT_NAMES:
            raise ParameterError(f"bounds: unknown parameter {n!r}; parameters: {', '.join(FIT_NAMES)}")
        try:
            lo, hi = (float(x) for x in v)
        except (TypeError, ValueError):
            raise ParameterError(f"bounds[{n!r}] must be a pair (low, high), got {v!r}") from None
        if not (0 < lo < hi < math.inf):
            raise ParameterError(f"bounds[{n!r}] must satisfy 0 < low < high < inf, got ({lo:g}, {hi:g})")
        out[n] = (lo, hi)
    return out


def _fit(meas, method, distribution, free, values, *, assumed, gen, n_starts, n_seeds, progress, have_initial,
         dispersion, bounds):
    """Build the problem and find its best optimum; ``(problem, theta)``."""
    values = dict(values)
    problem = _Problem(meas, method, distribution, free, values, _bounds(meas, free, values, bounds))
    problem.assumed_sigma = assumed
    problem.fit_shape = problem.use_shape and dispersion == "fit"
    if problem.use_shape and not problem.fit_shape:
        problem.weights["shape"] = 0.0
    quasi = problem.quasi_counts or (problem.fit_shape and problem.quasi_shape)
    if quasi and problem.fit_shape:
        problem.weights["shape"] = 0.0  # unknown scales: fit the mean curve first
    step_like = problem.values["eps_sigma"] == 0.0 and "eps_sigma" not in free and method == "poisson"
    if step_like and meas.kind == "flat-field":
        theta = _continuation(problem, gen, n_starts, n_seeds, progress, have_initial)
    elif step_like:
        # Rate tables: first a direct search (its starts come from a smoothed stand-in, and the exact
        # mismatch statistics of the continuation cost O(lam) per level at the large photon counts a
        # table may need); the continuation, within the bounds of a fit with mismatch, only when the
        # direct fit is rejected (few photons, where the steps of the likelihood are coarse).
        theta = _optimise(problem, problem.values, gen, n_starts, n_seeds, progress, have_initial)
        if _rejected(problem, theta):
            log.info("direct fit rejected; fitting the mismatch-free model by continuation")
            smooth = _Problem(meas, method, distribution, free, problem.values,
                              _bounds(meas, free, dict(problem.values, eps_sigma=SMOOTHING[0]), bounds))
            smooth.assumed_sigma, smooth.fit_shape, smooth.weights = assumed, problem.fit_shape, problem.weights
            theta2 = np.clip(_continuation(smooth, gen, n_starts, n_seeds, progress, have_initial),
                             problem.lo, problem.hi)
            theta2, _ = _local_fit(problem, theta2)
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
            _update_weights(problem, theta)
            theta, _ = _local_fit(problem, theta)
    return problem, theta


def _continuation(problem: _Problem, gen, n_starts, n_seeds, progress, have_initial):
    """Fit the mismatch-free (step-like) model by continuation: optimise with a little mismatch
    (:data:`SMOOTHING`) and follow the optimum as the mismatch goes to 0."""
    problem.set_value("eps_sigma", SMOOTHING[0])
    theta = _optimise(problem, problem.values, gen, n_starts, n_seeds, progress, have_initial)
    for s_c in SMOOTHING[1:] + (0.0,):
        problem.set_value("eps_sigma", s_c)
        theta, _ = _local_fit(problem, theta)
    return theta


def _rejected(problem: _Problem, theta) -> bool:
    """Whether the goodness of fit at ``theta`` rejects the model (see :func:`_verdict`)."""
    gof, _ = _goodness(problem, theta, {"ranges": None}, len(problem.free))
    return _verdict(problem, gof)[0] == "rejected"


def _comparable_loglik(problem: _Problem, theta) -> float:
    """Log-likelihood of the level totals with unit weights (profiled scale for rates without exposure)."""
    mu = problem.model_counts(problem.stats(theta))
    if problem.quasi_counts:
        used = problem.y > 0
        rss = float(np.sum(problem.log_residuals(mu)[used] ** 2))
        n = int(np.count_nonzero(used))
        return -0.5 * n * math.log(max(rss / n, 1e-300))
    return float(np.sum(problem.count_terms(mu)))


def _with_fixed(problem: _Problem, name: str, value: float):
    """A copy of ``problem`` with ``name`` held at ``value``; returns it and the indices of the others."""
    keep = [i for i, n in enumerate(problem.free) if n != name]
    sub = copy.copy(problem)
    sub.free = [problem.free[i] for i in keep]
    sub.lo, sub.hi = problem.lo[keep], problem.hi[keep]
    sub.values = dict(problem.values)
    sub.values[name] = float(value)
    sub._cache_key = sub._cache_val = None
    return sub, keep


def _step_like(problem: _Problem) -> bool:
    """Whether the likelihood is a step function of the thresholds (exact form, no mismatch)."""
    return problem.method == "poisson" and problem.values.get("eps_sigma", 0.0) == 0.0 \
        and "eps_sigma" not in problem.free


def _profile(problem: _Problem, theta, name: str, *, max_steps: int = 30):
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
    stop = PROFILE_STOP + (PROFILE_ROUGH if _step_like(problem) else 0.0)
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
            sub, keep = _with_fixed(problem, name, math.exp(t))
            ll, full = -math.inf, None
            for start in starts:
                x, _ = _local_fit(sub, np.clip(start[keep], sub.lo, sub.hi), max_iter=40, polish=False,
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
            flat = 2.0 * (best - ll) <= 1.0 + (PROFILE_ROUGH if _step_like(problem) else 0.0)
            step = min(step * 1.5, PROFILE_MAX_STEP) if flat else PROFILE_STEP
    points.sort(key=lambda q: q[0])
    k_best = int(np.argmax([q[1] for q in points]))
    if points[k_best][1] > ll0 + 1e-9 * (1.0 + abs(ll0)):
        # a better optimum along the profile: resume the full fit from it
        cand, _ = _local_fit(problem, points[k_best][2])
        theta = cand if problem.loglik(cand) >= points[k_best][1] else points[k_best][2]
        log.info("profile of %s found a better optimum: %.4g", name, math.exp(theta[i]))
        points.append((float(theta[i]), problem.loglik(theta), np.array(theta)))
        points.sort(key=lambda q: q[0])
    return theta, {"name": name, "points": points, "lo_bound": reached[-1], "hi_bound": reached[1]}


def _optimise(problem: _Problem, values, gen, n_starts, n_seeds, progress, have_initial):
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
        t, f = _local_fit(problem, s0, max_iter=10, polish=False, central=False) if len(starts) > 2 \
            else (s0, math.inf)
        trial.append((f, k, t))
        if bar is not None:
            bar.update(1)
    trial.sort(key=lambda r: r[0])
    for _, k, t0 in trial[:N_CONVERGED]:
        t, f = _local_fit(problem, t0)
        log.info("start %d/%d: objective %.10g", k + 1, len(starts), f)
        if f < best[1]:
            best = (t, f)
    if bar is not None:
        bar.close()
    return _ridge_walk(problem, best[0], best[1])


def _ridge_walk(problem: _Problem, theta, f, *, rounds: int = 2, n_directions: int = 3):
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
        info, _, _ = _information(problem, theta, _steps(problem, 1e-4), want_meat=False)
        cov, _ = _covariance(info, info)
        w, v = np.linalg.eigh(cov)
        improved = False
        base = theta
        for k in range(1, (min(n_directions, len(w)) if thorough else 1) + 1):
            direction = v[:, -k]
            scale = max(0.5, 1.5 * math.sqrt(max(w[-k], 0.0)))
            for t in (-2.0, -1.0, 1.0, 2.0):
                start = np.clip(base + t * scale * direction, problem.lo, problem.hi)
                cand, fc = (_local_fit(problem, start, central=False) if thorough else
                            _local_fit(problem, start, max_iter=12, polish=False, central=False))
                if fc < f - 1e-9 * (1 + abs(f)):
                    cand, fc = _local_fit(problem, cand)
                    if fc < f:
                        log.info("ridge walk: objective %.10g -> %.10g", f, fc)
                        theta, f, improved = cand, fc, True
        if not improved:
            break
    return theta


def _looks_bad(problem: _Problem, theta) -> bool:
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


def _update_weights(problem: _Problem, theta):
    stats = problem.stats(theta)
    n_free = len(problem.free)
    n_c = problem.y.size
    n_s = problem.k_obs.size if problem.fit_shape else 0
    dof_share = lambda n: max(n - n_free * n / (n_c + n_s), 1.0)  # noqa: E731
    if problem.quasi_counts:
        r = problem.log_residuals(problem.model_counts(stats))
        n_c = int(np.count_nonzero(problem.y > 0))
        problem.weights["counts"] = 1.0 / max(float(np.sum(r**2)) / dof_share(n_c), 1e-300)
    if problem.fit_shape and problem.quasi_shape:
        e = problem.shape_residuals(stats)
        problem.weights["shape"] = 1.0 / max(float(np.sum(e**2)) / dof_share(n_s), 1e-300)


def _finish(problem: _Problem, theta, max_rel_se, *, profile=None, sigma_note=None) -> CalibrationResult:
    meas = problem.meas
    params = problem.params(theta)
    free = list(problem.free)
    p = len(free)
    status = {n: "fixed" for n in FIT_NAMES}
    at_bound = []  # indices held at a bound
    bound_side = {}  # name -> "lower" | "upper"
    for i, n in enumerate(free):
        status[n] = "fitted"
        if theta[i] <= problem.lo[i] + 1e-3:
            bound_side[n] = "lower"
        elif theta[i] >= problem.hi[i] - 1e-3:
            bound_side[n] = "upper"
        if n in _AT_BOUND_OK and bound_side.get(n) == "lower":
            status[n] = "at lower bound"
            at_bound.append(i)
        elif n in bound_side:
            status[n] = "not identified"
            at_bound.append(i)
    # a profile that falls beyond its tolerance within one step on both sides is sharper than its
    # grid resolves: the local information is the better uncertainty then
    sharp = profile is not None and _profile_is_sharp(problem, theta, profile)
    i_prof = free.index(profile["name"]) if profile is not None and not sharp else None
    held = sorted(set(at_bound) | ({i_prof} if i_prof is not None else set()))
    inner = [i for i in range(p) if i not in held]
    notes = []
    h = _steps(problem)
    info, meat, extras = _information(problem, theta, h)
    cov = np.full((p, p), np.nan)
    if inner:
        ix = np.ix_(inner, inner)
        c_in, null_dirs = _covariance(info[ix], meat[ix])
        cov[ix] = c_in
        # checked step: redo with half the steps; disagreement means a step-like likelihood
        info2, meat2, _ = _information(problem, theta, h / 2)
        c2, _ = _covariance(info2[ix], meat2[ix])
        se1 = np.sqrt(np.maximum(np.diag(c_in), 0))
        se2 = np.sqrt(np.maximum(np.diag(c2), 0))
        for a, i in enumerate(inner):
            if se1[a] > 0 and np.isfinite(se1[a]) and abs(se2[a] / se1[a] - 1) > 0.25:
                notes.append(f"the uncertainty of {free[i]} depends on the differencing step ({se1[a]:.3g} vs "
                             f"{se2[a]:.3g} in log): the likelihood is step-like there (no threshold mismatch); "
                             f"treat it as approximate")
    else:
        null_dirs = []
    ident = []
    moving = []  # parameters that move with an unbounded profile
    profile_range = {}
    if i_prof is not None:
        text, cov, moving, closed, profile_range = _profile_uncertainty(problem, theta, profile, cov, inner,
                                                                        max_rel_se)
        ident.append(text)
        if closed and i_prof not in at_bound:
            inner = sorted(inner + [i_prof])
        else:
            status[free[i_prof]] = "not identified"
        for n in moving:
            status[n] = "not identified"
        inner = [i for i in inner if free[i] not in moving]
    rel = {n: math.nan for n in FIT_NAMES}
    se = {n: math.nan for n in FIT_NAMES}
    for i, n in enumerate(free):
        if i in inner:
            rel[n] = float(math.sqrt(max(cov[i, i], 0.0)))
            se[n] = rel[n] * getattr(params, n)
    if sharp:
        n = profile["name"]
        profile_range = {"name": n, "best": getattr(params, n), "low": getattr(params, n) * math.exp(-rel[n]),
                         "high": getattr(params, n) * math.exp(rel[n]), "closed_low": True, "closed_high": True,
                         "loglik_tolerance": 0.5}
    flagged = [free[i] for i in inner if not (rel[free[i]] <= max_rel_se)]
    for n in flagged:
        status[n] = "not identified"
    with np.errstate(invalid="ignore", divide="ignore"):
        dd = np.sqrt(np.diag(cov))
        corr = cov / np.outer(dd, dd)
    ident += _identifiability_text(free, inner, cov, corr, flagged, null_dirs, max_rel_se)
    if problem.assumed_sigma:
        status["eps_sigma"] = "fixed (assumed)"
        ident.append(f"eps_sigma is not determined by mean rates; it is fixed at an assumed "
                     f"{problem.values['eps_sigma']:g}" + (f" ({sigma_note})" if sigma_note else "")
                     + " (give per-pixel counts or measured NB shapes to fit it, or --fix eps_sigma=...)")
    for i in at_bound:
        n = free[i]
        v = getattr(params, n)
        if status[n] == "at lower bound":
            ident.append(f"{n} is at its lower bound ({v:.3g}): the data are consistent with 0; it is held there "
                         f"for the other uncertainties")
        elif n == "photons_per_lux" and bound_side.get(n) == "upper":
            ident.append(f"photons_per_lux ran into its upper bound ({v:.3g}, {v * float(meas.lux.max()):.3g} "
                         f"photons per trial at the brightest level): the rates look like the many-photon (Gaussian) "
                         f"limit, where only photons_per_lux / bias_pr and eps scaled by sqrt(photons_per_lux) are "
                         f"determined; it is not identified, fix it if it is known (--fix photons_per_lux=...)")
        else:
            ident.append(f"{n} ran into its {bound_side[n]} bound ({v:.3g}) and is not identified by these data; "
                         f"it is held there for the other uncertainties")
    gof, dispersion = _goodness(problem, theta, extras, p)
    fit_status, why = _verdict(problem, gof)
    warnings = []
    if fit_status == "rejected":
        warnings.append(f"fit rejected: {why}; the model with these parameters does not describe the data (check "
                        f"the measurements, fixed values and bounds)")
        for n in free:
            if status[n] == "fitted":
                status[n] = "fitted (fit rejected)"
    for n, side in bound_side.items():
        v = getattr(params, n)
        lo, hi = problem.bounds[n]
        extra = " (consistent with 0)" if status[n] == "at lower bound" else " (not identified)"
        warnings.append(f"{n} is on its {side} bound {v:.4g} (bounds {lo:.3g} .. {hi:.3g}){extra}")
    return CalibrationResult(params=params, method=problem.method, distribution=problem.distribution,
                             free=tuple(free), status=status, std_error=se, rel_error=rel, cov_log=cov,
                             correlation=corr, identifiability=ident, gof=gof, dispersion=dispersion,
                             measurements=meas, loglik=float(problem.loglik(theta)), notes=notes,
                             fit_status=fit_status, warnings=warnings, at_bound=dict(bound_side),
                             bounds={n: tuple(problem.bounds[n]) for n in free}, profile=profile_range)


def _verdict(problem: _Problem, gof) -> tuple[str, str]:
    """``("accepted" | "rejected", reason)`` from the goodness of fit."""
    if problem.meas.kind == "flat-field":
        pv, z = gof.get("histogram_p_value", math.nan), gof.get("mean_rate_max_abs_z", math.nan)
        if not pv >= REJECT_P:
            return "rejected", (f"the count histograms do not match (G/dof = {gof['histogram_G_per_dof']:.3g}, "
                                f"p = {pv:.2g} < {REJECT_P:g})")
        if not z <= 6.0:
            return "rejected", f"a level's mean count is {z:.3g} standard errors off"
        return "accepted", ""
    if problem.quasi_counts:
        rms = gof.get("rate_rms_log_residual", math.nan)
        if not rms <= REJECT_RMS:
            return "rejected", f"rms relative residual of the rates {rms:.3g} > {REJECT_RMS:g}"
        return "accepted", ""
    pv = gof.get("p_value", math.nan)
    if not pv >= REJECT_P:
        return "rejected", (f"Pearson chi2/dof = {gof['pearson_chi2_per_dof']:.3g} on {gof['dof']} dof "
                            f"(p = {pv:.2g} < {REJECT_P:g})")
    return "accepted", ""


def _profile_levels(problem: _Problem, theta, profile):
    """``(t, dev, k0, level)``: profile points, twice the log-likelihood drop, index of the best, tolerance."""
    i = problem.free.index(profile["name"])
    pts = profile["points"]
    t = np.array([q[0] for q in pts])
    ll = np.array([q[1] for q in pts])
    dev = 2.0 * (max(float(ll.max()), float(problem.loglik(theta))) - ll)
    k0 = int(np.argmin(np.abs(t - theta[i])))
    level = 1.0 + (PROFILE_ROUGH if _step_like(problem) else 0.0)
    return t, dev, k0, level


def _profile_is_sharp(problem: _Problem, theta, profile) -> bool:
    t, dev, k0, level = _profile_levels(problem, theta, profile)
    return 0 < k0 < t.size - 1 and dev[k0 - 1] > level and dev[k0 + 1] > level


def _profile_uncertainty(problem: _Problem, theta, profile, cov, inner, max_rel_se):
    """Uncertainty of the profiled parameter and the others' movement along its profile.

    Returns ``(finding, cov, moving, closed, range)``: ``cov`` with the profiled parameter's row (and
    the others' path term) filled in when its interval is closed; ``moving``: parameters that
    change by more than ``max_rel_se`` (in log) while it runs over an open interval.
    """
    name = profile["name"]
    free = problem.free
    i = free.index(name)
    th = np.array([q[2] for q in profile["points"]])
    t, dev, k0, level = _profile_levels(problem, theta, profile)
    rough = level - 1.0

    def crossing(step):
        k = k0
        while 0 <= k + step < t.size:
            if dev[k + step] > level:
                a, b = dev[k], dev[k + step]
                w = (level - a) / (b - a) if b != a else 0.0
                return t[k] + w * (t[k + step] - t[k]), True
            k += step
        return t[k], False

    t_lo, closed_lo = crossing(-1)
    t_hi, closed_hi = crossing(+1)
    closed = closed_lo and closed_hi
    info = {"name": name, "best": math.exp(theta[i]), "low": math.exp(t_lo), "high": math.exp(t_hi),
            "closed_low": closed_lo, "closed_high": closed_hi, "loglik_tolerance": (1.0 + rough) / 2.0}
    cov = cov.copy()
    v = math.exp(theta[i])
    within = dev <= (4.0 + rough if closed else level)
    others = [j for j in inner if j != i]
    moving = []
    if closed:
        var_t = ((t_hi - t_lo) / 2.0) ** 2
        g = np.zeros(len(free))
        g[i] = 1.0
        if np.count_nonzero(within) >= 2:
            for j in others:
                g[j] = np.polyfit(t[within], th[within, j], 1)[0]
        idx = others + [i]
        base = np.where(np.isfinite(cov), cov, 0.0)
        full = base + np.outer(g, g) * var_t
        cov[np.ix_(idx, idx)] = full[np.ix_(idx, idx)]
        text = (f"{name}: profile likelihood within {level / 2:g} of its maximum from {math.exp(t_lo):.4g} to "
                f"{math.exp(t_hi):.4g} (best {v:.4g}); the other uncertainties include their movement along it")
        return text, cov, moving, True, info
    # open interval: how far the others move over it
    parts = []
    for j in others:
        spread = float(th[within, j].max() - th[within, j].min()) if within.any() else 0.0
        if spread / 2.0 > max_rel_se:
            moving.append(free[j])
            slope = np.polyfit(t[within], th[within, j], 1)[0] if np.count_nonzero(within) >= 2 else math.nan
            parts.append(f"{free[j]} ~ {name}^{slope:+.2f}")
        elif spread > 0:
            cov[j, j] = cov[j, j] + (spread / 2.0) ** 2
    lo_txt = f"{math.exp(t_lo):.4g}" + (" (its lower bound)" if not closed_lo and profile["lo_bound"] else
                                        "" if closed_lo else " (end of the profile)")
    hi_txt = f"{math.exp(t_hi):.4g}" + (" (its upper bound)" if not closed_hi and profile["hi_bound"] else
                                        "" if closed_hi else " (end of the profile)")
    text = (f"{name} is not identified: the profile likelihood stays within {level / 2:g} of its maximum from "
            f"{lo_txt} to {hi_txt} (best {v:.4g})")
    if parts:
        text += f"; {', '.join(moving)} move with it ({', '.join(parts)}) and are not identified either"
    return text, cov, moving, False, info


def _identifiability_text(free, inner, cov, corr, flagged, null_dirs, max_rel_se):
    out = []
    names = [free[i] for i in inner]
    for a in range(len(inner)):
        for b in range(a + 1, len(inner)):
            r = corr[inner[a], inner[b]]
            if np.isfinite(r) and abs(r) > 0.95:
                out.append(f"{names[a]} and {names[b]} are strongly correlated (r = {r:+.3f})")
    for n in flagged:
        i = free.index(n)
        best = None
        for j in inner:
            if j == i:
                continue
            for sign in (+1, -1):
                v = cov[i, i] + cov[j, j] + 2 * sign * cov[i, j]
                if np.isfinite(v) and (best is None or v < best[0]):
                    best = (v, j, sign)
        text = f"{n} is not identified (relative error {math.sqrt(max(cov[i, i], 0)):.2g} > {max_rel_se:g})"
        if best is not None and best[0] < max_rel_se**2:
            op = "*" if best[2] > 0 else "/"
            text += (f"; only {n} {op} {free[best[1]]} is constrained (relative error "
                     f"{math.sqrt(max(best[0], 0)):.2g})")
        out.append(text)
    if len(inner) > 1:
        sub = cov[np.ix_(inner, inner)]
        w, v = np.linalg.eigh(sub)
        for k in range(len(w) - 1, -1, -1):
            if not (np.isfinite(w[k]) and w[k] > max_rel_se**2):
                break
            comp = v[:, k] / np.max(np.abs(v[:, k]))
            terms = [f"{names[a]}^{comp[a]:+.2f}" for a in np.argsort(-np.abs(comp)) if abs(comp[a]) > 0.2]
            out.append(f"poorly constrained direction (relative sd {math.sqrt(w[k]):.2g}): "
                       f"{' * '.join(terms)} can change together with little effect on the fit")
    for dvec in null_dirs:
        comp = dvec / np.max(np.abs(dvec))
        terms = [f"{names[a]}^{comp[a]:+.2f}" for a in np.argsort(-np.abs(comp)) if abs(comp[a]) > 0.2]
        out.append(f"unconstrained direction (no information): {' * '.join(terms)}")
    return out


def _goodness(problem: _Problem, theta, extras, n_free):
    from scipy.stats import chi2

    meas = problem.meas
    stats = problem.stats(theta)
    gof = {}
    rate_model = stats.mean_rate()
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_res = rate_model / meas.rate_hz - 1.0
    ok = np.isfinite(rel_res)
    gof["rate_rms_relative_residual"] = float(np.sqrt(np.mean(rel_res[ok] ** 2))) if ok.any() else math.nan
    gof["rate_max_relative_residual"] = float(np.max(np.abs(rel_res[ok]))) if ok.any() else math.nan
    disp = {"r_measured": meas.nb_shape, "r_model": None, "summary": ""}
    if meas.duration_s is not None and (meas.nb_shape is not None or stats.log_m1.size):
        inv = stats.inverse_shape(meas.duration_s)
        with np.errstate(divide="ignore"):
            r_model = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), np.inf)
        disp["r_model"] = r_model
    if meas.kind == "flat-field":
        g_total, dof_total = 0.0, 0
        z_means = np.zeros((2, meas.n_levels))
        for (k, j), (vals, mult) in problem.hist.items():
            c = extras["ranges"][k, j]
            prob = np.exp(problem.hist_tables(stats, k, j, c))
            n = meas.n_pixels[j]
            obs = np.zeros(c.size)
            inside = vals <= c[-1]
            obs[vals[inside].astype(int)] = mult[inside]
            exp_ = n * prob
            # pool bins from the top so that each has expected >= 5
            o_b, e_b = [], []
            acc_o = acc_e = 0.0
            for i in range(c.size - 1, -1, -1):
                acc_o += obs[i]
                acc_e += exp_[i]
                if acc_e >= 5.0:
                    o_b.append(acc_o)
                    e_b.append(acc_e)
                    acc_o = acc_e = 0.0
            if o_b:
                o_b[-1] += acc_o
                e_b[-1] += acc_e
            o_b, e_b = np.array(o_b), np.array(e_b)
            e_b *= o_b.sum() / max(e_b.sum(), 1e-300)
            with np.errstate(divide="ignore", invalid="ignore"):
                g = 2.0 * np.sum(np.where(o_b > 0, o_b * np.log(o_b / e_b), 0.0))
            g_total += float(g)
            dof_total += max(o_b.size - 1, 0)
            counts = meas.pixel_counts[j][k]
            sd = counts.std(ddof=1) / math.sqrt(counts.size) if counts.size > 1 else math.inf
            z_means[k, j] = (counts.mean() - rate_model[k, j] * meas.duration_s[j]) / sd if sd > 0 else 0.0
        dof = max(dof_total - n_free, 1)
        gof["histogram_G"] = g_total
        gof["histogram_dof"] = dof
        gof["histogram_G_per_dof"] = g_total / dof
        gof["histogram_p_value"] = float(chi2.sf(g_total, dof))
        gof["mean_rate_max_abs_z"] = float(np.max(np.abs(z_means)))
        gof["note"] = ("G-test of each level's count histogram against the fitted mixture (levels share pixels, "
                       "so the p-value is approximate)")
    else:
        mu = problem.model_counts(stats)
        y = problem.y
        with np.errstate(divide="ignore", invalid="ignore"):
            dev = 2.0 * np.sum(np.where(y > 0, y * np.log(np.where(y > 0, y, 1.0) / mu), 0.0) - (y - mu))
            pearson = float(np.sum((y - mu) ** 2 / mu))
        n_data = y.size + (problem.k_obs.size if problem.fit_shape else 0)
        dof = max(n_data - n_free, 1)
        if problem.quasi_counts:
            gof["counts"] = ("unknown (no n_pixels/duration_s): relative (log) residuals, uncertainties scaled by "
                             "their scatter")
            gof["rate_rms_log_residual"] = float(np.sqrt(np.mean(problem.log_residuals(mu)[y > 0] ** 2)))
        else:
            gof["poisson_deviance"] = float(dev)
            gof["pearson_chi2"] = pearson
            gof["dof"] = dof
            gof["pearson_chi2_per_dof"] = pearson / dof
            gof["p_value"] = float(chi2.sf(pearson, dof))
        if problem.fit_shape:
            e = problem.shape_residuals(stats)
            gof["shape_residual_rms"] = float(np.sqrt(np.mean(e**2)))
        gof["dispersion_weights"] = {k: float(v) for k, v in problem.weights.items()}
    if disp["r_model"] is not None and meas.nb_shape is not None:
        r_m, r_o = disp["r_model"], meas.nb_shape
        both = np.isfinite(r_m) & np.isfinite(r_o) & (r_o > 0)
        finite_o = r_o[np.isfinite(r_o)]
        if not np.any(np.isfinite(r_m)) and finite_o.size:
            disp["summary"] = (f"the fit has no threshold mismatch (eps_sigma = 0), so its counts are not "
                               f"over-dispersed; measured r {finite_o.min():.3g} .. {finite_o.max():.3g}")
        if both.any():
            lr = np.log(r_m[both] / r_o[both])
            disp["log_ratio_rms"] = float(np.sqrt(np.mean(lr**2)))
            disp["log_ratio_max"] = float(np.max(np.abs(lr)))
            disp["summary"] = (f"model/measured r: median {np.exp(np.median(lr)):.3g}, rms |log ratio| "
                               f"{disp['log_ratio_rms']:.3g}, worst {np.exp(lr[np.argmax(np.abs(lr))]):.3g} "
                               f"(measured r {np.nanmin(r_o[both]):.3g} .. {np.nanmax(r_o[both]):.3g})")
    return gof, disp

