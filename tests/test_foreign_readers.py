"""events.h5 as other people's readers see it: evlib's loader (the owner-independent DSEC reader on PyPI)."""

import numpy as np
import pytest

import evnoise as ev

evlib = pytest.importorskip("evlib")


def _events(t0_us: int, n: int = 2000, seed: int = 0):
    g = np.random.default_rng(seed)
    events = np.zeros(n, dtype=ev.EVENT_DTYPE)
    events["t"] = t0_us + np.sort(g.integers(0, 3_000_000, n))
    events["x"], events["y"] = g.integers(0, 64, n), g.integers(0, 48, n)
    events["p"] = g.integers(0, 2, n)
    return events


def _evlib_columns(path):
    frame = evlib.load_events(str(path)).collect()
    t = frame["t"].cast(int).to_numpy()  # a Duration in microseconds
    return frame["x"].to_numpy(), frame["y"].to_numpy(), t, frame["polarity"].to_numpy()


@pytest.mark.parametrize("t0_us", [0, 1_643_240_000_000_000], ids=["clock-0", "unix-clock"])
def test_evlib_reads_every_event_of_an_events_h5(tmp_path, t0_us):
    events = _events(t0_us)
    path = tmp_path / "events.h5"
    ev.write_events(path, events, (48, 64))
    assert evlib.detect_format(str(path))[0] == "HDF5"
    x, y, t, pol = _evlib_columns(path)
    assert np.array_equal(x, events["x"]) and np.array_equal(y, events["y"])
    assert np.array_equal(pol, np.where(events["p"] == 1, 1, -1))
    # evlib returns the stored times and does not add /t_offset (DSEC's EventSlicer and evnoise's reader do):
    # a Unix clock comes back relative to the whole second evnoise stored as the offset
    _, meta = ev.read_events(path)
    offset = int(meta["t_offset"])
    assert np.array_equal(t + offset, events["t"])
    assert (offset == 0) == (t0_us == 0)
