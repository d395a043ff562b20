"""The reconstruction benchmark runs end to end at its smoke size (``pytest -m slow``).

Only the report's structure is checked: no timing and no quality numbers are asserted (a
``--tiny`` run trains each network for a few steps, far too few to mean anything).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch")
pytest.importorskip("skimage")
pytest.importorskip("matplotlib")

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "reconstruction.py"

SECTIONS = (
    "## Setup",
    "## 1. Main table (paper Table 1 analogue)",
    "## 2. By how much the U-Net beats baseline (b)",
    "## 3. Integration window (paper Table S1 analogue)",
    "## 4. Polarity (paper Table 2 analogue)",
    "## 5. Threshold mismatch: an analogue of the synthetic-to-real gap",
    "## 6. Examples",
    "## 7. Speed",
    "## Reproduce",
)


@pytest.mark.slow
def test_reconstruction_benchmark_tiny_run_writes_the_report(tmp_path):
    from evnoise.reconstruct.lpips import weights_path

    if not weights_path().is_file():
        pytest.skip("LPIPS weights not installed (python -m evnoise.reconstruct.lpips install)")
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(SCRIPT), "--tiny", "--work", str(tmp_path / "work"), "--out", str(out)],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    text = (out / "RECONSTRUCTION.md").read_text(encoding="utf-8")
    for heading in SECTIONS:
        assert heading in text, heading
    for row in ("**U-Net (evnoise)**", "(b) ML inversion", "(a) count image, affine fit (**oracle**)",
                "(a) count image, min-max", "ON only", "OFF only", "nominal → mismatch", "mismatch → nominal"):
        assert row in text, row
    for window in ("0.1 s — U-Net", "0.25 s — U-Net", "0.5 s — U-Net", "1 s — U-Net", "2 s — U-Net"):
        assert window in text, window
    assert "640×360" in text and "python benchmarks/reconstruction.py --tiny" in text
    for name in ("reconstruction_examples.png", "reconstruction_windows.png", "reconstruction_training.png"):
        png = out / name
        assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
        assert f"]({name})" in text

    # a second run reuses every cached job result and rewrites the same report structure
    again = subprocess.run([sys.executable, str(SCRIPT), "--tiny", "--work", str(tmp_path / "work"), "--out",
                            str(out)], capture_output=True, text=True, check=False)
    assert again.returncode == 0, again.stderr[-4000:]
    assert "start    train:" not in again.stdout and "cached   train:nominal-w1" in again.stdout
    assert "## 7. Speed" in (out / "RECONSTRUCTION.md").read_text(encoding="utf-8")
