"""What to set (issue 16): ``companion.diagnose.advice.actions`` and ``diagnose --json``'s ``actions``.

The autopilot mappings are checked against the autopilot's own arithmetic, written out here from
its source (not from ``advice``): ArduPilot's flow backends multiply the sensor's X/Y flow rate by
``1 + 0.001 FLOW_FxSCALER`` and then turn it into body axes with ``Vector2f::rotate(FLOW_ORIENT_YAW)``
(AP_OpticalFlow_Pixart.cpp / AP_OpticalFlow_MAV.cpp ``update()``, AP_OpticalFlow_Backend.cpp
``_applyYaw``); PX4's VehicleOpticalFlow multiplies both axes by ``SENS_FLOW_SCALE`` and turns them
with ``rotate_3f(SENS_FLOW_ROT)`` (``ROTATION_YAW_45``: x' = (x - y)/sqrt 2, y' = (x + y)/sqrt 2).
A sensor with the finder's effects reads, in its own axes, the body scene angle turned by -yaw
and divided by the scale (CONVENTIONS.md, simvehicle/model/flow_sensor.py).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from companion.diagnose.advice import actions, flow_scaler_permille, orient_yaw_cd, px4_flow_rot
from companion.diagnose.report import Action, Finding, Report

Q = 0.09 / 57.3


def _report(*findings: Finding) -> Report:
    return Report(recording="x.tlog", findings=list(findings))


def _scale(sx: float, sy: float, sdx: float = 0.01, sdy: float = 0.02) -> Finding:
    return Finding("flow_scale", True, {"scale_x": sx, "scale_y": sy}, {"scale_x": sdx, "scale_y": sdy}, "")


def _yaw(yaw: float, sd: float = 0.004) -> Finding:
    return Finding("flow_yaw_misalignment", True, {"yaw": yaw}, {"yaw": sd}, "")


def _by_name(acts: list[Action], system: str) -> dict[str, Action]:
    return {a.parameter: a for a in acts if a.system == system}


def _sensor_reads(phi_body: np.ndarray, sx: float, sy: float, yaw: float) -> np.ndarray:
    """The paper-convention scene angle a misaligned, mis-scaled sensor reports (its own axes)."""
    c, s = math.cos(yaw), math.sin(yaw)
    sensor = np.array([c * phi_body[0] + s * phi_body[1], -s * phi_body[0] + c * phi_body[1]])
    return sensor / np.array([sx, sy])


def _ardupilot_frontend(phi_sensor: np.ndarray, fx: float, fy: float, yaw_cd: float) -> np.ndarray:
    """ArduPilot's flow frontend on one frame, back in the paper's convention."""
    rate = np.array([phi_sensor[1], -phi_sensor[0]])  # MAVLink: x-flow carries y-motion
    rate = rate * np.array([1.0 + 0.001 * fx, 1.0 + 0.001 * fy])
    a = math.radians(yaw_cd / 100.0)
    rate = np.array([math.cos(a) * rate[0] - math.sin(a) * rate[1], math.sin(a) * rate[0] + math.cos(a) * rate[1]])
    return np.array([-rate[1], rate[0]])


@pytest.mark.parametrize(("sx", "sy", "yaw_deg"), [(1.1, 1.08, 0.0), (0.9, 0.93, 6.0), (1.2, 1.0, -10.0),
                                                   (1.0, 1.0, 25.0)])
def test_ardupilot_parameters_undo_a_scale_and_a_yaw_through_ardupilots_own_arithmetic(sx, sy, yaw_deg):
    acts = _by_name(actions(_report(_scale(sx, sy), _yaw(math.radians(yaw_deg))), profile="ardupilot",
                            q_rad_per_count=Q), "ardupilot")
    fx, fy, yaw_cd = (acts["FLOW_FXSCALER"].value, acts["FLOW_FYSCALER"].value, acts["FLOW_ORIENT_YAW"].value)
    rng = np.random.default_rng(1)
    for _ in range(5):
        phi = rng.normal(0.0, 0.01, 2)
        back = _ardupilot_frontend(_sensor_reads(phi, sx, sy, math.radians(yaw_deg)), fx, fy, yaw_cd)
        # per mille and centidegrees are whole numbers: 0.05 % of scale and 0.005 deg of yaw at most
        assert back == pytest.approx(phi, rel=2e-3, abs=1e-9)


def test_ardupilot_scaler_is_per_mille_on_the_swapped_axis_relative_to_the_one_flown():
    acts = _by_name(actions(_report(_scale(1.10, 0.95, 0.01, 0.02)), profile="ardupilot", q_rad_per_count=Q,
                            current={"FLOW_FXSCALER": 50.0}), "ardupilot")
    # FLOW_FXSCALER scales MAVLink's x rate = the paper's y axis: (1.05 x 0.95 - 1) x 1000 = -2.5 -> -2
    assert acts["FLOW_FXSCALER"].value == round((1.05 * 0.95 - 1.0) * 1000.0)
    assert acts["FLOW_FXSCALER"].sigma == pytest.approx(1050.0 * 0.02)
    assert acts["FLOW_FYSCALER"].value == 100.0 and acts["FLOW_FYSCALER"].sigma == pytest.approx(10.0)
    assert flow_scaler_permille(1.1) == pytest.approx(100.0)


def test_orient_yaw_is_centidegrees_added_to_the_one_flown_and_wrapped():
    assert orient_yaw_cd(math.radians(6.0)) == pytest.approx(600.0)
    assert orient_yaw_cd(math.radians(-30.0), current_cd=1000.0) == pytest.approx(-2000.0)
    assert orient_yaw_cd(math.radians(20.0), current_cd=17000.0) == pytest.approx(-17000.0)
    act = _by_name(actions(_report(_yaw(math.radians(3.0), sd=math.radians(0.5))), profile="ardupilot",
                           q_rad_per_count=Q), "ardupilot")["FLOW_ORIENT_YAW"]
    assert (act.value, act.sigma) == (300.0, pytest.approx(50.0))


def test_delays_are_milliseconds_and_lever_arms_metres():
    f_delay = Finding("flow_delay", True, {"delay": 0.034}, {"delay": 0.002}, "")
    f_arm = Finding("flow_lever_arm", True, {"rx": 0.0, "ry": 0.0, "rz": 0.08},
                    {"rx": math.nan, "ry": math.nan, "rz": 0.01}, "")
    ap = _by_name(actions(_report(f_delay, f_arm), profile="ardupilot", q_rad_per_count=Q,
                          current={"EK3_FLOW_DELAY": 10.0}), "ardupilot")
    assert (ap["EK3_FLOW_DELAY"].value, ap["EK3_FLOW_DELAY"].sigma) == (44.0, pytest.approx(2.0))
    assert (ap["FLOW_POS_Z"].value, ap["FLOW_POS_Z"].sigma) == (0.08, 0.01)
    assert "FLOW_POS_X" not in ap  # rx, ry are not fitted without yaw rate
    px = _by_name(actions(_report(f_delay, f_arm), profile="px4", q_rad_per_count=Q), "px4")
    assert px["EKF2_OF_DELAY"].value == pytest.approx(34.0) and px["EKF2_OF_POS_Z"].value == 0.08


def test_range_offset_is_taken_off_a_pwm_rangefinders_offset_in_cm():
    f = Finding("range_offset", True, {"offset": 0.05}, {"offset": 0.004}, "")
    act = _by_name(actions(_report(f), profile="ardupilot", q_rad_per_count=Q), "ardupilot")["RNGFND1_OFFSET"]
    assert (act.value, act.sigma) == (-5.0, pytest.approx(0.4))


def _px4_frontend(phi_sensor: np.ndarray, scale: float, rot: int) -> np.ndarray:
    """PX4's VehicleOpticalFlow on one frame: both axes scaled, then rotate_3f by rot x 45 deg."""
    rate = np.array([phi_sensor[1], -phi_sensor[0]]) * scale  # integrated_x carries y-motion
    for _ in range(rot):
        rate = np.array([(rate[0] - rate[1]) / math.sqrt(2.0), (rate[0] + rate[1]) / math.sqrt(2.0)])
    return np.array([-rate[1], rate[0]])


def test_px4_scale_is_one_factor_and_its_rotation_a_45_degree_step():
    acts = _by_name(actions(_report(_scale(1.1, 1.1), _yaw(math.radians(44.0))), profile="px4", q_rad_per_count=Q,
                            current={"SENS_FLOW_SCALE": 1.05}), "px4")
    assert acts["SENS_FLOW_SCALE"].value == pytest.approx(1.05 * 1.1)
    assert acts["SENS_FLOW_ROT"].value == 1.0
    phi = np.array([0.01, -0.004])
    back = _px4_frontend(_sensor_reads(phi, 1.1, 1.1, math.radians(45.0)), 1.1, 1)
    assert back == pytest.approx(phi, rel=1e-9)
    assert px4_flow_rot(math.radians(-90.0)) == 6
    # a small misalignment has no 45-degree step that undoes it: no PX4 action
    small = actions(_report(_yaw(math.radians(6.0))), profile="px4", q_rad_per_count=Q)
    assert not [a for a in small if a.parameter == "SENS_FLOW_ROT"]


def test_companion_keys_for_the_paper_profile_and_none_of_the_autopilots():
    drag = Finding("linear_drag", True, {"b": 0.3}, {"b": 0.02}, "")
    att = Finding("attitude_dynamics", True, {"omega_p": 13.7, "zeta": 1.14}, {"omega_p": 0.5, "zeta": 0.03}, "")
    wind = Finding("wind_force", True, {"fx": 1.0, "fy": 0.0, "start_s": 3.0, "end_s": 9.0},
                   {"fx": 0.1, "fy": 0.1, "start_s": 0.2, "end_s": 0.2}, "")
    lag = Finding("gyro_lag", True, {"tau": 0.01}, {"tau": 0.001}, "")
    out = actions(_report(_scale(1.1, 1.06, 0.01, 0.02), drag, att, wind, lag), profile="paper", q_rad_per_count=Q)
    assert {a.system for a in out} == {"companion"}
    comp = _by_name(out, "companion")
    # one Q for both axes: the mean of the scales, its sigma that of a mean of independent estimates
    assert comp["flow_sensor.q_rad_per_count"].value == pytest.approx(Q * 1.08)
    assert comp["flow_sensor.q_rad_per_count"].sigma == pytest.approx(Q * math.hypot(0.01, 0.02) / 2)
    assert comp["effects.linear_drag.b"].value == 0.3
    assert (comp["airframe.omega_p_rad_s"].value, comp["airframe.zeta"].value) == (13.7, 1.14)
    # a wind is this flight's circumstance and a gyro filter is not in the config: nothing to set
    assert not [a for a in out if a.because in ("wind_force", "gyro_lag")]
    # the ardupilot profile's flow is in rad: the scale goes to the autopilot, not to Q
    ap = actions(_report(_scale(1.1, 1.06)), profile="ardupilot", q_rad_per_count=Q)
    assert {a.system for a in ap} == {"ardupilot"}


def test_actions_json_shape():
    rep = _report(_scale(1.1, 1.06), Finding("flow_scale", False, {"scale_x": 2.0}, {"scale_x": 1.0}, ""))
    rep.actions = actions(rep, profile="ardupilot", q_rad_per_count=Q)
    data = json.loads(json.dumps(rep.to_json(), allow_nan=False))
    assert len(data["actions"]) == 2  # the not-significant finding gives none
    for a in data["actions"]:
        assert set(a) == {"system", "parameter", "value", "sigma", "because"}
        assert a["system"] in ("companion", "ardupilot", "px4")
        assert isinstance(a["value"], float) and isinstance(a["sigma"], float) and a["because"] == "flow_scale"


def test_the_html_page_lists_the_autopilot_values(tmp_path):
    from companion.diagnose.report_html import render

    rep = _report(_scale(1.1, 1.06), _yaw(math.radians(6.0)))
    rep.actions = actions(rep, profile="ardupilot", q_rad_per_count=Q)
    page = render(rep, "# x\n\ntext\n", tmp_path, q_rad_per_count=Q)
    assert "<code>FLOW_ORIENT_YAW</code></td><td>600</td>" in page
    assert "<code>FLOW_FXSCALER</code></td><td>60</td>" in page  # scale_y 1.06: x rate
    assert page.index("On the autopilot") < page.index("The evidence")
    rep.actions = actions(rep, profile="paper", q_rad_per_count=Q)
    assert "On the autopilot" not in render(rep, "# x\n", tmp_path, q_rad_per_count=Q)
