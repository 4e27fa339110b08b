"""Parameter sets: TOML files bound once into frozen dataclasses.

Every key is required and every unknown key is an error, so that a misspelt gain can never
silently become zero. The one exception is ``[effects]``: an effect that is not listed is off
(the nominal, paper model); an effect that is listed must give ``enabled`` and all its
parameters. Units are in the key names (SI unless the name says otherwise).

``configs/paper.toml`` is Table VI of the paper.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from companion.errors import ConfigError

#: the shipped parameter sets: package data (``companion/configs``, in a checkout a symlink to the
#: top-level ``configs/``), beside this module, so an installed wheel has them too; a package on
#: disk, never zipped, so it is a directory (what importlib.resources.files gives here, without
#: the 6 ms of loading importlib.resources and zipfile at every command's start)
CONFIG_DIR = Path(__file__).parent / "configs"
DEFAULT_CONFIG = CONFIG_DIR / "paper.toml"


@dataclass(frozen=True)
class Airframe:
    """Translational and attitude-loop parameters of the plant (eq. 26-28)."""

    mass_kg: float
    gravity_m_s2: float
    omega_p_rad_s: float
    zeta: float


@dataclass(frozen=True)
class Controller:
    """The discrete PI law of the paper (Table VI), one per axis."""

    kp_rad_per_m_s: float
    ki_rad_per_m: float
    tilt_limit_deg: float

    @property
    def tilt_limit_rad(self) -> float:
        return math.radians(self.tilt_limit_deg)


@dataclass(frozen=True)
class FlowSensor:
    """The optical-flow sensor: frame rate and quantization step Q (eq. 10)."""

    frame_rate_hz: float
    q_rad_per_count: float

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.frame_rate_hz


@dataclass(frozen=True)
class Imu:
    """Gyro model. Noise is off unless ``gyro_noise``; the density is the VN-100's (Table II).
    Accelerometer model (issue 19; the simulator's truth, the companion's noise model): body FRD
    specific force with, when ``accel_noise``, white noise of this density (a sample's 1 sigma is
    density x sqrt(rate); off in the paper's noise-free simulation, as the gyro's) and a constant
    bias on x and y, saturating at its range; ``accelerometer`` false: RAW_IMU's accelerometer
    fields hold the (0, 0, -1000) mg placeholder older recordings have."""

    rate_hz: float
    gyro_noise: bool
    gyro_noise_density_deg_s_sqrt_hz: float
    gyro_range_deg_s: float
    accelerometer: bool
    accel_noise: bool
    accel_noise_density_m_s2_sqrt_hz: float
    accel_bias_x_m_s2: float
    accel_bias_y_m_s2: float
    accel_range_m_s2: float


@dataclass(frozen=True)
class Rangefinder:
    """Downward rangefinder: resolution, valid limits, optional Gaussian noise."""

    resolution_m: float
    min_m: float
    max_m: float
    noise_std_m: float


@dataclass(frozen=True)
class World:
    """The scene: the height of the sensor above flat ground."""

    altitude_m: float


@dataclass(frozen=True)
class Sim:
    """Numerical settings of the reference simulator."""

    #: integration steps per flow frame for the continuous-time plant and scene angle
    substeps_per_frame: int


#: ``[companion] velocity_estimator`` values
VELOCITY_ESTIMATORS = ("auto", "eq15", "tilt", "kf")


@dataclass(frozen=True)
class CompanionSettings:
    """Live-companion settings: setpoint limits and the failsafe thresholds."""

    max_speed_m_s: float
    setpoint_timeout_s: float
    flow_timeout_s: float
    range_timeout_s: float
    #: a gyro sample further than this from a flow frame's time is not aligned with it
    max_gyro_skew_s: float
    #: a scene-angle rate beyond this (rad/s, the flow sensor's physical limit) is a spike, not motion
    max_flow_rate_rad_s: float
    #: body rate for eq. 15: "imu" (RAW_IMU nearest the frame), "flow" (the flow message's own
    #: body rate), or "auto" (flow for the ardupilot profile, imu otherwise; docs/ardupilot.md)
    gyro_source: str
    #: the velocity the PI flies on: "eq15" (the paper's, frame by frame), "tilt" (the attitude-predicted
    #: observer, core.TiltFilter), "kf" (the Kalman filter with the flow sample's age compensated,
    #: estimator.VelocityKalman; docs/estimator.md) or "auto" (kf for ardupilot and px4, eq15 for paper)
    velocity_estimator: str
    #: how much older the flow sample is than its message's time, beyond half the frame it covers
    #: (s; the Kalman filter fuses it at its own time; docs/estimator.md says how to measure it)
    flow_sample_age_s: float
    #: the Kalman filter takes the vehicle's accelerometer (RAW_IMU / SCALED_IMU / HIGHRES_IMU) as its
    #: prediction's input when the vehicle has one (docs/estimator.md); false: the filter without it
    use_accelerometer: bool


# ---------------------------------------------------------------------------------------------
# Effects the paper leaves out (names and parameters as in CONVENTIONS.md). All off by default.


@dataclass(frozen=True)
class LinearDrag:
    b: float  # N s/m


@dataclass(frozen=True)
class GyroBias:
    bias_x: float  # rad/s on the roll-rate gyro
    bias_y: float  # rad/s on the pitch-rate gyro


@dataclass(frozen=True)
class FlowScale:
    scale_x: float  # true rad per count = scale_x * Q
    scale_y: float


@dataclass(frozen=True)
class FlowDelay:
    delay: float  # s, beyond the nominal one-frame latency


@dataclass(frozen=True)
class FlowYawMisalignment:
    yaw: float  # rad, flow-sensor axes turned about body z


@dataclass(frozen=True)
class AttitudeDynamics:
    omega_p: float  # rad/s
    zeta: float


@dataclass(frozen=True)
class RangeOffset:
    offset: float  # m, the rangefinder reads true + offset


@dataclass(frozen=True)
class WindForce:
    fx: float  # N along body x
    fy: float  # N along body y
    start_s: float
    end_s: float


@dataclass(frozen=True)
class Effects:
    """Physical effects the paper leaves out; ``None`` means off."""

    linear_drag: LinearDrag | None = None
    gyro_bias: GyroBias | None = None
    flow_scale: FlowScale | None = None
    flow_delay: FlowDelay | None = None
    flow_yaw_misalignment: FlowYawMisalignment | None = None
    attitude_dynamics: AttitudeDynamics | None = None
    range_offset: RangeOffset | None = None
    wind_force: WindForce | None = None

    def active(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self) if getattr(self, f.name) is not None]


EFFECT_TYPES: dict[str, type] = {
    "linear_drag": LinearDrag,
    "gyro_bias": GyroBias,
    "flow_scale": FlowScale,
    "flow_delay": FlowDelay,
    "flow_yaw_misalignment": FlowYawMisalignment,
    "attitude_dynamics": AttitudeDynamics,
    "range_offset": RangeOffset,
    "wind_force": WindForce,
}


@dataclass(frozen=True)
class Config:
    airframe: Airframe
    controller: Controller
    flow_sensor: FlowSensor
    imu: Imu
    rangefinder: Rangefinder
    world: World
    sim: Sim
    companion: CompanionSettings
    effects: Effects = field(default_factory=Effects)
    source: str = "<built-in>"


_SECTIONS: dict[str, type] = {
    "airframe": Airframe,
    "controller": Controller,
    "flow_sensor": FlowSensor,
    "imu": Imu,
    "rangefinder": Rangefinder,
    "world": World,
    "sim": Sim,
    "companion": CompanionSettings,
}

T = TypeVar("T")

#: keys the parameter sets had and nothing read (issue 13): a file that still gives one is told why
#: in one line, rather than "unknown key"
REMOVED_KEYS: dict[tuple[str, str], str] = {
    ("airframe", "drag_b_n_s_per_m"): "Table VI's drag b is left out of eq. 28 and nothing read this key; drag is the "
                                      "effect [effects.linear_drag] b (N s/m)",
    ("companion", "gyro_timeout_s"): "nothing read it; a frame without a gyro sample within companion.max_gyro_skew_s "
                                     "of its time is held (no gyro sample at the flow frame)",
}


def _coerce(value: Any, annotation: Any, where: str) -> Any:
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ConfigError(f"{where}: must be finite, got {value!r}")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{where}: unsupported field type {annotation!r}")  # pragma: no cover


def bind(cls: type[T], table: Any, where: str) -> T:
    """Bind a TOML table to the frozen dataclass ``cls``: every field required, no others allowed."""
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table, got {table!r}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(table) - set(names))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)} (allowed: {', '.join(names)})")
    missing = [n for n in names if n not in table]
    if missing:
        raise ConfigError(f"{where}: missing key(s) {', '.join(missing)}")
    return cls(**{n: _coerce(table[n], hints[n], f"{where}.{n}") for n in names})


def _bind_effects(table: Any, where: str) -> Effects:
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table of effects")
    unknown = sorted(set(table) - set(EFFECT_TYPES))
    if unknown:
        raise ConfigError(f"{where}: unknown effect(s) {', '.join(unknown)} (known: {', '.join(EFFECT_TYPES)})")
    bound: dict[str, Any] = {}
    for name, sub in table.items():
        if not isinstance(sub, dict) or "enabled" not in sub:
            raise ConfigError(f"{where}.{name}: needs 'enabled = true|false' and its parameters")
        enabled = _coerce(sub["enabled"], bool, f"{where}.{name}.enabled")
        params = {k: v for k, v in sub.items() if k != "enabled"}
        effect: object = bind(EFFECT_TYPES[name], params, f"{where}.{name}")
        if enabled:
            bound[name] = effect
    return Effects(**bound)


def config_from_dict(data: dict[str, Any], source: str = "<dict>") -> Config:
    unknown = sorted(set(data) - set(_SECTIONS) - {"effects"})
    if unknown:
        raise ConfigError(f"{source}: unknown section(s) {', '.join(unknown)} (allowed: "
                          f"{', '.join([*_SECTIONS, 'effects'])})")
    for (section, key), why in REMOVED_KEYS.items():
        if isinstance(data.get(section), dict) and key in data[section]:
            raise ConfigError(f"{source} [{section}]: {key} is no longer a key: {why}; delete the line")
    missing = [s for s in _SECTIONS if s not in data]
    if missing:
        raise ConfigError(f"{source}: missing section(s) {', '.join(missing)}")
    comp = data["companion"]
    if isinstance(comp, dict) and "velocity_filter" in comp:  # renamed by issue 19
        raise ConfigError(f"{source} [companion]: velocity_filter was replaced by velocity_estimator "
                          '("none" -> "eq15", "tilt" -> "tilt"; "kf" and "auto" are new: docs/estimator.md)')
    sections: dict[str, Any] = {name: bind(cls, data[name], f"{source} [{name}]") for name, cls in _SECTIONS.items()}
    effects = _bind_effects(data.get("effects", {}), f"{source} [effects]")
    cfg = Config(**sections, effects=effects, source=source)
    validate(cfg)
    return cfg


def validate(cfg: Config) -> None:
    """Physical sanity checks: a value that would make the model meaningless is an error."""
    checks = [
        (cfg.airframe.mass_kg > 0, "airframe.mass_kg must be > 0"),
        (cfg.airframe.gravity_m_s2 > 0, "airframe.gravity_m_s2 must be > 0"),
        (cfg.airframe.omega_p_rad_s > 0, "airframe.omega_p_rad_s must be > 0"),
        (cfg.airframe.zeta > 0, "airframe.zeta must be > 0"),
        (0 < cfg.controller.tilt_limit_deg < 60, "controller.tilt_limit_deg must be in (0, 60)"),
        (cfg.flow_sensor.frame_rate_hz > 0, "flow_sensor.frame_rate_hz must be > 0"),
        (cfg.flow_sensor.q_rad_per_count > 0, "flow_sensor.q_rad_per_count must be > 0"),
        (cfg.imu.rate_hz > 0, "imu.rate_hz must be > 0"),
        (cfg.imu.accel_noise_density_m_s2_sqrt_hz >= 0, "imu.accel_noise_density_m_s2_sqrt_hz must be >= 0"),
        (cfg.imu.accel_range_m_s2 > 0, "imu.accel_range_m_s2 must be > 0"),
        (cfg.rangefinder.resolution_m >= 0, "rangefinder.resolution_m must be >= 0"),
        (0 <= cfg.rangefinder.min_m < cfg.rangefinder.max_m, "rangefinder needs 0 <= min_m < max_m"),
        (cfg.world.altitude_m > 0, "world.altitude_m must be > 0"),
        (cfg.sim.substeps_per_frame >= 4, "sim.substeps_per_frame must be >= 4 (much finer than a frame)"),
        (cfg.companion.max_speed_m_s > 0, "companion.max_speed_m_s must be > 0"),
        (cfg.companion.max_flow_rate_rad_s > 0, "companion.max_flow_rate_rad_s must be > 0"),
        (cfg.companion.gyro_source in ("auto", "imu", "flow"), "companion.gyro_source must be auto, imu or flow"),
        (cfg.companion.velocity_estimator in VELOCITY_ESTIMATORS,
         f"companion.velocity_estimator must be {', '.join(VELOCITY_ESTIMATORS[:-1])} or {VELOCITY_ESTIMATORS[-1]}, "
         f"got {cfg.companion.velocity_estimator!r}"),
        (0.0 <= cfg.companion.flow_sample_age_s <= 0.2, "companion.flow_sample_age_s must be in [0, 0.2] s"),
    ]
    for ok, message in checks:
        if not ok:
            raise ConfigError(f"{cfg.source}: {message}")


def read_toml(path: str | Path, what: str) -> dict[str, Any]:
    """A TOML file's tables, or a ConfigError with one clear line naming ``what`` it was meant
    to be ("config file", "sensor config", "sweep file")."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{what} not found: {p}") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} path is a directory: {p}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None


def load_config(path: str | Path | None = None) -> Config:
    """Load a parameter set; ``None`` is ``configs/paper.toml`` (Table VI)."""
    p = Path(path) if path is not None else DEFAULT_CONFIG
    return config_from_dict(read_toml(p, "config file"), source=str(p))


def with_effects(cfg: Config, **effects: Any) -> Config:
    """A copy of ``cfg`` with the named effects switched on (an instance) or off (``None``)."""
    unknown = sorted(set(effects) - set(EFFECT_TYPES))
    if unknown:
        raise ConfigError(f"unknown effect(s) {', '.join(unknown)}")
    return dataclasses.replace(cfg, effects=dataclasses.replace(cfg.effects, **effects))


def replace_section(cfg: Config, section: str, **changes: Any) -> Config:
    """A copy of ``cfg`` with fields of one section changed (``replace_section(c, 'world', altitude_m=2)``)."""
    if section not in _SECTIONS:
        raise ConfigError(f"unknown section {section!r}")
    return dataclasses.replace(cfg, **{section: dataclasses.replace(getattr(cfg, section), **changes)})
