"""Image-quality metrics of the paper: PSNR, SSIM and LPIPS (AlexNet).

PSNR and SSIM need NumPy (and scikit-image for SSIM); LPIPS needs PyTorch and the offline
AlexNet/LPIPS weights (see :mod:`evnoise.reconstruct.lpips`). All take display-encoded
grayscale images in ``[0, 1]`` of the same shape ``(H, W)``.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError

__all__ = ["psnr", "ssim", "lpips_distance", "SSIM_SETTINGS"]

# scikit-image settings of the paper's SSIM (Wang et al. 2004): Gaussian window sigma 1.5
SSIM_SETTINGS = {"gaussian_weights": True, "sigma": 1.5, "use_sample_covariance": False, "data_range": 1.0}


def _pair(pred, target):
    p = np.asarray(pred, dtype=np.float64)
    t = np.asarray(target, dtype=np.float64)
    if p.shape != t.shape:
        raise InputError(f"images must have the same shape, got {p.shape} and {t.shape}")
    if p.ndim != 2 or p.size == 0:
        raise InputError(f"images must be non-empty 2-D arrays (H, W), got shape {p.shape}")
    if not (np.isfinite(p).all() and np.isfinite(t).all()):
        raise InputError("images contain NaN or Inf")
    return p, t


def psnr(pred, target, *, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(data_range^2 / MSE)`` (inf when identical).

    Parameters
    ----------
    pred : array_like, shape (H, W)
        Estimated image (finite).
    target : array_like, shape (H, W)
        Reference image of the same shape (finite).
    data_range : float, default 1.0
        Peak value of the images' range (1 for images in ``[0, 1]``).

    Returns
    -------
    float
        PSNR in decibels.
    """
    p, t = _pair(pred, target)
    mse = float(np.mean((p - t) ** 2))
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(data_range**2 / mse)


def ssim(pred, target) -> float:
    """Structural similarity (scikit-image, Gaussian window sigma 1.5, data range 1).

    Parameters
    ----------
    pred : array_like, shape (H, W)
        Estimated image in ``[0, 1]``, at least 7 x 7 pixels.
    target : array_like, shape (H, W)
        Reference image of the same shape.

    Returns
    -------
    float
        Mean SSIM, at most 1 (1 when identical).
    """
    p, t = _pair(pred, target)
    if min(p.shape) < 7:
        raise InputError(f"SSIM needs images of at least 7x7 pixels, got {p.shape}")
    from skimage.metrics import structural_similarity

    return float(structural_similarity(t, p, **SSIM_SETTINGS))


_LPIPS = {}


def lpips_distance(pred, target, *, weights=None) -> float:
    """LPIPS (AlexNet, v0.1) between two grayscale images in ``[0, 1]``.

    The images are mapped to ``[-1, 1]`` and replicated to three channels (the usual practice
    for grayscale images; the paper normalises to ``[-1, 1]`` the same way).

    Parameters
    ----------
    pred : array_like, shape (H, W)
        Estimated image in ``[0, 1]``, at least 32 x 32 pixels.
    target : array_like, shape (H, W)
        Reference image of the same shape.
    weights : str or os.PathLike, optional
        Converted LPIPS weights file; default :func:`evnoise.reconstruct.lpips.weights_path`. The
        network of each weights file is built once and kept for later calls.

    Returns
    -------
    float
        LPIPS distance (0 when identical; lower is more similar).
    """
    p, t = _pair(pred, target)
    from .lpips import LPIPS

    key = str(weights)
    if key not in _LPIPS:
        _LPIPS[key] = LPIPS(weights=weights)
    return _LPIPS[key].distance(p, t)
