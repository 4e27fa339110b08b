"""The three residual groups the diagnosis fits, each on the channels where its effects show.

| group | channels (unit) | candidate effects |
|---|---|---|
| attitude | ``attitude_roll``, ``attitude_pitch`` (rad) | ``attitude_dynamics``, ``attitude_delay`` |
| gyro | ``gyro_x``, ``gyro_y`` (rad/s) | ``gyro_bias`` |
| flow | ``flow_x``, ``flow_y`` (rad), ``force_x``, ``force_y`` (N) | ``flow_scale``, ``flow_yaw_misalignment``, |
| | | ``flow_delay``, ``flow_rotation_gain``, ``range_offset``, ``linear_drag``, ``wind_force`` |

The groups share no parameters and no inputs that another group's effects change (the flow
group uses the recorded attitude, not the gyro, for the rotation; the attitude group uses the
recorded command and attitude), so they are fitted and chosen independently.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.linalg import cholesky_banded, solve_banded

from companion.config import Config
from companion.diagnose import filters
from companion.diagnose.closed_loop.attitude import (
    OMEGA_P_MAX_RAD_S,
    OMEGA_P_RESOLVED_T,
    AttitudeProblem,
    restart_choice,
)
from companion.diagnose.closed_loop.channels import FlightData
from companion.diagnose.closed_loop.flowmodel import AXIS_SIGN, IDX, NOMINAL, PARAMS, FlowProblem
from companion.diagnose.closed_loop.select import Candidate, Group, block_meat, robust_std
from companion.diagnose.closed_loop.sizes import threshold
from companion.diagnose.closed_loop.wind import WindWindow, kernel_regressor, locate, null_pvalue

#: rows this far either side of a wind window count as "around" it for its held-out improvement (s)
AROUND_WINDOW_S = 5.0


#: frames after a gap of lost commands whose attitude residual is not used: the simulation restarts
#: there from the recorded attitude and the gyro's rate (s)
AFTER_COMMAND_GAP_S = 0.1
#: frames after a single lost (interpolated) command whose attitude residual is not used
COMMAND_SETTLE_FRAMES = 3
#: the longest attitude-loop delay fitted (s)
ATTITUDE_DELAY_MAX_S = 0.25
#: the attitude loop is assessed only with at least this much of usable attitude rows (s of frames):
#: fewer cannot pin a second-order loop and a delay (a DataFlash log's 10 Hz attitude target leaves
#: one row in 160 s)
ATTITUDE_MIN_S = 2.0
#: frames of a long flight the whole-frame delay that places the rows after lost commands is
#: taken from (``_loop_delay_frames``)
DELAY_PREFIT_FRAMES = 3000


def _runs(missing: np.ndarray, min_len: int) -> list[tuple[int, int]]:
    """(start, stop) of the runs of True in ``missing`` at least ``min_len`` long."""
    if not np.any(missing):
        return []
    x = np.concatenate([[False], missing, [False]]).astype(int)
    d = np.diff(x)
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True) if b - a >= min_len]


def attitude_rows(data: FlightData, delay_frames: int = 0) -> np.ndarray:
    """Frames whose attitude residual is used: the attitude was recorded there, and the
    simulation is not just coming out of a gap of lost commands (``AFTER_COMMAND_GAP_S``). A loop
    that answers ``delay_frames`` late answers a lost command that much later too: the frames left
    out after it are shifted on by as many."""
    rows = data.att_rec.copy()
    t = data.t_s
    # a single lost command is bridged by interpolation; the attitude's response to its error
    # has faded after a few frames
    lost = np.flatnonzero(~data.cmd_rec)
    for k in range(COMMAND_SETTLE_FRAMES + max(delay_frames, 0)):
        rows[np.minimum(lost + k, data.n - 1)] = False
    # after a run of lost commands, every frame timed from its first to AFTER_COMMAND_GAP_S past its
    # last (plus the delay): intervals of time, marked on the frames sorted by time at once (a
    # lossy hour has thousands of runs)
    runs = np.array(_runs(~data.cmd_rec, 2), dtype=np.int64).reshape(-1, 2)
    if len(runs):
        lo = t[runs[:, 0]]
        hi = t[runs[:, 1] - 1] + AFTER_COMMAND_GAP_S + max(delay_frames, 0) * data.frame_s
        order = np.argsort(t, kind="stable")
        ts = t[order]
        i0 = np.searchsorted(ts, lo, side="left")
        i1 = np.searchsorted(ts, hi, side="right")
        keep = i1 > i0
        d = np.zeros(len(t) + 1, dtype=np.int64)
        np.add.at(d, i0[keep], 1)
        np.add.at(d, i1[keep], -1)
        out = np.empty(len(t), dtype=bool)
        out[order] = np.cumsum(d[:-1]) > 0
        rows &= ~out
    return rows


def _loop_delay_frames(ap: AttitudeProblem, data: FlightData, omega_p: float, zeta: float) -> int:
    """Whole frames by which the attitude loop answers late (at least), for ``attitude_rows``: the
    whole-frame delay that best explains the attitude at the nominal dynamics, on the rows that
    delay leaves (a fixed point, a few rounds), plus one frame for a delay between frames. It only
    places the rows; the delay and the dynamics are fitted as effects later. A slower loop reads as
    a delay here, and its answer to a lost command does come later."""
    T = data.frame_s
    n_max = int(math.ceil(ATTITUDE_DELAY_MAX_S / T))
    if data.n > DELAY_PREFIT_FRAMES:  # a long flight: blocks spread over it are plenty for whole frames
        block = DELAY_PREFIT_FRAMES // 12
        starts = np.linspace(0, data.n - block, 12).round().astype(int)
        mask = np.zeros(data.n, dtype=bool)
        for a in starts:
            mask[a:a + block] = True
        data = data.take(mask)
        ap = AttitudeProblem(data, ap.restart)
    m = 0
    for _round in range(4):
        rows = attitude_rows(data, m)
        if not np.any(rows):
            return m
        costs = []
        for j in range(n_max + 1):
            e = ap.residual(omega_p, zeta, j * T, fit_mask=rows)[:, rows]
            costs.append(float(np.nansum(e * e)))
        j_best = int(np.argmin(costs))
        m_new = j_best + 1 if j_best else 0
        if m_new == m:
            break
        m = m_new
    return m


def attitude_group(data: FlightData, cfg: Config) -> tuple[Group, AttitudeProblem]:
    wp, z = cfg.airframe.omega_p_rad_s, cfg.airframe.zeta
    choice = restart_choice(data, wp, z)
    if choice.note:
        data.notes.append(choice.note)
    ap = AttitudeProblem(data, choice.restart)
    T = data.frame_s
    rows = attitude_rows(data)
    if np.any(~data.cmd_rec) and np.any(rows):
        rows = attitude_rows(data, _loop_delay_frames(ap, data, wp, z))
    n_rows = int(np.count_nonzero(rows))
    assessed = n_rows * T >= ATTITUDE_MIN_S
    if not assessed:
        data.notes.append(f"the attitude loop is not assessed: {n_rows} of {data.n} frames have a recorded attitude "
                          f"answering known commands (the others are lost, or bridged between commands logged slower "
                          f"than the frames, and a lost command's answer is not known); attitude_dynamics and "
                          f"attitude_delay are not tried")
    if not np.any(rows):
        rows = np.ones(data.n, dtype=bool)
    ap.rows = rows

    def residuals(p: np.ndarray) -> list[np.ndarray]:
        e = ap.residual(float(p[0]), float(p[1]), float(p[2]), fit_mask=rows)
        return [e[0][rows], e[1][rows]]

    tr = data.t_s[rows]
    g = Group(
        name="attitude", params=("omega_p", "zeta", "delay"), nominal=np.array([wp, z, 0.0]),
        timing=("delay", timing_sigma_s(data, "flow", "attitude")),
        steps=np.array([0.005 * wp, 0.005, 0.0005]), lower=np.array([0.3, 0.05, -T]),
        upper=np.array([OMEGA_P_MAX_RAD_S, 5.0, ATTITUDE_DELAY_MAX_S]), channels=("attitude_roll", "attitude_pitch"),
        units=("rad", "rad"),
        floors=(1e-4, 1e-4), residuals=residuals, row_times=[tr, tr], coloured=(True, True),
        candidates=[Candidate("attitude_dynamics", ("omega_p", "zeta"),
                              matters=threshold("attitude_dynamics", {"omega_p": wp, "zeta": z}),
                              resolution_upper=("omega_p",) if OMEGA_P_MAX_RAD_S * T >= OMEGA_P_RESOLVED_T else ()),
                    Candidate("attitude_delay", ("delay",), matters=threshold("attitude_delay"))] if assessed else [])
    return g, ap


class GyroProblem:
    """Gyro against the attitude in integrated form (the paper's per-axis kinematics,
    angle' = rate): over each interval between two frames where the attitude was recorded, the
    attitude change divided by the interval, minus the trapezoidal mean of the gyro over it.
    The command changes at the frames, so within a frame the rate is smooth and the trapezoid is
    exact to (T^2/12) rate'', far below a gyro's resolution; a derivative of the attitude would
    not be (its second derivative jumps at every frame). With the attitude at every frame the
    intervals are the frames; where it was lost or is logged slower, they span several frames
    (at most ``MAX_SPAN_FRAMES``). Rows at the intervals' midpoints."""

    MAX_SPAN_FRAMES = 10

    def __init__(self, data: FlightData) -> None:
        t = data.t_s
        seg = data.seg
        have = np.flatnonzero(data.att_rec)
        if len(have) < 2:
            have = np.arange(data.n)
        a, b = have[:-1], have[1:]
        ok = (seg[a] == seg[b]) & (b - a <= self.MAX_SPAN_FRAMES)
        if np.mean(data.gyro_rec) >= 0.75:  # a gyro at the frame rate: its lost samples are not guessed at,
            # at the interval's ends or within it (a bridged sample's error, 0.12 rad/s over a 3-frame
            # interval of --seed 1 gen_0169 against a 0.01 rad/s noise, is no noise of the model's)
            lost = filters.running_count(~data.gyro_rec)
            ok &= lost[b + 1] == lost[a]
        a, b = a[ok], b[ok]
        self.k = b
        self.k_prev = a
        dt = t[b] - t[a]
        self.t_s = 0.5 * (t[b] + t[a])
        ang = np.stack([data.roll_rad, data.pitch_rad])
        gyr = np.stack([data.gyro_x_rad_s, data.gyro_y_rad_s])
        cg = np.zeros_like(gyr)
        inc = 0.5 * (gyr[:, 1:] + gyr[:, :-1]) * np.diff(t)
        inc[:, np.diff(seg) != 0] = 0.0
        cg[:, 1:] = np.cumsum(inc, axis=1)
        self.rate = (ang[:, b] - ang[:, a]) / dt  # mean body rate over the interval from the attitude
        self.gyro = (cg[:, b] - cg[:, a]) / dt
        self.angle = 0.5 * (ang[:, b] + ang[:, a])
        # a gyro low-passed with time constant tau reads g with omega = g + tau g': over the
        # interval, the body rate is the gyro's mean plus tau (g_b - g_a) / dt. The regressor comes
        # from the gyro alone, so an attitude estimate's noise (in ``rate`` only) cannot bias tau
        self.dgyro = (gyr[:, b] - gyr[:, a]) / dt
        # where the spline through the gyro's samples at their own times (``channels.gyro_spline``)
        # covers every frame of the interval: its integral and its values at the interval's ends.
        # Why: the gyro put on the frames by linear interpolation, from samples taken a few ms
        # before them, answers a command's kink late (the chord of a bent curve), and that
        # correlates with g': on noise-free generator flights with the IMU sampled 1.5-1.8 ms
        # ahead of the attitude (seeds 63 and 284), tau read 0.74 and 0.73 ms long, 0.27 ms of it
        # more than the attitude stamps' rounding explains; through the spline, 0.38 and 0.44 ms,
        # what that rounding gives (0.44 and 0.46 ms; ``timing_sigma_s`` is its uncertainty). A
        # gyro logged slower than the frames keeps the linear form: ArduCopter's DataFlash log
        # (IMU at 25 Hz, frames at 50 Hz; the SITL flight_c0.BIN) read 8.0 ms through it and 6.8
        # ms through the spline, where the same vehicle's tlogs read 10.2 and 12.1 ms
        spl = [data.gyro_angle_x_rad, data.gyro_angle_y_rad, data.gyro_fine_x_rad_s, data.gyro_fine_y_rad_s]
        if all(s is not None for s in spl) and np.mean(data.gyro_rec) >= 0.75:
            S = np.stack(spl)  # type: ignore[arg-type]
            gap = filters.running_count(~np.all(np.isfinite(S), axis=0))
            covered = gap[b + 1] - gap[a] == 0  # frames a..b all on one run of the spline
            self.gyro = np.where(covered, (S[:2, b] - S[:2, a]) / dt, self.gyro)
            self.dgyro = np.where(covered, (S[2:, b] - S[2:, a]) / dt, self.dgyro)
        self.r = self.gyro - self.rate
        self.dt_s = dt
        #: per axis, the filter the group's rows go through, and the noise model it is made from
        self.whiten, self.noise = gyro_whitener(self)
        #: the lag the nominal model carries: the stamps' timing (``_gyro_stamp_alignment``)
        self.timing_offset_s = 0.0


#: frames between a lag interval's ends and the gyro samples its instruments are made of
#: (``lag_by_instruments``): the spline's value at a frame leans on the two samples either side
IV_GAP_FRAMES = 3
#: the first stage's F statistic under which the instruments are too weak to use (the usual rule)
IV_MIN_F = 19.93


@dataclass
class LagEstimate:
    """The gyro lag by instrumental variables (``lag_by_instruments``)."""

    tau_s: float
    sd_s: float  #: the sandwich's, with the stamps' timing in quadrature
    first_stage_f: float  #: the weaker axis's


def lag_by_instruments(gp: GyroProblem, data: FlightData, block_s: float, timing_s: float) -> LagEstimate | None:
    """The gyro lag's two-stage least squares: the lag regressor (the gyro's change over each
    interval) replaced by its projection on two instruments, the gyro's change over a frame
    ``IV_GAP_FRAMES`` before the interval and one as far after it, which share no sample with it;
    per axis, with the gyro's bias; covariance by the cluster-robust sandwich over time blocks of
    ``block_s`` (adjacent blocks' cross terms at half weight, as ``Selector._cov``), plus
    ``timing_s`` squared. None when the gyro is not recorded at the frame rate, when fewer than
    100 rows have instruments, or when the instruments are weak (first-stage F under ``IV_MIN_F``
    on either axis).

    Why: the regressor is made of the gyro's own noisy samples, so least squares is attenuated
    towards zero by the share of its variance that is noise (errors in variables), and in a hover,
    where the gyro's change over a frame is mostly noise, by far more than its sigma: on the
    generalisation matrix gen_0278 (a hover, 2.9 mrad/s gyro noise) read 12.4 +- 0.86 ms for 47.8
    ms. The instruments move with the rate (the loop's motion spans many frames) but not with the
    noise of the interval's own samples, so the estimate is not attenuated; its sigma is larger,
    as it should be. The lag is chosen by least squares (the held-out test of ``Selector``), and
    reported from here."""
    if np.mean(data.gyro_rec) < 0.75:
        return None
    n = data.n
    a, b = gp.k_prev, gp.k
    lo, hi = a - IV_GAP_FRAMES - 1, b + IV_GAP_FRAMES + 1
    ok = (lo >= 0) & (hi < n)
    ok[ok] &= (data.seg[lo[ok]] == data.seg[a[ok]]) & (data.seg[hi[ok]] == data.seg[b[ok]])
    ok[ok] &= data.gyro_rec[lo[ok]] & data.gyro_rec[lo[ok] + 1] & data.gyro_rec[hi[ok]] & data.gyro_rec[hi[ok] - 1]
    t = data.t_s
    gyr = np.stack([data.gyro_x_rad_s, data.gyro_y_rad_s])
    rows = np.flatnonzero(ok)
    if len(rows) < 100:
        return None
    l0, l1, h0, h1 = lo[rows], lo[rows] + 1, hi[rows] - 1, hi[rows]
    y_all, x_all, xh_all, time_all = [], [], [], []
    f_min = math.inf
    for i in (0, 1):
        g = gyr[i]
        z = np.stack([(g[l1] - g[l0]) / (t[l1] - t[l0]), (g[h1] - g[h0]) / (t[h1] - t[h0]),
                      np.ones(len(rows))], axis=1)
        x = gp.dgyro[i][rows]
        y = gp.rate[i][rows] - gp.gyro[i][rows]
        fin = np.all(np.isfinite(z), axis=1) & np.isfinite(x) & np.isfinite(y)
        z, x, y = z[fin], x[fin], y[fin]
        if len(x) < 100:
            return None
        coef, *_ = np.linalg.lstsq(z, x, rcond=None)
        xh = z @ coef
        ss_res = float(np.sum((x - xh) ** 2))
        ss_tot = float(np.sum((x - x.mean()) ** 2))
        f = ((ss_tot - ss_res) / 2.0) / (ss_res / max(len(x) - 3, 1)) if ss_res > 0 else math.inf
        f_min = min(f_min, f)
        # each axis weighted by its residual's scale (least squares' residual about its own fit)
        c_ols, *_ = np.linalg.lstsq(np.stack([x, np.ones_like(x)], axis=1), y, rcond=None)
        w = 1.0 / max(robust_std(y - c_ols[0] * x - c_ols[1]), 1e-12)
        y_all.append(w * y)
        x_all.append(np.stack([w * x, w * (i == 0) * np.ones_like(x), w * (i == 1) * np.ones_like(x)], axis=1))
        xh_all.append(np.stack([w * xh, w * (i == 0) * np.ones_like(x), w * (i == 1) * np.ones_like(x)], axis=1))
        time_all.append(gp.t_s[rows][fin])
    if not f_min >= IV_MIN_F:
        return None
    Y, X, XH = np.concatenate(y_all), np.concatenate(x_all), np.concatenate(xh_all)
    A = XH.T @ X
    beta = np.linalg.solve(A, XH.T @ Y)
    u = Y - X @ beta
    ts = np.concatenate(time_all)
    blk = np.floor((ts - ts.min()) / block_s).astype(int)
    sb = np.zeros((blk.max() + 1, 3))
    np.add.at(sb, blk, XH * u[:, None])
    S = block_meat(sb)
    Ai = np.linalg.inv(A)
    B = len(sb)
    cov = Ai @ S @ Ai.T * B / max(B - 3, 1)
    sd = math.sqrt(max(float(cov[0, 0]), 0.0) + timing_s ** 2)
    return LagEstimate(tau_s=float(beta[0]), sd_s=sd, first_stage_f=float(f_min))


def timing_sigma_s(data: FlightData, a: str, b: str) -> float:
    """How well the recording's time stamps fix the relative timing of streams ``a`` and ``b``
    (s, 1 sigma): each stream's stamps are rounded (or truncated) to their step
    (``channels.stamp_step_s``) at a phase against the clock's ticks that stays put over a flight
    when the sampling is regular, so each is off by a constant uniform over one step: sigma
    step / sqrt(12) each, independent. Two 1 ms streams: 0.41 ms; 1 ms against 1 us: 0.29 ms. A
    delay or a lag between them cannot be known better, however long the flight (``Group.timing``)."""
    steps = [data.stamp_step_s.get(a, 0.0), data.stamp_step_s.get(b, 0.0)]
    return math.hypot(*steps) / math.sqrt(12.0)


#: the flow's timing against the rotation it is compared with is known to this share of a flow
#: frame, however well stamped (``flow_timing_sigma_s``)
FLOW_FRAME_TIMING_SHARE = 0.05


def flow_timing_sigma_s(data: FlightData, rotation_stream: str | None) -> float:
    """How well the flow's timing against its rotation source is known (s, 1 sigma): the stamps'
    share (``timing_sigma_s``) and a share of the flow frame, ``FLOW_FRAME_TIMING_SHARE`` x the
    frame period, in quadrature.

    Why the frame's share: a frame's increment is the scene's turn over the frame, compared with a
    rotation reconstructed between the rotation source's samples, and where in the frame the
    sensor's integration sits is the sensor's own business. How the reconstruction is made moves
    a fitted flow delay by a fraction of a frame that no length of flight removes: on the 300
    generated flights of the generalisation matrix (20 ms frames), the gyro integrated through a
    C2 cubic spline instead of PCHIP moved the delay by up to 1.9 ms (mean 1.0 ms), and the
    fitted delays missed the truth by a median 0.8 ms (up to 3 ms) while their statistical sigma
    was 0.03-0.5 ms (40 % of pulls within 2 sigma); a clean flight (no effect, 0.8 ms stamp jitter)
    gave a 3.4 +- 0.57 ms delay. With 1 ms at 50 Hz, every one of the matrix's 21 named flow
    delays lies within 2 sigma of its truth (median |pull| 0.66)."""
    stamps = timing_sigma_s(data, "flow", rotation_stream) if rotation_stream else 0.0
    return math.hypot(stamps, FLOW_FRAME_TIMING_SHARE * data.frame_s)


@dataclass
class GyroNoise:
    """The gyro residual's noise model per axis (``gyro_whitener``)."""

    attitude_white_rad: float  #: the attitude's white noise, sigma (rad)
    rest_rad: float  #: the rest of an interval's angle noise, sigma over a median interval (rad)


#: the span (s) over which ``gyro_whitener`` measures the part of the gyro residual's noise that is
#: not the attitude's white noise
GYRO_NOISE_SPAN_S = 0.5


def gyro_whitener(gp: GyroProblem) -> tuple[list[Callable[[np.ndarray], np.ndarray]], list[GyroNoise]]:
    """Per axis, the filter that whitens the gyro residual's rows (``GyroProblem``), and the noise
    model it is made from: an interval's residual is the change of the attitude's white noise
    (sigma_a) over it divided by its length, plus noise of its own (the gyro's, the attitude's
    coloured noise; white, its angle variance growing with the interval's length). So two intervals
    that share an end (``k_prev`` of one is ``k`` of the other) have a covariance of
    -sigma_a^2 / (dt_1 dt_2): a tridiagonal covariance C. Its two variances are measured on the
    nominal residual e in angle units, robustly (1.4826 x MAD about the median, so a bias does not
    count): D1 the variance of one interval's e, DK that of the sum of K adjacent ones spanning
    ``GYRO_NOISE_SPAN_S``; by the model D1 = 2 sigma_a^2 + rest^2 and DK = 2 sigma_a^2 + K rest^2.
    The rest is thus whatever grows over half a second, the model's white part and whatever slow
    error the model leaves out as well (a coloured attitude, bridged samples, the stamps' timing),
    and the filter's memory is no longer than that rest allows. The filter is
    the inverse of C's banded Cholesky factor (the innovations), scaled back to rad/s by the
    factor's median diagonal, so a row's unit and size stay about those of an interval's
    innovation; the whole is least squares weighted by C (generalised least squares).

    Why: an attitude estimate's white noise, differenced over 20 ms, is most of the residual (0.3
    mrad gives 21 mrad/s) and it is blue: nearly all of it at the frame rate, where a gyro lag's or
    bias's signature has little. Least squares weighs every frequency alike, and the lag's share of
    that residual is small however sure its fit. On the generalisation matrix's --seed 1 gen_0240
    (a 45 s hover, a 49.5 ms lag, 0.3 mrad of attitude noise) the lag lowered the held-out residual
    by 3.1 % (held-out z 1.9) and was turned down; on the whitened rows by 14 % (z 7.0), and it is
    named (51.4 +- 1.9 ms). Without white attitude noise (sigma_a^2 nil) C is diagonal and the rows
    are only weighed by their interval's length."""
    n = len(gp.k)
    filters_: list[Callable[[np.ndarray], np.ndarray]] = []
    noise: list[GyroNoise] = []
    if n < 3:
        return [lambda r: r, lambda r: r], [GyroNoise(0.0, 0.0), GyroNoise(0.0, 0.0)]
    dt = gp.dt_s
    adj = gp.k_prev[1:] == gp.k[:-1]
    ref = float(np.median(dt))
    # the residual's angle over K intervals in a row: K spans GYRO_NOISE_SPAN_S (at least 2)
    K = max(2, int(round(GYRO_NOISE_SPAN_S / ref)))
    brk = filters.running_count(~adj)  # breaks before each row
    for i in (0, 1):
        e = (gp.gyro[i] - gp.rate[i]) * dt  # the nominal residual in angle units (rad per interval)
        fin = np.isfinite(e)
        Y = np.concatenate([[0.0], np.cumsum(np.where(fin, e, 0.0))])  # Y[j]: the sum of rows before j
        bad = filters.running_count(~fin)
        j = np.arange(n - K + 1)
        whole = (brk[j + K - 1] == brk[j]) & (bad[j + K] == bad[j])  # K adjacent finite rows from j
        one = fin & (np.abs(dt - ref) < 0.25 * ref)
        if np.count_nonzero(whole) < 20 or np.count_nonzero(one) < 20:
            filters_.append(lambda r: r)
            noise.append(GyroNoise(0.0, 0.0))
            continue
        d1 = robust_std(e[one]) ** 2
        dk = robust_std((Y[j + K] - Y[j])[whole]) ** 2
        rest2 = max((dk - d1) / (K - 1), 1e-3 * d1, 1e-30)  # kept off nil: C stays well conditioned
        sa2 = max(0.5 * (d1 - rest2), 0.0)
        var = (2.0 * sa2 + rest2 * dt / ref) / dt ** 2
        off = np.where(adj, -sa2 / (dt[:-1] * dt[1:]), 0.0)
        ab = np.zeros((2, n))
        ab[0, 1:] = off
        ab[1] = var
        U = cholesky_banded(ab, lower=False)  # C = U' U
        low = np.zeros((2, n))
        low[0] = U[1]
        low[1, :-1] = U[0, 1:]
        scale = float(np.median(U[1]))

        def apply(r: np.ndarray, low: np.ndarray = low, scale: float = scale) -> np.ndarray:
            out = np.full(r.shape, np.nan)
            fin = np.isfinite(r)
            if np.all(fin):
                return solve_banded((1, 0), low, r) * scale
            out[fin] = solve_banded((1, 0), low, np.where(fin, r, 0.0))[fin] * scale
            return out

        filters_.append(apply)
        noise.append(GyroNoise(math.sqrt(sa2), math.sqrt(rest2)))
    return filters_, noise


def gyro_group(data: FlightData) -> tuple[Group, GyroProblem]:
    gp = GyroProblem(data)
    whiten = gp.whiten

    def residuals(p: np.ndarray) -> list[np.ndarray]:
        r = gp.gyro + p[2] * gp.dgyro - gp.rate
        return [whiten[0](r[0] - p[0]), whiten[1](r[1] - p[1])]

    g = Group(
        name="gyro", params=("bias_x", "bias_y", "tau"), nominal=np.zeros(3), steps=np.array([1e-4, 1e-4, 5e-4]),
        timing=("tau", timing_sigma_s(data, "gyro", "attitude")),
        lower=np.array([-2.0, -2.0, 0.0]), upper=np.array([2.0, 2.0, 0.3]), channels=("gyro_x", "gyro_y"),
        units=("rad/s", "rad/s"), floors=(max(data.gyro_resolution_rad_s, 1e-5),) * 2, residuals=residuals,
        # coloured: the whitened rows keep what their noise model leaves out (an estimator's attitude
        # error is not white: ArduCopter SITL flight C0's whitened gyro residual has lag-1 to 3
        # correlations of 0.31, 0.23 and 0.31), so a stretch is judged against the typical window too
        row_times=[gp.t_s, gp.t_s], coloured=(True, True),
        candidates=[Candidate("gyro_bias", ("bias_x", "bias_y"), matters=threshold("gyro_bias")),
                    Candidate("gyro_lag", ("tau",), physical=_positive_lag, matters=threshold("gyro_lag"))],
        linear=("bias_x", "bias_y", "tau"))
    bound = STAMP_ALIGN_SIGMAS * timing_sigma_s(data, "gyro", "attitude")
    g.nominal[2] = gp.timing_offset_s = _gyro_stamp_alignment(g, bound)
    g.lower[2] = min(0.0, gp.timing_offset_s)
    if abs(gp.timing_offset_s) >= 1e-5:
        data.notes.append(f"the gyro's timing against the attitude aligned by {1e3 * gp.timing_offset_s:+.2f} ms (the "
                          f"stamps leave +-{1e3 * bound:.2f} ms uncertain): the nominal model's gyro lag")
    return g, gp


def _gyro_stamp_alignment(g: Group, bound_s: float) -> float:
    """The gyro lag, within +-``bound_s``, that the gyro channels ask for at the nominal model:
    least squares of the lag with both axes' biases on the whitened rows (the residuals are linear
    in all three), clipped.

    Why, as for the flow (``_stamp_alignment``): a timing error between the gyro's stamps and the
    attitude's is a lag (either sign), which stamps in whole ms leave uncertain by 0.29 ms. Through
    the whitened rows (``gyro_whitener``) a residual that slow stands far above its noise: on the
    generalisation matrix's clean gen_0177 (no attitude or gyro noise, attitude stamps in ms) a
    -0.27 ms lag left the gyro channels five unexplained entries (a lag over the whole flight, four
    "local disturbances" where it turned most). A lag that small is not a finding (under 2 ms,
    ``sizes``); the nominal model carries it, and a gyro lag is judged from it."""
    if not bound_s > 0:
        return 0.0
    r0 = g.residuals(g.nominal)
    cols = []
    for j in (2, 0, 1):
        p = g.nominal.copy()
        p[j] += 1.0
        cols.append(np.concatenate([b - a for a, b in zip(r0, g.residuals(p), strict=True)]))
    X, y = np.stack(cols, axis=1), np.concatenate(r0)
    ok = np.all(np.isfinite(X), axis=1) & np.isfinite(y)
    if np.count_nonzero(ok) < 10:
        return 0.0
    step = np.linalg.lstsq(X[ok], -y[ok], rcond=None)[0]
    return float(np.clip(g.nominal[2] + step[0], -bound_s, bound_s))


class FlowGroupState:
    """The flow group's wind window, found by search (``wind.locate``) and kept between fits."""

    def __init__(self, fp: FlowProblem) -> None:
        self.fp = fp
        self.window: WindWindow | None = None
        #: rows per flow channel (the kept windows' frames after the whitening filter's start-up)
        self.n_flow_rows = fp.flow.idx.size
        #: the filter each flow channel's window rows go through (``ar_whitener``), per axis
        self.whiten: list[Callable[[np.ndarray], np.ndarray]] = [lambda r: r, lambda r: r]
        #: the flow's rotation source (``ROTATION_SOURCES``) and the note that said why, when chosen
        self.source = "attitude"
        self.source_note: str | None = None
        #: whether the flow channels' translation takes the accelerometer's force too (``flow_group``)
        self.accelerometer = False
        self.accel_note: str | None = None
        #: the gyro lag undone in the flow's rotation (``_flow_lag``) and the note that said so
        self.lag_s = 0.0
        self.lag_note: str | None = None
        #: the flow delay the group's nominal model carries: the flow's timing against its
        #: rotation source, aligned within what the stamps leave uncertain (``_stamp_alignment``)
        self.timing_offset_s = 0.0
        #: ``null_pvalue`` by the parameters it reads (the selector's comparisons ask for the same
        #: model without wind from models that differ only in the wind)
        self._null_p: dict[bytes, float] = {}

    @property
    def start_end(self) -> tuple[float, float]:
        if self.window is None:
            return math.nan, math.nan
        return self.window.start_s, self.window.end_s

    def as_dict(self) -> dict[str, float]:
        """The window for the report: a force on from the first force window (or to the last),
        or from a time that its uncertainty does not tell from it (2 sigma), is on from the first
        usable frame (to the last), as CONVENTIONS.md states. When no force window could be
        formed before the first one (lost telemetry), the onset was not seen: the window is still
        said to start at the first frame, its uncertainty then spans the unseen stretch."""
        s, e = self.start_end
        w = self.window
        W = self.fp.force.idx
        start_sd = w.start_sd if w else math.nan
        end_sd = w.end_sd if w else math.nan
        if w is not None and len(W):
            t = self.fp.t
            fp = self.fp
            tol = (fp.h + 1) * fp.data.frame_s
            segs = fp.data.segments()
            first = segs[0][0] + fp.h + fp.L2  # the first and last boundaries a flight can have
            last = segs[-1][1] - 1 - fp.h - fp.L2
            if s <= t[W[0, 0]] + max(tol, 2.0 * np.nan_to_num(start_sd)):
                if W[0, 0] > first:  # no force window before this one (lost telemetry)
                    start_sd = max(np.nan_to_num(start_sd), 0.5 * (t[W[0, 0]] - t[0]))
                s = float(t[0])
            if e >= t[W[-1, 1]] - max(tol, 2.0 * np.nan_to_num(end_sd)):
                if W[-1, 1] < last - fp.L2:
                    end_sd = max(np.nan_to_num(end_sd), 0.5 * (t[-1] - t[W[-1, 1]]))
                e = float(t[-1])
        return {"start_s": s, "end_s": e, "start_sd": start_sd, "end_sd": end_sd}

    def search(self, p: np.ndarray, masks: list[np.ndarray] | None) -> list[np.ndarray]:
        """Locate the wind window on the rows of ``masks`` from the force residual at p without
        wind; returns d(residual)/d(fx, fy) per channel (zero on the flow channels)."""
        q = p.copy()
        q[IDX["fx"]] = q[IDX["fy"]] = 0.0
        W = self.fp.force.idx
        nf = self.n_flow_rows
        self.window = None
        cols = [np.zeros((nf, 2)), np.zeros((nf, 2)), np.zeros((len(W), 2)), np.zeros((len(W), 2))]
        if len(W) == 0:
            return cols
        e = self.fp.force_residual(q)
        m = None if masks is None else (masks[2] & masks[3])
        self.window = locate(e, self.fp.t, W[:, 0], W[:, 1], self.fp.h, m)
        if self.window is not None:
            x = kernel_regressor(self.fp.t, W[:, 0], W[:, 1], self.fp.h, self.window.start_s, self.window.end_s)
            cols[2][:, 0] = -x  # the force residual is (unexplained force) - F x
            cols[3][:, 1] = -x
        return cols


    def null_pvalue(self, p_with: np.ndarray, p_without: np.ndarray) -> float:
        """Tail probability of the wind search's statistic under no wind, calibrated on this
        recording's force residual (``wind.null_pvalue``), with the other effects as in ``p_with``."""
        del p_without
        W = self.fp.force.idx
        if len(W) < 4:
            return 1.0
        q = p_with.copy()
        q[IDX["fx"]] = q[IDX["fy"]] = 0.0
        key = q.tobytes()
        if key not in self._null_p:
            e = self.fp.force_residual(q)
            self._null_p[key] = null_pvalue(e, self.fp.t, W[:, 0], W[:, 1], seed=len(W))
        return self._null_p[key]

    def active_rows(self) -> list[np.ndarray] | None:
        """Rows inside and around the current wind window: none on the flow channels, the force
        windows that overlap [start - AROUND_WINDOW_S, end + AROUND_WINDOW_S]."""
        s, e = self.start_end
        if not (math.isfinite(s) and math.isfinite(e)):
            return None
        nf = self.n_flow_rows
        f0, f1 = self.fp.force.t_start_s, self.fp.force.t_end_s
        on = (f1 >= s - AROUND_WINDOW_S) & (f0 <= e + AROUND_WINDOW_S)
        none = np.zeros(nf, dtype=bool)
        return [none, none, on, on]


#: the accelerometer checks the flow group's effects (``accelerometer_z``) with at least this many
#: inertial rows (force windows that accelerate), in time blocks of this long (s)
ACCEL_CHECK_MIN_ROWS = 8
ACCEL_CHECK_BLOCK_S = 10.0


def accelerometer_z(fp: FlowProblem, p_with: np.ndarray, p_without: np.ndarray) -> tuple[float, int]:
    """The accelerometer's verdict on the change from ``p_without`` to ``p_with``, as a normal z,
    and its rows (``FlowProblem.inertial_residual``: the flow's odometry against the accelerometer's
    strapdown velocity over the windows that accelerate); NaN, 0 with fewer than
    ``ACCEL_CHECK_MIN_ROWS`` rows or where the two models read the same there (a force effect).

    The fit does not use these rows, so they are held out as a whole. With d = e_without - e_with,
    the change the effect makes there, the gain G = sum(e_without^2 - e_with^2) / sigma^2 is
    +sum(d^2) / sigma^2 + 2 sum(d e_with) / sigma^2 when the effect is real (e_with is noise) and
    -sum(d^2) / sigma^2 + 2 sum(d e_without) / sigma^2 when it is not (e_without is noise). Its
    noise's variance V is taken over time blocks (``block_meat``, as ``Selector.heldout_z`` does)
    from d times whichever residual is the noise: the smaller of the two estimates (the other holds
    d itself, which would bound |z| by about half the root of the number of blocks); sigma per axis
    likewise, the smaller robust scale. z = G / (2 sqrt(V)): far above 0 confirms the effect, far
    below contradicts it."""
    a = fp.inertial_residual(p_with)
    if a.shape[1] < ACCEL_CHECK_MIN_ROWS:
        return math.nan, 0
    b = fp.inertial_residual(p_without)
    d = b - a
    sigma = np.array([max(min(robust_std(x), robust_std(y)), 1e-4) for x, y in zip(a, b, strict=True)])[:, None]
    if not np.any(np.abs(d) > 1e-3 * sigma):
        return math.nan, 0
    gain = float(np.sum((b * b - a * a) / sigma ** 2))
    t = 0.5 * (fp.force.t_start_s + fp.force.t_end_s)[fp.inertial_rows]
    blk = np.floor((t - t.min()) / ACCEL_CHECK_BLOCK_S).astype(int)
    v = min(float(block_meat(np.bincount(blk, weights=np.sum(d * e / sigma ** 2, axis=0)))) for e in (a, b))
    if not v > 0.0:
        return math.nan, 0
    return gain / (2.0 * math.sqrt(v)), a.shape[1]


def _positive_lag(p: dict[str, float]) -> str | None:
    return "a gyro ahead of the attitude (negative lag) is not a filter" if p["tau"] <= 0 else None


def _positive_form_drag(p: dict[str, float]) -> str | None:
    return "a negative form drag (the air pushing the vehicle along) is not physical" if p["c"] <= 0 else None


def _causal_flow_delay(p: dict[str, float]) -> str | None:
    """A flow that leads the rotation it sees is not a flow delay: the sensor cannot report motion
    before it happens. What fits a negative delay is a late rotation source (a lagging gyro or
    attitude estimate, or their time stamps), which the unexplained section reports instead."""
    if p["delay"] < 0:
        return (f"a negative flow delay ({1e3 * p['delay']:.1f} ms: the flow leading the rotation it sees) is not "
                "physical; the rotation source is late instead")
    return None


def _positive_drag(p: dict[str, float]) -> str | None:
    return "a negative drag (the air pushing the vehicle along) is not physical" if p["b"] <= 0 else None


#: the widest flow scale and rotation gain a flow sensor can physically have: a lens, a surface
#: texture or a mis-set FLOW_FXSCALER (ArduPilot: 0.2-1.8 x) moves the scale by tens of per cent, a
#: mount or the sampling of rates the rotation gain likewise (ArduCopter SITL: 1.1-1.2). A fit
#: beyond it is a flow channel whose modelled translation the fit is shrinking (a scale far above
#: 1 together with a rotation gain that keeps the rotation: the translation the recorded tilt
#: predicts does not match the flow's, e.g. under gusts), not a sensor
PLAUSIBLE_FLOW_GAIN = (0.5, 2.0)


def _plausible_scale(p: dict[str, float]) -> str | None:
    lo, hi = PLAUSIBLE_FLOW_GAIN
    bad = [f"{k} = {p[k]:.3g}" for k in ("scale_x", "scale_y") if not lo <= p[k] <= hi]
    if bad:
        return (f"a flow scale of {', '.join(bad)} (a sensor reading under half or over twice the nominal Q) is "
                f"beyond any lens or texture error: something else is at work, or q_rad_per_count is not this "
                f"sensor's")
    return None


def _plausible_gain(p: dict[str, float]) -> str | None:
    lo, hi = PLAUSIBLE_FLOW_GAIN
    if not lo <= p["gain"] <= hi:
        return (f"a flow that sees {p['gain']:.3g} times the rotation is beyond any mount or sampling effect: "
                f"something else is at work")
    return None


#: frames a gap run of the gyro is widened by, at most, to ends where the attitude was recorded
#: (``rebridge_gyro_gaps``)
GAP_ATTITUDE_REACH_FRAMES = 3
#: fewest comparisons an error variance of ``rebridge_gyro_gaps`` is taken from
GAP_MIN_SAMPLES = 30
#: most span starts an error variance of ``rebridge_gyro_gaps`` is taken from (evenly spread: a
#: mean square needs a few thousand, and a lossy hour has runs of dozens of lengths)
GAP_MAX_SAMPLES = 20000


def _spline_bridge(t: np.ndarray, y: np.ndarray, i: np.ndarray, j: np.ndarray, tau_s: float) -> np.ndarray:
    """The increment from frame i to frame j (arrays) of ``channels.gyro_spline``'s cubic through
    the samples y at frames i - 1, i, j, j + 1 alone (the samples between i and j taken as lost):
    Hermite on [t_i, t_j] with slopes from ``np.gradient``'s second-order rule on uneven steps, its
    integral H (y_i + y_j) / 2 + H^2 (d_i - d_j) / 12, plus ``tau_s`` (y_j - y_i) for a lag undone."""
    def slope(k0: np.ndarray, k1: np.ndarray, k2: np.ndarray) -> np.ndarray:
        h1, h2 = t[k1] - t[k0], t[k2] - t[k1]
        return (h1 * h1 * y[k2] - h2 * h2 * y[k0] + (h2 * h2 - h1 * h1) * y[k1]) / (h1 * h2 * (h1 + h2))
    H = t[j] - t[i]
    di, dj = slope(i - 1, i, j), slope(i, j, j + 1)
    return H * 0.5 * (y[i] + y[j]) + H * H * (di - dj) / 12.0 + tau_s * (y[j] - y[i])


def _trapezoid_bridge(t: np.ndarray, y: np.ndarray, i: np.ndarray, j: np.ndarray, tau_s: float) -> np.ndarray:
    """The increment from frame i to frame j (arrays) of the straight line between the samples y at
    i and j alone (the samples between taken as lost), plus ``tau_s`` (y_j - y_i) for a lag undone:
    bounded by the end samples however long the gap, where the cubic's slopes, taken across a long
    gap, can run away."""
    return (t[j] - t[i]) * 0.5 * (y[i] + y[j]) + tau_s * (y[j] - y[i])


def _run_intervals(i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The intervals (k: from frame k to k + 1) of each run from frame i to frame j (arrays), and
    the index of the run each belongs to (vectorised: a lossy hour has tens of thousands of runs)."""
    lengths = j - i
    run = np.repeat(np.arange(len(i)), lengths)
    return i[run] + np.arange(int(lengths.sum())) - np.repeat(np.cumsum(lengths) - lengths, lengths), run


def _spread(k: np.ndarray, at_most: int) -> np.ndarray:
    """``k`` itself, or at most ``at_most`` of its elements evenly spread over it."""
    if len(k) <= at_most:
        return k
    return k[:: math.ceil(len(k) / at_most)]


def rebridge_gyro_gaps(data: FlightData, G: np.ndarray, y: np.ndarray, att: np.ndarray, tau_s: float = 0.0
                       ) -> tuple[np.ndarray, int]:
    """The gyro's angle G (per frame, each segment from its own start; the lag undone) with each
    run of frames whose gyro sample was lost re-bridged with the attitude's help.

    First the gyro's own bridge of each run: the spline's (what G holds), or the straight line
    between the run's end samples (``_trapezoid_bridge``) where this flight's whole stretches say
    the line is the nearer over runs of that length (each bridge's error variance against the
    spline's own increment, on the same spans), or where they are too few to say. The line is
    bounded by its end samples; the cubic's slopes, taken across a long gap, are not (a burst of
    0.5 s in a 6 Hz rotation with the attitude lost around it too: 0.2-0.4 rad from the truth,
    tests/test_diagnose_rotation.py).

    Over a run, from the sample before it (frame i) to the one after it (frame j), widened by up to
    ``GAP_ATTITUDE_REACH_FRAMES`` frames of whole gyro intervals to ends where the attitude was
    recorded, the attitude's difference from G (att - G, at the frames where the attitude was
    recorded, linear between them) is added to G with weight w = v_g / (v_g + v_a). v_g is the
    chosen bridge's error over a run of that length and v_a the attitude's over the widened span,
    both measured on this flight: on stretches where every gyro sample is there, against the
    spline's own increment, the bridge made from the samples it would have there
    (``_spline_bridge``: four, ``_trapezoid_bridge``: two) and the attitude's change. Returns the
    angle and how many runs took some of the attitude.

    Why: where a loop's rotation is fast the spline bridges a lost sample badly (a noise-free
    generator flight whose loop oscillates at 12 Hz with 15 % of its messages lost, seed 15:
    2.9 mrad rms over a gap of one sample on an increment of 5.9, 10 over two, where the
    attitude's change was within 0.1), and the flow's residual and the effects' gyro regressors
    share that error: errors in variables, read as a rotation gain of 0.90. Over a burst of 0.5 s
    the cubic's slopes, taken across the gap, run away: the effects' regressors of gen_0120 (three
    bursts) stood 0.23-0.28 rad rms from the recorded attitude (6 mrad with the attitude's help).
    Where the attitude is noisy and the rotation slow, the spline is the better, and the variances
    say so."""
    y = np.asarray(y, dtype=float)
    out = np.array(G, dtype=float)
    n = data.n
    if n < 8:
        return out, 0
    t, seg = data.t_s, data.seg
    rec_g, rec_a = data.gyro_rec, data.att_rec
    same = seg[1:] == seg[:-1]
    fin = np.isfinite(G) & np.isfinite(y)
    ok = rec_g[1:] & rec_g[:-1] & same & fin[1:] & fin[:-1]
    runs = np.array(_runs(~rec_g, 1), dtype=np.int64).reshape(-1, 2)  # runs of lost samples
    bad = filters.running_count(~ok)  # intervals not measured among the first k

    def span_ok(i: np.ndarray, j: np.ndarray) -> np.ndarray:  # intervals i..j-1 all measured
        return bad[j] - bad[i] == 0

    var_cache: dict[tuple[str, int], float] = {}

    def variance(kind: str, m: int) -> float:
        if (kind, m) not in var_cache:
            if kind in ("spline", "trapezoid"):  # on the same spans, so that the two compare
                i = _spread(np.arange(1, max(n - m - 1, 1)), GAP_MAX_SAMPLES)
                j = i + m
                use = span_ok(i - 1, j + 1)
                i, j = i[use], j[use]
                bridge = _spline_bridge if kind == "spline" else _trapezoid_bridge
                d = bridge(t, y, i, j, tau_s) - (G[j] - G[i])
            else:
                i = _spread(np.arange(0, max(n - m, 0)), GAP_MAX_SAMPLES)
                j = i + m
                use = span_ok(i, j) & rec_a[i] & rec_a[j]
                d = (att[j[use]] - att[i[use]]) - (G[j[use]] - G[i[use]])
            d = d[np.isfinite(d)]
            var_cache[(kind, m)] = float(np.mean(d * d)) if len(d) >= GAP_MIN_SAMPLES else math.nan
        return var_cache[(kind, m)]

    # the runs of lost samples, from the sample before each (i) to the one after it (j), then
    # widened to ends where the attitude was recorded (vectorised: a lossy hour has tens of thousands)
    i, j = runs[:, 0] - 1, runs[:, 1].copy()
    keep = (i >= 0) & (j < n)
    i, j = i[keep], j[keep]
    keep = (seg[i] == seg[j]) & fin[i] & fin[j]
    i, j = i[keep], j[keep]
    m = j - i
    # the gyro's own bridge of each run: the spline's (what G holds), or the straight line between
    # the run's end samples where this flight's whole stretches say that is the nearer over runs of
    # that length, or where they are too few to say (the line is bounded by the end samples); v_g
    # is the chosen one's error variance
    lengths, length_of = np.unique(m, return_inverse=True)  # per run length, not per run
    v_g_of = np.empty(len(lengths))
    line_of = np.empty(len(lengths), dtype=bool)
    for q, k in enumerate(lengths.tolist()):
        v_s, v_t = variance("spline", k), variance("trapezoid", k)
        line_of[q] = not math.isfinite(v_s) or v_t < v_s
        v_g_of[q] = v_t if line_of[q] else v_s
    line = line_of[length_of]
    if np.any(line):
        li, lj = i[line], j[line]
        delta = _trapezoid_bridge(t, y, li, lj, tau_s) - (out[lj] - out[li])
        k_int, run = _run_intervals(li, lj)
        add = np.zeros(n - 1)  # spread over the run's intervals in proportion to their length
        add[k_int] = (delta / (t[lj] - t[li]))[run] * (t[k_int + 1] - t[k_int])
        for s0, e0 in data.segments():
            if e0 - s0 >= 2 and np.any(add[s0:e0 - 1]):
                out[s0 + 1:e0] += np.cumsum(add[s0:e0 - 1])
    for _ in range(GAP_ATTITUDE_REACH_FRAMES):
        move = ~rec_a[i] & (i > 0)
        move[move] &= ok[i[move] - 1]
        i = i - move
        move = ~rec_a[j] & (j < n - 1)
        move[move] &= ok[j[move]]
        j = j + move
    keep = rec_a[i] & rec_a[j]
    i, j, length_of = i[keep], j[keep], length_of[keep]
    if len(i) == 0:
        return out, 0
    v_g = v_g_of[length_of]
    spans, span_of = np.unique(j - i, return_inverse=True)
    v_a = np.array([variance("attitude", k) for k in spans.tolist()])[span_of]
    keep = np.isfinite(v_g) & np.isfinite(v_a) & (v_g + v_a > 0.0)
    i, j, v_g, v_a = i[keep], j[keep], v_g[keep], v_a[keep]
    if len(i) == 0:
        return out, 0
    # each interval's weight: the largest of the runs' that cover it (widened runs may overlap)
    k_int, run = _run_intervals(i, j)
    weight = np.zeros(n - 1)
    np.maximum.at(weight, k_int, (v_g / (v_g + v_a))[run])
    have = rec_a & fin & np.isfinite(att)
    for s0, e0 in data.segments():
        if e0 - s0 < 2 or not np.any(weight[s0:e0 - 1]):
            continue
        # the attitude's difference from G, linear between the frames where it was recorded (each
        # run's ends are such frames, so within a run this is the run's own interpolation; per
        # segment, as a log across reboots starts its clock again)
        h = have[s0:e0]
        D = np.interp(t[s0:e0], t[s0:e0][h], (att[s0:e0] - out[s0:e0])[h])
        inc = np.diff(out[s0:e0]) + weight[s0:e0 - 1] * np.diff(D)
        out[s0 + 1:e0] = out[s0] + np.cumsum(inc)
    return out, int(len(i))


#: crossover of the rotation the flow is compared with: the attitude estimate below, the integrated
#: gyro above (Hz)
ROTATION_CROSSOVER_HZ = 1.0
#: crossover of the rotation the effects' regressors are built from (``FlowProblem.anchor``): the
#: gyro nearly everywhere, so that its noise is independent of the attitude noise in the residual
REGRESSOR_CROSSOVER_HZ = 0.1


@dataclass(frozen=True)
class GyroAngles:
    """The gyro's angle about the pitch and the roll axis (``gyro_angles``), per frame, and the
    segments it is made over (at least 30 frames; NaN elsewhere)."""

    angles: tuple[np.ndarray, np.ndarray]
    segments: list[tuple[int, int]]


def gyro_angles(data: FlightData, gyro_lag_s: float = 0.0) -> GyroAngles | None:
    """The gyro's part of ``rotation_angles``, which does not depend on the crossover: per axis
    (pitch, roll) and segment of at least 30 frames, the gyro's integral from the segment's start
    (the spline's, ``channels.gyro_spline``, where it covers the segment), the lag ``gyro_lag_s``
    undone, its runs of lost samples re-bridged (``rebridge_gyro_gaps``). None when the gyro is
    not recorded at the frame rate."""
    if np.mean(data.gyro_rec) < 0.75:
        return None
    angles = []
    long_segments = [(a0, b0) for a0, b0 in data.segments() if b0 - a0 >= 30]
    for ang, gyr, gang, gfine in ((data.pitch_rad, data.gyro_y_rad_s, data.gyro_angle_y_rad, data.gyro_fine_y_rad_s),
                                  (data.roll_rad, data.gyro_x_rad_s, data.gyro_angle_x_rad, data.gyro_fine_x_rad_s)):
        G_all = np.full(data.n, np.nan)
        for a0, b0 in long_segments:
            t = data.t_s[a0:b0]
            g = gyr[a0:b0]
            if gang is not None and gfine is not None and np.all(np.isfinite(gang[a0:b0])) \
                    and np.all(np.isfinite(gfine[a0:b0])):
                # the integral of a spline through the gyro's own samples (``channels.gyro_spline``)
                G = gang[a0:b0] - gang[a0]
                g = gfine[a0:b0]
            else:
                G = np.concatenate([[0.0], np.cumsum(0.5 * (g[1:] + g[:-1]) * np.diff(t))])
            if gyro_lag_s > 0:
                # the body rate is g + tau g', so the angle is the integral of g plus tau (g - g0):
                # exact, where a derivative of the samples (central differences, then the
                # trapezoid) averages g over neighbouring frames and undoes too little of the lag
                # at high frequency (a rotation gain or a flow scale of 1-2 % that is not there)
                G = G + gyro_lag_s * (g - g[0])
            G_all[a0:b0] = G
        # the runs the gyro was lost over, bridged with the attitude's help where it is the better
        G_all, _n_runs = rebridge_gyro_gaps(data, G_all, gyr, ang, gyro_lag_s)
        angles.append(G_all)
    return GyroAngles((angles[0], angles[1]), long_segments)


def rotation_angles(data: FlightData, gyro_lag_s: float = 0.0, crossover_hz: float = ROTATION_CROSSOVER_HZ,
                    gyro: GyroAngles | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """(pitch, roll) for the flow's rotation: the integrated gyro above ``crossover_hz``
    and the attitude estimate below it (a complementary filter, zero phase: fused = G + LP(att - G)
    with G the gyro's integral per segment, so the two parts add up to the attitude wherever the
    two sources agree). ``gyro``: ``gyro_angles(data, gyro_lag_s)`` when already made (the flow
    group fuses the same G at two crossovers).

    Why: an attitude estimate carries its own noise (white or coloured, an EKF output) and is
    smoothed at high frequency; the flow sees the true rotation. Compared with the noisy attitude,
    the flow's residual holds the attitude's noise, and every rotation regressor built from the same
    attitude holds it too: errors in variables, read as a rotation gain, a delay or a lever arm.
    The gyro has the high-frequency rotation; a bias becomes a constant after the high-pass (gone
    in every difference); a gyro low-pass (``gyro_lag`` from the gyro group) is undone first,
    integral(gyro) + tau (gyro - gyro(0)); a run of lost gyro samples is bridged with the attitude's
    help where the flight's own errors say it is the better (``rebridge_gyro_gaps``). None when the
    gyro is not recorded at the frame rate (then the attitude)."""
    if gyro is None:
        gyro = gyro_angles(data, gyro_lag_s)
    if gyro is None:
        return None
    fs = 1.0 / data.frame_s
    b, a = filters.butter2_lowpass(crossover_hz / (0.5 * fs))
    out = []
    for ang, G_all in zip((data.pitch_rad, data.roll_rad), gyro.angles, strict=True):
        fused = np.array(ang, dtype=float)
        for a0, b0 in gyro.segments:
            G = G_all[a0:b0]
            fused[a0:b0] = G + filters.filtfilt(b, a, ang[a0:b0] - G)
        out.append(fused)
    return out[0], out[1]


#: crossover of the velocity the effects' regressors are built from: the flow's odometry below,
#: the velocity the recorded tilt gives above (``regressor_scene_angle``)
VELOCITY_CROSSOVER_HZ = 0.2


def regressor_scene_angle(base: FlowProblem, rotation: tuple[np.ndarray, np.ndarray],
                          p_anchor: np.ndarray | None = None) -> np.ndarray:
    """A scene angle (2, n) for the effects' regressors: what the sensor would report, under the
    geometry of ``p_anchor`` (the nominal when None), for the rotation ``rotation`` and a velocity
    that follows the flow's odometry (``base`` under that geometry) below ``VELOCITY_CROSSOVER_HZ``
    and the integral of the tilt (of ``rotation``) above it (zero phase).

    Why: every effect that scales the flow velocity (flow scale, range offset, and drag through
    the velocity) has the flow velocity as its regressor in the force balance, and the measured
    flow's noise (counts, quantization, rotation compensation) sits in both that regressor and the
    residual: errors in variables, fitted as a scale below 1 or a positive range offset that
    shrink the noise. Above the crossover the tilt gives the velocity's changes without the flow's
    noise (and without the unexplained forces, turbulence among them, that the loop answers).

    Why the geometry: the odometry below the crossover is the measured flow read through the
    anchor's geometry, the tilt's velocity above it is in body axes; the synthetic flow must be
    the same sensor's reading at both frequencies, or reading it through a geometry far from the
    nominal (a yaw of 12 deg, a scale of 1.2) treats the two parts differently, and the
    difference, second order in the geometry (1 - cos 12 deg = 2 %), is fitted as a flow scale."""
    data = base.data
    p_a = NOMINAL if p_anchor is None else p_anchor
    X, _ = base.flow_velocity(p_a)
    fs = 1.0 / data.frame_s
    b, a = filters.butter2_lowpass(VELOCITY_CROSSOVER_HZ / (0.5 * fs))
    phi = np.zeros((2, data.n))
    t = data.t_s
    kx, ky, yaw, delay, offset = (float(p_a[IDX[k]]) for k in ("scale_x", "scale_y", "yaw", "delay", "offset"))
    gain, rz = float(p_a[IDX["gain"]]), float(p_a[IDX["rz"]])
    c, s = math.cos(yaw), math.sin(yaw)
    for a0, b0 in data.segments():
        if b0 - a0 < 2:
            continue
        ts = t[a0:b0]
        v = np.gradient(X[:, a0:b0], ts, axis=1)
        if b0 - a0 >= 30:
            # the tilt's velocity from ``rotation`` too: the recorded attitude's noise is in the
            # residual's tilt term (errors in variables again)
            acc = np.stack([AXIS_SIGN[i] * base.g * np.tan(rotation[i][a0:b0]) for i in (0, 1)])
            vt = np.concatenate([np.zeros((2, 1)), np.cumsum(0.5 * (acc[:, 1:] + acc[:, :-1]) * np.diff(ts), axis=1)],
                                axis=1)
            v = vt + filters.filtfilt(b, a, v - vt, axis=1)
        xf = np.concatenate([np.zeros((2, 1)), np.cumsum(0.5 * (v[:, 1:] + v[:, :-1]) * np.diff(ts), axis=1)],
                            axis=1)
        y = np.concatenate([np.zeros((2, 1)), np.cumsum(np.diff(xf, axis=1) / (base._Amid[a0:b0 - 1] - offset),
                                                        axis=1)], axis=1)
        # body-axis scene angle under the anchor's geometry (``FlowProblem.flow_velocity`` inverted)
        rot = np.stack([AXIS_SIGN[i] * (rotation[i][a0:b0] - rotation[i][a0]) for i in (0, 1)])
        body = gain * rot - y
        if rz != 0.0:  # a lever arm's translation, integral(dR / A) (``FlowProblem.RA``)
            body = body + rz * np.concatenate([np.zeros((2, 1)), np.cumsum(np.diff(rot, axis=1) / base._Amid[a0:b0 - 1],
                                                                             axis=1)], axis=1)
        sens = np.stack([(c * body[0] + s * body[1]) / kx, (-s * body[0] + c * body[1]) / ky])
        if delay != 0.0:  # the sensor reports the scene angle of ``delay`` earlier
            sens = np.stack([np.interp(ts - delay, ts, sens[i]) for i in (0, 1)])
        phi[:, a0:b0] = sens
    return phi


#: a lever arm is told from a rotation gain only when 1/height varies by this much (coefficient of
#: variation over the flight): at one height rz / h is a constant, the same as a gain
LEVER_ARM_MIN_CV = 0.1


def lever_arm_observable(data: FlightData) -> bool:
    """Whether the flight's heights vary enough to tell ``flow_lever_arm`` from ``flow_rotation_gain``."""
    inv = 1.0 / data.range_m[np.isfinite(data.range_m) & (data.range_m > 0)]
    return bool(len(inv) > 1 and np.std(inv) >= LEVER_ARM_MIN_CV * np.mean(inv))


def flow_body_angles(data: FlightData) -> tuple[np.ndarray, np.ndarray] | None:
    """(pitch, roll) integrated from the flow message's own body rates the way the flow itself is
    (rate x frame period, frame by frame), or None when the flow message has none. A sensor that
    samples rates at instants sees a body rate that jitters near the Nyquist frequency aliased;
    its own body rate, sampled at the same instants, carries the same alias, which a 50 Hz attitude
    cannot (ArduCopter SITL: the flow shows about 1.1-1.2 x the rotation the attitude shows)."""
    if data.flow_body_x_rad_s is None or data.flow_body_y_rad_s is None:
        return None
    out = []
    for rate in (data.flow_body_y_rad_s, data.flow_body_x_rad_s):
        inc = np.nan_to_num(rate) * data.dt_s
        ang = np.zeros(data.n)
        for a0, b0 in data.segments():
            ang[a0:b0] = np.cumsum(np.concatenate([[0.0], inc[a0 + 1:b0]]))
        out.append(ang)
    return out[0], out[1]


#: order of the autoregressive model of the flow channel's noise (``ar_whitener``)
WHITEN_ORDER = 2

#: a flow window is used only when the rotation it holds (root mean square over the window, the
#: cubic removed) is at least this many of the flow's counts on one axis or both (``quiet_windows``)
QUIET_ROTATION_COUNTS = 1.0


def quiet_windows(fp: FlowProblem, count_rad: float) -> np.ndarray:
    """(n_windows,) True where a flow window's rotation is under ``QUIET_ROTATION_COUNTS`` counts of
    ``count_rad`` on both axes (none when the flow is not quantized: ArduPilot's flow rates). A
    window whose other axis turns keeps its quiet axis too, where a turned sensor
    (``flow_yaw_misalignment``) shows that rotation (left out per axis, the matrix lost four yaw
    misalignments).

    Why: in a hover the rotation within a window is mostly the loop's own answer to the flow's
    quantization. The companion's velocity comes from the counts, a count that flips moves the
    velocity, the command and then the attitude, so the rotation is correlated with the counts'
    rounding error that is the residual's noise: errors in the residual that follow the regressor,
    which no whitening removes. Fitted against the simulator's true rotation without any noise, a
    flight's windows with under 0.4 counts of rotation asked for flow scales wrong by 0.2-66 %
    (ten generator flights: e.g. 1.95 for a true 1.17, 1.56 for 1.13), windows with over one count
    for the truth within 5 % (most within 3 %); a flight of quiet windows only was fitted 7-9 % high. In a
    cross-validation the quiet windows are the training set of the fold that holds out a flight's
    one manoeuvre, whose scale is then the quiet windows' wrong one (a true scale of 0.91 refused)."""
    W = fp.flow.idx
    if count_rad <= 0 or len(W) == 0:
        return np.zeros(len(W), dtype=bool)
    rms = np.sqrt(np.mean(fp.window_rotation() ** 2, axis=2))
    return np.all(rms < QUIET_ROTATION_COUNTS * count_rad, axis=0)


def ar_whitener(e: np.ndarray, order: int = WHITEN_ORDER) -> Callable[[np.ndarray], np.ndarray]:
    """A prediction-error filter for the rows of ``e`` (n_windows, L): an autoregressive model of
    ``order`` fitted to the nominal residual within the windows, applied to any residual of the
    same shape (the first ``order`` samples of each window are dropped).

    Why: the flow residual is quantization (white) plus what the plant's tilt does not explain
    of the translation: turbulence, a smooth, coloured process that the closed loop answers with
    rotation, so it is correlated with every rotation regressor (a rotation gain, a lever arm).
    Least squares on the whitened residual weighs each frequency by its noise (the prediction
    error method, consistent in closed loop when the noise model is right), so coloured noise
    neither dominates the fit nor reads as an effect."""
    coef = np.zeros(order)
    if e.size and e.shape[1] > order + 2:
        y = e[:, order:].ravel()
        X = np.stack([e[:, order - j - 1:e.shape[1] - j - 1].ravel() for j in range(order)], axis=1)
        sol, *_ = np.linalg.lstsq(X, y, rcond=None)
        roots = np.roots(np.concatenate([[1.0], -sol]))
        if np.all(np.isfinite(sol)) and np.all(np.abs(roots) < 0.999):
            coef = sol

    def apply(r: np.ndarray) -> np.ndarray:
        out = r[:, order:].copy()
        for j in range(order):
            out -= coef[j] * r[:, order - j - 1:r.shape[1] - j - 1]
        return out

    return apply


def _scale_or_inf(x: np.ndarray) -> float:
    """``robust_std`` of x's finite values; inf when there are none (a source that leaves a
    channel nothing to fit scores worst, never best)."""
    x = x[np.isfinite(x)]
    return robust_std(x) if x.size else math.inf


def _force_noise(fp: FlowProblem) -> float:
    """Robust scale of the nominal force-balance residual (both axes), N."""
    return _scale_or_inf(fp.force_residual(NOMINAL).ravel())


def _flow_noise(fp: FlowProblem) -> float:
    """Robust scale of the nominal flow-geometry residual (both axes), rad."""
    return _scale_or_inf(fp.flow_residual(NOMINAL).ravel())


#: the attitude estimate is the flow's rotation source only when it explains the flow better than
#: the next source (the gyro fused with it, else the flow message's own body rate) by more than
#: this share of the score. Why: the score is the residual at the nominal model, and where the
#: flow's geometry is off (a delay, a rotation gain) that residual is the geometry's signature,
#: the same whatever the source, and the choice falls to rounding; the gyro measures the rotation
#: the estimate infers from it. On the generalisation matrix this changed one recording of 300
#: (gen_0282: a form drag found, a false flow scale gone) and nothing else
SOURCE_TIE = 0.02

#: the parameters of the flow's geometry (those ``FlowProblem.flow_velocity`` reads): the ones an
#: anchor (``FlowProblem.anchor``) is moved to
GEOMETRY = ("scale_x", "scale_y", "yaw", "delay", "offset", "gain", "rz")
#: the effects that free them
GEOMETRY_EFFECTS = ("flow_scale", "flow_yaw_misalignment", "flow_delay", "range_offset", "flow_rotation_gain",
                    "flow_lever_arm")


#: the flow's rotation sources, in the order they are tried (``flow_group``), each with the stream
#: whose time its rotation comes on (``timing_sigma_s``; None: the flow's own)
ROTATION_SOURCES: dict[str, str | None] = {"attitude": "attitude", "gyro": "gyro", "flow": None}


def flow_group(data: FlightData, cfg: Config, gyro_lag_s: float = 0.0, p_anchor: np.ndarray | None = None,
               source: str | None = None, refine_lag: bool = True,
               accelerometer: bool | None = None) -> tuple[Group, FlowProblem, FlowGroupState]:
    """The flow group, its rotation taken from the source that explains the recorded flow better:
    the attitude estimate, or the gyro fused with it (``rotation_angles``), or the flow message's
    own body rate. The flow sees the true rotation, so the source nearer the truth leaves the
    smaller nominal residual; which one was used goes to ``data.notes`` and to the state
    (``FlowGroupState.source``). ``source`` (one of ``ROTATION_SOURCES``): take that one without
    choosing, and say nothing of it (the group rebuilt about an anchor, whose choice would be the
    same; the part of a long flight held back from the fit, judged with the fit's source); when
    this flight has no such source, the choice is made. ``refine_lag``: the gyro lag undone in the
    gyro's rotation is timed for the flow (``_flow_lag``; the lag used is ``FlowGroupState.lag_s``);
    False: ``gyro_lag_s`` as it is (the group rebuilt, or the held-back part, with the fit's lag).
    ``accelerometer``: the flow channels' translation with the accelerometer's horizontal force
    (True) or from the tilt alone (False); None: with it when the recording has an accelerometer
    and that leaves a nominal flow residual more than ``SOURCE_TIE`` smaller
    (``FlowGroupState.accelerometer``, and a note)."""
    if source is not None and source not in ROTATION_SOURCES:
        raise ValueError(f"flow_group: no rotation source {source!r} (one of {', '.join(ROTATION_SOURCES)})")
    kw: dict[str, Any] = dict(mass_kg=cfg.airframe.mass_kg, gravity_m_s2=cfg.airframe.gravity_m_s2)
    gyro = gyro_angles(data, gyro_lag_s)  # made once: fused here, and for the regressors below
    fused = rotation_angles(data, gyro_lag_s, gyro=gyro) if source in (None, "gyro") else None
    own = flow_body_angles(data) if source in (None, "flow") else None
    if (source == "gyro" and fused is None) or (source == "flow" and own is None):
        source = None
        fused, own = rotation_angles(data, gyro_lag_s, gyro=gyro), flow_body_angles(data)
    fp = FlowProblem(data, **kw) if source in (None, "attitude") else None
    sources: list[tuple[str, FlowProblem]] = [] if fp is None else [("the attitude estimate", fp)]
    keys: list[str] = [] if fp is None else ["attitude"]  # each source's ``ROTATION_SOURCES`` key
    if fused is not None:
        sources.append((f"the gyro above {ROTATION_CROSSOVER_HZ:g} Hz and the attitude below",
                        FlowProblem(data, rotation_angles=fused, **kw)))
        keys.append("gyro")
    if own is not None:
        sources.append(("the flow message's own body rate, sampled with the flow",
                        FlowProblem(data, rotation_angles=own, **kw)))
        keys.append("flow")
    fp = sources[0][1]
    chosen = keys[0]
    source_note = None
    if len(sources) > 1:
        # both channels judge: the flow's geometry, and the force balance the odometry feeds
        noise = np.array([_flow_noise(f) for _name, f in sources])
        force = np.array([_force_noise(f) for _name, f in sources])
        score = noise / max(noise[0], 1e-300) + force / max(force[0], 1e-300)
        best = int(np.argmin(score))
        tie = best == 0 and score[1] <= score[0] * (1.0 + SOURCE_TIE)
        if tie:  # a measured rate over the estimate that infers the rotation from it
            best = 1
        fp = sources[best][1]
        chosen = keys[best]
        if best:
            why = (f"as good as the attitude estimate, within {100 * SOURCE_TIE:g} %, and a measurement" if tie
                   else "it explains the flow best")
            source_note = (f"the flow's rotation from {sources[best][0]} ({why}: residual "
                           f"{noise[best]:.3g} rad and {force[best]:.3g} N against {noise[0]:.3g} rad and "
                           f"{force[0]:.3g} N from the attitude estimate)")
            data.notes.append(source_note)
    lag_sigma = timing_sigma_s(data, "gyro", "attitude")
    lag_note = None
    if refine_lag and chosen == "gyro" and gyro_lag_s > 0 and lag_sigma > 0:
        # the lag was timed against the attitude; the flow sees the rotation on its own time
        lag_flow = _flow_lag(fp, data, gyro_lag_s, STAMP_ALIGN_SIGMAS * lag_sigma, kw)
        if abs(lag_flow - gyro_lag_s) >= 1e-5:
            lag_note = (f"the gyro lag undone in the flow's rotation: {1e3 * lag_flow:.2f} ms, what the flow "
                        f"asks for within +-{1e3 * STAMP_ALIGN_SIGMAS * lag_sigma:.2f} ms of the gyro group's "
                        f"{1e3 * gyro_lag_s:.2f} ms (the attitude stamps' rounding)")
            data.notes.append(lag_note)
            gyro_lag_s = lag_flow
            gyro = gyro_angles(data, gyro_lag_s)
            fp = FlowProblem(data, rotation_angles=rotation_angles(data, gyro_lag_s, gyro=gyro), **kw)
    accel_note = None
    if accelerometer is not False and data.accel_x_m_s2 is not None:
        # the translation: the tilt's alone, or with the horizontal force the accelerometer measures
        # (turbulence, wind, drag: the loop answers turbulence with tilt, so a translation without it
        # is off by what the loop cancels, and that follows every regressor)
        fa = FlowProblem(data, rotation_angles=fp.rotation_angles, accelerometer=True, **kw)
        if accelerometer is None:
            n_tilt, n_acc = _flow_noise(fp), _flow_noise(fa)
            accelerometer = bool(n_acc < (1.0 - SOURCE_TIE) * n_tilt)
            if accelerometer:
                accel_note = (f"the flow's translation from the tilt and the accelerometer's horizontal force (it "
                              f"explains the flow best: residual {n_acc:.3g} rad against {n_tilt:.3g} rad from the "
                              f"tilt alone)")
                data.notes.append(accel_note)
        if accelerometer:
            fp = fa
    base = fp
    # the effects' regressors from sources whose noise the residual does not share (``anchor``):
    # the rotation from the gyro, the velocity from the tilt above a low crossover
    regressor = rotation_angles(data, gyro_lag_s, REGRESSOR_CROSSOVER_HZ, gyro=gyro)
    what = f"the gyro above {REGRESSOR_CROSSOVER_HZ:g} Hz"
    if regressor is None:
        regressor = (data.pitch_rad, data.roll_rad)
        what = "the attitude estimate"
    p_a = NOMINAL.copy()
    if p_anchor is not None:  # only the geometry: the forces do not enter the regressors
        geo = [IDX[k] for k in GEOMETRY]
        p_a[geo] = p_anchor[geo]
    # quiet windows (``quiet_windows``) are left out of both problems, not evaluated and dropped
    keep = ~quiet_windows(base, data.flow_resolution_rad * math.sqrt(12.0))
    if not keep.all():
        base.keep_flow_windows(keep)

    def anchored(rotation: tuple[np.ndarray, np.ndarray]) -> FlowProblem:
        """The flow problem whose regressors take their rotation from ``rotation``, on the kept
        windows, anchored to ``base``'s nominal residual."""
        prob = FlowProblem(data, rotation_angles=rotation, scene_angle=regressor_scene_angle(base, rotation, p_a), **kw)
        if not keep.all():
            prob.keep_flow_windows(keep)
        prob.anchor(base, p_a)
        return prob

    fp = anchored(regressor)
    data.notes.append(f"the flow effects' regressors: rotation from {what}, velocity from the tilt above "
                      f"{VELOCITY_CROSSOVER_HZ:g} Hz and the flow below (their noise is not the residual's)")
    if len(keep) and not keep.all():
        data.notes.append(f"{int((~keep).sum())} of {len(keep)} flow windows left out of the flow channels: "
                          f"under {QUIET_ROTATION_COUNTS:g} count of rotation on both axes, what rotation there is "
                          f"is the loop's answer to the flow's own rounding")
    state = FlowGroupState(fp)
    state.source, state.source_note = chosen, source_note
    state.accelerometer = bool(accelerometer) and data.accel_x_m_s2 is not None  # asked for or chosen, and recorded
    state.accel_note = accel_note
    state.lag_s = gyro_lag_s
    state.lag_note = lag_note
    e0 = base.flow_residual(p_a)
    whiten = state.whiten = [ar_whitener(e0[0]), ar_whitener(e0[1])]
    state.n_flow_rows = fp.flow.idx.shape[0] * max(fp.flow.idx.shape[1] - WHITEN_ORDER, 0)

    def residuals(p: np.ndarray) -> list[np.ndarray]:
        s, e = state.start_end
        f = fp.flow_residual(p)
        r = fp.force_residual(p, s, e)
        return [whiten[0](f[0]).ravel(), whiten[1](f[1]).ravel(), r[0], r[1]]

    instrument = None
    if chosen == "flow":
        # the flow message's body rate is the autopilot's gyro over each frame, and the regressors'
        # rotation is the gyro's: they share its noise (errors in variables: a hover read as a
        # rotation gain of 0.5 and a flow delay of 26 ms). The same regressors built from the
        # attitude, whose noise is its own, are the flow channels' instruments (Group.instrument)
        fi = anchored((data.pitch_rad, data.roll_rad))

        def instrument(p: np.ndarray) -> list[np.ndarray | None]:
            f = fi.flow_residual(p)
            return [whiten[0](f[0]).ravel(), whiten[1](f[1]).ravel(), None, None]

    tf = data.t_s[fp.flow.idx[:, WHITEN_ORDER:]].ravel() if len(fp.flow.idx) else np.zeros(0)
    tw = 0.5 * (fp.force.t_start_s + fp.force.t_end_s)
    a_min = float(np.nanmin(data.range_m))
    # a rangefinder offset of half the lowest height is far beyond any mounting error: a fit that
    # runs there is shrinking the flow velocity of a hover towards nothing, not measuring an offset
    lower = np.array([0.3, 0.3, -math.pi / 2, -0.1, -0.5 * a_min, -5.0, -50.0, -50.0, 0.3, -5.0, -0.5])
    upper = np.array([3.0, 3.0, math.pi / 2, 0.3, 0.5 * a_min, 10.0, 50.0, 50.0, 3.0, 10.0, 0.5])
    assert len(lower) == len(PARAMS)
    g = Group(
        name="flow", params=PARAMS, nominal=NOMINAL.copy(),
        timing=("delay", flow_timing_sigma_s(data, ROTATION_SOURCES[chosen])),
        steps=np.array([1e-3, 1e-3, 1e-3, 1e-3, 2e-3, 1e-2, 1e-2, 1e-2, 1e-3, 1e-2, 1e-3]), lower=lower, upper=upper,
        channels=("flow_x", "flow_y", "force_x", "force_y"), units=("rad", "rad", "N", "N"),
        floors=(max(data.flow_resolution_rad, 1e-5),) * 2 + (1e-3, 1e-3), residuals=residuals,
        row_times=[tf, tf, tw, tw],
        candidates=[Candidate(e, ps, physical=phys, matters=threshold(e)) for e, ps, phys in (
            ("flow_scale", ("scale_x", "scale_y"), _plausible_scale),
            ("flow_yaw_misalignment", ("yaw",), None),
            ("flow_delay", ("delay",), _causal_flow_delay),
            ("flow_rotation_gain", ("gain",), _plausible_gain),
            ("range_offset", ("offset",), None),
            ("linear_drag", ("b",), _positive_drag),
            ("quadratic_drag", ("c",), _positive_form_drag),
            ("flow_lever_arm", ("rz",), None),
            ("wind_force", ("fx", "fy"), None)) if e != "flow_lever_arm" or lever_arm_observable(data)],
        linear=("b", "fx", "fy", "c"), search=state.search, state=state.as_dict, searched_effect="wind_force",
        null_pvalue=state.null_pvalue, active_rows=state.active_rows, instrument=instrument,
        check=lambda p_with, p_without: accelerometer_z(base, p_with, p_without))
    stream = ROTATION_SOURCES[chosen]
    if stream is not None:
        bound = STAMP_ALIGN_SIGMAS * timing_sigma_s(data, "flow", stream)
        g.nominal[IDX["delay"]] = state.timing_offset_s = _stamp_alignment(g, bound)
        if abs(state.timing_offset_s) >= 1e-5:
            data.notes.append(f"the flow's timing against its rotation source aligned by "
                              f"{1e3 * state.timing_offset_s:+.2f} ms (the stamps leave +-{1e3 * bound:.2f} ms "
                              f"uncertain): the nominal model's flow delay")
    return g, fp, state


#: the flow's timing against its rotation source, and a gyro lag undone in that rotation, are
#: aligned within this many sigmas of what the stamps leave uncertain (``timing_sigma_s``)
STAMP_ALIGN_SIGMAS = 2.0


def _flow_lag(fp: FlowProblem, data: FlightData, lag_s: float, bound_s: float, kw: dict[str, Any]) -> float:
    """The gyro lag, within +-``bound_s`` of ``lag_s``, whose undoing in the flow's rotation leaves
    the smallest nominal flow residual: one Gauss-Newton step from ``fp`` (the flow problem with
    ``lag_s`` undone; a one-sided difference of 0.1 ms, the rotation being linear in the lag),
    clipped.

    Why: the gyro group times the lag against the attitude, whose stamps' rounding shifts it by a
    fraction of a ms (``timing_sigma_s``), and the flow of a flight whose rotation moves fast is
    far more sensitive to it: gen_0183 of the generalisation matrix (a 47.06 ms gyro lag only,
    ArduPilot's ms stamps) had its flow residual 27 % larger undone of 46.8 ms than of 47.1 ms,
    and named a 7-10 cm range offset beside the lag; a flow delay aligned instead
    (``_stamp_alignment``) shifts the translation with the rotation and left it at z 3.2."""
    h = 1e-4

    def flow_rows(lag: float) -> np.ndarray:
        rot = rotation_angles(data, lag)
        return FlowProblem(data, rotation_angles=rot, **kw).flow_residual(NOMINAL).ravel()

    r0 = fp.flow_residual(NOMINAL).ravel()
    return _clipped_step(lag_s, r0, (flow_rows(lag_s + h) - r0) / h, bound_s)


def _stamp_alignment(g: Group, bound_s: float) -> float:
    """The flow delay, within +-``bound_s``, that the flow channels ask for at the nominal model:
    one Gauss-Newton step on the whitened flow residual (central difference of 0.1 ms), clipped.

    Why: a timing error between the flow's stamps and its rotation source's is exactly a flow
    delay (the rotation compared a little early or late), and stamps in whole ms leave that timing
    uncertain by a fraction of a ms (``timing_sigma_s``: 0.29 ms for ms against us stamps). A flow
    delay that small is not a finding (under 2 ms, ``sizes``), so it was never fitted, and in a
    flight whose rotation moves fast the residual it leaves can go to another effect. The nominal
    model carries the alignment; a flow delay is still judged from it and reported as the delay it
    fits. (A gyro lag's own timing, against the attitude, is the gyro's: ``_flow_lag``.)"""
    if not bound_s > 0:
        return 0.0
    k = IDX["delay"]
    h = 1e-4

    def flow_rows(d: float) -> np.ndarray:
        p = g.nominal.copy()
        p[k] = d
        r = g.residuals(p)
        return np.concatenate([r[0], r[1]])

    return _clipped_step(0.0, flow_rows(0.0), (flow_rows(h) - flow_rows(-h)) / (2 * h), bound_s)


def _clipped_step(x0: float, r0: np.ndarray, j: np.ndarray, bound_s: float) -> float:
    """One Gauss-Newton step of one parameter from ``x0`` (residual ``r0``, its derivative ``j``,
    over their finite rows), kept within +-``bound_s`` of ``x0``; ``x0`` when ``j`` is nil."""
    ok = np.isfinite(r0) & np.isfinite(j)
    jj = float(j[ok] @ j[ok])
    if not jj > 0:
        return x0
    return float(np.clip(x0 - float(j[ok] @ r0[ok]) / jj, x0 - bound_s, x0 + bound_s))
