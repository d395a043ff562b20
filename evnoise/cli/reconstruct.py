"""``evnoise reconstruct EVENTS --out image.png [--model model.pt]``: image from noise events.

EVENTS is any event file evnoise reads (events.h5 or a camera recording).

Without ``--model`` the reconstructor shipped with evnoise (``evnoise/models/evk3-hd.pt``,
trained for the ``evk3-hd`` preset) is used.
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger("evnoise")


def register(subparsers):
    from . import _options as opt
    from .evaluate import TORCH_THREADS_HELP

    p = subparsers.add_parser(
        "reconstruct",
        help="reconstruct a static image from the noise events of an event file (events.h5 or a camera "
        "recording)",
        description="Count the ON/OFF events of a window, bin them as in training, run the trained "
        "U-Net and write an 8-bit grayscale PNG. With --step, a moving window writes one PNG per "
        "position (OUT_0000.png, OUT_0001.png, ...). A window shorter than the model's training window is "
        "shown to the model as its counts scaled up to that window (an estimate of the same rates; noisier).",
        parents=[opt.events_input(),
                 opt.output(required=True, metavar="PNG|DIR", help="output PNG (with --fps: the output folder)"),
                 opt.run_options(threads_help=TORCH_THREADS_HELP, threads_default=1)],
    )
    opt.add_model(p)
    p.add_argument("--window", type=opt.seconds("--window", positive=True), default=None, metavar="S",
                   help="integration window in seconds (default: the longest window the model was trained on "
                   "that fits into the recording)")
    opt.add_t_start(p, help="start of the window in seconds on the recording's clock (default: its start, 0 for "
                    "events.h5, the first event of a camera file)")
    p.add_argument("--step", type=opt.seconds("--step", positive=True, minimum=1e-6), default=None, metavar="S",
                   help="moving window: advance by S seconds per frame")
    p.add_argument("--frames", type=opt.count("--frames"), default=None,
                   help="with --step or --fps: at most this many frames")
    opt.add_binning(p, help="check that the model uses this binning")
    video = p.add_argument_group("video mode (--fps): the static background behind moving things")
    opt.add_fps(video, help="write one frame per 1/F seconds into the folder --out (frame_NNNNN.png, "
                "overlay_NNNNN.png, frames.csv), from the noise events of pixels without motion over the "
                "last --window seconds")
    video.add_argument("--separator", choices=("density", "activity", "none"), default="density",
                       help="signal/noise separator of the video mode (default density; none: no motion mask)")
    video.add_argument("--no-overlay", action="store_true", help="video mode: do not write the overlay PNGs")
    video.add_argument("--no-sheet", action="store_true",
                       help="video mode: do not write contact_sheet.png and frames.gif (a sheet of frames spread "
                       "over the run and an animation, both with a legend of the overlay colours)")
    p.set_defaults(func=run)


def run(args) -> int:
    import math
    import time
    from pathlib import Path

    from .._clock import seconds_text
    from ..errors import InputError, OutputError, ParameterError
    from ..io import open_output_path
    from ..reconstruct.imaging import write_png
    from ..reconstruct.infer import Reconstructor, counts_from_h5, default_model_path, h5_duration_s
    from ._options import counted
    from ._paths import refuse_writing_inputs

    refuse_writing_inputs([("--out", args.out)], [("the events file", args.events), ("the --model", args.model)],
                          folder_files=("frame_*.png", "overlay_*.png", "frames.csv", "contact_sheet.png",
                                        "frames.gif") if args.fps else None)
    model_path = args.model if args.model is not None else default_model_path()
    if args.fps is not None:
        if args.step is not None:
            raise ParameterError("--step and --fps are two different moving-window modes; give one")
        from ..reconstruct.video import reconstruct_video

        res = reconstruct_video(args.events, model_path, args.out, fps=args.fps, window_s=args.window,
                                separator=None if args.separator == "none" else args.separator,
                                binning=args.binning, t_start_s=args.t_start, max_frames=args.frames,
                                sensor=args.sensor, csv_columns=args.csv_columns,
                                overlay=not args.no_overlay, overwrite=args.overwrite, threads=args.threads,
                                progress=not args.quiet)
        extra = ""
        if not args.no_sheet:
            from ..reconstruct.sheets import animated_gif, contact_sheet

            sheet = contact_sheet(res["out_dir"])
            gif = animated_gif(res["out_dir"], fps=res["fps"])
            extra = f"; {sheet.name} and {gif.name}"
        if not args.quiet:
            print(f"wrote {counted(res['n_frames'], 'frame')}{extra} to {res['out_dir']} ({res['fps']:g} fps, window "
                  f"{res['window_s']:g} s, {res['mean_masked']:.1%} of the pixels masked on average)")
        return 0
    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise ParameterError(f"--out must be a .png file, got {out}")
    open_output_path(args.out, overwrite=True, what="PNG file")  # a folder, a missing or unwritable one: one line
    from ..readers import recording_span_us, window_counts

    camera = (args.sensor is not None or args.csv_columns is not None
              or Path(args.events).suffix.lower() not in (".h5", ".hdf5"))
    if camera:  # any camera file, streamed: the span on its own clock
        start_us, end_us = recording_span_us(args.events, sensor=args.sensor, csv_columns=args.csv_columns)
        duration = end_us * 1e-6
    else:
        start_us, duration = 0, h5_duration_s(args.events)  # checks the events file first: cheap, clear errors
    if args.t_start is None:
        args.t_start = start_us * 1e-6
    meta = None
    if camera:
        from ..io import read_metadata

        meta = read_metadata(args.events, sensor=args.sensor, csv_columns=args.csv_columns)
        if not meta.get("shape"):  # before the model is loaded and its warnings are printed
            raise InputError(f"{args.events}: the header gives no sensor size; add --sensor WxH")
    rec = Reconstructor(model_path, threads=args.threads)
    _warn_mismatch(args.events, rec)
    if camera:  # a real camera's noise is not the model's simulated preset: say so, do not fail
        card = rec.doc.get("card") or {}
        size = f"{meta['shape'][1]}x{meta['shape'][0]}" if meta.get("shape") else "unknown size"
        log.warning("%s carries no evnoise model parameters (%s, %s: a camera's recording?), the model was "
                    "trained on simulated noise (preset %s%s): the noise statistics may differ",
                    args.events, meta.get("camera") or meta.get("format"), size,
                    card.get("preset") or "unknown", f", {card['sensor']}" if card.get("sensor") else "")
    if args.binning is not None and args.binning != rec.binning:
        raise ParameterError(
            f"the model was trained on {rec.binning}x{rec.binning}-binned counts; "
            f"--binning {args.binning} does not match"
        )
    from ..reconstruct.infer import choose_window, short_window_note

    if args.window is not None:
        window, note = args.window, short_window_note(rec.spec, args.window)
    else:
        window, note = choose_window(rec.spec, duration, args.t_start)
    if note:
        log.warning(note)
    starts = [args.t_start]
    if args.step is not None:
        from ..reconstruct.infer import check_frame_plan

        # the number of windows, counted before they are listed (a far-off last event spans years of steps)
        room = duration + 1e-6 - window - args.t_start
        planned = 0 if room < 0 else math.floor(room / args.step) + 1
        if args.frames is not None:
            planned = min(planned, args.frames)
        check_frame_plan(planned, hint=f"the recording runs from t = {seconds_text(args.t_start)} s to "
                         f"{seconds_text(duration)} s: give --frames N, a later --t-start or a larger --step")
        starts = []
        t = args.t_start
        while t + window <= duration + 1e-6 and (args.frames is None or len(starts) < args.frames):
            starts.append(t)
            t += args.step
        if not starts:
            raise ParameterError(f"the stream from t = {seconds_text(args.t_start)} s to its end at "
                                 f"{seconds_text(duration)} s is shorter than one window of {window:g} s")
    if args.step is None:
        targets = [out]
    else:
        targets = [out.with_name(f"{out.stem}_{k:04d}{out.suffix}") for k in range(len(starts))]
    refuse_writing_inputs([("--out", path) for path in targets],
                          [("the events file", args.events), ("the --model", args.model)])
    for path in targets:
        if os.path.lexists(path) and not args.overwrite:  # a link counts, even a broken one
            raise OutputError(f"{path} exists (use --overwrite)")
    times = []
    written = []  # this run's frames: removed again if it does not finish (a full disk, Ctrl-C), as in video mode
    try:
        for t0, path in zip(starts, targets, strict=True):
            if camera:
                if t0 + window > duration + 1e-6:
                    raise InputError(f"the window {seconds_text(t0)} s + {window:g} s runs past the end of the "
                                     f"recording ({seconds_text(duration)} s)")
                counts, used = window_counts(args.events, t0, window, sensor=args.sensor,
                                             csv_columns=args.csv_columns), window
            else:
                counts, used = counts_from_h5(args.events, t_start_s=t0, window_s=window)
            tic = time.perf_counter()
            image = rec.predict(counts, used)
            ms = 1000 * (time.perf_counter() - tic)
            times.append(ms)
            write_png(path, image)
            written.append(path)
            log.info("%s: window %.6g s from %s s, %d events, %dx%d -> %dx%d in %.0f ms", path, used,
                     seconds_text(t0), int(counts.sum()), counts.shape[2], counts.shape[1], image.shape[1],
                     image.shape[0], ms)
    except BaseException:  # the first frames alone would look like a finished, shorter series
        for path in written:
            path.unlink(missing_ok=True)
        raise
    if not args.quiet:
        what = targets[0] if len(targets) == 1 else f"{len(targets)} frames {targets[0]} ... {targets[-1]}"
        print(f"wrote {what} ({image.shape[1]}x{image.shape[0]}, window {window:g} s, "
              f"U-Net {sum(times) / len(times):.0f} ms per image)")
    return 0


def _warn_mismatch(events, rec) -> None:
    """Warn when the recording's preset or sensor differs from the model's (names both)."""
    from ..errors import EvnoiseError
    from ..reconstruct.infer import recording_mismatch

    try:
        from ..io import read_metadata

        meta = read_metadata(events)
    except (EvnoiseError, OSError, KeyError, ValueError):
        return  # no metadata to compare (other formats, foreign files)
    for message in recording_mismatch(meta, rec.doc):
        log.warning(message)
