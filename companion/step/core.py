"""The companion's control step: align sensors, gate bad data, estimate (eq. 15), PI, command.

``CompanionCore`` is the one stateful object that the live MAVLink loop and the simulator's
scenarios drive; replay runs the column form of the same step over a whole recording:

    core.on_gyro(t, gx, gy)        # RAW_IMU / SCALED_IMU / HIGHRES_IMU, rad/s, sensor time s
    core.on_accel(t, fx, fy)       # the same messages' accelerometer, m/s^2 body FRD (the Kalman filter's input)
    core.on_range(t, range_m)      # DISTANCE_SENSOR facing down, m
    core.on_attitude(t, roll, pitch)  # ATTITUDE, rad (used only by the optional tilt filter)
    core.set_setpoint(vx, vy)      # body-frame velocity setpoint, m/s
    core.set_engaged(True/False)   # the vehicle is / is not in the companion's mode
    out = core.on_flow(frame)      # one flow frame (profiles.FlowColumns of scalars) -> StepOutput

A step has three parts, each run on one frame (the live loop, the scenarios) and over whole
columns (replay). Each rule is written once, in ``companion.step.rules`` (the gates, the spike, the
repeat test, the gyro scan, the cross-frame checks' bounds, what a held or disengaged frame does
to the PI), and both forms call it; where a sequential state makes the column form a second
algorithm (the gyro scan over all frames at once, the PI's linear stretches, the repeat walk),
``tests/test_replay.py`` holds the two equal, bit for bit, on every option and every hold cause
(docs/layout.md, "The step's rules"):

1. inputs aligned as the live loop sees them: the last ``GYRO_HISTORY`` gyro samples and the
   latest range and attitude *received before* the flow message (``CompanionCore.on_*``;
   columns: ``align_gyro_columns``, ``latest_before``), and the repeated-sample rule
   (``CompanionCore.on_flow``; columns: ``repeat_mask``);
2. gating and eq. 15 (``gate_frame`` + ``estimator.VelocitySensor``; columns: ``gate_frames``,
   ``estimate_frames``), the same arithmetic in the same order;
3. the sequential part, the optional tilt filter and the PI law (``control_step``; columns:
   ``run_control``). Both call the same ``tilt_filter_step`` and ``controller._axis``;
   ``pi_axis_columns`` runs ``_axis``'s linear branch vectorised (``np.add.accumulate`` does the
   very additions ``integral + err * dt`` in the same order) and the saturated frames through
   ``_axis`` itself.

Time alignment (CONVENTIONS.md): the gyro sample used is the one nearest the flow frame's own
sensor time (within ``max_gyro_skew_s``); the range is the latest reading. The command computed
from frame k is meant to act from frame k+1 on; the caller sends it.

Gyro source (``EstimatorOptions.gyro_source``). ``imu``: the RAW_IMU / SCALED_IMU /
HIGHRES_IMU sample nearest the frame (the contract). ``flow``: the body rate the flow message
carries for its own sample (ArduPilot: ``flow_rate - flow_comp_m``, which ArduPilot fills from
the gyro it uses to compensate that very flow sample; px4: ``integrated_x/ygyro`` over the
integration time). ``auto`` (default) is ``flow`` for the ``ardupilot`` profile and ``imu``
otherwise: on ArduCopter SITL (``flight_a.tlog``) RAW_IMU carries the autopilot's low-pass
filtered gyro while the flow holds the instantaneous rotation, and the flow message's own body
rate cuts the estimate error against the EKF velocity from 0.113 to 0.047 m/s per axis.

Repeated and out-of-order frames are not stepped (``StepOutput.repeat``: the previous output is
returned, nothing integrates twice). ArduPilot streams OPTICAL_FLOW at the message rate, not the
sensor rate, and stamps it with the send time, so a sample can arrive twice under two times: a
flow message whose payload (scene x/y, quality, integration time, body rates) equals the last
frame's and whose time is less than ``REPEAT_WINDOW_FRAMES`` nominal frames after it is that
sample again (the same payload a whole frame later is a new sample of a still, noise-free
sensor, and is used: the paper profile's integer counts really repeat when the sensor is still).
In the ``ardupilot`` profile the payload carries float rates and the gyro, which a real sensor
never repeats to the bit, and ArduCopter re-sends its last sample for ~0.5 s after the sensor
stops (issue 18): there an identical payload is a repeat whatever its time, so the flow timeout
runs from the last new sample (``repeat_window``; exception: body rates exactly 0.0, a noise-free
simulated source). A frame whose time is not after the last frame's, by less than
``FRAME_REBOOT_S`` (more is a vehicle reboot: a new frame), is a duplicate or out of order.

Failsafe: when the frame cannot be trusted (quality 0, a count spike, no gyro near the frame,
a saturated or non-finite gyro, range missing, stale or outside the sensor's limits) the step
commands level attitude (hold), freezes the integrator and names the cause in
``StepOutput.hold_cause``; the next good frame resumes control. While not engaged (the vehicle
is not in the companion's mode) the step holds with the integrator and filter reset, so control
starts afresh at the next take-over.
"""

from __future__ import annotations

import bisect
import dataclasses
import enum
import math
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion import native
from companion.config import Config
from companion.step import rules
from companion.step.controller import PiController, PiState, _axis
from companion.step.estimator import KalmanSettings, VelocityKalman, VelocitySensor, scene_rate, velocity_from_flow
from companion.step.profiles import FlowColumns, Profile

#: gyro samples the live core keeps (the newest received)
GYRO_HISTORY = 32
#: a gyro time this much (s) before the previous sample's means the vehicle rebooted
GYRO_REBOOT_S = 1.0
#: an identical flow payload less than this many nominal frames after the last frame used is a repeat
REPEAT_WINDOW_FRAMES = 0.75
#: a flow time this much (s) before the last frame's means the vehicle rebooted (a new frame)
FRAME_REBOOT_S = rules.FRAME_REBOOT_S


class HoldCause(enum.StrEnum):
    NONE = ""
    FLOW_QUALITY = "flow quality 0"
    FLOW_SPIKE = "flow spike"
    FLOW_STALE = "flow stale"
    FLOW_INVALID = "flow not finite"
    GYRO_MISSING = "no gyro sample at the flow frame"
    GYRO_INVALID = "gyro saturated or not finite"
    RANGE_MISSING = "no range reading"
    RANGE_STALE = "range stale"
    RANGE_INVALID = "range outside sensor limits"
    LINK = "link lost"
    #: the live loop did not run (a stalled companion): what waited meanwhile was dropped, not flown
    COMPANION_STALLED = "companion stalled"
    #: flow frames arrived older than the live loop's age limit (a backlog upstream) and were dropped
    BACKLOG = "backlog dropped"
    DISENGAGED = "vehicle not in the companion's mode"
    VELOCITY_JUMP = "velocity jump"
    FLOW_FROZEN = "flow frozen"
    GYRO_FROZEN = "gyro frozen"


#: hold causes by the integer code the column functions use (0 = none), in gate precedence order
CAUSE_CODES: tuple[HoldCause, ...] = (
    HoldCause.NONE, HoldCause.FLOW_INVALID, HoldCause.FLOW_QUALITY, HoldCause.GYRO_MISSING,
    HoldCause.GYRO_INVALID, HoldCause.RANGE_MISSING, HoldCause.RANGE_INVALID, HoldCause.RANGE_STALE,
    HoldCause.FLOW_SPIKE, HoldCause.DISENGAGED, HoldCause.VELOCITY_JUMP, HoldCause.FLOW_FROZEN,
    HoldCause.GYRO_FROZEN)
_CODE = {c: i for i, c in enumerate(CAUSE_CODES)}
#: the causes only the live session decides (``companion.mavlink.session``: the link, the loop's own
#: timing, the flow's age on the caller's clock); no step returns them
SESSION_CAUSES = (HoldCause.FLOW_STALE, HoldCause.LINK, HoldCause.COMPANION_STALLED, HoldCause.BACKLOG)
#: the causes found by comparing a frame with the ones before it (``Plausibility``)
CROSS_FRAME_CAUSES = (HoldCause.VELOCITY_JUMP, HoldCause.FLOW_FROZEN, HoldCause.GYRO_FROZEN)


class FrameOrder(enum.Enum):
    """Where a flow frame's time stands against the last frame's (``classify_frame``)."""

    NEW = "new"
    DUPLICATE = "duplicate or out of order"
    REBOOT = "vehicle reboot"


def classify_frame(prev_time_s: float | None, time_s: float, reboot_jump_s: float = FRAME_REBOOT_S) -> FrameOrder:
    """Is a flow frame at ``time_s`` (s) new, a duplicate or out of order (not after the last
    frame's ``prev_time_s``, by at most ``reboot_jump_s``), or the first after a vehicle reboot
    (further back)? A time that is not a number, or no last frame, is new. The time part of
    ``repeat_mask`` and ``CompanionCore.on_flow``'s rule, and the live session's."""
    if prev_time_s is None:
        return FrameOrder.NEW
    dt = time_s - prev_time_s
    if rules.duplicate_time(dt, reboot_jump_s):
        return FrameOrder.DUPLICATE
    if dt < -reboot_jump_s:
        return FrameOrder.REBOOT
    return FrameOrder.NEW


class GyroSource(enum.StrEnum):
    AUTO = "auto"
    IMU = "imu"
    FLOW = "flow"


@dataclass(frozen=True)
class TiltFilter:
    """Optional velocity filter: a steady-state two-state observer per axis, off by default.

    Predict with the plant's kinematics (eq. 28 without the external force),
    ``v_dot = -g tan(pitch) + b`` (x) and ``+g tan(roll) + b`` (y), from the autopilot's
    ATTITUDE, with ``b`` an unknown slowly varying acceleration (drag, wind, trim), then correct
    with eq. 15: ``v += velocity_gain * innovation``, ``b += disturbance_gain_per_s * dt *
    innovation``. The disturbance state removes the steady-state bias a tilt-only predictor has
    under a steady force. Gains for 50 Hz frames; the error dynamics have poles at 0.83 and
    0.965 per frame (time constants 0.11 s and 0.56 s). Without a fresh attitude (older than
    ``max_attitude_age_s``) or after a held frame it restarts from the measurement.
    """

    velocity_gain: float = 0.2
    disturbance_gain_per_s: float = 15.0
    max_attitude_age_s: float = 0.1


class VelocityEstimator(enum.StrEnum):
    """What the PI flies on (``[companion] velocity_estimator``)."""

    AUTO = "auto"
    EQ15 = "eq15"
    TILT = "tilt"
    KF = "kf"


@dataclass(frozen=True)
class EstimatorOptions:
    """Choices beyond the paper's estimator; the defaults keep every profile exactly eq. 15 (a
    config's ``velocity_estimator``, through ``from_config``, may choose otherwise).

    ``tilt_filter`` given with the default ``estimator`` selects the tilt filter (the form before
    issue 19); ``estimator`` TILT without one uses ``TiltFilter()``'s gains. ``kalman``: the
    Kalman filter's settings instead of the config's (``kalman_settings``), for studies."""

    gyro_source: GyroSource = GyroSource.AUTO
    tilt_filter: TiltFilter | None = None
    estimator: VelocityEstimator = VelocityEstimator.EQ15
    kalman: KalmanSettings | None = None

    @classmethod
    def from_config(cls, cfg: Config) -> EstimatorOptions:
        """The options the ``[companion]`` table selects (``gyro_source``, ``velocity_estimator``)."""
        est = VelocityEstimator(cfg.companion.velocity_estimator)
        return cls(GyroSource(cfg.companion.gyro_source), TiltFilter() if est is VelocityEstimator.TILT else None,
                   est)

    def resolved_gyro(self, profile: Profile) -> GyroSource:
        """``auto`` -> ``flow`` for ardupilot (validated on ArduCopter SITL), ``imu`` otherwise."""
        if self.gyro_source is GyroSource.AUTO:
            return GyroSource.FLOW if profile is Profile.ARDUPILOT else GyroSource.IMU
        return self.gyro_source

    def resolved_estimator(self, profile: Profile) -> VelocityEstimator:
        """``auto`` -> ``kf`` for ardupilot and px4, ``eq15`` for paper (its figures are eq. 15's)."""
        est = self.estimator
        if est is VelocityEstimator.AUTO:
            return VelocityEstimator.EQ15 if profile is Profile.PAPER else VelocityEstimator.KF
        if est is VelocityEstimator.EQ15 and self.tilt_filter is not None:
            return VelocityEstimator.TILT
        return est

    def resolved_tilt(self, profile: Profile) -> TiltFilter | None:
        """The tilt filter's gains when the tilt filter is selected, else None."""
        if self.resolved_estimator(profile) is not VelocityEstimator.TILT:
            return None
        return self.tilt_filter if self.tilt_filter is not None else TiltFilter()


def kalman_settings(cfg: Config, profile: Profile) -> KalmanSettings:
    """The velocity Kalman filter's noise model for ``profile`` (counts: Q's quantization)."""
    return KalmanSettings.from_config(cfg, counts=profile is Profile.PAPER)


def gyro_window_mean(samples: Sequence[tuple[float, float, float]], t0_s: float, t1_s: float,
                     max_skew_s: float) -> tuple[float, float] | None:
    """The gyro's mean over [``t0_s``, ``t1_s``] from ``samples`` (time s, gx, gy rad/s) in
    arrival order: the samples joined by straight lines (held before the first and after the
    last), integrated exactly and divided by the window. Samples that are not finite or that
    do not advance in time are left out; None when no sample lies within ``max_skew_s`` of the
    window (nothing to say about its rotation)."""
    ts: list[float] = []
    xs: list[float] = []
    ys: list[float] = []
    lo, hi = t0_s - max_skew_s, t1_s + max_skew_s
    for t, gx, gy in samples:
        if lo <= t <= hi and gx - gx == 0.0 and gy - gy == 0.0 and (not ts or t > ts[-1]):
            ts.append(t)
            xs.append(gx)
            ys.append(gy)
    if not ts:
        return None
    if not t1_s > t0_s:
        i = min(range(len(ts)), key=lambda k: abs(ts[k] - t0_s))
        return xs[i], ys[i]

    def at(x: float) -> tuple[float, float]:
        i = bisect.bisect_right(ts, x)
        if i == 0:
            return xs[0], ys[0]
        if i == len(ts):
            return xs[-1], ys[-1]
        w = (x - ts[i - 1]) / (ts[i] - ts[i - 1])
        return xs[i - 1] + w * (xs[i] - xs[i - 1]), ys[i - 1] + w * (ys[i] - ys[i - 1])

    knots = [t0_s, *(t for t in ts if t0_s < t < t1_s), t1_s]
    sx = sy = 0.0
    pa = at(knots[0])
    for a, b in zip(knots[:-1], knots[1:], strict=True):
        pb = at(b)
        sx += 0.5 * (pa[0] + pb[0]) * (b - a)
        sy += 0.5 * (pa[1] + pb[1]) * (b - a)
        pa = pb
    span = t1_s - t0_s
    return sx / span, sy / span


def kalman_measurement(vx_m_s: float, vy_m_s: float, gyro_x_rad_s: float, gyro_y_rad_s: float,
                       mean_gyro: tuple[float, float] | None, range_m: float) -> tuple[float, float]:
    """eq. 15 as the Kalman filter takes it. When the flow is an increment over a window (counts,
    integrated radians) and the gyro is the IMU's, the rotation removed is the gyro's mean over
    the window the flow sample covers (``gyro_window_mean``), not the sample nearest the message's
    time (``V_x = (-omega_y - Omega_x) A``: ``omega_y`` -> its mean adds ``(g_y - mean) A``; None:
    eq. 15 as it is). A rate (ardupilot) and the flow message's own body rate are used as they are."""
    if mean_gyro is None:
        return vx_m_s, vy_m_s
    return (vx_m_s + (gyro_y_rad_s - mean_gyro[1]) * range_m,
            vy_m_s - (gyro_x_rad_s - mean_gyro[0]) * range_m)


def kalman_span(integration_s: float, dt_s: float) -> float:
    """The time the flow of a frame covers: the integration time its message states, else the
    frame spacing (``rules.covered_span``, ``estimator.scene_rate``'s too)."""
    return float(rules.covered_span(integration_s, dt_s))


def kalman_columns(kf: VelocityKalman, usable: np.ndarray, record: np.ndarray, time_s: np.ndarray,
                   span_s: np.ndarray, z_x: np.ndarray, z_y: np.ndarray, range_m: np.ndarray,
                   att_record: np.ndarray, att_time_s: np.ndarray, att_roll_rad: np.ndarray,
                   att_pitch_rad: np.ndarray, att_roll_rate_rad_s: np.ndarray, att_pitch_rate_rad_s: np.ndarray,
                   accel: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``VelocityKalman`` over a recording's frames as the live core runs it: before each frame
    every ATTITUDE received before it (``record`` order) goes to ``on_attitude`` and, with
    ``accel`` (record, time s, body x and y specific force m/s^2 of the gyro messages,
    ``profiles.accel_m_s2``), every accelerometer sample to ``on_accel``, the two in the order
    they were received; each usable frame is ``update``d. Returns (vx, vy, var_x, var_y), NaN
    on the frames not usable."""
    n = len(time_s)
    out = np.full((4, n), np.nan)
    att = [a.tolist() for a in (att_time_s, att_roll_rad, att_pitch_rad, att_roll_rate_rad_s, att_pitch_rate_rad_s)]
    rows = list(zip(*att, strict=True))
    in_rec = att_record
    if accel is not None and len(accel[0]):  # attitude and accelerometer rows merged by arrival
        acc_rows = list(zip(*(a.tolist() for a in accel[1:]), strict=True))
        in_rec = np.concatenate([att_record, accel[0]])
        order = np.argsort(in_rec, kind="stable")
        in_rec = in_rec[order]
        tagged = [(kf.on_attitude, r) for r in rows] + [(kf.on_accel, r) for r in acc_rows]
        calls = [tagged[k] for k in order.tolist()]
    else:
        calls = [(kf.on_attitude, r) for r in rows]
    j_end = native.searchsorted(in_rec, record, side="left")  # rows received before each frame
    cols = [c.tolist() for c in (time_s, span_s, z_x, z_y, range_m)]
    j = 0
    update = kf.update
    for i, (ok, end) in enumerate(zip(usable.tolist(), j_end.tolist(), strict=True)):
        while j < end:
            fn, row = calls[j]
            fn(*row)
            j += 1
        if ok:
            out[:, i] = update(cols[0][i], cols[1][i], cols[2][i], cols[3][i], cols[4][i])
    return out[0], out[1], out[2], out[3]


@dataclass(frozen=True)
class StepParams:
    """Everything one step needs, bound once from a ``Config`` (SI units)."""

    nominal_frame_s: float
    max_gyro_skew_s: float
    range_timeout_s: float
    gyro_limit_rad_s: float
    range_min_m: float
    range_max_m: float
    max_scene_rate_rad_s: float
    repeat_window_s: float
    kp_rad_per_m_s: float
    ki_rad_per_m: float
    limit_rad: float
    gravity_m_s2: float

    @classmethod
    def from_config(cls, cfg: Config) -> StepParams:
        c = cfg.companion
        t_nom = cfg.flow_sensor.frame_period_s
        return cls(
            nominal_frame_s=t_nom,
            max_gyro_skew_s=c.max_gyro_skew_s,
            range_timeout_s=c.range_timeout_s,
            gyro_limit_rad_s=math.radians(cfg.imu.gyro_range_deg_s) * 0.999,
            range_min_m=cfg.rangefinder.min_m,
            range_max_m=cfg.rangefinder.max_m,
            # a spike: more than this scene-angle rate (rad/s) in one frame
            max_scene_rate_rad_s=c.max_flow_rate_rad_s,
            repeat_window_s=REPEAT_WINDOW_FRAMES * t_nom,
            kp_rad_per_m_s=cfg.controller.kp_rad_per_m_s,
            ki_rad_per_m=cfg.controller.ki_rad_per_m,
            limit_rad=cfg.controller.tilt_limit_rad,
            gravity_m_s2=cfg.airframe.gravity_m_s2,
        )


@dataclass(frozen=True)
class StepOutput:
    """The result of one control step (one flow frame). Angles in rad, speeds in m/s."""

    time_s: float  # the flow frame's sensor time
    dt_s: float  # the time the frame covers
    vx_m_s: float  # estimate used by the PI (NaN when the frame was not usable)
    vy_m_s: float
    vx_set_m_s: float
    vy_set_m_s: float
    roll_cmd_rad: float
    pitch_cmd_rad: float
    hold_cause: HoldCause
    gyro_x_rad_s: float
    gyro_y_rad_s: float
    range_m: float
    #: eq. 15 before the optional tilt filter (equal to vx_m_s without it)
    vx_raw_m_s: float = math.nan
    vy_raw_m_s: float = math.nan
    #: True when this flow message repeated the last sample, or came out of order: nothing was
    #: stepped, this is the previous step's output again
    repeat: bool = False
    #: the variance of vx_m_s, vy_m_s (m^2/s^2) when the Kalman filter made them, else NaN
    vx_var_m2_s2: float = math.nan
    vy_var_m2_s2: float = math.nan

    @property
    def holding(self) -> bool:
        return self.hold_cause is not HoldCause.NONE


# ---------------------------------------------------------------------------------------------
# 1. Gating and eq. 15, elementwise over frames (scalars in length-1 arrays, or whole columns)


#: the per-frame gates in the order they are checked (the first that fails names the cause)
GATE_CAUSES = CAUSE_CODES[1:8]


def _gates(time_s: Any, scene_x: Any, scene_y: Any, quality: Any, gyro_found: Any, gyro_x_rad_s: Any,
           gyro_y_rad_s: Any, range_found: Any, range_time_s: Any, range_m: Any, p: StepParams) -> Iterator[Any]:
    """Each gate of ``GATE_CAUSES`` in turn (True: the frame fails it), one frame or columns:
    ``companion.step.rules``' predicates, evaluated lazily so that one frame stops at the first."""
    yield rules.flow_invalid(time_s, scene_x, scene_y)
    yield rules.quality_zero(quality)
    yield gyro_found == False  # noqa: E712 (arrays too)
    yield rules.gyro_invalid(gyro_x_rad_s, gyro_y_rad_s, p.gyro_limit_rad_s)
    yield range_found == False  # noqa: E712
    yield rules.range_invalid(range_m, p.range_min_m, p.range_max_m)
    yield rules.range_stale(time_s, range_time_s, p.range_timeout_s)


def gate_frames(time_s: np.ndarray, scene_x: np.ndarray, scene_y: np.ndarray, quality: np.ndarray,
                gyro_found: np.ndarray, gyro_x_rad_s: np.ndarray, gyro_y_rad_s: np.ndarray,
                range_found: np.ndarray, range_time_s: np.ndarray, range_m: np.ndarray, *,
                p: StepParams) -> np.ndarray:
    """Hold-cause code of each frame (index into ``CAUSE_CODES``; 0 = usable), before the spike
    check: the first gate of ``GATE_CAUSES`` the frame fails (``_gates``): flow not finite,
    quality 0 (or not a number), no gyro, gyro saturated or not finite, no range, range outside
    the limits, range stale."""
    with np.errstate(all="ignore"):
        conds = list(_gates(time_s, scene_x, scene_y, np.asarray(quality, dtype=float), np.asarray(gyro_found),
                            gyro_x_rad_s, gyro_y_rad_s, np.asarray(range_found), range_time_s, range_m, p))
    codes = np.select(conds, [_CODE[c] for c in GATE_CAUSES], default=0)
    return codes.astype(np.int8)


def gate_frame(time_s: float, scene_x: float, scene_y: float, quality: float, gyro_found: bool,
               gyro_x_rad_s: float, gyro_y_rad_s: float, range_found: bool, range_time_s: float, range_m: float, *,
               p: StepParams) -> HoldCause:
    """``gate_frames`` for one frame (the live loop): the same gates, stopping at the first."""
    for cause, failed in zip(GATE_CAUSES, _gates(time_s, scene_x, scene_y, quality, gyro_found, gyro_x_rad_s,
                                                 gyro_y_rad_s, range_found, range_time_s, range_m, p), strict=True):
        if failed:
            return cause
    return HoldCause.NONE


def estimate_frames(codes: np.ndarray, time_s: np.ndarray, prev_time_s: np.ndarray, scene_x: np.ndarray,
                    scene_y: np.ndarray, increment: bool, integration_s: np.ndarray, gyro_x_rad_s: np.ndarray,
                    gyro_y_rad_s: np.ndarray, range_m: np.ndarray, *, p: StepParams
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 15 on the usable frames, and the spike check.

    ``prev_time_s``: the previous flow frame's time (NaN for none); the frame spacing follows
    ``estimator.frame_spacing``. Returns (codes with FLOW_SPIKE added, vx_m_s, vy_m_s, dt_s,
    scene_rate_x_rad_s, scene_rate_y_rad_s); held frames have NaN velocity and the nominal
    frame period as dt.
    """
    ok = codes == 0
    with np.errstate(all="ignore"):
        d = time_s - prev_time_s
        dt = np.where(ok, rules.spacing(d, p.nominal_frame_s), p.nominal_frame_s)
        rate_x = scene_rate(scene_x, increment, integration_s, dt)
        rate_y = scene_rate(scene_y, increment, integration_s, dt)
        vx, vy = velocity_from_flow(rate_x, rate_y, gyro_x_rad_s, gyro_y_rad_s, range_m)
        spike = ok & rules.scene_spike(rate_x, rate_y, p.max_scene_rate_rad_s)
    codes = np.where(spike, np.int8(_CODE[HoldCause.FLOW_SPIKE]), codes).astype(np.int8)
    usable = codes == 0
    return codes, np.where(usable, vx, np.nan), np.where(usable, vy, np.nan), dt, rate_x, rate_y


# ---------------------------------------------------------------------------------------------
# 2. The live alignment rules over a recording's columns


def frame_repeat_window(integration_s: Any, body_x_rad_s: Any, body_y_rad_s: Any, nominal_window_s: float,
                        profile: Profile) -> Any:
    """The repeat window of a frame, or of each of a column of frames: ``REPEAT_WINDOW_FRAMES``
    of the reading's own span when the message states one, else the nominal window
    (``rules.repeat_window``). In the ``ardupilot`` profile the window is infinite: float rates
    equal to the bit are the sample ArduPilot re-sends (it keeps streaming the last sample ~0.5 s
    after the sensor stops), never a new one, so a frozen flow is a lost flow (issue 18). The one
    exception: body rates (the gyro ArduPilot sends with the sample) both exactly 0.0 keep the
    frame window: a real gyro is never exactly 0.0, so such a sample comes from a noise-free
    (simulated or converted) source, where a still sensor really repeats."""
    window = rules.repeat_window(integration_s, nominal_window_s, REPEAT_WINDOW_FRAMES)
    if profile is Profile.ARDUPILOT:
        return rules.select((body_x_rad_s == 0.0) & (body_y_rad_s == 0.0), window, math.inf)
    return window


def repeat_window(integration_s: np.ndarray, nominal_window_s: float,
                  profile: Profile = Profile.PAPER, payload: np.ndarray | None = None) -> np.ndarray:
    """``frame_repeat_window`` of each frame, the body rates from ``payload`` (n, 6, as
    ``CompanionCore.payload``); without it none is exactly 0.0."""
    integ = np.asarray(integration_s, dtype=float)
    body = np.full((len(integ), 2), np.nan) if payload is None else np.asarray(payload, dtype=float)[:, 4:6]
    with np.errstate(invalid="ignore"):
        return np.asarray(frame_repeat_window(integ, body[:, 0], body[:, 1], nominal_window_s, profile))


def repeat_mask(time_s: np.ndarray, payload: np.ndarray, window_s: float | np.ndarray) -> np.ndarray:
    """Which flow messages (in arrival order) ``CompanionCore.on_flow`` does not step
    (``rules.is_repeat``): the same sample again (payload (n, k) equal to the last frame's, NaN
    equal to NaN, and ``0 <= t - t_last < window_s``) or a time not after the last frame's
    (``-FRAME_REBOOT_S <= t - t_last <= 0``). ``t_last``: the time of the last stepped frame with
    a finite time."""
    n = len(time_s)
    rep = np.zeros(n, dtype=bool)
    if n < 2:
        return rep
    window_s = np.broadcast_to(np.asarray(window_s, dtype=float), (n,))
    # as long as nothing is skipped, the last frame is the previous message with a finite time
    finite = np.isfinite(time_s)
    idx = np.maximum.accumulate(np.where(finite, np.arange(n), -1))
    t_last = np.full(n, np.nan)
    t_last[1:] = np.where(idx[:-1] >= 0, time_s[np.maximum(idx[:-1], 0)], np.nan)
    same = np.zeros(n, dtype=bool)
    same[1:] = np.all(rules.same_value(payload[1:], payload[:-1]), axis=1)
    with np.errstate(invalid="ignore"):
        flagged = rules.is_repeat(time_s - t_last, same, window_s)
    if not flagged.any():
        return rep
    # from the first skipped message on, each decision depends on the previous ones: walk them
    k = int(np.argmax(flagged))
    t = time_s.tolist()
    rows = payload.tolist()
    last_t = t_last[k]
    last_row = rows[k - 1]
    windows = window_s.tolist()
    same_value, is_repeat = rules.same_value, rules.is_repeat
    for i in range(k, n):
        row = rows[i]
        same_row = all(same_value(x, y) for x, y in zip(row, last_row, strict=True))
        if is_repeat(t[i] - last_t, same_row, windows[i]):
            rep[i] = True
            continue
        last_row = row
        if t[i] == t[i] and abs(t[i]) != math.inf:
            last_t = t[i]
    return rep


def latest_before(event_record: np.ndarray, query_record: np.ndarray) -> np.ndarray:
    """Index of the latest event received before each query (both sorted by ``record``); -1 if none."""
    return native.searchsorted(event_record, query_record, side="left") - 1  # np.searchsorted, compiled


def gyro_history_columns(gyro_record: np.ndarray, gyro_time_s: np.ndarray, flow_record: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """The gyro samples ``CompanionCore`` holds when each flow frame arrives, as index bounds
    (first, last) into the gyro columns (inclusive; last -1: none): the newest ``GYRO_HISTORY``
    received before the frame since the last reboot (``align_gyro_columns``'s rule)."""
    if len(gyro_record) == 0:
        e = np.full(len(flow_record), -1, dtype=np.int64)
        return e, e
    with np.errstate(invalid="ignore"):
        reboot = np.zeros(len(gyro_time_s), dtype=bool)
        reboot[1:] = gyro_time_s[1:] < gyro_time_s[:-1] - GYRO_REBOOT_S
    start = np.maximum.accumulate(np.where(reboot, np.arange(len(gyro_time_s)), 0))
    last = latest_before(gyro_record, flow_record)
    first = np.where(last >= 0, np.maximum(start[np.maximum(last, 0)], last - (GYRO_HISTORY - 1)), 0)
    return first, last


def align_gyro_columns(gyro_record: np.ndarray, gyro_time_s: np.ndarray, flow_record: np.ndarray,
                       flow_time_s: np.ndarray, max_skew_s: float) -> np.ndarray:
    """The gyro sample ``CompanionCore`` aligns with each flow frame, from columns.

    Emulates the live history exactly: only samples received before the flow message, the
    newest ``GYRO_HISTORY`` of them since the last reboot (a sample more than ``GYRO_REBOOT_S``
    before its predecessor clears the history); scanning from the newest, the one nearest the
    frame's time within ``max_skew_s`` (ties: the older), the scan stopping at the first sample
    older than the frame by more than ``max_skew_s``. Returns the gyro index per frame, or -1.
    """
    n_f = len(flow_record)
    if len(gyro_record) == 0 or n_f == 0:
        return np.full(n_f, -1, dtype=np.int64)
    with np.errstate(invalid="ignore"):
        reboot = np.zeros(len(gyro_time_s), dtype=bool)
        reboot[1:] = gyro_time_s[1:] < gyro_time_s[:-1] - GYRO_REBOOT_S
    start = np.maximum.accumulate(np.where(reboot, np.arange(len(gyro_time_s)), 0))
    last = latest_before(gyro_record, flow_record)  # newest sample received before each frame
    best = np.full(n_f, -1, dtype=np.int64)
    best_skew = np.full(n_f, max_skew_s)
    alive = last >= 0  # the scan has not stopped yet
    lo = np.where(alive, start[np.maximum(last, 0)], 0)
    lo = np.maximum(lo, last - (GYRO_HISTORY - 1))
    for k in range(GYRO_HISTORY):
        j = last - k
        alive &= j >= lo
        if not alive.any():
            break
        jj = np.where(alive, j, 0)
        with np.errstate(invalid="ignore"):
            skew, take, stop = rules.gyro_scan(gyro_time_s[jj], flow_time_s, best_skew, max_skew_s)
        take &= alive
        stop &= alive
        best = np.where(take, jj, best)
        best_skew = np.where(take, skew, best_skew)
        alive &= ~stop
    return best


# ---------------------------------------------------------------------------------------------
# 3. The sequential part: tilt filter and PI


#: filter state: (vx, vy, bx, by, initialised)
FilterState = tuple[float, float, float, float, bool]
FILTER_RESET: FilterState = (0.0, 0.0, 0.0, 0.0, False)
#: frames the PI runs vectorised at a time between saturations
_PI_BLOCK = 4096


def tilt_filter_step(filt: FilterState, vx_m_s: float, vy_m_s: float, roll_rad: float, pitch_rad: float,
                     dt_s: float, *, gravity_m_s2: float, tilt: TiltFilter) -> FilterState:
    """One usable frame of the tilt filter (``TiltFilter``): predict with the attitude, correct
    with eq. 15 (``vx_m_s``, ``vy_m_s``). ``roll_rad``/``pitch_rad`` NaN (no fresh attitude) or an
    uninitialised state: restart from the measurement. Returns the new state; its first two
    entries are the filtered velocity."""
    fresh = roll_rad == roll_rad and pitch_rad == pitch_rad  # not NaN
    if not (filt[4] and fresh):
        return (vx_m_s, vy_m_s, 0.0, 0.0, fresh)
    # eq. 28 without the force: v_dot = -g tan(pitch) (x), +g tan(roll) (y), plus the disturbance b
    px = filt[0] + (-gravity_m_s2 * math.tan(pitch_rad) + filt[2]) * dt_s
    py = filt[1] + (gravity_m_s2 * math.tan(roll_rad) + filt[3]) * dt_s
    ix, iy = vx_m_s - px, vy_m_s - py
    kb = tilt.disturbance_gain_per_s * dt_s
    return (px + tilt.velocity_gain * ix, py + tilt.velocity_gain * iy, filt[2] + kb * ix, filt[3] + kb * iy,
            True)


def tilt_filter_columns(filt: FilterState, active: np.ndarray, vx_m_s: np.ndarray, vy_m_s: np.ndarray,
                        roll_rad: np.ndarray, pitch_rad: np.ndarray, dt_s: np.ndarray, *, gravity_m_s2: float,
                        tilt: TiltFilter) -> tuple[FilterState, np.ndarray, np.ndarray]:
    """``tilt_filter_step`` over frames; inactive frames (held or not engaged) reset the filter
    and pass their input through. Returns (state, vx_filtered, vy_filtered)."""
    out_x = np.array(vx_m_s, dtype=float)
    out_y = np.array(vy_m_s, dtype=float)
    step = tilt_filter_step
    cols = [a.tolist() for a in (vx_m_s, vy_m_s, roll_rad, pitch_rad, dt_s)]
    for i, (act, v_x, v_y, r, pt, d) in enumerate(zip(active.tolist(), *cols, strict=True)):
        if not act:
            filt = FILTER_RESET
            continue
        filt = step(filt, v_x, v_y, r, pt, d, gravity_m_s2=gravity_m_s2, tilt=tilt)
        out_x[i], out_y[i] = filt[0], filt[1]
    return filt, out_x, out_y


def pi_axis_columns(integral_m: float, active: np.ndarray, reset: np.ndarray, err_m_s: np.ndarray,
                    dt_s: np.ndarray, *, kp: float, ki: float, limit_rad: float) -> tuple[float, np.ndarray]:
    """One axis of the PI law (``controller._axis``, the arithmetic of ``pi_step``) over frames.

    ``active`` frames step the integral; ``reset`` frames set it to 0; the others leave it.
    Returns (final integral m, effort rad per frame; 0 where not active). While the effort stays
    inside the limit the law is linear and runs vectorised: ``np.add.accumulate`` performs the
    very additions ``integral + err * dt`` of the frame-by-frame law, in the same order, so
    the result is bit-identical; the frames that saturate go through ``_axis`` one by one."""
    n = len(active)
    effort = np.zeros(n)
    events = np.flatnonzero(active | reset)
    if len(events) == 0:
        return integral_m, effort
    is_reset = reset[events]
    x_all = err_m_s[events] * dt_s[events]
    e_all = err_m_s[events]
    d_all = dt_s[events]
    m = len(events)
    # for each event: the next reset event and the next active event at or after it (m: none)
    ar = np.arange(m + 1)
    r_idx, a_idx = np.flatnonzero(is_reset), np.flatnonzero(~is_reset)
    next_reset = np.append(r_idx, m)[native.searchsorted(r_idx, ar)]
    next_active = np.append(a_idx, m)[native.searchsorted(a_idx, ar)]
    eff_ev = np.zeros(m)
    i = integral_m
    k = 0
    while k < m:
        if is_reset[k]:  # a run of reset events: the integral restarts from 0
            i = 0.0
            k = int(next_active[k])
            continue
        end = min(k + _PI_BLOCK, int(next_reset[k]))
        x = x_all[k:end]
        cand = np.add.accumulate(np.concatenate(([i], x)))[1:]
        eff = kp * e_all[k:end] + ki * cand
        sat = (eff > limit_rad) | (eff < -limit_rad)
        first = int(np.argmax(sat)) if sat.any() else end - k
        eff_ev[k:k + first] = eff[:first]
        if first:
            i = float(cand[first - 1])
        k += first
        # through the saturated stretch frame by frame, up to and including the first frame inside
        while k < end:
            i, eff_k = _axis(i, float(e_all[k]), float(d_all[k]), kp, ki, limit_rad)
            eff_ev[k] = eff_k
            k += 1
            if -limit_rad < eff_k < limit_rad:
                break
    effort[events] = np.where(is_reset, 0.0, eff_ev)
    return i, effort


def control_step(pi: tuple[float, float], filt: FilterState, usable: bool, engaged: bool, vx_m_s: float,
                 vy_m_s: float, roll_rad: float, pitch_rad: float, vx_set_m_s: float, vy_set_m_s: float,
                 dt_s: float, *, p: StepParams, tilt: TiltFilter | None
                 ) -> tuple[tuple[float, float], FilterState, float, float, float, float]:
    """``run_control`` for one frame, in plain Python (the live loop): the same
    ``tilt_filter_step`` and the same PI arithmetic (``controller._axis``); tested equal."""
    step, reset = rules.control_action(usable, engaged)
    if reset:
        return (0.0, 0.0), FILTER_RESET, vx_m_s, vy_m_s, 0.0, 0.0
    if not step:
        return pi, FILTER_RESET, vx_m_s, vy_m_s, 0.0, 0.0
    if tilt is not None:
        filt = tilt_filter_step(filt, vx_m_s, vy_m_s, roll_rad, pitch_rad, dt_s, gravity_m_s2=p.gravity_m_s2,
                                tilt=tilt)
        vx_m_s, vy_m_s = filt[0], filt[1]
    else:
        filt = FILTER_RESET
    integ_x, effort_x = _axis(pi[0], vx_set_m_s - vx_m_s, dt_s, p.kp_rad_per_m_s, p.ki_rad_per_m, p.limit_rad)
    integ_y, effort_y = _axis(pi[1], vy_set_m_s - vy_m_s, dt_s, p.kp_rad_per_m_s, p.ki_rad_per_m, p.limit_rad)
    return (integ_x, integ_y), filt, vx_m_s, vy_m_s, effort_y, -effort_x


def run_control(pi: tuple[float, float], filt: FilterState, usable: np.ndarray, engaged: np.ndarray,
                vx_m_s: np.ndarray, vy_m_s: np.ndarray, roll_rad: np.ndarray, pitch_rad: np.ndarray,
                vx_set_m_s: np.ndarray, vy_set_m_s: np.ndarray, dt_s: np.ndarray, *, p: StepParams,
                tilt: TiltFilter | None
                ) -> tuple[tuple[float, float], FilterState, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The sequential part of the step over frames (one frame live, all of them in replay).

    ``pi``: integrals (x, y) m; ``filt``: the tilt filter's state; ``roll_rad``/``pitch_rad``:
    the fresh attitude for the filter (NaN: none). Not engaged: integrals and filter reset,
    level command. Not usable (held): integrals frozen, filter reset, level command. Otherwise
    the optional filter, then the PI law. Returns (pi, filt, vx_used, vy_used, roll_cmd_rad,
    pitch_cmd_rad)."""
    active, reset = rules.control_action(usable, engaged)
    if tilt is not None:
        filt, vx_m_s, vy_m_s = tilt_filter_columns(filt, active, vx_m_s, vy_m_s, roll_rad, pitch_rad, dt_s,
                                                   gravity_m_s2=p.gravity_m_s2, tilt=tilt)
    elif len(active):
        filt = FILTER_RESET
    with np.errstate(all="ignore"):
        ex = np.where(active, vx_set_m_s - vx_m_s, 0.0)
        ey = np.where(active, vy_set_m_s - vy_m_s, 0.0)
    ix, eff_x = pi_axis_columns(pi[0], active, reset, ex, dt_s, kp=p.kp_rad_per_m_s, ki=p.ki_rad_per_m,
                                limit_rad=p.limit_rad)
    iy, eff_y = pi_axis_columns(pi[1], active, reset, ey, dt_s, kp=p.kp_rad_per_m_s, ki=p.ki_rad_per_m,
                                limit_rad=p.limit_rad)
    pitch_cmd = np.where(active, -eff_x, 0.0)
    return (ix, iy), filt, vx_m_s, vy_m_s, eff_y, pitch_cmd


# ---------------------------------------------------------------------------------------------
# 4. Checks across frames (what one frame cannot show)


#: the estimate may move by the flow of this many counts per frame beyond what the vehicle can
#: accelerate (quantization and sensor noise) before a frame is an outlier
JUMP_NOISE_COUNTS = 8.0
#: an outlier lasting more than this many frames is a real change: the estimate re-anchors on it
JUMP_HOLD_FRAMES = 3
#: a sensor repeating the same values this long (s) while the vehicle turns has stopped seeing
FROZEN_WINDOW_S = 0.5
#: ... "turns": the rotation rate spans this many counts of flow per frame across the window
FROZEN_ROTATION_COUNTS = 3.0
#: floors of the two allowances in rad/s, for sensors whose noise is not their quantization
#: (ArduPilot's flow rates, a fine Q): the values Table VI's Q gives (0.63 and 0.24 rad/s) rounded down
JUMP_NOISE_FLOOR_RAD_S = 0.5
FROZEN_ROTATION_FLOOR_RAD_S = 0.2


@dataclass(frozen=True)
class PlausibilityParams:
    """Bounds of the cross-frame checks (SI units), bound once from a ``Config``.

    ``max_accel_m_s2``: the fastest the vehicle can change its velocity, twice ``g tan(tilt
    limit)`` (the tilt limit's acceleration, and as much again for wind and transients).
    ``jump_noise_rad_s``: ``JUMP_NOISE_COUNTS`` counts per frame as a scene rate, at least
    ``JUMP_NOISE_FLOOR_RAD_S``. ``frozen_frames``: ``FROZEN_WINDOW_S`` in frames.
    ``frozen_rotation_rad_s``: ``FROZEN_ROTATION_COUNTS`` counts per frame as a body rate, at least
    ``FROZEN_ROTATION_FLOOR_RAD_S``.
    """

    max_accel_m_s2: float
    jump_noise_rad_s: float
    jump_hold_frames: int
    frozen_frames: int
    frozen_rotation_rad_s: float

    @classmethod
    def from_config(cls, cfg: Config) -> PlausibilityParams:
        t = cfg.flow_sensor.frame_period_s
        q = cfg.flow_sensor.q_rad_per_count
        return cls(max_accel_m_s2=2.0 * cfg.airframe.gravity_m_s2 * math.tan(cfg.controller.tilt_limit_rad),
                   jump_noise_rad_s=max(JUMP_NOISE_COUNTS * q / t, JUMP_NOISE_FLOOR_RAD_S),
                   jump_hold_frames=JUMP_HOLD_FRAMES, frozen_frames=max(2, round(FROZEN_WINDOW_S / t)),
                   frozen_rotation_rad_s=max(FROZEN_ROTATION_COUNTS * q / t, FROZEN_ROTATION_FLOOR_RAD_S))


def _span(values: deque[float]) -> float:
    return max(values) - min(values) if values else 0.0


class Plausibility:
    """What one frame cannot show, checked across frames (pure: times come with the frames).

    - **velocity jump**: eq. 15's estimate moved further from the last accepted one than the
      vehicle can accelerate in the time between (``max_accel_m_s2 * dt``) plus the flow noise
      at the lower of the two ranges (``jump_noise_rad_s * range``): a flow spike below the
      sensor's limit, a one-reading range or gyro glitch. Such a frame is held (level, integrator
      frozen) instead of kicking the vehicle; a change that lasts more than ``jump_hold_frames``
      frames is real, and the estimate re-anchors on it.
    - **flow frozen**: the same flow values, frame after frame with the time advancing, for
      ``frozen_frames`` frames while the gyro's rate spans more than ``frozen_rotation_rad_s``
      across them: a working sensor would have seen that rotation (eq. 15's ``omega`` term). Held
      until the values change. Without rotation a frozen sensor cannot be told from steady flight.
    - **gyro frozen**: the same gyro rates for ``frozen_frames`` frames while the autopilot's own
      ATTITUDE rates span more than ``frozen_rotation_rad_s``. Held until the rates change.
    """

    def __init__(self, params: PlausibilityParams) -> None:
        self.p = params
        self.reset()

    def reset(self) -> None:
        """Forget the history (when the vehicle's clock restarts)."""
        self.anchor: tuple[float, float, float, float] | None = None  # (time s, vx, vy, range m) accepted
        self.rejected = 0
        self._flow_value: tuple[float, float] | None = None
        self._flow_rot: tuple[deque[float], deque[float]] = (deque(maxlen=self.p.frozen_frames),
                                                               deque(maxlen=self.p.frozen_frames))
        self.flow_frozen: tuple[float, float] | None = None
        self._gyro_value: tuple[float, float] | None = None
        self._att_rot: tuple[deque[float], deque[float]] = (deque(maxlen=self.p.frozen_frames),
                                                              deque(maxlen=self.p.frozen_frames))
        self.gyro_frozen: tuple[float, float] | None = None

    def check(self, time_s: float, flow_xy: tuple[float, float], gyro_rad_s: tuple[float, float],
              v_m_s: tuple[float, float], range_m: float,
              attitude_rate_rad_s: tuple[float, float] | None) -> HoldCause | None:
        """The cause to hold this frame for, or None. ``flow_xy``: the frame's flow values as
        the message carries them (increments or rates); ``gyro_rad_s``: (roll rate, pitch rate)
        used for the frame; ``v_m_s``: eq. 15's estimate; ``attitude_rate_rad_s``: the latest
        ATTITUDE (rollspeed, pitchspeed), None without one. Call only for frames the core used."""
        if self.anchor is not None and time_s < self.anchor[0]:
            self.reset()  # the clock went back (reboot)
        frozen = self._frozen_flow(flow_xy, gyro_rad_s)
        frozen_gyro = self._frozen_gyro(gyro_rad_s, attitude_rate_rad_s)
        if frozen or frozen_gyro:
            return HoldCause.FLOW_FROZEN if frozen else HoldCause.GYRO_FROZEN
        return self._jump(time_s, v_m_s, range_m)

    def _frozen_flow(self, flow_xy: tuple[float, float], gyro: tuple[float, float]) -> bool:
        if self.flow_frozen is not None:
            if flow_xy == self.flow_frozen:
                return True
            self.flow_frozen = None
        rx, ry = self._flow_rot
        if flow_xy != self._flow_value:
            self._flow_value = flow_xy
            rx.clear()
            ry.clear()
        rot_x, rot_y = rules.flow_rotation(gyro[0], gyro[1])  # the rotation part of eq. 15 on each axis
        rx.append(rot_x)
        ry.append(rot_y)
        if len(rx) == rx.maxlen and rules.rotating(_span(rx), _span(ry), self.p.frozen_rotation_rad_s):
            self.flow_frozen = flow_xy
            return True
        return False

    def _frozen_gyro(self, gyro: tuple[float, float], att: tuple[float, float] | None) -> bool:
        if self.gyro_frozen is not None:
            if gyro == self.gyro_frozen:
                return True
            self.gyro_frozen = None
        ax, ay = self._att_rot
        if gyro != self._gyro_value or att is None:
            self._gyro_value = gyro
            ax.clear()
            ay.clear()
        if att is None:
            return False
        ax.append(att[0])
        ay.append(att[1])
        if len(ax) == ax.maxlen and rules.rotating(_span(ax), _span(ay), self.p.frozen_rotation_rad_s):
            self.gyro_frozen = gyro
            return True
        return False

    def _jump(self, time_s: float, v: tuple[float, float], range_m: float) -> HoldCause | None:
        if self.anchor is not None:
            t0, vx0, vy0, r0 = self.anchor
            allowed = rules.jump_allowance(self.p.max_accel_m_s2, self.p.jump_noise_rad_s, time_s - t0, range_m, r0)
            if rules.velocity_jump(v[0] - vx0, v[1] - vy0, allowed) and self.rejected < self.p.jump_hold_frames:
                self.rejected += 1
                return HoldCause.VELOCITY_JUMP
        self.anchor = (time_s, v[0], v[1], range_m)
        self.rejected = 0
        return None


def _run_length(cont: np.ndarray) -> np.ndarray:
    """Length of the run ending at each index, where ``cont[i]`` says index i continues the run
    of index i-1 (``cont[0]`` is ignored)."""
    n = len(cont)
    idx = np.arange(n)
    start = np.where(cont, -1, idx)
    if n:
        start[0] = 0
    return idx - np.maximum.accumulate(start) + 1


def _trailing_span(x: np.ndarray, m: int) -> np.ndarray:
    """max - min over the last ``m`` values at each index (NaN before ``m`` values exist; NaN
    where the window holds a NaN). The sliding extremes in O(n) whatever ``m`` (van Herk / Gil-Werman:
    a window of ``m`` spans at most two blocks of ``m``; its extreme is that of the block suffix
    it starts in and the block prefix it ends in); ``_trailing_span_direct`` is the same with
    a window view."""
    n = len(x)
    out = np.full(n, np.nan)
    if n >= m:
        out[m - 1:] = _sliding_extreme(x, m, np.maximum, -np.inf) - _sliding_extreme(x, m, np.minimum, np.inf)
    return out


def _sliding_extreme(x: np.ndarray, m: int, op: np.ufunc, neutral: float) -> np.ndarray:
    """``op``-extreme (np.maximum or np.minimum, NaN propagating) of each window ``x[a:a + m]``,
    a = 0 .. len(x) - m."""
    n = len(x)
    blocks = -(-n // m)
    padded = np.full(blocks * m, neutral)
    padded[:n] = x
    grid = padded.reshape(blocks, m)
    if m > 100:
        prefix = op.accumulate(grid, axis=1).reshape(-1)
        suffix = op.accumulate(grid[:, ::-1], axis=1)[:, ::-1].reshape(-1)
        return op(suffix[:n - m + 1], prefix[m - 1:n])
    # the running extremes within each block, a column at a time (the operations of
    # op.accumulate along the rows, in its order: op(so far, next), so the same bits; m calls of
    # `blocks` values each rather than `blocks` calls of m, 1.3-7x faster for the windows of 2-100
    # frames the frozen-sensor screen uses; slower beyond)
    prefix = np.empty_like(grid)
    suffix = np.empty_like(grid)
    prefix[:, 0] = grid[:, 0]
    for j in range(1, m):
        op(prefix[:, j - 1], grid[:, j], out=prefix[:, j])
    suffix[:, m - 1] = grid[:, m - 1]
    for j in range(m - 2, -1, -1):
        op(suffix[:, j + 1], grid[:, j], out=suffix[:, j])
    return op(suffix.reshape(-1)[:n - m + 1], prefix.reshape(-1)[m - 1:n])


def _trailing_span_direct(x: np.ndarray, m: int) -> np.ndarray:
    """``_trailing_span`` with a window view (O(n m)): the definition the tests hold it to."""
    out = np.full(len(x), np.nan)
    if len(x) >= m:
        w = np.lib.stride_tricks.sliding_window_view(x, m)
        out[m - 1:] = w.max(axis=1) - w.min(axis=1)
    return out


def plausibility_columns(params: PlausibilityParams, time_s: np.ndarray, flow_x: np.ndarray, flow_y: np.ndarray,
                         gyro_x_rad_s: np.ndarray, gyro_y_rad_s: np.ndarray, vx_m_s: np.ndarray, vy_m_s: np.ndarray,
                         range_m: np.ndarray, att_rate_x_rad_s: np.ndarray, att_rate_y_rad_s: np.ndarray
                         ) -> list[tuple[int, HoldCause]]:
    """``Plausibility.check`` over a column of frames (those the per-frame gates passed, in
    order): the (index, cause) of each veto, equal to calling ``check`` frame by frame.

    A vectorised screen finds the first frame where any check *could* fire, assuming none fired
    before (then the anchor is always the previous frame and the frozen windows are the trailing
    runs); the sequential checker starts a few windows before it, once its history is full. On
    a flight without a fault that is no Python loop at all. Attitude rates: NaN = none."""
    n = len(time_s)
    if n == 0:
        return []
    p = params
    m = p.frozen_frames
    att_ok = np.isfinite(att_rate_x_rad_s) & np.isfinite(att_rate_y_rad_s)
    same_flow = np.r_[False, (flow_x[1:] == flow_x[:-1]) & (flow_y[1:] == flow_y[:-1])]
    same_gyro = np.r_[False, (gyro_x_rad_s[1:] == gyro_x_rad_s[:-1]) & (gyro_y_rad_s[1:] == gyro_y_rad_s[:-1])]
    with np.errstate(invalid="ignore"):
        rot_x, rot_y = rules.flow_rotation(gyro_x_rad_s, gyro_y_rad_s)
        rot = rules.rotating(_trailing_span(rot_x, m), _trailing_span(rot_y, m), p.frozen_rotation_rad_s)
        frozen_flow = (_run_length(same_flow) >= m) & rot
        att_run = np.where(att_ok, _run_length(same_gyro & att_ok & np.r_[False, att_ok[:-1]]), 0)
        att_rot = rules.rotating(_trailing_span(att_rate_x_rad_s, m), _trailing_span(att_rate_y_rad_s, m),
                                 p.frozen_rotation_rad_s)
        frozen_gyro = (att_run >= m) & att_rot
        jump = np.zeros(n, dtype=bool)
        dt = time_s[1:] - time_s[:-1]
        allowed = rules.jump_allowance(p.max_accel_m_s2, p.jump_noise_rad_s, dt, range_m[1:], range_m[:-1])
        dvx, dvy = vx_m_s[1:] - vx_m_s[:-1], vy_m_s[1:] - vy_m_s[:-1]
        # NaN or a clock going back: left to the sequential checker
        jump[1:] = rules.velocity_jump(dvx, dvy, allowed) | (dt < 0.0) | ~np.isfinite(dvx + dvy) \
            | ~np.isfinite(allowed)
    candidates = np.flatnonzero(frozen_flow | frozen_gyro | jump)
    if len(candidates) == 0:
        return []
    first = max(0, int(candidates[0]) - (m + 2))
    checker = Plausibility(p)
    cols = [c[first:].tolist() for c in (time_s, flow_x, flow_y, gyro_x_rad_s, gyro_y_rad_s, vx_m_s, vy_m_s,
                                          range_m, att_rate_x_rad_s, att_rate_y_rad_s)]
    vetoes = []
    for k, (t, fx, fy, g_x, g_y, v_x, v_y, r, a_x, a_y) in enumerate(zip(*cols, strict=True)):
        rates = (a_x, a_y) if math.isfinite(a_x) and math.isfinite(a_y) else None
        veto = checker.check(t, (fx, fy), (g_x, g_y), (v_x, v_y), r, rates)
        if veto is not None:
            vetoes.append((first + k, veto))
    return vetoes


# ---------------------------------------------------------------------------------------------
# The stateful wrapper the live loop and the scenarios drive


class CompanionCore:
    """Estimator + PI + gating, bound to one parameter set and one sensor profile."""

    def __init__(self, cfg: Config, profile: Profile = Profile.PAPER,
                 options: EstimatorOptions | None = None) -> None:
        self.cfg = cfg
        self.profile = profile
        self.options = options if options is not None else EstimatorOptions.from_config(cfg)
        self.params = StepParams.from_config(cfg)
        #: the Kalman filter; fed every attitude sample whatever the estimator (the profile, and so the
        #: estimator, may be told only after the first samples)
        self.kalman = VelocityKalman(self.options.kalman or kalman_settings(cfg, profile))
        self._bind(profile)
        self.sensor = VelocitySensor(nominal_frame_s=cfg.flow_sensor.frame_period_s)  # prev frame time
        self.pi = PiController(cfg.controller.kp_rad_per_m_s, cfg.controller.ki_rad_per_m,
                               cfg.controller.tilt_limit_rad)
        self.filter_state: FilterState = FILTER_RESET
        self._gyro: deque[tuple[float, float, float]] = deque(maxlen=GYRO_HISTORY)
        self._range: tuple[float, float] | None = None  # (time_s, range_m) of the latest reading
        self._attitude: tuple[float, float, float] | None = None  # (time_s, roll, pitch)
        self._attitude_rate: tuple[float, float] | None = None  # the latest finite (rollspeed, pitchspeed)
        self.plausible = Plausibility(PlausibilityParams.from_config(cfg))
        self._last_payload: tuple[float, ...] | None = None
        self._last_used_time_s = math.nan
        self.engaged = True
        self.setpoint_m_s = (0.0, 0.0)
        self.last: StepOutput | None = None

    # -- inputs ------------------------------------------------------------------------------

    def on_gyro(self, time_s: float, gyro_x_rad_s: float, gyro_y_rad_s: float) -> None:
        if self._gyro and time_s < self._gyro[-1][0] - GYRO_REBOOT_S:  # the vehicle rebooted
            self._gyro.clear()
        self._gyro.append((time_s, gyro_x_rad_s, gyro_y_rad_s))

    def on_accel(self, time_s: float, f_x_m_s2: float, f_y_m_s2: float) -> None:
        """A gyro message's accelerometer (``profiles.accel_m_s2``: body FRD specific force, m/s^2):
        the Kalman filter's input (``VelocityKalman.on_accel``), fed whatever the estimator."""
        self.kalman.on_accel(float(time_s), float(f_x_m_s2), float(f_y_m_s2))

    def on_range(self, time_s: float, range_m: float) -> None:
        self._range = (time_s, range_m)

    def on_attitude(self, time_s: float, roll_rad: float, pitch_rad: float, roll_rate_rad_s: float = math.nan,
                    pitch_rate_rad_s: float = math.nan) -> None:
        """The autopilot's attitude estimate (ATTITUDE): the angles for the optional tilt filter,
        the rates for the frozen-gyro check (``Plausibility``)."""
        self._attitude = (time_s, roll_rad, pitch_rad)
        rates = (float(roll_rate_rad_s), float(pitch_rate_rad_s))
        self._attitude_rate = rates if all(math.isfinite(r) for r in rates) else None
        self.kalman.on_attitude(float(time_s), float(roll_rad), float(pitch_rad), rates[0], rates[1])

    def set_setpoint(self, vx_m_s: float, vy_m_s: float) -> None:
        """Body-frame velocity setpoint; non-finite values are ignored, each axis is clipped to
        the maximum speed (as the tilt limit is per axis)."""
        if not (math.isfinite(vx_m_s) and math.isfinite(vy_m_s)):
            return
        vmax = self.cfg.companion.max_speed_m_s
        self.setpoint_m_s = (float(rules.clip_speed(vx_m_s, vmax)), float(rules.clip_speed(vy_m_s, vmax)))

    def set_profile(self, profile: Profile) -> None:
        """Bind the core to ``profile`` once a live link has told which it is (before any flow
        frame was stepped: gyro, range and attitude samples do not depend on it)."""
        self._bind(profile)

    def _bind(self, profile: Profile) -> None:
        """The profile's choices: gyro source, estimator, the Kalman filter's noise model."""
        self.profile = profile
        self.gyro_source = self.options.resolved_gyro(profile)
        self.estimator = self.options.resolved_estimator(profile)
        self.tilt = self.options.resolved_tilt(profile)
        self.kalman.s = self.options.kalman or kalman_settings(self.cfg, profile)
        self.kalman.reset()

    def set_engaged(self, engaged: bool) -> None:
        """Whether the vehicle is in the companion's mode (GUIDED_NOGPS). While not engaged the
        steps hold level and the integrator and filter are reset; re-engaging starts afresh."""
        self.engaged = bool(engaged)

    # -- the step ----------------------------------------------------------------------------

    def _aligned_gyro(self, time_s: float) -> tuple[float, float] | None:
        """The gyro sample nearest the frame (``rules.gyro_scan`` from the newest back)."""
        best = None
        max_skew = best_skew = self.params.max_gyro_skew_s
        scan = rules.gyro_scan
        for t, gx, gy in reversed(self._gyro):
            skew, take, stop = scan(t, time_s, best_skew, max_skew)
            if take:
                best, best_skew = (gx, gy), skew
            elif stop:
                break
        return best

    @staticmethod
    def payload(f: FlowColumns) -> tuple[float, ...]:
        """The values that identify a flow sample (its time excluded): see ``repeat_mask``."""
        return (float(f.scene_x), float(f.scene_y), float(f.quality), float(f.integration_s),
                float(f.body_x_rad_s), float(f.body_y_rad_s))

    def _is_repeat(self, f: FlowColumns, payload: tuple[float, ...]) -> bool:
        """The same sample again, or a frame not after the last one (``rules.is_repeat``, with
        ``frame_repeat_window``; ``repeat_mask`` over columns)."""
        prev = self._last_payload
        if prev is None or self.last is None:
            return False
        window = frame_repeat_window(f.integration_s, payload[4], payload[5], self.params.repeat_window_s,
                                     self.profile)
        same = all(rules.same_value(a, b) for a, b in zip(payload, prev, strict=True))
        return bool(rules.is_repeat(f.time_s - self._last_used_time_s, same, window))

    def is_repeat(self, f: FlowColumns) -> bool:
        """Whether ``on_flow`` would take ``f`` as a repeat (and step nothing)."""
        return self._is_repeat(f, self.payload(f))

    # -- what a live session asks of the core (companion.mavlink.session) ------------------------------

    @property
    def last_frame_time_s(self) -> float | None:
        """The time of the last flow frame stepped (a repeat excluded) or skipped, s; None before any."""
        t = self._last_used_time_s
        return t if math.isfinite(t) else None

    def frame_order(self, time_s: float) -> FrameOrder:
        """Where a flow frame at ``time_s`` stands against the last frame stepped or skipped
        (``classify_frame``): a duplicate is what ``on_flow`` returns as a repeat by its time."""
        return classify_frame(self._last_used_time_s, time_s)

    def skip_frame(self, time_s: float) -> None:
        """A flow frame the caller does not step (too old to fly on): frame order and the repeat
        window run from its time; the estimator, the integrator and the checks are untouched."""
        if math.isfinite(time_s):
            self._last_used_time_s = float(time_s)

    def reset_integrator(self) -> None:
        """The PI integrals back to zero (a take-over; every step while the pilot flies)."""
        self.pi.state = PiState()

    def restart_checks(self) -> None:
        """Forget the cross-frame checks' history (``Plausibility``): the vehicle's clock restarted."""
        self.plausible.reset()

    def on_flow(self, f: FlowColumns) -> StepOutput:
        """Run one control step on a flow frame (scalars). Always returns a finite command."""
        payload = self.payload(f)
        if self._is_repeat(f, payload):
            assert self.last is not None
            return dataclasses.replace(self.last, repeat=True)
        self._last_payload = payload
        if math.isfinite(f.time_s):
            self._last_used_time_s = float(f.time_s)
        p = self.params
        if self.gyro_source is GyroSource.FLOW:
            gx, gy = float(f.body_x_rad_s), float(f.body_y_rad_s)
            gyro_found = not (math.isnan(gx) or math.isnan(gy))
        else:
            gyro = self._aligned_gyro(f.time_s)
            gyro_found = gyro is not None
            gx, gy = gyro if gyro is not None else (math.nan, math.nan)
        range_found = self._range is not None
        t_r, rng = self._range if self._range is not None else (math.nan, math.nan)
        cause = gate_frame(f.time_s, f.scene_x, f.scene_y, f.quality, gyro_found, gx, gy, range_found, t_r, rng,
                           p=p)
        vx = vy = math.nan
        raw: tuple[float, float] | None = None  # eq. 15 of a frame the cross-frame checks vetoed
        if cause is HoldCause.NONE:
            vx, vy, dt, rate_x, rate_y = self.sensor.update(f.time_s, f.scene_x, f.scene_y, f.increment,
                                                            f.integration_s, gx, gy, rng)
            if rules.scene_spike(rate_x, rate_y, p.max_scene_rate_rad_s):
                cause = HoldCause.FLOW_SPIKE
                vx = vy = math.nan
            else:  # what one frame cannot show: checked against the frames before
                veto = self.plausible.check(f.time_s, (f.scene_x, f.scene_y), (gx, gy), (vx, vy), rng,
                                            self._attitude_rate)
                if veto is not None:
                    cause = veto
                    raw = (vx, vy)
                    vx = vy = math.nan
        else:
            dt = p.nominal_frame_s
            if math.isfinite(f.time_s):
                self.sensor.prev_time_s = f.time_s
        vx_raw, vy_raw = raw if raw is not None else (vx, vy)
        var_x = var_y = math.nan
        if self.estimator is VelocityEstimator.KF and cause is HoldCause.NONE:
            span = kalman_span(f.integration_s, dt)
            zx, zy = vx, vy
            if self.gyro_source is GyroSource.IMU and f.increment:  # the rotation over the sample's own window
                t1 = f.time_s - self.kalman.s.flow_sample_age_s
                zx, zy = kalman_measurement(vx, vy, gx, gy, gyro_window_mean(self._gyro, t1 - span, t1,
                                                                               p.max_gyro_skew_s), rng)
            vx, vy, var_x, var_y = self.kalman.update(f.time_s, span, zx, zy, rng)
        roll = pitch = math.nan
        tilt = self.tilt
        if tilt is not None and self._attitude is not None:
            t_a, r_a, p_a = self._attitude
            if f.time_s - t_a <= tilt.max_attitude_age_s:
                roll, pitch = float(r_a), float(p_a)
        sx, sy = self.setpoint_m_s
        pi_state = (self.pi.state.integral_x_m, self.pi.state.integral_y_m)
        pi_state, self.filter_state, vx_f, vy_f, roll_cmd, pitch_cmd = control_step(
            pi_state, self.filter_state, cause is HoldCause.NONE, self.engaged, vx, vy, roll, pitch, sx, sy, dt,
            p=p, tilt=tilt)
        self.pi.state = PiState(*pi_state)
        if rules.disengaged(cause is HoldCause.NONE, self.engaged):
            cause = HoldCause.DISENGAGED
        out = StepOutput(f.time_s, dt, vx_f, vy_f, sx, sy, roll_cmd, pitch_cmd, cause, gx, gy, rng, vx_raw, vy_raw,
                         vx_var_m2_s2=var_x, vy_var_m2_s2=var_y)
        self.last = out
        return out
