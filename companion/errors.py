"""Typed errors shared by the companion, the simulator and the analysis tools.

Library code raises these; only the command lines turn them into one clear line on stderr and
an exit code (see ``ExitCode``). Nothing below ``cli.py`` calls ``exit()``.
"""

from __future__ import annotations

import enum
import os
import sys
from collections.abc import Callable


class ExitCode(enum.IntEnum):
    OK = 0
    FAILURE = 1
    USAGE = 2
    CONFIG = 3
    BAD_INPUT = 4
    LINK = 5


def run_command(command: Callable[[], int]) -> int:
    """Run a command-line action: a ``FlowholdError`` becomes one line on stderr and its exit
    code, Ctrl-C exits 130, and any other exception one line too (FLOWHOLD_DEBUG=1 re-raises it
    to show the traceback). The one place where exceptions become exit codes."""
    try:
        return int(command())
    except FlowholdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return int(exc.exit_code)
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the last line of defence: one line, no traceback
        if os.environ.get("FLOWHOLD_DEBUG"):
            raise
        print(f"error: {type(exc).__name__}: {exc} (set FLOWHOLD_DEBUG=1 for details)", file=sys.stderr)
        return int(ExitCode.FAILURE)


class FlowholdError(Exception):
    """Base class: an error a user can act on, with the exit code the command line uses."""

    exit_code: ExitCode = ExitCode.FAILURE


class ConfigError(FlowholdError):
    """A TOML parameter file is missing, malformed, or has unknown, missing or ill-typed keys."""

    exit_code = ExitCode.CONFIG


class RecordingError(FlowholdError):
    """A recording cannot be read, or holds nothing usable (names what is missing)."""

    exit_code = ExitCode.BAD_INPUT


class LinkError(FlowholdError):
    """A MAVLink connection could not be opened or the vehicle was never heard."""

    exit_code = ExitCode.LINK


class UsageError(FlowholdError):
    """A command-line value is malformed (e.g. ``--setpoint abc``, ``--listen nohost``)."""

    exit_code = ExitCode.USAGE
