"""Calibration of the background terms (issue 15): leak floors from simulated flat fields.

The flat fields are simulated with ``ev.sample_counts`` (each pixel keeps its thresholds at every
level) from parameters with an ON and an OFF floor; the fit must recover each floor within
``K_SIGMA`` of its own reported standard error, report a floor that the data cannot separate from
photon noise as not identified (and warn), report a floor the data do not need as 0, and refuse
terms that static data cannot determine. Fast tests hold ``eps_sigma`` and ``photons_per_lux`` at
the truth (the search over them is tested in test_calibration.py); the slow test runs the default fit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import evnoise as ev
from evnoise import calibration as cal
from evnoise.calibration.rates import likelihood as L
from evnoise.calibration.rates import spec as SP

K_SIGMA = 3.0
TRUTH = ev.NoiseParams(eps_pos=0.6, eps_neg=0.8, bias_pr=1.5, trial_rate_hz=40.0, photons_per_lux=2.0,
                       dark_lux=0.01, eps_sigma=0.06, leak_on_hz=0.02, leak_off_hz=0.14)
#: dark_lux is small, so in the dark the photon noise (~1e-3 events/s) is far below the floors
DARK_AND_LIT = (0.0, 0.3, 1.0, 4.0, 12.0)
LIT_ONLY = DARK_AND_LIT[1:]
HELD = {"eps_sigma": TRUTH.eps_sigma, "photons_per_lux": TRUTH.photons_per_lux}


def _flat_fields(params, lux, seed=1, shape=(30, 40), duration_s=5.0):
    rng = np.random.default_rng(seed)
    thr = ev.draw_thresholds(shape, params, rng)
    counts = [ev.sample_counts(np.full(shape, lx), params, duration_s, rng, thresholds=thr) for lx in lux]
    return cal.flat_field(np.array(lux), counts, duration_s, source=f"simulated (seed {seed})")


def _z(result, name, truth=TRUTH):
    return (getattr(result.params, name) - getattr(truth, name)) / result.std_error[name]


def test_the_likelihood_uses_the_rate_with_the_background():
    """Without mismatch a pixel's count is Binomial(M, P) with P from evnoise.rates (independent route)."""
    from scipy.stats import binom

    from evnoise.rates import trial_probabilities

    truth = TRUTH.replace(eps_sigma=0.0)
    meas = _flat_fields(truth, DARK_AND_LIT, shape=(6, 6))
    free = list(SP.CORE) + ["leak_on_hz", "leak_off_hz"]
    values = truth.to_dict()
    problem = L.Problem(meas, "poisson", "binomial", free, values, SP.data_bounds(meas, free, values))
    stats = problem.stats(problem.theta(truth))
    c = np.arange(40.0)
    trials = truth.trial_rate_hz * 5.0
    for j, lux in enumerate(DARK_AND_LIT):
        p_on, p_off = trial_probabilities(truth.photons_per_trial(lux), truth)
        for k, p in enumerate((p_on, p_off)):
            np.testing.assert_allclose(problem.hist_tables(stats, k, j, c), binom.logpmf(c, trials, float(p)),
                                       rtol=1e-9)
    np.testing.assert_allclose(stats.mean_rate(), ev.expected_rate(np.array(DARK_AND_LIT), truth), rtol=1e-12)


@pytest.mark.long
def test_floors_are_recovered_from_dark_flat_fields():
    meas = _flat_fields(TRUTH, DARK_AND_LIT)
    r = cal.calibrate(meas, fixed=HELD, n_starts=1, n_seeds=128, rng=0)
    assert r.fit_status == "accepted", r.summary()
    assert {"leak_on_hz", "leak_off_hz"} <= set(r.free)
    for name in ("leak_on_hz", "leak_off_hz"):
        assert r.status[name] == "fitted", r.summary()
        assert abs(_z(r, name)) < K_SIGMA, (name, _z(r, name), r.summary())
        # the reported error is that of a floor measured in the dark: about sqrt(floor / exposure)
        naive = math.sqrt(getattr(TRUTH, name) / (meas.n_pixels[0] * meas.duration_s[0]))
        assert 0.5 * naive < r.std_error[name] < 3.0 * naive, (name, r.std_error[name], naive)
    assert not r.warnings, r.warnings
    text = r.summary()
    assert "background (rates in events/s per pixel): leak_on_hz" in text
    assert "pr_tau_s_at_1lux" in text and r.status["pr_tau_s_at_1lux"] == "not identified"
    doc = r.to_toml()
    assert "leak_off_hz = " in doc and 'leak_off_hz = "fitted"' in doc


@pytest.mark.long
def test_without_a_dark_level_the_on_floor_is_reported_not_identified():
    """Lit levels only: the small ON floor hides under the photon noise; the OFF floor shows at the bright end."""
    meas = _flat_fields(TRUTH, LIT_ONLY)
    # by default, without a dark level the floors are not fitted and are reported as not identified
    plain = cal.calibrate(meas, fixed=HELD, initial=TRUTH.replace(leak_on_hz=0.0, leak_off_hz=0.0), n_starts=1,
                          n_seeds=16, rng=0)
    assert plain.status["leak_on_hz"].startswith("not identified (no dark level"), plain.summary()
    assert "leak_on_hz" not in plain.free
    # asked to fit them anyway (--fit), the OFF floor still shows at the bright end
    core = [n for n in cal.FIT_NAMES[:6] if n not in HELD]
    r = cal.calibrate(meas, free=core + ["leak_on_hz", "leak_off_hz"], fixed=HELD, initial=TRUTH, n_starts=1,
                      n_seeds=16, rng=0)
    assert r.fit_status == "accepted", r.summary()
    assert r.status["leak_on_hz"] in ("not identified", "at lower bound"), r.summary()
    if r.status["leak_on_hz"] == "not identified":
        assert r.rel_error["leak_on_hz"] > 0.5
        assert abs(_z(r, "leak_on_hz")) < K_SIGMA
    assert any(w.startswith("leak_on_hz (background floor) is not identified") for w in r.warnings), r.warnings
    assert r.status["leak_off_hz"] == "fitted" and abs(_z(r, "leak_off_hz")) < K_SIGMA, r.summary()


@pytest.mark.long
def test_a_sensor_without_floors_reports_them_as_zero(tmp_path):
    truth = TRUTH.replace(leak_on_hz=0.0, leak_off_hz=0.0)
    meas = _flat_fields(truth, DARK_AND_LIT, seed=2)
    r = cal.calibrate(meas, fixed=HELD, initial=truth, n_starts=1, n_seeds=16, rng=0)
    assert r.fit_status == "accepted", r.summary()
    for name in ("leak_on_hz", "leak_off_hz"):
        if r.status[name] == "at lower bound":
            assert getattr(r.params, name) == 0.0
            assert any(t.startswith(f"{name} is at its lower bound") for t in r.identifiability)
        else:  # a small value with an error that includes 0
            assert getattr(r.params, name) < K_SIGMA * r.std_error[name], r.summary()
    assert not [w for w in r.warnings if "bound" in w], r.warnings
    # the written preset carries the floors as reported
    loaded = ev.load_preset(r.write_preset(tmp_path / "p.toml"))
    assert (loaded.leak_on_hz, loaded.leak_off_hz) == (r.params.leak_on_hz, r.params.leak_off_hz)


def test_terms_static_data_cannot_determine_are_refused():
    meas = cal.rate_table([0.0, 1.0, 2.0, 4.0, 8.0], [0.2, 0.5, 0.3, 0.2, 0.1], [0.1, 0.3, 0.2, 0.15, 0.1])
    with pytest.raises(ev.InputError, match="pr_tau_s_at_1lux cannot be fitted from static measurements"):
        cal.calibrate(meas, free=["eps_pos", "pr_tau_s_at_1lux"])
    with pytest.raises(ev.InputError, match="only be fitted from flat fields"):
        cal.calibrate(meas, free=["eps_pos", "leak_sigma"])
    with pytest.raises(ev.InputError, match="too few to fit 8 parameters"):
        cal.calibrate(cal.rate_table([0.0, 1.0, 2.0], [0.2, 0.5, 0.3], [0.1, 0.3, 0.2]))


def test_cli_fits_the_floors_and_writes_them(tmp_path, capsys):
    from evnoise.cli import main
    from evnoise.params import load_preset_document

    lux = np.array([0.0, 0.5, 2.0, 8.0, 30.0])
    rate = cal.population_rate(lux, TRUTH)
    counts = np.random.default_rng(5).poisson(rate * 20_000 * 2.0)
    path = tmp_path / "rates.csv"
    path.write_text("lux,count_on,count_off,n_pixels,duration_s\n"
                    + "".join(f"{lx},{counts[0, i]},{counts[1, i]},20000,2\n" for i, lx in enumerate(lux)))
    out = tmp_path / "cam.toml"
    fix = [f"{n}={getattr(TRUTH, n)}" for n in ("eps_pos", "eps_neg", "bias_pr", "photons_per_lux", "eps_sigma")]
    assert main(["-q", "calibrate", str(path), "--out", str(out), "--starts", "1", "--fix", *fix]) == 0
    doc = load_preset_document(out)
    assert doc["fit"]["status"]["leak_off_hz"] == "fitted"
    for name in ("leak_on_hz", "leak_off_hz"):
        est, se = doc["params"][name], doc["fit"]["std_error"][name]
        assert abs(est - getattr(TRUTH, name)) < K_SIGMA * se, (name, est, se)
    assert ev.load_preset(out).leak_off_hz == doc["params"]["leak_off_hz"]


@pytest.mark.slow
def test_default_fit_recovers_the_floors():
    """The default search (every core parameter and the mismatch free) on the dark + lit flat fields."""
    meas = _flat_fields(TRUTH, DARK_AND_LIT, shape=(40, 50))
    r = cal.calibrate(meas, n_starts=3, rng=0)
    assert r.fit_status == "accepted", r.summary()
    for name in ("leak_on_hz", "leak_off_hz"):
        assert r.status[name] == "fitted" and abs(_z(r, name)) < K_SIGMA, (name, r.summary())
