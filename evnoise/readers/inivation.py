"""iniVation / jAER files: AEDAT 4 (through faery) and AEDAT 2.0 (tonic's container reader).

AEDAT 4 (``.aedat4``): the first event track; the sensor size comes from its description. A file
written by evnoise also carries evnoise's parameters, seed and version in the description
(node ``evnoise``), reported in ``meta``. The data table at the file's end (``dataTablePosition``
in the IO header, an LZ4 or Zstandard frame) must end exactly at the end of the file: a cut or
bytes appended are errors (:func:`check_aedat4_end`).

AEDAT 2.0 (jAER ``.aedat``): ``#`` header lines (the ``AEChip`` names the camera), then
big-endian pairs of 32-bit address and 32-bit timestamp (µs). The records have a fixed size, so
the body is memory-mapped and a time window is found by binary search. The address -> x, y,
polarity map is per camera (:data:`AEDAT2_CHIPS`); it is the only bit-level decoding evnoise
does itself.
"""

from __future__ import annotations

import json
import re

import numpy as np

from .._aedat import EVNOISE_NODE
from ..errors import InputError
from ._base import (
    EventSource,
    check_whole_records,
    decoder_error,
    decoder_words,
    from_faery,
    header_lines,
    log,
    packets_in_window,
    require,
    to_events,
    tonic_io,
    warn_no_data,
)


# --------------------------------------------------------------------------------------
# AEDAT 4
# --------------------------------------------------------------------------------------
def _description_attrs(nodes) -> dict:
    """evnoise's attributes from an AEDAT 4 description (``{}`` if none)."""
    for node in nodes:
        if node.name == EVNOISE_NODE:
            out = {}
            for key, attr in node.attributes.items():
                value = attr.value
                if key.endswith("_json") and isinstance(value, str):
                    try:
                        value = json.loads(value)
                    except (ValueError, RecursionError):  # kept as the text it is (RecursionError: nested too deep)
                        pass
                    key = key[:-5]
                out[key] = value
            return out
        found = _description_attrs(node.nodes)
        if found:
            return found
    return {}


def _u32(fh, pos: int) -> int | None:
    fh.seek(pos)
    raw = fh.read(4)
    return int.from_bytes(raw, "little") if len(raw) == 4 else None


def _aedat4_io_header(path) -> tuple[int, int]:
    """``(compression, dataTablePosition)`` from an AEDAT 4 file's IOHeader (a FlatBuffers table after the
    14-byte magic and a 32-bit size: field 0 compression (int32, default 0 = none), field 1
    dataTablePosition (int64, default -1 = no table))."""
    import struct

    with open(path, "rb") as fh:
        fh.seek(14)
        raw = fh.read(4)
        size = int.from_bytes(raw, "little") if len(raw) == 4 else 0
        buf = fh.read(min(size, 1 << 20))
    try:
        if len(buf) < size:
            raise struct.error("short")
        root = struct.unpack_from("<I", buf, 0)[0]
        vtable = root - struct.unpack_from("<i", buf, root)[0]
        vsize = struct.unpack_from("<H", buf, vtable)[0]
        fields = [struct.unpack_from("<H", buf, vtable + 4 + 2 * i)[0] for i in range(max(0, (vsize - 4) // 2))]
        compression = struct.unpack_from("<i", buf, root + fields[0])[0] if fields and fields[0] else 0
        position = struct.unpack_from("<q", buf, root + fields[1])[0] if len(fields) > 1 and fields[1] else -1
        if len(fields) > 2 and fields[2]:  # field 2, infoNode: the description (XML text)
            at = root + fields[2]
            at += struct.unpack_from("<I", buf, at)[0]
            length = struct.unpack_from("<I", buf, at)[0]
            text = buf[at + 4:at + 4 + length]
            if len(text) < length:
                raise struct.error("short")
            # faery 0.7.1 aborts the whole process (a panic in a destructor) on a description that is not UTF-8
            text.decode("utf-8")
    except (struct.error, IndexError):
        raise InputError(f"cannot read {path} as AEDAT 4: its IO header is cut or damaged (truncated file?)") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"cannot read {path} as AEDAT 4: its description is not UTF-8 text (byte {exc.start}: a "
                         f"damaged file)") from None
    return compression, position


def _lz4_frame_end(fh, pos: int, size: int) -> int | None:
    """End of the LZ4 frame at ``pos`` (after its end mark and checksum), from its block headers; ``None``
    when the file ends inside it (the LZ4 frame format: magic, FLG, BD, [content size], [dict id], HC,
    blocks of a 32-bit size (high bit: stored), [block checksum], end mark 0, [content checksum])."""
    fh.seek(pos)
    head = fh.read(6)
    if len(head) < 6:
        return None
    flg = head[4]
    i = pos + 6 + (8 if flg & 0x08 else 0) + (4 if flg & 0x01 else 0) + 1
    while True:
        block = _u32(fh, i)
        if block is None:
            return None
        i += 4
        if block == 0:
            break
        i += (block & 0x7FFFFFFF) + (4 if flg & 0x10 else 0)
        if i > size:
            return None
    i += 4 if flg & 0x04 else 0
    return i if i <= size else None


def _zstd_frame_end(fh, pos: int, size: int) -> int | None:
    """End of the Zstandard frame at ``pos``, from its header and block headers (RFC 8878); ``None`` when
    the file ends inside it."""
    fh.seek(pos + 4)
    raw = fh.read(1)
    if not raw:
        return None
    fhd = raw[0]
    single = (fhd >> 5) & 1
    fcs = {0: 1 if single else 0, 1: 2, 2: 4, 3: 8}[fhd >> 6]
    i = pos + 5 + (0 if single else 1) + (0, 1, 2, 4)[fhd & 3] + fcs
    while True:
        fh.seek(i)
        raw = fh.read(3)
        if len(raw) < 3:
            return None
        h = int.from_bytes(raw, "little")
        i += 3 + (1 if (h >> 1) & 3 == 1 else h >> 3)
        if i > size:
            return None
        if h & 1:
            break
    i += 4 if (fhd >> 2) & 1 else 0
    return i if i <= size else None


_LZ4_MAGIC = b"\x04\x22\x4d\x18"
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"


def check_aedat4_packets(path, end: int) -> None:
    """Walk the packets of an AEDAT 4 file (after the IO header: a 32-bit stream id, a 32-bit size, then
    that many bytes) up to byte ``end`` (the data table, or the end of the file): a packet whose size
    runs past ``end`` is an :class:`InputError` (faery allocates the size it reads before it reads a
    byte: a damaged size of 2 GiB aborted the process when that memory was not there)."""
    with open(path, "rb") as fh:
        fh.seek(14)
        raw = fh.read(4)
        i = 18 + int.from_bytes(raw, "little")
        while i + 8 <= end:
            fh.seek(i)
            head = fh.read(8)
            if len(head) < 8:
                break
            stream = int.from_bytes(head[:4], "little", signed=True)
            size = int.from_bytes(head[4:], "little")
            if i + 8 + size > end:
                raise InputError(f"cannot read {path} as AEDAT 4: the packet at byte {i} (stream {stream}) declares "
                                 f"{size:,} bytes, past {'its data table' if end < path.stat().st_size else 'the end'}"
                                 f" at byte {end} (a damaged or truncated file)")
            i += 8 + size


def check_aedat4_end(path) -> None:
    """A cut or an appended tail of an AEDAT 4 file: its data table runs from ``dataTablePosition`` to the
    end of the file, so a table that ends before the file (stray bytes) or after it (a cut) is an error.
    A file without a table (a recording that was not closed) gets a warning; an uncompressed table,
    which does not say where it ends, is not checked."""
    compression, position = _aedat4_io_header(path)
    size = path.stat().st_size
    check_aedat4_packets(path, position if 0 <= position <= size else size)
    if position < 0:
        log.warning("%s: the AEDAT 4 file has no data table (a recording that was not closed properly, or cut); "
                    "its packets are read in order", path)
        return
    if position >= size:
        raise InputError(f"cannot read {path} as AEDAT 4: its data table starts at byte {position} but the file has "
                         f"{size} bytes; it was cut (truncated file)")
    with open(path, "rb") as fh:
        fh.seek(position)
        magic = fh.read(4)
        if compression in (1, 2) and magic == _LZ4_MAGIC:
            end = _lz4_frame_end(fh, position, size)
        elif compression in (3, 4) and magic == _ZSTD_MAGIC:
            end = _zstd_frame_end(fh, position, size)
        elif compression in (0,):
            return
        else:
            raise InputError(f"cannot read {path} as AEDAT 4: no compressed data table at byte {position} "
                             f"(a damaged file)")
    if end is None:
        raise InputError(f"cannot read {path} as AEDAT 4: the file ends inside its data table; it was cut "
                         f"(truncated file)")
    if end < size:
        raise InputError(f"cannot read {path} as AEDAT 4: {size - end} stray bytes after its data table (bytes "
                         f"appended to the file, or a damaged one)")


class Aedat4Source(EventSource):
    """AEDAT 4 (the first event track)."""

    format = "aedat4"

    def __init__(self, path, *, sensor=None):
        super().__init__(path, sensor=sensor)
        require("faery", "AEDAT 4 files")
        from faery.extension import aedat

        check_aedat4_end(self.path)

        try:
            with aedat.Decoder(self.path) as dec:
                tracks = dec.tracks()
                description = dec.description()
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, "AEDAT 4", exc) from None
        events = [t for t in tracks if t.data_type == "events"]
        if not events:
            raise InputError(f"{self.path}: the AEDAT 4 file has no event track "
                             f"(tracks: {', '.join(t.data_type for t in tracks) or 'none'})")
        self._track = events[0].id
        self.meta = {"tracks": [f"{t.id}: {t.data_type}" for t in tracks]}
        self.meta.update(_description_attrs(description))
        dims = events[0].dimensions
        self._set_shape((dims[1], dims[0]) if dims else None)

    def _chunks(self, t_start_us, t_end_us):
        from faery.extension import aedat

        done = {"packets": 0, "t": None}

        def counted(dec):
            for track, packet in dec:
                done["packets"] += 1
                if track.id == self._track:
                    if len(packet):
                        done["t"] = int(packet["t"][-1])
                    yield packet

        try:
            with aedat.Decoder(self.path) as dec:
                for packet in packets_in_window(counted(dec), t_start_us, t_end_us):
                    yield from_faery(packet)
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise _packet_error(self.path, exc, done["packets"], done["t"]) from None


def _packet_error(path, exc: BaseException, packets_read: int, last_t_us) -> InputError:
    """One-line error for a packet the decoder rejects: which packet (counted from 1), the time reached,
    what the decoder's message means, and the message itself (interrupts re-raised, as :func:`decoder_error`)."""
    plain = decoder_error(path, "AEDAT 4", exc)  # re-raises interrupts and evnoise's own errors
    text = " ".join(str(exc).split()) or type(exc).__name__
    meaning = decoder_words(text)
    if meaning is None:
        return plain
    if last_t_us is None:
        reached = "no event of the track before it"
    else:
        reached = (f"events read up to t = {last_t_us} us on the file's clock (a time window that ends by then reads "
                   "the events ahead of it)")
    return InputError(f"cannot read {path} as AEDAT 4: packet {packets_read + 1} is unreadable: {meaning} "
                      f"[decoder: {text}]; {reached}")


# --------------------------------------------------------------------------------------
# AEDAT 2.0 (jAER)
# --------------------------------------------------------------------------------------
def _dvs128(a):
    """DVS128 (and eDVS128): x = 127 - bits 1-7, y = bits 8-14, ON when bit 0 is 0."""
    keep = np.ones(a.shape, dtype=bool)
    return keep, 127 - ((a >> 1) & 0x7F), (a >> 8) & 0x7F, (a & 1) == 0


def _davis(width):
    """DAVIS (jAER's DavisBaseCamera): DVS events have bit 31 = 0 and bit 10 = 0 (bit 10 marks
    external-input events); x = width - 1 - bits 12-21, y = bits 22-30, ON when bit 11 is 1."""

    def decode(a):
        keep = ((a >> 31) & 1 == 0) & ((a >> 10) & 1 == 0)
        return keep, (width - 1) - ((a >> 12) & 0x3FF), (a >> 22) & 0x1FF, ((a >> 11) & 1) == 1

    return decode


#: AEDAT 2.0 address tables: regular expression on the header's ``AEChip`` -> (width, height, decode).
#: The DVS128 row is tested on the real recordings in ``shared/data/realdata``; the DAVIS rows
#: follow jAER's DAVIS extractor (no DAVIS AEDAT 2.0 recording with events was available to test).
AEDAT2_CHIPS = [
    (r"DVS128|Tmpdiff128", 128, 128, _dvs128),
    (r"DAVIS240|SBret10", 240, 180, _davis(240)),
    (r"Davis346", 346, 260, _davis(346)),
]

_AEDAT2_RECORD = np.dtype([("address", ">u4"), ("timeStamp", ">u4")])


class Aedat2Source(EventSource):
    """jAER AEDAT 2.0."""

    format = "aedat2"
    seekable = True

    def __init__(self, path, *, sensor=None, chip: str | None = None):
        super().__init__(path, sensor=sensor)
        tio = tonic_io()
        try:
            version, _, created_ms = tio.read_aedat_header_from_file(str(self.path))
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, "jAER AEDAT 2.0", exc) from None
        if not 2 <= version < 3:
            raise InputError(f"{self.path}: AEDAT version {version:g}; this reader handles AEDAT 2.0")
        # tonic's data_start is one byte short when the header runs to the end of the file (a
        # header-only recording); the end of the '#' lines is the start of the data
        lines, start = header_lines(self.path, b"#")
        head = "\n".join(lines)
        chip = chip or _header_value(head, "AEChip")
        self.meta = {"aedat_version": float(version), "chip": chip}
        if chip:
            self.meta["camera"] = chip.rsplit(".", 1)[-1]  # jAER class name: DVS128, Davis346red, ...
        hw = _header_value(head, "HardwareInterface")
        if hw:
            self.meta["hardware_interface"] = hw.split(" with ")[0]
        if created_ms is not None:
            self.meta["created_unix_ms"] = int(created_ms)
        body = self.path.stat().st_size - start
        check_whole_records(self.path, "jAER AEDAT 2.0", body, _AEDAT2_RECORD.itemsize)
        if body == 0:
            opened = any(line.startswith("#Start of Preferences") for line in lines)
            closed = any(line.startswith(("#End of Preferences", "#End Of ASCII Header")) for line in lines)
            if opened and not closed:
                log.warning("%s: the AEDAT 2.0 header stops inside its preferences block and no event follows: the "
                            "file was cut inside its header (truncated file); reading it as 0 events", self.path)
            else:
                warn_no_data(self.path, "jAER AEDAT 2.0")
        self._start = start
        self.n_records = body // _AEDAT2_RECORD.itemsize
        self._decode = None
        header_shape = None
        for pattern, width, height, decode in AEDAT2_CHIPS:
            if chip and re.search(pattern, chip, re.IGNORECASE):
                self._decode, header_shape = decode, (height, width)
                break
        if self._decode is None:
            names = ", ".join(p for p, *_ in AEDAT2_CHIPS)
            raise InputError(f"{self.path}: AEDAT 2.0 camera {chip or '(no AEChip line)'} has no address table in "
                             f"evnoise (known: {names})")
        self._set_shape(header_shape, source="header")

    def _records(self):
        if self.n_records == 0:
            return np.empty(0, dtype=_AEDAT2_RECORD)
        return np.memmap(self.path, dtype=_AEDAT2_RECORD, mode="r", offset=self._start, shape=(self.n_records,))

    def _index(self, rec, t_us) -> int:
        """First record with ``timeStamp >= t_us`` (binary search on the mapped file)."""
        if t_us is None:
            return 0
        if t_us <= 0:
            return 0
        if t_us > 0xFFFFFFFF:
            return rec.shape[0]
        return int(np.searchsorted(rec["timeStamp"], np.uint32(t_us), side="left"))

    def _chunks(self, t_start_us, t_end_us, chunk: int = 1 << 20):
        rec = self._records()
        n = rec.shape[0]
        ts = rec["timeStamp"]
        sorted_ts = n < 2 or bool(np.all(ts[1:] >= ts[:-1])) if n <= (1 << 22) else True
        lo = self._index(rec, t_start_us) if sorted_ts else 0
        hi = (self._index(rec, t_end_us) if t_end_us is not None else n) if sorted_ts else n
        for a in range(lo, hi, chunk):
            part = np.asarray(rec[a:min(a + chunk, hi)])
            addr = part["address"].astype(np.uint32)
            keep, x, y, on = self._decode(addr)
            t = part["timeStamp"].astype(np.int64)
            if not keep.all():
                t, x, y, on = t[keep], x[keep], y[keep], on[keep]
            yield to_events(t, x, y, on)


def _header_value(head: str, key: str) -> str | None:
    m = re.search(rf"^#\s*{key}:\s*(.+?)\s*$", head, re.MULTILINE)
    return m.group(1) if m else None


def is_aedat2(head: bytes) -> bool:
    return head.startswith(b"#!AER-DAT2")


def is_aedat4(head: bytes) -> bool:
    return head.startswith(b"#!AER-DAT4")
