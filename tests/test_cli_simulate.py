"""``evnoise simulate`` and ``evnoise info`` through the command line (in-process and one subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import evnoise as ev
from evnoise.cli import main

PIL_Image = pytest.importorskip("PIL.Image")
h5py = pytest.importorskip("h5py")


def grey_image(path, shape=(24, 32), seed=0, lo=0, hi=256):
    rng = np.random.default_rng(seed)
    PIL_Image.fromarray(rng.integers(lo, hi, size=shape, dtype=np.uint8)).save(path)
    return path


@pytest.fixture
def image(tmp_path):
    return grey_image(tmp_path / "scene.png")


@pytest.fixture
def frames(tmp_path):
    """Three 32x24 frames, named so that only a natural sort puts them in order."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, name in enumerate(("f1.png", "f2.png", "f10.png")):
        PIL_Image.fromarray(np.full((24, 32), 40 + 80 * i, dtype=np.uint8)).save(folder / name)
    return folder


def run_cli(capsys, *args):
    code = main(["-q", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def assert_clean_failure(code, err, folder, *, expect=None):
    """Exit code 2, one line ``evnoise: error: ...`` on stderr, and nothing new in ``folder``."""
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("evnoise: error: "), err
    if expect:
        assert expect in lines[0], lines[0]
    leftovers = [p.name for p in folder.iterdir() if p.suffix in (".h5", ".tmp") or p.name.startswith(".")]
    assert leftovers == [], leftovers


# --------------------------------------------------------------------------------------
# working runs
# --------------------------------------------------------------------------------------
def test_image_to_events_h5(tmp_path, image, capsys):
    out = tmp_path / "ev.h5"
    code = main(["simulate", str(image), "--out", str(out), "--duration", "2", "--seed", "5", "--max-lux", "3"])
    stdout, _ = capsys.readouterr()
    assert code == 0
    events, meta = ev.read_events(out)
    assert meta["shape"] == (24, 32) and meta["seed"] == 5 and meta["source"] == str(image)
    assert meta["scene"] == "static" and meta["duration_s"] == 2.0 and meta["t_end_us"] == 2_000_000
    assert ev.NoiseParams.from_dict(meta["params"]) == ev.load_preset("evk3-hd")
    assert events.size > 0 and events["t"].min() >= 0 and events["t"].max() < 2_000_000
    # the file holds what the library gives for the same scene and seed
    lux = ev.image_to_lux(image, max_lux=3.0)
    expected = ev.simulate_events(lux, ev.load_preset("evk3-hd"), 2.0, rng=5)
    assert events.tobytes() == expected.tobytes()
    # the summary paragraph
    on, off = int(events["p"].sum()), int((events["p"] == 0).sum())
    assert f"{events.size:,} events ({on:,} ON, {off:,} OFF)" in " ".join(stdout.split())
    assert "seed 5" in stdout and str(out) in " ".join(stdout.split())


def test_same_seed_same_file_for_any_thread_count(tmp_path, image, capsys):
    for threads in (1, 2):
        assert run_cli(capsys, "simulate", image, "--out", tmp_path / f"t{threads}.h5", "--duration", "1",
                       "--seed", "11", "--threads", threads)[0] == 0
    a, _ = ev.read_events(tmp_path / "t1.h5")
    b, _ = ev.read_events(tmp_path / "t2.h5")
    assert a.size > 0 and a.tobytes() == b.tobytes()


def test_random_seed_is_recorded(tmp_path, image, capsys):
    assert run_cli(capsys, "simulate", image, "--out", tmp_path / "a.h5", "--duration", "0.5")[0] == 0
    seed = ev.read_events(tmp_path / "a.h5")[1]["seed"]
    assert run_cli(capsys, "simulate", image, "--out", tmp_path / "b.h5", "--duration", "0.5",
                   "--seed", seed)[0] == 0
    assert ev.read_events(tmp_path / "a.h5")[0].tobytes() == ev.read_events(tmp_path / "b.h5")[0].tobytes()


def test_png_of_the_count_maps(tmp_path, image, capsys):
    code, _, _ = run_cli(capsys, "simulate", image, "--out", tmp_path / "ev.h5", "--png", tmp_path / "ev.png",
                         "--duration", "3", "--seed", "1")
    assert code == 0
    with PIL_Image.open(tmp_path / "ev.png") as im:
        assert im.format == "PNG" and im.mode == "RGB"
        assert im.height > 24 and im.width > 3 * 32  # scene, ON and OFF side by side, titles and colour bars
        pixels = np.asarray(im)
    assert pixels.std() > 0  # not blank
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ev.h5", "ev.png", "scene.png"]


def test_count_png_brightness_follows_counts(tmp_path):
    from evnoise.cli.simulate import save_count_png

    counts = np.zeros((2, 80, 400), dtype=np.int64)
    counts[0, :, 200:] = 50  # ON: right half busy
    counts[1, :40, :] = 5  # OFF: top half a little
    save_count_png(counts, tmp_path / "c.png")
    with PIL_Image.open(tmp_path / "c.png") as im:
        rgb = np.asarray(im.convert("RGB")).reshape(-1, 3)
    from evnoise.cli._pictures import LogScale, colormap

    scale = LogScale.of_rates(counts, floor=1.0)
    busy, some, none = (colormap(scale(np.array([c])))[0] for c in (50, 5, 0))
    assert tuple(none) == (0, 0, 0)  # black: no events, darker than the lowest rate
    assert tuple(busy) != tuple(some) and colormap([1.0]).mean() > colormap([0.5]).mean() > colormap([0.0]).mean()
    n = {name: int(np.all(rgb == c, axis=1).sum()) for name, c in (("busy", busy), ("some", some), ("none", none))}
    # the maps' pixels (the colour bar adds a few columns of each colour)
    assert 200 * 80 <= n["busy"] < 200 * 80 + 400 and 400 * 40 <= n["some"] < 400 * 40 + 400
    assert 200 * 80 + 400 * 40 <= n["none"] < 200 * 80 + 400 * 40 + 400


def test_folder_of_frames_is_a_video(tmp_path, frames, capsys):
    out = tmp_path / "video.h5"
    code, stdout, _ = run_cli(capsys, "simulate", frames, "--out", out, "--fps", "20", "--seed", "3")
    assert code == 0
    events, meta = ev.read_events(out)
    assert meta["scene"] == "video" and meta["n_frames"] == 3 and meta["fps"] == 20.0
    assert meta["t_end_us"] == 100_000 and events["t"].max() < 100_000
    # natural order f1, f2, f10: brightness rises twice, so signal events are ON
    lux = [ev.image_to_lux(frames / n) for n in ("f1.png", "f2.png", "f10.png")]
    expected = ev.simulate_video(lux, [0.0, 0.05, 0.1], ev.load_preset("evk3-hd"), rng=3)
    assert events.tobytes() == expected.tobytes()


def test_sensor_resize(tmp_path, capsys):
    image = grey_image(tmp_path / "big.png", shape=(48, 64))
    code, _, _ = run_cli(capsys, "simulate", image, "--out", tmp_path / "ev.h5", "--duration", "0.2",
                         "--sensor", "16x12", "--fit", "resize", "--seed", "1")
    assert code == 0
    meta = ev.read_events(tmp_path / "ev.h5")[1]
    assert meta["shape"] == (12, 16) and meta["fit"] == "resize"


def test_bundled_example(tmp_path, capsys):
    # the README's main job, on a smaller sensor to keep the test quick
    code, _, _ = run_cli(capsys, "simulate", "--example", "--duration", "0.2", "--sensor", "128x72", "--fit",
                         "resize", "--out", tmp_path / "example.h5", "--png", tmp_path / "example.png")
    assert code == 0
    meta = ev.read_events(tmp_path / "example.h5")[1]
    assert meta["shape"] == (72, 128) and "example" in meta["source"]
    assert (tmp_path / "example.png").stat().st_size > 0


def test_aedat4_output(tmp_path, image, capsys):
    faery = pytest.importorskip("faery")
    code, _, _ = run_cli(capsys, "simulate", image, "--out", tmp_path / "ev.aedat4", "--duration", "1",
                         "--seed", "4", "--png", tmp_path / "ev.png")
    assert code == 0
    got = faery.events_stream_from_file(tmp_path / "ev.aedat4").to_array()
    expected = ev.simulate_events(ev.image_to_lux(image), ev.load_preset("evk3-hd"), 1.0, rng=4)
    np.testing.assert_array_equal(got["t"], expected["t"])
    np.testing.assert_array_equal(got["on"], expected["p"] == 1)
    assert (tmp_path / "ev.png").exists()


def test_clip_invalid_exr(tmp_path, capsys):
    OpenEXR = pytest.importorskip("OpenEXR")
    y = np.ones((12, 16), dtype=np.float32)
    y[3, 4] = np.nan
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(hdr, {"Y": y}) as f:
        f.write(str(tmp_path / "nan.exr"))
    code = main(["simulate", str(tmp_path / "nan.exr"), "--out", str(tmp_path / "ev.h5"), "--clip-invalid",
                 "--duration", "0.1", "--lux-scale", "2"])
    _, err = capsys.readouterr()
    assert code == 0
    assert "nan.exr" in err and "clipped 1 NaN" in err
    assert ev.read_events(tmp_path / "ev.h5")[1]["lux_max"] == 2.0


# --------------------------------------------------------------------------------------
# bad input: one clear line, exit code 2, no output file
# --------------------------------------------------------------------------------------
def test_missing_input(tmp_path, capsys):
    code, _, err = run_cli(capsys, "simulate", tmp_path / "nothere.png", "--out", tmp_path / "ev.h5")
    assert_clean_failure(code, err, tmp_path, expect="not found")
    assert "nothere.png" in err


def test_empty_folder(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code, _, err = run_cli(capsys, "simulate", tmp_path / "empty", "--out", tmp_path / "ev.h5", "--fps", "30")
    assert_clean_failure(code, err, tmp_path, expect="no image files")


def test_corrupt_image(tmp_path, capsys):
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20)
    code, _, err = run_cli(capsys, "simulate", tmp_path / "bad.png", "--out", tmp_path / "ev.h5")
    assert_clean_failure(code, err, tmp_path, expect="bad.png")


def test_corrupt_frame_in_a_folder(tmp_path, frames, capsys):
    (frames / "f5.png").write_bytes(b"not a png")
    code, _, err = run_cli(capsys, "simulate", frames, "--out", tmp_path / "ev.h5", "--fps", "30")
    assert_clean_failure(code, err, tmp_path, expect="f5.png")


def test_frames_of_different_sizes(tmp_path, frames, capsys):
    grey_image(frames / "f3.png", shape=(20, 32))
    code, _, err = run_cli(capsys, "simulate", frames, "--out", tmp_path / "ev.h5", "--fps", "30")
    assert_clean_failure(code, err, tmp_path, expect="f3.png is 32x20 pixels")
    # fitting to a sensor size makes them agree
    code, _, _ = run_cli(capsys, "simulate", frames, "--out", tmp_path / "ev.h5", "--fps", "30",
                         "--sensor", "32x24", "--fit", "resize")
    assert code == 0


def test_frames_of_display_and_linear_kinds_are_not_mixed(tmp_path, frames, capsys):
    """An 8-bit PNG is scaled by --max-lux (display white = 18 lux), an EXR by --lux-scale (values are lux): a
    video mixing them jumped between two illuminance scales without a word."""
    OpenEXR = pytest.importorskip("OpenEXR")
    y = np.full((24, 32), 5.0, dtype=np.float32)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"Y": y}) as f:
        f.write(str(frames / "f3.exr"))
    code, _, err = run_cli(capsys, "simulate", frames, "--out", tmp_path / "ev.h5", "--fps", "30")
    assert_clean_failure(code, err, tmp_path, expect="f3.exr is a linear (EXR / floating-point) image, but the first")


def test_linear_image_beyond_the_lux_cap_is_refused(tmp_path, capsys):
    """--max-lux and --lux-scale stop at 1e9 lux; a float pixel storing 3e38 lux gave a file of no events, exit 0."""
    OpenEXR = pytest.importorskip("OpenEXR")
    y = np.full((4, 4), 1.0, dtype=np.float32)
    y[1, 2] = 3e38
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"Y": y}) as f:
        f.write(str(tmp_path / "sun.exr"))
    code, _, err = run_cli(capsys, "simulate", tmp_path / "sun.exr", "--out", tmp_path / "ev.h5")
    assert_clean_failure(code, err, tmp_path, expect="sun.exr reaches 3e+38 lux, above the 1e+09 lux")
    code, _, _ = run_cli(capsys, "simulate", tmp_path / "sun.exr", "--out", tmp_path / "ev.h5", "--lux-scale", "1e-30",
                         "--duration", "0.01")
    assert code == 0


def test_exr_with_nan(tmp_path, capsys):
    OpenEXR = pytest.importorskip("OpenEXR")
    y = np.ones((4, 4), dtype=np.float32)
    y[0, 0] = np.nan
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"Y": y}) as f:
        f.write(str(tmp_path / "nan.exr"))
    code, _, err = run_cli(capsys, "simulate", tmp_path / "nan.exr", "--out", tmp_path / "ev.h5")
    assert_clean_failure(code, err, tmp_path, expect="nan.exr has invalid pixel values (1 NaN)")


@pytest.mark.parametrize("flag, value", [("--duration", "-1"), ("--duration", "0"), ("--duration", "nan"),
                                         ("--fps", "-30"), ("--fps", "0")])
def test_negative_duration_or_fps(tmp_path, image, frames, capsys, flag, value):
    source = frames if flag == "--fps" else image
    code, _, err = run_cli(capsys, "simulate", source, "--out", tmp_path / "ev.h5", flag, value)
    assert_clean_failure(code, err, tmp_path, expect=f"{flag} must be finite and > 0")


def test_unwritable_output_directory(tmp_path, image, capsys):
    code, _, err = run_cli(capsys, "simulate", image, "--out", tmp_path / "no" / "dir" / "ev.h5")
    assert_clean_failure(code, err, tmp_path, expect="does not exist")
    code, _, err = run_cli(capsys, "simulate", image, "--out", image / "ev.h5")  # "directory" is a file
    assert_clean_failure(code, err, tmp_path, expect="not a directory")


def test_read_only_output_directory(tmp_path, image, capsys, monkeypatch):
    # root may write anywhere, so the permission answer is simulated
    import evnoise.io

    real_access = evnoise.io.os.access
    monkeypatch.setattr(evnoise.io.os, "access", lambda p, mode: False if str(p) == str(tmp_path) else
                        real_access(p, mode))
    code, _, err = run_cli(capsys, "simulate", image, "--out", tmp_path / "ev.h5")
    assert_clean_failure(code, err, tmp_path, expect="is not writable")


def test_existing_output_without_overwrite(tmp_path, image, capsys):
    out = tmp_path / "ev.h5"
    out.write_bytes(b"keep me")
    code, _, err = run_cli(capsys, "simulate", image, "--out", out, "--duration", "0.1")
    assert code == 2 and "already exists" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert out.read_bytes() == b"keep me"
    png = tmp_path / "ev.png"
    png.write_bytes(b"old png")
    code, _, err = run_cli(capsys, "simulate", image, "--out", tmp_path / "new.h5", "--png", png)
    assert code == 2 and "ev.png already exists" in err and not (tmp_path / "new.h5").exists()
    code, _, _ = run_cli(capsys, "simulate", image, "--out", out, "--png", png, "--duration", "0.1",
                         "--overwrite")
    assert code == 0 and ev.read_events(out)[0].dtype == ev.EVENT_DTYPE and png.read_bytes() != b"old png"


@pytest.mark.parametrize("args, expect", [
    (["--example", "IMAGE"], "not both"),
    ([], "no input"),
    (["IMAGE", "--fps", "30"], "--fps is for a folder"),
    (["FRAMES", "--duration", "1"], "--duration is for a single image"),
    (["FRAMES"], "give their frame rate with --fps"),
    (["IMAGE", "--sensor", "1280by720"], "--sensor must be WIDTHxHEIGHT"),
    (["IMAGE", "--preset", "no-such-camera"], "unknown preset"),
    (["IMAGE", "--seed", "-3"], "--seed must be a non-negative integer"),
    (["IMAGE", "--threads", "0"], "--threads must be >= 1"),
    (["IMAGE", "--lux-scale", "2"], "--lux-scale applies to linear"),
    (["IMAGE", "--sensor", "64x48", "--fit", "crop"], "cannot crop"),
    (["IMAGE", "--method", "renewal", "--png", "OUT"], "--png and --out name the same file"),
])
def test_argument_errors(tmp_path, image, frames, capsys, args, expect):
    out = tmp_path / "ev.h5"
    subst = {"IMAGE": str(image), "FRAMES": str(frames), "OUT": str(out)}
    code, _, err = run_cli(capsys, "simulate", *[subst.get(a, a) for a in args], "--out", out)
    assert_clean_failure(code, err, tmp_path, expect=expect)


def test_failure_during_simulation_leaves_no_files(tmp_path, image, capsys, monkeypatch):
    import evnoise.simulate as sim

    real = sim.iter_events

    def failing(*args, **kwargs):
        stream = real(*args, **kwargs)

        def gen():
            yield next(stream)
            raise ev.InputError("simulated failure half-way")

        return gen()

    monkeypatch.setattr(sim, "iter_events", failing)
    code, _, err = run_cli(capsys, "simulate", image, "--out", tmp_path / "ev.h5", "--png", tmp_path / "ev.png",
                           "--duration", "0.5")
    assert_clean_failure(code, err, tmp_path, expect="half-way")
    assert not (tmp_path / "ev.png").exists()


def test_subprocess_bad_input(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "evnoise", "-q", "simulate", str(tmp_path / "missing.png"),
                           "--out", str(tmp_path / "ev.h5")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [f"evnoise: error: input not found: {tmp_path / 'missing.png'}"]
    assert proc.stdout == ""
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------
# evnoise info
# --------------------------------------------------------------------------------------
def test_info_on_an_events_file(tmp_path, image, capsys):
    out = tmp_path / "ev.h5"
    assert run_cli(capsys, "simulate", image, "--out", out, "--duration", "2", "--seed", "9")[0] == 0
    events, _ = ev.read_events(out)
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "sensor:" in text and "32x24" in text and f"{events.size:,}" in text
    assert "seed:" in text and " 9" in text and "evk3-hd" in text and "trial_rate_hz" in text
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    n_on = int(events["p"].sum())
    assert info["kind"] == "events" and info["events"] == events.size
    assert info["ON"] == n_on and info["OFF"] == events.size - n_on
    assert info["duration_s"] == 2.0
    assert info["rate_per_pixel_hz"]["total"] == pytest.approx(events.size / (24 * 32 * 2.0))
    assert info["params"]["eps_pos"] == ev.load_preset("evk3-hd").eps_pos


def test_info_errors(tmp_path, capsys):
    code, _, err = run_cli(capsys, "info", tmp_path / "missing.h5")
    assert code == 2 and "not found" in err
    (tmp_path / "notes.md").write_text("hello")
    code, _, err = run_cli(capsys, "info", tmp_path / "notes.md")
    assert code == 2 and "notes.md" in err and "not a kind of file" in err
    # .txt is read as a text export of events: a file that is not one is one clean line too
    (tmp_path / "notes.txt").write_text("hello")
    code, _, err = run_cli(capsys, "info", tmp_path / "notes.txt")
    assert code == 2 and "notes.txt" in err and len(err.strip().splitlines()) == 1


def test_info_kinds_can_be_added(tmp_path, capsys, monkeypatch):
    from evnoise.cli import info

    monkeypatch.setattr(info, "KINDS", dict(info.KINDS))
    info.register_kind("greeting", lambda p: p.suffix == ".hello", lambda p: {"words": len(p.read_text().split())})
    (tmp_path / "a.hello").write_text("hi there you")
    assert main(["info", str(tmp_path / "a.hello"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"file": str(tmp_path / "a.hello"), "kind": "greeting",
                                                   "words": 3}
