"""Windows of a static scene (issue 33): windows of about 1 M events against windows of at least
``evnoise.simulate.EVENTS_PER_PIXEL_PER_WINDOW`` events per pixel, on the v2e job's scene.

    python benchmarks/bench_windows.py [--repeats 3] [--lux 2 --lux 300] [--duration 1 --duration 4 --duration 16]
        [--baseline-tree DIR --baseline-label TEXT] [--env-row NAME=VALUE ...] [--no-report]

Every window advances every pixel (a pass over the pixels' state, ~30 ns a pixel on one core here), so a
1280x720 scene in windows of 1 M events pays that pass once per million events. Each row runs
``evnoise.simulate_events`` on a flat 1280x720 field (preset ``evk3-hd``) under both rules (the earlier one is
``EVENTS_PER_PIXEL_PER_WINDOW = 0``): *in one process*, after a warm-up run, median (min-max) of ``--repeats``
runs; and *first call of a fresh process* (as ``evnoise simulate`` and the v2e benchmark run it), median of
``--repeats`` processes, each timing its first full-size call after a tiny one that loads the kernels. The error
column: whether both rules give the same events, bit for bit (SHA-256 of the event arrays), which the output must.
The first-touch row times a process's first and second writing of a fresh array of the size of the longest run's
output (the machine's cost of memory a process has not used before, which a fresh process's long run pays).
``--baseline-tree DIR`` adds rows for the code in ``DIR`` (another checkout, imported through ``PYTHONPATH`` in
child processes that run in an empty folder) with its own default windows, timed the same way. ``--env-row
NAME=VALUE`` (repeatable) adds rows for this code with that environment variable set, both columns timed in child
processes (e.g. ``NUMPY_MADVISE_HUGEPAGE=0``: NumPy's arrays in ordinary pages instead of transparent huge pages),
and a first-touch figure with it.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _report import cpu_name, replace_section  # noqa: E402

TITLE = "## Windows of a static scene (issue 33)"
SHAPE = (720, 1280)
PRESET = "evk3-hd"
RULES = {"this code, windows of ~1 M events": 0, "this code": None}  # EVENTS_PER_PIXEL_PER_WINDOW (None: as shipped)


def _set_rule(per_pixel):
    from evnoise import simulate

    if per_pixel is not None:
        simulate.EVENTS_PER_PIXEL_PER_WINDOW = per_pixel


def _run(lux, duration_s, params):
    import evnoise as ev

    return ev.simulate_events(np.full(SHAPE, lux), params, duration_s, rng=1)


def child(lux, duration_s, per_pixel) -> dict:
    """One fresh process: its first full-size call, timed."""
    import evnoise as ev

    params = ev.load_preset(PRESET)
    ev.simulate_events(np.full((8, 8), lux), params, 0.01, rng=1)  # loads the kernels
    _set_rule(per_pixel)
    t0 = time.perf_counter()
    events = _run(lux, duration_s, params)
    return {"s": time.perf_counter() - t0, "events": int(events.size)}


def in_process(lux, duration_s, per_pixel, repeats):
    import evnoise as ev
    from evnoise import simulate

    params = ev.load_preset(PRESET)
    before = simulate.EVENTS_PER_PIXEL_PER_WINDOW
    _set_rule(per_pixel)
    try:
        windows = list(ev.iter_events(np.full(SHAPE, lux), params, duration_s, rng=1))
        digest = hashlib.sha256(b"".join(np.ascontiguousarray(w).tobytes() for w in windows)).hexdigest()
        times = []
        for _ in range(repeats + 1):  # the first is a warm-up
            t0 = time.perf_counter()
            events = _run(lux, duration_s, params)
            times.append(time.perf_counter() - t0)
            n = int(events.size)
            del events
    finally:
        simulate.EVENTS_PER_PIXEL_PER_WINDOW = before
    return {"windows": len(windows), "digest": digest, "events": n, "times": times[1:]}


def _child(args, tree, env_extra=None):
    """The JSON a child process of this script prints, the code of ``tree`` (None: this one) imported, with the
    environment variables ``env_extra`` set."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | (env_extra or {})
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    with tempfile.TemporaryDirectory() as cwd:  # an empty folder: evnoise comes from PYTHONPATH or the install
        done = subprocess.run([sys.executable, str(Path(__file__).resolve()), *args], capture_output=True,
                              text=True, check=True, env=env, cwd=cwd)
    return json.loads(done.stdout.strip().splitlines()[-1])


def fresh(lux, duration_s, per_pixel, repeats, tree=None, env_extra=None):
    arg = "default" if per_pixel is None else str(per_pixel)
    return [_child(["--child", f"{lux}", f"{duration_s}", arg], tree, env_extra)["s"] for _ in range(repeats)]


def first_touch(n_bytes, env_extra=None):
    """Seconds to write every page of a fresh array of ``n_bytes``, the first and the second time in a process."""
    code = ("import numpy as np, time, json\nout = []\nfor _ in range(2):\n"
            f"    t = time.perf_counter(); a = np.empty({n_bytes}, np.uint8); a[::4096] = 0\n"
            "    out.append(time.perf_counter() - t); del a\nprint(json.dumps(out))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          env=os.environ | (env_extra or {}))
    return json.loads(done.stdout)


def _env_label(env):
    return " ".join(f"{k}={v}" for k, v in env.items())


def fmt(times):
    return f"{statistics.median(times):.3f} ({min(times):.3f}–{max(times):.3f})"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--child-in-process", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--baseline-tree", type=Path, default=None, help="another checkout, timed beside this code")
    ap.add_argument("--baseline-label", default="baseline", help="what the baseline tree is, for the report")
    ap.add_argument("--env-row", action="append", default=[], metavar="NAME=VALUE",
                    help="rows for this code with an environment variable set (repeatable)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--lux", type=float, action="append", default=None, help="illuminance (repeatable; default 2)")
    ap.add_argument("--duration", type=float, action="append", default=None, help="simulated seconds (repeatable)")
    ap.add_argument("--report", type=Path, default=HERE / "REPORT.md")
    ap.add_argument("--no-report", action="store_true")
    args = ap.parse_args(argv)
    if args.child:
        lux, duration_s, rule = args.child
        print(json.dumps(child(float(lux), float(duration_s), None if rule == "default" else int(rule))))
        return 0
    if args.child_in_process:
        lux, duration_s, repeats = args.child_in_process
        print(json.dumps(in_process(float(lux), float(duration_s), None, int(repeats))))
        return 0
    import numba

    import evnoise as ev
    from evnoise import simulate
    from evnoise.events import EVENT_DTYPE

    env_rows = [dict([item.split("=", 1)]) for item in args.env_row]
    durations = args.duration or [1.0, 4.0, 16.0]
    luxes = args.lux or [2.0]
    load0 = os.getloadavg()
    rows, digests = [], {}
    for lux in luxes:
        for d in durations:
            runs = [(label, in_process(lux, d, per_pixel, args.repeats), fresh(lux, d, per_pixel, args.repeats))
                    for label, per_pixel in RULES.items()]
            if args.baseline_tree is not None:
                runs.append((args.baseline_label,
                             _child(["--child-in-process", f"{lux}", f"{d}", f"{args.repeats}"], args.baseline_tree),
                             fresh(lux, d, None, args.repeats, args.baseline_tree)))
            for env in env_rows:
                runs.append((f"this code, {_env_label(env)}",
                             _child(["--child-in-process", f"{lux}", f"{d}", f"{args.repeats}"], None, env),
                             fresh(lux, d, None, args.repeats, None, env)))
            for label, r, f in runs:
                digests.setdefault((lux, d), set()).add(r["digest"])
                rows.append((lux, d, label, r, f))
                print(lux, d, label, r["windows"], fmt(r["times"]), fmt(f), flush=True)
    longest = max(row[3]["events"] for row in rows)
    touches = [first_touch(longest * EVENT_DTYPE.itemsize) for _ in range(args.repeats)]
    env_touches = [(env, [first_touch(longest * EVENT_DTYPE.itemsize, env) for _ in range(args.repeats)])
                   for env in env_rows]
    load1 = os.getloadavg()
    lines = [TITLE, "",
             f"Machine: {cpu_name()}, {os.cpu_count()} cores shared with other jobs, {platform.system()}; "
             f"{_dt.date.today()}. evnoise {ev.__version__} (Python {platform.python_version()}, NumPy "
             f"{np.__version__}, Numba {numba.__version__}), every core (Numba's default threads). Command: "
             f"`python benchmarks/bench_windows.py --repeats {args.repeats}"
             + "".join(f" --lux {lux:g}" for lux in luxes) + "".join(f" --duration {d:g}" for d in durations)
             + (f" --baseline-tree DIR --baseline-label '{args.baseline_label}'" if args.baseline_tree else "")
             + "".join(f" --env-row {item}" for item in args.env_row)
             + "`. Load average (1 min): "
             f"{load0[0]:.2f} before, {load1[0]:.2f} after.", "",
             f"Flat 1280x720 field, `{PRESET}`, `simulate_events` (events collected in memory). 'this code': its "
             f"windows, at least {simulate.EVENTS_PER_PIXEL_PER_WINDOW} events per pixel up to "
             f"{simulate.MAX_EVENTS_PER_WINDOW:,} and at most {simulate.MAX_STATIC_WINDOW_US / 1e6:.0f} s; 'windows of "
             f"~1 M events': the same code with windows of about {simulate.TARGET_EVENTS_PER_WINDOW:,} events"
             + (f"; '{args.baseline_label}': the code of `--baseline-tree` with its own windows"
                if args.baseline_tree else "")
             + "".join(f"; 'this code, {_env_label(env)}': this code with that environment variable (both columns "
                       "in child processes)" for env in env_rows)
             + ". Seconds, median (min–max). 'same events': the event arrays of every row of that lux and duration "
             "equal bit for bit.", "",
             "| lux | simulated s | code | windows | events | in one process (s) | ns/event "
             "| fresh process, first call (s) | same events |", "|---|---|---|---|---|---|---|---|---|"]
    for lux, d, label, r, f in rows:
        same = "yes" if len(digests[(lux, d)]) == 1 else "**NO**"
        lines.append(f"| {lux:g} | {d:g} | {label} | {r['windows']} | {r['events']:,} | {fmt(r['times'])} | "
                     f"{statistics.median(r['times']) / r['events'] * 1e9:.0f} | {fmt(f)} | {same} |")
    lines += ["", f"First touch of memory: writing every page of a fresh {longest * EVENT_DTYPE.itemsize / 1e6:.0f} MB "
              f"array (the longest run's output) took {fmt([t[0] for t in touches])} s the first time in a process "
              f"and {fmt([t[1] for t in touches])} s the second ({args.repeats} processes; the machine's cost of "
              "memory a process has not used before, which a fresh process's long run pays for its output and its "
              "windows' buffers; on this virtual machine it has varied from 0.03 to 0.6 s for 256 MB)"
              + "".join(f"; with {_env_label(env)} {fmt([t[0] for t in ts])} s and {fmt([t[1] for t in ts])} s"
                        for env, ts in env_touches) + ".", "",
              "Reading it: in one process (the steady cost, what a long or repeated job pays) fewer windows save "
              "the pixel pass of each window they no longer make (at a low event rate, ~0.1 events per pixel and "
              "second, that pass is most of a window's cost). A fresh process's first call pays besides for "
              "the memory it touches first, and a larger window's buffers (~40 bytes per event, no longer reused "
              "from window to window) are memory it has not used before: where first touches are dear that "
              "column can lose what the pass saves (compare its ranges).", ""]
    text = "\n".join(lines)
    print(text)
    if not args.no_report:
        replace_section(args.report, TITLE, text)
    return 0 if all(len(v) == 1 for v in digests.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
