"""Windows of a still scene: a recording's per-pixel ON/OFF counts over a time window
(:class:`QuietWindow`, :func:`quiet_window`), what :func:`evnoise.calibration.quiet.fit.fit_quiet` fits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evnoise._clock import seconds_text
from evnoise.errors import InputError, ParameterError

__all__ = ["QuietWindow", "quiet_window", "window_events", "merge_doublets", "DOUBLET_US"]

#: Readout doublets: a pixel's event within this many microseconds after its previous event of the same
#: polarity is merged into it (:func:`merge_doublets`). The DVS128 recordings hold such pairs 0-2 us apart
#: (up to 13 of the 31 same-pixel intervals of the eDVS128 window), which no photon or leak process
#: makes and the simulator has no term for; 0 keeps them.
DOUBLET_US = 10


@dataclass
class QuietWindow:
    """Per-pixel counts ``(2, H, W)`` ``[ON, OFF]`` of a still scene over ``duration_s`` seconds."""

    counts: np.ndarray
    duration_s: float
    source: str = ""
    group: str = ""
    t_start_s: float | None = None
    t_end_s: float | None = None
    lux: float | None = None
    #: model-free checks that the window is pure stationary noise (:mod:`.checks`), if computed
    checks: list = field(default_factory=list)
    #: the window's events for the timing likelihood (:func:`window_events`), or None (counts only)
    events: dict | None = None
    #: readout doublets merged when the window was read (:data:`DOUBLET_US`)
    doublets: int = 0

    def __post_init__(self):
        counts = np.asarray(self.counts)
        if counts.ndim != 3 or counts.shape[0] != 2:
            raise InputError(f"counts must have shape (2, H, W), got {counts.shape}")
        if counts.size == 0 or np.any(counts < 0):
            raise InputError("counts must be non-negative and not empty")
        self.counts = counts.astype(np.int64)
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise ParameterError(f"duration_s must be > 0, got {self.duration_s!r}")
        if self.lux is not None and not (math.isfinite(self.lux) and self.lux >= 0):
            raise ParameterError(f"lux must be finite and >= 0, got {self.lux!r}")
        if not self.group:
            self.group = self.source

    @property
    def shape(self):
        return self.counts.shape[1:]

    def describe(self) -> str:
        when = "" if self.t_start_s is None else f" {seconds_text(self.t_start_s)}-{seconds_text(self.t_end_s)} s"
        return f"{Path(self.source).name or 'counts'}{when}"


def merge_doublets(events: np.ndarray, width: int, doublet_us: float = DOUBLET_US) -> tuple:
    """``(events, merged)``: events without the readout doublets (:data:`DOUBLET_US`): an event of a pixel
    within ``doublet_us`` microseconds after that pixel's previous event of the same polarity is dropped
    (the first of a run is kept). Time order is kept."""
    if doublet_us <= 0 or events.size < 2:
        return events, 0
    pix = events["y"].astype(np.int64) * int(width) + events["x"].astype(np.int64)
    key = pix * 2 + events["p"].astype(np.int64)
    order = np.lexsort((events["t"], key))
    k, t = key[order], events["t"][order].astype(np.int64)
    dup = np.zeros(events.size, dtype=bool)
    dup[order[1:]] = (k[1:] == k[:-1]) & (t[1:] - t[:-1] <= doublet_us)
    return events[~dup], int(np.count_nonzero(dup))


def window_events(events: np.ndarray, shape: tuple, t_start_us: int) -> dict:
    """The events of a window as the timing likelihood reads them: ``pixel`` (flat index ``y * W + x``),
    ``t_s`` (seconds from the window's start) and ``on`` (bool), sorted by pixel, then time."""
    width = int(shape[1])
    pix = events["y"].astype(np.int64) * width + events["x"].astype(np.int64)
    t = events["t"].astype(np.int64) - int(t_start_us)
    order = np.lexsort((t, pix))
    return {"pixel": pix[order], "t_s": t[order] * 1e-6, "on": (events["p"] == 1)[order]}


def quiet_window(path, t_start_s: float, t_end_s: float, *, lux: float | None = None, sensor=None,
                 csv_columns=None, checks: bool = False, seed: int = 0, progress: bool = False,
                 doublet_us: float = DOUBLET_US) -> QuietWindow:
    """The counts of a recording's window ``[t_start_s, t_end_s)`` (seconds on the file's clock).

    Any file :func:`evnoise.read_events` opens. The sensor size is the file's (or ``sensor``). With
    ``checks``, the window's events are also checked for what the fit assumes (polarity pairs,
    stationarity, scene motion; :func:`evnoise.calibration.quiet.checks.window_checks`, resampled
    with ``seed``), into ``QuietWindow.checks``; ``progress`` shows a bar over their resamples. Readout
    doublets are merged first (:func:`merge_doublets`, ``doublet_us``; 0 keeps them); the window keeps its
    events (``QuietWindow.events``) for the fit's timing likelihood.
    """
    from evnoise.events import count_events
    from evnoise.io import read_events

    if not (t_end_s > t_start_s):
        raise ParameterError(f"t_end_s must be after t_start_s, got {seconds_text(t_start_s)} .. "
                             f"{seconds_text(t_end_s)} s")
    events, meta = read_events(path, t_start=t_start_s, t_end=t_end_s, sensor=sensor, csv_columns=csv_columns)
    shape = meta.get("shape")
    if shape is None:
        raise InputError(f"{path}: the file does not give its sensor size; pass sensor='WxH'")
    if events.size == 0:
        raise InputError(f"{path}: no events in the window {seconds_text(t_start_s)} .. {seconds_text(t_end_s)} s "
                         "(check the times: they are seconds on the file's clock)")
    events, doublets = merge_doublets(events, int(shape[1]), doublet_us)
    counts = count_events(events, tuple(shape))
    found = []
    if checks:
        from .checks import window_checks

        t0_us, t1_us = round(t_start_s * 1e6), round(t_end_s * 1e6)  # as read_events cuts the window
        found = window_checks(events, counts, t0_us, t1_us - t0_us, seed=seed, progress=progress,
                              desc=f"checks of {Path(str(path)).name}")
    t0_us = round(t_start_s * 1e6)
    return QuietWindow(counts, float(t_end_s - t_start_s), str(path), str(path), float(t_start_s), float(t_end_s),
                       None if lux is None else float(lux), found, window_events(events, tuple(shape), t0_us),
                       doublets)
