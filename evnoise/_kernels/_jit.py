"""The one place that decides how Numba compiles evnoise's kernels.

Every kernel is compiled through :func:`kernel` so that options are uniform:
``cache=True`` (compiled code is reused across processes), ``nogil=True`` (kernels can
run in Python threads), ``error_model="numpy"`` (division by zero gives inf/nan instead of
raising, which is what the closed forms expect and is faster), and no ``fastmath``
(the numerics rely on IEEE semantics: inf, nan, exact rounding of log1p/expm1).
"""

from __future__ import annotations

import numba

_OPTIONS = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)


def kernel(func=None, *, parallel: bool = False, inline: bool = False):
    """Compile ``func`` with evnoise's standard Numba options (usable with or without arguments).

    ``inline=True`` inlines the function into its callers at Numba-IR level (for small helpers
    on hot paths that pass arrays around, where a call would cost reference counting).
    """

    def wrap(f):
        extra = {"inline": "always"} if inline else {}
        return numba.njit(parallel=parallel, **_OPTIONS, **extra)(f)

    return wrap(func) if func is not None else wrap
