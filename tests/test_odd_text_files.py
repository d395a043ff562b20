"""Files from other people's tools that are odd rather than hostile: text event lists with a byte-order mark,
old-Mac line ends or a block of nothing but comments, a calibration listing with a bad key, a PNG of zero width.
Each was noticed by a hostile-file review and gave a wrong error, a 64 kB error line or a stray warning."""

from __future__ import annotations

import struct
import warnings
import zlib

import numpy as np
import pytest

import evnoise as ev
import evnoise.readers.text as text_reader
from _cli_helpers import one_error_line, run_cli

EVENTS_TXT = b"t x y p\n10 1 2 1\n20 3 0 0\n35 2 2 1\n"


def _events(path, **kw):
    events, _ = ev.read_events(path, sensor=(4, 4), **kw)
    return [tuple(int(v) for v in row) for row in events.tolist()]


def test_a_utf8_byte_order_mark_before_the_header_is_read_as_no_mark(tmp_path):
    """Spreadsheet programs write CSV with a UTF-8 byte-order mark; the header was refused as '\\ufefft x y p'."""
    plain, marked = tmp_path / "plain.csv", tmp_path / "marked.csv"
    plain.write_bytes(EVENTS_TXT.replace(b" ", b","))
    marked.write_bytes(b"\xef\xbb\xbf" + EVENTS_TXT.replace(b" ", b","))
    assert _events(marked) == _events(plain) == [(10, 1, 2, 1), (20, 3, 0, 0), (35, 2, 2, 1)]


def test_a_block_of_only_comments_reads_without_a_warning(tmp_path, monkeypatch):
    """A data block holding only '#' lines made NumPy warn 'loadtxt: input contained no data'."""
    monkeypatch.setattr(text_reader, "BLOCK_BYTES", 64)  # blocks of 64 bytes: the comments fill whole blocks
    path = tmp_path / "events.txt"
    path.write_bytes(b"t x y p\n10 1 2 1\n" + b"# a comment that fills the block, and the next one\n" * 8
                     + b"20 3 0 0\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _events(path) == [(10, 1, 2, 1), (20, 3, 0, 0)]


@pytest.mark.parametrize("n_lines", [20, 20_000])
def test_carriage_return_line_ends_are_named_in_a_short_error(tmp_path, capsys, n_lines):
    """Old-Mac line ends (CR only): the error line repeated the first 64 kB of the file, or (a file longer than
    64 kB) called it an empty event file."""
    path = tmp_path / "mac.csv"
    path.write_bytes(b"t,x,y,p\r" + b"".join(b"%d,1,2,1\r" % i for i in range(n_lines)))
    with pytest.raises(ev.InputError, match="carriage return"):
        ev.read_events(path)
    code, _, err = run_cli(capsys, "info", path)
    one_error_line(code, err, "line ends are carriage returns only")
    assert len(err) < 400, err


def test_a_long_header_is_cut_in_the_error_line(tmp_path, capsys):
    """A header line that names no columns is quoted in the error, but not all of it."""
    path = tmp_path / "long.csv"
    path.write_bytes(b"a" * 50_000 + b",b\n1,2\n")
    code, _, err = run_cli(capsys, "info", path)
    one_error_line(code, err, "does not name t, x, y and p")
    assert len(err) < 400, err


def test_a_file_of_one_long_line_is_not_called_empty(tmp_path):
    path = tmp_path / "one-line.txt"
    path.write_bytes(b"1 2 3 4 " * 20_000)
    with pytest.raises(ev.InputError, match="no line end in its first"):
        ev.read_events(path)


def test_a_bad_key_in_a_listing_is_named_as_the_files_key_not_as_a_flag(tmp_path, capsys):
    """The CLI's rewrite of Python names into flags turned the listing's key t_start_s into '--t-start' (a flag
    of calibrate, but not what the file holds)."""
    rec = ev.simulate_events(np.full((8, 8), 2.0), "evk3-hd", 0.2, rng=0)
    ev.write_events(tmp_path / "flat.h5", rec, (8, 8))
    listing = tmp_path / "levels.toml"
    listing.write_text("".join(f'[[level]]\nfile = "flat.h5"\nlux = {lux}\nt_start_s = nan\n\n' for lux in (1, 2, 3)))
    code, _, err = run_cli(capsys, "calibrate", listing, "--out", tmp_path / "fit.toml", "-q")
    one_error_line(code, err, "level 1: 't_start_s' must be finite and >= 0, got nan")
    assert "--t-start" not in err


def _png(path, width, height, bit_depth, colour_type):
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 4))
                     + chunk(b"IEND", b""))
    return path


@pytest.mark.parametrize("colour_type", [0, 2, 4, 6])
@pytest.mark.parametrize("size", [(0, 4), (4, 0)])
def test_a_png_of_no_pixels_is_one_error_line_without_decoder_warnings(tmp_path, capsys, colour_type, size):
    """A 16-bit colour PNG of zero width let libpng print 'PNG warning: Image width is zero in IHDR' before the
    error line."""
    path = _png(tmp_path / "empty.png", *size, 16, colour_type)
    code, _, err = run_cli(capsys, "simulate", path, "--out", tmp_path / "out.h5", "--duration", "0.01")
    one_error_line(code, err, "empty.png")
    assert f"declares a {size[0]}x{size[1]} image (no pixels)" in err, err
    assert not (tmp_path / "out.h5").exists()


def test_a_column_order_that_contradicts_the_files_header_is_refused(tmp_path, capsys):
    """``--csv-columns x,y,p,t`` on a file whose header says ``t,x,y,p`` read times as x: "near line 2995: x = 65572
    is not a pixel coordinate", nothing about the header. The given order agreeing with the header, or a header of
    other names, reads as before."""
    header, comment, other = tmp_path / "h.csv", tmp_path / "c.txt", tmp_path / "o.csv"
    header.write_bytes(EVENTS_TXT.replace(b" ", b","))
    comment.write_bytes(b"# " + EVENTS_TXT)
    other.write_bytes(b"time,col,row,pol\n" + EVENTS_TXT.split(b"\n", 1)[1].replace(b" ", b","))
    for path, what in ((header, "header"), (comment, "comment line")):
        with pytest.raises(ev.InputError, match=f"csv_columns='x,y,p,t' contradicts the file's {what}, which names "
                                                f"the columns t,x,y,p; leave csv_columns out"):
            ev.read_events(path, sensor=(4, 4), csv_columns="x,y,p,t")
        assert _events(path, csv_columns="t,x,y,p") == _events(path) == [(10, 1, 2, 1), (20, 3, 0, 0), (35, 2, 2, 1)]
    assert _events(other, csv_columns="t,x,y,p") == _events(header)
    prose = tmp_path / "prose.txt"  # a comment's words are not columns: its order agrees, its places do not
    prose.write_bytes(b"# columns: t x y p\n" + EVENTS_TXT.split(b"\n", 1)[1])
    assert _events(prose, csv_columns="t,x,y,p") == _events(header)
    code, _, err = run_cli(capsys, "info", header, "--csv-columns", "x,y,p,t", "--sensor", "4x4")
    one_error_line(code, err, "--csv-columns x,y,p,t contradicts the file's header")


def test_a_fractional_coordinate_is_refused_with_numpy_1_loadtxt_too(tmp_path, monkeypatch):
    """NumPy 1.x's ``loadtxt(dtype=int64)`` parses "5.5" as 5 with only a DeprecationWarning (hidden by default),
    where NumPy 2 raises: a text file of whole-microsecond times and a fractional coordinate read as pixel 5 there.
    NumPy 1.x's behaviour is reproduced here (CI runs NumPy 2)."""
    real = np.loadtxt

    def numpy1_loadtxt(fname, *args, dtype=float, **kw):
        if dtype is not np.int64:
            return real(fname, *args, dtype=dtype, **kw)
        values = real(fname, *args, dtype=np.float64, **kw)
        if not np.array_equal(values, np.trunc(values)):
            warnings.warn("loadtxt(): Parsing an integer via a float is deprecated.", DeprecationWarning,
                          stacklevel=2)
        return values.astype(np.int64)

    monkeypatch.setattr(text_reader.np, "loadtxt", numpy1_loadtxt)
    path = tmp_path / "events.txt"
    path.write_bytes(b"100 3 2 1\n200 5.5 3 0\n")
    with pytest.raises(ev.InputError, match="x = 5.5 is not a pixel coordinate"):
        _events(path)
    path.write_bytes(b"100 3 2 1\n200 1 3 0\n")  # whole numbers still take the integer path
    assert _events(path) == [(100, 3, 2, 1), (200, 1, 3, 0)]
