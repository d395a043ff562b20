"""The API reference's docstrings, read by the parser that renders them (numpydoc, as the docs site does).

Every public name the reference documents (``docs/api_lists.py``: ``evnoise`` and its subpackages' and plugins'
``__all__``, classes with their public methods, as the class template's ``:members:`` renders them) has a
docstring whose Parameters section names exactly its parameters, in the signature's order, each with a type and
a description; a generator says what it yields. A paragraph left under a Parameters section renders as a
parameter named after its first words (numpydoc reads every unindented line there as one); a parameter renamed in
the code and not in its docstring is documented under its old name.
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
from pathlib import Path

import pytest
from numpydoc.validate import validate

ROOT = Path(__file__).resolve().parents[1]

#: numpydoc's checks held here: no docstring (GL08); parameters missing (PR01), unknown (PR02), out of order
#: (PR03), without a type (PR04) or description (PR07), malformed "name : type" (PR10); a generator without
#: Yields (YD01); a Returns entry without a description (RT03)
CHECKS = {"GL08", "PR01", "PR02", "PR03", "PR04", "PR07", "PR10", "YD01", "RT03"}
#: a class's fields are its constructor's parameters; result records that users receive rather than build
#: (their docstrings describe the fields under Attributes) are held to the checks of a malformed section only
CLASS_CHECKS = {"GL08", "PR02", "PR10"}


def _api_lists():
    spec = importlib.util.spec_from_file_location("api_lists", ROOT / "docs" / "api_lists.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _documented() -> list[tuple[str, object]]:
    lists = _api_lists()
    modules = ["evnoise"] + [m for _, m, *_ in lists.SUBPACKAGES] + [m for m, *_ in lists.PLUGINS]
    out, seen = [], set()
    for modname in modules:
        if modname == "evnoise.reconstruct" and importlib.util.find_spec("torch") is None:
            continue  # the reconstructor needs torch (the test extras install it; its own tests skip without)
        module = importlib.import_module(modname)
        for name in lists._public(module):
            obj = getattr(module, name)
            if not (inspect.isclass(obj) or inspect.isfunction(obj)) or id(obj) in seen:
                continue
            seen.add(id(obj))
            out.append((f"{modname}.{name}", obj))
            if inspect.isclass(obj):
                for member, value in vars(obj).items():
                    if member.startswith("_") or not (
                            inspect.isfunction(value) or isinstance(value, (classmethod, staticmethod))):
                        continue
                    out.append((f"{modname}.{name}.{member}", getattr(obj, member)))
    return out


DOCUMENTED = _documented()


def test_the_reference_is_found():
    names = {qual for qual, _ in DOCUMENTED}
    assert {"evnoise.simulate_events", "evnoise.NoiseParams", "evnoise.calibration.fit_quiet",
            "evnoise.generators.make_dataset", "evnoise.plugins.tonic.PhotonNoise"} <= names
    assert len(DOCUMENTED) > 100


@pytest.mark.parametrize(("qual", "obj"), DOCUMENTED, ids=[qual for qual, _ in DOCUMENTED])
def test_docstring_parses_as_rendered(qual, obj):
    checks = CLASS_CHECKS if inspect.isclass(obj) else CHECKS
    problems = [f"{code} {text}" for code, text in validate(qual)["errors"] if code in checks]
    assert not problems, "\n".join(problems)
