"""Photon noise for frame-driven event emulators (v2e, ESIM-style loops), frame interval by interval.

An emulator of this kind is driven one frame at a time with ``generate_events(frame, t_s)``
and returns the events since the previous frame as an ``N x 4`` float array
``[t_s, x, y, p]`` with ``p = +1`` (ON) or ``-1`` (OFF), or ``None`` when there are none; the
first call only initialises it. :class:`EmulatorNoise` wraps such an object, exposes the same
method, and merges evnoise's photon-noise events of the same interval into the rows.

Noise and signal are independent here: the emulator's pixel state does not see evnoise's noise
events, nor the other way round. For the coupled model (a noise event resets the pixel's
reference level) simulate the whole scene with :func:`evnoise.simulate_video`.
"""

from __future__ import annotations

import math

import numpy as np

from .._budget import check_allocation, memory_budget
from .._checks import as_generator, check_lux, check_params, resolve_threads
from .._engine import check_span
from ..errors import InputError, ParameterError
from ..events import EVENT_DTYPE

__all__ = ["EmulatorNoise", "noise_rows", "merge_rows", "merge_with_positions", "interleave"]

MAX_T_S = float(1 << 62) * 1e-6  #: largest |t_frame| in seconds (2**62 microseconds): room for differences in int64
#: peak memory per noise event of a frame interval: the kernel's columns, the sorted events, the float64 rows and their
#: merge (measured ~55 bytes), and the copies v2e's writers make (~190 bytes with dvs_h5 and AEDAT 2)
BYTES_PER_NOISE_EVENT = 256


def _seconds_to_us(t_s, name: str = "t_frame") -> int:
    try:
        t = float(t_s)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a time in seconds, got {t_s!r}") from None
    if not math.isfinite(t):
        raise ParameterError(f"{name} must be a finite time in seconds, got {t_s!r}")
    if abs(t) > MAX_T_S:
        raise ParameterError(f"{name} must be a time in seconds within +-{MAX_T_S:.4g} s (2**62 microseconds), "
                             f"got {t_s!r}")
    return int(round(t * 1e6))


def noise_rows(noise) -> np.ndarray:
    """evnoise events as ``N x 4`` float64 rows ``[t_s, x, y, p]`` with ``p = +1`` (ON) / ``-1`` (OFF).

    Parameters
    ----------
    noise : numpy.ndarray
        Events of :data:`~evnoise.events.EVENT_DTYPE` (``t`` in integer microseconds, ``p`` 1 for ON
        and 0 for OFF).

    Returns
    -------
    numpy.ndarray
        float64 array of shape ``(N, 4)``: time in seconds, ``x``, ``y`` and polarity ``+1`` / ``-1``,
        in the order of ``noise``.
    """
    out = np.empty((noise.size, 4), dtype=np.float64)
    out[:, 0] = noise["t"] * 1e-6
    out[:, 1] = noise["x"]
    out[:, 2] = noise["y"]
    out[:, 3] = 2.0 * noise["p"] - 1.0
    return out


def merge_rows(signal, noise):
    """Insert ``noise`` rows (sorted by time) into ``signal`` rows without changing the signal rows.

    The signal rows keep their values and their order, whatever it is (an emulator may emit a
    few out of order); each noise row goes after every signal row whose time, or any earlier
    signal row's time, is ``<=`` its own. When the signal rows are sorted by time, so is the
    result.

    Parameters
    ----------
    signal : array_like or None
        The emulator's rows ``[t_s, x, y, p]``, shape ``(N, 4)``, or ``None`` for no rows.
    noise : array_like
        Noise rows ``[t_s, x, y, p]`` sorted by time (as :func:`noise_rows` makes them); any
        array with a multiple of 4 values, reshaped to ``(M, 4)``.

    Returns
    -------
    numpy.ndarray or None
        float64 array of shape ``(N + M, 4)``, or ``None`` when both are empty.

    Raises
    ------
    InputError
        If ``signal`` is not an ``N x 4`` array.
    """
    return merge_with_positions(signal, noise)[0]


def merge_with_positions(signal, noise):
    """:func:`merge_rows` and the positions of the noise rows in the result (``(rows, positions)``), so that
    other per-row data (an emulator's own conversion of its rows, labels) can be interleaved the same way
    with :func:`interleave`.

    Parameters
    ----------
    signal : array_like or None
        The emulator's rows ``[t_s, x, y, p]``, shape ``(N, 4)``, or ``None`` for no rows.
    noise : array_like
        Noise rows ``[t_s, x, y, p]`` sorted by time, reshaped to ``(M, 4)``.

    Returns
    -------
    rows : numpy.ndarray or None
        The merged float64 rows, shape ``(N + M, 4)``, or ``None`` when both are empty.
    positions : numpy.ndarray
        Integer indices, one per noise row in its order, of that row in ``rows``.
    """
    noise = np.asarray(noise, dtype=np.float64).reshape(-1, 4)
    n_n = noise.shape[0]
    if signal is not None:
        signal = np.asarray(signal)
        if signal.ndim != 2 or signal.shape[1] != 4:
            raise InputError(f"the emulator returned events of shape {signal.shape}; expected N x 4 [t, x, y, p]")
    if signal is None or signal.shape[0] == 0:
        return (noise if n_n else None), np.arange(n_n)
    running_max = np.maximum.accumulate(signal[:, 0].astype(np.float64))
    pos = np.searchsorted(running_max, noise[:, 0], side="right") + np.arange(n_n)
    return interleave(signal, noise, pos, np.float64), pos


def interleave(signal, noise, positions, dtype=None):
    """Rows of ``signal`` in their order with the rows of ``noise`` at ``positions`` of the result
    (first axis; the other axes must agree).

    Parameters
    ----------
    signal : array_like
        Rows that fill the positions not in ``positions``, in their order.
    noise : array_like
        Rows placed at ``positions``, one per position.
    positions : array_like of int
        Indices into the result, along the first axis, of the ``noise`` rows (as
        :func:`merge_with_positions` returns them).
    dtype : numpy.dtype, optional
        Type of the result; by default the common type of ``signal`` and ``noise``.

    Returns
    -------
    numpy.ndarray
        ``len(signal) + len(noise)`` rows.
    """
    signal, noise = np.asarray(signal), np.asarray(noise)
    n = signal.shape[0] + noise.shape[0]
    out = np.empty((n, *signal.shape[1:]), dtype=dtype or np.result_type(signal, noise))
    is_signal = np.ones(n, dtype=bool)
    is_signal[positions] = False
    out[is_signal] = signal
    out[positions] = noise
    return out


class EmulatorNoise:
    """Wrap a frame-driven emulator and add evnoise's photon noise to its events.

    Parameters
    ----------
    emulator : object
        Anything with ``generate_events(frame, t_s)`` returning ``N x 4`` rows
        ``[t_s, x, y, +-1]`` or ``None`` (v2e's ``EventEmulator`` and the ESIM-style example's
        emulator). It is called first, with the frame and time unchanged.
    params : NoiseParams or str
        Noise model parameters, or the name / path of a preset.
    frame_to_lux : callable, optional
        Maps a frame to illuminance in lux, shape ``(H, W)`` indexed ``[y, x]``; by default the
        frames are already lux.
    rng : numpy.random.Generator, int or None
        Randomness of the noise (threshold mismatch and events). The same seed and the same
        frames give the same output.
    threads : int, optional
        Worker threads of the noise simulator.

    Notes
    -----
    The noise of the interval between two frames is simulated under the illuminance of the
    *earlier* frame (sample-and-hold, exact for piecewise-constant light); timestamps are
    integer microseconds, returned in seconds. An interval whose noise would not fit in memory
    (frame times in another unit than seconds) is a :class:`~evnoise.errors.ParameterError`
    before the emulator sees the frame. Attribute access the wrapper does not define
    (``reset`` excepted) goes to the wrapped emulator, and so does setting an attribute the
    emulator has (other than the wrapper's :attr:`OWN_ATTRIBUTES` and private names).
    """

    def __init__(self, emulator, params, frame_to_lux=None, rng=None, *, threads: int | None = None):
        if not callable(getattr(emulator, "generate_events", None)):
            raise ParameterError("emulator must have a generate_events(frame, t_s) method, "
                                 f"got {type(emulator).__name__}")
        self.emulator = emulator
        self.params = check_params(params)
        self._frame_to_lux = frame_to_lux
        self._gen = as_generator(rng)
        resolve_threads(threads)  # checked here, not at the second frame
        self._threads = threads
        self._stream = None
        self._lux = None
        self.signal_count = 0  # events the emulator returned, in total
        self.noise_count = 0  # photon-noise events added, in total

    def __getattr__(self, name):
        # only called for names not found on the wrapper: hand them to the emulator
        if name == "emulator":
            raise AttributeError(name)
        return getattr(self.emulator, name)

    #: public attributes of the wrapper itself; others that the emulator has are set on the emulator
    OWN_ATTRIBUTES = frozenset({"emulator", "params", "signal_count", "noise_count"})

    def __setattr__(self, name, value):
        # v2e.py sets ``emulator.output_width`` on what it believes is the emulator
        emulator = self.__dict__.get("emulator")
        if (emulator is not None and not name.startswith("_") and name not in self.OWN_ATTRIBUTES
                and not hasattr(type(self), name) and hasattr(emulator, name)):
            setattr(emulator, name, value)
        else:
            object.__setattr__(self, name, value)

    def frame_lux(self, frame) -> np.ndarray:
        """The illuminance (lux, float64 ``(H, W)``) that the wrapper uses for ``frame``.

        Parameters
        ----------
        frame : array_like
            A frame as passed to :meth:`generate_events`; mapped by ``frame_to_lux`` when one was given.

        Returns
        -------
        numpy.ndarray
            Illuminance in lux, float64 of shape ``(H, W)``, checked to be finite and non-negative.
        """
        lux = frame if self._frame_to_lux is None else self._frame_to_lux(frame)
        return check_lux(lux, name="frame illuminance")

    def reset(self):
        """Reset the emulator (when it has ``reset()``) and start a new noise stream at the next frame."""
        if callable(getattr(self.emulator, "reset", None)):
            self.emulator.reset()
        self.restart_noise()

    def restart_noise(self):
        """Start a new noise stream at the next frame (the emulator is left as it is)."""
        self._stream = None
        self._lux = None

    def generate_events(self, new_frame, t_frame):
        """The emulator's events for this frame plus the photon noise since the previous frame.

        Parameters
        ----------
        new_frame : array_like, shape (H, W)
            The frame, passed to the emulator unchanged.
        t_frame : float
            Its time in seconds.

        Returns
        -------
        numpy.ndarray or None
            float64 ``N x 4`` rows ``[t_s, x, y, p]`` (``p`` = +1 ON, -1 OFF): the emulator's
            rows unchanged and in their order, with the noise rows of ``[t_previous, t_frame)``
            inserted by time; ``None`` when there are no events (e.g. on the first frame).
        """
        from ..stream import NoiseStream

        lux = self.frame_lux(new_frame)
        t_us = _seconds_to_us(t_frame)
        stream = self._stream
        if stream is not None:
            if lux.shape != stream.shape:
                raise InputError(f"frame has shape {lux.shape}, but earlier frames had {stream.shape}")
            if t_us < stream.t_us:
                raise ParameterError(f"t_frame={t_frame!r} s is before the previous frame's time "
                                     f"{stream.t_us * 1e-6!r} s")
            check_span(stream.t_start_us, t_us - stream.t_start_us, self.params.trial_us, "time since the first frame")
            self._check_interval(t_us - stream.t_us)
        signal = self._emulate(new_frame, t_frame)
        if stream is None:
            self._stream = NoiseStream(lux.shape, self.params, rng=self._gen, t_start_us=t_us, threads=self._threads)
            noise = np.empty(0, dtype=EVENT_DTYPE)
        else:
            noise = stream.advance(self._lux, t_us)
        self._lux = lux
        if signal is not None:
            self.signal_count += int(np.shape(signal)[0])
        self.noise_count += int(noise.size)
        return self._merge(signal, noise)

    def _check_interval(self, span_us: int) -> None:
        """Refuse an interval whose noise cannot fit in memory (a frame time in another unit than seconds), before the
        emulator sees the frame: against the bound of one event per pixel and trial first (no computation), and where
        that bound passes the budget against the expected count at the earlier frame's light (a closed form over the
        frame, seconds on a large one: only for such long intervals)."""
        budget = memory_budget()
        bound = self._lux.size * (span_us / self.params.trial_us + 1.0)
        if budget is None or bound * BYTES_PER_NOISE_EVENT <= budget:
            return
        from ..rates import expected_rate

        expected = float(expected_rate(self._lux, self.params).sum()) * span_us * 1e-6
        check_allocation((expected + 8.0 * math.sqrt(expected)) * BYTES_PER_NOISE_EVENT,
                         f"the photon noise of the {span_us * 1e-6:.6g} s since the previous frame "
                         f"({expected:.3g} events expected)", hint="is t_frame in seconds?", error=ParameterError)

    #: what :meth:`generate_events` calls for the emulator's events: None for ``emulator.generate_events``, or a
    #: function ``(frame, t_s) -> rows`` (an emulator subclass that adds the noise itself calls its base method)
    _generate = None

    def _emulate(self, new_frame, t_frame):
        """The emulator's events of the frame (a hook: the v2e wrapper watches v2e's file writers here)."""
        generate = self._generate if self._generate is not None else self.emulator.generate_events
        return generate(new_frame, t_frame)

    def _merge(self, signal, noise):
        """The rows :meth:`generate_events` returns: the emulator's rows with ``noise`` (evnoise events) merged in."""
        return merge_rows(signal, noise_rows(noise))
