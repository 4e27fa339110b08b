"""The translational channels: the flow against the rotation and the plant, and the force balance.

Per axis i (x pairs with pitch, y with roll; s_x = -1, s_y = +1, CONVENTIONS.md) the paper's
model says the scene angle the flow sensor integrates is

    phi_i(t) = R_i(t) - Y_i(t),   R_i = s_i (angle_i(t) - angle_i(0)),   Y_i = integral(v_i / A) dt
    v_i' = s_i g tan(angle_i) + F_i / m - (b / m) v_i

The recorded attitude (ATTITUDE) gives R exactly and the tilt acceleration s g tan(angle); the
recorded flow gives phi; the range gives A. Two residual channels come out of this, each built so
that the closed loop cannot hide what it measures (the inputs are recorded signals, never a
simulation of the loop):

``flow_x``, ``flow_y`` (rad): over windows of ``flow_window_s`` the recorded scene angle minus the
model's, after removing per window and axis a cubic in time and, where it shows, the scene angle
the window's unknown start velocity adds, v0 times the integral of 1 / A (``project_windows``: the
unknown velocity at the window start and a slowly varying force; translation is smooth, so what
remains is the rotation content, the part the plant's tilt predicts, and how the sensor's geometry
distorts them). This is where ``flow_scale`` (the rotation comes out scaled), ``flow_delay`` (the
rotation comes out late), ``flow_yaw_misalignment`` (one axis' rotation leaks into the other) and,
weakly, ``range_offset`` show.

``force_x``, ``force_y`` (N): over windows of ``force_window_s`` the change in flow-derived velocity
minus the change the tilt explains, times m / window length: the mean horizontal force the model
leaves unexplained. Steady drag and wind, which the PI integrator hides in the velocity, show here
in full (the vehicle must tilt against them). The flow-derived velocity uses the model's sensor
geometry (scale, turn, delay, range offset), so ``range_offset`` (a velocity scale that changes
with altitude) and ``flow_scale`` show here too.

Both channels are vectors of window residuals, linear-time in the recording, and are evaluated
for any parameter vector ``PARAMS`` (nominal = ``NOMINAL``) by ``FlowProblem.residuals``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.interpolate import CubicSpline

from companion import native
from companion.diagnose import filters
from companion.diagnose.closed_loop.channels import FlightData
from companion.diagnose.closed_loop.select import robust_std

AXIS_SIGN = (-1.0, 1.0)
#: parameter vector of the translational model (CONVENTIONS.md names)
PARAMS = ("scale_x", "scale_y", "yaw", "delay", "offset", "b", "fx", "fy", "gain", "c", "rz")
NOMINAL = np.array([1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
IDX = {p: i for i, p in enumerate(PARAMS)}


#: a window's start-velocity direction (``FlowProblem._start_velocity_directions``) is removed
#: when what the cubic leaves of it is at least this share of it (below: round-off of a constant A)
START_VELOCITY_MIN_SHARE = 1e-9

#: flow windows with more bridged (lost) frames than this share, or a run of bridged frames longer
#: than ``BRIDGED_RUN_MAX`` frames, are left out of the flow and force channels
BRIDGED_SHARE_MAX = 0.25
BRIDGED_RUN_MAX = 3


#: the inertial rows (``FlowProblem.inertial_residual``) take an accelerometer bias of their own
#: per block of this long within a segment (s): a bias drifts with temperature over a long flight
INERTIAL_BIAS_BLOCK_S = 60.0
#: the inertial rows are the windows whose mean acceleration (the accelerometer's) is at least
#: this many times the rows' noise on either axis (``FlowProblem.inertial_residual``)
INERTIAL_ACTIVE_TIMES_NOISE = 10.0


def _long_runs(missing: np.ndarray, max_len: int) -> np.ndarray:
    """Frames in runs of True longer than ``max_len``."""
    out = np.zeros(len(missing), dtype=bool)
    if not np.any(missing):
        return out
    x = np.concatenate([[False], missing, [False]]).astype(int)
    d = np.diff(x)
    for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True):
        if b - a > max_len:
            out[a:b] = True
    return out


def _cumtrapz(y: np.ndarray, t: np.ndarray) -> np.ndarray:
    out = np.zeros_like(y)
    out[1:] = np.cumsum(0.5 * (y[1:] + y[:-1]) * np.diff(t))
    return out


def accel_bias_removed(v_acc: np.ndarray, v_tilt: np.ndarray, x_flow: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``v_acc`` (the velocity the accelerometer's levelled force adds over one segment, m/s) less
    the ramp b (t - t0) of a constant accelerometer bias b: the b whose ramp, integrated, best
    explains (least squares, with a position and a velocity of its own) how the displacement of
    ``v_tilt + v_acc`` drifts away from the flow's odometry ``x_flow`` (m) over the segment.

    Why: a flight accelerometer keeps a bias of a tenth of a m/s^2 after calibration; integrated
    over a minute's segment that is metres per second, far more than the forces it is there for.
    Neither the accelerometer's own mean (a vehicle held against drag or wind for the whole
    segment has a true mean force of 1 m/s^2 and more) nor a high-pass can tell the two apart;
    the flow can: the vehicle's true velocity stays bounded, its odometry's curvature over the
    segment is the true mean acceleration (read through the nominal geometry, which a scale error
    changes by a share of that mean, small over any segment longer than a manoeuvre)."""
    if len(t) < 4 or t[-1] <= t[0]:
        return v_acc
    tau = t - t[0]
    d = _cumtrapz(v_tilt + v_acc, t) - x_flow
    basis = np.stack([np.ones_like(tau), tau, 0.5 * tau * tau], axis=1)
    ok = np.isfinite(d)
    if ok.sum() < 4:
        return v_acc
    coef, *_ = np.linalg.lstsq(basis[ok], d[ok], rcond=None)
    return v_acc - coef[2] * tau


def level_acceleration(fx: np.ndarray, fy: np.ndarray, fz: np.ndarray, pitch_rad: np.ndarray,
                       roll_rad: np.ndarray) -> np.ndarray:
    """(2, n) the horizontal acceleration (m/s^2) along the flow's axes (x forward, y right, level,
    the heading's) that the body FRD specific force (fx, fy, fz) gives at (pitch, roll): R f + g
    with R = Ry(pitch) Rx(roll), whose horizontal rows do not hold gravity. A hover's
    f = (0, 0, -g / (cos pitch cos roll)) gives (-g tan pitch, g tan roll / cos pitch): the paper's
    s g tan(angle) (``AXIS_SIGN``) to second order in the other angle, with the thrust as measured
    (a vehicle that sinks while it tilts accelerates less than g tan: ArduCopter SITL)."""
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    return np.stack([cp * fx + sp * sr * fy + sp * cr * fz, cr * fy - sr * fz])


def ramp_integral(t: np.ndarray, start_s: float | np.ndarray, end_s: float | np.ndarray) -> np.ndarray:
    """G(t) = integral_0^t clip(tau - start, 0, end - start) dtau (s^2): the double integral of a
    unit force switched on over [start, end). Broadcasts (e.g. start, end of shape (G, 1))."""
    start = np.asarray(start_s, dtype=float)
    end = np.asarray(end_s, dtype=float)
    if start.ndim == 0 and not (math.isfinite(float(start)) and math.isfinite(float(end)) and end > start):
        return np.zeros_like(t)
    d = np.maximum(end - start, 0.0)
    on = np.minimum(np.maximum(t - start, 0.0), d)  # time the force has acted by t (np.clip, without its wrapper)
    return 0.5 * on * on + d * np.maximum(t - end, 0.0)


def _bridge_plan(lost: np.ndarray) -> tuple[np.ndarray, ...] | None:
    """For the lost entries of ``lost`` (n_windows, m): their (window, position), the nearest
    recorded positions left and right in the same window (one side's when the other has none) and
    the left one's linear-interpolation weight; None when nothing is lost (or nothing is recorded)."""
    if not np.any(lost) or np.all(lost):
        return None
    m = lost.shape[1]
    pos = np.arange(m)
    rec_pos = np.where(lost, -1, pos)
    left = np.maximum.accumulate(rec_pos, axis=1)  # nearest recorded at or before (-1: none)
    rec_pos_r = np.where(lost, m, pos)
    right = np.minimum.accumulate(rec_pos_r[:, ::-1], axis=1)[:, ::-1]  # at or after (m: none)
    w, j = np.nonzero(lost)
    jl, jr = left[w, j], right[w, j]
    keep = (jl >= 0) | (jr < m)  # a window with nothing recorded keeps its bridged steps
    w, j, jl, jr = w[keep], j[keep], jl[keep], jr[keep]
    jl_ok, jr_ok = jl >= 0, jr < m
    al = np.where(jl_ok & jr_ok, (jr - j) / np.maximum(jr - jl, 1), np.where(jl_ok, 1.0, 0.0))
    jl = np.where(jl_ok, jl, jr)
    jr = np.where(jr_ok, jr, jl)
    return w, j, jl, jr, al.astype(float)


@dataclass
class Windows:
    """Index structure of one channel's windows (flat frame indices)."""

    idx: np.ndarray  # (n_windows, L) frame indices (flow) or (n_windows, 2) boundary pairs (force)
    t_start_s: np.ndarray
    t_end_s: np.ndarray


class _Cache:
    """The last few results of an expensive piece, keyed by the parameters it depends on (a
    Jacobian varies one parameter at a time, so most pieces repeat)."""

    def __init__(self, size: int = 6) -> None:
        self.size = size
        self.items: dict[tuple[float, ...], object] = {}

    def get(self, key: tuple[float, ...], make: Callable[[], Any]) -> Any:
        if key in self.items:
            return self.items[key]
        value = make()
        if len(self.items) >= self.size:
            self.items.pop(next(iter(self.items)))
        self.items[key] = value
        return value


def _geometry_key(p: np.ndarray) -> tuple[float, ...]:
    """The parameters the flow's odometry depends on (scale, turn, delay, range offset, rotation
    gain, lever arm): the key of what is cached per sensor geometry."""
    return tuple(float(x) for x in (p[0], p[1], p[2], p[3], p[4], p[8], p[10]))


class _FormDrag:
    """The force channel's form-drag regressor ``dq`` for one sensor geometry, made on first use:
    it needs the odometry's rate over the whole flight, the costliest piece of the force channel,
    and most residuals have no form drag."""

    def __init__(self, fp: FlowProblem, X: np.ndarray) -> None:
        self._fp = fp
        self._X = X
        self._dq: np.ndarray | None = None

    def dq(self) -> np.ndarray:
        if self._dq is None:
            self._dq = self._form_drag_regressor()
        return self._dq

    def _form_drag_regressor(self) -> np.ndarray:
        fp, X = self._fp, self._X
        lib = native.kernels()
        if lib is not None and X.shape == (2, len(fp.t)) and len(fp.t) >= 2 and len(fp._k0):
            # the compiled copy (``fh_form_drag``, tests/test_native.py holds the two equal)
            args = fp._native()
            X = np.ascontiguousarray(X, dtype=float)
            out = np.empty((2, len(fp._k0)))
            scratch = np.empty(2 * X.shape[1])
            lib.fh_form_drag(X.ctypes.data, X.shape[1], args["t"].ctypes.data, args["dt"].ctypes.data,
                             args["seg_starts"].ctypes.data, args["seg_stops"].ctypes.data, len(args["seg_starts"]),
                             args["k0"].ctypes.data, args["k1"].ctypes.data, args["den0"].ctypes.data,
                             args["den1"].ctypes.data, len(fp._k0), fp.h, scratch.ctypes.data, out.ctypes.data)
            return out
        # the form-drag regressor: integral of v |v|, v the odometry's change over +-h frames (the
        # boundary-averaging span): a frame-to-frame derivative of quantized odometry is a train of
        # spikes, and squared they would swamp the drag
        v = np.zeros_like(X)
        h = fp.h
        t = fp.t
        for a, b in fp.data.segments():
            if b - a > 2 * h + 1:
                # inside the segment lo = k - h, hi = k + h (slices); at its ends they are clipped
                v[:, a + h:b - h] = (X[:, a + 2 * h:b] - X[:, a:b - 2 * h]) / (t[a + 2 * h:b] - t[a:b - 2 * h])
                k = np.r_[a:a + h, b - h:b]
                lo = np.clip(k - h, a, b - 1)
                hi = np.clip(k + h, a, b - 1)
                v[:, k] = (X[:, hi] - X[:, lo]) / (t[hi] - t[lo])
        # integral of v|v| (as X is of v); the windows' change of its integral's boundary means, as
        # for dx
        return fp._window_means(fp._integral(fp._integral(v * np.abs(v))))


class FlowProblem:
    """The two translational channels of one flight, ready to evaluate for any parameters.

    ``flow_window_s``: length of the flow-geometry windows; ``force_window_s``: spacing of the
    force-balance boundaries; ``average_s``: the velocity at a boundary is the mean over this span;
    ``max_flow_windows``: a longer recording uses this many evenly spread flow windows (25 min of
    1 s windows pin the sensor geometry far below any tolerance; the force channel uses every window).
    ``accelerometer``: the flow channels' translation from the tilt's acceleration plus the
    horizontal force the accelerometer measures (``FlightData.accel_x_m_s2``: drag, wind and
    turbulence, which the tilt does not give; the force channels keep the tilt alone, they measure
    that force).
    """

    def __init__(self, data: FlightData, *, mass_kg: float, gravity_m_s2: float, flow_window_s: float = 1.0,
                 force_window_s: float = 1.0, average_s: float = 0.2, max_flow_windows: int = 1000,
                 rotation_angles: tuple[np.ndarray, np.ndarray] | None = None,
                 scene_angle: np.ndarray | None = None, accelerometer: bool = False) -> None:
        self.data = data
        self.mass_kg = mass_kg
        self.g = gravity_m_s2
        T = data.frame_s
        self.L1 = max(8, int(round(flow_window_s / T)))
        self.L2 = max(4, int(round(force_window_s / T)))
        self.h = max(1, int(round(0.5 * average_s / T)))
        t = data.t_s
        n = data.n
        self.t = t
        self.A = data.range_m
        # per-frame signals, per segment
        self.R = np.zeros((2, n))
        self.Phi = np.zeros((2, n))
        self.V = np.zeros((2, n))
        self.D = np.zeros((2, n))
        self.Rdot = np.zeros((2, n))
        self.RA = np.zeros((2, n))
        self._splines: list[tuple[int, int, CubicSpline]] = []
        ang = (data.pitch_rad, data.roll_rad)
        #: the angles the rotation is taken from (pitch, roll): the recorded attitude, or a fused one
        rot = rotation_angles if rotation_angles is not None else ang
        self.rotation_angles = rotation_angles
        dphi = (data.dphi_x_rad, data.dphi_y_rad)
        flow_w: list[np.ndarray] = []
        force_w: list[np.ndarray] = []
        acc_xy = (data.accel_x_m_s2, data.accel_y_m_s2)
        v_acc = np.zeros((2, n)) if accelerometer and acc_xy[0] is not None and acc_xy[1] is not None else None
        for a, b in data.segments():
            ts = t[a:b]
            for i in (0, 1):
                s = AXIS_SIGN[i]
                self.R[i, a:b] = s * (rot[i][a:b] - rot[i][a])
                self.Phi[i, a:b] = np.cumsum(dphi[i][a:b]) if scene_angle is None else scene_angle[i, a:b]
                acc = s * self.g * np.tan(ang[i][a:b])
                self.V[i, a:b] = _cumtrapz(acc, ts)
                self.D[i, a:b] = _cumtrapz(self.V[i, a:b], ts)
                # a flow sensor rz below the centre of gravity moves at v + omega x r: its translation
                # carries the body rate times rz / A, i.e. integral(dR / A)
                inc_r = np.diff(self.R[i, a:b]) / (0.5 * (self.A[a + 1:b] + self.A[a:b - 1]))
                self.RA[i, a:b] = np.concatenate([[0.0], np.cumsum(inc_r)])
            if v_acc is not None:
                # the body axes' specific force, levelled: what pushes the vehicle besides its tilt
                # (its bias taken out below, once the flow's odometry is at hand)
                for i in (0, 1):
                    acc_b = acc_xy[i]
                    assert acc_b is not None
                    v_acc[i, a:b] = _cumtrapz(np.nan_to_num(acc_b[a:b]) / np.cos(ang[i][a:b]), ts)
            sp = CubicSpline(ts, self.R[:, a:b].T, axis=0)
            self._splines.append((a, b, sp))
            self.Rdot[:, a:b] = sp(ts, 1).T
            # windows of whole frames; the first and last window of a segment are left out, so that
            # a delayed (or advanced) signal never reaches past the segment's ends (|delay| < 1 window)
            m = b - a
            nw = m // self.L1
            if nw >= 3:
                flow_w.append(a + self.L1 + np.arange((nw - 2) * self.L1).reshape(nw - 2, self.L1))
            bounds = np.arange(a + self.h + self.L2, b - self.h - self.L2, self.L2)
            if len(bounds) >= 2:
                force_w.append(np.stack([bounds[:-1], bounds[1:]], axis=1))
        fwin = np.concatenate(flow_w) if flow_w else np.zeros((0, self.L1), int)
        # windows over lost flow frames: a few isolated ones are bridged well (rotation from the
        # attitude, translation interpolated); a window with a long run or many is left out
        long_gap = _long_runs(~data.flow_rec, BRIDGED_RUN_MAX)
        if len(fwin):
            bridged = (~data.flow_rec)[fwin]
            fwin = fwin[(bridged.mean(axis=1) <= BRIDGED_SHARE_MAX) & ~long_gap[fwin].any(axis=1)]
        if len(fwin) > max_flow_windows:  # a long recording: evenly spread windows are plenty
            fwin = fwin[np.unique(np.linspace(0, len(fwin) - 1, max_flow_windows).round().astype(int))]
        fw = np.concatenate(force_w) if force_w else np.zeros((0, 2), int)
        if len(fw) and np.any(long_gap):
            cg = filters.running_count(long_gap)
            fw = fw[cg[fw[:, 1] + self.h + 1] - cg[fw[:, 0] - self.h] == 0]
        self.force = Windows(fw, t[fw[:, 0]] if len(fw) else np.zeros(0), t[fw[:, 1]] if len(fw) else np.zeros(0))
        # projector removing a cubic in time from each flow window (same for every window)
        tau = np.linspace(-1.0, 1.0, self.L1)
        basis = np.vander(tau, 4, increasing=True)
        q, _ = np.linalg.qr(basis)
        self.P = np.eye(self.L1) - q @ q.T
        self._Amid = 0.5 * (self.A[1:] + self.A[:-1])
        self._dt = np.diff(t)
        self._first = np.zeros(n, dtype=bool)
        self._seg_t0 = np.zeros(n)
        self._seg_last = np.zeros(n, dtype=int)
        for a, b in data.segments():
            self._first[a] = True
            self._seg_t0[a:b] = t[a]
            self._seg_last[a:b] = b - 1
        self._set_flow_windows(fwin)
        self._vel_cache = _Cache(4)
        self._trans_integrals = _Cache(3)
        self._form_drag_cache = _Cache()
        self._wind_cache = _Cache(4)
        self._phi_cache = _Cache(3)
        if v_acc is not None:
            # the accelerometer's velocity, its bias removed against the flow's odometry under the
            # nominal geometry (``accel_bias_removed``), joins the tilt's in the flow channels
            X, _ = self.flow_velocity(NOMINAL)
            for a, b in data.segments():
                for i in (0, 1):
                    self.V[i, a:b] += accel_bias_removed(v_acc[i, a:b], self.V[i, a:b], X[i, a:b], t[a:b])
        self._dPhi = np.zeros_like(self.Phi)
        for a, b in data.segments():
            if b - a > 1:
                self._dPhi[:, a:b] = np.gradient(self.Phi[:, a:b], t[a:b], axis=1)
        # boundary indices and spans of the force channel
        F = self.force.idx
        self._k0, self._k1 = F[:, 0], F[:, 1]
        h = self.h
        self._span = t[self._k1] - t[self._k0]
        self._den0 = t[self._k0 + h] - t[self._k0 - h]
        self._den1 = t[self._k1 + h] - t[self._k1 - h]
        self._dv_tilt = self._window_means(self.D)
        self._rot_basis: np.ndarray | None = None  # ``_odometry_changes`` of R and RA (on first use)
        self._phi_basis_cache = _Cache(4)
        self._native_args: dict[str, np.ndarray] | None = None  # the compiled kernels' (``_native``)
        #: constant residual offsets set by ``anchor`` (None: this problem's own nominal residual)
        self._flow_offset: np.ndarray | None = None
        self._force_offset: np.ndarray | None = None
        #: the inertial rows' constants (``_inertial_constants``, made on first use)
        self._inertial: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def _inertial_constants(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The inertial rows' constants (``inertial_residual``), made on first use: the force
        windows whose frames, boundary averages included, all have an accelerometer reading
        (indices into ``force.idx``); per such window the velocity change the accelerometer gives
        (m/s, (2, n)): its specific force (body FRD) turned level by the recorded attitude, a
        strapdown integration that needs no model of the thrust (``level_acceleration``); the
        blocks of at most ``INERTIAL_BIAS_BLOCK_S`` within a segment that each take a bias of
        their own; and which of the windows are the rows (``INERTIAL_ACTIVE_TIMES_NOISE``). Empty
        without an accelerometer, or with the (0, 0, -1 g) placeholder a vehicle without one sends."""
        if self._inertial is not None:
            return self._inertial
        empty = (np.zeros(0, dtype=int), np.zeros((2, 0)), np.zeros(0, dtype=int), np.zeros(0, dtype=bool))
        self._inertial = empty
        data = self.data
        fx, fy, fz = data.accel_x_m_s2, data.accel_y_m_s2, data.accel_z_m_s2
        F = self.force.idx
        if fx is None or fy is None or fz is None or len(F) == 0:
            return empty
        with np.errstate(invalid="ignore"):
            if not np.any((fx != 0.0) | (fy != 0.0)):  # the placeholder, or nothing finite
                return empty
        acc = level_acceleration(fx, fy, fz, data.pitch_rad, data.roll_rad)
        cb = filters.running_count(~np.all(np.isfinite(acc), axis=0))
        h = self.h
        valid = np.flatnonzero(cb[F[:, 1] + h + 1] - cb[F[:, 0] - h] == 0)
        if len(valid) == 0:
            return empty
        dv = self._window_means(self._cum(self._cum(np.nan_to_num(acc))))[:, valid]
        seg = np.searchsorted([b for _a, b in data.segments()], F[valid, 0], side="right")
        t0 = self.t[F[valid, 0]]
        first = {k: float(t0[seg == k].min()) for k in np.unique(seg)}
        block = np.floor((t0 - np.array([first[k] for k in seg])) / INERTIAL_BIAS_BLOCK_S).astype(int)
        blocks = np.unique(np.stack([seg, block], axis=1), axis=0, return_inverse=True)[1].ravel()
        # the rows: windows whose acceleration stands clear of the rows' noise (the nominal
        # residual's robust scale, per axis): in a hover the motion is largely the loop's answer
        # to the flow's own noise, which the residual holds too
        noise = np.array([robust_std(x) for x in self._inertial_errors(NOMINAL, valid, dv, blocks)])
        a = np.abs(dv) / self._span[valid]
        self._inertial = (valid, dv, blocks, np.any(a >= INERTIAL_ACTIVE_TIMES_NOISE * noise[:, None], axis=0))
        return self._inertial

    @property
    def inertial_rows(self) -> np.ndarray:
        """The force windows (indices into ``force.idx``) that are the inertial rows."""
        valid, _dv, _blocks, active = self._inertial_constants()
        return valid[active]

    def inertial_residual(self, p: np.ndarray) -> np.ndarray:
        """``inertial_x``, ``inertial_y`` (m/s^2), shape (2, n_rows): over each force window with an
        accelerometer reading throughout whose acceleration stands clear of the noise
        (``inertial_rows``), the mean acceleration of the flow's odometry under p's sensor geometry
        minus the one the accelerometer's levelled specific force gives, less its mean over each
        bias block (``INERTIAL_BIAS_BLOCK_S``, over every window with an accelerometer).

        Why: the accelerometer measures every horizontal force the tilt does not give (drag, wind,
        turbulence), so this residual holds none of them: what is left is how the flow's velocity
        is read (scale, range offset, turn, delay, lever arm), with the accelerometer's noise. The
        fit does not use it: it is the flow group's independent check (``accelerometer_z``). A
        constant accelerometer bias is a constant here, taken out per block.

        Why only the windows that accelerate: in a hover the vehicle's motion is mostly the loop's
        answer to the flow's own noise (a count that flips moves the velocity, the command, the
        tilt and then the vehicle), so a window's velocity change is correlated with the flow noise
        at its start, which is the residual's. A window whose acceleration stands
        ``INERTIAL_ACTIVE_TIMES_NOISE`` x the noise above it moves by the setpoints or the air."""
        valid, dv_acc, blocks, active = self._inertial_constants()
        if len(valid) == 0:
            return np.zeros((2, 0))
        return self._inertial_errors(p, valid, dv_acc, blocks)[:, active]

    def _inertial_errors(self, p: np.ndarray, valid: np.ndarray, dv_acc: np.ndarray, blocks: np.ndarray) -> np.ndarray:
        """``inertial_residual`` over every window with an accelerometer (``valid``), before the
        active ones are picked: the odometry's mean acceleration minus the accelerometer's
        (``dv_acc``), less its mean per bias block."""
        dv, _dx = self._odometry_window_changes(p)
        e = (dv[:, valid] - dv_acc) / self._span[valid]
        nb = int(blocks.max()) + 1
        count = np.bincount(blocks, minlength=nb)
        means = np.stack([np.bincount(blocks, weights=row, minlength=nb) / count for row in e])
        return e - means[:, blocks]

    def _set_flow_windows(self, W: np.ndarray, U: np.ndarray | None = None) -> None:
        """The flow channels' windows W (n_windows, L1) of frame indices, and their constants;
        ``U``: their start-velocity directions when known (each window's is its own), else made."""
        t = self.t
        self.flow = Windows(W, t[W[:, 0]] if len(W) else np.zeros(0), t[W[:, -1]] if len(W) else np.zeros(0))
        seg_of = np.searchsorted([b for _a, b in self.data.segments()], W[:, 0], side="right") if len(W) \
            else np.zeros(0, int)
        self._seg_windows = [(int(np.searchsorted(seg_of, i)), int(np.searchsorted(seg_of, i, side="right")))
                             for i in range(len(self.data.segments()))]
        self._Phiw = self.Phi[:, W]
        #: per window, the increments into frames whose flow was lost (bridged), and the recorded
        #: increments either side of each that the flow residual takes its step from there
        #: (``flow_residual``)
        self._lost = _bridge_plan(~self.data.flow_rec[W][:, 1:] if len(W) else np.zeros((0, self.L1 - 1), dtype=bool))
        self._U = self._start_velocity_directions(W) if U is None else U
        self._Rw = self.R[:, W]  # constant gathers of every flow-residual evaluation
        self._RAw = self.RA[:, W]
        self._trans_cache = _Cache()
        self._forget_projections()
        self._shift_cache = _Cache(4)

    def _forget_projections(self) -> None:
        """Empty the ``_projected`` pieces of the flow residual: the scene angle and the lever-arm
        rotation (made once), the rotation per delay, the translation per (offset, delay). They hold
        the windows' nuisance (``_U``), so they go whenever it changes."""
        self._proj_fixed: tuple[np.ndarray, np.ndarray] | None = None
        self._proj_rot = _Cache(4)
        self._proj_trans = _Cache()

    def _start_velocity_directions(self, W: np.ndarray) -> np.ndarray:
        """(n_windows, L1): per flow window, the unit direction of what its unknown start velocity
        v0 adds to the scene angle, v0 times the integral of 1 / A from the window's start, with the
        cubic removed (``project_windows``); zero where the range is constant enough over the window
        for the cubic to hold it all, and where the window's speed (the flow's odometry under the
        nominal geometry) times that direction's rms stays under the flow's resolution (a count's
        rounding: what the cubic then misses is below what the sensor resolves, and the window keeps
        the freedom; removed everywhere, it took enough of a 0.05 m range offset's evidence on the
        issue's old matrix, range_offset-a, for a flow scale and a rotation gain to be named instead).

        Why: the cubic holds v0's translation only while the height A is constant over the window.
        A vehicle that pitches 17 deg either way at 1 m reads a slant range that swings 1.01-1.08 m
        twice a manoeuvre, and v0 times that swing's integral is left in the residual: on a
        noise-free generator flight (seed 1000171, a 0.5 Hz sine at 1 m) 92 % of its flow residual,
        fitted as a range offset of +0.10 m, a flow scale of 0.97 or a rotation gain of 1.02."""
        if len(W) == 0:
            return np.zeros((0, self.L1))
        cum = self._cum(1.0 / self.A)  # windows lie within a segment
        integral = cum[W] - cum[W[:, :1]]
        u = integral @ self.P
        size = np.linalg.norm(u, axis=1)
        whole = np.linalg.norm(integral, axis=1)
        ok = np.isfinite(size) & (size > START_VELOCITY_MIN_SHARE * whole)
        # where the window's speed times that direction stays under the flow's own rounding, the
        # cubic's error is below what the sensor resolves: left to the cubic (no freedom lost)
        X, _ = self._flow_velocity_uncached(NOMINAL)  # the windows are being set: no cache yet
        v = np.hypot(*(X[:, W[:, -1]] - X[:, W[:, 0]])) / np.maximum(self.t[W[:, -1]] - self.t[W[:, 0]], 1e-9)
        ok &= v * size / math.sqrt(self.L1) >= self.data.flow_resolution_rad
        return np.where(ok[:, None], u / np.where(ok, size, 1.0)[:, None], 0.0)

    def project_windows(self, z: np.ndarray) -> np.ndarray:
        """A flow-window signal z (..., n_windows, L1) with each window's cubic in time and its
        start velocity's translation (``_start_velocity_directions``) removed: the nuisance the
        flow residual does not model (both are linear in z)."""
        zp = z @ self.P
        return zp - np.sum(zp * self._U, axis=-1, keepdims=True) * self._U

    def keep_flow_windows(self, keep: np.ndarray) -> None:
        """Leave the flow windows where not ``keep`` ((n_windows,) bool) out of the flow channels
        (e.g. ``groups.quiet_windows``'s): the kept windows' residuals are as before (to the last
        bits of a matrix product over fewer rows), and no evaluation spends time on the others.
        Before ``anchor``."""
        if self._flow_offset is not None:
            raise ValueError("keep_flow_windows: an anchored problem's windows are fixed")
        self._set_flow_windows(self.flow.idx[keep], self._U[keep])

    def anchor(self, base: FlowProblem, p_anchor: np.ndarray | None = None) -> None:
        """Take the residual at ``p_anchor`` (the nominal when None) from ``base`` (the same flight,
        its rotation from another source) and only the change with the parameters from this problem:

            r(p) = r_base(p_anchor) + [r_self(p) - r_self(p_anchor)]

        Why: the residual compared with the rotation of a noisy source holds that source's noise,
        and so does every regressor (rotation gain, delay, lever arm, scale) built from the same
        source: errors in variables, which a least-squares fit reads as a rotation gain below 1, a
        delay, a scale, however many held-out folds confirm it (they share the noise too). With the
        regressors from a source whose noise is independent of the residual's, noise cannot make an
        effect; a real one still shows (both sources see the true rotation). At the anchor
        nothing changes; away from it the change is exact to first order, so the anchor is moved to
        the chosen model once one is found (``groups.flow_group``)."""
        if base.flow.idx.shape != self.flow.idx.shape or base.force.idx.shape != self.force.idx.shape:
            raise ValueError("anchor: the two problems must share their windows")
        p_a = NOMINAL if p_anchor is None else p_anchor
        self._flow_offset = None
        self._force_offset = None
        # the windows' nuisance is the base's: which windows take the start velocity's direction
        # depends on the flow's speed there, and this problem's scene angle may be another's (the
        # regressors' synthetic one); the residual and its change with p must lose the same part
        self._U = base._U
        self._forget_projections()
        self._flow_offset = base.flow_residual(p_a) - self.flow_residual(p_a)
        self._force_offset = base.force_residual(p_a) - self.force_residual(p_a)

    # -- model pieces --------------------------------------------------------------------------

    def window_rotation(self) -> np.ndarray:
        """The rotation R over each flow window with the window's nuisance removed
        (``project_windows``), as the flow residual sees it: (2, n_windows, L1), rad."""
        return self.project_windows(self._Rw)

    def _rotation_at(self, delay_s: float) -> np.ndarray:
        """R(t - delay) at the flow windows' frames, (2, n_windows, L1): cubic spline through the
        recorded attitude of each segment (held at the segment's ends)."""
        if delay_s == 0.0:
            return self._Rw
        W = self.flow.idx
        out = np.empty((2,) + W.shape)
        for (a, b, sp), (w0, w1) in zip(self._splines, self._seg_windows, strict=True):
            if w1 > w0:
                tq = np.clip(self.t[W[w0:w1]] - delay_s, self.t[a], self.t[b - 1])
                out[:, w0:w1] = np.moveaxis(sp(tq), -1, 0)
        return out

    def _shifted(self, y: np.ndarray, dy: np.ndarray, delay_s: float, idx: np.ndarray | None = None) -> np.ndarray:
        """y(t - delay) at frames ``idx`` (all frames when None) by cubic Hermite interpolation
        between frames from values y and derivatives dy (shape (..., n)), held at each segment's
        ends."""
        if delay_s == 0.0:
            return y[..., np.arange(len(self.t)) if idx is None else idx]
        if idx is None and y.ndim == 2 and len(self.t) >= 2:
            lib = native.kernels()
            if lib is not None:  # the compiled copy (``fh_hermite_shift``, tests/test_native.py)
                a = self._native()
                y = np.ascontiguousarray(y, dtype=float)
                dy = np.ascontiguousarray(dy, dtype=float)
                out = np.empty_like(y)
                lib.fh_hermite_shift(a["t"].ctypes.data, len(self.t), a["seg_t0"].ctypes.data,
                                     a["seg_last"].ctypes.data, y.ctypes.data, dy.ctypes.data, y.shape[0],
                                     float(delay_s), out.ctypes.data)
                return out
        # the frames and weights depend on the delay and the frames only, not on y: kept for
        # the next signal shifted alike (a translation shifts two, a Jacobian repeats delays)
        if idx is None or idx is self.flow.idx:
            j, w00, w10, w01, w11 = self._shift_cache.get((float(delay_s), float(idx is None)),
                                                          lambda: self._shift_plan(delay_s, idx))
        else:
            j, w00, w10, w01, w11 = self._shift_plan(delay_s, idx)
        return w00 * y[..., j] + w10 * dy[..., j] + w01 * y[..., j + 1] + w11 * dy[..., j + 1]

    def _shift_plan(self, delay_s: float, idx: np.ndarray | None) -> tuple[np.ndarray, ...]:
        """``_shifted``'s frames j and Hermite weights (of y[j], dy[j], y[j + 1], dy[j + 1])."""
        t = self.t
        k = np.arange(len(t)) if idx is None else idx
        tq = np.clip(t[k] - delay_s, self._seg_t0[k], t[self._seg_last[k]])
        j = np.clip(native.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)  # np.searchsorted, compiled
        j = np.minimum(j, np.maximum(self._seg_last[k] - 1, 0))
        h = t[j + 1] - t[j]
        u = np.clip((tq - t[j]) / h, 0.0, 1.0)
        h00 = (1 + 2 * u) * (1 - u) ** 2
        h10 = u * (1 - u) ** 2
        h01 = u * u * (3 - 2 * u)
        h11 = u * u * (u - 1)
        return j, h00, h10 * h, h01, h11 * h

    def model_translation(self, offset: float, delay_s: float = 0.0, power: int = 1) -> np.ndarray:
        """The plant's translational scene angle in each flow window, delayed by ``delay_s``:
        integral of (V(tau) - V(t_start)) / (A(tau) - offset)^power over [t_start, t - delay],
        up to a constant per window; shape (2, n_windows, L1). V is the velocity the recorded tilt
        gives (the window's unknown start velocity and a constant force are the cubic's job)."""
        return self._trans_cache.get((float(offset), float(delay_s), float(power)),
                                     lambda: self._translation_uncached(offset, delay_s, power))

    def _translation_uncached(self, offset: float, delay_s: float, power: int) -> np.ndarray:
        W = self.flow.idx
        f, F = self._trans_integrals.get((float(offset), float(power)),
                                         lambda: self._translation_integrals(offset, power))
        I = self._shifted(F, f, delay_s, W)
        return I[:2] - self.V[:, W][:, :, :1] * I[2]

    def _translation_integrals(self, offset: float, power: int) -> tuple[np.ndarray, np.ndarray]:
        """``model_translation``'s integrands V / (A - offset)^power (two rows) and 1 / (A -
        offset)^power, stacked (3, n), and their integrals (``_cum``): per offset, not per delay,
        which only shifts them (a Jacobian's delay column, a fit of the delay alone)."""
        ainv = 1.0 / (self.A - offset) ** power
        f = np.concatenate([self.V * ainv, ainv[None]])
        return f, self._cum(f)

    def _cum(self, f: np.ndarray) -> np.ndarray:
        """Trapezoidal integral of f over time, restarting at each segment (constant offsets are
        irrelevant: every use is within one segment)."""
        inc = 0.5 * (f[..., 1:] + f[..., :-1]) * self._dt
        inc[..., self._first[1:]] = 0.0
        out = np.zeros_like(f)
        out[..., 1:] = np.cumsum(inc, axis=-1)
        return out

    def flow_residual(self, p: np.ndarray) -> np.ndarray:
        """``flow_x``, ``flow_y`` window residuals (rad), shape (2, n_windows, L1), each window's
        nuisance removed (``project_windows``)."""
        W = self.flow.idx
        if len(W) == 0:
            return np.zeros((2, 0, self.L1))
        kx, ky, yaw, delay, offset = p[0], p[1], p[2], p[3], p[4]
        # the residual is linear in the scene angle, the rotation and the translation, and so are
        # the bridging of lost frames and the cubic's removal (``_projected``): each piece is
        # projected once and combined for any geometry
        if self._proj_fixed is None:
            self._proj_fixed = (self._projected(self._Phiw), self._projected(self._RAw))
        phi, ra = self._proj_fixed
        rot = self._proj_rot.get((float(delay),), lambda: self._projected(self._rotation_at(delay)))
        trans = self._proj_trans.get((float(offset), float(delay)),
                                     lambda: self._projected(self.model_translation(offset, delay)))
        body = p[8] * rot + p[10] * ra - trans
        c, s = math.cos(yaw), math.sin(yaw)
        e = np.empty_like(phi)
        e[0] = phi[0] - (c * body[0] + s * body[1]) / kx
        e[1] = phi[1] - (-s * body[0] + c * body[1]) / ky
        return e if self._flow_offset is None else e + self._flow_offset

    def _projected(self, z: np.ndarray) -> np.ndarray:
        """A flow-window signal z (2, n_windows, L1) as the flow residual takes it: its steps into
        lost frames bridged, then the window's nuisance removed (``project_windows``). Both are
        linear in z."""
        if self._lost is not None:
            # a lost frame's increment was bridged from the attitude's rotation (no delay, no
            # gain, no scale) and the neighbours' translation: the extraction's guess, not a
            # measurement, which would pull a delay, a gain or a scale towards the nominal model.
            # The residual's step over it is interpolated from the recorded steps either side
            # (the residual is smooth: the translation the cubic removes, and what the effects add)
            w, j, jl, jr, al = self._lost
            inc = np.diff(z, axis=-1)
            inc[:, w, j] = al * inc[:, w, jl] + (1.0 - al) * inc[:, w, jr]
            z = np.concatenate([z[..., :1], z[..., :1] + np.cumsum(inc, axis=-1)], axis=-1)
        return self.project_windows(z)

    def flow_velocity(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Odometry from the flow under the model's sensor geometry: X (2, n) in m (per segment,
        from 0) and Y (2, n) the translational scene angle integral(v/A) in rad."""
        return self._vel_cache.get(_geometry_key(p), lambda: self._flow_velocity_uncached(p))

    def _phi_at(self, delay_s: float) -> np.ndarray:
        """The recorded scene angle at t + delay (2, n): cubic Hermite with the frames' mean rates."""
        if delay_s == 0.0:
            return self.Phi
        return self._phi_cache.get((float(delay_s),), lambda: self._shifted(self.Phi, self._dPhi, -delay_s))

    def _flow_velocity_uncached(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kx, ky, yaw, delay, offset = p[0], p[1], p[2], p[3], p[4]
        phi = self._phi_at(delay)
        sx, sy = kx * phi[0], ky * phi[1]
        c, s = math.cos(yaw), math.sin(yaw)
        bx = c * sx - s * sy
        by = s * sx + c * sy
        Y = p[8] * self.R + p[10] * self.RA - np.stack([bx, by])
        X = np.zeros_like(Y)
        inc = (self._Amid - offset) * np.diff(Y, axis=1)
        inc[:, self._first[1:]] = 0.0  # no increment across a gap
        X[:, 1:] = np.cumsum(inc, axis=1)
        return X, Y

    def _odometry_changes(self, S: np.ndarray) -> np.ndarray:
        """The force channel's pieces of the odometry that the scene-angle signals S (k, n) alone
        give, per unit of range and per metre of range offset: (2 [dv, dx], 2 [A, 1], k, n_windows).
        The odometry X = cumsum((A_mid - offset) diff(Y)) (``flow_velocity``) is linear in Y and in
        the offset, and Y in the rotation and the sensor's rotated, scaled flow, so are the windows'
        changes of X and of its integral: ``_odometry_window_changes`` combines these for any
        geometry without touching a frame."""
        lib = native.kernels()
        if lib is not None and S.ndim == 2 and S.shape[1] >= 2 and len(self._k0):
            # the compiled copy (``fh_odometry_changes``, tests/test_native.py holds the two equal):
            # no whole-flight arrays
            a = self._native()
            S = np.ascontiguousarray(S, dtype=float)
            out = np.empty((2, 2, S.shape[0], len(self._k0)))
            scratch = np.empty(2 * S.shape[1])
            lib.fh_odometry_changes(S.ctypes.data, S.shape[0], S.shape[1], a["first"].ctypes.data,
                                    a["amid"].ctypes.data, a["dt"].ctypes.data, a["k0"].ctypes.data,
                                    a["k1"].ctypes.data, a["den0"].ctypes.data, a["den1"].ctypes.data, len(self._k0),
                                    self.h, scratch.ctypes.data, out.ctypes.data)
            return out
        d = np.diff(S, axis=-1)
        d[..., self._first[1:]] = 0.0  # no increment across a gap
        out = np.empty((2, 2) + S.shape[:-1] + (len(self._k0),))
        for j, inc in enumerate((self._Amid * d, d)):
            X = np.zeros(S.shape)
            X[..., 1:] = np.cumsum(inc, axis=-1)
            out[0, j] = self._window_means(X)
            out[1, j] = self._window_means(self._integral(X))
        return out

    def _native(self) -> dict[str, np.ndarray]:
        """This problem's constant arrays as the compiled kernels take them (made once)."""
        if self._native_args is None:
            c = np.ascontiguousarray
            self._native_args = {"t": c(self.t, dtype=float), "seg_t0": c(self._seg_t0, dtype=float),
                                 "seg_last": c(self._seg_last, dtype=np.int64), "first": c(self._first, dtype=np.uint8),
                                 "amid": c(self._Amid, dtype=float), "dt": c(self._dt, dtype=float),
                                 "k0": c(self._k0, dtype=np.int64), "k1": c(self._k1, dtype=np.int64),
                                 "den0": c(self._den0, dtype=float), "den1": c(self._den1, dtype=float)}
            seg = np.array(self.data.segments(), dtype=np.int64).reshape(-1, 2)
            self._native_args["seg_starts"] = c(seg[:, 0])
            self._native_args["seg_stops"] = c(seg[:, 1])
        return self._native_args

    def _odometry_window_changes(self, p: np.ndarray) -> np.ndarray:
        """``dv`` and ``dx`` of ``force_parts`` under p's sensor geometry: the windows' change of the
        odometry ``flow_velocity`` gives (m/s) and of its integral (m), (2 [dv, dx], 2 axes, n_windows),
        combined from ``_odometry_changes`` of R, RA (once) and the scene angle (per delay)."""
        kx, ky, yaw, delay, offset, gain, rz = p[0], p[1], p[2], p[3], p[4], p[8], p[10]
        if self._rot_basis is None:
            self._rot_basis = self._odometry_changes(np.concatenate([self.R, self.RA]))
        rb = self._rot_basis
        fb = self._phi_basis_cache.get((float(delay),), lambda: self._odometry_changes(self._phi_at(delay)))
        m = rb[:, 0] - offset * rb[:, 1]  # (2, 4 [R_x, R_y, RA_x, RA_y], n_windows)
        f = fb[:, 0] - offset * fb[:, 1]  # (2, 2 [phi_x, phi_y], n_windows)
        c, s = math.cos(yaw), math.sin(yaw)
        # Y_x = gain R_x + rz RA_x - (c kx phi_x - s ky phi_y), Y_y = gain R_y + rz RA_y - (s kx phi_x + c ky phi_y)
        x = gain * m[:, 0] + rz * m[:, 2] - (c * kx) * f[:, 0] + (s * ky) * f[:, 1]
        y = gain * m[:, 1] + rz * m[:, 3] - (s * kx) * f[:, 0] - (c * ky) * f[:, 1]
        return np.stack([x, y], axis=1)

    def force_parts(self, p: np.ndarray, start_s: float = math.nan, end_s: float = math.nan, *,
                    with_dq: bool = True) -> dict[str, np.ndarray]:
        """Boundary-averaged pieces of the force balance (each (2, n_windows), m/s per window):
        ``dv`` flow velocity change, ``dv_tilt`` what the tilt explains, ``dx`` the window's
        averaged displacement change (drag regressor, m), ``dq`` the form-drag regressor (absent
        when ``with_dq`` is False: the costliest piece, and a residual without form drag does not
        need it), ``dt1`` the wind regressor (s)."""
        dv, dx = self._odometry_window_changes(p)
        parts = {
            "dv": dv,
            "dv_tilt": self._dv_tilt,
            "dx": dx,
            # per wind window, not per parameter vector: a fit moves the window seldom
            "dt1": self._wind_cache.get((float(start_s), float(end_s)), lambda: self._wind_regressor(start_s, end_s)),
            "span_s": self._span,
        }
        if with_dq:
            parts["dq"] = self._form_drag_cache.get(_geometry_key(p),
                                                    lambda: _FormDrag(self, self.flow_velocity(p)[0])).dq()
        return parts

    def _wind_regressor(self, start_s: float, end_s: float) -> np.ndarray:
        """``force_parts``'s ``dt1`` (read-only, (2, n_windows)): each force window's change of the
        boundary means of a unit force's double integral over [start_s, end_s)."""
        k0, k1, d0, d1 = self._k0, self._k1, self._den0, self._den1
        h = self.h
        t = self.t

        def ravg(k: np.ndarray, den: np.ndarray) -> np.ndarray:
            return (ramp_integral(t[k + h], start_s, end_s) - ramp_integral(t[k - h], start_s, end_s)) / den

        out = np.broadcast_to(ravg(k1, d1) - ravg(k0, d0), (2, len(k0))).copy()
        out.flags.writeable = False
        return out

    def _bavg(self, Z: np.ndarray, k: np.ndarray, den: np.ndarray) -> np.ndarray:
        """Mean of the derivative of Z over [t_k-h, t_k+h]: (Z(k+h) - Z(k-h)) / span."""
        return (Z[..., k + self.h] - Z[..., k - self.h]) / den

    def _window_means(self, Z: np.ndarray) -> np.ndarray:
        """Each force window's change of Z's boundary means: _bavg at its end minus at its start."""
        return self._bavg(Z, self._k1, self._den1) - self._bavg(Z, self._k0, self._den0)

    def _integral(self, Z: np.ndarray) -> np.ndarray:
        """Trapezoidal integral of Z over time along the last axis, through the gaps between
        segments (every use takes differences within one segment)."""
        out = np.zeros_like(Z)
        out[..., 1:] = np.cumsum(0.5 * (Z[..., 1:] + Z[..., :-1]) * self._dt, axis=-1)
        return out

    def force_residual(self, p: np.ndarray, start_s: float = math.nan, end_s: float = math.nan) -> np.ndarray:
        """``force_x``, ``force_y`` (N), shape (2, n_windows): the mean force over each window the
        model leaves unexplained."""
        if len(self.force.idx) == 0:
            return np.zeros((2, 0))
        m = self.mass_kg
        f = self.force_parts(p, start_s, end_s, with_dq=p[9] != 0.0)
        e = f["dv"] - f["dv_tilt"] + (p[5] / m) * f["dx"]
        if p[9] != 0.0:  # 0 * dq adds nothing: dq is finite (the odometry is)
            e = e + (p[9] / m) * f["dq"]
        e = e - (np.array([[p[6]], [p[7]]]) / m) * f["dt1"]
        e = e * m / f["span_s"]
        return e if self._force_offset is None else e + self._force_offset
