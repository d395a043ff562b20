"""One memory budget, checked before any allocation whose size comes from a file, a header or a parameter.

A size a stranger's file declares (a 65535 x 65535 sensor, 1e11 events) or an absurd parameter must
give one clear error *before* memory is asked for, never a MemoryError or a machine that swaps.
The budget is the memory available now (Linux ``MemAvailable``), or ``EVNOISE_MAX_MEMORY`` bytes
(a number, optionally with a k/M/G/T suffix, powers of 1024) when that is set.
"""

from __future__ import annotations

import os

from .errors import InputError, ParameterError

__all__ = ["available_memory", "memory_budget", "check_allocation", "human_bytes"]

_SUFFIX = {"": 1, "k": 1024, "m": 1024**2, "g": 1024**3, "t": 1024**4}


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux ``MemAvailable``), or None if unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def memory_budget() -> int | None:
    """The budget in bytes: ``EVNOISE_MAX_MEMORY`` if set, else the available memory (None: unknown)."""
    text = os.environ.get("EVNOISE_MAX_MEMORY", "").strip()
    if text:
        unit = text[-1].lower() if text[-1].isalpha() else ""
        number = text[:-1] if unit else text
        try:
            value = float(number) * _SUFFIX[unit]
        except (ValueError, KeyError):
            raise ParameterError(f"EVNOISE_MAX_MEMORY must be a number of bytes (e.g. 8G), got {text!r}") from None
        if not value > 0:
            raise ParameterError(f"EVNOISE_MAX_MEMORY must be positive, got {text!r}")
        return int(value)
    return available_memory()


def human_bytes(n: float) -> str:
    """``n`` bytes as a short decimal string (``1.2 GB``)."""
    for unit in ("bytes", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:,.0f} {unit}" if unit == "bytes" else f"{n:,.1f} {unit}"
        n /= 1000.0
    return f"{n:.3g} PB"  # pragma: no cover


def check_allocation(nbytes: float, what: str, *, hint: str = "", error: type = InputError) -> None:
    """Raise ``error`` when ``nbytes`` exceed the memory budget, before anything is allocated.

    ``what`` names the allocation and where its size came from (``"count maps of the 65535x65535 sensor
    the header declares"``); ``hint`` says what the user can do.
    """
    budget = memory_budget()
    if budget is not None and nbytes > budget:
        source = "EVNOISE_MAX_MEMORY" if os.environ.get("EVNOISE_MAX_MEMORY", "").strip() else "available"
        tail = f"; {hint}" if hint else ""
        raise error(f"{what} would need {human_bytes(nbytes)} of memory, more than the {human_bytes(budget)} "
                    f"{source}{tail}")
