"""Attitude conversions: ZYX Euler angles <-> quaternions [w, x, y, z], the one implementation.

The MAVLink / ArduPilot / PX4 convention (CONVENTIONS.md): the quaternion of the rotation from
body FRD to local NED, made of yaw about z, then pitch about the new y, then roll about the new
x; roll, pitch and yaw in rad. Each formula is written once and evaluated with either ``math``
(scalars: the live loop, the simulated vehicle, one message at a time) or numpy (columns of a
recording): the quaternions agree bit for bit, the angles to an ulp (numpy's arctan2 and arcsin
are not libm's). scipy's ``Rotation`` would do as well, but replay and info must not load scipy
(tests/test_lazy_imports.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import numpy as np

X = TypeVar("X", float, np.ndarray)


def _quaternion(cos: Callable[[X], X], sin: Callable[[X], X], roll: X, pitch: X, yaw: X) -> tuple[X, X, X, X]:
    cr, sr = cos(roll / 2), sin(roll / 2)
    cp, sp = cos(pitch / 2), sin(pitch / 2)
    cy, sy = cos(yaw / 2), sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy)


def _euler(atan2: Callable[[X, X], X], asin_clipped: Callable[[X], X], w: X, x: X, y: X, z: X) -> tuple[X, X, X]:
    roll = atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = asin_clipped(2 * (w * y - z * x))
    yaw = atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def _asin_clipped_scalar(v: float) -> float:
    return math.asin(max(-1.0, min(1.0, v)))


def _asin_clipped_array(v: np.ndarray) -> np.ndarray:
    return np.arcsin(np.clip(v, -1.0, 1.0))


def euler_to_quaternion(roll_rad: float, pitch_rad: float, yaw_rad: float) -> list[float]:
    """[w, x, y, z] of the ZYX (yaw, pitch, roll) rotation body -> local NED (one attitude)."""
    return list(_quaternion(math.cos, math.sin, float(roll_rad), float(pitch_rad), float(yaw_rad)))


def quaternion_to_euler(q: Sequence[float] | np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) rad of one quaternion [w, x, y, z] (ZYX; pitch in [-pi/2, pi/2], roll
    and yaw in [-pi, pi])."""
    w, x, y, z = (float(v) for v in q)
    return _euler(math.atan2, _asin_clipped_scalar, w, x, y, z)


def euler_to_quaternions(roll_rad: Any, pitch_rad: Any, yaw_rad: Any) -> np.ndarray:
    """Quaternions [w, x, y, z] of the ZYX Euler angles (rad, equal shapes ``s``): shape ``s + (4,)``."""
    r, p, y = (np.asarray(a, dtype=np.float64) for a in (roll_rad, pitch_rad, yaw_rad))
    return np.stack(_quaternion(np.cos, np.sin, r, p, y), axis=-1)


def quaternions_to_euler(q: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(roll, pitch, yaw) rad of quaternions [w, x, y, z], shape ``s + (4,)``: three arrays of
    shape ``s`` (ZYX, as ``quaternion_to_euler``)."""
    a = np.asarray(q, dtype=np.float64)
    return _euler(np.arctan2, _asin_clipped_array, a[..., 0], a[..., 1], a[..., 2], a[..., 3])
