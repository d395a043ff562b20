"""Separate signal events (caused by intensity changes) from noise events in a time-sorted stream.

The Noise2Image paper (§4.1, §5.3) reconstructs the static background of a dynamic recording
from its *noise* events, after an event denoiser has taken out the *signal* events of the moving
parts. Two classic spatio-temporal correlation filters are implemented here from their published
descriptions; both return a boolean ``is_signal`` per event (True = keep as signal, False = noise):

:class:`DensityFilter` (YNoise-style event density; Feng et al., "Event density based denoising
    method for dynamic vision sensor", Appl. Sci. 10, 2024, 2020; used through the E-MLB
    benchmark by the paper). The density of an event is the number of other events in its
    spatio-temporal neighbourhood: the ``(2 r + 1) x (2 r + 1)`` pixels around it (its own pixel
    included) and the time window ``[t - window_us, t + lookahead_us]``. Events whose density
    reaches ``threshold`` are signal. Moving edges fire many neighbouring pixels within a short
    time, photon noise fires pixels independently at a few events per second, so the density
    separates them. Unlike implementations that keep only the last timestamp of each pixel, the
    density here counts *every* event in the window (a pixel crossed by a strong edge fires
    several times), kept exact by a sliding window over the sorted stream. ``lookahead_us > 0``
    makes the window two-sided (non-causal): the first events of an edge then see the events that
    follow them. ``polarity="same"`` counts only events of the event's own polarity.

:class:`ActivityFilter` (the background-activity filter, BAF, also called the nearest-neighbour
    filter; Delbruck 2008). An event is signal if at least one *other* pixel within ``radius_px``
    fired within the last ``window_us`` microseconds; each pixel remembers the time of its last
    event. Causal, one timestamp per pixel of state.

Both run as Numba kernels (:mod:`evnoise._kernels.filters`) over sorted events. The streaming
:class:`Separator` carries the per-pixel state (and, for the density filter, the events of the
current window) from one chunk to the next, so the labels do not depend on how a stream is cut
into chunks: pushing the events in any number of pieces gives exactly the labels of one call on
the whole stream.

Examples
--------
>>> is_signal = density_filter(events, (480, 640), radius_px=2, window_us=5_000, threshold=3)  # doctest: +SKIP
>>> noise = events[~is_signal]                                                                  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from ._checks import check_int, path_text
from ._recordings import recording_blocks, recording_info, recording_start_us
from .errors import InputError, ParameterError
from .events import check_events, check_shape, empty_events

__all__ = [
    "DensityFilter",
    "ActivityFilter",
    "Separator",
    "density_filter",
    "activity_filter",
    "separate_events",
    "separation_scores",
    "separate_file",
    "FILTERS",
]

#: Names accepted where a filter can be given by name (``"density"``, ``"activity"``).
FILTERS = ("density", "activity")

_MAX_US = 10**12  # about 11.6 days: a generous bound on windows, keeps int64 time arithmetic safe

#: filter settings are whole numbers; 1e4 (a float) is taken for 10,000 microseconds
_whole = partial(check_int, integral_floats=True)


@dataclass(frozen=True)
class DensityFilter:
    """Parameters of the YNoise-style spatio-temporal density filter (see the module docstring).

    Parameters
    ----------
    radius_px : int
        Half-side of the square neighbourhood in pixels: ``radius_px = 1`` is the 3 x 3
        neighbourhood (YNoise's ``L = 3``), ``0`` the pixel alone.
    window_us : int
        How far back the time window reaches, in microseconds.
    threshold : int
        Minimum number of other events in the neighbourhood and window for an event to be
        signal (``>= 1``).
    lookahead_us : int
        How far forward the time window reaches, in microseconds (0: causal, as YNoise). A
        streaming separator holds events back until ``lookahead_us`` of later events are known.
    polarity : {"any", "same"}
        Count events of both polarities, or only those of the event's own polarity.

    Notes
    -----
    The defaults suit evnoise's presets in the low-light regime where noise events carry the
    image. There a pixel fires about one signal event per edge that crosses it (the log
    contrast between 0 and 20 lux is only about two thresholds), so an edge shows up as a *line*
    of near-simultaneous events of one polarity rather than as a burst at one pixel, while photon
    noise fires each pixel independently, at most about 1.3 ON (0.6 OFF) events per second. The
    5 x 5 neighbourhood and the 10 ms window then hold on average at most
    ``25 * 1.3 Hz * 0.01 s = 0.33`` noise events of the same polarity, and a density of 3 or more
    arises by chance for about 0.4 % of noise events. ``benchmarks/bench_dynamic.py`` compares
    settings on scenes with ground truth. Sensors with a higher noise rate or a slower pixel
    response need other values (YNoise itself is usually run with a 3 x 3 neighbourhood, a 10 ms
    causal window and a threshold of 2).
    """

    radius_px: int = 2
    window_us: int = 5_000
    threshold: int = 3
    lookahead_us: int = 5_000
    polarity: str = "same"

    def __post_init__(self):
        object.__setattr__(self, "radius_px", _whole(self.radius_px, "radius_px", 0, 255, "pixels"))
        object.__setattr__(self, "window_us", _whole(self.window_us, "window_us", 0, _MAX_US, "microseconds"))
        object.__setattr__(self, "lookahead_us",
                           _whole(self.lookahead_us, "lookahead_us", 0, _MAX_US, "microseconds"))
        object.__setattr__(self, "threshold", _whole(self.threshold, "threshold", 1, 2**62, "events"))
        if self.polarity not in ("any", "same"):
            raise ParameterError(f"polarity must be 'any' or 'same', got {self.polarity!r}")


@dataclass(frozen=True)
class ActivityFilter:
    """Parameters of the background-activity filter (see the module docstring).

    Parameters
    ----------
    radius_px : int
        Neighbourhood half-side in pixels (1: the 8 neighbours; the pixel itself never counts).
    window_us : int
        An event is signal if a neighbour fired at most this many microseconds before it.
    """

    radius_px: int = 1
    window_us: int = 5_000

    def __post_init__(self):
        object.__setattr__(self, "radius_px", _whole(self.radius_px, "radius_px", 1, 255, "pixels"))
        object.__setattr__(self, "window_us", _whole(self.window_us, "window_us", 0, _MAX_US, "microseconds"))

    @property
    def lookahead_us(self) -> int:
        return 0


def as_filter(method, **params):
    """A filter object from a filter object or a name in :data:`FILTERS` plus keyword parameters."""
    if isinstance(method, (DensityFilter, ActivityFilter)):
        if params:
            raise ParameterError(f"give parameters either in the filter object or as keywords, not both: "
                                 f"{sorted(params)}")
        return method
    if method == "density":
        return DensityFilter(**params)
    if method == "activity":
        return ActivityFilter(**params)
    raise ParameterError(f"method must be one of {FILTERS} or a DensityFilter/ActivityFilter, got {method!r}")


class Separator:
    """Label a time-sorted event stream chunk by chunk, with results independent of chunking.

    Parameters
    ----------
    shape : (H, W)
        Sensor size in pixels.
    method : DensityFilter, ActivityFilter or {"density", "activity"}
        The filter (with a name, ``params`` are its keyword parameters).
    **params
        Keyword parameters of the named filter.

    Notes
    -----
    :meth:`push` returns the events it could decide, with their labels, in stream order; with a
    two-sided density window (``lookahead_us > 0``) the events of the last ``lookahead_us`` are
    held back until later events (or :meth:`finish`) complete their window. Concatenating
    everything :meth:`push` and :meth:`finish` return gives every event exactly once, in order.
    Memory: one int32 count per pixel (and polarity) plus the events of one window for the
    density filter; one int64 timestamp per pixel for the activity filter.

    Examples
    --------
    >>> sep = Separator((480, 640), "density", window_us=5_000)      # doctest: +SKIP
    >>> for chunk in chunks:                                         # doctest: +SKIP
    ...     done, is_signal = sep.push(chunk)
    ...     write(done[~is_signal])
    >>> done, is_signal = sep.finish()                               # doctest: +SKIP
    """

    def __init__(self, shape, method="density", **params):
        self.shape = check_shape(shape)
        self.filter = as_filter(method, **params)
        height, width = self.shape
        self._last_t = None  # last time pushed
        self._t_complete = None
        self._finished = False
        from ._budget import check_allocation

        if isinstance(self.filter, DensityFilter):
            channels = 2 if self.filter.polarity == "same" else 1
            check_allocation(channels * height * width * 4, f"the filter's counts of the {width}x{height} sensor",
                             error=InputError)
            self._counts = np.zeros((channels, height, width), dtype=np.int32)
            self._buf = empty_events(0)
            self._lo = self._hi = self._next = 0
        else:
            check_allocation(height * width * 8, f"the filter's last event times of the {width}x{height} sensor",
                             error=InputError)
            self._last = np.full((height, width), np.iinfo(np.int64).min // 2, dtype=np.int64)

    @property
    def pending(self) -> int:
        """Number of pushed events not decided yet (held back for their look-ahead window)."""
        if isinstance(self.filter, DensityFilter):
            return self._buf.size - self._next
        return 0

    def push(self, events, *, t_complete_us: int | None = None):
        """Add the next chunk of events; returns ``(decided_events, is_signal)``.

        Parameters
        ----------
        events : numpy.ndarray
            :data:`evnoise.EVENT_DTYPE`, sorted by time, not earlier than the previous chunk.
        t_complete_us : int, optional
            A promise that every event with ``t < t_complete_us`` has now been pushed (for
            example the end of the time block just read from a file); lets the density filter
            decide events up to ``t_complete_us - lookahead_us`` instead of only up to the last
            pushed timestamp.
        """
        if self._finished:
            raise InputError("this Separator has finished; make a new one for another stream")
        events = check_events(events, self.shape)
        if events.size:
            if self._last_t is not None and events["t"][0] < self._last_t:
                raise InputError(f"events are not sorted across chunks: t = {int(events['t'][0])} after "
                                 f"t = {self._last_t}")
            if self._t_complete is not None and events["t"][0] < self._t_complete:
                raise InputError(f"event at t = {int(events['t'][0])} us arrives after t_complete_us = "
                                 f"{self._t_complete} was promised")
            self._last_t = int(events["t"][-1])
        if t_complete_us is not None:
            t_complete_us = int(t_complete_us)
            if self._last_t is not None and t_complete_us <= self._last_t:
                raise InputError(f"t_complete_us = {t_complete_us} must be after the last pushed event "
                                 f"(t = {self._last_t})")
            self._t_complete = t_complete_us if self._t_complete is None else max(t_complete_us, self._t_complete)
        return self._run(events, final=False)

    def finish(self):
        """End of the stream: decide the held-back events; returns ``(decided_events, is_signal)``."""
        if self._finished:
            return empty_events(0), np.zeros(0, dtype=bool)
        out = self._run(empty_events(0), final=True)
        self._finished = True
        return out

    def _run(self, events, final: bool):
        from ._kernels.filters import activity_pass, density_pass

        f = self.filter
        if isinstance(f, ActivityFilter):
            is_signal = np.zeros(events.size, dtype=bool)
            if events.size:
                activity_pass(events["t"], events["x"], events["y"], self._last, f.radius_px, f.window_us, is_signal)
            return events, is_signal
        buf = np.concatenate([self._buf, events]) if events.size else self._buf
        n = buf.size
        if n == 0:
            return empty_events(0), np.zeros(0, dtype=bool)
        # the latest time up to which windows are complete
        if self._t_complete is not None and (self._last_t is None or self._t_complete > self._last_t):
            t_complete = self._t_complete
        else:
            t_complete = self._last_t  # more events may still come at this very timestamp
        density = np.empty(n, dtype=np.int64)
        is_signal = np.zeros(n, dtype=bool)
        t = np.ascontiguousarray(buf["t"])
        x = np.ascontiguousarray(buf["x"])
        y = np.ascontiguousarray(buf["y"])
        p = np.ascontiguousarray(buf["p"])
        start = self._next
        lo, hi, nxt = density_pass(t, x, y, p, self._counts, self._lo, self._hi, start, np.int64(t_complete),
                                   final, np.int64(f.window_us), np.int64(f.lookahead_us), f.radius_px,
                                   f.polarity == "same", f.threshold, density, is_signal)
        decided = buf[start:nxt]
        labels = is_signal[start:nxt]
        # keep the events still inside the window, and the undecided ones
        keep = min(lo, nxt)
        self._buf = buf[keep:].copy()
        self._lo, self._hi, self._next = lo - keep, hi - keep, nxt - keep
        return decided, labels


def _run_whole(events, shape, flt):
    sep = Separator(shape, flt)
    events = check_events(events, sep.shape)
    parts = [sep.push(events), sep.finish()]
    return np.concatenate([p[1] for p in parts]) if events.size else np.zeros(0, dtype=bool)


def density_filter(events, shape, *, radius_px: int = 2, window_us: int = 5_000, threshold: int = 3,
                   lookahead_us: int = 5_000, polarity: str = "same") -> np.ndarray:
    """Label events with the YNoise-style density filter (True = signal); see :class:`DensityFilter`.

    Parameters
    ----------
    events : numpy.ndarray
        :data:`evnoise.EVENT_DTYPE`, sorted by time.
    shape : (H, W)
        Sensor size in pixels.
    radius_px : int
        Half-side of the square neighbourhood in pixels (0 .. 255; 0: the pixel alone), as in
        :class:`DensityFilter`.
    window_us : int
        How far back the time window reaches, in microseconds.
    threshold : int
        Minimum number of other events in the neighbourhood and window for an event to be signal (``>= 1``).
    lookahead_us : int
        How far forward the time window reaches, in microseconds (0: causal).
    polarity : {"any", "same"}
        Count events of both polarities, or only those of the event's own polarity.

    Returns
    -------
    numpy.ndarray of bool
        ``is_signal``, one entry per event.

    Raises
    ------
    InputError
        Events not sorted by time, with a wrong dtype, or outside the sensor.
    ParameterError
        A parameter out of range.
    """
    flt = DensityFilter(radius_px=radius_px, window_us=window_us, threshold=threshold, lookahead_us=lookahead_us,
                        polarity=polarity)
    return _run_whole(events, shape, flt)


def activity_filter(events, shape, *, radius_px: int = 1, window_us: int = 5_000) -> np.ndarray:
    """Label events with the background-activity filter (True = signal); see :class:`ActivityFilter`.

    Parameters
    ----------
    events : numpy.ndarray
        :data:`evnoise.EVENT_DTYPE`, sorted by time.
    shape : (H, W)
        Sensor size in pixels.
    radius_px : int
        Neighbourhood half-side in pixels (the event's own pixel does not count).
    window_us : int
        Support window in microseconds.

    Returns
    -------
    numpy.ndarray of bool
        ``is_signal``, one entry per event.
    """
    return _run_whole(events, shape, ActivityFilter(radius_px=radius_px, window_us=window_us))


def separate_events(events, shape, method="density", **params):
    """Split events into ``(signal, noise)`` arrays with a filter (see :class:`Separator`).

    Parameters
    ----------
    events : numpy.ndarray
        :data:`evnoise.EVENT_DTYPE`, sorted by time.
    shape : (H, W)
        Sensor size in pixels.
    method : DensityFilter, ActivityFilter or {"density", "activity"}
        The filter: a filter object, or a name whose keyword parameters are ``params``.
    **params
        Keyword parameters of the named filter (:class:`DensityFilter`, :class:`ActivityFilter`); none with a
        filter object.

    Returns
    -------
    signal : numpy.ndarray
        The events labelled signal, in their order.
    noise : numpy.ndarray
        The events labelled noise, in their order.
    """
    flt = as_filter(method, **params)
    events = check_events(events, shape)
    is_signal = _run_whole(events, shape, flt)
    return events[is_signal], events[~is_signal]


def separation_scores(predicted, truth) -> dict:
    """Precision and recall of signal *and* of noise labels against ground truth.

    Parameters
    ----------
    predicted, truth : array_like of bool
        ``is_signal`` per event from a filter and from the simulator
        (:func:`evnoise.simulate_video` with ``return_labels=True``).

    Returns
    -------
    dict
        ``signal_precision``, ``signal_recall``, ``noise_precision``, ``noise_recall``,
        ``accuracy``, and the counts ``n_signal``, ``n_noise`` (true) and ``n_predicted_signal``.
        A ratio with an empty denominator is NaN.
    """
    pred = np.asarray(predicted, dtype=bool)
    true = np.asarray(truth, dtype=bool)
    if pred.shape != true.shape or pred.ndim != 1:
        raise InputError(f"predicted and truth must be 1-D of equal length, got {pred.shape} and {true.shape}")

    def ratio(a, b):
        return float(a) / float(b) if b else math.nan

    tp = int(np.count_nonzero(pred & true))
    tn = int(np.count_nonzero(~pred & ~true))
    n_pred = int(np.count_nonzero(pred))
    n_true = int(np.count_nonzero(true))
    return {
        "signal_precision": ratio(tp, n_pred),
        "signal_recall": ratio(tp, n_true),
        "noise_precision": ratio(tn, pred.size - n_pred),
        "noise_recall": ratio(tn, pred.size - n_true),
        "accuracy": ratio(tp + tn, pred.size),
        "n_signal": n_true,
        "n_noise": pred.size - n_true,
        "n_predicted_signal": n_pred,
    }


#: Time span of the blocks read from a file at a time, in microseconds.
FILE_BLOCK_US = 250_000


def separate_file(path, signal_out=None, noise_out=None, method="density", *, overwrite: bool = False,
                  progress: bool = False, sensor=None, csv_columns=None, **params) -> dict:
    """Split an event file into signal and noise files, streaming (bounded memory).

    Parameters
    ----------
    path : path
        Input: events.h5 or any camera file :mod:`evnoise.readers` opens.
    signal_out, noise_out : path, optional
        Output files for the events labelled signal and noise (at least one); the suffix
        decides the format (``.h5``, ``.aedat4``, ``.raw``, ``.dat``, ``.es``, ``.csv``).
        Written atomically (temporary name, renamed on success), both or neither. An events.h5 output of a
        recording whose clock does not start near 0 stores it as ``/t_offset``.
    sensor : str or (int, int), optional
        Sensor size ``"WxH"`` for inputs whose header has none.
    csv_columns : str, optional
        Column order of a CSV input (e.g. ``"x,y,p,t"``).
    method, **params
        The filter, as in :class:`Separator`.
    overwrite : bool
        Replace existing output files.
    progress : bool
        Show a progress bar (seconds of recording).

    Returns
    -------
    dict
        ``n_events``, ``n_signal``, ``n_noise``, ``filter`` (the filter object).
    """
    import contextlib

    from .io import EventFileWriter, open_output_path, output_format
    from .readers import parse_sensor

    flt = as_filter(method, **params)
    if signal_out is None and noise_out is None:
        raise ParameterError("give at least one output: signal_out or noise_out")
    named = [(name, Path(p)) for name, p in (("signal_out", signal_out), ("noise_out", noise_out)) if p is not None]
    outs = [out for _, out in named]
    if len(outs) == 2 and outs[0].resolve() == outs[1].resolve():
        raise ParameterError(f"signal and noise outputs are the same file: {outs[0]}")
    for name, out in named:
        if out.resolve() == Path(path).resolve():
            raise ParameterError(f"the output {out} is the input file")
        output_format(out, flag=name)
        open_output_path(out, overwrite=overwrite, what="event file")
    user = parse_sensor(sensor)
    shape, n, t_first, t_last, t_end_attr = recording_info(path, user, csv_columns=csv_columns)
    t_end = max(t_end_attr or 0, (t_last + 1) if n else 0)
    t_begin = recording_start_us(path, t_first)
    t_begin = min(t_begin, t_first) if n else t_begin
    t_offset = t_begin // 1_000_000 * 1_000_000  # whole seconds: a camera clock that reads 1.6e15 us
    sep = Separator(shape, flt)
    attrs = {"source": path_text(path), "separator": {"name": type(flt).__name__, **dataclasses.asdict(flt)}}
    counts = {"n_events": 0, "n_signal": 0, "n_noise": 0}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=(t_end - t_begin) * 1e-6, desc="separate", unit="s", leave=False,
                   bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s [{elapsed}<{remaining}]")
    with contextlib.ExitStack() as stack:
        writers = {}
        for key, out in (("signal", signal_out), ("noise", noise_out)):
            if out is not None:
                writers[key] = stack.enter_context(EventFileWriter(out, shape, {**attrs, "kind": key},
                                                                   overwrite=overwrite, t_end_us=t_end,
                                                                   t_offset_us=t_offset))

        def emit(done, labels):
            counts["n_events"] += int(labels.size)
            counts["n_signal"] += int(np.count_nonzero(labels))
            if "signal" in writers:
                writers["signal"].write(done[labels])
            if "noise" in writers:
                writers["noise"].write(done[~labels])

        if n:
            blocks = recording_blocks(path, t_begin, t_end, FILE_BLOCK_US, shape, csv_columns=csv_columns,
                                      skip_empty=True)  # long gaps cost nothing
            for chunk, b in blocks:
                emit(*sep.push(chunk, t_complete_us=b))
                if bar is not None:
                    bar.update((min(b, t_end) - t_begin) * 1e-6 - bar.n)
            emit(*sep.finish())
        if counts["n_events"] != n:  # the outputs (still temporary) are removed: they would look complete
            raise InputError(f"{path}: {n:,} events, but {counts['n_events']:,} of them were read in time order: its "
                             f"timestamps decrease somewhere (a recording's must not); sort it by time first")
        # closed here, both or neither: when one output cannot be finished (a full disk), one already renamed is
        # removed again (alone it would look like a finished run); the rest are discarded by the stack
        finished = []
        try:
            for writer in writers.values():
                finished.append(writer.close())
        except BaseException:
            for done in finished:
                try:
                    os.unlink(done)
                except OSError:
                    pass
            raise
    if bar is not None:
        bar.close()
    counts["n_noise"] = counts["n_events"] - counts["n_signal"]
    counts["filter"] = flt
    return counts
