"""``companion.rotation``, the one ZYX Euler <-> quaternion conversion (issue 13), against the
closed form: the product of the three elementary rotations, and their rotation matrices."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from companion.rotation import euler_to_quaternion, euler_to_quaternions, quaternion_to_euler, quaternions_to_euler

ANGLES = [(0.0, 0.0, 0.0), (0.3, 0.0, 0.0), (0.0, -0.2, 0.0), (0.0, 0.0, 2.5), (0.1, -0.35, 1.2),
          (-2.9, 1.4, -3.0), (0.7, -1.5, 0.4)]


def _hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@pytest.mark.parametrize("roll,pitch,yaw", ANGLES)
def test_quaternion_is_yaw_then_pitch_then_roll(roll, pitch, yaw):
    q = np.array(euler_to_quaternion(roll, pitch, yaw))
    qx = np.array([math.cos(roll / 2), math.sin(roll / 2), 0, 0])
    qy = np.array([math.cos(pitch / 2), 0, math.sin(pitch / 2), 0])
    qz = np.array([math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)])
    assert_allclose(q, _hamilton(_hamilton(qz, qy), qx), atol=1e-15)
    # body FRD -> NED: R = Rz(yaw) Ry(pitch) Rx(roll); positive pitch lifts the nose (x gets -z in NED)
    assert_allclose(_matrix(q), _rz(yaw) @ _ry(pitch) @ _rx(roll), atol=1e-15)
    assert math.isclose(float(np.dot(q, q)), 1.0, rel_tol=1e-15)


@pytest.mark.parametrize("roll,pitch,yaw", ANGLES)
def test_euler_round_trip(roll, pitch, yaw):
    assert quaternion_to_euler(euler_to_quaternion(roll, pitch, yaw)) == pytest.approx((roll, pitch, yaw), abs=1e-12)


def test_nose_up_pitch_points_the_body_x_axis_up():
    r = _matrix(np.array(euler_to_quaternion(0.0, math.radians(10.0), 0.0)))
    assert r[2, 0] == pytest.approx(-math.sin(math.radians(10.0)))  # NED z of body x: negative = up


def test_array_and_scalar_forms_agree():
    """One formula, two backends: the quaternions agree bit for bit (cos and sin round alike), the
    angles to an ulp or two (numpy's arctan2 and arcsin are not libm's)."""
    rng = np.random.default_rng(13)
    e = rng.uniform([-math.pi, -1.5, -math.pi], [math.pi, 1.5, math.pi], size=(500, 3))
    q = euler_to_quaternions(e[:, 0], e[:, 1], e[:, 2])
    assert q.shape == (500, 4)
    assert_array_equal(q, np.array([euler_to_quaternion(*row) for row in e]))
    back = np.stack(quaternions_to_euler(q), axis=-1)
    assert_allclose(back, np.array([quaternion_to_euler(row) for row in q]), rtol=0, atol=1e-15)
    assert_allclose(back, e, atol=1e-12)


def test_pitch_is_clipped_not_nan_past_the_pole():
    q = [math.sqrt(0.5) * 1.001, 0.0, math.sqrt(0.5) * 1.001, 0.0]  # 2(wy - zx) = 1.002
    assert quaternion_to_euler(q)[1] == math.pi / 2
    assert quaternions_to_euler(np.array([q]))[1][0] == math.pi / 2
