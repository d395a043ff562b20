"""``evnoise presets [NAME] [--plot FILE] [--json]``: the shipped camera presets and what they predict.

Without NAME: one line per shipped preset (name, sensor size, summary). With NAME (or a preset
``.toml`` path): its non-default parameters, provenance summary, fit quality lines and file; with
``--plot FILE`` a PNG of the ON and OFF noise rate against illuminance, split into its terms.
"""

from __future__ import annotations

import json
import math

from ..errors import InputError

#: lux range of the rate plot
PLOT_LUX = (1e-3, 1e4)
#: points of the population-mean curve, and the most photons per trial it is evaluated at
MEAN_POINTS = 29
MEAN_MAX_PHOTONS = 2e4
_QUALITY_KEYS = ("rate_rms_relative_residual", "rate_max_relative_residual", "rate_rms_relative_error",
                 "rate_max_relative_error", "worst_at_lux", "worst_polarity")


def register(subparsers) -> None:
    from . import _options as opt

    p = subparsers.add_parser(
        "presets",
        help="list the camera presets, show one, plot its noise rate against lux",
        description="Without NAME: the shipped presets (name, sensor size, one line on where the numbers come "
        "from). With NAME (or a preset .toml file): its parameters that differ from the defaults, its provenance "
        "and fit quality, and where the file is. --plot FILE draws the ON and OFF noise rate (events/s per pixel) "
        "against lux with each term's share: shot noise alone, background activity, total, and the population "
        "mean when pixels differ.",
        parents=[opt.output(overwrite_help="replace an existing --plot file")],
    )
    p.add_argument("name", nargs="?", metavar="NAME", help="a preset name (see the list) or a preset .toml file")
    opt.add_plot(p, metavar="FILE", help="with NAME: write a PNG of the rate against lux")
    opt.add_json_output(p)
    p.set_defaults(func=run)


def _non_default(params) -> dict:
    import dataclasses

    out = {}
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if f.default is dataclasses.MISSING or value != f.default:
            out[f.name] = value
    return out


def describe(name_or_path) -> dict:
    """Everything ``evnoise presets NAME`` shows, as plain JSON types."""
    from ..params import NoiseParams, load_preset_document, preset_info
    from ._options import check_text_file

    check_text_file(name_or_path, "preset")
    info = preset_info(name_or_path)
    doc = load_preset_document(name_or_path)
    if not isinstance(doc.get("params"), dict):
        raise InputError(f"preset {name_or_path} has no [params] table")
    params = NoiseParams.from_dict(doc["params"])
    provenance = doc.get("provenance") if isinstance(doc.get("provenance"), dict) else {}
    quality = {}
    fit = doc.get("fit") if isinstance(doc.get("fit"), dict) else {}
    for source in (fit.get("quality") if isinstance(fit.get("quality"), dict) else {}, provenance):
        for key in _QUALITY_KEYS:
            if key in source and not isinstance(source[key], (dict, list)):
                quality[key] = source[key]
    info.update(params=_non_default(params), source=provenance.get("source"), status=provenance.get("status"),
                quality=quality)
    from ..params import preset_light_range

    light = preset_light_range(name_or_path)
    info["fitted_lux"] = None if light is None else {"lo": light.lo, "hi": light.hi, "note": light.note,
                                                      "meaning": light.meaning}
    return info


def _text_table(rows) -> str:
    lines = []
    width = max([len(r["name"]) for r in rows] + [4])
    for r in rows:
        size = f"{r['width']}x{r['height']}" if r["width"] and r["height"] else "?"
        lines.append(f"{r['name']:<{width}}  {size:>9}  {r['summary'] or '(no summary)'}")
    return "\n".join(lines)


def _text_show(d: dict) -> str:
    size = f"{d['width']}x{d['height']}" if d["width"] and d["height"] else "unknown"
    lines = [f"preset: {d['name']}", f"sensor: {d['sensor'] or 'unknown'} ({size})"]
    if d["summary"]:
        lines.append(f"summary: {d['summary']}")
    if d["status"]:
        lines.append(f"status: {d['status']}")
    if d["source"]:
        lines.append(f"source: {d['source']}")
    light = d.get("fitted_lux")
    if light:
        note = f" ({light['note']})" if light["note"] else ""
        lines.append(f"fitted on: {light['lo']:g} .. {light['hi']:g} lux{note}")
    lines.append("parameters (non-default):")
    lines += [f"  {k} = {v:.6g}" for k, v in d["params"].items()]
    if d["quality"]:
        lines.append("fit quality:")
        lines += [f"  {k} = {v:.4g}" if isinstance(v, float) else f"  {k} = {v}" for k, v in d["quality"].items()]
    lines.append(f"file: {d['path']}")
    return "\n".join(lines)


def rate_curves(params, lux) -> dict:
    """``{label: (2, n) array}`` of ON/OFF rates in events/s per pixel: shot, background, total, mean.

    ``shot``: the photon-noise rate alone (background terms zeroed); ``background``: the background
    intensities (:func:`evnoise.background_rate`); ``total``: the nominal pixel with both;
    ``population mean`` (only when pixels differ: threshold mismatch, leak spread or hot pixels).
    """
    from ..background import background_rate
    from ..rates import expected_rate

    shot = expected_rate(lux, params.replace(leak_on_hz=0.0, leak_off_hz=0.0, leak_on_hz_per_lux=0.0,
                                             leak_off_hz_per_lux=0.0, hot_pixel_fraction=0.0))
    curves = {"shot noise": shot, "background": background_rate(lux, params), "total": expected_rate(lux, params)}
    spread = params.eps_sigma > 0 or (params.leak_sigma > 0 and params.has_background) or params.hot_pixels_on
    if spread:
        # the exact population mean costs seconds per point at many photons per trial: a coarse grid,
        # up to MEAN_MAX_PHOTONS (NaN beyond it and between the grid points is interpolated in log-log)
        import numpy as np

        lux = np.asarray(lux, dtype=np.float64)
        grid = np.geomspace(lux.min(), lux.max(), MEAN_POINTS)
        grid = grid[params.photons_per_trial(grid) <= MEAN_MAX_PHOTONS]
        mean = np.full((2, lux.size), np.nan)
        if grid.size >= 2:
            coarse = expected_rate(grid, params, mismatch="mean")
            inside = (lux >= grid[0]) & (lux <= grid[-1])
            for k in range(2):
                mean[k, inside] = np.exp(np.interp(np.log(lux[inside]), np.log(grid), np.log(coarse[k])))
        curves["population mean"] = mean
    return curves


def plot_rates(params, path, *, title: str = "", overwrite: bool = False) -> None:
    """PNG of the ON and OFF rates against lux (log-log), one panel per polarity, written atomically."""
    import numpy as np

    try:
        import matplotlib
    except ImportError:
        raise InputError("--plot needs matplotlib (pip install 'evnoise[plot]')") from None
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from .._atomic import atomic_output

    lux = np.geomspace(*PLOT_LUX, 241)
    curves = rate_curves(params, lux)
    styles = {"shot noise": dict(ls="--", color="tab:blue"), "background": dict(ls=":", color="tab:green"),
              "total": dict(ls="-", color="black", lw=2), "population mean": dict(ls="-.", color="tab:red")}
    positive = np.concatenate([c[c > 0] for c in curves.values() if (c > 0).any()])  # NaN > 0 is False
    top = float(positive.max()) if positive.size else 1.0
    bottom = max(float(positive.min()) if positive.size else 1e-6, top * 1e-6)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), sharey=True)
    for k, (ax, pol) in enumerate(zip(axes, ("ON", "OFF"))):
        for label, c in curves.items():
            y = np.where(c[k] > 0, c[k], np.nan)
            if np.isfinite(y).any():
                ax.plot(lux, y, label=label, **styles[label])
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(bottom / 2, top * 2)
        ax.set_xlabel("illuminance (lux)")
        ax.set_title(f"{pol} events")
        ax.grid(True, which="major", alpha=0.3)
    axes[0].set_ylabel("rate (events/s per pixel)")
    axes[1].legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    try:
        with atomic_output(path, overwrite=overwrite, what="plot") as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    finally:
        plt.close(fig)


def run(args) -> int:
    from ..params import list_presets, load_preset, preset_info

    if args.name is None:
        if args.plot:
            raise InputError("--plot needs a preset NAME")
        rows = [preset_info(n) for n in list_presets()]
        print(json.dumps(rows, indent=2) if args.json else _text_table(rows))
        return 0
    d = describe(args.name)
    if args.plot:
        from ..io import open_output_path

        open_output_path(args.plot, overwrite=args.overwrite, what="plot")  # before the curves are computed
        params = load_preset(args.name)
        plot_rates(params, args.plot, title=f"{d['name']}: {d['sensor'] or ''}".rstrip(": "),
                   overwrite=args.overwrite)
        d["plot"] = str(args.plot)
    print(json.dumps(d, indent=2, default=_json_default) if args.json else _text_show(d))
    if args.plot and not args.json:
        print(f"wrote {args.plot}")
    return 0


def _json_default(v):
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    raise TypeError(f"not JSON: {type(v).__name__}")
