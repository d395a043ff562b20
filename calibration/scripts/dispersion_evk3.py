"""How far do threshold mismatch and background spread explain the EVK3-HD's measured r(grey)?

Run ``python -m evnoise.calibration.scripts.dispersion_evk3 [--reference DIR] [--out JSON] [--step N]``.

The Noise2Image authors measured the negative-binomial shape ``r`` of the per-pixel noise count
over 1 s windows at every grey level of their monitor (``synthetic_param.npz``; grey -> lux as in
:mod:`evnoise.calibration.scripts.refit_evk3`). With the mean model of the shipped ``evk3-hd`` preset
(read at run time; the authors' constant extra OFF rate ``leak_off_hz = 0.1398`` added when the
preset does not have it yet), the population NB shape :func:`evnoise.mismatch.nb_shape` (threshold
mismatch, log-normal background spread, hot pixels; exact moments, refractory 0) is fitted to the
measured ``r`` by least squares on ``log r`` (both polarities, every ``step``-th grey level) for
nested models:

``mismatch``
    ``eps_sigma`` alone (the preset's comparison, rms log ratio 0.90);
``mismatch+spread``
    ``eps_sigma`` and the spread ``leak_sigma`` of the constant OFF leak;
``mismatch+spread+growth``
    plus a leak growing with lux, ``leak_on_hz_per_lux`` and ``leak_off_hz_per_lux`` (its spread is
    the same ``leak_sigma``);
``mismatch+spread+growth+hot``
    plus hot pixels (fraction, mean rate; spread 0, half ON), the other source of across-pixel
    variance that does not scale with the photon-noise rate.

``eps_sigma`` is optimised in an outer bounded search on its log (the threshold statistics are the
expensive part and do not depend on the background), the background terms in an inner Nelder-Mead
on their logs. The added terms also change the *mean* rate; the summary reports how far the
population mean then departs from the authors' rate curve, because ``r`` alone does not constrain
it. Writes ``calibration/evk3-dispersion.json`` (best values, rms log ratios overall, per polarity
and per region, the mean-rate change, and one sentence). The reference folder is only read.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from evnoise.errors import EvnoiseError

HERE = Path(__file__).resolve().parents[1]  # calibration/: the scripts' outputs are kept there
DEFAULT_OUT = HERE / "evk3-dispersion.json"
#: The authors' constant extra OFF rate (their fit), used when the preset has no OFF leak yet.
AUTHORS_EXTRA_OFF_HZ = 0.1398
#: Grey-level regions of the summary (lux = 9.02e-5 grey^2.2: < 0.85 lux, 0.85 .. 6.4 lux, > 6.4 lux).
REGIONS = {"dark (grey < 64)": (0, 64), "middle (grey 64-159)": (64, 160), "bright (grey >= 160)": (160, 256)}
#: Bounds of the outer search on eps_sigma (absolute, in log units of the contrast threshold).
SIGMA_BOUNDS = (0.005, 0.3)
MODELS = ("mismatch", "mismatch+spread", "mismatch+spread+growth", "mismatch+spread+growth+hot")


def base_params():
    """The shipped preset's mean model, with the authors' constant OFF leak if it has none."""
    import evnoise as ev

    p = ev.load_preset("evk3-hd")
    if p.leak_off_hz <= 0:
        p = p.replace(leak_off_hz=AUTHORS_EXTRA_OFF_HZ)
    return p


def _background_names(model):
    names = []
    if "spread" in model:
        names.append("leak_sigma")
    if "growth" in model:
        names += ["leak_on_hz", "leak_on_hz_per_lux", "leak_off_hz_per_lux"]
    if "hot" in model:
        names += ["hot_pixel_fraction", "hot_pixel_rate_hz"]
    return names


#: Starting points of the inner search (each fit also starts from the best of the previous eps_sigma).
_STARTS = (
    {"leak_sigma": 1.0, "leak_on_hz": 0.05, "leak_on_hz_per_lux": 0.003, "leak_off_hz_per_lux": 0.003,
     "hot_pixel_fraction": 1e-3, "hot_pixel_rate_hz": 5.0},
    {"leak_sigma": 2.2, "leak_on_hz": 0.01, "leak_on_hz_per_lux": 0.01, "leak_off_hz_per_lux": 0.01,
     "hot_pixel_fraction": 1e-2, "hot_pixel_rate_hz": 2.0},
)
_LOWER = {"leak_sigma": 1e-3, "leak_on_hz": 1e-6, "leak_on_hz_per_lux": 1e-7, "leak_off_hz_per_lux": 1e-7,
          "hot_pixel_fraction": 1e-7, "hot_pixel_rate_hz": 1e-3}
_UPPER = {"leak_sigma": 3.0, "leak_on_hz": 5.0, "leak_on_hz_per_lux": 10.0, "leak_off_hz_per_lux": 10.0,
          "hot_pixel_fraction": 0.2, "hot_pixel_rate_hz": 30.0}


class _Problem:
    def __init__(self, lux, r_meas, base, authors_mean, mean_weight=0.0):
        self.lux = lux
        self.log_r = np.log(r_meas)  # (2, J)
        self.log_mean = np.log(authors_mean)  # (2, J)
        self.base = base
        self.mean_weight = float(mean_weight)
        self._stats = {}

    def stats(self, eps_sigma):
        from evnoise.mismatch import LevelStats

        key = float(eps_sigma)
        if key not in self._stats:
            p = self.base.replace(eps_sigma=key)
            self._stats[key] = LevelStats(p.photons_per_trial(self.lux), p, "poisson")
        return self._stats[key]

    def params(self, eps_sigma, names, x):
        vals = {n: math.exp(min(max(float(v), math.log(_LOWER[n])), math.log(_UPPER[n])))
                for n, v in zip(names, x, strict=True)}
        return self.base.replace(eps_sigma=float(eps_sigma), **vals)

    def log_ratio(self, stats, params):
        """``log(r_model / r_measured)``, ``(2, J)``; +10 where the model has no over-dispersion."""
        inv = stats.with_background(params).inverse_shape(1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            lr = np.where(inv > 0, -np.log(np.where(inv > 0, inv, 1.0)), math.inf) - self.log_r
        return np.where(np.isfinite(lr), lr, 10.0)

    def mean_log_ratio(self, stats, params):
        """``log(population mean rate / authors' rate curve)``, ``(2, J)`` (refractory 0: exact)."""
        st = stats.with_background(params)
        return math.log(st.trial_rate_hz) + st.log_P1 - self.log_mean

    def objective(self, stats, params):
        val = float(np.mean(self.log_ratio(stats, params) ** 2))
        if self.mean_weight > 0:
            val += self.mean_weight * float(np.mean(self.mean_log_ratio(stats, params) ** 2))
        return val

    def inner(self, eps_sigma, names, x0):
        """Best background terms at one ``eps_sigma``: ``(rms, x)``."""
        from scipy.optimize import minimize

        stats = self.stats(eps_sigma)

        def f(x):
            return self.objective(stats, self.params(eps_sigma, names, x))

        if not names:
            return math.sqrt(f(np.empty(0))), np.empty(0)
        best = None
        for start in (x0, *(np.log([st[n] for n in names]) for st in _STARTS)):
            res = minimize(f, start, method="Nelder-Mead",
                           options={"xatol": 1e-4, "fatol": 1e-10, "maxiter": 400 * len(names)})
            if best is None or res.fun < best.fun:
                best = res
        return math.sqrt(best.fun), best.x


def fit_model(prob, model, *, progress=False):
    """Least squares on ``log r`` for one nested model. Returns a dict of the fit."""
    from scipy.optimize import minimize_scalar

    names = _background_names(model)
    memo = {}
    x_last = [np.log([_STARTS[0][n] for n in names])]

    def outer(log_s):
        rms, x = prob.inner(math.exp(log_s), names, x_last[0])
        memo[log_s] = (rms, x)
        x_last[0] = x
        if progress:
            print(f"  {model}: eps_sigma {math.exp(log_s):.4g} -> rms log ratio {rms:.4f}", file=sys.stderr)
        return rms

    lo, hi = (math.log(b) for b in SIGMA_BOUNDS)
    grid = np.linspace(lo, hi, 7)
    vals = [outer(g) for g in grid]
    i = int(np.argmin(vals))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    res = minimize_scalar(outer, bounds=(a, b), method="bounded", options={"xatol": 0.01})
    log_s = min(memo, key=lambda k: memo[k][0])
    rms, x = memo[log_s]
    params = prob.params(math.exp(log_s), names, x)
    del res
    return {"model": model, "params": params, "names": names, "objective": rms**2, "mean_weight": prob.mean_weight}


def _at_bound(name, value) -> bool:
    lo, hi = SIGMA_BOUNDS if name == "eps_sigma" else (_LOWER[name], _UPPER[name])
    return bool(value <= lo * 1.01 or value >= hi / 1.01)


def summarize(prob, fits, grey, step):
    out = {
        "what": "fit of the population NB shape r (threshold mismatch + background spread + hot pixels, exact moments) "
                "to the measured r(grey) of the Noise2Image EVK3-HD tables, least squares on log r",
        "command": "python -m evnoise.calibration.scripts.dispersion_evk3",
        "mean_model": {k: getattr(prob.base, k) for k in ("eps_pos", "eps_neg", "bias_pr", "trial_rate_hz",
                                                           "photons_per_lux", "dark_lux", "leak_off_hz")},
        "grey_step": step,
        "regions": {k: list(v) for k, v in REGIONS.items()},
        "authors_mean_curve": "the authors' fitted rate curve with their constant extra OFF rate "
                              "(refit_evk3.authors_rate)",
        "models": [],
    }
    for fit in fits:
        p = fit["params"]
        stats = prob.stats(p.eps_sigma)
        lr = prob.log_ratio(stats, p)
        mean_lr = prob.mean_log_ratio(stats, p)
        entry = {
            "model": fit["model"],
            "fitted_to": "log r and log mean rate (equal weights)" if fit["mean_weight"] > 0 else "log r only",
            "best": {"eps_sigma": p.eps_sigma, **{n: getattr(p, n) for n in fit["names"]}},
            "at_bounds": [n for n in ("eps_sigma", *fit["names"])
                          if _at_bound(n, getattr(p, n))],
            "eps_sigma_over_eps_pos": p.eps_sigma / p.eps_pos,
            "r_rms_log_ratio": float(np.sqrt(np.mean(lr**2))),
            "r_rms_log_ratio_on_off": [float(np.sqrt(np.mean(lr[k] ** 2))) for k in range(2)],
            "r_mean_log_ratio_by_region": {},
            "r_rms_log_ratio_by_region": {},
            "mean_rate_rms_log_ratio_vs_authors_curve": {},
        }
        for name, (g0, g1) in REGIONS.items():
            sel = (grey >= g0) & (grey < g1)
            entry["r_mean_log_ratio_by_region"][name] = [float(np.mean(lr[k, sel])) for k in range(2)]
            entry["r_rms_log_ratio_by_region"][name] = float(np.sqrt(np.mean(lr[:, sel] ** 2)))
            ok = np.isfinite(mean_lr[:, sel])
            entry["mean_rate_rms_log_ratio_vs_authors_curve"][name] = float(np.sqrt(np.mean(mean_lr[:, sel][ok] ** 2)))
        entry["mean_rate_rms_log_ratio_vs_authors_curve"]["all"] = float(np.sqrt(np.mean(mean_lr**2)))
        pick = [g for g in (0, 32, 64, 128, 192, 240) if g in set(grey.astype(int).tolist())]
        idx = [int(np.flatnonzero(grey == g)[0]) for g in pick]
        r_model = np.exp(lr + prob.log_r)
        entry["r_at_grey"] = {str(g): {"measured": np.exp(prob.log_r[:, i]).tolist(), "model": r_model[:, i].tolist()}
                              for g, i in zip(pick, idx)}
        out["models"].append(entry)
    return out


def _verdict(summary):
    """One sentence on how far the explanation goes, from the fitted numbers."""
    r_only = [e for e in summary["models"] if e["fitted_to"] == "log r only"]
    joint = [e for e in summary["models"] if e["fitted_to"] != "log r only"]
    alone = r_only[0]
    best = min(r_only, key=lambda e: e["r_rms_log_ratio"])
    bj = min(joint, key=lambda e: e["r_rms_log_ratio"] ** 2 + e["mean_rate_rms_log_ratio_vs_authors_curve"]["all"] ** 2)
    dark = "dark (grey < 64)"
    bounds = "; its parameters at their bounds" if best["at_bounds"] else ""
    return (f"Threshold mismatch alone misses the measured r(grey) by an rms log ratio of "
            f"{alone['r_rms_log_ratio']:.2f} "
            f"(factor {math.exp(alone['r_rms_log_ratio']):.1f}); adding a log-normal background spread, a leak growing "
            f"with lux and hot pixels improves this only to {best['r_rms_log_ratio']:.2f} (factor "
            f"{math.exp(best['r_rms_log_ratio']):.1f}, dark levels still off by "
            f"{best['r_rms_log_ratio_by_region'][dark]:.2f}{bounds}) while moving the population mean off the "
            f"authors' rate curve (rms log ratio {best['mean_rate_rms_log_ratio_vs_authors_curve']['all']:.1f}), and "
            f"held to the mean curve the best is {bj['r_rms_log_ratio']:.2f} on r: the model's across-pixel terms do "
            f"not explain r(grey), whose dispersion is small in the dark (r ~ 0.5) and heavy-tailed at the bright end "
            f"(r ~ 0.02), which one shared log-normal spread plus a threshold mismatch (that, at this preset's small "
            f"thresholds, inflates the dark mean) cannot produce together.")


def run(reference: Path, out: Path | None, *, step: int = 1, models=MODELS, progress=False):
    from .refit_evk3 import authors_rate, load_reference

    grey, lux, lux_authors, r_on, r_off, _ = load_reference(reference)
    idx = np.unique(np.concatenate([np.arange(0, 256, step), [255]]))
    grey, lux, lux_authors = grey[idx], lux[idx], lux_authors[idx]
    r = np.stack([r_on[idx], r_off[idx]])
    authors_mean = authors_rate(lux_authors, include_extra_off=True)
    prob = _Problem(lux, r, base_params(), authors_mean)
    fits = []
    for weight in (0.0, 1.0):
        prob.mean_weight = weight
        fits += [fit_model(prob, m, progress=progress) for m in models]
    summary = summarize(prob, fits, grey, step)
    summary["verdict"] = _verdict(summary)
    if out is not None:
        out = Path(out)
        out.write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def main(argv=None) -> int:
    from .refit_evk3 import DEFAULT_REFERENCE

    ap = argparse.ArgumentParser(prog="python -m evnoise.calibration.scripts.dispersion_evk3",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE, help="noise2image-reference folder")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="summary JSON (default: %(default)s)")
    ap.add_argument("--step", type=int, default=4, help="use every STEP-th grey level (default: %(default)s)")
    ap.add_argument("--quiet", action="store_true", help="no progress on stderr")
    args = ap.parse_args(argv)
    try:
        if args.step < 1:
            raise EvnoiseError("--step must be >= 1")
        s = run(args.reference, args.out, step=args.step, progress=not args.quiet)
    except EvnoiseError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for e in s["models"]:
        best = ", ".join(f"{k} = {v:.4g}" for k, v in e["best"].items())
        reg = ", ".join(f"{k.split(' (')[0]} {v:.2f}" for k, v in e["r_rms_log_ratio_by_region"].items())
        bound = f" [at bounds: {', '.join(e['at_bounds'])}]" if e["at_bounds"] else ""
        print(f"[{e['fitted_to']}] {e['model']:<28} rms log r ratio {e['r_rms_log_ratio']:.3f} ({reg}); "
              f"mean-rate rms log ratio {e['mean_rate_rms_log_ratio_vs_authors_curve']['all']:.2f}; {best}{bound}")
    print(s["verdict"])
    if args.out is not None:
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
