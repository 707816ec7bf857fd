"""style.md, library vs CLI: library errors name parameters (:class:`kernels.errors.ParameterError`);
the CLI adds the flags from one table (:mod:`feedmon.errors`)."""

from __future__ import annotations

import pickle

import pytest

from feedmon.cli import COMMANDS, main
from feedmon.errors import FLAGS, describe
from kernels.errors import ParameterError
from monitor.axes import load_axes


def test_describe_adds_the_flags_of_the_command():
    exc = ParameterError("period and spindle_rpm both give the disturbance period; give one of them",
                         "period", "spindle_rpm")
    assert describe(exc, "identify") == (f"{exc} (command line: --period, --spindle-rpm)")
    assert describe(exc, "replay") == str(exc)  # replay has no such options: no hint
    assert describe(ValueError("plain"), "identify") == "plain"
    err = OSError("cannot open Zenoh session: refused")
    err.parameters = ("connect",)  # as feedio.transport.open_session raises it
    assert describe(err, "status") == "cannot open Zenoh session: refused (command line: --connect)"
    assert set(FLAGS) <= set(COMMANDS)


def test_parameter_error_is_a_value_error_and_survives_pickling():
    exc = ParameterError("rate must be > 0", "rate")
    assert isinstance(exc, ValueError) and exc.parameters == ("rate",)
    back = pickle.loads(pickle.dumps(exc))  # e.g. from an offline worker process
    assert type(back) is ParameterError and str(back) == "rate must be > 0" and back.parameters == ("rate",)


def test_run_without_models(capsys):
    with pytest.raises(ParameterError, match="^model_paths is empty: give at least one model file$") as err:
        load_axes([])
    assert err.value.parameters == ("model_paths",)
    assert main(["run", "--from", "trial.mcap", "-o", "out.mcap"]) == 2
    assert "--model" in capsys.readouterr().err


def test_no_library_error_names_a_flag():
    """Every ``raise`` in kernels/, feedio/, monitor/, replay/, bridge/ words its message without a command-line flag
    (the CLI's argparse helpers in feedio.transport excepted: they are the CLI's own code)."""
    import ast
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    cli_helpers = {("feedio/transport.py", "config_from_args"), ("feedio/transport.py", "add_zenoh_arguments")}
    flag = re.compile(r"(?<![\w-])--[a-z]")
    found = []
    for package in ("kernels", "feedio", "monitor", "replay", "bridge"):
        for path in sorted((root / package).rglob("*.py")):
            rel = path.relative_to(root).as_posix()
            tree = ast.parse(path.read_text(encoding="utf-8"))
            for func in [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)]:
                if (rel, func.name) in cli_helpers:
                    continue
                for node in ast.walk(func):
                    if isinstance(node, ast.Raise) and node.exc is not None:
                        for const in ast.walk(node.exc):
                            if isinstance(const, ast.Constant) and isinstance(const.value, str) \
                                    and flag.search(const.value):
                                found.append(f"{rel}:{node.lineno}: {const.value!r}")
    assert not found, "\n".join(found)
