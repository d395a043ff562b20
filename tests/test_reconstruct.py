"""Tests of the reconstructor: model, checkpoints, training, metrics, baselines, inference, CLI.

Small and fast (tiny U-Nets, 16-32 px crops, a few steps, one torch thread). Longer runs are in
test_reconstruct_slow.py.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import pickle
import subprocess
import sys
import warnings

import numpy as np
import pytest

import evnoise as ev
from evnoise.errors import InputError, OutputError, ParameterError
from evnoise.reconstruct.baselines import MLInversion, count_image
from evnoise.reconstruct.data import (
    NpzPairs,
    PairList,
    ResampledPairs,
    Subset,
    item_seed,
    save_pairs_npz,
    split_by_source,
)
from evnoise.reconstruct.imaging import bin_counts, bin_mean, lux_to_display, srgb_decode, srgb_encode
from evnoise.reconstruct.metrics import psnr, ssim

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from evnoise.cli import main  # noqa: E402
from evnoise.reconstruct.checkpoint import (  # noqa: E402
    InputSpec,
    describe_checkpoint,
    load_model,
    read_checkpoint,
    save_checkpoint,
)
from evnoise.reconstruct.infer import Reconstructor, counts_from_h5  # noqa: E402
from evnoise.reconstruct.train import TrainConfig, train  # noqa: E402
from evnoise.reconstruct.unet import UNet, UNetConfig  # noqa: E402

TINY = {"base_channels": 8, "channel_mults": (1, 2), "groups": 4, "stem": 1}
# Fixed parameters (the Noise2Image authors' published values), not the shipped preset, so that
# the floors below do not move when the preset is refitted: the refit has much smaller
# thresholds (many more signal events per edge) and ON/OFF curves that peak at the same lux.
PARAMS = ev.NoiseParams(eps_pos=0.904, eps_neg=1.0235, bias_pr=1.7023, trial_rate_hz=21.9882, photons_per_lux=1.005,
                        dark_lux=0.193)
MAX_LUX = 20.0


def scene(seed, size=64):
    """A procedural display-encoded scene: gradient, discs and bars (no third-party images)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    img = 0.2 + 0.6 * (rng.uniform(-1, 1) * xx + rng.uniform(-1, 1) * yy + 1) / 2
    for _ in range(4):
        cy, cx, r = rng.uniform(0.1, 0.9, 2).tolist() + [rng.uniform(0.05, 0.25)]
        img[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = rng.uniform(0, 1)
    img[:, int(size * rng.uniform(0.1, 0.9))] = rng.uniform(0, 1)
    return np.round(np.clip(img, 0, 1) * 255) / 255  # 8-bit, like a photo


def resampled(n=4, size=64, seed=0, window_s=1.0, **kw):
    lux = [srgb_decode(scene(seed * 100 + i, size)) * MAX_LUX for i in range(n)]
    return ResampledPairs(lux, PARAMS, window_s=window_s, max_lux=MAX_LUX, sources=[f"s{seed}-{i}" for i in range(n)],
                          seed=seed, **kw)


def write_events_h5(path, events, width, height):
    """A minimal DSEC-layout events.h5, written with h5py directly."""
    import h5py

    t = events["t"]
    n_ms = int(t[-1] // 1000) + 2 if t.size else 1
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        for k in ("t", "x", "y", "p"):
            g.create_dataset(k, data=events[k])
        f.create_dataset("ms_to_idx", data=np.searchsorted(t, np.arange(n_ms) * 1000, "left").astype(np.uint64))
        f.create_dataset("t_offset", data=np.int64(0))
        f.attrs["width"] = width
        f.attrs["height"] = height


def random_events(rng, width, height, n, duration_us):
    t = np.sort(rng.integers(0, duration_us, n)).astype(np.int64)
    return ev.events.make_events(t, rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n))


# -- imaging -------------------------------------------------------------------------------
def test_srgb_round_trip_and_known_values():
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-12)
    assert srgb_encode(0.18) == pytest.approx(0.4613561295, abs=1e-9)  # middle grey
    assert lux_to_display(MAX_LUX, MAX_LUX) == pytest.approx(1.0)


def test_bin_counts_sums_blocks_and_drops_partial_edges():
    c = np.arange(2 * 5 * 7).reshape(2, 5, 7)
    b = bin_counts(c, 2)
    assert b.shape == (2, 2, 3)
    assert b[1, 1, 2] == c[1, 2:4, 4:6].sum()
    assert bin_mean(np.ones((5, 7)), 2).shape == (2, 3)
    with pytest.raises(InputError):
        bin_counts(np.zeros((2, 1, 5)), 2)
    with pytest.raises(ParameterError):
        bin_counts(c, 0)


# -- model ---------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [(32, 32), (17, 45), (1, 1), (40, 24)])
def test_unet_output_shape_for_any_size(shape):
    net = UNet(base_channels=8, channel_mults=(1, 2, 2), groups=4, stem=2)  # multiple of 8
    x = torch.rand(2, 2, *shape)
    assert net(x).shape == (2, 1, *shape)


def test_unet_shape_errors():
    net = UNet(**TINY, padding="none")
    assert net(torch.rand(1, 2, 8, 10)).shape == (1, 1, 8, 10)
    with pytest.raises(InputError, match="multiples of 2"):
        net(torch.rand(1, 2, 9, 10))
    with pytest.raises(InputError, match=r"\(N, 2, H, W\)"):
        net(torch.rand(1, 3, 8, 8))
    with pytest.raises(InputError):
        net(torch.rand(2, 8, 8))
    with pytest.raises(ParameterError, match="groups"):
        UNetConfig(base_channels=6, groups=4)
    with pytest.raises(ParameterError):
        UNetConfig(padding="circular")
    with pytest.raises(TypeError):
        UNet(8)  # hyper-parameters are keyword-only


def test_checkpoint_round_trip_with_weights_only(tmp_path):
    torch.manual_seed(0)
    net = UNet(**TINY)
    spec = InputSpec(binning=2, rate_scale_hz=2.5, window_s=1.0, max_lux=20.0)
    path = save_checkpoint(tmp_path / "m.pt", model_config=net.config, input_spec=spec, state_dict=net.state_dict(),
                           train_state={"epoch": 3, "history": {"val_loss": [0.5, 0.4]}})
    raw = torch.load(path, weights_only=True)  # plain data only
    assert raw["format"] == "evnoise-reconstructor" and raw["evnoise_version"] == ev.__version__
    assert raw["model"] == net.config.to_dict() and raw["train"]["epoch"] == 3
    model, spec2, _ = load_model(path)
    assert spec2.to_dict() == spec.to_dict()
    x = torch.rand(1, 2, 12, 20)
    with torch.no_grad():
        torch.testing.assert_close(model(x), net.eval()(x), rtol=0, atol=0)
    text = describe_checkpoint(path)
    assert "parameters" in text and "binning: 2x2" in text


class _Evil:
    def __reduce__(self):
        return (print, ("this must never run",))


def test_read_checkpoint_rejects_foreign_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_checkpoint(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint at all")
    with pytest.raises(InputError, match=r"not an evnoise model checkpoint \(not a PyTorch file\)"):
        read_checkpoint(junk)
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match=r"\(an empty file\)"):
        read_checkpoint(empty)
    whole = tmp_path / "whole.pt"
    torch.save({"weights": torch.zeros(300)}, whole)
    cut = tmp_path / "cut.pt"  # an interrupted download: was called "not a PyTorch file"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    with pytest.raises(InputError, match=r"\(a PyTorch file cut short: its end is missing"):
        read_checkpoint(cut)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(InputError, match="not an evnoise reconstructor"):
        read_checkpoint(other)
    evil = tmp_path / "evil.pt"
    with open(evil, "wb") as fh:
        pickle.dump({"format": "evnoise-reconstructor", "x": _Evil()}, fh, protocol=2)
    with pytest.raises(InputError):
        read_checkpoint(evil)  # weights_only refuses arbitrary callables


# -- data ----------------------------------------------------------------------------------
def test_split_by_source_is_disjoint_and_reproducible():
    sources = ["a", "a", "b", "c", "c", "d", "e", "f"]
    data = PairList([np.zeros((2, 4, 4))] * 8, [np.zeros((4, 4))] * 8, window_s=1.0, sources=sources)
    tr, va = split_by_source(data, val_fraction=0.3, seed=1)
    assert sorted(tr + va) == list(range(8))
    assert not {sources[i] for i in tr} & {sources[i] for i in va}
    assert (tr, va) == split_by_source(data, val_fraction=0.3, seed=1)
    with pytest.raises(InputError):
        split_by_source(PairList([np.zeros((2, 4, 4))], [np.zeros((4, 4))], window_s=1.0), val_fraction=0.5)


def test_pairs_refuse_a_window_per_other_count_and_images_outside_0_1(tmp_path):
    """A ``window_s`` of 2 values for 4 pairs was a NumPy broadcasting traceback; 8-bit images (0..255) were scored
    with PSNR near -43 dB, the metrics taking a data range of 1."""
    counts, images = [np.zeros((2, 4, 4))] * 4, [np.full((4, 4), 0.5)] * 4
    with pytest.raises(InputError, match="2 values of window_s for 4 pairs"):
        PairList(counts, images, window_s=[1.0, 2.0])
    assert len(PairList(counts, images, window_s=[1.0, 2.0, 1.0, 2.0])) == 4
    with pytest.raises(InputError, match=r"\[0, 1\], found 200 \(8-bit values\? divide by 255\)"):
        PairList(counts, [np.full((4, 4), 200.0)] * 4, window_s=1.0)
    for bad in (np.nan, -0.1):
        with pytest.raises(InputError, match=r"in \[0, 1\]"):
            PairList(counts, [np.full((4, 4), bad)] * 4, window_s=1.0)
    np.savez(tmp_path / "p.npz", counts=np.zeros((4, 2, 4, 4), np.uint16), images=np.full((4, 4, 4), 255.0),
             window_s=np.ones(2))
    with pytest.raises(InputError, match="p.npz: 2 values of window_s"):
        NpzPairs(tmp_path / "p.npz")


def test_resampled_pairs_are_reproducible_and_fresh_per_seed():
    ds = resampled(n=2, size=32)
    a, b = ds[1], ds[1]
    np.testing.assert_array_equal(a["counts"], b["counts"])
    assert a["counts"].dtype == np.uint16 and a["counts"].shape == (2, 16, 16) and a["image"].shape == (16, 16)
    c = ds.sample(1, item_seed(0, 5, 1), None)
    assert not np.array_equal(a["counts"], c["counts"])
    crop = ds.sample(0, item_seed(0, 1, 1), 8)
    assert crop["counts"].shape == (2, 8, 8) and crop["image"].shape == (8, 8)


@pytest.mark.parametrize("distribution", ["exact", "poisson"])
def test_fast_count_sampler_matches_the_simulator(distribution):
    """Flat field: the precomputed-probability sampler against sample_counts (mean and variance)."""
    lux = np.full((64, 64), 2.0)
    ds = ResampledPairs([lux], PARAMS, window_s=0.8, max_lux=MAX_LUX, binning=1, distribution=distribution)
    fast = np.stack([ds.sample(0, item_seed(1, k), None)["counts"] for k in range(4)]).astype(float)
    ref = np.stack([ev.sample_counts(lux, PARAMS, 0.8, k, threads=1) for k in range(4)]).astype(float)
    mean = ev.expected_rate(np.array([2.0]), PARAMS)[:, 0] * 0.8
    n = fast[:, 0].size
    for pol in (0, 1):
        for sample in (fast, ref):
            se = math.sqrt(mean[pol] / n)
            assert abs(sample[:, pol].mean() - mean[pol]) < 4 * se
        if distribution == "exact":  # same distribution: variances agree too (Poisson's is larger)
            assert fast[:, pol].var() == pytest.approx(ref[:, pol].var(), rel=0.08)


# -- metrics -------------------------------------------------------------------------------
def test_psnr_by_hand():
    a = np.zeros((8, 8))
    b = np.full((8, 8), 0.1)
    assert psnr(b, a) == pytest.approx(20.0)  # MSE 0.01
    assert psnr(a, a) == math.inf
    with pytest.raises(InputError):
        psnr(a, np.zeros((8, 9)))


def test_ssim_matches_an_independent_computation():
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(3)
    x = gaussian_filter(rng.random((48, 40)), 2)
    y = np.clip(x + rng.normal(0, 0.05, x.shape), 0, 1)

    def f(z):  # Gaussian window sigma 1.5, truncated at 3.5 sigma, as Wang et al.
        return gaussian_filter(z, 1.5, truncate=3.5)

    mx, my = f(x), f(y)
    vx, vy, cxy = f(x * x) - mx * mx, f(y * y) - my * my, f(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    smap = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    pad = 5  # scikit-image averages away from a border of (win_size - 1) / 2
    assert ssim(y, x) == pytest.approx(smap[pad:-pad, pad:-pad].mean(), abs=1e-6)
    assert ssim(x, x) == pytest.approx(1.0)


def _lpips_or_skip():
    from evnoise.reconstruct.lpips import LPIPS, LPIPSWeightsMissing

    try:
        return LPIPS()
    except LPIPSWeightsMissing:
        pytest.skip("LPIPS weights not installed (python -m evnoise.reconstruct.lpips install)")


def test_lpips_identical_images_is_zero_and_reference_value():
    lp = _lpips_or_skip()
    import skimage.data

    cam = skimage.data.camera()[100:164, 50:150] / 255.0
    assert lp.distance(cam, cam) == 0.0
    # value of the reference implementation (lpips 0.1.4, AlexNet, v0.1) on the same weights
    assert lp.distance(cam, cam**2) == pytest.approx(0.058370, abs=2e-6)
    from evnoise.reconstruct.lpips import reference_check

    assert reference_check(lp) == pytest.approx(0.058370, abs=2e-6)
    assert lp.distance(cam, 1 - cam) > lp.distance(cam, cam**2)
    with pytest.raises(InputError):
        lp.distance(cam[:20, :20], cam[:20, :20])


def test_lpips_unpickler_refuses_code(tmp_path):
    from evnoise.reconstruct.lpips import convert_ckpt, install_weights

    with pytest.raises(InputError):
        convert_ckpt(pickle.dumps({"AlexNet_0": _Evil()}))
    bad = tmp_path / "alexnet.ckpt"
    bad.write_bytes(pickle.dumps({"a": 1}))
    with pytest.raises(InputError, match="SHA-256"):
        install_weights(bad, dest=tmp_path / "w.npz")


# -- baselines -----------------------------------------------------------------------------
def test_count_image_baselines():
    rng = np.random.default_rng(0)
    counts = rng.poisson(3, (2, 10, 12))
    target = rng.random((10, 12))
    mm = count_image(counts)
    assert mm.min() == 0 and mm.max() == 1
    fit = count_image(counts, target=target, mode="affine")
    total = counts.sum(0).ravel()
    slope, icpt = np.polyfit(total, target.ravel(), 1)
    np.testing.assert_allclose(fit.ravel(), np.clip(slope * total + icpt, 0, 1), atol=1e-12)
    with pytest.raises(ParameterError):
        count_image(counts, mode="affine")


def test_ml_inversion_recovers_flat_field_within_statistical_error():
    lux0, window = 1.0, 200.0
    inv = MLInversion(PARAMS, max_lux=MAX_LUX, binning=2, smoothing_sigma=0.0)
    mu = ev.expected_rate(np.array([lux0]), PARAMS)[:, 0] * 4 * window
    rng = np.random.default_rng(7)
    counts = rng.poisson(mu[:, None, None] * np.ones((2, 48, 48)))
    est = inv.lux(counts, window)
    sigma = float(inv.cramer_rao_std(lux0, window)[0])
    grid_step = float(np.max(np.diff(inv.lux_grid)[np.abs(inv.lux_grid[1:] - lux0) < 0.5]))
    n = est.size
    assert abs(est.mean() - lux0) < 4 * sigma / math.sqrt(n) + grid_step
    assert est.std() == pytest.approx(sigma, rel=0.15)
    np.testing.assert_allclose(inv.display(counts, window).mean(), lux_to_display(lux0, MAX_LUX), atol=0.01)
    # another white level (a pair's own lux_scale) changes the search range, not the estimate
    assert inv.lux(counts, window, max_lux=8.0).mean() == pytest.approx(est.mean(), abs=0.02)
    assert inv.display(counts, window, max_lux=8.0).mean() == pytest.approx(lux_to_display(lux0, 8.0), abs=0.01)


# -- training ------------------------------------------------------------------------------
TINY_CFG = dict(epochs=3, steps_per_epoch=6, batch_size=4, crop=16, lr=3e-3, val_crop=32, patience=None, seed=5)


def test_tiny_training_reduces_validation_loss_and_is_reproducible(tmp_path, caplog):
    tr, va = resampled(n=3, size=64, seed=1), resampled(n=1, size=64, seed=2)
    cfg = TrainConfig(**TINY_CFG)
    r1 = train(tr, tmp_path / "a.pt", val_data=va, config=cfg, model=TINY, progress=False, plot=False)
    hist = r1["history"]["val_loss"]
    assert len(hist) == 3 and hist[-1] < hist[0]
    assert r1["best_epoch"] == int(np.argmin(hist)) + 1
    # a run interrupted after two of three epochs and resumed ends exactly where the uninterrupted run ended
    part = train(tr, tmp_path / "b.pt", val_data=va, config=cfg, model=TINY, progress=False, plot=False,
                 on_epoch_end=lambda epoch, history: epoch == 2)
    assert part["stopped"] == "callback" and part["epochs"] == 2
    assert not read_checkpoint(tmp_path / "b.pt")["train"]["finished"]
    with caplog.at_level("WARNING", logger="evnoise"):
        load_model(tmp_path / "b.pt")  # usable, but an unfinished run's: said
    assert "unfinished training run (epoch 2 of 3)" in caplog.text
    caplog.clear()
    load_model(tmp_path / "a.pt")
    assert "unfinished" not in caplog.text
    for other_tr, other_va in ((resampled(n=3, size=64, seed=3), va), (tr, resampled(n=1, size=64, seed=4))):
        with pytest.raises(ParameterError, match="other data"):  # was taken: the card named the first data
            train(other_tr, tmp_path / "b.pt", val_data=other_va, config=cfg, model=TINY, resume=True,
                  progress=False, plot=False)
    r2 = train(tr, tmp_path / "b.pt", val_data=va, config=cfg, model=TINY, resume=True, progress=False, plot=False)
    assert r2["history"]["val_loss"] == hist
    a, _, _ = load_model(tmp_path / "a.pt", which="last")
    b, _, _ = load_model(tmp_path / "b.pt", which="last")
    sa, sb = a.state_dict(), b.state_dict()
    assert list(sa) == list(sb)
    for key in sa:
        torch.testing.assert_close(sa[key], sb[key], rtol=0, atol=0)


def test_a_run_saved_before_a_setting_existed_resumes_with_its_default(tmp_path):
    """A checkpoint whose training config lacks a later setting (``pixel_loss``) resumes under the default and
    is refused under another value; one without the digest of its data resumes."""
    tr, va = resampled(n=3, size=64, seed=1), resampled(n=1, size=64, seed=2)
    cfg = TrainConfig(**TINY_CFG)
    path = tmp_path / "old.pt"
    train(tr, path, val_data=va, config=cfg, model=TINY, progress=False, plot=False,
          on_epoch_end=lambda epoch, history: epoch == 1)
    doc = torch.load(path, map_location="cpu", weights_only=True)
    del doc["train"]["config"]["pixel_loss"]
    del doc["train"]["data_fingerprint"]  # (nor the digest of its data)
    torch.save(doc, path)
    with pytest.raises(ParameterError, match="pixel_loss"):
        train(tr, path, val_data=va, config=TrainConfig(**TINY_CFG, pixel_loss="mse"), model=TINY, resume=True,
              progress=False, plot=False)
    done = train(tr, path, val_data=va, config=cfg, model=TINY, resume=True, progress=False, plot=False)
    assert done["epochs"] == 3


def test_training_refuses_bad_setups(tmp_path):
    tr = resampled(n=3, size=32, seed=1)
    with pytest.raises(ParameterError):
        TrainConfig(crop=0)
    out = tmp_path / "m.pt"
    out.write_bytes(b"x")
    with pytest.raises(OutputError, match="exists"):
        train(tr, out, config=TrainConfig(**TINY_CFG), model=TINY, progress=False)
    with pytest.raises(InputError, match="both training and validation"):
        train(tr, tmp_path / "n.pt", val_data=Subset(tr, [0]), config=TrainConfig(**TINY_CFG), model=TINY,
              progress=False)
    with pytest.raises(ParameterError, match="multiple of"):
        train(tr, tmp_path / "n.pt", config=TrainConfig(**{**TINY_CFG, "crop": 15}), model=TINY, progress=False)


def test_training_loss_terms_by_hand():
    from evnoise.reconstruct.train import training_loss

    rng = np.random.default_rng(3)
    pred, target = rng.random((2, 1, 1, 20, 24))
    tp, tt = torch.from_numpy(pred), torch.from_numpy(target)
    l1 = float(training_loss(torch, tp, tt, TrainConfig(ssim_weight=0.0)))
    mse = float(training_loss(torch, tp, tt, TrainConfig(ssim_weight=0.0, pixel_loss="mse")))
    assert l1 == pytest.approx(np.abs(pred - target).mean(), rel=1e-12)
    assert mse == pytest.approx(((pred - target) ** 2).mean(), rel=1e-12)
    # the SSIM term adds w * (1 - SSIM), SSIM from the independent reference of test_ssim_matches_...
    with_ssim = float(training_loss(torch, tp, tt, TrainConfig(ssim_weight=0.5, pixel_loss="mse")))
    assert with_ssim == pytest.approx(mse + 0.5 * (1 - ssim(pred[0, 0], target[0, 0])), abs=1e-6)
    with pytest.raises(ParameterError, match="pixel_loss"):
        TrainConfig(pixel_loss="l2")


def test_loss_curve_png_is_written(tmp_path):
    pytest.importorskip("matplotlib")
    tr = resampled(n=3, size=32, seed=1)
    r = train(tr, tmp_path / "m.pt", config=TrainConfig(**{**TINY_CFG, "epochs": 1, "steps_per_epoch": 2}),
              model=TINY, progress=False)
    assert r["plot"].is_file() and r["plot"].read_bytes()[:4] == b"\x89PNG"


# -- inference and CLI ---------------------------------------------------------------------
def test_counts_from_h5_matches_count_events(tmp_path):
    rng = np.random.default_rng(2)
    events = random_events(rng, 20, 10, 5000, 3_000_000)
    path = tmp_path / "e.h5"
    write_events_h5(path, events, 20, 10)
    counts, window = counts_from_h5(path, t_start_s=0.7345, window_s=1.2)
    assert window == 1.2
    np.testing.assert_array_equal(counts, ev.count_events(events, (10, 20), 734_500, 1_934_500))
    full, w_all = counts_from_h5(path)
    assert full.sum() == events.size and w_all == pytest.approx((events["t"][-1] + 1) * 1e-6)
    with pytest.raises(InputError, match="past the end"):
        counts_from_h5(path, t_start_s=2.5, window_s=1.0)
    for bad in (0.0, -1.0, float("nan"), "one"):  # a string was a TypeError; the message said "window"
        with pytest.raises(ev.ParameterError, match="window_s must be"):
            counts_from_h5(path, window_s=bad)


def test_ml_inversion_refuses_a_window_it_cannot_count_in():
    """``lux`` refused a window <= 0; ``expected_counts`` and ``cramer_rao_std`` gave zeros, inf or NaN for it."""
    inv = MLInversion(PARAMS, max_lux=MAX_LUX, grid_size=16)
    for bad in (0.0, -0.5, float("inf"), float("nan")):
        for call in (lambda w: inv.expected_counts(w), lambda w: inv.cramer_rao_std(1.0, w),
                     lambda w: inv.lux(np.ones((2, 4, 4)), w)):
            with pytest.raises(ev.ParameterError, match="window_s must be finite and > 0 seconds"):
                call(bad)


def test_save_pairs_npz_refuses_counts_uint16_would_wrap(tmp_path):
    """Counts of a dataset that is not a PairList (which checks them) were cast to uint16 unchecked: 70000 was
    saved as 4464, -1 as 65535."""
    class Pairs:
        def __init__(self, counts):
            self.counts = counts

        def __len__(self):
            return 1

        def __getitem__(self, i):
            return {"counts": self.counts, "image": np.zeros((4, 4)), "window_s": 1.0}

    for bad in (70000, -1, 2.5, np.nan):
        counts = np.zeros((2, 4, 4))
        counts[0, 1, 1] = bad
        with pytest.raises(InputError, match="whole numbers in \\[0, 65535\\]"):
            save_pairs_npz(tmp_path / "p.npz", Pairs(counts))
        assert not (tmp_path / "p.npz").exists()
    counts = np.zeros((2, 4, 4), dtype=np.int64)
    counts[1, 2, 3] = 65535
    save_pairs_npz(tmp_path / "p.npz", Pairs(counts))
    with np.load(tmp_path / "p.npz") as saved:
        assert saved["counts"].dtype == np.uint16 and saved["counts"][0, 1, 2, 3] == 65535
    # PairList, which checked the range, took 2.5 as 2: the same one check now
    with pytest.raises(InputError, match="pair 0: counts must be whole numbers"):
        PairList([np.full((2, 4, 4), 2.5)], [np.zeros((4, 4))], window_s=1.0)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny model trained through the CLI on a .npz pairs file."""
    folder = tmp_path_factory.mktemp("cli")
    pairs = resampled(n=4, size=64, seed=3)
    save_pairs_npz(folder / "pairs.npz", pairs)
    model = folder / "model.pt"
    code = main(["-q", "train", str(folder / "pairs.npz"), "--out", str(model), "--epochs", "1",
                 "--steps-per-epoch", "2", "--batch-size", "2", "--crop", "16", "--base-channels", "8",
                 "--val-fraction", "0.25", "--no-plot"])
    assert code == 0 and model.is_file()
    return folder, model


def test_cli_reconstruct_writes_png(trained, tmp_path, capsys):
    from PIL import Image

    _, model = trained
    rng = np.random.default_rng(4)
    path = tmp_path / "events.h5"
    write_events_h5(path, random_events(rng, 41, 30, 4000, 2_500_000), 41, 30)
    out = tmp_path / "image.png"
    assert main(["reconstruct", str(path), "--model", str(model), "--out", str(out), "--window", "1"]) == 0
    with Image.open(out) as img:
        assert img.size == (20, 15)  # 41 x 30 sensor, 2x2 binning
    assert main(["-q", "reconstruct", str(path), "--model", str(model), "--out", str(tmp_path / "f.png"),
                 "--window", "1", "--step", "0.5", "--frames", "3"]) == 0
    assert sorted(p.name for p in tmp_path.glob("f_*.png")) == ["f_0000.png", "f_0001.png", "f_0002.png"]


@pytest.mark.parametrize("case", ["missing-model", "not-a-model", "other-binning", "not-events", "exists",
                                  "past-end"])
def test_cli_reconstruct_errors(trained, tmp_path, capsys, case):
    folder, model = trained
    events = tmp_path / "events.h5"
    write_events_h5(events, random_events(np.random.default_rng(1), 8, 8, 100, 1_500_000), 8, 8)
    out = tmp_path / "o.png"
    args = ["reconstruct", str(events), "--model", str(model), "--out", str(out), "--window", "1"]
    expect = {
        "missing-model": "model file not found",
        "not-a-model": "not an evnoise model checkpoint",
        "other-binning": "trained on 2x2-binned counts",
        "not-events": "not an HDF5 events file",
        "exists": "exists",
        "past-end": "runs past the end",
    }[case]
    if case == "missing-model":
        args[3] = str(tmp_path / "nope.pt")
    elif case == "not-a-model":
        args[3] = str(folder / "pairs.npz")
    elif case == "other-binning":
        args += ["--binning", "1"]
    elif case == "not-events":
        bad = tmp_path / "bad.h5"
        bad.write_text("hello")
        args[1] = str(bad)
    elif case == "exists":
        out.write_bytes(b"keep me")
    elif case == "past-end":
        args[-1] = "5"
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evnoise: error:") and expect in err[0]
    if case == "exists":
        assert out.read_bytes() == b"keep me"
    else:
        assert not out.exists()


def test_cli_train_errors(tmp_path, capsys):
    assert main(["train", str(tmp_path / "nothing"), "--out", str(tmp_path / "m.pt")]) == 2
    assert "dataset not found" in capsys.readouterr().err
    txt = tmp_path / "data.txt"
    txt.write_text("x")
    assert main(["train", str(txt), "--out", str(tmp_path / "m.pt")]) == 2
    assert "not a dataset" in capsys.readouterr().err


def test_reconstructor_predict_checks_binning(trained):
    _, model = trained
    rec = Reconstructor(model)
    img = rec.predict(np.random.default_rng(0).poisson(1, (2, 20, 24)), 1.0)
    assert img.shape == (10, 12) and 0 <= img.min() and img.max() <= 1
    with pytest.raises(ParameterError, match="binning"):
        rec.predict(np.zeros((2, 20, 24)), 1.0, binning=4)


def test_importing_evnoise_and_the_cli_does_not_import_torch():
    code = ("import sys, evnoise, evnoise.reconstruct, evnoise.cli; evnoise.cli.build_parser(); "
            "import evnoise.reconstruct.baselines, evnoise.reconstruct.data, evnoise.reconstruct.metrics; "
            "sys.exit('torch' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_evaluate_table_has_every_method(trained, tmp_path):
    from evnoise.reconstruct.evaluate import comparison_figure, evaluate, format_table

    _, model = trained
    src = resampled(n=2, size=64, seed=8)
    items = [src[i] for i in range(2)]
    test = PairList([it["counts"] for it in items], [it["image"] for it in items], window_s=1.0,
                    sources=["a", "b"], max_lux=MAX_LUX, params=PARAMS)
    result = evaluate(test, model, lpips=False, smoothing_sigma=(0.7, 2.0), keep_predictions=1)
    assert set(result["metrics"]) == {"unet", "ml-inversion@0.7", "ml-inversion@2", "counts-affine", "counts-minmax"}
    for values in result["metrics"].values():
        assert np.isfinite(values["psnr"][0]) and -1 <= values["ssim"][0] <= 1 and values["lpips"] == (None, None)
    table = format_table(result)
    assert table.count("\n| ") == 5 and "sigma 2" in table and "n/a" in table
    pytest.importorskip("matplotlib")
    assert comparison_figure(result["examples"], tmp_path / "fig.png").is_file()
    with pytest.raises(ParameterError, match="max_lux"):
        evaluate(PairList([items[0]["counts"]], [items[0]["image"]], window_s=1.0), model, lpips=False)


def test_evaluate_warns_of_pairs_shorter_than_the_models_windows_and_records_each_window(trained, caplog):
    """evaluate said nothing when pairs' windows were shorter than every window the model was trained on
    (reconstruct warns), and its per-pair rows had no window."""
    from evnoise.reconstruct.evaluate import evaluate
    from evnoise.reconstruct.infer import Reconstructor, trained_windows

    _, model = trained
    shortest = trained_windows(Reconstructor(model).spec)[0]
    src = resampled(n=3, size=64, seed=8)
    items = [src[i] for i in range(3)]
    windows = [shortest / 10, shortest, shortest / 10]
    test = PairList([it["counts"] for it in items], [it["image"] for it in items], window_s=windows)
    with caplog.at_level(logging.WARNING, logger="evnoise"):
        result = evaluate(test, model, methods=("unet",), lpips=False)
    assert [row["window_s"] for row in result["per_item"]] == windows
    warned = [r.getMessage() for r in caplog.records if "shorter than every window" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith(f"2 of the 3 pairs have windows ({shortest / 10:g} s)")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="evnoise"):
        evaluate(PairList([items[1]["counts"]], [items[1]["image"]], window_s=shortest), model, methods=("unet",),
                 lpips=False)
    assert not [r for r in caplog.records if "shorter than every window" in r.getMessage()]


@pytest.mark.parametrize("distribution", ["exact", "poisson"])
def test_resampled_pairs_draw_hot_pixels_and_the_leak_spread(distribution):
    """A model whose pixels differ (hot pixels, leak spread): the counts' mean is the population's, from
    ``expected_rate(..., mismatch="mean")``, not the nominal pixel's (which has no hot pixel: 2x lower here)."""
    params = dataclasses.replace(PARAMS, leak_on_hz=0.5, leak_sigma=0.8, hot_pixel_fraction=0.1,
                                 hot_pixel_rate_hz=20.0)
    lux = np.full((64, 64), 0.05)
    ds = ResampledPairs([lux], params, window_s=0.5, max_lux=MAX_LUX, binning=1, distribution=distribution)
    counts = np.stack([ds.sample(0, item_seed(2, k), None)["counts"] for k in range(6)]).astype(float)
    population = ev.expected_rate(np.array([0.05]), params, mismatch="mean")[:, 0] * 0.5
    nominal = ev.expected_rate(np.array([0.05]), params)[:, 0] * 0.5
    on = counts[:, 0].ravel()
    # the hot pixels make the counts over-dispersed: the standard error from the sample's own variance
    se = on.std() / math.sqrt(on.size)
    assert population[0] - nominal[0] > 10 * se  # the test can tell the two apart
    assert abs(on.mean() - population[0]) < 4 * se


def test_resampled_poisson_counts_include_the_dead_time():
    """Poisson counts about the expected count of the event process, dead time included."""
    params = dataclasses.replace(PARAMS, eps_pos=0.3, eps_neg=0.3, refractory_s=0.05)  # ~3 events/s: 30 % dead
    lux = np.full((64, 64), 15.0)
    ds = ResampledPairs([lux], params, window_s=0.8, max_lux=MAX_LUX, binning=1, distribution="poisson")
    counts = np.stack([ds.sample(0, item_seed(3, k), None)["counts"] for k in range(4)]).astype(float)
    mean = ev.expected_rate(np.array([15.0]), params)[:, 0] * 0.8
    no_dead_time = ev.expected_rate(np.array([15.0]), dataclasses.replace(params, refractory_s=0.0))[:, 0] * 0.8
    for pol in (0, 1):
        sample = counts[:, pol].ravel()
        se = math.sqrt(mean[pol] / sample.size)
        assert abs(no_dead_time[pol] - mean[pol]) > 10 * se  # the test can tell the two apart
        assert abs(sample.mean() - mean[pol]) < 4 * se


def test_resampled_poisson_pairs_with_memory_and_per_pixel_maps_are_refused_up_front():
    params = dataclasses.replace(PARAMS, reset_memory=0.5, eps_sigma=0.03)
    with pytest.raises(ParameterError, match="distribution='exact'"):
        ResampledPairs([np.full((8, 8), 2.0)], params, window_s=0.5, max_lux=MAX_LUX, distribution="poisson")


def test_ml_inversion_white_level_and_cramer_rao_at_the_light_limit():
    """The model takes at most 1e9 lux: a white level above it was refused by the rates as "lux contains
    illuminance above ..." (not naming max_lux), and the Cramér-Rao bound at 1e9 lux evaluated at 1e9 + h."""
    with pytest.raises(ParameterError, match="max_lux must be finite, > 0 and at most 1e.09 lux"):
        MLInversion(PARAMS, max_lux=2e9)
    inv = MLInversion(PARAMS, max_lux=MAX_LUX, grid_size=16)
    with pytest.raises(ParameterError, match="max_lux must be finite, > 0 and at most 1e.09 lux"):
        inv.lux(np.zeros((2, 4, 4)), 1.0, max_lux=2e9)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sigma = inv.cramer_rao_std([1.0, 1e9], 1.0)  # a one-sided difference at the limit
    assert sigma.shape == (2,) and np.isfinite(sigma[0]) and sigma[0] > 0 and sigma[1] > 0  # inf: no information
