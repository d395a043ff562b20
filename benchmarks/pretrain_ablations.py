"""Short ablations of the shipped reconstructor's recipe: same data, same steps, same test sets.

Each variant is ``python -m evnoise.reconstruct.pretrain`` with a fixed number of steps (no
time cap, so the budget is the same whatever the machine load) and one change; every model is
scored on the held-out test sets of ``pretrain --make-test-sets``. Writes a markdown table.

    python benchmarks/pretrain_ablations.py --work /tmp/ablations --steps 600 --parallel 2
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

VARIANTS = {
    "rate input (as `evnoise train`)": ["--transform", "rate"],
    "Anscombe input": ["--transform", "anscombe"],
    "Anscombe + ML-estimate channel (sigma 1)": ["--transform", "anscombe", "--ml-sigma", "1"],
    "Anscombe, 5 levels (wider receptive field)": ["--transform", "anscombe", "--channel-mults", "1,2,4,4,4"],
    "Anscombe, SSIM weight 0.5": ["--transform", "anscombe", "--ssim-weight", "0.5"],
    "rate input, no brightness augmentation (white 18 lux)": ["--transform", "rate", "--white-range", "18"],
    "rate input, dead leaves only (no photos)": ["--transform", "rate", "--no-photos"],
    "Anscombe, 5 levels, MSE pixel loss": ["--transform", "anscombe", "--channel-mults", "1,2,4,4,4",
                                           "--pixel-loss", "mse"],
    "Anscombe, 5 levels, MSE pixel loss, no SSIM term": ["--transform", "anscombe", "--channel-mults", "1,2,4,4,4",
                                                         "--pixel-loss", "mse", "--ssim-weight", "0"],
}


def run_variant(name, extra, work: Path, steps: int, dead_leaves: int, seed: int, nice: int = 0) -> dict:
    tag = "".join(c if c.isalnum() else "-" for c in name.lower())[:40]
    out = work / f"{tag}.pt"
    epochs = max(1, steps // 100)
    cmd = (["nice", "-n", str(nice)] if nice else []) + [
        sys.executable, "-m", "evnoise.reconstruct.pretrain", "--out", str(out), "--epochs", str(epochs),
        "--steps-per-epoch", "100", "--max-minutes", "600", "--dead-leaves", str(dead_leaves), "--seed", str(seed),
        "--overwrite", "-q", *extra]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise RuntimeError(f"{name} failed: {proc.stderr[-2000:]}")
    return {"name": name, "model": str(out), "wall_s": wall, "log": proc.stdout.strip().splitlines()[-1]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", required=True, help="folder for the test sets, models and results")
    ap.add_argument("--steps", type=int, default=600, help="training steps per variant (default 600)")
    ap.add_argument("--dead-leaves", type=int, default=60, help="training dead-leaves scenes (default 60)")
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", nargs="*", help="variant names to run (default: all)")
    ap.add_argument("--out", help="markdown table (default WORK/ablations.md)")
    ap.add_argument("--nice", type=int, default=0, help="run the trainings under this niceness (default 0)")
    args = ap.parse_args(argv)
    from evnoise.generators import PairDataset
    from evnoise.reconstruct.evaluate import evaluate
    from evnoise.reconstruct.pretrain import make_test_sets

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    if not (work / "heldout" / "photos" / "manifest.json").exists():
        make_test_sets(work / "heldout", progress=False)
    tests = {name: PairDataset(work / "heldout" / name, "test") for name in ("dead-leaves", "photos")}
    variants = {k: v for k, v in VARIANTS.items() if not args.only or k in args.only}
    with ThreadPoolExecutor(args.parallel) as pool:
        runs = list(pool.map(lambda kv: run_variant(kv[0], kv[1], work, args.steps, args.dead_leaves, args.seed,
                                                         args.nice),
                             variants.items()))
    rows = ["| variant | dead leaves PSNR ↑ | SSIM ↑ | LPIPS ↓ | photos PSNR ↑ | SSIM ↑ | LPIPS ↓ "
            "| train wall (min) |",
            "|---|---|---|---|---|---|---|---|"]
    results = {}
    for r in runs:
        cells, res = [], {}
        for tname, ds in tests.items():
            out = evaluate(ds, r["model"], methods=("unet",), lpips=True)
            m = out["metrics"]["unet"]
            res[tname] = {k: m[k][0] for k in m}
            cells += [f"{m['psnr'][0]:.2f}", f"{m['ssim'][0]:.3f}", f"{m['lpips'][0]:.3f}"]
        results[r["name"]] = {**res, "wall_s": r["wall_s"], "log": r["log"]}
        rows.append(f"| {r['name']} | " + " | ".join(cells) + f" | {r['wall_s'] / 60:.1f} |")
    table = "\n".join(rows)
    print(table)
    out = Path(args.out) if args.out else work / "ablations.md"
    previous = {}
    if (work / "ablations.json").is_file():  # runs of other variants (--only) are kept
        previous = json.loads((work / "ablations.json").read_text(encoding="utf-8"))
    previous.update(results)
    out.write_text(table + "\n", encoding="utf-8")
    (work / "ablations.json").write_text(json.dumps(previous, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
