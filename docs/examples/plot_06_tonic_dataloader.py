"""
Photon noise inside a tonic DataLoader
======================================

:class:`evnoise.plugins.tonic.PhotonNoise` is a tonic transform, the physical replacement for
``tonic.transforms.UniformNoise``: it adds the noise events of an illuminance (a scalar or a
per-pixel map in lux) for each sample's own time span, with tonic's dtype and field names. The
event probabilities are computed once, when the transform is made, so a call only draws events and
runs in forked DataLoader workers.

To stay offline, the samples here are made up: a bright bar sweeping an N-MNIST-sized
(34 × 34) sensor for 0.3 s. With a real dataset it is
``tonic.datasets.NMNIST(save_to="data", train=False, transform=transform)``.
"""

import time

import matplotlib.pyplot as plt
import numpy as np
import tonic
import torch
from torch.utils.data import DataLoader, Dataset

from evnoise.plugins.tonic import PhotonNoise

sensor_size = tonic.datasets.NMNIST.sensor_size  # (W, H, P) = (34, 34, 2)
dtype = tonic.datasets.NMNIST.dtype


class SweepingBars(Dataset):
    """Stand-in samples: ON events of a vertical bar sweeping right, then OFF events behind it."""

    def __init__(self, n, transform=None):
        self.n, self.transform = n, transform

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        gen = np.random.default_rng(i)
        t = np.sort(gen.integers(0, 300_000, 600))
        x = np.clip((t / 300_000 * 30).astype(int) + gen.integers(0, 4, t.size), 0, 33)
        events = np.zeros(t.size, dtype=dtype)
        events["t"], events["x"], events["y"] = t, x, gen.integers(4 + i % 4, 30, t.size)
        events["p"] = gen.integers(0, 2, t.size)
        return (self.transform(events) if self.transform else events), i % 10


# %%
# The transform: 2 lux everywhere except a brighter disc (a per-pixel map, indexed ``lux[y, x]``).
yy, xx = np.mgrid[0:34, 0:34]
lux = np.where((xx - 17) ** 2 + (yy - 17) ** 2 < 64, 6.0, 2.0)
noise = PhotonNoise(sensor_size, "evk3-hd", lux=lux, rng=0)  # int seed: noise fixed per sample
to_frame = tonic.transforms.ToFrame(sensor_size, n_time_bins=3)
transform = tonic.transforms.Compose([noise, to_frame])

clean = SweepingBars(16)
noisy = SweepingBars(16, transform=transform)
sample, _ = clean[0]
print(f"noise events added to sample 0: {noise(sample).size - sample.size} "
      f"(expected about {1.2 * 34 * 34 * 0.3:.0f})")

# %%
# In a DataLoader with two forked workers. With an int seed a sample gets the same noise in
# every epoch and worker, and different samples get independent noise.
loader = DataLoader(noisy, batch_size=4, num_workers=2, multiprocessing_context="fork",
                    collate_fn=tonic.collation.PadTensors(batch_first=True))
start = time.perf_counter()
batches = [frames for frames, _ in loader]
print(f"{len(batches)} batches of {tuple(batches[0].shape)} (B, T, P, H, W) "
      f"in {time.perf_counter() - start:.2f} s")
again = next(iter(loader))[0]
print("same noise in a second epoch:", torch.equal(again, batches[0]))

# %%
# The first sample's frames without and with photon noise.
fig, axes = plt.subplots(2, 3, figsize=(9, 6), constrained_layout=True)
plain = to_frame(sample)
for j in range(3):
    for row, (frames, name) in enumerate(((plain, "clean"), (batches[0][0].numpy(), "with photon noise"))):
        ax = axes[row, j]
        ax.imshow(frames[j, 0] - frames[j, 1], cmap="coolwarm", vmin=-3, vmax=3)
        ax.set_title(f"{name}, bin {j} (ON − OFF)", fontsize=9)
        ax.set_axis_off()
plt.show()
