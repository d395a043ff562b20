"""Event-array helpers."""

import numpy as np
import pytest

import evnoise as ev


def _events(rows):
    return ev.events_from_array(np.array(rows, dtype=float))


def test_count_events_by_polarity_and_window():
    e = _events([[0, 0, 0, 1], [5, 1, 0, 0], [10, 1, 0, 0], [20, 2, 1, 1]])
    c = ev.count_events(e, (2, 3))
    assert c.shape == (2, 2, 3)
    assert c[0, 0, 0] == 1 and c[1, 0, 1] == 2 and c[0, 1, 2] == 1 and c.sum() == 4
    w = ev.count_events(e, (2, 3), t_start_us=5, t_end_us=20)
    assert w.sum() == 2 and w[1, 0, 1] == 2


def test_count_events_rejects_bad_input():
    e = _events([[0, 5, 0, 1]])
    with pytest.raises(ev.InputError, match="outside"):
        ev.count_events(e, (2, 3))
    unsorted = np.zeros(2, dtype=ev.EVENT_DTYPE)
    unsorted["t"] = [5, 1]
    with pytest.raises(ev.InputError, match="sorted"):
        ev.count_events(unsorted, (2, 3))
    with pytest.raises(ev.InputError, match="fields"):
        ev.count_events(np.zeros(3), (2, 3))


def test_merge_is_sorted_and_stable():
    a = _events([[1, 0, 0, 1], [5, 0, 0, 1], [9, 0, 0, 1]])
    b = _events([[0, 1, 1, 0], [5, 1, 1, 0], [12, 1, 1, 0]])
    m = ev.merge_events(a, b)
    assert m["t"].tolist() == [0, 1, 5, 5, 9, 12]
    assert m["x"].tolist() == [1, 0, 0, 1, 0, 1]  # a before b on the tie at t = 5
    assert ev.merge_events(a, ev.events_from_array(np.zeros((0, 4)))).tolist() == a.tolist()


def test_array_round_trip_and_conventions():
    arr = np.array([[0.5e-6 * 4, 3, 4, -1], [1e-6 * 7, 1, 2, 1]])
    e = ev.events_from_array(arr, time_unit="s")
    assert e["t"].tolist() == [2, 7] and e["p"].tolist() == [0, 1]
    back = ev.events_to_array(e)
    assert back[:, 0].tolist() == [2.0, 7.0] and back[:, 3].tolist() == [0.0, 1.0]
    assert np.allclose(ev.events_to_array(e, time_unit="s")[:, 0], [2e-6, 7e-6])
    with pytest.raises(ev.InputError):
        ev.events_from_array(np.array([[0, 1, 2, 3]]))  # polarity 3
    with pytest.raises(ev.InputError):
        ev.events_from_array(np.zeros((2, 3)))
    with pytest.raises(ev.InputError):
        ev.events_from_array(np.array([[0, -1, 2, 1]]))


@pytest.mark.parametrize("t, unit", [(1e30, "us"), (1e30, "s"), (-1e19, "us"), (2**62, "s")])
def test_events_from_array_refuses_times_beyond_the_int64_clock(t, unit):
    """A time outside int64 microseconds was cast to -2**63 and sorted first, with only NumPy's RuntimeWarning."""
    arr = np.array([[5, 1, 1, 0], [t, 0, 0, 1]], dtype=np.float64 if isinstance(t, float) else np.int64)
    with pytest.raises(ev.InputError, match=r"event 1: time .* is outside the 64-bit microsecond clock"):
        ev.events_from_array(arr, time_unit=unit)


def test_events_from_array_keeps_large_integer_times_exactly_and_refuses_complex():
    big = np.array([[2**62 + 1, 1, 1, 0], [3, 0, 0, 1]], dtype=np.int64)
    assert ev.events_from_array(big)["t"].tolist() == [3, 2**62 + 1]
    with pytest.raises(ev.InputError, match="numeric"):
        ev.events_from_array(np.array([[1 + 2j, 1, 1, 0]]))
