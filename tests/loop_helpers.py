"""Test harness for the MAVLink loop: start the vehicle and the companion as a user would
(``python -m simvehicle serve``, ``python -m companion run``), and a small ground station.

Every wait has a timeout; every process is stopped in a ``finally`` (``Procs``). Ports come
from the vehicle itself (``--listen 127.0.0.1:0`` binds a free one and prints it), so parallel
runs never collide. Output goes to files (a full pipe would block a child).
"""

from __future__ import annotations

import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from pymavlink import mavutil

import companion.mavlink.link  # sets MAVLINK20 (MAVLink 2) before any connection picks its dialect

REPO = Path(__file__).resolve().parent.parent
PY = sys.executable
mav = companion.mavlink.link.mav

#: generous: the machine may be shared and slow
START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 20.0


def free_udp_port() -> int:
    """A UDP port that was free a moment ago (for a companion started before its vehicle)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Proc:
    """A child process started as ``python -m ...`` in the repository, output to a file."""

    def __init__(self, args: list[str], log: Path, cwd: Path = REPO) -> None:
        self.args = args
        self.log = log
        self._fh = open(log, "w")  # noqa: SIM115 - closed in stop()/wait()
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
        self.p = subprocess.Popen([PY, *args], cwd=cwd, stdout=self._fh, stderr=subprocess.STDOUT, env=env)

    def text(self) -> str:
        try:
            return self.log.read_text()
        except OSError:
            return ""

    def wait_for(self, pattern: str, timeout_s: float = START_TIMEOUT_S) -> re.Match[str]:
        """The first match of ``pattern`` in the output; AssertionError if it never comes."""
        deadline = time.monotonic() + timeout_s
        while True:
            m = re.search(pattern, self.text())
            if m:
                return m
            if self.p.poll() is not None:
                raise AssertionError(f"{' '.join(self.args[:3])} exited ({self.p.returncode}) before "
                                     f"{pattern!r}:\n{self.text()[-3000:]}")
            if time.monotonic() > deadline:
                raise AssertionError(f"no {pattern!r} within {timeout_s} s:\n{self.text()[-3000:]}")
            time.sleep(0.05)

    def wait(self, timeout_s: float) -> int:
        """Wait for the process to end by itself; kill it and fail if it does not."""
        try:
            rc = self.p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"{' '.join(self.args[:3])} still running after {timeout_s} s:\n"
                                 f"{self.text()[-3000:]}") from None
        self._fh.close()
        return rc

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
        """Ask it to stop (Ctrl-C by default); kill it if it does not. Returns its exit code
        (None when it had to be killed)."""
        if self.p.poll() is None:
            self.p.send_signal(sig)
            try:
                self.p.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.kill()
                return None
        self._fh.close()
        return self.p.returncode

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait(timeout=STOP_TIMEOUT_S)
        self._fh.close()


class Procs:
    """Context manager that stops every process started through it, whatever happens."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: list[Proc] = []

    def __enter__(self) -> Procs:
        return self

    def __exit__(self, *exc: Any) -> None:
        for p in reversed(self.procs):
            p.stop(timeout_s=5.0)

    def vehicle(self, *args: str, name: str = "vehicle", port: int = 0) -> tuple[Proc, int]:
        """``python -m simvehicle serve --listen 127.0.0.1:PORT ARGS``; returns (proc, bound port)."""
        p = Proc(["-m", "simvehicle", "serve", "--listen", f"127.0.0.1:{port}", *args], self.tmp / f"{name}.log")
        self.procs.append(p)
        m = p.wait_for(r"listening on udp 127\.0\.0\.1:(\d+)")
        return p, int(m.group(1))

    def companion(self, port: int, *args: str, name: str = "companion") -> Proc:
        """``python -m companion run --connect udpout:127.0.0.1:PORT ARGS``."""
        p = Proc(["-m", "companion", "run", "--connect", f"udpout:127.0.0.1:{port}", *args],
                 self.tmp / f"{name}.log")
        self.procs.append(p)
        return p

    def start(self, *args: str, name: str, cwd: Path | None = None) -> Proc:
        """``python ARGS`` (e.g. ``-m MAVProxy.mavproxy ...``), in ``cwd`` (default: the repository)."""
        p = Proc(list(args), self.tmp / f"{name}.log", cwd or REPO)
        self.procs.append(p)
        return p


class Gcs:
    """A minimal ground station on ``udpout:127.0.0.1:PORT`` (system 255, component 190).

    ``recv`` keeps the latest vehicle time (LOCAL_POSITION_NED / ATTITUDE ``time_boot_ms``)
    and every STATUSTEXT seen, whatever message it waits for.
    """

    def __init__(self, port: int, *, sysid: int = 255, compid: int = 190, key: bytes | None = None) -> None:
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=sysid,
                                               source_component=compid, dialect="ardupilotmega")
        if key is not None:
            companion.mavlink.link.setup_signing(self.conn.mav, key)
        self.vehicle_time_s = -math.inf
        self.statustexts: list[tuple[float, int, int, str]] = []  # (vehicle time, sysid, compid, text)
        self.heartbeat()

    def close(self) -> None:
        self.conn.close()

    def heartbeat(self) -> None:
        self.conn.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE)

    def _note(self, msg: Any) -> None:
        t = msg.get_type()
        if t in ("LOCAL_POSITION_NED", "ATTITUDE", "ATTITUDE_TARGET") and msg.get_srcComponent() == 1:
            self.vehicle_time_s = msg.time_boot_ms * 1e-3
        elif t == "STATUSTEXT":
            self.statustexts.append((self.vehicle_time_s, msg.get_srcSystem(), msg.get_srcComponent(), msg.text))

    def recv(self, types: str | Iterable[str] | None = None, *, timeout_s: float = 10.0,
             cond: Callable[[Any], bool] | None = None) -> Any:
        """The next message of ``types`` satisfying ``cond``; AssertionError after ``timeout_s``."""
        want = {types} if isinstance(types, str) else (set(types) if types is not None else None)
        deadline = time.monotonic() + timeout_s
        next_hb = time.monotonic() + 1.0
        while True:
            now = time.monotonic()
            if now > deadline:
                raise AssertionError(f"no {want} within {timeout_s} s (vehicle time {self.vehicle_time_s:.2f} s)")
            if now > next_hb:
                self.heartbeat()
                next_hb = now + 1.0
            msg = self.conn.recv_msg()
            if msg is None:
                self.conn.select(0.05)
                continue
            if msg.get_type() == "BAD_DATA":
                continue
            self._note(msg)
            if (want is None or msg.get_type() in want) and (cond is None or cond(msg)):
                return msg

    def drain(self, seconds: float) -> list[Any]:
        """Everything received for ``seconds`` of wall time."""
        out = []
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            msg = self.conn.recv_msg()
            if msg is None:
                self.conn.select(0.02)
                continue
            if msg.get_type() != "BAD_DATA":
                self._note(msg)
                out.append(msg)
        return out

    def wait_vehicle(self, timeout_s: float = START_TIMEOUT_S) -> Any:
        """The vehicle's HEARTBEAT."""
        return self.recv("HEARTBEAT", timeout_s=timeout_s, cond=lambda m: m.get_srcComponent() == 1)

    def wait_time(self, t_s: float, timeout_s: float = 60.0) -> float:
        """Receive until the vehicle's clock reaches ``t_s``; returns it."""
        self.recv(("LOCAL_POSITION_NED", "ATTITUDE", "ATTITUDE_TARGET"), timeout_s=timeout_s,
                  cond=lambda m: m.get_srcComponent() == 1 and m.time_boot_ms * 1e-3 >= t_s - 1e-9)
        return self.vehicle_time_s

    def wait_text(self, text: str, timeout_s: float = 30.0, since: int = 0) -> tuple[float, int, int, str]:
        """The first STATUSTEXT (from index ``since`` of ``statustexts``) containing ``text``."""
        deadline = time.monotonic() + timeout_s
        while True:
            for st in self.statustexts[since:]:
                if text in st[3]:
                    return st
            if time.monotonic() > deadline:
                raise AssertionError(f"no STATUSTEXT {text!r} within {timeout_s} s; got "
                                     f"{[s[3] for s in self.statustexts[since:]]}")
            self.drain(0.05)

    def recv_text(self, text: str, timeout_s: float = 30.0) -> Any:
        """Receive up to the STATUSTEXT containing ``text`` (later messages stay unread)."""
        return self.recv("STATUSTEXT", timeout_s=timeout_s, cond=lambda m: text in m.text)

    def set_interval(self, msg_id: int, interval_s: float) -> Any:
        """SET_MESSAGE_INTERVAL to the vehicle; returns its COMMAND_ACK."""
        self.conn.mav.send(companion.mavlink.link.set_message_interval(self.conn.mav, 1, msg_id, interval_s))
        return self.recv("COMMAND_ACK", cond=lambda m: m.command == mav.MAV_CMD_SET_MESSAGE_INTERVAL)

    def quiet(self, keep: dict[str, float] | None = None) -> None:
        """Turn the vehicle's streams to this GCS off, except ``keep`` (name -> rate Hz)."""
        keep = keep or {}
        for name in ("RAW_IMU", "DISTANCE_SENSOR", "OPTICAL_FLOW", "OPTICAL_FLOW_RAD", "ATTITUDE",
                     "LOCAL_POSITION_NED", "ATTITUDE_TARGET", "SYS_STATUS"):
            mid = getattr(mav, f"MAVLINK_MSG_ID_{name}")
            ack = self.set_interval(mid, 1.0 / keep[name] if name in keep else -1.0)
            assert ack.result == mav.MAV_RESULT_ACCEPTED, (name, ack)

    def set_param(self, name: str, value: float, timeout_s: float = 10.0) -> Any:
        """PARAM_SET; returns the PARAM_VALUE that answers it."""
        self.conn.mav.param_set_send(1, 1, name.encode(), float(value), mav.MAV_PARAM_TYPE_REAL32)
        return self.recv("PARAM_VALUE", timeout_s=timeout_s, cond=lambda m: m.param_id == name)

    def command(self, command: int, *params: float, timeout_s: float = 10.0) -> Any:
        self.conn.mav.send(companion.mavlink.link.command_long(self.conn.mav, 1, 1, command, *params))
        return self.recv("COMMAND_ACK", timeout_s=timeout_s, cond=lambda m: m.command == command)

    def velocity(self, vx_m_s: float, vy_m_s: float, *, frame: int = mav.MAV_FRAME_BODY_FRD) -> None:
        """SET_POSITION_TARGET_LOCAL_NED (velocity only) to the companion (1, 191)."""
        from companion.mavlink.outbound import VELOCITY_TYPE_MASK

        self.conn.mav.set_position_target_local_ned_send(0, 1, 191, frame, VELOCITY_TYPE_MASK, 0, 0, 0,
                                                         vx_m_s, vy_m_s, 0, 0, 0, 0, 0, 0)

    def sticks(self, x: int, y: int) -> None:
        """MANUAL_CONTROL x (forward) and y (right) in [-1000, 1000]."""
        self.conn.mav.manual_control_send(1, x, y, 500, 0, 0)
