"""The command line's one home for options: the parser class, each shared option's declaration, the
parent parsers that group them, the checkers of numbers and sizes, and the table of Python names to flags.

**Declarations.** Every option that two commands (or a command and a ``python -m`` script) share has
one ``add_*`` function here holding its one ``add_argument`` call (``-o`` is always ``--out``); a command
passes its own help text or default where the meaning differs in detail ("replace an existing --plot
file"). ``tests/test_cli_shared_options.py`` guards that no shared flag is declared twice.

**Parent parsers** (argparse ``parents=``) bundle the declarations commands take together:
:func:`events_input` (an event file and how to read it: ``--sensor``, ``--csv-columns``),
:func:`output` (``-o/--out``, ``--overwrite``, and ``--format`` for event outputs), :func:`run_options`
(``--seed``, ``--threads``), :func:`image_input` (how an image becomes lux) and :func:`training` (the
U-Net training options of ``train`` and ``pretrain``). Each call makes a fresh parent, so a command's
defaults and help never leak into another's.

**Checkers.** The argparse types ``seconds``, ``frequency``, ``positive_number``, ``seed``, ``count`` and
``size`` check a value when it is parsed, so that an absurd one (``--duration 1e308``, ``--seed 2**64``)
is one error line before any work, never a traceback after it. :func:`positive` is the one
positive-number check of values that arrive some other way, :func:`load_preset_arg` the one way a
command loads a ``--preset`` (a name or a TOML file). ``--sensor WxH`` is parsed by
:func:`evnoise.readers.parse_sensor`, for every command.

**Names to flags.** The library's messages name Python parameters (``max_lux must be > 0``);
:class:`Parser` records, for each option it declares, its flag under its ``dest``, its name with
underscores, and the library names of :data:`PYTHON_NAMES`; ``evnoise.cli.main`` rewrites an error's
names with that table (:func:`flag_names`).
"""

from __future__ import annotations

import argparse
import math
import re

from .._checks import MAX_LUX
from ..errors import ParameterError

#: times are int64 microseconds: the largest number of seconds any time option may hold (~292,000 years)
MAX_SECONDS = (2**63 - 1) // 1_000_000
#: frequencies (--fps) give steps of at least one microsecond, the clock's resolution
MIN_HZ = 1e-6  #: slowest --fps: a frame per 11.6 days (times are microseconds in 64 bits)
MAX_HZ = 1e6
#: seeds are stored as int64 attributes of the event file
MAX_SEED = 2**63 - 1


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
    """argparse type of a rate (``--fps``): finite, from :data:`MIN_HZ` (a frame per 11.6 days) to :data:`MAX_HZ`
    (one step per µs)."""
    return positive_number(flag, unit, maximum=MAX_HZ, why="one per microsecond, the clock's resolution",
                           minimum=MIN_HZ)


def positive_number(flag: str, unit: str = "", *, maximum: float | None = None, why: str = "",
                    minimum: float | None = None):
    """argparse type of a finite number > 0 (e.g. ``--max-lux``), at most ``maximum`` if given (``why``: the
    reason for that limit, shown in the error) and at least ``minimum`` if given."""

    def parse(text):
        value = _number(text, flag)
        try:
            value = positive(value, flag, unit)
        except ParameterError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        if minimum is not None and value < minimum:
            raise argparse.ArgumentTypeError(f"{flag} must be at least {minimum:g}{' ' + unit if unit else ''}, "
                                             f"got {text}")
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


def size(flag: str, *, minimum: tuple = (1, 1), maximum: int = 65536):
    """argparse type of a size ``WxH`` (``640x480``; ``x``, ``X``, ``*`` or ``,`` between): the one "WxH"
    checker of the command line. Returns the size as ``"WxH"`` text (what the library's ``sensor=`` takes);
    width and height must be at least ``minimum`` ``(W, H)`` and at most ``maximum``."""

    def parse(text):
        m = re.fullmatch(r"\s*(\d+)\s*[xX*,]\s*(\d+)\s*", str(text))
        if not m:
            raise argparse.ArgumentTypeError(f"{flag} must be WIDTHxHEIGHT, e.g. 640x480, got {text!r}")
        width, height = int(m.group(1)), int(m.group(2))
        if minimum == (1, 1) and maximum == 65536:
            if not (1 <= width <= maximum and 1 <= height <= maximum):
                raise argparse.ArgumentTypeError(f"{flag} must be WIDTHxHEIGHT with 1 .. {maximum} each, got "
                                                 f"{text!r}")
        elif not (minimum[0] <= width <= maximum and minimum[1] <= height <= maximum):
            raise argparse.ArgumentTypeError(f"{flag} must be between {minimum[0]}x{minimum[1]} and "
                                             f"{maximum}x{maximum} pixels, got {text!r}")
        return f"{width}x{height}"

    parse.__name__ = "size"
    return parse


def height_width(text) -> tuple:
    """``"WxH"`` (as :func:`size` returns it) -> ``(H, W)``."""
    width, height = (int(v) for v in str(text).lower().split("x"))
    return height, width


# --------------------------------------------------------------------------------------
# the parser: one-line errors, and the table of Python names to flags
# --------------------------------------------------------------------------------------
#: library parameter names whose flag is not the name with dashes: flag -> the names the library uses for it
PYTHON_NAMES = {
    "--duration": ("duration_s",), "--window": ("window_s", "windows_s"), "--crop": ("crop_shape",),
    "--sensor": ("sensor_shape",), "--t-start": ("t_start_s",), "--step": ("step_s",), "--radius": ("radius_px",),
    "--starts": ("n_starts",), "--frames": ("max_frames",), "--fps": ("fps_out",), "--preset": ("params",),
    "--model": ("model_path",), "--out": ("signal_out",),
}


class ArgumentsError(Exception):
    """A command line argparse refused; ``evnoise.cli.main`` prints it as one line (argparse would print the
    usage block and exit)."""

    def __init__(self, prog: str, message: str):
        super().__init__(message)
        self.prog = prog
        self.message = message

    def line(self) -> str:
        """``evnoise: error: ...`` without argparse's ``argument --x:`` when the message names the flag."""
        message = self.message
        m = re.match(r"argument ([^:]+): (.*)$", message, re.S)
        if m and any(m.group(2).startswith(flag) for flag in m.group(1).split("/")):
            message = m.group(2)
        return f"evnoise: error: {message} (see {self.prog} --help)"


class Parser(argparse.ArgumentParser):
    """argparse's parser whose errors are one line (:class:`ArgumentsError`; its subparsers are of this class
    too) and which keeps ``flags``: Python name -> flag of every option declared on it, in its argument
    groups or in its ``parents`` (the table ``evnoise.cli.main`` rewrites error messages with)."""

    def __init__(self, *args, parents=(), **kwargs):
        self.flags: dict = {}
        super().__init__(*args, parents=parents, **kwargs)
        for parent in parents:
            for name, flag in getattr(parent, "flags", {}).items():
                self.flags.setdefault(name, flag)

    def add_argument(self, *args, **kwargs):
        action = super().add_argument(*args, **kwargs)
        self._record(action)
        return action

    def add_argument_group(self, *args, **kwargs):
        group = super().add_argument_group(*args, **kwargs)
        add = group.add_argument

        def add_argument(*a, **k):
            action = add(*a, **k)
            self._record(action)
            return action

        group.add_argument = add_argument
        return group

    def _record(self, action) -> None:
        longs = [o for o in action.option_strings if o.startswith("--")]
        if not longs:
            return
        flag = longs[0]
        for name in (flag[2:].replace("-", "_"), action.dest, *PYTHON_NAMES.get(flag, ())):
            self.flags.setdefault(name, flag)

    def error(self, message):
        raise ArgumentsError(self.prog, message)


def flag_names(message: str, flags: dict) -> str:
    """``message`` with the Python parameter names of ``flags`` (a :class:`Parser`'s table) written as flags.

    A name with an underscore is rewritten wherever it stands as a word (``max_lux must be ...`` ->
    ``--max-lux must be ...``); a plain word (``sensor``, ``overwrite``: as likely prose as a parameter) only
    in its keyword form: ``overwrite=True`` -> ``--overwrite``, ``sensor="WxH"`` -> ``--sensor WxH``,
    ``windows_s=0.05`` -> ``--window 0.05``, and ``params=`` (the name itself) -> ``--preset``. A name in quotes
    (``'t_start_s'``: a key or column of the user's file) is left as it is."""
    before = r"(?<![\w./'\"-])"
    for name, flag in sorted(flags.items(), key=lambda kv: -len(kv[0])):
        word = before + re.escape(name)
        message = re.sub(rf"{word}=True(?!\w)", flag, message)
        message = re.sub(rf"{word}=(['\"])([^'\"]*)\1", lambda m, flag=flag: f"{flag} {m.group(2)}", message)
        message = re.sub(rf"{word}=(\d[\w.,:+-]*\w|\d)", lambda m, flag=flag: f"{flag} {m.group(1)}", message)
        message = re.sub(rf"{word}=(?![\w'\"(\[{{])", flag, message)
        if "_" in name:
            message = re.sub(rf"{word}(?![\w/=]|\.\w)", flag, message)
    # "(clip_invalid=True, --clip-invalid)" and "window_s (--window)" now say the flag twice
    return re.sub(r"(--[\w-]+)(?:, \1(?![\w-])| \(\1\))", r"\1", message)


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``"1 epoch"``, ``"2 epochs"``: a count with its noun in the right number."""
    return f"{n} {noun if n == 1 else (plural or noun + 's')}"


def parent() -> Parser:
    """An empty parent parser (no ``-h``), for ``parents=``."""
    return Parser(add_help=False)


# --------------------------------------------------------------------------------------
# option declarations: each shared option's one add_argument
# --------------------------------------------------------------------------------------
def event_suffixes() -> str:
    """The suffixes of the event files evnoise reads, e.g. ``.h5, .raw, .dat, ...``."""
    from ..readers import SUFFIXES

    return ", ".join(SUFFIXES)


def event_input_help(what: str = "input event file") -> str:
    """Help of a positional argument that takes any event file evnoise reads."""
    return f"{what}: evnoise's events.h5 or a camera recording ({event_suffixes()})"


def add_verbosity(p, *, dest_prefix: str = "") -> None:
    """``-v/--verbose`` and ``-q/--quiet`` (before the subcommand, and after it under ``sub_*`` dests)."""
    p.add_argument("-v", "--verbose", dest=f"{dest_prefix}verbose", action="count", default=0,
                   help="more log output (-vv for debug)")
    add_quiet(p, dest=f"{dest_prefix}quiet")


def add_quiet(p, *, dest: str = "quiet", help: str = "only errors; no progress bars"):
    """``-q/--quiet``."""
    return p.add_argument("-q", "--quiet", dest=dest, action="store_true", help=help)


def add_out(p, *, help: str, metavar: str | None = None, required: bool = False, default=None):
    """``-o/--out``."""
    return p.add_argument("-o", "--out", required=required, default=default, metavar=metavar, help=help)


def add_overwrite(p, help: str = "replace existing output files"):
    """``--overwrite``."""
    return p.add_argument("--overwrite", action="store_true", help=help)


def add_format(p, *, help: str | None = None):
    """``--format`` of an event output: the formats of the registry (:mod:`evnoise.formats`)."""
    from ..formats import output_format_names, output_formats_help

    return p.add_argument("--format", choices=output_format_names(),
                          help=help or f"check the output format, which must agree with --out: {output_formats_help()}")


def add_sensor(p, *, help: str = "sensor size, e.g. 640x480, for files whose header has none (or a wrong one)",
               default=None):
    """``--sensor WxH`` (checked by :func:`size`; the value stays ``"WxH"`` text)."""
    return p.add_argument("--sensor", type=size("--sensor"), metavar="WxH", default=default, help=help)


def add_csv_columns(p):
    """``--csv-columns``."""
    return p.add_argument("--csv-columns", metavar="COLS", help="column order of a CSV recording, e.g. x,y,p,t")


def add_t_start(p, *, help: str, default=None):
    """``--t-start S``: seconds on a recording's clock."""
    return p.add_argument("--t-start", type=seconds("--t-start"), default=default, metavar="S", help=help)


def add_t_end(p, *, help: str):
    """``--t-end S``: seconds on a recording's clock."""
    return p.add_argument("--t-end", type=seconds("--t-end"), metavar="S", help=help)


def add_fps(p, *, help: str, default=None):
    """``--fps F``: frames per second, at most one per microsecond."""
    return p.add_argument("--fps", type=frequency("--fps"), default=default, metavar="F", help=help)


#: most worker threads a command starts: more than any machine's cores gains nothing, and 100,000 made OpenMP (torch)
#: run out of memory starting them
MAX_THREADS = 1024


def add_threads(p, *, help: str, default=None):
    """``--threads N`` (at most :data:`MAX_THREADS`)."""
    return p.add_argument("--threads", type=count("--threads", maximum=MAX_THREADS), default=default, metavar="N",
                          help=help)


def add_seed(p, *, help: str, default=None):
    """``--seed N`` (0 .. 2**63 - 1)."""
    return p.add_argument("--seed", type=seed(), default=default, metavar="N", help=help)


def add_preset(p, *, help: str = "noise-model preset name or parameter TOML file (default: %(default)s)",
               default="evk3-hd"):
    """``--preset NAME|TOML`` (loaded by :func:`load_preset_arg`)."""
    return p.add_argument("--preset", default=default, metavar="NAME|TOML", help=help)


def add_model(p):
    """``--model``: a reconstructor checkpoint."""
    return p.add_argument("--model", default=None,
                          help="checkpoint written by `evnoise train` (default: the shipped evk3-hd model)")


def add_max_lux(p, *, help: str, ranges: bool = False, default=None):
    """``--max-lux``: lux of full-scale white; ``ranges``: also ``LO:HI`` (text, checked by
    :func:`check_range_text`), else one positive number."""
    kind = dict(metavar="LUX|LO:HI") if ranges else dict(type=positive_number("--max-lux", "lux", maximum=MAX_LUX),
                                                          metavar="LUX")
    return p.add_argument("--max-lux", default=default, help=help, **kind)


def add_lux_scale(p, *, help: str, ranges: bool = False, default=None):
    """``--lux-scale``: lux per unit of linear images (``ranges``: also ``LO:HI``, as :func:`add_max_lux`)."""
    kind = dict(metavar="K|LO:HI") if ranges else dict(
        type=positive_number("--lux-scale", "lux per unit", maximum=MAX_LUX), metavar="K")
    return p.add_argument("--lux-scale", default=default, help=help, **kind)


def add_encoding(p):
    """``--encoding``: transfer function of 8/16-bit images."""
    from ..radiometry import ENCODINGS

    return p.add_argument("--encoding", choices=ENCODINGS, default="srgb",
                          help="transfer function of 8/16-bit images (default: %(default)s)")


def add_clip_invalid(p, *, help: str):
    """``--clip-invalid``."""
    return p.add_argument("--clip-invalid", action="store_true", help=help)


def add_image_fit(p, *, help: str):
    """``--fit cover|crop|resize``: how images are brought to ``--sensor``."""
    from ..radiometry import FIT_MODES

    return p.add_argument("--fit", choices=FIT_MODES, default="cover", help=help)


def add_compression(p, *, help: str, default: str):
    """``--compression``: HDF5 compression (``none``: off)."""
    return p.add_argument("--compression", choices=("gzip", "lzf", "none"), default=default, help=help)


def add_binning(p, *, help: str, default=None, metavar: str | None = None):
    """``--binning B``: counts summed over BxB pixels."""
    return p.add_argument("--binning", type=count("--binning"), default=default, metavar=metavar, help=help)


def add_json_output(p, *, help: str = "print as JSON"):
    """``--json``: print the command's result as JSON instead of text."""
    return p.add_argument("--json", action="store_true", help=help)


def add_png(p, *, help: str):
    """``--png FILE``: a picture beside the command's output."""
    return p.add_argument("--png", default=None, metavar="FILE", help=help)


def add_plot(p, *, help: str, metavar: str = "PNG"):
    """``--plot FILE``: a figure."""
    return p.add_argument("--plot", metavar=metavar, help=help)


def add_example(p, *, help: str):
    """``--example``: a bundled input instead of the positional one."""
    return p.add_argument("--example", action="store_true", help=help)


# --------------------------------------------------------------------------------------
# parent parsers: the blocks commands share (each call a fresh parent)
# --------------------------------------------------------------------------------------
def events_input(*, sensor_help: str | None = None) -> Parser:
    """An event file to read: the positional ``events``, ``--sensor`` and ``--csv-columns``."""
    p = parent()
    p.add_argument("events", help=event_input_help())
    if sensor_help is None:
        add_sensor(p)
    else:
        add_sensor(p, help=sensor_help)
    add_csv_columns(p)
    return p


def output(*, help: str | None = None, metavar: str | None = None, required: bool = False,
           overwrite_help: str = "replace existing output files", event_formats: bool = False) -> Parser:
    """What a command writes: ``-o/--out`` (when ``help`` is given), ``--overwrite``, and with
    ``event_formats`` the ``--format`` check of an event file."""
    p = parent()
    if help is not None:
        add_out(p, help=help, metavar=metavar, required=required)
    if event_formats:
        add_format(p)
    add_overwrite(p, help=overwrite_help)
    return p


def run_options(*, seed_help: str | None = None, seed_default=None, threads_help: str | None = None,
                threads_default=None) -> Parser:
    """Randomness and parallelism: ``--seed`` and/or ``--threads`` (those whose help is given)."""
    p = parent()
    if seed_help is not None:
        add_seed(p, help=seed_help, default=seed_default)
    if threads_help is not None:
        add_threads(p, help=threads_help, default=threads_default)
    return p


def image_input(*, sensor_help: str, fit_help: str, max_lux_help: str, lux_scale_help: str,
                clip_invalid_help: str, ranges: bool = False, sensor_default=None, **defaults) -> Parser:
    """How an image becomes illuminance: ``--sensor``, ``--fit``, ``--max-lux``, ``--lux-scale``,
    ``--encoding``, ``--clip-invalid`` (``ranges``: ``--max-lux``/``--lux-scale`` also take ``LO:HI``)."""
    p = parent()
    add_sensor(p, help=sensor_help, default=sensor_default)
    add_image_fit(p, help=fit_help)
    add_max_lux(p, help=max_lux_help, ranges=ranges)
    add_lux_scale(p, help=lux_scale_help, ranges=ranges)
    add_encoding(p)
    add_clip_invalid(p, help=clip_invalid_help)
    if defaults:
        p.set_defaults(**defaults)
    return p


def training(*, crop_help: str = "training crop side in binned pixels, i.e. make-dataset's sensor-pixel --crop "
             "divided by its --binning (default: 64, or the largest size that fits the pairs)", **defaults) -> Parser:
    """The U-Net training options of ``evnoise train`` and ``evnoise pretrain``; ``defaults`` (by ``dest``)
    set the command's own defaults, which the help texts show."""
    p = parent()
    budget = defaults.get("max_minutes")
    p.add_argument("--max-minutes", type=positive_number("--max-minutes", "minutes"), default=None, metavar="M",
                   help=f"wall-clock budget in minutes (default: {'none' if budget is None else f'{budget:g}'})")
    p.add_argument("--epochs", type=count("--epochs"), default=60, help="maximum epochs (default %(default)s)")
    p.add_argument("--steps-per-epoch", type=count("--steps-per-epoch"), default=50,
                   help="batches per epoch (default %(default)s)")
    p.add_argument("--batch-size", type=count("--batch-size"), default=16, help="crops per batch (default %(default)s)")
    p.add_argument("--crop", type=count("--crop"), default=None, help=crop_help)
    p.add_argument("--lr", type=positive_number("--lr"), default=2e-3, help="AdamW learning rate (default %(default)g)")
    p.add_argument("--ssim-weight", type=float, default=0.2,
                   help="weight of the 1 - SSIM loss term (default %(default)g)")
    p.add_argument("--pixel-loss", choices=("l1", "mse"), default="l1",
                   help="pixel term of the loss: l1 (sharp) or mse (the mean, what PSNR scores; default %(default)s)")
    p.add_argument("--transform", choices=("rate", "anscombe"), default="rate",
                   help="input transform of the counts: rate, or the variance-stabilising Anscombe square root "
                   "(default %(default)s)")
    p.add_argument("--ml-sigma", type=float, default=None, metavar="S",
                   help="add the closed-form ML estimate (counts smoothed with a Gaussian of S binned pixels) as "
                   "an input channel")
    p.add_argument("--base-channels", type=count("--base-channels"), default=None, help="U-Net width (default 16)")
    p.add_argument("--resume", action="store_true", help="continue the run stored in --out")
    if defaults:
        p.set_defaults(**defaults)
    return p


__all__ = ["seconds", "frequency", "positive_number", "seed", "count", "size", "height_width", "positive",
           "load_preset_arg", "check_text_file", "check_range_text", "event_input_help", "event_suffixes",
           "Parser", "ArgumentsError", "PYTHON_NAMES", "flag_names", "parent", "add_verbosity", "add_out",
           "add_overwrite", "add_format", "add_sensor", "add_csv_columns", "add_t_start", "add_t_end", "add_fps",
           "add_threads", "add_seed", "add_preset", "add_model", "add_max_lux", "add_lux_scale", "add_encoding",
           "add_clip_invalid", "add_image_fit", "add_compression", "add_quiet", "add_binning", "add_json_output",
           "add_png", "add_plot", "add_example",
           "events_input", "output", "run_options", "image_input", "training",
           "MAX_SECONDS", "MAX_HZ", "MAX_SEED", "MAX_LUX"]
