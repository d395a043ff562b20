"""Throughput of ``evnoise make-dataset``: pairs per second at 1280x720 -> 640x360 (2x2 binning).

    python benchmarks/bench_dataset.py --quick          # standalone: prints a markdown section
    python benchmarks/bench_dataset.py --tiny --out /tmp/dataset.md

``benchmarks/run.py`` calls :func:`bench_dataset` for its report. Source images are 8-bit PNG
dead-leaves scenes at 1280x720 written to a temporary folder beforehand (not timed); each job
makes a complete dataset (one 1 s window per image, default options) into a fresh folder, so
the wall time includes starting the worker processes. Timings are medians of repeated jobs
with the min-max range; the per-phase shares come from the generator's own clocks (summed over
workers) and the compression cost from the same job without compression.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SIZES = {"tiny": dict(scale=0.02, repeats=1), "quick": dict(scale=0.25, repeats=3), "full": dict(scale=1.0, repeats=5)}
SENSOR = (720, 1280)
PAIRS_FULL = 64  # source images (one pair each) at scale 1


def _write_sources(folder: Path, n: int) -> None:
    from PIL import Image

    from evnoise.generators import dead_leaves

    for k in range(n):
        img = dead_leaves(SENSOR, 1000 + k)
        Image.fromarray(np.round(img * 255).astype(np.uint8)).save(folder / f"scene{k:04d}.png")


def _cpu_seconds() -> float:
    """CPU time of this process and of its finished child processes (the pool's workers)."""
    total = time.process_time()
    try:
        import resource

        r = resource.getrusage(resource.RUSAGE_CHILDREN)
        total += r.ru_utime + r.ru_stime
    except ImportError:  # pragma: no cover - not POSIX
        pass
    return total


def _job(sources, config, workers, tmp: Path):
    """Run one complete job into a fresh folder; returns (wall seconds, CPU seconds, result, bytes of its shards)."""
    from evnoise.generators import make_dataset

    out = tmp / "ds"
    shutil.rmtree(out, ignore_errors=True)
    cpu = _cpu_seconds()
    t0 = time.perf_counter()
    result = make_dataset(sources, out, config, workers=workers)
    wall = time.perf_counter() - t0
    cpu = _cpu_seconds() - cpu
    size = sum(p.stat().st_size for p in out.rglob("*.h5"))
    shutil.rmtree(out, ignore_errors=True)
    return wall, cpu, result, size


def _stats(values):
    return float(np.median(values)), float(np.min(values)), float(np.max(values))


def _rate(n, walls):
    med, lo, hi = _stats(walls)
    return f"{n / med:.1f} ({n / hi:.1f}–{n / lo:.1f})"


def bench_dataset(size: dict, out_dir: Path, report: list) -> None:
    """Append the make-dataset throughput section to ``report`` (markdown lines).

    Parameters
    ----------
    size : dict
        ``scale`` in (0, 1] (the number of pairs per job is ``64 * scale``, at least 4) and
        ``repeats`` (jobs per configuration; medians with min-max).
    out_dir : pathlib.Path
        The report's folder (nothing is written there; data goes to a temporary folder).
    report : list of str
        Markdown lines, appended to.
    """
    import evnoise as ev
    from evnoise.generators import DeadLeaves, PairConfig

    n = max(4, round(PAIRS_FULL * size["scale"]))
    repeats = max(1, int(size["repeats"]))
    load_before = os.getloadavg() if hasattr(os, "getloadavg") else None
    params = ev.load_preset("evk3-hd")
    base = PairConfig(sensor_shape=SENSOR, windows_s=(1.0,), seed=1, shard_size=max(1, n // 8), params=params)
    rows, phases = [], {}
    with tempfile.TemporaryDirectory(prefix="evnoise-bench-") as tmp_name:
        tmp = Path(tmp_name)
        src = tmp / "scenes"
        src.mkdir()
        _write_sources(src, n)
        # warm-up (Numba cache loading, closed-form tables) outside the timings
        _job(src, base.replace(shard_size=n), 1, tmp)
        # start-up of a job: one pair per worker (one shard each)
        few = {}
        for workers in (1, 2):
            few[workers] = tmp / f"few{workers}"
            few[workers].mkdir()
            for p in sorted(src.iterdir())[:workers]:
                shutil.copy(p, few[workers] / p.name)
        configs = [(1, "gzip"), (2, "gzip"), (1, "lzf"), (2, "lzf"), (1, None)]
        startup = {1: [], 2: []}
        walls = {c: [] for c in configs}
        cpus = {c: [] for c in configs}
        timings = {c: {} for c in configs}
        sizes = {}
        # configurations interleaved within each repeat, so that changes of the machine's load
        # during the benchmark affect all of them alike
        for _ in range(repeats):
            for workers in (1, 2):
                startup[workers].append(_job(few[workers], base.replace(shard_size=1), workers, tmp)[0])
            for workers, comp in configs:
                wall, cpu, result, sizes[comp] = _job(src, base.replace(compression=comp), workers, tmp)
                walls[(workers, comp)].append(wall)
                cpus[(workers, comp)].append(cpu)
                for k, v in result.timings.items():
                    timings[(workers, comp)].setdefault(k, []).append(v)
        startup = {w: float(np.median(v)) for w, v in startup.items()}
        for workers, comp in configs:
            phase = {k: float(np.median(v)) for k, v in timings[(workers, comp)].items()}
            phases[(workers, comp)] = phase
            med = float(np.median(walls[(workers, comp)]))
            # marginal rate: the job's pairs beyond one per worker, over the time beyond the start-up job
            marginal = ((n - workers) / (med - startup[workers])
                        if med > startup[workers] and n - workers >= 8 else None)
            cpu_rate = n / float(np.median(cpus[(workers, comp)]))
            default = " (default)" if comp == base.compression else ""
            rows.append(f"| {workers} | {comp or 'none'}{default} | {_rate(n, walls[(workers, comp)])} | "
                        f"{'–' if marginal is None else f'{marginal:.1f}'} | {med:.2f} s | {cpu_rate:.1f} | "
                        f"{1000 * sum(phase.values()) / n:.0f} ms | {sizes[comp] / n / 1e6:.2f} MB |")
        # other paths, one job each (for orientation, not repeated)
        extra = []
        wall, _, result, _ = _job(DeadLeaves(n), base, 1, tmp)
        extra.append(f"| procedural dead leaves (made at 1280×720 in the worker), 1 worker, {base.compression} | "
                     f"{n / wall:.1f} | {result.sampler} |")
        k_small = max(2, n // 8)
        one = tmp / "one"
        one.mkdir()
        for p in sorted(src.iterdir())[:k_small]:
            shutil.copy(p, one / p.name)
        wall, _, result, _ = _job(one, base.replace(mode="events"), 1, tmp)
        extra.append(f"| `--mode events` (simulate_events + count_events), 1 worker | {k_small / wall:.2f} | "
                     f"{result.sampler} |")
        wall, _, result, _ = _job(one, base.replace(params=params.replace(refractory_s=1e-3)), 1, tmp)
        extra.append(f"| refractory period 1 ms (general sampler), 1 worker | {k_small / wall:.2f} | "
                     f"{result.sampler} |")
        if size["scale"] >= 0.25:
            single = tmp / "single"
            single.mkdir()
            shutil.copy(sorted(src.iterdir())[0], single)
            wall, _, result, _ = _job(single, base.replace(params=params.replace(eps_sigma=0.03)), 1, tmp)
            extra.append(f"| threshold mismatch eps_sigma = 0.03 (general sampler), 1 worker | {1 / wall:.3f} | "
                         f"{result.sampler} |")
    load_after = os.getloadavg() if hasattr(os, "getloadavg") else None
    ph = phases[(1, "gzip")]
    ph_none = phases[(1, None)]
    total = sum(ph.values())
    compression = max(0.0, ph["write"] - ph_none["write"])
    shares = [
        ("read + decode + fit the source image", ph["scene"]),
        ("illuminance levels + display image (crop, quantise, 2×2 mean, sRGB)", ph["illuminance"]),
        ("sampling the counts (direct trial sampler, incl. 2×2 binning)", ph["sampling"]),
        ("HDF5 write without compression (I/O)", ph["write"] - compression),
        ("gzip-1 + shuffle compression", compression),
        ("SHA-256 of the shard", ph.get("checksum", 0.0)),
    ]
    lines = [
        "## make-dataset throughput (1280×720 → 640×360 pairs)",
        "",
        f"{n} source PNGs (8-bit dead-leaves scenes, 1280×720), one 1 s window each, preset evk3-hd, 2×2 binning, "
        f"{max(1, n // 8)} pairs per shard; each job makes a complete dataset in a fresh folder (worker start-up "
        f"included). Median of {repeats} job(s), min–max in brackets. Load average before/after: "
        f"{_fmt_load(load_before)} / {_fmt_load(load_after)} on {os.cpu_count()} cores (a shared machine: "
        "other processes compete for the cores, so 2 workers cannot double the rate here).",
        "",
        "| workers | compression | pairs/s (job) | pairs/s (marginal) | job wall time | "
        "pairs per CPU-second | generator time per pair (summed over workers) | shard size per pair |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"*pairs/s (job)*: pairs / wall time of the whole job, start-up included. *Marginal*: the pairs beyond "
        f"one per worker over the time beyond a job of one pair per worker (start-up: "
        f"{startup[1]:.2f} s with 1 worker, {startup[2]:.2f} s with 2 spawned worker processes, which import "
        "NumPy, h5py and Numba and load the compiled kernels); this is the rate of a large job. "
        "*Pairs per CPU-second*: the job's pairs over the CPU time it used (this process and its worker "
        "processes, start-up included), which the other load on the machine does not inflate: with the "
        "machine to itself, a job cannot run faster than this times the number of busy cores. The default "
        "compression is LZF: the shards' reader is h5py (evnoise's training and evaluation), which always "
        "includes the LZF filter, so the files' readers do not care, and it is the fastest of the compressed "
        "choices; gzip remains for shards that tools without that filter must read.",
        "",
        "Where the time goes (1 worker, gzip; share of the generator's own clocks, "
        f"{1000 * total / n:.0f} ms per pair):",
        "",
        "| phase | ms per pair | share |",
        "|---|---|---|",
        *[f"| {name} | {1000 * t / n:.1f} | {t / total:.0%} |" for name, t in shares],
        "",
        "Other paths (one job each, pairs/s):",
        "",
        "| path | pairs/s | sampler |",
        "|---|---|---|",
        *extra,
        "",
    ]
    report.extend(lines)


def _fmt_load(load):
    return "n/a" if load is None else "/".join(f"{x:.1f}" for x in load)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--quick", action="store_true", help="fewer pairs and repeats")
    group.add_argument("--tiny", action="store_true", help="smoke test")
    parser.add_argument("--out", type=Path, help="also write the section to this markdown file")
    args = parser.parse_args(argv)
    size = SIZES["tiny" if args.tiny else "quick" if args.quick else "full"]
    report: list = []
    bench_dataset(size, Path(args.out).parent if args.out else Path("."), report)
    text = "\n".join(report) + "\n"
    print(text)
    if args.out:
        Path(args.out).write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
