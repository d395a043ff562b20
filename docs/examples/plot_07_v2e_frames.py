"""
Photon noise for frame-driven emulators (v2e, ESIM)
===================================================

Frame-driven event simulators step through video frames and emit an event where a pixel's log
intensity moved by a threshold: a clean stream. evnoise adds the calibrated photon noise of every
frame interval to it, through the emulator's own interface (``generate_events(frame, t_s)``
returning ``N × 4`` rows ``[t_s, x, y, ±1]``):

* :class:`evnoise.plugins.v2e.PhotonNoise` wraps v2e's ``EventEmulator`` (frames are grey levels
  0–255, ``white_lux`` is the illuminance of grey 255);
* :class:`evnoise.plugins.frames.EmulatorNoise` wraps any emulator with that interface whose
  frames can be turned into lux.

v2e is not installed where these docs are built, so the emulator here is the small
log-threshold emulator that ships with evnoise's ESIM-style example; with v2e the code is the same
but for the emulator's constructor::

    from v2ecore.emulator import EventEmulator
    emulator = EventEmulator(pos_thres=0.2, neg_thres=0.2, sigma_thres=0.03, cutoff_hz=0,
                             shot_noise_rate_hz=0, leak_rate_hz=0, device="cpu")  # v2e's noise off
    v2e = PhotonNoise(emulator, "evk3-hd", white_lux=18.0, rng=0)

and v2e's own command line runs with the noise as::

    python -m evnoise.plugins.v2e --params evk3-hd --white-lux 18 --seed 0 -- \\
        -i input.mp4 --output_folder out --dvs_h5 events.h5

(everything after ``--`` goes to ``v2e.py``; its files and printed totals include the noise).
"""

import matplotlib.pyplot as plt
import numpy as np

import evnoise as ev
from evnoise.examples.add_noise_to_esim import LogFrameEmulator, moving_disc_frames
from evnoise.plugins.frames import EmulatorNoise
from evnoise.plugins.v2e import PhotonNoise

frames, times = moving_disc_frames(shape=(120, 160), n_frames=51, fps=50.0)  # lux, 1 s
print(f"{len(frames)} frames of {frames.shape[1:]} lux, {times[-1]:.1f} s")

# %%
# Frames in lux: ``EmulatorNoise``. The wrapped emulator is called first, unchanged; the noise
# rows of ``[t_previous, t)`` are merged in by time.
clean_emulator = LogFrameEmulator(threshold=0.3)
noisy_emulator = EmulatorNoise(LogFrameEmulator(threshold=0.3), "evk3-hd", rng=0)
clean_rows, noisy_rows = [], []
for frame, t in zip(frames, times):  # the host simulator's loop
    for emulator, rows in ((clean_emulator, clean_rows), (noisy_emulator, noisy_rows)):
        out = emulator.generate_events(frame, t)
        if out is not None:
            rows.append(out)
clean = ev.events_from_array(np.concatenate(clean_rows), time_unit="s")
noisy = ev.events_from_array(np.concatenate(noisy_rows), time_unit="s")
print(f"clean {clean.size:,} events, with noise {noisy.size:,} ({noisy_emulator.noise_count:,} noise)")

# %%
# Grey-level frames, as v2e reads them: the v2e wrapper maps grey ``g`` to
# ``white_lux * g / 255`` lux (v2e takes the log of the luma itself, no gamma decoding).
grey = np.clip(frames / frames.max() * 255.0, 0, 255)
v2e_like = PhotonNoise(LogFrameEmulator(threshold=0.3), "evk3-hd", white_lux=float(frames.max()), rng=0)
n = 0
for frame, t in zip(grey, times):
    out = v2e_like.generate_events(frame, t)
    n += 0 if out is None else len(out)
print(f"v2e wrapper: {n:,} rows, first columns of the last frame's rows:\n{out[:3]}")

# %%
# Counts of the clean and the noisy stream: the disc's trail is the signal; the photon noise
# depends on the light (the gradient from 1 to 12 lux, brightest on the right).
shape = frames.shape[1:]
fig, axes = plt.subplots(1, 3, figsize=(13, 3.3), constrained_layout=True)
axes[0].imshow(frames[len(frames) // 2], cmap="gray")
axes[0].set_title("middle frame (lux)")
for ax, events, name in ((axes[1], clean, "clean emulator"), (axes[2], noisy, "with photon noise")):
    counts = ev.count_events(events, shape).sum(axis=0)
    im = ax.imshow(counts, cmap="magma", vmax=np.percentile(counts, 99))
    fig.colorbar(im, ax=ax, label="events in 1 s")
    ax.set_title(name)
for ax in axes:
    ax.set_axis_off()
plt.show()
