"""IEBCS' per-pixel noise measured at 0.1, 161 and 3000 lux against evnoise's shot noise + leak curve.

    python -m evnoise.calibration.scripts.iebcs_ratios [--data ../shared/data/realdata] [--preset davis346]

The IEBCS repository ships, for a 50x50 patch of a real sensor, per-pixel noise histograms at three
illuminances (the sensor and the recording duration are not given). Only relative numbers can be
compared: per polarity, the mean count per pixel at each illuminance. The model is a preset's
photon shot noise (its thresholds and bias, fixed; its photon scale ``photons_per_lux`` free, which
slides the shot-noise curve along the lux axis) plus a background with an ON and an OFF floor and an
ON term growing with lux; the unknown duration ``T`` is a free scale. The five free numbers are
fitted by least squares on the log of the five non-zero mean counts; the sixth (OFF at 3000 lux,
measured 0 in 2500 pixels) is a prediction.
Prints a table and writes ``calibration/iebcs-comparison.json``. The data are read, never copied.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[1]  # calibration/: the scripts' outputs are kept there
LUX = (0.1, 161.0, 3000.0)
FILES = {("ON", 0.1): "noise_pos_0.1lux.npy", ("ON", 161.0): "noise_pos_161lux.npy",
         ("ON", 3000.0): "noise_pos_3klux.npy", ("OFF", 0.1): "noise_neg_0.1lux.npy",
         ("OFF", 161.0): "noise_neg_161lux.npy", ("OFF", 3000.0): "noise_neg_3klux.npy"}


def measured_means(folder: Path) -> dict:
    """Mean count per pixel (column -2 of each pixel's cumulative histogram) per (polarity, lux)."""
    return {key: float(np.load(folder / name)[:, :, -2].mean()) for key, name in FILES.items()}


def model_means(params, scale_s: float) -> dict:
    import evnoise as ev

    rate = ev.expected_rate(np.array(LUX), params)
    return {(pol, lux): float(scale_s * rate[k, i]) for k, pol in enumerate(("ON", "OFF")) for i, lux in enumerate(LUX)}


def fit(measured: dict, base):
    from scipy.optimize import least_squares

    keys = [k for k, v in measured.items() if v > 0]

    def params_of(x):
        return base.replace(leak_on_hz=math.exp(x[1]), leak_off_hz=math.exp(x[2]), leak_on_hz_per_lux=math.exp(x[3]),
                            photons_per_lux=base.photons_per_lux * math.exp(x[4]))

    def resid(x):
        model = model_means(params_of(x), math.exp(x[0]))
        return [math.log(max(model[k], 1e-300)) - math.log(measured[k]) for k in keys]

    best = None
    for x0 in ([math.log(10.0), math.log(0.1), math.log(0.01), math.log(1e-4), 0.0],
               [math.log(100.0), math.log(0.01), math.log(1e-3), math.log(1e-5), math.log(0.1)],
               [math.log(100.0), math.log(1e-3), math.log(1e-6), math.log(1e-5), math.log(10.0)]):
        res = least_squares(resid, x0, method="trf")
        if best is None or res.cost < best.cost:
            best = res
    return params_of(best.x), math.exp(best.x[0]), best


def main(argv=None) -> int:
    import evnoise as ev

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=HERE.parent.parent / "shared" / "data" / "realdata")
    ap.add_argument("--preset", default="davis346")
    ap.add_argument("--out", type=Path, default=HERE / "iebcs-comparison.json")
    args = ap.parse_args(argv)
    folder = args.data / "iebcs"
    if not folder.is_dir():
        print(f"error: no iebcs folder in {args.data}", file=sys.stderr)
        return 2
    measured = measured_means(folder)
    base = ev.load_preset(args.preset).replace(leak_sigma=0.0, eps_sigma=0.0)
    params, scale, res = fit(measured, base)
    model = model_means(params, scale)
    rows = []
    for pol in ("ON", "OFF"):
        for lux in LUX:
            m, f = measured[(pol, lux)], model[(pol, lux)]
            rows.append({"polarity": pol, "lux": lux, "measured_mean_count": m, "model_mean_count": f,
                         "measured_relative_to_0.1lux": m / measured[(pol, 0.1)],
                         "model_relative_to_0.1lux": f / model[(pol, 0.1)]})
            print(f"{pol:3s} {lux:7g} lux: measured {m:9.4g} ({m / measured[(pol, 0.1)]:.3g} of 0.1 lux), "
                  f"model {f:9.4g} ({f / model[(pol, 0.1)]:.3g})")
    shot = ev.expected_rate(np.array(LUX), params.replace(leak_on_hz=0.0, leak_off_hz=0.0, leak_on_hz_per_lux=0.0))
    summary = {
        "preset": args.preset,
        "fitted": {"duration_scale_s": scale, "leak_on_hz": params.leak_on_hz, "leak_off_hz": params.leak_off_hz,
                   "leak_on_hz_per_lux": params.leak_on_hz_per_lux, "photons_per_lux": params.photons_per_lux},
        "rms_log_residual": float(np.sqrt(np.mean(np.square(res.fun)))),
        "shot_noise_share": {f"{pol} {lux:g} lux": float(scale * shot[k, i] / model[(pol, lux)])
                             for k, pol in enumerate(("ON", "OFF")) for i, lux in enumerate(LUX)
                             if model[(pol, lux)] > 0},
        "rows": rows,
        "finding": "",
    }
    on_rise = measured[("ON", 3000.0)] / measured[("ON", 161.0)]
    n_pix = 2500
    p_zero = math.exp(-model[("OFF", 3000.0)] * n_pix)
    ratio_m = measured[("ON", 0.1)] / measured[("OFF", 0.1)]
    ratio_f = model[("ON", 0.1)] / model[("OFF", 0.1)]
    summary["off_3000lux_zero_probability"] = p_zero
    summary["finding"] = (
        f"Shot noise ({args.preset}'s thresholds and bias, photon scale fitted) plus an ON/OFF floor and an ON "
        f"background growing with lux match the five non-zero mean counts with an rms log residual of "
        f"{summary['rms_log_residual']:.2f}. Photon noise dominates at 0.1 lux (ON share "
        f"{summary['shot_noise_share'].get('ON 0.1 lux', float('nan')):.2f}) and has died out by 161 lux, where the "
        f"background takes over; the rise of ON noise from 161 to 3000 lux (x{on_rise:.2f}) is the growing term "
        f"(at 3000 lux {params.leak_on_hz_per_lux * 3000 / params.leak_on_hz:.2f} times the floor). Two things the "
        f"model does not reproduce: the ON/OFF ratio at 0.1 lux (measured {ratio_m:.2f}, model {ratio_f:.2f}: "
        f"{args.preset} has equal thresholds, a smaller eps_pos would raise it), and OFF noise that vanishes in bright "
        f"light: the constant OFF floor that gives OFF at 161 lux also predicts "
        f"{model[('OFF', 3000.0)] * n_pix:.0f} OFF events in the 50x50 patch at 3000 lux, where none were measured "
        f"(Poisson probability {p_zero:.1g}) - OFF background falls with light (a floor that decreases with "
        f"photocurrent, not in evnoise's parameterisation). Durations and sensor unknown: ratios only.")
    print(summary["finding"])
    args.out.write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
