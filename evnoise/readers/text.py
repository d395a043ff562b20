"""Text event lists: CSV and whitespace-separated exports (``.csv``, ``.txt``), parsed here, streamed.

One event per line; the columns are separated by commas, or by spaces/tabs when the first data
line has no comma. What the file may start with (the header rule):

- comment lines starting with ``#`` (anywhere; a leading one that names the columns, such as
  ``# t x y p``, gives the column order);
- a line of exactly two integers: the sensor size ``W H`` (the layout of E2VID's and many
  datasets' ``events.txt``);
- a line naming the columns (``t``/``timestamp``, ``x``, ``y``, ``p``/``polarity``/``on``; faery
  writes ``t,x@W,y@H,on``, which also gives the sensor size).

The column order comes from ``csv_columns`` (``"x,y,p,t"``: the EvCamMOKE files have that order
and no header), else from the header or a comment naming the columns. Without either, a
whitespace-separated file is read as ``t x y p`` (the common ``events.txt`` layout) and checked
(polarity 0/1/-1, integer coordinates, non-decreasing time: a file that fails says to give
``--csv-columns``); a comma-separated file without a header is refused rather than guessed.

Time: integer microseconds, or seconds when the time column has a decimal point or an exponent
(``0.003811``, as RPG's datasets write it; rounded to the microsecond). Polarity: ``1`` ON,
``0`` or ``-1`` OFF.

Damage is never read silently: a row whose time goes back, a row with missing or extra columns
or a token that is not a number (a last line cut short included) is an :class:`InputError`
naming the line.
"""

from __future__ import annotations

import io
import re
import warnings

import numpy as np

from ..errors import InputError, ParameterError
from ._base import EventSource, to_events

_ALIASES = {
    "t": "t", "ts": "t", "t_us": "t", "time": "t", "timestamp": "t", "timestamp_us": "t", "t_s": "t",
    "x": "x", "y": "y",
    "p": "p", "pol": "p", "polarity": "p", "on": "p",
}

#: Bytes parsed at a time (memory stays at a few times this).
BLOCK_BYTES = 1 << 23
#: Longest line accepted (an event line has a few dozen bytes).
MAX_LINE_BYTES = 1 << 20
#: Largest ``|t|`` accepted, in µs (2^62, as for events.h5's ``t_offset``): past it a time cannot be held in
#: int64 with room for differences.
MAX_ABS_T_US = 1 << 62
#: Bytes looked at for the header.
_HEAD_BYTES = 1 << 16
_BOM = b"\xef\xbb\xbf"
_DATA_LINE = re.compile(rb"^[ \t\r\f\v]*[^#\s]", re.MULTILINE)  # a line that is neither blank nor a comment


def parse_columns(text) -> dict[str, int]:
    """``"x,y,p,t"`` (or a list of names) -> ``{"t": 3, "x": 0, "y": 1, "p": 2}``; other names are skipped columns."""
    if not (isinstance(text, str) or (isinstance(text, (list, tuple)) and all(isinstance(n, str) for n in text))):
        raise ParameterError(f"csv_columns must be text such as 'x,y,p,t' or a list of column names, got {text!r}")
    names = re.split(r"[,\s]+", text.strip()) if isinstance(text, str) else list(text)
    out: dict[str, int] = {}
    for i, name in enumerate(n.strip().lower() for n in names):
        key = _ALIASES.get(name)
        if key is None:
            continue
        if key in out:
            raise ParameterError(f"csv_columns names {key!r} twice: {text!r}")
        out[key] = i
    missing = [k for k in "txyp" if k not in out]
    if missing:
        raise ParameterError(f"csv_columns must name the columns t, x, y and p (e.g. 'x,y,p,t'); "
                             f"{', '.join(missing)} missing in {text!r}")
    return out


def _order(cols: dict[str, int]) -> str:
    """``{"t": 3, "x": 0, "y": 1, "p": 2}`` -> ``"x,y,p,t"``."""
    return ",".join(k for k, _ in sorted(cols.items(), key=lambda kv: kv[1]))


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _cut(text: str, limit: int = 80) -> str:
    """``text``, or its first ``limit`` characters and an ellipsis (for quoting a file's line in an error)."""
    return text if len(text) <= limit else text[:limit] + "..."


def _split(line: str, comma: bool) -> list[str]:
    return [tok.strip() for tok in line.split(",")] if comma else line.split()


class CsvSource(EventSource):
    format = "csv"

    def __init__(self, path, *, sensor=None, csv_columns=None):
        super().__init__(path, sensor=sensor)
        cols = parse_columns(csv_columns) if csv_columns is not None else None
        with open(self.path, "rb") as fh:
            head = fh.read(_HEAD_BYTES)
        if b"\n" not in head and b"\r" in head:
            raise InputError(f"{self.path}: its line ends are carriage returns only (old Mac text); evnoise reads "
                             f"text with \\n or \\r\\n line ends: convert it first (e.g. tr '\\r' '\\n')")
        if len(head) == _HEAD_BYTES and b"\n" not in head:
            raise InputError(f"{self.path}: no line end in its first {_HEAD_BYTES // 1024} kB: not a text event file "
                             f"(one event per line)")
        # a byte-order mark (spreadsheet programs write one before the header) is not part of the first line
        offset = len(_BOM) if head.startswith(_BOM) else 0
        # split as bytes, so that the data's offset counts the file's own bytes (a comment that is not UTF-8
        # decodes to other lengths)
        lines = head[offset:].split(b"\n")
        if len(head) == _HEAD_BYTES:
            lines = lines[:-1]  # the last one may be cut by the read
        line_no = 0
        comment_names = None
        size_line = None
        names_line = None
        first = None
        for raw_bytes in lines:
            step = len(raw_bytes) + 1
            line = raw_bytes.decode("utf-8", "replace").strip()
            if not line:
                offset += step
                line_no += 1
                continue
            if line.startswith("#"):
                body = line.lstrip("#").strip()
                if comment_names is None and first is None and names_line is None:
                    try:
                        comment_names = parse_columns(body) if body else None
                    except ParameterError:
                        comment_names = None
                offset += step
                line_no += 1
                continue
            comma = "," in line
            tokens = _split(line, comma)
            numeric = all(_is_number(tok) for tok in tokens)
            if (size_line is None and names_line is None and numeric and len(tokens) == 2
                    and all(tok.isdigit() for tok in tokens)):
                size_line = (int(tokens[0]), int(tokens[1]))  # W H
            elif names_line is None and size_line is None and not numeric:
                names_line = tokens
            else:
                first = (line, comma, tokens)
                break
            offset += step
            line_no += 1
        if first is None and names_line is None and size_line is None and comment_names is None:
            raise InputError(f"{self.path}: empty text event file (no events, no header)")
        self._comma = first[1] if first is not None else (names_line is not None and "," in ",".join(names_line))
        self._default_columns = False
        if cols is not None:  # a header that names the columns otherwise: the given order read x as t, say
            for named, what in ((names_line, "header"), (comment_names, "comment line")):
                if isinstance(named, list):
                    try:
                        named = parse_columns([tok.split("@")[0] for tok in named])
                    except ParameterError:
                        named = None  # a header of other names says nothing against the given order
                # a comment is prose ("# columns: t x y p"): only its order of the names counts, not their places
                if named is not None and (named != cols if what == "header" else _order(named) != _order(cols)):
                    raise InputError(f"{self.path}: csv_columns={csv_columns!r} contradicts the file's {what}, "
                                     f"which names the columns {_order(named)}; leave csv_columns out or give "
                                     f"that order")
        if cols is None and names_line is not None:
            try:
                cols = parse_columns([tok.split("@")[0] for tok in names_line])
            except ParameterError:
                raise InputError(f"{self.path}: the header {_cut(' '.join(names_line))!r} does not name t, x, y and p; "
                                 f"give the column order with csv_columns (e.g. csv_columns='x,y,p,t')") from None
        if cols is None and comment_names is not None:
            cols = comment_names
        if cols is None:
            if first is not None and not first[1]:
                cols = {"t": 0, "x": 1, "y": 2, "p": 3}  # the events.txt layout; checked while reading
                self._default_columns = True
            else:
                raise InputError(f"{self.path}: a CSV file without a header; give the column order with "
                                 f"csv_columns (e.g. csv_columns='x,y,p,t')")
        self._cols = cols
        self._n_cols = None
        self._seconds = False
        if first is not None:
            self._n_cols = len(first[2])
            if max(cols.values()) >= self._n_cols:
                raise InputError(f"{self.path}: line {line_no + 1} has {self._n_cols} columns; the column order "
                                 f"{self._columns_text()} needs {max(cols.values()) + 1}")
            self._seconds = bool(re.search(r"[.eE]", first[2][cols["t"]]))
        self._data_offset = offset
        self._first_line = line_no + 1
        self.meta = {"columns": self._columns_text(), "header_line": names_line is not None,
                     "time_unit": "s" if self._seconds else "us", "delimiter": "comma" if self._comma else "space"}
        if self._default_columns:
            self.meta["columns_from"] = "default t x y p (no header); give csv_columns for another order"
        header_shape = None
        if names_line is not None:  # faery writes the sensor size into the header: t,x@W,y@H,on
            sizes = dict(tok.split("@", 1) for tok in names_line if "@" in tok)
            if sizes.get("x", "").isdigit() and sizes.get("y", "").isdigit():
                header_shape = (int(sizes["y"]), int(sizes["x"]))
        if size_line is not None:
            if not all(1 <= v <= 65536 for v in size_line):
                raise InputError(f"{self.path}: the size line {size_line[0]} {size_line[1]} is not a sensor size "
                                 f"(W H, 1 .. 65536 each)")
            header_shape = (size_line[1], size_line[0])
            self.meta["size_line"] = f"{size_line[0]} {size_line[1]} (W H)"
        self._set_shape(header_shape)

    def _columns_text(self) -> str:
        return _order(self._cols)

    def _hint(self) -> str:
        if self._default_columns:
            return " (the columns were taken as t x y p: give the order with csv_columns if it is another)"
        return ""

    def _bad_line(self, block: bytes, line0: int) -> InputError:
        """The first malformed line of ``block`` (its first line is file line ``line0``), as an error."""
        want = self._n_cols
        for k, raw in enumerate(block.split(b"\n")):
            line = raw.decode("utf-8", "replace").strip()
            if not line or line.startswith("#"):
                continue
            tokens = _split(line.split("#", 1)[0], self._comma)
            bad = [tok for tok in tokens if not _is_number(tok)]
            if len(tokens) != want or bad:
                what = (f"{len(tokens)} columns instead of {want}" if len(tokens) != want
                        else f"{bad[0]!r} is not a number")
                return InputError(f"{self.path}: line {line0 + k}: {what}: {line[:80]!r} (a damaged or truncated "
                                  f"file){self._hint()}")
        return InputError(f"{self.path}: a line near line {line0} could not be read as numbers{self._hint()}")

    def _parse(self, block: bytes, line0: int) -> np.ndarray:
        if _DATA_LINE.search(block) is None:  # blank or comments only (NumPy would warn that it read no data)
            return np.empty((0, self._n_cols or 4))
        text = block.decode("utf-8", "replace")
        delimiter = "," if self._comma else None
        rows = None
        if not self._seconds:  # integers parse about five times faster than floats
            try:
                with warnings.catch_warnings():  # NumPy 1.x truncates "1.5" to 1 with a DeprecationWarning; 2.x raises
                    warnings.simplefilter("error", DeprecationWarning)
                    rows = np.loadtxt(io.StringIO(text), delimiter=delimiter, comments="#", dtype=np.int64, ndmin=2)
            except (ValueError, DeprecationWarning):
                rows = None
        if rows is None:
            try:
                with np.errstate(all="ignore"):
                    rows = np.loadtxt(io.StringIO(text), delimiter=delimiter, comments="#", dtype=np.float64,
                                      ndmin=2)
            except ValueError:
                raise self._bad_line(block, line0) from None
        if rows.shape[0] and self._n_cols is not None and rows.shape[1] != self._n_cols:
            raise self._bad_line(block, line0)
        if rows.shape[0] and self._n_cols is None:
            self._n_cols = rows.shape[1]
        return rows

    def _convert(self, rows: np.ndarray, line0: int, prev_t) -> np.ndarray:
        c = self._cols
        if rows.shape[1] <= max(c.values()):
            raise InputError(f"{self.path}: line {line0}: {rows.shape[1]} columns; the column order "
                             f"{self._columns_text()} needs {max(c.values()) + 1}{self._hint()}")
        t_raw, x, y, p = rows[:, c["t"]], rows[:, c["x"]], rows[:, c["y"]], rows[:, c["p"]]
        if rows.dtype.kind == "f" and not np.all(np.isfinite(rows)):
            k = int(np.flatnonzero(~np.all(np.isfinite(rows), axis=1))[0])
            raise InputError(f"{self.path}: near line {line0 + k}: a value that is not a finite number{self._hint()}")
        t = np.rint(t_raw * 1e6) if self._seconds else t_raw
        if not self._seconds and rows.dtype.kind == "f" and np.any(t != np.floor(t)):
            raise InputError(f"{self.path}: the time column holds fractions after integer microseconds at the first "
                             f"line; write the times all in µs or all in seconds with a decimal point{self._hint()}")
        for name, v in (("x", x), ("y", y)):
            bad = (v < 0) | (v > 65535) | ((v != np.floor(v)) if v.dtype.kind == "f" else False)
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise InputError(f"{self.path}: near line {line0 + k}: {name} = {v[k]:g} is not a pixel coordinate "
                                 f"(an integer 0 .. 65535){self._hint()}")
        bad = (p != 0) & (p != 1) & (p != -1)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise InputError(f"{self.path}: near line {line0 + k}: polarity {p[k]:g} is not 1 (ON), 0 or -1 (OFF)"
                             f"{self._hint()}")
        bad = (t < -MAX_ABS_T_US) | (t > MAX_ABS_T_US)  # before the cast, which would wrap it silently
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            shown = f"{t_raw[k]:g}" if rows.dtype.kind == "f" else str(int(t_raw[k]))
            raise InputError(f"{self.path}: near line {line0 + k}: the time {shown}"
                             f"{' s' if self._seconds else ' us'} is beyond +-2^62 us (about 146,000 years); a "
                             f"damaged file{self._hint()}")
        t = t.astype(np.int64)
        back = np.flatnonzero(np.diff(t) < 0)
        if prev_t is not None and t.size and t[0] < prev_t:
            back = np.concatenate([[-1], back])
        if back.size:
            k = int(back[0]) + 1
            before = prev_t if k == 0 else int(t[k - 1])
            raise InputError(f"{self.path}: near line {line0 + k}: the time goes back ({int(t[k])} us after "
                             f"{before} us); rows must be sorted by time (a damaged or unsorted file){self._hint()}")
        return to_events(t, x, y, p > 0)

    def _chunks(self, t_start_us, t_end_us):
        prev_t = None
        line0 = self._first_line
        with open(self.path, "rb") as fh:
            fh.seek(self._data_offset)
            rest = b""
            while True:
                data = fh.read(BLOCK_BYTES)
                block = rest + data
                if not data:
                    if not block.strip():
                        return
                    last = True
                else:
                    cut = block.rfind(b"\n")
                    if cut < 0:
                        if len(block) > MAX_LINE_BYTES:  # a file without line ends must not be gathered whole
                            raise InputError(f"{self.path}: line {line0} is longer than {MAX_LINE_BYTES:,} bytes; "
                                             "not a text file of one event per line")
                        rest = block
                        continue
                    block, rest = block[:cut + 1], block[cut + 1:]
                    last = False
                rows = self._parse(block, line0)
                if rows.shape[0]:
                    events = self._convert(rows, line0, prev_t)
                    prev_t = int(events["t"][-1])
                    if t_start_us is None or prev_t >= t_start_us:
                        yield events
                    if t_end_us is not None and prev_t >= t_end_us:
                        return
                line0 += block.count(b"\n")
                if last:
                    return
