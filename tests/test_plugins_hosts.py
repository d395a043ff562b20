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
    out = {"parent": parent, "seeded": [epoch(seeded, False), epoch(seeded, False)]}
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


def test_tonic_transform_runs_in_forked_dataloader_workers_after_a_call_in_the_parent(dataloader_run):
    """Two forked workers, two epochs, after the transform ran in the main process (no OpenMP pool in a worker);
    an int seed gives every sample the noise it gets in the main process, in any worker and epoch."""
    parent = dataloader_run["parent"]
    assert len(set(parent)) == len(parent)
    for epoch in dataloader_run["seeded"]:
        assert epoch == parent


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


@pytest.mark.parametrize("dtype", [ev.EVENT_DTYPE, np.dtype([("x", int), ("y", int), ("t", int), ("p", int)])])
def test_tonic_transforms_accept_the_output(dtype):
    """tonic's ToFrame, ToVoxelGrid, ToTimesurface and Denoise after PhotonNoise, also on evnoise's own event
    dtype (whose unsigned ``p`` made ToVoxelGrid raise OverflowError: it writes -1 for OFF)."""
    tonic = pytest.importorskip("tonic")
    from evnoise.plugins.tonic import PhotonNoise

    sensor_size = (34, 34, 2)
    sample = _sample(dtype)
    out = PhotonNoise(sensor_size, "evk3-hd", 2.0, rng=0)(sample)
    assert out.dtype.names == dtype.names and out["p"].dtype.kind == "i"
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
