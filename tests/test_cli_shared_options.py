"""A command-line option shared by two commands is declared once (issue 30 item 5).

The declarations live in ``evnoise/cli/_options.py`` (one ``add_*`` function per shared option, grouped into
parent parsers); the commands, the ``python -m`` scripts and the plugins call them. These tests read the source
(AST) of all of ``evnoise/`` and the parsers the CLI builds, and check that

* each long option that two or more subcommands have appears in exactly one ``add_argument`` call, except the
  few flags that mean different things in different commands (:data:`DIFFERENT_MEANINGS`, with the reason);
* no code of evnoise reads argparse's private ``_actions`` (the CLI's names -> flags table is its own);
* ``pretrain`` and ``lpips`` are subcommands, and their ``python -m`` entry points are thin aliases.
"""

from __future__ import annotations

import ast
import collections
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "evnoise"

#: flags that two commands use for different things: flag -> (number of add_argument calls, why)
DIFFERENT_MEANINGS = {
    "--method": (3, "simulate: simulation tier; calibrate: closed form; separate: filter"),
    "--window": (3, "make-dataset: list of integration windows; reconstruct: one window in seconds; calibrate: "
                    "A:B[@LUX] still windows of a recording"),
    "--fit": (2, "simulate/make-dataset: how images meet the sensor (one declaration); calibrate: parameters to fit"),
    "--crop": (2, "make-dataset: WxH crops in sensor pixels; train/pretrain: square side in binned pixels "
                  "(one declaration)"),
    "--split": (2, "make-dataset: TRAIN,VAL,TEST fractions; evaluate: which split to score"),
    "--ml-sigma": (2, "train/pretrain: one ML input channel (one declaration); evaluate: baseline rows, repeatable"),
    "--json": (2, "evaluate: a JSON file to write; presets/info: print JSON (one declaration)"),
}

#: argparse's own, never declared by evnoise
ARGPARSE_OWN = {"--help"}


def _subparsers():
    from evnoise.cli import build_parser

    return build_parser().get_default("subparsers_action").choices


def _declarations() -> dict:
    """Long option -> ["path:line", ...] of every ``*.add_argument("--flag", ...)`` call under evnoise/."""
    found = collections.defaultdict(list)
    for path in sorted(ROOT.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument":
                for arg in node.args:
                    if isinstance(arg, ast.Constant) and isinstance(arg.value, str) and arg.value.startswith("--"):
                        found[arg.value].append(f"{path.relative_to(ROOT.parent)}:{node.lineno}")
    return found


def _shared_flags() -> dict:
    """Long option -> the subcommands that have it (from the tables the CLI's parsers record)."""
    commands = collections.defaultdict(set)
    for name, parser in _subparsers().items():
        for flag in set(parser.flags.values()):
            commands[flag].add(name)
    return {flag: names for flag, names in commands.items() if len(names) >= 2 and flag not in ARGPARSE_OWN}


def test_shared_options_are_declared_once():
    declared = _declarations()
    shared = _shared_flags()
    assert {"--out", "--overwrite", "--sensor", "--seed", "--threads"} <= set(shared)
    wrong = {}
    for flag, names in sorted(shared.items()):
        places = declared.get(flag, [])
        expected = DIFFERENT_MEANINGS.get(flag, (1, ""))[0]
        if len(places) != expected:
            wrong[flag] = (sorted(names), places)
    assert not wrong, f"shared options declared more than once (or not found): {wrong}"


def test_the_exceptions_are_still_needed():
    shared = _shared_flags()
    for flag in DIFFERENT_MEANINGS:
        assert flag in shared, f"{flag} is no longer shared: drop it from DIFFERENT_MEANINGS"


def test_no_code_reads_argparse_private_actions():
    offenders = []
    for path in sorted(ROOT.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr in ("_actions", "_option_string_actions",
                                                                 "_group_actions", "_choices_actions"):
                offenders.append(f"{path.relative_to(ROOT.parent)}:{node.lineno}")
    assert not offenders, f"argparse's private action lists read at {offenders}"


def test_pretrain_and_lpips_are_subcommands():
    subs = _subparsers()
    assert "pretrain" in subs and "lpips" in subs
    assert {"--epochs", "--crop", "--seed", "--threads", "--overwrite", "--out"} <= set(subs["pretrain"].flags.values())


def test_python_m_entry_points_are_thin_aliases(monkeypatch):
    """``python -m evnoise.reconstruct.{pretrain,lpips,evaluate}`` pass their arguments to ``evnoise CMD``."""
    import evnoise.cli as cli
    from evnoise.reconstruct import evaluate, lpips, pretrain

    seen = []
    monkeypatch.setattr(cli, "main", lambda argv=None: seen.append(argv) or 0)
    assert pretrain.main(["--epochs", "2"]) == 0
    assert lpips.main(["where"]) == 0
    assert evaluate.main(["ds"]) == 0
    assert seen == [["pretrain", "--epochs", "2"], ["lpips", "where"], ["evaluate", "ds"]]
    for module in (pretrain, lpips, evaluate):
        assert "ArgumentParser" not in Path(module.__file__).read_text(encoding="utf-8")


def test_error_names_come_from_the_commands_own_table():
    """A library message in Python names is written with the flags of the command that ran (train's ``max_minutes``
    is ``--max-minutes``; ``sensor_shape`` is ``--sensor``); names of options the command lacks stay as they are."""
    from evnoise.cli import _flag_names, build_parser

    args = build_parser().parse_args(["train", "d.npz", "--out", "m.pt"])
    assert _flag_names("max_minutes must be > 0; steps_per_epoch too", args) == \
        "--max-minutes must be > 0; --steps-per-epoch too"
    assert _flag_names("sensor_shape is wrong", args) == "sensor_shape is wrong"  # train has no --sensor
    args = build_parser().parse_args(["make-dataset", "x", "--out", "d"])
    assert _flag_names("sensor_shape is wrong; crop_shape too", args) == "--sensor is wrong; --crop too"


def test_pretrain_refuses_bad_training_numbers_in_one_line(capsys):
    from evnoise.cli import main

    assert main(["pretrain", "--epochs", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evnoise: error: --epochs must be >= 1") and err.count("\n") == 1


def test_lpips_subcommand_where(capsys, monkeypatch, tmp_path):
    from evnoise.cli import main

    monkeypatch.setenv("EVNOISE_LPIPS_WEIGHTS", str(tmp_path / "w.npz"))
    assert main(["lpips", "where"]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "w.npz")
