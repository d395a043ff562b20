"""Tests of the pair-dataset generator (``evnoise.generators``, ``evnoise make-dataset``).

Statistical checks use fixed seeds and tolerances of k standard errors computed here; the
model's closed form (``evnoise.expected_rate``) and an independent multinomial computation
(SciPy) are the references. Reproducibility checks compare file bytes (SHA-256).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from evnoise.cli import main
from evnoise.errors import InputError, OutputError, ParameterError
from evnoise.generators import DeadLeaves, PairConfig, PairDataset, make_dataset
from evnoise.generators.dataset import MANIFEST, PROGRESS_DIR, _assign_splits, plan_dataset
from evnoise.generators.pairs import CountSampler, linear_to_srgb, quantise, to_uint16
from evnoise.generators.sources import FolderSource, PackagePhotos

# fixed model parameters (the shipped preset is being refitted; tests must not move with it)
PARAMS = ev.NoiseParams(eps_pos=0.9, eps_neg=1.0, bias_pr=1.7, trial_rate_hz=22.0, photons_per_lux=1.0,
                        dark_lux=0.2)
MAX_LUX = 18.0
GREYS = (0, 24, 64, 110, 160, 210, 255)  # 8-bit sRGB codes of the stripes
STRIPE = 8  # stripe width in pixels (a multiple of the 2x2 binning)


def _srgb_decode(code):
    """Independent sRGB decoding of an 8-bit code (IEC 61966-2-1)."""
    v = code / 255.0
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def _stripes(height=32):
    row = np.repeat(np.array(GREYS, dtype=np.uint8), STRIPE)
    return np.tile(row, (height, 1))


def _write_png(path, arr):
    from PIL import Image

    Image.fromarray(arr).save(path)
    return path


def _hashes(root) -> dict:
    root = Path(root)
    files = [root / MANIFEST, *sorted((root / "shards").glob("*.h5"))]
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


@pytest.fixture(scope="module")
def stripe_folder(tmp_path_factory):
    """Four identical stripe images, 56 x 32 pixels (enough sources for every split)."""
    folder = tmp_path_factory.mktemp("stripes")
    for name in ("a.png", "b.png", "c.png", "d.png"):
        _write_png(folder / name, _stripes())
    return folder


# small dataset used by the reproducibility tests: 5 dead-leaves sources, 2 crops x 2 windows
SMALL = PairConfig(sensor_shape=(24, 32), crop_shape=(16, 16), crops_per_image=2, windows_s=(0.25, 1.0),
                   shard_size=4, seed=11, params=PARAMS, splits=(0.6, 0.2, 0.2))
SMALL_SOURCES = DeadLeaves(5)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The small dataset made in-process (workers=1): the bytes every other run must match."""
    out = tmp_path_factory.mktemp("ref") / "ds"
    result = make_dataset(SMALL_SOURCES, out, SMALL, workers=1)
    return out, _hashes(out), result


# --------------------------------------------------------------------------------------
# statistics against the closed form
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("mode, params", [
    ("counts", PARAMS),  # direct trial sampler
    ("events", PARAMS),  # simulate_events + count_events
    ("counts", PARAMS.replace(refractory_s=0.02)),  # general path: evnoise.sample_counts
])
def test_mean_counts_per_grey_level_match_closed_form(tmp_path, stripe_folder, mode, params):
    windows = (0.25, 1.0)
    config = PairConfig(sensor_shape=(32, 56), windows_s=windows, mode=mode, params=params, seed=5,
                        splits=(1, 0, 0))
    make_dataset(stripe_folder, tmp_path / "ds", config, workers=1)
    ds = PairDataset(tmp_path / "ds", "train")
    assert len(ds) == 4 * len(windows)
    step = MAX_LUX / 16383
    for window in windows:
        items = [ds[i] for i in range(len(ds)) if ds[i]["window_s"] == window]
        counts = np.stack([it["counts"] for it in items]).astype(np.float64)  # (n, 2, 16, 28)
        images = np.stack([it["image"] for it in items])
        per_stripe = STRIPE // 2  # binned columns per stripe
        for k, code in enumerate(GREYS):
            cols = slice(k * per_stripe, (k + 1) * per_stripe)
            lux = round(MAX_LUX * _srgb_decode(code) / step) * step  # the 14-bit quantised scene
            # image: the display-encoded grey level (float32, from the quantised illuminance)
            assert np.allclose(images[:, :, cols], code / 255, atol=2e-3)
            # counts: 2x2 binning sums four pixels, each with rate expected_rate(lux)
            expected = 4 * ev.expected_rate(np.array([lux]), params)[:, 0] * window
            observed = counts[:, :, :, cols].mean(axis=(0, 2, 3))
            m = counts[:, 0, :, cols].size
            sigma = np.sqrt(expected / m)  # Poisson bound: trial counts vary less than Poisson
            assert np.all(np.abs(observed - expected) <= 4.5 * sigma + 1e-12), (code, window, observed, expected)


def _trinomial_pmf(n_full, frac, p_on, p_off, max_count):
    """Exact joint pmf of (ON, OFF) counts: n_full whole trials plus a fraction of one more."""
    from scipy.stats import binom

    pmf = np.zeros((max_count + 2, max_count + 2))
    q = p_off / (1 - p_on)
    for a in range(min(n_full, max_count) + 1):
        pa = binom.pmf(a, n_full, p_on)
        for c in range(min(n_full - a, max_count) + 1):
            pmf[a, c] += pa * binom.pmf(c, n_full - a, q)
    out = pmf * (1 - frac * (p_on + p_off))
    out[1:, :] += pmf[:-1, :] * frac * p_on
    out[:, 1:] += pmf[:, :-1] * frac * p_off
    return out


def _joint_chi2(lux, window_us, side, seed=12345):
    """Chi-square statistic and dof of the direct sampler's (ON, OFF) histogram against the exact pmf."""
    config = PairConfig(sensor_shape=(side, side), binning=1, params=PARAMS, seed=0)
    sampler = CountSampler(config)
    assert sampler.method == "direct-trials"
    codes, lux_q = quantise(np.full((side, side), lux), config.lux_step)
    counts = sampler.sample(codes, window_us, seed=seed)
    on, off = counts[0].ravel(), counts[1].ravel()
    p_on, p_off = (float(p) for p in ev.event_probability(PARAMS.photons_per_trial(lux_q[0, 0]),
                                                           np.array([PARAMS.eps_pos, PARAMS.eps_neg]),
                                                           PARAMS.bias_pr))
    trials = window_us * 1e-6 * PARAMS.trial_rate_hz
    n_full, frac = math.floor(trials), trials - math.floor(trials)
    pmf = _trinomial_pmf(n_full, frac, p_on, p_off, 12)
    n = on.size
    observed = np.zeros_like(pmf)
    np.add.at(observed, (np.minimum(on, 13), np.minimum(off, 13)), 1)
    expected = pmf * n
    cells = expected >= 5
    rest_obs = n - observed[cells].sum()
    rest_exp = n - expected[cells].sum()
    stat = float(((observed[cells] - expected[cells]) ** 2 / expected[cells]).sum())
    dof = int(cells.sum()) - 1
    if rest_exp >= 5:
        stat += (rest_obs - rest_exp) ** 2 / rest_exp
        dof += 1
    return stat, dof


@pytest.mark.parametrize("lux, window_us", [(2.0, 250_000), (9.0, 1_000_000)])
def test_direct_sampler_joint_distribution(lux, window_us):
    """The direct trial sampler against the exact multinomial pmf (chi-square at a fixed seed)."""
    from scipy.stats import chi2

    stat, dof = _joint_chi2(lux, window_us, 120)
    assert stat < chi2.ppf(0.999, dof), (stat, dof)


@pytest.mark.slow
@pytest.mark.parametrize("lux", [0.0, 0.5, 2.0, 9.0, 18.0])
@pytest.mark.parametrize("window_us", [100_000, 250_000, 2_000_000])
def test_direct_sampler_joint_distribution_slow(lux, window_us):
    """As above with 100 times the pixels (the same significance level, so a smaller bias is caught)."""
    from scipy.stats import chi2

    stat, dof = _joint_chi2(lux, window_us, 1200, seed=777)
    assert stat < chi2.ppf(0.999, dof), (stat, dof)


def test_direct_sampler_does_not_depend_on_crop_split():
    """Same seed, same counts; different seeds differ (the kernel is a pure function of its key)."""
    config = PairConfig(sensor_shape=(16, 16), params=PARAMS, seed=0)
    sampler = CountSampler(config)
    codes, _ = quantise(np.linspace(0, 18, 256).reshape(16, 16), config.lux_step)
    a = sampler.sample(codes, 500_000, seed=7)
    b = CountSampler(config).sample(codes, 500_000, seed=7)
    c = sampler.sample(codes, 500_000, seed=8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_saturation_is_counted(tmp_path):
    """Binned counts above 65535 saturate, and the pair and the manifest say how many."""
    counts, n = to_uint16(np.array([[[70000, 3]], [[65535, 65536]]]))
    assert counts.dtype == np.uint16 and n == 2
    assert counts.tolist() == [[[65535, 3]], [[65535, 65535]]]
    fast = ev.NoiseParams(eps_pos=0.2, eps_neg=0.2, bias_pr=0.0, trial_rate_hz=1e6, photons_per_lux=1.0)
    img = tmp_path / "img"
    img.mkdir()
    _write_png(img / "x.png", np.full((4, 4), 128, dtype=np.uint8))
    config = PairConfig(sensor_shape=(4, 4), windows_s=(0.1,), params=fast, seed=1, splits=(1, 0, 0))
    result = make_dataset(img, tmp_path / "ds", config, workers=1)
    item = PairDataset(tmp_path / "ds")[0]
    assert item["saturated"] > 0 and result.manifest["totals"]["saturated_bins"] == item["saturated"]
    assert item["counts"].max() == 65535


# --------------------------------------------------------------------------------------
# reproducibility: workers, resume, Dask
# --------------------------------------------------------------------------------------
def test_reference_dataset_layout(reference):
    out, hashes, result = reference
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["format"] == "evnoise-pairs"
    assert manifest["config"]["seed"] == 11 and manifest["config"]["params"] == PARAMS.to_dict()
    assert manifest["evnoise_version"] == ev.__version__
    assert manifest["totals"]["samples"] == 5 * 2 * 2
    assert not (out / PROGRESS_DIR).exists()
    for shard in manifest["shards"]:
        assert hashes[shard["file"]] == shard["sha256"]
        assert shard["bytes"] == (out / shard["file"]).stat().st_size
    item = PairDataset(out, "train")[0]
    assert item["counts"].dtype == np.uint16 and item["counts"].shape == (2, 8, 8)
    assert item["image"].dtype == np.float32 and item["image"].shape == (8, 8)
    assert 0.0 <= item["image"].min() and item["image"].max() <= 1.0
    assert isinstance(item["window_s"], float) and isinstance(item["source"], str)
    assert result.sampler == "direct-trials"


def test_one_and_two_workers_give_identical_bytes(reference, tmp_path):
    _, hashes, _ = reference
    result = make_dataset(SMALL_SOURCES, tmp_path / "two", SMALL, workers=2)
    assert result.workers == 2
    assert _hashes(tmp_path / "two") == hashes


def test_interrupted_run_resumes_to_identical_bytes(reference, tmp_path, monkeypatch):
    import evnoise.generators.dataset as dataset

    _, hashes, _ = reference
    real = dataset.generate_shard
    calls = []

    def interrupted(job, on_sample=None):
        if len(calls) == 2:
            raise KeyboardInterrupt  # as if the user pressed Ctrl-C during the third shard
        calls.append(job.task.name)
        return real(job, on_sample)

    monkeypatch.setattr(dataset, "generate_shard", interrupted)
    out = tmp_path / "ds"
    with pytest.raises(KeyboardInterrupt):
        make_dataset(SMALL_SOURCES, out, SMALL, workers=1)
    assert not (out / MANIFEST).exists() and (out / PROGRESS_DIR / "plan.json").exists()
    assert len(list((out / "shards").glob("*.h5"))) == 2
    with pytest.raises(InputError, match="incomplete"):
        PairDataset(out)
    assert main(["info", os.fspath(out)]) == 2  # "incomplete ...; run the same command again"
    # a half-written temporary file of the interrupted shard must not survive either
    gone = subprocess.Popen([sys.executable, "-c", "pass"])  # the temporary's writer: a process that ended
    gone.wait()
    (out / "shards" / f".val-00000.h5.{gone.pid}-abcd.tmp").write_bytes(b"partial")
    monkeypatch.setattr(dataset, "generate_shard", real)
    # resume without giving the seed again: the interrupted run's seed is reused
    result = make_dataset(SMALL_SOURCES, out, SMALL.replace(seed=None), workers=1)
    assert sorted(result.reused) == sorted(calls)
    assert len(result.generated) == len(hashes) - 1 - 2
    assert _hashes(out) == hashes
    assert not list((out / "shards").glob(".*.tmp"))


def test_corrupt_or_missing_shards_are_regenerated(reference, tmp_path):
    _, hashes, _ = reference
    out = tmp_path / "ds"
    make_dataset(SMALL_SOURCES, out, SMALL, workers=1)
    shards = sorted((out / "shards").glob("*.h5"))
    data = bytearray(shards[0].read_bytes())
    data[len(data) // 2] ^= 0xFF  # flip one byte in the middle of the file
    shards[0].write_bytes(bytes(data))
    shards[1].unlink()
    result = make_dataset(SMALL_SOURCES, out, SMALL, workers=1)
    assert sorted(result.generated) == sorted(p.stem for p in shards[:2])
    assert _hashes(out) == hashes
    again = make_dataset(SMALL_SOURCES, out, SMALL, workers=1)  # complete: verified, nothing to do
    assert again.generated == [] and len(again.reused) == len(shards)


def test_dask_local_cluster_gives_identical_bytes(reference, tmp_path):
    distributed = pytest.importorskip("distributed")
    _, hashes, _ = reference
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None) as cluster:
        make_dataset(SMALL_SOURCES, tmp_path / "dask", SMALL, scheduler=cluster.scheduler_address)
    assert _hashes(tmp_path / "dask") == hashes


def test_default_path_imports_neither_dask_nor_torch(reference, tmp_path):
    out, _, _ = reference
    code = ("import sys; from evnoise.generators import DeadLeaves, PairConfig, PairDataset, make_dataset; "
            f"ds = PairDataset({os.fspath(out)!r}); ds[0]; "
            f"make_dataset(DeadLeaves(2), {os.fspath(tmp_path / 'ds')!r}, "
            "PairConfig(sensor_shape=(8, 8), seed=1), workers=1); "
            "assert 'dask' not in sys.modules and 'distributed' not in sys.modules, 'dask imported'; "
            "assert 'torch' not in sys.modules, 'torch imported'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


# --------------------------------------------------------------------------------------
# splits and the reader
# --------------------------------------------------------------------------------------
def test_splits_are_disjoint_by_source(reference):
    out, _, _ = reference
    by_split = {s: set(PairDataset(out, s).sources) for s in ("train", "val", "test")}
    assert all(by_split.values())
    assert not (by_split["train"] & by_split["val"] or by_split["train"] & by_split["test"]
                or by_split["val"] & by_split["test"])
    assert set().union(*by_split.values()) == set(SMALL_SOURCES.items())
    # every crop and window of a source lands in the source's split
    for split, sources in by_split.items():
        ds = PairDataset(out, split)
        assert sorted(ds[i]["source"] for i in range(len(ds))) == sorted(ds.sources)
        assert len(ds) == 4 * len(sources)


def test_split_assignment_sizes_and_stability():
    ids = [f"img{k:04d}.png" for k in range(200)]
    splits = _assign_splits(ids, (0.8, 0.1, 0.1))
    sizes = {s: sum(v == s for v in splits.values()) for s in ("train", "val", "test")}
    assert sizes == {"train": 160, "val": 20, "test": 20}
    assert _assign_splits(list(reversed(ids)), (0.8, 0.1, 0.1)) == splits  # order does not matter
    small = _assign_splits(["a", "b", "c"], (0.8, 0.1, 0.1))
    assert sorted(small.values()) == ["test", "train", "val"]
    assert set(_assign_splits(["a"], (0.8, 0.1, 0.1)).values()) == {"train"}


def test_pair_dataset_with_torch_dataloader_workers(reference):
    torch = pytest.importorskip("torch")
    from torch.utils.data import DataLoader

    out, _, _ = reference
    ds = PairDataset(out, "train")
    ds[0]  # opens a handle in this process; workers must not reuse it
    clone = pickle.loads(pickle.dumps(ds))
    assert clone._handles == {} and len(clone) == len(ds)
    loader = DataLoader(ds, batch_size=3, num_workers=2, shuffle=False)
    batches = list(loader)
    total = sum(b["counts"].shape[0] for b in batches)
    assert total == len(ds)
    first = batches[0]
    assert first["counts"].shape[1:] == (2, 8, 8) and first["image"].dtype == torch.float32
    assert np.array_equal(first["counts"][0].numpy(), ds[0]["counts"])
    assert list(first["source"]) == [ds[i]["source"] for i in range(3)]


def test_pair_dataset_errors(reference, tmp_path):
    out, _, _ = reference
    with pytest.raises(ParameterError, match="split"):
        PairDataset(out, "training")
    with pytest.raises(InputError, match="not an evnoise dataset"):
        PairDataset(tmp_path)
    ds = PairDataset(out, "train")
    with pytest.raises(IndexError):
        ds[len(ds)]
    assert np.array_equal(ds[-1]["counts"], ds[len(ds) - 1]["counts"])
    assert PairDataset(out, "train", verify=True)[0]["seed"] == ds[0]["seed"]


def test_training_and_evaluation_open_datasets_checked_against_their_checksums(reference, tmp_path):
    """A shard whose bytes changed after make-dataset (counts of 32512 where 344 is possible) was trained on and
    scored without a word: ``open_pairs`` (train, evaluate) checks the split's shards against the manifest."""
    import shutil

    from evnoise.reconstruct.data import open_pairs

    out, _, _ = reference
    copy = tmp_path / "ds"
    shutil.copytree(out, copy)
    shard = sorted((copy / "shards").glob("train-*.h5"))[0]
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(InputError, match="does not match its checksum"):
        open_pairs(copy, "train")
    assert len(open_pairs(copy, "val")) == len(PairDataset(out, "val"))  # other splits' shards are not read
    assert len(open_pairs(copy, "train", verify=False)) == len(PairDataset(out, "train"))


# --------------------------------------------------------------------------------------
# bad inputs
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("workers", [1, 2])
def test_progress_bar_ends_at_the_pairs_made_when_a_source_is_skipped(tmp_path, monkeypatch, workers):
    """A skipped image's planned pairs were counted as made: the bar ended at 9/9 with 8 pairs written."""
    import tqdm.auto

    seen = []

    class Recording(tqdm.auto.tqdm):
        def close(self):
            seen.append((self.n, self.total))
            super().close()

    monkeypatch.setattr(tqdm.auto, "tqdm", Recording)
    folder = tmp_path / "imgs"
    folder.mkdir()
    for name in ("img1.png", "img2.png", "img4.png"):
        _write_png(folder / name, _stripes(16))
    (folder / "img3.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    config = PairConfig(sensor_shape=(16, 56), windows_s=(0.5, 1.0), params=PARAMS, seed=2, shard_size=1)
    result = make_dataset(folder, tmp_path / "ds", config, workers=workers, progress=True)
    made = result.manifest["totals"]["samples"]
    assert made == 6 and seen[-1] == (made, made)


def test_empty_folder_is_an_input_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="holds no image files"):
        make_dataset(tmp_path / "empty", tmp_path / "ds", SMALL, workers=1)
    assert not (tmp_path / "ds").exists()  # nothing is written before the inputs are checked


def test_corrupt_image_is_skipped_and_counted(tmp_path, caplog):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for name in ("img1.png", "img2.png", "img4.png", "img5.png"):
        _write_png(folder / name, _stripes(16))
    (folder / "img3.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    config = PairConfig(sensor_shape=(16, 56), windows_s=(0.5,), params=PARAMS, seed=2, shard_size=1)
    with caplog.at_level(logging.WARNING, logger="evnoise"):
        result = make_dataset(folder, tmp_path / "ds", config, workers=1)
    skipped = result.manifest["skipped"]
    assert [s["source"] for s in skipped] == ["img3.png"]
    assert "cannot read image" in skipped[0]["reason"]
    assert result.manifest["totals"]["skipped_sources"] == 1
    assert result.manifest["totals"]["sources"] == 4 and result.manifest["totals"]["sources_planned"] == 5
    assert any("img3.png" in r.getMessage() for r in caplog.records)
    total = sum(len(PairDataset(tmp_path / "ds", s)) for s in ("train", "val", "test"))
    assert total == 4
    code = main(["info", os.fspath(tmp_path / "ds"), "--json"])
    assert code == 0


def test_output_errors(tmp_path, stripe_folder):
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    with pytest.raises(OutputError, match="does not exist|not a folder"):
        make_dataset(stripe_folder, blocker / "ds", SMALL, workers=1)
    with pytest.raises(OutputError, match="not a folder"):
        make_dataset(stripe_folder, blocker, SMALL, workers=1)
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="not empty"):
        make_dataset(stripe_folder, busy, SMALL, workers=1)


def test_other_options_in_existing_dataset_are_refused(reference, tmp_path):
    out = tmp_path / "ds"
    make_dataset(SMALL_SOURCES, out, SMALL, workers=1)
    with pytest.raises(OutputError, match="seed"):
        make_dataset(SMALL_SOURCES, out, SMALL.replace(seed=12), workers=1)
    result = make_dataset(SMALL_SOURCES, out, SMALL.replace(seed=12), workers=1, overwrite=True)
    assert result.manifest["config"]["seed"] == 12


@pytest.mark.parametrize("windows", [(0.0,), (-1.0,), (float("nan"),), (1.0, 1.0000001), (), ("a",), (1e-9,)])
def test_invalid_windows(windows):
    with pytest.raises(ParameterError, match="window"):
        PairConfig(windows_s=windows)


@pytest.mark.parametrize("changes, match", [
    ({"crop_shape": (1000, 16)}, "larger than the sensor"),
    ({"sensor_shape": (31, 32)}, "multiple of binning"),
    ({"crops_per_image": 3}, "needs a crop_shape"),
    ({"max_lux": (20, 10)}, "low <= high"),
    ({"splits": (0, 0, 0)}, "splits"),
    ({"mode": "magic"}, "mode"),
    ({"compression": "zstd"}, "compression"),
])
def test_invalid_config(changes, match):
    with pytest.raises(ParameterError, match=match):
        PairConfig(**changes)


def test_cli_errors_are_one_line(tmp_path, capsys, stripe_folder):
    out = os.fspath(tmp_path / "ds")
    assert main(["make-dataset", os.fspath(stripe_folder), "--out", out, "--window", "0.1,abc"]) == 2
    assert "--window must be a number, got 'abc'" in capsys.readouterr().err
    assert main(["make-dataset", "--out", out]) == 2
    assert "no scenes" in capsys.readouterr().err
    assert main(["make-dataset", "--procedural", "dead-leaves", "--out", out]) == 2
    assert "--count" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["make-dataset", os.fspath(tmp_path / "empty"), "--out", out]) == 2
    assert "holds no image files" in capsys.readouterr().err


# --------------------------------------------------------------------------------------
# command line and info
# --------------------------------------------------------------------------------------
def test_cli_make_dataset_and_info(tmp_path, capsys):
    out = tmp_path / "dl"
    code = main(["-q", "make-dataset", "--procedural", "dead-leaves", "--count", "3", "--sensor", "48x32",
                 "--crop", "16", "--crops-per-image", "2", "--window", "0.25,1", "--max-lux", "6:30",
                 "--contrast", "0.8:1.25", "--seed", "4", "--workers", "1", "--out", os.fspath(out)])
    assert code == 0
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["config"]["max_lux"] == [6.0, 30.0] and manifest["config"]["white_lux"] == 30.0
    ds = PairDataset(out, "train")
    draws = {(ds[i]["source"], ds[i]["crop_index"]): (ds[i]["max_lux"], ds[i]["contrast_gamma"])
             for i in range(len(ds))}
    assert all(6 <= m <= 30 and 0.8 <= g <= 1.25 for m, g in draws.values())
    assert len(set(draws.values())) == len(draws)  # every crop has its own draws
    capsys.readouterr()
    assert main(["info", os.fspath(out)]) == 0
    text = capsys.readouterr().out
    assert "kind:" in text and "dataset" in text and "pairs:" in text and "sanity" in text
    assert main(["info", os.fspath(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["kind"] == "dataset" and info["pairs"] == 12


def test_info_sanity_table_agrees_with_model(tmp_path, stripe_folder):
    from evnoise.generators.summary import sanity_rows

    config = PairConfig(sensor_shape=(32, 56), windows_s=(1.0,), params=PARAMS, seed=9, splits=(1, 0, 0))
    make_dataset(stripe_folder, tmp_path / "ds", config, workers=1)
    rows = sanity_rows(tmp_path / "ds", json.loads((tmp_path / "ds" / MANIFEST).read_text()))
    assert sum(r["pixels"] for r in rows) >= 0.4 * 4 * 16 * 28  # stripe interiors are flat
    for row in rows:
        assert abs(row["on_z"]) < 4.5 and abs(row["off_z"]) < 4.5, row
        assert row["on_predicted_hz"] > 0


# --------------------------------------------------------------------------------------
# scene sources
# --------------------------------------------------------------------------------------
def test_dead_leaves_is_deterministic_and_scale_invariant():
    from evnoise.generators import dead_leaves

    a = dead_leaves((128, 128), 3)
    assert np.array_equal(a, dead_leaves((128, 128), 3))
    assert not np.array_equal(a, dead_leaves((128, 128), 4))
    assert a.min() >= 0 and a.max() <= 1 and a.std() > 0.1
    # radially averaged power spectrum ~ f^-2 for a dead-leaves model with r^-3 radii
    img = dead_leaves((256, 256), 5)
    spec = np.abs(np.fft.fftshift(np.fft.fft2(img - img.mean()))) ** 2
    y, x = np.indices(spec.shape) - 128
    r = np.hypot(x, y).astype(int)
    radial = np.bincount(r.ravel(), spec.ravel()) / np.bincount(r.ravel())
    f = np.arange(4, 48)
    slope = np.polyfit(np.log(f), np.log(radial[f]), 1)[0]
    assert -3.2 < slope < -1.5, slope


def test_dead_leaves_source_ids_and_seeds():
    src = DeadLeaves(3)
    assert src.items() == ["dead-leaves/000000", "dead-leaves/000001", "dead-leaves/000002"]
    from evnoise.generators.sources import LoadContext

    ctx = LoadContext((16, 24), "srgb", False, 1)
    y0, kind = src.load("dead-leaves/000001", ctx)
    assert kind == "display" and y0.shape == (16, 24)
    assert np.array_equal(y0, DeadLeaves(10).load("dead-leaves/000001", ctx)[0])  # depends on id and seed only
    from evnoise.generators.sources import source_from_spec

    assert source_from_spec(json.loads(json.dumps(src.spec()))) == src
    assert not np.array_equal(y0, src.load("dead-leaves/000001", ctx._replace(seed=2))[0])


def test_package_photos(tmp_path):
    pytest.importorskip("skimage")
    src = PackagePhotos()
    items = src.items()
    assert "skimage/astronaut.png" in items and "skimage/camera.png" in items
    from evnoise.generators.sources import LoadContext

    y, kind = src.load("skimage/camera.png", LoadContext((8, 8), "srgb", False, 0))
    assert kind == "display" and y.shape == (512, 512) and 0 <= y.min() and y.max() <= 1
    config = PairConfig(sensor_shape=(32, 48), crop_shape=(16, 16), windows_s=(0.5,), params=PARAMS, seed=3)
    result = make_dataset(PackagePhotos(("skimage",)), tmp_path / "ph", config, workers=1)
    splits = result.manifest["splits"]
    assert result.manifest["skipped"] == []
    assert splits["val"]["sources"] >= 1 and splits["test"]["sources"] >= 1
    assert sum(s["sources"] for s in splits.values()) == len([i for i in items if i.startswith("skimage/")])


def test_folder_source_ids_are_file_names(stripe_folder):
    assert FolderSource(stripe_folder).items() == ["a.png", "b.png", "c.png", "d.png"]
    plan = plan_dataset([stripe_folder], SMALL.replace(crop_shape=None, crops_per_image=1, sensor_shape=(32, 56)))
    names = [i for t in plan.shards for _, i in t.items]
    assert sorted(names) == ["a.png", "b.png", "c.png", "d.png"]


def test_linear_to_srgb_inverts_decoding():
    from evnoise.radiometry import srgb_to_linear

    v = np.linspace(0, 1, 1001)
    assert np.allclose(linear_to_srgb(srgb_to_linear(v)), v, atol=1e-12)
    assert np.allclose(linear_to_srgb(np.array([-1.0, 2.0])), [0.0, 1.0], atol=1e-15)
