"""The independent flight generator (simvehicle/engines/flightgen.py) and the matrix scorer.

Signs and units per CONVENTIONS.md are checked against closed forms (a pure rotation's flow is the
rotation, a steady tilt gives v_dot = g tan, translation gives -v/A, a lever arm's flow, a first-order
gyro lag), the loss fraction against the one requested, the recordings' messages against the
contract, the closed loop against steady states that follow from eq. 15 and the PI, and the scorer
on synthetic reports. The small end-to-end matrix is ``slow``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from simvehicle.engines import flightgen as fg

ROOT = Path(__file__).resolve().parent.parent
KT = np.array([0.0, 1000.0])


def heights(h: float) -> np.ndarray:
    return np.array([h, h])


# ---------------------------------------------------------------------------------------------
# the physics against closed forms


def test_pure_rotation_gives_flow_equal_to_the_rotation() -> None:
    """No translation (g = 0, no force): phi_x = -(pitch - pitch0), phi_y = +(roll - roll0)."""
    s = np.zeros(fg.NS)
    fg.integrate(s, 0.0, 3.0, par=fg.make_params(g=0.0), kt=KT, kh=heights(1.2), command=(0.05, -0.08))
    assert abs(s[fg.TH] - 0.05) < 2e-3 and abs(s[fg.PH] + 0.08) < 3e-3  # the attitude loop settled
    assert s[fg.VX] == 0.0 and s[fg.VY] == 0.0
    assert s[fg.SX] == pytest.approx(-s[fg.TH], abs=1e-12)
    assert s[fg.SY] == pytest.approx(s[fg.PH], abs=1e-12)


def test_a_rotation_gain_scales_only_the_rotation() -> None:
    s = np.zeros(fg.NS)
    fg.integrate(s, 0.0, 2.0, par=fg.make_params(g=0.0, gain=1.1), kt=KT, kh=heights(1.0), command=(0.04, 0.03))
    assert s[fg.SX] == pytest.approx(-1.1 * s[fg.TH], abs=1e-12)
    assert s[fg.SY] == pytest.approx(1.1 * s[fg.PH], abs=1e-12)


def test_steady_tilt_gives_v_dot_g_tan() -> None:
    """Held at pitch th and roll ph: vx' = -g tan(th) + Fx/m, vy' = +g tan(ph) + Fy/m."""
    th, ph, g, m, fx, fy, t = 0.1, -0.07, 9.81, 2.0, 0.5, -0.3, 2.0
    s = np.zeros(fg.NS)
    s[fg.TH], s[fg.PH] = th, ph
    fg.integrate(s, 0.0, t, par=fg.make_params(g=g, m=m), kt=KT, kh=heights(1.0), command=(th, ph), force=(fx, fy))
    assert s[fg.VX] == pytest.approx((-g * math.tan(th) + fx / m) * t, rel=1e-9)
    assert s[fg.VY] == pytest.approx((g * math.tan(ph) + fy / m) * t, rel=1e-9)


def test_translation_gives_minus_v_over_height() -> None:
    vx, vy, h, t = 0.8, -0.5, 1.5, 2.0
    s = np.zeros(fg.NS)
    s[fg.VX], s[fg.VY] = vx, vy
    fg.integrate(s, 0.0, t, par=fg.make_params(), kt=KT, kh=heights(h))
    assert s[fg.SX] == pytest.approx(-vx * t / h, rel=1e-12)
    assert s[fg.SY] == pytest.approx(-vy * t / h, rel=1e-12)
    assert s[fg.PX] == pytest.approx(vx * t, rel=1e-12)


def test_drag_decays_the_velocity_exponentially() -> None:
    b, m, v0, t = 0.4, 2.0, 1.0, 1.5
    s = np.zeros(fg.NS)
    s[fg.VX] = v0
    fg.integrate(s, 0.0, t, par=fg.make_params(m=m, b=b), kt=KT, kh=heights(1.0))
    assert s[fg.VX] == pytest.approx(v0 * math.exp(-b / m * t), rel=1e-6)
    c = 0.3
    s = np.zeros(fg.NS)
    s[fg.VY] = -v0
    fg.integrate(s, 0.0, t, par=fg.make_params(m=m, c=c), kt=KT, kh=heights(1.0))
    assert s[fg.VY] == pytest.approx(-v0 / (1 + c / m * v0 * t), rel=1e-6)  # v' = -(c/m) v|v|


def test_lever_arm_flow_and_height() -> None:
    """A sensor rz below the CG moves at omega x r: a roll rate p adds -p rz to its y velocity, so
    phi_y' = p + p rz / D with D the sensor's own distance (h - rz when level)."""
    h, rz = 1.0, 0.1
    s = np.zeros(fg.NS)
    fg.integrate(s, 0.0, 3.0, par=fg.make_params(g=0.0, rz=rz), kt=KT, kh=heights(h), command=(0.0, 0.03))
    assert s[fg.SY] == pytest.approx(s[fg.PH] * (1 + rz / (h - rz)), rel=1e-3)
    s = np.zeros(fg.NS)
    fg.integrate(s, 0.0, 3.0, par=fg.make_params(g=0.0, rz=rz), kt=KT, kh=heights(h), command=(0.03, 0.0))
    assert s[fg.SX] == pytest.approx(-s[fg.TH] * (1 + rz / (h - rz)), rel=1e-3)
    # the sensor's height changes with tilt: nose up lifts a sensor ahead of the CG
    assert fg.sensor_distance(1.0, 0.0, 0.0, rz=0.1) == pytest.approx(0.9)
    th = 0.1
    assert fg.sensor_distance(1.0, th, 0.0, rx=0.2) == pytest.approx((1.0 + 0.2 * math.sin(th)) / math.cos(th))
    assert fg.sensor_distance(1.0, 0.0, 0.2) == pytest.approx(1.0 / math.cos(0.2))  # slant range


def test_gyro_lag_is_a_first_order_low_pass_of_the_rate() -> None:
    tau, dt = 0.03, 1e-4
    s = np.zeros(fg.NS)
    t = np.arange(1, 10001) * dt
    out = fg.integrate(s, 0.0, 1.0, par=fg.make_params(g=0.0, omega_p=8.0, tau=tau), kt=KT, kh=heights(1.0),
                       command=(0.1, 0.05), samples=t)
    y = np.zeros(2)
    prev = np.zeros(2)
    a = math.exp(-dt / tau)
    err = 0.0
    for row in out:
        rate = np.array([row[fg.PR], row[fg.QR]])
        # exact response to a rate linear over the step
        y = a * y + (1 - a) * rate - (rate - prev) * (tau / dt * (1 - a) - a) * 1.0
        prev = rate
        err = max(err, float(np.max(np.abs(y - row[[fg.GX, fg.GY]]))))
    assert err < 1e-5
    assert np.max(np.abs(out[:, fg.QR])) > 0.1  # there was something to lag


def test_command_switch_and_samples_land_exactly() -> None:
    """A command switching inside the step acts exactly from the switch time."""
    par = fg.make_params(g=0.0)
    a = np.zeros(fg.NS)
    fg.integrate(a, 0.0, 0.0123, par=par, kt=KT, kh=heights(1.0))
    fg.integrate(a, 0.0123, 0.5, par=par, kt=KT, kh=heights(1.0), command=(0.1, 0.0))
    b = np.zeros(fg.NS)
    fg.integrate(b, 0.0, 0.02, par=par, kt=KT, kh=heights(1.0), switch=(0.0123, 0.1, 0.0))
    fg.integrate(b, 0.02, 0.5, par=par, kt=KT, kh=heights(1.0), command=(0.1, 0.0))
    assert b[fg.TH] == pytest.approx(a[fg.TH], abs=1e-7)
    c = np.zeros(fg.NS)  # a switch 0.3 ms later is a different flight
    fg.integrate(c, 0.0, 0.02, par=par, kt=KT, kh=heights(1.0), switch=(0.0126, 0.1, 0.0))
    fg.integrate(c, 0.02, 0.5, par=par, kt=KT, kh=heights(1.0), command=(0.1, 0.0))
    assert abs(c[fg.TH] - a[fg.TH]) > 1e-5


def test_sensor_counts_floor_and_axes() -> None:
    q = 0.001
    assert fg.sensor_counts(-0.5 * q, 0.0, 0.0, q, q) == (-1, 0)  # floor, not truncation
    assert fg.sensor_counts(2.5 * q, -3.5 * q, 0.0, q, q) == (2, -4)
    # axes turned by +90 deg about z: sensor x = body y, sensor y = -body x
    assert fg.sensor_counts(5.2 * q, 3.2 * q, math.pi / 2, q, q) == (3, -6)
    # a true rad per count 1.2 x Q: fewer counts
    assert fg.sensor_counts(12.1 * q, 0.0, 0.0, 1.2 * q, q) == (10, 0)


def test_gauss_markov_noise_statistics() -> None:
    rng = np.random.default_rng(3)
    x = fg.ar1(rng, 200_000, 0.3, 0.5, 0.02)
    assert np.std(x) == pytest.approx(0.3, rel=0.05)
    assert np.corrcoef(x[1:], x[:-1])[0, 1] == pytest.approx(math.exp(-0.02 / 0.5), abs=0.005)
    assert not np.any(fg.ar1(rng, 10, 0.0, 0.5, 0.02))


def test_loss_fraction_as_requested() -> None:
    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(0.0, 100.0, 200_000))
    keep = fg.apply_loss(t, fg.Loss(random_frac=0.15), rng)
    assert 1 - keep.mean() == pytest.approx(0.15, abs=0.004)
    keep = fg.apply_loss(t, fg.Loss(bursts_s=(10.0, 50.2), burst_s=0.5), rng)
    lost = ~keep
    assert np.all(lost == (((t >= 10.0) & (t < 10.5)) | ((t >= 50.2) & (t < 50.7))))
    assert fg.Loss(random_frac=0.1, bursts_s=(1.0,)).kind == "both" and fg.Loss().kind == "none"


# ---------------------------------------------------------------------------------------------
# what a seed draws


def test_drawn_specs_cover_the_issue_ranges() -> None:
    specs = [fg.draw_spec(s) for s in range(400)]
    d = np.array([s.duration_s for s in specs])
    assert d.min() >= 20 and d.max() <= 1200
    assert 0.02 <= np.mean(d > 300) <= 0.10 and np.mean((d >= 30) & (d <= 300)) > 0.7
    clean = [s for s in specs if not s.effects]
    assert 0.13 <= len(clean) / len(specs) <= 0.27
    assert any(s.loss.kind != "none" for s in clean) and any(s.noise.att_white_rad > 0 for s in clean)
    assert {s.loss.kind for s in specs} == {"none", "random", "bursts", "both"}
    assert 0.12 <= np.mean([s.sensors.profile == "ardupilot" for s in specs]) <= 0.28
    assert {len(s.effects) for s in specs} == {0, 1, 2}
    assert 0.1 <= np.mean([s.noise.accel_white_m_s2 == 0 for s in specs]) <= 0.3  # some without accelerometer noise
    seen = set()
    for s in specs:
        v = s.vehicle
        assert 0.5 <= v.mass_kg <= 3 and 4 <= v.omega_p_nominal <= 15 and 0.5 <= v.zeta_nominal <= 1.2
        assert 0.0 < s.flight.speed_limit_m_s <= 2.0 and all(0.5 <= h <= 3.0 for h in s.flight.alt_m)
        assert s.noise.att_white_rad <= math.radians(0.2) and s.noise.att_gm_rad <= math.radians(0.3)
        assert s.noise.flow_count_error_frac <= 0.05 and s.noise.range_noise_m <= 0.02
        assert s.noise.record_jitter_s <= 0.005 and s.noise.sensor_time_jitter_s <= 0.001
        assert s.noise.turbulence_n <= 0.4 and s.loss.random_frac <= 0.2
        assert s.noise.accel_white_m_s2 == 0 or 0.02 <= s.noise.accel_white_m_s2 <= 0.5
        assert max(abs(s.noise.accel_bias_x_m_s2), abs(s.noise.accel_bias_y_m_s2)) <= 0.2
        assert s.noise.accel_vibration_m_s2 <= 0.5 and 1.0 <= s.noise.accel_vibration_hz <= 24.0
        for name, p in s.effects.items():
            seen.add(name)
            if name == "linear_drag":
                assert 0.15 <= p["b"] <= 0.8
            elif name == "quadratic_drag":
                assert 0.1 <= p["c"] <= 0.5
            elif name == "gyro_bias":
                assert 0.01 <= abs(p["bias_x"]) <= 0.05 and 0.01 <= abs(p["bias_y"]) <= 0.05
            elif name == "flow_scale":
                for k in ("scale_x", "scale_y"):
                    assert 0.8 <= p[k] <= 0.92 or 1.08 <= p[k] <= 1.25
            elif name == "flow_delay":
                assert 0.01 <= p["delay"] <= 0.04
            elif name == "flow_yaw_misalignment":
                assert 3 <= abs(math.degrees(p["yaw"])) <= 15
            elif name == "attitude_dynamics":
                k = p["omega_p"] / v.omega_p_nominal
                assert 0.6 <= k <= 0.8 or 1.25 <= k <= 1.6
                assert abs(p["zeta"] - v.zeta_nominal) <= 0.2 + 1e-9 or p["zeta"] == 0.3
            elif name == "range_offset":
                assert 0.05 <= p["offset"] <= 0.2
            elif name == "wind_force":
                assert 0.4 <= math.hypot(p["fx"], p["fy"]) <= 4.0
                on = min(p["end_s"], s.warmup_s + s.duration_s) - max(p["start_s"], s.warmup_s)
                assert on >= 6.0 - 0.05
                assert (p["start_s"] == 0.0) == s.wind_from_start
            elif name == "attitude_delay":
                assert 0.02 <= p["delay"] <= 0.06
            elif name == "flow_rotation_gain":
                assert 0.85 <= p["gain"] <= 0.93 or 1.08 <= p["gain"] <= 1.2
            elif name == "flow_lever_arm":
                assert max(abs(p["rx"]), abs(p["ry"]), abs(p["rz"])) <= 0.2 and abs(p["rz"]) >= 0.05
            elif name == "gyro_lag":
                assert 0.01 <= p["tau"] <= 0.05
    assert seen == set(fg.EFFECT_NAMES)
    assert fg.draw_spec(7) == fg.draw_spec(7)  # deterministic


# ---------------------------------------------------------------------------------------------
# closed loop and recordings


def quiet_spec(seed: int = 3, *, effects: dict | None = None, profile: str | None = None, duration: float = 30.0,
               setpoint: tuple[float, float] = (1.0, -0.5), height: float = 1.0) -> fg.FlightSpec:
    """A noise-free, lossless flight at constant height with a constant setpoint."""
    spec = fg.draw_spec(seed, ardupilot_share=0.0 if profile != "ardupilot" else 1.0)
    flight = fg.FlightProfile((fg.SetpointSegment(0.0, 1e4, "step", (0.0, 0.0), setpoint),), (0.0, 1e4),
                              (height, height), 2.0)
    return dataclasses.replace(spec, duration_s=duration, warmup_s=2.0, flight=flight, noise=fg.Noise(),
                               loss=fg.Loss(), effects=effects or {}, wind_from_start=False, wind_to_end=False,
                               sensors=dataclasses.replace(spec.sensors, imu_lead_s=0.0, att_lead_s=0.0,
                                                           range_lead_s=0.0))


def tail_mean(x: np.ndarray, n: int = 150) -> float:
    return float(np.mean(x[-n:]))


@pytest.mark.parametrize("profile", ["paper", "ardupilot"])
def test_the_companion_flies_the_setpoint_and_its_estimate_is_the_truth(profile: str) -> None:
    fl = fg.simulate(quiet_spec(profile=profile))
    t = fl.truth
    assert tail_mean(t["vx"]) == pytest.approx(1.0, abs=0.01)
    assert tail_mean(t["vy"]) == pytest.approx(-0.5, abs=0.01)
    assert tail_mean(t["vx_est"]) == pytest.approx(tail_mean(t["vx"]), abs=0.01)
    assert tail_mean(t["vy_est"]) == pytest.approx(tail_mean(t["vy"]), abs=0.01)
    assert fl.stats["holds"] == {} and fl.stats["flyable"]


def test_flow_scale_and_range_offset_move_the_steady_velocity_as_eq15_says() -> None:
    """eq. 15 with Q x scale true rad per count reads v / scale: the loop flies scale x setpoint; a
    range reading D + offset reads v (D + offset) / D: the loop flies setpoint D / (D + offset)."""
    fl = fg.simulate(quiet_spec(effects={"flow_scale": {"scale_x": 1.2, "scale_y": 0.85}}))
    assert tail_mean(fl.truth["vx"]) == pytest.approx(1.2 * 1.0, abs=0.015)
    assert tail_mean(fl.truth["vy"]) == pytest.approx(0.85 * -0.5, abs=0.015)
    fl = fg.simulate(quiet_spec(effects={"range_offset": {"offset": 0.2}}, height=1.0))
    assert tail_mean(fl.truth["vx"]) == pytest.approx(1.0 / 1.2, abs=0.015)


def test_a_steady_wind_is_held_by_tilting_against_it() -> None:
    spec = quiet_spec(effects={"wind_force": {"fx": 1.5, "fy": -1.0, "start_s": 0.0, "end_s": 1e4}},
                      setpoint=(0.0, 0.0))
    fl = fg.simulate(spec)
    mg = spec.vehicle.mass_kg * spec.vehicle.gravity_m_s2
    assert tail_mean(fl.truth["pitch"]) == pytest.approx(math.atan(1.5 / mg), abs=0.003)  # nose up against +x
    assert tail_mean(fl.truth["roll"]) == pytest.approx(math.atan(1.0 / mg), abs=0.003)  # right down against -y


def _decoded(fl: fg.Flight, kind: str) -> list:
    from pymavlink.dialects.v20 import ardupilotmega as mav

    parser = mav.MAVLink(None)
    return [parser.decode(bytearray(b)) for _t, _c, b, k, _f in fl.packets if k == kind]


def test_the_accelerometer_carries_its_drawn_noise_and_changes_nothing_else() -> None:
    """RAW_IMU xacc/yacc (milli-g) minus the noise-free flight's: mean = the bias, standard deviation
    = sqrt(white^2 + vibration^2 / 2) (a sinusoid's rms), to the sampling error of 1000 frames (about
    2 % on the sd, 0.01 m/s^2 on the mean) and the 1 milli-g rounding; the loop does not read the
    accelerometer, so the flow and the companion's commands are the same message for message."""
    spec = quiet_spec(duration=20.0)
    nz = fg.Noise(accel_white_m_s2=0.3, accel_bias_x_m_s2=0.1, accel_bias_y_m_s2=-0.15, accel_vibration_m_s2=0.2,
                  accel_vibration_hz=7.3)
    clean, noisy = fg.simulate(spec), fg.simulate(dataclasses.replace(spec, noise=nz))
    g_mg = spec.vehicle.gravity_m_s2 / 1000.0
    a0, a1 = _decoded(clean, "RAW_IMU"), _decoded(noisy, "RAW_IMU")
    dx = np.array([(m1.xacc - m0.xacc) * g_mg for m0, m1 in zip(a0, a1, strict=True)])
    dy = np.array([(m1.yacc - m0.yacc) * g_mg for m0, m1 in zip(a0, a1, strict=True)])
    assert len(dx) > 1000
    sd = math.hypot(0.3, 0.2 / math.sqrt(2))
    for d, bias in ((dx, 0.1), (dy, -0.15)):
        assert float(np.mean(d)) == pytest.approx(bias, abs=0.04)
        assert float(np.std(d)) == pytest.approx(sd, rel=0.08)
    for kind in ("OPTICAL_FLOW", "SET_ATTITUDE_TARGET", "ATTITUDE"):
        assert [m.to_dict() for m in _decoded(clean, kind)] == [m.to_dict() for m in _decoded(noisy, kind)], kind
    assert [m.xgyro for m in a0] == [m.xgyro for m in a1]


def read_messages(path: Path) -> dict[str, list]:
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    out: dict[str, list] = {}
    last = -1.0
    try:
        while True:
            m = conn.recv_match()
            if m is None:
                break
            assert m._timestamp >= last  # records in arrival order
            last = m._timestamp
            out.setdefault(m.get_type(), []).append(m)
    finally:
        conn.close()
    return out


def test_a_recording_follows_the_message_contract(tmp_path: Path) -> None:
    from companion.config import load_config

    spec = quiet_spec(effects={"gyro_bias": {"bias_x": 0.02, "bias_y": -0.03}}, duration=12.0)
    spec = dataclasses.replace(spec, loss=fg.Loss(random_frac=0.1), noise=fg.Noise(record_jitter_s=0.003))
    g = fg.write_flight(spec, fg.simulate(spec), tmp_path, "rec")
    msgs = read_messages(g.tlog)
    for name in ("OPTICAL_FLOW", "RAW_IMU", "DISTANCE_SENSOR", "ATTITUDE", "SET_ATTITUDE_TARGET",
                 "POSITION_TARGET_LOCAL_NED", "LOCAL_POSITION_NED", "HEARTBEAT", "VISION_SPEED_ESTIMATE"):
        assert name in msgs, name
    n_frames = round(spec.duration_s * 50)
    assert 0.85 * n_frames < len(msgs["OPTICAL_FLOW"]) < 0.95 * n_frames  # 10 % lost
    vehicle = {(m.get_srcSystem(), m.get_srcComponent()) for n in ("OPTICAL_FLOW", "RAW_IMU", "ATTITUDE",
                                                                    "DISTANCE_SENSOR") for m in msgs[n]}
    assert vehicle == {(1, 1)}
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in msgs["SET_ATTITUDE_TARGET"]} == {(1, 191)}
    assert {m.get_srcComponent() for m in msgs["HEARTBEAT"]} == {1, 191}
    # gyro in mrad/s integers = attitude rate + bias (roll-rate gyro carries bias_x)
    att = {m.time_boot_ms: m for m in msgs["ATTITUDE"]}
    pairs = [(g_, att[round(g_.time_usec / 1000)]) for g_ in msgs["RAW_IMU"] if round(g_.time_usec / 1000) in att]
    assert len(pairs) > 300
    dx = np.array([g_.xgyro - 1000 * a.rollspeed for g_, a in pairs])
    dy = np.array([g_.ygyro - 1000 * a.pitchspeed for g_, a in pairs])
    assert np.median(dx) == pytest.approx(20, abs=1) and np.median(dy) == pytest.approx(-30, abs=1)
    # range in cm, facing down, with the sensor's limits
    ds = msgs["DISTANCE_SENSOR"]
    assert {m.orientation for m in ds} == {25}
    assert {(m.min_distance, m.max_distance) for m in ds} == {(2, 400)}
    assert np.median([m.current_distance for m in ds]) == pytest.approx(100, abs=1)
    # the command of flow frame k carries that frame's time, from the companion, type_mask 7, thrust 0.5
    flow_ms = {round(m.time_usec / 1000) for m in msgs["OPTICAL_FLOW"]}
    sat = msgs["SET_ATTITUDE_TARGET"]
    assert sum(m.time_boot_ms in flow_ms for m in sat) > 0.85 * len(sat)
    assert {m.type_mask for m in sat} == {7} and {round(m.thrust, 3) for m in sat} == {0.5}
    pt = msgs["POSITION_TARGET_LOCAL_NED"]
    assert {(round(m.vx, 3), round(m.vy, 3), m.coordinate_frame) for m in pt} == {(1.0, -0.5, 12)}
    # the nominal config and the truth
    cfg = load_config(g.config)
    assert cfg.airframe.mass_kg == pytest.approx(spec.vehicle.mass_kg)
    assert cfg.airframe.omega_p_rad_s == pytest.approx(spec.vehicle.omega_p_nominal)
    assert cfg.flow_sensor.q_rad_per_count == pytest.approx(spec.sensors.q_rad_per_count)
    truth = json.loads(g.truth_path.read_text())
    assert truth["effects"] == {"gyro_bias": {"bias_x": 0.02, "bias_y": -0.03}}
    assert truth["duration_s"] == 12.0 and truth["loss"]["random_frac"] == 0.1 and truth["profile"] == "paper"
    assert abs(truth["first_frame_s"]) < 0.05


def test_ardupilot_profile_messages(tmp_path: Path) -> None:
    spec = quiet_spec(profile="ardupilot", duration=10.0)
    g = fg.write_flight(spec, fg.simulate(spec), tmp_path, "ap")
    msgs = read_messages(g.tlog)
    of = msgs["OPTICAL_FLOW"]
    t_ms = np.array([m.time_usec for m in of], dtype=float)
    assert np.median(np.diff(t_ms)) == 20  # milliseconds
    assert {m.quality for m in of} == {51}
    # flow_rate_x carries y motion: flying at vy = -0.5 m/s at 1 m, flow_rate_x = -vy / d = +0.5 rad/s
    assert np.median([m.flow_rate_x for m in of[-100:]]) == pytest.approx(0.5, abs=0.02)
    assert np.median([m.flow_rate_y for m in of[-100:]]) == pytest.approx(1.0, abs=0.02)  # +vx / d
    assert {m.flow_x for m in of[-100:]} == {0}  # the rates truncated to whole rad/s


def test_a_replay_of_a_lossless_recording_reproduces_its_commands(tmp_path: Path) -> None:
    """The messages carry exactly what the companion saw: replay recomputes the recorded commands
    (recorded from the first frame: a replay starts its integrator at zero)."""
    spec = quiet_spec(duration=12.0)
    spec = dataclasses.replace(spec, warmup_s=0.0, noise=fg.Noise(att_white_rad=0.002, gyro_white_rad_s=0.003,
                                                                  turbulence_n=0.2, range_noise_m=0.01))
    g = fg.write_flight(spec, fg.simulate(spec), tmp_path, "r")
    csv = tmp_path / "r.csv"
    subprocess.run([sys.executable, "-m", "companion", "replay", str(g.tlog), "--csv", str(csv), "--config",
                    str(g.config)], cwd=ROOT, check=True, capture_output=True)
    rows = np.genfromtxt(csv, delimiter=",", names=True)
    msgs = read_messages(g.tlog)
    from companion.rotation import quaternions_to_euler

    q = np.array([m.q for m in msgs["SET_ATTITUDE_TARGET"]])
    roll, pitch, _ = quaternions_to_euler(q)
    n = min(len(rows), len(roll))
    assert n > 500
    assert np.max(np.abs(rows["roll_cmd_rad"][:n] - roll[:n])) < 1e-5
    assert np.max(np.abs(rows["pitch_cmd_rad"][:n] - pitch[:n])) < 1e-5


# ---------------------------------------------------------------------------------------------
# the scorer on synthetic reports


def finding(effect: str, significant: bool = True, **params: float) -> dict:
    return {"effect": effect, "significant": significant, "parameters": params}


def truth_of(effects: dict, **extra: object) -> dict:
    return {"effects": effects, **extra}


def test_score_hits_misses_and_tolerances() -> None:
    t = truth_of({"flow_scale": {"scale_x": 1.1, "scale_y": 0.9}})
    s = fg.score(t, {"findings": [finding("flow_scale", scale_x=1.12, scale_y=0.885)], "unexplained": []})
    assert s["right"] and s["hits"] == ["flow_scale"]
    s = fg.score(t, {"findings": [finding("flow_scale", scale_x=1.14, scale_y=0.9)], "unexplained": []})
    assert not s["right"] and s["effects"]["flow_scale"]["reason"] == "out of tolerance"
    assert s["effects"]["flow_scale"]["errors"]["scale_x"] == pytest.approx(4 / 3)
    s = fg.score(t, {"findings": [finding("flow_scale", significant=False, scale_x=1.1, scale_y=0.9)]})
    assert s["misses"] == ["flow_scale"] and s["effects"]["flow_scale"]["reason"] == "not reported"
    t = truth_of({"attitude_dynamics": {"omega_p": 8.0, "zeta": 0.9}, "linear_drag": {"b": 0.5}})
    rep = {"findings": [finding("attitude_dynamics", omega_p=9.1, zeta=1.04), finding("linear_drag", b=0.59)]}
    assert fg.score(t, rep)["right"]
    rep = {"findings": [finding("attitude_dynamics", omega_p=9.3, zeta=0.9), finding("linear_drag", b=0.61)]}
    assert set(fg.score(t, rep)["misses"]) == {"attitude_dynamics", "linear_drag"}
    t = truth_of({"flow_yaw_misalignment": {"yaw": math.radians(5)}, "gyro_lag": {"tau": 0.02}})
    rep = {"findings": [finding("flow_yaw_misalignment", yaw=math.radians(6.9)), finding("gyro_lag", tau=0.0259)]}
    assert fg.score(t, rep)["right"]
    rep = {"findings": [finding("flow_yaw_misalignment", yaw=math.radians(-5)), finding("gyro_lag", tau=None)]}
    assert set(fg.score(t, rep)["misses"]) == {"flow_yaw_misalignment", "gyro_lag"}  # sign; a missing value


def test_score_false_findings() -> None:
    s = fg.score(truth_of({}), {"findings": [finding("gyro_bias", bias_x=0.01, bias_y=0.0),
                                             finding("range_offset", significant=False, offset=0.1)]})
    assert s["false"] == ["gyro_bias"] and not s["right"] and s["clean"]
    s = fg.score(truth_of({}), {"findings": [], "unexplained": [{"channel": "gyro_x", "rms": 1.0}]})
    assert s["right"] and s["n_unexplained"] == 1  # unexplained is not a finding


def test_score_a_finding_that_names_alternatives() -> None:
    """"flow_rotation_gain, or flow_scale: this flight cannot tell them apart": a hit on whichever
    it names is true (with that one's parameters), false only when none of them is."""
    amb = dict(finding("flow_rotation_gain", gain=1.22),
               alternatives=[{"effect": "flow_scale", "parameters": {"scale_x": 0.83, "scale_y": 0.81},
                              "cv_t": 0.8}])
    s = fg.score(truth_of({"flow_scale": {"scale_x": 0.84, "scale_y": 0.82}}), {"findings": [amb]})
    assert s["right"] and s["hits"] == ["flow_scale"] and s["ambiguous_hits"] == ["flow_scale"]
    s = fg.score(truth_of({"flow_scale": {"scale_x": 0.90, "scale_y": 0.82}}), {"findings": [amb]})
    assert s["misses"] == ["flow_scale"] and s["false"] == []  # named, out of tolerance
    s = fg.score(truth_of({"range_offset": {"offset": 0.1}}), {"findings": [amb]})
    assert s["false"] == ["flow_rotation_gain"] and s["misses"] == ["range_offset"]
    s = fg.score(truth_of({}), {"findings": [amb]})
    assert s["false"] == ["flow_rotation_gain"] and not s["right"]


def test_score_quadratic_drag_alias() -> None:
    t = truth_of({"quadratic_drag": {"c": 0.3}})
    rep = {"findings": [finding("linear_drag", b=0.4)],
           "unexplained": [{"channel": "force_x", "start_s": 0, "end_s": 9, "rms": 0.1,
                            "best_term": "-0.3 N per m^2/s^2 of velocity |velocity| (a quadratic (form) drag)"}]}
    s = fg.score(t, rep)
    assert s["false"] == [] and s["misses"] == ["quadratic_drag"]
    assert s["effects"]["quadratic_drag"]["reason"].startswith("aliased")
    rep["unexplained"] = []
    assert fg.score(t, rep)["false"] == ["linear_drag"]
    assert fg.score(t, {"findings": [finding("quadratic_drag", c=0.36)]})["right"]


def test_score_gyro_lag_left_unexplained() -> None:
    t = truth_of({"gyro_lag": {"tau": 0.03}})
    lag = {"channel": "gyro_y", "start_s": 0, "end_s": 50, "rms": 0.1,
           "best_term": "+0.03 rad/s per rad/s^2 of angular acceleration (the gyro lags the attitude (a low-pass "
                        "filter or a delay))"}
    assert fg.score(t, {"findings": [], "unexplained": [lag]})["right"]
    s = fg.score(t, {"findings": [finding("flow_delay", delay=0.03)], "unexplained": [lag]})
    assert s["misses"] == ["gyro_lag"] and s["false"] == ["flow_delay"]
    other = dict(lag, channel="flow_x", best_term="+0.0003 rad per rad/s^2 of rotation acceleration (a filter in "
                                                  "the flow or attitude path)")
    assert not fg.score(t, {"findings": [], "unexplained": [other]})["right"]


def test_score_wind_vector_and_window() -> None:
    t = truth_of({"wind_force": {"fx": 2.0, "fy": 0.0, "start_s": 10.0, "end_s": 40.0}},
                 wind={"start_at_first_frame": False, "end_at_last_frame": False})
    ok = finding("wind_force", fx=2.3, fy=0.2, start_s=11.4, end_s=38.6)
    assert fg.score(t, {"findings": [ok]})["right"]  # |dF| = 0.36 N <= 20 % of 2 N
    assert not fg.score(t, {"findings": [dict(ok, parameters=dict(ok["parameters"], fy=0.35))]})["right"]
    assert not fg.score(t, {"findings": [dict(ok, parameters=dict(ok["parameters"], start_s=11.6))]})["right"]
    # two windows reported, one of them right: a hit (noted)
    s = fg.score(t, {"findings": [finding("wind_force", fx=0.5, fy=0.0, start_s=60, end_s=70), ok]})
    assert s["right"] and s["notes"]
    # a wind from before the recording: its start may match the first usable frame
    t = truth_of({"wind_force": {"fx": 0.0, "fy": -1.0, "start_s": 0.02, "end_s": 30.0}},
                 wind={"start_at_first_frame": True, "end_at_last_frame": True}, first_usable_s=3.0,
                 last_usable_s=28.0)
    assert fg.score(t, {"findings": [finding("wind_force", fx=0.1, fy=-1.0, start_s=4.2, end_s=27.0)]})["right"]
    assert fg.score(t, {"findings": [finding("wind_force", fx=0.1, fy=-1.0, start_s=1.0, end_s=29.9)]})["right"]
    assert not fg.score(t, {"findings": [finding("wind_force", fx=0.1, fy=-1.0, start_s=5.0, end_s=29.9)]})["right"]


def test_score_lever_arm_scores_rz_only() -> None:
    t = truth_of({"flow_lever_arm": {"rx": 0.15, "ry": -0.1, "rz": 0.12}})
    assert fg.score(t, {"findings": [finding("flow_lever_arm", rz=0.16)]})["right"]
    assert fg.score(t, {"findings": [finding("flow_lever_arm", rx=-0.2, ry=0.2, rz=0.08)]})["right"]
    assert not fg.score(t, {"findings": [finding("flow_lever_arm", rz=0.18)]})["right"]


# ---------------------------------------------------------------------------------------------
# the matrix end to end


@pytest.mark.slow
def test_a_small_generalisation_matrix_has_no_hang(tmp_path: Path) -> None:
    sys.path.insert(0, str(ROOT / "scripts"))
    import generalisation_matrix as gm

    out = tmp_path / "gm"
    assert gm.main(["--n", "12", "--seed", "1", "--out", str(out), "--workers", "2", "--timeout", "120",
                    "--doc", str(tmp_path / "doc.md"), "--quiet"]) == 0
    lines = (out / "results.jsonl").read_text().splitlines()
    results = [json.loads(x) for x in lines]
    assert len(results) == 12
    t = gm.totals(results)
    assert t["timeouts"] == 0, [r["name"] for r in results if r["status"] == "timeout"]
    assert t["errors"] == 0, [r.get("error") for r in results if r["status"] != "ok"]
    assert "| effect |" in (tmp_path / "doc.md").read_text()


def test_the_matrix_measures_its_stated_uncertainty_against_the_truth() -> None:
    sys.path.insert(0, str(ROOT / "scripts"))
    import generalisation_matrix as gm

    def rec(name: str, found_b: float, sd: float) -> dict[str, object]:
        return {"name": name, "status": "ok", "truth_effects": {"linear_drag": {"b": 0.4}},
                "found": [{"effect": "linear_drag", "parameters": {"b": found_b}, "uncertainty": {"b": sd}},
                          {"effect": "gyro_bias", "parameters": {"bias_x": 0.1}, "uncertainty": {"bias_x": 0.01}}]}

    # pulls 0.5, -1.5, 3.0, 0.2; the gyro bias is not true (a false finding has no pull); NaN sigma left out
    results = [rec("a", 0.45, 0.1), rec("b", 0.25, 0.1), rec("c", 0.7, 0.1), rec("d", 0.42, 0.1),
               rec("e", 0.5, math.nan)]
    pu = gm.pulls(results)
    assert list(pu) == ["linear_drag.b"]
    assert [round(p, 9) for p, _n in pu["linear_drag.b"]] == [0.5, -1.5, 3.0, 0.2]
    row = next(x for x in gm.uncertainty_section(results) if x.startswith("| linear_drag.b"))
    assert row == "| linear_drag.b | 4 | 50 % | 75 % | 1.00 | 3 (c) |"


def test_the_matrix_counts_unexplained_entries_on_clean_recordings() -> None:
    """Issue 12 asks that nothing the recording's own noise explains be listed as unexplained: on a
    clean recording (no true effect) every unexplained entry is that, and the matrix counts and
    lists them; entries on recordings with true effects, and errors, are not counted."""
    sys.path.insert(0, str(ROOT / "scripts"))
    import generalisation_matrix as gm

    def rec(name: str, truth: dict[str, object], n_unexplained: int, status: str = "ok") -> dict[str, object]:
        ents = [{"channel": "force_x", "start_s": 1.0, "end_s": 9.0, "rms": 0.1,
                 "best_term": "+20 N per rad of tilt (a thrust or tilt-estimate scale error)"}] * n_unexplained
        return {"name": name, "status": status, "truth_effects": truth, "duration_s": 30.0, "noise": {},
                "gen_s": 1.0, "diag_s": 1.0,
                "n_unexplained": n_unexplained, "unexplained": ents,
                "score": {"clean": not truth, "right": True, "hits": [], "misses": [], "false": []}}

    results = [rec("a", {}, 0), rec("b", {}, 2), rec("c", {"linear_drag": {"b": 0.3}}, 1), rec("d", {}, 1)]
    results[3]["n_unexplained"] = 0  # an entry list the count does not match is read by its count
    t = gm.totals(results)
    assert (t["clean"], t["clean_unexplained"]) == (3, 1)
    rows = [x for x in gm.clean_unexplained_section(results) if x.startswith("| b ")]
    assert rows == ["| b | 30 | - | force_x: +20 N per rad of tilt; force_x: +20 N per rad of tilt |"]
    assert gm.clean_unexplained_section(results[:1])[-2] == "None."
