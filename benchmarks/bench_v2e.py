"""Issue 33: evnoise and v2e side by side on a still scene, one fresh process per run.

    python benchmarks/bench_v2e.py --v2e-python PATH [--repeats 3] [--v2e-setting davis@30 ...] [--no-report]

The job: a uniform (flat) 1280x720 scene, 1 s of simulated time, at 0.01, 2 and 300 lux. Each run is a
separate process, its wall time measured from start to exit (imports included, as
``bench_fresh_process.py`` does), its CPU time from the OS's accounting of the child.

* evnoise: ``evnoise.simulate_events(np.full((720, 1280), lux), 'evk3-hd', 1.0)`` with this interpreter;
  the field is the illuminance itself, no image mapping.
* v2e: its ``EventEmulator`` (from https://github.com/SensorsINI/v2e, not on PyPI) run by ``--v2e-python``,
  an interpreter that can import ``v2ecore.emulator``, on CPU, fed the same flat frame ``fps * 1 s + 1``
  times (``t = 0, 1/fps, ..., 1 s``: the first frame sets the pixels up, each later one closes an interval
  whose noise v2e draws once). v2e has no lux: the frame's grey level is ``255 * lux / WHITE_LUX``, the
  convention of ``evnoise.plugins.v2e`` (grey linear in intensity) with the brightest level white.

``--v2e-setting PARAMS@FPS`` (repeatable) picks v2e's noise parameters, ``davis`` (the defaults of v2e's
command line, ``v2ecore/v2e_args.py``, whose help calls them typical of a DAVIS in good light) or
``noisy`` (v2e's ``--dvs_params noisy``), and the frame rate. Each run prints its event count. The runs
take turns (evnoise, then each v2e setting, per repeat), after uncounted runs that fill the caches
(Numba's and evnoise's tables in a temporary folder; v2e's imports). The table goes to stdout and, unless
``--no-report``, into ``REPORT.md`` under ``TITLE``.

Per simulated second. A 1 s job's wall is mostly start-up (imports, set-up of the pixels), which neither tool
pays again for a longer job. So each tool also runs the same job for ``--long-duration`` seconds (default 4 s,
for the settings up to ``--marginal-max-fps``, default 100 fps: v2e at 1000 fps would take minutes per run), and
the *marginal* cost per simulated second is ``(work(long) - work(1 s)) / (long - 1 s)`` (medians), where *work*
is the time each job measures around its own work after its imports (evnoise: the ``simulate_events`` call,
after a tiny one that loads its kernels; v2e:
the emulator made and fed): the processes' start-up varies by more than evnoise's whole marginal cost, so a
difference of walls cannot show it. The ratio of the two tools' marginal costs is the speed-up per simulated
second of a long job.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _report import cpu_name, replace_section  # noqa: E402  (the benchmarks folder, put on the path above)

TITLE = "## v2e side by side (issue 33)"
LUX = (0.01, 2.0, 300.0)
HEIGHT, WIDTH = 720, 1280
DURATION_S = 1.0
PRESET = "evk3-hd"
#: illuminance of v2e's grey level 255 (the brightest level of the job is white)
WHITE_LUX = 300.0
#: the goal of issue 33: evnoise this many times faster per simulated second, at every lux
GOAL = 100.0
DEFAULT_SETTINGS = ("davis@30", "noisy@30", "davis@1000")

#: v2e's noise parameters by name. ``davis``: the defaults of v2e.py's command line (v2ecore/v2e_args.py:
#: leak 0.01 Hz "typical for normal illumination levels with Davis cameras", shot noise 0.001 Hz "default for
#: good lighting"); ``noisy``: what ``--dvs_params noisy`` sets (EventEmulator.set_dvs_params). Options not
#: named keep EventEmulator's defaults (leak_jitter_fraction 0.1, noise_rate_cov_decades 0.1).
V2E_PARAMS = {
    "davis": {"pos_thres": 0.2, "neg_thres": 0.2, "sigma_thres": 0.03, "cutoff_hz": 300.0, "leak_rate_hz": 0.01,
              "shot_noise_rate_hz": 0.001, "refractory_period_s": 0.0005},
    "noisy": {"pos_thres": 0.2, "neg_thres": 0.2, "sigma_thres": 0.05, "cutoff_hz": 30.0, "leak_rate_hz": 0.1,
              "shot_noise_rate_hz": 5.0, "refractory_period_s": 0.0},
}

#: the evnoise run: argv = lux seed height width duration; prints the number of events and the seconds of the
#: work itself (the call, after the imports and a tiny call that loads the kernels and the closed form's table)
EVNOISE_JOB = (
    "import sys, time, numpy as np, evnoise as ev\n"
    "lux, seed, h, w, duration = float(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), "
    "float(sys.argv[5])\n"
    f"ev.simulate_events(np.full((8, 8), lux), {PRESET!r}, 0.01, rng=seed)  # kernels and tables loaded\n"
    "t0 = time.perf_counter()\n"
    f"n = ev.simulate_events(np.full((h, w), lux), {PRESET!r}, duration, rng=seed).size\n"
    "print(n, time.perf_counter() - t0)\n"
)

#: the v2e run: argv = grey fps seed height width duration options-json; prints the number of events and the
#: seconds of the work itself (the emulator made and fed, after the imports)
V2E_JOB = (
    "import json, sys, time\n"
    "import numpy as np\n"
    "from v2ecore.emulator import EventEmulator\n"
    "grey, fps, seed = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])\n"
    "h, w, duration, options = int(sys.argv[4]), int(sys.argv[5]), float(sys.argv[6]), json.loads(sys.argv[7])\n"
    "t0 = time.perf_counter()\n"
    "emulator = EventEmulator(seed=seed, device='cpu', **options)\n"
    "frame = np.full((h, w), grey)\n"
    "count = 0\n"
    "for k in range(int(round(fps * duration)) + 1):\n"
    "    rows = emulator.generate_events(frame, k / fps)\n"
    "    count += 0 if rows is None else len(rows)\n"
    "print(count, time.perf_counter() - t0)\n"
)

#: what every run of each tool pays before any work
EVNOISE_FLOOR = ("import numpy as np, evnoise; from evnoise._kernels.levels import find_levels; "
                 "find_levels(np.zeros(8), 2)")
V2E_FLOOR = "import v2ecore.emulator"


def v2e_problem(python: str | None) -> str | None:
    """Why ``python`` cannot run the v2e job, in one line, or None when it imports ``v2ecore.emulator``.

    Parameters
    ----------
    python : str or None
        The interpreter given as ``--v2e-python``.

    Returns
    -------
    str or None
        The reason, or None.
    """
    hint = "an interpreter that can import v2ecore.emulator (v2e, https://github.com/SensorsINI/v2e)"
    if not python:
        return f"pass --v2e-python PATH, {hint}"
    try:
        proc = subprocess.run([python, "-c", V2E_FLOOR], capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"--v2e-python {python} cannot be run ({exc.__class__.__name__}: {exc}); it must be {hint}"
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["no message"])[-1]
        return f"--v2e-python {python} cannot import v2ecore.emulator ({last}); it must be {hint}"
    return None


def parse_setting(text: str) -> tuple[str, float]:
    """``"davis@30"`` -> ``("davis", 30.0)``: v2e's parameter set and frame rate (Hz).

    Parameters
    ----------
    text : str
        ``PARAMS@FPS`` with PARAMS a key of :data:`V2E_PARAMS` and FPS > 0.

    Returns
    -------
    tuple of (str, float)
    """
    name, _, fps = text.partition("@")
    try:
        rate = float(fps)
    except ValueError:
        rate = float("nan")
    if name not in V2E_PARAMS or not rate > 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected PARAMS@FPS with PARAMS one of "
                                         f"{', '.join(V2E_PARAMS)} and FPS > 0, e.g. davis@30")
    return name, rate


def run_process(cmd: list[str], env: dict, cwd: Path) -> dict:
    """One separate process: wall from start to exit, the child's CPU, what it printed, the load around it.

    Parameters
    ----------
    cmd : list of str
        The command.
    env : dict
        Its environment.
    cwd : Path
        Its working folder.

    Returns
    -------
    dict
        ``wall`` and ``cpu`` (s), ``out`` (stdout), ``load`` (1-minute load averages before and after).

    Raises
    ------
    RuntimeError
        When the process exits non-zero (with the end of its stderr).
    """
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=out, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read().decode(errors="replace"), err.read().decode(errors="replace")
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        raise RuntimeError(f"{shlex.join(cmd[:2])} ... exited with {code}: {stderr.strip()[-2000:]}")
    return {"wall": wall, "cpu": usage.ru_utime + usage.ru_stime, "out": stdout,
            "load": (load_before, os.getloadavg()[0])}


def environment(scratch: Path) -> dict:
    """The children's environment: this one, with Numba's cache and evnoise's table cache in ``scratch``."""
    # PYTHONDONTWRITEBYTECODE dropped: the warm-up runs write the bytecode a warm install has (bench_fresh_process)
    env = {k: v for k, v in os.environ.items() if k not in ("EVNOISE_TABLE_CACHE", "PYTHONDONTWRITEBYTECODE")}
    env.update(NUMBA_CACHE_DIR=str(scratch / "numba"), EVNOISE_CACHE=str(scratch / "tables"), PYTHONHASHSEED="0")
    return env


def jobs(lux: float, settings: list[tuple[str, float]], v2e_python: str, seed: int,
         duration_s: float = DURATION_S, tag: str | None = None) -> dict:
    """The commands of one lux level: ``{"evnoise": cmd, ("davis", 30.0): cmd, ...}`` (keys prefixed by ``tag``
    as ``(tag, key)`` when given: the long runs)."""
    size = [str(HEIGHT), str(WIDTH)]
    out = {"evnoise": [sys.executable, "-c", EVNOISE_JOB, repr(lux), str(seed), *size, repr(duration_s)]}
    grey = 255.0 * lux / WHITE_LUX
    for name, fps in settings:
        out[(name, fps)] = [v2e_python, "-c", V2E_JOB, repr(grey), repr(fps), str(seed + 1), *size,
                            repr(duration_s), json.dumps(V2E_PARAMS[name])]
    return out if tag is None else {(tag, key): cmd for key, cmd in out.items()}


def warm_up(v2e_python: str, env: dict, cwd: Path) -> None:
    """Uncounted runs that fill the caches: evnoise's job (Numba's kernels, evnoise's tables) and v2e's imports
    (the OS's file cache; v2e keeps no cache of its own, so a whole v2e run would add nothing)."""
    for cmd in ([sys.executable, "-c", EVNOISE_JOB, repr(LUX[0]), "0", str(HEIGHT), str(WIDTH), repr(DURATION_S)],
                [v2e_python, "-c", V2E_FLOOR]):
        run_process(cmd, env, cwd)


def time_jobs(commands: dict, repeats: int, env: dict, cwd: Path) -> dict:
    """``repeats`` runs of each command, taking turns (a drift of the machine's speed reaches all alike).

    Returns
    -------
    dict
        Per key of ``commands``: lists ``wall``, ``cpu``, ``events`` and ``load``.
    """
    times = {key: {"wall": [], "cpu": [], "events": [], "work": [], "load": []} for key in commands}
    for _ in range(repeats):
        for key, cmd in commands.items():
            r = run_process(cmd, env, cwd)
            times[key]["wall"].append(r["wall"])
            times[key]["cpu"].append(r["cpu"])
            events, work = r["out"].split()[-2:]
            times[key]["events"].append(int(events))
            times[key]["work"].append(float(work))
            times[key]["load"].extend(r["load"])
            print(f"  {key}: {r['wall']:.2f} s, {times[key]['events'][-1]:,} events, load "
                  f"{r['load'][0]:.2f} -> {r['load'][1]:.2f}", flush=True)
    return times


def floor_times(v2e_python: str, repeats: int, env: dict, cwd: Path) -> dict:
    """Wall and CPU of each tool's start-up alone (imports; evnoise: one cached kernel's first call)."""
    commands = {"evnoise": [sys.executable, "-c", EVNOISE_FLOOR], "v2e": [v2e_python, "-c", V2E_FLOOR]}
    out = {}
    for key, cmd in commands.items():
        run_process(cmd, env, cwd)
        rs = [run_process(cmd, env, cwd) for _ in range(repeats)]
        out[key] = {"wall": [r["wall"] for r in rs], "cpu": [r["cpu"] for r in rs],
                    "load": [x for r in rs for x in r["load"]]}
    return out


def versions(v2e_python: str) -> str:
    """Versions of the v2e interpreter's Python, torch and NumPy, in words."""
    code = ("import platform, numpy, torch; print(f'Python {platform.python_version()}, torch {torch.__version__}, "
            "NumPy {numpy.__version__}')")
    proc = subprocess.run([v2e_python, "-c", code], capture_output=True, text=True, timeout=300)
    return proc.stdout.strip() or "versions unknown"


def _fmt(values) -> str:
    v = np.asarray(values, dtype=float)
    return f"{np.median(v):.2f} ({v.min():.2f}–{v.max():.2f})"


def _load(values) -> str:
    return f"{min(values):.1f}–{max(values):.1f}"


def ratio(v2e: dict, evnoise: dict, stat=np.median) -> float:
    """v2e's wall over evnoise's (``stat`` of each tool's runs): how many times faster evnoise is per simulated
    second. ``np.min`` gives the ratio of the fastest runs, the least touched by other jobs."""
    return float(stat(v2e["wall"]) / stat(evnoise["wall"]))


def table(results: dict, settings: list[tuple[str, float]]) -> str:
    """The markdown table: per v2e setting and lux, both tools' wall, CPU and events, and the ratio."""
    lines = ["| v2e setting | lux | evnoise wall (s) | evnoise CPU (s) | evnoise events | v2e wall (s) | v2e CPU (s) "
             "| v2e events | v2e wall / evnoise wall: medians, fastest runs | load avg (1 min) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for key in settings:
        for lux in LUX:
            ev, v2 = results[lux]["evnoise"], results[lux][key]
            lines.append(
                f"| {key[0]}, {key[1]:g} fps | {lux:g} | {_fmt(ev['wall'])} | {_fmt(ev['cpu'])} | "
                f"{int(np.median(ev['events'])):,} | {_fmt(v2['wall'])} | {_fmt(v2['cpu'])} | "
                f"{int(np.median(v2['events'])):,} | {ratio(v2, ev):.1f}×, {ratio(v2, ev, np.min):.1f}× | "
                f"{_load(ev['load'] + v2['load'])} |")
    return "\n".join(lines)


def marginal(short: dict, long: dict, long_s: float, what: str = "work") -> float:
    """Seconds of ``what`` (the in-process work time) per simulated second beyond the 1 s job: difference of the
    medians over the difference of the durations."""
    return float((np.median(long[what]) - np.median(short[what])) / (long_s - DURATION_S))


def marginal_table(results: dict, settings: list[tuple[str, float]], long_s: float) -> str:
    """Markdown table of the marginal cost per simulated second, per v2e setting (with long runs) and lux."""
    lines = [f"| v2e setting | lux | evnoise work at 1 s, {long_s:g} s | evnoise s per simulated s | "
             f"v2e work at 1 s, {long_s:g} s | v2e s per simulated s | v2e / evnoise per simulated s |",
             "|---|---|---|---|---|---|---|"]
    for key in settings:
        for lux in LUX:
            r = results[lux]
            ev_s, ev_l, v_s, v_l = r["evnoise"], r[("long", "evnoise")], r[key], r[("long", key)]
            ew, vw = marginal(ev_s, ev_l, long_s), marginal(v_s, v_l, long_s)
            ratio_w = f"{vw / ew:.0f}×" if ew > 0 else "not measurable (evnoise's difference ≤ 0)"
            lines.append(f"| {key[0]}, {key[1]:g} fps | {lux:g} | {_fmt(ev_s['work'])}, {_fmt(ev_l['work'])} | "
                         f"{ew:.4f} | {_fmt(v_s['work'])}, {_fmt(v_l['work'])} | {vw:.2f} | {ratio_w} |")
    return "\n".join(lines)


def marginal_verdicts(results: dict, settings: list[tuple[str, float]], long_s: float) -> list[str]:
    """One line per setting with long runs: is the marginal (wall) ratio at least :data:`GOAL` at every lux?"""
    out = []
    for key in settings:
        ratios = {}
        for lux in LUX:
            r = results[lux]
            ew = marginal(r["evnoise"], r[("long", "evnoise")], long_s)
            vw = marginal(r[key], r[("long", key)], long_s)
            ratios[lux] = vw / ew if ew > 0 else float("nan")
        if any(np.isnan(list(ratios.values()))):
            out.append(f"- per simulated second against v2e `{key[0]}` at {key[1]:g} fps: not measurable (evnoise's "
                       "work did not grow with the duration in this run); the goal is **not shown**.")
            continue
        worst = min(ratios, key=ratios.get)
        met = "met" if ratios[worst] >= GOAL else "NOT met"
        out.append(f"- per simulated second against v2e `{key[0]}` at {key[1]:g} fps: smallest ratio "
                   f"{ratios[worst]:.0f}× (at {worst:g} lux); the goal (≥ {GOAL:g}× at every lux) is **{met}**.")
    return out


def verdicts(results: dict, settings: list[tuple[str, float]]) -> list[str]:
    """One line per v2e setting: is evnoise at least :data:`GOAL` times faster at every lux?"""
    out = []
    for key in settings:
        worst = min(LUX, key=lambda lux: ratio(results[lux][key], results[lux]["evnoise"]))
        r = ratio(results[worst][key], results[worst]["evnoise"])
        fastest = min(ratio(results[lux][key], results[lux]["evnoise"], np.min) for lux in LUX)
        met = "met" if r >= GOAL else "NOT met"
        out.append(f"- against v2e `{key[0]}` at {key[1]:g} fps: smallest ratio of medians {r:.1f}× (at {worst:g} "
                   f"lux; of the fastest runs {fastest:.1f}×); the goal (≥ {GOAL:g}× at every lux) is **{met}**.")
    return out


MODELS = """What each tool models (the two noise models differ; the times compare tools, not the same physics):

- **evnoise** (`evk3-hd`): photon shot noise of each pixel from its illuminance through the preset's
  calibrated closed form (photons per lux, dark current, photoreceptor bias, the two thresholds, trials at
  42.5 Hz), simulated exactly in the renewal tier, plus the preset's leak (background) events; microsecond
  timestamps; the event rate depends on lux, not monotonically (of the three levels, most events at 2 lux).
- **v2e** (`EventEmulator`, on CPU, torch): a per-frame pixel model (lin-log of the grey level, a first-order
  photoreceptor low-pass, thresholds with mismatch, refractory period) with noise added per frame interval:
  "shot noise", each pixel at most one event (ON or OFF) per interval, each polarity with probability
  `shot_noise_rate_hz / 2 * dt` scaled from 0.95 at grey 0 down to 0.25 at white (fixed, not calibrated,
  not a function of lux), and leak events from a constant drift of each pixel's memorised level
  (`leak_rate_hz`: over 1 s it adds no event at these rates). Noise events carry the frame's timestamp,
  so the frame rate sets their time resolution. Its cost is per frame (about the same for every frame of a
  still scene), so its wall time grows with the frame rate; the rate that its noise model itself needs is
  low (v2e warns only when `shot_noise_rate_hz * dt` > 1; at 30 fps it is 3e-5 for `davis` and
  0.17 for `noisy`), while its photoreceptor filter at the `davis`
  `cutoff_hz` of 300 Hz would want `dt ≤ 0.3 / (2π · 300 Hz)` (≈ 6.3 kHz; v2e warns below that, harmless
  on a still frame). Rows at 30 fps (a video's own rate, as v2e feeds it with `--disable_slomo`) are v2e's cheapest
  sensible setting, a lower bound of its cost; 1000 fps gives 1 ms timestamps, the resolution v2e's help
  names as its slow example.
- Reading the times: on a shared 2-core machine v2e's two torch threads slow down far more than evnoise
  when other jobs take a core (a frame of v2e took from ~40 ms on a quiet machine to ~500 ms at load 4);
  the load column says how busy the machine was, and CPU time is less sensitive than wall.
- Grey levels for v2e: `255 * lux / 300` (0.0085, 1.7 and 255), `evnoise.plugins.v2e`'s convention with
  300 lux white; v2e's noise depends on the grey level only through its shot-noise scaling."""


def long_settings(settings: list[tuple[str, float]], args) -> list[tuple[str, float]]:
    """The settings that also run for ``--long-duration`` (frame rate up to ``--marginal-max-fps``)."""
    return [key for key in settings if key[1] <= args.marginal_max_fps] if args.long_duration > DURATION_S else []


def marginal_lines(results, settings, args) -> list[str]:
    """The per-simulated-second part of the section (empty without long runs)."""
    keys = long_settings(settings, args)
    if not keys:
        return []
    return [f"**Per simulated second** (the same jobs run for {args.long_duration:g} s too, in the same turns; "
            f"marginal cost = (median work at {args.long_duration:g} s − median work at 1 s) / "
            f"{args.long_duration - 1:g} s, work = the time each run measures around its own job after its imports, "
            "median (min–max); what a long job costs per simulated second once both tools have started):", "",
            marginal_table(results, keys, args.long_duration), "", *marginal_verdicts(results, keys,
                                                                                      args.long_duration), ""]


def section(results, floors, settings, args, loads, v2e_versions) -> str:
    """The report's section: machine, command, table, start-up floors, verdicts and what each tool models."""
    import numba

    import evnoise as ev

    command = "python benchmarks/bench_v2e.py " + shlex.join(args.argv)
    lines = [
        TITLE, "",
        f"Machine: {cpu_name()}, {os.cpu_count()} cores shared with other jobs, {platform.system()}; "
        f"{_dt.date.today().isoformat()}. evnoise {ev.__version__} (Python {platform.python_version()}, NumPy "
        f"{np.__version__}, Numba {numba.__version__}); v2e {args.v2e_label} ({v2e_versions}, CPU). Both use "
        "every core (Numba's and torch's default threads). Command: "
        f"`{command}`. Load average (1, 5, 15 min): {loads[0][0]:.2f} {loads[0][1]:.2f} {loads[0][2]:.2f} "
        f"before, {loads[1][0]:.2f} {loads[1][1]:.2f} {loads[1][2]:.2f} after; the last column is the 1-minute "
        "load before and after each run of the row.",
        "",
        f"Job: a flat {WIDTH}x{HEIGHT} scene, {DURATION_S:g} s simulated; each run a fresh process, wall from start "
        "to exit (imports included), median (min–max) of "
        f"{args.repeats} runs taking turns, after uncounted runs that fill the caches (Numba's and evnoise's "
        "tables; v2e's imports). Wall seconds per simulated second = wall here (1 s simulated). v2e is fed "
        "`fps + 1` frames of the flat scene.",
        "",
        table(results, settings),
        "",
        "Start-up alone (imports; for evnoise also one cached kernel's first call), fresh processes, same "
        "environment: evnoise " + _fmt(floors["evnoise"]["wall"]) + " s, v2e " + _fmt(floors["v2e"]["wall"])
        + " s (`import v2ecore.emulator`, torch included).",
        "",
        *verdicts(results, settings),
        "",
        *marginal_lines(results, settings, args),
        MODELS,
        "",
    ]
    return "\n".join(lines)


def measure(args, settings) -> tuple[dict, dict]:
    """All timed runs: ``{lux: {key: times}}`` and the start-up floors."""
    results = {}
    with tempfile.TemporaryDirectory(prefix="evnoise-v2e-") as tmp:
        scratch = Path(tmp)
        cwd = scratch / "cwd"
        cwd.mkdir()
        env = environment(scratch)
        warm_up(args.v2e_python, env, cwd)
        for lux in LUX:
            print(f"{lux:g} lux", flush=True)
            commands = jobs(lux, settings, args.v2e_python, args.seed)
            keys = long_settings(settings, args)
            if keys:
                commands.update(jobs(lux, keys, args.v2e_python, args.seed, args.long_duration, tag="long"))
            results[lux] = time_jobs(commands, args.repeats, env, cwd)
        floors = floor_times(args.v2e_python, args.repeats, env, cwd)
    return results, floors


def main(argv=None) -> int:
    """Run the side-by-side timing; print the table; write it into the report unless ``--no-report``."""
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--v2e-python", default=None, help="interpreter that can import v2ecore.emulator")
    ap.add_argument("--v2e-label", default="(snapshot of SensorsINI/v2e)", help="what v2e is (a commit), for "
                    "the report")
    ap.add_argument("--v2e-setting", type=parse_setting, action="append", default=None, metavar="PARAMS@FPS",
                    help=f"v2e's noise parameters ({', '.join(V2E_PARAMS)}) and frame rate, repeatable "
                    f"(default: {' '.join(DEFAULT_SETTINGS)})")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per tool, setting and lux (default 3)")
    ap.add_argument("--long-duration", type=float, default=4.0, help="simulated seconds of the long runs that give "
                    "the cost per simulated second (default 4; 1 or less: no long runs)")
    ap.add_argument("--marginal-max-fps", type=float, default=100.0, help="v2e settings up to this frame rate get "
                    "long runs (default 100)")
    ap.add_argument("--seed", type=int, default=1, help="seed of both tools' noise (v2e gets seed + 1, not 0)")
    ap.add_argument("--lux", type=float, action="append", default=None, metavar="LUX",
                    help=f"illuminance of the flat scene, repeatable (default: {' '.join(f'{x:g}' for x in LUX)})")
    ap.add_argument("--report", type=Path, default=HERE / "REPORT.md", help="report to write the section into")
    ap.add_argument("--no-report", action="store_true", help="print the section only")
    args = ap.parse_args(argv)
    args.argv = argv
    if args.repeats < 1:
        ap.error("--repeats must be >= 1")
    if args.lux:
        if not all(x >= 0 and np.isfinite(x) for x in args.lux):
            ap.error("--lux must be finite and >= 0")
        globals()["LUX"] = tuple(args.lux)  # the module's lux list, read by every table and verdict
    problem = v2e_problem(args.v2e_python)
    if problem:
        print(f"bench_v2e.py: {problem}", file=sys.stderr)
        return 2
    settings = args.v2e_setting or [parse_setting(s) for s in DEFAULT_SETTINGS]
    loads = [os.getloadavg()]
    results, floors = measure(args, settings)
    loads.append(os.getloadavg())
    text = section(results, floors, settings, args, loads, versions(args.v2e_python))
    print(text)
    if not args.no_report:
        replace_section(args.report, TITLE, text)
        print(f"wrote {args.report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
