"""Camera files in, evnoise events out: one reader per format family and a dispatcher.

========================  ===========================  ==========================================
suffix                    format                       decoder
========================  ===========================  ==========================================
``.h5``, ``.hdf5``        events.h5 (DSEC layout)      h5py (evnoise's own; ``t_offset`` honoured)
``.raw``, ``.evt``        Prophesee EVT 2.0/2.1/3.0    faery
``.dat``                  Prophesee DAT (CD, Event2d)  faery (CD), expelliarmus (Event2d)
``.aedat4``               iniVation AEDAT 4            faery
``.aedat``                jAER AEDAT 2.0 (or 4)        tonic's container reader + address table
``.es``                   Event Stream (DVS, ATIS)     faery
``.csv``, ``.txt``        CSV / text event list        evnoise (comma or space separated; column order:
                                                       header, ``csv_columns`` or ``t x y p``)
``.bin``                  N-MNIST                      tonic
========================  ===========================  ==========================================

The format is told by the file's magic bytes where it has them (HDF5, ``#!AER-DAT``,
``Event Stream``) and by the suffix otherwise; a suffix that contradicts the content, or one
that no reader knows, is an :class:`~evnoise.InputError`. The third-party decoders are the
optional extra ``evnoise[readers]``; a missing one is an error naming that extra.

Every reader returns :data:`evnoise.EVENT_DTYPE` on the file's own clock (integer µs as stored,
plus ``t_offset`` for DSEC files), sorted by time, with the sensor size from the header, the
caller's ``sensor`` (``"WxH"``), or ``None`` when neither gives it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from .._checks import check_input_file
from ..errors import InputError, ParameterError
from ..events import EVENT_DTYPE
from ._base import EventSource, parse_sensor, seconds_to_us

__all__ = ["EventSource", "open_events", "read_events", "iter_event_chunks", "scan_events", "parse_sensor",
           "detect_format", "SUFFIXES", "is_event_file"]

#: suffix -> formats it may hold
SUFFIXES = {
    ".h5": ("h5",), ".hdf5": ("h5",),
    ".raw": ("raw",), ".evt": ("raw",),
    ".dat": ("dat",),
    ".aedat4": ("aedat4",),
    ".aedat": ("aedat2", "aedat4"),
    ".es": ("es",),
    ".csv": ("csv",), ".txt": ("csv",),
    ".bin": ("nmnist",),
}

_NAMES = {"h5": "events.h5 (HDF5)", "raw": "Prophesee RAW", "dat": "Prophesee DAT", "aedat4": "AEDAT 4",
          "aedat2": "jAER AEDAT 2.0", "es": "Event Stream", "csv": "CSV / text event list",
          "nmnist": "N-MNIST .bin"}


def _magic(head: bytes) -> str | None:
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        return "h5"
    if head.startswith(b"#!AER-DAT4"):
        return "aedat4"
    if head.startswith(b"#!AER-DAT2"):
        return "aedat2"
    if head.startswith(b"#!AER-DAT"):
        return "aedat?"
    if head.startswith(b"Event Stream"):
        return "es"
    return None


def detect_format(path) -> str:
    """Format name of an event file (see the module table); :class:`~evnoise.InputError` if none fits."""
    path = check_input_file(path, missing="event file", kind="an event file")
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror or exc}") from None
    suffix = path.suffix.lower()
    allowed = SUFFIXES.get(suffix)
    if not head:
        raise InputError(f"{path} is empty (0 bytes): not an event file")
    magic = _magic(head)
    if magic == "aedat?":
        raise InputError(f"{path}: AEDAT version {head[9:12].decode('latin-1', 'replace')!r} is not supported "
                         f"(AEDAT 2.0 and 4.0 are)")
    if allowed is None:
        known = ", ".join(SUFFIXES)
        hint = f" (its content looks like {_NAMES[magic]})" if magic else ""
        raise InputError(f"{path}: unknown event file suffix {suffix or '(none)'!r}{hint}; evnoise reads {known}")
    if magic is not None:
        if magic not in allowed:
            raise InputError(f"{path}: the content is {_NAMES[magic]} but the suffix {suffix} says "
                             f"{' or '.join(_NAMES[a] for a in allowed)}; rename the file")
        return magic
    fmt = allowed[0]
    if fmt in ("h5", "aedat4", "aedat2", "es"):
        raise InputError(f"{path} is not a valid {_NAMES[fmt]} file (its first bytes do not match the format)")
    return fmt


def is_event_file(path) -> bool:
    """Cheap check for ``evnoise info``: a file with an event suffix (an HDF5 file needs ``/events``)."""
    path = Path(path)
    if not path.is_file() or path.suffix.lower() not in SUFFIXES:
        return False
    if SUFFIXES[path.suffix.lower()] == ("h5",):
        try:
            import h5py

            with h5py.File(path, "r") as f:
                group = f.get("events")
                return isinstance(group, h5py.Group) and all(k in group for k in "xytp")
        except OSError:
            return True  # a corrupt .h5: let the reader say why
    return True


def open_events(path, *, sensor=None, csv_columns=None) -> EventSource:
    """Open an event file of any supported format (see the module table).

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    sensor : str or (int, int), optional
        Sensor size ``"WxH"`` (e.g. ``"640x480"``) or ``(width, height)``; overrides the header
        (with a warning when they differ) and sets it where the header has none. Width first,
        unlike ``shape`` (H, W): a tuple that is the header's size swapped is a
        :class:`~evnoise.ParameterError`; ``meta["sensor"]`` is the ``"WxH"`` string to pass back.
    csv_columns : str or list of str, optional
        Column order of a CSV or text file, e.g. ``"x,y,p,t"`` (t in µs, or seconds when written
        with a decimal point; p 1 = ON, 0 or -1 = OFF).

    Returns
    -------
    EventSource
        ``shape`` (H, W) or ``None``, ``format``, ``meta`` and :meth:`EventSource.chunks`.
    """
    path = Path(path)
    parse_sensor(sensor)  # a malformed --sensor is reported before anything is read
    fmt = detect_format(path)
    if csv_columns is not None and fmt != "csv":
        raise ParameterError(f"--csv-columns applies to CSV files only; {path} is {_NAMES[fmt]}")
    if fmt == "h5":
        from .hdf5 import H5Source

        return H5Source(path, sensor=sensor)
    if fmt == "raw":
        from .prophesee import RawSource

        return RawSource(path, sensor=sensor)
    if fmt == "dat":
        from .prophesee import DatSource

        return DatSource(path, sensor=sensor)
    if fmt == "aedat4":
        from .inivation import Aedat4Source

        return Aedat4Source(path, sensor=sensor)
    if fmt == "aedat2":
        from .inivation import Aedat2Source

        return Aedat2Source(path, sensor=sensor)
    if fmt == "es":
        from .eventstream import EsSource

        return EsSource(path, sensor=sensor)
    if fmt == "csv":
        from .text import CsvSource

        return CsvSource(path, sensor=sensor, csv_columns=csv_columns)
    from .nmnist import NmnistSource

    return NmnistSource(path, sensor=sensor)


def _window(t_start, t_end, t_start_us=None, t_end_us=None):
    if t_start is not None and t_start_us is not None:
        raise ParameterError("give t_start (seconds) or t_start_us (microseconds), not both")
    if t_end is not None and t_end_us is not None:
        raise ParameterError("give t_end (seconds) or t_end_us (microseconds), not both")
    a = seconds_to_us(t_start, "t_start") if t_start is not None else t_start_us
    b = seconds_to_us(t_end, "t_end") if t_end is not None else t_end_us
    if a is not None and b is not None and b < a:
        raise ParameterError(f"the end of the time window ({b * 1e-6:g} s) is before its start ({a * 1e-6:g} s)")
    return a, b


def iter_event_chunks(path, *, sensor=None, t_start=None, t_end=None, csv_columns=None,
                      t_start_us=None, t_end_us=None) -> Iterator[np.ndarray]:
    """Events of a file chunk by chunk (memory bounded by one decoder packet, not by the file).

    Parameters
    ----------
    path, sensor, csv_columns
        As in :func:`open_events`.
    t_start, t_end : float, optional
        Time window in seconds on the file's own clock (``t_start <= t < t_end``).
    t_start_us, t_end_us : int, optional
        The same window in integer microseconds (give one form, not both).

    Yields
    ------
    numpy.ndarray
        :data:`evnoise.EVENT_DTYPE` chunks, sorted by time.
    """
    a, b = _window(t_start, t_end, t_start_us, t_end_us)
    src = open_events(path, sensor=sensor, csv_columns=csv_columns)
    with src:
        yield from src.chunks(a, b)


def source_meta(src: EventSource) -> dict:
    """``meta`` of :func:`read_events`: the header's facts plus ``format``, ``shape``, ``shape_from``, ``t_offset``."""
    meta = dict(src.meta)
    meta["format"] = src.format
    meta["shape"] = src.shape
    meta["shape_from"] = src.shape_from
    meta.setdefault("t_offset", getattr(src, "t_offset_us", 0))
    if src.shape is not None:
        meta.setdefault("height", src.shape[0])
        meta.setdefault("width", src.shape[1])
        meta["sensor"] = f"{src.shape[1]}x{src.shape[0]}"  # what to pass back as sensor= (width first)
    return meta


def read_events(path, *, sensor=None, t_start=None, t_end=None, csv_columns=None, t_start_us=None,
                t_end_us=None):
    """All events of a file (or of a time window) in memory: ``(events, meta)``.

    Parameters as in :func:`iter_event_chunks`. ``meta`` holds the header's facts, ``format``,
    ``shape`` (H, W) or ``None``, ``sensor`` (``"WxH"``, what ``sensor=`` takes) when known,
    ``shape_from``, ``t_offset`` and ``n_events`` (events returned).
    For files larger than memory use :func:`iter_event_chunks`.
    """
    a, b = _window(t_start, t_end, t_start_us, t_end_us)
    src = open_events(path, sensor=sensor, csv_columns=csv_columns)
    with src:
        parts = list(src.chunks(a, b))
    events = np.concatenate(parts) if parts else np.empty(0, dtype=EVENT_DTYPE)
    meta = source_meta(src)
    meta["n_events"] = int(events.size)
    return events, meta


def scan_events(src: EventSource, t_start_us=None, t_end_us=None, *, progress: bool = False) -> dict:
    """One streaming pass: ``n_events``, ``n_on``, ``t_first_us``, ``t_last_us``, ``x_max``, ``y_max``."""
    out = {"n_events": 0, "n_on": 0, "t_first_us": None, "t_last_us": None, "x_max": None, "y_max": None}
    for chunk in src.chunks(t_start_us, t_end_us):
        out["n_events"] += int(chunk.size)
        out["n_on"] += int(np.count_nonzero(chunk["p"]))
        if out["t_first_us"] is None:
            out["t_first_us"] = int(chunk["t"][0])
        out["t_last_us"] = int(chunk["t"][-1])
        xm, ym = int(chunk["x"].max()), int(chunk["y"].max())
        out["x_max"] = xm if out["x_max"] is None else max(out["x_max"], xm)
        out["y_max"] = ym if out["y_max"] is None else max(out["y_max"], ym)
    return out


def recording_span_us(path, *, sensor=None, csv_columns=None) -> tuple[int, int]:
    """``(start_us, end_us)`` of a recording on its own clock.

    events.h5: from 0 (evnoise's clock; ``t_offset`` added) to the stored ``t_end_us`` or the
    last event + 1 µs, reading two timestamps. Camera files: first event to last event + 1 µs,
    from one streaming pass (no header stores the end).
    """
    src = open_events(path, sensor=sensor, csv_columns=csv_columns)
    with src:
        if src.format == "h5":
            off = src.t_offset_us
            last = src.t_last_us + 1 if src.n_events else off
            end = src.meta.get("t_end_us")
            start = off if not off else (src.t_first_us if src.n_events else off)
            return start, max(last, (int(end) + off) if end is not None else last)
        info = scan_events(src)
    if not info["n_events"]:
        raise InputError(f"{path} has no events")
    return info["t_first_us"], info["t_last_us"] + 1


def window_counts(path, t_start_s: float, window_s: float, *, sensor=None, csv_columns=None):
    """ON/OFF counts ``(2, H, W)`` of ``[t_start_s, t_start_s + window_s)`` (file clock), streamed.

    Memory: the count maps and one decoder packet. The sensor size must be known (header or
    ``sensor``).
    """
    from .stats import pixel_counts

    a = seconds_to_us(t_start_s, "--t-start")
    w = seconds_to_us(window_s, "--window")
    if w is None or w <= 0:
        raise ParameterError(f"--window must be > 0 seconds, got {window_s!r}")
    src = open_events(path, sensor=sensor, csv_columns=csv_columns)
    if src.shape is None:
        raise InputError(f"{path}: the header gives no sensor size; add --sensor WxH")
    with src:
        counts, _ = pixel_counts(src.chunks(a, a + w), src.shape)
    return counts
