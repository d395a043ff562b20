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
The steps number about ``eps_sigma lam^1.5``; where enumerating them would cost more than a grid of
thresholds (:func:`uses_threshold_grid`: ``lam`` of about 1e5 and more, evk4 above about 1000 lux),
``p`` is bracketed on the grid instead (:func:`evnoise._kernels.mismatch.threshold_atoms_grid`). Both
moments then lie inside rigorous brackets (1e-3 to 2e-2 wide, relative); ``E[p]`` is taken within ~1e-10 by
a smooth (Euler-Maclaurin) form of the steps' double sum where the steps are dense enough
(``eps_sigma (m + bias) >= 30`` counts, which holds where the grid is chosen in practice; else within about
1e-4), ``E[p^2]`` within about 1e-4 (measured against the enumeration), and each pixel's ``p`` is
represented within its grid cell (``eps_sigma / 1024`` wide, the enumeration's own resolution there; the
dead-time factor, an average over these atoms, moves by about 1e-5 between the two representations).
With ``method="gaussian"`` (the paper's eq. 3, smooth in ``eps``) it uses Gauss-Legendre
quadrature on the normal's probability scale (``GAUSS_NODES`` nodes).

Count model of one pixel (thresholds fixed) over ``T`` seconds: ``Binomial(M, q)`` with
``M = trial_rate_hz * T`` trials (a real ``M`` through the gamma function) and
``q = nu / trial_rate_hz``; ``nu`` includes the refractory period as the non-paralyzable
dead time of :func:`evnoise.expected_rate`, with the other polarity at its population mean
(exact for ``refractory_s = 0``; the error is second order in ``nu * refractory_s``).

Background activity and hot pixels (:mod:`evnoise.background`) are averaged over too. A pixel's
spread factor ``s`` (log-normal, mean 1, ``sigma = leak_sigma``) and hot rate ``h`` (0 for a share
``1 - hot_pixel_fraction``; log-normal with mean ``hot_pixel_rate_hz`` and ``sigma = hot_pixel_sigma``
for the others) are independent of its thresholds, so the population is a two-component mixture
(ordinary, hot) over *background nodes* ``(s, h)`` with weights, each node giving the arrival shares
``a_on, a_off`` of :func:`evnoise.background.arrival_shares`. The nodes are a trapezoid rule on the
standard normal of ``log s`` (and ``log h``) over ``[-8, sigma + 8]`` with step
``min(0.5, 0.35 / sigma)`` (:func:`background_nodes`): for these smooth, saturating integrands it
converges geometrically and its relative error on the means is below ``1e-12`` for ``sigma <= 3``
(Gauss-Hermite needs more than 150 nodes for ``1e-10`` at ``sigma = 2``, because ``1 - exp(-c e^{sigma z})``
is far from a polynomial; ``tests/test_background_population.py`` checks both claims against adaptive
quadrature). Hot pixels use the product rule in ``(log s, log h)``.

With ``refractory_s = 0`` the population moments are exact: since ``P_on = p_on (1 - a_on) + a_on (1 - p_off)``
with ``p_on``, ``p_off`` and ``(a_on, a_off)`` independent,

    E[P_on]   = E[p_on] (1 - E[a_on]) + E[a_on] (1 - E[p_off])
    E[P_on^2] = E[p_on^2] E[(1 - a_on)^2] + 2 E[p_on] (1 - E[p_off]) E[a_on (1 - a_on)]
                + E[a_on^2] E[(1 - p_off)^2]

(the same for OFF), which give :func:`population_rate` and :func:`nb_shape`. With dead time the
mean rate is summed over threshold atoms and background nodes with the *other* polarity's
photon-noise probability at its population mean (as without background). The error is second order
in the other polarity's spread: per atom and node, relatively at most
``N R (N R + 1 / (1 - p_other)) Var(p_other)`` (``N R = trial_rate_hz * refractory_s``; from the second
derivative of ``q = P / (1 + N R (P + P_other))`` in ``p_other``), e.g. ``3e-4`` for ``N R = 0.2`` and
``Var(p_other) = 1e-3``. :func:`nb_shape` ignores the dead time (as without background).

With a regular background timer (``leak_regularity > 0``) a pixel's trials are not i.i.d.: the mean
rate is :func:`evnoise.background.regular_rates` averaged over the threshold atoms of each polarity and
the background nodes, with the other polarity's ``p`` at its mean (an approximation also for
``refractory_s = 0``, second order in the other polarity's spread because the timer couples the
polarities; about 1 % at ``eps_sigma = 0.08``, ``eps ~ 0.65``, exact without threshold mismatch), and
:func:`nb_shape` (a binomial count per pixel) raises :class:`ParameterError`.
"""

from __future__ import annotations

import math

import numpy as np

from . import terms
from ._checks import check_lux, check_params, check_positive
from .errors import ParameterError

__all__ = ["threshold_distribution", "population_rate", "nb_shape", "level_statistics", "background_nodes"]

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
    from ._kernels.mismatch import LOG_ZERO, threshold_atoms, threshold_atoms_grid

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
    if uses_threshold_grid(lam, b, mu, s):
        lp, mass, m1, m2, _, _ = threshold_atoms_grid(float(lam), float(b), float(mu), float(s), ATOM_BIN)
        return lp, mass, m1, m2
    return threshold_atoms(float(lam), float(b), float(mu), float(s), ATOM_BIN)


#: The breakpoints are enumerated (exact) unless they are more than this many ...
GRID_MIN_PAIRS = 1e6
#: (which they never are at this many photons per trial or fewer: the enumeration's window holds at most ~1000
#: counts there, 5e5 pairs, even for a mean as small as it keeps, 1e-326, so there is nothing to estimate) ...
ENUMERATE_BELOW = 200.0
#: ... and enumerating them (about ``PAIR_S`` seconds per pair, measured) would cost more than ``GRID_COST_RATIO``
#: times the threshold grid (about ``GRID_POINT_S * sqrt(lam)`` seconds per grid point, measured).
PAIR_S = 50e-9
GRID_POINT_S = 0.15e-6
GRID_COST_RATIO = 1.5


def uses_threshold_grid(lam, bias, eps, eps_sigma) -> bool:
    """Whether the distribution of ``p`` at ``lam`` photons per trial comes from the threshold grid.

    :func:`evnoise._kernels.mismatch.threshold_atoms` enumerates the breakpoints (exact; about ``s lam^1.5`` pairs,
    1e8 .. 1e9 at ``lam ~ 1e5 .. 1e6``); :func:`evnoise._kernels.mismatch.threshold_atoms_grid` brackets ``p`` on
    a grid of thresholds (cost about ``sqrt(lam)`` per grid point). The grid is taken where the enumeration would
    visit more than :data:`GRID_MIN_PAIRS` pairs and cost more than :data:`GRID_COST_RATIO` times the grid, by the
    measured costs :data:`PAIR_S` and :data:`GRID_POINT_S` (about 1000 lux with the ``evk4`` preset); below, the
    results are those of the enumeration, bit for bit. Unchecked (the callers have checked the values).

    Parameters
    ----------
    lam : float
        Mean photons per trial (``> 0``).
    bias : float
        Photoreceptor bias in photons per trial (``>= 0``).
    eps, eps_sigma : float
        Mean threshold and its standard deviation (both ``> 0``).

    Returns
    -------
    bool
        True where :func:`evnoise._kernels.mismatch.threshold_atoms_grid` is used.
    """
    from ._kernels.mismatch import enumeration_size

    if lam <= ENUMERATE_BELOW:
        return False
    pairs, grid = enumeration_size(float(lam), float(bias), float(eps), float(eps_sigma))
    return pairs > GRID_MIN_PAIRS and pairs * PAIR_S > GRID_COST_RATIO * grid * GRID_POINT_S * math.sqrt(lam)


#: Trapezoid step on the standard normal of ``log s`` / ``log h`` is ``min(BG_STEP_MAX, BG_STEP_SIGMA / sigma)``.
BG_STEP_SIGMA = 0.35
BG_STEP_MAX = 0.5
#: The rule covers ``z`` in ``[-BG_Z, sigma + BG_Z]`` (``sigma``: the tilt of a log-normal's mean).
BG_Z = 8.0
#: Product nodes (hot pixels) lighter than this are dropped (their total weight is below ``1e-25``).
BG_MIN_WEIGHT = 1e-30


def _lognormal_rule(sigma: float):
    """Nodes and weights of ``E[g(X)]`` for a log-normal ``X`` of mean 1 and ``sd(log X) = sigma``."""
    if sigma <= 0:
        return np.ones(1), np.ones(1)
    step = min(BG_STEP_MAX, BG_STEP_SIGMA / sigma)
    n = int(math.ceil((sigma + 2.0 * BG_Z) / step))
    z = np.linspace(-BG_Z, sigma + BG_Z, n + 1)
    w = np.exp(-0.5 * z * z)
    w /= w.sum()  # the trapezoid's end weights are ~1e-14 of the peak: plain sums, normalised
    return np.exp(-0.5 * sigma * sigma + sigma * z), w


def background_nodes(params):
    """Background nodes of the pixel population: ``(scale, hot, weight)``, 1-D arrays.

    ``E[g(s, h)]`` over pixels is ``sum(weight * g(scale, hot))`` for the spread factor ``s`` and
    the hot-pixel rate ``h`` (events/s) of :func:`evnoise.draw_background`: ordinary pixels
    (``h = 0``, weight ``1 - hot_pixel_fraction``) on a rule in ``log s``, hot pixels on the
    product rule in ``(log s, log h)`` (module doc). One node ``(1, 0, 1)`` when both are off.
    """
    params = check_params(params)
    s, ws = _lognormal_rule(params.leak_sigma if terms.LEAK.is_on(params) else 0.0)
    f = params.hot_pixel_fraction if params.hot_pixel_rate_hz > 0 else 0.0
    scale, hot, weight = [s], [np.zeros_like(s)], [(1.0 - f) * ws]
    if f > 0:
        h, wh = _lognormal_rule(params.hot_pixel_sigma)
        w2 = f * np.outer(ws, wh)
        keep = w2 >= BG_MIN_WEIGHT * f
        ss, hh = np.meshgrid(s, params.hot_pixel_rate_hz * h, indexing="ij")
        scale.append(ss[keep])
        hot.append(hh[keep])
        weight.append(w2[keep])
    scale, hot, weight = (np.concatenate(v) for v in (scale, hot, weight))
    keep = weight > 0
    return scale[keep], hot[keep], weight[keep]


def _merge_atoms(q, mass):
    """Atoms ``q`` (flat) gathered into bins ``ATOM_BIN`` wide in ``log q`` (mass and mean kept)."""
    from ._kernels.mismatch import LOG_ZERO

    pos = q > 0
    lq = np.full(q.shape, LOG_ZERO)
    lq[pos] = np.log(q[pos])
    keys, inv = np.unique(np.floor(lq / ATOM_BIN), return_inverse=True)
    m = np.bincount(inv, weights=mass, minlength=keys.size)
    mq = np.bincount(inv, weights=mass * q, minlength=keys.size)
    keep = m > 0
    m, mq = m[keep], mq[keep]
    out = np.full(m.shape, LOG_ZERO)
    ok = mq > 0
    out[ok] = np.log(mq[ok] / m[ok])
    return out, m / m.sum()


def _node_mean(weight, values):
    """Weighted sums over background nodes, one per level.

    Parameters
    ----------
    weight : numpy.ndarray
        Node weights, ``(B,)``.
    values : numpy.ndarray
        C-contiguous ``(J, B)``: one row of node values per level.

    Returns
    -------
    numpy.ndarray
        ``sum_b weight[b] * values[j, b]``, ``(J,)``; each row is summed on its own (contiguous,
        numpy's pairwise sum), so a level's result does not depend on the other levels.
    """
    return np.sum(weight[None, :] * values, axis=1)


def _logsumexp(lp, w):
    top = np.max(lp)
    if not np.isfinite(top):
        return -math.inf
    return float(top + np.log(np.sum(w * np.exp(lp - top))))


class LevelStats:
    """Per-level, per-polarity atoms and moments of ``p`` for one parameter set (internal).

    Attributes ``log_p[k][j]``, ``mass[k][j]`` (atoms of the photon-noise probability ``p``),
    ``log_m1``, ``log_m2`` (``log E[p]``, ``log E[p^2]``, arrays ``(2, J)``), for polarity ``k``
    (0 = ON, 1 = OFF) and level ``j``. With background activity (``params.has_background``) also
    ``bg_weight`` (``(B,)``) and ``bg_a`` (``(2, B, J)``, the arrival shares ``a_on, a_off`` at each
    background node, :func:`background_nodes`), and ``log_P1``, ``log_P2`` (``log E[P]``,
    ``log E[P^2]`` of the total per-trial probability ``P``, exact); without it ``bg_weight`` is
    None and ``log_P1``, ``log_P2`` are ``log_m1``, ``log_m2``.
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
        else:
            self._with_mismatch(lam, params, method)
        self._background(lam, params)

    def _with_mismatch(self, lam, params, method):
        n = lam.size
        for k, eps in enumerate((params.eps_pos, params.eps_neg)):
            for j in range(n):
                lp, mass, m1, m2 = _atoms(lam[j], params.bias_pr, eps, params.eps_sigma, method)
                self.log_p[k][j] = lp
                self.mass[k][j] = mass
                self.log_m1[k, j] = m1
                self.log_m2[k, j] = m2
        self.trial_rate_hz = params.trial_rate_hz
        self.refractory_s = params.refractory_us * 1e-6

    def with_background(self, params) -> "LevelStats":
        """These threshold statistics with the background activity of ``params`` (a shallow copy).

        For fits that vary only the background terms: ``params`` must have the same thresholds,
        mismatch, photon scale, trial rate and refractory period as the parameters these
        statistics were made with (not checked); only its background terms are used.
        """
        import copy

        out = copy.copy(self)
        out._background(self.lam, params)
        return out

    def _background(self, lam, params):
        """Background nodes and the exact moments of ``P`` (module doc); nothing when it is off."""
        self.log_P1, self.log_P2 = self.log_m1, self.log_m2
        self.bg_weight = None
        self.bg_a = None
        self.bg_l = None
        self.regularity = 0.0
        if not terms.background_on(params):
            return
        from .background import arrival_shares, lux_of_photons

        scale, hot, weight = background_nodes(params)
        lux = lux_of_photons(lam, params)
        l_on, l_off = terms.intensities(lux[None, :], params, scale[:, None], hot[:, None])
        a_on, a_off = arrival_shares(l_on, l_off, params.trial_rate_hz)
        self.bg_weight = weight
        self.bg_a = np.stack([a_on, a_off])  # (2, B, J)
        self.bg_l = np.stack([l_on, l_off])  # (2, B, J), events/s
        self.regularity = 0.0
        if terms.regular_timer(params):
            from .terms.timer import largest_regularity, pixel_regularity

            # the largest (the timer is on where it is > 0); each node's own in node_regularity
            self.regularity = largest_regularity(params)
            self.node_regularity = np.ascontiguousarray(
                np.broadcast_to(pixel_regularity(params, hot), hot.shape), dtype=np.float64)
        m1, m2 = np.exp(self.log_m1), np.exp(self.log_m2)
        P1 = np.empty_like(m1)
        P2 = np.empty_like(m1)
        for k in range(2):
            # levels as contiguous rows (J, B): each level's sum over the nodes is then the same
            # pairwise sum as for that level alone, so an array of levels equals the scalar calls
            # bit for bit (a sum over axis 0 of (B, J) accumulates in another order for J > 1)
            a = np.ascontiguousarray(self.bg_a[k].T)
            e_a = _node_mean(weight, a)
            e_a2 = _node_mean(weight, a * a)
            e_b2 = _node_mean(weight, (1.0 - a) ** 2)
            e_ab = _node_mean(weight, a * (1.0 - a))
            mo1, mo2 = m1[1 - k], m2[1 - k]
            P1[k] = m1[k] * (1.0 - e_a) + e_a * (1.0 - mo1)
            P2[k] = m2[k] * e_b2 + 2.0 * m1[k] * (1.0 - mo1) * e_ab + e_a2 * (1.0 - 2.0 * mo1 + mo2)
        with np.errstate(divide="ignore"):
            self.log_P1 = np.log(P1)
            self.log_P2 = np.log(P2)

    def _no_mismatch(self, lam, params):
        """Every pixel at the nominal thresholds: one atom per level, all levels in one kernel call."""
        from ._kernels.mismatch import LOG_ZERO
        from ._kernels.poisson import log_event_probability_exact_serial

        n = lam.size
        pos = lam > 0
        lam2 = np.ascontiguousarray(np.tile(np.where(pos, lam, 1.0), 2))
        c2 = np.repeat([math.expm1(params.eps_pos), math.expm1(params.eps_neg)], n)
        out = np.empty(2 * n)
        log_event_probability_exact_serial(lam2, c2, np.full(2 * n, float(params.bias_pr)), out)
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
        if self.bg_weight is None:
            return self.trial_rate_hz * np.exp(self.log_m1) * self.dead_factor_mean()
        if self.regularity > 0:
            return self._regular_mean_rate()
        if self.refractory_s <= 0:
            return self.trial_rate_hz * np.exp(self.log_P1)
        out = np.empty_like(self.log_m1)
        for k in range(2):
            for j in range(out.shape[1]):
                lq, mass, weight = self.atom_q_nodes(k, j)
                out[k, j] = self.trial_rate_hz * float(weight @ (np.exp(lq) @ mass))
        return out

    def _regular_mean_rate(self):
        """Mean rate with a regular background timer (other polarity's ``p`` at its mean; module doc)."""
        from ._kernels.background import regular_mean_rate

        out = np.empty_like(self.log_m1)
        weight = np.ascontiguousarray(self.bg_weight, dtype=np.float64)
        for k in range(2):
            for j in range(out.shape[1]):
                out[k, j] = regular_mean_rate(
                    np.exp(self.log_p[k][j]), np.ascontiguousarray(self.mass[k][j], dtype=np.float64),
                    math.exp(self.log_m1[1 - k, j]), np.ascontiguousarray(self.bg_l[k, :, j]),
                    np.ascontiguousarray(self.bg_l[1 - k, :, j]), weight, self.trial_rate_hz, self.refractory_s,
                    self.node_regularity, k == 0)
        return out

    def _check_not_regular(self, what):
        if self.regularity > 0:
            raise ParameterError(f"{what} needs i.i.d. trials: not available with a regular background "
                                 f"(leak_regularity or hot_pixel_regularity {self.regularity:g} > 0); simulate the "
                                 "counts instead")

    def atom_q_nodes(self, k, j):
        """Per-trial event probabilities of each threshold atom at each background node.

        Returns ``(log_q, mass, weight)``: ``log_q`` ``(B, A)``, ``mass`` ``(A,)`` (threshold atoms
        of polarity ``k`` at level ``j``, sum 1), ``weight`` ``(B,)`` (background nodes, sum 1). A
        pixel's count of polarity ``k`` over ``M`` trials is modelled as the mixture
        ``sum_b weight[b] sum_a mass[a] Binomial(M, exp(log_q[b, a]))``. The other polarity's
        photon-noise probability is at its population mean (exact in the mean; its spread
        enters ``P`` only through ``a (1 - p_other)``), and the dead time as in :meth:`atom_q`.
        Without background ``B = 1``, ``weight = [1]`` and ``log_q[0]`` is :meth:`atom_q`'s.
        ``log_q = -1e4`` stands for ``q = 0``.
        """
        if self.bg_weight is None:
            lq, mass = self.atom_q(k, j)
            return np.asarray(lq)[None, :], mass, np.ones(1)
        self._check_not_regular("a binomial count model")
        from ._kernels.mismatch import LOG_ZERO

        p = np.exp(self.log_p[k][j])[None, :]  # exp(LOG_ZERO) is exactly 0
        mo = math.exp(self.log_m1[1 - k, j])
        a = self.bg_a[k, :, j][:, None]
        ao = self.bg_a[1 - k, :, j][:, None]
        P = p * (1.0 - a) + a * (1.0 - mo)
        if self.refractory_s > 0:
            Po = mo * (1.0 - ao) + ao * (1.0 - p)
            P = P / (1.0 + self.trial_rate_hz * self.refractory_s * (P + Po))
        with np.errstate(divide="ignore"):
            lq = np.where(P > 0, np.log(np.where(P > 0, P, 1.0)), LOG_ZERO)
        return lq, self.mass[k][j], self.bg_weight

    def atom_q(self, k, j):
        """Per-trial event probability ``q`` of each atom (dead time included) and the masses.

        With background activity the atoms are those of :meth:`atom_q_nodes` (threshold atoms
        times background nodes), gathered into bins ``ATOM_BIN`` wide in ``log q`` (mass and mean
        kept), so a likelihood that mixes over atoms mixes over the background too.
        """
        if self.bg_weight is not None:
            lq, mass, weight = self.atom_q_nodes(k, j)
            return _merge_atoms(np.exp(lq).ravel(), np.outer(weight, mass).ravel())
        lp = self.log_p[k][j]
        if self.refractory_s <= 0:
            return lp, self.mass[k][j]
        n_r = self.trial_rate_hz * self.refractory_s
        other = math.exp(self.log_m1[1 - k, j])
        return lp - np.log1p(n_r * (np.exp(lp) + other)), self.mass[k][j]

    def inverse_shape(self, duration_s):
        """Excess dispersion ``1/r`` of the per-pixel count over ``duration_s`` (``(2, J)``, may be < 0).

        ``1/r = (E[P^2] / E[P]^2) (1 - 1/M) - 1`` with ``M = trial_rate_hz * duration_s``: the
        across-pixel variance of ``P`` minus the binomial deficit of a pixel's own count (``P``
        is the photon-noise ``p`` when there is no background activity).
        """
        self._check_not_regular("the NB shape")
        duration_s = np.broadcast_to(np.asarray(duration_s, dtype=np.float64), self.log_m1.shape[1:])
        trials = self.trial_rate_hz * duration_s
        ratio = np.exp(self.log_P2 - 2.0 * self.log_P1)
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
        ``ATOM_BIN`` wide in ``log p`` (mean preserved). Where :func:`uses_threshold_grid` (large
        ``lam``), the cells of a grid of thresholds ``eps_sigma / 1024`` wide, merged the same way.
    mass : numpy.ndarray
        Their probabilities (sum 1).
    log_mean, log_mean_sq : float
        Exact ``log E[p]`` and ``log E[p^2]``; on the grid, ``log E[p]`` within about 1e-10 and
        ``log E[p^2]`` within about 1e-4 (relative; module doc).
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
    over the threshold mismatch ``params.eps_sigma``, the background spread ``leak_sigma`` and
    the hot pixels (module doc); the two agree when all three are 0. Exact for
    ``refractory_s = 0``; with dead time the other polarity is at its mean (module doc).

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
    of a pixel drawn from the population (threshold mismatch, background spread, hot pixels);
    a pixel's own count is ``Binomial(M, P)``, ``M = trial_rate_hz * duration_s``. ``inf`` where
    the counts are not over-dispersed (no mismatch); the dead time is ignored here.

    Parameters
    ----------
    lux : array_like
        Illuminance in lux (``>= 0``), any shape.
    params : NoiseParams or str
        Parameters or a preset name.
    duration_s : float
        Length of the counting window in seconds (``> 0``).
    method : {"poisson", "gaussian"}
        Exact closed form or the paper's eq. 3.

    Returns
    -------
    numpy.ndarray
        float64 array of shape ``(2, *lux.shape)``, ``[ON, OFF]``: the shape ``r``, ``inf`` where the counts
        are not over-dispersed (the Poisson limit, which :func:`evnoise.sample_counts` takes as such).
    """
    params = check_params(params)
    lux = check_lux(lux, ndim=None)
    duration_s = check_positive(duration_s, "duration_s", "seconds")
    stats = level_statistics(lux.ravel(), params, method=method)
    inv = stats.inverse_shape(duration_s)
    with np.errstate(divide="ignore"):
        r = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), np.inf)
    return r.reshape(2, *lux.shape)
