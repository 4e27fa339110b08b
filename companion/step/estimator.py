"""The paper's velocity sensor (eq. 15), both axes, as a pure function with a thin wrapper.

    V_x = (-omega_y - dX_k Q / T) A        V_y = (+omega_x - dY_k Q / T) A

``Omega = dphi / T`` is the scene-angle rate over the frame in the paper's convention (see
``companion.step.profiles``), ``omega_x``, ``omega_y`` the roll- and pitch-rate gyro (rad/s, body
FRD) time-aligned to the frame, ``A`` the range to the ground (m).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.step.rules import covered_span, spacing


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
    return scene / covered_span(integration_s, frame_dt_s)


def scene_rate_scalar(scene: float, increment: bool, integration_s: float, frame_dt_s: float) -> float:
    """``scene_rate`` for one frame, as a float."""
    return float(scene_rate(scene, increment, integration_s, frame_dt_s))


def frame_spacing(prev_time_s: float | None, time_s: float, nominal_s: float) -> float:
    """The time a flow frame's counts cover (``companion.step.rules.spacing``): the spacing from the
    previous frame when it is plausible (0 < dt <= 5 frames), else the nominal frame period
    (first frame, reboot, gap)."""
    if prev_time_s is None:
        return nominal_s
    return float(spacing(time_s - prev_time_s, nominal_s))


def frame_spacing_array(time_s: np.ndarray, nominal_s: float) -> np.ndarray:
    """``frame_spacing`` over a whole column of frame times (replay, the fast simulator)."""
    dt = np.empty_like(time_s, dtype=float)
    if len(time_s) == 0:
        return dt
    dt[0] = nominal_s
    with np.errstate(invalid="ignore"):
        dt[1:] = spacing(np.diff(time_s), nominal_s)
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
#: steps in the disturbance beyond its random walk (a gust: a force switched on or off; ground
#: contact; a payload let go), as a prior: they come at random at STEP_RATE_PER_S, each of a size
#: drawn from N(0, STEP_SIGMA_M_S2^2): one sigma is the paper's gust (4 N on 2.3 kg, held by 10 deg
#: of tilt); the rate is the one the published variance answers for (docs/estimator.md)
STEP_RATE_PER_S = 0.1
STEP_SIGMA_M_S2 = 9.80665 * math.tan(math.radians(10.0))
#: a step is looked for starting in each prediction interval of the last STEP_WINDOW_S before the
#: fusion horizon (the paper's gust at 3 m is more likely than not after 0.1-0.2 s)
STEP_WINDOW_S = 0.3
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
SQRT3 = math.sqrt(3.0)
#: counts: no hypothesis gives the frame's count this much probability: the phase is lost (``_Axis._fuse_counts``)
PHASE_LOST = 1e-9
#: the smallest probability whose logarithm is taken
TINY = 1e-300
#: accelerometer samples kept (5 s at 50 Hz, as the attitude's)
ACCEL_HISTORY = 256
#: the accelerometer's measured noise (second differences) uses samples at most this far apart
ACCEL_MAX_SPACING_S = 0.1
#: with the accelerometer as the input, the drag rate holds only what the input misses in proportion to
#: the velocity (its scale factor and filter: SITL's RAW_IMU reads the truth's acceleration with a slope
#: of 0.97): 1 sigma a tenth of the prior without it
ACCEL_DRAG_PRIOR_PER_S = 0.1 * DRAG_PRIOR_PER_S
#: RAW_IMU's and SCALED_IMU's accelerometer resolution (1 milli-g): its rounding, uniform over it,
#: is the least white noise a sample is taken to have
ACCEL_RESOLUTION_M_S2 = 9.80665e-3


def _phi(t: float) -> float:
    return math.exp(-0.5 * t * t) * 0.3989422804014327


def _cdf(t: float) -> float:
    return 0.5 * math.erfc(-t * 0.7071067811865476)


def _box_integrals(lo: float, hi: float, c: float, s: float) -> tuple[float, float, float]:
    """The integrals of ``x^n Phi((x - c) / s)`` over [``lo``, ``hi``], n = 0, 1, 2."""
    out = [0.0, 0.0, 0.0]
    for sign, x in ((-1.0, lo), (1.0, hi)):
        t = (x - c) / s
        cdf, pdf = _cdf(t), _phi(t)
        g0 = t * cdf + pdf
        g1 = 0.5 * ((t * t - 1.0) * cdf + t * pdf)
        g2 = (t * t * t * cdf + (t * t + 2.0) * pdf) / 3.0
        out[0] += sign * s * g0
        out[1] += sign * (s * c * g0 + s * s * g1)
        out[2] += sign * (s * c * c * g0 + 2.0 * s * s * c * g1 + s * s * s * g2)
    return out[0], out[1], out[2]


def boxed_moments(mu: float, h: float, sd: float, lo: float, hi: float) -> tuple[float, float, float]:
    """A uniform over [``mu - h``, ``mu + h``] plus independent Gaussian noise of standard deviation
    ``sd``, restricted to [``lo``, ``hi``]: (the probability it lies there, its mean and its
    variance there). The prior of a quantizer's running rounding error (``_Axis._fuse_counts``):
    uniform over what the counts so far allow, moved by a Gaussian increment; closed form from
    the integrals of the normal distribution function. Mass 0 when the two do not meet."""
    a, b = lo - mu, hi - mu  # centred on the prior's mean
    if sd <= 1e-4 * h:  # the uniform alone (its edges blurred by less than 1e-4 of its width)
        x0, x1 = max(a, -h), min(b, h)
        if not x1 > x0:
            return 0.0, mu, 0.0
        return (x1 - x0) / (2.0 * h), mu + 0.5 * (x0 + x1), (x1 - x0) ** 2 / 12.0 + sd * sd
    if h <= 1e-4 * sd:  # the Gaussian alone (a truncated normal)
        sd = math.sqrt(sd * sd + h * h / 3.0)
        al, be = a / sd, b / sd
        if al > 0.0:  # both bounds above the mean: the upper tails, for accuracy
            z = 0.5 * (math.erfc(al * 0.7071067811865476) - math.erfc(be * 0.7071067811865476))
        else:
            z = _cdf(be) - _cdf(al)
        if not z > 0.0:
            return 0.0, mu, 0.0
        pa, pb = _phi(al), _phi(be)
        m = (pa - pb) / z
        return z, mu + sd * m, sd * sd * max(1.0 + (al * pa - be * pb) / z - m * m, 0.0)
    lo0, lo1, lo2 = _box_integrals(a, b, -h, sd)
    hi0, hi1, hi2 = _box_integrals(a, b, h, sd)
    m0, m1, m2 = lo0 - hi0, lo1 - hi1, lo2 - hi2  # times 2h
    if not m0 > 0.0:
        return 0.0, mu, 0.0
    mean = m1 / m0
    if abs(mean) < 1e-12 * (hi - lo):  # below the integrals' rounding: a bound symmetric about the mean
        mean = 0.0
    return m0 / (2.0 * h), mu + mean, max(m2 / m0 - mean * mean, 0.0)


def bound_moments(mu: float, h: float, sd: float, lo: float, hi: float) -> tuple[float, float, float]:
    """``boxed_moments``, and where the bound holds nothing of the prediction to double precision
    (far in a tail) the Gaussian tail's beyond the nearer bound: mean ``sd^2 / D`` inside it,
    standard deviation the same, ``D`` the distance from the uniform's edge (mass 0)."""
    mass, mean, var = boxed_moments(mu, h, sd, lo, hi)
    if mass > 0.0:
        return mass, mean, var
    sd = max(sd, 1e-6 * (hi - lo))
    if mu + h < lo:
        tail = sd * sd / (lo - mu - h)
        return 0.0, lo + tail, tail * tail
    tail = sd * sd / (mu - h - hi)
    return 0.0, hi - tail, tail * tail


@dataclass(frozen=True)
class KalmanSettings:
    """The velocity filter's noise model and timing, bound once from a ``Config`` and profile.

    Measurement (eq. 15, per axis): ``v + (range / span) (e_k - e_(k-1)) + w``. ``e_k`` is, for
    sensors that report counts, the running sum's rounding error after frame k (rad; eq. 10: the
    count is the floor of the accumulated angle, so a frame's error is the difference of two and
    a run of frames is exact to one count): within half a count of its cell's centre, ``|e_k| <=
    Q / 2``, ``quantization_rad`` = Q / sqrt 12 the standard deviation of a uniform over one
    count; 0 for rates and radians. ``w`` is white, of variance ``range^2 * flow_noise_rad_s^2``
    plus the range error's share ``(v * range_noise_m / range)^2``, ``flow_noise_rad_s`` the
    gyro's white noise when the config says it has some; for rates and radians the white noise
    measured on the recording (second differences of eq. 15 over ``NOISE_AVERAGE_S``) replaces it
    when larger (the second differences of counts are the quantizer's own pattern, not white
    noise). Process: white acceleration of PSD ``(g ATTITUDE_NOISE_RAD)^2 T`` on the
    velocity, a random walk of PSD ``DISTURBANCE_DRIFT_M_S2^2 / DISTURBANCE_DRIFT_S`` on the
    disturbance and ``DRAG_DRIFT_PER_S_SQRT_S^2`` on the drag rate, and steps in the disturbance
    at ``step_rate_per_s`` of 1 sigma ``step_sigma_m_s2``. Timing: the flow sample is half its
    frame (the integration time the message states, else the frame spacing) plus
    ``flow_sample_age_s`` older than its message's time.
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
    quantization_rad: float = 0.0
    step_rate_per_s: float = STEP_RATE_PER_S
    step_sigma_m_s2: float = STEP_SIGMA_M_S2
    use_accelerometer: bool = True
    accel_noise_m_s2: float = 0.0

    @classmethod
    def from_config(cls, cfg: Any, counts: bool) -> KalmanSettings:
        """``counts``: the profile's flow is integer counts (``paper``), so Q's quantization is
        part of its noise; rates and radians (``ardupilot``, ``px4``) carry no quantization."""
        t = cfg.flow_sensor.frame_period_s
        g = cfg.airframe.gravity_m_s2
        gyro = math.radians(cfg.imu.gyro_noise_density_deg_s_sqrt_hz) * math.sqrt(cfg.imu.rate_hz) \
            if cfg.imu.gyro_noise else 0.0
        rf = cfg.rangefinder
        return cls(gravity_m_s2=g, nominal_frame_s=t, flow_sample_age_s=cfg.companion.flow_sample_age_s,
                   flow_noise_rad_s=gyro,
                   quantization_rad=cfg.flow_sensor.q_rad_per_count / math.sqrt(12.0) if counts else 0.0,
                   range_noise_m=math.hypot(rf.noise_std_m, rf.resolution_m / math.sqrt(12.0)),
                   accel_psd=(g * ATTITUDE_NOISE_RAD) ** 2 * t,
                   disturbance_psd=DISTURBANCE_DRIFT_M_S2 ** 2 / DISTURBANCE_DRIFT_S,
                   drag_psd=DRAG_DRIFT_PER_S_SQRT_S ** 2,
                   use_accelerometer=cfg.companion.use_accelerometer,
                   accel_noise_m_s2=cfg.imu.accel_noise_density_m_s2_sqrt_hz * math.sqrt(cfg.imu.rate_hz)
                   if cfg.imu.accel_noise else 0.0)

    def sample_time_s(self, time_s: float, span_s: float) -> float:
        """When the flow sample of a message stamped ``time_s`` covering ``span_s`` was taken."""
        return time_s - 0.5 * span_s - self.flow_sample_age_s

    def model_variance(self, v_m_s: float, range_m: float) -> float:
        """eq. 15's white noise variance from the sensor model (m^2/s^2) at this speed and range
        (the quantization apart: ``quantization_rad``)."""
        rel = self.range_noise_m / range_m if range_m > 0.0 else 0.0
        return (range_m * self.flow_noise_rad_s) ** 2 + (v_m_s * rel) ** 2


class _Axis:
    """One axis: state (v, b, c, e) = velocity m/s, disturbance acceleration m/s^2, drag rate 1/s
    and, for counts, the running sum's rounding error after the last fused frame, rad (0 and
    fixed without counts), with ``v' = a_tilt + b - c v``; P symmetric 4x4 as its ten entries.

    The candidate steps in ``b``, one per prediction interval of the last ``STEP_WINDOW_S``:
    rates and radians (linear measurements): ``steps``, each ``[dv, db, dc, de, d, info,
    log_prior]``, the error a unit step starting in that interval has left in (v, b, c, e) after
    the filter's own updates (Willsky and Jones' signature), the sum over the innovations since of
    signature x innovation / its variance (``d``) and of signature^2 / variance (``info``), and
    the log of the step's prior probability there; ``mix`` the posterior after the last update:
    per candidate (probability, step size m/s^2, its variance). Counts (a bound, not a linear
    measurement: ``_fuse_counts``): ``bank``, one filter per candidate (an ``_Axis`` begun from
    this one with the step's prior added, ``_onset``), its ``logw`` the log of its prior times
    its likelihood of the counts since against no step's, ``weights`` the posterior. Diagnostics:
    ``nu``, ``nu_var`` the last innovation and its variance (counts: the Gaussian measurement
    equivalent to the bound), ``p_step`` the probability of a step in the window, ``steps_found``
    the steps taken into the state."""

    __slots__ = ("v", "b", "c", "e", "p00", "p01", "p02", "p03", "p11", "p12", "p13", "p22", "p23", "p33",
                 "ready", "steps", "mix", "z1", "z2", "t1", "t2", "r_data", "n_data", "nu", "nu_var", "p_step",
                 "steps_found", "bank", "weights", "logw", "accel_input")

    def __init__(self, s: KalmanSettings) -> None:
        self.b = 0.0
        self.c = s.drag_initial_per_s
        self.p11 = s.disturbance_prior_m_s2 ** 2
        self.p22 = s.drag_prior_per_s ** 2
        self.p12 = 0.0
        self.r_data = math.nan
        self.n_data = 0
        self.steps_found = 0
        self.logw = 0.0
        self.accel_input = False  # the accelerometer is the prediction's input (``accelerometer_input``)
        self.restart(s)

    def accelerometer_input(self) -> None:
        """The accelerometer is the prediction's input from now on: it measures the drag with every
        other force, so the drag rate holds only what the input misses in proportion to the
        velocity: its standard deviation is brought to ``ACCEL_DRAG_PRIOR_PER_S`` if larger (its
        covariances scaled with it). The disturbance state holds the accelerometer's bias, the
        attitude's trim and second-order terms; the step search stays, as the repair of a wrong
        disturbance (docs/estimator.md: a gust is in the input, the steps it takes are not gusts)."""
        self.accel_input = True
        k = min(1.0, ACCEL_DRAG_PRIOR_PER_S / math.sqrt(self.p22)) if self.p22 > 0.0 else 1.0
        self.p02 *= k
        self.p12 *= k
        self.p23 *= k
        self.p22 *= k * k
        for hyp in self.bank:
            hyp.accelerometer_input()

    def unlink(self, s: KalmanSettings) -> None:
        """The previous frame's quantization error is not known (no frame just before this one)."""
        self.e = 0.0
        self.p03 = self.p13 = self.p23 = 0.0
        self.p33 = s.quantization_rad ** 2
        for st in self.steps:
            st[3] = 0.0
        for hyp in self.bank:
            hyp.unlink(s)

    def restart(self, s: KalmanSettings) -> None:
        """Forget the velocity (the next measurement sets it); keep the disturbance and drag."""
        self.v = 0.0
        self.p00 = self.p01 = self.p02 = 0.0
        self.ready = False
        self.steps: list[list[float]] = []
        self.mix: list[tuple[float, float, float]] = []
        self.bank: list[_Axis] = []
        self.weights: list[float] = []
        self.nu = self.nu_var = math.nan
        self.p_step = 0.0
        self.z1 = self.z2 = self.t1 = self.t2 = math.nan
        self.unlink(s)

    def start(self, z: float, r: float, g: float, s: KalmanSettings) -> None:
        """The velocity from one measurement: ``z`` of white variance ``r``, ``g`` = range / span."""
        q2 = s.quantization_rad ** 2
        self.v = z
        self.p00, self.p01, self.p02 = r + 2.0 * g * g * q2, 0.0, 0.0
        # the state's e is this frame's error, which z's error holds with the sign -g
        self.e, self.p03, self.p13, self.p23, self.p33 = 0.0, -g * q2, 0.0, 0.0, q2
        self.ready = True

    def predict(self, accel_integral: float, dt: float, s: KalmanSettings, search: bool = True,
                input_psd: float = 0.0, input_var: float = 0.0) -> None:
        """Over ``dt`` s with the tilt acceleration's integral ``accel_integral`` (m/s; with the
        accelerometer's, ``VelocityKalman._input``); a new candidate step starts in this interval
        (``search``: this is the no-step state). ``input_psd``: the accelerometer's white noise
        on the velocity (m^2/s^3), ``input_var`` its sampling error over the interval (m^2/s^2),
        0 without one."""
        if dt <= 0.0:
            return
        v, b, c = self.v, self.b, self.c
        self.v = v + accel_integral + (b - c * v) * dt
        # F = [[1 - c dt, dt, -v dt, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
        f0, f1, f2 = 1.0 - c * dt, dt, -v * dt
        p00, p01, p02, p11, p12, p22 = self.p00, self.p01, self.p02, self.p11, self.p12, self.p22
        r0 = f0 * p00 + f1 * p01 + f2 * p02  # row 0 of F P
        r1 = f0 * p01 + f1 * p11 + f2 * p12
        r2 = f0 * p02 + f1 * p12 + f2 * p22
        qb = s.disturbance_psd
        self.p00 = f0 * r0 + f1 * r1 + f2 * r2 + s.accel_psd * dt + qb * dt ** 3 / 3.0
        if input_psd or input_var:
            self.p00 += input_psd * dt + input_var
        self.p01 = r1 + qb * dt * dt / 2.0
        self.p02 = r2
        self.p03 = f0 * self.p03 + f1 * self.p13 + f2 * self.p23
        self.p11 = p11 + qb * dt
        self.p22 = p22 + s.drag_psd * dt
        if not search or s.step_rate_per_s <= 0.0:
            return
        window = max(1, round(STEP_WINDOW_S / s.nominal_frame_s))
        if s.quantization_rad > 0.0:  # counts: a filter per candidate (``_fuse_counts``)
            bank = self.bank
            for hyp in bank:
                hyp.predict(accel_integral, dt, s, search=False, input_psd=input_psd, input_var=input_var)
            bank.append(self._onset(dt, s))
            if len(bank) > window:
                del bank[0]
            return
        steps = self.steps
        for st in steps:
            st[0] = f0 * st[0] + f1 * st[1] + f2 * st[2]
        # a unit step at a time uniform over this interval: half of it in v on average
        steps.append([0.5 * dt, 1.0, 0.0, 0.0, 0.0, 0.0, math.log(s.step_rate_per_s * dt)])
        if len(steps) > window:
            del steps[0]

    def _onset(self, dt: float, s: KalmanSettings) -> _Axis:
        """Counts: the hypothesis that a step began in the last ``dt``: this state with a step of
        N(0, step_sigma^2) m/s^2 at a time uniform over the interval (its second moments: b by
        step_sigma^2, v by step_sigma^2 dt^2 / 3, their covariance step_sigma^2 dt / 2), and the
        log of its prior probability as its weight."""
        h = object.__new__(_Axis)
        for name in ("v", "b", "c", "e", "p00", "p01", "p02", "p03", "p11", "p12", "p13", "p22", "p23", "p33",
                     "ready", "z1", "z2", "t1", "t2", "r_data", "n_data", "nu", "nu_var", "p_step", "steps_found",
                     "accel_input"):
            setattr(h, name, getattr(self, name))
        h.steps, h.mix, h.bank, h.weights = [], [], [], []
        var = s.step_sigma_m_s2 ** 2
        h.p00 += var * dt * dt / 3.0
        h.p01 += var * dt / 2.0
        h.p11 += var
        h.logw = math.log(s.step_rate_per_s * dt)
        return h

    def fuse(self, z: float, r: float, g: float, s: KalmanSettings) -> None:
        """Update with eq. 15 of one frame, ``z = v + g (e' - e) + w``: ``e'`` this frame's
        quantization error (rad), ``e`` the last frame's (the state's), ``g`` = range / span (m/s
        per rad), ``w`` white of variance ``r`` (m^2/s^2); then the candidate steps. Rates and
        radians: ``_fuse_white``; counts: ``_fuse_counts``."""
        if s.quantization_rad > 0.0:
            self._fuse_counts(z, r, g, s)
        else:
            self._fuse_white(z, r, g, s)

    def _fuse_white(self, z: float, r: float, g: float, s: KalmanSettings) -> None:
        """Rates and radians: the linear Kalman update (``e`` is 0 and stays 0; the algebra keeps
        ``e'`` as an error independent of the state, the counts' model before the bound)."""
        q2 = s.quantization_rad ** 2
        # P H' over (v, b, c, e, e'), H = [1, 0, 0, -g, g]
        u0 = self.p00 - g * self.p03
        u1 = self.p01 - g * self.p13
        u2 = self.p02 - g * self.p23
        u3 = self.p03 - g * self.p33
        u4 = g * q2
        s_ = u0 - g * u3 + g * u4 + r
        nu = z - self.v + g * self.e
        k0, k1, k2, k4 = u0 / s_, u1 / s_, u2 / s_, u4 / s_
        self.v += k0 * nu
        self.b += k1 * nu
        self.c += k2 * nu
        self.e = k4 * nu  # e' becomes the state's e; the last frame's is no longer needed
        self.p00 -= k0 * u0
        self.p01 -= k0 * u1
        self.p02 -= k0 * u2
        self.p11 -= k1 * u1
        self.p12 -= k1 * u2
        self.p22 -= k2 * u2
        self.p03 = -k0 * u4
        self.p13 = -k1 * u4
        self.p23 = -k2 * u4
        self.p33 = q2 - k4 * u4
        self.nu, self.nu_var = nu, s_
        if not self.steps:
            return
        nu_s, inv_s = nu / s_, 1.0 / s_
        for st in self.steps:  # each candidate's signature in this innovation, then in the state after it
            rho = st[0] - g * st[3]
            st[0] -= k0 * rho
            st[1] -= k1 * rho
            st[2] -= k2 * rho
            st[3] = -k4 * rho
            st[4] += rho * nu_s
            st[5] += rho * rho * inv_s
        if self._posterior(s) > 0.5:
            self._take_step()

    def _fuse_counts(self, z: float, r: float, g: float, s: KalmanSettings) -> None:
        """Counts: ``e'`` is not a new unknown but the running sum's rounding error, ``e' = e +
        (z - v - w) / g`` (the scene moved by what the frame's count and rotation say, less the
        sum's new rounding), and all the frame tells is that it lies within one count, ``|e'| <=
        Q / 2`` (eq. 9-11). Each hypothesis, no step (this state) and a step begun in each
        interval of the window (``bank``, one filter each), takes the bound by moment matching on
        its own prediction of ``e'`` (``_bound``): a bound the prediction lies within tells
        nothing, however often it is applied, so the counts of a slow motion are read once, not
        once a frame. A hypothesis' weight grows by its prediction's probability of the bound
        against no step's: the count's exact likelihood under it. A count no hypothesis gives a
        chance (``PHASE_LOST``): the phase is lost (a slip), ``e`` goes back to its prior."""
        hyps = [self, *self.bank]
        half = s.quantization_rad * SQRT3  # half a count, rad
        priors = [hyp._bound_prior(z, r, g, half) for hyp in hyps]
        if max(pr[4] for pr in priors) < PHASE_LOST:
            self.unlink(s)
            priors = [hyp._bound_prior(z, r, g, half) for hyp in hyps]
        log0 = math.log(max(priors[0][4], TINY))
        for hyp, pr in zip(hyps, priors, strict=True):
            hyp._bound(pr, g)
            hyp.logw += math.log(max(pr[4], TINY)) - log0
        self.logw = 0.0
        if self.bank and self._posterior(s) > 0.5:
            self._take_step()

    def _bound_prior(self, z: float, r: float, g: float, half: float) -> tuple[float, ...]:
        """This state's prediction of the running rounding error ``e' = e + (z - v - w) / g`` and
        the bound |e'| <= ``half`` on it: (its mean, its covariances with v, b, c, its variance,
        the bound's probability, the posterior mean and variance). Its prediction: ``e``'s own
        part (what the velocity does not explain) uniform, the rest Gaussian (``bound_moments``)."""
        inv_g = 1.0 / g
        mu = self.e + (z - self.v) * inv_g
        c0 = self.p03 - self.p00 * inv_g
        c1 = self.p13 - self.p01 * inv_g
        c2 = self.p23 - self.p02 * inv_g
        var = self.p33 - self.p03 * inv_g - c0 * inv_g + r * inv_g * inv_g
        own = min(self.p33, var)  # e's own part (the phase the counts so far allow) as uniform
        h, sd = math.sqrt(3.0 * own), math.sqrt(var - own)
        if abs(mu) + h + 9.0 * sd < half:  # wholly within the bound (to 1e-19): it tells nothing
            return mu, c0, c1, c2, 1.0, mu, var, var
        mass, mean, post = bound_moments(mu, h, sd, -half, half)
        return mu, c0, c1, c2, mass, mean, min(post, var), var

    def _bound(self, pr: tuple[float, ...], g: float) -> None:
        """Take the bound (``_bound_prior``'s ``pr``): the linear regression on ``e'`` moves
        (v, b, c) by its posterior mean's shift and shrinks their covariance by its variance's;
        ``e'`` becomes the state's ``e``. The innovation diagnostics are the Gaussian measurement
        of ``e'`` that does the same (expectation propagation's site), in eq. 15's units."""
        mu, c0, c1, c2, _, mean, post, var = pr
        gain = (mean - mu) / var
        shrink = (var - post) / (var * var)
        self.v += c0 * gain
        self.b += c1 * gain
        self.c += c2 * gain
        self.e = mean
        self.p00 -= c0 * c0 * shrink
        self.p01 -= c0 * c1 * shrink
        self.p02 -= c0 * c2 * shrink
        self.p11 -= c1 * c1 * shrink
        self.p12 -= c1 * c2 * shrink
        self.p22 -= c2 * c2 * shrink
        keep = post / var
        self.p03, self.p13, self.p23, self.p33 = c0 * keep, c1 * keep, c2 * keep, post
        if post < var * (1.0 - 1e-12) and post > 0.0:
            r_site = 1.0 / (1.0 / post - 1.0 / var)
            self.nu, self.nu_var = -g * (mean - mu) * (var + r_site) / var, g * g * (var + r_site)
        else:
            self.nu, self.nu_var = 0.0, math.inf

    def _posterior(self, s: KalmanSettings) -> float:
        """The posterior over no step and one step starting in each candidate interval (prior
        ``log_prior``, size N(0, step_sigma^2)): fills ``mix`` (counts: ``weights``); returns the
        probability of a step."""
        if self.bank:  # counts: each hypothesis' weight against no step's (``weights``)
            logs = [hyp.logw for hyp in self.bank]
            top = max(0.0, *logs)
            ws = [math.exp(lg - top) for lg in logs]
            norm = math.exp(-top) + sum(ws)
            self.weights = [w / norm for w in ws]
            self.p_step = sum(ws) / norm
            return self.p_step
        a = 1.0 / (s.step_sigma_m_s2 * s.step_sigma_m_s2)
        logs = [lp + 0.5 * (math.log(a / (info + a)) + d * d / (info + a)) for _, _, _, _, d, info, lp in self.steps]
        top = max(0.0, *logs)
        ws = [math.exp(lg - top) for lg in logs]
        norm = math.exp(-top) + sum(ws)
        self.mix = [(w / norm, st[4] / (st[5] + a), 1.0 / (st[5] + a)) for w, st in zip(ws, self.steps, strict=True)]
        self.p_step = sum(ws) / norm
        return self.p_step

    def _take_step(self) -> None:
        """A step is more likely than not: the state becomes the posterior's mean and covariance
        over no step and each candidate (moment matched), and the search starts again."""
        if self.bank:
            self._merge_bank()
            return
        m = [0.0, 0.0, 0.0, 0.0]
        m2 = [0.0] * 10  # the correction's second moment, upper triangle of 4x4 row by row
        for (w, beta, var), st in zip(self.mix, self.steps, strict=True):
            wb, we2 = w * beta, w * (var + beta * beta)
            k = 0
            for i in range(4):
                m[i] += wb * st[i]
                for j in range(i, 4):
                    m2[k] += we2 * st[i] * st[j]
                    k += 1
        self.v += m[0]
        self.b += m[1]
        self.c += m[2]
        self.e += m[3]
        cov = [m2[k] - m[i] * m[j] for k, (i, j) in enumerate((i, j) for i in range(4) for j in range(i, 4))]
        self.p00 += cov[0]
        self.p01 += cov[1]
        self.p02 += cov[2]
        self.p03 += cov[3]
        self.p11 += cov[4]
        self.p12 += cov[5]
        self.p13 += cov[6]
        self.p22 += cov[7]
        self.p23 += cov[8]
        self.p33 += cov[9]
        self.steps, self.mix = [], []
        self.steps_found += 1

    def _merge_bank(self) -> None:
        """Counts: the state becomes the mixture of no step and the hypotheses (``weights``),
        its mean and covariance over (v, b, c, e)."""
        hyps = [self, *self.bank]
        ws = [1.0 - self.p_step, *self.weights]
        xs = [(h.v, h.b, h.c, h.e) for h in hyps]
        ps = [((h.p00, h.p01, h.p02, h.p03), (h.p01, h.p11, h.p12, h.p13), (h.p02, h.p12, h.p22, h.p23),
               (h.p03, h.p13, h.p23, h.p33)) for h in hyps]
        m = [sum(w * x[i] for w, x in zip(ws, xs, strict=True)) for i in range(4)]
        cov = [[sum(w * (p[i][j] + x[i] * x[j]) for w, x, p in zip(ws, xs, ps, strict=True)) - m[i] * m[j]
                for j in range(4)] for i in range(4)]
        self.v, self.b, self.c, self.e = m
        self.p00, self.p01, self.p02, self.p03 = cov[0]
        self.p11, self.p12, self.p13 = cov[1][1:]
        self.p22, self.p23 = cov[2][2:]
        self.p33 = cov[3][3]
        self.bank, self.weights = [], []
        self.steps_found += 1

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

    def output(self, accel_integral: float, dt: float, s: KalmanSettings, input_psd: float = 0.0,
               input_var: float = 0.0) -> tuple[float, float]:
        """The velocity and its variance ``dt`` s after the state's time, without changing the
        state: the posterior mean over no step and the candidate steps, its variance the mixture's
        plus that of a step too recent for any fused sample to show."""
        v, b, c = self.v, self.b, self.c
        f0, f1, f2 = 1.0 - c * dt, dt, -v * dt
        var = (f0 * (f0 * self.p00 + f1 * self.p01 + f2 * self.p02) + f1 * (f0 * self.p01 + f1 * self.p11
               + f2 * self.p12) + f2 * (f0 * self.p02 + f1 * self.p12 + f2 * self.p22)
               + s.accel_psd * dt + (s.disturbance_psd + s.step_rate_per_s * s.step_sigma_m_s2 ** 2) * dt ** 3 / 3.0)
        if input_psd or input_var:
            var += input_psd * dt + input_var
        out = v + accel_integral + (b - c * v) * dt
        if self.bank:  # counts: the mixture of no step and the hypotheses
            m1 = (1.0 - self.p_step) * out
            m2 = (1.0 - self.p_step) * (var + out * out)
            for w, hyp in zip(self.weights, self.bank, strict=True):
                o, vo = hyp.output(accel_integral, dt, s, input_psd, input_var)
                m1 += w * o
                m2 += w * (vo + o * o)
            return m1, m2 - m1 * m1
        if self.mix:
            m1 = m2 = 0.0
            for (w, beta, var_b), st in zip(self.mix, self.steps, strict=True):
                x = f0 * st[0] + f1 * st[1] + f2 * st[2]
                m1 += w * beta * x
                m2 += w * (var_b + beta * beta) * x * x
            out += m1
            var += m2 - m1 * m1
        return out, var


class VelocityKalman:
    """The companion's velocity estimate (issue 19), both axes, pure: every time is passed in.

    Per axis a Kalman filter (velocity, disturbance acceleration, linear drag rate, and for counts
    the running rounding error of their sum; ``_Axis``) predicted with the attitude,
    ``v' = s g tan(tilt) + b - c v`` (the plant's eq. 28 with the unknown force as ``b`` and drag
    as ``c``), from the ATTITUDE samples (``on_attitude``) interpolated linearly between them; and
    updated with eq. 15 (``update``) **at the flow sample's own time**
    (``KalmanSettings.sample_time_s``): the state is kept at the time of the last fused sample (the
    fusion horizon), predicted from there to the next sample's time, updated, and the estimate
    handed out is that state carried forward with the attitude to the newest information, the
    frame's time or the newest attitude, whichever is later (past the newest attitude with its
    rates, ``MAX_EXTRAPOLATION_S`` at most). A step in the disturbance (a gust) is searched for
    over the last ``STEP_WINDOW_S``: the estimate handed out is the posterior mean over no step and
    a step starting in each interval, and once a step is more likely than not the state takes it
    (``_Axis``). The noise model is ``KalmanSettings``'s; docs/estimator.md says where each number
    comes from.

    Without a fresh attitude (none within ``MAX_ATTITUDE_AGE_S`` of the frame) there is nothing
    to predict with: eq. 15 is returned with its variance, and the velocity restarts from the
    next measurement once the attitude is back. A measurement more than ``MAX_GAP_S`` after the
    last fused one restarts the velocity too; a clock going back (a reboot) restarts everything.
    """

    def __init__(self, settings: KalmanSettings) -> None:
        self.s = settings
        self.attitude: deque[tuple[float, float, float, float, float]] = deque(maxlen=ATTITUDE_HISTORY)
        #: the accelerometer's horizontal non-gravitational acceleration (time s, x, y m/s^2), ``on_accel``
        self.accel: deque[tuple[float, float, float]] = deque(maxlen=ACCEL_HISTORY)
        #: whether the vehicle has shown an accelerometer (a reading other than the placeholder)
        self.accel_seen = False
        self._accel_noise_reset()
        self.reset()

    def _accel_noise_reset(self) -> None:
        self.acc_r = [math.nan, math.nan]  # measured white noise per axis (m^2/s^4)
        self.acc_n = 0
        self.acc_spacing_s = math.nan
        self.input_psd = (0.0, 0.0)  # the accelerometer's white noise on the velocity, per axis (m^2/s^3)

    def reset(self) -> None:
        """Back to the priors (a new vehicle or a rebooted one); the attitude history is kept."""
        self.axes = (_Axis(self.s), _Axis(self.s))
        self.horizon_s = math.nan  # the time of the state: the last fused sample's
        self.last_time_s = math.nan  # the last frame's message time (s)

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

    def on_accel(self, time_s: float, f_x_m_s2: float, f_y_m_s2: float) -> None:
        """One accelerometer sample (a gyro message's accelerometer, ``profiles.accel_m_s2``: body
        FRD specific force, m/s^2, at the message's own time): to first order in the tilt the
        horizontal non-gravitational force over mass (wind, gust, drag), which the attitude's
        ``g tan(tilt)`` leaves out (eq. 28's ``F_W / m``), taken as ``f / cos(tilt)`` per axis with
        the newest attitude (exact for one axis of the plant). It is the prediction's input
        (``_input``), with its white noise (``input_psd``). Ignored: a non-finite sample (clipped,
        NaN), every sample while the settings say not to use it, and every sample until the
        vehicle shows a horizontal reading other than exactly 0: a vehicle without an accelerometer
        sends the (0, 0, -1 g) placeholder, and the filter is then exactly the one without."""
        if not (self.s.use_accelerometer and math.isfinite(time_s) and math.isfinite(f_x_m_s2)
                and math.isfinite(f_y_m_s2)):
            return
        if not self.accel_seen:
            if f_x_m_s2 == 0.0 and f_y_m_s2 == 0.0:
                return
            self.accel_seen = True
        h = self.accel
        if h:
            last = h[-1][0]
            if time_s < last - CLOCK_RESTART_S:  # the vehicle's clock restarted
                h.clear()
                self._accel_noise_reset()
            elif time_s <= last:  # the same time again (replace) or slightly out of order (drop)
                if time_s == last:
                    h[-1] = (time_s, *self._horizontal(f_x_m_s2, f_y_m_s2))
                return
        a_x, a_y = self._horizontal(f_x_m_s2, f_y_m_s2)
        self._accel_noise(time_s, a_x, a_y)
        h.append((time_s, a_x, a_y))
        if self.acc_n == 0:  # not measured yet: the config's noise at the frame spacing
            q = self._accel_noise_floor() * self.s.nominal_frame_s
            self.input_psd = (q, q)

    def _horizontal(self, f_x: float, f_y: float) -> tuple[float, float]:
        """The specific force over the cosine of the newest attitude's tilt, per axis."""
        if not self.attitude:
            return f_x, f_y
        g = self.s.gravity_m_s2
        _, tx, ty = self.attitude[-1][:3]  # -g tan(pitch), g tan(roll): 1 / cos = sqrt(1 + tan^2)
        return f_x * math.sqrt(1.0 + (tx / g) ** 2), f_y * math.sqrt(1.0 + (ty / g) ** 2)

    def _accel_noise(self, t: float, a_x: float, a_y: float) -> None:
        """The accelerometer's white noise per axis: the larger of the config's
        (``KalmanSettings.accel_noise_m_s2``) and the one measured on the samples, the mean of
        (second difference)^2 / 6 (a running mean, then ``NOISE_AVERAGE_S`` of memory, as the
        flow's ``_Axis.measured_noise``), over consecutive samples at most
        ``ACCEL_MAX_SPACING_S`` apart; on the velocity it is white of PSD noise^2 x the sample
        spacing (its running mean)."""
        h = self.accel
        if len(h) < 2 or not (0.0 < t - h[-1][0] <= ACCEL_MAX_SPACING_S
                              and 0.0 < h[-1][0] - h[-2][0] <= ACCEL_MAX_SPACING_S):
            return
        dt = t - h[-1][0]
        self.acc_n += 1
        w = max(1.0 / self.acc_n, dt / NOISE_AVERAGE_S)
        sp = self.acc_spacing_s
        self.acc_spacing_s = dt if self.acc_n == 1 else (1.0 - w) * sp + w * dt
        floor = self._accel_noise_floor()
        psd = []
        for i, a in enumerate((a_x, a_y)):
            d2 = a - 2.0 * h[-1][1 + i] + h[-2][1 + i]
            sample = d2 * d2 / 6.0
            r = self.acc_r[i]
            if self.acc_n > 1:  # a jolt (a gust's step) is not noise: a sample counts at most 9 times the mean
                sample = min(sample, 9.0 * max(r, floor))
            self.acc_r[i] = sample if self.acc_n == 1 else (1.0 - w) * r + w * sample
            psd.append(max(self.acc_r[i], floor) * self.acc_spacing_s)
        self.input_psd = (psd[0], psd[1])

    def _accel_noise_floor(self) -> float:
        """The least white noise variance of an accelerometer sample (m^2/s^4): the config's, and
        at least the 1 mg rounding's (``ACCEL_RESOLUTION_M_S2``)."""
        return max(self.s.accel_noise_m_s2 ** 2, ACCEL_RESOLUTION_M_S2 ** 2 / 12.0)

    def _input(self, t0: float, t1: float) -> tuple[float, float, float, float]:
        """The prediction's input from ``t0`` to ``t1``, both axes, m/s, and its sampling error's
        variance, m^2/s^2: the tilt acceleration's integral (``_integral``) and, once the vehicle
        has shown an accelerometer, the accelerometer's: a sample is the mean over the interval
        since the sample before it (an IMU's decimation: PX4's delta velocity, ArduPilot's low-pass
        filtered samples), the newest held after it, 0 before the first's interval (there was none:
        the disturbance state held what it would have told). A stretch ``d`` of a sample's interval
        ``T_j`` is wrong by up to ``da d (T_j - d) / T_j``, ``da`` the change from the sample before
        (the force may have changed anywhere inside; a whole interval is exact), taken as uniform,
        variance a twelfth of its square; after the newest sample by up to ``da d``."""
        ix, iy = self._integral(t0, t1)
        h = self.accel
        if not h or not t1 > t0:
            return ix, iy, 0.0, 0.0
        spacing = self.acc_spacing_s if self.acc_spacing_s == self.acc_spacing_s else self.s.nominal_frame_s
        jx = jy = vx = vy = 0.0
        n = len(h)
        i = n - 1
        while i > 0 and h[i - 1][0] > t0:  # h[i]: the first sample after t0 (or the newest)
            i -= 1
        if i > 0:
            prev_t, prev = h[i - 1][0], (h[i - 1][1], h[i - 1][2])
        else:
            prev_t, prev = h[0][0] - spacing, (0.0, 0.0)  # the start of the first sample's interval
        a = t0
        for j in range(i, n):  # the samples whose interval meets [t0, t1], oldest first
            k = h[j]
            tk = k[0]
            if tk > a:
                b = min(tk, t1)
                if b > prev_t:
                    lo = max(a, prev_t)
                    d, span = b - lo, tk - prev_t
                    jx += k[1] * d
                    jy += k[2] * d
                    e = d * (span - d) / span
                    vx += ((k[1] - prev[0]) * e) ** 2 / 12.0
                    vy += ((k[2] - prev[1]) * e) ** 2 / 12.0
                a = b
                if a >= t1:
                    break
            prev_t, prev = tk, (k[1], k[2])
        if a < t1:  # after the newest sample: held
            d = t1 - a
            new, old = h[-1], (h[-2] if len(h) > 1 else (0.0, 0.0, 0.0))
            jx += new[1] * d
            jy += new[2] * d
            vx += ((new[1] - old[1]) * d) ** 2 / 12.0
            vy += ((new[2] - old[2]) * d) ** 2 / 12.0
        return ix + jx, iy + jy, vx, vy

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
        g = range_m / (span_s if span_s > 0.0 else s.nominal_frame_s)  # m/s per rad of flow
        gq2 = (g * s.quantization_rad) ** 2  # one frame's quantization error in eq. 15, m^2/s^2
        # the frame just before this one was fused: the running sum goes on from the state's e
        linked = 0.0 < time_s - self.last_time_s <= 1.5 * s.nominal_frame_s
        self.last_time_s = time_s
        r_model = (s.model_variance(z_x, range_m), s.model_variance(z_y, range_m))
        r = []
        if self.accel and not axes[0].accel_input:  # the accelerometer is the input from now on
            for ax in axes:
                ax.accelerometer_input()
        for ax, z, rm in zip(axes, (z_x, z_y), r_model, strict=True):
            if not linked:
                ax.unlink(s)
            if gq2 > 0.0:  # counts: the quantizer is modelled exactly, the white rest is the sensor model's
                r.append(rm)
                continue
            measured = ax.measured_noise(t_m, z, s.nominal_frame_s)
            if measured != measured:  # not measured yet: the model, or the generous prior if larger
                measured = (range_m * FLOW_NOISE_PRIOR_RAD_S) ** 2
            r.append(measured if measured > rm else rm)
        if not self.fresh(time_s):
            for ax in axes:
                ax.restart(s)
            self.horizon_s = math.nan
            return z_x, z_y, r[0] + 2.0 * gq2, r[1] + 2.0 * gq2
        h = self.horizon_s
        if h == h and t_m < h - CLOCK_RESTART_S:  # the vehicle's clock restarted
            self.reset()
            return self.update(time_s, span_s, z_x, z_y, range_m)
        if not (h == h and t_m - h <= MAX_GAP_S and all(ax.ready for ax in axes)):
            for ax, z, rr in zip(axes, (z_x, z_y), r, strict=True):
                ax.restart(s)
                ax.start(z, rr, g, s)
        else:
            t_m = max(t_m, h)  # a sample older than the horizon is fused at the horizon
            ix, iy, jx, jy = self._input(h, t_m)
            for ax, a_int, z, rr, q, j in zip(axes, (ix, iy), (z_x, z_y), r, self.input_psd, (jx, jy), strict=True):
                ax.predict(a_int, t_m - h, s, input_psd=q, input_var=j)
                ax.fuse(z, rr, g, s)
        self.horizon_s = t_m
        t_out = max(time_s, self.attitude[-1][0])
        ox, oy, jx, jy = self._input(t_m, t_out)
        (vx, var_x), (vy, var_y) = (ax.output(o, t_out - t_m, s, q, j)
                                    for ax, o, q, j in zip(axes, (ox, oy), self.input_psd, (jx, jy), strict=True))
        return vx, vy, var_x, var_y
