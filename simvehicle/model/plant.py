"""The paper's plant, one horizontal axis at a time (eq. 26-28), and the scene angle (eq. 8).

Per axis the continuous state is ``(omega, angle, v, pos, phi)``:

    omega_dot = Omega_p^2 (u - angle) - 2 zeta Omega_p omega       (attitude loop, eq. 26)
    angle_dot = omega
    v_dot     = s g tan(angle) + F_W / m - (b / m) v                  (eq. 28 with F_W / m; b = 0 nominal)
    pos_dot   = v
    phi_dot   = s omega - v / A                                       (scene angle, eq. 5-8)

with ``s = -1`` for the x axis (pitch: nose-up pitch accelerates backwards, phi_x = -omega_y -
V_x/A) and ``s = +1`` for y (roll: right-side-down roll accelerates right, phi_y = +omega_x -
V_y/A). The two axes are independent. Pure functions of (state, input, time step); the
parameters are keyword-only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.config import Config

AXIS_SIGN = (-1.0, +1.0)  # x (pitch), y (roll)

AxisState = tuple[float, float, float, float, float]  # omega rad/s, angle rad, v m/s, pos m, phi rad


@dataclass(frozen=True)
class PlantParams:
    """Truth parameters of the plant (nominal Table VI values unless an effect changes them)."""

    mass_kg: float
    gravity_m_s2: float
    omega_p_rad_s: float
    zeta: float
    drag_b_n_s_per_m: float  # 0 in the paper's eq. 28; the linear_drag effect sets it

    @classmethod
    def truth(cls, cfg: Config) -> PlantParams:
        """The plant the simulator flies: nominal, with attitude_dynamics / linear_drag applied."""
        a = cfg.airframe
        e = cfg.effects
        wp, z = a.omega_p_rad_s, a.zeta
        if e.attitude_dynamics is not None:
            wp, z = e.attitude_dynamics.omega_p, e.attitude_dynamics.zeta
        b = e.linear_drag.b if e.linear_drag is not None else 0.0
        return cls(a.mass_kg, a.gravity_m_s2, wp, z, b)

    @classmethod
    def nominal(cls, cfg: Config) -> PlantParams:
        """The paper's model (eq. 26-28): no drag, nominal attitude loop."""
        a = cfg.airframe
        return cls(a.mass_kg, a.gravity_m_s2, a.omega_p_rad_s, a.zeta, 0.0)


def axis_derivative(x: AxisState, u_rad: float, force_n: float, altitude_m: float, sign: float, *,
                    p: PlantParams) -> AxisState:
    """Time derivative of one axis' state (see the module docstring)."""
    omega, angle, v, _pos, _phi = x
    wp = p.omega_p_rad_s
    omega_dot = wp * wp * (u_rad - angle) - 2.0 * p.zeta * wp * omega
    v_dot = sign * p.gravity_m_s2 * math.tan(angle) + (force_n - p.drag_b_n_s_per_m * v) / p.mass_kg
    phi_dot = sign * omega - v / altitude_m
    return (omega_dot, omega, v_dot, v, phi_dot)


def axis_rk4(x: AxisState, u_rad: float, force_n: float, altitude_m: float, sign: float, dt_s: float, *,
             p: PlantParams) -> AxisState:
    """One classical Runge-Kutta step of one axis, input and altitude held over the step.

    Written out by hand (it is the simulator's inner loop); the same arithmetic as four calls
    of ``axis_derivative`` (a test checks the two agree).
    """
    h = dt_s
    wp2 = p.omega_p_rad_s * p.omega_p_rad_s
    c = 2.0 * p.zeta * p.omega_p_rad_s
    sg = sign * p.gravity_m_s2
    inv_m = 1.0 / p.mass_kg
    b = p.drag_b_n_s_per_m
    inv_a = 1.0 / altitude_m
    tan = math.tan
    w0, a0, v0, x0, f0 = x
    # k1
    dw1 = wp2 * (u_rad - a0) - c * w0
    dv1 = sg * tan(a0) + (force_n - b * v0) * inv_m
    # k2
    w2, a2, v2 = w0 + 0.5 * h * dw1, a0 + 0.5 * h * w0, v0 + 0.5 * h * dv1
    dw2 = wp2 * (u_rad - a2) - c * w2
    dv2 = sg * tan(a2) + (force_n - b * v2) * inv_m
    # k3
    w3, a3, v3 = w0 + 0.5 * h * dw2, a0 + 0.5 * h * w2, v0 + 0.5 * h * dv2
    dw3 = wp2 * (u_rad - a3) - c * w3
    dv3 = sg * tan(a3) + (force_n - b * v3) * inv_m
    # k4
    w4, a4, v4 = w0 + h * dw3, a0 + h * w3, v0 + h * dv3
    dw4 = wp2 * (u_rad - a4) - c * w4
    dv4 = sg * tan(a4) + (force_n - b * v4) * inv_m
    h6 = h / 6.0
    return (w0 + h6 * (dw1 + 2.0 * dw2 + 2.0 * dw3 + dw4),
            a0 + h6 * (w0 + 2.0 * w2 + 2.0 * w3 + w4),
            v0 + h6 * (dv1 + 2.0 * dv2 + 2.0 * dv3 + dv4),
            x0 + h6 * (v0 + 2.0 * v2 + 2.0 * v3 + v4),
            f0 + h6 * ((sign * w0 - v0 * inv_a) + 2.0 * (sign * w2 - v2 * inv_a)
                       + 2.0 * (sign * w3 - v3 * inv_a) + (sign * w4 - v4 * inv_a)))


def axis_rk4_reference(x: AxisState, u_rad: float, force_n: float, altitude_m: float, sign: float, dt_s: float,
                       *, p: PlantParams) -> AxisState:
    """The textbook RK4 step built from ``axis_derivative`` (to check ``axis_rk4`` against)."""
    h = dt_s
    k1 = axis_derivative(x, u_rad, force_n, altitude_m, sign, p=p)
    x2 = tuple(xi + 0.5 * h * ki for xi, ki in zip(x, k1, strict=True))
    k2 = axis_derivative(x2, u_rad, force_n, altitude_m, sign, p=p)  # type: ignore[arg-type]
    x3 = tuple(xi + 0.5 * h * ki for xi, ki in zip(x, k2, strict=True))
    k3 = axis_derivative(x3, u_rad, force_n, altitude_m, sign, p=p)  # type: ignore[arg-type]
    x4 = tuple(xi + h * ki for xi, ki in zip(x, k3, strict=True))
    k4 = axis_derivative(x4, u_rad, force_n, altitude_m, sign, p=p)  # type: ignore[arg-type]
    return tuple(xi + h / 6.0 * (a + 2.0 * b + 2.0 * c + d)  # type: ignore[return-value]
                 for xi, a, b, c, d in zip(x, k1, k2, k3, k4, strict=True))


ZERO_AXIS: AxisState = (0.0, 0.0, 0.0, 0.0, 0.0)
