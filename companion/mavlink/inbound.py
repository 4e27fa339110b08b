"""Incoming MAVLink messages -> the companion core, in one place (live loop and scenarios).

Units and signs are converted here and nowhere else: RAW_IMU / SCALED_IMU gyro mrad/s and
HIGHRES_IMU rad/s -> rad/s; DISTANCE_SENSOR cm -> m (orientation 25 only); the flow message by
the sensor profile (``companion.step.profiles``); velocity setpoints from SET_POSITION_TARGET_LOCAL_NED
(body frames 8, 9, 12, or LOCAL_NED rotated by the vehicle's yaw) and MANUAL_CONTROL sticks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from companion.mavlink_ids import BODY_FRAMES, COMPANION_COMPONENT, DOWNWARD, MAV_COMP_ID_ALL, MAV_FRAME_LOCAL_NED
from companion.step.core import CompanionCore, StepOutput
from companion.step.profiles import (
    FLOW_MESSAGE,
    GYRO_MESSAGES,
    INT16_CLIP,
    TIME_FIELDS,
    FlowColumns,
    Profile,
    accel_m_s2,
    flow_scalar,
)

#: POSITION_TARGET type_mask bits: vx, vy ignored (a position or acceleration target)
VELOCITY_IGNORED = 0b11000


def scalar_flow(msg: Any, profile: Profile, q_rad_per_count: float) -> FlowColumns:
    """One flow message as scalars in the paper's convention (``profiles.flow_scalar``)."""
    return flow_scalar(msg, profile, q_rad_per_count)


def gyro_time_s(msg: Any) -> float:
    """Sensor time of a gyro message, s, from its own time field (``profiles.TIME_FIELDS``, the
    rule recordings are read by too): RAW_IMU / HIGHRES_IMU ``time_usec``, SCALED_IMU ``time_boot_ms``."""
    name, factor, scale = TIME_FIELDS[msg.get_type()]
    return getattr(msg, name) * factor * scale


@dataclass
class MessageRouter:
    """Feeds a vehicle's messages to a ``CompanionCore``; returns a step output per flow frame."""

    core: CompanionCore
    profile: Profile
    vehicle_sysid: int | None = None
    #: messages ignored (wrong sender or target, wrong orientation, bad values) or setpoints clipped, by reason
    ignored: dict[str, int] = field(default_factory=dict)
    yaw_rad: float = 0.0
    #: the ``now_s`` of the last setpoint taken (None before any)
    last_setpoint_time: float | None = None

    def _ignore(self, why: str) -> None:
        self.ignored[why] = self.ignored.get(why, 0) + 1

    def handle(self, msg: Any, now_s: float | None = None) -> StepOutput | None:
        mtype = msg.get_type()
        if mtype in ("SET_POSITION_TARGET_LOCAL_NED", "MANUAL_CONTROL"):
            self.setpoint(msg, now_s)
            return None
        if self.vehicle_sysid is not None and msg.get_srcSystem() != self.vehicle_sysid:
            if mtype in GYRO_MESSAGES or mtype in ("DISTANCE_SENSOR", "OPTICAL_FLOW", "OPTICAL_FLOW_RAD"):
                self._ignore("sensor data from another system")
            return None
        if mtype in GYRO_MESSAGES:
            scale = GYRO_MESSAGES[mtype]
            gx, gy = msg.xgyro * scale, msg.ygyro * scale
            if mtype != "HIGHRES_IMU" and max(abs(msg.xgyro), abs(msg.ygyro)) >= INT16_CLIP:
                gx = gy = math.nan  # the int16 mrad/s field clipped: the rate is unknown (saturated)
            t = gyro_time_s(msg)
            self.core.on_gyro(t, gx, gy)
            fx, fy, _ = accel_m_s2(mtype, msg.xacc, msg.yacc, msg.zacc)
            self.core.on_accel(t, fx, fy)
        elif mtype == "DISTANCE_SENSOR":
            if msg.orientation != DOWNWARD:
                self._ignore("range not facing down")
                return None
            r = msg.current_distance * 0.01
            if not (msg.min_distance <= msg.current_distance <= msg.max_distance):
                r = math.nan  # outside the sensor's own limits: invalid
            self.core.on_range(msg.time_boot_ms * 1e-3, r)
        elif mtype == "ATTITUDE":
            if math.isfinite(msg.yaw):
                self.yaw_rad = msg.yaw
            self.core.on_attitude(msg.time_boot_ms * 1e-3, msg.roll, msg.pitch, msg.rollspeed, msg.pitchspeed)
        elif mtype == FLOW_MESSAGE[self.profile]:
            return self.core.on_flow(scalar_flow(msg, self.profile, self.core.cfg.flow_sensor.q_rad_per_count))
        return None

    def setpoint(self, msg: Any, now_s: float | None = None) -> bool:
        """A SET_POSITION_TARGET_LOCAL_NED or MANUAL_CONTROL: its velocity setpoint to the core
        (``CompanionCore.set_setpoint``). Returns whether it was taken (False: not for us, or
        ignored with the reason counted in ``ignored``)."""
        mtype = msg.get_type()
        target = msg.target if mtype == "MANUAL_CONTROL" else msg.target_system
        if self.vehicle_sysid is not None and target not in (0, self.vehicle_sysid):
            self._ignore("setpoint for another system")
            return False
        vmax = self.core.cfg.companion.max_speed_m_s
        if mtype == "MANUAL_CONTROL":
            vx, vy = msg.x / 1000.0 * vmax, msg.y / 1000.0 * vmax
        else:
            if msg.target_component not in (MAV_COMP_ID_ALL, COMPANION_COMPONENT):
                return False
            if msg.type_mask & VELOCITY_IGNORED:
                self._ignore("setpoint without a horizontal velocity")
                return False
            vx, vy = float(msg.vx), float(msg.vy)
            if msg.coordinate_frame == MAV_FRAME_LOCAL_NED:
                c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
                vx, vy = c * vx + s * vy, -s * vx + c * vy
            elif msg.coordinate_frame not in BODY_FRAMES:
                self._ignore("setpoint in an unsupported frame")
                return False
        if not (math.isfinite(vx) and math.isfinite(vy)):
            self._ignore("non-finite setpoint")
            return False
        if max(abs(vx), abs(vy)) > vmax:
            self._ignore("setpoint beyond max_speed_m_s (clipped)")
        self.core.set_setpoint(vx, vy)
        self.last_setpoint_time = now_s
        return True
