"""Prophesee files: RAW (EVT 2.0, 2.1, 3.0) and DAT, through faery (and expelliarmus for Event2d DAT).

- ``.raw``: the ``% key value`` text header, then EVT words. faery decodes all three EVT versions
  (version and geometry from the header: ``% evt 3.0``, ``% format EVT3;height=720;width=1280``
  or ``% geometry``). EVT words carry no absolute index, so a time window is found by decoding
  from the start; decoding stops at the window's end and memory stays at one packet.
- ``.dat``: the ``%`` header, then 8-byte records. ``CD`` files (as faery and Metavision write
  them) go through faery; ``Event2d`` files (ATIS datasets such as N-CARS), which faery refuses,
  through expelliarmus, in chunks. expelliarmus is never used for EVT3 (it decodes EVT3
  timestamps wrongly).
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
    """Prophesee DAT (CD through faery, Event2d through expelliarmus)."""

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
        if kind == "2d":
            require("expelliarmus", "Prophesee DAT Event2d files")
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

            try:
                with dat.Decoder(self.path, self._fallback, None) as dec:
                    for packet in packets_in_window(dec, t_start_us, t_end_us):
                        yield to_events(packet["t"], packet["x"], packet["y"], packet["payload"])
            except BaseException as exc:  # noqa: BLE001 - see decoder_error
                raise decoder_error(self.path, "Prophesee DAT", exc) from None
            return
        import expelliarmus

        wiz = expelliarmus.Wizard(encoding="dat", fpath=str(self.path), chunk_size=1 << 20)
        try:
            for packet in packets_in_window(wiz.read_chunk(), t_start_us, t_end_us):
                if np.any(packet["x"] < 0) or np.any(packet["y"] < 0):
                    raise InputError(f"{self.path}: negative coordinates in a DAT file (corrupt?)")
                yield to_events(packet["t"], packet["x"], packet["y"], packet["p"])
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, "Prophesee DAT (Event2d)", exc) from None
