"""The reference simulator: plant + flow sensor + IMU + rangefinder, advanced one flow frame at a time.

Frame k is at ``t_k = k T``. ``sample()`` returns what the sensors report at t_k;
``advance(u)`` integrates the continuous-time plant and scene angle over [t_k, t_k+1] with the
command that is *active* (the one given at the previous frame), then makes ``u`` active and
returns the sensors at t_k+1. So a command computed from frame k acts from frame k+1 on: the
paper's one-sample loop latency (CONVENTIONS.md).

Integration is classical RK4 with ``cfg.sim.substeps_per_frame`` steps per frame (1 ms at
50 Hz), much finer than a frame, as eq. 9 requires. Time is passed in, never read from a clock;
randomness comes from the Generator passed in.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from companion.config import Config
from simvehicle.model.flow_sensor import flow_frame
from simvehicle.model.imu import accel_sample, gyro_sample, specific_force
from simvehicle.model.plant import AXIS_SIGN, ZERO_AXIS, AxisState, PlantParams, axis_derivative, axis_rk4
from simvehicle.model.rangefinder import range_reading

ForceFn = Callable[[float], tuple[float, float]]
AltitudeFn = Callable[[float], float]


@dataclass(frozen=True)
class FrameSample:
    """What the vehicle knows at one frame time: sensor outputs and the truth behind them."""

    frame: int
    t_s: float
    flow_x_counts: int  # dX_k, paper convention
    flow_y_counts: int
    flow_quality: int
    gyro_x_rad_s: float  # roll rate as measured
    gyro_y_rad_s: float  # pitch rate as measured
    gyro_z_rad_s: float
    range_m: float  # rangefinder reading
    # truth
    roll_rad: float
    pitch_rad: float
    roll_rate_rad_s: float
    pitch_rate_rad_s: float
    vx_m_s: float
    vy_m_s: float
    x_m: float
    y_m: float
    altitude_m: float
    phi_x_rad: float
    phi_y_rad: float
    force_x_n: float
    force_y_n: float
    roll_cmd_active_rad: float
    pitch_cmd_active_rad: float
    # the accelerometer as measured: body FRD specific force, m/s^2 (NaN: the IMU reports none)
    accel_x_m_s2: float = math.nan
    accel_y_m_s2: float = math.nan
    accel_z_m_s2: float = math.nan


@dataclass
class Turbulence:
    """Random horizontal force: a first-order Gauss-Markov process per axis, held over a frame."""

    sigma_n: float
    tau_s: float
    state_n: list[float] = field(default_factory=lambda: [0.0, 0.0])

    def step(self, dt_s: float, rng: np.random.Generator) -> tuple[float, float]:
        a = math.exp(-dt_s / self.tau_s)
        w = self.sigma_n * math.sqrt(1.0 - a * a)
        n = rng.normal(0.0, 1.0, 2)
        self.state_n = [a * self.state_n[0] + w * float(n[0]), a * self.state_n[1] + w * float(n[1])]
        return self.state_n[0], self.state_n[1]


def _no_force(_t: float) -> tuple[float, float]:
    return 0.0, 0.0


class Simulator:
    """Stateful wrapper over the pure models, advanced one frame per call."""

    def __init__(self, cfg: Config, *, rng: np.random.Generator | None = None,
                 external_force: ForceFn = _no_force, altitude: AltitudeFn | None = None,
                 turbulence: Turbulence | None = None) -> None:
        self.rng = rng if rng is not None else np.random.default_rng(0)
        # the accelerometer's noise from its own stream, spawned from ``rng``'s seed: the draws of
        # every other sensor are those they were before the simulator had an accelerometer
        self.accel_rng = self.rng.spawn(1)[0]
        self.T = cfg.flow_sensor.frame_period_s
        self.n_sub = cfg.sim.substeps_per_frame
        self.external_force = external_force
        self.altitude_fn: AltitudeFn = altitude if altitude is not None else (lambda _t: cfg.world.altitude_m)
        self.turbulence = turbulence
        self.turb_force = (0.0, 0.0)
        self._derive(cfg)
        self.frame = 0
        self.t_s = 0.0
        self.x: AxisState = ZERO_AXIS
        self.y: AxisState = ZERO_AXIS
        self.u_active = (0.0, 0.0)  # (roll, pitch) rad
        self.counts = (0, 0)
        # scene-angle history over the last frames for the flow_delay effect: (t, phi_x, phi_y, dphi_x, dphi_y)
        self._hist: list[tuple[float, float, float, float, float]] = []
        self._record_hist()
        self.current = self._sample()

    def _derive(self, cfg: Config) -> None:
        """Bind the parameters that follow from ``cfg`` (plant truth, sensor effects)."""
        self.cfg = cfg
        self.params = PlantParams.truth(cfg)
        e = cfg.effects
        q = cfg.flow_sensor.q_rad_per_count
        self.q_x = q * (e.flow_scale.scale_x if e.flow_scale else 1.0)
        self.q_y = q * (e.flow_scale.scale_y if e.flow_scale else 1.0)
        self.yaw_mis = e.flow_yaw_misalignment.yaw if e.flow_yaw_misalignment else 0.0
        self.delay_s = e.flow_delay.delay if e.flow_delay else 0.0
        self.bias = (e.gyro_bias.bias_x, e.gyro_bias.bias_y) if e.gyro_bias else (0.0, 0.0)
        self.range_offset = e.range_offset.offset if e.range_offset else 0.0
        self.gyro_density = (math.radians(cfg.imu.gyro_noise_density_deg_s_sqrt_hz)
                             if cfg.imu.gyro_noise else 0.0)
        self.gyro_range = math.radians(cfg.imu.gyro_range_deg_s)
        self.accel_bias = (cfg.imu.accel_bias_x_m_s2, cfg.imu.accel_bias_y_m_s2)
        self._hist_len = self.n_sub * (2 + int(self.delay_s / self.T + 1))

    def set_config(self, cfg: Config) -> None:
        """Take a new parameter set in flight (a GCS changing an effect), keeping the state.

        The change acts from the next ``advance``. The flow sensor's accumulated counts are
        re-quantized with the new Q and axes, so the change itself makes no jump in dX, dY.
        A ``flow_delay`` switched on reads the scene angle at the switch until ``delay`` of
        history has built up (the sensor output pauses for ``delay``, then lags). The frame
        rate and integration step cannot change in flight.
        """
        if (cfg.flow_sensor.frame_period_s != self.T or cfg.sim.substeps_per_frame != self.n_sub):
            raise ValueError("the frame rate and substeps cannot change in flight")
        had_delay = self.delay_s > 0.0
        self._derive(cfg)
        if self.delay_s > 0.0 and not had_delay:
            self._hist = []
            self._record_hist()
        phi_x, phi_y = self.x[4], self.y[4]
        if self.delay_s > 0.0:
            phi_x, phi_y = self._phi_at(self.t_s - self.delay_s)
        self.counts, _ = flow_frame(phi_x, phi_y, (0, 0), q_x_rad_per_count=self.q_x,
                                    q_y_rad_per_count=self.q_y, yaw_rad=self.yaw_mis)

    # -- forces --------------------------------------------------------------------------

    def force_at(self, t_s: float) -> tuple[float, float]:
        fx, fy = self.external_force(t_s)
        w = self.cfg.effects.wind_force
        if w is not None and w.start_s <= t_s < w.end_s:
            fx, fy = fx + w.fx, fy + w.fy
        return fx + self.turb_force[0], fy + self.turb_force[1]

    # -- stepping ------------------------------------------------------------------------

    def _record_hist(self) -> None:
        a = self.altitude_fn(self.t_s)
        dx = AXIS_SIGN[0] * self.x[0] - self.x[2] / a
        dy = AXIS_SIGN[1] * self.y[0] - self.y[2] / a
        self._hist.append((self.t_s, self.x[4], self.y[4], dx, dy))
        if len(self._hist) > self._hist_len:
            del self._hist[0]

    def _phi_at(self, t_s: float) -> tuple[float, float]:
        """Scene angle at an earlier time, by cubic Hermite interpolation of the substep history."""
        h = self._hist
        if t_s >= h[-1][0]:
            return h[-1][1], h[-1][2]
        if t_s <= h[0][0]:
            return h[0][1], h[0][2]
        i = len(h) - 1
        while h[i - 1][0] > t_s:
            i -= 1
        t0, px0, py0, dx0, dy0 = h[i - 1]
        t1, px1, py1, dx1, dy1 = h[i]
        dt = t1 - t0
        s = (t_s - t0) / dt
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        return (h00 * px0 + h10 * dt * dx0 + h01 * px1 + h11 * dt * dx1,
                h00 * py0 + h10 * dt * dy0 + h01 * py1 + h11 * dt * dy1)

    def advance(self, roll_cmd_rad: float, pitch_cmd_rad: float) -> FrameSample:
        """Integrate one frame with the active command, then activate this one; sample at the end."""
        if not (math.isfinite(roll_cmd_rad) and math.isfinite(pitch_cmd_rad)):
            raise ValueError("the simulator was given a non-finite attitude command")
        if self.turbulence is not None:
            self.turb_force = self.turbulence.step(self.T, self.rng)
        h = self.T / self.n_sub
        roll_u, pitch_u = self.u_active
        t0 = self.t_s
        accel = self.cfg.imu.accelerometer
        f_sum = [0.0, 0.0, 0.0]
        for j in range(self.n_sub):
            t = t0 + j * h
            fx, fy = self.force_at(t + 0.5 * h)
            a = self.altitude_fn(t + 0.5 * h)
            x0, y0 = self.x, self.y
            self.x = axis_rk4(self.x, pitch_u, fx, a, AXIS_SIGN[0], h, p=self.params)
            self.y = axis_rk4(self.y, roll_u, fy, a, AXIS_SIGN[1], h, p=self.params)
            if accel:  # the substep's mean acceleration, at its mean attitude
                f = specific_force(0.5 * (y0[1] + self.y[1]), 0.5 * (x0[1] + self.x[1]), (self.x[2] - x0[2]) / h,
                                   (self.y[2] - y0[2]) / h, 0.0, self.params.gravity_m_s2)
                f_sum = [f_sum[0] + f[0], f_sum[1] + f[1], f_sum[2] + f[2]]
            self.t_s = t0 + (j + 1) * h
            if self.delay_s > 0.0:
                self._record_hist()
        self._frame_specific_force = (f_sum[0] / self.n_sub, f_sum[1] / self.n_sub, f_sum[2] / self.n_sub)
        self.frame += 1
        self.t_s = self.frame * self.T  # no drift from repeated addition
        self.u_active = (roll_cmd_rad, pitch_cmd_rad)
        self.current = self._sample()
        return self.current

    def _sample(self) -> FrameSample:
        t = self.t_s
        phi_x, phi_y = self.x[4], self.y[4]
        if self.delay_s > 0.0:
            phi_x, phi_y = self._phi_at(t - self.delay_s)
        self.counts, (dx, dy) = flow_frame(phi_x, phi_y, self.counts, q_x_rad_per_count=self.q_x,
                                           q_y_rad_per_count=self.q_y, yaw_rad=self.yaw_mis)
        if self.frame == 0:
            dx = dy = 0  # the first frame has no previous image to compare with
        gx, gy, gz = gyro_sample(self.y[0], self.x[0], 0.0, self.rng, bias_x_rad_s=self.bias[0],
                                 bias_y_rad_s=self.bias[1], noise_density_rad_s_sqrt_hz=self.gyro_density,
                                 rate_hz=self.cfg.imu.rate_hz, range_rad_s=self.gyro_range)
        alt = self.altitude_fn(t)
        rf = self.cfg.rangefinder
        rng_m = range_reading(alt, self.rng, offset_m=self.range_offset, noise_std_m=rf.noise_std_m,
                              resolution_m=rf.resolution_m)
        fx, fy = self.force_at(t)
        ax, ay, az = self.accelerometer(fx, fy, alt)
        return FrameSample(
            frame=self.frame, t_s=t, flow_x_counts=dx, flow_y_counts=dy, flow_quality=255,
            gyro_x_rad_s=gx, gyro_y_rad_s=gy, gyro_z_rad_s=gz, range_m=rng_m,
            roll_rad=self.y[1], pitch_rad=self.x[1], roll_rate_rad_s=self.y[0], pitch_rate_rad_s=self.x[0],
            vx_m_s=self.x[2], vy_m_s=self.y[2], x_m=self.x[3], y_m=self.y[3], altitude_m=alt,
            phi_x_rad=self.x[4], phi_y_rad=self.y[4], force_x_n=fx, force_y_n=fy,
            roll_cmd_active_rad=self.u_active[0], pitch_cmd_active_rad=self.u_active[1],
            accel_x_m_s2=ax, accel_y_m_s2=ay, accel_z_m_s2=az,
        )

    def accelerometer(self, force_x_n: float, force_y_n: float, altitude_m: float) -> tuple[float, float, float]:
        """The accelerometer's sample now, through ``imu.accel_sample``: the mean specific force
        (``imu.specific_force`` of the plant's acceleration, eq. 28 with the force and drag acting)
        over the frame just integrated, as an IMU's decimation reports it (PX4's delta velocity over
        its interval, ArduPilot's low-pass filtered samples), each substep's mean acceleration
        (its change of velocity over its length) at its mean attitude; the first frame, with none
        before it, the specific force at that instant. NaN when the config's IMU has none. The
        plant holds its altitude (eq. 26-28 have no vertical motion): no vertical acceleration."""
        imu = self.cfg.imu
        if not imu.accelerometer:
            return math.nan, math.nan, math.nan
        if self.frame > 0:
            f = self._frame_specific_force
        else:
            u_pitch, u_roll = self.u_active[1], self.u_active[0]
            a_x = axis_derivative(self.x, u_pitch, force_x_n, altitude_m, AXIS_SIGN[0], p=self.params)[2]
            a_y = axis_derivative(self.y, u_roll, force_y_n, altitude_m, AXIS_SIGN[1], p=self.params)[2]
            f = specific_force(self.y[1], self.x[1], a_x, a_y, 0.0, self.params.gravity_m_s2)
        return accel_sample(*f, self.accel_rng, bias_x_m_s2=self.accel_bias[0], bias_y_m_s2=self.accel_bias[1],
                            noise_density_m_s2_sqrt_hz=imu.accel_noise_density_m_s2_sqrt_hz if imu.accel_noise else 0.0,
                            rate_hz=imu.rate_hz,
                            range_m_s2=imu.accel_range_m_s2)

