"""Hostile links: the simulated vehicle and the companion keep running, and keep flying well,
under garbage datagrams, oversized datagrams and packets, floods at ten times the normal rate,
bad CRCs, messages from unexpected system ids, commands with non-finite or out-of-range fields
and MAVLink 2 signing failures; every refusal is counted where a user sees it (SYS_STATUS
``errors_comm`` / ``errors_count1``, the status line, the exit summaries).

Three layers:
- the vehicle's model (``simvehicle.server.server.Vehicle``) and its UDP adapter run in process on a
  free port, fed exact datagrams (exact counts, no timing);
- the companion (``python -m companion run``) against a hand-made vehicle on a socket
  (``FakeVehicle``) that sends the reference simulator's frames one at a time and puts hostile
  packets exactly between them, in lockstep with the companion's answers;
- the real pair (``python -m simvehicle serve`` + ``python -m companion run``, ``loop_helpers``)
  in real time while a hostile peer floods the vehicle.

Run time (2 shared cores): about 25 s.
"""

from __future__ import annotations

import math
import re
import socket
import time
from typing import Any

import numpy as np
import pytest
from loop_helpers import Gcs, Procs

from companion.config import Config
from companion.mavlink import link
from companion.mavlink.outbound import COMPANION_COMPONENT, VELOCITY_TYPE_MASK, quaternion_to_euler
from companion.step.profiles import Profile
from simvehicle.model import telemetry
from simvehicle.model.sim import Simulator
from simvehicle.server.server import MAX_DATAGRAM_IN, StreamSchedule, UdpVehicle, Vehicle

mav = link.mav
NAN, INF = math.nan, math.inf
TILT_LIMIT_RAD = math.radians(20.0)
SOCKET_TIMEOUT_S = 30.0


def packed(msg: Any, enc: Any) -> bytes:
    return bytes(msg.pack(enc))


def decoded(msg: Any, enc: Any) -> Any:
    """``msg`` as a receiver sees it (packed by ``enc``, then parsed: sender ids set)."""
    return mav.MAVLink(None).decode(bytearray(packed(msg, enc)))


def bad_crc(buf: bytes) -> bytes:
    """The packet with its checksum broken (last two bytes of an unsigned packet)."""
    return buf[:-2] + bytes([buf[-2] ^ 0x55, buf[-1]])


def long_prefix() -> bytes:
    """The start of a MAVLink 2 packet that claims a 255-byte payload, then nothing: a parser
    that kept it would swallow the next datagram into it."""
    return bytes([0xFD, 0xFF, 0, 0, 0, 1, 1, 0, 0, 0]) + b"\x00" * 20


def oversized_payload(enc: Any) -> bytes:
    """A HEARTBEAT whose length byte says 200 payload bytes (a HEARTBEAT has 9), with a valid CRC.
    MAVLink 2 lets a newer sender add extension fields, so a receiver decodes the fields it
    knows and ignores the rest: a valid packet."""
    payload = bytes(packed(enc.heartbeat_encode(6, 8, 0, 0, 0), enc))[10:-2] + b"\x00" * 191
    header = bytes([0xFD, len(payload), 0, 0, 0, enc.srcSystem, enc.srcComponent, 0, 0, 0])
    crc = mav.x25crc(header[1:] + payload)
    crc.accumulate(bytes([mav.MAVLink_heartbeat_message.crc_extra]))
    return header + payload + crc.crc.to_bytes(2, "little")


# ---------------------------------------------------------------------------------------------
# 1. The vehicle's model: commands with non-finite or out-of-range fields


def _armed_guided(cfg: Config) -> Vehicle:
    v = Vehicle(cfg)
    v.custom_mode, v.armed = link.GUIDED_NOGPS, True
    return v


GCS_ENC = mav.MAVLink(None, srcSystem=255, srcComponent=190)
COMMANDS = [
    ("set mode NaN", mav.MAV_CMD_DO_SET_MODE, (NAN, 20.0), mav.MAV_RESULT_DENIED),
    ("set mode inf", mav.MAV_CMD_DO_SET_MODE, (1.0, INF), mav.MAV_RESULT_DENIED),
    ("set mode fractional", mav.MAV_CMD_DO_SET_MODE, (1.0, 0.5), mav.MAV_RESULT_DENIED),
    ("arm NaN", mav.MAV_CMD_COMPONENT_ARM_DISARM, (NAN,), mav.MAV_RESULT_DENIED),
    ("arm 7", mav.MAV_CMD_COMPONENT_ARM_DISARM, (7.0,), mav.MAV_RESULT_DENIED),
    ("interval NaN id", mav.MAV_CMD_SET_MESSAGE_INTERVAL, (NAN, 20000.0), mav.MAV_RESULT_DENIED),
    ("interval inf", mav.MAV_CMD_SET_MESSAGE_INTERVAL, (30.0, INF), mav.MAV_RESULT_DENIED),
    ("interval unknown id", mav.MAV_CMD_SET_MESSAGE_INTERVAL, (1e9, 20000.0), mav.MAV_RESULT_DENIED),
    ("get interval NaN", mav.MAV_CMD_GET_MESSAGE_INTERVAL, (NAN,), mav.MAV_RESULT_DENIED),
    ("request message inf", mav.MAV_CMD_REQUEST_MESSAGE, (-INF,), mav.MAV_RESULT_UNSUPPORTED),
    ("request message 1e30", mav.MAV_CMD_REQUEST_MESSAGE, (1e30,), mav.MAV_RESULT_UNSUPPORTED),
    ("unknown command", 31999, (1.0,), mav.MAV_RESULT_UNSUPPORTED),
]


@pytest.mark.parametrize("what,command,params,result", COMMANDS, ids=[c[0] for c in COMMANDS])
def test_vehicle_refuses_bad_commands_with_an_ack_and_counts_them(paper_cfg, what, command, params, result):
    v = Vehicle(paper_cfg)
    streams = StreamSchedule(v.T)
    for make in (lambda: link.command_long(GCS_ENC, 1, 1, command, *params),
                 lambda: GCS_ENC.command_int_encode(1, 1, 0, command, 0, 0, *(list(params) + [0.0] * 4)[:4], 0, 0, 0)):
        replies = v.handle(decoded(make(), GCS_ENC), streams)
        ack = replies[0].msg
        assert ack.get_type() == "COMMAND_ACK" and ack.command == command and ack.result == result
        assert (ack.target_system, ack.target_component) == (255, 190)
    assert (v.armed, v.custom_mode, streams.intervals_s) == (False, 0, {})  # nothing changed
    assert v.refused == 2
    assert v.sys_status().errors_count1 == 2


@pytest.mark.parametrize("name,value", [("SIM_WIND_FX", NAN), ("SIM_WIND_FX", INF), ("SIM_WIND_FX", 1e30),
                                        ("ANGLE_MAX", 3000.5), ("NO_SUCH_PARAM", 1.0)])
def test_vehicle_refuses_bad_parameters_and_counts_them(paper_cfg, name, value):
    v = Vehicle(paper_cfg)
    before = dict(v.values)
    msg = decoded(GCS_ENC.param_set_encode(1, 1, name.encode(), value, mav.MAV_PARAM_TYPE_REAL32), GCS_ENC)
    replies = v.handle(msg, StreamSchedule(v.T))
    assert v.values == before
    assert any(r.msg.get_type() == "STATUSTEXT" for r in replies)  # says why
    if name in v.specs:  # the unchanged value is sent back
        assert [r.msg.param_value for r in replies if r.msg.get_type() == "PARAM_VALUE"] == [before[name]]
    assert v.refused == 1 and v.sys_status().errors_count1 == 1


def _target(q: list[float], thrust: float = 0.5, type_mask: int = 7) -> Any:
    return decoded(GCS_ENC.set_attitude_target_encode(0, 1, 1, type_mask, q, 0, 0, 0, thrust), GCS_ENC)


@pytest.mark.parametrize("what,q,thrust,type_mask", [
    ("q NaN", [NAN, 0, 0, 0], 0.5, 7),
    ("q inf", [1, INF, 0, 0], 0.5, 7),
    ("q zero", [0, 0, 0, 0], 0.5, 7),
    ("q not unit", [2, 0, 0, 0], 0.5, 7),
    ("thrust NaN", [1, 0, 0, 0], NAN, 7),
    ("thrust 3", [1, 0, 0, 0], 3.0, 7),
    ("thrust -1", [1, 0, 0, 0], -1.0, 7),
    ("attitude ignored", [1, 0, 0, 0], 0.5, 7 | 128),
])
def test_vehicle_rejects_bad_attitude_targets_and_counts_them(paper_cfg, what, q, thrust, type_mask):
    v = _armed_guided(paper_cfg)
    v.handle(_target([0.9990482, 0.0436194, 0.0, 0.0]), StreamSchedule(v.T))  # 5 deg roll, accepted
    good = v.cmd_rad
    assert good[0] == pytest.approx(math.radians(5.0), abs=1e-6)
    v.handle(_target(q, thrust, type_mask), StreamSchedule(v.T))
    assert v.cmd_rad == good  # the last good target stays
    assert v.refused == 1 and v.counters["SET_ATTITUDE_TARGET accepted"] == 1


def test_vehicle_clamps_a_lean_beyond_angle_max(paper_cfg):
    v = _armed_guided(paper_cfg)
    roll = math.radians(80.0)
    v.handle(_target([math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0]), StreamSchedule(v.T))
    assert v.cmd_rad[0] == pytest.approx(math.radians(30.0))  # ANGLE_MAX 3000 cdeg
    assert v.refused == 0


# ---------------------------------------------------------------------------------------------
# 2. The vehicle's UDP adapter, in process: what is dropped on the link, and what survives


class InProcessVehicle:
    """A ``UdpVehicle`` on a free port driven by hand (``pump``), and a client socket."""

    def __init__(self, cfg: Config, key: bytes | None = None) -> None:
        self.v = Vehicle(cfg)
        self.u = UdpVehicle(self.v, "127.0.0.1", 0, key=key, log=lambda _s: None)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.parser = mav.MAVLink(None)
        self.parser.robust_parsing = True

    def close(self) -> None:
        self.sock.close()
        self.u.close()

    def send(self, *datagrams: bytes, sock: socket.socket | None = None) -> None:
        for d in datagrams:
            (sock or self.sock).sendto(d, self.u.address)
        self.u.pump(time.monotonic() + 0.05)  # the vehicle reads them

    def replies(self) -> list[Any]:
        out = []
        try:
            while True:
                data, _ = self.sock.recvfrom(65535)
                out += [m for m in self.parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]
        except (TimeoutError, BlockingIOError):
            return out


@pytest.fixture
def udp_vehicle(paper_cfg):
    iv = InProcessVehicle(paper_cfg)
    try:
        yield iv
    finally:
        iv.close()


def test_a_broken_datagram_never_costs_the_next_good_one(udp_vehicle):
    """Each garbage datagram ends in the start of a long packet; the PARAM_REQUEST_READ in the
    next datagram is still answered, every time (the vehicle parses each datagram on its own)."""
    iv = udp_vehicle
    req = packed(GCS_ENC.param_request_read_encode(1, 1, b"ANGLE_MAX", -1), GCS_ENC)
    for _ in range(20):
        iv.send(long_prefix(), req)
    answers = [m for m in iv.replies() if m.get_type() == "PARAM_VALUE"]
    assert len(answers) == 20 and all(m.param_id == "ANGLE_MAX" for m in answers)
    assert iv.u.counters["bad packets"] == 20
    assert iv.v.comm_errors == 20 and iv.v.sys_status().errors_comm == 20


def test_garbage_oversized_and_bad_crc_are_dropped_and_counted(udp_vehicle):
    iv = udp_vehicle
    rng = np.random.default_rng(3)
    hb = packed(GCS_ENC.heartbeat_encode(6, 8, 0, 0, 4), GCS_ENC)
    req = packed(GCS_ENC.param_request_read_encode(1, 1, b"ANGLE_MAX", -1), GCS_ENC)
    iv.send(hb)  # a peer
    iv.replies()
    junk = [rng.integers(0, 256, n, dtype=np.uint8).tobytes().replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x00")
            for n in (1, 40, 1400)]
    iv.send(*junk)  # no start byte at all: one "bad prefix" each
    iv.send(bad_crc(req), bad_crc(hb))
    iv.send(b"\xfd" * (MAX_DATAGRAM_IN + 1))  # one datagram larger than any link sends
    iv.send(hb[:7], req[:-3])  # truncated packets
    n_heard = len(iv.u.peers[iv.sock.getsockname()].seen)
    iv.send(oversized_payload(GCS_ENC))  # a longer payload than HEARTBEAT's: decoded, the rest ignored
    assert len(iv.u.peers[iv.sock.getsockname()].seen) == n_heard
    c = iv.u.counters
    assert c["oversized datagrams dropped"] == 1
    assert c["bad packets"] == 3 + 2 + 2
    assert iv.v.comm_errors == sum(c.values())
    assert not [m for m in iv.replies() if m.get_type() == "PARAM_VALUE"]  # the broken request did nothing
    iv.send(req)
    assert [m.param_id for m in iv.replies() if m.get_type() == "PARAM_VALUE"] == ["ANGLE_MAX"]  # still serving
    assert iv.v.sys_status().errors_comm == iv.v.comm_errors


def test_signed_vehicle_rejects_unsigned_wrongly_signed_and_replayed_packets(paper_cfg):
    key = link.signing_key("robust link test")
    iv = InProcessVehicle(paper_cfg, key=key)
    good = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    link.setup_signing(good, key)
    wrong = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    link.setup_signing(wrong, link.signing_key("not the key"))
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    attacker.bind(("127.0.0.1", 0))
    try:
        arm = link.command_long(GCS_ENC, 1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        wind = GCS_ENC.param_set_encode(1, 1, b"SIM_WIND_FX", 50.0, mav.MAV_PARAM_TYPE_REAL32)
        iv.send(packed(arm, GCS_ENC), packed(wind, GCS_ENC))  # unsigned
        iv.send(packed(link.command_long(wrong, 1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1), wrong),
                packed(wrong.param_set_encode(1, 1, b"SIM_WIND_FX", 50.0, mav.MAV_PARAM_TYPE_REAL32), wrong))
        assert not iv.v.armed and iv.v.values["SIM_WIND_FX"] == 0.0 and not iv.u.peers
        # a signed PARAM_SET is taken; the same bytes sent again (a replay, from another address) are not
        signed = packed(good.param_set_encode(1, 1, b"SIM_WIND_FX", 1.5, mav.MAV_PARAM_TYPE_REAL32), good)
        iv.send(signed)
        assert iv.v.values["SIM_WIND_FX"] == 1.5
        iv.send(packed(good.param_set_encode(1, 1, b"SIM_WIND_FX", 0.0, mav.MAV_PARAM_TYPE_REAL32), good))
        assert iv.v.values["SIM_WIND_FX"] == 0.0
        iv.send(signed, sock=attacker)
        iv.send(signed)
        assert iv.v.values["SIM_WIND_FX"] == 0.0
        assert iv.u.counters["packets rejected: unsigned or badly signed"] == 6
        assert iv.v.sys_status().errors_comm == 6
        assert len(iv.u.peers) == 1  # only the signed GCS is served
    finally:
        attacker.close()
        iv.close()


# ---------------------------------------------------------------------------------------------
# 3. The companion against a hand-made vehicle


class FakeVehicle:
    """A vehicle on a UDP socket, driven frame by frame by the test.

    ``step()`` sends the reference simulator's current frame (RAW_IMU, DISTANCE_SENSOR,
    OPTICAL_FLOW, ATTITUDE, LOCAL_POSITION_NED in one datagram), waits for the companion's
    SET_ATTITUDE_TARGET stamped with the frame's time (lockstep, up to ``wait_s``), and advances
    the simulator with the command received. Heartbeats say "armed, GUIDED_NOGPS"; COMMAND_LONGs
    are acknowledged. ``key``: sign what it sends and drop unsigned packets.
    """

    def __init__(self, cfg: Config, *, sysid: int = 1, key: bytes | None = None, wind_n: float = 2.0) -> None:
        self.cfg = cfg
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.enc = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
        self.parser = mav.MAVLink(None)
        self.parser.robust_parsing = True
        if key is not None:
            link.setup_signing(self.enc, key)
            link.setup_signing(self.parser, key, sign_outgoing=False)
        self.sim = Simulator(cfg, external_force=lambda _t: (-wind_n, wind_n))
        self.addr: tuple[str, int] | None = None
        self.received: list[Any] = []
        self.cmd = (0.0, 0.0)
        self.commands: list[tuple[int, float, float]] = []  # (time_boot_ms, roll, pitch) per frame answered
        self.missed = 0
        self.bad = 0  # packets from the companion this vehicle could not take (bad, or unsigned when signing)

    def close(self) -> None:
        self.sock.close()

    def send(self, *data: bytes | Any) -> None:
        assert self.addr is not None
        for d in data:
            self.sock.sendto(d if isinstance(d, bytes) else packed(d, self.enc), self.addr)

    def heartbeat(self) -> Any:
        return telemetry.heartbeat(self.enc, armed=True)

    def wait_companion(self, timeout_s: float = 60.0) -> None:
        self.sock.settimeout(timeout_s)
        _data, self.addr = self.sock.recvfrom(65535)  # its first HEARTBEAT
        self.send(self.heartbeat())

    def pump(self, deadline: float, want_ms: int | None) -> bool:
        found = False
        while True:
            self.sock.settimeout(max(1e-3, deadline - time.monotonic()))
            try:
                data, _ = self.sock.recvfrom(65535)
            except (TimeoutError, BlockingIOError):
                return found
            for m in self.parser.parse_buffer(data) or []:
                if m.get_type() == "BAD_DATA":
                    self.bad += 1
                    continue
                self.received.append(m)
                if m.get_type() == "COMMAND_LONG" and m.target_component in (0, 1):
                    self.send(self.enc.command_ack_encode(m.command, mav.MAV_RESULT_ACCEPTED, 0, 0,
                                                          m.get_srcSystem(), m.get_srcComponent()))
                elif m.get_type() == "SET_ATTITUDE_TARGET":
                    roll, pitch, _ = quaternion_to_euler(m.q)
                    if want_ms is not None and m.time_boot_ms == want_ms:
                        self.cmd = (roll, pitch)
                        self.commands.append((m.time_boot_ms, roll, pitch))
                        found = True
            if found:
                return True

    def frame_packets(self) -> list[bytes]:
        s = self.sim.current
        rf = self.cfg.rangefinder
        return [packed(m, self.enc) for m in telemetry.frame_messages(
            self.enc, s, Profile.PAPER, self.cfg.flow_sensor.q_rad_per_count, self.sim.T, rf.min_m, rf.max_m)]

    def step(self, before: list[bytes] = (), after: list[bytes] = (), wait_s: float = 1.0) -> None:
        if self.sim.frame % 25 == 0:
            self.send(self.heartbeat())
        for d in before:
            self.send(d)
        self.send(b"".join(self.frame_packets()))
        for d in after:
            self.send(d)
        ms = int(round(self.sim.t_s * 1e3))
        if not self.pump(time.monotonic() + wait_s, ms):
            self.missed += 1
        self.sim.advance(*self.cmd)

    def fly(self, n: int, **kw: Any) -> None:
        for _ in range(n):
            self.step(**kw)

    def texts(self) -> list[str]:
        return [m.text for m in self.received if m.get_type() == "STATUSTEXT"]


LEAN_RAD = math.atan(2.0 / (2.3 * 9.81))  # held against the fake vehicle's 2 N wind on each axis


def _assert_leaning(fv: FakeVehicle, last: int) -> None:
    """The last ``last`` commands lean into the wind (nose down, left side down), none kicked."""
    rp = np.array([(r, p) for _ms, r, p in fv.commands[-last:]])
    assert len(rp) == last
    assert np.all(rp[:, 1] < -0.6 * LEAN_RAD) and np.all(rp[:, 0] < -0.6 * LEAN_RAD), rp
    assert np.all(np.abs(rp) < 2.0 * LEAN_RAD), rp  # no kick: about the lean, far from the 20 deg limit


def _counts(parts: list[str]) -> dict[str, int]:
    return {k: int(v) for k, v in (p.rsplit(": ", 1) for p in parts)}


def _summary(proc: Any) -> dict[str, int]:
    """The companion's exit summary ("flowhold: N steps, N commands, N hold episode(s), key: value, ...")."""
    line = [ln for ln in proc.text().splitlines() if re.match(r"flowhold: \d+ steps", ln)][-1]
    return _counts(line.removeprefix("flowhold: ").split(", ")[3:])


def _vehicle_summary(proc: Any) -> dict[str, int]:
    """The vehicle's exit summary ("simvehicle: stopped at ... of wall time; key: value, ...")."""
    line = [ln for ln in proc.text().splitlines() if re.match(r"simvehicle: (stopped|done) at", ln)][-1]
    return _counts(line.split("; ", 1)[1].split(", "))


@pytest.fixture
def fake_pair(tmp_path, paper_cfg):
    """(FakeVehicle, Procs); the companion is started by the test with its own arguments."""
    fv = FakeVehicle(paper_cfg)
    try:
        with Procs(tmp_path) as procs:
            yield fv, procs
    finally:
        fv.close()


def test_companion_flies_on_through_garbage_floods_and_strangers(fake_pair):
    """Between frames: garbage datagrams (each ending in a long packet's start), bad-CRC copies
    of the frame, an oversized datagram, a flood of the same frame ten times over, flow spikes
    and clipped gyros from system 7, non-finite and absurd setpoints, setpoints for another
    system, a position-only setpoint, and a COMMAND_LONG to the companion. The companion
    answers every frame, keeps leaning into the wind with no kick, refuses the command with an
    ACK, and counts everything in its exit summary."""
    fv, procs = fake_pair
    comp = procs.companion(fv.port, "--quiet", "--vehicle-sysid", "1")
    fv.wait_companion()
    fv.fly(150)  # settle on the lean into the wind
    _assert_leaning(fv, 20)
    stranger = mav.MAVLink(None, srcSystem=7, srcComponent=1)
    gcs = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    rng = np.random.default_rng(11)

    def setpoint(vx: float, vy: float, target: int = 1, mask: int = VELOCITY_TYPE_MASK) -> bytes:
        return packed(gcs.set_position_target_local_ned_encode(0, target, COMPANION_COMPONENT, 12, mask, 0, 0, 0,
                                                               vx, vy, 0, 0, 0, 0, 0, 0), gcs)

    garbage = [rng.integers(0, 256, 500, dtype=np.uint8).tobytes() + long_prefix(), long_prefix()]
    hostile = [
        bytes(60_000),  # oversized datagram
        oversized_payload(stranger),
        packed(stranger.optical_flow_encode(0, 0, 90, -90, 0, 0, 255, -1, 0, 0), stranger),
        packed(stranger.raw_imu_encode(0, 0, 0, 0, 32767, -32767, 0, 0, 0, 0), stranger),
        packed(stranger.distance_sensor_encode(0, 2, 400, 3, 0, 0, 25, 0), stranger),
        setpoint(NAN, 0.0), setpoint(INF, -INF), setpoint(0.3, 0.0, target=7),
        setpoint(1e6, -1e6), setpoint(0.0, 0.0, mask=VELOCITY_TYPE_MASK | 0b11000),
        packed(gcs.manual_control_encode(1, 32767, -32768, 500, 0, 0), gcs),
        packed(link.command_long(gcs, 1, COMPANION_COMPONENT, mav.MAV_CMD_DO_SET_MODE, NAN, INF), gcs),
    ]
    n0 = len(fv.commands)
    for k in range(60):  # each frame: its bad-CRC copy and garbage before it, 9 copies after it (a flood)
        frame = b"".join(fv.frame_packets())
        fv.step(before=[bad_crc(p) for p in fv.frame_packets()] + garbage,
                after=[frame] * 9 + (hostile if k % 10 == 0 else []))
    answered = len(fv.commands) - n0
    assert answered == 60 and fv.missed == 0  # every frame stepped, none lost to the garbage before it
    # the absurd setpoints were clipped to max speed, then a steady stream of frames brings it back
    fv.fly(100)
    _assert_leaning(fv, 20)
    acks = [m for m in fv.received if m.get_type() == "COMMAND_ACK" and m.get_srcComponent() == COMPANION_COMPONENT]
    assert acks and all(a.result == mav.MAV_RESULT_UNSUPPORTED and a.command == mav.MAV_CMD_DO_SET_MODE
                        for a in acks)
    assert not [t for t in fv.texts() if "spike" in t or "gyro" in t or "range" in t]
    sats = [m for m in fv.received if m.get_type() == "SET_ATTITUDE_TARGET"]
    q = np.array([m.q for m in sats], dtype=float)
    assert np.all(np.isfinite(q))
    assert max(abs(a) for m in sats for a in quaternion_to_euler(m.q)[:2]) <= TILT_LIMIT_RAD + 1e-6
    assert comp.stop() == 0
    s = _summary(comp)
    assert s["sensor data from another system"] == 3 * 6
    assert s["bad packets"] >= 60 * (5 + 2)  # the bad-CRC copies and the garbage
    assert s["oversized datagrams dropped"] == 6
    assert s["flow frames repeated or out of order"] == 60 * 9  # the flood of copies: each frame stepped once
    assert s["commands refused (unsupported)"] == 6
    assert s["ignored: non-finite setpoint"] == 12
    assert s["ignored: setpoint for another system"] == 6
    assert s["ignored: setpoint without a horizontal velocity"] == 6
    assert s["ignored: setpoint beyond max_speed_m_s (clipped)"] == 12


def test_a_flapping_cause_cannot_flood_the_link_with_statustext(fake_pair):
    """Flow quality 0 every other frame for 200 frames: without a limit the companion would send a
    STATUSTEXT each frame (HOLD, resumed, HOLD, ...). It says each once per TEXT_REPEAT_S
    (companion.mavlink.live.TextLimiter), and once the flow is good again the last text tells the ground
    station the current state, with how many texts it held back."""
    import dataclasses

    from companion.mavlink.live import TEXT_REPEAT_S

    fv, procs = fake_pair
    comp = procs.companion(fv.port, "--quiet", "--profile", "paper")
    fv.wait_companion()
    fv.fly(50)

    def texts() -> list[Any]:
        return [m for m in fv.received if m.get_type() == "STATUSTEXT" and m.get_srcComponent() == COMPANION_COMPONENT]

    n0 = len(texts())
    t0 = time.monotonic()
    rf = fv.cfg.rangefinder
    for k in range(200):
        s = dataclasses.replace(fv.sim.current, flow_quality=0 if k % 2 == 0 else 255)
        fv.send(b"".join(packed(m, fv.enc) for m in telemetry.frame_messages(
            fv.enc, s, Profile.PAPER, fv.cfg.flow_sensor.q_rad_per_count, fv.sim.T, rf.min_m, rf.max_m)))
        if not fv.pump(time.monotonic() + 1.0, int(round(fv.sim.t_s * 1e3))):
            fv.missed += 1
        fv.sim.advance(*fv.cmd)
    elapsed = time.monotonic() - t0
    flapping = texts()[n0:]
    assert len(flapping) <= 2 * (elapsed / TEXT_REPEAT_S + 2), [m.text for m in flapping]
    assert sum("HOLD flow quality 0" in m.text for m in flapping) >= 1
    # good frames, until a token comes back for what was held back and the state it tells is
    # "resumed" (on a loaded machine this process can stall past flow_timeout_s of wall time: the
    # companion then rightly says "HOLD link lost" first, and resumes when the frames come again)
    resumed = re.compile(r"flowhold: resumed( \(\+\d+ held back\))?")
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and not (resumed.fullmatch(texts()[-1].text)
                                               and any("held back)" in m.text for m in texts()[n0:])):
        fv.fly(5)
    last = texts()[-1]
    assert resumed.fullmatch(last.text), last.text
    assert any(re.search(r" \(\+\d+ held back\)$", m.text) for m in texts()[n0:]), [m.text for m in texts()[n0:]]
    assert last.severity == mav.MAV_SEVERITY_NOTICE
    assert fv.missed == 0
    assert comp.stop() == 0
    assert _summary(comp)["status texts dropped (rate limit)"] > 100


def test_signed_companion_takes_only_signed_data_from_its_vehicle(tmp_path, paper_cfg):
    """``--signing-key`` and ``--vehicle-sysid 1``: spoofed frames with spikes (unsigned, signed
    with another key, or a signed frame replayed) and signed ones from system 7 never reach the
    control step; the companion keeps flying on the real frames and counts the rejections."""
    key = link.signing_key("robust companion key")
    key_file = tmp_path / "signing.key"
    key_file.write_text(key.hex() + "\n")  # the key as 64 hex digits in a file
    fv = FakeVehicle(paper_cfg, key=key)
    other = mav.MAVLink(None, srcSystem=7, srcComponent=1)
    link.setup_signing(other, key)
    spoof = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    wrong = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    link.setup_signing(wrong, link.signing_key("not the key"))
    try:
        with Procs(tmp_path) as procs:
            comp = procs.companion(fv.port, "--quiet", "--vehicle-sysid", "1", "--signing-key", str(key_file))
            fv.wait_companion()
            fv.fly(150)
            _assert_leaning(fv, 20)
            old_frame = fv.frame_packets()
            for _ in range(40):
                t_us = int(round(fv.sim.t_s * 1e6)) + 10_000  # between this frame and the next
                spike = [spoof.optical_flow_encode(t_us, 0, 95, 95, 0, 0, 255, -1, 0, 0),
                         wrong.optical_flow_encode(t_us, 0, 95, 95, 0, 0, 255, -1, 0, 0),
                         other.optical_flow_encode(t_us, 0, 95, 95, 0, 0, 255, -1, 0, 0)]
                encs = (spoof, wrong, other)
                fv.step(after=[packed(m, e) for m, e in zip(spike, encs, strict=True)] + old_frame)
            _assert_leaning(fv, 40)
            fv.fly(5)  # the last spikes read before the companion stops
            assert not [t for t in fv.texts() if "HOLD" in t]
            assert comp.stop() == 0
            s = _summary(comp)
    finally:
        fv.close()
    assert s["packets rejected: unsigned or badly signed"] == 40 * (2 + len(old_frame))
    assert s["sensor data from another system"] == 40
    assert fv.bad == 0 and all(m.get_signed() for m in fv.received)  # everything the companion sent was signed


def test_signing_key_from_a_passphrase_or_a_file(tmp_path):
    """``--signing-key``: a passphrase is sha256(passphrase), as MAVProxy's ``signing setup``; a file
    holds 32 raw bytes, 64 hex digits or a passphrase."""
    import hashlib

    from companion.errors import UsageError

    words = "correct horse battery staple"
    want = hashlib.sha256(words.encode()).digest()
    assert link.signing_key(words) == want
    for name, content in (("raw", want), ("hex", want.hex().encode() + b"\n"), ("words", words.encode() + b"\n")):
        (tmp_path / name).write_bytes(content)
        assert link.signing_key(str(tmp_path / name)) == want, name
    with pytest.raises(UsageError, match="empty passphrase"):
        link.signing_key("")


def test_status_line_shows_what_was_rejected(paper_cfg):
    from companion.mavlink.live import LiveCompanion

    url = f"udpout:127.0.0.1:{_free_port()}"
    conn = link.open_connection(url, source_system=1, source_component=COMPANION_COMPONENT)
    live = LiveCompanion(paper_cfg, Profile.PAPER, conn, url=url, out=lambda _s: None)
    try:
        assert "rejected" not in live.status_line(0.0)
        live.counters["bad packets"] += 3
        live.counters["packets rejected: unsigned or badly signed"] += 2
        live.router.ignored["non-finite setpoint"] = 4
        live.counters["steps"] += 100  # not a rejection
        assert live.status_line(0.0).endswith("rejected 9")
        summary = live.summary()
        assert "bad packets: 3" in summary and "ignored: non-finite setpoint: 4" in summary
    finally:
        live.close()


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ---------------------------------------------------------------------------------------------
# 4. The real pair in real time, the vehicle flooded by a hostile peer


def test_real_time_loop_flies_on_under_a_flood(tmp_path):
    """For 3 s a hostile peer (system 200) sends the vehicle 500 datagrams a second (ten times
    its frame rate, each holding a heartbeat, a NaN attitude target, a bad-CRC packet and a flow
    spike that is routed on to the companion). The vehicle keeps its 50 Hz frame rate, the
    companion keeps leaning into the wind with no hold and no kick, and both count what they
    dropped: the vehicle in SYS_STATUS and its exit summary, the companion in its summary."""
    with Procs(tmp_path) as procs:
        veh, port = procs.vehicle()
        comp = procs.companion(port, "--arm", "--quiet")
        gcs = Gcs(port)
        hostile = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            gcs.wait_vehicle()
            gcs.quiet({"ATTITUDE_TARGET": 50.0, "SYS_STATUS": 5.0})
            assert gcs.set_param("SIM_WIND_FX", -2.0).param_value == -2.0
            assert gcs.set_param("SIM_WIND_FY", 2.0).param_value == 2.0
            veh.wait_for("armed GUIDED_NOGPS", timeout_s=60)
            _wait_leaning(gcs, timeout_s=60)
            enc = mav.MAVLink(None, srcSystem=200, srcComponent=1)
            t_end = time.monotonic() + 3.0
            n_sent, targets, next_send = 0, [], time.monotonic()
            while time.monotonic() < t_end:
                now = time.monotonic()
                if now >= next_send:
                    dgram = (packed(enc.heartbeat_encode(6, 8, 0, 0, 4), enc)
                             + packed(enc.set_attitude_target_encode(0, 1, 1, 7, [NAN] * 4, 0, 0, 0, NAN), enc)
                             + bad_crc(packed(enc.attitude_encode(0, 0, 0, 0, 0, 0, 0), enc))
                             + packed(enc.optical_flow_encode(0, 0, 99, 99, 0, 0, 255, -1, 0, 0), enc))
                    hostile.sendto(dgram, ("127.0.0.1", port))
                    n_sent += 1
                    next_send += 1 / 500.0
                    continue
                m = gcs.conn.recv_msg()
                if m is None:
                    time.sleep(1e-4)
                elif m.get_type() == "ATTITUDE_TARGET" and m.get_srcComponent() == 1:
                    targets.append((time.monotonic(), *quaternion_to_euler(m.q)[:2]))
            assert n_sent >= 0.8 * 1500
            tt = np.array(targets)
            rate_hz = (len(tt) - 1) / (tt[-1, 0] - tt[0, 0])
            assert rate_hz == pytest.approx(50.0, rel=0.15)  # the vehicle kept its frame rate
            lean = math.atan(2.0 / (2.3 * 9.81))
            assert np.all(tt[:, 2] < -0.6 * lean) and np.all(tt[:, 1] < -0.6 * lean), tt[:, 1:].min(axis=0)
            assert np.all(np.abs(tt[:, 1:]) < 2.0 * lean)  # no kick
            status = gcs.recv("SYS_STATUS", timeout_s=10)
            assert status.errors_comm >= 0.9 * n_sent  # the bad-CRC packet of each datagram
            assert not [s for s in gcs.statustexts if "HOLD" in s[3]]
        finally:
            hostile.close()
            gcs.close()
        assert comp.stop() == 0
        assert veh.stop() == 0
    v = _vehicle_summary(veh)
    assert v["bad packets"] >= 0.9 * n_sent  # (UDP may drop a datagram; none was, on this machine)
    assert v["SET_ATTITUDE_TARGET rejected: not a unit quaternion"] >= 0.9 * n_sent
    s = _summary(comp)
    assert s["sensor data from another system"] >= 0.9 * n_sent  # the spikes the vehicle routed on


def _wait_leaning(gcs: Gcs, timeout_s: float) -> None:
    """Until the vehicle has tracked the lean into the wind (within 20 %) for 25 frames running."""
    lean = math.atan(2.0 / (2.3 * 9.81))
    deadline = time.monotonic() + timeout_s
    run = 0
    while run < 25:
        at = gcs.recv("ATTITUDE_TARGET", cond=lambda m: m.get_srcComponent() == 1)
        roll, pitch, _ = quaternion_to_euler(at.q)
        run = run + 1 if abs(pitch + lean) < 0.2 * lean and abs(roll + lean) < 0.2 * lean else 0
        assert time.monotonic() < deadline, "never settled on the lean into the wind"
