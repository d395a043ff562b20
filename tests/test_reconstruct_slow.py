"""Slow reconstructor checks (``pytest -m slow``): a real training run and full-size inference.

The training run uses scikit-image's bundled photos (read from the installed package, not
shipped with evnoise), held out by source image, with counts re-drawn on the fly.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

import evnoise as ev

torch = pytest.importorskip("torch")
pytest.importorskip("skimage")

from evnoise.reconstruct.data import PairList, ResampledPairs, item_seed, photos_to_lux, skimage_photos  # noqa: E402
from evnoise.reconstruct.evaluate import evaluate  # noqa: E402
from evnoise.reconstruct.train import DEFAULT_MODEL, TrainConfig, train  # noqa: E402
from evnoise.reconstruct.unet import UNet  # noqa: E402

pytestmark = pytest.mark.slow
MAX_LUX = 20.0
TRAIN = ["astronaut", "brick", "camera", "chelsea", "coins", "gravel", "moon", "page", "rocket", "text", "grass"]
VAL = ["cell"]
TEST = ["coffee", "retina"]


def test_unet_beats_the_model_based_baseline(tmp_path):
    torch.set_num_threads(1)
    params = ev.load_preset("evk3-hd")
    lux = photos_to_lux(skimage_photos(TRAIN + VAL + TEST), MAX_LUX)

    def pairs(names, seed):
        return ResampledPairs([lux[k] for k in names], params, window_s=1.0, max_lux=MAX_LUX, sources=names, seed=seed)

    test_src = pairs(TEST, 3)
    items = [test_src.sample(i, item_seed(9, i), 128) for i in range(len(TEST))]
    test = PairList([it["counts"] for it in items], [it["image"] for it in items], window_s=1.0, sources=TEST,
                    max_lux=MAX_LUX, params=params)
    cfg = TrainConfig(epochs=12, steps_per_epoch=25, batch_size=12, crop=64, seed=1, patience=None)
    result = train(pairs(TRAIN, 1), tmp_path / "m.pt", val_data=pairs(VAL, 2), config=cfg, progress=False, plot=False)
    assert result["history"]["val_loss"][-1] < result["history"]["val_loss"][0]
    table = evaluate(test, tmp_path / "m.pt", lpips=False, methods=("unet", "ml-inversion", "counts-minmax"))
    m = table["metrics"]
    assert m["unet"]["psnr"][0] > m["ml-inversion"]["psnr"][0] + 1.0
    assert m["unet"]["ssim"][0] > m["ml-inversion"]["ssim"][0]
    assert m["ml-inversion"]["psnr"][0] > m["counts-minmax"]["psnr"][0]


def test_inference_on_a_640x360_input_runs():
    """Runs the default-size U-Net on 640 x 360 (binned) counts; prints the time (not asserted)."""
    torch.manual_seed(0)
    net = UNet(**DEFAULT_MODEL).eval().to(memory_format=torch.channels_last)
    x = torch.rand(1, 2, 360, 640).contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        net(x)
        t0 = time.perf_counter()
        y = net(x)
        dt = time.perf_counter() - t0
    assert y.shape == (1, 1, 360, 640) and np.isfinite(y.numpy()).all()
    print(f"640x360 inference: {1000 * dt:.0f} ms with {torch.get_num_threads()} threads")
