"""One signal path from a recording (issue 13): every gyro message of the contract gives the same
signals to replay, diagnose and the sensor-only diagnosis; one vehicle-id rule for all three (the
most frequent flow sender, ``companion.columnar.vehicle_sysid``); the simulated vehicle's
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

from companion.columnar import MessageTable, vehicle_sysid
from companion.config import Config, replace_section
from companion.diagnose.diagnosis import diagnose
from companion.profiles import Profile
from companion.recording import load_recording
from companion.replay import replay
from companion.sensor_diagnose import extract_series
from simvehicle.scenarios import run_named
from simvehicle.server import recording_run

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


@pytest.fixture(scope="module")
def gust_stray(gust) -> Path:
    """The gust flight with five OPTICAL_FLOW messages from another system (7) first, at the
    recording's first record time: replay took the first flow sender as the vehicle."""
    enc = mav.MAVLink(None, srcSystem=7, srcComponent=1)
    first = [True]

    def stray(msg: Any) -> list[tuple[float, bytes]]:
        out = []
        if first[0]:
            first[0] = False
            out = [(msg._timestamp, bytes(enc.optical_flow_encode(k, 0, 90, -90, 0.0, 0.0, 255, 1.0).pack(enc)))
                   for k in range(5)]
        return out + _same(msg)

    return _rewrite(gust, gust.with_name("gust_stray.tlog"), stray)


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
