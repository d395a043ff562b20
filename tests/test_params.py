"""NoiseParams validation and presets."""

import dataclasses
import math

import pytest

import evnoise as ev

GOOD = dict(eps_pos=0.9, eps_neg=1.0, bias_pr=1.7, trial_rate_hz=22.0, photons_per_lux=1.0)


def test_valid_and_frozen():
    p = ev.NoiseParams(**GOOD, dark_lux=0.2, refractory_s=1e-4, eps_sigma=0.05)
    assert p.trial_us == pytest.approx(1e6 / 22.0)
    assert p.refractory_us == 100
    assert p.photons_per_trial(1.8) == pytest.approx(2.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.eps_pos = 1.0
    q = p.replace(eps_pos=0.5)
    assert q.eps_pos == 0.5 and p.eps_pos == 0.9
    assert ev.NoiseParams.from_dict(p.to_dict()) == p
    assert "eps_pos=0.9" in repr(p)


def test_refractory_rounds_up_to_whole_microseconds():
    assert ev.NoiseParams(**GOOD, refractory_s=79e-6).refractory_us == 79
    assert ev.NoiseParams(**GOOD, refractory_s=79.2e-6).refractory_us == 80
    assert ev.NoiseParams(**GOOD).refractory_us == 0


@pytest.mark.parametrize(
    "field, value",
    [("eps_pos", 0.0), ("eps_pos", -0.1), ("eps_neg", math.nan), ("bias_pr", -1.0), ("trial_rate_hz", 0.0),
     ("trial_rate_hz", -5.0), ("trial_rate_hz", math.inf), ("photons_per_lux", 0.0), ("dark_lux", -0.1),
     ("refractory_s", -1e-6), ("eps_sigma", math.nan), ("eps_pos", "abc"), ("trial_rate_hz", 2e6)],
)
def test_invalid_values_are_rejected_with_the_field_name(field, value):
    kwargs = dict(GOOD, **{field: value})
    with pytest.raises(ev.ParameterError, match=field):
        ev.NoiseParams(**kwargs)


def test_shipped_preset_loads():
    assert "evk3-hd" in ev.list_presets()
    p = ev.load_preset("evk3-hd")
    assert isinstance(p, ev.NoiseParams)
    assert 0 < p.eps_pos < 5 and 0 < p.eps_neg < 5 and p.trial_rate_hz > 0


def test_preset_from_file(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text("[params]\n" + "\n".join(f"{k} = {v}" for k, v in GOOD.items()) + "\n")
    assert ev.load_preset(path) == ev.NoiseParams(**GOOD)
    assert ev.load_preset(str(path)) == ev.NoiseParams(**GOOD)


def test_preset_errors(tmp_path):
    with pytest.raises(ev.ParameterError, match="unknown preset"):
        ev.load_preset("no-such-camera")
    with pytest.raises(ev.ParameterError, match="not found"):
        ev.load_preset(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[params\n")
    with pytest.raises(ev.ParameterError, match="TOML"):
        ev.load_preset(bad)
    extra = tmp_path / "extra.toml"
    extra.write_text("[params]\n" + "\n".join(f"{k} = {v}" for k, v in GOOD.items()) + "\nfoo = 1\n")
    with pytest.raises(ev.ParameterError, match="foo"):
        ev.load_preset(extra)
    missing = tmp_path / "missing_field.toml"
    missing.write_text("[params]\neps_pos = 1.0\n")
    with pytest.raises(ev.ParameterError, match="missing"):
        ev.load_preset(missing)


def test_import_is_light():
    """`import evnoise` must not import torch, colour, numba or scipy."""
    import subprocess
    import sys

    code = ("import sys, evnoise; "
            "print(','.join(m for m in ('torch', 'colour', 'numba', 'scipy', 'h5py') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""
