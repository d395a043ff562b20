"""
The static background behind motion
===================================

Noise events reveal a still scene, but real scenes move. evnoise tells scene (signal) events from
noise events (:func:`evnoise.separate_events`), masks where things move, and counts noise in a
moving window only where the view is clear (:func:`evnoise.iter_motion`), so the background can be
reconstructed over time (:func:`evnoise.reconstruct_video`, ``evnoise reconstruct REC --fps``).

The recording is simulated with ground truth: the bundled example scene seen by the ``evk3-hd``
camera for 4 s while a bright disc crosses it (:func:`evnoise.simulate_video` with
``return_labels=True``).
"""

import tempfile
from importlib.resources import files
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import evnoise as ev
from evnoise.reconstruct import default_model_path

params = ev.load_preset("evk3-hd")
scene = ev.image_to_lux(files("evnoise.data") / "example.png", max_lux=18.0)[::4, ::4][:176, :320]
shape = scene.shape
yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
times = np.linspace(0.0, 4.0, 81)
frames = []
for t in times:
    cx = 30 + (shape[1] - 60) * t / times[-1]
    disc = (xx - cx) ** 2 + (yy - shape[0] / 2) ** 2 < 22 ** 2
    frames.append(np.where(disc, 40.0, scene))
frames = np.array(frames)
events, is_signal = ev.simulate_video(frames, times, params, rng=0, return_labels=True)
print(f"{events.size:,} events, {is_signal.mean():.1%} of them signal")

# %%
# Separation: the density filter labels events in busy neighbourhoods as signal. Against the
# simulator's labels:
signal, noise = ev.separate_events(events, shape)
said_signal = np.isin(events["t"] * 1_000_000 + events["y"].astype(np.int64) * shape[1] + events["x"],
                      signal["t"] * 1_000_000 + signal["y"].astype(np.int64) * shape[1] + signal["x"])
print(f"signal found: {np.mean(said_signal[is_signal]):.1%} of true signal; "
      f"noise kept as noise: {np.mean(~said_signal[~is_signal]):.1%}")

# %%
# Moving-window noise counts with a motion mask, one frame per second: the counts grow where the
# view is clear and pause where the disc passes.
steps = list(ev.iter_motion(events, shape, fps=1.0, window_s=2.0))
for frame in steps:
    print(f"step {frame.index}: [{frame.t_start_us / 1e6:.0f}, {frame.t_end_us / 1e6:.0f}) s, "
          f"masked {frame.mask.mean():.1%}, noise {frame.n_noise:,}, signal {frame.n_signal:,}")

# %%
# Reconstruct the background every second with the shipped ``evk3-hd`` model.
tmp = Path(tempfile.mkdtemp())
h5 = ev.write_events(tmp / "motion.h5", events, shape, {"params": params, "seed": 0})
summary = ev.reconstruct_video(h5, default_model_path(), tmp / "frames", fps=1.0, window_s=2.0,
                               progress=False)
print({k: v for k, v in summary.items() if not isinstance(v, (list, dict))})
pngs = sorted((tmp / "frames").glob("frame_*.png"))
overlays = sorted((tmp / "frames").glob("overlay_*.png"))

fig, axes = plt.subplots(2, 3, figsize=(13, 5.6), constrained_layout=True)
axes[0, 0].imshow(np.log10(np.maximum(scene, 1e-2)), cmap="gray")
axes[0, 0].set_title("true background (log lux)")
mid = steps[len(steps) // 2]
axes[0, 1].imshow(mid.mask, cmap="Reds")
axes[0, 1].set_title(f"motion mask, step {mid.index}")
axes[0, 2].imshow(mid.counts.sum(axis=0) / np.maximum(mid.exposure_s, 1e-9), cmap="magma")
axes[0, 2].set_title("noise rate in the clear window (events/s)")
for ax, path in zip(axes[1], [pngs[0], pngs[len(pngs) // 2], overlays[len(overlays) // 2]]):
    ax.imshow(plt.imread(path), cmap="gray")
    ax.set_title(path.name)
for ax in axes.ravel():
    ax.set_axis_off()
plt.show()
