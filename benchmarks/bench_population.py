"""Population mean rate with a regular background timer: the fused kernel against the broadcast formula.

    python benchmarks/bench_population.py [--preset dvs128] [--repeats 3] [--threads 2]

What a calibration evaluates hundreds of times: ``evnoise.calibration.population_rate`` on a
15-level table (0.05-50 lux) for a preset with threshold mismatch and a regular leak (``dvs128``:
eps_sigma 0.021, leak_regularity ~1, spread and hot pixels, so every level averages
``regular_rates`` over background nodes x threshold atoms). The reference is the same average
written with NumPy broadcasting over the whole (node, atom) grid (``regular_rates``, the
per-pixel formula), which is what the library did before; the error column is the largest
relative difference between the two. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import math
import platform
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

LUX = np.geomspace(0.05, 50.0, 15)


def broadcast_reference(stats) -> np.ndarray:
    """The population mean of ``stats`` (a ``LevelStats``) by ``regular_rates`` on the whole grid."""
    from evnoise.background import regular_rates

    out = np.empty_like(stats.log_m1)
    for k in range(2):
        for j in range(out.shape[1]):
            p = np.exp(stats.log_p[k][j])[None, :]
            po = np.full_like(p, math.exp(stats.log_m1[1 - k, j]))
            l_k = stats.bg_l[k, :, j][:, None]
            l_o = stats.bg_l[1 - k, :, j][:, None]
            p_on, p_off, l_on, l_off = (p, po, l_k, l_o) if k == 0 else (po, p, l_o, l_k)
            nu = regular_rates(p_on, p_off, l_on, l_off, stats.trial_rate_hz, stats.refractory_s,
                               stats.node_regularity[:, None])[k]  # each node's own (hot pixels: theirs)
            out[k, j] = float(stats.bg_weight @ (nu @ stats.mass[k][j]))
    return out


def median_time(fn, repeats):
    """Median seconds of ``repeats`` calls after a warm-up (``run.timed``), and the last result."""
    from run import timed

    (median, _, _), out = timed(fn, repeats)
    return median, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="dvs128")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="Numba threads (default: all)")
    args = ap.parse_args(argv)
    import numba

    import evnoise as ev
    from evnoise.mismatch import LevelStats

    if args.threads:
        numba.set_num_threads(args.threads)
    params = ev.load_preset(args.preset)
    if not params.regular_background:
        raise SystemExit(f"preset {args.preset} has no regular background")
    lam = params.photons_per_trial(LUX)

    def stats():
        return LevelStats(lam, params, "poisson")

    t_stats, st = median_time(stats, args.repeats)
    t_ref, ref = median_time(lambda: broadcast_reference(st), args.repeats)
    t_new, new = median_time(st.mean_rate, args.repeats)
    pairs = sum(len(st.mass[k][j]) for k in range(2) for j in range(LUX.size)) * st.bg_weight.size
    err = float(np.max(np.abs(new / ref - 1.0)))
    print(f"Machine: {platform.machine()}, {platform.system()}, Python {platform.python_version()}, "
          f"Numba threads {numba.get_num_threads()}; preset {args.preset}, {LUX.size} levels, "
          f"{st.bg_weight.size} background nodes, {pairs:,} (node, atom) pairs; medians of {args.repeats}.\n")
    print("| step | time (s) | ns per pair | max relative difference |")
    print("|---|---|---|---|")
    print(f"| threshold atoms and background nodes (shared) | {t_stats:.3f} | | |")
    print(f"| mean rate, broadcast formula (before) | {t_ref:.3f} | {t_ref / pairs * 1e9:.1f} | reference |")
    print(f"| mean rate, fused kernel (now) | {t_new:.3f} | {t_new / pairs * 1e9:.1f} | {err:.1e} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
