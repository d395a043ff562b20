"""The plugin example: evnoise noise added to an ESIM/v2e-style clean stream."""

import math

import numpy as np

import evnoise as ev
from evnoise.examples import add_noise_to_esim as ex


def test_noise_is_added_to_a_clean_frame_emulator_stream(tmp_path):
    params = ev.load_preset("evk3-hd")
    frames, times = ex.moving_disc_frames(shape=(60, 80), n_frames=51, fps=50.0)
    clean_n4 = ex.clean_events_from_frames(frames, times)
    assert clean_n4.shape[1] == 4 and clean_n4.shape[0] > 100
    noisy, clean, noise = ex.add_noise(clean_n4, frames, times, params, rng=3)
    assert noisy.size == clean.size + noise.size
    assert np.all(np.diff(noisy["t"]) >= 0)
    # the clean stream is still in there, untouched
    key = lambda e: set(zip(e["t"].tolist(), e["x"].tolist(), e["y"].tolist(), e["p"].tolist()))  # noqa: E731
    assert key(clean) <= key(noisy)
    # noise on the static background (rows the disc never touches) has the closed-form rate
    shape = frames.shape[1:]
    counts = ev.count_events(noise, shape)
    rows = slice(0, 8)
    duration = times[-1] - times[0]
    expected = ev.expected_rate(frames[0][rows], params) * duration
    observed = counts[:, rows].reshape(2, -1).sum(axis=1)
    exp_total = expected.reshape(2, -1).sum(axis=1)
    assert np.all(np.abs(observed - exp_total) <= 5 * np.sqrt(exp_total))
    # round trip through the N x 4 convention
    back = ev.events_from_array(ev.events_to_array(noisy))
    assert np.array_equal(back, noisy)


def test_example_runs_as_a_program(tmp_path, capsys):
    out = tmp_path / "noisy.h5"
    assert ex.main(["--out", str(out), "--seed", "1"]) == 0
    events, meta = ev.read_events(out)
    assert events.size > 0 and meta["width"] == 160
    assert "merged stream" in capsys.readouterr().out
    assert not math.isnan(float(events["t"].mean()))
