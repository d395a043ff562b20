"""Reset memory (issue 32): what it costs beside the memoryless simulator, and its error against the closed form.

    python benchmarks/bench_memory.py [--side 128] [--duration 20] [--out benchmarks/REPORT.md] [--tiny] [--no-large]

Still scenes of ``side x side`` pixels at one light, ``--duration`` seconds, in one process after a warm-up call
(compiled kernels): the memoryless model, ``reset_memory = 0.3`` without and with threshold mismatch and a leak
spread (the davis346 preset: a chain per pixel), with the regular timer (the dvs128 preset, nominal pixels), and
a video (half the pixels changing, trial tier). Columns: *set-up*, the seconds of a 1 ms run (tables, steady
state; the smallest of three); *run*, the seconds of the whole run; *per event*, the marginal cost, the time of
the last three quarters of the run over their events (a run of a quarter of the duration timed too);
the simulated rate per pixel against the closed form (``memory_statistics``; nominal pixels only: the closed form
is the nominal pixel's) as a z-score from the per-pixel spread. Then a 1280 x 720 evk4 scene beyond the table budget
(:func:`run_large`). Shared machines make the timings noisy.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import cpu_name, replace_section  # noqa: E402

TITLE = "## Reset memory: cost and error (issue 32)"
#: fewer extra events than this between the quarter and the whole run: no per-event figure (timing noise)
MIN_MARGINAL_EVENTS = 200_000


def _timed(fn, repeats=1):
    best, out = math.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _configs():
    import evnoise as ev

    davis = ev.load_preset("davis346")
    nominal = davis.replace(eps_sigma=0.0, leak_sigma=0.0)
    dvs = ev.load_preset("dvs128")
    dvs_nominal = dvs.replace(eps_sigma=0.0, leak_sigma=0.0, hot_pixel_fraction=0.0)
    return [
        ("davis346 nominal, memoryless", nominal, 2.0, True),
        ("davis346 nominal, k = 0.3", nominal.replace(reset_memory=0.3), 2.0, True),
        ("davis346 (mismatch, leak spread), memoryless", davis, 2.0, False),
        ("davis346 (mismatch, leak spread), k = 0.3", davis.replace(reset_memory=0.3), 2.0, False),
        ("dvs128 nominal (regular timer), k = 0.3", dvs_nominal.replace(reset_memory=0.3), 0.05, True),
        ("dvs128 (timer, hot pixels, mismatch), k = 0.3", dvs.replace(reset_memory=0.3), 0.05, False),
    ]


def run(side: int, duration_s: float) -> list[dict]:
    import evnoise as ev
    from evnoise.terms import memory

    rows = []
    for name, params, lux_value, nominal in _configs():
        lux = np.full((side, side), lux_value)
        ev.simulate_events(lux[:4, :4], params, 0.01, rng=0)  # compile
        setup, _ = _timed(lambda: ev.simulate_events(lux, params, 0.001, rng=1), repeats=3)
        quarter, part = _timed(lambda: ev.simulate_events(lux, params, duration_s / 4, rng=2))
        total, events = _timed(lambda: ev.simulate_events(lux, params, duration_s, rng=2))
        per_pixel = np.bincount(events["y"].astype(np.int64) * side + events["x"], minlength=side * side) / duration_s
        extra = events.size - part.size  # the marginal cost: the last three quarters' time over their events
        per_event = (total - quarter) / extra * 1e9 if extra >= MIN_MARGINAL_EVENTS and total > quarter else math.nan
        row = {"name": name, "setup_s": setup, "run_s": total, "events": int(events.size),
               "ns_per_event": per_event, "rate": float(per_pixel.mean())}
        if nominal:
            want = float(memory.memory_statistics(lux_value, params).rate_hz.sum())
            row["closed_form"] = want
            row["z"] = (per_pixel.mean() - want) / (per_pixel.std() / math.sqrt(per_pixel.size))
        rows.append(row)
    # a video: half the pixels change (trial tier), half are still (renewal tier)
    params = ev.load_preset("davis346").replace(eps_sigma=0.0, leak_sigma=0.0)
    frames = np.full((3, side, side), 2.0)
    frames[1:, :, side // 2:] = 4.0
    times = [0.0, 0.1, duration_s / 4]
    for k in (0.0, 0.3):
        p = params.replace(reset_memory=k)
        ev.simulate_video(frames[:, :4, :4], times, p, rng=0)
        total, events = _timed(lambda: ev.simulate_video(frames, times, p, rng=3))
        rows.append({"name": f"video {side}x{side} (half changing, {times[-1]:g} s), k = {k:g}", "setup_s": math.nan,
                     "run_s": total, "events": int(events.size), "ns_per_event": math.nan,
                     "rate": events.size / (side * side) / times[-1]})
    return rows


def run_large(shape, duration_s: float, force: bool = False) -> list[dict]:
    """A scene beyond the table budget (``evnoise.terms.memory.MAX_TABLE_STATES``): evk4 with its threshold mismatch
    at 2 lux, nearly a chain per pixel, which runs trial by trial with each chain's start computed on its own; beside
    it the memoryless renewal and trial tiers. ``force``: lower the budget so that a small (smoke) scene takes that
    path too. Set-up: a 1 ms run (once: it is most of the run)."""
    import evnoise as ev
    from evnoise.terms import memory

    evk4 = ev.load_preset("evk4")
    lux = np.full(shape, 2.0)
    budget = memory.MAX_TABLE_STATES
    if force:
        memory.MAX_TABLE_STATES = 10
    rows = []
    try:
        for name, params, method in [("evk4, memoryless (renewal tier)", evk4, "auto"),
                                     ("evk4, memoryless (trial tier)", evk4, "trials"),
                                     ("evk4, k = 0.3 (trial tier, starts without tables)", evk4.replace(
                                         reset_memory=0.3), "auto")]:
            ev.simulate_events(lux[:4, :4], params, 0.01, rng=0, method=method)  # compile
            setup, _ = _timed(lambda: ev.simulate_events(lux, params, 0.001, rng=1, method=method))
            total, events = _timed(lambda: ev.simulate_events(lux, params, duration_s, rng=2, method=method))
            rows.append({"name": name, "setup_s": setup, "run_s": total, "events": int(events.size),
                         "rate": events.size / lux.size / duration_s})
        # the same scene through NoiseStream (what the v2e and frames plugins drive), 30 intervals per second
        params = evk4.replace(reset_memory=0.3)
        n = max(1, int(round(30 * duration_s)))

        def stream(seed, t_end_s, intervals):
            st = ev.NoiseStream(lux.shape, params, rng=seed)
            return np.concatenate([st.advance(lux, int(round((i + 1) * t_end_s * 1e6 / intervals)))
                                   for i in range(intervals)])

        setup, _ = _timed(lambda: stream(1, 0.001, 1))
        total, events = _timed(lambda: stream(2, duration_s, n))
        rows.append({"name": f"evk4, k = 0.3, NoiseStream in {n} intervals (trial tier, starts without tables)",
                     "setup_s": setup, "run_s": total, "events": int(events.size),
                     "rate": events.size / lux.size / duration_s})
    finally:
        memory.MAX_TABLE_STATES = budget
    return rows


def section(rows, side, duration_s, command, large=(), large_shape=None, large_s=None) -> str:
    import evnoise

    lines = [TITLE, "",
             f"Machine: {cpu_name()}, evnoise {evnoise.__version__}. Command: `{command}`. Still scenes of "
             f"{side}×{side} pixels, {duration_s:g} s (davis346 at 2 lux, dvs128 at 0.05 lux); set-up = a 1 ms run "
             "(the smallest of three); per event = the marginal cost: (run − run of a quarter of the duration) / "
             "their difference in events (–: under 200 000 events apart, timing noise); z = (simulated − closed-form "
             "rate) / its standard error over pixels (nominal pixels only: the closed form is the nominal pixel's). "
             "The video (half the pixels changing: the trial tier) is timed whole.", "",
             "| scene | set-up (s) | run (s) | events | per event (ns) | rate / pixel (events/s) | closed form | z |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cf = f"{r['closed_form']:.4g}" if "closed_form" in r else "–"
        z = f"{r['z']:+.2f}" if "z" in r else "–"
        setup = "–" if math.isnan(r["setup_s"]) else f"{r['setup_s']:.3f}"
        per_event = "–" if math.isnan(r["ns_per_event"]) else f"{r['ns_per_event']:.0f}"
        lines.append(f"| {r['name']} | {setup} | {r['run_s']:.2f} | {r['events']:,} | {per_event} | "
                     f"{r['rate']:.4g} | {cf} | {z} |")
    lines += ["", "Memory adds a stored count per pixel and, per event, the draw of its new state from the state's "
              "tables (the renewal tier) or one more uniform per trial (the trial tier); its set-up builds a chain "
              "per distinct light level, so threshold mismatch or a leak spread (a chain per pixel) costs a few "
              "tenths of a millisecond per pixel at a few photons per trial (above) and 1-3 ms at thousands (the "
              "tables and the iterated steady state: `evnoise.terms.memory.kernel_tables`).", ""]
    if large:
        h, w = large_shape
        lines += [f"**Beyond the table budget** ({w}×{h}, 2 lux, {large_s:g} s; set-up = a 1 ms run, once): with "
                  "`evk4`'s threshold mismatch nearly every pixel is a chain of its own, whose tables would pass "
                  "`MAX_TABLE_STATES` (refused before); the run goes trial by trial, each chain's start computed on "
                  "its own (`evnoise._kernels.memory_start`). Its events are those of the table path's trial tier "
                  "with the same seed (`tests/test_memory_own_start.py`, on scenes small enough for tables), so its "
                  "error is the trial tier's (validated against the closed form in `tests/test_memory_video.py`). "
                  "`NoiseStream` (the v2e and frames plugins) goes the same way, its events `simulate_events`' event "
                  "for event (same test file; through changes of light: `tests/test_memory_term.py`).", "",
                  "| scene | set-up (s) | run (s) | events | rate / pixel (events/s) |", "|---|---|---|---|---|"]
        for r in large:
            lines.append(f"| {r['name']} | {r['setup_s']:.2f} | {r['run_s']:.2f} | {r['events']:,} | "
                         f"{r['rate']:.4g} |")
        lines += ["", "Where the set-up goes (a profile of the full-size run, 2 threads, this machine, 2026-11-27): "
                  "the chains' starts ~12 s (624 186 chains, ~38 µs each on one thread: 40 embedded steps over ~216 "
                  "states, four chains at a time), grouping the pixels into chains (threshold classes) ~3.5 s, the "
                  "chains' rate estimates ~6 s (~20 embedded steps each). Not timed: the same scene with tables "
                  "would need 135 M table states (18 GB) and ~0.45 ms per chain.", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=128)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--out", type=Path, default=None, help="report to write the section into (default: print it)")
    ap.add_argument("--tiny", action="store_true", help="a smoke run (16 x 16, 1 s): the numbers mean nothing")
    ap.add_argument("--no-large", action="store_true", help="leave out the 1280 x 720 scene beyond the table budget")
    args = ap.parse_args(argv)
    side, duration = (16, 1.0) if args.tiny else (args.side, args.duration)
    large_shape, large_s = ((12, 16), 0.5) if args.tiny else ((720, 1280), 1.0)
    command = "python benchmarks/bench_memory.py" + (" --tiny" if args.tiny else
                                                      f" --side {side} --duration {duration:g}")
    rows = run(side, duration)
    large = run_large(large_shape, large_s, force=args.tiny) if not args.no_large else ()
    text = section(rows, side, duration, command, large, large_shape, large_s)
    if args.out is None:
        print(text)
    else:
        replace_section(args.out, TITLE, text)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
