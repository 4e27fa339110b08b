"""DataFlash and ULog importers: planted values, sign conventions, and failure modes.

The recordings in tests/data/importers/ are made by make_fixtures.py from a planted truth
(piecewise-constant body velocity ``vx, vy``, body rates ``wx, wy, wz``, height ``A``), with the
flow synthesised in each autopilot's own convention. Here the imported columns are checked
against the planted values after the documented unit/sign mapping, and the ``ardupilot`` /
``px4`` profiles are checked against the paper's scene-angle increments computed directly from
CONVENTIONS.md: ``dphi_x = (-omega_y - V_x / A) dt``, ``dphi_y = (+omega_x - V_y / A) dt``.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from companion.errors import RecordingError
from companion.recordings.importers.dataflash import read_dataflash
from companion.recordings.importers.ulog import read_ulog
from companion.recordings.load import Recording, load_recording
from companion.rotation import euler_to_quaternions, quaternions_to_euler
from companion.step.estimator import scene_rate, velocity_from_flow
from companion.step.profiles import Profile, flow_columns

DATA = Path(__file__).parent / "data" / "importers"
BIN = DATA / "copter_flow.bin"
ULG = DATA / "px4_flow.ulg"
Q_PAPER = 0.09 / 57.3  # rad/count; unused by the ardupilot/px4 profiles


def _load_generator():
    spec = importlib.util.spec_from_file_location("make_fixtures", DATA / "make_fixtures.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["make_fixtures"] = module  # dataclasses resolve their module by name
    spec.loader.exec_module(module)
    return module


mf = _load_generator()


@pytest.fixture(scope="module")
def df() -> Recording:
    return read_dataflash(BIN)


@pytest.fixture(scope="module")
def ul() -> Recording:
    return read_ulog(ULG)


def _segments_at(truth, t_us: np.ndarray) -> dict[str, np.ndarray]:
    """Planted vx, vy, wx, wy, wz, A in force at each time (us)."""
    segs = [truth.at(float(t)) for t in t_us]
    return {k: np.array([getattr(s, k) for s in segs]) for k in ("vx", "vy", "wx", "wy", "wz", "A")}


def _paper_increments(truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CONVENTIONS.md eq. 5-6 over each flow frame k >= 1: (dphi_x, dphi_y, dt_s)."""
    t = np.array(truth.frame_times_us(), dtype=np.int64)
    s = _segments_at(truth, t[1:])
    dt = np.diff(t) * 1e-6
    dphi_x = (-s["wy"] - s["vx"] / s["A"]) * dt
    dphi_y = (+s["wx"] - s["vy"] / s["A"]) * dt
    return dphi_x, dphi_y, dt


def _angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi


def _check_record_order(rec: Recording) -> None:
    t = np.concatenate([tab.t_s for tab in rec])
    r = np.concatenate([tab.record for tab in rec])
    assert_array_equal(np.sort(r), np.arange(len(r)))
    assert np.all(np.diff(t[np.argsort(r)]) >= 0)
    for tab in rec:
        assert np.all(np.diff(tab.record) > 0), tab.name
        assert np.all(tab.sysid == 1) and np.all(tab.compid == 1)


# --------------------------------------------------------------------------- DataFlash


def test_dataflash_recording_shape(df: Recording) -> None:
    assert df.source_format == "dataflash" and df.profile_hint == "ardupilot"
    assert df.skipped_bytes == 0
    assert set(df.tables) == {"OPTICAL_FLOW", "RAW_IMU", "DISTANCE_SENSOR", "ATTITUDE", "ATTITUDE_TARGET", "RATE"}
    assert len(df.table("OPTICAL_FLOW")) == mf.DF_TRUTH.n_frames + 1
    assert df.notes == ["IMU: instances [0, 1] present, using I=0"]
    assert df.t0_s == pytest.approx(mf.DF_TRUTH.t0_us * 1e-6)


def test_dataflash_matches_pymavlink_dfreader(df: Recording) -> None:
    """The numpy decoder and the mapping agree with pymavlink's own message objects."""
    from pymavlink import DFReader

    reader = DFReader.DFReader_binary(str(BIN))
    rows: dict[str, list] = {"OF": [], "IMU": [], "RFND": [], "ATT": [], "RATE": []}
    try:
        while (m := reader.recv_match(type=list(rows))) is not None:
            rows[m.get_type()].append(m)
    finally:
        reader.close()
    of, imu = rows["OF"], [m for m in rows["IMU"] if m.I == 0]
    t = df.table("OPTICAL_FLOW")
    assert_allclose(t["flow_rate_x"], [m.flowX for m in of], rtol=0, atol=0)
    assert_allclose(t["flow_rate_y"], [m.flowY for m in of], rtol=0, atol=0)
    assert_allclose(t["flow_comp_m_x"], [m.flowX - m.bodyX for m in of], rtol=0, atol=1e-15)
    assert_array_equal(t["quality"], [m.Qual for m in of])
    assert_allclose(t["time_usec"], [m.TimeUS / 1000 for m in of])
    g = df.table("RAW_IMU")
    assert_allclose(g["ygyro"], [m.GyrY * 1000 for m in imu])
    assert_allclose(g["zacc"], [m.AccZ / 9.80665 * 1000 for m in imu])
    d = df.table("DISTANCE_SENSOR")
    assert_allclose(d["current_distance"], [m.Dist * 100 for m in rows["RFND"]])
    a = df.table("ATTITUDE")
    assert_allclose(a["pitch"], [math.radians(m.Pitch) for m in rows["ATT"]])
    assert_allclose(a["pitchspeed"], [math.radians(m.P) for m in rows["RATE"]])


def test_dataflash_flow_columns_follow_ardupilot_mavlink(df: Recording) -> None:
    tr = mf.DF_TRUTH
    t_us = np.array(tr.frame_times_us())
    s = _segments_at(tr, t_us)
    of = df.table("OPTICAL_FLOW")
    assert_allclose(of["time_usec"], t_us / 1000.0)  # ms, as ArduPilot's OPTICAL_FLOW stream
    assert_allclose(of.t_s, t_us * 1e-6)
    # ArduPilot: flowRate = (wx - vy/A, wy + vx/A); flow_comp_m = flowRate - bodyRate
    assert_allclose(of["flow_rate_x"], s["wx"] - s["vy"] / s["A"], rtol=1e-6)
    assert_allclose(of["flow_rate_y"], s["wy"] + s["vx"] / s["A"], rtol=1e-6)
    assert_allclose(of["flow_comp_m_x"], -s["vy"] / s["A"], rtol=1e-6)
    assert_allclose(of["flow_comp_m_y"], +s["vx"] / s["A"], rtol=1e-6)
    assert_array_equal(of["quality"], [mf._quality(k) for k in range(len(t_us))])
    assert np.all(of["quality"][list(mf.DF_QUALITY_ZERO_FRAMES)] == 0)
    assert np.all(of["flow_x"] == 0) and np.all(of["flow_y"] == 0)
    assert np.all(of["ground_distance"] == -1.0)


def test_dataflash_gyro_range_attitude_planted(df: Recording) -> None:
    tr = mf.DF_TRUTH
    imu = df.table("RAW_IMU")
    s = _segments_at(tr, imu["time_usec"])
    assert_allclose(imu.t_s, imu["time_usec"] * 1e-6)
    # instance 0 only (instance 1 carries a +0.01 rad/s offset); mrad/s, milli-g
    assert_allclose(imu["xgyro"], s["wx"] * 1000, atol=1e-4)
    assert_allclose(imu["ygyro"], s["wy"] * 1000, atol=1e-4)
    assert_allclose(imu["zgyro"], s["wz"] * 1000, atol=1e-4)
    assert_allclose(imu["zacc"], -1000.0, atol=1e-4)
    assert_allclose(imu["temperature"], mf.DF_IMU_TEMP_C * 100)

    rng = df.table("DISTANCE_SENSOR")
    down = rng.select(rng["orientation"] == 25)
    fwd = rng.select(rng["orientation"] == 0)
    assert_allclose(down["current_distance"], _segments_at(tr, down.t_s * 1e6)["A"] * 100, atol=0.5)
    assert_allclose(down["time_boot_ms"], down.t_s * 1000)
    assert np.all(down["min_distance"] == 20.0) and np.all(down["max_distance"] == 700.0)
    assert np.all(down["id"] == 0) and np.all(fwd["id"] == 1)
    assert_allclose(fwd["current_distance"], mf.DF_RFND2_DIST_M * 100)
    assert np.all(fwd["min_distance"] == 10.0) and np.all(fwd["max_distance"] == 1200.0)
    quality = np.zeros(len(down), np.uint8)
    quality[list(mf.DF_RFND_NODATA_ROWS)] = 1  # MAVLink signal_quality 1 = invalid
    assert_array_equal(down["signal_quality"], quality)

    att = df.table("ATTITUDE")
    planted = np.array([tr.attitude(t) for t in att.t_s * 1e6])
    assert_allclose(att["roll"], planted[:, 0], atol=1e-6)
    assert_allclose(att["pitch"], planted[:, 1], atol=1e-6)
    assert_allclose(_angle_diff(att["yaw"], planted[:, 2]), 0, atol=1e-5)
    assert np.all((att["yaw"] >= -np.pi) & (att["yaw"] < np.pi))  # 0-360 deg wrapped
    s = _segments_at(tr, att.t_s * 1e6)
    assert_allclose(att["rollspeed"], s["wx"], atol=1e-7)
    assert_allclose(att["pitchspeed"], s["wy"], atol=1e-7)
    assert_allclose(att["yawspeed"], s["wz"], atol=1e-7)

    tgt = df.table("ATTITUDE_TARGET")
    assert tgt["q"].shape == (len(tgt), 4)
    assert_allclose(np.linalg.norm(tgt["q"], axis=1), 1.0, atol=1e-12)
    roll, pitch, yaw = quaternions_to_euler(tgt["q"])
    off = np.radians(mf.DF_DES_OFFSET_DEG)
    assert_allclose(roll, planted[:, 0] + off[0], atol=1e-6)
    assert_allclose(pitch, planted[:, 1] + off[1], atol=1e-6)
    assert_allclose(_angle_diff(yaw, planted[:, 2] + off[2]), 0, atol=1e-5)
    rate_off = np.radians(mf.DF_RATE_DES_OFFSET_DEG_S)
    assert_allclose(tgt["body_roll_rate"], s["wx"] + rate_off[0], atol=1e-6)
    assert_allclose(tgt["body_yaw_rate"], s["wz"] + rate_off[2], atol=1e-6)
    assert np.all(tgt["type_mask"] == 0)


def test_ardupilot_profile_gives_paper_scene_angle(df: Recording) -> None:
    dphi_x, dphi_y, dt = _paper_increments(mf.DF_TRUTH)
    fc = flow_columns(df.table("OPTICAL_FLOW"), Profile.ARDUPILOT, Q_PAPER)
    assert not fc.increment
    assert_allclose(fc.time_s, np.array(mf.DF_TRUTH.frame_times_us()) * 1e-6)
    frame_dt = np.diff(fc.time_s)
    assert_allclose(frame_dt, dt, rtol=1e-9)
    assert_allclose(fc.scene_x[1:] * frame_dt, dphi_x, rtol=1e-6, atol=1e-12)
    assert_allclose(fc.scene_y[1:] * frame_dt, dphi_y, rtol=1e-6, atol=1e-12)


def test_ardupilot_recording_recovers_planted_velocity(df: Recording) -> None:
    """Eq. 15 on the imported flow, gyro (nearest sample) and range gives the planted V."""
    tr = mf.DF_TRUTH
    fc = flow_columns(df.table("OPTICAL_FLOW"), Profile.ARDUPILOT, Q_PAPER)
    imu = df.table("RAW_IMU")
    gi = np.searchsorted(imu["time_usec"] * 1e-6, fc.time_s[1:]) - 1
    rng = df.table("DISTANCE_SENSOR")
    rng = rng.select(rng["orientation"] == 25)
    ri = np.searchsorted(rng.t_s, fc.time_s[1:]) - 1
    vx, vy = velocity_from_flow(fc.scene_x[1:], fc.scene_y[1:], imu["xgyro"][gi] * 1e-3, imu["ygyro"][gi] * 1e-3,
                                rng["current_distance"][ri] * 1e-2)
    s = _segments_at(tr, np.array(tr.frame_times_us()[1:]))
    steady = np.abs(fc.time_s[1:] - tr.segments[0].t_end_us * 1e-6) > 0.06  # gyro/range lag at the step
    assert_allclose(vx[steady], s["vx"][steady], atol=1e-5)
    assert_allclose(vy[steady], s["vy"][steady], atol=1e-5)


def test_dataflash_record_order(df: Recording) -> None:
    _check_record_order(df)


def test_load_recording_dispatches_by_suffix() -> None:
    assert load_recording(BIN).source_format == "dataflash"
    assert load_recording(ULG).source_format == "ulog"


def _df_writer(with_of: bool = True):
    w = mf.DataFlashWriter()
    if with_of:
        w.fmt(0x83, "OF", "QBffff", "TimeUS,Qual,flowX,flowY,bodyX,bodyY")
        for k in range(5):
            w.msg("OF", TimeUS=1_000_000 + 20_000 * k, Qual=200, flowX=0.1 * k, flowY=-0.2, bodyX=0.0, bodyY=0.0)
    return w


def test_dataflash_legacy_layouts_and_gyr_fallback(tmp_path: Path) -> None:
    """Centidegree ATT ('c'/'C'), two-sensor RFND, RNGFND_*_CM params, GYR when IMU is absent."""
    w = _df_writer()
    w.fmt(0x90, "ATT", "QccccCCCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw")
    w.fmt(0x91, "RFND", "QCBCB", "TimeUS,Dist1,Orient1,Dist2,Orient2")
    w.fmt(0x92, "GYR", "QBQfff", "TimeUS,I,SampleUS,GyrX,GyrY,GyrZ")
    w.fmt(0x93, "PARM", "QNf", "TimeUS,Name,Value")
    w.msg("PARM", TimeUS=10, Name="RNGFND1_MIN_CM", Value=25.0)
    w.msg("PARM", TimeUS=11, Name="RNGFND1_MAX_CM", Value=1500.0)
    w.msg("ATT", TimeUS=1_000_100, DesRoll=-12.34, Roll=-12.5, DesPitch=3.21, Pitch=3.0, DesYaw=270.0, Yaw=181.0)
    w.msg("RFND", TimeUS=1_000_200, Dist1=1.23, Orient1=25, Dist2=0.0, Orient2=0)
    for inst in (1, 0):
        w.msg("GYR", TimeUS=1_000_300, I=inst, SampleUS=1_000_250, GyrX=0.5 + inst, GyrY=-0.25, GyrZ=0.125)
    path = tmp_path / "legacy.bin"
    path.write_bytes(bytes(w.buf))
    rec = read_dataflash(path)
    att = rec.table("ATTITUDE")
    assert_allclose(att["roll"], [math.radians(-12.5)])
    assert_allclose(att["yaw"], [math.radians(181.0 - 360.0)])
    roll, pitch, yaw = quaternions_to_euler(rec.table("ATTITUDE_TARGET")["q"])
    assert_allclose([roll[0], pitch[0], yaw[0]], np.radians([-12.34, 3.21, -90.0]), atol=1e-9)
    assert np.isnan(att["rollspeed"][0]) and rec.table("ATTITUDE_TARGET")["type_mask"][0] == 7
    rng = rec.table("DISTANCE_SENSOR")
    assert len(rng) == 1  # the absent second sensor (all zero) is dropped
    assert_allclose([rng["current_distance"][0], rng["min_distance"][0], rng["max_distance"][0]], [123, 25, 1500])
    imu = rec.table("RAW_IMU")
    assert_allclose([imu["xgyro"][0], imu["ygyro"][0]], [500.0, -250.0])
    assert imu["time_usec"][0] == 1_000_250 and np.isnan(imu["xacc"][0])
    assert any("GYR" in n for n in rec.notes) and any("RATE" in n for n in rec.notes)


def test_dataflash_without_optional_messages_notes_them(tmp_path: Path) -> None:
    path = tmp_path / "flow_only.bin"
    path.write_bytes(bytes(_df_writer().buf))
    rec = read_dataflash(path)
    assert list(rec.tables) == ["OPTICAL_FLOW"]
    assert_allclose(rec.table("OPTICAL_FLOW")["flow_rate_x"], 0.1 * np.arange(5), atol=1e-7)
    joined = " | ".join(rec.notes)
    for missing in ("no IMU or GYR messages", "no RFND messages: range missing", "no ATT messages"):
        assert missing in joined


def test_dataflash_survives_corruption(tmp_path: Path) -> None:
    blob = BIN.read_bytes()
    cut = len(blob) // 2
    path = tmp_path / "corrupt.bin"
    path.write_bytes(blob[:cut] + bytes(range(7, 44)) + blob[cut:-5])
    rec = read_dataflash(path)
    assert rec.skipped_bytes > 0 and "corrupt or truncated" in rec.notes[0]
    clean = read_dataflash(BIN)
    for name in ("OPTICAL_FLOW", "ATTITUDE"):
        assert len(clean.table(name)) - len(rec.table(name)) <= 2


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (b"", "empty file"),
        (b"\xfe\x09\x00\x01\x01" + bytes(40), "not an ArduPilot DataFlash log"),
        (b"ULog\x01\x12\x35\x01" + bytes(8), "not an ArduPilot DataFlash log"),
    ],
)
def test_dataflash_rejects_non_dataflash(tmp_path: Path, content: bytes, expected: str) -> None:
    path = tmp_path / "x.bin"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=expected) as info:
        read_dataflash(path)
    assert "\n" not in str(info.value)


def test_dataflash_without_flow_is_an_error(tmp_path: Path) -> None:
    w = _df_writer(with_of=False)
    w.fmt(0x90, "RATE", "Qffffff", "TimeUS,RDes,R,PDes,P,YDes,Y")
    w.msg("RATE", TimeUS=5)
    path = tmp_path / "noflow.bin"
    path.write_bytes(bytes(w.buf))
    with pytest.raises(RecordingError, match=r"noflow.bin: no OF \(optical flow\) messages"):
        read_dataflash(path)
    with pytest.raises(RecordingError, match="recording not found"):
        read_dataflash(tmp_path / "missing.bin")


def test_dataflash_unknown_layouts(tmp_path: Path) -> None:
    """An OF without flowX (the pre-3.3 layout) is an error; an unusable optional message a note."""
    w = mf.DataFlashWriter()
    w.fmt(0x83, "OF", "QBhhhh", "TimeUS,Qual,dx,dy,x_cm,y_cm")
    w.msg("OF", TimeUS=1000, Qual=10)
    path = tmp_path / "old_of.bin"
    path.write_bytes(bytes(w.buf))
    with pytest.raises(RecordingError, match=r"old_of.bin: OF messages lack flowX, flowY, bodyX, bodyY"):
        read_dataflash(path)
    w = _df_writer()
    w.fmt(0x90, "IMU", "Qfff", "TimeUS,GyroX,GyroY,GyroZ")
    w.msg("IMU", TimeUS=1_000_000)
    path = tmp_path / "odd_imu.bin"
    path.write_bytes(bytes(w.buf))
    rec = read_dataflash(path)
    assert "OPTICAL_FLOW" in rec and "RAW_IMU" not in rec
    assert "IMU messages lack GyrX, GyrY, GyrZ (unsupported log layout): skipped" in rec.notes


@pytest.mark.parametrize("fixture", [BIN, ULG])
def test_damaged_files_read_or_fail_cleanly(tmp_path: Path, fixture: Path) -> None:
    """Seeded byte damage: the importer returns a Recording or raises RecordingError, nothing else."""
    rng = np.random.default_rng(20250611)
    blob = np.frombuffer(fixture.read_bytes(), dtype=np.uint8)
    reader = read_dataflash if fixture.suffix == ".bin" else read_ulog
    outcomes = []
    for i in range(12):
        damaged = blob.copy()
        at = rng.integers(16, len(blob), size=int(rng.integers(1, 40)))
        damaged[at] = rng.integers(0, 256, size=len(at), dtype=np.uint8)
        path = tmp_path / f"damaged{i}{fixture.suffix}"
        path.write_bytes(damaged.tobytes()[: int(rng.integers(len(blob) // 2, len(blob) + 1))])
        try:
            rec = reader(path)
        except RecordingError as exc:
            assert "\n" not in str(exc)
            outcomes.append("error")
        else:
            _check_record_order(rec)
            outcomes.append("read")
    assert "read" in outcomes


# --------------------------------------------------------------------------- ULog


def test_ulog_recording_shape(ul: Recording) -> None:
    assert ul.source_format == "ulog" and ul.profile_hint == "px4"
    assert set(ul.tables) == {"OPTICAL_FLOW_RAD", "RAW_IMU", "DISTANCE_SENSOR", "ATTITUDE", "ATTITUDE_TARGET"}
    assert ul.notes == []
    _check_record_order(ul)


def test_ulog_flow_is_mavlink_optical_flow_rad(ul: Recording) -> None:
    tr = mf.ULOG_TRUTH
    t_us = np.array(tr.frame_times_us())
    s = _segments_at(tr, t_us)
    dt = np.diff(t_us, prepend=t_us[0] - tr.frame_us) * 1e-6
    f = ul.table("OPTICAL_FLOW_RAD")
    assert_array_equal(f["time_usec"], t_us)  # timestamp_sample
    assert_allclose(f.t_s, (t_us + mf.UL_FLOW_PUBLISH_DELAY_US) * 1e-6)  # topic timestamp
    assert_array_equal(f["integration_time_us"], np.round(dt * 1e6))
    # MAVLink OPTICAL_FLOW_RAD: RH rotation gives +, motion along +Y gives -x flow, +X gives +y flow
    assert_allclose(f["integrated_x"], (s["wx"] - s["vy"] / s["A"]) * dt, rtol=1e-6)
    assert_allclose(f["integrated_y"], (s["wy"] + s["vx"] / s["A"]) * dt, rtol=1e-6)
    assert_allclose(f["integrated_xgyro"], s["wx"] * dt, rtol=1e-6)
    assert_allclose(f["integrated_zgyro"], s["wz"] * dt, rtol=1e-6, atol=1e-12)
    assert_array_equal(f["quality"], [mf._quality(k) for k in range(len(t_us))])
    assert np.all(f["distance"] == -1.0)  # NaN distance_m -> unknown


def test_ulog_gyro_range_attitude_planted(ul: Recording) -> None:
    tr = mf.ULOG_TRUTH
    imu = ul.table("RAW_IMU")
    s = _segments_at(tr, imu["time_usec"])
    assert_allclose(imu["xgyro"], s["wx"] * 1000, atol=1e-4)
    assert_allclose(imu["ygyro"], s["wy"] * 1000, atol=1e-4)
    assert_allclose(imu["zacc"], -1000.0, atol=1e-4)

    rng = ul.table("DISTANCE_SENSOR")
    down = rng.select(rng["orientation"] == 25)
    assert_allclose(down["current_distance"], _segments_at(tr, down.t_s * 1e6)["A"] * 100, rtol=1e-6)
    lo, hi = mf.UL_RANGE_LIMITS_M
    assert_allclose(down["min_distance"], lo * 100, rtol=1e-6)
    assert_allclose(down["max_distance"], hi * 100, rtol=1e-6)
    assert down["signal_quality"][2] == 0 and np.all(np.delete(down["signal_quality"], 2) == 100)
    assert np.all(rng.select(rng["orientation"] == 0)["id"] == 1)

    att = ul.table("ATTITUDE")
    planted = np.array([tr.attitude(t) for t in att.t_s * 1e6])
    assert_allclose(att["roll"], planted[:, 0], atol=1e-6)
    assert_allclose(att["pitch"], planted[:, 1], atol=1e-6)
    assert_allclose(_angle_diff(att["yaw"], planted[:, 2]), 0, atol=1e-6)
    s = _segments_at(tr, att.t_s * 1e6)
    steady = np.abs(att.t_s - tr.segments[0].t_end_us * 1e-6) > 0.011
    assert_allclose(att["rollspeed"][steady], s["wx"][steady], atol=1e-7)
    assert_allclose(att["yawspeed"][steady], s["wz"][steady], atol=1e-7)

    tgt = ul.table("ATTITUDE_TARGET")
    planted = np.array([tr.attitude(t) for t in tgt.t_s * 1e6])
    off = np.radians(mf.UL_SETPOINT_OFFSET_DEG)
    expected_q = euler_to_quaternions(planted[:, 0] + off[0], planted[:, 1] + off[1], planted[:, 2] + off[2])
    assert_allclose(tgt["q"], expected_q, atol=1e-6)
    assert_allclose(tgt["thrust"], 0.55, rtol=1e-6)
    assert_allclose(tgt["body_roll_rate"], mf.UL_RATES_SP[0], rtol=1e-6)
    assert_allclose(tgt["body_pitch_rate"], mf.UL_RATES_SP[1], rtol=1e-6)
    assert np.all(tgt["type_mask"] == 0)


def test_px4_profile_gives_paper_scene_angle(ul: Recording) -> None:
    dphi_x, dphi_y, dt = _paper_increments(mf.ULOG_TRUTH)
    fc = flow_columns(ul.table("OPTICAL_FLOW_RAD"), Profile.PX4, Q_PAPER)
    assert fc.increment
    assert_allclose(fc.integration_s[1:], dt, rtol=1e-12)
    assert_allclose(fc.scene_x[1:], dphi_x, rtol=1e-6, atol=1e-12)
    assert_allclose(fc.scene_y[1:], dphi_y, rtol=1e-6, atol=1e-12)


def test_px4_recording_recovers_planted_velocity(ul: Recording) -> None:
    tr = mf.ULOG_TRUTH
    fc = flow_columns(ul.table("OPTICAL_FLOW_RAD"), Profile.PX4, Q_PAPER)
    frame_dt = np.full(len(fc.time_s), tr.frame_us * 1e-6)
    rx = scene_rate(fc.scene_x, fc.increment, fc.integration_s, frame_dt)
    ry = scene_rate(fc.scene_y, fc.increment, fc.integration_s, frame_dt)
    imu = ul.table("RAW_IMU")
    gi = np.searchsorted(imu["time_usec"] * 1e-6, fc.time_s) - 1
    rng = ul.table("DISTANCE_SENSOR")
    rng = rng.select(rng["orientation"] == 25)
    ri = np.searchsorted(rng.t_s, fc.time_s) - 1
    ok = (gi >= 0) & (ri >= 0)
    vx, vy = velocity_from_flow(rx[ok], ry[ok], imu["xgyro"][gi[ok]] * 1e-3, imu["ygyro"][gi[ok]] * 1e-3,
                                rng["current_distance"][ri[ok]] * 1e-2)
    s = _segments_at(tr, np.array(tr.frame_times_us())[ok])
    steady = np.abs(fc.time_s[ok] - tr.segments[0].t_end_us * 1e-6) > 0.06
    assert_allclose(vx[steady], s["vx"][steady], atol=1e-5)
    assert_allclose(vy[steady], s["vy"][steady], atol=1e-5)


def test_ulog_legacy_optical_flow_topic(tmp_path: Path) -> None:
    path = tmp_path / "legacy.ulg"
    path.write_bytes(mf.ulog_bytes(legacy_flow=True))
    rec = read_ulog(path)
    tr = mf.ULOG_TRUTH
    t_us = np.array(tr.frame_times_us())
    s = _segments_at(tr, t_us)
    f = rec.table("OPTICAL_FLOW_RAD")
    dt = f["integration_time_us"] * 1e-6
    assert_array_equal(f["time_usec"], t_us)
    assert_allclose(f["integrated_x"], (s["wx"] - s["vy"] / s["A"]) * dt, rtol=1e-6)
    assert_allclose(f["integrated_y"], (s["wy"] + s["vx"] / s["A"]) * dt, rtol=1e-6)
    assert_allclose(f["distance"], s["A"], rtol=1e-6)
    assert np.all(f["sensor_id"] == 3)
    att = rec.table("ATTITUDE")  # rates from sensor_combined when vehicle_angular_velocity is absent
    assert np.isfinite(att["rollspeed"]).all()
    tgt = rec.table("ATTITUDE_TARGET")
    assert np.all(tgt["type_mask"] == 7) and np.isnan(tgt["body_roll_rate"]).all()


def test_ulog_without_flow_is_an_error(tmp_path: Path) -> None:
    w = mf.ULogWriter(0)
    w.format("sensor_combined", [("uint64_t", "timestamp"), ("float[3]", "gyro_rad")])
    w.add_logged("sensor_combined")
    w.data("sensor_combined", timestamp=1000, gyro_rad=[0.1, 0.2, 0.3])
    path = tmp_path / "noflow.ulg"
    path.write_bytes(bytes(w.buf))
    with pytest.raises(RecordingError, match="noflow.ulg: no optical flow in the ULog") as info:
        read_ulog(path)
    assert "vehicle_optical_flow" in str(info.value) and "\n" not in str(info.value)


def test_ulog_flow_topic_of_unknown_version_is_named(tmp_path: Path) -> None:
    w = mf.ULogWriter(0)
    w.format("vehicle_optical_flow", [("uint64_t", "timestamp"), ("float[2]", "flow_rad")])
    w.add_logged("vehicle_optical_flow")
    w.data("vehicle_optical_flow", timestamp=1000, flow_rad=[0.1, 0.2])
    path = tmp_path / "odd.ulg"
    path.write_bytes(bytes(w.buf))
    with pytest.raises(RecordingError, match=r"no optical flow in the ULog .*; vehicle_optical_flow lacks pixel_flow"):
        read_ulog(path)


@pytest.mark.parametrize("content", [b"", b"ULog\x01\x12", bytes(BIN.read_bytes()[:64]), b"hello, world" * 4])
def test_ulog_rejects_non_ulog(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "x.ulg"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match="not a PX4 ULog file"):
        read_ulog(path)


def test_ulog_truncated_file_still_reads(tmp_path: Path) -> None:
    blob = ULG.read_bytes()
    path = tmp_path / "cut.ulg"
    path.write_bytes(blob[: len(blob) * 2 // 3 + 5])
    rec = read_ulog(path)
    n = len(rec.table("OPTICAL_FLOW_RAD"))
    assert 0.5 * (mf.ULOG_TRUTH.n_frames + 1) < n < mf.ULOG_TRUTH.n_frames + 1
    _check_record_order(rec)


# --------------------------------------------------------------------------- fixtures


def test_committed_fixtures_are_reproducible(tmp_path: Path) -> None:
    """make_fixtures.py regenerates the committed files byte for byte (and they stay small)."""
    fresh = mf.write_all(tmp_path)
    for name, path in fresh.items():
        committed = DATA / name
        assert committed.read_bytes() == path.read_bytes(), name
        assert committed.stat().st_size < 200_000
