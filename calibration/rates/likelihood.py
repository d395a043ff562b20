"""The likelihood of the measurements: rate tables (Poisson or negative binomial of level totals, or
relative residuals without exposure, plus measured NB shapes) and flat fields (composite likelihood
of per-pixel counts, exact mixtures over the threshold distribution). Internal.

Background (leak floors, their growth with lux, per-pixel spread, hot pixels; see
:mod:`evnoise.background`): every rate and count distribution uses the per-trial probability with
the background added, ``P_k = p_k (1 - a_k) + a_k (1 - p_o)``, through
:class:`evnoise.mismatch.LevelStats`: its means and ``E[P^2]`` are exact, and its atoms
(:meth:`~evnoise.mismatch.LevelStats.atom_q`) mix the threshold atoms over the background nodes
(spread factor, hot-pixel rate), with the other polarity's photon-noise probability at its
population mean inside ``a_k (1 - p_o)`` (an error second order in small probabilities).
"""

from __future__ import annotations

import math

import numpy as np

from evnoise.mismatch import LevelStats
from evnoise.params import PARAM_LIMITS, NoiseParams

from ..measurements import Measurements
from .spec import FitSpec


class Prepared:
    """What the likelihood needs from the measurements, computed once and shared by every problem
    built on them (read-only after construction)."""

    def __init__(self, meas: Measurements):
        self.meas = meas
        self.lux = meas.lux
        if meas.kind == "flat-field":
            self._prepare_histograms()
        self._prepare_table()

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


class Problem:
    """The likelihood of measurements under a frozen :class:`~.spec.FitSpec`.

    ``Problem(meas, method, distribution, free, values, bounds, **options)`` builds the spec;
    :meth:`from_spec` takes one, and :meth:`derive` makes the problem of a changed spec on the same
    (already prepared) measurements. Only the cache of the last model statistics changes after
    construction.
    """

    def __init__(self, meas: Measurements, method, distribution, free, values, bounds, **options):
        self._build(FitSpec(method, distribution, free, values, bounds, **options), Prepared(meas))

    @classmethod
    def from_spec(cls, meas: Measurements, spec: FitSpec, prepared: Prepared | None = None) -> "Problem":
        """The problem of ``spec`` on ``meas`` (``prepared``: the measurements' prepared data, if at hand)."""
        problem = cls.__new__(cls)
        problem._build(spec, prepared if prepared is not None else Prepared(meas))
        return problem

    def derive(self, spec: FitSpec) -> "Problem":
        """The problem of another spec on the same measurements."""
        return Problem.from_spec(self.meas, spec, self._prepared)

    def with_value(self, name, value) -> "Problem":
        """The same problem with the fixed parameter ``name`` at ``value``."""
        return self.derive(self.spec.with_value(name, value))

    def _build(self, spec: FitSpec, prepared: Prepared):
        self.spec = spec
        self._prepared = prepared
        d = prepared
        self.meas, self.lux = d.meas, d.lux
        if self.meas.kind == "flat-field":
            self.hist, self.max_count = d.hist, d.max_count
        self.exposure, self.y, self.quasi_counts, self.use_shape = d.exposure, d.y, d.quasi_counts, d.use_shape
        self.nb_total_shape = d.nb_total_shape
        if self.use_shape:
            self.k_obs, self.k_sd, self.quasi_shape = d.k_obs, d.k_sd, d.quasi_shape
        self.lo = np.log([spec.bounds[n][0] for n in spec.free])
        # the search stays below NoiseParams' limits (PARAM_LIMITS), by the largest finite-difference
        # step taken there (uncertainty.steps), so that no point it evaluates is out of range
        margin = [0.02 if n in ("eps_pos", "eps_neg", "bias_pr") else 1e-3 for n in spec.free]
        limit = np.log([PARAM_LIMITS.get(n, math.inf) for n in spec.free]) - margin
        self.hi = np.minimum(np.log([spec.bounds[n][1] for n in spec.free]), limit)
        self._cache_key = None
        self._cache_val = None

    # -- the spec --------------------------------------------------------------------
    method = property(lambda self: self.spec.method)
    distribution = property(lambda self: self.spec.distribution)
    free = property(lambda self: self.spec.free)
    values = property(lambda self: self.spec.values)  # every field of NoiseParams: current value
    bounds = property(lambda self: self.spec.bounds)  # name -> (lo, hi), natural units
    weights = property(lambda self: self.spec.weights)
    fit_shape = property(lambda self: self.spec.fit_shape)
    assumed_sigma = property(lambda self: self.spec.assumed_sigma)

    # -- parameters --------------------------------------------------------------------
    def in_domain(self, theta) -> bool:
        """Whether ``theta`` (log values of the free parameters) is finite and within the bounds: the
        search's domain. :meth:`loglik` is ``-inf`` outside it, so that an optimiser step there is
        rejected like any worse point (and the search goes on)."""
        t = np.asarray(theta, dtype=np.float64)
        tol = 1e-9  # log(exp(t)) round trips of a value on a bound (NoiseParams -> theta) stay inside
        return bool(t.shape == self.lo.shape and np.all(np.isfinite(t)) and np.all(t >= self.lo - tol)
                    and np.all(t <= self.hi + tol))

    def params(self, theta) -> NoiseParams:
        t = np.asarray(theta, dtype=np.float64)
        if t.shape != self.lo.shape or not np.all(np.isfinite(t)) or not np.all(np.abs(t) < 700.0):
            # a bug of the search, not of the data: the optimisers only evaluate the model within the
            # bounds (loglik refuses other points) or a finite-difference step beyond them
            raise RuntimeError(f"calibration: the model was asked at a non-finite point (log values "
                               f"{dict(zip(self.free, t.ravel().tolist()))})")
        vals = dict(self.values)
        for name, t in zip(self.free, theta, strict=True):
            vals[name] = float(math.exp(t))
        return NoiseParams(**vals)

    def theta(self, params: NoiseParams) -> np.ndarray:
        return np.array([math.log(getattr(params, n)) for n in self.free])

    def stats(self, theta) -> LevelStats:
        key = tuple(np.asarray(theta, dtype=np.float64).tolist())
        if key != self._cache_key:
            p = self.params(theta)
            self._cache_val = LevelStats(p.photons_per_trial(self.lux), p, self.method)
            self._cache_key = key
        return self._cache_val

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
        """Log-likelihood (up to constants); ``-inf`` outside the search domain (a non-finite point or one
        beyond the bounds: an optimiser step there is rejected like any worse point, and the search goes on)."""
        if not self.in_domain(theta):
            return -math.inf
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
        """Negative log-likelihood, scaled per data point (for the optimisers); clipped into the bounds,
        ``inf`` at a non-finite point."""
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
