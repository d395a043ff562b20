"""Issue 35: files from strangers and absurd numbers. Every case here crashed (a segfault), hung,
allocated without bound or read or wrote outside what the user named before it was fixed; now
each gives a right answer or one clear evnoise error."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from evnoise.cli import main

REPO = Path(__file__).resolve().parents[1]
GOOD = dict(eps_pos=0.2, eps_neg=0.2, bias_pr=1.7, trial_rate_hz=1000.0, photons_per_lux=1.0)


def run_cli(capsys, *args):
    code = main([*map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(code, err, expect):
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("evnoise: error: "), err
    assert expect in lines[0], lines[0]


def run_python(code: str, limit_s: float = 300.0) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter (a crash there fails the test instead of killing pytest);
    ``limit_s`` only stops a hang from hanging the suite, it is no speed requirement."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=limit_s, cwd=REPO)


# --------------------------------------------------------------------------------------
# 1. thresholds past 43, absurd parameters
# --------------------------------------------------------------------------------------
def _mp_log_p(lam, eps, b, terms=40):
    """Reference ``log p`` at 60 digits: ``sum_m pmf(m) P(N > k(m))`` with ``k(m) = m + floor(c (m + b))``,
    ``c = expm1(eps)`` as the kernel rounds it, the tails by their upward series."""
    mpmath = pytest.importorskip("mpmath")
    mp = mpmath.mp
    mp.dps = 60
    c = mpmath.mpf(math.expm1(eps))
    lam = mpmath.mpf(lam)
    logs = []
    for m in range(terms):
        k = m + mpmath.floor(c * (m + mpmath.mpf(b)))
        a = k + 1  # P(N > k) = pmf(a) (1 + lam / (a + 1) + lam^2 / ((a + 1)(a + 2)) + ...)
        s, t, n = mpmath.mpf(1), mpmath.mpf(1), a
        for _ in range(60):
            n += 1
            t *= lam / n
            s += t
        log_pmf_a = -lam + a * mpmath.log(lam) - mpmath.loggamma(a + 1)
        log_pmf_m = -lam + m * mpmath.log(lam) - mpmath.loggamma(m + 1)
        logs.append(log_pmf_m + log_pmf_a + mpmath.log(s))
    top = max(logs)
    return float(top + mpmath.log(mpmath.fsum(mpmath.exp(x - top) for x in logs)))


def test_thresholds_past_43_do_not_crash_any_entry_point():
    # Numba's math.floor is an int64: k(m) wrapped to a negative count and indexed memory before the
    # kernel's table (exit 139) in every entry point built on the probability
    code = """
import numpy as np, evnoise as ev
print(float(ev.event_probability(5.0, 43.0, 1.7)), float(ev.log_event_probability(5.0, 50.0, 1.7)))
lux = np.full((3, 4), 50.0)
params = ev.NoiseParams(eps_pos=0.2, eps_neg=0.2, bias_pr=1.7, trial_rate_hz=1000.0, photons_per_lux=1.0)
big = np.full((2, 3, 4), 50.0)
print(float(ev.expected_rate(lux, params, thresholds=big).sum()))
print(ev.simulate_events(lux, params, 0.05, rng=1, thresholds=big).size)
print(ev.simulate_events(lux, params, 0.05, rng=1, thresholds=big, method="trials").size)
print(ev.NoiseStream((3, 4), params, rng=1, thresholds=big).advance(lux, 50000).size)
"""
    proc = run_python(code)
    assert proc.returncode == 0, proc.stderr[-2000:]
    first, rate, n_renewal, n_trials, n_stream = proc.stdout.split("\n")[:5]
    p, log_p = map(float, first.split())
    assert p == 0.0 and math.isfinite(log_p) and log_p < -1e23
    # the trials tier compared counts against the wrapped (negative) threshold: an event every trial
    assert float(rate) == 0.0 and int(n_renewal) == 0 and int(n_trials) == 0 and int(n_stream) == 0


@pytest.mark.parametrize("eps, b", [(43.0, 1.7), (50.0, 1.7), (44.5, 0.3), (30.0, 1e15), (0.2, 1e100)])
def test_log_probability_for_huge_thresholds_matches_a_60_digit_sum(eps, b):
    want = _mp_log_p(5.0, eps, b)
    got = float(ev.log_event_probability(5.0, eps, b))
    assert got == pytest.approx(want, rel=1e-13)


def test_zero_bias_keeps_the_dark_reference_event_for_any_threshold():
    # n0 = 0, b = 0: any photon is an infinite log step, so p >= pmf(0) P(N > 0) whatever eps is
    # (c * (m + b) = inf * 0 must not turn into NaN)
    want = -5.0 + math.log1p(-math.exp(-5.0))
    for eps in (43.0, 200.0, 800.0):
        with np.errstate(over="ignore"):
            assert float(ev.log_event_probability(5.0, eps, 0.0)) == pytest.approx(want, rel=1e-12)
    with np.errstate(over="ignore"):
        assert float(ev.log_event_probability(5.0, 800.0, 1.7)) == -math.inf  # c = inf, b > 0: never


def test_huge_photon_counts_use_the_saddle_point_form_and_agree_with_the_exact_sum():
    # the exact sum costs ~sqrt(lam) (and never ended past 2^53: m - 1 == m); above LAM_EXACT_MAX
    # the saddle-point form takes over. Here both are evaluated where the sum is still cheap.
    from evnoise._kernels.poisson import (
        LAM_EXACT_MAX,
        log_event_probability_exact,
        log_event_probability_saddlepoint,
    )

    for lam in (1e8, 1e10):
        for eps in (1e-5, 1e-3, 0.2, 3.0):
            c = math.expm1(eps)
            exact = log_event_probability_exact(lam, c, 1.7)
            rel = 1e-4 if lam < 1e9 else 1e-6
            assert log_event_probability_saddlepoint(lam, c, 1.7) == pytest.approx(exact, rel=rel)
    assert LAM_EXACT_MAX <= 2.0**52
    for lam in (1e16, 1e300):
        v = float(ev.log_event_probability(lam, 0.2, 1.7))
        assert math.isfinite(v) and v < -1e13
    # near the mean the normal form: S = n - (1 + c) n0 has mean -lam c and variance lam (1 + (1 + c)^2)
    c = math.expm1(1e-9)
    z = (1.7 * c + 1e16 * c) / math.sqrt(1e16 * (1.0 + (1.0 + c) ** 2))
    want = math.log(0.5 * math.erfc(z / math.sqrt(2)))
    assert float(ev.log_event_probability(1e16, 1e-9, 1.7)) == pytest.approx(want, rel=1e-6)


def test_poisson_draws_past_2_to_the_52_are_finite_and_near_lam():
    from evnoise._kernels.rng import poisson, seed_state

    state = np.zeros(4, dtype=np.uint64)
    seed_state(np.arange(1, 5, dtype=np.uint64), 0, state)
    for lam in (1e16, 1e19, 1e300):
        draws = np.array([poisson(state, lam) for _ in range(200)])
        assert np.isfinite(draws).all()
        assert abs(draws.mean() / lam - 1.0) < 10.0 / math.sqrt(lam) + 1e-15


@pytest.mark.parametrize("field", sorted(set(ev.params.PARAM_LIMITS) - {"hot_pixel_fraction",
                                                                      "hot_pixel_on_fraction", "leak_regularity"}))
def test_each_parameter_has_a_physical_upper_limit(field):
    from evnoise.params import PARAM_LIMITS

    limit = PARAM_LIMITS[field]
    ev.NoiseParams(**dict(GOOD, **{field: limit}))  # the limit itself is allowed
    with pytest.raises(ev.ParameterError, match=re.escape(f"NoiseParams.{field} must be <= {limit:g}")):
        ev.NoiseParams(**dict(GOOD, **{field: limit * 2.5}))


def test_preset_with_an_absurd_threshold_gives_one_error_line(tmp_path, capsys):
    preset = tmp_path / "wild.toml"
    preset.write_text("[params]\neps_pos = 50.0\neps_neg = 0.2\nbias_pr = 1.7\ntrial_rate_hz = 1000.0\n"
                      "photons_per_lux = 1.0\n")
    from PIL import Image

    Image.fromarray(np.full((12, 16), 128, dtype=np.uint8)).save(tmp_path / "grey.png")
    code, _, err = run_cli(capsys, "simulate", tmp_path / "grey.png", "--preset", preset, "--duration", "0.01",
                           "--seed", "1", "-o", tmp_path / "out.h5")
    one_error_line(code, err, "eps_pos must be <= 20")
    assert not (tmp_path / "out.h5").exists()


# --------------------------------------------------------------------------------------
# 2. make-dataset never deletes or writes through a link; 4. manifests name only files inside
# --------------------------------------------------------------------------------------
DATASET_ARGS = ("make-dataset", "--procedural", "dead-leaves", "--count", "2", "--sensor", "128x96", "--crop", "64",
                "--seed", "3", "-q")


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile") / "ds"
    assert main([*DATASET_ARGS, "--out", str(root)]) == 0
    return root


def _copy_dataset(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


@pytest.mark.parametrize("part", ["shards", ".evnoise-progress", "manifest.json", "preview.png"])
def test_make_dataset_refuses_a_symlinked_part_and_touches_nothing_behind_it(tmp_path, capsys, part):
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "a.h5").write_text("x")
    (victim / ".b.tmp").write_text("y")
    ds = tmp_path / "ds"
    ds.mkdir()
    if part != ".evnoise-progress":
        (ds / ".evnoise-progress").mkdir()
    else:
        (ds / "manifest.json").write_text("{}")  # a dataset is there, so --overwrite would clear it
    target = victim if part in ("shards", ".evnoise-progress") else victim / "a.h5"
    (ds / part).symlink_to(os.path.relpath(target, ds))
    code, _, err = run_cli(capsys, *DATASET_ARGS, "--out", ds, "--overwrite")
    one_error_line(code, err, "is a symbolic link")
    assert sorted(p.name for p in victim.iterdir()) == [".b.tmp", "a.h5"]
    assert (victim / "a.h5").read_text() == "x" and (victim / ".b.tmp").read_text() == "y"


def test_make_dataset_refuses_links_inside_its_shards_folder(tmp_path, capsys, small_dataset):
    ds = _copy_dataset(small_dataset, tmp_path / "ds")
    outside = tmp_path / "outside.h5"
    outside.write_text("keep")
    (ds / "shards" / "test-00000.h5").symlink_to(outside)
    code, _, err = run_cli(capsys, *DATASET_ARGS, "--out", ds, "--overwrite")
    one_error_line(code, err, "is a symbolic link")
    assert outside.read_text() == "keep"


@pytest.mark.parametrize("where", ["parent", "absolute", "link"])
def test_manifest_naming_a_file_outside_the_dataset_is_refused(tmp_path, capsys, small_dataset, where):
    from evnoise.generators import PairDataset

    ds = _copy_dataset(small_dataset, tmp_path / "ds")
    outside = tmp_path / "outside"
    outside.mkdir()
    manifest = json.loads((ds / "manifest.json").read_text())
    shard = manifest["shards"][0]
    real = ds / shard["file"]
    (outside / "x.h5").write_bytes(real.read_bytes())
    if where == "parent":
        shard["file"] = "../outside/x.h5"
    elif where == "absolute":
        shard["file"] = str(outside / "x.h5")
    else:
        real.unlink()
        real.symlink_to(outside / "x.h5")
    (ds / "manifest.json").write_text(json.dumps(manifest))
    code, _, err = run_cli(capsys, "info", ds)
    one_error_line(code, err, "outside the dataset folder")
    with pytest.raises(ev.InputError, match="outside the dataset folder"):
        PairDataset(ds, split=shard["split"])
    from evnoise.reconstruct.data import open_pairs

    with pytest.raises(ev.InputError, match="outside the dataset folder"):
        open_pairs(ds, split=shard["split"])
