"""One exit-code convention for every command-line tool of the package.

=====  ==================================================================================
code   meaning
=====  ==================================================================================
0      done
1      failed while running, or bad input data (any ``PairVPRError``: a missing or corrupt
       bag, checkpoint or dataset, an invalid parameter value); one ``error: ...`` line
2      usage error: the command line itself is wrong (argparse's own code; ``UsageError``)
130    interrupted by Ctrl-C (128 + SIGINT, as shells report it)
141    stdout was closed by its reader (``pairvpr-map info --json | head``): the output stops
       there without a word (128 + SIGPIPE, the code of ``cat`` in the same place)
=====  ==================================================================================

``run_cli`` applies it: every ``main(argv=None) -> int`` of the package is
``return run_cli(build_parser(), body, argv)``. The node (``vpr_node``) uses the same codes but
not ``run_cli``: it logs through rclpy, and Ctrl-C / SIGTERM are its normal way to stop (0).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable

from pair_vpr_ros.errors import PairVPRError, UsageError

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
EXIT_PIPE = 141


def _stdout_closed() -> int:
    """stdout's reader went away: point stdout at /dev/null, so that the interpreter's last
    flush at exit cannot raise again ("Exception ignored ... BrokenPipeError"); -> EXIT_PIPE."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # no file descriptor (a captured stream): nothing to flush
        pass
    return EXIT_PIPE


def run_cli(
    parser: argparse.ArgumentParser,
    body: Callable[[argparse.Namespace], int | None],
    argv: list[str] | None = None,
    *,
    interrupted: str = "interrupted",
) -> int:
    """Parse ``argv`` with ``parser`` and run ``body(args)`` -> the exit code.

    ``body`` returns its own code (None: ``EXIT_OK``). A ``PairVPRError`` prints
    ``error: <message>`` to stderr (``EXIT_USAGE`` for a ``UsageError``, else ``EXIT_ERROR``);
    Ctrl-C prints ``error: <interrupted>`` and gives ``EXIT_INTERRUPTED``. argparse's own exits
    (``--help``: 0, a bad flag: 2, message already printed) come back as codes, not exceptions.
    A closed stdout (a pipe into ``head``) stops the tool quietly with ``EXIT_PIPE``.
    """
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        if exc.code is None:
            return EXIT_OK
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    try:
        code = body(args)
        sys.stdout.flush()  # a closed pipe shows here, not at exit after the code is chosen
    except BrokenPipeError:
        return _stdout_closed()
    except UsageError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except PairVPRError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f"error: {interrupted}", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK if code is None else code


# ---- argparse types for numeric flags: a bad value is a usage error (2) naming the flag


def int_flag(requirement: str, ok: Callable[[int], bool]) -> Callable[[str], int]:
    """An argparse type: an integer for which `ok` holds, else "must be <requirement>"."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {requirement}, got {text!r}") from None
        if not ok(value):
            raise argparse.ArgumentTypeError(f"must be {requirement}, got {value}")
        return value

    return parse


def float_flag(requirement: str, ok: Callable[[float], bool]) -> Callable[[str], float]:
    """An argparse type: a finite float for which `ok` holds, else "must be <requirement>"."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and ok(value)):
            raise argparse.ArgumentTypeError(f"must be {requirement}, got {text!r}")
        return value

    return parse


positive_int = int_flag("an integer >= 1", lambda v: v >= 1)
nonnegative_int = int_flag("an integer >= 0", lambda v: v >= 0)
finite_float = float_flag("a finite number", lambda v: True)
positive_float = float_flag("a finite number > 0", lambda v: v > 0)
nonnegative_float = float_flag("a finite number >= 0", lambda v: v >= 0)
