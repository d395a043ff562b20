"""Fit reset memory to the real quiet windows' event times, with and without memory.

``python -m evnoise.calibration.scripts.memory_fit [--all]`` (about 20 s for the eDVS128 window; ``--all``: every
window of ``quiet_segments.json``, several minutes each).

The exact likelihood of the memory chain (:mod:`evnoise.calibration.quiet.memory`) on the ``dvs128`` preset's
photon noise (thresholds, bias, trial rate; its dead time is 0) with a spread Poisson leak, against the same chain
without memory (``k = 0``): the likelihood-ratio test says whether the window's events carry memory. Also the
window's polarity alternation against the memoryless expectation given each pixel's counts
(the window checks' ``same_pixel`` numbers, :mod:`evnoise.calibration.quiet.checks`), with an exact binomial
test against the memoryless share. Writes
``calibration/memory-fit.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "memory-fit.json"
#: the window whose events pair (calibration/README.md, "Timing on the real quiet windows")
DEFAULT = "jaer_colleenpamchen/DVS128-2017-03-21-short.aedat"


def analyse(data: Path, rel: str, seg: dict, base) -> dict:
    from scipy.stats import binomtest

    from ..quiet.memory import fit_memory
    from ..quiet.window import quiet_window

    t0 = time.time()
    w = quiet_window(data / rel, seg["t_from_us"] * 1e-6, seg["t_to_us"] * 1e-6, checks=True)
    w.source = rel
    fit = fit_memory([w], base)
    pairs = next(c for c in w.checks if c["check"] == "polarity_pairs")
    same = pairs.get("same_pixel") or next(c["same_pixel"] for c in w.checks if "same_pixel" in c)
    n, opposite = int(same["transitions"]), int(same["opposite"])
    expected = same["memoryless_mean"] / n if n else math.nan
    test = binomtest(opposite, n, expected).pvalue if n else math.nan
    return {"file": rel, "from_s": seg["from_s"], "to_s": seg["to_s"], "events": int(w.counts.sum()),
            "doublets_merged": int(w.doublets), "values": fit.values, "std_error": fit.std_error,
            "log_likelihood": fit.log_likelihood, "memoryless": fit.memoryless,
            "memoryless_log_likelihood": fit.memoryless_log_likelihood, "lr": fit.lr, "p_value": fit.p_value,
            "alternation": {"transitions": n, "opposite": opposite, "memoryless_share": expected,
                            "binomial_p": test},
            "seconds": round(time.time() - t0, 1), "summary": fit.summary()}


def main(argv=None) -> int:
    import evnoise as ev

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=HERE.parent.parent / "shared" / "data" / "realdata",
                    help="the real-data folder (with quiet_segments.json)")
    ap.add_argument("--out", type=Path, default=OUT, help="JSON written (default calibration/memory-fit.json)")
    ap.add_argument("--all", action="store_true", help="every window of quiet_segments.json, not only the eDVS128 one")
    args = ap.parse_args(argv)
    data = args.data if args.data.exists() else HERE.parent.parent.parent / "shared" / "data" / "realdata"
    segments = json.loads((data / "quiet_segments.json").read_text())["segments"]
    base = ev.load_preset("dvs128")
    rows = []
    for rel, segs in segments.items():
        if not args.all and rel != DEFAULT:
            continue
        for seg in segs:
            row = analyse(data, rel, seg, base)
            print(row["summary"])
            a = row["alternation"]
            print(f"  alternation {a['opposite']}/{a['transitions']} opposite, memoryless {a['memoryless_share']:.3f}, "
                  f"binomial p = {a['binomial_p']:.3g}  ({row['seconds']} s)")
            rows.append(row)
    from .. import write_text_atomic

    write_text_atomic(args.out, json.dumps({"base": "dvs128", "windows": rows}, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
