"""Failsafes end to end: the simulated vehicle spoils one sensor on a GCS's PARAM_SET, the
companion commands level attitude (hold) and says why in a STATUSTEXT, and resumes when the
data is good again. Plus a vehicle reboot, a lost link, and garbage on the wire.

The session flies in lockstep with a steady wind (2 N on each axis), so that the companion's
normal command is a lean into the wind (atan(2 / (2.3 x 9.81)) = 5.06 deg) and a hold (level)
is told apart from normal flight by the vehicle's ATTITUDE_TARGET.

Run time (2 shared cores): about 20 s.
"""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest
from loop_helpers import Gcs, Procs

from companion.mavlink.outbound import quaternion_to_euler
from companion.recordings.load import load_recording

WIND_N = 2.0
LEAN_DEG = math.degrees(math.atan(WIND_N / (2.3 * 9.81)))  # 5.06 deg held against the wind
TILT_LIMIT_RAD = math.radians(20.0)


def _angles_deg(at) -> tuple[float, float]:
    roll, pitch, _ = quaternion_to_euler(at.q)
    return math.degrees(roll), math.degrees(pitch)


class Session:
    def __init__(self, tmp, procs: Procs) -> None:
        self.tmp = tmp
        self.procs = procs
        self.ctlog = tmp / "companion.tlog"
        self.vtlog = tmp / "vehicle.tlog"
        # lockstep at most 4x real time: the GCS here reads every ATTITUDE_TARGET and must keep up
        # (uncapped, its socket can overflow and lose the PARAM_VALUE a test waits for)
        self.vehicle, self.port = procs.vehicle("--lockstep", "--max-speedup", "4", "--tlog", str(self.vtlog))
        self.companion = procs.companion(self.port, "--arm", "--quiet", "--tlog", str(self.ctlog))
        self.gcs = Gcs(self.port)
        self.gcs.wait_vehicle()
        self.gcs.quiet({"ATTITUDE_TARGET": 50.0})
        assert self.gcs.set_param("SIM_WIND_FX", -WIND_N).param_value == -WIND_N
        assert self.gcs.set_param("SIM_WIND_FY", WIND_N).param_value == WIND_N
        self.gcs.wait_time(6.0)  # the PI settles on its lean into the wind
        self.assert_leaning()

    def next_target(self) -> tuple[float, float]:
        return _angles_deg(self.gcs.recv("ATTITUDE_TARGET", cond=lambda m: m.get_srcComponent() == 1))

    def assert_leaning(self, timeout_s: float = 30.0) -> None:
        """The vehicle tracks a lean into the wind (nose down, left side down) again."""
        deadline = time.monotonic() + timeout_s
        while True:
            roll, pitch = self.next_target()
            if pitch < -0.6 * LEAN_DEG and roll < -0.6 * LEAN_DEG:
                return
            assert time.monotonic() < deadline, f"never leaned into the wind again ({roll}, {pitch})"


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("failsafe")
    with Procs(tmp) as procs:
        s = Session(tmp, procs)
        try:
            yield s
        finally:
            s.gcs.close()


CASES = [
    ("SIM_FLOW_FAULT", 1, "flow quality 0"),
    ("SIM_FLOW_FAULT", 2, "flow stale"),  # frozen: the same frame again and again
    ("SIM_FLOW_FAULT", 4, "flow stale"),  # the stream stops
    ("SIM_GYRO_FAULT", 1, "no gyro sample at the flow frame"),  # frozen
    ("SIM_GYRO_FAULT", 2, "gyro saturated or not finite"),
    ("SIM_GYRO_FAULT", 3, "no gyro sample at the flow frame"),  # stops
    ("SIM_RNG_FAULT", 1, "range outside sensor limits"),  # beyond 4 m
    ("SIM_RNG_FAULT", 2, "range outside sensor limits"),  # 0, below 2 cm
    ("SIM_RNG_FAULT", 3, "range stale"),  # stops: stale after companion.range_timeout_s
]


@pytest.mark.parametrize("param,value,cause", CASES, ids=[f"{p}={v}" for p, v, _ in CASES])
def test_sensor_fault_holds_level_and_resumes(session, param, value, cause):
    gcs = session.gcs
    pv = gcs.set_param(param, value)
    assert pv.param_value == value
    gcs.recv_text(f"flowhold: HOLD {cause}")
    # every frame while the fault lasts: the vehicle tracks level
    for _ in range(10):
        roll, pitch = session.next_target()
        assert abs(roll) < 1e-4 and abs(pitch) < 1e-4, (roll, pitch)
    assert gcs.set_param(param, 0).param_value == 0
    gcs.recv_text("flowhold: resumed")
    session.assert_leaning()


def test_flow_spike_holds_one_frame(session):
    gcs = session.gcs
    gcs.set_param("SIM_FLOW_FAULT", 3)  # 500 counts once (39 rad/s), beyond companion.max_flow_rate_rad_s = 7.4
    targets, seen_text, after = [], False, 0
    deadline = time.monotonic() + 30.0  # the loop's own deadline: a lost STATUSTEXT must fail, not hang
    while after < 4:  # the vehicle's targets around the STATUSTEXT
        assert time.monotonic() < deadline, "no 'HOLD flow spike' STATUSTEXT within 30 s"
        m = gcs.recv(("ATTITUDE_TARGET", "STATUSTEXT"), timeout_s=30)
        if m.get_type() == "STATUSTEXT":
            seen_text = seen_text or "flowhold: HOLD flow spike" in m.text
        elif m.get_srcComponent() == 1:
            targets.append(_angles_deg(m))
            after += seen_text
    level = [abs(r) < 1e-4 and abs(p) < 1e-4 for r, p in targets]
    assert sum(level) == 1, targets  # exactly the frame after the spike is level
    assert all(p < -0.6 * LEAN_DEG for (_r, p), lv in zip(targets, level, strict=True) if not lv)
    gcs.wait_text("flowhold: resumed")
    session.assert_leaning(timeout_s=5)
    # the one-shot fault cleared itself and said so
    gcs.conn.mav.param_request_read_send(1, 1, b"SIM_FLOW_FAULT", -1)
    assert gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "SIM_FLOW_FAULT").param_value == 0


def test_vehicle_reboot_restarts_the_clock_and_control_goes_on(session):
    gcs = session.gcs
    before = gcs.wait_time(gcs.vehicle_time_s + 0.5)
    assert before > 2.0
    gcs.set_param("SIM_REBOOT", 1)
    at = gcs.recv("ATTITUDE_TARGET", cond=lambda m: m.time_boot_ms * 1e-3 < before - 1.0)
    assert at.time_boot_ms < 500  # boot time restarted at 0
    n = len(gcs.statustexts)
    session.assert_leaning(timeout_s=10)
    gcs.drain(0.5)
    assert not [t for t in gcs.statustexts[n:] if "HOLD" in t[3]]
    session.companion.wait_for("clock restarted")


def test_lost_link_keeps_commanding_level_at_the_frame_rate(session):
    """Last: the vehicle goes away; the companion keeps sending level SET_ATTITUDE_TARGET at
    about 50 Hz (wall clock) and says "HOLD link lost"; it never sent a bad command."""
    assert session.vehicle.stop() == 0
    time.sleep(2.0)
    assert session.companion.stop() == 0
    rec = load_recording(session.ctlog)
    sat = rec.table("SET_ATTITUDE_TARGET").from_sender(compid=191)
    q = np.asarray(sat["q"], dtype=float)
    assert np.all(np.isfinite(q)) and np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    ang = np.array([quaternion_to_euler(qq)[:2] for qq in q])
    assert np.abs(ang).max() <= TILT_LIMIT_RAD + 1e-6
    assert np.all(np.isfinite(sat["thrust"])) and np.all(sat["thrust"] == 0.5)
    last_rx = max(float(t.from_sender(sysid=1, compid=1).t_s.max()) for t in rec
                  if len(t.from_sender(sysid=1, compid=1)))
    after = sat.t_s > last_rx + 0.5  # well after the vehicle went silent
    assert after.sum() > 10
    span = float(sat.t_s[after][-1] - sat.t_s[after][0])
    rate_hz = (after.sum() - 1) / span
    assert rate_hz == pytest.approx(50.0, rel=0.3)
    assert np.abs(ang[after]).max() == 0.0
    texts = rec.table("STATUSTEXT").from_sender(compid=191)["text"]
    assert any("flowhold: HOLD link lost" in str(t) for t in texts)


# ---------------------------------------------------------------------------------------------
# Garbage on the wire: a hand-made vehicle that sends nonsense between good frames


def test_garbage_and_nonsense_never_break_the_companion(tmp_path, paper_cfg):
    from companion.mavlink.link import mav as dialect
    from companion.step.profiles import Profile
    from simvehicle.model import telemetry
    from simvehicle.model.sim import Simulator

    rng = np.random.default_rng(7)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.01)
    port = sock.getsockname()[1]
    enc = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
    other = dialect.MAVLink(None, srcSystem=7, srcComponent=1)
    ctlog = tmp_path / "companion.tlog"
    sim = Simulator(paper_cfg)
    received: list = []
    parser = dialect.MAVLink(None)
    parser.robust_parsing = True

    def pkt(msg, e=enc):
        return bytes(msg.pack(e))

    def pump(addr):
        try:
            while True:
                data, addr = sock.recvfrom(65535)
                received.extend(m for m in (parser.parse_buffer(data) or []) if m.get_type() != "BAD_DATA")
        except (TimeoutError, BlockingIOError):
            return addr

    try:
        with Procs(tmp_path) as procs:
            comp = procs.companion(port, "--quiet", "--setpoint", "0.5,0", "--tlog", str(ctlog))
            sock.settimeout(30)
            _data, addr = sock.recvfrom(65535)  # the companion's first HEARTBEAT
            sock.settimeout(0.01)
            armed_guided = telemetry.heartbeat(enc, armed=True, custom_mode=20)
            sock.sendto(pkt(armed_guided), addr)
            nan = math.nan
            nonsense = [
                rng.integers(0, 256, 300, dtype=np.uint8).tobytes(),
                pkt(armed_guided)[:7],  # truncated
                pkt(armed_guided)[:-1] + b"\x00",  # bad CRC
                pkt(enc.raw_imu_encode(0, 0, 0, 0, 32767, -32768, 0, 0, 0, 0)),  # clipped gyro
                pkt(enc.distance_sensor_encode(0, 2, 400, 100, 0, 0, 0, 0)),  # facing forward
                pkt(enc.set_position_target_local_ned_encode(0, 1, 191, 12, 3527, 0, 0, 0, nan, math.inf, 0,
                                                             0, 0, 0, 0, 0)),
                pkt(enc.set_position_target_local_ned_encode(0, 1, 191, 12, 3527, 0, 0, 0, 1e6, -1e6, 0,
                                                             0, 0, 0, 0, 0)),
                pkt(enc.manual_control_encode(1, 32767, -32768, 0, 0, 0)),
                pkt(enc.attitude_encode(0, nan, nan, nan, nan, nan, nan)),
                pkt(enc.command_ack_encode(400, 4, 0, 0, 1, 191)),
                pkt(other.optical_flow_encode(0, 0, 30000, -30000, 0, 0, 255, -1, 0, 0), other),
                pkt(enc.optical_flow_encode(2**63, 0, 30000, -30000, nan, nan, 255, nan, nan, nan)),
            ]
            for k in range(250):
                s = sim.current
                frame = telemetry.frame_messages(enc, s, Profile.PAPER, paper_cfg.flow_sensor.q_rad_per_count,
                                                 sim.T, 0.02, 4.0)
                if k % 20 == 10:  # a clipped (saturated) gyro at the frame's own time
                    frame[0] = enc.raw_imu_encode(int(s.t_s * 1e6), 0, 0, -1000, 32767, 32767, 0, 0, 0, 0)
                for m in frame:
                    sock.sendto(pkt(m), addr)
                if k % 20 == 10:
                    for junk in nonsense:
                        sock.sendto(junk, addr)
                if k % 50 == 0:
                    sock.sendto(pkt(armed_guided), addr)
                addr = pump(addr)
                sats = [m for m in received if m.get_type() == "SET_ATTITUDE_TARGET"]
                roll, pitch = quaternion_to_euler(sats[-1].q)[:2] if sats else (0.0, 0.0)
                sim.advance(roll, pitch)
                time.sleep(0.004)
            assert comp.p.poll() is None, comp.text()  # still running
            assert comp.stop() == 0
    finally:
        sock.close()
    sats = [m for m in received if m.get_type() == "SET_ATTITUDE_TARGET"]
    assert len(sats) > 100
    q = np.array([m.q for m in sats], dtype=float)
    assert np.all(np.isfinite(q))
    ang = np.array([quaternion_to_euler(qq)[:2] for qq in q])
    assert np.abs(ang).max() <= TILT_LIMIT_RAD + 1e-6
    assert np.abs(ang).max() > 0.01  # it did fly the 0.5 m/s setpoint between the junk
    assert any(m.get_type() == "STATUSTEXT" and "HOLD gyro saturated" in m.text for m in received)
