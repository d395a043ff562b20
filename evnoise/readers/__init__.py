"""Camera files in, evnoise events out: one reader per format family and a dispatcher.

Each format is one entry of :data:`evnoise.formats.FORMATS` (suffixes, magic bytes, label,
reader, writer, extra): events.h5 (``.h5``, ``.hdf5``; h5py), Prophesee RAW EVT 2.0/2.1/3.0
(``.raw``, ``.evt``) and DAT (``.dat``), iniVation AEDAT 4 (``.aedat4``), jAER AEDAT 2.0
(``.aedat``), Event Stream (``.es``), CSV / text event lists (``.csv``, ``.txt``; column order from
the header, ``csv_columns`` or ``t x y p``) and N-MNIST (``.bin``).

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

from ..errors import InputError, ParameterError
from ..events import EVENT_DTYPE
from ..formats import FORMATS, detect_format, format_for_suffix, get_format, input_suffixes, reader_for, resolve
from ._base import EventSource, parse_sensor, seconds_to_us

__all__ = ["EventSource", "open_events", "read_events", "iter_event_chunks", "scan_events", "parse_sensor",
           "detect_format", "SUFFIXES", "is_event_file", "time_window", "source_meta", "recording_span_us",
           "window_counts"]


def __getattr__(name):
    if name == "SUFFIXES":  # derived from the registry on each use (a format registered at run time shows)
        return input_suffixes()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def is_event_file(path) -> bool:
    """Cheap check for ``evnoise info``: a file with an event suffix (whose format's probe, if any, agrees)."""
    path = Path(path)
    fmt = format_for_suffix(path)
    if not path.is_file() or fmt is None:
        return False
    return fmt.probe is None or bool(resolve(fmt.probe)(path))


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
    entry = get_format(detect_format(path))
    options = {"csv_columns": csv_columns}
    for key, value in options.items():
        if value is not None and key not in entry.options:
            raise ParameterError(f"{key} applies to {' and '.join(f.label for f in FORMATS if key in f.options)} "
                                 f"files only; {path} is {entry.label}")
    return reader_for(entry)(path, sensor=sensor, **{k: v for k, v in options.items() if k in entry.options})


def time_window(t_start, t_end, t_start_us=None, t_end_us=None) -> tuple:
    """``(t_start_us, t_end_us)`` of a window given in seconds or in integer microseconds (one form each).

    Either bound may be ``None`` (open); an end before the start is a :class:`~evnoise.ParameterError`.
    """
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
    path : str or os.PathLike
        The file, as in :func:`open_events`.
    sensor : str or (int, int), optional
        Sensor size ``"WxH"`` or ``(width, height)`` (width first), as in :func:`open_events`.
    t_start, t_end : float, optional
        Time window in seconds on the file's own clock (``t_start <= t < t_end``).
    csv_columns : str or list of str, optional
        Column order of a CSV or text file, e.g. ``"x,y,p,t"``, as in :func:`open_events`.
    t_start_us, t_end_us : int, optional
        The same window in integer microseconds (give one form, not both).

    Yields
    ------
    numpy.ndarray
        :data:`evnoise.EVENT_DTYPE` chunks, sorted by time.
    """
    a, b = time_window(t_start, t_end, t_start_us, t_end_us)
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
    a, b = time_window(t_start, t_end, t_start_us, t_end_us)
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

    a = seconds_to_us(t_start_s, "t_start_s")
    w = seconds_to_us(window_s, "window_s")
    if w is None or w <= 0:
        raise ParameterError(f"window_s must be > 0 seconds, got {window_s!r}")
    src = open_events(path, sensor=sensor, csv_columns=csv_columns)
    if src.shape is None:
        raise InputError(f"{path}: the header gives no sensor size; add sensor='WxH'")
    with src:
        counts, _ = pixel_counts(src.chunks(a, a + w), src.shape)
    return counts
