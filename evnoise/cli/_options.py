"""Options and value checks shared by the subcommands, each declared once.

``add_out``, ``add_overwrite``, ``add_sensor``, ``add_threads``, ``add_seed`` and ``add_csv_columns``
declare an option the same way in every command that has it (``-o`` is always ``--out``); the
argparse types ``seconds``, ``frequency``, ``seed`` and ``count`` check a value when it is parsed,
so that an absurd one (``--duration 1e308``, ``--seed 2**64``) is one error line before any work,
never a traceback after it. :func:`positive` is the one positive-number check of values that
arrive some other way, :func:`load_preset_arg` the one way a command loads a ``--preset`` (a name or
a TOML file). ``--sensor WxH`` is parsed by :func:`evnoise.readers.parse_sensor`, for every command.
"""

from __future__ import annotations

import argparse
import math

from ..errors import ParameterError

#: times are int64 microseconds: the largest number of seconds any time option may hold (~292,000 years)
MAX_SECONDS = (2**63 - 1) // 1_000_000
#: frequencies (--fps) give steps of at least one microsecond, the clock's resolution
MAX_HZ = 1e6
#: seeds are stored as int64 attributes of the event file
MAX_SEED = 2**63 - 1
#: the largest illuminance (and lux per unit) an option may give: 10,000 times full sunlight; 1e308 overflowed
MAX_LUX = 1e9


# --------------------------------------------------------------------------------------
# argparse types: one clear line for a bad value, before anything runs
# --------------------------------------------------------------------------------------
def _number(text: str, flag: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{flag} must be a number, got {text!r}") from None


def seconds(flag: str, *, positive: bool = False, minimum: float | None = None):
    """argparse type of a time in seconds: finite, within the µs clock's range (and > 0 if ``positive``)."""

    def parse(text):
        value = _number(text, flag)
        if positive and not (math.isfinite(value) and value > 0):
            raise argparse.ArgumentTypeError(f"{flag} must be finite and > 0 seconds, got {text}")
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{flag} must be a finite number of seconds, got {text}")
        if abs(value) > MAX_SECONDS:
            raise argparse.ArgumentTypeError(f"{flag} must be at most {MAX_SECONDS:.3g} seconds (times are "
                                             f"microseconds in 64 bits), got {text}")
        if minimum is not None and value < minimum:
            raise argparse.ArgumentTypeError(f"{flag} must be at least {minimum:g} seconds (the clock counts "
                                             f"microseconds), got {text}")
        return value

    parse.__name__ = "seconds"
    return parse


def frequency(flag: str, unit: str = "frames per second"):
    """argparse type of a rate (``--fps``): finite, > 0 and at most :data:`MAX_HZ` (one step per µs)."""
    return positive_number(flag, unit, maximum=MAX_HZ, why="one per microsecond, the clock's resolution")


def positive_number(flag: str, unit: str = "", *, maximum: float | None = None, why: str = ""):
    """argparse type of a finite number > 0 (e.g. ``--max-lux``), at most ``maximum`` if given (``why``: the
    reason for that limit, shown in the error)."""

    def parse(text):
        value = _number(text, flag)
        try:
            value = positive(value, flag, unit)
        except ParameterError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        if maximum is not None and value > maximum:
            raise argparse.ArgumentTypeError(f"{flag} must be at most {maximum:g}{' ' + unit if unit else ''}"
                                             f"{f' ({why})' if why else ''}, got {text}")
        return value

    parse.__name__ = "number"
    return parse


def seed(flag: str = "--seed"):
    """argparse type of a seed: an integer in ``0 .. 2**63 - 1`` (it is stored in the event file)."""

    def parse(text):
        try:
            value = int(text, 0) if text.strip().lower().startswith(("0x", "0o", "0b")) else int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} must be a non-negative integer, got {text!r}") from None
        if value < 0:
            raise argparse.ArgumentTypeError(f"{flag} must be a non-negative integer, got {text}")
        if value > MAX_SEED:
            raise argparse.ArgumentTypeError(f"{flag} must be at most 2**63 - 1 = {MAX_SEED} (it is stored as a "
                                             f"64-bit integer), got {text}")
        return value

    parse.__name__ = "seed"
    return parse


def count(flag: str, *, minimum: int = 1, maximum: int = 2**31 - 1):
    """argparse type of a whole number in ``minimum .. maximum`` (``--threads``, ``--frames``)."""

    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} must be a whole number, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{flag} must be >= {minimum}, got {value}")
        if value > maximum:
            raise argparse.ArgumentTypeError(f"{flag} must be <= {maximum}, got {value}")
        return value

    parse.__name__ = "count"
    return parse


# --------------------------------------------------------------------------------------
# checks of values that arrive otherwise (defaults, other options' parts)
# --------------------------------------------------------------------------------------
def positive(value, flag: str, unit: str = "") -> float | None:
    """``value`` as a float if finite and > 0 (``None`` stays ``None``), else :class:`~evnoise.ParameterError`."""
    if value is None:
        return None
    value = float(value)
    if not math.isfinite(value) or value <= 0:
        raise ParameterError(f"{flag} must be finite and > 0{' ' + unit if unit else ''}, got {value:g}")
    return value


def check_range_text(text, flag: str, unit: str = "", maximum: float = MAX_LUX) -> None:
    """``LUX`` or ``LO:HI`` (make-dataset's ranges): :class:`~evnoise.ParameterError` for a number that is not
    finite and > 0 or above ``maximum``; text that is no number is left to the range parser to report."""
    for part in str(text).split(":"):
        try:
            value = float(part)
        except ValueError:
            continue
        if not (math.isfinite(value) and 0 < value <= maximum):
            raise ParameterError(f"{flag} must be finite, > 0 and at most {maximum:g}{' ' + unit if unit else ''}, "
                                 f"got {text}")


def check_text_file(value, flag: str = "--preset", what: str = "a preset is a TOML file") -> None:
    """If ``value`` names an existing file, :class:`~evnoise.ParameterError` unless it is UTF-8 text (a binary
    file, or one saved in another encoding, would otherwise be a ``UnicodeDecodeError`` traceback)."""
    from pathlib import Path

    if value is None:
        return
    path = Path(value)
    try:
        if not path.is_file():
            return  # a preset name, or a missing file: the loader says which
        path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ParameterError(f"{flag} {value}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at position "
                             f"{exc.start}); {what} saved as UTF-8") from None
    except OSError:
        return  # unreadable: the loader reports it


def load_preset_arg(value, flag: str = "--preset"):
    """:func:`evnoise.load_preset` of a command's ``--preset`` value (a name or a TOML file), with one clear
    line for a file that is not UTF-8 text."""
    from ..params import load_preset

    check_text_file(value, flag)
    return load_preset(value)


# --------------------------------------------------------------------------------------
# option declarations
# --------------------------------------------------------------------------------------
def event_suffixes() -> str:
    """The suffixes of the event files evnoise reads, e.g. ``.h5, .raw, .dat, ...``."""
    from ..readers import SUFFIXES

    return ", ".join(SUFFIXES)


def event_input_help(what: str = "input event file") -> str:
    """Help of a positional argument that takes any event file evnoise reads."""
    return f"{what}: evnoise's events.h5 or a camera recording ({event_suffixes()})"


def add_out(p, *, help: str, metavar: str | None = None, required: bool = False, default=None):
    """``-o/--out``."""
    return p.add_argument("-o", "--out", required=required, default=default, metavar=metavar, help=help)


def add_overwrite(p, help: str = "replace existing output files"):
    return p.add_argument("--overwrite", action="store_true", help=help)


def add_sensor(p, *, help: str = "sensor size, e.g. 640x480, for files whose header has none (or a wrong one)",
               default=None):
    return p.add_argument("--sensor", metavar="WxH", default=default, help=help)


def add_csv_columns(p):
    return p.add_argument("--csv-columns", metavar="COLS", help="column order of a CSV recording, e.g. x,y,p,t")


def add_threads(p, *, help: str, default=None):
    return p.add_argument("--threads", type=count("--threads"), default=default, metavar="N", help=help)


def add_seed(p, *, help: str, default=None):
    return p.add_argument("--seed", type=seed(), default=default, metavar="N", help=help)


__all__ = ["seconds", "frequency", "positive_number", "seed", "count", "positive", "load_preset_arg",
           "check_text_file", "check_range_text", "event_input_help", "add_out", "add_overwrite", "add_sensor",
           "add_csv_columns", "add_threads", "add_seed", "MAX_SECONDS", "MAX_HZ", "MAX_SEED", "MAX_LUX"]
