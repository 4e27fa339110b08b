"""The vehicle's messages from a simulated frame, in the chosen sensor profile (CONVENTIONS.md).

Conversion to MAVLink units, integer fields and each autopilot's conventions happens only here:
paper (OPTICAL_FLOW counts, time_usec in µs), ardupilot (OPTICAL_FLOW rates in flow_rate_*,
time_usec in *milliseconds*, flow_x/y truncated rad/s), px4 (OPTICAL_FLOW_RAD integrated rad).
"""

from __future__ import annotations

import math
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.mavlink_ids import DOWNWARD, GUIDED_NOGPS
from companion.recordings.importers.common import GRAVITY_M_S2
from companion.rotation import euler_to_quaternion
from companion.step.profiles import Profile
from simvehicle.model.sim import FrameSample


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(x))))


def ardupilot_flow_frontend(rate_x: float, rate_y: float, *, fx_scaler_permille: float, fy_scaler_permille: float,
                            orient_yaw_cd: float) -> tuple[float, float]:
    """ArduPilot's flow frontend on one MAVLink flow-rate pair (rad/s, sensor axes): each axis
    times ``1 + 0.001 FLOW_FxSCALER``, then turned into body axes by ``+FLOW_ORIENT_YAW``
    (libraries/AP_OpticalFlow/AP_OpticalFlow_Pixart.cpp ``update()``: ``flowScaleFactorX = 1.0f +
    0.001f * flowScaler.x``; AP_OpticalFlow_Backend.cpp ``_applyYaw``: ``v.rotate(yaw)``)."""
    rx = rate_x * (1.0 + 0.001 * fx_scaler_permille)
    ry = rate_y * (1.0 + 0.001 * fy_scaler_permille)
    if orient_yaw_cd == 0.0:
        return rx, ry
    a = math.radians(orient_yaw_cd / 100.0)
    c, s = math.cos(a), math.sin(a)
    return c * rx - s * ry, s * rx + c * ry


#: the ArduPilot flow frontend's parameters at their defaults: (FLOW_FXSCALER, FLOW_FYSCALER, FLOW_ORIENT_YAW)
NO_FRONTEND = (0.0, 0.0, 0.0)


def flow_message(enc: Any, s: FrameSample, profile: Profile, q_rad_per_count: float, frame_s: float,
                 frontend: tuple[float, float, float] = NO_FRONTEND) -> Any:
    """The flow message of one frame. The sensor's counts are the truth model's (eq. 9-11).
    ``frontend``: ArduPilot's FLOW_FXSCALER, FLOW_FYSCALER (per mille), FLOW_ORIENT_YAW (cdeg), applied
    to the ``ardupilot`` profile's rates as ArduPilot applies them (``ardupilot_flow_frontend``)."""
    dphi_x = s.flow_x_counts * q_rad_per_count  # paper-convention scene-angle increments
    dphi_y = s.flow_y_counts * q_rad_per_count
    rate_x, rate_y = dphi_y / frame_s, -dphi_x / frame_s  # MAVLink flow_rate: x-flow carries y-motion
    if profile is Profile.ARDUPILOT and frontend != NO_FRONTEND:
        rate_x, rate_y = ardupilot_flow_frontend(rate_x, rate_y, fx_scaler_permille=frontend[0],
                                                 fy_scaler_permille=frontend[1], orient_yaw_cd=frontend[2])
    t_us = int(round(s.t_s * 1e6))
    if profile is Profile.PAPER:
        return enc.optical_flow_encode(t_us, 0, s.flow_x_counts, s.flow_y_counts, 0.0, 0.0, s.flow_quality,
                                       -1.0, rate_x, rate_y)
    if profile is Profile.ARDUPILOT:
        return enc.optical_flow_encode(int(round(s.t_s * 1e3)), 0, int(rate_x), int(rate_y),
                                       rate_x - s.gyro_x_rad_s, rate_y - s.gyro_y_rad_s, s.flow_quality,
                                       s.range_m, rate_x, rate_y)
    return enc.optical_flow_rad_encode(t_us, 0, int(round(frame_s * 1e6)), dphi_y, -dphi_x,
                                       s.gyro_x_rad_s * frame_s, s.gyro_y_rad_s * frame_s,
                                       s.gyro_z_rad_s * frame_s, 2500, s.flow_quality, 0, s.range_m)


def accel_mg(s: FrameSample) -> tuple[int, int, int]:
    """RAW_IMU's accelerometer fields: the sample's body FRD specific force in milli-g of standard
    gravity (ArduPilot's GRAVITY_MSS, 9.80665), rounded to 1 mg and clipped to int16 (level: (0, 0,
    -1000)); a sample without an accelerometer (NaN) gives that placeholder, as recordings made
    before the simulator had one hold."""
    if not (math.isfinite(s.accel_x_m_s2) and math.isfinite(s.accel_y_m_s2) and math.isfinite(s.accel_z_m_s2)):
        return 0, 0, -1000
    k = 1e3 / GRAVITY_M_S2
    return _i16(s.accel_x_m_s2 * k), _i16(s.accel_y_m_s2 * k), _i16(s.accel_z_m_s2 * k)


def raw_imu(enc: Any, s: FrameSample) -> Any:
    """RAW_IMU: gyro in mrad/s (ArduPilot's convention), accelerometer in milli-g (``accel_mg``)."""
    return enc.raw_imu_encode(int(round(s.t_s * 1e6)), *accel_mg(s), _i16(s.gyro_x_rad_s * 1e3),
                              _i16(s.gyro_y_rad_s * 1e3), _i16(s.gyro_z_rad_s * 1e3), 0, 0, 0)


def distance_sensor(enc: Any, s: FrameSample, min_m: float, max_m: float) -> Any:
    cm = s.range_m * 100.0
    cur = 0 if not math.isfinite(cm) else int(max(0, min(65535, round(cm))))
    return enc.distance_sensor_encode(int(round(s.t_s * 1e3)), int(round(min_m * 100)), int(round(max_m * 100)),
                                      cur, mav.MAV_DISTANCE_SENSOR_LASER, 0, DOWNWARD, 255)


def attitude(enc: Any, s: FrameSample) -> Any:
    return enc.attitude_encode(int(round(s.t_s * 1e3)), s.roll_rad, s.pitch_rad, 0.0, s.roll_rate_rad_s,
                               s.pitch_rate_rad_s, 0.0)


def local_position(enc: Any, s: FrameSample) -> Any:
    """Ground truth (simulator only), NED = body axes at yaw 0."""
    return enc.local_position_ned_encode(int(round(s.t_s * 1e3)), s.x_m, s.y_m, -s.altitude_m, s.vx_m_s,
                                         s.vy_m_s, 0.0)


def attitude_target(enc: Any, t_s: float, roll_rad: float, pitch_rad: float) -> Any:
    return enc.attitude_target_encode(int(round(t_s * 1e3)), 7, euler_to_quaternion(roll_rad, pitch_rad, 0.0),
                                      0.0, 0.0, 0.0, 0.5)


def heartbeat(enc: Any, armed: bool, custom_mode: int = GUIDED_NOGPS) -> Any:
    base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
    return enc.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base, custom_mode,
                                mav.MAV_STATE_ACTIVE if armed else mav.MAV_STATE_STANDBY)


def frame_messages(enc: Any, s: FrameSample, profile: Profile, q_rad_per_count: float, frame_s: float,
                   range_min_m: float, range_max_m: float) -> list[Any]:
    """The per-frame stream, gyro and range before the flow so the frame finds them aligned."""
    return [raw_imu(enc, s), distance_sensor(enc, s, range_min_m, range_max_m),
            flow_message(enc, s, profile, q_rad_per_count, frame_s), attitude(enc, s), local_position(enc, s)]
