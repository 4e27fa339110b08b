"""Sensor-only diagnosis: the paper's flow-sensor model against a recording with no commands.

For recordings of the flow sensor, gyro and rangefinder alone (carried by hand, on a rail, on a
desk), there is no commanded attitude and no flown plant to compare with. What can be compared
is the flow-sensor model itself (eq. 9-14), driven by the recorded gyro and range and by an
estimate of the motion:

    counts_k = (1 / (s Q)) * integral over the reading's window of (-omega - V / A) dt   (x axis:
    omega = omega_y; y axis: +omega_x), window = [t_k - d - T_read, t_k - d]

with the paper's Q (``configs/paper.toml``), and the effects the paper leaves out: the scale
``s`` (true rad per count = s Q), the delay ``d`` of the flow behind the gyro, a gyro bias, and a
turn of the sensor's axes about z. Three parts of a recording each constrain some of them:

* Timing of the log itself (``analyse_timing``, ``analyse_range``): the flow sensor is read on
  a fixed grid (``T_read``); rows that sample faster repeat readings, rows that sample slower
  lose them. These are counted and located as named findings.
* The rotation band (``RotationBandFit``): between ``band_low_hz`` and ``band_high_hz`` a
  hand-held recording carries tremor and tilting whose flow the gyro predicts. Counts and model
  are band-passed alike; the in-band translation is estimated from the accelerometer (specific
  force minus gravity through the gyro-integrated tilt) and enters with a free gain, as a
  nuisance. This fits the delay, the rotation gain (``1/s`` from rotation alone), the sign of the
  rotation term and the axis turn, with block-bootstrap uncertainty and blocked k-fold held-out
  residuals.
* Displacement (``displacement_parts``, ``find_legs``, ``LegScaleFit``), as the paper's Fig. 6:
  the running sum of rotation-compensated flow times range, segmented into legs and compared
  with the documented leg length (``DOCUMENTED_MOTIONS``). This is the scale constraint; its
  uncertainty carries the hand-carrying tolerance of the legs and the range calibration.
* Still segments (``fit_gyro_bias``): with no motion the flow sees only true rotation, so the
  gyro's mean minus the flow's rotation rate is the bias.

Each finding says which constraint its numbers come from (``evidence.constraint``). A parameter
the data cannot pin down is reported as NaN (null in JSON) with the reason in its explanation.

Times in the report are seconds from the first record of the recording.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal

from companion.advice import actions, recorded_parameters
from companion.columnar import vehicle_sysid
from companion.config import Config, load_config
from companion.errors import RecordingError
from companion.importers.common import ReadGrid, find_read_grid
from companion.mavlink_ids import DOWNWARD
from companion.profiles import GYRO_MESSAGES, Profile, detect_profile, flow_columns
from companion.recording import MessageTable, Recording, load_recording, recording_name, recording_stem
from companion.report import Finding, Fit, Report, Unexplained, Window
from companion.report_html import write_html_report

GRAVITY_M_S2 = 9.80665
#: quantization noise of one reading, counts RMS (uniform error of +-0.5 count)
QUANT_RMS_COUNTS = 1.0 / math.sqrt(12.0)


@dataclass(frozen=True)
class SensorDiagnosisSettings:
    """Analysis settings (units in the names). The defaults are the ones docs/stampfly.md uses."""

    band_low_hz: float = 0.7
    band_high_hz: float = 12.0
    delay_min_s: float = -0.02
    delay_max_s: float = 0.06
    delay_step_s: float = 0.001
    n_folds: int = 5
    n_bootstrap: int = 200
    bootstrap_block_s: float = 1.0
    #: PMW3901 working range starts at 80 mm (paper Table I): flow below it is not used for motion
    flow_min_range_m: float = 0.08
    still_window_s: float = 0.5
    still_gyro_std_rad_s: float = 0.01
    #: still: windowed mean flow below this (counts per reading; 0.3 is about 1 cm/s at 0.2 m)
    still_flow_counts: float = 0.3
    still_min_s: float = 1.0
    #: hand-carried legs: 1-sigma tolerance of each leg's true length, relative
    leg_tolerance_rel: float = 0.10
    #: range (ToF) calibration, 1-sigma relative: a common factor on every displacement
    range_scale_rel: float = 0.03
    #: a parameter whose 1-sigma relative uncertainty exceeds this is reported as not identifiable
    max_rel_uncertainty: float = 0.15
    #: held-out improvement a finding must earn to be significant
    min_improvement_pct: float = 5.0
    #: a range value held longer than this (and 3 median update intervals) is located
    range_hold_limit_s: float = 0.15


@dataclass(frozen=True)
class DocumentedMotion:
    """What a recording's maker says was done: straight legs of ``leg_m`` in the body
    directions of ``pattern`` (repeated when ``cyclic``), yaw held."""

    leg_m: float
    pattern: tuple[str, ...]
    cyclic: bool
    documented: bool
    source: str


#: Documented motions of known recordings, by file name, also gzip-compressed (data/real/stampfly/README.md).
DOCUMENTED_MOTIONS: dict[str, DocumentedMotion] = {
    "flow_test_x_axis_01.csv": DocumentedMotion(
        0.20, ("+x", "-x"), False, True,
        "maker's plan: single-axis X test, forward 20 cm, pause, back 20 cm"),
    "flow_test_square_01_final.csv": DocumentedMotion(
        0.20, ("+y", "-x", "-y", "+x"), True, True,
        "maker's plan: clockwise square, 20 cm sides, yaw held, from the front-left corner"),
    "square01_13s.csv": DocumentedMotion(
        0.20, ("+y", "-x", "-y", "+x"), True, False,
        "undocumented: one clockwise loop in the data; 20 cm sides assumed from the plan"),
    "square_30cm.csv": DocumentedMotion(
        0.20, ("+y", "-x", "-y", "+x"), True, False,
        "undocumented: about three clockwise loops; 20 cm sides assumed (maker's notes: 20 cm square at 30 cm)"),
    "square_30cm_air.csv": DocumentedMotion(
        0.20, ("+y", "-x", "-y", "+x"), True, False,
        "undocumented: about three clockwise loops; 20 cm sides assumed (maker's notes: 20 cm square at 30 cm)"),
}


# ---------------------------------------------------------------------------------------------
# The recording as sensor series


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


# ---------------------------------------------------------------------------------------------
# Timing of the log


@dataclass
class TimingAnalysis:
    grid: ReadGrid
    new_reading: np.ndarray  # (n,) bool: the row carries a reading no earlier row carried
    missing_per_row: np.ndarray  # (n,) readings lost just before each row (expected value)
    gaps: list[tuple[float, float, float]]  # (start_s, end_s, readings lost) for steps > 2.5 reads
    n_same_timestamp: int
    identical_consecutive: int  # rows whose (counts, quality) equal the previous row's

    @property
    def n_rows(self) -> int:
        return len(self.new_reading)

    @property
    def n_repeated(self) -> int:
        return int(np.sum(~self.new_reading))

    @property
    def n_missing(self) -> float:
        return float(np.sum(self.missing_per_row))

    @property
    def expected_readings(self) -> float:
        return float(np.sum(self.new_reading)) + self.n_missing


def analyse_timing(s: SensorSeries) -> TimingAnalysis:
    """Repeated and missing flow readings, gaps and repeated timestamps."""
    t = s.t_s
    period = s.read_period_s
    vals = np.column_stack([s.counts_x, s.counts_y, s.quality])
    grid = find_read_grid(t, vals, period)
    n = len(t)
    steps = np.diff(t)
    new = np.ones(n, dtype=bool)
    missing = np.zeros(n)
    if grid.slot is not None:
        jump = np.diff(grid.slot)
        new[1:] = jump != 0
        missing[1:] = np.maximum(jump - 1, 0)
    else:
        missing[1:] = np.maximum(steps / period - 1.0, 0.0)
    gaps = [(float(t[k]), float(t[k + 1]), float(missing[k + 1])) for k in np.flatnonzero(steps > 2.5 * period)]
    same = np.zeros(n, dtype=bool)
    same[1:] = np.all(vals[1:] == vals[:-1], axis=1)
    return TimingAnalysis(grid, new, missing, gaps, int(np.sum(steps == 0)), int(np.sum(same)))


def merge_windows(times: np.ndarray, join_s: float, pad_s: float = 0.0) -> list[tuple[float, float]]:
    """Sorted event times -> windows, joining events closer than ``join_s``."""
    if len(times) == 0:
        return []
    t = np.sort(np.asarray(times, dtype=float))
    breaks = np.flatnonzero(np.diff(t) > join_s)
    starts = np.r_[t[0], t[breaks + 1]]
    ends = np.r_[t[breaks], t[-1]]
    return [(float(a - pad_s), float(b + pad_s)) for a, b in zip(starts, ends, strict=True)]


def timing_findings(s: SensorSeries, tm: TimingAnalysis) -> list[Finding]:
    """``missing_flow_readings`` and ``repeated_flow_readings``: counted, not fitted (no held-out fit)."""
    t = s.t_s
    period_ms = 1e3 * s.read_period_s
    steps = np.diff(t)
    med_ms = 1e3 * float(np.median(steps)) if len(steps) else float("nan")
    expected = tm.expected_readings
    frac = tm.n_missing / expected if expected > 0 else float("nan")
    in_gaps = sum(g[2] for g in tm.gaps)
    spread = tm.n_missing - in_gaps
    where = [Window("OPTICAL_FLOW", a, b) for a, b, _ in tm.gaps]
    if spread / max(expected, 1.0) > 0.01:
        where.insert(0, Window("OPTICAL_FLOW", float(t[0]), float(t[-1])))
    longest = max((b - a for a, b, _ in tm.gaps), default=float(steps.max()) if len(steps) else 0.0)
    if spread / max(expected, 1.0) > 0.01:
        why = (f"The log took a row every {med_ms:.1f} ms (median) while the sensor is read every {period_ms:g} ms, "
               f"so about one reading in {expected / max(spread, 1e-9):.0f} never reached the log and a plain sum "
               f"of the logged counts undercounts the motion by that fraction")
    else:
        why = (f"Rows keep pace with the {period_ms:g} ms reads, so readings are lost only where the log stops "
               f"({len(tm.gaps)} gaps)")
    if tm.gaps:
        why += f"; {len(tm.gaps)} gaps of {1e3 * min(b - a for a, b, _ in tm.gaps):.0f}-" \
               f"{1e3 * max(b - a for a, b, _ in tm.gaps):.0f} ms lose {in_gaps:.0f} readings outright"
    why += "."
    missing = Finding(
        effect="missing_flow_readings", significant=bool(frac > 0.01),
        parameters={"count": round(tm.n_missing, 1), "fraction": frac, "in_gaps": in_gaps,
                    "longest_gap_s": longest},
        uncertainty={}, explanation=why, where=where, fit=None,
        evidence={"constraint": "log timing", "units": {"count": "readings", "in_gaps": "readings"},
                  "read_period_ms": period_ms, "median_row_step_ms": med_ms,
                  "rows": tm.n_rows, "expected_readings": expected, "read_grid": tm.grid.method,
                  "gaps": [{"start_s": a, "end_s": b, "readings_lost": m} for a, b, m in tm.gaps],
                  "handling": "the displacement sums weight each reading by the time its row covers "
                              "(up to two read periods), so readings lost between rows are bridged; "
                              "gaps are not"})

    nonzero = (s.counts_x != 0) | (s.counts_y != 0)
    rep = ~tm.new_reading
    rep_nz = float(np.sum(rep & nonzero) / max(1, np.sum(nonzero)))
    if tm.grid.slot is not None:
        where_r = [Window("OPTICAL_FLOW", a, b) for a, b in merge_windows(t[rep], 0.5)]
        why_r = (f"Rows come every {med_ms:.1f} ms (median) but the sensor is read every {period_ms:g} ms, so "
                 f"{100 * tm.n_repeated / tm.n_rows:.0f} % of rows repeat the reading of the row before "
                 f"({100 * rep_nz:.0f} % of the rows with motion); summing them would count the same motion "
                 f"several times.")
    else:
        where_r = []
        why_r = (f"No row is closer than one {period_ms:g} ms read to the one before, so no row can repeat a "
                 f"reading; the {tm.identical_consecutive} rows equal to the previous one "
                 f"({100 * tm.identical_consecutive / max(tm.n_rows, 1):.0f} %) are slow motion or rest, not repeats.")
    repeated = Finding(
        effect="repeated_flow_readings", significant=bool(tm.n_repeated > 0),
        parameters={"count": tm.n_repeated, "fraction_of_rows": tm.n_repeated / max(tm.n_rows, 1),
                    "fraction_of_nonzero_rows": rep_nz if tm.grid.slot is not None else 0.0,
                    "repeated_timestamps": tm.n_same_timestamp},
        uncertainty={}, explanation=why_r, where=where_r, fit=None,
        evidence={"constraint": "log timing", "units": {"count": "rows", "repeated_timestamps": "rows"},
                  "read_grid": tm.grid.method,
                  "read_phase_ms": None if tm.grid.phase_s is None else 1e3 * tm.grid.phase_s,
                  "identical_consecutive_rows": tm.identical_consecutive,
                  "handling": "repeats are dropped before any fit or sum (the first row of each read slot is kept)"})
    return [missing, repeated]


def range_finding(s: SensorSeries, settings: SensorDiagnosisSettings) -> Finding:
    """``held_range``: range values carried over between sensor updates."""
    t, r = s.range_t_s, s.range_m
    new = np.ones(len(r), dtype=bool)
    new[1:] = r[1:] != r[:-1]
    tu = t[new]
    iv = np.diff(tu)
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    rate = (len(tu) - 1) / duration if duration > 0 else float("nan")
    held = 1.0 - float(np.mean(new))
    med = float(np.median(iv)) if len(iv) else float("nan")
    limit = max(settings.range_hold_limit_s, 3.0 * med) if len(iv) else float("inf")
    long_idx = np.flatnonzero(iv > limit)
    where = [Window("DISTANCE_SENSOR", float(tu[k]), float(tu[k + 1])) for k in long_idx]
    flow_dt = float(np.median(np.diff(s.t_s))) if len(s.t_s) > 1 else float("nan")
    if len(tu) < 3:
        return Finding(
            effect="held_range", significant=False,
            parameters={"update_rate_hz": float("nan"), "held_fraction": held, "median_update_s": float("nan"),
                        "longest_hold_s": float("nan"), "long_holds": 0},
            uncertainty={},
            explanation=(f"The range value changes {len(tu) - 1} times in {duration:.0f} s: a steady height gives "
                         f"no update timing to judge."),
            where=[], fit=None, evidence={"constraint": "log timing", "units": {"long_holds": "holds"},
                                          "rows": len(r)})
    return Finding(
        effect="held_range", significant=bool(held > 0.5),
        parameters={"update_rate_hz": rate, "held_fraction": held, "median_update_s": med,
                    "longest_hold_s": float(iv.max()) if len(iv) else float("nan"), "long_holds": len(long_idx)},
        uncertainty={},
        explanation=(f"The range changes {rate:.0f} times a second while rows come every {1e3 * flow_dt:.0f} ms, so "
                     f"{100 * held:.0f} % of rows carry an older range value; {len(long_idx)} holds last longer than "
                     f"{1e3 * limit:.0f} ms (a steady height also repeats a value, so holds bound the update rate "
                     f"from below)."),
        where=where, fit=None,
        evidence={"constraint": "log timing", "units": {"long_holds": "holds"}, "rows": len(r),
                  "new_values": int(np.sum(new)),
                  "handling": "range is interpolated between logged values at each flow row"})


# ---------------------------------------------------------------------------------------------
# Gyro bias from still segments


def _moving_mean(x: np.ndarray, n: int) -> np.ndarray:
    n = max(1, int(n))
    k = np.ones(n) / n
    return np.convolve(np.pad(x, (n // 2, n - 1 - n // 2), mode="edge"), k, mode="valid")


def still_rows(t: np.ndarray, gyro: np.ndarray, cx: np.ndarray, cy: np.ndarray,
               settings: SensorDiagnosisSettings) -> np.ndarray:
    """Rows inside still segments: windowed gyro std (x, y) and net flow (counts per reading,
    windowed signed mean) below the settings' thresholds for at least ``still_min_s``."""
    if len(t) < 3:
        return np.zeros(len(t), dtype=bool)
    n = int(round(settings.still_window_s / float(np.median(np.diff(t)))))
    std = np.zeros(len(t))
    for i in range(2):
        m = _moving_mean(gyro[:, i], n)
        std += np.maximum(_moving_mean(gyro[:, i] ** 2, n) - m**2, 0.0)
    # net flow (signed mean): sensor noise averages out, a slow translation does not
    net = np.abs(_moving_mean(cx, n)) + np.abs(_moving_mean(cy, n))
    ok = (np.sqrt(std) < settings.still_gyro_std_rad_s) & (net < settings.still_flow_counts)
    out = np.zeros(len(t), dtype=bool)
    for a, b in _runs(ok):
        if t[b - 1] - t[a] >= settings.still_min_s:
            out[a:b] = True
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index pairs of the True runs of ``mask``."""
    m = np.r_[False, np.asarray(mask, dtype=bool), False]
    d = np.diff(m.astype(np.int8))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True))


@dataclass
class BiasFit:
    """Gyro bias (rad/s, roll and pitch rate) from still rows, with blocked held-out residuals."""

    bias: np.ndarray  # (2,) rad/s, or NaN
    sigma: np.ndarray  # (2,)
    still_s: float
    before: float  # held-out RMS scene-angle drift (rad), bias 0
    after: float  # the same with the fitted bias
    windows: list[tuple[float, float]]
    quietest_gyro_std: float
    reason: str = ""


def fit_gyro_bias(t: np.ndarray, dt: np.ndarray, gyro: np.ndarray, cx: np.ndarray, cy: np.ndarray,
                  read_period_s: float, q_x: float, q_y: float, settings: SensorDiagnosisSettings) -> BiasFit:
    """Bias = mean over still rows of (gyro - the rotation rate the flow sees): with no
    translation, ``omega_y = -dX q / T`` and ``omega_x = +dY q / T`` (eq. 5-6, 13-14).

    ``q_x``, ``q_y``: rad per count in use (scale x Q). Held-out check: the still rows are cut
    into ``n_folds`` contiguous blocks; each block's scene-angle drift (the running sum of
    (gyro - bias - flow rotation) x row time) is predicted with the bias from the other blocks.
    """
    still = still_rows(t, gyro, cx, cy, settings)
    n = int(round(settings.still_window_s / float(np.median(np.diff(t))))) if len(t) > 2 else 1
    qstd = float("nan")
    if len(t) > n:
        std = np.sqrt(sum(np.maximum(_moving_mean(gyro[:, i] ** 2, n) - _moving_mean(gyro[:, i], n) ** 2, 0)
                          for i in range(2)))
        qstd = float(np.min(std[n:-n])) if len(std) > 2 * n else float(np.min(std))
    windows = [(float(t[a]), float(t[b - 1])) for a, b in _runs(still)]
    still_s = float(np.sum(dt[still]))
    nan2 = np.full(2, np.nan)
    if still_s < settings.still_min_s or np.sum(still) < 2 * settings.n_folds:
        return BiasFit(nan2, nan2, still_s, float("nan"), float("nan"), windows, qstd,
                       reason=(f"no still segment (gyro std below {settings.still_gyro_std_rad_s} rad/s and no net "
                               f"flow for {settings.still_min_s:g} s): the quietest {settings.still_window_s:g} s has "
                               f"gyro std {qstd:.3f} rad/s, hand motion that hides a bias of a few mrad/s"))
    # residual rate per row: measured gyro minus the rotation the flow sees
    r = np.column_stack([gyro[still, 0] - cy[still] * q_y / read_period_s,
                         gyro[still, 1] + cx[still] * q_x / read_period_s])
    w = dt[still]
    bias = np.sum(r * w[:, None], axis=0) / np.sum(w)
    # blocks of about 1 s for the standard error
    ts = t[still]
    blk = np.floor((ts - ts[0]) / 1.0).astype(int)
    means = np.array([np.sum(r[blk == b] * w[blk == b, None], axis=0) / np.sum(w[blk == b])
                      for b in np.unique(blk)])
    sigma = np.std(means, axis=0, ddof=1) / math.sqrt(len(means)) if len(means) >= 3 else np.full(2, np.nan)
    folds = np.array_split(np.arange(len(ts)), settings.n_folds)
    err0, err1 = [], []
    for f in folds:
        train = np.setdiff1d(np.arange(len(ts)), f)
        b = np.sum(r[train] * w[train, None], axis=0) / np.sum(w[train])
        seg = np.r_[0, np.flatnonzero(np.diff(ts[f]) > 2.5 * np.median(np.diff(ts))) + 1, len(f)]
        for a, e in zip(seg[:-1], seg[1:], strict=True):
            idx = f[a:e]
            err0.append(np.cumsum(r[idx] * w[idx, None], axis=0))
            err1.append(np.cumsum((r[idx] - b) * w[idx, None], axis=0))
    before = float(np.sqrt(np.mean(np.concatenate(err0) ** 2)))
    after = float(np.sqrt(np.mean(np.concatenate(err1) ** 2)))
    return BiasFit(bias, sigma, still_s, before, after, windows, qstd)


# ---------------------------------------------------------------------------------------------
# The rotation band


def window_integral(t_query: np.ndarray, t_sig: np.ndarray, sig: np.ndarray, delay_s: float,
                    width_s: np.ndarray | float) -> np.ndarray:
    """Integral of the piecewise-linear ``sig(t)`` over ``[t - delay - width, t - delay]`` for each
    query time (trapezoid on the signal's own samples, exact for piecewise-linear signals)."""
    c = np.concatenate([[0.0], np.cumsum(0.5 * (sig[1:] + sig[:-1]) * np.diff(t_sig))])
    hi = t_query - delay_s
    return _cum_at(hi, t_sig, sig, c) - _cum_at(hi - width_s, t_sig, sig, c)


def window_integrals(t_query: np.ndarray, t_sig: np.ndarray, sig: np.ndarray, delays_s: np.ndarray,
                     width_s: float) -> np.ndarray:
    """``window_integral`` for many delays at once: shape (len(delays_s), len(t_query))."""
    c = np.concatenate([[0.0], np.cumsum(0.5 * (sig[1:] + sig[:-1]) * np.diff(t_sig))])
    hi = t_query[None, :] - np.asarray(delays_s, dtype=float)[:, None]
    return _cum_at(hi, t_sig, sig, c) - _cum_at(hi - width_s, t_sig, sig, c)


def _cum_at(tq: np.ndarray, t: np.ndarray, s: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The cumulative integral of the piecewise-linear signal at ``tq`` (held flat outside)."""
    tq = np.clip(tq, t[0], t[-1])
    i = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)
    h = tq - t[i]
    dt = t[i + 1] - t[i]
    slope = np.where(dt > 0, (s[i + 1] - s[i]) / np.where(dt > 0, dt, 1.0), 0.0)
    return c[i] + s[i] * h + 0.5 * slope * h**2


def inband_velocity(series: SensorSeries, settings: SensorDiagnosisSettings,
                    fs_hz: float = 500.0) -> tuple[np.ndarray, np.ndarray] | None:
    """In-band horizontal velocity over range, ``V_x / A`` and ``V_y / A`` (1/s), on a uniform
    grid, from the accelerometer: ``a_x = f_x - g theta``, ``a_y = f_y + g phi`` with the tilt
    from the integrated gyro, integrated and band-passed. None without an accelerometer."""
    if series.accel_m_s2 is None or series.accel_t_s is None:
        return None
    t0, t1 = float(series.gyro_t_s[0]), float(series.gyro_t_s[-1])
    if t1 - t0 < 3.0 / settings.band_low_hz:
        return None
    tg = np.arange(t0, t1, 1.0 / fs_hz)
    sos = signal.butter(2, [settings.band_low_hz, settings.band_high_hz], btype="band", fs=fs_hz, output="sos")
    w = series.gyro_at(tg)
    f = np.column_stack([np.interp(tg, series.accel_t_s, series.accel_m_s2[:, i]) for i in range(2)])
    tilt_pitch = np.cumsum(w[:, 1]) / fs_hz
    tilt_roll = np.cumsum(w[:, 0]) / fs_hz
    ax = signal.sosfiltfilt(sos, f[:, 0]) - GRAVITY_M_S2 * signal.sosfiltfilt(sos, tilt_pitch)
    ay = signal.sosfiltfilt(sos, f[:, 1]) + GRAVITY_M_S2 * signal.sosfiltfilt(sos, tilt_roll)
    vx = signal.sosfiltfilt(sos, np.cumsum(ax) / fs_hz)
    vy = signal.sosfiltfilt(sos, np.cumsum(ay) / fs_hz)
    a = np.maximum(series.range_at(tg), settings.flow_min_range_m)
    return tg, np.column_stack([vx / a, vy / a])


@dataclass
class RotationBandFit:
    """Band-limited fit of the flow counts to the gyro's rotation (and the accelerometer's
    in-band translation), per axis: ``y = g_rot R(d) + g_tr Tr(d)``, both sides band-passed.

    ``R`` = predicted rotation counts at the nominal Q (x: ``-int omega_y / Q``, y:
    ``+int omega_x / Q``), ``Tr`` = predicted translation counts (``-int V / A / Q``). With the
    paper's model and the true scale s, ``g_rot = 1/s``. Fitted values end in ``_``.
    """

    settings: SensorDiagnosisSettings
    rng: np.random.Generator
    delays_: np.ndarray = field(default_factory=lambda: np.zeros(0))
    delay_: float = float("nan")
    delay_sigma_: float = float("nan")
    gain_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))  # (2,) g_rot x, y
    gain_sigma_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    tr_gain_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    yaw_: float = float("nan")
    yaw_sigma_: float = float("nan")
    r2_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    rotation_rms_counts_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    gyro_band_rms_rad_s_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    expected_rel_sigma_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    reason_: str = ""
    subband_hz_: tuple[tuple[float, float], ...] = ()
    subband_gain_: np.ndarray = field(default_factory=lambda: np.full((2, 2), np.nan))  # (band, axis)
    subband_gain_sigma_: np.ndarray = field(default_factory=lambda: np.full((2, 2), np.nan))
    heldout_: dict[str, float] = field(default_factory=dict)
    baseline_rms_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    n_rows_: int = 0
    has_translation_: bool = False
    # kept for plots and residual windows
    t_: np.ndarray = field(default_factory=lambda: np.zeros(0))
    y_: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    pred_nominal_: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    pred_fitted_: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    use_: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def fit(self, series: SensorSeries, rows: np.ndarray, bias: np.ndarray) -> RotationBandFit:
        """``rows``: flow rows to use (new readings, in order); ``bias``: (2,) rad/s (0 if unknown)."""
        st = self.settings
        t = series.t_s[rows]
        y = np.column_stack([series.counts_x[rows], series.counts_y[rows]])
        if len(t) < 50 or t[-1] - t[0] < 3.0 / st.band_low_hz:
            self.reason_ = f"too short for the {st.band_low_hz:g} Hz band edge ({len(t)} readings)"
            return self
        q = series.q_rad_per_count
        T = series.read_period_s
        fs_rows = 1.0 / float(np.median(np.diff(t)))
        hi = min(st.band_high_hz, 0.45 * fs_rows)
        sos = signal.butter(2, [st.band_low_hz, hi], btype="band", fs=fs_rows, output="sos")
        # rotation content: in-band gyro and the counts it predicts per reading
        w_rows = series.gyro_at(t)[:, :2] - np.where(np.isfinite(bias), bias, 0.0)
        w_band = signal.sosfiltfilt(sos, w_rows, axis=0)
        self.gyro_band_rms_rad_s_ = np.sqrt(np.mean(w_band**2, axis=0))
        self.rotation_rms_counts_ = self.gyro_band_rms_rad_s_[::-1] * T / q  # x counts <- pitch, y <- roll
        n_eff = 2.0 * (hi - st.band_low_hz) * float(t[-1] - t[0])
        with np.errstate(divide="ignore"):
            self.expected_rel_sigma_ = QUANT_RMS_COUNTS / (self.rotation_rms_counts_ * math.sqrt(n_eff))
        a_med = float(np.median(series.range_at(t)))
        rng_ok = series.range_at(t) >= st.flow_min_range_m
        if not np.any(rng_ok):
            self.reason_ = (f"the range (median {100 * a_med:.1f} cm) is below the flow sensor's "
                            f"{100 * st.flow_min_range_m:.0f} cm working range throughout")
            return self
        edge = int(round(1.0 * fs_rows / st.band_low_hz))  # filter start-up at the ends
        use = rng_ok.copy()
        use[:edge] = False
        use[-edge:] = False
        # rows near excluded stretches carry filter transients from them
        bad = ~rng_ok
        if np.any(bad):
            near = np.convolve(bad.astype(float), np.ones(2 * edge + 1), mode="same") > 0
            use &= ~near
        if np.sum(use) < 50:
            self.reason_ = (f"only {int(np.sum(use))} readings with the range inside the flow sensor's working range, "
                            "away from the band filter's start-up")
            return self
        self.n_rows_ = int(np.sum(use))
        yb = signal.sosfiltfilt(sos, y, axis=0)
        wx = series.gyro_rad_s[:, 0] - (bias[0] if np.isfinite(bias[0]) else 0.0)
        wy = series.gyro_rad_s[:, 1] - (bias[1] if np.isfinite(bias[1]) else 0.0)
        vel = inband_velocity(series, st)
        self.has_translation_ = vel is not None
        delays = np.arange(st.delay_min_s, st.delay_max_s + 1e-12, st.delay_step_s)
        self.delays_ = delays
        R = np.zeros((len(delays), len(t), 2))
        Tr = np.zeros((len(delays), len(t), 2))
        R[:, :, 0] = -window_integrals(t, series.gyro_t_s, wy, delays, T) / q
        R[:, :, 1] = window_integrals(t, series.gyro_t_s, wx, delays, T) / q
        R = signal.sosfiltfilt(sos, R, axis=1)
        if vel is not None:
            tg, v = vel
            Tr[:, :, 0] = -window_integrals(t, tg, v[:, 0], delays, T) / q
            Tr[:, :, 1] = -window_integrals(t, tg, v[:, 1], delays, T) / q
            Tr = signal.sosfiltfilt(sos, Tr, axis=1)
        i0 = int(np.argmin(np.abs(delays)))
        # blocks for the bootstrap and folds for the held-out check
        tu = t[use]
        Yu, Ru, Tu = yb[use], R[:, use], Tr[:, use]
        blocks = np.floor((tu - tu[0]) / st.bootstrap_block_s).astype(int)
        nb = int(blocks.max()) + 1
        S = _block_sums(Yu, Ru, Tu, blocks, nb, self.has_translation_)  # per block cross-products
        tot = {k: v.sum(axis=-1) for k, v in S.items()}
        sse, coef = _sse_all(tot, self.has_translation_)
        k = int(np.argmin(sse.sum(axis=-1)))
        self.delay_ = float(delays[k])
        self.gain_ = coef[k, :, 0].copy()
        self.tr_gain_ = coef[k, :, 1].copy() if self.has_translation_ else np.full(2, np.nan)
        self.r2_ = 1.0 - sse[k] / tot["yy"][k]
        # moving-block bootstrap of delay and gains
        W = self.rng.multinomial(nb, np.full(nb, 1.0 / nb), size=st.n_bootstrap).astype(float)  # (B, nb)
        boot = {kk: np.einsum("bn,...n->b...", W, v) for kk, v in S.items()}
        bsse, bcoef = _sse_all(boot, self.has_translation_)
        kb = np.argmin(bsse.sum(axis=-1), axis=1)
        self.delay_sigma_ = float(np.std(delays[kb]))
        gb = bcoef[np.arange(st.n_bootstrap), kb, :, 0]
        self.gain_sigma_ = np.std(gb, axis=0)
        # yaw: shared cross term u (X gets +u R_y, Y gets -u R_x), at the fitted delay
        yaw, ub = _yaw_fit(Yu, Ru[k], Tu[k], blocks, nb, W, self.has_translation_)
        g_mean = float(np.mean(self.gain_))
        self.yaw_ = float(yaw / g_mean) if g_mean > 0 else float("nan")
        self.yaw_sigma_ = float(np.std(ub) / abs(g_mean)) if g_mean != 0 else float("nan")
        # held-out: contiguous folds; each model refitted on the other folds
        self.heldout_ = _heldout(Yu, Ru, Tu, tu, st.n_folds, i0, self.has_translation_)
        # nominal model: gains 1, delay 0 (translation included when estimated)
        nominal = Ru[i0] + (Tu[i0] if self.has_translation_ else 0.0)
        self.baseline_rms_ = np.sqrt(np.mean((Yu - nominal) ** 2, axis=0))
        fitted = Ru[k] * self.gain_ + (Tu[k] * self.tr_gain_ if self.has_translation_ else 0.0)
        self.t_, self.y_, self.use_ = t, yb, use
        self.pred_nominal_ = np.full_like(yb, np.nan)
        self.pred_fitted_ = np.full_like(yb, np.nan)
        self.pred_nominal_[use] = nominal
        self.pred_fitted_[use] = fitted
        # model check: one rotation gain across the band? (lower and upper half, geometric split)
        split = math.sqrt(st.band_low_hz * hi)
        self.subband_hz_ = ((st.band_low_hz, split), (split, hi))
        raw_r = np.stack([-window_integral(t, series.gyro_t_s, wy, self.delay_, T) / q,
                          window_integral(t, series.gyro_t_s, wx, self.delay_, T) / q], axis=1)
        raw_t = None
        if vel is not None:
            tg, v = vel
            raw_t = np.stack([-window_integral(t, tg, v[:, a], self.delay_, T) / q for a in range(2)], axis=1)
        for j, band_j in enumerate(self.subband_hz_):
            sos_j = signal.butter(2, list(band_j), btype="band", fs=fs_rows, output="sos")
            yj = signal.sosfiltfilt(sos_j, y, axis=0)[use]
            rj = signal.sosfiltfilt(sos_j, raw_r, axis=0)[use][None]
            tj = signal.sosfiltfilt(sos_j, raw_t, axis=0)[use][None] if raw_t is not None else np.zeros_like(rj)
            Sj = _block_sums(yj, rj, tj, blocks, nb, self.has_translation_)
            _, cj = _sse_all({kk: v.sum(axis=-1) for kk, v in Sj.items()}, self.has_translation_)
            _, cb = _sse_all({kk: np.einsum("bn,...n->b...", W, v) for kk, v in Sj.items()}, self.has_translation_)
            self.subband_gain_[j] = cj[0, :, 0]
            self.subband_gain_sigma_[j] = np.std(cb[:, 0, :, 0], axis=0)
        return self

    def rotation_scale_identifiable(self) -> np.ndarray:
        """Per axis: the rotation-only scale is precise (1-sigma below ``max_rel_uncertainty``)
        and the same in both halves of the band (within 2 sigma)."""
        if not self.fitted:
            return np.zeros(2, dtype=bool)
        sr, ssr = self.scale_from_rotation()
        with np.errstate(divide="ignore", invalid="ignore"):
            s_sub = 1.0 / self.subband_gain_
            ss_sub = self.subband_gain_sigma_ / self.subband_gain_**2
            same = np.abs(s_sub[0] - s_sub[1]) <= 2.0 * np.hypot(ss_sub[0], ss_sub[1])
            precise = (sr > 0) & (ssr / sr <= self.settings.max_rel_uncertainty)
        return np.asarray(precise & same, dtype=bool)

    @property
    def fitted(self) -> bool:
        return self.n_rows_ > 0 and np.isfinite(self.delay_)

    def scale_from_rotation(self) -> tuple[np.ndarray, np.ndarray]:
        """Scale relative to Q from the rotation gain alone (1/g) and its 1-sigma."""
        g, sg = self.gain_, self.gain_sigma_
        with np.errstate(divide="ignore", invalid="ignore"):
            return 1.0 / g, sg / g**2


def _block_sums(Y: np.ndarray, R: np.ndarray, Tr: np.ndarray, blocks: np.ndarray, nb: int,
                with_tr: bool) -> dict[str, np.ndarray]:
    """Per-block cross-products, shape (n_delay, 2 axes, nb)."""
    def bsum(x: np.ndarray) -> np.ndarray:  # x: (nd, n, 2) -> (nd, 2, nb)
        out = np.zeros(x.shape[:1] + (2, nb))
        for a in range(2):
            for j in range(x.shape[0]):
                out[j, a] = np.bincount(blocks, weights=x[j, :, a], minlength=nb)
        return out
    nd = R.shape[0]
    Yr = np.broadcast_to(Y, (nd,) + Y.shape)
    S = {"yy": bsum(Yr * Yr), "rr": bsum(R * R), "ry": bsum(R * Yr)}
    if with_tr:
        S.update({"tt": bsum(Tr * Tr), "rt": bsum(R * Tr), "ty": bsum(Tr * Yr)})
    return S


def _sse_all(S: dict[str, np.ndarray], with_tr: bool) -> tuple[np.ndarray, np.ndarray]:
    """Least squares per (..., delay, axis) from summed cross-products: SSE and coefficients
    (..., 2) = (g_rot, g_tr)."""
    rr, ry, yy = S["rr"], S["ry"], S["yy"]
    if not with_tr:
        g = np.where(rr > 0, ry / np.where(rr > 0, rr, 1.0), 0.0)
        return yy - g * ry, np.stack([g, np.zeros_like(g)], axis=-1)
    tt, rt, ty = S["tt"], S["rt"], S["ty"]
    det = rr * tt - rt**2
    ok = det > 1e-12 * np.maximum(rr * tt, 1e-300)
    det = np.where(ok, det, 1.0)
    g1 = np.where(ok, (tt * ry - rt * ty) / det, ry / np.where(rr > 0, rr, 1.0))
    g2 = np.where(ok, (rr * ty - rt * ry) / det, 0.0)
    return yy - g1 * ry - g2 * ty, np.stack([g1, g2], axis=-1)


def _yaw_fit(Y: np.ndarray, R: np.ndarray, Tr: np.ndarray, blocks: np.ndarray, nb: int, W: np.ndarray,
             with_tr: bool) -> tuple[float, np.ndarray]:
    """Joint least squares over both axes with a shared antisymmetric cross term ``u``:
    ``X = g_x R_x + u R_y (+ n_x Tr_x)``, ``Y = g_y R_y - u R_x (+ n_y Tr_y)``. Returns u and
    its bootstrap replicates (``W``: block weights)."""
    n = len(Y)
    cols = [np.r_[R[:, 0], np.zeros(n)], np.r_[np.zeros(n), R[:, 1]], np.r_[R[:, 1], -R[:, 0]]]
    if with_tr:
        cols += [np.r_[Tr[:, 0], np.zeros(n)], np.r_[np.zeros(n), Tr[:, 1]]]
    A = np.column_stack(cols)
    b = np.r_[Y[:, 0], Y[:, 1]]
    bl = np.r_[blocks, blocks]
    AtA = np.zeros((nb, A.shape[1], A.shape[1]))
    Atb = np.zeros((nb, A.shape[1]))
    for j in range(nb):
        m = bl == j
        AtA[j] = A[m].T @ A[m]
        Atb[j] = A[m].T @ b[m]
    u = float(np.linalg.lstsq(AtA.sum(0), Atb.sum(0), rcond=None)[0][2])
    M = np.einsum("bn,nij->bij", W, AtA)
    v = np.einsum("bn,ni->bi", W, Atb)
    ub = np.array([np.linalg.lstsq(M[i], v[i], rcond=None)[0][2] for i in range(len(W))])
    return u, ub


def _heldout(Y: np.ndarray, R: np.ndarray, Tr: np.ndarray, t: np.ndarray, n_folds: int, i0: int,
             with_tr: bool) -> dict[str, float]:
    """Blocked k-fold held-out RMS (counts, both axes pooled) of: the nominal model (gains 1,
    no delay), gains fitted without delay, gains and delay fitted, and with the yaw term."""
    folds = np.array_split(np.arange(len(t)), n_folds)
    err: dict[str, list[np.ndarray]] = {"nominal": [], "no_delay": [], "delay": [], "yaw": []}
    Yb = np.broadcast_to(Y, R.shape)
    P = {"rr": R * R, "ry": R * Yb, "yy": Yb * Yb}
    if with_tr:
        P.update({"tt": Tr * Tr, "rt": R * Tr, "ty": Tr * Yb})
    total = {key: v.sum(axis=1) for key, v in P.items()}
    for f in folds:
        train = np.ones(len(t), dtype=bool)
        train[f] = False
        S = {key: total[key] - P[key][:, f].sum(axis=1) for key in P}
        sse, coef = _sse_all(S, with_tr)
        k = int(np.argmin(sse.sum(axis=-1)))

        nominal = R[i0][f] + (Tr[i0][f] if with_tr else 0.0)
        err["nominal"].append(Y[f] - nominal)
        for key, j in (("no_delay", i0), ("delay", k)):
            pred = R[j][f] * coef[j, :, 0] + (Tr[j][f] * coef[j, :, 1] if with_tr else 0.0)
            err[key].append(Y[f] - pred)
        # yaw model at the training delay
        n = int(np.sum(train))
        Rt, Tt, Yt = R[k][train], Tr[k][train], Y[train]
        cols = [np.r_[Rt[:, 0], np.zeros(n)], np.r_[np.zeros(n), Rt[:, 1]], np.r_[Rt[:, 1], -Rt[:, 0]]]
        if with_tr:
            cols += [np.r_[Tt[:, 0], np.zeros(n)], np.r_[np.zeros(n), Tt[:, 1]]]
        c = np.linalg.lstsq(np.column_stack(cols), np.r_[Yt[:, 0], Yt[:, 1]], rcond=None)[0]
        Rf, Tf = R[k][f], Tr[k][f]
        px = c[0] * Rf[:, 0] + c[2] * Rf[:, 1] + (c[3] * Tf[:, 0] if with_tr else 0.0)
        py = c[1] * Rf[:, 1] - c[2] * Rf[:, 0] + (c[4] * Tf[:, 1] if with_tr else 0.0)
        err["yaw"].append(Y[f] - np.column_stack([px, py]))
    return {key: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for key, v in err.items()}


# ---------------------------------------------------------------------------------------------
# Displacement (Fig. 6) and legs


@dataclass
class Displacement:
    """Running sums (m), world frame (x = north at the start heading, y = east), split into the
    parts linear in the scale: ``path(sx, sy) = sx * flow_x + sy * flow_y + rotation``.

    ``flow_x``: the body-x flow counts' contribution at the nominal Q, rotated by the yaw
    angle; ``rotation``: the gyro's rotation compensation; shapes (n, 2)."""

    t_s: np.ndarray
    flow_x: np.ndarray
    flow_y: np.ndarray
    rotation: np.ndarray
    valid: np.ndarray  # rows whose range is inside the flow sensor's working range

    def path(self, sx: float, sy: float) -> np.ndarray:
        return sx * self.flow_x + sy * self.flow_y + self.rotation


def displacement_parts(series: SensorSeries, rows: np.ndarray, bias: np.ndarray, bias_z: float,
                       delay_s: float, settings: SensorDiagnosisSettings) -> Displacement:
    """Eq. 15 integrated: each reading's rate ``-dX Q / T`` (and the gyro over the same window)
    times the range, held over the time its row covers (the step from the previous reading, at
    most two read periods), so readings lost between rows are bridged and gaps are not."""
    t = series.t_s[rows]
    T = series.read_period_s
    cover = np.r_[T, np.minimum(np.diff(t), 2.0 * T)]
    a = series.range_at(t)
    valid = a >= settings.flow_min_range_m
    b = np.where(np.isfinite(bias), bias, 0.0)
    wint_x = window_integral(t, series.gyro_t_s, series.gyro_rad_s[:, 0] - b[0], delay_s, cover)
    wint_y = window_integral(t, series.gyro_t_s, series.gyro_rad_s[:, 1] - b[1], delay_s, cover)
    q = series.q_rad_per_count
    # rows below the working range are left out of the sums, unless no row is inside it (a
    # recording resting on a desk: its sums then show the sensor's and the gyro's drift)
    keep = valid if np.mean(valid) > 0.1 else np.ones_like(valid)
    fx = np.where(keep, -series.counts_x[rows] * q * a * cover / T, 0.0)
    fy = np.where(keep, -series.counts_y[rows] * q * a * cover / T, 0.0)
    rx = np.where(keep, -wint_y * a, 0.0)
    ry = np.where(keep, wint_x * a, 0.0)
    bz = bias_z if np.isfinite(bias_z) else 0.0
    yaw = np.cumsum(window_integral(t, series.gyro_t_s, series.gyro_rad_s[:, 2] - bz, 0.0, cover))
    c, s = np.cos(yaw), np.sin(yaw)

    def world(px: np.ndarray, py: np.ndarray) -> np.ndarray:
        return np.column_stack([np.cumsum(c * px - s * py), np.cumsum(s * px + c * py)])

    z = np.zeros_like(fx)
    return Displacement(t, world(fx, z), world(z, fy), world(rx, ry), valid)


AXIS_NAMES = ("+x", "-x", "+y", "-y")
#: at a corner without a pause, a leg's sideways displacement is taken between its first and last this many s
CROSS_END_S = 0.1


@dataclass
class Leg:
    """One straight leg: ``axis`` 0 (x) or 1 (y), ``direction`` +1/-1, the reference windows
    before and after it, and its along-axis length split into the parts linear in the scale."""

    start_s: float
    end_s: float
    axis: int
    direction: int
    before: tuple[float, float]
    after: tuple[float, float]
    d_flow_x: float  # m at the nominal Q
    d_flow_y: float
    d_rotation: float
    #: sideways displacement across the leg at the nominal Q: between the pauses around it, or
    #: between its own first and last 0.1 s where it turns a corner without a pause
    cross_m: float

    @property
    def name(self) -> str:
        return ("+" if self.direction > 0 else "-") + "xy"[self.axis]

    def length(self, sx: float, sy: float) -> float:
        """Signed along-axis length times the direction: positive for a leg that went its way."""
        return self.direction * (sx * self.d_flow_x + sy * self.d_flow_y + self.d_rotation)


def find_legs(disp: Displacement, settings: SensorDiagnosisSettings, scale: float = 1.0) -> list[Leg]:
    """Straight legs of the running displacement: runs of motion whose dominant direction is
    one of +x, -x, +y, -y (smoothed velocity, 0.3 s; speed above a quarter of its 95th
    percentile, widened while above a tenth), at least 0.5 s long and 3 cm. Each leg's
    length is measured between the mean positions of the reference windows around it: the
    stillest 0.4 s of the pause before and after, or, at a corner without a pause, the
    perpendicular neighbouring leg (its mean position along this leg's axis)."""
    t = disp.t_s
    if len(t) < 10:
        return []
    p = disp.path(scale, scale)
    dt = float(np.median(np.diff(t)))
    n = max(3, int(round(0.3 / dt)))
    v = np.column_stack([np.gradient(_moving_mean(p[:, i], n), t) for i in range(2)])
    speed = np.hypot(v[:, 0], v[:, 1])
    thr = max(0.01, 0.25 * float(np.percentile(speed, 95)))
    cls = np.where(np.abs(v[:, 0]) >= np.abs(v[:, 1]), np.where(v[:, 0] > 0, 0, 1), np.where(v[:, 1] > 0, 2, 3))
    cls = np.where((speed > thr) & disp.valid, cls, -1)
    runs = _label_runs(cls)
    runs = [r if r[2] < 0 or t[r[1] - 1] - t[r[0]] >= 0.25 else (r[0], r[1], -1) for r in runs]
    runs = _merge_runs(runs, t, join_s=0.3)
    cand = [r for r in runs if r[2] >= 0 and t[r[1] - 1] - t[r[0]] >= 0.5]
    # hysteresis: widen each leg while the speed stays above a lower threshold, so that its
    # slow start and stop belong to it and the reference windows fall in the pauses
    low = max(0.005, 0.1 * float(np.percentile(speed, 95)))
    wide: list[tuple[int, int, int]] = []
    for i, (a, b, c) in enumerate(cand):
        lo_lim = wide[-1][1] if wide else 0
        hi_lim = cand[i + 1][0] if i + 1 < len(cand) else len(t)
        while a - 1 >= lo_lim and speed[a - 1] > low:
            a -= 1
        while b < hi_lim and speed[b] > low:
            b += 1
        wide.append((a, b, c))
    cand = wide
    legs: list[Leg] = []
    for i, (a, b, c) in enumerate(cand):
        axis, direction = (0 if c < 2 else 1), (1 if c % 2 == 0 else -1)
        prev = cand[i - 1] if i > 0 else None
        nxt = cand[i + 1] if i + 1 < len(cand) else None
        before, kind_b = _reference(t, speed, a, prev, axis, before=True)
        after, kind_a = _reference(t, speed, b - 1, nxt, axis, before=False)

        def diff(x: np.ndarray, ax: int, before: Any = before, after: Any = after) -> float:
            return _mean_in(t, x[:, ax], after) - _mean_in(t, x[:, ax], before)

        # across the leg: the pause windows where there are pauses; at a corner the neighbour leg
        # moves along this leg's cross axis, so the leg's own ends instead
        cross_before = before if kind_b == "pause" else (float(t[a]), float(t[a]) + CROSS_END_S)
        cross_after = after if kind_a == "pause" else (float(t[b - 1]) - CROSS_END_S, float(t[b - 1]))
        cross = _mean_in(t, p[:, 1 - axis], cross_after) - _mean_in(t, p[:, 1 - axis], cross_before)
        leg = Leg(float(t[a]), float(t[b - 1]), axis, direction, before, after,
                  diff(disp.flow_x, axis), diff(disp.flow_y, axis), diff(disp.rotation, axis), cross)
        if leg.length(scale, scale) >= 0.03:
            legs.append(leg)
    return legs


def _label_runs(cls: np.ndarray) -> list[tuple[int, int, int]]:
    edges = np.r_[0, np.flatnonzero(np.diff(cls) != 0) + 1, len(cls)]
    return [(int(a), int(b), int(cls[a])) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def _merge_runs(runs: list[tuple[int, int, int]], t: np.ndarray, join_s: float) -> list[tuple[int, int, int]]:
    """Join runs of the same class separated by a short unclassified gap; join equal neighbours."""
    out: list[tuple[int, int, int]] = []
    for r in runs:
        if out and out[-1][2] == r[2]:
            out[-1] = (out[-1][0], r[1], r[2])
            continue
        if (len(out) >= 2 and out[-1][2] < 0 and out[-2][2] == r[2] and r[2] >= 0
                and t[out[-1][1] - 1] - t[out[-1][0]] < join_s):
            gap = out.pop()
            out[-1] = (out[-1][0], r[1], r[2])
            del gap
            continue
        out.append(r)
    return out


def _reference(t: np.ndarray, speed: np.ndarray, idx: int, neighbour: tuple[int, int, int] | None, axis: int,
               before: bool, window_s: float = 0.4, reach_s: float = 2.0) -> tuple[tuple[float, float], str]:
    """Reference window next to a leg end ``idx``: in the pause, the stillest ``window_s``
    (lowest mean speed) within ``reach_s`` of the leg, so slow creep into or out of the leg
    counts as part of it; a short pause as a whole; at a corner without a pause, the
    perpendicular neighbour leg (its middle 60 %); else the boundary itself (0.1 s). Returns
    the window and its kind: "pause", "corner" or "boundary"."""
    if before:
        lo = max(float(t[neighbour[1] - 1]) if neighbour else float(t[0]), float(t[idx]) - reach_s)
        hi = float(t[idx])
    else:
        lo = float(t[idx])
        hi = min(float(t[neighbour[0]]) if neighbour else float(t[-1]), float(t[idx]) + reach_s)
    if hi - lo >= window_s:
        m = np.flatnonzero((t >= lo) & (t <= hi))
        n = max(1, int(np.sum(t[m] <= t[m[0]] + window_s)))
        if len(m) > n:
            mean_speed = np.convolve(speed[m], np.ones(n) / n, mode="valid")
            # the stillest window; among near-equals (within 10 %) the one nearest the leg
            ok = np.flatnonzero(mean_speed <= 1.1 * mean_speed.min())
            j = int(ok[-1] if before else ok[0])
            return (float(t[m[j]]), float(t[m[j + n - 1]])), "pause"
        return (lo, hi), "pause"
    if hi - lo >= 0.1 or neighbour is None:
        return (lo, hi), "pause"
    n_axis = 0 if neighbour[2] < 2 else 1
    if n_axis != axis:
        a, b = t[neighbour[0]], t[neighbour[1] - 1]
        return (float(a + 0.2 * (b - a)), float(b - 0.2 * (b - a))), "corner"
    return (float(t[idx] - 0.05), float(t[idx] + 0.05)), "boundary"


def _mean_in(t: np.ndarray, x: np.ndarray, win: tuple[float, float]) -> float:
    m = (t >= win[0]) & (t <= win[1])
    if not np.any(m):
        return float(np.interp(0.5 * (win[0] + win[1]), t, x))
    return float(np.mean(x[m]))


@dataclass
class LegScaleFit:
    """Scale per axis (relative to Q) from legs of known length: weighted least squares of
    ``direction * (sx dFx + sy dFy + dR) = L`` with each leg's true length uncertain by
    ``leg_tolerance_rel``; reduced chi-square > 1 inflates the covariance; the range
    calibration adds a common ``range_scale_rel``. Leave-one-leg-out held-out residuals."""

    settings: SensorDiagnosisSettings
    leg_m: float
    scale_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    sigma_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    #: the part of ``sigma_`` from the legs alone (without the common range calibration)
    sigma_stat_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    identifiable_: np.ndarray = field(default_factory=lambda: np.zeros(2, dtype=bool))
    chi2_red_: float = float("nan")
    heldout_before_: float = float("nan")
    heldout_after_: float = float("nan")
    heldout_errors_: list[float] = field(default_factory=list)
    reasons_: list[str] = field(default_factory=list)

    def fit(self, legs: list[Leg]) -> LegScaleFit:
        st = self.settings
        self.reasons_ = []
        counts = [sum(1 for lg in legs if lg.axis == a) for a in range(2)]
        sc, cov, chi2 = _solve_legs(legs, self.leg_m, st, counts)
        self.chi2_red_ = chi2
        for a in range(2):
            if counts[a] == 0:
                self.reasons_.append(f"no legs along {'xy'[a]}: scale_{'xy'[a]} not identifiable from displacement")
                continue
            sig = math.sqrt(cov[a, a] + (st.range_scale_rel * sc[a]) ** 2)
            self.scale_[a], self.sigma_[a], self.sigma_stat_[a] = sc[a], sig, math.sqrt(cov[a, a])
            self.identifiable_[a] = sig / abs(sc[a]) <= st.max_rel_uncertainty
            if not self.identifiable_[a]:
                self.reasons_.append(f"scale_{'xy'[a]} from {counts[a]} legs has a relative uncertainty of "
                                     f"{100 * sig / abs(sc[a]):.0f} %")
        # leave one leg out
        before, after = [], []
        for i, lg in enumerate(legs):
            rest = legs[:i] + legs[i + 1:]
            rc = [sum(1 for x in rest if x.axis == a) for a in range(2)]
            if rc[lg.axis] == 0:
                continue
            s_i, _, _ = _solve_legs(rest, self.leg_m, st, rc)
            after.append(lg.length(s_i[0], s_i[1]) - self.leg_m)
            before.append(lg.length(1.0, 1.0) - self.leg_m)
        if after:
            self.heldout_before_ = float(np.sqrt(np.mean(np.square(before))))
            self.heldout_after_ = float(np.sqrt(np.mean(np.square(after))))
            self.heldout_errors_ = [float(e) for e in after]
        return self


def _solve_legs(legs: list[Leg], leg_m: float, st: SensorDiagnosisSettings,
                counts: list[int]) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted LS for the axes that have legs (the other scale held at 1)."""
    free = [a for a in range(2) if counts[a] > 0]
    sc = np.ones(2)
    cov = np.full((2, 2), np.nan)
    if not free:
        return sc, cov, float("nan")
    sigma = st.leg_tolerance_rel * leg_m
    A = np.array([[lg.direction * (lg.d_flow_x, lg.d_flow_y)[a] for a in free] for lg in legs])
    fixed = np.array([lg.direction * (lg.d_rotation + sum((lg.d_flow_x, lg.d_flow_y)[a] for a in range(2)
                                                          if a not in free)) for lg in legs])
    b = leg_m - fixed
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    resid = b - A @ x
    dof = len(legs) - len(free)
    chi2 = float(np.sum((resid / sigma) ** 2) / dof) if dof > 0 else float("nan")
    c = np.linalg.pinv(A.T @ A) * sigma**2
    if dof > 0 and chi2 > 1.0:
        c = c * chi2
    for i, a in enumerate(free):
        sc[a] = x[i]
        for j, b2 in enumerate(free):
            cov[a, b2] = c[i, j]
    return sc, cov, chi2


def pattern_match(legs: list[Leg], motion: DocumentedMotion) -> tuple[float, str]:
    """Fraction of detected legs that follow the documented direction sequence (best cyclic
    alignment) and the detected sequence as text."""
    seq = [lg.name for lg in legs]
    if not seq:
        return 0.0, ""
    pat = list(motion.pattern)
    best = 0
    shifts = range(len(pat)) if motion.cyclic else [0]
    for sh in shifts:
        hits = sum(1 for i, s in enumerate(seq)
                   if (motion.cyclic or i < len(pat)) and s == pat[(i + sh) % len(pat)])
        best = max(best, hits)
    return best / len(seq), " ".join(seq)


@dataclass
class PooledScale:
    """The leg-based scale across recordings: inverse-variance mean per axis over the files
    where it is identifiable (legs-only uncertainties; the common range calibration added
    after pooling; reduced chi-square > 1 inflates), the spread, and leave-one-file-out
    held-out leg residuals (m): each file's legs predicted with the other files' pooled scale."""

    per_file: dict[str, tuple[np.ndarray, np.ndarray]]  # name -> (scale (2,), sigma_stat (2,)), NaN = none
    scale: np.ndarray
    sigma: np.ndarray
    chi2_red: np.ndarray
    spread_sd_rel: np.ndarray  # sample standard deviation / mean
    spread_range: np.ndarray  # (2, 2): min, max per axis
    n_files: np.ndarray
    heldout_before: float
    heldout_after: float
    heldout_per_file: dict[str, tuple[float, float]]


def _pool(values: list[tuple[np.ndarray, np.ndarray]], range_rel: float) -> tuple[np.ndarray, ...]:
    scale, sigma, chi2, sd, rng, n = (np.full(2, np.nan), np.full(2, np.nan), np.full(2, np.nan),
                                      np.full(2, np.nan), np.full((2, 2), np.nan), np.zeros(2, dtype=int))
    for a in range(2):
        v = np.array([x[0][a] for x in values if np.isfinite(x[0][a])])
        e = np.array([x[1][a] for x in values if np.isfinite(x[0][a])])
        n[a] = len(v)
        if len(v) == 0:
            continue
        w = 1.0 / e**2
        m = float(np.sum(w * v) / np.sum(w))
        se = 1.0 / math.sqrt(float(np.sum(w)))
        if len(v) > 1:
            chi2[a] = float(np.sum(w * (v - m) ** 2) / (len(v) - 1))
            se *= math.sqrt(max(1.0, chi2[a]))
            sd[a] = float(np.std(v, ddof=1) / np.mean(v))
        scale[a], sigma[a] = m, math.hypot(se, range_rel * m)
        rng[a] = (float(v.min()), float(v.max()))
    return scale, sigma, chi2, sd, rng, n


def pool_scales(diags: list[SensorDiagnosis], settings: SensorDiagnosisSettings | None = None) -> PooledScale:
    """Pool the per-file leg-based scales (files without an identifiable scale are skipped)."""
    st = settings or SensorDiagnosisSettings()
    per: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for d in diags:
        f = d.scale_fit
        if f is None:
            continue
        per[d.series.name] = (np.where(f.identifiable_, f.scale_, np.nan), np.where(f.identifiable_, f.sigma_stat_,
                                                                                    np.nan))
    scale, sigma, chi2, sd, rng, n = _pool(list(per.values()), st.range_scale_rel)
    before, after, by_file = [], [], {}
    for d in diags:
        if d.motion is None or not d.legs:
            continue
        others = [v for k, v in per.items() if k != d.series.name]
        s_o = np.where(np.isfinite(p := _pool(others, st.range_scale_rel)[0]), p, 1.0)
        b = [lg.length(1.0, 1.0) - d.motion.leg_m for lg in d.legs]
        a = [lg.length(s_o[0], s_o[1]) - d.motion.leg_m for lg in d.legs]
        before += b
        after += a
        by_file[d.series.name] = (float(np.sqrt(np.mean(np.square(b)))), float(np.sqrt(np.mean(np.square(a)))))
    rms = (lambda x: float(np.sqrt(np.mean(np.square(x)))) if x else float("nan"))  # noqa: E731
    return PooledScale(per, scale, sigma, chi2, sd, rng, n, rms(before), rms(after), by_file)


# ---------------------------------------------------------------------------------------------
# The whole diagnosis


@dataclass
class SensorDiagnosis:
    """Everything ``diagnose_sensor`` computed, for the report, the plots and the docs."""

    series: SensorSeries
    timing: TimingAnalysis
    rows: np.ndarray
    bias: BiasFit
    bias_z: float
    band: RotationBandFit
    motion: DocumentedMotion | None
    legs: list[Leg]
    scale_fit: LegScaleFit | None
    disp_nominal: Displacement
    disp_fitted: Displacement
    scale: np.ndarray  # (2,) used for the extended model (1 where not identifiable)
    report: Report = field(default_factory=lambda: Report(recording=""))


def diagnose_sensor(rec: Recording, cfg: Config, *, report_dir: Path | None = None, profile: str | None = None,
                    settings: SensorDiagnosisSettings | None = None,
                    rng: np.random.Generator | None = None) -> Report:
    """Sensor-only diagnosis of ``rec`` against the paper's flow-sensor model with ``cfg``'s Q.

    Returns the mismatch report (``mode = "sensor"``); with ``report_dir``, also writes one PNG
    and ``report.md`` there. ``rng`` drives the bootstrap (default: seeded with 0, so reports
    are reproducible).
    """
    return run_sensor_diagnosis(rec, cfg, report_dir=report_dir, profile=profile, settings=settings,
                                rng=rng).report


def run_sensor_diagnosis(rec: Recording, cfg: Config, *, report_dir: Path | None = None,
                         profile: str | None = None, settings: SensorDiagnosisSettings | None = None,
                         rng: np.random.Generator | None = None) -> SensorDiagnosis:
    """``diagnose_sensor`` keeping the intermediate results (``SensorDiagnosis``)."""
    st = settings or SensorDiagnosisSettings()
    rng = rng if rng is not None else np.random.default_rng(0)
    s = extract_series(rec, cfg, profile)
    tm = analyse_timing(s)
    rows = np.flatnonzero(tm.new_reading)
    t = s.t_s[rows]
    cover = np.r_[s.read_period_s, np.minimum(np.diff(t), 2.0 * s.read_period_s)]
    g_rows = s.gyro_at(t)
    cx, cy = s.counts_x[rows], s.counts_y[rows]
    q = s.q_rad_per_count
    bias = fit_gyro_bias(t, cover, g_rows, cx, cy, s.read_period_s, q, q, st)
    still = still_rows(t, g_rows, cx, cy, st)
    bias_z = float(np.mean(g_rows[still, 2])) if np.any(still) else float("nan")
    band = RotationBandFit(st, rng).fit(s, rows, bias.bias)
    motion = DOCUMENTED_MOTIONS.get(recording_name(s.name))  # flow_test_x_axis_01.csv(.gz)
    zero2 = np.zeros(2)
    disp_nominal = displacement_parts(s, rows, zero2, 0.0, 0.0, st)
    delay = band.delay_ if band.fitted and band.delay_sigma_ < 0.01 else 0.0
    disp_b = displacement_parts(s, rows, bias.bias, bias_z, delay, st)
    legs: list[Leg] = []
    scale_fit = None
    scale = np.ones(2)
    if motion is not None:
        legs = find_legs(disp_b, st)
        scale_fit = LegScaleFit(st, motion.leg_m).fit(legs)
        scale = np.where(scale_fit.identifiable_, scale_fit.scale_, 1.0)
    if np.any(np.isfinite(bias.bias)) and np.any(scale != 1.0):
        bias = fit_gyro_bias(t, cover, g_rows, cx, cy, s.read_period_s, q * scale[0], q * scale[1], st)
        disp_b = displacement_parts(s, rows, bias.bias, bias_z, delay, st)
    d = SensorDiagnosis(s, tm, rows, bias, bias_z, band, motion, legs, scale_fit, disp_nominal, disp_b, scale)
    d.report = _build_report(rec, cfg, d, st)
    if report_dir is not None:
        write_report_dir(d, Path(report_dir))
    return d


def _build_report(rec: Recording, cfg: Config, d: SensorDiagnosis, st: SensorDiagnosisSettings) -> Report:
    s, band = d.series, d.band
    rep = Report(recording=Path(rec.path).name, mode="sensor")
    q = cfg.flow_sensor.q_rad_per_count
    rep.notes.append(f"sensor-only diagnosis against the paper's flow model (eq. 9-15), Q = {q:.6g} rad/count "
                     f"from {Path(cfg.source).name}; flow rows read every {1e3 * s.read_period_s:g} ms; "
                     f"profile {s.profile}")
    rep.notes.extend(f"recording: {n}" for n in rec.notes)
    rep.findings.extend(timing_findings(s, d.timing))
    rep.findings.append(range_finding(s, st))
    rep.findings.append(_scale_finding(d, st, q))
    rep.findings.append(_bias_finding(d, st))
    rep.findings.append(_delay_finding(d, st))
    rep.findings.append(_yaw_finding(d, st))
    rep.notes.append(_rotation_note(band, st))
    if band.fitted:
        rep.baseline_rms["flow_x_band_counts"] = float(band.baseline_rms_[0])
        rep.baseline_rms["flow_y_band_counts"] = float(band.baseline_rms_[1])
        rep.unexplained.extend(_band_unexplained(band))
    for f in rep.findings:
        if not f.significant and f.effect in ("flow_scale", "gyro_bias", "flow_delay", "flow_yaw_misalignment") \
                and not any(np.isfinite(v) for v in f.parameters.values()):
            rep.notes.append(f"{f.effect}: {f.explanation}")
    if d.scale_fit is not None and d.legs:
        errs = [lg.length(1.0, 1.0) - d.motion.leg_m for lg in d.legs] if d.motion else []
        rep.baseline_rms["leg_length_m"] = float(np.sqrt(np.mean(np.square(errs)))) if errs else float("nan")
        for lg in d.legs:
            e = lg.length(d.scale[0], d.scale[1]) - (d.motion.leg_m if d.motion else 0.0)
            if abs(e) > 2 * st.leg_tolerance_rel * (d.motion.leg_m if d.motion else 0.0):
                rep.unexplained.append(Unexplained("leg_length_m", lg.start_s, lg.end_s, abs(e),
                                                   best_term="leg length off the documented one by more than 2 sigma "
                                                             "of the hand tolerance"))
    if np.isfinite(d.bias.before):
        rep.baseline_rms["still_scene_angle_rad"] = d.bias.before
    rep.actions = actions(rep, profile=s.profile, q_rad_per_count=q, current=recorded_parameters(rec))
    return rep


def _rotation_content(band: RotationBandFit) -> str:
    """The rotation content in words: in-band gyro, counts per reading, expected precision."""
    if not np.all(np.isfinite(band.gyro_band_rms_rad_s_)):
        return "no rotation content could be measured"
    return (f"in-band rotation {band.gyro_band_rms_rad_s_[1]:.2g} (pitch) / {band.gyro_band_rms_rad_s_[0]:.2g} "
            f"(roll) rad/s, i.e. {band.rotation_rms_counts_[0]:.2g} / {band.rotation_rms_counts_[1]:.2g} counts per "
            f"reading against {QUANT_RMS_COUNTS:.2f} counts of quantization noise, which alone would limit a "
            f"rotation-only scale to +-{100 * np.nanmin(band.expected_rel_sigma_):.0f} % at best")


def _rotation_note(band: RotationBandFit, st: SensorDiagnosisSettings) -> str:
    head = f"rotation band {st.band_low_hz:g}-{st.band_high_hz:g} Hz: {_rotation_content(band)}"
    if not band.fitted:
        return f"{head}; not fitted: {band.reason_}"
    sr, ssr = band.scale_from_rotation()
    ok = band.rotation_scale_identifiable()
    words = [f"{'xy'[a]} {sr[a]:.2f} +- {ssr[a]:.2f}" + ("" if ok[a] else " (not identifiable)") for a in range(2)]
    return (f"{head}; delay {1e3 * band.delay_:.0f} +- {1e3 * band.delay_sigma_:.0f} ms; rotation-only scale "
            f"{', '.join(words)} (R^2 {band.r2_[0]:.2f} / {band.r2_[1]:.2f}; identifiable only if within "
            f"{100 * st.max_rel_uncertainty:.0f} % and equal in both halves of the band)")


def _fmt_g(v: float, s: float) -> str:
    if not np.isfinite(v):
        return "n/a"
    return f"{v:.4g} +- {s:.2g}" if np.isfinite(s) else f"{v:.4g}"


def _fmt_pm(v: float, s: float, nd: int = 2) -> str:
    if not np.isfinite(v):
        return "n/a"
    return f"{v:.{nd}f} +- {s:.{nd}f}" if np.isfinite(s) else f"{v:.{nd}f}"


def _scale_finding(d: SensorDiagnosis, st: SensorDiagnosisSettings, q: float) -> Finding:
    band = d.band
    sr, ssr = band.scale_from_rotation()
    rot_ok = [bool(v) for v in band.rotation_scale_identifiable()]
    with np.errstate(divide="ignore", invalid="ignore"):
        s_sub, ss_sub = 1.0 / band.subband_gain_, band.subband_gain_sigma_ / band.subband_gain_**2
    ev: dict[str, Any] = {
        "constraint": "displacement: legs of documented length (Fig. 6 style)",
        "q_nominal_rad_per_count": q,
        "rotation_band_scale": {"x": sr[0], "y": sr[1], "sigma_x": ssr[0], "sigma_y": ssr[1],
                                "identifiable_x": rot_ok[0], "identifiable_y": rot_ok[1],
                                "r2_x": band.r2_[0], "r2_y": band.r2_[1],
                                "subbands_hz": [list(b) for b in band.subband_hz_],
                                "subband_x": list(s_sub[:, 0]), "subband_sigma_x": list(ss_sub[:, 0]),
                                "subband_y": list(s_sub[:, 1]), "subband_sigma_y": list(ss_sub[:, 1]),
                                "note": "rotation-only scale: identifiable only if precise and equal in both "
                                        "halves of the band; never used for the parameters"},
    }
    if d.motion is None or d.scale_fit is None:
        if band.fitted:
            rot = (f"the rotation band alone gives x {_fmt_pm(sr[0], ssr[0])}, y {_fmt_pm(sr[1], ssr[1])}, "
                   f"{'consistent' if all(rot_ok) else 'not consistent'} across the band")
        else:
            rot = f"the rotation band is unusable: {band.reason_}; {_rotation_content(band)}"
        return Finding(
            effect="flow_scale", significant=False, parameters={"scale_x": float("nan"), "scale_y": float("nan")},
            uncertainty={"scale_x": float("nan"), "scale_y": float("nan")},
            explanation=(f"Not identifiable: there is no documented motion to measure the counts against, and {rot}."),
            fit=None, evidence=ev)
    f = d.scale_fit
    m = d.motion
    pm, seq = pattern_match(d.legs, m)
    ev.update({
        "reference": ("documented" if m.documented else "assumed") + f": {m.source}",
        "leg_m": m.leg_m, "leg_tolerance_rel": st.leg_tolerance_rel, "range_scale_rel": st.range_scale_rel,
        "legs_detected": seq, "pattern_match": pm, "chi2_reduced": f.chi2_red_,
        "scale_rad_per_count": {"x": f.scale_[0] * q, "y": f.scale_[1] * q},
        "legs": [{"leg": lg.name, "start_s": lg.start_s, "end_s": lg.end_s,
                  "nominal_m": lg.length(1.0, 1.0), "fitted_m": lg.length(d.scale[0], d.scale[1]),
                  "rotation_part_m": lg.direction * lg.d_rotation, "cross_m": lg.cross_m} for lg in d.legs],
    })
    params = {"scale_x": float(f.scale_[0]) if f.identifiable_[0] else float("nan"),
              "scale_y": float(f.scale_[1]) if f.identifiable_[1] else float("nan")}
    unc = {"scale_x": float(f.sigma_[0]) if f.identifiable_[0] else float("nan"),
           "scale_y": float(f.sigma_[1]) if f.identifiable_[1] else float("nan")}
    fit = Fit(f.heldout_before_, f.heldout_after_) if np.isfinite(f.heldout_after_) else None
    away = any(f.identifiable_[a] and abs(f.scale_[a] - 1.0) > 2 * f.sigma_[a] for a in range(2))
    earned = bool(fit is not None and fit.improvement_pct >= st.min_improvement_pct)
    sig = earned and away
    parts = [f"{'xy'[a]} {f.scale_[a]:.2f} +- {f.sigma_[a]:.2f}" for a in range(2) if f.identifiable_[a]]
    bigger = all(f.scale_[a] > 1.0 for a in range(2) if f.identifiable_[a])
    expl = (f"Each count is a {'larger' if bigger else 'different'} angle than the paper's Q (true rad per count = "
            f"scale x Q: {', '.join(parts) or 'none identifiable'}), measured by making the rotation-compensated "
            f"running sum of flow times range span the {100 * m.leg_m:.0f} cm legs ({len(d.legs)} found)")
    if f.reasons_:
        expl += "; " + "; ".join(f.reasons_)
    if fit is not None and earned and not away:
        expl += (f"; the held-out leg error drops ({100 * fit.heldout_rms_before:.1f} -> "
                 f"{100 * fit.heldout_rms_after:.1f} cm) but the scale is within 2 sigma of the paper's Q")
    expl += "."
    where = [Window("flow_x" if lg.axis == 0 else "flow_y", lg.start_s, lg.end_s) for lg in d.legs]
    return Finding(effect="flow_scale", significant=sig, parameters=params, uncertainty=unc, explanation=expl,
                   where=where, fit=fit, evidence=ev)


def _bias_finding(d: SensorDiagnosis, st: SensorDiagnosisSettings) -> Finding:
    b = d.bias
    ev: dict[str, Any] = {"constraint": "still segments: gyro mean minus the rotation the flow sees",
                          "still_s": b.still_s, "quietest_gyro_std_rad_s": b.quietest_gyro_std,
                          "bias_z_rad_s": d.bias_z}
    if not np.all(np.isfinite(b.bias)):
        return Finding(effect="gyro_bias", significant=False,
                       parameters={"bias_x": float("nan"), "bias_y": float("nan")},
                       uncertainty={"bias_x": float("nan"), "bias_y": float("nan")},
                       explanation=f"Not identifiable: {b.reason}.", fit=None, evidence=ev)
    fit = Fit(b.before, b.after)
    away = bool(np.any(np.abs(b.bias) > 2 * np.nan_to_num(b.sigma, nan=np.inf)))
    sig = bool(fit.improvement_pct >= st.min_improvement_pct and away)
    return Finding(
        effect="gyro_bias", significant=sig,
        parameters={"bias_x": float(b.bias[0]), "bias_y": float(b.bias[1])},
        uncertainty={"bias_x": float(b.sigma[0]), "bias_y": float(b.sigma[1])},
        explanation=(f"At rest the gyro reads {1e3 * b.bias[0]:+.1f} (roll) and {1e3 * b.bias[1]:+.1f} (pitch) mrad/s "
                     f"that the flow does not see, so the model without this offset drifts by that rate in scene "
                     f"angle ({b.still_s:.1f} s of still data)."),
        where=[Window("gyro", a, e) for a, e in b.windows], fit=fit, evidence=ev)


def _delay_finding(d: SensorDiagnosis, st: SensorDiagnosisSettings) -> Finding:
    band = d.band
    T = d.series.read_period_s
    if not band.fitted:
        return Finding(effect="flow_delay", significant=False, parameters={"delay": float("nan")},
                       uncertainty={"delay": float("nan")},
                       explanation=f"Not identifiable: {band.reason_}; {_rotation_content(band)}.", fit=None,
                       evidence={"constraint": "rotation band"})
    ho = band.heldout_
    ev = {"constraint": f"rotation band {st.band_low_hz:g}-{st.band_high_hz:g} Hz, blocked {st.n_folds}-fold",
          "nominal_window": f"each row's counts cover the {1e3 * T:g} ms before its timestamp",
          "gyro_band_rms_rad_s": {"x": band.gyro_band_rms_rad_s_[0], "y": band.gyro_band_rms_rad_s_[1]},
          "rotation_rms_counts": {"x": band.rotation_rms_counts_[0], "y": band.rotation_rms_counts_[1]},
          "quantization_rms_counts": QUANT_RMS_COUNTS, "heldout_rms_counts": ho,
          "rows": band.n_rows_, "translation_from_accelerometer": band.has_translation_}
    ident = band.delay_sigma_ <= max(0.005, 0.25 * abs(band.delay_))
    if not ident:
        return Finding(effect="flow_delay", significant=False, parameters={"delay": float("nan")},
                       uncertainty={"delay": float("nan")},
                       explanation=(f"Not identifiable: {_rotation_content(band)}, and the delay scatters by "
                                    f"{1e3 * band.delay_sigma_:.0f} ms under resampling."),
                       fit=Fit(ho["no_delay"], ho["delay"]), evidence=ev)
    fit = Fit(ho["no_delay"], ho["delay"])
    sig = bool(fit.improvement_pct >= st.min_improvement_pct and abs(band.delay_) > 2 * band.delay_sigma_)
    return Finding(
        effect="flow_delay", significant=sig, parameters={"delay": band.delay_},
        uncertainty={"delay": band.delay_sigma_}, where=_band_windows(band),
        explanation=(f"The flow counts follow the gyro's rotation {1e3 * band.delay_:.0f} ms later than a reading of "
                     f"the {1e3 * T:g} ms before its row would (the logged reading is up to one read old, and the "
                     f"sensor reports a frame after it images it)."),
        fit=fit, evidence=ev)


def _yaw_finding(d: SensorDiagnosis, st: SensorDiagnosisSettings) -> Finding:
    band = d.band
    if not band.fitted or not np.isfinite(band.yaw_):
        return Finding(effect="flow_yaw_misalignment", significant=False, parameters={"yaw": float("nan")},
                       uncertainty={"yaw": float("nan")},
                       explanation=f"Not identifiable: {band.reason_ or 'the rotation band could not be fitted'}.",
                       fit=None, evidence={"constraint": "rotation band"})
    ho = band.heldout_
    fit = Fit(ho["delay"], ho["yaw"])
    ev = {"constraint": "rotation band: cross-axis response of the flow to roll and pitch",
          "convention": "sensor x axis turned by +yaw towards body y (simvehicle.flow_sensor.sensor_axes)"}
    if band.yaw_sigma_ > math.radians(10):
        return Finding(effect="flow_yaw_misalignment", significant=False, parameters={"yaw": float("nan")},
                       uncertainty={"yaw": float("nan")},
                       explanation=(f"Not identifiable: the cross-axis response scatters by "
                                    f"{math.degrees(band.yaw_sigma_):.0f} deg under resampling."), fit=fit, evidence=ev)
    sig = bool(fit.improvement_pct >= st.min_improvement_pct and abs(band.yaw_) > 2 * band.yaw_sigma_)
    return Finding(
        effect="flow_yaw_misalignment", significant=sig, parameters={"yaw": band.yaw_},
        uncertainty={"yaw": band.yaw_sigma_}, where=_band_windows(band),
        explanation=(f"Roll and pitch leak into the other flow axis as a turn of the sensor by "
                     f"{math.degrees(band.yaw_):+.1f} +- {math.degrees(band.yaw_sigma_):.1f} deg about z"
                     + ("." if sig else ", which does not improve the held-out fit enough to count.")),
        fit=fit, evidence=ev)


def _band_windows(band: RotationBandFit) -> list[Window]:
    """The stretches the rotation band was fitted on."""
    return [Window("flow_band", float(band.t_[a]), float(band.t_[b - 1])) for a, b in _runs(band.use_)]


def _band_unexplained(band: RotationBandFit, window_s: float = 1.0, factor: float = 2.5) -> list[Unexplained]:
    """1-s windows where the extended model's in-band residual RMS exceeds ``factor`` x the median."""
    out: list[Unexplained] = []
    t = band.t_[band.use_]
    if len(t) == 0:
        return out
    res = (band.y_ - band.pred_fitted_)[band.use_]
    idx = np.floor((t - t[0]) / window_s).astype(int)
    for a, ch in enumerate(("flow_x_band_counts", "flow_y_band_counts")):
        rms = np.array([np.sqrt(np.mean(res[idx == k, a] ** 2)) if np.any(idx == k) else np.nan
                        for k in range(idx.max() + 1)])
        med = float(np.nanmedian(rms))
        for k in np.flatnonzero(rms > factor * med):
            sel = t[idx == k]
            out.append(Unexplained(ch, float(sel[0]), float(sel[-1]), float(rms[k])))
    return out


# ---------------------------------------------------------------------------------------------
# Plots and report.md


def plot_diagnosis(d: SensorDiagnosis, path: Path) -> None:
    """One figure per recording: the running displacement (Fig. 6) on x and y with the paper's
    nominal model (Q, no bias, no delay) and the extended one, the legs and their documented
    length; the band-passed counts against both models; the still-segment drift."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(2, 2, figsize=(13, 8.5), constrained_layout=True)
    nom = d.disp_nominal.path(1.0, 1.0)
    ext = d.disp_fitted.path(d.scale[0], d.scale[1])
    t = d.disp_fitted.t_s
    for a, ax in enumerate(axs[0]):
        unit = 1e3 if np.max(np.abs(ext)) < 0.01 else 100.0  # mm for a recording that does not move
        ax.plot(d.disp_nominal.t_s, unit * nom[:, a], "--", color="0.5", lw=1, label="paper model (Q, no bias)")
        ax.plot(t, unit * ext[:, a], color="C0" if a == 0 else "C1", lw=1.5,
                label=f"extended (scale {d.scale[a]:.2f}, bias, delay)")
        for lg in d.legs:
            if lg.axis != a:
                continue
            ax.axvspan(lg.start_s, lg.end_s, color="C2", alpha=0.12)
            base = float(np.mean(ext[(t >= lg.before[0]) & (t <= lg.before[1]), a])) \
                if np.any((t >= lg.before[0]) & (t <= lg.before[1])) else 0.0
            if d.motion is not None:
                ax.hlines(100 * (base + lg.direction * d.motion.leg_m), lg.after[0], lg.after[1], colors="C3", lw=2)
            ax.annotate(f"{100 * lg.length(1.0, 1.0):.1f} / {100 * lg.length(d.scale[0], d.scale[1]):.1f} cm",
                        (0.5 * (lg.start_s + lg.end_s), 100 * base), fontsize=8, ha="center",
                        xytext=(0, -12 if lg.direction > 0 else 12), textcoords="offset points")
        ax.set_title(f"{'xy'[a]} position from the flow (gyro rotation removed, times range), "
                     f"{'mm' if unit > 100 else 'cm'}")
        ax.set_xlabel("time from first row (s)")
        ax.set_ylabel("displacement (mm)" if unit > 100 else "displacement (cm)")
        ax.grid(alpha=0.3)
        if d.motion is not None:
            ax.plot([], [], color="C3", lw=2, label=f"{_leg_reference(d.motion)} leg end")
        ax.legend(fontsize=8, loc="best")
    band = d.band
    ax = axs[1, 0]
    if band.fitted:
        u = band.use_
        tb = band.t_
        energy = np.convolve(np.where(u, np.sum(band.pred_fitted_ ** 2, axis=1), 0.0),
                             np.ones(max(1, int(4.0 / np.median(np.diff(tb))))), mode="same")
        c = tb[int(np.argmax(energy))]
        m = u & (tb >= c - 2.0) & (tb <= c + 2.0)
        for a, col in enumerate(("C0", "C1")):
            off = 3.0 * a
            ax.plot(tb[m], band.y_[m, a] + off, color=col, lw=1, label=f"recorded {'xy'[a]} (band-passed)")
            ax.plot(tb[m], band.pred_nominal_[m, a] + off, "--", color="0.4", lw=1,
                    label="paper model" if a == 0 else None)
            ax.plot(tb[m], band.pred_fitted_[m, a] + off, color="k", lw=1, label="extended" if a == 0 else None)
        ax.set_title(f"counts, {d.band.settings.band_low_hz:g}-{d.band.settings.band_high_hz:g} Hz band "
                     f"(y offset +3); delay {1e3 * band.delay_:.0f} ms")
        ax.legend(fontsize=8, loc="upper right")
    else:
        import textwrap

        ax.text(0.5, 0.5, textwrap.fill(f"rotation band not fitted: {band.reason_}; {_rotation_content(band)}", 60),
                ha="center", va="center", transform=ax.transAxes, fontsize=9)
    ax.set_xlabel("time from first row (s)")
    ax.set_ylabel("counts per reading")
    ax.grid(alpha=0.3)
    ax = axs[1, 1]
    s = d.series
    q = s.q_rad_per_count
    if d.legs and d.motion is not None:
        x = np.arange(len(d.legs))
        ax.bar(x - 0.2, [100 * lg.length(1.0, 1.0) for lg in d.legs], 0.4, color="0.6", label="paper model (Q)")
        ax.bar(x + 0.2, [100 * lg.length(d.scale[0], d.scale[1]) for lg in d.legs], 0.4, color="C0",
               label="extended (fitted scale)")
        ax.axhline(100 * d.motion.leg_m, color="C3", lw=2, label=_leg_reference(d.motion))
        ax.axhspan(100 * d.motion.leg_m * (1 - d.band.settings.leg_tolerance_rel),
                   100 * d.motion.leg_m * (1 + d.band.settings.leg_tolerance_rel), color="C3", alpha=0.1)
        ax.set_xticks(x, [f"{lg.name}\n{lg.start_s:.0f}s" for lg in d.legs], fontsize=7)
        ax.set_ylabel("leg length (cm)")
        ax.set_title(f"reconstructed legs against the {'documented' if d.motion.documented else 'assumed'} "
                     f"length (+-{100 * d.band.settings.leg_tolerance_rel:.0f} % shaded), cm")
        ax.legend(fontsize=8, loc="lower right")
    else:
        tt = s.t_s[d.rows]
        g = s.gyro_at(tt)
        cover = np.r_[s.read_period_s, np.minimum(np.diff(tt), 2.0 * s.read_period_s)]
        still = np.zeros(len(tt), dtype=bool)
        for a0, b0 in d.bias.windows:
            still |= (tt >= a0) & (tt <= b0)
        flow_rot = np.column_stack([s.counts_y[d.rows] * q * d.scale[1], -s.counts_x[d.rows] * q * d.scale[0]])
        for a, (lab, col) in enumerate((("roll", "C0"), ("pitch", "C1"))):
            rate = np.where(still, g[:, a] - flow_rot[:, a] / s.read_period_s, 0.0)
            drift = np.cumsum(rate * cover)
            ax.plot(tt, 1e3 * drift, "--", color=col, lw=1, label=f"{lab}: paper model (no bias)")
            if np.isfinite(d.bias.bias[a]):
                ax.plot(tt, 1e3 * (drift - np.cumsum(np.where(still, d.bias.bias[a], 0.0) * cover)), color=col,
                        lw=1.5, label=f"{lab}: bias {1e3 * d.bias.bias[a]:+.1f} mrad/s removed")
        for a0, b0 in d.bias.windows:
            ax.axvspan(a0, b0, color="C2", alpha=0.1)
        ax.set_title("gyro angle minus flow angle over still segments (shaded)")
        ax.set_xlabel("time from first row (s)")
        ax.set_ylabel("angle (mrad)")
        ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.suptitle(f"{s.name}: paper's flow model vs recording (Q = {q:.5f} rad/count)")
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _fmt_param(f: Finding, key: str, v: float) -> str:
    """``key value +- sigma unit`` of one parameter, ``n/a`` when not identifiable."""
    text = f"{key} {_fmt_g(v, f.uncertainty.get(key, float('nan')))}"
    return text + (f" {f.unit(key)}" if f.unit(key) and np.isfinite(v) else "")


def _leg_reference(m: DocumentedMotion) -> str:
    """``documented 20 cm`` where the maker documents the legs, ``assumed 20 cm`` where they are assumed."""
    return f"{'documented' if m.documented else 'assumed'} {100 * m.leg_m:.0f} cm"


def write_report_dir(d: SensorDiagnosis, report_dir: Path) -> Path:
    """Write ``<stem>_sensor.png``, ``report.md`` and ``report.html`` (the same, one page with the
    plot embedded) into ``report_dir``; returns the .md path."""
    report_dir.mkdir(parents=True, exist_ok=True)
    stem = recording_stem(d.series.name)
    png = report_dir / f"{stem}_sensor.png"
    plot_diagnosis(d, png)
    md = report_dir / "report.md"
    md.write_text(markdown_report(d, png.name))
    write_html_report(d.report, md, q_rad_per_count=d.series.q_rad_per_count)
    return md


def markdown_report(d: SensorDiagnosis, png_name: str) -> str:
    rep = d.report
    lines = [f"# Sensor diagnosis: {rep.recording}", "",
             f"![paper model vs extended model]({png_name})", "", "## Findings", "",
             "| effect | significant | parameters | held-out RMS before -> after | explanation |",
             "|---|---|---|---|---|"]
    for f in rep.findings:
        params = ", ".join(_fmt_param(f, k, v) for k, v in f.parameters.items())
        if f.fit is not None:
            fit = f"{f.fit.heldout_rms_before:.4g} -> {f.fit.heldout_rms_after:.4g}"
        else:
            fit = "(counted, not fitted)" if f.evidence.get("constraint") == "log timing" else "n/a"
        lines.append(f"| {f.effect} | {'yes' if f.significant else 'no'} | {params} | {fit} | {f.explanation} |")
    if d.legs and d.motion is not None:
        lines += ["", f"## Legs ({_leg_reference(d.motion)}; {d.motion.source})", "",
                  "Each leg's length along its axis with the paper's Q and with the fitted scale, the part of it "
                  "that is rotation removed with the gyro, and how far it went sideways (across its axis, at the "
                  "paper's Q, between the pauses around it, or between its own ends where it turns a corner).", "",
                  "| leg | time (s) | paper Q (cm) | fitted scale (cm) | rotation part (cm) | sideways (cm) |",
                  "|---|---|---|---|---|---|"]
        for lg in d.legs:
            lines.append(f"| {lg.name} | {lg.start_s:.1f}-{lg.end_s:.1f} | {100 * lg.length(1, 1):.1f} | "
                         f"{100 * lg.length(d.scale[0], d.scale[1]):.1f} | {100 * lg.direction * lg.d_rotation:+.1f} | "
                         f"{100 * lg.cross_m:+.1f} |")
    if rep.unexplained:
        lines += ["", "## Unexplained", "", "| channel | start s | end s | RMS |", "|---|---|---|---|"]
        lines += [f"| {u.channel} | {u.start_s:.2f} | {u.end_s:.2f} | {u.rms:.3g} |" for u in rep.unexplained]
    lines += ["", "## Notes", ""] + [f"- {n}" for n in rep.notes] + [""]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Command line


def summary_lines(rep: Report) -> list[str]:
    """One line per finding for the console."""
    out = [f"{rep.recording}: sensor-only diagnosis"]
    for f in rep.findings:
        params = ", ".join(
            (f"{k}={v:.4g}" + (f"+-{f.uncertainty[k]:.2g}" if np.isfinite(f.uncertainty.get(k, np.nan)) else "")
             + (f" {f.unit(k)}" if f.unit(k) else ""))
            if np.isfinite(v) else f"{k}=n/a" for k, v in f.parameters.items())
        mark = "*" if f.significant else " "
        out.append(f" {mark} {f.effect:<24} {params}")
    return out


def run_sensor_cli(args: Any) -> int:
    """``python -m companion diagnose RECORDING [--sensor-config MAP] [--config] [--profile]
    [--json OUT] [--report DIR]`` for a recording without commands: the whole command."""
    rec = load_recording(args.recording, sensor_config=getattr(args, "sensor_config", None),
                         progress=sys.stderr.isatty())
    cfg = load_config(getattr(args, "config", None))
    report_dir = getattr(args, "report", None)
    rep = diagnose_sensor(rec, cfg, report_dir=Path(report_dir) if report_dir else None,
                          profile=getattr(args, "profile", None))
    if getattr(args, "json", None):
        rep.write_json(args.json)
    for line in summary_lines(rep):
        print(line)
    if getattr(args, "json", None):
        print(f"json: {args.json}")
    if report_dir:
        print(f"report: {Path(report_dir) / 'report.md'}")
        print(f"report: {Path(report_dir) / 'report.html'} (one page, plot embedded)")
    return 0


__all__ = [
    "DOCUMENTED_MOTIONS", "DocumentedMotion", "SensorDiagnosisSettings", "SensorSeries", "extract_series",
    "ReadGrid", "find_read_grid", "TimingAnalysis", "analyse_timing", "timing_findings", "range_finding",
    "fit_gyro_bias", "RotationBandFit", "window_integral", "displacement_parts", "find_legs", "Leg",
    "LegScaleFit", "PooledScale", "pool_scales", "diagnose_sensor", "run_sensor_diagnosis", "SensorDiagnosis",
    "run_sensor_cli",
    "plot_diagnosis", "write_report_dir", "markdown_report", "summary_lines",
]
