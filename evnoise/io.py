"""events.h5: event files in the DSEC layout, written incrementally and atomically.

Layout (readable by plain h5py, DSEC's ``EventSlicer``, evlib, tonic)::

    /events/x  uint16     /events/y  uint16
    /events/t  int64 (microseconds, non-decreasing)     /events/p  uint8 (1 = ON, 0 = OFF)
    /ms_to_idx uint64     ms_to_idx[k] = index of the first event with t >= 1000 k
    /t_offset  int64 scalar     (absolute time = t + t_offset; 0 for a clock that starts near 0,
                                 the first event's whole second for a Unix clock)
    root attributes: width, height, time_unit = "us", evnoise_version, and the caller's
    attributes (model parameters as JSON, seed, source, ...)

The event datasets are chunked and resizable, gzip + shuffle compressed by default.
:class:`EventWriter` appends time-sorted chunks, so memory stays bounded by one chunk; it
writes to a temporary file in the target directory and renames it on success, so an error
never leaves a file that looks complete.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import stat
from pathlib import Path

import numpy as np

from ._atomic import AtomicFile, close_h5_discarding, os_error_text, refuse_folder_name
from ._h5 import READ_BLOCK, event_datasets, h5_metadata, open_h5
from ._version import __version__
from .errors import EvnoiseError, InputError, OutputError, ParameterError
from .events import ON, check_events, check_shape

__all__ = ["EventWriter", "EventFileWriter", "Aedat4FileWriter", "Evt3FileWriter", "DatFileWriter",  # noqa: F822
           "EsFileWriter", "CsvFileWriter", "open_event_writer", "import_faery", "output_format", "OUTPUT_FORMATS",
           "write_events", "read_events", "read_metadata", "write_aedat4", "open_output_path"]

log = logging.getLogger(__name__)

#: Events per HDF5 chunk of each ``/events/*`` dataset.
CHUNK_EVENTS = 1 << 16
#: Entries per HDF5 chunk of ``/ms_to_idx``.
CHUNK_MS = 1 << 14
#: ``t_offset_us=None``: a first event at or after this time (2**32 µs, 71.6 minutes) sets
#: ``/t_offset`` to its whole second; an earlier one keeps the clock as it is (``t_offset`` 0).
AUTO_OFFSET_US = 1 << 32
#: Longest ``/ms_to_idx`` written (2**32 entries, 49.7 days after ``t_offset``, 32 GiB); a longer
#: one is refused (a clock that does not start near ``t_offset``), never allocated.
MAX_MS_ENTRIES = 1 << 32
#: ``/ms_to_idx`` entries computed and appended at a time (bounds the memory of a long gap).
_MS_BLOCK = 1 << 20

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
    refuse_folder_name(path, what)
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.exists():
        raise OutputError(f"cannot write {what} {path}: directory {parent} does not exist")
    if not parent.is_dir():
        raise OutputError(f"cannot write {what} {path}: {parent} is not a directory")
    if path.is_dir():
        raise OutputError(f"cannot write {what} {path}: it is a directory")
    if _is_symlink_loop(path):  # Python 3.11's resolve() raised on it by chance; 3.13's returns the path
        raise OutputError(f"cannot write {what} {path}: a loop of symbolic links; give a path that leads to a file")
    if os.path.lexists(path) and not overwrite:  # a symbolic link counts, even a broken one
        raise OutputError(f"{what} {path} already exists; pass overwrite=True to replace it")
    if os.path.lexists(path) and not (path.is_symlink() or path.is_file()):
        # a pipe, socket or device node would be replaced by a regular file (the writers rename into place)
        raise OutputError(f"cannot write {what} {path}: it is a {_special_kind(path)}, not a regular file; "
                          "evnoise writes only regular files")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write {what} {path}: directory {parent} is not writable")
    return path


def _is_symlink_loop(path: Path) -> bool:
    """Whether ``path`` is a symbolic link that leads back to itself (directly or through others)."""
    if not path.is_symlink():
        return False
    try:
        os.stat(path)
    except OSError as exc:
        return exc.errno == errno.ELOOP
    return False


def _special_kind(path: Path) -> str:
    """What a path that is neither a regular file, a folder nor a link is, in words."""
    mode = path.lstat().st_mode
    return ("named pipe (FIFO)" if stat.S_ISFIFO(mode) else "socket" if stat.S_ISSOCK(mode)
            else "device node" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "special file")


def _check_us(value, name: str) -> int | None:
    """A non-negative integer of microseconds (or ``None``), else :class:`~evnoise.ParameterError`."""
    if value is None:
        return None
    try:
        ok = not isinstance(value, bool) and int(value) == value and value >= 0
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok or int(value) >= 1 << 63:
        raise ParameterError(f"{name} must be a non-negative integer of microseconds, got {value!r}")
    return int(value)


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


class _AtomicWriter:
    """What the streaming writers share: a context manager that closes (renames) on success and
    aborts (removes the temporary file) on an exception, and no temporary file left when dropped."""

    _closed = True

    def __enter__(self):
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


class EventWriter(_AtomicWriter):
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
    t_offset_us : int or None
        Stored as ``/t_offset`` (DSEC): events are given on the recording's clock and stored as
        ``t - t_offset_us`` (as is ``t_end_us``), so a camera recording whose clock reads, say,
        1.6e15 µs keeps a short ``/ms_to_idx``. :func:`read_events` adds it back. ``None`` (the
        default) picks it from the first event: 0 when that event is before
        :data:`AUTO_OFFSET_US` (a clock that starts near 0, as simulated streams do), otherwise
        the first event's time rounded down to a whole second (a Unix clock).

    Examples
    --------
    >>> with EventWriter("events.h5", (720, 1280), {"seed": 1}) as out:  # doctest: +SKIP
    ...     for chunk in evnoise.iter_events(lux, params, 10.0, rng=1):
    ...         out.write(chunk)
    """

    def __init__(self, path, shape, attrs=None, *, overwrite: bool = False, compression: str | None = "gzip",
                 t_end_us: int | None = None, t_offset_us: int | None = None):
        import h5py

        self.shape = check_shape(shape)
        if compression not in COMPRESSIONS:
            raise ParameterError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")
        t_end_us = _check_us(t_end_us, "t_end_us")
        self._auto_offset = t_offset_us is None
        self.t_offset_us = 0 if t_offset_us is None else _check_us(t_offset_us, "t_offset_us")
        self._t_end_abs = t_end_us  # on the recording's clock
        self.t_end_us = None  # on the file's clock (t - t_offset), once the offset is known
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
        if not self._auto_offset:
            self._set_offset(self.t_offset_us)
        self.overwrite = overwrite
        self._out = AtomicFile(self.path, overwrite=overwrite, what="event file")
        self._tmp = self._out.tmp
        self._closed = False
        self.n_events = 0
        self._last_t = None
        self._next_ms = 0  # entries of ms_to_idx already written
        self._out.create()  # a clean one-line error (not h5py's) if it cannot be created
        try:
            self._file = h5py.File(self._tmp, "w")
        except OSError as exc:
            self._remove_tmp()
            raise OutputError(f"cannot write event file {self.path}: {os_error_text(exc)}") from None
        try:
            f = self._file
            height, width = self.shape
            f.attrs["width"] = np.int64(width)
            f.attrs["height"] = np.int64(height)
            f.attrs["time_unit"] = "us"
            f.attrs["evnoise_version"] = __version__
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
            self._offset_ds = f.create_dataset("t_offset", data=np.int64(self.t_offset_us))
            self._gzip = None  # gzip chunks are compressed in threads (evnoise._gzip_chunks)
            if compression == "gzip":
                from ._checks import default_threads
                from ._gzip_chunks import ParallelGzipChunks

                self._gzip = ParallelGzipChunks(self._dsets, CHUNK_EVENTS, GZIP_LEVEL, default_threads())
        except BaseException:
            self.abort()
            raise

    # -- context manager ---------------------------------------------------------------
    # -- writing -------------------------------------------------------------------------
    def write(self, events) -> None:
        """Append a chunk of events, sorted by time and not earlier than the previous chunk.

        Parameters
        ----------
        events : numpy.ndarray
            Events (:data:`evnoise.EVENT_DTYPE`) on the recording's clock, sorted by time, at or after
            ``t_offset_us`` and before ``t_end_us`` when given, coordinates inside ``shape``. An empty
            chunk writes nothing. An invalid chunk raises and removes the unfinished file (as :meth:`abort`).
        """
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
        if self._auto_offset and self._last_t is None:
            t0 = int(events["t"][0])
            self._set_offset(t0 // 1_000_000 * 1_000_000 if t0 >= AUTO_OFFSET_US else 0)
        if self.t_offset_us:
            if int(events["t"][0]) < self.t_offset_us:
                raise InputError(f"event at t = {int(events['t'][0])} us is before t_offset_us = {self.t_offset_us}")
            events = events.copy()
            events["t"] -= self.t_offset_us
        t = events["t"]
        if t[0] < 0:
            raise InputError(f"event times must be >= 0 microseconds in an events.h5 file, got t = {t[0]}")
        self._check_ms(int(t[-1]) // 1000 + 1, f"an event at t = {int(t[-1]) + self.t_offset_us} us")
        if self._last_t is not None and t[0] < self._last_t:
            raise InputError(f"events are not sorted across chunks: t = {t[0]} after t = {self._last_t}")
        if self.t_end_us is not None and t[-1] >= self.t_end_us:
            raise InputError(f"event at t = {t[-1]} us is not before t_end_us = {self.t_end_us}")
        base = self.n_events
        try:
            if self._gzip is not None:
                self._gzip.append({name: events[name] for name, _ in _FIELDS})
            else:
                for name, _ in _FIELDS:
                    ds = self._dsets[name]
                    ds.resize((base + n,))
                    ds[base:] = events[name]
            # entries k with 1000 k <= t[-1] are final: no later event can fall before them
            last_ms = int(t[-1]) // 1000
            for lo in range(self._next_ms, last_ms + 1, _MS_BLOCK):  # a long gap: in bounded blocks
                ks = np.arange(lo, min(lo + _MS_BLOCK, last_ms + 1), dtype=np.int64)
                self._append_ms(base + np.searchsorted(t, ks * 1000, side="left"))
        except OSError as exc:
            raise OutputError(f"writing event file {self.path} failed: {os_error_text(exc)}") from None
        self.n_events = base + n
        self._last_t = int(t[-1])

    def _set_offset(self, offset: int) -> None:
        """Fix ``t_offset`` (before the first event): ``t_end_us`` moves to the file's clock."""
        self.t_offset_us = int(offset)
        if getattr(self, "_offset_ds", None) is not None:
            self._offset_ds[()] = np.int64(self.t_offset_us)
        self._auto_offset = False
        if self._t_end_abs is not None:
            if self._t_end_abs < self.t_offset_us:
                raise ParameterError(f"t_end_us = {self._t_end_abs} is before t_offset_us = {self.t_offset_us}")
            self.t_end_us = self._t_end_abs - self.t_offset_us
            self._check_ms(-(-self.t_end_us // 1000) + 1, f"t_end_us = {self._t_end_abs}")

    def _check_ms(self, n_ms: int, what: str) -> None:
        """Refuse a ``/ms_to_idx`` longer than :data:`MAX_MS_ENTRIES` before anything is allocated."""
        if n_ms > MAX_MS_ENTRIES:
            raise InputError(f"cannot write event file {self.path}: {what} is {(n_ms - 1) / 86_400_000:.4g} days "
                             f"after t_offset_us = {self.t_offset_us}, and /ms_to_idx would need {n_ms:,} entries "
                             f"(at most {MAX_MS_ENTRIES:,}); leave t_offset_us at None (it is then taken from the "
                             f"first event) or give the recording's start")

    def _append_ms(self, values):
        m = self._ms.shape[0]
        self._ms.resize((m + len(values),))
        self._ms[m:] = np.asarray(values, dtype=np.uint64)
        self._next_ms = m + len(values)

    def close(self) -> Path:
        """Finish ``/ms_to_idx``, close the file and rename it to its final name; returns the path."""
        if self._closed:
            return self.path

        def close():
            if self._auto_offset:  # no event: an end on a Unix clock sets the offset
                end = self._t_end_abs
                self._set_offset(end // 1_000_000 * 1_000_000 if end is not None and end >= AUTO_OFFSET_US else 0)
            if self.t_end_us is not None:
                self._file.attrs["t_end_us"] = np.int64(self.t_end_us)
                n_ms = -(-self.t_end_us // 1000) + 1
            else:
                n_ms = 1 if self._last_t is None else self._last_t // 1000 + 2
            n_ms = max(n_ms, self._next_ms)
            for lo in range(self._next_ms, n_ms, _MS_BLOCK):
                self._append_ms(np.full(min(_MS_BLOCK, n_ms - lo), self.n_events, dtype=np.uint64))
            if self._gzip is not None:
                self._gzip.finish(self.n_events)
            # flush first: a failure (a full disk) leaves the file open, so abort() can free the space
            # and close it cleanly (a failed close leaves HDF5 a handle it crashes on at exit)
            try:
                self._file.flush()
                self._file.close()
            except RuntimeError as exc:  # h5py raises some write failures as RuntimeError
                raise OSError(os_error_text(exc)) from None

        self._out.finish(close, self.abort)
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Discard everything written so far (the temporary file is removed)."""
        self._closed = True
        if getattr(self, "_gzip", None) is not None:
            self._gzip.close()
        file, self._file = getattr(self, "_file", None), None
        if file is not None:
            # a full disk: see close_h5_discarding (a failed close crashed the process at exit, 139)
            close_h5_discarding(file, getattr(self, "_out", None),
                                [*getattr(self, "_dsets", {}).values(), getattr(self, "_ms", None)])
        self._remove_tmp()

    def _remove_tmp(self):
        out = getattr(self, "_out", None)
        if out is not None:
            out.discard()


def write_events(path, events, shape, attrs=None, *, overwrite: bool = False, compression: str | None = "gzip",
                 t_end_us: int | None = None, t_offset_us: int | None = None) -> Path:
    """Write an event array to an event file, atomically, in the format its suffix names.

    Parameters
    ----------
    path : str or os.PathLike
        Output file. The suffix decides the format, as for the command line's ``--out``
        (:data:`OUTPUT_FORMATS`): ``.h5``/``.hdf5`` (events.h5, DSEC layout), ``.aedat4``,
        ``.raw`` (EVT 3.0), ``.dat``, ``.es``, ``.csv``; any other suffix is a
        :class:`~evnoise.ParameterError`.
    events : numpy.ndarray
        Events (:data:`evnoise.EVENT_DTYPE`), sorted by time, ``t >= 0`` microseconds.
    shape : (H, W)
        Sensor size in pixels.
    attrs : dict, optional
        Attributes stored with the events (``params``, ``seed``, ``source``, ...), as in :class:`EventWriter`.
    overwrite : bool
        Replace an existing ``path``; otherwise an existing file is an :class:`~evnoise.OutputError`.
    compression : {"gzip", "lzf", None}
        HDF5 filter of an events.h5 file, as in :class:`EventWriter`; the other formats ignore it.
    t_end_us : int, optional
        End of the recording in microseconds (exclusive); every event must have ``t < t_end_us``.
    t_offset_us : int, optional
        events.h5 only: the ``/t_offset`` stored, as in :class:`EventWriter`; by default it is taken from the
        first event, so a Unix clock is stored compactly. The other formats ignore it.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    fmt = output_format(path, flag="path")
    events = check_events(events, shape)
    with EventFileWriter(path, shape, attrs, overwrite=overwrite, compression=compression, t_end_us=t_end_us,
                         file_format=fmt, t_offset_us=t_offset_us) as out:
        for lo in range(0, events.size, READ_BLOCK):
            out.write(events[lo:lo + READ_BLOCK])
    return out.path


# --------------------------------------------------------------------------------------
# AEDAT4 (through the optional faery package)
# --------------------------------------------------------------------------------------
def import_faery():
    """The optional ``faery`` package, which the writers of every format but events.h5 use.

    Raises :class:`~evnoise.OutputError` naming the formats that need it and the extra that
    installs it when it is missing.
    """
    try:
        import faery
    except ImportError:
        from .formats import FORMATS

        suffixes = [s for f in FORMATS if f.extra for s in f.written_suffixes]
        listed = ", ".join(suffixes[:-1]) + f" or {suffixes[-1]}" if len(suffixes) > 1 else "".join(suffixes)
        raise OutputError(f"writing {listed} needs the faery package: pip install 'evnoise[readers]'") from None
    return faery


def write_aedat4(path, chunks, shape, *, overwrite: bool = False, attrs=None) -> Path:
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
    attrs : dict, optional
        evnoise's attributes (parameters, seed, source, ...), stored in the file's description
        (node ``evnoise``) and reported by :func:`read_events` / ``evnoise info``.

    Notes
    -----
    Timestamps are kept as they are (not shifted to zero). Needs the optional ``faery``
    package (``pip install 'evnoise[readers]'``).
    """
    if isinstance(chunks, np.ndarray):
        chunks = [chunks]
    with EventFileWriter(path, shape, attrs, overwrite=overwrite, file_format="aedat4") as out:
        for chunk in chunks:
            out.write(chunk)
    return out.path


def __getattr__(name):
    if name == "OUTPUT_FORMATS":
        # Output suffix -> format written (the suffix decides; anything else is an error), derived from
        # evnoise.formats.FORMATS on each use so that a format registered at run time shows
        from .formats import output_formats

        return output_formats()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def output_format(path, *, flag: str = "out") -> str:
    """The format an event output is written in, from its suffix (see :data:`OUTPUT_FORMATS`).

    A folder (an existing one, or a name ending in ``/``) or an unknown suffix is an error;
    ``flag`` names the argument in the message (the caller's parameter name).
    """
    from .formats import output_formats

    table = output_formats()
    text = os.fspath(path)
    known = ", ".join(table)
    if text.endswith(("/", os.sep)) or Path(text).is_dir():
        raise OutputError(f"{flag}={text!r} is a folder; give an event file name ending in {known}")
    suffix = Path(text).suffix.lower()
    if suffix not in table:
        raise ParameterError(f"{flag}={text!r}: unknown event file suffix {suffix or '(none)'!r}; the suffix decides "
                             f"the format: {known}")
    return table[suffix]


class EventFileWriter(_AtomicWriter):
    """Write an event file of any output format chunk by chunk, atomically (a context manager).

    ``EventFileWriter(path, ...)`` returns the writer that :data:`evnoise.formats.FORMATS` names
    for the format: :class:`EventWriter` for ``.h5``; for ``.aedat4``, ``.raw`` (EVT 3.0),
    ``.dat`` (Prophesee DAT 2, CD events), ``.es`` (Event Stream, DVS) and ``.csv`` (header
    ``t,x@W,y@H,on``) one of its subclasses below, through faery's encoders. Every format is written
    under a temporary name in the target folder and renamed on :meth:`close`; an error (or
    :meth:`abort`) removes it.

    Times are written as they are: ``.aedat4`` and ``.csv`` hold any clock; ``.raw`` and ``.dat`` hold
    the camera's clock from its start (no ``% t0`` line, so faery, expelliarmus and OpenEB-style
    decoders read the same times), and a clock they cannot hold (EVT 3.0 from 2**24 µs, DAT from
    2**32 µs: a Unix clock) is written less the first event's whole second, :attr:`time_shift_us`,
    with a warning.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; its suffix decides the format (:func:`output_format`).
    shape : (H, W)
        Sensor size in pixels.
    attrs : dict, optional
        evnoise's attributes (``params``, ``seed``, ``source``, ...): kept in ``.h5`` (root
        attributes) and ``.aedat4`` (description); the other formats have no place for them.
    overwrite, compression, t_end_us, t_offset_us
        As in :class:`EventWriter` (``compression`` and ``t_offset_us`` apply to ``.h5`` only).
    file_format : str, optional
        Force a format (one of :data:`OUTPUT_FORMATS`' values) instead of the suffix.

    Notes
    -----
    A subclass for a faery encoder sets :attr:`format` and :attr:`what` and implements
    :meth:`_open_encoder` and :meth:`_encode`.
    """

    #: Name of the written format (an :data:`OUTPUT_FORMATS` value).
    format = "?"
    #: What the messages call the file.
    what = "event file"
    #: First time (µs) that is written as it is; a later first event shifts the clock (see
    #: :meth:`_check_time_base`). ``None``: every clock is written as it is.
    absolute_below_us = None
    #: The format's name in the warning about a shifted clock.
    _clock_name = ""
    #: Largest width and height (pixels) the format's words hold (``None``: every size :func:`check_shape` takes),
    #: checked before anything is written: a larger coordinate would be cut to its low bits without an error.
    max_side = None
    #: Why, for the error line.
    _side_why = ""

    def __new__(cls, path, shape, attrs=None, *, overwrite: bool = False, compression: str | None = "gzip",
                t_end_us: int | None = None, file_format: str | None = None, t_offset_us: int | None = None):
        if cls is not EventFileWriter:
            return super().__new__(cls)
        from .formats import writer_for

        fmt = file_format or output_format(path)
        try:
            writer = writer_for(fmt)
        except KeyError:
            from .formats import output_format_names

            raise ParameterError(f"file_format must be one of {', '.join(output_format_names())}, "
                                 f"got {fmt!r}") from None
        if isinstance(writer, type) and issubclass(writer, EventFileWriter):
            return super().__new__(writer)  # Python then runs writer.__init__ with these arguments
        return writer(path, shape, attrs, overwrite=overwrite, compression=compression, t_end_us=t_end_us,
                      t_offset_us=t_offset_us)

    def __init__(self, path, shape, attrs=None, *, overwrite: bool = False, compression: str | None = "gzip",
                 t_end_us: int | None = None, file_format: str | None = None, t_offset_us: int | None = None):
        what = self.what
        self.shape = check_shape(shape)
        if self.max_side is not None and max(self.shape) > self.max_side:
            other = ".h5 or .aedat4" if max(self.shape) <= Aedat4FileWriter.max_side else ".h5"
            raise OutputError(f"cannot write {what} {path}: the sensor is {self.shape[1]}x{self.shape[0]} and "
                              f"{self._side_why}, at most {self.max_side}x{self.max_side}; write {other}")
        self.t_end_us = t_end_us
        self.overwrite = overwrite
        self.n_events = 0
        self._last_t = None
        self._t0 = None
        #: What is subtracted from every time written (``.raw``/``.dat`` only; see :meth:`_check_time_base`).
        self.time_shift_us = 0
        self._closed = False
        self._encoder = None
        faery = import_faery()
        from faery import extension

        self.path = open_output_path(path, overwrite=overwrite, what=what)
        self._out = AtomicFile(self.path, overwrite=overwrite, what=what)
        self._tmp = self._out.tmp
        self._out.create()
        self._faery_dtype = faery.EVENTS_DTYPE
        try:
            self._encoder = self._open_encoder(extension, dict(attrs or {})).__enter__()
        except BaseException as exc:  # faery's Rust encoders raise PanicException (a BaseException)
            self.abort()
            if not isinstance(exc, (EvnoiseError, KeyboardInterrupt, SystemExit, GeneratorExit)):
                raise OutputError(f"cannot write {what} {self.path}: {os_error_text(exc)}") from None
            raise

    def _open_encoder(self, extension, attrs: dict):  # pragma: no cover - abstract
        """faery's encoder for :attr:`_tmp` (``extension`` is ``faery.extension``), not yet entered."""
        raise NotImplementedError

    def _encode(self, out: np.ndarray, events: np.ndarray, t: np.ndarray) -> None:
        """Write one chunk: ``out`` in faery's dtype (times less the shift), ``events`` as given, ``t`` shifted."""
        self._encoder.write(out)

    def write(self, events) -> None:
        """Append a chunk of events, sorted by time and not earlier than the previous chunk."""
        if self._closed:
            raise OutputError(f"{self.what} {self.path} is already closed")
        try:
            self._write(events)
        except BaseException as exc:
            self.abort()
            if not isinstance(exc, (EvnoiseError, KeyboardInterrupt, SystemExit, GeneratorExit)):
                raise OutputError(f"writing {self.what} {self.path} failed: {os_error_text(exc)}") from None
            raise

    def _write(self, events):
        events = check_events(events, self.shape)
        if not events.size:
            return
        t = events["t"]
        if t[0] < 0:
            raise InputError(f"event times must be >= 0 microseconds, got t = {t[0]}")
        if self._last_t is not None and t[0] < self._last_t:
            raise InputError(f"events are not sorted across chunks: t = {t[0]} after t = {self._last_t}")
        if self.t_end_us is not None and t[-1] >= self.t_end_us:
            raise InputError(f"event at t = {t[-1]} us is not before t_end_us = {self.t_end_us}")
        self._check_time_base(t)
        last = int(t[-1])  # on the stream's own clock, as the next chunk's times are compared (not shifted)
        if self.time_shift_us:
            t = t - self.time_shift_us
        out = np.empty(events.size, dtype=self._faery_dtype)
        out["t"] = t
        out["x"] = events["x"]
        out["y"] = events["y"]
        out["on"] = events["p"] == ON
        self._encode(out, events, t)
        self.n_events += int(events.size)
        self._last_t = last

    def _check_time_base(self, t):
        """Choose the time shift at the first event, and refuse what the format cannot hold (before
        anything of the chunk is written). Returns the times as written (``t - time_shift_us``).

        ``.raw`` and ``.dat`` count time from the camera's start. A clock whose first event is before
        :attr:`absolute_below_us` (every simulated stream, most camera recordings) is written as it
        is. A later one (a Unix clock from an AEDAT4 camera) cannot be: it is written from the first
        event's whole second, ``time_shift_us``, with a warning naming the shift; the file keeps no
        ``% t0`` line (only faery reads one), so every decoder reads the same, shifted, times.
        """
        if self._t0 is None:
            self._t0 = int(t[0])
            limit = self.absolute_below_us
            if limit is not None and self._t0 >= limit:
                self.time_shift_us = self._t0 // 1_000_000 * 1_000_000
                log.warning("%s: %s counts time from the camera's start and cannot hold this clock (first event at "
                            "%d us); times are written minus %d us (add it back for the original clock; .h5 and "
                            ".aedat4 keep it)", self.path, self._clock_name, self._t0, self.time_shift_us)
        return t - self.time_shift_us

    def close(self) -> Path:
        """Finish the file and rename it to its final name; returns the path."""
        if self._closed:
            return self.path

        def close():
            enc, self._encoder = self._encoder, None
            enc.__exit__(None, None, None)
            self._out.verify_tail()  # faery drops the error of its last flush: a full disk cut the file silently

        # faery's Rust encoders raise errors that are not OSError: catch every Exception, in one line
        self._out.finish(close, self.abort, catch=Exception, one_line=True)
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Discard everything written so far (the temporary file is removed)."""
        self._closed = True
        enc, self._encoder = getattr(self, "_encoder", None), None
        if enc is not None:
            try:
                enc.__exit__(None, None, None)
            except Exception:
                pass
        out = getattr(self, "_out", None)
        if out is not None:
            out.discard()


class Aedat4FileWriter(EventFileWriter):
    """iniVation AEDAT 4 (``.aedat4``): any clock; evnoise's attributes in the description (node ``evnoise``)."""

    format = "aedat4"
    what = "AEDAT4 file"
    max_side = 32767
    _side_why = "AEDAT 4 holds sizes and coordinates as 16-bit signed integers"

    def _open_encoder(self, extension, attrs):
        from ._aedat import aedat_description

        height, width = self.shape
        return extension.aedat.Encoder(self._tmp, aedat_description(extension.aedat, width, height, attrs),
                                       ("lz4", 1))

    def _encode(self, out, events, t):
        self._encoder.write(0, out)


class Evt3FileWriter(EventFileWriter):
    """Prophesee RAW EVT 3.0 (``.raw``): the camera's clock, shifted from 2**24 µs (see the base class)."""

    format = "evt3"
    what = "RAW file"
    _clock_name = "EVT 3.0"
    max_side = 2048
    _side_why = "EVT 3.0 holds x and y in 11 bits (Prophesee: sensors up to 2048x2048)"
    #: EVT 3.0 counts time modulo 2**24 µs (a 12-bit TIME_HIGH of 4096 µs) from the first TIME_HIGH word.
    absolute_below_us = 1 << 24

    def _open_encoder(self, extension, attrs):
        # no zero_t0: the words hold the clock itself (less time_shift_us), as Prophesee's cameras
        # write it, with no "% t0" line that only faery reads (see _check_time_base)
        height, width = self.shape
        return extension.evt.Encoder(self._tmp, "evt3", False, (width, height), True)

    def _encode(self, out, events, t):
        self._encoder.write({"events": out})

    def _check_time_base(self, t):
        rel = super()._check_time_base(t)
        # faery 0.7.1 decodes a TIME_HIGH wrap only when the words step 4095 -> 0: a stream
        # without an event in the last and first 4096 us around a wrap would read back wrong
        prev = np.empty(rel.size, dtype=np.int64)
        prev[0] = rel[0] if self._last_t is None else self._last_t - self.time_shift_us
        prev[1:] = rel[:-1]
        crossed = (rel >> 24) != (prev >> 24)
        if crossed.any():
            ok = ((((prev >> 12) & 0xFFF) == 0xFFF) & (((rel >> 12) & 0xFFF) == 0)
                  & ((rel >> 24) == (prev >> 24) + 1))
            bad = np.flatnonzero(crossed & ~ok)
            if bad.size:
                k = int(bad[0])
                raise OutputError(
                    f"cannot write {self.what} {self.path} as EVT 3.0: the stream has no event near "
                    f"{(self.time_shift_us + ((int(rel[k]) >> 24) << 24)) * 1e-6:.6g} s, where the EVT 3.0 time "
                    f"base (16.8 s) wraps, and faery's decoder would misread every later time; write .h5, "
                    f".aedat4 or .dat, or a shorter or denser stream")
        return rel


class DatFileWriter(EventFileWriter):
    """Prophesee DAT 2 (``.dat``, CD events): 32-bit times of the camera's clock, shifted from 2**32 µs."""

    format = "dat"
    what = "DAT file"
    _clock_name = "DAT"
    max_side = 16383
    _side_why = "DAT CD events hold x and y in 14 bits (faery's encoder takes sizes below 16384)"
    absolute_below_us = 1 << 32

    def _open_encoder(self, extension, attrs):
        height, width = self.shape
        return extension.dat.Encoder(self._tmp, "dat2", "cd", False, (width, height))

    def _encode(self, out, events, t):
        rec = np.empty(events.size, dtype=[("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("payload", "u1")])
        rec["t"], rec["x"], rec["y"], rec["payload"] = t, events["x"], events["y"], events["p"]
        self._encoder.write(rec)

    def _check_time_base(self, t):
        rel = super()._check_time_base(t)
        if int(rel[-1]) >= 1 << 32:
            raise OutputError(f"cannot write {self.what} {self.path}: DAT holds 32-bit timestamps (71.6 minutes "
                              f"from the camera's start or the first event's second); write .h5 or .aedat4")
        return rel


class EsFileWriter(EventFileWriter):
    """Event Stream (``.es``, DVS): time from 0, rows counted from the bottom."""

    format = "es"
    what = "Event Stream file"
    max_side = 65535
    _side_why = "Event Stream holds its size in 16-bit words"

    def _open_encoder(self, extension, attrs):
        height, width = self.shape
        return extension.es.Encoder(self._tmp, "dvs", False, (width, height))

    def _encode(self, out, events, t):
        out["y"] = (self.shape[0] - 1) - out["y"].astype(np.int64)  # Event Stream counts rows from the bottom
        self._encoder.write(out)

    def _check_time_base(self, t):
        if self._t0 is None and int(t[0]) >= 1 << 32:
            raise OutputError(f"cannot write {self.what} {self.path}: Event Stream counts time from 0 and this "
                              f"recording's clock starts at {int(t[0]) * 1e-6:.6g} s; write .h5 or .aedat4")
        return super()._check_time_base(t)


class CsvFileWriter(EventFileWriter):
    """CSV (``.csv``, header ``t,x@W,y@H,on``: the sensor size in the names, as faery writes it): any clock."""

    format = "csv"
    what = "CSV file"
    max_side = 65535
    _side_why = "faery's CSV encoder holds x and y in 16 bits"

    def _open_encoder(self, extension, attrs):
        height, width = self.shape
        return extension.csv.Encoder(self._tmp, ord(","), True, (width, height), True)


def open_event_writer(path, shape, attrs=None, *, overwrite: bool = False, compression: str | None = "gzip",
                      t_end_us: int | None = None, t_offset_us: int | None = None):
    """A writer for ``path`` in the format its suffix names (:class:`EventWriter` or :class:`EventFileWriter`).

    ``t_offset_us`` applies to events.h5 only (``None``: taken from the first event, see
    :class:`EventWriter`).
    """
    return EventFileWriter(path, shape, attrs, overwrite=overwrite, compression=compression, t_end_us=t_end_us,
                           t_offset_us=t_offset_us)


# --------------------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------------------
def read_metadata(path, *, sensor=None, csv_columns=None) -> dict:
    """Root attributes of an events.h5 file, decoded, plus ``shape``, ``n_events`` and ``t_offset``.

    ``shape`` is ``(height, width)`` from the attributes, or ``None`` for files without them
    (DSEC files, for example). JSON-encoded attributes (``params``) are decoded to dicts.
    A camera file gives its header's facts instead (no events are decoded): ``format``,
    ``shape``, ``shape_from``, ``t_offset`` and, where the header names it, ``camera``.
    """
    from .readers import detect_format, open_events, source_meta

    if sensor is not None or csv_columns is not None or detect_format(path) != "h5":
        return source_meta(open_events(path, sensor=sensor, csv_columns=csv_columns))
    with open_h5(path) as f:
        ds = event_datasets(f, path)
        return _with_sensor(h5_metadata(f, ds))


def _with_sensor(meta: dict) -> dict:
    """``meta["sensor"]``: the ``"WxH"`` string to pass back as ``sensor=`` (``shape`` is (H, W))."""
    if meta.get("shape") is not None:
        meta["sensor"] = f"{meta['shape'][1]}x{meta['shape'][0]}"
    return meta


def read_events(path, t_start_us: int | None = None, t_end_us: int | None = None, *, sensor=None,
                t_start: float | None = None, t_end: float | None = None, csv_columns=None):
    """Read events (all, or a time window) from an events.h5 file or any camera file evnoise reads.

    Parameters
    ----------
    path : str or os.PathLike
        An events.h5 file (evnoise's, or any file with the DSEC layout), or a camera file:
        Prophesee ``.raw`` (EVT 2.0/2.1/3.0) and ``.dat``, ``.aedat4``, jAER ``.aedat``, ``.es``,
        ``.csv``, N-MNIST ``.bin`` (see :mod:`evnoise.readers`).
    t_start_us, t_end_us : int, optional
        Time window ``t_start_us <= t < t_end_us`` in integer microseconds on the file's clock
        (for events.h5: ``t`` as stored plus ``t_offset``, which is 0 in evnoise's files);
        located through ``/ms_to_idx`` when the file has it.
    sensor : str or (int, int), optional
        Sensor size ``"WxH"`` or ``(width, height)`` (width first, unlike ``meta["shape"]``), for
        files whose header has none (EVT 2.0, CSV, N-CARS ``.dat``) or a wrong one. A tuple that is
        the header's size swapped is refused; pass ``meta["sensor"]`` back, not ``meta["shape"]``.
    t_start, t_end : float, optional
        The time window in seconds instead (give one form, not both).
    csv_columns : str, optional
        Column order of a CSV file, e.g. ``"x,y,p,t"``.

    Returns
    -------
    events : numpy.ndarray
        :data:`evnoise.EVENT_DTYPE`, sorted by time.
    meta : dict
        For events.h5: the root attributes (decoded: JSON attributes such as ``params`` become
        dicts), plus ``shape`` ``(H, W)`` (or ``None``), ``sensor`` (``"WxH"``, when known),
        ``n_events`` (in the file) and ``t_offset``. For camera files: the header's facts,
        ``format``, ``shape`` (or ``None``), ``sensor``, ``shape_from``, ``t_offset`` and
        ``n_events`` (events returned).

    Raises
    ------
    InputError
        Missing, unreadable, malformed or truncated file; an unknown suffix.
    """
    from .readers import detect_format, time_window
    from .readers import read_events as read_any

    t_start_us, t_end_us = time_window(t_start, t_end, t_start_us, t_end_us)
    if sensor is not None or csv_columns is not None or detect_format(path) != "h5":
        return read_any(path, sensor=sensor, csv_columns=csv_columns, t_start_us=t_start_us, t_end_us=t_end_us)
    from .readers.hdf5 import h5_events_window

    with open_h5(path) as f:
        meta = _with_sensor(h5_metadata(f, event_datasets(f, path)))
    # the events through the camera-file reader's checks (coordinates inside the sensor and 16 bits, times
    # within +-2^62 us, in order): a damaged file is an InputError, not wrapped or absurd events
    events, _ = h5_events_window(path, t_start_us, t_end_us)
    return events, meta

