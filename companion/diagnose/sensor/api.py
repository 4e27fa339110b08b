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


The parts, one module each (``companion.diagnose.sensor.api`` re-exports their public names):

- ``settings``: ``SensorDiagnosisSettings`` (units in the names) and the constants;
- ``motions``: the documented motions of known recordings, by file name (data, not method);
- ``series``: extraction, the recording as ``SensorSeries`` (``extract_series``);
- the estimators: ``timing`` (the log's timing and held range), ``bias`` (gyro bias from still
  segments), ``band`` (the rotation band), ``legs`` (displacement, legs and the scale fitted to
  them), ``pool`` (the scale across recordings); ``numerics``, what they share;
- ``diagnosis``: ``analyse``, every fit of one recording (``SensorDiagnosis``);
- ``findings``: the mismatch report built from them; ``plots`` and ``markdown``: the figure,
  ``report.md`` and ``report.html``; ``run``: ``diagnose_sensor``, ``run_sensor_diagnosis`` and the
  command (``run_sensor_cli``).
"""

from __future__ import annotations

from companion.diagnose.sensor.band import RotationBandFit, inband_velocity
from companion.diagnose.sensor.bias import BiasFit, fit_gyro_bias, still_rows
from companion.diagnose.sensor.diagnosis import SensorDiagnosis, analyse
from companion.diagnose.sensor.legs import (
    AXIS_NAMES,
    CROSS_END_S,
    Displacement,
    Leg,
    LegScaleFit,
    displacement_parts,
    find_legs,
    pattern_match,
)
from companion.diagnose.sensor.markdown import markdown_report, write_report_dir
from companion.diagnose.sensor.motions import DOCUMENTED_MOTIONS, DocumentedMotion
from companion.diagnose.sensor.numerics import window_integral, window_integrals
from companion.diagnose.sensor.plots import plot_diagnosis
from companion.diagnose.sensor.pool import PooledScale, pool_scales
from companion.diagnose.sensor.run import diagnose_sensor, run_sensor_cli, run_sensor_diagnosis, summary_lines
from companion.diagnose.sensor.series import SensorSeries, extract_series
from companion.diagnose.sensor.settings import GRAVITY_M_S2, QUANT_RMS_COUNTS, SensorDiagnosisSettings
from companion.diagnose.sensor.timing import (
    TimingAnalysis,
    analyse_timing,
    merge_windows,
    range_finding,
    timing_findings,
)
from companion.recordings.importers.common import ReadGrid, find_read_grid

__all__ = [
    "DOCUMENTED_MOTIONS", "DocumentedMotion", "SensorDiagnosisSettings", "SensorSeries", "extract_series",
    "ReadGrid", "find_read_grid", "TimingAnalysis", "analyse_timing", "timing_findings", "range_finding",
    "fit_gyro_bias", "RotationBandFit", "window_integral", "displacement_parts", "find_legs", "Leg",
    "LegScaleFit", "PooledScale", "pool_scales", "diagnose_sensor", "run_sensor_diagnosis", "SensorDiagnosis",
    "run_sensor_cli",
    "plot_diagnosis", "write_report_dir", "markdown_report", "summary_lines",
    # the rest of what the single module held at its top level
    "GRAVITY_M_S2", "QUANT_RMS_COUNTS", "merge_windows", "still_rows", "BiasFit", "window_integrals",
    "inband_velocity", "Displacement", "AXIS_NAMES", "CROSS_END_S", "pattern_match", "analyse",
]
