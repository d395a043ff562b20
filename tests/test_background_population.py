"""Population statistics with background activity (leak floor, growth, log-normal spread) and hot pixels.

``expected_rate(mismatch="mean")`` / :func:`evnoise.mismatch.population_rate` and
:func:`evnoise.mismatch.nb_shape` are compared with independent computations:

- the quadrature over the log-normal spread against SciPy's adaptive quadrature;
- the population mean and the across-pixel variance of the per-trial probability against a Monte
  Carlo over drawn pixels (``draw_thresholds``, ``draw_background`` and each pixel's own
  ``expected_rate(..., thresholds=, background=)``), tolerance k standard errors;
- the counts that ``sample_counts`` draws for many pixels (mean and NB shape ``r``, with a
  bootstrap standard error of ``r``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import evnoise as ev
from evnoise import background, mismatch

K = 4.5  # standard errors; several comparisons per test

PARAMS = ev.NoiseParams(eps_pos=0.60, eps_neg=0.70, bias_pr=1.7, trial_rate_hz=40.0, photons_per_lux=10.0,
                        dark_lux=0.05, eps_sigma=0.08, leak_on_hz=0.05, leak_off_hz=0.15, leak_on_hz_per_lux=0.03,
                        leak_off_hz_per_lux=0.01, leak_sigma=0.8, hot_pixel_fraction=0.01, hot_pixel_rate_hz=4.0,
                        hot_pixel_sigma=0.7, hot_pixel_on_fraction=0.3)
LUX = np.array([0.0, 0.3, 2.0, 12.0])


def _pixels(params, lux, n, seed):
    """Per-pixel rates ``(2, n)`` of ``n`` drawn pixels at one illuminance (independent of the closed form)."""
    rng = np.random.default_rng(seed)
    thr = ev.draw_thresholds((1, n), params, rng)
    bg = ev.draw_background((1, n), params, rng)
    return ev.expected_rate(np.full((1, n), lux), params, thresholds=thr, background=bg)[:, 0, :]


@pytest.mark.parametrize("sigma", [0.3, 1.0, 2.0])
@pytest.mark.parametrize("c", [1e-5, 0.05, 1.0, 200.0])
def test_lognormal_rule_is_accurate_to_1e_10(sigma, c):
    from scipy.integrate import quad

    def f(z):
        return -math.expm1(-c * math.exp(-0.5 * sigma * sigma + sigma * z)) * math.exp(-0.5 * z * z)

    edges = [-12.0, -6.0, 0.0, sigma, sigma + 6.0, sigma + 12.0]  # the normal beyond is below 1e-31
    ref = sum(quad(f, a, b, epsabs=0.0, epsrel=1e-13, limit=400)[0] for a, b in zip(edges[:-1], edges[1:]))
    ref /= math.sqrt(2.0 * math.pi)
    s, w = mismatch._lognormal_rule(sigma)
    assert abs(w.sum() - 1.0) < 1e-14 and abs(np.dot(w, s) - 1.0) < 1e-12
    got = float(np.dot(w, -np.expm1(-c * s)))
    assert abs(got / ref - 1.0) < 1e-10, (got, ref)


def test_gauss_hermite_would_not_be_enough_at_sigma_2():
    """Why the rule is a trapezoid: 100 Gauss-Hermite nodes miss 1e-10 (the integrand saturates)."""
    sigma, c = 2.0, 1.0
    x, w = np.polynomial.hermite.hermgauss(100)
    gh = float(np.dot(w, -np.expm1(-c * np.exp(-0.5 * sigma**2 + math.sqrt(2.0) * sigma * x)))) / math.sqrt(math.pi)
    s, ws = mismatch._lognormal_rule(sigma)
    assert abs(gh / float(np.dot(ws, -np.expm1(-c * s))) - 1.0) > 1e-9


def test_background_nodes_mixture_weights():
    s, h, w = mismatch.background_nodes(PARAMS)
    assert abs(w.sum() - 1.0) < 1e-14
    assert abs(np.dot(w, s) - 1.0) < 1e-12
    assert abs(np.dot(w, h) - PARAMS.hot_pixel_fraction * PARAMS.hot_pixel_rate_hz) < 1e-12
    assert abs(w[h > 0].sum() - PARAMS.hot_pixel_fraction) < 1e-14
    s0, h0, w0 = mismatch.background_nodes(dataclasses.replace(PARAMS, leak_sigma=0.0, hot_pixel_fraction=0.0))
    assert s0.tolist() == [1.0] and h0.tolist() == [0.0] and w0.tolist() == [1.0]


@pytest.mark.parametrize("j", range(len(LUX)))
@pytest.mark.long
def test_population_mean_and_variance_match_monte_carlo_refractory_0(j):
    """Exact with refractory 0: mean rate and across-pixel variance of P against drawn pixels."""
    n = 200_000
    rates = _pixels(PARAMS, LUX[j], n, seed=11 + j)
    exact = ev.expected_rate(LUX[j:j + 1], PARAMS, mismatch="mean")[:, 0]
    mc, se = rates.mean(axis=1), rates.std(axis=1, ddof=1) / math.sqrt(n)
    assert np.all(np.abs(exact - mc) < K * se), (exact, mc, se)
    # across-pixel variance of P = rate / N: E[P^2] - E[P]^2 from the exact moments (nb_shape's input)
    stats = mismatch.level_statistics(LUX[j:j + 1], PARAMS)
    var_formula = np.exp(stats.log_P2[:, 0]) - np.exp(2.0 * stats.log_P1[:, 0])
    p = rates / PARAMS.trial_rate_hz
    dev2 = (p - p.mean(axis=1, keepdims=True)) ** 2
    var_mc, var_se = dev2.mean(axis=1), dev2.std(axis=1, ddof=1) / math.sqrt(n)
    assert np.all(np.abs(var_formula - var_mc) < K * var_se), (var_formula, var_mc, var_se)


def test_without_background_terms_nothing_changes():
    off = dataclasses.replace(PARAMS, leak_on_hz=0.0, leak_off_hz=0.0, leak_on_hz_per_lux=0.0, leak_off_hz_per_lux=0.0,
                              hot_pixel_rate_hz=0.0)
    plain = dataclasses.replace(off, leak_sigma=0.0, hot_pixel_fraction=0.0, hot_pixel_sigma=0.0)
    np.testing.assert_array_equal(mismatch.population_rate(LUX, off), mismatch.population_rate(LUX, plain))
    np.testing.assert_array_equal(mismatch.nb_shape(LUX, off, 1.0), mismatch.nb_shape(LUX, plain, 1.0))


def test_nominal_population_without_mismatch_is_expected_rate():
    """No spread of any kind: the population is the nominal pixel (leak floor included)."""
    params = dataclasses.replace(PARAMS, eps_sigma=0.0, leak_sigma=0.0, hot_pixel_fraction=0.0, refractory_s=0.002)
    np.testing.assert_allclose(ev.expected_rate(LUX, params, mismatch="mean"), ev.expected_rate(LUX, params),
                               rtol=1e-12, atol=0)


@pytest.mark.parametrize("lux", [0.3, 2.0])
def test_population_mean_with_dead_time(lux):
    """Refractory > 0: the other polarity at its mean per background node.

    The approximation error is second order in the other polarity's spread, relatively at most
    ``N R (N R + 1 / (1 - p_other)) Var(p_other)`` (module doc of :mod:`evnoise.mismatch`); here
    ``N R = 0.2``, ``Var(p_other) <= 1.1e-3`` and ``p_other < 0.15``, so below ``3.1e-4``: the tolerance is
    ``K`` standard errors plus ``4e-4`` of the value.
    """
    params = dataclasses.replace(PARAMS, refractory_s=0.005)
    n = 200_000
    rates = _pixels(params, lux, n, seed=5)
    approx = ev.expected_rate(np.array([lux]), params, mismatch="mean")[:, 0]
    mc, se = rates.mean(axis=1), rates.std(axis=1, ddof=1) / math.sqrt(n)
    assert np.all(np.abs(approx - mc) < K * se + 4e-4 * approx), (approx, mc, se)
    # the dead time matters at this precision (the test can tell)
    no_dead = ev.expected_rate(np.array([lux]), PARAMS, mismatch="mean")[:, 0]
    assert np.all(np.abs(no_dead - mc) > 6 * se)


def test_atom_q_nodes_reproduce_the_moments():
    stats = mismatch.level_statistics(LUX, PARAMS)
    for k in range(2):
        for j in range(LUX.size):
            lq, mass, weight = stats.atom_q_nodes(k, j)
            q = np.exp(lq)
            assert lq.shape == (weight.size, mass.size)
            # E[P] = E[p] (1 - E[a]) + E[a] (1 - E[p_other]), with E[p] the atoms' own mean (the threshold
            # atoms' mean can differ from the exact log_m1 by ~1e-5 relative where p is tiny: pairs dropped)
            e_p = float(np.dot(mass, np.exp(stats.log_p[k][j])))
            e_a = float(np.dot(stats.bg_weight, stats.bg_a[k, :, j]))
            expect = e_p * (1.0 - e_a) + e_a * (1.0 - math.exp(stats.log_m1[1 - k, j]))
            np.testing.assert_allclose(weight @ q @ mass, expect, rtol=1e-12)
            np.testing.assert_allclose(expect, math.exp(stats.log_P1[k, j]), rtol=1e-4)
            lq2, m2 = stats.atom_q(k, j)  # merged mixture: mass and mean kept
            np.testing.assert_allclose(m2.sum(), 1.0, rtol=1e-14)
            np.testing.assert_allclose(np.dot(m2, np.exp(lq2)), expect, rtol=1e-12)


@pytest.mark.parametrize("lux", [0.0, 2.0])
def test_sample_counts_give_the_predicted_mean_and_nb_shape(lux):
    """Counts over 1 s of many simulated pixels (the simulator draws its own thresholds and background)."""
    shape, duration_s = (250, 400), 1.0
    counts = ev.sample_counts(np.full(shape, lux), PARAMS, duration_s, rng=2024).reshape(2, -1).astype(np.float64)
    n = counts.shape[1]
    mu = ev.expected_rate(np.array([lux]), PARAMS, mismatch="mean")[:, 0] * duration_s
    r = mismatch.nb_shape(np.array([lux]), PARAMS, duration_s)[:, 0]
    mean, sd = counts.mean(axis=1), counts.std(axis=1, ddof=1)
    assert np.all(np.abs(mean - mu) < K * sd / math.sqrt(n)), (mean, mu)

    def r_hat(c):
        m, v = c.mean(axis=-1), c.var(axis=-1, ddof=1)
        return m * m / (v - m)

    rng = np.random.default_rng(3)
    boot = np.array([r_hat(counts[:, rng.integers(0, n, n)]) for _ in range(60)])
    r_se = boot.std(axis=0, ddof=1)
    est = r_hat(counts)
    assert np.all(np.abs(est - r) < K * r_se), (est, r, r_se)


def test_with_background_reuses_threshold_statistics():
    """``LevelStats.with_background`` (used by fits that vary only the background) equals a fresh computation."""
    plain = dataclasses.replace(PARAMS, leak_on_hz=0.0, leak_off_hz=0.0, leak_on_hz_per_lux=0.0,
                                leak_off_hz_per_lux=0.0, hot_pixel_rate_hz=0.0)
    base = mismatch.level_statistics(LUX, plain)
    swapped = base.with_background(PARAMS)
    fresh = mismatch.level_statistics(LUX, PARAMS)
    np.testing.assert_array_equal(swapped.mean_rate(), fresh.mean_rate())
    np.testing.assert_array_equal(swapped.inverse_shape(1.0), fresh.inverse_shape(1.0))
    assert base.bg_weight is None  # the original is untouched
    np.testing.assert_array_equal(base.mean_rate(), mismatch.population_rate(LUX, plain))


@pytest.mark.parametrize("lux", [0.0, 2.0])
def test_regular_background_mean_matches_monte_carlo(lux):
    """``leak_regularity > 0``: the mean over background nodes of the regular-timer rates.

    Without threshold mismatch the average is exact (only the background spread and the hot pixels
    vary), so the tolerance is K standard errors; the NB shape (binomial per pixel) is refused.
    """
    params = dataclasses.replace(PARAMS, eps_sigma=0.0, leak_regularity=0.7, refractory_s=0.002)
    n = 200_000
    rates = _pixels(params, lux, n, seed=21)
    mean = ev.expected_rate(np.array([lux]), params, mismatch="mean")[:, 0]
    mc, se = rates.mean(axis=1), rates.std(axis=1, ddof=1) / math.sqrt(n)
    assert np.all(np.abs(mean - mc) < K * se), (mean, mc, se)
    poisson_bg = ev.expected_rate(np.array([lux]), dataclasses.replace(params, leak_regularity=0.0), mismatch="mean")
    assert np.any(np.abs(poisson_bg[:, 0] - mc) > 6 * se)  # the timer matters at this precision
    with pytest.raises(ev.ParameterError, match="regular background"):
        mismatch.nb_shape(np.array([lux]), params, 1.0)


@pytest.mark.parametrize("leak_regularity, hot_regularity", [(0.7, 0.0), (0.0, 0.9)])
def test_hot_pixels_own_regularity_mean_matches_monte_carlo(leak_regularity, hot_regularity):
    """Hot pixels with a regularity of their own (``hot_pixel_regularity``): each background node its own timer."""
    params = dataclasses.replace(PARAMS, eps_sigma=0.0, leak_regularity=leak_regularity, refractory_s=0.002,
                                 hot_pixel_fraction=0.2, hot_pixel_regularity=hot_regularity)
    n = 200_000
    rates = _pixels(params, 2.0, n, seed=5)
    mean = ev.expected_rate(np.array([2.0]), params, mismatch="mean")[:, 0]
    mc, se = rates.mean(axis=1), rates.std(axis=1, ddof=1) / math.sqrt(n)
    assert np.all(np.abs(mean - mc) < K * se), (mean, mc, se)
    tied = ev.expected_rate(np.array([2.0]), dataclasses.replace(params, hot_pixel_regularity=-1.0), mismatch="mean")
    assert np.any(np.abs(tied[:, 0] - mc) > 6 * se)  # the hot pixels' own timer matters at this precision


def test_regular_background_with_mismatch_is_approximate_to_about_1_percent():
    """With threshold mismatch too, the other polarity at its mean: measured error ~1 % (OFF at 2 lux, 7 sigma
    with 400k pixels); the tolerance is K standard errors plus 2 % of the value."""
    params = dataclasses.replace(PARAMS, leak_regularity=0.7, refractory_s=0.002)
    n = 200_000
    rates = _pixels(params, 2.0, n, seed=3)
    mean = ev.expected_rate(np.array([2.0]), params, mismatch="mean")[:, 0]
    mc, se = rates.mean(axis=1), rates.std(axis=1, ddof=1) / math.sqrt(n)
    assert np.all(np.abs(mean - mc) < K * se + 0.02 * mean), (mean, mc, se)


def test_dispersion_evk3_script_runs_on_the_reference_tables():
    """Smoke test of calibration/scripts/dispersion_evk3 (coarse grey step, one model); skipped without the tables."""
    from pathlib import Path

    from evnoise.calibration.scripts import dispersion_evk3
    from evnoise.calibration.scripts.refit_evk3 import DEFAULT_REFERENCE

    if not (Path(DEFAULT_REFERENCE) / "synthetic_param.npz").is_file():
        pytest.skip(f"reference tables not found in {DEFAULT_REFERENCE}")
    s = dispersion_evk3.run(DEFAULT_REFERENCE, None, step=32, models=("mismatch",))
    assert [e["fitted_to"] for e in s["models"]] == ["log r only", "log r and log mean rate (equal weights)"]
    for e in s["models"]:
        assert 0 < e["r_rms_log_ratio"] < 5 and set(e["r_rms_log_ratio_by_region"]) == set(dispersion_evk3.REGIONS)
    # the joint fit trades r for the mean curve
    assert s["models"][1]["r_rms_log_ratio"] >= s["models"][0]["r_rms_log_ratio"] - 1e-9
    assert "r(grey)" in s["verdict"]


@pytest.mark.parametrize("regularity, refractory_s", [(0.7, 0.002), (1.0, 0.0), (1e-6, 0.0005)])
def test_regular_mean_rate_kernel_matches_the_broadcast_formula(regularity, refractory_s):
    """The fused kernel of the population mean against ``regular_rates`` on the whole (node, atom) grid, for
    both polarities, including atoms with p = 0, p = 1 and p_own + p_other > 1 (clipped), nodes without
    background and intensities so small that the timer's geometric rest has a2 below the float epsilon."""
    from evnoise._kernels.background import regular_mean_rate

    rng = np.random.default_rng(5)
    p_own = np.concatenate([[0.0, 1.0, 0.95, 0.8, 1e-300], 10.0 ** rng.uniform(-12, -0.3, 60)])
    mass = rng.random(p_own.size)
    mass /= mass.sum()
    l_own = np.concatenate([[0.0, 0.0, 1e-8, 1e4, 1e-300, 1e-20], 10.0 ** rng.uniform(-4, 2, 40)])
    l_other = np.concatenate([[0.0, 0.5, 0.0, 1e3, 0.0, 1e-20], 10.0 ** rng.uniform(-4, 2, 40)])
    weight = rng.random(l_own.size)
    weight /= weight.sum()
    n = 40.0
    # each node its own regularity (hot pixels with one of their own): every third node Poisson
    node_reg = np.where(np.arange(l_own.size) % 3 == 0, 0.0, regularity)
    regularity = node_reg[:, None]
    for p_other in (0.0, 0.02, 0.3):
        po = np.full((1, p_own.size), p_other)
        for own_is_on in (True, False):
            got = regular_mean_rate(p_own, mass, p_other, l_own, l_other, weight, n, refractory_s, node_reg,
                                    own_is_on)
            if own_is_on:
                nu = background.regular_rates(p_own[None, :], po, l_own[:, None], l_other[:, None], n, refractory_s,
                                              regularity)[0]
            else:
                nu = background.regular_rates(po, p_own[None, :], l_other[:, None], l_own[:, None], n, refractory_s,
                                              regularity)[1]
            assert np.all(np.isfinite(nu)) and np.all(nu >= 0)
            assert got == pytest.approx(float(weight @ (nu @ mass)), rel=1e-12, abs=1e-300), (p_other, own_is_on)


def test_regular_mean_rate_with_a_subnormal_p():
    """An atom whose p is subnormal (below 1 / DBL_MAX: 1 / p overflows) has the rate of a pixel without photon
    noise, the timer's alone (it came out 0), and p = 1e-300 the same to rounding; without background N p."""
    from evnoise._kernels.background import regular_mean_rate

    def rate(p, l_own=0.5):
        return regular_mean_rate(np.array([p]), np.ones(1), 0.0, np.array([l_own]), np.zeros(1), np.ones(1), 1e4, 1e-3,
                                 np.array([0.5]), True)

    timer_alone = rate(0.0)
    assert timer_alone == pytest.approx(0.5 / (1.0 + 0.5e-3), rel=1e-3)  # the background's rate, less its dead time
    for p in (1e-310, 5e-324, 1e-300):
        assert rate(p) == pytest.approx(timer_alone, rel=1e-12), p
    assert rate(1e-310, l_own=0.0) == pytest.approx(1e4 * 1e-310, rel=1e-12)


def test_regular_rates_at_the_smallest_intensities():
    """A background of 1e-300 events/s beside photon noise as rare as p = 1e-300: the timer's
    ``1 - q (1 - a2)`` is below the float epsilon (computed as 1 - q (1 - a2) it rounds to 0, and the rate
    came out 0); the rate is the photon-noise one ``N p / (1 + N p R)``, or the background's alone at p = 0."""
    n, r_s, l_bg = 40.0, 0.002, 1e-300
    for p in (1e-300, 1e-3):
        on, off = background.regular_rates(p, 0.0, l_bg, 0.0, n, r_s, 0.8)
        assert off == 0.0 and float(on) == pytest.approx(n * p / (1 + n * p * r_s), rel=1e-9, abs=0.0)
    on, off = background.regular_rates(0.0, 0.0, l_bg, 0.0, n, r_s, 0.8)
    assert off == 0.0 and float(on) == pytest.approx(l_bg, rel=1e-9, abs=0.0)
