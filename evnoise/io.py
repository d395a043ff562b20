"""events.h5: event files in the DSEC layout, written incrementally and atomically.

Layout (readable by plain h5py, DSEC's ``EventSlicer``, evlib, tonic)::

    /events/x  uint16     /events/y  uint16
    /events/t  int64 (microseconds, non-decreasing)     /events/p  uint8 (1 = ON, 0 = OFF)
    /ms_to_idx uint64     ms_to_idx[k] = index of the first event with t >= 1000 k
    /t_offset  int64 scalar 0   (absolute time = t + t_offset)
    root attributes: width, height, time_unit = "us", evnoise_version, and the caller's
    attributes (model parameters as JSON, seed, source, ...)

The event datasets are chunked and resizable, gzip + shuffle compressed by default.
:class:`EventWriter` appends time-sorted chunks, so memory stays bounded by one chunk; it
writes to a temporary file in the target directory and renames it on success, so an error
never leaves a file that looks complete.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
from pathlib import Path

import numpy as np

from ._version import __version__
from .errors import EvnoiseError, InputError, OutputError, ParameterError
from .events import _check_shape, check_events, make_events

__all__ = ["EventWriter", "write_events", "read_events", "read_metadata", "write_aedat4", "open_output_path"]

log = logging.getLogger(__name__)

#: Events per HDF5 chunk of each ``/events/*`` dataset.
CHUNK_EVENTS = 1 << 16
#: Entries per HDF5 chunk of ``/ms_to_idx``.
CHUNK_MS = 1 << 14
#: Events read at a time when scanning a file.
READ_BLOCK = 1 << 22

_FIELDS = (("x", np.uint16), ("y", np.uint16), ("t", np.int64), ("p", np.uint8))
_RESERVED = ("width", "height", "time_unit", "evnoise_version", "json_attrs", "t_end_us")
COMPRESSIONS = ("gzip", "lzf", None)
#: gzip level of the event datasets: level 1 writes about twice as fast as h5py's default
#: level 4, for files about 5 % larger (noise events compress little beyond the shuffle filter).
GZIP_LEVEL = 1


def open_output_path(path, *, overwrite: bool = False, what: str = "output") -> Path:
    """Check that ``path`` can be (over)written: its directory exists, it is not a folder.

    Raises :class:`~evnoise.OutputError` naming the path. Used by the writers and by the
    command line to fail before any work is done.
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.exists():
        raise OutputError(f"cannot write {what} {path}: directory {parent} does not exist")
    if not parent.is_dir():
        raise OutputError(f"cannot write {what} {path}: {parent} is not a directory")
    if path.is_dir():
        raise OutputError(f"cannot write {what} {path}: it is a directory")
    if path.exists() and not overwrite:
        raise OutputError(f"{what} {path} already exists; pass --overwrite (overwrite=True in Python) to "
                          f"replace it")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write {what} {path}: directory {parent} is not writable")
    return path


def _encode_attr(key: str, value):
    """``(stored_value, is_json)`` for an HDF5 attribute."""
    from .params import NoiseParams

    if isinstance(value, NoiseParams):
        return value.to_json(), True
    if isinstance(value, (dict, list, tuple)):
        try:
            return json.dumps(value, sort_keys=True), True
        except TypeError as exc:
            raise ParameterError(f"attribute {key!r} cannot be stored as JSON: {exc}") from None
    if isinstance(value, Path):
        return os.fspath(value), False
    if isinstance(value, (str, bool, int, float, np.generic, np.ndarray)):
        return value, False
    raise ParameterError(f"attribute {key!r} has unsupported type {type(value).__name__} "
                         f"(use str, numbers, arrays, dicts or lists)")


def _decode_attr(value):
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.generic):
        return value.item()
    return value


class EventWriter:
    """Write an events.h5 file chunk by chunk (a context manager).

    Parameters
    ----------
    path : str or os.PathLike
        Output file. Written first to a hidden temporary file in the same directory and
        renamed to ``path`` by :meth:`close`; :meth:`abort` (or an exception inside the
        ``with`` block) removes it.
    shape : (H, W)
        Sensor size in pixels; stored as the ``height`` and ``width`` attributes.
    attrs : dict, optional
        Root attributes: strings, numbers, arrays; :class:`~evnoise.NoiseParams`, dicts and
        lists are stored as JSON strings (and decoded again by :func:`read_events`).
        Conventional keys: ``params``, ``seed``, ``source``. ``None`` values are skipped.
    overwrite : bool
        Replace an existing ``path``; otherwise an existing file is an :class:`~evnoise.OutputError`.
    compression : {"gzip", "lzf", None}
        HDF5 filter of the event datasets and ``/ms_to_idx``, with the shuffle filter unless
        ``None``; gzip at level :data:`GZIP_LEVEL`.
    t_end_us : int, optional
        End of the recording in microseconds (exclusive); every event must have
        ``t < t_end_us``. It sets the length of ``/ms_to_idx`` (one entry per millisecond
        up to and including ``ceil(t_end_us / 1000)``) and is stored as an attribute.
        Without it ``/ms_to_idx`` ends one entry after the last event's millisecond.

    Examples
    --------
    >>> with EventWriter("events.h5", (720, 1280), {"seed": 1}) as out:  # doctest: +SKIP
    ...     for chunk in evnoise.iter_events(lux, params, 10.0, rng=1):
    ...         out.write(chunk)
    """

    def __init__(self, path, shape, attrs=None, *, overwrite: bool = False, compression: str | None = "gzip",
                 t_end_us: int | None = None):
        import h5py

        self.shape = _check_shape(shape)
        if compression not in COMPRESSIONS:
            raise ParameterError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")
        if t_end_us is not None:
            if isinstance(t_end_us, bool) or int(t_end_us) != t_end_us or t_end_us < 0:
                raise ParameterError(f"t_end_us must be a non-negative integer of microseconds, got {t_end_us!r}")
            t_end_us = int(t_end_us)
        self.t_end_us = t_end_us
        encoded = {}
        json_keys = []
        for key, value in dict(attrs or {}).items():
            if not isinstance(key, str):
                raise ParameterError(f"attribute names must be strings, got {key!r}")
            if key in _RESERVED:
                raise ParameterError(f"attribute {key!r} is set by evnoise; do not pass it in attrs")
            if value is None:
                continue
            encoded[key], is_json = _encode_attr(key, value)
            if is_json:
                json_keys.append(key)
        self.path = open_output_path(path, overwrite=overwrite, what="event file")
        self.overwrite = overwrite
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
        self._closed = False
        self.n_events = 0
        self._last_t = None
        self._next_ms = 0  # entries of ms_to_idx already written
        try:
            self._file = h5py.File(self._tmp, "w-")
        except OSError as exc:
            self._remove_tmp()
            raise OutputError(f"cannot write event file {self.path}: {exc}") from None
        try:
            f = self._file
            height, width = self.shape
            f.attrs["width"] = np.int64(width)
            f.attrs["height"] = np.int64(height)
            f.attrs["time_unit"] = "us"
            f.attrs["evnoise_version"] = __version__
            if t_end_us is not None:
                f.attrs["t_end_us"] = np.int64(t_end_us)
            for key, value in encoded.items():
                f.attrs[key] = value
            if json_keys:
                f.attrs["json_attrs"] = json.dumps(json_keys)
            filt = {} if compression is None else {"compression": compression, "shuffle": True}
            if compression == "gzip":
                filt["compression_opts"] = GZIP_LEVEL
            group = f.create_group("events")
            self._dsets = {
                name: group.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype,
                                           chunks=(CHUNK_EVENTS,), **filt)
                for name, dtype in _FIELDS
            }
            self._ms = f.create_dataset("ms_to_idx", shape=(0,), maxshape=(None,), dtype=np.uint64,
                                        chunks=(CHUNK_MS,), **filt)
            f.create_dataset("t_offset", data=np.int64(0))
        except BaseException:
            self.abort()
            raise

    # -- context manager ---------------------------------------------------------------
    def __enter__(self) -> "EventWriter":
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False

    def __del__(self):  # a writer dropped without close() leaves no temporary file
        try:
            if not self._closed:
                self.abort()
        except Exception:
            pass

    # -- writing -------------------------------------------------------------------------
    def write(self, events) -> None:
        """Append a chunk of events, sorted by time and not earlier than the previous chunk."""
        if self._closed:
            raise OutputError(f"event file {self.path} is already closed")
        try:
            self._write(events)
        except BaseException:
            self.abort()
            raise

    def _write(self, events):
        events = check_events(events, self.shape)
        n = events.size
        if n == 0:
            return
        t = events["t"]
        if t[0] < 0:
            raise InputError(f"event times must be >= 0 microseconds in an events.h5 file, got t = {t[0]}")
        if self._last_t is not None and t[0] < self._last_t:
            raise InputError(f"events are not sorted across chunks: t = {t[0]} after t = {self._last_t}")
        if self.t_end_us is not None and t[-1] >= self.t_end_us:
            raise InputError(f"event at t = {t[-1]} us is not before t_end_us = {self.t_end_us}")
        base = self.n_events
        try:
            for name, _ in _FIELDS:
                ds = self._dsets[name]
                ds.resize((base + n,))
                ds[base:] = events[name]
            # entries k with 1000 k <= t[-1] are final: no later event can fall before them
            last_ms = int(t[-1]) // 1000
            if last_ms >= self._next_ms:
                ks = np.arange(self._next_ms, last_ms + 1, dtype=np.int64)
                self._append_ms(base + np.searchsorted(t, ks * 1000, side="left"))
        except OSError as exc:
            raise OutputError(f"writing event file {self.path} failed: {exc}") from None
        self.n_events = base + n
        self._last_t = int(t[-1])

    def _append_ms(self, values):
        m = self._ms.shape[0]
        self._ms.resize((m + len(values),))
        self._ms[m:] = np.asarray(values, dtype=np.uint64)
        self._next_ms = m + len(values)

    def close(self) -> Path:
        """Finish ``/ms_to_idx``, close the file and rename it to its final name; returns the path."""
        if self._closed:
            return self.path
        try:
            if self.t_end_us is not None:
                n_ms = -(-self.t_end_us // 1000) + 1
            else:
                n_ms = 1 if self._last_t is None else self._last_t // 1000 + 2
            n_ms = max(n_ms, self._next_ms)
            if n_ms > self._next_ms:
                self._append_ms(np.full(n_ms - self._next_ms, self.n_events, dtype=np.uint64))
            self._file.close()
            if not self.overwrite and self.path.exists():
                raise OutputError(f"event file {self.path} appeared while writing; not replacing it")
            os.replace(self._tmp, self.path)
        except OutputError:
            self.abort()
            raise
        except OSError as exc:
            self.abort()
            raise OutputError(f"cannot finish event file {self.path}: {exc}") from None
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Discard everything written so far (the temporary file is removed)."""
        self._closed = True
        file = getattr(self, "_file", None)
        if file is not None:
            try:
                file.close()
            except Exception:
                pass
        self._remove_tmp()

    def _remove_tmp(self):
        _unlink_quietly(self._tmp)


def write_events(path, events, shape, attrs=None, *, overwrite: bool = False, compression: str | None = "gzip",
                 t_end_us: int | None = None) -> Path:
    """Write an event array to an events.h5 file (DSEC layout, atomically).

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    events : numpy.ndarray
        Events (:data:`evnoise.EVENT_DTYPE`), sorted by time, ``t >= 0`` microseconds.
    shape : (H, W)
        Sensor size in pixels.
    attrs, overwrite, compression, t_end_us
        As in :class:`EventWriter`.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    events = check_events(events, shape)
    with EventWriter(path, shape, attrs, overwrite=overwrite, compression=compression, t_end_us=t_end_us) as out:
        for lo in range(0, events.size, READ_BLOCK):
            out.write(events[lo:lo + READ_BLOCK])
    return out.path


# --------------------------------------------------------------------------------------
# AEDAT4 (through the optional faery package)
# --------------------------------------------------------------------------------------
def _import_faery():
    try:
        import faery
    except ImportError:
        raise OutputError("writing AEDAT4 needs the faery package: pip install 'evnoise[aedat]'") from None
    return faery


def write_aedat4(path, chunks, shape, *, overwrite: bool = False) -> Path:
    """Write event chunks to an AEDAT4 file (iniVation's format) through faery, streaming.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; written to a temporary file in the same directory and renamed on success.
    chunks : iterable of numpy.ndarray
        Event arrays (:data:`evnoise.EVENT_DTYPE`), each sorted by time and not earlier than
        the previous one, ``t >= 0``; consumed one at a time (memory bounded by one chunk).
        A single event array works too.
    shape : (H, W)
        Sensor size in pixels.
    overwrite : bool
        Replace an existing file.

    Notes
    -----
    Timestamps are kept as they are (faery's ``zero_t0=False``). AEDAT4 has no place for
    evnoise's attributes (parameters, seed): keep an events.h5 file for provenance.
    Needs the optional ``faery`` package (``pip install 'evnoise[aedat]'``).
    """
    faery = _import_faery()
    height, width = _check_shape(shape)
    path = open_output_path(path, overwrite=overwrite, what="AEDAT4 file")
    if isinstance(chunks, np.ndarray):
        chunks = [chunks]
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp.aedat4")

    class _Chunks(faery.EventsStream):
        def __init__(self):
            super().__init__()
            self.last_t = None

        def dimensions(self):
            return (width, height)

        def __iter__(self):
            for chunk in chunks:
                events = check_events(chunk, (height, width))
                if not events.size:
                    continue
                if events["t"][0] < 0:
                    raise InputError(f"event times must be >= 0 microseconds, got t = {events['t'][0]}")
                if self.last_t is not None and events["t"][0] < self.last_t:
                    raise InputError(f"events are not sorted across chunks: t = {events['t'][0]} after "
                                     f"t = {self.last_t}")
                self.last_t = int(events["t"][-1])
                out = np.empty(events.size, dtype=faery.EVENTS_DTYPE)
                out["t"] = events["t"]
                out["x"] = events["x"]
                out["y"] = events["y"]
                out["on"] = events["p"] == 1
                yield out

    try:
        _Chunks().to_file(tmp, zero_t0=False, file_type="aedat")
        if not overwrite and path.exists():
            raise OutputError(f"AEDAT4 file {path} appeared while writing; not replacing it")
        os.replace(tmp, path)
    except EvnoiseError:
        _unlink_quietly(tmp)
        raise
    except OSError as exc:
        _unlink_quietly(tmp)
        raise OutputError(f"cannot write AEDAT4 file {path}: {exc}") from None
    except BaseException:
        _unlink_quietly(tmp)
        raise
    return path


def _unlink_quietly(path):
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    except OSError as exc:
        log.warning("could not remove temporary file %s: %s", path, exc)


# --------------------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------------------
def _open_h5(path):
    import h5py

    path = Path(path)
    if not path.exists():
        raise InputError(f"event file not found: {path}")
    if path.is_dir():
        raise InputError(f"expected an event file, got a folder: {path}")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"cannot open event file {path} as HDF5: {exc}") from None


def _event_datasets(f, path):
    group = f.get("events")
    import h5py

    if not isinstance(group, h5py.Group) or not all(isinstance(group.get(k), h5py.Dataset) for k in "xytp"):
        raise InputError(f"{path} is not an events.h5 file (no /events/x, y, t, p datasets)")
    ds = {k: group[k] for k in "xytp"}
    sizes = {ds[k].shape for k in "xytp"}
    if len(sizes) != 1 or len(next(iter(sizes))) != 1:
        raise InputError(f"{path}: /events/x, y, t, p must be 1-D and of equal length, got {sorted(sizes)}")
    return ds


def read_metadata(path) -> dict:
    """Root attributes of an events.h5 file, decoded, plus ``shape``, ``n_events`` and ``t_offset``.

    ``shape`` is ``(height, width)`` from the attributes, or ``None`` for files without them
    (DSEC files, for example). JSON-encoded attributes (``params``) are decoded to dicts.
    """
    with _open_h5(path) as f:
        ds = _event_datasets(f, path)
        return _metadata(f, ds)


def _metadata(f, ds) -> dict:
    meta = {k: _decode_attr(v) for k, v in f.attrs.items()}
    json_keys = meta.pop("json_attrs", None)
    if json_keys:
        for key in json.loads(json_keys):
            if key in meta:
                try:
                    meta[key] = json.loads(meta[key])
                except (TypeError, ValueError):
                    pass
    meta["shape"] = (int(meta["height"]), int(meta["width"])) if "height" in meta and "width" in meta else None
    meta["n_events"] = int(ds["t"].shape[0])
    meta["t_offset"] = int(f["t_offset"][()]) if "t_offset" in f else 0
    return meta


def _first_index(f, t_ds, t_us: int) -> int:
    """Index of the first event with ``t >= t_us``, reading only one millisecond of events."""
    n = t_ds.shape[0]
    ms = f.get("ms_to_idx")
    k = t_us // 1000
    if ms is not None and 0 <= k < ms.shape[0]:
        lo = int(ms[k])
        hi = int(ms[k + 1]) if k + 1 < ms.shape[0] else n
    else:
        lo, hi = 0, n  # no index for this time: search the whole column in blocks
    # binary search over [lo, hi) in blocks, reading at most READ_BLOCK values at a time
    while hi - lo > READ_BLOCK:
        mid = (lo + hi) // 2
        if int(t_ds[mid]) < t_us:
            lo = mid + 1
        else:
            hi = mid
    return lo + int(np.searchsorted(t_ds[lo:hi], t_us, side="left"))


def read_events(path, t_start_us: int | None = None, t_end_us: int | None = None):
    """Read events (all, or those with ``t_start_us <= t < t_end_us``) from an events.h5 file.

    Parameters
    ----------
    path : str or os.PathLike
        An events.h5 file (evnoise's, or any file with the DSEC layout).
    t_start_us, t_end_us : int, optional
        Time window in microseconds, in the file's time base (``t`` as stored, without
        ``t_offset``); located through ``/ms_to_idx`` when the file has it.

    Returns
    -------
    events : numpy.ndarray
        :data:`evnoise.EVENT_DTYPE`, sorted by time.
    meta : dict
        The root attributes (decoded: JSON attributes such as ``params`` become dicts),
        plus ``shape`` ``(H, W)`` (or ``None``), ``n_events`` (in the file) and ``t_offset``.

    Raises
    ------
    InputError
        Missing, unreadable or malformed file.
    """
    with _open_h5(path) as f:
        ds = _event_datasets(f, path)
        meta = _metadata(f, ds)
        n = meta["n_events"]
        try:
            lo = 0 if t_start_us is None else _first_index(f, ds["t"], int(t_start_us))
            hi = n if t_end_us is None else _first_index(f, ds["t"], int(t_end_us))
            hi = max(lo, hi)
            events = make_events(ds["t"][lo:hi], ds["x"][lo:hi], ds["y"][lo:hi], ds["p"][lo:hi])
        except OSError as exc:
            raise InputError(f"cannot read events from {path}: {exc}") from None
    return events, meta
