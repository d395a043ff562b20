"""Add evnoise's photon noise to the clean events of an ESIM/v2e-style frame emulator.

Run ``python -m evnoise.examples.add_noise_to_esim [--out noisy.h5]``.

Event simulators such as ESIM or v2e step through video frames and emit an event whenever a
pixel's log intensity has moved by a contrast threshold since its last event - a clean,
noise-free stream. :class:`evnoise.NoiseStream` keeps per-pixel noise state between frames
and returns the photon-noise events of each frame interval; :func:`evnoise.merge_events`
interleaves the two sorted streams. The same works with the ``N x 4`` ``[t, x, y, p]`` arrays
those tools exchange (:func:`evnoise.events_from_array` / :func:`evnoise.events_to_array`).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

import evnoise as ev


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


def clean_events_from_frames(frames, times_s, threshold=0.3, floor=1e-3):
    """A minimal ESIM/v2e-style emulator: log-intensity threshold crossings between frames.

    Every pixel keeps a reference log intensity; whenever the frame's log intensity has moved
    ``k`` whole thresholds from it, ``k`` events are emitted at times interpolated linearly
    between the two frames and the reference moves by ``k`` thresholds. No noise at all.
    Returns an ``N x 4`` float array ``[t_us, x, y, p]`` sorted by time (p = +1 / -1), the
    format such tools use.
    """
    log_i = np.log(np.asarray(frames, dtype=np.float64) + floor)
    ref = log_i[0].copy()
    rows = []
    for k in range(1, len(frames)):
        prev, cur = log_i[k - 1], log_i[k]
        delta = cur - ref
        n = np.floor(np.abs(delta) / threshold).astype(np.int64)
        ys, xs = np.nonzero(n)
        for yy, xx in zip(ys, xs):
            sign = 1.0 if delta[yy, xx] > 0 else -1.0
            for i in range(1, n[yy, xx] + 1):
                level = ref[yy, xx] + sign * i * threshold
                span = cur[yy, xx] - prev[yy, xx]
                frac = 0.0 if span == 0 else np.clip((level - prev[yy, xx]) / span, 0.0, 1.0)
                t = times_s[k - 1] + frac * (times_s[k] - times_s[k - 1])
                rows.append((t * 1e6, xx, yy, sign))
            ref[yy, xx] += sign * n[yy, xx] * threshold
    out = np.array(rows, dtype=np.float64).reshape(-1, 4)
    return out[np.argsort(out[:, 0], kind="stable")]


def add_noise(clean_n4, frames, times_s, params, rng=0):
    """Merge photon-noise events into a clean ``N x 4`` stream, frame interval by frame interval."""
    clean = ev.events_from_array(clean_n4)
    stream = ev.NoiseStream(frames.shape[1:], params, rng=rng, t_start_us=int(round(times_s[0] * 1e6)))
    noise = []
    for k in range(len(frames) - 1):
        # the host simulator's loop: illuminance of this interval, then the interval's noise
        noise.append(stream.advance(frames[k], int(round(times_s[k + 1] * 1e6))))
    noise = np.concatenate(noise)
    return ev.merge_events(clean, noise), clean, noise


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", help="write the noisy stream to this events.h5")
    parser.add_argument("--preset", default="evk3-hd")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    params = ev.load_preset(args.preset)
    frames, times = moving_disc_frames()
    clean_n4 = clean_events_from_frames(frames, times)
    noisy, clean, noise = add_noise(clean_n4, frames, times, params, rng=args.seed)
    noisy_n4 = ev.events_to_array(noisy)  # back to the N x 4 [t, x, y, p] convention
    print(f"clean events from the frame emulator: {clean.size:,}")
    print(f"photon-noise events added by evnoise: {noise.size:,} "
          f"({noise.size / (frames[0].size * (times[-1] - times[0])):.2f} per pixel per second)")
    print(f"merged stream: {noisy.size:,} events, sorted: {bool(np.all(np.diff(noisy_n4[:, 0]) >= 0))}")
    if args.out:
        from evnoise.io import write_events

        write_events(args.out, noisy, frames.shape[1:], {"params": params, "seed": args.seed,
                                                          "source": "evnoise.examples.add_noise_to_esim"},
                     overwrite=True)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
