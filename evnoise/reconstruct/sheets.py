"""Pictures of a ``reconstruct --fps`` run: a contact sheet and an animated GIF, with a legend.

Both are made from the PNGs that :func:`evnoise.motion.reconstruct_video` wrote into its folder
(``frame_*.png``, ``overlay_*.png``, ``frames.csv``), with Pillow only:

``contact_sheet.png``  up to ``max_tiles`` frames spread over the run, each with its time, the
                       overlay beside the frame when there are overlays, and a legend strip
``frames.gif``         every frame (or overlay, with the legend strip below it), at the run's fps
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from .._atomic import atomic_output
from ..errors import InputError

__all__ = ["contact_sheet", "animated_gif", "LEGEND"]

#: colour (RGB) and meaning of what :func:`evnoise.motion.overlay_rgb` draws
LEGEND = (
    ((230, 60, 60), "motion mask (not used for the background)"),
    ((255, 230, 26), "ON signal events"),
    ((26, 230, 255), "OFF-only signal events"),
)


def _frames(folder: Path):
    frames = sorted(folder.glob("frame_*.png"))
    if not frames:
        raise InputError(f"no frame_*.png in {folder}")
    overlays = sorted(folder.glob("overlay_*.png"))
    times = {}
    csv_path = folder / "frames.csv"
    if csv_path.is_file():
        with open(csv_path, newline="", encoding="utf-8") as fh:
            for row in csv.DictReader(fh):
                times[int(row["frame"])] = float(row["t_end_s"])
    return frames, overlays if len(overlays) == len(frames) else [], times


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1
        return ImageFont.load_default()


def legend_strip(width: int, *, overlay: bool = True):
    """An RGB strip (Pillow image) naming the overlay colours; ``overlay=False``: a plain caption."""
    from PIL import Image, ImageDraw

    font = _font(11)
    items = LEGEND if overlay else ()
    line_h = 16
    height = 6 + line_h * max(1, len(items))
    strip = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(strip)
    if not items:
        draw.text((6, 4), "static background reconstructed from noise events", fill=(0, 0, 0), font=font)
    for k, (colour, text) in enumerate(items):
        y = 4 + k * line_h
        draw.rectangle([6, y + 2, 18, y + 12], fill=colour, outline=(0, 0, 0))
        draw.text((24, y), text, fill=(0, 0, 0), font=font)
    return strip


def _with_legend(img, overlay: bool):
    from PIL import Image

    strip = legend_strip(max(img.width, 280), overlay=overlay)
    out = Image.new("RGB", (max(img.width, strip.width), img.height + strip.height), (255, 255, 255))
    out.paste(img.convert("RGB"), (0, 0))
    out.paste(strip, (0, img.height))
    return out


def _tile(path: Path, size: tuple):
    """The image at ``path`` as RGB, resized to ``size`` (nearest neighbour), its file closed."""
    from PIL import Image

    with Image.open(path) as img:
        return img.convert("RGB").resize(size, Image.Resampling.NEAREST)


def contact_sheet(folder, out=None, *, max_tiles: int = 12, columns: int = 4, overwrite: bool = True) -> Path:
    """Write ``contact_sheet.png`` (or ``out``): frames spread over the run, with times and a legend."""
    from PIL import Image, ImageDraw

    folder = Path(folder)
    frames, overlays, times = _frames(folder)
    pick = np.unique(np.linspace(0, len(frames) - 1, min(max_tiles, len(frames))).round().astype(int))
    with Image.open(frames[0]) as first:  # the size only (an image left open holds its file)
        w, h = first.size
    scale = max(1, 160 // max(w, 1)) if w < 160 else 1
    tile_w = w * scale * (2 if overlays else 1) + (4 if overlays else 0)
    tile_h = h * scale + 16
    cols = min(columns, len(pick))
    rows = -(-len(pick) // cols)
    legend = legend_strip(cols * (tile_w + 6), overlay=bool(overlays))
    sheet = Image.new("RGB", (cols * (tile_w + 6), rows * (tile_h + 6) + legend.height), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    font = _font(11)
    for k, idx in enumerate(pick):
        r, c = divmod(k, cols)
        x0, y0 = c * (tile_w + 6) + 3, r * (tile_h + 6) + 3
        frame = _tile(frames[idx], (w * scale, h * scale))
        sheet.paste(frame, (x0, y0 + 14))
        if overlays:
            ov = _tile(overlays[idx], (w * scale, h * scale))
            sheet.paste(ov, (x0 + w * scale + 4, y0 + 14))
        label = f"frame {idx}" + (f", t = {times[idx]:.3f} s" if idx in times else "") + \
            ("  (image | overlay)" if overlays and k == 0 else "")
        draw.text((x0, y0), label, fill=(0, 0, 0), font=font)
    sheet.paste(legend, (0, rows * (tile_h + 6)))
    path = Path(out) if out is not None else folder / "contact_sheet.png"
    with atomic_output(path, overwrite=overwrite, what="contact sheet") as tmp:
        sheet.save(tmp, format="PNG")
    return path


def animated_gif(folder, out=None, *, fps: float = 10.0, overwrite: bool = True, max_frames: int = 600) -> Path:
    """Write ``frames.gif`` (or ``out``): the overlays (else the frames) with a legend strip, at ``fps``."""
    from PIL import Image

    folder = Path(folder)
    frames, overlays, _ = _frames(folder)
    source = (overlays or frames)[:max_frames]
    images = []
    for p in source:
        with Image.open(p) as img:
            images.append(_with_legend(img, bool(overlays)))
    duration_ms = max(20, int(round(1000.0 / fps))) if fps > 0 else 100
    path = Path(out) if out is not None else folder / "frames.gif"
    with atomic_output(path, overwrite=overwrite, what="animated GIF") as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration_ms, loop=0)
    return path
