"""
A tiny dataset, a tiny reconstructor, and the shipped one
=========================================================

Noise2Image recovers a still scene from its noise events alone: the noise rate depends on the
illuminance, so per-pixel counts carry an image. This example runs the whole pipeline at toy size
(about half a minute on a CPU):

1. :func:`evnoise.generators.make_dataset` makes NE2I count/image pairs from procedural dead-leaves
   scenes (:class:`evnoise.generators.DeadLeaves`; nothing downloaded), sharded and reproducible;
2. ``evnoise train`` trains a small U-Net for a few steps;
3. :class:`evnoise.reconstruct.Reconstructor` turns held-out counts into images, with the tiny
   model and with the model shipped for the ``evk3-hd`` preset
   (:func:`evnoise.reconstruct.default_model_path`), scored with
   :func:`evnoise.reconstruct.psnr` and :func:`evnoise.reconstruct.ssim`.

The command-line equivalents are ``evnoise make-dataset --procedural dead-leaves ...``,
``evnoise train ds --out model.pt`` and ``evnoise reconstruct events.h5 --model model.pt``.
"""

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import matplotlib.pyplot as plt

from evnoise.generators import DeadLeaves, PairConfig, PairDataset, make_dataset
from evnoise.reconstruct import Reconstructor, count_image, default_model_path, psnr, ssim

tmp = Path(tempfile.mkdtemp())
config = PairConfig(sensor_shape=(128, 128), binning=2, windows_s=(1.0,), preset="evk3-hd",
                    splits=(0.75, 0.0, 0.25), shard_size=8, seed=0)
start = time.perf_counter()
result = make_dataset(DeadLeaves(24), tmp / "ds", config)
print(f"dataset in {time.perf_counter() - start:.1f} s: {result.manifest['totals']}")
train, test = PairDataset(tmp / "ds", "train"), PairDataset(tmp / "ds", "test")
pair = test[0]
print(f"{len(train)} training pairs, {len(test)} test pairs; a pair has {sorted(pair)}")
print(f"counts {pair['counts'].shape} {pair['counts'].dtype}, image {pair['image'].shape}")

# %%
# Train for a few dozen steps (``--max-minutes`` bounds a real run; the default is 60 epochs).
start = time.perf_counter()
subprocess.run([sys.executable, "-m", "evnoise", "train", str(tmp / "ds"), "--out", str(tmp / "tiny.pt"),
                "--epochs", "12", "--steps-per-epoch", "10", "--batch-size", "8", "--crop", "32",
                "--base-channels", "8", "--no-plot", "-q"], check=True)
print(f"trained in {time.perf_counter() - start:.1f} s")

# %%
# Reconstruct the held-out pairs with both models; the count image (ON + OFF, stretched) is the
# baseline a U-Net has to beat.
tiny = Reconstructor(tmp / "tiny.pt")
shipped = Reconstructor(default_model_path())
rows = min(3, len(test))
fig, axes = plt.subplots(rows, 4, figsize=(11, 2.9 * rows), squeeze=False,
                         constrained_layout=True)
for row in range(rows):
    pair = test[row]
    target = pair["image"]
    shown = {"target": target,
             "count image": count_image(pair["counts"]),
             "tiny U-Net (120 steps)": tiny.predict_binned(pair["counts"], pair["window_s"]),
             "shipped evk3-hd model": shipped.predict_binned(pair["counts"], pair["window_s"])}
    for ax, (name, img) in zip(axes[row], shown.items()):
        ax.imshow(img, cmap="gray", vmin=0, vmax=1)
        score = "" if name == "target" else f"\n{psnr(img, target):.1f} dB, SSIM {ssim(img, target):.2f}"
        ax.set_title(name + score, fontsize=9)
        ax.set_axis_off()
plt.show()
