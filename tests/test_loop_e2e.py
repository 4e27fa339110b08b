"""The closed loop over MAVLink/UDP on loopback, both processes started as a user starts them.

- The paper's scenarios flown through the loop in lockstep (``serve --scenario``) reproduce the
  in-process ``fly()`` frame for frame (truth to float32 precision, the same flow counts), and
  so meet the same figures of merit as ``tests/test_scenarios.py`` (Fig. 16-18), in each sensor
  profile.
- A GCS injecting a gust by PARAM_SET ``SIM_WIND_FX = -4`` (Fig. 17's 4 N headwind) pushes the
  vehicle back 2.3-3.3 m and it stops; a GCS's velocity setpoints and sticks are followed.
- Real-time pacing (``--speedup``), the vehicle's protocol (modes, arming, validation,
  GUID_TIMEOUT, parameters, stream intervals, routing, signing) and the recordings.

Run time (2 shared cores): about 55 s for the default set (each process pair costs 1-2 s to
start; lockstep runs 150-250 frames per second); the slow set adds five full scenario runs in
the other profiles (about 50 s).
"""

from __future__ import annotations

import math
import subprocess

import numpy as np
import pytest
from loop_helpers import PY, REPO, Gcs, Procs, free_udp_port, mav

from companion.mavlink.outbound import euler_to_quaternion, quaternion_to_euler
from companion.step.profiles import Profile
from simvehicle.engines.scenarios import SCENARIOS, figures, fly
from simvehicle.server.server import recording_run

#: one float32 rounding of values up to ~30 m (truth travels in float32 fields)
F32_POS_TOL_M = 4e-6
F32_VEL_TOL_M_S = 5e-7


def _fly_loop(tmp_path, name: str, profile: str) -> tuple:
    """Lockstep loop of scenario ``name``: returns (vehicle tlog, companion tlog, logs)."""
    vt, ct = tmp_path / f"{name}_vehicle.tlog", tmp_path / f"{name}_companion.tlog"
    with Procs(tmp_path) as procs:
        veh, port = procs.vehicle("--lockstep", "--scenario", name, "--profile", profile, "--tlog", str(vt))
        comp = procs.companion(port, "--arm", "--profile", profile, "--tlog", str(ct), "--quiet")
        assert veh.wait(timeout_s=300) == 0, veh.text()
        assert comp.stop() == 0, comp.text()
        return vt, ct, veh.text(), comp.text()


@pytest.fixture(scope="module")
def step_loop(tmp_path_factory):
    return _fly_loop(tmp_path_factory.mktemp("step"), "step", "paper")


def _check_against_fly(cfg, name: str, profile: str, vehicle_tlog) -> dict:
    ref = fly(cfg, SCENARIOS[name], profile=Profile(profile))
    run = recording_run(vehicle_tlog, name=name)
    np.testing.assert_array_equal(run["t_s"], np.round(ref["t_s"] * 1e3) * 1e-3)
    # the same frames: truth to float32 precision, identical commands and flow counts
    for col, tol in (("vx_m_s", F32_VEL_TOL_M_S), ("vy_m_s", F32_VEL_TOL_M_S), ("x_m", F32_POS_TOL_M),
                     ("y_m", F32_POS_TOL_M), ("pitch_cmd_rad", 1e-6), ("roll_cmd_rad", 1e-6),
                     ("flow_x_counts", 1e-4), ("flow_y_counts", 1e-4)):
        np.testing.assert_allclose(run[col], ref[col], rtol=0, atol=tol, err_msg=col)
    return figures(run, cfg)


def _assert_paper_figures(name: str, fig: dict) -> None:
    """The thresholds of tests/test_scenarios.py (the paper's Fig. 16, 17, 18-19), both axes."""
    for axis in ("x", "y"):
        f = fig[axis]
        if name == "step":
            assert f["rise_time_10_90_s"] < 1.0
            assert f["extreme_command_deg"] == pytest.approx(-20.0 if axis == "x" else 20.0, abs=1e-4)
            assert f["final_velocity_m_s"] == pytest.approx(2.0, rel=0.02)
        elif name == "gust":
            assert -2.9 <= f["displacement_m"] <= -2.7
            assert f["final_speed_m_s"] < 0.01
            assert abs(f["held_angle_deg"]) == pytest.approx(10.0, abs=0.5)
        else:
            assert 0.6 <= f["first_count_after_command_s"] <= 0.9
            assert set(f["count_values"]) == {0, -1}
            assert 6.0 <= f["pulses_per_s"] <= 7.5
            assert f["final_velocity_cm_s"] == pytest.approx(1.0, rel=0.10)


def test_step_through_the_loop_is_the_in_process_scenario(step_loop, paper_cfg):
    vt, _ct, vlog, clog = step_loop
    fig = _check_against_fly(paper_cfg, "step", "paper", vt)
    _assert_paper_figures("step", fig)
    assert "SET_ATTITUDE_TARGET accepted: 751" in vlog  # one command per frame, none missed
    assert "lockstep frames without a command" not in vlog
    assert "751 steps" in clog


@pytest.mark.slow
@pytest.mark.parametrize("name,profile", [("gust", "ardupilot"), ("slow", "px4"), ("step", "px4"),
                                          ("gust", "paper"), ("slow", "ardupilot")])
def test_paper_scenarios_through_the_loop(tmp_path, paper_cfg, name, profile):
    vt, _ct, _vlog, _clog = _fly_loop(tmp_path, name, profile)
    _assert_paper_figures(name, _check_against_fly(paper_cfg, name, profile, vt))


def test_lockstep_recordings_are_stamped_with_simulated_time(step_loop):
    """Issue 14: the companion's lockstep recording was stamped with the wall clock (``info``: 1.3 s,
    flow at 1590 Hz). Both recordings now carry simulated time from SIM_EPOCH_S, as a SITL's log
    does: a vehicle message has the same stamp in both (its time field + the epoch), and ``info``
    says the clock is simulated (the vehicle's STATUSTEXT, which both recordings keep)."""
    from companion.recordings.load import load_recording
    from companion.recordings.tlog_writer import SIM_CLOCK_TEXT, SIM_EPOCH_S
    from companion.tools.info import summarise

    vt, ct, _vlog, _clog = step_loop
    for path in (vt, ct):
        rec = load_recording(path)
        att = rec.table("ATTITUDE").from_sender(compid=1)
        np.testing.assert_allclose(att.t_s - SIM_EPOCH_S, att["time_boot_ms"] * 1e-3, rtol=0, atol=2e-6)
        texts = [str(t) for t in rec.table("STATUSTEXT")["text"]]
        assert f"simvehicle: {SIM_CLOCK_TEXT} (lockstep)" in texts
        s = summarise(rec)
        assert s["clock"]["simulated"] is True
        assert 15.0 <= s["duration_s"] < 18.0  # 15 s flown; the companion's tail on the wall clock
        flow = next(m for m in s["messages"] if m["name"] == "OPTICAL_FLOW")
        assert flow["rate_hz"] == pytest.approx(50.0, rel=1e-3)
        # never back in time, the companion's own messages included
        assert np.all(np.diff(np.sort(np.concatenate([t.record for t in rec]))) > 0)
        order = np.argsort(np.concatenate([t.record for t in rec]))
        assert np.all(np.diff(np.concatenate([t.t_s for t in rec])[order]) >= 0)
    sat = load_recording(ct).table("SET_ATTITUDE_TARGET").from_sender(compid=191)
    in_flight = sat["time_boot_ms"] < 15_000
    # each command is stamped at the frame it answers
    np.testing.assert_allclose(sat.t_s[in_flight] - SIM_EPOCH_S, sat["time_boot_ms"][in_flight] * 1e-3, atol=2e-6)


def test_recordings_open_in_mavlogdump(step_loop):
    vt, ct, _vlog, _clog = step_loop
    n_frames = int(round(15.0 / 0.02)) + 1

    def dump(path, types):
        r = subprocess.run([PY, "-m", "pymavlink.tools.mavlogdump", "--types", types, str(path)],
                           capture_output=True, text=True, timeout=120, cwd=REPO)
        assert r.returncode == 0, r.stderr
        return r.stdout

    out = dump(vt, "OPTICAL_FLOW,RAW_IMU,SET_ATTITUDE_TARGET,LOCAL_POSITION_NED")
    for t in ("OPTICAL_FLOW", "RAW_IMU", "LOCAL_POSITION_NED"):
        assert out.count(f"{t} {{") == n_frames, t
    # received: one per frame, and the odd stale one (a wall-clock hold) the vehicle ignored
    assert n_frames <= out.count("SET_ATTITUDE_TARGET {") <= n_frames + 5
    assert "time_usec : 5000000," in out  # simulated time in the time fields
    out = dump(ct, "SET_ATTITUDE_TARGET,OPTICAL_FLOW,HEARTBEAT,VISION_SPEED_ESTIMATE")
    assert out.count("OPTICAL_FLOW {") == n_frames  # everything received ...
    assert out.count("SET_ATTITUDE_TARGET {") >= n_frames  # ... and sent
    assert "VISION_SPEED_ESTIMATE {" in out and "type : 18" in out  # our heartbeat: onboard controller


def _truth_mean(run, t0: float, t1: float) -> tuple[float, float]:
    m = (run["t_s"] >= t0) & (run["t_s"] <= t1)
    assert m.sum() > 10
    return float(run["vx_m_s"][m].mean()), float(run["vy_m_s"][m].mean())


def test_gcs_gust_by_param_set_pushes_back_and_stops(tmp_path):
    """Fig. 17 by a GCS: SIM_WIND_FX = -4 N in flight; the vehicle drifts back 2.3-3.3 m and stops."""
    vt = tmp_path / "vehicle.tlog"
    with Procs(tmp_path) as procs:
        veh, port = procs.vehicle("--lockstep", "--duration", "17", "--tlog", str(vt))
        procs.companion(port, "--arm", "--quiet")
        gcs = Gcs(port)
        try:
            gcs.wait_vehicle()
            gcs.quiet({"LOCAL_POSITION_NED": 10.0})
            gcs.wait_time(0.5)
            pv = gcs.set_param("SIM_WIND_FX", -4.0)
            assert pv.param_value == -4.0
            t_onset = gcs.vehicle_time_s
        finally:
            gcs.close()
        assert veh.wait(timeout_s=300) == 0, veh.text()
    run = recording_run(vt)
    t, x, y = run["t_s"], run["x_m"], run["y_m"]
    i0 = int(np.searchsorted(t, t_onset))
    assert abs(x[i0]) < 1e-3  # still at the origin before the gust
    assert -3.3 <= x[-1] - x[i0] <= -2.3
    last2 = t >= t[-1] - 2.0
    assert np.abs(run["vx_m_s"][last2]).max() < 0.01  # and stops there
    assert np.abs(y).max() < 1e-3  # no force on y
    held = np.degrees(run["pitch_rad"][last2].mean())
    # F = m g tan(theta): 4 N on 2.3 kg needs atan(4 / 22.56) = 10.05 deg, nose down
    assert held == pytest.approx(-math.degrees(math.atan(4.0 / (2.3 * 9.81))), abs=0.3)


def test_gcs_velocity_setpoints_and_sticks_are_followed(tmp_path):
    """A third process (this test) flies the vehicle: SET_POSITION_TARGET_LOCAL_NED to the
    companion, then MANUAL_CONTROL sticks; the vehicle's truth velocity follows both."""
    vt = tmp_path / "vehicle.tlog"
    phase1, phase2, end = (1.0, -0.5), (-0.5, 1.0), 13.0
    with Procs(tmp_path) as procs:
        veh, port = procs.vehicle("--lockstep", "--duration", str(end), "--tlog", str(vt))
        procs.companion(port, "--arm", "--quiet")
        gcs = Gcs(port)
        try:
            gcs.wait_vehicle()
            gcs.quiet({"LOCAL_POSITION_NED": 10.0})
            t_switch = None
            while gcs.vehicle_time_s < end - 0.2:
                gcs.recv("LOCAL_POSITION_NED", timeout_s=60)
                if gcs.vehicle_time_s < 6.5:
                    gcs.velocity(*phase1)
                else:
                    t_switch = t_switch or gcs.vehicle_time_s
                    # full stick = companion.max_speed_m_s (2 m/s): -250 -> -0.5 m/s, 500 -> 1.0 m/s
                    gcs.sticks(-250, 500)
        finally:
            gcs.close()
        assert veh.wait(timeout_s=300) == 0, veh.text()
    run = recording_run(vt)
    assert t_switch is not None
    # when the companion's tracked setpoint (its POSITION_TARGET_LOCAL_NED) changed
    t1 = float(run["t_s"][np.nonzero(run["vx_set_m_s"] == phase1[0])[0][0]])
    t2 = float(run["t_s"][np.nonzero(run["vx_set_m_s"] == phase2[0])[0][0]])
    assert t1 < 1.0 and t_switch <= t2 < t_switch + 1.0
    # after 5 s a PI step of size D is within 4 % of D (the closed-loop step response; 1 cm/s slack)
    for (t0, sp, prev) in ((t1, phase1, (0.0, 0.0)), (t2, phase2, phase1)):
        v = _truth_mean(run, t0 + 5.0, t0 + 5.4)
        for k in range(2):
            assert v[k] == pytest.approx(sp[k], abs=0.04 * abs(sp[k] - prev[k]) + 0.01), (sp, v)
    # the companion published the setpoints it tracked
    assert np.nanmax(run["vx_set_m_s"]) == pytest.approx(1.0, abs=1e-6)
    assert np.nanmax(run["vy_set_m_s"]) == pytest.approx(1.0, abs=1e-6)


def test_real_time_speedup_paces_the_vehicle(tmp_path):
    """--speedup 4: 12 simulated seconds take about 3 s, and --setpoint is flown."""
    port = free_udp_port()
    vt, ct = tmp_path / "vehicle.tlog", tmp_path / "companion.tlog"
    with Procs(tmp_path) as procs:
        comp = procs.companion(port, "--arm", "--setpoint", "0.8,-0.4", "--quiet", "--tlog", str(ct))
        comp.wait_for("waiting for a vehicle")
        veh, _ = procs.vehicle("--speedup", "4", "--duration", "12", "--tlog", str(vt), port=port)
        assert veh.wait(timeout_s=120) == 0, veh.text()
        wall = float(veh.wait_for(r"after ([0-9.]+) s of wall time").group(1))
    # 12 s / 4 = 3 s, never faster; slower only when a loaded machine cannot keep up
    assert 3.0 - 0.03 <= wall <= 6.0
    run = recording_run(vt)
    assert run["t_s"][-1] == pytest.approx(12.0)
    vx, vy = _truth_mean(run, 10.0, 12.0)
    assert vx == pytest.approx(0.8, abs=0.04 * 0.8 + 0.01)
    assert vy == pytest.approx(-0.4, abs=0.04 * 0.4 + 0.01)
    # sped up: both recordings in simulated time (issue 14), a vehicle message stamped alike in both
    from companion.recordings.load import load_recording
    from companion.recordings.tlog_writer import SIM_EPOCH_S
    from companion.tools.info import summarise

    for path in (vt, ct):
        rec = load_recording(path)
        att = rec.table("ATTITUDE").from_sender(compid=1)
        np.testing.assert_allclose(att.t_s - SIM_EPOCH_S, att["time_boot_ms"] * 1e-3, rtol=0, atol=2e-6)
        assert summarise(rec)["clock"]["simulated"] is True


# ---------------------------------------------------------------------------------------------
# The vehicle's protocol, with this test as the only peer (real time)


@pytest.fixture
def vehicle_port(tmp_path):
    with Procs(tmp_path) as procs:
        _veh, port = procs.vehicle()
        yield port


def _attitude_target(gcs, sat_q, *, thrust=0.5, type_mask=7):
    ms = int(max(gcs.vehicle_time_s, 0.0) * 1e3)  # real time: the vehicle does not check it
    gcs.conn.mav.set_attitude_target_send(ms, 1, 1, type_mask, sat_q, 0, 0, 0, thrust)


def test_modes_arming_attitude_targets_and_guided_timeout(vehicle_port):
    gcs = Gcs(vehicle_port)
    try:
        hb = gcs.wait_vehicle()
        assert (hb.type, hb.autopilot, hb.custom_mode) == (mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0)
        assert not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        tilted = euler_to_quaternion(0.05, -0.1, 0.0)
        _attitude_target(gcs, tilted)  # disarmed: ignored
        gcs.wait_time(gcs.vehicle_time_s + 0.1)
        at = gcs.recv("ATTITUDE_TARGET")
        assert list(at.q) == [1.0, 0.0, 0.0, 0.0]
        # no GPS: a position mode is refused; GUIDED_NOGPS by SET_MODE is acknowledged as ArduPilot does
        assert gcs.command(mav.MAV_CMD_DO_SET_MODE, 1, 5).result == mav.MAV_RESULT_DENIED
        gcs.conn.mav.set_mode_send(1, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 20)
        ack = gcs.recv("COMMAND_ACK", cond=lambda m: m.command == mav.MAVLINK_MSG_ID_SET_MODE)
        assert ack.result == mav.MAV_RESULT_ACCEPTED
        assert gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == mav.MAV_RESULT_ACCEPTED
        hb = gcs.recv("HEARTBEAT", cond=lambda m: m.get_srcComponent() == 1 and m.base_mode & 128)
        assert hb.custom_mode == 20
        # invalid targets are ignored: not a unit quaternion, thrust not finite, attitude ignored
        for q, thrust, mask in (([0.5, 0.0, 0.0, 0.0], 0.5, 7), (tilted, math.nan, 7), (tilted, 0.5, 128)):
            _attitude_target(gcs, q, thrust=thrust, type_mask=mask)
        gcs.drain(0.2)
        at = gcs.recv("ATTITUDE_TARGET")
        assert list(at.q) == [1.0, 0.0, 0.0, 0.0]
        # one valid target: tracked from the next frame, then GUID_TIMEOUT (0.5 s) levels it
        _attitude_target(gcs, tilted)
        at = gcs.recv("ATTITUDE_TARGET", cond=lambda m: m.q[0] != 1.0, timeout_s=5)
        t_on = at.time_boot_ms * 1e-3
        roll, pitch, _ = quaternion_to_euler(at.q)
        assert (roll, pitch) == (pytest.approx(0.05, abs=1e-6), pytest.approx(-0.1, abs=1e-6))
        at = gcs.recv("ATTITUDE_TARGET", cond=lambda m: m.q[0] == 1.0, timeout_s=5)
        # accepted at frame t_c, active from t_c + T; levelled at the first frame more than 0.5 s
        # after t_c (t_c + 0.52), active from t_c + 0.54: 0.5 + T after it was first tracked
        assert at.time_boot_ms * 1e-3 - t_on == pytest.approx(0.5 + 0.02, abs=1e-6)
        assert gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0).result == mav.MAV_RESULT_ACCEPTED
    finally:
        gcs.close()


def test_parameters_intervals_and_capabilities(vehicle_port):
    gcs = Gcs(vehicle_port)
    try:
        gcs.wait_vehicle()
        gcs.conn.mav.param_request_list_send(1, 1)
        first = gcs.recv("PARAM_VALUE")
        names = {first.param_id}
        while len(names) < first.param_count:
            names.add(gcs.recv("PARAM_VALUE").param_id)
        assert {"SIM_WIND_FX", "SIM_WIND_FY", "SIM_DRAG_B", "SIM_GYRO_BIAS_X", "SIM_GYRO_BIAS_Y", "SIM_FLOW_SCALE_X",
                "SIM_FLOW_SCALE_Y", "SIM_FLOW_DELAY", "SIM_FLOW_YAW", "SIM_ATT_OMEGA", "SIM_ATT_ZETA",
                "SIM_RNG_OFFSET", "SIM_FLOW_FAULT", "SIM_GYRO_FAULT", "SIM_RNG_FAULT", "SIM_REBOOT",
                "GUID_TIMEOUT"} <= names
        gcs.conn.mav.param_request_read_send(1, 1, b"SIM_ATT_OMEGA", -1)
        assert gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "SIM_ATT_OMEGA").param_value == \
            pytest.approx(5.4, rel=1e-6)  # Table VI's Omega_p
        assert gcs.set_param("SIM_FLOW_FAULT", 9).param_value == 0.0  # out of range: refused, unchanged
        gcs.wait_text("SIM_FLOW_FAULT must be in [0, 5]")
        assert gcs.set_param("SIM_WIND_FY", 2.5).param_value == 2.5
        # SET_MESSAGE_INTERVAL: ATTITUDE at 5 Hz -> consecutive ATTITUDE 200 ms apart
        gcs.quiet({"ATTITUDE": 5.0})
        gcs.drain(0.1)
        times = [gcs.recv("ATTITUDE").time_boot_ms for _ in range(4)]
        assert np.diff(times).tolist() == [200, 200, 200]
        ack = gcs.command(mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1)
        assert ack.result == mav.MAV_RESULT_ACCEPTED
        av = gcs.recv("AUTOPILOT_VERSION")
        assert av.capabilities & mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        assert av.capabilities & mav.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    finally:
        gcs.close()


def test_packets_are_routed_between_peers(vehicle_port):
    """A setpoint for component 191 reaches the peer where 191 lives and no other; a peer's
    STATUSTEXT (untargeted) reaches every other peer."""
    gcs, comp, other = Gcs(vehicle_port), Gcs(vehicle_port, sysid=1, compid=191), Gcs(vehicle_port, compid=191 - 1)
    try:
        for g in (gcs, comp, other):
            g.wait_vehicle()
            g.quiet()
        comp.conn.mav.heartbeat_send(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, 4)
        gcs.drain(0.2)
        gcs.velocity(0.7, -0.3)
        sp = comp.recv("SET_POSITION_TARGET_LOCAL_NED", timeout_s=5)
        assert (sp.vx, sp.vy, sp.target_component) == (pytest.approx(0.7), pytest.approx(-0.3), 191)
        assert not [m for m in other.drain(0.5) if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
        comp.conn.mav.statustext_send(mav.MAV_SEVERITY_INFO, b"hello from 191")
        gcs.wait_text("hello from 191", timeout_s=5)
        other.wait_text("hello from 191", timeout_s=5)
    finally:
        for g in (gcs, comp, other):
            g.close()


def test_signed_vehicle_serves_only_signed_peers(tmp_path):
    """MAVLink 2 signing: a GCS and a companion with the passphrase are served (the companion
    arms it), one without is not."""
    from companion.mavlink.link import signing_key

    words = "correct horse battery staple"
    with Procs(tmp_path) as procs:
        veh, port = procs.vehicle("--signing-key", words)
        unsigned, signed = Gcs(port), Gcs(port, key=signing_key(words))
        try:
            hb = signed.wait_vehicle(timeout_s=20)
            assert hb.get_signed()
            assert not [m for m in unsigned.drain(1.5) if m.get_type() == "HEARTBEAT"]
            procs.companion(port, "--arm", "--quiet", "--signing-key", words)
            veh.wait_for("armed GUIDED_NOGPS", timeout_s=60)
        finally:
            unsigned.close()
            signed.close()


@pytest.mark.parametrize("argv,needle", [
    (["-m", "companion", "run", "--connect", "bogus"], "--connect: not a MAVLink URL"),
    (["-m", "companion", "run", "--connect", "udpout:127.0.0.1:9", "--setpoint", "fast"], "--setpoint"),
    (["-m", "simvehicle", "serve", "--listen", "nowhere"], "--listen: expected HOST:PORT"),
    (["-m", "simvehicle", "serve", "--speedup", "-2"], "--speedup must be a positive"),
    (["-m", "simvehicle", "serve", "--max-speedup", "4"], "--max-speedup caps a --lockstep run"),
    (["-m", "simvehicle", "serve", "--lockstep", "--max-speedup", "0"], "--max-speedup must be a positive"),
])
def test_bad_command_lines_fail_in_one_line(argv, needle):
    r = subprocess.run([PY, *argv], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert r.returncode == 2
    assert needle in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def test_companion_gives_up_on_a_silent_link_in_one_line():
    """No vehicle: LinkError naming the URL after the connect timeout (library level, 0.3 s)."""
    from companion.config import load_config
    from companion.errors import LinkError
    from companion.mavlink.link import open_connection
    from companion.mavlink.live import LiveCompanion

    url = f"udpout:127.0.0.1:{free_udp_port()}"
    conn = open_connection(url, source_system=1, source_component=191)
    live = LiveCompanion(load_config(), Profile.PAPER, conn, url=url, out=lambda _s: None)
    try:
        with pytest.raises(LinkError, match="no HEARTBEAT from a vehicle on udpout:127.0.0.1"):
            live.connect(timeout_s=0.3)
    finally:
        live.close()


@pytest.mark.parametrize("profile", ["ardupilot", "px4"])
def test_other_profiles_through_the_loop_match_fly(tmp_path, paper_cfg, profile):
    """The ArduPilot and PX4 message conventions end to end: the first 5.4 s of the step scenario
    (the step at 5 s, the command at its -20 deg limit) equal fly() in that profile."""
    import dataclasses

    vt = tmp_path / "vehicle.tlog"
    with Procs(tmp_path) as procs:
        veh, port = procs.vehicle("--lockstep", "--scenario", "step", "--duration", "5.4", "--profile", profile,
                                  "--tlog", str(vt))
        comp = procs.companion(port, "--arm", "--profile", profile, "--quiet")
        assert veh.wait(timeout_s=300) == 0, veh.text()
        assert comp.stop() == 0
    ref = fly(paper_cfg, dataclasses.replace(SCENARIOS["step"], duration_s=5.4), profile=Profile(profile))
    run = recording_run(vt, name="step")
    for col, tol in (("vx_m_s", F32_VEL_TOL_M_S), ("vy_m_s", F32_VEL_TOL_M_S), ("pitch_cmd_rad", 1e-6),
                     ("roll_cmd_rad", 1e-6)):
        np.testing.assert_allclose(run[col], ref[col], rtol=0, atol=tol, err_msg=col)
    assert np.degrees(run["pitch_cmd_rad"].min()) == pytest.approx(-20.0, abs=1e-4)


def test_companion_detects_the_vehicles_profile_before_taking_control(tmp_path, paper_cfg):
    """Issue 14: without ``--profile`` the companion assumed paper and sat in "HOLD flow stale" for the
    whole flight against an ArduPilot-convention vehicle. It now tells the profile from the vehicle's
    first frames (the flow's time_usec in ms against the vehicle's clock), says which and why, and
    then flies the step exactly as fly() does in that profile."""
    import dataclasses

    vt = tmp_path / "vehicle.tlog"
    with Procs(tmp_path) as procs:
        veh, port = procs.vehicle("--lockstep", "--scenario", "step", "--duration", "5.4", "--profile", "ardupilot",
                                  "--tlog", str(vt))
        comp = procs.companion(port, "--arm", "--quiet")
        assert veh.wait(timeout_s=300) == 0, veh.text()
        assert comp.stop() == 0
    log = comp.text()
    assert "flowhold: sensor profile ardupilot (detected: OPTICAL_FLOW time_usec" in log, log
    assert "milliseconds" in log and "HEARTBEAT autopilot ArduPilot" in log
    assert log.index("sensor profile ardupilot") < log.index("flowhold: in control")
    assert "HOLD" not in log.split("flowhold: in control")[1].split("HOLD link lost")[0]
    ref = fly(paper_cfg, dataclasses.replace(SCENARIOS["step"], duration_s=5.4), profile=Profile.ARDUPILOT)
    run = recording_run(vt, name="step")
    for col, tol in (("vx_m_s", F32_VEL_TOL_M_S), ("vy_m_s", F32_VEL_TOL_M_S), ("pitch_cmd_rad", 1e-6),
                     ("roll_cmd_rad", 1e-6)):
        np.testing.assert_allclose(run[col], ref[col], rtol=0, atol=tol, err_msg=col)


def test_gcs_setpoint_is_held_then_ramps_to_the_constant_one(tmp_path, paper_cfg):
    """A GCS setpoint that stops arriving: held for companion.setpoint_timeout_s (1 s), then a
    linear ramp back to --setpoint over another second (decayed_setpoint), on the wall clock."""
    from companion.mavlink.live import decayed_setpoint
    from companion.recordings.load import load_recording

    ct = tmp_path / "companion.tlog"
    timeout = paper_cfg.companion.setpoint_timeout_s
    with Procs(tmp_path) as procs:
        _veh, port = procs.vehicle()
        comp = procs.companion(port, "--arm", "--setpoint", "0.2,0", "--quiet", "--tlog", str(ct))
        comp.wait_for("in control")
        gcs = Gcs(port)
        try:
            gcs.wait_vehicle()
            for _ in range(5):
                gcs.velocity(1.0, 0.5)
                gcs.drain(0.1)
            gcs.drain(3.0)
        finally:
            gcs.close()
        assert comp.stop() == 0
    rec = load_recording(ct)
    last_rx = float(rec.table("SET_POSITION_TARGET_LOCAL_NED").t_s[-1])
    pt = rec.table("POSITION_TARGET_LOCAL_NED").from_sender(compid=191)
    age = pt.t_s - last_rx
    m = (age > 0.05) & (age < 2.5 * timeout)
    expect = np.array([decayed_setpoint((1.0, 0.5), (0.2, 0.0), a, timeout) for a in age[m]])
    # stamps are taken a moment after the step's clock reading: 0.8 m/s per s x 15 ms
    np.testing.assert_allclose(pt["vx"][m], expect[:, 0], atol=0.02)
    np.testing.assert_allclose(pt["vy"][m], expect[:, 1], atol=0.02)
    assert pt["vx"][age > 2.2 * timeout].max() == pytest.approx(0.2, abs=1e-6)  # back on --setpoint


# ---------------------------------------------------------------------------------------------
# The live loop's pure pieces


def test_record_stamps_follow_a_simulated_vehicles_clock(tmp_path):
    """The companion's recording: the wall clock until a simulated vehicle says otherwise; then its
    time fields + SIM_EPOCH_S (what waited in memory too), carried on across a reboot, on the
    wall clock's rate once the vehicle's clock stands still, never back in time."""
    from companion.mavlink.live import RecordStamps
    from companion.recordings.load import load_recording
    from companion.recordings.tlog_writer import SIM_EPOCH_S, TlogWriter

    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    parse = mav.MAVLink(None)
    clock = [100.0]

    def msg(m):
        return parse.decode(bytearray(m.pack(enc)))

    def att(t_s):
        return msg(enc.attitude_encode(int(round(t_s * 1e3)), 0, 0, 0, 0, 0, 0))

    # a simulated vehicle: heartbeat, the notice, then frames
    st = RecordStamps(TlogWriter(tmp_path / "sim.tlog"), wall=lambda: 1.7e9 + clock[0], clock=lambda: clock[0])
    hb = msg(enc.heartbeat_encode(2, 3, 0, 0, 0))
    st.write(bytes(hb.get_msgbuf()))  # ours, before the vehicle: waits
    for m in (hb, msg(enc.statustext_encode(6, b"simvehicle: simulated clock (lockstep)")), att(0.0), att(0.02),
              att(5.0), att(0.0), att(0.02)):  # ... and a reboot: boot time back to 0
        st.observe(m)
        st.write(bytes(m.get_msgbuf()))
        clock[0] += 0.001
    clock[0] += 2.0  # the vehicle stands still for 2 s of wall time: 1.5 s after FREEZE_S
    st.write(bytes(hb.get_msgbuf()))
    st.close()
    assert st.simulated is True
    t = np.concatenate([tab.t_s for tab in load_recording(tmp_path / "sim.tlog")])
    rel = np.sort(t) - SIM_EPOCH_S
    np.testing.assert_allclose(rel, [0, 0, 0, 0, 0.02, 5.0, 5.0, 5.02, 5.02 + 1.5 + 0.001], atol=1e-5)

    # a vehicle with no notice: its sensor data comes first, the wall clock it is
    clock[0] = 100.0
    st = RecordStamps(TlogWriter(tmp_path / "real.tlog"), wall=lambda: 1.7e9 + clock[0], clock=lambda: clock[0])
    for m in (hb, att(3.0), att(3.02)):
        st.observe(m)
        st.write(bytes(m.get_msgbuf()))
        clock[0] += 0.5
    st.close()
    assert st.simulated is False
    t = np.sort(np.concatenate([tab.t_s for tab in load_recording(tmp_path / "real.tlog")]))
    np.testing.assert_allclose(t - 1.7e9, [100.0, 100.5, 101.0], atol=1e-5)


def test_decayed_setpoint_closed_form():
    from companion.mavlink.live import decayed_setpoint

    sp, base = (2.0, -1.0), (0.5, 0.0)
    assert decayed_setpoint(sp, base, 0.3, 1.0) == sp
    assert decayed_setpoint(sp, base, 1.0, 1.0) == sp
    assert decayed_setpoint(sp, base, 1.5, 1.0) == pytest.approx((1.25, -0.5))
    assert decayed_setpoint(sp, base, 2.0, 1.0) == pytest.approx(base)
    assert decayed_setpoint(sp, base, 9.0, 1.0) == pytest.approx(base)


def test_frame_order_safe_attitude_and_hold_texts():
    from companion.mavlink.live import FrameOrder, HoldMonitor, classify_frame, parse_setpoint, safe_attitude
    from companion.step.core import HoldCause

    assert classify_frame(None, 3.0) is FrameOrder.NEW
    assert classify_frame(3.0, 3.02) is FrameOrder.NEW
    assert classify_frame(3.0, 3.0) is FrameOrder.DUPLICATE
    assert classify_frame(3.0, 2.5) is FrameOrder.DUPLICATE
    assert classify_frame(3.0, 0.0) is FrameOrder.REBOOT
    lim = math.radians(20)
    assert safe_attitude(0.1, -0.2, lim) == (0.1, -0.2, True)
    assert safe_attitude(1.0, -1.0, lim) == (lim, -lim, False)
    assert safe_attitude(math.nan, 0.1, lim) == (0.0, 0.0, False)
    mon = HoldMonitor()
    assert mon.update(HoldCause.NONE) is None
    assert mon.update(HoldCause.FLOW_QUALITY) == ("flowhold: HOLD flow quality 0", mav.MAV_SEVERITY_WARNING)
    assert mon.update(HoldCause.FLOW_QUALITY) is None  # once per episode
    assert mon.update(HoldCause.RANGE_STALE)[0] == "flowhold: HOLD range stale"  # the cause changed
    assert mon.update(HoldCause.NONE) == ("flowhold: resumed", mav.MAV_SEVERITY_NOTICE)
    assert mon.episodes == 1
    assert parse_setpoint(" 1.5,-0.25") == (1.5, -0.25)
    from companion.errors import UsageError

    for bad in ("1.5", "a,b", "1,2,3", "nan,0", "inf,1"):
        with pytest.raises(UsageError):
            parse_setpoint(bad)


def test_text_limiter_holds_back_a_flapping_cause_and_ends_with_the_current_state():
    from companion.mavlink.live import STATUSTEXT_LEN, TextLimiter

    lim = TextLimiter(repeat_s=1.0, burst=4, rate_hz=2.0)
    hold, ok = "flowhold: HOLD flow quality 0", "flowhold: resumed"
    # a cause that comes and goes every frame: each text once, then held back
    sent = [lim.offer(0.02 * k, hold if k % 2 == 0 else ok, 4 if k % 2 == 0 else 5) for k in range(20)]
    assert sent[:2] == [(hold, 4), (ok, 5)] and sent[2:] == [None] * 18
    assert lim.poll(0.5) is None  # the same text again within repeat_s
    assert lim.poll(1.1) == (ok + " (+17 held back)", 5)  # the latest state, and how many never went out
    assert lim.poll(5.0) is None and lim.dropped == 17
    # a new cause is said at once, even right after another one
    assert lim.offer(5.0, "flowhold: HOLD flow spike", 4) == ("flowhold: HOLD flow spike", 4)
    assert lim.offer(5.02, "flowhold: HOLD range stale", 4) == ("flowhold: HOLD range stale", 4)
    # many causes at once: the token bucket caps them; the count survives a long text's cut
    lim = TextLimiter(repeat_s=1.0, burst=2, rate_hz=1.0)
    texts = [f"{'y' * 48}{k}" for k in range(5)]
    assert [lim.offer(0.0, t, 4) for t in texts] == [(texts[0], 4), (texts[1], 4), None, None, None]
    text, _sev = lim.poll(1.0)
    assert len(text) == STATUSTEXT_LEN and text.endswith(" (+2 held back)")


def test_companion_announces_control_holds_and_release_to_the_gcs(tmp_path):
    """Issue 14: README and docs/ardupilot.md say the companion announces taking and releasing
    control as STATUSTEXT; it only printed them. Over UDP, a ground station receives from (1, 191):
    in control (NOTICE), a hold with its cause (WARNING), resumed (NOTICE), released (NOTICE)."""
    with Procs(tmp_path) as procs:
        _veh, port = procs.vehicle()
        gcs = Gcs(port)
        try:
            gcs.wait_vehicle()
            gcs.quiet()
            procs.companion(port, "--arm", "--quiet")

            def text(needle):
                return gcs.recv("STATUSTEXT", timeout_s=60, cond=lambda m: needle in m.text)

            m = text("flowhold: in control")
            assert (m.get_srcSystem(), m.get_srcComponent()) == (1, 191)
            assert (m.text, m.severity) == ("flowhold: in control (GUIDED_NOGPS)", mav.MAV_SEVERITY_NOTICE)
            gcs.set_param("SIM_FLOW_FAULT", 1)
            m = text("flowhold: HOLD")
            assert (m.text, m.severity, m.get_srcComponent()) == ("flowhold: HOLD flow quality 0",
                                                                  mav.MAV_SEVERITY_WARNING, 191)
            gcs.set_param("SIM_FLOW_FAULT", 0)
            m = text("flowhold: resumed")
            assert (m.severity, m.get_srcComponent()) == (mav.MAV_SEVERITY_NOTICE, 191)
            ack = gcs.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 2)  # ALT_HOLD
            assert ack.result == mav.MAV_RESULT_ACCEPTED
            m = text("flowhold: released control")
            assert (m.text, m.severity, m.get_srcComponent()) == ("flowhold: released control (ALT_HOLD)",
                                                                  mav.MAV_SEVERITY_NOTICE, 191)
        finally:
            gcs.close()


def test_stream_schedule_and_faults_are_pure(paper_cfg):
    from simvehicle.model.sim import Simulator
    from simvehicle.server.server import FlowFault, GyroFault, RangeFault, StreamSchedule, faulted_sensors

    sched = StreamSchedule(0.02)
    assert [sched.due(30, k) for k in range(3)] == [True, True, True]  # default: every frame (50 Hz)
    sched.set(30, 0.1)
    assert [k for k in range(3, 23) if sched.due(30, k)] == [7, 12, 17, 22]  # 10 Hz
    sched.set(30, -1.0)
    assert not any(sched.due(30, k) for k in range(23, 40))
    assert sched.interval_s(mav.MAVLINK_MSG_ID_SYS_STATUS) == 1.0
    s = Simulator(paper_cfg).current
    kw = dict(spike_counts=500, last_flow=None, last_gyro=None, range_max_m=4.0, gyro_range_rad_s=34.9)
    f = faulted_sensors(s, flow_fault=FlowFault.SPIKE, gyro_fault=GyroFault.SATURATED,
                        range_fault=RangeFault.TOO_FAR, **kw)
    assert (f.flow.flow_x_counts, f.flow.flow_y_counts) == (500, 500)
    assert f.gyro.gyro_x_rad_s == 34.9 and f.range.range_m == 5.0
    f = faulted_sensors(s, flow_fault=FlowFault.STOPPED, gyro_fault=GyroFault.STOPPED,
                        range_fault=RangeFault.STOPPED, **kw)
    assert (f.flow, f.gyro, f.range) == (None, None, None)


def test_every_vehicle_parameter_is_documented(paper_cfg):
    from simvehicle.server.server import param_specs

    doc = (REPO / "docs" / "loop.md").read_text()
    for p in param_specs(paper_cfg):
        assert f"| `{p.name}` | {p.default:g} |" in doc, p.name


def test_effect_parameters_reach_the_simulator_in_flight(paper_cfg):
    """PARAM_SET on the vehicle model (no sockets): each effect acts from the next frame."""
    from simvehicle.server.server import Vehicle

    v = Vehicle(paper_cfg)
    for _ in range(10):
        v.advance()
    assert v.set_param("SIM_GYRO_BIAS_X", 0.01)[0].msg.param_value == pytest.approx(0.01)
    v.set_param("SIM_RNG_OFFSET", 0.3)
    v.set_param("SIM_DRAG_B", 0.2)
    v.set_param("SIM_ATT_OMEGA", 4.0)
    v.set_param("SIM_FLOW_SCALE_X", 2.0)
    v.advance()
    msgs = dict(v.frame().messages)
    assert msgs["RAW_IMU"].xgyro == 10  # mrad/s
    assert msgs["DISTANCE_SENSOR"].current_distance == 130  # cm: 1 m + 0.3 m
    assert (v.sim.params.drag_b_n_s_per_m, v.sim.params.omega_p_rad_s) == (0.2, 4.0)
    assert v.sim.q_x == pytest.approx(2.0 * paper_cfg.flow_sensor.q_rad_per_count)
    assert v.sim.cfg.effects.active() == ["linear_drag", "gyro_bias", "flow_scale", "attitude_dynamics",
                                          "range_offset"]
    v.set_param("SIM_ATT_OMEGA", paper_cfg.airframe.omega_p_rad_s)  # back to Table VI: the effect is off
    assert "attitude_dynamics" not in v.sim.cfg.effects.active()
    assert v.set_param("SIM_DRAG_B", -1.0)[0].msg.param_value == pytest.approx(0.2)  # refused, unchanged
