"""events.h5 in the DSEC layout: evnoise's own files and those other tools wrote.

``/events/{t,x,y,p}`` (``/ms_to_idx`` when present locates a time window without reading the
events before it). The file's clock is ``t + t_offset`` (``/t_offset``, 0 in evnoise's files).
Width and height come from the root attributes; DSEC's own files have none (use ``sensor``).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..events import make_events
from ._base import EventSource

#: Largest ``|t + t_offset|`` (µs) accepted: 2^62 (as ``t_offset`` itself), so that differences and ends
#: computed from event times cannot wrap.
MAX_ABS_T_US = 1 << 62
#: Events read from the file at a time.
CHUNK_EVENTS = 1 << 21


def has_events(path) -> bool:
    """Whether an HDF5 file holds ``/events/{x,y,t,p}`` (the format's probe for ``evnoise info``).

    A file h5py cannot open counts as one (the reader then says why).
    """
    import h5py

    try:
        with h5py.File(path, "r") as f:
            group = f.get("events")
            return isinstance(group, h5py.Group) and all(k in group for k in "xytp")
    except Exception:  # noqa: BLE001 -- any damage h5py meets (OSError, KeyError, ...): the reader says what
        return True


class H5Source(EventSource):
    format = "h5"
    seekable = True

    def __init__(self, path, *, sensor=None):
        from .._h5 import event_datasets, h5_metadata, open_h5

        super().__init__(path, sensor=sensor)
        with open_h5(self.path) as f:
            ds = event_datasets(f, self.path)
            meta = h5_metadata(f, ds)
            n = meta["n_events"]
            self.t_offset_us = int(meta["t_offset"])
            try:
                first = int(ds["t"][0]) if n else None
                last = int(ds["t"][n - 1]) if n else None
            except (OSError, RuntimeError, ValueError, TypeError) as exc:
                raise InputError(f"cannot read events from {self.path}: {exc}") from None
        for t in (first, last):
            if t is not None and not -(1 << 63) <= t < (1 << 63):
                raise InputError(f"{self.path}: /events/t holds {t}, past the int64 range of event times (damaged)")
            if t is not None and not -(1 << 63) <= t + self.t_offset_us < (1 << 63):
                raise InputError(f"{self.path}: /t_offset {self.t_offset_us} puts event times past the int64 range")
            if t is not None and abs(t + self.t_offset_us) > MAX_ABS_T_US:
                raise InputError(f"{self.path}: an event time of {t + self.t_offset_us} us is beyond +-2^62 us "
                                 f"(about 146,000 years); the file is damaged")
        self.t_first_us = None if first is None else first + self.t_offset_us
        self.t_last_us = None if last is None else last + self.t_offset_us
        self.n_events = n
        self.meta = {k: v for k, v in meta.items() if k != "shape"}
        self._set_shape(meta["shape"])

    def _chunks(self, t_start_us, t_end_us):
        from .._h5 import event_datasets, first_index, open_h5

        off = self.t_offset_us
        with open_h5(self.path) as f:
            ds = event_datasets(f, self.path)
            lo = 0 if t_start_us is None else first_index(f, ds["t"], int(t_start_us) - off)
            hi = self.n_events if t_end_us is None else first_index(f, ds["t"], int(t_end_us) - off)
            for a in range(lo, hi, CHUNK_EVENTS):
                b = min(a + CHUNK_EVENTS, hi)
                try:
                    raw_t, x, y, p = ds["t"][a:b], ds["x"][a:b], ds["y"][a:b], ds["p"][a:b]
                except (OSError, RuntimeError, ValueError, TypeError) as exc:
                    raise InputError(f"cannot read events from {self.path}: {exc}") from None
                self._check_range(x, y, a)
                t = raw_t.astype(np.int64, copy=False)
                t = t + off if off else t
                if t.size and (int(t.min()) < -MAX_ABS_T_US or int(t.max()) > MAX_ABS_T_US):
                    k = int(np.flatnonzero((t < -MAX_ABS_T_US) | (t > MAX_ABS_T_US))[0])
                    raise InputError(f"{self.path}: /events/t[{a + k}] puts an event at {int(t[k])} us, beyond "
                                     f"+-2^62 us (about 146,000 years); the file is damaged")
                events = make_events(t, x, y, p)
                if events.size and int(events["p"].max()) > 1:
                    events["p"] = events["p"] != 0
                yield events

    def _check_range(self, x, y, first: int) -> None:
        """``InputError`` for coordinates that evnoise's event type cannot hold (they would wrap silently
        into pixels of the sensor): ``x`` or ``y`` outside 0 .. 65535."""
        for name, v in (("x", x), ("y", y)):
            if v.size and (v.dtype.kind == "i" or v.dtype.itemsize > 2):
                bad = np.flatnonzero((v < 0) | (v > 65535))
                if bad.size:
                    k = int(bad[0])
                    raise InputError(f"{self.path}: /events/{name}[{first + k}] = {v[k]} is not a pixel coordinate "
                                     f"(0 .. 65535); the file is damaged")


def is_hdf5(head: bytes) -> bool:
    return head.startswith(b"\x89HDF\r\n\x1a\n")


def h5_events_window(path, t_start_us, t_end_us):
    """All events of an events.h5 file in a window, as one array (used by :func:`evnoise.io.read_events`)."""
    src = H5Source(path)
    parts = list(src.chunks(t_start_us, t_end_us))
    return np.concatenate(parts) if parts else make_events([], [], [], []), src
