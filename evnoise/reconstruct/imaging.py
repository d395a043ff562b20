"""Image helpers of the reconstructor (NumPy only): display encoding, binning, PNG output.

The reconstruction target is *display-encoded* grayscale: the sRGB transfer function applied
to ``lux / max_lux`` (what a person sees when ``max_lux`` is shown as white). Counts are binned
by summing ``binning x binning`` blocks, as in the Noise2Image paper (2 x 2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._atomic import atomic_output
from .._checks import check_positive
from ..errors import InputError, ParameterError
from ..radiometry import block_sum, srgb_encode, srgb_to_linear

__all__ = [
    "srgb_encode",
    "srgb_decode",
    "lux_to_display",
    "display_to_lux",
    "bin_counts",
    "bin_mean",
    "write_png",
]


def srgb_decode(display) -> np.ndarray:
    """Inverse of :func:`srgb_encode`: display ``[0, 1]`` -> linear ``[0, 1]`` (clipped first).

    :func:`evnoise.radiometry.srgb_to_linear` of the clipped values (the one home of the closed form).

    Parameters
    ----------
    display : float or array_like
        Display-encoded values; clipped to ``[0, 1]``.

    Returns
    -------
    numpy.ndarray
        Linear values in ``[0, 1]``, float64, of the shape of ``display``.
    """
    return srgb_to_linear(np.clip(np.asarray(display, dtype=np.float64), 0.0, 1.0))


def _check_max_lux(max_lux) -> float:
    return check_positive(max_lux, "max_lux (lux shown as white)", "lux")


def lux_to_display(lux, max_lux) -> np.ndarray:
    """Display-encoded image ``srgb_encode(lux / max_lux)`` in ``[0, 1]`` (float64).

    Parameters
    ----------
    lux : float or array_like
        Illuminance in lux.
    max_lux : float
        Illuminance in lux shown as white (> 0).

    Returns
    -------
    numpy.ndarray
        Display-encoded values of the shape of ``lux``.
    """
    return srgb_encode(np.asarray(lux, dtype=np.float64) / _check_max_lux(max_lux))


def display_to_lux(display, max_lux) -> np.ndarray:
    """Illuminance in lux of a display-encoded image (inverse of :func:`lux_to_display`)."""
    return srgb_decode(display) * _check_max_lux(max_lux)


def _check_binning(binning) -> int:
    if isinstance(binning, bool) or not isinstance(binning, (int, np.integer)) or binning < 1:
        raise ParameterError(f"binning must be an integer >= 1, got {binning!r}")
    return int(binning)


def bin_counts(counts, binning: int = 2) -> np.ndarray:
    """Sum ``binning x binning`` blocks of counts ``(..., H, W)`` -> ``(..., H // b, W // b)`` int64.

    A last row or column that does not fill a whole block is dropped (as a sensor crop would).

    Parameters
    ----------
    counts : array_like, shape (..., H, W)
        Event counts, at least 2-D; converted to int64.
    binning : int, default 2
        Side ``b`` of the square blocks, an integer >= 1 (1 keeps the counts as they are).

    Returns
    -------
    numpy.ndarray
        int64 block sums of shape ``(..., H // b, W // b)``.

    Raises
    ------
    InputError
        If ``counts`` has fewer than 2 dimensions or is smaller than one block.
    """
    arr = np.asarray(counts)
    if arr.ndim < 2:
        raise InputError(f"counts must have at least 2 dimensions (..., H, W), got shape {arr.shape}")
    return block_sum(arr.astype(np.int64, copy=False), _check_binning(binning), "counts")


def bin_mean(image, binning: int = 2) -> np.ndarray:
    """Mean over ``binning x binning`` blocks (float64); incomplete last blocks are dropped."""
    b = _check_binning(binning)
    return block_sum(np.asarray(image, dtype=np.float64), b) / (b * b)


def write_png(path, image, *, overwrite: bool = True) -> Path:
    """Write a ``[0, 1]`` grayscale image as an 8-bit PNG, atomically (temporary name, then rename).

    Parameters
    ----------
    path : str or os.PathLike
        The PNG file to write; its folder must exist.
    image : array_like, shape (H, W)
        Grayscale values; clipped to ``[0, 1]`` (NaN as 0) and rounded to ``0..255``.
    overwrite : bool, default True
        Replace an existing file; when False an existing ``path`` is an
        :class:`~evnoise.errors.OutputError`.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    from PIL import Image

    path = Path(path)
    arr = np.asarray(image, dtype=np.float64)
    if arr.ndim != 2:
        raise InputError(f"image must be 2-D (H, W), got shape {arr.shape}")
    data = np.round(np.clip(np.nan_to_num(arr, nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
    with atomic_output(path, overwrite=overwrite, what="PNG file") as tmp:
        Image.fromarray(data).save(tmp, format="PNG")
    return path
