"""The live loop's scalar flow path equals the column path used by replay, for every profile."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.step.estimator import scene_rate, scene_rate_scalar
from companion.step.profiles import FieldView, Profile, flow_columns, flow_scalar

ENC = mav.MAVLink(None, 1, 1)


def _same(a: float, b: float) -> bool:
    return (a == b) or (math.isnan(a) and math.isnan(b))


def _messages(rng: np.random.Generator, profile: Profile):
    for _ in range(300):
        if profile is Profile.PX4:
            integ = int(rng.choice([0, 10000, 20000, int(rng.integers(1, 100000))]))
            yield ENC.optical_flow_rad_encode(int(rng.integers(0, 2**40)), 0, integ, *rng.normal(0, 0.1, 5).tolist(),
                                              0, int(rng.integers(0, 256)), 0, float(rng.uniform(0, 5)))
        else:
            yield ENC.optical_flow_encode(int(rng.integers(0, 2**40)), 0, int(rng.integers(-300, 300)),
                                          int(rng.integers(-300, 300)), *rng.normal(0, 1, 2).tolist(),
                                          int(rng.integers(0, 256)), float(rng.uniform(-1, 5)),
                                          *rng.normal(0, 2, 2).tolist())


@pytest.mark.parametrize("profile", list(Profile))
def test_scalar_flow_equals_columns_bit_for_bit(profile):
    rng = np.random.default_rng(7)
    q = 0.09 / 57.3
    for msg in _messages(rng, profile):
        msg = mav.MAVLink(None).decode(bytearray(msg.pack(ENC)))  # float32 on the wire, as live
        s = flow_scalar(msg, profile, q)
        c = flow_columns(FieldView(msg), profile, q)
        for name in ("time_s", "scene_x", "scene_y", "integration_s", "quality", "counts_x", "counts_y",
                     "body_x_rad_s", "body_y_rad_s"):
            with np.errstate(all="ignore"):
                assert _same(float(getattr(s, name)), float(getattr(c, name))), (profile, name)
        assert s.increment == c.increment
        for dt in (0.02, 0.013):
            assert _same(scene_rate_scalar(s.scene_x, s.increment, s.integration_s, dt),
                         float(scene_rate(c.scene_x, c.increment, c.integration_s, dt)))


def _detect_live(msgs) -> tuple[Profile, str] | None:
    from companion.step.profiles import LiveProfileDetector

    det = LiveProfileDetector()
    for m in msgs:
        if det.observe(m) is not None:
            break
    return det.result


def _sim_messages(profile: Profile, n_frames: int, *, with_clock: bool = True, moving: bool = False):
    """The simulated vehicle's HEARTBEAT and first frames in ``profile``, decoded as a link delivers them."""
    import dataclasses

    from companion.config import load_config
    from simvehicle.model import telemetry
    from simvehicle.model.sim import Simulator

    cfg = load_config()
    sim = Simulator(cfg)
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = mav.MAVLink(None)
    rf = cfg.rangefinder
    out = [parser.decode(bytearray(telemetry.heartbeat(enc, armed=False).pack(enc)))]
    s = sim.current
    for k in range(n_frames):
        if moving:
            s = dataclasses.replace(s, flow_x_counts=3 + k % 2, flow_y_counts=-2)
        for m in telemetry.frame_messages(enc, s, profile, cfg.flow_sensor.q_rad_per_count, sim.T, rf.min_m,
                                          rf.max_m):
            if with_clock or m.get_type() in ("OPTICAL_FLOW", "OPTICAL_FLOW_RAD"):
                out.append(parser.decode(bytearray(m.pack(enc))))
        s = sim.advance(0.0, 0.0)
    return out


@pytest.mark.parametrize("profile", list(Profile))
def test_live_detector_tells_the_simulated_vehicles_profile_on_its_second_frame(profile):
    """Issue 14: ``companion run`` without ``--profile`` assumed paper and held "flow stale" for a whole
    flight against an ArduPilot-convention vehicle. The simulated vehicle says ArduPilot in its
    HEARTBEAT in every profile: the flow tells (time_usec ms vs µs against the vehicle's clock,
    OPTICAL_FLOW_RAD, ground_distance -1). Frame 0 (boot time 0) cannot tell ms from µs: an
    ArduPilot-convention vehicle is known from frame 1."""
    first = _detect_live(_sim_messages(profile, 1))
    if profile is Profile.ARDUPILOT:
        assert first is None
    else:  # OPTICAL_FLOW_RAD, or ground_distance -1, says it on frame 0
        assert first is not None and first[0] is profile
    found = _detect_live(_sim_messages(profile, 2))
    assert found is not None and found[0] is profile
    assert "HEARTBEAT autopilot ArduPilot" in found[1]
    if profile is Profile.ARDUPILOT:
        assert "milliseconds" in found[1]


@pytest.mark.parametrize("moving,expected", [(True, Profile.ARDUPILOT), (False, None)])
def test_live_detector_without_a_clock_decides_by_content(moving, expected):
    """No gyro, range or attitude to compare times with: ArduPilot's rates moving while its truncated
    counts stay zero, after enough frames; at rest nothing tells."""
    from companion.step.profiles import CONTENT_FRAMES

    found = _detect_live(_sim_messages(Profile.ARDUPILOT, CONTENT_FRAMES + 1, with_clock=False, moving=moving))
    assert (found[0] if found else None) is expected


def test_live_detector_on_a_real_arducopter_sitl_link(flight_a_plain):
    """ArduCopter SITL's own messages (data/sitl/ardupilot/flight_a): ardupilot, from its clock."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(flight_a_plain), dialect="ardupilotmega")
    try:
        msgs = []
        while len(msgs) < 20000:
            m = conn.recv_msg()
            if m is None:
                break
            if m.get_type() != "BAD_DATA" and m.get_srcComponent() == 1:
                msgs.append(m)
    finally:
        conn.close()
    found = _detect_live(msgs)
    assert found is not None and found[0] is Profile.ARDUPILOT, found
    assert "milliseconds" in found[1]
