"""The simulated vehicle over MAVLink/UDP: ``python -m simvehicle serve``.

An ArduCopter-like quadrotor (CONVENTIONS.md, "The simulated vehicle") around the reference
simulator (``simvehicle.model.sim.Simulator``, the physics) and ``simvehicle.model.telemetry`` (the message
encoding), so the loop over UDP flies exactly what the in-process scenarios fly.

Two layers, as STYLE.md asks (the network adapter wraps the model, never the reverse):

- ``Vehicle``: the autopilot's state machine, free of sockets and clocks: modes and arming
  (GUIDED_NOGPS = custom_mode 20), SET_ATTITUDE_TARGET validation and GUID_TIMEOUT, parameters
  (``SIM_*`` effects and faults), the per-frame sensor messages with faults applied.
- ``UdpVehicle``: one UDP socket, every peer that sent a valid packet is served and packets are
  routed between peers as an autopilot routes between its links; per-peer stream intervals;
  the clock (real time, ``--speedup X`` or ``--lockstep``); the ``--tlog`` recording.

Timing (CONVENTIONS.md: the command computed from frame k acts from frame k+1):

- real time / speedup: frame k is sent at wall time ``t_k / X``; the last valid
  SET_ATTITUDE_TARGET received during [t_k, t_k+1) becomes active at t_k+1.
- lockstep: frame k is sent, then the vehicle waits for the SET_ATTITUDE_TARGET whose
  ``time_boot_ms`` is frame k's time (stale ones are ignored) and advances at once; if none comes
  within ``LOCKSTEP_WAIT_S`` of wall time (companion not running, not armed in GUIDED_NOGPS) it
  advances anyway with the GUID_TIMEOUT rule applied in simulated time. The simulated clock
  starts when the first peer is heard. ``--max-speedup X`` caps it at X times real time (frame k
  not before wall time ``t_k / X``), so that a reader of the streams slower than the loop (a
  ground station, a test) is not left behind with a socket that overflows.

The vehicle's recording is stamped with simulated time, so a lockstep recording has the same
time axis as a real-time one: in real time from the UNIX time at start; in lockstep and
speed-up from ``SIM_EPOCH_S`` (2026-01-01), as a SITL's log is, and the vehicle says so to each new
peer in a STATUSTEXT ("simvehicle: simulated clock (lockstep)"), which the recordings keep.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import select
import signal
import socket
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import (
    AttitudeDynamics,
    Config,
    FlowDelay,
    FlowScale,
    FlowYawMisalignment,
    GyroBias,
    LinearDrag,
    RangeOffset,
    load_config,
    with_effects,
)
from companion.errors import LinkError, RecordingError, UsageError, check_output, output_error
from companion.mavlink import link
from companion.mavlink.outbound import VELOCITY_TYPE_MASK
from companion.mavlink_ids import COMPANION_COMPONENT, GUIDED_NOGPS
from companion.recordings.load import MessageTable, load_recording
from companion.recordings.signals import (
    Attitude,
    AttitudeCommand,
    companion_commands,
    companion_table,
    downward_range,
    gyro_sensor,
    time_ms,
    vehicle_flow,
    vehicle_table,
)
from companion.recordings.tlog_writer import SIM_CLOCK_TEXT, SIM_EPOCH_S, TlogWriter
from companion.rotation import quaternion_to_euler
from companion.step.profiles import FLOW_MESSAGE, Profile, detect_profile
from simvehicle.engines.scenarios import SCENARIOS, Run, Scenario
from simvehicle.model import telemetry
from simvehicle.model.sim import FrameSample, Simulator, Turbulence

mav = link.mav

#: lockstep: wall-clock wait for the companion's command before advancing anyway (s)
LOCKSTEP_WAIT_S = 0.2
#: a peer not heard for this long (wall clock, s) is no longer streamed to
PEER_TIMEOUT_S = 30.0
#: ArduCopter modes this vehicle accepts (no GPS: the position modes are refused)
SUPPORTED_MODES = frozenset({0, 2, 9, 20})  # STABILIZE, ALT_HOLD, LAND, GUIDED_NOGPS
ARMABLE_MODES = frozenset({0, 2, 20})
STABILIZE = 0
LAND = 9
#: the scenario's velocity setpoints are sent as this ground station would (sysid, compid)
SCENARIO_GCS = (255, mav.MAV_COMP_ID_MISSIONPLANNER)
#: |q| may differ from 1 by this much (float32 rounding is ~1e-7)
QUATERNION_NORM_TOL = 1e-3


# ---------------------------------------------------------------------------------------------
# Parameters


class FlowFault(enum.IntEnum):
    NONE = 0
    QUALITY_ZERO = 1  # frames keep coming with quality 0 and no counts
    FROZEN = 2  # the sensor repeats its last frame (same time and counts): stale
    SPIKE = 3  # the next frame carries SIM_FLOW_SPIKE extra counts on both axes, once
    STOPPED = 4  # no flow messages
    STUCK = 5  # frames keep coming on time, quality kept, with the counts of the frame before the fault


class GyroFault(enum.IntEnum):
    NONE = 0
    FROZEN = 1  # RAW_IMU repeats its last sample (same time and rates)
    SATURATED = 2  # the gyro reads its full range (RAW_IMU clips at +-32767 mrad/s)
    STOPPED = 3  # no RAW_IMU
    STUCK = 4  # RAW_IMU keeps coming on time with the rates of the sample before the fault


class RangeFault(enum.IntEnum):
    NONE = 0
    TOO_FAR = 1  # reads 1 m beyond the sensor's maximum
    TOO_NEAR = 2  # reads 0 (below its minimum: no echo)
    STOPPED = 3  # no DISTANCE_SENSOR
    JUMP = 4  # one reading SIM_RNG_JUMP m off (inside the sensor's limits), then clears itself


@dataclass(frozen=True)
class ParamSpec:
    """One vehicle parameter: its default, its valid range and what it means (with units)."""

    name: str
    default: float
    lo: float
    hi: float
    integer: bool
    doc: str

    @property
    def mav_type(self) -> int:
        return mav.MAV_PARAM_TYPE_INT32 if self.integer else mav.MAV_PARAM_TYPE_REAL32

    def check(self, value: float) -> float:
        """The value to store, or ValueError with the reason."""
        if not math.isfinite(value):
            raise ValueError(f"{self.name} must be finite")
        if self.integer:
            if value != round(value):
                raise ValueError(f"{self.name} must be an integer")
            value = float(round(value))
        if not self.lo <= value <= self.hi:
            raise ValueError(f"{self.name} must be in [{self.lo:g}, {self.hi:g}]")
        return value


def param_specs(cfg: Config) -> tuple[ParamSpec, ...]:
    """The vehicle's parameters; effect defaults come from ``cfg`` (its enabled effects)."""
    e, a = cfg.effects, cfg.airframe
    att = e.attitude_dynamics
    return (
        ParamSpec("GUID_TIMEOUT", 0.5, 0.05, 30.0, False,
                  "s: GUIDED_NOGPS without a new SET_ATTITUDE_TARGET for this long levels and holds"),
        ParamSpec("ANGLE_MAX", 3000.0, 1000.0, 8000.0, True, "cdeg: the vehicle clamps lean targets to this"),
        ParamSpec("SIM_WIND_FX", 0.0, -100.0, 100.0, False, "N: steady force along body x from when it is set"),
        ParamSpec("SIM_WIND_FY", 0.0, -100.0, 100.0, False, "N: steady force along body y from when it is set"),
        ParamSpec("SIM_DRAG_B", e.linear_drag.b if e.linear_drag else 0.0, 0.0, 20.0, False,
                  "N s/m: linear_drag effect, force -b v (0 = off, the paper's eq. 28)"),
        ParamSpec("SIM_GYRO_BIAS_X", e.gyro_bias.bias_x if e.gyro_bias else 0.0, -1.0, 1.0, False,
                  "rad/s: gyro_bias effect on the roll-rate gyro"),
        ParamSpec("SIM_GYRO_BIAS_Y", e.gyro_bias.bias_y if e.gyro_bias else 0.0, -1.0, 1.0, False,
                  "rad/s: gyro_bias effect on the pitch-rate gyro"),
        ParamSpec("SIM_FLOW_SCALE_X", e.flow_scale.scale_x if e.flow_scale else 1.0, 0.1, 10.0, False,
                  "flow_scale effect: true rad per count = scale x Q, x axis (1 = off)"),
        ParamSpec("SIM_FLOW_SCALE_Y", e.flow_scale.scale_y if e.flow_scale else 1.0, 0.1, 10.0, False,
                  "flow_scale effect, y axis (1 = off)"),
        ParamSpec("SIM_FLOW_DELAY", e.flow_delay.delay if e.flow_delay else 0.0, 0.0, 0.5, False,
                  "s: flow_delay effect, flow lags the gyro by this beyond one frame (0 = off)"),
        ParamSpec("SIM_FLOW_YAW", e.flow_yaw_misalignment.yaw if e.flow_yaw_misalignment else 0.0,
                  -math.pi, math.pi, False, "rad: flow_yaw_misalignment effect, sensor axes turned about z"),
        ParamSpec("SIM_ATT_OMEGA", att.omega_p if att else a.omega_p_rad_s, 0.5, 50.0, False,
                  "rad/s: attitude_dynamics effect, attitude-loop natural frequency (nominal = off)"),
        ParamSpec("SIM_ATT_ZETA", att.zeta if att else a.zeta, 0.05, 5.0, False,
                  "attitude_dynamics effect, attitude-loop damping (nominal = off)"),
        ParamSpec("SIM_RNG_OFFSET", e.range_offset.offset if e.range_offset else 0.0, -2.0, 2.0, False,
                  "m: range_offset effect, the rangefinder reads true + offset"),
        ParamSpec("FLOW_FXSCALER", 0.0, -800.0, 800.0, True,
                  "per mille: ArduPilot's flow X-rate scale correction, applied to the ardupilot profile's flow"),
        ParamSpec("FLOW_FYSCALER", 0.0, -800.0, 800.0, True,
                  "per mille: ArduPilot's flow Y-rate scale correction, applied to the ardupilot profile's flow"),
        ParamSpec("FLOW_ORIENT_YAW", 0.0, -17999.0, 18000.0, True,
                  "cdeg: ArduPilot's flow sensor yaw, turns the ardupilot profile's flow rates into body axes"),
        ParamSpec("SIM_FLOW_FAULT", 0.0, 0.0, 5.0, True,
                  "0 none, 1 quality 0, 2 frozen (repeats its last frame), 3 one spike, 4 stream stops, "
                  "5 stuck counts (on time)"),
        ParamSpec("SIM_FLOW_SPIKE", 500.0, -30000.0, 30000.0, True,
                  "counts: the spike SIM_FLOW_FAULT = 3 adds to one frame on both axes"),
        ParamSpec("SIM_GYRO_FAULT", 0.0, 0.0, 4.0, True,
                  "0 none, 1 frozen, 2 saturated, 3 stream stops, 4 stuck rates (on time)"),
        ParamSpec("SIM_RNG_FAULT", 0.0, 0.0, 4.0, True,
                  "0 none, 1 reads beyond its maximum, 2 reads 0 (below its minimum), 3 stream stops, "
                  "4 one reading off by SIM_RNG_JUMP"),
        ParamSpec("SIM_RNG_JUMP", 2.0, -4.0, 4.0, False,
                  "m: how far the one reading of SIM_RNG_FAULT = 4 is off (kept inside the sensor's limits)"),
        ParamSpec("SIM_REBOOT", 0.0, 0.0, 1.0, True,
                  "1: the boot clock restarts at 0 (time fields jump back; the vehicle flies on)"),
        ParamSpec("FHW_ENABLE", 0.0, 0.0, 1.0, True,
                  "1: the flowhold watchdog applet runs (companion/ardupilot/flowhold_watchdog.lua): armed in "
                  "GUIDED_NOGPS, no SET_ATTITUDE_TARGET from the companion for FHW_TIMEOUT switches to FHW_MODE"),
        ParamSpec("FHW_TIMEOUT", 1.0, 0.1, 30.0, False,
                  "s: the watchdog's wait for the companion's commands (simulated time)"),
        ParamSpec("FHW_MODE", 9.0, 0.0, 30.0, True,
                  "the mode the watchdog switches to: 9 LAND, 2 ALT_HOLD (a mode refused here, as BRAKE without "
                  "GPS, gives LAND)"),
    )


def config_with_params(cfg: Config, values: dict[str, float]) -> Config:
    """``cfg`` with the effects the ``SIM_*`` parameters describe (a parameter at its
    nominal value switches its effect off). The ``wind_force`` window effect stays as ``cfg`` has it."""
    a = cfg.airframe
    v = values
    b = v["SIM_DRAG_B"]
    bx, by = v["SIM_GYRO_BIAS_X"], v["SIM_GYRO_BIAS_Y"]
    sx, sy = v["SIM_FLOW_SCALE_X"], v["SIM_FLOW_SCALE_Y"]
    d, yaw, off = v["SIM_FLOW_DELAY"], v["SIM_FLOW_YAW"], v["SIM_RNG_OFFSET"]
    wp, z = v["SIM_ATT_OMEGA"], v["SIM_ATT_ZETA"]
    return with_effects(
        cfg,
        linear_drag=LinearDrag(b) if b != 0.0 else None,
        gyro_bias=GyroBias(bx, by) if (bx, by) != (0.0, 0.0) else None,
        flow_scale=FlowScale(sx, sy) if (sx, sy) != (1.0, 1.0) else None,
        flow_delay=FlowDelay(d) if d > 0.0 else None,
        flow_yaw_misalignment=FlowYawMisalignment(yaw) if yaw != 0.0 else None,
        attitude_dynamics=AttitudeDynamics(wp, z) if (wp, z) != (a.omega_p_rad_s, a.zeta) else None,
        range_offset=RangeOffset(off) if off != 0.0 else None,
    )


# ---------------------------------------------------------------------------------------------
# Sensor faults (pure)


@dataclass(frozen=True)
class SensorFrame:
    """What each sensor reports at one frame (None: it sends nothing). Times are boot times."""

    flow: FrameSample | None
    gyro: FrameSample | None
    range: FrameSample | None


def faulted_sensors(s: FrameSample, *, flow_fault: FlowFault, gyro_fault: GyroFault, range_fault: RangeFault,
                    spike_counts: int, last_flow: FrameSample | None, last_gyro: FrameSample | None,
                    range_max_m: float, gyro_range_rad_s: float, stuck_flow: FrameSample | None = None,
                    stuck_gyro: FrameSample | None = None, range_jump_m: float = 0.0,
                    range_min_m: float = 0.0) -> SensorFrame:
    """Apply the injected faults to one frame's sensor sample ``s`` (already on the boot clock).

    ``stuck_flow`` / ``stuck_gyro``: the sample whose counts / rates a STUCK sensor keeps
    repeating (default: ``s`` itself); ``range_jump_m``: the offset of a JUMP reading, kept
    inside [``range_min_m``, ``range_max_m``]."""
    flow: FrameSample | None = s
    if flow_fault is FlowFault.QUALITY_ZERO:
        flow = dataclasses.replace(s, flow_x_counts=0, flow_y_counts=0, flow_quality=0)
    elif flow_fault is FlowFault.FROZEN:
        flow = last_flow if last_flow is not None else s
    elif flow_fault is FlowFault.SPIKE:
        flow = dataclasses.replace(s, flow_x_counts=s.flow_x_counts + spike_counts,
                                   flow_y_counts=s.flow_y_counts + spike_counts)
    elif flow_fault is FlowFault.STOPPED:
        flow = None
    elif flow_fault is FlowFault.STUCK:
        ref = stuck_flow if stuck_flow is not None else s
        flow = dataclasses.replace(s, flow_x_counts=ref.flow_x_counts, flow_y_counts=ref.flow_y_counts,
                                   flow_quality=ref.flow_quality)
    gyro: FrameSample | None = s
    if gyro_fault is GyroFault.FROZEN:
        gyro = last_gyro if last_gyro is not None else s
    elif gyro_fault is GyroFault.SATURATED:
        gyro = dataclasses.replace(s, gyro_x_rad_s=math.copysign(gyro_range_rad_s, s.gyro_x_rad_s),
                                   gyro_y_rad_s=math.copysign(gyro_range_rad_s, s.gyro_y_rad_s))
    elif gyro_fault is GyroFault.STOPPED:
        gyro = None
    elif gyro_fault is GyroFault.STUCK:
        ref = stuck_gyro if stuck_gyro is not None else s
        gyro = dataclasses.replace(s, gyro_x_rad_s=ref.gyro_x_rad_s, gyro_y_rad_s=ref.gyro_y_rad_s,
                                   gyro_z_rad_s=ref.gyro_z_rad_s)
    rng: FrameSample | None = s
    if range_fault is RangeFault.TOO_FAR:
        rng = dataclasses.replace(s, range_m=range_max_m + 1.0)
    elif range_fault is RangeFault.TOO_NEAR:
        rng = dataclasses.replace(s, range_m=0.0)
    elif range_fault is RangeFault.STOPPED:
        rng = None
    elif range_fault is RangeFault.JUMP:
        rng = dataclasses.replace(s, range_m=min(max(s.range_m + range_jump_m, range_min_m), range_max_m))
    return SensorFrame(flow, gyro, rng)


# ---------------------------------------------------------------------------------------------
# Streams


STREAM_IDS = {
    "RAW_IMU": mav.MAVLINK_MSG_ID_RAW_IMU,
    "DISTANCE_SENSOR": mav.MAVLINK_MSG_ID_DISTANCE_SENSOR,
    "OPTICAL_FLOW": mav.MAVLINK_MSG_ID_OPTICAL_FLOW,
    "OPTICAL_FLOW_RAD": mav.MAVLINK_MSG_ID_OPTICAL_FLOW_RAD,
    "ATTITUDE": mav.MAVLINK_MSG_ID_ATTITUDE,
    "LOCAL_POSITION_NED": mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    "ATTITUDE_TARGET": mav.MAVLINK_MSG_ID_ATTITUDE_TARGET,
    "SYS_STATUS": mav.MAVLINK_MSG_ID_SYS_STATUS,
}
#: REQUEST_DATA_STREAM groups (ArduPilot's SRx_ groups) -> the streams they hold
DATA_STREAM_GROUPS = {
    mav.MAV_DATA_STREAM_RAW_SENSORS: ("RAW_IMU",),
    mav.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS",),
    mav.MAV_DATA_STREAM_POSITION: ("LOCAL_POSITION_NED",),
    mav.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE", "ATTITUDE_TARGET"),
    mav.MAV_DATA_STREAM_EXTRA3: ("OPTICAL_FLOW", "OPTICAL_FLOW_RAD", "DISTANCE_SENSOR"),
}


#: default stream intervals other than one frame (s)
DEFAULT_INTERVALS_S = {mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0}


@dataclass
class StreamSchedule:
    """One peer's stream intervals (simulated time), as SET_MESSAGE_INTERVAL sets them.

    ``intervals_s``: message id -> interval; absent = the default (every frame, i.e. the frame
    rate, 50 Hz; SYS_STATUS 1 Hz); negative = off. Intervals shorter than a frame give every frame.
    """

    frame_s: float
    intervals_s: dict[int, float] = field(default_factory=dict)
    last_frame: dict[int, int] = field(default_factory=dict)

    def interval_s(self, msg_id: int) -> float:
        return self.intervals_s.get(msg_id, DEFAULT_INTERVALS_S.get(msg_id, self.frame_s))

    def set(self, msg_id: int, interval_s: float | None) -> None:
        """``None``: back to the default; negative: off."""
        if interval_s is None:
            self.intervals_s.pop(msg_id, None)
        else:
            self.intervals_s[msg_id] = interval_s

    def due(self, msg_id: int, frame: int) -> bool:
        """Whether ``msg_id`` goes out at ``frame`` (and if so, remember it)."""
        iv = self.interval_s(msg_id)
        if iv < 0:
            return False
        every = max(1, int(round(iv / self.frame_s)))
        last = self.last_frame.get(msg_id)
        if last is not None and frame - last < every and frame >= last:
            return False
        self.last_frame[msg_id] = frame
        return True


# ---------------------------------------------------------------------------------------------
# The vehicle model


@dataclass
class Reply:
    """A message the vehicle sends in answer: to the asking peer only, or to every peer."""

    msg: Any
    to_all: bool = False


@dataclass
class FrameOut:
    """One frame's messages: (stream name or None for always, message), in sending order."""

    time_boot_ms: int
    scenario_setpoint: Any | None
    messages: list[tuple[str | None, Any]]
    notes: list[str]


class Vehicle:
    """The ArduCopter-like vehicle's logic around a ``Simulator``: no sockets, no clock.

    ``handle(msg, streams)`` answers one incoming message; ``frame()`` gives the current
    frame's messages (faults applied); ``advance()`` moves the simulation one frame with the
    command the rules make active. ``lockstep`` changes one rule: only a SET_ATTITUDE_TARGET
    stamped with the current frame's time is taken.
    """

    def __init__(self, cfg: Config, *, profile: Profile = Profile.PAPER, sysid: int = 1, seed: int = 0,
                 scenario: Scenario | None = None, lockstep: bool = False) -> None:
        self.base_cfg = cfg
        self.profile = profile
        self.sysid = sysid
        self.lockstep = lockstep
        self.scenario = scenario
        self.specs = {p.name: p for p in param_specs(cfg)}
        self.values = {name: p.default for name, p in self.specs.items()}
        turb = None
        if scenario is not None and scenario.turbulence_sigma_n > 0:
            turb = Turbulence(scenario.turbulence_sigma_n, scenario.turbulence_tau_s)
        self.sim = Simulator(config_with_params(cfg, self.values), rng=np.random.default_rng(seed),
                             external_force=self._force, altitude=scenario.altitude if scenario else None,
                             turbulence=turb)
        self.T = self.sim.T
        self.enc = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
        self.gcs_enc = mav.MAVLink(None, srcSystem=SCENARIO_GCS[0], srcComponent=SCENARIO_GCS[1])
        self.armed = False
        self.custom_mode = STABILIZE
        self.cmd_rad = (0.0, 0.0)  # (roll, pitch) of the last accepted SET_ATTITUDE_TARGET
        self.cmd_time_s = -math.inf  # simulated time it was accepted
        self.cmd_for_frame = False  # lockstep: the current frame's command has arrived
        self.frame_ms = 0  # boot time of the frame last sent (ms)
        self.boot_offset_s = 0.0
        self._last_flow: FrameSample | None = None
        self._last_gyro: FrameSample | None = None
        self._stuck_flow: FrameSample | None = None  # what a STUCK flow sensor repeats
        self._stuck_gyro: FrameSample | None = None
        self.counters: Counter[str] = Counter()
        #: packets dropped on the links (bad CRC or header, unsigned, oversized): SYS_STATUS errors_comm
        self.comm_errors = 0
        #: the companion (component 191 of this system): simulated time of its last SET_ATTITUDE_TARGET
        #: and HEARTBEAT; the watchdog's episode (when GUIDED_NOGPS began) and whether it acted in it
        self.companion_cmd_s = -math.inf
        self.companion_hb_s = -math.inf
        self._fhw_episode_s: float | None = None
        self._fhw_acted = False

    # -- state ---------------------------------------------------------------------------

    @property
    def refused(self) -> int:
        """Messages refused (SET_ATTITUDE_TARGET rejected, commands and parameters refused):
        SYS_STATUS ``errors_count1``."""
        return sum(v for k, v in self.counters.items() if "rejected" in k or "refused" in k)

    @property
    def guided(self) -> bool:
        return self.custom_mode == GUIDED_NOGPS

    @property
    def boot_s(self) -> float:
        """The vehicle's boot clock at the current frame (s)."""
        return self.sim.t_s - self.boot_offset_s

    def _force(self, t_s: float) -> tuple[float, float]:
        fx, fy = self.scenario.force(t_s) if self.scenario is not None else (0.0, 0.0)
        return fx + self.values["SIM_WIND_FX"], fy + self.values["SIM_WIND_FY"]

    def heartbeat(self) -> Any:
        return telemetry.heartbeat(self.enc, self.armed, self.custom_mode)

    def status(self) -> str:
        return f"{'armed' if self.armed else 'disarmed'} {link.mode_name(self.custom_mode)}"

    # -- the frame -----------------------------------------------------------------------

    def frame(self, *, commit: bool = True) -> FrameOut:
        """The current frame's messages in sending order: gyro and range before the flow
        (time alignment), then attitude, truth, the tracked target and the status.
        ``commit``: this frame is being sent (remember it for frozen sensors and lockstep,
        spend a one-shot spike); False for a one-off REQUEST_MESSAGE."""
        s = self.sim.current
        if self.boot_offset_s:
            s = dataclasses.replace(s, t_s=s.t_s - self.boot_offset_s)
        v = self.values
        flow_fault = FlowFault(int(v["SIM_FLOW_FAULT"]))
        gyro_fault = GyroFault(int(v["SIM_GYRO_FAULT"]))
        range_fault = RangeFault(int(v["SIM_RNG_FAULT"]))
        stuck_flow = (self._stuck_flow or self._last_flow) if flow_fault is FlowFault.STUCK else None
        stuck_gyro = (self._stuck_gyro or self._last_gyro) if gyro_fault is GyroFault.STUCK else None
        rf = self.base_cfg.rangefinder
        sensors = faulted_sensors(s, flow_fault=flow_fault, gyro_fault=gyro_fault, range_fault=range_fault,
                                  spike_counts=int(v["SIM_FLOW_SPIKE"]), last_flow=self._last_flow,
                                  last_gyro=self._last_gyro, range_max_m=rf.max_m,
                                  gyro_range_rad_s=self.sim.gyro_range, stuck_flow=stuck_flow,
                                  stuck_gyro=stuck_gyro, range_jump_m=v["SIM_RNG_JUMP"], range_min_m=rf.min_m)
        notes = []
        frame_ms = int(round(s.t_s * 1e3))
        if commit:
            self._last_flow = sensors.flow or self._last_flow
            self._last_gyro = sensors.gyro or self._last_gyro
            self._stuck_flow = stuck_flow
            self._stuck_gyro = stuck_gyro
            if flow_fault is FlowFault.SPIKE:  # once
                v["SIM_FLOW_FAULT"] = 0.0
                notes.append("SIM_FLOW_FAULT")
            if range_fault is RangeFault.JUMP:  # once
                v["SIM_RNG_FAULT"] = 0.0
                notes.append("SIM_RNG_FAULT")
            self.frame_ms = frame_ms
            self.cmd_for_frame = False
        enc, q = self.enc, self.base_cfg.flow_sensor.q_rad_per_count
        msgs: list[tuple[str | None, Any]] = []
        if sensors.gyro is not None:
            msgs.append(("RAW_IMU", telemetry.raw_imu(enc, sensors.gyro)))
        if sensors.range is not None:
            msgs.append(("DISTANCE_SENSOR", telemetry.distance_sensor(enc, sensors.range, rf.min_m, rf.max_m)))
        if sensors.flow is not None:
            msgs.append((FLOW_MESSAGE[self.profile],
                         telemetry.flow_message(enc, sensors.flow, self.profile, q, self.T,
                                                frontend=(v["FLOW_FXSCALER"], v["FLOW_FYSCALER"],
                                                          v["FLOW_ORIENT_YAW"]))))
        msgs.append(("ATTITUDE", telemetry.attitude(enc, s)))
        msgs.append(("LOCAL_POSITION_NED", telemetry.local_position(enc, s)))
        msgs.append(("ATTITUDE_TARGET", telemetry.attitude_target(enc, s.t_s, *self.sim.u_active)))
        msgs.append(("SYS_STATUS", self.sys_status()))
        sp = None
        if self.scenario is not None:
            vx, vy = self.scenario.setpoint(self.sim.t_s)
            sp = self.gcs_enc.set_position_target_local_ned_encode(
                frame_ms & 0xFFFFFFFF, self.sysid, COMPANION_COMPONENT, mav.MAV_FRAME_BODY_FRD,
                VELOCITY_TYPE_MASK, 0.0, 0.0, 0.0, vx, vy, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if commit:
            msgs += [(None, m) for m in self.watchdog()]
        return FrameOut(frame_ms, sp, msgs, notes)

    def sys_status(self) -> Any:
        gyro, flow, laser = (mav.MAV_SYS_STATUS_SENSOR_3D_GYRO, mav.MAV_SYS_STATUS_SENSOR_OPTICAL_FLOW,
                             mav.MAV_SYS_STATUS_SENSOR_LASER_POSITION)
        present = gyro | flow | laser | mav.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
        health = present | mav.MAV_SYS_STATUS_GEOFENCE  # as ArduPilot: no fence breached
        if self.values["SIM_GYRO_FAULT"]:
            health &= ~gyro
        if self.values["SIM_FLOW_FAULT"]:
            health &= ~flow
        if self.values["SIM_RNG_FAULT"]:
            health &= ~laser
        return self.enc.sys_status_encode(present, present, health, 0, 12600, -1, 100, 0,
                                          min(self.comm_errors, 0xFFFF), min(self.refused, 0xFFFF), 0, 0, 0)

    def watchdog(self) -> list[Any]:
        """The flowhold watchdog applet (``companion/ardupilot/flowhold_watchdog.lua``) as this
        vehicle runs it, each frame in simulated time (the applet: every 50 ms): armed in
        GUIDED_NOGPS with ``FHW_ENABLE`` 1, once the companion's SET_ATTITUDE_TARGETs have stopped
        for more than ``FHW_TIMEOUT`` since the later of the last one and the start of the episode,
        a STATUSTEXT (CRITICAL) and a switch to ``FHW_MODE`` (LAND if that is refused), once per
        episode. Returns the messages to send (the texts, and the HEARTBEAT of the new mode)."""
        v = self.values
        if not (v["FHW_ENABLE"] >= 1 and self.armed and self.guided):
            self._fhw_episode_s = None
            return []
        now = self.sim.t_s
        if self._fhw_episode_s is None:
            self._fhw_episode_s, self._fhw_acted = now, False
        timeout = v["FHW_TIMEOUT"]
        if self._fhw_acted or now - max(self._fhw_episode_s, self.companion_cmd_s) <= timeout + 1e-9:
            return []
        self._fhw_acted = True
        mode = int(v["FHW_MODE"])
        why = "no commands" if now - self.companion_hb_s <= timeout else "companion lost"
        crit = mav.MAV_SEVERITY_CRITICAL
        out = [link.statustext(self.enc, f"flowhold watchdog: {why} {timeout:.1f} s: {link.mode_name(mode)}", crit)]
        flag = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self._set_mode(flag, mode) == mav.MAV_RESULT_ACCEPTED:
            return [*out, self.heartbeat()]
        out.append(link.statustext(self.enc, f"flowhold watchdog: {link.mode_name(mode)} refused", crit))
        if mode != LAND and self._set_mode(flag, LAND) == mav.MAV_RESULT_ACCEPTED:
            out += [link.statustext(self.enc, "flowhold watchdog: LAND instead", crit), self.heartbeat()]
        return out

    def command_to_activate(self) -> tuple[float, float]:
        """The (roll, pitch) command to make active at the end of this frame (rad)."""
        if not (self.armed and self.guided):
            return (0.0, 0.0)
        if self.sim.t_s - self.cmd_time_s > self.values["GUID_TIMEOUT"] + 1e-9:
            return (0.0, 0.0)  # GUID_TIMEOUT: level and hold
        return self.cmd_rad

    def advance(self) -> FrameSample:
        """Integrate one frame with the active command and activate the next one."""
        s = self.sim.advance(*self.command_to_activate())
        self.cmd_for_frame = False
        return s

    # -- incoming messages -----------------------------------------------------------------

    def for_me(self, msg: Any) -> bool:
        """Whether a message is addressed to this autopilot (or to everyone)."""
        ts = getattr(msg, "target_system", None)
        if ts is None:
            ts = getattr(msg, "target", None) if msg.get_type() == "MANUAL_CONTROL" else None
        if ts not in (None, 0, self.sysid):
            return False
        tc = getattr(msg, "target_component", None)
        return tc in (None, 0, 1)

    def handle(self, msg: Any, streams: StreamSchedule) -> list[Reply]:
        """Answer one incoming message addressed to this vehicle."""
        mtype = msg.get_type()
        if msg.get_srcComponent() == COMPANION_COMPONENT and msg.get_srcSystem() == self.sysid:
            if mtype == "SET_ATTITUDE_TARGET":  # (taken or not: the watchdog sees it arrive)
                self.companion_cmd_s = self.sim.t_s
            elif mtype == "HEARTBEAT":
                self.companion_hb_s = self.sim.t_s
        if mtype == "SET_ATTITUDE_TARGET":
            self._attitude_target(msg)
            return []
        if mtype == "COMMAND_LONG":
            return self._command(msg, msg.command, [msg.param1, msg.param2, msg.param3, msg.param4,
                                                    msg.param5, msg.param6, msg.param7], streams)
        if mtype == "COMMAND_INT":
            return self._command(msg, msg.command, [msg.param1, msg.param2, msg.param3, msg.param4,
                                                    float(msg.x), float(msg.y), msg.z], streams)
        if mtype == "SET_MODE":
            if msg.target_system != self.sysid:
                return []
            result = self._set_mode(msg.base_mode, msg.custom_mode)
            return [self._ack(msg, mav.MAVLINK_MSG_ID_SET_MODE, result), *self._mode_notes(result)]
        if mtype == "PARAM_REQUEST_LIST":
            return [Reply(self._param_value(n)) for n in self.specs]
        if mtype == "PARAM_REQUEST_READ":
            names = list(self.specs)
            if msg.param_index >= 0:
                return [Reply(self._param_value(names[msg.param_index]))] if msg.param_index < len(names) else []
            name = _param_name(msg.param_id)
            return [Reply(self._param_value(name))] if name in self.specs else []
        if mtype == "PARAM_SET":
            return self.set_param(_param_name(msg.param_id), float(msg.param_value))
        if mtype == "REQUEST_DATA_STREAM":
            self._data_stream(msg, streams)
        return []

    def _attitude_target(self, msg: Any) -> None:
        reason = self._reject_reason(msg)
        if reason:
            self.counters[f"SET_ATTITUDE_TARGET rejected: {reason}"] += 1
            return
        roll, pitch, _yaw = quaternion_to_euler(msg.q)
        lim = math.radians(self.values["ANGLE_MAX"] / 100.0)
        self.cmd_rad = (min(max(roll, -lim), lim), min(max(pitch, -lim), lim))
        self.cmd_time_s = self.sim.t_s
        self.cmd_for_frame = True
        self.counters["SET_ATTITUDE_TARGET accepted"] += 1

    def _reject_reason(self, msg: Any) -> str:
        if not self.armed:
            return "disarmed"
        if not self.guided:
            return "not in GUIDED_NOGPS"
        q = [float(x) for x in msg.q]
        if not all(math.isfinite(x) for x in q) or abs(math.sqrt(sum(x * x for x in q)) - 1.0) > QUATERNION_NORM_TOL:
            return "not a unit quaternion"
        if msg.type_mask & mav.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE:
            return "attitude ignored by type_mask"
        if not (math.isfinite(msg.thrust) and 0.0 <= msg.thrust <= 1.0):
            return "thrust not in [0, 1]"
        if self.lockstep and msg.time_boot_ms != (self.frame_ms & 0xFFFFFFFF):
            return "stale (lockstep)"
        return ""

    def _ack(self, msg: Any, command: int, result: int) -> Reply:
        if result != mav.MAV_RESULT_ACCEPTED:  # counted: SYS_STATUS errors_count1 and the exit summary
            if msg.get_type() == "SET_MODE":
                name = "SET_MODE"
            elif command in mav.enums["MAV_CMD"]:
                name = mav.enums["MAV_CMD"][command].name
            else:
                name = f"command {command}"
            self.counters[f"{name} refused"] += 1
        return Reply(self.enc.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(),
                                                 msg.get_srcComponent()))

    def _mode_notes(self, result: int) -> list[Reply]:
        return [Reply(self.heartbeat(), to_all=True)] if result == mav.MAV_RESULT_ACCEPTED else []

    def _set_mode(self, base_mode: float, custom_mode: float) -> int:
        if _whole(base_mode) is None or _whole(custom_mode) is None:
            return mav.MAV_RESULT_DENIED  # NaN, infinite or fractional
        if not int(base_mode) & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mav.MAV_RESULT_DENIED
        mode = int(custom_mode)
        if mode not in SUPPORTED_MODES:
            self.counters[f"mode {link.mode_name(mode)} asked for"] += 1  # refused: no GPS
            return mav.MAV_RESULT_DENIED
        self.custom_mode = mode
        return mav.MAV_RESULT_ACCEPTED

    def _command(self, msg: Any, command: int, p: list[float], streams: StreamSchedule) -> list[Reply]:
        if getattr(msg, "target_system", 0) not in (0, self.sysid):
            return []
        replies: list[Reply] = []
        if command == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] == 1.0:
                ok = self.custom_mode in ARMABLE_MODES
                result = mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_DENIED
                if ok and not self.armed:
                    self.armed = True
                    replies += [Reply(self.heartbeat(), to_all=True),
                                Reply(link.statustext(self.enc, "Arming motors", mav.MAV_SEVERITY_INFO), True)]
                elif not ok:
                    replies.append(Reply(link.statustext(
                        self.enc, f"Arm: {link.mode_name(self.custom_mode)} not armable", mav.MAV_SEVERITY_WARNING)))
            elif p[0] == 0.0:
                result = mav.MAV_RESULT_ACCEPTED
                if self.armed:
                    self.armed = False
                    replies += [Reply(self.heartbeat(), to_all=True),
                                Reply(link.statustext(self.enc, "Disarming motors", mav.MAV_SEVERITY_INFO), True)]
            else:
                result = mav.MAV_RESULT_DENIED
        elif command == mav.MAV_CMD_DO_SET_MODE:
            result = self._set_mode(p[0], p[1])
            replies += self._mode_notes(result)
        elif command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(_whole(p[0]), p[1], streams)
        elif command == mav.MAV_CMD_GET_MESSAGE_INTERVAL:
            mid = _whole(p[0])
            if mid is not None and mid in STREAM_IDS.values():
                iv = streams.interval_s(mid)
                replies.append(Reply(self.enc.message_interval_encode(mid, -1 if iv < 0 else int(iv * 1e6))))
                result = mav.MAV_RESULT_ACCEPTED
            else:
                result = mav.MAV_RESULT_DENIED
        elif command == mav.MAV_CMD_REQUEST_MESSAGE:
            mid = _whole(p[0])
            one = self._one_message(mid) if mid is not None else None
            result = mav.MAV_RESULT_ACCEPTED if one is not None else mav.MAV_RESULT_UNSUPPORTED
            if one is not None:
                replies.append(Reply(one))
        elif command == mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            replies.append(Reply(self.autopilot_version()))
            result = mav.MAV_RESULT_ACCEPTED
        else:
            result = mav.MAV_RESULT_UNSUPPORTED
        return [self._ack(msg, command, result), *replies]

    def _set_interval(self, msg_id: int | None, interval_us: float, streams: StreamSchedule) -> int:
        if msg_id is None or msg_id not in STREAM_IDS.values() or not math.isfinite(interval_us):
            return mav.MAV_RESULT_DENIED
        if interval_us == 0:
            streams.set(msg_id, None)
        elif interval_us < 0:
            streams.set(msg_id, -1.0)
        else:
            streams.set(msg_id, interval_us * 1e-6)
        return mav.MAV_RESULT_ACCEPTED

    def _data_stream(self, msg: Any, streams: StreamSchedule) -> None:
        groups = DATA_STREAM_GROUPS if msg.req_stream_id == mav.MAV_DATA_STREAM_ALL else \
            {msg.req_stream_id: DATA_STREAM_GROUPS.get(msg.req_stream_id, ())}
        on = msg.start_stop != 0 and msg.req_message_rate > 0
        for names in groups.values():
            for name in names:
                streams.set(STREAM_IDS[name], 1.0 / msg.req_message_rate if on else -1.0)

    def _one_message(self, msg_id: int) -> Any | None:
        if msg_id == mav.MAVLINK_MSG_ID_HEARTBEAT:
            return self.heartbeat()
        if msg_id == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return self.autopilot_version()
        for name, m in self.frame(commit=False).messages:
            if name is not None and STREAM_IDS.get(name) == msg_id:
                return m
        return None

    def autopilot_version(self) -> Any:
        caps = (mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mav.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | mav.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT)
        return self.enc.autopilot_version_encode(caps, 0, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0)

    # -- parameters ----------------------------------------------------------------------

    def _param_value(self, name: str) -> Any:
        names = list(self.specs)
        return self.enc.param_value_encode(name.encode(), self.values[name], self.specs[name].mav_type,
                                           len(names), names.index(name))

    def set_param(self, name: str, value: float) -> list[Reply]:
        """PARAM_SET: validate, apply (effects from the next frame), and answer PARAM_VALUE to
        every peer (as ArduPilot announces a change); a refused value is answered with the
        unchanged value and a STATUSTEXT saying why."""
        spec = self.specs.get(name)
        if spec is None:
            self.counters["PARAM_SET refused: unknown parameter"] += 1
            return [Reply(link.statustext(self.enc, f"unknown parameter {name}", mav.MAV_SEVERITY_WARNING))]
        try:
            value = spec.check(value)
        except ValueError as exc:
            self.counters["PARAM_SET refused: bad value"] += 1
            return [Reply(self._param_value(name)),
                    Reply(link.statustext(self.enc, str(exc), mav.MAV_SEVERITY_WARNING))]
        self.values[name] = value
        self.counters[f"param {name}"] += 1
        if name == "SIM_REBOOT" and value:
            self.boot_offset_s = self.sim.t_s + self.T  # the next frame is boot time 0
            self.values[name] = 0.0
        elif name.startswith("SIM_") and name not in ("SIM_WIND_FX", "SIM_WIND_FY", "SIM_FLOW_FAULT",
                                                      "SIM_FLOW_SPIKE", "SIM_GYRO_FAULT", "SIM_RNG_FAULT",
                                                      "SIM_RNG_JUMP"):
            self.sim.set_config(config_with_params(self.base_cfg, self.values))
        return [Reply(self._param_value(name), to_all=True)]

    def param_value(self, name: str) -> Any:
        return self._param_value(name)


#: bytes per UDP datagram when batching packets (below a typical 1500-byte MTU)
MAX_DATAGRAM = 1400
#: a received datagram longer than this is dropped unread (bytes; see companion.mavlink.link)
MAX_DATAGRAM_IN = link.MAX_DATAGRAM_IN


def _datagrams(packets: list[bytes]) -> list[bytes]:
    """Packets joined into datagrams of at most MAX_DATAGRAM bytes (a packet is never split)."""
    out: list[bytes] = []
    cur = b""
    for pkt in packets:
        if cur and len(cur) + len(pkt) > MAX_DATAGRAM:
            out.append(cur)
            cur = b""
        cur += pkt
    if cur:
        out.append(cur)
    return out


def _whole(x: float) -> int | None:
    """A command parameter that must be a whole number (message id, mode): the int, or None
    when it is NaN, infinite or fractional."""
    if not math.isfinite(x) or x != round(x):
        return None
    return int(x)


def _param_name(param_id: Any) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", "replace")
    return str(param_id).split("\x00", 1)[0].strip()


# ---------------------------------------------------------------------------------------------
# The UDP adapter


@dataclass
class Peer:
    """A link: a UDP address that sent a valid packet, with its own parser and streams."""

    addr: tuple[str, int]
    parser: Any
    streams: StreamSchedule
    seen: set[tuple[int, int]] = field(default_factory=set)
    last_heard_wall_s: float = 0.0


class UdpVehicle:
    """Serve a ``Vehicle`` on one UDP port; see the module docstring for the timing rules."""

    def __init__(self, vehicle: Vehicle, host: str, port: int, *, lockstep: bool = False, speedup: float = 1.0,
                 max_speedup: float | None = None, duration_s: float | None = None,
                 tlog: str | Path | None = None, key: bytes | None = None,
                 log: Callable[[str], None] | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.v = vehicle
        self.lockstep = lockstep
        self.speedup = speedup
        #: lockstep: never faster than this many times real time (None: as fast as the companion)
        self.max_speedup = max_speedup
        self.duration_s = duration_s
        self.key = key
        self.clock = clock
        self.log = log or (lambda text: print(text, flush=True))
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, port))
        except OSError as exc:
            self.sock.close()
            raise LinkError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        self.sock.setblocking(False)
        self.address = self.sock.getsockname()
        self.peers: dict[tuple[str, int], Peer] = {}
        #: MAVLink 2 signing: the newest timestamp of each (link id, system, component), all links
        self._signing_streams: dict[tuple[int, int, int], int] = {}
        self.unix_start_s = time.time()
        #: a clock that is not the wall clock (lockstep, speed-up) is said to each new peer in a
        #: STATUSTEXT, and stamps the recording from SIM_EPOCH_S as a SITL's log would; in real
        #: time the recording is stamped from the UNIX time at start
        self.clock_note: str | None = None
        if lockstep or speedup != 1.0:
            mode = "lockstep" if lockstep else f"speedup x{speedup:g}"
            self.clock_note = f"simvehicle: {SIM_CLOCK_TEXT} ({mode})"
        self.epoch_s = SIM_EPOCH_S if self.clock_note else self.unix_start_s
        if key is not None:
            link.setup_signing(vehicle.enc, key, unix_s=self.unix_start_s)
            link.setup_signing(vehicle.gcs_enc, key, unix_s=self.unix_start_s)
        try:
            if tlog:
                Path(tlog).parent.mkdir(parents=True, exist_ok=True)
            self.tlog = TlogWriter(tlog) if tlog else None
        except OSError as exc:
            self.sock.close()
            raise output_error("--tlog", tlog or "", exc) from None
        self.counters: Counter[str] = Counter()
        self._next_heartbeat = 0.0
        self._next_status = 0.0
        #: set by a signal handler: the loop ends between two packets, never inside a record
        self.stop_requested = False

    # -- sending -------------------------------------------------------------------------

    def _stamp(self) -> float:
        return self.epoch_s + self.v.sim.t_s

    def _pack(self, msg: Any, enc: Any | None = None) -> bytes:
        enc = enc or self.v.enc
        buf = bytes(msg.pack(enc))
        enc.seq = (enc.seq + 1) % 256
        if self.tlog is not None:
            self.tlog.write_bytes(buf, self._stamp())
        return buf

    def _sendto(self, buf: bytes, peers: Any) -> None:
        for p in peers:
            try:
                self.sock.sendto(buf, p.addr)
            except OSError:
                self.counters["send errors"] += 1

    def _live_peers(self) -> list[Peer]:
        now = self.clock()
        return [p for p in self.peers.values() if now - p.last_heard_wall_s < PEER_TIMEOUT_S]

    def _reply(self, replies: list[Reply], peer: Peer) -> None:
        for r in replies:
            self._sendto(self._pack(r.msg), self._live_peers() if r.to_all else [peer])

    def send_frame(self) -> None:
        """Send the current frame to every peer whose stream schedule wants each message: one
        datagram per peer holding its packets in order (as an autopilot's UDP link batches)."""
        before = self.v.status()
        out = self.v.frame()
        if self.v.status() != before:  # the watchdog switched mode
            self.log(f"simvehicle: {self.v.status()} at t={self.v.sim.t_s:.2f} s (flowhold watchdog)")
        peers = self._live_peers()
        batches: dict[tuple[str, int], list[bytes]] = {p.addr: [] for p in peers}
        if out.scenario_setpoint is not None:
            buf = self._pack(out.scenario_setpoint, self.v.gcs_enc)
            for p in peers:
                if any(c == COMPANION_COMPONENT for _s, c in p.seen):
                    batches[p.addr].append(buf)
        frame = self.v.sim.frame
        for name, msg in out.messages:
            mid = STREAM_IDS[name] if name is not None else None
            wanted = [p for p in peers if mid is None or p.streams.due(mid, frame)]
            if wanted:
                buf = self._pack(msg)
                for p in wanted:
                    batches[p.addr].append(buf)
        for name in out.notes:
            buf = self._pack(self.v.param_value(name))
            for p in peers:
                batches[p.addr].append(buf)
        for p in peers:
            for datagram in _datagrams(batches[p.addr]):
                self._sendto(datagram, [p])

    def _heartbeat(self, now: float) -> None:
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + 1.0
            peers = self._live_peers()
            if peers:
                self._sendto(self._pack(self.v.heartbeat()), peers)
        if now >= self._next_status:
            self._next_status = now + 5.0
            if self.peers:
                dropped = f", {self.v.comm_errors} packet(s) dropped" if self.v.comm_errors else ""
                refused = f", {self.v.refused} message(s) refused" if self.v.refused else ""
                self.log(f"simvehicle: t={self.v.sim.t_s:.2f} s {self.v.status()}, "
                         f"{len(self._live_peers())} peer(s){dropped}{refused}")

    # -- receiving -----------------------------------------------------------------------

    def _new_peer(self, addr: tuple[str, int]) -> Peer:
        parser = mav.MAVLink(None)
        parser.robust_parsing = True
        if self.key is not None:
            link.setup_signing(parser, self.key, unix_s=time.time(), sign_outgoing=False)
            # one replay window for every link, as ArduPilot keeps: a signed packet heard on one
            # link and sent again from another address is as old there as here
            parser.signing.stream_timestamps = self._signing_streams
        return Peer(addr, parser, StreamSchedule(self.v.T))

    def _receive_one(self) -> bool:
        """Read and handle one datagram; False when none is waiting."""
        try:
            data, addr = self.sock.recvfrom(65535)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError:
            self.counters["receive errors"] += 1
            return True
        if len(data) > MAX_DATAGRAM_IN:  # no MAVLink link sends this much at once: not worth parsing
            self._reject("oversized datagrams dropped")
            return True
        peer = self.peers.get(addr)
        fresh = peer is None
        if peer is None:
            peer = self._new_peer(addr)
        try:
            msgs = peer.parser.parse_buffer(data) or []
        except Exception:  # noqa: BLE001 - a malformed datagram must not stop the vehicle
            msgs = [None]
        if link.discard_partial(peer.parser):  # never join a datagram's broken tail to the next one
            self._reject("bad packets")
        for msg in msgs:
            if msg is None or msg.get_type() == "BAD_DATA":
                self._reject(link.bad_data_kind(msg) if msg is not None else "bad packets")
                continue
            if fresh:
                self.peers[addr] = peer
                fresh = False
                self.log(f"simvehicle: peer {addr[0]}:{addr[1]} (system {msg.get_srcSystem()} "
                         f"component {msg.get_srcComponent()})")
                hello = [self._pack(self.v.heartbeat())]
                if self.clock_note:  # in the same datagram: the peer knows before any sensor data
                    hello.append(self._pack(link.statustext(self.v.enc, self.clock_note, mav.MAV_SEVERITY_INFO)))
                self._sendto(b"".join(hello), [peer])
            peer.last_heard_wall_s = self.clock()
            peer.seen.add((msg.get_srcSystem(), msg.get_srcComponent()))
            try:
                self._on_message(msg, peer)
            except Exception as exc:  # noqa: BLE001 - one bad message must not stop the vehicle
                self.counters[f"handler error {type(exc).__name__}"] += 1
        return True

    def _reject(self, why: str) -> None:
        """Count a datagram or packet dropped on the link; the total goes out in SYS_STATUS
        ``errors_comm``."""
        self.counters[why] += 1
        self.v.comm_errors += 1

    def _on_message(self, msg: Any, peer: Peer) -> None:
        raw = bytes(msg.get_msgbuf())
        if self.tlog is not None:
            self.tlog.write_bytes(raw, self._stamp())
        self._sendto(raw, self._route(msg, peer))
        if self.v.for_me(msg):
            before = (self.v.armed, self.v.custom_mode)
            self._reply(self.v.handle(msg, peer.streams), peer)
            if (self.v.armed, self.v.custom_mode) != before:
                self.log(f"simvehicle: {self.v.status()} at t={self.v.sim.t_s:.2f} s")
            if msg.get_type() == "PARAM_SET":
                name = _param_name(msg.param_id)
                if name in self.v.specs:
                    self.log(f"simvehicle: {name} = {self.v.values[name]:g} at t={self.v.sim.t_s:.2f} s")

    def _route(self, msg: Any, src: Peer) -> list[Peer]:
        """The other peers a message goes to: all of them unless it targets a system (and
        component) seen on particular links, as ArduPilot's MAVLink routing does."""
        ts = getattr(msg, "target_system", None)
        if ts is None and msg.get_type() == "MANUAL_CONTROL":
            ts = msg.target
        others = [p for p in self._live_peers() if p is not src]
        if not ts:
            return others
        tc = getattr(msg, "target_component", 0) or 0
        if ts == self.v.sysid and tc == 1:
            return []
        return [p for p in others if any(s == ts and (tc == 0 or c == tc) for s, c in p.seen)]

    def pump(self, until_wall_s: float, done: Callable[[], bool] = lambda: False) -> None:
        """Receive and answer until ``until_wall_s`` (monotonic clock) or ``done()``."""
        while not done() and not self.stop_requested:
            now = self.clock()
            self._heartbeat(now)
            if now >= until_wall_s:
                return
            if self._receive_one():
                continue
            wait = min(until_wall_s, self._next_heartbeat) - now
            select.select([self.sock], [], [], max(0.0, min(wait, 0.1)))

    # -- the loop ------------------------------------------------------------------------

    def _finished(self) -> bool:
        return self.duration_s is not None and self.v.sim.t_s >= self.duration_s - 1e-9

    def run(self) -> None:
        """Fly until the duration (simulated time) is reached or the process is stopped."""
        if self.lockstep:
            while not self.peers and not self.stop_requested:  # the clock starts when someone listens
                self.pump(self.clock() + 0.5, lambda: bool(self.peers))
        start = self.clock()
        n0 = self.v.sim.frame
        self.send_frame()
        while not self.stop_requested:
            if self.lockstep:
                self.pump(self.clock() + LOCKSTEP_WAIT_S, lambda: self.v.cmd_for_frame)
                if not self.v.cmd_for_frame:
                    self.counters["lockstep frames without a command"] += 1
                if self.max_speedup is not None:
                    due = start + (self.v.sim.frame - n0 + 1) * self.v.T / self.max_speedup
                    if self.clock() < due:
                        self.pump(due)
                    else:  # behind the cap (a slow companion): the cap never makes it sprint
                        start, n0 = self.clock(), self.v.sim.frame + 1
            else:
                due = start + (self.v.sim.frame - n0 + 1) * self.v.T / self.speedup
                self.pump(due)
                if self.clock() - due > 1.0:  # fell behind by a second: do not sprint to catch up
                    self.counters["real-time overruns"] += 1
                    start, n0 = self.clock(), self.v.sim.frame + 1
            if self._finished() or self.stop_requested:
                return
            self.v.advance()
            self.send_frame()

    def close(self) -> None:
        if self.tlog is not None:
            self.tlog.close()
        self.sock.close()


# ---------------------------------------------------------------------------------------------
# Reading a vehicle recording back as per-frame columns


def recording_run(path: str | Path, *, name: str = "loop", config: Config | str | Path | None = None) -> Run:
    """The per-frame columns of a recording made by this vehicle (its ``--tlog``), in the
    layout of ``simvehicle.engines.scenarios.Run`` (so ``figures`` and ``plot_run`` apply).

    Frames are the vehicle's LOCAL_POSITION_NED (truth); the other columns are matched by
    their time fields: ATTITUDE, the gyro, the downward DISTANCE_SENSOR (the reading as sent), the
    flow message (counts in the paper's convention, ``dphi / Q`` rounded to whole counts, whatever
    the profile), the companion's VISION_SPEED_ESTIMATE (NaN while it holds) and
    POSITION_TARGET_LOCAL_NED. The signals, their sender (the vehicle: the most frequent flow
    sender), time fields and units are ``companion.recordings.signals``' (replay's and diagnose's). The command of
    frame k is the one that acted from frame k+1: the vehicle's ATTITUDE_TARGET there (the last
    frame takes the companion's SET_ATTITUDE_TARGET for it when there is one). Only the first
    boot is read when the recording holds a SIM_REBOOT.

    ``config``: the parameter set the vehicle flew with (``serve --config``; a Config or a TOML
    path; default ``configs/paper.toml``): its Q and frame period turn the ``ardupilot`` and
    ``px4`` profiles' flow rates into counts.
    """
    cfg = config if isinstance(config, Config) else load_config(config)
    rec = load_recording(path)
    profile = Profile(detect_profile(rec)[0])
    flow = vehicle_flow(rec, profile, cfg.flow_sensor.q_rad_per_count)
    vehicle = flow.sysid

    def vehicle_only(name: str) -> MessageTable:
        rec.table(name)  # a RecordingError naming the message when the recording has none
        table = vehicle_table(rec, name, vehicle)
        if table is None:
            raise RecordingError(f"{Path(path).name}: no {name} from the vehicle (system {vehicle})")
        return table

    lp = vehicle_only("LOCAL_POSITION_NED")
    t_ms = time_ms(lp)
    n = len(t_ms)
    if n > 1 and np.any(np.diff(t_ms) <= 0):
        n = int(np.argmax(np.diff(t_ms) <= 0)) + 1
    t_ms = t_ms[:n]
    key = {int(t): i for i, t in enumerate(t_ms)}

    def column(keys_ms: np.ndarray, values: np.ndarray, *, last: bool = False) -> np.ndarray:
        """``values`` on the frames, matched by their whole-millisecond times ``keys_ms``."""
        out = np.full(n, np.nan)
        order = range(len(keys_ms) - 1, -1, -1) if not last else range(len(keys_ms))
        for j in order:  # first occurrence wins (reversed fill), or last
            i = key.get(int(keys_ms[j]))
            if i is not None:
                out[i] = values[j]
        return out

    nan = np.full(n, np.nan)
    cols: dict[str, np.ndarray] = {"t_s": t_ms * 1e-3}
    cols["x_m"], cols["y_m"] = lp["x"][:n].astype(float), lp["y"][:n].astype(float)
    cols["vx_m_s"], cols["vy_m_s"] = lp["vx"][:n].astype(float), lp["vy"][:n].astype(float)
    att = Attitude(vehicle_only("ATTITUDE"))
    a_ms = time_ms(att.table)
    for col, angle in (("roll_rad", att.roll), ("pitch_rad", att.pitch), ("roll_rate_rad_s", att.rollspeed),
                       ("pitch_rate_rad_s", att.pitchspeed)):
        cols[col] = column(a_ms, angle)
    gyro = gyro_sensor(rec, vehicle)
    cols["gyro_x_rad_s"] = column(gyro.time_ms, gyro.x_rad_s) if len(gyro) else nan
    cols["gyro_y_rad_s"] = column(gyro.time_ms, gyro.y_rad_s) if len(gyro) else nan
    ds = downward_range(rec, vehicle)
    # the reading as sent (the scenarios' Run holds the rangefinder's reading, valid or not)
    cols["range_m"] = column(ds.time_ms, ds.reading_m) if ds is not None else nan
    # counts in the paper's convention whatever the profile, with the flight's own Q and frame period
    q = cfg.flow_sensor.q_rad_per_count
    fc = flow.columns
    scale = 1.0 / q if fc.increment else cfg.flow_sensor.frame_period_s / q
    f_ms = np.round(np.asarray(fc.time_s) * 1e3).astype(np.int64)
    # the simulated sensor's counts are whole: undo the float32 rounding of rates and radians
    cols["flow_x_counts"] = column(f_ms, np.round(np.asarray(fc.scene_x) * scale))
    cols["flow_y_counts"] = column(f_ms, np.round(np.asarray(fc.scene_y) * scale))
    cols["est_vx_m_s"] = cols["est_vy_m_s"] = nan
    vs = companion_table(rec, "VISION_SPEED_ESTIMATE")
    if vs is not None:
        v_ms = time_ms(vs)
        cols["est_vx_m_s"], cols["est_vy_m_s"] = column(v_ms, vs["x"]), column(v_ms, vs["y"])
    cols["vx_set_m_s"] = cols["vy_set_m_s"] = nan
    pt = companion_table(rec, "POSITION_TARGET_LOCAL_NED")
    if pt is not None:
        p_ms = time_ms(pt)
        cols["vx_set_m_s"], cols["vy_set_m_s"] = column(p_ms, pt["vx"]), column(p_ms, pt["vy"])
    roll_cmd, pitch_cmd = np.zeros(n), np.zeros(n)
    at = AttitudeCommand(vehicle_only("ATTITUDE_TARGET"))
    # the angles one message at a time (rotation.quaternion_to_euler, libm), as the vehicle and
    # the scenarios compute them: the vectorised form (AttitudeCommand.roll) differs by an ulp
    eul = np.array([quaternion_to_euler(qq)[:2] for qq in at.q]).reshape(-1, 2)
    acted_roll = column(at.time_ms, eul[:, 0])
    acted_pitch = column(at.time_ms, eul[:, 1])
    roll_cmd[:-1], pitch_cmd[:-1] = acted_roll[1:], acted_pitch[1:]
    roll_cmd[-1], pitch_cmd[-1] = acted_roll[-1], acted_pitch[-1]
    st = companion_commands(rec)
    if st is not None:
        j = np.nonzero(st.time_ms == t_ms[-1])[0]
        if len(j):
            roll_cmd[-1], pitch_cmd[-1] = quaternion_to_euler(st.q[j[0]])[:2]
    cols["roll_cmd_rad"], cols["pitch_cmd_rad"] = roll_cmd, pitch_cmd
    cols["hold"] = np.isnan(cols["est_vx_m_s"]).astype(float)
    return Run(name, cols, Path(path), {"profile": profile.value})


# ---------------------------------------------------------------------------------------------
# Command line


def run_cli(args: Any) -> int:
    """``python -m simvehicle serve``: returns 0 when the duration is flown or on Ctrl-C/SIGTERM."""
    host, port = link.parse_host_port(args.listen, what="--listen")
    if not (math.isfinite(args.speedup) and args.speedup > 0):
        raise UsageError(f"--speedup must be a positive number, got {args.speedup}")
    max_speedup = getattr(args, "max_speedup", None)
    if max_speedup is not None:
        if not args.lockstep:
            raise UsageError("--max-speedup caps a --lockstep run; without --lockstep use --speedup")
        if not (math.isfinite(max_speedup) and max_speedup > 0):
            raise UsageError(f"--max-speedup must be a positive number, got {max_speedup}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise UsageError(f"--duration must be a positive number of seconds, got {args.duration}")
    if not 1 <= args.sysid <= 255:
        raise UsageError(f"--sysid must be in 1..255, got {args.sysid}")
    if args.tlog:
        check_output(args.tlog, "--tlog")
    cfg = load_config(args.config)
    scenario_name = getattr(args, "scenario", None)
    scenario = SCENARIOS[scenario_name] if scenario_name else None
    duration = args.duration if args.duration is not None else (scenario.duration_s if scenario else None)
    key = link.signing_key(args.signing_key) if args.signing_key else None
    vehicle = Vehicle(cfg, profile=Profile(args.profile), sysid=args.sysid, seed=args.seed, scenario=scenario,
                      lockstep=args.lockstep)
    server = UdpVehicle(vehicle, host, port, lockstep=args.lockstep, speedup=args.speedup,
                        max_speedup=max_speedup, duration_s=duration,
                        tlog=args.tlog, key=key)
    h, p = server.address[:2]
    clock = "lockstep" if args.lockstep else ("real time" if args.speedup == 1.0 else f"speedup x{args.speedup:g}")
    if max_speedup is not None:
        clock += f" at most x{max_speedup:g}"
    extra = f", scenario {scenario_name}" if scenario else ""
    print(f"simvehicle: listening on udp {h}:{p} ({clock}, profile {args.profile}, system {args.sysid}{extra})",
          flush=True)
    def request_stop(_signum: int, _frame: Any) -> None:
        server.stop_requested = True

    old = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    wall0 = time.monotonic()
    try:
        server.run()
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        server.close()
    why = "stopped" if server.stop_requested else "done"
    counts = dict(server.counters) | dict(vehicle.counters)
    summary = ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))
    print(f"simvehicle: {why} at t={vehicle.sim.t_s:.2f} s ({vehicle.sim.frame + 1} frames) "
          f"after {time.monotonic() - wall0:.2f} s of wall time"
          + (f"; {summary}" if summary else ""), flush=True)
    if args.tlog:
        print(f"simvehicle: recording {args.tlog}", flush=True)
    sys.stdout.flush()
    return 0
