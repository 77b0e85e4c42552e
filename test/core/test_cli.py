"""cli: the one exit-code convention of every command-line tool."""

from __future__ import annotations

import argparse
import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from pair_vpr_ros import cli
from pair_vpr_ros.cli import (
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_PIPE,
    EXIT_USAGE,
    run_cli,
)
from pair_vpr_ros.errors import BagError, UsageError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="tool")
    p.add_argument("--n", type=int, default=1, help="a number")
    return p


def _raise(err: BaseException):
    def body(args: argparse.Namespace) -> int:
        raise err

    return body


def test_codes_are_the_documented_ones():
    assert (EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED) == (0, 1, 2, 130)


def test_body_result_and_parsed_args(capsys):
    seen = []
    assert run_cli(_parser(), lambda args: seen.append(args.n), ["--n", "4"]) == EXIT_OK
    assert seen == [4]
    assert run_cli(_parser(), lambda args: 7, []) == 7
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    ("err", "code", "line"),
    [
        (BagError("bag x.mcap does not exist"), EXIT_ERROR, "error: bag x.mcap does not exist\n"),
        (UsageError("give OUT or --dataset"), EXIT_USAGE, "error: give OUT or --dataset\n"),
        (KeyboardInterrupt(), EXIT_INTERRUPTED, "error: interrupted\n"),
    ],
)
def test_errors_become_one_line_and_a_code(capsys, err, code, line):
    assert run_cli(_parser(), _raise(err), []) == code
    assert capsys.readouterr() == ("", line)


def test_interrupt_message_and_other_exceptions(capsys):
    body = _raise(KeyboardInterrupt())
    assert run_cli(_parser(), body, [], interrupted="stopped; resume with --resume") == 130
    assert capsys.readouterr().err == "error: stopped; resume with --resume\n"
    with pytest.raises(ZeroDivisionError):  # a bug is a traceback, not an "error:" line
        run_cli(_parser(), _raise(ZeroDivisionError()), [])


def test_argparse_exits_become_codes(capsys):
    assert run_cli(_parser(), _raise(AssertionError()), ["--n", "x"]) == EXIT_USAGE
    assert "tool: error: argument --n: invalid int value: 'x'" in capsys.readouterr().err
    assert run_cli(_parser(), _raise(AssertionError()), ["--help"]) == EXIT_OK
    assert capsys.readouterr().out.startswith("usage: tool [-h] [--n N]")


@pytest.mark.parametrize(
    ("parse", "text", "value", "message"),
    [
        (cli.positive_int, "3", 3, None),
        (cli.positive_int, "0", None, "must be an integer >= 1, got 0"),
        (cli.positive_int, "2.5", None, "must be an integer >= 1, got '2.5'"),
        (cli.nonnegative_int, "0", 0, None),
        (cli.positive_float, "1e-3", 1e-3, None),
        (cli.positive_float, "-inf", None, "must be a finite number > 0, got '-inf'"),
        (cli.finite_float, "-7", -7.0, None),
        (cli.finite_float, "nan", None, "must be a finite number, got 'nan'"),
    ],
)
def test_numeric_flag_types(parse, text, value, message):
    if message is None:
        assert parse(text) == value
    else:
        with pytest.raises(argparse.ArgumentTypeError, match=re.escape(message)):
            parse(text)


CHATTY = """
import argparse, sys
from pair_vpr_ros.cli import run_cli
def body(args):
    for i in range(200000):  # far more than a pipe's buffer
        print(f"line {i}")
sys.exit(run_cli(argparse.ArgumentParser(prog="tool"), body, []))
"""


def test_a_closed_stdout_stops_the_tool_quietly():
    """`pairvpr-map info --json | head`: the reader closes the pipe after a line; the tool stops
    with 141 (128 + SIGPIPE) and nothing on stderr (no BrokenPipeError traceback, not even the
    interpreter's "Exception ignored" at exit)."""
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    proc = subprocess.Popen(
        [sys.executable, "-c", CHATTY], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env
    )
    assert proc.stdout.readline() == b"line 0\n"
    proc.stdout.close()
    _, err = proc.communicate(timeout=60)
    assert (proc.returncode, err.decode()) == (EXIT_PIPE, "")
    assert EXIT_PIPE == 141


def test_every_console_script_goes_through_run_cli():
    """Each tool of setup.py's console_scripts (the nodes aside) calls run_cli (the trainers
    through driver.stage_main), so each gets the exit codes and the quiet stop on a closed
    stdout. Read from the source's AST: importing every tool would take seconds."""
    root = Path(__file__).resolve().parents[2]
    entries = re.findall(r'"([\w-]+) = ([\w.]+):(\w+)"', (root / "setup.py").read_text())
    tools = [(m, f) for name, m, f in entries if not m.startswith("pair_vpr_ros.ros.")]
    assert len(tools) >= 8
    for module, func in tools:
        tree = ast.parse((root / (module.replace(".", "/") + ".py")).read_text())
        main = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == func)
        called = {n.func.id for n in ast.walk(main) if isinstance(n, ast.Call)
                  and isinstance(n.func, ast.Name)}  # fmt: skip
        assert called & {"run_cli", "stage_main"}, module
    driver = (root / "pair_vpr_ros/learn/train/driver.py").read_text()
    assert "return run_cli(parser, body, argv, interrupted=resume)" in driver
