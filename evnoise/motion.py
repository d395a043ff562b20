"""Static background behind moving things: motion masks, moving-window noise counts, video output.

The Noise2Image paper (§4.1, §5.3) reconstructs the static background of a recording with
motion from its *noise* events: a denoiser separates the signal events of the moving parts, a
binary motion mask is found by thresholding the signal events, and the noise events of pixels
without motion are aggregated over a moving window of fixed length and fed to the
reconstructor. This module implements that pipeline with bounded memory.

Time steps
    The recording is cut into steps of ``step_s`` seconds (``1 / fps``) starting at
    ``t_start``; step ``k`` covers ``[t_start + k step, t_start + (k + 1) step)`` and produces
    one :class:`MotionFrame` at its end. The count window is a whole number of steps
    (``window_s`` rounded to the nearest multiple of ``step_s``, at least one step).

Motion mask (per step)
    Signal events of the last ``mask.window_s`` seconds (rounded up to whole steps) are counted
    per pixel, summed over the ``(2 r + 1) x (2 r + 1)`` neighbourhood (``r = mask.radius_px``);
    pixels where that density reaches ``mask.threshold`` events are moving, and the mask is
    dilated by a disc of ``mask.dilation_px`` pixels (to cover the uniform inside of objects and
    the pixels next to edges, which fire fewer signal events).

Moving-window noise counts, and pixels that become static again
    Frame ``k`` counts, per pixel, the noise events (``is_signal`` False; all events with
    ``count="all"``) of the window's steps ``k - W + 1 .. k`` (``W``: the window in steps) in
    which the pixel was *not* masked (``on_motion="skip"``, the default). A masked step is left
    out, so a pixel that becomes static again keeps the static steps it had before the motion
    and adds new ones, and the masked steps age out of the window after ``W`` steps: from then
    on the pixel is counted over the whole window again. :attr:`MotionFrame.exposure_s` is the
    counted time of each pixel (unmasked steps times the step), and ``counts / exposure_s`` its
    rate. With ``on_motion="restart"`` a masked step empties the pixel's window instead: its
    counts restart after the motion and cover the steps ``max(k - W + 1, s) .. k``, ``s`` being
    the step after the pixel's last masked step. (On the scenes of
    ``benchmarks/bench_dynamic.py`` "skip" gives the lower rate error behind moving objects.)
    Memory: ``W`` per-step count maps of ``2 x H x W`` uint16 (int32 if a count overflows) and
    ``W`` masks, independent of the recording's length.

Reconstruction over time (:func:`evnoise.reconstruct.video.reconstruct_video`, built on this module)
    A pixel's event rate is refreshed only when its exposure reaches ``min_exposure_s``
    (default: the whole window, i.e. no masked step in the window): ``rate = counts /
    exposure``. Pixels under motion, or moving too recently, keep their *last static estimate*
    (the rate of the last frame where they were refreshed); pixels never refreshed yet use
    their counts so far, or the median rate of the refreshed pixels while they have none. The
    U-Net therefore always sees a complete rate image of the background, and masked regions
    show the last static estimate of what is behind the moving object. This choice keeps every
    frame an image of the static background; the moving foreground is not reconstructed but
    drawn in the overlay PNG (mask tinted red, this step's signal events marked), which is the
    simple event-integration view of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from ._checks import check_float, check_int
from .errors import InputError, ParameterError
from .events import check_events, check_shape, empty_events, polarity_index

__all__ = [
    "MaskParams",
    "MotionFrame",
    "MotionTracker",
    "BackgroundHold",
    "iter_motion",
    "motion_mask",
    "box_sum",
    "disc",
    "bin_rates",
    "bin_mask",
    "overlay_rgb",
    "COUNT_MODES",
    "ON_MOTION",
]

#: What the moving window counts at unmasked pixels: the events labelled noise (as the paper),
#: or all events (signal labels then only make the mask).
COUNT_MODES = ("noise", "all")

#: What a masked step does to a pixel's moving window: ``"skip"`` leaves the step out (the window
#: keeps the pixel's other, static steps), ``"restart"`` empties the window (counting starts
#: again after the motion).
ON_MOTION = ("skip", "restart")

#: Time span of the blocks read from a file (or cut from an array) at a time, in seconds.
BLOCK_S = 0.25


@dataclass(frozen=True)
class MaskParams:
    """How the motion mask is made from signal events (see the module docstring).

    Parameters
    ----------
    window_s : float
        Signal events of the last ``window_s`` seconds count (rounded up to whole steps).
    radius_px : int
        Half-side in pixels of the square over which signal events are summed.
    threshold : int
        Minimum number of signal events in that neighbourhood and window for a moving pixel.
    dilation_px : int
        Radius in pixels of the disc the mask is dilated with (0: no dilation).
    """

    window_s: float = 0.2
    radius_px: int = 2
    threshold: int = 3
    dilation_px: int = 3

    def __post_init__(self):
        object.__setattr__(self, "window_s", check_float(self.window_s, "mask window_s", "seconds"))
        object.__setattr__(self, "radius_px", check_int(self.radius_px, "mask radius_px", 0, 255, "pixels"))
        object.__setattr__(self, "threshold", check_int(self.threshold, "mask threshold", 1, 2**31 - 1, "events"))
        object.__setattr__(self, "dilation_px", check_int(self.dilation_px, "dilation_px", 0, 255, "pixels"))


@dataclass
class MotionFrame:
    """The state at the end of one time step (see the module docstring).

    Attributes
    ----------
    index : int
        Step number ``k`` (0 = the first step after ``t_start``).
    t_start_us, t_end_us : int
        The step ``[t_start_us, t_end_us)`` in microseconds.
    mask : numpy.ndarray of bool (H, W)
        Motion mask of the step.
    counts : numpy.ndarray of int32 (2, H, W)
        Moving-window noise counts ``[ON, OFF]`` of each pixel's counted (unmasked) steps.
    exposure_s : numpy.ndarray of float64 (H, W)
        Counted time of each pixel in seconds (at most ``window_s``; below it when some step of
        the window was masked, or since the motion with ``on_motion="restart"``).
    signal : numpy.ndarray of int64 (2, H, W)
        Signal events ``[ON, OFF]`` of this step alone.
    window_s, step_s : float
        The count window and the step actually used (whole steps).
    n_noise, n_signal : int
        Events of this step labelled noise and signal.
    """

    index: int
    t_start_us: int
    t_end_us: int
    mask: np.ndarray
    counts: np.ndarray
    exposure_s: np.ndarray
    signal: np.ndarray
    window_s: float
    step_s: float
    n_noise: int = 0
    n_signal: int = 0

    @property
    def full(self) -> np.ndarray:
        """Pixels counted over the whole window (no masked step in the last ``window_s``)."""
        return self.exposure_s >= self.window_s - 0.5e-6


def box_sum(image, radius_px: int) -> np.ndarray:
    """Sum of ``image`` (H, W) over the ``(2 r + 1)^2`` square around each pixel (zeros outside), exact."""
    a = np.asarray(image)
    r = int(radius_px)
    if r == 0:
        return a.astype(np.int64, copy=True)
    h, w = a.shape
    c = np.zeros((h + 2 * r + 1, w + 2 * r + 1), dtype=np.int64)
    c[r + 1:r + 1 + h, r + 1:r + 1 + w] = a
    c = c.cumsum(axis=0).cumsum(axis=1)
    k = 2 * r + 1
    return c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]


def disc(radius_px: int) -> np.ndarray:
    """The dilation's structuring element: a round disc ``dy^2 + dx^2 <= r^2 + r`` (not a diamond)."""
    r = int(radius_px)
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    return yy * yy + xx * xx <= r * r + r


def motion_mask(signal_counts, mask: MaskParams | None = None) -> np.ndarray:
    """Motion mask (H, W) from per-pixel signal event counts (H, W) of the mask window.

    Pixels whose ``(2 r + 1)^2`` box sum (:func:`box_sum`) reaches ``mask.threshold``, dilated by
    :func:`disc` of ``mask.dilation_px`` (as ``scipy.ndimage.binary_dilation``). The kernel
    visits only the neighbourhoods of pixels with signal events (cost proportional to them).
    """
    from ._kernels.filters import dense_mask

    mask = MaskParams() if mask is None else mask
    counts = np.ascontiguousarray(signal_counts, dtype=np.int64)
    if counts.ndim != 2:
        raise InputError(f"signal_counts must be 2-D (H, W), got shape {counts.shape}")
    dy, dx = np.nonzero(disc(mask.dilation_px))
    out = np.zeros(counts.shape, dtype=bool)
    dense_mask(counts, mask.radius_px, mask.threshold, dy - mask.dilation_px, dx - mask.dilation_px, out)
    return out


class MotionTracker:
    """Streaming motion masks and moving-window noise counts (see the module docstring).

    Parameters
    ----------
    shape : (H, W)
        Sensor size in pixels.
    step_s : float
        Time step in seconds (one :class:`MotionFrame` per step).
    window_s : float
        Count window in seconds (rounded to whole steps, at least one).
    t_start_us : int
        Start of step 0 in microseconds; earlier events are an error.
    mask : MaskParams, optional
        Motion-mask settings.
    count : {"noise", "all"}
        What the window counts at unmasked pixels (:data:`COUNT_MODES`).
    on_motion : {"skip", "restart"}
        What a masked step does to a pixel's window (:data:`ON_MOTION`).

    Notes
    -----
    :meth:`push` takes labelled events in time order and returns the frames of the steps it has
    completed; :meth:`finish` completes the steps up to the end of the recording.
    """

    def __init__(self, shape, *, step_s: float, window_s: float, t_start_us: int = 0, mask: MaskParams | None = None,
                 count: str = "noise", on_motion: str = "skip"):
        self.shape = check_shape(shape)
        if count not in COUNT_MODES:
            raise ParameterError(f"count must be one of {COUNT_MODES}, got {count!r}")
        if on_motion not in ON_MOTION:
            raise ParameterError(f"on_motion must be one of {ON_MOTION}, got {on_motion!r}")
        self.count = count
        self.on_motion = on_motion
        step_s = check_float(step_s, "step_s", "seconds")
        window_s = check_float(window_s, "window_s", "seconds")
        self.step_us = int(round(step_s * 1e6))
        if self.step_us < 1:
            raise ParameterError(f"step_s must be at least 1 microsecond, got {step_s!r}")
        self.mask_params = MaskParams() if mask is None else mask
        if not isinstance(self.mask_params, MaskParams):
            raise ParameterError(f"mask must be a MaskParams, got {type(mask).__name__}")
        self.window_steps = max(1, int(round(window_s * 1e6 / self.step_us)))
        self.mask_steps = max(1, math.ceil(self.mask_params.window_s * 1e6 / self.step_us - 1e-9))
        self.step_s = self.step_us * 1e-6
        self.window_s = self.window_steps * self.step_s
        if isinstance(t_start_us, bool) or not isinstance(t_start_us, (int, np.integer)):
            raise ParameterError(f"t_start_us must be an integer of microseconds, got {t_start_us!r}")
        self.t0 = int(t_start_us)
        height, width = self.shape
        self._noise_ring = np.zeros((self.window_steps, 2, height, width), dtype=np.uint16)
        self._signal_ring = np.zeros((self.mask_steps, height, width), dtype=np.int32)
        self._signal_sum = np.zeros((height, width), dtype=np.int64)
        self._sum = np.zeros((2, height, width), dtype=np.int32)
        self._start = np.zeros((height, width), dtype=np.int64)  # restart: first counted step of each pixel
        self._static_ring = np.zeros((self.window_steps, height, width), dtype=bool)  # skip: unmasked steps
        self._static_steps = np.zeros((height, width), dtype=np.int64)
        self._k = 0
        self._pending = empty_events(0)
        self._pending_sig = np.zeros(0, dtype=bool)
        self._known_us = self.t0  # every event with t < _known_us has been pushed
        self._finished = False

    @property
    def next_step_end_us(self) -> int:
        return self.t0 + (self._k + 1) * self.step_us

    def push(self, events, is_signal, *, t_complete_us: int | None = None) -> list:
        """Add labelled events (sorted, not earlier than those before); returns completed frames.

        ``t_complete_us`` promises that every event with ``t < t_complete_us`` has been pushed.
        """
        if self._finished:
            raise InputError("this MotionTracker has finished")
        events = check_events(events, self.shape)
        labels = np.asarray(is_signal, dtype=bool)
        if labels.shape != events.shape:
            raise InputError(f"is_signal must have one entry per event ({events.size}), got shape {labels.shape}")
        if events.size:
            t_first = int(events["t"][0])
            floor_us = int(self._pending["t"][-1]) if self._pending.size else self.t0 + self._k * self.step_us
            if t_first < floor_us:
                raise InputError(f"event at t = {t_first} us is earlier than t = {floor_us} us, which was already "
                                 f"processed (push events in time order, none before t_start)")
            self._pending = np.concatenate([self._pending, events])
            self._pending_sig = np.concatenate([self._pending_sig, labels])
            self._known_us = max(self._known_us, int(events["t"][-1]))
        if t_complete_us is not None:
            self._known_us = max(self._known_us, int(t_complete_us))
        return self._complete(self._known_us)

    def finish(self, t_end_us: int | None = None) -> list:
        """The frames of every step that ends at or before ``t_end_us`` (default: the last event + 1)."""
        if self._finished:
            return []
        if t_end_us is None:
            t_end_us = (int(self._pending["t"][-1]) + 1) if self._pending.size else self._known_us
        frames = self._complete(int(t_end_us))
        self._finished = True
        return frames

    def _complete(self, known_us: int) -> list:
        frames = []
        while self.next_step_end_us <= known_us:
            end = self.next_step_end_us
            n = int(np.searchsorted(self._pending["t"], end, side="left"))
            frames.append(self._step(self._pending[:n], self._pending_sig[:n]))
            self._pending = self._pending[n:]
            self._pending_sig = self._pending_sig[n:]
        return frames

    def _bins(self, events):
        height, width = self.shape
        flat = (polarity_index(events["p"]) * (height * width) + events["y"].astype(np.int64) * width
                + events["x"])
        return np.bincount(flat, minlength=2 * height * width).reshape(2, height, width)

    def _step(self, events, is_signal) -> MotionFrame:
        from ._kernels.filters import window_skip

        k = self._k
        signal = self._bins(events[is_signal])
        noise = self._bins(events if self.count == "all" else events[~is_signal])
        # motion mask from the signal events of the last mask_steps steps
        slot = k % self.mask_steps
        sig_now = signal.sum(axis=0)
        self._signal_sum += sig_now - self._signal_ring[slot]
        self._signal_ring[slot] = sig_now
        mask = motion_mask(self._signal_sum, self.mask_params)
        # moving-window noise counts
        w = self.window_steps
        slot = k % w
        if noise.max(initial=0) > np.iinfo(self._noise_ring.dtype).max:
            self._noise_ring = self._noise_ring.astype(np.int32)
        if self.on_motion == "skip":
            window_skip(self._sum, self._static_steps, self._noise_ring[slot], self._static_ring[slot], noise, mask,
                        k >= w)  # step k - w leaves the window
            exposure = self._static_steps * self.step_s
        else:  # restart
            if k >= w:
                drop = (k - w) >= self._start
                self._sum -= np.where(drop, self._noise_ring[slot], 0)
            self._noise_ring[slot] = noise
            self._sum += noise
            self._sum[:, mask] = 0
            self._start[mask] = k + 1
            first = np.maximum(k - w + 1, self._start)
            exposure = (k + 1 - first) * self.step_s
        t_start = self.t0 + k * self.step_us
        self._k += 1
        return MotionFrame(index=k, t_start_us=t_start, t_end_us=t_start + self.step_us, mask=mask,
                           counts=self._sum.copy(), exposure_s=exposure, signal=signal, window_s=self.window_s,
                           step_s=self.step_s, n_noise=int(noise.sum()), n_signal=int(signal.sum()))


# --------------------------------------------------------------------------------------
# sources: an events.h5 file or an array, cut into time blocks
# --------------------------------------------------------------------------------------
def _array_blocks(events, t_start_us: int, t_end_us: int, block_us: int):
    t = events["t"]
    a = t_start_us
    lo = int(np.searchsorted(t, a, side="left"))
    while a < t_end_us:
        b = min(a + block_us, t_end_us)
        hi = int(np.searchsorted(t, b, side="left"))
        yield events[lo:hi], b
        lo, a = hi, b


def iter_motion(source, shape=None, *, fps: float, window_s: float, separator="density", is_signal=None,
                mask: MaskParams | None = None, count: str = "noise", on_motion: str = "skip",
                t_start_s: float | None = None, t_end_s: float | None = None, stats: dict | None = None,
                csv_columns=None) -> Iterator[MotionFrame]:
    """Motion masks and moving-window noise counts of a recording, one :class:`MotionFrame` per step.

    Parameters
    ----------
    source : path or numpy.ndarray
        An event file, events.h5 or any camera file :mod:`evnoise.readers` opens (read block by
        block: memory stays bounded), or an event array
        (:data:`evnoise.EVENT_DTYPE`, sorted).
    shape : (H, W), optional
        Sensor size; required for an array, read from the file otherwise.
    fps : float
        Steps (frames) per second.
    window_s : float
        Count window in seconds (rounded to whole steps).
    separator : DensityFilter, ActivityFilter, "density", "activity" or None
        How signal events are told from noise events (:mod:`evnoise.separation`); ``None``
        treats every event as noise (no motion mask: the naive moving window).
    is_signal : array of bool, optional
        Known labels of an event array (for example the simulator's ground truth); replaces
        the separator.
    mask : MaskParams, optional
        Motion-mask settings.
    count : {"noise", "all"}
        What the moving window counts at unmasked pixels (:data:`COUNT_MODES`).
    on_motion : {"skip", "restart"}
        What a masked step does to a pixel's window (:data:`ON_MOTION`).
    t_start_s, t_end_s : float, optional
        Time span in seconds on the recording's clock (default: from its start, 0 for an
        events.h5 file and the first event for a camera file, to its end: the file's
        ``t_end_us`` attribute, or the last event + 1 µs). Only whole steps are produced.
    stats : dict, optional
        Filled with ``n_events``, ``n_signal`` (as labelled) while iterating.
    csv_columns : str, optional
        Column order of a CSV recording (e.g. ``"x,y,p,t"``).

    Yields
    ------
    MotionFrame
    """
    from ._recordings import recording_blocks, recording_info, recording_start_us
    from .separation import Separator, as_filter

    fps = check_float(fps, "fps", "frames per second")
    window_s = check_float(window_s, "window_s", "seconds")
    if t_start_s is not None:
        t_start_s = check_float(t_start_s, "t_start_s", "seconds", strict=False)
    t_start_us = 0 if t_start_s is None else int(round(t_start_s * 1e6))
    if isinstance(source, np.ndarray):
        if shape is None:
            raise InputError("shape (H, W) is required with an event array")
        shape = check_shape(shape)
        events = check_events(source, shape)
        if events.size == 0:
            raise InputError("the recording has no events")
        t_last = int(events["t"][-1])
        t_file_end = None
        if is_signal is not None:
            is_signal = np.asarray(is_signal, dtype=bool)
            if is_signal.shape != events.shape:
                raise InputError(f"is_signal must have one entry per event ({events.size}), got {is_signal.shape}")
    else:
        if is_signal is not None:
            raise InputError("is_signal can only be given with an event array")
        # any event file
        file_shape, n, t_first, t_last, t_file_end = recording_info(source, shape, csv_columns=csv_columns,
                                                                    shape_argument="shape=(H, W)")
        shape = file_shape
        if t_start_s is None:
            t_start_us = recording_start_us(source, t_first)
            t_start_s = t_start_us * 1e-6
        if n == 0:
            raise InputError(f"{source} has no events: nothing to reconstruct")
    if t_end_s is not None:
        t_end_us = int(round(check_float(t_end_s, "t_end_s", "seconds") * 1e6))
    else:
        t_end_us = max(t_file_end or 0, t_last + 1)
    if t_end_us <= t_start_us:
        raise ParameterError(f"t_end_s must be after t_start_s = {t_start_s:g} s")
    tracker = MotionTracker(shape, step_s=1.0 / fps, window_s=window_s, t_start_us=t_start_us, mask=mask, count=count,
                            on_motion=on_motion)
    block_us = max(tracker.step_us, int(BLOCK_S * 1e6) // tracker.step_us * tracker.step_us)
    if isinstance(source, np.ndarray):
        if is_signal is not None:
            lo = int(np.searchsorted(events["t"], t_start_us, side="left"))
            hi = int(np.searchsorted(events["t"], t_end_us, side="left"))
            blocks = ((events[lo:hi], is_signal[lo:hi], t_end_us),)
        else:
            blocks = _array_blocks(events, t_start_us, t_end_us, block_us)
    else:
        blocks = recording_blocks(source, t_start_us, t_end_us, block_us, shape, csv_columns=csv_columns)
    sep = None
    if is_signal is None and separator is not None:
        sep = Separator(shape, as_filter(separator))
    if stats is not None:
        stats.update(n_events=0, n_signal=0)

    def account(labels):
        if stats is not None:
            stats["n_events"] += int(labels.size)
            stats["n_signal"] += int(np.count_nonzero(labels))

    for block in blocks:
        if len(block) == 3:  # labelled array
            chunk, labels, b = block
            account(labels)
            yield from tracker.push(chunk, labels, t_complete_us=b)
            continue
        chunk, b = block
        if sep is None:
            labels = np.zeros(chunk.size, dtype=bool)
            account(labels)
            yield from tracker.push(chunk, labels, t_complete_us=b)
        else:
            done, labels = sep.push(chunk, t_complete_us=b)
            account(labels)
            yield from tracker.push(done, labels, t_complete_us=b - sep.filter.lookahead_us)
    if sep is not None:
        done, labels = sep.finish()
        account(labels)
        yield from tracker.push(done, labels)
    yield from tracker.finish(t_end_us)


# --------------------------------------------------------------------------------------
# the last static estimate
# --------------------------------------------------------------------------------------
class BackgroundHold:
    """Per-pixel event rates of the static background, held while pixels are under motion.

    Parameters
    ----------
    shape : (H, W)
        Sensor size in pixels.
    min_exposure_s : float
        A pixel's rate is refreshed (``counts / exposure``) only when it has been counted for at
        least this long; otherwise it keeps its last refreshed value.

    Notes
    -----
    :meth:`update` returns rates ``(2, H, W)`` in events per second for *every* pixel. Pixels
    never refreshed yet use their counts so far (``counts / exposure``) when they have any
    exposure, and otherwise the median rate of the refreshed pixels (0 while there are none).
    """

    def __init__(self, shape, *, min_exposure_s: float):
        self.shape = check_shape(shape)
        self.min_exposure_s = check_float(min_exposure_s, "min_exposure_s", "seconds")
        self.rates = np.zeros((2, *self.shape), dtype=np.float64)
        self.seen = np.zeros(self.shape, dtype=bool)

    def update(self, frame: MotionFrame) -> np.ndarray:
        """Refresh from a frame; returns the complete rate image ``(2, H, W)`` (events/s)."""
        fresh = frame.exposure_s >= self.min_exposure_s - 0.5e-6
        if fresh.any():
            self.rates[:, fresh] = frame.counts[:, fresh] / frame.exposure_s[fresh]
            self.seen |= fresh
        out = self.rates.copy()
        if not self.seen.all():
            # never refreshed: the counts so far if any, else the median rate of the refreshed pixels
            fill = np.median(self.rates[:, self.seen], axis=1) if self.seen.any() else np.zeros(2)
            out[:, ~self.seen] = fill[:, None]
            partial = ~self.seen & (frame.exposure_s > 0)
            if partial.any():
                out[:, partial] = frame.counts[:, partial] / frame.exposure_s[partial]
        return out

    @property
    def fresh_fraction(self) -> float:
        return float(self.seen.mean())


def bin_rates(rates, binning: int) -> np.ndarray:
    """Sum float rates or counts ``(2, H, W)`` over ``binning x binning`` blocks (partial edges dropped)."""
    from .radiometry import block_sum

    return block_sum(np.asarray(rates, dtype=np.float64), int(binning), "sensor")


def bin_mask(mask, binning: int) -> np.ndarray:
    """A boolean mask ``(H, W)`` over ``binning x binning`` blocks.

    True where any pixel of the block is (partial edges dropped).
    """
    b = int(binning)
    h, w = mask.shape[0] // b, mask.shape[1] // b
    return mask[:h * b, :w * b].reshape(h, b, w, b).any(axis=(1, 3))


def overlay_rgb(image, mask, signal=None, *, alpha: float = 0.45) -> np.ndarray:
    """An RGB uint8 overlay: the grayscale ``image`` with the motion ``mask`` tinted red.

    ``signal`` (2, h, w) (binned signal counts of the step, optional) marks pixels with ON
    events in yellow and OFF-only pixels in cyan: the event-integration foreground.
    """
    g = np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0)
    rgb = np.repeat(g[..., None], 3, axis=2)
    red = np.array([1.0, 0.1, 0.1])
    rgb[mask] = (1 - alpha) * rgb[mask] + alpha * red
    if signal is not None:
        on = signal[0] > 0
        off = (signal[1] > 0) & ~on
        rgb[on] = [1.0, 0.9, 0.1]
        rgb[off] = [0.1, 0.9, 1.0]
    return np.round(rgb * 255).astype(np.uint8)
