"""Procedural scenes with natural-image statistics: the dead-leaves model.

A dead-leaves image is a stack of opaque disks ("leaves") dropped at uniformly random
positions, each hiding what lies below. With radii drawn from a power law
``p(r) ~ r^-3`` between ``r_min`` and ``r_max`` the model is scale invariant: its power spectrum
falls like ``1 / f^2`` and its edge and occlusion statistics resemble those of natural
photographs (Lee, Mumford and Huang, "Occlusion models for natural images", IJCV 2001).
Each leaf here also carries a linear shading gradient and, for some leaves, a sinusoidal
texture; the image gets a smooth illumination gradient and a small defocus blur (which also
anti-aliases the disk edges). Values are generated as display-encoded grey levels and decoded
with the sRGB transfer function, so they behave like an 8-bit photograph shown on a monitor.

Everything is drawn from the generator passed in: the same seed gives the same image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from evnoise._checks import as_generator
from evnoise.errors import ParameterError

__all__ = ["DeadLeavesModel", "dead_leaves"]

_BATCH = 4096


@dataclass(frozen=True)
class DeadLeavesModel:
    """Parameters of the dead-leaves model (sizes relative to the image's shorter side).

    Parameters
    ----------
    r_min : float
        Smallest leaf radius as a fraction of the image's shorter side (default 0.004;
        at least half a pixel is used).
    r_max : float
        Largest leaf radius as a fraction of the shorter side (default 0.4).
    exponent : float
        Radius density ``p(r) ~ r^-exponent`` (default 3, the scale-invariant case).
    texture_fraction : float
        Fraction of leaves with a sinusoidal texture (default 0.3).
    texture_amplitude : float
        Largest texture amplitude in display units (default 0.12).
    shading : float
        Largest change of a leaf's grey level across its radius (default 0.15).
    illumination : float
        Largest relative change of the global illumination across the image (default 0.3).
    blur_px : (float, float)
        Range of the defocus blur's standard deviation in pixels (default 0.5 .. 1.5).
    max_leaves : int
        Cap on the number of leaves; pixels still uncovered show the background grey.
    """

    r_min: float = 0.004
    r_max: float = 0.4
    exponent: float = 3.0
    texture_fraction: float = 0.3
    texture_amplitude: float = 0.12
    shading: float = 0.15
    illumination: float = 0.3
    blur_px: tuple = (0.5, 1.5)
    max_leaves: int = 400_000

    def __post_init__(self):
        if not (0 < self.r_min < self.r_max):
            raise ParameterError(f"dead leaves need 0 < r_min < r_max, got r_min={self.r_min}, r_max={self.r_max}")
        if not (math.isfinite(self.exponent) and self.exponent > 1):
            raise ParameterError(f"dead-leaves exponent must be > 1, got {self.exponent}")
        for name in ("texture_fraction",):
            v = getattr(self, name)
            if not 0 <= v <= 1:
                raise ParameterError(f"{name} must be in [0, 1], got {v}")
        for name in ("texture_amplitude", "shading", "illumination"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ParameterError(f"{name} must be finite and >= 0, got {v}")
        lo, hi = self.blur_px
        if not (0 <= lo <= hi and math.isfinite(hi)):
            raise ParameterError(f"blur_px must be a range 0 <= low <= high pixels, got {self.blur_px}")
        object.__setattr__(self, "blur_px", (float(lo), float(hi)))
        if int(self.max_leaves) < 1:
            raise ParameterError(f"max_leaves must be >= 1, got {self.max_leaves}")

    def to_dict(self) -> dict:
        """The model's parameters in plain JSON types (``DeadLeavesModel(**d)`` rebuilds it, ``blur_px`` as a tuple).

        Returns
        -------
        dict
            Each field by name; ``blur_px`` as a list ``[low, high]``.
        """
        return {"r_min": self.r_min, "r_max": self.r_max, "exponent": self.exponent,
                "texture_fraction": self.texture_fraction, "texture_amplitude": self.texture_amplitude,
                "shading": self.shading, "illumination": self.illumination, "blur_px": list(self.blur_px),
                "max_leaves": int(self.max_leaves)}


def _radii(gen, n, r_min, r_max, exponent):
    """Inverse-CDF draws from ``p(r) ~ r^-exponent`` on ``[r_min, r_max]``."""
    a = 1.0 - exponent
    u = gen.random(n)
    lo, hi = r_min**a, r_max**a
    return (lo + u * (hi - lo)) ** (1.0 / a)


def dead_leaves(shape, rng=None, model: DeadLeavesModel | None = None) -> np.ndarray:
    """A dead-leaves image: display-encoded grey levels in ``[0, 1]``, float64 ``(H, W)``.

    Parameters
    ----------
    shape : (H, W)
        Image size in pixels.
    rng : numpy.random.Generator, int or None
        Randomness (the same seed gives the same image).
    model : DeadLeavesModel, optional
        Model parameters (default :class:`DeadLeavesModel()`).

    Returns
    -------
    numpy.ndarray
        float64 ``(H, W)`` display values (sRGB-encoded); decode with
        :func:`evnoise.radiometry.srgb_to_linear` for linear luminance.
    """
    from scipy.ndimage import gaussian_filter

    from ._kernels import paint_leaves, tile_counts

    model = DeadLeavesModel() if model is None else model
    gen = as_generator(rng)
    height, width = (int(s) for s in shape)
    if height < 1 or width < 1:
        raise ParameterError(f"dead_leaves needs a positive shape, got {shape!r}")
    side = min(height, width)
    r_min = max(0.5, model.r_min * side)
    r_max = max(r_min * 1.0001, model.r_max * side)
    img = np.zeros((height, width))
    covered = np.zeros((height, width), dtype=bool)
    open_in_tile = tile_counts(height, width)
    background = gen.random()
    remaining = height * width
    drawn = 0
    while remaining > 0 and drawn < model.max_leaves:
        n = min(_BATCH, int(model.max_leaves) - drawn)
        radius = _radii(gen, n, r_min, r_max, model.exponent)
        # centres may lie outside the image by up to one radius, so the borders are not thin
        cx = gen.uniform(-radius, width + radius)
        cy = gen.uniform(-radius, height + radius)
        value = gen.random(n)
        angle = gen.uniform(0.0, 2.0 * math.pi, n)
        slope = gen.uniform(-1.0, 1.0, n) * model.shading / radius
        grad_x, grad_y = slope * np.cos(angle), slope * np.sin(angle)
        textured = gen.random(n) < model.texture_fraction
        tex_amp = np.where(textured, gen.uniform(0.0, model.texture_amplitude, n), 0.0)
        period = np.exp(gen.uniform(math.log(3.0), math.log(40.0), n))
        tex_angle = gen.uniform(0.0, math.pi, n)
        tex_kx = 2.0 * math.pi / period * np.cos(tex_angle)
        tex_ky = 2.0 * math.pi / period * np.sin(tex_angle)
        tex_phase = gen.uniform(0.0, 2.0 * math.pi, n)
        remaining -= paint_leaves(img, covered, open_in_tile, cx, cy, radius, value, grad_x, grad_y, tex_amp, tex_kx,
                                  tex_ky, tex_phase)
        drawn += n
    if remaining > 0:
        img[~covered] = background
    # smooth illumination: a linear ramp in a random direction
    angle = gen.uniform(0.0, 2.0 * math.pi)
    amount = gen.uniform(0.0, model.illumination)
    yy = (np.arange(height) - 0.5 * (height - 1)) / side
    xx = (np.arange(width) - 0.5 * (width - 1)) / side
    ramp = 1.0 + amount * (math.cos(angle) * xx[None, :] + math.sin(angle) * yy[:, None])
    img *= ramp
    sigma = gen.uniform(*model.blur_px)
    if sigma > 0:
        img = gaussian_filter(img, sigma, mode="reflect", truncate=3.0)
    np.clip(img, 0.0, 1.0, out=img)
    return img
