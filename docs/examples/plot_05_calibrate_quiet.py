"""
Calibrating a preset from a quiet recording
===========================================

With your own camera, record a still scene for a few seconds and let evnoise fit the background
it sees (``evnoise calibrate rec.aedat --t-start 48.87 --t-end 53.37 --out mycam.toml``, a window on the
file's clock). Here the "camera" is evnoise itself: we simulate a quiet recording of a sensor whose true parameters we
know (a leaky sensor with near-periodic, log-normally spread leak events, in the dark), write it as an AEDAT 4 file, fit it with :func:`evnoise.calibration.quiet_window` and
:func:`evnoise.calibration.fit_quiet`, and compare fitted and true values.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from scipy.stats import poisson

import evnoise as ev
from evnoise.calibration import fit_quiet, quiet_window

true = ev.load_preset("davis346").replace(
    leak_on_hz=0.08, leak_off_hz=0.01, leak_sigma=0.8, leak_regularity=0.9)
shape, duration_s = (128, 128), 40.0
events = ev.simulate_events(np.zeros(shape), true, duration_s, rng=7)  # 0 lux: background only
path = ev.write_events(Path(tempfile.mkdtemp()) / "quiet.aedat4", events, shape, {"seed": 7})
print(f"{events.size:,} events in {duration_s:.0f} s on {shape[1]}x{shape[0]} pixels")

# %%
# The window's per-pixel counts, then the fit (each term is kept only where a likelihood-ratio
# test says the data carry it). ``base`` supplies the photon-noise part, which a quiet scene at
# unknown light cannot determine.
window = quiet_window(path, 0.0, duration_s)
fit = fit_quiet([window], base="davis346", hot="off")  # hot="auto" would test for hot pixels too
print(fit.summary())

# %%
# Fitted against true values (the standard errors come from the observed information). The rates
# and the spread come out within a few standard errors; the regularity is the hardest to pin down
# from one window of counts (it only shows in how narrow the count distribution is), and here it
# lands several standard errors below the truth.
fitted = fit.to_params()  # a NoiseParams: the base preset with the fitted background
for name in ("leak_on_hz", "leak_off_hz", "leak_sigma", "leak_regularity"):
    print(f"{name:16s} true {getattr(true, name):8.4g}   fitted {getattr(fitted, name):8.4g}")
print("standard errors:", {k: float(f"{v:.3g}") for k, v in fit.std_error.items() if v is not None})

# %%
# The event *times* say much more about the regularity: a near-periodic leak leaves gaps of at least
# ``r / rate`` between a pixel's events. ``timing="on"`` fits each pixel's event times (a renewal
# process with the simulator's gap law, integrated over the spread of the rates) instead of its counts:
# several times slower (about 30 s here against 6 s), and the regularity's standard error shrinks
# about sixty-fold. Compare such numbers against a simulation of your own, as done here, before
# relying on them.
timed = fit_quiet([window], base="davis346", hot="off", timing="on")
print(timed.summary())
for name in ("rate_on_hz", "rate_off_hz", "sigma", "regularity"):
    print(f"{name:12s} counts {fit.values[name]:.4g} +- {fit.std_error[name]:.2g}   "
          f"times {timed.values[name]:.4g} +- {timed.std_error[name]:.2g}")
fitted = timed.to_params()

# %%
# The recording against a simulation of the fitted preset: the distribution of per-pixel counts.
# A near-periodic leak narrows each pixel's count distribution (less dispersed than Poisson); the
# spread of the rates across pixels widens the population's, and here the spread wins.
again = ev.simulate_events(np.zeros(shape), fitted, duration_s, rng=8)
fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), constrained_layout=True)
for ax, pol, name in ((axes[0], 0, "ON"), (axes[1], 1, "OFF")):
    rec = window.counts[pol].ravel()
    sim = ev.count_events(again, shape)[pol].ravel()
    top = int(np.percentile(np.concatenate([rec, sim]), 99.9)) + 2
    bins = np.arange(top + 1) - 0.5
    ax.hist(rec, bins=bins, histtype="stepfilled", alpha=0.5, label="recording (true preset)")
    ax.hist(sim, bins=bins, histtype="step", lw=2, color="k", label="simulation of the fit")
    mean = rec.mean()
    ax.plot(np.arange(top), rec.size * poisson.pmf(np.arange(top), mean), "C3.:",
            label="Poisson of the same mean")
    ax.set(yscale="log", ylim=(0.5, None), xlabel=f"{name} events per pixel in {duration_s:.0f} s", ylabel="pixels",
           title=f"{name}: variance/mean {rec.var() / max(mean, 1e-12):.2f}")
    ax.legend(fontsize=8)
plt.show()
