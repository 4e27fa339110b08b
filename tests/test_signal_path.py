"""One signal path from a recording (issue 13): every gyro message of the contract gives the same
signals to replay, diagnose and the sensor-only diagnosis; one vehicle-id rule for all three (the
most frequent flow sender, ``companion.recordings.columnar.vehicle_sysid``); the simulated vehicle's
recording run reads the flow with the flight's own parameter set."""

from __future__ import annotations

import dataclasses
import os
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from companion.config import Config, replace_section
from companion.diagnose.closed_loop.channels import extract
from companion.diagnose.closed_loop.diagnosis import diagnose
from companion.diagnose.sensor.api import extract_series
from companion.mavlink.inbound import gyro_time_s
from companion.recordings import signals
from companion.recordings.columnar import MessageTable, Recording, vehicle_sysid
from companion.recordings.load import load_recording
from companion.step.profiles import GYRO_MESSAGES, Profile
from companion.tools.replay import replay
from simvehicle.engines.scenarios import run_named
from simvehicle.server.server import recording_run

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402


def _rewrite(src: Path, dst: Path, change: Callable[[Any], list[tuple[float, bytes]]]) -> Path:
    """Copy the .tlog ``src`` to ``dst``, each message replaced by ``change(msg)``: a list of
    (record time s, packet bytes)."""
    conn = mavutil.mavlink_connection(str(src), dialect="ardupilotmega")
    with dst.open("wb") as out:
        while (msg := conn.recv_msg()) is not None:
            for t, buf in change(msg):
                out.write(struct.pack(">Q", int(round(t * 1e6))) + buf)
    conn.close()
    return dst


def _same(msg: Any) -> list[tuple[float, bytes]]:
    return [(msg._timestamp, bytes(msg.get_msgbuf()))]


@pytest.fixture(scope="module")
def gust(tmp_path_factory, paper_cfg) -> Path:
    path = tmp_path_factory.mktemp("signal") / "gust.tlog"
    run_named("gust", paper_cfg, profile=Profile.PAPER, seed=0, tlog=str(path))
    return path


@pytest.fixture(scope="module")
def gust_scaled(gust) -> Path:
    """The gust flight with its RAW_IMU sent as SCALED_IMU (time_boot_ms, the same mrad/s)."""
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)

    def scaled(msg: Any) -> list[tuple[float, bytes]]:
        if msg.get_type() != "RAW_IMU":
            return _same(msg)
        assert msg.time_usec % 1000 == 0
        new = enc.scaled_imu_encode(msg.time_usec // 1000, msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro,
                                    msg.zgyro, 0, 0, 0)
        return [(msg._timestamp, bytes(new.pack(enc)))]

    return _rewrite(gust, gust.with_name("gust_scaled.tlog"), scaled)


def _with_strays(src: Path, dst: Path, encode: Any) -> Path:
    """``src`` rewritten to ``dst`` with five messages from another system (7) first, at the
    recording's first record time: ``encode(enc, k)`` makes the k-th."""
    enc = mav.MAVLink(None, srcSystem=7, srcComponent=1)
    first = [True]

    def stray(msg: Any) -> list[tuple[float, bytes]]:
        out = []
        if first[0]:
            first[0] = False
            out = [(msg._timestamp, bytes(encode(enc, k).pack(enc))) for k in range(5)]
        return out + _same(msg)

    return _rewrite(src, dst, stray)


@pytest.fixture(scope="module")
def gust_stray(gust) -> Path:
    """The gust flight with five OPTICAL_FLOW messages from another system (7) first, at the
    recording's first record time: replay took the first flow sender as the vehicle."""
    return _with_strays(gust, gust.with_name("gust_stray.tlog"),
                        lambda enc, k: enc.optical_flow_encode(k, 0, 90, -90, 0.0, 0.0, 255, 1.0))


@pytest.fixture(scope="module")
def gust_vehicle_target(gust) -> Path:
    """The gust flight with the companion's POSITION_TARGET_LOCAL_NED sent by the autopilot's
    component (1) instead: a vehicle's position-controller target, not the companion's setpoint."""
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)

    def move(msg: Any) -> list[tuple[float, bytes]]:
        if msg.get_type() != "POSITION_TARGET_LOCAL_NED":
            return _same(msg)
        new = enc.position_target_local_ned_encode(msg.time_boot_ms, msg.coordinate_frame, msg.type_mask, msg.x,
                                                   msg.y, msg.z, msg.vx, msg.vy, msg.vz, msg.afx, msg.afy, msg.afz,
                                                   msg.yaw, msg.yaw_rate)
        return [(msg._timestamp, bytes(new.pack(enc)))]

    return _rewrite(gust, gust.with_name("gust_vehicle_target.tlog"), move)


@pytest.fixture(scope="module")
def gust_scaled_stray_raw(gust_scaled) -> Path:
    """The SCALED_IMU gust flight with five RAW_IMU messages from another system (7) first: RAW_IMU
    comes first in the order of preference, but these are not the vehicle's gyro."""
    return _with_strays(gust_scaled, gust_scaled.with_name("gust_scaled_stray_raw.tlog"),
                        lambda enc, k: enc.raw_imu_encode(k, 0, 0, -1000, 500, 500, 500, 0, 0, 0))


#: the RAW_IMU samples (1-based) whose x gyro is set to its int16 limit in ``gust_clipped`` (8 s and 16 s)
CLIPPED = (401, 801)


@pytest.fixture(scope="module")
def gust_clipped(gust) -> Path:
    """The gust flight with the x gyro of two RAW_IMU at its int16 limit (clipped)."""
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    k = [0]

    def clip(msg: Any) -> list[tuple[float, bytes]]:
        if msg.get_type() != "RAW_IMU":
            return _same(msg)
        k[0] += 1
        x = 32767 if k[0] in CLIPPED else msg.xgyro
        new = enc.raw_imu_encode(msg.time_usec, msg.xacc, msg.yacc, msg.zacc, x, msg.ygyro, msg.zgyro, msg.xmag,
                                 msg.ymag, msg.zmag)
        return [(msg._timestamp, bytes(new.pack(enc)))]

    return _rewrite(gust, gust.with_name("gust_clipped.tlog"), clip)


def _assert_replays_equal(a: Any, b: Any) -> None:
    assert sorted(a.columns) == sorted(b.columns)
    for key in a.columns:
        assert_array_equal(a.columns[key], b.columns[key], err_msg=key)


def _report(rec: Any, cfg: Config) -> dict[str, Any]:
    rep = diagnose(rec, cfg).report.to_json()
    rep.pop("recording")
    rep["notes"] = [n for n in rep.get("notes", []) if not n.startswith("diagnosed in")]
    return rep


def _series(rec: Any, cfg: Config) -> dict[str, Any]:
    s = dataclasses.asdict(extract_series(rec, cfg))
    s.pop("name")
    return s


def _assert_series_equal(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert a.keys() == b.keys()
    for key, value in a.items():
        if isinstance(value, np.ndarray):
            assert_array_equal(value, b[key], err_msg=key)
        else:
            assert value == b[key], key


def test_a_scaled_imu_gyro_gives_the_raw_imu_signals(gust, gust_scaled, paper_cfg):
    """SCALED_IMU (time_boot_ms) is a gyro of the contract as RAW_IMU (time_usec) is: replay, the
    closed-loop diagnosis and the sensor-only diagnosis see the same signals and say the same."""
    raw, scaled = load_recording(gust), load_recording(gust_scaled)
    assert "RAW_IMU" not in scaled and len(scaled.table("SCALED_IMU")) == len(raw.table("RAW_IMU")) > 1000
    _assert_replays_equal(replay(scaled, paper_cfg, Profile.PAPER), replay(raw, paper_cfg, Profile.PAPER))
    rep = _report(scaled, paper_cfg)
    assert rep == _report(raw, paper_cfg)
    assert [f["effect"] for f in rep["findings"] if f["significant"]] == ["wind_force"]
    _assert_series_equal(_series(scaled, paper_cfg), _series(raw, paper_cfg))


def test_the_vehicle_is_the_most_frequent_flow_sender_everywhere(gust, gust_stray, paper_cfg):
    """Five flow messages from another system ahead of the vehicle's 1251: replay (which took the
    first sender), the closed-loop and the sensor-only diagnosis all take system 1, and say the
    same as for the clean recording."""
    clean, stray = load_recording(gust), load_recording(gust_stray)
    flow = stray.table("OPTICAL_FLOW")
    assert int(flow.sysid[0]) == 7 and vehicle_sysid(flow) == 1
    res = replay(stray, paper_cfg, Profile.PAPER)
    assert "ignored 5 OPTICAL_FLOW messages from systems other than 1" in res.notes
    _assert_replays_equal(res, replay(clean, paper_cfg, Profile.PAPER))
    assert _report(stray, paper_cfg) == _report(clean, paper_cfg)
    _assert_series_equal(_series(stray, paper_cfg), _series(clean, paper_cfg))


def test_another_systems_gyro_is_not_the_vehicles(gust, gust_scaled_stray_raw, paper_cfg):
    """Five RAW_IMU from system 7 beside the vehicle's SCALED_IMU: the analyses took the first gyro
    message of the recording (RAW_IMU, none of it the vehicle's: diagnose found no usable frame, the
    sensor-only diagnosis an empty gyro); they now take the vehicle's own
    (companion.recordings.signals.gyro_sensor), and so see the RAW_IMU recording's signals and say the same."""
    raw, rec = load_recording(gust), load_recording(gust_scaled_stray_raw)
    assert len(rec.table("RAW_IMU")) == 5 and set(rec.table("RAW_IMU").sysid.tolist()) == {7}
    _assert_replays_equal(replay(rec, paper_cfg, Profile.PAPER), replay(raw, paper_cfg, Profile.PAPER))
    assert _report(rec, paper_cfg) == _report(raw, paper_cfg)
    _assert_series_equal(_series(rec, paper_cfg), _series(raw, paper_cfg))


def test_a_clipped_gyro_sample_is_unknown_everywhere(gust, gust_clipped, paper_cfg):
    """An int16 mrad/s gyro field at 32767 has clipped: the rate is unknown. Replay (the live
    loop's rule) holds the frames aligned with such a sample; the sensor-only diagnosis leaves the
    sample out and the closed-loop diagnosis the frame it is nearest (both read 32.8 rad/s)."""
    clean, rec = load_recording(gust), load_recording(gust_clipped)
    n_clipped = int(np.count_nonzero(rec.table("RAW_IMU")["xgyro"] == 32767))
    assert n_clipped == len(CLIPPED)
    res = replay(rec, paper_cfg, Profile.PAPER)
    assert np.count_nonzero(res["hold_cause"] == "GYRO_INVALID") == n_clipped
    s, ref = extract_series(rec, paper_cfg), extract_series(clean, paper_cfg)
    assert len(s.gyro_t_s) == len(ref.gyro_t_s) - n_clipped and np.all(np.isfinite(s.gyro_rad_s))
    assert np.abs(s.gyro_rad_s).max() < 30.0
    keep = np.isin(ref.gyro_t_s, s.gyro_t_s)
    assert_array_equal(s.gyro_rad_s, ref.gyro_rad_s[keep])
    d, ref_d = extract(rec, paper_cfg), extract(clean, paper_cfg)
    assert d.n == ref_d.n - n_clipped and np.abs(d.gyro_x_rad_s).max() < 30.0
    kept = np.isin(ref_d.t_s, d.t_s)
    assert_array_equal(d.gyro_x_rad_s, ref_d.gyro_x_rad_s[kept])
    assert_array_equal(np.diff(d.seg) != 0, np.diff(np.flatnonzero(kept)) != 1)  # split where a frame went


def test_a_vehicles_position_target_is_not_the_companions_setpoint(gust, gust_vehicle_target, paper_cfg):
    """POSITION_TARGET_LOCAL_NED is the companion's (component 191, CONVENTIONS.md); diagnose took
    anyone's when the companion sent none, replay and the recording run only the companion's."""
    d = extract(load_recording(gust_vehicle_target), paper_cfg)
    assert np.all(np.isnan(d.vx_set_m_s)) and np.all(np.isnan(d.vy_set_m_s))
    assert np.all(np.isnan(recording_run(gust_vehicle_target)["vx_set_m_s"]))
    assert np.any(np.isfinite(extract(load_recording(gust), paper_cfg).vx_set_m_s))


def _assert_runs_equal(a: Any, b: Any) -> None:
    assert sorted(a.columns) == sorted(b.columns)
    for key in a.columns:
        assert_array_equal(a.columns[key], b.columns[key], err_msg=key)


def test_recording_run_takes_every_gyro_message_and_the_vehicle_by_its_flow(gust, gust_scaled, gust_stray,
                                                                             gust_clipped):
    """simvehicle.server.server.recording_run reads the recording through companion.recordings.signals: a SCALED_IMU
    gyro gives the RAW_IMU columns (it read RAW_IMU only: NaN); stray flow messages from another
    system's autopilot component are not the vehicle's (it took component 1 of any system: the
    first frame's counts were the stray message's); a clipped gyro sample is unknown (NaN)."""
    clean = recording_run(gust)
    assert np.all(np.isfinite(clean["gyro_x_rad_s"])) and np.all(np.isfinite(clean["flow_x_counts"]))
    _assert_runs_equal(recording_run(gust_scaled), clean)
    _assert_runs_equal(recording_run(gust_stray), clean)
    clipped = recording_run(gust_clipped)
    bad = np.isnan(clipped["gyro_x_rad_s"])
    assert np.count_nonzero(bad) == len(CLIPPED)
    assert_array_equal(np.isnan(clipped["gyro_y_rad_s"]), bad)
    assert_array_equal(clipped["gyro_x_rad_s"][~bad], clean["gyro_x_rad_s"][~bad])


def _flow(sysids: list[int]) -> MessageTable:
    n = len(sysids)
    return MessageTable("OPTICAL_FLOW", np.arange(n, dtype=float), np.array(sysids, np.uint8), np.ones(n, np.uint8),
                        np.arange(n, dtype=np.int64))


@pytest.mark.parametrize("sysids,vehicle", [([1, 1, 1], 1), ([7, 1, 1, 1], 1), ([7, 1, 7, 1], 7), ([1, 7, 7, 1], 1),
                                            ([3, 7, 7, 3, 7], 7)])
def test_vehicle_sysid_most_frequent_then_first(sysids, vehicle):
    assert vehicle_sysid(_flow(sysids)) == vehicle


@pytest.mark.parametrize("profile", [Profile.ARDUPILOT, Profile.PX4])
def test_recording_run_reads_the_flow_with_the_flights_config(tmp_path, paper_cfg, profile):
    """The recording run turns the ardupilot and px4 profiles' flow (rad) into counts with Q: the
    counts are the flight's own with the config it flew with, not with Table VI's Q."""
    cfg = replace_section(paper_cfg, "flow_sensor", q_rad_per_count=0.0015)
    tlog = tmp_path / "step.tlog"
    run = run_named("step", cfg, profile=profile, seed=0, tlog=str(tlog))
    flown = recording_run(tlog, config=cfg)
    n = len(run.columns["t_s"])
    assert len(flown.columns["t_s"]) == n
    assert_array_equal(flown.columns["flow_x_counts"], run.columns["flow_x_counts"])
    assert_array_equal(flown.columns["flow_y_counts"], run.columns["flow_y_counts"])
    nominal = recording_run(tlog)  # Table VI's Q: other counts
    assert np.nanmax(np.abs(nominal.columns["flow_x_counts"] - run.columns["flow_x_counts"])) >= 1.0


def _table(name: str, records: list[int], sysid: int = 1, compid: int = 1, **fields: Any) -> MessageTable:
    n = len(records)
    return MessageTable(name, np.arange(n, dtype=float), np.full(n, sysid, np.uint8), np.full(n, compid, np.uint8),
                        np.array(records, np.int64), {k: np.asarray(v) for k, v in fields.items()})


def test_signals_every_gyro_message_in_si_units_on_its_own_time_field():
    """companion.recordings.signals: RAW_IMU (mrad/s, time_usec), SCALED_IMU (mrad/s, time_boot_ms) and
    HIGHRES_IMU (rad/s, time_usec) give the same rad/s and seconds; an int16 field at 32767 has
    clipped (x and y NaN, as the live loop has it); as received they merge in arrival order, as
    one sensor the first of the three the vehicle sent; another system's gyro is not the vehicle's."""
    i16 = np.int16
    raw = _table("RAW_IMU", [0, 3], time_usec=np.array([1_000_000, 1_040_000], np.uint64),
                 xgyro=np.array([25, 32767], i16), ygyro=np.array([-40, 1], i16), zgyro=np.array([3, -32767], i16),
                 xacc=np.array([0, 10], i16), yacc=np.array([0, 0], i16), zacc=np.array([-1000, -1000], i16))
    scaled = _table("SCALED_IMU", [1], time_boot_ms=np.array([1021], np.uint32), xgyro=np.array([25], i16),
                    ygyro=np.array([-40], i16), zgyro=np.array([3], i16))
    highres = _table("HIGHRES_IMU", [2], time_usec=np.array([1_030_000], np.uint64),
                     xgyro=np.array([0.025], np.float32), ygyro=np.array([-0.04], np.float32),
                     zgyro=np.array([0.003], np.float32))
    stray = _table("SCALED_IMU", [4], sysid=7, time_boot_ms=np.array([9], np.uint32), xgyro=np.array([1], i16),
                   ygyro=np.array([1], i16), zgyro=np.array([1], i16))
    other = MessageTable("SCALED_IMU", *(np.concatenate([getattr(scaled, k), getattr(stray, k)])
                                         for k in ("t_s", "sysid", "compid", "record")),
                         {k: np.concatenate([scaled.fields[k], stray.fields[k]]) for k in scaled.fields})
    rec = Recording("x.tlog", {"RAW_IMU": raw, "SCALED_IMU": other, "HIGHRES_IMU": highres}, "tlog")
    g = signals.gyro_as_received(rec, 1)
    assert g.names == ("RAW_IMU", "SCALED_IMU", "HIGHRES_IMU")
    assert_array_equal(g.record, [0, 1, 2, 3])
    np.testing.assert_allclose(g.time_s, [1.0, 1.021, 1.03, 1.04], rtol=0, atol=1e-12)
    assert_array_equal(g.time_ms, [1000, 1021, 1030, 1040])
    assert g.time_s[1] == 1_021_000 * 1e-6 != 1021 * 1e-3  # through microseconds: a RAW_IMU's time of that instant
    np.testing.assert_allclose(g.x_rad_s[:3], 0.025, rtol=0, atol=1e-8)
    np.testing.assert_allclose(g.y_rad_s[:3], -0.04, rtol=0, atol=1e-8)
    assert np.isnan(g.x_rad_s[3]) and np.isnan(g.y_rad_s[3]) and np.isnan(g.z_rad_s[3])  # clipped
    assert g.accel_m_s2 is None  # SCALED_IMU and HIGHRES_IMU were sent without accelerometer fields here
    one = signals.gyro_sensor(rec, 1)
    assert one.names == ("RAW_IMU",) and len(one) == 2
    np.testing.assert_allclose(one.accel_m_s2, [[0, 0, -9.80665], [0.0980665, 0, -9.80665]], rtol=1e-12)
    assert signals.gyro_sensor(rec, 7).names == ("SCALED_IMU",)
    assert len(signals.gyro_as_received(rec, 5)) == 0 and signals.gyro_sensor(rec, 5).names == ()


def test_signals_senders_range_and_commands():
    """The vehicle's messages are its system's; the companion's those of component 191 (any
    system); DISTANCE_SENSOR facing down only, cm -> m, invalid outside [min, max]; a companion
    command's angles from its quaternion, its time as whole ms (a microsecond field rounded)."""
    ds = _table("DISTANCE_SENSOR", [0, 1, 2, 3], sysid=1, time_boot_ms=np.array([10, 20, 30, 40], np.uint32),
                current_distance=np.array([100, 5, 120, 300], np.uint16), min_distance=np.full(4, 10, np.uint16),
                max_distance=np.full(4, 400, np.uint16), orientation=np.array([25, 25, 0, 25], np.uint8))
    q = np.array([[np.cos(0.05), np.sin(0.05), 0.0, 0.0]], np.float32)  # roll 0.1 rad
    sat = _table("SET_ATTITUDE_TARGET", [5], sysid=1, compid=191, time_boot_ms=np.array([40], np.uint32), q=q)
    vse = _table("VISION_SPEED_ESTIMATE", [6, 7], sysid=1, compid=191, usec=np.array([40_400, 40_600], np.uint64),
                 x=np.zeros(2, np.float32), y=np.zeros(2, np.float32))
    rec = Recording("x.tlog", {"DISTANCE_SENSOR": ds, "SET_ATTITUDE_TARGET": sat, "VISION_SPEED_ESTIMATE": vse},
                    "tlog")
    r = signals.downward_range(rec, 1)
    assert r is not None
    assert_array_equal(r.record, [0, 1, 3])
    np.testing.assert_allclose(r.time_s, [0.01, 0.02, 0.04])
    assert_array_equal(r.valid, [True, False, True])
    np.testing.assert_allclose(r.reading_m, [1.0, 0.05, 3.0])
    assert_array_equal(np.isnan(r.range_m), [False, True, False])
    assert signals.downward_range(rec, 2) is None
    assert signals.vehicle_table(rec, "SET_ATTITUDE_TARGET", 1) is not None  # its system's, component aside
    cmd = signals.companion_commands(rec)
    assert cmd is not None
    np.testing.assert_allclose([cmd.roll[0], cmd.pitch[0]], [0.1, 0.0], atol=1e-7)
    est = signals.companion_table(rec, "VISION_SPEED_ESTIMATE")
    assert est is not None
    assert_array_equal(signals.time_ms(est), [40, 41])
    assert signals.companion_table(rec, "DISTANCE_SENSOR") is None


def test_the_live_loop_reads_a_gyro_message_by_the_same_rules():
    """The live router (one message) and companion.recordings.signals (columns) share the time-field table,
    the units and the clip limit (profiles.TIME_FIELDS, GYRO_MESSAGES, INT16_CLIP)."""
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    msgs = [enc.raw_imu_encode(1_235_000, 0, 0, -1000, 25, -40, 3, 0, 0, 0),
            enc.scaled_imu_encode(1235, 0, 0, -1000, 25, -40, 3, 0, 0, 0),
            enc.highres_imu_encode(1_235_000, 0.0, 0.0, -9.8, 0.025, -0.04, 0.003, 0, 0, 0, 0, 0, 0, 0, 0)]
    for m in msgs:
        m = mav.MAVLink(None).decode(bytearray(m.pack(enc)))
        name = m.get_type()
        table = _table(name, [0], **{k: np.array([getattr(m, k)]) for k in m.get_fieldnames()})
        assert gyro_time_s(m) == signals.time_s(table)[0] == 1_235_000 * 1e-6  # one instant, one time
        g = signals.GyroSamples([table])
        assert (g.x_rad_s[0], g.y_rad_s[0]) == (m.xgyro * GYRO_MESSAGES[name], m.ygyro * GYRO_MESSAGES[name])
    assert 1235 * 1e-3 != 1_235_000 * 1e-6  # (which the milliseconds alone would not give)
