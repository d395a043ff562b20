"""Dynamic scenes with ground truth: signal/noise separation, motion masks, the static background.

    python benchmarks/bench_dynamic.py                    # full size (several minutes on 2 cores)
    python benchmarks/bench_dynamic.py --quick
    python benchmarks/bench_dynamic.py --tiny --out /tmp/bench
    python benchmarks/bench_dynamic.py --model model.pt   # also evaluate a trained U-Net

The Noise2Image paper shows its dynamic-scene pipeline (§4.1, §5.3: denoiser -> motion mask ->
moving-window noise counts -> reconstruction of the static background) on one real recording,
without ground truth. Here :func:`evnoise.simulate_video` makes recordings of moving objects over
static natural-image backgrounds, so that the true background, the true motion mask (where an
object covers the background) and the true signal/noise label of every event are known.

Scenes (backgrounds are scikit-image's bundled photos, read from the installed package at run time;
none is stored in evnoise): ``sprites`` (discs moving and bouncing over ``camera``), ``bar`` (a
dark bar rotating like a fan over ``coffee``) and ``patch`` (a square of ``brick`` texture
translating over ``chelsea``). Illuminance is display-encoded photo -> linear -> 0 .. 20 lux (the
low-light regime where noise events carry the image), preset ``evk3-hd``.

Reported: separator precision/recall of signal and noise events, mask IoU per time step, and the
background PSNR/SSIM in *static regions* (2x2 bins never covered by an object during the count
window) against window length, for three pipelines: ``naive`` (every event counted, no mask),
``oracle`` (the simulator's labels, mask from the true signal events) and ``density`` (the
density separator and the mask made from its signal events). Reconstruction: the model-based
per-pixel maximum-likelihood inversion (``evnoise.reconstruct.baselines.MLInversion``), and a
U-Net if ``--model`` is given or ``--train-minutes`` > 0 (a small one trained on other photos).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

import evnoise as ev  # noqa: E402
from evnoise.motion import BackgroundHold, MaskParams, bin_rates, iter_motion  # noqa: E402
from evnoise.separation import ActivityFilter, DensityFilter, Separator, separation_scores  # noqa: E402

SIZES = {"tiny": dict(scale=0.02, repeats=1), "quick": dict(scale=0.25, repeats=3), "full": dict(scale=1.0, repeats=5)}
MAX_LUX = 20.0
BINNING = 2
SCENE_PHOTOS = {"sprites": "camera", "bar": "coffee", "patch": "chelsea"}
TEXTURE = "brick"
#: photos the optional U-Net is trained on: disjoint from the scenes' photos
TRAIN_PHOTOS = ("astronaut", "grass", "gravel", "moon", "coins", "rocket", "motorcycle_left", "page",
                "immunohistochemistry", "cell", "text", "hubble_deep_field")
FPS = 10.0  # motion steps per second (the evk3-hd pixel samples the scene 22 times per second)


# ------------------------------------------------------------------------------ scenes
def _triangle(u):
    """Triangle wave in [0, 1] with period 2 (position of a point bouncing between two walls)."""
    u = np.mod(u, 2.0)
    return np.where(u <= 1.0, u, 2.0 - u)


def _photo(name, shape):
    from skimage.transform import resize

    from evnoise.reconstruct.data import skimage_photos

    img = skimage_photos((name,))[name]
    h, w = shape
    # centre crop to the aspect ratio, then resize (anti-aliased)
    ih, iw = img.shape
    if ih * w > iw * h:
        ch = int(round(iw * h / w))
        img = img[(ih - ch) // 2:(ih - ch) // 2 + ch]
    else:
        cw = int(round(ih * w / h))
        img = img[:, (iw - cw) // 2:(iw - cw) // 2 + cw]
    return np.clip(resize(img, shape, anti_aliasing=True), 0.0, 1.0)


def _to_lux(display):
    from evnoise.reconstruct.imaging import srgb_decode

    return srgb_decode(display) * MAX_LUX


@dataclass
class Scene:
    """A static background with moving objects; ``render(t)`` gives illuminance and coverage."""

    name: str
    shape: tuple
    duration_s: float
    background: np.ndarray  # lux (H, W)
    objects: list = field(default_factory=list)  # callables t -> (cover (H, W) bool, lux (H, W) or float)
    sim_fps: float = 50.0

    def render(self, t):
        lux = self.background.copy()
        cover = np.zeros(self.shape, dtype=bool)
        for obj in self.objects:
            c, value = obj(t)
            lux[c] = value[c] if np.ndim(value) else value
            cover |= c
        return lux, cover

    def cover_between(self, t0, t1, n=6):
        """Pixels covered by an object at any of ``n`` times in ``[t0, t1]``."""
        out = np.zeros(self.shape, dtype=bool)
        for t in np.linspace(t0, t1, n):
            out |= self.render(float(t))[1]
        return out

    @property
    def timestamps(self):
        return np.arange(int(round(self.duration_s * self.sim_fps)) + 1) / self.sim_fps


class _Frames:
    """Frames rendered on demand (the simulator reads any sequence of 2-D arrays)."""

    def __init__(self, scene):
        self.scene = scene
        self.ts = scene.timestamps

    def __len__(self):
        return len(self.ts)

    def __getitem__(self, i):
        return self.scene.render(float(self.ts[i]))[0]


def make_scene(kind: str, shape, duration_s: float) -> Scene:
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    bg = _to_lux(_photo(SCENE_PHOTOS[kind], shape))
    scene = Scene(kind, tuple(shape), float(duration_s), bg)
    s = min(h, w)
    if kind == "sprites":
        # (radius, x0, y0, vx, vy in sensor widths per second, lux)
        for rad, x0, y0, vx, vy, lux in ((0.12, 0.2, 0.3, 0.35, 0.22, 0.15), (0.09, 0.7, 0.6, -0.25, 0.4, 0.15),
                                         (0.08, 0.5, 0.2, 0.5, -0.3, MAX_LUX)):
            r = rad * s

            def obj(t, r=r, x0=x0, y0=y0, vx=vx, vy=vy, lux=lux):
                cx = r + (w - 2 * r) * _triangle(x0 + vx * w / (w - 2 * r) * t)
                cy = r + (h - 2 * r) * _triangle(y0 + vy * w / (h - 2 * r) * t)
                return (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r, lux

            scene.objects.append(obj)
    elif kind == "bar":
        half_len, half_wid, omega = 0.42 * s, max(1.5, 0.05 * s), 2 * math.pi * 0.35

        def obj(t):
            a = omega * t
            u = (xx - w / 2) * math.cos(a) + (yy - h / 2) * math.sin(a)
            v = -(xx - w / 2) * math.sin(a) + (yy - h / 2) * math.cos(a)
            return (np.abs(u) <= half_len) & (np.abs(v) <= half_wid), 0.1

        scene.objects.append(obj)
    elif kind == "patch":
        side = int(round(0.4 * s))
        tex = _photo(TEXTURE, (side, side))
        tex = _to_lux((tex - tex.min()) / max(np.ptp(tex), 1e-9))  # stretched: full 0-20 lux contrast
        top = (h - side) // 2

        def obj(t):
            x0 = int(round((w - side) * _triangle(0.1 + 0.3 * t)))
            cover = np.zeros(shape, dtype=bool)
            cover[top:top + side, x0:x0 + side] = True
            lux = np.zeros(shape)
            lux[top:top + side, x0:x0 + side] = tex
            return cover, lux

        scene.objects.append(obj)
    else:
        raise ValueError(f"unknown scene {kind!r}")
    return scene


def simulate(scene: Scene, params, seed: int):
    frames = _Frames(scene)
    return ev.simulate_video(frames, frames.ts, params, rng=seed, return_labels=True)


# ------------------------------------------------------------------------------ metrics
def region_metrics(pred, target, region, ssim_map):
    """PSNR (dB) and mean SSIM over the bins of ``region`` (the SSIM map is of the whole image)."""
    if not region.any():
        return math.nan, math.nan
    mse = float(np.mean((pred[region] - target[region]) ** 2))
    psnr = math.inf if mse == 0 else 10 * math.log10(1.0 / mse)
    return psnr, float(ssim_map[region].mean())


def ssim_map(pred, target):
    from skimage.metrics import structural_similarity

    from evnoise.reconstruct.metrics import SSIM_SETTINGS

    return structural_similarity(target, pred, full=True, **SSIM_SETTINGS)[1]


def rate_error(est, true, region):
    """RMS error of binned ON/OFF rates over ``region``, relative to the mean true rate there."""
    if not region.any():
        return math.nan
    d = est[:, region] - true[:, region]
    return float(np.sqrt(np.mean(d * d)) / max(np.mean(true[:, region]), 1e-12))


def iou(a, b):
    union = np.count_nonzero(a | b)
    return math.nan if union == 0 else np.count_nonzero(a & b) / union


def _bin_all(mask, b=BINNING):
    h, w = mask.shape[0] // b, mask.shape[1] // b
    return mask[:h * b, :w * b].reshape(h, b, w, b).all(axis=(1, 3))


# ------------------------------------------------------------------------------ reconstructors
class _ML:
    name = "ML inversion"

    def __init__(self, params):
        from evnoise.reconstruct.baselines import MLInversion

        self.inv = MLInversion(params, max_lux=MAX_LUX, binning=BINNING)
        self.binning = BINNING

    def __call__(self, binned_counts, window_s):
        return self.inv.display(binned_counts, window_s)


class _UNet:
    def __init__(self, path, name="U-Net"):
        from evnoise.reconstruct.infer import Reconstructor

        self.rec = Reconstructor(path, threads=2)
        self.binning = self.rec.binning
        self.name = name
        if self.binning != BINNING:
            raise SystemExit(f"the model uses {self.binning}x{self.binning} binning; this benchmark needs {BINNING}")

    def __call__(self, binned_counts, window_s):
        return self.rec.predict_binned(binned_counts, window_s)


def train_tiny_unet(path: Path, params, window_s: float, minutes: float, seed: int = 0) -> Path:
    """evnoise's default small U-Net trained for ``minutes`` on photos that no scene uses."""
    from evnoise.reconstruct.data import ResampledPairs
    from evnoise.reconstruct.train import TrainConfig, train

    lux = [_to_lux(_photo(name, (192, 192))) for name in TRAIN_PHOTOS]
    data = ResampledPairs(lux, params, window_s=window_s, max_lux=MAX_LUX, binning=BINNING, sources=list(TRAIN_PHOTOS),
                          seed=seed)
    config = TrainConfig(epochs=1000, steps_per_epoch=20, batch_size=8, crop=48, max_minutes=minutes, patience=None,
                         val_crop=96, seed=seed)
    train(data, path, config=config, overwrite=True, progress=False, plot=False, threads=2,
          data_description=f"bench_dynamic: {len(TRAIN_PHOTOS)} scikit-image photos, window {window_s} s")
    return path


# ------------------------------------------------------------------------------ pipelines
PIPELINES = ("naive", "oracle", "density")
REGIONS = ("static", "behind")


def run_pipeline(events, labels, shape, scene, params, *, window_s, pipeline, reconstructors, mask_params, n_eval,
                 keep=None, on_motion="skip"):
    """Rate error, PSNR/SSIM per region (means over ``n_eval`` frames) and the mask IoU per step."""
    from evnoise.reconstruct.imaging import bin_mean, lux_to_display

    kw = {"fps": FPS, "window_s": window_s, "mask": mask_params, "t_end_s": scene.duration_s, "on_motion": on_motion}
    if pipeline == "naive":
        kw["separator"] = None
    elif pipeline == "oracle":
        kw["is_signal"] = labels
    else:
        kw["separator"] = DensityFilter()
    target = lux_to_display(bin_mean(scene.background, BINNING), MAX_LUX)
    true_rates = bin_rates(ev.expected_rate(scene.background, params), BINNING)
    hold = BackgroundHold(shape, min_exposure_s=window_s)
    w_steps = max(1, int(round(window_s * FPS)))
    n_steps = int(round(scene.duration_s * FPS))
    eval_at = set(np.unique(np.linspace(w_steps - 1, n_steps - 1, n_eval).round().astype(int)).tolist())
    truth_steps = []
    ious = []
    acc = {}
    for frame in iter_motion(events, shape, **kw):
        t1 = frame.t_end_us * 1e-6
        truth = scene.cover_between(t1 - frame.step_s, t1)
        truth_steps.append(truth)
        if pipeline != "naive" and (truth.any() or frame.mask.any()):
            ious.append(iou(frame.mask, truth))
        rates = hold.update(frame)
        if frame.index not in eval_at:
            continue
        covered = np.any(truth_steps[-w_steps:], axis=0)
        regions = {"static": _bin_all(~covered), "behind": ~_bin_all(~covered)}
        est = bin_rates(rates, BINNING)
        for region, m in regions.items():
            acc.setdefault(("rate", region), []).append(rate_error(est, true_rates, m))
        for r in reconstructors:
            pred = r(est * frame.window_s, frame.window_s)
            smap = ssim_map(pred, target)
            for region, m in regions.items():
                acc.setdefault((r.name, region), []).append(region_metrics(pred, target, m, smap))
            if keep is not None and frame.index == max(eval_at):
                keep[r.name] = dict(pred=pred, mask=frame.mask, truth=truth, target=target,
                                    counts=bin_rates(frame.counts, BINNING))
    out = {}
    for key, values in acc.items():
        arr = np.array(values, dtype=float)
        out[key] = tuple(np.nanmean(arr, axis=0).tolist()) if arr.ndim > 1 else float(np.nanmean(arr))
    return out, (float(np.nanmean(ious)) if ious else math.nan)


def static_reference(scene, params, window_s, reconstructors, seed):
    """The same background without objects: counts of one window straight from the model."""
    from evnoise.reconstruct.imaging import bin_mean, lux_to_display

    target = lux_to_display(bin_mean(scene.background, BINNING), MAX_LUX)
    true_rates = bin_rates(ev.expected_rate(scene.background, params), BINNING)
    counts = bin_rates(ev.sample_counts(scene.background, params, window_s, rng=seed), BINNING)
    everywhere = np.ones(target.shape, dtype=bool)
    out = {("rate", "static"): rate_error(counts / window_s, true_rates, everywhere)}
    for r in reconstructors:
        pred = r(counts, window_s)
        out[(r.name, "static")] = region_metrics(pred, target, everywhere, ssim_map(pred, target))
    return out


# ------------------------------------------------------------------------------ the benchmark
def _dims(scale):
    if scale >= 1.0:
        return (120, 160), 24.0, [0.5, 1.0, 2.0, 4.0, 8.0, 16.0], 12
    if scale >= 0.25:
        return (72, 96), 12.0, [0.5, 1.0, 2.0, 4.0, 8.0], 8
    return (48, 64), 4.0, [1.0, 2.0], 4


def _fmt(v, digits=2):
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def bench_dynamic(size: dict, out_dir: Path, report: list, *, model: Path | None = None,
                  train_minutes: float | None = None) -> None:
    """Append the dynamic-scene section to ``report`` and write ``dynamic_strip.png`` into ``out_dir``.

    ``size`` has ``scale`` in (0, 1] and ``repeats`` (seeds per scene, at most 3 used).
    ``model``: a trained checkpoint to evaluate too; ``train_minutes``: train a small U-Net for
    that long first (default: 0 at tiny scale, 3 at quick, 10 at full).
    """
    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    params = ev.load_preset("evk3-hd")
    shape, duration, windows, n_eval = _dims(size["scale"])
    repeats = max(1, min(int(size["repeats"]), 3))
    if train_minutes is None:
        train_minutes = 0.0 if size["scale"] < 0.25 else (3.0 if size["scale"] < 1.0 else 10.0)
    mask_params = MaskParams()
    d = DensityFilter()
    separators = {
        f"density, default ({2 * d.radius_px + 1}x{2 * d.radius_px + 1}, -{d.window_us // 1000}/"
        f"+{d.lookahead_us // 1000} ms, >= {d.threshold}, {d.polarity} polarity)": d,
        "density, YNoise-like causal (3x3, 10 ms, >= 2)": DensityFilter(window_us=10_000, lookahead_us=0, threshold=2),
        "density, causal (3x3, 20 ms, >= 3)": DensityFilter(window_us=20_000, lookahead_us=0, threshold=3),
        "density, 5x5, +-5 ms, >= 3, same polarity": DensityFilter(radius_px=2, window_us=5_000, lookahead_us=5_000,
                                                                   threshold=3, polarity="same"),
        "background activity (8 neighbours, 5 ms)": ActivityFilter(window_us=5_000),
        "background activity (8 neighbours, 20 ms)": ActivityFilter(window_us=20_000),
    }
    reconstructors = [_ML(params)]
    unet_note = "No U-Net in this run (pass --model or --train-minutes)."
    if model is not None:
        reconstructors.append(_UNet(model))
        unet_note = f"U-Net: the checkpoint `{model.name}`."
    elif train_minutes > 0:
        try:
            import torch  # noqa: F401
        except ImportError:
            unet_note = "No U-Net (torch is not installed)."
        else:
            t0 = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:  # the checkpoint (10 MB) is not kept
                path = train_tiny_unet(Path(tmp) / "bench_dynamic_unet.pt", params, 2.0, train_minutes)
                reconstructors.append(_UNet(path, name="U-Net"))
            unet_note = (f"U-Net: evnoise's default small U-Net trained here for {train_minutes:g} min "
                         f"({time.perf_counter() - t0:.0f} s wall) on 2 CPU threads, window 2 s, "
                         f"{len(TRAIN_PHOTOS)} other scikit-image photos; applied at every window length.")
    sep_rows = {name: [] for name in separators}
    rates_rows = []
    mask_rows = {"oracle": [], "density": []}
    bg = {}
    ref = {}
    strip = {}
    sim_time = 0.0
    mid = windows[len(windows) // 2]
    for kind in SCENE_PHOTOS:
        scene = make_scene(kind, shape, duration)
        for rep in range(repeats):
            seed = 1000 * rep + len(kind)
            t0 = time.perf_counter()
            events, labels = simulate(scene, params, seed=seed)
            sim_time += time.perf_counter() - t0
            rates_rows.append((kind, events.size / duration, float(labels.mean())))
            for name, flt in separators.items():
                sep = Separator(shape, flt)
                done = [sep.push(events), sep.finish()]
                pred = np.concatenate([x[1] for x in done])
                sep_rows[name].append((kind, separation_scores(pred, labels)))
            for w in windows:
                for key, value in static_reference(scene, params, w, reconstructors, seed).items():
                    ref.setdefault((w, *key), []).append(value)
                for pipeline in PIPELINES:
                    keep = {} if (rep == 0 and w == mid and pipeline in ("naive", "density")) else None
                    res, m_iou = run_pipeline(events, labels, shape, scene, params, window_s=w, pipeline=pipeline,
                                              reconstructors=reconstructors, mask_params=mask_params, n_eval=n_eval,
                                              keep=keep)
                    for key, value in res.items():
                        bg.setdefault((w, pipeline, *key), []).append(value)
                    if pipeline != "naive" and w == windows[0]:
                        mask_rows[pipeline].append((kind, m_iou))
                    if keep:
                        strip.setdefault(kind, {})[pipeline] = keep
                res, _ = run_pipeline(events, labels, shape, scene, params, window_s=w, pipeline="density",
                                      reconstructors=[], mask_params=mask_params, n_eval=n_eval, on_motion="restart")
                for key, value in res.items():
                    bg.setdefault((w, "density, restart", *key), []).append(value)

    def mean(values, i=None):
        vals = [v if i is None else v[i] for v in values]
        vals = [v for v in vals if v is not None and not (isinstance(v, float) and math.isnan(v))]
        return float(np.mean(vals)) if vals else math.nan

    lines = ["## Dynamic scenes: signal/noise separation, motion mask, static background (ground truth)", ""]
    lines.append(
        f"Scenes: {', '.join(f'`{k}` over `{v}`' for k, v in SCENE_PHOTOS.items())} (`benchmarks/bench_dynamic.py`), "
        f"{shape[1]}x{shape[0]} pixels, {duration:g} s, frames at 50 Hz, 0-{MAX_LUX:g} lux, preset `evk3-hd`, "
        f"{repeats} seed(s) per scene; motion steps at {FPS:g} Hz (`evnoise.motion`). Simulation: {sim_time:.1f} s in "
        "total.")
    lines += ["", "| scene | events/s | signal share (truth) |", "|---|---|---|"]
    for kind in SCENE_PHOTOS:
        rr = [r for r in rates_rows if r[0] == kind]
        lines.append(f"| {kind} | {mean([r[1] for r in rr]):,.0f} | {mean([r[2] for r in rr]):.1%} |")
    keys = ("signal_precision", "signal_recall", "noise_precision", "noise_recall")
    lines += ["", "### Separator: precision and recall against the simulator's labels", "",
              "Signal precision: share of the events called signal that are signal; noise recall: share of the true "
              "noise events kept as noise (what the background receives). Means over scenes and seeds.", "",
              "| separator | signal precision | signal recall | noise precision | noise recall |",
              "|---|---|---|---|---|"]
    for name, rows in sep_rows.items():
        lines.append(f"| {name} | " + " | ".join(_fmt(mean([r[1][k] for r in rows]), 3) for k in keys) + " |")
    first = next(iter(separators))
    lines += ["", "Per scene, default density filter:", "",
              "| scene | signal precision | signal recall | noise precision | noise recall |", "|---|---|---|---|---|"]
    for kind in SCENE_PHOTOS:
        rr = [r[1] for r in sep_rows[first] if r[0] == kind]
        lines.append(f"| {kind} | " + " | ".join(_fmt(mean([r[k] for r in rr]), 3) for k in keys) + " |")
    lines += ["", "### Motion mask: IoU with the true object coverage, per time step", "",
              f"Mask: signal events of the last {mask_params.window_s:g} s summed over "
              f"{2 * mask_params.radius_px + 1}x{2 * mask_params.radius_px + 1} pixels, >= {mask_params.threshold} "
              f"events, dilated by a disc of {mask_params.dilation_px} px. Truth: the pixels an object covers at some "
              "time in the step (uniform object interiors fire no signal events: only the dilation covers them). Mean "
              "over the steps where mask or truth is non-empty.", "",
              "| scene | mask from the true signal events | mask from the density separator |", "|---|---|---|"]
    for kind in SCENE_PHOTOS:
        lines.append(f"| {kind} | {_fmt(mean([r[1] for r in mask_rows['oracle'] if r[0] == kind]), 3)} | "
                     f"{_fmt(mean([r[1] for r in mask_rows['density'] if r[0] == kind]), 3)} |")
    names = [r.name for r in reconstructors]
    lines += ["", "### Static background against window length", "",
              "Pipelines: `naive` counts every event, no mask; `oracle` uses the simulator's labels (mask from the "
              "true signal events); `density` uses the default density separator. `static reference`: the same "
              "background *without* objects, counts of one window drawn from the model (the best any pipeline can do; "
              "scored over all bins). "
              "Regions, in 2x2 bins: *static* = no object covered the bin during the window; *behind* = an object "
              "covered it at some time in the window (under the object now, or uncovered too recently). Rate error: "
              "RMS error of the binned ON/OFF rates relative to the mean true rate (the pipeline alone, before any "
              f"reconstruction). Means over {n_eval} frames per recording, scenes and seeds. {unet_note} Image metrics "
              "mix the pipeline with the reconstructor's own error (compare them with the static reference); the rate "
              "error measures the pipeline alone.", "",
              "| window | pipeline | rate error static / behind | " + " | ".join(
                  f"{n} PSNR static / behind | {n} SSIM static / behind" for n in names) + " |",
              "|---|---|---|" + "---|---|" * len(names)]
    for w in windows:
        cells = [_fmt(mean(ref.get((w, "rate", "static"), [])), 3) + " / –"]
        for n in names:
            vals = ref.get((w, n, "static"), [])
            cells += [f"{_fmt(mean(vals, 0))} / –", f"{_fmt(mean(vals, 1), 3)} / –"]
        lines.append(f"| {w:g} s | static reference | " + " | ".join(cells) + " |")
        for pipeline in PIPELINES:
            cells = [" / ".join(_fmt(mean(bg.get((w, pipeline, "rate", reg), [])), 3) for reg in REGIONS)]
            for n in names:
                cells.append(" / ".join(_fmt(mean(bg.get((w, pipeline, n, reg), []), 0)) for reg in REGIONS))
                cells.append(" / ".join(_fmt(mean(bg.get((w, pipeline, n, reg), []), 1), 3) for reg in REGIONS))
            lines.append(f"| {w:g} s | {pipeline} | " + " | ".join(cells) + " |")
    lines += ["", "What a masked step does to a pixel's window (`on_motion`, density pipeline), rate error static / "
              "behind: `skip` (default: the step is left out, the pixel's other static steps in the window still "
              "count) against `restart` (the window empties and counting restarts after the motion).", "",
              "| window | skip | restart |", "|---|---|---|"]
    for w in windows:
        cells = [" / ".join(_fmt(mean(bg.get((w, pipe, "rate", reg), [])), 3) for reg in REGIONS)
                 for pipe in ("density", "density, restart")]
        lines.append(f"| {w:g} s | " + " | ".join(cells) + " |")
    lines.append("")
    if strip:
        _plot_strip(strip, names[-1], out_dir / "dynamic_strip.png")
        lines += [f"Figure: moving-window counts of all events (the naive input), motion mask of the density pipeline "
                  f"(red; true coverage outlined in yellow), reconstruction ({names[-1]}) from the density pipeline "
                  "and "
                  f"from the naive window, true background; window {mid:g} s, last evaluated frame, first seed.", "",
                  "![dynamic strip](dynamic_strip.png)", ""]
    lines.append(f"Section generated in {time.perf_counter() - t_start:.0f} s.")
    lines.append("")
    report.extend(lines)


def _plot_strip(strip, rname, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = list(strip)
    fig, axes = plt.subplots(len(kinds), 5, figsize=(12, 2.3 * len(kinds)), squeeze=False)
    for row, kind in zip(axes, kinds):
        d = strip[kind].get("density", {}).get(rname)
        n = strip[kind].get("naive", {}).get(rname)
        if d is None:
            continue
        counts = n["counts"].sum(axis=0) if n is not None else d["counts"].sum(axis=0)
        row[0].imshow(counts, cmap="gray")
        row[0].set_title(f"{kind}: counts (naive window)", fontsize=8)
        rgb = np.repeat((d["target"] * 0.6)[..., None], 3, axis=2)
        m = d["mask"][: 2 * d["target"].shape[0]:2, : 2 * d["target"].shape[1]:2]
        rgb[m] = [0.9, 0.15, 0.15]
        row[1].imshow(rgb)
        tr = d["truth"][::2, ::2][: rgb.shape[0], : rgb.shape[1]]
        row[1].contour(tr, levels=[0.5], colors="yellow", linewidths=0.7)
        row[1].set_title("mask (red), truth (yellow)", fontsize=8)
        row[2].imshow(d["pred"], cmap="gray", vmin=0, vmax=1)
        row[2].set_title(f"{rname}: density pipeline", fontsize=8)
        if n is not None:
            row[3].imshow(n["pred"], cmap="gray", vmin=0, vmax=1)
        row[3].set_title(f"{rname}: naive window", fontsize=8)
        row[4].imshow(d["target"], cmap="gray", vmin=0, vmax=1)
        row[4].set_title("true background", fontsize=8)
        for a in row:
            a.set_xticks([])
            a.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--quick", action="store_true", help="smaller sizes and fewer repeats")
    group.add_argument("--tiny", action="store_true", help="smoke test sizes")
    parser.add_argument("--out", type=Path, default=HERE, help="folder for DYNAMIC.md and the figure")
    parser.add_argument("--model", type=Path, default=None, help="a trained reconstructor checkpoint to evaluate too")
    parser.add_argument("--train-minutes", type=float, default=None,
                        help="train a small U-Net for this long first (default 0 tiny, 3 quick, 10 full)")
    args = parser.parse_args(argv)
    size = SIZES["tiny" if args.tiny else "quick" if args.quick else "full"]
    args.out.mkdir(parents=True, exist_ok=True)
    report = ["# evnoise: dynamic-scene benchmark", ""]
    bench_dynamic(size, args.out, report, model=args.model, train_minutes=args.train_minutes)
    (args.out / "DYNAMIC.md").write_text("\n".join(report) + "\n", encoding="utf-8")
    print(f"wrote {args.out / 'DYNAMIC.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
