"""Is a recording's window pure stationary noise? Three model-free checks of the quiet-fit's assumptions.

:mod:`evnoise.calibration.quiet` describes a still scene's events as, per pixel, an ON and an OFF
stream that are stationary over the window, independent of each other, and whose pixels are
exchangeable (the rate spread is a property of the pixel, not of where it sits). A recording that
breaks one of these cannot be reproduced by any preset, whatever the fit; these checks say which
assumption fails, each with a p-value from a null distribution that does not depend on the fit:

- **polarity pairs**: the number of (OFF, ON) event pairs of one pixel closer than ``pair_gap_s``,
  against the same number after each pixel's ON stream is shifted circularly in time by its own
  random offset of 10 to 40 pair gaps, either way (``shifts`` times). The shift keeps each stream
  exactly (rate, regularity, spread, hot pixels) and, being short, keeps what ON and OFF share on
  longer time scales (a drifting rate, slow bursts); it removes only their coupling within a few
  pair gaps. An excess means the pixel's ON and OFF events come in close pairs (a transient that
  crosses the threshold and comes back), which the model cannot produce: its ON and OFF arrivals
  are independent but for the refractory period and the regular timer they share, which make close
  pairs rarer, never commoner (the test is one-sided). Windows shorter than 80 pair gaps (4 s) have
  no room for that range: the offsets then run from ``max(2, D/2 - 30)`` gaps to half the window
  ``D/2`` (a 1 s window: 0.1 to 0.5 s either way, i.e. every circular lag from 2 gaps to ``D`` - 2
  gaps). Two gaps is the least lag after which a pair within one gap is at least a gap apart (also
  across the wrap), and under stationary independent streams a circular shift of one stream by any
  lag leaves the pair count's distribution unchanged, so every such lag is a valid resample. A
  single lag (``D/2``, what a first version used on a 1 s window) gives a null without spread and a
  check that could not fail (p stopped at ``1 / (1 + shifts)``). Where the lags span fewer than 4
  gaps (windows shorter than 12 gaps, 0.6 s) the ON events of each pixel are instead placed
  uniformly at random in the window, keeping the pixel's ON count: the exact conditional null of
  stationary Poisson streams (given its count, a Poisson stream's times are independent and
  uniform), and, as quiet pixels hold a few events at most in so short a window, close to that of
  the model's regular or refractory streams, which again only make pairs rarer. A window no longer
  than the pair gap cannot be tested (every OFF/ON pair of a pixel is within the gap: the pixels'
  counts fix the statistic);
- **stationarity**: the window's events in ``pieces`` equal time slices against equal shares
  (Pearson chi-square on ``pieces - 1`` degrees of freedom; the pixels' streams are independent, so
  the total over many pixels is close to Poisson: a rate that drifts shows up here);
- **scene motion**: the counts of ``block`` x ``block`` pixel blocks in ``pieces`` time slices,
  Pearson's chi-square of independence of block and slice, against the same statistic after each
  pixel's whole stream is shifted circularly in time (``shifts`` times). A still scene's noise may
  follow the scene (the rate depends on the illuminance: that is the spread's business) and may
  drift as a whole (the slice margin), but its pattern does not change; a structure that sweeps the
  sensor (a slow edge, a domain wall, a person shifting) shows up here, and so does a drift that is
  not the same factor for every pixel (e.g. ordinary pixels speeding up while hot pixels do not).

Two tests of timing are not checks of the window but of the fitted model (the fit's goodness report,
``QuietFit.timing``, :func:`evnoise.calibration.quiet.goodness.timing_tests`); the window's events
for them are gathered here (:func:`same_pixel_timing`, kept in the polarity pairs' dict as ``same_pixel``):

- **polarity transitions**: of a pixel's consecutive events, how many are opposite in polarity,
  against what a memoryless model predicts. The fit's model draws each event's polarity
  independently with the pixel's ON share (whatever its arrival times), so given a pixel's ``n_on``
  ON and ``n_off`` OFF events their order is a uniformly random arrangement: the number of opposite
  transitions has mean ``2 n_on n_off / n`` and variance ``2 n_on n_off (2 n_on n_off - n) / (n^2 (n - 1))``
  (Wald-Wolfowitz runs, ``n = n_on + n_off``), exactly, for any per-pixel ON share (the ``2 q (1 - q)``
  per transition, with ``q`` taken from the pixel's own counts). Summed over the pixels (independent),
  a two-sided normal test: real quiet pixels alternate (93 % opposite, issue 32) where the model says
  about 50 %. A model with reset memory predicts its own ``p_opposite``
  (:func:`evnoise.terms.memory.memory_statistics`): pass it to :func:`polarity_transitions` for a
  binomial test instead. Fewer than :data:`MIN_INTERVALS` transitions: not testable ("not enough
  intervals");
- **inter-event intervals**: the same pass collects the pixels' inter-event intervals (``intervals_s``,
  at most :data:`STORED_INTERVALS` order statistics, and ``n_intervals``), which the fit's goodness
  report tests against the fitted model's distribution (a KS test).

And one for information, not an assumption of the fit:

- **spatial structure**: the variance of the mean count of ``block`` x ``block`` pixel blocks
  against the same variance after the pixels' count pairs are permuted over the sensor
  (``shifts`` permutations). A still scene's noise has the scene's structure (noise rate depends
  on the illuminance) or the sensor's (vignetting); the fit's spread absorbs it, since the
  per-pixel count histograms do not depend on where a pixel sits.

Each check is a dict ``{check, statistic, null_mean, null_sd, p_value, assumption, detail}`` (and
``testable: False`` where the window holds nothing to test, e.g. no OFF events for the pairs: such a check
neither passes nor fails; :func:`check_verdict` words a result with its threshold); p-values from
resampling are ``(1 + #(null >= observed)) / (1 + resamples)``; where the observed value lies beyond
every resample, the tail of a gamma distribution with the resamples' mean and variance is given
instead when it is smaller (right-skewed like the counts and chi-square statistics here; approximate),
so that p-values below ``1 / (1 + shifts)`` can be stated. With 200 resamples, checks of simulated
noise failed at ``CHECK_P`` about as often as they should (tests/test_quiet_checks.py).
"""

from __future__ import annotations

import math

import numpy as np

from evnoise._clock import seconds_text

__all__ = ["window_checks", "failed_checks", "check_verdict", "polarity_pairs", "same_pixel_timing",
           "stored_order_statistics",
           "polarity_transitions", "stationarity", "stationary_span", "scene_motion", "spatial_structure",
           "PAIR_GAP_S", "CHECK_P", "MIN_INTERVALS", "STORED_INTERVALS"]

#: Largest gap (seconds) between a pixel's OFF and ON events counted as a pair.
PAIR_GAP_S = 0.05
#: p-value below which a check is reported as failed.
CHECK_P = 1e-3
#: Fewest same-pixel intervals (consecutive events of one pixel) for the timing tests.
MIN_INTERVALS = 100
#: Most order statistics of the intervals kept in a check's ``intervals_s`` (evenly spaced in rank; all of
#: them up to this many): bounds what a window's checks hold; the KS statistic from them is within
#: ``1 / STORED_INTERVALS`` of the full sample's.
STORED_INTERVALS = 5000


def _resampled(observed: float, null: np.ndarray) -> tuple:
    """Mean, sd and p-value of ``observed`` against resamples ``null`` (module doc)."""
    from scipy.stats import gamma

    null = np.asarray(null, dtype=np.float64)
    mean = float(null.mean())
    sd = float(null.std(ddof=1)) if null.size > 1 else 0.0
    above = np.count_nonzero(null >= observed)
    p = (1.0 + above) / (1.0 + null.size)
    if above == 0 and sd > 0 and mean > 0:  # beyond every resample: a moment-matched gamma tail, if smaller
        shape = (mean / sd) ** 2
        p = min(p, float(gamma.sf(observed, shape, scale=mean / shape)))
    return mean, sd, float(p)


def _result(name: str, observed: float, null: np.ndarray, describe, *, assumption: bool = True) -> dict:
    """A check's dict; ``describe(mean, sd)`` writes its detail."""
    mean, sd, p = _resampled(observed, null)
    return {"check": name, "statistic": observed, "null_mean": mean, "null_sd": sd, "p_value": p,
            "assumption": assumption, "detail": describe(mean, sd)}


def _times(observed: float, mean: float) -> str:
    """``observed`` against the resamples' ``mean`` in words: ``"2.6 times"``, ``"none"`` (no resample had any)."""
    if mean > 0:
        return f"{observed / mean:.3g} times"
    return "none" if observed == 0 else "some (none)"


def check_verdict(check: dict, *, p: float = CHECK_P) -> str:
    """``"passed (p = 0.41 >= 0.001)"``, ``"FAILED (p = 8e-05 < 0.001)"``, ``"information (p = ...)"`` or
    ``"not testable"``: the p-value always with the threshold it is compared with.

    Parameters
    ----------
    check : dict
        One check's dict (module doc): its ``p_value``, ``assumption`` and, where present, ``testable``
        are read.
    p : float, default CHECK_P
        Threshold below which an assumption check fails.

    Returns
    -------
    str
        The verdict in words.
    """
    if check.get("testable") is False:
        return "not testable"
    pv = check["p_value"]
    if not check["assumption"]:
        return f"information (p = {pv:.3g}; not a test of the fit's assumptions)"
    if pv < p:
        return f"FAILED (p = {pv:.3g} < {p:g})"
    return f"passed (p = {pv:.3g} >= {p:g})"


def _pairs_within(off_key: np.ndarray, on_key: np.ndarray, gap: int) -> int:
    """Pairs (OFF, ON) of one pixel with ``|t_on - t_off| <= gap``; keys are ``pixel * stride + t`` sorted."""
    hi = np.searchsorted(on_key, off_key + gap, side="right")
    lo = np.searchsorted(on_key, off_key - gap, side="left")
    return int(np.sum(hi - lo))


def _no_tick() -> None:
    pass


def _pair_lags(gap: int, duration_us: int) -> tuple:
    """``(lo, hi)`` of the ON streams' circular shifts (module doc), or ``None`` where the window has no room
    for lags spanning 4 gaps (the ON events are then placed at random)."""
    hi = min(40 * gap, duration_us // 2)
    lo = min(10 * gap, max(2 * gap, hi - 30 * gap))
    return (lo, hi) if hi - lo >= 4 * gap else None


def polarity_pairs(events: np.ndarray, shape: tuple, t_start_us: int, duration_us: int, *,
                   pair_gap_s: float = PAIR_GAP_S, shifts: int = 200, seed: int = 0, tick=_no_tick) -> dict:
    """OFF/ON pairs of a pixel closer than ``pair_gap_s`` against circularly shifted ON streams, or ON events
    placed at random in windows too short for the shifts (module doc); ``tick()`` is called after each
    resample (progress)."""
    width = int(shape[1])
    gap = max(1, int(round(pair_gap_s * 1e6)))
    duration_us = max(int(duration_us), 1)
    stride = 2 * duration_us + 4 * gap + 1  # keys of different pixels never come within gap
    lags = _pair_lags(gap, duration_us)
    pix = events["y"].astype(np.int64) * width + events["x"].astype(np.int64)
    t = events["t"].astype(np.int64) - int(t_start_us)
    on = events["p"] == 1
    off_key = np.sort(pix[~on] * stride + t[~on])
    on_pix, on_t = pix[on], t[on]
    observed = _pairs_within(off_key, np.sort(on_pix * stride + on_t), gap)
    n_on, n_off = int(on.sum()), int((~on).sum())
    if duration_us <= gap:
        return {"check": "polarity_pairs", "statistic": observed, "null_mean": float(observed), "null_sd": 0.0,
                "p_value": float("nan"), "assumption": True, "testable": False,
                "detail": (f"the window ({duration_us / 1e6:.3g} s) is no longer than the pair gap "
                           f"({pair_gap_s * 1e3:g} ms): every OFF/ON pair of a pixel is within it, so the pixels' "
                           f"counts fix the {observed} pairs ({n_off} OFF and {n_on} ON events)")}
    rng = np.random.default_rng(seed)
    n_pix = int(shape[0]) * width
    null = np.empty(int(shifts))
    for k in range(int(shifts)):
        if lags is None:
            shifted = rng.integers(0, duration_us, size=on_t.size)
        else:
            offset = rng.integers(lags[0], lags[1] + 1, size=n_pix) * rng.choice(np.array([-1, 1]), size=n_pix)
            shifted = (on_t + offset[on_pix]) % duration_us
        null[k] = _pairs_within(off_key, np.sort(on_pix * stride + shifted), gap)
        tick()
    if lags is None:
        how = (f"each pixel's ON events placed at random in the window (too short, {duration_us / 1e6:.3g} s, "
               f"for circular shifts over {4 * pair_gap_s:g} s of lags)")
    else:
        how = f"each pixel's ON stream shifted by {lags[0] / 1e6:.3g} to {lags[1] / 1e6:.3g} s either way"
    out = _result("polarity_pairs", observed, null, lambda mean, sd: (
        f"{observed} OFF/ON pairs of one pixel within {pair_gap_s * 1e3:g} ms, {mean:.1f} +- {sd:.1f} with "
        f"{how} ({_times(observed, mean)} as many; {int(shifts)} resamples)"))
    if observed == 0 and not np.any(null):
        out["testable"] = False
        out["detail"] = (f"no OFF/ON pairs of one pixel within {pair_gap_s * 1e3:g} ms, shifted or not "
                         f"({n_off} OFF and {n_on} ON events): nothing to compare")
    return out


def stored_order_statistics(intervals: np.ndarray) -> np.ndarray:
    """The order statistics kept of sorted ``intervals``: all of them, or :data:`STORED_INTERVALS` evenly spaced
    ones (ranks ``round(linspace(0, n - 1, STORED_INTERVALS))``)."""
    if intervals.size > STORED_INTERVALS:
        return intervals[np.round(np.linspace(0, intervals.size - 1, STORED_INTERVALS)).astype(np.int64)]
    return intervals


def same_pixel_timing(events: np.ndarray, shape: tuple) -> dict:
    """Consecutive events of one pixel (module doc, polarity transitions): how many, how many opposite in
    polarity, the memoryless model's mean and sd of that number given the pixels' ON/OFF counts, and the
    intervals (``intervals_s``: at most :data:`STORED_INTERVALS` order statistics of ``n_intervals``)."""
    width = int(shape[1])
    pix = events["y"].astype(np.int64) * width + events["x"].astype(np.int64)
    t = events["t"].astype(np.int64)
    order = np.lexsort((t, pix))
    pix, t, on = pix[order], t[order], (events["p"] == 1)[order]
    same = pix[1:] == pix[:-1]
    n_trans = int(np.count_nonzero(same))
    observed = int(np.count_nonzero(same & (on[1:] != on[:-1])))
    intervals = stored_order_statistics(np.sort((t[1:] - t[:-1])[same] * 1e-6))
    n_pix = int(shape[0]) * width
    n_on = np.bincount(pix[on], minlength=n_pix).astype(np.float64)
    n = np.bincount(pix, minlength=n_pix).astype(np.float64)
    two = n >= 2
    prod = 2.0 * n_on[two] * (n[two] - n_on[two])
    mean = float(np.sum(prod / n[two]))
    var = float(np.sum(prod * (prod - n[two]) / (n[two] ** 2 * (n[two] - 1.0))))
    return {"transitions": n_trans, "opposite": observed, "memoryless_mean": mean,
            "memoryless_sd": float(np.sqrt(max(var, 0.0))), "n_intervals": n_trans,
            "intervals_s": [float(x) for x in intervals]}


def polarity_transitions(timing: dict, *, p_opposite: float | None = None) -> dict:
    """Opposite-polarity transitions of consecutive same-pixel events (``timing`` from
    :func:`same_pixel_timing`) against a memoryless model (module doc), or against ``p_opposite`` (a
    binomial test): ``{test, statistic, null_mean, null_sd, p_value, testable, opposite_share, transitions,
    detail}``.

    The memoryless expectation is exact given each pixel's counts (polarity does not depend on timing). A
    model with memory is different: its same-polarity pairs are further apart than its opposite pairs, so a
    window's end cuts more of them and the share of opposite pairs seen in a window of ``T`` seconds is
    higher than the stationary ``p_opposite`` by about ``p_opposite (mean gap - mean opposite gap) / T``
    (+0.006 for a 6 s window of a dvs128-like pixel with ``reset_memory = 0.7``). Give a ``p_opposite`` that
    includes that cut (``tests/test_memory_term.py`` computes it from ``memory_iei_cdf``) or a window long
    enough for it not to matter."""
    from scipy.stats import binomtest, norm

    n_trans, observed = int(timing["transitions"]), int(timing["opposite"])
    mean, sd = float(timing["memoryless_mean"]), float(timing["memoryless_sd"])
    share = observed / n_trans if n_trans else float("nan")
    out = {"test": "polarity_transitions", "statistic": observed, "null_mean": mean, "null_sd": sd,
           "p_value": float("nan"), "testable": False, "opposite_share": share, "transitions": n_trans}
    if n_trans < MIN_INTERVALS:
        out["detail"] = (f"not enough intervals: {n_trans} pairs of consecutive events of one pixel "
                         f"(< {MIN_INTERVALS}), {observed} of them opposite in polarity")
        return out
    if p_opposite is not None:
        out["null_mean"] = float(p_opposite) * n_trans
        out["null_sd"] = float(np.sqrt(n_trans * p_opposite * (1.0 - p_opposite)))
        out["p_value"] = float(binomtest(observed, n_trans, float(p_opposite)).pvalue)
        how = f"the model's p_opposite {p_opposite:.3g}; binomial test"
    elif sd <= 0:
        out["detail"] = (f"{observed} of {n_trans} consecutive same-pixel events opposite in polarity, but no pixel "
                         f"has events of both polarities: the order says nothing")
        return out
    else:
        out["p_value"] = float(2.0 * norm.sf(abs(observed - mean) / sd))
        how = "memoryless polarities given each pixel's ON/OFF counts; two-sided normal test"
    out["testable"] = True
    out["detail"] = (f"{observed} of {n_trans} consecutive same-pixel events opposite in polarity "
                     f"({100 * share:.1f} %), model {out['null_mean']:.1f} +- {out['null_sd']:.1f} "
                     f"({100 * out['null_mean'] / n_trans:.1f} %; {how})")
    return out


#: :func:`stationary_span` looks for the longest stretch of a window, on a grid of this many steps, that passes the
#: stationarity check alone ...
SPAN_STEPS = 40
#: ... and at least this share of the window long (a shorter one is no window to suggest)
SPAN_MIN_SHARE = 0.5


def _stationarity_p(t_sorted: np.ndarray, a: float, b: float, pieces: int) -> float:
    """The stationarity check's p-value of the events ``t_sorted`` (sorted) within ``[a, b)``."""
    from scipy.stats import chi2

    counts = np.diff(np.searchsorted(t_sorted, np.linspace(a, b, pieces + 1), side="left")).astype(np.float64)
    expected = counts.sum() / pieces
    if expected <= 0:
        return 1.0
    return float(chi2.sf(float(np.sum((counts - expected) ** 2 / expected)), pieces - 1))


def stationary_span(events: np.ndarray, t_start_us: int, duration_us: int, *, pieces: int = 4,
                    p: float = CHECK_P) -> tuple | None:
    """The longest stretch ``(start_us, end_us)`` of the window, its ends on a grid of :data:`SPAN_STEPS` steps and
    at least :data:`SPAN_MIN_SHARE` of it long, whose events pass the stationarity check (``pieces`` slices, p >=
    ``p``); the earliest of equally long ones; None if none does. A suggestion for a window to check again (it is
    chosen among many, so its own p-value is optimistic), not a test."""
    t = np.sort(events["t"].astype(np.int64) - int(t_start_us)).astype(np.float64)
    step = max(int(duration_us), 1) / SPAN_STEPS
    for length in range(SPAN_STEPS, int(math.ceil(SPAN_MIN_SHARE * SPAN_STEPS)) - 1, -1):
        for first in range(SPAN_STEPS - length + 1):
            a, b = first * step, (first + length) * step
            if _stationarity_p(t, a, b, pieces) >= p:
                return int(t_start_us + round(a)), int(t_start_us + round(b))
    return None


def stationarity(events: np.ndarray, t_start_us: int, duration_us: int, *, pieces: int = 4) -> dict:
    """Events in ``pieces`` equal time slices against equal shares (Pearson chi-square). Where it fails, the
    longest stretch of the window that passes (:func:`stationary_span`) is named in the detail and kept as
    ``span_us`` (absent if none)."""
    from scipy.stats import chi2

    t = events["t"].astype(np.int64) - int(t_start_us)
    duration_us = max(int(duration_us), 1)
    idx = np.minimum(t * pieces // duration_us, pieces - 1)
    observed = np.bincount(idx, minlength=pieces).astype(np.float64)
    expected = observed.sum() / pieces
    stat = float(np.sum((observed - expected) ** 2 / expected)) if expected > 0 else 0.0
    rate = observed / (duration_us * 1e-6 / pieces)
    p_value = float(chi2.sf(stat, pieces - 1))
    out = {"check": "stationarity", "statistic": stat, "null_mean": float(pieces - 1),
           "null_sd": float(np.sqrt(2.0 * (pieces - 1))), "p_value": p_value, "assumption": True,
           "detail": f"events/s in {pieces} slices: " + ", ".join(f"{r:.4g}" for r in rate)}
    if p_value < CHECK_P:
        span = stationary_span(events, t_start_us, duration_us, pieces=pieces)
        if span is not None:  # (no key where none passes: a preset's TOML has no null)
            out["span_us"] = list(span)
        out["detail"] += ("; no stretch of at least half the window passes this check" if span is None else
                          f"; the longest stretch that passes it alone: {seconds_text(span[0] * 1e-6)}-"
                          f"{seconds_text(span[1] * 1e-6)} s "
                          "(a suggestion: check it again)")
    return out


def _block_index(shape: tuple, block: int) -> tuple:
    """Block number of every pixel (``-1`` outside the whole blocks) and the number of blocks."""
    h, w = int(shape[0]), int(shape[1])
    nby, nbx = h // block, w // block
    by = np.arange(h) // block
    bx = np.arange(w) // block
    idx = by[:, None] * nbx + bx[None, :]
    idx[(by >= nby)[:, None] | (bx >= nbx)[None, :]] = -1
    return idx.ravel(), nby * nbx


def _block_size(shape: tuple, block: int) -> int:
    return max(1, min(int(block), min(int(shape[0]), int(shape[1])) // 2 or 1))


def _block_variance(total: np.ndarray, index: np.ndarray, n_blocks: int) -> float:
    inside = index >= 0
    sums = np.bincount(index[inside], weights=total[inside], minlength=n_blocks)
    return float(sums.var())


def spatial_structure(counts: np.ndarray, *, block: int = 16, shifts: int = 200, seed: int = 0,
                      tick=_no_tick) -> dict:
    """Variance of ``block`` x ``block`` mean counts against permutations of the pixels (module doc)."""
    total = np.asarray(counts).sum(axis=0).astype(np.float64)
    block = _block_size(total.shape, block)
    index, n_blocks = _block_index(total.shape, block)
    flat = total.ravel()
    observed = _block_variance(flat, index, n_blocks)
    rng = np.random.default_rng(seed)
    null = np.empty(int(shifts))
    for k in range(int(shifts)):
        null[k] = _block_variance(rng.permutation(flat), index, n_blocks)
        tick()
    return _result("spatial_structure", observed, null, lambda mean, sd: (
        f"variance of {block}x{block}-block counts {_times(observed, mean)} that of pixels placed at random "
        f"({int(shifts)} permutations; the noise follows the scene or the optics)"), assumption=False)


def _independence_chi2(block_id: np.ndarray, slice_id: np.ndarray, n_blocks: int, pieces: int) -> float:
    table = np.bincount(block_id * pieces + slice_id, minlength=n_blocks * pieces).reshape(n_blocks, pieces)
    table = table[table.sum(axis=1) > 0].astype(np.float64)
    col = table.sum(axis=0)
    table = table[:, col > 0]
    if table.size == 0 or table.shape[1] < 2:
        return 0.0
    expected = np.outer(table.sum(axis=1), table.sum(axis=0)) / table.sum()
    return float(np.sum((table - expected) ** 2 / expected))


def scene_motion(events: np.ndarray, shape: tuple, t_start_us: int, duration_us: int, *, block: int = 16,
                 pieces: int = 4, shifts: int = 200, seed: int = 0, tick=_no_tick) -> dict:
    """Block x time-slice independence against per-pixel circular time shifts (module doc)."""
    block = _block_size(shape, block)
    index, n_blocks = _block_index(shape, block)
    width = int(shape[1])
    duration_us = max(int(duration_us), 1)
    pix = events["y"].astype(np.int64) * width + events["x"].astype(np.int64)
    blk = index[pix]
    inside = blk >= 0
    pix, blk = pix[inside], blk[inside]
    t = events["t"][inside].astype(np.int64) - int(t_start_us)
    observed = _independence_chi2(blk, np.minimum(t * pieces // duration_us, pieces - 1), n_blocks, pieces)
    rng = np.random.default_rng(seed)
    n_pix = int(shape[0]) * width
    null = np.empty(int(shifts))
    for k in range(int(shifts)):
        shifted = (t + rng.integers(0, duration_us, size=n_pix)[pix]) % duration_us
        null[k] = _independence_chi2(blk, shifted * pieces // duration_us, n_blocks, pieces)
        tick()
    return _result("scene_motion", observed, null, lambda mean, sd: (
        f"block x time chi-square of {block}x{block} blocks in {pieces} slices {_times(observed, mean)} that of "
        f"the pixels' streams shifted in time ({int(shifts)} circular shifts)"))


def window_checks(events: np.ndarray, counts: np.ndarray, t_start_us: int, duration_us: int, *,
                  shifts: int = 200, seed: int = 0, progress: bool = False, desc: str = "quiet checks") -> list:
    """The checks of one window (module doc): polarity pairs, stationarity, scene motion, spatial structure.

    The polarity pairs' dict also carries the window's same-pixel timing (``same_pixel``:
    :func:`same_pixel_timing`), which the fit's timing tests use (:func:`.goodness.timing_tests`).

    ``progress``: a bar over the resamples of the three resampled checks (about 15 s per million events).
    """
    shape = counts.shape[1:]
    bar = None
    tick = _no_tick
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=3 * int(shifts), desc=desc, unit="resample", leave=False)
        tick = bar.update
    try:
        pairs = polarity_pairs(events, shape, t_start_us, duration_us, shifts=shifts, seed=seed, tick=tick)
        pairs["same_pixel"] = same_pixel_timing(events, shape)
        return [pairs,
                stationarity(events, t_start_us, duration_us),
                scene_motion(events, shape, t_start_us, duration_us, shifts=shifts, seed=seed, tick=tick),
                spatial_structure(counts, shifts=shifts, seed=seed, tick=tick)]
    finally:
        if bar is not None:
            bar.close()


def failed_checks(checks: list, *, p: float = CHECK_P) -> list:
    """The assumption checks (not the information ones) whose p-value is below ``p``.

    Parameters
    ----------
    checks : list of dict
        Check dicts (module doc), e.g. from :func:`window_checks`; those marked ``testable: False`` never fail.
    p : float, default CHECK_P
        Threshold below which a check fails.

    Returns
    -------
    list of dict
        The failed checks, in the order given.
    """
    return [c for c in checks if c["assumption"] and c.get("testable", True) and c["p_value"] < p]
