"""calibration/ is three packages (rates, quiet, scripts) plus shared modules: no import cycle (function-level
and TYPE_CHECKING imports included), no private name imported across modules, scripts never imported by the
library (issue 30 item 6)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CALIBRATION = ROOT / "calibration"
PACKAGE = "evnoise.calibration"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(CALIBRATION).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join([PACKAGE, *parts])


def _imports(path: Path):
    """``(module, names)`` for every import statement in ``path``, at any depth."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, ()
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            yield module, tuple(a.name for a in node.names)


def _graph():
    files = sorted(CALIBRATION.rglob("*.py"))
    modules = {_module_name(p): p for p in files}
    edges = {}
    for name, path in modules.items():
        out = set()
        for module, names in _imports(path):
            targets = [module] + [f"{module}.{n}" for n in names]
            for target in targets:
                parts = target.split(".")
                for i in range(3, len(parts) + 1):  # a module and the packages above it
                    candidate = ".".join(parts[:i])
                    if candidate in modules and candidate != name:
                        out.add(candidate)
        edges[name] = out
    return modules, edges


def test_no_import_cycle_in_calibration():
    _, edges = _graph()
    state, stack, cycles = {}, [], []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(edges[node]):
            if state.get(nxt) == "open":
                cycles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = "done"

    for node in sorted(edges):
        if node not in state:
            visit(node)
    assert not cycles, cycles


def test_no_private_name_crosses_a_module_boundary():
    found = []
    for path in sorted(CALIBRATION.rglob("*.py")):
        for module, names in _imports(path):
            found += [f"{path.relative_to(ROOT)}: {n} from {module}" for n in names
                      if n.startswith("_") and not (n.startswith("__") and n.endswith("__"))]
    assert not found, found


def test_the_library_never_imports_the_scripts():
    modules, edges = _graph()
    scripts = f"{PACKAGE}.scripts"
    wrong = [(a, b) for a, out in edges.items() for b in out
             if b.startswith(scripts) and not a.startswith(scripts)]
    assert not wrong, wrong


def test_the_layout_and_the_public_names():
    import evnoise.calibration as cal

    for sub in ("rates", "quiet", "scripts"):
        assert (CALIBRATION / sub / "__init__.py").is_file()
    assert not [p.name for p in CALIBRATION.glob("*.py")
                if p.name not in ("__init__.py", "_progress.py", "measurements.py", "preset.py")]
    for name in cal.__all__:
        assert getattr(cal, name) is not None, name
    from evnoise.calibration.quiet import fit_quiet, quiet_window
    from evnoise.calibration.rates import calibrate

    assert (cal.fit_quiet, cal.quiet_window, cal.calibrate) == (fit_quiet, quiet_window, calibrate)


def test_pyproject_installs_every_calibration_package():
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    packages = {_module_name(p.parent / "__init__.py") for p in CALIBRATION.rglob("__init__.py")}
    assert packages <= set(project["packages"]), packages - set(project["packages"])


def test_importing_calibration_is_cheap():
    code = ("import sys, evnoise.calibration, evnoise.calibration.quiet, evnoise.calibration.rates; "
            "print(sorted(m for m in ('scipy', 'numba', 'matplotlib', 'evnoise.calibration.rates.fit', "
            "'evnoise.calibration.quiet.fit') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


@pytest.mark.parametrize("name", ["refit_evk3", "refit_evk4", "fit_dvs128", "dispersion_evk3", "iebcs_ratios",
                                  "slow_csv", "quiet_timing"])
def test_scripts_run_as_modules(name):
    out = subprocess.run([sys.executable, "-m", f"evnoise.calibration.scripts.{name}", "--help"],
                         capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0 and "usage" in out.stdout, out.stderr
