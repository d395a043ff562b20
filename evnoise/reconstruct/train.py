"""Training loop of the reconstructor (CPU friendly, reproducible, resumable).

Randomness is derived from ``(seed, epoch, step, slot)`` with :class:`numpy.random.SeedSequence`
(crops, augmentation, on-the-fly count draws) and from ``seed`` alone for the initial weights,
so a run resumed from its checkpoint continues exactly as an uninterrupted run would (resume
happens at epoch boundaries). Global random state is never touched.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._atomic import AtomicFile, os_error_text, refuse_folder_name
from ..errors import InputError, OutputError, ParameterError
from .checkpoint import InputSpec, read_checkpoint, save_checkpoint
from .data import Subset, dataset_sources, item_seed, random_crop, split_by_source
from .infer import counts_to_input

__all__ = ["TrainConfig", "train", "plot_history", "DEFAULT_MODEL"]

log = logging.getLogger("evnoise")

# small enough to train in minutes on two cores and to run 640x360 in well under a second
DEFAULT_MODEL = {"base_channels": 16, "channel_mults": (1, 2, 4, 4), "blocks_per_level": 1, "groups": 8,
                 "stem": 2}


@dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (all keyword-only through the dataclass; stored in checkpoints).

    Parameters
    ----------
    epochs : int
        Maximum number of epochs (an epoch is ``steps_per_epoch`` batches of random crops).
    steps_per_epoch : int
        Batches per epoch.
    batch_size : int
        Crops per batch.
    crop : int
        Side of the training crops in binned pixels.
    lr, weight_decay : float
        AdamW learning rate (cosine-decayed to ``lr / 20`` over ``epochs``) and weight decay.
    ssim_weight : float
        Loss = pixel loss + ``ssim_weight`` * (1 - SSIM) (Gaussian window, sigma 1.5).
    patience : int or None
        Early stopping: stop after this many epochs without a lower validation loss.
    max_minutes : float or None
        Wall-clock budget (all resumed sessions together); training stops after the step that
        exceeds it, then validates and saves.
    val_fraction : float
        Share of *source images* held out for validation when no validation set is given.
    val_crop : int or None
        Validation images are centre-cropped to at most this side (None: whole images).
    polarities : {"both", "on", "off"}
        Count channels the network sees.
    augment : bool
        Random flips and 90-degree rotations of the crops.
    seed : int
        Seed of everything random.
    transform : {"rate", "anscombe"}
        Input transform of the counts (see :class:`~evnoise.reconstruct.checkpoint.InputSpec`).
    ml_sigma : float or None
        Add the closed-form ML estimate (counts smoothed with this Gaussian sigma, binned
        pixels) as an input channel; needs a dataset with ``params`` and ``max_lux``.
    pixel_loss : {"l1", "mse"}
        Pixel term of the loss: mean absolute error (favours the median of what the counts allow,
        sharp) or mean squared error (favours the mean, which is what PSNR scores).
    """

    epochs: int = 60
    steps_per_epoch: int = 50
    batch_size: int = 16
    crop: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    ssim_weight: float = 0.2
    patience: int | None = 12
    max_minutes: float | None = None
    val_fraction: float = 0.15
    val_crop: int | None = 128
    polarities: str = "both"
    augment: bool = True
    seed: int = 0
    transform: str = "rate"
    ml_sigma: float | None = None
    pixel_loss: str = "l1"

    def __post_init__(self):
        for name in ("epochs", "steps_per_epoch", "batch_size", "crop"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ParameterError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("lr",):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ParameterError(f"{name} must be finite and > 0, got {v!r}")
        for name in ("weight_decay", "ssim_weight"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ParameterError(f"{name} must be finite and >= 0, got {v!r}")
        if self.patience is not None and (not isinstance(self.patience, int) or self.patience < 1):
            raise ParameterError(f"patience must be an integer >= 1 or None, got {self.patience!r}")
        if self.max_minutes is not None and not (math.isfinite(self.max_minutes) and self.max_minutes > 0):
            raise ParameterError(f"max_minutes must be > 0 or None, got {self.max_minutes!r}")
        if not 0 < self.val_fraction < 1:
            raise ParameterError(f"val_fraction must be in (0, 1), got {self.val_fraction!r}")
        if self.val_crop is not None and (not isinstance(self.val_crop, int) or self.val_crop < 8):
            raise ParameterError(f"val_crop must be an integer >= 8 or None, got {self.val_crop!r}")
        if self.polarities not in ("both", "on", "off"):
            raise ParameterError(f"polarities must be 'both', 'on' or 'off', got {self.polarities!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ParameterError(f"seed must be a non-negative integer, got {self.seed!r}")
        if self.transform not in ("rate", "anscombe"):
            raise ParameterError(f"transform must be 'rate' or 'anscombe', got {self.transform!r}")
        if self.pixel_loss not in ("l1", "mse"):
            raise ParameterError(f"pixel_loss must be 'l1' or 'mse', got {self.pixel_loss!r}")
        if self.ml_sigma is not None and not (math.isfinite(self.ml_sigma) and self.ml_sigma >= 0):
            raise ParameterError(f"ml_sigma must be >= 0 or None, got {self.ml_sigma!r}")

    def to_dict(self) -> dict:
        """The settings as plain values (the checkpoint's ``train["config"]`` entry).

        Returns
        -------
        dict
            Every field by name; ``TrainConfig(**d)`` rebuilds the configuration.
        """
        return dataclasses.asdict(self)


# settings that may change when a run is resumed (budget and stopping rule only)
_RESUMABLE_CHANGES = {"epochs", "max_minutes", "patience"}


def _augment(counts, image, rng, enabled):
    if not enabled:
        return counts, image
    k = int(rng.integers(4))
    flip = bool(rng.integers(2))
    counts = np.rot90(counts, k, axes=(1, 2))
    image = np.rot90(image, k)
    if flip:
        counts = counts[:, :, ::-1]
        image = image[:, ::-1]
    return np.ascontiguousarray(counts), np.ascontiguousarray(image)


def _draw_pair(dataset, index, rng, crop):
    if hasattr(dataset, "sample"):
        return dataset.sample(index, rng, crop)
    return random_crop(dataset[index], crop, rng)


def _centre_crop(item, size):
    if size is None:
        return item
    h, w = np.asarray(item["image"]).shape
    if h <= size and w <= size:
        return item
    r0, c0 = max(0, (h - size) // 2), max(0, (w - size) // 2)
    out = dict(item)
    out["counts"] = np.asarray(item["counts"])[:, r0:r0 + size, c0:c0 + size]
    out["image"] = np.asarray(item["image"])[r0:r0 + size, c0:c0 + size]
    return out


def dataset_windows(dataset, n=64) -> list:
    """Integration windows (s) of a pair dataset: its ``windows_s`` attribute, else those of up to ``n`` items."""
    windows = getattr(dataset, "windows_s", None)
    if windows:
        return sorted({float(w) for w in windows})
    idx = np.linspace(0, len(dataset) - 1, min(n, len(dataset))).round().astype(int)
    return sorted({float(dataset[int(i)]["window_s"]) for i in set(idx.tolist())})


def _data_fingerprint(train_data, val_data) -> str:
    """A digest of what a run trains and validates on (each set's size, sources, windows and the target images of
    up to four of its items): a resumed run must continue on the same."""
    import hashlib
    import json

    digest = hashlib.sha256()
    for d in (train_data, val_data):
        digest.update(json.dumps([len(d), sorted(dataset_sources(d)), dataset_windows(d)]).encode())
        for i in sorted({int(i) for i in np.linspace(0, len(d) - 1, min(4, len(d))).round()}):
            digest.update(np.ascontiguousarray(d[i]["image"], dtype=np.float32).tobytes())
    return digest.hexdigest()


def _estimate_rate_scale(dataset, n=16) -> float:
    """Mean event rate (both polarities, per binned pixel) over up to ``n`` items, in Hz."""
    idx = np.linspace(0, len(dataset) - 1, min(n, len(dataset))).round().astype(int)
    total = 0.0
    pixels = 0
    for i in sorted(set(idx.tolist())):
        item = dataset[i]
        c = np.asarray(item["counts"], dtype=np.float64)
        total += c.sum() / float(item["window_s"]) / 2.0
        pixels += c.shape[1] * c.shape[2]
    rate = total / max(pixels, 1)
    return rate if rate > 0 else 1.0


def _ssim_loss(torch, pred, target):
    F = torch.nn.functional
    coords = torch.arange(11, dtype=pred.dtype) - 5
    g = torch.exp(-(coords**2) / (2 * 1.5**2))
    g = (g / g.sum())
    w = (g[:, None] * g[None, :]).view(1, 1, 11, 11)
    if pred.shape[-1] < 11 or pred.shape[-2] < 11:
        return pred.new_zeros(())
    mu_p, mu_t = F.conv2d(pred, w), F.conv2d(target, w)
    s_pp = F.conv2d(pred * pred, w) - mu_p**2
    s_tt = F.conv2d(target * target, w) - mu_t**2
    s_pt = F.conv2d(pred * target, w) - mu_p * mu_t
    c1, c2 = 0.01**2, 0.03**2
    ssim = ((2 * mu_p * mu_t + c1) * (2 * s_pt + c2)) / ((mu_p**2 + mu_t**2 + c1) * (s_pp + s_tt + c2))
    return 1.0 - ssim.mean()


def training_loss(torch, pred, target, config: TrainConfig):
    """The loss ``config`` asks for: the pixel term (L1 or MSE) plus ``ssim_weight`` * (1 - SSIM)."""
    diff = pred - target
    loss = (diff * diff).mean() if config.pixel_loss == "mse" else diff.abs().mean()
    if config.ssim_weight > 0:
        loss = loss + config.ssim_weight * _ssim_loss(torch, pred, target)
    return loss


def describe_loss(config: TrainConfig) -> str:
    """The loss of ``config`` in words, for plots."""
    pixel = "MSE" if config.pixel_loss == "mse" else "L1"
    return f"{pixel} + {config.ssim_weight:g} (1 - SSIM)" if config.ssim_weight > 0 else pixel


def plot_history(history: dict, path, *, loss_label: str = "L1 + w (1 - SSIM)") -> Path | None:
    """Loss curves (train and validation loss, validation PSNR) as a PNG; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("matplotlib is not installed: no loss-curve plot (pip install 'evnoise[plot]')")
        return None
    path = Path(path)
    epochs = np.arange(1, len(history.get("train_loss", [])) + 1)
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    ax[0].plot(epochs, history.get("train_loss", []), ".-", label="train (crops)")
    ax[0].plot(epochs, history.get("val_loss", []), ".-", label="validation")
    ax[0].set_xlabel("epoch")
    ax[0].set_ylabel(f"loss ({loss_label})")
    ax[0].legend()
    ax[1].plot(epochs, history.get("val_psnr", []), ".-", color="C2")
    ax[1].set_xlabel("epoch")
    ax[1].set_ylabel("validation PSNR (dB)")
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    out = AtomicFile(path, what="plot", suffix=".tmp.png")
    try:
        fig.savefig(out.tmp, dpi=110)
        out.commit()
    except OSError as exc:
        out.discard()
        raise OutputError(f"cannot write plot {path}: {os_error_text(exc)}") from None
    finally:
        plt.close(fig)
    return path


def train(train_data, out, *, val_data=None, config: TrainConfig | None = None, model: dict | None = None,
          resume: bool = False, overwrite: bool = False, progress: bool = True, plot=True,
          threads: int | None = None, data_description: str | None = None, on_epoch_end=None,
          card: dict | None = None) -> dict:
    """Train a U-Net reconstructor on a pair dataset and write the checkpoint ``out``.

    Parameters
    ----------
    train_data : pair dataset
        See :mod:`evnoise.reconstruct.data` (``ResampledPairs`` re-draws counts each epoch).
    out : path
        Checkpoint to write (best weights plus the resumable training state), after every epoch.
    val_data : pair dataset, optional
        Validation pairs. Without it, ``config.val_fraction`` of the *source images* of
        ``train_data`` are held out.
    config : TrainConfig
        Training hyper-parameters.
    model : dict, optional
        U-Net settings (:class:`~evnoise.reconstruct.unet.UNetConfig` fields) overriding
        :data:`DEFAULT_MODEL`; ``in_channels`` follows ``config.polarities``.
    resume : bool
        Continue the run stored in ``out`` (same data, model and settings; ``epochs``,
        ``max_minutes`` and ``patience`` may be raised).
    overwrite : bool
        Replace an existing ``out`` when not resuming.
    progress : bool
        Show a progress bar.
    plot : bool or path
        Write loss curves to ``<out stem>.loss.png`` (or to the given path) after every epoch.
    threads : int, optional
        Torch CPU threads for this run (restored afterwards).
    on_epoch_end : callable, optional
        Called as ``on_epoch_end(epoch, history)`` after each epoch's checkpoint is written;
        returning True stops the run there (it stays resumable).
    card : dict, optional
        Model card stored in the checkpoint (see :mod:`~evnoise.reconstruct.checkpoint`); the
        trainer adds the windows, binning, steps and validation scores.

    Returns
    -------
    dict
        Summary: ``epochs``, ``steps``, ``best_epoch``, ``best_val``, ``elapsed_s``, ``history``,
        ``stopped`` (``"epochs"``, ``"early-stopping"``, ``"time-budget"`` or ``"callback"``),
        ``out``, ``plot``, ``val_psnr`` and ``val_ssim`` (of the best epoch).

    Notes
    -----
    The learning rate follows a cosine over ``epochs * steps_per_epoch`` steps; raising
    ``epochs`` when resuming stretches the remaining schedule.
    """
    from ._torch import require_torch
    from .unet import UNet, UNetConfig

    torch = require_torch()
    config = TrainConfig() if config is None else config
    if not isinstance(config, TrainConfig):
        raise ParameterError(f"config must be a TrainConfig, got {type(config).__name__}")
    refuse_folder_name(out, "checkpoint")
    out = Path(out)
    if not out.parent.is_dir():
        raise OutputError(f"output folder {out.parent} does not exist")
    if os.path.lexists(out) and not resume and not overwrite:  # a link counts, even a broken one
        raise OutputError(f"{out} exists: use resume=True to continue it or overwrite=True to replace it")
    if len(train_data) == 0:
        raise InputError("the training set is empty")

    if val_data is None:
        train_idx, val_idx = split_by_source(train_data, val_fraction=config.val_fraction, seed=config.seed)
        val_data = Subset(train_data, val_idx)
        train_data = Subset(train_data, train_idx)
    elif len(val_data) == 0:
        raise InputError("the validation set is empty")
    overlap = set(dataset_sources(train_data)) & set(dataset_sources(val_data))
    if overlap:
        raise InputError(f"source image(s) in both training and validation sets: {sorted(overlap)[:5]}")

    fingerprint = _data_fingerprint(train_data, val_data)
    state = None
    settings = dict(DEFAULT_MODEL)
    settings.update(model or {})
    settings["in_channels"] = 2 if config.polarities == "both" else 1
    settings["in_channels"] += 1 if config.ml_sigma is not None else 0
    model_config = UNetConfig(**settings)
    if resume:
        if not out.exists():
            raise InputError(f"cannot resume: {out} does not exist")
        doc = read_checkpoint(out)
        state = doc.get("train") or {}
        if "optimizer" not in state or "last_state_dict" not in state:
            raise InputError(f"cannot resume {out}: it holds no training state")
        old = dict(state.get("config", {}))
        new = config.to_dict()
        defaults = TrainConfig().to_dict()  # a setting added later: the old run used its default
        changed = sorted(k for k in new if k not in _RESUMABLE_CHANGES and old.get(k, defaults[k]) != new[k])
        if changed:
            listed = ", ".join(f"{k}={new[k]!r} (the run's: {old.get(k, defaults[k])!r})" for k in changed)
            raise ParameterError(f"cannot resume {out} with different settings: {listed}")
        if dict(doc["model"]) != model_config.to_dict():
            raise ParameterError(f"cannot resume {out}: the model settings differ")
        if state.get("data_fingerprint", fingerprint) != fingerprint:  # (checkpoints before it have none)
            raise ParameterError(f"cannot resume {out}: its run trained on other data (other pairs, sources or windows "
                                 f"in the training or validation set); train anew with overwrite=True")
        spec = InputSpec.from_dict(dict(doc["input"]))
    else:
        windows = dataset_windows(train_data)
        max_lux = getattr(train_data, "max_lux", None)
        params = getattr(train_data, "params", None)
        if config.ml_sigma is not None and (params is None or max_lux is None):
            raise ParameterError("the ML-estimate input channel needs a dataset that records its noise "
                                 "parameters and white level (params, max_lux)")
        # the longest window is the default for inference: the least noisy one trained on
        spec = InputSpec(binning=int(getattr(train_data, "binning", 2)), rate_scale_hz=_estimate_rate_scale(train_data),
                         polarities=config.polarities, window_s=max(windows), windows_s=windows,
                         max_lux=None if max_lux is None else float(max_lux), transform=config.transform,
                         ml_sigma=config.ml_sigma, params=None if params is None else params.to_dict())
    if config.crop % model_config.multiple:
        raise ParameterError(f"crop must be a multiple of {model_config.multiple} for this model, got {config.crop}")
    card = _with_preset(dict(card or {}), getattr(train_data, "preset", None))

    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(max(1, int(threads)))
    try:
        return _run(torch, UNet, model_config, spec, config, train_data, val_data, out, state, progress, plot,
                    data_description, on_epoch_end, card, fingerprint)
    finally:
        torch.set_num_threads(old_threads)


def _run(torch, UNet, model_config, spec, config, train_data, val_data, out, state, progress, plot, data_description,
         on_epoch_end, card, fingerprint):
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        net = UNet(config=model_config)
    opt = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    total_steps = config.epochs * config.steps_per_epoch

    def lr_factor(step):
        frac = min(1.0, step / max(1, total_steps))
        return 0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * frac))

    history = {"train_loss": [], "val_loss": [], "val_psnr": [], "val_ssim": []}
    epoch, step, elapsed0 = 0, 0, 0.0
    best_val, best_epoch, best_state = math.inf, 0, None
    if state is not None:
        try:
            net.load_state_dict(state["last_state_dict"])
            opt.load_state_dict(state["optimizer"])
        except (RuntimeError, KeyError, ValueError, TypeError, IndexError) as exc:
            raise InputError(f"cannot resume {out}: its training state (last weights, optimiser) is damaged or "
                             f"belongs to another model ({' '.join(str(exc).split())[:160]})") from None
        epoch, step = int(state["epoch"]), int(state["step"])
        elapsed0 = float(state.get("elapsed_s", 0.0))
        history.update({k: list(v) for k, v in state.get("history", history).items()})
        card = {**(read_checkpoint(out).get("card") or {}), **card}
        best_val, best_epoch = float(state.get("best_val", math.inf)), int(state.get("best_epoch", 0))
        best_state = read_checkpoint(out)["state_dict"]
    for group in opt.param_groups:
        group["lr"] = config.lr * lr_factor(step)

    # fixed validation set: draws do not change between epochs
    val_items = [_centre_crop(val_data[i], config.val_crop) for i in range(len(val_data))]
    val_x = [torch.from_numpy(counts_to_input(it["counts"], float(it["window_s"]), spec))[None] for it in val_items]
    val_y = [torch.from_numpy(np.asarray(it["image"], dtype=np.float32))[None, None] for it in val_items]

    def loss_fn(pred, target):
        return training_loss(torch, pred, target, config)

    def validate():
        net.eval()
        losses, psnrs, ssims = [], [], []
        with torch.no_grad():
            for x, y in zip(val_x, val_y, strict=True):
                pred = net(x)
                losses.append(float(loss_fn(pred, y)))
                clamped = pred.clamp(0, 1)
                mse = float(((clamped - y) ** 2).mean())
                psnrs.append(10 * math.log10(1.0 / max(mse, 1e-12)))
                ssims.append(1.0 - float(_ssim_loss(torch, clamped, y)))
        net.train()
        return float(np.mean(losses)), float(np.mean(psnrs)), float(np.mean(ssims))

    plot_path = None
    if plot:
        plot_path = Path(plot) if not isinstance(plot, bool) else out.with_name(out.stem + ".loss.png")

    start = time.perf_counter()
    stopped = "epochs"
    n_train = len(train_data)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=config.epochs * config.steps_per_epoch, initial=step, unit="step", desc="training")
    net.train()
    try:
        while epoch < config.epochs:
            if config.patience is not None and epoch - best_epoch >= config.patience and best_epoch > 0:
                stopped = "early-stopping"
                break
            running, n_run = 0.0, 0
            over_budget = False
            for s in range(config.steps_per_epoch):
                xs, ys = [], []
                for slot in range(config.batch_size):
                    rng = item_seed(config.seed, 1 + epoch, s, slot)
                    idx = int(rng.integers(n_train))
                    item = _draw_pair(train_data, idx, rng, config.crop)
                    counts, image = _augment(np.asarray(item["counts"]), np.asarray(item["image"]), rng,
                                             config.augment)
                    xs.append(counts_to_input(counts, float(item["window_s"]), spec))
                    ys.append(image.astype(np.float32)[None])
                x = torch.from_numpy(np.stack(xs))
                y = torch.from_numpy(np.stack(ys))
                loss = loss_fn(net(x), y)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                step += 1
                for group in opt.param_groups:
                    group["lr"] = config.lr * lr_factor(step)
                running += loss.item()
                n_run += 1
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(epoch=epoch + 1, loss=f"{running / n_run:.4f}")
                if config.max_minutes is not None and elapsed0 + time.perf_counter() - start > 60 * config.max_minutes:
                    over_budget = True
                    break
            epoch += 1
            val_loss, val_psnr, val_ssim = validate()
            history["train_loss"].append(running / max(n_run, 1))
            history["val_loss"].append(val_loss)
            history["val_psnr"].append(val_psnr)
            history["val_ssim"].append(val_ssim)
            if val_loss < best_val:
                best_val, best_epoch = val_loss, epoch
                best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
            log.info("epoch %d: train loss %.4f, val loss %.4f, val PSNR %.2f dB%s", epoch,
                     history["train_loss"][-1], val_loss, val_psnr, " (best)" if best_epoch == epoch else "")
            finished = over_budget or epoch >= config.epochs
            if over_budget:
                stopped = "time-budget"
            _save(out, model_config, spec, best_state, net, opt, config, epoch, step, history, best_epoch, best_val,
                  elapsed0 + time.perf_counter() - start, finished, data_description, card, fingerprint)
            if plot_path is not None:
                plot_history(history, plot_path, loss_label=describe_loss(config))
            if over_budget:
                break
            if on_epoch_end is not None and on_epoch_end(epoch, history) and epoch < config.epochs:
                stopped = "callback"
                break
        else:
            stopped = "epochs"
        if stopped == "early-stopping":
            _save(out, model_config, spec, best_state, net, opt, config, epoch, step, history, best_epoch, best_val,
                  elapsed0 + time.perf_counter() - start, True, data_description, card, fingerprint)
    finally:
        if bar is not None:
            bar.close()
    best = best_epoch - 1
    return {"epochs": epoch, "steps": step, "best_epoch": best_epoch, "best_val": best_val,
            "elapsed_s": elapsed0 + time.perf_counter() - start, "history": history, "stopped": stopped,
            "out": out, "plot": plot_path, "n_parameters": net.n_parameters(), "input": spec.to_dict(),
            "val_psnr": history["val_psnr"][best] if 0 <= best < len(history["val_psnr"]) else None,
            "val_ssim": history["val_ssim"][best] if 0 <= best < len(history["val_ssim"]) else None}


def _with_preset(card: dict, preset) -> dict:
    """``card`` with the training data's preset and its camera (``preset``: a dataset's preset name or TOML path)
    where it names none: a recording of another camera is then warned about, as for the shipped model. Only a
    shipped preset is read; of a path only the file's name is kept."""
    if not isinstance(preset, str) or not preset or "preset" in card:
        return card
    from ..params import list_presets, preset_info

    if preset not in list_presets():  # a TOML path the dataset names: never opened (the dataset is a stranger's)
        return {**card, "preset": Path(preset).stem}
    card["preset"] = preset
    sensor = preset_info(preset)["sensor"]
    if sensor and "sensor" not in card:
        card["sensor"] = f"{sensor} (the preset's camera)"
    return card


def _save(out, model_config, spec, best_state, net, opt, config, epoch, step, history, best_epoch, best_val,
          elapsed, finished, data_description, card=None, fingerprint=None):
    train_state = {
        "data_fingerprint": fingerprint,
        "config": config.to_dict(),
        "epoch": epoch,
        "step": step,
        "history": {k: [float(v) for v in vals] for k, vals in history.items()},
        "best_epoch": best_epoch,
        "best_val": float(best_val),
        "last_state_dict": {k: v.detach().clone() for k, v in net.state_dict().items()},
        "optimizer": opt.state_dict(),
        "elapsed_s": float(elapsed),
        "finished": bool(finished),
        "data": data_description or "",
    }
    card = dict(card or {})
    best = best_epoch - 1
    card.update({
        "windows_s": list(spec.windows_s), "binning": spec.binning, "white_lux": spec.max_lux,
        "steps": int(step), "epochs": int(epoch), "batch_size": config.batch_size, "crop": config.crop,
        "input": spec.transform + (f" + ML estimate (sigma {spec.ml_sigma:g})" if spec.ml_sigma is not None else ""),
        "validation": ({"psnr_db": float(history["val_psnr"][best]), "ssim": float(history["val_ssim"][best]),
                        "best_epoch": int(best_epoch)} if 0 <= best < len(history.get("val_ssim", [])) else {}),
    })
    card.setdefault("training_data", data_description or "")
    save_checkpoint(out, model_config=model_config, input_spec=spec,
                    state_dict=best_state if best_state is not None else net.state_dict(), train_state=train_state,
                    card=card)
