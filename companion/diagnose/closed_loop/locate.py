"""Where and under what conditions a residual departs from the noise: sliding windows and bins.

``excess_windows`` marks sliding windows whose residual RMS is above a multiple of the channel's
noise scale and merges them into intervals; ``effect_windows`` does the same for the part of the
residual an effect explains (its contribution). ``conditions`` bins a residual by operating
condition (speed, tilt, rate, altitude) so a report can say *when* the model fails.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Interval:
    start_s: float
    end_s: float
    rms: float


def window_rms(t_s: np.ndarray, r: np.ndarray, width_s: float, step_s: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """RMS of ``r`` over sliding windows of ``width_s`` every ``step_s`` (rows sorted by time or
    not). Returns (start_s, end_s, rms, count) per window; windows with no rows are dropped."""
    if len(t_s) == 0:
        z = np.zeros(0)
        return z, z, z, z
    order = np.argsort(t_s, kind="stable")
    t = t_s[order]
    r2 = np.concatenate([[0.0], np.cumsum(np.nan_to_num(r[order]) ** 2)])
    starts = np.arange(t[0], max(t[-1] - width_s, t[0]) + step_s / 2, step_s)
    ends = starts + width_s
    i0 = np.searchsorted(t, starts, side="left")
    i1 = np.searchsorted(t, ends, side="left")
    n = i1 - i0
    ok = n > 0
    rms = np.sqrt((r2[i1] - r2[i0])[ok] / n[ok])
    return starts[ok], np.minimum(ends[ok], t[-1]), rms, n[ok].astype(float)


def merge(starts: np.ndarray, ends: np.ndarray, rms: np.ndarray, flag: np.ndarray, gap_s: float
          ) -> list[Interval]:
    """Merge flagged windows that overlap or lie within ``gap_s`` of each other."""
    out: list[Interval] = []
    for s, e, v in zip(starts[flag], ends[flag], rms[flag], strict=True):
        if out and s <= out[-1].end_s + gap_s:
            last = out[-1]
            out[-1] = Interval(last.start_s, max(last.end_s, float(e)), max(last.rms, float(v)))
        else:
            out.append(Interval(float(s), float(e), float(v)))
    return out


def excess_windows(t_s: np.ndarray, r: np.ndarray, sigma: float, *, factor: float = 2.0, width_s: float = 5.0,
                   step_s: float = 2.5, min_rows: int = 10) -> list[Interval]:
    """Intervals where the residual's sliding-window RMS exceeds ``factor`` x ``sigma``."""
    s, e, v, n = window_rms(t_s, r, width_s, step_s)
    return merge(s, e, v, (v > factor * sigma) & (n >= min_rows), gap_s=step_s)


def effect_windows(t_s: np.ndarray, contribution: np.ndarray, sigma: float, *, width_s: float = 5.0,
                   step_s: float = 2.5, max_intervals: int = 8) -> list[Interval]:
    """Where an effect's contribution to a residual is larger than the noise (``sigma``); when it
    never is, the single window where it is largest. At most ``max_intervals``, the largest."""
    s, e, v, _n = window_rms(t_s, contribution, width_s, step_s)
    if len(v) == 0:
        return []
    flag = v > sigma
    if not np.any(flag):
        flag = v == v.max()
    out = merge(s, e, v, flag, gap_s=width_s)
    if len(out) > max_intervals:
        out = sorted(sorted(out, key=lambda i: -i.rms)[:max_intervals], key=lambda i: i.start_s)
    return out


#: operating conditions a residual is binned by: name -> (unit, description)
CONDITIONS = {
    "speed_m_s": ("m/s", "horizontal speed"),
    "tilt_rad": ("rad", "tilt"),
    "rate_rad_s": ("rad/s", "body rate"),
    "altitude_m": ("m", "height"),
}


def conditions(values: dict[str, np.ndarray], contribution: np.ndarray, n_bins: int = 4) -> dict[str, object]:
    """Bin ``contribution`` (rows) by each condition (same rows) in quantile bins; return the
    condition under which it varies most, its bin edges and RMS per bin."""
    best: dict[str, object] = {}
    best_ratio = 0.0
    for name, x in values.items():
        ok = np.isfinite(x) & np.isfinite(contribution)
        if np.count_nonzero(ok) < 4 * n_bins:
            continue
        edges = np.unique(np.quantile(x[ok], np.linspace(0, 1, n_bins + 1)))
        if len(edges) < 3:
            continue
        idx = np.clip(np.searchsorted(edges, x[ok], side="right") - 1, 0, len(edges) - 2)
        rms = np.array([np.sqrt(np.mean(contribution[ok][idx == b] ** 2)) if np.any(idx == b) else 0.0
                        for b in range(len(edges) - 1)])
        lo = max(float(rms.min()), 1e-300)
        ratio = float(rms.max()) / lo
        if ratio > best_ratio:
            best_ratio = ratio
            best = {"condition": name, "unit": CONDITIONS.get(name, ("", ""))[0], "edges": edges.tolist(),
                    "rms": rms.tolist(), "max_over_min": ratio}
    return best
