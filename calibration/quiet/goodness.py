"""Goodness of fit of quiet-scene models: the fitted model's count histograms against the windows', and
a preset simulated against a recording. Part of :mod:`evnoise.calibration.quiet`.
"""

from __future__ import annotations

import math

import numpy as np

from .counts import count_pmf
from .likelihood import component_rates
from .window import QuietWindow, drop_pixels

__all__ = ["GOF_MAX_COUNT", "simulate_window", "compare_to_recording", "interval_cdf", "timing_tests",
           "window_intervals", "compare_intervals", "renewal_intervals", "interval_sampler", "simulated_ks_p_value",
           "pixel_permutation_ks"]


#: Largest count evaluated one by one in the goodness-of-fit histograms (higher ones form the tail bin).
GOF_MAX_COUNT = 200
#: The interval test's p-value comes from windows simulated from the fitted model: at most this many (so the
#: smallest p-value, ``1 / (INTERVAL_REPLICAS + 1)``, is below the fit's ``GOODNESS_P`` of 1e-3) ...
INTERVAL_REPLICAS = 1999
#: ... stopped once this many of them are at least as extreme as the window (Besag and Clifford's sequential
#: p-value: a window that fits stops after a few dozen)
INTERVAL_EXCEEDANCES = 10


def _marginal_pmf(v, model, gi, grp, wi, pol, kmax):
    """Model probability of a pixel's count 0..kmax of polarity ``pol`` in window ``wi`` (the mixture).

    Each event is ON with the pixel's ON share, independently: the polarity's count is a binomial
    thinning of the renewal count ``N`` (evaluated up to the window's largest total count).
    """
    from scipy.stats import binom

    w = grp.windows[wi]
    n_cap = min(int(w.counts.sum(axis=0).max()) + 5, 2 * GOF_MAX_COUNT)
    n = np.arange(n_cap + 1)
    k = np.arange(kmax + 1)
    comps = component_rates(v, gi, model, grp)
    fractions = [1.0 - v["hot_fraction"], v["hot_fraction"]]
    out = np.zeros(kmax + 1)
    for (rates, share_on, weights), frac, reg in zip(comps, fractions, _regularities(v)):
        keep = weights > 1e-14 * weights.max()
        pmf_n = count_pmf(n_cap, rates[keep, wi], w.duration_s, reg)  # (M, N)
        q = share_on[keep, wi] if pol == 0 else 1.0 - share_on[keep, wi]
        thin = binom.pmf(k[None, :, None], n[None, None, :], q[:, None, None])  # (M, K, N)
        out += frac * np.einsum("mkn,mn,m->k", thin, pmf_n, weights[keep] / weights[keep].sum())
    return out


def _regularities(v):
    """The regularity of the ordinary and of the hot pixels (the same unless the fit gave the hot their own)."""
    return v["regularity"], v.get("hot_regularity", v["regularity"])


def goodness_of_fit(v, model, groups, n_fitted):
    from scipy.stats import chi2

    out = []
    for gi, grp in enumerate(groups):
        for wi, w in enumerate(grp.windows):
            n_pix = w.n_pixels
            kept = w.pixel_counts()
            for pol, name in enumerate(("ON", "OFF")):
                counts = np.minimum(kept[pol], GOF_MAX_COUNT)
                kmax = int(counts.max())
                pmf = _marginal_pmf(v, model, gi, grp, wi, pol, kmax)
                observed = np.bincount(counts, minlength=kmax + 1).astype(np.float64)
                expected = pmf * n_pix
                expected[-1] += max(n_pix - expected.sum(), 0.0)  # the tail beyond kmax
                obs, exp = _pool(observed, expected)
                # one bin left after pooling (a handful of events) is no test at all: p is NaN and the summary
                # says "not testable", where it said "p = 1"
                testable = len(obs) > 1
                dof = max(1, len(obs) - 1 - n_fitted) if testable else 0
                stat = float(np.sum((obs - exp) ** 2 / exp)) if testable else 0.0
                out.append({"window": w.describe(), "polarity": name, "chi2": stat, "dof": dof,
                            "p_value": float(chi2.sf(stat, dof)) if testable else math.nan, "bins": len(obs),
                            "pooled": len(obs) < kmax + 1, "max_count": kmax, "events": int(w.counts[pol].sum()),
                            "expected_events": float(np.dot(np.arange(kmax + 1), pmf) * n_pix)})
    return out


def _gap_parts(x, rate, regularity):
    """``F(x)`` and ``int_0^x u f(u) du`` of the renewal gap ``r mu + Exp((1 - r) mu)``, ``mu = 1 / rate``
    (``x`` (N,), ``rate`` (M,) -> (M, N))."""
    x = np.asarray(x, dtype=np.float64)[None, :]
    mu = 1.0 / np.maximum(np.asarray(rate, dtype=np.float64), 1e-300)[:, None]
    d = regularity * mu
    theta = np.maximum((1.0 - regularity) * mu, 1e-300)
    y = np.maximum(x - d, 0.0)
    tail = np.exp(-y / theta)
    cdf = np.where(x >= d, 1.0 - tail, 0.0)
    partial = np.where(x >= d, d * (1.0 - tail) + theta * (1.0 - tail * (1.0 + y / theta)), 0.0)
    return cdf, partial


def interval_cdf(x, v, model, gi, grp, wi):
    """CDF of the fitted model's same-pixel inter-event intervals as a window observes them.

    A pixel's events form a renewal process of its total rate ``lam`` (gaps ``r mu + Exp((1 - r) mu)``, the
    fit's model: refractory period and trial steps are negligible beside the gaps); a window of ``T`` seconds
    holds on average ``lam (T - x) f(x) dx`` intervals of length ``x`` (the long ones are cut by its ends), and
    the window's intervals are the mixture of that over its pixels (spread grid, hot pixels) weighted by
    their share of pixels.
    """
    T = float(grp.windows[wi].duration_s)
    x = np.minimum(np.asarray(x, dtype=np.float64), T)
    num = np.zeros(x.shape)
    den = 0.0
    fractions = [1.0 - v["hot_fraction"], v["hot_fraction"]]
    for (rates, _share, weights), frac, reg in zip(component_rates(v, gi, model, grp), fractions, _regularities(v)):
        if frac <= 0:
            continue
        lam = rates[:, wi]
        wgt = frac * weights / weights.sum() * lam
        cdf, part = _gap_parts(x, lam, reg)
        cdf_t, part_t = _gap_parts(np.array([T]), lam, reg)
        num += wgt @ (T * cdf - part)
        den += float(wgt @ (T * cdf_t - part_t)[:, 0])
    return np.clip(num / den, 0.0, 1.0) if den > 0 else np.zeros(x.shape)


def renewal_intervals(rate_hz, regularity, duration_s: float, rng) -> np.ndarray:
    """Sorted same-pixel intervals (s) of pixels with total rates ``rate_hz`` and timer regularities ``regularity``
    (1-D arrays, one entry per pixel) seen in a window of ``duration_s``: each pixel a stationary renewal process
    with gaps ``r mu + Exp((1 - r) mu)``, ``mu = 1 / rate`` (:func:`interval_cdf`'s model), its first event at the
    stationary forward recurrence time (with probability ``r`` uniform on ``[0, r mu)``, else ``r mu`` plus an
    exponential); the intervals between its consecutive events inside the window. Rates at or below
    :data:`~.counts.RATE_TINY_HZ` give no events."""
    from .counts import RATE_TINY_HZ

    rate = np.asarray(rate_hz, dtype=np.float64)
    r = np.asarray(regularity, dtype=np.float64)
    live = np.flatnonzero(rate > RATE_TINY_HZ)
    mu, r = 1.0 / rate[live], r[live]
    fixed = r * mu
    scale = (1.0 - r) * mu
    in_fixed = rng.random(live.size) < r
    t = np.where(in_fixed, rng.random(live.size) * fixed, fixed + rng.exponential(scale))
    prev = np.full(live.size, np.nan)
    out = []
    idx = np.flatnonzero(t < duration_s)
    while idx.size:
        seen = ~np.isnan(prev[idx])
        out.append(t[idx[seen]] - prev[idx[seen]])
        prev[idx] = t[idx]
        t[idx] += fixed[idx] + rng.exponential(scale[idx])
        idx = idx[t[idx] < duration_s]
    return np.sort(np.concatenate(out)) if out else np.zeros(0)


def interval_sampler(v, model, gi, grp, wi):
    """A function ``rng -> sorted intervals`` of window ``wi`` simulated from the fitted model (:func:`interval_cdf`'s):
    its pixels (as many as the window's kept ones) drawn from the model's components (ordinary, hot) and their
    spread nodes by weight, then :func:`renewal_intervals`."""
    w = grp.windows[wi]
    n_pix = w.n_pixels
    parts = []
    for (rates, _share, weights), frac, reg in zip(component_rates(v, gi, model, grp),
                                                  [1.0 - v["hot_fraction"], v["hot_fraction"]], _regularities(v)):
        if frac > 0:
            parts.append((frac, np.ascontiguousarray(rates[:, wi]), weights / weights.sum(), float(reg)))
    fractions = np.array([p[0] for p in parts])
    fractions /= fractions.sum()

    def draw(rng):
        comp = rng.choice(len(parts), size=n_pix, p=fractions)
        rate = np.empty(n_pix)
        reg = np.empty(n_pix)
        for c, (_, lam, weight, r) in enumerate(parts):
            sel = np.flatnonzero(comp == c)
            rate[sel] = lam[rng.choice(lam.size, size=sel.size, p=weight)]
            reg[sel] = r
        return renewal_intervals(rate, reg, w.duration_s, rng)

    return draw


def _ranks(xs, n):
    """The ranks (0-based) of the stored order statistics ``xs`` of ``n`` intervals
    (:func:`.checks.stored_order_statistics`)."""
    return np.round(np.linspace(0, n - 1, xs.size)) if xs.size < n else np.arange(n, dtype=np.float64)


def _ks_distance(xs, n, cdf):
    """KS distance of ``n`` intervals whose stored order statistics (:func:`.checks.stored_order_statistics`) are
    ``xs`` from the model CDF ``cdf`` (a function)."""
    ranks = _ranks(xs, n)
    model_cdf = cdf(xs)
    return float(max(np.max((ranks + 1) / n - model_cdf), np.max(model_cdf - ranks / n)))


def simulated_ks_p_value(xs, n: int, draw, cdf, seed=0, min_intervals: int = 1):
    """P-value of a KS test of intervals that are not independent, from windows simulated under the model.

    A pixel's intervals share its rate (and the fitted model's spread and hot pixels make the rates differ), so the
    pooled intervals are not a sample of independent draws and the KS distribution of ``n`` independent ones is too
    narrow for them (a true model with a DVS128-like spread is "rejected" at 1e-3 about 20 times as often as that;
    ``tests/test_quiet_timing.py``). The statistic is the independent-sample p-value of the intervals (``xs``: the
    stored order statistics of ``n``, :func:`.checks.stored_order_statistics`; ``cdf``: the model's CDF, a
    function); the returned p-value is the share of windows simulated from the model (``draw(rng)``: their sorted
    intervals) whose statistic is as small or smaller: Besag and Clifford's sequential estimate, at most
    :data:`INTERVAL_REPLICAS` windows, stopped after :data:`INTERVAL_EXCEEDANCES` as extreme; only windows with at
    least ``min_intervals`` intervals count, as only those are tested (others are drawn again). Returns
    ``(p_value, windows simulated)``; deterministic for a ``seed``."""
    from scipy.stats import kstwo

    from .checks import stored_order_statistics

    observed = float(kstwo.sf(_ks_distance(xs, n, cdf), n))
    rng = np.random.default_rng(seed)

    def as_extreme(_):
        # a window is tested only with at least min_intervals intervals: the simulated ones as well (redrawn; a
        # model that rarely gives that many counts a window without them as not extreme)
        for _attempt in range(100):
            sim = draw(rng)
            m = sim.size
            if m >= min_intervals:
                return float(kstwo.sf(_ks_distance(stored_order_statistics(sim), m, cdf), m)) <= observed
        return False

    return _monte_carlo_p(as_extreme)


def _tabulated_cdf(cdf, duration_s: float):
    """``cdf`` (a CDF on ``[0, duration_s]``) interpolated from 4 097 values, denser near 0 where the busiest pixels'
    intervals are (the simulated windows' statistics need thousands of evaluations; off by at most 2e-5 on the
    tested populations, against KS distances of 1e-2 and more). The observed window's statistic for the p-value is
    measured with the same table."""
    grid = duration_s * np.linspace(0.0, 1.0, 4097) ** 2
    values = np.maximum.accumulate(cdf(grid))

    def tabulated(x):
        return np.interp(x, grid, values)

    return tabulated


def timing_tests(v, model, groups, *, p_opposite: float | None = None) -> list:
    """The timing tests of each window whose checks gathered its events (``same_pixel`` in the polarity
    pairs' check, :func:`.checks.same_pixel_timing`; windows without have no entry): the polarity transitions
    (:func:`.checks.polarity_transitions`; against ``p_opposite`` if given, a reset-memory model's) and a KS
    test of the same-pixel inter-event intervals against the fitted model's (:func:`interval_cdf`). Dicts
    ``{window, test, statistic, p_value, testable, detail, ...}``; fewer than
    :data:`.checks.MIN_INTERVALS` intervals: not testable, "not enough intervals"."""
    from scipy.optimize import brentq
    from scipy.stats import kstwo

    from .checks import MIN_INTERVALS, polarity_transitions

    out = []
    for gi, grp in enumerate(groups):
        for wi, w in enumerate(grp.windows):
            found = [c["same_pixel"] for c in w.checks if "same_pixel" in c]
            if not found:
                continue
            timing = found[0]
            out.append(dict(window=w.describe(), **polarity_transitions(timing, p_opposite=p_opposite)))
            n = int(timing["n_intervals"])
            xs = np.asarray(timing["intervals_s"], dtype=np.float64)
            row = {"window": w.describe(), "test": "intervals", "statistic": math.nan, "p_value": math.nan,
                   "testable": n >= MIN_INTERVALS, "intervals": n}
            if n < MIN_INTERVALS:
                row["detail"] = (f"not enough intervals: {n} pairs of consecutive events of one pixel "
                                 f"(< {MIN_INTERVALS})")
                out.append(row)
                continue

            def cdf(x, gi=gi, grp=grp, wi=wi):
                return interval_cdf(x, v, model, gi, grp, wi)

            # the stored order statistics (all of them, or evenly spaced ones: checks.STORED_INTERVALS)
            stat = _ks_distance(xs, n, cdf)
            p_independent = float(kstwo.sf(stat, n))
            pv, replicas = simulated_ks_p_value(xs, n, interval_sampler(v, model, gi, grp, wi),
                                                _tabulated_cdf(cdf, w.duration_s), seed=[gi, wi],
                                                min_intervals=MIN_INTERVALS)

            def half(x):
                return interval_cdf(np.array([x]), v, model, gi, grp, wi)[0] - 0.5

            # a model without intervals in the window (every rate ~0: its CDF is 0) has no median
            med = brentq(half, 0.0, w.duration_s) if half(0.0) < 0.0 < half(w.duration_s) else math.nan
            emp_med = float(np.interp((n - 1) / 2, _ranks(xs, n), xs))
            row.update(statistic=stat, p_value=pv, p_value_independent=p_independent, replicas=replicas,
                       median_s=emp_med, model_median_s=float(med),
                       detail=(f"KS D = {stat:.3g} over {n} same-pixel intervals (p from {replicas} windows "
                               f"simulated from the model: a pixel's intervals are not independent; "
                               f"{p_independent:.3g} if they were), median {emp_med:.4g} s against the model's "
                               f"{med:.4g} s"))
            out.append(row)
    return out


def _pool(observed, expected, minimum=5.0):
    """Adjacent bins merged (from 0 upwards) until each expected count is at least ``minimum``."""
    obs, exp = [], []
    acc_o = acc_e = 0.0
    for o, e in zip(observed, expected):
        acc_o += o
        acc_e += e
        if acc_e >= minimum:
            obs.append(acc_o)
            exp.append(acc_e)
            acc_o = acc_e = 0.0
    if acc_e > 0 or acc_o > 0:
        if exp:
            obs[-1] += acc_o
            exp[-1] += acc_e
        else:
            obs.append(acc_o)
            exp.append(acc_e)
    return np.array(obs), np.array(exp)


def simulate_window(params, window: QuietWindow, *, replicas: int = 1, seed: int = 0) -> np.ndarray:
    """Counts ``(replicas, 2, H, W)`` of ``params`` simulated on the window's sensor for its duration.

    At the window's lux (0 when unknown: a quiet-scene preset carries the recording's shot noise in its
    background), each replica with its own draw of thresholds and background maps.
    """
    import evnoise as ev

    lux = np.full(window.shape, float(window.lux or 0.0))
    seq = np.random.SeedSequence(seed)
    return np.stack([ev.sample_counts(lux, params, window.duration_s, rng=np.random.default_rng(s))
                     for s in seq.spawn(int(replicas))])


def compare_to_recording(params, window: QuietWindow, *, replicas: int = 20, seed: int = 0) -> list:
    """Two-sample chi-square test of the per-pixel count histograms: recording against simulation.

    The simulated histogram pools ``replicas`` independent sensors (so its own noise is small and
    accounted for): a homogeneity test of the 2 x bins table, bins merged from 0 upwards until both
    expected counts are at least 5, ``bins - 1`` degrees of freedom. One dict per polarity.

    Parameters
    ----------
    params : NoiseParams
        The model to compare with the recording.
    window : QuietWindow
        The recording's quiet window; its kept pixels are compared.
    replicas : int, default 20
        Independent simulated sensors pooled into the simulated histogram.
    seed : int, default 0
        Seed of the simulation (each replica draws from its own child seed).

    Returns
    -------
    list of dict
        One dict per polarity (ON, then OFF) with keys ``window``, ``polarity``, ``chi2``, ``dof``,
        ``p_value``, ``events``, ``simulated_events_per_replica`` and ``replicas``.

    Notes
    -----
    Counts above ``GOF_MAX_COUNT`` are pooled into one top bin.
    """
    from scipy.stats import chi2

    sim = simulate_window(params, window, replicas=replicas, seed=seed)
    sim = sim.reshape(sim.shape[0], 2, -1)[:, :, window.kept()]  # the pixels the window keeps
    kept = window.pixel_counts()
    out = []
    for pol, name in enumerate(("ON", "OFF")):
        real = np.minimum(kept[pol], GOF_MAX_COUNT)
        fake = np.minimum(sim[:, pol].ravel(), GOF_MAX_COUNT)
        top = int(max(real.max(), fake.max()))
        h_real = np.bincount(real, minlength=top + 1).astype(np.float64)
        h_fake = np.bincount(fake, minlength=top + 1).astype(np.float64)
        n_r, n_f = h_real.sum(), h_fake.sum()
        # merge bins until the expected count of the smaller (real) row is at least 5
        share = (h_real + h_fake) / (n_r + n_f)
        obs_r, exp_r = _pool(h_real, share * n_r)
        obs_f, _ = _pool(h_fake, share * n_r)  # same merging (driven by the same expected)
        table = np.stack([obs_r, obs_f])
        if table.shape[1] < 2:
            stat, dof, p = 0.0, 0, 1.0
        else:
            tot = table.sum(axis=0)
            expected = np.outer(table.sum(axis=1), tot) / tot.sum()
            stat = float(np.sum((table - expected) ** 2 / expected))
            dof = table.shape[1] - 1
            p = float(chi2.sf(stat, dof))
        out.append({"window": window.describe(), "polarity": name, "chi2": stat, "dof": dof, "p_value": p,
                    "events": int(window.counts[pol].sum()),
                    "simulated_events_per_replica": float(sim[:, pol].sum() / replicas),
                    "replicas": int(replicas)})
    return out


def window_intervals(window: QuietWindow) -> np.ndarray:
    """Same-pixel inter-event intervals (s) of a window read with its events (either polarity)."""
    return _pixel_intervals(window)[0]


def _pixel_intervals(window: QuietWindow):
    """``(intervals (s), pixel)``: :func:`window_intervals` and the flat index of each interval's pixel."""
    if window.events is None:
        from evnoise.errors import InputError

        raise InputError(f"{window.describe()}: no events (a QuietWindow made from counts alone; quiet_window "
                         "reads them)")
    return _intervals_of(window.events["pixel"], window.events["t_s"])


def _intervals_of(pix, t):
    """``(intervals, pixel)`` of events at flat pixels ``pix`` and times ``t``: consecutive events of one pixel."""
    order = np.lexsort((t, pix))
    t, pix = t[order], pix[order]
    same = pix[1:] == pix[:-1]
    return np.diff(t)[same], pix[1:][same]


def _monte_carlo_p(as_extreme):
    """Besag and Clifford's sequential Monte Carlo p-value: ``as_extreme(b)`` tells whether the ``b``-th simulated
    statistic is at least as extreme as the observed one; at most :data:`INTERVAL_REPLICAS` of them, stopped after
    :data:`INTERVAL_EXCEEDANCES` hits. Returns ``(p_value, replicas)``."""
    hits = 0
    for b in range(1, INTERVAL_REPLICAS + 1):
        hits += bool(as_extreme(b))
        if hits >= INTERVAL_EXCEEDANCES:
            return hits / b, b
    return (hits + 1) / (INTERVAL_REPLICAS + 1), INTERVAL_REPLICAS


def pixel_permutation_ks(real, real_pixel, simulated, simulated_pixel, n_pixels: int, n_replicas: int,
                         seed=0) -> dict:
    """Two-sample KS test of a window's same-pixel intervals against simulated windows', pixels as the units.

    ``real``, ``real_pixel``: the window's intervals and the index (``0 .. n_pixels - 1``) of each one's pixel;
    ``simulated``, ``simulated_pixel``: those of ``n_replicas`` simulated windows of the same ``n_pixels`` pixels,
    replica ``r``'s pixels numbered ``(r + 1) n_pixels ..`` (pixels without intervals count too). A pixel's
    intervals are not independent (they share its rate), so the KS distribution of independent samples is too
    narrow; under the model the ``(n_replicas + 1) n_pixels`` pixels are exchangeable, and the p-value is the
    share of random relabellings (``n_pixels`` pixels drawn as "the window") whose KS distance is at least the
    observed one (:func:`_monte_carlo_p`). Returns ``{statistic, p_value,
    replicas, p_value_independent}`` (the last: SciPy's ``ks_2samp`` as if the intervals were independent)."""
    from scipy.stats import ks_2samp

    real = np.asarray(real, dtype=np.float64)
    simulated = np.asarray(simulated, dtype=np.float64)
    values = np.concatenate([real, simulated])
    units = np.concatenate([np.asarray(real_pixel, dtype=np.int64), np.asarray(simulated_pixel, dtype=np.int64)])
    order = np.argsort(values, kind="stable")
    values, units = values[order], units[order]
    last = np.flatnonzero(np.append(values[1:] != values[:-1], True))  # the ECDFs at each distinct value
    n_units = (int(n_replicas) + 1) * int(n_pixels)

    def distance(in_window):
        first = in_window[units]
        n1 = int(np.count_nonzero(first))
        n2 = first.size - n1
        if n1 == 0 or n2 == 0:
            return 0.0
        c1 = np.cumsum(first)[last] / n1
        c2 = np.cumsum(~first)[last] / n2
        return float(np.max(np.abs(c1 - c2)))

    observed_mask = np.zeros(n_units, dtype=bool)
    observed_mask[:n_pixels] = True
    observed = distance(observed_mask)
    rng = np.random.default_rng(seed)

    def as_extreme(_):
        mask = np.zeros(n_units, dtype=bool)
        mask[rng.choice(n_units, size=n_pixels, replace=False)] = True
        return distance(mask) >= observed - 1e-12

    p, replicas = _monte_carlo_p(as_extreme)
    return {"statistic": observed, "p_value": p, "replicas": replicas,
            "p_value_independent": float(ks_2samp(real, simulated).pvalue)}


def compare_intervals(params, window: QuietWindow, *, replicas: int = 4, seed: int = 0, real_intervals=None) -> dict:
    """A preset simulated on a window (``replicas`` sensors at 0 lux for its duration) against its real events.

    Returns events per replica, the simulated same-pixel intervals' count, median and CV, the share of consecutive
    same-pixel events of opposite polarity, and a two-sample KS test of the intervals against the real ones
    (NaN with fewer than 20 on either side): ``ks_2samp_p_value`` from relabelling pixels between the window and
    the replicas (:func:`pixel_permutation_ks`: a pixel's intervals are not independent), where the window has its
    events; ``ks_2samp_p_value_independent`` as if they were (SciPy's ``ks_2samp``, also what a window without
    events gets). The real intervals' median and CV beside them (``real_intervals``, else
    :func:`window_intervals`).
    """
    from scipy.stats import ks_2samp

    import evnoise as ev

    from .checks import same_pixel_timing

    keep = window.kept()
    own = None
    if window.events is not None:
        gaps, pix = _pixel_intervals(window)
        kept = keep[pix]  # a hand-made window may still hold its left-out pixels' events
        # on the simulated intervals' grid: whole microseconds (the window's times are microseconds too)
        own = np.rint(gaps[kept] * 1e6) * 1e-6, pix[kept]
    if real_intervals is None:  # a window without events: window_intervals says so (InputError)
        real_intervals = own[0] if own is not None else window_intervals(window)
    real = np.asarray(real_intervals, dtype=np.float64)
    lux = np.zeros(window.shape)
    position = np.cumsum(keep) - 1  # a kept pixel's index among the kept ones
    n_pix = window.n_pixels
    width = window.shape[1]
    counts, ivals, units, opp, trans = [], [], [], 0, 0
    for r, s in enumerate(np.random.SeedSequence(seed).spawn(replicas)):
        events = ev.simulate_events(lux, params, window.duration_s, rng=np.random.default_rng(s))
        if window.excluded.size:  # the pixels the window leaves out, left out here too
            events = drop_pixels(events, width, window.excluded)
        counts.append([int(np.count_nonzero(events["p"] == 1)), int(np.count_nonzero(events["p"] == 0))])
        sp = same_pixel_timing(events, window.shape)
        gaps, pix = _intervals_of(events["y"].astype(np.int64) * width + events["x"], events["t"].astype(np.int64))
        ivals.append(gaps * 1e-6)
        units.append(position[pix] + (r + 1) * n_pix)
        opp += sp["opposite"]
        trans += sp["transitions"]
    xs = np.concatenate(ivals)
    counts = np.array(counts, dtype=np.float64)

    def cv(x):
        return float(np.std(x, ddof=1) / np.mean(x)) if x.size > 1 and np.mean(x) > 0 else math.nan

    test = {"statistic": math.nan, "p_value": math.nan, "replicas": 0, "p_value_independent": math.nan}
    if real.size >= 20 and xs.size >= 20:
        if own is not None:
            test = pixel_permutation_ks(own[0], position[own[1]], xs, np.concatenate(units), n_pix, replicas,
                                        seed=seed)
        else:
            plain = ks_2samp(real, xs)
            test = {"statistic": float(plain.statistic), "p_value": float(plain.pvalue), "replicas": 0,
                    "p_value_independent": float(plain.pvalue)}
    return {"replicas": replicas, "events_on_per_replica": float(counts[:, 0].mean()),
            "events_off_per_replica": float(counts[:, 1].mean()),
            "events_sd_per_replica": float(counts.sum(axis=1).std(ddof=1)) if replicas > 1 else math.nan,
            "intervals": int(xs.size), "median_s": float(np.median(xs)) if xs.size else math.nan, "cv": cv(xs),
            "opposite_share": opp / trans if trans else math.nan,
            "real_intervals": int(real.size), "real_median_s": float(np.median(real)) if real.size else math.nan,
            "real_cv": cv(real), "ks_statistic": test["statistic"], "ks_2samp_p_value": test["p_value"],
            "ks_2samp_p_value_independent": test["p_value_independent"], "ks_relabellings": test["replicas"]}
