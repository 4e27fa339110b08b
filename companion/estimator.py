"""The paper's velocity sensor (eq. 15), both axes, as a pure function with a thin wrapper.

    V_x = (-omega_y - dX_k Q / T) A        V_y = (+omega_x - dY_k Q / T) A

``Omega = dphi / T`` is the scene-angle rate over the frame in the paper's convention (see
``companion.profiles``), ``omega_x``, ``omega_y`` the roll- and pitch-rate gyro (rad/s, body
FRD) time-aligned to the frame, ``A`` the range to the ground (m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np


def velocity_from_flow(scene_rate_x_rad_s: Any, scene_rate_y_rad_s: Any, gyro_x_rad_s: Any,
                       gyro_y_rad_s: Any, range_m: Any) -> tuple[Any, Any]:
    """Eq. 15 on scalars or arrays: body-frame horizontal velocity (vx_m_s, vy_m_s)."""
    vx = (-gyro_y_rad_s - scene_rate_x_rad_s) * range_m
    vy = (gyro_x_rad_s - scene_rate_y_rad_s) * range_m
    return vx, vy


def scene_rate(scene: Any, increment: bool, integration_s: Any, frame_dt_s: Any) -> Any:
    """Scene-angle rate (rad/s) from a profile's flow quantity.

    Increments (rad) are divided by the message's own integration time when it states one
    (finite ``integration_s``), otherwise by the spacing of the flow frames ``frame_dt_s``.
    Rates (rad/s) pass through.
    """
    if not increment:
        return scene
    dt = np.where(np.isfinite(integration_s) & (np.asarray(integration_s) > 0), integration_s, frame_dt_s)
    return scene / dt


def scene_rate_scalar(scene: float, increment: bool, integration_s: float, frame_dt_s: float) -> float:
    """``scene_rate`` for one frame in plain floats (the live loop's hot path), same rule."""
    if not increment:
        return scene
    own = integration_s == integration_s and integration_s != math.inf and integration_s > 0.0
    return scene / (integration_s if own else frame_dt_s)


def frame_spacing(prev_time_s: float | None, time_s: float, nominal_s: float) -> float:
    """The time a flow frame's counts cover: the spacing from the previous frame when it is
    plausible (0 < dt <= 5 frames), else the nominal frame period (first frame, reboot, gap)."""
    if prev_time_s is None:
        return nominal_s
    dt = time_s - prev_time_s
    if 0.0 < dt <= 5.0 * nominal_s:
        return dt
    return nominal_s


def frame_spacing_array(time_s: np.ndarray, nominal_s: float) -> np.ndarray:
    """``frame_spacing`` over a whole column of frame times (replay), same rule."""
    dt = np.empty_like(time_s, dtype=float)
    if len(time_s) == 0:
        return dt
    dt[0] = nominal_s
    d = np.diff(time_s)
    dt[1:] = np.where((d > 0.0) & (d <= 5.0 * nominal_s), d, nominal_s)
    return dt


@dataclass
class VelocitySensor:
    """Stateful wrapper: remembers the previous frame time to get the frame spacing."""

    nominal_frame_s: float
    prev_time_s: float | None = None

    def update(self, time_s: float, scene_x: float, scene_y: float, increment: bool,
               integration_s: float, gyro_x_rad_s: float, gyro_y_rad_s: float,
               range_m: float) -> tuple[float, float, float, float, float]:
        """Returns (vx_m_s, vy_m_s, frame_dt_s, scene_rate_x_rad_s, scene_rate_y_rad_s)."""
        dt = frame_spacing(self.prev_time_s, time_s, self.nominal_frame_s)
        self.prev_time_s = time_s
        rx = scene_rate_scalar(scene_x, increment, integration_s, dt)
        ry = scene_rate_scalar(scene_y, increment, integration_s, dt)
        vx, vy = velocity_from_flow(rx, ry, gyro_x_rad_s, gyro_y_rad_s, range_m)
        return float(vx), float(vy), dt, rx, ry
