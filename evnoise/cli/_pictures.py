"""PNG pictures of the command line: event-rate maps beside their scene, with labels and colour bars.

Only numpy and Pillow (no matplotlib): ``simulate --png`` (scene, ON and OFF rate maps),
``make-dataset``'s ``preview.png`` (a few pairs), ``separate --png`` (signal and noise maps).
Rates are shown on a log colour scale in events per second per pixel, zero in black; the scene
in grey on a log lux scale (the noise rate peaks near 1-2 lux, so a linear grey scene would not
explain the maps).
"""

from __future__ import annotations

import math

import numpy as np

#: anchors of the rate colour map (dark violet - red - orange - pale yellow), rising in lightness; it starts
#: above black, which is kept for "no events"
_ANCHORS = np.array([
    (0.00, 22, 8, 56), (0.15, 40, 12, 86), (0.30, 85, 15, 109), (0.45, 136, 34, 106), (0.60, 186, 54, 85),
    (0.72, 227, 89, 51), (0.84, 249, 140, 10), (0.93, 249, 201, 50), (1.00, 252, 255, 164),
], dtype=np.float64)
BACKGROUND = (30, 30, 30)
TEXT = (235, 235, 235)
PANEL_MAX_WIDTH = 640  # wider images are shown block-averaged
PANEL_MIN_WIDTH = 240  # narrower ones are enlarged (nearest neighbour) so that labels fit


def colormap(values) -> np.ndarray:
    """``values`` in ``[0, 1]`` -> uint8 RGB of shape ``values.shape + (3,)``; NaN (no events) is black."""
    raw = np.asarray(values, dtype=np.float64)
    v = np.clip(np.nan_to_num(raw, nan=0.0), 0.0, 1.0)
    rgb = np.stack([np.interp(v, _ANCHORS[:, 0], _ANCHORS[:, k]) for k in (1, 2, 3)], axis=-1)
    rgb[np.isnan(raw)] = 0.0
    return np.round(rgb).astype(np.uint8)


def font(size: int):
    """Pillow's scalable default font at ``size`` pixels (the bitmap font on old Pillow)."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except (TypeError, ImportError, OSError):  # pragma: no cover - Pillow < 10.1 or no FreeType
        return ImageFont.load_default()


def display_factor(width: int) -> tuple[int, int]:
    """``(shrink, enlarge)`` integer factors that bring ``width`` pixels to a readable panel width."""
    shrink = max(1, math.ceil(width / PANEL_MAX_WIDTH))
    enlarge = max(1, math.ceil(PANEL_MIN_WIDTH / max(width, 1))) if shrink == 1 else 1
    return shrink, enlarge


def resample(values, shrink: int, enlarge: int) -> np.ndarray:
    """Block mean over ``shrink x shrink`` pixels (edges trimmed), or ``enlarge``-fold nearest enlarging."""
    a = np.asarray(values, dtype=np.float64)
    if shrink > 1:
        h, w = (a.shape[0] // shrink) * shrink, (a.shape[1] // shrink) * shrink
        a = a[:max(h, shrink), :max(w, shrink)]
        if a.shape[0] < shrink or a.shape[1] < shrink:
            return a
        a = a.reshape(a.shape[0] // shrink, shrink, a.shape[1] // shrink, shrink).mean(axis=(1, 3))
    if enlarge > 1:
        a = np.repeat(np.repeat(a, enlarge, axis=0), enlarge, axis=1)
    return a


class LogScale:
    """A log scale from ``lo`` to ``hi`` mapped to ``[0, 1]``; values <= 0 map to NaN (shown black)."""

    def __init__(self, lo: float, hi: float):
        hi = float(hi) if hi > 0 and math.isfinite(hi) else 1.0
        lo = float(lo) if 0 < lo < hi else hi / 100.0
        self.lo, self.hi = lo, hi

    @classmethod
    def of_rates(cls, maps, floor: float):
        """From the 99.9th percentile of the positive values down by at most 3 decades, not below ``floor``."""
        pos = np.concatenate([np.asarray(m, dtype=np.float64).ravel() for m in maps])
        pos = pos[pos > 0]
        if pos.size == 0:
            return cls(floor, 10 * floor)
        hi = float(np.percentile(pos, 99.9))
        lo = max(float(np.percentile(pos, 1)), hi / 1000.0, floor)
        if lo >= hi:
            lo = hi / 10.0
        return cls(lo, hi)

    def __call__(self, values) -> np.ndarray:
        v = np.asarray(values, dtype=np.float64)
        out = np.full(v.shape, np.nan)
        pos = v > 0
        out[pos] = (np.log10(np.maximum(v[pos], self.lo)) - math.log10(self.lo)) / (
            math.log10(self.hi) - math.log10(self.lo))
        return np.clip(out, 0.0, 1.0, where=pos, out=out)

    def ticks(self) -> list[float]:
        """Round values (1, 2, 5 x 10^k) inside the scale, at most about 6."""
        k0, k1 = math.floor(math.log10(self.lo)), math.ceil(math.log10(self.hi))
        for mantissas in ((1,), (1, 3), (1, 2, 5)):
            ticks = [m * 10.0 ** k for k in range(k0, k1 + 1) for m in mantissas]
            ticks = [t for t in ticks if self.lo * 0.999 <= t <= self.hi * 1.001]
            if len(ticks) >= 3 or mantissas == (1, 2, 5):
                if len(ticks) > 7:
                    ticks = ticks[::2]
                return ticks
        return []  # pragma: no cover


def number(value: float) -> str:
    """A short tick label: 0.001, 0.5, 20, 3k, 1.5M."""
    if value >= 1e6:
        return f"{value / 1e6:g}M"
    if value >= 1e4:
        return f"{value / 1e3:g}k"
    return f"{value:g}"


def colour_bar(width: int, scale: LogScale, caption: str, *, grey: bool = False, zero: bool = True,
               size: int = 14):
    """A horizontal colour bar (PIL image) with round ticks and a caption below."""
    from PIL import Image, ImageDraw

    fnt = font(size)
    bar_h, left, right = max(10, size), 6, 6
    zero_w = 3 * size if zero else 0
    span = max(width - left - right - zero_w, 20)
    height = bar_h + 2 * size + 14
    image = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(image)
    ramp = np.linspace(0.0, 1.0, span)
    rgb = (np.repeat(np.round(255 * ramp)[:, None], 3, axis=1).astype(np.uint8) if grey else colormap(ramp))
    image.paste(Image.fromarray(np.repeat(rgb[None], bar_h, axis=0)), (left + zero_w, 0))
    if zero:
        draw.rectangle((left, 0, left + size, bar_h - 1), fill=(0, 0, 0), outline=(120, 120, 120))
        draw.text((left + size / 2, bar_h + 2), "0", fill=TEXT, font=fnt, anchor="ma")
    x0 = left + zero_w
    for t in scale.ticks():
        x = x0 + (span - 1) * float(scale(np.array([t]))[0])
        draw.line((x, bar_h - 3, x, bar_h + 2), fill=TEXT)
        draw.text((x, bar_h + 2), number(t), fill=TEXT, font=fnt, anchor="ma")
    draw.text((x0 + span / 2, bar_h + size + 8), caption, fill=TEXT, font=fnt, anchor="ma")
    return image


def titled(rgb, title: str, *, size: int = 16, colour=TEXT, min_lines: int = 1):
    """A panel (uint8 RGB array or PIL image) with ``title`` above it, wrapped to the panel's width
    (at least ``min_lines`` lines high, so that panels in a row line up)."""
    from PIL import Image, ImageDraw

    panel = rgb if isinstance(rgb, Image.Image) else Image.fromarray(np.asarray(rgb, dtype=np.uint8))
    fnt = font(size)
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    lines, words = [], title.split(" ")
    while words:  # wrap at spaces to the panel's width (a word longer than it is cut)
        line = words.pop(0)
        while words and measure.textlength(line + " " + words[0], font=fnt) <= panel.width - 4:
            line += " " + words.pop(0)
        while len(line) > 1 and measure.textlength(line, font=fnt) > panel.width - 4:
            line = line[:-2] + "…"
        lines.append(line)
    head = max(len(lines), min_lines) * (size + 4) + 6
    image = Image.new("RGB", (panel.width, panel.height + head), BACKGROUND)
    draw = ImageDraw.Draw(image)
    for k, line in enumerate(lines):
        draw.text((2, 4 + k * (size + 4)), line, fill=colour, font=fnt)
    image.paste(panel, (0, head))
    return image


def hstack(images, gap: int = 10, *, pad: int = 0):
    """Images side by side (top-aligned), ``gap`` pixels apart, with ``pad`` around."""
    from PIL import Image

    images = [im for im in images if im is not None]
    width = sum(im.width for im in images) + gap * (len(images) - 1) + 2 * pad
    height = max(im.height for im in images) + 2 * pad
    out = Image.new("RGB", (width, height), BACKGROUND)
    x = pad
    for im in images:
        out.paste(im, (x, pad))
        x += im.width + gap
    return out


def vstack(images, gap: int = 8, *, pad: int = 0, align: str = "left"):
    """Images one below the other, left-aligned or centred."""
    from PIL import Image

    images = [im for im in images if im is not None]
    width = max(im.width for im in images) + 2 * pad
    height = sum(im.height for im in images) + gap * (len(images) - 1) + 2 * pad
    out = Image.new("RGB", (width, height), BACKGROUND)
    y = pad
    for im in images:
        x = pad + ((width - 2 * pad - im.width) // 2 if align == "center" else 0)
        out.paste(im, (x, y))
        y += im.height + gap
    return out


def save_png(image, path) -> None:
    """Write a PIL image as PNG to ``path`` (a temporary name of the caller, typically)."""
    image.save(path, format="PNG")


# --------------------------------------------------------------------------------------
# simulate --png
# --------------------------------------------------------------------------------------
def simulate_sheet(counts, *, lux=None, duration_s=None, scene_title: str = "scene"):
    """The ``simulate --png`` picture: scene (log lux) | ON | OFF rate maps, with colour bars.

    ``counts``: ``(2, H, W)`` ON/OFF event counts; ``lux``: the scene's ``(H, W)`` illuminance
    (omitted: no scene panel); ``duration_s``: the recording's length, for rates in events/s
    (omitted: counts are shown).
    """
    counts = np.asarray(counts, dtype=np.float64)
    _, height, width = counts.shape
    shrink, enlarge = display_factor(width)
    per = 1.0 / duration_s if duration_s else 1.0
    maps = [resample(c * per, shrink, enlarge) for c in counts]
    unit = "events/s per pixel" if duration_s else "events per pixel"
    if shrink > 1:
        unit += f" (mean of {shrink}x{shrink} pixels)"
    scale = LogScale.of_rates(maps, floor=per / (shrink * shrink))
    size = max(13, min(18, maps[0].shape[1] // 28))
    total = counts.sum(axis=(1, 2)) * per / (height * width)
    rate_word = "events/s" if duration_s else "events"
    panels = [titled(colormap(scale(m)), f"{name}: mean {t:.3g} {rate_word} per pixel", size=size,
                     colour=colour)
              for m, name, t, colour in zip(maps, ("ON", "OFF"), total, ((120, 255, 120), (255, 140, 140)),
                                            strict=True)]
    gap = 10
    maps_row = hstack(panels, gap)
    bar = colour_bar(maps_row.width, scale, f"event rate, {unit}, log scale", size=size - 1)
    right = vstack([maps_row, bar], gap=6)
    if lux is None:
        return vstack([right], pad=8)
    lux = np.asarray(lux, dtype=np.float64)
    shown = resample(lux, shrink, enlarge)
    positive = shown[shown > 0]
    hi = float(np.max(positive)) if positive.size else 1.0
    lo = max(float(np.min(positive)) if positive.size else hi / 100, hi / 1e4)
    if hi < 10 * lo:  # a nearly uniform scene: one decade around it (shown mid-grey)
        middle = math.sqrt(lo * hi)
        lo, hi = middle / math.sqrt(10), middle * math.sqrt(10)
    lux_scale = LogScale(lo, hi)
    grey = np.round(255 * np.nan_to_num(lux_scale(shown), nan=0.0)).astype(np.uint8)
    scene = titled(np.repeat(grey[..., None], 3, axis=2),
                   f"{scene_title}: {lux.min():.3g} to {lux.max():.3g} lux", size=size)
    lux_bar = colour_bar(scene.width, lux_scale, "illuminance, lux, log scale", grey=True, zero=False,
                         size=size - 1)
    left = vstack([scene, lux_bar], gap=6)
    return hstack([left, right], gap=2 * gap, pad=8)


# --------------------------------------------------------------------------------------
# make-dataset preview.png
# --------------------------------------------------------------------------------------
from ..generators.folder import PREVIEW  # noqa: E402  (the dataset folder's file names have one home)


def dataset_preview(root, *, n_pairs: int = 4):
    """A sheet of up to ``n_pairs`` pairs of a dataset: image | ON | OFF counts per row (PIL image).

    Pairs are taken from the splits in turn (train, val, test), one per source image, at the
    dataset's longest window (the least noisy counts).
    """
    from ..generators.reader import PairDataset

    splits = [PairDataset(root, split) for split in ("train", "val", "test")]
    splits = [ds for ds in splits if len(ds)]
    if not splits:
        return None
    n_total = sum(len(ds) for ds in splits)
    longest = max(splits[0].windows_s)
    picked, seen = [], set()
    for ds in splits:
        for i, source in enumerate(ds.sources):
            if len(picked) == n_pairs:
                break
            if source in seen:
                continue
            seen.add(source)
            item = next((ds[j] for j in range(i, min(i + 64, len(ds)))
                         if ds.sources[j] == source and abs(ds[j]["window_s"] - longest) <= 1e-9), None)
            picked.append((item if item is not None else ds[i], ds.split))
    ds = splits[0]
    labels = [split for _, split in picked]
    picked = [item for item, _ in picked]
    counts = [np.asarray(p["counts"], dtype=np.float64) / p["window_s"] for p in picked]
    width = counts[0].shape[2]
    enlarge = max(1, 200 // max(width, 1))
    shrink = max(1, math.ceil(width / 320))
    scale = LogScale.of_rates([c for c in counts], floor=1.0 / longest)
    size = 14
    rows = []
    b = ds.binning
    for item, c, split in zip(picked, counts, labels, strict=True):
        image = resample(np.asarray(item["image"], dtype=np.float64), shrink, enlarge)
        grey = np.round(255 * np.clip(image, 0, 1)).astype(np.uint8)
        source = str(item["source"])
        cells = [titled(np.repeat(grey[..., None], 3, axis=2),
                        f"{source} ({split}; source white {item['max_lux']:.3g} lux)", size=size, min_lines=2)]
        for k, name in enumerate(("ON", "OFF")):
            shown = resample(c[k], shrink, enlarge)
            cells.append(titled(colormap(scale(shown)), f"{name} events, {item['window_s']:g} s window", size=size,
                                min_lines=2))
        rows.append(hstack(cells, 8))
    bar = colour_bar(rows[0].width, scale, f"event rate, events/s per {b}x{b}-binned pixel, log scale",
                     size=size - 1)
    head = titled(np.zeros((1, rows[0].width, 3), np.uint8) + np.uint8(BACKGROUND[0]),
                  f"{len(picked)} of {n_total} pairs, image = sRGB(lux / {ds.max_lux:g} lux)", size=size + 2)
    return vstack([head, *rows, bar], gap=8, pad=8)


def write_dataset_preview(root, *, n_pairs: int = 4):
    """Write ``preview.png`` in a dataset folder (atomically); returns its path, or None (no pairs)."""
    from pathlib import Path

    from .._atomic import atomic_output

    sheet = dataset_preview(root, n_pairs=n_pairs)
    if sheet is None:
        return None
    path = Path(root) / PREVIEW
    with atomic_output(path, what="preview") as tmp:
        save_png(sheet, tmp)
    return path


# --------------------------------------------------------------------------------------
# separate --png
# --------------------------------------------------------------------------------------
def count_map(path, *, sensor=None, csv_columns=None, shape=None) -> tuple[np.ndarray, float]:
    """``(counts (2, H, W), duration_s)`` of an event file of any format, read chunk by chunk.

    ``shape`` (H, W) is used where the file does not give the sensor size (a CSV output);
    the duration is the file's ``t_end_us`` (evnoise's events.h5) or the span of its events.
    """
    from ..errors import InputError
    from ..events import polarity_index
    from ..readers import open_events

    src = open_events(path, sensor=sensor, csv_columns=csv_columns)
    with src:
        hw = src.shape or (tuple(shape) if shape is not None else None)
        if hw is None:
            raise InputError(f"{path}: the sensor size is unknown (give --sensor WxH) to draw its events")
        height, width = hw
        flat = np.zeros(2 * height * width, dtype=np.int64)
        t_first = t_last = None
        for chunk in src.chunks():
            x, y = chunk["x"].astype(np.int64), chunk["y"].astype(np.int64)
            flat += np.bincount(polarity_index(chunk["p"]) * (height * width) + y * width + x, minlength=flat.size)
            t_first = int(chunk["t"][0]) if t_first is None else t_first
            t_last = int(chunk["t"][-1])
        t_end = src.meta.get("t_end_us")
    if t_end:
        duration_us = int(t_end)
    else:
        duration_us = (t_last - t_first + 1) if t_first is not None else 1
    return flat.reshape(2, height, width), max(duration_us, 1) * 1e-6


def separation_sheet(total, signal, duration_s: float, *, filter_text: str = ""):
    """Signal | noise rate maps (ON + OFF) and an overlay (signal green, noise magenta)."""
    total = np.asarray(total, dtype=np.float64).sum(axis=0)
    signal = np.asarray(signal, dtype=np.float64).sum(axis=0)
    noise = total - signal
    width = total.shape[1]
    shrink, enlarge = display_factor(width)
    per = 1.0 / duration_s
    maps = [resample(m * per, shrink, enlarge) for m in (signal, noise)]
    scale = LogScale.of_rates(maps, floor=per / (shrink * shrink))
    size = max(13, min(18, maps[0].shape[1] // 28))
    n_total = total.sum()
    names = ("signal", "noise")
    shares = [m.sum() / n_total if n_total else 0.0 for m in (signal, noise)]
    panels = [titled(colormap(scale(m)), f"{name}: {int(round(s * n_total)):,} events ({s:.1%})", size=size)
              for m, name, s in zip(maps, names, shares, strict=True)]
    green = np.nan_to_num(scale(maps[0]), nan=0.0)
    magenta = np.nan_to_num(scale(maps[1]), nan=0.0)
    overlay = np.stack([magenta, green, magenta], axis=-1)
    panels.append(titled(np.round(255 * overlay).astype(np.uint8), "signal (green) over noise (magenta)",
                         size=size))
    row = hstack(panels, 10)
    unit = "events/s per pixel, ON + OFF" + (f" (mean of {shrink}x{shrink} pixels)" if shrink > 1 else "")
    bar = colour_bar(hstack(panels[:2], 10).width, scale, f"event rate, {unit}, log scale", size=size - 1)
    parts = [row, bar]
    if filter_text:
        parts.insert(0, titled(np.full((1, row.width, 3), BACKGROUND[0], np.uint8), filter_text, size=size))
    return vstack(parts, gap=6, pad=8)


def check_png_output(png, others, *, overwrite: bool) -> None:
    """Fail early (before the work) when ``png`` cannot be written or names another output."""
    from pathlib import Path

    from ..errors import OutputError
    from ..io import open_output_path

    if png is None:
        return
    if Path(png).suffix.lower() != ".png":
        raise OutputError(f"--png must name a .png file, got {png}")
    open_output_path(png, overwrite=overwrite, what="PNG file")
    for other in others:
        if other is not None and Path(other).resolve() == Path(png).resolve():
            raise OutputError(f"--png and an event output name the same file: {png}")


def write_separation_png(events, signal_out, noise_out, png, *, overwrite: bool, filter_text: str = "",
                         sensor=None, csv_columns=None):
    """``separate --png``: count the written outputs (and the input where one is missing) and draw them."""
    from .._atomic import atomic_output

    total, duration = count_map(events, sensor=sensor, csv_columns=csv_columns)
    shape = total.shape[1:]
    if signal_out is not None:
        signal, _ = count_map(signal_out, shape=shape)
    else:
        signal = total - count_map(noise_out, shape=shape)[0]
    sheet = separation_sheet(total, signal, duration, filter_text=filter_text)
    with atomic_output(png, overwrite=overwrite, what="PNG file") as tmp:
        save_png(sheet, tmp)
    return png


__all__ = ["colormap", "simulate_sheet", "dataset_preview", "write_dataset_preview", "separation_sheet",
           "write_separation_png", "count_map", "PREVIEW"]
