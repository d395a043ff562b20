"""Reconstructor checkpoints: weights plus everything needed to use and resume them.

A checkpoint is a ``torch.save``-d dict of tensors and plain Python values only, so it loads
with ``torch.load(path, weights_only=True)`` (no arbitrary code runs on load)::

    format           "evnoise-reconstructor"
    format_version   1
    evnoise_version  version that wrote it;  torch_version
    model            U-Net hyper-parameters (UNetConfig.to_dict())
    input            {"binning", "rate_scale_hz", "polarities", "window_s", "encoding", "max_lux"}
    state_dict       weights of the best model (lowest validation loss)
    train            training state: config, epoch, step, history, best_epoch, best_val,
                     last_state_dict, optimizer, elapsed_s, finished, data (description)

Files are written to a temporary name and renamed, so an interrupted save never leaves a
truncated checkpoint behind.
"""

from __future__ import annotations

import math
from pathlib import Path

from .._atomic import atomic_output
from .._version import __version__
from ..errors import InputError, ParameterError
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
]

FORMAT = "evnoise-reconstructor"
FORMAT_VERSION = 1
POLARITIES = {"both": (0, 1), "on": (0,), "off": (1,)}


class InputSpec:
    """How counts become network input: binning, polarities and the rate scale.

    Parameters
    ----------
    binning : int
        Counts are summed over ``binning x binning`` blocks before the network (paper: 2).
    rate_scale_hz : float
        Rates (events per second per *binned* pixel) are divided by this, so inputs are O(1).
    polarities : {"both", "on", "off"}
        Which count channels the network sees.
    window_s : float or None
        Integration window of the training data, seconds (a default for inference).
    max_lux : float or None
        Illuminance shown as white in the training targets, if known (for the ML baseline).
    """

    def __init__(self, *, binning: int = 2, rate_scale_hz: float = 1.0, polarities: str = "both",
                 window_s: float | None = None, max_lux: float | None = None, encoding: str = "srgb"):
        if isinstance(binning, bool) or not isinstance(binning, int) or binning < 1:
            raise ParameterError(f"binning must be an integer >= 1, got {binning!r}")
        if not (isinstance(rate_scale_hz, (int, float)) and math.isfinite(rate_scale_hz) and rate_scale_hz > 0):
            raise ParameterError(f"rate_scale_hz must be finite and > 0, got {rate_scale_hz!r}")
        if polarities not in POLARITIES:
            raise ParameterError(f"polarities must be one of {tuple(POLARITIES)}, got {polarities!r}")
        for name, v in (("window_s", window_s), ("max_lux", max_lux)):
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ParameterError(f"{name} must be finite and > 0 (or None), got {v!r}")
        self.binning = int(binning)
        self.rate_scale_hz = float(rate_scale_hz)
        self.polarities = polarities
        self.window_s = None if window_s is None else float(window_s)
        self.max_lux = None if max_lux is None else float(max_lux)
        self.encoding = str(encoding)

    @property
    def channels(self) -> tuple:
        return POLARITIES[self.polarities]

    def to_dict(self) -> dict:
        return {"binning": self.binning, "rate_scale_hz": self.rate_scale_hz, "polarities": self.polarities,
                "window_s": self.window_s, "max_lux": self.max_lux, "encoding": self.encoding}

    @classmethod
    def from_dict(cls, data: dict) -> "InputSpec":
        return cls(**data)

    def __repr__(self):
        return f"InputSpec({', '.join(f'{k}={v!r}' for k, v in self.to_dict().items())})"


def _atomic_torch_save(obj, path: Path):
    torch = require_torch()
    with atomic_output(path, what="checkpoint") as tmp:
        torch.save(obj, tmp)


def save_checkpoint(path, *, model_config, input_spec: InputSpec, state_dict, train_state=None) -> Path:
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
    }
    _atomic_torch_save(doc, Path(path))
    return Path(path)


def read_checkpoint(path) -> dict:
    """Load a checkpoint dict with ``weights_only=True`` and check that it is one of ours."""
    torch = require_torch()
    path = Path(path)
    if not path.exists():
        raise InputError(f"model file not found: {path}")
    if not path.is_file():
        raise InputError(f"model path is not a file: {path}")
    try:
        doc = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for foreign or corrupt files
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{path} is not a readable evnoise model checkpoint ({msg[:200]})") from None
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
    return doc


def load_model(path, *, which: str = "best"):
    """Build the U-Net of a checkpoint; returns ``(model, input_spec, doc)`` (model in eval mode).

    ``which="last"`` loads the weights of the last epoch instead of the best one.
    """
    from .unet import UNet, UNetConfig

    doc = read_checkpoint(path)
    try:
        config = UNetConfig.from_dict(dict(doc["model"]))
        spec = InputSpec.from_dict(dict(doc["input"]))
    except (ParameterError, TypeError) as exc:
        raise InputError(f"{path} has an invalid model description: {exc}") from None
    model = UNet(config=config)
    if which == "best":
        state = doc["state_dict"]
    elif which == "last":
        state = doc.get("train", {}).get("last_state_dict")
        if state is None:
            raise InputError(f"{path} holds no last-epoch weights")
    else:
        raise ParameterError(f"which must be 'best' or 'last', got {which!r}")
    try:
        model.load_state_dict(state)
    except (RuntimeError, KeyError) as exc:
        raise InputError(f"{path}: weights do not match the model description ({str(exc)[:200]})") from None
    model.eval()
    return model, spec, doc


def describe_checkpoint(path) -> str:
    """A few human-readable lines about a reconstructor checkpoint (for ``evnoise info``)."""
    doc = read_checkpoint(path)
    model = doc["model"]
    spec = doc["input"]
    train = doc.get("train") or {}
    n_params = sum(int(v.numel()) for v in doc["state_dict"].values())
    lines = [
        f"evnoise reconstructor checkpoint (format {doc['format_version']}, written by evnoise "
        f"{doc.get('evnoise_version', '?')}, torch {doc.get('torch_version', '?')})",
        f"model: U-Net, {n_params:,} parameters, base_channels={model.get('base_channels')}, "
        f"channel_mults={tuple(model.get('channel_mults', ()))}, stem={model.get('stem', 1)}",
        f"input: {spec.get('polarities')} polarities, {spec.get('binning')}x{spec.get('binning')} binning, "
        f"rates / {spec.get('rate_scale_hz'):.4g} Hz, trained window {spec.get('window_s')} s, "
        f"max_lux {spec.get('max_lux')}",
    ]
    if train:
        hist = train.get("history") or {}
        val = hist.get("val_loss") or []
        lines.append(
            f"training: {train.get('epoch', 0)} epochs, {train.get('step', 0)} steps, "
            f"{float(train.get('elapsed_s', 0.0)) / 60:.1f} min, "
            f"{'finished' if train.get('finished') else 'resumable (not finished)'}; "
            f"best epoch {train.get('best_epoch')} (val loss {train.get('best_val', float('nan')):.4g})"
            + (f", last val loss {val[-1]:.4g}" if val else "")
        )
        if train.get("data"):
            lines.append(f"data: {train['data']}")
    return "\n".join(lines)
