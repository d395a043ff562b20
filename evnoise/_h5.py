"""Reading events.h5 files: the helpers :mod:`evnoise.io`, the readers and the separators share.

Public names in an internal module (they were ``io._open_h5``, ``_event_datasets``, ``_metadata``,
``_first_index``, ``_decode_attr``; ``evnoise.io`` keeps those names as aliases).
"""

from __future__ import annotations

import json
import logging

import numpy as np

from ._checks import check_input_file
from .errors import InputError

log = logging.getLogger("evnoise")

#: Events read at a time when scanning a file.
READ_BLOCK = 1 << 22

__all__ = ["READ_BLOCK", "decode_attr", "open_h5", "event_datasets", "h5_metadata", "sensor_shape", "first_index"]


def decode_attr(value):
    """An HDF5 attribute value as Python (bytes to str, NumPy scalars to numbers)."""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.generic):
        return value.item()
    return value


#: Most objects (groups, datasets, links) looked at in one file before it is refused: an events.h5 file
#: has about ten; the limit only bounds the check below on a file built to be slow to walk.
MAX_H5_OBJECTS = 10_000
#: Largest ``|t_offset|`` (µs) accepted: about 146,000 years, so that ``t + t_offset`` cannot wrap.
MAX_T_OFFSET = 1 << 62


def open_h5(path):
    """Open an events.h5 file read-only (``InputError`` with one clean line if it is missing or not HDF5).

    The one place where evnoise opens an HDF5 file to read its data: a file that keeps any dataset's
    data outside itself is refused here, before anything is read (see :func:`check_stored_inside`).
    """
    import h5py

    path = check_input_file(path, missing="event file", kind="an event file")
    check_global_heaps(path)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"cannot open {path}: not an HDF5 events file ({exc})") from None
    try:
        check_stored_inside(f, path)
    except BaseException:
        f.close()
        raise
    return f


#: Largest number of objects in one HDF5 global heap collection (object indices are 16-bit).
_MAX_HEAP_OBJECTS = 1 << 16
#: Global heap collections already checked: ``(path, inode, size, mtime) -> None`` (a file is walked once).
_HEAPS_CHECKED: dict = {}


def _global_heap_damage(mm, at: int, size_len: int) -> str | None:
    """Why the global heap collection whose ``GCOL`` signature is at ``at`` would stop HDF5, or None.

    The layout (HDF5 file format, "Global Heap"): ``GCOL``, version 1, 3 reserved zero bytes, the
    collection's size (``size_len`` bytes), then objects of a 16-bit index, 16-bit reference count,
    4 reserved bytes, the object's size and its data padded to 8 bytes; index 0 is the free space.
    HDF5 (2.0) walks these objects when it loads the collection and loops forever on an object that
    does not advance the walk (index 0 and size 0, left by a damaged size before it).
    """
    head = 8 + size_len
    if at + head > len(mm) or mm[at + 4] != 1 or mm[at + 5:at + 8] != b"\0\0\0":
        return None  # not a collection HDF5 would accept (it refuses those itself): a chance "GCOL"
    total = int.from_bytes(mm[at + 8:at + head], "little")
    if total < head:
        return f"declares a size of {total:,} bytes, less than its own header"
    if at + total > len(mm):
        return f"declares {total:,} bytes, past the end of the file"
    end = at + total
    obj_head = 8 + size_len
    p = at + (head + 7) // 8 * 8
    count = 0
    while p < end:
        if p + obj_head > end:
            break  # too short for an object header: free space
        idx = int.from_bytes(mm[p:p + 2], "little")
        size = int.from_bytes(mm[p + 8:p + obj_head], "little")
        need = obj_head + (size + 7) // 8 * 8 if idx > 0 else size
        if need <= 0:
            return f"holds an empty object record at byte {p}, which HDF5 would step on forever"
        if p + need > end:
            return f"holds an object of {size:,} bytes at byte {p} that does not fit in it"
        count += 1
        if count > _MAX_HEAP_OBJECTS:
            return f"holds more than {_MAX_HEAP_OBJECTS:,} objects"
        p += need
    return None


def check_global_heaps(path) -> None:
    """Refuse an HDF5 file with a damaged global heap collection (where variable-length strings, such
    as evnoise's attributes, are stored) before HDF5 reads it: HDF5 hangs for good on some damage
    (an object size that does not advance its walk). ``InputError`` naming the byte offset."""
    import mmap
    import os

    try:
        st = os.stat(path)
        key = (os.fspath(path), st.st_ino, st.st_size, st.st_mtime_ns)
        if key in _HEAPS_CHECKED or st.st_size < 8:
            return
        with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            # size of lengths: superblock v0/v1 byte 14, v2/v3 byte 10 (a superblock at 0; 8 otherwise, the default)
            size_len = 8
            if mm[:8] == b"\x89HDF\r\n\x1a\n" and len(mm) > 14:
                size_len = mm[14] if mm[8] in (0, 1) else mm[10]
                if size_len not in (2, 4, 8, 16):
                    size_len = 8
            why = None
            at = mm.find(b"GCOL")
            while at >= 0 and why is None:
                why = _global_heap_damage(mm, at, size_len)
                at = mm.find(b"GCOL", at + 4) if why is None else at
    except (OSError, ValueError):
        return  # unreadable here: h5py says why when it opens the file
    if why:
        raise InputError(f"{path}: the HDF5 global heap at byte {at} {why} (a damaged file)")
    _HEAPS_CHECKED[key] = None


def _outside(obj, path) -> str | None:
    """Why dataset ``obj`` reads data from outside the file ``path``, or None."""
    try:
        if obj.is_virtual:
            files = sorted({m.file_name for m in obj.virtual_sources()})
            return f"is a virtual dataset whose data live in {', '.join(files[:2]) or 'other files'}"
        external = obj.external
    except (OSError, RuntimeError, ValueError) as exc:
        return f"has a storage layout that cannot be read ({exc})"
    if external:
        return f"keeps its data in the external file {decode_attr(external[0][0])!r}"
    return None


def check_stored_inside(f, path) -> None:
    """Refuse a file that would make a read touch anything but the file itself: a dataset with
    external storage (raw bytes of any local file, ``create_dataset(..., external=...)``), a virtual
    dataset (data mapped from other files), or an external link (an object of another HDF5 file).
    ``InputError`` naming the object; at most :data:`MAX_H5_OBJECTS` objects are looked at."""
    import h5py

    seen = set()
    stack = [f]
    count = 0
    try:
        while stack:
            group = stack.pop()
            for name in group:
                count += 1
                if count > MAX_H5_OBJECTS:
                    raise InputError(f"{path} holds more than {MAX_H5_OBJECTS:,} HDF5 objects; an events.h5 file "
                                     "has a handful (refused rather than walked)")
                link = group.get(name, getlink=True)
                where = f"{group.name.rstrip('/')}/{name}"
                if isinstance(link, h5py.ExternalLink):
                    raise InputError(f"{path}: {where} links to another file ({link.filename!r}); evnoise reads "
                                     "only data stored inside the file it is given")
                if isinstance(link, h5py.SoftLink):
                    continue  # points inside the file: its target is checked where it is
                obj = group.get(name)
                if isinstance(obj, h5py.Dataset):
                    why = _outside(obj, path)
                    if why:
                        raise InputError(f"{path}: dataset {where} {why}; evnoise reads only data stored inside "
                                         "the file it is given")
                elif isinstance(obj, h5py.Group):
                    if obj.id not in seen:  # ObjectIDs compare (and hash) by the object they name
                        seen.add(obj.id)
                        stack.append(obj)
    except InputError:
        raise
    except (OSError, RuntimeError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"cannot read {path}: its HDF5 structure is damaged ({exc})") from None


def _check_present(ds, path, what: str, file_size: int) -> None:
    """Refuse a dataset whose declared length is not backed by data in the file: a chunked one with
    chunks never written (they would read as fill-value zeros: a header declaring 1e11 events made the
    readers count through 1e11 invented events), or a contiguous one that is unallocated or ends past
    the end of the file (truncated)."""
    import h5py

    n = int(ds.shape[0])
    if n == 0:
        return
    try:
        layout = ds.id.get_create_plist().get_layout()
        if layout == h5py.h5d.CHUNKED:
            chunk = int(ds.chunks[0])
            needed = -(-n // chunk)
            have = int(ds.id.get_num_chunks())
            if have < needed:
                raise InputError(f"{path}: {what} declares {n:,} events but stores only {have:,} of the "
                                 f"{needed:,} blocks that hold them (unwritten or damaged data)")
        elif layout == h5py.h5d.CONTIGUOUS:
            offset = ds.id.get_offset()
            end = None if offset is None else int(offset) + n * ds.dtype.itemsize
            if end is None or end > file_size:
                raise InputError(f"{path}: {what} declares {n:,} events but the file "
                                 f"{'stores none of them' if end is None else 'ends before them (truncated)'}")
    except InputError:
        raise
    except (OSError, RuntimeError, ValueError, TypeError) as exc:
        raise InputError(f"cannot read {path}: {what} is damaged ({exc})") from None


def event_datasets(f, path) -> dict:
    """The ``/events/x, y, t, p`` datasets of an open file, checked (1-D, equal length, integers, and
    every declared event actually stored in the file)."""
    import os

    import h5py

    try:
        group = f.get("events")
        found = isinstance(group, h5py.Group) and all(isinstance(group.get(k), h5py.Dataset) for k in "xytp")
    except (OSError, RuntimeError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"cannot read {path}: its HDF5 structure is damaged ({exc})") from None
    if not found:
        raise InputError(f"{path} is not an events.h5 file (no /events/x, y, t, p datasets)")
    ds = {k: group[k] for k in "xytp"}
    sizes = {ds[k].shape for k in "xytp"}  # None: a dataset without a dataspace (h5py.Empty)
    if len(sizes) != 1 or None in sizes or len(next(iter(sizes))) != 1:
        shapes = sorted("no dataspace" if s is None else str(s) for s in sizes)
        raise InputError(f"{path}: /events/x, y, t, p must be 1-D and of equal length, got {', '.join(shapes)}")
    for k in "xytp":
        kind = ds[k].dtype.kind
        if kind not in "iub":
            raise InputError(f"{path}: /events/{k} must hold integers, got {ds[k].dtype}")
    try:
        file_size = os.path.getsize(f.filename)
    except OSError:
        file_size = 1 << 62
    for k in "xytp":
        _check_present(ds[k], path, f"/events/{k}", file_size)
    return ds


def _int_attr(value, what: str, path):
    """``value`` as an int, or InputError naming ``what`` (a string, a fraction, an array)."""
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.reshape(()).item()
    if isinstance(value, (bool, np.bool_)):
        value = None
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)) and np.isfinite(value) and float(value).is_integer():
        return int(value)
    raise InputError(f"{path}: {what} must be an integer, got {value!r}"[:300])


def h5_metadata(f, ds) -> dict:
    """Root attributes decoded (JSON ones to dicts) plus ``shape``, ``n_events`` and ``t_offset``.

    ``InputError`` (one line) for metadata that evnoise relies on and that is damaged: ``json_attrs``
    that is not a JSON list of names, a width or height that is not a positive integer (or only one
    of them), a ``/t_offset`` that is not one integer within :data:`MAX_T_OFFSET`.
    """
    path = f.filename
    try:
        # a name that is not UTF-8 comes back as bytes: as text (with replacement characters)
        meta = {decode_attr(k): decode_attr(v) for k, v in f.attrs.items()}
    except (OSError, RuntimeError, ValueError, TypeError, KeyError) as exc:
        raise InputError(f"cannot read the attributes of {path} ({exc})") from None
    json_keys = meta.pop("json_attrs", None)
    if json_keys is not None:
        try:
            keys = json.loads(json_keys)
        except (TypeError, ValueError, RecursionError):  # RecursionError: lists nested past the recursion limit
            keys = None
        if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
            raise InputError(f"{path}: its json_attrs attribute is not a JSON list of attribute names")
        for key in keys:
            if key in meta:
                try:
                    meta[key] = json.loads(meta[key])
                except (TypeError, ValueError, RecursionError):  # kept as the text it is
                    pass
    if "height" in meta and "width" in meta:
        height = _int_attr(meta["height"], "the height attribute", path)
        width = _int_attr(meta["width"], "the width attribute", path)
        if height <= 0 or width <= 0 or height > 65536 or width > 65536:
            raise InputError(f"{path} has an invalid sensor size {width}x{height} (1 .. 65536 each)")
        meta["shape"] = (height, width)
    elif "height" in meta or "width" in meta:
        raise InputError(f"{path} has only one of the width and height attributes")
    else:
        meta["shape"] = None
    for key in ("t_end_us", "t_start_us"):  # evnoise's clock: read as integer µs by info and the recordings
        if key in meta:
            meta[key] = _int_attr(meta[key], f"the {key} attribute", path)
            if abs(meta[key]) > MAX_T_OFFSET:
                raise InputError(f"{path}: the {key} attribute {meta[key]} is beyond +-2^62 µs")
    meta["n_events"] = int(ds["t"].shape[0])
    offset = 0
    if "t_offset" in f:
        try:
            node = f["t_offset"]
            value = node[()] if hasattr(node, "shape") and node.shape is not None else None
        except (OSError, RuntimeError, ValueError, TypeError, KeyError) as exc:
            raise InputError(f"cannot read /t_offset of {path} ({exc})") from None
        offset = _int_attr(value, "/t_offset", path)
        if abs(offset) > MAX_T_OFFSET:
            raise InputError(f"{path}: /t_offset {offset} is beyond +-2^62 µs")
    meta["t_offset"] = offset
    return meta


def sensor_shape(f, path) -> tuple:
    """``(height, width)`` from the root attributes of an open file (``InputError`` if absent or not positive)."""
    try:
        width, height = int(f.attrs["width"]), int(f.attrs["height"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{path} has no width/height attributes") from None
    if width <= 0 or height <= 0:
        raise InputError(f"{path} has an invalid sensor size {width}x{height}")
    return height, width


#: Files whose damaged /ms_to_idx this process has warned about (the warning says what happens for every read).
_WARNED_INDEX: set = set()


def _indexed_range(f, n: int, k: int):
    """``(range, damaged)``: millisecond ``k``'s ``[lo, hi)`` from the file's ``/ms_to_idx``; None where it has none
    (no index, or ``k`` beyond it: not damage) or where the index is damaged (not a 1-D integer dataset, unreadable,
    or entries outside ``0 <= lo <= hi <= n``)."""
    import h5py

    try:
        ms = f.get("ms_to_idx")
        if ms is None:
            return None, False
        if not isinstance(ms, h5py.Dataset) or ms.shape is None or len(ms.shape) != 1 or ms.dtype.kind not in "iu":
            return None, True
        if not 0 <= k < ms.shape[0]:
            return None, False
        lo = int(ms[k])
        hi = int(ms[k + 1]) if k + 1 < ms.shape[0] else n
    except (OSError, RuntimeError, ValueError, TypeError, KeyError):
        return None, True
    return ((lo, hi), False) if 0 <= lo <= hi <= n else (None, True)


def _search(t_ds, t_us: int, lo: int, hi: int) -> int:
    """Index of the first event with ``t >= t_us`` within ``[lo, hi)`` (``hi`` if none): a binary search in blocks,
    reading at most :data:`READ_BLOCK` values at a time."""
    while hi - lo > READ_BLOCK:
        mid = (lo + hi) // 2
        if int(t_ds[mid]) < t_us:
            lo = mid + 1
        else:
            hi = mid
    return lo + int(np.searchsorted(t_ds[lo:hi], t_us, side="left"))


def first_index(f, t_ds, t_us: int) -> int:
    """Index of the first event with ``t >= t_us``, reading only one millisecond of events where the file's
    ``/ms_to_idx`` indexes it.

    The index is a shortcut, not trusted: the answer is checked against the events beside it (the one before is
    earlier than ``t_us``, the one found is not), and where the index is damaged (wrong type or shape, entries
    outside the file, or entries that do not bracket ``t_us``) the whole column is searched instead, with a warning.
    """
    n = int(t_ds.shape[0])
    k = t_us // 1000
    got, damaged = _indexed_range(f, n, k)
    if got is not None:
        i = _search(t_ds, t_us, *got)
        if (i == 0 or int(t_ds[i - 1]) < t_us) and (i == n or int(t_ds[i]) >= t_us):
            return i
        damaged = True
    if damaged and f.filename not in _WARNED_INDEX:  # once per file: a recording read in blocks asks per block
        _WARNED_INDEX.add(f.filename)
        log.warning("%s: /ms_to_idx does not index millisecond %d (damaged); searching the event times instead",
                    f.filename, k)
    return _search(t_ds, t_us, 0, n)
