"""Train the reconstructor that evnoise ships (``evnoise/models/evk3-hd.pt``), reproducibly.

Usage (``python -m evnoise.reconstruct.pretrain`` is the same command as ``evnoise pretrain``)::

    evnoise pretrain --out evk3-hd-run.pt --max-minutes 55                            # train
    evnoise pretrain --make-test-sets heldout/                                         # test sets
    evnoise evaluate heldout/dead-leaves --model evk3-hd-run.pt --json id.json        # scores
    evnoise pretrain --ship evk3-hd-run.pt --scores dead-leaves=id.json photos=ood.json \\
        --out evnoise/models/evk3-hd.pt                                                # package it

Training data (nothing is downloaded):

* procedural dead-leaves scenes (:func:`evnoise.generators.dead_leaves`, 640x360), drawn
  from ``seed``;
* the photos that installed packages ship (:class:`evnoise.generators.PackagePhotos`), except
  :data:`HELD_OUT_PHOTOS`, which are kept for the out-of-distribution test set;

Every training crop gets a fresh draw of everything random: position, brightness (the scene's
white level log-uniform in :data:`WHITE_RANGE_LUX`), contrast (``Y -> Y ** gamma``, gamma
log-uniform in :data:`CONTRAST_RANGE`), flips and rotations, and the noise counts themselves
(re-drawn on the fly with the dataset generator's exact sampler,
:class:`evnoise.generators.pairs.CountSampler`: the event process's own count distribution).
With ``--mismatch-sigma`` the thresholds also vary per pixel, a fresh pattern per crop
(through :func:`evnoise.sample_counts`; much slower). Targets are display-encoded like
``make-dataset``'s: ``srgb(lux / DISPLAY_WHITE_LUX)``, clipped to ``[0, 1]``.

Validation uses fixed draws of separate dead-leaves scenes. Randomness derives from
``--seed`` only (see :mod:`evnoise.reconstruct.train`), so the same command gives the same
model on the same software.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from ..errors import InputError, ParameterError

__all__ = ["SceneCrops", "build_training_data", "make_test_sets", "ship", "main", "HELD_OUT_PHOTOS"]

PRESET = "evk3-hd"
SENSOR_SHAPE = (360, 640)  # (H, W) of the procedural scenes; photos are scaled to this height
DISPLAY_WHITE_LUX = 18.0  # lux shown as white in the targets (the Noise2Image monitor's white)
WHITE_RANGE_LUX = (9.0, 36.0)  # the scene's full-scale white, log-uniform per crop
CONTRAST_RANGE = (0.8, 1.25)  # gamma of Y -> Y ** gamma, log-uniform per crop
WINDOW_S = 1.0
PHOTO_SHARE = 0.4  # share of training crops cut from photos (the rest: dead leaves)
#: photos never used in training or validation: the out-of-distribution test set
HELD_OUT_PHOTOS = ("skimage/astronaut.png", "skimage/camera.png", "skimage/coffee.png", "skimage/rocket.jpg",
                   "matplotlib/grace_hopper.jpg", "sklearn/china.jpg")
TEST_SEED = 7  # seed of the held-out test sets (the training scenes come from --seed)


def _log_uniform(rng, lo: float, hi: float) -> float:
    return lo if lo == hi else float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _resize_to_height(y: np.ndarray, height: int) -> np.ndarray:
    """Linear luminance resized (area average down, bilinear up) to ``height`` rows."""
    from PIL import Image

    h, w = y.shape
    if h == height:
        return y
    width = max(1, round(w * height / h))
    method = Image.Resampling.BOX if height < h else Image.Resampling.BILINEAR
    out = Image.fromarray(y.astype(np.float32), mode="F").resize((width, height), method)
    return np.clip(np.asarray(out, dtype=np.float64), 0.0, 1.0)


def training_photos(*, height: int = SENSOR_SHAPE[0]) -> dict:
    """``{id: linear luminance}`` of the package photos used for training (not held out)."""
    from ..generators import PackagePhotos
    from ..generators.sources import LoadContext

    source = PackagePhotos()
    ctx = LoadContext(sensor_shape=SENSOR_SHAPE, encoding="srgb", clip_invalid=True, seed=0)
    out = {}
    for item in source.items():
        if item in HELD_OUT_PHOTOS:
            continue
        y, kind = source.load(item, ctx)
        y = np.asarray(y, dtype=np.float64)
        if kind != "display":
            y = y / max(float(y.max()), 1e-12)
        out[item] = _resize_to_height(np.clip(y, 0.0, 1.0), height)
    return out


def dead_leaves_scenes(count: int, seed: int, tag: str, *, progress: bool = False) -> dict:
    """``{id: linear luminance}`` of ``count`` dead-leaves scenes drawn from ``(seed, tag, k)``."""
    import hashlib

    from ..generators.procedural import dead_leaves
    from ..radiometry import srgb_to_linear

    word = int.from_bytes(hashlib.sha256(tag.encode()).digest()[:4], "little")
    iterator = range(count)
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(iterator, desc=f"dead leaves ({tag})", unit="scene")
    return {f"dead-leaves-{tag}/{k:04d}":
            srgb_to_linear(dead_leaves(SENSOR_SHAPE, np.random.default_rng([seed, word, k]))) for k in iterator}


class SceneCrops:
    """Training scenes whose crops, brightness, contrast and noise counts are drawn afresh each time.

    A pair dataset for :func:`evnoise.reconstruct.train.train` (``len``, ``ds[i]``, and
    ``sample(i, rng, crop)``, which the trainer calls with a fresh generator per crop).

    Parameters
    ----------
    scenes : dict
        ``{source id: linear luminance (H, W) in [0, 1]}``.
    params : NoiseParams
        Noise model (``eps_sigma > 0``: a fresh per-pixel threshold pattern per crop).
    window_s : float
        Integration window, seconds.
    white_lux : float
        Lux shown as white in the targets.
    white_range_lux : (float, float)
        The scene's full-scale white is drawn log-uniformly from this range, per crop.
    contrast : (float, float)
        Range of the contrast exponent (log-uniform).
    weights : sequence of float, optional
        Sampling weight of each scene (default uniform); the trainer draws ``i`` uniformly, so
        ``sample`` redraws the scene from these weights with its generator.
    binning : int
        Counts are summed over ``binning x binning`` blocks.
    seed : int
        Seed of the fixed view ``ds[i]`` (whole scene, middle brightness).
    """

    def __init__(self, scenes: dict, params, *, window_s: float = WINDOW_S, white_lux: float = DISPLAY_WHITE_LUX,
                 white_range_lux=WHITE_RANGE_LUX, contrast=CONTRAST_RANGE, weights=None, binning: int = 2,
                 seed: int = 0):
        from ..generators.config import PairConfig
        from ..generators.pairs import CountSampler

        if not scenes:
            raise InputError("SceneCrops needs at least one scene")
        self.sources = list(scenes)
        self.scenes = [np.asarray(scenes[k], dtype=np.float64) for k in self.sources]
        self.params = params
        self.window_s = float(window_s)
        self.windows_s = (self.window_s,)
        self.max_lux = float(white_lux)
        self.white_range_lux = tuple(float(v) for v in white_range_lux)
        self.contrast = tuple(float(v) for v in contrast)
        self.binning = int(binning)
        self.seed = int(seed)
        if weights is None:
            weights = np.ones(len(self.scenes))
        w = np.asarray(weights, dtype=np.float64)
        self.weights = w / w.sum()
        config = PairConfig(sensor_shape=SENSOR_SHAPE, binning=self.binning, windows_s=(self.window_s,),
                            max_lux=self.white_range_lux, white_lux=self.max_lux, params=params, seed=0)
        self.sampler = CountSampler(config)
        self.step_lux = config.lux_step

    def __len__(self):
        return len(self.scenes)

    def __getitem__(self, i):
        rng = np.random.default_rng([self.seed, int(i)])
        return self._make(int(i), rng, None, white=math.sqrt(self.white_range_lux[0] * self.white_range_lux[1]),
                          gamma=1.0)

    def sample(self, i, rng, crop=None):
        """A fresh pair; ``crop`` is in binned pixels (the scene is picked by the weights)."""
        j = int(rng.choice(len(self.scenes), p=self.weights))
        white = _log_uniform(rng, *self.white_range_lux)
        gamma = _log_uniform(rng, *self.contrast)
        return self._make(j, rng, crop, white=white, gamma=gamma)

    def _make(self, j, rng, crop, *, white, gamma):
        from ..generators.pairs import quantise
        from .imaging import bin_mean, lux_to_display

        y = self.scenes[j]
        b = self.binning
        h, w = (y.shape[0] // b) * b, (y.shape[1] // b) * b
        if crop is None:
            r0, c0, ch, cw = 0, 0, h, w
        else:
            side = crop * b
            if side > h or side > w:
                raise InputError(f"crop {crop} binned pixels is larger than scene {self.sources[j]}")
            r0, c0 = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
            ch = cw = side
        lux = white * np.power(y[r0:r0 + ch, c0:c0 + cw], gamma)
        codes, lux_q = quantise(lux, self.step_lux)
        seed = int(rng.integers(2**63 - 1))
        counts = self.sampler.sample(codes, int(round(self.window_s * 1e6)), seed)
        image = lux_to_display(bin_mean(lux_q, b), self.max_lux).astype(np.float32)
        return {"counts": np.minimum(counts, 65535).astype(np.uint16), "image": image, "window_s": self.window_s,
                "source": self.sources[j]}


def build_training_data(*, seed: int = 0, n_dead_leaves: int = 120, n_val: int = 12, mismatch_sigma: float = 0.0,
                        photos: bool = True, progress: bool = True, white_range_lux=WHITE_RANGE_LUX):
    """``(train, val, description)``: :class:`SceneCrops` of the training scenes and fixed validation pairs."""
    from ..params import load_preset
    from .data import PairList

    params = load_preset(PRESET)
    if mismatch_sigma:
        params = params.replace(eps_sigma=float(mismatch_sigma)) if hasattr(params, "replace") else \
            type(params).from_dict({**params.to_dict(), "eps_sigma": float(mismatch_sigma)})
    scenes = dead_leaves_scenes(n_dead_leaves, seed, "train", progress=progress)
    n_dl = len(scenes)
    photo_scenes = training_photos() if photos else {}
    scenes.update(photo_scenes)
    if photo_scenes:
        weights = [(1 - PHOTO_SHARE) / n_dl] * n_dl + [PHOTO_SHARE / len(photo_scenes)] * len(photo_scenes)
    else:
        weights = None
    white_range_lux = tuple(float(v) for v in white_range_lux)
    train = SceneCrops(scenes, params, weights=weights, seed=seed, white_range_lux=white_range_lux)
    val_scenes = SceneCrops(dead_leaves_scenes(n_val, seed, "val"), params, seed=seed + 1,
                            white_range_lux=(DISPLAY_WHITE_LUX, DISPLAY_WHITE_LUX), contrast=(1.0, 1.0))
    items = [val_scenes[i] for i in range(len(val_scenes))]
    val = PairList([it["counts"] for it in items], [it["image"] for it in items],
                   window_s=[it["window_s"] for it in items], sources=[it["source"] for it in items],
                   max_lux=DISPLAY_WHITE_LUX, params=params)
    description = (f"{n_dl} procedural dead-leaves scenes (640x360) and {len(photo_scenes)} package photos "
                   f"({', '.join(photo_scenes)}), {PHOTO_SHARE:.0%} of crops from photos; scene white "
                   f"{white_range_lux[0]:g}-{white_range_lux[1]:g} lux (log-uniform), contrast gamma "
                   f"{CONTRAST_RANGE[0]:g}-{CONTRAST_RANGE[1]:g}, display white {DISPLAY_WHITE_LUX:g} lux, "
                   f"window {WINDOW_S:g} s, counts re-drawn for every crop (exact sampler)"
                   + (f", threshold mismatch eps_sigma {mismatch_sigma:g}" if mismatch_sigma else ""))
    return train, val, description


def make_test_sets(out_dir, *, progress: bool = True) -> dict:
    """Write the held-out test sets (``dead-leaves`` and ``photos``) under ``out_dir``; returns their paths.

    The same sets come from the command line::

        evnoise make-dataset --procedural dead-leaves --count 20 --sensor 640x360 --crop 256 \\
            --crops-per-image 2 --window 1 --max-lux 18 --split 0,0,1 --seed 7 --out DIR/dead-leaves
        evnoise make-dataset PHOTO ... --sensor 640x360 --crop 256 --crops-per-image 4 --window 1 \\
            --max-lux 18 --split 0,0,1 --seed 7 --out DIR/photos      # PHOTO: the HELD_OUT_PHOTOS files
    """
    from ..generators import DeadLeaves, FilesSource, PairConfig, make_dataset
    from ..generators.sources import PackagePhotos

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    base = dict(sensor_shape=SENSOR_SHAPE, crop_shape=(256, 256), windows_s=(WINDOW_S,),
                max_lux=(DISPLAY_WHITE_LUX, DISPLAY_WHITE_LUX), splits=(0.0, 0.0, 1.0), seed=TEST_SEED, preset=PRESET)
    photos = PackagePhotos()
    paths = [str(photos._path(p)) for p in HELD_OUT_PHOTOS]
    made = {}
    make_dataset([DeadLeaves(20)], out_dir / "dead-leaves", PairConfig(crops_per_image=2, **base), progress=progress)
    made["dead-leaves"] = out_dir / "dead-leaves"
    make_dataset([FilesSource(tuple(paths))], out_dir / "photos", PairConfig(crops_per_image=4, **base),
                 progress=progress)
    made["photos"] = out_dir / "photos"
    return made


def scores_problem(result) -> str:
    """What in a held-out test set's scores is not what :func:`ship` takes (``""``: nothing).

    Scores are :func:`evnoise.reconstruct.evaluate.evaluate`'s result (as its JSON reads back):
    ``{"n": count, "metrics": {method: {name: [mean, ...] or null}}}`` with finite means.
    """
    import math

    def number(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    if not isinstance(result, dict):
        return f"it holds a JSON {type(result).__name__}, not an object"
    n = result.get("n")
    if n is not None and not (isinstance(n, int) and not isinstance(n, bool) and n >= 0):
        return f"its 'n' is {n!r}, not a count of pairs"
    metrics = result.get("metrics")
    if not isinstance(metrics, dict) or not metrics:
        return "it has no 'metrics' object of methods"
    for method, vals in metrics.items():
        if not isinstance(vals, dict):
            return f"metrics[{method!r}] is not an object of scores"
        for key, v in vals.items():
            if v is None:
                continue
            if not isinstance(v, list) or not v or not (v[0] is None or number(v[0])):
                return f"metrics[{method!r}][{key!r}] is not a list starting with a finite number (or null)"
    return ""


def ship(checkpoint, out, *, scores=None) -> Path:
    """Copy a trained checkpoint without its resumable state (last weights, optimiser), with its card.

    ``scores``: ``{test-set name: evaluate() JSON}``; each method's PSNR/SSIM/LPIPS means go to
    the card's ``held_out_scores``.
    """
    from .checkpoint import InputSpec, read_checkpoint, save_checkpoint
    from .unet import UNetConfig

    doc = read_checkpoint(checkpoint)
    train_state = {k: v for k, v in (doc.get("train") or {}).items() if k not in ("last_state_dict", "optimizer")}
    card = dict(doc.get("card") or {})
    if scores:
        if not isinstance(scores, dict):
            raise ParameterError(f"scores must be a dict of test-set name to evaluate() result, got "
                                 f"{type(scores).__name__}")
        for name, result in scores.items():
            problem = scores_problem(result)
            if problem:
                raise ParameterError(f"scores[{name!r}] is not an evaluate() result: {problem}"[:300])
        held = {}
        for name, result in scores.items():
            held[name] = {"pairs": result.get("n"), **{
                m: {k: (None if v is None or v[0] is None else round(float(v[0]), 4)) for k, v in vals.items()}
                for m, vals in result["metrics"].items()}}
        card["held_out_scores"] = held
    return save_checkpoint(out, model_config=UNetConfig.from_dict(dict(doc["model"])),
                           input_spec=InputSpec.from_dict(dict(doc["input"])), state_dict=doc["state_dict"],
                           train_state=train_state, card=card)


def main(argv=None) -> int:
    """``python -m evnoise.reconstruct.pretrain ARGS``: the same as ``evnoise pretrain ARGS`` (one declaration of
    its options, in :mod:`evnoise.cli.pretrain`)."""
    from ..cli import main as cli

    return cli(["pretrain", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
