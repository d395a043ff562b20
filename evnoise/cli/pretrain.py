"""``evnoise pretrain``: train the reconstructor that evnoise ships, make its held-out test sets, package it.

The recipe and its data are :mod:`evnoise.reconstruct.pretrain`; the U-Net training options are
``evnoise train``'s (one declaration, :func:`evnoise.cli._options.training`), with this recipe's defaults.
``python -m evnoise.reconstruct.pretrain ...`` is the same command.
"""

from __future__ import annotations

import logging

log = logging.getLogger("evnoise")

#: the recipe's training defaults (train's are for a user's own dataset)
DEFAULTS = dict(max_minutes=55.0, epochs=90, steps_per_epoch=100, crop=64, transform="anscombe", base_channels=16)


def register(subparsers) -> None:
    from ..reconstruct.pretrain import WHITE_RANGE_LUX
    from . import _options as opt
    from .train import SEED_HELP, THREADS_HELP

    p = subparsers.add_parser(
        "pretrain",
        help="train the shipped evk3-hd reconstructor reproducibly (or make its test sets, or package it)",
        description="Train the reconstructor that evnoise ships on procedural dead-leaves scenes and the photos "
        "installed packages carry (nothing is downloaded), with fresh brightness, contrast and noise per crop; "
        "or write the held-out test sets (--make-test-sets DIR); or strip a checkpoint's training state and add "
        "its held-out scores (--ship).",
        epilog="example: evnoise pretrain --out run.pt --max-minutes 55; evnoise pretrain --make-test-sets heldout; "
        "evnoise pretrain --ship run.pt --scores dead-leaves=id.json photos=ood.json --out evnoise/models/evk3-hd.pt",
        parents=[opt.output(metavar="MODEL.pt", help="checkpoint to write (training) or the shipped file (--ship)",
                            overwrite_help="replace an existing --out"),
                 opt.training(crop_help="training crop side, binned pixels (default %(default)s)", **DEFAULTS),
                 opt.run_options(seed_help=SEED_HELP, seed_default=0, threads_help=THREADS_HELP, threads_default=1)],
    )
    p.add_argument("--make-test-sets", metavar="DIR", help="write the held-out test sets to DIR and stop")
    p.add_argument("--ship", metavar="CHECKPOINT", help="strip CHECKPOINT's training state, add --scores, write --out")
    p.add_argument("--scores", nargs="*", default=[], metavar="NAME=JSON",
                   help="with --ship: held-out scores, e.g. dead-leaves=id.json photos=ood.json "
                   "(from evnoise evaluate --json)")
    p.add_argument("--channel-mults", default="1,2,4,4", help="U-Net levels (default %(default)s)")
    p.add_argument("--mismatch-sigma", type=float, default=0.0,
                   help="threshold-mismatch augmentation: eps_sigma of the training counts (default 0; slow)")
    p.add_argument("--dead-leaves", type=opt.count("--dead-leaves"), default=120,
                   help="procedural training scenes (default %(default)s)")
    p.add_argument("--white-range", default=f"{WHITE_RANGE_LUX[0]:g}:{WHITE_RANGE_LUX[1]:g}", metavar="LO:HI",
                   help="scene white level in lux, log-uniform per crop (brightness augmentation; default "
                   "%(default)s; one number: no augmentation)")
    p.add_argument("--no-photos", action="store_true", help="train on dead leaves only")
    p.set_defaults(func=run)


def _white_range(text) -> list:
    import math

    from ..errors import ParameterError

    try:
        white = [float(v) for v in str(text).split(":")]
    except ValueError:
        raise ParameterError(f"--white-range must be LO:HI lux, got {text!r}") from None
    white = white * 2 if len(white) == 1 else white
    if len(white) != 2 or not all(math.isfinite(v) for v in white) or not 0 < white[0] <= white[1]:
        raise ParameterError(f"--white-range must be LO:HI lux with 0 < LO <= HI, got {text!r}")
    return white


def _channel_mults(text) -> tuple:
    from ..errors import ParameterError

    try:
        mults = tuple(int(m) for m in str(text).split(","))
    except ValueError:
        mults = ()
    if not mults or min(mults) < 1:
        raise ParameterError(f"--channel-mults must be positive whole numbers separated by commas, got {text!r}")
    return mults


#: Largest --scores file read (an evaluate --json result is a few kB; its per-image lists grow with the test set).
MAX_SCORES_BYTES = 16 * 1024 * 1024


def _scores_file(path):
    """The bytes of a --scores file: a regular file (not a FIFO or a device) of at most MAX_SCORES_BYTES."""
    from .._checks import read_bounded_file

    return read_bounded_file(path, max_bytes=MAX_SCORES_BYTES, missing="scores", kind="a scores file (JSON)",
                             bound="an evaluate result (JSON) may have")


def _scores(items) -> dict:
    import json

    from ..errors import InputError, ParameterError
    from ..reconstruct import pretrain as recipe

    scores = {}
    for item in items:
        name, _, path = item.partition("=")
        if not path or not name:
            raise ParameterError(f"--scores takes NAME=JSON, got {item!r}")
        data = _scores_file(path)
        try:
            result = json.loads(data)
        except (ValueError, RecursionError) as exc:  # RecursionError: lists nested past the recursion limit
            why = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
            raise InputError(f"cannot read scores {path}: not JSON ({why})"[:300]) from None
        problem = recipe.scores_problem(result)
        if problem:
            raise InputError(f"scores {path} is not an evnoise evaluate --json result: {problem}"[:300])
        scores[name] = result
    return scores


def run(args) -> int:
    import shlex
    import time

    from ..errors import ParameterError
    from ..reconstruct import pretrain as recipe
    from ._options import counted

    if args.make_test_sets:
        made = recipe.make_test_sets(args.make_test_sets, progress=not args.quiet)
        print("wrote " + ", ".join(str(p) for p in made.values()))
        return 0
    if not args.out:
        raise ParameterError("--out is required")
    if args.ship:
        from ._paths import refuse_writing_inputs

        refuse_writing_inputs([("--out", args.out)], [("the --ship checkpoint", args.ship)]
                              + [("a --scores file", item.partition("=")[2]) for item in args.scores])
        path = recipe.ship(args.ship, args.out, scores=_scores(args.scores))
        print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
        return 0
    from ..reconstruct.train import TrainConfig, train

    white = _white_range(args.white_range)
    mults = _channel_mults(args.channel_mults)
    t0 = time.perf_counter()
    data, val, description = recipe.build_training_data(
        seed=args.seed, n_dead_leaves=args.dead_leaves, mismatch_sigma=args.mismatch_sigma,
        photos=not args.no_photos, progress=not args.quiet, white_range_lux=white)
    log.info("training data ready in %.0f s", time.perf_counter() - t0)
    config = TrainConfig(epochs=args.epochs, steps_per_epoch=args.steps_per_epoch, batch_size=args.batch_size,
                         crop=args.crop, lr=args.lr, ssim_weight=args.ssim_weight, patience=None,
                         max_minutes=args.max_minutes, val_crop=128, seed=args.seed, transform=args.transform,
                         ml_sigma=args.ml_sigma, pixel_loss=args.pixel_loss)
    model = {"base_channels": args.base_channels, "channel_mults": mults}
    card = {"preset": recipe.PRESET, "sensor": "Prophesee EVK3-HD (IMX636), 1280x720 (the preset's camera)",
            "white_lux_range": list(white), "display_white_lux": recipe.DISPLAY_WHITE_LUX,
            "contrast_range": list(recipe.CONTRAST_RANGE), "mismatch_eps_sigma": args.mismatch_sigma,
            "training_data": description, "held_out_photos": list(recipe.HELD_OUT_PHOTOS),
            "recipe": "evnoise " + shlex.join(getattr(args, "argv", None) or ["pretrain"])}
    result = train(data, args.out, val_data=val, config=config, model=model, resume=args.resume,
                   overwrite=args.overwrite, progress=not args.quiet, threads=args.threads,
                   data_description=description, card=card)
    print(f"trained {counted(result['epochs'], 'epoch')} ({counted(result['steps'], 'step')}, "
        f"{result['elapsed_s'] / 60:.1f} min, "
          f"stopped by {result['stopped']}); validation PSNR {result['val_psnr']:.2f} dB, SSIM "
          f"{result['val_ssim']:.3f} (epoch {result['best_epoch']}); wrote {result['out']}")
    return 0
