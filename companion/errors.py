"""Typed errors shared by the companion, the simulator and the analysis tools.

Library code raises these; only the command lines turn them into one clear line on stderr and
an exit code (see ``ExitCode``). Nothing below ``cli.py`` calls ``exit()``.
"""

from __future__ import annotations

import enum


class ExitCode(enum.IntEnum):
    OK = 0
    FAILURE = 1
    USAGE = 2
    CONFIG = 3
    BAD_INPUT = 4
    LINK = 5


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
