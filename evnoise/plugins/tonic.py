"""evnoise's photon noise as a tonic transform (a physical replacement for ``UniformNoise``).

tonic (https://github.com/neuromorphs/tonic) represents a sample as a structured NumPy array
with fields ``x``, ``y``, ``t`` (microseconds) and ``p`` (0 = OFF, 1 = ON) in any order and in
whatever integer (or bool) types the dataset chose, and a sensor as ``sensor_size = (W, H, P)``.
:class:`PhotonNoise` follows those conventions and does not import tonic itself.
"""

from __future__ import annotations

import hashlib
import math
import numbers
import os
import sys

import numpy as np

from .._budget import check_allocation
from .._checks import as_generator, check_lux, resolve_threads
from ..errors import InputError, ParameterError

__all__ = ["PhotonNoise"]

_SAMPLE_STREAM = 1  # SeedSequence words that separate the per-sample noise ...
_THRESHOLD_STREAM = 0  # ... from the sensor's threshold mismatch
_WORKER_STREAM = 2  # ... and a Generator's per-worker streams
MAX_T_US = 1 << 62  #: largest |t| of a sample (µs), as evnoise's readers take: room for differences in int64
#: peak memory per pixel of the transform (its per-pixel maps and inputs, and a call's pixel state: 60-390 bytes
#: measured over the presets, with and without reset memory), checked against the budget at construction
BYTES_PER_PIXEL = 400


def _worker_identity():
    """``("torch", worker seed)`` inside a torch DataLoader worker, else ``("pid", process id)``.

    torch is not imported here: if the process has not loaded ``torch.utils.data`` it is not a
    DataLoader worker. A worker's seed is ``base_seed + worker_id``, with ``base_seed`` drawn from
    torch's generator in the main process for each epoch (so ``torch.manual_seed`` fixes it).
    """
    data = sys.modules.get("torch.utils.data")
    info = data.get_worker_info() if data is not None and hasattr(data, "get_worker_info") else None
    if info is not None:
        return "torch", int(info.seed)
    return "pid", os.getpid()


def _signed_p(dtype: np.dtype) -> np.dtype:
    """``dtype`` with an unsigned ``p`` field made signed of the same width (tonic writes -1 into ``p``:
    ``ToVoxelGrid`` maps OFF to -1 in place, which overflows an unsigned field)."""
    if dtype["p"].kind != "u":
        return dtype
    signed = np.dtype(f"{dtype['p'].byteorder if dtype['p'].byteorder in '<>' else '='}i{dtype['p'].itemsize}")
    fields = [(name, signed if name == "p" else dtype.fields[name][0]) for name in dtype.names]
    return np.dtype(fields)


def _check_sensor_size(sensor_size):
    try:
        width, height, n_pol = (int(v) for v in sensor_size)
        whole = all(float(v) == int(v) for v in sensor_size)
    except (TypeError, ValueError, OverflowError):
        raise ParameterError(f"sensor_size must be tonic's (W, H, P), got {sensor_size!r}") from None
    if not whole or not (1 <= width <= 65536 and 1 <= height <= 65536) or n_pol not in (1, 2):
        raise ParameterError(f"sensor_size must be (W, H, P) of whole numbers with 1 <= W, H <= 65536 and P = 1 or 2, "
                             f"got {sensor_size!r}")
    # the transform keeps per-pixel maps and a call works on every pixel: refuse a sensor whose state cannot fit
    check_allocation(BYTES_PER_PIXEL * width * height, f"PhotonNoise's per-pixel state of a {width}x{height} sensor",
                     hint="check sensor_size (W, H, P)", error=ParameterError)
    return width, height, n_pol


def _packed(events: np.ndarray) -> np.ndarray:
    """``events`` with its fields only, packed (no padding or bytes of fields left out of a view): what a seed's
    noise is keyed on, so that bytes that are not the sample's values cannot change it."""
    fields = [(name, events.dtype.fields[name][0]) for name in events.dtype.names]
    packed = np.dtype(fields)
    if packed == events.dtype:
        return events
    out = np.empty(events.shape, dtype=packed)
    for name in events.dtype.names:
        out[name] = events[name]
    return out


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
          content* (its dtype and field values; not padding bytes): calling the transform again
          on the same sample gives the same output (in any epoch, order or DataLoader worker),
          and different samples get independent noise;
        * a Generator: drawn from it on every call, so the same sample gets new noise each
          time (reproducible for a fixed order of calls in one process). A copy of the
          transform in another process (a DataLoader worker, forked or spawned) draws from its
          own stream, derived once per process from the Generator's state and the worker's
          seed (torch's ``get_worker_info().seed``: ``base_seed + worker_id``, new each epoch,
          fixed by ``torch.manual_seed``), or from the process id outside torch: workers never
          repeat each other's noise.

        Threshold mismatch (``params.eps_sigma > 0``) belongs to the sensor: it is drawn once,
        at construction, and used for every sample.
    threads : int, optional
        Python threads over blocks of 16384 pixels in one call (default ``NUMBA_NUM_THREADS``
        or the CPU count; a sensor of at most 16384 pixels, such as N-MNIST's, uses one).
    off_polarity : {None, 0, -1}
        ``p`` of OFF noise events. None (default): the sample's own convention, -1 where it holds a
        negative ``p``, else 0 -- a sample of +-1 data holding only ON events cannot show it: give -1
        for such a dataset. A ``bool`` ``p`` takes False.

    Notes
    -----
    The span of a sample is the whole microseconds ``t`` with ``t_first <= t <= t_last`` of its
    events (noise times are whole microseconds; float times are not rounded out of the span), so
    the expected number of added events is ``sum(expected_rate(lux)) * (t_last - t_first +
    1e-6 s)`` for integer times: ``t`` in another unit changes the noise by that factor. A sample whose noise would
    not fit in memory is an :class:`~evnoise.errors.InputError` before the draw, and a sensor whose
    per-pixel state would not (:data:`BYTES_PER_PIXEL`) a :class:`~evnoise.errors.ParameterError`
    at construction. An empty sample is returned unchanged (it has no span). The output has the input's
    dtype and field names (an unsigned ``p`` becomes signed of the same width, so that tonic's
    ``ToVoxelGrid`` can write -1 into it) and is sorted by ``t`` (stably: input events before
    noise events at equal times). Noise events take the input's polarity convention: 1 ON and 0
    OFF, or -1 OFF when the input uses -1 (or as ``off_polarity`` says).

    Everything that depends only on the constructor's arguments (the per-pixel event
    probabilities and rates at ``lux``) is computed once, at construction; a call only draws the
    sample's events, with single-threaded kernels: it starts no OpenMP pool, so the transform
    runs in forked DataLoader workers whatever the main process computed before.

    With reset memory (``params.reset_memory > 0``) each sample starts in the steady state of
    its light. Where the chains' tables would pass the table budget
    (``evnoise.terms.memory.MAX_TABLE_STATES``: threshold mismatch on a large sensor), every
    pixel runs trial by trial and each sample computes every chain's start again (seconds per
    sample on a megapixel sensor; the noise is then ``simulate_events``' trial tier for the
    sample's span, event for event).
    """

    def __init__(self, sensor_size, params, lux, rng=None, *, threads: int | None = None,
                 off_polarity: int | None = None):
        from .._run import run_setup

        if off_polarity is not None and (not isinstance(off_polarity, numbers.Integral)
                                         or isinstance(off_polarity, (bool, np.bool_)) or off_polarity not in (0, -1)):
            raise ParameterError(f"off_polarity must be 0, -1 or None, got {off_polarity!r}")
        self.off_polarity = None if off_polarity is None else int(off_polarity)

        self.sensor_size = tuple(_check_sensor_size(sensor_size))
        width, height, _ = self.sensor_size
        self.lux = self._lux_map(lux, height, width)
        resolve_threads(threads)  # checked here, not at the first call (in a DataLoader worker)
        self.threads = threads
        if rng is None or isinstance(rng, np.random.Generator):
            self._seed = None
            self._gen = rng  # None: a fresh generator per call
            map_rng = rng
        elif isinstance(rng, numbers.Integral) and not isinstance(rng, bool):
            if rng < 0:
                as_generator(rng)  # its error names the negative seed
            self._seed = int(rng)
            self._gen = None
            map_rng = np.random.SeedSequence([self._seed, _THRESHOLD_STREAM])
        else:
            raise ParameterError(f"rng must be None, an integer seed or a numpy Generator, got {type(rng).__name__}")
        self._pid = os.getpid()  # a Generator's copy in another process derives its own stream
        self._worker_gen = None  # (process identity, Generator) of that copy
        # the sensor's per-pixel maps (threshold mismatch, background spread, hot pixels): drawn once, here;
        # each sample's kernel key is drawn per call (_draw)
        self._setup = run_setup((height, width), params, map_rng, draw_key=False)
        self.params = self._setup.params
        self._thresholds = self._setup.threshold_map() if self.params.eps_sigma > 0 else None
        self._background = self._setup.background_map()
        self._precompute()

    def _precompute(self):
        """The renewal kernel's per-pixel inputs at ``self.lux`` (what ``simulate_events`` computes per call)."""
        from .._engine import static_inputs
        from .._memory_chains import memory_chains
        from ..terms.memory import memory_on

        run = self._setup
        lam = self.params.photons_per_trial(self.lux).ravel()
        self._pix = np.arange(self.lux.size, dtype=np.int64)
        self._memory = None
        if memory_on(self.params):
            # reset memory: the state tables of the map's light levels (terms/memory.py), or where those would pass
            # the table budget (threshold mismatch on a large sensor) each chain's start, the pixels then running
            # trial by trial (as simulate_events runs such a scene)
            self._memory = memory_chains(lam, self.params, run.background, *run.thresholds, resolve_threads(
                self.threads))
            self._nu = self._memory.rates[self._memory.group]
            return
        self._log1m_p, self._q_on, self._timer, self._nu = static_inputs(lam, self.params, run.eps_on, run.eps_off,
                                                                         run.background)

    def __getstate__(self):
        # with reset memory the chains' tables can be hundreds of MB (threshold mismatch, a spread leak: a chain per
        # pixel); a DataLoader worker rebuilds them from the maps (no randomness) instead of receiving a copy
        state = self.__dict__.copy()
        if state.get("_memory") is not None:
            state["_memory"] = "rebuild"
            state.pop("_nu", None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        if self.__dict__.get("_memory") == "rebuild":
            self._precompute()

    @staticmethod
    def _lux_map(lux, height, width):
        if lux is None:
            raise InputError("lux must be a scalar or an (H, W) map of illuminance in lux, got None")
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
        off = "" if self.off_polarity is None else f", off_polarity={self.off_polarity}"
        return f"PhotonNoise(sensor_size={self.sensor_size}, params={self.params!r}, lux={lux_text}, rng={rng}{off})"

    def _check_events(self, events):
        events = np.asarray(events)
        names = events.dtype.names or ()
        missing = [f for f in "xytp" if f not in names]
        if missing or events.ndim != 1:
            raise InputError(f"events must be a 1-D structured array with fields x, y, t, p (tonic's format), "
                             f"got dtype {events.dtype} and shape {events.shape}")
        width, height, _ = self.sensor_size
        for field, top in (("x", width - 1), ("y", height - 1), ("t", None), ("p", None)):
            kind = events.dtype[field].kind
            if kind not in "iuf" + ("b" if field == "p" else ""):
                raise InputError(f"events field {field!r} holds {events.dtype[field]}; expected numbers")
            if top is not None and kind in "iu" and top > np.iinfo(events.dtype[field]).max:
                # the noise is written into the input's dtype: a larger coordinate would wrap around
                raise InputError(f"events field {field!r} is {events.dtype[field]}, which cannot hold {field} up to "
                                 f"{top} of sensor_size {self.sensor_size}; use a wider integer type")
        if events.size:
            x, y = events["x"], events["y"]
            if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
                raise InputError("events have coordinates that are not finite numbers")
            if x.min() < 0 or y.min() < 0 or x.max() >= width or y.max() >= height:
                raise InputError(f"events have coordinates outside sensor_size (W, H) = {(width, height)}: "
                                 f"x in {x.min()}..{x.max()}, y in {y.min()}..{y.max()}")
            if self.off_polarity == -1 and events.dtype["p"].kind == "b":
                raise InputError("off_polarity=-1, but the events' p field is bool: it cannot hold -1")
            t = events["t"]
            if not np.all(np.isfinite(t)) or t.min() < -MAX_T_US or t.max() > MAX_T_US:
                raise InputError(f"events have times that are not finite numbers of microseconds within "
                                 f"+-2**62 (t in {t.min()}..{t.max()})")
        return events

    def _generator(self, events):
        if self._seed is not None:
            values = _packed(events)  # the sample's values: not the padding of an aligned dtype
            digest = hashlib.blake2b(str(values.dtype.descr).encode(), digest_size=16)
            digest.update(np.ascontiguousarray(values).tobytes())
            words = np.frombuffer(digest.digest(), dtype=np.uint32).tolist()
            return np.random.default_rng(np.random.SeedSequence([self._seed, _SAMPLE_STREAM, *words]))
        if self._gen is None:
            return np.random.default_rng()
        if os.getpid() == self._pid:
            return self._gen
        # a copy in another process: every worker starts from the same Generator state, so give each its own stream
        kind, ident = _worker_identity()
        if self._worker_gen is None or self._worker_gen[0] != (kind, ident, os.getpid()):
            state = self._gen.integers(0, 2**32, size=4, dtype=np.uint64).tolist()
            seq = np.random.SeedSequence([*state, _WORKER_STREAM, int(kind == "torch"), ident])
            self._worker_gen = ((kind, ident, os.getpid()), np.random.default_rng(seq))
        return self._worker_gen[1]

    def _draw(self, events):
        """The sample's noise as unsorted columns ``(t, x, y, on)`` (the kernel's order, chunk by chunk)."""
        from .._engine import PixelState, memory_step, renewal_step

        key = self._setup.keyed(self._generator(events)).key
        t = events["t"]
        # the whole microseconds within [min t, max t]: noise times are whole, and float times may not be
        t_first = int(np.ceil(t.min()))
        span_us = int(np.floor(t.max())) - t_first + 1
        if span_us < 1:  # float times within one microsecond: no whole microsecond inside
            return tuple(np.empty(0, dtype=d) for d in (np.int64, np.uint16, np.uint16)) + (np.empty(0, dtype=bool),)
        expected = float(self._nu.sum()) * span_us * 1e-6
        # a call's peak: the kernel's columns, their sort, the noise events and the merged output (measured: 41-106
        # bytes per event for items of 7-32 bytes)
        per_event = 3 * events.dtype.itemsize + 48
        check_allocation((expected + 8.0 * math.sqrt(expected)) * per_event, f"the noise of a sample spanning "
                         f"{span_us * 1e-6:.6g} s ({expected:.3g} events expected)",
                         hint="is the sample's t in microseconds?")
        threads = resolve_threads(self.threads)
        state = PixelState(self._pix, key, threads)
        chains = self._memory
        if chains is not None and chains.tables is None:
            parts = self._trials(state, chains, t_first, span_us, threads)
        elif chains is not None:  # each sample starts in the steady state of its light (stored counts drawn)
            parts = memory_step(state, np.full(self._pix.size, math.nan), self.sensor_size[0], chains.group,
                                chains.tables, self.params.trial_us, self.params.refractory_us, 0.0, float(span_us),
                                math.inf, t_first, threads, self._nu * (span_us * 1e-6), chains.timer)
        else:
            parts = renewal_step(state, self.sensor_size[0], self._log1m_p, self._q_on, self.params.trial_us,
                                 self.params.refractory_us, 0, span_us, math.inf, t_first, threads,
                                 expected=self._nu * (span_us * 1e-6), timer=self._timer)
        cols = [np.concatenate([p[i] for p in parts]) if len(parts) != 1 else parts[0][i].copy() for i in range(4)]
        return cols[0], cols[1], cols[2], cols[3] == 1

    def _trials(self, state, chains, t_first: int, span_us: int, threads: int):
        """The sample's noise trial by trial (reset memory whose chains are too many for tables): every pixel starts
        in the steady state of its chain (:meth:`evnoise._memory_chains.OwnChainStarts.start_trials`), then runs the
        trials that start in the span, as ``simulate_events`` runs a still scene with such chains (its trial tier,
        in one window; the kernel's events unsorted, as the other paths return them)."""
        from .. import terms
        from .._engine import trial_step

        p = self.params
        run = self._setup
        lam = p.photons_per_trial(self.lux).ravel()
        state.lam_ref[:] = lam  # a still scene: no signal crossings, noise only
        state.lam_prev[:] = lam
        bg_rows = terms.kernel_coefficients(p, run.background, self._pix)
        model = terms.kernel_model(p)
        chains.start_trials(state, chains.group, p.trial_us, p.refractory_us, threads, bg_rows, lam, model)
        eps_on, eps_off = run.thresholds
        thr = np.stack([np.expm1(eps_on), np.expm1(eps_off), eps_on, eps_off])
        n_trials = math.ceil(span_us / p.trial_us - 1e-12)
        return trial_step(state, self.sensor_size[0], lam[None, :], np.zeros(1), 0, n_trials, thr, bg_rows, model,
                          span_us, t_first, threads)

    def _as_events(self, events, t, x, y, on, dtype):
        out = np.zeros(t.size, dtype=dtype)
        out["x"] = x
        out["y"] = y
        out["t"] = t
        if self.sensor_size[2] == 1:
            out["p"] = 0
        elif events["p"].dtype.kind == "b":
            out["p"] = on
        else:
            off = self.off_polarity if self.off_polarity is not None else (-1 if events["p"].min() < 0 else 0)
            out["p"] = np.where(on, 1, off)
        return out

    def _noise(self, events, dtype):
        t, x, y, on = self._draw(events)
        order = np.argsort(t, kind="stable")
        return self._as_events(events, t[order], x[order], y[order], on[order], dtype)

    def noise(self, events) -> np.ndarray:
        """The noise events alone that :meth:`__call__` adds to ``events`` (the output's dtype, sorted by t).

        Parameters
        ----------
        events : numpy.ndarray
            A tonic sample: 1-D structured array with fields ``x``, ``y``, ``t`` (microseconds) and ``p``,
            inside ``sensor_size``. It sets the span of the noise and, with an int seed, its randomness.

        Returns
        -------
        numpy.ndarray
            The noise events, in the input's dtype with ``p`` made signed, sorted by ``t``; empty for an
            empty sample. With an int seed they are the ones :meth:`__call__` adds to the same sample;
            with a Generator or ``None`` each call draws new ones.
        """
        events = self._check_events(events)
        dtype = _signed_p(events.dtype)
        if events.size == 0:
            return np.empty(0, dtype=dtype)
        return self._noise(events, dtype)

    def __call__(self, events):
        """``events`` with photon-noise events added, sorted by ``t``, in the input's dtype (``p`` signed)."""
        events = self._check_events(events)
        dtype = _signed_p(events.dtype)
        if events.size == 0:
            return events.astype(dtype, copy=False)
        noise = self._noise(events, dtype)  # drawn for the sample as given (an int seed hashes its bytes)
        events = events.astype(dtype, copy=False)
        t = events["t"]
        if not np.all(t[1:] >= t[:-1]):
            # stable: input events first at equal times, then the noise in its own (sorted) order
            out = np.concatenate([events, noise])
            return out[np.argsort(out["t"], kind="stable")]
        # a sorted sample (the usual case): the same order, by inserting the noise (no sort of the whole)
        pos = np.searchsorted(t, noise["t"], side="right") + np.arange(noise.size)
        out = np.empty(events.size + noise.size, dtype=dtype)
        is_input = np.ones(out.size, dtype=bool)
        is_input[pos] = False
        out[is_input] = events
        out[pos] = noise
        return out
