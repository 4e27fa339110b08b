"""The companion's messages (CONVENTIONS.md): SET_ATTITUDE_TARGET, POSITION_TARGET_LOCAL_NED,
VISION_SPEED_ESTIMATE and its HEARTBEAT. Conversion to MAVLink units and fields happens only here."""

from __future__ import annotations

import math
from typing import Any

COMPANION_COMPONENT = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
ATTITUDE_TYPE_MASK = 7  # body roll, pitch and yaw rates ignored
HOLD_THRUST = 0.5  # ArduCopter GUIDED_NOGPS: 0.5 = hold altitude
FRAME_BODY_FRD = 12
#: POSITION_TARGET type_mask: position, acceleration, yaw and yaw rate ignored (velocity only)
VELOCITY_TYPE_MASK = 0b0000110111000111  # 3527


def euler_to_quaternion(roll_rad: float, pitch_rad: float, yaw_rad: float) -> list[float]:
    """[w, x, y, z] of the ZYX (yaw, pitch, roll) rotation body -> local NED."""
    cr, sr = math.cos(roll_rad / 2), math.sin(roll_rad / 2)
    cp, sp = math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
    cy, sy = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2)
    return [cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy]


def quaternion_to_euler(q: Any) -> tuple[float, float, float]:
    """(roll, pitch, yaw) rad from [w, x, y, z] (ZYX)."""
    w, x, y, z = (float(v) for v in q)
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def set_attitude_target(enc: Any, time_boot_ms: int, target_system: int, roll_rad: float, pitch_rad: float,
                        yaw_rad: float, target_component: int = 1) -> Any:
    return enc.set_attitude_target_encode(int(time_boot_ms) & 0xFFFFFFFF, target_system, target_component,
                                          ATTITUDE_TYPE_MASK, euler_to_quaternion(roll_rad, pitch_rad, yaw_rad),
                                          0.0, 0.0, 0.0, HOLD_THRUST)


def position_target(enc: Any, time_boot_ms: int, vx_m_s: float, vy_m_s: float) -> Any:
    return enc.position_target_local_ned_encode(int(time_boot_ms) & 0xFFFFFFFF, FRAME_BODY_FRD,
                                                VELOCITY_TYPE_MASK, 0.0, 0.0, 0.0, vx_m_s, vy_m_s, 0.0,
                                                0.0, 0.0, 0.0, 0.0, 0.0)


def vision_speed(enc: Any, usec: int, vx_m_s: float, vy_m_s: float) -> Any:
    nan = float("nan")
    return enc.vision_speed_estimate_encode(int(usec), vx_m_s, vy_m_s, 0.0, [nan] * 9, 0)


def heartbeat(enc: Any) -> Any:
    from pymavlink.dialects.v20 import ardupilotmega as mav

    return enc.heartbeat_encode(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0,
                                mav.MAV_STATE_ACTIVE)
