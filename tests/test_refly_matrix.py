"""Issue 16 end to end: effects set by PARAM_SET while flying, found, flown again, undone.

``simvehicle.server.paramflight`` flies the in-process vehicle of ``serve`` with the companion; the
vehicle applies ArduPilot's flow frontend (FLOW_FXSCALER, FLOW_FYSCALER, FLOW_ORIENT_YAW) to the
``ardupilot`` profile's flow as ArduPilot's source does (telemetry.ardupilot_flow_frontend).
The whole matrix is ``scripts/refly_matrix.py`` (docs/refly_matrix.md).
"""

from __future__ import annotations

import math

import pytest

from companion.config import FlowScale, FlowYawMisalignment, LinearDrag, WindForce, load_config, replace_section
from companion.diagnose.advice import flow_scaler_permille, orient_yaw_cd
from companion.diagnose.closed_loop.command import write_model_out
from companion.diagnose.closed_loop.diagnosis import diagnose
from companion.recordings.load import load_recording
from companion.step.profiles import Profile
from simvehicle.engines.flights import flight_plan, param_error_ratios, with_sensor_noise
from simvehicle.engines.scenarios import Scenario
from simvehicle.server.paramflight import ParamChange, fly_with_params
from simvehicle.server.server import Vehicle
from simvehicle.tools.refly import compare


def _rates(v: Vehicle) -> tuple[float, float]:
    m = dict(v.frame(commit=False).messages)["OPTICAL_FLOW"]
    return m.flow_rate_x, m.flow_rate_y


def test_ardupilots_frontend_in_the_vehicle_undoes_a_scale_and_a_yaw(paper_cfg):
    """The same motion seen by a sensor with scale (1.15, 1.10) turned 8 deg, through the frontend
    set to the values ``advice`` computes from the truth, gives the flow of a perfect sensor."""
    sx, sy, yaw = 1.15, 1.10, math.radians(8.0)
    ref = Vehicle(paper_cfg, profile=Profile.ARDUPILOT)
    bad = Vehicle(paper_cfg, profile=Profile.ARDUPILOT)
    for name, value in (("SIM_FLOW_SCALE_X", sx), ("SIM_FLOW_SCALE_Y", sy), ("SIM_FLOW_YAW", yaw),
                        # FLOW_FXSCALER scales MAVLink's x rate, the paper's y axis
                        ("FLOW_FXSCALER", round(flow_scaler_permille(sy))),
                        ("FLOW_FYSCALER", round(flow_scaler_permille(sx))),
                        ("FLOW_ORIENT_YAW", round(orient_yaw_cd(yaw)))):
        bad.set_param(name, value)
    for v in (ref, bad):
        v.armed, v.custom_mode = True, 20
        v.cmd_rad, v.cmd_time_s = (0.15, -0.2), 0.0  # lean right and forward: moving and turning
        v.values["GUID_TIMEOUT"] = 30.0
    worst = 0.0
    for _ in range(150):
        ref.advance()
        bad.advance()
        (rx, ry), (bx, by) = _rates(ref), _rates(bad)
        worst = max(worst, abs(bx - rx), abs(by - ry))
    # a count (Q / T = 0.0785 rad/s) of quantization each, times the scale: a little over 0.1 rad/s at most
    assert worst < 0.12
    moving = _rates(ref)
    assert math.hypot(*moving) > 1.0  # the comparison is not of two zeros


def test_a_param_set_during_the_flight_acts_from_then_and_is_recorded(tmp_path, paper_cfg):
    tlog = tmp_path / "p.tlog"
    vals = fly_with_params(paper_cfg, Scenario("hover", 6.0, lambda _t: (0.0, 0.0)),
                           [ParamChange(2.0, "SIM_WIND_FX", 2.3), ParamChange(2.0, "FLOW_ORIENT_YAW", 500.0)], tlog)
    assert vals["SIM_WIND_FX"] == pytest.approx(2.3)  # PARAM_SET carries float32
    rec = load_recording(tlog)
    pv = rec.table("PARAM_VALUE")
    got = dict(zip(pv["param_id"], pv["param_value"], strict=True))
    assert got["SIM_WIND_FX"] == pytest.approx(2.3) and got["FLOW_ORIENT_YAW"] == 500.0
    # the vehicle leans against the forward force from 2 s on (v' = -g tan(pitch) + F / m = 0): nose up by
    # atan(2.3 N / (2.3 kg g)) = 0.10 rad, 4 s later still settling (the PI's overshoot: within 0.01 rad)
    att = rec.table("ATTITUDE")
    t = att["time_boot_ms"] * 1e-3
    assert abs(float(att["pitch"][t < 2.0].max())) < 1e-6
    assert float(att["pitch"][-1]) == pytest.approx(math.atan(2.3 / (2.3 * 9.81)), abs=0.01)


def test_combined_effects_are_found_flown_again_within_the_noise_and_undone(tmp_path):
    """The combined case of docs/refly_matrix.md (seed 35): drag 0.5, scale (1.15, 1.10), yaw 8 deg set
    1 s into the flight, a wind of (2, -1) N from 50 to 100 s."""
    truth = {"linear_drag": LinearDrag(0.5), "flow_scale": FlowScale(1.15, 1.10),
             "flow_yaw_misalignment": FlowYawMisalignment(math.radians(8.0)),
             "wind_force": WindForce(2.0, -1.0, 50.0, 100.0)}
    changes = [ParamChange(1.0, "SIM_DRAG_B", 0.5), ParamChange(1.0, "SIM_FLOW_SCALE_X", 1.15),
               ParamChange(1.0, "SIM_FLOW_SCALE_Y", 1.10), ParamChange(1.0, "SIM_FLOW_YAW", math.radians(8.0)),
               ParamChange(50.0, "SIM_WIND_FX", 2.0), ParamChange(50.0, "SIM_WIND_FY", -1.0),
               ParamChange(100.0, "SIM_WIND_FX", 0.0), ParamChange(100.0, "SIM_WIND_FY", 0.0)]
    # flown on eq. 15, the estimator the fast engine that refly uses flies (the ardupilot profile's
    # default, the Kalman filter, would differ from it frame by frame whatever the model)
    base = replace_section(with_sensor_noise(load_config()), "companion", velocity_estimator="eq15")
    plan = flight_plan(35)
    tlog = tmp_path / "combined.tlog"
    fly_with_params(base, plan.scenario(), changes, tlog, profile=Profile.ARDUPILOT, seed=35)
    rec = load_recording(tlog)
    diag = diagnose(rec, base)
    model = tmp_path / "fitted.toml"
    write_model_out(rec, base, diag, model)
    fitted = load_config(model)
    for e, v in truth.items():  # the written model, within the finder's tolerances of the truth
        got = vars(getattr(fitted.effects, e))
        assert all(r <= 1.0 for r in param_error_ratios(e, vars(v), got).values()), (e, got)
    res = compare(tlog, fitted)
    floor, by = res.unrepro.floor, {s.channel: s for s in res.scores}
    for ch in ("pitch_cmd", "roll_cmd"):
        assert by[ch].rms_fitted < 1.15 * floor[ch], ch  # within the recording's noise (measured: 1.03, 1.02)
    for ch in ("pitch_cmd_1s", "roll_cmd_1s"):
        # 1 s means hide the frame noise and show what the half-flight fit misses (measured: 1.19, 1.28 widths)
        assert by[ch].rms_fitted < 1.5 * floor[ch], ch
    for ch in ("pitch_cmd_1s", "roll_cmd_1s"):
        assert by[ch].rms_nominal > 10.0 * floor[ch], ch  # the nominal model many noise widths off (20.7, 15.1)
    fixes = [ParamChange(0.5, a.parameter, float(a.value)) for a in diag.report.actions
             if a.system == "ardupilot" and a.parameter in ("FLOW_FXSCALER", "FLOW_FYSCALER", "FLOW_ORIENT_YAW")]
    assert len(fixes) == 3
    tlog2 = tmp_path / "fixed.tlog"
    fly_with_params(base, plan.scenario(), fixes + changes, tlog2, profile=Profile.ARDUPILOT, seed=35)
    left = {f.effect for f in diagnose(load_recording(tlog2), base).report.significant()}
    assert not left & {"flow_scale", "flow_yaw_misalignment"}  # undone; drag and wind are physics
    assert {"linear_drag", "wind_force"} <= left
