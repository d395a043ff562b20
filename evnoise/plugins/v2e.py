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

v2e's own outputs
-----------------
v2e writes its files (``dvs_h5``, ``dvs_aedat2``, ``dvs_aedat4``, ``dvs_text``) and counts its
events (``num_events_total``, ``num_events_on``, ``num_events_off``) inside ``generate_events``.
During that call the wrapper stands in for the emulator's writers (the attributes ``dvs_h5_dataset``,
``dvs_aedat2``, ``dvs_aedat4``, ``dvs_text``), takes what v2e hands them, and then writes to the real
writers the rows it returns: v2e's rows (in v2e's own conversion) with the noise rows merged in, the
noise labelled as noise when v2e labels signal and noise (``label_signal_noise``). The counts include
the noise, and ``dvs_h5``'s ``frame_idx`` counts the merged rows.

From the command line, ``python -m evnoise.plugins.v2e --params evk3-hd --white-lux 18 -- <v2e.py
arguments>`` runs v2e's own ``v2e.py`` with every ``EventEmulator`` it creates wrapped (v2e's own
noise defaults to 0 there; ``--shot_noise_rate_hz`` / ``--leak_rate_hz`` given after ``--`` win).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import runpy
import shutil
import sys
import warnings
from pathlib import Path

import numpy as np

from .._checks import check_params, check_positive
from ..errors import EvnoiseError, InputError, ParameterError
from .frames import EmulatorNoise, interleave, merge_with_positions, noise_rows

__all__ = ["PhotonNoise", "grey_to_lux", "noisy_emulator_class", "noisy_emulators", "main"]

#: v2e's writers that take float rows ``[t_s, x, y, +-1]`` through ``appendEvents``; all but the text
#: writer truncate ``t * 1e6`` to integer microseconds
_ROW_WRITERS = ("dvs_aedat2", "dvs_aedat4", "dvs_text")
_TRUNCATING = ("dvs_aedat2", "dvs_aedat4")

WHITE_GREY = 255.0


def grey_to_lux(frame, white_lux: float, *, log_input: bool = False) -> np.ndarray:
    """Illuminance (lux, float64) of a v2e luma frame: ``white_lux * grey / 255``.

    Parameters
    ----------
    frame : array_like, shape (height, width)
        Grey levels (white = 255, at least 0), or ``ln(grey)`` with ``log_input``.
    white_lux : float
        Illuminance at the sensor of grey level 255, in lux; must be positive.
    log_input : bool, default False
        The frame holds ``ln(grey)`` (v2e's ``--hdr`` input, at most 700) instead of the grey level.

    Returns
    -------
    numpy.ndarray
        Illuminance in lux, float64 of the frame's shape.

    Raises
    ------
    InputError
        If the frame is not a finite numeric 2-D array, has a negative grey level, or (with
        ``log_input``) a value above 700.
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



class _RowRecorder:
    """Stands in for one of v2e's ``appendEvents`` writers during the emulator's call."""

    def __init__(self):
        self.rows, self.labels = [], []

    def appendEvents(self, events, signnoise_label=None):  # noqa: N802 - v2e's name
        self.rows.append(np.array(events, copy=True))
        self.labels.append(None if signnoise_label is None else np.array(signnoise_label, dtype=bool))


class _DatasetRecorder:
    """Stands in for v2e's ``dvs_h5`` ``events`` dataset (``resize`` then ``dataset[-n:] = rows``)."""

    def __init__(self, dataset):
        self.size = int(dataset.shape[0])
        self.rows = []

    @property
    def shape(self):
        return (self.size, 4)

    def resize(self, size, axis=0):
        self.size = int(size)

    def __setitem__(self, key, value):
        self.rows.append(np.array(value, copy=True))


def _v2e_microseconds(t_s) -> np.ndarray:
    """Microseconds as v2e's writers make them from its rows: ``t * 1e6`` in the rows' own float type, truncated."""
    t_s = np.asarray(t_s)
    return (t_s * t_s.dtype.type(1e6)).astype(np.int64)


class _Outputs:
    """v2e's file writers of one emulator, watched during ``generate_events`` and then given the merged rows."""

    def __init__(self, emulator):
        self.emulator = emulator
        self.saved = {}

    def __enter__(self):
        em = self.emulator
        if getattr(em, "dvs_h5", None) is not None and getattr(em, "dvs_h5_dataset", None) is not None:
            self.saved["dvs_h5_dataset"] = em.dvs_h5_dataset
            em.dvs_h5_dataset = _DatasetRecorder(em.dvs_h5_dataset)
        for name in _ROW_WRITERS:
            if getattr(em, name, None) is not None:
                self.saved[name] = getattr(em, name)
                setattr(em, name, _RowRecorder())
        return self

    def __exit__(self, *exc):
        self.recorded = {name: getattr(self.emulator, name) for name in self.saved}
        for name, writer in self.saved.items():
            setattr(self.emulator, name, writer)
        return False

    def write(self, signal, noise, positions, rows):
        """Write v2e's recorded rows with ``noise`` (evnoise events) at ``positions`` to the real writers."""
        em = self.emulator
        if noise.size == 0:  # nothing to add: what v2e handed its writers goes through unchanged
            self._replay()
            return
        labelled = bool(getattr(em, "label_signal_noise", False))
        n_signal = 0 if signal is None else int(np.shape(signal)[0])
        for name, writer in self.saved.items():
            rec = self.recorded[name]
            if name == "dvs_h5_dataset":
                own = np.concatenate(rec.rows) if rec.rows else np.zeros((0, 4), dtype=np.uint32)
                if own.shape[0] != n_signal:
                    raise InputError(f"v2e wrote {own.shape[0]} rows to dvs_h5 for {n_signal} events")
                extra = np.stack([noise["t"], noise["x"], noise["y"], noise["p"]], axis=1).astype(own.dtype)
                merged = interleave(own, extra, positions)
                writer.resize(writer.shape[0] + merged.shape[0], axis=0)
                writer[-merged.shape[0]:] = merged
                continue
            own_labels = [lab for lab in rec.labels if lab is not None]
            label = None
            if own_labels or labelled:  # v2e labels signal (True) and noise (False)
                own = np.concatenate(own_labels) if own_labels else np.ones(n_signal, dtype=bool)
                label = interleave(own, np.zeros(noise.size, dtype=bool), positions, bool)
            out = rows
            if name in _TRUNCATING:
                # these writers truncate t * 1e6: hand them each row's microseconds plus half of one, so that
                # v2e's rows come out as v2e alone writes them and evnoise's at their exact microsecond
                us_signal = _v2e_microseconds(signal[:, 0]) if n_signal else np.zeros(0, dtype=np.int64)
                us = interleave(us_signal, noise["t"].astype(np.int64), positions, np.int64)
                out = rows.copy()
                out[:, 0] = (us + 0.5) * 1e-6
            if label is None:
                writer.appendEvents(out)
            else:
                writer.appendEvents(out, signnoise_label=label)
        if getattr(em, "frame_ev_idx_dataset", None) is not None and "dvs_h5_dataset" in self.saved:
            em.frame_ev_idx_dataset[em.frame_counter - 1] = self.saved["dvs_h5_dataset"].shape[0]
        on = int(np.count_nonzero(noise["p"] == 1))
        for name, add in (("num_events_total", noise.size), ("num_events_on", on), ("num_events_off", noise.size - on)):
            value = getattr(em, name, None)
            if isinstance(value, (int, np.integer)):
                setattr(em, name, value + add)

    def _replay(self):
        for name, writer in self.saved.items():
            rec = self.recorded[name]
            if name == "dvs_h5_dataset":
                if rec.rows:
                    own = np.concatenate(rec.rows)
                    writer.resize(writer.shape[0] + own.shape[0], axis=0)
                    writer[-own.shape[0]:] = own
                continue
            for rows, label in zip(rec.rows, rec.labels):
                if label is None:
                    writer.appendEvents(rows)
                else:
                    writer.appendEvents(rows, signnoise_label=label)
        if getattr(self.emulator, "frame_ev_idx_dataset", None) is not None and "dvs_h5_dataset" in self.saved:
            self.emulator.frame_ev_idx_dataset[self.emulator.frame_counter - 1] = \
                self.saved["dvs_h5_dataset"].shape[0]


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

    v2e's own outputs get the same rows: its ``dvs_h5`` ``events`` dataset (v2e's rows as v2e
    converts them, the noise rows at their exact microsecond, ``p`` 1 ON / 0 OFF), its AEDAT 2 /
    AEDAT 4 and text writers (noise labelled as noise when v2e has ``label_signal_noise``), the
    ``frame_idx`` of its ``dvs_h5`` and its counts ``num_events_total``, ``num_events_on`` and
    ``num_events_off``.
    """

    OWN_ATTRIBUTES = EmulatorNoise.OWN_ATTRIBUTES | {"white_lux", "log_input"}

    def __init__(self, emulator, params, white_lux, rng=None, *, log_input: bool | None = None,
                 threads: int | None = None):
        self.white_lux = check_positive(white_lux, "white_lux", "lux")
        if log_input is None:
            log_input = bool(getattr(emulator, "log_input", False))
        self.log_input = bool(log_input)
        super().__init__(emulator, params, self._to_lux, rng, threads=threads)
        self._warned_own_noise = False
        self._check_own_noise(stacklevel=3)

    def _check_own_noise(self, stacklevel: int) -> None:
        """Warn (once) when v2e's own noise is on: at construction, and again at each frame, since v2e can turn
        it on after the emulator is made (``v2e.py --dvs_params noisy`` calls ``set_dvs_params``)."""
        if self._warned_own_noise:
            return
        own = {name: getattr(self.emulator, name, 0) for name in ("shot_noise_rate_hz", "leak_rate_hz")}
        own = {k: v for k, v in own.items() if isinstance(v, (int, float)) and v > 0}
        if own:
            self._warned_own_noise = True
            settings = ", ".join(f"{k}={v:g}" for k, v in own.items())
            warnings.warn(f"the v2e emulator adds its own noise ({settings}); set them to 0 so that only "
                          "evnoise's photon noise is added", UserWarning, stacklevel=stacklevel)

    def generate_events(self, new_frame, t_frame):
        """As :meth:`EmulatorNoise.generate_events`, after checking that v2e's own noise is still off.

        Parameters
        ----------
        new_frame : array_like, shape (height, width)
            v2e's luma frame (grey levels, or ``ln(grey)`` with ``log_input``), passed to the emulator unchanged.
        t_frame : float
            Its time in seconds.

        Returns
        -------
        numpy.ndarray or None
            float64 ``N x 4`` rows ``[t_s, x, y, p]`` (``p`` = +1 ON, -1 OFF): v2e's rows unchanged and in
            their order with the noise rows of ``[t_previous, t_frame)`` inserted by time; ``None`` when
            there are no events (e.g. on the first frame).

        Warns
        -----
        UserWarning
            Once, when v2e's ``shot_noise_rate_hz`` or ``leak_rate_hz`` is above 0.
        """
        self._check_own_noise(stacklevel=3)
        return super().generate_events(new_frame, t_frame)

    def _to_lux(self, frame):
        return grey_to_lux(frame, self.white_lux, log_input=self.log_input)

    def _emulate(self, new_frame, t_frame):
        self._outputs = _Outputs(self.emulator)
        with self._outputs:
            return super()._emulate(new_frame, t_frame)

    def _merge(self, signal, noise):
        rows, positions = merge_with_positions(signal, noise_rows(noise))
        outputs, self._outputs = self._outputs, None
        outputs.write(None if signal is None else np.asarray(signal), noise, positions, rows)
        return rows


def noisy_emulator_class(base, params, white_lux, rng=None, **kwargs):
    """A subclass of v2e's ``EventEmulator`` class ``base`` whose instances add evnoise's photon noise.

    Each instance wraps itself in a :class:`PhotonNoise` that calls ``base``'s own
    ``generate_events``: v2e's code that creates ``EventEmulator(...)`` and uses its attributes
    (``v2e.py``) runs unchanged, with the noise in its events, files and counts. The class keeps the
    wrappers it made in ``made``.

    Parameters
    ----------
    base : type
        v2e's ``EventEmulator`` class (or a class with its interface) to subclass.
    params : NoiseParams or str
        Noise model parameters, or a preset name / path (e.g. ``"evk3-hd"``).
    white_lux : float
        Illuminance at the sensor of grey level 255, in lux.
    rng : numpy.random.Generator, int or None
        Randomness of the noise, given to every instance's :class:`PhotonNoise`: an int seed gives
        every instance the same noise, a Generator is shared by them.
    **kwargs
        Further keyword arguments of :class:`PhotonNoise` (``log_input``, ``threads``).

    Returns
    -------
    type
        The subclass, named ``Noisy`` + ``base``'s name; instances have the wrapper as ``evnoise``.
    """

    class NoisyEventEmulator(base):
        made = []

        def __init__(self, *args, **emulator_kwargs):
            super().__init__(*args, **emulator_kwargs)
            noise = PhotonNoise(self, params, white_lux, rng, **kwargs)
            noise._generate = functools.partial(base.generate_events, self)
            self._evnoise = noise
            NoisyEventEmulator.made.append(noise)

        @property
        def evnoise(self):
            """The :class:`PhotonNoise` that adds the noise (``noise_count``, ``signal_count``)."""
            return self._evnoise

        def generate_events(self, new_frame, t_frame):
            return self._evnoise.generate_events(new_frame, t_frame)

        def reset(self):
            super().reset()
            if getattr(self, "_evnoise", None) is not None:  # v2e's __init__ calls reset() too
                self._evnoise.restart_noise()

    NoisyEventEmulator.__name__ = NoisyEventEmulator.__qualname__ = f"Noisy{base.__name__}"
    return NoisyEventEmulator


@contextlib.contextmanager
def noisy_emulators(params, white_lux, rng=None, **kwargs):
    """Within the block, ``v2ecore.emulator.EventEmulator`` is :func:`noisy_emulator_class` of v2e's class, so code
    that imports the name inside the block, as ``v2e.py`` does, creates emulators that add evnoise's photon noise.

    A context manager; v2e's class is put back when the block ends. v2e's ``v2ecore`` must be importable.

    Parameters
    ----------
    params : NoiseParams or str
        Noise model parameters, or a preset name / path (e.g. ``"evk3-hd"``).
    white_lux : float
        Illuminance at the sensor of grey level 255, in lux.
    rng : numpy.random.Generator, int or None
        Randomness of the noise, as in :func:`noisy_emulator_class`.
    **kwargs
        Further keyword arguments of :class:`PhotonNoise` (``log_input``, ``threads``).

    Yields
    ------
    list of PhotonNoise
        The wrappers of the emulators made in the block, filled as they are made.
    """
    import v2ecore.emulator as emulator_module

    original = emulator_module.EventEmulator
    noisy = noisy_emulator_class(original, params, white_lux, rng, **kwargs)
    emulator_module.EventEmulator = noisy
    try:
        yield noisy.made
    finally:
        emulator_module.EventEmulator = original


def _find_v2e_script(given):
    if given:
        path = Path(given)
    else:
        found = shutil.which("v2e.py") or shutil.which("v2e.py", path=str(Path(sys.executable).parent))
        path = Path(found) if found else None
    if path is None or not path.is_file():
        raise ParameterError("cannot find v2e's v2e.py" + (f" at {path}" if path else " on PATH") +
                             ": install v2e from https://github.com/SensorsINI/v2e or pass --v2e-script")
    return path


def main(argv=None) -> int:
    """``python -m evnoise.plugins.v2e [options] -- <v2e.py arguments>``: v2e.py with evnoise's photon noise.

    ``--seed`` and the check of ``--white-lux`` are the command line's (:mod:`evnoise.cli._options`).

    Parameters
    ----------
    argv : list of str, optional
        The command line's arguments without the program name; by default ``sys.argv[1:]``.

    Returns
    -------
    int
        The exit status of v2e.py (0 when it ends normally). Bad options exit through argparse.
    """
    from ..cli import _options as opt

    parser = argparse.ArgumentParser(
        prog="python -m evnoise.plugins.v2e",
        description="Run v2e's v2e.py with evnoise's photon noise added to every EventEmulator it creates "
                    "(its files and counts include the noise). Arguments after -- go to v2e.py.")
    parser.add_argument("--params", required=True, help="noise preset name or parameter file (e.g. evk3-hd)")
    parser.add_argument("--white-lux", type=opt.positive_number("--white-lux", "lux", maximum=opt.MAX_LUX),
                        required=True, help="illuminance at the sensor of grey 255, lux")
    opt.add_seed(parser, help="seed of the noise (default: fresh randomness)")
    parser.add_argument("--v2e-script", default=None, help="path of v2e.py (default: v2e.py on PATH)")
    parser.add_argument("v2e_args", nargs=argparse.REMAINDER, help="-- then v2e.py's arguments")
    args = parser.parse_args(argv)
    v2e_args = list(args.v2e_args)
    if v2e_args[:1] == ["--"]:
        v2e_args = v2e_args[1:]
    try:
        params = check_params(args.params)
        script = _find_v2e_script(args.v2e_script)
        importlib.import_module("v2ecore.emulator")
    except EvnoiseError as exc:
        parser.error(str(exc))
    except ImportError as exc:
        parser.error(f"v2e's v2ecore cannot be imported ({exc}): install v2e from https://github.com/SensorsINI/v2e")
    # v2e's own noise off unless asked for after -- (argparse keeps the last value given)
    argv_v2e = [str(script), "--shot_noise_rate_hz", "0", "--leak_rate_hz", "0", *v2e_args]
    saved_argv = sys.argv
    status = 0
    with noisy_emulators(params, args.white_lux, rng=args.seed) as made:
        sys.argv = argv_v2e
        try:
            runpy.run_path(str(script), run_name="__main__")
        except SystemExit as exc:
            status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        finally:
            sys.argv = saved_argv
            added = sum(w.noise_count for w in made)
            print(f"evnoise: added {added} photon-noise events ({args.params}, grey 255 = {args.white_lux:g} lux) "
                  "to v2e's events, files and counts", file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
