"""Every ``python -m evnoise...`` a user reads in the docs runs a module that exists.

docs/presets.md sent users to ``python -m evnoise.calibration.refit_evk3`` (and three more) after the scripts had
moved to ``evnoise.calibration.scripts``: "No module named evnoise.calibration.refit_evk3".
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: what users read: the README, the docs, the calibration notes, the package's own docstrings and help texts
SOURCES = [ROOT / "README.md", ROOT / "calibration" / "README.md",
           *sorted(p for p in (ROOT / "docs").rglob("*") if p.suffix in (".md", ".rst") and "_build" not in p.parts),
           *sorted((ROOT / "evnoise").rglob("*.py"))]
COMMAND = re.compile(r"python3? -m (evnoise(?:\.[A-Za-z_][A-Za-z0-9_]*)*)(?=[\s`'\"),;:]|\.?$)", re.M)


def _named_modules():
    found = {}
    for path in SOURCES:
        for match in COMMAND.finditer(path.read_text(encoding="utf-8")):
            found.setdefault(match.group(1), path.relative_to(ROOT).as_posix())
    return sorted(found.items())


def test_the_docs_name_modules_to_run():
    names = dict(_named_modules())
    assert "evnoise.calibration.scripts.refit_evk3" in names and "evnoise.reconstruct.lpips" in names


@pytest.mark.parametrize("module, where", _named_modules())
def test_every_module_the_docs_run_exists(module, where):
    assert importlib.util.find_spec(module) is not None, f"{where} runs python -m {module}, which does not exist"


def test_each_calibration_script_describes_itself_in_a_whole_sentence():
    """A script's ``--help`` shows its docstring's first line: memory_fit's read "... (issue 32 §2): ``python -m"."""
    import ast

    scripts = sorted((ROOT / "calibration" / "scripts").glob("*.py"))
    assert len(scripts) >= 8
    for path in scripts:
        first = (ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or "").splitlines()[0]
        assert first.endswith((".", "?")), f"{path.name}: {first!r}"
