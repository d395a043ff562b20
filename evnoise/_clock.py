"""Times on a recording's clock as text: every digit down to the microsecond, none beyond.

A camera's clock is often Unix time (1.6e9 s), where ``f"{t:g}"`` prints ``1.64324e+09`` and
hides the part that matters; ``seconds_text`` prints ``1643240000.05``. Used by every message and
title that names a time on a file's clock (``info``, ``reconstruct``, the quiet calibration).
"""

from __future__ import annotations

import math

__all__ = ["seconds_text"]


def seconds_text(value) -> str:
    """``value`` seconds with microsecond resolution and no trailing zeros: ``1643240000.05``, ``0.5``, ``12``."""
    value = float(value)
    if not math.isfinite(value):
        return str(value)
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text
