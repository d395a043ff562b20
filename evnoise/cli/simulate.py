"""``evnoise simulate INPUT --out events.h5``: an image or a folder of frames to an event file (any format
evnoise writes: the ``--out`` suffix decides).

An image is a static scene simulated for ``--duration`` seconds (renewal tier, O(events));
a folder of frames is a video at ``--fps`` frames per second, frames sorted naturally by
file name (``frame2`` before ``frame10``) and read lazily.
"""

from __future__ import annotations

import logging
import secrets
import textwrap
import time
from pathlib import Path
from typing import Iterator, NamedTuple

from .._checks import path_text
from ..errors import InputError, OutputError, ParameterError
from . import _options as opt

log = logging.getLogger(__name__)

EXAMPLE = "example.png"


def register(subparsers) -> None:
    from ..radiometry import DEFAULT_MAX_LUX

    p = subparsers.add_parser(
        "simulate",
        help="simulate the events of an image (static scene) or a folder of frames (video)",
        description="Simulate event-camera events of an image (a static scene, for --duration seconds) "
        "or of a folder of frames (a video at --fps) and write them to an event file: events.h5 (DSEC layout) or "
        "another format, as the --out suffix says.",
        epilog="example: evnoise simulate --example --duration 10 --out example.h5 --png example.png "
        "(-q: no progress bar and no summary)",
        parents=[
            opt.output(required=True, metavar="FILE", event_formats=True,
                       help="output event file; the suffix decides the format: .h5 (events.h5, DSEC layout, with "
                       "parameters and seed), .aedat4 (parameters and seed in its description), .raw (Prophesee EVT "
                       "3.0), .dat (Prophesee DAT), .es (Event Stream), .csv (t,x@W,y@H,on)"),
            opt.image_input(
                sensor_help="sensor size, e.g. 1280x720 (default: the image's size)",
                fit_help="how to bring images to --sensor: cover (scale keeping the aspect ratio, crop the "
                "centre), crop (centre crop, no scaling), resize (stretch) (default: %(default)s)",
                max_lux_help=f"illuminance of full-scale white of 8/16-bit images (default {DEFAULT_MAX_LUX:g} lux, "
                "the Noise2Image monitor at grey 255)",
                lux_scale_help="lux per unit of linear images (OpenEXR, float TIFF) (default 1)",
                clip_invalid_help="clip NaN, Inf and negative pixel values (with a warning) instead of failing"),
            opt.run_options(seed_help="random seed, 0 .. 2**63-1 (default: a fresh one, printed and stored in the "
                            "file)", threads_help="worker threads (default: all CPUs)"),
        ],
    )
    p.add_argument("input", nargs="?", metavar="INPUT",
                   help="an image (PNG, JPEG, TIFF, OpenEXR) or a folder of frames")
    opt.add_example(p, help="use the bundled 1280x720 example image as INPUT")
    p.add_argument("--duration", type=opt.seconds("--duration", positive=True), metavar="S",
                   help="length of a static scene in seconds (default 1); not used for a folder")
    opt.add_fps(p, help="frame rate of a folder of frames (required for a folder)")
    opt.add_preset(p)
    p.add_argument("--method", choices=("auto", "renewal", "trials"), default="auto",
                   help="simulation tier (default: %(default)s)")
    opt.add_compression(p, default="gzip", help="HDF5 compression of the events (default: %(default)s)")
    opt.add_png(p, help="also write a PNG of the scene beside its ON/OFF event-rate maps (log scales, colour bars)")
    p.set_defaults(func=run)


# --------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------
def parse_sensor(text):
    """``"1280x720"`` -> ``(720, 1280)`` (H, W); ``None`` stays ``None`` (the readers' parser: one for every
    command)."""
    from ..readers import parse_sensor as parse

    return parse(text)


class LuxFrames:
    """Frames of a folder as illuminance, read lazily (``len`` and indexing, as ``iter_video`` wants).

    Every frame must have the size (after fitting to the sensor) and kind of the first one; the last
    few frames read are kept, since the simulator reads neighbouring frames repeatedly.
    """

    def __init__(self, paths, convert, keep: int = 4, on_frame=None):
        self.paths = list(paths)
        self.kind = None  # "display" or "linear" (radiometry.lux_and_kind): the first frame's, for all
        self._convert = convert
        self._on_frame = on_frame  # called with each frame's illuminance when it is first read
        self._keep = keep
        self._cache: dict[int, object] = {}
        self.shape = None
        self.shape = self[0].shape

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i):
        i = int(i)
        if i in self._cache:
            return self._cache[i]
        lux, kind = self._convert(self.paths[i])
        if self.kind is None:
            self.kind = kind
        elif kind != self.kind:
            names = {"display": "an 8/16-bit display-referred image", "linear": "a linear (EXR / floating-point) image"}
            raise InputError(f"frame {self.paths[i]} is {names[kind]}, but the first frame {self.paths[0]} is "
                             f"{names[self.kind]}: their illuminance scales differ (--max-lux vs --lux-scale); "
                             f"give all frames one kind")
        if self._on_frame is not None:
            self._on_frame(lux)
        if self.shape is not None and lux.shape != self.shape:
            h, w = lux.shape
            raise InputError(
                f"frame {self.paths[i]} is {w}x{h} pixels, but the first frame {self.paths[0]} is "
                f"{self.shape[1]}x{self.shape[0]}; give all frames one size or pass --sensor WxH"
            )
        if len(self._cache) >= self._keep:
            self._cache.pop(next(iter(self._cache)))
        self._cache[i] = lux
        return lux


# --------------------------------------------------------------------------------------
# the command
# --------------------------------------------------------------------------------------
def run(args) -> int:
    """Run ``evnoise simulate`` with parsed arguments; returns the exit code."""
    from ..io import open_output_path
    from ._paths import refuse_writing_inputs

    started = time.perf_counter()
    quiet = bool(getattr(args, "quiet", False))
    source, source_label = _source(args)
    is_video = source.is_dir()
    refuse_writing_inputs([("--out", args.out), ("--png", args.png)],
                          [("the input folder" if is_video else "the input image", source),
                           ("the --preset file", args.preset)], frames_folder=True)
    duration, fps = _timing(args, source, is_video)
    # --threads, --seed, --duration, --fps are checked when parsed (_options), before anything runs
    sensor = parse_sensor(args.sensor)
    params = opt.load_preset_arg(args.preset)
    from ..io import output_format

    fmt = output_format(args.out)  # the suffix decides; a folder or an unknown suffix is an error
    if args.format is not None and args.format != fmt:
        raise ParameterError(f"--format {args.format} disagrees with --out {args.out} ({fmt}); the suffix decides")
    out = open_output_path(args.out, overwrite=args.overwrite, what="event file")
    if fmt != "h5":
        from ..io import import_faery

        import_faery()  # fail before the work if faery is missing
    png = None
    if args.png:
        png = open_output_path(args.png, overwrite=args.overwrite, what="PNG file")
        if png.resolve() == out.resolve():
            raise OutputError(f"--png and --out name the same file: {out}")
    seed = args.seed if args.seed is not None else secrets.randbelow(1 << 32)
    if args.seed is None:
        log.info("no --seed given; using seed %d (stored in the file)", seed)
    attrs = {
        "source": source_label, "preset": path_text(args.preset), "params": params, "seed": int(seed),
        "method": args.method, "encoding": args.encoding, "max_lux": args.max_lux, "lux_scale": args.lux_scale,
        "fit": args.fit if sensor else None,
    }
    scene = _scene(args, source, is_video, duration, fps, sensor, params, seed, progress=not quiet)
    attrs.update(scene.attrs)
    if hasattr(scene.stream, "expected_events"):  # before anything runs: print the size, refuse what cannot fit
        import sys

        from ..simulate import check_disk_space

        compression = None if args.compression == "none" else args.compression
        room = check_disk_space(scene.stream, out, fmt, compression=compression)
        if not quiet:
            print(f"evnoise: {room}", file=sys.stderr)
    counts = _write_outputs(args, fmt, out, png, scene, attrs)
    if not quiet:
        print(summary(counts, scene.t_end_us * 1e-6, scene.text, params_label=str(args.preset), seed=seed,
                      method=args.method, out=out, png=png, elapsed_s=time.perf_counter() - started))
    return 0


def _source(args):
    """``(path, label)`` of the input image or folder."""
    if args.example and args.input:
        raise InputError(f"give either INPUT ({args.input}) or --example, not both")
    if args.example:
        return Path(str(_example_path())), f"evnoise example ({EXAMPLE})"
    if not args.input:
        raise InputError("no input: give an image or a folder of frames as INPUT, or --example")
    source = Path(args.input)
    if not source.exists():
        raise InputError(f"input not found: {source}")
    return source, path_text(source)


def _timing(args, source, is_video):
    """``(duration_s, fps)``: a duration for an image (default 1 s), a frame rate for a folder."""
    duration = opt.positive(args.duration, "--duration", "seconds")
    fps = opt.positive(args.fps, "--fps", "frames per second")
    if is_video:
        if duration is not None:
            raise ParameterError("--duration is for a single image; the length of a folder of frames is set "
                                 "by the number of frames and --fps")
        if fps is None:
            raise ParameterError(f"{source} is a folder of frames: give their frame rate with --fps")
    else:
        if fps is not None:
            raise ParameterError(f"--fps is for a folder of frames, but {source} is a single image "
                                 f"(use --duration)")
        if duration is None:
            duration = 1.0
    return duration, fps


class _Scene(NamedTuple):
    """What ``_scene`` prepares: the event stream and what the outputs need to know about it."""

    stream: Iterator  # time-sorted event arrays
    shape: tuple  # (H, W)
    t_end_us: int  # end of the recording (exclusive)
    attrs: dict  # attributes for the event file
    text: str  # description for the summary
    lux: object = None  # (H, W) illuminance shown beside the event maps (a video: its first frame)


def _scene(args, source, is_video, duration, fps, sensor, params, seed, *, progress) -> _Scene:
    """Read the input (validating every frame) and start the simulation (nothing written yet)."""
    import functools

    import numpy as np

    from .. import radiometry
    from ..simulate import iter_events, iter_video

    convert = functools.partial(
        _scene_lux, max_lux=args.max_lux, lux_scale=args.lux_scale, encoding=args.encoding,
        clip_invalid=args.clip_invalid, sensor_shape=sensor, fit=args.fit,
    )
    light = _LightCheck(params, args.preset)
    if is_video:
        frames = LuxFrames(radiometry.list_frames(source), convert, on_frame=light)
        if len(frames) < 2:
            raise InputError(f"folder {source} holds one frame; a video needs at least 2 "
                             f"(simulate the image itself with --duration for a static scene)")
        log.info("%s: %d frames of %dx%d pixels, %s .. %s", source, len(frames), frames.shape[1],
                 frames.shape[0], frames.paths[0].name, frames.paths[-1].name)
        timestamps = np.arange(len(frames)) / fps
        t_end_us = int(round(timestamps[-1] * 1e6))
        stream = iter_video(frames, timestamps, params, seed, args.method, threads=args.threads, progress=progress)
        attrs = {"scene": "video", "fps": fps, "n_frames": len(frames), "duration_s": t_end_us * 1e-6}
        return _Scene(stream, frames.shape, t_end_us, attrs, f"a {len(frames)}-frame video at {fps:g} fps",
                      frames[0])
    lux = convert(source)[0]
    light(lux)
    stream = iter_events(lux, params, duration, seed, args.method, threads=args.threads, progress=progress)
    attrs = {"scene": "static", "duration_s": duration, "lux_min": float(lux.min()),
             "lux_mean": float(lux.mean()), "lux_max": float(lux.max())}
    text = (f"a static scene ({lux.min():.3g} to {lux.max():.3g} lux, mean {lux.mean():.3g} lux) "
            f"for {duration:g} s")
    return _Scene(stream, lux.shape, int(round(duration * 1e6)), attrs, text, lux)


def _scene_lux(path, **options):
    """:func:`evnoise.radiometry.lux_and_kind` of an input file, refusing illuminance above the
    :data:`~evnoise.cli._options.MAX_LUX` that ``--max-lux`` and ``--lux-scale`` are held to (a linear image
    stores its lux itself: a float pixel of 3e38 lux gave a file of no events and exit 0)."""
    from ..radiometry import lux_and_kind

    lux, kind = lux_and_kind(path, **options)
    top = float(lux.max()) if lux.size else 0.0
    if top > opt.MAX_LUX:
        raise InputError(f"{path_text(path)} reaches {top:.3g} lux, above the {opt.MAX_LUX:.0e} lux this command "
                         f"takes (full sunlight is about 1e5 lux); scale a linear image with --lux-scale")
    return lux, kind


class _LightCheck:
    """Warns once (a log warning: ``-q`` hides it, like the command's other warnings) when at least
    :data:`evnoise.params.LIGHT_WARNING_SHARE` of the scene's pixels (over the image, or over the frames
    read so far) lie outside the range the preset was fitted on (:func:`evnoise.params.light_range_warning`);
    a photograph's few black pixels do not count as a dark scene."""

    def __init__(self, params, preset):
        from ..params import preset_light_range

        self.preset = preset if preset is not None else params
        self.range = preset_light_range(self.preset)  # once: a video's frames are counted against it
        self.active = self.range is not None
        self.lo = self.hi = None
        self.outside = self.total = 0

    def __call__(self, lux) -> None:
        if not self.active:
            return
        from ..params import LIGHT_WARNING_SHARE, light_outside_range, light_range_warning

        lo, hi = float(lux.min()), float(lux.max())
        self.lo = lo if self.lo is None else min(self.lo, lo)
        self.hi = hi if self.hi is None else max(self.hi, hi)
        outside, total = light_outside_range(self.range, lux)
        self.outside += outside
        self.total += total
        share = self.outside / max(self.total, 1)
        if share < LIGHT_WARNING_SHARE:
            return
        message = light_range_warning(self.preset, self.lo, self.hi, outside_share=share)
        if message is not None:
            self.active = False
            log.warning("%s", message)


def _write_outputs(args, fmt, out, png, scene: _Scene, attrs):
    """Run the simulation into the event file (and the PNG); returns the counts ``(2, H, W)``."""
    import numpy as np

    from .._atomic import AtomicFile, os_error_text
    from ..events import polarity_index
    from ..io import open_event_writer

    height, width = scene.shape
    counts = np.zeros(2 * height * width, dtype=np.int64)

    def counted(chunks):
        for chunk in chunks:
            flat = polarity_index(chunk["p"]) * (height * width) + chunk["y"].astype(np.int64) * width
            flat += chunk["x"]
            counts[:] += np.bincount(flat, minlength=counts.size)
            yield chunk

    png_out = None
    try:
        compression = None if args.compression == "none" else args.compression
        with open_event_writer(out, scene.shape, attrs, overwrite=args.overwrite, compression=compression,
                               t_end_us=scene.t_end_us) as writer:  # the format of the --out suffix
            for chunk in counted(scene.stream):
                writer.write(chunk)
            if png is not None:  # written before the event file is renamed: both or neither
                png_out = AtomicFile(png, what="PNG file")
                _write_png_file(counts.reshape(2, height, width), png_out, scene)
        if png_out is not None:
            try:
                png_out.commit()
            except OSError as exc:
                raise OutputError(f"cannot write PNG file {png}: {os_error_text(exc)}") from None
    finally:
        if png_out is not None and not png_out.done:
            png_out.discard()
    return counts.reshape(2, height, width)


def _write_png_file(counts, out, scene: _Scene) -> None:
    """Draw the PNG into the temporary file of ``out`` (an ``AtomicFile``); an error names the final name."""
    from .._atomic import os_error_text

    try:
        save_count_png(counts, out.tmp, lux=scene.lux, duration_s=scene.t_end_us * 1e-6,
                       scene_title="first frame" if scene.attrs.get("scene") == "video" else "scene")
    except OSError as exc:  # its errno's text: str(exc) reads "[Errno 28] ..." and may name the temporary file
        raise OutputError(f"cannot write PNG file {out.path}: {os_error_text(exc)}") from None


def _example_path():
    from importlib import resources

    path = resources.files("evnoise.data") / EXAMPLE
    if not path.is_file():
        raise InputError(f"the bundled example image {EXAMPLE} is missing from the installed evnoise package")
    return path


def save_count_png(counts, path, *, lux=None, duration_s=None, scene_title: str = "scene") -> None:
    """PNG of the scene and its ON and OFF event-rate maps, with labels and colour bars.

    Left: ``lux`` (the scene's illuminance, ``(H, W)``) in grey on a log lux scale, so that the
    maps can be read against it (the noise rate peaks near 1-2 lux: a bright sky is dark in the
    maps); omitted when ``lux`` is None. Right: ON and OFF maps in events/s per pixel
    (``counts / duration_s``; plain counts without ``duration_s``) on one shared log colour
    scale (99.9th percentile at the top, black = no events), labelled, with the colour bar
    below. Sensors wider than 640 pixels are shown block-averaged (the caption says so).
    """
    from ._pictures import save_png, simulate_sheet

    save_png(simulate_sheet(counts, lux=lux, duration_s=duration_s, scene_title=scene_title), path)


def summary(counts, duration_s, scene, *, params_label, seed, method, out, png, elapsed_s) -> str:
    """The one-paragraph report printed at the end of a run."""
    from .._budget import human_bytes

    on, off = (int(c.sum()) for c in counts)
    total = on + off
    pixels = counts.shape[1] * counts.shape[2]
    size = Path(out).stat().st_size
    outputs = f"{out} ({human_bytes(size)})" + (f" and {png}" if png else "")
    per_pixel_s = pixels * duration_s
    text = (
        f"Simulated {scene} on a {counts.shape[2]}x{counts.shape[1]} sensor (preset {params_label}, "
        f"seed {seed}, method {method}): {total:,} events ({on:,} ON, {off:,} OFF), on average "
        f"{total / per_pixel_s:.3g} events/s per pixel (ON {on / per_pixel_s:.3g}, OFF {off / per_pixel_s:.3g}). "
        f"Wrote {outputs} in {elapsed_s:.1f} s."
    )
    return textwrap.fill(text, width=100)


__all__ = ["register", "run", "parse_sensor", "LuxFrames", "save_count_png", "summary"]
