"""Estimator 1, the log's timing: repeated and missing flow readings, gaps, repeated timestamps
and held range values, counted and located (findings without a held-out fit)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.diagnose.report import Finding, Window
from companion.diagnose.sensor.series import SensorSeries
from companion.diagnose.sensor.settings import SensorDiagnosisSettings
from companion.recordings.importers.common import ReadGrid, find_read_grid


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
