"""Event Stream ``.es`` (neuromorphic-paris), DVS and ATIS types, through faery.

The header holds the sensor size; y is flipped to evnoise's top-left origin as faery does
(Event Stream counts rows from the bottom). ATIS exposure measurements are dropped, change
detections kept. The ``generic`` and ``color`` types carry no polarity events and are refused.
Timestamps are delta-encoded, so a window is found by decoding from the start (stopping at
its end).

faery drops an event cut short at the end of the file without a word; evnoise walks the byte
structure first (Event Stream 2.x, as faery and loris write it: a DVS or ATIS event is 5 bytes, a
time byte then x and y as 16-bit words; an overflow or reset is one byte whose high 7 (DVS) or 6
(ATIS) bits are all set) and refuses a file that ends inside an event.
"""

from __future__ import annotations

import numpy as np

from .._kernels._jit import kernel
from ..errors import InputError
from ._base import EventSource, decoder_error, packets_in_window, require, to_events, warn_no_data

#: Bytes before the events in an Event Stream 2.x DVS or ATIS file: magic (12), version (3),
#: type (1), width and height (2 + 2).
_ES2_DATA_START = 20
#: Per type, the shift of byte 0 whose result 0b1111111 (DVS) / 0b111111 (ATIS) marks a one-byte
#: overflow or reset instead of a 5-byte event.
_SPECIAL = {"dvs": (1, 0x7F), "atis": (2, 0x3F)}
_EVENT_BYTES = 5
#: Bytes walked per call of the structure check (bounds its memory).
_BLOCK = 1 << 24


@kernel
def _walk_kernel(buf, i, shift, value, size):
    """Offset after the last whole unit of ``buf`` from ``i`` (may exceed ``buf.size`` when the last
    event is cut): a byte with ``byte >> shift == value`` is one byte, any other starts an event."""
    n = buf.size
    while i < n:
        if (buf[i] >> shift) == value:
            i += 1
        else:
            i += size
    return i


def _walk(data: np.ndarray, start: int, shift: int, value: int) -> int:
    return int(_walk_kernel(data, np.int64(start), np.uint8(shift), np.uint8(value), np.int64(_EVENT_BYTES)))


def es_cut_event(path, kind: str) -> int:
    """Bytes missing from the last event of an Event Stream 2.x DVS/ATIS file (0 when it ends between events)."""
    shift, value = _SPECIAL[kind]
    size = path.stat().st_size
    if size <= _ES2_DATA_START:
        return 0
    data = np.memmap(path, dtype=np.uint8, mode="r")
    i = _ES2_DATA_START
    while True:  # block by block: an event overhanging a block's end carries over
        end = min(size, i + _BLOCK)
        j = _walk(np.asarray(data[:end]), i, shift, value)
        if end == size:
            return max(0, j - size)
        i = j  # the walk stops at the first unit that starts at or after ``end``


class EsSource(EventSource):
    format = "es"

    def __init__(self, path, *, sensor=None):
        super().__init__(path, sensor=sensor)
        require("faery", "Event Stream files")
        from faery.extension import es

        size = self.path.stat().st_size
        with open(self.path, "rb") as fh:
            head = fh.read(_ES2_DATA_START)
        if len(head) < 16 or (head[12] == 2 and head[15] in (1, 2) and len(head) < _ES2_DATA_START):
            raise InputError(f"cannot read {self.path} as Event Stream: the file ends inside its header (after "
                             f"{size} bytes); it was cut (truncated file)")
        try:
            with es.Decoder(self.path, 0) as dec:
                kind, dims, version = dec.event_type, dec.dimensions, dec.version
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, "Event Stream", exc) from None
        if kind not in ("dvs", "atis"):
            raise InputError(f"{self.path}: Event Stream type {kind!r} holds no polarity events (dvs or atis needed)")
        self._kind = kind
        self._height = dims[1]
        self.meta = {"es_version": str(version), "event_type": kind}
        if str(version).startswith("2."):
            missing = es_cut_event(self.path, kind)
            if size == _ES2_DATA_START:
                warn_no_data(self.path, "Event Stream")
            if missing:
                raise InputError(f"cannot read {self.path} as Event Stream: the file ends inside an event "
                                 f"({missing} of its {_EVENT_BYTES} bytes missing): it was cut (truncated file) or "
                                 f"has stray bytes at its end")
        self._set_shape((dims[1], dims[0]))

    def _chunks(self, t_start_us, t_end_us):
        from faery.extension import es

        try:
            with es.Decoder(self.path, 0) as dec:
                atis = self._kind == "atis"
                packets = (p[~p["exposure"]] if atis else p for p in dec)  # ATIS: polarity events only
                for packet in packets_in_window(packets, t_start_us, t_end_us):
                    on = packet["polarity"] if atis else packet["on"]
                    yield to_events(packet["t"], packet["x"], (self._height - 1) - packet["y"].astype("i4"), on)
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, "Event Stream", exc) from None
