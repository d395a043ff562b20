"""Damaged camera files are never read silently (issues 29 §3.4 and 35 §3), and text exports are read (29 §3.11).

A file cut inside a word, an event or its header, or with stray bytes at its end, gives one
:class:`InputError` line naming the truncation (or, where the damage leaves a readable but empty
file, a warning). The real recordings of ``../shared/data/realdata`` are read in place, never
copied into the repository; the tests that need them skip when the folder is absent.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from evnoise.cli import main
from evnoise.errors import InputError
from evnoise.events import make_events
from evnoise.readers import read_events

REALDATA = Path(__file__).resolve().parents[1].parent / "shared/data/realdata"


def _real(name: str) -> Path:
    path = REALDATA / name
    if not path.is_file():
        pytest.skip(f"the real recording {name} is not here ({REALDATA}); it lives in shared/data/realdata beside "
                    f"the repository")
    return path


def _events(n=3000, seed=0, shape=(240, 320), t0=0):
    rng = np.random.default_rng(seed)
    t = t0 + np.sort(rng.integers(0, 2_000_000, n))
    return make_events(t, rng.integers(0, shape[1], n), rng.integers(0, shape[0], n), rng.integers(0, 2, n))


def _written(tmp_path, suffix) -> bytes:
    pytest.importorskip("faery")
    path = ev.write_events(tmp_path / f"w{suffix}", _events(), (240, 320))
    data = path.read_bytes()
    path.unlink()
    return data


def _one_line(capsys, path, *flags):
    capsys.readouterr()  # what earlier steps printed
    code = main(["info", str(path), *flags])
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.startswith("evnoise: error:") and err.count("\n") == 1, (code, err)
    assert "Traceback" not in err
    return err


# --------------------------------------------------------------------------------------
# Prophesee RAW: a cut inside a word, inside the header
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("drop", [1, 2, 3, 1001])
def test_real_evt2_cut_mid_word_is_an_error(tmp_path, capsys, drop):
    data = _real("faery/evt2.raw").read_bytes()
    (tmp_path / "cut.raw").write_bytes(data[:-drop])
    with pytest.raises(InputError, match="cut inside one .truncated file."):
        read_events(tmp_path / "cut.raw", sensor="640x480")
    assert "truncated" in _one_line(capsys, tmp_path / "cut.raw", "--sensor", "640x480")


def test_real_evt3_cut_mid_word_and_stray_bytes(tmp_path):
    data = _real("expelliarmus/evt3_sample.raw").read_bytes()
    for name, damaged in (("cut.raw", data[:-1]), ("cut2.raw", data[:-1001]), ("tail.raw", data + b"\x00\x01\x02")):
        (tmp_path / name).write_bytes(damaged)
        with pytest.raises(InputError, match="16-bit|2-byte word"):
            read_events(tmp_path / name, sensor="1280x720")


def test_evnoise_raw_cut_mid_word_is_an_error(tmp_path):
    data = _written(tmp_path, ".raw")  # EVT 3.0
    (tmp_path / "cut.raw").write_bytes(data[:-1])
    with pytest.raises(InputError, match="truncated"):
        read_events(tmp_path / "cut.raw")


def test_raw_cut_inside_its_header(tmp_path, capsys, caplog):
    data = _real("expelliarmus/evt3_sample.raw").read_bytes()
    end = data.index(b"\n% system_ID") + 1  # cut at a header line's end: no event data at all
    (tmp_path / "lines.raw").write_bytes(data[:end])
    with caplog.at_level(logging.WARNING, logger="evnoise"):
        events, _ = read_events(tmp_path / "lines.raw", sensor="1280x720")
    assert events.size == 0 and "no event data" in caplog.text
    (tmp_path / "head.raw").write_bytes(data[:50])  # ends inside the third header line: was 0 events, no word
    with pytest.raises(InputError, match="ends inside its text header"):
        read_events(tmp_path / "head.raw", sensor="1280x720")
    _one_line(capsys, tmp_path / "head.raw", "--sensor", "1280x720")


# --------------------------------------------------------------------------------------
# Event Stream: a cut inside an event, inside the header, stray bytes
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("drop", [1, 2, 3, 4])
def test_real_event_stream_cut_inside_an_event(tmp_path, capsys, drop):
    data = _real("loris/test.es").read_bytes()
    (tmp_path / "cut.es").write_bytes(data[:-drop])  # faery read 4,406 of 4,407 events without a word
    with pytest.raises(InputError, match="ends inside an event"):
        read_events(tmp_path / "cut.es")
    assert "truncated" in _one_line(capsys, tmp_path / "cut.es")


def test_event_stream_whole_file_still_reads(tmp_path):
    events, meta = read_events(_real("loris/test.es"))
    assert events.size == 4407 and meta["shape"] == (239, 54)


def test_evnoise_event_stream_cut_and_extended(tmp_path):
    data = _written(tmp_path, ".es")
    assert read_events_bytes(tmp_path, "ok.es", data).size == 3000
    for damaged in (data[:-2], data + b"\x01\x02"):
        with pytest.raises(InputError, match="ends inside an event"):
            read_events_bytes(tmp_path, "bad.es", damaged)


def read_events_bytes(tmp_path, name, data):
    (tmp_path / name).write_bytes(data)
    return read_events(tmp_path / name)[0]


@pytest.mark.parametrize("size", [12, 15, 16, 19])
def test_event_stream_cut_inside_its_header(tmp_path, size):
    data = _written(tmp_path, ".es")
    with pytest.raises(InputError, match="inside its header|not a valid Event Stream"):
        read_events_bytes(tmp_path, "head.es", data[:size])


def test_event_stream_header_without_events_warns(tmp_path, caplog):
    data = _written(tmp_path, ".es")
    with caplog.at_level(logging.WARNING, logger="evnoise"):
        assert read_events_bytes(tmp_path, "empty.es", data[:20]).size == 0
    assert "no event data" in caplog.text


# --------------------------------------------------------------------------------------
# AEDAT 2.0 and DAT
# --------------------------------------------------------------------------------------
def test_aedat2_cut_inside_its_header_warns(caplog):
    with caplog.at_level(logging.WARNING, logger="evnoise"):
        events, _ = read_events(_real("tonic/sample_aedat_header.aedat"))  # the header stops mid-preferences
    assert events.size == 0 and "cut inside its header" in caplog.text


def test_dat_stray_bytes_are_an_error(tmp_path):
    data = _written(tmp_path, ".dat")
    with pytest.raises(InputError, match="8-byte events"):
        read_events_bytes(tmp_path, "tail.dat", data + b"abc")
    with pytest.raises(InputError, match="ends inside its text header"):
        read_events_bytes(tmp_path, "head.dat", data[:data.index(b"\n") - 2])


# --------------------------------------------------------------------------------------
# CSV and text: time going back, a cut last line (faery clamped the time and dropped the line)
# --------------------------------------------------------------------------------------
def test_csv_row_going_back_in_time_is_an_error(tmp_path, capsys):
    path = tmp_path / "back.csv"
    path.write_text("t,x,y,p\n1000,3,4,1\n999,5,6,0\n1001,5,6,0\n")
    with pytest.raises(InputError, match="line 3: the time goes back .999 us after 1000 us."):
        read_events(path)
    _one_line(capsys, path)


def test_real_csv_cut_in_its_last_line(tmp_path, capsys):
    data = _real("evcammoke/Feedback/feedback-sorted.csv").read_bytes()
    last = data.rstrip(b"\n").rindex(b"\n")
    for keep in (3, 8, len(data) - last - 4):  # x,y,p,t: a cut inside t reads as an earlier time
        (tmp_path / "cut.csv").write_bytes(data[:last + 1 + keep])
        with pytest.raises(InputError, match="columns instead of 4|time goes back"):
            read_events(tmp_path / "cut.csv", csv_columns="x,y,p,t", sensor="640x480")
    _one_line(capsys, tmp_path / "cut.csv", "--csv-columns", "x,y,p,t", "--sensor", "640x480")
    (tmp_path / "whole.csv").write_bytes(data.rstrip(b"\n"))  # a last line without its line end is fine
    events, _ = read_events(tmp_path / "whole.csv", csv_columns="x,y,p,t", sensor="640x480")
    assert events.size == 21436 and int(events["t"][-1]) == 135541940


def test_csv_garbage_rows_are_an_error(tmp_path):
    path = tmp_path / "junk.csv"
    path.write_bytes(b"t,x,y,p\n1000,3,4,1\n1005,5,6,0\n\x00\x13zz,1,2,3\n")
    with pytest.raises(InputError, match="line 4: 'zz' is not a number|line 4"):
        read_events(path)
    path.write_text("t,x,y,p\n1000,3,4,7\n")
    with pytest.raises(InputError, match="polarity 7"):
        read_events(path)


# --------------------------------------------------------------------------------------
# issue 29 §3.11: space-separated exports with a size line or # comments (events.txt)
# --------------------------------------------------------------------------------------
def test_events_txt_with_a_size_line_and_seconds(tmp_path, capsys):
    path = tmp_path / "events.txt"  # the layout of E2VID's and RPG's event files
    path.write_text("240 180\n0.000000000 33 39 1\n0.000011001 158 145 1\n0.000050000 88 143 0\n1.5 239 179 0\n")
    events, meta = read_events(path)
    assert meta["shape"] == (180, 240) and meta["time_unit"] == "s"
    assert events["t"].tolist() == [0, 11, 50, 1_500_000] and events["p"].tolist() == [1, 1, 0, 0]
    assert events["x"].tolist() == [33, 158, 88, 239] and events["y"].tolist() == [39, 145, 143, 179]
    code = main(["info", str(path), "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert '"events": 4' in out


def test_events_txt_with_comments_and_column_order(tmp_path):
    path = tmp_path / "a.txt"
    path.write_text("# exported by some tool\n# t x y p\n1000\t3\t4\t1\n1005\t5\t6\t-1\n")
    events, meta = read_events(path, sensor="8x8")
    assert events.tolist() == [(1000, 3, 4, 1), (1005, 5, 6, 0)] and meta["columns"] == "t,x,y,p"
    path.write_text("3 4 1 1000\n5 6 0 1005\n")  # x y p t without names: the default t x y p cannot be right
    with pytest.raises(InputError, match="give the order with csv_columns "):  # the Python parameter, not the flag
        read_events(path)
    events, _ = read_events(path, csv_columns="x,y,p,t")
    assert events.tolist() == [(1000, 3, 4, 1), (1005, 5, 6, 0)]


def test_events_txt_size_line_is_checked_against_the_events(tmp_path):
    path = tmp_path / "b.txt"
    path.write_text("180 240\n0.1 200 10 1\n")  # H W by mistake: x = 200 is outside a 180-wide sensor
    with pytest.raises(InputError, match="outside the 180x240 sensor"):
        read_events(path)


def test_comma_csv_without_header_still_needs_the_order(tmp_path):
    path = tmp_path / "c.csv"
    path.write_text("3,4,1,1000\n")
    with pytest.raises(InputError, match="csv_columns='x,y,p,t'"):
        read_events(path)


# --------------------------------------------------------------------------------------
# AEDAT 4: the data table ends the file (issue 35 §3: appended garbage was accepted 8 of 8)
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("change", ["+3", "+5000", "-1", "-100"])
def test_real_aedat4_cut_or_extended(tmp_path, capsys, change):
    data = _real("aestream/davis.aedat4").read_bytes()
    n = int(change[1:])
    damaged = data + bytes(range(256)) * 20 if n == 5000 else (data + b"abc" if change[0] == "+" else data[:-n])
    (tmp_path / "d.aedat4").write_bytes(damaged)
    match = "stray bytes after its data table" if change[0] == "+" else "ends inside its data table"
    with pytest.raises(InputError, match=match):
        read_events(tmp_path / "d.aedat4")
    _one_line(capsys, tmp_path / "d.aedat4")


def test_real_dat_with_a_damaged_version_line_says_so(tmp_path, capsys):
    """A DAT header whose "% Version" line is damaged: the decoder's own words ("no versions fallback was
    provided") are kept, after what they mean."""
    pytest.importorskip("faery")
    data = _real("tonic/sample_ncars.dat").read_bytes()
    assert b"% Version 2" in data[:200]
    path = tmp_path / "v.dat"
    path.write_bytes(data.replace(b"% Version 2", b"% Xersion 2", 1))
    with pytest.raises(InputError, match="the header's version line is missing or damaged"):
        read_events(path)
    _one_line(capsys, path)


def _dat_with_times(tmp_path, name, kind: int, times) -> Path:
    """A DAT file of ``kind`` (0 Event2d, 0x0C CD) whose records have the raw 32-bit ``times``."""
    n = len(times)
    records = np.empty((n, 2), dtype="<u4")
    records[:, 0] = np.asarray(times, dtype=np.int64) % (1 << 32)
    records[:, 1] = (np.arange(n) % 304) | ((np.arange(n) % 240) << 14) | ((np.arange(n) % 2) << 28)
    header = b"% Data file\n% Version 2\n% Height 240\n% Width 304\n" + bytes([kind, 8])
    (tmp_path / name).write_bytes(header + records.tobytes())
    return tmp_path / name


@pytest.mark.parametrize("block", [1 << 20, 7, 500], ids=["one-block", "blocks-of-7", "damage-at-a-block-start"])
@pytest.mark.parametrize("kind", [0x00, 0x0C], ids=["Event2d", "CD"])
def test_dat_time_going_back_is_an_error_not_clamped_or_unwrapped(tmp_path, capfd, monkeypatch, kind, block):
    """faery clamped a CD file's time that goes back to the one before it (4990, 4990, ...) and expelliarmus
    took an Event2d file's for a wrap of its clock (+2^32 us) and printed "WARNING: The timestamps are not
    monotonic." on standard output: either way the file read as if whole. A window that ends before the damage
    still reads, and the record named is the same whichever blocks the file is read in."""
    import evnoise.readers.prophesee as prophesee

    if kind == 0x0C:
        pytest.importorskip("faery")
    monkeypatch.setattr(prophesee, "DAT_CHECK_RECORDS", block)
    times = np.arange(1000) * 10
    times[500:] -= 4000  # the 501st record is 1000 us, after 4990 us
    path = _dat_with_times(tmp_path, "back.dat", kind, times)
    with pytest.raises(InputError, match=r"go back in time at event 501 \(1000 us after 4990 us\)"):
        read_events(path)
    before, _ = read_events(path, t_end=4e-3)
    np.testing.assert_array_equal(before["t"], times[:400])
    out, err = capfd.readouterr()
    assert "WARNING" not in out + err
    wrapped = _dat_with_times(tmp_path, "wrap.dat", kind, 0xFFFFF000 + np.arange(1000) * 10)
    with pytest.raises(InputError, match="32-bit clock of the DAT file wraps at event 411"):
        read_events(wrapped)


def test_dat_event2d_reads_as_expelliarmus_does():
    """Event2d DAT is read by evnoise itself (expelliarmus printed its own warnings): the real N-CARS files
    read the same as through expelliarmus, the independent reader."""
    expelliarmus = pytest.importorskip("expelliarmus")
    for name in ("tonic/sample_ncars.dat", "loris/NCARS_obj_004397_td.dat"):
        got, meta = read_events(_real(name), sensor="304x240")
        assert meta["event_type"] == "Event2d"
        other = expelliarmus.Wizard(encoding="dat", fpath=str(_real(name))).read()
        assert got.size == other.size > 1000
        for column in ("t", "x", "y"):
            np.testing.assert_array_equal(got[column], other[column])
        np.testing.assert_array_equal(got["p"], other["p"] != 0)


def test_real_aedat4_damaged_packet_is_named_and_the_events_before_it_read(tmp_path, capsys):
    """A packet whose LZ4 data is damaged: the message names the packet, what failed and the time reached
    (faery's own words alone, "LZ4 error: ERROR_decompressionFailed", said none of it), and a window ending
    at that time reads the events ahead of the damage, as the message says."""
    pytest.importorskip("faery")
    data = bytearray(_real("tonic/sample.aedat4").read_bytes())
    whole = read_events(_real("tonic/sample.aedat4"))[0]
    middle = len(data) // 2
    data[middle:middle + 8] = bytes(b ^ 0xFF for b in data[middle:middle + 8])
    path = tmp_path / "mid.aedat4"
    path.write_bytes(bytes(data))
    with pytest.raises(InputError) as err:
        read_events(path)
    text = str(err.value)
    m = re.search(r"packet (\d+) is unreadable: compressed data cannot be decompressed \(LZ4\): the file is damaged "
                  r"\[decoder: .*\]; events read up to t = (\d+) us on the file's clock", text)
    assert m, text
    reached = int(m.group(2))
    assert whole["t"][0] <= reached < whole["t"][-1]
    before = read_events(path, t_end_us=reached)[0]
    assert before.size > 0 and np.array_equal(before, whole[whole["t"] < reached])
    _one_line(capsys, path)


@pytest.mark.parametrize("compression", [("lz4", 1), ("zstd", 1)])
def test_aedat4_tables_of_both_compressions_are_checked(tmp_path, compression):
    faery = pytest.importorskip("faery")
    from faery.extension import aedat

    from evnoise._aedat import aedat_description

    path = tmp_path / "z.aedat4"
    with aedat.Encoder(path, aedat_description(aedat, 64, 48, {}), compression) as enc:
        arr = np.zeros(5000, dtype=faery.EVENTS_DTYPE)
        arr["t"], arr["x"], arr["y"] = np.arange(5000) * 7, np.arange(5000) % 64, np.arange(5000) % 48
        enc.write(0, arr)
    data = path.read_bytes()
    assert read_events(path)[0].size == 5000
    with pytest.raises(InputError, match="stray bytes"):
        read_events_bytes(tmp_path, "plus.aedat4", data + b"\x00")
    with pytest.raises(InputError, match="ends inside its data table"):
        read_events_bytes(tmp_path, "minus.aedat4", data[:-1])


# --------------------------------------------------------------------------------------
# seeded mutation fuzz (issue 35 §3): a clean error, a warning or events, never a traceback
# --------------------------------------------------------------------------------------
_FUZZ_SUFFIXES = (".raw", ".dat", ".es", ".aedat4", ".csv", ".h5")


def _mutations(data: bytes, rng, n: int):
    """``n`` damaged copies of ``data``: cuts, appended bytes, flipped bytes, a zeroed run."""
    size = len(data)
    for k in range(n):
        kind = k % 4
        if kind == 0:
            yield "cut", data[:int(rng.integers(0, size))]
        elif kind == 1:
            yield "append", data + rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
        elif kind == 2:
            buf = bytearray(data)
            for i in rng.integers(0, size, int(rng.integers(1, 8))):
                buf[i] ^= int(rng.integers(1, 256))
            yield "flip", bytes(buf)
        else:
            buf = bytearray(data)
            a = int(rng.integers(0, size))
            buf[a:a + int(rng.integers(1, 256))] = bytes(min(255, size - a))
            yield "zero", bytes(buf)


def _fuzz(tmp_path, suffix, n, seed):
    from evnoise.errors import EvnoiseError

    data = _written(tmp_path, suffix)
    rng = np.random.default_rng(seed)
    for i, (kind, damaged) in enumerate(_mutations(data, rng, n)):
        path = tmp_path / f"m{i}{suffix}"
        path.write_bytes(damaged)
        try:
            events, _ = read_events(path)
        except EvnoiseError as exc:
            assert "\n" not in str(exc), (kind, str(exc))
        except Exception as exc:  # noqa: BLE001 - what the test is about
            pytest.fail(f"{suffix} {kind} #{i}: {type(exc).__name__}: {exc}")
        else:
            assert events.dtype == ev.EVENT_DTYPE
        path.unlink()


@pytest.mark.parametrize("suffix", _FUZZ_SUFFIXES)
def test_mutated_files_never_give_a_traceback(tmp_path, suffix):
    _fuzz(tmp_path, suffix, 24, seed=35)


@pytest.mark.slow
@pytest.mark.parametrize("suffix", _FUZZ_SUFFIXES)
def test_mutated_files_never_give_a_traceback_many(tmp_path, suffix):
    _fuzz(tmp_path, suffix, 400, seed=3535)


def test_aedat4_description_not_utf8_is_an_error_not_an_abort(tmp_path):
    """faery 0.7.1 panics in a destructor on it and the whole process aborts (found by the fuzz above)."""
    import subprocess
    import sys

    data = bytearray(_written(tmp_path, ".aedat4"))
    data[data.index(b"<dv") + 20] = 0xFF
    path = tmp_path / "bad.aedat4"
    path.write_bytes(bytes(data))
    code = ("import sys\nfrom evnoise.errors import InputError\nfrom evnoise.readers import read_events\n"
            "try:\n    read_events(sys.argv[1])\nexcept InputError as exc:\n    print(exc)\n")
    proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-1500:]
    assert "not UTF-8" in proc.stdout


_REAL_FUZZ = {"faery/evt2.raw": "640x480", "expelliarmus/evt3_sample.raw": "1280x720",
              "loris/NCARS_obj_004397_td.dat": "304x240", "tonic/sample.aedat4": None,
              "tonic/sample_nmnist.bin": None, "jaer_colleenpamchen/DVS128-2017-03-21-short.aedat": None,
              "loris/test.es": None, "evcammoke/Feedback/feedback-sorted.csv": "640x480"}


@pytest.mark.parametrize("name", sorted(_REAL_FUZZ))
def test_mutated_real_files_never_give_a_traceback(tmp_path, name):
    from evnoise.errors import EvnoiseError

    data = _real(name).read_bytes()
    extra = {"csv_columns": "x,y,p,t"} if name.endswith(".csv") else {}
    rng = np.random.default_rng(7)
    for i, (kind, damaged) in enumerate(_mutations(data, rng, 8)):
        path = tmp_path / f"m{i}{Path(name).suffix}"
        path.write_bytes(damaged)
        try:
            read_events(path, sensor=_REAL_FUZZ[name], **extra)
        except EvnoiseError as exc:
            assert "\n" not in str(exc), (kind, str(exc))
        except Exception as exc:  # noqa: BLE001 - what the test is about
            pytest.fail(f"{name} {kind} #{i}: {type(exc).__name__}: {exc}")
        path.unlink()


def test_a_text_file_without_line_ends_is_refused_after_one_block(tmp_path, monkeypatch):
    """A 'text' file with no newline must not be gathered whole into memory before it is judged."""
    import evnoise.readers.text as text_reader

    monkeypatch.setattr(text_reader, "BLOCK_BYTES", 1 << 12)
    monkeypatch.setattr(text_reader, "MAX_LINE_BYTES", 1 << 14)
    path = tmp_path / "events.txt"
    path.write_bytes(b"# t x y p\n" + b"1 " * (1 << 16))
    reads = []
    real_open = open

    def counting_open(*args, **kwargs):
        fh = real_open(*args, **kwargs)
        if str(args[0]) == str(path):
            real_read = fh.read
            fh.read = lambda n=-1: reads.append(n) or real_read(n)
        return fh

    monkeypatch.setattr("builtins.open", counting_open)
    with pytest.raises(ev.InputError, match="longer than 16,384 bytes"):
        ev.read_events(path, sensor=(4, 4))
    assert len(reads) <= 1 + (1 << 14) // (1 << 12) + 2  # the header read and a few blocks, not the whole file


def test_a_header_comment_that_is_not_utf8_keeps_the_data_offset(tmp_path):
    """The data start is counted in the file's bytes: a Latin-1 comment (1 byte, 3 as a replacement character)
    must not move it into the middle of the first event line."""
    path = tmp_path / "events.txt"
    path.write_bytes(b"# cam\xe9ra \xe9\xe9\xe9\xe9\n# t x y p\n10 1 2 1\n20 3 0 0\n")
    events, _ = ev.read_events(path, sensor=(4, 4))
    assert events["t"].tolist() == [10, 20] and events["x"].tolist() == [1, 3] and events["p"].tolist() == [1, 0]
