"""Hostile inputs of reconstruct and pretrain --ship: damaged events.h5 values, far-off last events, odd --scores
files and checkpoint bombs give one clear error line (exit 2), never a traceback, a hang or gigabytes of memory."""

from __future__ import annotations

import os
import re
import zipfile

import numpy as np
import pytest

from evnoise.errors import InputError, ParameterError

h5py = pytest.importorskip("h5py")
torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from evnoise.cli import main  # noqa: E402
from evnoise.reconstruct import infer  # noqa: E402
from evnoise.reconstruct.infer import counts_from_h5, default_model_path  # noqa: E402

N = 200


def write_h5(path, *, t=None, x=None, y=None, p=None, dtypes=None, attrs=None, t_offset=None):
    """A small events.h5 file (64x48 sensor, N events over 1 s) with the given columns replaced."""
    rng = np.random.default_rng(0)
    cols = {"t": np.sort(rng.integers(0, 1_000_000, N)), "x": rng.integers(0, 64, N), "y": rng.integers(0, 48, N),
            "p": rng.integers(0, 2, N)}
    cols.update({k: v for k, v in (("t", t), ("x", x), ("y", y), ("p", p)) if v is not None})
    types = {"t": "i8", "x": "u2", "y": "u2", "p": "u1", **(dtypes or {})}
    with h5py.File(path, "w") as f:
        f.attrs["width"] = 64
        f.attrs["height"] = 48
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
        g = f.create_group("events")
        for k in "txyp":
            g[k] = np.asarray(cols[k], types[k])
        if t_offset is not None:
            f.create_dataset("t_offset", data=np.int64(t_offset))
    return path


def one_error_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "WARNING" not in line]
    assert len(err) == 1, err
    assert err[0].startswith("evnoise: error:"), err
    return err[0]


# -- 1. reconstruct reads events.h5 as the readers (and evnoise info) do -------------------------------------------
@pytest.mark.parametrize("p_value, dtype", [(7, "u1"), (255, "u1"), (-1, "i1")])
def test_counts_take_any_nonzero_polarity_as_on(tmp_path, p_value, dtype):
    path = write_h5(tmp_path / "e.h5", p=np.full(N, p_value), dtypes={"p": dtype})
    counts, window = counts_from_h5(path, t_start_s=0.0, window_s=0.99)
    assert counts.shape == (2, 48, 64) and window == 0.99
    assert int(counts[0].sum()) > N // 2 and int(counts[1].sum()) == 0  # as the readers read them: ON


@pytest.mark.parametrize("case, expect", [
    ("x_negative", "not a pixel coordinate"),
    ("t_int64_max", "beyond +-2^62"),
    ("t_offset_huge", "beyond +-2^62"),
    ("width_text", "the width attribute must be an integer"),
])
def test_counts_refuse_what_info_refuses(tmp_path, case, expect):
    path = tmp_path / "e.h5"
    if case == "x_negative":
        write_h5(path, x=np.where(np.arange(N) == 3, -1, np.arange(N) % 64), dtypes={"x": "i8"})
    elif case == "t_int64_max":
        write_h5(path, t=np.r_[np.arange(N - 1) * 1000, 2**63 - 1])
    elif case == "t_offset_huge":
        write_h5(path, t_offset=2**62)
    else:
        write_h5(path, attrs={"width": "64"})
    with pytest.raises(InputError, match=expect.replace("+", r"\+").replace("^", r"\^")):
        counts_from_h5(path, t_start_s=0.0, window_s=0.5)


def test_counts_of_a_huge_declared_sensor_are_refused_before_allocating(tmp_path, monkeypatch):
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "1G")
    path = write_h5(tmp_path / "e.h5", attrs={"width": 65536, "height": 65536})
    with pytest.raises(InputError, match="65536x65536.*memory"):
        counts_from_h5(path, t_start_s=0.0, window_s=0.5)


def test_cli_reconstruct_refuses_a_negative_x_in_one_line(tmp_path, capsys):
    path = write_h5(tmp_path / "e.h5", x=np.where(np.arange(N) == 3, -1, np.arange(N) % 64), dtypes={"x": "i8"})
    out = tmp_path / "o.png"
    assert main(["reconstruct", str(path), "--out", str(out)]) == 2
    assert "/events/x[3] = -1" in one_error_line(capsys)
    assert not out.exists()


# -- 2. a far-off last event does not plan years of frames ---------------------------------------------------------
def far_off(tmp_path):
    t = np.r_[np.sort(np.random.default_rng(1).integers(0, 1_000_000, N - 1)), 2_000_000 * 10**6]  # 2e6 s
    return write_h5(tmp_path / "far.h5", t=t)


def test_cli_step_refuses_a_plan_of_millions_of_frames(tmp_path, capsys):
    path = far_off(tmp_path)
    assert main(["reconstruct", str(path), "--out", str(tmp_path / "s.png"), "--step", "1", "--window", "1"]) == 2
    line = one_error_line(capsys)
    assert f"{2_000_000:,} frames" in line and f"{infer.MAX_FRAMES:,}" in line and "--frames" in line
    assert not list(tmp_path.glob("s_*.png"))
    # narrowed, the same file works
    assert main(["-q", "reconstruct", str(path), "--out", str(tmp_path / "s.png"), "--step", "1", "--window", "1",
                 "--frames", "2"]) == 0
    assert sorted(p.name for p in tmp_path.glob("s_*.png")) == ["s_0000.png", "s_0001.png"]


def test_cli_fps_refuses_a_plan_of_millions_of_frames(tmp_path, capsys):
    path = far_off(tmp_path)
    out = tmp_path / "video"
    assert main(["reconstruct", str(path), "--out", str(out), "--fps", "1", "--window", "1"]) == 2
    line = one_error_line(capsys)
    assert "frames" in line and f"{infer.MAX_FRAMES:,}" in line
    assert line.endswith("give fewer frames (--frames), a later --t-start or a lower --fps (1 per second)"), line
    assert not out.exists()


def test_frame_plan_checks_the_memory_budget(monkeypatch):
    infer.check_frame_plan(10)
    with pytest.raises(ParameterError, match="more than the 1,000,000"):
        infer.check_frame_plan(infer.MAX_FRAMES + 1)
    with pytest.raises(ParameterError, match="steps"):
        infer.check_frame_plan(1, n_steps=infer.MAX_STEPS + 1)
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "1k")
    with pytest.raises(ParameterError, match="memory"):
        infer.check_frame_plan(1000)


# -- 3. pretrain --ship: its --scores files and its output ----------------------------------------------------------
@pytest.mark.parametrize("case, expect", [
    ("list", "JSON list, not an object"),
    ("metrics_int", "is not an object of scores"),
    ("metrics_text", "not a list starting with a finite number"),
    ("metrics_inf", "not a list starting with a finite number"),
    ("no_metrics", "no 'metrics'"),
    ("deep", "nested too deeply"),
    ("not_json", "not JSON"),
    ("fifo", "special file"),
    ("dev_zero", "special file"),
    ("too_big", "more than the"),
    ("no_name", "NAME=JSON"),
])
def test_ship_refuses_bad_scores_in_one_line(tmp_path, capsys, case, expect):
    path = tmp_path / "s.json"
    text = {"list": "[1, 2]", "metrics_int": '{"metrics": {"unet": 5}}',
            "metrics_text": '{"metrics": {"unet": {"psnr": ["x"]}}}',
            "metrics_inf": '{"metrics": {"unet": {"psnr": [1e999]}}}', "no_metrics": '{"n": 3}',
            "deep": "[" * 100_000 + "]" * 100_000, "not_json": "{oops", "no_name": "{}"}.get(case)
    if text is not None:
        path.write_text(text)
    elif case == "fifo":
        os.mkfifo(path)
    elif case == "dev_zero":
        path = "/dev/zero"
        if not os.path.exists(path):
            pytest.skip("no /dev/zero here")
    elif case == "too_big":
        with open(path, "wb") as fh:
            fh.truncate(17 * 1024 * 1024)
    item = f"={path}" if case == "no_name" else f"a={path}"
    out = tmp_path / "shipped.pt"
    assert main(["pretrain", "--ship", str(default_model_path()), "--scores", item, "--out", str(out)]) == 2
    assert expect in one_error_line(capsys)
    assert not out.exists()


def test_ship_takes_evaluate_scores(tmp_path, capsys):
    scores = tmp_path / "s.json"
    scores.write_text('{"n": 3, "metrics": {"unet": {"psnr": [20.5, 0.1], "ssim": [0.6, 0.01], "lpips": null}}}')
    out = tmp_path / "shipped.pt"
    assert main(["-q", "pretrain", "--ship", str(default_model_path()), "--scores", f"id={scores}",
                 "--out", str(out)]) == 0
    from evnoise.reconstruct.checkpoint import read_checkpoint

    assert read_checkpoint(out)["card"]["held_out_scores"]["id"]["unet"]["psnr"] == 20.5


@pytest.mark.parametrize("which", ["checkpoint", "scores"])
def test_ship_never_writes_over_its_input(tmp_path, capsys, which):
    model = tmp_path / "m.pt"
    model.write_bytes(default_model_path().read_bytes())
    scores = tmp_path / "s.json"
    scores.write_text('{"n": 1, "metrics": {"unet": {"psnr": [20.0, 0.0]}}}')
    before = {model: model.read_bytes(), scores: scores.read_bytes()}
    out = model if which == "checkpoint" else scores
    assert main(["pretrain", "--ship", str(model), "--scores", f"a={scores}", "--out", str(out), "--overwrite"]) == 2
    assert "never writes over its own input" in one_error_line(capsys)
    assert {p: p.read_bytes() for p in before} == before


# -- 4. checkpoint bombs -------------------------------------------------------------------------------------------
def test_checkpoint_bomb_is_refused_before_torch_inflates_it(tmp_path, capsys):
    """The shipped model's archive plus a deflated member of 128 MiB of zeros (a file of about 3.6 MB)."""
    bomb = tmp_path / "bomb.pt"
    with zipfile.ZipFile(default_model_path()) as zin, zipfile.ZipFile(bomb, "w") as zout:
        prefix = zin.namelist()[0].split("/")[0]
        for info in zin.infolist():
            zout.writestr(info, zin.read(info))
        member = zipfile.ZipInfo(f"{prefix}/data/blob")
        member.compress_type = zipfile.ZIP_DEFLATED
        block = bytes(1 << 24)
        with zout.open(member, "w", force_zip64=True) as dst:
            for _ in range(8):
                dst.write(block)
    assert bomb.stat().st_size < 8 << 20
    assert main(["info", str(bomb)]) == 2
    line = one_error_line(capsys)
    assert "compression bomb" in line and "137.7 MB" in line  # the model (3.5 MB) and 134.2 MB of zeros
    assert main(["reconstruct", str(write_h5(tmp_path / "e.h5")), "--model", str(bomb),
                 "--out", str(tmp_path / "o.png")]) == 2
    assert "compression bomb" in one_error_line(capsys)


def test_checkpoint_size_bound_is_the_largest_model(tmp_path, capsys):
    from evnoise.reconstruct import checkpoint
    from evnoise.reconstruct.unet import MAX_PARAMETERS

    assert checkpoint.MAX_CHECKPOINT_BYTES == 4 * 4 * MAX_PARAMETERS + (256 << 20)
    assert main(["-q", "info", str(default_model_path())]) == 0  # the shipped model still loads


def test_ship_as_a_library_call_checks_its_scores(tmp_path):
    """``ship(..., scores=...)`` called from Python took any dict: a result without ``metrics`` was a KeyError and
    a text mean a ValueError from deep inside; now one ParameterError naming the test set, and nothing written."""
    from evnoise.reconstruct.pretrain import ship

    out = tmp_path / "shipped.pt"
    for scores, expect in [({"id": {"n": 3}}, "scores['id'] is not an evaluate() result: it has no 'metrics'"),
                           ({"id": {"metrics": {"unet": {"psnr": ["x"]}}}}, "not a list starting with a finite"),
                           ([("id", {})], "must be a dict")]:
        with pytest.raises(ParameterError, match=re.escape(expect)):
            ship(default_model_path(), out, scores=scores)
        assert not out.exists()
