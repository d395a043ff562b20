"""The ``evnoise`` command line: ``main(argv) -> exit code`` with one module per subcommand.

Each subcommand lives in ``evnoise/cli/<name>.py`` and defines ``register(subparsers)``, which
adds its parser and sets ``func`` (called with the parsed arguments, returning an exit code).
Registration must stay cheap: heavy imports happen inside ``func``. Errors that evnoise raises
on purpose (:class:`evnoise.EvnoiseError`) print one line ``evnoise: error: ...`` and exit 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from .._version import __version__
from ..errors import EvnoiseError

# subcommand modules, in the order they appear in --help
COMMANDS = ["simulate", "make_dataset", "calibrate", "train", "reconstruct", "separate", "info"]

log = logging.getLogger("evnoise")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evnoise",
        description="Photon noise of event cameras: simulate noise events, make datasets, "
        "calibrate the model, train and run a reconstructor.",
    )
    parser.add_argument("--version", action="version", version=f"evnoise {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    parser.add_argument("-q", "--quiet", action="store_true", help="only errors; no progress bars")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"{__name__}.{name}":
                continue  # subcommand not built yet
            raise
        module.register(sub)
    return parser


def main(argv=None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.ERROR if args.quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="evnoise: %(levelname)s: %(message)s", force=True)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        code = args.func(args)
    except EvnoiseError as exc:
        print(f"evnoise: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("evnoise: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `evnoise info FILE | head`: the reader went away, not an error
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    return 0 if code is None else int(code)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
