"""Issue 33, part 1: the closed form is evaluated once per distinct (lam, thresholds), with the same bits.

A static field with few distinct photon counts (a flat field, an 8-bit image) is evaluated once per value
and scattered; the closed form's path (exact sum for small arrays, Chebyshev table for large ones) stays
the one the whole field would take. Each check compares, with ``np.array_equal``, against the per-pixel
evaluation (``model.MAX_LEVELS = 0``, what earlier versions did).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import evnoise as ev
from evnoise import _engine, model
from evnoise._kernels import chebyshev
from evnoise._kernels.levels import find_levels


def _fields():
    g = np.random.default_rng(33)
    img = g.integers(0, 256, (180, 320)).astype(np.uint8)
    return {
        "flat 0.01 lux": np.full((180, 320), 0.01),
        "flat 2 lux": np.full((180, 320), 2.0),
        "flat 300 lux": np.full((180, 320), 300.0),
        "8-bit image": img / 255.0 * 18.0,
        "8-bit image, small (exact path)": img[:40, :50] / 255.0 * 18.0,
        "random float field": g.uniform(0.0, 20.0, (180, 320)),
        "few levels in a random field": g.choice([0.0, 0.5, 7.0, 1e4], (180, 320)),
    }


def _per_pixel(monkeypatch, fn):
    with monkeypatch.context() as m:
        m.setattr(model, "MAX_LEVELS", 0)
        return fn()


@pytest.mark.parametrize("name", list(_fields()))
@pytest.mark.long
def test_probabilities_once_per_level_are_bit_identical(name, monkeypatch):
    lux = _fields()[name]
    params = ev.load_preset("evk3-hd")
    lam = params.photons_per_trial(lux)
    for eps in (params.eps_pos, params.eps_neg, 0.05, 1.5):
        for fn in (model.event_probability, model.log_event_probability):
            new = fn(lam, eps, params.bias_pr)
            old = _per_pixel(monkeypatch, lambda: fn(lam, eps, params.bias_pr))
            assert np.array_equal(new, old), (name, eps, fn.__name__)


def _timer_params():
    p = ev.load_preset("dvs128")
    return dataclasses.replace(p, eps_sigma=0.0, leak_sigma=0.0, hot_pixel_fraction=0.0)


@pytest.mark.parametrize("preset", ["evk3-hd", "timer"])
@pytest.mark.parametrize("name", list(_fields()))
def test_static_inputs_once_per_level_are_bit_identical(name, preset, monkeypatch):
    """Probabilities, background, dead time and the regular timer: every renewal input, bit for bit."""
    params = _timer_params() if preset == "timer" else ev.load_preset(preset)
    lam = params.photons_per_trial(_fields()[name]).ravel()
    eps_on, eps_off = np.full(lam.size, params.eps_pos), np.full(lam.size, params.eps_neg)
    new = _engine.static_inputs(lam, params, eps_on, eps_off, None)
    old = _per_pixel(monkeypatch, lambda: _engine.static_inputs(lam, params, eps_on, eps_off, None))
    for a, b in zip(new, old):
        assert (a is None) == (b is None)
        if a is not None:
            assert a.shape == b.shape and a.flags.c_contiguous
            assert np.array_equal(a.view(np.uint64), b.view(np.uint64)), name


def test_per_pixel_maps_are_not_grouped():
    """Thresholds that differ between pixels, or background maps, keep the per-pixel evaluation."""
    lam = np.full(5000, 10.0)
    eps = np.full(5000, 0.2)
    assert _engine._scene_levels(lam, eps, eps, None) is not None
    eps2 = eps.copy()
    eps2[7] = 0.21
    assert _engine._scene_levels(lam, eps2, eps, None) is None
    assert _engine._scene_levels(lam, eps, eps, (np.ones(5000), np.zeros(5000))) is None


def test_simulated_streams_do_not_depend_on_grouping(monkeypatch):
    lux = _fields()["8-bit image"]
    for preset in ("evk3-hd", "dvs128"):
        new = ev.simulate_events(lux, preset, 0.2, rng=5)
        old = _per_pixel(monkeypatch, lambda: ev.simulate_events(lux, preset, 0.2, rng=5))
        assert new.size > 0 and np.array_equal(new, old)


def test_same_path_values_pads_only_for_the_table():
    levels = np.array([1.0, 2.0])
    assert np.array_equal(model.same_path_values(levels, 10), levels)
    padded = model.same_path_values(levels, 10 * model.TABLE_MIN_SIZE)
    assert padded.size == model.TABLE_MIN_SIZE and np.array_equal(padded[:2], levels) and (padded[2:] == 2.0).all()


def test_find_levels_is_exact_and_gives_up():
    g = np.random.default_rng(1)
    values = g.choice(np.array([0.0, -0.0, 1.5, 1e300, 5e-324]), 10_000)
    levels, inverse = find_levels(values, 16)
    assert levels.size == 5 and inverse.dtype == np.int32
    assert np.array_equal(levels[inverse].view(np.uint64), values.view(np.uint64))  # -0.0 kept apart
    assert find_levels(g.random(10_000), 100) is None
    levels, inverse = find_levels(np.zeros(0), 4)
    assert levels.size == 0 and inverse.size == 0


@pytest.mark.long
def test_serial_and_parallel_table_evaluation_agree():
    """The one-thread kernel for few values is the parallel one's body: same bits, direct panels included."""
    g = np.random.default_rng(2)
    lam = np.concatenate([10.0 ** g.uniform(-19, 8, 3000), [0.0, np.inf, 1e-300, 3e7]])
    table = model._table_for(float(np.expm1(0.1)), 5.0)
    table.evaluate(lam)
    serial, parallel = np.empty(lam.size), np.empty(lam.size)
    certify = np.ones(table.last_unit - table.first_unit + 1, dtype=np.bool_)  # certified panels where built
    args = (*table._arrays, certify, table.first_unit, table.c, table.b)
    for skip in ((-np.inf, np.inf), (-760.0, 100.0)):
        chebyshev._evaluate_serial(lam, *args, *skip, serial)
        chebyshev._evaluate(lam, *args, *skip, parallel)
        assert np.array_equal(serial.view(np.uint64), parallel.view(np.uint64))
