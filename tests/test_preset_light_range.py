"""Issue 32 section 4: every shipped preset records the light range it was fitted on, and `evnoise simulate`
warns (once, one line) when a scene leaves it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evnoise.cli import main
from evnoise.params import LightRange, light_range_warning, list_presets, load_preset, preset_light_range

PIL_Image = pytest.importorskip("PIL.Image")
pytest.importorskip("h5py")

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", list_presets())
def test_every_shipped_preset_has_a_light_range(name):
    light = preset_light_range(name)
    assert isinstance(light, LightRange)
    assert 0.0 <= light.lo < light.hi
    assert light.note  # where the range comes from
    assert light.note.startswith(("measured", "assumed"))
    # parameters made from the preset find it too
    assert preset_light_range(load_preset(name)) == light


def test_the_dvs128_range_is_marked_assumed():
    assert preset_light_range("dvs128").assumed
    assert preset_light_range("davis346").assumed
    assert not preset_light_range("evk3-hd").assumed


def test_parameters_of_no_preset_have_no_range():
    params = load_preset("evk3-hd").replace(eps_pos=0.3)
    assert preset_light_range(params) is None
    assert light_range_warning(params, 0.0, 1e6) is None


def test_warning_only_outside_the_range_by_more_than_the_factor():
    assert light_range_warning("evk3-hd", 0.0, 17.77) is None
    assert light_range_warning("evk3-hd", 0.0, 30.0) is None  # within x2
    assert "evk3-hd" in light_range_warning("evk3-hd", 0.0, 40.0)
    assert light_range_warning("evk4", 0.1, 20.0) is None
    assert light_range_warning("evk4", 0.05, 20.0) is not None  # below lo / 2
    message = light_range_warning("dvs128", 0.0, 18.0)
    assert "dvs128" in message and "18 lux" in message and "0 .. 0.05 lux" in message and "1000x" in message
    assert "\n" not in message


@pytest.fixture
def image(tmp_path):
    path = tmp_path / "ramp.png"
    PIL_Image.fromarray(np.linspace(0, 255, 24 * 32).reshape(24, 32).astype(np.uint8)).save(path)
    return path


def _simulate(tmp_path, image, capsys, *extra):
    code = main(["simulate", str(image), "--out", str(tmp_path / "out.h5"), "--duration", "0.01", "--seed", "1",
                 "--overwrite", *extra])
    _, err = capsys.readouterr()
    assert code == 0
    return [line for line in err.splitlines() if "fitted on" in line]


def test_simulate_warns_once_for_dvs128_at_the_default_white(tmp_path, image, capsys):
    lines = _simulate(tmp_path, image, capsys, "--preset", "dvs128")
    assert len(lines) == 1
    assert "WARNING" in lines[0] and "dvs128" in lines[0] and "0 .. 18 lux" in lines[0]


def test_simulate_quiet_hides_the_warning(tmp_path, image, capsys):
    assert _simulate(tmp_path, image, capsys, "--preset", "dvs128", "-q") == []


def test_simulate_inside_the_range_does_not_warn(tmp_path, image, capsys):
    assert _simulate(tmp_path, image, capsys, "--preset", "evk3-hd") == []
    assert _simulate(tmp_path, image, capsys, "--preset", "dvs128", "--max-lux", "0.05") == []


def test_simulate_video_warns_once(tmp_path, capsys):
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(3):
        PIL_Image.fromarray(np.full((8, 8), 100 + 50 * i, dtype=np.uint8)).save(folder / f"f{i}.png")
    code = main(["simulate", str(folder), "--fps", "100", "--out", str(tmp_path / "v.h5"), "--seed", "1",
                 "--preset", "dvs128"])
    _, err = capsys.readouterr()
    assert code == 0
    assert len([line for line in err.splitlines() if "fitted on" in line]) == 1


def test_presets_command_prints_the_range(capsys):
    assert main(["presets", "dvs128"]) == 0
    out, _ = capsys.readouterr()
    assert "fitted on: 0 .. 0.05 lux (assumed" in out


def test_a_few_black_pixels_do_not_warn_but_a_dark_scene_does(tmp_path, capsys):
    """evk4 was fitted on 0.15 .. 25 lux: a photograph with a few black pixels (under 1 % of them) is inside it,
    a scene whose dark part is a tenth of the image is not, and the line says how much lies outside."""
    scene = np.full((40, 50), 128, dtype=np.uint8)
    scene[0, :10] = 0  # 10 of 2000 pixels black: 0.5 %
    path = tmp_path / "photo.png"
    PIL_Image.fromarray(scene).save(path)
    assert _simulate(tmp_path, path, capsys, "--preset", "evk4") == []
    scene[:4] = 0  # 200 of 2000: 10 %
    PIL_Image.fromarray(scene).save(path)
    lines = _simulate(tmp_path, path, capsys, "--preset", "evk4")
    assert len(lines) == 1 and "(10 % of its pixels)" in lines[0]
    from evnoise.params import light_outside_range

    assert light_outside_range("evk4", np.array([0.0, 0.074, 0.076, 50.0, 50.3])) == (3, 5)
    assert light_outside_range(load_preset("evk4").replace(eps_pos=0.3), np.zeros(3)) == (0, 3)  # no recorded range

