"""Background video: reconstruct the static background of a recording over time (one PNG per step).

The layer above :mod:`evnoise.motion` (core, no torch): the moving windows and motion masks come
from there, the reconstructor from :mod:`evnoise.reconstruct.infer`. ``evnoise.reconstruct_video``
and ``evnoise.reconstruct.reconstruct_video`` name the function here (``evnoise.motion`` no longer
does: the core may not import the layer above it).
"""

from __future__ import annotations

import contextlib
import csv
import logging
from pathlib import Path

import numpy as np

from .._atomic import atomic_output
from .._checks import check_float, check_int
from ..errors import InputError, OutputError, ParameterError
from ..motion import BackgroundHold, MaskParams, bin_mask, bin_rates, iter_motion, overlay_rgb

__all__ = ["reconstruct_video"]


def _write_rgb_png(path: Path, rgb: np.ndarray) -> None:
    from PIL import Image

    with atomic_output(path, what="PNG file") as tmp:
        Image.fromarray(rgb, mode="RGB").save(tmp, format="PNG")


# --------------------------------------------------------------------------------------
# video
# --------------------------------------------------------------------------------------
def reconstruct_video(events_h5, model_path, out_dir, *, fps: float, window_s: float | None = None,
                      separator="density", mask: MaskParams | None = None, count: str = "noise",
                      on_motion: str = "skip", min_exposure_s: float | None = None, binning: int | None = None,
                      t_start_s: float | None = None, t_end_s: float | None = None, max_frames: int | None = None,
                      sensor=None, csv_columns=None,
                      overlay: bool = True, overwrite: bool = False, threads: int | None = None,
                      progress: bool = True) -> dict:
    """Reconstruct the static background of a recording over time, one PNG per step.

    Parameters
    ----------
    events_h5 : path
        Recording (streamed block by block): events.h5 or any camera file :mod:`evnoise.readers` opens.
    model_path : path
        Reconstructor checkpoint (``evnoise train``).
    out_dir : path
        Folder for the frames (created if its parent exists): ``frame_00000.png`` (8-bit
        grayscale background at the model's binned resolution), ``overlay_00000.png`` (RGB: the
        motion mask tinted red, this step's signal events in yellow/cyan) and ``frames.csv``
        (index, end time, masked and refreshed fractions, event counts of each frame).
    fps : float
        Frames per second (the step is ``1 / fps``).
    window_s : float, optional
        Count window in seconds (default: the model's training window), rounded to whole steps.
    separator : DensityFilter, ActivityFilter, "density", "activity" or None
        Signal/noise separator (:mod:`evnoise.separation`).
    mask : MaskParams, optional
        Motion-mask settings.
    count : {"noise", "all"}
        What the moving window counts at unmasked pixels (see :data:`COUNT_MODES`).
    on_motion : {"skip", "restart"}
        What a masked step does to a pixel's window (see :data:`ON_MOTION`).
    min_exposure_s : float, optional
        Motion-free time after which a pixel's estimate is refreshed (default: the window).
    binning : int, optional
        Check that the model uses this binning (a guard; a mismatch is a ParameterError).
    t_start_s, t_end_s : float, optional
        Time span in seconds on the recording's clock (default: all of it; see :func:`iter_motion`).
    max_frames : int, optional
        Stop after this many frames.
    sensor : str or (int, int), optional
        Sensor size ``"WxH"`` for a recording whose header has none.
    csv_columns : str, optional
        Column order of a CSV recording (e.g. ``"x,y,p,t"``).
    overlay : bool
        Also write the overlay PNGs.
    overwrite : bool
        Replace frames already in ``out_dir`` (its ``frame_*.png``, ``overlay_*.png`` and
        ``frames.csv`` are deleted first, once every check has passed).
    threads : int, optional
        Torch CPU threads.
    progress : bool
        Show a progress bar.

    Returns
    -------
    dict
        ``n_frames``, ``out_dir``, ``fps``, ``step_s``, ``window_s``, ``first_t_s``, ``last_t_s``,
        ``mean_masked``, ``n_events``, ``signal_fraction``.

    Notes
    -----
    Frames start at the first step where a whole window has elapsed since ``t_start_s``. See
    the module docstring for how masked pixels are shown (the last static estimate).
    """
    from .._clock import seconds_text
    from .._recordings import recording_info, recording_start_us
    from ..readers import parse_sensor
    from .imaging import write_png
    from .infer import Reconstructor, check_frame_plan, short_window_note

    fps = check_float(fps, "fps", "frames per second")
    if max_frames is not None:
        max_frames = check_int(max_frames, "max_frames", 1, 2**62, "frames")
    out_dir = Path(out_dir)
    parent = out_dir.parent if str(out_dir.parent) else Path(".")
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"output folder {out_dir} is a file")
    if not out_dir.exists() and not parent.is_dir():
        raise OutputError(f"cannot create output folder {out_dir}: {parent} does not exist")
    if out_dir.is_dir() and not overwrite and (any(out_dir.glob("frame_*.png")) or any(out_dir.glob("overlay_*.png"))):
        raise OutputError(f"{out_dir} already holds frames; pass overwrite=True to replace them")
    shape, n, t_first, t_last, t_file_end = recording_info(events_h5, parse_sensor(sensor),
                                                           csv_columns=csv_columns)  # input errors before the model
    if n == 0:
        raise InputError(f"{events_h5} has no events: nothing to reconstruct")
    rec = Reconstructor(model_path, threads=threads)
    if binning is not None and binning != rec.binning:
        raise ParameterError(f"the model was trained on {rec.binning}x{rec.binning}-binned counts; "
                             f"binning {binning} does not match")
    if shape[0] < rec.binning or shape[1] < rec.binning:
        raise InputError(f"the sensor ({shape[1]}x{shape[0]}) is smaller than the model's "
                         f"{rec.binning}x{rec.binning} bins")
    if window_s is None:
        window_s = rec.spec.window_s
        if window_s is None:
            raise ParameterError("the model does not record its training window: give window_s=")
    window_s = check_float(window_s, "window_s", "seconds")
    note = short_window_note(rec.spec, window_s)
    if note:  # the frames are still made (counts scaled to the model's window), but the user must know
        logging.getLogger("evnoise").warning(note)
    step_us = int(round(1e6 / fps))
    window_steps = max(1, int(round(window_s * 1e6 / step_us)))
    if t_start_s is None:
        t_start_us = recording_start_us(events_h5, t_first)
    else:
        t_start_us = int(round(check_float(t_start_s, "t_start_s", "seconds", strict=False) * 1e6))
    if t_end_s is None:
        t_end_us = max(t_file_end or 0, t_last + 1)
    else:
        t_end_us = int(round(check_float(t_end_s, "t_end_s", "seconds") * 1e6))
    n_steps = (t_end_us - t_start_us) // step_us
    n_out = n_steps - window_steps + 1
    if n_out < 1:
        raise InputError(f"the recording ({(t_end_us - t_start_us) * 1e-6:.3g} s from t_start) is shorter than one "
                         f"window of {window_steps * step_us * 1e-6:.3g} s")
    if max_frames is not None:
        if n_out < max_frames:  # e.g. a 2 s recording and the model's 2 s window: 1 frame, not the 3 asked
            logging.getLogger("evnoise").warning(
                "only %d of the %d frames asked fit: each frame counts a whole window of %.6g s and the recording "
                "holds %.6g s from its start (a shorter window_s= gives more frames)", n_out, max_frames,
                window_steps * step_us * 1e-6, (t_end_us - t_start_us) * 1e-6)
        n_out = min(n_out, max_frames)
    span = f"t = {seconds_text(t_start_us * 1e-6)} s to {seconds_text(t_end_us * 1e-6)} s"
    check_frame_plan(n_out, n_steps=n_out + window_steps - 1,
                     hint=f"the recording runs from {span}: give fewer frames (max_frames=), a later t_start_s= "
                     f"or a lower fps= ({fps:g} per second)")
    created = not out_dir.exists()
    out_dir.mkdir(exist_ok=True)
    if overwrite:  # no stale frames of an earlier, longer run
        for old in [*out_dir.glob("frame_*.png"), *out_dir.glob("overlay_*.png"), out_dir / "frames.csv"]:
            old.unlink(missing_ok=True)
    hold = BackgroundHold(shape, min_exposure_s=window_steps * step_us * 1e-6 if min_exposure_s is None
                          else check_float(min_exposure_s, "min_exposure_s", "seconds"))
    stats: dict = {}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_out, desc="reconstruct", unit="frame", leave=False)
    rows = []
    written = 0
    masked = []
    paths = []  # this run's files: removed again if it does not finish (frames.csv marks a finished folder)
    try:
        frames = iter_motion(events_h5, shape, fps=fps, window_s=window_s, separator=separator, mask=mask, count=count,
                             on_motion=on_motion, t_start_s=t_start_us * 1e-6, t_end_s=t_end_us * 1e-6, stats=stats,
                             csv_columns=csv_columns)
        for frame in frames:
            rates = hold.update(frame)
            if frame.index < window_steps - 1:
                continue
            image = rec.predict_binned(bin_rates(rates, rec.binning) * frame.window_s, frame.window_s)
            name = f"{written:05d}.png"
            paths.append(out_dir / f"frame_{name}")
            write_png(paths[-1], image)
            if overlay:
                rgb = overlay_rgb(image, bin_mask(frame.mask, rec.binning)[:image.shape[0], :image.shape[1]],
                                  bin_rates(frame.signal, rec.binning)[:, :image.shape[0], :image.shape[1]])
                paths.append(out_dir / f"overlay_{name}")
                _write_rgb_png(paths[-1], rgb)
            masked.append(float(frame.mask.mean()))
            rows.append((written, frame.index, f"{frame.t_end_us * 1e-6:.6f}", f"{masked[-1]:.4f}",
                         f"{float(frame.full.mean()):.4f}", frame.n_noise, frame.n_signal))
            written += 1
            if bar is not None:
                bar.update(1)
            if written >= n_out:
                break
        if written == 0:
            raise InputError("no frame could be made: the recording is shorter than one window")
        with atomic_output(out_dir / "frames.csv", what="frames table") as tmp:
            with open(tmp, "w", newline="", encoding="utf-8") as fh:
                w = csv.writer(fh)
                w.writerow(["frame", "step", "t_end_s", "masked_fraction", "full_window_fraction",
                            "noise_events_in_step", "signal_events_in_step"])
                w.writerows(rows)
    except BaseException:  # an error, a full disk, Ctrl-C: no folder of frames that looks finished
        for path in paths:
            path.unlink(missing_ok=True)
        if created:
            with contextlib.suppress(OSError):
                out_dir.rmdir()  # only if empty
        raise
    finally:
        if bar is not None:
            bar.close()
    step_s = step_us * 1e-6
    return {
        "n_frames": written,
        "out_dir": out_dir,
        "fps": fps,
        "step_s": step_s,
        "window_s": window_steps * step_s,
        "first_t_s": float(rows[0][2]),
        "last_t_s": float(rows[-1][2]),
        "mean_masked": float(np.mean(masked)),
        "n_events": stats.get("n_events", 0),
        "signal_fraction": stats.get("n_signal", 0) / max(stats.get("n_events", 0), 1),
    }
