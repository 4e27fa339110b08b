"""Typed errors shared by the companion, the simulator and the analysis tools.

Library code raises these; only the command lines turn them into one clear line on stderr and
an exit code (see ``ExitCode``). Nothing below ``cli.py`` calls ``exit()``.
"""

from __future__ import annotations

import contextlib
import enum
import errno
import os
import select
import sys
from collections.abc import Callable, Iterator
from pathlib import Path


class ExitCode(enum.IntEnum):
    OK = 0
    #: anything else that went wrong (one line, FLOWHOLD_DEBUG=1 for the traceback)
    FAILURE = 1
    #: a bad command-line value, or an output path that cannot be written
    USAGE = 2
    CONFIG = 3
    BAD_INPUT = 4
    LINK = 5
    #: Ctrl-C
    INTERRUPTED = 130
    #: the reader of our standard output went away (``| head``): quiet, as SIGPIPE ends a C tool
    PIPE_CLOSED = 141


def run_command(command: Callable[[], int]) -> int:
    """Run a command-line action: a ``FlowholdError`` becomes one line on stderr and its exit
    code, Ctrl-C exits 130, an output file that cannot be written exits 2 naming it, a closed
    standard output (``| head``) ends quietly with 141, and any other exception is one line too
    (FLOWHOLD_DEBUG=1 re-raises it to show the traceback). The one place where exceptions become
    exit codes."""
    try:
        code = int(command())
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return code
    except FlowholdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return int(exc.exit_code)
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
        return int(ExitCode.INTERRUPTED)
    except BrokenPipeError:
        if _stdout_closed():
            _silence_stdout()
            return int(ExitCode.PIPE_CLOSED)
        if os.environ.get("FLOWHOLD_DEBUG"):
            raise
        print("error: BrokenPipeError: a connection was closed by the other end", file=sys.stderr)
        return int(ExitCode.FAILURE)
    except OSError as exc:
        if os.environ.get("FLOWHOLD_DEBUG"):
            raise
        if exc.filename is not None:  # a file or folder named on the command line
            print(f"error: cannot use {exc.filename}: {exc.strerror or exc}", file=sys.stderr)
            return int(ExitCode.USAGE)
        print(f"error: {type(exc).__name__}: {exc} (set FLOWHOLD_DEBUG=1 for details)", file=sys.stderr)
        return int(ExitCode.FAILURE)
    except Exception as exc:  # noqa: BLE001 - the last line of defence: one line, no traceback
        if os.environ.get("FLOWHOLD_DEBUG"):
            raise
        print(f"error: {type(exc).__name__}: {exc} (set FLOWHOLD_DEBUG=1 for details)", file=sys.stderr)
        return int(ExitCode.FAILURE)


def _stdout_closed() -> bool:
    """Whether standard output is a pipe whose reader has gone (POLLERR on its descriptor)."""
    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        return any(ev & select.POLLERR for _fd, ev in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # no descriptor (captured) or no poll: assume it was
        return True


def _silence_stdout() -> None:
    """Point standard output at /dev/null, so the interpreter's last flush finds no broken pipe."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (AttributeError, OSError, ValueError):
        pass


def output_error(what: str, path: str | Path, exc: OSError) -> UsageError:
    """The one line for an output that cannot be written: ``--csv: cannot write PATH: reason``."""
    return UsageError(f"{what}: cannot write {path}: {exc.strerror or exc}")


def check_output(path: str | Path, what: str, *, folder: bool = False) -> Path:
    """Fail before any work is done when an output cannot be written (UsageError, exit code 2,
    naming the option and the reason). Creates the missing parent folders (or the folder itself
    with ``folder``) and tries the file for appending, removing it again if it was not there."""
    p = Path(path)
    try:
        if folder:
            p.mkdir(parents=True, exist_ok=True)
            probe = p / f".flowhold-write-test-{os.getpid()}"
            probe.touch()
            probe.unlink()
            return p
        if p.is_dir():
            raise IsADirectoryError(errno.EISDIR, "is a folder", str(p))
        existing = next((a for a in p.parents if a.exists()), None)
        if existing is not None and not existing.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, f"{existing} is a file, not a folder", str(p))
        p.parent.mkdir(parents=True, exist_ok=True)
        existed = p.exists()
        with open(p, "ab"):
            pass
        if not existed:
            p.unlink()
    except OSError as exc:
        raise output_error(what, p, exc) from None
    return p


@contextlib.contextmanager
def writing(what: str, path: str | Path) -> Iterator[None]:
    """Turn an OSError while writing the output ``path`` into ``output_error``."""
    try:
        yield
    except BrokenPipeError:
        raise
    except OSError as exc:
        raise output_error(what, path, exc) from None


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
