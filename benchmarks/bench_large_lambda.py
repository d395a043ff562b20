"""``event_probability`` at large lam (1e3-1e6): seconds per 1e6 values and error, per decade.

    python benchmarks/bench_large_lambda.py [--n 200000] [--label after]

lam log-uniform in each decade, ``bias = 1.7``, two thresholds: ``eps = 0.904`` (the Noise2Image
EVK3-HD ON value; p underflows to 0 above lam ~ 5e3) and ``eps = 0.3`` (p representable up to lam ~ 1e5).
Error: the largest relative difference from the exact windowed sum evaluated value by value (scalar
kernel) on 2,000 of the values, where that is > 1e-300, and whether both agree on which values are 0.
Both cores; median of 3 timings after a warm-up on the same decade. Prints markdown table rows.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200_000)
    ap.add_argument("--label", default="")
    args = ap.parse_args(argv)
    import evnoise as ev
    from evnoise._kernels.poisson import log_event_probability_exact

    rng = np.random.default_rng(0)
    for eps in (0.904, 0.3):
        for lo in (1e3, 1e4, 1e5):
            lam = np.exp(rng.uniform(math.log(lo), math.log(10 * lo), args.n))
            ev.event_probability(lam[: args.n // 10], eps, 1.7)  # warm-up: tables of this decade
            times = []
            for _ in range(3):
                t0 = time.perf_counter()
                p = ev.event_probability(lam, eps, 1.7)
                times.append(time.perf_counter() - t0)
            sub = rng.choice(args.n, 2000, replace=False)
            ref = np.exp([log_event_probability_exact(x, math.expm1(eps), 1.7) for x in lam[sub]])
            rep = ref > 1e-300
            err = float(np.max(np.abs(p[sub][rep] / ref[rep] - 1.0))) if rep.any() else float("nan")
            zeros = bool(np.array_equal(p[sub] == 0, ref == 0))
            print(f"| {args.label} | {eps} | {lo:.0e}–{10 * lo:.0e} | {np.median(times) / args.n * 1e6:.3g} | "
                  f"{np.count_nonzero(p) / args.n:.0%} | {err:.1e} | {'yes' if zeros else 'NO'} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
