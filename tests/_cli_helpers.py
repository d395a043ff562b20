"""Helpers shared by the command-line tests: run ``evnoise`` in-process, check one error line, a small events file."""

import numpy as np

import evnoise as ev
from evnoise.cli import main


def run_cli(capsys, *args):
    """``(exit code, stdout, stderr)`` of ``evnoise ARGS`` run in this process."""
    code = main([*map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(code, err, expect):
    """The run failed with exit 2 and exactly one ``evnoise: error:`` line containing ``expect``."""
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("evnoise: error: "), err
    assert expect in lines[0], lines[0]


def small_events_file(path, shape=(16, 20), n=400, seed=0, duration_us=1_000_000):
    """An events.h5 (or any suffix write_events knows) of ``n`` random events over ``duration_us``."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, duration_us, n))
    events = ev.events.make_events(t, rng.integers(0, shape[1], n), rng.integers(0, shape[0], n),
                                   rng.integers(0, 2, n))
    return ev.write_events(path, events, shape, t_end_us=duration_us)
