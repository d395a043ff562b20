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

__all__ = ["QuietWindow", "quiet_window", "window_events", "merge_doublets", "oscillating_pixels", "oscillating_notes",
           "same_exclusions", "drop_pixels",
           "DOUBLET_US",
           "OSCILLATING_MIN_EVENTS", "OSCILLATING_MAX_CV", "OSCILLATING_RATE_FACTOR"]

#: Readout doublets: a pixel's event within this many microseconds after its previous event of the same
#: polarity is merged into it (:func:`merge_doublets`). The DVS128 recordings hold such pairs 0-2 us apart
#: (up to 13 of the 31 same-pixel intervals of the eDVS128 window), which no photon or leak process
#: makes and the simulator has no term for; 0 keeps them.
DOUBLET_US = 10

#: Oscillating pixels (:func:`oscillating_pixels`): a pixel with at least this many events of one polarity ...
OSCILLATING_MIN_EVENTS = 15
#: ... whose same-polarity intervals have a coefficient of variation below this (a Poisson pixel's is 1; with
#: 14 intervals a Poisson pixel's sample CV is below 0.3 with probability about 5e-6, with 9 about 3e-4) ...
OSCILLATING_MAX_CV = 0.3
#: ... and at least this many times the window's mean events per pixel of that polarity (so a sensor whose
#: every pixel leaks near-periodically, the model's regular timer, is not flagged: its pixels are alike).
#: A DVS128 recording holds one such pixel firing ON every 185 ms for 14-21 s (calibration/README); no term of
#: the model makes a lone periodic pixel, and its intervals decide a timing fit's KS test.
OSCILLATING_RATE_FACTOR = 10.0


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
    #: flat indices ``y * W + x`` of pixels left out of the fit (their counts are 0 and their events dropped;
    #: :meth:`without`); ``pixel_counts`` and ``n_pixels`` count only the others
    excluded: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    #: the oscillating pixels found when the window was read (:func:`oscillating_pixels`), dropped or not
    oscillating: list = field(default_factory=list)

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
        excluded = np.unique(np.asarray(self.excluded, dtype=np.int64).ravel())
        n = int(np.prod(counts.shape[1:]))
        if excluded.size and (excluded[0] < 0 or excluded[-1] >= n):
            raise InputError(f"excluded pixels must be flat indices 0 .. {n - 1}")
        if excluded.size >= n:
            raise InputError("every pixel of the window is excluded")
        self.excluded = excluded
        self.counts.reshape(2, -1)[:, excluded] = 0

    @property
    def shape(self):
        return self.counts.shape[1:]

    @property
    def n_pixels(self) -> int:
        """The number of pixels the fit uses (the sensor's, less the excluded ones)."""
        return int(np.prod(self.shape)) - int(self.excluded.size)

    def kept(self) -> np.ndarray:
        """Flat boolean mask ``(H * W,)`` of the pixels the fit uses."""
        keep = np.ones(int(np.prod(self.shape)), dtype=bool)
        keep[self.excluded] = False
        return keep

    def pixel_counts(self) -> np.ndarray:
        """Counts ``(2, n_pixels)`` ``[ON, OFF]`` of the pixels the fit uses, in flat order."""
        return self.counts.reshape(2, -1)[:, self.kept()]

    def without(self, pixels) -> "QuietWindow":
        """A copy with ``pixels`` (flat indices) excluded too: their counts set to 0 and their events dropped.

        Parameters
        ----------
        pixels : int or array_like of int
            Flat indices ``y * W + x`` of the pixels to leave out, in addition to those already excluded.

        Returns
        -------
        QuietWindow
            The new window; this one itself where no pixel is added.

        Notes
        -----
        The same-pixel timing the checks gathered (``same_pixel``, which the fit's timing tests read) is
        recomputed from the remaining events; the checks' own p-values stay those of the window as it was read.
        """
        import dataclasses

        excluded = np.union1d(self.excluded, np.asarray(pixels, dtype=np.int64).ravel())
        if excluded.size == self.excluded.size:
            return self
        events, checks = self.events, self.checks
        if events is not None:
            keep = ~np.isin(events["pixel"], excluded)
            events = {k: np.asarray(v)[keep] for k, v in events.items()}
            if any("same_pixel" in c for c in checks):
                from .checks import same_pixel_timing

                timing = same_pixel_timing(_event_array(events, self.shape[1]), self.shape)
                checks = [dict(c, same_pixel=timing) if "same_pixel" in c else c for c in checks]
        return dataclasses.replace(self, counts=self.counts.copy(), events=events, excluded=excluded, checks=checks)

    def describe(self) -> str:
        """The window in a few words: the file's name (``"counts"`` without one) and, where known, its span.

        Returns
        -------
        str
            E.g. ``"recording.aedat4 2-12 s"``.
        """
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


def drop_pixels(events: np.ndarray, width: int, pixels: np.ndarray) -> np.ndarray:
    """The events (an event array) of the pixels other than ``pixels`` (flat indices ``y * width + x``)."""
    pix = events["y"].astype(np.int64) * int(width) + events["x"].astype(np.int64)
    return events[~np.isin(pix, pixels)]


def _event_array(events: dict, width: int) -> np.ndarray:
    """The events of :func:`window_events`' dict as an event array (times in microseconds from the window start)."""
    from evnoise.events import EVENT_DTYPE

    out = np.zeros(events["pixel"].size, dtype=EVENT_DTYPE)
    out["t"] = np.round(np.asarray(events["t_s"]) * 1e6)
    out["x"] = events["pixel"] % int(width)
    out["y"] = events["pixel"] // int(width)
    out["p"] = np.asarray(events["on"], dtype=bool)
    return out


def oscillating_pixels(events: np.ndarray, shape: tuple) -> list:
    """Pixels firing near-periodically far above the others: per polarity, at least
    :data:`OSCILLATING_MIN_EVENTS` events, at least :data:`OSCILLATING_RATE_FACTOR` times the window's mean
    events per pixel of that polarity, and same-polarity intervals with a coefficient of variation below
    :data:`OSCILLATING_MAX_CV`. One dict per pixel and polarity: ``x``, ``y``, ``polarity`` (1 ON, 0 OFF),
    ``events``, ``period_s`` (mean interval) and ``cv``, busiest first."""
    if events.size < OSCILLATING_MIN_EVENTS:
        return []
    height, width = int(shape[0]), int(shape[1])
    n_pix = height * width
    pol = (events["p"] == 1).astype(np.int64)
    key = (events["y"].astype(np.int64) * width + events["x"].astype(np.int64)) * 2 + pol
    n = np.bincount(key, minlength=2 * n_pix)
    mean = np.array([n[0::2].sum(), n[1::2].sum()], dtype=np.float64) / n_pix
    busy = (n >= OSCILLATING_MIN_EVENTS) & (n >= OSCILLATING_RATE_FACTOR * mean[np.arange(n.size) % 2])
    if not busy.any():
        return []
    # the busy streams' gaps at once (sorted by stream, then time): one pass however many pixels are busy
    sel = busy[key]
    k, t = key[sel], events["t"][sel].astype(np.int64)
    order = np.lexsort((t, k))
    k, t = k[order], t[order]
    same = k[1:] == k[:-1]
    gk, gaps = k[1:][same], (np.diff(t)[same]) * 1e-6
    m = np.bincount(gk, minlength=n.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        gap_mean = np.bincount(gk, weights=gaps, minlength=n.size) / m
        ss = np.bincount(gk, weights=(gaps - gap_mean[gk]) ** 2, minlength=n.size)
        cv = np.sqrt(ss / (m - 1.0)) / gap_mean
    found = []
    for k in np.flatnonzero(busy):
        if gap_mean[k] > 0 and cv[k] < OSCILLATING_MAX_CV:
            pix = int(k // 2)
            found.append({"x": pix % width, "y": pix // width, "polarity": int(k % 2), "events": int(n[k]),
                          "period_s": float(gap_mean[k]), "cv": float(cv[k])})
    return sorted(found, key=lambda d: -d["events"])


def oscillating_notes(windows) -> list:
    """One line per window with oscillating pixels (:func:`oscillating_pixels`): which, and whether they were left
    out of the fit (``quiet_window(..., drop_oscillating=True)``, ``evnoise calibrate --drop-oscillating``)."""
    out = []
    for w in windows:
        if not w.oscillating:
            continue
        width = w.shape[1]
        dropped = set(int(i) for i in w.excluded)
        pixels = ", ".join(f"x {o['x']} y {o['y']} ({'ON' if o['polarity'] else 'OFF'}, {o['events']} events every "
                           f"{o['period_s']:.3g} s, interval CV {o['cv']:.2f})" for o in w.oscillating[:5])
        more = f" and {len(w.oscillating) - 5} more" if len(w.oscillating) > 5 else ""
        left = all(o["y"] * width + o["x"] in dropped for o in w.oscillating)
        out.append(f"{w.describe()}: {len(w.oscillating)} oscillating pixel(s) {pixels}{more}: "
                   + ("left out of the fit" if left else "kept in the fit, where no term of the model makes a lone "
                      "periodic pixel (drop_oscillating / --drop-oscillating leaves them out)"))
    return out


def same_exclusions(windows) -> list:
    """The windows with every window of a group (:attr:`QuietWindow.group`: its pixels are tied) excluding the
    pixels any of them excludes, so the group's pixels are the same in each."""
    union = {}
    for w in windows:
        union[w.group] = np.union1d(union.get(w.group, w.excluded), w.excluded)
    return [w.without(union[w.group]) for w in windows]


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
                 doublet_us: float = DOUBLET_US, drop_oscillating: bool = False) -> QuietWindow:
    """The counts of a recording's window ``[t_start_s, t_end_s)`` (seconds on the file's clock).

    Any file :func:`evnoise.read_events` opens. The sensor size is the file's (or ``sensor``). With
    ``checks``, the window's events are also checked for what the fit assumes (polarity pairs,
    stationarity, scene motion; :func:`evnoise.calibration.quiet.checks.window_checks`, resampled
    with ``seed``), into ``QuietWindow.checks``; ``progress`` shows a bar over their resamples. Readout
    doublets are merged first (:func:`merge_doublets`, ``doublet_us``; 0 keeps them); the window keeps its
    events (``QuietWindow.events``) for the fit's timing likelihood. Oscillating pixels
    (:func:`oscillating_pixels`) are found and kept in ``QuietWindow.oscillating``; with ``drop_oscillating`` they
    are left out of the window (``QuietWindow.excluded``: counts 0, events dropped, before the checks), as the
    model has no term for a lone periodic pixel.

    Parameters
    ----------
    path : str or os.PathLike
        The recording, any file :func:`evnoise.read_events` opens.
    t_start_s, t_end_s : float
        The window's start and end in seconds on the file's clock (``t_end_s > t_start_s``).
    lux : float, optional
        Illuminance of the scene in lux (finite, ``>= 0``), if known.
    sensor : str or (int, int), optional
        Sensor size ``"WxH"`` or ``(width, height)``, for files whose header has none or a wrong one.
    csv_columns : str, optional
        Column order of a CSV file, e.g. ``"x,y,p,t"``.
    checks : bool, default False
        Run the model-free checks of the window (:func:`evnoise.calibration.quiet.checks.window_checks`).
    seed : int, default 0
        Seed of the checks' resamples.
    progress : bool, default False
        Show a progress bar over the checks' resamples.
    doublet_us : float, default DOUBLET_US
        Readout doublets within this many microseconds are merged; 0 keeps them.
    drop_oscillating : bool, default False
        Leave the oscillating pixels out of the window.

    Returns
    -------
    QuietWindow
        The window's counts, events, checks, oscillating pixels and the number of doublets merged.
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
    oscillating = oscillating_pixels(events, tuple(shape))
    excluded = np.unique([o["y"] * int(shape[1]) + o["x"] for o in oscillating]).astype(np.int64)
    if drop_oscillating and excluded.size:
        events = drop_pixels(events, int(shape[1]), excluded)
    else:
        excluded = np.zeros(0, dtype=np.int64)
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
                       doublets, excluded, oscillating)
