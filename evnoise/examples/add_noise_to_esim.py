"""Add evnoise's photon noise to the clean events of an ESIM/v2e-style frame emulator.

Run ``python -m evnoise.examples.add_noise_to_esim --out noisy.h5``.

Event simulators such as ESIM or v2e step through video frames and emit an event whenever a
pixel's log intensity has moved by a contrast threshold since its last event: a clean,
noise-free stream. :class:`LogFrameEmulator` is a minimal emulator of that kind with v2e's
interface (``generate_events(frame, t_s)`` returning ``N x 4`` rows ``[t_s, x, y, +-1]`` or
``None``); :class:`evnoise.plugins.frames.EmulatorNoise` wraps it, exactly as
:class:`evnoise.plugins.v2e.PhotonNoise` wraps v2e's ``EventEmulator``, and merges the photon
noise of every frame interval into its rows.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import evnoise as ev
from evnoise.errors import EvnoiseError, OutputError
from evnoise.plugins.frames import EmulatorNoise

SOURCE = "evnoise.examples.add_noise_to_esim"


def moving_disc_frames(shape=(120, 160), n_frames=101, fps=100.0, lux_background=(1.0, 12.0), lux_disc=40.0):
    """A bright disc crossing a static gradient: frames of illuminance in lux and their times in s."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    background = lux_background[0] + (lux_background[1] - lux_background[0]) * x / (w - 1)
    times = np.arange(n_frames) / fps
    frames = []
    for t in times:
        cx = 20 + (w - 40) * t / times[-1]
        disc = (x - cx) ** 2 + (y - h / 2) ** 2 < (h / 6) ** 2
        frames.append(np.where(disc, lux_disc, background))
    return np.array(frames), times


class LogFrameEmulator:
    """A minimal ESIM/v2e-style emulator: log-intensity threshold crossings between frames.

    Every pixel keeps a reference log intensity ``log(I + floor)``; whenever a new frame's log
    intensity has moved ``k`` whole thresholds from it, ``k`` events are emitted at times
    interpolated linearly between the two frames and the reference moves by ``k`` thresholds.
    No noise at all. The interface is v2e's: the first call initialises the references and
    returns ``None``; later calls return the events since the previous frame as ``N x 4``
    float64 rows ``[t_s, x, y, p]`` (``p`` = +1 ON, -1 OFF) sorted by time, or ``None``.
    """

    def __init__(self, threshold=0.3, floor=1e-3):
        self.threshold = float(threshold)
        self.floor = float(floor)
        self.reset()

    def reset(self):
        self._ref = None
        self._prev = None
        self._t_prev = None

    def generate_events(self, new_frame, t_frame):
        log_i = np.log(np.asarray(new_frame, dtype=np.float64) + self.floor)
        if self._ref is None:
            self._ref, self._prev, self._t_prev = log_i.copy(), log_i, float(t_frame)
            return None
        prev, ref, thr = self._prev, self._ref, self.threshold
        t0, t1 = self._t_prev, float(t_frame)
        delta = log_i - ref
        n = np.floor(np.abs(delta) / thr).astype(np.int64)
        ys, xs = np.nonzero(n)
        k = n[ys, xs]
        sign = np.sign(delta[ys, xs])
        # one row per crossing: repeat each pixel k times, crossing index i = 1..k
        idx = np.repeat(np.arange(ys.size), k)
        i = np.arange(idx.size) - np.repeat(np.cumsum(k) - k, k) + 1
        yy, xx, ss = ys[idx], xs[idx], sign[idx]
        level = ref[yy, xx] + ss * i * thr
        span = log_i[yy, xx] - prev[yy, xx]
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(span == 0, 0.0, (level - prev[yy, xx]) / np.where(span == 0, 1.0, span))
        t = t0 + np.clip(frac, 0.0, 1.0) * (t1 - t0)
        ref[ys, xs] += sign * k * thr
        self._prev, self._t_prev = log_i, t1
        if t.size == 0:
            return None
        rows = np.column_stack([t, xx, yy, ss]).astype(np.float64)
        return rows[np.argsort(rows[:, 0], kind="stable")]


def add_noise(frames, times_s, params, rng=0, *, threshold=0.3, progress=False):
    """Drive the emulator through the frames, with and without photon noise.

    Returns ``(noisy, clean, noise_count)``: the noisy and the clean stream as event arrays
    (:data:`evnoise.EVENT_DTYPE`) and the number of noise events added.
    """
    noisy_emulator = EmulatorNoise(LogFrameEmulator(threshold), params, rng=rng)  # frames are lux already
    clean_emulator = LogFrameEmulator(threshold)
    noisy_rows, clean_rows = [], []
    frame_iter = zip(frames, times_s)
    if progress:
        from tqdm.auto import tqdm

        frame_iter = tqdm(frame_iter, total=len(frames), desc="frames", unit="frame", leave=False)
    for frame, t in frame_iter:  # the host simulator's loop, unchanged but for the wrapper
        rows = noisy_emulator.generate_events(frame, t)
        if rows is not None:
            noisy_rows.append(rows)
        rows = clean_emulator.generate_events(frame, t)
        if rows is not None:
            clean_rows.append(rows)

    def to_events(parts):
        arr = np.concatenate(parts) if parts else np.empty((0, 4))
        return ev.events_from_array(arr, time_unit="s")

    return to_events(noisy_rows), to_events(clean_rows), noisy_emulator.noise_count


def build_parser() -> argparse.ArgumentParser:
    """The options (``--out``, ``--overwrite``, ``--preset``, ``--seed`` and the size check are declared once for
    evnoise's command line, :mod:`evnoise.cli._options`, and used here as they are)."""
    from evnoise.cli import _options as opt

    parser = opt.Parser(
        prog="python -m evnoise.examples.add_noise_to_esim",
        description="Add evnoise's photon noise to the clean events of a small ESIM/v2e-style frame "
        "emulator (a bright disc crossing a gradient, by default 160x120 pixels for 1 s at 100 frames/s) and "
        "report the counts; with --out, write the noisy stream to an events.h5 file.",
    )
    opt.add_out(parser, metavar="FILE.h5", help="write the noisy stream to this events.h5 file")
    opt.add_overwrite(parser, help="replace --out if it exists")
    opt.add_preset(parser, help="noise preset name or TOML file (default: %(default)s)")
    opt.add_seed(parser, default=0, help="random seed of the noise (default: %(default)s)")
    parser.add_argument("--size", type=opt.size("--size", minimum=(41, 4), maximum=4096), default="160x120",
                        metavar="WxH", help="sensor size in pixels (default: %(default)s)")
    parser.add_argument("--frames", type=opt.count("--frames", minimum=2), default=101, metavar="N",
                        help="number of frames at 100 frames/s (default: %(default)s, i.e. 1 s)")
    opt.add_quiet(parser, help="no progress bar")
    return parser


def _check_out(out, preset, overwrite) -> Path:
    path = Path(out)
    if path.suffix.lower() not in (".h5", ".hdf5"):
        raise OutputError(f"--out {out}: the output is an events.h5 file; give it the suffix .h5")
    if path.is_dir():
        raise OutputError(f"--out {out} is a directory")
    preset_path = Path(preset)
    if preset_path.is_file() and path.exists() and path.resolve() == preset_path.resolve():
        raise OutputError(f"--out {out} is the --preset input; choose another output file")
    if path.exists() and not overwrite:
        raise OutputError(f"{out} already exists; pass --overwrite to replace it")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise OutputError(f"cannot write {out}: directory {folder} does not exist")
    return path


def main(argv=None) -> int:
    from evnoise.cli._options import ArgumentsError, height_width

    try:
        args = build_parser().parse_args(argv)
    except ArgumentsError as exc:
        print(exc.line(), file=sys.stderr)
        return 2
    try:
        out = _check_out(args.out, args.preset, args.overwrite) if args.out else None
        shape = height_width(args.size)
        params = ev.load_preset(args.preset)
        frames, times = moving_disc_frames(shape, n_frames=args.frames)
        noisy, clean, n_noise = add_noise(frames, times, params, rng=args.seed, progress=not args.quiet)
        print(f"clean events from the frame emulator: {clean.size:,}")
        print(f"photon-noise events added by evnoise: {n_noise:,} "
              f"({n_noise / (frames[0].size * (times[-1] - times[0])):.2f} per pixel per second)")
        print(f"merged stream: {noisy.size:,} events, sorted: {bool(np.all(np.diff(noisy['t']) >= 0))}")
        if out is not None:
            ev.write_events(out, noisy, frames.shape[1:], {"params": params, "seed": args.seed, "source": SOURCE},
                            overwrite=args.overwrite, t_end_us=int(round(times[-1] * 1e6)) + 1)
            print(f"wrote {out}")
    except EvnoiseError as exc:
        print(f"evnoise: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
