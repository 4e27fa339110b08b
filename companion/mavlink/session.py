"""The live companion's session: engagement, take-over, setpoints, staleness and holds, and what is
said about them, in one object with time passed in (issue 13). ``companion.mavlink.live`` keeps the
socket, the clock and the I/O: it reads the link, hands each message to ``Session.on_message``
with its time, runs ``Session.tick`` (the watchdog) each pass of its loop, and sends what comes
back (``Command``, ``Estimate``, ``Say``, ``Note``). Nothing here reads a clock, opens a socket or
prints; tests drive it message by message (tests/test_session.py).

- engagement: control is taken while the vehicle is armed in GUIDED_NOGPS and the sensor profile
  is known; at each take-over the PI integrator restarts (``CompanionCore.reset_integrator``), yaw
  is held at its take-over value, the flow timeout runs from the take-over, and a level command
  goes out at the latest frame; taking and releasing control are said (NOTICE). While the pilot
  flies, each frame is still stepped (its VISION_SPEED_ESTIMATE published) and the integrator is
  reset after it;
- one control step per new flow frame: the frame order is the core's rule
  (``CompanionCore.frame_order``: a duplicate or out-of-order frame is counted and dropped, one
  more than ``REBOOT_JUMP_S`` older is a vehicle reboot, which restarts the cross-frame checks);
  a frame more than ``MAX_FRAME_AGE_FRAMES`` frame periods old by the link's clock mapping
  (``link.ClockMapping``, fed by ``observe``), or one of a stall's backlog other than the newest
  (``behind``), is dropped and counted (``CompanionCore.skip_frame``), never stepped: a stall is
  not replayed, the integrator is not charged for it;
- setpoints: the constant one (``--setpoint``), or a GCS's SET_POSITION_TARGET_LOCAL_NED / a
  MANUAL_CONTROL stick (``MessageRouter.setpoint`` says whether it was taken), held for
  ``companion.setpoint_timeout_s`` after its last refresh, then ramped back to the constant one
  (``setpoint.decayed_setpoint``); the ramp's start is said once;
- holds, each commanding level attitude: per frame the core's causes; by vehicle time, flow stale
  (the gyro's clock runs on but no new flow frame for ``companion.flow_timeout_s``, one level
  command per frame period of vehicle time); by the caller's clock (``tick``), no flow frame for
  ``flow_timeout_s``: link lost (nothing from the vehicle), companion stalled (``on_stall``),
  backlog (frames come, too old) or flow stale, one level command per frame period, only while
  the vehicle's clock is silent; each cause said once per change (WARNING, ``HoldMonitor``),
  "resumed" (NOTICE) when good again, a hold lasting over ``LONG_HOLD_S`` once more at CRITICAL;
- no command leaves that is not finite and inside the tilt limit (``safe_attitude``).

Counters (steps, commands, holds, drops, what came from another system) are in ``counters``, which
the live loop shares for its own (bad packets, send errors, ...).
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any

from companion.config import Config
from companion.mavlink import link
from companion.mavlink.inbound import MessageRouter, gyro_time_s, scalar_flow
from companion.mavlink_ids import GUIDED_NOGPS
from companion.step.core import CROSS_FRAME_CAUSES, FRAME_REBOOT_S, CompanionCore, FrameOrder, HoldCause, StepOutput
from companion.step.profiles import FLOW_MESSAGE, GYRO_MESSAGES, Profile
from companion.step.setpoint import decayed_setpoint

mav = link.mav

#: a flow frame or gyro sample this much older (s) than the last one is a vehicle reboot
REBOOT_JUMP_S = FRAME_REBOOT_S
#: a vehicle HEARTBEAT older than this (caller's clock, s) means the link is lost
HEARTBEAT_TIMEOUT_S = 3.0
#: a flow frame older than this many frame periods by the link's clock mapping (``link.ClockMapping``)
#: when its turn comes is dropped and counted, never stepped: a stall is not replayed (issue 18)
MAX_FRAME_AGE_FRAMES = 2.0
#: the vehicle's time resolution (time_usec), s: an age at the limit to within it is not over it
AGE_SLACK_S = 1e-6
#: a run of dropped frames at least this long (frame periods) is said (STATUSTEXT and console)
#: even without a stall of the companion; shorter ones are only counted
BACKLOG_SAY_FRAMES = 5
#: a hold lasting longer than this (caller's clock, s) is said once more, at CRITICAL: the pilot's cue
LONG_HOLD_S = 1.0
#: the flow frames the status line's rate is measured over
FLOW_RATE_FRAMES = 50


# ---------------------------------------------------------------------------------------------
# What the session asks its caller to send


@dataclass(frozen=True)
class Command:
    """One control output: POSITION_TARGET_LOCAL_NED (the setpoint tracked), VISION_SPEED_ESTIMATE
    when ``estimate`` is given, then SET_ATTITUDE_TARGET, all stamped with the flow frame's time
    ``time_s`` (vehicle time, s). Every value is finite and the angles inside the tilt limit."""

    time_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    vx_set_m_s: float
    vy_set_m_s: float
    #: (vx m/s, vy m/s, var_x m^2/s^2, var_y m^2/s^2), the variances NaN when the estimator gives none
    estimate: tuple[float, float, float, float] | None


@dataclass(frozen=True)
class Estimate:
    """VISION_SPEED_ESTIMATE alone (the pilot flies: no command), stamped ``time_s`` (s)."""

    time_s: float
    vx_m_s: float
    vy_m_s: float
    vx_var_m2_s2: float
    vy_var_m2_s2: float


@dataclass(frozen=True)
class Say:
    """A STATUSTEXT to the ground station (``severity``: MAV_SEVERITY), and ``console`` (the text
    itself when None) on the console: it may say more than the 50 characters a STATUSTEXT carries."""

    text: str
    severity: int
    console: str | None = None


@dataclass(frozen=True)
class Note:
    """A line for the console only."""

    text: str


Out = Command | Estimate | Say | Note


# ---------------------------------------------------------------------------------------------
# Pure pieces


def safe_attitude(roll_rad: float, pitch_rad: float, limit_rad: float) -> tuple[float, float, bool]:
    """The command that may leave: finite and inside +-limit. Returns (roll, pitch, was_ok);
    a non-finite command becomes level."""
    if not (math.isfinite(roll_rad) and math.isfinite(pitch_rad)):
        return 0.0, 0.0, False
    r = min(max(roll_rad, -limit_rad), limit_rad)
    p = min(max(pitch_rad, -limit_rad), limit_rad)
    return r, p, (r, p) == (roll_rad, pitch_rad)


class HoldMonitor:
    """Turns the hold cause of each step into STATUSTEXTs: one per change of cause; and tells
    when a hold episode (from its first cause to "resumed", whatever the causes between) has
    lasted long enough to be said again (``long_hold``). Times passed in (s)."""

    def __init__(self) -> None:
        self.cause: HoldCause = HoldCause.NONE
        self.episodes = 0
        #: when the current hold episode began (None while not holding, or when not told)
        self.since_s: float | None = None
        self._long_said = False

    def update(self, cause: HoldCause, now_s: float | None = None) -> tuple[str, int] | None:
        """(text, severity) to send, or None when nothing changed. ``now_s``: when the cause
        began (a new episode starts then)."""
        if cause == self.cause:
            return None
        was_holding = self.cause is not HoldCause.NONE
        self.cause = cause
        if cause is HoldCause.NONE:
            self.since_s = None
            return "flowhold: resumed", mav.MAV_SEVERITY_NOTICE
        if not was_holding:
            self.episodes += 1
            self.since_s = now_s
            self._long_said = False
        return f"flowhold: HOLD {cause.value}", mav.MAV_SEVERITY_WARNING

    def long_hold(self, now_s: float, after_s: float) -> bool:
        """True once per episode, when the hold has lasted more than ``after_s``."""
        if self.cause is HoldCause.NONE or self.since_s is None or self._long_said \
                or now_s - self.since_s <= after_s:
            return False
        self._long_said = True
        return True


def vehicle_time_s(msg: Any) -> float | None:
    """The vehicle's boot time a message carries (s): ``time_boot_ms``, or a gyro's ``time_usec``;
    None for messages without one (and for the flow, whose ``time_usec`` unit depends on the profile)."""
    ms = getattr(msg, "time_boot_ms", None)
    if ms is not None:
        return float(ms) * 1e-3
    if msg.get_type() in GYRO_MESSAGES:
        return gyro_time_s(msg)
    return None


# ---------------------------------------------------------------------------------------------
# The session


class Session:
    """The companion's side of one link to one vehicle (see the module docstring).

    ``now_s`` is the caller's monotonic clock (s); vehicle times come in the messages. Each
    ``on_message``, ``tick`` and ``on_stall`` returns what to send, in order. ``profile``: the
    sensor profile, or None while the caller is still detecting it (``set_profile`` binds it;
    until then no flow frame is stepped and control is not taken)."""

    def __init__(self, cfg: Config, profile: Profile | None = None, *, vehicle_sysid: int | None = None,
                 setpoint_m_s: tuple[float, float] | None = None) -> None:
        self.cfg = cfg
        self.profile = profile if profile is not None else Profile.PAPER
        self.profile_known = profile is not None
        self.core = CompanionCore(cfg, self.profile)
        self.router = MessageRouter(self.core, self.profile, vehicle_sysid=vehicle_sysid)
        self.T = cfg.flow_sensor.frame_period_s
        self.tilt_limit = cfg.controller.tilt_limit_rad
        self.max_frame_age_s = MAX_FRAME_AGE_FRAMES * self.T
        #: the vehicle's clock seen from ours: how old each frame is when its turn comes
        self.clockmap = link.ClockMapping(jump_s=REBOOT_JUMP_S)
        self.monitor = HoldMonitor()
        self.counters: Counter[str] = Counter()
        # setpoints
        self.base_setpoint = setpoint_m_s or (0.0, 0.0)
        self.gcs_setpoint: tuple[float, float] | None = None
        self.gcs_setpoint_s = 0.0  # when it was last refreshed
        self._ramp_said = False  # "GCS setpoints stopped" said for the current setpoint
        # the vehicle and engagement
        self.armed = False
        self.mode = -1
        self.in_control = False
        self.yaw_hold = 0.0
        self.control_start: float | None = None
        # sensor clocks (vehicle time, s)
        self.flow_ref_s: float | None = None  # vehicle time from which flow staleness is measured
        self.last_gyro_time_s: float | None = None
        self.vehicle_time_s: float | None = None  # time of the latest gyro or flow sample
        self.last_hold_stamp_s: float | None = None
        # the caller's clock (s)
        self.last_flow_s = -math.inf  # the last frame stepped (or the take-over)
        self.last_vehicle_s = -math.inf  # anything from the vehicle
        self.last_heartbeat_s = -math.inf
        self.last_cmd_s = -math.inf
        #: the last command paced by the vehicle's clock (a step, or a vehicle-time hold)
        self.last_vehicle_cmd_s = -math.inf
        self._next_wall_hold = -math.inf
        self._link_lost_said = False
        # what was last done
        self.last_step: StepOutput | None = None
        self.last_held = False  # the last step held
        self.last_cmd_rad = (0.0, 0.0)
        #: since the last frame stepped: the longest stall of the caller's loop (s), and the frames
        #: dropped as too old (how many, and the oldest's age, s)
        self._stall_gap_s = 0.0
        self._drops = 0
        self._drop_oldest_s = 0.0
        self._flow_times: deque[float] = deque(maxlen=FLOW_RATE_FRAMES)
        self._out: list[Out] = []

    # -- the caller's entry points -------------------------------------------------------

    def set_profile(self, profile: Profile) -> None:
        """Bind the sensor profile once the caller has told which it is."""
        self.profile = profile
        self.profile_known = True
        self.router.profile = profile
        self.core.set_profile(profile)

    def observe(self, msg: Any, arrival_s: float, *, vehicle: bool) -> None:
        """Show the clock mapping a vehicle sample's time (its own clock: ``time_boot_ms``, a gyro's
        ``time_usec``, the flow frame's time in the profile's unit), as it arrives (``arrival_s``,
        the caller's clock): the caller shows every message it has read before handling any, so
        that a frame of a backlog is aged against the newest sample behind it."""
        if not vehicle:
            return
        try:
            t = vehicle_time_s(msg)
            if t is None and self.profile_known and msg.get_type() == FLOW_MESSAGE[self.profile]:
                t = scalar_flow(msg, self.profile, self.cfg.flow_sensor.q_rad_per_count).time_s
            if t is not None:
                self.clockmap.observe(float(t), arrival_s)
        except Exception:  # noqa: BLE001 - a time that cannot be read is no evidence (the handler will say)
            return

    def on_message(self, msg: Any, now_s: float, *, vehicle: bool, arrival_s: float,
                   behind: bool = False) -> list[Out]:
        """Handle one message at ``now_s``: ``vehicle`` whether it comes from the vehicle,
        ``arrival_s`` when it arrived (``observe``d then), ``behind`` a flow frame of a stall's
        backlog that is not the newest (dropped). Commands to and from the link (COMMAND_LONG,
        COMMAND_ACK) are the caller's; ``on_vehicle_state`` tells what they changed."""
        mtype = msg.get_type()
        if vehicle:
            self.last_vehicle_s = max(self.last_vehicle_s, min(arrival_s, now_s))
        if mtype == "STATUSTEXT":
            if vehicle:  # a simulator's clock notice: the rate of the vehicle's clock (lockstep: 0)
                self.clockmap.set_clock_text(str(msg.text))
        elif mtype == "HEARTBEAT":
            if vehicle:
                self.last_heartbeat_s = now_s
                self.armed = link.heartbeat_armed(msg)
                self.mode = msg.custom_mode
        elif mtype in ("COMMAND_ACK", "COMMAND_LONG", "COMMAND_INT"):
            pass  # the caller's (it sends the commands and answers those to the companion)
        elif mtype in ("SET_POSITION_TARGET_LOCAL_NED", "MANUAL_CONTROL"):
            if self.router.setpoint(msg, now_s):
                self.gcs_setpoint = self.core.setpoint_m_s  # as the core took it (clipped)
                self.gcs_setpoint_s = now_s
                self._ramp_said = False
        elif mtype in ("OPTICAL_FLOW", "OPTICAL_FLOW_RAD") and not self.profile_known:
            if vehicle:
                self.counters["flow frames before the profile was known"] += 1
            else:
                self.counters["sensor data from another system"] += 1
        elif mtype == FLOW_MESSAGE[self.profile]:
            if vehicle:
                self._on_flow(msg, now_s, behind)
            else:
                self.counters["sensor data from another system"] += 1
        elif mtype in GYRO_MESSAGES:
            if vehicle:
                self.router.handle(msg, now_s)
                self._on_gyro_time(gyro_time_s(msg), now_s)
            else:
                self.counters["sensor data from another system"] += 1
        elif vehicle:
            self.router.handle(msg, now_s)  # DISTANCE_SENSOR, ATTITUDE (yaw, angles and rates)
        elif mtype in ("DISTANCE_SENSOR", "ATTITUDE"):
            self.counters["sensor data from another system"] += 1
        self._update_control(now_s)
        return self._take()

    def on_vehicle_state(self, now_s: float, *, armed: bool | None = None, mode: int | None = None) -> list[Out]:
        """The vehicle's state as a command's acknowledgement tells it (armed, the custom mode);
        its HEARTBEATs tell it through ``on_message``."""
        if armed is not None:
            self.armed = armed
        if mode is not None:
            self.mode = mode
        self._update_control(now_s)
        return self._take()

    def tick(self, now_s: float) -> list[Out]:
        """The watchdog, each pass of the caller's loop: the link lost or back (HEARTBEAT), the
        GCS's setpoints stopping, no flow frame for ``flow_timeout_s`` (a level command at the frame
        rate while the vehicle's clock is silent), a hold lasting over ``LONG_HOLD_S``."""
        lost = now_s - self.last_heartbeat_s > HEARTBEAT_TIMEOUT_S
        if lost != self._link_lost_said:
            self._link_lost_said = lost
            self._out.append(Note("flowhold: link lost (no vehicle HEARTBEAT)" if lost else "flowhold: link back"))
        if not self.in_control:
            return self._take()
        sp_timeout = self.cfg.companion.setpoint_timeout_s
        if self.gcs_setpoint is not None and not self._ramp_said and now_s - self.gcs_setpoint_s > sp_timeout:
            self._ramp_said = True  # issue 18: say it when the GCS's setpoints stop and the ramp begins
            self._say("flowhold: GCS setpoints stopped, ramp to hold", mav.MAV_SEVERITY_WARNING,
                      console=f"flowhold: GCS setpoints stopped for {sp_timeout:g} s: ramping to "
                              f"{self.base_setpoint[0]:+.2f} {self.base_setpoint[1]:+.2f} m/s over "
                              f"{sp_timeout:g} s")
        timeout = self.cfg.companion.flow_timeout_s
        if now_s - self.last_flow_s <= timeout:
            self._next_wall_hold = now_s + self.T
        elif now_s >= self._next_wall_hold and now_s - self.last_cmd_s >= 0.5 * self.T \
                and now_s - self.last_vehicle_cmd_s > 1.5 * self.T:
            # the caller's clock commands only while the vehicle's clock is silent: one clock at a
            # time, one level command per frame period (issue 18: both fired, ~100 Hz)
            self._next_wall_hold = max(self._next_wall_hold + self.T, now_s - self.T)  # frame rate, no burst
            if now_s - self.last_vehicle_s > timeout:
                cause = HoldCause.LINK
            elif self._stall_gap_s:  # the companion itself stood still, and no fresh frame since
                cause = HoldCause.COMPANION_STALLED
            elif self._drops:  # frames come, but too old to fly on
                cause = HoldCause.BACKLOG
            else:
                cause = HoldCause.FLOW_STALE
            self.counters[f"holds: {cause.value} (wall clock)"] += 1
            # stamped with the vehicle's latest sensor time: a lockstep vehicle waiting on that frame takes
            # it, one that has moved on (its frames arrive whole, flow with gyro) ignores it as stale
            stamp = self.vehicle_time_s if self.vehicle_time_s is not None else 0.0
            self._level(stamp, now_s)
            self._report(cause, now_s)
        if self.monitor.long_hold(now_s, LONG_HOLD_S):  # issue 18: the pilot's cue
            self._say(f"flowhold: HOLD for {LONG_HOLD_S:g} s, drifting: switch mode", mav.MAV_SEVERITY_CRITICAL,
                      console=f"flowhold: holding level for {LONG_HOLD_S:.1f} s ({self.monitor.cause.value}): "
                              "level is not hover, the vehicle drifts with the wind: switch mode (LAND, ALT_HOLD)")
        return self._take()

    def on_stall(self, gap_s: float, now_s: float) -> list[Out]:
        """The caller's loop did not run for ``gap_s`` (> ``flow_timeout_s``): the process was
        stopped, starved or swapped out. The hold is named (not "link lost": the link may well be
        fine); the caller then hands in what waited, every flow frame but the newest ``behind``."""
        self.counters["companion stalls"] += 1
        self._stall_gap_s = max(self._stall_gap_s, gap_s)
        if self.in_control:
            self._report(HoldCause.COMPANION_STALLED, now_s - gap_s)
        return self._take()

    def setpoint(self, now_s: float) -> tuple[float, float]:
        """The velocity setpoint flown at ``now_s`` (m/s, body frame)."""
        if self.gcs_setpoint is None:
            return self.base_setpoint
        return decayed_setpoint(self.gcs_setpoint, self.base_setpoint, now_s - self.gcs_setpoint_s,
                                self.cfg.companion.setpoint_timeout_s)

    def flow_rate_hz(self) -> float:
        """The rate of the frames stepped lately, on the caller's clock (0 before two)."""
        t = self._flow_times
        if len(t) >= 2 and t[-1] > t[0]:
            return (len(t) - 1) / (t[-1] - t[0])
        return 0.0

    # -- the flow, the gyro's clock, engagement --------------------------------------------

    def _on_flow(self, msg: Any, now_s: float, behind: bool) -> None:
        f = scalar_flow(msg, self.profile, self.cfg.flow_sensor.q_rad_per_count)
        t = f.time_s
        order = self.core.frame_order(t)
        if order is FrameOrder.DUPLICATE:
            self.counters["flow frames repeated or out of order"] += 1
            return
        if order is FrameOrder.REBOOT:
            self.counters["vehicle reboots"] += 1
            self.core.restart_checks()
            self._out.append(Note(f"flowhold: the vehicle's clock restarted ({self.core.last_frame_time_s:.3f} s "
                                  f"-> {t:.3f} s)"))
        age = self.clockmap.age_s(t, now_s)
        if (behind or age > self.max_frame_age_s + AGE_SLACK_S) and not self.core.is_repeat(f):
            self._drop_frame(t, age)  # a stall is not replayed: never stepped, never commanded
            return
        self.core.set_setpoint(*self.setpoint(now_s))
        out = self.core.on_flow(f)
        if out.repeat:  # the same flow sample again (ArduPilot streams faster than the sensor)
            self.counters["flow samples repeated"] += 1
            return
        if math.isfinite(t):
            self.flow_ref_s = t
            self.vehicle_time_s = t
        self.last_flow_s = now_s
        self._flow_times.append(now_s)
        self.counters["steps"] += 1
        if out.hold_cause in CROSS_FRAME_CAUSES:
            self.counters[f"holds: {out.hold_cause.value}"] += 1
        self.last_step = out
        self.last_held = out.holding
        if not self.in_control:
            self.core.reset_integrator()  # the pilot flies: no integration
            if not out.holding:
                self._out.append(Estimate(out.time_s, out.vx_m_s, out.vy_m_s, out.vx_var_m2_s2, out.vy_var_m2_s2))
            return
        self.last_vehicle_cmd_s = now_s
        self._command(out.time_s, out.roll_cmd_rad, out.pitch_cmd_rad, out.vx_set_m_s, out.vy_set_m_s, now_s,
                      estimate=None if self.last_held else (out.vx_m_s, out.vy_m_s, out.vx_var_m2_s2,
                                                            out.vy_var_m2_s2))
        self._say_backlog()
        self._report(out.hold_cause, now_s)

    def _drop_frame(self, t: float, age_s: float) -> None:
        """A flow frame too old to fly on: counted, and its time noted (the flow is not stale,
        the frame is late), but not stepped: the integrator is not charged for a stall."""
        self.counters["flow frames dropped (too old)"] += 1
        self._drops += 1
        self._drop_oldest_s = max(self._drop_oldest_s, age_s)
        self.core.skip_frame(t)
        if math.isfinite(t):
            self.flow_ref_s = t
            self.vehicle_time_s = t

    def _say_backlog(self) -> None:
        """At the first frame stepped after a stall or a run of dropped frames: say how many were
        dropped (STATUSTEXT WARNING and console); a few late frames are only counted."""
        n, oldest, gap = self._drops, self._drop_oldest_s, self._stall_gap_s
        self._drops, self._drop_oldest_s, self._stall_gap_s = 0, 0.0, 0.0
        if not gap and n < BACKLOG_SAY_FRAMES:
            return
        resumed = "resumed from the newest frame, integrator as it was"
        if gap:
            console = (f"flowhold: companion stalled for {gap:.2f} s (this process did not run): dropped {n} "
                       f"backlog frames (the oldest {oldest:.2f} s old); {resumed}")
        else:
            console = (f"flowhold: dropped {n} flow frames older than {self.max_frame_age_s * 1e3:.0f} ms "
                       f"(a backlog on the link, the oldest {oldest:.2f} s old); {resumed}")
        self._say(f"flowhold: backlog dropped: {n} frames ({oldest:.1f} s)", mav.MAV_SEVERITY_WARNING,
                  console=console)

    def _on_gyro_time(self, t_s: float, now_s: float) -> None:
        """Flow staleness on the vehicle's own clock: the gyro's time runs on, the flow's does not."""
        if self.last_gyro_time_s is not None and t_s < self.last_gyro_time_s - REBOOT_JUMP_S:
            self.flow_ref_s = None  # reboot (or a bogus time): measure again from the next sample
        self.last_gyro_time_s = t_s
        self.vehicle_time_s = t_s
        if not self.in_control or self.clockmap.age_s(t_s, now_s) > self.max_frame_age_s + AGE_SLACK_S:
            return  # (a sample of a backlog commands nothing)
        if self.flow_ref_s is None or t_s < self.flow_ref_s - REBOOT_JUMP_S:
            self.flow_ref_s = t_s
        # one level command per frame period of vehicle time (the gyro may stream faster than the flow)
        if t_s - self.flow_ref_s > self.cfg.companion.flow_timeout_s + 1e-9 and (
                self.last_hold_stamp_s is None or not 0.0 <= t_s - self.last_hold_stamp_s < 0.999 * self.T):
            self.last_hold_stamp_s = t_s
            self.last_vehicle_cmd_s = now_s
            self.counters["holds: flow stale (vehicle time)"] += 1
            self._level(t_s, now_s)
            self._report(HoldCause.FLOW_STALE, now_s)

    def _update_control(self, now_s: float) -> None:
        want = self.armed and self.mode == GUIDED_NOGPS and self.profile_known
        if want and not self.in_control:
            self.in_control = True
            self.core.reset_integrator()
            self.yaw_hold = self.router.yaw_rad
            self.control_start = now_s if self.control_start is None else self.control_start
            last_frame_s = self.core.last_frame_time_s
            self.flow_ref_s = last_frame_s
            self.last_flow_s = max(self.last_flow_s, now_s)  # the flow timeout runs from the take-over
            self._say("flowhold: in control (GUIDED_NOGPS)", mav.MAV_SEVERITY_NOTICE,
                      console="flowhold: in control (armed, GUIDED_NOGPS)")
            if last_frame_s is not None:  # take over from level at the latest frame
                self._level(last_frame_s, now_s)
        elif not want and self.in_control:
            self.in_control = False
            why = link.mode_name(self.mode) if self.armed else "disarmed"
            self._say(f"flowhold: released control ({why})", mav.MAV_SEVERITY_NOTICE,
                      console=f"flowhold: released control ({'armed' if self.armed else 'disarmed'}, "
                              f"{link.mode_name(self.mode)})")

    # -- output ----------------------------------------------------------------------------

    def _level(self, time_s: float, now_s: float) -> None:
        """A level command (a hold, or the take-over) at the setpoint flown now."""
        sp = self.setpoint(now_s)
        self._command(time_s, 0.0, 0.0, sp[0], sp[1], now_s, estimate=None)

    def _command(self, time_s: float, roll: float, pitch: float, vx_set: float, vy_set: float, now_s: float, *,
                 estimate: tuple[float, float, float, float] | None) -> None:
        roll, pitch, ok = safe_attitude(roll, pitch, self.tilt_limit)
        if not ok:
            self.counters["commands clipped or levelled"] += 1
        if not (math.isfinite(vx_set) and math.isfinite(vy_set)):
            vx_set = vy_set = 0.0
        if estimate is not None and not all(math.isfinite(v) for v in estimate[:2]):
            estimate = None
        self._out.append(Command(time_s, roll, pitch, self.yaw_hold, vx_set, vy_set, estimate))
        self.last_cmd_s = now_s
        self.last_cmd_rad = (roll, pitch)
        self.counters["commands"] += 1

    def _report(self, cause: HoldCause, now_s: float) -> None:
        said = self.monitor.update(cause, now_s)
        if said is not None:
            self._say(*said)

    def _say(self, text: str, severity: int, console: str | None = None) -> None:
        self._out.append(Say(text, severity, console))

    def _take(self) -> list[Out]:
        out, self._out = self._out, []
        return out
