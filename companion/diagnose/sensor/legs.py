"""Estimator 4, displacement and legs (the paper's Fig. 6): the running sum of
rotation-compensated flow times range, cut into straight legs, whose lengths against the
documented one give the scale per axis (``LegScaleFit``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.diagnose.sensor.motions import DocumentedMotion
from companion.diagnose.sensor.numerics import moving_mean, window_integral
from companion.diagnose.sensor.series import SensorSeries
from companion.diagnose.sensor.settings import SensorDiagnosisSettings


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
    v = np.column_stack([np.gradient(moving_mean(p[:, i], n), t) for i in range(2)])
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
