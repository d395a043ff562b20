"""Make ``example.png``, the bundled 1280x720 8-bit grey test scene, deterministically.

Run ``python -m evnoise.data.make_example [OUT]`` (default: next to this file). The scene is
drawn with NumPy only (no fonts, no random state), at twice the resolution and averaged down
for smooth edges, so the same NumPy gives the same bytes. It holds what shows the photon
noise of an event camera at work:

* a sky gradient, a bright sun with a halo, two mountain ridges and a textured field:
  smooth regions over the whole grey range;
* a row of 16 grey patches from 0 to 255 (a step wedge): the noise-event rate against
  brightness, patch by patch;
* shaded spheres (smooth Lambertian gradients) and a house with windows (hard edges);
* a Siemens star (fine radial detail, black and white).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

WIDTH, HEIGHT = 1280, 720
SS = 2  # supersampling factor


def _grid():
    y, x = np.mgrid[0:HEIGHT * SS, 0:WIDTH * SS].astype(np.float64)
    return (x + 0.5) / SS, (y + 0.5) / SS  # pixel coordinates of the final image


def _ridge(x, base, amps, periods, phases):
    h = np.full_like(x, base, dtype=np.float64)
    for a, p, ph in zip(amps, periods, phases):
        h += a * np.sin(2 * np.pi * x / p + ph)
    return h


def render() -> np.ndarray:
    """The scene as a ``(720, 1280)`` uint8 array."""
    x, y = _grid()
    horizon = 455.0
    # sky: brighter at the top, a little lighter towards the sun
    img = 232.0 - 70.0 * (y / horizon) ** 1.3
    sun_x, sun_y, sun_r = 1020.0, 130.0, 52.0
    d_sun = np.hypot(x - sun_x, y - sun_y)
    img += 22.0 * np.exp(-((d_sun - sun_r).clip(0) / 90.0))
    img = np.where(d_sun < sun_r, 255.0, img)
    # distant ridge, then a nearer, darker one
    far = _ridge(x[0], 330.0, (38, 17, 7), (610.0, 230.0, 71.0), (0.3, 1.9, 4.0))
    img = np.where(y > far[None, :], 128.0 - 0.10 * (y - far[None, :]), img)
    near = _ridge(x[0], 400.0, (30, 14, 5), (470.0, 160.0, 53.0), (2.2, 0.4, 1.1))
    img = np.where(y > near[None, :], 92.0 - 0.12 * (y - near[None, :]), img)
    # field: rows that converge in perspective, darker towards the viewer
    ground = y > horizon
    depth = (y - horizon + 12.0) / (HEIGHT - horizon + 12.0)
    rows = np.sin(2 * np.pi * (x - WIDTH / 2) / (40.0 + 260.0 * depth) * depth * 3.0)
    waves = np.sin(2 * np.pi * y / (9.0 + 30.0 * depth))
    field = 82.0 - 40.0 * depth + 9.0 * rows + 4.0 * waves
    img = np.where(ground, field, img)
    # house: walls, roof, door and lit windows
    hx0, hx1, hy0, hy1 = 760.0, 960.0, 380.0, 520.0
    walls = (x >= hx0) & (x < hx1) & (y >= hy0) & (y < hy1)
    img = np.where(walls, 175.0 - 25.0 * (x - hx0) / (hx1 - hx0), img)
    roof = (y < hy0) & (y >= hy0 - 90.0) & (np.abs(x - (hx0 + hx1) / 2) < (y - (hy0 - 90.0)) * 1.25)
    img = np.where(roof, 48.0, img)
    for wx in (785.0, 895.0):
        window = (x >= wx) & (x < wx + 45.0) & (y >= 410.0) & (y < 455.0)
        img = np.where(window, 245.0, img)
        bars = window & ((np.abs(x - (wx + 22.5)) < 2.0) | (np.abs(y - 432.5) < 2.0))
        img = np.where(bars, 60.0, img)
    door = (x >= 842.0) & (x < 878.0) & (y >= 450.0) & (y < hy1)
    img = np.where(door, 25.0, img)
    # shaded spheres, lit from the upper right
    light = np.array([0.5, -0.6, 0.62])
    light /= np.linalg.norm(light)
    spheres = ((150.0, 500.0, 75.0, 240.0), (330.0, 540.0, 50.0, 170.0), (470.0, 560.0, 32.0, 110.0))
    for cx, cy, r, albedo in spheres:
        dx, dy = (x - cx) / r, (y - cy) / r
        inside = dx * dx + dy * dy < 1.0
        dz = np.sqrt(np.clip(1.0 - dx * dx - dy * dy, 0.0, None))
        shade = np.clip(dx * light[0] + dy * light[1] + dz * light[2], 0.0, None)
        img = np.where(inside, 12.0 + (albedo - 12.0) * shade, img)
    # Siemens star, 24 spokes
    sx, sy, sr = 1135.0, 575.0, 110.0
    ang = np.arctan2(y - sy, x - sx)
    star = np.hypot(x - sx, y - sy) < sr
    img = np.where(star, np.where(np.sin(12 * ang) > 0, 235.0, 10.0), img)
    # step wedge: 16 patches from 0 to 255 on a mid-grey frame
    wx0, wy0, pw, ph = 40.0, 640.0, 42.0, 56.0
    frame = (x >= wx0 - 6) & (x < wx0 + 16 * pw + 6) & (y >= wy0 - 6) & (y < wy0 + ph + 6)
    img = np.where(frame, 128.0, img)
    k = np.floor((x - wx0) / pw)
    patch = (k >= 0) & (k < 16) & (y >= wy0) & (y < wy0 + ph) & ((x - wx0) - k * pw < pw - 4)
    img = np.where(patch, k * 17.0, img)
    img = np.clip(img, 0.0, 255.0)
    small = img.reshape(HEIGHT, SS, WIDTH, SS).mean(axis=(1, 3))
    return np.round(small).astype(np.uint8)


def main(argv=None) -> int:
    from PIL import Image

    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else Path(__file__).with_name("example.png")
    Image.fromarray(render()).save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size / 1000:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
