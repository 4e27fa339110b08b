"""The sensor-only diagnosis's settings (units in the names) and its physical constants."""

from __future__ import annotations

import math
from dataclasses import dataclass

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
