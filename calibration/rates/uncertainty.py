"""Uncertainty and quality of a fit: expected information and sandwich by central differences,
the profile of photons_per_lux, identifiability findings, goodness of fit and the verdict
(accepted/rejected), assembled into a :class:`~evnoise.calibration.rates.result.CalibrationResult`. Internal.
"""

from __future__ import annotations

import math

import numpy as np

from .likelihood import Problem
from .result import CalibrationResult
from .spec import (
    AT_BOUND_OK,
    DARK_LUX,
    FIT_NAMES,
    FLOORS,
    NEVER,
    PROFILE_ROUGH,
    REJECT_P,
    REJECT_RMS,
    UNMODELLED,
    ZERO_AT_BOUND,
)


def steps(problem: Problem, base: float = 1e-3) -> np.ndarray:
    """Central-difference steps in log space (larger for step-like parameters without mismatch)."""
    coarse = problem.values.get("eps_sigma", 0.0) == 0.0 and "eps_sigma" not in problem.free
    h = np.full(len(problem.free), base)
    if coarse:
        for i, n in enumerate(problem.free):
            if n in ("eps_pos", "eps_neg", "bias_pr"):
                h[i] = max(base, 0.02)
    return h


def _shifted(theta, i, d):
    t = np.array(theta, dtype=np.float64)
    t[i] += d
    return t


def information(problem: Problem, theta, h, *, want_meat: bool = True, central: bool = True):
    """``(info, meat, extras)`` in log space: expected information and the robust meat.

    ``extras["score"]`` is the gradient of the log-likelihood (for Fisher scoring).
    """
    p = len(theta)
    m = problem.meas
    if m.kind == "flat-field":
        # per (k, j): log P(c) for c in the support, differentiated by central differences
        base = problem.stats(theta)
        ranges = {}
        for (k, j), (vals, _) in problem.hist.items():
            trials = base.trial_rate_hz * m.duration_s[j]
            hi = int(max(vals[-1], min(trials, 10.0 * base.mean_rate()[k, j] * m.duration_s[j] + 50.0)))
            ranges[k, j] = np.arange(hi + 1, dtype=np.float64)
        lp0 = {kj: problem.hist_tables(base, *kj, c) for kj, c in ranges.items()}
        deriv = {kj: np.zeros((c.size, p)) for kj, c in ranges.items()}
        for i in range(p):
            sp = problem.stats(_shifted(theta, i, h[i]))
            tables_p = {kj: problem.hist_tables(sp, *kj, c) for kj, c in ranges.items()}
            if central:
                sm = problem.stats(_shifted(theta, i, -h[i]))
            for kj, c in ranges.items():
                tm = problem.hist_tables(sm, *kj, c) if central else lp0[kj]
                with np.errstate(invalid="ignore"):
                    d = (tables_p[kj] - tm) / ((2 if central else 1) * h[i])
                deriv[kj][:, i] = np.where(np.isfinite(d), d, 0.0)
        problem.stats(theta)
        info = np.zeros((p, p))
        score = np.zeros(p)
        for (k, j) in ranges:
            prob = np.exp(lp0[k, j])
            d = deriv[k, j]
            info += m.n_pixels[j] * (d * prob[:, None]).T @ d
            vals, mult = problem.hist[k, j]
            score += mult @ d[vals.astype(np.int64)]
        if not want_meat:
            return info, None, {"deriv": deriv, "ranges": ranges, "score": score}
        # meat: per-pixel scores summed over levels and polarities, clustered by pixel id
        ids_all = np.concatenate(m.pixel_ids)
        uniq, inv_all = np.unique(ids_all, return_inverse=True)
        scores = np.zeros((uniq.size, p))
        start = 0
        for j, counts in enumerate(m.pixel_counts):
            n = counts.shape[1]
            inv = inv_all[start:start + n]
            start += n
            for k in range(2):
                s = deriv[k, j][counts[k]]
                np.add.at(scores, inv, s)
        g = uniq.size
        meat = scores.T @ scores * (g / max(g - 1, 1))
        return info, meat, {"deriv": deriv, "ranges": ranges, "score": score}
    # tables: Jacobians of the model means (and shapes) by central differences
    base = problem.stats(theta)
    mu0 = problem.model_counts(base)
    jac_mu = np.zeros((*mu0.shape, p))
    jac_e = None
    if problem.use_shape:
        e0 = problem.shape_residuals(base)
        jac_e = np.zeros((*e0.shape, p))
    for i in range(p):
        sp = problem.stats(_shifted(theta, i, h[i]))
        mup = problem.model_counts(sp)
        ep = problem.shape_residuals(sp) if jac_e is not None else None
        if central:
            sm = problem.stats(_shifted(theta, i, -h[i]))
            jac_mu[..., i] = (mup - problem.model_counts(sm)) / (2 * h[i])
            if jac_e is not None:
                jac_e[..., i] = (ep - problem.shape_residuals(sm)) / (2 * h[i])
        else:
            jac_mu[..., i] = (mup - mu0) / h[i]
            if jac_e is not None:
                jac_e[..., i] = (ep - e0) / h[i]
    problem.stats(theta)
    var = mu0.copy()
    if problem.nb_total_shape is not None:
        R = problem.nb_total_shape
        var = np.where(np.isfinite(R), mu0 + mu0**2 / np.where(np.isfinite(R), R, 1.0), mu0)
    jm = jac_mu.reshape(-1, p)
    if problem.quasi_counts:  # normal in log rate: d log mu = d mu / mu
        used = (problem.y > 0).ravel()
        with np.errstate(invalid="ignore", over="ignore"):
            jl = jm / np.maximum(mu0.ravel(), 1e-300)[:, None]
        jl = np.where(used[:, None] & np.isfinite(jl), jl, 0.0)
        info = problem.weights["counts"] * jl.T @ jl
        res = problem.log_residuals(mu0).ravel()
        score = problem.weights["counts"] * jl.T @ np.where(np.isfinite(res), res, 0.0)
    else:
        w = problem.weights["counts"] / np.maximum(var.ravel(), 1e-300)
        info = (jm * w[:, None]).T @ jm
        score = jm.T @ (w * (problem.y - mu0).ravel())
    if jac_e is not None:
        je = jac_e.reshape(-1, p)
        info += problem.weights["shape"] * je.T @ je
        score -= problem.weights["shape"] * je.T @ e0.ravel()
    return info, info.copy(), {"jac_mu": jac_mu, "jac_e": jac_e, "score": score}


def covariance(info, meat):
    """Sandwich ``info^-1 meat info^-1`` by a scaled pseudo-inverse (rank-deficient safe)."""
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    scaled = info / np.outer(d, d)
    w, v = np.linalg.eigh(scaled)
    tol = max(w.max(), 0.0) * 1e-12
    inv_w = np.where(w > tol, 1.0 / np.where(w > tol, w, 1.0), 0.0)
    pinv = (v * inv_w) @ v.T / np.outer(d, d)
    cov = pinv @ meat @ pinv
    singular = np.where(w <= tol)[0]
    null_dirs = [v[:, i] / d for i in singular]
    return 0.5 * (cov + cov.T), null_dirs


def is_step_like(problem: Problem) -> bool:
    """Whether the likelihood is a step function of the thresholds (exact form, no mismatch)."""
    return problem.method == "poisson" and problem.values.get("eps_sigma", 0.0) == 0.0 \
        and "eps_sigma" not in problem.free


def rejected(problem: Problem, theta) -> bool:
    """Whether the goodness of fit at ``theta`` rejects the model (see :func:`_verdict`)."""
    gof, _ = _goodness(problem, theta, {"ranges": None}, len(problem.free))
    return _verdict(problem, gof)[0] == "rejected"


def finish(problem: Problem, theta, max_rel_se, *, profile=None, sigma_note=None) -> CalibrationResult:
    meas = problem.meas
    params = problem.params(theta)
    free = list(problem.free)
    p = len(free)
    status = {n: ("not identified" if n in NEVER else "fixed") for n in FIT_NAMES}
    # floors held at 0, not fitted: without a dark level nothing in the data separates them from the photon noise
    held_floors = ([n for n in FLOORS if n not in problem.free and problem.values[n] == 0.0]
                   if float(meas.lux.min()) > DARK_LUX else [])
    for n in held_floors:
        status[n] = "not identified (no dark level; fit with --fit)"
    at_bound = []  # indices held at a bound
    bound_side = {}  # name -> "lower" | "upper"
    for i, n in enumerate(free):
        status[n] = "fitted"
        if theta[i] <= problem.lo[i] + 1e-3:
            bound_side[n] = "lower"
        elif theta[i] >= problem.hi[i] - 1e-3:
            bound_side[n] = "upper"
        if n in AT_BOUND_OK and bound_side.get(n) == "lower":
            status[n] = "at lower bound"
            at_bound.append(i)
        elif n in bound_side:
            status[n] = "not identified"
            at_bound.append(i)
    # a profile that falls beyond its tolerance within one step on both sides is sharper than its
    # grid resolves: the local information is the better uncertainty then
    sharp = profile is not None and _profile_is_sharp(problem, theta, profile)
    i_prof = free.index(profile["name"]) if profile is not None and not sharp else None
    held = sorted(set(at_bound) | ({i_prof} if i_prof is not None else set()))
    inner = [i for i in range(p) if i not in held]
    notes = []
    h = steps(problem)
    info, meat, extras = information(problem, theta, h)
    cov = np.full((p, p), np.nan)
    if inner:
        ix = np.ix_(inner, inner)
        c_in, null_dirs = covariance(info[ix], meat[ix])
        # over every free parameter (``inner`` changes below when a profile moves parameters)
        null_dirs = [np.zeros(p) + np.bincount(inner, weights=d, minlength=p) for d in null_dirs]
        cov[ix] = c_in
        # checked step: redo with half the steps; disagreement means a step-like likelihood
        info2, meat2, _ = information(problem, theta, h / 2)
        c2, _ = covariance(info2[ix], meat2[ix])
        se1 = np.sqrt(np.maximum(np.diag(c_in), 0))
        se2 = np.sqrt(np.maximum(np.diag(c2), 0))
        for a, i in enumerate(inner):
            if se1[a] > 0 and np.isfinite(se1[a]) and abs(se2[a] / se1[a] - 1) > 0.25:
                notes.append(f"the uncertainty of {free[i]} depends on the differencing step ({se1[a]:.3g} vs "
                             f"{se2[a]:.3g} in log): the likelihood is step-like there (no threshold mismatch); "
                             f"treat it as approximate")
    else:
        null_dirs = []
    ident = []
    moving = []  # parameters that move with an unbounded profile
    profile_range = {}
    if i_prof is not None:
        text, cov, moving, closed, profile_range = _profile_uncertainty(problem, theta, profile, cov, inner,
                                                                        max_rel_se)
        ident.append(text)
        if closed and i_prof not in at_bound:
            inner = sorted(inner + [i_prof])
        else:
            status[free[i_prof]] = "not identified"
        for n in moving:
            status[n] = "not identified"
        inner = [i for i in inner if free[i] not in moving]
    rel = {n: math.nan for n in FIT_NAMES}
    se = {n: math.nan for n in FIT_NAMES}
    for i, n in enumerate(free):
        if i in inner:
            rel[n] = float(math.sqrt(max(cov[i, i], 0.0)))
            se[n] = rel[n] * getattr(params, n)
    if sharp:
        n = profile["name"]
        profile_range = {"name": n, "best": getattr(params, n), "low": getattr(params, n) * math.exp(-rel[n]),
                         "high": getattr(params, n) * math.exp(rel[n]), "closed_low": True, "closed_high": True,
                         "loglik_tolerance": 0.5}
    flagged = [free[i] for i in inner if not (rel[free[i]] <= max_rel_se)]
    for n in flagged:
        status[n] = "not identified"
    with np.errstate(invalid="ignore", divide="ignore"):
        dd = np.sqrt(np.diag(cov))
        corr = cov / np.outer(dd, dd)
    ident += _identifiability_text(free, inner, cov, corr, flagged, null_dirs, max_rel_se)
    if problem.assumed_sigma:
        status["eps_sigma"] = "fixed (assumed)"
        ident.append(f"eps_sigma is not determined by mean rates; it is fixed at an assumed "
                     f"{problem.values['eps_sigma']:g}" + (f" ({sigma_note})" if sigma_note else "")
                     + " (give per-pixel counts or measured NB shapes to fit it, or --fix eps_sigma=...)")
    for i in at_bound:
        n = free[i]
        v = getattr(params, n)
        if status[n] == "at lower bound" and n in ZERO_AT_BOUND:
            ident.append(f"{n} is at its lower bound ({v:.3g}, which stands for 0): the data are consistent with "
                         f"no such term; it is reported as 0")
        elif status[n] == "at lower bound":
            ident.append(f"{n} is at its lower bound ({v:.3g}): the data are consistent with 0; it is held there "
                         f"for the other uncertainties")
        elif n == "photons_per_lux" and bound_side.get(n) == "upper":
            ident.append(f"photons_per_lux ran into its upper bound ({v:.3g}, {v * float(meas.lux.max()):.3g} "
                         f"photons per trial at the brightest level): the rates look like the many-photon (Gaussian) "
                         f"limit, where only photons_per_lux / bias_pr and eps scaled by sqrt(photons_per_lux) are "
                         f"determined; it is not identified, fix it if it is known (--fix photons_per_lux=...)")
        else:
            ident.append(f"{n} ran into its {bound_side[n]} bound ({v:.3g}) and is not identified by these data; "
                         f"it is held there for the other uncertainties")
    gof, dispersion = _goodness(problem, theta, extras, p)
    fit_status, why = _verdict(problem, gof)
    warnings = []
    if fit_status == "rejected":
        warnings.append(f"fit rejected: {why}; the model with these parameters does not describe the data (check "
                        f"the measurements, fixed values and bounds)")
        if held_floors:  # the commonest cause with real sensors: a background floor the default fit leaves at 0
            warnings.append(f"the background floors were held at 0 (the table has no dark level): if the sensor has "
                            f"background activity, fit them too (--fit ... {' '.join(held_floors)}, or free=[..., "
                            f"{', '.join(repr(n) for n in held_floors)}])")
        for n in free:
            if status[n] == "fitted":
                status[n] = "fitted (fit rejected)"
    for n, side in bound_side.items():
        v = getattr(params, n)
        lo, hi = problem.bounds[n]
        if n in ZERO_AT_BOUND and status[n] == "at lower bound":
            continue  # no such term in the data: an ordinary result (a status and a finding, not a warning)
        extra = " (consistent with 0)" if status[n] == "at lower bound" else " (not identified)"
        warnings.append(f"{n} is on its {side} bound {v:.4g} (bounds {lo:.3g} .. {hi:.3g}){extra}")
    for n in FLOORS:
        if n in free and status[n] == "not identified" and n not in bound_side:
            warnings.append(f"{n} (background floor) is not identified by these data (relative error "
                            f"{rel[n]:.2g}): measure a level in the dark or where the photon noise is negligible, "
                            f"or fix it (--fix {n}=...)")
    for n in UNMODELLED:
        if getattr(params, n) > 0:
            ident.append(f"{n} = {getattr(params, n):g} is kept as given but not modelled by the likelihood (it takes "
                         f"background arrivals as Poisson): the fitted background is the Poisson equivalent")
    for n in NEVER:
        if getattr(params, n) > 0:
            ident.append(f"{n} = {getattr(params, n):g} is kept as given: static measurements do not identify it "
                         f"(it only acts on changing scenes)")
    # terms on the lower bound that stands for 0 are reported (and written) as 0
    zero = {n: 0.0 for n in ZERO_AT_BOUND if status.get(n) == "at lower bound"}
    if zero:
        params = params.replace(**zero)
    return CalibrationResult(params=params, method=problem.method, distribution=problem.distribution,
                             free=tuple(free), status=status, std_error=se, rel_error=rel, cov_log=cov,
                             correlation=corr, identifiability=ident, gof=gof, dispersion=dispersion,
                             measurements=meas, loglik=float(problem.loglik(theta)), notes=notes,
                             fit_status=fit_status, warnings=warnings, at_bound=dict(bound_side),
                             bounds={n: tuple(problem.bounds[n]) for n in free}, profile=profile_range)


def _verdict(problem: Problem, gof) -> tuple[str, str]:
    """``("accepted" | "rejected", reason)`` from the goodness of fit."""
    if problem.meas.kind == "flat-field":
        pv, z = gof.get("histogram_p_value", math.nan), gof.get("mean_rate_max_abs_z", math.nan)
        if not pv >= REJECT_P:
            return "rejected", (f"the count histograms do not match (G/dof = {gof['histogram_G_per_dof']:.3g}, "
                                f"p = {pv:.2g} < {REJECT_P:g})")
        if not z <= 6.0:
            return "rejected", f"a level's mean count is {z:.3g} standard errors off"
        return "accepted", ""
    if problem.quasi_counts:
        rms = gof.get("rate_rms_log_residual", math.nan)
        if not rms <= REJECT_RMS:
            return "rejected", f"rms relative residual of the rates {rms:.3g} > {REJECT_RMS:g}"
        return "accepted", ""
    pv = gof.get("p_value", math.nan)
    if not pv >= REJECT_P:
        return "rejected", (f"Pearson chi2/dof = {gof['pearson_chi2_per_dof']:.3g} on {gof['dof']} dof "
                            f"(p = {pv:.2g} < {REJECT_P:g})")
    return "accepted", ""


def _profile_levels(problem: Problem, theta, profile):
    """``(t, dev, k0, level)``: profile points, twice the log-likelihood drop, index of the best, tolerance."""
    i = problem.free.index(profile["name"])
    pts = profile["points"]
    t = np.array([q[0] for q in pts])
    ll = np.array([q[1] for q in pts])
    dev = 2.0 * (max(float(ll.max()), float(problem.loglik(theta))) - ll)
    k0 = int(np.argmin(np.abs(t - theta[i])))
    level = 1.0 + (PROFILE_ROUGH if is_step_like(problem) else 0.0)
    return t, dev, k0, level


def _profile_is_sharp(problem: Problem, theta, profile) -> bool:
    t, dev, k0, level = _profile_levels(problem, theta, profile)
    return 0 < k0 < t.size - 1 and dev[k0 - 1] > level and dev[k0 + 1] > level


def _profile_uncertainty(problem: Problem, theta, profile, cov, inner, max_rel_se):
    """Uncertainty of the profiled parameter and the others' movement along its profile.

    Returns ``(finding, cov, moving, closed, range)``: ``cov`` with the profiled parameter's row (and
    the others' path term) filled in when its interval is closed; ``moving``: parameters that
    change by more than ``max_rel_se`` (in log) while it runs over an open interval.
    """
    name = profile["name"]
    free = problem.free
    i = free.index(name)
    th = np.array([q[2] for q in profile["points"]])
    t, dev, k0, level = _profile_levels(problem, theta, profile)
    rough = level - 1.0

    def crossing(step):
        k = k0
        while 0 <= k + step < t.size:
            if dev[k + step] > level:
                a, b = dev[k], dev[k + step]
                w = (level - a) / (b - a) if b != a else 0.0
                return t[k] + w * (t[k + step] - t[k]), True
            k += step
        return t[k], False

    t_lo, closed_lo = crossing(-1)
    t_hi, closed_hi = crossing(+1)
    closed = closed_lo and closed_hi
    info = {"name": name, "best": math.exp(theta[i]), "low": math.exp(t_lo), "high": math.exp(t_hi),
            "closed_low": closed_lo, "closed_high": closed_hi, "loglik_tolerance": (1.0 + rough) / 2.0}
    cov = cov.copy()
    v = math.exp(theta[i])
    within = dev <= (4.0 + rough if closed else level)
    others = [j for j in inner if j != i]
    moving = []
    if closed:
        var_t = ((t_hi - t_lo) / 2.0) ** 2
        g = np.zeros(len(free))
        g[i] = 1.0
        if np.count_nonzero(within) >= 2:
            for j in others:
                g[j] = np.polyfit(t[within], th[within, j], 1)[0]
        idx = others + [i]
        base = np.where(np.isfinite(cov), cov, 0.0)
        full = base + np.outer(g, g) * var_t
        cov[np.ix_(idx, idx)] = full[np.ix_(idx, idx)]
        text = (f"{name}: profile likelihood within {level / 2:g} of its maximum from {math.exp(t_lo):.4g} to "
                f"{math.exp(t_hi):.4g} (best {v:.4g}); the other uncertainties include their movement along it")
        return text, cov, moving, True, info
    # open interval: how far the others move over it
    parts = []
    for j in others:
        spread = float(th[within, j].max() - th[within, j].min()) if within.any() else 0.0
        if spread / 2.0 > max_rel_se:
            moving.append(free[j])
            slope = np.polyfit(t[within], th[within, j], 1)[0] if np.count_nonzero(within) >= 2 else math.nan
            parts.append(f"{free[j]} ~ {name}^{slope:+.2f}")
        elif spread > 0:
            cov[j, j] = cov[j, j] + (spread / 2.0) ** 2
    lo_txt = f"{math.exp(t_lo):.4g}" + (" (its lower bound)" if not closed_lo and profile["lo_bound"] else
                                        "" if closed_lo else " (end of the profile)")
    hi_txt = f"{math.exp(t_hi):.4g}" + (" (its upper bound)" if not closed_hi and profile["hi_bound"] else
                                        "" if closed_hi else " (end of the profile)")
    text = (f"{name} is not identified: the profile likelihood stays within {level / 2:g} of its maximum from "
            f"{lo_txt} to {hi_txt} (best {v:.4g})")
    if parts:
        text += f"; {', '.join(moving)} move with it ({', '.join(parts)}) and are not identified either"
    return text, cov, moving, False, info


def _identifiability_text(free, inner, cov, corr, flagged, null_dirs, max_rel_se):
    out = []
    names = [free[i] for i in inner]
    for a in range(len(inner)):
        for b in range(a + 1, len(inner)):
            r = corr[inner[a], inner[b]]
            if np.isfinite(r) and abs(r) > 0.95:
                out.append(f"{names[a]} and {names[b]} are strongly correlated (r = {r:+.3f})")
    for n in flagged:
        i = free.index(n)
        best = None
        for j in inner:
            if j == i:
                continue
            for sign in (+1, -1):
                v = cov[i, i] + cov[j, j] + 2 * sign * cov[i, j]
                if np.isfinite(v) and (best is None or v < best[0]):
                    best = (v, j, sign)
        text = f"{n} is not identified (relative error {math.sqrt(max(cov[i, i], 0)):.2g} > {max_rel_se:g})"
        if best is not None and best[0] < max_rel_se**2:
            op = "*" if best[2] > 0 else "/"
            text += (f"; only {n} {op} {free[best[1]]} is constrained (relative error "
                     f"{math.sqrt(max(best[0], 0)):.2g})")
        out.append(text)
    if len(inner) > 1:
        sub = cov[np.ix_(inner, inner)]
        w, v = np.linalg.eigh(sub)
        for k in range(len(w) - 1, -1, -1):
            if not (np.isfinite(w[k]) and w[k] > max_rel_se**2):
                break
            comp = v[:, k] / np.max(np.abs(v[:, k]))
            terms = [f"{names[a]}^{comp[a]:+.2f}" for a in np.argsort(-np.abs(comp)) if abs(comp[a]) > 0.2]
            out.append(f"poorly constrained direction (relative sd {math.sqrt(w[k]):.2g}): "
                       f"{' * '.join(terms)} can change together with little effect on the fit")
    for dvec in null_dirs:
        comp = dvec / np.max(np.abs(dvec))
        labels = free if len(comp) == len(free) else names  # over every free parameter or the inner ones
        terms = [f"{labels[a]}^{comp[a]:+.2f}" for a in np.argsort(-np.abs(comp)) if abs(comp[a]) > 0.2]
        out.append(f"unconstrained direction (no information): {' * '.join(terms)}")
    return out


def _goodness(problem: Problem, theta, extras, n_free):
    from scipy.stats import chi2

    meas = problem.meas
    stats = problem.stats(theta)
    gof = {}
    rate_model = stats.mean_rate()
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_res = rate_model / meas.rate_hz - 1.0
    ok = np.isfinite(rel_res)
    gof["rate_rms_relative_residual"] = float(np.sqrt(np.mean(rel_res[ok] ** 2))) if ok.any() else math.nan
    gof["rate_max_relative_residual"] = float(np.max(np.abs(rel_res[ok]))) if ok.any() else math.nan
    disp = {"r_measured": meas.nb_shape, "r_model": None, "summary": ""}
    if stats.regularity > 0:  # counts of a timer are not negative binomial: no model shape to show
        disp["summary"] = (f"no model over-dispersion: the background timer is regular (leak_regularity or "
                           f"hot_pixel_regularity {stats.regularity:.6g}), which the mean rates allow but the NB shape "
                           "does not")
    elif meas.duration_s is not None and (meas.nb_shape is not None or stats.log_m1.size):
        inv = stats.inverse_shape(meas.duration_s)
        with np.errstate(divide="ignore"):
            r_model = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), np.inf)
        disp["r_model"] = r_model
    if meas.kind == "flat-field":
        g_total, dof_total = 0.0, 0
        z_means = np.zeros((2, meas.n_levels))
        for (k, j), (vals, mult) in problem.hist.items():
            c = extras["ranges"][k, j]
            prob = np.exp(problem.hist_tables(stats, k, j, c))
            n = meas.n_pixels[j]
            obs = np.zeros(c.size)
            inside = vals <= c[-1]
            obs[vals[inside].astype(int)] = mult[inside]
            exp_ = n * prob
            # pool bins from the top so that each has expected >= 5
            o_b, e_b = [], []
            acc_o = acc_e = 0.0
            for i in range(c.size - 1, -1, -1):
                acc_o += obs[i]
                acc_e += exp_[i]
                if acc_e >= 5.0:
                    o_b.append(acc_o)
                    e_b.append(acc_e)
                    acc_o = acc_e = 0.0
            if o_b:
                o_b[-1] += acc_o
                e_b[-1] += acc_e
            o_b, e_b = np.array(o_b), np.array(e_b)
            e_b *= o_b.sum() / max(e_b.sum(), 1e-300)
            with np.errstate(divide="ignore", invalid="ignore"):
                g = 2.0 * np.sum(np.where(o_b > 0, o_b * np.log(o_b / e_b), 0.0))
            g_total += float(g)
            dof_total += max(o_b.size - 1, 0)
            counts = meas.pixel_counts[j][k]
            sd = counts.std(ddof=1) / math.sqrt(counts.size) if counts.size > 1 else math.inf
            z_means[k, j] = (counts.mean() - rate_model[k, j] * meas.duration_s[j]) / sd if sd > 0 else 0.0
        dof = max(dof_total - n_free, 1)
        gof["histogram_G"] = g_total
        gof["histogram_dof"] = dof
        gof["histogram_G_per_dof"] = g_total / dof
        gof["histogram_p_value"] = float(chi2.sf(g_total, dof))
        gof["mean_rate_max_abs_z"] = float(np.max(np.abs(z_means)))
        gof["note"] = ("G-test of each level's count histogram against the fitted mixture (levels share pixels, "
                       "so the p-value is approximate)")
    else:
        mu = problem.model_counts(stats)
        y = problem.y
        with np.errstate(divide="ignore", invalid="ignore"):
            dev = 2.0 * np.sum(np.where(y > 0, y * np.log(np.where(y > 0, y, 1.0) / mu), 0.0) - (y - mu))
            pearson = float(np.sum((y - mu) ** 2 / mu))
        n_data = y.size + (problem.k_obs.size if problem.fit_shape else 0)
        dof = max(n_data - n_free, 1)
        if problem.quasi_counts:
            gof["counts"] = ("unknown (no n_pixels/duration_s): relative (log) residuals, uncertainties scaled by "
                             "their scatter")
            gof["rate_rms_log_residual"] = float(np.sqrt(np.mean(problem.log_residuals(mu)[y > 0] ** 2)))
        else:
            gof["poisson_deviance"] = float(dev)
            gof["pearson_chi2"] = pearson
            gof["dof"] = dof
            gof["pearson_chi2_per_dof"] = pearson / dof
            gof["p_value"] = float(chi2.sf(pearson, dof))
        if problem.fit_shape:
            e = problem.shape_residuals(stats)
            gof["shape_residual_rms"] = float(np.sqrt(np.mean(e**2)))
        gof["dispersion_weights"] = {k: float(v) for k, v in problem.weights.items()}
    if disp["r_model"] is not None and meas.nb_shape is not None:
        r_m, r_o = disp["r_model"], meas.nb_shape
        both = np.isfinite(r_m) & np.isfinite(r_o) & (r_o > 0)
        finite_o = r_o[np.isfinite(r_o)]
        if not np.any(np.isfinite(r_m)) and finite_o.size:
            disp["summary"] = (f"the fit has no threshold mismatch (eps_sigma = 0), so its counts are not "
                               f"over-dispersed; measured r {finite_o.min():.3g} .. {finite_o.max():.3g}")
        if both.any():
            lr = np.log(r_m[both] / r_o[both])
            disp["log_ratio_rms"] = float(np.sqrt(np.mean(lr**2)))
            disp["log_ratio_max"] = float(np.max(np.abs(lr)))
            disp["summary"] = (f"model/measured r: median {np.exp(np.median(lr)):.3g}, rms |log ratio| "
                               f"{disp['log_ratio_rms']:.3g}, worst {np.exp(lr[np.argmax(np.abs(lr))]):.3g} "
                               f"(measured r {np.nanmin(r_o[both]):.3g} .. {np.nanmax(r_o[both]):.3g})")
    return gof, disp
