"""Estimator 5, across recordings: the leg-based scales of several recordings pooled, with
leave-one-file-out held-out leg residuals."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.diagnose.sensor.diagnosis import SensorDiagnosis
from companion.diagnose.sensor.settings import SensorDiagnosisSettings


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
