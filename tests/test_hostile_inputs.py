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
import warnings
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from _cli_helpers import one_error_line, run_cli
from evnoise.cli import main

REPO = Path(__file__).resolve().parents[1]
GOOD = dict(eps_pos=0.2, eps_neg=0.2, bias_pr=1.7, trial_rate_hz=1000.0, photons_per_lux=1.0)






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


# --------------------------------------------------------------------------------------
# 3. events.h5 from strangers: nothing read from outside the file, declared sizes backed by data
# --------------------------------------------------------------------------------------
def _events_h5(path, n=500, shape=(24, 32), seed=0):
    from evnoise.events import make_events

    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 1_000_000, n))
    ev.write_events(path, make_events(t, rng.integers(0, shape[1], n), rng.integers(0, shape[0], n),
                                      rng.integers(0, 2, n)), shape=shape)
    return path


def _rewrite(path, column, make):
    """Replace ``/events/<column>`` by what ``make(f, name, old_values)`` creates."""
    h5py = pytest.importorskip("h5py")
    with h5py.File(path, "r+") as f:
        old = f["events"][column][()]
        del f["events"][column]
        make(f, f"events/{column}", old)


def _read_everywhere(capsys, path, tmp_path, expect):
    """read_events, the chunked reader, `info` and `separate` all refuse ``path`` with ``expect``."""
    with pytest.raises(ev.InputError, match=expect):
        ev.read_events(path)
    with pytest.raises(ev.InputError, match=expect):
        list(ev.open_events(path).chunks(None, None))
    code, _, err = run_cli(capsys, "info", path)
    one_error_line(code, err, expect)
    code, _, err = run_cli(capsys, "separate", path, "--out", tmp_path / "sep.h5")
    one_error_line(code, err, expect)
    assert not (tmp_path / "sep.h5").exists()


def test_external_storage_is_not_read(tmp_path, capsys):
    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.arange(500, dtype=np.int64).tobytes())  # stands for /etc/passwd
    path = _events_h5(tmp_path / "ext.h5")
    _rewrite(path, "t", lambda f, name, old: f.create_dataset(name, shape=old.shape, dtype=np.int64,
                                                              external=[(str(secret), 0, old.size * 8)]))
    _read_everywhere(capsys, path, tmp_path, "external file")


def test_virtual_datasets_and_external_links_are_not_followed(tmp_path, capsys):
    h5py = pytest.importorskip("h5py")
    other = _events_h5(tmp_path / "other.h5", seed=1)
    path = _events_h5(tmp_path / "virtual.h5")

    def virtual(f, name, old):
        layout = h5py.VirtualLayout(shape=old.shape, dtype=old.dtype)
        layout[:] = h5py.VirtualSource(str(other), "events/x", shape=old.shape)
        f.create_virtual_dataset(name, layout)

    _rewrite(path, "x", virtual)
    _read_everywhere(capsys, path, tmp_path, "virtual dataset")
    linked = _events_h5(tmp_path / "linked.h5")
    _rewrite(linked, "y", lambda f, name, old: f.__setitem__(name, h5py.ExternalLink(str(other), "events/y")))
    _read_everywhere(capsys, linked, tmp_path, "links to another file")


def test_declared_but_unwritten_events_are_refused_not_invented(tmp_path, capsys):
    # a 1e11-event header with no data read as 1e11 zeros (hours); now: checked against the stored chunks
    h5py = pytest.importorskip("h5py")
    path = _events_h5(tmp_path / "huge.h5")
    with h5py.File(path, "r+") as f:
        for k in "xytp":
            dtype = f["events"][k].dtype
            del f["events"][k]
            f["events"].create_dataset(k, shape=(10**11,), dtype=dtype, chunks=(1 << 16,))
    # first in a fresh interpreter: before the fix this read ran for hours (limit_s only guards the suite)
    proc = run_python(f"import evnoise as ev; ev.read_events({str(path)!r})", limit_s=120)
    assert proc.returncode != 0 and "declares 100,000,000,000 events" in proc.stderr, proc.stderr[-2000:]
    _read_everywhere(capsys, path, tmp_path, "declares 100,000,000,000 events")
    contiguous = _events_h5(tmp_path / "contiguous.h5")
    _rewrite(contiguous, "p", lambda f, name, old: f.create_dataset(name, shape=(old.size,), dtype=old.dtype))
    _read_everywhere(capsys, contiguous, tmp_path, "stores none of them")


@pytest.mark.parametrize("damage, expect", [
    (lambda f: f.attrs.__setitem__("width", "abc"), "width attribute must be an integer"),
    (lambda f: f.attrs.__setitem__("height", 2.5), "height attribute must be an integer"),
    (lambda f: f.attrs.__setitem__("width", -3), "invalid sensor size"),
    (lambda f: f.attrs.__delitem__("height"), "only one of the width and height"),
    (lambda f: f.attrs.__setitem__("json_attrs", "{not json"), "json_attrs attribute is not a JSON list"),
    (lambda f: f.attrs.__setitem__("json_attrs", "7"), "json_attrs attribute is not a JSON list"),
    (lambda f: f.__setitem__("t_offset", "soon"), "/t_offset must be an integer"),
    (lambda f: f.__setitem__("t_offset", np.arange(3)), "/t_offset must be an integer"),
    (lambda f: f.__setitem__("t_offset", 2**63 - 1), "beyond"),
])
def test_damaged_metadata_gives_one_clean_error(tmp_path, capsys, damage, expect):
    h5py = pytest.importorskip("h5py")
    path = _events_h5(tmp_path / "meta.h5")
    with h5py.File(path, "r+") as f:
        if "t_offset" in f:
            del f["t_offset"]
        damage(f)
    with pytest.raises(ev.InputError, match=re.escape(expect)):
        ev.read_events(path)
    code, _, err = run_cli(capsys, "info", path)
    one_error_line(code, err, expect)


def test_unreadable_first_time_is_an_input_error(tmp_path):
    # readers/hdf5.py read t[0] outside its OSError handler: a damaged chunk gave a traceback
    h5py = pytest.importorskip("h5py")
    path = _events_h5(tmp_path / "chunk.h5", n=5000)
    with h5py.File(path, "r") as f:
        t = f["events/t"]
        assert t.chunks is not None
        info = t.id.get_chunk_info(0)
    raw = bytearray(path.read_bytes())
    raw[info.byte_offset:info.byte_offset + info.size] = b"\xff" * info.size  # the first block of t, garbled
    path.write_bytes(bytes(raw))
    with pytest.raises(ev.InputError, match="cannot read events"):
        ev.open_events(path)


# --------------------------------------------------------------------------------------
# 5. separate / reconstruct of a file whose clock is a camera's (t_offset 1.6e15 µs)
# --------------------------------------------------------------------------------------
CAMERA_T0 = 1_633_953_690_000_000


def _offset_h5(path, t_offset=CAMERA_T0, gap_us=0):
    """An events.h5 whose events lie at ``t_offset + t`` (as ``separate`` writes from a camera file), the
    second half of them ``gap_us`` later."""
    h5py = pytest.importorskip("h5py")
    _events_h5(path, n=400)
    with h5py.File(path, "r+") as f:
        if gap_us:
            t = f["events/t"][()]
            t[200:] += gap_us
            f["events/t"][...] = t
            del f["ms_to_idx"]
        if "t_offset" in f:
            del f["t_offset"]
        f["t_offset"] = np.int64(t_offset)
        if "t_end_us" in f.attrs:
            f.attrs["t_end_us"] = int(f["events/t"][-1]) + 1
    return path


def test_a_recording_with_a_camera_clock_starts_at_its_offset(tmp_path):
    from evnoise._recordings import recording_start_us

    path = _offset_h5(tmp_path / "cam.h5")
    assert recording_start_us(path, None) == CAMERA_T0
    assert recording_start_us(_events_h5(tmp_path / "own.h5"), 5) == 0  # evnoise's own clock starts at 0


def test_separate_of_a_camera_clock_file_finishes(tmp_path):
    # stepped 1 ms blocks from 0 to 1.6e15 µs before: it never ended. limit_s only guards the suite.
    path = _offset_h5(tmp_path / "cam.h5")
    code = (f"from evnoise.separation import separate_file; r = separate_file({str(path)!r}, "
            f"{str(tmp_path / 's.h5')!r}, {str(tmp_path / 'n.h5')!r}); print(r['n_events'])")
    proc = run_python(code)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert int(proc.stdout.split()[-1]) == 400
    noise = ev.open_events(tmp_path / "n.h5")
    assert noise.t_offset_us == CAMERA_T0  # the outputs keep the camera's clock
    proc = run_python(f"from evnoise.separation import separate_file; separate_file({str(tmp_path / 'n.h5')!r}, "
                      f"{str(tmp_path / 's2.h5')!r})")  # evnoise's own output, separated again
    assert proc.returncode == 0, proc.stderr[-2000:]


@pytest.mark.parametrize("offset", [0, CAMERA_T0])
def test_blocks_skip_long_empty_stretches(tmp_path, offset):
    # 200 events, a gap of 1e12 µs (a million 1-s... blocks of 1 ms: 1e9 of them), 200 events
    from evnoise._recordings import recording_blocks

    path = _offset_h5(tmp_path / "gap.h5", t_offset=offset, gap_us=10**12)
    start = offset
    end = offset + 10**12 + 1_000_001
    blocks = []
    for events, b in recording_blocks(path, start, end, 1000, skip_empty=True):
        blocks.append((events.size, b))
        assert len(blocks) < 5000  # far fewer than the 1e9 blocks of the span
    assert sum(n for n, _ in blocks) == 400
    assert all((b - start) % 1000 == 0 for _, b in blocks)  # still the grid of [start + k 1000, ...)
    # skipping yields exactly the non-empty blocks of the dense stream (every block, empty ones too)
    dense = []
    for events, b in recording_blocks(path, start, end, 1000):
        if b > start + 1_000_000:
            break
        dense.append((events.size, b))
    assert [x for x in dense if x[0]] == [x for x in blocks if x[1] <= start + 1_000_000]


def test_reblock_skips_gaps_of_a_camera_stream():
    from evnoise._recordings import _reblock
    from evnoise.events import make_events

    t = np.array([5, 7, 10**15 + 3, 10**15 + 4000], dtype=np.int64)
    chunks = [make_events(t[:2], [0, 1], [0, 0], [1, 0]), make_events(t[2:], [2, 3], [0, 0], [1, 1])]
    out = list(_reblock(iter(chunks), 0, 10**15 + 5000, 1000, skip_empty=True))
    assert [(e.size, b) for e, b in out] == [(2, 1000), (1, 10**15 + 1000), (1, 10**15 + 5000)]


# --------------------------------------------------------------------------------------
# 6. a checkpoint's network size is bounded before anything is allocated
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("change, expect", [
    (dict(base_channels=65536), "base_channels must be <= 4096"),
    (dict(blocks_per_level=100_000), "blocks_per_level must be <= 64"),
    (dict(base_channels=4096, channel_mults=[1, 2, 4, 8]), "parameters, more than"),
    (dict(channel_mults=list(range(1, 40))), "at most 10 levels"),
    (dict(channel_mults="1,2"), "channel_mults must be a sequence"),
])
def test_checkpoint_declaring_a_huge_network_is_refused(tmp_path, capsys, change, expect):
    torch = pytest.importorskip("torch")
    from evnoise.reconstruct.checkpoint import load_model, read_checkpoint
    from evnoise.reconstruct.infer import default_model_path
    from evnoise.reconstruct.unet import UNetConfig

    doc = read_checkpoint(default_model_path())
    doc["model"] = {**doc["model"], **change}
    bad = tmp_path / "huge.pt"
    torch.save(doc, bad)
    with pytest.raises(ev.ParameterError, match=re.escape(expect)):  # first: this allocates nothing
        UNetConfig.from_dict(doc["model"])
    with pytest.raises(ev.InputError, match=re.escape(expect)):
        load_model(bad)
    events = _events_h5(tmp_path / "ev.h5")
    code, _, err = run_cli(capsys, "reconstruct", events, "--model", bad, "-o", tmp_path / "out.png")
    one_error_line(code, err, expect)


def test_parameter_bound_is_an_upper_bound():
    torch = pytest.importorskip("torch")  # noqa: F841 - the network is built
    from evnoise.reconstruct.unet import UNet, UNetConfig

    for kw in (dict(), dict(base_channels=8, channel_mults=(1, 2)), dict(stem=2, blocks_per_level=3),
               dict(base_channels=32, channel_mults=(1, 2, 4, 8), blocks_per_level=2, in_channels=1)):
        config = UNetConfig(**kw)
        assert sum(p.numel() for p in UNet(config=config).parameters()) <= config.parameter_bound()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are a POSIX feature")
@pytest.mark.parametrize("flag", ["--out", "--png"])
def test_overwrite_does_not_replace_a_named_pipe_with_a_file(tmp_path, capsys, flag):
    """``--overwrite`` replaces an existing file, not a pipe (or socket or device node) of that name: the writers
    rename a finished file into place, which would have turned the pipe into a regular file (found by a review)."""
    import stat

    fifo = tmp_path / ("events.h5" if flag == "--out" else "maps.png")
    os.mkfifo(fifo)
    other = {"--out": tmp_path / "other.h5", "--png": tmp_path / "other.png"}
    args = ["simulate", "--example", "--duration", "0.001", "--overwrite",
            "--out", fifo if flag == "--out" else other["--out"], "--png", fifo if flag == "--png" else other["--png"]]
    code, _, err = run_cli(capsys, *args)
    one_error_line(code, err, "named pipe (FIFO), not a regular file")
    assert stat.S_ISFIFO(fifo.lstat().st_mode)
    if flag == "--out":
        with pytest.raises(ev.OutputError, match="not a regular file"):
            ev.write_events(fifo, np.zeros(0, ev.EVENT_DTYPE), (4, 4), overwrite=True)


@pytest.mark.parametrize("edit, expect", [
    (("eps_pos = ", "eps_pos = 1" + "0" * 400 + "  # "), "eps_pos must be a number, got an integer of about 400"),
    (("eps_pos = ", "eps_pos = 1" + "0" * 5000 + "  # "), "is not a preset: Exceeds the limit (4300 digits)"),
    (("fitted_lux = ", "fitted_lux = [0, 1" + "0" * 400 + "]  # "), "fitted_lux must be [lo, hi] lux"),
    (None, "its TOML nests too deeply"),
    (("eps_pos = ", "eps_pos = true  # "), "eps_pos must be a number, got True"),  # was read as 1.0
    (("eps_pos = ", "eps_pos = \"0.2\"  # "), "eps_pos must be a number, got '0.2'"),  # was read as 0.2
])
def test_a_preset_with_absurd_numbers_or_nesting_is_one_error_line(tmp_path, capsys, edit, expect):
    """Integers beyond the double range, beyond Python's digit limit, and arrays nested past the recursion limit
    (found by a hostile-file review: OverflowError, ValueError and RecursionError tracebacks)."""
    text = (Path(ev.__file__).parent / "presets" / "evk3-hd.toml").read_text()
    if edit is None:
        text += "\nzz = " + "[" * 100_000 + "]" * 100_000 + "\n"
    else:
        assert edit[0] in text
        text = text.replace(edit[0], edit[1], 1)
    preset = tmp_path / "odd.toml"
    preset.write_text(text)
    code, _, err = run_cli(capsys, "presets", preset)
    one_error_line(code, err, expect)
    assert len(err) < 400


@pytest.mark.parametrize("where", ["h5 attribute", "h5 json_attrs", "aedat4 attribute"])
def test_metadata_json_nested_past_the_recursion_limit_is_kept_as_text(tmp_path, capsys, where):
    """An attribute whose JSON nests 100,000 deep (found by a hostile-file review: RecursionError in ``info``)."""
    import h5py

    from evnoise.io import read_metadata, write_aedat4

    deep = "[" * 100_000 + "]" * 100_000
    events = np.zeros(3, ev.EVENT_DTYPE)
    events["t"] = [1, 2, 3]
    if where.startswith("aedat4"):
        path = write_aedat4(tmp_path / "e.aedat4", events, (4, 4), attrs={"foo_json": deep})
    else:
        path = ev.write_events(tmp_path / "e.h5", events, (4, 4))
        with h5py.File(path, "a") as f:
            f.attrs["json_attrs"] = '["foo"]' if where == "h5 attribute" else deep
            f.attrs["foo"] = deep
    code, out, err = run_cli(capsys, "info", path)
    if where == "h5 json_attrs":
        one_error_line(code, err, "json_attrs attribute is not a JSON list")
    else:
        assert code == 0, err
        assert read_metadata(path)["foo"] == deep


@pytest.mark.parametrize("case", ["long cell", "csv_columns number", "huge t_start", "deep nesting"])
def test_calibrate_inputs_with_odd_fields_are_one_error_line(tmp_path, capsys, case):
    """A rate table with a cell over the csv module's 128 kB limit, a listing whose csv_columns is a number, one whose
    t_start_s is an integer beyond the double range, one nested past the recursion limit (found by a hostile-file
    review: csv.Error, TypeError, OverflowError and RecursionError tracebacks)."""
    rec = ev.simulate_events(np.full((8, 8), 2.0), "evk3-hd", 1.0, rng=0)
    csv_rec = tmp_path / "flat.csv"
    ev.write_events(csv_rec, rec, (8, 8))
    listing = tmp_path / "levels.toml"
    level = f'[[level]]\nfile = "{csv_rec.name}"\nlux = 2.0\nsensor = "8x8"\n'
    more = "".join(level.replace("lux = 2.0", f"lux = {lux}") for lux in (5.0, 20.0))
    if case == "long cell":
        listing = tmp_path / "rates.csv"
        listing.write_text("lux,rate_on_hz,rate_off_hz\n1," + "9" * 200_000 + ",0.1\n")
        expect = "not a table of rates or counts"
    elif case == "csv_columns number":
        listing.write_text(level + "csv_columns = 5\n" + more)
        expect = "must be text such as 'x,y,p,t'"
    elif case == "huge t_start":
        listing.write_text(level + "t_start_s = 1" + "0" * 400 + "\n" + more)
        expect = "level 1: "
    else:
        listing.write_text(level + "zz = " + "[" * 100_000 + "]" * 100_000 + "\n")
        expect = "its TOML nests too deeply"
    code, _, err = run_cli(capsys, "calibrate", listing, "--out", tmp_path / "fit.toml", "-q")
    one_error_line(code, err, expect)
    assert not (tmp_path / "fit.toml").exists()
    if case == "huge t_start":
        assert "must be finite and >= 0, got inf" in err
    if case == "csv_columns number":
        with pytest.raises(ev.ParameterError, match="csv_columns must be text"):
            ev.read_events(csv_rec, csv_columns=5)


def _damage_nan_weights(doc):
    doc["state_dict"] = {k: v.clone().fill_(float("nan")) if v.is_floating_point() else v
                         for k, v in doc["state_dict"].items()}


@pytest.mark.parametrize("damage, expect", [
    (lambda d: d.update(state_dict=[1, 2]), "'state_dict' is not a table of tensors"),
    (lambda d: d.update(card="abc"), "'card' is not a table"),
    (lambda d: d.update(card={"white_lux_range": [1]}), "card['white_lux_range'] is not two numbers"),
    (lambda d: d.update(train=[1]), "'train' is not a table"),
    (lambda d: d.update(train={"epoch": "x"}), "train['epoch'] is not a whole number >= 0"),
    (lambda d: d.update(train={"history": [1]}), "train['history'] is not a table of lists of numbers"),
    (lambda d: d.update(train={"last_state_dict": [1]}), "train['last_state_dict'] is not a table of tensors"),
    (lambda d: d["input"].update(ml_sigma=1e300, params={}, max_lux=1.0), "'ml_sigma' must be between 0 and"),
    (lambda d: d["input"].update(window_s=1e-300, windows_s=[1e-300]), "'window_s' must be at least 1e-06 s"),
    (lambda d: d["input"].update(rate_scale_hz=1e-300), "'rate_scale_hz' must be between 1e-9 and 1e9"),
    (_damage_nan_weights, "weights that are not finite numbers"),
], ids=["state_dict list", "card text", "card lux range", "train list", "epoch text", "history list",
        "last weights list", "huge ml_sigma", "tiny window", "tiny rate scale", "NaN weights"])
def test_a_damaged_checkpoint_is_one_error_line_in_every_command(tmp_path, capsys, damage, expect):
    """Checkpoints torch loads safely (plain tables and tensors) but with entries of the wrong kind or absurd
    values gave TypeError, AttributeError or ValueError tracebacks in reconstruct and info, and NaN weights or a
    1e-300 s window an all-black image with exit 0 (found by a hostile-input review)."""
    torch = pytest.importorskip("torch")
    from evnoise.reconstruct.checkpoint import read_checkpoint
    from evnoise.reconstruct.infer import default_model_path

    doc = read_checkpoint(default_model_path())
    damage(doc)
    bad = tmp_path / "damaged.pt"
    torch.save(doc, bad)
    events = _events_h5(tmp_path / "ev.h5")
    code, _, err = run_cli(capsys, "reconstruct", events, "--model", bad, "-o", tmp_path / "out.png")
    one_error_line(code, err, expect)
    assert not (tmp_path / "out.png").exists()
    if " is not " in expect:  # the file's structure: info reads it too (values are checked where used)
        code, _, err = run_cli(capsys, "info", bad)
        one_error_line(code, err, expect)


def test_a_plain_pickle_as_a_model_is_one_error_line_and_is_not_run(tmp_path, capsys):
    """torch's warning about the pickle protocol came before the error line; the pickle's payload never runs."""
    import pickle

    pytest.importorskip("torch")
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    bad = tmp_path / "evil.pt"
    bad.write_bytes(pickle.dumps(Payload(), protocol=4))
    events = _events_h5(tmp_path / "ev.h5")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, _, err = run_cli(capsys, "reconstruct", events, "--model", bad, "-o", tmp_path / "out.png")
    one_error_line(code, err, "is not an evnoise model checkpoint")
    assert not caught, [str(w.message) for w in caught]
    assert not marker.exists()


@pytest.mark.parametrize("command", ["simulate --png", "presets --plot", "info --png", "reconstruct --out"])
def test_an_output_name_ending_in_a_slash_is_refused_not_written_without_it(tmp_path, capsys, command):
    """'--png maps.png/' names a folder; Path() dropped the slash and evnoise wrote the file maps.png with exit 0
    (the event file's --out was already refused; found by a hostile-input review)."""
    events = _events_h5(tmp_path / "ev.h5")
    target = str(tmp_path / "out.png") + "/"
    argv = {"simulate --png": ["simulate", "--example", "--sensor", "32x24", "--duration", "0.01", "--out",
                               tmp_path / "sim.h5", "--png", target],
            "presets --plot": ["presets", "evk3-hd", "--plot", target],
            "info --png": ["info", events, "--stats", "--png", target],
            "reconstruct --out": ["reconstruct", events, "--out", target]}[command]
    if command == "reconstruct --out":
        pytest.importorskip("torch")
    code, _, err = run_cli(capsys, *argv)
    one_error_line(code, err, "the name ends in '/', a folder")
    assert not (tmp_path / "out.png").exists() and not (tmp_path / "sim.h5").exists()


def test_atomic_outputs_refuse_a_name_ending_in_a_slash(tmp_path):
    from evnoise._atomic import AtomicFile, atomic_output

    with pytest.raises(ev.OutputError, match="ends in '/'"):
        AtomicFile(str(tmp_path / "a.json") + "/")
    with pytest.raises(ev.OutputError, match="ends in '/'"):
        with atomic_output(str(tmp_path / "b.json") + "/"):
            pass
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("keep", [400, 2000, 3000])
def test_a_truncated_exr_is_one_error_line_without_the_librarys_own_lines(tmp_path, capfd, keep):
    """OpenEXR's C core printed its complaints on the standard error and its Python module a 'Warning:' line on the
    standard output before evnoise's error, which said 'file has 0 parts' (found by a hostile-input review). The
    library's lines are captured: the error names the damage once; a whole file still reads."""
    OpenEXR = pytest.importorskip("OpenEXR")
    red = np.random.default_rng(0).random((24, 32)).astype(np.float32)
    whole = tmp_path / "rgb.exr"
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, {"R": red, "G": red, "B": red}) as f:
        f.write(str(whole))
    cut = tmp_path / "cut.exr"
    cut.write_bytes(whole.read_bytes()[:keep])
    code, out, err = run_cli(capfd, "simulate", cut, "--duration", "0.01", "--out", tmp_path / "out.h5")
    one_error_line(code, err, "cannot read OpenEXR image")
    assert out == ""
    assert not (tmp_path / "out.h5").exists()
    code, out, err = run_cli(capfd, "-q", "simulate", whole, "--duration", "0.01", "--out", tmp_path / "ok.h5")
    assert code == 0 and err == "", err


def test_exact_counts_run_in_windows_with_the_same_counts_and_refuse_days_of_work(monkeypatch):
    """A huge duration made the exact count sampler run for days in one kernel call that neither SIGTERM nor
    Ctrl-C stopped, and the Poisson sampler raised NumPy's 'lam value too large' (found by a hostile-input
    review). The exact sampler now runs in windows of a bounded number of events (the same counts, bit for bit),
    and refuses a scene expecting more than MAX_EXACT_COUNT_EVENTS; means past NumPy's Poisson range are refused."""
    from evnoise import simulate

    lux = np.full((6, 7), 3.0)
    params = ev.load_preset("evk3-hd")
    whole = ev.sample_counts(lux, params, 20.0, rng=4)
    assert whole.sum() > 500
    monkeypatch.setattr(simulate, "EXACT_COUNT_WINDOW_EVENTS", 37.0)  # dozens of windows
    np.testing.assert_array_equal(ev.sample_counts(lux, params, 20.0, rng=4), whole)
    with pytest.raises(ev.ParameterError, match="distribution='exact' draws every event"):
        ev.sample_counts(lux, params, 1e12, rng=1)
    for distribution, extra in (("poisson", {}), ("negative-binomial", {"nb_shape": 2.0})):
        with pytest.raises(ev.ParameterError, match="expected count is .* beyond"):
            ev.sample_counts(lux, params, 1e20, rng=1, distribution=distribution, **extra)


@pytest.mark.parametrize("case, expect", [
    ("uint8 x on a wide sensor", "cannot hold x up to 299"),
    ("NaN time", "times that are not finite numbers"),
    ("infinite time", "times that are not finite numbers"),
    ("2**62 us span", "is the sample's t in microseconds?"),
    ("text polarity", "field 'p' holds <U1; expected numbers"),
])
def test_tonic_transform_refuses_samples_it_cannot_hold(case, expect):
    """The tonic transform wrote noise at x >= 256 into a uint8 x field (wrapped: pixels 0..43 got twice their
    noise), and NaN/inf times, a 2**62 us span (a 60 PiB allocation) and text polarities gave ValueError,
    OverflowError, MemoryError and UFuncTypeError (found by a hostile-input review)."""
    from evnoise.plugins.tonic import PhotonNoise

    fields = {"x": "<i2", "y": "<i2", "t": "<i8", "p": "<i1"}
    rows = [(1, 2, 0, 1), (3, 4, 1_000_000, 0)]
    width = 34
    if case == "uint8 x on a wide sensor":
        fields["x"], width = "u1", 300
    elif case in ("NaN time", "infinite time"):
        fields["t"] = "<f8"
        rows[1] = (3, 4, math.nan if case == "NaN time" else math.inf, 0)
    elif case == "2**62 us span":
        rows[1] = (3, 4, 2**62, 0)
    else:
        fields["p"], rows = "U1", [(1, 2, 0, "a"), (3, 4, 1000, "b")]
    sample = np.array(rows, dtype=list(fields.items()))
    transform = PhotonNoise((width, 10, 2), "evk3-hd", 2.0, rng=1)
    for call in (transform, transform.noise):
        with pytest.raises(ev.InputError, match=re.escape(expect)):
            call(sample)


@pytest.mark.parametrize("shape, expect", [
    ((10**6, 10**6), "memory"), ((-4, 5), "whole numbers >= 1"), (5, "shape must be (H, W)"),
    ((4.5, 5), "whole numbers >= 1"), ((65536, 65536), "memory"), ((2**31, 2**31), "memory"),
])
def test_drawing_maps_checks_the_shape_and_the_memory_first(shape, expect, monkeypatch):
    """draw_background / draw_thresholds took any shape: MemoryError for 14.6 TiB, ValueError, TypeError, or
    (4.5, 5) silently as (4, 5) (found by a hostile-input review)."""
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", str(2**30))
    params = ev.load_preset("davis346")
    for draw in (ev.draw_background, ev.draw_thresholds):
        with pytest.raises(ev.EvnoiseError, match=re.escape(expect)):
            draw(shape, params, 1)
    assert ev.draw_thresholds((3, 4), params, 1).shape == (2, 3, 4)
    assert ev.draw_thresholds((1, 70_000), params, 1).shape == (2, 1, 70_000)  # a population: any side


def test_an_eps_file_named_png_is_not_handed_to_ghostscript(tmp_path, capsys, monkeypatch):
    """Pillow was asked to open any format it knows: an EPS file named .png reached its EPS plugin, which runs
    Ghostscript on the file where one is installed (found by a hostile-input review). Only plain raster formats
    are tried now."""
    from PIL import EpsImagePlugin

    tried = []
    monkeypatch.setattr(EpsImagePlugin.EpsImageFile, "_open", lambda self: tried.append(1))
    eps = tmp_path / "scene.png"
    eps.write_text("%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 10 10\nnewpath 0 0 moveto 10 10 lineto stroke\n")
    code, _, err = run_cli(capsys, "simulate", eps, "--duration", "0.01", "--out", tmp_path / "out.h5")
    one_error_line(code, err, "cannot identify image file")
    assert not tried


@pytest.mark.parametrize("odd", ["named pipe", "folder", "link to a device"])
def test_a_frame_that_is_not_a_regular_file_is_an_error_not_a_dropped_frame(tmp_path, capsys, odd):
    """A named pipe, a folder or a link to /dev/zero named like a frame (a2.png) was skipped: a 3-frame video
    became 2 frames, a3 shown at a2's time (found by a hostile-input review)."""
    from PIL import Image

    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("a1.png", "a3.png"):
        Image.fromarray(np.full((6, 8), 120, np.uint8)).save(frames / name)
    middle = frames / "a2.png"
    if odd == "named pipe":
        os.mkfifo(middle)
    elif odd == "folder":
        middle.mkdir()
    else:
        middle.symlink_to("/dev/zero")
    code, _, err = run_cli(capsys, "simulate", frames, "--fps", "30", "--out", tmp_path / "out.h5")
    one_error_line(code, err, "a2.png is named like a frame but is")
    assert not (tmp_path / "out.h5").exists()


def test_light_outside_range_takes_the_range_itself():
    """A video's light check counted every frame against the preset by name, re-reading its TOML each time
    (75 % of a 5000-frame run); the range is now read once and passed."""
    lux = np.geomspace(1e-4, 1e5, 50)
    light = ev.params.preset_light_range("dvs128")
    assert light is not None
    assert ev.params.light_outside_range(light, lux) == ev.params.light_outside_range("dvs128", lux)
    assert 0 < ev.params.light_outside_range(light, lux)[0] < lux.size


def test_a_checkpoint_that_cannot_be_written_is_an_output_error_and_no_file(tmp_path, monkeypatch):
    """torch's zip writer reports a full disk as RuntimeError ('unexpected pos'): train ended in a traceback
    (found by a hostile-input review)."""
    torch = pytest.importorskip("torch")
    from evnoise.reconstruct.checkpoint import InputSpec, save_checkpoint
    from evnoise.reconstruct.unet import UNet

    def full_disk(obj, f, *a, **k):
        raise RuntimeError("[enforce fail at inline_container.cc:778] . PytorchStreamWriter failed writing file "
                           "data/0: file write failed")

    net = UNet(base_channels=8, channel_mults=(1, 2), groups=4, stem=1)
    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(ev.OutputError, match="cannot write checkpoint .*file write failed"):
        save_checkpoint(tmp_path / "m.pt", model_config=net.config, input_spec=InputSpec(window_s=0.5),
                        state_dict=net.state_dict())
    assert list(tmp_path.iterdir()) == []


def test_fps_below_a_frame_per_days_and_parameters_that_are_no_table_are_one_error(tmp_path, capsys):
    """--fps 1e-300 gave an OverflowError traceback (or a 440-character error quoting a 300-digit time), and
    NoiseParams.from_dict([1]) a TypeError (found by a hostile-input review)."""
    from PIL import Image

    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(3):
        Image.fromarray(np.full((4, 6), 100 + k, np.uint8)).save(frames / f"f{k}.png")
    code, _, err = run_cli(capsys, "simulate", frames, "--fps", "1e-300", "--out", tmp_path / "out.h5")
    one_error_line(code, err, "--fps must be at least 1e-06 frames per second, got 1e-300")
    for data in ([1], "abc", {1: 2}):
        with pytest.raises(ev.ParameterError, match="must be a table of names and values"):
            ev.NoiseParams.from_dict(data)


@pytest.mark.parametrize("kind", ["fifo", "device", "too large"])
def test_a_calibration_table_that_is_no_bounded_regular_file_is_refused_before_reading(tmp_path, capsys,
                                                                                      monkeypatch, kind):
    """``calibrate --monitor FIFO`` waited for ever and ``--monitor /dev/zero`` filled 7.5 GB before a MemoryError
    traceback (found by a hostile-file review): tables are regular files of at most MAX_TABLE_BYTES."""
    import evnoise.calibration.measurements as measurements

    table = tmp_path / "monitor.csv"
    if kind == "fifo":
        os.mkfifo(table)
    elif kind == "device":
        table = Path("/dev/zero")
    else:
        table.write_text("grey,lux\n" + "".join(f"{g},{g / 10}\n" for g in range(256)))
        monkeypatch.setattr(measurements, "MAX_TABLE_BYTES", 1000)
    with pytest.raises(ev.InputError, match="special file|a table of rates, counts or monitor levels may have"):
        measurements.read_monitor_table(table)
    rates = tmp_path / "rates.csv"
    rates.write_text("grey,on_rate_hz,off_rate_hz\n10,1,1\n")
    code, _, err = run_cli(capsys, "calibrate", rates, "--monitor", table, "--out", tmp_path / "c.toml")
    one_error_line(code, err, "special file" if kind != "too large" else "a table of rates, counts or monitor levels")


def _h5_events(path, t, width=8, height=6):
    import h5py

    n = len(t)
    with h5py.File(path, "w") as f:
        f["events/x"] = (np.arange(n) % width).astype(np.uint16)
        f["events/y"] = (np.arange(n) % height).astype(np.uint16)
        f["events/t"] = np.asarray(t, dtype=np.int64)
        f["events/p"] = (np.arange(n) % 2).astype(np.uint8)
        f["t_offset"] = np.int64(0)
        f.attrs["width"], f.attrs["height"] = width, height


def test_separate_refuses_a_recording_whose_times_decrease_instead_of_writing_empty_outputs(tmp_path, capsys):
    """An events.h5 in descending time order (found by a hostile-file review): ``separate`` wrote two complete-looking
    files of 0 events and exited 0 (its span, first to last event, was negative)."""
    rec = tmp_path / "desc.h5"
    _h5_events(rec, np.arange(2000, 0, -1) * 500)
    signal, noise = tmp_path / "s.h5", tmp_path / "n.h5"
    code, _, err = run_cli(capsys, "separate", rec, "--out", signal, "--noise-out", noise, "-q")
    one_error_line(code, err, "2,000 events, but 0 of them were read in time order: its timestamps decrease")
    assert not signal.exists() and not noise.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["desc.h5"]  # no temporary left


def test_separate_refuses_a_sensor_whose_filter_state_cannot_fit(tmp_path, capsys, monkeypatch):
    """A header declaring 65536x65536 pixels: a 32 GiB ArrayMemoryError traceback (hostile-file review)."""
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "64M")
    rec = tmp_path / "wide.h5"
    _h5_events(rec, np.arange(100) * 10, width=8192, height=8192)
    code, _, err = run_cli(capsys, "separate", rec, "--out", tmp_path / "s.h5", "-q")
    one_error_line(code, err, "the filter's counts of the 8192x8192 sensor would need 536.9 MB of memory")
    with pytest.raises(ev.InputError, match="last event times of the 8192x8192 sensor"):
        ev.Separator((8192, 8192), "activity")
