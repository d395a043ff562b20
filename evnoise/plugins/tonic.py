"""evnoise's photon noise as a tonic transform (a physical replacement for ``UniformNoise``).

tonic (https://github.com/neuromorphs/tonic) represents a sample as a structured NumPy array
with fields ``x``, ``y``, ``t`` (microseconds) and ``p`` (0 = OFF, 1 = ON) in any order and in
whatever integer (or bool) types the dataset chose, and a sensor as ``sensor_size = (W, H, P)``.
:class:`PhotonNoise` follows those conventions and does not import tonic itself.
"""

from __future__ import annotations

import hashlib
import numbers

import numpy as np

from .._checks import as_generator, check_lux, check_params
from ..errors import InputError, ParameterError

__all__ = ["PhotonNoise"]

_SAMPLE_STREAM = 1  # SeedSequence words that separate the per-sample noise ...
_THRESHOLD_STREAM = 0  # ... from the sensor's threshold mismatch


def _check_sensor_size(sensor_size):
    try:
        width, height, n_pol = (int(v) for v in sensor_size)
    except (TypeError, ValueError):
        raise ParameterError(f"sensor_size must be tonic's (W, H, P), got {sensor_size!r}") from None
    if not (1 <= width <= 65536 and 1 <= height <= 65536) or n_pol not in (1, 2):
        raise ParameterError(f"sensor_size must be (W, H, P) with 1 <= W, H <= 65536 and P = 1 or 2, "
                             f"got {sensor_size!r}")
    return width, height, n_pol


class PhotonNoise:
    """A tonic transform adding photon-noise events for the sample's own time span.

    Parameters
    ----------
    sensor_size : (W, H, P)
        tonic's sensor size (e.g. ``tonic.datasets.NMNIST.sensor_size``); ``P`` is 2, or 1 for
        merged polarities (noise events then get ``p = 0``).
    params : NoiseParams or str
        Noise model parameters, or a preset name / path (e.g. ``"evk3-hd"``).
    lux : float or array_like
        Illuminance at the sensor in lux: a scalar, or a map of shape ``(H, W) =
        (sensor_size[1], sensor_size[0])`` indexed ``lux[y, x]`` -- the orientation of the
        frames tonic's ``ToFrame`` makes (a ``(W, H)`` map of a non-square sensor is an error).
    rng : None, int or numpy.random.Generator
        How the noise is drawn on repeated calls:

        * ``None``: fresh randomness on every call (augmentation; not reproducible);
        * an int seed: the noise of a sample is a function of the seed *and the sample's
          content*: calling the transform again on the same sample gives the same output (in
          any epoch, order or DataLoader worker), and different samples get independent noise;
        * a Generator: drawn from it on every call, so the same sample gets new noise each
          time (reproducible for a fixed order of calls in one process; DataLoader workers
          forked from one process would share its state).

        Threshold mismatch (``params.eps_sigma > 0``) belongs to the sensor: it is drawn once,
        at construction, and used for every sample.
    threads : int, optional
        Worker threads of the noise simulator.

    Notes
    -----
    The span of a sample is ``t_first <= t <= t_last`` of its events (integer microseconds),
    so the expected number of added events is ``sum(expected_rate(lux)) * (t_last - t_first +
    1e-6 s)``. An empty sample is returned unchanged (it has no span). The output has the input's
    dtype and field names and is sorted by ``t`` (stably: input events before noise events at
    equal times). Noise events take the input's polarity convention: 1 ON and 0 OFF, or -1 OFF
    when the input uses -1.
    """

    def __init__(self, sensor_size, params, lux, rng=None, *, threads: int | None = None):
        from .._engine import resolve_thresholds

        self.sensor_size = tuple(_check_sensor_size(sensor_size))
        width, height, _ = self.sensor_size
        self.params = check_params(params)
        self.lux = self._lux_map(lux, height, width)
        self.threads = threads
        if rng is None or isinstance(rng, np.random.Generator):
            self._seed = None
            self._gen = rng  # None: a fresh generator per call
            thr_gen = as_generator(rng)
        elif isinstance(rng, numbers.Integral) and not isinstance(rng, bool):
            as_generator(rng)  # validates (non-negative)
            self._seed = int(rng)
            self._gen = None
            thr_gen = np.random.default_rng(np.random.SeedSequence([self._seed, _THRESHOLD_STREAM]))
        else:
            raise ParameterError(f"rng must be None, an integer seed or a numpy Generator, got {type(rng).__name__}")
        if self.params.eps_sigma > 0:
            eps_on, eps_off = resolve_thresholds((height, width), self.params, thr_gen, None)
            self._thresholds = np.stack([eps_on, eps_off]).reshape(2, height, width)
        else:
            self._thresholds = None
        self._background = None
        if self.params.has_background and (self.params.leak_sigma > 0 or self.params.hot_pixel_fraction > 0):
            from ..background import draw_background

            self._background = draw_background((height, width), self.params, thr_gen)  # once per sensor

    @staticmethod
    def _lux_map(lux, height, width):
        if np.ndim(lux) == 0:
            return np.full((height, width), check_lux([[lux]])[0, 0])
        arr = check_lux(lux)
        if arr.shape != (height, width):
            hint = ""
            if arr.shape == (width, height):
                hint = " (it looks transposed: tonic's sensor_size is (W, H, P), the map is indexed lux[y, x])"
            raise InputError(f"lux must be a scalar or an (H, W) = {(height, width)} map, got shape {arr.shape}{hint}")
        return arr

    def __repr__(self):
        lux = self.lux
        lux_text = f"{lux.flat[0]:g}" if np.all(lux == lux.flat[0]) else f"map {lux.shape} {lux.min():g}..{lux.max():g}"
        rng = ("None" if self._seed is None and self._gen is None
               else (self._seed if self._seed is not None else "Generator"))
        return f"PhotonNoise(sensor_size={self.sensor_size}, params={self.params!r}, lux={lux_text}, rng={rng})"

    def _check_events(self, events):
        events = np.asarray(events)
        names = events.dtype.names or ()
        missing = [f for f in "xytp" if f not in names]
        if missing or events.ndim != 1:
            raise InputError(f"events must be a 1-D structured array with fields x, y, t, p (tonic's format), "
                             f"got dtype {events.dtype} and shape {events.shape}")
        if events.size:
            width, height, _ = self.sensor_size
            x, y = events["x"], events["y"]
            if x.min() < 0 or y.min() < 0 or x.max() >= width or y.max() >= height:
                raise InputError(f"events have coordinates outside sensor_size (W, H) = {(width, height)}: "
                                 f"x in {x.min()}..{x.max()}, y in {y.min()}..{y.max()}")
        return events

    def _generator(self, events):
        if self._seed is not None:
            digest = hashlib.blake2b(str(events.dtype.descr).encode(), digest_size=16)
            digest.update(np.ascontiguousarray(events).tobytes())
            words = np.frombuffer(digest.digest(), dtype=np.uint32).tolist()
            return np.random.default_rng(np.random.SeedSequence([self._seed, _SAMPLE_STREAM, *words]))
        return as_generator(self._gen)

    def noise(self, events) -> np.ndarray:
        """The noise events alone that :meth:`__call__` adds to ``events`` (same dtype, sorted by t)."""
        from ..simulate import simulate_events

        events = self._check_events(events)
        out_dtype = events.dtype
        if events.size == 0:
            return np.empty(0, dtype=out_dtype)
        gen = self._generator(events)
        t = events["t"]
        t_first = int(np.floor(t.min()))
        t_last = int(np.ceil(t.max()))
        span_us = t_last - t_first + 1
        noise = simulate_events(self.lux, self.params, span_us * 1e-6, rng=gen, thresholds=self._thresholds,
                                background=self._background,
                                t_start_us=t_first, threads=self.threads)
        out = np.zeros(noise.size, dtype=out_dtype)
        out["x"] = noise["x"]
        out["y"] = noise["y"]
        out["t"] = noise["t"]
        on = noise["p"] == 1
        if self.sensor_size[2] == 1:
            out["p"] = 0
        elif events["p"].dtype.kind == "b":
            out["p"] = on
        else:
            off = -1 if events["p"].min() < 0 else 0
            out["p"] = np.where(on, 1, off)
        return out

    def __call__(self, events):
        """``events`` with photon-noise events added, sorted by ``t``, in the input's dtype."""
        events = self._check_events(events)
        if events.size == 0:
            return events
        noise = self.noise(events)
        out = np.concatenate([events, noise])
        return out[np.argsort(out["t"], kind="stable")]
