"""Reading events.h5 files: the helpers :mod:`evnoise.io`, the readers and the separators share.

Public names in an internal module (they were ``io._open_h5``, ``_event_datasets``, ``_metadata``,
``_first_index``, ``_decode_attr``; ``evnoise.io`` keeps those names as aliases).
"""

from __future__ import annotations

import json

import numpy as np

from ._checks import check_input_file
from .errors import InputError

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


def open_h5(path):
    """Open an events.h5 file read-only (``InputError`` with one clean line if it is missing or not HDF5)."""
    import h5py

    path = check_input_file(path, missing="event file", kind="an event file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"cannot open {path}: not an HDF5 events file ({exc})") from None


def event_datasets(f, path) -> dict:
    """The ``/events/x, y, t, p`` datasets of an open file, checked (1-D, equal length)."""
    group = f.get("events")
    import h5py

    if not isinstance(group, h5py.Group) or not all(isinstance(group.get(k), h5py.Dataset) for k in "xytp"):
        raise InputError(f"{path} is not an events.h5 file (no /events/x, y, t, p datasets)")
    ds = {k: group[k] for k in "xytp"}
    sizes = {ds[k].shape for k in "xytp"}
    if len(sizes) != 1 or len(next(iter(sizes))) != 1:
        raise InputError(f"{path}: /events/x, y, t, p must be 1-D and of equal length, got {sorted(sizes)}")
    return ds


def h5_metadata(f, ds) -> dict:
    """Root attributes decoded (JSON ones to dicts) plus ``shape``, ``n_events`` and ``t_offset``."""
    meta = {k: decode_attr(v) for k, v in f.attrs.items()}
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


def sensor_shape(f, path) -> tuple:
    """``(height, width)`` from the root attributes of an open file (``InputError`` if absent or not positive)."""
    try:
        width, height = int(f.attrs["width"]), int(f.attrs["height"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{path} has no width/height attributes") from None
    if width <= 0 or height <= 0:
        raise InputError(f"{path} has an invalid sensor size {width}x{height}")
    return height, width


def first_index(f, t_ds, t_us: int) -> int:
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
