"""The trial tier's geometric jump over pixels that are static within a window (issue 16, part 2).

The per-trial algorithm (two Poisson draws per trial, ``evnoise.simulate.TRIAL_FAST_STATIC =
False``) is kept as the slow reference; the fast path must be statistically indistinguishable
from it and from the exact closed form (fixed seeds, k-sigma tolerances and KS tests), and
give the same output for any thread count.
"""

import math

import numpy as np
import pytest
from scipy import stats

import evnoise as ev
import evnoise.simulate as es

K = 5.0
PARAMS = ev.NoiseParams(eps_pos=0.9, eps_neg=1.0, bias_pr=1.7, trial_rate_hz=20.0, photons_per_lux=1.0,
                        refractory_s=0.07)
LEVELS = np.array([0.3, 2.0, 8.0])
PER_LEVEL = 2000
WIDTH = 50


def _bands(levels=LEVELS, per_level=PER_LEVEL):
    return np.repeat(levels, per_level // WIDTH)[:, None] * np.ones((1, WIDTH))


def _counts(events, shape, duration_s, levels=LEVELS, per_level=PER_LEVEL):
    c = ev.count_events(events, shape, 0, int(round(duration_s * 1e6)))
    return c.reshape(2, len(levels), per_level)


def _gaps(events, shape):
    order = np.lexsort((events["t"], events["y"].astype(np.int64) * shape[1] + events["x"]))
    e = events[order]
    pix = e["y"].astype(np.int64) * shape[1] + e["x"]
    return np.diff(e["t"])[pix[1:] == pix[:-1]]


@pytest.fixture
def reference(monkeypatch):
    """Run a callable with the per-trial reference algorithm."""

    def run(fn):
        monkeypatch.setattr(es, "TRIAL_FAST_STATIC", False)
        try:
            return fn()
        finally:
            monkeypatch.setattr(es, "TRIAL_FAST_STATIC", True)

    return run


def _assert_same_law(ca, cb):
    for pol in range(2):
        for lev in range(ca.shape[1]):
            a, b = ca[pol, lev], cb[pol, lev]
            se = math.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size)
            assert abs(a.mean() - b.mean()) <= K * se + 1e-12, (pol, lev, a.mean(), b.mean(), se)
            assert stats.ks_2samp(a, b, method="asymp").pvalue > 1e-4, (pol, lev)  # counts: ties, no exact p


def test_static_pixels_match_per_trial_reference_and_closed_form(reference):
    lux = _bands()
    duration = 20.0  # 400 trials
    fast = ev.simulate_events(lux, PARAMS, duration, rng=31, method="trials")
    slow = reference(lambda: ev.simulate_events(lux, PARAMS, duration, rng=32, method="trials"))
    cf, cs = _counts(fast, lux.shape, duration), _counts(slow, lux.shape, duration)
    _assert_same_law(cf, cs)
    # the exact dead-time rate of the closed form
    rate = ev.expected_rate(LEVELS, PARAMS)  # (2, levels)
    for pol in range(2):
        c = cf[pol]
        se = c.std(axis=1, ddof=1) / math.sqrt(c.shape[1])
        assert np.all(np.abs(c.mean(axis=1) - rate[pol] * duration) <= K * se), pol
    # refractory period and the distribution of the gaps between a pixel's events
    gf, gs = _gaps(fast, lux.shape), _gaps(slow, lux.shape)
    assert gf.min() >= PARAMS.refractory_us
    assert stats.ks_2samp(gf, gs).pvalue > 1e-4


def test_fast_path_is_taken_and_differs_in_bits_only(reference):
    """Same seed: different bits (a different sampler ran), same event count law (checked above)."""
    lux = _bands(per_level=200)
    fast = ev.simulate_events(lux, PARAMS, 3.0, rng=5, method="trials")
    slow = reference(lambda: ev.simulate_events(lux, PARAMS, 3.0, rng=5, method="trials"))
    assert fast.size > 100 and slow.size > 100
    assert not np.array_equal(fast, slow)


def test_mismatch_thresholds_match_reference(reference):
    params = PARAMS.replace(eps_sigma=0.1)
    lux = _bands()
    duration = 15.0
    thr = ev.draw_thresholds(lux.shape, params, rng=4)
    fast = ev.simulate_events(lux, params, duration, rng=41, method="trials", thresholds=thr)
    slow = reference(lambda: ev.simulate_events(lux, params, duration, rng=42, method="trials", thresholds=thr))
    _assert_same_law(_counts(fast, lux.shape, duration), _counts(slow, lux.shape, duration))


def _video():
    """Bands; the lower half of each band steps up at 2 s, then stays (static within later windows)."""
    base = _bands()
    frames = [base, base.copy(), base * 3.0, base * 3.0]
    frames[2][:, WIDTH // 2:] = base[:, WIDTH // 2:]
    frames[3][:, WIDTH // 2:] = base[:, WIDTH // 2:]
    frames[2][:, : WIDTH // 2] = base[:, : WIDTH // 2] * 3.0
    return np.stack(frames), np.array([0.0, 2.0, 2.2, 12.0])


def test_video_matches_reference_in_changing_and_static_regions(reference, monkeypatch):
    monkeypatch.setattr(es, "TARGET_PIXEL_TRIALS_PER_WINDOW", 20_000)  # many windows: jumps start mid-run
    frames, times = _video()
    shape = frames.shape[1:]
    fast, lab_f = ev.simulate_video(frames, times, PARAMS, rng=51, method="trials", return_labels=True)
    slow, lab_s = reference(lambda: ev.simulate_video(frames, times, PARAMS, rng=52, method="trials",
                                                       return_labels=True))
    duration = times[-1]
    for events, labels in ((fast, lab_f), (slow, lab_s)):
        assert np.all(np.diff(events["t"]) >= 0)
        assert labels.sum() > 0  # the step gives signal events
    noise_f, noise_s = fast[lab_f == 0], slow[lab_s == 0]
    cf = ev.count_events(noise_f, shape, 0, int(duration * 1e6)).reshape(2, len(LEVELS), -1, WIDTH)
    cs = ev.count_events(noise_s, shape, 0, int(duration * 1e6)).reshape(2, len(LEVELS), -1, WIDTH)
    for half in (slice(0, WIDTH // 2), slice(WIDTH // 2, WIDTH)):
        a = cf[..., half].reshape(2, len(LEVELS), -1)
        b = cs[..., half].reshape(2, len(LEVELS), -1)
        _assert_same_law(a, b)
    sig_f = ev.count_events(fast[lab_f == 1], shape, 0, int(duration * 1e6))
    sig_s = ev.count_events(slow[lab_s == 1], shape, 0, int(duration * 1e6))
    for pol in range(2):
        se = math.sqrt(sig_f[pol].var(ddof=1) / sig_f[pol].size + sig_s[pol].var(ddof=1) / sig_s[pol].size)
        assert abs(sig_f[pol].mean() - sig_s[pol].mean()) <= K * se + 1e-12


@pytest.mark.long
def test_video_same_output_for_any_thread_count(monkeypatch):
    monkeypatch.setattr(es, "TARGET_PIXEL_TRIALS_PER_WINDOW", 20_000)
    from evnoise import _engine

    monkeypatch.setattr(_engine, "CHUNK_PIXELS", 700)
    frames, times = _video()
    runs = [ev.simulate_video(frames, times, PARAMS, rng=6, method="trials", threads=t) for t in (1, 2, 3)]
    for r in runs[1:]:
        assert np.array_equal(r, runs[0])


def test_still_scene_trial_tier_does_not_depend_on_the_windows(monkeypatch):
    """The trial tier's jump over a still pixel dropped an event that fell beyond its window and drew it again in
    the next: the events depended on where time was cut, so on the sensor's size (rows 0..7 of a 200-row sensor
    differed from an 8-row sensor's). An event beyond the window now stays pending."""
    g = np.random.default_rng(5)
    lux = g.uniform(0.2, 20, (40, 48))
    runs = []
    for per_window in (40_000_000, 30_720, 9_001):
        monkeypatch.setattr(es, "TARGET_PIXEL_TRIALS_PER_WINDOW", per_window)
        runs.append(np.concatenate(list(ev.iter_events(lux, PARAMS, 3.0, rng=3, method="trials"))))
    assert runs[0].size > 1000
    for r in runs[1:]:
        np.testing.assert_array_equal(r, runs[0])
    monkeypatch.setattr(es, "TARGET_PIXEL_TRIALS_PER_WINDOW", 7 * lux.size)  # 7 trials a window; 8 rows: 35
    top = ev.simulate_events(lux[:8], PARAMS, 3.0, rng=3, method="trials")  # fewer pixels: other windows
    whole = ev.simulate_events(lux, PARAMS, 3.0, rng=3, method="trials")
    np.testing.assert_array_equal(top, whole[whole["y"] < 8])


@pytest.mark.long
def test_video_trial_tier_does_not_depend_on_the_windows(monkeypatch):
    """A changing pixel jumps over its runs of trials at one light; the runs were the windows' (a window whose frames
    all had one light), so the events depended on the windows and on the number of changing pixels. Runs are now
    the trials' own (between frames of one light), whatever the windows: random piecewise-constant videos, frames
    faster and slower than the trials, cut into windows of 1, 3, 7 trials and one window."""
    for seed in range(3):
        g = np.random.default_rng(seed)
        n_frames = 9
        looks = g.uniform(0.3, 30, (3, 12, 16))
        frames = np.stack([looks[g.integers(0, 3)] if g.uniform() < 0.7 else g.uniform(0.3, 30, (12, 16))
                           for _ in range(n_frames)])
        keep = g.uniform(size=(12, 16)) < 0.5
        frames[:, keep] = frames[0, keep]  # these pixels never change: one long run
        frames[1:, 0, 0] = 2 * frames[0, 0, 0]  # at least one pixel changes (a video, not a still scene)
        times = np.cumsum(np.r_[0.0, g.uniform(0.005, 4.0, n_frames - 1)])  # 0.1 to 80 trials apart
        runs = []
        for per_window in (40_000_000, 7 * 192, 3 * 192, 192):
            monkeypatch.setattr(es, "TARGET_PIXEL_TRIALS_PER_WINDOW", per_window)
            runs.append(ev.simulate_video(frames, times, PARAMS, rng=seed, method="trials"))
        assert runs[0].size > 200
        for r in runs[1:]:
            np.testing.assert_array_equal(r, runs[0])


@pytest.mark.parametrize("eps_sigma", [0.0, 0.05])
@pytest.mark.long
def test_video_jump_probabilities_do_not_depend_on_the_windows_at_any_batch_size(monkeypatch, eps_sigma):
    """The closed form takes another path (equal to ~1e-11, not bit for bit) for batches from
    ``evnoise.model.TABLE_MIN_SIZE`` values on: a video whose jumps' probabilities were evaluated per window would
    get other bits when windows hold other numbers of pixels at one light. 4,800 changing pixels on a few lights,
    uniform thresholds (the table) and spread ones (the grouped sum), cut into windows of 1 and 5 trials and one, and
    a crop of the sensor."""
    g = np.random.default_rng(7)
    shape = (60, 80)
    looks = g.choice([0.5, 2.0, 9.0, 40.0], size=(4, *shape))
    frames = looks[[0, 0, 1, 1, 2, 3, 3, 0]]  # pairs of one light for all pixels (4,800 values) and for some
    frames[:, 0, 0] = [1, 2, 3, 4, 5, 6, 7, 8]  # a pixel that changes in every frame
    times = np.array([0.0, 0.3, 0.35, 0.9, 1.0, 1.6, 1.7, 2.5])
    params = PARAMS.replace(eps_sigma=eps_sigma)
    thresholds = ev.draw_thresholds(shape, params, rng=9)  # (given: drawn ones are drawn for the whole sensor)
    runs = []
    for per_window in (10**9, 5 * 4800, 4800):
        monkeypatch.setattr(es, "TARGET_PIXEL_TRIALS_PER_WINDOW", per_window)
        runs.append(ev.simulate_video(frames, times, params, rng=5, method="trials", thresholds=thresholds))
    assert runs[0].size > 1000
    for r in runs[1:]:
        np.testing.assert_array_equal(r, runs[0])
    top = ev.simulate_video(frames[:, :20], times, params, rng=5, method="trials",  # a crop: other batches
                            thresholds=thresholds[:, :20])
    np.testing.assert_array_equal(top, runs[-1][runs[-1]["y"] < 20])
