"""Shipped presets (sensor table, provenance) and ``evnoise presets``; the evk4 mapping against Noise2Params."""

from __future__ import annotations

import json
import math
import tomllib
from importlib import resources

import numpy as np
import pytest

import evnoise as ev
from evnoise.cli import main
from evnoise.params import list_presets, load_preset_document, preset_info

SHIPPED = list_presets()


def test_the_three_cameras_are_shipped():
    assert {"evk3-hd", "evk4", "davis346"} <= set(SHIPPED)


@pytest.mark.parametrize("name", SHIPPED)
def test_every_preset_loads_with_sensor_summary_and_provenance(name):
    params = ev.load_preset(name)
    assert isinstance(params, ev.NoiseParams)
    doc = load_preset_document(name)
    sensor = doc["sensor"]
    assert isinstance(sensor["width"], int) and sensor["width"] > 0
    assert isinstance(sensor["height"], int) and sensor["height"] > 0
    assert isinstance(sensor["name"], str) and sensor["name"]
    prov = doc["provenance"]
    assert isinstance(prov["summary"], str) and prov["summary"] and "\n" not in prov["summary"]
    assert len(prov) > 2  # more than a summary: where the numbers come from
    info = preset_info(name)
    assert info["width"] == sensor["width"] and info["height"] == sensor["height"]
    assert info["summary"] == prov["summary"]


def test_sensor_sizes():
    assert (preset_info("evk4")["width"], preset_info("evk4")["height"]) == (1280, 720)
    assert (preset_info("davis346")["width"], preset_info("davis346")["height"]) == (346, 260)


def test_list(capsys):
    assert main(["presets"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == len(SHIPPED)
    for line, name in zip(out, SHIPPED):
        assert line.startswith(name)
    assert any("346x260" in line for line in out)


def test_list_json(capsys):
    assert main(["presets", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["name"] for r in rows] == SHIPPED
    assert all(r["width"] and r["height"] and r["summary"] for r in rows)


def test_show(capsys):
    assert main(["presets", "evk4"]) == 0
    out = capsys.readouterr().out
    assert "refractory_s = 7.9e-05" in out
    assert "rate_rms_relative_error" in out
    assert "hot_pixel_on_fraction" not in out  # default: not shown
    assert "evk4.toml" in out


def test_show_json_and_path(capsys, tmp_path):
    assert main(["presets", "davis346", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["params"]["leak_on_hz"] == pytest.approx(0.2)
    assert d["width"] == 346
    copy = tmp_path / "mine.toml"
    copy.write_text((resources.files("evnoise") / "presets" / "evk4.toml").read_text())
    assert main(["presets", str(copy), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["name"] == "mine" and d["path"] == str(copy)


def test_unknown_name_one_error_line(capsys):
    assert main(["presets", "no-such-camera"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "no-such-camera" in err[0] and all(n in err[0] for n in SHIPPED)


@pytest.mark.parametrize("name", [
    "evk3-hd",  # no spread: no population-mean curve, fast
    pytest.param("davis346", marks=pytest.mark.slow),  # population mean (threshold and leak spread): ~20 s
])
def test_plot_writes_a_png(tmp_path, capsys, name):
    pytest.importorskip("matplotlib")
    from PIL import Image

    out = tmp_path / "rates.png"
    assert main(["presets", name, "--plot", str(out)]) == 0
    with Image.open(out) as img:
        assert img.format == "PNG"
        w, h = img.size
        assert 600 <= w <= 3000 and 300 <= h <= 2000
        pixels = np.asarray(img.convert("L"))
    assert pixels.std() > 5  # not blank
    assert not list(tmp_path.glob("*.tmp*"))
    # an existing plot is kept unless --overwrite
    before = out.read_bytes()
    assert main(["presets", name, "--plot", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err and out.read_bytes() == before
    assert main(["presets", name, "--plot", str(out), "--overwrite"]) == 0


def test_rate_curves_add_up():
    from evnoise.cli.presets import rate_curves

    params = ev.load_preset("evk4")
    lux = np.geomspace(0.01, 1000, 9)
    c = rate_curves(params, lux)
    # background far below the trial rate: the terms add (to first order in rate / trial rate)
    assert np.allclose(c["total"], c["shot noise"] + c["background"], rtol=0.03)


# --- evk4 against Noise2Params, recomputed independently from their published numbers -------------

def _their_probability(lam, B, coeffs, sign):
    """Saddle-point P for one lam (scalar root finding on the CGF of their comparison variable)."""
    from scipy.optimize import brentq

    c1, c2, c3 = coeffs
    theta = c1 + c2 * math.sqrt(lam) + c3 * lam
    e = math.exp(sign * B)  # ON: Z = n + th - e^B (n0 + th) > 0; OFF: Z = n + th - e^-B (n0 + th) < 0

    def k(s):
        return lam * math.expm1(s) + lam * math.expm1(-s * e) + theta * (1 - e) * s

    def k1(s):
        return lam * math.exp(s) - lam * e * math.exp(-s * e) + theta * (1 - e)

    def k2(s):
        return lam * math.exp(s) + lam * e * e * math.exp(-s * e)

    if sign > 0:
        s = brentq(lambda s: k1(s) - 1 / s, 1e-12, 200.0, xtol=1e-15, rtol=1e-13)
    else:
        s = brentq(lambda s: k1(s) - 1 / s, -200.0, -1e-12, xtol=1e-15, rtol=1e-13)
    return math.exp(k(s)) / (abs(s) * math.sqrt(2 * math.pi * (k2(s) + 1 / s**2)))


def test_evk4_reproduces_noise2params_within_stated_error():
    doc = load_preset_document("evk4")
    prov = doc["provenance"]
    B, alpha, R_us = 0.15, 4.5, 79.0
    on = (18.917319991515015, 35.49036559887983, 0.4394373558876216)
    off = (16.41747084565865, 37.42249743893243, 0.06759986822465787)
    floors = (9.567536526687546e-09, 3.178722048504662e-08)
    lux = np.geomspace(0.01, 1000, 61)
    p = np.array([[_their_probability(alpha * x, B, c, sign) + f for x in lux]
                  for c, sign, f in ((on, 1, floors[0]), (off, -1, floors[1]))])
    theirs = p / (1 + p.sum(axis=0) * R_us) * 1e6
    params = ev.load_preset("evk4")
    assert params.refractory_s == pytest.approx(79e-6)
    assert params.leak_on_hz == pytest.approx(floors[0] * 1e6)
    assert params.leak_off_hz == pytest.approx(floors[1] * 1e6)
    rel = ev.expected_rate(lux, params) / theirs - 1
    rms = float(np.sqrt(np.mean(rel**2)))
    # the preset states its error to 7 digits: ours must agree with it (same curve, same model)
    assert rms == pytest.approx(prov["rate_rms_relative_error"], rel=1e-4)
    assert float(np.abs(rel).max()) == pytest.approx(prov["rate_max_relative_error"], rel=1e-4)
    worst = np.unravel_index(int(np.argmax(np.abs(rel))), rel.shape)
    assert lux[worst[1]] == pytest.approx(prov["worst_at_lux"], rel=1e-6)
    # the peak (where the shot noise dominates) is placed right: same lux of the ON maximum within 25 %
    assert lux[np.argmax(ev.expected_rate(lux, params)[0])] == pytest.approx(lux[np.argmax(theirs[0])], rel=0.25)


def test_evk4_preset_is_valid_toml_with_their_parameters():
    text = (resources.files("evnoise") / "presets" / "evk4.toml").read_text()
    doc = tomllib.loads(text)
    assert doc["provenance"]["their_parameters"]["threshold"] == 0.15
    assert "saddle" in doc["provenance"]["their_model"]
