"""Certified large-lam panels (issue 33, item 3): values/s, error and build time per lam band and eps.

    python benchmarks/bench_certified.py [--n 200000] [--n-before 10000] [--bias 1.7]

For each eps: a fresh table (cache in a temporary folder) is built for lam in 1e3-1e6 and timed (the
one-off build; "cert" is the part spent certifying panels). Then ``log_event_probability`` on ``n``
values log-uniform in each band (median of 3, both cores, after the build) and the same with the
certified panels switched off (``before``: the exact sum in direct units, on ``n_before`` values, median of 3
after a warm-up; in 1e3-1e4 both are the same log-spaced table, so the two columns differ only by noise and n).
Error: the largest ``|log p - log p_exact|`` (= relative error of p) against the scalar exact sum on
2,000 of the values, the largest proven part of the panels' bound (``par[6]``) and the largest whole
bound (``par[6] + par[7]``, which adds the exact sum's own ``128 u |log p|`` carried through the nodes).
Prints markdown table rows.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time

import numpy as np


def _rate(f, lam, repeat=3):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f(lam)
        times.append(time.perf_counter() - t0)
    return lam.size / float(np.median(times))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200_000)
    ap.add_argument("--n-before", type=int, default=10_000)
    ap.add_argument("--bias", type=float, default=1.7)
    ap.add_argument("--eps", type=float, nargs="*", default=[0.05, 0.1, 0.2, 0.5, 1.0, 2.0])
    ap.add_argument("--cache", default=None, help="cache folder (default: a new temporary one, so tables are built)")
    args = ap.parse_args(argv)
    os.environ["EVNOISE_CACHE"] = args.cache or tempfile.mkdtemp(prefix="evnoise-bench-cert-")
    from evnoise import model
    from evnoise._kernels import chebyshev
    from evnoise._kernels.poisson import log_event_probability_exact

    # the panels themselves are measured: a library call certifies a unit only when it asks for
    # chebyshev.CERT_MIN_VALUES values in it (fewer are summed exactly), which the error samples below are not
    chebyshev.CERT_MIN_VALUES = 1
    b = args.bias
    rng = np.random.default_rng(0)
    print("| eps | lam band | values/s after | values/s before | speed-up | max abs err log p (vs exact sum) "
          "| max err / (u abs(log p)) | max proven bound | max whole bound | certified panels |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    builds = []
    for eps in args.eps:
        c = math.expm1(eps)
        table = chebyshev.LogPTable(c, b, *model._TABLE_UNITS)
        t0 = time.perf_counter()
        table.ensure(range(6, 14))  # the log-spaced panels (units left to the exact sum found)
        t_tab = time.perf_counter() - t0
        t0 = time.perf_counter()
        table.evaluate(np.geomspace(1e3, 9.99e5, 4096))  # certification of the units above
        t_cert = time.perf_counter() - t0
        old = chebyshev.LogPTable(c, b, *model._TABLE_UNITS)
        saved = chebyshev.CERT_LAST_UNIT
        panels = table.certified_panels()
        n_panels = sum(len(v) for v in panels.values())
        n_fallback = sum(cf is None for v in panels.values() for cf, _ in v)
        builds.append((eps, t_tab + t_cert, t_cert, n_panels, n_fallback))
        for lo in (1e3, 1e4, 1e5):
            lam = np.exp(rng.uniform(math.log(lo), math.log(10 * lo), args.n))
            after = _rate(table.evaluate, lam)
            chebyshev.CERT_LAST_UNIT = 0
            try:
                old.evaluate(lam[: args.n_before])  # warm-up: builds this band's log-spaced panels
                before = _rate(old.evaluate, lam[: args.n_before])
            finally:
                chebyshev.CERT_LAST_UNIT = saved
            sub = rng.choice(args.n, 2000, replace=False)
            got = table.evaluate(lam[sub])
            ref = np.array([log_event_probability_exact(x, c, b) for x in lam[sub]])
            err = float(np.max(np.abs(got - ref)))
            ulps = float(np.max(np.abs(got - ref) / (2.0**-53 * np.maximum(np.abs(ref), 1.0))))
            proven = whole = 0.0
            for u, v in panels.items():
                for cf, par in v:
                    if cf is not None and par[1] > lo and par[0] < 10 * lo:
                        proven = max(proven, par[6])
                        whole = max(whole, par[6] + par[7])
            inband = sum(1 for v in panels.values() for cf, par in v if par[1] > lo and par[0] < 10 * lo)
            bounds = f"{proven:.1e} | {whole:.1e}" if inband else "– | –"
            print(f"| {eps} | {lo:.0e}–{10 * lo:.0e} | {after:.3g} | {before:.3g} | {after / before:.1f}x | "
                  f"{err:.1e} | {ulps:.0f} | {bounds} | {inband} |", flush=True)
    print()
    print(f"| eps | build s (table for 1e3–1.2e6, bias {b}) | of which certification s | certified panels "
          "| fallback panels |")
    print("|---|---|---|---|---|")
    for eps, t, tc, n_p, n_f in builds:
        print(f"| {eps} | {t:.1f} | {tc:.1f} | {n_p} | {n_f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
