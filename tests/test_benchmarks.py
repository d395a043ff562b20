"""The benchmark report script runs end to end at its smoke size (about 45 s).

Only the report's structure is checked: timings are never asserted (shared, noisy machines),
and at ``--tiny`` size the numbers mean nothing.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "run.py"


@pytest.mark.long
def test_benchmark_report_tiny_run(tmp_path):
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        from run import KEEP_MARKER
    finally:
        sys.path.remove(str(SCRIPT.parent))
    # a report with sections written by other scripts below the marker: regenerating keeps them
    (tmp_path / "REPORT.md").write_text(f"# old\n\n## 1. stale\n\n{KEEP_MARKER}\n\n## Readers (kept)\nkept text\n")
    proc = subprocess.run([sys.executable, str(SCRIPT), "--tiny", "--out", str(tmp_path)], capture_output=True,
                          text=True, check=False)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    text = (tmp_path / "REPORT.md").read_text(encoding="utf-8")
    for heading in ("## 1. Closed forms", "## 2. Simulator tiers", "## 3. Scaling", "## 4. Against a naive reference",
                    "## 5. End to end into events.h5", "## 6. The paper's Gaussian form", "## make-dataset throughput",
                    "## Dynamic scenes"):
        assert heading in text, heading
    assert "Machine:" in text and "python benchmarks/run.py --tiny" in text
    assert "## 1. stale" not in text and text.count(KEEP_MARKER) == 1
    assert text.rstrip().endswith("## Readers (kept)\nkept text")
    for line in text.splitlines():
        if line.startswith("![") and "](" in line:
            name = line.split("](", 1)[1].rstrip(")")
            png = tmp_path / name
            assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name


@pytest.mark.long
def test_memory_benchmark_tiny_run(tmp_path):
    """benchmarks/bench_memory.py writes its section into a report (structure only, at smoke size)."""
    script = SCRIPT.parent / "bench_memory.py"
    report = tmp_path / "REPORT.md"
    report.write_text("# report\n\n## Other\nkept\n")
    proc = subprocess.run([sys.executable, str(script), "--tiny", "--out", str(report)], capture_output=True,
                          text=True, check=False)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    text = report.read_text(encoding="utf-8")
    assert "## Other\nkept" in text and "## Reset memory: cost and error (issue 32)" in text
    assert "| davis346 nominal, k = 0.3 |" in text and "Machine:" in text
    assert "| evk4, k = 0.3 (trial tier, starts without tables) |" in text
