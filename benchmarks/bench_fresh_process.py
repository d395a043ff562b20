"""Issue 33: what a fresh process pays (Numba cache and table cache, cold and warm), and the set-up per pixel.

    nice -n 10 python benchmarks/bench_fresh_process.py [--repeats 5] [--baseline-tree DIR] [--report REPORT.md]

Each timed command is a separate process (wall from start to exit, CPU from the OS's accounting of the
child): ``python -m evnoise simulate --example --duration 1 --out OUT.h5 --overwrite`` (the README's quick
start, 1 s) and a 1280x720 flat field simulated for 1 s at 0.01, 2 and 300 lux
(``evnoise.simulate_events``). Caches: Numba's compiled kernels in a temporary ``NUMBA_CACHE_DIR``
(cold: empty for every run; warm: filled by a run that is not counted) and evnoise's closed-form tables in
a temporary ``EVNOISE_CACHE`` (same). ``--baseline-tree DIR`` times the same commands with ``DIR`` (a
checkout of the code before issue 33, e.g. ``git archive <commit> | tar -x -C DIR``) first on
``PYTHONPATH``, side by side in the same run.

In-process (after a warm-up): the set-up per pixel of a 1 s static 1280x720 run, as the issue defines it
(the 1 s run's time less its events at the marginal per-event cost of a 10 s run), with its parts, and the
closed form's error on the photon counts the runs use (max relative error of ``p`` against the exact
sum). With ``--report`` the section below ``TITLE`` is replaced (or appended) and ``fresh_process.png``
written beside the report.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from _report import cpu_name, replace_section  # noqa: E402  (the benchmarks folder, put on the path above)

TITLE = "## Fresh process: fixed costs once per machine, set-up per pixel (issue 33)"
LUX = (0.01, 2.0, 300.0)
FLAT = ("import sys, numpy as np, evnoise as ev; "
        "ev.simulate_events(np.full((720, 1280), float(sys.argv[1])), 'evk3-hd', 1.0, rng=0)")
#: what every run pays before any work: the imports and Numba's first load from its cache (its registries)
FLOOR = ("import numpy as np, evnoise, h5py; from evnoise._kernels.levels import find_levels; "
         "find_levels(np.zeros(8), 2)")


def run_process(cmd, env, cwd) -> tuple[float, float, int]:
    """``(wall s, CPU s, exit code)`` of one separate process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    return wall, usage.ru_utime + usage.ru_stime, proc.returncode


#: dropped from the children's environment: a warm install has its modules' bytecode (pip compiles it at install
#: time; a checkout writes it at its first import), so the uncounted warm-up run must be free to write it. With
#: ``PYTHONDONTWRITEBYTECODE`` set (as on some CI machines and containers) every run would compile each module
#: changed since its bytecode was last written, which no user's second run does.
NOT_INHERITED = ("EVNOISE_TABLE_CACHE", "PYTHONPATH", "PYTHONDONTWRITEBYTECODE")


def environment(tree: Path | None, numba_dir: Path, table_dir: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in NOT_INHERITED}
    env.update(NUMBA_CACHE_DIR=str(numba_dir), EVNOISE_CACHE=str(table_dir), PYTHONHASHSEED="0")
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    return env


def _empty(d: Path) -> None:
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)


def scenario(cmd, trees, numba_warm: bool, tables_warm: bool, repeats: int, scratch: Path) -> dict:
    """Times of ``repeats`` fresh processes of ``cmd`` per code tree, the trees taking turns (A B A B ...: a drift
    in the machine's speed reaches both alike), with the caches cold (emptied before each run) or warm.

    The processes run in an empty folder, so that ``python -m`` / ``-c`` import evnoise from ``PYTHONPATH``
    (the tree) or the installed package, not from the current folder."""
    cwd = scratch / "cwd"
    cwd.mkdir(parents=True, exist_ok=True)
    setups = {}
    for name, tree in trees:
        numba_dir, table_dir = scratch / name / "numba", scratch / name / "tables"
        _empty(numba_dir)
        _empty(table_dir)
        env = environment(tree, numba_dir, table_dir)
        if numba_warm or tables_warm:
            run_process(cmd, env, cwd)  # fills both caches; a cold one is emptied again before each run
        setups[name] = (env, numba_dir, table_dir)
    times = {name: {"wall": [], "cpu": []} for name, _ in trees}
    for _ in range(repeats):
        for name, _tree in trees:
            env, numba_dir, table_dir = setups[name]
            if not numba_warm:
                _empty(numba_dir)
            if not tables_warm:
                _empty(table_dir)
            wall, cpu, rc = run_process(cmd, env, cwd)
            if rc != 0:
                raise RuntimeError(f"{cmd} ({name}) exited with {rc}")
            times[name]["wall"].append(wall)
            times[name]["cpu"].append(cpu)
    return times


def fresh_process_rows(repeats: int, cold_repeats: int, baseline: Path | None, scratch: Path) -> list[dict]:
    out_h5 = scratch / "example.h5"
    example = [sys.executable, "-m", "evnoise", "simulate", "--example", "--duration", "1", "--out", str(out_h5),
               "--overwrite"]
    trees = [("after", None)] + ([("before", baseline)] if baseline is not None else [])
    rows = []

    def add(job, t, numba_state, table_state):
        for name, _ in trees:
            if name in t:
                rows.append({"job": job, "tree": name, "numba": numba_state,
                             "tables": table_state if name == "after" else "(none)", **t[name]})
                print(job, name, numba_state, table_state, f"{np.median(t[name]['wall']):.2f} s", flush=True)

    job = "`evnoise simulate --example --duration 1`"
    add(job, scenario(example, trees, True, True, repeats, scratch), "warm", "warm")
    add(job, scenario(example, trees[:1], True, False, max(2, repeats // 2), scratch), "warm", "cold")
    add(job, scenario(example, trees[:1], False, True, cold_repeats, scratch), "cold", "warm")
    add(job, scenario(example, trees, False, False, cold_repeats, scratch), "cold", "cold")
    for lux in LUX:
        t = scenario([sys.executable, "-c", FLAT, repr(lux)], trees, True, True, max(3, repeats // 2), scratch)
        add(f"flat field {lux:g} lux, 1 s (`simulate_events`)", t, "warm", "warm")
    floor = scenario([sys.executable, "-c", FLOOR], trees[:1], True, True, repeats, scratch)
    add("floor: `import evnoise, numba, h5py` and one cached kernel's first call", floor, "warm", "-")
    return rows


def setup_per_pixel(repeats: int) -> list[dict]:
    """In-process set-up per pixel at each lux: grouped (this version) and per-pixel (``MAX_LEVELS = 0``)."""
    import evnoise as ev
    from evnoise import _engine, model

    params = ev.load_preset("evk3-hd")
    key = np.arange(4, dtype=np.uint64)

    def best(fn, n=repeats):
        fn()
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            out = fn()
            times.append(time.perf_counter() - t0)
        return float(np.min(times)), float(np.median(times)), out

    rows = []
    saved = model.MAX_LEVELS
    try:
        for lux in LUX:
            field = np.full((720, 1280), lux)
            lam = params.photons_per_trial(field).ravel()
            n = lam.size
            eps_on, eps_off = np.full(n, params.eps_pos), np.full(n, params.eps_neg)
            for label, levels in (("per pixel (earlier versions)", 0), ("once per distinct lam", saved)):
                model.MAX_LEVELS = levels
                si = best(lambda: _engine.static_inputs(lam, params, eps_on, eps_off, None))
                ps = best(lambda: _engine.PixelState(np.arange(n), key, 2))
                t1 = best(lambda: ev.simulate_events(field, params, 1.0, rng=1))
                t10 = best(lambda: ev.simulate_events(field, params, 10.0, rng=1), max(2, repeats // 2))
                e1, e10 = t1[2].size, t10[2].size
                per_event = (t10[1] - t1[1]) / max(e10 - e1, 1)
                rows.append({"lux": lux, "how": label, "static_inputs": si, "pixel_state": ps, "run1": t1[:2],
                             "events": e1, "per_event": per_event,
                             "setup": ((t1[0] - e1 * per_event) / n, (t1[1] - e1 * per_event) / n), "n": n})
                print(lux, label, f"set-up {rows[-1]['setup'][1] * 1e9:.0f} ns/px", flush=True)
    finally:
        model.MAX_LEVELS = saved
    return rows


def closed_form_error() -> list[dict]:
    """Max relative error of the closed form (table path) against the exact sum on the photon counts the runs use."""
    import evnoise as ev
    from evnoise import model, radiometry
    from evnoise._kernels.poisson import log_event_probability_exact_array
    from evnoise.cli.simulate import _example_path

    params = ev.load_preset("evk3-hd")
    fields = {"the example image (the CLI's default scaling)": radiometry.image_to_lux(str(_example_path()))}
    fields.update({f"flat {lux:g} lux": np.full((720, 1280), lux) for lux in LUX})
    out = []
    for name, lux in fields.items():
        lam = params.photons_per_trial(lux).ravel()
        levels = np.unique(lam)
        at = np.searchsorted(levels, lam)
        worst = 0.0
        for eps in (params.eps_pos, params.eps_neg):
            p = model.event_probability(lam, eps, params.bias_pr)  # the run's path (the table, for a full field)
            exact = np.empty(levels.size)
            log_event_probability_exact_array(levels, np.full(levels.size, np.expm1(eps)),
                                              np.full(levels.size, params.bias_pr), exact)
            ref = np.exp(exact)[at]
            ok = ref > 0
            if ok.any():
                worst = max(worst, float((np.abs(p[ok] - ref[ok]) / ref[ok]).max()))
        out.append({"field": name, "levels": levels.size, "max_rel": worst})
    return out


def _fmt(values) -> str:
    v = np.asarray(values)
    return f"{np.median(v):.2f} ({v.min():.2f}–{v.max():.2f})"


def section(fresh, setup, errors, args, plot_name) -> str:
    import numba

    import evnoise as ev

    load = os.getloadavg()
    lines = [
        TITLE, "",
        f"Machine: {cpu_name()}, {os.cpu_count()} cores shared with other jobs (load average {load[0]:.1f} at the "
        f"end), {platform.system()}; Python {platform.python_version()}, NumPy {np.__version__}, Numba "
        f"{numba.__version__}; evnoise {ev.__version__}; {_dt.date.today().isoformat()}. Command: "
        f"`python benchmarks/bench_fresh_process.py --repeats {args.repeats} --cold-repeats {args.cold_repeats}"
        + (" --baseline-tree DIR" if args.baseline_tree else "") + " --report benchmarks/REPORT.md`"
        + (f" (DIR: the tree at commit {args.baseline_label}, before issue 33)" if args.baseline_tree else "") + ".",
        "",
        "**Fresh processes.** Each row is separate processes, wall from start to exit and the OS's CPU time of the "
        "child, median (min–max). Numba cache: a temporary `NUMBA_CACHE_DIR`, emptied before every run (cold: a "
        "fresh install) or filled by an uncounted run (warm: every later run); table cache: a temporary "
        "`EVNOISE_CACHE` likewise. 'before' is the code before issue 33 (no table cache: every process builds its "
        "tables); the two codes ran in turns (A B A B ...) in empty folders. A table read back is the same, bit "
        "for bit, as one built (`tests/test_table_cache.py`), so every row's events are those of a build from "
        "scratch.",
        "",
        "| job | code | Numba cache | table cache | wall (s) | CPU (s) | runs |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in fresh:
        lines.append(f"| {r['job']} | {r['tree']} | {r['numba']} | {r['tables']} | {_fmt(r['wall'])} | "
                     f"{_fmt(r['cpu'])} | {len(r['wall'])} |")
    lines += [
        "",
        f"![fresh-process wall times]({plot_name})",
        "",
        "**Set-up per pixel** (in one warm process, 1280x720, preset `evk3-hd`, flat field): the issue's measure, "
        "the 1 s run's time less its events at the marginal cost per event of a 10 s run (min / median of "
        f"{args.repeats} runs), with its parts. 'Per pixel' is the evaluation earlier versions made "
        "(`evnoise.model.MAX_LEVELS = 0`); the renewal inputs are bit for bit the same either way "
        "(`tests/test_scene_cost.py`).",
        "",
        "| lux | closed form evaluated | set-up (ns/pixel) | of it: renewal inputs (ns/pixel) | pixel state "
        "(ns/pixel) | 1 s run (s) | events | ns/event (marginal) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in setup:
        n = r["n"]
        lines.append(
            f"| {r['lux']:g} | {r['how']} | {r['setup'][0] * 1e9:.0f} / {r['setup'][1] * 1e9:.0f} | "
            f"{r['static_inputs'][0] * 1e9 / n:.1f} / {r['static_inputs'][1] * 1e9 / n:.1f} | "
            f"{r['pixel_state'][0] * 1e9 / n:.1f} / {r['pixel_state'][1] * 1e9 / n:.1f} | "
            f"{r['run1'][0]:.3f} / {r['run1'][1]:.3f} | {r['events']:,} | {r['per_event'] * 1e9:.0f} |")
    lines += [
        "",
        "**Error of the closed form on the values the runs use** (both thresholds of `evk3-hd`): max relative "
        "error of `p` from the table path (the one a full field takes, cached or built) against the exact sum "
        "(`log_event_probability_exact_array`).",
        "",
        "| field | distinct photon counts | max relative error of p |",
        "|---|---|---|",
    ]
    for e in errors:
        lines.append(f"| {e['field']} | {e['levels']} | {e['max_rel']:.1e} |")
    lines += ["", NOTES, ""]
    return "\n".join(lines)


NOTES = """What the rows say. A fresh process with warm caches pays first the floor row: Python, NumPy, evnoise and
h5py imported, and Numba's first load of a kernel from its cache (Numba then loads its typing registries and
imports `scipy.linalg` to look for BLAS, about 0.2 s of it), which evnoise cannot avoid while its kernels are
Numba's. Above the floor the quick start spends its events (renewal kernel and sort), the pixel state and the
HDF5 file; the closed form is a table read (a few ms) and one evaluation per distinct photon count (the
example has 245). With a cold Numba cache, the table cache saves compiling the table builder (the exact
kernel and the panel fit): only the kernels a run calls are compiled. The pixel state (~20 ns per pixel) is
the 12-column float state the renewal kernel takes (96-byte rows, faulted in by both threads); a narrower
state for renewal-only pixels needs a change in the kernel's column layout (`evnoise/_kernels/simulate.py`).
Items 3 (large-lam certified panels) and 4 (threshold-mismatch counts) of issue 33 have their own sections below."""


def plot(fresh, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in fresh if r["tree"] in ("after", "before")]
    labels = [f"{r['job'].replace('`', '')[:42]}\n{r['tree']}, Numba {r['numba']}, tables {r['tables']}"
              for r in rows]
    med = [np.median(r["wall"]) for r in rows]
    lo = [m - np.min(r["wall"]) for m, r in zip(med, rows)]
    hi = [np.max(r["wall"]) - m for m, r in zip(med, rows)]
    colors = ["tab:blue" if r["tree"] == "after" else "tab:gray" for r in rows]
    fig, ax = plt.subplots(figsize=(9, 0.42 * len(rows) + 1.2))
    y = np.arange(len(rows))[::-1]
    ax.barh(y, med, xerr=[lo, hi], color=colors, capsize=2)
    ax.set_yticks(y, labels, fontsize=6)
    ax.set_xscale("log")
    ax.axvline(1.0, color="tab:red", ls="--", lw=1, label="goal for the quick start, warm install: 1.0 s")
    ax.set_xlabel("wall time of a fresh process (s), median with min-max")
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="runs per warm-cache row (default 5)")
    ap.add_argument("--cold-repeats", type=int, default=2, help="runs per cold-Numba-cache row (default 2)")
    ap.add_argument("--baseline-tree", type=Path, default=None, help="code before issue 33, timed side by side")
    ap.add_argument("--baseline-label", default="?", help="what the baseline tree is (a commit), for the report")
    ap.add_argument("--report", type=Path, default=None, help="replace this report's section, plot beside it")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="evnoise-fresh-") as tmp:
        fresh = fresh_process_rows(args.repeats, args.cold_repeats, args.baseline_tree, Path(tmp))
    setup = setup_per_pixel(args.repeats)
    errors = closed_form_error()
    if args.report:
        plot(fresh, args.report.parent / "fresh_process.png")
        replace_section(args.report, TITLE, section(fresh, setup, errors, args, "fresh_process.png"))
        print(f"wrote {args.report}")
    else:
        print(section(fresh, setup, errors, args, "fresh_process.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
