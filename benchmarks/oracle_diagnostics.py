"""How much of the oracle baselines' score is the target's own brightness: reference rows for issue 20.

The oracle affine count image takes its offset and gain from the target. This script scores, on the
held-out test sets of ``python -m evnoise.reconstruct.pretrain --make-test-sets``, what such an oracle
gets with no counts at all, and what the U-Net gets when it is given the same oracle:

``constant, target's mean``   every pixel at the target's own mean (oracle, no counts)
``constant 0.4``              every pixel at 0.4 (no oracle, no counts)
``U-Net``                     the model as shipped
``U-Net, target's mean``      the U-Net shifted so that its mean is the target's (oracle)
``U-Net, affine fit``         the U-Net's best affine fit to the target (oracle, like the count image's)
``count image, affine fit``   baseline (a) of RECONSTRUCTION.md (oracle)

PSNR only (the brightness question is a PSNR question), with each row's paired difference to the count
image's oracle fit; standard errors over source images (the crops of one image are correlated).
Prints a markdown table.

    python benchmarks/oracle_diagnostics.py --test-sets heldout [--model evnoise/models/evk3-hd.pt]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROWS = ("constant, target's mean", "constant 0.4", "U-Net", "U-Net, target's mean", "U-Net, affine fit",
        "count image, affine fit")
REFERENCE = "count image, affine fit"


def affine_fit(pred, target):
    """``pred``'s least-squares affine map onto ``target``, clipped to [0, 1]."""
    a = np.stack([pred.ravel(), np.ones(pred.size)], axis=1)
    coef, *_ = np.linalg.lstsq(a, target.ravel(), rcond=None)
    return np.clip(a @ coef, 0.0, 1.0).reshape(target.shape)


def variants(unet, counts_affine, target) -> dict:
    """The images of every row for one pair."""
    return {
        "constant, target's mean": np.full_like(target, target.mean()),
        "constant 0.4": np.full_like(target, 0.4),
        "U-Net": unet,
        "U-Net, target's mean": np.clip(unet - unet.mean() + target.mean(), 0.0, 1.0),
        "U-Net, affine fit": affine_fit(unet, target),
        "count image, affine fit": counts_affine,
    }


def _per_source(values, sources):
    """Means over the pairs of each source image (its crops are correlated), in order of first appearance."""
    groups = {}
    for v, src in zip(values, sources, strict=True):
        groups.setdefault(src, []).append(v)
    return np.array([np.mean(g) for g in groups.values()])


def _mean_se(per_source):
    return float(per_source.mean()), float(per_source.std(ddof=1) / math.sqrt(per_source.size))


def diagnose(dataset, model) -> dict:
    """Per row: mean PSNR ± standard error, and the paired difference to the count image's oracle fit ± its
    standard error (both over source images)."""
    from evnoise.reconstruct.evaluate import evaluate
    from evnoise.reconstruct.metrics import psnr

    out = evaluate(dataset, model, methods=("unet", "counts-affine"), lpips=False, keep_predictions=len(dataset))
    scores = {r: [] for r in ROWS}
    sources = [ex["source"] for ex in out["examples"]]
    for ex in out["examples"]:
        target = ex["target"]
        for name, img in variants(ex["predictions"]["unet"], ex["predictions"]["counts-affine"], target).items():
            scores[name].append(psnr(img, target))
    ref = np.array(scores[REFERENCE])
    res = {}
    for r, v in scores.items():
        v = np.array(v)
        res[r] = (*_mean_se(_per_source(v, sources)), *_mean_se(_per_source(v - ref, sources)))
    res["n_sources"] = len(set(sources))
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--test-sets", required=True, help="folder written by pretrain --make-test-sets")
    ap.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    args = ap.parse_args(argv)
    from evnoise.generators import PairDataset
    from evnoise.reconstruct.infer import default_model_path

    model = args.model or str(default_model_path())
    names = ("dead-leaves", "photos")
    res = {n: diagnose(PairDataset(Path(args.test_sets) / n, "test"), model) for n in names}
    print("PSNR in dB; ± standard errors over source images (" +
          ", ".join(f"{n}: {res[n]['n_sources']}" for n in names) + f"); difference: paired, to '{REFERENCE}'.\n")
    print("| image | " + " | ".join(f"{n} PSNR | {n} difference" for n in names) + " |")
    print("|---|" + "---|---|" * len(names))
    for r in ROWS:
        cells = []
        for n in names:
            m, se, dm, dse = res[n][r]
            cells += [f"{m:.2f} ± {se:.2f}", "reference" if r == REFERENCE else f"{dm:+.2f} ± {dse:.2f}"]
        print(f"| {r} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
