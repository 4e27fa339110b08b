"""The companion's messages (CONVENTIONS.md): SET_ATTITUDE_TARGET, POSITION_TARGET_LOCAL_NED,
VISION_SPEED_ESTIMATE and its HEARTBEAT. Conversion to MAVLink units and fields happens only here."""

from __future__ import annotations

import math
from typing import Any

from companion.mavlink_ids import COMPANION_COMPONENT, MAV_FRAME_BODY_FRD
from companion.rotation import euler_to_quaternion, quaternion_to_euler

__all__ = ["COMPANION_COMPONENT", "ATTITUDE_TYPE_MASK", "HOLD_THRUST", "VELOCITY_TYPE_MASK", "euler_to_quaternion",
           "quaternion_to_euler", "set_attitude_target", "position_target", "vision_speed", "heartbeat"]

ATTITUDE_TYPE_MASK = 7  # body roll, pitch and yaw rates ignored
HOLD_THRUST = 0.5  # ArduCopter GUIDED_NOGPS: 0.5 = hold altitude
#: POSITION_TARGET type_mask: position, acceleration, yaw and yaw rate ignored (velocity only)
VELOCITY_TYPE_MASK = 0b0000110111000111  # 3527


def set_attitude_target(enc: Any, time_boot_ms: int, target_system: int, roll_rad: float, pitch_rad: float,
                        yaw_rad: float, target_component: int = 1) -> Any:
    return enc.set_attitude_target_encode(int(time_boot_ms) & 0xFFFFFFFF, target_system, target_component,
                                          ATTITUDE_TYPE_MASK, euler_to_quaternion(roll_rad, pitch_rad, yaw_rad),
                                          0.0, 0.0, 0.0, HOLD_THRUST)


def position_target(enc: Any, time_boot_ms: int, vx_m_s: float, vy_m_s: float) -> Any:
    return enc.position_target_local_ned_encode(int(time_boot_ms) & 0xFFFFFFFF, MAV_FRAME_BODY_FRD,
                                                VELOCITY_TYPE_MASK, 0.0, 0.0, 0.0, vx_m_s, vy_m_s, 0.0,
                                                0.0, 0.0, 0.0, 0.0, 0.0)


def vision_speed(enc: Any, usec: int, vx_m_s: float, vy_m_s: float, vx_var_m2_s2: float = math.nan,
                 vy_var_m2_s2: float = math.nan) -> Any:
    """VISION_SPEED_ESTIMATE (body axes; ``z`` 0, not estimated). ``covariance`` is the 3x3 of
    (vx, vy, vz) row-major: the per-axis variances (m^2/s^2) on the diagonal when both are
    known (the Kalman filter's), 0 between the axes (estimated independently), NaN for vz;
    without them all NaN (MAVLink: NaN in the first element = unknown)."""
    nan = math.nan
    if math.isfinite(vx_var_m2_s2) and math.isfinite(vy_var_m2_s2):
        cov = [vx_var_m2_s2, 0.0, 0.0, 0.0, vy_var_m2_s2, 0.0, 0.0, 0.0, nan]
    else:
        cov = [nan] * 9
    return enc.vision_speed_estimate_encode(int(usec), vx_m_s, vy_m_s, 0.0, cov, 0)


def heartbeat(enc: Any) -> Any:
    from pymavlink.dialects.v20 import ardupilotmega as mav

    return enc.heartbeat_encode(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0,
                                mav.MAV_STATE_ACTIVE)
