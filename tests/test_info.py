"""``companion info``: the numbers in the summary against an independent count of what a
generated recording holds."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

import companion.step.profiles
from companion.cli import main
from companion.errors import RecordingError
from companion.recordings.load import Recording
from companion.recordings.tlog_reader import read_tlog
from companion.recordings.tlog_writer import TlogWriter, mav_encoder
from companion.tools.info import format_summary, run_cli, stream_timing, summarise

T0 = 1_750_000_000.0
FLOW_HZ = 50.0
GAP_START_S, GAP_S = 4.0, 1.0  # the flow stream stops after 4 s for 1 s


def _flow_times() -> np.ndarray:
    """10 s of 50 Hz flow frames, s from T0, with none in (4.0, 5.0)."""
    t = np.arange(0, 10.0, 1 / FLOW_HZ)
    return t[(t <= GAP_START_S + 1e-9) | (t >= GAP_START_S + GAP_S - 1e-9)]


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Vehicle (1/1): 50 Hz OPTICAL_FLOW with a 1 s hole, 50 Hz RAW_IMU, 10 Hz ATTITUDE,
    20 Hz DISTANCE_SENSOR down (orientation 25) and 5 Hz forward (0), 1 Hz HEARTBEAT;
    companion (1/191): 1 Hz HEARTBEAT and 25 Hz SET_ATTITUDE_TARGET; three STATUSTEXTs."""
    path = tmp_path_factory.mktemp("info") / "flight.tlog"
    veh, comp = mav_encoder(1, 1), mav_encoder(1, 191)
    rng = np.random.default_rng(0)
    events: list[tuple[float, object, object]] = []
    for t in _flow_times():
        events.append((t, veh, veh.optical_flow_encode(int(t * 1e6), 0, int(rng.integers(-5, 5)), 1, 0, 0, 200, -1)))
    for t in np.arange(0, 10.0, 0.02):
        events.append((t + 0.001, veh, veh.raw_imu_encode(int(t * 1e6), 0, 0, -1000, 1, 2, 3, 0, 0, 0)))
    for t in np.arange(0, 10.0, 0.1):
        events.append((t + 0.002, veh, veh.attitude_encode(int(t * 1e3), 0.01, -0.02, 0.0, 0, 0, 0)))
    for t in np.arange(0, 10.0, 0.05):
        events.append((t + 0.003, veh, veh.distance_sensor_encode(int(t * 1e3), 20, 1000, 100, 0, 0, 25, 0)))
    for t in np.arange(0, 10.0, 0.2):
        events.append((t + 0.004, veh, veh.distance_sensor_encode(int(t * 1e3), 20, 1000, 300, 0, 1, 0, 0)))
    for t in np.arange(0, 10.0, 1.0):
        events.append((t + 0.005, veh, veh.heartbeat_encode(2, 3, 0, 20, 4)))
        events.append((t + 0.006, comp, comp.heartbeat_encode(18, 8, 0, 0, 4)))
    for t in np.arange(0, 10.0, 0.04):
        events.append((t + 0.007, comp, comp.set_attitude_target_encode(int(t * 1e3), 1, 1, 7, [1, 0, 0, 0],
                                                                          0, 0, 0, 0.5)))
    for t in (0.5, 2.5, 9.5):
        events.append((t, veh, veh.statustext_encode(6, b"hello")))
    events.sort(key=lambda e: e[0])
    with TlogWriter(path) as log:
        for t, enc, msg in events:
            log.write(msg, T0 + float(t), encoder=enc)
    return path


@pytest.fixture()
def fixed_profile(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(companion.step.profiles, "detect_profile", lambda rec: ("paper", "stub for the test"))


def _message(summary: dict, name: str) -> dict:
    return next(m for m in summary["messages"] if m["name"] == name)


def test_counts_rates_and_duration(flight, fixed_profile):
    s = summarise(read_tlog(flight))
    flow = _message(s, "OPTICAL_FLOW")
    assert flow["count"] == len(_flow_times())
    assert flow["rate_hz"] == pytest.approx(FLOW_HZ, abs=0.1)
    assert _message(s, "RAW_IMU")["count"] == 500
    assert _message(s, "RAW_IMU")["rate_hz"] == pytest.approx(50.0, abs=0.1)
    assert _message(s, "ATTITUDE")["rate_hz"] == pytest.approx(10.0, abs=0.02)
    assert _message(s, "DISTANCE_SENSOR")["count"] == 200 + 50
    assert _message(s, "SET_ATTITUDE_TARGET")["rate_hz"] == pytest.approx(25.0, abs=0.05)
    # first record: the flow frame at 0 s; last: the RAW_IMU at 9.98 + 0.001 s (times stored to 1 µs)
    assert s["duration_s"] == pytest.approx(9.981, abs=2e-6)
    assert s["t0_s"] == T0
    assert s["n_messages"] == sum(m["count"] for m in s["messages"])
    assert (s["skipped_bytes"], s["skipped_packets"], s["notes"]) == (0, 0, [])


def test_planted_gap_is_found_at_its_time(flight, fixed_profile):
    flow = _message(summarise(read_tlog(flight)), "OPTICAL_FLOW")
    assert flow["n_gaps"] == 1 and flow["streamed"]
    gap = flow["gaps"][0]
    assert gap["start_s"] == pytest.approx(GAP_START_S, abs=2e-6)
    assert gap["duration_s"] == pytest.approx(GAP_S, abs=2e-6)
    assert (gap["sysid"], gap["compid"]) == (1, 1)
    for name in ("RAW_IMU", "ATTITUDE", "HEARTBEAT", "SET_ATTITUDE_TARGET"):
        assert _message(summarise(read_tlog(flight)), name)["n_gaps"] == 0, name


def test_senders_per_message(flight, fixed_profile):
    s = summarise(read_tlog(flight))
    hb = _message(s, "HEARTBEAT")
    assert [(x["sysid"], x["compid"], x["count"]) for x in hb["senders"]] == [(1, 1, 10), (1, 191, 10)]
    assert [x["rate_hz"] for x in hb["senders"]] == pytest.approx([1.0, 1.0], abs=1e-6)
    assert hb["rate_hz"] == pytest.approx(2.0, abs=1e-6)  # two senders at 1 Hz each
    assert [(x["sysid"], x["compid"]) for x in _message(s, "SET_ATTITUDE_TARGET")["senders"]] == [(1, 191)]
    assert not _message(s, "STATUSTEXT")["streamed"]


def test_sensors_found(flight, fixed_profile):
    s = summarise(read_tlog(flight))
    sensors = s["sensors"]
    assert [x["message"] for x in sensors["flow"]] == ["OPTICAL_FLOW"]
    assert [x["message"] for x in sensors["gyro"]] == ["RAW_IMU"]
    (rng,) = sensors["range"]
    assert (rng["count"], rng["orientations"]) == (200, [0, 25])  # only the downward rows count
    assert rng["rate_hz"] == pytest.approx(20.0, abs=0.05)
    assert [x["message"] for x in sensors["commands"]] == ["SET_ATTITUDE_TARGET"]
    assert sensors["truth"] == []
    assert s["missing_for_diagnosis"] == []
    assert s["profile"] == {"name": "paper", "reason": "stub for the test"}


def test_missing_sensors_are_listed(tmp_path, fixed_profile):
    enc = mav_encoder(1, 1)
    path = tmp_path / "hb.tlog"
    with TlogWriter(path) as log:
        for k in range(5):
            log.write(enc.heartbeat_encode(2, 3, 0, 0, 4), T0 + k, encoder=enc)
            log.write(enc.distance_sensor_encode(k, 20, 1000, 100, 0, 0, 0, 0), T0 + k + 0.5, encoder=enc)
    s = summarise(read_tlog(path))
    assert s["missing_for_diagnosis"] == ["flow", "gyro", "range", "attitude", "commands"]
    assert s["sensors"]["range"] == []  # a forward-facing rangefinder is not altitude
    assert "missing for diagnosis: flow, gyro, range, attitude, commands" in format_summary(s)


def test_profile_comes_from_detect_profile(flight):
    """Whatever companion.step.profiles says, info reports (here: the real detector)."""
    rec = read_tlog(flight)
    name, reason = companion.step.profiles.detect_profile(rec)
    s = summarise(rec)
    assert s["profile"] == {"name": str(name), "reason": str(reason)}
    assert f"profile: {name} ({reason})" in format_summary(s)


def test_stream_timing_closed_form():
    t = np.concatenate([np.arange(0, 2, 0.1), np.arange(2.5, 4, 0.1)])
    timing = stream_timing(t, t0_s=-1.0)
    assert timing["rate_hz"] == pytest.approx(10.0, rel=1e-9)
    assert timing["gaps"] == [pytest.approx({"start_s": 1.9 + 1.0, "duration_s": 0.6})]
    assert stream_timing(np.array([5.0]), 0.0)["rate_hz"] is None
    assert stream_timing(np.array([5.0, 5.0, 5.0]), 0.0)["rate_hz"] is None


def test_empty_recording_is_an_error():
    with pytest.raises(RecordingError, match="no messages"):
        summarise(Recording("x.tlog", {}, "tlog"))


def test_run_cli_prints_and_writes_json(flight, fixed_profile, tmp_path, capsys):
    out = tmp_path / "info.json"
    assert run_cli(argparse.Namespace(recording=str(flight), sensor_config=None, json=str(out))) == 0
    text = capsys.readouterr().out
    assert "OPTICAL_FLOW" in text and "profile: paper (stub for the test)" in text
    assert "OPTICAL_FLOW from 1/1: 1.000 s at 4.000 s" in text
    data = json.loads(out.read_text())
    assert data == json.loads(json.dumps(summarise(read_tlog(flight))))


def test_command_line(flight, tmp_path, capsys):
    assert main(["info", str(flight)]) == 0
    assert "duration  10.0 s" in capsys.readouterr().out
    bad = tmp_path / "empty.tlog"
    bad.write_bytes(b"")
    assert main(["info", str(bad)]) == 4  # ExitCode.BAD_INPUT
    assert "no MAVLink packets found" in capsys.readouterr().err


def _attitude_log(path: Path, stamps: np.ndarray, boot_s: np.ndarray, text: bytes | None = None) -> Recording:
    veh = mav_encoder(1, 1)
    with TlogWriter(path) as log:
        if text is not None:
            log.write(veh.statustext_encode(6, text), float(stamps[0]), encoder=veh)
        for t, b in zip(stamps, boot_s, strict=True):
            log.write(veh.attitude_encode(int(round(b * 1e3)), 0, 0, 0, 0, 0, 0), float(t), encoder=veh)
    return read_tlog(path)


def test_recording_clock_tells_simulated_from_wall_stamps(tmp_path):
    """Issue 14: ``info`` said a lockstep recording lasted 1.3 s with flow at 1590 Hz. It now says
    whose clock stamped the records: the simulated vehicle's STATUSTEXT; stamps that advance exactly
    as the vehicle's time field (a simulator's log); a link's jittery arrivals (wall clock); and wall
    stamps of a simulation that ran faster than real time."""
    from companion.recordings.tlog_writer import SIM_EPOCH_S
    from companion.tools.info import recording_clock

    rng = np.random.default_rng(1)
    boot = np.arange(0, 10.0, 0.02)
    cases = {
        "marker": (T0 + boot / 7 + rng.uniform(0, 2e-3, len(boot)), b"simvehicle: simulated clock (lockstep)"),
        "exact": (SIM_EPOCH_S + boot, None),
        "link": (T0 + 5.0 + boot + rng.uniform(0, 3e-3, len(boot)), None),
        "fast": (T0 + np.sort(boot / 7 + rng.uniform(0, 2e-4, len(boot))), None),
    }
    found = {name: recording_clock(_attitude_log(tmp_path / f"{name}.tlog", stamps, boot, text))
             for name, (stamps, text) in cases.items()}
    assert found["marker"] == {"simulated": True,
                               "reason": "the recording says so: 'simvehicle: simulated clock (lockstep)'"}
    assert found["exact"]["simulated"] is True and "exactly as ATTITUDE time_boot_ms" in found["exact"]["reason"]
    assert found["link"]["simulated"] is False and "jitter" in found["link"]["reason"]
    assert found["fast"]["simulated"] is False and "ran 7.0x faster" in found["fast"]["reason"]
    stamps, marker = cases["marker"]
    text = format_summary(summarise(_attitude_log(tmp_path / "again.tlog", stamps, boot, marker)))
    assert "clock     simulated (the recording says so" in text
