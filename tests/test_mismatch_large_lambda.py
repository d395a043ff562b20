"""Issue 33: the population statistics over threshold mismatch at large photon counts (the threshold grid).

Every grid result is compared with an independent computation: the enumeration of the breakpoints
(``threshold_atoms``, exact in ``E[p]``), the plain double sum (``mean_probability_double_sum``), the windowed
exact sum of the closed form, and SciPy for the normal's log cdf.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import evnoise as ev
from evnoise._kernels.mismatch import (
    GRID_PER_SIGMA,
    log_ndtr,
    log_p_thresholds,
    mean_probability_double_sum,
    mean_probability_smooth,
    threshold_atoms,
    threshold_atoms_grid,
)
from evnoise._kernels.poisson import log_event_probability_exact
from evnoise.mismatch import ATOM_BIN, threshold_distribution, uses_threshold_grid

# (lam, bias, mu, s): evk4-like; tiny s; s large enough that the truncation at eps = 0 matters; no bias; a
# large bias; E[p] tiny in log space (about e^-560)
HARD = [
    (3.0e4, 187.3, 0.12, 0.005),
    (3.0e4, 187.3, 0.12, 0.0005),
    (1.0e4, 187.3, 0.05, 0.03),
    (2.0e4, 0.0, 0.2, 0.02),
    (2.0e4, 1.0e4, 0.2, 0.02),
    (1.0e4, 187.3, 0.5, 0.005),
]


def test_log_ndtr_matches_scipy():
    special = pytest.importorskip("scipy.special")
    z = np.concatenate([np.linspace(-80.0, 12.0, 2001), [-37.0, -36.999, -37.001, 0.0, -1e-300, 1e-300]])
    got = np.array([log_ndtr(float(v)) for v in z])
    want = special.log_ndtr(z)
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-300)


@pytest.mark.parametrize("lam", [2.0e3, 6.4e4, 6.4e5])
def test_table_sums_match_the_windowed_exact_sum(lam):
    """``log p`` on a grid of thresholds from shared tables equals the closed form's own windowed sum."""
    eps = np.concatenate([[0.0], np.linspace(1e-6, 0.2, 197), [0.05 + 1e-12]])
    eps.sort()
    out = np.empty(eps.size)
    n_exact = log_p_thresholds(lam, 187.3, eps, out)
    want = np.array([log_event_probability_exact(lam, math.expm1(e), 187.3) for e in eps])
    assert n_exact == 0  # the tables reached every threshold
    assert np.all(np.isfinite(out)) and np.all(np.diff(out) <= 1e-12 * np.abs(out[1:]))  # non-increasing
    np.testing.assert_allclose(out, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("lam, b, mu, s", HARD)
@pytest.mark.long
def test_grid_brackets_hold_the_enumerated_moments(lam, b, mu, s):
    lp_e, mass_e, m1_e, m2_e = threshold_atoms(lam, b, mu, s, ATOM_BIN)
    lp, mass, m1, m2, info, n_grid = threshold_atoms_grid(lam, b, mu, s, ATOM_BIN)
    lo1, hi1, lo2, hi2, m1_grid, m1_smooth = info
    assert -700.0 < m1_e  # the enumeration's exact branch (not its early return far below the smallest double)
    # rigorous: the enumerated (exact) moments lie inside the grid's brackets, and so do the estimates
    assert lo1 <= m1_e <= hi1 and lo2 <= m2_e <= hi2
    assert lo1 <= m1 <= hi1 and lo2 <= m2 <= hi2
    assert hi1 - lo1 < 0.05 and hi2 - lo2 < 0.05
    # the estimates: E[p] by the smooth double sum where it applies, E[p^2] by the grid
    if math.isfinite(m1_smooth):
        assert m1 == m1_smooth
        assert abs(math.expm1(m1 - m1_e)) < 1e-10
    else:
        assert m1 == m1_grid
        assert abs(math.expm1(m1 - m1_e)) < 2e-4
    assert abs(math.expm1(m2 - m2_e)) < 3e-4
    assert abs(math.expm1(m1_grid - m1_e)) < 2e-4
    # atoms: masses sum to 1, log p decreasing, p <= 1
    assert mass.sum() == pytest.approx(1.0, abs=1e-12) and np.all(mass > 0)
    assert np.all(np.diff(lp) < 0) and lp[0] <= 0.0
    assert n_grid <= (9.0 + mu / s) * GRID_PER_SIGMA + 2


def test_atoms_keep_the_mean_and_match_the_enumerated_distribution():
    lam, b, mu, s = 3.0e4, 187.3, 0.12, 0.005
    lp_e, mass_e, m1_e, _ = threshold_atoms(lam, b, mu, s, ATOM_BIN)
    lp, mass, m1, _, _, _ = threshold_atoms_grid(lam, b, mu, s, ATOM_BIN)
    assert float(np.sum(mass * np.exp(lp - m1))) == pytest.approx(1.0, rel=1e-9)
    # the two distributions of log p agree up to the resolution of a cell (both are s / 1024 wide in eps):
    # the quantiles of log p over the pixels, where the mass is, differ by less than one cell's change of log p
    q = np.array([1e-12, 1e-9, 1e-6, 1e-3, 0.01, 0.1, 0.5, 0.9, 0.99, 1 - 1e-6])

    def quantiles(lp_, mass_):
        order = np.argsort(-lp_)  # decreasing p: cumulative mass from the lowest thresholds
        cum = np.cumsum(mass_[order])
        return lp_[order][np.minimum(np.searchsorted(cum, q), lp_.size - 1)]

    slope = abs(np.diff(np.array([log_event_probability_exact(lam, math.expm1(mu + d), b) for d in (0.0, s)]))[0] / s)
    cell = slope * s / GRID_PER_SIGMA
    # the enumeration drops pairs below exp(-50) of the mean, so where p itself is that small its atoms are too
    # small (down to p = 0): compare where the enumerated p is well above that
    keep = quantiles(lp_e, mass_e) > m1_e - 30.0
    assert keep.sum() >= 4
    np.testing.assert_allclose(quantiles(lp, mass)[keep], quantiles(lp_e, mass_e)[keep], atol=3 * cell + 2 * ATOM_BIN)


@pytest.mark.parametrize("lam, b, mu, s", [(3.0e3, 187.3, 0.3, 0.03), (4.0e3, 187.3, 0.05, 0.03),
                                           (2.5e3, 20.0, 0.2, 0.05)])
def test_smooth_mean_matches_the_plain_double_sum(lam, b, mu, s):
    """The Euler-Maclaurin form against the plain double sum (linear arithmetic; truncation at 0 matters in the
    second and third cases, where the correction at j = 0 is needed)."""
    n_max = int(lam + 40 * math.sqrt(lam))
    want = mean_probability_double_sum(lam, b, mu, s, n_max)
    got = mean_probability_smooth(lam, b, mu, s, mu - 2 * s if mu > 2 * s else 0.5 * mu)
    assert math.isfinite(got) and want > 1e-250
    assert abs(math.expm1(got - math.log(want))) < 1e-10


def test_smooth_mean_declines_coarse_steps():
    """Steps too coarse for a smooth form (tiny s at modest lam): NaN, and the grid keeps its own estimate."""
    assert math.isnan(mean_probability_smooth(3.0e3, 187.3, 0.12, 0.0005, 0.12))


def test_switch_over_keeps_the_enumeration_bit_for_bit():
    params = ev.load_preset("evk4")
    for lux, grid in ((30.0, False), (300.0, False), (10000.0, True)):
        lam = float(params.photons_per_trial(np.array([lux]))[0])
        for eps in (params.eps_pos, params.eps_neg):
            assert uses_threshold_grid(lam, params.bias_pr, eps, params.eps_sigma) is grid
    lam = float(params.photons_per_trial(np.array([300.0]))[0])
    got = threshold_distribution(lam, params.eps_pos, params.eps_sigma, params.bias_pr)
    want = threshold_atoms(lam, params.bias_pr, params.eps_pos, params.eps_sigma, ATOM_BIN)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)


@pytest.mark.long
def test_evk4_mean_rate_at_10000_lux_with_a_bounded_grid():
    """evk4 at 10,000 lux (lam ~ 6.4e5: about 1e9 breakpoints, minutes to enumerate) takes the grid; the number of
    p evaluations is bounded by the grid's span, and the rate is the nominal pixel's (p ~ e^-258 and below
    everywhere that matters, so only the background counts, in both computations)."""
    params = ev.load_preset("evk4")
    lux = np.array([10000.0])
    lam = float(params.photons_per_trial(lux)[0])
    rate = ev.expected_rate(lux, params, mismatch="mean")
    nominal = ev.expected_rate(lux, params)
    assert np.all(np.isfinite(rate)) and np.all(rate > 0)
    np.testing.assert_allclose(rate, nominal, rtol=1e-12)
    for eps in (params.eps_pos, params.eps_neg):
        _, _, m1, m2, info, n_grid = threshold_atoms_grid(lam, params.bias_pr, eps, params.eps_sigma, ATOM_BIN)
        assert n_grid <= (9.0 + eps / params.eps_sigma) * GRID_PER_SIGMA + 2
        assert -300.0 < m1 < -200.0 and info[0] <= m1 <= info[1] and info[2] <= m2 <= info[3]
        assert math.isfinite(info[5])  # E[p] from the smooth double sum


@pytest.mark.parametrize("refractory_s", [0.0, 1e-4])
@pytest.mark.long
def test_population_rate_and_nb_shape_on_the_grid_match_the_enumeration(monkeypatch, refractory_s):
    """A level where the grid is chosen for ON only (lam = 6.4e4) against the enumeration forced everywhere.

    Without dead time the mean rate is ``trial_rate E[p]`` (E[p] to 1e-10); with it the atoms enter the dead-time
    factor (both sets of atoms represent each pixel's p to the resolution of s / 1024 in eps: they agree to ~1e-5).
    The NB shape follows E[p^2] (1e-4)."""
    from evnoise import mismatch

    params = ev.NoiseParams(eps_pos=0.3, eps_neg=0.25, bias_pr=187.3, trial_rate_hz=1000.0, photons_per_lux=64.0,
                            eps_sigma=0.03, refractory_s=refractory_s)
    lux = np.array([1000.0, 2.0])
    lam = params.photons_per_trial(lux)
    assert uses_threshold_grid(lam[0], params.bias_pr, params.eps_pos, params.eps_sigma)
    assert not uses_threshold_grid(lam[0], params.bias_pr, params.eps_neg, params.eps_sigma)
    rate = ev.expected_rate(lux, params, mismatch="mean")
    shape = mismatch.nb_shape(lux, params, 10.0)
    monkeypatch.setattr(mismatch, "uses_threshold_grid", lambda *args: False)
    rate_e = ev.expected_rate(lux, params, mismatch="mean")
    shape_e = mismatch.nb_shape(lux, params, 10.0)
    np.testing.assert_array_equal(rate[1], rate_e[1])  # OFF: enumerated in both
    np.testing.assert_array_equal(rate[:, 1], rate_e[:, 1])  # the dim level: enumerated in both
    np.testing.assert_allclose(rate[0, 0], rate_e[0, 0], rtol=1e-10 if refractory_s == 0 else 3e-5)
    np.testing.assert_allclose(shape, shape_e, rtol=1e-4)
