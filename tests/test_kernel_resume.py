"""The window kernels write into buffers owned by the caller and stop when they are full.

The caller grows the buffers and calls again from the pixel that stopped (the renewal kernel keeps
that pixel's next event pending; the trial kernel puts the pixel's stream and state back and runs
it again). Forcing a stop at every event must give exactly the events of one uninterrupted call.
"""

import numpy as np
import pytest

import evnoise as ev
import evnoise._engine as engine
import evnoise.simulate as es


def _force_stops(monkeypatch, keep: bool):
    """Buffers that start with one slot and grow by one: the kernels stop at every event. With ``keep``
    the grown buffers are kept for the next window (reuse and stops together), else every window starts
    at one slot again."""
    buffers = engine.event_buffers

    def tiny(capacity):
        return buffers(min(int(capacity), 1))

    def one_more(out, n):
        bigger = buffers(out[0].size + 1)
        for new, old in zip(bigger, out):
            new[:n] = old[:n]
        return bigger

    monkeypatch.setattr(engine, "event_buffers", tiny)
    monkeypatch.setattr(engine, "grown", one_more)
    if not keep:
        monkeypatch.setattr(engine.PixelState, "keep", lambda self, lo, out: None)


def _runs(params):
    rng = np.random.default_rng(3)
    lux = rng.uniform(0.05, 20.0, (6, 9))
    yy, xx = np.mgrid[0:6, 0:9]
    times = np.arange(8) / 20.0
    frames = np.stack([np.where((xx - 8 * t) ** 2 + (yy - 3) ** 2 < 5, 40.0, lux) for t in times])
    out = {"static": ev.simulate_events(lux, params, 5.0, rng=5, threads=2)}
    for fast in (True, False):
        es.TRIAL_FAST_STATIC = fast
        try:
            out[f"video fast={fast}"] = ev.simulate_video(frames, times, params, rng=7, method="trials", threads=2)
        finally:
            es.TRIAL_FAST_STATIC = True
    events, labels = ev.simulate_video(frames, times, params, rng=8, threads=2, return_labels=True)
    out["video auto"] = events
    out["labels"] = labels
    stream = ev.NoiseStream(lux.shape, params, rng=9, threads=1)
    out["stream"] = np.concatenate([stream.advance(frames[i], 200_000 * (i + 1)) for i in range(4)])
    return out


@pytest.mark.parametrize("extra", [
    {},
    {"hot_pixel_fraction": 0.2, "hot_pixel_rate_hz": 200.0},  # many events per pixel and window
    {"leak_regularity": 0.8, "hot_pixel_fraction": 0.2, "hot_pixel_rate_hz": 200.0},  # regular timer: PEND_ON
    {"refractory_s": 2e-3, "eps_sigma": 0.03},
    {"pr_tau_s_at_1lux": 0.05},  # bandwidth: the trial tier's filtered level
])
@pytest.mark.parametrize("keep", [False, True])
@pytest.mark.long
def test_stopping_at_every_event_gives_the_same_events(extra, keep, monkeypatch):
    params = ev.load_preset("evk3-hd").replace(**extra)
    whole = _runs(params)
    _force_stops(monkeypatch, keep)
    pieces = _runs(params)
    for name, events in whole.items():
        assert events.size > 15, name  # the runs have events to cut
        np.testing.assert_array_equal(pieces[name], events, err_msg=name)


def test_a_chunk_keeps_small_buffers_for_the_next_window_and_drops_large_ones():
    state = engine.PixelState(np.arange(4), np.arange(1, 5, dtype=np.uint64), 1)
    small = engine.event_buffers(10)
    state.keep(0, small)
    assert state.buffers(0, 5) is small  # reused: room enough
    assert state.buffers(0, 11) is not small  # too small for the next window: new ones
    state.keep(0, engine.event_buffers(engine.KEEP_EVENTS_PER_CHUNK + 1))  # one long window
    fresh = state.buffers(0, 5)
    assert fresh is not small and fresh[0].size == 5  # neither the long window's buffers nor the old ones
