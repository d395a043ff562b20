"""Reconstruction benchmark: the evaluation table and the paper's ablations, with one command.

    python benchmarks/reconstruction.py                 # full run (about 60-90 minutes on 2 cores)
    python benchmarks/reconstruction.py --quick         # smaller data and budgets (about 15 minutes)
    python benchmarks/reconstruction.py --tiny --work /tmp/rb --out /tmp/rb   # smoke run (1-2 minutes)

It builds the datasets with :func:`evnoise.generators.make_dataset` (the API behind
``evnoise make-dataset``), trains every U-Net with a fixed step budget, evaluates it and the
baselines, and writes ``RECONSTRUCTION.md`` plus three PNG figures to ``--out``.

Design (mirrors the Noise2Image paper's: a confined training distribution, a broad test):

* training and in-distribution (ID) test: procedural dead-leaves scenes, split by scene
  (80 / 10 / 10 %); out-of-distribution (OOD) test: the natural photos that installed
  packages ship (scikit-image, matplotlib, ...), never used for training or validation;
* noise model: the shipped ``evk3-hd`` preset, loaded by name when the run starts; two
  variants are written to the work folder: *nominal* (``eps_sigma = 0``) and *mismatch*
  (the shipped ``eps_sigma`` when it is > 0, else :data:`DEFAULT_MISMATCH`); the main table
  uses the variant equal to the shipped preset;
* models: the main one plus the ablations of the paper (window, Table S1; polarity, Table 2)
  on the nominal variant, and the threshold-mismatch cross test (synthetic-to-real gap);
* baselines on the same pairs: (a) the count image, min-max and affine-fit oracle; (b) the
  per-pixel maximum-likelihood inversion, its smoothing chosen on the ID validation split.

Everything random is seeded (``--seed`` for the data, ``--train-seed`` for the networks);
training budgets are step counts, so the numbers do not depend on the machine's load (a
wall-clock cap only guards against a machine far slower than expected, and is reported if
it was hit). Results of finished jobs are cached in the work folder (keyed by every setting
and the preset), so an interrupted run continues where it stopped; ``--fresh`` ignores them.
Nothing is downloaded; nothing here is a test (the slow test suite only runs ``--tiny``).

Why one file of ~1000 lines: it is a script whose parts (datasets, jobs, cache, tables, figures)
only exist to write one report, read top to bottom; nothing imports them.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import inspect
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

WINDOWS = (0.1, 0.25, 0.5, 1.0, 2.0)
MAIN_WINDOW = 1.0
#: Threshold mismatch (standard deviation of eps, in log-intensity units) used for the
#: mismatch ablation when the shipped preset has none.
DEFAULT_MISMATCH = 0.07
SENSOR = (360, 640)  # (H, W): the photos are used near their native resolution
WHITE_LUX = 18.0  # lux of display white (the Noise2Image monitor's)
ML_SIGMAS = (0.0, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 4.0)  # candidate smoothings of baseline (b), binned pixels
ML_DEFAULT_SIGMA = 0.7
FIGURE_OOD = ("skimage/camera.png", "skimage/coffee.png", "matplotlib/grace_hopper.jpg", "skimage/astronaut.png")


@dataclass(frozen=True)
class Size:
    """Data sizes and training budget of one run size."""

    dl_images: int  # dead-leaves scenes (80 / 10 / 10 % train / val / test)
    crops_per_image: int  # crops per scene (and per OOD photo: photo_crops)
    photo_crops: int
    crop_px: int  # side of the stored crops in sensor pixels (binned: crop_px // 2)
    epochs: int
    steps_per_epoch: int
    batch_size: int
    train_crop: int  # training crop side, binned pixels
    val_items: int  # validation pairs used during training
    max_minutes: float  # wall-clock cap per model (a guard, normally not reached)
    ml_sigmas: tuple = ML_SIGMAS
    speed_repeats: int = 20
    figure_rows: tuple = (2, 3)  # (ID, OOD) examples in the figure


SIZES = {
    "tiny": Size(dl_images=12, crops_per_image=2, photo_crops=1, crop_px=128, epochs=2, steps_per_epoch=3,
                 batch_size=4, train_crop=32, val_items=4, max_minutes=2.0, ml_sigmas=(0.7, 1.5), speed_repeats=3,
                 figure_rows=(1, 2)),
    "quick": Size(dl_images=100, crops_per_image=4, photo_crops=4, crop_px=256, epochs=8, steps_per_epoch=40,
                  batch_size=16, train_crop=64, val_items=16, max_minutes=10.0),
    "full": Size(dl_images=300, crops_per_image=4, photo_crops=4, crop_px=256, epochs=30, steps_per_epoch=50,
                 batch_size=16, train_crop=64, val_items=24, max_minutes=30.0),
}

# the paper's numbers (real EVK3-HD recordings of a monitor; not comparable in absolute terms)
PAPER_TABLE1 = {
    "Noise2Image, synthetic training": ((20.3, 0.614, 0.449), (16.6, 0.504, 0.532)),
    "Noise2Image, experimental training": ((25.0, 0.742, 0.349), (19.3, 0.552, 0.509)),
    "best pre-trained E2VID method (per metric)": ((9.78, 0.229, 0.764), (10.5, 0.149, 0.720)),
}
PAPER_S1 = {0.1: ((23.8, 0.714, 0.391), (18.4, 0.513, 0.586)), 0.25: ((24.4, 0.721, 0.377), (18.8, 0.522, 0.564)),
            0.5: ((24.7, 0.738, 0.358), (19.1, 0.545, 0.537)), 1.0: ((25.0, 0.742, 0.349), (19.3, 0.552, 0.509)),
            2.0: ((25.4, 0.765, 0.324), (19.5, 0.598, 0.473))}
PAPER_T2 = {"both": ((25.0, 0.742, 0.349), (19.3, 0.552, 0.509)), "on": ((24.1, 0.686, 0.378), (18.7, 0.501, 0.526)),
            "off": ((24.2, 0.696, 0.378), (18.8, 0.513, 0.531))}


# ==================================================================================== helpers
def _wtag(window: float) -> str:
    return f"w{window:g}"


def _torch_one_thread():
    import torch

    torch.set_num_threads(1)
    return torch


def write_preset(path: Path, params, note: str) -> Path:
    """A preset TOML with ``params`` (a NoiseParams) and a provenance note."""
    lines = ["# written by benchmarks/reconstruction.py", "[params]"]
    lines += [f"{k} = {float(v)!r}" for k, v in params.to_dict().items()]
    lines += ["", "[provenance]", f"status = {json.dumps('derived')}", f"note = {json.dumps(note)}", ""]
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def pair_config(size: Size, *, windows, preset: Path, seed: int, photos: bool):
    from evnoise import load_preset
    from evnoise.generators import PairConfig

    return PairConfig(sensor_shape=SENSOR, crop_shape=(size.crop_px, size.crop_px),
                      crops_per_image=size.photo_crops if photos else size.crops_per_image, binning=2,
                      windows_s=tuple(windows), max_lux=WHITE_LUX, white_lux=WHITE_LUX,
                      splits=(0.0, 0.0, 1.0) if photos else (0.8, 0.1, 0.1), seed=seed, preset=str(preset),
                      params=load_preset(preset))


def cli_equivalent(size: Size, *, windows, preset: Path, seed: int, photos: bool, out: Path) -> str:
    """The ``evnoise make-dataset`` command that makes the same dataset."""
    crops = size.photo_crops if photos else size.crops_per_image
    src = "--source package-photos --split 0,0,1" if photos else f"--procedural dead-leaves --count {size.dl_images}"
    return (f"evnoise make-dataset {src} --sensor {SENSOR[1]}x{SENSOR[0]} --crop {size.crop_px} "
            f"--crops-per-image {crops} --window {','.join(f'{w:g}' for w in windows)} --max-lux {WHITE_LUX:g} "
            f"--preset {preset} --seed {seed} --out {out}")


def split_windows(data_dir, split: str):
    """``(PairDataset, window of every item in µs)`` for one split (reads only the shards'
    ``/window_s`` columns, in the reader's item order)."""
    import h5py

    from evnoise.generators import PairDataset, load_manifest

    ds = PairDataset(data_dir, split)
    root, manifest = load_manifest(data_dir)
    windows = []
    for shard in manifest["shards"]:
        if shard["split"] == split and shard["samples"] > 0:
            with h5py.File(Path(root) / shard["file"], "r") as f:
                windows.extend(np.asarray(f["window_s"][()], dtype=np.float64).tolist())
    if len(windows) != len(ds):
        raise RuntimeError(f"{data_dir} [{split}]: {len(windows)} windows for {len(ds)} pairs")
    return ds, np.round(np.asarray(windows) * 1e6).astype(np.int64)


def select(data_dir, split: str, window: float, limit: int | None = None):
    """The pairs of ``split`` at ``window`` seconds (at most ``limit``, evenly spaced)."""
    from evnoise.reconstruct.data import Subset

    ds, w_us = split_windows(data_dir, split)
    idx = np.flatnonzero(w_us == round(window * 1e6))
    if idx.size == 0:
        raise RuntimeError(f"{data_dir} [{split}] has no pairs at {window:g} s")
    if limit is not None and idx.size > limit:
        idx = idx[np.linspace(0, idx.size - 1, limit).round().astype(int)]
    return Subset(ds, idx.tolist())


def _per_item(result: dict, method: str) -> dict:
    rows = result["per_item"]
    return {"source": [r["source"] for r in rows],
            **{k: [None if r[method][k] is None else float(r[method][k]) for r in rows]
               for k in ("psnr", "ssim", "lpips")}}


# ==================================================================================== jobs
# Each job runs in its own spawned process (one torch thread) and returns plain JSON data.
def job_dataset(*, photos: bool, windows, preset: str, seed: int, size: dict, out: str) -> dict:
    from evnoise.generators import DeadLeaves, PackagePhotos, make_dataset

    sz = Size(**size)
    t0 = time.perf_counter()
    config = pair_config(sz, windows=windows, preset=Path(preset), seed=seed, photos=photos)
    source = PackagePhotos() if photos else DeadLeaves(sz.dl_images)
    res = make_dataset([source], out, config, workers=1, threads=1, progress=False)
    m = res.manifest
    return {"seconds": time.perf_counter() - t0, "samples": m["totals"]["samples"],
            "sources": m["totals"]["sources"],
            "splits": {s: {"sources": m["splits"][s].get("sources"), "samples": m["splits"][s]["samples"]}
                       for s in ("train", "val", "test")},
            "cli": cli_equivalent(sz, windows=windows, preset=Path(preset), seed=seed, photos=photos, out=Path(out))}


def job_baselines(*, val: dict, tests: dict, sigmas, lpips: bool = True) -> dict:
    """Baselines (a) and (b) on test sets; (b)'s smoothing chosen on ``val`` by PSNR."""
    _torch_one_thread()
    from evnoise.reconstruct.evaluate import evaluate

    t0 = time.perf_counter()
    sigmas = [float(s) for s in sigmas]
    tune = evaluate(select(**val), methods=("ml-inversion",), smoothing_sigma=sigmas, lpips=False)
    key = (lambda s: f"ml-inversion@{s:g}") if len(sigmas) > 1 else (lambda s: "ml-inversion")
    tuning = {f"{s:g}": tune["metrics"][key(s)]["psnr"][0] for s in sigmas}
    best = max(sigmas, key=lambda s: tuning[f"{s:g}"])
    use = [best] if best == ML_DEFAULT_SIGMA else [best, ML_DEFAULT_SIGMA]
    out = {"sigma": best, "tuning_psnr": tuning, "tests": {}}
    for name, spec in tests.items():
        res = evaluate(select(**spec), methods=("ml-inversion", "counts-affine", "counts-minmax"),
                       smoothing_sigma=use if len(use) > 1 else use[0], lpips=lpips)
        methods = {}
        for m in res["metrics"]:
            if m.startswith("ml-inversion"):
                s = best if m == "ml-inversion" else float(m.split("@")[1])
                label = "ml-tuned" if s == best else "ml-default"
            else:
                label = m
            methods[label] = _per_item(res, m)
        out["tests"][name] = {"n": res["n"], "methods": methods}
    out["seconds"] = time.perf_counter() - t0
    return out


def job_train(*, train: dict, val: dict, out: str, polarities: str, size: dict, seed: int, tests: dict) -> dict:
    """Train one U-Net with a fixed step budget, then evaluate it on ``tests``."""
    _torch_one_thread()
    from evnoise.reconstruct.evaluate import evaluate
    from evnoise.reconstruct.train import TrainConfig
    from evnoise.reconstruct.train import train as run_training

    sz = Size(**size)
    config = TrainConfig(epochs=sz.epochs, steps_per_epoch=sz.steps_per_epoch, batch_size=sz.batch_size,
                         crop=sz.train_crop, patience=None, max_minutes=sz.max_minutes, polarities=polarities,
                         seed=seed)
    result = run_training(select(**train), out, val_data=select(**val, limit=sz.val_items), config=config,
                          progress=False, plot=True, threads=1, overwrite=True,
                          data_description=f"{train['data_dir']} [train, {train['window']:g} s]")
    h = result["history"]
    summary = {"elapsed_s": result["elapsed_s"], "steps": result["steps"], "epochs": result["epochs"],
               "stopped": result["stopped"], "best_epoch": result["best_epoch"],
               "best_val_psnr": h["val_psnr"][result["best_epoch"] - 1] if result["best_epoch"] else None,
               "history": h, "n_parameters": result["n_parameters"], "config": config.to_dict(),
               "n_train": len(select(**train)), "out": out}
    t0 = time.perf_counter()
    evals = {}
    for name, spec in tests.items():
        res = evaluate(select(**spec), out, methods=("unet",), lpips=True)
        evals[name] = {"n": res["n"], "unet": _per_item(res, "unet")}
    summary["tests"] = evals
    summary["eval_s"] = time.perf_counter() - t0
    return summary


def job_speed(*, model: str, repeats: int) -> dict:
    """Median time of the U-Net on 640x360 and 320x180 binned inputs (1 thread, then all cores),
    and of baseline (b) (NumPy/SciPy)."""
    torch = _torch_one_thread()
    from evnoise import load_preset
    from evnoise.reconstruct.baselines import MLInversion
    from evnoise.reconstruct.infer import Reconstructor

    net = Reconstructor(model, threads=1)
    rng = np.random.default_rng(0)
    out = {"repeats": repeats, "cores": os.cpu_count()}

    def timeit(fn):
        fn()
        fn()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return [float(np.median(times)), float(np.min(times)), float(np.max(times))]

    ml = MLInversion(load_preset("evk3-hd"), max_lux=WHITE_LUX, smoothing_sigma=ML_DEFAULT_SIGMA)
    inputs = {(h, w): rng.poisson(3.0, size=(2, h, w)).astype(np.uint16) for h, w in ((360, 640), (180, 320))}
    for threads in sorted({1, os.cpu_count() or 1}):
        torch.set_num_threads(threads)
        for (h, w), counts in inputs.items():
            out[f"unet_{w}x{h}_t{threads}"] = timeit(lambda c=counts: net.predict_binned(c, 1.0))
    torch.set_num_threads(1)
    for (h, w), counts in inputs.items():
        out[f"ml_{w}x{h}"] = timeit(lambda c=counts: ml.display(c, 1.0))
    return out


def job_figure(*, model: str, id_test: dict, ood_test: dict, sigma: float, rows, out: str) -> dict:
    """Input counts / baselines / U-Net / ground truth for a few ID and OOD test pairs."""
    _torch_one_thread()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from evnoise.reconstruct.baselines import MLInversion, count_image
    from evnoise.reconstruct.infer import Reconstructor
    from evnoise.reconstruct.metrics import psnr

    net = Reconstructor(model, threads=1)
    picks = []
    for tag, spec, n, preferred in (("ID", id_test, rows[0], ()), ("OOD", ood_test, rows[1], FIGURE_OOD)):
        ds = select(**spec)
        first = {}
        for i, s in enumerate(ds.sources):
            first.setdefault(s, i)
        names = [s for s in preferred if s in first]
        others = sorted(first)
        names += [others[k] for k in np.linspace(0, len(others) - 1, len(others)).round().astype(int)
                  if others[k] not in names]
        picks += [(tag, ds, first[s]) for s in names[:n]]
    cols = ["counts ON+OFF", "(a) counts, affine\n(oracle)", "(b) ML inversion", "U-Net", "ground truth"]
    fig, axes = plt.subplots(len(picks), len(cols), figsize=(1.75 * len(cols), 1.85 * len(picks)), squeeze=False)
    for r, (tag, ds, i) in enumerate(picks):
        item = ds[i]
        counts, target, window = np.asarray(item["counts"]), np.asarray(item["image"], np.float64), item["window_s"]
        ml = MLInversion(ds.params, max_lux=ds.max_lux, binning=ds.binning, smoothing_sigma=sigma)
        preds = [count_image(counts, target=target, mode="affine"),
                 ml.display(counts, window, max_lux=item["lux_scale"]),
                 net.predict_binned(counts, window)]
        panels = [counts.sum(axis=0)] + preds + [target]
        for c, img in enumerate(panels):
            ax = axes[r, c]
            ax.imshow(img, cmap="gray", vmin=0 if c else None, vmax=1 if c else None, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if 1 <= c <= 3:
                ax.set_xlabel(f"{psnr(img, target):.1f} dB", fontsize=7, labelpad=1)
            if r == 0:
                ax.set_title(cols[c], fontsize=7)
        axes[r, 0].set_ylabel(f"{tag}: {item['source'].split('/')[-1]}", fontsize=6)
    fig.tight_layout(pad=0.3, h_pad=0.4, w_pad=0.2)
    fig.savefig(out, dpi=72)
    plt.close(fig)
    return {"path": out, "rows": [[tag, ds[i]["source"]] for tag, ds, i in picks]}


# ==================================================================================== running
@dataclass
class Job:
    name: str
    fn: object
    kwargs: dict
    deps: tuple = ()
    exclusive: bool = False  # runs alone (timings)


def _fingerprint(job: Job) -> str:
    """Identity of a job's result: its function's code and its arguments."""
    code = inspect.getsource(job.fn)
    return hashlib.sha256(json.dumps([code, job.kwargs], sort_keys=True, default=str).encode()).hexdigest()


def run_jobs(jobs, *, parallel: int, cache: Path, fresh: bool, log) -> dict:
    """Run ``jobs`` (in list order as their dependencies allow, ``parallel`` at a time, each in
    a fresh spawned process); results are cached as JSON in ``cache``."""
    cache.mkdir(parents=True, exist_ok=True)
    done, timing, pending, running = {}, {}, list(jobs), {}
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=parallel, mp_context=get_context("spawn"), max_tasks_per_child=1) as pool:
        while pending or running:
            progressed = True
            while progressed:
                progressed = False
                for job in list(pending):
                    if len(running) >= parallel or any(j.exclusive for j, _ in running.values()):
                        break
                    if not all(d in done for d in job.deps) or (job.exclusive and running):
                        continue
                    pending.remove(job)
                    progressed = True
                    path = cache / f"{job.name.replace(':', '_')}.json"
                    if not fresh and path.is_file():
                        doc = json.loads(path.read_text())
                        if doc.get("fingerprint") == _fingerprint(job):
                            done[job.name], timing[job.name] = doc["result"], doc["wall_s"]
                            log(f"cached   {job.name}")
                            continue
                    log(f"start    {job.name}")
                    running[pool.submit(job.fn, **job.kwargs)] = (job, time.perf_counter())
                    break  # re-scan from the top: keep the list order as the priority
            if not running:
                if pending:
                    raise RuntimeError(f"jobs with unmet dependencies: {[j.name for j in pending]}")
                break
            finished, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for fut in finished:
                job, t0 = running.pop(fut)
                result = fut.result()  # a failed job stops the run with its traceback
                wall = time.perf_counter() - t0
                done[job.name], timing[job.name] = result, wall
                path = cache / f"{job.name.replace(':', '_')}.json"
                path.write_text(json.dumps({"fingerprint": _fingerprint(job), "wall_s": wall, "result": result},
                                           default=float))
                log(f"finished {job.name} in {wall / 60:.1f} min (run at {(time.perf_counter() - start) / 60:.1f} min)")
    return {"results": done, "wall_s": timing}


def plan(size_name: str, size: Size, work: Path, out: Path, seed: int, train_seed: int):
    """Presets, and the list of jobs of a run (in priority order)."""
    from evnoise import load_preset

    shipped = load_preset("evk3-hd")
    mismatch_sigma = shipped.eps_sigma if shipped.eps_sigma > 0 else DEFAULT_MISMATCH
    variants = {"nominal": shipped.replace(eps_sigma=0.0), "mismatch": shipped.replace(eps_sigma=mismatch_sigma)}
    main = "mismatch" if shipped.eps_sigma > 0 else "nominal"
    (work / "presets").mkdir(parents=True, exist_ok=True)
    presets = {}
    for name, params in variants.items():
        presets[name] = str(write_preset(work / "presets" / f"evk3-hd-{name}.toml", params,
                                         f"evk3-hd as shipped, with eps_sigma = {params.eps_sigma:g}"))
    data = {f"{kind}-{v}": str(work / "data" / f"{kind}-{v}") for kind in ("dl", "photos") for v in variants}
    (work / "data").mkdir(exist_ok=True)
    (work / "models").mkdir(exist_ok=True)
    sz = dataclasses.asdict(size)
    win = {"nominal": WINDOWS, "mismatch": (MAIN_WINDOW,)}

    def spec(kind, v, split, w):
        return {"data_dir": data[f"{kind}-{v}"], "split": split, "window": w}

    def tests(v, w):
        return {f"id-{v}-{_wtag(w)}": spec("dl", v, "test", w), f"ood-{v}-{_wtag(w)}": spec("photos", v, "test", w)}

    # the slow variant (per-pixel thresholds use the general count sampler) first
    order = ["mismatch", "nominal"]
    jobs = []
    for v in order:
        for kind in ("dl", "photos"):
            jobs.append(Job(f"data:{kind}-{v}", job_dataset,
                            {"photos": kind == "photos", "windows": win[v], "preset": presets[v], "seed": seed,
                             "size": sz, "out": data[f"{kind}-{v}"]}))
    deps = {v: (f"data:dl-{v}", f"data:photos-{v}") for v in variants}

    def model(name, v, w, pol, test_sets):
        # every dataset the model is trained or tested on must be complete first
        used = {v} | {u for u in variants if any(f"-{u}-" in key for key in test_sets)}
        return Job(f"train:{name}", job_train,
                   {"train": spec("dl", v, "train", w), "val": spec("dl", v, "val", w),
                        "out": str(work / "models" / f"{name}.pt"), "polarities": pol, "size": sz, "seed": train_seed,
                        "tests": test_sets}, tuple(d for u in sorted(used) for d in deps[u]))

    cross = {**tests("nominal", MAIN_WINDOW), **tests("mismatch", MAIN_WINDOW)}
    models = {
        "nominal-w1": model("nominal-w1", "nominal", MAIN_WINDOW, "both", cross),
        "mismatch-w1": model("mismatch-w1", "mismatch", MAIN_WINDOW, "both", cross),
        "nominal-on": model("nominal-on", "nominal", MAIN_WINDOW, "on", tests("nominal", MAIN_WINDOW)),
        "nominal-off": model("nominal-off", "nominal", MAIN_WINDOW, "off", tests("nominal", MAIN_WINDOW)),
    }
    for w in WINDOWS:
        if w != MAIN_WINDOW:
            models[f"nominal-{_wtag(w)}"] = model(f"nominal-{_wtag(w)}", "nominal", w, "both", tests("nominal", w))
    baselines = [Job(f"base:{v}-{_wtag(w)}", job_baselines,
                     {"val": spec("dl", v, "val", w), "tests": tests(v, w), "sigmas": size.ml_sigmas}, deps[v])
                 for v in ("nominal", "mismatch") for w in win[v]]
    main_model = f"{main}-w1"
    train_order = [main_model] + [k for k in ("nominal-w1", "nominal-on", "nominal-off") if k != main_model]
    train_order += [f"nominal-{_wtag(w)}" for w in WINDOWS if w != MAIN_WINDOW]
    train_order += [k for k in ("mismatch-w1",) if k != main_model]
    jobs += [models[k] for k in train_order[:2]] + baselines + [models[k] for k in train_order[2:]]
    main_base = f"base:{main}-{_wtag(MAIN_WINDOW)}"
    jobs.append(Job("speed", job_speed, {"model": str(work / "models" / f"{main_model}.pt"),
                                         "repeats": size.speed_repeats}, (f"train:{main_model}",), exclusive=True))
    info = {"shipped": shipped, "variants": variants, "presets": presets, "main": main, "data": data,
            "main_model": main_model, "main_base": main_base, "spec": spec}
    return jobs, info


# ==================================================================================== report
def stats(values, sources):
    """Mean over pairs and its standard error from the per-source means (pairs of one source
    are correlated: same scene)."""
    v = np.asarray([np.nan if x is None else x for x in values], dtype=np.float64)
    ok = np.isfinite(v)
    if not ok.any():
        return None, None
    src = np.asarray(sources)[ok]
    v = v[ok]
    means = np.array([v[src == s].mean() for s in np.unique(src)])
    se = float(means.std(ddof=1) / math.sqrt(means.size)) if means.size > 1 else float("nan")
    return float(v.mean()), se


def paired(a: dict, b: dict, key: str):
    """Mean difference ``a - b`` over pairs, its standard error (per-source means), the share of
    pairs where ``a`` is better."""
    x = np.asarray(a[key], dtype=np.float64) - np.asarray(b[key], dtype=np.float64)
    mean, se = stats(x.tolist(), a["source"])
    better = float(np.mean(x < 0 if key == "lpips" else x > 0))
    return mean, se, better


def pm(v, digits):
    """``+1.23 ± 0.45`` (signed mean, standard error when defined)."""
    mean, se = v[0], v[1]
    return f"{mean:+.{digits}f}" + (f" ± {se:.{digits}f}" if se is not None and math.isfinite(se) else "")


def cell(v, digits):
    mean, se = v
    if mean is None:
        return "n/a"
    return f"{mean:.{digits}f}" + ("" if se is None or not math.isfinite(se) else f" ± {se:.{digits}f}")


def metric_cells(m: dict):
    return [cell(stats(m[k], m["source"]), d) for k, d in (("psnr", 2), ("ssim", 3), ("lpips", 3))]


HEAD = ("| {} | ID PSNR ↑ | ID SSIM ↑ | ID LPIPS ↓ | OOD PSNR ↑ | OOD SSIM ↑ | OOD LPIPS ↓ |",
        "|---|---|---|---|---|---|---|")


def row(label, id_m, ood_m):
    return "| " + " | ".join([label] + metric_cells(id_m) + metric_cells(ood_m)) + " |"


def paper_row(label, vals):
    (a, b, c), (d, e, f) = vals
    return f"| {label} | {a:.1f} | {b:.3f} | {c:.3f} | {d:.1f} | {e:.3f} | {f:.3f} |"


def machine_info() -> dict:
    """``run.machine_info()`` (CPU, cores, load, versions, commit) plus the torch version."""
    import torch

    from run import machine_info as base_info

    return {**base_info(), "torch": torch.__version__}


def preset_provenance() -> dict:
    from evnoise.params import load_preset_document

    prov = dict(load_preset_document("evk3-hd").get("provenance", {}))
    try:
        log = subprocess.run(["git", "log", "-1", "--format=%h %cs %s", "--", "evnoise/presets/evk3-hd.toml"],
                             cwd=HERE.parent, capture_output=True, text=True, check=False).stdout.strip()
    except OSError:
        log = ""
    prov["last_commit"] = log or "?"
    return prov


def windows_figure(results, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(9.6, 2.9))
    for ax, key, label in zip(axes, ("psnr", "ssim", "lpips"), ("PSNR (dB) ↑", "SSIM ↑", "LPIPS ↓"), strict=True):
        for test, ls in (("id", "-"), ("ood", "--")):
            for meth, color in (("unet", "C0"), ("ml-tuned", "C1")):
                ys, es = [], []
                for w in WINDOWS:
                    name = f"{test}-nominal-{_wtag(w)}"
                    if meth == "unet":
                        m = results[f"train:nominal-{_wtag(w)}"]["tests"][name]["unet"]
                    else:
                        m = results[f"base:nominal-{_wtag(w)}"]["tests"][name]["methods"]["ml-tuned"]
                    mean, se = stats(m[key], m["source"])
                    ys.append(mean)
                    es.append(0 if not math.isfinite(se) else se)
                ax.errorbar(WINDOWS, ys, yerr=es, color=color, ls=ls, marker="o", ms=3, capsize=2,
                            label=f"{'U-Net' if meth == 'unet' else '(b) ML inversion'}, {test.upper()}")
        ax.set_xscale("log")
        ax.set_xticks(WINDOWS)
        ax.set_xticklabels([f"{w:g}" for w in WINDOWS])
        ax.set_xlabel("window (s)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def training_figure(results, names, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9.6, 3.0))
    for k, name in enumerate(names):
        h = results[f"train:{name}"]["history"]
        ep = np.arange(1, len(h["val_loss"]) + 1)
        axes[0].plot(ep, h["train_loss"], color=f"C{k}", lw=1, alpha=0.5)
        axes[0].plot(ep, h["val_loss"], color=f"C{k}", lw=1.4, label=name)
        axes[1].plot(ep, h["val_psnr"], color=f"C{k}", lw=1.4, label=name)
    axes[0].set_ylabel("loss: L1 + 0.2 (1 - SSIM)\n(thin: train crops, thick: val)")
    axes[1].set_ylabel("validation PSNR (dB)")
    for ax in axes:
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_report(*, run, info, size_name, size, args, machine_start, machine_end, total_s, out: Path, figures):
    R = run["results"]
    walls = run["wall_s"]
    main, main_model, main_base = info["main"], info["main_model"], info["main_base"]
    shipped, variants = info["shipped"], info["variants"]
    w1 = _wtag(MAIN_WINDOW)
    idn, oodn = f"id-{main}-{w1}", f"ood-{main}-{w1}"
    unet = R[f"train:{main_model}"]["tests"]
    base = R[main_base]
    bm = {t: base["tests"][t]["methods"] for t in (idn, oodn)}
    prov = preset_provenance()
    d = R[f"data:dl-{main}"]
    p = R[f"data:photos-{main}"]
    L = []
    add = L.append
    add("# Reconstruction benchmark: U-Net against baselines, and the paper's ablations")
    add("")
    add(f"Generated by `{args['command']}` on {machine_start['date']} (total wall time "
        f"{total_s / 60:.1f} min, up to {args['jobs']} jobs in parallel, each in its own process with 1 torch "
        f"thread). Run size: **{size_name}**. Everything here is synthetic: counts drawn from evnoise's noise "
        "model, not recorded with a camera.")
    add("")
    add("Machine: " + f"{machine_start['cpu']}, {machine_start['cores']} cores, load average at start "
        f"{machine_start['load']}, at end {machine_end['load']} (the machine is shared); Python "
        f"{machine_start['python']}, NumPy {machine_start['numpy']}, torch {machine_start['torch']} (CPU), "
        f"evnoise {machine_start['evnoise']}, commit {machine_start['commit']}.")
    add("")
    add("## Setup")
    add("")
    add(f"* **Noise model**: preset `evk3-hd` as shipped at run time (provenance status "
        f"`{prov.get('status', '?')}`, file last committed {prov['last_commit']}): "
        f"`{shipped!r}`.")
    add(f"  Two variants are written to the work folder: *nominal* (`eps_sigma = 0`) and *mismatch* "
        f"(`eps_sigma = {variants['mismatch'].eps_sigma:g}`, "
        + ("the shipped value" if shipped.eps_sigma > 0 else
           "a documented choice, since the shipped preset has none")
        + f"). The main table uses the **{main}** variant (= the shipped preset).")
    add(f"* **Scenes**: sensor {SENSOR[1]}×{SENSOR[0]} (photos are fitted by `cover`), crops of "
        f"{size.crop_px}×{size.crop_px} sensor pixels, counts binned 2×2 → pairs of "
        f"{size.crop_px // 2}×{size.crop_px // 2}; display white = {WHITE_LUX:g} lux (the paper's monitor), "
        "targets sRGB-encoded like the paper's images.")
    add(f"* **Training / in-distribution (ID)**: {size.dl_images} procedural dead-leaves scenes × "
        f"{size.crops_per_image} crops, split by scene: {d['splits']['train']['sources']} scenes for training, "
        f"{d['splits']['val']['sources']} for validation, {d['splits']['test']['sources']} for the ID test (the "
        "nominal dead-leaves dataset holds every window of the ablation; each model uses the pairs of its window).")
    add(f"* **Out-of-distribution (OOD) test**: the {p['sources']} natural photos shipped by installed packages "
        f"(`--source package-photos`: scikit-image, matplotlib, ...), {size.photo_crops} crop(s) each, "
        "never seen in training or validation (disjoint by source and by kind). This mirrors the paper's "
        "design: a confined training distribution (there: portraits; here: dead leaves) and a broad test "
        "(there: DIV2K; here: photos).")
    add("* **Data commands** (the same datasets from the command line):")
    add("")
    add("  ```")
    for k in sorted(info["data"]):
        add(f"  {R[f'data:{k}']['cli']}")
    add("  ```")
    add("")
    cfg = R[f"train:{main_model}"]["config"]
    add(f"* **Training** (every model alike): `TrainConfig(epochs={cfg['epochs']}, steps_per_epoch="
        f"{cfg['steps_per_epoch']}, batch_size={cfg['batch_size']}, crop={cfg['crop']}, lr={cfg['lr']:g}, "
        f"ssim_weight={cfg['ssim_weight']:g}, patience=None, seed={cfg['seed']})`: a fixed budget of "
        f"{cfg['epochs'] * cfg['steps_per_epoch']} steps × {cfg['batch_size']} random {cfg['crop']}×{cfg['crop']} "
        f"crops (flips/rotations), {size.val_items} validation pairs, the best validation epoch kept; a "
        f"wall-clock cap of {size.max_minutes:g} min per model guards against a far slower machine "
        "(see the training table: `stopped` says whether it was hit). U-Net "
        f"{R[f'train:{main_model}']['n_parameters']:,} parameters (`DEFAULT_MODEL`).")
    add(f"* **Seeds**: datasets `--seed {args['seed']}` (the nominal and mismatch datasets share scenes, crops "
        f"and noise seeds: paired), networks `seed={args['train_seed']}`.")
    add("* **Metrics**: PSNR, SSIM (Gaussian σ 1.5, data range 1) and LPIPS (AlexNet, offline weights) on the "
        "display-encoded images; mean over test pairs ± standard error computed from the per-source means "
        "(pairs from one scene are correlated).")
    add(f"* **Baselines**: (a) the count image ON+OFF, min-max stretched (what a user sees), and its best "
        "affine fit to the ground truth (an *oracle*: it uses the target); (b) per-pixel maximum-likelihood "
        "illuminance from ON and OFF jointly with the exact closed form and nominal thresholds, after "
        "Gaussian smoothing of the counts; its σ is chosen per window and variant on the ID *validation* "
        f"pairs from {{{', '.join(f'{s:g}' for s in size.ml_sigmas)}}} binned pixels "
        f"(chosen for the main table: σ = {base['sigma']:g}; the library default is {ML_DEFAULT_SIGMA:g}).")
    add("")

    # ---------------------------------------------------------------- main table
    add("## 1. Main table (paper Table 1 analogue)")
    add("")
    add(f"Window {MAIN_WINDOW:g} s, both polarities, {main} noise. ID: {unet[idn]['n']} pairs; "
        f"OOD: {unet[oodn]['n']} pairs.")
    add("")
    add(HEAD[0].format("method"))
    add(HEAD[1])
    add(row("**U-Net (evnoise)**", unet[idn]["unet"], unet[oodn]["unet"]))
    add(row(f"(b) ML inversion, σ = {base['sigma']:g} (tuned on val)", bm[idn]["ml-tuned"], bm[oodn]["ml-tuned"]))
    if "ml-default" in bm[idn]:
        add(row(f"(b) ML inversion, σ = {ML_DEFAULT_SIGMA:g} (default)", bm[idn]["ml-default"],
                bm[oodn]["ml-default"]))
    add(row("(a) count image, affine fit (**oracle**)", bm[idn]["counts-affine"], bm[oodn]["counts-affine"]))
    add(row("(a) count image, min-max", bm[idn]["counts-minmax"], bm[oodn]["counts-minmax"]))
    add("")
    u_id, u_ood = stats(unet[idn]["unet"]["psnr"], unet[idn]["unet"]["source"])[0], \
        stats(unet[oodn]["unet"]["psnr"], unet[oodn]["unet"]["source"])[0]
    a_id, a_ood = stats(bm[idn]["counts-affine"]["psnr"], bm[idn]["counts-affine"]["source"])[0], \
        stats(bm[oodn]["counts-affine"]["psnr"], bm[oodn]["counts-affine"]["source"])[0]
    if u_ood > u_id:
        add(f"Unlike the paper, OOD scores are *higher* than ID scores here (U-Net {u_ood:.1f} against {u_id:.1f} dB; "
            f"the oracle affine count image too: {a_ood:.1f} against {a_id:.1f} dB): the dead-leaves test scenes, "
            "with sharp occlusion edges and texture at every scale down to a pixel, are harder to reconstruct from "
            "a few events per bin than the smoother photos. ID against OOD here measures the kind of scene as much "
            "as generalisation; the comparison between methods on each set is what the table is for.")
        add("")
    add("For orientation only, the paper's Table 1 (real EVK3-HD recordings of a monitor, 1280×720 images, "
        "a larger network trained much longer on a GPU; its ID set is portraits, its OOD set DIV2K):")
    add("")
    add(HEAD[0].format("paper"))
    add(HEAD[1])
    for k, v in PAPER_TABLE1.items():
        add(paper_row(k, v))
    add("")

    # ---------------------------------------------------------------- margin over (b)
    add("## 2. By how much the U-Net beats baseline (b)")
    add("")
    add("Paired differences on the same test pairs, U-Net minus (b) (σ tuned on validation); ± is the "
        "standard error from per-source means; the last column is the share of pairs where the U-Net's "
        "PSNR is higher.")
    add("")
    add("| test set | ΔPSNR (dB) | ΔSSIM | ΔLPIPS (negative = better) | U-Net better on |")
    add("|---|---|---|---|---|")
    margins = {}
    for tag, t in (("ID", idn), ("OOD", oodn)):
        u, b = unet[t]["unet"], bm[t]["ml-tuned"]
        dp, ds_, dl = paired(u, b, "psnr"), paired(u, b, "ssim"), paired(u, b, "lpips")
        margins[tag] = (dp, ds_, dl)
        add(f"| {tag} | {pm(dp, 2)} | {pm(ds_, 3)} | {pm(dl, 3)} | {100 * dp[2]:.0f} % of {len(u['psnr'])} pairs |")
    add("")
    for tag, (dp, ds_, dl) in margins.items():
        verdict = ("beats (b) on all three metrics" if dp[0] > 0 and ds_[0] > 0 and dl[0] < 0 else
                   "does **not** beat (b) on every metric")
        ratio = 10 ** (-dp[0] / 10)  # MSE ratio U-Net / (b) (geometric mean over pairs)
        change = f"{100 * (1 - ratio):.0f} % lower" if ratio < 1 else f"{100 * (ratio - 1):.0f} % higher"
        add(f"* {tag}: the U-Net {verdict} (PSNR {dp[0]:+.2f} dB: its mean squared error is {change} than (b)'s, "
            "geometric mean over pairs).")
    add("")

    # ---------------------------------------------------------------- windows
    add("## 3. Integration window (paper Table S1 analogue)")
    add("")
    add("One U-Net per window, trained and tested at that window (nominal noise, both polarities, same budget). "
        "Baseline (b) at the same window, σ tuned on validation for each window.")
    add("")
    add(HEAD[0].format("window"))
    add(HEAD[1])
    for w in WINDOWS:
        r = R[f"train:nominal-{_wtag(w)}"]["tests"]
        add(row(f"{w:g} s — U-Net", r[f"id-nominal-{_wtag(w)}"]["unet"], r[f"ood-nominal-{_wtag(w)}"]["unet"]))
    for w in WINDOWS:
        b = R[f"base:nominal-{_wtag(w)}"]
        add(row(f"{w:g} s — (b) ML, σ = {b['sigma']:g}", b["tests"][f"id-nominal-{_wtag(w)}"]["methods"]["ml-tuned"],
                b["tests"][f"ood-nominal-{_wtag(w)}"]["methods"]["ml-tuned"]))
    add("")
    add(f"![PSNR, SSIM and LPIPS against the window]({figures['windows'].name})")
    add("")
    add("Paper Table S1 (real data) for orientation:")
    add("")
    add(HEAD[0].format("paper window"))
    add(HEAD[1])
    for w, v in PAPER_S1.items():
        add(paper_row(f"{w:g} s", v))
    add("")

    # ---------------------------------------------------------------- polarity
    add("## 4. Polarity (paper Table 2 analogue)")
    add("")
    add(f"Trained and tested on the same counts ({MAIN_WINDOW:g} s, nominal noise) with both channels, ON only or "
        "OFF only.")
    add("")
    add(HEAD[0].format("channels"))
    add(HEAD[1])
    for pol, name in (("both", "nominal-w1"), ("on", "nominal-on"), ("off", "nominal-off")):
        r = R[f"train:{name}"]["tests"]
        add(row({"both": "ON + OFF", "on": "ON only", "off": "OFF only"}[pol], r[f"id-nominal-{w1}"]["unet"],
                r[f"ood-nominal-{w1}"]["unet"]))
    add("")
    add("Paper Table 2 (real data):")
    add("")
    add(HEAD[0].format("paper channels"))
    add(HEAD[1])
    for pol, v in PAPER_T2.items():
        add(paper_row({"both": "positive & negative", "on": "positive only", "off": "negative only"}[pol], v))
    add("")

    # ---------------------------------------------------------------- mismatch
    add("## 5. Threshold mismatch: an analogue of the synthetic-to-real gap")
    add("")
    add(f"The paper's synthetic-data model lacks the per-pixel threshold variation of a real sensor and loses "
        f"4.7 dB (ID) / 2.7 dB (OOD) against a model trained on real recordings. Here: one U-Net trained without "
        f"mismatch (`eps_sigma = 0`) and one with it (`eps_sigma = {variants['mismatch'].eps_sigma:g}`, a fresh "
        f"mismatch pattern per pair), each tested on both kinds of counts ({MAIN_WINDOW:g} s; the same scenes, "
        "crops and noise seeds). Baseline (b) assumes nominal thresholds in both cases.")
    add("")
    add(HEAD[0].format("trained on → tested on"))
    add(HEAD[1])
    for tr in ("nominal", "mismatch"):
        r = R[f"train:{tr}-w1"]["tests"]
        for te in ("nominal", "mismatch"):
            add(row(f"{tr} → {te}", r[f"id-{te}-{w1}"]["unet"], r[f"ood-{te}-{w1}"]["unet"]))
    for te in ("nominal", "mismatch"):
        b = R[f"base:{te}-{w1}"]
        add(row(f"(b) ML inversion → {te} (σ = {b['sigma']:g})", b["tests"][f"id-{te}-{w1}"]["methods"]["ml-tuned"],
                b["tests"][f"ood-{te}-{w1}"]["methods"]["ml-tuned"]))
    add("")
    lines = []
    for tag in ("id", "ood"):
        t_mm = f"{tag}-mismatch-{w1}"
        t_nom = f"{tag}-nominal-{w1}"
        gap = paired(R["train:nominal-w1"]["tests"][t_mm]["unet"], R["train:mismatch-w1"]["tests"][t_mm]["unet"],
                     "psnr")
        rev = paired(R["train:mismatch-w1"]["tests"][t_nom]["unet"], R["train:nominal-w1"]["tests"][t_nom]["unet"],
                     "psnr")
        lines.append(f"* {tag.upper()}: on mismatched counts the model trained without mismatch is "
                     f"{pm(gap, 2)} dB against the one trained with it (the gap); on nominal "
                     f"counts the model trained with mismatch is {pm(rev, 2)} dB against the "
                     "nominal one (the reverse).")
    L.extend(lines)
    add("")

    # ---------------------------------------------------------------- figure
    add("## 6. Examples")
    add("")
    add(f"Main model, {MAIN_WINDOW:g} s window, test pairs (first crop of the scenes listed on the left); "
        "PSNR under each reconstruction. The count panel is auto-scaled.")
    add("")
    add(f"![counts, baselines, U-Net and ground truth]({figures['examples'].name})")
    add("")

    # ---------------------------------------------------------------- speed
    sp = R["speed"]
    add("## 7. Speed")
    add("")
    add(f"Inference with the main checkpoint, median (min–max) of {sp['repeats']} runs after two warm-up runs, "
        "on random counts; `Reconstructor.predict_binned` (counts → normalised rates → U-Net → clipped image):")
    add("")
    cores = sp["cores"] or 1
    add(f"| input (binned counts) | U-Net, 1 thread | U-Net, {cores} threads | baseline (b), for comparison |")
    add("|---|---|---|---|")

    def ms(t):
        return f"{1000 * t[0]:.0f} ms ({1000 * t[1]:.0f}–{1000 * t[2]:.0f})"

    for w, h, what in ((640, 360, "640×360 (a 1280×720 EVK3-HD frame, binned 2×2)"),
                       (320, 180, "320×180 (a 640×360 sensor, binned 2×2)")):
        add(f"| {what} | {ms(sp[f'unet_{w}x{h}_t1'])} | "
            f"{ms(sp[f'unet_{w}x{h}_t{cores}']) if cores > 1 else 'n/a'} | {ms(sp[f'ml_{w}x{h}'])} |")
    add("")
    add("The speed job ran alone (no other job of this benchmark in parallel); other users of the machine may "
        "not have been idle (see the load averages above).")
    add("")
    add("Training (1 torch thread per model; two models ran at a time on the 2 cores, so the wall times "
        "include contention):")
    add("")
    add("| model | training pairs | steps | wall (min) | s / step | stopped by | best epoch | val PSNR (dB) | "
        "evaluation (s) |")
    add("|---|---|---|---|---|---|---|---|---|")
    names = [k.split(":", 1)[1] for k in R if k.startswith("train:")]
    for name in names:
        t = R[f"train:{name}"]
        add(f"| {name} | {t['n_train']} | {t['steps']} | {t['elapsed_s'] / 60:.1f} | "
            f"{t['elapsed_s'] / max(t['steps'], 1):.2f} | {t['stopped']} | {t['best_epoch']} | "
            f"{t['best_val_psnr']:.2f} | {t['eval_s']:.0f} |")
    add("")
    add(f"![training curves]({figures['training'].name})")
    add("")
    add("Data generation (1 worker each): " + "; ".join(
        f"{k}: {R[f'data:{k}']['samples']} pairs in {R[f'data:{k}']['seconds']:.0f} s" for k in sorted(info["data"]))
        + ". The mismatch variant uses the general per-pixel-threshold count sampler, which is much slower "
        "than the direct sampler of the nominal model.")
    add("")
    add("Job wall times (min): " + ", ".join(f"{k} {v / 60:.1f}" for k, v in walls.items()) + ".")
    add("")
    add("## Reproduce")
    add("")
    add("```")
    add("python -m evnoise.reconstruct.lpips check      # the offline LPIPS weights")
    add(f"{args['command']}")
    add("```")
    add("")
    add("`--quick` (about 15 minutes) and `--tiny` (a smoke run) use smaller data and budgets; `--work DIR` keeps "
        "the datasets, checkpoints and cached job results (a second run reuses finished jobs; `--fresh` "
        "ignores them).")
    text = "\n".join(L) + "\n"
    kept = shipped_model_section(out)
    if kept:  # the shipped model's section is written by hand from `evnoise evaluate`: keep it
        text = text.replace("## Setup\n", kept + "\n\n## Setup\n", 1)
    out.write_text(text, encoding="utf-8")


SHIPPED_BEGIN, SHIPPED_END = "<!-- shipped-model:begin -->", "<!-- shipped-model:end -->"


def shipped_model_section(path: Path) -> str:
    """The block between the shipped-model markers of an existing report ('' when absent)."""
    try:
        old = Path(path).read_text(encoding="utf-8")
    except OSError:
        return ""
    i, j = old.find(SHIPPED_BEGIN), old.find(SHIPPED_END)
    return old[i:j + len(SHIPPED_END)] if 0 <= i < j else ""


# ==================================================================================== main
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--quick", action="store_true", help="smaller data and budgets (about 15 minutes)")
    g.add_argument("--tiny", action="store_true", help="smoke run (1-2 minutes)")
    parser.add_argument("--work", type=Path, help="work folder for datasets, checkpoints and cached results "
                        "(default: a folder in the system's temporary directory)")
    parser.add_argument("--out", type=Path, default=HERE, help="where RECONSTRUCTION.md and the PNGs go "
                        "(default: benchmarks/)")
    parser.add_argument("--jobs", type=int, default=2, help="jobs in parallel, one process each (default 2)")
    parser.add_argument("--seed", type=int, default=1, help="dataset seed (default 1)")
    parser.add_argument("--train-seed", type=int, default=0, help="network seed (default 0)")
    parser.add_argument("--fresh", action="store_true", help="ignore cached job results in --work")
    args = parser.parse_args(argv)
    size_name = "tiny" if args.tiny else "quick" if args.quick else "full"
    size = SIZES[size_name]
    if args.jobs < 1:
        parser.error("--jobs must be >= 1")

    import evnoise

    shipped = evnoise.load_preset("evk3-hd")
    key = hashlib.sha256(json.dumps([dataclasses.asdict(size), shipped.to_dict(), args.seed, args.train_seed,
                                     evnoise.__version__], sort_keys=True, default=str).encode()).hexdigest()[:10]
    work = (args.work or Path(tempfile.gettempdir()) / "evnoise-reconstruction") / f"{size_name}-{key}"
    work.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    machine_start = machine_info()
    logfile = (work / "log.txt").open("a", encoding="utf-8")

    def log(msg):
        line = f"[{(time.perf_counter() - t_start) / 60:5.1f} min] {msg}"
        print(line, flush=True)
        logfile.write(line + "\n")
        logfile.flush()

    log(f"{size_name} run; work folder {work}; report to {args.out}")
    jobs, info = plan(size_name, size, work, args.out, args.seed, args.train_seed)
    run = run_jobs(jobs, parallel=args.jobs, cache=work / "results", fresh=args.fresh, log=log)
    R = run["results"]
    figures = {"examples": args.out / "reconstruction_examples.png",
               "windows": args.out / "reconstruction_windows.png",
               "training": args.out / "reconstruction_training.png"}
    spec = info["spec"]
    with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn")) as pool:
        pool.submit(job_figure, model=str(work / "models" / f"{info['main_model']}.pt"),
                    id_test=spec("dl", info["main"], "test", MAIN_WINDOW),
                    ood_test=spec("photos", info["main"], "test", MAIN_WINDOW), sigma=R[info["main_base"]]["sigma"],
                    rows=size.figure_rows, out=str(figures["examples"])).result()
    windows_figure(R, figures["windows"])
    training_figure(R, [k.split(":", 1)[1] for k in R if k.startswith("train:")], figures["training"])
    argv_text = " ".join(["python benchmarks/reconstruction.py"] + (["--" + size_name] if size_name != "full" else [])
                         + ([f"--seed {args.seed}"] if args.seed != 1 else [])
                         + ([f"--train-seed {args.train_seed}"] if args.train_seed != 0 else []))
    total = time.perf_counter() - t_start
    write_report(run=run, info=info, size_name=size_name, size=size,
                 args={"command": argv_text, "jobs": args.jobs, "seed": args.seed, "train_seed": args.train_seed},
                 machine_start=machine_start, machine_end=machine_info(), total_s=total,
                 out=args.out / "RECONSTRUCTION.md", figures=figures)
    log(f"wrote {args.out / 'RECONSTRUCTION.md'} in {total / 60:.1f} min")
    logfile.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
