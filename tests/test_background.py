"""Background activity (leak), hot pixels and photoreceptor bandwidth in every tier (issue 15).

Each tier is checked against the closed form (:func:`evnoise.expected_rate` with the background
of :mod:`evnoise.background`) with tolerances of ``K`` standard errors, and against the brute-force
reference :func:`evnoise.testing.naive_static_events`, which draws the background arrivals of a
trial as a Poisson count (an independent route to ``1 - exp(-l dt)``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import evnoise as ev
from evnoise import simulate as sim
from evnoise.errors import ParameterError
from evnoise.model import event_probability
from evnoise.testing import naive_static_events

K = 5.0  # standard errors

BASE = ev.NoiseParams(eps_pos=0.3, eps_neg=0.35, bias_pr=2.0, trial_rate_hz=200.0, photons_per_lux=4.0,
                      dark_lux=0.05)
LEAKY = BASE.replace(leak_on_hz=2.0, leak_off_hz=0.7, leak_on_hz_per_lux=0.4, leak_off_hz_per_lux=0.05)


def _mean_rate_check(counts, expected_rate, duration_s, label):
    """Per-polarity mean count per pixel vs ``expected_rate * duration`` within K standard errors."""
    counts = counts.reshape(2, -1).astype(np.float64)
    expected = np.asarray(expected_rate).reshape(2, -1) * duration_s
    n = counts.shape[1]
    for k, name in enumerate(("ON", "OFF")):
        diff = counts[k].mean() - expected[k].mean()
        se = max(counts[k].std(ddof=1), 1e-12) / math.sqrt(n)
        assert abs(diff) < K * se + 1e-9, f"{label} {name}: mean {counts[k].mean():.5g} vs {expected[k].mean():.5g}"


def test_closed_form_limits():
    lux = np.array([0.0, 0.5, 3.0, 40.0])
    shot = ev.expected_rate(lux, BASE)
    total = ev.expected_rate(lux, LEAKY)
    l_on, l_off = ev.background_rate(lux, LEAKY)
    np.testing.assert_allclose(l_on, 2.0 + 0.4 * lux)
    np.testing.assert_allclose(l_off, 0.7 + 0.05 * lux)
    # independent evaluation of the documented per-trial combination
    lam = BASE.photons_per_trial(lux)
    p_on = event_probability(lam, BASE.eps_pos, BASE.bias_pr)
    p_off = event_probability(lam, BASE.eps_neg, BASE.bias_pr)
    n = BASE.trial_rate_hz
    a = 1.0 - np.exp(-(l_on + l_off) / n)
    np.testing.assert_allclose(total[0], n * (p_on + (1 - p_on - p_off) * a * l_on / (l_on + l_off)), rtol=1e-12)
    np.testing.assert_allclose(total[1], n * (p_off + (1 - p_on - p_off) * a * l_off / (l_on + l_off)), rtol=1e-12)
    # l << N: the background adds its rate in the trials the photon comparison leaves quiet (first order in
    # l / N); where the photon noise is rare (p << 1) the rates simply add
    small = BASE.replace(leak_on_hz=1e-3, leak_off_hz=2e-3)
    quiet = 1.0 - p_on - p_off
    np.testing.assert_allclose(ev.expected_rate(lux, small) - shot, [1e-3 * quiet, 2e-3 * quiet], rtol=2e-5)
    rare = BASE.replace(eps_pos=3.0, eps_neg=3.0)
    added = ev.expected_rate(lux, rare.replace(leak_on_hz=1e-3, leak_off_hz=2e-3)) - ev.expected_rate(lux, rare)
    np.testing.assert_allclose(added, [[1e-3] * 4, [2e-3] * 4], rtol=1e-4)
    # l >> N: one event per trial at most
    huge = BASE.replace(leak_on_hz=1e7)
    np.testing.assert_allclose(ev.expected_rate(lux, huge).sum(axis=0), n, rtol=1e-12)
    # dead time applies to the sum
    refr = LEAKY.replace(refractory_s=2e-3)
    nu0 = total.sum(axis=0)
    np.testing.assert_allclose(ev.expected_rate(lux, refr), total / (1 + nu0 * 2e-3), rtol=1e-12)


def test_tiny_background_no_warnings():
    import warnings

    p = BASE.replace(leak_off_hz=1e-300, leak_on_hz=0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = ev.expected_rate(np.array([0.0, 1.0, 1e6]), p)
    assert np.all(np.isfinite(r)) and np.all(r >= 0)


def test_parameter_validation():
    with pytest.raises(ParameterError, match="hot_pixel_fraction"):
        BASE.replace(hot_pixel_fraction=1.5)
    with pytest.raises(ParameterError, match="leak_on_hz"):
        BASE.replace(leak_on_hz=-1.0)
    with pytest.raises(ParameterError, match="hot_pixel_on_fraction"):
        BASE.replace(hot_pixel_on_fraction=2.0)


@pytest.mark.parametrize("refractory_s", [0.0, 3e-3])
@pytest.mark.long
def test_renewal_and_counts_match_closed_form(refractory_s):
    params = LEAKY.replace(refractory_s=refractory_s)
    lux = np.tile(np.array([0.0, 0.2, 2.0, 30.0]).repeat(50), (20, 1))  # (20, 200)
    rate = ev.expected_rate(lux, params)
    duration = 20.0
    events = ev.simulate_events(lux, params, duration, rng=11, method="renewal")
    counts = ev.count_events(events, lux.shape)
    for col in range(4):  # each illuminance on its own
        sel = slice(col * 50, (col + 1) * 50)
        _mean_rate_check(counts[:, :, sel], rate[:, :, sel], duration, f"renewal lux col {col}")
    exact = ev.sample_counts(lux, params, duration, rng=12)
    for col in range(4):
        sel = slice(col * 50, (col + 1) * 50)
        _mean_rate_check(exact[:, :, sel], rate[:, :, sel], duration, f"sample_counts col {col}")
    pois = ev.sample_counts(lux, params, duration, rng=13, distribution="poisson")
    _mean_rate_check(pois, rate, duration, "poisson")


def test_count_variance_is_binomial_without_dead_time():
    # i.i.d. trials: a pixel's count over M trials is Binomial(M, P_on) for ON
    params = BASE.replace(leak_on_hz=5.0, leak_off_hz=1.0)
    lux = np.full((100, 100), 0.0)
    duration = 10.0
    counts = ev.sample_counts(lux, params, duration, rng=5)
    m = params.trial_rate_hz * duration
    p_on = ev.expected_rate(lux[:1, :1], params)[0, 0, 0] / params.trial_rate_hz
    var = m * p_on * (1 - p_on)
    sample_var = counts[0].var(ddof=1)
    se = var * math.sqrt(2.0 / (counts[0].size - 1))
    assert abs(sample_var - var) < K * se


@pytest.mark.parametrize("fast", [True, False])
def test_trial_tier_matches_closed_form(monkeypatch, fast):
    monkeypatch.setattr(sim, "TRIAL_FAST_STATIC", fast)
    params = LEAKY.replace(refractory_s=2e-3)
    lux = np.tile(np.array([0.0, 3.0]).repeat(40), (15, 1))
    duration = 6.0
    events = ev.simulate_events(lux, params, duration, rng=3, method="trials")
    counts = ev.count_events(events, lux.shape)
    rate = ev.expected_rate(lux, params)
    for sel in (slice(0, 40), slice(40, 80)):
        _mean_rate_check(counts[:, :, sel], rate[:, :, sel], duration, f"trials fast={fast}")


@pytest.mark.parametrize("regularity", [0.0, 1.0])
def test_trial_tier_changing_scene_background_follows_lux(regularity):
    # a pixel that alternates between two illuminances every 0.5 s: the background follows the input
    # illuminance trial by trial (a regular timer's pending interval is rescaled when the intensity changes),
    # so the mean rate is the time average of the two closed-form rates. The photon comparison of a changing
    # pixel is not the static one (its reference lags), so it is made negligible: many photons (relative
    # fluctuations 1e-3) and thresholds (3) far above the level change (log 9 = 2.2).
    params = BASE.replace(eps_pos=3.0, eps_neg=3.0, photons_per_lux=1e6, leak_on_hz=1.0, leak_off_hz=0.5,
                          leak_on_hz_per_lux=0.5, leak_regularity=regularity)
    shape = (30, 40)
    levels = [1.0, 9.0]
    frames, times = [], []
    for k in range(13):
        frames += [np.full(shape, levels[k % 2])] * 2
        times += [0.5 * k, 0.5 * k + 0.5 - 1e-6]
    events, signal = ev.simulate_video(np.array(frames), np.array(times), params, rng=8, return_labels=True)
    counts = ev.count_events(events[~signal], shape, 0, int(round(times[-1] * 1e6)))
    rate = (7 * ev.expected_rate(np.full(shape, levels[0]), params)  # 7 half-seconds at 1 lux, 6 at 9 lux
            + 6 * ev.expected_rate(np.full(shape, levels[1]), params)) / 13
    _mean_rate_check(counts, rate, times[-1], f"changing scene, regularity {regularity}")


def test_noise_stream_follows_illuminance():
    params = LEAKY
    shape = (40, 50)
    stream = ev.NoiseStream(shape, params, rng=21)
    parts, expected = [], np.zeros((2, *shape))
    for k, lux in enumerate([0.0, 5.0, 50.0, 0.0]):
        lux_map = np.full(shape, lux)
        parts.append(stream.advance(lux_map, (k + 1) * 2_000_000))
        expected += ev.expected_rate(lux_map, params) * 2.0
    counts = ev.count_events(np.concatenate(parts), shape)
    _mean_rate_check(counts, expected / 8.0, 8.0, "NoiseStream")


def test_reference_simulator_agrees():
    params = LEAKY.replace(refractory_s=4e-3, leak_sigma=0.6, hot_pixel_fraction=0.05, hot_pixel_rate_hz=30.0,
                           hot_pixel_on_fraction=0.7)
    lux = np.full((10, 40), 1.5)
    bg = ev.draw_background(lux.shape, params, rng=9)
    duration = 4.0
    ref = ev.count_events(naive_static_events(lux, params, duration, rng=10, background=bg), lux.shape)
    fast = ev.count_events(ev.simulate_events(lux, params, duration, rng=11, background=bg), lux.shape)
    rate = ev.expected_rate(lux, params, background=bg)
    _mean_rate_check(ref, rate, duration, "naive reference")
    _mean_rate_check(fast, rate, duration, "renewal with maps")
    # hot pixels alone: their counts follow their own rates
    hot = bg[1] > 0
    _mean_rate_check(fast[:, hot], rate[:, hot], duration, "hot pixels")


def test_background_maps_are_reproducible_and_exact():
    params = BASE.replace(leak_on_hz=1.0, leak_sigma=0.8, hot_pixel_fraction=0.013, hot_pixel_rate_hz=50.0,
                          hot_pixel_sigma=0.5)
    a = ev.draw_background((100, 100), params, rng=4)
    b = ev.draw_background((100, 100), params, rng=4)
    c = ev.draw_background((100, 100), params, rng=5)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert int(np.count_nonzero(a[1])) == 130  # round(0.013 * 10000), exactly
    # spread factor: log-normal of mean 1 and log-sd 0.8
    logs = np.log(a[0].ravel())
    assert abs(logs.std(ddof=1) - 0.8) < K * 0.8 / math.sqrt(2 * (logs.size - 1))
    assert abs(a[0].mean() - 1.0) < K * math.sqrt(math.expm1(0.64)) / 100
    # same seed, same events, whatever the number of threads
    lux = np.full((60, 70), 2.0)
    e1 = ev.simulate_events(lux, params, 2.0, rng=7, threads=1)
    e2 = ev.simulate_events(lux, params, 2.0, rng=7, threads=2)
    np.testing.assert_array_equal(e1, e2)


def test_all_terms_zero_is_bit_identical_and_costs_no_draws():
    # a spread with no background rate changes nothing (no draw is made, so the stream key is the same)
    lux = np.full((30, 30), 2.0)
    plain = ev.simulate_events(lux, BASE, 3.0, rng=2)
    idle = BASE.replace(leak_sigma=0.7, hot_pixel_sigma=1.0, hot_pixel_on_fraction=0.9, hot_pixel_fraction=0.1)
    np.testing.assert_array_equal(plain, ev.simulate_events(lux, idle, 3.0, rng=2))
    np.testing.assert_array_equal(ev.sample_counts(lux, BASE, 3.0, rng=2), ev.sample_counts(lux, idle, 3.0, rng=2))
    frames = np.stack([lux, 3 * lux])
    np.testing.assert_array_equal(ev.simulate_video(frames, [0, 1.0], BASE, rng=2),
                                  ev.simulate_video(frames, [0, 1.0], BASE.replace(pr_tau_s_at_1lux=0.0), rng=2))


# --------------------------------------------------------------------------------------
# photoreceptor bandwidth
# --------------------------------------------------------------------------------------
# so many photons that the photon comparison never fires (relative fluctuations ~1e-5 against thresholds of 0.2)
QUIET = ev.NoiseParams(eps_pos=0.2, eps_neg=0.2, bias_pr=10.0, trial_rate_hz=1000.0, photons_per_lux=1e9)


def _step_video(lux1, lux2, t_step_s=0.1, t_end_s=0.4, shape=(1, 4)):
    frames = np.stack([np.full(shape, lux1), np.full(shape, lux1), np.full(shape, lux2), np.full(shape, lux2)])
    return frames, np.array([0.0, t_step_s, t_step_s + 1e-6, t_end_s])


def _expected_signal_times(lux1, lux2, params, t_step_s):
    """Signal event times of a step by an independent recursion of the documented filter."""
    b, dt = params.bias_pr, 1e6 / params.trial_rate_hz
    lam1, lam2 = params.photons_per_trial(lux1), params.photons_per_trial(lux2)
    alpha = -math.expm1(-lam2 * (1.0 / params.trial_rate_hz) / (params.pr_tau_s_at_1lux * params.photons_per_lux))
    level_in = math.log(lam2 + b)
    level = level_prev = math.log(lam1 + b)
    ref = level
    times = []
    j = int(round(t_step_s * 1e6 / dt))
    while len(times) < 40 and j * dt < 0.4e6:
        level_prev, level = level, level + alpha * (level_in - level)
        if abs(level - level_in) <= 1e-9:
            level = level_in
        while level - ref >= params.eps_pos:
            target = ref + params.eps_pos
            phi = (target - level_prev) / (level - level_prev)
            times.append(j * dt + min(max(phi, 0.0), 1.0) * dt)
            ref = target
        j += 1
    return np.floor(times).astype(np.int64)


@pytest.mark.parametrize("lux2", [20.0, 200.0])
def test_bandwidth_delays_signal_events_as_the_filter_predicts(lux2):
    params = QUIET.replace(pr_tau_s_at_1lux=1.0)  # tau = 1 s / lux: 50 ms at 20 lux, 5 ms at 200 lux
    frames, times = _step_video(2.0, lux2)
    events, signal = ev.simulate_video(frames, times, params, rng=1, return_labels=True)
    assert not np.any(~signal)  # photon noise is negligible at these photon counts
    expected = _expected_signal_times(2.0, lux2, params, 0.1)
    for x in range(4):
        got = events["t"][events["x"] == x]
        np.testing.assert_array_equal(got, expected)
    # without the filter every crossing happens in the trial of the step
    fast, _ = ev.simulate_video(frames, times, QUIET, rng=1, return_labels=True)
    assert fast["t"].max() < 101_000
    assert expected.size == fast[fast["x"] == 0].size  # same number of crossings, only later


def test_bandwidth_darker_pixels_lag_more():
    params = QUIET.replace(pr_tau_s_at_1lux=1.0)
    lags = []
    for lux1 in (1.0, 10.0):
        frames, times = _step_video(lux1, 3 * lux1)
        events, _ = ev.simulate_video(frames, times, params, rng=1, return_labels=True)
        lags.append(np.median(events["t"]) - 100_000)
    assert lags[0] > 5 * lags[1]


def test_bandwidth_leaves_static_pixels_alone():
    shape = (20, 30)
    static = np.full(shape, 2.0)
    frames = np.stack([static, static, static])
    frames[1:, :, :5] = 9.0  # a few changing pixels; the rest are static
    base = BASE.replace(refractory_s=1e-3)
    a = ev.simulate_video(frames, [0.0, 0.5, 2.0], base, rng=4)
    b = ev.simulate_video(frames, [0.0, 0.5, 2.0], base.replace(pr_tau_s_at_1lux=0.3), rng=4)
    keep_a, keep_b = a[a["x"] >= 5], b[b["x"] >= 5]
    np.testing.assert_array_equal(keep_a, keep_b)
    assert not np.array_equal(a[a["x"] < 5], b[b["x"] < 5])


# --------------------------------------------------------------------------------------
# regular (near-periodic) background: leak_regularity
# --------------------------------------------------------------------------------------
def _slow_regular_rate(p_on, p_off, l_on, l_off, n_hz, refr_trials, r):
    """E[gap] by direct summation of P(min(G_p, L) > m) over m (an independent route to the closed form)."""
    p = p_on + p_off
    a = 1 - math.exp(-(l_on + l_off) / n_hz)
    m_mean = 1 / a
    d = r * (m_mean - 1)
    a2 = 1 / (1 + (1 - r) * (m_mean - 1))
    d0 = math.floor(d)
    phi = d - d0
    total = 0.0
    photon = 0.0
    for m in range(0, 200000):
        surv_l = 0.0
        for dd, w in ((d0, 1 - phi), (d0 + 1, phi)):
            surv_l += w * (1.0 if m <= dd else (1 - a2) ** (m - dd))
        term = (1 - p) ** m * surv_l
        total += term
        if term < 1e-18:
            break
    photon = p * total
    nu = n_hz / (refr_trials + total)
    share_l = l_on / (l_on + l_off)
    return nu * (photon * p_on / p + (1 - photon) * share_l), nu * (photon * p_off / p + (1 - photon) * (1 - share_l))


@pytest.mark.parametrize("r", [0.3, 1.0])
def test_regular_closed_form_against_direct_sum(r):
    params = LEAKY.replace(leak_regularity=r, refractory_s=2e-3)
    lux = np.array([0.0, 1.0, 20.0])
    got = ev.expected_rate(lux, params)
    lam = params.photons_per_trial(lux)
    p_on = event_probability(lam, params.eps_pos, params.bias_pr)
    p_off = event_probability(lam, params.eps_neg, params.bias_pr)
    l_on, l_off = ev.background_rate(lux, params)
    for i in range(lux.size):
        want = _slow_regular_rate(p_on[i], p_off[i], l_on[i], l_off[i], params.trial_rate_hz,
                                  params.refractory_us * 1e-6 * params.trial_rate_hz, r)
        np.testing.assert_allclose(got[:, i], want, rtol=1e-10)


def test_regularity_zero_is_the_poisson_background():
    lux = np.array([0.0, 1.0, 20.0])
    a = ev.expected_rate(lux, LEAKY)
    b = ev.expected_rate(lux, LEAKY.replace(leak_regularity=1e-12))
    np.testing.assert_allclose(a, b, rtol=1e-9)


@pytest.mark.parametrize("r", [0.5, 1.0])
def test_regular_tiers_match_closed_form(monkeypatch, r):
    params = LEAKY.replace(leak_regularity=r, refractory_s=3e-3)
    lux = np.tile(np.array([0.0, 3.0]).repeat(60), (15, 1))
    rate = ev.expected_rate(lux, params)
    duration = 10.0
    tiers = {
        "renewal": ev.count_events(ev.simulate_events(lux, params, duration, rng=1), lux.shape),
        "sample_counts": ev.sample_counts(lux, params, duration, rng=2),
        "trials": ev.count_events(ev.simulate_events(lux, params, duration, rng=3, method="trials"), lux.shape),
    }
    for name, counts in tiers.items():
        for sel in (slice(0, 60), slice(60, 120)):
            _mean_rate_check(counts[:, :, sel], rate[:, :, sel], duration, f"{name} r={r}")


def test_periodic_background_counts_are_floor_or_ceil():
    # no photon noise (huge thresholds), periodic leak: a window of T holds floor(T l) or floor(T l) + 1 events,
    # and the stationary start makes the mean exactly T l (a binomial draw of the extra event per pixel)
    params = ev.NoiseParams(eps_pos=5, eps_neg=5, bias_pr=2, trial_rate_hz=1000, photons_per_lux=4,
                            leak_on_hz=0.3, leak_regularity=1.0)
    counts = ev.sample_counts(np.zeros((100, 100)), params, 4.5, rng=3)[0].ravel()
    assert set(np.unique(counts)) <= {1, 2}
    frac = 0.3 * 4.5 - 1  # share of pixels with the extra event
    assert abs(np.mean(counts == 2) - frac) < K * math.sqrt(frac * (1 - frac) / counts.size)
    # the Poisson background with the same rate is far more dispersed
    poisson_counts = ev.sample_counts(np.zeros((100, 100)), params.replace(leak_regularity=0.0), 4.5, rng=3)[0]
    assert poisson_counts.var() > 4 * counts.var()


def test_regular_noise_stream_and_changing_scene():
    params = LEAKY.replace(leak_regularity=0.7)
    shape = (40, 50)
    stream = ev.NoiseStream(shape, params, rng=21)
    parts, expected = [], np.zeros((2, *shape))
    for k, lux in enumerate([0.0, 5.0, 50.0, 0.0]):
        lux_map = np.full(shape, lux)
        parts.append(stream.advance(lux_map, (k + 1) * 2_000_000))
        expected += ev.expected_rate(lux_map, params) * 2.0
    counts = ev.count_events(np.concatenate(parts), shape)
    _mean_rate_check(counts, expected / 8.0, 8.0, "NoiseStream regular")


@pytest.mark.parametrize("refractory_s", [0.0, 2e-3])
@pytest.mark.long
def test_regular_background_starts_in_the_steady_state(refractory_s):
    # a window much shorter than the background period, with photon noise resetting the timer: the count of a
    # pixel that starts in its steady state has mean rate * T (a start that ignored the photon resets gave
    # 100 sigma too many background events in the benchmark)
    params = ev.load_preset("evk3-hd").replace(leak_on_hz=0.02, leak_off_hz=0.14, leak_regularity=1.0,
                                               refractory_s=refractory_s)
    lux = np.tile(np.array([0.2, 1.2, 7.3]).repeat(100), (100, 1))
    rate = ev.expected_rate(lux, params)
    for name, counts in (("sample_counts", ev.sample_counts(lux, params, 2.0, rng=3)),
                         ("trials", ev.count_events(ev.simulate_events(lux, params, 2.0, rng=4, method="trials"),
                                                    lux.shape))):
        for col in range(3):
            sel = slice(col * 100, (col + 1) * 100)
            _mean_rate_check(counts[:, :, sel], rate[:, :, sel], 2.0, f"{name} steady start, column {col}")
