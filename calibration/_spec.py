"""Specification of a fit: the parameters, their defaults and bounds, and the constants of the method.

Internal to :mod:`evnoise.calibration.fit`, which re-exports these names.
"""

from __future__ import annotations

import dataclasses
import math

from evnoise.errors import InputError, ParameterError
from evnoise.params import NoiseParams

from .measurements import Measurements

#: Every parameter of :class:`NoiseParams`, in its order.
FIT_NAMES = tuple(f.name for f in dataclasses.fields(NoiseParams))
CORE = FIT_NAMES[:6]
DISTRIBUTIONS = ("binomial", "poisson")
#: Bounds of the fit (natural units). ``None`` entries are set from the data: ``trial_rate_hz``
#: from the highest rate (p < 1/2), ``photons_per_lux`` so that the brightest level has 1e-3 to
#: :data:`LAM_MAX` photons per trial (:data:`LAM_MAX_MISMATCH` with threshold mismatch),
#: ``dark_lux`` from 1e-6 to 10 times the brightest level, ``refractory_s`` below half the
#: shortest mean interval between events. ``calibrate(bounds=...)`` overrides any of them.
BOUNDS = {
    "eps_pos": (1e-3, 5.0),
    "eps_neg": (1e-3, 5.0),
    "bias_pr": (1e-6, 1e4),
    "trial_rate_hz": (None, 5e5),
    "photons_per_lux": (None, None),
    "dark_lux": (None, None),
    "refractory_s": (1e-8, None),
    "eps_sigma": (1e-3, 1.5),
}
#: Most photons per trial at the brightest level that the fit explores without threshold
#: mismatch: the range over which :mod:`evnoise.model`'s exact probability is verified (its cost
#: grows like ``sqrt(lam)``: about 10 ms for a 15-level table at 1e4 photons per trial). Real
#: sensors (the shipped EVK3-HD preset has 3200 at 50 lux) are far in this range; a fit that
#: runs into it is in the many-photon limit, where ``photons_per_lux`` is not identified.
LAM_MAX = 1e6
#: The same with threshold mismatch (``eps_sigma > 0``): the exact distribution of ``p`` across
#: pixels (:func:`evnoise.calibration.threshold_distribution`) costs O(lam) per level and
#: polarity (about 0.1 s at 3000 photons per trial, 30 s at 3e5), so the search stops here; the
#: mismatch-free alternative of a mean-rate table (see :data:`TABLE_SIGMA`) is not limited by it.
LAM_MAX_MISMATCH = 3000.0
_DEFAULTS = dict(eps_pos=0.5, eps_neg=0.5, bias_pr=1.0, trial_rate_hz=100.0, photons_per_lux=1.0, dark_lux=0.1,
                 refractory_s=0.0, eps_sigma=0.0)
#: Threshold mismatch assumed when the measurements carry no dispersion (mean rates only), unless
#: it is fixed explicitly or given by ``initial``: it is not determined by mean rates, mismatch
#: is always present in real sensors, and without it the exact likelihood is a step function of
#: the thresholds and the bias (see ``SMOOTHING``).
TABLE_SIGMA = 0.05
#: Mismatch levels of the continuation used to fit the mismatch-free (step-like) model to flat
#: fields (rate tables are fitted directly: their stand-in search is already smoothed).
SMOOTHING = (0.05, 0.02, 0.008)
#: Starts fitted to convergence after the short screening fits (optima are close in likelihood).
N_CONVERGED = 4
#: Goodness-of-fit p-value below which a fit is rejected (tables with counts, flat fields).
REJECT_P = 1e-4
#: Rates without exposure (no absolute noise scale): rms relative residual above which a fit is rejected.
REJECT_RMS = 0.25
#: Step of the profile of ``photons_per_lux`` (rate tables), in log units.
PROFILE_STEP = 0.35
#: Largest profile step (steps grow by half while the profile stays within its interval).
PROFILE_MAX_STEP = 1.5
#: The profile stops where twice the log-likelihood has dropped by this much from its maximum
#: (plus :data:`PROFILE_ROUGH` for step-like likelihoods).
PROFILE_STOP = 9.0
#: Without threshold mismatch the exact likelihood is a step function of the thresholds and the
#: bias, and fits along the profile land a few log-likelihood units apart by chance (up to about
#: 4 on tables simulated from the EVK3-HD preset, where the smooth profile is flat): a profile
#: point counts as inside the interval when twice its log-likelihood is within 1 + this of the
#: maximum, so that such jitter is not mistaken for information (it errs towards "not identified").
PROFILE_ROUGH = 10.0
_AT_BOUND_OK = ("bias_pr", "dark_lux", "eps_sigma", "refractory_s")  # a lower bound standing for 0


def _resolve(meas: Measurements, free, fixed, initial, fit_dispersion: bool = True):
    fixed = dict(fixed or {})
    for n in fixed:
        if n not in FIT_NAMES:
            raise ParameterError(f"unknown parameter {n!r} to fix; parameters: {', '.join(FIT_NAMES)}")
    if free is None:
        free = list(CORE)
        if meas.has_dispersion and fit_dispersion:
            free.append("eps_sigma")
    else:
        free = list(free)
        for n in free:
            if n not in FIT_NAMES:
                raise ParameterError(f"unknown parameter {n!r} to fit; parameters: {', '.join(FIT_NAMES)}")
        if len(set(free)) != len(free):
            raise ParameterError("a parameter is listed twice in free")
    free = [n for n in FIT_NAMES if n in free and n not in fixed]
    if not free:
        raise ParameterError("nothing to fit: every parameter is fixed")
    if "eps_sigma" in free and not (meas.has_dispersion and fit_dispersion):
        raise InputError("eps_sigma cannot be fitted from mean rates alone: give per-pixel counts (flat fields) "
                         "or measured NB shapes (r_on, r_off columns), or fix it")
    values = dict(_DEFAULTS)
    if not (meas.has_dispersion and fit_dispersion) and "eps_sigma" not in fixed and initial is None:
        values["eps_sigma"] = TABLE_SIGMA
    if initial is not None:
        if not isinstance(initial, NoiseParams):
            raise ParameterError(f"initial must be a NoiseParams, got {type(initial).__name__}")
        values.update(initial.to_dict())
    values.update({n: float(v) for n, v in fixed.items()})
    NoiseParams(**values)  # validates the fixed values
    return free, fixed, values


def _bounds(meas: Measurements, free, values, override=None):
    b = dict(BOUNDS)
    lux_ref = float(max(meas.lux.max(), 1e-6))
    rate_max = float(meas.rate_hz.max())
    n_lo = 2.0 * rate_max
    if meas.kind == "flat-field":
        n_lo = max(n_lo, max(float(c.max()) / d for c, d in zip(meas.pixel_counts, meas.duration_s)))
    b["trial_rate_hz"] = (max(n_lo * (1 + 1e-6), 1e-3), 5e5)
    mismatch = "eps_sigma" in free or values["eps_sigma"] > 0
    b["photons_per_lux"] = (1e-3 / lux_ref, (LAM_MAX_MISMATCH if mismatch else LAM_MAX) / lux_ref)
    b["dark_lux"] = (1e-6 * lux_ref, 10.0 * lux_ref)
    # the bias moves with photons_per_lux along the many-photon ridge: allow it as many photons
    b["bias_pr"] = (BOUNDS["bias_pr"][0], max(BOUNDS["bias_pr"][1], 10.0 * b["photons_per_lux"][1] * lux_ref))
    b["refractory_s"] = (1e-8, min(1.0, 0.5 / max(rate_max, 1e-9)))
    for n, (lo, hi) in (override or {}).items():
        b[n] = (float(lo), float(hi))
    for n in free:
        lo, hi = b[n]
        v = values[n]
        if not (lo < v < hi):
            values[n] = float(min(max(v, lo * 1.5), hi / 1.5))
    return b


def _check_bounds(bounds):
    if bounds is None:
        return None
    if not isinstance(bounds, dict):
        raise ParameterError(f"bounds must be a dict name -> (low, high), got {type(bounds).__name__}")
    out = {}
    for n, v in bounds.items():
        if n not in FIT_NAMES:
            raise ParameterError(f"bounds: unknown parameter {n!r}; parameters: {', '.join(FIT_NAMES)}")
        try:
            lo, hi = (float(x) for x in v)
        except (TypeError, ValueError):
            raise ParameterError(f"bounds[{n!r}] must be a pair (low, high), got {v!r}") from None
        if not (0 < lo < hi < math.inf):
            raise ParameterError(f"bounds[{n!r}] must satisfy 0 < low < high < inf, got ({lo:g}, {hi:g})")
        out[n] = (lo, hi)
    return out
