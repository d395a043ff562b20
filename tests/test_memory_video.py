"""Reset memory in the trial tier: ``simulate_events(method="trials")`` and changing scenes (``simulate_video``).

The trial tier compares counts trial by trial; with ``reset_memory = k`` a share ``k`` of the comparisons take the
pixel's stored count as the reference (module doc of :mod:`evnoise.terms.memory`). Checked against the memory
closed form (:func:`~evnoise.terms.memory.memory_statistics`, a linear solve) on static pixels, against the renewal
tier bit for bit where a video does not change, and against a plain NumPy per-trial simulation of a step of light
(signal events included). Tolerances are k-sigma with sigmas from per-pixel totals (pixels are independent).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy import stats

import evnoise as ev
from evnoise.terms import memory
from test_memory_term import (
    BG,
    BG_LUX,
    K_SIGMA,
    MEM,
    _assert_phase_agrees,
    _check_against_closed_form,
    _ratio,
    _summaries,
)


def _pix_t_p(e, width):
    return e["y"].astype(np.int64) * width + e["x"], e["t"].astype(np.float64), e["p"]


@pytest.mark.parametrize("params, lux_value", [(MEM, 2.0), (BG, BG_LUX)], ids=["memory", "memory-and-background"])
@pytest.mark.long
def test_trial_tier_with_memory_against_the_closed_form(params, lux_value):
    """Static pixels in the trial tier: rate, ON share, alternation, transition matrix, mean intervals per polarity
    pair, and each pair's interval distribution (KS against the closed-form CDF)."""
    shape, duration_s = (20, 30), (4.0 if params is MEM else 60.0)
    e = ev.simulate_events(np.full(shape, lux_value), params, duration_s, rng=31, method="trials")
    pix, t, p = _pix_t_p(e, shape[1])
    s = _summaries(pix, t, p, shape[0] * shape[1])
    st = memory.memory_statistics(lux_value, params)
    assert s["trans"].sum() > 5000
    _check_against_closed_form(s, st, duration_s, shape[0] * shape[1])
    for a in (0, 1):
        for b in (0, 1):
            gaps = s["gaps", a, b] * 1e-6
            p_ks = stats.kstest(gaps, lambda x: memory.memory_iei_cdf(x, lux_value, params)[a, b]).pvalue
            assert p_ks > 1e-3, (a, b, p_ks)


def test_trial_tier_with_memory_starts_in_the_steady_state():
    """The first 10 trials of a run have the stationary rate: stored counts and the dead time of an event before
    t = 0 drawn from the steady state. (When written: a start without that dead time was +17 sigma off here, one
    with stored counts drawn Poisson(lam) -8 sigma.)"""
    shape, duration_s = (200, 200), 0.02
    params = MEM.replace(refractory_s=2e-3)  # the dead time is a large share of the mean interval
    lux = np.full(shape, 2.0)
    e = ev.simulate_events(lux, params, duration_s, rng=12, method="trials")
    pix = e["y"].astype(np.int64) * shape[1] + e["x"]
    rate = float(memory.memory_statistics(2.0, params).rate_hz.sum())
    head = np.bincount(pix[e["t"] < 10 * params.trial_us], minlength=lux.size).astype(np.float64)
    want = lux.size * rate * 10 * params.trial_us * 1e-6
    assert want > 50_000
    assert abs(head.sum() - want) < K_SIGMA * math.sqrt(lux.size * head.var()), (head.sum(), want)


@pytest.mark.parametrize("changes", [{}, {"leak_on_hz": 2.0, "leak_off_hz": 0.5, "leak_sigma": 0.4},
                                     {"eps_sigma": 0.03}, {"hot_pixel_fraction": 0.1, "hot_pixel_rate_hz": 20.0}],
                         ids=["plain", "spread-background", "mismatch", "hot-pixels"])
def test_a_video_that_does_not_change_is_the_static_simulation(changes):
    """Every pixel static: the video's pixels run the reset-memory renewal tier with their chains, stream by stream
    as simulate_events does, so the events are the same bit for bit."""
    params = MEM.replace(**changes)
    lux = np.random.default_rng(3).uniform(0.2, 5.0, (12, 17)).round(1)
    want = ev.simulate_events(lux, params, 0.8, rng=9)
    got = ev.simulate_video(np.stack([lux, lux, lux]), [0.0, 0.3, 0.8], params, rng=9)
    assert want.size > 1000 and np.array_equal(got, want)


def test_video_with_memory_does_not_depend_on_threads_or_windows(monkeypatch):
    from evnoise import simulate as sim

    rng = np.random.default_rng(4)
    frames = np.stack([np.full((70, 80), 1.0), rng.uniform(0.5, 4.0, (70, 80)), rng.uniform(0.5, 4.0, (70, 80))])
    frames[:, :35] = 2.0  # half the pixels static (renewal tier), half changing (trial tier)
    ts = [0.0, 0.002, 0.5]  # a fast change: signal events
    params = MEM.replace(leak_on_hz=1.0, eps_sigma=0.02)
    one, lab1 = ev.simulate_video(frames, ts, params, rng=5, threads=1, return_labels=True)
    two, lab2 = ev.simulate_video(frames, ts, params, rng=5, threads=2, return_labels=True)
    assert one.size > 10_000 and lab1.any() and np.array_equal(one, two) and np.array_equal(lab1, lab2)
    monkeypatch.setattr(sim, "TARGET_PIXEL_TRIALS_PER_WINDOW", 200_000)  # many windows of the trial tier
    parts = list(ev.iter_video(frames, ts, params, rng=5, threads=2))
    assert len(parts) > 5 and np.array_equal(np.concatenate(parts), one)


def _step_reference(params, lam_a, lam_b, n_pix, n_before, n_after, seed):
    """Plain NumPy, trial by trial: pixels at ``lam_a`` photons per trial for ``n_before`` trials, then ``lam_b``
    (a step at a trial boundary). The model as the trial kernel's docstring states it, in log comparisons:
    at the step the mean level ``log(lam + b)`` crosses whole thresholds above the reference, one signal event
    each, timed where the level (linear over the step's trial from the previous trial's) crosses it and at least
    the refractory period after the previous event; the reference moves to the last threshold crossed and the
    stored count is drawn ``Poisson(reference)``. Noise trials: a share ``k`` compares with the stored count,
    else with a fresh ``Poisson(reference)``; a noise event resets the reference to ``lam`` and stores ``n``.
    With a leak on the regular timer (``leak_regularity > 0``, intensity independent of the light): in an eligible
    trial without photon event the timer, drawn in the first such trial after an event (``L = D + G2`` as in
    :mod:`evnoise._kernels.background`), fires in trial ``j + L - 1``; every event (signal ones too) restarts it.
    Starts from a burn-in (the first ``n_before // 2`` trials, returned too: the caller looks later).
    Returns per event ``(pixel, time µs, polarity, is_signal)``."""
    rng = np.random.default_rng(seed)
    b, k, dt, refr = params.bias_pr, params.reset_memory, params.trial_us, params.refractory_us
    l_on, l_off, r = params.leak_on_hz, params.leak_off_hz, params.leak_regularity
    timed = l_on + l_off > 0 and r > 0
    if timed:
        a = -math.expm1(-(l_on + l_off) / params.trial_rate_hz)
        d = r * (1.0 / a - 1.0)
        a2 = 1.0 / (1.0 + (1.0 - r) * (1.0 / a - 1.0))
    arrival = np.full(n_pix, np.nan)
    ref = np.full(n_pix, float(lam_a))
    stored = rng.poisson(lam_a, n_pix).astype(np.float64)
    last_tau = np.full(n_pix, -np.inf)
    last_trial = np.full(n_pix, -1)
    out = []
    for j in range(n_before + n_after):
        lam = lam_a if j < n_before else lam_b
        sig = np.zeros(n_pix, dtype=bool)
        if j == n_before:  # the step: signal crossings (every pixel's reference is lam_a or stored there)
            lev_prev, lev = math.log(lam_a + b), math.log(lam_b + b)
            for i in range(n_pix):
                lev_ref = math.log(ref[i] + b)
                fired = False
                while lev - lev_ref >= params.eps_pos:
                    target = lev_ref + params.eps_pos
                    tau = j * dt + min(max((target - lev_prev) / (lev - lev_prev), 0.0), 1.0) * dt
                    tau = max(tau, last_tau[i] + refr)
                    if tau >= (j + 1) * dt:
                        raise AssertionError("the reference is written for crossings that fit in the step's trial")
                    out.append((i, tau, 1, True))
                    last_tau[i], last_trial[i], lev_ref, fired = tau, j, target, True
                if fired:
                    ref[i] = math.exp(lev_ref) - b
                    stored[i] = rng.poisson(ref[i])
                    sig[i] = True
                    arrival[i] = np.nan
        n = rng.poisson(lam, n_pix)
        use_stored = rng.random(n_pix) < k
        fresh = rng.poisson(ref)
        reference = np.where(use_stored, stored, fresh)
        diff = np.log(n + b) - np.log(reference + b)
        on, off = diff > params.eps_pos, -diff > params.eps_neg
        eligible = ~sig & (j > last_trial) & (j * dt >= last_tau + refr)
        if timed:
            quiet = eligible & ~(on | off)
            start = quiet & np.isnan(arrival)
            fixed = math.floor(d) + (rng.random(n_pix) < d - math.floor(d))
            arrival = np.where(start, j + fixed + rng.geometric(a2, n_pix) - 1.0, arrival)
            timer = quiet & (j >= arrival)
            timer_on = rng.random(n_pix) < l_on / (l_on + l_off)
            on, off = on | (timer & timer_on), off | (timer & ~timer_on)
        tau = (j + rng.random(n_pix)) * dt
        fire = (on | off) & eligible
        for i in np.flatnonzero(fire):
            out.append((i, tau[i], int(on[i]), False))
        last_tau[fire], last_trial[fire] = tau[fire], j
        ref[fire] = lam
        stored[fire] = n[fire]
        arrival[fire] = np.nan
    pix, t, p, s = (np.array(c) for c in zip(*out))
    return pix.astype(np.int64), t.astype(np.float64), p.astype(np.uint8), s.astype(bool)


@pytest.mark.parametrize("params", [MEM, MEM.replace(leak_on_hz=40.0, leak_off_hz=10.0, leak_regularity=0.7)],
                         ids=["memory", "memory-and-timer"])
@pytest.mark.long
def test_video_step_with_memory_against_a_per_trial_reference(params):
    """A step of light 0.5 -> 2 lux at 1 s: the changing pixels' signal events (two ON each), then their noise
    right after the step (the stored count drawn at the new reference meets the new light), and settled, against
    the plain per-trial reference of the same schedule: per-pixel counts, ON share and alternation per phase
    (two-sample, k-sigma from the per-pixel spread of each); settled phases against the closed form too. With a
    leak on the regular timer as well (restarted by the signal events)."""
    dt = params.trial_us
    shape = (30, 30)
    n_pix = shape[0] * shape[1]
    n_before, n_after = 1000, 2000
    lam_a, lam_b = 0.5 * params.photons_per_lux, 2.0 * params.photons_per_lux
    t_step = n_before * dt * 1e-6
    frames = np.stack([np.full(shape, 0.5), np.full(shape, 0.5), np.full(shape, 2.0), np.full(shape, 2.0)])
    ts = [0.0, t_step, t_step + 0.5 * dt * 1e-6, (n_before + n_after) * dt * 1e-6]
    e, signal = ev.simulate_video(frames, ts, params, rng=17, return_labels=True)
    got = _pix_t_p(e, shape[1]) + (signal,)
    ref = _step_reference(params, lam_a, lam_b, n_pix, n_before, n_after, seed=18)
    want_signal = math.floor((math.log(lam_b + params.bias_pr) - math.log(lam_a + params.bias_pr)) / params.eps_pos)
    assert want_signal == 2
    for pix, t, p, s in (got, ref):
        assert np.array_equal(np.bincount(pix[s], minlength=n_pix), np.full(n_pix, want_signal))
        assert np.all(p[s] == 1) and np.all(np.abs(t[s] - t_step * 1e6) < dt)
    phases = ((0.5, 1.0), (1.0, 1.005), (1.005, 1.05), (1.05, 1.2), (1.5, 3.0))
    for lo_s, hi_s in phases:
        sums = []
        for pix, t, p, s in (ref, got):
            sel = ~s & (t >= lo_s * 1e6) & (t < hi_s * 1e6)
            sums.append(_summaries(pix[sel], np.floor(t[sel]), p[sel], n_pix))
        _assert_phase_agrees(sums, n_pix, lo_s)
    for (lo_s, hi_s), lux in (((0.5, 1.0), 0.5), ((1.5, 3.0), 2.0)):
        pix, t, p, s = got
        sel = ~s & (t >= lo_s * 1e6) & (t < hi_s * 1e6)
        summary = _summaries(pix[sel], t[sel], p[sel], n_pix)
        st = memory.memory_statistics(lux, params)
        rate = summary["events"] / (hi_s - lo_s)
        assert abs(rate.mean() - st.rate_hz.sum()) < K_SIGMA * rate.std() / math.sqrt(n_pix)
        opp, se = _ratio(summary["opp"], summary["trans"])
        assert abs(opp - st.p_opposite) < K_SIGMA * se


@pytest.mark.parametrize("lux_pair", [(0.0, 1e-9), (0.0, 3.0), (1e4, 1e-3), (2.0, 2e3)])
def test_video_with_memory_at_hard_light_levels_is_finite_and_quiet(lux_pair):
    frames = np.stack([np.full((3, 4), lux_pair[0]), np.full((3, 4), lux_pair[1])])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        e = ev.simulate_video(frames, [0.0, 0.05], MEM.replace(leak_on_hz=1.0), rng=2)
    assert np.all(np.diff(e["t"].astype(np.int64)) >= 0)
    assert np.all(e["t"] < 50_000) and np.all(e["x"] < 4) and np.all(e["y"] < 3)
