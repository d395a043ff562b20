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
    """``(bracketed counts, plain counts, pixels left to the closed form)`` of one call (same seed); None for the
    last when the bracketed path declined."""
    seen = []
    real = _bracket.bracketed_counts

    def spy(*args, **kw):
        out = real(*args, **kw)
        seen.append(None if out is None else out[3])
        return out

    monkeypatch.setattr(_bracket, "bracketed_counts", spy)
    fast = ev.sample_counts(lux, params, duration_s, **kwargs)
    assert len(seen) == 1, "the bracketed path was not tried"
    monkeypatch.setattr(_bracket, "applies", lambda *a, **k: False)
    plain = ev.sample_counts(lux, params, duration_s, **kwargs)
    return fast, plain, seen[0]


EVK3 = ev.load_preset("evk3-hd")


@pytest.mark.parametrize("case", ["evk3-hd", "no-background", "long-refractory", "busy", "long-window"])
@pytest.mark.long
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
    fast, plain, exact = _both(monkeypatch, lux, params, duration_s, rng=7)
    assert np.array_equal(fast, plain)
    assert plain.sum() > 100  # the comparison has events in it
    assert exact is not None and exact < 0.01 * lux.size  # and the brackets decided (nearly) every pixel


def test_many_events_per_pixel_take_the_plain_path(monkeypatch):
    """At ~50 events per pixel a lattice step moves the count: the brackets would decide few pixels, so the
    bracketed path declines (None) and the plain path gives the counts."""
    params = ev.NoiseParams(eps_pos=0.2, eps_neg=0.25, eps_sigma=0.05, bias_pr=3.0, trial_rate_hz=1000.0,
                            photons_per_lux=5.0)
    fast, plain, exact = _both(monkeypatch, _scene(), params, 1.0, rng=7)
    assert exact is None and np.array_equal(fast, plain) and plain.sum() > 1e4


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


def test_lattice_cell_brackets_every_threshold():
    from evnoise._kernels.mismatch import lattice_cell

    rng = np.random.default_rng(2)
    eps = np.concatenate([rng.uniform(0.01, 1.0, 10_000), [0.1, 0.3, 0.7]])
    for h in (0.03 / 16, 1e-3 / 3, 0.1 / 7):
        # 1 / h rounded both ways: the cell must not depend on how the reciprocal was rounded
        for inv_h in (1.0 / h, np.nextafter(1.0 / h, 0.0), np.nextafter(1.0 / h, 2.0 / h)):
            j = np.array([lattice_cell(e, h, inv_h) for e in eps])
            assert np.all(j * h <= eps) and np.all(eps <= (j + 1.0) * h)


@pytest.mark.parametrize("lam, b", [(1e-3, 0.0), (0.7, 3.0), (26.4, 106.8), (967.0, 106.8), (2e4, 50.0), (40.0, 0.0)])
def test_window_sums_bracket_the_closed_form(lam, b):
    """The sums a level's table gives (lattice points and pixels' own sums) bracket the closed form's ``p`` at
    every threshold between their two ``c``, tightly: the reference is :func:`evnoise.event_probability` (its own
    sum over photon counts, summed and truncated its own way)."""
    from evnoise._kernels import mismatch as K

    eps = np.concatenate([np.linspace(1e-4, 0.5, 400), [0.01, 0.14, 0.16, 0.3]])
    c = np.expm1(eps)
    c_lo, c_hi = c.min() * (1 - 1e-12), c.max() * (1 + 1e-12)
    geo = np.zeros(5, dtype=np.int64)
    t_lo = np.zeros(2)
    K.level_geometry(lam, b, np.array([c_lo, c_lo]), np.array([c_hi, c_hi]), K.WINDOW_ATOL, geo, t_lo)
    assert geo[0] == K.LEVEL_TABLE
    n = int(geo[4] - geo[1] + 1)
    pmf, sf = np.empty(n), np.empty(n)
    K.fill_level_table(lam, int(geo[1]), pmf, sf)
    want = ev.event_probability(np.full(eps.size, lam), eps, b)
    for ci, p in zip(c, want):
        up, dn = K.window_sums(ci * (1 - K.C_MARGIN), ci * (1 + K.C_MARGIN), b, int(geo[1]), int(geo[2]), pmf, sf,
                               K.WINDOW_ATOL)
        upper, lower = up + t_lo[0], dn
        assert lower * (1 - K.BRACKET_WIDEN) <= p <= upper * (1 + K.BRACKET_WIDEN) + K.BRACKET_ABS
        # and the bracket is tight: only the left-out tails and the rounding between its ends
        assert upper - lower <= 3 * K.WINDOW_ATOL + 1e-11 * p


def test_same_counts_for_any_thread_count():
    lux = _scene(shape=(96, 80), seed=4)
    params = EVK3.replace(eps_sigma=0.03)
    runs = [ev.sample_counts(lux, params, 2.0, rng=3, threads=t) for t in (1, 2, 3)]
    assert all(np.array_equal(runs[0], r) for r in runs[1:]) and runs[0].sum() > 100


@pytest.mark.parametrize("outliers", [True, False])
def test_thresholds_and_levels_beyond_the_tables_take_the_closed_form(monkeypatch, outliers):
    """A threshold far beyond the lattice (its own sums would run past its level's table) and a light level too
    bright to tabulate (``lam`` ~ 6e6 photons per trial) are left to the closed form; the counts stay those of the
    plain path."""
    lux = _scene(seed=5)
    lux.flat[[3, 70, 500, 901, 2000]] = 1e5  # one more level, far brighter
    params = EVK3
    rng = np.random.default_rng(6)
    thresholds = np.stack([params.eps_pos + 0.03 * rng.standard_normal(lux.shape),
                           params.eps_neg + 0.03 * rng.standard_normal(lux.shape)]).clip(0.01)
    # beyond the lattice (3.5 standard deviations) but inside the tables (8): their own sums decide them
    thresholds[0].flat[20] = params.eps_pos + 6 * 0.03
    thresholds[1].flat[21] = max(params.eps_neg - 5 * 0.03, 0.01)
    if outliers:
        thresholds[0].flat[[10, 11]] = 3.0
        thresholds[1].flat[12] = 2.5
    fast, plain, exact = _both(monkeypatch, lux, params, 5.0, rng=2, thresholds=thresholds)
    assert np.array_equal(fast, plain) and plain.sum() > 100
    assert exact == (8 if outliers else 5)  # the five bright pixels and the three thresholds
