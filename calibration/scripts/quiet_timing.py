"""Timing of the real quiet windows against the quiet-window fits, before and after fitting timing, window by window.

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

Three fits per window (issue 32 section 2): *before*, the count fit (``timing="off"``: the per-pixel count
histograms only, as the quiet fit was before it fitted timing); *after*, the timing fit (``timing="auto"``:
the pixels' event times, :mod:`evnoise.calibration.quiet.likelihood`) with one regularity for ordinary and
hot pixels; *after, own hot regularity* (``hot_regularity="on"``), which the simulators run as the preset's
``hot_pixel_regularity``, started from the *after* fit too (``fit_quiet(start=...)``: it holds that model, so it
cannot end below it). For each: its log-likelihood *of the event times* (the count fit's values
evaluated under the timing likelihood, so all three compare), the count p-values, the timing tests and
issue 32's done-when criteria (opposite share within 5 points of the model's, OFF->ON pair excess within
30 % of the model's x1, IEI median within 30 %, IEI KS p >= 1e-3 where there are >= 100 intervals).
The two after fits' presets (:meth:`QuietFit.to_params` on the ``dvs128`` photon-noise base) are simulated on
the window (``evnoise.simulate_events``, 4 replicas) and their counts and intervals set beside the real ones.

Writes the JSON (``--out``) and prints markdown tables. The recordings are third-party data: they are
read, never copied. Readout doublets (:data:`evnoise.calibration.quiet.window.DOUBLET_US`) are merged, and
oscillating pixels (:func:`evnoise.calibration.quiet.window.oscillating_pixels`: one DVS128 pixel fires ON every
185 ms in two windows) are left out of the window (``drop_oscillating``), as the model has no term for them.
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

from ..quiet.checks import failed_checks
from ..quiet.fit import event_time_log_likelihood, fit_model
from ..quiet.goodness import compare_intervals

HERE = Path(__file__).resolve().parents[1]  # calibration/: the scripts' outputs are kept there
OUT = HERE / "quiet-timing.json"


def model_interval_stats(fit) -> dict:
    """Median, mean and CV of the fitted model's same-pixel intervals seen within the window (the censored
    distribution the KS test compares with), by quadrature of its CDF on [0, T]."""
    from ..quiet.goodness import interval_cdf

    model, groups = fit_model(fit)
    w = groups[0].windows[0]
    x = np.linspace(0.0, w.duration_s, 20001)
    cdf = interval_cdf(x, fit.values, model, 0, groups[0], 0)
    surv = 1.0 - cdf
    mean = float(np.trapezoid(surv, x))
    second = float(np.trapezoid(2.0 * x * surv, x))
    var = max(second - mean * mean, 0.0)
    median = float(np.interp(0.5, cdf, x)) if cdf[-1] >= 0.5 else math.nan
    return {"median_s": median, "mean_s": mean, "cv": math.sqrt(var) / mean if mean > 0 else math.nan}


#: The fits of each window. The timing fits keep every term (spread, hot pixels, regularity): their
#: likelihood-ratio tests are the comparison of the two timing fits and of the before fit's event-time
#: likelihood, and leaving out the term-by-term refits keeps the script's time to minutes per window.
VARIANTS = {"before": dict(timing="off"),
            "after": dict(timing="auto", spread="on", hot="on", regularity="on"),
            "after_hot_regularity": dict(timing="auto", spread="on", hot="on", regularity="on", hot_regularity="on")}
#: The fit each variant also starts from (``fit_quiet(start=...)``): a fit of a model it holds.
STARTED_FROM = {"after_hot_regularity": "after"}


def _fit_row(fit, w, same, pairs) -> dict:
    """One fit's numbers and issue 32's done-when criteria (module doc) on its window."""
    from ..quiet.checks import MIN_INTERVALS

    trans = next((t for t in fit.timing if t["test"] == "polarity_transitions"), {})
    ks = next((t for t in fit.timing if t["test"] == "intervals"), {})
    xs = np.asarray(same["intervals_s"] if same else [], dtype=np.float64)
    n_trans = int(same["transitions"]) if same else 0
    model_iei = model_interval_stats(fit)
    model_iei["median_s_timing_test"] = ks.get("model_median_s", math.nan)
    gof = {g["polarity"]: g for g in fit.goodness}
    real_median = float(np.median(xs)) if xs.size else math.nan
    opp = same["opposite"] / n_trans if n_trans else math.nan
    opp_model = same["memoryless_mean"] / n_trans if n_trans else math.nan
    excess = pairs["statistic"] / pairs["null_mean"] if pairs["null_mean"] > 0 else math.nan
    n = int(same["n_intervals"]) if same else 0
    crit = {
        "alternation_within_5_points": (abs(opp - opp_model) <= 0.05) if n_trans else None,
        # the memoryless model's pairs are those of the shifted streams: excess x1; testable with >= 5 pairs
        "pair_excess_within_30pct": (abs(excess - 1.0) <= 0.3)
        if (pairs["statistic"] + pairs["null_mean"] >= 5 and math.isfinite(excess)) else None,
        "iei_median_within_30pct": (abs(model_iei["median_s"] / real_median - 1.0) <= 0.3)
        if (n >= 1 and math.isfinite(model_iei["median_s"]) and real_median > 0) else None,
        "iei_ks_not_rejected": (ks.get("p_value", math.nan) >= 1e-3) if n >= MIN_INTERVALS else None,
        "counts_not_rejected": all(not (math.isfinite(g["p_value"]) and g["p_value"] < 1e-3) for g in fit.goodness),
    }
    return {
        "log_likelihood_fitted": fit.log_likelihood, "log_likelihood_event_times": event_time_log_likelihood(fit),
        "alternation": {"model_share": opp_model, "p_value": trans.get("p_value", math.nan),
                        "testable": bool(trans.get("testable", False))},
        "iei": {"model": model_iei, "ks_p_value": ks.get("p_value", math.nan),
                "ks_testable": bool(ks.get("testable", False)), "detail": ks.get("detail", "")},
        "count_goodness": {p: {"p_value": g["p_value"], "chi2": g["chi2"], "dof": g["dof"], "events": g["events"],
                               "expected_events": g["expected_events"]} for p, g in gof.items()},
        "criteria": crit, "fit_status": fit.fit_status, "rejections": list(fit.rejections),
        "values": {k: float(v) for k, v in fit.values.items()}, "std_error": {
            k: (None if v is None else float(v)) for k, v in fit.std_error.items()},
        "parameter_status": dict(fit.status), "tests": fit.tests,
    }


def analyse(data: Path, rel: str, seg: dict, *, simulate: bool = True) -> dict:
    from ..quiet.fit import fit_quiet
    from ..quiet.window import quiet_window

    w = quiet_window(data / rel, seg["t_from_us"] * 1e-6, seg["t_to_us"] * 1e-6, checks=True,
                     drop_oscillating=True)
    w.source = rel
    pairs = next(c for c in w.checks if c["check"] == "polarity_pairs")
    same = pairs.get("same_pixel") or next((c["same_pixel"] for c in w.checks if "same_pixel" in c), None)
    xs = np.asarray(same["intervals_s"] if same else [], dtype=np.float64)
    n_trans = int(same["transitions"]) if same else 0
    real_iei = {"n": int(same["n_intervals"]) if same else 0,
                "median_s": float(np.median(xs)) if xs.size else math.nan,
                "cv": float(np.std(xs, ddof=1) / np.mean(xs)) if xs.size > 1 and np.mean(xs) > 0 else math.nan,
                "stored_order_statistics": int(xs.size)}
    fits = {}
    for name, opts in VARIANTS.items():
        fits[name] = fit_quiet([w], **opts, start=fits[STARTED_FROM[name]] if name in STARTED_FROM else None)
    row = {
        "file": rel, "from_s": seg["from_s"], "to_s": seg["to_s"], "t_from_us": int(seg["t_from_us"]),
        "t_to_us": int(seg["t_to_us"]), "content": seg.get("content", ""), "doublets_merged": int(w.doublets),
        "oscillating_pixels_left_out": w.oscillating,
        "events": int(w.counts.sum()), "on_events": int(w.counts[0].sum()), "off_events": int(w.counts[1].sum()),
        "alternation": {"transitions": n_trans, "opposite": int(same["opposite"]) if same else 0,
                        "opposite_share": same["opposite"] / n_trans if n_trans else math.nan,
                        "memoryless_share": same["memoryless_mean"] / n_trans if n_trans else math.nan},
        "off_on_pairs_50ms": {"observed": int(pairs["statistic"]), "shifted_mean": float(pairs["null_mean"]),
                              "shifted_sd": float(pairs["null_sd"]), "p_value": float(pairs["p_value"]),
                              "testable": bool(pairs.get("testable", True)), "detail": pairs.get("detail", "")},
        "iei_real": real_iei,
        "checks": {c["check"]: {"p_value": c["p_value"], "failed": bool(c in failed_checks(w.checks))}
                   for c in w.checks},
        "fits": {name: _fit_row(f, w, same, pairs) for name, f in fits.items()},
    }
    if simulate:
        from .fit_dvs128 import base_params

        for key, name in (("after_preset_simulated", "after"), ("after_hot_preset_simulated", "after_hot_regularity")):
            row[key] = compare_intervals(fits[name].to_params(base_params()), w, seed=0, real_intervals=xs)
    return row


def _analyse_args(job) -> dict:
    data, rel, seg = job
    t = time.perf_counter()
    row = analyse(data, rel, seg)
    print(f"  {rel} {seg['from_s']}-{seg['to_s']} s: {row['fits']['after']['fit_status']} "
          f"({time.perf_counter() - t:.1f} s)", file=sys.stderr, flush=True)
    return row


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


def _mark(x) -> str:
    """A criterion's verdict: yes, no, or – (not testable: None, or NaN read back from the JSON)."""
    return ("yes" if x else "**no**") if isinstance(x, bool) else "–"


def criteria_table(rows) -> str:
    """Issue 32's done-when criteria per window: before (count fit) / after (timing fit) / after with its own
    hot regularity."""
    head = ("| window | IEI n | IEI median real / before / after / after-hot (s) | IEI KS p before / after / after-hot "
            "| counts p (ON) before / after / after-hot | log L(event times) before / after / after-hot "
            "| done-when after: alternation, pairs, median, KS, counts | done-when after-hot |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        f = r["fits"]
        names = ("before", "after", "after_hot_regularity")
        name = Path(r["file"]).name.replace(".aedat", "")
        keys = ("alternation_within_5_points", "pair_excess_within_30pct", "iei_median_within_30pct",
                "iei_ks_not_rejected", "counts_not_rejected")
        lines.append(
            f"| {name} {r['from_s']:g}–{r['to_s']:g} s | {r['iei_real']['n']} "
            f"| {_f(r['iei_real']['median_s'], '.3f')} / "
            + " / ".join(_f(f[k]["iei"]["model"]["median_s"], ".3f") for k in names)
            + " | " + " / ".join(_f(f[k]["iei"]["ks_p_value"], ".2g") for k in names)
            + " | " + " / ".join(_f(f[k]["count_goodness"].get("ON", {}).get("p_value"), ".2g") for k in names)
            # the timing fits' own maximum is already an event-time log-likelihood
            + " | " + " / ".join(_f(f[k]["log_likelihood_event_times" if k == "before" else "log_likelihood_fitted"],
                                    ".1f") for k in names)
            + " | " + " | ".join(", ".join(_mark(f[name]["criteria"][k]) for k in keys)
                                 for name in ("after", "after_hot_regularity")) + " |")
    return "\n".join(lines)


def table(rows) -> str:
    head = ("| window | events (ON/OFF) | opposite share: real / memoryless | OFF→ON pairs ≤ 50 ms: real / shifted "
            "| IEI n | IEI median real / model (s) | IEI CV real / model | count p ON / OFF "
            "| timing p: transitions / KS | fit |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        a, pr = r["alternation"], r["off_on_pairs_50ms"]
        fa = r["fits"]["after"]
        iei = {"real": r["iei_real"], "model": fa["iei"]["model"], "ks_p_value": fa["iei"]["ks_p_value"]}
        g = fa["count_goodness"]
        a = dict(a, p_value=fa["alternation"]["p_value"])
        r = dict(r, rejections=fa["rejections"], fit_status=fa["fit_status"])
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


def simulated_table(rows) -> str:
    """The two after fits' presets simulated on each window against the real events (4 sensors each)."""
    head = ("| window | events real / after / after-hot (per sensor) | IEI median real / after / after-hot (s) "
            "| IEI two-sample KS p after / after-hot |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        sims = [r.get("after_preset_simulated") or {}, r.get("after_hot_preset_simulated") or {}]
        name = Path(r["file"]).name.replace(".aedat", "")
        lines.append(
            f"| {name} {r['from_s']:g}–{r['to_s']:g} s | {r['events']} / "
            + " / ".join(_f((x.get("events_on_per_replica") or math.nan) + (x.get("events_off_per_replica") or 0.0),
                            ".0f") for x in sims)
            + f" | {_f(r['iei_real']['median_s'], '.3f')} / " + " / ".join(_f(x.get("median_s"), ".3f") for x in sims)
            + " | " + " / ".join(_f(x.get("ks_2samp_p_value"), ".2g") for x in sims) + " |")
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


def _write(path, rows, t0, version) -> dict:
    out = {
        "summary": "real quiet windows (quiet_segments.json) against the quiet fits of each window, before (counts) "
                   "and after (event times) fitting timing (issue 32 section 2)",
        "command": "python -m evnoise.calibration.scripts.quiet_timing",
        "date": _dt.date.today().isoformat(), "evnoise_version": version,
        "runtime_s": round(time.perf_counter() - t0, 1),
        "notes": ["opposite share: consecutive events of one pixel opposite in polarity; memoryless: its "
                  "expectation when each pixel's polarities are independent given its ON/OFF counts",
                  "OFF->ON pairs: OFF/ON pairs of one pixel within 50 ms, against each pixel's ON stream shifted "
                  "in time (polarity_pairs check; 200 resamples)",
                  "IEI: same-pixel inter-event intervals within the window; the model's median and CV are those "
                  "of the fitted model's interval distribution seen within the window (the KS test's CDF)",
                  "oscillating pixels (oscillating_pixels_left_out: >= 15 events of one polarity, >= 10 times the "
                  "mean, interval CV < 0.3) are left out of the window before its checks and fits"],
        "windows": rows,
    }
    path.write_text(json.dumps(_jsonable(out), indent=1) + "\n", encoding="utf-8")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=HERE.parent.parent / "shared" / "data" / "realdata",
                    help="the real-data folder (with quiet_segments.json)")
    ap.add_argument("--out", type=Path, default=OUT, help="JSON written (default calibration/quiet-timing.json)")
    ap.add_argument("--jobs", type=int, default=1, help="windows analysed in parallel (processes)")
    args = ap.parse_args(argv)
    if not (args.data / "quiet_segments.json").is_file():
        print(f"skipped: no quiet_segments.json in {args.data} (the real recordings are not here; "
              f"pass --data)", file=sys.stderr)
        return 0

    from evnoise._version import __version__

    segments = json.loads((args.data / "quiet_segments.json").read_text(encoding="utf-8"))["segments"]
    t0 = time.perf_counter()
    todo = [(args.data, rel, seg) for rel, windows in segments.items() for seg in windows]
    order = {(rel, seg["from_s"]): i for i, (_, rel, seg) in enumerate(todo)}
    rows = []

    def done(row):  # each window's row is written as it comes (the whole run takes a while)
        rows.append(row)
        rows.sort(key=lambda r: order[(r["file"], r["from_s"])])
        _write(args.out, rows, t0, __version__)

    if args.jobs > 1:
        from multiprocessing import Pool

        with Pool(args.jobs) as pool:
            for row in pool.imap_unordered(_analyse_args, todo):
                done(row)
    else:
        for job in todo:
            done(_analyse_args(job))
    out = _write(args.out, rows, t0, __version__)
    print(table(rows))
    print()
    print(criteria_table(rows))
    print()
    print(simulated_table(rows))
    print(f"\nwrote {args.out} ({out['runtime_s']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
