"""MAVLink link plumbing shared by the companion and the simulated vehicle.

Opening a connection from a pymavlink URL (with one clear error when it cannot be opened),
MAVLink 2 signing keys, ArduCopter's mode numbers, and small command helpers. No control
logic lives here; times are passed in.

URLs (what ``python -m companion run --connect`` takes, as pymavlink does):
``udpout:HOST:PORT`` (we send first; the usual way to reach the simulated vehicle),
``udpin:HOST:PORT`` (we listen), ``udp:HOST:PORT`` (listen), ``tcp:HOST:PORT``, ``tcpin:HOST:PORT``,
and a serial device with its baud rate: ``/dev/ttyUSB0,921600`` (``COM3,57600`` on Windows).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import io
import math
import os
import re
import socket
import struct
import sys
import threading
import time
import types
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink.mavutil picks its dialect: MAVLink 2

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

from companion.errors import LinkError, UsageError  # noqa: E402
from companion.mavlink_ids import GUIDED_NOGPS as GUIDED_NOGPS  # noqa: E402  (link.GUIDED_NOGPS, re-exported)
from companion.recordings.tlog_writer import SIM_CLOCK_TEXT  # noqa: E402

#: ArduCopter's flight modes by custom_mode number (the ones a GCS names)
COPTER_MODES = {0: "STABILIZE", 1: "ACRO", 2: "ALT_HOLD", 3: "AUTO", 4: "GUIDED", 5: "LOITER", 6: "RTL",
                7: "CIRCLE", 9: "LAND", 11: "DRIFT", 13: "SPORT", 14: "FLIP", 15: "AUTOTUNE", 16: "POSHOLD",
                17: "BRAKE", 18: "THROW", 19: "AVOID_ADSB", 20: "GUIDED_NOGPS", 21: "SMART_RTL"}
ARM_MAGIC_FORCE = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2 that skips pre-arm checks
#: 10 µs ticks from 2015-01-01 to now: the MAVLink 2 signing timestamp
SIGNING_EPOCH_S = 1_420_070_400

_SERIAL_RE = re.compile(r"^(?P<dev>(/dev/[^,]+|COM\d+))(,(?P<baud>\d+))?$")
_NET_PREFIXES = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:")


def mode_name(custom_mode: int) -> str:
    """ArduCopter's name for a custom_mode number (``MODE<n>`` if unknown)."""
    return COPTER_MODES.get(int(custom_mode), f"MODE{int(custom_mode)}")


def parse_host_port(text: str, *, what: str = "address") -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); port 0 means "any free port". UsageError if malformed."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise UsageError(f"{what}: expected HOST:PORT (e.g. 127.0.0.1:14550), got {text!r}")
    return host, int(port)


def check_url(url: str) -> None:
    """Reject what pymavlink would misread (a typo would otherwise be opened as a log file)."""
    if url.startswith(_NET_PREFIXES):
        rest = url.split(":", 1)[1]
        parse_host_port(rest, what=f"--connect {url}")
        return
    if _SERIAL_RE.match(url):
        return
    raise UsageError(f"--connect: not a MAVLink URL: {url!r} (use udpout:HOST:PORT, udpin:HOST:PORT, "
                     "tcp:HOST:PORT or a serial device such as /dev/ttyUSB0,921600)")


#: seconds a host name may take to resolve before ``open_connection`` gives up
RESOLVE_TIMEOUT_S = 5.0
#: seconds a TCP connection may take to be accepted
TCP_CONNECT_TIMEOUT_S = 5.0


def resolve_host(host: str, port: int, *, timeout_s: float = RESOLVE_TIMEOUT_S,
                 resolver: Callable[..., Any] = socket.getaddrinfo) -> str:
    """The IPv4 address of ``host`` (pymavlink's sockets are IPv4), or LinkError naming it: an
    unknown host, a malformed address (``999.1.1.1``) or a resolver that does not answer within
    ``timeout_s`` (the lookup runs in a thread, so a hung DNS cannot hang the caller)."""
    result: dict[str, Any] = {}

    def lookup() -> None:
        try:
            result["infos"] = resolver(host, port, socket.AF_INET, socket.SOCK_DGRAM)
        except Exception as exc:  # noqa: BLE001 - reported below as one line
            result["error"] = exc

    worker = threading.Thread(target=lookup, name="resolve-host", daemon=True)
    worker.start()
    worker.join(timeout_s)
    if worker.is_alive():
        raise LinkError(f"host {host!r} did not resolve within {timeout_s:g} s")
    if "error" in result:
        exc = result["error"]
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise LinkError(f"unknown host {host!r} ({why})")
    infos = result.get("infos") or []
    if not infos:
        raise LinkError(f"unknown host {host!r} (no IPv4 address)")
    return str(infos[0][4][0])


def _check_reachable(address: str, port: int) -> None:
    """LinkError when the system has no route to ``address`` (a UDP connect sends nothing)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect((address, port))
        except OSError as exc:
            raise LinkError(f"cannot reach {address}:{port}: {exc.strerror or exc}") from None


def open_connection(url: str, *, source_system: int, source_component: int) -> Any:
    """Open a pymavlink connection (MAVLink 2, ardupilotmega dialect). LinkError (one line, no
    output from pymavlink) if it fails: an unknown or unreachable host, a refused or unanswered
    TCP connection, a serial device that cannot be opened."""
    check_url(url)
    kwargs: dict[str, Any] = {"source_system": source_system, "source_component": source_component,
                              "dialect": "ardupilotmega", "autoreconnect": False}
    device = url
    m = _SERIAL_RE.match(url)
    if m:
        device = m.group("dev")
        kwargs["baud"] = int(m.group("baud") or 115200)
    timeout: float | None = None
    try:
        if url.startswith(_NET_PREFIXES):
            kind, rest = url.split(":", 1)
            host, port = parse_host_port(rest)
            address = resolve_host(host, port)
            if kind in ("udpout", "udpbcast", "tcp"):
                _check_reachable(address, port)
            if kind == "tcp":
                kwargs["retries"] = 0  # one attempt, no "sleeping" lines from pymavlink's retries
                timeout = TCP_CONNECT_TIMEOUT_S
    except LinkError as exc:
        raise LinkError(f"cannot open {url}: {exc}") from None
    previous = socket.getdefaulttimeout()
    try:
        socket.setdefaulttimeout(timeout)  # a TCP peer that never answers: give up after the timeout
        with contextlib.redirect_stdout(io.StringIO()):  # pymavlink prints its connection errors
            conn = mavutil.mavlink_connection(device, **kwargs)
    except Exception as exc:  # noqa: BLE001 - socket, serial and resolver errors alike: one line
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else (str(exc) or type(exc).__name__)
        raise LinkError(f"cannot open {url}: {why}") from None
    finally:
        socket.setdefaulttimeout(previous)
    conn.mav.robust_parsing = True
    enable_arrival_stamps(conn)
    if isinstance(conn, mavutil.mavtcp):
        # pymavlink prints "EOF on TCP socket" on every read once the peer has gone: note it instead
        conn.handle_eof = lambda: _note_closed(conn, "closed by the other end")
        conn.handle_disconnect = lambda: _note_closed(conn, "reset by the other end")
    return conn


def _note_closed(conn: Any, why: str) -> None:
    conn.flowhold_closed = why


def closed_reason(conn: Any) -> str | None:
    """Why a stream connection (TCP) has ended, or None while it is open (UDP never ends)."""
    return getattr(conn, "flowhold_closed", None)


def signing_key(text: str) -> bytes:
    """The 32-byte MAVLink 2 signing key from ``--signing-key``.

    A path to a file: its content (32 raw bytes, 64 hex digits, or a passphrase in the file);
    anything else is a passphrase. A passphrase becomes ``sha256(passphrase)``, as MAVProxy's
    ``signing setup`` does, so the same passphrase works in MAVProxy, the companion and the vehicle.
    """
    p = Path(text)
    if p.is_file():
        data = p.read_bytes()
        if len(data) == 32:
            return data
        stripped = data.strip()
        if re.fullmatch(rb"[0-9a-fA-F]{64}", stripped):
            return bytes.fromhex(stripped.decode())
        text = stripped.decode(errors="replace")
    if not text:
        raise UsageError("--signing-key: empty passphrase")
    return hashlib.sha256(text.encode()).digest()


def signing_timestamp(unix_s: float) -> int:
    """MAVLink 2 signing timestamp (10 µs units since 2015-01-01) of a UNIX time."""
    return int(max(unix_s - SIGNING_EPOCH_S, 0.0) * 100_000)


def setup_signing(mavobj: Any, key: bytes, *, unix_s: float | None = None, link_id: int = 0,
                  sign_outgoing: bool = True) -> None:
    """Sign outgoing packets with ``key`` and reject unsigned or badly signed incoming ones.

    ``mavobj``: a pymavlink ``MAVLink`` object (``conn.mav``, or the vehicle's encoder and
    per-peer parsers). ``unix_s``: the wall time that starts the signing clock (now if None).
    """
    s = mavobj.signing
    s.secret_key = key
    s.sign_outgoing = sign_outgoing
    s.allow_unsigned_callback = None
    s.link_id = link_id
    s.timestamp = signing_timestamp(time.time() if unix_s is None else unix_s)
    mavobj.check_signature = types.MethodType(_check_signature, mavobj)


def _check_signature(mavobj: Any, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
    """pymavlink's signature check, except that only a packet whose signature is good moves its
    stream's replay timestamp on. (pymavlink 2.4.50 stores the timestamp before it compares the
    signature, so one forged packet stamped in the future would lock a genuine sender out.)"""
    streams = mavobj.signing.stream_timestamps
    stream = (msgbuf[-13], src_system, src_component)
    before = streams.get(stream)
    ok = bool(type(mavobj).check_signature(mavobj, msgbuf, src_system, src_component))
    if not ok:
        if before is None:
            streams.pop(stream, None)
        else:
            streams[stream] = before
    return ok


#: a received UDP datagram longer than this (bytes) is dropped unread: a MAVLink 2 packet is at
#: most 280 bytes, and links batch packets up to an MTU (about 1500 bytes)
MAX_DATAGRAM_IN = 8192
#: BAD_DATA reason pymavlink gives a packet refused by signing (unsigned, wrong key, replayed)
SIGNATURE_REJECTED = "Invalid signature"


def bad_data_kind(msg: Any) -> str:
    """The counter a BAD_DATA message goes to: a packet refused by MAVLink 2 signing, or
    bytes that are not a valid packet (bad CRC, bad header, garbage)."""
    if getattr(msg, "reason", "") == SIGNATURE_REJECTED:
        return "packets rejected: unsigned or badly signed"
    return "bad packets"


def discard_partial(mavobj: Any) -> int:
    """Forget the unfinished packet a parser holds at the end of a UDP datagram; returns the
    number of bytes dropped.

    A MAVLink packet never spans two datagrams, so bytes left over when a datagram has been
    parsed are the start of a damaged or truncated packet. Left in the parser they would be
    joined to the next datagram and cost its (good) packets too.
    """
    n = int(mavobj.buf_len())
    if n:
        mavobj.buf = bytearray()
        mavobj.buf_index = 0
        mavobj.expected_length = mav.HEADER_LEN_V1 + 2
    return n


def is_datagram_link(conn: Any) -> bool:
    """Whether each read of ``conn`` is one whole UDP datagram (udpin/udpout/udp/udpbcast)."""
    return isinstance(conn, mavutil.mavudp | mavutil.mavmcast)


@dataclass(frozen=True)
class Datagram:
    """What one UDP datagram held: its messages (BAD_DATA included, in order), the bytes of an
    unfinished packet dropped at its end, whether it was dropped unread as oversized, and when
    the kernel received it (UNIX time, s; None when the link does not say)."""

    messages: list[Any]
    partial_bytes: int = 0
    oversized: bool = False
    arrival_unix_s: float | None = None


#: Linux ``SO_TIMESTAMPNS`` (also the control message's type, ``SCM_TIMESTAMPNS``): the kernel
#: stamps each datagram when it arrives (``CLOCK_REALTIME``, a ``struct timespec``)
SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@qq")


def enable_arrival_stamps(conn: Any) -> bool:
    """Ask the kernel to stamp each datagram of a UDP connection on arrival (Linux), so that a
    reader knows how long a datagram waited in the socket (a stalled reader's backlog). Returns
    whether ``read_datagram`` will report arrival times for ``conn``."""
    if not isinstance(conn, mavutil.mavudp) or not sys.platform.startswith("linux"):
        return False
    try:
        conn.port.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    except OSError:
        return False
    conn.flowhold_arrival_stamps = True
    return True


def _recv_stamped(conn: Any) -> tuple[bytes, float | None]:
    """``mavutil.mavudp.recv`` with the kernel's arrival stamp (UNIX time, s, or None)."""
    try:
        data, ancillary, _flags, addr = conn.port.recvmsg(mavutil.UDP_MAX_PACKET_LEN, socket.CMSG_SPACE(_TIMESPEC.size))
    except OSError as e:
        if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
            return b"", None
        raise
    if conn.udp_server:  # as mavudp.recv keeps its peers
        conn.clients.add(addr)
        conn.clients_last_alive[addr] = time.time()
    elif conn.broadcast:
        conn.last_address = addr
    stamp = None
    for level, kind, payload in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(payload)
            stamp = sec + nsec * 1e-9
    return data, stamp


def read_datagram(conn: Any) -> Datagram | None:
    """Read one datagram from a UDP pymavlink connection (None when none is waiting). A
    datagram longer than ``MAX_DATAGRAM_IN`` is dropped unread. Messages are posted to the
    connection as ``recv_msg`` does (its per-system state). The kernel's arrival stamp comes with
    it when ``enable_arrival_stamps`` was granted."""
    if getattr(conn, "flowhold_arrival_stamps", False):
        data, stamp = _recv_stamped(conn)
    else:
        data, stamp = conn.recv(), None
    if not data:
        return None
    if len(data) > MAX_DATAGRAM_IN:
        return Datagram([], oversized=True, arrival_unix_s=stamp)
    if conn.first_byte:
        conn.auto_mavlink_version(data)
    msgs = conn.mav.parse_buffer(data) or []
    dropped = discard_partial(conn.mav)
    for m in msgs:
        conn.post_message(m)
    return Datagram(msgs, dropped, arrival_unix_s=stamp)


@dataclass
class ClockMapping:
    """The vehicle's clock seen from the companion's: how old a sample the vehicle stamped is.

    The vehicle's time now is taken from the newest sample heard: its time, plus ``rate`` times
    the local time since it arrived (``rate`` 1 for a vehicle on the wall clock; X for a simulator
    at speed-up X; 0 for a lockstep simulator, whose clock stands until the companion answers).
    The age of a sample is that minus its time. Extrapolating only from the newest sample keeps
    the mapping free of the vehicle's clock rate and of the link's latency, both of which may
    drift; what it measures is what matters: how long a sample waited before being used, in the
    socket (``arrival_s``, the kernel's stamp where the link has one) and behind the newer samples
    already heard.

    A sample more than ``jump_s`` behind the newest (a vehicle reboot) or ahead of the vehicle's
    time now (a clock that cannot have run so far) is a jump: taken only when the next sample
    agrees with it (within ``jump_s``), so that one bogus time cannot make every frame look old.
    Times are passed in (s); arrival times are on the companion's monotonic clock.
    """

    rate: float = 1.0
    jump_s: float = 1.0
    #: the newest vehicle time heard (s), and the local time it arrived
    newest_s: float | None = None
    arrival_s: float = math.nan
    #: a jump waiting for a second sample to agree: (vehicle time, arrival)
    candidate: tuple[float, float] | None = None

    def observe(self, vehicle_s: float, arrival_s: float) -> None:
        """A sample stamped ``vehicle_s`` by the vehicle arrived at local time ``arrival_s``."""
        if not (math.isfinite(vehicle_s) and math.isfinite(arrival_s)):
            return
        now = self.vehicle_now_s(arrival_s)
        if now is None:
            self.newest_s, self.arrival_s = vehicle_s, arrival_s
            return
        assert self.newest_s is not None
        if self.newest_s - self.jump_s <= vehicle_s <= now + self.jump_s:
            self.candidate = None
            if vehicle_s > self.newest_s:
                self.newest_s, self.arrival_s = vehicle_s, arrival_s
            return
        if self.candidate is not None and abs(vehicle_s - self.candidate[0]) <= self.jump_s:
            self.newest_s, self.arrival_s = vehicle_s, arrival_s  # two samples agree: the clock jumped
            self.candidate = None
        else:
            self.candidate = (vehicle_s, arrival_s)

    def vehicle_now_s(self, local_s: float) -> float | None:
        """The vehicle's time at local time ``local_s`` (None before any sample)."""
        if self.newest_s is None:
            return None
        return self.newest_s + self.rate * max(0.0, local_s - self.arrival_s)

    def age_s(self, vehicle_s: float, local_s: float) -> float:
        """How old, at local time ``local_s``, a sample stamped ``vehicle_s`` is (s, >= 0; 0 when
        nothing is known, or for a time that is not a number)."""
        now = self.vehicle_now_s(local_s)
        if now is None or not math.isfinite(vehicle_s):
            return 0.0
        return max(0.0, now - vehicle_s)

    def set_clock_text(self, text: str) -> bool:
        """Take the rate from a simulator's clock notice ("simulated clock (lockstep)", "(speedup
        x4)"); returns whether ``text`` was one."""
        if SIM_CLOCK_TEXT not in text:
            return False
        if "lockstep" in text:
            self.rate = 0.0
        else:
            m = re.search(r"speedup x([0-9.eE+-]+)", text)
            try:
                rate = float(m.group(1)) if m else 1.0
            except ValueError:
                rate = 1.0
            self.rate = rate if math.isfinite(rate) and rate > 0.0 else 1.0
        return True


def is_vehicle_heartbeat(msg: Any) -> bool:
    """A HEARTBEAT from an autopilot (not a GCS, companion, gimbal or ADS-B receiver)."""
    if msg.get_type() != "HEARTBEAT":
        return False
    if msg.type in (mav.MAV_TYPE_GCS, mav.MAV_TYPE_GIMBAL, mav.MAV_TYPE_ADSB, mav.MAV_TYPE_ONBOARD_CONTROLLER):
        return False
    return msg.autopilot != mav.MAV_AUTOPILOT_INVALID


def heartbeat_armed(msg: Any) -> bool:
    return bool(msg.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)


def command_long(enc: Any, target_system: int, target_component: int, command: int, *params: float) -> Any:
    """A COMMAND_LONG with up to seven parameters (the rest 0)."""
    p = [float(v) for v in params] + [0.0] * (7 - len(params))
    return enc.command_long_encode(target_system, target_component, command, 0, *p[:7])


def set_message_interval(enc: Any, target_system: int, message_id: int, interval_s: float,
                         target_component: int = 1) -> Any:
    """MAV_CMD_SET_MESSAGE_INTERVAL: stream ``message_id`` every ``interval_s`` seconds
    (``interval_s < 0``: stop it; 0: the vehicle's default)."""
    us = -1 if interval_s < 0 else int(round(interval_s * 1e6))
    return command_long(enc, target_system, target_component, mav.MAV_CMD_SET_MESSAGE_INTERVAL, message_id, us)


def statustext(enc: Any, text: str, severity: int) -> Any:
    """STATUSTEXT, cut to the 50 characters the message carries."""
    return enc.statustext_encode(severity, text.encode("ascii", "replace")[:50])
