"""``sample_counts`` with reset memory (issue 32): the counts of the memory tier's own events, and the memory
model's closed-form rate for the Poisson / negative-binomial variants."""

from __future__ import annotations

import numpy as np
import pytest

import evnoise as ev
from evnoise.terms import memory

K_SIGMA = 5.0
MEM = ev.NoiseParams(eps_pos=0.5, eps_neg=0.6, bias_pr=1.0, trial_rate_hz=1000.0, photons_per_lux=5.0,
                     refractory_s=3e-4, reset_memory=0.7)


def test_exact_counts_are_those_of_the_event_stream_with_the_same_seed():
    """``distribution="exact"`` counts what ``simulate_events`` emits with the same seed, pixel for pixel (a
    different key, window cut or polarity mapping would break the equality)."""
    lux = np.array([[0.2, 1.0, 4.0, 20.0]] * 3)
    for seed in (1, 7):
        counts = ev.sample_counts(lux, MEM, 2.0, rng=seed)
        events = ev.simulate_events(lux, MEM, 2.0, rng=seed)
        np.testing.assert_array_equal(counts, ev.count_events(events, lux.shape))
        assert counts.sum() > 100  # the comparison is not between two empty maps
    assert not np.array_equal(ev.sample_counts(lux, MEM, 2.0, rng=1), ev.sample_counts(lux, MEM, 2.0, rng=2))


@pytest.mark.parametrize("distribution", ["exact", "poisson", "negative-binomial"])
def test_mean_counts_follow_the_memory_closed_form(distribution):
    """Over many independent pixels the mean count per polarity is the stationary rate of the Markov renewal
    closed form times the duration (within 5 standard errors of the pixels' own spread), and differs from the
    memoryless rate there (so the memory is what is counted)."""
    lux = np.full((60, 100), 5.0)
    duration = 3.0
    kw = {"nb_shape": 200.0} if distribution == "negative-binomial" else {}
    counts = ev.sample_counts(lux, MEM, duration, rng=11, distribution=distribution, **kw)
    want = memory.memory_statistics(5.0, MEM).rate_hz * duration  # (2,) [ON, OFF]
    memoryless = ev.expected_rate(5.0, MEM.replace(reset_memory=0.0)) * duration
    for pol in (0, 1):
        c = counts[pol].ravel().astype(float)
        se = c.std(ddof=1) / np.sqrt(c.size)
        assert abs(c.mean() - want[pol]) <= K_SIGMA * se, (pol, c.mean(), want[pol], se)
        assert abs(memoryless[pol] - want[pol]) > 2 * K_SIGMA * se  # the two models are told apart here


def test_counts_with_memory_are_the_events_counts_with_mismatch_and_the_timer():
    """Threshold mismatch and the regular timer are modelled: the counts are the events' (same seed); the Poisson
    variant of a pixel with the timer is about the closed form's rate."""
    lux = np.full((4, 4), 1.0)
    for params in (MEM.replace(eps_sigma=0.05), MEM.replace(leak_on_hz=20.0, leak_regularity=0.5)):
        np.testing.assert_array_equal(ev.sample_counts(lux, params, 1.0, rng=1),
                                      ev.count_events(ev.simulate_events(lux, params, 1.0, rng=1), lux.shape))
    timed = MEM.replace(leak_on_hz=20.0, leak_regularity=0.5)
    big = np.full((50, 50), 1.0)
    counts = ev.sample_counts(big, timed, 2.0, rng=2, distribution="poisson")
    want = memory.memory_statistics(1.0, timed).rate_hz * 2.0
    for pol in (0, 1):
        c = counts[pol].ravel().astype(float)
        assert abs(c.mean() - want[pol]) <= K_SIGMA * c.std(ddof=1) / np.sqrt(c.size), (pol, c.mean(), want[pol])


def test_dataset_counts_mode_with_memory_counts_the_memory_tier():
    """The dataset generator's counts mode with reset memory (refused before) takes ``sample_counts``, never the
    memoryless direct sampler, and gives the events mode's counts for the same seed."""
    from evnoise.generators.config import PairConfig
    from evnoise.generators.pairs import CountSampler, quantise

    params = MEM.replace(refractory_s=0.0)  # refractory 0: without memory the direct sampler would be used
    counts_cfg = PairConfig(sensor_shape=(16, 16), binning=1, params=params, seed=0, mode="counts")
    events_cfg = PairConfig(sensor_shape=(16, 16), binning=1, params=params, seed=0, mode="events")
    sampler = CountSampler(counts_cfg)
    assert sampler.method == "sample_counts"
    assert CountSampler(PairConfig(sensor_shape=(16, 16), binning=1, params=params.replace(reset_memory=0.0),
                                   seed=0, mode="counts")).method == "direct-trials"
    codes, _ = quantise(np.linspace(0.2, 18, 256).reshape(16, 16), counts_cfg.lux_step)
    got = sampler.sample(codes, 500_000, seed=7)
    want = CountSampler(events_cfg).sample(codes, 500_000, seed=7)
    np.testing.assert_array_equal(got, want)
    assert got.sum() > 100
