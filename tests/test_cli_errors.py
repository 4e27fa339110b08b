"""Command lines a first-time user gets wrong (issue 14): each ends within seconds in one line on
stderr and a documented exit code (``companion.errors.ExitCode``), never a traceback, a hang
or a line printed by a library."""

from __future__ import annotations

import re
import socket
import subprocess
import time

import pytest
from loop_helpers import PY, REPO

from companion.errors import ExitCode, LinkError
from companion.mavlink import link


def _run(*argv: str, timeout_s: float = 60.0, **kwargs) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    r = subprocess.run([PY, *argv], capture_output=True, text=True, timeout=timeout_s, cwd=REPO, **kwargs)
    return r, time.monotonic() - t0


def _one_line(r: subprocess.CompletedProcess) -> str:
    err = r.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, r.stderr
    return err


def _closed_tcp_port() -> int:
    """A loopback TCP port nothing listens on (connections to it are refused)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize("url,needle", [
    ("udpout:notahost.invalid:14550", "unknown host 'notahost.invalid'"),
    ("udpout:999.1.1.1:14550", "unknown host '999.1.1.1'"),
    ("udpin:nohost.invalid:14550", "unknown host 'nohost.invalid'"),
])
def test_run_with_an_unknown_host_fails_at_once(url, needle):
    """It used to wait forever for a HEARTBEAT that could never come."""
    r, took = _run("-m", "companion", "run", "--connect", url)
    assert r.returncode == ExitCode.LINK
    assert needle in _one_line(r) and url in r.stderr
    assert took < 20.0
    assert r.stdout == ""


def test_run_against_a_refused_tcp_port_prints_only_our_line():
    """pymavlink printed "[Errno 111] Connection refused sleeping" (twice) before our error."""
    url = f"tcp:127.0.0.1:{_closed_tcp_port()}"
    r, took = _run("-m", "companion", "run", "--connect", url)
    assert r.returncode == ExitCode.LINK
    assert _one_line(r) == f"error: cannot open {url}: Connection refused"
    assert "sleeping" not in r.stdout + r.stderr and r.stdout == ""
    assert took < 20.0


def test_run_ends_when_the_tcp_peer_closes():
    """A TCP peer that accepts and closes: pymavlink printed "EOF on TCP socket" in a loop while the
    companion waited the full connect timeout; now one line, exit code 5."""
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]
    try:
        p = subprocess.Popen([PY, "-m", "companion", "run", "--connect", f"tcp:127.0.0.1:{port}"], cwd=REPO,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            srv.settimeout(30)
            conn, _ = srv.accept()
            conn.close()
            out, err = p.communicate(timeout=30)
        finally:
            if p.poll() is None:
                p.kill()
                p.communicate()
    finally:
        srv.close()
    assert p.returncode == ExitCode.LINK
    # closed (FIN) or reset (RST: our HEARTBEAT was unread when it closed), depending on timing
    assert re.fullmatch(rf"error: the connection tcp:127\.0\.0\.1:{port} was (closed|reset) by the other end",
                        err.strip()), err
    assert "EOF" not in out


def test_a_resolver_that_hangs_is_given_up_on():
    """A DNS that never answers must not hang the companion (the lookup runs in a thread)."""
    def hung(*_args):
        time.sleep(5)

    t0 = time.monotonic()
    with pytest.raises(LinkError, match="did not resolve within 0.2 s"):
        link.resolve_host("slow.example", 14550, timeout_s=0.2, resolver=hung)
    assert time.monotonic() - t0 < 2.0
    assert link.resolve_host("127.0.0.1", 14550) == "127.0.0.1"


@pytest.fixture(scope="module")
def step_tlog(tmp_path_factory):
    """The step scenario's recording (15 s), made by the command line."""
    path = tmp_path_factory.mktemp("rec") / "step.tlog"
    r, _ = _run("-m", "simvehicle", "scenario", "step", "--tlog", str(path))
    assert r.returncode == 0, r.stderr
    return path


#: an output path that cannot be written: its parent is a regular file (and /proc refuses files)
_BAD = ["{rec}/out", "/proc/flowhold-test-output"]


@pytest.mark.parametrize("bad", _BAD)
@pytest.mark.parametrize("argv,flag", [
    (["-m", "companion", "replay", "{rec}", "--csv", "{bad}.csv"], "--csv"),
    (["-m", "companion", "replay", "{rec}", "--csv", "{tmp}/ok.csv", "--plot", "{bad}.png"], "--plot"),
    (["-m", "companion", "info", "{rec}", "--json", "{bad}.json"], "--json"),
    (["-m", "companion", "run", "--connect", "udpout:127.0.0.1:9", "--tlog", "{bad}.tlog"], "--tlog"),
    (["-m", "simvehicle", "scenario", "step", "--tlog", "{bad}.tlog"], "--tlog"),
    (["-m", "simvehicle", "scenario", "rail", "--plot", "{bad}.png"], "--plot"),
    (["-m", "simvehicle", "scenario", "rail", "--json", "{bad}.json"], "--json"),
    (["-m", "simvehicle", "serve", "--listen", "127.0.0.1:0", "--tlog", "{bad}.tlog"], "--tlog"),
    (["-m", "simvehicle", "sweep", "configs/sweeps/altitude_q.toml", "--out", "{bad}"], "--out"),
])
def test_an_unwritable_output_is_one_line_and_exit_code_2(step_tlog, tmp_path, argv, flag, bad):
    """``replay REC --csv /proc/o.csv`` gave "FileNotFoundError ..." and exit code 1 (not a documented
    code), after the whole replay. Every output option is tried before any work: one line naming
    the option, the path and the reason; exit code 2 (README: usage)."""
    bad = bad.format(rec=step_tlog)
    args = [a.format(rec=step_tlog, bad=bad, tmp=tmp_path) for a in argv]
    r, took = _run(*args)
    assert r.returncode == ExitCode.USAGE, r.stderr
    line = _one_line(r)
    assert line.startswith(f"error: {flag}: cannot write {bad}"), line
    assert took < 30.0


def test_an_unwritable_output_of_diagnose_is_one_line_and_exit_code_2(step_tlog):
    """``diagnose`` (its module is being rewritten) is covered by the last line of defence: an OSError
    naming a file is one line and exit code 2."""
    bad = f"{step_tlog}/report.json"
    r, _ = _run("-m", "companion", "diagnose", str(step_tlog), "--json", bad, timeout_s=300)
    assert r.returncode == ExitCode.USAGE
    assert _one_line(r) == f"error: cannot use {bad}: Not a directory"


@pytest.mark.parametrize("argv", [
    ["-m", "companion", "info", "{rec}"],
    ["-m", "simvehicle", "scenario", "rail", "--json", "-"],
])
def test_a_closed_standard_output_ends_quietly(step_tlog, argv):
    """``python -m companion info REC | head -1`` ended with a BrokenPipeError. The reader is gone
    before anything is written here (the worst case of ``| head``): nothing on stderr, exit code 141
    (128 + SIGPIPE, what a C tool ends with)."""
    p = subprocess.Popen([PY, *[a.format(rec=step_tlog) for a in argv]], cwd=REPO, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    p.stdout.close()
    try:
        err = p.stderr.read()
        rc = p.wait(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        p.stderr.close()
    assert err == ""
    assert rc == ExitCode.PIPE_CLOSED


def test_run_command_maps_errors_to_documented_codes(capsys):
    from companion.errors import run_command

    def missing() -> int:
        raise FileNotFoundError(2, "No such file or directory", "/nowhere/x.json")

    assert run_command(missing) == ExitCode.USAGE
    assert capsys.readouterr().err == "error: cannot use /nowhere/x.json: No such file or directory\n"
    assert {int(c) for c in ExitCode} == {0, 1, 2, 3, 4, 5, 130, 141}
