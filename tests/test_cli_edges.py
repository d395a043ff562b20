"""Issue 17, the command line's edges: inputs are never overwritten, SIGTERM cleans up, -q/-v after the
subcommand, flags (not Python names) in messages, log lines and "interrupted" off the progress bar's line,
scalar probabilities, and the pictures (simulate --png, make-dataset's preview.png, separate --png)."""

from __future__ import annotations

import fnmatch
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from _cli_helpers import one_error_line, run_cli, small_events_file

PIL_Image = pytest.importorskip("PIL.Image")
h5py = pytest.importorskip("h5py")

REPO = Path(__file__).resolve().parents[1]


def grey_image(path, shape=(24, 32), seed=0):
    rng = np.random.default_rng(seed)
    PIL_Image.fromarray(rng.integers(0, 256, size=shape, dtype=np.uint8)).save(path)
    return path








# --------------------------------------------------------------------------------------
# 1. no command writes over one of its inputs, not even with --overwrite
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("flag", ["--out", "--png"])
def test_simulate_never_replaces_its_input_image(tmp_path, capsys, flag):
    photo = grey_image(tmp_path / "photo.png")
    before = photo.read_bytes()
    other = {"--out": ["--png", tmp_path / "maps.png"], "--png": ["--out", tmp_path / "ev.h5"]}[flag]
    code, _, err = run_cli(capsys, "simulate", photo, flag, photo, *other, "--overwrite", "--duration", "0.01")
    one_error_line(code, err, f"{flag} {photo} is the input image")
    assert photo.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photo.png"]


def test_simulate_refuses_a_link_to_its_input_and_an_output_among_the_frames(tmp_path, capsys):
    photo = grey_image(tmp_path / "photo.png")
    (tmp_path / "link.png").symlink_to(photo)
    code, _, err = run_cli(capsys, "simulate", photo, "--out", tmp_path / "link.png", "--overwrite")
    one_error_line(code, err, "is the input image")
    with PIL_Image.open(photo) as img:
        assert img.format == "PNG"
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        grey_image(frames / f"f{i}.png", seed=i)
    # a --png inside the folder of frames would become a frame of the next run
    code, _, err = run_cli(capsys, "simulate", frames, "--fps", "10", "--out", tmp_path / "v.h5",
                           "--png", frames / "maps.png")
    one_error_line(code, err, "inside the input folder")
    assert sorted(p.name for p in frames.iterdir()) == ["f0.png", "f1.png", "f2.png"]


def test_every_command_refuses_to_write_over_its_input(tmp_path, capsys):
    rates = tmp_path / "rates.csv"
    rates.write_text("lux,rate_on_hz,rate_off_hz\n0.5,0.4,0.3\n1,0.5,0.4\n2,0.6,0.5\n4,0.5,0.4\n")
    events = small_events_file(tmp_path / "rec.h5")
    odd = small_events_file(tmp_path / "odd.h5").rename(tmp_path / "odd.png")  # an events.h5 file under a .png name
    pairs = tmp_path / "pairs.npz"
    pairs.write_bytes(b"not really pairs")
    photos = tmp_path / "photos"
    photos.mkdir()
    grey_image(photos / "a.png")
    cases = [
        (["calibrate", rates, "--out", rates, "--overwrite"], rates, "--out"),
        (["calibrate", rates, "--out", tmp_path / "p.toml", "--plot", rates, "--overwrite"], rates, "--plot"),
        (["train", pairs, "--out", pairs, "--overwrite"], pairs, "--out"),
        (["reconstruct", odd, "--model", tmp_path / "m.pt", "--out", odd, "--overwrite"], odd, "--out"),
        (["separate", events, "--noise-out", tmp_path / "n.h5", "--png", events, "--overwrite"], events, "--png"),
        (["make-dataset", photos / "a.png", "--out", photos / "a.png", "--overwrite"], photos / "a.png", "--out"),
    ]
    for args, victim, flag in cases:
        before = victim.read_bytes()
        code, _, err = run_cli(capsys, *args)
        one_error_line(code, err, f"{flag} {victim} is ")
        assert victim.read_bytes() == before, args
    # a dataset folder that holds an input
    code, _, err = run_cli(capsys, "make-dataset", photos / "a.png", "--out", photos, "--overwrite")
    one_error_line(code, err, f"--out {photos} contains an input")
    assert not (tmp_path / "n.h5").exists() and not (tmp_path / "p.toml").exists()


def test_reconstruct_video_folder_may_hold_the_input_unless_it_is_named_like_a_frame(tmp_path):
    from evnoise.cli._paths import refuse_writing_inputs
    from evnoise.errors import OutputError

    events = small_events_file(tmp_path / "rec.h5")
    patterns = ("frame_*.png", "overlay_*.png", "frames.csv")
    refuse_writing_inputs([("--out", tmp_path)], [("the events file", events)], folder_files=patterns)
    named = small_events_file(tmp_path / "frames.csv")
    with pytest.raises(OutputError, match="frames.csv"):
        refuse_writing_inputs([("--out", tmp_path)], [("the events file", named)], folder_files=patterns)


# --------------------------------------------------------------------------------------
# 2. SIGTERM: temporaries removed, exit code 143; .gitignore matches the temporary names
# --------------------------------------------------------------------------------------
def test_sigterm_mid_write_leaves_no_temporary_file(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "evnoise", "simulate", "--example", "--duration", "600", "--seed", "1",
           "--out", "big.h5"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while not any(p.name.endswith(".tmp") and p.stat().st_size > 100_000 for p in tmp_path.iterdir()):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no temporary file appeared"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = err.decode()
    assert proc.returncode == 143, err
    assert err.rstrip().splitlines()[-1] == "evnoise: terminated", err
    assert list(tmp_path.iterdir()) == []


def test_sigterm_in_process_is_handled_and_the_handler_restored(tmp_path, capsys, monkeypatch):
    from evnoise._atomic import atomic_output
    from evnoise.cli import separate

    seen = {}

    def fake_run(args):
        with atomic_output(tmp_path / "out.h5") as tmp:
            tmp.write_bytes(b"half")
            seen["tmp"] = tmp
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler interrupts this
        return 0

    monkeypatch.setattr(separate, "run", fake_run)
    before = signal.getsignal(signal.SIGTERM)
    code, _, err = run_cli(capsys, "separate", "x.h5", "--out", "y.h5")
    assert code == 143 and err.strip() == "evnoise: terminated"
    assert not seen["tmp"].exists() and list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is before


def test_gitignore_matches_the_temporary_names():
    from evnoise._atomic import temporary_name

    gitignore = REPO / ".gitignore"
    if not gitignore.exists():
        pytest.skip("not a source checkout")
    patterns = [line.strip() for line in gitignore.read_text().splitlines()
                if line.strip() and not line.startswith("#") and "/" not in line.strip()]
    names = [temporary_name(Path("events.h5")).name, temporary_name(Path("preset.toml")).name,
             temporary_name(Path("ev.aedat4")).name + ".aedat4", ".model.pt.tmp.png"]
    for name in names:
        assert any(fnmatch.fnmatch(name, p) for p in patterns), name
    assert not any(fnmatch.fnmatch("events.h5", p) for p in patterns)


# --------------------------------------------------------------------------------------
# 3. -q / -v after the subcommand
# --------------------------------------------------------------------------------------
def test_quiet_and_verbose_after_the_subcommand(tmp_path, capsys):
    photo = grey_image(tmp_path / "photo.png")
    code, out, err = run_cli(capsys, "simulate", photo, "--out", tmp_path / "a.h5", "--duration", "0.01", "-q")
    assert code == 0 and out == "" and err == ""
    code, out, err = run_cli(capsys, "simulate", photo, "--out", tmp_path / "b.h5", "--duration", "0.01", "-v")
    assert code == 0 and "Simulated" in out and "evnoise: INFO: no --seed given" in err
    code, out, _ = run_cli(capsys, "-q", "simulate", photo, "--out", tmp_path / "c.h5", "--duration", "0.01")
    assert code == 0 and out == ""


# --------------------------------------------------------------------------------------
# 4. messages name flags, not Python parameters
# --------------------------------------------------------------------------------------
def test_errors_name_flags(tmp_path, capsys):
    photo = grey_image(tmp_path / "photo.png")
    code, _, err = run_cli(capsys, "simulate", photo, "--out", tmp_path / "a.h5", "--max-lux", "-3")
    one_error_line(code, err, "--max-lux must be")
    assert "max_lux" not in err
    nan = np.ones((6, 8), dtype=np.float32)
    nan[2, 3] = np.nan
    PIL_Image.fromarray(nan, mode="F").save(tmp_path / "nan.tif")
    code, _, err = run_cli(capsys, "simulate", tmp_path / "nan.tif", "--out", tmp_path / "b.h5")
    one_error_line(code, err, "clip them (--clip-invalid)")
    assert "clip_invalid" not in err


def test_unknown_options_point_to_the_commands_help(tmp_path, capsys):
    events = small_events_file(tmp_path / "e.h5")
    code, _, err = run_cli(capsys, "info", events, "--bogus")
    one_error_line(code, err, "unrecognized arguments: --bogus (see evnoise info --help)")
    code, _, err = run_cli(capsys, "--bogus")
    one_error_line(code, err, "(see evnoise --help)")


def test_separate_threshold_error_names_the_flag(tmp_path, capsys):
    events = small_events_file(tmp_path / "e.h5")
    code, _, err = run_cli(capsys, "separate", events, "--threshold", "0", "--out", tmp_path / "s.h5")
    one_error_line(code, err, "--threshold must be >= 1, got 0")
    assert not (tmp_path / "s.h5").exists()


@pytest.mark.parametrize("flag,name,expect", [("--out", "preset.png", "--out must name a .toml file"),
                                              ("--plot", "fit.pdf", "--plot must name a .png file")])
def test_calibrate_outputs_are_named_by_their_format(tmp_path, capsys, flag, name, expect):
    outputs = {"--out": tmp_path / "cam.toml", "--plot": tmp_path / "fit.png", flag: tmp_path / name}
    code, _, err = run_cli(capsys, "calibrate", "--example", *(x for kv in outputs.items() for x in kv))
    one_error_line(code, err, expect)
    assert list(tmp_path.iterdir()) == []


def test_flag_names_rewrite_only_parameter_names():
    from evnoise.cli import _flag_names, build_parser

    args = build_parser().parse_args(["simulate", "x.png", "--out", "y.h5"])
    assert _flag_names("max_lux must be > 0; duration_s too", args) == "--max-lux must be > 0; --duration too"
    assert _flag_names("give window_s (--window)", build_parser().parse_args(
        ["reconstruct", "e.h5", "--out", "o.png"])) == "give --window"
    keep = "cannot read /data/max_lux/x_max_lux.png; eps_pos and seed are not flags"
    assert _flag_names(keep, args) == keep


# --------------------------------------------------------------------------------------
# 5. log lines and "interrupted" start on a line of their own, not on the progress bar's
# --------------------------------------------------------------------------------------
def test_log_lines_and_interrupted_do_not_land_on_the_progress_bar(capsys, monkeypatch):
    from tqdm import tqdm

    from evnoise.cli import separate

    def fake_run(args):
        bar = tqdm(total=10, desc="work", file=sys.stderr, mininterval=0)
        bar.update(3)
        logging.getLogger("evnoise.test").warning("something to know")
        bar.update(3)
        raise KeyboardInterrupt

    monkeypatch.setattr(separate, "run", fake_run)
    code, _, err = run_cli(capsys, "separate", "x.h5", "--out", "y.h5")
    assert code == 130
    for text in ("evnoise: WARNING: something to know", "evnoise: interrupted"):
        before = err.split(text)[0]
        assert before.endswith(("\n", "\r")), repr(err)  # the bar's line was ended or cleared first
    assert err.rstrip().endswith("evnoise: interrupted")
    assert not tqdm._instances  # the bar was closed


# --------------------------------------------------------------------------------------
# 6. scalar probabilities: numpy.float64 from both functions, arrays stay arrays
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["poisson", "gaussian"])
def test_scalar_probabilities_have_one_type(method):
    for func in (ev.event_probability, ev.log_event_probability):
        value = func(3.0, 0.2, 0.5, method=method)
        assert type(value) is np.float64, (func.__name__, type(value))
        assert type(func(np.asarray(3.0), 0.2, method=method)) is np.float64
        arr = func([3.0], 0.2, method=method)
        assert isinstance(arr, np.ndarray) and arr.shape == (1,)
        assert float(value) == pytest.approx(float(func(np.array([3.0]), 0.2, 0.5, method=method)[0]), rel=1e-12)
    assert ev.log_event_probability(3.0, 0.2, method=method) == pytest.approx(
        np.log(ev.event_probability(3.0, 0.2, method=method)), rel=1e-9)


# --------------------------------------------------------------------------------------
# 7. pictures
# --------------------------------------------------------------------------------------
def test_simulate_png_shows_the_scene_beside_the_maps(tmp_path):
    from evnoise.cli._pictures import simulate_sheet

    lux = np.repeat(np.array([[0.1, 10 ** 0.5, 100.0]]), 20, axis=0).repeat(40, axis=1)  # 20 x 120, 3 levels
    counts = np.zeros((2, 20, 120))
    counts[0, :, 40:80] = 7
    sheet = np.asarray(simulate_sheet(counts, lux=lux, duration_s=2.0))
    rgb = sheet.reshape(-1, 3)
    # the scene in grey on a log lux scale: 0.1 lux black, sqrt(10) lux mid-grey, 100 lux white
    enlarge = 2  # 120 pixels are shown twice as wide (at least 240)
    area = 20 * 40 * enlarge**2
    mid = np.all(rgb == (128, 128, 128), axis=1).sum()
    white = np.all(rgb == (255, 255, 255), axis=1).sum()
    assert area <= mid < area + 400 and area <= white < area + 400
    assert sheet.shape[1] > 3 * 120 * enlarge  # scene, ON and OFF side by side


def test_make_dataset_writes_a_preview(tmp_path, capsys):
    out = tmp_path / "ds"
    args = ["make-dataset", "--procedural", "dead-leaves", "--count", "3", "--sensor", "64x48", "--seed", "1",
            "--workers", "1", "--out", out]
    code, stdout, _ = run_cli(capsys, *args)
    assert code == 0 and "preview" in stdout
    with PIL_Image.open(out / "preview.png") as im:
        assert im.format == "PNG" and im.width > 3 * 32
        stamp = (out / "preview.png").stat().st_mtime_ns
    # a rerun verifies the dataset and keeps the picture (it is not a foreign file)
    code, _, _ = run_cli(capsys, *args)
    assert code == 0 and (out / "preview.png").stat().st_mtime_ns == stamp
    # --overwrite with other options redraws it
    code, _, _ = run_cli(capsys, *args[:-2], "--window", "0.5", "--out", out, "--overwrite")
    assert code == 0 and (out / "preview.png").stat().st_mtime_ns != stamp


def test_separate_png_counts_signal_and_noise(tmp_path, capsys):
    from evnoise.cli._pictures import count_map

    shape = (16, 20)
    rng = np.random.default_rng(3)
    t_sig = np.sort(rng.integers(0, 20_000, 600))  # a burst on a 3x3 patch: signal
    sig = ev.events.make_events(t_sig, rng.integers(5, 8, 600), rng.integers(5, 8, 600), np.ones(600, int))
    t_noise = np.sort(rng.integers(0, 1_000_000, 150))  # sparse noise everywhere
    noise = ev.events.make_events(t_noise, rng.integers(0, 20, 150), rng.integers(0, 16, 150), rng.integers(0, 2, 150))
    events = ev.events.merge_events(sig, noise)
    src = ev.write_events(tmp_path / "in.h5", events, shape, t_end_us=1_000_000)
    code, _, err = run_cli(capsys, "separate", src, "--noise-out", tmp_path / "noise.h5", "--png", tmp_path / "s.png")
    assert code == 0, err
    with PIL_Image.open(tmp_path / "s.png") as im:
        assert im.format == "PNG" and im.width > 3 * 20
    total, duration = count_map(src)
    expected = np.zeros((2, *shape), int)
    np.add.at(expected, (1 - events["p"].astype(int), events["y"].astype(int), events["x"].astype(int)), 1)
    np.testing.assert_array_equal(total, expected)
    assert duration == pytest.approx(1.0)
    # an existing --png is refused before any work (no event output written)
    code, _, err = run_cli(capsys, "separate", src, "--out", tmp_path / "sig.h5", "--png", tmp_path / "s.png")
    one_error_line(code, err, "already exists")
    assert not (tmp_path / "sig.h5").exists()


@pytest.mark.slow
def test_sigterm_stops_make_dataset_workers_promptly(tmp_path):
    """SIGTERM reaches only the main process; its workers are interrupted as Ctrl-C would (before the fix
    the pool finished every running shard first: 52 s on a busy 2-core machine)."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "evnoise", "make-dataset", "--procedural", "dead-leaves", "--count", "40",
           "--sensor", "640x480", "--mode", "events", "--window", "4", "--workers", "2", "--seed", "1",
           "--out", "ds"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not (tmp_path / "ds" / ".evnoise-progress" / "plan.json").exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.1)
        time.sleep(4)  # workers started and busy with their first shard
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        start = time.monotonic()
        _, err = proc.communicate(timeout=120)
        stop_s = time.monotonic() - start
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, err.decode()
    assert stop_s < 15, stop_s
    assert not [p.name for p in (tmp_path / "ds").rglob("*") if p.name.endswith(".tmp")]


def test_info_stats_png_never_replaces_the_recording(tmp_path, capsys):
    events = small_events_file(tmp_path / "rec.h5")
    before = events.read_bytes()
    code, _, err = run_cli(capsys, "info", events, "--stats", "--png", events, "--overwrite")
    one_error_line(code, err, f"--png {events} is the input file")
    assert events.read_bytes() == before


def test_info_of_an_empty_window_says_where_the_clock_is(tmp_path, capsys):
    """A window on a clock the file does not cover (the guide's "0 .. 4.5 s" on a DVS128 file starting at 48.9 s)
    reported 0 events over 4.5 s as a valid measurement, without a word."""
    path = small_events_file(tmp_path / "rec.h5")
    code, out, err = run_cli(capsys, "info", path, "--t-start", "100", "--t-end", "104.5")
    assert code == 0 and "events:" in out
    assert "no events in the window" in err and "t_first_us, t_last_us" in err
    code, _, err = run_cli(capsys, "info", path, "--t-start", "0", "--t-end", "0.5")
    assert code == 0 and "no events in the window" not in err


def test_calibrate_a_recording_without_its_window_says_so(tmp_path, capsys):
    """The most natural slip of the quiet-recording workflow, forgetting the window, gave "cannot read rec.aedat:
    'utf-8' codec can't decode bytes ..." (the file read as a rate table); an image gave the same."""
    pytest.importorskip("faery")
    rec = small_events_file(tmp_path / "rec.aedat4")
    code, _, err = run_cli(capsys, "calibrate", rec, "--out", tmp_path / "cam.toml")
    one_error_line(code, err, "is an event recording, not a rate table")
    assert "--t-start S --t-end S" in err
    grey_image(tmp_path / "photo.png")
    code, _, err = run_cli(capsys, "calibrate", tmp_path / "photo.png", "--out", tmp_path / "cam.toml")
    one_error_line(code, err, "is an image")
    assert not (tmp_path / "cam.toml").exists()
