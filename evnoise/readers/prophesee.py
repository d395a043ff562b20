"""Prophesee files: RAW (EVT 2.0, 2.1, 3.0) and DAT, through faery (Event2d DAT read here).

- ``.raw``: the ``% key value`` text header, then EVT words. faery decodes all three EVT versions
  (version and geometry from the header: ``% evt 3.0``, ``% format EVT3;height=720;width=1280``
  or ``% geometry``). EVT words carry no absolute index, so a time window is found by decoding
  from the start; decoding stops at the window's end and memory stays at one packet.
- ``.dat``: the ``%`` header, then 8-byte records. ``CD`` files (as faery and Metavision write
  them) go through faery; ``Event2d`` files (ATIS datasets such as N-CARS), which faery refuses, are
  read here (:func:`dat_records`: the same 8-byte layout, read in blocks from a memory map; the tests
  compare them with expelliarmus'). The records' raw 32-bit times are checked to go forward
  (:func:`dat_blocks`; for CD files in a pass before faery decodes): faery clamps a time that goes back
  to the one before and expelliarmus takes it for a wrap of the clock (printing a warning of its own on
  standard output), so a damaged file would otherwise read as if whole.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ._base import (
    EventSource,
    check_whole_records,
    decoder_error,
    from_faery,
    header_lines,
    packets_in_window,
    require,
    to_events,
    warn_no_data,
)

#: Placeholder geometry handed to faery when a file has none (faery needs one; no event is
#: checked against it). The events' extent is what evnoise reports then.
NO_GEOMETRY = (65535, 65535)


def _header_dict(lines):
    out = {}
    for line in lines:
        body = line[1:].strip()
        if not body:
            continue
        key, _, value = body.partition(" ")
        out[key] = value.strip() if key not in out else f"{out[key]}; {value.strip()}"
    return out


def fields_end(lines) -> bool:
    """Whether a RAW header closes with Metavision's ``% end`` line (a complete header of an empty file)."""
    return bool(lines) and lines[-1].strip().lower() == "% end"


class RawSource(EventSource):
    """Prophesee RAW (EVT 2.0 / 2.1 / 3.0)."""

    def __init__(self, path, *, sensor=None):
        super().__init__(path, sensor=sensor)
        require("faery", "Prophesee RAW files")
        from faery.extension import evt

        lines, self._data_offset = header_lines(self.path, b"%", what="Prophesee RAW")
        self.meta = {"header_fields": _header_dict(lines)}
        geometry = True
        try:
            with evt.Decoder(self.path, None, None) as dec:
                version, dims = dec.version, dec.dimensions
        except RuntimeError as exc:
            if "size" not in str(exc):
                raise decoder_error(self.path, "Prophesee RAW (EVT)", exc) from None
            geometry = False
            try:
                with evt.Decoder(self.path, NO_GEOMETRY, None) as dec:
                    version, dims = dec.version, dec.dimensions
            except BaseException as exc2:  # noqa: BLE001 - see decoder_error
                raise decoder_error(self.path, "Prophesee RAW (EVT)", exc2) from None
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, "Prophesee RAW (EVT)", exc) from None
        self.format = str(version)
        self.meta["evt_version"] = str(version)
        # EVT 2.0 / 2.1 words are 32 bits, EVT 3.0 words 16 bits: a cut inside a word is a truncation
        # (a cut between words cannot be told from a shorter recording)
        body = self.path.stat().st_size - self._data_offset
        check_whole_records(self.path, f"Prophesee RAW ({version})", body, 2 if "3" in str(version) else 4, "word")
        if body == 0 and not fields_end(lines):
            warn_no_data(self.path, "Prophesee RAW")
        fields = self.meta["header_fields"]
        if fields.get("plugin_name") or fields.get("integrator_name"):
            self.meta["camera"] = " ".join(v for v in (fields.get("integrator_name"), fields.get("plugin_name")) if v)
        self._fallback = NO_GEOMETRY  # faery checks nothing against it; evnoise checks the sensor itself
        self._set_shape((dims[1], dims[0]) if geometry else None)
        if not geometry:
            self.meta["geometry"] = "none in the header"

    def _chunks(self, t_start_us, t_end_us):
        from faery.extension import evt

        try:
            with evt.Decoder(self.path, self._fallback, None) as dec:
                for packet in dec:
                    events = packet.get("events")
                    if events is None or len(events) == 0:
                        continue
                    if t_start_us is not None and int(events["t"][-1]) < t_start_us:
                        continue
                    yield from_faery(events)
                    if t_end_us is not None and int(events["t"][-1]) >= t_end_us:
                        return
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, f"Prophesee RAW ({self.format})", exc) from None


class DatSource(EventSource):
    """Prophesee DAT (CD through faery, Event2d read here: :func:`dat_records`)."""

    format = "dat"

    def __init__(self, path, *, sensor=None):
        super().__init__(path, sensor=sensor)
        require("faery", "Prophesee DAT files")
        from faery.extension import dat

        lines, self._data_offset = header_lines(self.path, b"%", what="Prophesee DAT")
        self.meta = {"header_fields": _header_dict(lines)}
        if self._data_offset + 2 > self.path.stat().st_size:
            raise InputError(f"cannot read {self.path} as Prophesee DAT: no event-type header after the text header")
        geometry = True
        try:
            try:
                with dat.Decoder(self.path, None, None) as dec:
                    kind, dims = dec.event_type, dec.dimensions
            except RuntimeError as exc:
                if "size" not in str(exc):
                    raise
                geometry = False
                with dat.Decoder(self.path, NO_GEOMETRY, None) as dec:
                    kind, dims = dec.event_type, dec.dimensions
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, "Prophesee DAT", exc) from None
        if kind not in ("cd", "2d"):
            raise InputError(f"{self.path}: a DAT file of {kind} events holds no change-detection events")
        self.meta["event_type"] = "CD" if kind == "cd" else "Event2d"
        self._kind = kind
        self._fallback = NO_GEOMETRY
        self._set_shape((dims[1], dims[0]) if geometry and dims else None)
        if self.shape is None and not geometry:
            self.meta["geometry"] = "none in the header"
        body = self.path.stat().st_size - self._data_offset - 2
        check_whole_records(self.path, "Prophesee DAT", body, 8)
        if body == 0:
            warn_no_data(self.path, "Prophesee DAT")

    def _chunks(self, t_start_us, t_end_us):
        if self._kind == "cd":
            from faery.extension import dat

            check_dat_times(self.path, self._data_offset + 2, t_end_us)
            try:
                with dat.Decoder(self.path, self._fallback, None) as dec:
                    for packet in packets_in_window(dec, t_start_us, t_end_us):
                        yield to_events(packet["t"], packet["x"], packet["y"], packet["payload"])
            except BaseException as exc:  # noqa: BLE001 - see decoder_error
                raise decoder_error(self.path, "Prophesee DAT", exc) from None
            return
        yield from packets_in_window(dat_records(self.path, self._data_offset + 2, t_end_us), t_start_us, t_end_us)


#: Records that :func:`dat_blocks` reads at a time (8 MB of the file).
DAT_CHECK_RECORDS = 1 << 20


def dat_blocks(path, offset: int, t_end_us: int | None = None):
    """A DAT file's 8-byte records from ``offset`` (the first record), as ``(n, 2)`` little-endian uint32 arrays
    ``(time, address)`` of :data:`DAT_CHECK_RECORDS` records (read from a memory map), up to the first record that
    reaches ``t_end_us`` (a window's read ends there, so damage after it does not stop the read, wherever the blocks
    fall), each checked to go forward in time before it is yielded.

    A time before the previous record's is an :class:`InputError` naming the record: a drop of more than half the
    clock's range as the clock wrapping (a recording longer than 71.6 min), which evnoise's DAT decoders do not
    unwrap; any other as the file being corrupt.
    """
    body = path.stat().st_size - offset
    if body < 8:
        return
    table = np.memmap(path, dtype="<u4", mode="r", offset=offset, shape=(body // 8, 2))
    previous = None
    for start in range(0, table.shape[0], DAT_CHECK_RECORDS):
        block = np.asarray(table[start:start + DAT_CHECK_RECORDS])
        t = block[:, 0].astype(np.int64)
        reached = np.flatnonzero(t >= t_end_us) if t_end_us is not None else ()
        end = int(reached[0]) + 1 if len(reached) else t.size
        t = t[:end] if previous is None else np.concatenate(([previous], t[:end]))
        back = np.flatnonzero(t[1:] < t[:-1])
        if back.size:
            k = int(back[0])
            before, after = int(t[k]), int(t[k + 1])
            index = start + k + (1 if previous is None else 0) + 1  # counting records from 1
            if before - after > 1 << 31:
                raise InputError(f"{path}: the 32-bit clock of the DAT file wraps at event {index} ({after} us after "
                                 f"{before} us: a recording longer than 71.6 min); evnoise does not unwrap DAT clocks")
            raise InputError(f"{path}: timestamps go back in time at event {index} ({after} us after {before} us); "
                             "the file is corrupt or not time-sorted")
        yield block[:end]
        if len(reached):
            return
        previous = int(t[-1])


def dat_records(path, offset: int, t_end_us: int | None = None):
    """Event arrays of a DAT file's records (Event2d or CD: address bits 0-13 x, 14-27 y, 28-31 polarity, nonzero
    ON), block by block as :func:`dat_blocks` reads and checks them."""
    for block in dat_blocks(path, offset, t_end_us):
        address = block[:, 1]
        yield to_events(block[:, 0], address & 0x3FFF, (address >> 14) & 0x3FFF, address >> 28)


def check_dat_times(path, offset: int, t_end_us: int | None = None) -> None:
    """An :class:`InputError` naming the first DAT record, up to the one that reaches ``t_end_us``, whose time goes
    back (:func:`dat_blocks`' check), for a decoder that does not check it (faery clamps such a time)."""
    for _ in dat_blocks(path, offset, t_end_us):
        pass
