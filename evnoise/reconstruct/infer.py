"""Inference: counts from an events.h5 stream -> binned rates -> U-Net -> image.

:func:`counts_from_h5` reads only the events of the requested window (through ``/ms_to_idx``),
:class:`Reconstructor` wraps a trained checkpoint.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import InputError, ParameterError
from .imaging import bin_counts

__all__ = ["counts_from_h5", "h5_duration_s", "counts_to_input", "Reconstructor"]


def _open_h5(path):
    import h5py

    path = Path(path)
    if not path.is_file():
        raise InputError(f"events file not found: {path}")
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise InputError(f"{path} is not an HDF5 events file") from None
    if "events" not in f or not all(k in f["events"] for k in ("t", "x", "y", "p")):
        f.close()
        raise InputError(f"{path} has no /events/{{t,x,y,p}}: not an events.h5 file")
    try:
        width, height = int(f.attrs["width"]), int(f.attrs["height"])
    except (KeyError, TypeError, ValueError):
        f.close()
        raise InputError(f"{path} has no width/height attributes") from None
    if width <= 0 or height <= 0:
        f.close()
        raise InputError(f"{path} has an invalid sensor size {width}x{height}")
    return f, (height, width)


def h5_duration_s(path) -> float:
    """Time of the last event in seconds (0 for an empty stream)."""
    f, _ = _open_h5(path)
    with f:
        t = f["events/t"]
        return float(t[-1]) * 1e-6 if t.shape[0] else 0.0


def _index_at(f, t_us: int) -> int:
    """Index of the first event with ``t >= t_us`` (uses /ms_to_idx to read little of /events/t)."""
    t = f["events/t"]
    n = t.shape[0]
    if "ms_to_idx" in f:
        ms = f["ms_to_idx"]
        k = t_us // 1000
        if k >= ms.shape[0]:
            lo = int(ms[-1]) if ms.shape[0] else 0
            hi = n
        else:
            lo = int(ms[k])
            hi = int(ms[k + 1]) if k + 1 < ms.shape[0] else n
    else:
        lo, hi = 0, n
    # binary search inside [lo, hi) reading small slices
    while hi - lo > 4096:
        mid = (lo + hi) // 2
        if int(t[mid]) < t_us:
            lo = mid + 1
        else:
            hi = mid
    block = t[lo:hi]
    return lo + int(np.searchsorted(block, t_us, side="left"))


def counts_from_h5(path, *, t_start_s: float = 0.0, window_s: float | None = None):
    """Counts ``(2, H, W)`` ``[ON, OFF]`` of ``[t_start, t_start + window)`` and the window used.

    Without ``window_s`` the window runs to the last event. Returns ``(counts, window_s)``.
    """
    if not (math.isfinite(t_start_s) and t_start_s >= 0):
        raise ParameterError(f"t_start_s must be >= 0 seconds, got {t_start_s!r}")
    if window_s is not None and not (math.isfinite(window_s) and window_s > 0):
        raise ParameterError(f"window must be > 0 seconds, got {window_s!r}")
    f, (height, width) = _open_h5(path)
    with f:
        t = f["events/t"]
        n = t.shape[0]
        t0 = int(round(t_start_s * 1e6))
        last = int(t[-1]) if n else 0
        if window_s is None:
            if n == 0 or last < t0:
                raise InputError(f"{path} has no events after t = {t_start_s:g} s")
            t1 = last + 1
            window_s = (t1 - t0) * 1e-6
        else:
            t1 = t0 + int(round(window_s * 1e6))
            if t1 > last + 1:
                raise InputError(
                    f"the window {t_start_s:g} s + {window_s:g} s runs past the end of the stream "
                    f"({last * 1e-6:.6g} s)"
                )
        lo, hi = _index_at(f, t0), _index_at(f, t1)
        x = f["events/x"][lo:hi].astype(np.int64)
        y = f["events/y"][lo:hi].astype(np.int64)
        p = f["events/p"][lo:hi].astype(np.int64)
    if x.size and (x.max() >= width or y.max() >= height):
        raise InputError(f"{path} has events outside its {width}x{height} sensor")
    flat = (1 - p) * (height * width) + y * width + x  # channel 0 = ON (p = 1)
    counts = np.bincount(flat, minlength=2 * height * width).reshape(2, height, width)
    return counts, float(window_s)


def counts_to_input(counts, window_s: float, spec) -> np.ndarray:
    """Binned counts ``(2, h, w)`` -> network input ``(C, h, w)`` float32 (rates / rate scale)."""
    c = np.asarray(counts, dtype=np.float32)
    if c.ndim != 3 or c.shape[0] != 2:
        raise InputError(f"counts must have shape (2, h, w), got {c.shape}")
    return c[list(spec.channels)] / np.float32(window_s * spec.rate_scale_hz)


class Reconstructor:
    """A trained U-Net ready to turn counts into images.

    Parameters
    ----------
    path : path
        Checkpoint written by :func:`evnoise.reconstruct.train.train`.
    threads : int, optional
        Torch CPU threads (default: leave torch's setting).
    """

    def __init__(self, path, *, threads: int | None = None):
        from ._torch import require_torch
        from .checkpoint import load_model

        self.torch = require_torch()
        if threads is not None:
            self.torch.set_num_threads(max(1, int(threads)))
        self.model, self.spec, self.doc = load_model(path)
        self.model = self.model.to(memory_format=self.torch.channels_last)
        self.path = Path(path)

    @property
    def binning(self) -> int:
        return self.spec.binning

    def predict_binned(self, counts, window_s: float) -> np.ndarray:
        """Image ``(h, w)`` in ``[0, 1]`` from counts already binned like the training data."""
        x = self.torch.from_numpy(counts_to_input(counts, window_s, self.spec))[None]
        x = x.contiguous(memory_format=self.torch.channels_last)
        with self.torch.inference_mode():
            y = self.model(x)[0, 0]
        return np.clip(y.float().numpy(), 0.0, 1.0)

    def predict(self, counts, window_s: float, *, binning: int | None = None) -> np.ndarray:
        """Image from full-resolution counts ``(2, H, W)``: binned as in training, then the U-Net.

        ``binning``, when given, must equal the model's (a guard for callers that assume one).
        """
        if binning is not None and binning != self.spec.binning:
            raise ParameterError(
                f"the model was trained on {self.spec.binning}x{self.spec.binning}-binned counts; "
                f"binning {binning} does not match"
            )
        return self.predict_binned(bin_counts(counts, self.spec.binning), window_s)
