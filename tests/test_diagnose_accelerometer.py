"""The accelerometer as the flow group's independent check (``groups.accelerometer_z``): the flow's
odometry against the accelerometer's strapdown velocity over the windows that accelerate, rows the
fit never uses, which confirm a flow-geometry effect or contradict it."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion.config import load_config
from companion.diagnose.closed_loop.select import Candidate, Group, Selector, Settings
from companion.recordings.load import load_recording


def _steps_flight(tmp_path, name: str, effects: dict, duration_s: float = 90.0):
    """A generator flight (paper profile) of velocity steps on both axes every 6 s, at 1 m, in
    0.3 N of turbulence, with a white-noise accelerometer (0.05 m/s^2 a sample, 0.1 m/s^2 of bias
    on x)."""
    from simvehicle.engines import flightgen as fg

    spec = fg.draw_spec(11, ardupilot_share=0.0)
    segs, t, k = [], 0.0, 0
    while t < duration_s + 10.0:
        v = ((1.2, 0.6), (-1.2, -0.6), (0.0, 0.0))[k % 3]
        segs.append(fg.SetpointSegment(t, t + 6.0, "step", v, v))
        t, k = t + 6.0, k + 1
    flight = fg.FlightProfile(tuple(segs), (0.0, 1e4), (1.0, 1.0), 2.0)
    noise = fg.Noise(turbulence_n=0.3, turbulence_tau_s=0.6, accel_white_m_s2=0.05, accel_bias_x_m_s2=0.1)
    spec = dataclasses.replace(spec, duration_s=duration_s, warmup_s=2.0, flight=flight, effects=effects,
                               noise=noise, loss=fg.Loss(), wind_from_start=False, wind_to_end=False)
    fg.write_flight(spec, fg.simulate(spec), tmp_path, name)
    return tmp_path / f"{name}.tlog", tmp_path / f"{name}.toml"


def _problem(tlog, toml):
    from companion.diagnose.closed_loop.channels import extract
    from companion.diagnose.closed_loop.flowmodel import FlowProblem

    cfg = load_config(toml)
    data = extract(load_recording(tlog), cfg)
    return data, FlowProblem(data, mass_kg=cfg.airframe.mass_kg, gravity_m_s2=cfg.airframe.gravity_m_s2)


def test_the_inertial_residual_is_at_the_accelerometers_noise_at_the_true_range_offset(tmp_path):
    """A rangefinder that reads 0.15 m long makes the flow's velocity (h + 0.15) / h of the truth's,
    so the nominal inertial residual holds 15 % of every window's acceleration (at 1 m); at the true
    offset it is at the sensors' noise: the accelerometer's white 0.05 m/s^2 a sample at 50 Hz over a
    1 s window is 0.007 m/s^2, the flow's counts (0.0016 rad at 1 m over 0.2 s boundary means) about
    as much again; under 0.03 allows for both and the boundary means' shared samples. The force
    channel, with 0.3 N of turbulence, is far above that at either offset."""
    from companion.diagnose.closed_loop.flowmodel import IDX, NOMINAL

    data, fp = _problem(*_steps_flight(tmp_path, "offset", {"range_offset": {"offset": 0.15}}))
    assert len(fp.inertial_rows) >= 20  # the steps' windows
    p = NOMINAL.copy()
    p[IDX["offset"]] = 0.15
    at_truth = np.sqrt(np.mean(fp.inertial_residual(p) ** 2, axis=1))
    nominal = np.sqrt(np.mean(fp.inertial_residual(NOMINAL) ** 2, axis=1))
    force = np.sqrt(np.mean(fp.force_residual(p) ** 2, axis=1)) / fp.mass_kg
    assert np.all(at_truth < 0.03), at_truth
    assert np.all(nominal > 2.0 * at_truth), (nominal, at_truth)
    assert np.all(force > 2.0 * at_truth), (force, at_truth)


def test_the_accelerometer_confirms_a_true_offset_and_contradicts_a_false_one(tmp_path):
    """The same 0.15 m offset: the accelerometer's z for it is far above the confirming 3. On a
    flight without one, the same offset read into the flow makes the inertial residual 15 % of the
    acceleration worse: its z is far below the contradicting -2. A force (drag) does not change the
    inertial rows at all: no verdict."""
    from companion.diagnose.closed_loop.flowmodel import IDX, NOMINAL
    from companion.diagnose.closed_loop.groups import accelerometer_z

    p = NOMINAL.copy()
    p[IDX["offset"]] = 0.15
    _d, fp = _problem(*_steps_flight(tmp_path, "offset", {"range_offset": {"offset": 0.15}}))
    z, rows = accelerometer_z(fp, p, NOMINAL)
    assert rows >= 20 and z >= 3.0, (z, rows)
    _d, fp = _problem(*_steps_flight(tmp_path, "clean", {}))
    z, rows = accelerometer_z(fp, p, NOMINAL)
    assert rows >= 20 and z <= -2.0, (z, rows)
    drag = NOMINAL.copy()
    drag[IDX["b"]] = 0.5
    z, rows = accelerometer_z(fp, drag, NOMINAL)
    assert math.isnan(z) and rows == 0


def test_a_vehicle_without_an_accelerometer_is_not_checked(tmp_path):
    """The (0, 0, -1 g) placeholder a vehicle without an accelerometer sends gives no inertial rows
    and no verdict."""
    from companion.diagnose.closed_loop.flowmodel import IDX, NOMINAL, FlowProblem
    from companion.diagnose.closed_loop.groups import accelerometer_z

    data, fp = _problem(*_steps_flight(tmp_path, "clean", {}, duration_s=40.0))
    zero = np.zeros(data.n)
    blind = dataclasses.replace(data, accel_x_m_s2=zero, accel_y_m_s2=zero, accel_z_m_s2=zero - 9.81)
    fp = FlowProblem(blind, mass_kg=fp.mass_kg, gravity_m_s2=fp.g)
    p = NOMINAL.copy()
    p[IDX["offset"]] = 0.15
    assert len(fp.inertial_rows) == 0
    assert fp.inertial_residual(p).shape == (2, 0)
    z, rows = accelerometer_z(fp, p, NOMINAL)
    assert math.isnan(z) and rows == 0


def _weak_effect(seed: int, check=None) -> Selector:
    """A toy group: y = 0.006 x + noise 0.1 over 200 s (a Wald z of about 3), one effect fitting it."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 200.0, 0.05)
    x = np.sin(2 * np.pi * 0.07 * t) + 0.5 * np.sin(2 * np.pi * 0.31 * t + 1.0)
    y = 0.006 * x + rng.normal(0.0, 0.1, len(t))
    g = Group(name="toy", params=("a",), nominal=np.zeros(1), steps=np.array([1e-3]), lower=np.array([-10.0]),
              upper=np.array([10.0]), channels=("y",), units=("1",), floors=(1e-9,),
              residuals=lambda p: [y - p[0] * x], row_times=[t], candidates=[Candidate("effect_a", ("a",))],
              linear=("a",), check=check)
    return Selector(g, Settings(), 0.0)


def _held_out_reason(comp) -> bool:
    return any("held-out improvement" in r for r in comp.reasons)


def test_a_confirming_check_passes_the_held_out_test_and_a_contradicting_one_turns_the_effect_down():
    """Over seeds of a weak effect: wherever its own held-out z is between 0 and 2 (turned down for
    it), a check that confirms it (z 5) lifts that reason and nothing else; a check that contradicts
    it (z -3) turns down even an effect that passes everything else. Without rows the check is
    silent."""
    lifted = 0
    for seed in range(40):
        plain = _weak_effect(seed)
        with_ = plain.score_exact(["effect_a"], plain.g.nominal)
        without = plain.score_exact([], plain.g.nominal)
        base = plain.compare(with_, without, "effect_a")
        conf = _weak_effect(seed, check=lambda _a, _b: (5.0, 30))
        c = conf.compare(conf.score_exact(["effect_a"], conf.g.nominal), conf.score_exact([], conf.g.nominal),
                         "effect_a")
        assert c.check_z == 5.0 and c.check_rows == 30
        if 0.0 < base.cv_t < plain.s.cv_t_min:
            assert _held_out_reason(base) and not _held_out_reason(c)
            assert [r for r in c.reasons] == [r for r in base.reasons if "held-out improvement" not in r]
            lifted += 1
        else:
            assert c.reasons == base.reasons
        veto = _weak_effect(seed, check=lambda _a, _b: (-3.0, 30))
        v = veto.compare(veto.score_exact(["effect_a"], veto.g.nominal), veto.score_exact([], veto.g.nominal),
                         "effect_a")
        assert not v.significant and any("contradicts" in r for r in v.reasons)
        silent = _weak_effect(seed, check=lambda _a, _b: (math.nan, 0))
        s = silent.compare(silent.score_exact(["effect_a"], silent.g.nominal),
                           silent.score_exact([], silent.g.nominal), "effect_a")
        assert s.reasons == base.reasons
    assert lifted >= 1
