"""Timing of the real quiet windows against the quiet-window fit (no memory): counts and timing, window by window.

    python -m evnoise.calibration.scripts.quiet_timing [--data ../shared/data/realdata]
        [--out calibration/quiet-timing.json]

For every window of the real-data folder's ``quiet_segments.json`` (DVS128 and eDVS128 recordings, jAER
AEDAT 2.0, opened by :func:`evnoise.calibration.quiet.quiet_window` with its checks on), fits the quiet
model to that window alone (:func:`evnoise.calibration.quiet.fit_quiet`: rates, regularity, spread, hot
pixels; memoryless: a pixel's polarities are independent) and records what issue 32 asks the model to
reproduce:

* the share of consecutive same-pixel events opposite in polarity, and the memoryless expectation given
  each pixel's ON/OFF counts (:func:`evnoise.calibration.quiet.checks.same_pixel_timing`), with the
  transitions test's p-value;
* OFF->ON pairs of one pixel within 50 ms against the pixels' ON streams shifted in time (the
  ``polarity_pairs`` check);
* the same-pixel inter-event intervals: median and CV of the real ones against the fitted model's (the
  model's are those of its interval distribution within the window, :func:`.goodness.interval_cdf`, the
  one the KS test uses), and the KS p-value;
* the count goodness p-values (per-pixel ON and OFF histograms) and the fit status with its reasons.

Writes the JSON (``--out``) and prints a markdown table. The recordings are third-party data: they are
read, never copied. This is the baseline before a model with memory (issue 32).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[1]  # calibration/: the scripts' outputs are kept there
OUT = HERE / "quiet-timing.json"


def _model_of(fit):
    """The fitted (memoryless) model of a one-window fit, for :func:`.goodness.interval_cdf`: the terms the
    fit kept, no shot noise (the windows have no lux)."""
    from ..quiet.likelihood import Model, window_groups

    def kept(name):
        return not fit.status[name].startswith(("not identified", "fixed"))

    groups = window_groups(fit.windows)
    model = Model(kept("sigma"), kept("hot_fraction"), [np.zeros((len(g.windows), 2)) for g in groups], False,
                  [np.zeros(len(g.windows)) for g in groups], kept("regularity"))
    return model, groups


def model_interval_stats(fit) -> dict:
    """Median, mean and CV of the fitted model's same-pixel intervals seen within the window (the censored
    distribution the KS test compares with), by quadrature of its CDF on [0, T]."""
    from ..quiet.goodness import interval_cdf

    model, groups = _model_of(fit)
    w = groups[0].windows[0]
    x = np.linspace(0.0, w.duration_s, 20001)
    cdf = interval_cdf(x, fit.values, model, 0, groups[0], 0)
    surv = 1.0 - cdf
    mean = float(np.trapezoid(surv, x))
    second = float(np.trapezoid(2.0 * x * surv, x))
    var = max(second - mean * mean, 0.0)
    median = float(np.interp(0.5, cdf, x)) if cdf[-1] >= 0.5 else math.nan
    return {"median_s": median, "mean_s": mean, "cv": math.sqrt(var) / mean if mean > 0 else math.nan}


def analyse(data: Path, rel: str, seg: dict) -> dict:
    from ..quiet.fit import fit_quiet
    from ..quiet.window import quiet_window

    w = quiet_window(data / rel, seg["t_from_us"] * 1e-6, seg["t_to_us"] * 1e-6, checks=True)
    w.source = rel
    fit = fit_quiet([w])
    pairs = next(c for c in w.checks if c["check"] == "polarity_pairs")
    same = pairs.get("same_pixel") or next((c["same_pixel"] for c in w.checks if "same_pixel" in c), None)
    trans = next((t for t in fit.timing if t["test"] == "polarity_transitions"), {})
    ks = next((t for t in fit.timing if t["test"] == "intervals"), {})
    xs = np.asarray(same["intervals_s"] if same else [], dtype=np.float64)
    n_trans = int(same["transitions"]) if same else 0
    real_iei = {"n": int(same["n_intervals"]) if same else 0,
                "median_s": float(np.median(xs)) if xs.size else math.nan,
                "cv": float(np.std(xs, ddof=1) / np.mean(xs)) if xs.size > 1 and np.mean(xs) > 0 else math.nan,
                "stored_order_statistics": int(xs.size)}
    model_iei = model_interval_stats(fit)
    model_iei["median_s_timing_test"] = ks.get("model_median_s", math.nan)
    gof = {g["polarity"]: g for g in fit.goodness}
    return {
        "file": rel, "from_s": seg["from_s"], "to_s": seg["to_s"], "t_from_us": int(seg["t_from_us"]),
        "t_to_us": int(seg["t_to_us"]), "content": seg.get("content", ""),
        "events": int(w.counts.sum()), "on_events": int(w.counts[0].sum()), "off_events": int(w.counts[1].sum()),
        "alternation": {"transitions": n_trans, "opposite": int(same["opposite"]) if same else 0,
                        "opposite_share": same["opposite"] / n_trans if n_trans else math.nan,
                        "memoryless_share": same["memoryless_mean"] / n_trans if n_trans else math.nan,
                        "p_value": trans.get("p_value", math.nan), "testable": bool(trans.get("testable", False)),
                        "detail": trans.get("detail", "")},
        "off_on_pairs_50ms": {"observed": int(pairs["statistic"]), "shifted_mean": float(pairs["null_mean"]),
                              "shifted_sd": float(pairs["null_sd"]), "p_value": float(pairs["p_value"]),
                              "testable": bool(pairs.get("testable", True)), "detail": pairs.get("detail", "")},
        "iei": {"real": real_iei, "model": model_iei, "ks_p_value": ks.get("p_value", math.nan),
                "ks_testable": bool(ks.get("testable", False)), "detail": ks.get("detail", "")},
        "count_goodness": {p: {"p_value": g["p_value"], "chi2": g["chi2"], "dof": g["dof"], "events": g["events"],
                               "expected_events": g["expected_events"]} for p, g in gof.items()},
        "fit_status": fit.fit_status, "rejections": list(fit.rejections),
        "values": {k: float(v) for k, v in fit.values.items()}, "parameter_status": dict(fit.status),
    }


def _why(rejections) -> str:
    """The tests that rejected a fit, in a few words: counts ON/OFF, a failed model-free check, timing."""
    out = []
    for r in rejections:
        if "count histogram" in r:
            word = "counts " + ("ON" if " ON:" in r else "OFF")
        elif "not pure stationary noise" in r:
            word = r.split("noise: ", 1)[1].split(" ", 1)[0]
        elif "inter-event intervals" in r:
            word = "IEI KS"
        elif "alternate in polarity" in r:
            word = "transitions"
        else:
            word = "other"
        if word not in out:
            out.append(word)
    return ", ".join(out)


def _f(x, fmt):
    return "–" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def table(rows) -> str:
    head = ("| window | events (ON/OFF) | opposite share: real / memoryless | OFF→ON pairs ≤ 50 ms: real / shifted "
            "| IEI n | IEI median real / model (s) | IEI CV real / model | count p ON / OFF "
            "| timing p: transitions / KS | fit |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        a, pr, iei, g = r["alternation"], r["off_on_pairs_50ms"], r["iei"], r["count_goodness"]
        name = Path(r["file"]).name.replace(".aedat", "")
        why = f" ({_why(r['rejections'])})" if r["rejections"] else ""
        lines.append(
            f"| {name} {r['from_s']:g}–{r['to_s']:g} s | {r['events']} ({r['on_events']}/{r['off_events']}) "
            f"| {_f(a['opposite_share'], '.2f')} / {_f(a['memoryless_share'], '.2f')} (of {a['transitions']}) "
            f"| {pr['observed']} / {_f(pr['shifted_mean'], '.1f')} "
            f"| {iei['real']['n']} | {_f(iei['real']['median_s'], '.3f')} / {_f(iei['model']['median_s'], '.3f')} "
            f"| {_f(iei['real']['cv'], '.2f')} / {_f(iei['model']['cv'], '.2f')} "
            f"| {_f(g.get('ON', {}).get('p_value'), '.2g')} / {_f(g.get('OFF', {}).get('p_value'), '.2g')} "
            f"| {_f(a['p_value'], '.2g')} / {_f(iei['ks_p_value'], '.2g')} | {r['fit_status']}{why} |")
    return "\n".join(lines)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=HERE.parent.parent / "shared" / "data" / "realdata",
                    help="the real-data folder (with quiet_segments.json)")
    ap.add_argument("--out", type=Path, default=OUT, help="JSON written (default calibration/quiet-timing.json)")
    args = ap.parse_args(argv)
    if not (args.data / "quiet_segments.json").is_file():
        print(f"skipped: no quiet_segments.json in {args.data} (the real recordings are not here; "
              f"pass --data)", file=sys.stderr)
        return 0

    from evnoise._version import __version__

    segments = json.loads((args.data / "quiet_segments.json").read_text(encoding="utf-8"))["segments"]
    rows, t0 = [], time.perf_counter()
    for rel, windows in segments.items():
        for seg in windows:
            t = time.perf_counter()
            rows.append(analyse(args.data, rel, seg))
            print(f"  {rel} {seg['from_s']}-{seg['to_s']} s: {rows[-1]['fit_status']} "
                  f"({time.perf_counter() - t:.1f} s)", file=sys.stderr)
    out = {
        "summary": "real quiet windows (quiet_segments.json) against the memoryless quiet fit of each window: "
                   "counts and timing (issue 32 baseline, before the memory fit)",
        "command": "python -m evnoise.calibration.scripts.quiet_timing",
        "date": _dt.date.today().isoformat(), "evnoise_version": __version__,
        "runtime_s": round(time.perf_counter() - t0, 1),
        "notes": ["opposite share: consecutive events of one pixel opposite in polarity; memoryless: its "
                  "expectation when each pixel's polarities are independent given its ON/OFF counts",
                  "OFF->ON pairs: OFF/ON pairs of one pixel within 50 ms, against each pixel's ON stream shifted "
                  "in time (polarity_pairs check; 200 resamples)",
                  "IEI: same-pixel inter-event intervals within the window; the model's median and CV are those "
                  "of the fitted model's interval distribution seen within the window (the KS test's CDF)"],
        "windows": rows,
    }
    args.out.write_text(json.dumps(_jsonable(out), indent=1) + "\n", encoding="utf-8")
    print(table(rows))
    print(f"\nwrote {args.out} ({out['runtime_s']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
