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

PSNR only (the brightness question is a PSNR question). Prints a markdown table.

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


def diagnose(dataset, model) -> dict:
    """Mean PSNR and its standard error over the pairs, per row."""
    from evnoise.reconstruct.evaluate import evaluate
    from evnoise.reconstruct.metrics import psnr

    out = evaluate(dataset, model, methods=("unet", "counts-affine"), lpips=False, keep_predictions=len(dataset))
    scores = {r: [] for r in ROWS}
    for ex in out["examples"]:
        target = ex["target"]
        for name, img in variants(ex["predictions"]["unet"], ex["predictions"]["counts-affine"], target).items():
            scores[name].append(psnr(img, target))
    return {r: (float(np.mean(v)), float(np.std(v, ddof=1) / math.sqrt(len(v)))) for r, v in scores.items()}


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
    print("| PSNR (dB) | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for r in ROWS:
        print(f"| {r} | " + " | ".join(f"{res[n][r][0]:.2f} ± {res[n][r][1]:.2f}" for n in names) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
