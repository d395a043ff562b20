"""What every reader shares: the :class:`EventSource` protocol, sensor parsing, windowing.

A reader turns one file into an :class:`EventSource`: the sensor size (from the header, from
the user's ``sensor``, or unknown), the header's metadata, and :meth:`EventSource.chunks`, which
yields time-sorted chunks of :data:`evnoise.EVENT_DTYPE` inside a time window, decoding no more
of the file than the format requires (a format with an index or fixed-size records seeks to the
window; a stream format stops decoding at the window's end).
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import re
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import InputError, ParameterError
from ..events import EVENT_DTYPE, check_shape

log = logging.getLogger("evnoise")

#: The pip extra that installs the third-party decoders.
EXTRA = "readers"


def parse_sensor(sensor) -> tuple[int, int] | None:
    """Sensor size ``(H, W)`` from ``"WxH"`` (e.g. ``"640x480"``) or ``(width, height)``; ``None`` stays ``None``.

    Note the orders: ``sensor`` is width first (as ``--sensor WxH``), ``shape`` and ``meta["shape"]``
    are height first (as NumPy arrays). ``meta["sensor"]`` (``"WxH"``) is what to pass back as
    ``sensor``; a tuple that is exactly a file header's size swapped is refused.
    """
    if sensor is None:
        return None
    if isinstance(sensor, str):
        m = re.fullmatch(r"\s*(\d+)\s*[xX*,]\s*(\d+)\s*", sensor)
        if not m:
            raise ParameterError(f"sensor must be 'WIDTHxHEIGHT', e.g. '640x480', got {sensor!r}")
        width, height = int(m.group(1)), int(m.group(2))
    else:
        try:
            width, height = (int(v) for v in sensor)
        except (TypeError, ValueError):
            raise ParameterError(f"sensor must be 'WxH' or (width, height), got {sensor!r}") from None
    if not (1 <= width <= 65536 and 1 <= height <= 65536):
        raise ParameterError(f"sensor must be WIDTHxHEIGHT with 1 .. 65536 each, got {sensor!r}")
    return height, width


def seconds_to_us(value, name: str) -> int | None:
    """Seconds (float) -> integer microseconds, or ``None``."""
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number of seconds, got {value!r}") from None
    if not np.isfinite(v):
        raise ParameterError(f"{name} must be finite, got {value!r}")
    return int(round(v * 1e6))


def require(module: str, what: str):
    """Import an optional decoder package, or fail naming the extra that installs it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        package = module.split(".")[0]
        raise InputError(f"reading {what} needs the {package} package: pip install 'evnoise[{EXTRA}]'") from None


def tonic_io():
    """tonic's ``io`` module, loaded on its own (``import tonic`` would load its datasets, ~2 s)."""
    spec = importlib.util.find_spec("tonic")
    if spec is None or spec.origin is None:
        require("tonic", "this file")  # raises the error naming the extra
    path = Path(spec.origin).parent / "io.py"
    mod_spec = importlib.util.spec_from_file_location("_evnoise_tonic_io", path)
    module = importlib.util.module_from_spec(mod_spec)
    mod_spec.loader.exec_module(module)
    return module


def decoder_error(path, what: str, exc: BaseException) -> InputError:
    """One-line :class:`InputError` for a third-party decoder's failure on ``path``.

    Interrupts and generator shutdown are re-raised as they are (decoders written in Rust raise
    ``PanicException``, a ``BaseException``, on malformed input: callers catch ``BaseException``
    and pass it here).
    """
    if isinstance(exc, (KeyboardInterrupt, SystemExit, GeneratorExit, InputError)):
        raise exc
    text = " ".join(str(exc).split()) or type(exc).__name__
    meaning = decoder_words(text)
    return InputError(f"cannot read {path} as {what}: " + (f"{meaning} ({text})" if meaning else text))


#: what third-party decoders' messages mean, in words (first match; the decoder's own text is kept beside it)
DECODER_WORDS = (
    ("LZ4 error", "compressed data cannot be decompressed (LZ4): the file is damaged"),
    ("zstd", "compressed data cannot be decompressed (Zstandard): the file is damaged"),
    ("Zstd", "compressed data cannot be decompressed (Zstandard): the file is damaged"),
    ("missing packet size prefix", "a packet's size is missing: the file is cut or damaged"),
    ("no version information", "the header's version line is missing or damaged"),
    ("overflow (", "an event lies outside the sensor size the header gives: the file is damaged or was written "
                   "with the wrong size"),
)


def decoder_words(text: str) -> str | None:
    """What a decoder's message ``text`` means (:data:`DECODER_WORDS`), or None when it is not a known one."""
    return next((words for key, words in DECODER_WORDS if key in text), None)


class EventSource:
    """One event file, opened for reading (subclasses implement :meth:`_chunks`).

    Attributes
    ----------
    path : pathlib.Path
    format : str
        Short format name (``"h5"``, ``"evt2"``, ``"evt3"``, ``"dat"``, ``"aedat4"``,
        ``"aedat2"``, ``"es"``, ``"csv"``, ``"nmnist"``).
    shape : (H, W) or None
        Sensor size in pixels; ``None`` when neither the header nor the caller gives it.
    shape_from : str or None
        Where ``shape`` comes from: ``"header"``, ``"sensor"`` (the caller's ``sensor``) or
        ``"format"`` (a fixed-size format such as N-MNIST); ``None`` when unknown.
    meta : dict
        Header information (format specific), JSON-friendly.
    seekable : bool
        Whether a time window is found without decoding the events before it.
    """

    format = "?"
    seekable = False

    def __init__(self, path, *, sensor=None):
        self.path = Path(path)
        self.shape = None
        self.shape_from = None
        self.meta: dict = {}
        self._user_shape = parse_sensor(sensor)
        self._user_tuple = sensor is not None and not isinstance(sensor, str)
        self._last_t = None

    # -- sensor size -----------------------------------------------------------------
    def _set_shape(self, header_shape, source: str = "header"):
        """Combine the header's size with the caller's ``sensor`` (the caller wins, with a warning)."""
        user = self._user_shape
        if header_shape is not None:
            try:
                header_shape = check_shape(header_shape)
            except InputError:
                raise InputError(f"{self.path}: the {source} gives a {header_shape[1]}x{header_shape[0]} sensor; a "
                                 f"width and height of 1 .. 65536 are needed (a damaged header?)") from None
        if user is not None:
            if self._user_tuple and header_shape is not None and header_shape != user and header_shape == user[::-1]:
                # meta["shape"] is (H, W) and sensor is (W, H): one passed for the other swaps the sensor
                raise ParameterError(
                    f"{self.path}: sensor=({user[1]}, {user[0]}) is the header's {header_shape[1]}x{header_shape[0]} "
                    f"sensor swapped: sensor is (width, height), while meta['shape'] is (height, width); pass "
                    f"meta['sensor'] (\"WxH\"), or the string \"{user[1]}x{user[0]}\" if the header is wrong")
            if header_shape is not None and header_shape != user:
                log.warning("%s: the header says %dx%d; using sensor='%dx%d'", self.path, header_shape[1],
                            header_shape[0], user[1], user[0])
            self.shape, self.shape_from = user, "sensor"
        elif header_shape is not None:
            self.shape, self.shape_from = header_shape, source
        if header_shape is not None:
            self.meta["header_sensor"] = f"{header_shape[1]}x{header_shape[0]}"

    # -- events ------------------------------------------------------------------------
    def chunks(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Iterator[np.ndarray]:
        """Time-sorted chunks of events with ``t_start_us <= t < t_end_us`` (file clock, µs)."""
        self._last_t = None
        for chunk in self._chunks(t_start_us, t_end_us):
            if chunk.size == 0:
                continue
            chunk = self._checked(chunk)
            t = chunk["t"]
            if t_end_us is not None and t[0] >= t_end_us:
                return
            if (t_start_us is not None and t[0] < t_start_us) or (t_end_us is not None and t[-1] >= t_end_us):
                lo = 0 if t_start_us is None else int(np.searchsorted(t, t_start_us, side="left"))
                hi = t.size if t_end_us is None else int(np.searchsorted(t, t_end_us, side="left"))
                chunk = chunk[lo:hi]
            if chunk.size:
                yield chunk

    def _chunks(self, t_start_us, t_end_us) -> Iterator[np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError

    def _checked(self, chunk: np.ndarray) -> np.ndarray:
        """Order in time (a chunk that jitters is sorted; one that goes back across chunks is an
        error) and coordinates inside the sensor."""
        t = chunk["t"]
        if t.size > 1 and np.any(t[1:] < t[:-1]):
            chunk = chunk[np.argsort(t, kind="stable")]
            t = chunk["t"]
            if not getattr(self, "_warned_sort", False):
                log.warning("%s: timestamps are not sorted within a packet; sorting them", self.path)
                self._warned_sort = True
        if self._last_t is not None and t[0] < self._last_t:
            raise InputError(f"{self.path}: timestamps go back in time ({int(t[0])} us after {self._last_t} us); "
                             f"the file is corrupt or not time-sorted")
        self._last_t = int(t[-1])
        if self.shape is not None:
            height, width = self.shape
            if int(chunk["x"].max()) >= width or int(chunk["y"].max()) >= height:
                where = "sensor=" if self.shape_from == "sensor" else "the header"
                raise InputError(f"{self.path}: an event at x = {int(chunk['x'].max())}, y = {int(chunk['y'].max())} "
                                 f"lies outside the {width}x{height} sensor given by {where}")
        return chunk

    def close(self) -> None:
        """Release the file (readers that keep it open override this)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def packets_in_window(packets, t_start_us, t_end_us):
    """The non-empty packets of a time-sorted decoder stream that may hold events of the window.

    Skips packets that end before ``t_start_us`` and stops after the first one that reaches
    ``t_end_us`` (either may be None); the exact trimming is :meth:`EventSource.chunks`'.
    """
    for packet in packets:
        if len(packet) == 0:
            continue
        last = int(packet["t"][-1])
        if t_start_us is not None and last < t_start_us:
            continue
        yield packet
        if t_end_us is not None and last >= t_end_us:
            return


def to_events(t, x, y, p) -> np.ndarray:
    """Four columns -> :data:`EVENT_DTYPE` (``p`` nonzero -> 1)."""
    out = np.empty(len(t), dtype=EVENT_DTYPE)
    out["t"] = t
    out["x"] = x
    out["y"] = y
    out["p"] = np.asarray(p) != 0
    return out


def from_faery(packet: np.ndarray) -> np.ndarray:
    """faery's ``(t u8, x u2, y u2, on ?)`` -> :data:`EVENT_DTYPE`."""
    return to_events(packet["t"], packet["x"], packet["y"], packet["on"])


def header_lines(path: Path, prefix: bytes, *, limit: int = 1 << 20, what: str | None = None
                 ) -> tuple[list[str], int]:
    """The leading lines of ``path`` that start with ``prefix`` (decoded) and the offset after them.

    With ``what`` (the format's name), a file that ends inside a header line (no line end) is an
    :class:`InputError` naming the truncation.
    """
    lines = []
    offset = 0
    with open(path, "rb") as fh:
        while offset < limit:
            start = fh.tell()
            head = fh.read(len(prefix))
            if head != prefix:
                fh.seek(start)
                break
            line = fh.readline()
            if what is not None and not line.endswith(b"\n"):
                raise InputError(f"cannot read {path} as {what}: the file ends inside its text header (line "
                                 f"{len(lines) + 1} has no end); it was cut (truncated file)")
            lines.append((head + line).decode("latin-1").rstrip("\r\n"))
            offset = fh.tell()
    return lines, offset


def check_whole_records(path, what: str, body: int, size: int, unit: str = "event") -> None:
    """An :class:`InputError` when a data section of ``body`` bytes is not a whole number of ``size``-byte
    records: the file was cut inside one (or has bytes appended)."""
    if body % size:
        raise InputError(f"cannot read {path} as {what}: the data section ({body} bytes) is not a whole number "
                         f"of {size}-byte {unit}s; the file was cut inside one (truncated file) or has "
                         f"{body % size} stray bytes at its end")


def warn_no_data(path, what: str) -> None:
    """A warning for a file whose header is followed by no event data at all."""
    log.warning("%s: the %s file has a header and no event data after it (an empty recording, or a file cut "
                "at the end of its header)", path, what)
