"""
Noise rate against illuminance: exact, Gaussian and simulated
=============================================================

The rate of photon-noise events of a still pixel as a function of illuminance, three ways:

* the **exact** closed form (:func:`evnoise.expected_rate`, built on
  :func:`evnoise.event_probability` with ``method="poisson"``),
* the Noise2Image paper's **Gaussian** approximation (its eq. 3, ``method="gaussian"``),
* the **simulator** (:func:`evnoise.sample_counts`): the mean count of 4,000 pixels per level
  over 2 s, with ``3 σ`` error bars (σ the standard error of the mean).

Two parameter sets: the paper's operating point (thresholds 0.904 / 1.0235 and bias 1.7, a few
photons per trial), where the Gaussian form is off by a large factor, and evnoise's ``evk3-hd``
preset (a refit in the many-photon regime), where it is within about 30 % over 0.01–100 lux. The background leak is
switched off, so that the three curves describe the same process.
"""

import matplotlib.pyplot as plt
import numpy as np

import evnoise as ev

evk3 = ev.load_preset("evk3-hd").replace(leak_on_hz=0.0, leak_off_hz=0.0)
paper = evk3.replace(eps_pos=0.904, eps_neg=1.0235, bias_pr=1.7, photons_per_lux=4.0, dark_lux=0.0)
print(paper)

lux = np.logspace(-2, 2, 200)
levels = np.logspace(-2, 2, 13)
n_pixels, duration_s, k = 4000, 2.0, 3.0


def gaussian_rate(lux, params):
    """The paper's eq. 3 per trial, times the trials per second (these presets have no dead time)."""
    lam = params.photons_per_lux * (lux + params.dark_lux)
    p_on = ev.event_probability(lam, params.eps_pos, params.bias_pr, method="gaussian")
    p_off = ev.event_probability(lam, params.eps_neg, params.bias_pr, method="gaussian")
    return params.trial_rate_hz * np.stack([p_on, p_off])


def simulated_rate(params, seed):
    """One row of pixels per illuminance level; every pixel has its own random stream."""
    scene = np.repeat(levels[:, None], n_pixels, axis=1)  # (levels, pixels) of lux
    counts = ev.sample_counts(scene, params, duration_s, rng=seed)  # (2, levels, pixels)
    rate = counts.mean(axis=2) / duration_s
    sem = counts.std(axis=2, ddof=1) / np.sqrt(n_pixels) / duration_s
    expected = ev.expected_rate(levels, params)
    sigma = np.sqrt(expected / duration_s / n_pixels)  # standard error of a Poisson mean rate
    print(f"largest |simulated - exact| / sigma: {np.abs((rate - expected) / sigma).max():.2f}")
    return rate, sem


# %%
# The rates, and the ratio of the Gaussian form to the exact one.
fig, axes = plt.subplots(2, 3, figsize=(13, 8), constrained_layout=True)
for row, (name, params) in enumerate((("paper's operating point", paper), ("evk3-hd preset", evk3))):
    exact = ev.expected_rate(lux, params)  # (2, n): [ON, OFF] events/s
    gauss = gaussian_rate(lux, params)
    rate, sem = simulated_rate(params, seed=row)
    for col, pol in ((0, 0), (1, 1)):
        ax = axes[row, col]
        ax.plot(lux, exact[pol], "k-", lw=2, label="exact (poisson)")
        ax.plot(lux, gauss[pol], "C1--", lw=2, label="paper (gaussian, eq. 3)")
        ax.errorbar(levels, rate[pol], yerr=k * sem[pol], fmt="o", color="C0", ms=4, capsize=3,
                    label=f"simulated, ±{k:.0f}σ")
        ax.set(xscale="log", xlabel="illuminance (lux)", ylabel="events / s / pixel",
               title=f"{('ON', 'OFF')[pol]} noise, {name}")
        ax.legend(fontsize=8)
    ax = axes[row, 2]
    for pol in (0, 1):
        ax.plot(lux, gauss[pol] / exact[pol], lw=2, label=("ON", "OFF")[pol])
    ax.axhline(1.0, color="k", lw=1)
    ax.set(xscale="log", yscale="log", xlabel="illuminance (lux)", ylabel="gaussian / exact",
           title=f"Gaussian form / exact\n{name}")
    ax.legend(fontsize=8)
plt.show()

# %%
# The exact form stays finite far below what a float can hold, in log space (a million photons
# per trial, threshold 5):
print(ev.log_event_probability(1e6, 5.0, 1e3))
