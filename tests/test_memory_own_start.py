"""Reset memory on scenes whose chains are too many for tables: every pixel in the trial tier, each chain's start
computed on its own (:mod:`evnoise._kernels.memory_start`) instead of refused.

The start's law is checked against the table path's own computation (``level_tables``, ``_embedded_iterate``,
``initial_law``: NumPy, pairwise sums, another order of operations) on chains with and without background, dead
time, absorbing states and states spans; the events against the table path's trial tier, which the start is meant to
reproduce: on scenes with more than ``EXACT_RATE_LEVELS`` chains (where the table path iterates the same embedded
steps) the events are the same, event for event, once ``MAX_TABLE_STATES`` is lowered to send the scene down the new
path. The trial tier itself is validated against the closed form in ``tests/test_memory_video.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

import evnoise as ev
from evnoise._kernels import memory_start as ms
from evnoise.terms import memory
from test_memory_term import MEM

#: davis346 with memory and its threshold mismatch (most pixels a chain of their own), Poisson background
DAVIS = ev.load_preset("davis346").replace(reset_memory=0.3, leak_regularity=0.0, hot_pixel_regularity=0.0)


def _law_here(lam, eps_on, eps_off, bias, k, a_on, a_off, dt_s, refr_s, steps=memory.ITERATED_STEPS):
    """The start's law of one chain, as ``start_pixels`` computes it (``_block``, ``_finish``)."""
    lo, n_s, _ = memory.state_range(lam)
    pmf = np.empty(n_s)
    ms.level_pmf(float(lam), float(lo), n_s, pmf)
    zero = np.zeros(1, dtype=np.int64)
    _, x, p, _ = ms._block(pmf, zero, np.array([float(lo)]), np.array([n_s]), zero,
                           memory.threshold_factors([eps_on]), memory.threshold_factors([eps_off]),
                           np.array([float(a_on)]), np.array([float(a_off)]), float(bias), float(k), steps, zero, 0)
    cum, dead = np.empty(n_s), np.empty(n_s)
    ms._finish(np.ascontiguousarray(x[:, 0]), np.ascontiguousarray(p[0]), pmf, n_s, dt_s, refr_s, cum, dead)
    return cum, dead


def _law_of_tables(lam, eps_on, eps_off, bias, k, a_on, a_off, dt_s, refr_s, steps=memory.ITERATED_STEPS,
                   jitter=None):
    """The table path's law; ``jitter``: a generator that moves each of its input arrays by one rounding (a relative
    2^-53 of either sign per element), to measure how much rounding alone moves the law."""
    t = memory.level_tables(lam, eps_on, eps_off, bias, k, a_on=a_on, a_off=a_off)
    if jitter is not None:
        import dataclasses

        moved = {name: getattr(t, name) * (1.0 + jitter.choice([-1.0, 1.0], t.n_states) * 2.0 ** -53)
                 for name in ("pmf", "head", "tail", "fresh_on", "fresh_off", "stored_on", "stored_off", "none_fresh")}
        t = dataclasses.replace(t, **moved)
    weight, dead = memory.initial_law(t, memory._embedded_iterate(t, steps), dt_s, refr_s)
    return np.cumsum(weight), dead


CHAINS = [  # lam, eps_on, eps_off, bias, k, a_on, a_off, dt_s, refr_s
    (2.0, 0.5, 0.6, 1.0, 0.7, 0.0, 0.0, 1e-3, 0.0),
    (2.0, 0.5, 0.6, 1.0, 0.7, 0.0, 0.0, 1e-3, 2e-3),  # dead time
    (9.5, 1.5, 1.5, 4.0, 0.8, 3e-3, 1e-3, 0.02, 1e-4),  # background of the order of the photon noise
    (162.3, 0.12, 0.11, 187.3, 0.3, 6e-4, 0.0, 0.0149, 1e-3),  # evk4 at 2 lux
    (3200.0, 0.15, 0.15, 64.0, 0.99, 0.0, 0.0, 1 / 424, 0.0),  # slow mixing: the steps, not the limit
    (40.0, 25.0, 0.3, 2.0, 0.5, 0.0, 0.0, 1e-3, 0.0),  # ON never fires at most states
    (40.0, 800.0, 900.0, 2.0, 0.5, 0.0, 0.0, 1e-3, 0.0),  # no state ever fires: absorbing everywhere
    (0.0, 0.2, 0.2, 1.0, 0.5, 1e-3, 1e-3, 1e-3, 0.0),  # darkness: one state
]


@pytest.mark.parametrize("chain", CHAINS, ids=[f"lam{c[0]:g}-k{c[4]:g}-eps{c[1]:g}" for c in CHAINS])
def test_start_law_is_the_table_paths(chain):
    """State by state (differences of the cumulative laws) within what one rounding of the table path's own inputs
    moves its law (10 times the largest move over 3 jitters), or 1e-13: the laws are well conditioned (every move is
    below 1e-14, also for the slow-mixing k = 0.99 at 3200 photons per trial, whose states' event probabilities go
    down to 1e-11), so this is rounding-level. (A first version that added the stored branches' sums as
    ``(ca + W) - cb`` lost ``ca`` beside ``W`` there and was 5e-8 off: the jitter showed that it was not the
    conditioning.)"""
    cum, dead = _law_here(*chain)
    want_cum, want_dead = _law_of_tables(*chain)
    mass, want = np.diff(cum, prepend=0.0), np.diff(want_cum, prepend=0.0)
    moves = [np.abs(np.diff(_law_of_tables(*chain, jitter=np.random.default_rng(i))[0], prepend=0.0) - want).max()
             for i in range(3)]
    tol = max(1e-13, 10.0 * max(moves))
    assert cum[-1] == pytest.approx(1.0, rel=1e-12)
    assert np.abs(mass - want).max() <= tol, (np.abs(mass - want).max(), moves)
    np.testing.assert_allclose(dead, want_dead, rtol=1e-13, atol=0)


def test_start_law_stops_only_at_a_fixed_point():
    """Stopping early (a step that changes nothing) gives the law of all the steps: 40 and 400 steps of a fast-mixing
    chain agree to rounding, and a slow-mixing one's law still moves between 40 and 400 steps (it is the steps'
    law, as the table path's)."""
    fast = (2.0, 0.5, 0.6, 1.0, 0.3, 0.0, 0.0, 1e-3, 0.0)
    np.testing.assert_allclose(_law_here(*fast)[0], _law_here(*fast, steps=400)[0], rtol=0, atol=1e-15)
    slow = CHAINS[4]
    assert np.abs(_law_here(*slow)[0] - _law_here(*slow, steps=400)[0]).max() > 1e-6


def _prepared(lam, eps_on, eps_off, bias, k, a_on, a_off):
    lo, n_s, _ = memory.state_range(lam)
    pmf = np.empty(n_s)
    ms.level_pmf(float(lam), float(lo), n_s, pmf)
    fk, a, bb = np.empty((n_s, 4)), np.empty(n_s, dtype=np.int64), np.empty(n_s, dtype=np.int64)
    p, inv_p = np.empty(n_s), np.empty(n_s)
    ms._prepare(pmf, float(lo), n_s, memory._expm1(eps_on), memory._expm1(eps_off), float(bias), float(k),
                float(a_on), float(a_off), fk, a, bb, p, inv_p)
    return pmf, fk, a, bb, inv_p


@pytest.mark.parametrize("steps", [1, 3, 40, 400])
def test_chains_iterated_together_are_each_as_alone(steps):
    """A block of chains of one level (the starts iterate four at a time) gives each chain's law bit for bit as
    alone, also when some stop early: one that mixes (a fixed point in floating point), one whose states never fire,
    a slow-mixing one (k = 0.99), one with background, and one whose law vanishes (weights set to 0: it takes
    Poisson(lam) and keeps it)."""
    chains = [(40.0, 0.5, 0.6, 1.0, 0.3, 0.0, 0.0), (40.0, 800.0, 900.0, 1.0, 0.5, 0.0, 0.0),
              (40.0, 0.15, 0.15, 1.0, 0.99, 0.0, 0.0), (40.0, 25.0, 0.3, 1.0, 0.5, 1e-3, 0.0)]
    parts = [_prepared(*c) for c in chains]
    pmf, n_s = parts[0][0], parts[0][0].size
    fk = np.stack([q[1] for q in parts], axis=1)
    a, bb, inv_p = (np.ascontiguousarray(np.stack([q[i] for q in parts], axis=1)) for i in (2, 3, 4))
    vanished = fk.copy()
    vanished[:, 1, :] = 0.0
    for weights in (fk, vanished):
        x = np.empty((n_s, len(chains)))
        ms._iterate(pmf, n_s, np.ascontiguousarray(weights), a, bb, inv_p, steps, x)
        for g in range(len(chains)):
            alone = np.empty((n_s, 1))
            ms._iterate(pmf, n_s, np.ascontiguousarray(weights[:, g:g + 1]), np.ascontiguousarray(a[:, g:g + 1]),
                        np.ascontiguousarray(bb[:, g:g + 1]), np.ascontiguousarray(inv_p[:, g:g + 1]), steps, alone)
            np.testing.assert_array_equal(x[:, g], alone[:, 0])
    assert np.allclose(x[:, 1], pmf / pmf.sum())  # the vanished chain


@pytest.fixture
def no_tables(monkeypatch):
    """Every scene with memory has too many chains for tables."""
    monkeypatch.setattr(memory, "MAX_TABLE_STATES", 10)


def _scene():
    lux = np.full((12, 16), 2.0)
    lux[:6] = 40.0
    return lux


@pytest.mark.parametrize("params", [DAVIS, DAVIS.replace(refractory_s=5e-3, leak_sigma=0.8),
                                    DAVIS.replace(hot_pixel_fraction=0.1, hot_pixel_rate_hz=3.0)],
                         ids=["davis346", "dead-time-and-leak-spread", "hot-pixels"])
def test_events_without_tables_are_the_table_paths(params, monkeypatch):
    from evnoise._run import run_setup

    lux = _scene()
    run = run_setup(lux.shape, params, 5)  # what the runs below draw: the chains of their pixels
    groups = memory.pixel_groups(params.photons_per_trial(lux).ravel(), run.params, run.background, run.thresholds)
    with_tables = ev.simulate_events(lux, params, 3.0, rng=5, method="trials")
    assert with_tables.size > 1000
    monkeypatch.setattr(memory, "MAX_TABLE_STATES", 10)
    auto = ev.simulate_events(lux, params, 3.0, rng=5)
    trials = ev.simulate_events(lux, params, 3.0, rng=5, method="trials", threads=4)
    np.testing.assert_array_equal(auto, with_tables)
    np.testing.assert_array_equal(trials, with_tables)
    assert len(groups[0]) > memory.EXACT_RATE_LEVELS  # where the table path iterates as the start does


def test_windows_counts_and_video_without_tables(monkeypatch):
    """Windows, counts and a video down the new path: a video with the table path's trial tier everywhere
    (``method="trials"``) gives the same events as the new path, which runs every pixel trial by trial."""
    lux = _scene()
    frames = [lux, lux * 1.5, lux]
    video_tables = ev.simulate_video(frames, [0.0, 0.5, 1.0], DAVIS, rng=9, method="trials")
    monkeypatch.setattr(memory, "MAX_TABLE_STATES", 10)
    whole = ev.simulate_events(lux, DAVIS, 2.0, rng=8)
    windows = ev.iter_events(lux, DAVIS, 2.0, rng=8)
    assert windows.expected_events > 0.5 * whole.size
    np.testing.assert_array_equal(np.concatenate(list(windows)), whole)
    np.testing.assert_array_equal(ev.sample_counts(lux, DAVIS, 2.0, rng=8), ev.count_events(whole, lux.shape))
    video = ev.simulate_video(frames, [0.0, 0.5, 1.0], DAVIS, rng=9)
    assert video.size > 1000
    np.testing.assert_array_equal(video, video_tables)


def test_without_tables_refuses_what_it_does_not_cover(no_tables):
    lux = _scene()
    with pytest.raises(ev.ParameterError, match=r"for the renewal tier \(method='auto' or 'trials'"):
        ev.simulate_events(lux, DAVIS, 1.0, rng=1, method="renewal")
    with pytest.raises(ev.ParameterError, match=r"for the renewal tier \(method='auto' or 'trials'"):
        ev.simulate_video([lux, lux], [0.0, 0.5], DAVIS, rng=1, method="renewal")
    with pytest.raises(ev.ParameterError, match="regular background timer"):
        ev.simulate_events(lux, DAVIS.replace(leak_regularity=0.5), 1.0, rng=1)
    with pytest.raises(ev.ParameterError, match="regular background timer"):
        ev.simulate_events(lux, ev.load_preset("dvs128").replace(reset_memory=0.3), 1.0, rng=1)
    with pytest.raises(ev.ParameterError, match="regular background timer"):
        ev.NoiseStream(lux.shape, DAVIS.replace(leak_regularity=0.5), rng=1).advance(lux, 100_000)
    from evnoise.plugins.tonic import PhotonNoise

    with pytest.raises(ev.ParameterError, match="regular background timer"):
        PhotonNoise((lux.shape[1], lux.shape[0], 2), DAVIS.replace(leak_regularity=0.5), lux, rng=1)


def _tonic_sample(t_us):
    sample = np.zeros(len(t_us), dtype=[("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")])
    sample["t"] = t_us
    return sample


@pytest.mark.parametrize("params", [DAVIS, DAVIS.replace(refractory_s=5e-3, leak_sigma=0.8)],
                         ids=["davis346", "dead-time-and-leak-spread"])
def test_tonic_transform_without_tables_runs_as_the_still_scene_trial_tier(no_tables, params):
    """The tonic transform with reset memory whose chains would pass the table budget (was refused): each sample's
    noise is, event for event, what simulate_events' trial tier without tables gives for the sample's span and key
    and the transform's maps (that tier is held to the table path above); the same for any thread count and in a
    pickled copy (a DataLoader worker's, which rebuilds its chains)."""
    import pickle

    from evnoise import simulate
    from evnoise.plugins.tonic import PhotonNoise

    lux = _scene()
    transform = PhotonNoise((lux.shape[1], lux.shape[0], 2), params, lux, rng=4, threads=1)
    assert transform._memory.tables is None  # the path without tables
    sample = _tonic_sample([250_000, 900_000, 2_250_000])
    noise = transform.noise(sample)
    assert noise.size > 500
    setup = transform._setup
    key = setup.keyed(transform._generator(sample)).key
    reference = np.concatenate(list(simulate._still_trial_windows(
        lux, transform.params, key, 250_000, 2_000_001, 1, False, None, setup.background, setup.thresholds)))
    for field in "txy":
        np.testing.assert_array_equal(noise[field], reference[field])
    np.testing.assert_array_equal(noise["p"], reference["p"].astype(np.int64))
    wide = PhotonNoise((lux.shape[1], lux.shape[0], 2), params, lux, rng=4, threads=4)
    np.testing.assert_array_equal(wide.noise(sample), noise)
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(transform)).noise(sample), noise)
    out = transform(sample)
    assert out.size == noise.size + sample.size and np.all(np.diff(out["t"]) >= 0)


def _advance_through(stream, lux, ends):
    """``stream`` advanced to each of ``ends`` (µs) under ``lux``: the events of every interval, each checked to be
    sorted and inside its interval."""
    out = []
    for t_end in ends:
        t_start = stream.t_us
        e = stream.advance(lux, t_end)
        assert np.all(np.diff(e["t"].astype(np.int64)) >= 0) and np.all((e["t"] >= t_start) & (e["t"] < t_end))
        out.append(e)
    return np.concatenate(out)


def _in_order(e):
    return e[np.lexsort((e["p"], e["x"], e["y"], e["t"]))]


def test_stream_without_tables_is_simulate_events(no_tables):
    """A NoiseStream whose tables would pass the budget goes trial by trial from its first interval: through
    irregular intervals (1 µs, shorter than a trial, ends inside trials) and with 4 threads its events are those of
    ``simulate_events`` with the same seed, event for event (an event of an interval's last trial that falls after
    the interval's end comes with the next one)."""
    lux = _scene()
    want = ev.simulate_events(lux, DAVIS, 3.0, rng=5)
    assert want.size > 1000
    ends = [1, 2, 250_000, 250_900, 1_000_003, 1_000_004, 2_345_678, 2_999_999, 3_000_000]
    got = _advance_through(ev.NoiseStream(lux.shape, DAVIS, rng=5, threads=4), lux, ends)
    np.testing.assert_array_equal(_in_order(got), _in_order(want))


@pytest.mark.parametrize("params, background_hz", [(MEM, (0.0, 0.0)), (MEM.replace(eps_pos=1.5, eps_neg=1.5,
                                                                                    leak_on_hz=2.0, leak_off_hz=0.5),
                                                                        (2.0, 0.5))], ids=["memory", "background"])
@pytest.mark.long
def test_stream_goes_trial_by_trial_at_a_change_of_light(params, background_hz, monkeypatch):
    """A stream on tables whose next light would pass the budget goes on trial by trial: the events pending from the
    last interval on tables come with the next interval, and the light steps 0.5 -> 0 -> 2 lux (the switch at the
    first step) give per-pixel counts, ON share and alternation in each phase and right after each step of the
    plain per-trial simulation of the same schedule (as the tables' stream is checked in test_memory_term)."""
    from evnoise._kernels import simulate as ks
    from test_memory_term import STEPS, STEPS_SHAPE, check_steps_against_reference, steps_setup

    shape, steps, n_pix, dt = STEPS_SHAPE, STEPS, STEPS_SHAPE[0] * STEPS_SHAPE[1], params.trial_us
    ref, stream, ends = steps_setup(params, background_hz)
    ends[0] -= 0.5 * dt  # inside the last trial of the first light: the trials that start after it have the next one
    rng = np.random.default_rng(5)
    chunks = []
    for i, ((lux, _), end) in enumerate(zip(steps, ends)):
        if i == 1:  # the stream is on tables here; its pending events (in that last trial) carry over
            assert stream._trials is None
            fstate = stream._state.fstate
            pend = np.flatnonzero(np.isfinite(fstate[:, ks.PEND_TAU]))
            assert pend.size > 0
            pending = set(zip((stream._t0 + np.floor(fstate[pend, ks.PEND_TAU])).astype(int).tolist(),
                              (pend % shape[1]).tolist(), (pend // shape[1]).tolist(),
                              (fstate[pend, ks.PEND_ON].astype(int) % 2).tolist()))  # the kernel's code
            monkeypatch.setattr(memory, "MAX_TABLE_STATES", 1)  # the dark's tables hold the counts stored before
            first = stream.advance(np.full(shape, lux), int(stream.t_us + 5 * dt))
            assert stream._trials is not None
            got = set(zip(first["t"].astype(int).tolist(), first["x"].tolist(), first["y"].tolist(),
                          first["p"].astype(int).tolist()))
            assert pending <= got
            chunks.append(first)
        while stream.t_us < int(end):
            t_next = min(int(end), stream.t_us + int(rng.integers(1, 90_000)))
            chunks.append(stream.advance(np.full(shape, lux), t_next))
    e = np.concatenate(chunks)
    assert np.all(np.diff(e["t"].astype(np.int64)) >= 0)
    check_steps_against_reference(ref, (e["y"].astype(np.int64) * shape[1] + e["x"], e["t"].astype(np.float64), e["p"]),
                                  n_pix)


def test_stream_with_the_timer_refuses_to_go_trial_by_trial(monkeypatch):
    """The regular timer is not covered trial by trial without tables: a stream on tables with it refuses at the
    change of light that would pass the budget (and says why)."""
    lux = np.full((6, 6), 2.0)
    params = MEM.replace(leak_on_hz=2.0, leak_off_hz=0.5, leak_regularity=0.5)
    stream = ev.NoiseStream(lux.shape, params, rng=2)
    stream.advance(lux, 200_000)
    monkeypatch.setattr(memory, "MAX_TABLE_STATES", 10)
    with pytest.raises(ev.ParameterError, match="regular background timer"):
        stream.advance(3.0 * lux, 400_000)


@pytest.mark.parametrize("k", [0.3, 0.9])
@pytest.mark.parametrize("tables", [True, False], ids=["tables", "without-tables"])
def test_expected_events_are_the_memory_rate(tables, k, monkeypatch):
    """What a run with many chains says it expects (sizes its buffers, printed by the CLI) is the rate of the chains'
    iterated laws: within 5 sigma of the events (counts of memory pixels are under-dispersed: Poisson's sigma is
    ample). The states weighted by Poisson(lam), the estimate before, were ~30 % low with k = 0.3; five embedded
    steps alone were 17 % off with k = 0.9."""
    lux = np.full((40, 40), 2.0)
    if not tables:
        monkeypatch.setattr(memory, "MAX_TABLE_STATES", 10)
    windows = ev.iter_events(lux, DAVIS.replace(reset_memory=k), 4.0, rng=21)
    n = sum(w.size for w in windows)
    assert n > 10_000
    assert abs(windows.expected_events - n) < 5.0 * np.sqrt(n), (windows.expected_events, n)


@pytest.mark.parametrize("lam, k", [(162.3, 0.3), (162.3, 0.9), (20.0, 0.95), (3200.0, 0.9)])
def test_chain_rate_estimate_against_the_stationary_rate(lam, k):
    """The rate estimate without tables against the stationary solve (``level_statistics``): within 1 % on chains
    that mix slowly too (measured 4e-8 to 2e-3; five steps alone were +17 % at k = 0.9, -15 % at 3200 photons)."""
    eps_on, eps_off, bias, dt_s = 0.12, 0.11, 187.3, 1e-3
    lo, n_s, _ = memory.state_range(lam)
    pmf = np.empty(n_s)
    ms.level_pmf(float(lam), float(lo), n_s, pmf)
    out, zero = np.empty(1), np.zeros(1, dtype=np.int64)
    ms.chain_rates(pmf, zero, np.array([float(lo)]), np.array([n_s]), zero, np.array([memory._expm1(eps_on)]),
                   np.array([memory._expm1(eps_off)]), np.zeros(1), np.zeros(1), bias, k, dt_s, 0.0,
                   memory.ITERATED_STEPS, zero, out)
    r_on, r_off, *_ = memory.level_statistics(memory.level_tables(lam, eps_on, eps_off, bias, k), dt_s, 0.0)
    assert out[0] == pytest.approx(r_on + r_off, rel=1e-2)


def test_few_chains_keep_the_table_path():
    """Below the table budget nothing changes: the renewal tier with memory (whose events differ from the trial
    tier's) still runs by default."""
    lux = np.full((8, 8), 2.0)
    auto = ev.simulate_events(lux, MEM, 2.0, rng=4)
    np.testing.assert_array_equal(auto, ev.simulate_events(lux, MEM, 2.0, rng=4, method="renewal"))
    assert not np.array_equal(auto, ev.simulate_events(lux, MEM, 2.0, rng=4, method="trials"))
