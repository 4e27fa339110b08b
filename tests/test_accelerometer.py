"""The simulated vehicle's accelerometer (issue 19): ``imu.specific_force`` of the plant's motion,
``imu.accel_sample``'s bias, noise and range, RAW_IMU's milli-g fields (``telemetry.accel_mg``).

Closed forms: at rest an accelerometer reads (0, 0, -g) (ArduPilot's RAW_IMU -1000 mg on z); the
plant's eq. 28 with a horizontal force F and drag b v and the body pitched by theta reads
(F - b v) cos(theta) / m on body x (R^T (a - g): the thrust's share of the acceleration is along
body z), and the y axis likewise with roll. The sign: a force towards +x reads +x (ArduCopter
SITL's RAW_IMU against its SIM_STATE truth: docs/estimator.md)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.config import LinearDrag, WindForce, replace_section, with_effects
from companion.mavlink import link
from companion.recordings.importers.common import GRAVITY_M_S2
from companion.rotation import euler_to_quaternion
from simvehicle.model import telemetry
from simvehicle.model.imu import accel_sample, specific_force
from simvehicle.model.sim import Simulator

mav = link.mav


def _quiet(cfg, **imu):
    return replace_section(cfg, "imu", accel_noise_density_m_s2_sqrt_hz=0.0, **imu)


def test_a_hover_reads_minus_g_on_z(paper_cfg):
    cfg = _quiet(paper_cfg)
    sim = Simulator(cfg)
    for _ in range(10):
        s = sim.advance(0.0, 0.0)
    g = cfg.airframe.gravity_m_s2
    assert (s.accel_x_m_s2, s.accel_y_m_s2, s.accel_z_m_s2) == (0.0, 0.0, -g)
    m = mav.MAVLink(None).decode(bytearray(telemetry.raw_imu(mav.MAVLink(None), s).pack(mav.MAVLink(None))))
    assert (m.xacc, m.yacc, m.zacc) == (0, 0, round(-1000 * g / GRAVITY_M_S2))


@pytest.mark.parametrize("fx_n, fy_n", [(4.0, 0.0), (-4.0, 1.5), (0.0, -2.0)])
def test_a_steady_force_reads_force_over_mass_along_it(paper_cfg, fx_n, fy_n):
    """A sample is the mean specific force over the frame before it (an IMU's decimation). Level
    and still at the start: F / m exactly, with F's sign. Level against drag b: the frame's change
    of velocity over its length, which is (F - b v) / m at the frame's mean velocity (its change of
    position over its length). Pitched and rolled by constant commands, once the tilt has settled:
    (F - b v) cos(tilt) / m per axis at the frame's mean velocity and tilt (7e-9 m/s^2 apart as
    measured: the tilt has settled to 2e-9 rad a frame; held to 1e-7), y with the plant's
    second-order coupling (below)."""
    b = 0.3
    cfg = with_effects(_quiet(paper_cfg), wind_force=WindForce(fx_n, fy_n, 0.0, 1e9), linear_drag=LinearDrag(b))
    m, g, T = cfg.airframe.mass_kg, cfg.airframe.gravity_m_s2, cfg.flow_sensor.frame_period_s
    sim = Simulator(cfg)
    s = sim.current
    assert (s.accel_x_m_s2, s.accel_y_m_s2) == (pytest.approx(fx_n / m, abs=1e-15), pytest.approx(fy_n / m, abs=1e-15))
    for _ in range(20):
        p = sim.current
        s = sim.advance(0.0, 0.0)
        assert s.accel_x_m_s2 == pytest.approx((s.vx_m_s - p.vx_m_s) / T, abs=1e-12)
        assert s.accel_x_m_s2 == pytest.approx((fx_n - b * (s.x_m - p.x_m) / T) / m, abs=1e-9)
        assert s.accel_y_m_s2 == pytest.approx((fy_n - b * (s.y_m - p.y_m) / T) / m, abs=1e-9)
    worst = 0.0
    for k in range(200):
        p = sim.current
        s = sim.advance(math.radians(4.0), math.radians(-6.0))
        if k < 100:
            continue
        pitch, roll = 0.5 * (s.pitch_rad + p.pitch_rad), 0.5 * (s.roll_rad + p.roll_rad)
        vx, vy = (s.x_m - p.x_m) / T, (s.y_m - p.y_m) / T
        want_x = (fx_n - b * vx) * math.cos(pitch) / m
        want_y = (fy_n - b * vy) * math.cos(roll) / m
        # y: the plant's axes are independent (eq. 26-28), the rigid body's rotation is not: R^T adds
        # g sin(roll) (1 - cos(pitch)) + sin(roll) sin(pitch) a_x, second order in the tilt
        a_x = -g * math.tan(pitch) + (fx_n - b * vx) / m
        extra_y = g * math.sin(roll) * (1 - math.cos(pitch)) + math.sin(roll) * math.sin(pitch) * a_x
        assert s.accel_x_m_s2 == pytest.approx(want_x, abs=1e-7)
        assert s.accel_y_m_s2 - want_y == pytest.approx(extra_y, abs=1e-7)
        worst = max(worst, abs(extra_y))
    assert abs(s.pitch_rad) > math.radians(3.0) and worst < 0.02  # tilted, and the second-order term small


def test_specific_force_is_the_rotated_acceleration_less_gravity():
    """R^T (a - g) against the rotation matrix built from companion.rotation's quaternion."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        roll, pitch = rng.uniform(-0.5, 0.5, 2)
        a = rng.normal(0.0, 2.0, 3)
        w, x, y, z = euler_to_quaternion(roll, pitch, 0.0)
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        want = r.T @ (a - np.array([0.0, 0.0, 9.81]))
        assert specific_force(roll, pitch, *a, 9.81) == pytest.approx(tuple(want), abs=1e-12)


def test_bias_noise_range_and_the_raw_imu_fields(paper_cfg):
    rng = np.random.default_rng(3)
    xs = np.array([accel_sample(0.1, -0.2, -9.8, rng, bias_x_m_s2=0.05, bias_y_m_s2=-0.02,
                                noise_density_m_s2_sqrt_hz=0.0042, rate_hz=50.0, range_m_s2=156.9)
                   for _ in range(20000)])
    assert xs.mean(axis=0) == pytest.approx([0.15, -0.22, -9.8], abs=0.002)  # 4 sigma of the mean: 0.0009
    assert xs.std(axis=0) == pytest.approx([0.0042 * math.sqrt(50.0)] * 3, rel=0.03)  # 3 % = 4 sigma of a std
    assert accel_sample(500.0, -500.0, 0.0, None, bias_x_m_s2=0.0, bias_y_m_s2=0.0, noise_density_m_s2_sqrt_hz=0.0,
                        rate_hz=50.0, range_m_s2=156.9) == (156.9, -156.9, 0.0)
    s = Simulator(_quiet(paper_cfg)).current
    assert telemetry.accel_mg(dataclasses.replace(s, accel_x_m_s2=0.0049, accel_y_m_s2=-0.0051,
                                                  accel_z_m_s2=-400.0)) == (0, -1, -32768)
    assert telemetry.accel_mg(dataclasses.replace(s, accel_x_m_s2=math.nan)) == (0, 0, -1000)


def test_without_an_accelerometer_raw_imu_holds_the_placeholder(paper_cfg):
    cfg = replace_section(paper_cfg, "imu", accelerometer=False)
    s = Simulator(with_effects(cfg, wind_force=WindForce(4.0, 0.0, 0.0, 1e9))).advance(0.0, 0.0)
    assert math.isnan(s.accel_x_m_s2)
    assert telemetry.accel_mg(s) == (0, 0, -1000)


def test_the_accelerometer_noise_leaves_the_other_sensors_draws_alone(paper_cfg):
    """Its noise comes from its own stream: the rangefinder's noisy readings are those of a vehicle
    without an accelerometer, draw for draw."""
    cfg = replace_section(replace_section(paper_cfg, "rangefinder", noise_std_m=0.01), "imu", accel_noise=True)
    runs = []
    for acc in (True, False):
        sim = Simulator(replace_section(cfg, "imu", accelerometer=acc), rng=np.random.default_rng(5))
        runs.append([sim.advance(0.01, -0.01).range_m for _ in range(50)])
    assert runs[0] == runs[1] and len(set(runs[0])) > 3
