"""``evnoise make-dataset``: NE2I-style count/image pairs, sharded, reproducible, parallel.

Examples::

    evnoise make-dataset photos/ --out ds --window 0.1,0.25,0.5,1,2 --seed 1
    evnoise make-dataset --procedural dead-leaves --count 500 --out dl --crop 256 --crops-per-image 4
    evnoise make-dataset --source package-photos --crop 256 --crops-per-image 40 --max-lux 6:30 --out photos
    evnoise make-dataset photos/ --out ds --scheduler tcp://scheduler:8786   # on a Dask cluster

Running the same command again on the same ``--out`` resumes an interrupted run (finished
shards are verified by checksum and kept) or, for a complete dataset, verifies it.
"""

from __future__ import annotations

import argparse
import logging
import time

from ..errors import ParameterError

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    from . import _options as opt

    p = subparsers.add_parser(
        "make-dataset",
        help="make NE2I-style training pairs (noise-event counts + image), sharded and reproducible",
        description="Make Noise2Image-style training pairs: for every source image (and crop), ON/OFF "
        "noise-event counts over each --window, binned 2x2, with the display-encoded grey image. Pairs go "
        "to HDF5 shards under --out with a manifest.json (splits by source image, the full config). The "
        "same --seed gives the same bytes for any --workers or --scheduler; running the command again "
        "resumes an interrupted run.",
        epilog="examples: evnoise make-dataset photos/ --out ds --window 0.1,0.25,0.5,1,2 --seed 1;  "
        "evnoise make-dataset --procedural dead-leaves --count 500 --crop 256 --out dl;  "
        "evnoise make-dataset --source package-photos --crop 256 --crops-per-image 40 --max-lux 6:30 --out ph "
        "(photos shipped by scikit-image and matplotlib, read in place; their licences: see "
        "evnoise.generators.sources)",
    )
    p.add_argument("images", nargs="*", metavar="IMAGES",
                   help="image folders (PNG, JPEG, TIFF, OpenEXR; not recursive) and/or image files")
    opt.add_out(p, required=True, metavar="DIR", help="output folder (new, empty, or this job's)")
    src = p.add_argument_group("procedural and packaged scenes")
    src.add_argument("--procedural", choices=("dead-leaves",), help="add procedural images (needs --count)")
    src.add_argument("--count", type=opt.count("--count", maximum=1_000_000), metavar="N",
                     help="number of procedural images (at most 1,000,000)")
    src.add_argument("--source", action="append", choices=("package-photos",), default=[],
                     help="add the natural photos that installed packages ship (scikit-image, matplotlib, "
                     "scikit-learn, PyWavelets); nothing is downloaded")
    geo = p.add_argument_group("geometry")
    opt.add_sensor(geo, default="1280x720", help="sensor size every image is fitted to (default: %(default)s)")
    opt.add_image_fit(geo, help="how images are brought to --sensor (default: %(default)s)")
    geo.add_argument("--crop", metavar="WxH",
                     help="cut random crops of this size (sensor pixels, multiples of --binning) instead of "
                     "using the whole sensor; one number for a square")
    geo.add_argument("--crops-per-image", type=int, default=1, metavar="K",
                     help="crops per source image (needs --crop; default: %(default)s)")
    opt.add_binning(geo, default=2, metavar="B", help="sum counts over BxB pixels (default: %(default)s, as in the "
                    "paper)")
    sim = p.add_argument_group("illumination and noise")
    sim.add_argument("--window", action="append", metavar="S",
                     help="integration window(s) in seconds, comma separated or repeated "
                     "(default 1; the paper's Table S1: 0.1,0.25,0.5,1,2)")
    sim.add_argument("--mode", choices=("counts", "events"), default="counts",
                     help="counts: draw the counts directly (fast); events: simulate the event stream and "
                     "count it (slow; same distribution) (default: %(default)s)")
    opt.add_max_lux(sim, ranges=True, default="18",
                    help="lux of full-scale white of 8/16-bit and procedural images; LO:HI draws one per crop "
                    "(log-uniform brightness augmentation) (default: %(default)s)")
    opt.add_lux_scale(sim, ranges=True, default="1",
                      help="lux per unit of linear images (OpenEXR, float TIFF) (default: %(default)s)")
    sim.add_argument("--contrast", default="1", metavar="G|LO:HI",
                     help="exponent applied to linear luminance, Y -> Y^G; LO:HI draws one per crop "
                     "(contrast augmentation) (default: %(default)s)")
    sim.add_argument("--white-lux", type=opt.positive_number("--white-lux", "lux", maximum=opt.MAX_LUX),
                     metavar="LUX",
                     help="lux shown as white in the stored images (default: the top of --max-lux)")
    opt.add_encoding(sim)
    opt.add_clip_invalid(sim, help="clip NaN/Inf/negative pixel values instead of skipping the image")
    opt.add_preset(sim, help="noise-model preset (default: %(default)s)")
    opt.add_seed(sim, help="seed of everything (default: the interrupted run's in --out, else a fresh one, stored)")
    out = p.add_argument_group("output and execution")
    out.add_argument("--split", default="0.8,0.1,0.1", metavar="TRAIN,VAL,TEST",
                     help="fractions of source images per split (default: %(default)s)")
    out.add_argument("--shard-size", type=int, default=64, metavar="N",
                     help="pairs per HDF5 shard, about (default: %(default)s)")
    opt.add_compression(out, default="lzf",
                        help="HDF5 compression of counts and images (default: %(default)s, the fastest that h5py "
                        "always reads; gzip for tools without h5py's LZF filter)")
    out.add_argument("--workers", type=int, metavar="N",
                     help="worker processes (default: the CPU count); never changes the output")
    opt.add_threads(out, help="threads per worker for --mode events and the general sampler (default: CPUs / "
                    "workers)")
    out.add_argument("--scheduler", metavar="ADDRESS",
                     help="run on a Dask distributed cluster (e.g. tcp://host:8786; needs evnoise[dask]; workers "
                     "must see --out and the images at the same paths)")
    opt.add_overwrite(out, help="replace a dataset made with different options in --out")
    p.set_defaults(func=run)


def _splits(text: str):
    parts = [s.strip() for s in str(text).split(",")]
    try:
        values = tuple(float(s) for s in parts)
    except ValueError:
        raise ParameterError(f"--split must be three fractions TRAIN,VAL,TEST, got {text!r}") from None
    if len(values) != 3:
        raise ParameterError(f"--split must be three fractions TRAIN,VAL,TEST, got {text!r}")
    return values


def build_config(args):
    """A :class:`~evnoise.generators.PairConfig` from parsed arguments."""
    from ..generators.config import PairConfig, parse_range, parse_shape, parse_windows
    from . import _options as opt
    from ._options import check_text_file

    check_text_file(args.preset)
    opt.check_range_text(args.max_lux, "--max-lux", "lux")
    opt.check_range_text(args.lux_scale, "--lux-scale", "lux per unit")
    for text in args.window or []:
        for part in filter(str.strip, str(text).split(",")):
            try:
                opt.seconds("--window", positive=True)(part)
            except argparse.ArgumentTypeError as exc:
                raise ParameterError(str(exc)) from None

    return PairConfig(
        sensor_shape=parse_shape(args.sensor, "--sensor"),
        crop_shape=parse_shape(args.crop, "--crop") if args.crop else None,
        crops_per_image=args.crops_per_image,
        binning=args.binning,
        windows_s=parse_windows(args.window or ["1"]),
        mode=args.mode,
        max_lux=parse_range(args.max_lux, "--max-lux", "lux"),
        lux_scale=parse_range(args.lux_scale, "--lux-scale", "lux per unit"),
        contrast=parse_range(args.contrast, "--contrast", "exponent"),
        white_lux=args.white_lux,
        fit=args.fit,
        encoding=args.encoding,
        clip_invalid=args.clip_invalid,
        splits=_splits(args.split),
        shard_size=args.shard_size,
        compression=None if args.compression == "none" else args.compression,
        seed=args.seed,
        preset=args.preset,
    )


def build_sources(args) -> list:
    from ..generators.sources import DeadLeaves, PackagePhotos

    sources = list(args.images)
    if args.procedural:
        if args.count is None:
            raise ParameterError("--procedural needs --count N (the number of images)")
        sources.append(DeadLeaves(args.count))
    elif args.count is not None:
        raise ParameterError("--count is the number of --procedural images; give --procedural dead-leaves")
    if "package-photos" in args.source:
        sources.append(PackagePhotos())
    if not sources:
        raise ParameterError("no scenes: give IMAGES (folders or files), --procedural dead-leaves --count N, "
                             "or --source package-photos")
    return sources


def run(args) -> int:
    from ..generators.dataset import make_dataset

    started = time.perf_counter()
    quiet = bool(getattr(args, "quiet", False))
    if args.workers is not None and args.workers < 1:
        raise ParameterError(f"--workers must be >= 1, got {args.workers}")
    # --threads and --seed are checked when parsed (_options)
    config = build_config(args)
    sources = build_sources(args)
    from ._paths import refuse_writing_inputs

    refuse_writing_inputs([("--out", args.out)], [*(("an input", p) for p in args.images),
                                                  ("the --preset file", args.preset)], output_folder=True)
    result = make_dataset(sources, args.out, config, workers=args.workers, scheduler=args.scheduler,
                          threads=args.threads, progress=not quiet, overwrite=args.overwrite)
    preview = _write_preview(result.path, bool(result.generated))
    if not quiet:
        m = result.manifest
        t = m["totals"]
        splits = ", ".join(f"{s} {m['splits'][s]['samples']}" for s in ("train", "val", "test"))
        made = (f"made {len(result.generated)} shard(s)" + (f", kept {len(result.reused)} verified"
                                                            if result.reused else ""))
        if not result.generated:
            made = f"complete: all {len(result.reused)} shard(s) verified, nothing to do"
        print(f"{result.path}: {t['samples']} pairs ({splits}) from {t['sources']} source images in "
              f"{t['shards']} shards; {made}; seed {m['config']['seed']}; "
              f"{time.perf_counter() - started:.1f} s")
        if t["skipped_sources"]:
            print(f"skipped {t['skipped_sources']} source image(s); reasons in {result.path / 'manifest.json'}")
        if t["saturated_bins"]:
            print(f"warning: {t['saturated_bins']} count bins saturated at 65535")
        if preview is not None:
            print(f"preview of a few pairs: {preview}")
    return 0


def _write_preview(root, changed: bool):
    """``preview.png`` in the dataset folder (redrawn when shards were made or it is missing); a
    failure to draw it is a warning, not an error (the dataset itself is complete)."""
    from ._pictures import PREVIEW, write_dataset_preview

    path = root / PREVIEW
    if path.exists() and not changed:
        return path
    try:
        return write_dataset_preview(root)
    except Exception as exc:  # noqa: BLE001 - the picture must never fail a finished dataset
        log.warning("could not draw %s: %s", path, exc)
        return None


def _register_info_kind() -> None:
    from . import info

    def detect(path):
        from ..generators.summary import is_dataset

        return is_dataset(path)

    def summarise(path):
        from ..generators.summary import summarise_dataset

        return summarise_dataset(path)

    info.register_kind("dataset", detect, summarise)


_register_info_kind()
