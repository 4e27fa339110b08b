"""The ``ardupilot`` profile end to end on ArduCopter SITL data (issue #9).

``data/sitl/ardupilot/flight_a.tlog.gz``: ArduCopter V4.7.0-dev SITL flown 120 s in
GUIDED_NOGPS by a plain eq. 15 + PI companion on the simulated flow sensor (README beside it).
Third-party data: ArduPilot's physics, sensor noise and message conventions. The reference
velocity is the EKF's GPS-aided LOCAL_POSITION_NED rotated into body axes by ATTITUDE's yaw,
matched to each flow frame by ``time_boot_ms`` (computed here, independently of replay).
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.config import replace_section
from companion.mavlink.outbound import quaternion_to_euler
from companion.recordings.load import Recording, load_recording, read_recording_bytes
from companion.recordings.tlog_writer import TlogWriter
from companion.step.core import EstimatorOptions, GyroSource, TiltFilter, VelocityEstimator
from companion.step.profiles import Profile, detect_profile
from companion.tools.convert import _records, convert_tlog
from companion.tools.replay import replay, replay_live
from simvehicle.engines.scenarios import Scenario, fly

REPO = Path(__file__).resolve().parent.parent
FLIGHT_A = REPO / "data" / "sitl" / "ardupilot" / "flight_a.tlog.gz"
#: README: SIM_FLOW_RND = 0.05 (uniform +-0.05 rad/s on each flow rate) at a height of 1.5 m
FLOW_NOISE_M_S = 0.05 / math.sqrt(3.0) * 1.5
#: float32 on the wire: relative rounding 2^-24
F32 = 2.0 ** -24


@pytest.fixture(scope="module")
def rec() -> Recording:
    return load_recording(FLIGHT_A)


@pytest.fixture(scope="module")
def ekf(rec: Recording) -> dict[int, tuple[float, float]]:
    """EKF velocity in body axes by time_boot_ms (LOCAL_POSITION_NED, ATTITUDE yaw)."""
    lp, att = rec.table("LOCAL_POSITION_NED"), rec.table("ATTITUDE")
    yaw = dict(zip(att["time_boot_ms"].tolist(), att["yaw"].tolist(), strict=True))
    out = {}
    for ms, vn, ve in zip(lp["time_boot_ms"].tolist(), lp["vx"].tolist(), lp["vy"].tolist(), strict=True):
        if ms in yaw:
            c, s = math.cos(yaw[ms]), math.sin(yaw[ms])
            out[ms] = (c * vn + s * ve, -s * vn + c * ve)
    return out


@pytest.fixture(scope="module")
def plain(rec: Recording) -> dict[int, tuple[float, float]]:
    """The plain companion's VISION_SPEED_ESTIMATE by flow frame (ms): its 6001 steps in GUIDED_NOGPS."""
    vse = rec.table("VISION_SPEED_ESTIMATE")
    return {int(round(u / 1000)): (x, y) for u, x, y in zip(vse["usec"].tolist(), vse["x"].tolist(),
                                                             vse["y"].tolist(), strict=True)}


def errors(ms: np.ndarray, vx: np.ndarray, vy: np.ndarray, ekf: dict, window: dict) -> np.ndarray:
    """(n, 2) estimate - EKF over the frames in ``window`` (the GUIDED_NOGPS steps)."""
    rows = [(vx[i] - ekf[m][0], vy[i] - ekf[m][1]) for i, m in enumerate(ms.tolist()) if m in window and m in ekf]
    return np.array(rows)


def rms(e: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(e ** 2, axis=0))


def lag_s(est: np.ndarray, ref: np.ndarray, frame_s: float = 0.02, max_lag: int = 10) -> float:
    """How far ``est`` lags ``ref`` (s): the peak of their cross-correlation, parabola-refined."""
    e, r = est - est.mean(), ref - ref.mean()
    n = len(e)
    c = np.array([np.dot(e[max_lag + k:n - max_lag + k], r[max_lag:n - max_lag]) for k in range(-max_lag, max_lag + 1)])
    i = int(np.argmax(c))
    off = 0.0
    if 0 < i < len(c) - 1:
        off = 0.5 * (c[i - 1] - c[i + 1]) / (c[i - 1] - 2 * c[i] + c[i + 1])
    return (i - max_lag + off) * frame_s


@pytest.fixture(scope="module")
def cli_csv(tmp_path_factory) -> tuple[np.ndarray, str]:
    out = tmp_path_factory.mktemp("fa") / "flight_a.csv"
    r = subprocess.run([sys.executable, "-m", "companion", "replay", str(FLIGHT_A), "--profile", "ardupilot",
                        "--estimator", "eq15", "--csv", str(out)], capture_output=True, text=True, timeout=180,
                       cwd=REPO)
    assert r.returncode == 0, r.stderr
    return np.genfromtxt(out, delimiter=",", names=True, dtype=None, encoding="utf-8"), r.stderr


def test_detected_and_named_as_ardupilot(rec):
    name, why = detect_profile(rec)
    assert name == "ardupilot" and "milliseconds" in why
    r = subprocess.run([sys.executable, "-m", "companion", "info", str(FLIGHT_A)], capture_output=True, text=True,
                       timeout=180, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert "profile: ardupilot" in r.stdout


def test_replay_is_at_least_as_accurate_as_the_plain_companion(cli_csv, ekf, plain, rec):
    """``--profile ardupilot --estimator eq15`` (gyro: the flow message's own body rate) against the EKF
    over GUIDED_NOGPS: no worse than the recorded VISION_SPEED_ESTIMATE (README: 0.113 / 0.112),
    and down at the simulated flow noise combined with the EKF's own error."""
    data, stderr = cli_csv
    assert "profile ardupilot" in stderr and "gyro flow" in stderr and "estimator eq15" in stderr
    ms = np.round(data["frame_time_s"] * 1e3).astype(np.int64)
    e_replay = errors(ms, data["vx_m_s"], data["vy_m_s"], ekf, plain)
    pm = np.array(sorted(plain))
    e_plain = errors(pm, np.array([plain[m][0] for m in pm]), np.array([plain[m][1] for m in pm]), ekf, plain)
    assert len(e_replay) == len(e_plain) == 6001  # the 120 s of companion control, every frame
    r_replay, r_plain = rms(e_replay), rms(e_plain)
    assert r_plain == pytest.approx([0.113, 0.112], abs=0.0015)  # the README's numbers
    assert (r_replay <= r_plain).all()
    # the EKF's own error against the simulator's truth (SIM_STATE velocity, body axes), at the flow frames
    ss = rec.table("SIM_STATE")
    of = rec.table("OPTICAL_FLOW")
    t_log = np.interp(ms, np.round(of["time_usec"]).astype(np.int64), of.t_s)
    yaw = np.interp(t_log, ss.t_s, np.unwrap(ss["yaw"].astype(float)))
    vn, ve = np.interp(t_log, ss.t_s, ss["vn"]), np.interp(t_log, ss.t_s, ss["ve"])
    truth = {m: (math.cos(y) * a + math.sin(y) * b, -math.sin(y) * a + math.cos(y) * b)
             for m, y, a, b in zip(ms.tolist(), yaw, vn, ve, strict=True)}
    ex = np.array([ekf[m] for m in ms.tolist() if m in plain and m in ekf])
    tr = np.array([truth[m] for m in ms.tolist() if m in plain and m in ekf])
    ekf_err = rms(ex - tr)
    assert (ekf_err < 0.03).all()
    # eq. 15 with the flow's own body rate leaves only the flow noise: RMS = hypot(noise, EKF error)
    np.testing.assert_allclose(r_replay, np.hypot(FLOW_NOISE_M_S, ekf_err), rtol=0.10)
    assert (data["hold_cause"][np.isin(ms, pm)] == "").all()


def test_replay_with_raw_imu_reproduces_the_plain_companion(rec, paper_cfg, plain):
    """``--gyro imu`` is the plain companion's estimator: the recorded estimates to float32
    precision, and its commands (same Table VI PI, the integrator started at the take-over)."""
    res = replay(rec, paper_cfg, Profile.ARDUPILOT, EstimatorOptions(GyroSource.IMU))
    assert res.n_repeats == 0  # README: no frame repeats in this file
    ms = np.round(res["frame_time_s"] * 1e3).astype(np.int64)
    inside = np.isin(ms, np.array(sorted(plain)))
    assert inside.sum() == 6001 and (res["engaged"][inside] == 1).all() and res["engaged"].sum() == 6001
    rec_v = np.array([plain[m] for m in ms[inside].tolist()])
    vmax = np.abs(rec_v).max()
    np.testing.assert_allclose(res["vx_m_s"][inside], rec_v[:, 0], rtol=0, atol=vmax * F32)
    np.testing.assert_allclose(res["vy_m_s"][inside], rec_v[:, 1], rtol=0, atol=vmax * F32)
    sat = rec.table("SET_ATTITUDE_TARGET")
    rp = {m: quaternion_to_euler(q)[:2] for m, q in zip(sat["time_boot_ms"].tolist(), sat["q"], strict=True)}
    rec_rp = np.array([rp[m] for m in ms[inside].tolist()])
    np.testing.assert_allclose(res["roll_cmd_rad"][inside], rec_rp[:, 0], rtol=0, atol=3e-7)
    np.testing.assert_allclose(res["pitch_cmd_rad"][inside], rec_rp[:, 1], rtol=0, atol=3e-7)
    assert np.degrees(np.abs(rec_rp).max()) == pytest.approx(13.5, abs=0.1)  # README: largest command 13.5 deg


def test_tilt_filter_is_more_accurate_without_adding_lag(rec, paper_cfg, ekf, plain):
    """The optional tilt filter (core.TiltFilter) against the EKF over GUIDED_NOGPS: lower RMS
    than eq. 15 alone, with either gyro, and no more lag (cross-correlation peak) than eq. 15."""
    results = {}
    for gyro in (GyroSource.FLOW, GyroSource.IMU):
        for tilt in (None, TiltFilter()):
            res = replay(rec, paper_cfg, Profile.ARDUPILOT, EstimatorOptions(gyro, tilt))
            ms = np.round(res["frame_time_s"] * 1e3).astype(np.int64)
            e = errors(ms, res["vx_m_s"], res["vy_m_s"], ekf, plain)
            keep = np.array([m in plain and m in ekf for m in ms.tolist()])
            ref = np.array([ekf[m] for m in ms[keep].tolist()])
            lags = [lag_s(res[c][keep], ref[:, k]) for k, c in enumerate(("vx_m_s", "vy_m_s"))]
            results[(gyro, tilt is not None)] = (rms(e), np.array(lags))
    for gyro in (GyroSource.FLOW, GyroSource.IMU):
        (r0, lag0), (r1, lag1) = results[(gyro, False)], results[(gyro, True)]
        assert (r1 < 0.6 * r0).all(), (gyro, r0, r1)
        assert (lag1 <= lag0 + 0.002).all(), (gyro, lag0, lag1)
    assert (results[(GyroSource.FLOW, True)][0] < 0.03).all()


def test_flight_a_slice_fast_replay_equals_the_live_path(tmp_path, paper_cfg):
    """49-56 s of flight_a (the take-over at 51.16 s) message by message through the live
    router and core, against the column replay: equal, bit for bit, for both gyro sources."""
    data = read_recording_bytes(FLIGHT_A)
    path = tmp_path / "slice.tlog"
    t0 = None
    with TlogWriter(path) as w:
        for t_us, packet in _records(data, FLIGHT_A.name):
            t0 = t_us if t0 is None else t0
            if 49e6 <= t_us - t0 <= 56e6:
                w.write_bytes(packet, t_us * 1e-6)
    for options in (EstimatorOptions(), EstimatorOptions(GyroSource.IMU, TiltFilter()),
                    EstimatorOptions(estimator=VelocityEstimator.KF),
                    EstimatorOptions(GyroSource.IMU, estimator=VelocityEstimator.KF)):
        res = replay(load_recording(path), paper_cfg, Profile.ARDUPILOT, options)
        outs = replay_live(path, paper_cfg, Profile.ARDUPILOT, options)
        assert len(res) == len(outs) > 300
        for col, attr in (("vx_m_s", "vx_m_s"), ("vy_m_s", "vy_m_s"), ("roll_cmd_rad", "roll_cmd_rad"),
                          ("pitch_cmd_rad", "pitch_cmd_rad"), ("dt_s", "dt_s"), ("gyro_x_rad_s", "gyro_x_rad_s"),
                          ("vx_raw_m_s", "vx_raw_m_s"), ("vx_var_m2_s2", "vx_var_m2_s2"),
                          ("vy_var_m2_s2", "vy_var_m2_s2")):
            np.testing.assert_array_equal(res[col], [getattr(o, attr) for o in outs], err_msg=col)
        kf = options.estimator is VelocityEstimator.KF
        assert np.isfinite(res["vx_var_m2_s2"]).any() == kf
        assert 0 < res["engaged"].sum() < len(res)  # the take-over is inside


STEP = Scenario("short_step", 3.0, lambda t: (2.0, -1.5) if t >= 0.5 else (0.0, 0.0))


@pytest.mark.parametrize("gyro", [GyroSource.IMU, GyroSource.FLOW])
def test_paper_and_ardupilot_profiles_give_the_same_velocity(tmp_path, paper_cfg, gyro):
    """A simulated flight recorded in the paper's convention, converted to ArduPilot's (rates in
    flow_rate_*, time in ms, flow_comp_m from the gyro): both profiles give the same velocity
    and commands, to the float32 rounding of the rates."""
    src, dst = tmp_path / "paper.tlog", tmp_path / "ardupilot.tlog"
    fly(paper_cfg, STEP, profile=Profile.PAPER, tlog=src)
    n = convert_tlog(src, dst, src=Profile.PAPER, dst=Profile.ARDUPILOT, cfg=paper_cfg)
    a = replay(load_recording(src), paper_cfg, Profile.PAPER)
    b = replay(load_recording(dst), paper_cfg, Profile.ARDUPILOT, EstimatorOptions(gyro))
    assert n == len(a) == len(b) == 151
    assert (a["hold_cause"] == b["hold_cause"]).all()
    # |dv| <= |rate| 2^-24 A (float32 rate) + |gyro| 2^-24 A (float32 flow_comp_m, gyro=flow)
    rate = np.maximum(np.abs(a["scene_rate_x_rad_s"]), np.abs(a["scene_rate_y_rad_s"]))
    tol = 4 * (rate + 1.0) * F32 * a["range_m"]
    assert (np.abs(a["vx_m_s"] - b["vx_m_s"]) <= tol).all() and (np.abs(a["vy_m_s"] - b["vy_m_s"]) <= tol).all()
    assert np.abs(a["vx_m_s"]).max() > 1.0  # the comparison covers real motion
    np.testing.assert_allclose(b["pitch_cmd_rad"], a["pitch_cmd_rad"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(b["roll_cmd_rad"], a["roll_cmd_rad"], rtol=0, atol=1e-6)


@pytest.mark.slow
def test_flight_a_converted_to_the_paper_convention_gives_the_same_velocity(tmp_path, paper_cfg, rec):
    """flight_a converted to counts with a fine Q (1e-5 rad/count): the paper profile's velocity
    equals the ardupilot profile's within the quantization, Q / (2 dt) times the range."""
    q = 1e-5
    cfg = replace_section(replace_section(paper_cfg, "flow_sensor", q_rad_per_count=q), "companion",
                          max_flow_rate_rad_s=1e3)
    dst = tmp_path / "flight_a_paper.tlog"
    convert_tlog(FLIGHT_A, dst, src=Profile.ARDUPILOT, dst=Profile.PAPER, cfg=cfg)
    a = replay(rec, cfg, Profile.ARDUPILOT, EstimatorOptions(GyroSource.IMU))
    b = replay(load_recording(dst), cfg, Profile.PAPER)
    assert len(a) == len(b) and (a["hold_cause"] == b["hold_cause"]).all()
    ok = np.isfinite(a["vx_m_s"])
    bound = q / (2 * a["dt_s"][ok]) * a["range_m"][ok] * (1 + 1e-6) + 1e-9
    assert (np.abs(a["vx_m_s"][ok] - b["vx_m_s"][ok]) <= bound).all()
    assert (np.abs(a["vy_m_s"][ok] - b["vy_m_s"][ok]) <= bound).all()


@pytest.mark.slow
def test_flight_a_whole_file_fast_replay_equals_the_live_path(paper_cfg, rec):
    res = replay(rec, paper_cfg, Profile.ARDUPILOT)
    outs = replay_live(FLIGHT_A, paper_cfg, Profile.ARDUPILOT)
    assert len(res) == len(outs) == 8777
    for col in ("vx_m_s", "vy_m_s", "roll_cmd_rad", "pitch_cmd_rad"):
        np.testing.assert_array_equal(res[col], [getattr(o, col) for o in outs], err_msg=col)


def test_tilt_filter_leaves_the_closed_loop_step_response_alone(paper_cfg, monkeypatch):
    """The simulator's closed loop in the ardupilot profile, 0 -> 2 m/s step: with the tilt
    filter the 10-90 % rise time and the overshoot stay those of eq. 15 alone (the filter adds
    no lag that the loop would feel)."""
    import functools

    import simvehicle.engines.scenarios as scenarios
    from companion.step.core import CompanionCore

    step = Scenario("step_short", 4.0, lambda t: (2.0, 2.0) if t >= 0.5 else (0.0, 0.0))
    figures = []
    for tilt in (None, TiltFilter()):
        monkeypatch.setattr(scenarios, "CompanionCore",
                            functools.partial(CompanionCore, options=EstimatorOptions(tilt_filter=tilt)))
        run = fly(paper_cfg, step, profile=Profile.ARDUPILOT)
        t, v = run["t_s"], run["vx_m_s"]
        t10, t90 = t[np.argmax(v >= 0.2)], t[np.argmax(v >= 1.8)]
        figures.append((t90 - t10, v.max() / 2.0 - 1.0, v[t >= 3.0].mean()))
    (rise0, over0, end0), (rise1, over1, end1) = figures
    assert rise0 < 1.0 and rise1 == pytest.approx(rise0, abs=0.02)  # one frame
    assert over1 == pytest.approx(over0, abs=0.01)
    assert end1 == pytest.approx(end0, abs=0.02)
