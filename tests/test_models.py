"""The pure models against closed forms: attitude loop, translation, scene angle, flow counts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import FlowScale, FlowYawMisalignment, GyroBias, RangeOffset, with_effects
from simvehicle.model.flow_sensor import flow_frame, sensor_axes
from simvehicle.model.plant import AXIS_SIGN, PlantParams, axis_rk4
from simvehicle.model.sim import Simulator


def _integrate(x, u, force, alt, sign, p, t_end, h=1e-3):
    for _ in range(int(round(t_end / h))):
        x = axis_rk4(x, u, force, alt, sign, h, p=p)
    return x


def test_attitude_loop_step_response_matches_second_order_closed_form(paper_cfg):
    p = PlantParams.nominal(paper_cfg)
    wp, z, u = p.omega_p_rad_s, p.zeta, 0.1
    wd = wp * math.sqrt(1 - z * z)
    for t in (0.1, 0.3, 0.7, 1.5):
        x = _integrate((0.0, 0.0, 0.0, 0.0, 0.0), u, 0.0, 1.0, -1.0, p, t)
        theta = u * (1 - math.exp(-z * wp * t) * (math.cos(wd * t) + z / math.sqrt(1 - z * z) * math.sin(wd * t)))
        assert x[1] == pytest.approx(theta, abs=1e-9)


@pytest.mark.parametrize("sign", AXIS_SIGN)
def test_held_tilt_accelerates_by_g_tan_and_wind_by_f_over_m(paper_cfg, sign):
    p = PlantParams.nominal(paper_cfg)
    angle, force, t = 0.1, -4.0, 2.0
    # start in equilibrium at the tilt: omega 0, angle = u
    x = _integrate((0.0, angle, 0.0, 0.0, 0.0), angle, force, 1.0, sign, p, t)
    a = sign * 9.81 * math.tan(angle) + force / 2.3
    assert x[2] == pytest.approx(a * t, rel=1e-9)
    assert x[3] == pytest.approx(0.5 * a * t * t, rel=1e-9)


def test_linear_drag_gives_exponential_decay(paper_cfg):
    p = PlantParams(2.3, 9.81, 5.4, 0.71, 0.2)
    x = _integrate((0.0, 0.0, 1.0, 0.0, 0.0), 0.0, 0.0, 1.0, -1.0, p, 3.0)
    assert x[2] == pytest.approx(math.exp(-0.2 / 2.3 * 3.0), rel=1e-9)


@pytest.mark.parametrize("v0,omega0,alt", [(0.37, 0.0, 1.0), (0.0, 0.05, 1.0), (-0.8, 0.12, 0.66), (0.01, -0.003, 2.0)])
def test_flow_counts_match_closed_form_to_the_count(paper_cfg, v0, omega0, alt):
    """Constant velocity and body rate: phi_x(t) = (-omega_y - V/A) t, X_k = floor(phi(kT)/Q)."""
    # a plant with no attitude loop and no gravity keeps omega and v constant
    p = PlantParams(2.3, 0.0, 1e-9, 0.71, 0.0)
    q, T, n_sub = paper_cfg.flow_sensor.q_rad_per_count, 0.02, 20
    x = (omega0, 0.0, v0, 0.0, 0.0)
    prev = (0, 0)
    for k in range(1, 501):
        for _ in range(n_sub):
            x = axis_rk4(x, 0.0, 0.0, alt, -1.0, T / n_sub, p=p)
        prev, (dx, _) = flow_frame(x[4], 0.0, prev, q_x_rad_per_count=q, q_y_rad_per_count=q)
        phi = (-omega0 - v0 / alt) * k * T
        assert prev[0] == math.floor(phi / q), k
        assert dx == math.floor(phi / q) - math.floor((-omega0 - v0 / alt) * (k - 1) * T / q)


def test_sensor_axes_rotation_preserves_length_and_turns_by_yaw():
    sx, sy = sensor_axes(1.0, 0.0, math.radians(30))
    assert math.hypot(sx, sy) == pytest.approx(1.0)
    assert math.atan2(sy, sx) == pytest.approx(-math.radians(30))


def test_simulator_hover_is_quiet_and_effects_show_in_sensors(paper_cfg):
    sim = Simulator(paper_cfg)
    for _ in range(50):
        s = sim.advance(0.0, 0.0)
    assert (s.flow_x_counts, s.flow_y_counts, s.gyro_x_rad_s, s.range_m) == (0, 0, 0.0, 1.0)
    cfg = with_effects(paper_cfg, gyro_bias=GyroBias(0.01, -0.02), range_offset=RangeOffset(0.05))
    s = Simulator(cfg).advance(0.0, 0.0)
    assert (s.gyro_x_rad_s, s.gyro_y_rad_s) == pytest.approx((0.01, -0.02))
    assert s.range_m == pytest.approx(1.05)


def test_simulator_flow_scale_and_misalignment_change_counts(paper_cfg):
    def drift_counts(cfg):
        sim = Simulator(cfg)
        sim.x = (0.0, 0.0, 0.5, 0.0, 0.0)  # 0.5 m/s forward, level
        total = np.zeros(2)
        for _ in range(100):
            s = sim.advance(0.0, 0.0)
            total += (s.flow_x_counts, s.flow_y_counts)
        return total

    nominal = drift_counts(paper_cfg)
    scaled = drift_counts(with_effects(paper_cfg, flow_scale=FlowScale(1.25, 1.0)))
    assert nominal[0] < 0 and nominal[1] == 0
    assert scaled[0] == pytest.approx(nominal[0] / 1.25, abs=1.0)
    turned = drift_counts(with_effects(paper_cfg, flow_yaw_misalignment=FlowYawMisalignment(math.radians(10))))
    assert turned[1] == pytest.approx(-math.sin(math.radians(10)) * nominal[0], abs=1.0)


def test_hand_written_rk4_equals_textbook_rk4(paper_cfg):
    from simvehicle.model.plant import axis_rk4_reference

    rng = np.random.default_rng(5)
    p = PlantParams(2.3, 9.81, 5.4, 0.71, 0.2)
    for _ in range(200):
        x = tuple(rng.normal(0, 0.3, 5))
        args = (float(rng.normal(0, 0.2)), float(rng.normal(0, 2)), float(rng.uniform(0.3, 3)),
                float(rng.choice([-1.0, 1.0])), 1e-3)
        a = axis_rk4(x, *args, p=p)
        b = axis_rk4_reference(x, *args, p=p)
        assert np.allclose(a, b, rtol=1e-13, atol=1e-15)
