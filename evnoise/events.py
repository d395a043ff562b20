"""The one event dtype of evnoise, and small pure functions on event arrays.

Events are a structured NumPy array with fields ``t`` (int64, microseconds), ``x`` and ``y``
(uint16, pixel column and row) and ``p`` (uint8, 1 = ON / positive, 0 = OFF / negative),
sorted by ``t``.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError

EVENT_DTYPE = np.dtype([("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.uint8)])

# The one polarity convention of evnoise (outside the numba kernels, which follow it):
#: ``p`` of an ON event (brighter, positive).
ON = 1
#: ``p`` of an OFF event (darker, negative).
OFF = 0
#: Index of ON along the first axis of ``(2, H, W)`` count and rate maps (OFF is ``1 - ON_INDEX``).
ON_INDEX = 0
#: Index of OFF along the first axis of ``(2, H, W)`` maps.
OFF_INDEX = 1


def polarity_index(p) -> np.ndarray:
    """Map index (``ON_INDEX`` 0 for ON, ``OFF_INDEX`` 1 for OFF) of polarity codes ``p`` (int64)."""
    return ON - np.asarray(p).astype(np.int64)


__all__ = [
    "EVENT_DTYPE",
    "ON",
    "OFF",
    "ON_INDEX",
    "OFF_INDEX",
    "polarity_index",
    "empty_events",
    "make_events",
    "count_events",
    "merge_events",
    "events_to_array",
    "events_from_array",
    "check_events",
    "check_shape",
]


def empty_events(n: int = 0) -> np.ndarray:
    """An uninitialised event array of length ``n``."""
    return np.empty(n, dtype=EVENT_DTYPE)


def make_events(t, x, y, p) -> np.ndarray:
    """Pack four equal-length columns into an event array (no sorting, no checks)."""
    out = np.empty(len(t), dtype=EVENT_DTYPE)
    out["t"] = t
    out["x"] = x
    out["y"] = y
    out["p"] = p
    return out


def check_events(events, shape=None, *, name: str = "events") -> np.ndarray:
    """Validate an event array: the dtype, time order and (optionally) coordinates within ``shape``."""
    events = np.asarray(events)
    if events.dtype != EVENT_DTYPE:
        if events.dtype.names and set("txyp") <= set(events.dtype.names):
            events = make_events(events["t"], events["x"], events["y"], events["p"])
        else:
            raise InputError(f"{name} must have fields t, x, y, p (evnoise.EVENT_DTYPE), got dtype {events.dtype}")
    if events.ndim != 1:
        raise InputError(f"{name} must be one-dimensional, got shape {events.shape}")
    if events.size > 1 and np.any(np.diff(events["t"]) < 0):
        raise InputError(f"{name} are not sorted by time t")
    if events.size and np.any(events["p"] > 1):
        raise InputError(f"{name} polarity p must be 0 (OFF) or 1 (ON)")
    if shape is not None and events.size:
        height, width = check_shape(shape)
        if events["x"].max() >= width or events["y"].max() >= height:
            raise InputError(f"{name} have coordinates outside the sensor of shape (H, W) = {shape}")
    return events


def check_shape(shape) -> tuple:
    """``(height, width)`` as ints from a sensor shape ``(H, W)``; ``InputError`` unless 1 <= H, W <= 65536."""
    try:
        height, width = (int(v) for v in shape)
        whole = all(float(v) == int(v) for v in shape)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"shape must be (H, W), got {shape!r}") from None
    if not whole:
        raise InputError(f"shape must be (H, W) in whole pixels, got {shape!r}")
    if height <= 0 or width <= 0 or height > 65536 or width > 65536:
        raise InputError(f"shape must be (H, W) with 1 <= H, W <= 65536, got {shape!r}")
    return height, width



def count_events(events, shape, t_start_us=None, t_end_us=None) -> np.ndarray:
    """Per-pixel event counts ``(2, H, W)`` int64, ``[ON, OFF]``, for ``t_start_us <= t < t_end_us``.

    Parameters
    ----------
    events : numpy.ndarray
        Events (:data:`EVENT_DTYPE`, or any structured array with fields ``t, x, y, p``), sorted by time,
        with coordinates inside ``shape``.
    shape : (H, W)
        Sensor size in pixels.
    t_start_us : int, optional
        Start of the counted span in microseconds (included); None: from the first event.
    t_end_us : int, optional
        End of the counted span in microseconds (excluded); None: through the last event.

    Returns
    -------
    numpy.ndarray
        int64 array of shape ``(2, H, W)``: ON counts, then OFF counts.
    """
    height, width = check_shape(shape)
    events = check_events(events, shape)
    t = events["t"]
    lo = 0 if t_start_us is None else int(np.searchsorted(t, t_start_us, side="left"))
    hi = t.size if t_end_us is None else int(np.searchsorted(t, t_end_us, side="left"))
    ev = events[lo:hi]
    flat = polarity_index(ev["p"]) * (height * width) + ev["y"].astype(np.int64) * width + ev["x"]
    return np.bincount(flat, minlength=2 * height * width).reshape(2, height, width)


def merge_events(a, b) -> np.ndarray:
    """Merge two time-sorted event arrays into one sorted array (stable: ``a`` before ``b`` on ties).

    Parameters
    ----------
    a : numpy.ndarray
        First events (:data:`EVENT_DTYPE`), sorted by time; they come first among events of the same time.
    b : numpy.ndarray
        Second events (:data:`EVENT_DTYPE`), sorted by time.

    Returns
    -------
    numpy.ndarray
        The ``len(a) + len(b)`` events (:data:`EVENT_DTYPE`), sorted by time.
    """
    a = check_events(a, name="first events")
    b = check_events(b, name="second events")
    out = np.empty(a.size + b.size, dtype=EVENT_DTYPE)
    # position of each b event in the output: after all a events with t <= its t
    pos_b = np.searchsorted(a["t"], b["t"], side="right") + np.arange(b.size)
    mask = np.ones(out.size, dtype=bool)
    mask[pos_b] = False
    out[pos_b] = b
    out[mask] = a
    return out


def events_to_array(events, *, time_unit: str = "us") -> np.ndarray:
    """Events as an ``N x 4`` float64 array ``[t, x, y, p]`` as v2e / ESIM-style tools use.

    Polarity stays 1 (ON) / 0 (OFF); use ``2 * p - 1`` for the +1/-1 convention.

    Parameters
    ----------
    events : numpy.ndarray
        Events (:data:`EVENT_DTYPE`), sorted by time.
    time_unit : {"us", "s"}
        Unit of the time column: ``"us"`` (integer microseconds stored as float, the default) or ``"s"``
        (seconds).

    Returns
    -------
    numpy.ndarray
        float64 array of shape ``(N, 4)``, columns ``[t, x, y, p]``.
    """
    events = check_events(events)
    out = np.empty((events.size, 4), dtype=np.float64)
    if time_unit == "us":
        out[:, 0] = events["t"]
    elif time_unit == "s":
        out[:, 0] = events["t"] * 1e-6
    else:
        raise InputError(f"time_unit must be 'us' or 's', got {time_unit!r}")
    out[:, 1] = events["x"]
    out[:, 2] = events["y"]
    out[:, 3] = events["p"]
    return out


def events_from_array(arr, *, time_unit: str = "us") -> np.ndarray:
    """Events from an ``N x 4`` array ``[t, x, y, p]`` (p in {0, 1} or {-1, +1}); sorted stably by t.

    Parameters
    ----------
    arr : array_like, shape (N, 4)
        Numeric, finite columns ``[t, x, y, p]``: ``x`` and ``y`` whole numbers in 0 .. 65535, ``p`` 0 / 1 or
        -1 / +1 (positive is ON).
    time_unit : {"us", "s"}
        Unit of the time column: ``"us"`` (microseconds, the default) or ``"s"`` (seconds); times are rounded
        to whole microseconds.

    Returns
    -------
    numpy.ndarray
        Events (:data:`EVENT_DTYPE`), sorted by time (stable: rows of the same time keep their order).
    """
    arr = np.asarray(arr)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise InputError(f"expected an N x 4 array [t, x, y, p], got shape {arr.shape}")
    if arr.dtype.kind not in "biuf":
        raise InputError(f"expected a numeric N x 4 array [t, x, y, p], got dtype {arr.dtype}")
    if arr.size and not np.isfinite(arr).all():
        raise InputError("event array contains NaN or Inf")
    if time_unit not in ("us", "s"):
        raise InputError(f"time_unit must be 'us' or 's', got {time_unit!r}")
    t = arr[:, 0]
    if time_unit == "s" or t.dtype.kind == "f":
        t = np.round(t * 1e6 if time_unit == "s" else t)
        outside = ~((t >= -(2.0**63)) & (t < 2.0**63))
        if outside.any():
            i = int(np.flatnonzero(outside)[0])
            raise InputError(f"event {i}: time {float(arr[i, 0]):g} {time_unit} is outside the 64-bit microsecond "
                             f"clock (about +-292,000 years)")
    t = t.astype(np.int64)
    pol = arr[:, 3]
    if np.any((pol != 0) & (pol != 1) & (pol != -1)):
        raise InputError("polarity must be 0/1 or -1/+1")
    if np.any(arr[:, 1:3] < 0) or np.any(arr[:, 1:3] > 65535) or np.any(arr[:, 1:3] != np.round(arr[:, 1:3])):
        raise InputError("x and y must be integers in 0 .. 65535")
    out = make_events(t, arr[:, 1], arr[:, 2], (pol > 0).astype(np.uint8))
    return out[np.argsort(out["t"], kind="stable")]
