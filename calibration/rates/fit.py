"""Maximum-likelihood calibration of :class:`evnoise.NoiseParams` to measurements.

Model
    At illuminance ``lux`` a pixel with thresholds ``(eps_on, eps_off)`` fires per trial with the
    exact probabilities of :mod:`evnoise.model` at ``lam = photons_per_lux (lux + dark_lux)``;
    thresholds vary across pixels as ``N(eps_pos|eps_neg, eps_sigma)`` truncated to ``> 0``
    (:mod:`evnoise.mismatch` gives the exact distribution across pixels).

Likelihoods
    *Flat fields* (per-pixel counts): the composite likelihood of every pixel's count at every
    level, each the exact mixture over the threshold distribution of ``Binomial(M, q)``
    (``M = trial_rate_hz * duration_s`` trials; ``distribution="poisson"``: ``Poisson(M q)``).
    A pixel keeps its thresholds at all levels, so its counts are correlated; the
    uncertainties are the cluster-robust (sandwich) ones with pixels as clusters.
    *Rate tables*: Poisson likelihood of the total counts (negative binomial with the measured
    shape when ``r_on, r_off`` and ``n_pixels`` are given), plus, with measured shapes, a
    normal likelihood for the excess dispersion ``1/r``. When the absolute counts are unknown
    (no ``n_pixels, duration_s``) or the residuals scatter more than the count noise, the
    covariance is scaled by the residual dispersion (quasi-likelihood).

Fit
    All parameters are fitted on a log scale within data-scaled bounds (:data:`BOUNDS`). Global
    search: quasi-random seeds scored by a cheap stand-in (mean-rate deviance without mismatch,
    ``trial_rate_hz`` profiled out), stratified along ``bias_pr`` because the rate curve hardly
    changes along a ridge of (``photons_per_lux``, ``bias_pr``, thresholds) that carries several
    local optima of the exact model; two seeds per stratum are refined on the stand-in, a few
    Levenberg-Marquardt-damped Fisher-scoring steps of the full likelihood screen them, the
    best :data:`N_CONVERGED` are run to convergence, and short fits along the least-constrained
    direction look for a better optimum on the ridge. For the mismatch-free model (a step
    function of ``eps`` and ``bias_pr``) a Nelder-Mead polish follows. Uncertainties come from
    the expected information (or the sandwich) computed by central differences in
    log-parameter space; each step is checked against half of it, because without mismatch the
    likelihood is step-like.

Background (issue 15)
    The background floors ``leak_on_hz`` and ``leak_off_hz`` are fitted by default (:data:`FLOORS`):
    a level in the dark, or one bright enough that the photon noise vanishes, determines them; a
    floor the data cannot separate from the photon noise is reported as not identified (with a
    warning), and one the data do not need ends on its lower bound, which stands for 0 and is
    reported as 0. Their growth with lux (:data:`GROWTH`) is fitted only when listed in ``free``;
    the per-pixel spread ``leak_sigma`` and the hot-pixel terms (:data:`SPREAD`) only from flat
    fields and when listed (the likelihood mixes over them). ``pr_tau_s_at_1lux`` acts only on
    changing scenes: static data do not identify it, it is never fitted (:data:`NEVER`).

Rate tables: profile of ``photons_per_lux``
    Along the ridge (``photons_per_lux`` up, thresholds down like its inverse square root,
    ``bias_pr`` up in proportion) the rate curve approaches the many-photon limit, where it no
    longer changes; the exact likelihood is rough there (a step function of the thresholds), so
    its local curvature says nothing about how far the ridge extends. The fit therefore profiles
    ``photons_per_lux`` (steps of :data:`PROFILE_STEP` in log, the others refitted at each) out
    to where the log-likelihood has dropped by 4.5 or to the bound: its standard error is the
    half-width of the interval where it is within 0.5 of the maximum (0.5 plus half of
    :data:`PROFILE_ROUGH` for the step-like mismatch-free likelihood), and the others'
    uncertainties add their movement along the profile to the conditional ones; a profile
    sharper than its steps falls back to the local information. An interval that reaches a
    bound means *not identified*, and so are the parameters that move with it.

Fit status
    :attr:`CalibrationResult.fit_status` is ``"accepted"``, ``"rejected"`` (goodness-of-fit
    p-value below :data:`REJECT_P`, or for rates without exposure an rms relative residual above
    :data:`REJECT_RMS`; the parameters are then marked ``"fitted (fit rejected)"``) and
    :attr:`CalibrationResult.warnings` says so, and names every parameter that sits on a bound.

Identifiability
    A parameter whose relative standard error exceeds ``max_rel_se`` is reported as *not
    identified*, together with the products/ratios of parameters that the data do constrain;
    parameters that sit on a bound (``bias_pr``, ``dark_lux``, ``eps_sigma`` -> 0) are reported
    as such and treated as fixed there for the uncertainties of the others.

Layout
    This module holds :func:`calibrate`; the method is split by job into ``spec`` (parameters,
    defaults, bounds, constants, and the frozen ``FitSpec`` of a fit: each stage that changes it
    builds a new one), ``likelihood`` (the likelihood of each kind of data),
    ``search`` (stand-in pre-fits, local fits, ridge walk, continuation, profile),
    ``uncertainty`` (information, sandwich, profile intervals, identifiability, goodness of
    fit, verdict) and ``result`` (:class:`CalibrationResult`).
"""

from __future__ import annotations

import logging

from evnoise.errors import InputError, ParameterError
from evnoise.mismatch import METHODS
from evnoise.params import NoiseParams

from .._progress import Phases
from ..measurements import Measurements
from .result import CalibrationResult
from .search import comparable_loglik, profile_likelihood, run_search
from .spec import DISTRIBUTIONS, FIT_NAMES, FLOORS, GROWTH, SPREAD, TABLE_SIGMA, check_bounds, resolve_parameters
from .uncertainty import finish, rejected

__all__ = ["calibrate", "CalibrationResult", "FIT_NAMES"]

log = logging.getLogger("evnoise.calibration")


#: most strata of starting points and screened seeds a fit takes (each start is a full optimisation: 1000 take hours;
#: 1e9 asked for an array of gigabytes before the first one)
MAX_STARTS = 1000
MAX_SEEDS = 1 << 20


def calibrate(measurements: Measurements, *, method: str = "poisson", distribution: str = "binomial",
              free=None, fixed: dict | None = None, initial: NoiseParams | None = None, n_starts: int = 4,
              n_seeds: int = 2048, rng=None, unidentified: str = "report", max_rel_se: float = 0.5,
              dispersion: str = "fit", bounds: dict | None = None, progress: bool = False) -> CalibrationResult:
    """Fit the noise model to measurements by maximum likelihood.

    Parameters
    ----------
    measurements : Measurements
        From :func:`read_measurements`, :func:`rate_table`, :func:`flat_field`, ...
    method : {"poisson", "gaussian"}
        Closed form of the per-trial probability: exact (default) or the paper's eq. 3.
    distribution : {"binomial", "poisson"}
        Flat fields: count distribution of one pixel given its thresholds (binomial in
        ``trial_rate_hz * duration_s`` trials, as the model; or Poisson, as the paper).
    free : sequence of str, optional
        Parameters to fit (default: the six core parameters and the background floors
        ``leak_on_hz``, ``leak_off_hz``, plus ``eps_sigma`` when the measurements carry
        dispersion). ``refractory_s`` and the background's growth with lux are only fitted when
        listed; ``leak_sigma`` and the hot-pixel terms only from flat fields and when listed;
        ``pr_tau_s_at_1lux`` never (static data do not identify it).
    fixed : dict, optional
        Values of parameters held fixed (removed from ``free``).
    initial : NoiseParams, optional
        Starting point and values of parameters neither free nor fixed (default: zeros for
        ``refractory_s``, ``eps_sigma`` and the background terms).
    n_starts : int
        Strata of starting points along ``bias_pr`` (two starts each are screened, the best
        :data:`N_CONVERGED` fitted to convergence): the rate curve is not monotonic and the
        likelihood has several local optima. More strata are slower and safer (``evnoise calibrate``
        uses 6: the command line's fits and this default's may differ where optima compete).
    n_seeds : int
        Quasi-random parameter vectors scored to choose the starts.
    rng : int, Generator or None
        Scrambling of the quasi-random seeds (None: fresh entropy; pass a seed for a
        reproducible fit).
    unidentified : {"report", "fix"}
        What to do with parameters the data do not constrain: keep the fitted value and report
        them (default), or fix them (at ``fixed``/``initial`` values if given, else at the
        fitted value) and refit the rest, so the others' uncertainties are conditional on them.
    max_rel_se : float
        Relative standard error above which a parameter counts as not identified.
    dispersion : {"fit", "report"}
        Rate tables with measured NB shapes: fit them (default; determines ``eps_sigma``) or
        only compare them with the model (``eps_sigma`` then fixed, at 0 unless given).
    bounds : dict, optional
        ``{name: (low, high)}`` in natural units, replacing the default bounds of those
        parameters (see :data:`BOUNDS`); a parameter that ends on one is flagged.
    progress : bool
        Show progress: a line naming the running phase (search, profile, uncertainties, refits) with its
        elapsed time, and a bar over the starts of each search.

    Returns
    -------
    CalibrationResult
        The fitted parameters with their uncertainties, identifiability findings and goodness of fit.
    """
    from evnoise._checks import as_generator

    if not isinstance(measurements, Measurements):
        raise InputError(f"measurements must be a Measurements object, got {type(measurements).__name__}")
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    if distribution not in DISTRIBUTIONS:
        raise ParameterError(f"distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
    if unidentified not in ("report", "fix"):
        raise ParameterError(f"unidentified must be 'report' or 'fix', got {unidentified!r}")
    if dispersion not in ("fit", "report"):
        raise ParameterError(f"dispersion must be 'fit' or 'report', got {dispersion!r}")
    if dispersion == "report" and measurements.kind == "flat-field":
        raise ParameterError("dispersion='report' applies to rate tables; the flat-field likelihood always uses "
                             "the per-pixel counts")
    if not (isinstance(n_starts, int) and 1 <= n_starts <= MAX_STARTS):
        raise ParameterError(f"n_starts must be an integer from 1 to {MAX_STARTS}, got {n_starts!r}")
    if not (isinstance(n_seeds, int) and n_starts <= n_seeds <= MAX_SEEDS):
        raise ParameterError(f"n_seeds must be an integer from n_starts to {MAX_SEEDS:,}, got {n_seeds!r}")
    if not (isinstance(max_rel_se, (int, float)) and max_rel_se > 0):
        raise ParameterError(f"max_rel_se must be > 0, got {max_rel_se!r}")
    gen = as_generator(rng)
    meas = measurements
    free, fixed, values = resolve_parameters(meas, free, fixed, initial, fit_dispersion=dispersion == "fit")
    n_points = 2 * meas.n_levels
    needed = len([n for n in free if n != "eps_sigma"]) + 1
    if n_points < needed:
        raise InputError(
            f"{meas.n_levels} illuminance levels give {n_points} rates, too few to fit {needed - 1} parameters "
            f"({', '.join(n for n in free if n != 'eps_sigma')}); measure more levels or fix some parameters"
        )
    from evnoise.terms.timer import largest_regularity

    candidate = NoiseParams(**values)
    background_on = candidate.has_background or any(n in free for n in FLOORS + GROWTH + SPREAD)
    regular = largest_regularity(candidate) > 0
    if regular and background_on and (meas.kind == "flat-field" or meas.nb_shape is not None):
        what = "flat fields (per-pixel counts)" if meas.kind == "flat-field" else "a table's measured NB shapes"
        raise ParameterError(
            f"a regular background (leak_regularity = {values['leak_regularity']:g}, hot_pixel_regularity = "
            f"{values.get('hot_pixel_regularity', -1.0):g}) is modelled in the mean rates only, not in {what}: fix "
            "leak_regularity=0 and hot_pixel_regularity=-1, or calibrate the background from a quiet recording")
    bounds = check_bounds(bounds)
    assumed = ("eps_sigma" not in free and "eps_sigma" not in fixed and initial is None
               and values["eps_sigma"] == TABLE_SIGMA)
    fit_args = dict(gen=gen, n_starts=n_starts, n_seeds=n_seeds, progress=progress, have_initial=initial is not None,
                    dispersion=dispersion, bounds=bounds)
    want_profile = meas.kind == "table" and "photons_per_lux" in free and len(free) >= 2
    # every phase shows on the progress line (the search has its own bar over the starts below it): after the
    # search a profile and the uncertainties ran for up to 18 minutes without a sign of life (issue 29)
    with Phases("calibrate", 2 + want_profile, enabled=progress) as phases:
        return _calibrate_phases(phases, meas, method, distribution, free, fixed, values, initial, assumed,
                                 want_profile, fit_args, n_starts, max_rel_se, unidentified, dispersion, bounds, gen)


def _calibrate_phases(phases, meas, method, distribution, free, fixed, values, initial, assumed, want_profile,
                      fit_args, n_starts, max_rel_se, unidentified, dispersion, bounds, gen) -> CalibrationResult:
    """The phases of :func:`calibrate` after its checks, each shown on ``phases``."""
    with phases.phase("search"):
        problem, theta = run_search(meas, method, distribution, free, values, assumed=assumed, **fit_args)
    profile = sigma_note = None
    if assumed and TABLE_SIGMA > 0 and rejected(problem, theta):
        # The assumed mismatch changes the shape of the mean curve where photons are many (its
        # bright tail no longer falls as fast), and the data reject it: fit without mismatch as
        # well and keep that when the data clearly prefer it (twice the log-likelihood ratio above 4).
        phases.add(1 + want_profile)
        with phases.phase("search without mismatch"):
            problem0, theta0 = run_search(meas, method, distribution, free, dict(values, eps_sigma=0.0), assumed=True,
                                    **fit_args)
        profile0 = None
        if want_profile:
            with phases.phase("profile of photons_per_lux (without mismatch)"):
                theta0, profile0 = profile_likelihood(problem0, theta0, "photons_per_lux")
        ll_a, ll_0 = comparable_loglik(problem, theta), comparable_loglik(problem0, theta0)
        if 2.0 * (ll_0 - ll_a) > 4.0:
            problem, theta, profile = problem0, theta0, profile0
        sigma_note = (f"the fit with the assumed {TABLE_SIGMA:g} is rejected; of it and 0 the data prefer "
                      f"{problem.values['eps_sigma']:g} (twice the log-likelihood ratio {2.0 * (ll_0 - ll_a):+.3g} "
                      f"for 0; 0 is kept when above 4)")
    if want_profile:
        with phases.phase("profile of photons_per_lux"):
            if profile is None:
                theta, profile = profile_likelihood(problem, theta, "photons_per_lux")
    with phases.phase("uncertainties and goodness of fit"):
        result = finish(problem, theta, max_rel_se, profile=profile, sigma_note=sigma_note)
    if unidentified == "fix":
        flagged = [n for n in result.free if result.status[n] == "not identified"]
        if flagged:
            fit_vals = result.params.to_dict()
            new_fixed = dict(fixed)
            for n in flagged:
                new_fixed[n] = fixed.get(n, getattr(initial, n) if initial is not None else fit_vals[n])
            rest = [n for n in free if n not in flagged]
            if rest:
                init2 = result.params.replace(**{n: new_fixed[n] for n in flagged})
                phases.add(1)
                with phases.phase(f"refit without {', '.join(flagged)} (not identified)"):
                    result2 = calibrate(meas, method=method, distribution=distribution, free=rest, fixed=new_fixed,
                                        initial=init2, n_starts=1, n_seeds=max(n_starts, 1), rng=gen,
                                        unidentified="report", max_rel_se=max_rel_se, dispersion=dispersion,
                                        bounds=bounds, progress=False)
                for n in flagged:
                    result2.status[n] = "fixed (not identified)"
                result2.identifiability = result.identifiability + [
                    f"fixed (not identified): {', '.join(flagged)}; the other uncertainties are conditional on "
                    f"these values"] + [t for t in result2.identifiability if t not in result.identifiability]
                return result2
    return result
