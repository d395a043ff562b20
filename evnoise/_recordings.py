"""Event files read as recordings: their span, where they start, and their events in time blocks.

Any event file :mod:`evnoise.readers` opens (events.h5 or a camera file) is read here block by
block, with bounded memory; :mod:`evnoise.separation`, :mod:`evnoise.motion` and
:mod:`evnoise.reconstruct.video` share these helpers.
"""

from __future__ import annotations

import numpy as np

from ._h5 import event_datasets, first_index, open_h5
from .errors import InputError
from .events import check_shape, empty_events, make_events

__all__ = ["recording_info", "recording_start_us", "recording_blocks"]


def recording_info(path, shape=None, *, csv_columns=None):
    """``(shape, n_events, t_first, t_last, t_end_attr)`` of an event file (events.h5 or any camera file).

    An events.h5 file is read little (its attributes and two timestamps); a camera file is
    scanned once (streaming). ``shape`` (H, W) is the sensor size for files whose header has
    none; a file that does give one must agree.
    """
    from .readers import open_events, scan_events

    sensor = None if shape is None else (int(shape[1]), int(shape[0]))
    src = open_events(path, csv_columns=csv_columns)
    if shape is not None and src.shape is not None and tuple(src.shape) != tuple(check_shape(shape)):
        raise InputError(f"shape {tuple(shape)} does not match the file's sensor {src.shape}")
    if src.shape is None:
        if sensor is None:
            raise InputError(f"{path}: the sensor size is unknown (no width/height in the file); "
                             f"give it with --sensor WxH")
        src = open_events(path, sensor=sensor, csv_columns=csv_columns)
    if src.format == "h5":
        n, t_first, t_last = src.n_events, src.t_first_us, src.t_last_us
        t_end = src.meta.get("t_end_us")
        t_end = None if t_end is None else int(t_end) + src.t_offset_us
    else:
        info = scan_events(src)
        n, t_first, t_last, t_end = info["n_events"], info["t_first_us"], info["t_last_us"], None
    return src.shape, n, t_first, t_last, t_end


def recording_start_us(path, t_first) -> int:
    """Where a recording starts when no start is given: 0 for events.h5 (evnoise's clock starts
    at 0), the first event for camera files (whose clocks start anywhere)."""
    from .readers import detect_format

    if detect_format(path) == "h5" or t_first is None:
        return 0
    return int(t_first)


def recording_blocks(path, t_start_us: int, t_end_us: int, block_us: int, shape=None, *, csv_columns=None):
    """``(events, t_block_end)`` for consecutive blocks ``[a, b)`` of an event file (every block,
    empty ones too); events.h5 seeks through ``/ms_to_idx``, other formats are decoded in order."""
    from .readers import open_events

    sensor = None if shape is None else (int(shape[1]), int(shape[0]))
    src = open_events(path, sensor=sensor, csv_columns=csv_columns)
    if src.format == "h5" and not src.t_offset_us:
        with open_h5(path) as f:
            ds = event_datasets(f, path)
            a = t_start_us
            lo = first_index(f, ds["t"], a)
            while a < t_end_us:
                b = min(a + block_us, t_end_us)
                hi = first_index(f, ds["t"], b)
                try:
                    events = make_events(ds["t"][lo:hi], ds["x"][lo:hi], ds["y"][lo:hi], ds["p"][lo:hi])
                except OSError as exc:
                    raise InputError(f"cannot read events from {path}: {exc}") from None
                yield events, b
                lo, a = hi, b
        return
    yield from _reblock(src.chunks(t_start_us, t_end_us), t_start_us, t_end_us, block_us)


def _reblock(chunks, t_start_us: int, t_end_us: int, block_us: int):
    """Cut a stream of time-sorted chunks into consecutive blocks ``[a, a + block_us)``."""
    pending = []
    a = t_start_us
    for chunk in chunks:
        pending.append(chunk)
        while a < t_end_us and int(chunk["t"][-1]) >= min(a + block_us, t_end_us):
            b = min(a + block_us, t_end_us)
            buf = np.concatenate(pending) if len(pending) > 1 else pending[0]
            cut = int(np.searchsorted(buf["t"], b, side="left"))
            yield buf[:cut], b
            pending = [buf[cut:]]
            a = b
    while a < t_end_us:
        b = min(a + block_us, t_end_us)
        buf = np.concatenate(pending) if pending else empty_events(0)
        cut = int(np.searchsorted(buf["t"], b, side="left"))
        yield buf[:cut], b
        pending = [buf[cut:]]
        a = b
