"""Regressions for what a fuzzing campaign against the readers found (byte flips, truncations, header
edits, duplicated packets, appended garbage on evnoise's own files and on real recordings).

Each test builds its hostile bytes itself (from a file evnoise writes, or byte by byte) and checks the
standard for bad input: one :class:`~evnoise.InputError` line (exit 2 from the command line), never a
traceback, a crash, a hang or an allocation the file does not back.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys

import numpy as np
import pytest

import evnoise as ev
from evnoise.cli import main
from evnoise.errors import InputError
from evnoise.events import make_events
from evnoise.readers import open_events
from evnoise.readers import read_events as read_any

h5py = pytest.importorskip("h5py")


def _events(n=200, seed=0, shape=(48, 64)):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 50_000, n))
    return make_events(t, rng.integers(0, shape[1], n), rng.integers(0, shape[0], n), rng.integers(0, 2, n))


def _h5(tmp_path, name="events.h5", attrs=None):
    path = tmp_path / name
    ev.write_events(path, _events(), (48, 64), attrs={"source": "fuzz test", "params_note": "x" * 40,
                                                        **(attrs or {})})
    return path


def _cli(tmp_path, argv, *, address_space=None, timeout=120):
    """``python -m evnoise ARGV`` in a child (a hang, an abort or a traceback shows there, not here)."""
    def limit():  # pragma: no cover - runs in the child
        import resource

        if address_space is not None:
            resource.setrlimit(resource.RLIMIT_AS, (address_space, address_space))
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))

    return subprocess.run([sys.executable, "-m", "evnoise", *argv], capture_output=True, text=True,
                          timeout=timeout, preexec_fn=limit, cwd=tmp_path, env={**os.environ, "PYTHONFAULTHANDLER": ""})


def _one_error_line(proc):
    lines = [line for line in proc.stderr.splitlines() if line.strip() and "WARNING" not in line]
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("evnoise: error: "), proc.stderr[-2000:]
    return lines[0]


# -- events.h5 ------------------------------------------------------------------------------------------
def _global_heap_objects(data: bytes):
    """``(collection offset, [(object offset, index, size)])`` of the first HDF5 global heap collection."""
    at = data.find(b"GCOL")
    assert at >= 0, "evnoise's events.h5 stores its string attributes in a global heap"
    total = int.from_bytes(data[at + 8:at + 16], "little")
    objects, p = [], at + 16
    while p + 16 <= at + total:
        idx, size = int.from_bytes(data[p:p + 2], "little"), int.from_bytes(data[p + 8:p + 16], "little")
        objects.append((p, idx, size))
        if idx == 0:
            break
        p += 16 + (size + 7) // 8 * 8
    return at, objects


def test_h5_global_heap_that_would_loop_hdf5_forever_is_refused(tmp_path):
    """Found: one byte flipped in an object size of the global heap (string attributes) made HDF5 2.0 spin
    for good on the first attribute read (a free-space record of size 0 that its walk never steps over);
    SIGTERM could not stop it either. The collection is now walked before HDF5 loads it."""
    path = _h5(tmp_path)
    data = bytearray(path.read_bytes())
    _, objects = _global_heap_objects(bytes(data))
    free = [p for p, idx, _ in objects if idx == 0]
    assert free, objects
    data[free[0] + 8:free[0] + 16] = (0).to_bytes(8, "little")  # the free space: 0 bytes, never stepped over
    bad = tmp_path / "heap.h5"
    bad.write_bytes(bytes(data))
    try:
        proc = _cli(tmp_path, ["info", str(bad)], timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("evnoise info hung on a damaged HDF5 global heap")
    line = _one_error_line(proc)
    assert "global heap" in line and "heap.h5" in line
    with pytest.raises(InputError, match="global heap"):
        open_events(bad)


def test_h5_attribute_name_that_is_not_utf8_is_reported_as_text(tmp_path, capsys):
    """Found: a flipped byte in an attribute's name (``t\\x94me_unit``) came back from h5py as bytes, and
    ``evnoise info`` failed with a TypeError traceback while printing it."""
    path = _h5(tmp_path)
    data = path.read_bytes()
    assert data.count(b"time_unit") == 1
    bad = tmp_path / "name.h5"
    bad.write_bytes(data.replace(b"time_unit", b"t\x94me_unit"))
    _, meta = read_any(bad)
    assert all(isinstance(k, str) for k in meta)
    assert main(["info", str(bad)]) == 0
    assert "me_unit" in capsys.readouterr().out


@pytest.mark.parametrize("value", ["x", 1.5, np.nan])
def test_h5_t_end_us_that_is_not_an_integer_is_an_input_error(tmp_path, capsys, value):
    """Found: ``t_end_us = "x"`` made ``evnoise info`` fail with ``ValueError: invalid literal for int()``."""
    path = _h5(tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs["t_end_us"] = value
    with pytest.raises(InputError, match="t_end_us attribute must be an integer"):
        open_events(path)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "t_end_us" in err[0]


def test_h5_coordinates_past_16_bits_are_refused_not_wrapped(tmp_path):
    """Found: ``/events/x`` stored as int64 with values past 65535 were wrapped modulo 2^16 into pixels
    inside the sensor (x = 2^40 + 35 read as x = 35) and the file read as if nothing were wrong."""
    path = _h5(tmp_path)
    with h5py.File(path, "r+") as f:
        x = f["events/x"][...].astype(np.int64)
        del f["events/x"]
        f["events/x"] = x + (1 << 40)
    with pytest.raises(InputError, match=r"/events/x\[0\] = 1099511627\d+ is not a pixel coordinate"):
        read_any(path)
    with h5py.File(path, "r+") as f:
        del f["events/x"]
        f["events/x"] = x - 70_000
    with pytest.raises(InputError, match="is not a pixel coordinate"):
        read_any(path)
    with pytest.raises(InputError, match="is not a pixel coordinate"):  # the public reader too (it had its own path)
        ev.read_events(path)


def test_evnoise_read_events_of_h5_checks_what_the_readers_check(tmp_path):
    """Found: ``evnoise.read_events`` read events.h5 through a path of its own, without the readers' checks: an
    event outside the header's sensor, or at a time past 2^62 us, came back as if valid."""
    path = _h5(tmp_path)
    events, meta = ev.read_events(path)
    assert events.size == 200 and meta["shape"] == (48, 64)
    with h5py.File(path, "r+") as f:
        f["events/y"][3] = 60
    with pytest.raises(InputError, match="outside the 64x48 sensor"):
        ev.read_events(path)
    path = _h5(tmp_path, "t.h5")
    with h5py.File(path, "r+") as f:
        t = f["events/t"][...].astype(np.int64)
        del f["events/t"]
        f["events/t"] = np.concatenate([t[:-1], [(1 << 62) + 5]])
    with pytest.raises(InputError, match="beyond"):
        ev.read_events(path)


# -- AEDAT 4 --------------------------------------------------------------------------------------------
def _aedat4_packet(data: bytes) -> int:
    """Offset of the first packet header of an AEDAT 4 file (after the 14-byte magic and the IO header)."""
    return 18 + struct.unpack_from("<I", data, 14)[0]


@pytest.mark.parametrize("size", [0x7FFFFFFF, 0xFFFFFFFF])
def test_aedat4_packet_size_past_the_file_is_refused_before_faery_allocates_it(tmp_path, size):
    """Found: a packet header declaring 2 GiB (or 4 GiB) made faery allocate that much before reading; under a
    memory limit the process aborted (``memory allocation of 2147483647 bytes failed``, SIGABRT, a Rust
    backtrace), without one it took 2 GiB for a 3 kB file. The packets are now walked first."""
    pytest.importorskip("faery")
    path = tmp_path / "events.aedat4"
    ev.write_events(path, _events(), (48, 64))
    data = bytearray(path.read_bytes())
    at = _aedat4_packet(bytes(data))
    struct.pack_into("<I", data, at + 4, size)
    bad = tmp_path / "packet.aedat4"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match=rf"the packet at byte {at} \(stream 0\) declares {size:,} bytes"):
        open_events(bad)
    proc = _cli(tmp_path, ["info", str(bad), "--stats"], address_space=2 << 30)
    assert "packet at byte" in _one_error_line(proc)


# -- count maps of a file without a sensor size -----------------------------------------------------------
def test_count_maps_past_the_address_space_limit_are_one_error_line(tmp_path):
    """Found: a damaged N-CARS ``.dat`` (no geometry in its header) with one event at x, y ~ 15000 made
    ``info`` grow its count maps to 15000x12000 (8.7 GiB); under ``ulimit -v`` that was a MemoryError
    traceback (the memory budget looked at the machine's free memory only). The same with a CSV file."""
    path = tmp_path / "far.csv"
    path.write_text("t,x,y,p\n10,1,2,1\n20,9000,9000,0\n")
    proc = _cli(tmp_path, ["info", str(path), "--sensor", "9001x9001"], address_space=int(1.5 * (1 << 30)))
    line = _one_error_line(proc)
    assert "count maps of a 9001x9001 sensor" in line


def test_a_stray_coordinate_of_a_file_without_a_sensor_size_is_refused_not_allocated(tmp_path, capsys):
    """The same damage without a memory limit: maps sized by one stray event (9000 x 9000: 1.3 GB of maps for a
    40-byte file) are refused past the largest side inferred from events, and the line says how to go on."""
    path = tmp_path / "far.csv"
    path.write_text("t,x,y,p\n10,1,2,1\n20,5000,5000,0\n")
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "beyond 4096 pixels" in err[0] and "--sensor WxH" in err[0]  # the CLI names its flag
    assert main(["info", str(path), "--sensor", "5001x5001"]) == 0  # the caller says it is that large


# -- CSV ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("rows", ["1,2,3,1\n99999999999999999999,2,3,1\n",  # past int64: parsed as 1e20
                                  "0.5,2,3,1\n1e300,2,3,1\n",  # seconds: 1e306 µs
                                  "-5,2,3,1\n9223372036854775807,2,3,1\n"])  # the difference wraps
def test_csv_time_past_the_int64_range_is_refused_not_wrapped(tmp_path, capsys, rows):
    """Found: a time too large for int64 was cast to -9223372036854775808 without a word; the chunk was then
    sorted and ``info`` printed t_first_us = -9223372036854775808 and a duration of 9.2e12 s (exit 0)."""
    path = tmp_path / "far.csv"
    path.write_text("t,x,y,p\n" + rows)
    with pytest.raises(InputError, match=r"near line 3: the time .* is beyond \+-2\^62 us"):
        read_any(path)
    assert main(["info", str(path)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


# -- a header's sensor size ------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix", [".es", ".dat"])
def test_header_with_a_zero_sensor_size_names_the_file(tmp_path, capsys, suffix):
    """Found: an Event Stream header with height 0 (bytes 18-19) or a DAT header ``% Height 0`` gave
    ``shape must be (H, W) with 1 <= H, W <= 65536, got (0, 64)``: neither the file nor the header named."""
    pytest.importorskip("faery")
    path = tmp_path / f"events{suffix}"
    ev.write_events(path, _events(), (48, 64))
    data = bytearray(path.read_bytes())
    if suffix == ".es":
        assert data[18:20] == (48).to_bytes(2, "little")
        data[18:20] = b"\0\0"
    else:
        assert data.count(b"% Height 48\n") == 1
        data = bytearray(bytes(data).replace(b"% Height 48\n", b"% Height 0\n"))
    bad = tmp_path / f"zero{suffix}"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"zero\.\w+: the header gives a 64x0 sensor"):
        open_events(bad)
    assert main(["info", str(bad), "--stats"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_h5_event_times_past_2_to_62_are_refused(tmp_path):
    """Found: ``/events/t`` all at 2^63 - 1 read without a word (``info``: t_first_us 9223372036854775807,
    exit 0), though ``/t_offset`` is held to +-2^62 so that times and their differences cannot wrap."""
    path = _h5(tmp_path)
    with h5py.File(path, "r+") as f:
        t = f["events/t"][...]
        del f["events/t"]
        f["events/t"] = np.full_like(t, np.iinfo(np.int64).max)
    with pytest.raises(InputError, match=r"beyond \+-2\^62 us"):
        read_any(path)
    with h5py.File(path, "r+") as f:  # only one time in the middle (a sorted file's ends are fine)
        t[len(t) // 2] = -(1 << 63)
        del f["events/t"]
        f["events/t"] = t
    with pytest.raises(InputError, match=r"/events/t\[\d+\] puts an event at -9223372036854775808 us"):
        read_any(path)


# --------------------------------------------------------------------------------------
# twelfth session's campaign: the millisecond index, datasets without a dataspace, special files, damaged zips,
# control bytes in messages, broken links as outputs
# --------------------------------------------------------------------------------------
def _ms_file(tmp_path, index):
    """100 events one millisecond apart (t = 0 .. 99 ms) and ``index`` as ``/ms_to_idx`` (a callable gets the file)."""
    path = tmp_path / "indexed.h5"
    n = 100
    ev.write_events(path, make_events(np.arange(n) * 1000, np.zeros(n), np.zeros(n), np.ones(n)), (48, 64))
    with h5py.File(path, "a") as f:
        if "ms_to_idx" in f:
            del f["ms_to_idx"]
        if callable(index):
            index(f)
        else:
            f["ms_to_idx"] = index
    return path


@pytest.mark.parametrize("index", [
    np.full(200, np.nan),                                  # floats
    np.array([b"abc"] * 200),                              # strings
    np.zeros((200, 2), dtype=np.int64),                    # 2-D
    lambda f: f.create_group("ms_to_idx"),                 # a group
    lambda f: f.create_dataset("ms_to_idx", data=np.int64(5)),           # a scalar
    lambda f: f.create_dataset("ms_to_idx", data=h5py.Empty("<i8")),     # no dataspace
    np.full(200, -5, dtype=np.int64),                      # negative: would count from the end
    np.full(200, 1 << 62, dtype=np.int64),                 # past the file
    np.arange(200, dtype=np.int64)[::-1].copy(),           # decreasing
    np.arange(200, dtype=np.int64) // 2,                   # in range, but indexes the wrong events
], ids=["nan", "strings", "2d", "group", "scalar", "empty", "negative", "huge", "decreasing", "wrong"])
def test_a_damaged_millisecond_index_gives_the_right_window(tmp_path, index, caplog):
    """A windowed read of an events.h5 whose /ms_to_idx is damaged (ValueError, TypeError, AttributeError,
    IndexError before; a negative or wrong index silently gave 5 or 0 of the 99 events): the index is checked
    against the events beside the answer and the event times searched instead, with a warning."""
    path = _ms_file(tmp_path, index)
    got, _ = ev.read_events(path, t_start_us=5, t_end_us=50_500)
    np.testing.assert_array_equal(got["t"], np.arange(1, 51) * 1000)
    assert caplog.text.count("ms_to_idx") == 1  # once per file, not once per read
    chunks = list(ev.iter_event_chunks(path, t_start_us=5, t_end_us=10**12))
    assert sum(len(c) for c in chunks) == 99


def test_a_sound_millisecond_index_is_used_without_a_warning(tmp_path, caplog):
    path = _ms_file(tmp_path, np.arange(101, dtype=np.int64))  # event k at k ms: the first at or after k ms is k
    got, _ = ev.read_events(path, t_start_us=5, t_end_us=10**12)  # past the index's end: not damage
    np.testing.assert_array_equal(got["t"], np.arange(1, 100) * 1000)
    assert "ms_to_idx" not in caplog.text


def test_h5_event_datasets_without_a_dataspace_are_one_error_line(tmp_path):
    path = tmp_path / "null.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        for k in "xytp":
            g.create_dataset(k, data=h5py.Empty("<i8"))
        f.attrs["width"], f.attrs["height"] = 64, 48
    with pytest.raises(InputError, match="no dataspace"):
        ev.read_events(path)
    assert "1-D" in _one_error_line(_cli(tmp_path, ["info", str(path)]))


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
@pytest.mark.parametrize("suffix", [".h5", ".csv", ".raw", ".png"])
def test_a_named_pipe_is_refused_not_read_for_ever(tmp_path, suffix):
    """A FIFO passed as an input blocked the first read for ever (readers, read_image, info, simulate)."""
    fifo = tmp_path / f"pipe{suffix}"
    os.mkfifo(fifo)
    reader = "read_image" if suffix == ".png" else "read_events"
    code = (f"import evnoise as ev\ntry:\n    ev.{reader}({str(fifo)!r})\nexcept ev.InputError as e:\n    print(e)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)  # a hang fails
    assert "special file" in out.stdout, out.stdout + out.stderr[-2000:]
    for argv in (["info", str(fifo), "--stats"], ["simulate", str(fifo), "--out", "out.h5", "--duration", "0.01"]):
        line = _one_error_line(_cli(tmp_path, argv, timeout=60))
        assert "special file" in line or "not found" in line, line
    assert not (tmp_path / "out.h5").exists()


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="no /dev/zero")
def test_a_link_to_a_device_is_refused_not_read_to_the_end(tmp_path):
    """``evnoise info`` on a link to /dev/zero read the device until memory ran out (MemoryError traceback)."""
    link = tmp_path / "zero.h5"
    link.symlink_to("/dev/zero")
    line = _one_error_line(_cli(tmp_path, ["info", str(link)], address_space=2 << 30, timeout=60))
    assert "special file" in line
    with pytest.raises(InputError, match="special file"):
        ev.read_events(tmp_path / "zero.h5")


def _damaged_zip(path):
    import io
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("model/data.pkl", b"\x80\x02}q\x00.")
    data = bytearray(buf.getvalue())
    end = data.rfind(b"PK\x05\x06")
    central = struct.unpack_from("<I", data, end + 16)[0]
    data[central:central + 4] = b"XXXX"  # the central directory's signature
    path.write_bytes(bytes(data))
    return path


def test_info_on_a_damaged_zip_is_one_error_line(tmp_path):
    """``evnoise info`` on a .pt whose zip directory is damaged raised zipfile.BadZipFile."""
    path = _damaged_zip(tmp_path / "model.pt")
    assert "damaged zip" in _one_error_line(_cli(tmp_path, ["info", str(path)]))


def test_control_bytes_from_a_file_are_escaped_in_the_error_line(tmp_path):
    """An AEDAT 2.0 camera name holding ESC and NUL bytes reached the terminal raw in the error line."""
    path = tmp_path / "chip.aedat"
    path.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: evil\x1b[2J\x00chip\r\n# End Of ASCII Header\r\n" + bytes(16))
    proc = _cli(tmp_path, ["info", str(path), "--stats"])
    line = _one_error_line(proc)
    assert "\x1b" not in proc.stderr and "\x00" not in proc.stderr
    assert "evil\\x1b[2J\\x00chip" in line


def test_a_broken_link_as_output_is_not_replaced_without_overwrite(tmp_path):
    link = tmp_path / "out.h5"
    link.symlink_to(tmp_path / "nowhere.h5")
    with pytest.raises(ev.OutputError, match="already exists"):
        ev.write_events(link, _events(), (48, 64))
    assert link.is_symlink() and not (tmp_path / "nowhere.h5").exists()
    ev.write_events(link, _events(), (48, 64), overwrite=True)  # replaces the link itself, not its target
    assert not link.is_symlink() and not (tmp_path / "nowhere.h5").exists()
