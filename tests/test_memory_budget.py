"""One memory budget (evnoise._budget) checked before allocations whose size a file or a parameter declares."""

import subprocess
import sys

import numpy as np
import pytest

import evnoise as ev
from evnoise._budget import check_allocation, memory_budget
from evnoise.readers.stats import pixel_counts


def _events(n=10):
    ev_ = np.zeros(n, dtype=ev.EVENT_DTYPE)
    ev_["t"] = np.arange(n) * 1000
    ev_["x"] = np.arange(n) % 7
    ev_["y"] = np.arange(n) % 5
    ev_["p"] = np.arange(n) % 2
    return ev_


def test_budget_reads_the_environment(monkeypatch):
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "2G")
    assert memory_budget() == 2 * 1024**3
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "1500")
    assert memory_budget() == 1500
    check_allocation(1500, "exactly the budget")
    with pytest.raises(ev.InputError, match="would need 1.5 kB of memory, more than the 1.5 kB EVNOISE_MAX_MEMORY"):
        check_allocation(1501, "one byte more")
    for bad in ("lots", "-3G", "0"):
        monkeypatch.setenv("EVNOISE_MAX_MEMORY", bad)
        with pytest.raises(ev.ParameterError, match="EVNOISE_MAX_MEMORY"):
            memory_budget()


def test_count_maps_of_a_declared_huge_sensor_are_refused_before_allocating(monkeypatch):
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "1G")
    with pytest.raises(ev.InputError, match=r"count maps of a 65535x65535 sensor .* sensor='WxH'"):
        pixel_counts([_events()], (65535, 65535))
    # without a declared size the maps grow to the events, and an event far out is refused before any map grows
    # (beyond the largest side inferred from events, whatever the budget)
    far = _events(1)
    far["x"], far["y"] = 60000, 60000
    with pytest.raises(ev.InputError, match="lies beyond 4096 pixels .* sensor='WxH'"):
        pixel_counts([_events(), far])
    counts, (n, t0, t1) = pixel_counts([_events()], (5, 7))
    assert counts.sum() == n == 10 and (t0, t1) == (0, 9000)


def test_info_stats_on_a_header_declaring_65535_squared_is_one_error_line(tmp_path):
    path = tmp_path / "huge.h5"
    ev.write_events(path, _events(), (65535, 65535))
    env = {"EVNOISE_MAX_MEMORY": "4G", "PATH": "/usr/bin:/bin"}
    run = subprocess.run([sys.executable, "-m", "evnoise", "info", str(path), "--stats"], capture_output=True,
                         text=True, env=env, timeout=300)
    assert run.returncode != 0
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("evnoise: error:"), run.stderr
    assert "65535x65535" in lines[0] and "Traceback" not in run.stderr


def test_a_sensor_beyond_the_budget_is_refused_before_the_image_is_resampled(monkeypatch):
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "1G")
    with pytest.raises(ev.ParameterError, match=r"65536x65536 sensor.*\(sensor_shape\)"):
        ev.radiometry.fit_to_sensor(np.ones((4, 4)), (65536, 65536))
    assert ev.radiometry.fit_to_sensor(np.ones((4, 4)), (8, 8)).shape == (8, 8)
