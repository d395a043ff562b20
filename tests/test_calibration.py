"""Tests of evnoise.calibration: exact mismatch statistics, parameter recovery, inputs, CLI, presets.

Statistical checks use fixed seeds and tolerances of k standard errors computed in the test.
Recovery: a parameter estimate is a z-score ``(log est - log true) / rel_error``; with m
identified parameters per fit and S fits, each |z| must stay below the two-sided Bonferroni
bound for a 1 % family-wise false-alarm rate, ``k = Phi^-1(1 - 0.005 / (m S))`` (about 3.2 for
one fit of 7 parameters, 3.6 for four), and the sum of z^2 over identified parameters must lie
in the central 99.9 % of a chi-square with m degrees of freedom -- so reported uncertainties
that are far too large fail as well as ones that are too small.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from evnoise import calibration as cal
from evnoise.cli import main

#: The sensors simulated here have no background floors, and the floors have their own tests
#: (test_calibration_background.py): holding them at 0 keeps these core-recovery fits as fast as before.
NO_FLOORS = {"leak_on_hz": 0.0, "leak_off_hz": 0.0}

REFERENCE = Path(os.environ.get("EVNOISE_N2I_REFERENCE", "/work/shared/data/noise2image-reference"))
needs_reference = pytest.mark.skipif(
    not (REFERENCE / "lux_measurement.npz").is_file() or not (REFERENCE / "synthetic_param.npz").is_file(),
    reason=f"Noise2Image reference tables not found in {REFERENCE} (set EVNOISE_N2I_REFERENCE)",
)


def _bonferroni_k(n_tests: int, alpha: float = 0.01) -> float:
    from scipy.stats import norm

    return float(norm.isf(alpha / (2 * n_tests)))


def _truncated_normal(rng, mu, s, n):
    out = rng.normal(mu, s, size=2 * n + 100)
    out = out[out > 0][:n]
    assert out.size == n
    return out


# --------------------------------------------------------------------------------------
# the exact distribution of p across pixels
# --------------------------------------------------------------------------------------
CASES = [(0.2, 1.7, 0.9, 0.05), (0.2, 1.7, 0.9, 0.3), (2.0, 1.7, 1.0, 0.3), (18.0, 1.7, 1.0, 0.02),
         (5.0, 0.0, 0.5, 0.1), (40.0, 3.0, 0.3, 0.08)]


@pytest.mark.parametrize("lam,b,mu,s", CASES)
def test_mean_matches_plain_double_sum(lam, b, mu, s):
    from evnoise._kernels.mismatch import mean_probability_double_sum

    lp, mass, log_m1, _ = cal.threshold_distribution(lam, mu, s, b)
    ref = mean_probability_double_sum(lam, b, mu, s, lam + 15 * math.sqrt(lam) + 30)
    assert math.exp(log_m1) == pytest.approx(ref, rel=1e-11)
    assert mass.sum() == pytest.approx(1.0, rel=1e-12)
    # merged atoms keep the mean exactly
    assert float(np.sum(mass * np.exp(lp))) == pytest.approx(ref, rel=1e-11)


@pytest.mark.parametrize("lam,b,mu,s", CASES[1:4] + [(300.0, 2.0, 0.15, 0.05)])
def test_moments_match_monte_carlo_over_thresholds(lam, b, mu, s):
    """E[p], E[p^2] against thresholds drawn at random and evnoise's exact p (independent route)."""
    rng = np.random.default_rng(12)
    eps = _truncated_normal(rng, mu, s, 20000)
    p = ev.event_probability(lam, eps, b)
    _, _, log_m1, log_m2 = cal.threshold_distribution(lam, mu, s, b)
    for values, log_m in ((p, log_m1), (p**2, log_m2)):
        se = values.std(ddof=1) / math.sqrt(values.size)
        assert abs(values.mean() - math.exp(log_m)) < 4.5 * se + 1e-15


def test_small_mismatch_limit_is_the_exact_probability():
    lam, b, mu = 3.0, 1.2, 0.7
    exact = float(ev.event_probability(lam, mu, b))
    _, _, log_m1, log_m2 = cal.threshold_distribution(lam, mu, 1e-7, b)
    assert math.exp(log_m1) == pytest.approx(exact, rel=1e-9)
    assert math.exp(log_m2) == pytest.approx(exact**2, rel=1e-9)


def test_population_rate_without_mismatch_is_expected_rate():
    params = ev.NoiseParams(eps_pos=0.6, eps_neg=0.8, bias_pr=1.0, trial_rate_hz=50.0, photons_per_lux=3.0,
                            dark_lux=0.05, refractory_s=2e-3)
    lux = np.array([0.0, 0.1, 1.0, 10.0])
    np.testing.assert_allclose(cal.population_rate(lux, params), ev.expected_rate(lux, params), rtol=1e-12)


def test_nb_shape_matches_simulated_pixels():
    """Moment NB shape of simulated counts (thresholds drawn per pixel) vs the closed form."""
    params = ev.NoiseParams(eps_pos=0.6, eps_neg=0.8, bias_pr=1.0, trial_rate_hz=50.0, photons_per_lux=3.0,
                            dark_lux=0.05, eps_sigma=0.1)
    lux, dur = 1.5, 4.0
    rng = np.random.default_rng(5)
    counts = ev.sample_counts(np.full((100, 100), lux), params, dur, rng).reshape(2, -1)
    model_inv = 1.0 / cal.nb_shape(np.array([lux]), params, dur)[:, 0]
    mean_model = cal.population_rate(np.array([lux]), params)[:, 0] * dur

    def inv_shape(c):
        m = c.mean(axis=-1)
        return (c.var(axis=-1, ddof=1) - m) / m**2

    obs = inv_shape(counts)
    boot = np.array([inv_shape(counts[:, rng.integers(0, counts.shape[1], counts.shape[1])]) for _ in range(200)])
    se = boot.std(axis=0, ddof=1)
    assert np.all(np.abs(obs - model_inv) < 4.0 * se), (obs, model_inv, se)
    se_mean = counts.std(axis=-1, ddof=1) / math.sqrt(counts.shape[1])
    assert np.all(np.abs(counts.mean(axis=-1) - mean_model) < 4.0 * se_mean)


# --------------------------------------------------------------------------------------
# parameter recovery from simulated flat fields
# --------------------------------------------------------------------------------------
LUX_LEVELS = np.array([0.0, 0.1, 0.3, 0.8, 2.0, 5.0, 12.0])


def _random_params(seed: int) -> ev.NoiseParams:
    """Plausible parameters: peak near the middle of LUX_LEVELS, measurable rates."""
    r = np.random.default_rng(seed)
    bias = float(np.exp(r.uniform(np.log(0.8), np.log(3.0))))
    ppl = float(np.exp(r.uniform(np.log(1.0), np.log(4.0))))
    return ev.NoiseParams(eps_pos=float(r.uniform(0.55, 0.8)), eps_neg=float(r.uniform(0.7, 1.0)), bias_pr=bias,
                          trial_rate_hz=float(np.exp(r.uniform(np.log(20), np.log(80)))), photons_per_lux=ppl,
                          dark_lux=float(r.uniform(0.05, 0.2)), eps_sigma=float(r.uniform(0.04, 0.12)))


def _flat_fields(params, seed, shape=(30, 40), duration_s=4.0, lux=LUX_LEVELS):
    """Per-pixel counts of uniformly lit recordings; each pixel keeps its thresholds at every level."""
    rng = np.random.default_rng(seed)
    thr = ev.draw_thresholds(shape, params, rng)
    counts = [ev.sample_counts(np.full(shape, lx), params, duration_s, rng, thresholds=thr) for lx in lux]
    return cal.flat_field(lux, counts, duration_s, source=f"simulated (seed {seed})")


def _z_scores(result, truth):
    ident = [n for n in result.free if result.status[n] == "fitted"]
    z = {n: (math.log(getattr(result.params, n)) - math.log(getattr(truth, n))) / result.rel_error[n] for n in ident}
    return z


def _check_recovery(results_truths):
    from scipy.stats import chi2

    n_tests = sum(len(_z_scores(r, t)) for r, t in results_truths)
    k = _bonferroni_k(n_tests)
    for result, truth in results_truths:
        z = _z_scores(result, truth)
        assert len(z) >= 5, result.summary()
        bad = {n: v for n, v in z.items() if abs(v) > k}
        assert not bad, f"|z| > {k:.2f}: {bad}\n{result.summary()}"
        q = sum(v * v for v in z.values())
        lo, hi = chi2.ppf([0.0005, 0.9995], len(z))
        assert lo < q < hi, f"sum z^2 = {q:.3g} outside [{lo:.3g}, {hi:.3g}]\n{result.summary()}"
        # the population rate curve within 4 sd of the fit's own band and within 5 %
        grid = np.geomspace(0.05, LUX_LEVELS.max(), 12)
        rate, rel_sd = result.rate_band(grid)
        true_rate = cal.population_rate(grid, truth)
        err = np.log(rate / true_rate)
        assert np.all(np.abs(err) < 4.0 * rel_sd + 1e-9), (err, rel_sd)
        assert np.all(np.abs(err) < 0.05), err


@pytest.mark.long
def test_flat_field_recovery_one_parameter_set():
    truth = _random_params(101)
    meas = _flat_fields(truth, 7)
    result = cal.calibrate(meas, n_starts=3, rng=0, fixed=NO_FLOORS)
    assert result.gof["histogram_p_value"] > 1e-3, result.summary()
    _check_recovery([(result, truth)])
    # the fitted mismatch explains the measured dispersion
    assert result.dispersion["log_ratio_rms"] < 0.3


@pytest.mark.slow
def test_flat_field_recovery_coverage_several_parameter_sets():
    pairs = []
    for seed in (202, 303, 404, 505):
        truth = _random_params(seed)
        meas = _flat_fields(truth, seed + 1, shape=(40, 50))
        pairs.append((cal.calibrate(meas, n_starts=6, rng=seed, fixed=NO_FLOORS), truth))
    _check_recovery(pairs)


@pytest.mark.long
def test_flat_field_from_event_files_and_cli(tmp_path):
    """events.h5 recordings -> listing -> counts equal count_events; the CLI writes a usable preset."""
    truth = ev.NoiseParams(eps_pos=0.6, eps_neg=0.8, bias_pr=1.5, trial_rate_hz=40.0, photons_per_lux=2.0,
                           dark_lux=0.1, eps_sigma=0.08)
    shape = (12, 16)
    rng = np.random.default_rng(3)
    thr = ev.draw_thresholds(shape, truth, rng)
    lines = []
    expected = []
    for i, lux in enumerate([0.0, 0.2, 1.0, 4.0, 12.0]):
        events = ev.simulate_events(np.full(shape, lux), truth, 2.0, rng, thresholds=thr)
        ev.write_events(tmp_path / f"flat{i}.h5", events, shape, t_end_us=2_000_000)
        lines += ["[[level]]", f'file = "flat{i}.h5"', f"lux = {lux}", ""]
        expected.append(ev.count_events(events, shape).reshape(2, -1))
    listing = tmp_path / "flats.toml"
    listing.write_text("\n".join(lines))
    meas = cal.read_measurements(listing)
    assert meas.kind == "flat-field" and meas.n_levels == 5
    for got, want in zip(meas.pixel_counts, expected):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(meas.duration_s, 2.0)
    out = tmp_path / "cam.toml"
    png = tmp_path / "cam.png"
    fix = ["photons_per_lux=2.0", "dark_lux=0.1", "trial_rate_hz=40"]
    rc = main(["-q", "calibrate", str(listing), "--out", str(out), "--plot", str(png), "--starts", "1",
               "--fix", *fix])
    assert rc == 0
    params = ev.load_preset(out)
    assert params.photons_per_lux == 2.0 and params.dark_lux == 0.1
    assert 0.3 < params.eps_pos < 1.2 and params.eps_sigma > 0
    doc = __import__("evnoise.params", fromlist=["x"]).load_preset_document(out)
    assert doc["fit"]["status"]["photons_per_lux"] == "fixed"
    assert png.stat().st_size > 10_000
    # the preset drives the simulator
    assert ev.sample_counts(np.ones((4, 4)), str(out), 1.0, 0).shape == (2, 4, 4)
    # no overwrite without --overwrite
    assert main(["-q", "calibrate", str(listing), "--out", str(out), "--fix", *fix]) == 2


# --------------------------------------------------------------------------------------
# rate tables
# --------------------------------------------------------------------------------------
def _write_csv(path, header, rows):
    path.write_text("# test table\n" + ",".join(header) + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    return path


@pytest.mark.long
def test_rate_table_counts_recovery(tmp_path):
    """Counts from a known model: eps_sigma (not determined by means) assumed; the rest recovered."""
    from evnoise.calibration.rates.spec import TABLE_SIGMA

    truth = ev.NoiseParams(eps_pos=0.7, eps_neg=0.9, bias_pr=2.0, trial_rate_hz=30.0, photons_per_lux=1.5,
                           dark_lux=0.15, eps_sigma=TABLE_SIGMA)
    lux = np.array([0.0, 0.05, 0.2, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 30.0])
    n_pix, dur = 5000, 5.0
    rng = np.random.default_rng(11)
    counts = rng.poisson(cal.population_rate(lux, truth) * n_pix * dur)
    path = _write_csv(tmp_path / "rates.csv", ["lux", "count_on", "count_off", "n_pixels", "duration_s"],
                      [(lx, counts[0, i], counts[1, i], n_pix, dur) for i, lx in enumerate(lux)])
    meas = cal.read_measurements(path)
    assert meas.kind == "table" and not meas.has_dispersion
    result = cal.calibrate(meas, n_starts=3, rng=1, fixed=NO_FLOORS)
    assert result.status["eps_sigma"] == "fixed (assumed)" and result.params.eps_sigma == TABLE_SIGMA
    assert any("not determined by mean rates" in t for t in result.identifiability)
    assert result.gof["p_value"] > 1e-3, result.summary()
    z = _z_scores(result, truth)
    k = _bonferroni_k(len(z))
    assert len(z) == 6 and all(abs(v) < k for v in z.values()), (z, result.summary())
    rate, rel_sd = result.rate_band(lux[1:])
    err = np.log(rate / cal.population_rate(lux[1:], truth))
    assert np.all(np.abs(err) < 4.0 * rel_sd + 1e-9), (err, rel_sd)


@pytest.mark.long
def test_rates_without_exposure_use_residual_scatter(tmp_path):
    """Rates without n_pixels/duration_s: quasi-likelihood; 3 % scatter gives about 3 % residuals."""
    from evnoise.calibration.rates.spec import TABLE_SIGMA

    truth = ev.NoiseParams(eps_pos=0.7, eps_neg=0.9, bias_pr=2.0, trial_rate_hz=30.0, photons_per_lux=1.5,
                           dark_lux=0.15, eps_sigma=TABLE_SIGMA)
    lux = np.array([0.0, 0.1, 0.4, 1.0, 2.5, 6.0, 15.0])
    rate = cal.population_rate(lux, truth) * np.exp(np.random.default_rng(2).normal(0, 0.03, (2, lux.size)))
    path = _write_csv(tmp_path / "r.csv", ["lux", "rate_on_hz", "rate_off_hz"],
                      [(lx, rate[0, i], rate[1, i]) for i, lx in enumerate(lux)])
    result = cal.calibrate(cal.read_measurements(path), n_starts=3, rng=0, fixed=NO_FLOORS)
    assert "unknown" in result.gof["counts"]
    assert result.gof["rate_rms_relative_residual"] < 0.05, result.summary()


def test_monitor_grey_levels(tmp_path):
    mon = _write_csv(tmp_path / "mon.csv", ["grey", "lux"], [(0, 0.0), (64, 1.0), (128, 4.6), (255, 18.0)])
    table = cal.read_monitor_table(mon)
    lux = cal.grey_to_lux([0, 64, 100, 255], table)
    assert lux[0] == 0 and lux[1] == pytest.approx(1.0) and lux[3] == pytest.approx(18.0)
    assert 1.0 < lux[2] < 4.6
    with pytest.raises(ev.InputError, match="outside the monitor table"):
        cal.grey_to_lux([300], table)
    rates = _write_csv(tmp_path / "g.csv", ["grey", "rate_on_hz", "rate_off_hz"],
                       [(0, 0.1, 0.05), (64, 0.5, 0.3), (128, 0.3, 0.2), (255, 0.05, 0.02)])
    meas = cal.read_measurements(rates, monitor=mon)
    np.testing.assert_allclose(meas.lux, cal.grey_to_lux([0, 64, 128, 255], table))
    np.testing.assert_array_equal(meas.grey, [0, 64, 128, 255])


# --------------------------------------------------------------------------------------
# bad inputs: clear errors from the API and the command line
# --------------------------------------------------------------------------------------
GOOD_ROWS = [(0.0, 0.2, 0.1, 100, 1.0), (0.5, 0.8, 0.5, 100, 1.0), (2.0, 0.6, 0.4, 100, 1.0),
             (8.0, 0.1, 0.05, 100, 1.0)]
HEADER = ["lux", "rate_on_hz", "rate_off_hz", "n_pixels", "duration_s"]
BAD_TABLES = {
    "too few levels": (GOOD_ROWS[:2], "at least 3 illuminance levels"),
    "zero counts everywhere": ([(r[0], 0, 0, 100, 1.0) for r in GOOD_ROWS], "no noise events at any level"),
    "no OFF events": ([(r[0], r[1], 0, 100, 1.0) for r in GOOD_ROWS], "no OFF events"),
    "NaN lux": ([GOOD_ROWS[0], ("nan", 0.8, 0.5, 100, 1.0)] + GOOD_ROWS[2:], "lux of level 2 is nan"),
    "duplicate lux": ([GOOD_ROWS[0], GOOD_ROWS[1], GOOD_ROWS[1], GOOD_ROWS[2]], "level 3 .* repeats level 2"),
    "decreasing lux": ([GOOD_ROWS[0], GOOD_ROWS[2], GOOD_ROWS[1], GOOD_ROWS[3]], "level 3 .* is below level 2"),
    "negative rate": ([GOOD_ROWS[0], (0.5, -0.8, 0.5, 100, 1.0)] + GOOD_ROWS[2:], "must be >= 0"),
}


@pytest.mark.parametrize("case", sorted(BAD_TABLES))
def test_bad_tables_api_and_cli(tmp_path, capsys, case):
    rows, message = BAD_TABLES[case]
    path = _write_csv(tmp_path / "bad.csv", HEADER, rows)
    with pytest.raises(ev.InputError, match=message):
        cal.read_measurements(path)
    out = tmp_path / "out.toml"
    assert main(["-q", "calibrate", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evnoise: error: ") and err.count("\n") == 1
    assert not out.exists()


def test_bad_inputs_more(tmp_path):
    with pytest.raises(ev.InputError, match="lux of level 2 is nan"):
        cal.rate_table([0.0, np.nan, 1.0, 2.0], [1, 1, 1, 1], [1, 1, 1, 1])
    with pytest.raises(ev.InputError, match="at least 3"):
        cal.flat_field([0.0, 1.0], [np.ones((2, 4, 4), int)] * 2, 1.0)
    with pytest.raises(ev.InputError, match="no noise events"):
        cal.flat_field([0.0, 1.0, 2.0], [np.zeros((2, 4, 4), int)] * 3, 1.0)
    # too few levels for the number of free parameters
    meas = cal.rate_table([0.0, 1.0, 2.0], [0.2, 0.5, 0.3], [0.1, 0.3, 0.2])
    with pytest.raises(ev.InputError, match="too few to fit 8 parameters"):  # the core six and the two floors
        cal.calibrate(meas)
    with pytest.raises(ev.InputError, match="eps_sigma cannot be fitted from mean rates alone"):
        cal.calibrate(meas, free=["eps_pos", "eps_sigma"])
    with pytest.raises(ev.ParameterError, match="unknown parameter"):
        cal.calibrate(meas, fixed={"gain": 1.0})
    # grey levels without a monitor table; a monitor table with duplicates
    grey = _write_csv(tmp_path / "g.csv", ["grey", "rate_on_hz", "rate_off_hz"], [(0, 1, 1), (1, 1, 1), (2, 1, 1)])
    with pytest.raises(ev.InputError, match="monitor table"):
        cal.read_measurements(grey)
    mon = _write_csv(tmp_path / "m.csv", ["grey", "lux"], [(0, 0.0), (10, 1.0), (10, 2.0)])
    with pytest.raises(ev.InputError, match="row 3 .* repeats row 2"):
        cal.read_monitor_table(mon)
    mon2 = _write_csv(tmp_path / "m2.csv", ["grey", "lux"], [(0, 0.0), (10, 2.0), (20, 1.0)])
    with pytest.raises(ev.InputError, match="must not decrease"):
        cal.read_monitor_table(mon2)
    # a flat-field listing naming a missing file; --fix with a bad value
    listing = tmp_path / "l.toml"
    listing.write_text('[[level]]\nfile = "a.h5"\nlux = 0\n[[level]]\nfile = "b.h5"\nlux = 1\n'
                       '[[level]]\nfile = "c.h5"\nlux = 2\n')
    assert main(["-q", "calibrate", str(listing), "--out", str(tmp_path / "x.toml")]) == 2
    path = _write_csv(tmp_path / "ok.csv", HEADER, GOOD_ROWS)
    assert main(["-q", "calibrate", str(path), "--out", str(tmp_path / "y.toml"), "--fix", "eps_pos=abc"]) == 2
    assert main(["-q", "calibrate", str(path), "--out", str(tmp_path / "no" / "y.toml")]) == 2


# --------------------------------------------------------------------------------------
# presets
# --------------------------------------------------------------------------------------
def _round_trip_fit():
    truth = _random_params(9)
    meas = _flat_fields(truth, 10, shape=(20, 20), lux=LUX_LEVELS[1:])
    return truth, cal.calibrate(meas, n_starts=1, initial=truth, fixed={"refractory_s": 0.0}, rng=0)


@pytest.fixture(scope="module")
def round_trip_fit():
    return _round_trip_fit()


@pytest.mark.long
def test_preset_round_trip(tmp_path, round_trip_fit):
    _, result = round_trip_fit
    path = result.write_preset(tmp_path / "p.toml")
    assert ev.load_preset(path) == result.params
    # the light range the fit saw is recorded: evnoise simulate warns far outside it (issue 32, section 4)
    light = ev.params.preset_light_range(str(path))
    assert (light.lo, light.hi) == (min(LUX_LEVELS[1:]), max(LUX_LEVELS[1:])) and light.note.startswith("measured")
    assert ev.params.light_range_warning(str(path), light.lo, 2 * light.hi) is None
    assert "preset p was fitted on" in ev.params.light_range_warning(str(path), light.lo, 3 * light.hi)
    with pytest.raises(ev.OutputError):
        result.write_preset(path)
    from evnoise.params import load_preset_document

    doc = load_preset_document(path)
    assert set(doc) >= {"params", "provenance", "fit"}
    assert doc["fit"]["std_error"]["eps_pos"] == pytest.approx(result.std_error["eps_pos"], rel=1e-6)


def _round_trip_problem():
    """The flat fields of test_preset_round_trip and their likelihood (the core parameters free)."""
    from evnoise.calibration.rates import likelihood as L
    from evnoise.calibration.rates import spec as SP

    truth = _random_params(9)
    meas = _flat_fields(truth, 10, shape=(20, 20), lux=LUX_LEVELS[1:])
    free = list(SP.CORE)
    values = truth.to_dict()
    return truth, L.Problem(meas, "poisson", "binomial", free, values, SP.data_bounds(meas, free, values))


def test_points_outside_the_domain_have_infinite_cost():
    """A non-finite or out-of-bounds point is rejected (loglik -inf, objective inf; the objective clips
    into the bounds first), and a local fit from a non-finite start returns at once; none raises."""
    from evnoise.calibration.rates import search as S

    truth, problem = _round_trip_problem()
    theta = problem.theta(truth)
    assert math.isfinite(problem.loglik(theta))
    for i in range(theta.size):
        for bad in (math.nan, math.inf, -math.inf, problem.hi[i] + 0.1, problem.lo[i] - 0.1):
            t = theta.copy()
            t[i] = bad
            assert problem.loglik(t) == -math.inf
            if math.isnan(bad):
                assert problem.objective(t) == math.inf
            assert not problem.in_domain(t)
    assert problem.in_domain(theta)
    t = np.full(theta.size, math.nan)
    got, f = S.local_fit(problem, t)
    assert f == math.inf and not problem.in_domain(got)


def test_the_search_stays_within_the_parameter_limits():
    """Bounds beyond NoiseParams' limits (PARAM_LIMITS; here dark_lux up to 1e7 lux, asked for) are cut to
    them: the likelihood and its finite differences at the upper bound evaluate without ParameterError."""
    from evnoise.calibration.rates import likelihood as L
    from evnoise.calibration.rates import spec as SP
    from evnoise.calibration.rates import uncertainty as U
    from evnoise.params import PARAM_LIMITS

    truth, problem = _round_trip_problem()
    meas, free, values = problem.meas, list(problem.free), truth.to_dict()
    wide = L.Problem(meas, "poisson", "binomial", free, values,
                     SP.data_bounds(meas, free, values, {"dark_lux": (1e-3, 1e7)}))
    i = free.index("dark_lux")
    theta = wide.theta(truth)
    theta[i] = wide.hi[i]
    assert math.isfinite(wide.loglik(theta))  # -1e300 at worst (no count possible), never an exception
    info, _, _ = U.information(wide, theta, U.steps(wide), want_meat=False)
    assert info.shape == (len(free), len(free))
    assert math.exp(wide.hi[i]) < PARAM_LIMITS["dark_lux"] < wide.bounds["dark_lux"][1]


@pytest.mark.long
def test_calibration_survives_a_non_finite_optimiser_step(monkeypatch, round_trip_fit):
    """A degenerate information matrix (as on a CPU whose last bits differ, where Fisher scoring
    proposed NaN for eps_pos and bias_pr) is forced on purpose: the NaN step is rejected, no
    NoiseParams is ever built from a non-finite value, and the search goes on to the optimum the
    undisturbed fit finds (every estimate within a tenth of its standard error of it)."""
    from evnoise.calibration.rates import likelihood as L
    from evnoise.calibration.rates import search as S

    information = S.information
    corrupted = []

    def nan_score_at_first_call(problem, theta, h, **kw):
        info, meat, extras = information(problem, theta, h, **kw)
        if not corrupted:  # the first Fisher-scoring iteration of the first start
            extras = dict(extras, score=np.where(np.arange(len(theta)) == 0, math.nan, extras["score"]))
            corrupted.append(problem.free[0])
        return info, meat, extras

    built = []

    def checked_params(**vals):
        built.append(vals)
        assert all(math.isfinite(v) for v in vals.values()), vals
        return ev.NoiseParams(**vals)

    monkeypatch.setattr(S, "information", nan_score_at_first_call)
    monkeypatch.setattr(L, "NoiseParams", checked_params)
    _, result = _round_trip_fit()
    assert corrupted == ["eps_pos"] and len(built) > 50
    _, undisturbed = round_trip_fit
    fitted = [n for n in result.free if result.status[n] == "fitted"]
    assert len(fitted) >= 6 and fitted == [n for n in undisturbed.free if undisturbed.status[n] == "fitted"]
    for n in fitted:
        a, b = getattr(result.params, n), getattr(undisturbed.params, n)
        assert abs(a - b) <= 0.1 * undisturbed.std_error[n], (n, a, b, undisturbed.std_error[n])


def refit_evk3_authors():
    from evnoise.calibration.scripts import refit_evk3

    return refit_evk3.AUTHORS


def test_shipped_evk3_preset_is_the_refit():
    from evnoise.params import load_preset_document

    params = ev.load_preset("evk3-hd")
    doc = load_preset_document("evk3-hd")
    prov = doc["provenance"]
    assert prov["status"] == "refitted"
    assert "refit_evk3" in prov["command"] and "0.1398" in prov["background_floor"]
    assert "quality" in doc["fit"] and "identifiability" in doc["fit"]
    assert params.eps_sigma >= 0 and params.refractory_s == 0
    # the authors' constant extra OFF rate is the fitted OFF floor (within its error and 2 % of their number)
    assert doc["fit"]["status"]["leak_off_hz"] == "fitted"
    assert abs(params.leak_off_hz / refit_evk3_authors()["extra_off_hz"] - 1) < 0.02
    assert doc["sensor"] == {"width": 1280, "height": 720, "name": "Prophesee EVK3-HD (Sony IMX636)"}
    assert prov["summary"]


@needs_reference
def test_evk3_preset_reproduces_the_authors_curve():
    """The shipped preset's population rate vs the regenerated curve, within the recorded fit quality."""
    from evnoise.calibration.scripts import refit_evk3
    from evnoise.params import load_preset_document

    grey, lux, lux_authors, *_ = refit_evk3.load_reference(REFERENCE)
    # the regenerated curve is the authors' (README: ON peak ~0.83/s near 1-2 lux, < 0.1/s above 10 lux)
    target = refit_evk3.authors_rate(lux_authors, include_extra_off=True)
    i = int(np.argmax(target[0]))
    assert 0.75 < target[0, i] < 0.95 and 0.5 < lux[i] < 3.0
    assert np.all(target[0][lux > 10] < 0.1)
    assert np.all(np.abs(target[1][lux > 15] - 0.1398) < 0.01)  # the OFF floor
    model = cal.population_rate(lux, ev.load_preset("evk3-hd"))
    rel = model / target - 1
    quality = load_preset_document("evk3-hd")["fit"]["quality"]
    assert np.sqrt(np.mean(rel**2)) <= 1.05 * quality["rate_rms_relative_residual"] + 1e-3


@pytest.mark.slow
@needs_reference
def test_evk3_refit_is_reproducible(tmp_path):
    from evnoise.calibration.scripts import refit_evk3
    from evnoise.params import load_preset_document

    shipped = ev.load_preset("evk3-hd")
    doc = load_preset_document("evk3-hd")
    assert refit_evk3.main(["--reference", str(REFERENCE), "--out", str(tmp_path / "e.toml"), "--plot",
                            str(tmp_path / "e.png"), "-q"]) == 0
    again = ev.load_preset(tmp_path / "e.toml")
    for name in doc["fit"]["free"]:
        assert getattr(again, name) == pytest.approx(getattr(shipped, name), rel=1e-3), name
