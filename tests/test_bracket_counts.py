"""Counts with threshold mismatch decided by brackets (issue 33, item 4; :mod:`evnoise._bracket`).

The bracketed path must give, bit for bit, the counts of the plain path (each pixel's closed form evaluated
on its own thresholds, then the renewal kernel): compared here on scenes that exercise both ends of the
argument (dark pixels, pixels that fire at almost every trial, long refractory periods, background
activity, thresholds given by the caller), with the plain path forced by turning the bracket off.
"""

from __future__ import annotations

import numpy as np
import pytest

import evnoise as ev
from evnoise import _bracket


def _scene(shape=(48, 64), levels=12, top_lux=15.0, seed=0):
    rng = np.random.default_rng(seed)
    return np.linspace(0.0, top_lux, levels)[rng.integers(0, levels, shape)]


def _both(monkeypatch, lux, params, duration_s, **kwargs):
    """``(bracketed counts, plain counts, undecided pixels)`` of one call (same seed)."""
    seen = []
    real = _bracket.bracketed_counts

    def spy(*args, **kw):
        out = real(*args, **kw)
        seen.append(None if out is None else out[2])
        return out

    monkeypatch.setattr(_bracket, "bracketed_counts", spy)
    fast = ev.sample_counts(lux, params, duration_s, **kwargs)
    assert len(seen) == 1, "the bracketed path was not tried"
    monkeypatch.setattr(_bracket, "applies", lambda *a, **k: False)
    plain = ev.sample_counts(lux, params, duration_s, **kwargs)
    return fast, plain, seen[0]


EVK3 = ev.load_preset("evk3-hd")


@pytest.mark.parametrize("case", ["evk3-hd", "no-background", "long-refractory", "busy", "long-window"])
def test_bracketed_counts_equal_the_plain_path_bit_for_bit(monkeypatch, case):
    lux = _scene()
    params, duration_s = EVK3.replace(eps_sigma=0.03), 1.0
    if case == "no-background":
        params = ev.NoiseParams(eps_pos=0.2, eps_neg=0.25, eps_sigma=0.05, bias_pr=3.0, trial_rate_hz=1000.0,
                                photons_per_lux=5.0)
        duration_s = 0.02
    elif case == "long-refractory":
        params = params.replace(refractory_s=0.05)
    elif case == "busy":  # small thresholds, bright: p near 1 per trial for some pixels
        params = ev.NoiseParams(eps_pos=0.02, eps_neg=0.02, eps_sigma=0.01, bias_pr=0.0, trial_rate_hz=200.0,
                                photons_per_lux=2.0)
    elif case == "long-window":
        duration_s = 20.0
    fast, plain, undecided = _both(monkeypatch, lux, params, duration_s, rng=7)
    assert np.array_equal(fast, plain)
    assert plain.sum() > 100  # the comparison has events in it
    assert undecided is not None and undecided < 0.5 * lux.size  # and the brackets decided most pixels


def test_many_events_per_pixel_take_the_plain_path(monkeypatch):
    """At ~50 events per pixel a lattice step moves the count: the brackets would decide few pixels, so the
    bracketed path declines (None) and the plain path gives the counts."""
    params = ev.NoiseParams(eps_pos=0.2, eps_neg=0.25, eps_sigma=0.05, bias_pr=3.0, trial_rate_hz=1000.0,
                            photons_per_lux=5.0)
    fast, plain, undecided = _both(monkeypatch, _scene(), params, 1.0, rng=7)
    assert undecided is None and np.array_equal(fast, plain) and plain.sum() > 1e4


def test_thresholds_given_by_the_caller(monkeypatch):
    lux = _scene(seed=3)
    params = EVK3  # eps_sigma = 0: the caller's thresholds are the only spread
    rng = np.random.default_rng(5)
    thresholds = np.stack([params.eps_pos + 0.02 * rng.standard_normal(lux.shape),
                           params.eps_neg + 0.02 * rng.standard_normal(lux.shape)]).clip(0.01)
    fast, plain, _ = _both(monkeypatch, lux, params, 2.0, rng=11, thresholds=thresholds)
    assert np.array_equal(fast, plain)


def test_where_the_bracket_does_not_apply_the_plain_path_runs():
    lam = np.repeat(np.arange(4.0), 100)
    eps = (np.linspace(0.15, 0.25, lam.size), np.linspace(0.1, 0.3, lam.size))
    params = EVK3.replace(eps_sigma=0.03)
    assert _bracket.applies(lam, params, eps, None)
    # one polarity at one threshold: no spread to build its lattice on (h would be 0)
    assert not _bracket.applies(lam, params, (np.full(lam.size, 0.2), eps[1]), None)
    assert not _bracket.applies(lam, params, eps, (np.ones(lam.size), np.zeros(lam.size)))  # background maps
    assert not _bracket.applies(lam, params.replace(leak_regularity=0.5), eps, None)  # the regular timer
    assert not _bracket.applies(np.arange(400.0), params, eps, None)  # no shared light levels
    same = (np.full(lam.size, 0.2), np.full(lam.size, 0.2))
    assert not _bracket.applies(lam, params, same, None)  # nominal thresholds: the plain path is cheap


def test_lattice_index_brackets_every_threshold():
    rng = np.random.default_rng(2)
    eps = np.concatenate([rng.uniform(0.01, 1.0, 10_000), [0.1, 0.3, 0.7]])
    for h in (0.03 / 16, 1e-3 / 3, 0.1 / 7):
        j = _bracket._lattice_index(eps, h)
        assert np.all(j * h <= eps) and np.all(eps <= (j + 1.0) * h)
