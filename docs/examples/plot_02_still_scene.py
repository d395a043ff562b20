"""
A still scene: event counts and timing statistics
=================================================

The bundled example scene (the image that ``evnoise simulate --example`` uses), seen by the
``evk3-hd`` camera for 3 s at 18 lux for full-scale white. We look at the ON and OFF count maps,
the ON share against illuminance, and the intervals between a pixel's events, which for a still
pixel are geometric in the photoreceptor's trials (exponential at this scale), with the
refractory period as a dead time.
"""

from importlib.resources import files

import matplotlib.pyplot as plt
import numpy as np

import evnoise as ev

params = ev.load_preset("evk3-hd")
lux = ev.image_to_lux(files("evnoise.data") / "example.png", max_lux=18.0)[::2, ::2]  # (360, 640)
shape = lux.shape
events = ev.simulate_events(lux, params, duration_s=3.0, rng=1)
print(f"{events.size:,} events on {shape[1]}x{shape[0]} pixels; fields {events.dtype.names}")
counts = ev.count_events(events, shape)  # (2, H, W) [ON, OFF]
expected = ev.expected_rate(lux, params) * 3.0

# %%
# Count maps: the rate peaks near 1–2 lux, so the brightest parts of the scene are dark here.
fig, axes = plt.subplots(1, 3, figsize=(13, 3.2), constrained_layout=True)
im = axes[0].imshow(np.log10(np.maximum(lux, 1e-2)), cmap="gray")
fig.colorbar(im, ax=axes[0], label="log10 lux")
for ax, pol, name in ((axes[1], 0, "ON"), (axes[2], 1, "OFF")):
    im = ax.imshow(counts[pol], cmap="magma")
    fig.colorbar(im, ax=ax, label="events in 3 s")
    ax.set_title(f"{name} events")
axes[0].set_title("scene")
for ax in axes:
    ax.set_axis_off()
plt.show()

# %%
# Timing: inter-event intervals of the pixels near 1.5 lux against the exponential law of the
# predicted rate, and counts against the prediction pixel by pixel (binned by illuminance).
near = np.abs(lux - 1.5) < 0.15
pix = np.flatnonzero(near.ravel())
key = events["y"].astype(np.int64) * shape[1] + events["x"]
sel = np.isin(key, pix)
order = np.lexsort((events["t"][sel], key[sel]))
k_sorted, t_sorted = key[sel][order], events["t"][sel][order]
same = k_sorted[1:] == k_sorted[:-1]
gaps_s = np.diff(t_sorted)[same] * 1e-6
nu = ev.expected_rate(lux[near], params).sum(axis=0).mean()
T = 3.0  # a gap is only seen when both of its events fall in the 3 s record: density ∝ ν e^(-νg) (T - g)

fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), constrained_layout=True)
bins = np.linspace(0, 3, 40)
axes[0].hist(gaps_s, bins=bins, density=True, alpha=0.6, label=f"{gaps_s.size:,} intervals")
g = np.linspace(0, T, 200)
law = nu * np.exp(-nu * g) * (T - g)
axes[0].plot(g, law / np.trapezoid(law, g), "k-", label=f"exponential, ν = {nu:.2f}/s, seen in {T:.0f} s")
axes[0].set(yscale="log", xlabel="interval between a pixel's events (s)", ylabel="density",
            title="inter-event intervals near 1.5 lux")
axes[0].legend(fontsize=8)

edges = np.logspace(np.log10(max(lux.min(), 1e-2)), np.log10(lux.max()), 25)
idx = np.digitize(lux.ravel(), edges)
mid, obs_on, exp_on, share = [], [], [], []
for b in range(1, edges.size):
    m = idx == b
    if m.sum() < 50:
        continue
    mid.append(np.sqrt(edges[b - 1] * edges[b]))
    obs_on.append(counts[:, :, :].reshape(2, -1)[:, m].sum(axis=0).mean())
    exp_on.append(expected.reshape(2, -1)[:, m].sum(axis=0).mean())
    c = counts.reshape(2, -1)[:, m].sum(axis=1)
    share.append(c[0] / max(c.sum(), 1))
axes[1].plot(mid, exp_on, "k-", label="expected (exact model)")
axes[1].plot(mid, obs_on, "o", color="C0", ms=4, label="simulated")
axes[1].set(xscale="log", xlabel="illuminance (lux)", ylabel="events per pixel in 3 s",
            title="counts against the model (ON + OFF)")
axes[1].legend(fontsize=8)
axes[2].plot(mid, share, "o-", color="C3", ms=4)
axes[2].set(xscale="log", ylim=(0, 1), xlabel="illuminance (lux)", ylabel="ON / (ON + OFF)",
            title="polarity: the ON share")
plt.show()

# %%
# Timestamps are integer microseconds, uniform within a trial (not a comb at the trial rate):
phase = (events["t"] * 1e-6 * params.trial_rate_hz) % 1.0
print(f"trial phase of the events: mean {phase.mean():.3f} (uniform: 0.5), sd {phase.std():.3f} "
      f"(uniform: {np.sqrt(1 / 12):.3f})")
