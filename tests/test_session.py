"""The live companion's session (``companion.mavlink.session.Session``) in process, message by message:
no socket, no clock (times are passed in), every number exact. Engagement and take-over, the
setpoint's hold and ramp, each hold cause and the recovery from it, a stall's backlog, frame
order. The live loop around it (``companion.mavlink.live``) is tested over fake and real links in
test_stall.py, test_loop_e2e.py, test_robust_*.py and the *_e2e.py files."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from companion.config import load_config
from companion.mavlink import link
from companion.mavlink.outbound import VELOCITY_TYPE_MASK
from companion.mavlink.session import (
    BACKLOG_SAY_FRAMES,
    HEARTBEAT_TIMEOUT_S,
    LONG_HOLD_S,
    MAX_FRAME_AGE_FRAMES,
    Command,
    Estimate,
    Note,
    Out,
    Say,
    Session,
)
from companion.mavlink_ids import COMPANION_COMPONENT, GUIDED_NOGPS
from companion.step.controller import PiState, pi_step
from companion.step.core import HoldCause
from companion.step.profiles import Profile
from companion.step.setpoint import decayed_setpoint
from simvehicle.model import telemetry

mav = link.mav
CFG = load_config()
T_S = CFG.flow_sensor.frame_period_s
C = CFG.controller
TIMEOUT_S = CFG.companion.flow_timeout_s
LOITER = 5
ROOT = Path(__file__).resolve().parents[1]


def _wire(m: Any, enc: Any) -> Any:
    """``m`` as it comes off the link (packed by ``enc``, decoded)."""
    return mav.MAVLink(None).decode(bytearray(m.pack(enc)))


def _pi(n: int, err_x: float) -> tuple[PiState, float]:
    """The integrator after ``n`` steps of the error ``err_x`` (m/s) on x, and the last pitch (rad)."""
    state, pitch = PiState(), 0.0
    for _ in range(n):
        state, _roll, pitch = pi_step(state, err_x, 0.0, T_S, kp_rad_per_m_s=C.kp_rad_per_m_s,
                                      ki_rad_per_m=C.ki_rad_per_m, limit_rad=C.tilt_limit_rad)
    return state, pitch


def _next_pitch(state: PiState, err_x: float) -> float:
    return pi_step(state, err_x, 0.0, T_S, kp_rad_per_m_s=C.kp_rad_per_m_s, ki_rad_per_m=C.ki_rad_per_m,
                   limit_rad=C.tilt_limit_rad)[2]


class Bench:
    """A vehicle by hand: each frame a RAW_IMU, a DISTANCE_SENSOR and an OPTICAL_FLOW (paper
    profile) at vehicle time ``t_s``, handed to the session at ``now_s`` as they arrive; both
    clocks then advance one frame period. A still vehicle over ground at 1 m: eq. 15 reads 0."""

    def __init__(self, setpoint: tuple[float, float] | None = None, profile: Profile | None = Profile.PAPER) -> None:
        self.s = Session(CFG, profile, vehicle_sysid=1, setpoint_m_s=setpoint)
        self.veh = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        self.gcs = mav.MAVLink(None, srcSystem=255, srcComponent=190)
        self.t_s = 1.0  # vehicle time
        self.now_s = 100.0  # the session's caller's clock

    def handle(self, msgs: list[Any], *, vehicle: bool = True, behind: bool = False) -> list[Out]:
        out: list[Out] = []
        for m in msgs:
            self.s.observe(m, self.now_s, vehicle=vehicle)
        for m in msgs:
            out += self.s.on_message(m, self.now_s, vehicle=vehicle, arrival_s=self.now_s, behind=behind)
        return out

    def vehicle(self, m: Any) -> list[Out]:
        return self.handle([_wire(m, self.veh)])

    def frame_messages(self, *, flow: tuple[int, int] = (0, 0), quality: int = 255, range_cm: int = 100,
                       gyro_mrad_s: tuple[int, int] = (0, 0), gyro: bool = True, rng: bool = True,
                       advance: bool = True) -> list[Any]:
        us = round(self.t_s * 1e6)
        msgs = []
        if gyro:
            msgs.append(self.veh.raw_imu_encode(us, 0, 0, -1000, gyro_mrad_s[0], gyro_mrad_s[1], 0, 0, 0, 0))
        if rng:
            msgs.append(self.veh.distance_sensor_encode(us // 1000, 2, 400, range_cm, 0, 0, 25, 0))
        msgs.append(self.veh.optical_flow_encode(us, 0, flow[0], flow[1], 0.0, 0.0, quality, -1.0))
        if advance:
            self.t_s += T_S
        return [_wire(m, self.veh) for m in msgs]

    def frame(self, **kw: Any) -> list[Out]:
        out = self.handle(self.frame_messages(**kw))
        self.now_s += T_S
        return out

    def gyro_only(self) -> list[Out]:
        """A RAW_IMU alone (the caller's clock does not advance)."""
        return self.handle(self.frame_messages(rng=False)[:1])

    def heartbeat(self, armed: bool = True, mode: int = GUIDED_NOGPS) -> list[Out]:
        return self.vehicle(telemetry.heartbeat(self.veh, armed=armed, custom_mode=mode))

    def attitude(self, yaw_rad: float) -> list[Out]:
        return self.vehicle(self.veh.attitude_encode(round(self.t_s * 1e3), 0.0, 0.0, yaw_rad, 0.0, 0.0, 0.0))

    def gcs_setpoint(self, vx: float, vy: float, target: int = 1) -> list[Out]:
        sp = self.gcs.set_position_target_local_ned_encode(0, target, COMPANION_COMPONENT, 12, VELOCITY_TYPE_MASK,
                                                           0, 0, 0, vx, vy, 0, 0, 0, 0, 0, 0)
        return self.handle([_wire(sp, self.gcs)], vehicle=False)

    def tick(self) -> list[Out]:
        return self.s.tick(self.now_s)

    def in_control(self, n: int = 0) -> None:
        """Frames, the take-over, then ``n`` frames flown."""
        self.frame()
        self.heartbeat()
        assert self.s.in_control
        for _ in range(n):
            self.frame()


def _commands(out: list[Out]) -> list[Command]:
    return [o for o in out if isinstance(o, Command)]


def _said(out: list[Out]) -> list[tuple[str, int]]:
    return [(o.text, o.severity) for o in out if isinstance(o, Say)]


def _level(c: Command) -> bool:
    return c.roll_rad == 0.0 and c.pitch_rad == 0.0 and c.estimate is None


# ---------------------------------------------------------------------------------------------
# Engagement and take-over


def test_the_pilot_flies_until_the_vehicle_is_armed_in_guided_nogps():
    b = Bench(setpoint=(0.5, 0.0))
    for _ in range(5):  # the pilot flies: each frame stepped, its estimate published, no command
        out = b.frame()
        assert [type(o) for o in out] == [Estimate] and out[0].vx_m_s == 0.0
        assert b.s.core.pi.state == PiState()  # and nothing integrated
    assert b.heartbeat(armed=True, mode=LOITER) == [] and b.heartbeat(armed=False) == []
    last_frame_s = b.t_s - T_S
    out = b.heartbeat()
    assert _said(out) == [("flowhold: in control (GUIDED_NOGPS)", mav.MAV_SEVERITY_NOTICE)]
    assert out[0].console == "flowhold: in control (armed, GUIDED_NOGPS)"
    (take,) = _commands(out)  # from level at the latest frame, with the setpoint flown
    assert _level(take) and take.time_s == pytest.approx(last_frame_s, abs=1e-9)
    assert (take.vx_set_m_s, take.vy_set_m_s) == (0.5, 0.0)
    # the five steps before did not integrate: the first step in control is the PI's first
    (c,) = _commands(b.frame())
    assert c.pitch_rad == _pi(1, 0.5)[1] == -(C.kp_rad_per_m_s * 0.5 + C.ki_rad_per_m * 0.5 * T_S)
    assert c.pitch_rad < 0 and c.roll_rad == 0.0  # nose down to go forward (CONVENTIONS.md)
    assert c.estimate is not None and c.estimate[:2] == (0.0, 0.0)
    out = b.heartbeat(armed=True, mode=LOITER)
    assert out == [Say("flowhold: released control (LOITER)", mav.MAV_SEVERITY_NOTICE,
                       "flowhold: released control (armed, LOITER)")]
    assert [type(o) for o in b.frame()] == [Estimate]
    b.heartbeat()
    assert _said(b.heartbeat(armed=False)) == [("flowhold: released control (disarmed)", mav.MAV_SEVERITY_NOTICE)]
    assert b.s.counters["commands"] == 3


def test_take_over_restarts_the_integrator_and_holds_the_yaw_it_found():
    b = Bench(setpoint=(0.5, 0.0))
    b.attitude(0.3)
    b.in_control(20)
    b.attitude(0.8)  # the vehicle turns: the companion keeps the yaw it took over with
    (c,) = _commands(b.frame())
    assert c.yaw_rad == pytest.approx(0.3, abs=1e-7) and c.pitch_rad == _pi(21, 0.5)[1]  # (ATTITUDE: float32)
    b.heartbeat(mode=LOITER)
    # the arm / mode command acknowledged: control taken again without waiting for a HEARTBEAT
    out = b.s.on_vehicle_state(b.now_s, mode=GUIDED_NOGPS)
    assert _said(out) == [("flowhold: in control (GUIDED_NOGPS)", mav.MAV_SEVERITY_NOTICE)]
    (c,) = _commands(b.frame())
    assert c.yaw_rad == pytest.approx(0.8, abs=1e-7) and c.pitch_rad == _pi(1, 0.5)[1]


def test_control_waits_for_the_profile():
    b = Bench(profile=None)
    b.heartbeat()
    assert not b.s.in_control
    assert b.frame() == []
    assert b.s.counters["flow frames before the profile was known"] == 1
    b.s.set_profile(Profile.PAPER)
    out = b.frame()  # the next message takes control; its flow frame is stepped
    assert b.s.in_control and _said(out) == [("flowhold: in control (GUIDED_NOGPS)", mav.MAV_SEVERITY_NOTICE)]


# ---------------------------------------------------------------------------------------------
# Setpoints


def test_a_gcs_setpoint_is_held_then_ramps_back_to_the_constant_one():
    base = (0.25, 0.0)
    b = Bench(setpoint=base)
    b.in_control(5)
    assert b.gcs_setpoint(1.0, -0.375) == []  # (float32 on the wire: exact)
    t0 = b.now_s
    timeout = CFG.companion.setpoint_timeout_s
    flown, said = [], []
    while b.now_s - t0 < 2.5:
        said += _said(b.tick())
        (c,) = _commands(b.frame())
        flown.append((b.now_s - T_S - t0, c.vx_set_m_s, c.vy_set_m_s))
    for age, vx, vy in flown:
        assert (vx, vy) == decayed_setpoint((1.0, -0.375), base, age, timeout)
    at = {round(age, 2): (vx, vy) for age, vx, vy in flown}
    assert at[0.5] == (1.0, -0.375)  # held for the timeout
    assert at[1.5] == pytest.approx((0.625, -0.1875))  # half way down the ramp
    assert at[2.0] == pytest.approx(base) and at[2.4] == base  # back to the constant setpoint
    assert said == [("flowhold: GCS setpoints stopped, ramp to hold", mav.MAV_SEVERITY_WARNING)]


def test_a_setpoint_is_clipped_and_one_refused_changes_nothing():
    b = Bench()
    b.in_control(2)
    b.gcs_setpoint(5.0, -0.5)
    (c,) = _commands(b.frame())
    assert (c.vx_set_m_s, c.vy_set_m_s) == (CFG.companion.max_speed_m_s, -0.5)
    for bad in (dict(vx=math.nan, vy=0.0), dict(vx=0.3, vy=0.0, target=7)):
        b.gcs_setpoint(**bad)
        (c,) = _commands(b.frame())
        assert (c.vx_set_m_s, c.vy_set_m_s) == (CFG.companion.max_speed_m_s, -0.5)
    assert b.s.router.ignored == {"setpoint beyond max_speed_m_s (clipped)": 1, "non-finite setpoint": 1,
                                  "setpoint for another system": 1}


# ---------------------------------------------------------------------------------------------
# Holds and recovery


FRAME_CAUSES = [
    (HoldCause.FLOW_QUALITY, dict(quality=0)),
    (HoldCause.FLOW_SPIKE, dict(flow=(100, 0))),  # 7.9 rad/s of scene rate: over the PMW3901's 7.4
    (HoldCause.VELOCITY_JUMP, dict(flow=(60, 0))),  # 4.7 m/s in one frame: under the spike limit
    (HoldCause.GYRO_MISSING, dict(gyro=False)),
    (HoldCause.GYRO_INVALID, dict(gyro_mrad_s=(32767, 0))),  # the int16 field clipped
    (HoldCause.RANGE_INVALID, dict(range_cm=500)),  # beyond the sensor's 400 cm
]


@pytest.mark.parametrize("cause,bad", FRAME_CAUSES, ids=[c.name for c, _ in FRAME_CAUSES])
def test_a_bad_frame_holds_level_with_the_integrator_frozen_and_the_next_good_one_resumes(cause, bad):
    b = Bench(setpoint=(0.5, 0.0))
    b.in_control(10)
    before = _pi(10, 0.5)[0]
    out = b.frame(**bad)
    (c,) = _commands(out)
    assert _level(c) and (c.vx_set_m_s, c.vy_set_m_s) == (0.5, 0.0)
    assert _said(out) == [(f"flowhold: HOLD {cause.value}", mav.MAV_SEVERITY_WARNING)]
    assert b.s.last_step is not None and b.s.last_step.hold_cause is cause
    out = b.frame()
    (c,) = _commands(out)
    assert c.pitch_rad == _next_pitch(before, 0.5)  # one step on from where the hold froze it
    assert _said(out) == [("flowhold: resumed", mav.MAV_SEVERITY_NOTICE)]
    assert b.s.monitor.episodes == 1


def test_range_stale_after_its_timeout():
    b = Bench()
    b.in_control(1)
    t_range = b.t_s - T_S
    holds = []
    for _ in range(40):
        t = b.t_s
        out = b.frame(rng=False)
        if _said(out):
            holds.append((t, _said(out)))
    (t, said), = holds
    assert said == [("flowhold: HOLD range stale", mav.MAV_SEVERITY_WARNING)]
    assert CFG.companion.range_timeout_s < t - t_range <= CFG.companion.range_timeout_s + T_S + 1e-9
    assert _said(b.frame()) == [("flowhold: resumed", mav.MAV_SEVERITY_NOTICE)]


def test_flow_stale_on_the_vehicles_clock_one_level_command_per_frame():
    """The gyro's clock runs on, the flow's does not: after flow_timeout_s of vehicle time a level
    command per gyro sample (one per frame period), stamped with the gyro's time; the caller's
    clock (``tick``) stays silent meanwhile: one clock at a time."""
    b = Bench(setpoint=(0.5, 0.0))
    b.in_control(10)
    last_flow_s = b.t_s - T_S
    sent = []
    for _ in range(15):
        t = b.t_s
        out = b.gyro_only() + b.tick()  # the sample handled, then the watchdog, at one time
        sent += [(t, o) for o in out]
        b.now_s += T_S
    cmds = [(t, o) for t, o in sent if isinstance(o, Command)]
    assert all(_level(c) and c.time_s == pytest.approx(t, abs=1e-9) for t, c in cmds)
    first = cmds[0][0] - last_flow_s
    assert TIMEOUT_S < first <= TIMEOUT_S + T_S + 1e-9
    assert len(cmds) == 15 - round(first / T_S) + 1
    assert [o.text for _t, o in sent if isinstance(o, Say)] == ["flowhold: HOLD flow stale"]
    assert b.s.counters["holds: flow stale (vehicle time)"] == len(cmds)
    out = b.frame()  # (its gyro sample, first, is still one more level command)
    assert _said(out) == [("flowhold: resumed", mav.MAV_SEVERITY_NOTICE)]
    c = _commands(out)[-1]
    assert c.pitch_rad == _next_pitch(_pi(10, 0.5)[0], 0.5)


def test_nothing_from_the_vehicle_is_a_lost_link_held_at_the_frame_rate_then_the_pilots_cue():
    b = Bench()
    b.in_control(5)
    last_t = b.t_s - T_S
    start = b.now_s
    sent: list[tuple[float, Out]] = []
    while b.now_s - start < 1.5:
        b.now_s += T_S / 4
        sent += [(b.now_s, o) for o in b.tick()]
    cmds = [(now, o) for now, o in sent if isinstance(o, Command)]
    assert all(_level(c) and c.time_s == pytest.approx(last_t, abs=1e-9) for _now, c in cmds)  # the vehicle's latest
    assert TIMEOUT_S < cmds[0][0] - start <= TIMEOUT_S + T_S
    gaps = [b2[0] - a[0] for a, b2 in zip(cmds, cmds[1:], strict=False)]
    assert min(gaps) >= T_S - 1e-9  # the frame rate, no faster
    assert len(cmds) == pytest.approx((1.5 - TIMEOUT_S) / T_S, abs=2)
    said = [(now - start, o.text, o.severity) for now, o in sent if isinstance(o, Say)]
    assert [(s, v) for _t, s, v in said] == [
        ("flowhold: HOLD link lost", mav.MAV_SEVERITY_WARNING),
        ("flowhold: HOLD for 1 s, drifting: switch mode", mav.MAV_SEVERITY_CRITICAL)]
    assert LONG_HOLD_S < said[1][0] - said[0][0] <= LONG_HOLD_S + T_S
    # the vehicle back: control resumes at once
    out = b.heartbeat() + b.frame()
    assert _said(out) == [("flowhold: resumed", mav.MAV_SEVERITY_NOTICE)]


def test_the_link_lost_and_back_is_noted_by_the_heartbeat():
    b = Bench()
    b.heartbeat(armed=False)
    assert b.tick() == []
    b.now_s += HEARTBEAT_TIMEOUT_S + 0.01
    assert b.tick() == [Note("flowhold: link lost (no vehicle HEARTBEAT)")]
    assert b.tick() == []
    b.heartbeat(armed=False)
    assert b.tick() == [Note("flowhold: link back")]


def test_a_stall_is_named_its_backlog_dropped_and_control_resumes_from_the_newest_frame():
    b = Bench(setpoint=(0.5, 0.0))
    b.in_control(10)
    b.now_s += 2.0  # the caller stood still; the vehicle sent 10 frames meanwhile (the rest lost)
    out = b.s.on_stall(2.0, b.now_s)
    assert _said(out) == [("flowhold: HOLD companion stalled", mav.MAV_SEVERITY_WARNING)]
    frames = [b.frame_messages() for _ in range(10)]
    for m in (msg for f in frames for msg in f):  # read ahead: every message shown to the clock mapping first
        b.s.observe(m, b.now_s, vehicle=True)
    out = []
    handed = frames[:6] + [frames[3]] + frames[6:]  # frame 3 again after frame 5: out of order
    for k, f in enumerate(handed):
        for m in f:
            out += b.s.on_message(m, b.now_s, vehicle=True, arrival_s=b.now_s, behind=k < len(handed) - 1)
    (c,) = _commands(out)  # one command, from the newest frame
    assert c.time_s == pytest.approx(b.t_s - T_S, abs=1e-9)
    assert c.pitch_rad == _next_pitch(_pi(10, 0.5)[0], 0.5)  # the integrator as before the stall, one step on
    assert _said(out) == [("flowhold: backlog dropped: 9 frames (0.2 s)", mav.MAV_SEVERITY_WARNING),
                          ("flowhold: resumed", mav.MAV_SEVERITY_NOTICE)]
    assert out[1].console.startswith("flowhold: companion stalled for 2.00 s (this process did not run): "
                                     "dropped 9 backlog frames")
    assert b.s.counters["flow frames dropped (too old)"] == 9 and b.s.counters["steps"] == 12
    # frame order runs from the dropped frames too: frame 3 after frame 5 is out of order, not one more drop
    assert b.s.counters["flow frames repeated or out of order"] == 1


def test_frames_older_than_the_age_limit_are_dropped_without_a_stall():
    b = Bench()
    b.in_control(3)
    frames = [b.frame_messages() for _ in range(10)]  # held upstream, delivered at once
    for m in (msg for f in frames for msg in f):
        b.s.observe(m, b.now_s, vehicle=True)
    out = [o for f in frames for o in b.handle(f)]
    n_ok = int(MAX_FRAME_AGE_FRAMES) + 1  # ages 0, T, 2T
    assert len(_commands(out)) == n_ok and 10 - n_ok >= BACKLOG_SAY_FRAMES
    assert _said(out) == [("flowhold: backlog dropped: 7 frames (0.2 s)", mav.MAV_SEVERITY_WARNING)]
    assert b.s.counters["flow frames dropped (too old)"] == 7 and b.s.counters["companion stalls"] == 0


def test_a_repeated_frame_is_dropped_and_a_reboot_restarts_the_clock():
    b = Bench()
    b.in_control(3)
    again = b.frame_messages(advance=False)
    assert _commands(b.handle(again)) and b.handle(again) == []  # the same frame twice: stepped once
    b.t_s -= 0.5  # half a second back: out of order
    assert b.handle(b.frame_messages()) == []
    assert b.s.counters["flow frames repeated or out of order"] == 2
    before = b.s.core.last_frame_time_s
    b.t_s = 0.02  # the vehicle rebooted: its clock starts again
    out = b.handle(b.frame_messages())
    assert out[0] == Note(f"flowhold: the vehicle's clock restarted ({before:.3f} s -> 0.020 s)")
    (c,) = _commands(out)  # and the frame is flown
    assert c.time_s == pytest.approx(0.02) and b.s.counters["vehicle reboots"] == 1


def test_the_live_loop_reaches_into_no_field_of_the_core():
    """The session asks the core (``reset_integrator``, ``restart_checks``, ``frame_order``,
    ``skip_frame``); the live loop asks the session."""
    for name in ("live.py", "session.py"):
        text = (ROOT / "companion" / "mavlink" / name).read_text(encoding="utf-8")
        for reach in (".pi.state", ".plausible.", "last_setpoint_time", "classify_frame("):
            assert reach not in text, (name, reach)


def test_every_session_cause_is_held_by_a_session_here(monkeypatch):
    """The hold causes no step returns (``core.SESSION_CAUSES``; the step's are held equal across
    its forms in tests/test_replay.py) are each reached by the session, in the situations the
    tests above check in detail: the flow stale on the vehicle's clock, the link lost, a stall,
    frames that keep coming too old (a backlog). A new session cause fails here until a
    situation shows it."""
    from companion.step.core import SESSION_CAUSES

    seen: set[HoldCause] = set()

    def bench() -> Bench:
        b = Bench()
        update = b.s.monitor.update
        monkeypatch.setattr(b.s.monitor, "update", lambda cause, now_s: (seen.add(cause), update(cause, now_s))[1])
        b.in_control(5)
        return b

    b = bench()  # the flow stops, the gyro runs on
    for _ in range(round(2 * TIMEOUT_S / T_S)):
        b.gyro_only() + b.tick()
        b.now_s += T_S
    b = bench()  # nothing from the vehicle
    for _ in range(round(2 * TIMEOUT_S / T_S)):
        b.now_s += T_S
        b.tick()
    b = bench()  # the caller stood still
    b.now_s += 2.0
    b.s.on_stall(2.0, b.now_s)
    b = bench()  # a gyro sample 0.4 s ahead, then only flow frames 0.4 s old: each too old to fly on
    frames = [b.frame_messages() for _ in range(40)]
    b.handle(frames[20][:1])
    for f in frames[:20]:
        b.handle(f[2:])
        b.now_s += T_S
        b.tick()
    assert set(SESSION_CAUSES) <= seen, set(SESSION_CAUSES) - seen
