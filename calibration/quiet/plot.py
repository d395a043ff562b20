"""Figure of a quiet-scene fit: real against simulated count histograms and count maps."""

from __future__ import annotations

import numpy as np


def plot_quiet(fit, path, *, seed: int = 0, params=None):
    """One row per window: ON and OFF per-pixel count histograms (recording vs the fitted model,
    simulated), the recording's count map and a simulated one, written atomically to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from evnoise._atomic import atomic_output

    from .goodness import GOF_MAX_COUNT, simulate_window

    params = params if params is not None else fit.to_params()
    rows = fit.windows[:6]
    fig, axes = plt.subplots(len(rows), 4, figsize=(14, 3.1 * len(rows)), squeeze=False)
    for r, w in enumerate(rows):
        sim = simulate_window(params, w, replicas=5, seed=seed + r)
        kept, keep = w.pixel_counts(), w.kept()  # histograms of the pixels the fit uses
        for pol, name in enumerate(("ON", "OFF")):
            ax = axes[r, pol]
            real = np.minimum(kept[pol], GOF_MAX_COUNT)
            fake = np.minimum(sim[:, pol].reshape(sim.shape[0], -1)[:, keep].ravel(), GOF_MAX_COUNT)
            top = int(max(real.max(), fake.max())) + 1
            bins = np.arange(top + 1)
            ax.step(bins[:-1], np.bincount(real, minlength=top) / real.size, where="mid", label="recording")
            ax.step(bins[:-1], np.bincount(fake, minlength=top)[:top] / fake.size, where="mid",
                    label="fitted model (5 simulated sensors)", linestyle="--")
            ax.set_yscale("log")
            ax.set_xlabel(f"{name} events per pixel")
            ax.set_ylabel("fraction of pixels")
            good = [g for g in fit.goodness if g["window"] == w.describe() and g["polarity"] == name]
            title = f"{w.describe()} {name}"
            if good:
                title += f"\nchi2 {good[0]['chi2']:.1f} / {good[0]['dof']} dof, p = {good[0]['p_value']:.2g}"
            ax.set_title(title, fontsize=8)
            if r == 0 and pol == 0:
                ax.legend(fontsize=7)
        vmax = max(1, int(np.percentile(w.counts.sum(axis=0), 99.9)))
        for c, (img, label) in enumerate(((w.counts.sum(axis=0), "recording"), (sim[0].sum(axis=0), "simulated"))):
            ax = axes[r, 2 + c]
            im = ax.imshow(img, cmap="magma", vmin=0, vmax=vmax, interpolation="nearest")
            ax.set_title(f"{label}: events per pixel (ON + OFF)", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
            fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    try:
        with atomic_output(path, what="figure") as tmp:
            fig.savefig(tmp, dpi=90, format="png")
    finally:
        plt.close(fig)
