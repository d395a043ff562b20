"""NoiseParams validation and presets."""

import dataclasses
import math
import re

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


def test_parameter_metadata_is_the_one_home_of_units_limits_and_fit_ranges():
    """Every field carries its spec; PARAM_LIMITS, calibration's tables and the groups derive from it."""
    from evnoise import params as P

    specs = P.parameter_specs()
    assert tuple(s.name for s in specs) == tuple(f.name for f in dataclasses.fields(ev.NoiseParams))
    assert P.parameter_names() == tuple(s.name for s in specs)
    for s in specs:
        assert s.group in P.GROUPS and s.fit_role in P.FIT_ROLES and s.unit
        # every lower limit is 0 but hot_pixel_regularity's: -1 stands for "leak_regularity's" (tied)
        assert P.PARAM_LIMITS[s.name] == s.high and s.low == (-1.0 if s.name == "hot_pixel_regularity" else 0.0)
        assert (s.fit_bounds is None) == (s.fit_role == "unmodelled")
        field = next(f for f in dataclasses.fields(ev.NoiseParams) if f.name == s.name)
        assert s.default == (None if field.default is dataclasses.MISSING else field.default)
    with pytest.raises(dataclasses.FrozenInstanceError):
        specs[0].high = 1.0
    assert P.parameter_spec("trial_rate_hz").unit == "Hz" and P.fit_bounds("eps_pos") == (1e-3, 5.0)
    assert P.names_in_group("threshold") == ("eps_pos", "eps_neg", "eps_sigma")
    assert P.names_with_fit_role("floor") == ("leak_on_hz", "leak_off_hz")
    with pytest.raises(ev.ParameterError, match="unknown noise parameter 'nope'"):
        P.parameter_spec("nope")
    with pytest.raises(ev.ParameterError, match="unknown parameter group"):
        P.names_in_group("nope")


@pytest.mark.parametrize("name", [s.name for s in __import__("evnoise.params").params.parameter_specs()])
def test_messages_name_the_value_and_the_allowed_range(name):
    from evnoise.params import parameter_spec

    s = parameter_spec(name)
    # -1 for every field but hot_pixel_regularity (where -1 means "tied"; its own message below)
    below = s.low - 1.0
    allowed = ("-1 \\(the same as leak_regularity\\) or between 0 and 1" if name == "hot_pixel_regularity"
               else f"finite and {s.low_text}")
    message = rf"NoiseParams\.{name} must be {allowed}, got {re.escape(repr(below))}"
    with pytest.raises(ev.ParameterError, match=message):
        ev.NoiseParams(**dict(GOOD, **{name: below}))
    with pytest.raises(ev.ParameterError, match=rf"NoiseParams\.{name} must be <= {re.escape(f'{s.high:g}')}.*, got"):
        ev.NoiseParams(**dict(GOOD, **{name: s.high * 2}))
    ev.NoiseParams(**dict(GOOD, **{name: s.high}))  # the limit itself is valid


def test_hot_pixel_regularity_is_tied_by_default_and_valid_only_at_minus_one_or_in_0_1():
    p = ev.NoiseParams(0.2, 0.2, 1.0, 100.0, 1.0, leak_on_hz=0.1, hot_pixel_fraction=0.01, hot_pixel_rate_hz=1.0,
                       leak_regularity=0.7)
    assert p.hot_pixel_regularity == -1.0 and p.hot_regularity == 0.7 and p.regular_background
    assert p.replace(hot_pixel_regularity=0.0).hot_regularity == 0.0
    # a timer for the hot pixels alone turns the regular background on
    q = p.replace(leak_regularity=0.0, hot_pixel_regularity=0.9)
    assert q.regular_background and q.hot_regularity == 0.9
    assert not q.replace(hot_pixel_fraction=0.0).regular_background  # no hot pixels: nothing is regular
    for bad in (-0.5, -1e-9, 1.5, -2.0):
        with pytest.raises(ev.ParameterError, match="hot_pixel_regularity"):
            p.replace(hot_pixel_regularity=bad)
