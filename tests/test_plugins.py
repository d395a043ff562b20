"""evnoise.plugins: the tonic transform and the v2e wrapper (against a stand-in with v2e's interface)."""

from __future__ import annotations

import pickle
import re
import sys
import types
import warnings
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from evnoise.errors import InputError, ParameterError
from evnoise.plugins import frames as frames_plugin
from evnoise.plugins import tonic as tonic_plugin
from evnoise.plugins import v2e as v2e_plugin

tonic = pytest.importorskip("tonic", reason="tonic is a test extra: pip install -e '.[test]'")

REALDATA = Path(__file__).resolve().parents[1].parent / "shared/data/realdata"
NMNIST_FILE = REALDATA / "tonic/sample_nmnist.bin"
K_SIGMA = 4.0
PARAMS = ev.load_preset("evk3-hd")


@pytest.fixture(scope="module")
def nmnist():
    if not NMNIST_FILE.is_file():
        pytest.skip(f"the real N-MNIST sample is not there: {NMNIST_FILE} (../shared/data/realdata is absent)")
    from tonic.datasets import NMNIST

    events = tonic.io.read_mnist_file(str(NMNIST_FILE), dtype=NMNIST.dtype)
    assert events.size > 1000
    return events, NMNIST.sensor_size


def _two_band_lux(sensor_size, top=2.0, bottom=10.0):
    """Rows y < H/2 at ``top`` lux, the others at ``bottom``: a map whose orientation matters."""
    width, height, _ = sensor_size
    lux = np.full((height, width), bottom)
    lux[: height // 2] = top
    return lux


def _span_s(events):
    return (int(events["t"].max()) - int(events["t"].min()) + 1) * 1e-6


def _check_within(observed, expected, what):
    sigma = np.sqrt(expected)
    assert abs(observed - expected) <= K_SIGMA * sigma + 1, (
        f"{what}: observed {observed}, expected {expected:.1f} +- {sigma:.1f}")


# --------------------------------------------------------------------------------------
# tonic
# --------------------------------------------------------------------------------------
def test_tonic_added_events_match_expected_rate_on_a_real_nmnist_sample(nmnist):
    events, sensor_size = nmnist
    lux = _two_band_lux(sensor_size)
    rate = ev.expected_rate(lux, PARAMS)  # (2, H, W) events/s, independent closed form
    span = _span_s(events)
    half = sensor_size[1] // 2
    observed = np.zeros((2, 2))  # [polarity ON/OFF, band top/bottom]
    n_samples = 10
    for seed in range(n_samples):
        transform = tonic_plugin.PhotonNoise(sensor_size, PARAMS, lux, rng=seed)
        noise = transform.noise(events)
        if seed == 0:  # the transform adds exactly these events
            noisy = transform(events)
            assert noisy.size == events.size + noise.size
            both = np.concatenate([events, noise])
            assert np.array_equal(noisy, both[np.argsort(both["t"], kind="stable")])
        assert noise["t"].min() >= events["t"].min() and noise["t"].max() <= events["t"].max()
        for i, pol in enumerate((1, 0)):
            sel = noise["p"] == pol
            observed[i, 0] += np.count_nonzero(sel & (noise["y"] < half))
            observed[i, 1] += np.count_nonzero(sel & (noise["y"] >= half))
    expected = n_samples * span * np.stack([rate[:, :half].sum(axis=(1, 2)), rate[:, half:].sum(axis=(1, 2))], axis=1)
    assert expected[0, 0] > 1000  # enough events for a test that can fail (a swapped x/y halves the top band)
    for i in range(2):
        for j in range(2):
            _check_within(observed[i, j], expected[i, j],
                          f"{('ON', 'OFF')[i]} noise in the {('top', 'bottom')[j]} band")


def test_tonic_composes_with_compose_and_to_frame(nmnist):
    from tonic.transforms import Compose, ToFrame

    events, sensor_size = nmnist
    lux = _two_band_lux(sensor_size)
    t0, t1 = int(events["t"].min()), int(events["t"].max()) + 1
    to_frame = ToFrame(sensor_size, n_time_bins=3, start_time=t0, end_time=t1)
    noise_transform = tonic_plugin.PhotonNoise(sensor_size, "evk3-hd", lux, rng=7)
    frames = Compose([noise_transform, to_frame])(events)
    clean = to_frame(events)
    width, height, n_pol = sensor_size
    assert frames.shape == clean.shape == (3, n_pol, height, width)
    added = frames.astype(np.int64) - clean
    assert (added >= 0).all()
    noise = noise_transform.noise(events)
    assert added.sum() == noise.size > 0
    # tonic's frames are (T, P, H, W) with channel 1 = ON: the noise lands where evnoise put it
    on_top = np.count_nonzero((noise["p"] == 1) & (noise["y"] < height // 2))
    assert added[:, 1, : height // 2].sum() == on_top
    assert added[:, 0].sum() == np.count_nonzero(noise["p"] == 0)


@pytest.mark.parametrize("dtype", [
    np.dtype([("x", int), ("y", int), ("t", int), ("p", int)]),  # NMNIST, NCALTECH101
    np.dtype([("x", np.int16), ("y", np.int16), ("p", bool), ("t", np.int64)]),  # DVSGesture
    np.dtype([("t", np.int32), ("x", np.int16), ("y", np.int16), ("p", bool)]),  # NERDD
    np.dtype([("p", int), ("t", int), ("x", int), ("y", int)]),  # TUM-VIE
])
def test_tonic_output_keeps_dtype_and_field_names_and_is_sorted(dtype):
    width, height = 40, 24
    gen = np.random.default_rng(1)
    n = 300
    events = np.zeros(n, dtype=dtype)
    events["x"] = gen.integers(0, width, n)
    events["y"] = gen.integers(0, height, n)
    events["t"] = np.sort(gen.integers(1000, 400_000, n))
    events["p"] = gen.integers(0, 2, n).astype(dtype["p"])
    transform = tonic_plugin.PhotonNoise((width, height, 2), PARAMS, 2.0, rng=3)
    out = transform(events)
    assert out.dtype == events.dtype and out.dtype.names == dtype.names
    assert out.size > n
    assert np.all(np.diff(out["t"].astype(np.int64)) >= 0)
    assert out["x"].max() < width and out["y"].max() < height and out["x"].min() >= 0
    assert set(np.unique(out["p"]).tolist()) <= {0, 1}
    # the input events are all still there, unchanged
    key = lambda a: sorted(map(tuple, np.stack([a[f].astype(np.int64) for f in "xytp"], axis=1).tolist()))  # noqa: E731
    noise = transform.noise(events)
    assert key(out) == key(np.concatenate([events, noise]))


def test_tonic_polarity_convention_follows_the_input():
    dtype = np.dtype([("x", int), ("y", int), ("t", int), ("p", int)])
    events = np.zeros(4, dtype=dtype)
    events["t"] = [0, 100_000, 200_000, 300_000]
    events["p"] = [1, -1, 1, -1]
    out = tonic_plugin.PhotonNoise((30, 20, 2), PARAMS, 2.0, rng=0)(events)
    assert set(np.unique(out["p"]).tolist()) == {-1, 1}
    merged = tonic_plugin.PhotonNoise((30, 20, 1), PARAMS, 2.0, rng=0).noise(events)
    assert merged.size > 0 and np.all(merged["p"] == 0)


def test_tonic_rng_semantics(nmnist):
    events, sensor_size = nmnist
    a = tonic_plugin.PhotonNoise(sensor_size, PARAMS, 2.0, rng=5)
    b = tonic_plugin.PhotonNoise(sensor_size, PARAMS, 2.0, rng=5)
    # an int seed: the same sample gets the same noise, in any order and from any copy
    first = a(events)
    other_sample = events[: events.size // 2]
    a(other_sample)
    assert np.array_equal(a(events), first)
    assert np.array_equal(b(events), first)
    # DataLoader workers get the transform pickled: the copy adds the same noise
    assert np.array_equal(pickle.loads(pickle.dumps(a))(events), first)
    # ... but another sample (or another seed) gets other noise
    assert not np.array_equal(a.noise(other_sample), a.noise(events)[: a.noise(other_sample).size])
    assert not np.array_equal(tonic_plugin.PhotonNoise(sensor_size, PARAMS, 2.0, rng=6).noise(events), a.noise(events))
    # a Generator: new noise on every call, reproducible as a sequence
    g1 = tonic_plugin.PhotonNoise(sensor_size, PARAMS, 2.0, rng=np.random.default_rng(9))
    g2 = tonic_plugin.PhotonNoise(sensor_size, PARAMS, 2.0, rng=np.random.default_rng(9))
    s1 = [g1.noise(events) for _ in range(2)]
    s2 = [g2.noise(events) for _ in range(2)]
    assert not np.array_equal(s1[0], s1[1])
    assert all(np.array_equal(x, y) for x, y in zip(s1, s2))
    # None: fresh randomness on every call
    n = tonic_plugin.PhotonNoise(sensor_size, PARAMS, 2.0)
    assert not np.array_equal(n.noise(events), n.noise(events))


def test_tonic_threshold_mismatch_is_fixed_per_sensor(nmnist):
    """With eps_sigma > 0 the per-pixel thresholds are the sensor's: the same for every sample."""
    import dataclasses

    events, sensor_size = nmnist
    params = dataclasses.replace(PARAMS, eps_sigma=0.05)
    transform = tonic_plugin.PhotonNoise(sensor_size, params, 2.0, rng=2)
    thr = transform._thresholds.copy()
    transform(events)
    transform(events[:100])
    assert np.array_equal(transform._thresholds, thr) and thr.std() > 0.01
    assert np.array_equal(tonic_plugin.PhotonNoise(sensor_size, params, 2.0, rng=2)._thresholds, thr)


def test_tonic_scalar_lux_is_a_uniform_map(nmnist):
    events, sensor_size = nmnist
    scalar = tonic_plugin.PhotonNoise(sensor_size, PARAMS, 1.5, rng=4)(events)
    uniform = tonic_plugin.PhotonNoise(sensor_size, PARAMS, np.full((34, 34), 1.5), rng=4)(events)
    assert np.array_equal(scalar, uniform)


def test_tonic_bad_input():
    dtype = np.dtype([("x", int), ("y", int), ("t", int), ("p", int)])
    with pytest.raises(InputError, match="transposed"):
        tonic_plugin.PhotonNoise((30, 20, 2), PARAMS, np.ones((30, 20)))
    with pytest.raises(InputError, match="negative"):
        tonic_plugin.PhotonNoise((30, 20, 2), PARAMS, -1.0)
    with pytest.raises(ParameterError, match="sensor_size"):
        tonic_plugin.PhotonNoise((30, 20), PARAMS, 1.0)
    with pytest.raises(ParameterError, match="rng"):
        tonic_plugin.PhotonNoise((30, 20, 2), PARAMS, 1.0, rng="seed")
    transform = tonic_plugin.PhotonNoise((30, 20, 2), PARAMS, 1.0, rng=0)
    outside = np.zeros(2, dtype=dtype)
    outside["x"] = [0, 30]
    with pytest.raises(InputError, match="outside sensor_size"):
        transform(outside)
    with pytest.raises(InputError, match="fields x, y, t, p"):
        transform(np.zeros(3, dtype=[("t", int), ("x", int), ("p", int)]))
    empty = np.zeros(0, dtype=dtype)
    assert transform(empty) is empty or transform(empty).size == 0


def test_tonic_bad_arguments_are_refused_at_construction():
    """Bad arguments are one clear error when the transform is made, not at its first call (in a DataLoader worker,
    under torch's traceback): threads, a sensor_size that is not whole numbers (it was truncated: 34.5 -> 34) and
    lux=None (it was "lux contains NaN or Inf values")."""
    with pytest.raises(ParameterError, match="threads must be a whole number >= 1"):
        tonic_plugin.PhotonNoise((34, 34, 2), PARAMS, 2.0, threads=0)
    with pytest.raises(ParameterError, match="whole numbers"):
        tonic_plugin.PhotonNoise((34.5, 34, 2), PARAMS, 2.0)
    with pytest.raises(InputError, match="lux must be a scalar or an .H, W. map .*got None"):
        tonic_plugin.PhotonNoise((34, 34, 2), PARAMS, None)
    assert tonic_plugin.PhotonNoise((34.0, 34.0, 2.0), PARAMS, 2.0).sensor_size == (34, 34, 2)


def test_tonic_sensor_beyond_the_memory_budget_is_one_clear_error(monkeypatch):
    """A sensor whose per-pixel state cannot fit is refused at construction, naming it (it was NumPy's MemoryError
    from the lux map, or a machine swapping while the maps were computed)."""
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "64M")
    with pytest.raises(ParameterError, match=r"1280x720 sensor would need .* more than the 67.1 MB EVNOISE_MAX_MEMORY"):
        tonic_plugin.PhotonNoise((1280, 720, 2), PARAMS, 2.0)
    assert tonic_plugin.PhotonNoise((34, 34, 2), PARAMS, 2.0, rng=0)(np.zeros(2, tonic.datasets.NMNIST.dtype)).size


def test_tonic_memory_check_of_a_sample_covers_the_calls_peak(monkeypatch):
    """The check of a sample's noise counts what a call holds at its peak (the kernel's columns, their sort, the
    noise and the merged output: about three items per event), not 32 bytes per event: with a budget below the
    call's real peak the sample is refused before the draw instead of passing the check and then taking more."""
    import tracemalloc

    transform = tonic_plugin.PhotonNoise((4, 4, 2), PARAMS, 100.0, rng=0)
    sample = np.zeros(3, dtype=tonic.datasets.NMNIST.dtype)
    sample["t"] = [0, 1, 20_000_000_000]  # 20,000 s: about 45,000 noise events on 16 pixels
    transform(sample[:2])  # the kernels compiled before the measurement
    tracemalloc.start()
    try:
        out = transform(sample)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert out.size > 20_000
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", str(int(0.95 * peak)))
    with pytest.raises(InputError, match="is the sample's t in microseconds"):
        transform(sample)


def test_tonic_seed_noise_depends_on_the_values_not_on_padding_bytes():
    """An int seed keys a sample's noise on its values: the padding of an aligned dtype (whatever np.empty left
    there) and the bytes of fields a view leaves out changed it, so the same sample got other noise."""
    aligned = np.dtype([("x", np.int16), ("y", np.int16), ("t", np.int64), ("p", bool)], align=True)
    assert aligned.itemsize > 13  # padded
    gen = np.random.default_rng(1)
    cols = {"x": gen.integers(0, 34, 300), "y": gen.integers(0, 34, 300), "t": np.sort(gen.integers(0, 300_000, 300)),
            "p": gen.integers(0, 2, 300)}

    def sample(dtype, fill=0):
        events = np.full(300 * dtype.itemsize, fill, dtype=np.uint8).view(dtype)
        for name in dtype.names:
            events[name] = cols.get(name, fill)
        return events

    transform = tonic_plugin.PhotonNoise((34, 34, 2), PARAMS, 2.0, rng=0)
    noise = transform.noise(sample(aligned, 0))
    assert noise.size > 100 and np.array_equal(transform.noise(sample(aligned, 0xAB)), noise)
    # the packed dtype of the same fields (tonic's events_struct: what the noise has always been keyed on) gets it too
    assert tonic.io.events_struct.names == aligned.names and tonic.io.events_struct.itemsize == 13
    assert np.array_equal(transform.noise(sample(tonic.io.events_struct)), noise)
    # a view of four of a sample's five fields: the fifth (outside the view) does not change the noise
    wide = np.dtype([("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8"), ("label", "<i8")])
    views = [sample(wide, fill)[["x", "y", "t", "p"]] for fill in (0, 7)]
    assert views[0].dtype.itemsize == 40
    assert np.array_equal(transform.noise(views[0]), transform.noise(views[1]))
    assert np.array_equal(transform(views[1])[["x", "y", "t", "p"]], transform(views[0])[["x", "y", "t", "p"]])


# --------------------------------------------------------------------------------------
# v2e (a stand-in following v2e's documented EventEmulator interface)
# --------------------------------------------------------------------------------------
class StandInEmulator:
    """What v2e's ``EventEmulator`` documents, in a few lines.

    ``generate_events(new_frame, t_frame)``: ``new_frame`` a luma frame ``[height, width]`` in
    0-255, ``t_frame`` seconds; log intensity through v2e's lin-log mapping (linear below grey 20);
    the first call initialises the memorised log intensity and returns None; later calls return
    float32 rows ``[t, x, y, +-1]`` for every whole threshold crossed, spread over the interval
    as v2e does (``t_prev + dt * (i + 1) / n_iters``), or None. ``t_frame`` going backwards is a
    ValueError; ``reset()`` makes the next frame initialise again.
    """

    def __init__(self, pos_thres=0.2, neg_thres=0.2, sigma_thres=0.0, cutoff_hz=0.0, leak_rate_hz=0.0,
                 refractory_period_s=0.0, shot_noise_rate_hz=0.0, log_input=False, device="cpu", **other_options):
        self.pos_thres, self.neg_thres = pos_thres, neg_thres
        self.shot_noise_rate_hz, self.leak_rate_hz = shot_noise_rate_hz, leak_rate_hz
        self.log_input = log_input
        self.num_events_total = 0
        self.frame_counter = 0
        self.reset()

    def reset(self):
        self.base_log_frame = None
        self.t_previous = 0.0

    @staticmethod
    def lin_log(x, threshold=20.0):
        x = np.asarray(x, dtype=np.float64)
        return np.round(np.where(x <= threshold, x * np.log(threshold) / threshold,
                                 np.log(np.maximum(x, threshold))), 8)

    def generate_events(self, new_frame, t_frame):
        self.frame_counter += 1
        log_frame = np.asarray(new_frame, np.float64) if self.log_input else self.lin_log(new_frame)
        if self.base_log_frame is None:
            self.base_log_frame = log_frame.copy()
            self.t_previous = t_frame
            return None
        if t_frame < self.t_previous:
            raise ValueError("this frame time must be later than previous frame time")
        diff = log_frame - self.base_log_frame
        n_pos = np.floor(np.maximum(diff, 0) / self.pos_thres).astype(int)
        n_neg = np.floor(np.maximum(-diff, 0) / self.neg_thres).astype(int)
        n_iters = int(max(n_pos.max(), n_neg.max()))
        rows = []
        for i in range(n_iters):
            t = self.t_previous + (t_frame - self.t_previous) * (i + 1) / n_iters
            for count, sign in ((n_pos, 1.0), (n_neg, -1.0)):
                ys, xs = np.nonzero(count >= i + 1)
                rows.extend((t, x, y, sign) for y, x in zip(ys, xs))
        self.base_log_frame += n_pos * self.pos_thres - n_neg * self.neg_thres
        self.t_previous = t_frame
        self.num_events_total += len(rows)
        return np.array(rows, dtype=np.float32) if rows else None


def _band_frame(height=32, width=64, levels=(0, 64, 128, 255)):
    frame = np.zeros((height, width))
    band = width // len(levels)
    for k, g in enumerate(levels):
        frame[:, k * band:(k + 1) * band] = g
    return frame


def _is_subsequence(sub, rows):
    """Every row of ``sub`` appears in ``rows``, identically and in the same order."""
    j = 0
    for row in rows:
        if j < len(sub) and np.array_equal(row, sub[j]):
            j += 1
    return j == len(sub)


def test_v2e_noise_counts_match_expected_rate_with_v2e_grey_levels():
    white_lux = 20.0
    levels = (0, 64, 128, 255)
    frame = _band_frame(levels=levels)
    fps, n_frames = 5.0, 6  # 1 s in five intervals (each frame costs one closed-form evaluation)
    wrapper = v2e_plugin.PhotonNoise(StandInEmulator(), PARAMS, white_lux, rng=11)
    first = wrapper.generate_events(frame, 0.0)
    assert first is None  # v2e initialises on the first frame; no interval yet, no noise
    rows = [wrapper.generate_events(frame, k / fps) for k in range(1, n_frames)]
    rows = np.concatenate([r for r in rows if r is not None])
    duration = (n_frames - 1) / fps
    # independent expectation: v2e treats grey as linear intensity, grey g -> white_lux * g / 255
    band = frame.shape[1] // len(levels)
    for k, g in enumerate(levels):
        lux = np.full((frame.shape[0], band), white_lux * g / 255.0)
        exp_on, exp_off = ev.expected_rate(lux, PARAMS).sum(axis=(1, 2)) * duration
        in_band = (rows[:, 1] >= k * band) & (rows[:, 1] < (k + 1) * band)
        _check_within(np.count_nonzero(in_band & (rows[:, 3] == 1)), exp_on, f"ON noise at grey {g}")
        _check_within(np.count_nonzero(in_band & (rows[:, 3] == -1)), exp_off, f"OFF noise at grey {g}")
    # sRGB decoding would put grey 128 at 4.3 lux instead of 10: a rate over 3x higher (the OFF floor of the
    # refitted preset adds the same 0.14/s to both), far outside the test's tolerance
    assert ev.expected_rate(np.full((1, 1), 0.2159 * white_lux), PARAMS).sum() > 3 * ev.expected_rate(
        np.full((1, 1), 10.0), PARAMS).sum()
    assert wrapper.signal_count == 0 and wrapper.noise_count == rows.shape[0]


def test_v2e_output_format_and_none_handling():
    frame = _band_frame(height=16, width=32)
    wrapper = v2e_plugin.PhotonNoise(StandInEmulator(), "evk3-hd", 4.0, rng=1)
    assert wrapper.generate_events(frame, 1.0) is None
    out = wrapper.generate_events(frame, 1.5)
    assert isinstance(out, np.ndarray) and out.dtype == np.float64 and out.ndim == 2 and out.shape[1] == 4
    t, x, y, p = out.T
    assert np.all(np.diff(t) >= 0) and t.min() >= 1.0 and t.max() < 1.5
    assert np.array_equal(x, np.round(x)) and x.min() >= 0 and x.max() < 32
    assert np.array_equal(y, np.round(y)) and y.min() >= 0 and y.max() < 16
    assert set(np.unique(p).tolist()) <= {-1.0, 1.0}
    # timestamps are whole microseconds, in seconds
    assert np.allclose(t * 1e6, np.round(t * 1e6), atol=1e-6)
    # no signal and (practically) no noise: None, as v2e returns
    bright = v2e_plugin.PhotonNoise(StandInEmulator(), PARAMS, 1e6, rng=1)
    bright_frame = np.full((8, 8), 255.0)
    assert bright.generate_events(bright_frame, 0.0) is None
    assert bright.generate_events(bright_frame, 0.01) is None
    # a zero-length interval adds nothing
    assert wrapper.generate_events(frame, 1.5) is None


def test_v2e_merging_keeps_the_signal_events_intact():
    h, w = 24, 48
    frames = []
    for k in range(12):  # a bright bar moving right over a mid-grey background
        f = np.full((h, w), 60.0)
        f[:, 3 * k:3 * k + 6] = 220.0
        frames.append(f)
    times = np.arange(len(frames)) * 0.01
    clean = StandInEmulator()
    wrapper = v2e_plugin.PhotonNoise(StandInEmulator(), PARAMS, 5.0, rng=2)
    n_signal = n_noise = 0
    for f, t in zip(frames, times):
        sig = clean.generate_events(f, t)
        out = wrapper.generate_events(f, t)
        if sig is None:
            n_noise_here = 0 if out is None else out.shape[0]
        else:
            assert out is not None and _is_subsequence(sig.astype(np.float64), out)
            n_noise_here = out.shape[0] - sig.shape[0]
            n_signal += sig.shape[0]
            assert np.all(np.diff(out[:, 0]) >= 0)
        n_noise += n_noise_here
    assert n_signal > 100 and n_noise > 10
    assert wrapper.signal_count == n_signal and wrapper.noise_count == n_noise
    # other attributes are the emulator's; its counts (what v2e prints) include the noise
    assert wrapper.num_events_total == wrapper.emulator.num_events_total == n_signal + n_noise


def test_merge_rows_keeps_an_unsorted_signal_in_its_order():
    signal = np.array([[0.1, 1, 1, 1], [0.3, 2, 2, -1], [0.2, 3, 3, 1], [0.4, 4, 4, 1]], dtype=np.float32)
    noise = np.array([[0.05, 9, 9, 1], [0.25, 9, 9, -1], [0.35, 9, 9, 1], [0.5, 9, 9, 1]])
    out = frames_plugin.merge_rows(signal, noise)
    assert np.array_equal(out[out[:, 1] != 9], signal.astype(np.float64))
    assert np.array_equal(out[out[:, 1] == 9], noise)
    np.testing.assert_allclose(out[:, 0], [0.05, 0.1, 0.25, 0.3, 0.2, 0.35, 0.4, 0.5], rtol=1e-6)
    assert frames_plugin.merge_rows(None, np.empty((0, 4))) is None
    assert np.array_equal(frames_plugin.merge_rows(None, noise), noise)


def test_v2e_same_seed_same_output_and_reset():
    frame = _band_frame(height=16, width=32)

    def run(seed):
        wrapper = v2e_plugin.PhotonNoise(StandInEmulator(), PARAMS, 20.0, rng=seed)
        outs = [wrapper.generate_events(frame * (1 + 0.5 * (k % 2)), k * 0.02) for k in range(6)]
        return wrapper, outs

    w1, a = run(3)
    _, b = run(3)
    _, c = run(4)
    assert all((x is None and y is None) or np.array_equal(x, y) for x, y in zip(a, b))
    assert not all((x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y))
                   for x, y in zip(a, c))
    w1.reset()
    assert w1.generate_events(frame, 10.0) is None  # the emulator initialises again, no interval
    assert w1.generate_events(frame, 10.5) is not None


def test_v2e_log_input_gives_the_same_illuminance():
    frame = _band_frame(height=16, width=32, levels=(1, 64, 128, 255))
    a = v2e_plugin.PhotonNoise(StandInEmulator(), PARAMS, 20.0, rng=5)
    b = v2e_plugin.PhotonNoise(StandInEmulator(log_input=True), PARAMS, 20.0, rng=5)
    assert b.log_input and not a.log_input
    np.testing.assert_allclose(b.frame_lux(np.log(frame)), a.frame_lux(frame), rtol=1e-12)
    a.generate_events(frame, 0.0)
    b.generate_events(np.log(frame), 0.0)
    out_a, out_b = a.generate_events(frame, 0.2), b.generate_events(np.log(frame), 0.2)
    assert out_a is not None and np.array_equal(out_a, out_b)


def test_v2e_warns_about_its_own_noise_and_rejects_bad_input():
    with pytest.warns(UserWarning, match="shot_noise_rate_hz=5"):
        v2e_plugin.PhotonNoise(StandInEmulator(shot_noise_rate_hz=5.0), PARAMS, 20.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        v2e_plugin.PhotonNoise(StandInEmulator(), PARAMS, 20.0)  # v2e's noise off: no warning
    with pytest.raises(ParameterError, match="white_lux"):
        v2e_plugin.PhotonNoise(StandInEmulator(), PARAMS, 0.0)
    with pytest.raises(ParameterError, match="generate_events"):
        v2e_plugin.PhotonNoise(object(), PARAMS, 20.0)
    emulator = StandInEmulator()
    wrapper = v2e_plugin.PhotonNoise(emulator, PARAMS, 20.0, rng=0)
    with pytest.raises(InputError, match="grey levels must be >= 0"):
        wrapper.generate_events(np.full((4, 4), -1.0), 0.0)
    with pytest.raises(InputError, match="luma"):
        wrapper.generate_events(np.zeros((4, 4, 3)), 0.0)
    wrapper.generate_events(np.zeros((4, 4)), 1.0)
    calls = emulator.frame_counter
    with pytest.raises(ParameterError, match="before the previous frame"):
        wrapper.generate_events(np.zeros((4, 4)), 0.5)
    with pytest.raises(InputError, match="shape"):
        wrapper.generate_events(np.zeros((5, 4)), 2.0)
    assert emulator.frame_counter == calls  # rejected before the emulator saw the frame


def test_v2e_frame_times_out_of_range_are_one_clear_error(monkeypatch):
    """A frame interval whose noise cannot fit in memory (frame times in another unit than seconds) is refused before
    the emulator sees the frame (it was drawn: NumPy's MemoryError, or memory past the budget), a frame time beyond
    2**62 microseconds is refused (it hung in the kernel at the next frame), and so are bad threads at construction
    (they were found at the second frame)."""
    emulator = StandInEmulator()
    wrapper = v2e_plugin.PhotonNoise(emulator, PARAMS, 20.0, rng=0)
    frame = np.full((16, 32), 100.0)
    assert wrapper.generate_events(frame, 0.0) is None
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "16M")
    calls = emulator.frame_counter
    with pytest.raises(ParameterError, match=r"the photon noise of the 2000 s since the previous frame .*"
                                             r"EVNOISE_MAX_MEMORY; is t_frame in seconds\?"):
        wrapper.generate_events(frame, 2000.0)  # about 330,000 events: 85 MB at the peak with v2e's writers
    assert emulator.frame_counter == calls  # rejected before the emulator saw the frame
    assert wrapper.generate_events(frame, 0.5) is not None  # and the wrapper goes on
    with pytest.raises(ParameterError, match=r"2\*\*62 microseconds"):
        v2e_plugin.PhotonNoise(StandInEmulator(), PARAMS, 20.0, rng=0).generate_events(frame, 1e30)
    with pytest.raises(ParameterError, match="threads must be a whole number >= 1"):
        v2e_plugin.PhotonNoise(StandInEmulator(), PARAMS, 20.0, threads=0)


def test_v2e_frame_more_trials_after_the_first_than_the_stream_counts_is_refused_before_the_emulator():
    """At a 1 MHz trial rate, 5e9 s after the first frame is past the 2**52 trials the noise stream counts: the stream
    refused it, but only after the emulator had taken the frame (the two out of step)."""
    emulator = StandInEmulator()
    quiet = PARAMS.replace(trial_rate_hz=1e6, eps_pos=20.0, eps_neg=20.0, leak_on_hz=0.0, leak_off_hz=0.0)
    wrapper = v2e_plugin.PhotonNoise(emulator, quiet, 20.0, rng=0)  # no noise to speak of: the memory check passes
    frame = np.full((4, 4), 100.0)
    assert wrapper.generate_events(frame, 0.0) is None
    calls = emulator.frame_counter
    with pytest.raises(ParameterError, match=r"the time since the first frame .* more than the 2\*\*52"):
        wrapper.generate_events(frame, 5e9)
    assert emulator.frame_counter == calls


# --------------------------------------------------------------------------------------
# the plugin guide's snippets (docs/guides/plugins.md) run as written
# --------------------------------------------------------------------------------------
def _guide_snippet(heading):
    text = (Path(__file__).resolve().parents[1] / "docs" / "guides" / "plugins.md").read_text(encoding="utf-8")
    match = re.search(rf"^## {re.escape(heading)}\n(.*?)(?=^## |\Z)", text, flags=re.S | re.M)
    assert match, f"docs/guides/plugins.md has no section '## {heading}'"
    blocks = re.findall(r"```python\n(.*?)```", match.group(1), flags=re.S)
    assert blocks, f"docs/guides/plugins.md section '{heading}' has no python snippet"
    return "\n".join(blocks)


def test_guide_tonic_snippet_runs():
    namespace = {}
    exec(compile(_guide_snippet("tonic"), "plugins.md:tonic", "exec"), namespace)
    assert "frames" in namespace and namespace["frames"].ndim == 4


def test_guide_v2e_snippet_runs_against_the_stand_in(monkeypatch):
    v2ecore = types.ModuleType("v2ecore")
    emulator_module = types.ModuleType("v2ecore.emulator")
    emulator_module.EventEmulator = StandInEmulator
    v2ecore.emulator = emulator_module
    monkeypatch.setitem(sys.modules, "v2ecore", v2ecore)
    monkeypatch.setitem(sys.modules, "v2ecore.emulator", emulator_module)
    namespace = {}
    exec(compile(_guide_snippet("v2e"), "plugins.md:v2e", "exec"), namespace)
    assert namespace["events"] is not None and namespace["events"].shape[1] == 4


def test_v2e_setting_an_emulator_attribute_reaches_the_emulator():
    """v2e.py sets ``emulator.output_width`` on what it takes for the emulator: the wrapper passes such
    assignments on, and keeps its own attributes."""
    emulator = StandInEmulator()
    wrapper = v2e_plugin.PhotonNoise(emulator, PARAMS, 10.0, rng=0)
    wrapper.t_previous = 0.5
    wrapper.pos_thres = 0.3
    assert emulator.t_previous == 0.5 and emulator.pos_thres == 0.3 and "pos_thres" not in vars(wrapper)
    wrapper.log_input = True  # the wrapper's own (the emulator has one too)
    assert wrapper.log_input is True and emulator.log_input is False
    wrapper.new_name = 1  # not the emulator's: stays on the wrapper
    assert wrapper.new_name == 1 and not hasattr(emulator, "new_name")


def test_v2e_with_memory_beyond_the_table_budget_runs_trial_by_trial(monkeypatch):
    """Reset memory on a sensor whose chains' tables would pass the budget (lowered here: davis346's mismatch gives
    nearly a chain per pixel) runs through the v2e wrapper (its NoiseStream goes trial by trial) instead of being
    refused: the noise of each grey band is within k sigma of what simulate_events expects of that band's light and
    the stream's own threshold and background maps (the chains' rates; Poisson's sigma is ample for the
    under-dispersed counts of memory pixels)."""
    from evnoise.terms import memory

    monkeypatch.setattr(memory, "MAX_TABLE_STATES", 10)
    params = ev.load_preset("davis346").replace(reset_memory=0.5, leak_regularity=0.0, hot_pixel_regularity=0.0)
    white_lux, levels = 20.0, (32, 128, 255)
    frame = _band_frame(height=16, width=48, levels=levels)
    wrapper = v2e_plugin.PhotonNoise(StandInEmulator(), params, white_lux, rng=3)
    assert wrapper.generate_events(frame, 0.0) is None
    rows = [wrapper.generate_events(frame, k / 10.0) for k in range(1, 21)]
    rows = np.concatenate([r for r in rows if r is not None])
    stream = wrapper._stream
    assert stream._trials is not None
    maps = [np.reshape(m, (2, *frame.shape)) for m in ((stream._eps_on, stream._eps_off), stream._bg)]
    band = frame.shape[1] // len(levels)
    for k, g in enumerate(levels):
        lux = np.full((frame.shape[0], band), white_lux * g / 255.0)
        cols = slice(k * band, (k + 1) * band)
        expected = ev.iter_events(lux, params, 2.0, rng=0, thresholds=maps[0][:, :, cols],
                                  background=maps[1][:, :, cols]).expected_events
        in_band = (rows[:, 1] >= k * band) & (rows[:, 1] < (k + 1) * band)
        _check_within(np.count_nonzero(in_band), expected, f"noise at grey {g}")


def test_tonic_off_polarity_of_a_sample_with_only_on_events():
    """A +-1 dataset's sample holding only ON events cannot show its OFF value: its OFF noise got 0, which tonic's
    ToFrame and ToVoxelGrid then read as another polarity than the dataset's -1. ``off_polarity`` says it."""
    dtype = np.dtype([("x", int), ("y", int), ("t", int), ("p", int)])
    events = np.zeros(4, dtype=dtype)
    events["t"] = [0, 100_000, 200_000, 300_000]
    events["p"] = 1
    guessed = tonic_plugin.PhotonNoise((30, 20, 2), PARAMS, 2.0, rng=0).noise(events)
    told = tonic_plugin.PhotonNoise((30, 20, 2), PARAMS, 2.0, rng=0, off_polarity=-1).noise(events)
    assert set(np.unique(guessed["p"]).tolist()) == {0, 1}  # the sample's own (ambiguous) convention
    assert set(np.unique(told["p"]).tolist()) == {-1, 1}
    assert np.array_equal(told["t"], guessed["t"]) and np.array_equal(told["p"] == 1, guessed["p"] == 1)
    assert "off_polarity=-1" in repr(tonic_plugin.PhotonNoise((30, 20, 2), PARAMS, 2.0, off_polarity=-1))
    for bad in (1, True, "-1", -1.5, np.False_, np.array([0, -1])):
        with pytest.raises(ParameterError, match="off_polarity must be 0, -1 or None"):
            tonic_plugin.PhotonNoise((30, 20, 2), PARAMS, 2.0, off_polarity=bad)
    flags = np.zeros(2, dtype=[("x", int), ("y", int), ("t", int), ("p", bool)])
    with pytest.raises(InputError, match="p field is bool"):
        tonic_plugin.PhotonNoise((30, 20, 2), PARAMS, 2.0, off_polarity=-1)(flags)


def test_tonic_noise_of_float_times_stays_inside_the_samples_span():
    """Float times: noise times are whole microseconds, and those of [floor(min t), ceil(max t)] fell up to 1 us
    outside the sample (before its first event or after its last); a sample within one microsecond got noise. A
    trial per microsecond makes a 1 us span's noise countable (about 17 events)."""
    hot = PARAMS.replace(trial_rate_hz=1e6)
    dtype = np.dtype([("x", np.int16), ("y", np.int16), ("t", np.float64), ("p", np.int8)])
    events = np.zeros(2, dtype=dtype)
    events["t"] = [0.5, 1.75]  # holds one whole microsecond: t = 1
    transform = tonic_plugin.PhotonNoise((30, 20, 2), hot, 2.0, rng=0)
    noise = transform.noise(events)
    assert noise.size > 0 and np.all(noise["t"] == 1.0)
    rate = float(ev.expected_rate(np.full((20, 30), 2.0), hot).sum())
    _check_within(noise.size, rate * 1e-6, "noise of the one whole microsecond")
    events["t"] = [7.25, 7.75]  # no whole microsecond inside
    assert transform.noise(events).size == 0 and transform(events).size == 2
