"""Issue 16: per-pixel set-up and per-event cost of the renewal tier, the trial tier, counts with mismatch.

    nice -n 10 python benchmarks/bench_speed16.py                       # this checkout
    PYTHONPATH=/tmp/ev_before nice -n 10 python benchmarks/bench_speed16.py --label before
        # the same measurements on an older tree, e.g.
        # ``git archive 1044ad2 evnoise generators | tar -x -C /tmp/ev_before``
    nice -n 10 python benchmarks/bench_speed16.py --only trials,events  # part 2: trial tier, renewal per event

Scene: ``benchmarks/run.py:scene`` at 1280x720 (0.2-18 lux, lam 13-1160 photons per trial),
preset ``evk3-hd``. Each figure is the median of ``--repeats`` runs after one warm-up run
(Numba compilation excluded), with the min-max range. Prints one JSON object per measurement.
The machine these ran on is shared: compare the before/after runs made back to back.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def timed(fn, repeats):
    fn()
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), float(np.min(times)), float(np.max(times)), out


def scene(shape, rng=0, lux_max=18.0):
    # same scene as benchmarks/run.py (copied so that this script runs against an older tree too)
    h, w = shape
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    base = 0.5 + 0.35 * np.sin(7 * x) * np.cos(5 * y)
    r = np.random.default_rng(rng)
    for _ in range(12):
        cx, cy, rad, val = r.uniform(0, w / max(h, w)), r.uniform(0, h / max(h, w)), r.uniform(0.03, 0.15), r.uniform()
        base = np.where((x - cx) ** 2 + (y - cy) ** 2 < rad**2, val, base)
    return 0.2 + (lux_max - 0.2) * np.clip(base, 0, 1)


def emit(label, what, t, **extra):
    rec = {"label": label, "what": what, "median_s": round(t[0], 5), "min_s": round(t[1], 5),
           "max_s": round(t[2], 5), **extra}
    print(json.dumps(rec), flush=True)
    return rec


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", default="this")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--only", default="limit,setup,simulate,stream,mismatch,dataset",
                    help="comma-separated subset of limit,setup,simulate,stream,mismatch,dataset,memory,h5,"
                         "trials,events,writer,sumlimit")
    ap.add_argument("--trial-seconds", type=float, default=2.0, help="simulated seconds of the trial-tier runs")
    ap.add_argument("--event-seconds", type=float, default=30.0, help="simulated seconds of the `events` runs")
    ap.add_argument("--writer-seconds", type=float, default=60.0, help="simulated seconds of the `writer` runs")
    ap.add_argument("--memory-durations", default="10,60,240",
                    help="durations (s) of the peak-memory runs of simulate_events (`--only memory`)")
    ap.add_argument("--sigma", type=float, default=0.03, help="eps_sigma of the mismatch runs")
    args = ap.parse_args(argv)
    import evnoise as ev

    which = set(args.only.split(","))
    params = ev.load_preset("evk3-hd")
    lux = scene((720, 1280))
    n_pix = lux.size
    lam = params.photons_per_trial(lux)
    th = args.threads
    print(json.dumps({"label": args.label, "evnoise": str(Path(ev.__file__).parent), "pixels": n_pix,
                      "lam_range": [float(lam.min()), float(lam.max())]}), flush=True)

    if "limit" in which:
        # a measured limit in the same run: numpy's Generator drawing as many doubles as there are
        # pixels (two per pixel: one uniform for the first gap, one for the polarity)
        g = np.random.default_rng(0)
        t = timed(lambda: g.random(2 * n_pix), args.repeats)
        emit(args.label, "limit: numpy Generator.random, 2 doubles per pixel of 1280x720 (1 thread)", t,
             draws_per_s=2 * n_pix / t[0])
    if "setup" in which:
        t = timed(lambda: ev.event_probability(lam, params.eps_pos, params.bias_pr), args.repeats)
        emit(args.label, "event_probability 1280x720 (uniform eps)", t, us_per_pixel=t[0] / n_pix * 1e6)
    if "simulate" in which:
        for dur in (1.0, 10.0):
            t = timed(lambda: ev.simulate_events(lux, params, dur, rng=1, threads=th), args.repeats)
            n = int(t[3].size)
            emit(args.label, f"simulate_events 1280x720 {dur:g} s, {th} threads", t, events=n,
                 events_per_s=n / t[0])
        t = timed(lambda: ev.sample_counts(lux, params, 1.0, rng=1, threads=th), args.repeats)
        emit(args.label, f"sample_counts 1280x720 1 s, {th} threads", t)
    if "stream" in which:
        stream = ev.NoiseStream(lux.shape, params, rng=3, threads=th)
        state = {"t": 0}

        def step():
            state["t"] += 10_000
            return stream.advance(lux, state["t"])

        t = timed(step, max(5, args.repeats))
        emit(args.label, f"NoiseStream.advance 1280x720 10 ms, {th} threads", t,
             us_per_pixel=t[0] / n_pix * 1e6)
    if "mismatch" in which:
        mism = params.replace(eps_sigma=args.sigma)
        thr = ev.draw_thresholds(lux.shape, mism, rng=2)
        from evnoise.rates import trial_probabilities

        t = timed(lambda: trial_probabilities(lam.ravel(), mism, (thr[0].ravel(), thr[1].ravel())),
                  args.repeats)
        emit(args.label, f"trial_probabilities with mismatch (sigma {args.sigma}) 1280x720", t,
             values_per_s=2 * n_pix / t[0])
        t = timed(lambda: ev.sample_counts(lux, mism, 1.0, rng=1, threads=th), args.repeats)
        emit(args.label, f"sample_counts with mismatch (sigma {args.sigma}) 1280x720 1 s, {th} threads", t)
    if "memory" in which:
        import tracemalloc

        ev.simulate_events(lux, params, 0.1, rng=1, threads=th)  # compile outside the traced runs
        for dur in (float(d) for d in args.memory_durations.split(",")):
            tracemalloc.start()  # NumPy reports its allocations to tracemalloc
            t0 = time.perf_counter()
            out = ev.simulate_events(lux, params, dur, rng=1, threads=th)
            wall = time.perf_counter() - t0
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            emit(args.label, f"simulate_events peak memory 1280x720 {dur:g} s", (wall, wall, wall),
                 events=int(out.size), output_mib=out.nbytes / 2**20, peak_mib=peak / 2**20,
                 peak_over_output=peak / out.nbytes)
            del out
    if "h5" in which:
        import os
        import tempfile
        import zlib
        from concurrent.futures import ThreadPoolExecutor

        from evnoise.io import write_events

        events = ev.simulate_events(lux, params, 10.0, rng=1, threads=th)
        with tempfile.TemporaryDirectory() as tmp:
            for comp in ("gzip", "lzf", None):
                path = os.path.join(tmp, f"events_{comp}.h5")
                t = timed(lambda: write_events(path, events, lux.shape, overwrite=True, compression=comp),
                          args.repeats)
                emit(args.label, f"write_events events.h5 compression={comp}", t, events=int(events.size),
                     events_per_s=events.size / t[0], bytes_per_event=os.path.getsize(path) / events.size)
        # the limit of threaded gzip: zlib level 1 on byte-shuffled 64 Ki-event chunks of each column
        # (what HDF5's shuffle + deflate filters do), 1 and 2 threads (zlib releases the GIL)
        chunks = []
        for name in ("x", "y", "t", "p"):
            col = np.ascontiguousarray(events[name])
            for lo in range(0, col.size, 1 << 16):
                part = col[lo:lo + (1 << 16)]
                chunks.append(part.view(np.uint8).reshape(-1, part.itemsize).T.copy().tobytes())
        for workers in (1, 2):
            with ThreadPoolExecutor(workers) as pool:
                t = timed(lambda: list(pool.map(lambda b: zlib.compress(b, 1), chunks)), args.repeats)
            emit(args.label, f"limit: zlib level 1 on shuffled chunks, {workers} thread(s)", t,
                 events_per_s=events.size / t[0])
    if "writer" in which:
        _bench_writer(ev, args, params, lux)
    if "sumlimit" in which:
        _bench_sum_limit(args, params)
    if "trials" in which:
        _bench_trials(ev, args, params, lux, th)
    if "events" in which:
        _bench_events(ev, args, params, lux, th)
    if "dataset" in which:
        sys.path.insert(0, str(Path(ev.__file__).parent.parent))
        from evnoise.generators.config import PairConfig
        from evnoise.generators.pairs import CountSampler

        codes = np.minimum((lux / 18.0 * 16383).astype(np.int64), 16383)
        for sigma in (0.0, args.sigma):
            cfg = PairConfig(params=params.replace(eps_sigma=sigma), binning=2)
            sampler = CountSampler(cfg, threads=th)
            seeds = iter(range(10**6))
            t = timed(lambda: sampler.sample(codes, 1_000_000, next(seeds)), args.repeats)
            emit(args.label, f"make-dataset sampler (1280x720, bin 2, 1 s window), eps_sigma {sigma}", t,
                 pairs_per_s=1.0 / t[0], sampler=sampler.method)
    return 0


def _bare_kernels():
    """Bare Numba loops drawing the random numbers of each tier from evnoise's own per-pixel streams:
    the measured limit beside the tiers (no state, no output, no branching on the model)."""
    from evnoise._kernels._jit import kernel
    from evnoise._kernels.rng import geometric, poisson, uniform

    @kernel
    def per_trial(states, lam, n_trials):  # the per-trial algorithm: two Poisson draws per pixel-trial
        acc = 0.0
        for k in range(states.shape[0]):
            s = states[k]
            for _ in range(n_trials):
                acc += poisson(s, lam[k]) - poisson(s, lam[k])
        return acc

    @kernel
    def per_event(states, log1m_p, n_events):  # a geometric gap and two uniforms (time, polarity) per event
        acc = 0.0
        for k in range(states.shape[0]):
            s = states[k]
            for _ in range(n_events):
                acc += geometric(s, log1m_p) + uniform(s) + uniform(s)
        return acc

    return per_trial, per_event


def _bench_trials(ev, args, params, lux, th):
    """Trial tier: a static scene forced through it (method="trials") and a video with a moving disk."""
    import evnoise.simulate as es

    n_pix = lux.size
    dur = args.trial_seconds
    n_trials = math.ceil(dur * params.trial_rate_hz)
    modes = [("jump over static pixels", True), ("per-trial reference", False)]
    if not hasattr(es, "TRIAL_FAST_STATIC"):
        modes = [("per-trial (old code)", None)]
    # video: a bright disk (radius 60 px) crossing the scene in 2 s at 30 frames/s
    h, w = lux.shape
    yy, xx = np.mgrid[0:h, 0:w]
    times = np.arange(61) / 30.0
    frames = np.stack([np.where((xx - 100 - 1000 * t / 2.0) ** 2 + (yy - 360) ** 2 < 60**2, 40.0, lux)
                       for t in times])
    moving = int((frames != frames[0]).any(axis=0).sum())
    v_trials = math.ceil(times[-1] * params.trial_rate_hz)
    for name, fast in modes:
        if fast is not None:
            es.TRIAL_FAST_STATIC = fast
        t = timed(lambda: ev.simulate_events(lux, params, dur, rng=1, method="trials", threads=th), args.repeats)
        emit(args.label, f"trial tier, static 1280x720 {dur:g} s (method=trials), {name}, {th} threads", t,
             events=int(t[3].size), pixel_trials_per_s=n_pix * n_trials / t[0])
        t = timed(lambda: ev.simulate_video(frames, times, params, rng=1, method="trials", threads=th),
                  args.repeats)
        emit(args.label, f"trial tier, video 1280x720 2 s, moving disk ({moving} pixels change), {name}, "
             f"{th} threads", t, events=int(t[3].size), pixel_trials_per_s=n_pix * v_trials / t[0])
    if hasattr(es, "TRIAL_FAST_STATIC"):
        es.TRIAL_FAST_STATIC = True
    per_trial, per_event = _bare_kernels()
    from evnoise._kernels.rng import seed_state

    states = np.empty((n_pix, 4), dtype=np.uint64)
    key = np.arange(1, 5, dtype=np.uint64)
    for i in range(0, n_pix, 97):
        seed_state(key, i, states[i])
    lam = params.photons_per_trial(lux).ravel()
    t = timed(lambda: per_trial(states, lam, 4), args.repeats)
    emit(args.label, "limit: bare Numba loop, 2 Poisson draws per pixel-trial at the scene's lam (1 thread)", t,
         pixel_trials_per_s=4 * n_pix / t[0])
    t = timed(lambda: per_event(states, -1e-3, 8), args.repeats)
    emit(args.label, "limit: bare Numba loop, geometric gap + 2 uniforms per event (1 thread)", t,
         events_per_s=8 * n_pix / t[0])


def _bench_sum_limit(args, params):
    """The floor of any exact, term-by-term evaluation of p: a bare loop of the sum's terms
    ``pmf(m) P(N > m + floor(c (m + b)))`` from precomputed tables (no bounds, no stopping rule), per term,
    and the terms the exact sum keeps (about 12 sqrt(lam): +-6 standard deviations of its summand)."""
    from evnoise._kernels._jit import kernel

    @kernel
    def bare_sum(pmf, sf, c, b, m0, n_terms):
        total = 0.0
        for i in range(c.shape[0]):
            ci = c[i]
            acc = 0.0
            for m in range(m0, m0 + n_terms):
                acc += pmf[m] * sf[m + int(math.floor(ci * (m + b)))]
            total += acc
        return total

    lam, n_terms = 1000.0, 380
    from scipy import stats

    grid = np.arange(4 * int(lam) + 4000)
    pmf = stats.poisson.pmf(grid, lam)
    sf = stats.poisson.sf(grid, lam)
    c = np.expm1(np.random.default_rng(0).normal(params.eps_pos, 0.03, 100_000))
    m0 = int(lam - n_terms // 2)
    t = timed(lambda: bare_sum(pmf, sf, c, params.bias_pr, m0, n_terms), args.repeats)
    per_term = t[0] / (c.size * n_terms)
    emit(args.label, "limit: bare exact-sum loop from tables, per term (1 thread)", t, ns_per_term=per_term * 1e9,
         us_per_value_at_lam_1e3=per_term * 12 * math.sqrt(1e3) * 1e6,
         us_per_value_at_lam_1e5=per_term * 12 * math.sqrt(1e5) * 1e6)


def _bench_writer(ev, args, params, lux):
    """End to end into events.h5 as `evnoise simulate` does it: `iter_events` windows into an `EventWriter`."""
    import os
    import tempfile

    def run(path, compression):
        n = 0
        with ev.EventWriter(path, lux.shape, overwrite=True, compression=compression) as writer:
            for window in ev.iter_events(lux, params, args.writer_seconds, rng=1):
                writer.write(window)
                n += window.size
        return n

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "events.h5")
        for comp in ("gzip", "lzf", None):
            t = timed(lambda: run(path, comp), args.repeats)
            emit(args.label, f"iter_events into EventWriter, 1280x720 {args.writer_seconds:g} s, compression={comp}",
                 t, events=int(t[3]), events_per_s=t[3] / t[0], mb=os.path.getsize(path) / 1e6)


def _bench_events(ev, args, params, lux, th):
    """Renewal tier on a long static run: events/s end to end (set-up, kernels and sorting included)."""
    dur = args.event_seconds
    for threads in sorted({1, th}):
        t = timed(lambda: ev.simulate_events(lux, params, dur, rng=1, threads=threads), args.repeats)
        emit(args.label, f"renewal tier simulate_events 1280x720 {dur:g} s, {threads} thread(s)", t,
             events=int(t[3].size), events_per_s=t[3].size / t[0])


if __name__ == "__main__":
    raise SystemExit(main())
