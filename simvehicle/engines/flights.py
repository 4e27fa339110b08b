"""Varied closed-loop test flights, and the diagnose test matrix built on them.

``varied_flight(seed)`` is a ~150 s closed-loop flight of the kind a user flies to check a vehicle:
hover, velocity steps on each axis and on both, slow creeps (a few cm/s, where the flow is mostly
quantization), sinusoids on both axes at once, altitude changes between 0.7 and 2.5 m, and a
random horizontal force (turbulence, a Gauss-Markov process). The schedule comes from the seed, so
every seed is a different flight. ``with_sensor_noise(cfg)`` switches on the gyro's white noise
(the VN-100 density of Table II) and a rangefinder noise.

The matrix (``MATRIX``) flies these flights with each effect of CONVENTIONS.md alone at three sizes,
several pairs, and none at all (several seeds). ``score(case, report)`` compares what
``python -m companion diagnose`` found with the truth, using the tolerances of issue #5
(``TOLERANCES``). The diagnosis itself only ever sees the recording.

How the sizes were chosen (all are values real multicopters show):

| effect | sizes | why |
|---|---|---|
| linear_drag b | 0.15, 0.3, 0.5 N s/m | rotor drag of 1-3 kg quads is 0.1-0.6 N s/m (Table VI: 0.2) |
| gyro_bias | 0.005, 0.01, 0.02 rad/s | uncalibrated MEMS turn-on bias 0.3-1.2 deg/s |
| flow_scale | 0.9, 1.1, 1.2 | PMW3901 lens focus and texture change the rad per count by 10-20 % |
| flow_delay | 0.02, 0.04, 0.06 s | 1-3 frames of flow pipeline latency (ArduPilot's FLOW_DELAY is often 0-80 ms) |
| flow_yaw_misalignment | 3, 6, 10 deg | board mounted by hand, or one screw hole off |
| attitude_dynamics | (4.5, 0.71), (3.5, 0.5), (7.0, 0.9) | heavier or softer-tuned, underdamped, stiffer |
| range_offset | 0.05, -0.1, 0.2 m | rangefinder above or below the flow sensor / landing gear |
| wind_force | 1, 2, 3 N for 35-60 s | a 2.3 kg quad in 3-6 m/s of wind |

The smallest sizes are a few times the tolerance the matrix asserts, so they are detectable but not
trivially so under the flights' turbulence and quantization; the largest ones still fly the
paper's loop without saturating it for long.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import (
    EFFECT_TYPES,
    AttitudeDynamics,
    Config,
    FlowDelay,
    FlowScale,
    FlowYawMisalignment,
    GyroBias,
    LinearDrag,
    RangeOffset,
    WindForce,
    replace_section,
    with_effects,
)
from simvehicle.engines.scenarios import Run, Scenario, fly

#: rangefinder noise of the matrix flights (m, 1 sigma): a good ToF sensor indoors
RANGE_NOISE_STD_M = 0.005
#: altitude limits of the flights (m)
ALTITUDE_RANGE_M = (0.7, 2.5)
#: range of the turbulence force of the flights (N, 1 sigma per axis, correlation time 1 s): light air
#: to a light breeze's gusts on a 2.3 kg quad
TURBULENCE_SIGMA_N = (0.04, 0.12)

Pair = tuple[float, float]


# ---------------------------------------------------------------------------------------------
# One varied flight


@dataclass(frozen=True)
class Segment:
    """A stretch of the velocity-setpoint schedule (body axes, m/s)."""

    start_s: float
    end_s: float
    kind: str  # hold, step, slow, sine
    vx_m_s: float = 0.0
    vy_m_s: float = 0.0
    freq_x_hz: float = 0.0
    freq_y_hz: float = 0.0

    def setpoint(self, t_s: float) -> Pair:
        if self.kind != "sine":
            return self.vx_m_s, self.vy_m_s
        tau = t_s - self.start_s
        return (self.vx_m_s * math.sin(2 * math.pi * self.freq_x_hz * tau),
                self.vy_m_s * math.sin(2 * math.pi * self.freq_y_hz * tau))


@dataclass(frozen=True)
class FlightPlan:
    """The schedule of one varied flight: setpoint segments, altitude knots, turbulence."""

    seed: int
    duration_s: float
    segments: tuple[Segment, ...]
    #: altitude profile: piecewise linear through (time s, altitude m)
    altitude_knots: tuple[tuple[float, float], ...]
    turbulence_sigma_n: float
    turbulence_tau_s: float = 1.0

    def setpoint(self, t_s: float) -> Pair:
        starts = [s.start_s for s in self.segments]
        i = max(0, bisect.bisect_right(starts, t_s) - 1)
        return self.segments[i].setpoint(t_s)

    def altitude_fn(self) -> Callable[[float], float]:
        ts = [k[0] for k in self.altitude_knots]
        hs = [k[1] for k in self.altitude_knots]

        def altitude(t_s: float) -> float:
            i = bisect.bisect_right(ts, t_s)
            if i <= 0:
                return hs[0]
            if i >= len(ts):
                return hs[-1]
            t0, t1, h0, h1 = ts[i - 1], ts[i], hs[i - 1], hs[i]
            s = (t_s - t0) / (t1 - t0)
            return h0 + (h1 - h0) * (0.5 - 0.5 * math.cos(math.pi * s))  # smooth climb / descent

        return altitude

    def scenario(self) -> Scenario:
        return Scenario(f"varied-{self.seed}", self.duration_s, self.setpoint, altitude=self.altitude_fn(),
                        turbulence_sigma_n=self.turbulence_sigma_n, turbulence_tau_s=self.turbulence_tau_s,
                        description=f"varied flight, seed {self.seed}: steps, slow creeps, sinusoids, "
                                    f"altitude changes, turbulence {self.turbulence_sigma_n:.2f} N")


def flight_plan(seed: int, duration_s: float = 150.0, turbulence_sigma_n: float | None = None) -> FlightPlan:
    """A varied flight schedule drawn from ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(10_000 + seed)
    kinds = ["step_x", "step_y", "step_xy", "slow", "sine", "hold"]
    segments: list[Segment] = [Segment(0.0, 4.0, "hold")]
    t = 4.0
    order: list[str] = []
    while t < duration_s:
        if not order:
            order = list(rng.permutation(kinds))
        kind = order.pop()
        if kind == "sine":
            length = float(rng.uniform(12.0, 18.0))
            seg = Segment(t, t + length, "sine", float(rng.uniform(0.4, 0.9)), float(rng.uniform(0.4, 0.9)),
                          float(rng.uniform(0.12, 0.3)), float(rng.uniform(0.12, 0.3)))
        elif kind == "slow":
            length = float(rng.uniform(6.0, 10.0))
            sx, sy = rng.choice([-1.0, 1.0], 2)
            seg = Segment(t, t + length, "slow", float(sx * rng.uniform(0.02, 0.1)),
                          float(sy * rng.uniform(0.02, 0.1)))
        elif kind == "hold":
            length = float(rng.uniform(4.0, 7.0))
            seg = Segment(t, t + length, "hold")
        else:
            length = float(rng.uniform(5.0, 8.0))
            amp = float(rng.uniform(0.5, 1.5)) * float(rng.choice([-1.0, 1.0]))
            vx = amp if kind in ("step_x", "step_xy") else 0.0
            vy = (amp * float(rng.uniform(0.5, 1.0)) * float(rng.choice([-1.0, 1.0]))) if kind == "step_xy" \
                else (amp if kind == "step_y" else 0.0)
            seg = Segment(t, t + length, "step", vx, vy)
        segments.append(seg)
        t += length
    # altitude: hold a level 15-30 s, then move to another over 3-5 s
    lo, hi = ALTITUDE_RANGE_M
    h = float(rng.uniform(0.9, 1.5))
    knots = [(0.0, h)]
    t = float(rng.uniform(12.0, 25.0))
    while t < duration_s:
        knots.append((t, h))
        new = float(rng.uniform(lo, hi))
        while abs(new - h) < 0.4:
            new = float(rng.uniform(lo, hi))
        ramp = float(rng.uniform(3.0, 5.0))
        knots.append((t + ramp, new))
        h = new
        t += ramp + float(rng.uniform(15.0, 30.0))
    knots.append((duration_s + 1.0, h))
    sigma = float(rng.uniform(*TURBULENCE_SIGMA_N)) if turbulence_sigma_n is None else turbulence_sigma_n
    return FlightPlan(seed, duration_s, tuple(segments), tuple(knots), sigma)


def varied_flight(seed: int, duration_s: float = 150.0) -> Scenario:
    """The closed-loop scenario of ``flight_plan(seed)``."""
    return flight_plan(seed, duration_s).scenario()


def with_sensor_noise(cfg: Config, range_noise_std_m: float = RANGE_NOISE_STD_M) -> Config:
    """``cfg`` with the gyro's white noise on and a rangefinder noise (m, 1 sigma)."""
    cfg = replace_section(cfg, "imu", gyro_noise=True)
    return replace_section(cfg, "rangefinder", noise_std_m=range_noise_std_m)


# ---------------------------------------------------------------------------------------------
# The matrix


@dataclass(frozen=True)
class MatrixCase:
    """One cell of the matrix: a flight (seed) with some effects switched on (truth)."""

    name: str
    seed: int
    effects: dict[str, Any] = field(default_factory=dict)  # effect name -> config dataclass instance
    duration_s: float = 150.0

    def config(self, base: Config) -> Config:
        return with_effects(with_sensor_noise(base), **self.effects)

    def key(self) -> str:
        """A stable text key of everything that makes the recording (for caching)."""
        eff = ";".join(f"{k}={dataclasses.asdict(v)}" for k, v in sorted(self.effects.items()))
        return f"{self.name}|{self.seed}|{self.duration_s}|{eff}|noise={RANGE_NOISE_STD_M}"


def _deg(x: float) -> float:
    return math.radians(x)


def _wind(f_n: float, heading_deg: float, start_s: float, end_s: float) -> WindForce:
    a = math.radians(heading_deg)
    return WindForce(fx=round(f_n * math.cos(a), 6), fy=round(f_n * math.sin(a), 6), start_s=start_s, end_s=end_s)


def _cases() -> list[MatrixCase]:
    c: list[MatrixCase] = []
    for seed in (1, 2, 3, 4):
        c.append(MatrixCase(f"clean-s{seed}", seed))
    sizes: dict[str, list[Any]] = {
        "linear_drag": [LinearDrag(0.15), LinearDrag(0.3), LinearDrag(0.5)],
        "gyro_bias": [GyroBias(0.005, -0.005), GyroBias(-0.01, 0.008), GyroBias(0.02, 0.015)],
        "flow_scale": [FlowScale(0.9, 0.9), FlowScale(1.1, 1.08), FlowScale(1.2, 1.15)],
        "flow_delay": [FlowDelay(0.02), FlowDelay(0.04), FlowDelay(0.06)],
        "flow_yaw_misalignment": [FlowYawMisalignment(_deg(3.0)), FlowYawMisalignment(_deg(-6.0)),
                                  FlowYawMisalignment(_deg(10.0))],
        "attitude_dynamics": [AttitudeDynamics(4.5, 0.71), AttitudeDynamics(3.5, 0.5), AttitudeDynamics(7.0, 0.9)],
        "range_offset": [RangeOffset(0.05), RangeOffset(-0.1), RangeOffset(0.2)],
        "wind_force": [_wind(1.0, 30.0, 40.0, 100.0), _wind(2.0, -120.0, 60.0, 95.0),
                       _wind(3.0, 160.0, 30.0, 90.0)],
    }
    seed = 10
    for name, variants in sizes.items():
        for i, eff in enumerate(variants):
            c.append(MatrixCase(f"{name}-{'abc'[i]}", seed, {name: eff}))
            seed += 1
    pairs = [
        {"linear_drag": LinearDrag(0.25), "gyro_bias": GyroBias(0.01, -0.01)},
        {"flow_scale": FlowScale(1.1, 1.1), "range_offset": RangeOffset(0.1)},
        {"flow_delay": FlowDelay(0.04), "attitude_dynamics": AttitudeDynamics(4.5, 0.6)},
        {"wind_force": _wind(2.0, 45.0, 50.0, 100.0), "linear_drag": LinearDrag(0.3)},
        {"flow_yaw_misalignment": FlowYawMisalignment(_deg(6.0)), "flow_scale": FlowScale(0.92, 0.92)},
    ]
    for eff in pairs:
        c.append(MatrixCase("+".join(eff), seed, eff))
        seed += 1
    return c


MATRIX: tuple[MatrixCase, ...] = tuple(_cases())


def case(name: str) -> MatrixCase:
    for m in MATRIX:
        if m.name == name:
            return m
    raise KeyError(name)


def fly_case(m: MatrixCase, base: Config, tlog: str | Path) -> Run:
    """Fly one matrix case closed loop and write its recording (paper profile)."""
    return fly(m.config(base), flight_plan(m.seed, m.duration_s).scenario(), seed=m.seed, tlog=tlog)


# ---------------------------------------------------------------------------------------------
# Scoring a diagnosis against the truth

#: issue #5: how close a named effect's parameters must be. ("rel", x): |err| <= x |truth|;
#: ("abs", x): |err| <= x in the parameter's unit; wind fx, fy: the force vector within 15 % of |F|.
TOLERANCES: dict[str, dict[str, tuple[str, float]]] = {
    "linear_drag": {"b": ("rel", 0.20)},
    "gyro_bias": {"bias_x": ("abs", 0.002), "bias_y": ("abs", 0.002)},
    "flow_scale": {"scale_x": ("rel", 0.03), "scale_y": ("rel", 0.03)},
    "flow_delay": {"delay": ("abs", 0.008)},
    "flow_yaw_misalignment": {"yaw": ("abs", math.radians(1.5))},
    "attitude_dynamics": {"omega_p": ("rel", 0.10), "zeta": ("rel", 0.15)},
    "range_offset": {"offset": ("abs", 0.02)},
    "wind_force": {"fx": ("vec", 0.15), "fy": ("vec", 0.15), "start_s": ("abs", 1.5), "end_s": ("abs", 1.5)},
}
assert set(TOLERANCES) == set(EFFECT_TYPES)


@dataclass
class CaseScore:
    """How one diagnosis compares with its truth."""

    case: str
    truth: dict[str, dict[str, float]]
    found: dict[str, dict[str, float]]
    hits: list[str]  # named, parameters within tolerance
    misses: list[str]  # in the truth, not named (or named with parameters out of tolerance)
    false: list[str]  # named, not in the truth
    param_errors: dict[str, dict[str, float]]  # effect -> parameter -> error / tolerance (<= 1 passes)
    heldout_improved: dict[str, bool]  # named effect -> held-out rms lower with it

    @property
    def ok(self) -> bool:
        return not self.misses and not self.false and all(self.heldout_improved.values())


def _truth_params(effects: dict[str, Any]) -> dict[str, dict[str, float]]:
    return {k: {p: float(x) for p, x in dataclasses.asdict(v).items()} for k, v in effects.items()}


def param_error_ratios(effect: str, truth: dict[str, float], found: dict[str, float]) -> dict[str, float]:
    """|error| / tolerance for each parameter of ``effect`` (a ratio <= 1 is within tolerance)."""
    out: dict[str, float] = {}
    tol = TOLERANCES[effect]
    if effect == "wind_force":
        mag = math.hypot(truth["fx"], truth["fy"])
        err = math.hypot(found.get("fx", 0.0) - truth["fx"], found.get("fy", 0.0) - truth["fy"])
        out["force"] = err / (tol["fx"][1] * mag)
    for p, (kind, x) in tol.items():
        if kind == "vec":
            continue
        f = found.get(p, math.nan)
        err = abs(f - truth[p])
        out[p] = err / (x * abs(truth[p])) if kind == "rel" else err / x
    return {k: (v if math.isfinite(v) else math.inf) for k, v in out.items()}


def score(m: MatrixCase, report: dict[str, Any]) -> CaseScore:
    """Compare a diagnose JSON report (CONVENTIONS.md layout) with the case's truth."""
    truth = _truth_params(m.effects)
    found = {f["effect"]: {k: (v if v is not None else math.nan) for k, v in f["parameters"].items()}
             for f in report["findings"] if f["significant"]}
    hits: list[str] = []
    misses: list[str] = []
    false: list[str] = []
    errors: dict[str, dict[str, float]] = {}
    for eff, tp in truth.items():
        if eff not in found:
            misses.append(eff)
            continue
        errors[eff] = param_error_ratios(eff, tp, found[eff])
        (hits if all(r <= 1.0 for r in errors[eff].values()) else misses).append(eff)
    false = [eff for eff in found if eff not in truth]
    improved = {}
    for f in report["findings"]:
        if f["significant"]:
            fit = f.get("fit") or {}
            b, a = fit.get("heldout_rms_before"), fit.get("heldout_rms_after")
            improved[f["effect"]] = b is not None and a is not None and a < b
    return CaseScore(m.name, truth, found, hits, misses, false, errors, improved)
