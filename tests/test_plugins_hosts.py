"""evnoise's plugins and files inside the real host tools: a torch DataLoader with forked workers running
the tonic transform, tonic's own transforms after it, v2e's emulator writing its own files, and
iniVation's dv-processing reading evnoise's ``.aedat4``.

Each host is optional: its tests skip when the host is not installed.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev

ROOT = Path(__file__).resolve().parents[1]


def _run_python(code: str, timeout: float = 600.0) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter (the timeout only guards against a hang)."""
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)


def _sample(dtype, n=400, span_us=300_000, seed=1, size=34):
    gen = np.random.default_rng(seed)
    events = np.zeros(n, dtype=dtype)
    events["x"], events["y"] = gen.integers(0, size, n), gen.integers(0, size, n)
    events["t"], events["p"] = np.sort(gen.integers(0, span_us, n)), gen.integers(0, 2, n)
    return events


# --------------------------------------------------------------------------------------
# tonic and torch
# --------------------------------------------------------------------------------------
DATALOADER_SCRIPT = """
    import json, sys
    import numpy as np
    import torch
    from torch.utils.data import DataLoader, Dataset
    from evnoise.plugins.tonic import PhotonNoise

    DTYPE = np.dtype([("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")])  # tonic's NMNIST dtype
    N = 8

    def sample(i):
        gen = np.random.default_rng(100 + i)
        ev = np.zeros(300, DTYPE)
        ev["x"], ev["y"] = gen.integers(0, 34, 300), gen.integers(0, 34, 300)
        ev["t"], ev["p"] = np.sort(gen.integers(0, 300_000, 300)), gen.integers(0, 2, 300)
        return ev

    class Samples(Dataset):
        def __init__(self, transform, same):
            self.transform, self.same = transform, same
        def __len__(self):
            return N
        def __getitem__(self, i):
            out = self.transform(sample(0 if self.same else i))
            return torch.from_numpy(np.stack([out[f] for f in "xytp"]))

    def epoch(transform, same):
        loader = DataLoader(Samples(transform, same), batch_size=None, num_workers=2,
                            multiprocessing_context="fork")
        return [a.numpy().tobytes().hex() for a in loader]

    seeded = PhotonNoise((34, 34, 2), "evk3-hd", 2.0, rng=7)
    drawn = PhotonNoise((34, 34, 2), "evk3-hd", 2.0, rng=np.random.default_rng(3))
    # a call in the main process first (looking at a sample): the simulator's set-up has run here
    parent = [np.stack([seeded(sample(i))[f] for f in "xytp"]).tobytes().hex() for i in range(N)]
    drawn(sample(0))
    # dvs128: threshold mismatch, hot pixels and the regular background timer (another kernel path)
    timer = PhotonNoise((34, 34, 2), "dvs128", 2.0, rng=7)
    parent_timer = [np.stack([timer(sample(i))[f] for f in "xytp"]).tobytes().hex() for i in range(N)]
    # reset memory with mismatch beyond the table budget (lowered here; the workers inherit it): trial by trial
    import evnoise as ev
    from evnoise.terms import memory
    memory.MAX_TABLE_STATES = 10
    davis = ev.load_preset("davis346").replace(reset_memory=0.3, leak_regularity=0.0, hot_pixel_regularity=0.0)
    trials = PhotonNoise((34, 34, 2), davis, 2.0, rng=7)
    assert trials._memory.tables is None
    parent_trials = [np.stack([trials(sample(i))[f] for f in "xytp"]).tobytes().hex() for i in range(N)]
    out = {"parent": parent, "seeded": [epoch(seeded, False), epoch(seeded, False)],
           "parent_timer": parent_timer, "timer": epoch(timer, False),
           "parent_trials": parent_trials, "trials": epoch(trials, False)}
    torch.manual_seed(11)
    out["drawn"] = [epoch(drawn, True), epoch(drawn, True)]
    torch.manual_seed(11)
    out["drawn_again"] = epoch(drawn, True)
    json.dump(out, sys.stdout)
"""


@pytest.fixture(scope="module")
def dataloader_run():
    pytest.importorskip("torch")
    pytest.importorskip("tonic")
    if sys.platform != "linux":
        pytest.skip("the fork start method of DataLoader workers is the Linux default")
    proc = _run_python(DATALOADER_SCRIPT)
    assert proc.returncode == 0, f"the DataLoader run failed:\n{proc.stderr[-3000:]}"
    return json.loads(proc.stdout)


@pytest.mark.long
def test_tonic_transform_runs_in_forked_dataloader_workers_after_a_call_in_the_parent(dataloader_run):
    """Two forked workers, two epochs, after the transform ran in the main process (no OpenMP pool in a worker;
    also with the regular timer and with reset memory run trial by trial); an int seed gives every sample the noise it
    gets in the main process, in any worker and epoch."""
    parent = dataloader_run["parent"]
    assert len(set(parent)) == len(parent)
    for epoch in dataloader_run["seeded"]:
        assert epoch == parent
    assert dataloader_run["timer"] == dataloader_run["parent_timer"]
    assert dataloader_run["trials"] == dataloader_run["parent_trials"]  # reset memory beyond the table budget


def test_tonic_generator_never_repeats_across_workers_and_epochs(dataloader_run):
    """Every item is the same sample: with a Generator each of the 16 outputs (2 workers x 4 items x 2 epochs)
    is new noise, and the same torch seed gives the same epoch again."""
    outputs = [item for epoch in dataloader_run["drawn"] for item in epoch]
    assert len(set(outputs)) == len(outputs)
    assert dataloader_run["drawn_again"] == dataloader_run["drawn"][0]


def test_tonic_call_does_not_recompute_the_per_pixel_probabilities(monkeypatch):
    """The probabilities depend only on the constructor's lux map: they are computed once, not per sample."""
    import evnoise._engine as engine
    from evnoise.plugins.tonic import PhotonNoise

    calls = []
    original = engine.trial_probabilities

    def counted(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(engine, "trial_probabilities", counted)
    transform = PhotonNoise((34, 34, 2), "dvs128", np.linspace(0.5, 20.0, 34 * 34).reshape(34, 34), rng=0)
    assert calls  # computed at construction
    calls.clear()
    sample = _sample(np.dtype([("x", int), ("y", int), ("t", int), ("p", int)]))
    for k in range(3):
        assert transform(sample[: 100 * (k + 1)]).size > 100 * (k + 1)
    assert not calls


@pytest.mark.parametrize("preset", ["evk3-hd", "dvs128", "davis346", "evk4"])
def test_tonic_noise_is_exactly_simulate_events_for_the_sample_span(preset):
    """The precomputed path draws what ``simulate_events`` draws for the sample's span with the same generator
    (thresholds and background maps first, then the kernel key), event for event."""
    from evnoise.plugins.tonic import PhotonNoise

    params = ev.load_preset(preset)
    lux = np.linspace(0.2, 30.0, 20 * 26).reshape(20, 26)
    sample = _sample(np.dtype([("x", int), ("y", int), ("t", int), ("p", int)]), size=20)
    sample["t"] += 5_000_123
    transform = PhotonNoise((26, 20, 2), params, lux, rng=np.random.default_rng(42))
    noise = transform.noise(sample)
    t0, t1 = int(sample["t"].min()), int(sample["t"].max())
    expected = ev.simulate_events(lux, params, (t1 - t0 + 1) * 1e-6, rng=np.random.default_rng(42), t_start_us=t0)
    assert noise.size == expected.size > 50
    for f in "txy":
        assert np.array_equal(noise[f], expected[f])
    assert np.array_equal(noise["p"] == 1, expected["p"] == 1)


def test_tonic_unsorted_sample_comes_out_sorted_with_the_same_noise():
    """A sample not sorted by t gets the noise it would get anyway, merged by one stable sort (input events first
    at equal times, in their input order)."""
    from evnoise.plugins.tonic import PhotonNoise

    sample = _sample(np.dtype([("x", int), ("y", int), ("t", int), ("p", int)]))
    sample["t"] = sample["t"] // 1000 * 1000  # many equal times
    shuffled = sample[np.random.default_rng(0).permutation(sample.size)]
    transform = PhotonNoise((34, 34, 2), "evk3-hd", 2.0, rng=3)
    out = transform(shuffled)
    merged = np.concatenate([shuffled, transform.noise(shuffled)])
    assert np.array_equal(out, merged[np.argsort(merged["t"], kind="stable")])
    assert out.size > sample.size and np.all(np.diff(out["t"]) >= 0)


@pytest.mark.parametrize("dtype", [ev.EVENT_DTYPE, np.dtype([("x", int), ("y", int), ("t", int), ("p", int)])])
def test_tonic_transforms_accept_the_output(dtype):
    """tonic's ToFrame, ToVoxelGrid, ToTimesurface and Denoise after PhotonNoise, also on evnoise's own event
    dtype (whose unsigned ``p`` made ToVoxelGrid raise OverflowError: it writes -1 for OFF)."""
    tonic = pytest.importorskip("tonic")
    from evnoise.plugins.tonic import PhotonNoise

    sensor_size = (34, 34, 2)
    sample = _sample(dtype)
    transform = PhotonNoise(sensor_size, "evk3-hd", 2.0, rng=0)
    out = transform(sample)
    assert out.dtype.names == dtype.names and out["p"].dtype.kind == "i"
    added = out[np.argsort(out["t"], kind="stable")]
    noise = transform.noise(sample)
    assert noise.dtype == out.dtype and out.size == sample.size + noise.size
    # the call adds exactly the noise that noise() gives, input events first at equal times
    merged = np.concatenate([sample.astype(out.dtype), noise])
    assert np.array_equal(out, merged[np.argsort(merged["t"], kind="stable")]) and np.array_equal(added, out)
    assert out["p"].dtype.itemsize == dtype["p"].itemsize
    T = tonic.transforms
    frames = T.ToFrame(sensor_size, n_time_bins=3)(out)
    assert frames.shape == (3, 2, 34, 34) and out.size - 1 <= frames.sum() <= out.size  # tonic's last bin edge
    voxels = T.ToVoxelGrid(sensor_size, n_time_bins=5)(out.copy())
    assert voxels.shape == (5, 1, 34, 34) and np.isfinite(voxels).all()
    surfaces = T.ToTimesurface(sensor_size, dt=10_000, tau=30_000)(out)
    assert surfaces.shape[1:] == (2, 34, 34)
    kept = T.Denoise(filter_time=10_000)(out)
    assert 0 < kept.size <= out.size and kept.dtype == out.dtype


# --------------------------------------------------------------------------------------
# AEDAT 4 in iniVation's reader
# --------------------------------------------------------------------------------------
def _aedat4_with_metadata(tmp_path):
    pytest.importorskip("faery", reason="writing .aedat4 needs faery")
    from evnoise.io import write_aedat4

    events = ev.simulate_events(np.full((24, 30), 5.0), ev.load_preset("evk3-hd"), 2.0, rng=3)
    path = write_aedat4(tmp_path / "noise.aedat4", [events], (24, 30),
                        attrs={"params": ev.load_preset("evk3-hd"), "seed": 3, "lux": 5.0, "note": "test"})
    return path, events


def _description_xml(path):
    import xml.etree.ElementTree as ET

    data = Path(path).read_bytes()
    start, end = data.index(b"<dv"), data.index(b"</dv>") + len(b"</dv>")
    return ET.fromstring(data[start:end].decode("utf-8"))


def test_aedat4_description_has_one_root_node_with_evnoise_under_the_stream(tmp_path):
    """DV's description may have only one root node: evnoise's attributes sit under the stream's node."""
    path, _ = _aedat4_with_metadata(tmp_path)
    root = _description_xml(path)
    assert [n.get("name") for n in root.findall("node")] == ["outInfo"]
    stream = root.find("node/node")
    assert stream.get("path") == "/mainloop/Recorder/outInfo/0/"
    assert {n.get("name") for n in stream.findall("node")} == {"info", "evnoise"}
    own = stream.find("node[@name='evnoise']")
    assert own.get("path") == "/mainloop/Recorder/outInfo/0/evnoise/"
    assert {a.get("key") for a in own.findall("attr")} >= {"seed", "lux_json", "params_json", "note"}
    # evnoise's own reader still finds them
    from evnoise.io import read_metadata

    meta = read_metadata(path)
    assert meta["seed"] == 3 and meta["lux"] == 5.0 and meta["note"] == "test" and meta["params"]["eps_pos"] > 0


def test_aedat4_opens_in_dv_processing_with_the_same_events(tmp_path):
    """iniVation's own reader (dv-processing, what DV uses) opens a file written with metadata."""
    dv = pytest.importorskip("dv_processing", reason="dv-processing is iniVation's reader: pip install dv-processing")
    path, events = _aedat4_with_metadata(tmp_path)
    recording = dv.io.MonoCameraRecording(str(path))
    assert recording.isEventStreamAvailable()
    assert tuple(recording.getEventResolution()) == (30, 24)
    batches = []
    while recording.isRunning():
        batch = recording.getNextEventBatch()
        if batch is not None and batch.size():
            batches.append(batch.numpy())
    got = np.concatenate(batches)
    assert got.size == events.size > 500
    assert np.array_equal(got["timestamp"], events["t"])
    assert np.array_equal(got["x"], events["x"]) and np.array_equal(got["y"], events["y"])
    assert np.array_equal(got["polarity"].astype(bool), events["p"] == 1)
    # and faery, and evnoise's reader, give the same events
    from evnoise.io import read_events

    own, _ = read_events(path)
    assert np.array_equal(own, events)


def test_aedat4_opens_in_the_aedat_package(tmp_path):
    """The ``aedat`` package (neuromorphic-drivers' AEDAT 4 decoder) reads the same events."""
    aedat = pytest.importorskip("aedat", reason="pip install aedat")
    path, events = _aedat4_with_metadata(tmp_path)
    decoder = aedat.Decoder(str(path))
    assert decoder.id_to_stream() == {0: {"type": "events", "width": 30, "height": 24}}
    got = np.concatenate([packet["events"] for packet in decoder if "events" in packet])
    assert np.array_equal(got["t"], events["t"])
    assert np.array_equal(got["x"], events["x"]) and np.array_equal(got["y"], events["y"])
    assert np.array_equal(got["on"], events["p"] == 1)


# --------------------------------------------------------------------------------------
# evnoise's own namespace
# --------------------------------------------------------------------------------------
def test_evnoise_io_is_an_attribute_and_import_stays_light():
    """``import evnoise; evnoise.io.read_metadata`` works (a fresh interpreter: no test imported it yet),
    and ``import evnoise`` alone still loads neither evnoise.io nor Numba."""
    proc = _run_python("""
        import sys
        import evnoise
        light = [m for m in ("evnoise.io", "evnoise.readers", "numba", "scipy") if m in sys.modules]
        print(light, callable(evnoise.io.read_metadata), callable(evnoise.readers.open_events),
              evnoise.plugins.__name__, "io" in dir(evnoise))
    """)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["[]", "True", "True", "evnoise.plugins", "True"]


# --------------------------------------------------------------------------------------
# v2e: its own files and counts
# --------------------------------------------------------------------------------------
def _bar_frames(n, height, width, bar=200.0):
    for k in range(n):
        frame = np.full((height, width), 40.0)
        frame[:, 6 * k:6 * k + 20] = bar  # a bright bar moving right
        yield frame, k / 100


def _signal_mask(signal, rows):
    """Positions of ``signal``'s rows inside ``rows`` (in order, identical); asserts they are all there."""
    mask = np.zeros(rows.shape[0], dtype=bool)
    wanted = list(map(tuple, signal.tolist()))
    j = 0
    for i, row in enumerate(map(tuple, rows.tolist())):
        if j < len(wanted) and row == wanted[j]:
            mask[i] = True
            j += 1
    assert j == signal.shape[0], f"only {j} of v2e's {signal.shape[0]} rows are in the output, in order"
    return mask


class FakeV2eWriter:
    """v2e's ``appendEvents`` writers' interface (AEDAT 2, AEDAT 4, text): rows ``[t_s, x, y, +-1]``, optional
    signal(1)/noise(0) labels; keeps microseconds as v2e's AEDAT writers truncate them (``int(t * 1e6)``), and
    the seconds as its text writer prints them (as float64)."""

    def __init__(self):
        self.t, self.us, self.xyp, self.labels = [], [], [], []

    def appendEvents(self, events, signnoise_label=None):  # noqa: N802 - v2e's name
        self.t.append(events[:, 0].astype(np.float64))
        self.us.append((1e6 * events[:, 0]).astype(np.int64))
        self.xyp.append(np.asarray(events[:, 1:], dtype=np.int64))
        self.labels.append(None if signnoise_label is None else np.asarray(signnoise_label, dtype=bool))


class FakeV2eEmulator:
    """v2e's ``EventEmulator`` as far as its outputs go: ``generate_events`` makes float32 rows (a threshold
    rule on the frame difference) and, before returning them, writes them itself as v2e does: converted to
    uint32 ``[t_us, x, y, p 0/1]`` into the ``dvs_h5_dataset`` (h5py, resized then ``[-n:] =``), handed to
    ``dvs_aedat2`` / ``dvs_aedat4`` / ``dvs_text`` through ``appendEvents`` (with ``signnoise_label`` when
    ``label_signal_noise``), ``frame_ev_idx_dataset[frame_counter - 1]`` set to the dataset's length, and
    ``num_events_total`` / ``_on`` / ``_off`` counted."""

    def __init__(self, h5_path, label_signal_noise=False):
        import h5py

        self.shot_noise_rate_hz = self.leak_rate_hz = 0.0
        self.label_signal_noise = label_signal_noise
        self.dvs_h5 = h5py.File(h5_path, "w")
        self.dvs_h5_dataset = self.dvs_h5.create_dataset("events", shape=(0, 4), maxshape=(None, 4), dtype="uint32")
        self.frame_ev_idx_dataset = self.dvs_h5.create_dataset("frame_idx", shape=(50,), dtype="uint64")
        self.dvs_aedat2, self.dvs_aedat4, self.dvs_text = FakeV2eWriter(), None, FakeV2eWriter()
        self.num_events_total = self.num_events_on = self.num_events_off = 0
        self.frame_counter = 0
        self.base = None
        self.t_previous = 0.0

    def generate_events(self, new_frame, t_frame):
        self.frame_counter += 1
        log = np.log(np.maximum(np.asarray(new_frame, np.float64), 20.0))
        events = np.zeros((0, 4), dtype=np.float32)
        if self.base is None:
            self.base = log
        else:
            diff = log - self.base
            rows = []
            for sign in (1, -1):
                ys, xs = np.nonzero(sign * diff > 0.2)
                ts = self.t_previous + (t_frame - self.t_previous) * (np.arange(ys.size) + 1) / (ys.size + 1)
                rows.append(np.stack([ts, xs, ys, np.full(ys.size, sign)], axis=1))
            events = np.concatenate(rows).astype(np.float32)
            events = events[np.argsort(events[:, 0], kind="stable")]
            self.base = np.where(np.abs(diff) > 0.2, log, self.base)
            on = int(np.count_nonzero(events[:, 3] > 0))
            self.num_events_on += on
            self.num_events_off += events.shape[0] - on
            self.num_events_total += events.shape[0]
        if len(events) > 0:
            label = np.ones(events.shape[0], dtype=bool) if self.label_signal_noise else None
            temp = np.array(events, dtype=np.float32)
            temp[:, 0] = temp[:, 0] * 1e6
            temp[temp[:, 3] == -1, 3] = 0
            temp = temp.astype(np.uint32)
            self.dvs_h5_dataset.resize(self.dvs_h5_dataset.shape[0] + temp.shape[0], axis=0)
            self.dvs_h5_dataset[-temp.shape[0]:] = temp
            for writer in (self.dvs_aedat2, self.dvs_aedat4, self.dvs_text):
                if writer is not None:
                    if self.label_signal_noise:
                        writer.appendEvents(events, signnoise_label=label)
                    else:
                        writer.appendEvents(events)
        self.frame_ev_idx_dataset[self.frame_counter - 1] = self.dvs_h5_dataset.shape[0]
        self.t_previous = t_frame
        return events if len(events) > 0 else None


def _check_v2e_outputs(rows, plain_rows, h5_events, frame_idx, n_noise):
    """What the wrapper returned (``rows``) is what the h5 holds; v2e's rows (``plain_rows``) are unchanged."""
    assert h5_events.shape == rows.shape and rows.shape[0] == plain_rows.shape[0] + n_noise and n_noise > 100
    mask = _signal_mask(plain_rows.astype(np.float64), rows)
    assert np.array_equal(h5_events[:, 1:3], rows[:, 1:3].astype(np.uint32))
    assert np.array_equal(h5_events[:, 3], (rows[:, 3] > 0).astype(np.uint32))
    # v2e's rows as v2e converts them (float32 t * 1e6, truncated); the noise at its exact microsecond
    v2e_us = (plain_rows[:, 0].astype(np.float32) * np.float32(1e6)).astype(np.uint32)
    assert np.array_equal(h5_events[mask, 0], v2e_us)
    assert np.array_equal(h5_events[~mask, 0], np.round(rows[~mask, 0] * 1e6).astype(np.uint32))
    assert np.all(np.diff(h5_events[:, 0].astype(np.int64)) >= 0)
    assert frame_idx[-1] == rows.shape[0]
    return mask


@pytest.mark.parametrize("labelled", [False, True])
def test_v2e_writers_get_the_noise_with_a_faithful_fake_emulator(tmp_path, labelled):
    """v2e writes its files inside generate_events: the wrapper hands v2e's writers the rows it returns."""
    h5py = pytest.importorskip("h5py")
    from evnoise.plugins.v2e import PhotonNoise

    frames = list(_bar_frames(12, 60, 90))
    plain = FakeV2eEmulator(tmp_path / "plain.h5")
    plain_rows = np.concatenate([r for r in (plain.generate_events(f, t) for f, t in frames) if r is not None])
    emulator = FakeV2eEmulator(tmp_path / "noisy.h5", label_signal_noise=labelled)
    wrapper = PhotonNoise(emulator, "evk3-hd", white_lux=10.0, rng=1)
    rows = np.concatenate([r for r in (wrapper.generate_events(f, t) for f, t in frames) if r is not None])
    emulator.dvs_h5.close()
    plain.dvs_h5.close()
    with h5py.File(tmp_path / "noisy.h5") as f:
        h5_events, frame_idx = f["events"][:], f["frame_idx"][: len(frames)]
    mask = _check_v2e_outputs(rows, plain_rows, h5_events, frame_idx, wrapper.noise_count)
    # the counts v2e prints
    assert emulator.num_events_total == rows.shape[0]
    assert emulator.num_events_on == int(np.count_nonzero(rows[:, 3] > 0))
    assert emulator.num_events_off == int(np.count_nonzero(rows[:, 3] < 0))
    # AEDAT writers (truncating t * 1e6) get the same microseconds as the h5; labels mark evnoise's rows as noise
    assert np.array_equal(np.concatenate(emulator.dvs_aedat2.us), h5_events[:, 0].astype(np.int64))
    assert np.array_equal(np.concatenate(emulator.dvs_text.t), rows[:, 0])  # the text writer prints the seconds
    for writer in (emulator.dvs_aedat2, emulator.dvs_text):
        xyp = np.concatenate(writer.xyp)
        assert np.array_equal(xyp[:, :2], h5_events[:, 1:3]) and np.array_equal(xyp[:, 2] > 0, h5_events[:, 3] == 1)
        if labelled:
            assert np.array_equal(np.concatenate(writer.labels), mask)
        else:
            assert all(lab is None for lab in writer.labels)


def test_v2e_frames_without_v2e_events_still_write_the_noise(tmp_path):
    """An interval where v2e has no event (it writes nothing) still gets its noise into v2e's files."""
    h5py = pytest.importorskip("h5py")
    from evnoise.plugins.v2e import PhotonNoise

    emulator = FakeV2eEmulator(tmp_path / "still.h5")
    wrapper = PhotonNoise(emulator, "evk3-hd", white_lux=10.0, rng=2)
    still = np.full((40, 50), 90.0)
    rows = [wrapper.generate_events(still, k / 10) for k in range(5)]
    assert rows[0] is None and all(r is not None for r in rows[1:])
    emulator.dvs_h5.close()
    with h5py.File(tmp_path / "still.h5") as f:
        assert f["events"].shape[0] == sum(r.shape[0] for r in rows[1:]) == wrapper.noise_count
        assert list(f["frame_idx"][:5]) == list(np.cumsum([0] + [r.shape[0] for r in rows[1:]]))
    assert np.concatenate(emulator.dvs_aedat2.us).size == wrapper.noise_count == emulator.num_events_total


def test_v2e_noise_turned_on_after_the_wrapper_is_made_is_warned_about(tmp_path):
    """``v2e.py --dvs_params noisy`` calls ``set_dvs_params`` after the emulator is made, which turns v2e's own noise
    back on: the wrapper checked only at construction and said nothing while v2e added its noise beside evnoise's."""
    import warnings

    pytest.importorskip("h5py")
    from evnoise.plugins.v2e import PhotonNoise

    emulator = FakeV2eEmulator(tmp_path / "later.h5")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        wrapper = PhotonNoise(emulator, "evk3-hd", white_lux=10.0, rng=2)
        wrapper.generate_events(np.full((40, 50), 90.0), 0.0)
        assert not caught
        emulator.shot_noise_rate_hz, emulator.leak_rate_hz = 5.0, 0.1  # what set_dvs_params('noisy') does
        for k in (1, 2, 3):
            wrapper.generate_events(np.full((40, 50), 90.0), k / 10)
    own = [w for w in caught if "adds its own noise" in str(w.message)]
    assert len(own) == 1 and "shot_noise_rate_hz=5" in str(own[0].message)  # once, naming the settings
    emulator.dvs_h5.close()


def _real_v2e():
    pytest.importorskip("v2ecore.emulator", reason="v2e is installed from https://github.com/SensorsINI/v2e")
    pytest.importorskip("h5py")
    from v2ecore.emulator import EventEmulator

    return EventEmulator


def _real_v2e_run(tmp_path, name, wrap):
    EventEmulator = _real_v2e()
    from evnoise.plugins.v2e import PhotonNoise

    emulator = EventEmulator(pos_thres=0.2, neg_thres=0.2, sigma_thres=0.03, cutoff_hz=0, shot_noise_rate_hz=0,
                             leak_rate_hz=0, seed=5, device="cpu", output_folder=str(tmp_path), dvs_h5=f"{name}.h5",
                             dvs_aedat2=f"{name}.aedat", dvs_aedat4=f"{name}.aedat4", output_width=240,
                             output_height=180)
    driver = PhotonNoise(emulator, "evk3-hd", white_lux=18.0, rng=0) if wrap else emulator
    frames = list(_bar_frames(6, 180, 240, bar=70.0))  # v2e's AEDAT 4 writer takes a Python step per event
    emulator.prepare_storage(len(frames), [t for _, t in frames])
    rows = np.concatenate([r for r in (driver.generate_events(f, t) for f, t in frames) if r is not None])
    emulator.cleanup()
    return rows, emulator, driver


def _read_v2e_aedat2(path):
    data = Path(path).read_bytes()
    pos = 0
    while data.startswith(b"#", pos):
        pos = data.index(b"\r\n", pos) + 2
    words = np.frombuffer(data[pos:], dtype=">i4").reshape(-1, 2)
    return words[:, 0], words[:, 1]  # address, timestamp


def test_v2e_event_emulator_files_hold_the_noise(tmp_path):
    """The real EventEmulator writing its dvs_h5, AEDAT 2 and AEDAT 4 files: each holds the rows the wrapper
    returns (v2e's own rows unchanged), and v2e's counts include the noise."""
    import h5py

    plain_rows, _, _ = _real_v2e_run(tmp_path, "plain", wrap=False)
    rows, emulator, wrapper = _real_v2e_run(tmp_path, "noisy", wrap=True)
    with h5py.File(tmp_path / "noisy.h5") as f:
        h5_events, frame_idx = f["events"][:], f["frame_idx"][:]
    _check_v2e_outputs(rows, plain_rows, h5_events, frame_idx, wrapper.noise_count)
    assert emulator.num_events_total == rows.shape[0] == emulator.num_events_on + emulator.num_events_off
    address, timestamp = _read_v2e_aedat2(tmp_path / "noisy.aedat")
    assert np.array_equal(timestamp, h5_events[:, 0].astype(np.int64))
    dv = pytest.importorskip("dv_processing")
    recording = dv.io.MonoCameraRecording(str(tmp_path / "noisy.aedat4"))
    got = []
    while recording.isRunning():
        batch = recording.getNextEventBatch()
        if batch is not None and batch.size():
            got.append(batch.numpy())
    got = np.concatenate(got)
    assert np.array_equal(got["timestamp"], h5_events[:, 0].astype(np.int64))
    assert np.array_equal(got["x"], h5_events[:, 1]) and np.array_equal(got["y"], h5_events[:, 2])


V2E_SCRIPT = '''
"""A stand-in for v2e's v2e.py: what it does with the EventEmulator (imported by name, created with its
noise options, its output size set as attributes, driven frame by frame, cleaned up, its counts printed)."""
import argparse
import sys

import numpy as np
from v2ecore.emulator import EventEmulator

# v2e's argument help reads class attributes of EventEmulator (v2e_args.py)
states = f"{EventEmulator.MODEL_STATES.keys()} {EventEmulator.SINGLE_PIXEL_STATES_FILENAME}"
parser = argparse.ArgumentParser()
parser.add_argument("--shot_noise_rate_hz", type=float, default=0.001)  # v2e's defaults: its own noise on
parser.add_argument("--leak_rate_hz", type=float, default=0.01)
parser.add_argument("--output_folder")
parser.add_argument("--dvs_h5")
args = parser.parse_args()
emulator = EventEmulator(pos_thres=0.2, neg_thres=0.2, sigma_thres=0.03, cutoff_hz=0, seed=5, device="cpu",
                         shot_noise_rate_hz=args.shot_noise_rate_hz, leak_rate_hz=args.leak_rate_hz,
                         output_folder=args.output_folder, dvs_h5=args.dvs_h5, output_width=240, output_height=180)
emulator.output_width, emulator.output_height = 240, 180
for k in range(6):
    frame = np.full((180, 240), 40.0)
    frame[:, 6 * k:6 * k + 20] = 70.0
    emulator.generate_events(frame, k / 100)
emulator.cleanup()
print(f"generated total {emulator.num_events_total} events")
sys.exit(0)
'''


class FakeV2eModuleEmulator(FakeV2eEmulator):
    """:class:`FakeV2eEmulator` with the constructor and class attributes of v2e's EventEmulator (for a stand-in
    ``v2ecore.emulator``)."""

    MODEL_STATES = {"new_frame": (0, 255)}
    SINGLE_PIXEL_STATES_FILENAME = "pixel-states.dat"

    def __init__(self, output_folder=None, dvs_h5=None, shot_noise_rate_hz=0.0, leak_rate_hz=0.0, output_width=None,
                 output_height=None, **options):
        super().__init__(Path(output_folder) / dvs_h5)
        self.shot_noise_rate_hz, self.leak_rate_hz = shot_noise_rate_hz, leak_rate_hz
        self.output_width, self.output_height = output_width, output_height

    def cleanup(self):
        self.dvs_h5.close()


@pytest.mark.parametrize("host", ["stand-in", "v2e"])
def test_v2e_entry_point_runs_v2e_script_with_the_noise(tmp_path, monkeypatch, capsys, host):
    """``python -m evnoise.plugins.v2e --params ... --white-lux ... -- <v2e.py args>``: v2e.py's own emulator
    is wrapped, v2e's noise is off, and its dvs_h5 and printed total hold the noise."""
    h5py = pytest.importorskip("h5py")
    from evnoise.plugins import v2e as plugin

    if host == "v2e":
        _real_v2e()
    else:
        fake = type(sys)("v2ecore.emulator")
        fake.EventEmulator = FakeV2eModuleEmulator
        monkeypatch.setitem(sys.modules, "v2ecore", type(sys)("v2ecore"))
        monkeypatch.setitem(sys.modules, "v2ecore.emulator", fake)
    import importlib

    original = importlib.import_module("v2ecore.emulator").EventEmulator
    script = tmp_path / "v2e.py"
    script.write_text(V2E_SCRIPT, encoding="utf-8")
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        status = plugin.main(["--params", "evk3-hd", "--white-lux", "18", "--seed", "0", "--v2e-script", str(script),
                              "--", "--output_folder", str(tmp_path), "--dvs_h5", "events.h5"])
    assert status == 0
    assert not [w for w in caught if "adds its own noise" in str(w.message)]
    out = capsys.readouterr()
    total = int(out.out.split("generated total ")[1].split()[0])
    added = int(out.err.split("evnoise: added ")[1].split()[0])
    with h5py.File(tmp_path / "events.h5") as f:
        assert f["events"].shape[0] == total
    assert added > 100 and total > added
    assert sys.modules["v2ecore.emulator"].EventEmulator is original  # restored after the run


@pytest.mark.parametrize("argv, message", [
    (["--params", "nope", "--white-lux", "18"], "unknown preset 'nope'"),
    (["--params", "evk3-hd", "--white-lux", "-1"], "--white-lux must be finite and > 0"),
    (["--params", "evk3-hd", "--white-lux", "18", "--v2e-script", "/no/such/v2e.py"], "cannot find v2e's v2e.py"),
])
def test_v2e_entry_point_bad_input_is_one_error_line(argv, message, capsys):
    from evnoise.plugins import v2e as plugin

    with pytest.raises(SystemExit) as exc:
        plugin.main([*argv, "--", "-i", "video.mp4"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
