"""The quiet fit's timing likelihood (issue 32 section 2): each pixel's event times in a window as a
stationary renewal process, checked against the count distribution it must integrate to, and fitted on
event times simulated from a known renewal process."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evnoise.calibration.quiet import counts as qn
from evnoise.calibration.quiet import fit as q
from evnoise.calibration.quiet import likelihood as ql
from evnoise.calibration.quiet import timing as qt
from evnoise.calibration.quiet import window as qw
from evnoise.events import EVENT_DTYPE


def _one_pixel_window(times_s, pols, T):
    """A 1x1 window holding one pixel's events (``pols``: 1 ON, 0 OFF)."""
    ev = np.zeros(len(times_s), dtype=EVENT_DTYPE)
    ev["t"] = np.round(np.asarray(times_s) * 1e6).astype(np.int64)
    ev["p"] = pols
    counts = np.zeros((2, 1, 1), dtype=np.int64)
    counts[0, 0, 0] = int(np.sum(np.asarray(pols) == 1))
    counts[1, 0, 0] = int(np.sum(np.asarray(pols) == 0))
    return qw.QuietWindow(counts, T, "px", events=qw.window_events(ev, (1, 1), 0))


def _density(times_s, pols, T, rate, r, share_on=0.7):
    """The model's density of one pixel's events (no spread, no hot pixels) through the likelihood."""
    w = _one_pixel_window(times_s, pols, T)
    groups = ql.window_groups([w])
    model = ql.Model(False, False, [np.zeros((1, 2))], False, [np.zeros(1)], r > 0, True)
    theta = [math.log(rate * share_on), math.log(rate * (1 - share_on))] + ([q._logit(r)] if r > 0 else [])
    return math.exp(ql.mixture_log_likelihood(np.array(theta), model, groups))


def _densities(times, T, rate, r, share_on):
    """The model's density (no spread, no hot pixels) of each pixel's ON events at ``times`` (P, k) seconds,
    through the timing likelihood: one window of P pixels."""
    times = np.asarray(times, dtype=np.float64)
    n_pix, k = times.shape
    ev = np.zeros(n_pix * k, dtype=EVENT_DTYPE)
    width = 1000
    shape = (-(-n_pix // width), width)
    pix = np.repeat(np.arange(n_pix), k)
    ev["t"] = np.round(times.ravel() * 1e6).astype(np.int64)
    ev["x"], ev["y"] = pix % width, pix // width
    ev["p"] = 1
    counts = np.zeros((2, shape[0] * width), dtype=np.int64)
    counts[0, :n_pix] = k
    w = qw.QuietWindow(counts.reshape(2, *shape), T, "px", events=qw.window_events(ev, shape, 0))
    grp = ql.window_groups([w])[0]
    act = qt.log_point_density([rate * share_on], [rate * (1 - share_on)], grp.timing, r)
    return np.exp(act[:n_pix])  # the pixels with events come first (then the silent ones' column)


@pytest.mark.parametrize("r", [0.0, 0.4, 0.85])
@pytest.mark.long
def test_event_time_density_integrates_to_the_count_pmf(r):
    # P(N = 0) directly, P(N = 1) and P(N = 2) by integrating the density over the event times (trapezoid rules on
    # fine grids: the density jumps where a gap passes r / rate, so the error is O(grid step)), against the
    # renewal count distribution's closed form (incomplete gamma functions, counts.count_pmf)
    T, rate, share = 2.0, 1.3, 0.7
    pmf = qn.count_pmf(3, rate, T, r)
    assert _density([], [], T, rate, r, share) == pytest.approx(pmf[0], rel=1e-9, abs=1e-12)
    t = np.linspace(0.0, T - 1e-6, 20001)
    p1 = np.trapezoid(_densities(t[:, None], T, rate, r, share), t) / share
    assert p1 == pytest.approx(pmf[1], rel=1e-3)
    n = 1200
    a = (np.arange(n) + 0.5) / n * T  # midpoint rule in a, and in u for b = a + u (T - a)
    u = (np.arange(n) + 0.5) / n
    A, U = np.meshgrid(a, u, indexing="ij")
    B = A + U * (T - A)
    dens = _densities(np.stack([A.ravel(), B.ravel()], axis=1), T, rate, r, share).reshape(n, n)
    p2 = float(np.sum(dens * (T - A)) * (T / n) * (1.0 / n)) / share ** 2
    assert p2 == pytest.approx(pmf[2], rel=5e-3)


def test_poisson_event_times_have_the_poisson_density():
    # r = 0: rate_on^k_on rate_off^k_off exp(-rate T), whatever the times
    T, rate, share = 3.0, 0.8, 0.6
    got = _density([0.2, 1.1, 2.9], [1, 0, 1], T, rate, 0.0, share)
    want = (rate * share) ** 2 * (rate * (1 - share)) * math.exp(-rate * T)
    assert got == pytest.approx(want, rel=1e-10)


def _renewal_window(rng, shape, T, rate, r, share_on, sigma=0.0):
    """Events of a stationary renewal process (gaps r mu + Exp((1 - r) mu)) in every pixel of ``shape``, each
    pixel's rate ``rate`` times a log-normal factor of mean 1 (log sd ``sigma``)."""
    n_pix = shape[0] * shape[1]
    mu = 1.0 / (rate * np.exp(-0.5 * sigma * sigma + sigma * rng.standard_normal(n_pix)))
    # the stationary forward recurrence time: with probability r uniform on [0, r mu), else r mu + Exp
    u = rng.random(n_pix)
    first = np.where(rng.random(n_pix) < r, u * r * mu, r * mu + rng.exponential((1 - r) * mu, n_pix))
    ts = []
    for i in range(n_pix):
        t = first[i]
        while t < T:
            ts.append((int(t * 1e6), i))
            t += r * mu[i] + rng.exponential((1 - r) * mu[i])
    t_us = np.array([a for a, _ in ts], dtype=np.int64)
    pix = np.array([b for _, b in ts], dtype=np.int64)
    ev = np.zeros(t_us.size, dtype=EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"] = t_us, pix % shape[1], pix // shape[1]
    ev["p"] = (rng.random(t_us.size) < share_on).astype(np.uint8)
    ev = np.sort(ev, order="t")
    from evnoise.events import count_events

    counts = count_events(ev, shape)
    return qw.QuietWindow(counts, T, "sim", events=qw.window_events(ev, shape, 0))


def test_timing_fit_recovers_a_known_regularity():
    # pixels with a log-normal spread of rates (sigma 0.5): the fit of the event times finds the regularity,
    # the rates and the spread within 4 standard errors. (Without a spread the shift r / rate of the gaps is a
    # non-regular parameter, its maximum at the shortest gap, and the observed information gives no error.) Once
    # a strict xfail: each pixel's integral over the spread was a sum over a fixed 241-node grid, far coarser
    # than the spike of a regular pixel's integrand, so the likelihood jumped as the cut r / rate crossed the
    # nodes and its numerical Hessian was not positive definite (the per-pixel quadrature of .timing since)
    rng = np.random.default_rng(2026)
    w = _renewal_window(rng, (24, 24), 6.0, 0.5, 0.6, 0.8, sigma=0.5)
    fit = q.fit_quiet([w], spread="on", hot="off", regularity="on", timing="on")
    for name, want in (("regularity", 0.6), ("rate_on_hz", 0.4), ("rate_off_hz", 0.1), ("sigma", 0.5)):
        se = fit.std_error[name]
        assert se is not None and se > 0, (name, fit.status)
        assert abs(fit.values[name] - want) < 4 * se, (name, fit.values[name], se)


def test_doublets_are_merged():
    ev = np.zeros(5, dtype=EVENT_DTYPE)
    ev["t"] = [0, 1, 2, 30, 40]
    ev["x"] = [0, 0, 1, 0, 0]
    ev["p"] = [1, 1, 1, 0, 1]
    out, merged = qw.merge_doublets(ev, 2, 10)
    # the ON at 1 us (1 us after an ON of its pixel) goes; the other pixel, the OFF and the ON 40 us after go not
    assert merged == 1
    assert out["t"].tolist() == [0, 2, 30, 40]
    assert qw.merge_doublets(ev, 2, 0)[1] == 0


REALDATA = __import__("pathlib").Path(__file__).resolve().parents[2] / "shared" / "data" / "realdata"
needs_realdata = pytest.mark.skipif(not (REALDATA / "quiet_segments.json").is_file(),
                                    reason=f"real recordings not found at {REALDATA}")


@needs_realdata
@pytest.mark.long
def test_the_count_fits_periodic_timer_is_impossible_for_the_event_times():
    # the cleanest DVS128 window: the count fit's near-periodic leak (r = 1) gives its own window's event times
    # likelihood 0 in practice (gaps far shorter than r / rate in the active pixels: only pixels of rates far out in
    # the spread's tail, beyond its 7th sd, could make them), a Poisson background does not
    import json

    from evnoise.calibration.quiet.fit import event_time_log_likelihood as timing_log_likelihood

    segments = json.loads((REALDATA / "quiet_segments.json").read_text(encoding="utf-8"))["segments"]
    rel = "dvs128dataanalysis/cam255_neal_standing_up2.aedat"
    seg = segments[rel][0]
    w = qw.quiet_window(REALDATA / rel, seg["t_from_us"] * 1e-6, seg["t_to_us"] * 1e-6)
    counts_fit = q.fit_quiet([w], hot="off", timing="off")
    assert counts_fit.values["regularity"] > 0.9
    poisson = q.fit_quiet([w], hot="off", regularity="off", spread="off", timing="off")
    assert math.isfinite(timing_log_likelihood(poisson))
    assert timing_log_likelihood(counts_fit) < timing_log_likelihood(poisson) - 1e6


def test_a_fits_event_time_likelihood_is_its_own_at_a_bound():
    # event_time_log_likelihood evaluates a fit's values: a spread fitted to ~0 (Poisson pixels of one rate) was
    # floored at 0.05 on its way back to coordinates, so a timing fit's event-time log-likelihood differed from the
    # maximum it had reached (a real window: -1389.1 against -1388.5). Three events in every pixel: counts less
    # dispersed than Poisson, so the spread's maximum is at its end, 0
    rng = np.random.default_rng(3)
    shape, T = (32, 32), 4.0
    n = np.full(shape[0] * shape[1], 3)
    pix = np.repeat(np.arange(n.size), n)
    ev = np.zeros(pix.size, dtype=EVENT_DTYPE)
    ev["t"] = np.round(rng.uniform(0.0, T, pix.size) * 1e6).astype(np.int64)
    ev["x"], ev["y"], ev["p"] = pix % shape[1], pix // shape[1], rng.random(pix.size) < 0.6
    ev = ev[np.argsort(ev["t"], kind="stable")]
    counts = np.zeros((2, n.size), dtype=np.int64)
    np.add.at(counts, (1 - ev["p"].astype(np.int64), ev["y"].astype(np.int64) * shape[1] + ev["x"]), 1)
    w = qw.QuietWindow(counts.reshape(2, *shape), T, "sim", events=qw.window_events(ev, shape, 0))
    fit = q.fit_quiet([w], timing="on", spread="on", hot="off", regularity="off")
    assert fit.values["sigma"] < 0.05  # the case: the spread's maximum below the starts' floor
    assert q.event_time_log_likelihood(fit) == pytest.approx(fit.log_likelihood, rel=1e-12, abs=1e-9)
