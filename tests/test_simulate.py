"""The simulator's tiers against the exact closed form and against each other (fixed seeds, k-sigma)."""

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

import evnoise as ev
from evnoise.testing import naive_static_events

K = 5.0  # tolerance in standard errors
# 20 trials/s: one trial is exactly 50 ms, so a duration is a whole number of trials
PARAMS = ev.NoiseParams(eps_pos=0.9, eps_neg=1.0, bias_pr=1.7, trial_rate_hz=20.0, photons_per_lux=1.0)
LEVELS = np.array([0.05, 0.5, 2.0, 6.0, 20.0])  # lux
PER_LEVEL = 1500


def flat_fields(levels=LEVELS, per_level=PER_LEVEL, width=50):
    """An image made of horizontal bands, one band per illuminance level."""
    rows = per_level // width
    return np.repeat(levels, rows)[:, None] * np.ones((1, width))


def per_level_counts(counts, levels=LEVELS, per_level=PER_LEVEL, width=50):
    rows = per_level // width
    return counts.reshape(2, len(levels), rows * width)


def events_counts(events, shape, duration_s):
    return ev.count_events(events, shape, 0, int(round(duration_s * 1e6)))


@pytest.mark.parametrize("tier", ["renewal", "trials", "naive"])
def test_flat_field_rates_match_exact_closed_form(tier):
    duration = 20.0  # 400 trials
    lux = flat_fields()
    if tier == "naive":
        events = naive_static_events(lux, PARAMS, duration, rng=11)
    else:
        events = ev.simulate_events(lux, PARAMS, duration, rng=11, method=tier)
    counts = per_level_counts(events_counts(events, lux.shape, duration))
    n_trials = duration * PARAMS.trial_rate_hz
    lam = PARAMS.photons_per_trial(LEVELS)
    for pol, eps in enumerate((PARAMS.eps_pos, PARAMS.eps_neg)):
        p = ev.event_probability(lam, eps, PARAMS.bias_pr)
        total = counts[pol].sum(axis=1)
        expected = PER_LEVEL * n_trials * p
        se = np.sqrt(PER_LEVEL * n_trials * p * (1 - p))  # binomial per pixel, exact for whole trials
        assert np.all(np.abs(total - expected) <= K * se + 1e-9), (tier, pol, total, expected, se)


def test_gaussian_form_would_fail_the_same_check():
    """Sanity check that the rate test can fail: the paper's eq. 3 is rejected by the simulator."""
    duration = 20.0
    lux = flat_fields()
    counts = per_level_counts(events_counts(ev.simulate_events(lux, PARAMS, duration, rng=11), lux.shape, duration))
    lam = PARAMS.photons_per_trial(LEVELS)
    p = ev.event_probability(lam, PARAMS.eps_pos, PARAMS.bias_pr, method="gaussian")
    n = PER_LEVEL * duration * PARAMS.trial_rate_hz
    assert np.any(np.abs(counts[0].sum(axis=1) - n * p) > K * np.sqrt(n * p))


def _gaps_and_polarities(events, shape):
    order = np.lexsort((events["t"], events["y"].astype(np.int64) * shape[1] + events["x"]))
    e = events[order]
    pix = e["y"].astype(np.int64) * shape[1] + e["x"]
    same = pix[1:] == pix[:-1]
    return np.diff(e["t"])[same], e["p"]


def test_refractory_gaps_and_dead_time_rate():
    params = PARAMS.replace(refractory_s=0.12)  # 120 ms: skips 2-3 trials after every event
    lux = flat_fields(levels=np.array([2.0, 5.0]), per_level=2000)
    duration = 30.0
    for method in ("renewal", "trials"):
        events = ev.simulate_events(lux, params, duration, rng=3, method=method)
        gaps, _ = _gaps_and_polarities(events, lux.shape)
        assert gaps.min() >= params.refractory_us
        counts = per_level_counts(events_counts(events, lux.shape, duration), levels=[2.0, 5.0], per_level=2000)
        rate = ev.expected_rate(np.array([2.0, 5.0]), params)  # (2, levels)
        for pol in range(2):
            c = counts[pol]
            se = c.std(axis=1, ddof=1) / math.sqrt(c.shape[1])
            assert np.all(np.abs(c.mean(axis=1) - rate[pol] * duration) <= K * se), (method, pol)
        # and the dead time matters: the rate without it is rejected
        nodead = ev.expected_rate(np.array([2.0, 5.0]), PARAMS)
        total = counts.sum(axis=0)
        se = total.std(axis=1, ddof=1) / math.sqrt(total.shape[1])
        assert np.all(np.abs(total.mean(axis=1) - nodead.sum(axis=0) * duration) > K * se)


def test_tiers_are_statistically_indistinguishable():
    params = PARAMS.replace(refractory_s=0.07)
    lux = flat_fields(levels=np.array([1.0, 4.0]), per_level=2500)
    duration = 25.0
    a = ev.simulate_events(lux, params, duration, rng=21, method="renewal")
    b = ev.simulate_events(lux, params, duration, rng=22, method="trials")
    ca = per_level_counts(events_counts(a, lux.shape, duration), levels=[1, 4], per_level=2500)
    cb = per_level_counts(events_counts(b, lux.shape, duration), levels=[1, 4], per_level=2500)
    for pol in range(2):
        diff = ca[pol].mean(axis=1) - cb[pol].mean(axis=1)
        se = np.sqrt(ca[pol].var(axis=1, ddof=1) / ca.shape[2] + cb[pol].var(axis=1, ddof=1) / cb.shape[2])
        assert np.all(np.abs(diff) <= K * se)
        # the whole per-pixel count distribution, not only the mean
        for lev in range(2):
            assert stats.ks_2samp(ca[pol, lev], cb[pol, lev]).pvalue > 1e-4
    gaps_a, pol_a = _gaps_and_polarities(a, lux.shape)
    gaps_b, pol_b = _gaps_and_polarities(b, lux.shape)
    assert stats.ks_2samp(gaps_a, gaps_b).pvalue > 1e-4
    pa, pb = pol_a.mean(), pol_b.mean()
    pooled = (pol_a.sum() + pol_b.sum()) / (pol_a.size + pol_b.size)
    se = math.sqrt(pooled * (1 - pooled) * (1 / pol_a.size + 1 / pol_b.size))
    assert abs(pa - pb) <= K * se


def test_events_are_sorted_within_duration_and_typed():
    events = ev.simulate_events(flat_fields(), PARAMS, 3.0, rng=1, t_start_us=1_000_000)
    assert events.dtype == ev.EVENT_DTYPE
    assert np.all(np.diff(events["t"]) >= 0)
    assert events["t"].min() >= 1_000_000 and events["t"].max() < 4_000_000
    assert set(np.unique(events["p"])) <= {0, 1}
    # timestamps are not a comb on trial starts
    phase = (events["t"] - 1_000_000) % 50_000
    assert stats.kstest(phase / 50_000, "uniform").pvalue > 1e-4


def test_same_seed_same_events_and_independent_of_windows(monkeypatch):
    from evnoise import simulate as sim

    lux = flat_fields(levels=np.array([1.0, 3.0]), per_level=1000)
    a = ev.simulate_events(lux, PARAMS, 10.0, rng=5)
    assert np.array_equal(a, ev.simulate_events(lux, PARAMS, 10.0, rng=5))
    assert not np.array_equal(a, ev.simulate_events(lux, PARAMS, 10.0, rng=6))
    monkeypatch.setattr(sim, "TARGET_EVENTS_PER_WINDOW", 500)  # many more windows
    monkeypatch.setattr(sim, "EVENTS_PER_PIXEL_PER_WINDOW", 0)
    from evnoise import _engine

    monkeypatch.setattr(_engine, "CHUNK_PIXELS", 37)  # other chunking
    parts = list(ev.iter_events(lux, PARAMS, 10.0, rng=5))
    assert len(parts) > 5
    assert np.array_equal(a, np.concatenate(parts))


_THREAD_SCRIPT = """
import hashlib, numpy as np, evnoise as ev
p = ev.NoiseParams(eps_pos=0.9, eps_neg=1.0, bias_pr=1.7, trial_rate_hz=20.0, photons_per_lux=1.0,
                   refractory_s=0.01, eps_sigma=0.05)
lux = np.linspace(0.1, 20, 200 * 180).reshape(180, 200)
h = hashlib.sha256()
for method in ("renewal", "trials"):
    h.update(ev.simulate_events(lux, p, 3.0, rng=42, method=method).tobytes())
frames = np.stack([lux, lux[::-1], lux])
h.update(ev.simulate_video(frames, [0.0, 0.5, 1.0], p, rng=42).tobytes())
h.update(ev.sample_counts(lux, p, 3.0, rng=42).tobytes())
print(h.hexdigest())
"""


@pytest.mark.long
def test_same_output_for_one_and_two_threads():
    digests = []
    for threads in ("1", "2"):
        env = dict(__import__("os").environ, NUMBA_NUM_THREADS=threads)
        out = subprocess.run([sys.executable, "-c", _THREAD_SCRIPT], env=env, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        digests.append(out.stdout.strip())
    assert digests[0] == digests[1]


def test_sample_counts_exact_equals_counted_events():
    """The counts-only tier draws the same per-pixel streams as the event tier."""
    params = PARAMS.replace(refractory_s=0.03)
    lux = flat_fields(levels=np.array([0.5, 3.0]), per_level=1000)
    counts = ev.sample_counts(lux, params, 7.0, rng=9)
    events = ev.simulate_events(lux, params, 7.0, rng=9)
    assert np.array_equal(counts, ev.count_events(events, lux.shape))


def test_sample_counts_binomial_marginal_chi_square():
    lux = np.full((100, 100), 2.0)
    duration = 10.0  # 200 whole trials
    counts = ev.sample_counts(lux, PARAMS, duration, rng=4)
    n = int(duration * PARAMS.trial_rate_hz)
    for pol, eps in enumerate((PARAMS.eps_pos, PARAMS.eps_neg)):
        p = float(ev.event_probability(PARAMS.photons_per_trial(2.0), eps, PARAMS.bias_pr))
        x = counts[pol].ravel()
        support = np.arange(0, n + 1)
        expected = stats.binom.pmf(support, n, p) * x.size
        observed = np.bincount(x, minlength=n + 1)[: n + 1]
        keep = expected >= 5
        obs = np.append(observed[keep], observed[~keep].sum())
        exp = np.append(expected[keep], expected[~keep].sum())
        assert stats.chisquare(obs, exp * obs.sum() / exp.sum()).pvalue > 1e-4


def test_sample_counts_poisson_and_negative_binomial():
    lux = np.full((120, 120), 3.0)
    duration = 5.0
    mean = ev.expected_rate(lux, PARAMS) * duration
    pois = ev.sample_counts(lux, PARAMS, duration, rng=1, distribution="poisson")
    for pol in range(2):
        mu = mean[pol, 0, 0]
        x = pois[pol].ravel()
        assert abs(x.mean() - mu) <= K * math.sqrt(mu / x.size)
        assert abs(x.var(ddof=1) - mu) <= K * mu * math.sqrt(2.0 / x.size) * 2
    r = 0.5
    nb = ev.sample_counts(lux, PARAMS, duration, rng=2, distribution="negative-binomial", nb_shape=r)
    for pol in range(2):
        mu = mean[pol, 0, 0]
        x = nb[pol].ravel().astype(float)
        var = mu + mu**2 / r
        assert abs(x.mean() - mu) <= K * math.sqrt(var / x.size)
        # NB variance estimate: its standard error from the distribution's fourth moment
        m4 = stats.nbinom.stats(r, r / (r + mu), moments="k") * var**2 + 3 * var**2
        assert abs(x.var(ddof=1) - var) <= K * math.sqrt((m4 - var**2) / x.size)


def test_negative_binomial_takes_the_poisson_limit_nb_shape_gives():
    """``calibration.nb_shape`` is ``inf`` where counts are not over-dispersed (no threshold mismatch), and
    ``sample_counts`` refused any shape that was not finite: its own output could not be passed on."""
    from evnoise.calibration import nb_shape

    lux = np.full((120, 120), 3.0)
    duration = 5.0
    r = nb_shape(lux, PARAMS, duration)
    assert np.isinf(r).all()
    counts = ev.sample_counts(lux, PARAMS, duration, rng=3, distribution="negative-binomial", nb_shape=r)
    mean = ev.expected_rate(lux, PARAMS) * duration
    for pol in range(2):  # Poisson: mean and variance both mu
        mu = mean[pol, 0, 0]
        x = counts[pol].ravel().astype(float)
        assert abs(x.mean() - mu) <= K * math.sqrt(mu / x.size)
        assert abs(x.var(ddof=1) - mu) <= K * math.sqrt((mu + 2 * mu**2) / x.size)
    # mixed: ON at the Poisson limit, OFF over-dispersed (r = 0.5), each with its own variance
    r = 0.5
    mixed = ev.sample_counts(lux, PARAMS, duration, rng=4, distribution="negative-binomial",
                             nb_shape=np.array([np.inf, r])[:, None, None])
    for pol, var_of in ((0, lambda mu: mu), (1, lambda mu: mu + mu**2 / r)):
        mu = mean[pol, 0, 0]
        x = mixed[pol].ravel().astype(float)
        assert abs(x.mean() - mu) <= K * math.sqrt(var_of(mu) / x.size)
    x_on, x_off = (mixed[pol].ravel().astype(float) for pol in range(2))
    mu_on, mu_off = mean[0, 0, 0], mean[1, 0, 0]
    assert abs(x_on.var(ddof=1) - mu_on) <= K * math.sqrt((mu_on + 2 * mu_on**2) / x_on.size)
    var = mu_off + mu_off**2 / r
    m4 = stats.nbinom.stats(r, r / (r + mu_off), moments="k") * var**2 + 3 * var**2
    assert abs(x_off.var(ddof=1) - var) <= K * math.sqrt((m4 - var**2) / x_off.size)
    for bad in (np.nan, -np.inf, 0.0):
        with pytest.raises(ev.ParameterError, match="nb_shape"):
            ev.sample_counts(lux, PARAMS, duration, distribution="negative-binomial", nb_shape=bad)


def test_threshold_mismatch_matches_mixture_prediction():
    params = PARAMS.replace(eps_sigma=0.15)
    shape = (150, 150)
    lux = np.full(shape, 2.0)
    duration = 10.0
    n = int(duration * params.trial_rate_hz)
    thr = ev.draw_thresholds(shape, params, rng=31)
    assert abs(thr[0].std() - 0.15) < 0.01 and abs(thr[0].mean() - 0.9) < 0.01
    counts = ev.sample_counts(lux, params, duration, rng=32, thresholds=thr)
    lam = params.photons_per_trial(2.0)
    for pol in range(2):
        p = ev.event_probability(lam, thr[pol], params.bias_pr)  # each pixel's own probability
        mu = n * p
        predicted_var = np.mean(n * p * (1 - p)) + mu.var()  # E[Var | eps] + Var(E | eps)
        x = counts[pol].ravel().astype(float)
        assert abs(x.mean() - mu.mean()) <= K * math.sqrt(predicted_var / x.size)
        m4 = np.mean((x - x.mean()) ** 4)
        assert abs(x.var(ddof=1) - predicted_var) <= K * math.sqrt((m4 - x.var() ** 2) / x.size)
        # and the mismatch is visible: much more variance than a single binomial
        p_nom = float(ev.event_probability(lam, (params.eps_pos, params.eps_neg)[pol], params.bias_pr))
        assert x.var() > 1.5 * n * p_nom * (1 - p_nom)


def test_mismatch_is_drawn_from_rng_when_not_given():
    params = PARAMS.replace(eps_sigma=0.1)
    lux = np.full((40, 40), 2.0)
    a = ev.sample_counts(lux, params, 5.0, rng=np.random.default_rng(8))
    gen = np.random.default_rng(8)  # the thresholds come first from the generator, then the streams
    thr = ev.draw_thresholds(lux.shape, params, rng=gen)
    assert np.array_equal(a, ev.sample_counts(lux, params, 5.0, rng=gen, thresholds=thr))
    assert not np.array_equal(a, ev.sample_counts(lux, params.replace(eps_sigma=0.0), 5.0, rng=8))


# ------------------------------------------------------------------------------ video
def _step_video(lux0, lux1, t_step=1.0, t_end=2.0, shape=(20, 30)):
    frames = np.stack([np.full(shape, lux0), np.full(shape, lux0), np.full(shape, lux1), np.full(shape, lux1)])
    times = np.array([0.0, t_step, t_step + 1e-3, t_end])
    return frames, times


@pytest.mark.parametrize("lux0, lux1", [(100.0, 1000.0), (1000.0, 100.0), (50.0, 400.0)])
def test_step_change_gives_delta_log_over_eps_signal_events(lux0, lux1):
    params = PARAMS.replace(eps_pos=0.5, eps_neg=0.45, refractory_s=1e-3)
    frames, times = _step_video(lux0, lux1)
    events = ev.simulate_video(frames, times, params, rng=2)
    b = params.bias_pr
    delta = math.log(params.photons_per_trial(lux1) + b) - math.log(params.photons_per_trial(lux0) + b)
    pol = 1 if delta > 0 else 0
    eps = params.eps_pos if pol == 1 else params.eps_neg
    expected = math.floor(abs(delta) / eps)
    near = events[(events["t"] >= 0.95e6) & (events["t"] < 1.15e6)]
    counts = ev.count_events(near, frames.shape[1:])
    signal = counts[1 - pol]
    # floor(|delta| / eps) crossings of the mean level; a noise event near the threshold can
    # add one more (the residual |delta| - k eps raises the noise probability of that polarity)
    assert np.all((signal == expected) | (signal == expected + 1)), np.unique(signal)
    assert np.mean(signal == expected) >= 0.9
    assert abs(signal.mean() - abs(delta) / eps) < 1.0
    # opposite polarity: only noise, at most what the still scene gives before and after the step (k sigma; the
    # 0.95 .. 1.0 s at lux0 carry nearly all of it)
    rate = ev.expected_rate(np.array([lux0, lux1]), params)[pol]  # [ON, OFF], as count_events
    noise = signal.size * (rate[0] * 0.05 + rate[1] * 0.15)
    assert counts[pol].sum() <= noise + K * math.sqrt(noise) + 1.0, (counts[pol].sum(), noise)
    gaps, _ = _gaps_and_polarities(near, frames.shape[1:])
    assert gaps.min() >= params.refractory_us


def test_video_labels_mark_signal_events():
    params = PARAMS.replace(eps_pos=0.5, eps_neg=0.45)
    frames, times = _step_video(100.0, 1000.0)
    frames[:, :, :10] = 100.0  # the left third stays static
    events, is_signal = ev.simulate_video(frames, times, params, rng=2, return_labels=True)
    assert is_signal.dtype == bool and is_signal.shape == events.shape
    assert np.array_equal(events, ev.simulate_video(frames, times, params, rng=2))
    static = events["x"] < 10
    assert not is_signal[static].any()  # a static pixel only ever makes noise
    sig = events[is_signal]
    assert np.all(sig["p"] == 1) and np.all(sig["x"] >= 10)
    assert np.all((sig["t"] >= 0.95e6) & (sig["t"] < 1.15e6))
    n_expected = math.floor(math.log((1000 + 1.7) / (100 + 1.7)) / 0.5) * 20 * 20
    assert sig.size == n_expected


def test_video_static_pixels_and_noise_everywhere():
    params = PARAMS
    shape = (30, 40)
    frames = np.full((5, *shape), 3.0)
    frames[2:, :, :20] = 6.0  # the left half brightens, the right half stays static
    times = np.linspace(0, 10.0, 5)
    auto = ev.simulate_video(frames, times, params, rng=4)
    trials = ev.simulate_video(frames, times, params, rng=5, method="trials")
    assert np.all(np.diff(auto["t"]) >= 0)
    for events in (auto, trials):
        counts = ev.count_events(events, shape)
        right = counts[:, :, 20:]
        rate = ev.expected_rate(np.array([3.0]), params)[:, 0]
        for pol in range(2):
            x = right[pol].ravel()
            assert abs(x.mean() - rate[pol] * 10.0) <= K * x.std(ddof=1) / math.sqrt(x.size)
        assert counts[:, :, :20].sum() > 0


def test_video_reproducible_and_independent_of_frame_container():
    frames, times = _step_video(2.0, 8.0, shape=(10, 12))
    a = ev.simulate_video(frames, times, PARAMS, rng=12)
    b = ev.simulate_video([f for f in frames], times, PARAMS, rng=12)
    assert np.array_equal(a, b)
    assert a["t"].min() >= 0 and a["t"].max() < 2_000_000


# ------------------------------------------------------------------------------ stream API
@pytest.mark.long
def test_noise_stream_matches_static_rate_and_merges():
    shape = (60, 60)
    lux = np.full(shape, 2.0)
    stream = ev.NoiseStream(shape, PARAMS, rng=3, t_start_us=500)
    chunks = []
    t = 500
    for k in range(1, 301):  # 300 intervals of 33.333 ms: not aligned with the 50 ms trials
        t_end = 500 + int(round(k * 1e6 / 30))
        out = stream.advance(lux, t_end)
        assert np.all((out["t"] >= t) & (out["t"] < t_end))
        chunks.append(out)
        t = t_end
    events = np.concatenate(chunks)
    assert np.all(np.diff(events["t"]) >= 0)
    counts = ev.count_events(events, shape)
    duration = (t - 500) * 1e-6
    rate = ev.expected_rate(np.array([2.0]), PARAMS)[:, 0]
    for pol in range(2):
        x = counts[pol].ravel()
        assert abs(x.mean() - rate[pol] * duration) <= K * x.std(ddof=1) / math.sqrt(x.size)
    clean = ev.events_from_array(np.array([[600.0, 1, 2, 1], [1e6, 3, 4, 0]]))
    merged = ev.merge_events(clean, events)
    assert merged.size == events.size + 2 and np.all(np.diff(merged["t"]) >= 0)


def test_noise_stream_reuses_the_closed_form_only_while_the_light_is_the_same():
    """The stream keeps the last interval's closed form and reuses it for the same light: the events must be
    those of a stream that recomputes it every time (here: forgets it before each interval)."""
    rng = np.random.default_rng(4)
    lux = rng.uniform(0.1, 10.0, (20, 30))
    one_pixel_brighter = lux.copy()
    one_pixel_brighter[7, 11] *= 0.01  # a change in one pixel must not be missed
    lights = [lux, lux.copy(), one_pixel_brighter, one_pixel_brighter, lux, lux]
    kept = ev.NoiseStream(lux.shape, PARAMS, rng=5)
    fresh = ev.NoiseStream(lux.shape, PARAMS, rng=5)
    for k, light in enumerate(lights, start=1):
        a = kept.advance(light, 400_000 * k)
        fresh._inputs = None
        b = fresh.advance(light, 400_000 * k)
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(kept._inputs[0], PARAMS.photons_per_trial(lux).ravel())  # the last light's


# ------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    "lux, duration, exc",
    [
        (np.full((4, 4), np.nan), 1.0, ev.InputError),
        (np.full((4, 4), -1.0), 1.0, ev.InputError),
        (np.full(4, 1.0), 1.0, ev.InputError),
        (np.full((4, 4), 1.0), 0.0, ev.ParameterError),
        (np.full((4, 4), 1.0), -2.0, ev.ParameterError),
        (np.full((4, 4), 1.0), float("nan"), ev.ParameterError),
        (np.full((4, 4), 1.0), True, ev.ParameterError),  # float(True) is 1: ran for a second
    ],
)
def test_static_bad_input(lux, duration, exc):
    with pytest.raises(exc):
        ev.simulate_events(lux, PARAMS, duration)
    with pytest.raises(exc):
        ev.sample_counts(lux, PARAMS, duration)


def test_other_bad_arguments():
    lux = np.ones((4, 4))
    with pytest.raises(ev.ParameterError, match="method"):
        ev.simulate_events(lux, PARAMS, 1.0, method="fast")
    with pytest.raises(ev.ParameterError, match="rng"):
        ev.simulate_events(lux, PARAMS, 1.0, rng="seed")
    with pytest.raises(ev.ParameterError, match="nb_shape"):
        ev.sample_counts(lux, PARAMS, 1.0, distribution="negative-binomial")
    with pytest.raises(ev.InputError, match="thresholds"):
        ev.sample_counts(lux, PARAMS, 1.0, thresholds=np.ones((2, 3, 3)))


def test_video_bad_input():
    frames = np.ones((3, 4, 4))
    with pytest.raises(ev.InputError, match="shape"):
        ev.simulate_video([np.ones((4, 4)), np.ones((4, 5))], [0.0, 1.0], PARAMS)
    with pytest.raises(ev.InputError, match="increasing"):
        ev.simulate_video(frames, [0.0, 2.0, 1.0], PARAMS)
    with pytest.raises(ev.InputError, match="increasing"):
        ev.simulate_video(frames, [0.0, 1.0, 1.0], PARAMS)
    with pytest.raises(ev.InputError, match="one entry per frame"):
        ev.simulate_video(frames, [0.0, 1.0], PARAMS)
    bad = frames.copy()
    bad[1, 0, 0] = np.nan
    with pytest.raises(ev.InputError, match=r"frames_lux\[1\]"):
        ev.simulate_video(bad, [0.0, 1.0, 2.0], PARAMS)
    with pytest.raises(ev.ParameterError, match="static"):
        ev.simulate_video(np.stack([np.ones((4, 4)), 2 * np.ones((4, 4))]), [0.0, 1.0], PARAMS, method="renewal")
    stream = ev.NoiseStream((4, 4), PARAMS)
    stream.advance(np.ones((4, 4)), 1000)
    with pytest.raises(ev.ParameterError, match="before"):
        stream.advance(np.ones((4, 4)), 500)
    with pytest.raises(ev.InputError, match="shape"):
        stream.advance(np.ones((5, 4)), 2000)


# --------------------------------------------------------------------------------------
# bounded memory for any duration; the size of a run known before it runs (issue 35)
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["auto", "trials"])
def test_windows_are_made_lazily_whatever_the_duration(method):
    import tracemalloc

    import evnoise.simulate as sim
    from evnoise.simulate import EventWindows

    lux = np.full((4, 4), 2.0)
    list(ev.iter_events(lux, PARAMS, 0.5, rng=1, method=method))  # compile outside the measurement
    tracemalloc.start()
    try:
        # 1e7 s: 150 thousand windows of at most 67 s (static), 2.4 million of at most 4.2 s (trials) (the window
        # list alone used to take ~90 MB; 1e12 s: GBs)
        windows = ev.iter_events(lux, PARAMS, 1e7, rng=1, method=method)
        first = next(windows)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    windows.close()
    assert isinstance(windows, EventWindows) and windows.duration_us == 10**13
    assert peak < 5_000_000, peak
    longest = sim.MAX_STATIC_WINDOW_US if method == "auto" else sim.MAX_WINDOW_US
    assert first.size and first["t"].max() < longest  # the first window only
    rate = float(np.sum(ev.expected_rate(lux, PARAMS)))
    assert windows.expected_events == pytest.approx(rate * 1e7, rel=1e-9)


def test_expected_events_match_a_run():
    lux = flat_fields()
    windows = ev.iter_events(lux, PARAMS, 5.0, rng=3)
    expected = windows.expected_events
    n = sum(w.size for w in windows)
    assert abs(n - expected) < K * math.sqrt(expected)
    video = ev.iter_video(np.stack([lux, lux * 1.01]), [0.0, 5.0], PARAMS, rng=3)
    assert video.expected_events == pytest.approx(expected, rel=1e-12)  # noise of the first frame
    video.close()


def test_simulate_events_refuses_what_cannot_fit_in_memory(monkeypatch):
    lux = np.full((16, 16), 2.0)
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "10000")
    with pytest.raises(ev.ParameterError, match=r"would return about [\d,]+ events.*iter_events"):
        ev.simulate_events(lux, PARAMS, 100.0, rng=1)
    with pytest.raises(ev.ParameterError, match="would return about"):
        ev.simulate_events(lux, PARAMS, 100.0, rng=1, method="trials")
    assert ev.simulate_events(lux, PARAMS, 0.05, rng=1).size < 400  # a small run still fits
    monkeypatch.undo()
    with pytest.raises(ev.ParameterError, match="would return about"):  # 1e12 s: refused at once, not run
        ev.simulate_events(lux, PARAMS, 1e12, rng=1)


def test_disk_check_refuses_a_run_that_cannot_fit(tmp_path, monkeypatch):
    import shutil

    from evnoise.simulate import check_disk_space, estimate_file_size

    lux = np.full((64, 64), 2.0)
    huge = ev.iter_events(lux, PARAMS, 1e12, rng=1)  # made lazily: nothing is simulated yet
    with pytest.raises(ev.OutputError, match=r"x\.h5 would be about .* events expected\), more than the .* free"):
        check_disk_space(huge, tmp_path / "x.h5")
    small = ev.iter_events(lux, PARAMS, 1.0, rng=1)
    line = check_disk_space(small, tmp_path / "x.h5")
    assert line.startswith(f"expecting about {small.expected_events:,.0f} events, a file of about")
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage._replace(free=1000))
    with pytest.raises(ev.OutputError, match="more than the 1.0 kB free"):
        check_disk_space(small, tmp_path / "x.csv", "csv")
    # the estimate grows with the events, and with the index of events.h5 (one entry per millisecond)
    assert estimate_file_size(2e6, 10**6) > estimate_file_size(1e6, 10**6) > estimate_file_size(1e6, 10**3)
    assert estimate_file_size(1e6, 10**6, "h5", compression=None) > estimate_file_size(1e6, 10**6)
    assert estimate_file_size(0, 10**15) > 1e12  # 1e12 s of nothing still needs its ms_to_idx


def test_disk_line_of_a_video_says_it_counts_noise_only(tmp_path):
    """A video's expected_events counts its first frame's noise only: a 3000-frame ramp said "expecting about 27
    events" and made 61,000. The line says what the number counts."""
    from evnoise.simulate import check_disk_space

    frames = np.stack([np.full((8, 8), 2.0), np.full((8, 8), 200.0), np.full((8, 8), 2.0)])
    video = ev.iter_video(frames, [0.0, 1.0, 2.0], PARAMS, rng=1)
    assert video.noise_only and not ev.iter_events(frames[0], PARAMS, 2.0, rng=1).noise_only
    line = check_disk_space(video, tmp_path / "x.h5")
    assert line.startswith(f"expecting about {video.expected_events:,.0f} noise events at the first frame's light "
                           f"(the scene's changes add more), a file of about ")
    assert sum(w.size for w in video) > video.expected_events  # the signal events of two large steps on 64 pixels


def test_timestamps_beyond_int64_are_refused():
    with pytest.raises(ev.ParameterError, match="longer than a 64-bit time"):
        ev.iter_events(np.ones((2, 2)), PARAMS, 1e13, rng=1, t_start_us=2**62)
    with pytest.raises(ev.ParameterError, match=r"ends beyond the largest 64-bit timestamp"):
        ev.iter_events(np.ones((2, 2)), PARAMS, 4e12, rng=1, t_start_us=2**62 + 2**61)


@pytest.mark.parametrize("method", ["auto", "trials"])
def test_progress_steps_add_up_to_the_total_without_warnings(monkeypatch, method):
    """``simulate --preset davis346 --duration 20`` printed ``TqdmWarning: clamping frac`` and a negative ETA:
    20 s in 7 windows of float seconds add up to 20.000000000000004 s."""
    import warnings

    import evnoise.simulate as sim

    monkeypatch.setattr(sim, "MAX_WINDOW_US", -(-20_000_000 // 7))  # 7 windows, as davis346 gave
    monkeypatch.setattr(sim, "MAX_STATIC_WINDOW_US", sim.MAX_WINDOW_US)
    totals = []
    from tqdm import tqdm as real_tqdm

    class Spy(real_tqdm):
        def close(self):
            totals.append((self.n, self.total))
            super().close()

    monkeypatch.setattr("tqdm.auto.tqdm", Spy)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        n = sum(w.size for w in ev.iter_events(np.full((4, 4), 2.0), PARAMS, 20.0, rng=1, method=method,
                                                progress=True))
    assert n > 0 and totals and all(done == total for done, total in totals), totals


def test_simulate_video_refuses_what_cannot_fit_in_memory(monkeypatch):
    frames = np.stack([np.full((16, 16), 2.0), np.full((16, 16), 3.0)])
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "10000")
    with pytest.raises(ev.ParameterError, match=r"simulate_video would return about [\d,]+ events.*iter_events"):
        ev.simulate_video(frames, [0.0, 100.0], PARAMS, rng=1)
    monkeypatch.undo()
    with pytest.raises(ev.ParameterError, match="simulate_video would return about"):  # 1e12 s: not run
        ev.simulate_video(frames, [0.0, 1e12], PARAMS, rng=1)


@pytest.mark.parametrize("threads", [0, -3, 1.5, True, "a"])
def test_threads_must_be_a_whole_number_of_at_least_one(threads):
    """The CLI refused --threads 0 / 1.5 / a; the API made 0, -3, 1.5 and True valid counts (max(1, int(x))) and
    raised a bare ValueError for "a"."""
    lux = np.full((4, 4), 2.0)
    calls = [lambda: ev.simulate_events(lux, PARAMS, 0.1, rng=0, threads=threads),
             lambda: ev.sample_counts(lux, PARAMS, 0.1, rng=0, threads=threads),
             lambda: ev.NoiseStream(lux.shape, PARAMS, rng=0, threads=threads),
             lambda: ev.simulate_video(np.stack([lux, lux]), [0.0, 0.1], PARAMS, rng=0, threads=threads)]
    for call in calls:
        with pytest.raises(ev.ParameterError, match="threads must be a whole number >= 1"):
            call()
    assert ev.simulate_events(lux, PARAMS, 0.1, rng=0, threads=np.int64(2)).size >= 0


def test_given_hot_rates_are_held_to_their_limit_and_complex_maps_are_refused():
    """Hot rates of 1e300 passed as maps skipped NoiseParams' limit (1e9 events/s), and a complex illuminance lost
    its imaginary part with a ComplexWarning. Hot rates drawn at extreme spreads stay within the same limit, so what
    draw_background returns is always accepted back. (Thresholds of any size stay valid in a map: the kernels and
    the probability functions take them, tests/test_hostile_inputs.py.)"""
    lux = np.full((30, 40), 2.0)
    hot = np.stack([np.ones((30, 40)), np.full((30, 40), 1e300)])
    with pytest.raises(ev.InputError, match=r"hot rates \(row 1\) must be at most 1e\+09"):
        ev.simulate_events(lux, PARAMS, 0.1, rng=0, background=hot)
    for bad, name in ((lux + 1j, "lux"), (np.full((2, 30, 40), 0.3 + 0j), "thresholds")):
        kwargs = {"thresholds": bad} if name == "thresholds" else {}
        with pytest.raises(ev.InputError, match=f"{name} must be real numbers"):
            ev.simulate_events(bad if name == "lux" else lux, PARAMS, 0.1, rng=0, **kwargs)
    wild = PARAMS.replace(eps_sigma=15.0, hot_pixel_fraction=0.5, hot_pixel_rate_hz=9e8, hot_pixel_sigma=3.0)
    thresholds = ev.draw_thresholds(lux.shape, wild, rng=1)
    background = ev.draw_background(lux.shape, wild, rng=1)
    assert 0 < thresholds.min() and background[1].max() == 1e9
    ev.simulate_events(lux, wild, 1e-4, rng=0, thresholds=thresholds, background=background)


@pytest.mark.parametrize("bad, message", [
    (1e308, "illuminance above 1e.09 lux.*max 1e.308"),  # overflow warnings, then NaN rates
    (1e12, "illuminance above 1e.09 lux"),
    ("3", "must be numbers, got text"),  # NumPy's cast read it as 3.0
    (["1", "2"], "must be numbers, got text"),
    (np.array([2.0, None], dtype=object), "must be numbers, got NoneType"),  # read as NaN
    (np.zeros(2, dtype=[("lux", float)]), "must be numbers, got a structured array"),
    ([[1.0, 2.0], [3.0]], "must be a numeric array"),  # a ragged nesting: NumPy's ValueError
])
def test_illuminance_that_is_no_physical_number_of_lux_is_refused(bad, message):
    """The API takes the illuminance the CLI's options take (at most 1e9 lux, 10,000 times full sunlight): 1e308 lux
    gave overflow warnings and NaN rates; text was read as numbers."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ev.InputError, match=message):
            ev.expected_rate(bad, PARAMS)
        if isinstance(bad, (float, str)):  # the same in a map
            with pytest.raises(ev.InputError, match=message.replace("text", "(text|str)")):
                ev.simulate_events(np.full((2, 2), bad, dtype=object), PARAMS, 0.01, rng=0)
    assert ev.expected_rate(1e9, PARAMS).shape == (2,)  # the limit itself is taken
    from decimal import Decimal  # numbers that are not floats: as float() reads them

    assert np.array_equal(ev.expected_rate(np.array([Decimal("1.5"), np.True_, np.array(2.0)], dtype=object), PARAMS),
                          ev.expected_rate([1.5, 1.0, 2.0], PARAMS))
