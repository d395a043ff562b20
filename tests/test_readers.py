"""Camera-file readers: the real recordings of shared/data/realdata, faery-written files, bad files.

The real files (third-party licences) are read from ``../shared/data/realdata`` next to the
repository and never copied into it; the tests that need them skip, saying why, when the folder
is absent.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from evnoise.cli import main
from evnoise.errors import InputError, OutputError, ParameterError
from evnoise.events import make_events
from evnoise.readers import iter_event_chunks, open_events, read_events

REALDATA = Path(__file__).resolve().parents[1].parent / "shared/data/realdata"
EVENT_SUFFIXES = (".raw", ".dat", ".aedat4", ".aedat", ".es", ".csv", ".bin")
#: files whose header gives no sensor size: the size the manifest states (W, H)
NO_GEOMETRY = {"faery/evt2.raw", "expelliarmus/evt2_sample.raw", "expelliarmus/evt3_sample.raw",
               "tonic/sample_ncars.dat", "loris/NCARS_obj_004397_td.dat", "evcammoke/Expansion/slow.csv",
               "evcammoke/Feedback/feedback-sorted.csv"}
QUIET = "dvs128dataanalysis/cam255_neal_standing_up2.aedat"


def _manifest():
    path = REALDATA / "manifest.json"
    if not path.is_file():
        return []
    return [e for e in json.loads(path.read_text()) if e["path"].endswith(EVENT_SUFFIXES)]


def _need_realdata():
    if not (REALDATA / "manifest.json").is_file():
        pytest.skip(f"the real recordings are not here ({REALDATA}); they live in shared/data/realdata beside the "
                    f"repository")


def _flags(entry) -> list:
    flags = []
    if entry["path"] in NO_GEOMETRY:
        flags += ["--sensor", "{}x{}".format(*entry["resolution"])]
    if entry["path"].endswith(".csv"):
        flags += ["--csv-columns", "x,y,p,t"]
    return flags


def run_cli(capsys, *args):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


# --------------------------------------------------------------------------------------
# every event file of the manifest
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("entry", _manifest() or [None], ids=lambda e: e["path"] if e else "no-realdata")
def test_real_file_matches_the_manifest(entry, capsys):
    _need_realdata()
    path = REALDATA / entry["path"]
    code, out, err = run_cli(capsys, "info", path, "--json", *_flags(entry))
    assert code == 0, err
    info = json.loads(out)
    n = entry.get("n_events") or 0
    assert info["events"] == n
    if n == 0:  # the header-only AEDAT 2.0 file
        assert info["t_first_us"] is None and info["ON"] == 0
        return
    assert info["t_first_us"] == entry["t_first_us"] and info["t_last_us"] == entry["t_last_us"]
    assert info["sensor"] == "{}x{}".format(*entry["resolution"])
    assert round(info["on_fraction"], 4) == pytest.approx(entry["on_fraction"], abs=1e-12)
    assert info["duration_s"] == pytest.approx((entry["t_last_us"] - entry["t_first_us"]) * 1e-6, abs=1e-9)
    # the Python API agrees and gives the coordinates' extent
    flags = dict(zip(_flags(entry)[::2], _flags(entry)[1::2], strict=True))
    events, meta = read_events(path, sensor=flags.get("--sensor"), csv_columns=flags.get("--csv-columns"))
    assert events.dtype == ev.EVENT_DTYPE and events.size == n
    assert int(events["x"].max()) == entry["x_max"] and int(events["y"].max()) == entry["y_max"]
    assert np.all(np.diff(events["t"]) >= 0)
    assert (meta["width"], meta["height"]) == tuple(entry["resolution"])


def test_header_only_aedat2_reads_as_zero_events():
    _need_realdata()
    events, meta = read_events(REALDATA / "tonic/sample_aedat_header.aedat")
    assert events.size == 0 and meta["format"] == "aedat2" and "Davis346" in meta["chip"]
    assert meta["shape"] == (260, 346)


def test_no_geometry_reports_the_extent_and_asks_for_sensor(capsys):
    _need_realdata()
    path = REALDATA / "faery/evt2.raw"
    src = open_events(path)
    assert src.shape is None and src.format == "evt2"
    code, out, _ = run_cli(capsys, "info", path, "--json")
    info = json.loads(out)
    assert (code == 0 and info["sensor"] is None and "640x480" in info["sensor_note"]
            and "--sensor" in info["sensor_note"])
    code, out, err = run_cli(capsys, "info", path, "--stats")
    assert code == 2 and out == "" and err.count("\n") == 1 and "--sensor" in err
    code, _, err = run_cli(capsys, "info", path, "--sensor", "320x240")  # smaller than the events
    assert (code == 2 and err.startswith("evnoise: error:") and "outside the 320x240 sensor" in err
            and err.count("\n") == 1)


def test_csv_without_header_needs_the_column_order(capsys):
    _need_realdata()
    code, _, err = run_cli(capsys, "info", REALDATA / "evcammoke/Feedback/feedback-sorted.csv")
    assert code == 2 and "--csv-columns" in err and err.count("\n") == 1


# --------------------------------------------------------------------------------------
# the DVS128 quiet window (quiet_segments.json)
# --------------------------------------------------------------------------------------
def _independent_dvs128(path):
    """Events of a DVS128 AEDAT 2.0 file decoded here with plain NumPy (no evnoise, no tonic)."""
    data = path.read_bytes()
    pos = 0
    while data[pos:pos + 1] == b"#":
        pos = data.index(b"\n", pos) + 1
    rec = np.frombuffer(data[pos:], dtype=[("a", ">u4"), ("t", ">u4")])
    a = rec["a"].astype(np.int64)
    return rec["t"].astype(np.int64), 127 - ((a >> 1) & 0x7F), (a >> 8) & 0x7F, (a & 1) == 0


def test_quiet_window_statistics(tmp_path, capsys):
    _need_realdata()
    seg = json.loads((REALDATA / "quiet_segments.json").read_text())["segments"][QUIET][0]
    a, b = seg["t_from_us"] * 1e-6, seg["t_to_us"] * 1e-6
    png = tmp_path / "stats.png"
    code, out, err = run_cli(capsys, "info", REALDATA / QUIET, "--t-start", repr(a), "--t-end", repr(b), "--stats",
                             "--json", "--png", png)
    assert code == 0, err
    info = json.loads(out)
    st = info["stats"]
    assert info["events"] == seg["n"] == 2053
    assert round(st["on_fraction"], 3) == seg["on_frac"] == 0.998
    assert round(st["active_pixel_fraction"], 3) == seg["frac_pix_ge1"] == 0.115
    assert round(st["count_var_over_mean"], 2) == seg["count_var_over_mean"]
    assert round(st["rate_per_pixel_hz"]["mean"], 4) == seg["rate_ev_per_pix_per_s"]
    assert info["duration_s"] == pytest.approx(seg["dur_s"])
    # against an independent decode of the same bytes
    t, x, y, on = _independent_dvs128(REALDATA / QUIET)
    sel = (t >= seg["t_from_us"]) & (t < seg["t_to_us"])
    counts = np.bincount(y[sel] * 128 + x[sel], minlength=128 * 128)
    assert st["count_var_over_mean"] == pytest.approx(counts.var() / counts.mean(), rel=1e-12)
    assert counts.max() == seg["max_pix_count"]
    hot = st["hot_pixels"]
    assert hot["count"] == int(np.sum(counts > hot["threshold_events"]))
    assert hot["event_share"] == pytest.approx(counts[counts > hot["threshold_events"]].sum() / counts.sum())
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_hot_pixel_threshold_flag(capsys):
    _need_realdata()
    # the realdata README: 68 pixels with more than 100 events produce 7.7 % of slow.csv's events
    code, out, err = run_cli(capsys, "info", REALDATA / "evcammoke/Expansion/slow.csv", "--csv-columns", "x,y,p,t",
                             "--sensor", "640x480", "--stats", "--hot-threshold", "100", "--json")
    assert code == 0, err
    hot = json.loads(out)["stats"]["hot_pixels"]
    assert hot["count"] == 68 and round(hot["event_share"], 3) == 0.077 and hot["threshold_events"] == 100


# --------------------------------------------------------------------------------------
# time windows: seeking formats and streaming formats agree with filtering everything
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("name,kw", [
    (QUIET, {}),
    ("expelliarmus/evt3_sample.raw", {}),
    ("aestream/davis.aedat4", {}),
    ("evcammoke/Feedback/feedback-sorted.csv", {"csv_columns": "x,y,p,t", "sensor": "640x480"}),
])
def test_windows_match_filtering(name, kw):
    _need_realdata()
    path = REALDATA / name
    whole, _ = read_events(path, **kw)
    t = whole["t"]
    rng = np.random.default_rng(3)
    lo, hi = int(t[0]), int(t[-1])
    for _ in range(6):
        a, b = sorted(int(v) for v in rng.integers(lo - 1000, hi + 1000, 2))
        got, _ = read_events(path, t_start=a * 1e-6, t_end=b * 1e-6, **kw)
        a_us, b_us = int(round(a * 1e-6 * 1e6)), int(round(b * 1e-6 * 1e6))
        want = whole[(t >= a_us) & (t < b_us)]
        assert got.tobytes() == want.tobytes(), (a, b)
    chunks = list(iter_event_chunks(path, **kw))
    assert np.concatenate(chunks).tobytes() == whole.tobytes()


# --------------------------------------------------------------------------------------
# files faery writes, read back identically
# --------------------------------------------------------------------------------------
def _known_events(n=20_000, width=320, height=240, t0=1_000, seed=11):
    rng = np.random.default_rng(seed)
    t = t0 + np.sort(rng.integers(0, 2_000_000, n))
    return make_events(t, rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n))


@pytest.mark.parametrize("suffix,version", [(".raw", "evt2"), (".raw", "evt3"),  # faery writes no EVT 2.1
                                            (".dat", None), (".aedat4", None), (".es", None), (".csv", None)])
def test_faery_written_files_read_back(tmp_path, suffix, version):
    faery = pytest.importorskip("faery")
    events = _known_events()
    arr = np.empty(events.size, dtype=faery.EVENTS_DTYPE)
    arr["t"], arr["x"], arr["y"], arr["on"] = events["t"], events["x"], events["y"], events["p"] == 1
    path = tmp_path / f"known{suffix}"
    faery.events_stream_from_array(arr, (320, 240)).to_file(path, version=version, zero_t0=False)
    got, meta = read_events(path)
    assert meta["shape"] == (240, 320)
    assert got.tobytes() == events.tobytes()


@pytest.mark.parametrize("suffix", [".h5", ".aedat4", ".raw", ".dat", ".es", ".csv"])
def test_evnoise_writers_round_trip(tmp_path, suffix):
    from evnoise.io import EventFileWriter

    events = _known_events(seed=12, t0=5_000_000)
    params = ev.load_preset("evk3-hd")
    with EventFileWriter(tmp_path / f"ev{suffix}", (240, 320), {"seed": 7, "params": params}) as out:
        for lo in range(0, events.size, 6000):
            out.write(events[lo:lo + 6000])
    got, meta = ev.read_events(tmp_path / f"ev{suffix}")
    assert got.tobytes() == events.tobytes() and meta["shape"] == (240, 320)
    if suffix in (".h5", ".aedat4"):  # the formats with a place for evnoise's attributes
        assert meta["seed"] == 7 and meta["params"]["eps_pos"] == params.eps_pos
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"ev{suffix}"]


def test_evt3_writer_refuses_a_gap_faery_would_misread(tmp_path):
    from evnoise.io import EventFileWriter

    events = make_events([0, 10_000_000, 20_000_000], [1, 2, 3], [1, 1, 1], [1, 0, 1])
    with pytest.raises(OutputError, match="EVT 3.0"):
        with EventFileWriter(tmp_path / "gap.raw", (4, 4)) as out:
            out.write(events)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------
# bad files: one error line, exit 2
# --------------------------------------------------------------------------------------
def _bad_files(tmp_path):
    """(name, bytes) of files that must be refused."""
    files = {}
    for suffix in (".raw", ".dat", ".aedat4", ".aedat", ".es", ".csv", ".bin", ".h5"):
        files[f"empty{suffix}"] = b""
    files["noise.aedat4"] = bytes(range(256)) * 4
    files["noise.h5"] = b"hello, not hdf5" * 10
    files["noise.es"] = b"not an event stream" * 5
    files["noise.aedat"] = b"#!AER-DAT2.0\r\n# AEChip: SomethingElse\r\n" + bytes(16)
    files["wrong.png"] = b"\x89PNG\r\n\x1a\n" + bytes(40)
    files["text.csv"] = b"hello,world\nfoo,bar\n"
    files["odd.bin"] = bytes(7)
    return files


def test_bad_files_give_one_error_line(tmp_path, capsys):
    for name, data in _bad_files(tmp_path).items():
        path = tmp_path / name
        path.write_bytes(data)
        code, out, err = run_cli(capsys, "info", path)
        assert code == 2, name
        assert out == "" and err.startswith("evnoise: error:") and err.count("\n") == 1, (name, err)
        assert "Traceback" not in err


def test_truncated_and_renamed_real_files(tmp_path, capsys):
    _need_realdata()
    cases = {
        "cut.aedat": (REALDATA / QUIET, 3),
        "cut.dat": (REALDATA / "loris/NCARS_obj_004397_td.dat", 5),
        "cut.aedat4": (REALDATA / "aestream/davis.aedat4", 1000),
        "cut.bin": (REALDATA / "tonic/sample_nmnist.bin", 2),
    }
    for name, (src, drop) in cases.items():
        data = src.read_bytes()
        (tmp_path / name).write_bytes(data[:-drop])
        code, out, err = run_cli(capsys, "info", tmp_path / name)
        assert code == 2 and out == "" and err.startswith("evnoise: error:") and err.count("\n") == 1, (name, err)
    # content and suffix disagree
    (tmp_path / "davis.raw").write_bytes((REALDATA / "aestream/davis.aedat4").read_bytes())
    code, _, err = run_cli(capsys, "info", tmp_path / "davis.raw")
    assert code == 2 and "rename" in err and err.count("\n") == 1
    (tmp_path / "dvs.txt").write_bytes((REALDATA / QUIET).read_bytes())  # .txt is a text event list now
    code, _, err = run_cli(capsys, "info", tmp_path / "dvs.txt")
    assert code == 2 and "rename" in err and err.count("\n") == 1
    (tmp_path / "dvs.xyz").write_bytes((REALDATA / QUIET).read_bytes())
    code, _, err = run_cli(capsys, "info", tmp_path / "dvs.xyz")
    assert code == 2 and "not a kind of file" in err


def test_python_errors_are_input_errors(tmp_path):
    (tmp_path / "empty.raw").write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        read_events(tmp_path / "empty.raw")
    with pytest.raises(InputError, match="not found"):
        read_events(tmp_path / "missing.aedat4")
    with pytest.raises(ParameterError, match="WIDTHxHEIGHT"):
        open_events(tmp_path / "empty.raw", sensor="640by480")


# --------------------------------------------------------------------------------------
# real files through the pipeline
# --------------------------------------------------------------------------------------
def test_separate_a_real_recording(tmp_path, capsys):
    _need_realdata()
    src = REALDATA / "aestream/davis.aedat4"
    code, _, err = run_cli(capsys, "-q", "separate", src, "--out", tmp_path / "sig.h5", "--noise-out",
                           tmp_path / "noise.aedat4")
    assert code == 0, err
    sig, meta = ev.read_events(tmp_path / "sig.h5")
    noise, nmeta = ev.read_events(tmp_path / "noise.aedat4")
    whole, _ = read_events(src)
    assert sig.size + noise.size == whole.size == 117_667
    assert meta["t_offset"] > 0 and meta["shape"] == nmeta["shape"] == (260, 346)  # a Unix-time clock kept
    merged = np.sort(np.concatenate([sig, noise]), order=["t", "x", "y", "p"])
    assert merged.tobytes() == np.sort(whole, order=["t", "x", "y", "p"]).tobytes()
    assert nmeta["kind"] == "noise" and nmeta["source"] == str(src)


def test_csv_through_separate_needs_sensor(tmp_path, capsys):
    _need_realdata()
    src = REALDATA / "evcammoke/Feedback/feedback-sorted.csv"
    code, _, err = run_cli(capsys, "-q", "separate", src, "--csv-columns", "x,y,p,t", "--out", tmp_path / "s.h5")
    assert code == 2 and "--sensor" in err
    code, _, err = run_cli(capsys, "-q", "separate", src, "--csv-columns", "x,y,p,t", "--sensor", "640x480",
                           "--noise-out", tmp_path / "n.csv")
    assert code == 0, err
    assert read_events(tmp_path / "n.csv")[1]["shape"] == (480, 640)


# --------------------------------------------------------------------------------------
# the cost of importing evnoise
# --------------------------------------------------------------------------------------
def test_import_loads_no_decoder():
    code = ("import sys, evnoise, evnoise.readers; "
            "print(sorted(m for m in ('faery', 'tonic', 'expelliarmus', 'torch', 'h5py') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


# --------------------------------------------------------------------------------------
# reconstruct on real files (a tiny model trained through the CLI)
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    pytest.importorskip("torch")
    from evnoise.reconstruct.data import save_pairs_npz

    folder = tmp_path_factory.mktemp("model")
    rng = np.random.default_rng(5)
    pairs = [{"counts": rng.poisson(5.0, size=(2, 32, 32)), "image": rng.random((32, 32)), "window_s": 1.0}
             for _ in range(4)]
    save_pairs_npz(folder / "pairs.npz", pairs)
    model = folder / "model.pt"
    code = main(["-q", "train", str(folder / "pairs.npz"), "--out", str(model), "--epochs", "1", "--steps-per-epoch",
                 "2", "--batch-size", "2", "--crop", "16", "--base-channels", "8", "--val-fraction", "0.25",
                 "--no-plot"])
    assert code == 0
    return model


def test_reconstruct_real_recordings(tiny_model, tmp_path, capsys):
    _need_realdata()
    from PIL import Image

    code, _, err = run_cli(capsys, "reconstruct", REALDATA / QUIET, "--model", tiny_model,
                           "--out", tmp_path / "dvs.png", "--window", "2")
    assert code == 0, err
    assert Image.open(tmp_path / "dvs.png").size == (64, 64)  # 128x128, 2x2 binning
    assert "WARNING" in err and "DVS128" in err  # a camera's noise, not the model's: a warning, not a crash
    code, _, err = run_cli(capsys, "-q", "reconstruct", REALDATA / "evcammoke/Expansion/slow.csv", "--csv-columns",
                           "x,y,p,t", "--sensor", "640x480", "--model", tiny_model, "--out", tmp_path / "csv.png",
                           "--window", "1", "--t-start", "30")
    assert code == 0, err
    assert Image.open(tmp_path / "csv.png").size == (320, 240)
    code, _, err = run_cli(capsys, "-q", "reconstruct", REALDATA / "faery/evt2.raw", "--model", tiny_model, "--out",
                           tmp_path / "raw.png", "--window", "0.05")
    assert code == 2 and "--sensor" in err and not (tmp_path / "raw.png").exists()


def test_davis346_address_table(tmp_path):
    """jAER DAVIS addresses: y bits 22-30, x = 345 - bits 12-21, ON = bit 11; APS (bit 31) and
    external-input (bit 10) events are dropped."""
    xs, ys, ons = np.array([0, 345, 100, 7]), np.array([0, 259, 50, 3]), np.array([1, 0, 1, 0])
    addr = (ys << 22) | ((345 - xs) << 12) | (ons << 11)
    addr = np.concatenate([addr, [(1 << 31) | (5 << 22), 1 << 10]])  # an APS sample, an external input
    ts = np.arange(addr.size) * 10 + 1000
    rec = np.empty(addr.size, dtype=[("a", ">u4"), ("t", ">u4")])
    rec["a"], rec["t"] = addr, ts
    path = tmp_path / "davis.aedat"
    path.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.Davis346red\r\n" + rec.tobytes())
    events, meta = read_events(path)
    assert meta["shape"] == (260, 346) and meta["camera"] == "Davis346red"
    np.testing.assert_array_equal(events["x"], xs)
    np.testing.assert_array_equal(events["y"], ys)
    np.testing.assert_array_equal(events["p"], ons)
    np.testing.assert_array_equal(events["t"], ts[:4])


# --------------------------------------------------------------------------------------
# issue 29 §3.3: sensor is (W, H), meta["shape"] is (H, W): one passed for the other is refused
# --------------------------------------------------------------------------------------
def test_meta_shape_passed_as_sensor_is_refused(tmp_path):
    events = _known_events()
    path = ev.write_events(tmp_path / "e.h5", events, (240, 320))
    _, meta = read_events(path)
    assert meta["shape"] == (240, 320) and meta["sensor"] == "320x240"
    with pytest.raises(ParameterError, match=r"swapped.*\(width, height\)"):
        read_events(path, sensor=meta["shape"])  # was: a 240-wide, 320-high sensor, with a warning only
    with pytest.raises(ParameterError, match="swapped"):
        ev.read_events(path, sensor=meta["shape"])
    got, again = read_events(path, sensor=meta["sensor"])  # the round trip that works
    assert again["shape"] == (240, 320) and got.tobytes() == events.tobytes()
    got, again = read_events(path, sensor=(320, 240))
    assert again["shape"] == (240, 320)


def test_real_ncars_sensor_round_trip():
    _need_realdata()
    path = REALDATA / "tonic/sample_ncars.dat"  # no size in the header: the 304x240 ATIS is given
    _, meta = read_events(path, sensor="304x240")
    assert meta["shape"] == (240, 304) and meta["sensor"] == "304x240"
    _, again = read_events(path, sensor=meta["sensor"])
    assert again["shape"] == meta["shape"]


# --------------------------------------------------------------------------------------
# issue 31: .raw / .dat hold the clock itself; other decoders read the same times as evnoise
# --------------------------------------------------------------------------------------
def _evt3_words_decoded(path):
    """EVT 3.0 decoded here from Prophesee's format description (16-bit words, type in the top 4 bits):
    ADDR_Y 0x0, ADDR_X 0x2 (bit 11 polarity), VECT_BASE_X 0x3, VECT_12 0x4, VECT_8 0x5, TIME_LOW 0x6,
    TIME_HIGH 0x8; t = TIME_HIGH << 12 | TIME_LOW, plus 2**24 per TIME_HIGH wrap. No header line is
    used (a decoder from the description does not read faery's ``% t0``)."""
    data = path.read_bytes()
    pos = 0
    while data[pos:pos + 1] == b"%":
        pos = data.index(b"\n", pos) + 1
    words = np.frombuffer(data[pos:], dtype="<u2")
    out = []
    y = base_x = pol = high = low = 0
    wraps = 0
    for w in words.tolist():
        kind, v = w >> 12, w & 0xFFF
        if kind == 0x0:
            y = v & 0x7FF
        elif kind == 0x2:
            out.append(((wraps + (high << 12)) | low, v & 0x7FF, y, (v >> 11) & 1))
        elif kind == 0x3:
            base_x, pol = v & 0x7FF, (v >> 11) & 1
        elif kind in (0x4, 0x5):
            bits = 12 if kind == 0x4 else 8
            t = (wraps + (high << 12)) | low
            out += [(t, base_x + i, y, pol) for i in range(bits) if (v >> i) & 1]
            base_x += bits
        elif kind == 0x6:
            low = v
        elif kind == 0x8:
            if v < high:
                wraps += 1 << 24
            high = v
    t, x, yy, p = (np.array(c, dtype=np.int64) for c in zip(*out))
    order = np.argsort(t, kind="stable")  # vectors and single events of one time come in any order
    return t[order], x[order], yy[order], p[order]


def _same_events(events, t, x, y, p):
    key = np.lexsort((events["p"], events["y"], events["x"], events["t"]))
    key2 = np.lexsort((p, y, x, t))
    np.testing.assert_array_equal(events["t"][key], t[key2])
    np.testing.assert_array_equal(events["x"][key], x[key2])
    np.testing.assert_array_equal(events["y"][key], y[key2])
    np.testing.assert_array_equal(events["p"][key], p[key2])


@pytest.mark.parametrize("t0", [0, 5_000_000])
def test_raw_holds_the_clock_for_a_decoder_from_the_description(tmp_path, t0):
    events = _known_events(n=3000, seed=31, t0=t0)
    path = ev.write_events(tmp_path / "e.raw", events, (240, 320))
    assert b"% t0" not in path.read_bytes()[:400]  # was: relative times, the origin in a line only faery reads
    got, _ = ev.read_events(path)
    assert got.tobytes() == events.tobytes()
    _same_events(events, *_evt3_words_decoded(path))


@pytest.mark.parametrize("t0", [0, 5_000_000, 3_000_000_000])
def test_dat_holds_the_clock_for_expelliarmus(tmp_path, t0):
    expelliarmus = pytest.importorskip("expelliarmus")
    events = _known_events(n=3000, seed=32, t0=t0)
    path = ev.write_events(tmp_path / "e.dat", events, (240, 320))
    got, _ = ev.read_events(path)
    assert got.tobytes() == events.tobytes()
    other = expelliarmus.Wizard(encoding="dat", fpath=str(path)).read()
    np.testing.assert_array_equal(other["t"], events["t"])  # was: 0 at the first event
    np.testing.assert_array_equal(other["x"], events["x"])
    np.testing.assert_array_equal(other["p"], events["p"])


@pytest.mark.parametrize("suffix", [".raw", ".dat"])
def test_a_unix_clock_is_shifted_with_a_warning_and_read_alike(tmp_path, suffix, caplog):
    import logging

    from evnoise.io import EventFileWriter

    unix = 1_643_240_000_123_456
    events = _known_events(n=2000, seed=33, t0=unix)
    with caplog.at_level(logging.WARNING, logger="evnoise"):
        with EventFileWriter(tmp_path / f"u{suffix}", (240, 320)) as out:
            out.write(events)
    shift = unix // 1_000_000 * 1_000_000
    assert out.time_shift_us == shift and f"minus {shift} us" in caplog.text
    got, _ = ev.read_events(tmp_path / f"u{suffix}")
    np.testing.assert_array_equal(got["t"], events["t"] - shift)  # evnoise reads what the others read
    if suffix == ".raw":
        _same_events(got, *_evt3_words_decoded(tmp_path / "u.raw"))
    else:
        expelliarmus = pytest.importorskip("expelliarmus")
        other = expelliarmus.Wizard(encoding="dat", fpath=str(tmp_path / "u.dat")).read()
        np.testing.assert_array_equal(other["t"], got["t"])
