"""The companion's control step: align sensors, gate bad data, estimate (eq. 15), PI, command.

``CompanionCore`` is the one stateful object that the live MAVLink loop, the simulator's
scenarios and replay all drive, so the three run the same code:

    core.on_gyro(t, gx, gy)        # RAW_IMU / SCALED_IMU / HIGHRES_IMU, rad/s, sensor time s
    core.on_range(t, range_m)      # DISTANCE_SENSOR facing down, m
    core.set_setpoint(vx, vy)      # body-frame velocity setpoint, m/s
    out = core.on_flow(frame)      # one flow frame (profiles.FlowColumns of scalars) -> StepOutput

Time alignment (CONVENTIONS.md): the gyro sample used is the one nearest the flow frame's own
sensor time; the range is the latest reading. The command computed from frame k is meant to act
from frame k+1 on; the caller sends it.

Failsafe: when the frame cannot be trusted (quality 0, a count spike, no gyro near the frame,
a saturated or non-finite gyro, range missing, stale or outside the sensor's limits) the step
commands level attitude (hold), freezes the integrator and names the cause in
``StepOutput.hold_cause``; the next good frame resumes control.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass

from companion.config import Config
from companion.controller import PiController
from companion.estimator import VelocitySensor
from companion.profiles import FlowColumns, Profile


class HoldCause(enum.StrEnum):
    NONE = ""
    FLOW_QUALITY = "flow quality 0"
    FLOW_SPIKE = "flow spike"
    FLOW_STALE = "flow stale"
    FLOW_INVALID = "flow not finite"
    GYRO_MISSING = "no gyro sample at the flow frame"
    GYRO_INVALID = "gyro saturated or not finite"
    RANGE_MISSING = "no range reading"
    RANGE_STALE = "range stale"
    RANGE_INVALID = "range outside sensor limits"
    LINK = "link lost"


@dataclass(frozen=True)
class StepOutput:
    """The result of one control step (one flow frame). Angles in rad, speeds in m/s."""

    time_s: float  # the flow frame's sensor time
    dt_s: float  # the time the frame covers
    vx_m_s: float  # estimate (NaN when the frame was not usable)
    vy_m_s: float
    vx_set_m_s: float
    vy_set_m_s: float
    roll_cmd_rad: float
    pitch_cmd_rad: float
    hold_cause: HoldCause
    gyro_x_rad_s: float
    gyro_y_rad_s: float
    range_m: float

    @property
    def holding(self) -> bool:
        return self.hold_cause is not HoldCause.NONE


class CompanionCore:
    """Estimator + PI + gating, bound to one parameter set and one sensor profile."""

    def __init__(self, cfg: Config, profile: Profile = Profile.PAPER) -> None:
        self.cfg = cfg
        self.profile = profile
        c = cfg.companion
        self._skew_s = c.max_gyro_skew_s
        self._range_timeout_s = c.range_timeout_s
        self._gyro_limit = math.radians(cfg.imu.gyro_range_deg_s) * 0.999
        self._range_min_m = cfg.rangefinder.min_m
        self._range_max_m = cfg.rangefinder.max_m
        t_nom = cfg.flow_sensor.frame_period_s
        # a spike: more than this scene-angle rate (rad/s) in one frame
        self._max_scene_rate = c.max_flow_counts_per_frame * cfg.flow_sensor.q_rad_per_count / t_nom
        self.sensor = VelocitySensor(nominal_frame_s=t_nom)
        self.pi = PiController(cfg.controller.kp_rad_per_m_s, cfg.controller.ki_rad_per_m,
                               cfg.controller.tilt_limit_rad)
        self._gyro: deque[tuple[float, float, float]] = deque(maxlen=32)
        self._range: tuple[float, float] | None = None  # (time_s, range_m) of the latest reading
        self.setpoint_m_s = (0.0, 0.0)
        self.last: StepOutput | None = None

    # -- inputs ------------------------------------------------------------------------------

    def on_gyro(self, time_s: float, gyro_x_rad_s: float, gyro_y_rad_s: float) -> None:
        if self._gyro and time_s < self._gyro[-1][0] - 1.0:  # the vehicle rebooted: forget the past
            self._gyro.clear()
        self._gyro.append((time_s, gyro_x_rad_s, gyro_y_rad_s))

    def on_range(self, time_s: float, range_m: float) -> None:
        self._range = (time_s, range_m)

    def set_setpoint(self, vx_m_s: float, vy_m_s: float) -> None:
        """Body-frame velocity setpoint; non-finite values are ignored, each axis is clipped to
        the maximum speed (as the tilt limit is per axis)."""
        if not (math.isfinite(vx_m_s) and math.isfinite(vy_m_s)):
            return
        vmax = self.cfg.companion.max_speed_m_s
        self.setpoint_m_s = (min(max(vx_m_s, -vmax), vmax), min(max(vy_m_s, -vmax), vmax))

    # -- the step ----------------------------------------------------------------------------

    def _aligned_gyro(self, time_s: float) -> tuple[float, float] | None:
        best = None
        best_skew = self._skew_s
        for t, gx, gy in reversed(self._gyro):
            skew = abs(t - time_s)
            if skew <= best_skew:
                best, best_skew = (gx, gy), skew
            elif t < time_s - self._skew_s:
                break
        return best

    def _gate(self, f: FlowColumns, gyro: tuple[float, float] | None) -> HoldCause:
        if not (math.isfinite(f.scene_x) and math.isfinite(f.scene_y) and math.isfinite(f.time_s)):
            return HoldCause.FLOW_INVALID
        if int(f.quality) == 0:
            return HoldCause.FLOW_QUALITY
        if gyro is None:
            return HoldCause.GYRO_MISSING
        gx, gy = gyro
        if not (math.isfinite(gx) and math.isfinite(gy)) or abs(gx) >= self._gyro_limit \
                or abs(gy) >= self._gyro_limit:
            return HoldCause.GYRO_INVALID
        if self._range is None:
            return HoldCause.RANGE_MISSING
        t_r, r = self._range
        if not (math.isfinite(r) and self._range_min_m <= r <= self._range_max_m):
            return HoldCause.RANGE_INVALID
        if f.time_s - t_r > self._range_timeout_s:
            return HoldCause.RANGE_STALE
        return HoldCause.NONE

    def on_flow(self, f: FlowColumns) -> StepOutput:
        """Run one control step on a flow frame (scalars). Always returns a finite command."""
        gyro = self._aligned_gyro(f.time_s)
        cause = self._gate(f, gyro)
        gx, gy = gyro if gyro is not None else (math.nan, math.nan)
        rng = self._range[1] if self._range is not None else math.nan
        vx = vy = math.nan
        if cause is HoldCause.NONE:
            vx, vy, dt, rate_x, rate_y = self.sensor.update(f.time_s, f.scene_x, f.scene_y, f.increment,
                                                            f.integration_s, gx, gy, rng)
            if max(abs(rate_x), abs(rate_y)) > self._max_scene_rate:
                cause = HoldCause.FLOW_SPIKE
                vx = vy = math.nan
        else:
            dt = self.cfg.flow_sensor.frame_period_s
            if math.isfinite(f.time_s):
                self.sensor.prev_time_s = f.time_s
        sx, sy = self.setpoint_m_s
        if cause is HoldCause.NONE:
            roll, pitch = self.pi.step(sx - vx, sy - vy, dt)
        else:
            roll = pitch = 0.0
        out = StepOutput(f.time_s, dt, vx, vy, sx, sy, roll, pitch, cause, gx, gy, rng)
        self.last = out
        return out
