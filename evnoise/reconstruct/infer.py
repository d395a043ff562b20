"""Inference: counts from an events.h5 stream -> binned rates -> U-Net -> image.

:func:`counts_from_h5` reads only the events of the requested window (through ``/ms_to_idx``),
:class:`Reconstructor` wraps a trained checkpoint.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .._checks import check_positive
from .._clock import seconds_text
from ..errors import InputError, ParameterError
from .imaging import bin_counts

__all__ = ["counts_from_h5", "h5_duration_s", "counts_to_input", "Reconstructor", "default_model_path",
           "choose_window", "recording_mismatch", "model_window", "trained_windows", "short_window_note",
           "MAX_FRAMES", "MAX_STEPS", "check_frame_plan"]

#: file name of the shipped reconstructor inside the package folder ``evnoise/models``
DEFAULT_MODEL_FILE = "evk3-hd.pt"


#: Most frames (images) one moving-window run may write: a million frames is 11.6 days of a 1 fps video or 16 minutes
#: at 1 kHz, beyond any real use; a plan of more (a far-off last event of a damaged file spans years of steps) is
#: refused before any work, naming the count and how to narrow it.
MAX_FRAMES = 1_000_000
#: Most window steps one moving-window run may compute (the frames' steps plus those that fill the first window).
MAX_STEPS = 10 * MAX_FRAMES
#: Bytes of bookkeeping a planned frame takes before it is made (its start, its output path, its table row):
#: checked against the memory budget with the plan.
BYTES_PER_PLANNED_FRAME = 1024


def check_frame_plan(n_frames: int, *, n_steps: int | None = None, hint: str = "") -> None:
    """Refuse (:class:`~evnoise.ParameterError`) a moving-window plan before any work: more than
    :data:`MAX_FRAMES` frames, more than :data:`MAX_STEPS` steps, or frames whose bookkeeping exceeds
    the memory budget. ``hint`` says how to narrow the plan (in the caller's words)."""
    from .._budget import check_allocation

    tail = f"; {hint}" if hint else ""
    if n_frames > MAX_FRAMES:
        raise ParameterError(f"the moving window would make {n_frames:,} frames, more than the {MAX_FRAMES:,} one "
                             f"run may write{tail}")
    if n_steps is not None and n_steps > MAX_STEPS:
        raise ParameterError(f"the moving window would take {n_steps:,} steps, more than the {MAX_STEPS:,} one run "
                             f"may take{tail}")
    check_allocation(n_frames * BYTES_PER_PLANNED_FRAME, f"the plan of {n_frames:,} frames", hint=hint,
                     error=ParameterError)


def default_model_path() -> Path:
    """Path of the reconstructor shipped with evnoise (``evnoise/models/evk3-hd.pt``)."""
    from importlib.resources import files

    try:
        path = Path(str(files("evnoise.models") / DEFAULT_MODEL_FILE))
    except ModuleNotFoundError:  # pragma: no cover - a broken installation
        path = None
    if path is None or not path.is_file():
        raise InputError(f"this evnoise installation has no shipped reconstructor (evnoise/models/"
                         f"{DEFAULT_MODEL_FILE}); give model_path= (a model trained with `evnoise train`)")
    return path


def trained_windows(spec) -> list:
    """The windows (seconds) a model was trained on, sorted; empty if its checkpoint does not say."""
    return sorted(getattr(spec, "windows_s", None) or ([] if spec.window_s is None else [spec.window_s]))


def model_window(spec, window_s: float) -> float:
    """The window the model is shown counts of: ``window_s`` itself, or the shortest trained window when
    ``window_s`` is shorter (see :meth:`Reconstructor.predict_binned`)."""
    windows = trained_windows(spec)
    if windows and window_s < windows[0] * (1 - 1e-9):
        return float(windows[0])
    return float(window_s)


def choose_window(spec, duration_s: float, t_start_s: float = 0.0):
    """``(window_s, note)``: the longest trained window that fits into the recording after ``t_start_s``.

    A model trained on several windows (``spec.windows_s``) is best used at the longest one
    (the least noisy); a recording shorter than every trained window is used whole, with a
    ``note`` saying so (``note`` is None otherwise): its counts are scaled up to the shortest
    trained window before the model sees them (:meth:`Reconstructor.predict_binned`).

    Parameters
    ----------
    spec : InputSpec
        The model's input specification (its ``windows_s``, else ``window_s``).
    duration_s : float
        Length of the recording in seconds (e.g. :func:`h5_duration_s`).
    t_start_s : float, default 0.0
        Start of the window in seconds on the recording's clock.

    Returns
    -------
    window_s : float
        The window in seconds; a trained window within :data:`SHORT_WINDOW_SLACK` of the time left
        is cut to that time.
    note : str or None
        A warning when the recording is shorter than every trained window, else None.

    Raises
    ------
    ParameterError
        If the model does not record its training windows.
    InputError
        If nothing of the recording is left after ``t_start_s``.
    """
    windows = trained_windows(spec)
    if not windows:
        raise ParameterError("the model does not record its training window: give window_s=")
    available = duration_s - t_start_s
    # a window within SHORT_WINDOW_SLACK of the recording's length fits (a file without its end time ends at its
    # last event, a little short of the length recorded): the recording is then used whole
    fitting = [w for w in windows if w * (1.0 - SHORT_WINDOW_SLACK) <= available + 1e-9]
    if fitting:
        return min(max(fitting), available), None
    if available <= 0:
        raise InputError(f"the recording ends at t = {seconds_text(duration_s)} s on its own clock: nothing after "
                         f"t = {seconds_text(t_start_s)} s")
    return available, short_window_note(spec, available, "the recording")


#: a window this close to the shortest trained one (a share short of it) is used without a warning: its counts are
#: scaled by at most 1/0.95 (the image's noise within 3 % of the trained window's), and a recording's length read
#: from its first to its last event (a file without its end time) falls a little short of the length recorded
SHORT_WINDOW_SLACK = 0.05


def short_window_note(spec, window_s: float, what: str = "the window") -> str | None:
    """A warning when ``window_s`` is shorter than every window the model was trained on, by more than
    :data:`SHORT_WINDOW_SLACK` of the shortest (else ``None``)."""
    seen = model_window(spec, window_s)
    if window_s >= seen * (1.0 - SHORT_WINDOW_SLACK):
        return None
    trained = ", ".join(f"{w:g}" for w in trained_windows(spec))
    return (f"{what} ({window_s:.6g} s) is shorter than every window the model was trained on ({trained} s): its "
            f"counts are scaled by {seen / window_s:.3g} to the model's {seen:g} s window (the same rates; "
            f"expect a noisier image; a model trained on windows this short does better: make a dataset with "
            f"windows_s={window_s:.3g}, then train)")


_PARAM_KEYS = ("eps_pos", "eps_neg", "bias_pr", "trial_rate_hz", "photons_per_lux", "dark_lux", "refractory_s",
               "eps_sigma")


def _number(value):
    """``value`` as a finite float, or None where it is not one (text, a list, NaN, a bool)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        value = float(value)
    except OverflowError:
        return None
    return value if math.isfinite(value) else None


def recording_mismatch(meta: dict, doc: dict) -> list:
    """Warnings (strings) when a recording's sensor or noise preset differs from the model's.

    ``meta``: the recording's metadata (:func:`evnoise.io.read_metadata`); ``doc``: the
    checkpoint (:func:`~evnoise.reconstruct.checkpoint.read_checkpoint`). Compared: the preset
    name, the noise parameters when the recording stores them, and the camera/sensor name when
    the recording names one.
    """
    card = doc.get("card") or {}
    spec = doc.get("input") or {}
    model_preset = card.get("preset")
    model_params = spec.get("params")
    out = []
    rec_preset = meta.get("preset")
    rec_params = meta.get("params") if isinstance(meta.get("params"), dict) else None
    differs = False
    if rec_params and model_params:
        for key in _PARAM_KEYS:
            a, b = _number(rec_params.get(key)), _number(model_params.get(key))
            if a is None or b is None:  # absent, or not a number (a recording's metadata is the stranger's)
                continue
            if not math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-12):
                differs = True
                break
    elif rec_preset and model_preset and Path(str(rec_preset)).stem != model_preset:
        differs = True
    if differs and rec_preset and model_preset and Path(str(rec_preset)).stem == model_preset:
        out.append(f"the model was trained with an earlier version of preset {model_preset} (its noise parameters "
                   f"differ from the recording's): the image may be biased; retrain for the current preset "
                   f"(evnoise train, or python -m evnoise.reconstruct.pretrain)")
    elif differs:
        out.append(f"the recording was made with preset {rec_preset or 'custom'} but the model was trained for "
                   f"preset {model_preset or 'custom'} (different noise parameters): the image may be wrong")
    rec_sensor = meta.get("camera") or meta.get("sensor")
    model_sensor = card.get("sensor")
    if (isinstance(rec_sensor, str) and rec_sensor.split() and isinstance(model_sensor, str)
            and rec_sensor.split()[0].lower() not in model_sensor.lower()):
        out.append(f"the recording's sensor is {rec_sensor} but the model was trained for {model_sensor}")
    return out


def _h5_source(path):
    """The events.h5 file as the readers open it (:class:`evnoise.readers.hdf5.H5Source`): every check
    ``evnoise info`` makes (its metadata, sensor size, ``/t_offset``, first and last event times), and a
    sensor size the file must give."""
    from ..readers.hdf5 import H5Source

    src = H5Source(path)
    if src.shape is None:
        src.close()
        raise InputError(f"{path} has no width/height attributes")
    return src


def _end_us(src) -> int:
    """End of the recording in µs on evnoise's clock (the file's ``t`` as stored): the stored ``t_end_us``
    (events lie before it), else last event + 1."""
    last = src.t_last_us - src.t_offset_us + 1 if src.n_events else 0
    end = src.meta.get("t_end_us")
    return last if end is None else max(int(end), last)


def h5_duration_s(path) -> float:
    """Length of the recording in seconds: its stored end time ``t_end_us`` when it has one
    (a 10 s simulation lasts 10 s even if its last event came earlier), else the time just
    after the last event (0 for an empty stream without ``t_end_us``)."""
    with _h5_source(path) as src:
        return _end_us(src) * 1e-6


def counts_from_h5(path, *, t_start_s: float = 0.0, window_s: float | None = None):
    """Counts ``(2, H, W)`` ``[ON, OFF]`` of ``[t_start, t_start + window)`` and the window used.

    Times are on evnoise's clock (the file's ``/events/t``; a DSEC ``/t_offset`` is checked, not
    added). The file is read as the readers read it (:mod:`evnoise.readers`: the same checks as
    ``evnoise info``), and the count maps the sensor size declares are checked against the memory
    budget before they are allocated.

    Parameters
    ----------
    path : str or os.PathLike
        An events.h5 file with the sensor's width and height.
    t_start_s : float, default 0.0
        Start of the window in seconds (>= 0); rounded to whole microseconds.
    window_s : float, optional
        Length of the window in seconds (> 0); it must end within the recording. Without it the
        window runs to the end of the recording (its stored ``t_end_us``, else just after the last event).

    Returns
    -------
    counts : numpy.ndarray
        Event counts of shape ``(2, H, W)``, ON then OFF, at full sensor resolution.
    window_s : float
        The window's length in seconds.
    """
    from ..readers.stats import pixel_counts

    if not (math.isfinite(t_start_s) and t_start_s >= 0):
        raise ParameterError(f"t_start_s must be >= 0 seconds, got {t_start_s!r}")
    if window_s is not None:
        window_s = check_positive(window_s, "window_s", "seconds")
    with _h5_source(path) as src:
        t0 = int(round(t_start_s * 1e6))
        end = _end_us(src)
        if window_s is None:
            if end <= t0:
                raise InputError(f"{path} has no events after t = {seconds_text(t_start_s)} s")
            t1 = end
            window_s = (t1 - t0) * 1e-6
        else:
            t1 = t0 + int(round(window_s * 1e6))
            if t1 > end:
                raise InputError(
                    f"the window {seconds_text(t_start_s)} s + {window_s:g} s runs past the end of the recording "
                    f"({end * 1e-6:.6g} s)"
                )
        off = src.t_offset_us
        counts, _ = pixel_counts(src.chunks(t0 + off, t1 + off), src.shape)
    return counts, float(window_s)


def counts_to_input(counts, window_s: float, spec) -> np.ndarray:
    """Binned counts ``(2, h, w)`` -> network input ``(C, h, w)`` float32 (see :class:`InputSpec`).

    Count channels are ``counts / (window_s * rate_scale_hz)`` (transform ``"rate"``) or
    ``sqrt(counts + 3/8) / sqrt(window_s * rate_scale_hz)`` (``"anscombe"``); with
    ``spec.ml_sigma`` set, the closed-form ML estimate of the display image follows as a last
    channel.
    """
    c = np.asarray(counts)
    if c.ndim != 3 or c.shape[0] != 2:
        raise InputError(f"counts must have shape (2, h, w), got {c.shape}")
    scale = float(window_s) * spec.rate_scale_hz
    x = c[list(spec.channels)].astype(np.float64)
    if getattr(spec, "transform", "rate") == "anscombe":
        x = np.sqrt(x + 0.375) / math.sqrt(scale)
    else:
        x = x / scale
    if getattr(spec, "ml_sigma", None) is not None:
        ml = spec.ml_inversion().display(c, float(window_s))
        x = np.concatenate([x, ml[None]], axis=0)
    return x.astype(np.float32)


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
        """Image ``(h, w)`` in ``[0, 1]`` from counts already binned like the training data.

        Parameters
        ----------
        counts : array_like, shape (2, h, w)
            ON and OFF counts summed over ``binning x binning`` blocks (:attr:`binning`).
        window_s : float
            Length of the counting window in seconds.

        Returns
        -------
        numpy.ndarray
            float32 display-encoded image of shape ``(h, w)``, clipped to ``[0, 1]``.

        Notes
        -----
        A window shorter than every window the model was trained on is shown to it as its counts
        scaled to the shortest trained window ``W`` (``counts * W / window_s`` over ``W``: the same
        rates; :func:`model_window`). Unscaled, the Anscombe input of a pixel without events,
        ``sqrt(3/8) / sqrt(window_s * rate_scale_hz)``, rises far above anything seen in training
        as the window shrinks (4.7x at 45 ms for a 1 s model), and the network answered with an
        all-black image.
        """
        seen = model_window(self.spec, float(window_s))
        if seen != float(window_s):
            counts = np.asarray(counts, dtype=np.float64) * (seen / float(window_s))
            window_s = seen
        x = self.torch.from_numpy(counts_to_input(counts, window_s, self.spec))[None]
        x = x.contiguous(memory_format=self.torch.channels_last)
        with self.torch.inference_mode():
            y = self.model(x)[0, 0]
        image = y.float().numpy()
        if not np.all(np.isfinite(image)):  # weights too large for float32 (finite ones are checked at loading)
            raise InputError(f"{self.path}: the model's output is not finite numbers on these counts (a damaged or "
                             f"foreign checkpoint)")
        return np.clip(image, 0.0, 1.0)

    def predict(self, counts, window_s: float, *, binning: int | None = None) -> np.ndarray:
        """Image from full-resolution counts ``(2, H, W)``: binned as in training, then the U-Net.

        Parameters
        ----------
        counts : array_like, shape (2, H, W)
            ON and OFF counts at full sensor resolution.
        window_s : float
            Length of the counting window in seconds.
        binning : int, optional
            When given, must equal the model's binning (a guard for callers that assume one).

        Returns
        -------
        numpy.ndarray
            float32 display-encoded image ``(H // binning, W // binning)`` in ``[0, 1]`` (see
            :meth:`predict_binned`).
        """
        if binning is not None and binning != self.spec.binning:
            raise ParameterError(
                f"the model was trained on {self.spec.binning}x{self.spec.binning}-binned counts; "
                f"binning {binning} does not match"
            )
        return self.predict_binned(bin_counts(counts, self.spec.binning), window_s)
