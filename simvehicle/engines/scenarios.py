"""The paper's scenarios, run in simulation time (no sleeping), and their figures of merit.

Closed loop (both axes at once, the same profile on x and y):
- ``step``: velocity setpoint 0 -> 2 m/s at 5 s (Fig. 16);
- ``gust``: a 4 N headwind from 5 s (Fig. 17);
- ``slow``: setpoint 0 -> 1 cm/s at 2 s (Fig. 18-19).
Open loop, the flow sensor moved on a rail with no rotation:
- ``rail``: constant 0.05, 0.1, 0.2, 0.3 m/s at 0.66 m (Table V, Fig. 5-6);
- ``triangle``: back-and-forth at 17 cm and 62.5 cm, sampled at 25 Hz (Fig. 9).
Their recordings (``--tlog``) hold what the sensor produced: the runs one after the other on one
clock, each introduced by a STATUSTEXT, with the slider's position as LOCAL_POSITION_NED.

A closed-loop run pushes every vehicle message through MAVLink encoding and decoding and feeds
the companion's ``MessageRouter``, so the scenario, the live loop and replay of its recording
run the same code on the same numbers.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.config import Config
from companion.mavlink import outbound
from companion.mavlink.inbound import MessageRouter
from companion.recordings.tlog_writer import SIM_EPOCH_S, TlogWriter
from companion.step.core import CompanionCore
from companion.step.profiles import Profile
from simvehicle.model import telemetry
from simvehicle.model.flow_sensor import flow_frame
from simvehicle.model.sim import FrameSample, Simulator, Turbulence

#: UNIX time of scenario time 0 in recordings (2026-01-01T00:00:00Z): headers = TLOG_EPOCH_S + t
TLOG_EPOCH_S = SIM_EPOCH_S
VEHICLE_SYSID = 1

Pair = tuple[float, float]


@dataclass(frozen=True)
class Scenario:
    """A closed-loop flight: setpoint and external force as functions of time (body axes)."""

    name: str
    duration_s: float
    setpoint: Callable[[float], Pair]
    force: Callable[[float], Pair] = lambda _t: (0.0, 0.0)
    altitude: Callable[[float], float] | None = None
    turbulence_sigma_n: float = 0.0
    turbulence_tau_s: float = 1.0
    description: str = ""


def _step_at(t0: float, value: float) -> Callable[[float], Pair]:
    return lambda t: (value, value) if t >= t0 else (0.0, 0.0)


SCENARIOS: dict[str, Scenario] = {
    "step": Scenario("step", 15.0, _step_at(5.0, 2.0),
                     description="velocity setpoint 0 -> 2 m/s at 5 s on both axes (Fig. 16)"),
    "gust": Scenario("gust", 25.0, lambda _t: (0.0, 0.0), force=lambda t: (-4.0, -4.0) if t >= 5.0 else (0.0, 0.0),
                     description="4 N headwind (and 4 N from the right) from 5 s, setpoint 0 (Fig. 17)"),
    "slow": Scenario("slow", 12.0, _step_at(2.0, 0.01),
                     description="velocity setpoint 0 -> 1 cm/s at 2 s on both axes (Fig. 18-19)"),
}
OPEN_LOOP = ("rail", "triangle")
ALL_SCENARIOS = (*SCENARIOS, *OPEN_LOOP)


@dataclass
class Run:
    """A finished run: per-frame columns (numpy arrays) and where its recording went."""

    name: str
    columns: dict[str, np.ndarray]
    tlog: Path | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __getitem__(self, key: str) -> np.ndarray:
        return self.columns[key]


_COLUMNS = ("t_s", "vx_m_s", "vy_m_s", "x_m", "y_m", "roll_rad", "pitch_rad", "roll_rate_rad_s",
            "pitch_rate_rad_s", "flow_x_counts", "flow_y_counts", "gyro_x_rad_s", "gyro_y_rad_s", "range_m",
            "est_vx_m_s", "est_vy_m_s", "vx_set_m_s", "vy_set_m_s", "roll_cmd_rad", "pitch_cmd_rad", "hold")


def fly(cfg: Config, scenario: Scenario, *, profile: Profile = Profile.PAPER, seed: int = 0,
        tlog: str | Path | None = None) -> Run:
    """Fly ``scenario`` closed loop with the companion; optionally record a .tlog."""
    rng = np.random.default_rng(seed)
    turb = Turbulence(scenario.turbulence_sigma_n, scenario.turbulence_tau_s) \
        if scenario.turbulence_sigma_n > 0 else None
    sim = Simulator(cfg, rng=rng, external_force=scenario.force, altitude=scenario.altitude, turbulence=turb)
    core = CompanionCore(cfg, profile)
    router = MessageRouter(core, profile, vehicle_sysid=VEHICLE_SYSID)
    veh = mav.MAVLink(None, srcSystem=VEHICLE_SYSID, srcComponent=1)
    comp = mav.MAVLink(None, srcSystem=VEHICLE_SYSID, srcComponent=outbound.COMPANION_COMPONENT)
    parser = mav.MAVLink(None)
    writer = _open_tlog(tlog)
    q = cfg.flow_sensor.q_rad_per_count
    T = cfg.flow_sensor.frame_period_s
    rf = cfg.rangefinder
    n_frames = int(round(scenario.duration_s / T))
    cols: dict[str, list[float]] = {c: [] for c in _COLUMNS}
    s = sim.current
    try:
        for k in range(n_frames + 1):
            t = s.t_s
            stamp = TLOG_EPOCH_S + t
            if k % int(round(1.0 / T)) == 0:
                _emit(writer, telemetry.heartbeat(veh, armed=True), veh, stamp)
            core.set_setpoint(*scenario.setpoint(t))
            out = None
            for m in telemetry.frame_messages(veh, s, profile, q, T, rf.min_m, rf.max_m):
                decoded = parser.decode(bytearray(_emit(writer, m, veh, stamp)))
                step = router.handle(decoded)
                out = step if step is not None else out
            assert out is not None, "every frame carries one flow message"
            ms = int(round(t * 1e3))
            _emit(writer, outbound.set_attitude_target(comp, ms, VEHICLE_SYSID, out.roll_cmd_rad,
                                                       out.pitch_cmd_rad, 0.0), comp, stamp)
            _emit(writer, outbound.position_target(comp, ms, out.vx_set_m_s, out.vy_set_m_s), comp, stamp)
            if not out.holding:
                _emit(writer, outbound.vision_speed(comp, int(round(t * 1e6)), out.vx_m_s, out.vy_m_s), comp,
                      stamp)
            _emit(writer, telemetry.attitude_target(veh, t, *sim.u_active), veh, stamp)
            for name, value in (("t_s", t), ("vx_m_s", s.vx_m_s), ("vy_m_s", s.vy_m_s), ("x_m", s.x_m),
                                ("y_m", s.y_m), ("roll_rad", s.roll_rad), ("pitch_rad", s.pitch_rad),
                                ("roll_rate_rad_s", s.roll_rate_rad_s), ("pitch_rate_rad_s", s.pitch_rate_rad_s),
                                ("flow_x_counts", s.flow_x_counts), ("flow_y_counts", s.flow_y_counts),
                                ("gyro_x_rad_s", s.gyro_x_rad_s), ("gyro_y_rad_s", s.gyro_y_rad_s),
                                ("range_m", s.range_m), ("est_vx_m_s", out.vx_m_s), ("est_vy_m_s", out.vy_m_s),
                                ("vx_set_m_s", out.vx_set_m_s), ("vy_set_m_s", out.vy_set_m_s),
                                ("roll_cmd_rad", out.roll_cmd_rad), ("pitch_cmd_rad", out.pitch_cmd_rad),
                                ("hold", float(out.holding))):
                cols[name].append(value)
            if k < n_frames:
                s = sim.advance(out.roll_cmd_rad, out.pitch_cmd_rad)
    finally:
        if writer is not None:
            writer.close()
    return Run(scenario.name, {k: np.asarray(v, dtype=float) for k, v in cols.items()},
               Path(tlog) if tlog else None, {"profile": profile.value, "seed": seed})


def _open_tlog(path: str | Path | None) -> TlogWriter | None:
    if path is None:
        return None
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return TlogWriter(path)


def _emit(writer: TlogWriter | None, msg: Any, enc: Any, stamp_s: float) -> bytes:
    buf = msg.pack(enc)
    if writer is not None:
        writer.write_bytes(buf, stamp_s)
    return buf


# ---------------------------------------------------------------------------------------------
# Open-loop rail experiments (no rotation: the scene angle is exactly -position / A)


RAIL_SPEEDS_M_S = (0.05, 0.1, 0.2, 0.3)  # Table V
RAIL_ALTITUDE_M = 0.66
RAIL_Q_RAD_PER_COUNT = 0.0015  # Table V's derived quantization step
RAIL_TRAVEL_M = 0.53  # Fig. 6: about 0.52 m summed at every speed
#: Table V, measured output rate (counts/s) for each speed, for comparison only
TABLE_V_OUTPUT_RATE = {0.05: 50.8, 0.1: 102.5, 0.2: 199.0, 0.3: 294.0}

TRIANGLE_SPEED_M_S = 0.2  # what 31.4 and 8.5 counts/sample need (the text's 0.02 m/s is a slip)
TRIANGLE_RATE_HZ = 25.0
TRIANGLE_ALTITUDES_M = (0.17, 0.625)
TRIANGLE_LEG_S = 2.0


def _open_loop_counts(position_m: Callable[[float], float], altitude_m: float, duration_s: float,
                      frame_s: float, q_rad_per_count: float) -> tuple[np.ndarray, np.ndarray]:
    """Flow counts of a sensor translated without rotation: phi(t) = -(x(t) - x(0)) / A (eq. 8)."""
    n = int(round(duration_s / frame_s))
    t = np.arange(n + 1) * frame_s
    counts = np.zeros(n + 1, dtype=int)
    prev = (0, 0)
    x0 = position_m(0.0)
    for k in range(1, n + 1):
        phi = -(position_m(float(t[k])) - x0) / altitude_m
        prev, (dx, _dy) = flow_frame(phi, 0.0, prev, q_x_rad_per_count=q_rad_per_count,
                                     q_y_rad_per_count=q_rad_per_count)
        counts[k] = dx
    return t, counts

@dataclass
class OpenLoopRun:
    """One open-loop run for the recording: the slider's position, the sensor's height, its
    frame times and the counts it produced, and the line that introduces it (STATUSTEXT)."""

    label: str
    position_m: Callable[[float], float]
    altitude_m: float
    t_s: np.ndarray
    counts: np.ndarray


def _slider_velocity(position_m: Callable[[float], float], t_s: float, frame_s: float) -> float:
    """The slider's mean velocity over the frame ending at ``t_s`` (what the counts measure)."""
    return (position_m(t_s) - position_m(max(t_s - frame_s, 0.0))) / frame_s if t_s > 0 else 0.0


def _record_open_loop(path: str | Path, runs: list[OpenLoopRun], frame_s: float, q_rad_per_count: float,
                      profile: Profile, cfg: Config) -> None:
    """Record open-loop runs as the sensor produced them (CONVENTIONS.md, "Scenario run"): one
    after the other on one clock, each introduced by a STATUSTEXT; per frame RAW_IMU (no
    rotation: zero rates), DISTANCE_SENSOR (the height), the flow message in ``profile``,
    ATTITUDE (level) and LOCAL_POSITION_NED (the slider: x along the rail, the truth); a
    disarmed HEARTBEAT each second. Time fields are scenario time; headers TLOG_EPOCH_S + t."""
    veh = mav.MAVLink(None, srcSystem=VEHICLE_SYSID, srcComponent=1)
    rf = cfg.rangefinder
    writer = _open_tlog(path)
    assert writer is not None
    per_s = int(round(1.0 / frame_s))
    offset = 0.0
    try:
        for run in runs:
            _emit(writer, _info_text(veh, run.label), veh, TLOG_EPOCH_S + offset)
            for k, (t_run, dx) in enumerate(zip(run.t_s, run.counts, strict=True)):
                t = offset + float(t_run)
                stamp = TLOG_EPOCH_S + t
                if k % per_s == 0:
                    _emit(writer, telemetry.heartbeat(veh, armed=False, custom_mode=0), veh, stamp)
                x = run.position_m(float(t_run)) - run.position_m(0.0)
                s = FrameSample(frame=k, t_s=t, flow_x_counts=int(dx), flow_y_counts=0, flow_quality=255,
                                gyro_x_rad_s=0.0, gyro_y_rad_s=0.0, gyro_z_rad_s=0.0, range_m=run.altitude_m,
                                roll_rad=0.0, pitch_rad=0.0, roll_rate_rad_s=0.0, pitch_rate_rad_s=0.0,
                                vx_m_s=_slider_velocity(run.position_m, float(t_run), frame_s), vy_m_s=0.0,
                                x_m=x, y_m=0.0, altitude_m=run.altitude_m, phi_x_rad=-x / run.altitude_m,
                                phi_y_rad=0.0, force_x_n=0.0, force_y_n=0.0, roll_cmd_active_rad=0.0,
                                pitch_cmd_active_rad=0.0)
                for m in telemetry.frame_messages(veh, s, profile, q_rad_per_count, frame_s, rf.min_m, rf.max_m):
                    _emit(writer, m, veh, stamp)
            offset += float(run.t_s[-1]) + frame_s  # the next run starts one frame later
    finally:
        writer.close()


def _info_text(enc: Any, text: str) -> Any:
    """A STATUSTEXT (INFO) naming what follows in a recording."""
    return enc.statustext_encode(mav.MAV_SEVERITY_INFO, text.encode("ascii", "replace")[:50])


def rail_position(speed_m_s: float, still_s: float = 2.0) -> tuple[Callable[[float], float], float]:
    """The rail's slider: still, then at ``-speed`` (the rail ran in the negative direction) over
    RAIL_TRAVEL_M, then still. Returns (position function, duration)."""
    move_s = RAIL_TRAVEL_M / speed_m_s

    def x(t: float) -> float:
        return -speed_m_s * min(max(t - still_s, 0.0), move_s)

    return x, still_s + move_s + still_s


def run_rail(cfg: Config, *, tlog: str | Path | None = None, profile: Profile = Profile.PAPER) -> Run:
    """The four constant-speed rail runs of Table V at 0.66 m with Q = 0.0015 rad/count.
    ``tlog``: record what the sensor produced, the four runs one after the other (``profile``:
    the flow message's convention)."""
    T = cfg.flow_sensor.frame_period_s
    cols: dict[str, np.ndarray] = {}
    rows = []
    recorded: list[OpenLoopRun] = []
    for v in RAIL_SPEEDS_M_S:
        pos, dur = rail_position(v)
        t, c = _open_loop_counts(pos, RAIL_ALTITUDE_M, dur, T, RAIL_Q_RAD_PER_COUNT)
        recorded.append(OpenLoopRun(f"rail {v:g} m/s at {RAIL_ALTITUDE_M:g} m, Q {RAIL_Q_RAD_PER_COUNT:g}",
                                    pos, RAIL_ALTITUDE_M, t, c))
        cols[f"t_s_{v}"], cols[f"counts_{v}"] = t, c.astype(float)
        moving = (t > 2.0 + T) & (t <= dur - 2.0)
        rate = float(c[moving].sum() / (moving.sum() * T))
        expected = v / (RAIL_ALTITUDE_M * RAIL_Q_RAD_PER_COUNT)
        total = int(c.sum())
        rows.append({"speed_m_s": v, "counts_per_s": rate, "expected_counts_per_s": expected,
                     "table_v_counts_per_s": TABLE_V_OUTPUT_RATE[v],
                     "rel_error_vs_expected": rate / expected - 1.0, "sum_counts": total,
                     "distance_from_counts_m": total * RAIL_Q_RAD_PER_COUNT * RAIL_ALTITUDE_M,
                     "travel_m": RAIL_TRAVEL_M,
                     "travel_in_counts": RAIL_TRAVEL_M / (RAIL_Q_RAD_PER_COUNT * RAIL_ALTITUDE_M)})
    if tlog is not None:
        _record_open_loop(tlog, recorded, T, RAIL_Q_RAD_PER_COUNT, profile, cfg)
    return Run("rail", cols, Path(tlog) if tlog else None, meta={"rows": rows, "profile": profile.value})


def triangle_position(speed_m_s: float, leg_s: float) -> Callable[[float], float]:
    """Triangle wave: out at +speed for one leg, back at -speed for the next (starting at 0)."""

    def x(t: float) -> float:
        phase = t % (2 * leg_s)
        return speed_m_s * (phase if phase < leg_s else 2 * leg_s - phase)

    return x


def run_triangle(cfg: Config, *, tlog: str | Path | None = None, profile: Profile = Profile.PAPER) -> Run:
    """Fig. 9: triangular motion at 0.2 m/s sampled at 25 Hz at 17 cm and 62.5 cm, Q = 0.0015.
    ``tlog``: record what the sensor produced (25 Hz frames), both heights one after the other."""
    frame_s = 1.0 / TRIANGLE_RATE_HZ
    cols: dict[str, np.ndarray] = {}
    rows = []
    recorded: list[OpenLoopRun] = []
    for alt in TRIANGLE_ALTITUDES_M:
        pos = triangle_position(TRIANGLE_SPEED_M_S, TRIANGLE_LEG_S)
        t, c = _open_loop_counts(pos, alt, 6 * TRIANGLE_LEG_S, frame_s, RAIL_Q_RAD_PER_COUNT)
        recorded.append(OpenLoopRun(f"triangle {TRIANGLE_SPEED_M_S:g} m/s at {alt:g} m, "
                                    f"{TRIANGLE_RATE_HZ:g} Hz, Q {RAIL_Q_RAD_PER_COUNT:g}", pos, alt, t, c))
        cols[f"t_s_{alt}"], cols[f"counts_{alt}"] = t, c.astype(float)
        mag = np.abs(c[1:])
        # frames wholly inside a leg (a reversal splits its frame's motion)
        phase = (t[1:] - frame_s / 2) % TRIANGLE_LEG_S
        inside = (phase > frame_s) & (phase < TRIANGLE_LEG_S - frame_s)
        expected = TRIANGLE_SPEED_M_S * frame_s / alt / RAIL_Q_RAD_PER_COUNT
        rows.append({"altitude_m": alt, "counts_per_sample": float(mag[inside].mean()),
                     "expected_counts_per_sample": expected,
                     "mrad_per_sample": 1e3 * TRIANGLE_SPEED_M_S * frame_s / alt})
    if tlog is not None:
        _record_open_loop(tlog, recorded, frame_s, RAIL_Q_RAD_PER_COUNT, profile, cfg)
    return Run("triangle", cols, Path(tlog) if tlog else None, meta={"rows": rows, "profile": profile.value})


# ---------------------------------------------------------------------------------------------
# Figures of merit


def _first_crossing(t: np.ndarray, y: np.ndarray, level: float, after_s: float) -> float:
    idx = np.nonzero((t >= after_s) & (y >= level))[0]
    if len(idx) == 0:
        return math.nan
    i = int(idx[0])
    if i == 0 or t[i - 1] < after_s:
        return float(t[i])
    return float(t[i - 1] + (level - y[i - 1]) * (t[i] - t[i - 1]) / (y[i] - y[i - 1]))


def figures(run: Run, cfg: Config) -> dict[str, Any]:
    """The measured figures of merit of a run (the numbers the paper reports), per axis."""
    if run.name == "rail" or run.name == "triangle":
        return {"scenario": run.name, "rows": run.meta["rows"]}
    c = run.columns
    t = c["t_s"]
    last2 = t >= t[-1] - 2.0
    out: dict[str, Any] = {"scenario": run.name}
    limit_deg = cfg.controller.tilt_limit_deg
    for axis, v, pos, ang, cmd, counts in (("x", "vx_m_s", "x_m", "pitch_rad", "pitch_cmd_rad", "flow_x_counts"),
                                           ("y", "vy_m_s", "y_m", "roll_rad", "roll_cmd_rad", "flow_y_counts")):
        a: dict[str, Any] = {"final_velocity_m_s": float(c[v][last2].mean()),
                             "max_abs_command_deg": float(np.degrees(np.abs(c[cmd]).max())),
                             "command_limit_deg": limit_deg}
        if run.name == "step":
            t10 = _first_crossing(t, c[v], 0.2, 5.0)
            t90 = _first_crossing(t, c[v], 1.8, 5.0)
            a.update(rise_time_10_90_s=t90 - t10, overshoot_pct=100.0 * (c[v].max() / 2.0 - 1.0),
                     extreme_command_deg=float(np.degrees(c[cmd].min() if axis == "x" else c[cmd].max())))
        elif run.name == "gust":
            i5 = int(np.searchsorted(t, 5.0))
            a.update(displacement_m=float(c[pos][-1] - c[pos][i5]),
                     final_speed_m_s=float(np.abs(c[v][last2]).max()),
                     held_angle_deg=float(np.degrees(c[ang][last2].mean())))
        elif run.name == "slow":
            nz = np.nonzero((t > 2.0) & (c[counts] != 0))[0]
            later = t >= t[-1] - 6.0
            a.update(first_count_after_command_s=float(t[nz[0]] - 2.0) if len(nz) else math.nan,
                     count_values=sorted({int(x) for x in c[counts][t > 2.0]}),
                     pulses_per_s=float(np.count_nonzero(c[counts][later]) / 6.0),
                     final_velocity_cm_s=float(100 * c[v][last2].mean()))
        out[axis] = a
    return out


def run_named(name: str, cfg: Config, *, profile: Profile = Profile.PAPER, seed: int = 0,
              tlog: str | Path | None = None) -> Run:
    if name == "rail":
        return run_rail(cfg, tlog=tlog, profile=profile)
    if name == "triangle":
        return run_triangle(cfg, tlog=tlog, profile=profile)
    if name not in SCENARIOS:
        raise KeyError(name)
    return fly(cfg, SCENARIOS[name], profile=profile, seed=seed, tlog=tlog)

