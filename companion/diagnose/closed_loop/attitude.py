"""The attitude-loop channel: the recorded attitude against the model's response to the recorded command.

Per axis (roll, pitch) the paper's attitude loop is the second-order response (eq. 26)

    angle'' = Omega_p^2 (u - angle) - 2 zeta Omega_p angle'

to the command u, held over each frame (the command computed at frame k acts over
[t_k+1, t_k+2], CONVENTIONS.md; ``channels.extract`` already aligns it). Discretised exactly
(zero-order hold), the response of a whole segment to the recorded commands is one linear
filter (``scipy.signal.lfilter``'s rule: ``companion.diagnose.filters``) started from the recorded
attitude and rate at the segment's first frame: an output-error simulation, linear-time, that
never sees the velocity loop, so the closed loop cannot hide an attitude-loop mismatch. A constant
per-axis offset (a level trim of the attitude estimate) is removed as a nuisance in every model.

``attitude_roll``, ``attitude_pitch`` (rad): recorded minus simulated attitude.
Parameters: ``omega_p`` rad/s, ``zeta`` (effect ``attitude_dynamics``) and ``delay`` s (effect
``attitude_delay``: the loop responds this much later than the model's one-frame latency;
negative = earlier).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion import native
from companion.diagnose import filters
from companion.diagnose.closed_loop.channels import FlightData
from companion.diagnose.closed_loop.select import robust_std

#: the attitude loop's natural frequency at most (rad/s): at 50 Hz frames a loop this fast follows
#: a command within about a frame (rise time 1.8 / omega_p = 22 ms), and every faster one looks
#: the same; a fit there (``Candidate.resolution_upper``) says the recorded command is followed
#: as fast as the frames show, as an autopilot's own attitude target (after its input shaping) is
OMEGA_P_MAX_RAD_S = 80.0
#: ``OMEGA_P_MAX_RAD_S`` x the frame period at least this much (the rise time ~1.8 / omega_p within
#: about a frame) makes that bound the frames' resolution rather than a limit of the model
OMEGA_P_RESOLVED_T = 1.2


#: a run of lost (bridged) commands restarts the attitude simulation from the recorded attitude
#: when this flight says a restart carries less error than simulating on across the bridge
#: (``restart_choice``), and always when the command jumps across it by more than
#: ``RESTART_JUMP_RAD`` (a setpoint step: interpolation cannot know where the jump fell) or it is
#: longer than ``RESTART_DECIDE_MAX_S``
RESTART_JUMP_RAD = 0.02
RESTART_DECIDE_MAX_S = 0.5
#: stretches of recorded commands sampled per run length to measure the bridge's error (at most),
#: and the fewest that decide (fewer: that length restarts, as does every length without a gyro)
RESTART_SAMPLES_MAX = 2000
RESTART_SAMPLES_MIN = 30
#: the loop's responses are taken over this many time constants of its slower pole
RESTART_RESPONSE_DECAYS = 10.0
#: the free response of an initial rate is fitted over this many time constants of its slower pole
#: (e^-45: it is 0 to double precision past them)
FREE_RESPONSE_DECAYS = 45.0
#: a segment's start rate is fitted only when its fitted frames hold more than this share of the
#: free response's energy over the segment (less is rounding: the response is 0 at the start)
FREE_FIT_MIN_SHARE = 1e-12


def discretise(omega_p: float, zeta: float, T: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of the attitude loop: (Ad, Bd, b, a) with
    x = [angle, rate], the transfer function b(z)/a(z) from command to angle.

    Ad = exp(A T) by Sylvester's formula on the two poles (complex when zeta < 1),
    Bd = A^-1 (Ad - I) B; ``expm_discretise`` is the same by ``scipy.linalg.expm``."""
    w = omega_p
    A = np.array([[0.0, 1.0], [-w * w, -2.0 * zeta * w]])
    B = np.array([0.0, w * w])
    root = np.sqrt(complex(zeta * zeta - 1.0))
    l1, l2 = w * (-zeta + root), w * (-zeta - root)
    e1, e2 = np.exp(l1 * T), np.exp(l2 * T)
    if abs(l1 - l2) > 1e-9 * w:
        c0 = (l1 * e2 - l2 * e1) / (l1 - l2)
        c1 = (e1 - e2) / (l1 - l2)
    else:  # critically damped: the limit of the formula
        c0 = e1 * (1.0 - l1 * T)
        c1 = e1 * T
    Ad = (c0.real * np.eye(2) + c1.real * A)
    Bd = np.linalg.solve(A, (Ad - np.eye(2)) @ B)
    return Ad, Bd, *_transfer(Ad, Bd)


def expm_discretise(omega_p: float, zeta: float, T: float) -> tuple[np.ndarray, np.ndarray]:
    """(Ad, Bd) by the matrix exponential of the augmented system (reference for tests)."""
    from scipy import linalg  # only here: the diagnosis itself does not load scipy.linalg

    w = omega_p
    M = np.zeros((3, 3))
    M[:2, :2] = np.array([[0.0, 1.0], [-w * w, -2.0 * zeta * w]]) * T
    M[1, 2] = w * w * T
    E = linalg.expm(M)
    return E[:2, :2], E[:2, 2]


def _transfer(Ad: np.ndarray, Bd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """y_k = C x_k, C = [1, 0]:  a(z) = det(zI - Ad), b(z) = C adj(zI - Ad) Bd."""
    a1 = -(Ad[0, 0] + Ad[1, 1])
    a2 = Ad[0, 0] * Ad[1, 1] - Ad[0, 1] * Ad[1, 0]
    b1 = Bd[0]
    b2 = Ad[0, 1] * Bd[1] - Ad[1, 1] * Bd[0]
    return np.array([0.0, b1, b2]), np.array([1.0, a1, a2])


def _held_shift(x: np.ndarray, m: int) -> np.ndarray:
    """x[:, clip(k - m, 0, len - 1)] for every column k (x shifted on by m columns, held at its
    ends), by slices."""
    n = x.shape[1]
    if m >= n or -m >= n:
        return np.repeat(x[:, :1] if m > 0 else x[:, -1:], n, axis=1)
    if m >= 0:
        return np.concatenate([np.repeat(x[:, :1], m, axis=1), x[:, :n - m]], axis=1)
    return np.concatenate([x[:, -m:], np.repeat(x[:, -1:], -m, axis=1)], axis=1)


def masked_row_means(e: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Each row's mean over its finite values at the frames of ``mask``, (rows, 1): the same
    numbers as ``np.where(ok, x, 0.0).sum(axis=1, keepdims=True) / np.maximum(n, 1)`` on
    ``x = e[:, mask]``, ``ok = np.isfinite(x)``, ``n = ok.sum(axis=1, keepdims=True)``
    (tests/test_diagnose.py holds the two equal), in a quarter of the time on a long flight.

    Why not that: numpy lays ``e[:, mask]`` out column-major, and summing its rows strides through
    it a column at a time, in frame order (0.45 ms each for the two rows of a 15-minute fit; the
    attitude fit computes hundreds of residuals). Here each row is gathered contiguous and summed in
    the same order, by a running sum (``np.cumsum``: a contiguous row's ``sum`` adds pairwise,
    which would change the mean in its last bits)."""
    out = np.zeros((e.shape[0], 1))
    for i in range(e.shape[0]):
        x = e[i][mask]
        ok = np.isfinite(x)
        if len(x):
            out[i, 0] = np.cumsum(np.where(ok, x, 0.0))[-1] / max(np.count_nonzero(ok), 1)
    return out


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The runs of True in ``mask``: their first indices and the indices just past them."""
    x = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    return np.flatnonzero(x == 1), np.flatnonzero(x == -1)


def _pulse_responses(omega_p: float, zeta: float, T: float, L: int) -> tuple[np.ndarray, np.ndarray]:
    """The loop's angle over L frames (zero-order hold, exact): (its answer to a command of 1
    over the first frame only, its free response to a start angle of 1 at no rate)."""
    Ad, Bd, _b, _a = discretise(omega_p, zeta, T)
    r, g = np.zeros(L), np.zeros(L)
    x = Bd.copy()  # the state after the pulse's frame
    xg = np.array([1.0, 0.0])
    for k in range(L):
        g[k] = xg[0]
        xg = Ad @ xg
        if k + 1 < L:
            r[k + 1] = x[0]
            x = Ad @ x
    return r, g


@dataclass(frozen=True)
class RestartChoice:
    """Per run length m of lost commands (index m), whether the attitude simulation restarts
    after it (``restart``); the attitude's white noise it was judged with (rad, NaN: not
    measured); a note when some length is bridged instead."""

    restart: np.ndarray
    attitude_noise_rad: float
    note: str | None


def restart_choice(data: FlightData, omega_p: float, zeta: float) -> RestartChoice:
    """Whether to restart the attitude simulation after each length of run of lost commands (up
    to ``RESTART_DECIDE_MAX_S``; longer ones always restart), measured on this flight at the
    nominal loop (``omega_p``, ``zeta``).

    There are two ways across a run of lost commands, and each carries an error into the frames
    after it. A restart takes the recorded attitude for the state: its white noise sigma_a
    (measured as the attitude's frame-to-frame change against the gyro's, where both are
    recorded) is carried on by the loop's free response g, an error of sigma_a^2 sum g(k)^2 over
    the frames after the first. Simulating on takes the interpolated commands: their error e over
    a run of m frames is measured by interpolating the same gap over stretches where every command
    is recorded, and is carried on by the loop's answer to it, an error of E[e' R e] with R the
    autocorrelation of the loop's answer r to a one-frame pulse. The smaller decides.

    Why: a restart after every lost command put the attitude's noise into the simulation
    thousands of times, in the shape of the loop's own decay, which the fit of the dynamics then
    shapes itself to. A 1023 s flight of the matrix (``--seed 1`` gen_0249) with 0.12 deg of
    attitude noise and 14 % of its commands lost read a loop of 8.6 rad/s, zeta 1.44 and a 12 ms
    delay against the nominal and true 6.65 and 1.13; gen_0097 read a 58 ms delay as a slower
    loop. With a noise-free attitude the restart is exact, and simulating on across every lost
    command left the bridge's error as local disturbances (seven of the reference recordings)."""
    T = data.frame_s
    m_max = max(1, int(round(RESTART_DECIDE_MAX_S / T)))
    restart = np.ones(m_max + 1, dtype=bool)
    gx, gy = data.gyro_angle_x_rad, data.gyro_angle_y_rad
    if gx is None or gy is None or not np.any(~data.cmd_rec) or not (omega_p > 0 and zeta > 0):
        return RestartChoice(restart, math.nan, None)
    same = data.seg[1:] == data.seg[:-1]
    pair = same & data.att_rec[1:] & data.att_rec[:-1] & data.gyro_rec[1:] & data.gyro_rec[:-1]
    var_a = []
    for att, G in ((data.roll_rad, gx), (data.pitch_rad, gy)):
        d = (np.diff(att) - np.diff(G))[pair]
        if np.count_nonzero(np.isfinite(d)) < RESTART_SAMPLES_MIN:
            return RestartChoice(restart, math.nan, None)
        var_a.append(robust_std(d) ** 2 / 2.0)  # the difference holds two samples' noise
    sigma2 = float(np.mean(var_a))
    decay = omega_p * (zeta - math.sqrt(zeta * zeta - 1.0) if zeta > 1.0 else zeta)
    L = int(min(max(math.ceil(RESTART_RESPONSE_DECAYS / (decay * T)), 10), 1000))
    r, g = _pulse_responses(omega_p, zeta, T, L)
    cost_restart = sigma2 * float(np.sum(g[1:] ** 2))
    rho = np.array([float(r[:L - d] @ r[d:]) for d in range(min(m_max, L))] + [0.0] * max(m_max - L, 0))
    u = np.stack([data.roll_cmd_rad, data.pitch_cmd_rad])
    t = data.t_s
    ok = data.cmd_rec & np.all(np.isfinite(u), axis=0)
    ok_pair = np.concatenate([[False], ok[1:] & ok[:-1] & same])  # frames k - 1 and k recorded, one segment
    bad = filters.running_count(~ok_pair)
    k0, k1 = _runs(~data.cmd_rec)
    bridged = []
    for m in np.unique(k1 - k0).tolist():  # the lengths of this flight's runs of lost commands
        if m > m_max:
            continue
        i = np.arange(1, max(data.n - m, 1))  # a gap i..i+m-1 between the ends i-1 and i+m
        i = i[bad[i + m + 1] - bad[i] == 0]  # frames i-1..i+m recorded, in one segment
        if len(i) < RESTART_SAMPLES_MIN:
            continue
        if len(i) > RESTART_SAMPLES_MAX:
            i = i[np.linspace(0, len(i) - 1, RESTART_SAMPLES_MAX).round().astype(int)]
        a, b = i - 1, i + m
        R = rho[np.abs(np.subtract.outer(np.arange(m), np.arange(m)))]
        cost = 0.0
        for ax in (0, 1):
            w = (t[i[:, None] + np.arange(m)] - t[a][:, None]) / (t[b] - t[a])[:, None]
            e = u[ax, i[:, None] + np.arange(m)] - ((1.0 - w) * u[ax, a][:, None] + w * u[ax, b][:, None])
            cost += float(np.mean(np.einsum("sj,jl,sl->s", e, R, e))) / 2.0
        if cost < cost_restart:
            restart[m] = False
            bridged.append(m)
    note = None
    if bridged:
        note = (f"the attitude simulation goes on across runs of {', '.join(str(m) for m in bridged)} lost "
                f"command(s) instead of restarting from the recorded attitude: its noise "
                f"({1e3 * math.sqrt(sigma2):.2g} mrad) would carry more error into a restart than the interpolated "
                f"commands do")
    return RestartChoice(restart, math.sqrt(sigma2), note)


class AttitudeProblem:
    """Output-error simulation of the attitude loop over every segment of a flight."""

    def __init__(self, data: FlightData, restart: np.ndarray | None = None) -> None:
        """``restart``: per run length of lost commands, whether the simulation restarts after it
        (``restart_choice``; a length past its end restarts); None: after every run."""
        self.data = data
        self.restart = restart
        self.T = data.frame_s
        self.u = np.stack([data.roll_cmd_rad, data.pitch_cmd_rad])
        self.y = np.stack([data.roll_rad, data.pitch_rad])
        #: frames whose residual the attitude channel uses (``groups.attitude_rows``)
        self.rows = np.ones(data.n, dtype=bool)
        #: the fitted (omega_p, zeta, delay), once the attitude group is chosen (``diagnosis``)
        self.final_p: np.ndarray | None = None
        # the simulation restarts from the recorded attitude after a run of lost commands (it
        # would otherwise carry the bridged commands' error for a settling time); every run of a
        # segment at once (a lossy hour has thousands)
        self.segments: list[tuple[int, int]] = []
        u = self.u
        for a, b in data.segments():
            lost = ~data.cmd_rec[a:b]
            cuts = np.array([a, b])
            if np.any(lost):
                k0, k1 = (a + k for k in _runs(lost))  # lost commands k0..k1-1
                jump = np.max(np.abs(u[:, np.minimum(k1, b - 1)] - u[:, np.maximum(k0 - 1, a)]), axis=0)
                runs = k1 - k0
                by_length = np.ones(len(runs), dtype=bool) if restart is None else \
                    np.where(runs < len(restart), restart[np.minimum(runs, len(restart) - 1)], True)
                cut = by_length | (jump > RESTART_JUMP_RAD)
                cuts = np.unique(np.concatenate([cuts, k0[cut], k1[cut]]))
            keep = np.diff(cuts) >= 2
            self.segments += zip(cuts[:-1][keep].tolist(), cuts[1:][keep].tolist(), strict=True)
        # initial rate of each segment: the gyro's, or else from the recorded attitude, the
        # three-point one-sided difference (a two-point one gives the rate half a frame late, and a
        # simulation restarted often, after lost commands, would read that as a loop that answers
        # early)
        t = data.t_s
        gyro = np.stack([data.gyro_x_rad_s, data.gyro_y_rad_s])  # roll, pitch rate (small angles)
        bounds = np.array(self.segments, dtype=np.int64).reshape(-1, 2)
        first, stop = bounds[:, 0], bounds[:, 1]
        rate0 = np.empty((2, len(first)))
        # the gyro measures the rate itself: its noise is a small fraction of a rate differenced
        # from three noisy attitudes (0.05 deg of noise over two frames at 50 Hz is 0.1 rad/s). The
        # fit does not depend on it (``_free_rate`` fits the start's rate out of the rows); the
        # simulated attitude does: the unexplained terms' regressors and the loop-form check's
        # split take it whole
        by_gyro = data.gyro_rec[first] & np.all(np.isfinite(gyro[:, first]), axis=0)
        rate0[:, by_gyro] = gyro[:, first[by_gyro]]
        # else the derivative at the first frame of the parabola through the first three samples
        three = ~by_gyro & (stop - first >= 3)
        a3 = first[three]
        h1, h2 = t[a3 + 1] - t[a3], t[a3 + 2] - t[a3]
        y0, y1, y2 = self.y[:, a3], self.y[:, a3 + 1], self.y[:, a3 + 2]
        rate0[:, three] = (y1 - y0) * h2 / (h1 * (h2 - h1)) - (y2 - y0) * h1 / (h2 * (h2 - h1))
        # else (two frames) their difference
        two = ~by_gyro & ~three
        a2 = first[two]
        k = np.minimum(a2 + 1, stop[two] - 1)
        rate0[:, two] = (self.y[:, k] - self.y[:, a2]) / np.maximum(t[k] - t[a2], 1e-6)
        #: each segment's starting (roll, pitch) rate, (nseg, 2), and its first and stop frame
        self.rate0 = np.ascontiguousarray(rate0.T)
        self._starts = np.ascontiguousarray(bounds[:, 0])
        self._stops = np.ascontiguousarray(bounds[:, 1])
        self._free_cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def delayed_command(self, delay_s: float) -> np.ndarray:
        """The command shifted by ``delay_s`` (fractional frames: frame-averaged), per segment of
        the recording: a simulation restarted after a lost command still takes the commands sent
        before the restart (a loop that answers m frames late is, just after the restart, still
        answering them; the segment's first command in their place would read as a shorter delay)."""
        if delay_s == 0.0:
            return self.u
        shift = delay_s / self.T
        m = math.floor(shift)
        f = shift - m
        out = np.empty_like(self.u)
        for a, b in self.data.segments():
            seg = self.u[:, a:b]
            out[:, a:b] = (1.0 - f) * _held_shift(seg, m) + f * _held_shift(seg, m + 1)
        return out

    def simulate(self, omega_p: float, zeta: float, delay_s: float = 0.0) -> np.ndarray:
        """Simulated attitude (2, n) [roll, pitch], rad, each segment started from the recording."""
        if not (omega_p > 0 and zeta > 0 and math.isfinite(omega_p) and math.isfinite(zeta)):
            return np.full_like(self.y, np.nan)
        Ad, Bd, b, a = discretise(omega_p, zeta, self.T)
        Ainv = np.linalg.inv(Ad)
        u = self.delayed_command(delay_s)
        out = np.full_like(self.y, np.nan)
        if not self.segments:
            return out
        starts, stops = self._starts, self._stops
        for i in (0, 1):
            # each segment's state at its start (angle, rate), taken back two frames under its
            # first command: the filter's initial conditions (all segments at once)
            um1 = u[i, starts]
            w0 = self.y[i, starts] - Bd[0] * um1
            w1 = self.rate0[:, i] - Bd[1] * um1
            xm1_0 = Ainv[0, 0] * w0 + Ainv[0, 1] * w1
            xm1_1 = Ainv[1, 0] * w0 + Ainv[1, 1] * w1
            w0 = xm1_0 - Bd[0] * um1
            w1 = xm1_1 - Bd[1] * um1
            xm2_0 = Ainv[0, 0] * w0 + Ainv[0, 1] * w1
            zi = filters.lfiltic_rows(b, a, np.stack([xm1_0, xm2_0], axis=1), np.stack([um1, um1], axis=1))
            out[i] = filters.lfilter_segments(b, a, u[i], starts, stops, zi)
        return out

    def _free_rate(self, e: np.ndarray, omega_p: float, zeta: float, fit_mask: np.ndarray | None) -> np.ndarray:
        """Each segment's starting rate as a nuisance: its free response (the loop's answer to a
        unit initial rate, no command) is fitted out of the segment's residual. The start's rate
        is the gyro's (or, without one, three recorded attitudes differenced), never exact; a
        wrong start would read as a loop answering early or late, and a fit of the dynamics would
        shape the loop's decay to it (a single segment included)."""
        Ad, _Bd, b, a = discretise(omega_p, zeta, self.T)
        starts, stops = self._starts, self._stops
        L = int((stops - starts).max())
        # the free response decays at the slower pole's rate: past FREE_RESPONSE_DECAYS of its
        # time constants it is below 1e-19 of its start, so it is computed that far only (an
        # hour's segment needs seconds of it)
        decay = omega_p * (zeta - math.sqrt(zeta * zeta - 1.0) if zeta > 1.0 else zeta)
        if decay > 0 and math.isfinite(decay):
            L = min(L, int(math.ceil(FREE_RESPONSE_DECAYS / (decay * self.T))) + 2)
        Ainv = np.linalg.inv(Ad)
        xm1 = Ainv @ np.array([0.0, 1.0])
        xm2 = Ainv @ xm1
        zi = filters.lfiltic(b, a, [xm1[0], xm2[0]], [0.0, 0.0])
        h, _ = filters.lfilter(b, a, np.zeros(L), zi=zi)
        lib = native.kernels()
        if lib is not None and e.shape == (2, self.y.shape[1]):
            # the compiled copy (``fh_free_rate``, tests/test_native.py holds the two equal)
            e = np.ascontiguousarray(e, dtype=float)
            out = e.copy()
            h = np.ascontiguousarray(h, dtype=float)
            mask = None if fit_mask is None else np.ascontiguousarray(fit_mask, dtype=np.uint8)
            lib.fh_free_rate(e.ctypes.data, e.shape[1], h.ctypes.data, L, starts.ctypes.data, stops.ctypes.data,
                             len(starts), None if mask is None else mask.ctypes.data, FREE_FIT_MIN_SHARE,
                             out.ctypes.data)
            return out
        seg, k, frames = self._free_frames(L)
        hs = h[k]
        m = np.all(np.isfinite(e[:, frames]), axis=0)
        if fit_mask is not None:
            m &= fit_mask[frames]
        hm = np.where(m, hs, 0.0)
        den = np.bincount(seg, weights=hm * hm, minlength=len(starts))
        # a segment whose fitted frames hold none of the response (only its first, where the
        # response is 0 but for rounding) has no start rate to fit: e/h there is rounding over rounding
        fit = den > FREE_FIT_MIN_SHARE * np.bincount(seg, weights=hs * hs, minlength=len(starts))
        out = e.copy()
        for i in (0, 1):
            num = np.bincount(seg, weights=np.where(m, e[i, frames], 0.0) * hm, minlength=len(starts))
            coef = np.where(fit, num / np.where(fit, den, 1.0), 0.0)
            out[i, frames] -= coef[seg] * hs
        return out

    def _free_frames(self, L: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every segment's first min(length, L) frames at once: (segment, frames since its start,
        frame), kept for the last few L (a fit asks for the same again and again)."""
        if L not in self._free_cache:
            starts, stops = self._starts, self._stops
            lens = np.minimum(stops - starts, L)  # the response is 0 past L
            seg = np.repeat(np.arange(len(starts)), lens)
            k = np.arange(int(lens.sum())) - np.repeat(np.cumsum(lens) - lens, lens)
            if len(self._free_cache) >= 4:
                self._free_cache.pop(next(iter(self._free_cache)))
            self._free_cache[L] = (seg, k, starts[seg] + k)
        return self._free_cache[L]

    def residual(self, omega_p: float, zeta: float, delay_s: float = 0.0,
                 fit_mask: np.ndarray | None = None) -> np.ndarray:
        """Recorded minus simulated attitude (2, n), rad, with each axis' constant offset removed
        (the offset estimated on ``fit_mask`` frames, all frames by default)."""
        e = self.y - self.simulate(omega_p, zeta, delay_s)
        if omega_p > 0 and zeta > 0:
            e = self._free_rate(e, omega_p, zeta, fit_mask)
        if fit_mask is None:
            ok = np.isfinite(e)
            n = ok.sum(axis=1, keepdims=True)
            mean = np.where(ok, e, 0.0).sum(axis=1, keepdims=True) / np.maximum(n, 1)
        else:
            mean = masked_row_means(e, fit_mask)
        return e - mean
