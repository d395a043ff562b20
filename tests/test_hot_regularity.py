"""Hot pixels with a timer regularity of their own (``hot_pixel_regularity``).

Real quiet DVS128 windows are fitted best with an ordinary leak close to periodic and Poisson hot pixels
(calibration/README.md); the simulators run that model. The law of the timer (its module doc,
:mod:`evnoise._kernels.background`) is computed here independently: the gap between consecutive events of a
quiet pixel without photon noise is ``L = D + G`` trials (``D`` ``floor(d)`` or ``floor(d) + 1``, ``G``
geometric on 1, 2, ...) plus the difference of two uniform positions inside the trials.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import evnoise as ev

K = 5.0  # standard errors

# a dark pixel (no photons, so no photon noise): only the background fires
QUIET = ev.NoiseParams(eps_pos=0.3, eps_neg=0.3, bias_pr=1.0, trial_rate_hz=1000.0, photons_per_lux=1.0,
                       leak_on_hz=3.0, leak_off_hz=2.0, hot_pixel_fraction=0.25, hot_pixel_rate_hz=20.0,
                       hot_pixel_on_fraction=0.6, leak_regularity=0.8, hot_pixel_regularity=0.0)


def timer_gap_moments(rate_hz, regularity, trial_rate_hz):
    """Mean and variance (s, s^2) of the gap between consecutive background events (module doc of the test)."""
    dt = 1.0 / trial_rate_hz
    m = 1.0 / -math.expm1(-rate_hz * dt)
    d = regularity * (m - 1.0)
    phi = d - math.floor(d)
    a2 = 1.0 / (1.0 + (1.0 - regularity) * (m - 1.0))
    mean_trials = d + 1.0 / a2
    var_trials = phi * (1.0 - phi) + (1.0 - a2) / (a2 * a2) + 1.0 / 6.0
    return mean_trials * dt, var_trials * dt * dt


def gaps_by_pixel(events, width):
    """Gaps (s) between consecutive events of the same pixel and the pixel of each gap."""
    idx = events["y"].astype(np.int64) * width + events["x"]
    order = np.lexsort((events["t"], idx))
    t, i = events["t"][order], idx[order]
    same = i[1:] == i[:-1]
    return np.diff(t)[same] * 1e-6, i[1:][same]


def check_gaps(gaps, rate_hz, regularity, trial_rate_hz, duration_s):
    mean, var = timer_gap_moments(rate_hz, regularity, trial_rate_hz)
    n = gaps.size
    se_mean = math.sqrt(var / n)
    # complete gaps inside a window of T seconds are shorter on average by about mean CV^2 / (T / mean - 1)
    edge = mean * (var / mean ** 2) / (duration_s / mean - 1.0)
    assert abs(gaps.mean() - mean) < K * se_mean + edge, (gaps.mean(), mean, se_mean, edge)
    dev2 = (gaps - gaps.mean()) ** 2
    se_var = dev2.std() / math.sqrt(n)
    assert abs(dev2.mean() - var) < K * se_var + 2 * edge * mean, (dev2.mean(), var, se_var)
    return mean, var


@pytest.mark.parametrize("method, shape, duration_s", [("auto", (32, 32), 200.0), ("trials", (12, 12), 60.0)])
def test_hot_pixels_follow_their_own_timer_and_the_others_theirs(method, shape, duration_s):
    params = QUIET
    bg = ev.draw_background(shape, params, rng=7)
    hot = bg[1].ravel() > 0
    assert 0 < hot.sum() < hot.size
    events = ev.simulate_events(np.zeros(shape), params, duration_s, rng=11, background=bg, method=method)
    gaps, pix = gaps_by_pixel(events, shape[1])
    leak = params.leak_on_hz + params.leak_off_hz
    _, var_hot = check_gaps(gaps[hot[pix]], leak + params.hot_pixel_rate_hz, 0.0, params.trial_rate_hz, duration_s)
    _, var_ord = check_gaps(gaps[~hot[pix]], leak, 0.8, params.trial_rate_hz, duration_s)
    # the two laws differ far beyond the tolerance: a regularity shared by both would be caught
    tied_mean, tied_var = timer_gap_moments(leak + params.hot_pixel_rate_hz, 0.8, params.trial_rate_hz)
    assert tied_var < 0.1 * var_hot
    # counts against the closed form of each pixel (Poisson standard error: the counts are at most as dispersed)
    idx = events["y"].astype(np.int64) * shape[1] + events["x"]
    counts = np.bincount(idx, minlength=hot.size)
    rate = ev.expected_rate(np.zeros(shape), params, background=bg).sum(axis=0).ravel()
    for group in (hot, ~hot):
        want = rate[group].sum() * duration_s
        assert abs(counts[group].sum() - want) < K * math.sqrt(want), (counts[group].sum(), want)
    on_share_hot = np.mean(events["p"][hot[idx]] == 1)
    q = params.leak_on_hz + params.hot_pixel_rate_hz * params.hot_pixel_on_fraction
    q /= leak + params.hot_pixel_rate_hz
    n_hot = int(hot[idx].sum())
    assert abs(on_share_hot - q) < K * math.sqrt(q * (1 - q) / n_hot)


@pytest.mark.parametrize("reset_memory", [0.0, 0.3])
def test_a_timer_for_the_hot_pixels_alone(reset_memory):
    """``leak_regularity = 0`` and regular hot pixels: the ordinary pixels stay Poisson (CV 1). With reset memory
    (its renewal tier; refused before memory ran with the timer) the same in the dark, where the background is all
    there is: the hot pixels' gaps have their timer's mean and variance."""
    params = QUIET.replace(leak_regularity=0.0, hot_pixel_regularity=0.95, reset_memory=reset_memory)
    shape, duration_s = (24, 24), 200.0
    bg = ev.draw_background(shape, params, rng=8)
    hot = bg[1].ravel() > 0
    events = ev.simulate_events(np.zeros(shape), params, duration_s, rng=12, background=bg)
    gaps, pix = gaps_by_pixel(events, shape[1])
    leak = params.leak_on_hz + params.leak_off_hz
    check_gaps(gaps[hot[pix]], leak + params.hot_pixel_rate_hz, 0.95, params.trial_rate_hz, duration_s)
    check_gaps(gaps[~hot[pix]], leak, 0.0, params.trial_rate_hz, duration_s)


def test_tied_by_default_is_the_same_stream_as_the_same_value_given():
    lux = np.linspace(0.0, 20.0, 300).reshape(15, 20)
    tied = QUIET.replace(hot_pixel_regularity=-1.0)
    same = QUIET.replace(hot_pixel_regularity=QUIET.leak_regularity)
    for method in ("auto", "trials"):
        a = ev.simulate_events(lux, tied, 5.0, rng=3, method=method)
        b = ev.simulate_events(lux, same, 5.0, rng=3, method=method)
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ev.expected_rate(lux, tied, mismatch="mean"),
                                  ev.expected_rate(lux, same, mismatch="mean"))


def test_noise_stream_runs_the_same_model():
    shape, duration_s = (16, 16), 100.0
    bg = ev.draw_background(shape, QUIET, rng=9)
    hot = bg[1].ravel() > 0
    stream = ev.NoiseStream(shape, QUIET, rng=13, background=bg)
    parts = [stream.advance(np.zeros(shape), int((i + 1) * 10e6)) for i in range(10)]
    events = np.concatenate(parts)
    gaps, pix = gaps_by_pixel(events, shape[1])
    leak = QUIET.leak_on_hz + QUIET.leak_off_hz
    check_gaps(gaps[hot[pix]], leak + QUIET.hot_pixel_rate_hz, 0.0, QUIET.trial_rate_hz, duration_s)
    check_gaps(gaps[~hot[pix]], leak, 0.8, QUIET.trial_rate_hz, duration_s)


@pytest.mark.parametrize("off", [dict(hot_pixel_fraction=0.0), dict(hot_pixel_rate_hz=0.0)])
def test_without_hot_pixels_every_pixel_keeps_the_leaks_regularity(off):
    """A hot regularity with no hot pixels changes nothing: the trial kernel (changing scenes) once ran every pixel
    at the hot value there (found in review)."""
    params = QUIET.replace(leak_regularity=0.2, hot_pixel_regularity=0.95, **off)
    shape, duration_s = (10, 10), 60.0
    leak = params.leak_on_hz + params.leak_off_hz
    for method in ("auto", "trials"):
        events = ev.simulate_events(np.zeros(shape), params, duration_s, rng=21, method=method)
        gaps, _ = gaps_by_pixel(events, shape[1])
        check_gaps(gaps, leak, 0.2, params.trial_rate_hz, duration_s)
    frames = np.zeros((2,) + shape)
    events = ev.simulate_video(frames, np.array([0.0, duration_s]), params, rng=22)
    gaps, _ = gaps_by_pixel(events, shape[1])
    check_gaps(gaps, leak, 0.2, params.trial_rate_hz, duration_s)
