"""evnoise's photon noise inside v2e: wrap an ``EventEmulator`` and keep driving it as before.

v2e (https://github.com/SensorsINI/v2e, not on PyPI) is not imported: the wrapper relies only on
the interface its ``EventEmulator`` documents,

* ``generate_events(new_frame, t_frame)``: ``new_frame`` a luma frame ``[height, width]`` with
  grey levels 0-255 (white = 255), ``t_frame`` its time in seconds; the first call initialises
  the pixels and returns ``None``; later calls return the events since the previous frame as an
  ``N x 4`` array ``[t, x, y, p]`` (``t`` seconds, ``x`` column, ``y`` row, ``p`` = +1 ON / -1 OFF),
  or ``None`` when there are none;
* ``reset()`` (optional): the next frame initialises the pixels again.

Grey levels to lux follow v2e's own convention: v2e takes the logarithm of the grey level
itself (``lin_log``: linear below 20, ``ln`` above), i.e. it treats luma as *linear* in
intensity with no gamma decoding, so the wrapper maps grey ``g`` to ``white_lux * g / 255``.
With v2e's ``--hdr`` input (frames already ``ln`` of the grey level, white = ``ln 255``) pass
``log_input=True`` (detected from the emulator's ``log_input`` attribute when present).

Turn v2e's own noise off (``shot_noise_rate_hz=0``, ``leak_rate_hz=0``; the wrapper warns when
they are not): evnoise's calibrated model replaces the hand-set rates.
"""

from __future__ import annotations

import warnings

import numpy as np

from .._checks import check_positive
from ..errors import InputError
from .frames import EmulatorNoise

__all__ = ["PhotonNoise", "grey_to_lux"]

WHITE_GREY = 255.0


def grey_to_lux(frame, white_lux: float, *, log_input: bool = False) -> np.ndarray:
    """Illuminance (lux, float64) of a v2e luma frame: ``white_lux * grey / 255``.

    ``log_input``: the frame holds ``ln(grey)`` (v2e's ``--hdr`` input) instead of the grey level.
    """
    white_lux = check_positive(white_lux, "white_lux", "lux")
    try:
        arr = np.asarray(frame, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("the frame must be a numeric (height, width) array of grey levels") from None
    if arr.ndim != 2:
        raise InputError(f"the frame must be a (height, width) luma array, got shape {arr.shape}")
    if arr.size and not np.isfinite(arr).all():
        raise InputError("the frame contains NaN or Inf grey levels")
    if log_input:
        if arr.size and arr.max() > 700:
            raise InputError(f"log_input frame values must be ln(grey level), got up to {arr.max():g}")
        arr = np.exp(arr)
    elif arr.size and arr.min() < 0:
        raise InputError(f"grey levels must be >= 0, got {arr.min():g}")
    return arr * (white_lux / WHITE_GREY)


class PhotonNoise(EmulatorNoise):
    """A v2e ``EventEmulator`` with evnoise's photon noise added to every frame interval.

    Parameters
    ----------
    emulator : v2ecore.emulator.EventEmulator (or anything with its interface)
        The emulator, created with ``shot_noise_rate_hz=0`` and ``leak_rate_hz=0``.
    params : NoiseParams or str
        Noise model parameters, or a preset name / path (e.g. ``"evk3-hd"``).
    white_lux : float
        Illuminance at the sensor of grey level 255, in lux; grey ``g`` is ``white_lux * g / 255``.
    rng : numpy.random.Generator, int or None
        Randomness of the noise; the same seed and frames give the same noise.
    log_input : bool, optional
        Frames are ``ln(grey)`` (v2e's ``--hdr``); default: the emulator's ``log_input``
        attribute, else False.
    threads : int, optional
        Worker threads of the noise simulator.

    Notes
    -----
    ``generate_events(new_frame, t_frame)`` returns v2e's rows unchanged and in their order,
    with the noise rows of ``[t_previous, t_frame)`` inserted by time, as a float64 ``N x 4``
    array ``[t_s, x, y, +-1]`` (v2e itself returns float32 or float64; float64 keeps the noise
    timestamps' microseconds), or ``None`` when there are no events. The noise of an interval
    uses the earlier frame's illuminance; it does not interact with v2e's pixel state. Other
    attributes (``num_events_total``, ``cleanup``, ...) are the emulator's.
    """

    def __init__(self, emulator, params, white_lux, rng=None, *, log_input: bool | None = None,
                 threads: int | None = None):
        self.white_lux = check_positive(white_lux, "white_lux", "lux")
        if log_input is None:
            log_input = bool(getattr(emulator, "log_input", False))
        self.log_input = bool(log_input)
        super().__init__(emulator, params, self._to_lux, rng, threads=threads)
        own = {name: getattr(emulator, name, 0) for name in ("shot_noise_rate_hz", "leak_rate_hz")}
        own = {k: v for k, v in own.items() if isinstance(v, (int, float)) and v > 0}
        if own:
            settings = ", ".join(f"{k}={v:g}" for k, v in own.items())
            warnings.warn(f"the v2e emulator adds its own noise ({settings}); set them to 0 so that only "
                          "evnoise's photon noise is added", UserWarning, stacklevel=2)

    def _to_lux(self, frame):
        return grey_to_lux(frame, self.white_lux, log_input=self.log_input)
