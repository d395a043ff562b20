"""Issue 30: a noise term is one module in one registry; a run's set-up is made once per call.

A toy term registered at run time (a constant extra rate, the shape of any new background term) must
show up everywhere the registry is iterated: the closed form, the renewal and trial tiers, the counts
sampler, the noise stream and calibration's population-mean intensities.
"""

import ast
import dataclasses
import math
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from evnoise import mismatch, terms
from evnoise.background import arrival_shares
from evnoise.mismatch import background_nodes
from evnoise.terms.base import NoiseTerm

ROOT = Path(__file__).resolve().parents[1]
BASE = ev.NoiseParams(eps_pos=0.5, eps_neg=0.5, bias_pr=1.0, trial_rate_hz=1000.0, photons_per_lux=1.0)
BACKGROUND = BASE.replace(leak_on_hz=0.3, leak_off_hz=0.1, leak_on_hz_per_lux=0.05, leak_sigma=0.4,
                          hot_pixel_fraction=0.02, hot_pixel_rate_hz=40.0, hot_pixel_sigma=0.5)


class ConstantRate(NoiseTerm):
    """Toy term: every pixel gets ``on_hz`` / ``off_hz`` more background events per second."""

    name = "toy_constant"
    background = True

    def __init__(self, on_hz, off_hz):
        self.on_hz, self.off_hz = on_hz, off_hz

    def is_on(self, params):
        return True

    def intensities(self, lux, params, scale=None, hot=None):
        return self.on_hz, self.off_hz

    def mean_intensities(self, lux, values):
        return self.on_hz, self.off_hz

    def coefficients(self, params, scale, hot):
        return self.on_hz, 0.0, self.off_hz, 0.0


@pytest.fixture
def toy():
    term = ConstantRate(30.0, 10.0)
    terms.register(term)
    try:
        yield term
    finally:
        terms.unregister(term.name)
    assert term not in terms.TERMS


def test_every_parameter_has_one_term():
    owned = Counter(f for t in terms.TERMS for f in t.fields)
    assert all(n == 1 for n in owned.values()), owned
    assert set(owned) == {f.name for f in dataclasses.fields(ev.NoiseParams)}
    assert [t.name for t in terms.TERMS] == ["shot", "leak", "hot_pixels", "timer", "bandwidth", "memory"]
    assert set(terms.bounds()) == set(owned)
    with pytest.raises(ValueError, match="already registered"):
        terms.register(terms.LEAK)


@pytest.mark.parametrize("changes", [{}, {"leak_on_hz": 1.0}, {"leak_off_hz_per_lux": 0.1}, {"leak_sigma": 1.0},
                                     {"hot_pixel_fraction": 0.1}, {"hot_pixel_fraction": 0.1, "hot_pixel_rate_hz": 5.0},
                                     {"leak_regularity": 0.5}, {"leak_regularity": 0.5, "leak_off_hz": 2.0}])
def test_registry_agrees_with_the_parameter_properties(changes):
    p = BASE.replace(**changes)
    assert terms.background_on(p) == p.has_background
    assert terms.regular_timer(p) == p.regular_background
    spread = p.has_background and (p.leak_sigma > 0 or p.hot_pixel_fraction > 0)
    assert terms.maps_needed(p) == (p.eps_sigma > 0 or spread)


def test_kernel_coefficients_are_the_closed_form_intensities():
    """The trial kernel's ``l0 + l1 * lux`` and the closed form's intensities are one sum over the terms."""
    shape = (8, 9)
    bg = ev.draw_background(shape, BACKGROUND, rng=3).reshape(2, -1)
    lux = np.linspace(0.0, 50.0, bg.shape[1])
    c = terms.kernel_coefficients(BACKGROUND, (bg[0], bg[1]), np.arange(lux.size))
    l_on, l_off = terms.intensities(lux, BACKGROUND, bg[0], bg[1])
    np.testing.assert_allclose(c[0] + c[1] * lux, l_on, rtol=1e-14)
    np.testing.assert_allclose(c[2] + c[3] * lux, l_off, rtol=1e-14)


def test_calibration_hook_is_the_population_mean():
    """``terms.mean_intensities`` is calibration's additive stand-in, bit for bit, over a batch of candidates."""
    g = np.random.default_rng(1)
    names = ("leak_on_hz", "leak_off_hz", "leak_on_hz_per_lux", "leak_off_hz_per_lux", "hot_pixel_fraction",
             "hot_pixel_rate_hz", "hot_pixel_on_fraction")
    vals = {n: g.uniform(0.0, 2.0, 5) for n in names}
    vals["hot_pixel_rate_hz"][1] = 0.0
    lux = np.geomspace(0.1, 100.0, 7)
    f_hot = vals["hot_pixel_fraction"] * (vals["hot_pixel_rate_hz"] > 0)
    hot = f_hot * vals["hot_pixel_rate_hz"]
    q = vals["hot_pixel_on_fraction"]
    want = np.stack([vals["leak_on_hz"][:, None] + vals["leak_on_hz_per_lux"][:, None] * lux[None, :]
                     + (hot * q)[:, None],
                     vals["leak_off_hz"][:, None] + vals["leak_off_hz_per_lux"][:, None] * lux[None, :]
                     + (hot * (1.0 - q))[:, None]], axis=1)
    got = np.stack(terms.mean_intensities(lux[None, :], {n: v[:, None] for n, v in vals.items()}), axis=1)
    np.testing.assert_array_equal(got, want)
    # and it is the population mean of the per-pixel intensities
    p = BACKGROUND
    scale, h, w = background_nodes(p)
    l_on, _ = terms.intensities(np.array([2.0])[None, :], p, scale[:, None], h[:, None])
    mean_on, _ = terms.mean_intensities(2.0, {f.name: getattr(p, f.name) for f in dataclasses.fields(p)})
    assert np.sum(w * l_on[:, 0]) == pytest.approx(mean_on, rel=1e-10)


def _expected_toy_rate(params, lux, term):
    """Rate [ON, OFF] events/s of a pixel with the toy background only (no refractory period), by hand."""
    lam = params.photons_per_trial(lux)
    p_on = ev.event_probability(lam, params.eps_pos, params.bias_pr)
    p_off = ev.event_probability(lam, params.eps_neg, params.bias_pr)
    a_on, a_off = arrival_shares(np.float64(term.on_hz), np.float64(term.off_hz), params.trial_rate_hz)
    quiet = 1.0 - p_on - p_off
    return params.trial_rate_hz * np.array([p_on + quiet * a_on, p_off + quiet * a_off])


def test_toy_term_in_the_closed_form(toy):
    lux = np.array([[0.0, 1.0, 5.0]])
    rate = ev.expected_rate(lux, BASE)
    want = np.stack([_expected_toy_rate(BASE, x, toy) for x in lux.ravel()], axis=1).reshape(2, 1, 3)
    np.testing.assert_allclose(rate, want, rtol=1e-12)
    assert rate[0, 0, 0] == pytest.approx(30.0, rel=0.05)  # in the dark: the toy's own rate (saturating)
    terms.unregister(toy.name)
    assert ev.expected_rate(lux, BASE)[0, 0, 0] == 0.0


@pytest.mark.parametrize("tier", ["renewal", "trials", "counts", "stream"])
def test_toy_term_in_the_simulated_counts(toy, tier):
    """Counts of every tier within 5 sigma of the closed form (each pixel's count is binomial over trials)."""
    shape, duration = (32, 32), 2.0
    lux = np.full(shape, 2.0)
    rate = ev.expected_rate(lux, BASE)
    assert rate[0].mean() > 25.0  # the toy dominates
    if tier == "counts":
        counts = ev.sample_counts(lux, BASE, duration, rng=5).sum(axis=(1, 2))
    elif tier == "stream":
        stream = ev.NoiseStream(shape, BASE, rng=5)
        events = np.concatenate([stream.advance(lux, 500_000), stream.advance(lux, 2_000_000)])
        counts = ev.count_events(events, shape, 0, 2_000_000).sum(axis=(1, 2))
    else:
        events = ev.simulate_events(lux, BASE, duration, rng=5, method=tier)
        counts = ev.count_events(events, shape, 0, int(duration * 1e6)).sum(axis=(1, 2))
    trials = BASE.trial_rate_hz * duration
    prob = rate.reshape(2, -1) / BASE.trial_rate_hz
    mean = trials * prob.sum(axis=1)
    sd = np.sqrt(trials * (prob * (1.0 - prob)).sum(axis=1))
    assert np.all(np.abs(counts - mean) < 5.0 * sd), (counts, mean, sd)


def test_toy_term_in_a_changing_scene(toy):
    """The trial tier's kernel gets the toy's coefficients too: a changing pixel fires at least the toy's rate."""
    frames = np.stack([np.full((4, 4), 0.0), np.full((4, 4), 0.0)])
    frames[1, 0, 0] = 1e-9  # one changing pixel, dark: only the toy fires
    events = ev.simulate_video(frames, [0.0, 4.0], BASE, rng=2)
    on = events[(events["x"] == 0) & (events["y"] == 0) & (events["p"] == 1)].size
    want = 4.0 * _expected_toy_rate(BASE, 0.0, toy)[0]
    assert abs(on - want) < 5.0 * math.sqrt(want)


def _count_calls(fn, *funcs):
    codes = {f.__code__: f.__name__ for f in funcs}
    counts = Counter()

    def profile(frame, event, arg):
        if event == "call" and frame.f_code in codes:
            counts[codes[frame.f_code]] += 1

    sys.setprofile(profile)
    try:
        fn()
    finally:
        sys.setprofile(None)
    return counts


@pytest.mark.parametrize("call", ["simulate_events", "trials", "sample_counts", "poisson_counts", "simulate_video",
                                  "NoiseStream", "PhotonNoise"])
def test_a_run_is_set_up_once(call):
    """One public call normalises its generator once and checks its parameters once (at its edge)."""
    from evnoise import _checks, _run

    lux = np.full((6, 7), 3.0)
    p = BACKGROUND.replace(eps_sigma=0.05)
    run = {
        "simulate_events": lambda: ev.simulate_events(lux, p, 0.05, rng=1),
        "trials": lambda: ev.simulate_events(lux, p, 0.05, rng=1, method="trials"),
        "sample_counts": lambda: ev.sample_counts(lux, p, 0.05, rng=1),
        "poisson_counts": lambda: ev.sample_counts(lux, p, 0.05, rng=1, distribution="poisson"),
        "simulate_video": lambda: ev.simulate_video(np.stack([lux, 2 * lux]), [0.0, 0.05], p, rng=1),
        "NoiseStream": lambda: ev.NoiseStream(lux.shape, p, rng=1).advance(lux, 50_000),
        "PhotonNoise": lambda: _photon_noise(p),
    }[call]
    counts = _count_calls(run, _checks.as_generator, _checks.check_params, _run.run_setup)
    assert counts == {"as_generator": 1, "check_params": 1, "run_setup": 1}, counts


def _photon_noise(p):
    from evnoise.plugins.tonic import PhotonNoise

    events = np.zeros(3, dtype=[("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")])
    events["t"] = [0, 10_000, 50_000]
    PhotonNoise((7, 6, 2), p, 3.0, rng=np.random.default_rng(1))(events)


MY_FILES = ["evnoise/_engine.py", "evnoise/background.py", "evnoise/rates.py", "evnoise/simulate.py",
            "evnoise/stream.py", "evnoise/mismatch.py", "evnoise/model.py", "evnoise/_checks.py", "evnoise/_run.py",
            "evnoise/plugins/tonic.py", "evnoise/plugins/frames.py", "generators/pairs.py",
            *sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "evnoise" / "_kernels").glob("*.py")),
            *sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "evnoise" / "terms").glob("*.py"))]


def test_no_private_name_crosses_a_module_of_the_model():
    """The model's modules import public names only from each other (private modules are fine)."""
    found = []
    for rel in MY_FILES:
        for node in ast.walk(ast.parse((ROOT / rel).read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                found += [(rel, node.module, a.name) for a in node.names
                          if a.name.startswith("_") and not a.name.startswith("__")]
    assert not found, found


def test_needs_maps_is_decided_only_by_the_registry():
    """No module outside evnoise/terms re-decides which parameters need per-pixel maps."""
    offenders = [rel for rel in MY_FILES if not rel.startswith("evnoise/terms/")
                 and "leak_sigma > 0 or" in (ROOT / rel).read_text(encoding="utf-8")]
    assert not offenders
    assert not hasattr(mismatch, "_has_leak")
