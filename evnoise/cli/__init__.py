"""The ``evnoise`` command line: ``main(argv) -> exit code`` with one module per subcommand.

Each subcommand lives in ``evnoise/cli/<name>.py`` and defines ``register(subparsers)``, which
adds its parser and sets ``func`` (called with the parsed arguments, returning an exit code).
Registration must stay cheap: heavy imports happen inside ``func``. Options that several commands
share are declared once, in :mod:`evnoise.cli._options` (declarations, parent parsers, the checkers of
numbers and sizes); its :class:`~evnoise.cli._options.Parser` records each command's table of Python names
to flags, with which an error of the library (which speaks Python names) is written in flags.

Errors print one line ``evnoise: error: ...`` and exit 2: those evnoise raises on purpose
(:class:`evnoise.EvnoiseError`), argparse's (bad or missing options; ``see evnoise CMD --help``), and
failures with a known cause outside evnoise (a damaged Numba cache: the folder to delete). A signal
that arrives inside compiled code is still "terminated" (143) or "interrupted" (130).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import sys
import warnings

from .._version import __version__
from ..errors import EvnoiseError
from ._options import ArgumentsError, Parser, add_verbosity, flag_names

# subcommand modules, in the order they appear in --help
COMMANDS = ["simulate", "make_dataset", "calibrate", "train", "pretrain", "evaluate", "reconstruct", "separate",
            "info", "presets", "lpips"]

log = logging.getLogger("evnoise")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="evnoise",
        description="Photon noise of event cameras: simulate noise events, make datasets, "
        "calibrate the model, train and run a reconstructor.",
    )
    parser.add_argument("--version", action="version", version=f"evnoise {__version__}")
    add_verbosity(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"{__name__}.{name}":
                continue  # subcommand not built yet
            raise
        module.register(sub)
    seen = set()
    for subparser in sub.choices.values():  # -v/-q after the subcommand as well (merged in main)
        if id(subparser) in seen:
            continue
        seen.add(id(subparser))
        add_verbosity(subparser, dest_prefix="sub_")
        subparser.set_defaults(cli_flags=subparser.flags)  # the command's names -> flags, for error lines
        subparser.set_defaults(cli_prog=subparser.prog)  # "evnoise info": whose --help an error line points to
    parser.set_defaults(subparsers_action=sub)
    return parser


def main(argv=None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``); returns the exit code.

    SIGTERM (a plain ``kill``) is handled like Ctrl-C: the command stops, temporary files are
    removed, and the exit code is 143 (128 + 15, what a shell reports for a process killed by
    SIGTERM; Ctrl-C gives 130).
    """
    parser = build_parser()
    _tolerant_streams()
    try:
        args, extra = parser.parse_known_args(argv)
        if extra:  # argparse's own check would point to "evnoise --help", not to the command's
            raise ArgumentsError(getattr(args, "cli_prog", parser.prog), "unrecognized arguments: " + " ".join(extra))
    except ArgumentsError as exc:
        print(exc.line(), file=sys.stderr)
        return 2
    args.argv = list(sys.argv[1:] if argv is None else argv)  # the command as given (pretrain's recipe line)
    args.verbose = args.verbose + getattr(args, "sub_verbose", 0)
    args.quiet = bool(args.quiet or getattr(args, "sub_quiet", False))
    level = logging.ERROR if args.quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    handler = _ProgressAwareHandler(getattr(args, "cli_flags", None))
    handler.setFormatter(logging.Formatter("evnoise: %(levelname)s: %(message)s"))
    logging.basicConfig(level=level, handlers=[handler], force=True)
    # Numba warns in five lines when it cannot make the semaphore of its threading layer (no room for the file:
    # `ulimit -f 0`, a full /dev/shm) and runs on without it; the command's own error, if any, is the line to see
    warnings.filterwarnings("ignore", message="Could not obtain multiprocessing lock")
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    previous = _catch_sigterm()
    said = []  # the exit code once a final line is printed
    try:
        return _run_command(args, previous, said)
    except Terminated:  # SIGTERM's retry alarm after the command was left, before its handler was removed
        _restore_sigterm(previous)
        if not said:
            print("evnoise: terminated", file=sys.stderr)
        return said[0] if said else 143


def _run_command(args, previous, said: list) -> int:
    """Run the parsed command; its errors and interruptions become one line on standard error (appending the exit
    code to ``said`` once that line is printed)."""
    try:
        code = args.func(args)
    except EvnoiseError as exc:
        _close_progress_bars()
        print(f"evnoise: error: {printable(_flag_names(str(exc), args))}", file=sys.stderr)
        said.append(2)
        return 2
    except Terminated:
        _close_progress_bars()
        print("evnoise: terminated", file=sys.stderr)
        said.append(143)
        return 143
    except KeyboardInterrupt:
        _close_progress_bars()
        print("evnoise: interrupted", file=sys.stderr)
        said.append(130)
        return 130
    except BrokenPipeError:  # e.g. `evnoise info FILE | head`: the reader went away, not an error
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except Exception as exc:
        _close_progress_bars()
        stop = _interruption(exc)
        if stop is not None:  # Ctrl-C or SIGTERM inside compiled code comes back wrapped in a SystemError
            print("evnoise: terminated" if isinstance(stop, Terminated) else "evnoise: interrupted", file=sys.stderr)
            said.append(143 if isinstance(stop, Terminated) else 130)
            return said[0]
        line = _known_failure(exc)
        if line is None:
            raise
        print(f"evnoise: error: {printable(line)}", file=sys.stderr)
        said.append(2)
        return 2
    finally:
        _restore_sigterm(previous)
    return 0 if code is None else int(code)


def _tolerant_streams() -> None:
    """Print file names that are not valid UTF-8 (bytes kept by Python as surrogates) with backslash escapes
    instead of failing with ``UnicodeEncodeError`` on standard output."""
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is not None and getattr(stream, "errors", "strict") == "strict":
            try:
                reconfigure(errors="backslashreplace")
            except (ValueError, OSError):  # pragma: no cover - a stream that cannot change now
                pass


def _interruption(exc: BaseException):
    """The :class:`KeyboardInterrupt` (or :class:`Terminated`) that caused ``exc``, if any: a signal handled while
    Numba-compiled code runs surfaces as ``SystemError: ... returned a result with an exception set``."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


#: errors of a path itself (not of a file's contents) and what to do about each
_PATH_ERRNOS = {
    errno.ENAMETOOLONG: "the file name is too long for the file system (at most 255 bytes per name); give a shorter "
                        "one",
    errno.ELOOP: "a loop of symbolic links; give a path that leads to a file",
}


def _known_failure(exc: BaseException) -> str | None:
    """One line (what went wrong and what to do) for failures outside evnoise's own errors that have a known
    cause; ``None`` for anything else (a bug: the traceback is shown)."""
    cache = _numba_cache_dir(exc)
    if cache is not None:
        where = cache if cache == _NUMBA_CACHE_SOMEWHERE else f"the folder {cache}"
        return (f"the cache of compiled kernels is damaged ({type(exc).__name__}: {exc}); delete "
                f"{where} (it is rebuilt on the next run, which compiles again) or point NUMBA_CACHE_DIR to an "
                f"empty folder")
    if isinstance(exc, OSError) and exc.errno in _PATH_ERRNOS and exc.filename is not None:
        # a name the file system refuses, met wherever a path is first looked at (exists(), is_dir(), open())
        return f"{exc.filename}: {_PATH_ERRNOS[exc.errno]}"
    if isinstance(exc, RuntimeError) and str(exc).startswith("Symlink loop from "):  # pathlib's resolve()
        path = str(exc)[len("Symlink loop from "):].strip("'")
        return f"{path}: {_PATH_ERRNOS[errno.ELOOP]}"
    if isinstance(exc, UnicodeEncodeError) and "surrogates not allowed" in str(exc):
        return (f"a file name or text is not valid UTF-8 ({exc.object[exc.start:exc.end]!r} in "
                f"{exc.object!r}); rename the file to a UTF-8 name")
    return None


#: where Numba's cache is when the traceback does not name its folder
_NUMBA_CACHE_SOMEWHERE = "the Numba cache folder (NUMBA_CACHE_DIR, or __pycache__ beside evnoise/_kernels)"


def _numba_cache_dir(exc: BaseException):
    """The folder of Numba's on-disk cache when ``exc`` was raised while loading from it, else ``None``."""
    import os

    tb = exc.__traceback__
    found = None
    while tb is not None:
        frame = tb.tb_frame
        if frame.f_code.co_filename.replace(os.sep, "/").endswith("numba/core/caching.py"):
            found = found or _NUMBA_CACHE_SOMEWHERE
            owner = frame.f_locals.get("self")
            for attr in ("_cache_path", "cache_path"):
                path = getattr(owner, attr, None)
                if isinstance(path, str) and path:
                    found = path
        tb = tb.tb_next
    return found


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM, so that the cleanup of Ctrl-C runs (temporaries removed)."""


_NO_HANDLER = object()
#: while a SIGTERM is pending, how often (seconds) to raise Terminated again if it was swallowed
_RETRY_S = 0.5


def _catch_sigterm():
    """Turn SIGTERM into :class:`Terminated` while a command runs; returns what to restore.

    An exception raised from a signal handler can land where Python ignores it (a weakref
    callback, a ``__del__``): the command would then run on. So, once a SIGTERM has arrived, a
    timer raises :class:`Terminated` again every ``_RETRY_S`` seconds until the command is left,
    but only where no exception is being handled (not into the cleanup of the first one).
    """
    import os
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return _NO_HANDLER
    pid = os.getpid()
    timer = hasattr(signal, "setitimer") and hasattr(signal, "SIGALRM")
    pending = []
    left = []  # set by _restore_sigterm: the command is over, a late alarm must not raise out of main()

    def raise_unless_unwinding():
        if not left and sys.exc_info()[1] is None:
            raise Terminated()

    def on_sigterm(signum, frame):
        if os.getpid() != pid:  # a forked worker process: die as SIGTERM would (pools terminate workers so)
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGTERM)
            return
        if pending or left:
            raise_unless_unwinding()
            return
        pending.append(True)
        if timer:
            signal.setitimer(signal.ITIMER_REAL, _RETRY_S, _RETRY_S)
        raise Terminated()

    def on_alarm(signum, frame):
        raise_unless_unwinding()

    try:
        previous = signal.signal(signal.SIGTERM, on_sigterm)
    except (ValueError, OSError):  # pragma: no cover - no signals here (embedded interpreter)
        return _NO_HANDLER
    previous_alarm = signal.signal(signal.SIGALRM, on_alarm) if timer else _NO_HANDLER
    hook = sys.unraisablehook

    def quiet_retries(unraisable):  # a retry that landed in a weakref callback or __del__: not a bug to print
        if not isinstance(unraisable.exc_value, Terminated):
            hook(unraisable)

    sys.unraisablehook = quiet_retries
    return previous, previous_alarm, left, hook


def _restore_sigterm(previous) -> None:
    import signal

    if previous is _NO_HANDLER:
        return
    term, alarm, left, hook = previous
    left.append(True)
    sys.unraisablehook = hook
    if alarm is not _NO_HANDLER:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, alarm if alarm is not None else signal.SIG_DFL)
    signal.signal(signal.SIGTERM, term if term is not None else signal.SIG_DFL)


def printable(text: str, keep: str = "") -> str:
    """``text`` with control characters (bytes a file put into a message: a camera name, a column header) written
    as escapes, but those in ``keep``: an error stays one line, and a hostile file cannot send escape sequences to
    the terminal."""
    if text.isprintable():
        return text
    return "".join(ch if ch.isprintable() or ch in keep else ch.encode("unicode_escape").decode("ascii")
                   for ch in text)


class _ProgressAwareHandler(logging.Handler):
    """Log records to standard error through ``tqdm.write`` when tqdm is loaded, so that a warning
    does not land on the line of a progress bar (the bar is redrawn below the message). ``flags``: the
    running command's names -> flags, with which the library's Python names are written as flags, as in
    an error line."""

    def __init__(self, flags: dict | None = None):
        super().__init__()
        self.flags = flags or {}

    def emit(self, record) -> None:
        try:
            text = self.format(record)
            if self.flags:
                text = flag_names(text, self.flags)
            text = printable(text, keep="\n")
            tqdm_module = sys.modules.get("tqdm")
            if tqdm_module is not None and getattr(tqdm_module.tqdm, "_instances", None):
                tqdm_module.tqdm.write(text, file=sys.stderr)
            else:
                sys.stderr.write(text + "\n")
                sys.stderr.flush()
        except Exception:  # pragma: no cover - as logging.StreamHandler
            self.handleError(record)


def _close_progress_bars() -> None:
    """Close the progress bars still open (left by an error or interruption), so that the final
    message starts on a line of its own."""
    tqdm_module = sys.modules.get("tqdm")
    if tqdm_module is None:
        return
    for bar in list(getattr(tqdm_module.tqdm, "_instances", ())):
        try:
            bar.close()
        except Exception:  # pragma: no cover - a bar that cannot redraw
            pass


def _flag_names(message: str, args) -> str:
    """``message`` with the Python parameter names of the subcommand's options written as its flags
    (``max_lux must be ...`` -> ``--max-lux must be ...``), by the table its parser recorded while its options
    were declared (:class:`evnoise.cli._options.Parser`)."""
    flags = getattr(args, "cli_flags", None)
    return flag_names(message, flags) if flags else message


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
