"""Reset memory with the regular background timer (``reset_memory > 0`` and ``leak_regularity > 0``, issue 32).

From state ``m`` the next event comes after ``min(G, L)`` eligible trials (photons first on a tie): the closed form
(:func:`~evnoise.terms.memory.with_timer`) against the memoryless timer's closed form at ``k = 0`` and against a
plain NumPy per-trial simulation of the trial kernel's timer rules; the renewal kernel against both. Tolerances are
k-sigma with sigmas from per-pixel totals (pixels are independent).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

import evnoise as ev
from evnoise.terms import memory
from test_memory_term import (
    K_SIGMA,
    _assert_phase_agrees,
    _check_against_closed_form,
    _ratio,
    _stream_events,
    _summaries,
)

#: thresholds high enough that photon noise and the timer's background are of the same order (a few events/s)
TIMED = ev.NoiseParams(eps_pos=1.5, eps_neg=1.5, bias_pr=1.0, trial_rate_hz=1000.0, photons_per_lux=5.0,
                       refractory_s=0.0, reset_memory=0.8, leak_on_hz=2.0, leak_off_hz=0.5, leak_regularity=0.6)
LUX = 2.0


@pytest.mark.parametrize("regularity", [0.3, 0.8, 1.0])
@pytest.mark.parametrize("refractory_s", [0.0, 2e-3])
def test_without_memory_the_chain_is_the_memoryless_timer(regularity, refractory_s):
    """k = 0: the chain's rates are the memoryless timer's closed form (evnoise.background.regular_rates, its own
    code path; both use timer_mean_min for E[min(G, L)], checked against plain sums below), within the truncation's
    bound: this checks the chain's plumbing (per-state background, stationary law, rates)."""
    params = TIMED.replace(reset_memory=0.0, leak_regularity=regularity, refractory_s=refractory_s)
    lux = np.array([0.0, 0.3, 2.0, 20.0])
    st = memory.memory_statistics(lux, params)
    want = ev.expected_rate(lux, params)
    bound = 2.0 * st.tail_mass * params.trial_rate_hz
    assert np.all(np.abs(st.rate_hz - want) <= 1e-9 * want + bound), (st.rate_hz, want)


@pytest.mark.parametrize("p, d, a2", [(0.01, 30, 0.05), (0.3, 0, 0.5), (1e-4, 1000, 1e-3), (0.05, 10, 1.0),
                                      (0.2, 5, 1e-9), (0.0, 7, 0.3), (1.0, 4, 0.2)])
def test_the_timer_sums_against_plain_sums(p, d, a2):
    """E[min(G, L)] and E[G; G <= L] for L = d + G2 (G geometric with p, G2 with a2, both >= 1) against the plain
    sums over g (P(L >= g) = 1 up to d, then (1 - a2)^(g - d - 1)), to 1e-10 relative."""
    from evnoise.terms.timer import timer_mean_min

    g = np.arange(1, 400_001, dtype=np.float64)
    tail_l = np.where(g <= d, 1.0, (1.0 - a2) ** np.maximum(g - d - 1.0, 0.0))  # P(L >= g)
    p_g = p * (1.0 - p) ** (g - 1.0)  # P(G = g)
    e_photon = float((g * p_g * tail_l).sum())
    e_min = float((((1.0 - p) ** (g - 1.0)) * tail_l).sum())  # sum over t >= 0 of P(G > t) P(L > t)
    with np.errstate(divide="ignore"):
        log1m_p = np.log1p(-p)
    args = (np.array([log1m_p]), np.array([p]), float(d), math.log1p(-a2) if a2 < 1 else -math.inf)
    assert math.isclose(float(timer_mean_min(*args)[0]), e_min, rel_tol=1e-10)
    assert math.isclose(float(memory._photon_first_mean(*args)[0]), e_photon, rel_tol=1e-10, abs_tol=1e-300)


@pytest.mark.parametrize("method", ["auto", "trials"])
def test_memory_timer_and_refractory_period_against_the_closed_form(method):
    """With a refractory period (its dead time after every event; at the start only the first event is
    approximate, as without memory): both tiers against the closed form's rates, transitions and mean intervals."""
    params = TIMED.replace(refractory_s=2e-3)
    lux = np.full((20, 20), LUX)
    duration_s = 30.0
    e = ev.simulate_events(lux, params, duration_s, rng=19, method=method)
    pix, t, p = e["y"].astype(np.int64) * lux.shape[1] + e["x"], e["t"].astype(np.float64), e["p"]
    _check_against_closed_form(_summaries(pix, t, p, lux.size), memory.memory_statistics(LUX, params), duration_s,
                               lux.size)


@pytest.mark.parametrize("reset_memory", [0.0, 0.8])
def test_a_timer_without_intensity_starts_again_when_the_light_returns(reset_memory):
    """A leak proportional to the light (none in the dark) on the timer: a stream at 0 lux, then at 5 lux, has the
    closed form's rate there (before, without memory: the timer's arrival stayed at infinity after the dark interval
    and the background never came back until a photon event; the memory kernel has no timer in the dark)."""
    params = TIMED.replace(reset_memory=reset_memory, leak_on_hz=0.0, leak_off_hz=0.0, leak_on_hz_per_lux=1.0,
                           eps_pos=3.0, eps_neg=3.0)
    shape = (30, 30)
    stream = ev.NoiseStream(shape, params, rng=3)
    assert stream.advance(np.zeros(shape), 1_000_000).size == 0
    e = stream.advance(np.full(shape, 5.0), 21_000_000)
    e = e[e["t"] >= 2_000_000]  # after a settling second
    counts = np.bincount(e["y"].astype(np.int64) * shape[1] + e["x"], minlength=shape[0] * shape[1]) / 19.0
    rate = float(ev.expected_rate(5.0, params).sum())
    assert rate > 4.0
    assert abs(counts.mean() - rate) < K_SIGMA * counts.std() / math.sqrt(counts.size), (counts.mean(), rate)


def test_a_regularity_near_zero_is_the_poisson_background():
    """The timer with regularity -> 0 is a geometric arrival, the Poisson background's law (which the tables hold
    when the regularity is 0): the statistics are continuous there."""
    poisson = memory.memory_statistics(LUX, TIMED.replace(leak_regularity=0.0))
    nearly = memory.memory_statistics(LUX, TIMED.replace(leak_regularity=1e-9))
    for a, b in ((poisson.rate_hz, nearly.rate_hz), (poisson.transition, nearly.transition),
                 (poisson.iei_mean_s, nearly.iei_mean_s)):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    assert nearly.p_opposite != memory.memory_statistics(LUX, TIMED).p_opposite  # the timer changes the chain


def _timer_reference(lam, params, n_pix, n_trials, seed):
    """Plain NumPy, trial by trial, the trial kernel's rules in log comparisons: the photon comparison (a share
    ``k`` against the stored count); in an eligible trial without photon event the timer, drawn in the first such
    trial after an event (``L = D + G2``: ``D`` the fixed part ``r (1/a - 1)`` rounded up with probability its
    fraction, ``G2`` geometric with ``1 / (1 + (1 - r)(1/a - 1))``), fires in trial ``j + L - 1``; every event
    restarts it and stores the trial's count. ``lam``: photons per trial, or one value per trial (a schedule; the
    timer's intensity does not depend on the light here). Starts with stored counts Poisson(lam) and no timer (the
    caller discards a burn-in)."""
    lam = np.broadcast_to(np.asarray(lam, dtype=np.float64), (n_trials,))
    rng = np.random.default_rng(seed)
    b, k, dt = params.bias_pr, params.reset_memory, params.trial_us
    l_on, l_off = params.leak_on_hz, params.leak_off_hz
    a = -math.expm1(-(l_on + l_off) / params.trial_rate_hz)
    r = params.leak_regularity
    d = r * (1.0 / a - 1.0)
    a2 = 1.0 / (1.0 + (1.0 - r) * (1.0 / a - 1.0))
    stored = rng.poisson(lam[0], n_pix).astype(np.float64)
    arrival = np.full(n_pix, np.nan)
    out_pix, out_t, out_p = [], [], []
    for j in range(n_trials):
        n = rng.poisson(lam[j], n_pix)
        ref = np.where(rng.random(n_pix) < k, stored, rng.poisson(lam[j], n_pix))
        diff = np.log(n + b) - np.log(ref + b)
        on, off = diff > params.eps_pos, -diff > params.eps_neg
        quiet = ~(on | off)
        start = quiet & np.isnan(arrival)
        if start.any():
            fixed = math.floor(d) + (rng.random(n_pix) < d - math.floor(d))
            arrival = np.where(start, j + fixed + rng.geometric(a2, n_pix) - 1.0, arrival)
        timer = quiet & (j >= arrival)
        timer_on = rng.random(n_pix) < l_on / (l_on + l_off)
        on, off = on | (timer & timer_on), off | (timer & ~timer_on)
        fire = on | off
        idx = np.flatnonzero(fire)
        out_pix.append(idx)
        out_t.append((j + rng.random(n_pix)[idx]) * dt)
        out_p.append(on[idx].astype(np.uint8))
        stored[idx] = n[idx]
        arrival[idx] = np.nan
    return np.concatenate(out_pix), np.concatenate(out_t), np.concatenate(out_p)


def test_closed_form_against_a_per_trial_simulation_of_the_timer():
    n_pix, n_trials, burn = 400, 30_000, 2_000
    lam = LUX * TIMED.photons_per_lux
    pix, t, p = _timer_reference(lam, TIMED, n_pix, n_trials, seed=3)
    keep = t >= burn * TIMED.trial_us
    s = _summaries(pix[keep], np.floor(t[keep]), p[keep], n_pix)
    assert s["trans"].sum() > 20_000
    st = memory.memory_statistics(LUX, TIMED)
    assert st.p_opposite > memory.memory_statistics(LUX, TIMED.replace(reset_memory=0.0)).p_opposite + 0.1
    _check_against_closed_form(s, st, (n_trials - burn) * TIMED.trial_us * 1e-6, n_pix)


def _events(lux, params, duration_s, seed, threads=1):
    e = ev.simulate_events(lux, params, duration_s, rng=seed, threads=threads)
    return e["y"].astype(np.int64) * lux.shape[1] + e["x"], e["t"].astype(np.float64), e["p"]


def test_kernel_with_memory_and_timer_against_the_closed_form_and_the_reference():
    lux = np.full((20, 20), LUX)
    duration_s = 30.0
    pix, t, p = _events(lux, TIMED, duration_s, seed=5)
    s = _summaries(pix, t, p, lux.size)
    _check_against_closed_form(s, memory.memory_statistics(LUX, TIMED), duration_s, lux.size)
    # the intervals per polarity pair: two-sample KS against the per-trial reference
    burn = 2_000
    rp, rt, rpol = _timer_reference(LUX * TIMED.photons_per_lux, TIMED, 400, 30_000, seed=6)
    keep = rt >= burn * TIMED.trial_us
    ref = _summaries(rp[keep], np.floor(rt[keep]), rpol[keep], 400)
    for a in (0, 1):
        for b in (0, 1):
            assert stats.ks_2samp(ref["gaps", a, b], s["gaps", a, b]).pvalue > 1e-3, (a, b)


def test_kernel_with_memory_and_timer_starts_in_the_steady_state():
    """The first 2 % of a run has the stationary rate (state from its time-stationary law, the timer's first
    arrival from the steady-state age given that state). (When written: a start with the timer drawn afresh was
    over 40 sigma off here.)"""
    params = TIMED.replace(leak_regularity=0.95, leak_on_hz=5.0)
    lux = np.full((150, 150), LUX)
    duration_s = 1.0
    pix, t, _ = _events(lux, params, duration_s, seed=8)
    rate = float(memory.memory_statistics(LUX, params).rate_hz.sum())
    head = np.bincount(pix[t < 0.02 * duration_s * 1e6], minlength=lux.size).astype(np.float64)
    want = lux.size * rate * 0.02 * duration_s
    assert want > 3000
    assert abs(head.sum() - want) < K_SIGMA * math.sqrt(lux.size * head.var()), (head.sum(), want)


def test_a_tie_between_photon_and_timer_goes_to_the_photon_event():
    """A deterministic timer (regularity 1, an ON-only leak every ~20 trials) against photon noise of p ~ 0.04 per
    trial: ties are ~2 % of the events, and the trial kernel compares photons first. The ON share is the closed
    form's (which counts ties as photon events; when written, a kernel giving ties to the timer was 31 sigma off)."""
    params = TIMED.replace(eps_pos=0.9, eps_neg=0.9, reset_memory=0.5, leak_on_hz=50.0, leak_off_hz=0.0,
                           leak_regularity=1.0)
    lux = np.full((100, 100), LUX)
    pix, _, p = _events(lux, params, 2.0, seed=3)
    events = np.bincount(pix, minlength=lux.size)
    on = np.bincount(pix, weights=p, minlength=lux.size)
    share, se = _ratio(on, events)
    want = float(memory.memory_statistics(LUX, params).on_share)
    assert abs(share - want) < K_SIGMA * se, (share, want, se)


def test_the_dvs128_preset_runs_with_memory():
    """The shipped dvs128 preset (near-periodic leak, Poisson hot pixels of their own regularity, a leak spread,
    threshold mismatch) with reset memory: still scenes, counts, the nominal rate and the tonic transform run; with
    its spread, hot pixels and mismatch off, the simulated rate is the closed form's."""
    params = ev.load_preset("dvs128").replace(reset_memory=0.3)
    lux = np.full((16, 16), 0.02)
    e = ev.simulate_events(lux, params, 20.0, rng=1)
    assert e.size > 0 and np.all(np.diff(e["t"]) >= 0)
    counts = ev.sample_counts(lux, params, 20.0, rng=1)
    assert counts.shape == (2, 16, 16) and int(counts.sum()) == e.size  # the same stream, counted
    nominal = params.replace(leak_sigma=0.0, hot_pixel_fraction=0.0, eps_sigma=0.0)
    big = np.full((64, 64), 0.02)
    n = np.bincount(_events(big, nominal, 200.0, seed=2)[0], minlength=big.size) / 200.0
    rate = float(ev.expected_rate(0.02, nominal).sum())
    assert abs(n.mean() - rate) < K_SIGMA * n.std() / math.sqrt(big.size), (n.mean(), rate)
    from evnoise.plugins.tonic import PhotonNoise

    transform = PhotonNoise((16, 16, 2), params, 0.02, rng=3)
    sample = np.zeros(2, dtype=[("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")])
    sample["t"] = [0, 20_000_000]
    noise = transform.noise(sample)
    assert noise.size > 0 and np.array_equal(transform.noise(sample), noise)


def test_tonic_transform_with_memory_and_timer_against_the_closed_form():
    """Each sample starts in the steady state of its light (the timer's first arrival from its steady-state age):
    the pooled samples have the closed form's rate and alternation."""
    from evnoise.plugins.tonic import PhotonNoise

    transform = PhotonNoise((20, 20, 2), TIMED, LUX, rng=7)
    dtype = np.dtype([("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")])
    sample_us, pix, t, p = 20_000_000, [], [], []  # ~100 events per pixel: alternation inside a sample unbiased
    for k in range(10):
        sample = np.zeros(2, dtype=dtype)
        sample["t"] = [0, sample_us]
        sample["x"] = k
        noise = transform.noise(sample)
        pix.append(noise["y"] * 20 + noise["x"] + k * 400)
        t.append(noise["t"].astype(np.float64))
        p.append(noise["p"].astype(np.uint8))
    s = _summaries(np.concatenate(pix), np.concatenate(t), np.concatenate(p), 10 * 400)
    st = memory.memory_statistics(LUX, TIMED)
    rate = s["events"] / ((sample_us + 1) * 1e-6)
    assert abs(rate.mean() - st.rate_hz.sum()) < K_SIGMA * rate.std() / math.sqrt(rate.size)
    opp, se = _ratio(s["opp"], s["trans"])
    assert abs(opp - st.p_opposite) < K_SIGMA * se, (opp, st.p_opposite)


def test_trial_tier_with_memory_and_timer_against_the_closed_form():
    """Still pixels trial by trial (the trial kernel's own timer, started from the steady state): the closed form's
    rates, ON share, alternation, transitions and mean intervals, the first 5 % of the run included."""
    lux = np.full((20, 20), LUX)
    duration_s = 30.0
    e = ev.simulate_events(lux, TIMED, duration_s, rng=15, method="trials")
    pix, t, p = e["y"].astype(np.int64) * lux.shape[1] + e["x"], e["t"].astype(np.float64), e["p"]
    s = _summaries(pix, t, p, lux.size)
    st = memory.memory_statistics(LUX, TIMED)
    _check_against_closed_form(s, st, duration_s, lux.size)
    big = np.full((150, 150), LUX)
    params = TIMED.replace(leak_regularity=0.95, leak_on_hz=5.0)
    e = ev.simulate_events(big, params, 0.2, rng=16, method="trials")
    head = np.bincount((e["y"].astype(np.int64) * 150 + e["x"])[e["t"] < 20_000], minlength=big.size).astype(float)
    want = big.size * float(memory.memory_statistics(LUX, params).rate_hz.sum()) * 0.02
    assert want > 3000
    assert abs(head.sum() - want) < K_SIGMA * math.sqrt(big.size * head.var()), (head.sum(), want)


def test_trial_tier_timer_starts_from_the_age_given_the_stored_state():
    """k = 1 and a deterministic timer (every ~20 trials) against photon noise that depends on the stored count: the
    first 10 trials have the stationary rate only when the timer's first arrival is drawn from the steady-state age
    given the pixel's state (when written: drawn as for a memoryless pixel instead, -12.7 sigma)."""
    params = TIMED.replace(eps_pos=0.6, eps_neg=0.6, reset_memory=1.0, leak_on_hz=50.0, leak_off_hz=0.0,
                           leak_regularity=1.0)
    lux = np.full((200, 200), LUX)
    e = ev.simulate_events(lux, params, 0.01, rng=5, method="trials")
    head = np.bincount(e["y"].astype(np.int64) * 200 + e["x"], minlength=lux.size).astype(float)
    want = lux.size * float(memory.memory_statistics(LUX, params).rate_hz.sum()) * 0.01
    assert want > 50_000
    assert abs(head.sum() - want) < K_SIGMA * math.sqrt(lux.size * head.var()), (head.sum(), want)


def test_a_video_with_the_timer_that_does_not_change_is_the_static_simulation():
    params = ev.load_preset("dvs128").replace(reset_memory=0.3)
    lux = np.random.default_rng(3).uniform(0.01, 0.05, (12, 17)).round(2)
    want = ev.simulate_events(lux, params, 30.0, rng=9)
    got = ev.simulate_video(np.stack([lux, lux]), [0.0, 30.0], params, rng=9)
    assert want.size > 50 and np.array_equal(got, want)


def test_a_changing_video_with_memory_and_the_timer_runs():
    """The dvs128 preset with memory on a video (hot pixels with their own timer, mismatch, a spread leak): the
    static half is the still scene's chains, the changing half runs trial by trial; events sorted, in range."""
    params = ev.load_preset("dvs128").replace(reset_memory=0.3)
    frames = np.stack([np.full((16, 16), 0.02), np.full((16, 16), 0.02), np.full((16, 16), 0.02)])
    frames[1:, :, 8:] = 2.0  # half the sensor brightens
    e, signal = ev.simulate_video(frames, [0.0, 0.5, 20.0], params, rng=4, return_labels=True)
    assert signal.any() and (~signal).sum() > 20 and np.all(np.diff(e["t"]) >= 0)
    assert np.all(e["t"] < 20_000_000)


@pytest.mark.long
def test_noise_stream_with_memory_and_timer_against_the_closed_form():
    """Irregular intervals at one light: each drops its pending event and redraws the photon gap, keeping the
    timer's arrival; the closed form's rates, transitions and mean intervals. (When written: a stream that drew a
    new timer at every interval instead was 26 sigma off in the rate.)"""
    shape, duration_s = (20, 20), 30.0
    stream = ev.NoiseStream(shape, TIMED, rng=21)
    pix, t, p = _stream_events(stream, [(np.full(shape, LUX), int(duration_s * 1e6))], seed=4)
    s = _summaries(pix, t, p, shape[0] * shape[1])
    _check_against_closed_form(s, memory.memory_statistics(LUX, TIMED), duration_s, shape[0] * shape[1])


def test_noise_stream_with_memory_and_timer_through_a_change_of_light_against_the_per_trial_reference():
    """The light steps 0.5 -> 2 lux at 3 s: per-pixel counts, ON share and alternation before, right after and
    well after the step, against the plain per-trial simulation of the same schedule (two-sample, k-sigma)."""
    shape, n_pix = (20, 20), 400
    n_a, n_b = 3000, 3000
    dt = TIMED.trial_us
    lam = np.concatenate([np.full(n_a, 0.5), np.full(n_b, 2.0)]) * TIMED.photons_per_lux
    ref = _timer_reference(lam, TIMED, n_pix, n_a + n_b, seed=8)
    stream = ev.NoiseStream(shape, TIMED, rng=9)
    got = _stream_events(stream, [(np.full(shape, 0.5), int(n_a * dt)), (np.full(shape, 2.0), int((n_a + n_b) * dt))],
                         seed=5)
    for lo_s, hi_s in ((1.0, 3.0), (3.0, 3.3), (3.3, 6.0)):
        sums = []
        for pix, t, p in (ref, got):
            sel = (t >= lo_s * 1e6) & (t < hi_s * 1e6)
            sums.append(_summaries(pix[sel], np.floor(t[sel]), p[sel], n_pix))
        _assert_phase_agrees(sums, n_pix, lo_s)


def test_interval_distribution_with_the_timer_has_the_closed_form_means_and_limits():
    """memory_iei_cdf with the timer (cumulative sums of P(K <= m, photon / timer first)) against the mean intervals
    of memory_statistics (E[G; G <= L], E[L; L < G]: another derivation), to 1e-6; near regularity 0 it is the
    Poisson background's distribution (the geometric formula), to 1e-6."""
    grid = np.linspace(0.0, 20.0, 200_001)
    cdf = memory.memory_iei_cdf(grid, LUX, TIMED)
    assert np.all(np.diff(cdf, axis=-1) >= -1e-12) and np.allclose(cdf[..., -1], 1.0, atol=1e-12)
    means = ((1.0 - cdf[..., 1:]) + (1.0 - cdf[..., :-1])).sum(axis=-1) * 0.5 * (grid[1] - grid[0])
    np.testing.assert_allclose(means, memory.memory_statistics(LUX, TIMED).iei_mean_s, rtol=1e-6)
    ts = np.array([0.0005, 0.003, 0.02, 0.1, 0.4, 1.5])
    nearly = memory.memory_iei_cdf(ts, LUX, TIMED.replace(leak_regularity=1e-9))
    poisson = memory.memory_iei_cdf(ts, LUX, TIMED.replace(leak_regularity=0.0))
    np.testing.assert_allclose(nearly, poisson, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("refractory_s", [0.0, 2e-3])
def test_kernel_intervals_with_the_timer_follow_the_closed_form_distribution(refractory_s):
    """The renewal kernel's intervals per polarity pair against memory_iei_cdf with the timer (one-sample KS; a
    pixel's successive intervals are dependent through its state, which makes the p-values somewhat optimistic)."""
    params = TIMED.replace(refractory_s=refractory_s)
    lux = np.full((20, 20), LUX)
    pix, t, p = _events(lux, params, 30.0, seed=23)
    s = _summaries(pix, t, p, lux.size)
    for a in (0, 1):
        for b in (0, 1):
            gaps = s["gaps", a, b] * 1e-6
            p_ks = stats.kstest(gaps, lambda x: memory.memory_iei_cdf(x, LUX, params)[a, b]).pvalue
            assert p_ks > 1e-3, (a, b, p_ks)
