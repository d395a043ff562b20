"""events.h5 writing and reading (evnoise.io): layout, round trip, atomicity, errors."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

import evnoise as ev
from evnoise import InputError, OutputError, ParameterError
from evnoise.events import make_events
from evnoise.io import EventWriter, read_events, read_metadata, write_events

h5py = pytest.importorskip("h5py")

SHAPE = (48, 64)  # (H, W)


def random_events(n, t_max_us, seed, shape=SHAPE, t_min_us=0):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t_min_us, t_max_us, n))
    return make_events(t, rng.integers(0, shape[1], n), rng.integers(0, shape[0], n), rng.integers(0, 2, n))


def leftovers(folder):
    """Files in ``folder`` other than the expected outputs (temporary files, for one)."""
    return sorted(p.name for p in folder.iterdir())


def dsec_slice(f, t0_ms, t1_ms):
    """What DSEC's EventSlicer does for a whole-millisecond window [t0_ms, t1_ms): index by ms_to_idx."""
    ms = f["ms_to_idx"]
    lo, hi = int(ms[t0_ms]), int(ms[t1_ms])
    return make_events(f["events/t"][lo:hi], f["events/x"][lo:hi], f["events/y"][lo:hi], f["events/p"][lo:hi])


# --------------------------------------------------------------------------------------
# round trip and layout
# --------------------------------------------------------------------------------------
def test_round_trip_is_bit_exact(tmp_path):
    events = random_events(50_000, 3_000_000, seed=1)
    params = ev.load_preset("evk3-hd")
    path = write_events(tmp_path / "ev.h5", events, SHAPE, {"params": params, "seed": 7, "source": "unit test"})
    got, meta = read_events(path)
    assert got.dtype == ev.EVENT_DTYPE
    assert got.tobytes() == events.tobytes()
    assert meta["shape"] == SHAPE and meta["width"] == 64 and meta["height"] == 48
    assert meta["n_events"] == events.size and meta["t_offset"] == 0
    assert meta["time_unit"] == "us" and meta["evnoise_version"] == ev.__version__
    assert meta["seed"] == 7 and meta["source"] == "unit test"
    assert ev.NoiseParams.from_dict(meta["params"]) == params
    assert leftovers(tmp_path) == ["ev.h5"]


def test_gzip_chunks_compressed_in_threads_read_back_exactly(tmp_path):
    """Whole chunks go through the thread pool, the last partial one is zero-padded; h5py decodes them all."""
    from evnoise.io import CHUNK_EVENTS

    rng = np.random.default_rng(11)
    n = 3 * CHUNK_EVENTS + 12_345  # three whole chunks and a partial one, appended in uneven pieces
    events = random_events(n, 9_000_000, seed=3)
    cuts = np.sort(rng.choice(np.arange(1, n), 9, replace=False))
    cuts[2] = cuts[1]  # an empty piece too
    with EventWriter(tmp_path / "ev.h5", SHAPE) as out:
        for piece in np.split(events, cuts):
            out.write(piece)
    with h5py.File(tmp_path / "ev.h5", "r") as f:
        for name in ("x", "y", "t", "p"):
            ds = f["events"][name]
            assert ds.shape == (n,) and ds.compression == "gzip" and ds.shuffle
            assert ds.id.get_num_chunks() == 4
            np.testing.assert_array_equal(ds[:], events[name])


def test_shuffle_deflate_matches_hdf5s_own_filters(tmp_path):
    """The bytes handed to HDF5 decode, with zlib and HDF5's unshuffle, to what HDF5's filters encode."""
    import zlib

    from evnoise._gzip_chunks import shuffle_deflate

    rng = np.random.default_rng(4)
    for dtype in (np.int64, np.uint16, np.uint8):
        values = rng.integers(0, 60_000, 4096).astype(dtype)
        with h5py.File(tmp_path / f"ref{np.dtype(dtype).name}.h5", "w") as f:
            ds = f.create_dataset("v", data=values, chunks=(4096,), compression="gzip", compression_opts=1,
                                  shuffle=True)
            mask, stored = ds.id.read_direct_chunk((0,))
        assert mask == 0
        assert zlib.decompress(shuffle_deflate(values, 1)) == zlib.decompress(stored)


def test_layout_with_plain_h5py(tmp_path):
    events = random_events(20_000, 2_500_000, seed=2)
    write_events(tmp_path / "ev.h5", events, SHAPE, t_end_us=2_500_000)
    with h5py.File(tmp_path / "ev.h5", "r") as f:
        for name, dtype in (("x", np.uint16), ("y", np.uint16), ("t", np.int64), ("p", np.uint8)):
            ds = f["events"][name]
            assert ds.dtype == dtype and ds.shape == (events.size,)
            assert ds.chunks is not None and ds.maxshape == (None,)
            assert ds.compression == "gzip" and ds.shuffle
            np.testing.assert_array_equal(ds[:], events[name])
        assert f["t_offset"].shape == () and f["t_offset"].dtype == np.int64 and f["t_offset"][()] == 0
        ms = f["ms_to_idx"][:]
        assert ms.dtype == np.uint64
        assert ms.size == 2501  # one entry per millisecond, 0 .. 2500 ms inclusive
        np.testing.assert_array_equal(ms, np.searchsorted(events["t"], np.arange(ms.size) * 1000, side="left"))
        assert ms[-1] == events.size
        assert f.attrs["width"] == 64 and f.attrs["height"] == 48 and f.attrs["time_unit"] == "us"


def test_incremental_writing_builds_the_same_file(tmp_path):
    events = random_events(30_000, 4_000_000, seed=3)
    # chunks of uneven sizes, with chunk boundaries inside a millisecond and between equal times
    events["t"][9_999:10_002] = events["t"][9_999]
    cuts = [0, 1, 10_000, 10_001, 17_777, 17_777, 29_999, 30_000]
    with EventWriter(tmp_path / "inc.h5", SHAPE, {"seed": 1}) as out:
        for lo, hi in zip(cuts[:-1], cuts[1:]):
            out.write(events[lo:hi])
    write_events(tmp_path / "once.h5", events, SHAPE, {"seed": 1})
    with h5py.File(tmp_path / "inc.h5", "r") as a, h5py.File(tmp_path / "once.h5", "r") as b:
        for key in ("events/x", "events/y", "events/t", "events/p", "ms_to_idx"):
            np.testing.assert_array_equal(a[key][:], b[key][:])
        np.testing.assert_array_equal(a["ms_to_idx"][:], np.searchsorted(
            events["t"], np.arange(a["ms_to_idx"].shape[0]) * 1000, side="left"))
    assert out.n_events == events.size


def test_dsec_style_slicing_returns_exactly_the_window(tmp_path):
    events = random_events(40_000, 5_000_000, seed=4)
    path = write_events(tmp_path / "ev.h5", events, SHAPE, t_end_us=5_000_000)
    rng = np.random.default_rng(5)
    windows = [(0, 1), (0, 5000), (4999, 5000), (1234, 1234)] + [
        tuple(sorted(rng.integers(0, 5001, 2))) for _ in range(20)]
    with h5py.File(path, "r") as f:
        for t0, t1 in windows:
            got = dsec_slice(f, t0, t1)
            mask = (events["t"] >= t0 * 1000) & (events["t"] < t1 * 1000)
            assert got.tobytes() == events[mask].tobytes(), (t0, t1)


def test_read_events_time_window(tmp_path):
    events = random_events(40_000, 3_000_000, seed=6, t_min_us=100)
    path = write_events(tmp_path / "ev.h5", events, SHAPE)
    rng = np.random.default_rng(7)
    windows = [(None, None), (None, 1_000_000), (2_000_000, None), (-50, 10), (0, 3_500_000),
               (2_999_999, 10_000_000), (5_000_000, 6_000_000), (1_000_500, 1_000_500)]
    windows += [tuple(sorted(int(v) for v in rng.integers(-1000, 3_100_000, 2))) for _ in range(20)]
    for t0, t1 in windows:
        got, _ = read_events(path, t0, t1)
        mask = np.ones(events.size, dtype=bool)
        if t0 is not None:
            mask &= events["t"] >= t0
        if t1 is not None:
            mask &= events["t"] < t1
        assert got.tobytes() == events[mask].tobytes(), (t0, t1)


def test_read_window_without_ms_to_idx(tmp_path):
    # a foreign file with only /events: the window is found by binary search
    events = random_events(5_000, 1_000_000, seed=8)
    with h5py.File(tmp_path / "bare.h5", "w") as f:
        for k in "xytp":
            f.create_dataset(f"events/{k}", data=events[k])
    got, meta = read_events(tmp_path / "bare.h5", 250_000, 750_000)
    mask = (events["t"] >= 250_000) & (events["t"] < 750_000)
    assert got.tobytes() == events[mask].tobytes()
    assert meta["shape"] is None and meta["t_offset"] == 0


def test_empty_and_compression_variants(tmp_path):
    path = write_events(tmp_path / "empty.h5", ev.events.empty_events(0), SHAPE, t_end_us=2500)
    got, meta = read_events(path)
    assert got.size == 0 and meta["n_events"] == 0
    with h5py.File(path, "r") as f:
        np.testing.assert_array_equal(f["ms_to_idx"][:], [0, 0, 0, 0])
    events = random_events(1000, 10_000, seed=9)
    for comp in ("lzf", None):
        path = write_events(tmp_path / f"{comp}.h5", events, SHAPE, compression=comp)
        assert read_events(path)[0].tobytes() == events.tobytes()
    with pytest.raises(ParameterError, match="compression"):
        write_events(tmp_path / "bad.h5", events, SHAPE, compression="zstd")


def test_attributes(tmp_path):
    attrs = {"seed": np.int64(3), "source": tmp_path / "img.png", "note": None, "list": [1, 2],
             "nested": {"a": 1.5}, "flag": True, "arr": np.arange(3)}
    path = write_events(tmp_path / "a.h5", random_events(10, 1000, seed=1), SHAPE, attrs)
    meta = read_metadata(path)
    assert meta["seed"] == 3 and meta["source"] == str(tmp_path / "img.png")
    assert "note" not in meta
    assert meta["list"] == [1, 2] and meta["nested"] == {"a": 1.5} and meta["flag"] is True
    np.testing.assert_array_equal(meta["arr"], [0, 1, 2])
    with pytest.raises(ParameterError, match="width"):
        write_events(tmp_path / "b.h5", random_events(10, 1000, seed=1), SHAPE, {"width": 5})
    with pytest.raises(ParameterError, match="unsupported type"):
        write_events(tmp_path / "c.h5", random_events(10, 1000, seed=1), SHAPE, {"obj": object()})
    assert leftovers(tmp_path) == ["a.h5"]


# --------------------------------------------------------------------------------------
# failures leave nothing behind
# --------------------------------------------------------------------------------------
def test_exception_inside_the_writer_leaves_no_file(tmp_path):
    events = random_events(5000, 1_000_000, seed=10)
    with pytest.raises(RuntimeError, match="boom"):
        with EventWriter(tmp_path / "ev.h5", SHAPE) as out:
            out.write(events[:2500])
            raise RuntimeError("boom")
    assert leftovers(tmp_path) == []


def test_failing_event_source_leaves_no_file(tmp_path):
    events = random_events(5000, 1_000_000, seed=11)

    def source():
        yield events[:1000]
        yield events[1000:2000]
        raise InputError("frame 3 is corrupt")

    with pytest.raises(InputError, match="frame 3"):
        with EventWriter(tmp_path / "ev.h5", SHAPE) as out:
            for chunk in source():
                out.write(chunk)
    assert leftovers(tmp_path) == []


def test_unsorted_chunks_abort_the_file(tmp_path):
    events = random_events(2000, 1_000_000, seed=12)
    with pytest.raises(InputError, match="not sorted across chunks"):
        with EventWriter(tmp_path / "ev.h5", SHAPE) as out:
            out.write(events[1000:])
            out.write(events[:1000])
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("change, message", [
    (lambda e: e["x"].__setitem__(0, 64), "outside the sensor"),
    (lambda e: e["t"].__setitem__(slice(0, 2), [5, 4]), "not sorted"),
    (lambda e: e["t"].__setitem__(0, -1), ">= 0"),
])
def test_bad_events_are_rejected(tmp_path, change, message):
    events = random_events(100, 1000, seed=13)
    events["t"][:2] = [1, 2]
    change(events)
    with pytest.raises(InputError, match=message):
        write_events(tmp_path / "ev.h5", events, SHAPE)
    assert leftovers(tmp_path) == []


def test_events_after_t_end_are_rejected(tmp_path):
    events = random_events(100, 2000, seed=14)
    with pytest.raises(InputError, match="t_end_us"):
        write_events(tmp_path / "ev.h5", events, SHAPE, t_end_us=int(events["t"][-1]))
    assert leftovers(tmp_path) == []


def test_existing_output_needs_overwrite(tmp_path):
    path = tmp_path / "ev.h5"
    path.write_bytes(b"precious")
    events = random_events(100, 1000, seed=15)
    with pytest.raises(OutputError, match="already exists"):
        write_events(path, events, SHAPE)
    assert path.read_bytes() == b"precious"
    write_events(path, events, SHAPE, overwrite=True)
    assert read_events(path)[0].tobytes() == events.tobytes()
    assert leftovers(tmp_path) == ["ev.h5"]


def test_unwritable_destinations(tmp_path):
    events = random_events(10, 1000, seed=16)
    with pytest.raises(OutputError, match="does not exist"):
        write_events(tmp_path / "no" / "such" / "ev.h5", events, SHAPE)
    (tmp_path / "afile").write_bytes(b"")
    with pytest.raises(OutputError, match="not a directory"):
        write_events(tmp_path / "afile" / "ev.h5", events, SHAPE)
    (tmp_path / "adir.h5").mkdir()
    with pytest.raises(OutputError, match="is a (directory|folder)"):
        write_events(tmp_path / "adir.h5", events, SHAPE, overwrite=True)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root can write anywhere")
def test_read_only_directory(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(OutputError, match="not writable"):
            write_events(ro / "ev.h5", random_events(10, 1000, seed=17), SHAPE)
    finally:
        ro.chmod(0o700)


def test_writer_checks_its_arguments(tmp_path):
    with pytest.raises(InputError, match="shape"):
        EventWriter(tmp_path / "ev.h5", (0, 5))
    with pytest.raises(ParameterError, match="t_end_us"):
        EventWriter(tmp_path / "ev.h5", SHAPE, t_end_us=-1)
    writer = EventWriter(tmp_path / "ev.h5", SHAPE)
    writer.close()
    with pytest.raises(OutputError, match="closed"):
        writer.write(random_events(5, 100, seed=1))
    assert leftovers(tmp_path) == ["ev.h5"]


# --------------------------------------------------------------------------------------
# reading bad files
# --------------------------------------------------------------------------------------
def test_read_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="not found.*missing.h5"):
        read_events(tmp_path / "missing.h5")
    (tmp_path / "text.h5").write_text("hello")
    with pytest.raises(InputError, match="text.h5"):
        read_events(tmp_path / "text.h5")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.create_dataset("data", data=np.arange(3))
    with pytest.raises(InputError, match=r"other.h5.*/events"):
        read_events(tmp_path / "other.h5")
    with h5py.File(tmp_path / "ragged.h5", "w") as f:
        for k, n in zip("xytp", (3, 3, 4, 3)):
            f.create_dataset(f"events/{k}", data=np.zeros(n, dtype=np.uint16))
    with pytest.raises(InputError, match="equal length"):
        read_events(tmp_path / "ragged.h5")


def test_lazy_exports():
    assert ev.write_events is write_events and ev.read_events is read_events and ev.EventWriter is EventWriter


# --------------------------------------------------------------------------------------
# AEDAT4 through faery (optional)
# --------------------------------------------------------------------------------------
def test_aedat4_round_trip_through_faery(tmp_path):
    faery = pytest.importorskip("faery")
    from evnoise.io import write_aedat4

    events = random_events(20_000, 2_000_000, seed=20, t_min_us=123)
    write_aedat4(tmp_path / "ev.aedat4", (events[i:i + 7000] for i in range(0, events.size, 7000)), SHAPE)
    stream = faery.events_stream_from_file(tmp_path / "ev.aedat4")
    assert stream.dimensions() == (SHAPE[1], SHAPE[0])
    got = stream.to_array()
    np.testing.assert_array_equal(got["t"], events["t"])  # times kept, not shifted to zero
    np.testing.assert_array_equal(got["x"], events["x"])
    np.testing.assert_array_equal(got["y"], events["y"])
    np.testing.assert_array_equal(got["on"], events["p"] == 1)
    assert leftovers(tmp_path) == ["ev.aedat4"]


def test_aedat4_failure_leaves_no_file(tmp_path):
    pytest.importorskip("faery")
    from evnoise.io import write_aedat4

    events = random_events(2000, 1_000_000, seed=21)

    def source():
        yield events[:1000]
        raise InputError("frame 3 is corrupt")

    with pytest.raises(InputError, match="frame 3"):
        write_aedat4(tmp_path / "ev.aedat4", source(), SHAPE)
    with pytest.raises(InputError, match="not sorted across chunks"):
        write_aedat4(tmp_path / "ev.aedat4", [events[1000:], events[:1000]], SHAPE)
    (tmp_path / "old.aedat4").write_bytes(b"x")
    with pytest.raises(OutputError, match="already exists"):
        write_aedat4(tmp_path / "old.aedat4", events, SHAPE)
    assert leftovers(tmp_path) == ["old.aedat4"]


# --------------------------------------------------------------------------------------
# t_offset (DSEC): foreign files and camera clocks far from 0
# --------------------------------------------------------------------------------------
def test_t_offset_is_honoured(tmp_path):
    events = random_events(3000, 2_000_000, seed=30)
    off = 1_633_953_690_000_000  # a Unix-time clock, as the DAVIS recordings have
    with h5py.File(tmp_path / "dsec.h5", "w") as f:  # what DSEC's tools write: stored t, /t_offset, no sizes
        for k in "xytp":
            f.create_dataset(f"events/{k}", data=events[k])
        f.create_dataset("t_offset", data=np.int64(off))
    got, meta = read_events(tmp_path / "dsec.h5")
    np.testing.assert_array_equal(got["t"], events["t"] + off)  # on the file's own clock
    assert meta["t_offset"] == off and meta["shape"] is None
    a, b = off + 500_000, off + 1_500_000
    got, _ = read_events(tmp_path / "dsec.h5", a, b)
    np.testing.assert_array_equal(got["t"], events["t"][(events["t"] >= 500_000) & (events["t"] < 1_500_000)] + off)
    got, meta = read_events(tmp_path / "dsec.h5", sensor="64x48", t_start=a * 1e-6, t_end=b * 1e-6)
    assert meta["shape"] == SHAPE and got.size == np.count_nonzero((events["t"] >= 500_000) & (events["t"] < 1_500_000))
    # the writer stores such a clock as t - t_offset, keeping /ms_to_idx short
    shifted = events.copy()
    shifted["t"] += off
    with EventWriter(tmp_path / "w.h5", SHAPE, t_offset_us=off, t_end_us=off + 2_000_000) as out:
        out.write(shifted)
    with h5py.File(tmp_path / "w.h5", "r") as f:
        assert int(f["t_offset"][()]) == off and f["ms_to_idx"].shape[0] == 2001
        np.testing.assert_array_equal(f["events/t"][:], events["t"])
    assert read_events(tmp_path / "w.h5")[0].tobytes() == shifted.tobytes()


# --------------------------------------------------------------------------------------
# output formats: the suffix decides (issue 17, item 3)
# --------------------------------------------------------------------------------------
def test_output_format_by_suffix(tmp_path):
    from evnoise.io import output_format

    assert [output_format(f"a{s}") for s in (".h5", ".HDF5", ".aedat4", ".raw", ".dat", ".es", ".csv")] == \
        ["h5", "h5", "aedat4", "evt3", "dat", "es", "csv"]
    with pytest.raises(ParameterError, match="unknown event file suffix '.txt'"):
        output_format("out.txt")
    with pytest.raises(ParameterError, match="suffix"):
        output_format("events")
    with pytest.raises(OutputError, match="folder"):
        output_format("outdir/")
    with pytest.raises(OutputError, match="folder"):
        output_format(tmp_path)


def test_cli_outputs_follow_the_suffix(tmp_path, capsys):
    from evnoise.cli import main

    png = tmp_path / "scene.png"
    from PIL import Image

    Image.fromarray(np.full((12, 16), 128, dtype=np.uint8)).save(png)
    for out in ("outdir/", "out.txt"):
        assert main(["simulate", str(png), "--out", str(tmp_path / out), "--duration", "0.1", "--seed", "1"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("evnoise: error:") and err.count("\n") == 1
    assert not (tmp_path / "outdir").exists() and not (tmp_path / "out.txt").exists()
    code = main(["-q", "simulate", str(png), "--out", str(tmp_path / "ev.h5"), "--duration", "2", "--seed", "4"])
    assert code == 0
    events, _ = read_events(tmp_path / "ev.h5")
    # separate --out sig.aedat4 writes AEDAT 4 (it wrote HDF5 under that name before)
    pytest.importorskip("faery")  # the writer of .aedat4 and .raw (not installable at a NumPy 1.x floor)
    assert main(["-q", "separate", str(tmp_path / "ev.h5"), "--out", str(tmp_path / "sig.aedat4"),
                 "--noise-out", str(tmp_path / "noise.raw")]) == 0
    assert (tmp_path / "sig.aedat4").read_bytes()[:10] == b"#!AER-DAT4"
    assert (tmp_path / "noise.raw").read_bytes()[:1] == b"%"
    sig, smeta = read_events(tmp_path / "sig.aedat4")
    noise, _ = read_events(tmp_path / "noise.raw")
    assert sig.size + noise.size == events.size and smeta["kind"] == "signal"
    # simulate --out x.aedat4 keeps the parameters and seed (item 7), and info reads the file
    assert main(["-q", "simulate", str(png), "--out", str(tmp_path / "ev.aedat4"), "--duration", "2", "--seed",
                 "4"]) == 0
    capsys.readouterr()
    assert main(["info", str(tmp_path / "ev.aedat4"), "--json"]) == 0
    import json

    info = json.loads(capsys.readouterr().out)
    assert info["events"] == events.size and info["seed"] == 4 and info["params"]["eps_pos"] > 0
    assert info["size_bytes"] == (tmp_path / "ev.aedat4").stat().st_size  # a number, not "91.4 kB"


def test_unwritable_output_is_one_clean_line(tmp_path, capsys):
    from evnoise.cli import main

    if not os.path.isdir("/proc"):
        pytest.skip("no /proc")
    png = tmp_path / "scene.png"
    from PIL import Image

    Image.fromarray(np.full((12, 16), 128, dtype=np.uint8)).save(png)
    for out in ("/proc/x.h5", "/proc/x.raw"):
        assert main(["simulate", str(png), "--out", out, "--duration", "0.1", "--seed", "1"]) == 2
        err = capsys.readouterr().err
        # the CLI's free-space check (issue 35 §2) may speak first: /proc has no free bytes
        assert err.count("\n") == 1 and err.startswith("evnoise: error:") and "h5py" not in err
        assert err.startswith("evnoise: error: cannot write") or "free on its disk" in err
        assert "Unable to" not in err and "errno" not in err


# --------------------------------------------------------------------------------------
# issue 29 §3.1-2: the API picks the format by suffix; a Unix clock gets a t_offset
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix,magic", [(".aedat4", b"#!AER-DAT4"), (".raw", b"%"), (".es", b"Event Stream"),
                                          (".h5", b"\x89HDF")])
def test_write_events_picks_the_format_by_suffix(tmp_path, suffix, magic):
    pytest.importorskip("faery")
    events = random_events(500, 1_000_000, seed=40)
    path = write_events(tmp_path / f"x{suffix}", events, SHAPE)
    assert path.read_bytes().startswith(magic)  # not HDF5 under another name
    got, meta = read_events(path)
    assert got.tobytes() == events.tobytes() and meta["shape"] == SHAPE


def test_write_events_refuses_an_unknown_suffix(tmp_path):
    events = random_events(10, 1000, seed=41)
    for name in ("x.aedat5", "x.txt", "x"):
        with pytest.raises(ParameterError, match="suffix"):
            write_events(tmp_path / name, events, SHAPE)
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("streamed", [False, True])
def test_unix_clock_gets_a_t_offset(tmp_path, streamed):
    from evnoise.io import open_event_writer

    off = 1_643_240_000_123_456  # a DV camera's clock (Unix time in µs)
    events = random_events(4000, 2_000_000, seed=42)
    events["t"] += off
    path = tmp_path / "unix.h5"
    if streamed:
        with open_event_writer(path, SHAPE, t_end_us=off + 2_500_000) as out:
            out.write(events[:1000])
            out.write(events[1000:])
    else:
        write_events(path, events, SHAPE)  # was: MemoryError, 12 TiB for /ms_to_idx
    with h5py.File(path, "r") as f:
        stored_off = int(f["t_offset"][()])
        assert stored_off == off // 1_000_000 * 1_000_000  # the first event's whole second
        assert f["ms_to_idx"].shape[0] < 3000
        assert int(f["events/t"][0]) == int(events["t"][0]) - stored_off
        if streamed:
            assert int(f.attrs["t_end_us"]) == off + 2_500_000 - stored_off
    got, meta = read_events(path)
    assert got.tobytes() == events.tobytes() and meta["t_offset"] == stored_off
    a, b = off + 300_000, off + 900_000
    window, _ = read_events(path, a, b)
    assert window.tobytes() == events[(events["t"] >= a) & (events["t"] < b)].tobytes()


def test_a_clock_near_zero_keeps_t_offset_0(tmp_path):
    events = random_events(100, 2_000_000, seed=43, t_min_us=1_000_000)
    write_events(tmp_path / "e.h5", events, SHAPE)
    with h5py.File(tmp_path / "e.h5", "r") as f:
        assert int(f["t_offset"][()]) == 0 and int(f["events/t"][0]) == int(events["t"][0])


def test_an_offset_that_cannot_fit_is_refused_before_allocating(tmp_path):
    events = random_events(10, 1000, seed=44)
    events["t"] += 1_643_240_000_000_000
    with pytest.raises(InputError, match="ms_to_idx would need"):
        write_events(tmp_path / "e.h5", events, SHAPE, t_offset_us=0)
    with pytest.raises(InputError, match="ms_to_idx would need"):
        EventWriter(tmp_path / "e.h5", SHAPE, t_offset_us=0, t_end_us=1_643_240_000_000_000)
    assert leftovers(tmp_path) == []


# --------------------------------------------------------------------------------------
# issue 35 §1: a full disk is one clean error line, no crash, no partial file
# --------------------------------------------------------------------------------------
_FULL_DISK = """
import resource, signal, sys
import numpy as np
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG), as on a full disk
resource.setrlimit(resource.RLIMIT_FSIZE, (3 << 20, 3 << 20))
from evnoise.errors import EvnoiseError
from evnoise.events import make_events
from evnoise.io import write_events
rng = np.random.default_rng(0)
n = 2_000_000
events = make_events(np.sort(rng.integers(0, 10_000_000, n)), rng.integers(0, 1280, n), rng.integers(0, 720, n),
                     rng.integers(0, 2, n))
try:
    write_events(sys.argv[1], events, (720, 1280), compression=None if sys.argv[2] == "none" else sys.argv[2])
except EvnoiseError as exc:
    print("evnoise: error:", exc)
    sys.exit(2)
"""


@pytest.mark.skipif(not hasattr(os, "fork") or sys.platform != "linux", reason="needs RLIMIT_FSIZE (Linux)")
@pytest.mark.parametrize("compression", ["gzip", "none"])
def test_a_disk_that_refuses_writes_is_one_error_line(tmp_path, compression):
    """HDF5 kept a half-closed file after the failure and crashed on it at exit (exit 139)."""
    import subprocess

    proc = subprocess.run([sys.executable, "-c", _FULL_DISK, str(tmp_path / "big.h5"), compression],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert proc.stderr == "" and proc.stdout.count("\n") == 1, proc.stdout + proc.stderr
    assert proc.stdout.startswith("evnoise: error: writing event file") and "File too large" in proc.stdout
    assert leftovers(tmp_path) == []


_SMALL_DISK = """
import sys
import numpy as np
from evnoise.errors import EvnoiseError
from evnoise.events import make_events
from evnoise.io import write_events
folder, what, compression = sys.argv[1], sys.argv[2], sys.argv[3]
rng = np.random.default_rng(0)
try:
    if what == "events":
        n = 3_000_000
        events = make_events(np.sort(rng.integers(0, 10_000_000, n)), rng.integers(0, 1280, n),
                             rng.integers(0, 720, n), rng.integers(0, 2, n))
        write_events(folder + "/big.h5", events, (720, 1280),
                     compression=None if compression == "none" else compression)
    else:
        from evnoise.generators.shards import META_COLUMNS, ShardWriter
        with ShardWriter(folder + "/shard.h5", (128, 128), None if compression == "none" else compression, {}) as w:
            for i in range(1000):
                m = w.add_image(rng.random((128, 128), dtype=np.float32))
                meta = {k: ("x" if k == "source" else 0) for k in META_COLUMNS}
                meta["image_index"] = m
                w.append(rng.integers(0, 60000, (2, 128, 128)).astype(np.uint16), (0, 0, 128, 128), **meta)
            w.close()
except EvnoiseError as exc:
    print("evnoise: error:", exc)
    sys.exit(2)
"""


@pytest.fixture
def small_disk(tmp_path):
    """A 6 MiB tmpfs, four fifths full of another file (root only; skipped where it cannot be mounted)."""
    import shutil
    import subprocess

    if sys.platform != "linux" or os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a small tmpfs needs root on Linux")
    folder = tmp_path / "small"
    folder.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=6m", "tmpfs", str(folder)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        (folder / "other").write_bytes(bytes(5 << 20))  # others' data: freeing our own file is not enough
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


@pytest.mark.parametrize("what,compression", [("events", "gzip"), ("events", "lzf"), ("events", "none"),
                                              ("shard", "lzf"), ("shard", "none")])
def test_a_full_disk_is_one_error_line(small_disk, what, compression):
    """ENOSPC while writing or at the final flush: one line, exit 2, nothing left behind (was: exit 139)."""
    import subprocess
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", _SMALL_DISK, str(small_disk), what, compression], cwd=repo,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, (proc.returncode, proc.stdout[-2000:], proc.stderr[-2000:])
    assert proc.stderr == "" and proc.stdout.count("\n") == 1, proc.stdout + proc.stderr
    assert "No space left on device" in proc.stdout
    assert leftovers(small_disk) == ["other"]


@pytest.mark.parametrize("suffix, side", [(".raw", 2048), (".dat", 16383), (".aedat4", 32767), (".es", 65535),
                                          (".csv", 65535)])
def test_each_format_holds_its_largest_sensor_and_refuses_a_larger_one(tmp_path, suffix, side):
    """EVT 3.0 keeps 11 bits of x and y: a 4096x4096 sensor's (4095, 4095) was written as (2047, 2047) and its
    polarity bits flipped, without an error (found by reading evnoise's files with the formats' owners' readers).
    Each format now takes the largest sensor its words hold, events in its last column and row read back as
    written, and refuses a larger sensor before writing anything."""
    events = ev.events.make_events([10, 20, 30], [side - 1, 0, side - 1], [0, 1, 1], [1, 0, 0])
    path = ev.write_events(tmp_path / f"edge{suffix}", events, (2, side))
    back, meta = ev.read_events(path)
    assert meta["shape"] == (2, side)
    for field in "txyp":
        np.testing.assert_array_equal(back[field], events[field])
    wider = tmp_path / f"wider{suffix}"
    with pytest.raises(ev.OutputError, match=f"at most {side}x{side}"):
        ev.write_events(wider, events, (2, side + 1))
    with pytest.raises(ev.OutputError, match=f"at most {side}x{side}"):
        ev.write_events(wider, events[1:2], (side + 1, 2))
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"edge{suffix}"]


@pytest.mark.parametrize("suffix", [".raw", ".dat"])
def test_a_shifted_clock_written_in_chunks_reads_back_as_in_one(tmp_path, suffix, caplog):
    """A Unix clock written to .raw / .dat in several chunks (as `separate` streams a camera file): the writer kept
    the last time already shifted and shifted it again, so EVT 3.0's second chunk "crossed" a time-base wrap near
    1.6e9 s and was refused, and the sort check across chunks compared shifted with unshifted times (never fired)."""
    pytest.importorskip("faery")
    from evnoise.io import open_event_writer

    off = 1_633_953_690_123_456
    events = random_events(6000, 2_000_000, seed=31)
    events["t"] += off
    one, parts = tmp_path / f"one{suffix}", tmp_path / f"parts{suffix}"
    with caplog.at_level("WARNING"):
        write_events(one, events, SHAPE)
        with open_event_writer(parts, SHAPE) as out:
            for chunk in np.array_split(events, 5):
                out.write(chunk)
    assert one.read_bytes() == parts.read_bytes()
    got, _ = read_events(parts, sensor="64x48")
    np.testing.assert_array_equal(got["t"], events["t"] - off // 1_000_000 * 1_000_000)
    with pytest.raises(InputError, match="not sorted across chunks"):
        with open_event_writer(tmp_path / f"bad{suffix}", SHAPE) as out:
            out.write(events[3000:])
            out.write(events[:3000])
    assert not (tmp_path / f"bad{suffix}").exists()
