"""``evnoise info DATASET``: what a pair dataset holds, and a check of its counts against the model."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

__all__ = ["is_dataset", "summarise_dataset", "sanity_rows", "sanity_table"]

#: Pairs read for the sanity table (spread evenly over the dataset).
SANITY_PAIRS = 16


def is_dataset(path) -> bool:
    """A dataset folder (or its manifest.json) written by ``evnoise make-dataset`` (or being written)."""
    from .dataset import MANIFEST, PROGRESS_DIR
    from .shards import FORMAT

    path = Path(path)
    if path.is_dir() and not (path / MANIFEST).exists() and (path / PROGRESS_DIR / "plan.json").is_file():
        return True  # an interrupted run: summarising it explains how to resume
    manifest = path / MANIFEST if path.is_dir() else path
    if manifest.name != MANIFEST or not manifest.is_file():
        return False
    try:
        with open(manifest, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError:
        return False
    return f'"format": "{FORMAT}"'.encode() in head or FORMAT.encode() in head


def summarise_dataset(path, *, sanity: bool = True) -> dict:
    """``{label: value}`` for ``evnoise info`` (plain JSON types, display order).

    Parameters
    ----------
    path : str or os.PathLike
        The dataset's folder, or its ``manifest.json``.
    sanity : bool, default True
        Also compare measured noise rates in flat regions of some pairs with the model's (reads
        pairs from the shards); skipped for a dataset without pairs.

    Returns
    -------
    dict
        Layout, size, pair shapes, splits, skipped sources, configuration, parameters and, with
        ``sanity``, the rate comparison per lux bin.
    """
    from .dataset import load_manifest

    root, m = load_manifest(path)
    cfg = m["config"]
    totals = m["totals"]
    pair = m["pair"]
    c, h, w = pair["counts"]["shape"]
    b = pair["counts"]["binning"]
    out = {
        "layout": f"evnoise pairs dataset ({totals['shards']} HDF5 shard{'' if totals['shards'] == 1 else 's'} "
                  "+ manifest.json)",
        "size_bytes": int(totals["bytes"]),
        "pairs": int(totals["samples"]),
        "pair": f"counts {c}x{h}x{w} uint16 [ON, OFF] ({b}x{b} binned); image {h}x{w} float32, sRGB in [0, 1]",
        "windows_s": [float(x) for x in cfg["windows_s"]],
        "splits": {s: {"pairs": int(v["samples"]), "sources": int(v["sources"]),
                       "sources_skipped": int(v["sources_planned"] - v["sources"]), "shards": int(v["shards"])}
                   for s, v in sorted(m["splits"].items(), key=lambda kv: ("train", "val", "test").index(kv[0]))},
        "skipped_sources": len(m["skipped"]),
    }
    if m["skipped"]:
        out["skipped"] = {s["source"]: s["reason"] for s in m["skipped"][:10]}
        if len(m["skipped"]) > 10:
            out["skipped"]["..."] = f"{len(m['skipped']) - 10} more (see manifest.json)"
    out["saturated_bins"] = int(totals["saturated_bins"])
    out["sampler"] = m.get("sampler", "?")
    out["seed"] = cfg["seed"]
    out["evnoise_version"] = m.get("evnoise_version")
    sensor = cfg["sensor_shape"]
    crop = cfg["crop_shape"]
    out["config"] = {
        "sensor": f"{sensor[1]}x{sensor[0]} (fit: {cfg['fit']})",
        "crop": f"{crop[1]}x{crop[0]}, {cfg['crops_per_image']} per image" if crop else "whole sensor",
        "mode": cfg["mode"],
        "max_lux": _range_text(cfg["max_lux"]),
        "contrast_gamma": _range_text(cfg["contrast"]),
        "white_lux": cfg["white_lux"],
        "preset": cfg["preset"],
        "splits": "/".join(f"{f:.3g}" for f in cfg["splits"]),
        "shard_size": cfg["shard_size"],
        "compression": cfg["compression"] or "none",
        "sources": "; ".join(_source_text(s) for s in m["sources"]),
    }
    out["params"] = cfg["params"]
    if sanity and totals["samples"] > 0:
        out["sanity"] = {"(per lux bin)": "pixels; ON and OFF events/s per sensor pixel in flat regions, measured "
                                          "vs model (ratio, z-score)", **sanity_table(root, m)}
    return out


def _range_text(r) -> str:
    lo, hi = r
    return f"{lo:g}" if lo == hi else f"{lo:g} .. {hi:g} (log-uniform)"


def _source_text(spec: dict) -> str:
    kind = spec.get("kind")
    if kind == "folder":
        return f"folder {spec['path']}"
    if kind == "files":
        return f"{len(spec['paths'])} files"
    if kind == "dead-leaves":
        return f"dead leaves x {spec['count']}"
    if kind == "package-photos":
        return f"package photos ({', '.join(spec['packages'])})"
    return json.dumps(spec)


def _predicted_rate(lux, params):
    """Population-mean rate ``(2, n)`` events/s at illuminance ``lux`` (n,): threshold mismatch, background
    spread and hot pixels included (:func:`evnoise.expected_rate` with ``mismatch="mean"``, exact)."""
    from evnoise.rates import expected_rate

    return expected_rate(lux, params, mismatch="mean")


def _flat(lux, tolerance: float = 0.05):
    """Binned pixels whose 4 neighbours are within ``tolerance`` (relative) of them.

    The prediction uses a bin's mean illuminance; where the scene varies inside a bin the
    mean rate differs from the rate at the mean (the rate is not linear in lux), so only
    flat neighbourhoods are compared.
    """
    pad = np.pad(lux, 1, mode="edge")
    centre = pad[1:-1, 1:-1]
    dev = np.zeros_like(lux)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        np.maximum(dev, np.abs(pad[dy:dy + lux.shape[0], dx:dx + lux.shape[1]] - centre), out=dev)
    return dev <= tolerance * centre + 1e-9


def sanity_rows(root, manifest, *, n_pairs: int = SANITY_PAIRS) -> list:
    """Mean measured event rate per illuminance bin against the closed form.

    Reads ``n_pairs`` pairs spread over the dataset, recovers each binned pixel's illuminance
    from its image (``srgb_decode(image) * lux_scale``), keeps the pixels of flat
    neighbourhoods (see :func:`_flat`; saturated white pixels are left out too), and compares
    the counts per second and sensor pixel with the model's expected rate at that
    illuminance (the population mean when thresholds vary between pixels). ``z`` is
    ``(measured - predicted) / sqrt(predicted)`` in counts (a Poisson standard error; the
    trial model's counts vary a little less).
    """
    from evnoise.params import NoiseParams
    from evnoise.radiometry import srgb_to_linear

    from .reader import PairDataset

    cfg = manifest["config"]
    params = NoiseParams.from_dict(cfg["params"])
    white = float(cfg["white_lux"])
    b = int(cfg["binning"])
    edges = np.array([0.0, white / 256, white / 64, white / 16, white / 8, white / 4, white / 2, white])
    grid = np.concatenate([[0.0], np.geomspace(white * 1e-4, white, 400)])
    rate_grid = _predicted_rate(grid, params)
    obs = np.zeros((2, len(edges) - 1))
    pred = np.zeros((2, len(edges) - 1))
    pixels = np.zeros(len(edges) - 1, dtype=np.int64)
    expo = np.zeros(len(edges) - 1)  # sensor-pixel seconds per bin
    datasets = [PairDataset(root, s) for s in ("train", "val", "test")]
    total = sum(len(d) for d in datasets)
    picks = sorted(set(np.linspace(0, total - 1, min(n_pairs, total)).round().astype(int).tolist()))
    for idx in picks:
        for d in datasets:
            if idx < len(d):
                item = d[idx]
                break
            idx -= len(d)
        image = item["image"].astype(np.float64)
        lin = srgb_to_linear(image) * item["lux_scale"]
        keep = (image < 1.0 - 1e-6) & _flat(lin)
        lux = lin[keep]
        counts = item["counts"].reshape(2, -1)[:, keep.ravel()].astype(np.float64)
        exposure = item["window_s"] * b * b  # pixel-seconds per binned pixel
        k = np.clip(np.searchsorted(edges, lux, side="right") - 1, 0, len(edges) - 2)
        rates = np.stack([np.interp(lux, grid, rate_grid[0]), np.interp(lux, grid, rate_grid[1])])
        for p in range(2):
            obs[p] += np.bincount(k, weights=counts[p], minlength=len(edges) - 1)
            pred[p] += np.bincount(k, weights=rates[p] * exposure, minlength=len(edges) - 1)
        n_k = np.bincount(k, minlength=len(edges) - 1)
        pixels += n_k
        expo += n_k * exposure
    for d in datasets:
        d.close()
    rows = []
    for j in range(len(edges) - 1):
        if pixels[j] == 0:
            continue
        row = {"lux_low": float(edges[j]), "lux_high": float(edges[j + 1]), "pixels": int(pixels[j])}
        for p, name in enumerate(("on", "off")):
            row[f"{name}_rate_hz"] = float(obs[p, j] / expo[j])
            row[f"{name}_predicted_hz"] = float(pred[p, j] / expo[j])
            row[f"{name}_z"] = float((obs[p, j] - pred[p, j]) / math.sqrt(pred[p, j])) if pred[p, j] > 0 else 0.0
        rows.append(row)
    return rows


def sanity_table(root, manifest, *, n_pairs: int = SANITY_PAIRS) -> dict:
    """:func:`sanity_rows` as ``{"lux a-b": "text"}`` for ``evnoise info``."""
    table = {}
    for r in sanity_rows(root, manifest, n_pairs=n_pairs):
        cells = [f"{r['pixels']:>8d} px"]
        for name in ("on", "off"):
            pred = r[f"{name}_predicted_hz"]
            ratio = f"x{r[f'{name}_rate_hz'] / pred:.3f}" if pred > 0 else "x-"
            rate, z = r[f"{name}_rate_hz"], r[f"{name}_z"]
            cells.append(f"{name.upper()} {rate:.4g} vs {pred:.4g} ({ratio}, z {z:+.1f})")
        table[f"lux {r['lux_low']:.3g}-{r['lux_high']:.3g}"] = "  ".join(cells)
    return table
