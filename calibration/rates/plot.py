"""The figure people look at first: measured rates (and NB shapes) vs the fitted curves."""

from __future__ import annotations

import numpy as np

from evnoise.errors import OutputError

__all__ = ["plot_fit"]

_COLORS = {0: "tab:blue", 1: "tab:red"}
_NAMES = {0: "ON", 1: "OFF"}


def _curve_lux(lux):
    lo = float(lux.min())
    hi = float(lux.max())
    pos = lux[lux > 0]
    start = float(pos.min()) / 2 if lo <= 0 and pos.size else lo
    grid = np.geomspace(max(start, 1e-6), hi * 1.05, 300)
    if lo <= 0:
        grid = np.concatenate([[0.0], grid])
    return grid


def plot_fit(result, path, *, title: str | None = None, overwrite: bool = False, extra_curves=None, gaussian=True,
             extra_r_curves=None):
    """Save a PNG: rates per polarity vs lux with the fit, and NB shapes when measured.

    Parameters
    ----------
    result : CalibrationResult
        The fit to draw, with its measurements.
    path : str or os.PathLike
        Output PNG.
    title : str, optional
        Title of the figure (default: ``"evnoise calibration: "`` and the measurements' source).
    overwrite : bool, default False
        Replace an existing file.
    extra_curves : list of dict, optional
        More curves on the rate panel: ``dict(label=..., lux=(n,), rate=(2, n), style="--")``.
    gaussian : bool, default True
        Where the fit used the exact (``"poisson"``) form, also draw the paper's Gaussian form (eq. 3)
        at the fitted parameters.
    extra_r_curves : list of dict, optional
        More curves on the NB-shape panel: ``dict(label=..., lux=(n,), r=(2, n), style="--")``.

    Returns
    -------
    pathlib.Path
        The path written.
    """
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise OutputError("the plot needs matplotlib: pip install 'evnoise[plot]'") from None

    from evnoise.io import open_output_path
    from evnoise.mismatch import nb_shape, population_rate

    path = open_output_path(path, overwrite=overwrite, what="plot")
    meas = result.measurements
    lux = meas.lux
    grid = _curve_lux(lux)
    rate, rel_sd = result.rate_band(grid)
    show_r = meas.nb_shape is not None and meas.duration_s is not None
    fig = Figure(figsize=(12 if show_r else 7, 4.8))  # no pyplot: no global state, no backend switch
    axes = fig.subplots(1, 2 if show_r else 1, squeeze=False)
    ax = axes[0, 0]
    xs = np.where(grid > 0, grid, np.nan)
    for k in (0, 1):
        c = _COLORS[k]
        err = None
        if meas.kind == "flat-field":
            err = np.array([cnt[k].std(ddof=1) / np.sqrt(cnt.shape[1]) / d
                            for cnt, d in zip(meas.pixel_counts, meas.duration_s)])
        elif meas.exposure_known:
            err = np.sqrt(np.maximum(meas.rate_hz[k] * meas.duration_s * meas.n_pixels, 0)) / (
                meas.duration_s * meas.n_pixels)
        ax.errorbar(np.where(lux > 0, lux, np.nan), meas.rate_hz[k], yerr=err, fmt="o", ms=3.5, color=c,
                    mfc="none", label=f"measured {_NAMES[k]}", zorder=3)
        ax.plot(xs, rate[k], "-", color=c, lw=1.8, label=f"fit {_NAMES[k]} ({result.method})")
        ax.fill_between(xs, rate[k] * np.exp(-rel_sd[k]), rate[k] * np.exp(rel_sd[k]), color=c, alpha=0.2, lw=0)
    if gaussian and result.method == "poisson":
        g = population_rate(grid, result.params, method="gaussian")
        for k in (0, 1):
            ax.plot(xs, g[k], "--", color=_COLORS[k], lw=1.2, alpha=0.8,
                    label=f"Gaussian eq. 3 at the same parameters, {_NAMES[k]}")
    for curve in extra_curves or []:
        cl = np.asarray(curve["lux"], dtype=np.float64)
        cr = np.asarray(curve["rate"], dtype=np.float64)
        for k in (0, 1):
            ax.plot(np.where(cl > 0, cl, np.nan), cr[k], curve.get("style", ":"), color=_COLORS[k], lw=1.2,
                    alpha=0.9, label=f"{curve['label']}, {_NAMES[k]}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("illuminance at the sensor [lux]")
    ax.set_ylabel("noise-event rate per pixel [events/s]")
    top = float(np.nanmax(np.concatenate([meas.rate_hz.ravel(), rate.ravel()])))
    bottom = float(np.nanmin(np.where(meas.rate_hz > 0, meas.rate_hz, np.nan)))
    ax.set_ylim(max(bottom / 10, top * 1e-4), top * 2.5)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7, loc="lower center", ncol=2)
    ax.set_title("mean rate over pixels (band: 1 sd of the fit)" + (
        "; the 0-lux level is off the log axis" if np.any(lux <= 0) else ""), fontsize=9)
    if show_r:
        ax2 = axes[0, 1]
        durations = np.unique(meas.duration_s)
        d = float(durations[0])
        r_model = nb_shape(grid, result.params, d, method=result.method)
        for k in (0, 1):
            c = _COLORS[k]
            ax2.plot(np.where(lux > 0, lux, np.nan), meas.nb_shape[k], "o", ms=3.5, color=c, mfc="none",
                     label=f"measured {_NAMES[k]}")
            if np.any(np.isfinite(r_model[k])):
                ax2.plot(xs, r_model[k], "-", color=c, lw=1.8, label=f"fit, {_NAMES[k]}")
            for curve in extra_r_curves or []:
                cl = np.asarray(curve["lux"], dtype=np.float64)
                ax2.plot(np.where(cl > 0, cl, np.nan), np.asarray(curve["r"])[k], curve.get("style", "--"),
                         color=c, lw=1.2, label=f"{curve['label']}, {_NAMES[k]}")
        ax2.set_xscale("log")
        ax2.set_yscale("log")
        ax2.set_xlabel("illuminance at the sensor [lux]")
        ax2.set_ylabel(f"NB shape r of the count over {d:g} s")
        ax2.grid(True, which="both", alpha=0.25)
        ax2.legend(fontsize=7)
        ax2.set_title(f"over-dispersion: NB shape r (fit: eps_sigma = {result.params.eps_sigma:.3g})", fontsize=9)
    fig.suptitle(title or f"evnoise calibration: {meas.source}", fontsize=10)
    fig.tight_layout()
    from evnoise._atomic import atomic_output

    with atomic_output(path, overwrite=True, what="plot") as tmp:
        fig.savefig(tmp, dpi=130, format="png")
    return path
