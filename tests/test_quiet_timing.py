"""Timing in the quiet fit's goodness report (issue 32 section 2): the polarity-transition test (a check of
each window) and the same-pixel inter-event-interval KS test (``QuietFit.timing``), so a window whose counts
the model reproduces but whose timing it does not is not "accepted"."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import evnoise as ev
from evnoise.calibration.quiet import checks as qc
from evnoise.calibration.quiet import fit as q
from evnoise.calibration.quiet import goodness as qg
from evnoise.calibration.quiet import likelihood as ql
from evnoise.calibration.quiet.window import QuietWindow
from evnoise.events import count_events
from evnoise.terms.memory import memory_statistics


def _window(events, shape, duration_s, shifts=20):
    events = np.sort(events, order="t", kind="stable")
    counts = count_events(events, shape)
    found = qc.window_checks(events, counts, 0, round(duration_s * 1e6), shifts=shifts, seed=1)
    return QuietWindow(counts, duration_s, "sim.h5", checks=found)


def _timing(fit):
    return {t["test"]: t for t in fit.timing}


def _memoryless(shape, duration_s, seed):
    params = dataclasses.replace(ev.load_preset("dvs128"), leak_on_hz=0.6, leak_off_hz=0.4, leak_sigma=0.5,
                                 leak_regularity=0.0, hot_pixel_fraction=0.0)
    return ev.simulate_events(np.zeros(shape), params, duration_s, rng=seed)


@pytest.fixture(scope="module")
def memoryless_fit():
    shape, duration = (24, 24), 20.0
    # seed 6: every p-value of this fit is >= 0.2 (seed 5's second histogram sat at 0.0018, a coin toss across
    # machines' last bits against GOODNESS_P = 1e-3)
    w = _window(_memoryless(shape, duration, 6), shape, duration)
    return w, q.fit_quiet([w], hot="off", regularity="off")


def test_memoryless_window_passes_both_timing_tests(memoryless_fit):
    w, fit = memoryless_fit
    tests = _timing(fit)
    tr = tests["polarity_transitions"]
    assert tr["transitions"] > 1000
    # independent computation: a random arrangement's expected opposite share ~ 2 q (1 - q), q = 0.6
    assert abs(tr["opposite_share"] - 2 * 0.6 * 0.4) < 4 * np.sqrt(0.48 * 0.52 / tr["transitions"]) + 0.02
    assert tr["testable"] and tr["p_value"] >= q.GOODNESS_P
    iei = tests["intervals"]
    assert iei["testable"] and iei["intervals"] == tr["transitions"]
    assert iei["p_value"] >= q.GOODNESS_P
    assert fit.fit_status == "accepted", fit.rejections
    text = fit.summary()
    assert "timing sim.h5 intervals: passed" in text and "timing sim.h5 polarity_transitions: passed" in text
    tables = fit.to_toml_tables()
    assert "intervals_s" not in str(tables["checks"]) and len(tables["timing"]) == 2
    # the window's checks are the four they were
    assert {c["check"] for c in w.checks} == {"polarity_pairs", "stationarity", "scene_motion", "spatial_structure"}


def test_interval_cdf_against_simulated_renewal():
    """The window-truncated mixture CDF against a direct simulation of Poisson pixels in a window."""
    rng = np.random.default_rng(2)
    T, rates = 5.0, np.array([0.5, 2.0])
    ivals = []
    for lam in np.repeat(rates, 400):
        t = np.cumsum(rng.exponential(1 / lam, size=int(lam * T * 3 + 50)))
        t = t[t < T]
        ivals.append(np.diff(t))
    ivals = np.concatenate(ivals)
    # a two-point "spread" grid: the model's pixels at rates 0.5 and 2 in equal shares
    v = dict(rate_on_hz=0.5, rate_off_hz=0.0, growth_on=0.0, growth_off=0.0, sigma=0.0, hot_fraction=0.5,
             hot_rate_hz=1.5, hot_sigma=0.0, hot_on_fraction=1.0, regularity=0.0)
    w = QuietWindow(np.zeros((2, 2, 2), dtype=np.int64), T, "x")
    groups = ql.window_groups([w])
    model = ql.Model(False, True, [np.zeros((1, 2))], False, [np.zeros(1)], False)
    from scipy.stats import kstest

    res = kstest(ivals, lambda x: qg.interval_cdf(x, v, model, 0, groups[0], 0))
    assert res.pvalue > 1e-3
    # and it is the truncated law, not the plain mixture of exponentials
    plain = kstest(ivals, lambda x: 1 - 0.5 * np.exp(-0.5 * x) - 0.5 * np.exp(-2 * x))
    assert plain.pvalue < 1e-3


def test_alternating_window_fails_the_transition_test():
    shape, duration, lux = (16, 16), 6.0, 10.0
    params = dataclasses.replace(ev.load_preset("dvs128"), leak_on_hz=0.0, leak_off_hz=0.0, leak_sigma=0.0,
                                 hot_pixel_fraction=0.0, leak_regularity=0.0, eps_sigma=0.0, reset_memory=0.7)
    events = ev.simulate_events(np.full(shape, lux), params, duration, rng=7)
    w = _window(events, shape, duration)
    fit = q.fit_quiet([w], hot="off", regularity="off", spread="off")
    tr = _timing(fit)["polarity_transitions"]
    p_opp = float(memory_statistics(np.array([lux]), params).p_opposite[0])
    assert p_opp > 0.9
    se = np.sqrt(p_opp * (1 - p_opp) / tr["transitions"])
    assert abs(tr["opposite_share"] - p_opp) < 5 * se + 0.01  # the simulator alternates as the model says
    assert tr["p_value"] < q.GOODNESS_P
    assert fit.fit_status == "rejected"
    assert any("polarity_transitions FAILED" in r for r in fit.rejections)
    assert "timing sim.h5 polarity_transitions: FAILED" in fit.summary()
    # against the reset-memory model's own p_opposite the same window is far closer: its share sits above the
    # stationary p_opposite only by the window-end cut (polarity_transitions' doc; +0.006 here, about 2 binomial
    # sd, so a p-value against the uncorrected p_opposite would be a coin toss across machines' last bits)
    timing = qc.same_pixel_timing(np.sort(events, order="t", kind="stable"), shape)
    against_memory = qc.polarity_transitions(timing, p_opposite=p_opp)
    miss_memory = abs(against_memory["statistic"] - against_memory["null_mean"])
    assert miss_memory < 0.05 * abs(tr["statistic"] - tr["null_mean"])  # 20x closer than the memoryless model


def test_short_window_reports_not_enough_intervals():
    shape, duration = (4, 4), 2.0
    w = _window(_memoryless(shape, duration, 3), shape, duration)
    fit = q.fit_quiet([w], hot="off", regularity="off", spread="off")
    tests = _timing(fit)
    assert 0 < tests["intervals"]["intervals"] < qc.MIN_INTERVALS
    for t in tests.values():
        assert t["testable"] is False and t["detail"].startswith("not enough intervals")
    assert fit.fit_status == "accepted"
    text = fit.summary()
    assert "timing sim.h5 intervals: not testable; not enough intervals" in text
    assert "timing sim.h5 polarity_transitions: not testable; not enough intervals" in text


def test_counts_only_windows_have_no_timing_tests():
    w = QuietWindow(count_events(_memoryless((8, 8), 5.0, 4), (8, 8)), 5.0, "counts")
    fit = q.fit_quiet([w], hot="off", regularity="off", spread="off")
    assert fit.timing == [] and "timing" not in fit.summary()


@pytest.mark.long
def test_counts_right_timing_wrong_is_rejected():
    """Each pixel's events moved into a random 2 s stretch of the 20 s window: the per-pixel counts (and the
    polarity order) are those of the memoryless window, so the count histograms pass, but the intervals do
    not and the fit is not accepted."""
    shape, duration = (24, 24), 20.0
    events = np.sort(_memoryless(shape, duration, 6), order="t", kind="stable")
    rng = np.random.default_rng(9)
    pix = events["y"].astype(np.int64) * shape[1] + events["x"]
    start = rng.uniform(0, duration - 2.0, size=shape[0] * shape[1])
    bunched = events.copy()
    bunched["t"] = np.round((start[pix] + events["t"] * 1e-6 / duration * 2.0) * 1e6).astype(events["t"].dtype)
    w = _window(bunched, shape, duration)
    np.testing.assert_array_equal(w.counts, count_events(events, shape))
    fit = q.fit_quiet([w], hot="off", regularity="off")
    assert all(g["p_value"] >= q.GOODNESS_P for g in fit.goodness)
    iei = _timing(fit)["intervals"]
    # no window simulated from the model comes near (the smallest p-value the simulation gives); as independent
    # intervals, far below
    assert iei["p_value"] == 1.0 / (qg.INTERVAL_REPLICAS + 1) and iei["p_value_independent"] < 1e-6
    assert iei["median_s"] < 0.5 * iei["model_median_s"]
    assert fit.fit_status == "rejected"
    assert any("inter-event intervals do not match" in r for r in fit.rejections)


def test_compare_intervals_of_a_preset_on_its_own_window(tmp_path):
    """A preset simulated on a window of its own events: totals within a few standard deviations, intervals not told
    apart (two-sample KS, fixed seeds); the window's intervals are each pixel's consecutive gaps."""
    from evnoise.calibration.quiet.goodness import compare_intervals, window_intervals
    from evnoise.calibration.quiet.window import QuietWindow, quiet_window

    params = ev.NoiseParams(eps_pos=5, eps_neg=5, bias_pr=2, trial_rate_hz=1000, photons_per_lux=1, leak_on_hz=0.6,
                            leak_off_hz=0.3, leak_regularity=0.7, hot_pixel_fraction=0.05, hot_pixel_rate_hz=5.0,
                            hot_pixel_regularity=0.0)
    shape, T = (20, 20), 20.0
    events = ev.simulate_events(np.zeros(shape), params, T, rng=3)
    w = quiet_window(ev.write_events(tmp_path / "w.h5", events, shape), 0.0, T)
    xs = window_intervals(w)
    idx = events["y"].astype(np.int64) * shape[1] + events["x"]
    direct = np.concatenate([np.diff(events["t"][idx == k]) * 1e-6 for k in np.unique(idx)])
    np.testing.assert_allclose(np.sort(xs), np.sort(direct), rtol=0, atol=1e-9)
    out = compare_intervals(params, w, replicas=4, seed=2)
    total = out["events_on_per_replica"] + out["events_off_per_replica"]
    assert abs(total - events.size) < 5 * math.sqrt(events.size)
    assert out["real_intervals"] == xs.size and out["ks_2samp_p_value"] > 1e-3
    # a Poisson leak instead is told apart by its intervals
    poisson = compare_intervals(params.replace(leak_regularity=0.0, hot_pixel_regularity=-1.0), w, replicas=4, seed=2)
    assert poisson["ks_2samp_p_value"] < 1e-3
    with pytest.raises(ev.InputError, match="no events"):
        window_intervals(QuietWindow(w.counts, T, "counts only"))
    with pytest.raises(ev.InputError, match="no events"):
        compare_intervals(params, QuietWindow(w.counts, T, "counts only"))


def _spread_model(n_side, duration_s, regularity):
    """A fitted model's values as the interval test sees them, without a fit: a DVS128-like population (leak spread
    sigma 1, 3 % hot pixels five times as busy with their own spread, a regular ordinary timer) on an
    ``n_side`` x ``n_side`` window."""
    v = dict(rate_on_hz=0.3, rate_off_hz=0.0, growth_on=0.0, growth_off=0.0, sigma=1.0, hot_fraction=0.03,
             hot_rate_hz=1.5, hot_sigma=1.0, hot_on_fraction=1.0, regularity=regularity, hot_regularity=0.0)
    w = QuietWindow(np.zeros((2, n_side, n_side), dtype=np.int64), duration_s, "x")
    groups = ql.window_groups([w])
    model = ql.Model(False, True, [np.zeros((1, 2))], False, [np.zeros(1)], False)
    return v, model, groups[0]


def test_renewal_intervals_have_the_count_law_and_the_interval_law():
    """Simulated pixels (the interval test's null windows): the number of intervals per pixel is, on average,
    ``E[N] - P(N >= 1)`` of the stationary count law (:func:`counts.count_survival`, an independent closed form),
    and the pooled intervals of equal pixels follow the window-truncated interval law (:func:`interval_cdf`)."""
    from scipy.stats import kstest

    from evnoise.calibration.quiet.counts import count_survival

    rng = np.random.default_rng(12)
    n_pix, lam, T = 20_000, 2.0, 5.0
    for r in (0.0, 0.7, 1.0):
        xs = qg.renewal_intervals(np.full(n_pix, lam), np.full(n_pix, r), T, rng)
        k = np.arange(1, 60, dtype=np.float64)
        mean_n = float(np.sum(count_survival(k, lam, T, r)))  # E[N] = sum_k P(N >= k)
        want = n_pix * (mean_n - float(count_survival(1.0, lam, T, r)))
        assert abs(mean_n - lam * T) < 1e-6  # stationary: E[N] = lam T
        assert abs(xs.size - want) < 5 * np.sqrt(want), (r, xs.size, want)
        if r < 1.0:  # periodic pixels have one interval length
            v = dict(rate_on_hz=lam, rate_off_hz=0.0, growth_on=0.0, growth_off=0.0, sigma=0.0, hot_fraction=0.0,
                     hot_rate_hz=0.0, hot_sigma=0.0, hot_on_fraction=1.0, regularity=r)
            w = QuietWindow(np.zeros((2, 1, 1), dtype=np.int64), T, "x")
            groups = ql.window_groups([w])
            model = ql.Model(False, True, [np.zeros((1, 2))], False, [np.zeros(1)], False)
            sub = xs[rng.choice(xs.size, 4000, replace=False)]  # one or two per pixel: nearly independent
            assert kstest(sub, lambda x: qg.interval_cdf(x, v, model, 0, groups[0], 0)).pvalue > 1e-3
        else:
            np.testing.assert_allclose(xs, 1.0 / lam, rtol=1e-12)


@pytest.mark.long
def test_interval_p_value_holds_its_level_where_intervals_are_not_independent():
    """Windows drawn from the model itself (a population of pixels with spread rates and busy hot pixels, whose
    intervals share their pixel's rate): the KS p-value of independent intervals rejects them far more often than
    its level; the p-value from simulated windows holds it (binomial k-sigma over the null windows)."""
    from scipy.stats import kstwo

    v, model, grp = _spread_model(16, 6.0, 0.7)  # ~330 intervals a window, most from its ~8 hot pixels
    draw = qg.interval_sampler(v, model, 0, grp, 0)

    def cdf(x):
        return qg.interval_cdf(x, v, model, 0, grp, 0)

    rng = np.random.default_rng(3)
    plain, simulated = [], []
    fast = qg._tabulated_cdf(cdf, 6.0)
    grid = np.linspace(0.0, 6.0, 2001)
    assert np.max(np.abs(fast(grid) - cdf(grid))) < 3e-5  # the table the simulated windows are measured with
    for m in range(150):
        xs = draw(rng)
        n = xs.size
        plain.append(float(kstwo.sf(qg._ks_distance(xs, n, cdf), n)))
        simulated.append(qg.simulated_ks_p_value(xs, n, draw, fast, seed=1000 + m)[0])
    plain, simulated = np.array(plain), np.array(simulated)
    alpha, n_win = 0.05, plain.size
    sd = np.sqrt(alpha * (1 - alpha) / n_win)
    assert np.mean(plain < alpha) > alpha + 4 * sd, np.mean(plain < alpha)  # the defect: over-rejection
    assert np.mean(simulated < alpha) < alpha + 3 * sd, np.mean(simulated < alpha)
    assert np.mean(simulated < 0.5) > 0.5 - 4 * np.sqrt(0.25 / n_win)  # not conservative to uselessness


def _population_intervals(n_pix, duration_s, rng, first_unit=0):
    """Intervals and pixel of each of ``n_pix`` Poisson pixels of a spread population (leak spread sigma 1, 3 % hot
    pixels ten times as busy), written out pixel by pixel (an independent generator); pixels numbered from
    ``first_unit``."""
    gaps, units = [], []
    for k in range(n_pix):
        rate = 0.4 * np.exp(-0.5 + rng.standard_normal())
        if rng.random() < 0.03:
            rate += 4.0 * np.exp(-0.5 + rng.standard_normal())
        t = np.cumsum(rng.exponential(1.0 / rate, size=int(rate * duration_s * 2 + 20)))
        t = t[t < duration_s]
        gaps.append(np.diff(t))
        units.append(np.full(max(t.size - 1, 0), first_unit + k))
    return np.concatenate(gaps), np.concatenate(units)


@pytest.mark.long
def test_pixel_permutation_ks_holds_its_level_where_scipy_does_not():
    """A window and four replicas drawn from one spread population (pixels are the independent units): SciPy's
    two-sample KS p-value, which takes the intervals as independent, rejects far beyond its level; the pixel
    relabelling's p-value holds it; its statistic is SciPy's."""
    from scipy.stats import ks_2samp

    rng = np.random.default_rng(8)
    n_pix, T = 256, 6.0
    plain, relabelled = [], []
    for m in range(200):
        real, real_units = _population_intervals(n_pix, T, rng)
        sim, sim_units = _population_intervals(4 * n_pix, T, rng, first_unit=n_pix)
        out = qg.pixel_permutation_ks(real, real_units, sim, sim_units, n_pix, 4, seed=m)
        assert out["statistic"] == pytest.approx(ks_2samp(real, sim).statistic, abs=1e-12)
        plain.append(out["p_value_independent"])
        relabelled.append(out["p_value"])
    plain, relabelled = np.array(plain), np.array(relabelled)
    alpha, n_win = 0.05, plain.size
    sd = np.sqrt(alpha * (1 - alpha) / n_win)
    assert np.mean(plain < alpha) > alpha + 4 * sd, np.mean(plain < alpha)
    assert np.mean(relabelled < alpha) < alpha + 3 * sd, np.mean(relabelled < alpha)
    assert np.mean(relabelled < 0.5) > 0.5 - 4 * np.sqrt(0.25 / n_win)
    # another population (no hot pixels, a quarter of the rate spread) is told apart
    real, real_units = _population_intervals(n_pix, T, rng)
    other = []
    for k in range(4 * n_pix):
        t = np.cumsum(rng.exponential(1.0 / (0.4 * np.exp(0.25 * rng.standard_normal())), size=40))
        other.append(np.diff(t[t < T]))
    other_units = np.concatenate([np.full(g.size, n_pix + k) for k, g in enumerate(other)])
    assert qg.pixel_permutation_ks(real, real_units, np.concatenate(other), other_units, n_pix, 4)["p_value"] < 1e-3
