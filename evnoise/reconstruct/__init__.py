"""The reconstructor: a small PyTorch U-Net from noise-event counts to images (needs ``evnoise[train]``).

Importing this package is cheap and does not import torch; each name loads its module on first
use. Modules: ``unet`` (model), ``train`` (training loop), ``checkpoint`` (files, model
cards), ``infer`` (events.h5 -> image; the shipped model), ``data`` (pair datasets),
``metrics`` (PSNR, SSIM, LPIPS), ``lpips`` (offline AlexNet LPIPS), ``baselines`` (count
image, ML inversion), ``evaluate`` (the comparison table; ``evnoise evaluate``), ``imaging``
(sRGB encoding, binning, PNG), ``pretrain`` (the script that trains the shipped model),
``sheets`` (contact sheet and GIF of ``reconstruct --fps``). The functions ``train`` and
``evaluate`` live in the modules of the same name (``from evnoise.reconstruct.train import train``).
"""

from __future__ import annotations

from evnoise._lazy import lazy_attributes

_LAZY = {
    "UNet": ".unet",
    "UNetConfig": ".unet",
    "TrainConfig": ".train",
    "DEFAULT_MODEL": ".train",
    "InputSpec": ".checkpoint",
    "read_checkpoint": ".checkpoint",
    "load_model": ".checkpoint",
    "describe_checkpoint": ".checkpoint",
    "checkpoint_summary": ".checkpoint",
    "default_model_path": ".infer",
    "choose_window": ".infer",
    "Reconstructor": ".infer",
    "counts_from_h5": ".infer",
    "PairList": ".data",
    "NpzPairs": ".data",
    "ResampledPairs": ".data",
    "open_pairs": ".data",
    "split_by_source": ".data",
    "save_pairs_npz": ".data",
    "psnr": ".metrics",
    "ssim": ".metrics",
    "lpips_distance": ".metrics",
    "LPIPS": ".lpips",
    "install_weights": ".lpips",
    "count_image": ".baselines",
    "MLInversion": ".baselines",
    "format_table": ".evaluate",
    "bin_counts": ".imaging",
    "srgb_encode": ".imaging",
    "srgb_decode": ".imaging",
    "lux_to_display": ".imaging",
    "write_png": ".imaging",
    "reconstruct_video": ".video",
}

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
