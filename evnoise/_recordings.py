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


def recording_info(path, shape=None, *, csv_columns=None, shape_argument: str = "sensor='WxH'"):
    """``(shape, n_events, t_first, t_last, t_end_attr)`` of an event file (events.h5 or any camera file).

    An events.h5 file is read little (its attributes and two timestamps); a camera file is
    scanned once (streaming). ``shape`` (H, W) is the sensor size for files whose header has
    none; a file that does give one must agree. ``shape_argument`` is how the caller's own parameter
    for it is written in the message when it is missing (the library speaks its callers' names).
    """
    from .readers import open_events, scan_events

    sensor = None if shape is None else (int(shape[1]), int(shape[0]))
    src = open_events(path, csv_columns=csv_columns)
    if shape is not None and src.shape is not None and tuple(src.shape) != tuple(check_shape(shape)):
        raise InputError(f"shape {tuple(shape)} does not match the file's sensor {src.shape}")
    if src.shape is None:
        if sensor is None:
            raise InputError(f"{path}: the sensor size is unknown (no width/height in the file); "
                             f"give it with {shape_argument}")
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
    """Where a recording starts when no start is given: for events.h5 the zero of the file's clock
    (``/t_offset``: 0 in evnoise's simulations, a whole second of the camera's clock in what
    ``separate`` writes from a camera file), the first event for camera files (whose clocks start
    anywhere). Starting an events.h5 at 0 whatever its offset made ``separate`` and ``reconstruct``
    step through 1.6e15 µs of empty time before a camera's first event."""
    from .readers import detect_format

    if detect_format(path) == "h5":
        from ._h5 import h5_metadata

        with open_h5(path) as f:
            return int(h5_metadata(f, event_datasets(f, path))["t_offset"])
    if t_first is None:
        return 0
    return int(t_first)


def _aligned_jump(a: int, t_next: int, t_start_us: int, block_us: int) -> int:
    """Start of the block (on the grid ``t_start_us + k block_us``) that holds ``t_next``, if later than ``a``."""
    if t_next >= a + block_us:
        return t_start_us + (t_next - t_start_us) // block_us * block_us
    return a


def recording_blocks(path, t_start_us: int, t_end_us: int, block_us: int, shape=None, *, csv_columns=None,
                     skip_empty: bool = False):
    """``(events, t_block_end)`` for consecutive blocks ``[a, b)`` of an event file (every block,
    empty ones too, unless ``skip_empty``: then stretches without events are passed over, so the
    time taken depends on the events, not on how far apart they lie; the blocks that are yielded
    are the same); events.h5 seeks through ``/ms_to_idx``, other formats are decoded in order."""
    from .readers import open_events

    if int(block_us) < 1:
        raise InputError(f"block_us must be >= 1, got {block_us}")
    sensor = None if shape is None else (int(shape[1]), int(shape[0]))
    src = open_events(path, sensor=sensor, csv_columns=csv_columns)
    if src.format == "h5" and not src.t_offset_us:
        with open_h5(path) as f:
            ds = event_datasets(f, path)
            n_total = int(ds["t"].shape[0])
            a = t_start_us
            lo = first_index(f, ds["t"], a)
            while a < t_end_us:
                if skip_empty:
                    if lo >= n_total:
                        return
                    try:
                        a = _aligned_jump(a, int(ds["t"][lo]), t_start_us, block_us)
                    except OSError as exc:
                        raise InputError(f"cannot read events from {path}: {exc}") from None
                    if a >= t_end_us:
                        return
                b = min(a + block_us, t_end_us)
                hi = first_index(f, ds["t"], b)
                try:
                    events = make_events(ds["t"][lo:hi], ds["x"][lo:hi], ds["y"][lo:hi], ds["p"][lo:hi])
                except OSError as exc:
                    raise InputError(f"cannot read events from {path}: {exc}") from None
                yield events, b
                lo, a = hi, b
        return
    yield from _reblock(src.chunks(t_start_us, t_end_us), t_start_us, t_end_us, block_us, skip_empty)


def _reblock(chunks, t_start_us: int, t_end_us: int, block_us: int, skip_empty: bool = False):
    """Cut a stream of time-sorted chunks into consecutive blocks ``[a, a + block_us)`` (see
    :func:`recording_blocks` for ``skip_empty``)."""
    pending = []
    a = t_start_us
    for chunk in chunks:
        if not chunk.size:
            continue
        pending.append(chunk)
        last = int(chunk["t"][-1])
        while a < t_end_us and last >= min(a + block_us, t_end_us):
            buf = np.concatenate(pending) if len(pending) > 1 else pending[0]
            if skip_empty and buf.size:
                a = _aligned_jump(a, int(buf["t"][0]), t_start_us, block_us)
                if a >= t_end_us or last < min(a + block_us, t_end_us):
                    pending = [buf]
                    break
            b = min(a + block_us, t_end_us)
            cut = int(np.searchsorted(buf["t"], b, side="left"))
            yield buf[:cut], b
            pending = [buf[cut:]]
            a = b
    while a < t_end_us:
        buf = np.concatenate(pending) if pending else empty_events(0)
        if skip_empty:
            if not buf.size:
                return
            a = _aligned_jump(a, int(buf["t"][0]), t_start_us, block_us)
            if a >= t_end_us:
                return
        b = min(a + block_us, t_end_us)
        cut = int(np.searchsorted(buf["t"], b, side="left"))
        yield buf[:cut], b
        pending = [buf[cut:]]
        a = b
