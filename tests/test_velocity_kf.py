"""The velocity Kalman filter (issue 19): ``estimator.VelocityKalman`` and the companion flying on it.

In the reference simulator, closed loop, the companion flying on the filter (``velocity_estimator
= "kf"``, paper profile, in process, ~0.5 s per flight): under the paper's gust and a steady wind,
with a 2 deg attitude trim error, with drag, at 0.5-3 m and with the flow sample 0-20 ms old, its
estimate against the simulator's truth has an RMS no worse than eq. 15's on the same frames and a
lag of at most 3 ms either way. On ArduCopter SITL flights E1 and C0 (``data/sitl/ardupilot``):
RMS per axis at or below EKF3's 0.017 m/s and |lag| <= 3 ms (``benchmarks/bench_estimator.py``
prints the full comparison).

Tolerances: the simulated flights are deterministic (seeded: the flow's quantization, which is the
paper's, and the accelerometer's white noise, 0.030 m/s^2 a sample from its own stream; the other
sensors' noise off), so each number is exact for the code as it stands and the assertions are the
issue's own bounds, not fitted. The margins as measured (docs/estimator.md), the companion taking
the vehicle's accelerometer as RAW_IMU carries it: the filter's RMS is 0.0016-0.0056 m/s against
eq. 15's 0.014-0.106, its lag within -0.8..+1.5 ms against the 3 ms bound, the paper's gust in a
hover at 0.5-3 m included (without the accelerometer +3.6 and +8.7 ms at 2 m and 3 m: the first
count after the gust comes 4 frames late there, and an estimate exact from then on would already be
4.5 ms late; the accelerometer reads the gust in the frame it starts), eq. 15 is 11-63 ms late; its
error^2 / variance 0.19-0.53. The lag is the peak of the correlation with the truth shifted
continuously (0.25 ms steps, parabola-refined), from 2 s on (the start-up). The filter alone on a
counting sensor (``_counts_flight``) holds the parts of the gust's handling: the running sum's
rounding error as one bounded state, the step search, and the accelerometer as the input.
"""

from __future__ import annotations

import dataclasses
import gzip
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fake_link import FakeLink
from pymavlink import mavutil
from scipy.special import ndtr

from companion.config import (
    FlowDelay,
    LinearDrag,
    WindForce,
    config_from_dict,
    load_config,
    read_toml,
    replace_section,
    with_effects,
)
from companion.errors import ConfigError
from companion.mavlink import link, outbound
from companion.mavlink.live import LiveCompanion
from companion.recordings.load import load_recording
from companion.step.core import CompanionCore, EstimatorOptions, VelocityEstimator, gyro_window_mean, kalman_settings
from companion.step.estimator import MAX_ATTITUDE_AGE_S, KalmanSettings, VelocityKalman, boxed_moments
from companion.step.profiles import FlowColumns, Profile, accel_m_s2
from companion.tools.replay import replay
from simvehicle.engines.scenarios import figures, run_named
from simvehicle.model import telemetry
from simvehicle.model.sim import Simulator, Turbulence

mav = link.mav
G = 9.81
LAG_BOUND_MS = 3.0
REPO = Path(__file__).resolve().parent.parent
SITL = REPO / "data" / "sitl" / "ardupilot"


def excite(t: float) -> tuple[float, float]:
    """Setpoints that keep both axes moving (0.3 Hz and 0.2 Hz sinusoids from 1 s)."""
    if t < 1.0:
        return 0.0, 0.0
    return 0.5 * math.sin(2 * math.pi * 0.3 * (t - 1.0)), 0.4 * math.sin(2 * math.pi * 0.2 * (t - 1.0) + 1.0)


def fly_core(cfg, *, duration_s: float = 20.0, setpoint=excite, force=lambda _t: (0.0, 0.0), trim_rad: float = 0.0,
             seed: int = 0, options: EstimatorOptions | None = None, turbulence: Turbulence | None = None,
             accelerometer: bool = True) -> dict[str, np.ndarray]:
    """The reference simulator closed by ``CompanionCore`` (paper profile), sensors fed directly in
    the live loop's order (gyro and range, the flow, then ATTITUDE: the attitude of a frame arrives
    after its flow, as ``telemetry.frame_messages`` sends them); ``trim_rad`` is added to the
    roll and pitch the companion is told; ``options`` replace the config's estimator choice (a
    study's own Kalman settings); ``turbulence`` a random force besides ``force``;
    ``accelerometer``: the vehicle's accelerometer goes to the core with its gyro, as RAW_IMU
    carries it (False: none, as a vehicle that sends the placeholder). Per frame:
    truth, the estimate flown, eq. 15, the steps the filter has taken on the two axes so far."""
    sim = Simulator(cfg, rng=np.random.default_rng(seed), external_force=force, turbulence=turbulence)
    core = CompanionCore(cfg, Profile.PAPER, options)
    q = cfg.flow_sensor.q_rad_per_count
    n = int(round(duration_s / cfg.flow_sensor.frame_period_s))
    s = sim.current
    rows = []
    for k in range(n + 1):
        t = s.t_s
        core.on_gyro(t, s.gyro_x_rad_s, s.gyro_y_rad_s)
        if accelerometer:  # as RAW_IMU carries it (milli-g, int16: profiles.accel_m_s2)
            fx, fy, _ = accel_m_s2("RAW_IMU", *telemetry.accel_mg(s))
            core.on_accel(t, fx, fy)
        core.on_range(t, s.range_m)
        core.set_setpoint(*setpoint(t))
        out = core.on_flow(FlowColumns(t, s.flow_x_counts * q, s.flow_y_counts * q, True, math.nan, s.flow_quality,
                                       float(s.flow_x_counts), float(s.flow_y_counts)))
        core.on_attitude(t, s.roll_rad + trim_rad, s.pitch_rad + trim_rad, s.roll_rate_rad_s, s.pitch_rate_rad_s)
        rows.append((t, s.vx_m_s, s.vy_m_s, out.vx_m_s, out.vy_m_s, out.vx_raw_m_s, out.vy_raw_m_s,
                     out.vx_var_m2_s2, out.vy_var_m2_s2, float(out.holding),
                     float(sum(ax.steps_found for ax in core.kalman.axes))))
        if k < n:
            s = sim.advance(out.roll_cmd_rad, out.pitch_cmd_rad)
    a = np.array(rows)
    names = ("t", "vx", "vy", "est_x", "est_y", "eq15_x", "eq15_y", "var_x", "var_y", "hold", "steps")
    return {name: a[:, i] for i, name in enumerate(names)}


def lag_ms(est: np.ndarray, t: np.ndarray, truth_t: np.ndarray, truth: np.ndarray, span_s: float = 0.1,
           step_s: float = 0.00025) -> float:
    """How late ``est`` (at times ``t``) is against ``truth`` (at ``truth_t``): the shift s
    maximising the correlation of est(t) with truth(t - s), parabola-refined; ms."""
    shifts = np.arange(-span_s, span_s + step_s / 2, step_s)
    e = est - est.mean()
    c = []
    for s in shifts:
        r = np.interp(t - s, truth_t, truth)
        r = r - r.mean()
        c.append(np.dot(e, r) / np.sqrt(np.dot(r, r) * np.dot(e, e)))
    c_a = np.array(c)
    i = int(np.argmax(c_a))
    assert 0 < i < len(c_a) - 1, "the lag is outside the searched span"
    off = 0.5 * (c_a[i - 1] - c_a[i + 1]) / (c_a[i - 1] - 2 * c_a[i] + c_a[i + 1])
    return 1e3 * float(shifts[i] + off * step_s)


def rms_and_lag(run: dict[str, np.ndarray], est: str, t0_s: float = 2.0) -> tuple[list[float], list[float]]:
    t = run["t"]
    m = (t >= t0_s) & np.isfinite(run[f"{est}_x"])
    out_rms, out_lag = [], []
    for axis in ("x", "y"):
        e, tr = run[f"{est}_{axis}"][m], run[f"v{axis}"][m]
        out_rms.append(float(np.sqrt(np.mean((e - tr) ** 2))))
        out_lag.append(lag_ms(e, t[m], t, run[f"v{axis}"]))
    return out_rms, out_lag


def kf_config(base, **companion):
    """The filter flown, on a vehicle whose accelerometer has a MEMS IMU's white noise (0.030 m/s^2 a
    sample: ``[imu] accel_noise``, off in configs/paper.toml's noise-free simulation)."""
    return replace_section(replace_section(base, "companion", velocity_estimator="kf", **companion), "imu",
                           accel_noise=True)


def _aged(base, age_s: float):
    cfg = with_effects(base, flow_delay=FlowDelay(age_s)) if age_s > 0 else base
    return replace_section(cfg, "companion", flow_sample_age_s=age_s)


GUST = {"force": lambda t: (-4.0, -4.0) if t >= 8.0 else (0.0, 0.0)}  # the paper's 4 N gust (Fig. 17), at 8 s
WIND = WindForce(-2.0, 1.5, 0.0, 1e9)  # a steady wind: 2 N from ahead, 1.5 N from the left, all flight
TRIM = {"trim_rad": math.radians(2.0)}  # the companion is told roll and pitch 2 deg off
HOVER = {"setpoint": lambda _t: (0.0, 0.0)}  # the paper's setpoint: the gust's response is all the motion


def _conditions(paper_cfg) -> dict[str, tuple[Any, dict]]:
    base = kf_config(paper_cfg)

    def alt(cfg, m):
        return replace_section(cfg, "world", altitude_m=m)

    return {
        "nominal": (base, {}),
        "gust": (base, GUST),
        "steady wind": (with_effects(base, wind_force=WIND), {}),
        "trim 2 deg": (base, TRIM),
        "drag": (with_effects(base, linear_drag=LinearDrag(0.5)), {}),
        "altitude 0.5 m": (alt(base, 0.5), {}),
        "altitude 3 m": (alt(base, 3.0), {}),
        "flow 10 ms old": (_aged(base, 0.010), {}),
        "flow 20 ms old": (_aged(base, 0.020), {}),
        "gust at 0.5 m, flow 20 ms old": (_aged(alt(base, 0.5), 0.020), GUST),
        "gust, flow 20 ms old": (_aged(base, 0.020), GUST),
        "wind, drag, trim at 3 m, flow 20 ms old": (with_effects(_aged(alt(base, 3.0), 0.020), wind_force=WIND,
                                                                linear_drag=LinearDrag(0.5)), TRIM),
        "everything at 0.5 m, flow 20 ms old": (with_effects(_aged(alt(base, 0.5), 0.020), wind_force=WIND,
                                                            linear_drag=LinearDrag(0.5)), GUST | TRIM),
        "gust at 3 m": (alt(base, 3.0), GUST),
        "everything at 1 m, flow 20 ms old": (with_effects(_aged(base, 0.020), wind_force=WIND,
                                                          linear_drag=LinearDrag(0.5)), GUST | TRIM),
        **{f"hover, gust at {m:g} m": (alt(base, m), GUST | HOVER) for m in (0.5, 1.0, 2.0, 3.0)},
    }


CONDITIONS = ("nominal", "gust", "steady wind", "trim 2 deg", "drag", "altitude 0.5 m", "altitude 3 m",
              "flow 10 ms old", "flow 20 ms old", "gust at 0.5 m, flow 20 ms old", "gust, flow 20 ms old",
              "wind, drag, trim at 3 m, flow 20 ms old", "everything at 0.5 m, flow 20 ms old", "gust at 3 m",
              "everything at 1 m, flow 20 ms old")


def _check(condition: str, paper_cfg, lag_bound_ms: float) -> None:
    cfg, kw = _conditions(paper_cfg)[condition]
    run = fly_core(cfg, **kw)
    assert not run["hold"].any()
    (kf_rms, kf_lag), (eq_rms, eq_lag) = rms_and_lag(run, "est"), rms_and_lag(run, "eq15")
    for axis in (0, 1):
        assert kf_rms[axis] <= eq_rms[axis] / 2.5, (condition, kf_rms, eq_rms)
        assert abs(kf_lag[axis]) <= lag_bound_ms, (condition, kf_lag)
        assert eq_lag[axis] > 9.0  # eq. 15 is late by half a frame and more (so the comparison means something)
    # the variance it publishes bounds its error (the quantization errors telescope: smaller than white)
    m = run["t"] >= 2.0
    for axis in ("x", "y"):
        nees = np.mean((run[f"est_{axis}"][m] - run[f"v{axis}"][m]) ** 2 / run[f"var_{axis}"][m])
        assert 0.0 < nees < 1.5, (condition, axis, nees)


@pytest.mark.parametrize("condition", CONDITIONS)
def test_kalman_filter_is_never_worse_than_eq15_and_never_late(paper_cfg, condition):
    _check(condition, paper_cfg, LAG_BOUND_MS)


#: at 2 m and 3 m the first count after the gust comes 4 frames late (the hover has left the scene
#: angle exactly on a count's edge and the gust moves it away from it: a whole count to travel, 4.7 mm
#: at 3 m, 73 ms at 1.74 m/s^2): an estimate exact from that frame on is already 4.5 ms late
#: (``test_the_hover_corner_is_beyond_what_the_counts_tell``); the accelerometer shows the gust at once
HOVER_CONDITIONS = ("hover, gust at 0.5 m", "hover, gust at 1 m", "hover, gust at 2 m", "hover, gust at 3 m")


@pytest.mark.parametrize("condition", HOVER_CONDITIONS)
def test_the_paper_gust_in_a_hover_is_never_late(paper_cfg, condition):
    """The paper's gust (4 N on each axis at 8 s) with the paper's setpoint 0: the response to the
    gust is the only motion there is to measure a lag on, and the scene moves less than a count a
    frame before it. Held to the issue's 3 ms like every condition above. At 2 m and 3 m the counts
    alone cannot meet it (+3.6 and +8.7 ms without the accelerometer, the test below says why); the
    accelerometer, the prediction's input, shows the force in the frame it starts."""
    _check(condition, paper_cfg, LAG_BOUND_MS)


@pytest.mark.parametrize("altitude_m", [2.0, 3.0])
def test_without_the_accelerometer_the_hover_is_what_it_was(paper_cfg, altitude_m):
    """A vehicle without an accelerometer (none fed, or the (0, 0, -1 g) placeholder every frame,
    or a configuration that does not use it): the filter is the one before the accelerometer, bit
    for bit, and the hover at 2 m and 3 m as late as the counts make it."""
    cfg, kw = _conditions(paper_cfg)[f"hover, gust at {altitude_m:g} m"]
    none = fly_core(cfg, accelerometer=False, **kw)
    unused = fly_core(replace_section(cfg, "companion", use_accelerometer=False), **kw)
    quiet = fly_core(replace_section(cfg, "imu", accelerometer=False), **kw)  # RAW_IMU's placeholder
    for run in (unused, quiet):
        for key in ("est_x", "est_y", "var_x", "var_y", "vx", "vy"):
            assert np.array_equal(run[key], none[key])
    _, lag = rms_and_lag(none, "est")
    assert lag == pytest.approx([{2.0: 3.58, 3.0: 8.71}[altitude_m]] * 2, abs=0.01)  # docs/estimator.md before it


@pytest.mark.parametrize("altitude_m, lag_ms_at_least", [(2.0, 4.4), (3.0, 4.4)])
def test_the_hover_corner_is_beyond_what_the_counts_tell(paper_cfg, altitude_m, lag_ms_at_least):
    """Why the hovers at 2 m and 3 m are late without the accelerometer: before the gust the vehicle
    is still and the scene
    angle sits on a count's edge; the gust moves it away, so the first count comes only once it has
    moved a whole count (4 frames later at 2 m and 3 m). An estimate equal to the truth from that
    frame on and unchanged (0) before it is already more than 3 ms late by the same measure."""
    cfg, kw = _conditions(paper_cfg)[f"hover, gust at {altitude_m:g} m"]
    run = fly_core(cfg, accelerometer=False, **kw)  # the counts alone
    t = run["t"]
    assert not run["vx"][(t >= 2.0) & (t <= 8.0)].any()  # still before the gust
    first = t[np.argmax((t > 8.0) & (run["eq15_x"] != 0.0))]
    assert first == pytest.approx(8.08)
    oracle = np.where((t > 8.0) & (t < first), 0.0, run["vx"])
    m = t >= 2.0
    assert lag_ms(oracle[m], t[m], t, run["vx"]) > lag_ms_at_least


@pytest.mark.parametrize("altitude_m, setpoint", [(3.0, "slow"), (3.0, "sines"), (2.0, "slow")])
def test_no_step_is_taken_in_two_minutes_of_slow_motion(paper_cfg, altitude_m, setpoint):
    """At 2-3 m a count is 0.16-0.24 m/s of eq. 15 and the tests' setpoints (and a fifth of them,
    0.1 and 0.08 m/s) move the scene by less than a count a frame much of the time: consecutive
    rounding errors are then not independent. Read as independent they made the filter take 3-6
    steps in two minutes at 3 m where there are none; read as the running sum's one bounded error,
    none. (The counts' own reading, without the accelerometer; with it the gusts are in the input
    and the steps the filter takes are its disturbance's start-up, docs/estimator.md.)"""
    cfg = replace_section(kf_config(paper_cfg), "world", altitude_m=altitude_m)
    sp = excite if setpoint == "sines" else (lambda t: tuple(0.2 * v for v in excite(t)))
    run = fly_core(cfg, duration_s=120.0, setpoint=sp, accelerometer=False)
    assert run["steps"][-1] == 0
    m = run["t"] >= 2.0
    assert np.sqrt(np.mean((run["est_x"][m] - run["vx"][m]) ** 2)) < 0.1 * np.sqrt(
        np.mean((run["eq15_x"][m] - run["vx"][m]) ** 2))


def test_the_paper_scenarios_still_hold_on_the_kalman_filter(paper_cfg):
    """Fig. 16-19 with the companion flying the Kalman filter: the thresholds of
    tests/test_scenarios.py (configs/paper.toml itself keeps eq. 15 for the paper profile), in the
    paper's simulation, which has no sensor noise: the accelerometer's white noise off as the
    gyro's is (with it, 0.03 m/s^2 a sample, the slow motion of Fig. 19 jitters by a count: a +1
    among its 0 and -1, the first count 0.3 s after the command on x)."""
    cfg = replace_section(kf_config(paper_cfg), "imu", accel_noise=False)
    figs = {name: figures(run_named(name, cfg), cfg) for name in ("step", "gust", "slow")}
    for axis in ("x", "y"):
        f = figs["step"][axis]
        assert f["rise_time_10_90_s"] < 1.0
        assert f["extreme_command_deg"] == pytest.approx(-20.0 if axis == "x" else 20.0, abs=1e-6)
        assert f["final_velocity_m_s"] == pytest.approx(2.0, rel=0.02)
        g = figs["gust"][axis]
        assert -2.9 <= g["displacement_m"] <= -2.7 and g["final_speed_m_s"] < 0.01
        assert abs(g["held_angle_deg"]) == pytest.approx(10.0, abs=0.5)
        s = figs["slow"][axis]
        assert 0.6 <= s["first_count_after_command_s"] <= 0.9 and set(s["count_values"]) == {0, -1}
        assert 6.0 <= s["pulses_per_s"] <= 7.5 and s["final_velocity_cm_s"] == pytest.approx(1.0, rel=0.10)


def test_auto_is_eq15_for_the_paper_profile_and_the_filter_for_ardupilot_and_px4(paper_cfg):
    opts = EstimatorOptions.from_config(paper_cfg)
    assert paper_cfg.companion.velocity_estimator == "auto"
    assert opts.resolved_estimator(Profile.PAPER) is VelocityEstimator.EQ15
    assert opts.resolved_estimator(Profile.ARDUPILOT) is VelocityEstimator.KF
    assert opts.resolved_estimator(Profile.PX4) is VelocityEstimator.KF
    sitl = load_config(REPO / "configs" / "ardupilot_sitl.toml")
    assert EstimatorOptions.from_config(sitl).resolved_estimator(Profile.ARDUPILOT) is VelocityEstimator.KF
    core = CompanionCore(paper_cfg)  # a live core is told its profile once detected
    assert core.estimator is VelocityEstimator.EQ15
    core.set_profile(Profile.PX4)
    assert core.estimator is VelocityEstimator.KF
    # eq. 15 alone stays one key away, and the explicit forms before issue 19 keep their meaning
    assert EstimatorOptions.from_config(replace_section(sitl, "companion", velocity_estimator="eq15")) \
        .resolved_estimator(Profile.ARDUPILOT) is VelocityEstimator.EQ15
    assert EstimatorOptions().resolved_estimator(Profile.ARDUPILOT) is VelocityEstimator.EQ15


def _companion_table(cfg, **changes) -> dict:
    data = read_toml(cfg.source, "config file")
    data["companion"] = {**data["companion"], **changes}
    return data


def test_config_rejects_unknown_estimators_in_one_line(paper_cfg):
    with pytest.raises(ConfigError) as e:
        config_from_dict(_companion_table(paper_cfg, velocity_estimator="ekf"), source="x.toml")
    assert str(e.value) == ("x.toml: companion.velocity_estimator must be auto, eq15, tilt or kf, got 'ekf'")
    with pytest.raises(ConfigError, match="velocity_filter was replaced by velocity_estimator"):
        config_from_dict(_companion_table(paper_cfg, velocity_filter="tilt"), source="x.toml")
    with pytest.raises(ConfigError, match=r"flow_sample_age_s must be in \[0, 0.2\] s"):
        config_from_dict(_companion_table(paper_cfg, flow_sample_age_s=-0.01), source="x.toml")
    for name in ("auto", "eq15", "tilt", "kf"):
        assert config_from_dict(_companion_table(paper_cfg, velocity_estimator=name)).companion.velocity_estimator \
            == name


def test_fastsim_refuses_an_estimator_it_does_not_model(paper_cfg):
    from simvehicle.engines.fastsim import simulate_batch

    simulate_batch(paper_cfg, 1, duration_s=0.04, columns=("vx_m_s",))  # auto: eq. 15, modelled
    sitl = load_config(REPO / "configs" / "ardupilot_sitl.toml")  # auto, and an age only the filter reads
    simulate_batch(sitl, 1, duration_s=0.04, columns=("vx_m_s",))
    for name in ("kf", "tilt"):
        with pytest.raises(ConfigError, match=f"does not model companion.velocity_estimator = '{name}'"):
            simulate_batch(replace_section(paper_cfg, "companion", velocity_estimator=name), 1, duration_s=0.04)


# ---------------------------------------------------------------------------------------------
# The filter alone


def _settings(age_s: float = 0.0) -> KalmanSettings:
    return KalmanSettings(gravity_m_s2=G, nominal_frame_s=0.02, flow_sample_age_s=age_s, flow_noise_rad_s=0.01,
                          range_noise_m=0.0, accel_psd=1e-6, disturbance_psd=1e-3, drag_psd=1e-6)


@pytest.mark.parametrize("age_s", [0.0, 0.007, 0.02])
def test_the_measurement_is_fused_at_its_own_time_and_carried_to_now(age_s):
    """Noise-free, a constant tilt (constant acceleration g tan(pitch)) and eq. 15 exactly the
    velocity at the flow sample's time (half the frame plus the age before the message): the
    estimate handed out is the velocity at the message's time, not the sample's."""
    kf = VelocityKalman(_settings(age_s))
    pitch = math.radians(-3.0)
    a = -G * math.tan(pitch)  # +0.51 m/s^2 forward
    T = 0.02
    for k in range(200):
        t = k * T
        kf.on_attitude(t, 0.0, pitch, 0.0, 0.0)
        t_sample = t - T / 2 - age_s
        vx, vy, var_x, var_y = kf.update(t, T, 0.1 + a * t_sample, -0.2, 1.0)
    assert vx == pytest.approx(0.1 + a * t, abs=1e-9) and vy == pytest.approx(-0.2, abs=1e-9)
    assert 0.0 < var_x < (1.0 * 0.01) ** 2 and 0.0 < var_y < (1.0 * 0.01) ** 2  # below one measurement's


def test_the_disturbance_state_takes_a_steady_force_and_drag_is_learnt():
    """The truth accelerates by g tan(pitch) - 0.3 m/s^2 (a steady force) - 0.25 v (drag); the
    filter is told only the pitch: its disturbance and drag states take up the rest and its
    velocity has no bias."""
    kf = VelocityKalman(_settings())
    T = 0.02
    v, errs = 0.0, []
    for k in range(3000):
        t = k * T
        pitch = math.radians(-4.0 * math.sin(2 * math.pi * 0.2 * t))
        kf.on_attitude(t, 0.0, pitch, 0.0, 0.0)
        v += (-G * math.tan(pitch) - 0.3 - 0.25 * v) * T
        vx, _, _, _ = kf.update(t, 0.0, v, 0.0, 1.0)
        errs.append(vx - v)
    ax = kf.axes[0]
    assert ax.c == pytest.approx(0.25, abs=0.03) and ax.b == pytest.approx(-0.3, abs=0.03)
    assert abs(np.mean(errs[-500:])) < 2e-3


Q = 0.0015706806282722514  # Table VI's rad per count


def _counts_flight(range_m: float, pitch_deg: float, duration_s: float, *, quantization: bool = True,
                   step_at_s: float = math.inf, step_m_s2: float = 0.0, accel_noise_m_s2: float | None = None,
                   accel: Any = None) -> dict[str, np.ndarray]:
    """The filter alone on eq. 15 of a counting sensor (eq. 9-11, no rotation in the flow): the
    truth accelerates by -g tan(pitch) (pitch a 0.3 Hz sinusoid of ``pitch_deg``), plus
    ``step_m_s2`` from ``step_at_s``, integrated by 1 ms; the counts are the floor of the
    accumulated scene angle at each 20 ms frame. ``quantization``: the filter knows the counts'
    quantization (``quantization_rad``); else the white model of the same per-frame variance
    Q^2 / 6. ``accel_noise_m_s2``: an accelerometer reports each frame the mean over it of the
    force's share (the step), with white noise of this sigma (seeded), as the filter's input;
    ``accel(t, fx)``: instead of feeding it, what to feed (for the tests of an absent one). Per
    frame: time, truth, estimate, variance, normalised innovation, steps taken, disturbance,
    probability of a step."""
    T = 0.02
    common = dict(gravity_m_s2=G, nominal_frame_s=T, flow_sample_age_s=0.0, range_noise_m=0.0,
                  accel_psd=(G * math.radians(0.1)) ** 2 * T, disturbance_psd=0.1 ** 2 / 10, drag_psd=0.003 ** 2)
    s = (KalmanSettings(flow_noise_rad_s=0.0, quantization_rad=Q / math.sqrt(12.0), **common) if quantization
         else KalmanSettings(flow_noise_rad_s=Q / (T * math.sqrt(6.0)), **common))
    if accel_noise_m_s2 is not None:
        s = dataclasses.replace(s, accel_noise_m_s2=accel_noise_m_s2)
    kf = VelocityKalman(s)
    amp, w = math.radians(pitch_deg), 2 * math.pi * 0.3
    v = x = 0.0
    counts = 0
    rows = []
    force_sum = 0.0  # the step's share over the frame just integrated (m/s^2 x 1 ms steps)
    noise = np.random.default_rng(7)
    for k in range(int(round(duration_s / T))):
        t = k * T
        kf.on_attitude(t, 0.0, amp * math.sin(w * t), 0.0, amp * w * math.cos(w * t))
        if accel is not None:
            accel(kf, t)
        elif accel_noise_m_s2 is not None and k > 0:
            kf.on_accel(t, force_sum / 20.0 + accel_noise_m_s2 * float(noise.normal()), 0.0)
        force_sum = 0.0
        now = math.floor(-x / range_m / Q)  # eq. 8 and 10: phi = -x / A, X = floor(phi / Q)
        if k > 0:
            vx, _, var, _ = kf.update(t, T, -(now - counts) * Q * range_m / T, 0.0, range_m)
            ax = kf.axes[0]
            rows.append((t, v, vx, var, ax.nu / math.sqrt(ax.nu_var), ax.steps_found, ax.b, ax.p_step,
                         -x / range_m - Q * (now + 0.5), ax.e, math.sqrt(ax.p33)))
        counts = now
        for j in range(20):
            tj = t + 0.001 * j
            a = -G * math.tan(amp * math.sin(w * tj)) + (step_m_s2 if tj >= step_at_s else 0.0)
            force_sum += step_m_s2 if tj >= step_at_s else 0.0
            x += v * 0.001 + 0.5 * a * 1e-6
            v += a * 0.001
    a_ = np.array(rows)
    names = ("t", "v", "est", "var", "nu", "steps", "b", "p_step", "phase", "e", "e_sd")
    return {name: a_[:, i] for i, name in enumerate(names)}


@pytest.mark.parametrize("range_m, pitch_deg", [(1.0, 3.0), (3.0, 6.0)])
def test_the_running_rounding_error_is_tracked(range_m, pitch_deg):
    """A frame's count error is the difference of two rounding errors of the running sum (eq. 10),
    so treated as white noise the innovations are correlated -1/2 from one frame to the next. The
    filter carries the running sum's rounding error as one bounded state: against the truth's
    (the accumulated scene angle less the centre of its count) its error stays within its
    standard deviation (mean square below 1, never beyond 3 sigma) while that deviation is about a
    tenth of a count (the white model's is a third); the velocity's error is within its published
    variance, the bound's innovations are uncorrelated from frame to frame, and no step is found
    in two minutes of a flight that has none."""
    run = _counts_flight(range_m, pitch_deg, 120.0)
    z = ((run["phase"] - run["e"]) / run["e_sd"])[100:]
    assert np.mean(z ** 2) < 1.0 and np.abs(z).max() < 3.0
    assert np.median(run["e_sd"]) < 0.15 * Q
    assert np.mean((run["est"] - run["v"])[100:] ** 2 / run["var"][100:]) < 1.0
    nu = run["nu"][100:]
    assert abs(np.corrcoef(nu[:-1], nu[1:])[0, 1]) < 0.2
    assert run["steps"][-1] == 0
    white = _counts_flight(range_m, pitch_deg, 120.0, quantization=False)["nu"][100:]
    assert np.corrcoef(white[:-1], white[1:])[0, 1] < -0.4


def test_boxed_moments_are_those_of_the_distribution():
    """The bound's probability, mean and variance of a uniform plus Gaussian noise restricted to an
    interval, against the density integrated numerically (1e6 points), in the general case, a
    tail, and the two limits (uniform alone, Gaussian alone); a uniform within the bound is
    unchanged by it."""
    for mu, h, sd, lo, hi in [(0.0, 0.5, 0.3, -0.5, 0.5), (0.3, 0.5, 0.1, -0.5, 0.5), (-0.9, 0.5, 0.2, -0.5, 0.5),
                              (-2.0, 0.4, 0.5, -0.5, 0.5), (0.1, 0.5, 1e-6, -0.5, 0.5), (0.2, 1e-6, 0.3, -0.5, 0.5)]:
        x = np.linspace(lo, hi, 1_000_001)
        s_ = max(sd, 1e-300)
        dens = (ndtr((x - mu + h) / s_) - ndtr((x - mu - h) / s_)) / (2 * h)
        mass = np.trapezoid(dens, x)
        mean = np.trapezoid(x * dens, x) / mass
        var = np.trapezoid((x - mean) ** 2 * dens, x) / mass
        got = boxed_moments(mu, h, sd, lo, hi)
        assert got[0] == pytest.approx(mass, rel=1e-5, abs=1e-9)
        assert got[1] == pytest.approx(mean, abs=1e-5 * (hi - lo))
        assert got[2] == pytest.approx(var + (sd * sd if sd < 1e-4 * h else 0.0), rel=1e-4)
    assert boxed_moments(0.1, 0.2, 0.0, -0.5, 0.5) == (1.0, 0.1, pytest.approx(0.4 ** 2 / 12))


@pytest.mark.parametrize("range_m, pitch_deg, within_s, err_m_s", [(1.0, 3.0, 0.08, 0.01), (3.0, 6.0, 0.12, 0.02)])
def test_a_step_in_the_disturbance_is_found_taken_and_announced(range_m, pitch_deg, within_s, err_m_s):
    """The paper's gust as a step of -1.74 m/s^2 (4 N on 2.3 kg) at 10 s: taken into the state
    within 4 frames at 1 m and 6 at 3 m (the flow's count is three times coarser there), the
    disturbance then within 0.1 m/s^2 and the estimate within 0.01 (0.02) m/s; none before."""
    run = _counts_flight(range_m, pitch_deg, 12.0, step_at_s=10.0, step_m_s2=-1.74)
    t = run["t"]
    first = t[np.argmax(run["steps"] > 0)]
    assert 10.0 < first <= 10.0 + within_s
    after = t >= 10.3
    assert run["b"][np.searchsorted(t, 10.3)] == pytest.approx(-1.74, abs=0.1)
    assert np.abs(run["est"][after] - run["v"][after]).max() < err_m_s


@pytest.mark.xfail(strict=True, reason=(
    "with the counts read exactly the step is not yet shown at 10.04 s: probability 0.04 (0.1 asserted), "
    "standard deviation 2.6 times the one before (5), error 6.9 sigma (3); the first count after the step "
    "(10.02 s) is one the scene's phase near a count's edge explains 1 time in 25 without a step, and the "
    "next one is decisive (10.06 s, taken)"))
def test_the_variance_rises_with_a_step_before_it_is_taken():
    """Between the step and the frame that takes it the published variance holds the candidate
    steps: it grows several times over, so the error of those frames stays within a few sigma."""
    run = _counts_flight(1.0, 3.0, 12.0, step_at_s=10.0, step_m_s2=-1.74)
    t = run["t"]
    before = np.sqrt(run["var"][(t > 9.0) & (t < 10.0)]).max()
    k = np.searchsorted(t, 10.04)
    assert run["steps"][k] == 0 and run["p_step"][k] > 0.1
    assert np.sqrt(run["var"][k]) > 5 * before
    assert abs(run["est"][k] - run["v"][k]) < 3 * np.sqrt(run["var"][k])


@pytest.mark.parametrize("range_m, pitch_deg", [(1.0, 3.0), (3.0, 0.0), (3.0, 6.0)])
def test_the_accelerometer_shows_the_step_as_it_comes(range_m, pitch_deg):
    """The same step (the paper's gust, -1.74 m/s^2 at 10 s) with an accelerometer reporting the
    force's share each frame (its mean over the frame, white noise 0.03 m/s^2 a sample, the
    config's): it is the prediction's input, so the estimate follows the step from the frame it
    starts, within 0.02 m/s of the truth from the step on (0.005-0.013 as measured) and within a
    fifth of the counts alone's worst error (0.07-0.16 m/s, until they take the step 4-6 frames
    later), none is taken, and the velocity's error is within its published variance.
    In a hover at 3 m (pitch 0) the counts alone show nothing for 4 frames after the step."""
    run = _counts_flight(range_m, pitch_deg, 12.0, step_at_s=10.0, step_m_s2=-1.74, accel_noise_m_s2=0.03)
    t = run["t"]
    after = t >= 10.0
    assert np.abs(run["est"][after] - run["v"][after]).max() < 0.02
    assert run["steps"][-1] == 0
    m = t >= 2.0
    assert np.mean((run["est"][m] - run["v"][m]) ** 2 / run["var"][m]) < 1.0
    counts_alone = _counts_flight(range_m, pitch_deg, 12.0, step_at_s=10.0, step_m_s2=-1.74)
    assert np.abs(run["est"][after] - run["v"][after]).max() < 0.2 * np.abs(
        counts_alone["est"][after] - counts_alone["v"][after]).max()


def test_an_accelerometer_that_is_not_there_changes_nothing():
    """The placeholder (0, 0) every frame, clipped or missing samples (NaN, ``profiles.accel_m_s2``
    of an int16 field at 32767), or the settings' ``use_accelerometer`` false with a real one: the
    filter is the one without an accelerometer, bit for bit; a placeholder before the first real
    reading is ignored too (from then on every reading counts, 0 included)."""
    none = _counts_flight(1.0, 3.0, 12.0, step_at_s=10.0, step_m_s2=-1.74)
    clipped = accel_m_s2("RAW_IMU", 32767, 0, -1000)[0]
    feeds = {"placeholder": lambda kf, t: kf.on_accel(t, 0.0, 0.0),
             "clipped": lambda kf, t: kf.on_accel(t, clipped, 0.5),
             "not finite": lambda kf, t: kf.on_accel(t, math.nan, math.nan)}
    for name, feed in feeds.items():
        run = _counts_flight(1.0, 3.0, 12.0, step_at_s=10.0, step_m_s2=-1.74, accel=feed)
        for key in ("est", "var", "b"):
            assert np.array_equal(run[key], none[key]), name
    assert math.isnan(clipped)
    off = _counts_flight(1.0, 3.0, 12.0, step_at_s=10.0, step_m_s2=-1.74, accel=lambda kf, t: (
        object.__setattr__(kf, "s", dataclasses.replace(kf.s, use_accelerometer=False)), kf.on_accel(t, -1.0, 0.3)))
    assert np.array_equal(off["est"], none["est"])
    kf = VelocityKalman(_settings())
    kf.on_accel(0.0, 0.0, 0.0)
    assert not kf.accel and not kf.accel_seen
    kf.on_accel(0.02, 0.0, 0.01)
    kf.on_accel(0.04, 0.0, 0.0)
    assert kf.accel_seen and [a[2] for a in kf.accel] == [0.01, 0.0]


def test_profiles_reads_the_accelerometer_of_each_gyro_message():
    """milli-g of standard gravity in RAW_IMU and SCALED_IMU (int16: a field at 32767 has clipped,
    all three unknown), m/s^2 in HIGHRES_IMU; scalars as arrays."""
    g0 = 9.80665
    assert accel_m_s2("RAW_IMU", 100, -200, -1000) == pytest.approx((0.1 * g0, -0.2 * g0, -g0), rel=1e-15)
    assert accel_m_s2("SCALED_IMU", 1, 0, -1000)[0] == pytest.approx(1e-3 * g0, rel=1e-15)
    assert accel_m_s2("HIGHRES_IMU", 0.5, -0.25, -9.8) == (0.5, -0.25, -9.8)
    assert all(math.isnan(v) for v in accel_m_s2("RAW_IMU", 0, -32767, -1000))
    assert not any(math.isnan(v) for v in accel_m_s2("HIGHRES_IMU", 40000.0, 0.0, 0.0))
    x = np.array([100, 32767, -5])
    cols = accel_m_s2("RAW_IMU", x, np.zeros(3), np.full(3, -1000))
    for i in range(3):
        assert np.array_equal(np.array([c[i] for c in cols]),
                              np.array(accel_m_s2("RAW_IMU", int(x[i]), 0, -1000)), equal_nan=True)


def test_without_a_fresh_attitude_eq15_passes_through_and_a_reboot_restarts():
    kf = VelocityKalman(_settings())
    assert kf.update(1.0, 0.02, 0.3, -0.1, 1.0)[:2] == (0.3, -0.1)  # no attitude at all
    kf.on_attitude(1.0, 0.0, 0.0, 0.0, 0.0)
    assert kf.update(1.0 + MAX_ATTITUDE_AGE_S + 0.01, 0.02, 0.4, 0.0, 1.0)[:2] == (0.4, 0.0)  # stale
    for k in range(50):
        kf.on_attitude(2.0 + 0.02 * k, 0.0, 0.0, 0.0, 0.0)
        kf.update(2.0 + 0.02 * k, 0.02, 0.5, 0.0, 1.0)
    assert kf.horizon_s > 2.9
    kf.on_attitude(0.1, 0.0, 0.0, 0.0, 0.0)  # the vehicle rebooted: its clock restarts
    vx, _, _, _ = kf.update(0.1, 0.02, -0.2, 0.0, 1.0)
    assert vx == pytest.approx(-0.2) and kf.horizon_s < 0.1


def test_gyro_window_mean_integrates_the_samples_exactly():
    samples = [(k * 0.01, 0.1 * k, -0.2 * k) for k in range(10)]  # a ramp at 10 rad/s^2 and -20
    mx, my = gyro_window_mean(samples, 0.023, 0.057, 0.015)
    assert mx == pytest.approx(0.1 * 4.0, abs=1e-12) and my == pytest.approx(-0.2 * 4.0, abs=1e-12)
    assert gyro_window_mean(samples, 0.5, 0.52, 0.015) is None  # no sample near the window
    assert gyro_window_mean([(0.0, math.nan, 0.0)], -0.01, 0.0, 0.015) is None


def test_options_can_carry_their_own_kalman_settings(paper_cfg):
    ks = dataclasses.replace(kalman_settings(paper_cfg, Profile.ARDUPILOT), flow_sample_age_s=0.01)
    core = CompanionCore(paper_cfg, Profile.ARDUPILOT, EstimatorOptions(estimator=VelocityEstimator.KF, kalman=ks))
    assert core.kalman.s.flow_sample_age_s == 0.01


# ---------------------------------------------------------------------------------------------
# Its variance, published


def test_vision_speed_estimate_carries_the_variance_when_there_is_one():
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=191)
    m = mav.MAVLink(None).decode(bytearray(outbound.vision_speed(enc, 5, 0.1, 0.2, 1e-4, 2e-4).pack(enc)))
    cov = list(m.covariance)
    assert cov[0] == pytest.approx(1e-4) and cov[4] == pytest.approx(2e-4)
    assert cov[1:4] == [0.0, 0.0, 0.0] and cov[5:8] == [0.0, 0.0, 0.0] and math.isnan(cov[8])
    m = mav.MAVLink(None).decode(bytearray(outbound.vision_speed(enc, 5, 0.1, 0.2).pack(enc)))
    assert all(math.isnan(c) for c in m.covariance)  # eq. 15: unknown (NaN first)


@pytest.mark.parametrize("estimator", ["kf", "eq15"])
def test_the_live_companion_publishes_the_variance(paper_cfg, estimator):
    cfg = replace_section(paper_cfg, "companion", velocity_estimator=estimator)
    fl = FakeLink(cfg)
    live = LiveCompanion(cfg, Profile.PAPER, fl, clock=lambda: fl.clock, wall=lambda: 1.7e9 + fl.clock,
                         out=lambda _s: None, quiet=True)
    live.router.vehicle_sysid, live.vehicle_compid = 1, 1
    fl.live = live
    fl.send_frame()
    fl.frames_left = 100
    live.run()
    vse = [m for _t, m in fl.messages("VISION_SPEED_ESTIMATE")]
    assert len(vse) > 90
    cov = np.array([list(m.covariance) for m in vse])
    if estimator == "kf":
        assert np.isfinite(cov[:, [0, 4]]).all() and (cov[:, [0, 4]] > 0).all() and np.isnan(cov[:, 8]).all()
        assert (cov[-1, [0, 4]] < cov[0, [0, 4]]).all()  # it shrinks as measurements come in
    else:
        assert np.isnan(cov[:, 0]).all()


# ---------------------------------------------------------------------------------------------
# ArduCopter SITL: flights E1 and C0 against SIM_STATE (benchmarks/bench_estimator.py in full)



@pytest.mark.parametrize("flight", ["e1", "c0"])
def test_sitl_flights_at_or_below_ekf3_and_not_late(flight):
    """RMS per axis <= 0.017 m/s (EKF3's on E1) and |lag| <= 3 ms against SIM_STATE, as the
    benchmark measures them (truth at the ground station's record time of the frame's vehicle time,
    heading axes), for the default of configs/ardupilot_sitl.toml."""
    cfg = load_config(REPO / "configs" / "ardupilot_sitl.toml")
    comp = load_recording(SITL / f"flight_{flight}_companion.tlog.gz")
    gcs = load_recording(SITL / f"flight_{flight}_gcs.tlog.gz")
    res = replay(comp, cfg, Profile.ARDUPILOT)
    ok = (res["engaged"] == 1) & np.isfinite(res["vx_m_s"])
    assert ok.sum() == 7500 and np.isfinite(res["vx_var_m2_s2"][ok]).all()
    ss, of = gcs.table("SIM_STATE"), gcs.table("OPTICAL_FLOW")
    t = np.interp(np.round(res["frame_time_s"][ok] * 1e3), np.asarray(of["time_usec"], float), of.t_s)
    yaw = np.unwrap(np.asarray(ss["yaw"], float))
    c, s = np.cos(yaw), np.sin(yaw)
    truth = (c * ss["vn"] + s * ss["ve"], -s * ss["vn"] + c * ss["ve"])
    for axis, col in enumerate(("vx_m_s", "vy_m_s")):
        est = res[col][ok]
        err = est - np.interp(t, ss.t_s, truth[axis])
        assert np.sqrt(np.mean(err ** 2)) <= 0.017
        assert abs(lag_ms(est, t, ss.t_s, truth[axis], span_s=0.03)) <= LAG_BOUND_MS
        # the variance it publishes is that of its error, within a factor 2
        assert 0.5 < np.mean(err ** 2 / res[col.replace("_m_s", "_var_m2_s2")][ok]) < 2.0


def _placeholder_accelerometer(src: Path, dst: Path) -> Path:
    """``src`` (a .tlog, gzip or not) copied to ``dst`` with every RAW_IMU's accelerometer the (0, 0,
    -1000) mg placeholder, each packet re-encoded with its sender and sequence number."""
    plain = dst.with_suffix(".src.tlog")
    plain.write_bytes(gzip.decompress(src.read_bytes()) if src.suffix == ".gz" else src.read_bytes())
    conn = mavutil.mavlink_connection(str(plain), dialect="ardupilotmega")
    changed = 0
    with dst.open("wb") as out:
        while (msg := conn.recv_msg()) is not None:
            buf = bytes(msg.get_msgbuf())
            if msg.get_type() == "RAW_IMU":
                enc = mav.MAVLink(None, srcSystem=msg.get_srcSystem(), srcComponent=msg.get_srcComponent())
                enc.seq = msg.get_seq()
                buf = bytes(enc.raw_imu_encode(msg.time_usec, 0, 0, -1000, msg.xgyro, msg.ygyro, msg.zgyro, msg.xmag,
                                               msg.ymag, msg.zmag).pack(enc))
                changed += 1
            out.write(struct.pack(">Q", int(round(msg._timestamp * 1e6))) + buf)
    conn.close()
    assert changed > 1000
    return dst


def test_a_sitl_flight_without_its_accelerometer_replays_as_with_it_unused(tmp_path):
    """Flight E1's RAW_IMU carries ArduCopter's accelerometer. The recording with the placeholder in
    its place replays bit for bit as the recording itself with ``use_accelerometer = false``: the
    vehicle without an accelerometer and the filter told not to use one are the same filter (the one
    before the accelerometer; docs/estimator.md: the SITL replays without it equal those before it);
    with its accelerometer the estimate differs."""
    cfg = load_config(REPO / "configs" / "ardupilot_sitl.toml")
    src = SITL / "flight_e1_companion.tlog.gz"
    unused = replay(load_recording(src), replace_section(cfg, "companion", use_accelerometer=False), Profile.ARDUPILOT)
    none = replay(load_recording(_placeholder_accelerometer(src, tmp_path / "e1_no_accel.tlog")), cfg,
                  Profile.ARDUPILOT)
    used = replay(load_recording(src), cfg, Profile.ARDUPILOT)
    for col in ("vx_m_s", "vy_m_s", "vx_var_m2_s2", "vy_var_m2_s2", "roll_cmd_rad", "pitch_cmd_rad"):
        assert np.array_equal(unused[col], none[col], equal_nan=True), col
    ok = np.isfinite(used["vx_var_m2_s2"])
    assert ok.sum() > 7500 and not np.array_equal(used["vx_m_s"][ok], unused["vx_m_s"][ok])
