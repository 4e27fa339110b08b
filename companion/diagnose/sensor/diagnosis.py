"""One recording's sensor-only diagnosis, every fit: ``analyse`` runs the estimators in their
order (timing, bias, rotation band, legs and scale, bias again at the fitted scale) and keeps
what they found (``SensorDiagnosis``) for the report, the plots and the docs."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.config import Config
from companion.diagnose.report import Report
from companion.diagnose.sensor.band import RotationBandFit
from companion.diagnose.sensor.bias import BiasFit, fit_gyro_bias, still_rows
from companion.diagnose.sensor.legs import Displacement, Leg, LegScaleFit, displacement_parts, find_legs
from companion.diagnose.sensor.motions import DOCUMENTED_MOTIONS, DocumentedMotion
from companion.diagnose.sensor.series import SensorSeries, extract_series
from companion.diagnose.sensor.settings import SensorDiagnosisSettings
from companion.diagnose.sensor.timing import TimingAnalysis, analyse_timing
from companion.recordings.load import Recording, recording_name


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


def analyse(rec: Recording, cfg: Config, st: SensorDiagnosisSettings, rng: np.random.Generator, *,
            profile: str | None = None) -> SensorDiagnosis:
    """Every fit of the sensor-only diagnosis of ``rec`` (``run.run_sensor_diagnosis`` adds the
    report); ``rng`` drives the rotation band's bootstrap."""
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
    return SensorDiagnosis(s, tm, rows, bias, bias_z, band, motion, legs, scale_fit, disp_nominal, disp_b, scale)
