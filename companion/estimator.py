"""The paper's velocity sensor (eq. 15), both axes, as a pure function with a thin wrapper.

    V_x = (-omega_y - dX_k Q / T) A        V_y = (+omega_x - dY_k Q / T) A

``Omega = dphi / T`` is the scene-angle rate over the frame in the paper's convention (see
``companion.profiles``), ``omega_x``, ``omega_y`` the roll- and pitch-rate gyro (rad/s, body
FRD) time-aligned to the frame, ``A`` the range to the ground (m).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np


def velocity_from_flow(scene_rate_x_rad_s: Any, scene_rate_y_rad_s: Any, gyro_x_rad_s: Any,
                       gyro_y_rad_s: Any, range_m: Any) -> tuple[Any, Any]:
    """Eq. 15 on scalars or arrays: body-frame horizontal velocity (vx_m_s, vy_m_s)."""
    vx = (-gyro_y_rad_s - scene_rate_x_rad_s) * range_m
    vy = (gyro_x_rad_s - scene_rate_y_rad_s) * range_m
    return vx, vy


def scene_rate(scene: Any, increment: bool, integration_s: Any, frame_dt_s: Any) -> Any:
    """Scene-angle rate (rad/s) from a profile's flow quantity.

    Increments (rad) are divided by the message's own integration time when it states one
    (finite ``integration_s``), otherwise by the spacing of the flow frames ``frame_dt_s``.
    Rates (rad/s) pass through.
    """
    if not increment:
        return scene
    dt = np.where(np.isfinite(integration_s) & (np.asarray(integration_s) > 0), integration_s, frame_dt_s)
    return scene / dt


def scene_rate_scalar(scene: float, increment: bool, integration_s: float, frame_dt_s: float) -> float:
    """``scene_rate`` for one frame in plain floats (the live loop's hot path), same rule."""
    if not increment:
        return scene
    own = integration_s == integration_s and integration_s != math.inf and integration_s > 0.0
    return scene / (integration_s if own else frame_dt_s)


def frame_spacing(prev_time_s: float | None, time_s: float, nominal_s: float) -> float:
    """The time a flow frame's counts cover: the spacing from the previous frame when it is
    plausible (0 < dt <= 5 frames), else the nominal frame period (first frame, reboot, gap)."""
    if prev_time_s is None:
        return nominal_s
    dt = time_s - prev_time_s
    if 0.0 < dt <= 5.0 * nominal_s:
        return dt
    return nominal_s


def frame_spacing_array(time_s: np.ndarray, nominal_s: float) -> np.ndarray:
    """``frame_spacing`` over a whole column of frame times (replay), same rule."""
    dt = np.empty_like(time_s, dtype=float)
    if len(time_s) == 0:
        return dt
    dt[0] = nominal_s
    d = np.diff(time_s)
    dt[1:] = np.where((d > 0.0) & (d <= 5.0 * nominal_s), d, nominal_s)
    return dt


@dataclass
class VelocitySensor:
    """Stateful wrapper: remembers the previous frame time to get the frame spacing."""

    nominal_frame_s: float
    prev_time_s: float | None = None

    def update(self, time_s: float, scene_x: float, scene_y: float, increment: bool,
               integration_s: float, gyro_x_rad_s: float, gyro_y_rad_s: float,
               range_m: float) -> tuple[float, float, float, float, float]:
        """Returns (vx_m_s, vy_m_s, frame_dt_s, scene_rate_x_rad_s, scene_rate_y_rad_s)."""
        dt = frame_spacing(self.prev_time_s, time_s, self.nominal_frame_s)
        self.prev_time_s = time_s
        rx = scene_rate_scalar(scene_x, increment, integration_s, dt)
        ry = scene_rate_scalar(scene_y, increment, integration_s, dt)
        vx, vy = velocity_from_flow(rx, ry, gyro_x_rad_s, gyro_y_rad_s, range_m)
        return float(vx), float(vy), dt, rx, ry


# ---------------------------------------------------------------------------------------------
# The velocity Kalman filter (issue 19): eq. 15 fused with the attitude-driven prediction, the
# measurement fused at the flow sample's own time and the estimate carried to the newest
# attitude (docs/estimator.md)

#: ATTITUDE's error per sample (rad, 1 sigma, white): the attitude-predicted acceleration g tan(tilt)
#: is wrong by g times it; its slow part (a trim error) is the disturbance state's
ATTITUDE_NOISE_RAD = math.radians(0.1)
#: the disturbance (wind, trim, unmodelled force) as a random walk: 0.1 m/s^2 of drift in 10 s
DISTURBANCE_DRIFT_M_S2 = 0.1
DISTURBANCE_DRIFT_S = 10.0
#: prior of the disturbance at the start: the acceleration of a 5 deg trim error or wind (1 sigma)
DISTURBANCE_PRIOR_M_S2 = 9.80665 * math.tan(math.radians(5.0))
#: the linear drag rate c (drag force / mass / speed, 1/s): prior 1 sigma, and its drift (per sqrt(s))
DRAG_PRIOR_PER_S = 0.5
DRAG_DRIFT_PER_S_SQRT_S = 0.003
#: a step in the disturbance (a gust) beyond the random walk: the normalised innovations'
#: exponentially weighted mean (weight ``GUST_WEIGHT`` per frame: about three frames of memory)
#: beyond the chi-square 1-dof 0.999 quantile means the velocity is off by that mean and the
#: disturbance by at least that offset over the mean's memory: the velocity's variance is raised
#: by the offset squared, the disturbance's by twice that acceleration squared (the filter has
#: already taken up part of the step), and the filter re-learns both from the next frames
GUST_WEIGHT = 0.3
GUST_CHI2 = 10.83
GUST_STEP_SIGMAS = 2.0
#: the measured noise (second differences of eq. 15) averages over this long
NOISE_AVERAGE_S = 1.0
#: until the noise has been measured (three consecutive frames), at least this much flow noise
#: (rad/s, 1 sigma) is assumed: a generous figure for a real sensor (SITL's is 0.029)
FLOW_NOISE_PRIOR_RAD_S = 0.05
#: the estimate is carried past the newest attitude with its rates for at most this long, then held
MAX_EXTRAPOLATION_S = 0.04
#: no attitude newer than this before the frame: no prediction, eq. 15 is passed through
MAX_ATTITUDE_AGE_S = 0.1
#: no measurement fused for this long: the velocity restarts from the next one (disturbance and drag kept)
MAX_GAP_S = 0.5
#: a measurement time this much before the fusion horizon means the vehicle's clock restarted
CLOCK_RESTART_S = 1.0
#: attitude samples kept (5 s at 50 Hz; a fusion horizon is never more than MAX_GAP_S behind)
ATTITUDE_HISTORY = 256


@dataclass(frozen=True)
class KalmanSettings:
    """The velocity filter's noise model and timing, bound once from a ``Config`` and profile.

    Measurement (eq. 15, per axis, m^2/s^2): ``range^2 * flow_noise_rad_s^2`` plus the range
    error's share ``(v * range_noise_m / range)^2``, where ``flow_noise_rad_s`` is the sensor
    model's (the count quantization Q / (T sqrt 6) for sensors that report counts, and the gyro's
    white noise when the config says it has some); the noise measured on the recording (second
    differences of eq. 15 over ``NOISE_AVERAGE_S``) replaces it when larger. Process: white
    acceleration of PSD ``(g ATTITUDE_NOISE_RAD)^2 T`` on the velocity, a random walk of PSD
    ``DISTURBANCE_DRIFT_M_S2^2 / DISTURBANCE_DRIFT_S`` on the disturbance and
    ``DRAG_DRIFT_PER_S_SQRT_S^2`` on the drag rate. Timing: the flow sample is half its frame
    (the integration time the message states, else the frame spacing) plus ``flow_sample_age_s``
    older than its message's time.
    """

    gravity_m_s2: float
    nominal_frame_s: float
    flow_sample_age_s: float
    flow_noise_rad_s: float
    range_noise_m: float
    accel_psd: float
    disturbance_psd: float
    drag_psd: float
    disturbance_prior_m_s2: float = DISTURBANCE_PRIOR_M_S2
    drag_prior_per_s: float = DRAG_PRIOR_PER_S
    drag_initial_per_s: float = 0.0

    @classmethod
    def from_config(cls, cfg: Any, counts: bool) -> KalmanSettings:
        """``counts``: the profile's flow is integer counts (``paper``), so Q's quantization is
        part of its noise; rates and radians (``ardupilot``, ``px4``) carry no quantization."""
        t = cfg.flow_sensor.frame_period_s
        g = cfg.airframe.gravity_m_s2
        quant = cfg.flow_sensor.q_rad_per_count / (t * math.sqrt(6.0)) if counts else 0.0
        gyro = math.radians(cfg.imu.gyro_noise_density_deg_s_sqrt_hz) * math.sqrt(cfg.imu.rate_hz) \
            if cfg.imu.gyro_noise else 0.0
        rf = cfg.rangefinder
        return cls(gravity_m_s2=g, nominal_frame_s=t, flow_sample_age_s=cfg.companion.flow_sample_age_s,
                   flow_noise_rad_s=math.hypot(quant, gyro),
                   range_noise_m=math.hypot(rf.noise_std_m, rf.resolution_m / math.sqrt(12.0)),
                   accel_psd=(g * ATTITUDE_NOISE_RAD) ** 2 * t,
                   disturbance_psd=DISTURBANCE_DRIFT_M_S2 ** 2 / DISTURBANCE_DRIFT_S,
                   drag_psd=DRAG_DRIFT_PER_S_SQRT_S ** 2)

    def sample_time_s(self, time_s: float, span_s: float) -> float:
        """When the flow sample of a message stamped ``time_s`` covering ``span_s`` was taken."""
        return time_s - 0.5 * span_s - self.flow_sample_age_s

    def model_variance(self, v_m_s: float, range_m: float) -> float:
        """eq. 15's variance from the sensor model (m^2/s^2) at this speed and range."""
        rel = self.range_noise_m / range_m if range_m > 0.0 else 0.0
        return (range_m * self.flow_noise_rad_s) ** 2 + (v_m_s * rel) ** 2


class _Axis:
    """One axis: state (v, b, c) = velocity m/s, disturbance m/s^2, drag rate 1/s, with
    ``v' = a_tilt + b - c v``; P symmetric 3x3 as its six entries."""

    __slots__ = ("v", "b", "c", "p00", "p01", "p02", "p11", "p12", "p22", "ready", "gust", "z1", "z2", "t1", "t2",
                 "r_data", "n_data")

    def __init__(self, s: KalmanSettings) -> None:
        self.b = 0.0
        self.c = s.drag_initial_per_s
        self.p11 = s.disturbance_prior_m_s2 ** 2
        self.p22 = s.drag_prior_per_s ** 2
        self.p12 = 0.0
        self.r_data = math.nan
        self.n_data = 0
        self.restart()

    def restart(self) -> None:
        """Forget the velocity (the next measurement sets it); keep the disturbance and drag."""
        self.v = 0.0
        self.p00 = self.p01 = self.p02 = 0.0
        self.ready = False
        self.gust = 0.0
        self.z1 = self.z2 = self.t1 = self.t2 = math.nan

    def start(self, z: float, r: float) -> None:
        self.v = z
        self.p00, self.p01, self.p02 = r, 0.0, 0.0
        self.ready = True

    def predict(self, accel_integral: float, dt: float, s: KalmanSettings) -> None:
        """Over ``dt`` s with the tilt acceleration's integral ``accel_integral`` (m/s)."""
        if dt <= 0.0:
            return
        v, b, c = self.v, self.b, self.c
        self.v = v + accel_integral + (b - c * v) * dt
        # F = [[1 - c dt, dt, -v dt], [0, 1, 0], [0, 0, 1]]
        f0, f1, f2 = 1.0 - c * dt, dt, -v * dt
        p00, p01, p02, p11, p12, p22 = self.p00, self.p01, self.p02, self.p11, self.p12, self.p22
        r0 = f0 * p00 + f1 * p01 + f2 * p02  # row 0 of F P
        r1 = f0 * p01 + f1 * p11 + f2 * p12
        r2 = f0 * p02 + f1 * p12 + f2 * p22
        qb = s.disturbance_psd
        self.p00 = f0 * r0 + f1 * r1 + f2 * r2 + s.accel_psd * dt + qb * dt ** 3 / 3.0
        self.p01 = r1 + qb * dt * dt / 2.0
        self.p02 = r2
        self.p11 = p11 + qb * dt
        self.p22 = p22 + s.drag_psd * dt

    def fuse(self, z: float, r: float, nominal_s: float) -> None:
        """Update with a velocity measurement of variance ``r``; then the gust test."""
        s_ = self.p00 + r
        nu = z - self.v
        k0, k1, k2 = self.p00 / s_, self.p01 / s_, self.p02 / s_
        self.v += k0 * nu
        self.b += k1 * nu
        self.c += k2 * nu
        p00, p01, p02 = self.p00, self.p01, self.p02
        self.p00 = p00 - k0 * p00
        self.p01 = p01 - k0 * p01
        self.p02 = p02 - k0 * p02
        self.p11 -= k1 * p01
        self.p12 -= k1 * p02
        self.p22 -= k2 * p02
        # a step in the disturbance: the innovations' weighted mean, normalised, far from 0
        w = GUST_WEIGHT
        self.gust = (1.0 - w) * self.gust + w * nu / math.sqrt(s_)
        if self.gust * self.gust * (2.0 - w) / w > GUST_CHI2:
            offset = self.gust * math.sqrt(s_)  # m/s: the velocity error the innovations show
            step = GUST_STEP_SIGMAS * offset * w / nominal_s  # m/s^2: over the mean's memory, T / w
            self.p00 += offset * offset
            self.p11 += step * step
            self.gust = 0.0

    def measured_noise(self, t: float, z: float, nominal_s: float) -> float:
        """The measurement noise seen on the recording: the mean of (second difference)^2 / 6 of
        eq. 15 over consecutive frames (a running mean, then ``NOISE_AVERAGE_S`` of memory);
        NaN until three consecutive frames were seen."""
        gap = 1.5 * nominal_s
        if not (0.0 < t - self.t1 <= gap and 0.0 < self.t1 - self.t2 <= gap):
            self.z2, self.t2 = (self.z1, self.t1) if 0.0 < t - self.t1 <= gap else (math.nan, math.nan)
            self.z1, self.t1 = z, t
            return self.r_data
        d2 = z - 2.0 * self.z1 + self.z2
        self.n_data += 1
        w = max(1.0 / self.n_data, nominal_s / NOISE_AVERAGE_S)
        sample = d2 * d2 / 6.0
        self.r_data = sample if self.n_data == 1 else (1.0 - w) * self.r_data + w * sample
        self.z2, self.t2, self.z1, self.t1 = self.z1, self.t1, z, t
        return self.r_data

    def output(self, accel_integral: float, dt: float, s: KalmanSettings) -> tuple[float, float]:
        """The velocity and its variance ``dt`` s after the state's time, without changing the state."""
        v, b, c = self.v, self.b, self.c
        f0, f1, f2 = 1.0 - c * dt, dt, -v * dt
        var = (f0 * (f0 * self.p00 + f1 * self.p01 + f2 * self.p02) + f1 * (f0 * self.p01 + f1 * self.p11
               + f2 * self.p12) + f2 * (f0 * self.p02 + f1 * self.p12 + f2 * self.p22)
               + s.accel_psd * dt + s.disturbance_psd * dt ** 3 / 3.0)
        return v + accel_integral + (b - c * v) * dt, var


class VelocityKalman:
    """The companion's velocity estimate (issue 19), both axes, pure: every time is passed in.

    Per axis a three-state Kalman filter (velocity, disturbance acceleration, linear drag rate;
    ``_Axis``) predicted with the attitude, ``v' = s g tan(tilt) + b - c v`` (the plant's eq. 28
    with the unknown force as ``b`` and drag as ``c``), from the ATTITUDE samples (``on_attitude``)
    interpolated linearly between them; and updated with eq. 15 (``update``) **at the flow
    sample's own time** (``KalmanSettings.sample_time_s``): the state is kept at the time of the
    last fused sample (the fusion horizon), predicted from there to the next sample's time,
    updated, and the estimate handed out is that state carried forward with the attitude to the
    newest information, the frame's time or the newest attitude, whichever is later (past the
    newest attitude with its rates, ``MAX_EXTRAPOLATION_S`` at most). The noise model is
    ``KalmanSettings``'s; docs/estimator.md says where each number comes from.

    Without a fresh attitude (none within ``MAX_ATTITUDE_AGE_S`` of the frame) there is nothing
    to predict with: eq. 15 is returned with its variance, and the velocity restarts from the
    next measurement once the attitude is back. A measurement more than ``MAX_GAP_S`` after the
    last fused one restarts the velocity too; a clock going back (a reboot) restarts everything.
    """

    def __init__(self, settings: KalmanSettings) -> None:
        self.s = settings
        self.attitude: deque[tuple[float, float, float, float, float]] = deque(maxlen=ATTITUDE_HISTORY)
        self.reset()

    def reset(self) -> None:
        """Back to the priors (a new vehicle or a rebooted one); the attitude history is kept."""
        self.axes = (_Axis(self.s), _Axis(self.s))
        self.horizon_s = math.nan  # the time of the state: the last fused sample's

    def on_attitude(self, time_s: float, roll_rad: float, pitch_rad: float, roll_rate_rad_s: float,
                    pitch_rate_rad_s: float) -> None:
        """One attitude sample (ATTITUDE: time s, angles rad, rates rad/s; rates may be NaN)."""
        if not (math.isfinite(time_s) and math.isfinite(roll_rad) and math.isfinite(pitch_rad)):
            return
        g = self.s.gravity_m_s2
        cp, cr = math.cos(pitch_rad), math.cos(roll_rad)
        ax, ay = -g * math.tan(pitch_rad), g * math.tan(roll_rad)  # eq. 28: x uses -pitch, y +roll
        dax = -g * pitch_rate_rad_s / (cp * cp) if math.isfinite(pitch_rate_rad_s) else 0.0
        day = g * roll_rate_rad_s / (cr * cr) if math.isfinite(roll_rate_rad_s) else 0.0
        h = self.attitude
        if h:
            last = h[-1][0]
            if time_s < last - CLOCK_RESTART_S:
                h.clear()
            elif time_s <= last:  # the same time again (replace) or slightly out of order (drop)
                if time_s == last:
                    h[-1] = (time_s, ax, ay, dax, day)
                return
        h.append((time_s, ax, ay, dax, day))

    def _accel(self, t: float) -> tuple[float, float]:
        h = self.attitude
        t_new, ax, ay, dax, day = h[-1]
        if t >= t_new:
            e = min(t - t_new, MAX_EXTRAPOLATION_S)
            return ax + dax * e, ay + day * e
        if t <= h[0][0]:
            return h[0][1], h[0][2]
        i = len(h) - 1
        while h[i - 1][0] > t:
            i -= 1
        t0, ax0, ay0 = h[i - 1][0], h[i - 1][1], h[i - 1][2]
        t1, ax1, ay1 = h[i][0], h[i][1], h[i][2]
        w = (t - t0) / (t1 - t0)
        return ax0 + w * (ax1 - ax0), ay0 + w * (ay1 - ay0)

    def _integral(self, t0: float, t1: float) -> tuple[float, float]:
        """The tilt acceleration integrated from ``t0`` to ``t1`` (trapezoids between the attitude
        samples and the extrapolation's end), both axes, m/s."""
        if not t1 > t0:
            return 0.0, 0.0
        h = self.attitude
        inside = []
        for k in reversed(h):  # the samples strictly between t0 and t1, newest first
            if k[0] <= t0:
                break
            if k[0] < t1:
                inside.append(k[0])
        knots = [t0, *inside[::-1]]
        held = h[-1][0] + MAX_EXTRAPOLATION_S
        if t0 < held < t1:
            knots.append(held)
        knots.append(t1)
        ix = iy = 0.0
        pa = self._accel(knots[0])
        for a, b in zip(knots[:-1], knots[1:], strict=True):
            ca = self._accel(b)
            ix += 0.5 * (pa[0] + ca[0]) * (b - a)
            iy += 0.5 * (pa[1] + ca[1]) * (b - a)
            pa = ca
        return ix, iy

    def fresh(self, time_s: float) -> bool:
        """Whether an attitude sample within ``MAX_ATTITUDE_AGE_S`` of ``time_s`` is known."""
        return bool(self.attitude) and time_s - self.attitude[-1][0] <= MAX_ATTITUDE_AGE_S

    def update(self, time_s: float, span_s: float, z_x: float, z_y: float, range_m: float
               ) -> tuple[float, float, float, float]:
        """Fuse eq. 15 (``z_x``, ``z_y`` m/s) of a flow message stamped ``time_s`` covering
        ``span_s``, measured at ``range_m``. Returns (vx, vy, var_x, var_y): the estimate at the
        newest information's time and its variance (m^2/s^2)."""
        s = self.s
        t_m = s.sample_time_s(time_s, span_s)
        axes = self.axes
        r_model = (s.model_variance(z_x, range_m), s.model_variance(z_y, range_m))
        r = []
        for ax, z, rm in zip(axes, (z_x, z_y), r_model, strict=True):
            measured = ax.measured_noise(t_m, z, s.nominal_frame_s)
            if measured != measured:  # not measured yet: the model, or the generous prior if larger
                measured = (range_m * FLOW_NOISE_PRIOR_RAD_S) ** 2
            r.append(measured if measured > rm else rm)
        if not self.fresh(time_s):
            for ax in axes:
                ax.restart()
            self.horizon_s = math.nan
            return z_x, z_y, r[0], r[1]
        h = self.horizon_s
        if h == h and t_m < h - CLOCK_RESTART_S:  # the vehicle's clock restarted
            self.reset()
            return self.update(time_s, span_s, z_x, z_y, range_m)
        if not (h == h and t_m - h <= MAX_GAP_S and all(ax.ready for ax in axes)):
            for ax, z, rr in zip(axes, (z_x, z_y), r, strict=True):
                ax.restart()
                ax.start(z, rr)
        else:
            t_m = max(t_m, h)  # a sample older than the horizon is fused at the horizon
            ix, iy = self._integral(h, t_m)
            for ax, a_int, z, rr in zip(axes, (ix, iy), (z_x, z_y), r, strict=True):
                ax.predict(a_int, t_m - h, s)
                ax.fuse(z, rr, s.nominal_frame_s)
        self.horizon_s = t_m
        t_out = max(time_s, self.attitude[-1][0])
        ox, oy = self._integral(t_m, t_out)
        (vx, var_x), (vy, var_y) = (ax.output(o, t_out - t_m, s) for ax, o in zip(axes, (ox, oy), strict=True))
        return vx, vy, var_x, var_y
