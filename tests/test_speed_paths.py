"""Fast paths of issue 16 against the code they replaced and against the slow exact reference.

``PINNED`` holds sha256 digests of small fixed-seed outputs computed ONCE with the code *before*
the issue-16 changes (commit 1044ad2, by running ``_pinned_outputs()`` of this file there). The
speed work (dropping the per-pixel Chernoff skip bound where the Chebyshev table evaluates the
value anyway) must leave every one of these outputs unchanged for a given seed.

Only outputs that are exact by design are compared by digest on every machine: event streams and
counts (integers from the same draws). The three ``event_probability`` outputs are floats whose
last bits depend on the CPU (NumPy's SIMD ``exp``/``log``, Numba's target): their pre-issue-16
values are stored in ``data/speed_paths_p.npz`` (with the input ``lam`` they were computed from),
the stored arrays are checked against the pinned digests (file content, the same everywhere), and
the live values are compared to them within a stated tolerance (``_assert_same_probability``).
"""

import hashlib
import math
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from _legacy import LEGACY_EVK3

# the evk3-hd parameters the digests were pinned with (the preset itself was refitted in issue 15)
PRESET = LEGACY_EVK3


def _lux_image(shape=(64, 96), seed=5):
    """Illuminance from darkness to far beyond where p underflows (lam ~ 6e8), log-spaced.

    Most pixels span 0..1e4 lux (lam up to ~6.4e5, crossing the skip threshold log p = -760 near
    lam = 1.6e5); a handful sit beyond the Chebyshev table (lam > 2.4e7) or at exactly 0 lux.
    """
    g = np.random.default_rng(seed)
    lux = 10.0 ** g.uniform(-3.0, 4.0, size=shape)
    lux.flat[:5] = 0.0
    lux.flat[5:9] = [1e6, 1e7, 3e5, 5e4]
    return lux


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _pinned_outputs() -> dict:
    """Fixed-seed outputs of every public path that goes through ``event_probability``."""
    lux = _lux_image()
    out = {}
    lam = PRESET.photons_per_trial(lux)
    out["p_nominal"] = _digest(ev.event_probability(lam, PRESET.eps_pos, PRESET.bias_pr))
    out["p_small"] = _digest(ev.event_probability(lam[:4, :50], PRESET.eps_neg, PRESET.bias_pr))
    out["p_big_eps"] = _digest(ev.event_probability(lam, 3.0, 2.0))
    out["simulate"] = _digest(ev.simulate_events(lux, PRESET, 0.2, rng=7))
    out["iter"] = _digest(*ev.iter_events(lux, PRESET, 0.2, rng=7, threads=1))
    out["counts"] = _digest(ev.sample_counts(lux, PRESET, 2.0, rng=8))
    stream = ev.NoiseStream(lux.shape, PRESET, rng=9)
    out["stream"] = _digest(stream.advance(lux, 50_000), stream.advance(lux * 0.5, 120_000),
                            stream.advance(lux * 3.0, 200_000))
    mism = PRESET.replace(eps_sigma=0.03)
    out["simulate_mismatch"] = _digest(ev.simulate_events(lux, mism, 0.2, rng=7))
    out["counts_mismatch"] = _digest(ev.sample_counts(lux, mism, 2.0, rng=8))
    from evnoise.generators.config import PairConfig
    from evnoise.generators.pairs import CountSampler

    codes = np.minimum((np.sqrt(lux / 1e4) * 16383).astype(np.int64), 16383)
    sampler = CountSampler(PairConfig(binning=2, max_lux=18.0, params=PRESET))
    out["dataset_counts"] = _digest(sampler.sample(codes, 250_000, 123))
    return out


PINNED = {  # sha256 of _pinned_outputs() computed with commit 1044ad2 (before the issue-16 changes)
    "p_nominal": "c4c7fa927304e87ece06062a220c521331b1d29369e056bd3e8da6a00eddfe19",
    "p_small": "8c24d56aa707fb71829f937e1e62d47cecb8579142c9282fc3ead8dc9dd70ae6",
    "p_big_eps": "c38af057fecc677aa5146cd2fe7ff473fb6d512d64275f29796cf20e0216902c",
    "simulate": "1b10099c3bbf424de56cc521c804474193ef7c66b568a57160cb76d1fa34afcd",
    "iter": "1b10099c3bbf424de56cc521c804474193ef7c66b568a57160cb76d1fa34afcd",
    "counts": "a2e8373f37fd2e8e691d827d78e24193c903eba28a30d300142020f748232ddf",
    "stream": "2af210181c3b466728a95bed167e553d4be05903cee44a69d775cf264b427c37",
    "simulate_mismatch": "fba7d34e76b324fccd938428150ac1cd70c142bdf76072087686d94594cb08d1",
    "counts_mismatch": "a26d5828acec1620994f1279e1a59e80c8e2f923ce917555b9b356773e69f1ed",
    "dataset_counts": "957c7e56ba14d3423e52102a19c49a9d3acfb6efcb9d089980c5d25699504b20",
}


# float outputs: compared to the stored pre-issue-16 arrays within a tolerance, not by digest
FLOAT_PINS = {  # name -> (rows, cols of lam, eps, bias), as in _pinned_outputs()
    "p_nominal": (slice(None), slice(None), PRESET.eps_pos, PRESET.bias_pr),
    "p_small": (slice(0, 4), slice(0, 50), PRESET.eps_neg, PRESET.bias_pr),
    "p_big_eps": (slice(None), slice(None), 3.0, 2.0),
}
EXACT_PINS = sorted(set(PINNED) - set(FLOAT_PINS))
STORED = Path(__file__).parent / "data" / "speed_paths_p.npz"

# Allowed error of log p, relative to max(1, |log p|): 1e-14, i.e. about 45 ulp of log p.
# Why this size: p = exp(log p) is evaluated in the log domain, so an absolute error d in log p is a
# relative error d in p, and an ulp of log p is 1.1e-16..2.2e-16 times |log p| (up to 745 here).
# Measured: with NUMBA_CPU_NAME=generic and NumPy's AVX-512 kernels off, p on the stored lam moved by
# at most 1 ulp of p (relative 2.2e-16, 6e-17 on this scale), so the bound leaves ~170x for other CPUs
# and libms. It is still tight enough to see a change of evaluation path: the windowed exact sum, a
# correct alternative good to ~1e-12, misses it on ~70 pixels (test_tolerance_tells_evaluation_paths_apart).
LOG_P_TOL = 1e-14
SMALLEST_SUBNORMAL = 2.0**-1074


def _tolerance(want):
    """Allowed |got - want| per element: LOG_P_TOL * max(1, |log p|) relative, plus one subnormal step."""
    scale = np.maximum(1.0, np.abs(np.log(np.where(want > 0.0, want, 1.0))))
    return LOG_P_TOL * scale * want + SMALLEST_SUBNORMAL


def _assert_same_probability(got, want):
    """Within _tolerance where want > 0; exactly 0 where want is 0. Zeros are exact by design here:
    every pinned log p is either below -760 (skipped, p := 0) or at least 0.14 away from the skip
    threshold and from exp's underflow (-745.13), vastly more than the 1e-11 the tolerance allows."""
    assert got.shape == want.shape and got.dtype == want.dtype == np.float64
    assert np.array_equal(got == 0.0, want == 0.0), np.count_nonzero((got == 0.0) != (want == 0.0))
    err = np.abs(got - want)
    bad = err > _tolerance(want)
    assert not bad.any(), (np.count_nonzero(bad), np.max(err[want > 0] / want[want > 0]))


@pytest.fixture(scope="module")
def stored():
    with np.load(STORED) as f:
        return {k: f[k] for k in f.files}


@pytest.fixture(scope="module")
def pinned_now():
    return _pinned_outputs()


@pytest.mark.parametrize("name", EXACT_PINS)
@pytest.mark.long
def test_outputs_bit_identical_to_code_before_issue16(name, pinned_now):
    """Event streams and counts: integers from the same draws, identical on every machine."""
    assert pinned_now[name] == PINNED[name]


@pytest.mark.parametrize("name", sorted(FLOAT_PINS))
def test_stored_probabilities_are_the_pinned_ones(name, stored):
    """The stored arrays are bit for bit the pre-issue-16 outputs (a digest of file content)."""
    assert _digest(stored[name]) == PINNED[name]


def test_stored_input_is_the_pinned_scene(stored):
    """The stored lam is the pinned scene's: lux = 10**uniform and photons_per_trial agree to a few
    ulp across CPUs (measured: 1 ulp), nothing here amplifies rounding, so 1e-13 relative."""
    lam = PRESET.photons_per_trial(_lux_image())
    np.testing.assert_allclose(lam, stored["lam"], rtol=1e-13, atol=0.0)


@pytest.mark.parametrize("name", sorted(FLOAT_PINS))
def test_pinned_zeros_are_far_from_where_p_becomes_0(name, stored):
    """What makes the zero pattern exact on every machine: no pinned log p lies within 0.1 of the skip
    threshold (-760) or of exp's underflow to 0 (log of the smallest subnormal, -744.44, rounded
    down to 0 below -745.13)."""
    rows, cols, eps, bias = FLOAT_PINS[name]
    log_p = ev.log_event_probability(stored["lam"][rows, cols], eps, bias)
    finite = log_p[np.isfinite(log_p)]
    assert finite.size > 100
    assert np.min(np.abs(finite + 760.0)) > 0.1 and np.min(np.abs(finite + 745.1332191019412)) > 0.1
    assert np.array_equal(stored[name] == 0.0, ~(log_p >= -745.1332191019412))


@pytest.mark.parametrize("name", sorted(FLOAT_PINS))
def test_probabilities_match_code_before_issue16(name, stored):
    """event_probability on the stored lam gives the pre-issue-16 values within LOG_P_TOL."""
    rows, cols, eps, bias = FLOAT_PINS[name]
    got = ev.event_probability(stored["lam"][rows, cols], eps, bias)
    _assert_same_probability(got, stored[name])


def test_tolerance_tells_evaluation_paths_apart(stored):
    """The comparison is not vacuous: a correct but different evaluation (the windowed exact sum
    instead of the Chebyshev table) fails it, and so does a perturbation of 1e-12 relative."""
    from evnoise._kernels.poisson import log_event_probability_exact_array

    lam, want = stored["lam"], stored["p_nominal"]
    log_p = np.empty(lam.size)
    log_event_probability_exact_array(lam.ravel(), np.full(lam.size, np.expm1(PRESET.eps_pos)),
                                      np.full(lam.size, PRESET.bias_pr), log_p)
    with np.errstate(under="ignore"):
        exact = np.where(log_p < -760.0, 0.0, np.exp(log_p)).reshape(lam.shape)
    np.testing.assert_allclose(exact, want, rtol=1e-11, atol=1e-300)  # the same values...
    assert np.count_nonzero(np.abs(exact - want) > _tolerance(want)) > 10  # ...but not the same path
    with pytest.raises(AssertionError):
        _assert_same_probability(want * (1.0 + 1e-12), want)


def test_pinned_scene_exercises_the_skipped_region():
    """The pinned scene has tabulated values below the skip threshold (now tabulated, formerly skipped)
    and values beyond the table (still skipped by the bound), so the digests above cover both."""
    lam = PRESET.photons_per_trial(_lux_image()).ravel()
    log_p = ev.log_event_probability(lam, PRESET.eps_pos, PRESET.bias_pr)
    p = ev.event_probability(lam, PRESET.eps_pos, PRESET.bias_pr)
    tabulated = (lam > 100) & (lam < np.exp(17.0))
    assert np.count_nonzero(tabulated & (log_p < -760) & np.isfinite(log_p)) > 100
    assert np.count_nonzero(lam > np.exp(17.0)) >= 1
    assert np.all(p[log_p < -760] == 0.0)
    assert np.all(p[log_p > -700] > 0.0)


# --------------------------------------------------------------------------------------
# threshold mismatch: the grouped per-level path against the windowed exact sum
# --------------------------------------------------------------------------------------
HARD_EPS = {
    "tiny eps": (1e-4, 3e-3),
    "preset-like eps": (0.08, 0.3),
    "large eps": (0.7, 5.0),
}


@pytest.mark.parametrize("bias", [0.0, 1.7, 105.0])
@pytest.mark.parametrize("eps_range", sorted(HARD_EPS))
@pytest.mark.long
def test_grouped_mismatch_path_matches_exact_sum(eps_range, bias):
    """Per-pixel thresholds on shared lam levels (1e-3 .. 1e6, i.e. far beyond the old limit of 200)
    agree with the windowed exact sum to 1e-10 relative wherever p > 1e-300 (tiny p included)."""
    from evnoise import model
    from evnoise._kernels.poisson import log_event_probability_exact_array

    g = np.random.default_rng(11)
    levels = np.concatenate([10.0 ** np.linspace(-3, 6, 28), [200.0, 201.0, 1e3, 3e4, 1e5]])
    per_level = 128
    lam = np.repeat(levels, per_level)
    lo, hi = HARD_EPS[eps_range]
    eps = np.exp(g.uniform(np.log(lo), np.log(hi), lam.size))
    got = ev.log_event_probability(lam, eps, bias)
    ref = np.empty(lam.size)
    log_event_probability_exact_array(lam, np.expm1(eps), np.full(lam.size, bias), ref)
    sel = ref > np.log(1e-300)
    assert np.count_nonzero(sel) > 500
    assert np.all(np.abs(np.expm1(got[sel] - ref[sel])) <= 1e-10), np.max(np.abs(got[sel] - ref[sel]))
    assert np.all(got[~sel] < np.log(1e-290))
    # the grouped path itself did the work (it is what is under test), also above lam = 200
    out = np.empty(lam.size)
    done = model._grouped(lam, np.expm1(eps), bias, np.ones(lam.size, dtype=bool), out)
    big = lam > 200
    assert np.count_nonzero(done & big & sel) >= 0.5 * np.count_nonzero(big & sel)
    assert np.all(np.abs(out[done] - ref[done]) <= 1e-10)


def test_grouped_path_tail_bound_handles_tiny_probabilities():
    """Where p is far below 1e-25 the summand's peak sits many sqrt(lam) below lam (a fixed window
    around lam loses it): the grouped path must still agree with the exact sum or defer to it."""
    from evnoise import model
    from evnoise._kernels.poisson import log_event_probability_exact_array

    lam = np.repeat([3e3, 1e4, 1e5, 3e5], 1024)
    eps = np.linspace(0.15, 0.35, lam.size) % 0.2 + 0.15
    c = np.expm1(eps)
    ref = np.empty(lam.size)
    log_event_probability_exact_array(lam, c, np.zeros(lam.size), ref)
    assert np.count_nonzero((ref < np.log(1e-25)) & (ref > np.log(1e-280))) > 1000
    out = np.full(lam.size, np.nan)
    done = model._grouped(lam, c, 0.0, np.ones(lam.size, dtype=bool), out)
    assert np.count_nonzero(done & (ref < np.log(1e-25))) > 500
    assert np.all(np.abs(out[done] - ref[done]) <= 1e-10)


# --------------------------------------------------------------------------------------
# simulate_events sorts each window straight into one output array
# --------------------------------------------------------------------------------------
def test_simulate_events_collects_windows_in_place_identically(monkeypatch):
    """Many windows (small window target) give exactly the concatenation of iter_events' windows,
    also when the output outgrows its first allocation (forced by shrinking the margin)."""
    from evnoise import simulate as sim

    lux = np.full((40, 60), 5.0)
    monkeypatch.setattr(sim, "TARGET_EVENTS_PER_WINDOW", 500)
    monkeypatch.setattr(sim, "EVENTS_PER_PIXEL_PER_WINDOW", 0)
    windows = list(ev.iter_events(lux, PRESET, 3.0, rng=4))
    assert len(windows) > 5
    want = np.concatenate(windows)
    got = ev.simulate_events(lux, PRESET, 3.0, rng=4)
    assert got.flags.owndata and got.size == want.size > 1000
    assert np.array_equal(got, want)

    from evnoise._engine import Collector

    init = Collector.__init__
    monkeypatch.setattr(Collector, "__init__", lambda self, capacity: init(self, capacity // 10))
    assert np.array_equal(ev.simulate_events(lux, PRESET, 3.0, rng=4), want)


def test_a_large_scene_takes_few_windows_and_the_same_events(monkeypatch):
    """Every window advances every pixel, so a 1280x720 scene's windows hold at least EVENTS_PER_PIXEL_PER_WINDOW
    events per pixel (one window for its 1.2 M events of 1 s at 2 lux, not two of 1 M); the events are those of
    windows of 1 M events, bit for bit."""
    from evnoise import simulate as sim

    lux = np.full((720, 1280), 2.0)
    params = ev.load_preset("evk3-hd")
    assert sim.events_per_window(lux.size) == sim.EVENTS_PER_PIXEL_PER_WINDOW * lux.size
    assert sim.events_per_window(10) == sim.TARGET_EVENTS_PER_WINDOW
    assert sim.events_per_window(1 << 24) == sim.MAX_EVENTS_PER_WINDOW
    few = list(ev.iter_events(lux, params, 1.0, rng=3))
    monkeypatch.setattr(sim, "EVENTS_PER_PIXEL_PER_WINDOW", 0)
    many = list(ev.iter_events(lux, params, 1.0, rng=3))
    assert len(few) == 1 and len(many) == 2 and few[0].size > sim.TARGET_EVENTS_PER_WINDOW
    assert np.array_equal(few[0], np.concatenate(many))


def test_a_quiet_scene_takes_long_windows_and_the_same_events(monkeypatch):
    """At a low event rate a static scene's windows run up to MAX_STATIC_WINDOW_US (one window for 20 s here, whose
    sort takes more than SORT_COARSE coarse buckets), not the trial tier's MAX_WINDOW_US (five windows): the events
    are those of the short windows, bit for bit."""
    from evnoise import simulate as sim
    from evnoise._kernels import simulate as kernels

    lux = np.full((16, 16), 2.0)
    assert sim.MAX_STATIC_WINDOW_US >> kernels.SORT_FINE_BITS > kernels.SORT_COARSE
    long = list(ev.iter_events(lux, PRESET, 20.0, rng=8))
    monkeypatch.setattr(sim, "MAX_STATIC_WINDOW_US", sim.MAX_WINDOW_US)
    short = list(ev.iter_events(lux, PRESET, 20.0, rng=8))
    assert len(long) == 1 and len(short) == 5 and long[0].size > 1000
    assert np.array_equal(long[0], np.concatenate(short))


def test_the_window_sort_is_stable_whatever_its_blocks():
    """sort_into_events (every window's sort) against NumPy's stable argsort, on more events than one block of its
    parallel first pass holds and with many ties (pixel order must survive), for one and several threads; the
    signal flag goes to the labels."""
    import numba

    from evnoise._engine import sorted_window
    from evnoise._kernels import simulate as kernels

    rng = np.random.default_rng(11)
    n = 5 * kernels.SORT_BLOCK_MIN + 123
    assert kernels.SORT_BLOCKS >= 5
    t_lo, t_hi = 1000, 1000 + 300_000
    t = rng.integers(t_lo, t_hi, n)
    x = rng.integers(0, 1280, n).astype(np.uint16)
    y = rng.integers(0, 720, n).astype(np.uint16)
    p = rng.integers(0, 4, n).astype(np.uint8)  # bit 1: the signal flag
    order = np.argsort(t, kind="stable")
    try:
        for threads in (1, 2):
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            out, labels = sorted_window([(t, x, y, p)], t_lo, t_hi, labels=True)
            assert np.array_equal(out["t"], t[order]) and np.array_equal(out["x"], x[order])
            assert np.array_equal(out["y"], y[order]) and np.array_equal(out["p"], p[order] & 1)
            assert np.array_equal(labels, (p[order] >> 1).astype(bool))
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)


def _stable_reference(parts):
    t, x, y, p = (np.concatenate([part[i] for part in parts]) for i in range(4))
    order = np.argsort(t, kind="stable")
    return t[order], x[order], y[order], p[order]


def _random_columns(rng, n, t_lo, t_hi):
    return (rng.integers(t_lo, t_hi, n), rng.integers(0, 1280, n).astype(np.uint16),
            rng.integers(0, 720, n).astype(np.uint16), rng.integers(0, 4, n).astype(np.uint8))


@pytest.mark.parametrize("layout", ["regions of shared columns", "separate arrays", "long window"])
def test_the_window_sort_reads_parts_where_they_are_and_keeps_their_order(layout):
    """Parts that are regions of one set of columns (with gaps, an empty one, one beyond a block) are sorted where
    they lie; separate parts are concatenated; a window too long for the counting sort's histograms takes NumPy's
    stable sort: each gives NumPy's stable argsort of the parts in order (labels from the signal flag)."""
    from evnoise import _engine
    from evnoise._kernels import simulate as kernels

    rng = np.random.default_rng(5)
    t_lo = 7000
    span = (kernels.SORT_COARSE_MAX << kernels.SORT_FINE_BITS) + 5 if layout == "long window" else 3_000_000
    sizes = (150_000, 0, kernels.SORT_BLOCK_MIN * 3 + 5, 7, 90_000)
    shared = _engine.event_buffers(sum(sizes) + 1000 * len(sizes))
    parts, first, where = [], 0, []
    for m in sizes:
        cols = _random_columns(rng, m, t_lo, t_lo + span)
        if layout == "separate arrays":
            parts.append(cols)
            continue
        for column, values in zip(shared, cols):
            column[first:first + m] = values
        parts.append(tuple(c[first:first + m] for c in shared))
        if m:
            where.append([first, first + m])
        first += m + 1000
    found = _engine._segments_of([p for p in parts if p[0].size])
    if layout == "separate arrays":
        assert found is None
    else:
        assert found is not None and found.tolist() == where
    t, x, y, p = _stable_reference(parts)
    out, labels = _engine.sorted_window(parts, t_lo, t_lo + span, labels=True)
    assert np.array_equal(out["t"], t) and np.array_equal(out["x"], x) and np.array_equal(out["y"], y)
    assert np.array_equal(out["p"], p & 1) and np.array_equal(labels, (p >> 1).astype(bool))


def test_a_static_windows_parts_are_sorted_where_the_kernel_wrote_them():
    """The renewal step (as the memory step) gives every chunk a region of one set of columns, so the window's sort
    reads them in place (no concatenation of the window's events): the parts must be regions of the same columns."""
    from evnoise import _engine
    from evnoise.simulate import PixelState

    params = ev.load_preset("evk3-hd")
    shape = (40, 1000)  # more pixels than one chunk
    lam = params.photons_per_trial(np.full(shape, 2.0)).ravel()
    log1m_p, q_on, timer, nu = _engine.static_inputs(lam, params, np.full(lam.size, params.eps_pos),
                                                     np.full(lam.size, params.eps_neg), None)
    state = PixelState(np.arange(lam.size), np.arange(4, dtype=np.uint64) + 1, 2)
    assert len(_engine.pixel_chunks(lam.size)) > 1
    parts = _engine.renewal_step(state, shape[1], log1m_p, q_on, params.trial_us, params.refractory_us, 0, 2e6,
                                 math.inf, 0, 2, expected=nu * 2.0, timer=timer)
    parts = [p[:4] for p in parts if p[0].size]
    assert len(parts) > 1 and _engine._segments_of(parts) is not None


def _window(state, capacities, need=None):
    """What renewal_step does with each chunk's buffers in one window (``need``: events a chunk writes, growing its
    buffers where they exceed the room it was given); returns the parts."""
    from evnoise import _engine

    parts = []
    with state.shared(capacities):
        for (lo, _), cap, m in zip(_engine.pixel_chunks(state.pix.size), capacities, need or capacities):
            out = state.buffers(lo, cap)
            while m > out[0].size:  # as run_to_end
                out = _engine.grown(out, 0)
            state.keep(lo, out)
            parts.append(tuple(c[:m] for c in out))
    return parts


def test_a_long_windows_columns_are_not_held_after_it():
    """A window too large to keep (a long NoiseStream.advance) must not stay pinned by the state through a small
    chunk's region (the last chunk of 1280x720 is partial); short windows after it reuse small kept columns."""
    import gc
    import weakref

    from evnoise._engine import CHUNK_PIXELS, KEEP_EVENTS_PER_CHUNK, PixelState

    state = PixelState(np.arange(CHUNK_PIXELS + 4096), np.zeros(4, np.uint64), 1)
    parts = _window(state, [2 * KEEP_EVENTS_PER_CHUNK, 1000])
    big = weakref.ref(parts[0][0].base)
    del parts
    for _ in range(3):
        _window(state, [1000, 250])
    gc.collect()
    assert big() is None


def test_a_chunk_that_outgrew_its_region_gets_room_next_time():
    """A chunk whose events exceeded its share grows once; the next windows give it a region of what it needed, so
    their parts are again regions of one set of columns (sorted in place)."""
    from evnoise import _engine
    from evnoise._engine import CHUNK_PIXELS, PixelState

    state = PixelState(np.arange(2 * CHUNK_PIXELS), np.zeros(4, np.uint64), 1)
    first = _window(state, [500, 500], need=[500, 3000])
    assert _engine._segments_of(first) is None  # the grown chunk is elsewhere: concatenated
    for _ in range(2):
        assert _engine._segments_of(_window(state, [500, 500], need=[500, 3000])) is not None


def test_the_window_sort_takes_columns_of_any_origin():
    """Columns whose base is not an array (np.frombuffer's bytes) are concatenated, not inspected as arrays."""
    from evnoise._engine import sorted_window

    t = np.frombuffer(np.array([5, 3, 4], dtype=np.int64).tobytes(), dtype=np.int64)
    x = np.frombuffer(np.array([1, 2, 3], dtype=np.uint16).tobytes(), dtype=np.uint16)
    out = sorted_window([(t, x, x.copy(), np.zeros(3, np.uint8))], 0, 10)
    assert out["t"].tolist() == [3, 4, 5] and out["x"].tolist() == [2, 3, 1]


def test_the_window_sort_reuses_its_working_memory_and_gives_the_same_events():
    """A run that sorts window after window takes the sort's packed keys from its pixel state (a fresh array's pages
    cost a fault each, every window): the same array while it has room, a larger one kept when needed, none kept
    beyond the limit the event columns have; and whatever the reused array held, the window is the same."""
    from evnoise import _engine
    from evnoise.simulate import PixelState

    state = PixelState(np.arange(100), np.arange(4, dtype=np.uint64) + 1, 1)
    limit = _engine.KEEP_EVENTS_PER_CHUNK * len(_engine.pixel_chunks(100))
    first = state.sort_keys(1000)
    assert first.size == 1000 and state.sort_keys(600) is first
    bigger = state.sort_keys(5000)
    assert bigger.size == 5000 and state.sort_keys(1000) is bigger
    huge = state.sort_keys(limit + 1)
    assert huge.size == limit + 1 and state.sort_keys(10) is bigger  # the large one is not kept

    rng = np.random.default_rng(5)
    n = 3000
    part = (np.sort(rng.integers(0, 10**6, n)).astype(np.int64)[rng.permutation(n)], rng.integers(0, 100, n, np.uint16),
            rng.integers(0, 50, n, np.uint16), rng.integers(0, 4, n, np.uint8))
    bigger[:] = rng.integers(0, 2**63, bigger.size, dtype=np.uint64)  # stale keys from an earlier window
    reused, labels = _engine.sorted_window([part], 0, 10**6, labels=True, state=state)
    fresh, fresh_labels = _engine.sorted_window([part], 0, 10**6, labels=True)
    order = np.argsort(part[0], kind="stable")
    assert np.array_equal(reused, fresh) and np.array_equal(labels, fresh_labels)
    assert np.array_equal(reused["t"], part[0][order]) and np.array_equal(reused["x"], part[1][order])
    assert np.array_equal(reused["p"], part[3][order] & 1) and np.array_equal(labels, (part[3][order] & 2) > 0)


def test_static_runs_and_streams_sort_with_their_states_working_memory(monkeypatch):
    """Each window of a static run, a video and a NoiseStream's interval asks its pixel state for the sort's keys."""
    from evnoise import _engine
    from evnoise import simulate as sim

    asked = []
    plain = _engine.PixelState.sort_keys
    monkeypatch.setattr(_engine.PixelState, "sort_keys", lambda self, n: asked.append(n) or plain(self, n))
    monkeypatch.setattr(sim, "TARGET_EVENTS_PER_WINDOW", 300)
    monkeypatch.setattr(sim, "EVENTS_PER_PIXEL_PER_WINDOW", 0)
    params = ev.load_preset("evk3-hd")
    lux = np.full((20, 30), 2.0)
    windows = [w for w in ev.iter_events(lux, params, 2.0, rng=1) if w.size]
    assert len(windows) > 2 and asked == [w.size for w in windows]
    asked.clear()
    stream = ev.NoiseStream(lux.shape, params, rng=2)
    sizes = [stream.advance(lux, 300_000 * (i + 1)).size for i in range(3)]
    assert asked == [s for s in sizes if s]
    asked.clear()
    frames = np.stack([lux, np.where(np.arange(30) < 15, 40.0, lux)])
    events = ev.simulate_video(frames, [0.0, 0.5], params, rng=3)
    assert len(asked) >= 1 and sum(asked) == events.size
