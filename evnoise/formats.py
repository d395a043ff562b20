"""Event file formats: one registry entry per format, the one place a format is declared.

Each :class:`FileFormat` in :data:`FORMATS` says how a format is told (suffixes, magic bytes),
named (label, the names its reader reports), read and written (``"module:attribute"`` strings,
imported on first use, so importing this module imports no reader, writer or decoder) and what
it needs installed (the pip extra). Everything else is derived from the registry:

- detection (:func:`detect_format`: magic bytes first, then the suffix) and reader dispatch
  (:func:`reader_for`, used by :func:`evnoise.readers.open_events`);
- the suffix tables :data:`evnoise.readers.SUFFIXES` and :data:`evnoise.io.OUTPUT_FORMATS`,
  :func:`evnoise.io.output_format` and the writer :class:`evnoise.io.EventFileWriter` returns;
- ``evnoise info``'s format names and clock notes (:func:`describe`, :func:`clock_note`);
- the command line's output format choices and help (:func:`output_format_names`,
  :func:`output_formats_help`).

Adding a format: write its reader (an :class:`evnoise.readers.EventSource` subclass) and/or
writer (a class taking ``(path, shape, attrs=None, *, overwrite, compression, t_end_us,
t_offset_us)`` with ``write``, ``close``, ``abort`` and the context-manager protocol), and add
one :class:`FileFormat` to :data:`FORMATS` (or :func:`register` it at run time).
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

__all__ = ["FileFormat", "FORMATS", "register", "unregister", "get_format", "format_for_suffix",
           "formats_for_suffix", "detect_format", "reader_for", "writer_for", "input_suffixes", "output_formats",
           "output_format_names", "output_formats_help", "describe", "clock_note", "resolve"]


@dataclass(frozen=True)
class FileFormat:
    """One event file format.

    Parameters
    ----------
    name : str
        Short name (what :func:`detect_format` returns and readers' ``EventSource.format`` is,
        unless ``variants`` lists finer names).
    suffixes : tuple of str
        Lower-case suffixes that say this format (``".h5"``); a suffix may be shared by several
        formats (``.aedat``), and the format whose first suffix it is comes first.
    label : str
        Human name, used in messages and by ``evnoise info``.
    magic : tuple of bytes
        Prefixes that identify the content. A file whose suffix names a format with magic bytes
        but whose content has none of them is refused; a format without magic is told by its suffix.
    reader : str or callable, optional
        ``"module:attribute"`` (or the object itself) called as ``reader(path, sensor=..., **options)``
        and returning an :class:`evnoise.readers.EventSource`.
    writer : str or callable, optional
        ``"module:attribute"`` (or the object) called as ``writer(path, shape, attrs, overwrite=...,
        compression=..., t_end_us=..., t_offset_us=...)``, returning a writer with ``write(events)``,
        ``close() -> Path``, ``abort()`` and ``with`` support.
    extra : str, optional
        The pip extra that installs the packages the reader and writer need (``"readers"``:
        ``pip install 'evnoise[readers]'``); ``None`` when evnoise's own dependencies suffice.
    output_name : str, optional
        Name of the format written (``--format`` choice, :data:`evnoise.io.OUTPUT_FORMATS` value);
        defaults to ``name`` (Prophesee RAW is read in EVT 2.0, 2.1 and 3.0 and written as ``"evt3"``).
    output_suffixes : tuple of str, optional
        Suffixes that select this writer; defaults to ``suffixes``.
    variants : tuple of (str, str)
        Finer names a reader reports in ``EventSource.format`` (``("evt3", "Prophesee RAW EVT 3.0")``)
        with their labels.
    clock : str
        What the format's timestamps are (the convention of the format's owner), as ``info`` states it.
    options : tuple of str
        Keyword options the reader takes besides ``sensor`` (``("csv_columns",)``).
    probe : str or callable, optional
        ``"module:attribute"`` of a cheap ``probe(path) -> bool``: is this file an event file of the
        format (an HDF5 file needs ``/events``)? Without one, the suffix is enough.
    """

    name: str
    suffixes: tuple
    label: str
    magic: tuple = ()
    reader: str | Callable | None = None
    writer: str | Callable | None = None
    extra: str | None = None
    output_name: str | None = None
    output_suffixes: tuple | None = None
    variants: tuple = ()
    clock: str = ""
    options: tuple = ()
    probe: str | Callable | None = None

    @property
    def written_as(self) -> str:
        """The name of the written format (``output_name`` or ``name``)."""
        return self.output_name or self.name

    @property
    def written_suffixes(self) -> tuple:
        """Suffixes that select this format's writer (empty without a writer)."""
        if self.writer is None:
            return ()
        return self.output_suffixes if self.output_suffixes is not None else self.suffixes

    @property
    def written_label(self) -> str:
        """Label of what the writer writes (a variant's label where ``output_name`` is one)."""
        return dict(self.variants).get(self.written_as, self.label)


_CAMERA_CLOCK = "µs of the camera's clock as stored (Prophesee's convention: no offset line)"

#: The registry, in the order suffixes and output formats are listed.
FORMATS: tuple = (
    FileFormat("h5", (".h5", ".hdf5"), "events.h5 (HDF5, DSEC layout)", magic=(b"\x89HDF\r\n\x1a\n",),
               reader="evnoise.readers.hdf5:H5Source", writer="evnoise.io:EventWriter",
               clock="µs; absolute time = /events/t + /t_offset (DSEC)", probe="evnoise.readers.hdf5:has_events"),
    FileFormat("aedat4", (".aedat4", ".aedat"), "iniVation AEDAT 4", magic=(b"#!AER-DAT4",),
               reader="evnoise.readers.inivation:Aedat4Source", writer="evnoise.io:Aedat4FileWriter",
               extra="readers", output_suffixes=(".aedat4",),
               clock="µs as DV stores them (usually since the Unix epoch)"),
    FileFormat("raw", (".raw", ".evt"), "Prophesee RAW", reader="evnoise.readers.prophesee:RawSource",
               writer="evnoise.io:Evt3FileWriter", extra="readers", output_name="evt3", output_suffixes=(".raw",),
               variants=(("evt2", "Prophesee RAW EVT 2.0"), ("evt2.1", "Prophesee RAW EVT 2.1"),
                         ("evt3", "Prophesee RAW EVT 3.0")), clock=_CAMERA_CLOCK),
    FileFormat("dat", (".dat",), "Prophesee DAT", reader="evnoise.readers.prophesee:DatSource",
               writer="evnoise.io:DatFileWriter", extra="readers", clock=_CAMERA_CLOCK),
    FileFormat("es", (".es",), "Event Stream", magic=(b"Event Stream",), reader="evnoise.readers.eventstream:EsSource",
               writer="evnoise.io:EsFileWriter", extra="readers",
               clock="µs from the start of the recording (Event Stream counts from 0)"),
    FileFormat("csv", (".csv", ".txt"), "CSV / text event list", reader="evnoise.readers.text:CsvSource",
               writer="evnoise.io:CsvFileWriter", extra="readers", output_suffixes=(".csv",),
               clock="µs as written in the file (seconds when written with a decimal point)", options=("csv_columns",)),
    FileFormat("aedat2", (".aedat",), "jAER AEDAT 2.0", magic=(b"#!AER-DAT2",),
               reader="evnoise.readers.inivation:Aedat2Source", extra="readers", clock="µs of jAER's clock as stored"),
    FileFormat("nmnist", (".bin",), "N-MNIST .bin", reader="evnoise.readers.nmnist:NmnistSource", extra="readers",
               clock="µs from the start of the sample"),
)


def register(fmt: FileFormat) -> None:
    """Add a format to :data:`FORMATS` at run time (a plugin's format); its name must be new."""
    global FORMATS
    if not isinstance(fmt, FileFormat):
        raise TypeError(f"fmt must be a FileFormat, got {type(fmt).__name__}")
    taken = {f.name for f in FORMATS} | {f.written_as for f in FORMATS if f.writer is not None}
    if fmt.name in taken or (fmt.writer is not None and fmt.written_as in taken):
        raise ValueError(f"a format named {fmt.name!r} is already registered")
    FORMATS = FORMATS + (fmt,)


def unregister(name: str) -> None:
    """Remove the format named ``name`` from :data:`FORMATS` (undoes :func:`register`)."""
    global FORMATS
    FORMATS = tuple(f for f in FORMATS if f.name != name)


def resolve(target):
    """The object a ``"module:attribute"`` string names (imported now); a callable is returned as it is."""
    if not isinstance(target, str):
        return target
    module, _, attr = target.partition(":")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


# --------------------------------------------------------------------------------------
# look-ups
# --------------------------------------------------------------------------------------
def get_format(name: str) -> FileFormat:
    """The entry whose ``name``, written name or variant is ``name``; :class:`KeyError` if none."""
    for f in FORMATS:
        if f.name == name:
            return f
    for f in FORMATS:
        if name == f.written_as or name in dict(f.variants):
            return f
    raise KeyError(name)


def describe(name: str) -> str:
    """Label of a format or of a reader's variant name (``"evt3"`` -> ``"Prophesee RAW EVT 3.0"``)."""
    try:
        f = get_format(name)
    except KeyError:
        return name
    return dict(f.variants).get(name, f.label)


def clock_note(name: str) -> str | None:
    """What the timestamps of format ``name`` (or a variant) are; ``None`` for an unknown name."""
    try:
        return get_format(name).clock or None
    except KeyError:
        return None


def input_suffixes() -> dict:
    """Suffix -> names of the formats it may hold (the primary format first), in registry order."""
    out: dict = {}
    for f in FORMATS:
        if f.reader is None:
            continue
        for s in f.suffixes:
            out.setdefault(s, [])
    for s in out:
        out[s] = tuple(f.name for f in formats_for_suffix(s))
    return out


def formats_for_suffix(suffix: str) -> tuple:
    """Readable formats a suffix may hold: those whose first suffix it is, then the others."""
    suffix = suffix.lower()
    found = [f for f in FORMATS if f.reader is not None and suffix in f.suffixes]
    return tuple(sorted(found, key=lambda f: f.suffixes[0] != suffix))


def format_for_suffix(path) -> FileFormat | None:
    """The format a file name's suffix says first (``None`` for an unknown suffix); reads nothing."""
    found = formats_for_suffix(Path(os.fspath(path)).suffix)
    return found[0] if found else None


def output_formats() -> dict:
    """Output suffix -> written format name (the suffix decides), in registry order."""
    return {s: f.written_as for f in FORMATS for s in f.written_suffixes}


def output_format_names() -> tuple:
    """Names of the formats evnoise writes (the choices of the command line's output format)."""
    return tuple(dict.fromkeys(f.written_as for f in FORMATS if f.writer is not None))


def output_formats_help() -> str:
    """One sentence listing each written format with its suffixes and what it needs installed."""
    parts, extras = [], {}
    for f in FORMATS:
        if f.writer is None:
            continue
        parts.append(f"{f.written_as} ({' or '.join(f.written_suffixes)}): {f.written_label}")
        if f.extra:
            extras.setdefault(f.extra, []).append(f.written_as)
    text = "the file's suffix decides the format: " + "; ".join(parts)
    for extra, names in extras.items():
        text += f". {', '.join(names)} need pip install 'evnoise[{extra}]'"
    return text


def writer_for(name: str):
    """The writer of written format ``name`` (imported now); :class:`KeyError` for one evnoise cannot write."""
    for f in FORMATS:
        if f.writer is not None and f.written_as == name:
            return resolve(f.writer)
    raise KeyError(name)


def reader_for(fmt) -> Callable:
    """The reader of a format (a :class:`FileFormat` or its name), imported now."""
    f = fmt if isinstance(fmt, FileFormat) else get_format(fmt)
    if f.reader is None:
        raise KeyError(f.name)
    return resolve(f.reader)


# --------------------------------------------------------------------------------------
# detection
# --------------------------------------------------------------------------------------
def _by_magic(head: bytes) -> FileFormat | None:
    for f in FORMATS:
        if f.reader is not None and any(head.startswith(m) for m in f.magic):
            return f
    return None


def detect_format(path) -> str:
    """Name of the format of an event file: its magic bytes where it has them, its suffix otherwise.

    A suffix that contradicts the content, one that no format has, or a file without the magic
    bytes its suffix requires is an :class:`~evnoise.InputError`.
    """
    from ._checks import check_input_file
    from .errors import InputError

    path = check_input_file(path, missing="event file", kind="an event file")
    size = max([16] + [len(m) for f in FORMATS for m in f.magic])
    try:
        with open(path, "rb") as fh:
            head = fh.read(size)
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror or exc}") from None
    if not head:
        raise InputError(f"{path} is empty (0 bytes): not an event file")
    magic = _by_magic(head)
    if magic is None and head.startswith(b"#!AER-DAT"):  # an AEDAT version no entry declares
        raise InputError(f"{path}: AEDAT version {head[9:12].decode('latin-1', 'replace')!r} is not supported "
                         f"(AEDAT 2.0 and 4.0 are)")
    suffix = path.suffix.lower()
    allowed = formats_for_suffix(suffix)
    if not allowed:
        known = ", ".join(input_suffixes())
        hint = f" (its content looks like {magic.label})" if magic else ""
        raise InputError(f"{path}: unknown event file suffix {suffix or '(none)'!r}{hint}; evnoise reads {known}")
    if magic is not None:
        if magic not in allowed:
            raise InputError(f"{path}: the content is {magic.label} but the suffix {suffix} says "
                             f"{' or '.join(f.label for f in allowed)}; rename the file")
        return magic.name
    fmt = allowed[0]
    if fmt.magic:
        raise InputError(f"{path} is not a valid {fmt.label} file (its first bytes do not match the format)")
    return fmt.name
