"""Oscillating pixels in quiet windows (issue 32): a lone pixel firing near-periodically is found, named, and on
request left out of the fit, consistently in the likelihoods, the goodness of fit and the simulated comparisons."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import poisson

import evnoise as ev
from evnoise.calibration.quiet import fit as q
from evnoise.calibration.quiet import goodness as qg
from evnoise.calibration.quiet import likelihood as ql
from evnoise.calibration.quiet import window as qw
from evnoise.errors import InputError

SHAPE = (30, 40)
DURATION_S = 6.0
T0_US = 1_000_000
#: the oscillator: ON every 0.2 s with a 4 ms jitter (interval CV ~0.03), at (x, y)
OSC_XY = (7, 11)
POISSON = ev.NoiseParams(eps_pos=5, eps_neg=5, bias_pr=2, trial_rate_hz=1000, photons_per_lux=1, leak_on_hz=0.3,
                         leak_off_hz=0.1)
HOT = POISSON.replace(hot_pixel_fraction=0.05, hot_pixel_rate_hz=6.0, hot_pixel_sigma=0.0)


def _background(params, seed):
    return ev.simulate_events(np.zeros(SHAPE), params, DURATION_S, rng=seed, t_start_us=T0_US)


def _oscillator(seed, period_s=0.2, jitter_s=0.004):
    rng = np.random.default_rng(seed)
    n = int(DURATION_S / period_s)
    t = np.arange(period_s / 2, DURATION_S, period_s)[:n] + rng.uniform(-jitter_s, jitter_s, size=n)
    osc = np.zeros(t.size, dtype=ev.EVENT_DTYPE)
    osc["t"] = T0_US + np.round(t * 1e6).astype(np.int64)
    osc["x"], osc["y"], osc["p"] = OSC_XY[0], OSC_XY[1], 1
    return osc


def _with_oscillator(events, seed):
    both = np.concatenate([events[(events["x"] != OSC_XY[0]) | (events["y"] != OSC_XY[1])], _oscillator(seed)])
    return both[np.argsort(both["t"], kind="stable")]


def _recording(tmp_path, events, name="still.h5"):
    path = tmp_path / name
    ev.write_events(path, events, SHAPE)
    return path


def test_a_lone_periodic_pixel_is_found_and_poisson_hot_pixels_are_not():
    events = _with_oscillator(_background(HOT, 3), 4)
    n_hot = np.bincount(events["y"].astype(np.int64) * SHAPE[1] + events["x"], minlength=SHAPE[0] * SHAPE[1])
    assert np.count_nonzero(n_hot >= qw.OSCILLATING_MIN_EVENTS) > 30  # busy Poisson pixels the rule must pass over
    found = qw.oscillating_pixels(events, SHAPE)
    assert [(o["x"], o["y"], o["polarity"]) for o in found] == [(OSC_XY[0], OSC_XY[1], 1)]
    assert found[0]["events"] == 30 and abs(found[0]["period_s"] - 0.2) < 0.002 and found[0]["cv"] < 0.1


def test_a_sensor_whose_every_pixel_leaks_regularly_has_no_oscillating_pixel():
    """The regular timer of the model (every pixel near-periodic at a similar rate) is not an oscillator: the rule
    asks for a rate far above the window's mean."""
    regular = POISSON.replace(leak_on_hz=4.0, leak_regularity=0.95)
    events = _background(regular, 5)
    key = (events["y"].astype(np.int64) * SHAPE[1] + events["x"]) * 2 + events["p"]
    periodic = 0
    for k in np.unique(key):
        t = np.sort(events["t"][key == k]) * 1e-6
        gaps = np.diff(t)
        periodic += t.size >= qw.OSCILLATING_MIN_EVENTS and np.std(gaps, ddof=1) < qw.OSCILLATING_MAX_CV * np.mean(gaps)
    assert periodic > SHAPE[0] * SHAPE[1] / 2  # most pixels alone look periodic
    assert qw.oscillating_pixels(events, SHAPE) == []


def test_leaving_a_pixel_out_removes_exactly_its_term_from_both_likelihoods(tmp_path):
    """Count and timing log-likelihoods of a Poisson model (no spread, no hot pixels): with the oscillator left out
    they are the full window's less that pixel's own term, computed here with SciPy (counts: two Poisson pmfs;
    times: the Poisson process density of its events)."""
    path = _recording(tmp_path, _with_oscillator(_background(POISSON, 6), 7))
    full = qw.quiet_window(path, 1.0, 1.0 + DURATION_S)
    dropped = qw.quiet_window(path, 1.0, 1.0 + DURATION_S, drop_oscillating=True)
    pix = OSC_XY[1] * SHAPE[1] + OSC_XY[0]
    assert full.excluded.size == 0 and list(dropped.excluded) == [pix]
    assert dropped.n_pixels == full.n_pixels - 1 and dropped.counts.reshape(2, -1)[:, pix].sum() == 0
    assert not np.any(dropped.events["pixel"] == pix) and np.count_nonzero(full.events["pixel"] == pix) == 30
    assert int(dropped.counts.sum()) == int(full.counts.sum()) - 30
    fit = q.fit_quiet([dropped], spread="off", hot="off", regularity="off")
    v = fit.values
    k_on, k_off = full.counts.reshape(2, -1)[:, pix]
    r_on, r_off = v["rate_on_hz"], v["rate_off_hz"]
    own_counts = poisson.logpmf(k_on, r_on * DURATION_S) + poisson.logpmf(k_off, r_off * DURATION_S)
    own_times = k_on * math.log(r_on) + k_off * math.log(r_off) - (r_on + r_off) * DURATION_S
    for timing, own in ((False, own_counts), (True, own_times)):
        model, groups = q.fit_model(fit, timing=timing)
        theta = np.array(q.theta_of(v, model))
        with_it = ql.mixture_log_likelihood(theta, model, ql.window_groups([full]))
        without = ql.mixture_log_likelihood(theta, model, groups)
        assert with_it - without == pytest.approx(own, rel=1e-9, abs=1e-9)


def test_windows_of_one_recording_leave_out_the_same_pixels(tmp_path):
    path = _recording(tmp_path, _with_oscillator(_background(POISSON, 8), 9))
    a = qw.quiet_window(path, 1.0, 4.0, drop_oscillating=True)
    b = qw.quiet_window(path, 4.0, 7.0, checks=True)
    assert a.excluded.size == 1 and b.excluded.size == 0
    with pytest.raises(InputError, match="exclude different pixels"):
        ql.window_groups([a, b])
    same = qw.same_exclusions([a, b])
    assert [list(w.excluded) for w in same] == [list(a.excluded)] * 2
    assert not np.any(same[1].events["pixel"] == a.excluded[0])
    # the same-pixel timing the fit's timing tests read is that of the window without the pixel
    both = qw.quiet_window(path, 4.0, 7.0, checks=True, drop_oscillating=True)
    timing = [next(c["same_pixel"] for c in w.checks if "same_pixel" in c) for w in (b, same[1], both)]
    assert timing[0]["n_intervals"] > timing[1]["n_intervals"]
    assert timing[1] == timing[2]
    other = qw.QuietWindow(b.counts, b.duration_s, source="another sensor")  # another group: untouched
    assert qw.same_exclusions([a, other])[1] is other
    with pytest.raises(InputError, match="flat indices"):
        qw.QuietWindow(b.counts, 1.0, excluded=[SHAPE[0] * SHAPE[1]])


def test_the_fit_names_the_oscillator_and_its_checks_see_the_window_without_it(tmp_path):
    path = _recording(tmp_path, _with_oscillator(_background(POISSON, 10), 11))
    kept = qw.quiet_window(path, 1.0, 1.0 + DURATION_S, checks=True)
    dropped = qw.quiet_window(path, 1.0, 1.0 + DURATION_S, checks=True, drop_oscillating=True)
    fits = {name: q.fit_quiet([w], spread="off", hot="off", regularity="off", timing="auto")
            for name, w in (("kept", kept), ("dropped", dropped))}
    note = [n for n in fits["kept"].notes if "oscillating" in n]
    assert len(note) == 1 and "x 7 y 11" in note[0] and "kept in the fit" in note[0]
    assert any("left out of the fit" in n for n in fits["dropped"].notes)
    assert "notes" in fits["dropped"].to_toml_tables()
    # the goodness of fit counts the pixels the fit uses: its expected events are n_pixels times the Poisson mean
    # below the largest count (SciPy), and so is the simulated comparison
    v = fits["dropped"].values
    for g in fits["dropped"].goodness:
        pol = 0 if g["polarity"] == "ON" else 1
        mu = (v["rate_on_hz"], v["rate_off_hz"])[pol] * DURATION_S
        k = np.arange(g["max_count"] + 1)
        assert g["expected_events"] == pytest.approx(dropped.n_pixels * np.dot(k, poisson.pmf(k, mu)), rel=1e-6)
        assert g["events"] == int(dropped.counts[pol].sum())
    sim = qg.compare_to_recording(fits["dropped"].to_params("evk3-hd"), dropped, replicas=2, seed=1)
    assert [s["events"] for s in sim] == [int(dropped.counts[0].sum()), int(dropped.counts[1].sum())]
    real = qg.window_intervals(dropped)
    assert real.size == qg.window_intervals(kept).size - 29  # the oscillator's 29 intervals are gone
    # the window's own events, as the checks read them, no longer hold the oscillator's pairs of ON events
    same = next(c["same_pixel"] for c in dropped.checks if "same_pixel" in c)
    assert same["n_intervals"] == real.size


def test_cli_drop_oscillating(tmp_path, capsys):
    from evnoise.cli import main

    rec = _recording(tmp_path, _with_oscillator(_background(POISSON, 12), 13))
    out = tmp_path / "cam.toml"
    assert main(["calibrate", str(rec), "--t-start", "1", "--t-end", "7", "--out", str(out), "--hot", "off",
                 "--spread", "off", "--regularity", "off", "--base", "evk3-hd", "--no-checks",
                 "--drop-oscillating"]) == 0
    doc = ev.params.load_preset_document(out)
    assert any("x 7 y 11" in n and "left out" in n for n in doc["fit"]["notes"])
    rate_on = doc["fit"]["values"]["rate_on_hz"]
    se = doc["fit"]["std_error"]["rate_on_hz"]
    assert abs(rate_on - 0.3) < 4 * se  # the oscillator's 5 Hz is not in the ordinary pixels' rate


REALDATA = __import__("pathlib").Path(__file__).resolve().parents[2] / "shared" / "data" / "realdata"


@pytest.mark.skipif(not (REALDATA / "quiet_segments.json").is_file(), reason=f"real recordings not found at {REALDATA}")
def test_the_real_windows_have_one_oscillating_pixel():
    """Of the nine shared quiet windows, two hold the DVS128 pixel (34, 95) firing ON every ~0.19 s (calibration/
    README); the rule flags it there and nothing else anywhere."""
    import json

    segments = json.loads((REALDATA / "quiet_segments.json").read_text(encoding="utf-8"))["segments"]
    found = {}
    for rel, windows in segments.items():
        for seg in windows:
            w = qw.quiet_window(REALDATA / rel, seg["t_from_us"] * 1e-6, seg["t_to_us"] * 1e-6)
            if w.oscillating:
                found[(rel.split("/")[-1], seg["from_s"])] = [(o["x"], o["y"], o["polarity"]) for o in w.oscillating]
    assert found == {("cam255_neal_standing_up2.aedat", 0.0): [(34, 95, 1)],
                     ("cam255_neal_standing_up.aedat", 0.0): [(34, 95, 1)]}


def test_many_busy_pixels_against_a_pixel_by_pixel_reference():
    """Many busy streams (periodic and Poisson, both polarities) are judged in one pass: the same pixels, periods
    and CVs as a plain per-stream loop with NumPy's std."""
    rng = np.random.default_rng(21)
    parts = [_background(POISSON, 22)]
    for i in range(120):
        n = int(rng.integers(15, 60))
        if i % 2:
            t = np.sort(rng.uniform(0, DURATION_S, n))  # Poisson-like
        else:
            period = DURATION_S / n
            t = np.arange(n) * period + rng.normal(0, period * rng.uniform(0.01, 0.4), n)
        e = np.zeros(n, dtype=ev.EVENT_DTYPE)
        e["t"] = T0_US + np.round(t * 1e6).astype(np.int64)
        e["x"], e["y"], e["p"] = i % SHAPE[1], (i // SHAPE[1]) % SHAPE[0], (i // 3) % 2
        parts.append(e)
    events = np.concatenate(parts)
    pix = events["y"].astype(np.int64) * SHAPE[1] + events["x"]
    events = events[np.lexsort((events["t"], pix))]  # not in time order: the function must not rely on it
    found = qw.oscillating_pixels(events, SHAPE)
    key = (events["y"].astype(np.int64) * SHAPE[1] + events["x"]) * 2 + (events["p"] == 1)
    mean = [np.count_nonzero(key % 2 == pol) / (SHAPE[0] * SHAPE[1]) for pol in (0, 1)]
    want = []
    for k in np.unique(key):
        t = np.sort(events["t"][key == k]) * 1e-6
        if t.size < qw.OSCILLATING_MIN_EVENTS or t.size < qw.OSCILLATING_RATE_FACTOR * mean[k % 2]:
            continue
        gaps = np.diff(t)
        cv = np.std(gaps, ddof=1) / np.mean(gaps)
        if cv < qw.OSCILLATING_MAX_CV:
            want.append((int(k // 2) % SHAPE[1], int(k // 2) // SHAPE[1], int(k % 2), t.size, np.mean(gaps), cv))
    got = [(o["x"], o["y"], o["polarity"], o["events"], o["period_s"], o["cv"]) for o in found]
    assert 20 < len(want) < 60
    assert sorted(g[:4] for g in got) == sorted(w[:4] for w in want)
    for g, w in zip(sorted(got), sorted(want)):
        assert g[4] == pytest.approx(w[4], rel=1e-12) and g[5] == pytest.approx(w[5], rel=1e-9)
