"""Reconstructor checkpoints: weights plus everything needed to use and resume them.

A checkpoint is a ``torch.save``-d dict of tensors and plain Python values only, so it loads
with ``torch.load(path, weights_only=True)`` (no arbitrary code runs on load)::

    format           "evnoise-reconstructor"
    format_version   1
    evnoise_version  version that wrote it;  torch_version
    model            U-Net hyper-parameters (UNetConfig.to_dict())
    input            {"binning", "rate_scale_hz", "polarities", "window_s", "encoding", "max_lux",
                     "transform", "ml_sigma", "params", "windows_s"}  (InputSpec.to_dict())
    state_dict       weights of the best model (lowest validation loss)
    train            training state: config, epoch, step, history, best_epoch, best_val,
                     last_state_dict, optimizer, elapsed_s, finished, data (description)
                     (a shipped model keeps everything but the last weights and the optimizer)
    card             model card (format 2): preset, sensor, windows, binning, training data,
                     steps, white-level range, held-out scores ... (plain values; may be empty)

Format 2 added the input transform, the optional ML-estimate channel, the trained windows and
the card; format-1 files load unchanged (their missing entries take the format-1 meaning).

Files are written to a temporary name and renamed, so an interrupted save never leaves a
truncated checkpoint behind.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import warnings
from pathlib import Path

from .._atomic import atomic_output, errno_of, os_error_text
from .._budget import human_bytes
from .._version import __version__
from ..errors import InputError, OutputError, ParameterError
from ._torch import require_torch

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "POLARITIES",
    "InputSpec",
    "save_checkpoint",
    "read_checkpoint",
    "load_model",
    "describe_checkpoint",
    "checkpoint_summary",
]

FORMAT = "evnoise-reconstructor"
FORMAT_VERSION = 2
POLARITIES = {"both": (0, 1), "on": (0,), "off": (1,)}
TRANSFORMS = ("rate", "anscombe")
#: Shortest integration window a model can be trained on (the events' clock counts microseconds).
MIN_WINDOW_S = 1e-6
#: Widest smoothing of the ML-estimate input channel (pixels; its Gaussian kernel is ~8 sigma wide).
MAX_ML_SIGMA = 1e4


class InputSpec:
    """How counts become network input: binning, polarities, the rate scale and the transform.

    Parameters
    ----------
    binning : int
        Counts are summed over ``binning x binning`` blocks before the network (paper: 2).
    rate_scale_hz : float
        Rates (events per second per *binned* pixel) are divided by this, so inputs are O(1).
    polarities : {"both", "on", "off"}
        Which count channels the network sees.
    window_s : float or None
        Default integration window for inference, seconds (the longest window trained on).
    max_lux : float or None
        Illuminance shown as white in the training targets, if known (for the ML baseline).
    encoding : str
        Display encoding of the training targets (``"srgb"``: the sRGB transfer function of
        ``lux / max_lux``); recorded, not checked.
    transform : {"rate", "anscombe"}
        ``"rate"``: ``counts / (window_s * rate_scale_hz)``. ``"anscombe"``: the variance-
        stabilised ``sqrt(counts + 3/8) / sqrt(window_s * rate_scale_hz)`` (Poisson noise of
        about the same size at every brightness, for a given window).
    ml_sigma : float or None
        When set, the closed-form maximum-likelihood estimate of the display image (from both
        polarities, counts smoothed with a Gaussian of this many binned pixels) is an extra
        input channel; needs ``params`` and ``max_lux``.
    params : dict or None
        The noise model of the training data (``NoiseParams.to_dict()``).
    windows_s : sequence of float or None
        Every integration window trained on (default: ``[window_s]``).
    """

    def __init__(self, *, binning: int = 2, rate_scale_hz: float = 1.0, polarities: str = "both",
                 window_s: float | None = None, max_lux: float | None = None, encoding: str = "srgb",
                 transform: str = "rate", ml_sigma: float | None = None, params: dict | None = None,
                 windows_s=None):
        if isinstance(binning, bool) or not isinstance(binning, int) or binning < 1:
            raise ParameterError(f"binning must be an integer >= 1, got {binning!r}")
        if not (isinstance(rate_scale_hz, (int, float)) and 1e-9 <= rate_scale_hz <= 1e9):
            raise ParameterError(f"rate_scale_hz must be between 1e-9 and 1e9 events/s, got {rate_scale_hz!r}")
        if polarities not in POLARITIES:
            raise ParameterError(f"polarities must be one of {tuple(POLARITIES)}, got {polarities!r}")
        for name, v in (("window_s", window_s), ("max_lux", max_lux)):
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ParameterError(f"{name} must be finite and > 0 (or None), got {v!r}")
        if window_s is not None and window_s < MIN_WINDOW_S:
            raise ParameterError(f"window_s must be at least {MIN_WINDOW_S:g} s (the events' 1 us clock), "
                                 f"got {window_s!r}")
        if transform not in TRANSFORMS:
            raise ParameterError(f"transform must be one of {TRANSFORMS}, got {transform!r}")
        if ml_sigma is not None:
            if not (isinstance(ml_sigma, (int, float)) and math.isfinite(ml_sigma) and 0 <= ml_sigma <= MAX_ML_SIGMA):
                raise ParameterError(f"ml_sigma must be between 0 and {MAX_ML_SIGMA:g} pixels (or None), "
                                     f"got {ml_sigma!r}")
            if params is None or max_lux is None:
                raise ParameterError("the ML-estimate input channel (ml_sigma) needs params and max_lux")
        if params is not None and not isinstance(params, dict):
            raise ParameterError(f"params must be a dict (NoiseParams.to_dict()), got {type(params).__name__}")
        if windows_s is not None:
            windows_s = [float(w) for w in windows_s]
            if not windows_s or not all(math.isfinite(w) and w >= MIN_WINDOW_S for w in windows_s):
                raise ParameterError(f"windows_s must be windows of at least {MIN_WINDOW_S:g} s, got {windows_s!r}")
        self.binning = int(binning)
        self.rate_scale_hz = float(rate_scale_hz)
        self.polarities = polarities
        self.window_s = None if window_s is None else float(window_s)
        self.max_lux = None if max_lux is None else float(max_lux)
        self.encoding = str(encoding)
        self.transform = transform
        self.ml_sigma = None if ml_sigma is None else float(ml_sigma)
        self.params = None if params is None else dict(params)
        if windows_s is None:
            windows_s = [] if self.window_s is None else [self.window_s]
        self.windows_s = sorted(set(windows_s))
        self._ml = None

    @property
    def channels(self) -> tuple:
        """Count channels used (0 = ON, 1 = OFF)."""
        return POLARITIES[self.polarities]

    @property
    def in_channels(self) -> int:
        """Channels of the network input (count channels, plus one for the ML estimate)."""
        return len(self.channels) + (1 if self.ml_sigma is not None else 0)

    def ml_inversion(self):
        """The :class:`~evnoise.reconstruct.baselines.MLInversion` of the ML input channel (cached)."""
        if self._ml is None:
            from ..params import NoiseParams
            from .baselines import MLInversion

            self._ml = MLInversion(NoiseParams.from_dict(self.params), max_lux=self.max_lux, binning=self.binning,
                                   smoothing_sigma=self.ml_sigma, grid_size=256, count_step=0.25)
        return self._ml

    def to_dict(self) -> dict:
        """The specification as plain values (the checkpoint's ``input`` entry).

        Returns
        -------
        dict
            The constructor's keyword arguments by name, ``windows_s`` as a sorted list; :meth:`from_dict`
            takes it back.
        """
        return {"binning": self.binning, "rate_scale_hz": self.rate_scale_hz, "polarities": self.polarities,
                "window_s": self.window_s, "max_lux": self.max_lux, "encoding": self.encoding,
                "transform": self.transform, "ml_sigma": self.ml_sigma, "params": self.params,
                "windows_s": list(self.windows_s)}

    @classmethod
    def from_dict(cls, data: dict) -> "InputSpec":
        """Rebuild a specification from :meth:`to_dict`'s values, checked as the constructor checks them.

        Parameters
        ----------
        data : dict
            Constructor keyword arguments by name; missing ones take their defaults (a format-1
            checkpoint's ``input`` entry loads this way).

        Returns
        -------
        InputSpec
            The specification.

        Raises
        ------
        ParameterError
            If a value is out of range.
        TypeError
            If ``data`` has a key that is not a constructor argument.
        """
        return cls(**data)

    def __repr__(self):
        shown = {k: v for k, v in self.to_dict().items() if k != "params"}
        return f"InputSpec({', '.join(f'{k}={v!r}' for k, v in shown.items())})"


def _tensor_bytes(obj, torch) -> int:
    """Bytes of the tensors in ``obj`` (dicts, lists and tuples walked): about the size of its checkpoint."""
    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return sum(_tensor_bytes(v, torch) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(_tensor_bytes(v, torch) for v in obj)
    return 0


def _save_failure(exc: BaseException, path: Path, tmp: Path, needed: int) -> str:
    """Why a checkpoint could not be written, in one line: the errno's text where the error gives one, else a full
    disk when the folder has no room left for it (torch's zip writer reports a full disk as ``RuntimeError("[enforce
    fail at inline_container.cc:672] . unexpected pos ...")``, with no errno), else torch's words without their
    C++ prefix."""
    if errno_of(exc):
        return os_error_text(exc)
    folder = path.parent
    try:
        free = shutil.disk_usage(folder).free
        written = os.path.getsize(tmp) if os.path.exists(tmp) else 0
    except (OSError, ValueError):
        free = None
    if free is not None and free < max(needed - written, 0) + (1 << 20):  # the partial file still holds its part
        return (f"the disk is full ({human_bytes(free)} free in {folder}; the checkpoint needs about "
                f"{human_bytes(needed)}): free some space or write it elsewhere")
    text = re.sub(r"^\[enforce fail at [^\]]*\]\s*\.?\s*", "", " ".join(str(exc).split()))
    return f"torch could not write it ({text[:200] or type(exc).__name__})"


def _atomic_torch_save(obj, path: Path):
    torch = require_torch()
    with atomic_output(path, what="checkpoint") as tmp:
        try:
            torch.save(obj, tmp)
        except (RuntimeError, OSError) as exc:  # torch's zip writer reports a full disk or an I/O error as RuntimeError
            why = _save_failure(exc, path, tmp, _tensor_bytes(obj, torch))
            raise OutputError(f"cannot write checkpoint {path}: {why}") from None


def save_checkpoint(path, *, model_config, input_spec: InputSpec, state_dict, train_state=None,
                    card: dict | None = None) -> Path:
    """Write a checkpoint (see the module docstring for the layout); returns the path."""
    torch = require_torch()
    doc = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "evnoise_version": __version__,
        "torch_version": str(torch.__version__),
        "model": model_config.to_dict(),
        "input": input_spec.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in state_dict.items()},
        "train": train_state if train_state is not None else {},
        "card": dict(card) if card else {},
    }
    _atomic_torch_save(doc, Path(path))
    return Path(path)


def read_checkpoint(path) -> dict:
    """Load a checkpoint dict with ``weights_only=True`` and check that it is one of ours.

    Parameters
    ----------
    path : str or os.PathLike
        The checkpoint file.

    Returns
    -------
    dict
        The checkpoint's entries (see the module docstring), tensors on the CPU.

    Raises
    ------
    InputError
        If the file is missing, is not an evnoise reconstructor checkpoint, has a newer format
        version, is incomplete or damaged, or declares more data than a model can hold.
    """
    torch = require_torch()
    path = Path(path)
    if not path.exists():
        raise InputError(f"model file not found: {path}")
    if not path.is_file():
        raise InputError(f"model path is not a file: {path}")
    _check_archive_size(path)
    try:
        with warnings.catch_warnings():  # torch warns about the pickle protocol of files that are not ours
            warnings.simplefilter("ignore", UserWarning)
            doc = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for foreign or corrupt files
        # torch's own text talks about weights_only and unpickling: say what it means here
        import pickle
        import zipfile

        if isinstance(exc, pickle.UnpicklingError) and zipfile.is_zipfile(path):
            why = "a PyTorch file holding objects other than plain tensors and values"
        elif zipfile.is_zipfile(path):
            why = "a damaged or foreign PyTorch file"
        else:
            why = _not_a_zip_why(path)
        raise InputError(f"{path} is not an evnoise model checkpoint ({why})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"{path} is not an evnoise reconstructor checkpoint")
    version = doc.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise InputError(
            f"{path} has checkpoint format version {version!r}; this evnoise ({__version__}) reads "
            f"versions up to {FORMAT_VERSION} - upgrade evnoise"
        )
    for key in ("model", "input", "state_dict"):
        if key not in doc:
            raise InputError(f"{path} is an incomplete checkpoint (no {key!r})")
    problem = _damaged_entry(doc, torch)
    if problem:
        raise InputError(f"{path} is a damaged checkpoint: {problem}")
    return doc


#: Most bytes a checkpoint may hold once loaded: the largest U-Net evnoise builds
#: (:data:`~evnoise.reconstruct.unet.MAX_PARAMETERS` float32 weights) four times over (best and last weights,
#: the optimiser's two moments), plus 256 MiB for the rest.
MAX_CHECKPOINT_BYTES = 4 * 4 * 250_000_000 + (256 << 20)
#: Most a checkpoint's archive may hold beyond the bytes of the file itself (``torch.save`` stores its members
#: uncompressed: data that inflate far beyond the file are a compression bomb, not a model); files below
#: :data:`INFLATION_FREE_BYTES` of content are not looked at this way.
MAX_INFLATION = 8
INFLATION_FREE_BYTES = 64 << 20


def _check_archive_size(path: Path) -> None:
    """Refuse a checkpoint whose zip directory declares more data than a model can hold, far more than the file
    (a compression bomb), or more than the memory budget, before ``torch.load`` inflates any of it. Only the
    directory is read (:mod:`zipfile`); a file that is no zip archive is left to ``torch.load`` to refuse."""
    import zipfile

    from .._budget import check_allocation, human_bytes

    try:
        with zipfile.ZipFile(path) as archive:
            declared = sum(int(info.file_size) for info in archive.infolist())
        size = path.stat().st_size
    except (OSError, zipfile.BadZipFile, ValueError, EOFError, RuntimeError, NotImplementedError):
        return  # not an archive zipfile reads: torch.load's error (and _not_a_zip_why) says what it is
    if declared > MAX_CHECKPOINT_BYTES:
        raise InputError(f"{path} declares {human_bytes(declared)} of data, more than the "
                         f"{human_bytes(MAX_CHECKPOINT_BYTES)} of the largest model evnoise builds (a damaged or "
                         f"hostile file)")
    if declared > INFLATION_FREE_BYTES and declared > MAX_INFLATION * size:
        raise InputError(f"{path} declares {human_bytes(declared)} of data in a file of {human_bytes(size)}: "
                         f"compressed far beyond any checkpoint evnoise writes (a compression bomb?)")
    check_allocation(declared, f"loading the checkpoint {path}")


def _not_a_zip_why(path: Path) -> str:
    """Why a file that :mod:`zipfile` does not take (PyTorch saves zip archives) is no checkpoint: empty, the start
    of an archive whose end is missing (a copy or download cut short), or something else."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as exc:
        return f"cannot be read: {exc.strerror or exc}"
    if not head:
        return "an empty file"
    if head == b"PK\x03\x04":
        return "a PyTorch file cut short: its end is missing (an interrupted copy or download?)"
    return "not a PyTorch file"


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _is_weights(v, torch) -> bool:
    return isinstance(v, dict) and all(isinstance(k, str) and isinstance(t, torch.Tensor) for k, t in v.items())


#: What the readers of a checkpoint take from its ``train`` and ``card`` entries: each entry's test and what it is.
_TRAIN_KINDS = {
    "config": (lambda v, t: isinstance(v, dict), "a table"),
    "epoch": (lambda v, t: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "a whole number >= 0"),
    "step": (lambda v, t: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "a whole number >= 0"),
    "best_epoch": (lambda v, t: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "a whole number >= 0"),
    "best_val": (lambda v, t: _is_number(v), "a number"),
    "elapsed_s": (lambda v, t: _is_number(v), "a number"),
    "finished": (lambda v, t: isinstance(v, bool), "true or false"),
    "data": (lambda v, t: isinstance(v, str), "text"),
    "history": (lambda v, t: isinstance(v, dict) and all(isinstance(x, list) and all(_is_number(y) for y in x)
                                                         for x in v.values()), "a table of lists of numbers"),
    "last_state_dict": (_is_weights, "a table of tensors"),
    "optimizer": (lambda v, t: isinstance(v, dict), "a table"),
}
_CARD_KINDS = {
    "preset": (lambda v: isinstance(v, str), "text"),
    "sensor": (lambda v: isinstance(v, str), "text"),
    "training_data": (lambda v: isinstance(v, str), "text"),
    "recipe": (lambda v: isinstance(v, str), "text"),
    "white_lux_range": (lambda v: isinstance(v, list) and len(v) == 2 and all(_is_number(x) and math.isfinite(x)
                                                                                for x in v), "two numbers"),
    "validation": (lambda v: isinstance(v, dict), "a table"),
    "held_out_scores": (lambda v: isinstance(v, dict) and all(isinstance(x, dict) for x in v.values()),
                        "a table of tables"),
}


def _damaged_entry(doc: dict, torch) -> str:
    """What is not of the kind its readers take in a checkpoint (``""``: nothing), so that a damaged file is one
    error line naming the entry instead of a TypeError or AttributeError where it is used."""
    for key in ("model", "input"):
        if not isinstance(doc[key], dict):
            return f"{key!r} is not a table"
    if not _is_weights(doc["state_dict"], torch):
        return "'state_dict' is not a table of tensors"
    for key, kinds in (("train", _TRAIN_KINDS), ("card", _CARD_KINDS)):
        block = doc.get(key)
        if block is None:
            continue
        if not isinstance(block, dict):
            return f"{key!r} is not a table"
        for name, (test, what) in kinds.items():
            value = block.get(name)
            if value is not None and not (test(value, torch) if key == "train" else test(value)):
                return f"{key}[{name!r}] is not {what}"
    return ""


def load_model(path, *, which: str = "best"):
    """Build the U-Net of a checkpoint; returns ``(model, input_spec, doc)`` (model in eval mode).

    Parameters
    ----------
    path : str or os.PathLike
        The checkpoint file.
    which : {"best", "last"}, default "best"
        ``"best"``: the weights of the lowest validation loss; ``"last"``: those of the last epoch
        (an :class:`~evnoise.errors.InputError` when the checkpoint holds none, e.g. a shipped model).

    Returns
    -------
    model : UNet
        The network on the CPU, in eval mode.
    input_spec : InputSpec
        How counts become its input.
    doc : dict
        The checkpoint's entries, as :func:`read_checkpoint` returns them.

    Notes
    -----
    The checkpoint of an unfinished training run loads, with a warning on the ``evnoise`` logger.
    """
    from .unet import UNet, UNetConfig

    doc = read_checkpoint(path)
    try:
        config = UNetConfig.from_dict(dict(doc["model"]))
        spec = InputSpec.from_dict(dict(doc["input"]))
    except (ParameterError, TypeError, ValueError) as exc:  # a size beyond UNetConfig's limits included
        # the names are the file's entries (quoted: the command line would write them as its flags)
        text = re.sub(r"(?<![\w'])(window_s|windows_s|ml_sigma|rate_scale_hz|max_lux|binning)(?![\w'])", r"'\1'",
                      str(exc))
        raise InputError(f"{path} has an invalid model description: {text}") from None
    model = UNet(config=config)
    if which == "best":
        state = doc["state_dict"]
    elif which == "last":
        state = (doc.get("train") or {}).get("last_state_dict")
        if state is None:
            raise InputError(f"{path} holds no last-epoch weights")
    else:
        raise ParameterError(f"which must be 'best' or 'last', got {which!r}")
    try:
        model.load_state_dict(state)
    except (RuntimeError, KeyError) as exc:  # (torch's message is several indented lines)
        raise InputError(f"{path}: weights do not match the model description ({' '.join(str(exc).split())[:200]})"
                         ) from None
    torch = require_torch()
    bad = [name for name, value in state.items() if value.is_floating_point() and not bool(torch.isfinite(value).all())]
    if bad:
        raise InputError(f"{path} is a damaged checkpoint: weights that are not finite numbers ({bad[0]}"
                         f"{f' and {len(bad) - 1} more' if len(bad) > 1 else ''})")
    model.eval()
    run = doc.get("train") or {}
    if run.get("finished") is False:  # an interrupted or running training: usable, but say so
        import logging

        logging.getLogger("evnoise").warning(
            "%s is the checkpoint of an unfinished training run (epoch %s of %s); its %s epoch's weights are used",
            path, run.get("epoch", "?"), (run.get("config") or {}).get("epochs", "?"), which)
    return model, spec, doc


_METHOD_NAMES = {"unet": "U-Net", "counts-affine": "count image, affine fit (oracle)",
                 "counts-minmax": "count image, min-max"}


def _scores(vals: dict) -> dict:
    """Held-out scores as numbers, units in the keys (None where not measured)."""
    return {"psnr_db": vals.get("psnr"), "ssim": vals.get("ssim"), "lpips": vals.get("lpips")}


def checkpoint_summary(path) -> dict:
    """``{label: value}`` about a reconstructor checkpoint, model card first (for ``evnoise info``).

    Parameters
    ----------
    path : str or os.PathLike
        The checkpoint file.

    Returns
    -------
    dict
        Labels to plain values (text, numbers, lists, or nested dicts for the training state and the
        scores); ``None`` where a value was not recorded.
    """
    doc = read_checkpoint(path)
    model = doc["model"]
    spec = doc["input"]
    train = doc.get("train") or {}
    card = doc.get("card") or {}
    n_params = sum(int(v.numel()) for v in doc["state_dict"].values())
    out = {"checkpoint": f"evnoise reconstructor (format {doc['format_version']}, written by evnoise "
                         f"{doc.get('evnoise_version', '?')}, torch {doc.get('torch_version', '?')})"}
    if card.get("preset"):
        out["preset"] = card["preset"]
    if card.get("sensor"):
        out["sensor"] = card["sensor"]
    windows = spec.get("windows_s") or ([spec.get("window_s")] if spec.get("window_s") else [])
    out["windows_s"] = [float(w) for w in windows] if windows else "not recorded"
    out["default_window_s"] = spec.get("window_s")
    out["binning"] = f"{spec.get('binning')}x{spec.get('binning')}"
    out["input"] = (f"{spec.get('polarities')} polarities, {spec.get('transform', 'rate')} of the counts"
                    + (f" + ML estimate (sigma {spec['ml_sigma']:g})" if spec.get("ml_sigma") is not None else "")
                    + f", rates / {spec.get('rate_scale_hz'):.4g} Hz")
    out["white_lux"] = spec.get("max_lux")
    if card.get("white_lux_range"):
        lo, hi = card["white_lux_range"]
        out["white_lux_range"] = [float(lo), float(hi)]  # scene white, drawn log-uniform
    out["model"] = (f"U-Net, {n_params:,} parameters, base_channels={model.get('base_channels')}, "
                    f"channel_mults={tuple(model.get('channel_mults', ()))}, stem={model.get('stem', 1)}")
    if card.get("training_data") or train.get("data"):
        out["training_data"] = card.get("training_data") or train.get("data")
    if train:
        hist = train.get("history") or {}
        val = hist.get("val_loss") or []
        best_val = train.get("best_val")
        out["training"] = {
            "epochs": train.get("epoch", 0), "steps": train.get("step", 0),
            "batch_size": train.get("config", {}).get("batch_size"),
            "minutes": round(float(train.get("elapsed_s", 0.0)) / 60, 1), "finished": bool(train.get("finished")),
            "best_epoch": train.get("best_epoch"),
            "best_val_loss": None if best_val is None or not math.isfinite(best_val) else float(best_val),
            "last_val_loss": float(val[-1]) if val else None,
        }
    validation = card.get("validation") or {}
    if validation:
        out["validation"] = {"psnr_db": validation.get("psnr_db"), "ssim": validation.get("ssim")}
    scores = card.get("held_out_scores") or {}
    if scores:
        block = {}
        for test, methods in scores.items():
            block[test] = {"pairs": methods.get("pairs")}
            for m, vals in methods.items():
                if isinstance(vals, dict):
                    name = _METHOD_NAMES.get(m, m.replace("ml-inversion@", "ML inversion, sigma ")
                                           .replace("ml-inversion", "ML inversion"))
                    block[test][name] = _scores(vals)
        out["held_out_scores"] = block
    if card.get("recipe"):
        out["recipe"] = card["recipe"]
    return out


def describe_checkpoint(path) -> str:
    """Human-readable lines about a reconstructor checkpoint, its model card included.

    Parameters
    ----------
    path : str or os.PathLike
        The checkpoint file.

    Returns
    -------
    str
        :func:`checkpoint_summary` as ``label: value`` lines, nested entries indented.
    """
    lines = []

    def add(block: dict, indent: str) -> None:
        for key, value in block.items():
            if isinstance(value, dict):
                lines.append(f"{indent}{key}:")
                add(value, indent + "  ")
            else:
                text = "-" if value is None else f"{value:.4g}" if isinstance(value, float) else value
                lines.append(f"{indent}{key}: {text}")

    add(checkpoint_summary(path), "")
    return "\n".join(lines)
