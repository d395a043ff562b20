"""The ESIM-style example: evnoise's noise added to a clean frame-emulator stream through the plugin code."""

from collections import Counter

import numpy as np
import pytest

import evnoise as ev
from evnoise.examples import add_noise_to_esim as ex

SMALL = ["--size", "48x24", "--frames", "6"]


def test_emulator_follows_v2e_interface_and_counts_threshold_crossings():
    emulator = ex.LogFrameEmulator(threshold=0.3)
    dark, bright = np.full((3, 4), 1.0), np.full((3, 4), 10.0)
    assert emulator.generate_events(dark, 0.0) is None  # the first frame initialises
    assert emulator.generate_events(dark, 0.1) is None  # nothing changed
    rows = emulator.generate_events(bright, 0.2)
    # a step of log(10.001 / 1.001) = 2.30 is 7 whole thresholds of 0.3 in every pixel, all ON
    k = int(np.floor(np.log(10.001 / 1.001) / 0.3))
    assert k == 7 and rows.shape == (12 * k, 4)
    assert np.all(rows[:, 3] == 1) and np.all(np.diff(rows[:, 0]) >= 0)
    assert rows[:, 0].min() > 0.1 and rows[:, 0].max() <= 0.2
    assert np.array_equal(np.bincount((rows[:, 2] * 4 + rows[:, 1]).astype(int)), np.full(12, k))
    back = emulator.generate_events(dark, 0.3)
    assert back.shape == (12 * k, 4) and np.all(back[:, 3] == -1)


def test_noise_is_added_to_a_clean_frame_emulator_stream():
    params = ev.load_preset("evk3-hd")
    frames, times = ex.moving_disc_frames(shape=(60, 80), n_frames=11, fps=10.0)
    noisy, clean, n_noise = ex.add_noise(frames, times, params, rng=3)
    assert clean.size > 100 and n_noise > 100
    assert noisy.size == clean.size + n_noise
    assert np.all(np.diff(noisy["t"]) >= 0)
    # the clean stream is still in there, untouched
    key = lambda e: Counter(zip(e["t"].tolist(), e["x"].tolist(), e["y"].tolist(), e["p"].tolist()))  # noqa: E731
    all_events, clean_events = key(noisy), key(clean)
    assert all(all_events[k] >= n for k, n in clean_events.items())
    rest = sorted((all_events - clean_events).elements())
    noise = ev.events_from_array(np.array(rest, dtype=np.float64).reshape(-1, 4))
    assert noise.size == n_noise
    # noise on the static background (rows the disc never touches) has the closed-form rate
    counts = ev.count_events(noise, frames.shape[1:])
    rows = slice(0, 8)
    duration = times[-1] - times[0]
    expected = (ev.expected_rate(frames[0][rows], params) * duration).reshape(2, -1).sum(axis=1)
    observed = counts[:, rows].reshape(2, -1).sum(axis=1)
    assert np.all(np.abs(observed - expected) <= 4 * np.sqrt(expected) + 1), (observed, expected)


def test_same_seed_same_stream():
    params = ev.load_preset("evk3-hd")
    frames, times = ex.moving_disc_frames(shape=(20, 48), n_frames=4, fps=10.0)
    a = ex.add_noise(frames, times, params, rng=1)[0]
    b = ex.add_noise(frames, times, params, rng=1)[0]
    c = ex.add_noise(frames, times, params, rng=2)[0]
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_example_runs_as_a_program_with_a_progress_bar(tmp_path, capsys):
    out = tmp_path / "noisy.h5"
    assert ex.main(["--out", str(out), "--seed", "1", *SMALL]) == 0
    events, meta = ev.read_events(out)
    assert events.size > 0 and meta["width"] == 48 and meta["height"] == 24
    captured = capsys.readouterr()
    assert "merged stream" in captured.out and "wrote" in captured.out
    assert "frames" in captured.err  # the tqdm bar
    assert ex.main(["-q", *SMALL]) == 0
    assert "frames" not in capsys.readouterr().err


def test_example_refuses_to_overwrite_without_the_flag(tmp_path, capsys):
    out = tmp_path / "noisy.h5"
    out.write_bytes(b"precious")
    assert ex.main(["--out", str(out), "-q", *SMALL]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evnoise: error:") and "--overwrite" in err and err.count("\n") == 1
    assert out.read_bytes() == b"precious"
    assert ex.main(["--out", str(out), "--overwrite", "-q", *SMALL]) == 0
    assert ev.read_events(out)[0].size > 0


@pytest.mark.parametrize("argv, message", [
    (["--out", "noisy.txt"], "suffix .h5"),
    (["--out", "missing-dir/noisy.h5"], "does not exist"),
    (["--size", "10x10"], "--size"),
    (["--frames", "1"], "--frames"),
    (["--preset", "no-such-preset"], "no-such-preset"),
])
def test_example_bad_input_is_one_error_line(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    assert ex.main([*argv, "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evnoise: error:") and message in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []  # nothing written, no temporary left


def test_example_help_is_plain_text(capsys):
    with pytest.raises(SystemExit) as exc:
        ex.main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "--overwrite" in text and "events.h5" in text
    for markup in (":class:", ":func:", ":data:", "``"):
        assert markup not in text
