"""Sensor faults in the loop, end to end over UDP, and the rule that a single bad sample never
kicks the vehicle.

``tests/test_failsafe_e2e.py`` covers the faults that hold level until the data is good again
(flow quality 0, frozen or stopped flow, gyro frozen, saturated or stopped, range outside its
limits or stopped, a reboot, link loss); this module adds what it does not:

- one-frame outliers (a flow spike above the sensor's limit, one just below it, a rangefinder
  reading that jumps inside its limits): the vehicle's tracked command (its ATTITUDE_TARGET)
  never leaves the band of its commands just before the fault by more than two counts of flow
  through the P gain (1.9 deg; an unchecked 80-count spike is a 20 deg command, the range
  glitch 11.5 deg);
- sensors stuck on one value while their time runs on (flow counts, gyro rates): told from
  steady flight as soon as the vehicle turns, then held until the values change;
- a flow stream stopping and coming back, a reboot: no command beyond what the vehicle's real
  drift calls for;
- a link lost and back (a hand-made vehicle that falls silent): level commands at the frame
  rate, then control again from where it was.

The session flies in lockstep with a 2 N wind on each axis and a constant 0.5 m/s setpoint on
each axis, so the normal command is a steady lean into the wind (5.06 deg) while the flow sees
motion (6.4 counts per frame per axis at 1 m): a range glitch then moves the estimate, and stuck
counts are not the counts of a vehicle at rest.

Run time (2 shared cores): about 25 s.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pytest
from loop_helpers import Gcs, Procs
from test_robust_link import LEAN_RAD, FakeVehicle

from companion.mavlink.live import TEXT_REPEAT_S
from companion.mavlink.outbound import quaternion_to_euler

WIND_N = 2.0
MASS_KG, G = 2.3, 9.81  # Table VI
KP = 0.2  # rad/(m/s), Table VI
ZETA, OMEGA_P_RAD_S = 0.71, 5.4  # Table VI: the attitude loop
SETPOINT_M_S = 0.5
Q_RAD, T_S, ALT_M = 0.09 / 57.3, 0.02, 1.0  # Table VI
#: one count of flow through the P gain: the quantization of eq. 9-11 (Q / T x A = 0.0785 m/s at
#: 1 m) is 0.9 deg of command
COUNT_RAD = KP * Q_RAD / T_S * ALT_M
#: the tracked command may leave the band of its 50 pre-fault values by two counts more (the
#: chatter of steady flight has periods longer than the band), plus 0.1 deg: 1.9 deg. A kick is
#: far beyond: the 3 m range reading would be 11.5 deg, the 80-count spike the 20 deg limit
BAND_TOL_RAD = 2 * COUNT_RAD + math.radians(0.1)
#: the flight's cap on lockstep speed (times real time)
LOCKSTEP_CAP = 4.0


def _angles(at: Any) -> tuple[float, float]:
    roll, pitch, _ = quaternion_to_euler(at.q)
    return roll, pitch


class Flight:
    """The vehicle (lockstep) and the companion (``--arm --setpoint 0.5,0.5``), watched by a GCS
    that keeps only the vehicle's ATTITUDE_TARGET (the command it tracks) and STATUSTEXTs."""

    def __init__(self, procs: Procs) -> None:
        # lockstep, but at most LOCKSTEP_CAP x real time: the GCS here (a Python loop sharing two
        # cores with the vehicle and the companion) reads every ATTITUDE_TARGET; uncapped, the loop
        # outruns it, its socket overflows (a PARAM_VALUE lost) and its view of the vehicle's clock
        # falls behind, so a hold it ends "at once" lasts many simulated seconds
        self.vehicle, self.port = procs.vehicle("--lockstep", "--max-speedup", str(LOCKSTEP_CAP))
        self.companion = procs.companion(self.port, "--arm", "--quiet", "--setpoint",
                                         f"{SETPOINT_M_S},{SETPOINT_M_S}")
        self.gcs = Gcs(self.port)
        self.gcs.wait_vehicle()
        self.gcs.quiet({"ATTITUDE_TARGET": 50.0})
        assert self.gcs.set_param("SIM_WIND_FX", -WIND_N).param_value == -WIND_N
        assert self.gcs.set_param("SIM_WIND_FY", WIND_N).param_value == WIND_N
        self.gcs.wait_time(8.0)  # the PI settles on its lean at 0.5 m/s

    def targets(self, n: int) -> np.ndarray:
        """The next ``n`` tracked commands, (n, 2) [roll, pitch] rad."""
        return np.array([_angles(self.gcs.recv("ATTITUDE_TARGET", cond=lambda m: m.get_srcComponent() == 1))
                         for _ in range(n)])

    def band(self, n: int = 50, timeout_s: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) on each axis of ``n`` consecutive commands once the flight has settled: a
        lean into the wind whose commands differ by no more than two counts of flow through Kp
        (the quantization chatter of steady flight)."""
        # the companion says a cause again only TEXT_REPEAT_S of wall time after it last said it (its
        # rate limit for the link); in lockstep the previous test's fault may be far less wall time
        # ago, so let that pass first: each test's fault is then announced by its own text
        self.gcs.drain(TEXT_REPEAT_S + 0.1)
        deadline = time.monotonic() + timeout_s
        while True:
            t = self.targets(n)
            lo, hi = t.min(axis=0), t.max(axis=0)
            if np.all(hi - lo <= 2 * COUNT_RAD + 1e-6) and np.all(np.abs(t + LEAN_RAD) < 0.3 * LEAN_RAD):
                return lo, hi
            assert time.monotonic() < deadline, f"never settled: {lo} {hi}"

    def texts_since(self, k: int) -> list[str]:
        return [s[3] for s in self.gcs.statustexts[k:]]


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    with Procs(tmp_path_factory.mktemp("robust_faults")) as procs:
        f = Flight(procs)
        try:
            yield f
        finally:
            f.gcs.close()


def _assert_in_band(during: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float = BAND_TOL_RAD) -> None:
    assert np.all(np.isfinite(during))
    over = np.maximum(during - hi, lo - during).max()
    assert over <= tol, f"command left the pre-fault band by {math.degrees(over):.3f} deg"


def _assert_leaning(lo: np.ndarray, hi: np.ndarray) -> None:
    """A lean into the wind: nose down, left side down, near atan(F / m g)."""
    assert np.all(hi < -0.6 * LEAN_RAD) and np.all(lo > -1.6 * LEAN_RAD), (lo, hi)


SPIKES = [
    (500, "flow spike"),  # above the sensor's 7.4 rad/s (94 counts): the core's spike gate
    (80, "velocity jump"),  # below it: 6.3 m/s of estimate in one frame, the cross-frame gate
    (-30000, "flow spike"),
]


@pytest.mark.parametrize("counts,cause", SPIKES, ids=[str(c) for c, _ in SPIKES])
def test_a_one_frame_flow_spike_never_kicks_the_vehicle(flight, counts, cause):
    lo, hi = flight.band()
    _assert_leaning(lo, hi)
    k = len(flight.gcs.statustexts)
    assert flight.gcs.set_param("SIM_FLOW_SPIKE", counts).param_value == counts
    flight.gcs.set_param("SIM_FLOW_FAULT", 3)  # one frame, then it clears itself
    during = flight.targets(25)
    flight.gcs.wait_text("flowhold: resumed", since=k)
    texts = flight.texts_since(k)
    assert f"flowhold: HOLD {cause}" in texts and texts.count("flowhold: resumed") == 1, texts
    # the held frame is level (below the band: never beyond it); every other one stays in the band
    level = np.all(np.abs(during) < 1e-4, axis=1)
    assert level.sum() == 1, during
    _assert_in_band(during[~level], lo, hi)


@pytest.mark.parametrize("jump_m", [2.0, -0.9])
def test_a_one_reading_range_jump_never_kicks_the_vehicle(flight, jump_m):
    """At 1 m, 0.5 m/s per axis: a reading of 3 m would make eq. 15 read 1.5 m/s, of 0.1 m
    0.05 m/s: a 0.2 rad kick from the P term alone (Kp = 0.2 rad per m/s). It is held instead."""
    lo, hi = flight.band()
    k = len(flight.gcs.statustexts)
    assert flight.gcs.set_param("SIM_RNG_JUMP", jump_m).param_value == pytest.approx(jump_m)
    flight.gcs.set_param("SIM_RNG_FAULT", 4)  # one reading, then it clears itself
    during = flight.targets(25)
    flight.gcs.wait_text("flowhold: resumed", since=k)
    assert "flowhold: HOLD velocity jump" in flight.texts_since(k)
    level = np.all(np.abs(during) < 1e-4, axis=1)
    assert level.sum() == 1
    _assert_in_band(during[~level], lo, hi)


def _provoke_a_turn(flight: Flight, text: str, timeout_s: float = 30.0) -> list[str]:
    """GCS velocity steps (1.5 m/s forward, then back) until ``text`` comes: the vehicle pitches,
    which a working flow sensor and gyro would both see."""
    k = len(flight.gcs.statustexts)
    deadline = time.monotonic() + timeout_s
    vx = 1.5
    while not any(text in t for t in flight.texts_since(k)):
        assert time.monotonic() < deadline, flight.texts_since(k)
        flight.gcs.velocity(vx, SETPOINT_M_S)
        flight.gcs.wait_time(flight.gcs.vehicle_time_s + 0.5)  # simulated time: the same turn under any load
        vx = -vx
    return flight.texts_since(k)


@pytest.mark.parametrize("param,value,cause", [("SIM_FLOW_FAULT", 5, "flow frozen"),
                                               ("SIM_GYRO_FAULT", 4, "gyro frozen")])
def test_a_stuck_sensor_is_held_once_the_vehicle_turns(flight, param, value, cause):
    """Counts (or rates) stuck on their last value while time runs on. In steady flight that is
    what a working sensor would report too; the first turn gives it away (eq. 15's rotation
    term is missing from the flow, or the gyro disagrees with the autopilot's attitude). Without
    the check, stuck counts at 0.5 m/s leave a constant error that the integrator winds up into a
    flyaway. Held level until the values change, then control resumes."""
    k = len(flight.gcs.statustexts)
    assert flight.gcs.set_param(param, value).param_value == value
    _provoke_a_turn(flight, f"flowhold: HOLD {cause}")
    held = flight.targets(20)
    assert np.all(np.abs(held) < 1e-4), held  # level while it lasts
    assert flight.gcs.set_param(param, 0).param_value == 0
    flight.gcs.wait_text("flowhold: resumed", since=k)
    flight.gcs.wait_time(flight.gcs.vehicle_time_s + 5.0)  # back on the setpoint
    _assert_leaning(*flight.band())


def test_flow_stopping_and_coming_back_resumes_without_a_kick(flight):
    """About 0.3 s without flow: held level, the integrator frozen, while the wind pushes the
    levelling vehicle at up to F / m. Back, the commands answer only that drift, which goes on
    until the attitude loop has leaned the vehicle again (two of its time constants,
    2 / (zeta Omega_p) = 0.52 s with Table VI's 0.71 and 5.4 rad/s): at most
    Kp x (F / m) x (hold + 0.52 s) beyond the band. No sample of the returning stream adds to it."""
    lo, hi = flight.band()
    gcs = flight.gcs
    t0 = gcs.wait_time(gcs.vehicle_time_s)
    gcs.set_param("SIM_FLOW_FAULT", 4)
    targets, resumed_at, cleared = [], None, False
    while resumed_at is None or len(targets) < resumed_at + 25:
        m = gcs.recv(("ATTITUDE_TARGET", "STATUSTEXT"), timeout_s=30)
        if m.get_type() == "ATTITUDE_TARGET" and m.get_srcComponent() == 1:
            targets.append(_angles(m))
            if not cleared and gcs.vehicle_time_s >= t0 + 0.3:
                gcs.conn.mav.param_set_send(1, 1, b"SIM_FLOW_FAULT", 0.0, 2)  # answered later, unread
                cleared = True
        elif m.get_type() == "STATUSTEXT" and m.text == "flowhold: resumed" and cleared:
            resumed_at = len(targets)
    t = np.array(targets)
    level = np.all(np.abs(t) < 1e-4, axis=1)
    hold_s = level.sum() * T_S
    assert 0.2 <= hold_s <= 1.0, hold_s
    bound = KP * WIND_N / MASS_KG * (hold_s + 2.0 / (ZETA * OMEGA_P_RAD_S))
    _assert_in_band(t[resumed_at:], lo, hi, tol=bound + BAND_TOL_RAD)


def test_a_reboot_never_kicks_the_vehicle(flight):
    lo, hi = flight.band()
    k = len(flight.gcs.statustexts)
    flight.gcs.set_param("SIM_REBOOT", 1)
    during = flight.targets(50)
    _assert_in_band(during, lo, hi)
    assert not [t for t in flight.texts_since(k) if "HOLD" in t]
    flight.companion.wait_for("clock restarted")


# ---------------------------------------------------------------------------------------------
# A link lost and back (the hand-made vehicle of test_robust_link falls silent for 1 s)


def test_link_lost_and_back(tmp_path, paper_cfg):
    fv = FakeVehicle(paper_cfg)
    try:
        with Procs(tmp_path) as procs:
            comp = procs.companion(fv.port, "--quiet")
            fv.wait_companion()
            fv.fly(150)
            before = np.array([(r, p) for _ms, r, p in fv.commands[-25:]])
            n_sent = len([m for m in fv.received if m.get_type() == "SET_ATTITUDE_TARGET"])
            t_quiet = time.monotonic()
            fv.pump(time.monotonic() + 1.0, None)  # silence: nothing sent for 1 s, everything received
            quiet_s = time.monotonic() - t_quiet
            during = [m for m in fv.received if m.get_type() == "SET_ATTITUDE_TARGET"][n_sent:]
            fv.fly(50)
            after = np.array([(r, p) for _ms, r, p in fv.commands[-50:]])
            assert comp.stop() == 0
    finally:
        fv.close()
    texts = fv.texts()
    assert "flowhold: HOLD link lost" in texts and texts[-1] == "flowhold: resumed", texts
    # level commands at the frame rate once flow_timeout_s (0.1 s) has passed
    assert len(during) == pytest.approx(50 * (quiet_s - 0.1), rel=0.25)
    assert all(max(abs(a) for a in quaternion_to_euler(m.q)[:2]) == 0.0 for m in during)
    # the simulated time stood still: control takes up where it was, no kick
    _assert_in_band(after, before.min(axis=0), before.max(axis=0))
    assert fv.missed == 0


# ---------------------------------------------------------------------------------------------
# The cross-frame checks (companion.step.core.Plausibility) alone: closed-form bounds, and no false
# alarm in the paper's scenarios or a noisy flight


@pytest.fixture(scope="module")
def params(paper_cfg):
    from companion.step.core import PlausibilityParams

    return PlausibilityParams.from_config(paper_cfg)


def test_plausibility_bounds_are_table_vi(params):
    assert params.max_accel_m_s2 == pytest.approx(2 * G * math.tan(math.radians(20.0)))  # 7.14 m/s^2
    assert params.jump_noise_rad_s == pytest.approx(8 * Q_RAD / T_S)  # 8 counts per frame: 0.628 rad/s
    assert params.frozen_frames == 25  # 0.5 s at 50 Hz
    assert params.frozen_rotation_rad_s == pytest.approx(3 * Q_RAD / T_S)


def test_velocity_jump_gate_closed_form(params):
    from companion.step.core import HoldCause as LiveCause
    from companion.step.core import Plausibility

    allowed = params.max_accel_m_s2 * T_S + params.jump_noise_rad_s * ALT_M  # 0.771 m/s one frame later at 1 m
    for dv, vetoed in ((allowed - 1e-3, False), (allowed + 1e-3, True)):
        p = Plausibility(params)
        assert p.check(1.0, (0.1, 0.1), (0.0, 0.0), (0.5, 0.5), ALT_M, None) is None
        got = p.check(1.0 + T_S, (0.2, 0.1), (0.0, 0.0), (0.5 + dv, 0.5), ALT_M, None)
        assert got is (LiveCause.VELOCITY_JUMP if vetoed else None), dv
    # the lower of the two ranges sets the noise allowance: a reading of 0.1 m after 1 m
    p = Plausibility(params)
    p.check(1.0, (0.1, 0.1), (0.0, 0.0), (0.5, 0.5), 1.0, None)
    small = params.max_accel_m_s2 * T_S + params.jump_noise_rad_s * 0.1  # 0.206 m/s
    assert p.check(1.0 + T_S, (0.1, 0.1), (0.0, 0.0), (0.5 - small - 1e-3, 0.5), 0.1, None) is LiveCause.VELOCITY_JUMP
    # an outlier is held for at most 3 frames; a change that lasts is real: the 4th frame re-anchors on it
    p = Plausibility(params)
    p.check(1.0, (0.1, 0.1), (0.0, 0.0), (0.0, 0.0), 1.0, None)
    got = [p.check(1.0 + k * T_S, (0.1 * k, 0.1), (0.0, 0.0), (3.0, 0.0), 1.0, None) for k in range(1, 6)]
    assert got == [LiveCause.VELOCITY_JUMP] * 3 + [None, None]
    # the allowance grows with the time since the last accepted frame (a long hold, then good data)
    p = Plausibility(params)
    p.check(1.0, (0.1, 0.1), (0.0, 0.0), (0.0, 0.0), 1.0, None)
    assert p.check(2.0, (0.2, 0.1), (0.0, 0.0), (7.0, 0.0), 1.0, None) is None  # 7 m/s in 1 s < 7.14 + 0.63


def test_frozen_flow_and_gyro_closed_form(params):
    from companion.step.core import HoldCause as LiveCause
    from companion.step.core import Plausibility

    n, thr = params.frozen_frames, params.frozen_rotation_rad_s
    for span, frozen in ((0.9 * thr, False), (1.1 * thr, True)):
        p = Plausibility(params)
        got = [p.check(1.0 + k * T_S, (0.01, 0.0), (0.0, span * (k % 2)), (0.0, 0.0), 1.0, None) for k in range(n)]
        assert got[:-1] == [None] * (n - 1)
        assert got[-1] is (LiveCause.FLOW_FROZEN if frozen else None)
    # held until the value changes, whatever the gyro does then
    assert p.check(1.0 + n * T_S, (0.01, 0.0), (0.0, 0.0), (0.0, 0.0), 1.0, None) is LiveCause.FLOW_FROZEN
    assert p.check(1.0 + (n + 1) * T_S, (0.02, 0.0), (0.0, 0.0), (0.0, 0.0), 1.0, None) is None
    # the gyro: the same rates while ATTITUDE says the vehicle turns
    p = Plausibility(params)
    got = [p.check(1.0 + k * T_S, (0.001 * k, 0.0), (0.01, 0.02), (0.0, 0.0), 1.0, (0.0, 1.1 * thr * (k % 2)))
           for k in range(n)]
    assert got == [None] * (n - 1) + [LiveCause.GYRO_FROZEN]
    # a clock that goes back (a reboot) forgets the history
    assert p.check(0.5, (0.5, 0.0), (0.01, 0.02), (0.0, 0.0), 1.0, None) is None


def _flown_vetoes(run: Any, params: Any) -> int:
    from companion.step.core import Plausibility

    p = Plausibility(params)
    c = run.columns
    vetoes = 0
    for i in np.flatnonzero(c["hold"] == 0):
        gyro = (round(c["gyro_x_rad_s"][i] * 1e3) * 1e-3, round(c["gyro_y_rad_s"][i] * 1e3) * 1e-3)  # RAW_IMU mrad/s
        vetoes += p.check(c["t_s"][i], (c["flow_x_counts"][i] * Q_RAD, c["flow_y_counts"][i] * Q_RAD), gyro,
                          (c["est_vx_m_s"][i], c["est_vy_m_s"][i]), c["range_m"][i],
                          (c["roll_rate_rad_s"][i], c["pitch_rate_rad_s"][i])) is not None
    return vetoes


@pytest.mark.parametrize("name", ["step", "gust", "slow"])
def test_no_false_alarm_in_the_paper_scenarios(paper_cfg, params, name):
    from simvehicle.engines.scenarios import SCENARIOS, fly

    assert _flown_vetoes(fly(paper_cfg, SCENARIOS[name]), params) == 0


def test_no_false_alarm_in_a_noisy_varied_flight(paper_cfg, params):
    """20 s of varied flight with the gyro noise and rangefinder noise of the diagnosis flights."""
    from simvehicle.engines.flights import flight_plan, with_sensor_noise
    from simvehicle.engines.scenarios import fly

    run = fly(with_sensor_noise(paper_cfg), flight_plan(5, duration_s=20.0).scenario(), seed=5)
    assert np.abs(run["pitch_cmd_rad"]).max() > math.radians(5)  # it does manoeuvre
    assert _flown_vetoes(run, params) == 0


def test_every_test_named_in_docs_robustness_exists():
    """docs/robustness.md links each row to its test: each ``file.py::test_name`` is there."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parent
    doc = (root.parent / "docs" / "robustness.md").read_text()
    refs = re.findall(r"`(test_\w+\.py)::(\w+)", doc)
    assert len(refs) > 30
    for fname, test in refs:
        assert re.search(rf"^def {test}\(", (root / fname).read_text(), re.M), f"{fname}::{test}"


@pytest.mark.parametrize("seed", range(40))
def test_plausibility_columns_equal_frame_by_frame_checks(paper_cfg, seed):
    """Replay's screened column form of the cross-frame checks gives the same vetoes as calling
    ``Plausibility.check`` on every frame, on sequences built to trip every check (and not)."""
    from companion.step.core import Plausibility, PlausibilityParams, plausibility_columns

    rng = np.random.default_rng(seed)
    params = PlausibilityParams.from_config(paper_cfg)
    n = int(rng.integers(1, 400))
    t = np.cumsum(rng.choice([0.02, 0.02, 0.02, 0.04, -0.01 if seed % 7 == 0 else 0.02], n))
    q = paper_cfg.flow_sensor.q_rad_per_count
    fx = np.round(rng.normal(0, 2, n)) * q
    fy = np.round(rng.normal(0, 2, n)) * q
    gx, gy = rng.normal(0, 0.1 * (seed % 3), n), rng.normal(0, 0.1 * (seed % 3), n)
    for _ in range(int(rng.integers(0, 4))):  # frozen runs of flow or gyro
        a = int(rng.integers(0, n))
        b = min(n, a + int(rng.integers(5, 60)))
        if rng.random() < 0.5:
            fx[a:b], fy[a:b] = fx[a], fy[a]
        else:
            gx[a:b], gy[a:b] = gx[a], gy[a]
    vx = np.cumsum(rng.normal(0, 0.02, n))
    vy = np.cumsum(rng.normal(0, 0.02, n))
    for i in rng.integers(0, n, int(rng.integers(0, 4))):  # jumps
        vx[i] += rng.choice([-1, 1]) * rng.uniform(0.5, 3)
    rng_m = rng.uniform(0.5, 2, n)
    ax, ay = rng.normal(0, 0.2, n), rng.normal(0, 0.2, n)
    ax[rng.random(n) < 0.05] = np.nan
    got = plausibility_columns(params, t, fx, fy, gx, gy, vx, vy, rng_m, ax, ay)
    ref = Plausibility(params)
    want = []
    for i in range(n):
        rates = (ax[i], ay[i]) if np.isfinite(ax[i]) and np.isfinite(ay[i]) else None
        v = ref.check(float(t[i]), (float(fx[i]), float(fy[i])), (float(gx[i]), float(gy[i])),
                      (float(vx[i]), float(vy[i])), float(rng_m[i]), rates)
        if v is not None:
            want.append((i, v))
    assert got == want
