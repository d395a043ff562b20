"""
Camera presets and their rate curves
====================================

evnoise ships one preset per camera it has numbers for (:func:`evnoise.list_presets`). Each is a
TOML file with a ``[sensor]`` table, the model's parameters and a ``[provenance]`` table saying
where every number comes from; ``evnoise presets NAME`` prints it. Here: the expected ON and OFF
noise rate of each preset against illuminance, split into photon (shot) noise and background
activity (leak and hot pixels), and the population mean where pixels differ (threshold mismatch,
spread of the leak rates).
"""

import json
import subprocess
import sys

import matplotlib.pyplot as plt
import numpy as np

import evnoise as ev

listing = subprocess.run([sys.executable, "-m", "evnoise", "presets", "--json"], check=True,
                         capture_output=True, text=True).stdout
for entry in json.loads(listing):
    print(f"{entry['name']:9s} {entry.get('width')}x{entry.get('height')}  {entry.get('summary', '')}")

# %%
# The curves. ``expected_rate`` gives the nominal pixel (``mismatch="nominal"``) or the mean
# over the population of pixels (``mismatch="mean"``); ``background_rate`` the background alone.
lux = np.logspace(-3, 4, 300)
names = ev.list_presets()
fig, axes = plt.subplots(2, len(names), figsize=(3.3 * len(names), 6), sharex=True,
                         constrained_layout=True)
for col, name in enumerate(names):
    params = ev.load_preset(name)
    total = ev.expected_rate(lux, params)
    background = ev.background_rate(lux, params)
    shot = ev.expected_rate(lux, params.replace(
        leak_on_hz=0.0, leak_off_hz=0.0, leak_on_hz_per_lux=0.0, leak_off_hz_per_lux=0.0,
        hot_pixel_fraction=0.0))
    differ = params.eps_sigma > 0 or params.leak_sigma > 0 or params.hot_pixel_fraction > 0
    # the population mean integrates over the pixels' thresholds and rates: costly in bright
    # light, so a few points up to 100 lux, one call each
    lux_mean = np.logspace(-3, 2, 11)
    population = (np.concatenate([ev.expected_rate(lux_mean[i:i + 1], params, mismatch="mean")
                                  for i in range(lux_mean.size)], axis=1) if differ else None)
    for row, pol in enumerate(("ON", "OFF")):
        ax = axes[row, col]
        ax.plot(lux, shot[row], "C0-", label="shot noise")
        ax.plot(lux, background[row], "C2:", label="background")
        ax.plot(lux, total[row], "k-", lw=2, label="total (nominal pixel)")
        if population is not None:
            ax.plot(lux_mean, population[row], "C3o--", ms=3, label="population mean")
        ax.set(xscale="log", yscale="log", ylim=(1e-5, 1e2), title=f"{name}: {pol}")
        if col == 0:
            ax.set_ylabel("events / s / pixel")
        if row == 1:
            ax.set_xlabel("illuminance (lux)")
axes[0, 0].legend(fontsize=7, loc="lower left")
plt.show()

# %%
# One preset in full, as ``evnoise presets NAME`` prints it: the non-default parameters, the
# provenance and the fit quality. ``evnoise presets NAME --plot rates.png`` draws the curves above.
print(subprocess.run([sys.executable, "-m", "evnoise", "presets", "dvs128"], check=True,
                     capture_output=True, text=True).stdout)
