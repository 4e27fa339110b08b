"""An independent randomised flight generator for judging the mismatch finder (issue 12).

One seed in, one recording and its truth out::

    spec = draw_spec(seed)                 # every drawn parameter, a frozen dataclass
    flight = simulate(spec)                # closed loop: own plant + own sensors + the companion
    paths = write_flight(spec, flight, folder, "gen_0007")   # .tlog, nominal .toml, .truth.json
    result = score(truth, report)          # a diagnose JSON report against the truth

Independence. Nothing here comes from ``simvehicle/model/sim.py``, ``plant.py``, ``flow_sensor.py`` or
``fastsim.py``: the vehicle and the sensors are written again from CONVENTIONS.md, with another
integrator (Heun's explicit trapezoid, second order, at ``integrator_hz`` >= 1 kHz, every
sub-interval split exactly at the command switches and at the sample instants), and their own
noise code. A modelling choice our simulator and our finder share therefore does not hide here
unless this module makes it too. What is *not* independent, on purpose: the companion that flies
the loop (``companion.mavlink.inbound.MessageRouter`` + ``companion.step.core.CompanionCore``, eq. 15 and the
PI of Table VI: that is the behaviour under test) and the file layout
(``companion.recordings.tlog_writer.TlogWriter``, pymavlink's ``ardupilotmega`` encoder).

The model (CONVENTIONS.md, per axis; x pairs with pitch ``th`` and pitch rate ``q``, y with roll
``ph`` and roll rate ``p``):

    q'  = w^2 (u_pitch - th) - 2 z w q          p'  = w^2 (u_roll - ph) - 2 z w p
    vx' = -g tan(th) + Fx / m                   vy' = +g tan(ph) + Fy / m
    Fx  = wind + turbulence - b vx - c vx |vx|   (the same for y)
    phi_x' = -gain q - (vx + q rz) / D          phi_y' = +gain p - (vy - p rz) / D

``D`` is the flow sensor's distance to the ground along body z (slant range): the sensor sits at
the body offset ``r`` (``flow_lever_arm``, zero without it), so its height is
``h + sin(th) rx - cos(th) sin(ph) ry - cos(th) cos(ph) rz`` and its velocity ``v + omega x r``
(horizontal part ``(q rz, -p rz)`` with the yaw rate held at zero). The rangefinder is on the same
board as the flow sensor (a flow + range module) and reads ``D + offset + noise`` in whole cm.
``gain`` is ``flow_rotation_gain`` (1 without it). The flow sensor quantizes its scene angle
continuously integrated (eq. 9-11) in its own axes (``flow_yaw_misalignment`` turns them about z by
``yaw``: ``s_x = cos(yaw) phi_x + sin(yaw) phi_y``, ``s_y = -sin(yaw) phi_x + cos(yaw) phi_y``)
with ``scale x Q`` rad per count (``flow_scale``), sampled ``delay`` before the frame time
(``flow_delay``). The gyro reads the body rates, low-pass filtered (``gyro_lag``, a continuous
first-order state), plus ``gyro_bias``, plus white noise, in whole mrad/s. The accelerometer reads
the horizontal specific force of the model above, plus white noise, a bias and a vibration
sinusoid (``draw_accel_noise``; generator version 4), in whole milli-g. ATTITUDE is the true
attitude plus white and first-order Gauss-Markov noise (an EKF output). The command computed from
frame k acts from frame k+1 (plus ``attitude_delay``).

Telemetry loss is a property of the *recording* (the log is made over a lossy link, e.g. a GCS
radio); the companion's own link to the autopilot is lossless, so the flight itself is not
changed by the loss. See docs/generalisation_matrix.md.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit

from companion.config import CONFIG_DIR, load_config
from companion.mavlink.inbound import MessageRouter
from companion.mavlink_ids import COMPANION_COMPONENT
from companion.recordings.tlog_writer import TlogWriter, mav_encoder
from companion.rotation import euler_to_quaternion
from companion.step.core import CompanionCore
from companion.step.profiles import Profile

GENERATOR_VERSION = 4

EFFECT_NAMES = ("linear_drag", "quadratic_drag", "gyro_bias", "flow_scale", "flow_delay", "flow_yaw_misalignment",
                "attitude_dynamics", "range_offset", "wind_force", "attitude_delay", "flow_rotation_gain",
                "flow_lever_arm", "gyro_lag")

#: the nominal tilt limit of the companion's PI (deg); the drawn forces are kept to a share of it
TILT_LIMIT_DEG = 20.0
#: steady forces (wind, drag at the top speed) are kept under this share of m g tan(tilt limit)
FORCE_SHARE = 0.5
#: the top setpoint speed keeps the translational flow under this many rad/s at the lowest height
MAX_TRANSLATION_RATE = 3.5


# ---------------------------------------------------------------------------------------------
# parameters


@dataclass(frozen=True)
class SetpointSegment:
    """One piece of the velocity setpoint (body axes, m/s) over [t0_s, t1_s) of simulation time.

    ``hold``/``step``: constant ``end``; ``ramp``: linear from ``start`` to ``end``; ``sine``:
    ``start + amp sin(2 pi (t - t0) / period_s + phase)`` per axis."""

    t0_s: float
    t1_s: float
    kind: str
    start: tuple[float, float]
    end: tuple[float, float]
    amp: tuple[float, float] = (0.0, 0.0)
    period_s: float = 1.0
    phase: float = 0.0


@dataclass(frozen=True)
class FlightProfile:
    """Velocity setpoints and the vehicle's height (the autopilot holds it; knots joined by
    half-cosine transitions)."""

    segments: tuple[SetpointSegment, ...]
    alt_t_s: tuple[float, ...]
    alt_m: tuple[float, ...]
    speed_limit_m_s: float

    def setpoint(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t_s, dtype=float)
        vx = np.zeros_like(t)
        vy = np.zeros_like(t)
        for s in self.segments:
            m = (t >= s.t0_s) & (t < s.t1_s)
            if not np.any(m):
                continue
            tt = t[m]
            for out, i in ((vx, 0), (vy, 1)):
                if s.kind in ("hold", "step"):
                    out[m] = s.end[i]
                elif s.kind == "ramp":
                    out[m] = s.start[i] + (s.end[i] - s.start[i]) * (tt - s.t0_s) / (s.t1_s - s.t0_s)
                else:
                    out[m] = s.start[i] + s.amp[i] * np.sin(2 * np.pi * (tt - s.t0_s) / s.period_s + s.phase)
        last = self.segments[-1]
        after = t >= last.t1_s
        vx[after], vy[after] = last.end
        # the speed limit applies to the vector
        sp = np.hypot(vx, vy)
        k = np.where(sp > self.speed_limit_m_s, self.speed_limit_m_s / np.maximum(sp, 1e-12), 1.0)
        return vx * k, vy * k

    def altitude(self, t_s: np.ndarray) -> np.ndarray:
        return height_profile(np.asarray(t_s, dtype=float), np.asarray(self.alt_t_s), np.asarray(self.alt_m))


@dataclass(frozen=True)
class Vehicle:
    """The airframe. ``omega_p_nominal``/``zeta_nominal`` are what the user believes (written to
    the config); the true attitude loop differs only under ``attitude_dynamics``."""

    mass_kg: float
    gravity_m_s2: float
    omega_p_nominal: float
    zeta_nominal: float
    heading_rad: float
    boot_s: float
    unix0_s: float


@dataclass(frozen=True)
class Sensors:
    """Message convention and sampling. The IMU, attitude and range are sampled ``*_lead_s``
    before the flow frame they go with (so they reach the companion before it)."""

    profile: str  # "paper" | "ardupilot"
    q_rad_per_count: float
    frame_rate_hz: float
    imu_lead_s: float
    att_lead_s: float
    range_lead_s: float
    companion_proc_s: float
    range_min_m: float
    range_max_m: float
    base_config: str  # the file the nominal config is copied from


@dataclass(frozen=True)
class Noise:
    att_white_rad: float = 0.0
    att_gm_rad: float = 0.0
    att_gm_tau_s: float = 0.5
    flow_count_error_frac: float = 0.0
    gyro_white_rad_s: float = 0.0
    range_noise_m: float = 0.0
    record_jitter_s: float = 0.0
    sensor_time_jitter_s: float = 0.0
    turbulence_n: float = 0.0
    turbulence_tau_s: float = 1.0
    # the accelerometer (RAW_IMU xacc, yacc): white noise, a constant bias per axis, and a rotor
    # vibration left after the autopilot's filter (a sinusoid at its alias below the frame rate)
    accel_white_m_s2: float = 0.0
    accel_bias_x_m_s2: float = 0.0
    accel_bias_y_m_s2: float = 0.0
    accel_vibration_m_s2: float = 0.0
    accel_vibration_hz: float = 10.0


@dataclass(frozen=True)
class Loss:
    """Recording loss: each message independently with ``random_frac``, and everything inside
    the bursts (start times in simulation seconds, ``burst_s`` long)."""

    random_frac: float = 0.0
    bursts_s: tuple[float, ...] = ()
    burst_s: float = 0.5

    @property
    def kind(self) -> str:
        r, b = self.random_frac > 0, len(self.bursts_s) > 0
        return "both" if r and b else "random" if r else "bursts" if b else "none"


@dataclass(frozen=True)
class FlightSpec:
    """Everything one recording draws. Times are simulation seconds; the recording covers
    [warmup_s, warmup_s + duration_s] (the loop runs during the warm-up, unrecorded)."""

    seed: int
    duration_s: float
    warmup_s: float
    flight: FlightProfile
    vehicle: Vehicle
    sensors: Sensors
    noise: Noise
    loss: Loss
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    #: wind window flags: from before the recording / to its end
    wind_from_start: bool = False
    wind_to_end: bool = False
    integrator_hz: float = 2000.0

    @property
    def frame_s(self) -> float:
        return 1.0 / self.sensors.frame_rate_hz

    def true_attitude_loop(self) -> tuple[float, float]:
        ad = self.effects.get("attitude_dynamics")
        if ad:
            return ad["omega_p"], ad["zeta"]
        return self.vehicle.omega_p_nominal, self.vehicle.zeta_nominal


# ---------------------------------------------------------------------------------------------
# drawing a spec


def _u(rng: np.random.Generator, a: float, b: float) -> float:
    return float(rng.uniform(a, b))


def _two_sided(rng: np.random.Generator, lo: tuple[float, float], hi: tuple[float, float]) -> float:
    return _u(rng, *lo) if rng.random() < 0.5 else _u(rng, *hi)


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def draw_duration(rng: np.random.Generator) -> float:
    """20 s - 20 min, most between 30 and 300 s (log-uniform), ~5 % long (5-20 min)."""
    u = rng.random()
    if u < 0.05:
        return _u(rng, 300.0, 1200.0)
    if u < 0.15:
        return _u(rng, 20.0, 30.0)
    return float(math.exp(rng.uniform(math.log(30.0), math.log(300.0))))


def draw_effects(rng: np.random.Generator, vehicle: Vehicle, clean_share: float = 0.2) -> dict[str, dict[str, float]]:
    """None (``clean_share``), one (60 % of the rest) or two distinct effects, sizes from the issue's
    ranges (CONVENTIONS.md names, SI). The wind's times are drawn later (``draw_spec``)."""
    if rng.random() < clean_share:
        return {}
    n = 1 if rng.random() < 0.6 else 2
    names = [EFFECT_NAMES[i] for i in rng.choice(len(EFFECT_NAMES), size=n, replace=False)]
    out: dict[str, dict[str, float]] = {}
    m, g = vehicle.mass_kg, vehicle.gravity_m_s2
    for name in names:
        if name == "linear_drag":
            p = {"b": _u(rng, 0.15, 0.8)}
        elif name == "quadratic_drag":
            p = {"c": _u(rng, 0.1, 0.5)}
        elif name == "gyro_bias":
            p = {"bias_x": _sign(rng) * _u(rng, 0.01, 0.05), "bias_y": _sign(rng) * _u(rng, 0.01, 0.05)}
        elif name == "flow_scale":
            p = {"scale_x": _two_sided(rng, (0.8, 0.92), (1.08, 1.25)),
                 "scale_y": _two_sided(rng, (0.8, 0.92), (1.08, 1.25))}
        elif name == "flow_delay":
            p = {"delay": _u(rng, 0.01, 0.04)}
        elif name == "flow_yaw_misalignment":
            p = {"yaw": _sign(rng) * math.radians(_u(rng, 3.0, 15.0))}
        elif name == "attitude_dynamics":
            k = _two_sided(rng, (0.6, 0.8), (1.25, 1.6))
            p = {"omega_p": vehicle.omega_p_nominal * k,
                 "zeta": max(0.3, vehicle.zeta_nominal + _u(rng, -0.2, 0.2))}
        elif name == "range_offset":
            p = {"offset": _u(rng, 0.05, 0.2)}
        elif name == "wind_force":
            cap = min(4.0, FORCE_SHARE * m * g * math.tan(math.radians(TILT_LIMIT_DEG)))
            f = _u(rng, 0.4, max(cap, 0.45))
            a = _u(rng, -math.pi, math.pi)
            p = {"fx": f * math.cos(a), "fy": f * math.sin(a), "start_s": math.nan, "end_s": math.nan}
        elif name == "attitude_delay":
            p = {"delay": _u(rng, 0.02, 0.06)}
        elif name == "flow_rotation_gain":
            p = {"gain": _two_sided(rng, (0.85, 0.93), (1.08, 1.2))}
        elif name == "flow_lever_arm":
            p = {"rx": _u(rng, -0.2, 0.2), "ry": _u(rng, -0.2, 0.2), "rz": _sign(rng) * _u(rng, 0.05, 0.2)}
        else:  # gyro_lag
            p = {"tau": _u(rng, 0.01, 0.05)}
        out[name] = p
    return out


def draw_noise(rng: np.random.Generator) -> Noise:
    """Each kind present or not independently (a clean recording is often noisy too)."""
    return Noise(
        att_white_rad=math.radians(_u(rng, 0.0, 0.2)) if rng.random() < 0.6 else 0.0,
        att_gm_rad=math.radians(_u(rng, 0.0, 0.3)) if rng.random() < 0.5 else 0.0,
        att_gm_tau_s=_u(rng, 0.1, 1.0),
        flow_count_error_frac=_u(rng, 0.0, 0.05) if rng.random() < 0.5 else 0.0,
        gyro_white_rad_s=_u(rng, 0.0, 0.005) if rng.random() < 0.7 else 0.0,
        range_noise_m=_u(rng, 0.0, 0.02) if rng.random() < 0.7 else 0.0,
        record_jitter_s=_u(rng, 0.0, 0.005) if rng.random() < 0.6 else 0.0,
        sensor_time_jitter_s=_u(rng, 0.0, 0.001) if rng.random() < 0.5 else 0.0,
        turbulence_n=_u(rng, 0.0, 0.4) if rng.random() < 0.7 else 0.0,
        # gusty on sub-second scales: a steady force over seconds is the wind_force effect, not noise
        turbulence_tau_s=_u(rng, 0.2, 1.0),
    )


def draw_accel_noise(rng: np.random.Generator) -> dict[str, float]:
    """The accelerometer's noise (``Noise.accel_*``), from its own stream so that the other draws
    of a seed stay what they were before it was added (generator version 3). A filtered flight
    accelerometer carries about 0.02-0.5 m/s² of noise, a residual bias of up to 0.2 m/s² and
    what is left of the rotor vibration; some recordings have none (a simulator without IMU noise)."""
    white = math.exp(_u(rng, math.log(0.02), math.log(0.5))) if rng.random() < 0.8 else 0.0
    biased = rng.random() < 0.6
    bx, by = _u(rng, -0.2, 0.2), _u(rng, -0.2, 0.2)
    vib = _u(rng, 0.0, 0.5) if rng.random() < 0.4 else 0.0
    return dict(accel_white_m_s2=white, accel_bias_x_m_s2=bx if biased else 0.0,
                accel_bias_y_m_s2=by if biased else 0.0, accel_vibration_m_s2=vib,
                accel_vibration_hz=_u(rng, 1.0, 24.0))


def draw_loss(rng: np.random.Generator, t0_s: float, duration_s: float) -> Loss:
    """none 40 %, random 0-20 % 25 %, bursts of 0.5 s 20 %, both 15 %."""
    u = rng.random()
    random_frac = _u(rng, 0.0, 0.2) if (0.4 <= u < 0.65 or u >= 0.85) else 0.0
    bursts: tuple[float, ...] = ()
    if u >= 0.65:
        n = 1 + int(rng.poisson(duration_s / 60.0))
        bursts = tuple(sorted(float(t0_s + rng.uniform(0.0, max(duration_s - 0.5, 0.1))) for _ in range(n)))
    return Loss(random_frac=random_frac, bursts_s=bursts, burst_s=0.5)


def draw_profile(rng: np.random.Generator, t_end_s: float, speed_limit: float, constant_alt: bool,
                 alt0: float) -> FlightProfile:
    """Holds, steps, ramps and sinusoids on vx/vy; heights between 0.5 and 3 m."""
    segs: list[SetpointSegment] = []
    t = 0.0
    cur = (0.0, 0.0)
    long_flight = t_end_s > 400.0
    while t < t_end_s:
        length = _u(rng, 3.0, 60.0 if long_flight else 25.0)
        kind = str(rng.choice(["hold", "step", "ramp", "sine"], p=[0.3, 0.25, 0.25, 0.2]))

        def level() -> float:
            return 0.0 if rng.random() < 0.3 else _u(rng, -1.0, 1.0) * speed_limit

        if kind == "hold":
            segs.append(SetpointSegment(t, t + length, kind, cur, cur))
        elif kind in ("step", "ramp"):
            new = (level(), level())
            segs.append(SetpointSegment(t, t + length, kind, cur, new))
            cur = new
        else:
            amp = (_u(rng, 0.1, 0.8) * speed_limit * (rng.random() < 0.8),
                   _u(rng, 0.1, 0.8) * speed_limit * (rng.random() < 0.8))
            segs.append(SetpointSegment(t, t + length, kind, cur, cur, amp, _u(rng, 2.0, 15.0),
                                        _u(rng, 0.0, 2 * math.pi)))
        t += length
    kt, kh = [0.0], [alt0]
    if not constant_alt:
        t = _u(rng, 3.0, 30.0)
        while t < t_end_s:
            kt.append(t)
            kh.append(kh[-1])
            new_h = _u(rng, 0.5, 3.0)
            t += abs(new_h - kh[-1]) / _u(rng, 0.15, 0.5) + 0.5
            kt.append(t)
            kh.append(new_h)
            t += _u(rng, 5.0, 60.0)
    kt.append(max(t_end_s, kt[-1]) + 1.0)
    kh.append(kh[-1])
    return FlightProfile(tuple(segs), tuple(kt), tuple(kh), speed_limit)


def _speed_limit(effects: dict[str, dict[str, float]], m: float, g: float, h_min: float) -> float:
    """The top setpoint speed: 2 m/s, less when drag plus wind at that speed would need more than
    ``FORCE_SHARE`` of the tilt limit, or the flow would turn faster than ``MAX_TRANSLATION_RATE``."""
    budget = FORCE_SHARE * m * g * math.tan(math.radians(TILT_LIMIT_DEG))
    wind = effects.get("wind_force")
    if wind:
        budget -= math.hypot(wind["fx"], wind["fy"])
    b = effects.get("linear_drag", {}).get("b", 0.0)
    c = effects.get("quadratic_drag", {}).get("c", 0.0)
    v = 2.0
    if b > 0 or c > 0:
        budget = max(budget, 0.1 * m * g * math.tan(math.radians(TILT_LIMIT_DEG)))
        v = (-b + math.sqrt(b * b + 4 * c * budget)) / (2 * c) if c > 0 else budget / b
    rz = effects.get("flow_lever_arm", {}).get("rz", 0.0)
    v = min(v, MAX_TRANSLATION_RATE * (h_min - max(rz, 0.0) - 0.05))
    return float(min(2.0, max(v, 0.3)))


def draw_spec(seed: int, *, clean_share: float = 0.2, ardupilot_share: float = 0.2) -> FlightSpec:
    """Every parameter of one recording from ``seed`` (deterministic)."""
    rng = np.random.default_rng([int(seed), 12])
    duration = draw_duration(rng)
    warmup = _u(rng, 2.0, 8.0)
    ardupilot = rng.random() < ardupilot_share
    base = "configs/" + ("ardupilot_sitl.toml" if ardupilot else "paper.toml")  # shipped, as companion/configs
    g = 9.80665 if ardupilot else 9.81
    vehicle = Vehicle(mass_kg=_u(rng, 0.5, 3.0), gravity_m_s2=g, omega_p_nominal=_u(rng, 4.0, 15.0),
                      zeta_nominal=_u(rng, 0.5, 1.2), heading_rad=_u(rng, -math.pi, math.pi),
                      boot_s=_u(rng, 20.0, 600.0), unix0_s=1.7e9 + float(rng.integers(0, 30_000_000)))
    if ardupilot:
        q = 0.0015706806282722514
        rmin, rmax = 0.2, 10.0
    else:
        q = float(rng.choice([0.09 / 57.3, 0.0015, _u(rng, 0.0008, 0.003)]))
        rmin, rmax = 0.02, 4.0
    sensors = Sensors(profile="ardupilot" if ardupilot else "paper", q_rad_per_count=q, frame_rate_hz=50.0,
                      imu_lead_s=_u(rng, 0.0, 0.005), att_lead_s=_u(rng, 0.0, 0.005),
                      range_lead_s=_u(rng, 0.0, 0.005), companion_proc_s=_u(rng, 0.0005, 0.003),
                      range_min_m=rmin, range_max_m=rmax, base_config=base)
    effects = draw_effects(rng, vehicle, clean_share)
    noise = dataclasses.replace(draw_noise(rng), **draw_accel_noise(np.random.default_rng([int(seed), 14])))
    loss = draw_loss(rng, warmup, duration)
    constant_alt = rng.random() < 0.2
    alt0 = _u(rng, 0.5, 3.0)
    t_end = warmup + duration
    # the speed limit needs the lowest height: draw the heights first with a provisional limit
    prof = draw_profile(np.random.default_rng([int(seed), 13]), t_end, 2.0, constant_alt, alt0)
    h_min = float(min(prof.alt_m))
    limit = _speed_limit(effects, vehicle.mass_kg, g, h_min)
    # the same draws again with the real limit: levels and amplitudes scale with it, heights are unchanged
    prof = draw_profile(np.random.default_rng([int(seed), 13]), t_end, limit, constant_alt, alt0)
    wind_from_start = wind_to_end = False
    if "wind_force" in effects:
        T = 1.0 / sensors.frame_rate_hz
        w = effects["wind_force"]
        whole = rng.random() < 0.2
        wind_from_start = whole or rng.random() < 0.25
        wind_to_end = whole or rng.random() < 0.25
        start = 0.0 if wind_from_start else warmup + _u(rng, 0.5, duration - 7.0)
        lo = max(start, warmup) + 6.0
        end = t_end + 1.0 if wind_to_end else _u(rng, lo, max(lo, t_end - 0.5))
        w["start_s"] = round(start / T) * T  # simulation time, snapped to the frame grid
        w["end_s"] = round(end / T) * T
    return FlightSpec(seed=int(seed), duration_s=duration, warmup_s=warmup, flight=prof, vehicle=vehicle,
                      sensors=sensors, noise=noise, loss=loss, effects=effects, wind_from_start=wind_from_start,
                      wind_to_end=wind_to_end)


# ---------------------------------------------------------------------------------------------
# the physics (numba): state and parameter layouts

TH, QR, PH, PR, VX, VY, PX, PY, SX, SY, GX, GY, IX, IY = range(14)
NS = 14
#: par: g, m, b, c, omega_p, zeta, rotation gain, rx, ry, rz, gyro lag tau (0 = none)
NPAR = 11


@njit(cache=True)
def _height(t: float, kt: np.ndarray, kh: np.ndarray) -> float:
    n = kt.shape[0]
    if t <= kt[0]:
        return kh[0]
    if t >= kt[n - 1]:
        return kh[n - 1]
    i = np.searchsorted(kt, t, side="right") - 1
    s = (t - kt[i]) / (kt[i + 1] - kt[i])
    return kh[i] + (kh[i + 1] - kh[i]) * 0.5 * (1.0 - math.cos(math.pi * s))


def height_profile(t: np.ndarray, kt: np.ndarray, kh: np.ndarray) -> np.ndarray:
    """The height (m) at times ``t`` from the knots (half-cosine transitions)."""
    return np.array([_height(float(x), kt, kh) for x in np.atleast_1d(t)])


@njit(cache=True)
def _deriv(t: float, s: np.ndarray, up: float, ur: float, fx: float, fy: float, par: np.ndarray,
           kt: np.ndarray, kh: np.ndarray, d: np.ndarray) -> None:
    g, m, b, c, wp, ze, gain, rx, ry, rz, tau = (par[0], par[1], par[2], par[3], par[4], par[5], par[6], par[7],
                                                 par[8], par[9], par[10])
    th, q, ph, p, vx, vy = s[0], s[1], s[2], s[3], s[4], s[5]
    d[0] = q
    d[1] = wp * wp * (up - th) - 2.0 * ze * wp * q
    d[2] = p
    d[3] = wp * wp * (ur - ph) - 2.0 * ze * wp * p
    d[4] = -g * math.tan(th) + (fx - b * vx - c * vx * abs(vx)) / m
    d[5] = g * math.tan(ph) + (fy - b * vy - c * vy * abs(vy)) / m
    d[6] = vx
    d[7] = vy
    h = _height(t, kt, kh)
    ct, st, cp, sp = math.cos(th), math.sin(th), math.cos(ph), math.sin(ph)
    hs = h + st * rx - ct * sp * ry - ct * cp * rz
    dist = hs / (ct * cp)
    d[8] = -gain * q - (vx + q * rz) / dist
    d[9] = gain * p - (vy - p * rz) / dist
    if tau > 0.0:
        d[10] = (p - s[10]) / tau
        d[11] = (q - s[11]) / tau
        d[12] = s[10]
        d[13] = s[11]
    else:
        d[10] = 0.0
        d[11] = 0.0
        d[12] = p
        d[13] = q


@njit(cache=True)
def _advance(s: np.ndarray, t0: float, t1: float, h_max: float, t_sw: float, ua_p: float, ua_r: float,
             ub_p: float, ub_r: float, fx: float, fy: float, par: np.ndarray, kt: np.ndarray, kh: np.ndarray,
             t_req: np.ndarray, out: np.ndarray) -> None:
    """Integrate ``s`` in place from t0 to t1 (Heun, steps <= h_max). The command is (ua_p, ua_r)
    before ``t_sw`` and (ub_p, ub_r) from it; the force is constant. The state at each time of
    ``t_req`` (sorted, in (t0, t1]) goes to ``out`` rows. Every sub-interval ends exactly at a
    switch or a sample time."""
    k1 = np.empty(NS)
    k2 = np.empty(NS)
    sp = np.empty(NS)
    n_req = t_req.shape[0]
    j = 0
    t = t0
    while True:
        nb = t1
        if t < t_sw < nb:
            nb = t_sw
        if j < n_req and t_req[j] < nb:
            nb = max(t_req[j], t)
        span = nb - t
        if span > 0.0:
            mid = 0.5 * (t + nb)
            up = ub_p if mid >= t_sw else ua_p
            ur = ub_r if mid >= t_sw else ua_r
            n = int(math.ceil(span / h_max - 1e-9))
            if n < 1:
                n = 1
            h = span / n
            for i in range(n):
                tt = t + i * h
                _deriv(tt, s, up, ur, fx, fy, par, kt, kh, k1)
                for k in range(NS):
                    sp[k] = s[k] + h * k1[k]
                _deriv(tt + h, sp, up, ur, fx, fy, par, kt, kh, k2)
                for k in range(NS):
                    s[k] += 0.5 * h * (k1[k] + k2[k])
        t = nb
        done = t >= t1 - 1e-12
        while j < n_req and (done or t_req[j] <= t + 1e-12):
            for k in range(NS):
                out[j, k] = s[k]
            j += 1
        if done:
            break


def make_params(*, g: float = 9.81, m: float = 1.0, b: float = 0.0, c: float = 0.0, omega_p: float = 5.4,
                zeta: float = 0.71, gain: float = 1.0, rx: float = 0.0, ry: float = 0.0, rz: float = 0.0,
                tau: float = 0.0) -> np.ndarray:
    """The numba parameter vector (``NPAR`` entries) from named values (SI; ``tau`` 0 = no gyro lag)."""
    return np.array([g, m, b, c, omega_p, zeta, gain, rx, ry, rz, tau], dtype=float)


def plant_params(spec: FlightSpec) -> np.ndarray:
    """The parameter vector of the true vehicle of ``spec``."""
    e = spec.effects
    wp, ze = spec.true_attitude_loop()
    lever = e.get("flow_lever_arm", {})
    return make_params(g=spec.vehicle.gravity_m_s2, m=spec.vehicle.mass_kg, b=e.get("linear_drag", {}).get("b", 0.0),
                       c=e.get("quadratic_drag", {}).get("c", 0.0), omega_p=wp, zeta=ze,
                       gain=e.get("flow_rotation_gain", {}).get("gain", 1.0), rx=lever.get("rx", 0.0),
                       ry=lever.get("ry", 0.0), rz=lever.get("rz", 0.0), tau=e.get("gyro_lag", {}).get("tau", 0.0))


def sensor_distance(h: float, pitch: float, roll: float, rx: float = 0.0, ry: float = 0.0, rz: float = 0.0) -> float:
    """Distance along body z from a sensor at body offset (rx, ry, rz) to flat ground, the vehicle's
    centre of gravity ``h`` above it (the same expression the integrator uses)."""
    ct, cp = math.cos(pitch), math.cos(roll)
    return (h + math.sin(pitch) * rx - ct * math.sin(roll) * ry - ct * cp * rz) / (ct * cp)


def integrate(state: np.ndarray, t0: float, t1: float, *, par: np.ndarray, kt: np.ndarray, kh: np.ndarray,
              command: tuple[float, float] = (0.0, 0.0), switch: tuple[float, float, float] | None = None,
              force: tuple[float, float] = (0.0, 0.0), samples: np.ndarray | None = None,
              integrator_hz: float = 2000.0) -> np.ndarray:
    """Integrate ``state`` (modified in place) from ``t0`` to ``t1``; the command (pitch, roll)
    switches to ``switch[1:]`` at ``switch[0]``. Returns the states at ``samples`` (rows)."""
    req = np.zeros(0) if samples is None else np.asarray(samples, dtype=float)
    out = np.zeros((len(req), NS))
    t_sw, ub = (math.inf, command) if switch is None else (switch[0], (switch[1], switch[2]))
    _advance(state, float(t0), float(t1), 1.0 / integrator_hz, float(t_sw), float(command[0]), float(command[1]),
             float(ub[0]), float(ub[1]), float(force[0]), float(force[1]), par, kt, kh, req, out)
    return out


def sensor_counts(phi_x: float, phi_y: float, yaw: float, q_x: float, q_y: float) -> tuple[int, int]:
    """Eq. 10 in the sensor's own axes: accumulated counts floor(s / q) of the body-axis scene
    angle turned by ``yaw`` about z, with the sensor's true rad per count per axis."""
    c, s = math.cos(yaw), math.sin(yaw)
    sx = c * phi_x + s * phi_y
    sy = -s * phi_x + c * phi_y
    return math.floor(sx / q_x), math.floor(sy / q_y)


def ar1(rng: np.random.Generator, n: int, sigma: float, tau_s: float, dt_s: float) -> np.ndarray:
    """A first-order Gauss-Markov sequence sampled every ``dt_s`` (stationary, std ``sigma``)."""
    if sigma <= 0.0 or n == 0:
        return np.zeros(n)
    a = math.exp(-dt_s / tau_s)
    w = rng.standard_normal(n) * sigma * math.sqrt(1.0 - a * a)
    out = np.empty(n)
    x = rng.standard_normal() * sigma
    for i in range(n):  # plain recursion: n is at most a few 1e5
        x = a * x + w[i]
        out[i] = x
    return out


def apply_loss(t_s: np.ndarray, loss: Loss, rng: np.random.Generator) -> np.ndarray:
    """Keep mask of the messages sent at simulation times ``t_s``."""
    keep = rng.random(len(t_s)) >= loss.random_frac
    for b in loss.bursts_s:
        keep &= ~((t_s >= b) & (t_s < b + loss.burst_s))
    return keep


def _f32(x: float) -> float:
    return float(np.float32(x))


def _i16(x: float) -> int:
    return int(max(-32767, min(32767, round(x))))


# ---------------------------------------------------------------------------------------------
# the closed loop


@dataclass
class Flight:
    """A simulated flight: the packets sent (simulation send time, sender, bytes, message type),
    what the recording keeps, and per-frame truth for statistics."""

    packets: list[tuple[float, int, bytes, str, int]]  # (send time, component, bytes, type, frame index)
    record_t_s: np.ndarray  # per packet: UNIX arrival time in the log
    keep: np.ndarray  # per packet: kept in the recording
    frame_t_s: np.ndarray
    truth: dict[str, np.ndarray]
    stats: dict[str, Any]


def simulate(spec: FlightSpec) -> Flight:
    """Fly ``spec`` closed loop with the companion and make every message (see the module doc)."""
    from pymavlink.dialects.v20 import ardupilotmega as mav

    cfg = load_config_text(nominal_config_text(spec), f"gen{spec.seed}.toml", load_config)
    prof = Profile(spec.sensors.profile)
    core = CompanionCore(cfg, prof)
    router = MessageRouter(core, prof)
    rng = np.random.default_rng([spec.seed, 99])
    T = spec.frame_s
    n_frames = int(round((spec.warmup_s + spec.duration_s) / T)) + 1
    t_frames = np.arange(n_frames) * T
    rec_k0 = int(round(spec.warmup_s / T))
    e = spec.effects
    nz = spec.noise
    sen = spec.sensors
    veh = spec.vehicle
    ardu = prof is Profile.ARDUPILOT

    par = plant_params(spec)
    kt = np.asarray(spec.flight.alt_t_s, dtype=float)
    kh = np.asarray(spec.flight.alt_m, dtype=float)
    vx_set, vy_set = spec.flight.setpoint(t_frames)
    # forces per frame interval: the wind (edges on the frame grid) plus turbulence
    fx = ar1(rng, n_frames, nz.turbulence_n, nz.turbulence_tau_s, T)
    fy = ar1(rng, n_frames, nz.turbulence_n, nz.turbulence_tau_s, T)
    wind = e.get("wind_force")
    if wind:
        on = (t_frames >= wind["start_s"] - 1e-9) & (t_frames < wind["end_s"] - 1e-9)
        fx = fx + np.where(on, wind["fx"], 0.0)
        fy = fy + np.where(on, wind["fy"], 0.0)
    att_noise = [ar1(rng, n_frames, nz.att_gm_rad, nz.att_gm_tau_s, T)
                 + nz.att_white_rad * rng.standard_normal(n_frames) for _ in range(3)]
    gyro_noise = nz.gyro_white_rad_s * rng.standard_normal((n_frames, 2))
    range_noise = nz.range_noise_m * rng.standard_normal(n_frames)
    count_err = np.where(rng.random((n_frames, 2)) < nz.flow_count_error_frac,
                         np.where(rng.random((n_frames, 2)) < 0.5, -1, 1), 0)
    jit = nz.sensor_time_jitter_s * rng.uniform(-1.0, 1.0, (n_frames, 4))  # flow, imu, attitude, range
    arng = np.random.default_rng([spec.seed, 97])  # the accelerometer's own stream (generator version 4)
    acc_noise = (nz.accel_white_m_s2 * arng.standard_normal((n_frames, 2))
                 + np.array([nz.accel_bias_x_m_s2, nz.accel_bias_y_m_s2])
                 + nz.accel_vibration_m_s2 * np.sin(2 * math.pi * nz.accel_vibration_hz * t_frames[:, None]
                                                    + arng.uniform(0.0, 2 * math.pi, 2)))

    bias = e.get("gyro_bias", {})
    bias_x, bias_y = bias.get("bias_x", 0.0), bias.get("bias_y", 0.0)
    scale = e.get("flow_scale", {})
    qx = sen.q_rad_per_count * scale.get("scale_x", 1.0)
    qy = sen.q_rad_per_count * scale.get("scale_y", 1.0)
    yaw_mis = e.get("flow_yaw_misalignment", {}).get("yaw", 0.0)
    d_flow = e.get("flow_delay", {}).get("delay", 0.0)
    d_att = e.get("attitude_delay", {}).get("delay", 0.0)
    r_off = e.get("range_offset", {}).get("offset", 0.0)
    lever = e.get("flow_lever_arm", {})
    rx, ry, rz = lever.get("rx", 0.0), lever.get("ry", 0.0), lever.get("rz", 0.0)
    psi = veh.heading_rad
    cpsi, spsi = math.cos(psi), math.sin(psi)
    rmin_cm, rmax_cm = int(round(sen.range_min_m * 100)), int(round(sen.range_max_m * 100))

    venc = mav_encoder(1, 1)
    cenc = mav_encoder(1, COMPANION_COMPONENT)
    packets: list[tuple[float, int, bytes, str, int]] = []
    frame = [0]

    def send(t: float, enc: Any, msg: Any) -> Any:
        packets.append((t, enc.srcComponent, bytes(msg.pack(enc)), msg.get_type(), frame[0]))
        enc.seq = (enc.seq + 1) % 256
        return msg

    # state at t = 0: hovering level at the first height
    s = np.zeros(NS)
    lead = np.array([sen.imu_lead_s, sen.att_lead_s, sen.range_lead_s])
    sample_now = np.tile(s, (3, 1))  # states at the sensor samples of the current frame
    flow_samples: dict[int, tuple[float, float]] = {}
    n_skip = int(math.floor(d_flow / T + 1e-9))
    prev_counts = (0, 0)
    gint_prev = (0.0, 0.0)
    cmd_now = (0.0, 0.0)  # (pitch, roll) acting now
    pending: list[tuple[float, float, float]] = []  # (switch time, pitch, roll)
    truth = {k: np.zeros(n_frames) for k in ("vx", "vy", "pitch", "roll", "h", "pitch_cmd", "roll_cmd", "range",
                                             "vx_est", "vy_est", "scene_rate")}
    holds: dict[str, int] = {}
    next_hb = 0.0
    tb = veh.boot_s
    sample_end = s.copy()
    gint_now = (0.0, 0.0)
    last_s = (0.0, 0.0)
    for k in range(n_frames):
        t = float(t_frames[k])
        # -- the vehicle's messages for frame k
        s_imu, s_att, s_rng = sample_now
        g_x = (s_imu[GX] if par[10] > 0 else s_imu[PR]) + bias_x + gyro_noise[k, 0]
        g_y = (s_imu[GY] if par[10] > 0 else s_imu[QR]) + bias_y + gyro_noise[k, 1]
        th_i, ph_i = s_imu[TH], s_imu[PH]
        ax = (fx[k] - par[2] * s_imu[VX] - par[3] * s_imu[VX] * abs(s_imu[VX])) / par[1]
        ay = (fy[k] - par[2] * s_imu[VY] - par[3] * s_imu[VY] * abs(s_imu[VY])) / par[1]
        g0 = veh.gravity_m_s2
        acc_x = math.cos(th_i) * ax + acc_noise[k, 0]
        acc_y = math.cos(ph_i) * ay + acc_noise[k, 1]
        imu = venc.raw_imu_encode(int(round((tb + t - sen.imu_lead_s + jit[k, 1]) * 1e6)),
                                  _i16(1000 * acc_x / g0), _i16(1000 * acc_y / g0),
                                  _i16(-1000 / (math.cos(th_i) * math.cos(ph_i))), _i16(1000 * g_x),
                                  _i16(1000 * g_y), _i16(1000 * 0.0), 0, 0, 0)
        h_r = _height(t - sen.range_lead_s, kt, kh)
        th_r, ph_r = s_rng[TH], s_rng[PH]
        dist = sensor_distance(h_r, th_r, ph_r, rx, ry, rz)
        rng_cm = int(round(100 * (dist + r_off + range_noise[k])))
        dsm = venc.distance_sensor_encode(int(round((tb + t - sen.range_lead_s + jit[k, 3]) * 1e3)), rmin_cm, rmax_cm,
                                          max(0, min(65535, rng_cm)), 0, 0, 25, 0)
        att = venc.attitude_encode(int(round((tb + t - sen.att_lead_s + jit[k, 2]) * 1e3)),
                                   _f32(s_att[PH] + att_noise[0][k]), _f32(s_att[TH] + att_noise[1][k]),
                                   _f32(psi + 0.5 * att_noise[2][k]), _f32(s_att[PR]), _f32(s_att[QR]), 0.0)
        # the flow frame k: scene angle sampled d_flow before t_k, in sensor axes, quantized
        phi = flow_samples.pop(k, (0.0, 0.0))
        counts = sensor_counts(phi[0], phi[1], yaw_mis, qx, qy)
        dx, dy = counts[0] - prev_counts[0], counts[1] - prev_counts[1]
        prev_counts = counts
        if ardu:
            # ArduPilot: rates over the frame (no quantization), time in ms, body rate the mean
            # gyro the autopilot has over the frame (flow_rate - flow_comp_m)
            c_, s_ = math.cos(yaw_mis), math.sin(yaw_mis)
            if k == 0:
                rate_sx = rate_sy = 0.0
            else:
                sx_now = (c_ * phi[0] + s_ * phi[1]) / (qx / sen.q_rad_per_count)
                sy_now = (-s_ * phi[0] + c_ * phi[1]) / (qy / sen.q_rad_per_count)
                rate_sx = (sx_now - last_s[0]) / T + count_err[k, 0] * sen.q_rad_per_count / T
                rate_sy = (sy_now - last_s[1]) / T + count_err[k, 1] * sen.q_rad_per_count / T
            last_s = ((c_ * phi[0] + s_ * phi[1]) / (qx / sen.q_rad_per_count),
                      (-s_ * phi[0] + c_ * phi[1]) / (qy / sen.q_rad_per_count))
            gi = gint_now if k > 0 else (0.0, 0.0)
            body_x = (gi[0] - gint_prev[0]) / T + bias_x + gyro_noise[k, 0] if k > 0 else g_x
            body_y = (gi[1] - gint_prev[1]) / T + bias_y + gyro_noise[k, 1] if k > 0 else g_y
            gint_prev = gi
            fr_x, fr_y = _f32(rate_sy), _f32(-rate_sx)  # flow_rate_x = dphi_y/dt, flow_rate_y = -dphi_x/dt
            flow = venc.optical_flow_encode(int(round((tb + t + jit[k, 0]) * 1e3)), 0, int(fr_x), int(fr_y),
                                            _f32(fr_x - body_x), _f32(fr_y - body_y), 51,
                                            _f32(_height(t, kt, kh)), fr_x, fr_y)
        else:
            flow = venc.optical_flow_encode(int(round((tb + t + jit[k, 0]) * 1e6)), 0,
                                            int(dx + count_err[k, 0]), int(dy + count_err[k, 1]), 0.0, 0.0, 255,
                                            -1.0)
        t_send = t + 0.0002
        frame[0] = k
        if t >= next_hb:  # the vehicle's heartbeat leads its frame (the companion sees the mode first)
            send(t - 0.0055, venc, venc.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                         209, 20, mav.MAV_STATE_ACTIVE))
        for t_m, m_ in ((t - sen.imu_lead_s, imu), (t - sen.range_lead_s, dsm), (t - sen.att_lead_s, att),
                        (t, flow)):
            send(t_m + 0.0002, venc, m_)
        if k % 5 == 0:
            hd = (_height(t + 0.01, kt, kh) - _height(t - 0.01, kt, kh)) / 0.02
            vx_b, vy_b, px_b, py_b = sample_end[VX], sample_end[VY], sample_end[PX], sample_end[PY]
            send(t_send, venc, venc.local_position_ned_encode(
                int(round((tb + t) * 1e3)), cpsi * px_b - spsi * py_b, spsi * px_b + cpsi * py_b,
                -_height(t, kt, kh), cpsi * vx_b - spsi * vy_b, spsi * vx_b + cpsi * vy_b, -hd))
        # -- the companion: sensors in the order received, then its step on the flow frame
        core.set_setpoint(float(vx_set[k]), float(vy_set[k]))
        for m_ in (imu, dsm, att):
            router.handle(m_)
        out = router.handle(flow)
        assert out is not None
        if out.holding:
            holds[out.hold_cause.value] = holds.get(out.hold_cause.value, 0) + 1
        ms = int(round(out.time_s * 1e3)) if math.isfinite(out.time_s) else 0
        tc = t + sen.companion_proc_s
        send(tc, cenc, cenc.position_target_local_ned_encode(ms & 0xFFFFFFFF, 12, 3527, 0.0, 0.0, 0.0,
                                                             out.vx_set_m_s, out.vy_set_m_s, 0.0, 0.0, 0.0, 0.0,
                                                             0.0, 0.0))
        if math.isfinite(out.vx_m_s) and math.isfinite(out.vy_m_s):
            send(tc + 0.0001, cenc, cenc.vision_speed_estimate_encode(int(round(out.time_s * 1e6)), out.vx_m_s,
                                                                      out.vy_m_s, 0.0, [math.nan] * 9, 0))
        send(tc + 0.0002, cenc, cenc.set_attitude_target_encode(
            ms & 0xFFFFFFFF, 1, 1, 7, euler_to_quaternion(out.roll_cmd_rad, out.pitch_cmd_rad, psi), 0.0, 0.0, 0.0,
            0.5))
        if t >= next_hb:
            send(tc + 0.0003, cenc, cenc.heartbeat_encode(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID,
                                                          0, 0, mav.MAV_STATE_ACTIVE))
            next_hb += 1.0
        # the command of frame k acts from frame k+1 (+ attitude_delay)
        pending.append((t + T + d_att, out.pitch_cmd_rad, out.roll_cmd_rad))
        # truth of frame k
        st = sample_end
        truth["vx"][k], truth["vy"][k] = st[VX], st[VY]
        truth["pitch"][k], truth["roll"][k] = st[TH], st[PH]
        truth["h"][k] = _height(t, kt, kh)
        truth["pitch_cmd"][k], truth["roll_cmd"][k] = out.pitch_cmd_rad, out.roll_cmd_rad
        truth["range"][k] = dist
        truth["vx_est"][k], truth["vy_est"][k] = out.vx_m_s, out.vy_m_s
        truth["scene_rate"][k] = max(abs(dx), abs(dy)) * sen.q_rad_per_count / T
        if k == n_frames - 1:
            break
        # -- integrate (t_k, t_k+1]
        t1 = float(t_frames[k + 1])
        switch = None
        while pending and pending[0][0] <= t + 1e-12:
            cmd_now = (pending[0][1], pending[0][2])
            pending.pop(0)
        if pending and pending[0][0] <= t1 + 1e-12:
            switch = pending[0]
        j_flow = k + 1 + n_skip
        t_flow = j_flow * T - d_flow
        req = [t1 - lead[0], t1 - lead[1], t1 - lead[2], t1]
        if t < t_flow <= t1 + 1e-12:
            req.append(min(t_flow, t1))
        order = np.argsort(req, kind="stable")
        reqa = np.asarray(req)[order]
        outs = integrate(s, t, t1, par=par, kt=kt, kh=kh, command=cmd_now,
                         switch=None if switch is None else (max(switch[0], t), switch[1], switch[2]),
                         force=(float(fx[k]), float(fy[k])), samples=reqa, integrator_hz=spec.integrator_hz)
        got = np.empty_like(outs)
        got[order] = outs
        sample_now = got[:3]
        sample_end = got[3]
        gint_now = (float(sample_end[IX]), float(sample_end[IY]))
        if len(req) == 5:
            flow_samples[j_flow] = (float(got[4][SX]), float(got[4][SY]))
        elif j_flow * T - d_flow <= 0.0:
            flow_samples[j_flow] = (0.0, 0.0)
        if switch is not None:
            cmd_now = (switch[1], switch[2])
            pending.pop(0)

    # -- the recording: arrival times, loss
    send_t = np.array([p[0] for p in packets])
    lrng = np.random.default_rng([spec.seed, 7])
    rec_t = veh.unix0_s + send_t + nz.record_jitter_s * lrng.random(len(send_t))
    in_rec = np.array([p[4] for p in packets]) >= rec_k0
    keep = in_rec & apply_loss(send_t, spec.loss, lrng)
    k0 = rec_k0
    sat = np.abs(truth["pitch_cmd"][k0:]) >= math.radians(TILT_LIMIT_DEG) * 0.999
    sat |= np.abs(truth["roll_cmd"][k0:]) >= math.radians(TILT_LIMIT_DEG) * 0.999
    err = np.hypot(truth["vx"][k0:] - vx_set[k0:], truth["vy"][k0:] - vy_set[k0:])
    stats: dict[str, Any] = {
        "frames": int(n_frames - k0),
        "max_tilt_deg": float(np.degrees(np.max(np.abs(np.r_[truth["pitch"][k0:], truth["roll"][k0:]])))),
        "saturated_share": float(np.mean(sat)),
        "rms_velocity_error_m_s": float(np.sqrt(np.mean(err ** 2))),
        "max_speed_m_s": float(np.max(np.hypot(truth["vx"][k0:], truth["vy"][k0:]))),
        "max_scene_rate_rad_s": float(np.max(truth["scene_rate"][k0:])),
        "holds": holds,
        "packets_sent": int(np.count_nonzero(in_rec)),
        "packets_kept": int(np.count_nonzero(keep)),
    }
    stats["flyable"] = bool(stats["saturated_share"] < 0.05 and stats["max_speed_m_s"] < 4.0
                            and sum(holds.values()) < 0.02 * n_frames)
    truth["vx_set"], truth["vy_set"] = vx_set, vy_set
    return Flight(packets, rec_t, keep, t_frames, truth, stats)


# ---------------------------------------------------------------------------------------------
# files


_KEY_LINE = r"^(\s*{key}\s*=\s*)([^#\n]*?)(\s*(#.*)?)$"


def _set_key(text: str, section: str, key: str, value: str) -> str:
    """Replace ``key = ...`` inside ``[section]`` of a TOML text, keeping the comment."""
    m = re.search(rf"^\[{re.escape(section)}\]\s*$", text, flags=re.M)
    if m is None:
        raise ValueError(f"no [{section}] in the base config")
    nxt = re.search(r"^\[", text[m.end():], flags=re.M)
    end = m.end() + (nxt.start() if nxt else len(text) - m.end())
    body = text[m.end():end]
    body2, n = re.subn(_KEY_LINE.format(key=re.escape(key)), lambda mm: mm.group(1) + value + mm.group(3), body,
                       count=1, flags=re.M)
    if n != 1:
        raise ValueError(f"no {key} in [{section}] of the base config")
    return text[:m.end()] + body2 + text[end:]


def nominal_config_text(spec: FlightSpec) -> str:
    """The config the user believes: the base file with the vehicle's nominal values."""
    text = (CONFIG_DIR.parent / spec.sensors.base_config).read_text()
    head = (f"# Nominal model of generated recording seed {spec.seed} (simvehicle/engines/flightgen.py), copied from "
            f"{spec.sensors.base_config}\n# with the drawn airframe, attitude loop, frame rate and Q.\n")
    for section, key, value in (("airframe", "mass_kg", spec.vehicle.mass_kg),
                                ("airframe", "omega_p_rad_s", spec.vehicle.omega_p_nominal),
                                ("airframe", "zeta", spec.vehicle.zeta_nominal),
                                ("flow_sensor", "frame_rate_hz", spec.sensors.frame_rate_hz),
                                ("flow_sensor", "q_rad_per_count", spec.sensors.q_rad_per_count),
                                ("rangefinder", "min_m", spec.sensors.range_min_m),
                                ("rangefinder", "max_m", spec.sensors.range_max_m),
                                ("world", "altitude_m", spec.flight.alt_m[0])):
        text = _set_key(text, section, key, repr(float(value)))
    return head + text


def load_config_text(text: str, name: str, loader: Any) -> Any:
    """A Config from TOML text (through a temporary file, as the CLI reads it)."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / name
        p.write_text(text)
        return loader(p)


def _usable_window(times: dict[str, np.ndarray], t_first: float, t_last: float, max_gap: float = 0.6,
                   min_len: float = 5.0) -> tuple[float, float]:
    """First and last time of the stretches of at least ``min_len`` s where no needed message
    type has a gap over ``max_gap`` s (the usable frames)."""
    bad: list[tuple[float, float]] = []
    for ts in times.values():
        ts = np.sort(ts)
        if len(ts) == 0:
            return math.nan, math.nan
        bad.append((t_first - 1.0, ts[0]))
        bad.append((ts[-1], t_last + 1.0))
        d = np.diff(ts)
        for i in np.flatnonzero(d > max_gap):
            bad.append((float(ts[i]), float(ts[i + 1])))
    bad.sort()
    good: list[tuple[float, float]] = []
    cur = t_first - 1.0
    for a, b in bad:
        if a > cur:
            good.append((cur, a))
        cur = max(cur, b)
    if cur < t_last:
        good.append((cur, t_last))
    good = [(a, b) for a, b in good if b - a >= min_len]
    if not good:
        return math.nan, math.nan
    return good[0][0], good[-1][1]


def truth_of(spec: FlightSpec, flight: Flight) -> dict[str, Any]:
    """The truth sidecar: drawn parameters (effects in CONVENTIONS.md names, times in seconds from
    the recording's first record), noise, loss, duration and flight statistics."""
    kept = np.flatnonzero(flight.keep)
    t_first_unix = float(np.min(flight.record_t_s[kept]))
    t_last_unix = float(np.max(flight.record_t_s[kept]))
    first_sim = t_first_unix - spec.vehicle.unix0_s  # simulation time of the first record

    def rel(t_sim: float) -> float:
        return float(t_sim - first_sim)

    by_type: dict[str, list[float]] = {}
    for i in kept:
        p = flight.packets[i]
        if p[3] in ("OPTICAL_FLOW", "RAW_IMU", "DISTANCE_SENSOR", "ATTITUDE", "SET_ATTITUDE_TARGET"):
            by_type.setdefault(p[3], []).append(float(flight.record_t_s[i] - t_first_unix))
    times = {k: np.asarray(v) for k, v in by_type.items()}
    flow_t = times.get("OPTICAL_FLOW", np.zeros(0))
    u0, u1 = _usable_window(times, 0.0, t_last_unix - t_first_unix)
    effects: dict[str, dict[str, float]] = {}
    for name, drawn in spec.effects.items():
        q = dict(drawn)
        if name == "wind_force":
            q["start_s"] = rel(max(drawn["start_s"], spec.warmup_s)) if not spec.wind_from_start else (
                float(flow_t[0]) if len(flow_t) else 0.0)
            q["end_s"] = (float(flow_t[-1]) if len(flow_t) else rel(spec.warmup_s + spec.duration_s)) \
                if spec.wind_to_end else rel(drawn["end_s"])
        effects[name] = q
    wind = None
    if "wind_force" in spec.effects:
        wind = {"start_at_first_frame": spec.wind_from_start, "end_at_last_frame": spec.wind_to_end,
                "start_sim_s": spec.effects["wind_force"]["start_s"], "end_sim_s": spec.effects["wind_force"]["end_s"],
                "force_n": math.hypot(spec.effects["wind_force"]["fx"], spec.effects["wind_force"]["fy"])}
    return {
        "generator": "simvehicle/engines/flightgen.py",
        "generator_version": GENERATOR_VERSION,
        "seed": spec.seed,
        "profile": spec.sensors.profile,
        "duration_s": spec.duration_s,
        "recording_span_s": float(t_last_unix - t_first_unix),
        "first_record_sim_s": first_sim,
        "first_frame_s": float(flow_t[0]) if len(flow_t) else math.nan,
        "last_frame_s": float(flow_t[-1]) if len(flow_t) else math.nan,
        "first_usable_s": u0,
        "last_usable_s": u1,
        "effects": effects,
        "wind": wind,
        "nominal": {"mass_kg": spec.vehicle.mass_kg, "gravity_m_s2": spec.vehicle.gravity_m_s2,
                    "omega_p": spec.vehicle.omega_p_nominal, "zeta": spec.vehicle.zeta_nominal,
                    "q_rad_per_count": spec.sensors.q_rad_per_count, "frame_rate_hz": spec.sensors.frame_rate_hz},
        "true_attitude_loop": dict(zip(("omega_p", "zeta"), spec.true_attitude_loop(), strict=True)),
        "vehicle": dataclasses.asdict(spec.vehicle),
        "sensors": dataclasses.asdict(spec.sensors),
        "noise": dataclasses.asdict(spec.noise),
        "loss": {**dataclasses.asdict(spec.loss), "kind": spec.loss.kind,
                 "bursts_s": [rel(b) for b in spec.loss.bursts_s]},
        "flight": {"speed_limit_m_s": spec.flight.speed_limit_m_s, "warmup_s": spec.warmup_s,
                   "segments": [s.kind for s in spec.flight.segments],
                   "altitude_knots": [[rel(t), h] for t, h in zip(spec.flight.alt_t_s, spec.flight.alt_m,
                                                                  strict=True)]},
        "model": {"rangefinder": "on the flow sensor's board (reads the sensor's slant range + offset)",
                  "quadratic_drag": "per axis, -c v|v|", "telemetry_loss": "recording only; the loop is lossless",
                  "integrator": f"Heun (RK2) <= {1.0 / spec.integrator_hz * 1e3:g} ms steps, split at events"},
        "stats": flight.stats,
    }


@dataclass(frozen=True)
class Generated:
    tlog: Path
    config: Path
    truth_path: Path
    truth: dict[str, Any]


def write_flight(spec: FlightSpec, flight: Flight, folder: str | Path, stem: str) -> Generated:
    """Write ``stem.tlog`` (records in arrival order), ``stem.toml`` (nominal config) and
    ``stem.truth.json`` into ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    tlog = folder / f"{stem}.tlog"
    idx = np.flatnonzero(flight.keep)
    order = idx[np.argsort(flight.record_t_s[idx], kind="stable")]
    part = tlog.with_suffix(".tlog.part")
    with TlogWriter(part) as w:
        for i in order:
            w.write_bytes(flight.packets[i][2], float(flight.record_t_s[i]))
    part.replace(tlog)
    cfg = folder / f"{stem}.toml"
    cfg.write_text(nominal_config_text(spec))
    truth = truth_of(spec, flight)
    truth["files"] = {"tlog": tlog.name, "config": cfg.name}
    tp = folder / f"{stem}.truth.json"
    tp.write_text(json.dumps(jsonable(truth), indent=1) + "\n")
    return Generated(tlog, cfg, tp, truth)


def jsonable(x: Any) -> Any:
    """``x`` with numpy scalars as Python numbers and non-finite floats as None (strict JSON)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def generate(seed: int, folder: str | Path, stem: str | None = None, **draw_kw: Any) -> Generated:
    """``draw_spec`` + ``simulate`` + ``write_flight``."""
    spec = draw_spec(seed, **draw_kw)
    return write_flight(spec, simulate(spec), folder, stem or f"gen_{seed}")


# ---------------------------------------------------------------------------------------------
# scoring


#: (kind, tolerance): "abs" absolute, "rel" relative to the true value
TOLERANCES: dict[str, dict[str, tuple[str, float]]] = {
    "linear_drag": {"b": ("rel", 0.20)},
    "quadratic_drag": {"c": ("rel", 0.25)},
    "gyro_bias": {"bias_x": ("abs", 0.005), "bias_y": ("abs", 0.005)},
    "flow_scale": {"scale_x": ("abs", 0.03), "scale_y": ("abs", 0.03)},
    "flow_delay": {"delay": ("abs", 0.005)},
    "flow_yaw_misalignment": {"yaw": ("abs", math.radians(2.0))},
    "attitude_dynamics": {"omega_p": ("rel", 0.15), "zeta": ("abs", 0.15)},
    "range_offset": {"offset": ("abs", 0.03)},
    "wind_force": {"force": ("vec", 0.20), "start_s": ("abs", 1.5), "end_s": ("abs", 1.5)},
    "attitude_delay": {"delay": ("abs", 0.005)},
    "flow_rotation_gain": {"gain": ("abs", 0.03)},
    "flow_lever_arm": {"rz": ("abs", 0.05)},
    "gyro_lag": {"tau": ("rel", 0.30)},
}

_V2 = re.compile(r"velocity\s*\|\s*velocity\s*\||v\s*\|\s*v\s*\||v\s*\^\s*2|v\*\*2|v²|velocity[- ]squared|"
                 r"squared velocity|quadratic", re.I)
_LAG = re.compile(r"\blag|low-pass|lowpass|low pass", re.I)


def _num(v: Any) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return math.nan
    return x


def _param_errors(effect: str, truth: dict[str, Any], found: dict[str, Any], t_truth: dict[str, Any]
                  ) -> dict[str, float]:
    """|error| / tolerance per scored parameter (inf when missing)."""
    out: dict[str, float] = {}
    for p, (kind, tol) in TOLERANCES[effect].items():
        if kind == "vec":
            fx, fy = _num(found.get("fx")), _num(found.get("fy"))
            err = math.hypot(fx - truth["fx"], fy - truth["fy"])
            out[p] = err / (tol * math.hypot(truth["fx"], truth["fy"]))
            continue
        f = _num(found.get(p))
        tv = float(truth[p])
        if effect == "wind_force" and p in ("start_s", "end_s"):
            wind = t_truth.get("wind") or {}
            edge = "first" if p == "start_s" else "last"
            flagged = wind.get("start_at_first_frame" if p == "start_s" else "end_at_last_frame")
            err = abs(f - tv)
            if flagged:
                usable = _num(t_truth.get(f"{edge}_usable_s"))
                if math.isfinite(usable):
                    err = min(err, abs(f - usable))
            out[p] = err / tol
            continue
        err = abs(f - tv)
        out[p] = err / (tol * abs(tv)) if kind == "rel" else err / tol
    return {k: (v if math.isfinite(v) else math.inf) for k, v in out.items()}


def _text(u: dict[str, Any]) -> str:
    return " ".join(str(v) for v in u.values() if isinstance(v, str))


def score(truth: dict[str, Any], report: dict[str, Any]) -> dict[str, Any]:
    """Compare a diagnose report (CONVENTIONS.md layout) with a truth sidecar.

    Per true effect: ``hit`` when it is reported significant with every scored parameter within
    ``TOLERANCES``, else ``miss`` (``reason``: not reported / out of tolerance / aliased). A
    significant finding whose effect is not in the truth is a false finding, except a
    ``linear_drag`` for a true ``quadratic_drag`` when an unexplained entry names a velocity-squared
    term. A true ``gyro_lag`` not named but left as an unexplained gyro term that mentions a lag
    is a hit when nothing wrong is named. A finding that names alternatives ("X, or Y: this flight
    cannot tell them apart", the report's ``alternatives``) hits a true effect it names, with that
    effect's parameters, and is false only when none of its effects is true; such hits are listed
    in ``ambiguous_hits``. RIGHT = no miss and no false finding."""
    t_eff: dict[str, dict[str, Any]] = truth.get("effects", {})
    findings = [f for f in report.get("findings", []) if f.get("significant")]
    unexplained = report.get("unexplained", []) or []
    by_name: dict[str, list[dict[str, Any]]] = {}
    #: effects named only as an alternative of a finding ("X, or Y: this flight cannot tell them apart")
    as_alternative: set[str] = set()
    false_set: set[str] = set()
    for f in findings:
        by_name.setdefault(f["effect"], []).append(f)
        alts = f.get("alternatives") or []
        for a in alts:
            by_name.setdefault(a["effect"], []).append(a)
            as_alternative.add(a["effect"])
        named = {f["effect"], *(a["effect"] for a in alts)}
        if not named & set(t_eff):  # an ambiguous finding is false only when no effect it names is true
            false_set.add(f["effect"])
    false = sorted(false_set)
    notes: list[str] = []
    if "quadratic_drag" in t_eff and "linear_drag" in false and "linear_drag" not in t_eff:
        if any(_V2.search(_text(u)) for u in unexplained):
            false.remove("linear_drag")
            notes.append("linear_drag for the true quadratic_drag, velocity-squared term unexplained: not false")
    effects: dict[str, dict[str, Any]] = {}
    for name, tp in t_eff.items():
        cands = by_name.get(name, [])
        if not cands:
            res: dict[str, Any] = {"outcome": "miss", "reason": "not reported", "errors": {}}
            if name == "quadratic_drag" and "linear_drag" in by_name:
                res["reason"] = "aliased: linear_drag named"
            if name == "gyro_lag":
                lag = [u for u in unexplained if "gyro" in _text(u).lower() and _LAG.search(_text(u))]
                if lag and not false:
                    res = {"outcome": "hit", "reason": "unexplained gyro lag term", "errors": {}}
            effects[name] = res
            continue
        best: dict[str, float] | None = None
        for f in cands:
            errs = _param_errors(name, tp, f.get("parameters", {}), truth)
            if best is None or max(errs.values()) < max(best.values()):
                best = errs
        assert best is not None
        ok = all(v <= 1.0 for v in best.values())
        effects[name] = {"outcome": "hit" if ok else "miss", "reason": "" if ok else "out of tolerance",
                         "errors": best}
        if len(cands) > 1:
            notes.append(f"{len(cands)} significant {name} findings")
    hits = [n for n, r in effects.items() if r["outcome"] == "hit"]
    misses = [n for n, r in effects.items() if r["outcome"] == "miss"]
    ambiguous = sorted(n for n in hits
                       if n in as_alternative or any(f.get("alternatives") for f in by_name.get(n, [])))
    return {"effects": effects, "hits": hits, "misses": misses, "false": false, "ambiguous_hits": ambiguous,
            "right": not misses and not false, "clean": not t_eff,
            "reported": sorted(by_name), "n_unexplained": len(unexplained), "notes": notes}
