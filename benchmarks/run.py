"""Speed against error: regenerate ``benchmarks/REPORT.md`` and its plots with one command.

    python benchmarks/run.py                 # the full report (about 15 minutes on 2 cores)
    python benchmarks/run.py --quick         # smaller sizes, fewer repeats
    python benchmarks/run.py --tiny --out /tmp/bench   # smoke test (seconds)

Every timing is the median of repeated runs (after one warm-up run, so Numba's compilation is
excluded) with the min-max range; every speed figure sits next to the error of the method
that produced it. Nothing here is a test: the test suite only checks that this script runs.
"""

from __future__ import annotations

import argparse
import cProfile
import datetime as _dt
import io
import json
import math
import os
import platform
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import evnoise as ev  # noqa: E402
from evnoise.testing import naive_static_events, reference_log_event_probability  # noqa: E402

SIZES = {"tiny": dict(scale=0.02, repeats=1), "quick": dict(scale=0.25, repeats=3), "full": dict(scale=1.0, repeats=5)}


# ------------------------------------------------------------------------------ utilities
def timed(fn, repeats: int, warmup: bool = True):
    """Run ``fn`` (after a warm-up call) and return (median, min, max) seconds and the last result."""
    if warmup:
        fn()
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return (float(np.median(times)), float(np.min(times)), float(np.max(times))), result


def fmt_time(t):
    med, lo, hi = t
    return f"{med:.3g} s ({lo:.3g}–{hi:.3g})"


def machine_info() -> dict:
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True,
                                text=True, check=False).stdout.strip() or "?"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=HERE,
                               capture_output=True, text=True, check=False).stdout.strip()
        commit += " (with uncommitted changes)" if dirty else ""
    except OSError:
        commit = "?"
    import numba
    import scipy

    return {
        "date": _dt.datetime.now().strftime("%Y-%m-%d %H:%M"),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "load": [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "scipy": scipy.__version__,
        "evnoise": ev.__version__,
        "commit": commit,
    }


def scene(shape, rng=0, lux_max=18.0):
    """A deterministic test scene: smooth gradients and discs between 0.2 and ``lux_max`` lux."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    base = 0.5 + 0.35 * np.sin(7 * x) * np.cos(5 * y)
    r = np.random.default_rng(rng)
    for _ in range(12):
        cx, cy, rad, val = r.uniform(0, w / max(h, w)), r.uniform(0, h / max(h, w)), r.uniform(0.03, 0.15), r.uniform()
        base = np.where((x - cx) ** 2 + (y - cy) ** 2 < rad**2, val, base)
    return 0.2 + (lux_max - 0.2) * np.clip(base, 0, 1)


def stat_error(events_or_counts, lux, params, duration_s):
    """Relative error of total ON/OFF counts against the closed form, and its z-score."""
    if events_or_counts.dtype == ev.EVENT_DTYPE:
        counts = ev.count_events(events_or_counts, lux.shape)
    else:
        counts = events_or_counts
    expected = ev.expected_rate(lux, params).reshape(2, -1).sum(axis=1) * duration_s
    observed = counts.reshape(2, -1).sum(axis=1)
    rel = observed / expected - 1
    z = (observed - expected) / np.sqrt(expected)  # Poisson-like (binomial variance is smaller)
    return rel, z


# ------------------------------------------------------------------------------ 1. closed forms
def bench_closed_forms(size, out_dir, report):
    from approximations import continuity_corrected_normal, saddle_point
    from evnoise._kernels.chebyshev import CERT_MIN_VALUES
    from evnoise._kernels.poisson import log_event_probability_exact_array

    eps, b = 0.904, 1.7
    decades = [(-3, 0), (0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 6)]
    n_fast = max(2000, int(1_000_000 * size["scale"]))
    rows, points = [], []
    rng = np.random.default_rng(0)
    # the reference (direct windowed sum), itself checked against mpmath on a few points below
    for lo, hi in decades:
        # above lambda ~1e4 every method but the Gaussian one is a sum of O(sqrt(lambda)) terms:
        # fewer values there, so the section takes minutes, not hours
        n_eval = max(2000, int(n_fast / (10 ** max(0, hi - 4))))
        if lo >= 4 and size["scale"] >= 1.0:
            # an array call certifies a unit of log lam (and then uses its panels) only when it has at least
            # CERT_MIN_VALUES distinct values there, else it sums them exactly: time the table as a large call
            n_eval = max(n_eval, 8 * CERT_MIN_VALUES)
        lam = 10 ** rng.uniform(lo, hi, n_eval)
        n_direct = max(200, int(n_eval / (10 ** max(0, hi - 2))))
        lam_d = np.ascontiguousarray(lam[:n_direct])
        c = np.full(n_direct, math.expm1(eps))
        bb = np.full(n_direct, b)
        ref = np.empty(n_direct)
        t_direct, _ = timed(lambda: log_event_probability_exact_array(lam_d, c, bb, ref), size["repeats"])
        t_table, table = timed(lambda: ev.log_event_probability(lam, eps, b), size["repeats"])
        t_gauss, gauss = timed(lambda: ev.log_event_probability(lam, eps, b, method="gaussian"), size["repeats"])
        t_ccn, ccn = timed(lambda: continuity_corrected_normal(lam, eps, b), size["repeats"])
        t_sp, sp = timed(lambda: saddle_point(lam, eps, b), size["repeats"])

        def max_rel(logp_or_p, is_log):
            approx = logp_or_p[:n_direct]
            if is_log:  # log p compared in log space: also where p < 1e-300
                ok = np.isfinite(ref)
                if not ok.any():
                    return float("nan")
                with np.errstate(over="ignore", invalid="ignore"):
                    err = np.abs(np.expm1(approx[ok] - ref[ok]))
                return float(np.max(np.where(np.isnan(err), np.inf, err)))
            ok = ref > math.log(1e-300)
            if not ok.any():
                return float("nan")
            with np.errstate(divide="ignore"):
                return float(np.max(np.abs(approx[ok] / np.exp(ref[ok]) - 1)))

        per_m = lambda t, n: t[0] / n * 1e6  # noqa: E731
        entries = [
            ("poisson: adaptive Chebyshev table (used for arrays)", per_m(t_table, n_eval), max_rel(table, True)),
            ("poisson: windowed exact sum (used for scalars, mismatch maps)", per_m(t_direct, n_direct), 0.0),
            ("gaussian: paper eq. 3", per_m(t_gauss, n_eval), max_rel(gauss, True)),
            ("continuity-corrected normal (not used)", per_m(t_ccn, n_eval), max_rel(ccn, False)),
            ("saddle point, Lugannani-Rice (not used)", per_m(t_sp, n_eval), max_rel(sp, False)),
        ]
        for name, sec_per_m, err in entries:
            rows.append((f"1e{lo}–1e{hi}", name, sec_per_m, err))
            points.append((name, lo, sec_per_m, err))
    # the reference itself against mpmath
    checks = [(1e-12, eps, b), (0.2, eps, b), (5.0, eps, b), (18.0, eps, b), (300.0, eps, b), (1e3, 0.1, 0.0),
              (1e4, 0.05, 0.0)]
    if size["scale"] >= 1.0:
        checks += [(1e5, 0.01, 1.0)]
    worst = 0.0
    for lam, e_, b_ in checks:
        r = reference_log_event_probability(lam, e_, b_)
        got = float(ev.log_event_probability(lam, e_, b_))
        worst = max(worst, abs(math.expm1(got - r)))
    lines = [
        "## 1. Closed forms: time per million values and error",
        "",
        f"`eps = {eps}`, `bias = {b}` (the Noise2Image authors' EVK3-HD ON values), lam log-uniform in each decade "
        "(fewer values above 1e4, except the table's: a call certifies a unit of log lam and uses its panels only "
        f"with at least {CERT_MIN_VALUES:,} values in it, so the table is timed on {8 * CERT_MIN_VALUES:,} values "
        "per band there; its one-off certification is in the untimed warm-up). Error: maximum "
        "relative error of p against the exact windowed sum, for the methods that return log p (the two poisson "
        "rows, the paper's form) computed from log p wherever p > 0 (also below 1e-300), for the others wherever "
        "p > 1e-300 (nan: p < 1e-300 at every value checked); the windowed sum itself "
        f"agrees with an mpmath evaluation (50 digits) to {worst:.1e} relative at {len(checks)} check points "
        "(lam 1e-12 … " + f"{max(c[0] for c in checks):g}" + "). Times use both cores.",
        "",
        "| lam range | method | seconds per 1e6 values | max rel. error |",
        "|---|---|---|---|",
    ]
    for rng_s, name, spm, err in rows:
        lines.append(f"| {rng_s} | {name} | {spm:.3g} | {err:.1e} |")
    lines.append("")
    lines.append("Above λ = 1e4 the table's errors are where |log p| is 2e3–2e5 (at eps = 0.904 p is far below 1e-300 "
                 "there): a relative error of p of 1e-9 is then tens of ulps of log p, the order of the reference "
                 "sum's own rounding; the proven bounds of the certified panels used there are in 'Certified large-λ "
                 "panels' below.")
    lines.append("")
    lines.append("![speed vs error](closed_forms.png)")
    lines.append("")
    report.extend(lines)
    _plot_closed_forms(points, out_dir / "closed_forms.png")


#: top of the closed-form plot's error axis
PLOT_ERR_TOP = 1e12


def _plot_closed_forms(points, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    names = sorted({p[0] for p in points}, key=lambda n: [q[0] for q in points].index(n))
    for name in names:
        pts = [p for p in points if p[0] == name]
        # errors beyond the top of the axis (the Gaussian forms at large lam, where p is far below 1e-300) are
        # drawn at the top; nan / inf (nothing to compare, or overflow) are left out
        err = np.array([min(max(p[3], 1e-17), PLOT_ERR_TOP) if np.isfinite(p[3]) else np.nan for p in pts])
        spm = np.array([p[2] for p in pts])
        ax.plot(spm, err, "o-", label=name)
        for p, x, y in zip(pts, spm, err):
            if np.isfinite(y):
                ax.annotate(f"1e{p[1]}", (x, y), fontsize=6, alpha=0.7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("seconds per million values (2 threads)")
    ax.set_ylabel(f"max relative error of p (capped at {PLOT_ERR_TOP:.0e})")
    ax.set_title("Event probability: speed against error, per lam decade")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------------------ 2-4. simulator
def bench_simulator(size, out_dir, report, params):
    scale = size["scale"]
    reps = size["repeats"]
    lines = ["## 2. Simulator tiers: throughput and statistical error", ""]
    lines.append("Scene: smooth gradients and discs between 0.2 and 18 lux (`benchmarks/run.py:scene`), preset "
                 "`evk3-hd`. Statistical error: total ON/OFF counts against `expected_rate` (exact closed form) "
                 "for the same scene, as relative error and z-score (|z| < 3 is what a correct simulator shows).")
    lines.append("")
    lines.append("| resolution | tier | threads | work | time (median, min–max) | throughput "
                 "| rel. error ON / OFF | z ON / OFF |")
    lines.append("|---|---|---|---|---|---|---|---|")
    shapes = [(260, 346), (720, 1280)]
    for shape in shapes:
        lux = scene(shape)
        n_pix = lux.size
        for threads in (1, 2):
            dur_r = max(0.2, 10.0 * scale)
            t, events = timed(lambda: ev.simulate_events(lux, params, dur_r, rng=1, threads=threads), reps)
            rel, z = stat_error(events, lux, params, dur_r)
            lines.append(f"| {shape[1]}×{shape[0]} | renewal | {threads} | {dur_r:g} s, {events.size:,} events | "
                         f"{fmt_time(t)} | {events.size / t[0] / 1e6:.3g} M events/s | "
                         f"{rel[0]:+.1e} / {rel[1]:+.1e} | {z[0]:+.1f} / {z[1]:+.1f} |")
            dur_t = max(0.1, 2.0 * scale)
            t, events = timed(lambda: ev.simulate_events(lux, params, dur_t, rng=1, method="trials",
                                                         threads=threads), max(1, reps - 2))
            pt = n_pix * math.ceil(dur_t * params.trial_rate_hz)
            rel, z = stat_error(events, lux, params, dur_t)
            lines.append(f"| {shape[1]}×{shape[0]} | trials | {threads} | {dur_t:g} s, {pt:,} pixel-trials | "
                         f"{fmt_time(t)} | {pt / t[0] / 1e6:.3g} M pixel-trials/s | "
                         f"{rel[0]:+.1e} / {rel[1]:+.1e} | {z[0]:+.1f} / {z[1]:+.1f} |")
            t, counts = timed(lambda: ev.sample_counts(lux, params, 1.0, rng=1, threads=threads), reps)
            rel, z = stat_error(counts, lux, params, 1.0)
            lines.append(f"| {shape[1]}×{shape[0]} | counts only (1 s window) | {threads} | 1 count map | "
                         f"{fmt_time(t)} | {1 / t[0]:.3g} maps/s | "
                         f"{rel[0]:+.1e} / {rel[1]:+.1e} | {z[0]:+.1f} / {z[1]:+.1f} |")
    lines.append("")
    report.extend(lines)


def bench_naive(size, report, params):
    shape = (130, 173) if size["scale"] < 1 else (260, 346)
    lux = scene(shape)
    dur = max(0.5, 5.0 * size["scale"])
    reps = max(1, size["repeats"] - 2)
    t_naive, e_naive = timed(lambda: naive_static_events(lux, params, dur, rng=3), reps, warmup=False)
    t_trials, e_trials = timed(lambda: ev.simulate_events(lux, params, dur, rng=3, method="trials"), reps)
    t_renew, e_renew = timed(lambda: ev.simulate_events(lux, params, dur, rng=3), reps)
    lines = ["## 4. Against a naive reference (same run, same scene)", "",
             f"`evnoise.testing.naive_static_events`: vectorised NumPy, every trial draws both photon counts of every "
             f"eligible pixel. Scene {shape[1]}×{shape[0]}, {dur:g} s.", "",
             "| implementation | time (median, min–max) | speed-up vs naive | rel. error ON / OFF | z ON / OFF |",
             "|---|---|---|---|---|"]
    for name, t, e in (("naive NumPy per-trial", t_naive, e_naive), ("evnoise trials tier", t_trials, e_trials),
                       ("evnoise renewal tier", t_renew, e_renew)):
        rel, z = stat_error(e, lux, params, dur)
        lines.append(f"| {name} | {fmt_time(t)} | {t_naive[0] / t[0]:.1f}× | {rel[0]:+.1e} / {rel[1]:+.1e} | "
                     f"{z[0]:+.1f} / {z[1]:+.1f} |")
    lines.append("")
    report.extend(lines)


def bench_scaling(size, out_dir, report, params):
    scale = size["scale"]
    reps = max(1, size["repeats"] - 2)
    res = [(90, 160), (180, 320), (360, 640), (720, 1280)]
    if scale < 1:
        res = res[:3] if scale >= 0.25 else res[:2]
    out = {"resolution": [], "duration": [], "rate": []}
    base_dur = max(0.5, 4.0 * scale)
    for shape in res:
        lux = scene(shape)
        t, e = timed(lambda: ev.simulate_events(lux, params, base_dur, rng=2), reps)
        out["resolution"].append((lux.size, t[0], e.size))
    lux = scene(res[1])
    for dur in [base_dur * f for f in (0.25, 1, 4, 16)]:
        t, e = timed(lambda: ev.simulate_events(lux, params, dur, rng=2), reps)
        out["duration"].append((dur, t[0], e.size))
    for lux_level in (30.0, 15.0, 8.0, 2.0):  # brighter -> fewer noise events
        lux_f = np.full(res[1], lux_level)
        t, e = timed(lambda: ev.simulate_events(lux_f, params, base_dur, rng=2), reps)
        out["rate"].append((max(e.size, 1) / base_dur, t[0], e.size))
    _plot_scaling(out, out_dir / "scaling.png")
    # profile of the end-to-end run
    lux = scene(res[-1])
    prof = cProfile.Profile()
    prof.enable()
    ev.simulate_events(lux, params, base_dur, rng=2)
    prof.disable()
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(8)
    top = [ln for ln in s.getvalue().splitlines() if ln.strip() and ln.strip()[0].isdigit()][:8]
    lines = ["## 3. Scaling and where the time goes", "",
             f"Renewal tier (static scene). Resolution at {base_dur:g} s; duration at {res[1][1]}×{res[1][0]}; "
             "event rate by changing a flat field's illuminance.", "", "![scaling](scaling.png)", "",
             f"Profile (cProfile, by own time) of `simulate_events` at {res[-1][1]}×{res[-1][0]}, {base_dur:g} s:", "",
             "```", *[ln.rstrip() for ln in top], "```", ""]
    report.extend(lines)
    return out


def _plot_scaling(out, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(11, 3.6))
    for ax, (key, label) in zip(axes, [("resolution", "pixels"), ("duration", "duration [s]"),
                                       ("rate", "events per second of recording")]):
        x = np.array([p[0] for p in out[key]], dtype=float)
        y = np.array([p[1] for p in out[key]], dtype=float)
        ax.loglog(x, y, "o-")
        if len(x) > 1:
            slope = np.polyfit(np.log(x), np.log(y), 1)[0]
            ax.set_title(f"time vs {key} (slope {slope:.2f})", fontsize=9)
        ax.set_xlabel(label)
        ax.set_ylabel("wall time [s]")
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def bench_end_to_end(size, report, params):
    """Static 1280x720 into events.h5, in a subprocess, with peak memory."""
    try:
        import evnoise.io  # noqa: F401
    except ImportError:
        report.extend(["## 5. End to end into events.h5", "", "evnoise.io is not available yet.", ""])
        return
    lines = ["## 5. End to end into events.h5 (separate process, peak memory)", "",
             "| run | wall time | events | events.h5 size | writer share | peak RSS |", "|---|---|---|---|---|---|"]
    runs = [(10.0, (720, 1280))] if size["scale"] >= 1 else [(max(0.5, 10 * size["scale"]), (180, 320))]
    if size["scale"] >= 1:
        runs.append((60.0, (720, 1280)))
    for dur, shape in runs:
        code = f"""
import json, resource, time, numpy as np, evnoise as ev, sys
sys.path.insert(0, {str(HERE)!r})
from run import scene
p = ev.load_preset("evk3-hd")
lux = scene({shape!r})
ev.simulate_events(lux[:8, :8], p, 0.1, rng=0)  # compile outside the timing
t0 = time.perf_counter(); t_sim = 0.0; n = 0
with ev.EventWriter({{path!r}}, lux.shape, overwrite=True) as w:
    it = ev.iter_events(lux, p, {dur}, rng=1)
    while True:
        a = time.perf_counter()
        try:
            chunk = next(it)
        except StopIteration:
            break
        t_sim += time.perf_counter() - a
        w.write(chunk); n += chunk.size
wall = time.perf_counter() - t0
print(json.dumps(dict(wall=wall, sim=t_sim, n=n, rss=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)))
"""
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "bench.h5")
            res = subprocess.run([sys.executable, "-c", code.replace("{path!r}", repr(path))], capture_output=True,
                                 text=True)
            if res.returncode != 0:
                lines.append(f"| {shape[1]}×{shape[0]}, {dur:g} s | failed: {res.stderr.strip()[-200:]} | | | | |")
                continue
            r = json.loads(res.stdout.strip().splitlines()[-1])
            fsize = os.path.getsize(path) / 1e6
        share = 1 - r["sim"] / r["wall"]
        lines.append(f"| {shape[1]}×{shape[0]}, {dur:g} s | {r['wall']:.2f} s | {r['n']:,} | {fsize:.0f} MB | "
                     f"{share:.0%} | {r['rss'] / 1024:.0f} MB |")
    lines.append("")
    report.extend(lines)


# ------------------------------------------------------------------------------ 6. Gaussian error
def bench_gaussian_error(size, out_dir, report):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = 60 if size["scale"] >= 0.25 else 20
    lam = np.geomspace(1e-2, 1e3, n)
    eps = np.linspace(0.05, 2.0, n)
    L, E = np.meshgrid(lam, eps)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, b in zip(axes, (0.0, 1.7)):
        exact = ev.log_event_probability(L, E, b)
        gauss = ev.log_event_probability(L, E, b, method="gaussian")
        with np.errstate(over="ignore"):
            err = np.abs(np.expm1(np.clip(gauss - exact, -700, 700)))
        err = np.where(exact > math.log(1e-300), err, np.nan)
        im = ax.pcolormesh(L, E, np.log10(np.maximum(err, 1e-6)), shading="auto", cmap="magma", vmin=-3, vmax=3)
        ax.set_xscale("log")
        ax.set_xlabel("lam [photons per trial]")
        ax.set_ylabel("eps")
        ax.set_title(f"log10 |p_gauss / p_exact - 1|, bias = {b}", fontsize=9)
        fig.colorbar(im, ax=ax)
    fig.tight_layout()
    fig.savefig(out_dir / "gaussian_error.png", dpi=110)
    plt.close(fig)
    lam_op = np.array([0.2, 0.5, 1, 2, 5, 10, 20])
    lines = ["## 6. The paper's Gaussian form against the exact form", "",
             "Ratio `p_gauss / p_exact` at the paper's operating point (EVK3-HD: eps_pos 0.904, eps_neg 1.0235, "
             "bias 1.7):", "", "| lam | " + " | ".join(f"{x:g}" for x in lam_op) + " |",
             "|---|" + "---|" * len(lam_op)]
    for name, e in (("ON, eps 0.904", 0.904), ("OFF, eps 1.0235", 1.0235)):
        ratio = ev.event_probability(lam_op, e, 1.7, method="gaussian") / ev.event_probability(lam_op, e, 1.7)
        lines.append(f"| {name} | " + " | ".join(f"{r:.2f}" for r in ratio) + " |")
    lines += ["", "![gaussian error map](gaussian_error.png)", ""]
    report.extend(lines)


# ------------------------------------------------------------------------------ main
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--quick", action="store_true", help="smaller sizes and fewer repeats")
    group.add_argument("--tiny", action="store_true", help="smoke test sizes")
    parser.add_argument("--out", type=Path, default=HERE, help="folder for REPORT.md and the plots")
    parser.add_argument("--train-minutes", type=float, default=None,
                        help="train a small U-Net this long for the dynamic-scene section (default: 0 with "
                             "--tiny, 3 with --quick, 10 otherwise; 0 evaluates the model-based inversion only)")
    parser.add_argument("--only-closed-forms", action="store_true",
                        help="rerun section 1 only, in place in the existing REPORT.md (with its own machine line)")
    args = parser.parse_args(argv)
    size = SIZES["tiny" if args.tiny else "quick" if args.quick else "full"]
    args.out.mkdir(parents=True, exist_ok=True)
    params = ev.load_preset("evk3-hd")
    info = machine_info()
    if args.only_closed_forms:
        return _closed_forms_only(size, args, info)
    t_start = time.perf_counter()
    report = []
    bench_closed_forms(size, args.out, report)
    bench_simulator(size, args.out, report, params)
    bench_scaling(size, args.out, report, params)
    bench_naive(size, report, params)
    bench_end_to_end(size, report, params)
    bench_gaussian_error(size, args.out, report)
    from bench_dataset import bench_dataset

    bench_dataset(size, args.out, report)
    from bench_dynamic import bench_dynamic

    bench_dynamic(size, args.out, report, train_minutes=args.train_minutes)
    mode = "--tiny" if args.tiny else "--quick" if args.quick else ""
    head = [
        "# evnoise benchmark report",
        "",
        f"Generated by `python benchmarks/run.py {mode}`".rstrip() + f" on {info['date']} in "
        f"{time.perf_counter() - t_start:.0f} s.",
        "",
        f"Machine: {info['cpu']}, {info['cores']} cores, load average at start {info['load']}; Python "
        f"{info['python']}, NumPy {info['numpy']}, Numba {info['numba']}, SciPy {info['scipy']}; evnoise "
        f"{info['evnoise']} (commit {info['commit']}). The machine is shared, so absolute times vary by tens of "
        "percent between runs; ratios within one run are more stable.",
        "",
    ]
    kept = _kept_sections(args.out / "REPORT.md")
    (args.out / "REPORT.md").write_text("\n".join(head + report) + "\n" + kept, encoding="utf-8")
    print(f"wrote {args.out / 'REPORT.md'}")
    return 0


def _closed_forms_only(size, args, info) -> int:
    """Section 1 alone, written in place of the report's section 1 (the rest of the report is kept)."""
    from _report import replace_section

    t_start = time.perf_counter()
    section = []
    bench_closed_forms(size, args.out, section)
    mode = " --quick" if args.quick else " --tiny" if args.tiny else ""
    machine = (f"Rerun alone (`python benchmarks/run.py --only-closed-forms{mode}`) on {info['date']} in "
               f"{time.perf_counter() - t_start:.0f} s, load average at start {info['load']}; {info['cpu']}, "
               f"{info['cores']} cores, Python {info['python']}, NumPy {info['numpy']}, Numba {info['numba']}; "
               f"evnoise commit {info['commit']}.")
    section.insert(2, machine)
    section.insert(3, "")
    replace_section(args.out / "REPORT.md", section[0], "\n".join(section) + "\n")
    print(f"wrote section 1 of {args.out / 'REPORT.md'}")
    return 0


#: Sections of REPORT.md below this line are written by other scripts (bench_readers.py,
#: bench_speed16.py) or by hand; run.py keeps them when it regenerates the report.
KEEP_MARKER = "<!-- sections below are written by other benchmark scripts; run.py keeps them -->"


def _kept_sections(path: Path) -> str:
    """The part of an existing report from :data:`KEEP_MARKER` on ('' when there is none)."""
    if not path.exists():
        return ""
    text = path.read_text(encoding="utf-8")
    at = text.find(KEEP_MARKER)
    return "\n" + text[at:] if at >= 0 else ""


if __name__ == "__main__":
    sys.exit(main())
