"""``evnoise evaluate DATASET [--model M]``: PSNR / SSIM / LPIPS of the reconstructor and the baselines.

Methods, all on the same pairs: the U-Net (``--model``, default the shipped evk3-hd model),
per-pixel maximum-likelihood inversion with the closed form (baseline b; one row per
``--ml-sigma``), and the count image: affine fit to the target (an oracle) and min-max
stretched (baseline a). Reported: mean and standard error over the pairs.
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger("evnoise")

#: --threads of the commands that run the U-Net (evaluate, reconstruct)
TORCH_THREADS_HELP = "torch CPU threads (default 1)"


def register(subparsers):
    from . import _options as opt

    p = subparsers.add_parser(
        "evaluate",
        help="score the reconstructor against the baselines on a test set (PSNR, SSIM, LPIPS)",
        description="Score the U-Net reconstructor and the baselines (closed-form ML inversion, count "
        "image) on the pairs of a dataset from `evnoise make-dataset` (or a .npz pairs file): PSNR, SSIM "
        "and LPIPS (AlexNet, offline weights), mean and standard error over the pairs. Images are display "
        "values in [0, 1]: PSNR with a peak of 1; SSIM as scikit-image's with a Gaussian window (sigma 1.5), the "
        "population covariance and data range 1 (its defaults give 0.005-0.02 other values).",
        epilog="example: evnoise evaluate heldout/photos --ml-sigma 0.7 --ml-sigma 2 --ml-sigma 4 "
        "--out table.md --json results.json --figure examples.png",
        parents=[opt.output(metavar="TABLE.md", help="write the markdown table here"),
                 opt.run_options(threads_help=TORCH_THREADS_HELP, threads_default=1)],
    )
    p.add_argument("dataset", help="make-dataset folder or .npz pairs file")
    opt.add_model(p)
    p.add_argument("--split", default="test", choices=("train", "val", "test"),
                   help="dataset split (default: test; a .npz file has one)")
    opt.add_preset(p, default=None, help="noise preset of the ML baseline (default: the dataset's parameters)")
    opt.add_max_lux(p, help="white level of the ML baseline in lux (default: the dataset's)")
    p.add_argument("--ml-sigma", type=float, action="append", metavar="S",
                   help="Gaussian smoothing of the ML baseline, binned pixels (repeatable: one row each; "
                   "default 0.7)")
    p.add_argument("--no-lpips", action="store_true", help="skip LPIPS (faster)")
    p.add_argument("--max-items", type=int, metavar="N", help="score only the first N pairs")
    p.add_argument("--title", help="title line of the table (default: the dataset and split)")
    p.add_argument("--json", metavar="RESULTS.json", help="write every number (per pair too) here")
    p.add_argument("--figure", metavar="FIG.png",
                   help="PNG of counts / ML baseline / U-Net / ground truth (first pair of up to 6 source images)")
    p.set_defaults(func=run)


def _check_outputs(args):
    from pathlib import Path

    from .._atomic import refuse_folder_name
    from ..errors import OutputError, ParameterError

    outputs = []
    for flag, value, suffix in (("--out", args.out, ".md"), ("--json", args.json, ".json"),
                                ("--figure", args.figure, ".png")):
        if value is None:
            continue
        refuse_folder_name(value, f"{flag} file")
        path = Path(value)
        if path.suffix.lower() != suffix:
            raise ParameterError(f"{flag} must be a {suffix} file, got {path}")
        folder = path.parent if str(path.parent) else Path(".")
        if not folder.is_dir():
            raise OutputError(f"output folder {folder} does not exist")
        if path.is_dir():
            raise OutputError(f"{path} is a folder")
        if os.path.lexists(path) and not args.overwrite:  # a link counts, even a broken one
            raise OutputError(f"{path} exists (use --overwrite)")
        outputs.append((flag, path))
    return outputs


def run(args) -> int:
    import json
    import math

    from .._atomic import atomic_output
    from ..errors import ParameterError
    from ..reconstruct.data import open_pairs
    from ..reconstruct.evaluate import comparison_figure, evaluate, format_table
    from ..reconstruct.infer import Reconstructor, default_model_path

    if args.max_items is not None and args.max_items < 1:
        raise ParameterError(f"--max-items must be >= 1, got {args.max_items}")
    # --max-lux is checked when parsed (_options.positive_number)
    for sigma in args.ml_sigma or ():
        if not (math.isfinite(sigma) and sigma >= 0):
            raise ParameterError(f"--ml-sigma must be >= 0 binned pixels, got {sigma}")
    outputs = _check_outputs(args)
    try:
        from ._paths import refuse_writing_inputs

        refuse_writing_inputs([(flag, path) for flag, path in outputs],
                              [("the dataset", args.dataset), ("the --model", args.model)])
    except ImportError:  # pragma: no cover - older tree without the shared check
        pass
    data = open_pairs(args.dataset, split=args.split if not str(args.dataset).endswith(".npz") else "train")
    model = Reconstructor(args.model if args.model is not None else default_model_path(), threads=args.threads)
    data_white = getattr(data, "max_lux", None)
    if data_white is not None and model.spec.max_lux is not None and \
            not math.isclose(float(data_white), model.spec.max_lux, rel_tol=1e-6):
        log.warning("the dataset shows %g lux as white but the model was trained with %g lux as white: the U-Net's "
                    "images are on a different brightness scale than the targets", data_white, model.spec.max_lux)
    params = None
    if args.preset:
        from ._options import load_preset_arg

        params = load_preset_arg(args.preset)
    sigmas = args.ml_sigma or [0.7]
    result = evaluate(data, model, params=params, max_lux=args.max_lux, lpips=not args.no_lpips,
                      max_items=args.max_items, keep_predictions=len(data) if args.figure else 0,
                      progress=not args.quiet, smoothing_sigma=sigmas[0] if len(sigmas) == 1 else sigmas)
    table = format_table(result, title=args.title or f"{args.dataset} [{args.split}]")
    print(table)
    for flag, path in outputs:
        if flag == "--out":
            with atomic_output(path, overwrite=args.overwrite, what="table") as tmp:
                tmp.write_text(table + "\n", encoding="utf-8")
        elif flag == "--json":
            doc = {k: v for k, v in result.items() if k != "examples"}
            doc["model"] = str(model.path)
            doc["dataset"] = str(args.dataset)
            doc["split"] = args.split
            with atomic_output(path, overwrite=args.overwrite, what="JSON file") as tmp:
                tmp.write_text(json.dumps(doc, indent=1, default=float), encoding="utf-8")
        else:
            with atomic_output(path, overwrite=args.overwrite, what="figure") as tmp:
                comparison_figure(_one_per_source(result["examples"]), tmp)
    return 0


def _one_per_source(examples, limit: int = 6):
    """The first pair of each source image, up to ``limit`` (a figure that shows different scenes)."""
    seen, out = set(), []
    for ex in examples:
        if ex["source"] not in seen:
            seen.add(ex["source"])
            out.append(ex)
    return (out if len(out) > 1 else examples)[:limit]
