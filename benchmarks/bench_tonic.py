"""tonic's ``UniformNoise`` against evnoise's ``PhotonNoise`` per N-MNIST-sized sample (issue 31).

Usage::

    python benchmarks/bench_tonic.py [--calls 400] [--items 2000] [--report benchmarks/REPORT.md]

The sample is synthetic (no dataset is downloaded): 4,325 events on N-MNIST's 34x34 sensor over
310 ms, the size of a real N-MNIST sample. Timed: (1) a transform called in this process,
median over ``--calls`` calls (after a warm-up call, so Numba's compilation is excluded);
(2) a torch ``DataLoader`` with 2 forked workers over ``--items`` items, wall time per item, with
the transform called once in the parent first (the case that crashed before issue 31). The error
column is what makes the speed comparable: the mean number of noise events ``PhotonNoise`` added
per sample against the closed form (``expected_rate`` x pixels x span), in standard errors.
Nothing here is a test: timings are never asserted.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import multiprocessing
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import evnoise as ev
from evnoise.plugins.tonic import PhotonNoise

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import cpu_name  # noqa: E402  (the benchmarks folder, put on the path above)

SENSOR = (34, 34, 2)
N_EVENTS, SPAN_US = 4325, 310_000
PRESET, LUX = "evk3-hd", 2.0
DTYPE = np.dtype([("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")])  # tonic's NMNIST dtype


def sample(seed: int = 0) -> np.ndarray:
    """A stand-in N-MNIST sample: time-sorted events spanning exactly ``SPAN_US``."""
    g = np.random.default_rng(seed)
    events = np.zeros(N_EVENTS, dtype=DTYPE)
    events["x"], events["y"] = g.integers(0, 34, N_EVENTS), g.integers(0, 34, N_EVENTS)
    events["t"] = np.sort(g.integers(0, SPAN_US + 1, N_EVENTS))
    events["t"][[0, -1]] = 0, SPAN_US
    events["p"] = g.integers(0, 2, N_EVENTS)
    return events


def per_call(transform, events, calls: int) -> tuple[float, float, float]:
    transform(events)  # warm-up (compilation)
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        transform(events)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), min(times), max(times)


class _Items:
    """A map-style dataset of ``n`` copies of one sample, passed through ``transform``."""

    def __init__(self, events, transform, n):
        self.events, self.transform, self.n = events, transform, n

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        return self.transform(self.events).size


def through_dataloader(transform, events, items: int) -> float:
    import torch

    loader = torch.utils.data.DataLoader(_Items(events, transform, items), batch_size=None, num_workers=2,
                                         multiprocessing_context=multiprocessing.get_context("fork"))
    t0 = time.perf_counter()
    total = sum(int(n) for n in loader)
    assert total >= items * N_EVENTS
    return (time.perf_counter() - t0) / items


def added_events_error(events, calls: int) -> tuple[float, float, float]:
    """Mean noise events added per sample (fresh noise each call), its standard error, and the closed form."""
    noise = PhotonNoise(SENSOR, PRESET, lux=LUX, rng=np.random.default_rng(11))
    added = np.array([noise(events).size - events.size for _ in range(calls)], dtype=float)
    rate = ev.expected_rate(np.full((34, 34), LUX), ev.load_preset(PRESET)).sum()  # events/s, ON + OFF
    return added.mean(), added.std(ddof=1) / np.sqrt(calls), rate * SPAN_US * 1e-6


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=400)
    ap.add_argument("--items", type=int, default=2000)
    ap.add_argument("--report", type=Path, help="append the section to this markdown report")
    args = ap.parse_args(argv)
    import tonic

    events = sample()
    uniform = tonic.transforms.UniformNoise(sensor_size=SENSOR, n=455)  # about PhotonNoise's count at 2 lux
    seeded = PhotonNoise(SENSOR, PRESET, lux=LUX, rng=0)
    drawn = PhotonNoise(SENSOR, PRESET, lux=LUX, rng=np.random.default_rng(0))
    rows = []
    mean, se, expected = added_events_error(events, args.calls)
    z = (mean - expected) / se
    for name, tr, err in (("tonic UniformNoise(n=455)", uniform, "not a noise model"),
                          ("PhotonNoise, int seed", seeded, f"{mean:.1f} ± {se:.1f} added vs {expected:.1f} exact "
                                                            f"({z:+.1f} SE)"),
                          ("PhotonNoise, Generator", drawn, "same law as above")):
        med, lo, hi = per_call(tr, events, args.calls)
        seeded(events)  # the parent has used the transform (and Numba) before the workers fork
        loader = through_dataloader(tr, events, args.items)
        rows.append((name, med, lo, hi, loader, err))
    base = rows[0][1]
    lines = [
        "## tonic: PhotonNoise against UniformNoise per N-MNIST sample (issue 31)",
        "",
        f"Machine: {platform.machine()} {cpu_name()}, {multiprocessing.cpu_count()} cores (shared), "
        f"Python {platform.python_version()}, tonic {tonic.__version__}; {_dt.date.today()}. Command: "
        f"`python benchmarks/bench_tonic.py --calls {args.calls} --items {args.items}`. Sample: {N_EVENTS} events, "
        f"34x34, {SPAN_US / 1000:.0f} ms; preset `{PRESET}` at {LUX} lux. In-process: median (min-max) of "
        f"{args.calls} calls; DataLoader: 2 forked workers, {args.items} items, wall time per item, after a call "
        "in the parent.",
        "",
        "| transform | in-process (ms) | × UniformNoise | DataLoader, 2 workers (ms/item) | error |",
        "|---|---|---|---|---|",
    ]
    for name, med, lo, hi, loader, err in rows:
        lines.append(f"| {name} | {med * 1e3:.2f} ({lo * 1e3:.2f}-{hi * 1e3:.2f}) | {med / base:.1f} | "
                     f"{loader * 1e3:.2f} | {err} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.report:
        with open(args.report, "a", encoding="utf-8") as fh:
            fh.write("\n" + text)


if __name__ == "__main__":
    main()
