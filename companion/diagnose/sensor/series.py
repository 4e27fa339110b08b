"""Extraction: a recording as the sensor series the diagnosis fits (flow counts in the paper's
convention, gyro, accelerometer, valid downward range), on report time. The signals, their
sender, time fields and units, come from ``companion.recordings.signals`` (replay's and diagnose's)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.config import Config
from companion.errors import RecordingError
from companion.recordings.load import Recording
from companion.recordings.signals import downward_range, gyro_sensor, vehicle_flow
from companion.step.profiles import Profile, detect_profile


@dataclass
class SensorSeries:
    """One recording's flow, gyro, accelerometer and range, on report time (s from the first
    record). Flow rows are in recording order; counts in the paper's convention (eq. 11)."""

    name: str
    t_s: np.ndarray  # (n,) flow rows
    counts_x: np.ndarray  # (n,) dX_k, counts (paper convention; float)
    counts_y: np.ndarray
    quality: np.ndarray  # (n,) 0-255
    read_period_s: float  # time one row's counts cover
    gyro_t_s: np.ndarray  # (m,)
    gyro_rad_s: np.ndarray  # (m, 3) body FRD roll, pitch, yaw rate
    accel_t_s: np.ndarray | None  # (p,)
    accel_m_s2: np.ndarray | None  # (p, 3) body FRD specific force
    range_t_s: np.ndarray  # (r,) valid readings only
    range_m: np.ndarray  # (r,)
    q_rad_per_count: float
    profile: str

    def range_at(self, t: np.ndarray) -> np.ndarray:
        return np.interp(t, self.range_t_s, self.range_m)

    def gyro_at(self, t: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t, self.gyro_t_s, self.gyro_rad_s[:, i]) for i in range(3)])


def _sorted(t: np.ndarray, *cols: np.ndarray) -> tuple[np.ndarray, ...]:
    order = np.argsort(t, kind="stable")
    return (t[order], *(c[order] for c in cols))


def extract_series(rec: Recording, cfg: Config, profile: str | None = None) -> SensorSeries:
    """The flow (any profile, as paper-convention counts at the config's Q), gyro, accelerometer
    and valid downward range of the vehicle in ``rec`` (``companion.recordings.signals``: the most frequent
    flow sender; the first of RAW_IMU, SCALED_IMU, HIGHRES_IMU it sent, clipped samples left out),
    on one time base. RecordingError if one is missing."""
    name = Path(rec.path).name
    prof = Profile(profile) if profile else Profile(detect_profile(rec)[0])
    q = cfg.flow_sensor.q_rad_per_count
    flow = vehicle_flow(rec, prof, q)
    of, fc = flow.table, flow.columns
    if len(of) < 20:
        raise RecordingError(f"{name}: only {len(of)} {of.name} messages: too few for a sensor diagnosis")
    t_flow = np.asarray(fc.time_s, dtype=float)
    shift = float(np.median(of.t_s - t_flow))  # sensor (boot) time -> log time
    t0 = rec.t0_s

    def report_time(sensor_s: np.ndarray) -> np.ndarray:
        return (sensor_s + shift) - t0

    spacing = np.diff(t_flow)
    spacing = spacing[spacing > 0]
    nominal = float(np.median(spacing)) if len(spacing) else cfg.flow_sensor.frame_period_s
    if "integration_time_us" in of.fields and np.all(np.isfinite(of["integration_time_us"])) \
            and float(np.median(of["integration_time_us"])) > 0:
        read_period = float(np.median(of["integration_time_us"])) * 1e-6
    else:
        read_period = nominal
    if fc.increment:
        cx = np.asarray(fc.scene_x, dtype=float) / q
        cy = np.asarray(fc.scene_y, dtype=float) / q
    else:  # rates (rad/s) over the frame spacing
        cx = np.asarray(fc.scene_x, dtype=float) * read_period / q
        cy = np.asarray(fc.scene_y, dtype=float) * read_period / q

    gyro = gyro_sensor(rec, flow.sysid)
    if len(gyro) == 0:
        raise RecordingError(f"{name}: the sensor diagnosis needs a gyro (RAW_IMU, SCALED_IMU or HIGHRES_IMU) "
                             "from the vehicle")
    g = np.column_stack([gyro.x_rad_s, gyro.y_rad_s, gyro.z_rad_s])
    known = np.all(np.isfinite(g), axis=1)  # a clipped (or NaN) sample is not a sample
    t_gyro = gyro.time_s[known]
    tg, g = _sorted(report_time(t_gyro), g[known])
    acc = acc_t = None
    if gyro.accel_m_s2 is not None:
        a = gyro.accel_m_s2[known]
        if np.all(np.isfinite(a)):
            acc_t, acc = tg, a[np.argsort(t_gyro, kind="stable")]

    if "DISTANCE_SENSOR" not in rec:
        raise RecordingError(f"{name}: the sensor diagnosis needs DISTANCE_SENSOR (range to the ground)")
    ds = downward_range(rec, flow.sysid)
    if ds is None or not np.any(ds.valid):
        raise RecordingError(f"{name}: no valid downward (orientation 25) DISTANCE_SENSOR readings")
    tr, rm = _sorted(report_time(ds.time_s[ds.valid]), ds.reading_m[ds.valid])
    return SensorSeries(
        name=name, t_s=report_time(t_flow), counts_x=cx, counts_y=cy, quality=np.asarray(fc.quality, dtype=float),
        read_period_s=read_period, gyro_t_s=tg, gyro_rad_s=g, accel_t_s=acc_t, accel_m_s2=acc,
        range_t_s=tr, range_m=rm, q_rad_per_count=q, profile=prof.value)
