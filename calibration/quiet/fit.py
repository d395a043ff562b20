"""Calibrate the background of your own camera from a recording of a still scene.

A window of a recording in which nothing moves holds only noise: per pixel, an ON and an OFF
count. With the illuminance unknown the photon shot noise and the background (leak) cannot be
told apart, so what the data identify is each polarity's *total* rate at the recording's light,
its spread across pixels and the hot pixels:

- pixel ``i`` has rates ``(s_i r_on + h_i q, s_i r_off + h_i (1 - q))`` events/s, where ``s_i`` is a
  log-normal factor of mean 1 (``log`` sd ``sigma``, the preset's ``leak_sigma``) and ``h_i`` is 0
  for ordinary pixels and, for a fraction ``f`` of them (hot pixels), log-normal with mean
  ``r_hot`` and ``log`` sd ``sigma_hot`` (a hot pixel's own ``s`` is taken as 1: its ordinary
  rate is negligible beside ``h``);
- the counts of a pixel over windows of ``T_w`` seconds are independent Poisson variables (the
  rates are far below the trial rate, so the binomial trial structure and the refractory
  period change nothing measurable); the same pixel keeps its ``s_i``, ``h_i`` in every window of
  one recording.

The likelihood integrates each pixel's counts over ``s`` (and ``h``) on a fixed grid of the
standard normal (``GRID`` points over +-7 sd) and is maximised over ``(log r_on, log r_off, log sigma, logit f,
log r_hot, log sigma_hot, logit q)``. The spread and the hot pixels are kept only when a
likelihood-ratio test says the data carry them (:data:`LR_P`; each term against the full model, then the
terms dropped together, ``dropped_together``: while that rejects, the dropped term with the smallest p is
kept); otherwise they are reported as *not identified* and set to 0. Standard errors come from the observed
information (numerical Hessian in the fitted coordinates, delta method to natural units). A parameter whose
maximum lies on a bound of its range (the hot fraction at :data:`HOT_MAX_FRACTION`, a hot rate at
:data:`HOT_MIN_RATIO` times the ordinary one, a share or a regularity at 0 or 1, a spread below
:data:`SIGMA_FLOOR`) is labelled *at upper / lower bound* and has no standard error (a regularity at
1 keeps its one-sided profile-likelihood error); where such a coordinate makes the information
singular it is held at the bound and the others' errors are conditional on it. A fitted parameter
left without a standard error is labelled *fitted, no standard error*, never plain *fitted*.

Goodness of fit, per window and polarity: the histogram of per-pixel counts against the model's
(the same mixture), bins merged from the top until every expected count is at least 5; Pearson's
chi-square with ``bins - 1`` degrees of freedom minus the fitted parameters (at least 1). The fit as a
whole is *rejected* (``QuietFit.fit_status``, with its reasons in ``rejections``) when a histogram's
p-value is below :data:`GOODNESS_P` or a window fails one of the checks that it is pure stationary
noise (:mod:`.checks`: no preset reproduces such a window) or a timing test (``QuietFit.timing``,
:func:`.goodness.timing_tests`, for windows whose checks gathered their events): consecutive same-pixel
events opposite in polarity against the memoryless model's share (a normal test), and the same-pixel
inter-event intervals against the fitted model's distribution (a KS test), each at :data:`GOODNESS_P`;
windows with fewer than 100 intervals report "not enough intervals"; otherwise *accepted*. So a window
whose counts the model reproduces but whose timing it does not is not accepted.

Timing (``fit_quiet(timing="auto")``, opt-in, see the parameter; windows read with their events by
:func:`~evnoise.calibration.quiet_window`): the likelihood is that of each pixel's event *times* in the window
(a stationary renewal process with the simulator's gap law, :mod:`.likelihood`; each pixel's integral over
the spread on nodes of its own, :mod:`.timing`), which holds the counts' likelihood and the intervals' too;
the periodic-timer explanation of under-dispersed counts is then tested against the intervals it implies (a
gap shorter than ``r / rate`` has likelihood 0). On the simulator's own data it finds the truth within its
standard errors and pins the regularity tens of times more tightly than the counts
(``tests/test_quiet_timing_selfconsistency.py``). ``hot_regularity="on"`` gives the hot pixels their own
regularity (the preset's ``hot_pixel_regularity``).

With ``lux`` given for the windows, the shot noise of a base preset at that illuminance is part
of the model (fixed, not fitted) and the fitted rates are its background on top; with two or more
illuminances the background's growth with lux joins the fit as ``leak_*_hz_per_lux`` would.

Layout (:mod:`evnoise.calibration.quiet`): the windows are in :mod:`.window`; this module holds
:func:`fit_quiet` (starts, model selection, standard errors), :class:`QuietFit` and the preset document; the
count distribution is in :mod:`.counts`, the likelihood in :mod:`.likelihood`, the goodness of fit and the
comparison of a preset with a recording in :mod:`.goodness`, the checks that a window is pure noise in
:mod:`.checks`, the figure in :mod:`.plot`.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from evnoise.errors import InputError, ParameterError

from .._progress import Phases
from .checks import check_verdict, failed_checks
from .goodness import goodness_of_fit, timing_tests
from .likelihood import (
    HOT_MAX_FRACTION,
    HOT_MIN_RATIO,
    Model,
    hessian,
    maximise,
    mixture_log_likelihood,
    timing_available,
    unpack,
    window_groups,
)
from .window import DOUBLET_US, oscillating_notes, same_exclusions

__all__ = ["fit_quiet", "QuietFit", "LR_P", "GOODNESS_P", "preset_toml"]

#: Likelihood-ratio p-value below which the spread / the hot pixels count as identified.
LR_P = 1e-3
#: Goodness-of-fit p-value (a window's ON or OFF count histogram) below which the fit is rejected.
GOODNESS_P = 1e-3
NAMES = ("rate_on_hz", "rate_off_hz", "regularity", "sigma", "hot_fraction", "hot_rate_hz", "hot_sigma",
         "hot_on_fraction", "hot_regularity")


# --------------------------------------------------------------------------------------
# the fit
# --------------------------------------------------------------------------------------
@dataclass
class QuietFit:
    """Result of :func:`fit_quiet`: values, standard errors, status and goodness of fit."""

    values: dict
    std_error: dict
    status: dict
    log_likelihood: float
    tests: dict
    goodness: list
    windows: list
    base: object = None
    notes: list = field(default_factory=list)
    #: ``"accepted"`` or ``"rejected"`` (module doc), and why it was rejected
    fit_status: str = "accepted"
    rejections: list = field(default_factory=list)
    #: timing tests of the windows with events (:func:`.goodness.interval_test`)
    timing: list = field(default_factory=list)
    #: parameters the fit was told to leave out (``hot_regularity`` with ``hot_regularity="off"``): not in the
    #: summary, the standard errors or the preset's ``[fit]`` tables (``values`` and ``status`` keep them)
    hidden: tuple = ()

    def to_params(self, base=None):
        """NoiseParams whose nominal rates at 0 lux (or the windows' lux) reproduce the fitted ones.

        ``base`` (NoiseParams or preset name) supplies the shot-noise part; the background floors are
        set so that ``expected_rate(lux)`` of a pixel with ``s = 1`` equals the fitted rates exactly.
        """
        import evnoise as ev

        base = ev.load_preset(base) if isinstance(base, str) else (base or self.base)
        if base is None:
            raise ParameterError("to_params needs a base preset for the shot-noise parameters")
        v = self.values
        # hot pixels with a regularity of their own run as hot_pixel_regularity (-1: tied to leak_regularity); one on
        # a bound of its range is written as the bound it stands for (0: Poisson, 1: periodic)
        own_hot = abs(v.get("hot_regularity", v["regularity"]) - v["regularity"]) > 1e-9
        hot_regularity = v.get("hot_regularity", v["regularity"])
        bound = self.status.get("hot_regularity", "")
        if bound.startswith(("at lower bound (0", "at upper bound (1")):
            hot_regularity = 0.0 if bound.startswith("at lower") else 1.0
        lux0 = min((w.lux for w in self.windows if w.lux is not None), default=0.0)
        floors = _floors_for(base, lux0, v["rate_on_hz"], v["rate_off_hz"], v.get("growth_on", 0.0),
                             v.get("growth_off", 0.0), v["regularity"])
        return base.replace(leak_on_hz=floors[0], leak_off_hz=floors[1],
                            leak_on_hz_per_lux=v.get("growth_on", 0.0), leak_off_hz_per_lux=v.get("growth_off", 0.0),
                            leak_sigma=v["sigma"], hot_pixel_fraction=v["hot_fraction"],
                            hot_pixel_rate_hz=v["hot_rate_hz"], hot_pixel_sigma=v["hot_sigma"],
                            hot_pixel_on_fraction=v["hot_on_fraction"], leak_regularity=v["regularity"],
                            hot_pixel_regularity=hot_regularity if own_hot else -1.0)

    def summary(self) -> str:
        lines = [f"quiet-scene calibration from {len(self.windows)} window(s), "
                 f"{sum(w.n_pixels for w in self.windows)} pixel-windows; log-likelihood "
                 f"{self.log_likelihood:.2f}",
                 f"  fit status: {self.fit_status.upper()}"]
        lines += [f"  rejected: {r}" for r in self.rejections]
        for name in self.shown():
            val, se, st = self.values[name], self.std_error.get(name), self.status[name]
            err = "" if se is None or not math.isfinite(se) else f" +- {se:.3g}"
            lines.append(f"  {name:16s} {val:.6g}{err}  ({st})")
        for name, t in self.tests.items():
            lines.append(f"  test {name}: twice the log-likelihood ratio {t['lr']:.3g}, p = {t['p_value']:.3g}")
        for g in self.goodness:
            if not math.isfinite(g["p_value"]):
                events = f"{g['events']} event{'' if g['events'] == 1 else 's'}"
                lines.append(f"  fit {g['window']} {g['polarity']}: not testable ({events}: counts 0..{g['max_count']} "
                             f"pool into one bin of expected count >= 5; a chi-square needs two)")
                continue
            lines.append(f"  fit {g['window']} {g['polarity']}: chi2 {g['chi2']:.2f} on {g['dof']} dof, "
                         f"p = {g['p_value']:.3g} ({g['bins']} bins over counts 0..{g['max_count']})")
        for t in self.timing:
            lines.append(f"  timing {t['window']} {t['test']}: {_timing_verdict(t)}; {t['detail']}")
        for w in self.windows:
            for c in w.checks:
                lines.append(f"  check {w.describe()} {c['check']}: {check_verdict(c)}; {c['detail']}")
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)

    def shown(self) -> tuple:
        """The parameters the summary and the preset's ``[fit]`` tables list (:data:`NAMES` less ``hidden``)."""
        return tuple(n for n in NAMES if n not in self.hidden)

    def to_toml_tables(self) -> dict:
        """``[fit]`` and ``[fit.goodness]`` content for a preset."""
        return {
            "method": "quiet-scene maximum likelihood (evnoise.calibration.quiet)",
            "log_likelihood": round(self.log_likelihood, 3),
            "fit_status": self.fit_status,
            "rejections": list(self.rejections),
            "notes": list(self.notes),
            "status": {k: v for k, v in self.status.items() if k not in self.hidden},
            "values": {k: float(v) for k, v in self.values.items() if k in self.shown()},
            "std_error": {k: float(v) for k, v in self.std_error.items() if v is not None and math.isfinite(v)},
            "tests": {k: {kk: float(vv) for kk, vv in t.items()} for k, t in self.tests.items()},
            "goodness": [{k: (float(v) if isinstance(v, (int, float, np.floating)) and not isinstance(v, bool)
                              else v) for k, v in g.items()} for g in self.goodness],
            "checks": [dict(window=w.describe(), **{k: v for k, v in c.items() if k != "same_pixel"})
                       for w in self.windows for c in w.checks],
            "timing": [{k: (float(v) if isinstance(v, (int, float, np.floating)) and not isinstance(v, bool)
                            else v) for k, v in t.items()} for t in self.timing],
        }

    def plot(self, path, *, seed: int = 0, params=None):
        """Real vs fitted-model count histograms (ON, OFF) and count maps, side by side."""
        from .plot import plot_quiet

        plot_quiet(self, path, seed=seed, params=params)


def _floors_for(base, lux, rate_on, rate_off, growth_on, growth_off, regularity=0.0):
    """Background floors so that the nominal pixel's rates at ``lux`` equal the fitted ones.

    One root finding per polarity, repeated until neither floor moves (the two polarities share the
    pixel's trials, so each floor changes the other polarity's rate a little).
    """
    from scipy.optimize import brentq

    import evnoise as ev

    lux_arr = np.array([float(lux)])
    target = (rate_on, rate_off)
    floors = [0.0, 0.0]

    def excess(x, k):
        fl = list(floors)
        fl[k] = x
        p = base.replace(leak_on_hz=fl[0], leak_off_hz=fl[1], leak_on_hz_per_lux=growth_on,
                         leak_off_hz_per_lux=growth_off, leak_regularity=regularity)
        return float(ev.expected_rate(lux_arr, p)[k, 0]) - target[k]

    for _ in range(20):
        before = list(floors)
        for k in range(2):
            if excess(0.0, k) >= 0:
                floors[k] = 0.0  # the photon noise alone reaches the rate
                continue
            hi = max(2.0 * target[k], 1e-12)
            while excess(hi, k) < 0 and hi < 1e9:
                hi *= 2
            floors[k] = brentq(excess, 0.0, hi, args=(k,), xtol=1e-15, rtol=1e-13)
        if all(abs(a - b) <= 1e-13 * max(abs(a), 1e-300) for a, b in zip(floors, before)):
            break
    return floors


def _shot_rates(windows, base):
    import evnoise as ev

    out = []
    for w in windows:
        if w.lux is None or base is None:
            out.append([0.0, 0.0])
        else:
            out.append(list(ev.expected_rate(np.array([w.lux]), base)[:, 0]))
    return np.array(out)


def _hot_guess(windows, rates):
    """``(fraction, rate)`` of pixels whose total count is far above a Poisson count at the mean rates."""
    from scipy.stats import poisson

    n_pix, n_hot, hot_events, hot_time = 0, 0, 0.0, 0.0
    for w in windows:
        total = w.pixel_counts().sum(axis=0)
        mu = float(np.sum(rates)) * w.duration_s
        cut = poisson.isf(1e-4, mu) + 1
        sel = total > cut
        n_pix += total.size
        n_hot += int(sel.sum())
        hot_events += float(total[sel].sum())
        hot_time += int(sel.sum()) * w.duration_s
    if n_hot == 0:
        return 1.0 / max(n_pix, 1), 10.0 * float(np.sum(rates)) + 1.0
    return n_hot / n_pix, hot_events / hot_time


def _profile_distance(nll, theta_hat, index: int, value: float, upward: bool = False) -> float:
    """How far a proportion (coordinate ``index`` of ``theta_hat``, the logit of ``value``) can move down (``upward``:
    up) before the profile of ``nll`` (the others re-fitted) rises by 1/2: a one-sided standard error."""
    from scipy.optimize import brentq, minimize

    base = nll(theta_hat)
    others = [k for k in range(theta_hat.size) if k != index]
    start = theta_hat.copy()

    def rise(r):
        def sub(z):
            t = start.copy()
            t[index] = _logit(r)
            t[others] = z
            val = nll(t)
            return val if math.isfinite(val) else 1e300

        best = minimize(sub, start[others], method="BFGS", options=dict(gtol=1e-3, maxiter=100))
        start[others] = best.x  # the next point starts from this one
        return best.fun - base - 0.5

    if upward:  # at the lower bound (0): how far up the data let it go
        ceiling = 1.0 - 1e-6
        lo, step = value, max(1e-3, value)
        while True:
            hi = min(value + step, ceiling)
            if rise(hi) >= 0.0:
                break
            if hi >= ceiling:
                return 1.0 - value  # flat up to 1: not constrained from above
            lo, step = hi, 2.0 * step
        try:
            return brentq(rise, lo, hi, xtol=1e-4) - value
        except ValueError:
            return hi - value
    floor = 1e-6
    hi = value
    step = max(1e-3, 1.0 - value)
    while True:
        lo = max(value - step, floor)
        if rise(lo) >= 0.0:
            break
        if lo <= floor:
            return value  # flat down to 0: not constrained from below
        hi, step = lo, 2.0 * step
    try:
        return value - brentq(rise, lo, hi, xtol=1e-4)
    except ValueError:  # the warm-started re-fits are not exactly repeatable: keep the bracket's outer end
        return value - lo


def _logit(x):
    x = min(max(x, 1e-9), 1 - 1e-9)
    return math.log(x / (1 - x))


def fit_model(fit: QuietFit, timing: bool = False):
    """``(model, groups)`` of a fit: the terms it kept (its status), with the timing likelihood or not, and its
    windows' groups. For windows at an unknown illuminance (no shot noise in the model), as quiet recordings are."""
    if any(w.lux is not None for w in fit.windows):
        raise ParameterError("fit_model: the windows have an illuminance; only windows without lux are supported")

    def kept(name):
        return not fit.status[name].startswith(("not identified", "fixed", "tied"))

    groups = window_groups(fit.windows)
    model = Model(kept("sigma"), kept("hot_fraction"), [np.zeros((len(g.windows), 2)) for g in groups], False,
                  [np.zeros(len(g.windows)) for g in groups], kept("regularity"), timing,
                  kept("hot_fraction") and kept("hot_regularity"))
    return model, groups


def event_time_log_likelihood(fit: QuietFit) -> float:
    """The log-likelihood of the windows' event *times* (the timing likelihood) at a fit's values, whichever
    likelihood the fit maximised: a count fit and a timing fit compare on it (windows read with their events)."""
    model, groups = fit_model(fit, timing=True)
    return float(mixture_log_likelihood(np.array(theta_of(fit.values, model, exact=True)), model, groups))


def theta_of(values: dict, model: Model, exact: bool = False):
    """Fitted coordinates of a values dict (the inverse of :func:`_unpack`).

    Values are floored away from their coordinate's end (a rate at 1e-12, a spread of the pixels or of the hot
    pixels at 0.05, a hot rate's excess at 1e-3, a fraction or regularity within 1e-9 of 0 and 1, a lux growth at
    1e-9): a start there would sit on a flat stretch. With ``exact`` only a value that is 0 (or 1) is moved, a term
    the values lack, so that a fit's values (:func:`unpack`'s, from these coordinates) come back as they were.
    """
    def log(value, floor):
        return math.log(value if exact and value > 0 else max(value, floor))

    def logit(value):
        return math.log(value / (1.0 - value)) if exact and 0.0 < value < 1.0 else _logit(value)

    x = [log(values["rate_on_hz"], 1e-12), log(values["rate_off_hz"], 1e-12)]
    if model.spread:
        x.append(log(values.get("sigma", 0.5), 0.05))
    if model.hot:
        ordinary = values["rate_on_hz"] + values["rate_off_hz"]
        x += [logit(values["hot_fraction"] / HOT_MAX_FRACTION),
              log(values["hot_rate_hz"] / max(ordinary, 1e-12) - HOT_MIN_RATIO, 1e-3),
              log(values["hot_sigma"], 0.05), logit(values["hot_on_fraction"])]
    if model.growth:
        x += [log(values.get("growth_on", 1e-3), 1e-9), log(values.get("growth_off", 1e-3), 1e-9)]
    if model.regular:
        x.append(logit(values.get("regularity", 0.5)))
    if model.hot and model.hot_regular:
        x.append(logit(values.get("hot_regularity", values.get("regularity", 0.5))))
    return x


def _with_count_start(model: Model, groups, starts):
    """``starts``, and for a timing model first the maximum of the same model's count likelihood (cheap: the
    counts' likelihood takes the distinct count vectors, the timing likelihood every pixel) from them."""
    if not model.timing:
        return starts
    counts = maximise(dataclasses.replace(model, timing=False), groups, starts)
    return [counts.x] + list(starts)


def _starts(model: Model, previous: dict, hot_guess):
    """Starting points: moderate and strong spread/regularity (and, for the counts, near Poisson), hot pixels from
    the data."""
    starts = []
    # the timing likelihood of a regular timer is 0 for a gap shorter than r / rate: start near Poisson there
    # (the hot pixels' short gaps first of all). The counts' likelihood of a regular timer is 0 for two events of
    # a pixel whose r / rate exceeds the window (floored at 1e-300, :func:`.likelihood._log_component`): in a window
    # short against 1 / rate every r above rate x window is one flat plateau, where BFGS started from r = 0.5 or
    # 0.9 stays (a real 3.4 s DVS128 window: 46 000 log-units below its maximum), so they start near Poisson too
    pairs = ((0.5, 0.01), (1.2, 0.2)) if model.timing else ((0.5, 0.5), (1.2, 0.9), (0.5, 0.01))
    for sigma, reg in pairs:
        v = dict(previous, sigma=sigma if model.spread else 0.0, regularity=reg if model.regular else 0.0,
                 hot_regularity=1e-3)
        if model.hot and not previous.get("hot_fraction"):
            v.update(hot_fraction=min(hot_guess[0], 0.9 * HOT_MAX_FRACTION), hot_rate_hz=_hot_rate_start(v, hot_guess),
                     hot_sigma=0.5, hot_on_fraction=0.5)
        starts.append(theta_of(v, model))
    return starts


def _hot_rate_start(values: dict, hot_guess) -> float:
    """The hot pixels' rate a start takes: the data's (``hot_guess``), at least the lowest a hot pixel may have."""
    return max(hot_guess[1], (HOT_MIN_RATIO + 1.0) * (values["rate_on_hz"] + values["rate_off_hz"]))


#: The screen of a timing model's starts (:func:`_screen`): every combination of these values of the terms the model
#: has, the rates from the data.
SCREEN_SIGMAS = (0.3, 1.2)
SCREEN_REGULARITIES = (0.01, 0.5)
SCREEN_HOT_REGULARITIES = (0.01, 0.3)
SCREEN_HOT_FRACTIONS = (0.005, 0.03)


def _screen(model: Model, previous: dict, hot_guess):
    """A timing model's screened starts (:func:`.likelihood.maximise` runs BFGS from the best few): the spread,
    regularity, hot pixels' regularity and hot fraction at every combination of :data:`SCREEN_SIGMAS` ...
    (one value for a term the model does not have), the rates from ``previous``, the hot pixels' rate from the data
    (as :func:`_starts`). Empty for a count model (its starts are few and cheap to run)."""
    if not model.timing:
        return []
    grid = itertools.product(SCREEN_SIGMAS if model.spread else (0.0,),
                             SCREEN_REGULARITIES if model.regular else (0.0,),
                             SCREEN_HOT_REGULARITIES if model.hot and model.hot_regular else (0.0,),
                             SCREEN_HOT_FRACTIONS if model.hot else (0.0,))
    hot_rate = _hot_rate_start(previous, hot_guess)
    return [theta_of(dict(previous, sigma=sigma, regularity=reg, hot_regularity=hot_reg, hot_fraction=fraction,
                          hot_rate_hz=hot_rate, hot_sigma=0.5, hot_on_fraction=0.5), model)
            for sigma, reg, hot_reg, fraction in grid]


OPTIONS = ("auto", "on", "off")


def fit_quiet(windows, *, base=None, spread: str = "auto", hot: str = "auto", regularity: str = "auto",
              timing: str = "off", hot_regularity: str = "off", start=None, progress: bool = False) -> QuietFit:
    """Fit background rates, their regularity and spread, and hot pixels to quiet windows (module doc).

    Parameters
    ----------
    windows : sequence of QuietWindow
        Windows of still scenes; windows of one recording (same ``group``) share their pixels.
    base : NoiseParams or str, optional
        Preset for the shot noise of windows with a ``lux`` (and for :meth:`QuietFit.to_params`).
    spread, hot, regularity : {"auto", "on", "off"}
        Fit the per-pixel spread / the hot pixels / the regularity of the arrivals: ``"auto"`` adds
        them one at a time (regularity, spread, hot pixels) and keeps each only where a likelihood-
        ratio test at :data:`LR_P` says the data carry it.
    timing : {"off", "auto", "on"}
        Fit the event times (the timing likelihood of :mod:`.likelihood`), not only the counts: ``"auto"``
        where every window carries its events (:func:`~evnoise.calibration.quiet_window` keeps them),
        ``"on"`` requires it.
        Default ``"off"`` (the counts are fitted, the timing *tested*): the timing fit costs several times the
        count fit (about 30 s against 6 s for the documentation's 128 x 128 window of 58 000 events, longer
        with hot pixels, whose eight parameters each cost a likelihood evaluation per gradient), and on real
        sensors it can reach other conclusions than the counts (a Poisson background where the counts
        suggest a periodic one), so it is asked for, not implied. Its likelihood can have maxima far apart
        (a near-periodic leak, or a Poisson one with a broad spread and regular hot pixels), so BFGS runs
        from the count fit's maximum, starts near Poisson and the best of a screen of starts over the spread,
        regularities and hot fraction (``likelihood.maximise``), and the highest maximum is kept.
    hot_regularity : {"auto", "on", "off"}
        Give the hot pixels their own regularity (``hot_regularity``; else they share the ordinary pixels'):
        the preset (:meth:`QuietFit.to_params`) carries it as ``hot_pixel_regularity``, which the simulators
        run. Default ``"off"`` (one regularity for every pixel).
    start : QuietFit or dict or "nested", optional
        An earlier fit of the same windows (or its ``values``), typically of a model this one holds (the fit
        without the hot pixels' own regularity for one with it): one more start for every maximisation (the full
        model, each likelihood-ratio test's reduced model, the refit), each model taking the values it has (a
        regularity of the hot pixels the earlier fit lacks starts at the ordinary one), run besides the fit's own
        starts, which it does not displace. Every maximisation keeps the best of its runs and BFGS never descends,
        so the fit ends at least as high as ``start``'s values: a model cannot end below a model it holds, which
        a timing fit's local maxima otherwise allow (a real window, ``calibration/README.md``).
        ``"nested"``: where this fit has the hot pixels' own regularity (``hot_regularity`` "auto" or "on" with
        hot pixels, timing fitted), first fit the same windows with the same options and ``hot_regularity="off"``
        and start from that (about 1.5-2x the time; ``evnoise calibrate`` does so); elsewhere no start. The notes
        give that fit's log-likelihood; with ``"auto"`` terms the two fits' tests may keep different terms, and
        where this one keeps fewer it can end below that fit (the note says so).
    progress : bool
        Show a progress line naming the running phase (the full model, each likelihood-ratio test, the
        standard errors, the goodness of fit) with its elapsed time.
    """
    from scipy.stats import chi2

    import evnoise as ev

    windows = same_exclusions(list(windows))
    if not windows:
        raise InputError("no quiet windows to fit")
    for opt, name in ((spread, "spread"), (hot, "hot"), (regularity, "regularity"), (timing, "timing"),
                      (hot_regularity, "hot_regularity")):
        if opt not in OPTIONS:
            raise ParameterError(f"{name} must be 'auto', 'on' or 'off', got {opt!r}")
    base = ev.load_preset(base) if isinstance(base, str) else base
    nested = isinstance(start, str) and start == "nested"
    if nested:
        start = _nested_start(windows, base=base, spread=spread, hot=hot, regularity=regularity, timing=timing,
                              hot_regularity=hot_regularity, progress=progress)
    start_values = _start_values(start)
    if any(w.lux is not None for w in windows) and base is None:
        raise ParameterError("windows with a lux need a base preset for the shot noise (base=...)")
    groups = window_groups(windows)
    use_timing = timing != "off" and timing_available(groups)
    if timing == "on" and not use_timing:
        raise ParameterError("timing='on' needs every window's events (read the windows with quiet_window)")
    shot = [_shot_rates(g.windows, base) for g in groups]
    lux_levels = {w.lux for w in windows if w.lux is not None}
    growth = len(lux_levels) >= 2
    lux = [np.array([w.lux or 0.0 for w in g.windows]) for g in groups]
    exposure = sum(w.duration_s * w.n_pixels for w in windows)
    tot = np.sum([w.pixel_counts().sum(axis=1) for w in windows], axis=0).astype(np.float64)
    shot_total = np.zeros(2)
    for g, sh in zip(groups, shot):
        for i, w in enumerate(g.windows):
            shot_total += sh[i] * w.duration_s * w.n_pixels
    rates0 = [max((tot[k] - shot_total[k]) / exposure, 1e-9) for k in range(2)]
    hot_guess = _hot_guess(windows, np.array(rates0))

    options = {"regular": regularity, "spread": spread, "hot": hot, "hot_regular": hot_regularity}
    values0 = dict(rate_on_hz=rates0[0], rate_off_hz=rates0[1], sigma=0.0, hot_fraction=0.0, hot_rate_hz=0.0,
                   hot_sigma=0.0, hot_on_fraction=0.5, growth_on=1e-3, growth_off=1e-3, regularity=0.0,
                   hot_regularity=0.0)

    def model_of(flags):
        return Model(flags["spread"], flags["hot"], shot, growth, lux, flags["regular"], use_timing,
                     flags["hot_regular"] and flags["hot"])

    def given(model):  # ``start`` in the model's coordinates (none without it)
        return [] if start_values is None else [theta_of(dict(values0, **start_values), model, exact=True)]

    # backward selection: the full model first, then each term dropped in turn (likelihood-ratio test)
    full = {t: option != "off" for t, option in options.items()}
    full["hot_regular"] = full["hot_regular"] and full["hot"]
    with Phases("quiet fit", 3 + sum(full.values()), enabled=progress) as phases:
        with phases.phase("full model"):
            model = model_of(full)
            res = maximise(model, groups, _with_count_start(model, groups, _starts(model, values0, hot_guess)),
                           _screen(model, values0, hot_guess), given(model))
        values = dict(values0, **unpack(res.x, model))
        tests = {}
        dofs = {"regular": 1, "spread": 1, "hot": 4 + full["hot_regular"], "hot_regular": 1}
        names = {"regular": "regularity", "spread": "spread", "hot": "hot_pixels", "hot_regular": "hot_regularity"}
        keep = dict(full)
        reduced_nll = {}
        for term in ("hot_regular", "regular", "spread", "hot"):
            if not full[term] or (term == "hot_regular" and not full["hot"]):
                continue
            with phases.phase(f"test of {names[term]}"):
                reduced = model_of(dict(full, **{term: False}))
                red_values = dict(values, **({"hot_fraction": 0.0} if term == "hot" else {}))
                if term == "regular":
                    red_values["regularity"] = 0.0
                # the full fit's values may sit where the reduced model forbids what the window has (a gap, a count):
                # start afresh too
                red_starts = _with_count_start(reduced, groups, [theta_of(red_values, reduced)]
                                               + _starts(reduced, values0, hot_guess))
                red_res = maximise(reduced, groups, red_starts, _screen(reduced, values0, hot_guess), given(reduced))
                if use_timing and red_res.fun < res.fun - 1e-6:
                    # the full model holds the reduced one, so BFGS stopped at a lower maximum (seen on real windows
                    # with hot pixels): start the full model again from the reduced one's maximum
                    again = maximise(model, groups,
                                     [theta_of(dict(values, **unpack(red_res.x, reduced)), model, exact=True)])
                    if again.fun < res.fun:
                        res = again
                        values = dict(values0, **unpack(res.x, model))
            reduced_nll[term] = red_res.fun
        for term, red_fun in reduced_nll.items():  # against the best full fit
            stat = max(0.0, 2.0 * (red_fun - res.fun))
            tests[names[term]] = {"lr": stat, "p_value": float(chi2.sf(stat, dofs[term])), "dof": dofs[term]}
            if options[term] == "auto" and tests[names[term]]["p_value"] >= LR_P:
                keep[term] = False
        restored = []
        with phases.phase("refit of the terms kept"):
            full_res = res
            while keep != full:
                model = model_of(keep)
                kept_values = dict(values, **({} if keep["hot"] else {"hot_fraction": 0.0}))
                starts = _starts(model, values0, hot_guess)
                starts = starts[:1] if use_timing else starts  # (a timing model takes the best of its starts)
                res = maximise(model, groups, [theta_of(kept_values, model)] + starts,
                               _screen(model, values0, hot_guess), given(model))
                # each term was tested against the full model alone: two that are each dispensable may not be both
                # (a spread and hot pixels can stand in for each other); the terms dropped are tested together
                dropped = [t for t in reduced_nll if full[t] and not keep[t]]
                if len(dropped) < 2:
                    break
                stat = max(0.0, 2.0 * (res.fun - full_res.fun))
                dof = sum(dofs[t] for t in dropped)
                joint = {"lr": stat, "p_value": float(chi2.sf(stat, dof)), "dof": dof}
                tests["dropped_together"] = joint
                if joint["p_value"] >= LR_P:
                    break
                back = min(dropped, key=lambda t: tests[names[t]]["p_value"])  # the one the data carry most
                keep[back] = True
                restored.append(names[back])
            if keep == full:
                res = full_res
                model = model_of(full)
        with phases.phase("standard errors"):
            se, notes = _standard_errors(model, groups, res)
        if restored:
            notes.append(f"kept {', '.join(restored)} although its own likelihood-ratio test would drop it: the terms "
                         f"dropped together are not dispensable (test dropped_together)")
        with phases.phase("goodness of fit"):
            goodness = goodness_of_fit(unpack(res.x, model), model, groups, len(res.x))
            timing = timing_tests(unpack(res.x, model), model, groups)
    fit = _quiet_fit(model, res, se, notes, tests, goodness, windows, base, spread, hot, regularity, lux_levels,
                     timing, hot_regularity)
    if nested and start is not None:
        # the two fits choose their terms each by its own likelihood-ratio tests: where this one dropped a term the
        # other kept, it no longer holds that fit and can end below it (said so, not claimed otherwise)
        held = fit.log_likelihood >= start.log_likelihood - 1e-6 * max(1.0, abs(start.log_likelihood))
        fit.notes.append(f"started from the fit without the hot pixels' own regularity (log-likelihood "
                         f"{start.log_likelihood:.2f}), " + ("which this model holds: it ends at least as high" if held
                         else "but ends below it: the terms kept differ (each fit's likelihood-ratio tests)"))
    return fit


def _nested_start(windows, *, hot, timing, hot_regularity, **options):
    """``fit_quiet(start="nested")``'s start: the fit with ``hot_regularity="off"`` where the hot pixels may have a
    regularity of their own in a timing fit (the only term a count fit cannot identify), else ``None``."""
    if hot == "off" or hot_regularity == "off" or timing == "off" or not timing_available(window_groups(windows)):
        return None
    return fit_quiet(windows, hot=hot, timing=timing, hot_regularity="off", **options)


def _start_values(start) -> dict | None:
    """The values of :func:`fit_quiet`'s ``start`` (a :class:`QuietFit` or its ``values``), checked; ``None``
    without one. A regularity of the hot pixels that ``start`` lacks is the ordinary one (the nested value)."""
    if start is None:
        return None
    values = start.values if isinstance(start, QuietFit) else start
    if not isinstance(values, dict):
        raise ParameterError(f"start must be a QuietFit, a dict of its values or 'nested', got {start!r:.40}")
    for name in ("rate_on_hz", "rate_off_hz"):
        if name not in values:
            raise ParameterError(f"start lacks {name!r} (a QuietFit's values hold it)")
    values = {k: v for k, v in values.items() if k in NAMES or k in ("growth_on", "growth_off")}
    for k, v in values.items():
        if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ParameterError(f"start's {k} must be a finite number >= 0, got {v!r}")
    values.setdefault("hot_regularity", values.get("regularity", 0.0))
    return values


def _standard_errors(model: Model, groups, res):
    """``(se, notes)``: standard errors of the fitted values (observed information, delta method)."""
    v = unpack(res.x, model)

    # standard errors: observed information in the fitted coordinates, delta method
    def nll(t):
        return -mixture_log_likelihood(t, model, groups)

    def inverse_information(free):
        def nll_free(t):
            x = res.x.copy()
            x[free] = t
            return nll(x)

        try:
            cov = np.linalg.inv(hessian(nll_free, res.x[free])) if free else np.zeros((0, 0))
        except np.linalg.LinAlgError:
            return None
        return cov if np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0) else None

    se = {n: None for n in NAMES}
    notes = []
    coords = _coordinates(model)
    free = list(range(len(coords)))
    cov = inverse_information(free)
    # a coordinate on a bound of its range (_at_bounds), running off to +-inf, can make the information
    # singular: then it is held there and the others' errors are conditional on it
    bound = _at_bounds(v, model, [w for g in groups for w in g.windows])
    if cov is None and bound:
        free = [i for i, n in enumerate(coords) if n not in bound]
        cov = inverse_information(free)
        if cov is not None:
            notes.append("on a bound of its range: " + ", ".join(bound) + " (held there for the others' standard "
                         "errors)")
    if cov is not None:
        d = np.zeros(res.x.size)
        d[free] = np.sqrt(np.diag(cov))
        se["rate_on_hz"] = v["rate_on_hz"] * d[0]
        se["rate_off_hz"] = v["rate_off_hz"] * d[1]
        i = 2
        if model.spread:
            se["sigma"] = v["sigma"] * d[i]
            i += 1
        if model.hot:
            f = v["hot_fraction"]
            q = v["hot_on_fraction"]
            ordinary = v["rate_on_hz"] + v["rate_off_hz"]
            se["hot_fraction"] = f * (1 - f / HOT_MAX_FRACTION) * d[i]
            se["hot_rate_hz"] = (v["hot_rate_hz"] - HOT_MIN_RATIO * ordinary) * d[i + 1]  # ordinary's part ignored
            se["hot_sigma"] = v["hot_sigma"] * d[i + 2]
            se["hot_on_fraction"] = q * (1 - q) * d[i + 3]
            i += 4
        if model.growth:
            se["growth_on"] = v["growth_on"] * d[i]
            se["growth_off"] = v["growth_off"] * d[i + 1]
            i += 2
        if model.regular:
            se["regularity"] = v["regularity"] * (1 - v["regularity"]) * d[i]
            low = "regularity" in bound and v["regularity"] <= 0.5
            if low:
                # at r = 0 (a Poisson background) the delta method through the logit shrinks the error to
                # nothing as well: the profile likelihood says how far r can move up
                se["regularity"] = _profile_distance(nll, res.x, i, v["regularity"], upward=True)
                notes.append("regularity at its lower bound (0: a Poisson background): its standard error is the "
                             "profile-likelihood distance to the 1-sigma point above it (one-sided)")
            elif v["regularity"] + 2.0 * se["regularity"] > 1.0 or "regularity" in bound:
                # near r = 1 the delta method through the logit shrinks the error to nothing while the
                # likelihood may be flat: the profile likelihood says how far r can move inwards
                se["regularity"] = _profile_distance(nll, res.x, i, v["regularity"])
                notes.append("regularity close to 1: its standard error is the profile-likelihood distance to "
                             "the 1-sigma point below it (one-sided)")
            i += 1
        if model.hot and model.hot_regular:
            se["hot_regularity"] = v["hot_regularity"] * (1 - v["hot_regularity"]) * d[i]
    else:
        notes.append("the observed information is not positive definite: no standard errors")
    return se, notes


def _coordinates(model: Model) -> list:
    """The parameter behind each fitted coordinate, in the order of :func:`_unpack`."""
    names = ["rate_on_hz", "rate_off_hz"] + ["sigma"] * model.spread
    if model.hot:
        names += ["hot_fraction", "hot_rate_hz", "hot_sigma", "hot_on_fraction"]
    return (names + ["growth_on", "growth_off"] * model.growth + ["regularity"] * model.regular
            + ["hot_regularity"] * (model.hot and model.hot_regular))


#: A parameter held in an interval by its fitted coordinate (a logit, a log of the excess over a floor) counts as
#: at that bound when it is within this fraction of the interval (the coordinate beyond about +-9.2).
BOUND_TOL = 1e-4
#: An ordinary pixels' rate that accounts for fewer events than this in all the windows together is at its lower
#: bound, 0 (the events of its polarity are the hot pixels')
NEGLIGIBLE_EVENTS = 1e-3
#: A log-normal spread (``sigma``, ``hot_sigma``, fitted as its log) below this is at its lower bound, 0.
SIGMA_FLOOR = 1e-3


def _at_bounds(v: dict, model: Model, windows=()) -> dict:
    """``{name: "at upper bound (BOUND" | "at lower bound (BOUND"}`` (the caller closes the bracket) of the fitted
    parameters on a bound of their range (:data:`BOUND_TOL`): the maximum is there, not inside, so the
    observed information gives it no standard error. A polarity without any event in ``windows`` has its rate's
    maximum at 0 (the optimiser stops wherever its log's gradient falls below its tolerance)."""
    out = {}
    counts = [w.pixel_counts() for w in windows]
    exposure = sum(w.duration_s * c.shape[1] for w, c in zip(windows, counts))  # pixel-seconds
    for k, name in enumerate(("rate_on_hz", "rate_off_hz")):
        pol = "ON" if k == 0 else "OFF"
        if windows and not any(int(c[k].sum()) for c in counts):
            out[name] = f"at lower bound (0: no {pol} events"
        elif windows and v[name] * exposure < NEGLIGIBLE_EVENTS:
            # the polarity's events are the hot pixels': the likelihood is flat in the log of this rate, whose
            # numerical curvature is rounding noise of either sign
            out[name] = f"at lower bound (0: {v[name] * exposure:.1g} of the {pol} events expected from it"
    if model.spread and v["sigma"] < SIGMA_FLOOR:
        out["sigma"] = "at lower bound (0: no spread"
    if model.hot:
        if v["hot_sigma"] < SIGMA_FLOOR:
            out["hot_sigma"] = "at lower bound (0: no spread"
        if v["hot_fraction"] >= HOT_MAX_FRACTION * (1 - BOUND_TOL):
            out["hot_fraction"] = f"at upper bound (HOT_MAX_FRACTION = {HOT_MAX_FRACTION:g}"
        ordinary = v["rate_on_hz"] + v["rate_off_hz"]
        if v["hot_rate_hz"] <= HOT_MIN_RATIO * ordinary * (1 + BOUND_TOL):
            out["hot_rate_hz"] = f"at lower bound ({HOT_MIN_RATIO:g} times the ordinary rate"
        for side, bound in (("lower", 0.0), ("upper", 1.0)):
            if abs(v["hot_on_fraction"] - bound) <= BOUND_TOL:
                out["hot_on_fraction"] = f"at {side} bound ({bound:g}"
    for name, on in (("regularity", model.regular), ("hot_regularity", model.hot and model.hot_regular)):
        if not on:
            continue
        if v[name] >= 1 - BOUND_TOL:
            out[name] = "at upper bound (1: periodic"
        elif v[name] <= BOUND_TOL:
            out[name] = "at lower bound (0: Poisson"
    return out


def _quiet_fit(model, res, se, notes, tests, goodness, windows, base, spread, hot, regularity, lux_levels,
               timing=(), hot_regularity="off") -> QuietFit:
    """The :class:`QuietFit` of a finished fit: statuses and notes."""
    v = unpack(res.x, model)
    status = {n: "fitted" for n in NAMES}
    if not model.spread:
        status["sigma"] = "not identified (likelihood-ratio test)" if spread == "auto" else "fixed"
    if not model.hot:
        for n in ("hot_fraction", "hot_rate_hz", "hot_sigma", "hot_on_fraction"):
            status[n] = "not identified (likelihood-ratio test)" if hot == "auto" else "fixed"
    if not model.regular:
        status["regularity"] = "not identified (likelihood-ratio test)" if regularity == "auto" else "fixed"
    hidden = ()
    if hot_regularity == "off":
        status["hot_regularity"] = "tied to regularity"
        se.pop("hot_regularity", None)
        hidden = ("hot_regularity",)
    elif not (model.hot and model.hot_regular):
        status["hot_regularity"] = ("not identified (likelihood-ratio test)" if hot_regularity == "auto" and model.hot
                                    else "tied to regularity")
        se["hot_regularity"] = se.get("regularity")
    if model.timing:
        notes.append("timing likelihood: the pixels' event times in each window (renewal gaps, first event from "
                     "the stationary forward-recurrence law, the last gap censored), not only their counts")
    doublets = sum(getattr(w, "doublets", 0) for w in windows)
    if doublets:
        notes.append(f"{doublets} readout doublet(s) merged (a pixel's event within {DOUBLET_US} us after its "
                     "previous one of the same polarity)")
    notes += oscillating_notes(windows)
    for n in ("hot_sigma", "hot_on_fraction"):
        if model.hot and v["hot_fraction"] * sum(w.n_pixels for w in windows) < 5:
            status[n] = "weakly identified (fewer than 5 hot pixels)"
    for n, side in _at_bounds(v, model, windows).items():
        if n == "regularity" and side.startswith("at upper") and se.get(n) is not None and math.isfinite(se[n]):
            # near r = 1 the profile likelihood's one-sided error stands (_standard_errors)
            status[n] = f"{side}; one-sided profile-likelihood error)"
            continue
        status[n] = f"{side}; no standard error)"
        se[n] = None  # the delta method's error at a bound describes the coordinate, not the parameter
    for n in NAMES:
        if status[n] == "fitted" and (se.get(n) is None or not math.isfinite(se[n])):
            status[n] = "fitted, no standard error"
    if not lux_levels:
        notes.append("illuminance unknown: the rates are the totals at the recording's light (shot noise and "
                     "background together); the shot-noise parameters are not identified")
    rejections = _rejections(goodness, windows, timing)
    return QuietFit(v, se, status, -float(res.fun), tests, goodness, windows, base, notes,
                    "rejected" if rejections else "accepted", rejections, list(timing), hidden)


def _timing_verdict(t: dict) -> str:
    """A timing test's verdict in the words of :func:`.checks.check_verdict`."""
    if not t.get("testable", True) or not math.isfinite(t["p_value"]):
        return "not testable"
    if t["p_value"] < GOODNESS_P:
        return f"FAILED (p = {t['p_value']:.3g} < {GOODNESS_P:g})"
    return f"passed (p = {t['p_value']:.3g} >= {GOODNESS_P:g})"


def _rejections(goodness, windows, timing=()) -> list:
    """Why the fit is rejected (module doc): histograms the model does not describe, windows that are not noise."""
    out = [f"{g['window']} {g['polarity']}: the count histogram does not match the model (chi2 {g['chi2']:.3g} on "
           f"{g['dof']} dof, p = {g['p_value']:.3g} < {GOODNESS_P:g})"
           for g in goodness if math.isfinite(g["p_value"]) and g["p_value"] < GOODNESS_P]
    for w in windows:
        out += [f"{w.describe()} is not pure stationary noise: {c['check']} {check_verdict(c)}"
                for c in failed_checks(w.checks)]
    what = {"intervals": "the same-pixel inter-event intervals do not match the model",
            "polarity_transitions": "consecutive same-pixel events alternate in polarity unlike the model"}
    out += [f"{t['window']}: {what[t['test']]} ({t['test']} {_timing_verdict(t)}: {t['detail']})"
            for t in timing if _timing_verdict(t).startswith("FAILED")]
    return out


# --------------------------------------------------------------------------------------
# a fitted preset against a recording, and the preset document
# --------------------------------------------------------------------------------------
def preset_toml(params, *, sensor: tuple, header: str, provenance: dict, fit: QuietFit | None = None,
                validation: list | None = None) -> str:
    """A preset document: header comment, ``[sensor]``, ``[params]``, ``[provenance]``, ``[fit]``, validation.

    Parameters
    ----------
    params : NoiseParams
        The fitted parameters, written in full (``params.to_dict()``) under ``[params]``.
    sensor : tuple of (int, int, str)
        ``(width, height, name)`` of the sensor, written under ``[sensor]``.
    header : str
        Text written as comment lines (``#``) at the top of the document.
    provenance : dict
        Where the preset comes from, written under ``[provenance]``.
    fit : QuietFit, optional
        The fit's report, written under ``[fit]`` and its sub-tables (status, values, standard errors,
        tests, goodness, checks, timing); omitted when ``None``.
    validation : list of dict, optional
        Validation results, one ``[[validation]]`` table each.

    Returns
    -------
    str
        The TOML text, ending in a newline.
    """
    from ..preset import toml_table, toml_value

    width, height, name = sensor
    lines = [f"# {line}".rstrip() for line in header.strip().splitlines()] + [""]
    lines += toml_table("sensor", {"width": int(width), "height": int(height), "name": name}) + [""]
    lines += toml_table("params", params.to_dict(), digits=None) + [""]
    lines += toml_table("provenance", provenance) + [""]
    if fit is not None:
        tables = fit.to_toml_tables()
        lines += toml_table("fit", {"method": tables["method"], "log_likelihood": tables["log_likelihood"],
                                "fit_status": tables["fit_status"], "rejections": tables["rejections"],
                                "notes": tables["notes"]}) + [""]
        lines += toml_table("fit.status", tables["status"]) + [""]
        lines += toml_table("fit.values", tables["values"]) + [""]
        lines += toml_table("fit.std_error", tables["std_error"]) + [""]
        lines += toml_table("fit.tests", tables["tests"]) + [""]
        for g in tables["goodness"]:
            lines += ["[[fit.goodness]]"] + [f"{k} = {toml_value(v)}" for k, v in g.items()] + [""]
        for c in tables["checks"]:
            lines += ["[[fit.checks]]"] + [f"{k} = {toml_value(v)}" for k, v in c.items()] + [""]
        for t in tables["timing"]:
            lines += ["[[fit.timing]]"] + [f"{k} = {toml_value(v)}" for k, v in t.items()] + [""]
    for g in validation or []:
        lines += ["[[validation]]"] + [f"{k} = {toml_value(v)}" for k, v in g.items()] + [""]
    return "\n".join(lines).rstrip() + "\n"
