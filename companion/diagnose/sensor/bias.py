"""Estimator 2, gyro bias from still segments: with no motion the flow sees only true rotation,
so the gyro's mean minus the flow's rotation rate is the bias."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.diagnose.sensor.numerics import moving_mean, runs
from companion.diagnose.sensor.settings import SensorDiagnosisSettings


def still_rows(t: np.ndarray, gyro: np.ndarray, cx: np.ndarray, cy: np.ndarray,
               settings: SensorDiagnosisSettings) -> np.ndarray:
    """Rows inside still segments: windowed gyro std (x, y) and net flow (counts per reading,
    windowed signed mean) below the settings' thresholds for at least ``still_min_s``."""
    if len(t) < 3:
        return np.zeros(len(t), dtype=bool)
    n = int(round(settings.still_window_s / float(np.median(np.diff(t)))))
    std = np.zeros(len(t))
    for i in range(2):
        m = moving_mean(gyro[:, i], n)
        std += np.maximum(moving_mean(gyro[:, i] ** 2, n) - m**2, 0.0)
    # net flow (signed mean): sensor noise averages out, a slow translation does not
    net = np.abs(moving_mean(cx, n)) + np.abs(moving_mean(cy, n))
    ok = (np.sqrt(std) < settings.still_gyro_std_rad_s) & (net < settings.still_flow_counts)
    out = np.zeros(len(t), dtype=bool)
    for a, b in runs(ok):
        if t[b - 1] - t[a] >= settings.still_min_s:
            out[a:b] = True
    return out


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
        std = np.sqrt(sum(np.maximum(moving_mean(gyro[:, i] ** 2, n) - moving_mean(gyro[:, i], n) ** 2, 0)
                          for i in range(2)))
        qstd = float(np.min(std[n:-n])) if len(std) > 2 * n else float(np.min(std))
    windows = [(float(t[a]), float(t[b - 1])) for a, b in runs(still)]
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
