"""``evnoise train DATASET --out model.pt``: train the U-Net reconstructor (needs ``evnoise[train]``)."""

from __future__ import annotations

import logging

log = logging.getLogger("evnoise")


#: --seed and --threads of train and pretrain (one declaration, the same help)
SEED_HELP = "seed of everything random (default 0)"
THREADS_HELP = ("torch CPU threads (default 1: on a busy 2-core machine one thread was 3-10x faster per step than "
                "two; raise it on an idle machine)")


def register(subparsers):
    from . import _options as opt

    p = subparsers.add_parser(
        "train",
        help="train the U-Net reconstructor on count/image pairs",
        description="Train the noise-events-to-image U-Net on a dataset from `evnoise make-dataset` "
        "(or a .npz pairs file). Writes a resumable checkpoint after every epoch and a PNG of the "
        "loss curves next to it.",
        parents=[opt.output(required=True, metavar="MODEL.pt", help="checkpoint to write (e.g. model.pt)",
                            overwrite_help="replace an existing --out"),
                 opt.training(),
                 opt.run_options(seed_help=SEED_HELP, seed_default=0, threads_help=THREADS_HELP, threads_default=1)],
    )
    p.add_argument("dataset", help="make-dataset folder or .npz pairs file")
    p.add_argument("--val", help="separate validation dataset (default: the dataset's 'val' split, "
                                  "else a share of its source images)")
    p.add_argument("--val-fraction", type=float, default=0.15, help="share of source images held out (default 0.15)")
    p.add_argument("--patience", type=int, default=12, help="early stopping after N epochs without improvement "
                                                               "(default 12; 0 disables)")
    p.add_argument("--polarities", choices=("both", "on", "off"), default="both", help="count channels used")
    p.add_argument("--no-plot", action="store_true", help="do not write the loss-curve PNG")
    p.set_defaults(func=run)


def _open_val(path, args):
    from ..errors import EvnoiseError
    from ..reconstruct.data import open_pairs

    if args.val:
        return open_pairs(args.val, split="val" if not args.val.endswith(".npz") else "train")
    if str(path).endswith(".npz"):
        return None
    try:
        val = open_pairs(path, split="val")
    except (EvnoiseError, KeyError, ValueError):
        return None  # no validation split: hold out source images instead
    return val if len(val) else None


def run(args) -> int:
    from ..errors import ParameterError
    from ..reconstruct.data import open_pairs
    from ..reconstruct.train import TrainConfig, train
    from ._options import counted

    if args.patience is not None and args.patience < 0:
        raise ParameterError(f"--patience must be >= 0, got {args.patience}")
    from pathlib import Path

    from ._paths import refuse_writing_inputs

    out = Path(args.out)
    refuse_writing_inputs([("--out", out), ("the loss plot", None if args.no_plot else
                                            out.with_name(out.stem + ".loss.png"))],
                          [("the dataset", args.dataset), ("the --val dataset", args.val)])
    data = open_pairs(args.dataset, split="train")
    val = _open_val(args.dataset, args)
    crop = args.crop if args.crop is not None else _default_crop(data, val)
    config = TrainConfig(
        epochs=args.epochs, steps_per_epoch=args.steps_per_epoch, batch_size=args.batch_size, crop=crop,
        lr=args.lr, ssim_weight=args.ssim_weight, patience=args.patience or None, max_minutes=args.max_minutes,
        val_fraction=args.val_fraction, polarities=args.polarities, seed=args.seed, transform=args.transform,
        ml_sigma=args.ml_sigma, pixel_loss=args.pixel_loss,
    )
    model = {"base_channels": args.base_channels} if args.base_channels else None
    result = train(data, args.out, val_data=val, config=config, model=model, resume=args.resume,
                   overwrite=args.overwrite, progress=not args.quiet, plot=not args.no_plot, threads=args.threads,
                   data_description=str(args.dataset))
    scores = ""
    if result.get("val_psnr") is not None:
        scores = f"validation PSNR {result['val_psnr']:.2f} dB, SSIM {result['val_ssim']:.3f} (best epoch " \
                 f"{result['best_epoch']}); "
    print(
        f"trained {counted(result['epochs'], 'epoch')} ({counted(result['steps'], 'step')}, "
        f"{result['elapsed_s'] / 60:.1f} min, "
        f"stopped by {result['stopped']}); {scores}wrote {result['out']}"
        + (f" and {result['plot']}" if result["plot"] else "")
    )
    return 0


def _default_crop(data, val) -> int:
    """64 binned pixels, or the largest multiple of the model's size step that fits every pair."""
    import numpy as np

    from ..errors import InputError
    from ..reconstruct.train import DEFAULT_MODEL

    multiple = int(DEFAULT_MODEL.get("stem", 1)) * 2 ** (len(DEFAULT_MODEL["channel_mults"]) - 1)
    side = min(min(np.asarray(ds[0]["image"]).shape) for ds in (data, val) if ds is not None and len(ds))
    crop = min(64, side // multiple * multiple)
    if crop < multiple:
        raise InputError(f"the pairs are {side} binned pixels across, smaller than the {multiple} the U-Net needs: "
                         f"make the dataset with a larger make-dataset --crop (sensor pixels)")
    return crop


def _register_info_kind() -> None:
    """Let ``evnoise info model.pt`` describe reconstructor checkpoints (torch loads only then)."""
    from . import info

    def detect(path):
        import zipfile

        from ..errors import InputError

        if not zipfile.is_zipfile(path):
            return False
        try:
            with zipfile.ZipFile(path) as z:
                return any(name.endswith("data.pkl") for name in z.namelist())
        except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:  # a damaged archive: no checkpoint of ours
            raise InputError(f"{path}: a damaged zip archive ({exc}), not a model checkpoint evnoise reads") from None

    def summarise(path):
        from ..reconstruct.checkpoint import checkpoint_summary

        return checkpoint_summary(path)

    info.register_kind("checkpoint", detect, summarise)


_register_info_kind()
