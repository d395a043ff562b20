"""Issue 13: each concept has one home; the old names are that one function, and it is right."""

import numpy as np
import pytest

import evnoise as ev
from evnoise import radiometry
from evnoise.generators import pairs
from evnoise.reconstruct import imaging


def test_srgb_names_are_one_function():
    assert imaging.srgb_encode is radiometry.srgb_encode
    assert pairs.linear_to_srgb is radiometry.srgb_encode
    assert imaging.srgb_decode(np.array([0.5])) == radiometry.srgb_to_linear(np.array([0.5]))


def test_srgb_encode_matches_colour_science():
    colour = pytest.importorskip("colour")
    v = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(radiometry.srgb_encode(v), colour.models.eotf_inverse_sRGB(v), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(imaging.srgb_decode(radiometry.srgb_encode(v)), v, atol=1e-12)
    np.testing.assert_array_equal(imaging.srgb_decode(np.array([-0.5, 1.5])), [0.0, 1.0])  # clipped


def test_block_sum_is_one_function():
    assert imaging.block_sum is radiometry.block_sum
    assert pairs.bin_sum is radiometry.block_sum
    a = np.arange(2 * 5 * 7).reshape(2, 5, 7)
    got = radiometry.block_sum(a, 2)
    want = np.array([[[a[c, 2 * i:2 * i + 2, 2 * j:2 * j + 2].sum() for j in range(3)] for i in range(2)]
                     for c in range(2)])
    np.testing.assert_array_equal(got, want)


def test_kernel_key_is_what_the_simulator_draws():
    """One key derivation (``evnoise._run.stream_key``): a run set-up draws it after its maps, and the
    dataset's seed-only path is its ``seed=`` branch; no other module derives a key."""
    from evnoise import _checks
    from evnoise._kernels import rng as kernel_rng
    from evnoise._run import run_setup, stream_key

    params = ev.NoiseParams(eps_pos=0.3, eps_neg=0.3, bias_pr=1.0, trial_rate_hz=1e3, photons_per_lux=1.0)
    want = np.random.default_rng(7).integers(0, 2**64, size=4, dtype=np.uint64, endpoint=False)
    np.testing.assert_array_equal(stream_key(np.random.default_rng(7)), want)
    np.testing.assert_array_equal(stream_key(7), want)
    np.testing.assert_array_equal(run_setup((3, 4), params, 7).key, want)  # no map drawn: the key comes first
    # with threshold mismatch the key is drawn after the thresholds, from the same generator
    gen = np.random.default_rng(7)
    ev.draw_thresholds((3, 4), params.replace(eps_sigma=0.05), gen)
    np.testing.assert_array_equal(run_setup((3, 4), params.replace(eps_sigma=0.05), 7).key, stream_key(gen))
    from_seed = np.random.SeedSequence(7).generate_state(4, np.uint64)
    np.testing.assert_array_equal(stream_key(seed=7), from_seed)
    np.testing.assert_array_equal(run_setup((3, 4), params, key_seed=7).key, from_seed)
    assert stream_key(seed=7).dtype == np.uint64
    for module in (_checks, kernel_rng):
        assert not {"kernel_key", "kernel_key_from_seed", "key_from"} & set(vars(module))


def test_polarity_convention():
    from evnoise.events import OFF, OFF_INDEX, ON, ON_INDEX, count_events, make_events, polarity_index

    assert (ON, OFF, ON_INDEX, OFF_INDEX) == (1, 0, 0, 1)
    np.testing.assert_array_equal(polarity_index(np.array([ON, OFF, ON], dtype=np.uint8)), [0, 1, 0])
    ev = make_events(np.array([0, 1, 2]), np.array([0, 1, 1]), np.array([0, 0, 0]), np.array([ON, OFF, OFF]))
    c = count_events(ev, (1, 2), 0, 10)
    assert c[ON_INDEX, 0, 0] == 1 and c[OFF_INDEX, 0, 1] == 2 and c.sum() == 3


def _private_imports_across_modules():
    """``(file, module, name)`` of every private name one evnoise module imports from another."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    found = []
    for path in sorted([*root.joinpath("evnoise").rglob("*.py"), *root.joinpath("generators").rglob("*.py"),
                       *root.joinpath("calibration").rglob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("evnoise")):
                found += [(path.relative_to(root).as_posix(), node.module or "", a.name) for a in node.names
                          if a.name.startswith("_") and not a.name.startswith("__")]
    return found


def test_recording_and_check_helpers_are_imported_by_public_names():
    watched = {"_check_shape", "_h5_info", "_h5_blocks", "_recording_start_us", "_as_filter", "_check_float",
               "_check_int", "_check_fps", "_bin_any", "_open_h5", "_index_at"}
    crossing = [imp for imp in _private_imports_across_modules() if imp[2] in watched]
    # evnoise/simulate.py still names events.check_shape by its former alias
    assert not crossing, crossing


def test_recording_helpers_have_one_home():
    from evnoise import _checks, _recordings, motion, separation
    from evnoise.reconstruct import video

    assert separation.recording_info is _recordings.recording_info
    assert motion.check_float is _checks.check_float and video.check_float is _checks.check_float
    assert video.bin_mask is motion.bin_mask
    mask = np.zeros((5, 7), dtype=bool)
    mask[3, 4] = True
    np.testing.assert_array_equal(motion.bin_mask(mask, 2), [[False, False, False], [False, False, True]])


def test_exact_log_probability_over_arrays_is_one_kernel():
    """The serial kernel (calibration's small arrays) is the parallel one's body: same bits, extremes included."""
    from evnoise._kernels import mismatch as mismatch_kernels
    from evnoise._kernels.poisson import log_event_probability_exact_array, log_event_probability_exact_serial

    assert not hasattr(mismatch_kernels, "log_probability_serial")
    g = np.random.default_rng(13)
    n = 3000
    extremes = np.array([[0.0, 1e-300, 1e-12, 1.0, 1e6, 3e6], [0.0, 1e-12, 1e-300, 5.0, 100.0, 1e-4]])
    lam = np.concatenate([10.0 ** g.uniform(-8, 6.5, n), np.repeat(extremes[0], 6)])
    c = np.concatenate([np.expm1(10.0 ** g.uniform(-5, 1.0, n)), np.tile(extremes[1], 6)])
    b = np.concatenate([10.0 ** g.uniform(-6, 4, n), np.tile([0.0, 1e-6, 1e4], 12)])
    serial, parallel = np.empty(lam.size), np.empty(lam.size)
    log_event_probability_exact_serial(lam, c, b, serial)
    log_event_probability_exact_array(lam, c, b, parallel)
    np.testing.assert_array_equal(serial.view(np.int64), parallel.view(np.int64))
    assert np.count_nonzero(np.isfinite(serial)) > n - 10


def test_generators_and_calibration_are_imported_under_one_name():
    """``generators/`` and ``calibration/`` are ``evnoise.generators`` and ``evnoise.calibration``. Imported as
    top-level ``generators`` too (the repository root is on sys.path in tests), a module has two names, and
    Numba's cache of its kernels (keyed by the file) then records the one a later process cannot import."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    pattern = re.compile(r"^\s*(from|import)\s+(generators|calibration)\b", re.M)
    offenders = [f"{path.relative_to(root)}: {m.group(0).strip()}"
                 for folder in ("tests", "benchmarks", "evnoise", "generators", "calibration")
                 for path in sorted((root / folder).rglob("*.py"))
                 for m in pattern.finditer(path.read_text(encoding="utf-8"))]
    assert not offenders, offenders


# --- issue 30: the package's shape -------------------------------------------------------------------------

_PACKAGE_ROOTS = {"evnoise": "evnoise", "evnoise.generators": "generators", "evnoise.calibration": "calibration"}


def _library_modules():
    """``{module name: path}`` of every library module (the three folders installed as ``evnoise``)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    modules = {}
    for package, folder in _PACKAGE_ROOTS.items():
        for path in root.joinpath(folder).rglob("*.py"):
            parts = list(path.relative_to(root / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join([package, *parts])] = path
    return modules


def _import_edges():
    """``{module: {imported library modules}}`` over every import statement, module level or inside a function."""
    import ast

    modules = _library_modules()

    def owner(name):
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name

    edges = {}
    for module, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                targets.update(owner(a.name) for a in node.names if a.name.startswith("evnoise"))
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
                    base = base[:len(base) - node.level + 1]
                    name = ".".join(base + ([node.module] if node.module else []))
                else:
                    name = node.module or ""
                if not name.startswith("evnoise"):
                    continue
                for alias in node.names:
                    sub = f"{name}.{alias.name}"
                    targets.add(owner(sub if sub in modules else name))
        edges[module] = targets - {module, ""}
    return edges


def _cycles(edges):
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    counter = 0
    for start in edges:
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_cycle_finder_finds_a_cycle():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(edges) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_anywhere():
    """Issue 30: no cycle between library modules, counting imports inside functions too."""
    edges = _import_edges()
    assert "evnoise.simulate" in edges and "evnoise.calibration" in edges  # the walk saw the tree
    assert not _cycles(edges), _cycles(edges)


def test_no_private_name_crosses_a_module_boundary():
    """Issue 30: a ``_private`` function, class or constant is used only in its own module (private
    *modules* such as ``evnoise._checks`` are the package's internals and may be imported)."""
    modules = _library_modules()
    # a private *module* imported by name (``from . import _checks``) is allowed: the name is one of the modules
    names = {m.rpartition(".")[2] for m in modules}
    crossing = [imp for imp in _private_imports_across_modules() if imp[2] not in names]
    assert not crossing, crossing


def test_every_library_package_is_installed():
    """A package folder missing from pyproject's list is left out of the wheel (an editable install hides it)."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    listed = set(tomllib.loads(root.joinpath("pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
                 ["packages"])
    packages = {name for name, path in _library_modules().items() if path.name == "__init__.py"}
    assert "evnoise.terms" in packages and "evnoise.calibration.rates" in packages
    assert packages <= listed, sorted(packages - listed)


def test_the_readme_layout_names_every_package():
    """The README's "Layout" block names each subpackage of the tree, and names none that is gone."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    text = root.joinpath("README.md").read_text(encoding="utf-8")
    layout = text.split("## Layout", 1)[1].split("```", 2)[1]
    packages = {name.rpartition(".")[2] for name, path in _library_modules().items()
                if path.name == "__init__.py" and name.count(".") >= 1}
    missing = sorted(p for p in packages if not re.search(rf"(?<![\w.]){re.escape(p)}/", layout))
    assert not missing, f"README Layout does not name {missing}"
    named = set(re.findall(r"(?<![\w.])([a-z_]+)/", layout))
    top = {"evnoise", "generators", "calibration", "tests", "benchmarks", "docs"}
    gone = sorted(n for n in named - top - packages)
    assert not gone, f"README Layout names folders that are not packages: {gone}"


def test_the_core_does_not_import_the_layers_above_it():
    """The model, simulator, radiometry, readers and io never import the reconstructor, the CLI, the plugins,
    the generators or calibration (they build on the core, not the other way round)."""
    upper = ("evnoise.reconstruct", "evnoise.cli", "evnoise.plugins", "evnoise.examples", "evnoise.generators",
             "evnoise.calibration", "evnoise.data")
    edges = _import_edges()
    core = [m for m in edges if not m.startswith(upper) and m not in ("evnoise", "evnoise.__main__")]
    assert "evnoise._cache" in core and "evnoise.simulate" in core
    upward = {m: sorted(t for t in edges[m] if t.startswith(upper)) for m in core}
    assert not {m: t for m, t in upward.items() if t}, upward
