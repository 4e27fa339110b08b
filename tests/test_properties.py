"""Property-based tests: whatever the sensors say, the command is finite and inside the limit."""

from __future__ import annotations

import math

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.config import load_config
from companion.step.controller import PiState, pi_step
from companion.step.core import CompanionCore, HoldCause
from companion.step.estimator import velocity_from_flow
from companion.step.profiles import FlowColumns

CFG = load_config()
LIMIT = CFG.controller.tilt_limit_rad
anything = st.floats(allow_nan=True, allow_infinity=True)
sane = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)

event = st.one_of(
    st.tuples(st.just("gyro"), anything, anything, anything),
    st.tuples(st.just("range"), anything, anything),
    st.tuples(st.just("setpoint"), anything, anything),
    st.tuples(st.just("flow"), anything, anything, anything, st.integers(-10, 300), st.booleans(), anything),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(event, min_size=1, max_size=60))
def test_core_command_always_finite_and_limited(events):
    core = CompanionCore(CFG)
    for e in events:
        kind = e[0]
        if kind == "gyro":
            core.on_gyro(e[1], e[2], e[3])
        elif kind == "range":
            core.on_range(e[1], e[2])
        elif kind == "setpoint":
            core.set_setpoint(e[1], e[2])
        else:
            _, t, sx, sy, quality, increment, integ = e
            out = core.on_flow(FlowColumns(t, sx, sy, increment, integ, quality, math.nan, math.nan))
            assert math.isfinite(out.roll_cmd_rad) and math.isfinite(out.pitch_cmd_rad)
            assert abs(out.roll_cmd_rad) <= LIMIT and abs(out.pitch_cmd_rad) <= LIMIT
            if out.hold_cause is not HoldCause.NONE:
                assert (out.roll_cmd_rad, out.pitch_cmd_rad) == (0.0, 0.0)
            else:
                assert math.isfinite(out.vx_m_s) and math.isfinite(out.vy_m_s)


@settings(max_examples=500, deadline=None)
@given(st.lists(st.tuples(sane, sane, st.floats(min_value=1e-4, max_value=1.0)), min_size=1, max_size=200))
def test_pi_step_never_leaves_the_limit(steps):
    s = PiState()
    for ex, ey, dt in steps:
        s, roll, pitch = pi_step(s, ex, ey, dt, kp_rad_per_m_s=0.2, ki_rad_per_m=0.062, limit_rad=LIMIT)
        assert math.isfinite(roll) and math.isfinite(pitch)
        assert abs(roll) <= LIMIT and abs(pitch) <= LIMIT
        assert math.isfinite(s.integral_x_m) and math.isfinite(s.integral_y_m)


@settings(max_examples=300, deadline=None)
@given(sane, sane, sane, sane, st.floats(min_value=0.01, max_value=10))
def test_estimator_is_linear_in_flow_and_gyro(rx, ry, gx, gy, a):
    vx, vy = velocity_from_flow(rx, ry, gx, gy, a)
    assert vx == (-gy - rx) * a and vy == (gx - ry) * a
