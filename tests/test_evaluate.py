"""``evnoise evaluate``: the comparison table from the command line (tiny dataset, tiny model)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import evnoise as ev

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from evnoise.cli import main  # noqa: E402
from evnoise.reconstruct.checkpoint import InputSpec, save_checkpoint  # noqa: E402
from evnoise.reconstruct.data import PairList, ResampledPairs, save_pairs_npz  # noqa: E402
from evnoise.reconstruct.evaluate import evaluate  # noqa: E402
from evnoise.reconstruct.imaging import srgb_decode  # noqa: E402
from evnoise.reconstruct.unet import UNet  # noqa: E402

PARAMS = ev.NoiseParams(eps_pos=0.904, eps_neg=1.0235, bias_pr=1.7023, trial_rate_hz=21.9882, photons_per_lux=1.005,
                        dark_lux=0.193)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    folder = tmp_path_factory.mktemp("evaluate")
    rng = np.random.default_rng(0)
    lux = [srgb_decode(rng.uniform(0, 1, (32, 32))) * 18 for _ in range(3)]
    ds = ResampledPairs(lux, PARAMS, window_s=1.0, max_lux=18.0, sources=["a", "b", "c"], seed=2)
    items = [ds[i] for i in range(3)]
    pairs = PairList([it["counts"] for it in items], [it["image"] for it in items], window_s=1.0,
                     sources=["a", "b", "c"], max_lux=18.0, params=PARAMS)
    save_pairs_npz(folder / "pairs.npz", pairs)
    torch.manual_seed(0)
    net = UNet(base_channels=8, channel_mults=(1, 2), groups=4)
    model = save_checkpoint(folder / "m.pt", model_config=net.config, state_dict=net.state_dict(),
                            input_spec=InputSpec(rate_scale_hz=2.0, window_s=1.0, max_lux=18.0))
    return folder, model, pairs


def test_cli_evaluate_writes_table_json_and_figure_matching_the_library(setup, tmp_path, capsys):
    folder, model, pairs = setup
    out, js, fig = tmp_path / "t.md", tmp_path / "r.json", tmp_path / "f.png"
    assert main(["evaluate", str(folder / "pairs.npz"), "--model", str(model), "--no-lpips", "--ml-sigma", "0.7",
                 "--ml-sigma", "2", "--out", str(out), "--json", str(js), "--figure", str(fig)]) == 0
    printed = capsys.readouterr()
    table = out.read_text()
    assert table.strip() in printed.out
    assert "evaluating" in printed.err  # the progress bar
    assert table.count("\n| ") == 6  # header rule + U-Net, two ML rows, two count-image rows
    doc = json.loads(js.read_text())
    assert doc["n"] == 3 and set(doc["metrics"]) == {"unet", "ml-inversion@0.7", "ml-inversion@2", "counts-affine",
                                                      "counts-minmax"}
    assert isinstance(doc["metrics"]["unet"]["psnr"][0], float)
    # the CLI's numbers are the library's
    ref = evaluate(pairs, model, lpips=False, smoothing_sigma=(0.7, 2.0))
    for m, vals in ref["metrics"].items():
        assert doc["metrics"][m]["psnr"][0] == pytest.approx(vals["psnr"][0], rel=1e-12)
    assert fig.read_bytes()[:4] == b"\x89PNG"
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.parametrize("case", ["missing-dataset", "bad-suffix", "exists", "no-folder", "bad-model"])
def test_cli_evaluate_errors_are_one_line_and_leave_no_file(setup, tmp_path, capsys, case):
    folder, model, _ = setup
    out = tmp_path / "t.md"
    args = ["evaluate", str(folder / "pairs.npz"), "--model", str(model), "--no-lpips", "--out", str(out)]
    expect = {"missing-dataset": "dataset not found", "bad-suffix": "must be a .md file", "exists": "exists",
              "no-folder": "does not exist", "bad-model": "not an evnoise model checkpoint"}[case]
    if case == "missing-dataset":
        args[1] = str(tmp_path / "nothing")
    elif case == "bad-suffix":
        args[-1] = str(tmp_path / "t.txt")
    elif case == "exists":
        out.write_text("keep")
    elif case == "no-folder":
        args[-1] = str(tmp_path / "no" / "t.md")
    elif case == "bad-model":
        junk = tmp_path / "junk.pt"
        junk.write_bytes(b"junk")
        args[3] = str(junk)
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evnoise: error:") and expect in err[0], err
    if case == "exists":
        assert out.read_text() == "keep"
    else:
        assert not out.exists()


def test_cli_evaluate_defaults_to_the_shipped_model(setup, capsys):
    folder, _, _ = setup
    assert main(["-q", "evaluate", str(folder / "pairs.npz"), "--no-lpips", "--max-items", "1"]) == 0
    assert "U-Net" in capsys.readouterr().out
