"""Exception hierarchy of evnoise.

Every error raised on bad user input derives from :class:`EvnoiseError`, so a caller
(and the command line) can catch one type. Messages name the offending value and
the allowed range.
"""

from __future__ import annotations


class EvnoiseError(Exception):
    """Base class of all errors evnoise raises on purpose."""


class ParameterError(EvnoiseError, ValueError):
    """A parameter is outside its allowed range (negative rate, eps <= 0, NaN, ...)."""


class InputError(EvnoiseError, ValueError):
    """Input data (an image, frames, events, a file) is missing, corrupt or inconsistent."""


class OutputError(EvnoiseError, OSError):
    """An output cannot be written (unwritable directory, existing file without overwrite)."""
