"""Reset memory's kernel tables are built block by block (issue 32): the same tables whatever the blocks, and the
memory the build takes beyond its final tables is bounded by a block's, not by the number of chains."""

from __future__ import annotations

import tracemalloc

import numpy as np

import evnoise as ev
from evnoise._run import run_setup
from evnoise.terms import memory as tm


def _groups(shape, lux, seed=1):
    params = ev.load_preset("davis346").replace(reset_memory=0.5, leak_regularity=0.0)
    run = run_setup(shape, params, np.random.default_rng(seed))
    lam = params.photons_per_trial(np.full(shape, lux)).ravel()
    levels, a_on, a_off, _, _, eps = tm.pixel_groups(lam, run.params, run.background, run.thresholds)
    return params, levels, (a_on, a_off), eps


def _build(params, levels, background, eps):
    tracemalloc.start()
    try:
        out = tm.kernel_tables(levels, params, background=background, thresholds=eps)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return out, peak


def test_tables_do_not_depend_on_the_blocks_and_the_build_memory_is_a_blocks(monkeypatch):
    params, levels, background, eps = _groups((24, 30), 0.5)
    assert levels.size > tm.EXACT_RATE_LEVELS  # the iterated path, where blocks are
    monkeypatch.setattr(tm, "ITERATE_BLOCK_STATES", 10**12)
    monkeypatch.setattr(tm, "ITERATE_BLOCK", 10**9)
    whole, peak_whole = _build(params, levels, background, eps)  # every chain in one block
    monkeypatch.setattr(tm, "ITERATE_BLOCK_STATES", 1_000)
    monkeypatch.setattr(tm, "ITERATE_BLOCK", 2048)
    blocks, peak_blocks = _build(params, levels, background, eps)
    for a, b in zip(whole, blocks):
        assert np.array_equal(a, b)  # bit for bit (NaN-free tables)
    final = whole[0].nbytes + whole[1].nbytes
    states = int(whole[3].sum())
    assert states > 50 * 1_000  # many blocks
    # one block at a time: what the build holds beyond its final tables is far below one block per chain
    assert peak_blocks - final < 0.25 * (peak_whole - final), (peak_blocks, peak_whole, final)


def test_many_chains_show_a_progress_bar_and_the_same_events(capsys, monkeypatch):
    """Threshold mismatch gives about a chain per pixel, whose tables take about 0.5 ms each before the first event
    (a DAVIS346 sensor: ~40 s with nothing on the screen before): with ``progress`` a bar counts the chains to
    their number (counted through a stand-in bar: tqdm draws at most every 0.1 s), and the events are those of a
    run without it."""
    from _bars import stand_in_bars
    from evnoise import simulate

    params = ev.load_preset("davis346").replace(reset_memory=0.3, leak_regularity=0.0, hot_pixel_regularity=0.0)
    lux = np.full((12, 16), 2.0)
    quiet = ev.simulate_events(lux, params, 0.5, rng=3)
    capsys.readouterr()
    shown = ev.simulate_events(lux, params, 0.5, rng=3, progress=True)
    np.testing.assert_array_equal(shown, quiet)
    assert "memory tables:" in capsys.readouterr().err  # the real bar is drawn
    bars = stand_in_bars(monkeypatch, simulate, "memory tables")
    np.testing.assert_array_equal(ev.simulate_events(lux, params, 0.5, rng=3, progress=True), quiet)
    n_chains = len(tm.chain_plan(params.photons_per_trial(lux).ravel(), *_maps(params, lux))[0][0])
    assert n_chains > tm.EXACT_RATE_LEVELS
    bar = bars["memory tables"]
    assert bar.total == bar.counted == n_chains and bar.closed


def _maps(params, lux):
    run = run_setup(lux.shape, params, 3)
    return run.params, run.background, run.thresholds
