"""Eq. 15 against an independent computation; the PI law, its anti-windup and its wrapper."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.step.controller import PiController, PiState, pi_step
from companion.step.core import CompanionCore, HoldCause
from companion.step.estimator import VelocitySensor, velocity_from_flow
from companion.step.profiles import FlowColumns


def test_eq15_against_hand_computation():
    rng = np.random.default_rng(1)
    q, T = 0.09 / 57.3, 0.02
    for _ in range(200):
        dX, dY = rng.integers(-40, 40, 2)
        wx, wy = rng.normal(0, 0.5, 2)
        A = rng.uniform(0.2, 4)
        vx, vy = velocity_from_flow(dX * q / T, dY * q / T, wx, wy, A)
        assert vx == pytest.approx((-wy - dX * (q / T)) * A, rel=1e-12, abs=1e-15)
        assert vy == pytest.approx((+wx - dY * (q / T)) * A, rel=1e-12, abs=1e-15)


def test_eq15_inverts_the_truth_model_for_constant_motion():
    """A sensor moving at V with no rotation for one frame: dX = -V T/(A Q) -> V back."""
    q, T, A, V = 0.0015, 0.02, 0.66, 0.3
    dX = -V * T / (A * q)
    vx, _ = velocity_from_flow(dX * q / T, 0.0, 0.0, 0.0, A)
    assert vx == pytest.approx(V, rel=1e-12)


def test_array_and_scalar_forms_agree():
    rng = np.random.default_rng(2)
    args = [rng.normal(size=50) for _ in range(4)] + [rng.uniform(0.5, 2, 50)]
    vx, vy = velocity_from_flow(*args)
    for i in range(50):
        sx, sy = velocity_from_flow(*(float(a[i]) for a in args))
        assert (sx, sy) == (vx[i], vy[i])


def _plain_pi(errors, dt, kp, ki):
    """The paper's PI with no limit: an independent, textbook implementation."""
    integ = [0.0, 0.0]
    out = []
    for ex, ey in errors:
        integ[0] += ex * dt
        integ[1] += ey * dt
        out.append((kp * ey + ki * integ[1], -(kp * ex + ki * integ[0])))
    return out


def test_pi_equals_the_paper_law_while_inside_the_limit():
    rng = np.random.default_rng(3)
    errors = rng.normal(0, 0.2, (500, 2))
    ref = _plain_pi(errors, 0.02, 0.2, 0.062)
    assert max(max(abs(r), abs(p)) for r, p in ref) < math.radians(20)
    c = PiController(0.2, 0.062, math.radians(20))
    for (ex, ey), (r_ref, p_ref) in zip(errors, ref, strict=True):
        r, p = c.step(ex, ey, 0.02)
        assert (r, p) == pytest.approx((r_ref, p_ref), abs=1e-12)


def test_pure_step_and_wrapper_agree_to_1e12():
    rng = np.random.default_rng(4)
    c = PiController(0.2, 0.062, math.radians(20))
    s = PiState()
    for ex, ey in rng.normal(0, 3, (300, 2)):
        s, r1, p1 = pi_step(s, ex, ey, 0.02, kp_rad_per_m_s=0.2, ki_rad_per_m=0.062, limit_rad=math.radians(20))
        r2, p2 = c.step(ex, ey, 0.02)
        assert abs(r1 - r2) < 1e-12 and abs(p1 - p2) < 1e-12
    assert s == c.state


def test_saturation_clips_and_does_not_wind_up():
    lim = math.radians(20)
    c = PiController(0.2, 0.062, lim)
    for _ in range(1000):  # 20 s of a 5 m/s error: saturated throughout
        r, p = c.step(5.0, -5.0, 0.02)
        assert abs(r) <= lim and abs(p) <= lim
    assert p == -lim and r == -lim
    # integral held: without anti-windup it would be 5 m/s * 20 s = 100 m
    assert abs(c.state.integral_x_m) < lim / 0.062 + 1e-9
    # as soon as the error reverses, the command leaves the limit
    r, p = c.step(-0.5, 0.5, 0.02)
    assert abs(p) < lim


def test_velocity_sensor_wrapper_uses_frame_spacing():
    vs = VelocitySensor(nominal_frame_s=0.02)
    q = 0.0015
    vx, _, dt, _, _ = vs.update(0.0, -10 * q, 0.0, True, math.nan, 0.0, 0.0, 1.0)
    assert dt == 0.02 and vx == pytest.approx(10 * q / 0.02)
    vx, _, dt, _, _ = vs.update(0.04, -10 * q, 0.0, True, math.nan, 0.0, 0.0, 1.0)  # one frame missed
    assert dt == pytest.approx(0.04) and vx == pytest.approx(10 * q / 0.04)


def _frame(t, cx=0.0, cy=0.0, quality=255, q=0.09 / 57.3):
    return FlowColumns(t, cx * q, cy * q, True, math.nan, quality, cx, cy)


@pytest.mark.parametrize("case,cause", [
    ("quality", HoldCause.FLOW_QUALITY), ("spike", HoldCause.FLOW_SPIKE), ("nogyro", HoldCause.GYRO_MISSING),
    ("gyrosat", HoldCause.GYRO_INVALID), ("norange", HoldCause.RANGE_MISSING),
    ("rangeout", HoldCause.RANGE_INVALID), ("rangestale", HoldCause.RANGE_STALE)])
def test_core_holds_level_on_bad_data_and_resumes(paper_cfg, case, cause):
    core = CompanionCore(paper_cfg)
    core.set_setpoint(1.0, 0.0)
    t = 1.0
    if case != "nogyro":
        core.on_gyro(t, 40.0 if case == "gyrosat" else 0.0, 0.0)
    if case != "norange":
        core.on_range(t - (1.0 if case == "rangestale" else 0.0), 9.0 if case == "rangeout" else 1.0)
    f = _frame(t, cx=500 if case == "spike" else 0, quality=0 if case == "quality" else 255)
    out = core.on_flow(f)
    assert out.hold_cause is cause
    assert (out.roll_cmd_rad, out.pitch_cmd_rad) == (0.0, 0.0)
    # good data again: control resumes (nose down to speed up)
    t2 = t + 0.02
    core.on_gyro(t2, 0.0, 0.0)
    core.on_range(t2, 1.0)
    out = core.on_flow(_frame(t2))
    assert out.hold_cause is HoldCause.NONE and out.pitch_cmd_rad < 0
