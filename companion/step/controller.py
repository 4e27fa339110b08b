"""The paper's discrete PI velocity controller (Fig. 12, Table VI), both axes.

    u_pitch = -(Kp e_x + Ki sum(e_x T)),   u_roll = +(Kp e_y + Ki sum(e_y T)),   e = v_set - v_est

each clipped to the tilt limit. Anti-windup by conditional integration: a step's error is
added to the integral unless the output is saturated and the error pushes it further in; so
while the command stays inside its limit the law is exactly the paper's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class PiState:
    """Integral of the velocity error per axis, sum(e T), in metres."""

    integral_x_m: float = 0.0
    integral_y_m: float = 0.0


def _axis(integral_m: float, err_m_s: float, dt_s: float, kp: float, ki: float,
          limit_rad: float) -> tuple[float, float]:
    """One axis: returns (new integral, effort in rad clipped to +-limit)."""
    candidate = integral_m + err_m_s * dt_s
    effort = kp * err_m_s + ki * candidate
    if effort > limit_rad or effort < -limit_rad:
        if err_m_s * effort > 0.0:  # pushing further into saturation: hold the integral
            candidate = integral_m
            effort = kp * err_m_s + ki * candidate
        effort = min(max(effort, -limit_rad), limit_rad)
    return candidate, effort


def pi_step(state: PiState, err_x_m_s: float, err_y_m_s: float, dt_s: float, *, kp_rad_per_m_s: float,
            ki_rad_per_m: float, limit_rad: float) -> tuple[PiState, float, float]:
    """One control step. Returns (new state, roll_cmd_rad, pitch_cmd_rad)."""
    ix, effort_x = _axis(state.integral_x_m, err_x_m_s, dt_s, kp_rad_per_m_s, ki_rad_per_m, limit_rad)
    iy, effort_y = _axis(state.integral_y_m, err_y_m_s, dt_s, kp_rad_per_m_s, ki_rad_per_m, limit_rad)
    return PiState(ix, iy), effort_y, -effort_x


@dataclass
class PiController:
    """Stateful wrapper around ``pi_step`` with gains bound once."""

    kp_rad_per_m_s: float
    ki_rad_per_m: float
    limit_rad: float
    state: PiState = PiState()

    def step(self, err_x_m_s: float, err_y_m_s: float, dt_s: float) -> tuple[float, float]:
        """Returns (roll_cmd_rad, pitch_cmd_rad)."""
        if not (math.isfinite(err_x_m_s) and math.isfinite(err_y_m_s) and math.isfinite(dt_s)):
            raise ValueError("PI step needs finite errors and time step")
        self.state, roll, pitch = pi_step(self.state, err_x_m_s, err_y_m_s, dt_s,
                                          kp_rad_per_m_s=self.kp_rad_per_m_s,
                                          ki_rad_per_m=self.ki_rad_per_m, limit_rad=self.limit_rad)
        return roll, pitch
