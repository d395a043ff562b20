"""Specification of a fit: the parameters, their defaults and bounds, the constants of the method, and
:class:`FitSpec`, the frozen description of one fit.

Used by :mod:`.fit` (the names the tests need are public here, in the module that owns them).
"""

from __future__ import annotations

import dataclasses
import math
from types import MappingProxyType
from typing import Mapping

from evnoise.errors import InputError, ParameterError
from evnoise.params import NoiseParams, fit_bounds, names_with_fit_role, parameter_names, parameter_specs

from ..measurements import Measurements

#: Every parameter of :class:`NoiseParams`, in its order.
FIT_NAMES = parameter_names()
#: Fitted by default (``fit_role == "core"`` in :func:`evnoise.params.parameter_specs`).
CORE = names_with_fit_role("core")
DISTRIBUTIONS = ("binomial", "poisson")
#: Bounds of the fit (natural units), from :func:`evnoise.params.fit_bounds`. ``None`` entries are set
#: from the data: ``trial_rate_hz`` from the highest rate (p < 1/2), ``photons_per_lux`` so that the
#: brightest level has 1e-3 to :data:`LAM_MAX` photons per trial (:data:`LAM_MAX_MISMATCH` with threshold
#: mismatch), ``dark_lux`` from 1e-6 to 10 times the brightest level, ``refractory_s`` below half the
#: shortest mean interval between events. ``calibrate(bounds=...)`` overrides any of them.
BOUNDS = MappingProxyType({n: fit_bounds(n) for n in FIT_NAMES if fit_bounds(n) is not None})
#: Background floors: fitted by default when the data have a dark level (lux <= :data:`DARK_LUX`,
#: which identifies them), else only when asked (a floor the data do not need ends on its lower
#: bound, which stands for 0, and is reported as 0). Bounds from the data: ``1e-7`` to 10 times the
#: highest measured rate (per lux of the brightest level for the growing terms).
FLOORS = names_with_fit_role("floor")
#: Illuminance up to which a level counts as dark (the floors are then fitted by default): a level at 0 lux.
DARK_LUX = 0.0
#: Growth of the background with lux: fitted only when asked (``free=[...]``, ``--fit``).
GROWTH = names_with_fit_role("growth")
#: Per-pixel spread of the background and hot pixels: only from flat fields (per-pixel counts),
#: only when asked; the likelihood then mixes over them (:mod:`.likelihood`).
SPREAD = names_with_fit_role("spread")
#: The photoreceptor time constant only acts on changing scenes: static measurements do not
#: identify it, it is never fitted and always reported as not identified.
NEVER = names_with_fit_role("never")
#: Terms whose lower bound stands for 0 and that are reported as 0 there (no warning: a sensor
#: without a floor is an ordinary result).
ZERO_AT_BOUND = tuple(s.name for s in parameter_specs() if s.fit_low == "zero")
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
#: Starting values of the search where nothing else gives one (every field).
STARTS = MappingProxyType({s.name: s.fit_start for s in parameter_specs()})
#: Terms the likelihood does not model: kept at their given values, never fitted (the count
#: likelihood treats background arrivals as Poisson, ``leak_regularity = 0``).
UNMODELLED = names_with_fit_role("unmodelled")
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
#: Terms for which ending on the lower bound is an ordinary result, not flagged (the bound stands for 0).
AT_BOUND_OK = tuple(s.name for s in parameter_specs() if s.fit_low in ("ok", "zero"))


@dataclasses.dataclass(frozen=True, eq=False)
class FitSpec:
    """What one fit is: the frozen specification a likelihood (``likelihood.Problem``) is built on.

    A stage of the fit that changes any of it (a continuation step, a parameter held on a
    profile, reweighted blocks) builds a new spec (:func:`dataclasses.replace` or the ``with_``
    helpers below) and a new problem from it; nothing is assigned on a live one.

    Attributes
    ----------
    method : str
        Closed form of the per-trial probability (:data:`evnoise.mismatch.METHODS`).
    distribution : str
        Count distribution of one pixel given its thresholds (:data:`DISTRIBUTIONS`).
    free : tuple of str
        Fitted parameters, in :data:`FIT_NAMES` order as given.
    values : mapping
        Every field of :class:`NoiseParams`: the value of each parameter that is not free (and
        the starting value of the free ones); read-only.
    bounds : mapping
        ``name -> (low, high)`` in natural units (at least every free parameter); read-only.
    weights : mapping
        Weight of each block of a rate table's likelihood: ``"counts"`` (the level totals) and
        ``"shape"`` (the measured NB shapes); read-only.
    fit_shape : bool
        Whether the measured NB shapes are fitted (otherwise only compared with the model).
    assumed_sigma : bool
        Whether ``eps_sigma`` is the assumed :data:`TABLE_SIGMA` (reported as such).
    """

    method: str
    distribution: str
    free: tuple
    values: Mapping[str, float]
    bounds: Mapping[str, tuple]
    weights: Mapping[str, float] = dataclasses.field(default_factory=lambda: {"counts": 1.0, "shape": 1.0})
    fit_shape: bool = False
    assumed_sigma: bool = False

    def __post_init__(self):
        # frozen all the way down: tuples and read-only copies of the mappings
        object.__setattr__(self, "free", tuple(self.free))
        object.__setattr__(self, "values", MappingProxyType(dict(self.values)))
        object.__setattr__(self, "bounds", MappingProxyType({n: tuple(b) for n, b in self.bounds.items()}))
        object.__setattr__(self, "weights", MappingProxyType(dict(self.weights)))

    def with_value(self, name: str, value: float) -> "FitSpec":
        """The same fit with parameter ``name`` at ``value``."""
        return dataclasses.replace(self, values={**self.values, name: float(value)})

    def with_fixed(self, name: str, value: float) -> "FitSpec":
        """The same fit with ``name`` held at ``value`` (no longer free)."""
        return dataclasses.replace(self, free=tuple(n for n in self.free if n != name),
                                   values={**self.values, name: float(value)})

    def with_weights(self, **weights: float) -> "FitSpec":
        """The same fit with the given block weights changed."""
        return dataclasses.replace(self, weights={**self.weights, **weights})


def resolve_parameters(meas: Measurements, free, fixed, initial, fit_dispersion: bool = True):
    fixed = dict(fixed or {})
    for n in fixed:
        if n not in FIT_NAMES:
            raise ParameterError(f"unknown parameter {n!r} to fix; parameters: {', '.join(FIT_NAMES)}")
    if free is None:
        free = list(CORE)
        if meas.has_dispersion and fit_dispersion:
            free.append("eps_sigma")
        if float(meas.lux.min()) <= DARK_LUX:
            free += list(FLOORS)  # a dark level identifies the floors; without one they cost time and rarely fit
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
    for n in NEVER:
        if n in free:
            raise InputError(f"{n} cannot be fitted from static measurements (it only acts on changing scenes); "
                             f"fix it (--fix {n}=...) or leave it out")
    for n in UNMODELLED:
        if n in free:
            raise InputError(f"{n} cannot be fitted: the calibration likelihood does not model it (background "
                             f"arrivals are taken as Poisson); fix it or leave it out")
    spread = [n for n in free if n in SPREAD]
    if spread and meas.kind != "flat-field":
        raise InputError(f"{', '.join(spread)} describe(s) how the background differs between pixels: they can only "
                         f"be fitted from flat fields with per-pixel counts, not from a rate table; fix them")
    if "eps_sigma" in free and not (meas.has_dispersion and fit_dispersion):
        raise InputError("eps_sigma cannot be fitted from mean rates alone: give per-pixel counts (flat fields) "
                         "or measured NB shapes (r_on, r_off columns), or fix it")
    values = dict(STARTS)
    if not (meas.has_dispersion and fit_dispersion) and "eps_sigma" not in fixed and initial is None:
        values["eps_sigma"] = TABLE_SIGMA
    if initial is not None:
        if not isinstance(initial, NoiseParams):
            raise ParameterError(f"initial must be a NoiseParams, got {type(initial).__name__}")
        values.update(initial.to_dict())
    values.update({n: float(v) for n, v in fixed.items()})
    NoiseParams(**values)  # validates the fixed values
    return free, fixed, values


def data_bounds(meas: Measurements, free, values, override=None):
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
    rate_ref = max(rate_max, 1e-9)
    for n in FLOORS:
        b[n] = (1e-7 * rate_ref, 10.0 * rate_ref)
    for n in GROWTH:
        b[n] = (1e-7 * rate_ref / lux_ref, 10.0 * rate_ref / lux_ref)
    # a hot pixel fires at most once per trial: its rate stays below the trial rate
    b["hot_pixel_rate_hz"] = (1e-3 * rate_ref, b["trial_rate_hz"][1])
    for n, (lo, hi) in (override or {}).items():
        b[n] = (float(lo), float(hi))
    for n in free:
        lo, hi = b[n]
        v = values[n]
        if not (lo < v < hi):
            values[n] = float(min(max(v, lo * 1.5), hi / 1.5))
    return b


def check_bounds(bounds):
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
