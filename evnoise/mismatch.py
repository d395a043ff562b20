"""Population statistics of the noise model across pixels with threshold mismatch.

:func:`evnoise.expected_rate` gives the rate of *one* pixel whose thresholds are the nominal
ones. A measurement averages over many pixels whose thresholds differ (``eps_sigma > 0``), and
the across-pixel spread is what makes counts negative-binomial. This module computes, for a
static illuminance, the distribution of the per-trial probability ``p`` across pixels and
from it:

- :func:`population_rate`: the mean rate over pixels, events/s ``[ON, OFF]``;
- :func:`nb_shape`: the negative-binomial shape ``r`` of the per-pixel count over a window of
  ``duration_s`` seconds that has the same mean and variance (``var = mu + mu^2 / r``).

With ``method="poisson"`` (default) the distribution is exact (see
:mod:`evnoise._kernels.mismatch`): ``p`` is a step function of the threshold, so the
average over a normal threshold is a finite sum over the steps, with no quadrature error.
With ``method="gaussian"`` (the paper's eq. 3, smooth in ``eps``) it uses Gauss-Legendre
quadrature on the normal's probability scale (``GAUSS_NODES`` nodes).

Count model of one pixel (thresholds fixed) over ``T`` seconds: ``Binomial(M, q)`` with
``M = trial_rate_hz * T`` trials (a real ``M`` through the gamma function) and
``q = nu / trial_rate_hz``; ``nu`` includes the refractory period as the non-paralyzable
dead time of :func:`evnoise.expected_rate`, with the other polarity at its population mean
(exact for ``refractory_s = 0``; the error is second order in ``nu * refractory_s``).
"""

from __future__ import annotations

import math

import numpy as np

from ._checks import check_lux, check_params, check_positive
from .errors import ParameterError

__all__ = ["threshold_distribution", "population_rate", "nb_shape", "level_statistics"]

METHODS = ("poisson", "gaussian")
#: Width in ``log p`` of the bins the exact atoms are merged into for count likelihoods.
ATOM_BIN = 0.01
#: Gauss-Legendre nodes of the Gaussian-form average over the threshold distribution.
GAUSS_NODES = 96


def _gauss_atoms(lam, b, mu, s):
    """Atoms of ``log p`` for the Gaussian form (quadrature on the probability scale)."""
    from scipy.special import ndtr, ndtri

    from evnoise.model import log_event_probability

    if s <= 0:
        lp = float(log_event_probability(lam, mu, b, method="gaussian"))
        return np.array([lp]), np.array([1.0])
    x, w = np.polynomial.legendre.leggauss(GAUSS_NODES)
    lo = ndtr(-mu / s)  # P(eps <= 0): truncated away
    u = lo + (1.0 - lo) * 0.5 * (x + 1.0)
    eps = mu + s * ndtri(u)
    eps = np.maximum(eps, 1e-12)
    lp = log_event_probability(lam, eps, b, method="gaussian")
    return lp, 0.5 * w


def _atoms(lam, b, mu, s, method):
    """``(log_p atoms, masses, log E[p], log E[p^2])`` at one photon count."""
    from ._kernels.mismatch import LOG_ZERO, threshold_atoms

    if not lam > 0:
        return np.array([LOG_ZERO]), np.array([1.0]), -math.inf, -math.inf
    if method == "gaussian":
        lp, mass = _gauss_atoms(lam, b, mu, s)
        lp = np.maximum(lp, LOG_ZERO)
        m1 = _logsumexp(lp, mass)
        m2 = _logsumexp(2.0 * lp, mass)
        return lp, mass, m1, m2
    if s <= 0:
        from evnoise._kernels.poisson import log_event_probability_exact

        lp = log_event_probability_exact(float(lam), math.expm1(mu), float(b))
        return np.array([max(lp, LOG_ZERO)]), np.array([1.0]), lp, 2.0 * lp
    return threshold_atoms(float(lam), float(b), float(mu), float(s), ATOM_BIN)


def _logsumexp(lp, w):
    top = np.max(lp)
    if not np.isfinite(top):
        return -math.inf
    return float(top + np.log(np.sum(w * np.exp(lp - top))))


class LevelStats:
    """Per-level, per-polarity atoms and moments of ``p`` for one parameter set (internal).

    Attributes ``log_p[k][j]``, ``mass[k][j]`` (atoms), ``log_m1``, ``log_m2`` (arrays
    ``(2, J)``), for polarity ``k`` (0 = ON, 1 = OFF) and level ``j``.
    """

    def __init__(self, lam, params, method):
        lam = np.asarray(lam, dtype=np.float64).ravel()
        n = lam.size
        self.lam = lam
        self.log_p = [[None] * n, [None] * n]
        self.mass = [[None] * n, [None] * n]
        self.log_m1 = np.empty((2, n))
        self.log_m2 = np.empty((2, n))
        if method == "poisson" and params.eps_sigma <= 0 and n:
            self._no_mismatch(lam, params)
            return
        for k, eps in enumerate((params.eps_pos, params.eps_neg)):
            for j in range(n):
                lp, mass, m1, m2 = _atoms(lam[j], params.bias_pr, eps, params.eps_sigma, method)
                self.log_p[k][j] = lp
                self.mass[k][j] = mass
                self.log_m1[k, j] = m1
                self.log_m2[k, j] = m2
        self.trial_rate_hz = params.trial_rate_hz
        self.refractory_s = params.refractory_us * 1e-6

    def _no_mismatch(self, lam, params):
        """Every pixel at the nominal thresholds: one atom per level, all levels in one kernel call."""
        from ._kernels.mismatch import LOG_ZERO, log_probability_serial

        n = lam.size
        pos = lam > 0
        lam2 = np.ascontiguousarray(np.tile(np.where(pos, lam, 1.0), 2))
        c2 = np.repeat([math.expm1(params.eps_pos), math.expm1(params.eps_neg)], n)
        out = np.empty(2 * n)
        log_probability_serial(lam2, c2, np.full(2 * n, float(params.bias_pr)), out)
        lp = np.where(np.tile(pos, 2), out, -math.inf).reshape(2, n)
        self.log_m1[...] = lp
        self.log_m2[...] = 2.0 * lp
        one = np.ones(1)
        for k in range(2):
            for j in range(n):
                self.log_p[k][j] = np.array([max(lp[k, j], LOG_ZERO)])
                self.mass[k][j] = one
        self.trial_rate_hz = params.trial_rate_hz
        self.refractory_s = params.refractory_us * 1e-6

    def dead_factor_mean(self):
        """Dead-time factor of the population mean rate, ``(2, J)``: ``E[nu] = N E[p] * factor``."""
        if self.refractory_s <= 0:
            return np.ones_like(self.log_m1)
        n_r = self.trial_rate_hz * self.refractory_s
        m1 = np.exp(self.log_m1)
        out = np.empty_like(m1)
        for k in range(2):
            other = m1[1 - k]
            for j in range(m1.shape[1]):
                p = np.exp(self.log_p[k][j])
                num = np.sum(self.mass[k][j] * p / (1.0 + n_r * (p + other[j])))
                out[k, j] = num / m1[k, j] if m1[k, j] > 0 else 1.0 / (1.0 + n_r * other[j])
        return out

    def mean_rate(self):
        """Population mean rate, events/s, ``(2, J)``."""
        return self.trial_rate_hz * np.exp(self.log_m1) * self.dead_factor_mean()

    def atom_q(self, k, j):
        """Per-trial event probability ``q`` of each atom (dead time included) and the masses."""
        lp = self.log_p[k][j]
        if self.refractory_s <= 0:
            return lp, self.mass[k][j]
        n_r = self.trial_rate_hz * self.refractory_s
        other = math.exp(self.log_m1[1 - k, j])
        return lp - np.log1p(n_r * (np.exp(lp) + other)), self.mass[k][j]

    def inverse_shape(self, duration_s):
        """Excess dispersion ``1/r`` of the per-pixel count over ``duration_s`` (``(2, J)``, may be < 0).

        ``1/r = (E[p^2] / E[p]^2) (1 - 1/M) - 1`` with ``M = trial_rate_hz * duration_s``: the
        across-pixel variance of ``p`` minus the binomial deficit of a pixel's own count.
        """
        duration_s = np.broadcast_to(np.asarray(duration_s, dtype=np.float64), self.log_m1.shape[1:])
        trials = self.trial_rate_hz * duration_s
        ratio = np.exp(self.log_m2 - 2.0 * self.log_m1)
        return ratio * (1.0 - 1.0 / trials) - 1.0


def level_statistics(lux, params, *, method: str = "poisson") -> LevelStats:
    """Atoms and moments of the per-trial probability at each illuminance (checked)."""
    params = check_params(params)
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    lux = check_lux(lux, ndim=None)
    return LevelStats(params.photons_per_trial(lux.ravel()), params, method)


def threshold_distribution(lam, eps, eps_sigma, bias=0.0, *, method: str = "poisson"):
    """Distribution across pixels of the per-trial event probability at one photon count.

    Parameters
    ----------
    lam : float
        Mean photons per trial (``>= 0``).
    eps : float
        Mean threshold (``> 0``).
    eps_sigma : float
        Threshold mismatch, standard deviation of the normal (truncated to ``eps > 0``), ``>= 0``.
    bias : float
        Photoreceptor bias in photons per trial (``>= 0``).
    method : {"poisson", "gaussian"}
        Exact step-function form or the paper's eq. 3.

    Returns
    -------
    log_p : numpy.ndarray
        Atoms of ``log p`` (``-1e4`` stands for ``p = 0``); exact steps merged into bins
        ``ATOM_BIN`` wide in ``log p`` (mean preserved).
    mass : numpy.ndarray
        Their probabilities (sum 1).
    log_mean, log_mean_sq : float
        Exact ``log E[p]`` and ``log E[p^2]``.
    """
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    vals = {}
    for name, value, zero_ok in (("lam", lam, True), ("eps", eps, False), ("eps_sigma", eps_sigma, True),
                                 ("bias", bias, True)):
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ParameterError(f"{name} must be a number, got {value!r}") from None
        if not math.isfinite(v) or v < 0 or (v == 0 and not zero_ok):
            raise ParameterError(f"{name} must be finite and {'>= 0' if zero_ok else '> 0'}, got {value!r}")
        vals[name] = v
    return _atoms(vals["lam"], vals["bias"], vals["eps"], vals["eps_sigma"], method)


def population_rate(lux, params, *, method: str = "poisson") -> np.ndarray:
    """Mean noise-event rate over a population of pixels, events/s, ``(2, *lux.shape)`` ``[ON, OFF]``.

    Unlike :func:`evnoise.expected_rate` (one pixel at the nominal thresholds), this averages
    over the threshold mismatch ``params.eps_sigma``; the two agree when it is 0.

    Parameters
    ----------
    lux : array_like
        Illuminance in lux (``>= 0``), any shape.
    params : NoiseParams or str
        Parameters or a preset name.
    method : {"poisson", "gaussian"}
        Exact closed form or the paper's eq. 3.
    """
    params = check_params(params)
    lux = check_lux(lux, ndim=None)
    stats = level_statistics(lux.ravel(), params, method=method)
    return stats.mean_rate().reshape(2, *lux.shape)


def nb_shape(lux, params, duration_s: float, *, method: str = "poisson") -> np.ndarray:
    """Negative-binomial shape ``r`` of per-pixel counts over ``duration_s`` seconds, ``(2, *lux.shape)``.

    ``r`` matches the first two moments across pixels (``var = mu + mu^2 / r``) of the count
    of a pixel drawn from the mismatch distribution. ``inf`` where the counts are not
    over-dispersed (no mismatch); the dead time is ignored here.
    """
    params = check_params(params)
    lux = check_lux(lux, ndim=None)
    duration_s = check_positive(duration_s, "duration_s", "seconds")
    stats = level_statistics(lux.ravel(), params, method=method)
    inv = stats.inverse_shape(duration_s)
    with np.errstate(divide="ignore"):
        r = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), np.inf)
    return r.reshape(2, *lux.shape)
