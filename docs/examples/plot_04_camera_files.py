"""
Reading and writing camera files, and ``info --stats``
======================================================

evnoise writes the formats that cameras and their tools read (the suffix picks the format) and
reads them back through one reader layer. Here we simulate 2 s of a DAVIS346 looking at a still
gradient, write it as an iniVation AEDAT 4 file and as a Prophesee RAW (EVT 3.0) file, read both
back with :func:`evnoise.read_events` and :func:`evnoise.open_events`, check that nothing changed,
and summarise the recording's noise with ``evnoise info FILE --stats`` (what you would run on a
recording of your own camera).
"""

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import evnoise as ev

params = ev.load_preset("davis346")
shape = (260, 346)  # (H, W)
lux = np.broadcast_to(np.logspace(-1, 1.5, shape[1]), shape)  # 0.1 to 32 lux, left to right
events = ev.simulate_events(lux, params, duration_s=2.0, rng=3)
print(f"{events.size:,} events")

tmp = Path(tempfile.mkdtemp())
paths = []
for suffix in (".aedat4", ".raw"):
    path = ev.write_events(tmp / f"quiet{suffix}", events, shape, {"params": params, "seed": 3})
    paths.append(path)
    print(f"{path.name}: {path.stat().st_size:,} bytes")

# %%
# Read back: ``read_events`` returns ``(events, meta)``; the format comes from the file's magic
# bytes and suffix. ``meta["sensor"]`` is ``"WxH"``, ``meta["shape"]`` is ``(H, W)``.
for path in paths:
    back, meta = ev.read_events(path)
    same = all(np.array_equal(back[f], events[f]) for f in ("t", "x", "y", "p"))
    print(f"{path.name}: {back.size:,} events, sensor {meta['sensor']}, identical: {same}")

# %%
# For files larger than memory, ``open_events`` streams chunks; a time window is read without
# decoding what comes after it.
source = ev.open_events(paths[1])
n, n_chunks = 0, 0
for chunk in ev.iter_event_chunks(paths[1], t_start=0.5, t_end=1.5):
    n += chunk.size
    n_chunks += 1
print(f"{type(source).__name__}: {n:,} events in [0.5 s, 1.5 s) from {n_chunks} chunk(s)")

# %%
# ``evnoise info --stats``: rates, ON fraction, active pixels, dispersion, hot pixels. With
# ``--json`` the numbers come as JSON numbers with their units in the keys.
out = subprocess.run([sys.executable, "-m", "evnoise", "info", str(paths[0]), "--stats", "--json"],
                     check=True, capture_output=True, text=True).stdout
stats = json.loads(out)
print(json.dumps(stats, indent=1)[:1500])

# %%
# The recording's count maps and the per-pixel count histogram, against the model.
counts = ev.count_events(back, shape)
expected = ev.expected_rate(lux, params) * 2.0
fig, axes = plt.subplots(1, 3, figsize=(13, 3.4), constrained_layout=True)
for ax, pol, name in ((axes[0], 0, "ON"), (axes[1], 1, "OFF")):
    im = ax.imshow(counts[pol], cmap="magma")
    fig.colorbar(im, ax=ax, label="events in 2 s")
    ax.set_title(f"{name} counts, read from {paths[1].name}")
    ax.set_axis_off()
total = counts.sum(axis=0)
axes[2].hist(total.ravel(), bins=np.arange(total.max() + 2) - 0.5, log=True, color="C0")
axes[2].set(xlabel="events per pixel in 2 s", ylabel="pixels",
            title=f"mean {total.mean():.2f}, expected {expected.sum(axis=0).mean():.2f}")
plt.show()
