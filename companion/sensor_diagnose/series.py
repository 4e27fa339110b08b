"""Extraction: a recording as the sensor series the diagnosis fits (flow counts in the paper's
convention, gyro, accelerometer, valid downward range), on report time."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.columnar import vehicle_sysid
from companion.config import Config
from companion.errors import RecordingError
from companion.mavlink_ids import DOWNWARD
from companion.profiles import GYRO_MESSAGES, Profile, detect_profile, flow_columns
from companion.recording import MessageTable, Recording
from companion.sensor_diagnose.settings import GRAVITY_M_S2


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


def _sensor_time_s(tab: MessageTable) -> np.ndarray:
    if "time_usec" in tab.fields:
        return np.asarray(tab["time_usec"], dtype=float) * 1e-6
    if "time_boot_ms" in tab.fields:
        return np.asarray(tab["time_boot_ms"], dtype=float) * 1e-3
    return np.asarray(tab.t_s, dtype=float)


def _sorted(t: np.ndarray, *cols: np.ndarray) -> tuple[np.ndarray, ...]:
    order = np.argsort(t, kind="stable")
    return (t[order], *(c[order] for c in cols))


def extract_series(rec: Recording, cfg: Config, profile: str | None = None) -> SensorSeries:
    """The flow (any profile, as paper-convention counts at the config's Q), gyro, accelerometer
    and valid downward range of ``rec``, on one time base. RecordingError if one is missing."""
    name = Path(rec.path).name
    prof = Profile(profile) if profile else Profile(detect_profile(rec)[0])
    q = cfg.flow_sensor.q_rad_per_count
    flow_msg = "OPTICAL_FLOW_RAD" if prof is Profile.PX4 else "OPTICAL_FLOW"
    sysid = vehicle_sysid(rec.table(flow_msg))  # the vehicle's messages only (replay's and diagnose's rule)

    def vehicle(tab: MessageTable) -> MessageTable:
        return tab if np.all(tab.sysid == sysid) else tab.from_sender(sysid=sysid)

    of = vehicle(rec.table(flow_msg))
    if len(of) < 20:
        raise RecordingError(f"{name}: only {len(of)} {flow_msg} messages: too few for a sensor diagnosis")
    fc = flow_columns(of, prof, q)
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

    gyro_name = next((g for g in GYRO_MESSAGES if g in rec), None)
    if gyro_name is None:
        raise RecordingError(f"{name}: the sensor diagnosis needs a gyro (RAW_IMU, SCALED_IMU or HIGHRES_IMU)")
    gt = vehicle(rec.tables[gyro_name])
    gscale = GYRO_MESSAGES[gyro_name]
    g = np.column_stack([np.asarray(gt[k], dtype=float) * gscale for k in ("xgyro", "ygyro", "zgyro")])
    tg, g = _sorted(report_time(_sensor_time_s(gt)), g)
    acc = acc_t = None
    if all(k in gt.fields for k in ("xacc", "yacc", "zacc")):
        ascale = 1.0 if gyro_name == "HIGHRES_IMU" else GRAVITY_M_S2 * 1e-3
        a = np.column_stack([np.asarray(gt[k], dtype=float) * ascale for k in ("xacc", "yacc", "zacc")])
        if np.all(np.isfinite(a)):
            acc_t, acc = tg, a[np.argsort(_sensor_time_s(gt), kind="stable")]

    if "DISTANCE_SENSOR" not in rec:
        raise RecordingError(f"{name}: the sensor diagnosis needs DISTANCE_SENSOR (range to the ground)")
    ds = vehicle(rec.tables["DISTANCE_SENSOR"])
    dist_cm = np.asarray(ds["current_distance"], dtype=float)
    ok = (np.asarray(ds["orientation"]) == DOWNWARD) & (dist_cm >= np.asarray(ds["min_distance"], dtype=float)) \
        & (dist_cm <= np.asarray(ds["max_distance"], dtype=float))
    if not np.any(ok):
        raise RecordingError(f"{name}: no valid downward (orientation 25) DISTANCE_SENSOR readings")
    tr, rm = _sorted(report_time(_sensor_time_s(ds)[ok]), dist_cm[ok] * 1e-2)
    return SensorSeries(
        name=name, t_s=report_time(t_flow), counts_x=cx, counts_y=cy, quality=np.asarray(fc.quality, dtype=float),
        read_period_s=read_period, gyro_t_s=tg, gyro_rad_s=g, accel_t_s=acc_t, accel_m_s2=acc,
        range_t_s=tr, range_m=rm, q_rad_per_count=q, profile=prof.value)
