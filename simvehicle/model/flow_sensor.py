"""The optical-flow sensor truth model (eq. 9-11), both axes.

The scene angle ``phi`` is integrated in continuous time by the plant (``plant.py``); at each
frame time kT the sensor quantizes it and outputs the difference:

    X_k = floor(phi(kT) / Q),   dX_k = X_k - X_(k-1)

Effects the paper leaves out are applied here: ``flow_scale`` (a different true Q per axis),
``flow_yaw_misalignment`` (the sensor's axes turned about z), ``flow_delay`` (the scene angle
sampled ``delay`` before the frame time; the caller supplies the delayed angle).
"""

from __future__ import annotations

import math


def sensor_axes(phi_x_rad: float, phi_y_rad: float, yaw_rad: float) -> tuple[float, float]:
    """Body-frame scene angle expressed in flow-sensor axes turned by ``yaw_rad`` about body z."""
    if yaw_rad == 0.0:
        return phi_x_rad, phi_y_rad
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return c * phi_x_rad + s * phi_y_rad, -s * phi_x_rad + c * phi_y_rad


def quantize(phi_rad: float, q_rad_per_count: float) -> int:
    """Eq. 10: the accumulated count, ``floor(phi / Q)``."""
    return math.floor(phi_rad / q_rad_per_count)


def flow_frame(phi_x_rad: float, phi_y_rad: float, prev_counts: tuple[int, int], *, q_x_rad_per_count: float,
               q_y_rad_per_count: float, yaw_rad: float = 0.0) -> tuple[tuple[int, int], tuple[int, int]]:
    """One frame of eq. 9-11 on both axes.

    Returns ``((X_k, Y_k), (dX_k, dY_k))``: the accumulated counts to carry to the next frame
    and the per-frame counts the sensor outputs.
    """
    sx, sy = sensor_axes(phi_x_rad, phi_y_rad, yaw_rad)
    xk, yk = quantize(sx, q_x_rad_per_count), quantize(sy, q_y_rad_per_count)
    return (xk, yk), (xk - prev_counts[0], yk - prev_counts[1])
