"""Issue 29 section 3 (what a new user hit on the command line) and issue 35's absurd numbers, non-UTF-8 files
and a damaged Numba cache: each gives a result or one clean error line, never a traceback."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from _cli_helpers import small_events_file
from evnoise.cli import build_parser, main

PIL_Image = pytest.importorskip("PIL.Image")
h5py = pytest.importorskip("h5py")

REPO = Path(__file__).resolve().parents[1]


def run_cli(capsys, *args):
    code = main([*map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(code, err, expect=None):
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("evnoise: error: "), err
    if expect is not None:
        assert expect in lines[0], lines[0]


def grey_image(path, shape=(24, 32), value=128):
    PIL_Image.fromarray(np.full(shape, value, dtype=np.uint8)).save(path)
    return path




def subparsers():
    parser = build_parser()
    return parser._defaults["subparsers_action"].choices


# --------------------------------------------------------------------------------------
# item 12: -o is --out everywhere; help texts name every format read
# --------------------------------------------------------------------------------------
def test_o_is_out_in_every_command_that_has_out():
    with_out = []
    for name, sub in subparsers().items():
        for action in sub._actions:
            if "--out" in action.option_strings:
                with_out.append(name)
                assert "-o" in action.option_strings, f"evnoise {name}: --out has no -o"
    assert {"simulate", "make-dataset", "calibrate", "train", "evaluate", "reconstruct", "separate"} <= set(with_out)


def test_o_writes_like_out(tmp_path, capsys):
    events = small_events_file(tmp_path / "rec.h5")
    code, _, err = run_cli(capsys, "separate", events, "-o", tmp_path / "signal.h5", "-q")
    assert code == 0, err
    assert (tmp_path / "signal.h5").is_file()


def test_help_of_commands_that_read_any_event_file_does_not_say_events_h5_only():
    subs = subparsers()
    parser = build_parser()
    commands = parser._defaults["subparsers_action"]._choices_actions
    helps = {a.dest: a.help for a in commands}
    assert "events.h5 file" not in helps["reconstruct"] and "camera" in helps["reconstruct"]
    for name in ("reconstruct", "separate"):
        positional = next(a for a in subs[name]._actions if a.dest == "events")
        for suffix in (".h5", ".raw", ".dat", ".aedat4", ".aedat", ".es", ".csv", ".bin"):
            assert suffix in positional.help, (name, suffix)


# --------------------------------------------------------------------------------------
# issue 35: absurd numbers are one error line, before any work
# --------------------------------------------------------------------------------------
@pytest.fixture
def no_simulation(monkeypatch):
    """Fail the test if a simulation starts (the check must come before it)."""
    import evnoise.simulate as sim

    def refuse(*args, **kwargs):
        raise AssertionError("the simulation ran before the arguments were checked")

    monkeypatch.setattr(sim, "iter_events", refuse)
    monkeypatch.setattr(sim, "iter_video", refuse)


@pytest.mark.parametrize("argv, expect", [
    (["simulate", "IMAGE", "--duration", "1e308"], "--duration must be at most"),
    (["simulate", "IMAGE", "--duration", "inf"], "--duration must be finite"),
    (["simulate", "FRAMES", "--fps", "1e308"], "--fps must be at most"),
    (["simulate", "IMAGE", "--seed", str(2**64)], "--seed must be at most 2**63 - 1"),
    (["simulate", "IMAGE", "--seed", "-3"], "--seed must be a non-negative integer"),
    (["simulate", "IMAGE", "--threads", "0"], "--threads must be >= 1"),
    (["reconstruct", "EVENTS", "--threads", "100000"], "--threads must be <= 1024"),  # libgomp: Out of memory
    (["simulate", "IMAGE", "--duration", "abc"], "--duration must be a number"),
    (["reconstruct", "EVENTS", "--window", "1e308"], "--window must be at most"),
    (["reconstruct", "EVENTS", "--t-start", "1e308"], "--t-start must be at most"),
    (["reconstruct", "EVENTS", "--fps", "1e308"], "--fps must be at most"),
    (["reconstruct", "EVENTS", "--step", "1e-308"], "--step must be at least"),
    (["info", "EVENTS", "--t-start", "1e308"], "--t-start must be at most"),
    (["info", "EVENTS", "--t-end=-1e308"], "--t-end must be at most"),
    (["calibrate", "EVENTS", "--t-start", "0", "--t-end", "1e308"], "--t-end must be at most"),
    (["calibrate", "EVENTS", "--window", "0:1e308"], "at most"),
    (["make-dataset", "IMAGE", "--window", "1e308"], "--window must be at most"),
    (["make-dataset", "IMAGE", "--seed", str(2**64)], "--seed must be at most"),
    # 1e308 lux overflowed to NaN (simulate: a traceback; make-dataset: a worker that ignored SIGTERM for minutes)
    (["simulate", "IMAGE", "--max-lux", "1e308"], "--max-lux must be at most 1e+09 lux"),
    (["make-dataset", "IMAGE", "--max-lux", "6:1e308"], "--max-lux must be finite, > 0 and at most 1e+09 lux"),
    (["make-dataset", "--procedural", "dead-leaves", "--count", str(10**23)], "--count must be <= 1000000"),
    # a 65536x65536 sensor: an ArrayMemoryError traceback; 1e9 crops per image: a run of days (hostile-input review)
    (["make-dataset", "--procedural", "dead-leaves", "--count", "1", "--sensor", "65536x65536"],
     "--sensor 65536x65536 has more than the 67,108,864 pixels"),
    (["make-dataset", "IMAGE", "--crop", "4", "--crops-per-image", str(10**9)],
     "--crops-per-image must be at most 100,000"),
    # 1e9 starts: an ArrayMemoryError traceback (hostile-input review)
    (["calibrate", "--example", "--starts", str(10**9)], "--starts must be an integer from 1 to 1000"),
])
def test_absurd_numbers_are_one_line_before_any_work(tmp_path, capsys, no_simulation, argv, expect):
    image = grey_image(tmp_path / "g.png")
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(2):
        grey_image(frames / f"f{i}.png")
    events = small_events_file(tmp_path / "rec.h5")
    subst = {"IMAGE": image, "FRAMES": frames, "EVENTS": events}
    out = {"simulate": ["-o", tmp_path / "o.h5"], "reconstruct": ["-o", tmp_path / "r.png"], "info": [],
           "calibrate": ["-o", tmp_path / "c.toml"], "make-dataset": ["-o", tmp_path / "ds"]}[argv[0]]
    before = sorted(p.name for p in tmp_path.iterdir())
    code, _, err = run_cli(capsys, *[subst.get(a, a) for a in argv], *out)
    one_error_line(code, err, expect)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_a_preset_file_that_is_not_utf8_is_one_line(tmp_path, capsys, no_simulation):
    image = grey_image(tmp_path / "g.png")
    bad = tmp_path / "cam.toml"
    bad.write_bytes(b"eps_pos = 0.2\n# caf\xe9 (Latin-1)\n")
    cases = [
        (["simulate", image, "--preset", bad, "-o", tmp_path / "o.h5"], "--preset"),
        (["presets", bad], "preset"),
        (["make-dataset", image, "--preset", bad, "-o", tmp_path / "ds"], "--preset"),
        (["calibrate", "--example", "--initial", bad, "-o", tmp_path / "c.toml"], "--initial"),
    ]
    for argv, flag in cases:
        code, _, err = run_cli(capsys, *argv)
        one_error_line(code, err, f"{flag} {bad}: not UTF-8 text (byte 0xe9 at position 19)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cam.toml", "g.png"]


@pytest.mark.skipif(sys.platform in ("win32", "darwin"), reason="file names are bytes on Linux only")
def test_a_file_name_that_is_not_utf8_is_simulated_and_described(tmp_path, capsys):
    image = grey_image(tmp_path / os.fsdecode(b"sc\xe8ne.png"))
    out = tmp_path / os.fsdecode(b"\xe9v.h5")
    code, _, err = run_cli(capsys, "simulate", image, "--duration", "0.01", "--seed", "1", "-o", out, "-q")
    assert code == 0, err
    from evnoise.io import read_metadata

    meta = read_metadata(out)
    assert meta["source"].endswith("sc\\xe8ne.png")  # the byte, escaped: stored as UTF-8 text
    code, text, err = run_cli(capsys, "info", out)
    assert code == 0, err
    assert "events.h5" in text


def test_separate_takes_a_file_name_that_is_not_utf8(tmp_path, capsys):
    """issue 35 §4: a recording whose name is not UTF-8 is separated; its name is stored with the byte escaped."""
    rec = small_events_file(tmp_path / os.fsdecode(b"r\xe9c.h5"))
    out = tmp_path / os.fsdecode(b"s\xe9p.h5")
    code, _, err = run_cli(capsys, "separate", rec, "-o", out, "-q")
    assert code == 0, err
    from evnoise.io import read_metadata

    assert read_metadata(out)["source"].endswith("r\\xe9c.h5")


def test_a_damaged_numba_cache_is_one_line_naming_the_folder_to_delete(tmp_path):
    pytest.importorskip("numba")
    (tmp_path / "tinymod.py").write_text(textwrap.dedent("""
        import numba

        @numba.njit(cache=True)
        def plus_one(x):
            return x + 1
    """))
    cache = tmp_path / "cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONPATH": f"{tmp_path}{os.pathsep}{REPO}"}
    subprocess.run([sys.executable, "-c", "import tinymod; tinymod.plus_one(1)"], env=env, check=True,
                   timeout=300)
    damaged = list(cache.rglob("*.nbc"))
    assert damaged
    for path in damaged:
        path.write_bytes(b"\x15 not a pickle")
    script = textwrap.dedent("""
        import sys
        import tinymod
        from evnoise.cli import info, main

        info.run = lambda args: tinymod.plus_one(1)
        sys.exit(main(["info", "anything"]))
    """)
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("evnoise: error: the cache of compiled kernels is damaged"), \
        proc.stderr
    assert str(damaged[0].parent) in lines[0] and "delete the folder" in lines[0]


# --------------------------------------------------------------------------------------
# item 5: a recording shorter than the model's window gives an image, not a black PNG
# --------------------------------------------------------------------------------------
def test_reconstruct_a_45_ms_recording_is_not_black(tmp_path, capsys):
    pytest.importorskip("torch")
    from evnoise.reconstruct.infer import Reconstructor, default_model_path

    rec = Reconstructor(default_model_path(), threads=1)
    assert min(rec.spec.windows_s) >= 0.5  # the shipped model was trained on longer windows
    events = tmp_path / "short.h5"
    code, _, err = run_cli(capsys, "simulate", "--example", "--sensor", "320x180", "--duration", "0.045",
                           "--seed", "5", "-o", events, "-q")
    assert code == 0, err
    code, _, err = run_cli(capsys, "reconstruct", events, "-o", tmp_path / "r.png")
    assert code == 0, err
    # says what it did, and what to do
    assert "counts are scaled by" in err and "make a dataset with --window 0.045" in err
    image = np.asarray(PIL_Image.open(tmp_path / "r.png"), dtype=np.float64)
    assert image.mean() > 40 and image.std() > 5  # was all 0: the Anscombe input of empty pixels out of range


def test_a_short_window_is_shown_to_the_model_as_the_same_rates_over_its_window():
    torch = pytest.importorskip("torch")
    from evnoise.reconstruct.infer import Reconstructor, default_model_path, model_window

    rec = Reconstructor(default_model_path(), threads=1)
    trained = min(rec.spec.windows_s)
    assert model_window(rec.spec, trained / 10) == trained
    assert model_window(rec.spec, trained * 2) == trained * 2  # longer windows as they are
    counts = np.random.default_rng(0).poisson(0.05, (2, 32, 48))
    torch.manual_seed(0)
    short = rec.predict_binned(counts, trained / 20)
    scaled = rec.predict_binned(counts * 20.0, trained)
    np.testing.assert_allclose(short, scaled, atol=1e-6)


# --------------------------------------------------------------------------------------
# item 7: times on a Unix clock are printed to the microsecond
# --------------------------------------------------------------------------------------
UNIX_T0_US = 1_643_240_000_000_000  # 2022-01-26, a DV camera's clock


def unix_clock_file(path, shape=(16, 20), n=600):
    rng = np.random.default_rng(3)
    t = np.sort(rng.integers(0, 1_000_000, n)) + UNIX_T0_US
    events = ev.events.make_events(t, rng.integers(0, shape[1], n), rng.integers(0, shape[0], n),
                                   rng.integers(0, 2, n))
    return ev.write_events(path, events, shape, t_offset_us=UNIX_T0_US)


def test_info_prints_unix_clock_windows_to_the_microsecond(tmp_path, capsys, monkeypatch):
    import evnoise.cli.info
    import evnoise.readers.stats

    titles = []

    def fake_png(path, counts, *, title="", overwrite=False):
        titles.append(title)
        Path(path).write_bytes(b"png")

    monkeypatch.setattr(evnoise.cli.info, "stats_png", fake_png, raising=False)
    monkeypatch.setattr(evnoise.readers.stats, "stats_png", fake_png, raising=False)
    path = unix_clock_file(tmp_path / "unix.h5")
    code, out, err = run_cli(capsys, "info", path, "--t-start", "1643240000.25", "--t-end", "1643240000.750001",
                             "--stats", "--png", tmp_path / "stats.png")
    assert code == 0, err
    assert "1.64324e+09" not in out
    assert "t_start_s:  1643240000.25\n" in out and "t_end_s:    1643240000.750001\n" in out
    assert titles and "t 1643240000.25" in titles[0] and "-1643240000.750001 s" in titles[0], titles


# --------------------------------------------------------------------------------------
# item 6: info --stats --png shows a pixel with one event in colour, not black
# --------------------------------------------------------------------------------------
def test_info_png_shows_pixels_with_one_event(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    shape = (40, 60)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    t = np.arange(yy.size) * 100
    events = ev.events.make_events(t, xx.ravel(), yy.ravel(), np.ones(yy.size, dtype=int))  # one ON event each
    path = ev.write_events(tmp_path / "ones.h5", events, shape, t_end_us=int(t[-1]) + 1)
    png = tmp_path / "ones.png"
    code, _, err = run_cli(capsys, "info", path, "--stats", "--png", png)
    assert code == 0, err
    rgb = np.asarray(PIL_Image.open(png).convert("RGB"), dtype=np.int64)
    on_panel = rgb[:, : rgb.shape[1] // 3]  # the ON count map and its colour bar
    black = np.mean(on_panel.max(axis=2) < 25)
    assert black < 0.05, f"{black:.0%} of the ON panel is black: its pixels with one event are drawn black"


def test_seconds_text():
    from evnoise._clock import seconds_text

    assert seconds_text(1643240000.05) == "1643240000.05"
    assert seconds_text(1643240000.000001) == "1643240000.000001"
    assert seconds_text(0.5) == "0.5" and seconds_text(12.0) == "12" and seconds_text(-0.0) == "0"


def test_quiet_window_names_unix_clock_times_to_the_microsecond(tmp_path):
    from evnoise.calibration.quiet import quiet_window

    path = unix_clock_file(tmp_path / "unix.h5")
    w = quiet_window(path, 1643240000.0, 1643240000.9)
    assert w.describe() == "unix.h5 1643240000-1643240000.9 s"


# --------------------------------------------------------------------------------------
# item 8: every long phase shows progress
# --------------------------------------------------------------------------------------
def test_calibrate_shows_each_phase_after_the_search(capsys, monkeypatch):
    from importlib import resources

    from evnoise.calibration import read_measurements
    from evnoise.calibration.rates import fit as F

    ran = []

    def phase(name, value):
        def run(*args, **kwargs):
            ran.append(name)
            return value
        return run

    # the phases themselves are stand-ins: this test is about what the user sees while they run
    monkeypatch.setattr(F, "run_search", phase("search", ("problem", "theta")))
    monkeypatch.setattr(F, "rejected", lambda problem, theta: False)
    monkeypatch.setattr(F, "profile_likelihood", phase("profile", ("theta", "profile")))
    monkeypatch.setattr(F, "finish", phase("finish", "result"))
    meas = read_measurements(str(resources.files("evnoise.data") / "rates-example.csv"))
    capsys.readouterr()
    assert F.calibrate(meas, rng=0, progress=True) == "result"
    err = capsys.readouterr().err
    assert ran == ["search", "profile", "finish"]
    for name in ("calibrate: search", "calibrate: profile of photons_per_lux",
                 "calibrate: uncertainties and goodness of fit"):
        assert name in err, err
    assert "2/3 phases" in err  # three phases planned and counted (the last redraw may be throttled)
    assert F.calibrate(meas, rng=0, progress=False) == "result"
    assert capsys.readouterr().err == ""  # progress=False (-q): nothing


def test_a_phase_line_keeps_its_clock_running(monkeypatch, capsys):
    import time

    from evnoise.calibration import _progress

    monkeypatch.setattr(_progress, "REFRESH_S", 0.01)
    with _progress.Phases("fit", 1) as phases, phases.phase("a long phase"):
        give_up = time.monotonic() + 120  # a guard against a hang, not a timing: any redraw rate passes
        while phases.redraws < 3 and time.monotonic() < give_up:
            time.sleep(0.01)
        assert phases.redraws >= 3  # redrawn although the phase never advanced
    assert "fit: a long phase" in capsys.readouterr().err


@pytest.mark.long
def test_quiet_fit_and_checks_show_progress(tmp_path, capsys):
    from evnoise.calibration.quiet import fit_quiet, quiet_window

    rng = np.random.default_rng(7)
    n = 3000
    t = np.sort(rng.integers(0, 4_000_000, n))
    events = ev.events.make_events(t, rng.integers(0, 40, n), rng.integers(0, 30, n), rng.integers(0, 2, n))
    path = ev.write_events(tmp_path / "quiet.h5", events, (30, 40), t_end_us=4_000_000)
    capsys.readouterr()
    window = quiet_window(path, 0.0, 4.0, checks=True, progress=True)
    err = capsys.readouterr().err
    assert "checks of quiet.h5" in err and "/600" in err  # 3 checks x 200 resamples
    fit_quiet([window], base="dvs128", hot="off", progress=True)
    err = capsys.readouterr().err
    for name in ("quiet fit: full model", "quiet fit: test of regularity", "quiet fit: test of spread",
                 "quiet fit: standard errors", "quiet fit: goodness of fit"):
        assert name in err, err
    fit_quiet([window], base="dvs128", hot="off")
    assert capsys.readouterr().err == ""


def test_reconstruct_asks_for_the_sensor_size_before_anything_else(tmp_path, capsys):
    pytest.importorskip("torch")
    csv = tmp_path / "rec.csv"
    rng = np.random.default_rng(8)
    t = np.sort(rng.integers(0, 200_000, 50))
    csv.write_text("t,x,y,p\n" + "".join(f"{a},{b},{c},{d}\n" for a, b, c, d in
                                         zip(t, rng.integers(0, 30, 50), rng.integers(0, 20, 50),
                                             rng.integers(0, 2, 50), strict=True)))
    code, _, err = run_cli(capsys, "reconstruct", csv, "-o", tmp_path / "r.png")
    one_error_line(code, err, "gives no sensor size; add --sensor WxH")  # no model warnings before it


@pytest.mark.parametrize("signal_exc, code, line", [("Terminated", 143, "evnoise: terminated"),
                                                     ("KeyboardInterrupt", 130, "evnoise: interrupted")])
def test_a_signal_inside_compiled_code_is_not_a_traceback(tmp_path, capsys, monkeypatch, signal_exc, code, line):
    # SIGTERM (or Ctrl-C) handled while a Numba function runs comes back as a SystemError caused by it
    import evnoise.cli as cli
    from evnoise.cli import info

    cause = cli.Terminated() if signal_exc == "Terminated" else KeyboardInterrupt()

    def compiled_code_interrupted(args):
        raise SystemError("CPUDispatcher(<function f>) returned a result with an exception set") from cause

    monkeypatch.setattr(info, "run", compiled_code_interrupted)
    got, _, err = run_cli(capsys, "info", small_events_file(tmp_path / "rec.h5"))
    assert got == code and err.strip().splitlines() == [line], err


@pytest.mark.parametrize("ending", ["terminated", "finished"])
def test_a_late_sigterm_retry_is_one_line_not_a_traceback(tmp_path, capsys, monkeypatch, ending):
    """After a SIGTERM, a timer raises Terminated again every 0.5 s until the command is left: landing between the
    command's end and the handler's removal it printed a traceback after "evnoise: terminated" (2 of 3 kills of a
    long reconstruct), and landing in a weakref callback Python printed "Exception ignored in ...". Simulated at both
    moments: one line, exit 143."""
    import evnoise.cli as cli
    from evnoise.cli import info

    restore = cli._restore_sigterm
    calls = []

    def alarm_lands_here(previous):
        if not calls:
            calls.append(1)
            raise cli.Terminated()
        restore(previous)

    def command(args):
        sys.unraisablehook(type("U", (), {"exc_value": cli.Terminated(), "exc_type": cli.Terminated,
                                          "exc_traceback": None, "err_msg": None, "object": None})())
        if ending == "terminated":
            raise cli.Terminated()

    monkeypatch.setattr(cli, "_restore_sigterm", alarm_lands_here)
    monkeypatch.setattr(info, "run", command)
    hook = sys.unraisablehook
    try:
        got, _, err = run_cli(capsys, "info", small_events_file(tmp_path / "rec.h5"))
    except cli.Terminated:  # a KeyboardInterrupt: it would stop the whole test run
        pytest.fail("Terminated escaped from main()")
    assert got == 143 and err.strip().splitlines() == ["evnoise: terminated"], err
    assert sys.unraisablehook is hook and len(calls) == 1


def test_info_states_each_formats_time_convention(tmp_path, capsys):
    """issue 31: the clock a format's owner uses is stated by info (.raw/.dat: the camera's clock as stored)."""
    import json

    events = np.zeros(50, dtype=ev.EVENT_DTYPE)
    events["t"] = 5_000_000 + np.arange(50) * 100
    events["x"], events["y"], events["p"] = np.arange(50) % 8, np.arange(50) % 6, np.arange(50) % 2
    for suffix, needle in ((".raw", "Prophesee's convention"), (".dat", "Prophesee's convention"),
                           (".h5", "/t_offset"), (".es", "Event Stream counts from 0")):
        path = tmp_path / f"rec{suffix}"
        ev.write_events(path, events, (6, 8))
        assert main(["info", str(path), "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert needle in out["clock"], (suffix, out["clock"])
        if suffix in (".raw", ".dat"):
            assert out["t_first_us"] == 5_000_000  # the clock itself, no offset
