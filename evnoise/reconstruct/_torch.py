"""Lazy access to PyTorch, an optional dependency (``pip install evnoise[train]``)."""

from __future__ import annotations

from ..errors import EvnoiseError


class MissingDependencyError(EvnoiseError, ImportError):
    """An optional dependency of the reconstructor is not installed."""


def require_torch():
    """Import and return :mod:`torch`, or raise a one-line error that says how to install it."""
    try:
        import torch
    except ImportError:
        raise MissingDependencyError(
            "the reconstructor needs PyTorch: pip install 'evnoise[train]'"
        ) from None
    return torch
