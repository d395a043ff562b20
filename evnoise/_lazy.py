"""Lazy attributes for packages (PEP 562): names load their module on first access.

Keeps ``import evnoise`` (and its subpackages) cheap: Numba, SciPy, torch and colour load only
when a name that needs them is used.
"""

from __future__ import annotations

import importlib


def lazy_attributes(package: str, names: dict[str, str], submodules=()):
    """``(__getattr__, __dir__)`` for ``package`` where ``names`` maps attribute -> module.

    A module name starting with ``.`` is relative to ``package``. ``submodules`` names submodules
    of ``package`` that are attributes too (``evnoise.io`` without ``import evnoise.io``), imported
    on first access.
    """
    submodules = frozenset(submodules)

    def __getattr__(name):
        if name in submodules:
            return importlib.import_module(f"{package}.{name}")  # the import sets the attribute
        module = names.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        target = importlib.import_module(package + module if module.startswith(".") else module)
        value = getattr(target, name)
        setattr(importlib.import_module(package), name, value)
        return value

    def __dir__():
        return sorted(set(vars(importlib.import_module(package))) | set(names) | submodules)

    return __getattr__, __dir__
