"""Evaluation table: PSNR / SSIM / LPIPS of the U-Net and both baselines on a test set.

Usage (once a dataset exists)::

    evnoise evaluate DATASET [--model model.pt] [--split test] \\
        [--out table.md] [--json results.json] [--figure examples.png] [--no-lpips]

Methods, each on the same pairs:

``unet``            the trained reconstructor
``ml-inversion``    per-pixel maximum-likelihood illuminance (closed form, ON and OFF jointly,
                    Gaussian smoothing sigma 0.7 binned pixels), display-encoded like the targets
``counts-affine``   ON + OFF counts, best affine fit to the target (oracle: uses the target)
``counts-minmax``   ON + OFF counts stretched to [0, 1] (what a user sees without us)

Reported: mean and standard error over the pairs.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from pathlib import Path

import numpy as np

from .._atomic import atomic_output
from ..errors import InputError, ParameterError
from .baselines import MLInversion, count_image
from .metrics import psnr, ssim

log = logging.getLogger(__name__)

__all__ = ["evaluate", "format_table", "comparison_figure", "METHODS"]

METHODS = ("unet", "ml-inversion", "counts-affine", "counts-minmax")
LABELS = {
    "unet": "U-Net (evnoise)",
    "ml-inversion": "ML inversion, closed form (baseline b)",
    "counts-affine": "count image, affine fit to target (baseline a, oracle)",
    "counts-minmax": "count image, min-max (baseline a)",
}


def _summary(values):
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return None, None
    sem = float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else 0.0
    return float(v.mean()), sem


def evaluate(dataset, model=None, *, params=None, max_lux=None, lpips: bool = True, methods=METHODS,
             smoothing_sigma: float = 0.7, max_items: int | None = None, keep_predictions: int = 0,
             progress: bool = False) -> dict:
    """Metrics of every method on every pair of ``dataset``.

    Parameters
    ----------
    dataset : pair dataset
        Test pairs (see :mod:`evnoise.reconstruct.data`).
    model : path or Reconstructor, optional
        Checkpoint of the U-Net (needed for ``"unet"``).
    params : NoiseParams, optional
        Noise model of the ML baseline (default: the dataset's ``params`` attribute).
    max_lux : float, optional
        White level in lux of the ML baseline (default: the dataset's ``max_lux`` attribute, then
        the checkpoint's ``max_lux``). A pair with a ``"lux_scale"`` (lux of image value 1) uses
        that instead.
    lpips : bool, default True
        Also compute LPIPS (needs torch and the installed weights).
    methods : sequence of str, default METHODS
        Which of :data:`METHODS` to run.
    smoothing_sigma : float or sequence of float, default 0.7
        Gaussian smoothing (binned pixels) of the ML baseline; several values give one row
        each (``"ml-inversion@<sigma>"``).
    max_items : int, optional
        Evaluate only the first this-many pairs (default: all).
    keep_predictions : int, default 0
        Keep the outputs of the first this-many pairs (for :func:`comparison_figure`).
    progress : bool, default False
        Show a progress bar (needs tqdm).

    Returns
    -------
    dict
        ``{"n": int, "metrics": {method: {"psnr": (mean, sem), "ssim": ..., "lpips": ...}},
        "per_item": [...], "seconds": {method: s}, "examples": [...]}``.
    """
    from .infer import Reconstructor, short_window_note

    methods = tuple(methods)
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise ParameterError(f"unknown method(s) {sorted(unknown)}; choose from {METHODS}")
    net = None
    if "unet" in methods:
        if model is None:
            raise ParameterError("the 'unet' method needs a model")
        net = model if isinstance(model, Reconstructor) else Reconstructor(model)
    inverter = None
    if "ml-inversion" in methods:
        params = params if params is not None else getattr(dataset, "params", None)
        if max_lux is None:
            max_lux = getattr(dataset, "max_lux", None)
        if max_lux is None and net is not None:
            max_lux = net.spec.max_lux
        if params is None or max_lux is None:
            raise ParameterError(
                "the ML-inversion baseline needs the noise parameters and max_lux of the dataset "
                "(give params= / max_lux=)"
            )
        binning = int(getattr(dataset, "binning", net.spec.binning if net is not None else 2))
        sigmas = [float(smoothing_sigma)] if np.ndim(smoothing_sigma) == 0 else [float(x) for x in smoothing_sigma]
        inverter = {("ml-inversion" if len(sigmas) == 1 else f"ml-inversion@{x:g}"):
                    MLInversion(params, max_lux=float(max_lux), binning=binning, smoothing_sigma=x) for x in sigmas}
        methods = tuple(m2 for m in methods for m2 in (inverter if m == "ml-inversion" else [m]))
    lp = None
    if lpips:
        from .lpips import LPIPS

        lp = LPIPS()

    n = len(dataset) if max_items is None else min(len(dataset), int(max_items))
    if n == 0:
        raise InputError("the test set is empty")
    per_item, examples = [], []
    short = {}  # pair windows shorter than every window the U-Net was trained on: how many pairs each
    seconds = {m: 0.0 for m in methods}
    iterator = range(n)
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(iterator, desc="evaluating", unit="pair")
    for i in iterator:
        item = dataset[i]
        counts = np.asarray(item["counts"])
        target = np.asarray(item["image"], dtype=np.float64)
        window = float(item["window_s"])
        preds = {}
        for m in methods:
            t0 = time.perf_counter()
            if m == "unet":
                preds[m] = net.predict_binned(counts, window)
                if short_window_note(net.spec, window) is not None:
                    short[window] = short.get(window, 0) + 1
            elif m.startswith("ml-inversion"):
                # a pair's own white level (make-dataset's "lux_scale") when it has one
                preds[m] = inverter[m].display(counts, window, max_lux=item.get("lux_scale"))
            elif m == "counts-affine":
                preds[m] = count_image(counts, target=target, mode="affine")
            else:
                preds[m] = count_image(counts, mode="minmax")
            seconds[m] += time.perf_counter() - t0
        row = {"index": i, "source": str(item.get("source", i)), "window_s": window}
        for m, pred in preds.items():
            row[m] = {"psnr": psnr(pred, target), "ssim": ssim(pred, target),
                      "lpips": lp.distance(pred, target) if lp is not None else None}
        per_item.append(row)
        if len(examples) < keep_predictions:
            examples.append({"counts": counts, "target": target, "window_s": window, "predictions": preds,
                             "source": row["source"]})
    if short:
        log.warning("%d of the %d pairs have windows (%s s) shorter than the model's; %s", sum(short.values()), n,
                    ", ".join(f"{w:g}" for w in sorted(short)), short_window_note(net.spec, min(short), "the shortest"))
    metrics = {}
    for m in methods:
        metrics[m] = {k: _summary([r[m][k] for r in per_item]) for k in ("psnr", "ssim", "lpips")}
    return {"n": n, "metrics": metrics, "per_item": per_item, "seconds": seconds, "examples": examples}


def format_table(result: dict, *, title: str | None = None) -> str:
    """Markdown table of :func:`evaluate`'s result (mean +- standard error).

    Parameters
    ----------
    result : dict
        What :func:`evaluate` returns (its ``"n"`` and ``"metrics"`` are used).
    title : str, optional
        A bold heading above the table, followed by the number of pairs.

    Returns
    -------
    str
        The table, one row per method; ``n/a`` where a metric was not computed.
    """

    def cell(v, digits):
        mean, sem = v
        return "n/a" if mean is None else f"{mean:.{digits}f} ± {sem:.{digits}f}"

    lines = []
    if title:
        lines += [f"**{title}** ({result['n']} pairs)", ""]
    lines += ["| method | PSNR (dB) ↑ | SSIM ↑ | LPIPS (AlexNet) ↓ |", "|---|---|---|---|"]
    for m, v in result["metrics"].items():
        label = LABELS.get(m) or LABELS["ml-inversion"].replace("closed form", f"closed form, sigma {m.split('@')[1]}")
        lines.append(f"| {label} | {cell(v['psnr'], 2)} | {cell(v['ssim'], 3)} | {cell(v['lpips'], 3)} |")
    return "\n".join(lines)


def comparison_figure(examples, path, *, methods=None) -> Path:
    """PNG grid: input counts (ON + OFF) / baseline / U-Net / ground truth, one row per pair."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    if not examples:
        raise InputError("no examples to plot")
    if methods is None:
        preds = examples[0]["predictions"]
        methods = ([m for m in ("counts-affine",) if m in preds]
                   + [m for m in preds if m.startswith("ml-inversion")][-1:] + ["unet"])
    cols = ["counts (ON + OFF)"] + [LABELS.get(m, m).split(" (")[0] for m in methods] + ["ground truth"]
    cols = [c.replace("ml-inversion@", "ML inversion, sigma ") for c in cols]
    fig, axes = plt.subplots(len(examples), len(cols), figsize=(2.6 * len(cols), 2.6 * len(examples)), squeeze=False)
    for r, ex in enumerate(examples):
        panels = [np.asarray(ex["counts"]).sum(axis=0)] + [ex["predictions"][m] for m in methods] + [ex["target"]]
        for c, img in enumerate(panels):
            ax = axes[r, c]
            ax.imshow(img, cmap="gray", vmin=0 if c else None, vmax=1 if c else None, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(cols[c], fontsize=9)
        axes[r, 0].set_ylabel(f"{ex['source']} ({ex['window_s']:g} s)", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    try:
        with atomic_output(path, what="PNG file") as tmp:
            fig.savefig(tmp, dpi=100, format="png")
    finally:
        plt.close(fig)
    return path


def main(argv=None) -> int:
    """``python -m evnoise.reconstruct.evaluate ARGS``: the same as ``evnoise evaluate ARGS`` (one declaration of
    its options, in :mod:`evnoise.cli.evaluate`)."""
    from ..cli import main as cli

    return cli(["evaluate", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
