"""A recorded command followed within about a frame (an autopilot's own attitude target, as in
a ground station's copy of an ArduCopter flight): the attitude loop's fit runs to the fastest
the frames resolve, and that is a finding ("at least"), not a misfit."""

from __future__ import annotations

import dataclasses

from companion.config import load_config
from companion.diagnose.closed_loop.attitude import OMEGA_P_MAX_RAD_S
from companion.recordings.load import load_recording


def _steps_flight(tmp_path, name: str, omega_p: float, zeta: float):
    """A generator flight (paper profile, 50 Hz frames, 60 s) of velocity steps on both axes whose
    true attitude loop is (omega_p, zeta); the config keeps the vehicle's nominal loop."""
    from simvehicle.engines import flightgen as fg

    spec = fg.draw_spec(5, ardupilot_share=0.0)
    segs, t, k = [], 0.0, 0
    while t < 70.0:
        v = ((1.0, 0.5), (-1.0, -0.5), (0.0, 0.0))[k % 3]
        segs.append(fg.SetpointSegment(t, t + 5.0, "step", v, v))
        t, k = t + 5.0, k + 1
    flight = fg.FlightProfile(tuple(segs), (0.0, 1e4), (1.0, 1.0), 2.0)
    spec = dataclasses.replace(spec, duration_s=60.0, warmup_s=2.0, flight=flight,
                               effects={"attitude_dynamics": {"omega_p": omega_p, "zeta": zeta}},
                               noise=fg.Noise(), loss=fg.Loss(), wind_from_start=False, wind_to_end=False)
    assert abs(spec.frame_s - 0.02) < 1e-9
    fg.write_flight(spec, fg.simulate(spec), tmp_path, name)
    return tmp_path / f"{name}.tlog", tmp_path / f"{name}.toml"


def test_a_loop_faster_than_the_frames_resolve_is_named_at_the_bound(tmp_path):
    """A true loop of 400 rad/s follows a step within 5 ms, a quarter of a frame: every Omega_p
    from about 80 rad/s up explains the 50 Hz attitude alike, so the fit stops at the bound. It is
    named (the held-out gain is large: the nominal loop lags by a fifth of a second), says "at
    least", and the headline does not blame an unexplained attitude residual on it."""
    from companion.diagnose.closed_loop.diagnosis import diagnose

    tlog, toml = _steps_flight(tmp_path, "fast", 400.0, 0.8)
    rep = diagnose(load_recording(tlog), load_config(toml)).report
    found = {f.effect: f for f in rep.significant()}
    assert "attitude_dynamics" in found, rep.headline
    f = found["attitude_dynamics"]
    assert f.parameters["omega_p"] == OMEGA_P_MAX_RAD_S
    assert f"at least {OMEGA_P_MAX_RAD_S:g} rad/s" in f.explanation
    assert "attitude_dynamics" in rep.headline


def test_a_loop_within_the_frames_resolution_is_fitted_not_bounded(tmp_path):
    """A loop of 20 rad/s (rise time 90 ms, four frames) is resolved: its Omega_p comes out
    within the generalisation matrix's tolerance of it (15 %), well under the bound, and its
    explanation gives the value, not a bound."""
    from companion.diagnose.closed_loop.diagnosis import diagnose

    tlog, toml = _steps_flight(tmp_path, "resolved", 20.0, 0.8)
    rep = diagnose(load_recording(tlog), load_config(toml)).report
    found = {f.effect: f for f in rep.significant()}
    assert "attitude_dynamics" in found, rep.headline
    f = found["attitude_dynamics"]
    assert abs(f.parameters["omega_p"] - 20.0) < 0.15 * 20.0, f.parameters
    assert "at least" not in f.explanation
