"""From a recording to aligned per-flow-frame arrays (``FlightData``), the diagnosis' only input.

One row per flow frame k, at the frame's own sensor time t_k. Everything else is brought to
those times by the sensors' own time fields (never by arrival order): the gyro (RAW_IMU,
SCALED_IMU or HIGHRES_IMU, interpolated), the downward range (DISTANCE_SENSOR orientation 25,
interpolated; readings outside the sensor's own limits are invalid), the attitude estimate
(ATTITUDE, interpolated), and the attitude command *active over [t_k, t_k+1]*:

* SET_ATTITUDE_TARGET from the companion (component 191) is computed from flow frame k and acts
  from frame k+1 (CONVENTIONS.md), so the command active at frame k is the one computed at k-1;
* without it, the vehicle's ATTITUDE_TARGET at t_k (the target it is tracking then).

The flow is turned into scene-angle increments in the paper's convention by the profile
(``companion.step.profiles``): ``dphi_x``, ``dphi_y`` (rad) over the frame that ends at t_k.
LOCAL_POSITION_NED is read for plots only (``truth_vx_m_s``), never for fitting.

The signals, their sender (the vehicle: the most frequent flow sender; the companion: component
191), time fields, units and gyro message (the vehicle's gyro as one sensor: the first of RAW_IMU,
SCALED_IMU, HIGHRES_IMU it sent), come from ``companion.recordings.signals``, as replay's do.

Frames are grouped into segments of contiguous valid frames (no gap longer than 1.5 frames, every
channel valid, a command present). Times are seconds from the first record of the recording.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion import native
from companion.config import Config
from companion.errors import RecordingError
from companion.recordings.load import Recording
from companion.recordings.signals import (
    companion_commands,
    companion_table,
    downward_range,
    gyro_sensor,
    vehicle_attitude,
    vehicle_id,
    vehicle_table,
    vehicle_targets,
)
from companion.recordings.signals import time_s as message_time_s
from companion.step.profiles import FLOW_MESSAGE, GYRO_MESSAGES, Profile, detect_profile, flow_columns

#: a segment shorter than this is not used (s)
MIN_SEGMENT_S = 5.0
#: gaps in a signal up to this long are bridged from its neighbours (lost telemetry, slow logging);
#: a longer gap ends the segment (s)
MAX_BRIDGE_S = 0.6
#: a flow timestamp this far behind the previous one (in file order) starts a new boot session (s)
REBOOT_BACKSTEP_S = 1.0
CUBIC = True
_FLAGS = ("flow_rec", "att_rec", "gyro_rec", "cmd_rec")
_OPTIONAL = ("flow_body_x_rad_s", "flow_body_y_rad_s", "gyro_angle_x_rad", "gyro_angle_y_rad", "gyro_fine_x_rad_s",
             "gyro_fine_y_rad_s", "accel_x_m_s2", "accel_y_m_s2", "accel_z_m_s2")
_ARRAYS = ("t_s", "dt_s", "seg", "dphi_x_rad", "dphi_y_rad", "gyro_x_rad_s", "gyro_y_rad_s", "range_m", "roll_rad",
           "pitch_rad", "yaw_rad", "roll_cmd_rad", "pitch_cmd_rad", "vx_set_m_s", "vy_set_m_s", "truth_vx_m_s",
           "truth_vy_m_s")


@dataclass
class FlightData:
    """Aligned per-frame arrays of one recording, all of shape (n,). Angles rad, rates rad/s, m, s.

    ``t_s`` report time (s from the first record); ``dt_s`` spacing to the previous frame;
    ``seg`` segment id (contiguous valid frames, 0..n_seg-1); ``dphi_x_rad``/``dphi_y_rad`` the
    measured scene-angle increments over the frame (paper convention); ``gyro_*_rad_s`` body
    rates as measured; ``range_m`` range to the ground; ``roll_rad``, ``pitch_rad``, ``yaw_rad``
    the attitude estimate; ``roll_cmd_rad``, ``pitch_cmd_rad`` the command active over
    [t_k, t_k+1]; ``vx_set_m_s``/``vy_set_m_s`` the velocity setpoint (NaN when not recorded);
    ``truth_v*_m_s`` LOCAL_POSITION_NED in body axes (plots only; NaN when absent).
    """

    path: str
    profile: str
    profile_reason: str
    frame_s: float
    command_source: str
    t_s: np.ndarray
    dt_s: np.ndarray
    seg: np.ndarray
    dphi_x_rad: np.ndarray
    dphi_y_rad: np.ndarray
    gyro_x_rad_s: np.ndarray
    gyro_y_rad_s: np.ndarray
    range_m: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray
    roll_cmd_rad: np.ndarray
    pitch_cmd_rad: np.ndarray
    vx_set_m_s: np.ndarray
    vy_set_m_s: np.ndarray
    truth_vx_m_s: np.ndarray
    truth_vy_m_s: np.ndarray
    notes: list[str] = field(default_factory=list)
    #: standard deviation of the recorded values' rounding (gyro: mrad/s integers; flow: counts)
    gyro_resolution_rad_s: float = 0.0
    flow_resolution_rad: float = 0.0
    #: the step of each stream's own time stamps (s; ``stamp_step_s``), by stream: "flow",
    #: "attitude", "gyro"; a stream not in it is taken as exact
    stamp_step_s: dict[str, float] = field(default_factory=dict)
    #: per frame, whether the signal was recorded at the frame (False: bridged over a gap from its
    #: neighbours, lost telemetry or a slower logging rate); None (the default) = recorded
    #: everywhere, which ``__post_init__`` turns into ones: an array once constructed
    flow_rec: np.ndarray = None  # type: ignore[assignment]
    #: the flow message's own body rates (roll, pitch rate, rad/s; ArduPilot: flow_rate - flow_comp_m,
    #: PX4: integrated gyro / integration time), sampled with the flow; None when it has none
    flow_body_x_rad_s: np.ndarray | None = None
    flow_body_y_rad_s: np.ndarray | None = None
    #: the gyro's integral (rad, from an arbitrary start per run of samples) and the gyro (rad/s)
    #: at the frames, both from a cubic spline through the gyro's samples at their own times
    #: (``gyro_spline``); None when not computed
    gyro_angle_x_rad: np.ndarray | None = None
    gyro_angle_y_rad: np.ndarray | None = None
    gyro_fine_x_rad_s: np.ndarray | None = None
    gyro_fine_y_rad_s: np.ndarray | None = None
    #: the accelerometer's body x, y and z specific force (m/s^2, FRD) at the frames, from the gyro's
    #: message (RAW_IMU xacc, yacc, zacc); None when it has none
    accel_x_m_s2: np.ndarray | None = None
    accel_y_m_s2: np.ndarray | None = None
    accel_z_m_s2: np.ndarray | None = None
    att_rec: np.ndarray = None  # type: ignore[assignment]
    gyro_rec: np.ndarray = None  # type: ignore[assignment]
    cmd_rec: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        for name in _FLAGS:
            if getattr(self, name) is None:
                setattr(self, name, np.ones(self.n, dtype=bool))

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def duration_s(self) -> float:
        return float(np.sum(self.dt_s[1:][np.diff(self.seg) == 0])) if self.n > 1 else 0.0

    def segments(self) -> list[tuple[int, int]]:
        """(start, stop) index ranges of the segments, stop exclusive."""
        if self.n == 0:
            return []
        cuts = np.flatnonzero(np.diff(self.seg)) + 1
        starts = np.concatenate([[0], cuts])
        stops = np.concatenate([cuts, [self.n]])
        return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]

    def take(self, mask: np.ndarray) -> FlightData:
        """The frames where ``mask``; segments are renumbered and split where frames were removed."""
        idx = np.flatnonzero(mask)
        kw = {}
        for name in ("t_s", "dt_s", "dphi_x_rad", "dphi_y_rad", "gyro_x_rad_s", "gyro_y_rad_s", "range_m",
                     "roll_rad", "pitch_rad", "yaw_rad", "roll_cmd_rad", "pitch_cmd_rad", "vx_set_m_s",
                     "vy_set_m_s", "truth_vx_m_s", "truth_vy_m_s"):
            kw[name] = getattr(self, name)[idx]
        old = self.seg[idx]
        brk = np.ones(len(idx), dtype=bool)
        brk[1:] = (np.diff(idx) != 1) | (np.diff(old) != 0)
        kw["seg"] = np.cumsum(brk) - 1
        for name in _FLAGS:
            kw[name] = getattr(self, name)[idx]
        for name in _OPTIONAL:
            v = getattr(self, name)
            kw[name] = None if v is None else v[idx]
        return FlightData(self.path, self.profile, self.profile_reason, self.frame_s, self.command_source,
                          notes=list(self.notes), gyro_resolution_rad_s=self.gyro_resolution_rad_s,
                          flow_resolution_rad=self.flow_resolution_rad, stamp_step_s=dict(self.stamp_step_s), **kw)


# ---------------------------------------------------------------------------------------------
# helpers


def _sorted_unique(t: np.ndarray, *cols: np.ndarray) -> tuple[np.ndarray, ...]:
    order = np.argsort(t, kind="stable")
    t = t[order]
    keep = np.ones(len(t), dtype=bool)
    keep[1:] = np.diff(t) > 0
    return (t[keep], *(c[order][keep] for c in cols))


def _interp(t_query: np.ndarray, t: np.ndarray, y: np.ndarray, max_gap_s: float) -> np.ndarray:
    """Linear interpolation; NaN where the nearest sample is further than ``max_gap_s``."""
    if len(t) == 0:
        return np.full(len(t_query), np.nan)
    out = np.interp(t_query, t, y)
    i = np.clip(native.searchsorted(t, t_query), 1, max(len(t) - 1, 1))  # np.searchsorted, compiled
    near = np.minimum(np.abs(t_query - t[i - 1]), np.abs(t[np.minimum(i, len(t) - 1)] - t_query))
    out[near > max_gap_s] = np.nan
    return out


def _nearest(t_query: np.ndarray, t: np.ndarray, tol_s: float) -> np.ndarray:
    """Index of the sample of ``t`` nearest each query time, -1 when none is within ``tol_s``."""
    if len(t) == 0:
        return np.full(len(t_query), -1)
    i = np.clip(native.searchsorted(t, t_query), 1, max(len(t) - 1, 1))  # np.searchsorted, compiled
    left = i - 1
    right = np.minimum(i, len(t) - 1)
    pick = np.where(np.abs(t[left] - t_query) <= np.abs(t[right] - t_query), left, right)
    pick = np.where(np.abs(t[pick] - t_query) <= tol_s, pick, -1)
    return pick


def missing_channels(rec: Recording, profile: str) -> list[str]:
    """The messages diagnosis needs that the recording lacks (CONVENTIONS.md, Recordings)."""
    missing = []
    flow = FLOW_MESSAGE[Profile(profile)]
    if flow not in rec:
        missing.append(flow if profile != Profile.PAPER else "OPTICAL_FLOW")
    if not any(g in rec for g in GYRO_MESSAGES):
        missing.append("RAW_IMU (or SCALED_IMU / HIGHRES_IMU)")
    if "DISTANCE_SENSOR" not in rec:
        missing.append("DISTANCE_SENSOR")
    if "ATTITUDE" not in rec:
        missing.append("ATTITUDE")
    return missing


def has_commands(rec: Recording) -> bool:
    """True when the recording holds a commanded attitude (companion or vehicle target)."""
    return companion_commands(rec) is not None or "ATTITUDE_TARGET" in rec


# ---------------------------------------------------------------------------------------------
# extraction


def _sessions(rec: Recording, flow_name: str, sysid: int, prof: Profile, q: float) -> list[Recording]:
    """The recording cut into boot sessions: a flow time that steps back by more than
    ``REBOOT_BACKSTEP_S`` in file order is a reboot (logs kept across reboots, or concatenated).
    Each session holds the records from its first flow frame to the next session's."""
    of = vehicle_table(rec, flow_name, sysid)
    assert of is not None  # the vehicle is the flow's most frequent sender
    order = np.argsort(of.record, kind="stable")
    tb = np.asarray(flow_columns(of, prof, q).time_s, float)[order]
    back = np.flatnonzero(np.diff(tb) < -REBOOT_BACKSTEP_S) + 1
    if len(back) == 0:
        return [rec]
    cuts = [-np.inf, *[float(of.record[order][i]) for i in back], np.inf]
    out = []
    for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
        tables = {n: t.select((t.record >= lo) & (t.record < hi)) for n, t in rec.tables.items()}
        out.append(Recording(rec.path, tables, rec.source_format, profile_hint=rec.profile_hint))
    return out


def _grid(tb: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray]:
    """Frame times on a regular grid: the recorded ones, plus frames inserted in gaps up to
    ``MAX_BRIDGE_S`` at the gap's own mean spacing. Returns (times, index of each recorded frame
    in the grid)."""
    d = np.diff(tb)
    missing = np.where((d > 1.5 * T) & (d <= MAX_BRIDGE_S + 0.5 * T), np.rint(d / T).astype(int) - 1, 0)
    missing = np.maximum(missing, 0)
    pos = np.concatenate([[0], np.cumsum(missing + 1)])
    n = int(pos[-1]) + 1
    t = np.empty(n)
    t[pos] = tb
    # the j-th of the k frames inserted after recorded frame i at tb[i] + d[i] j / (k + 1), every
    # gap at once (a lossy hour has thousands)
    i = np.repeat(np.arange(len(missing)), missing)
    j = np.arange(1, len(i) + 1) - np.repeat(np.cumsum(missing) - missing, missing)
    t[pos[i] + j] = tb[i] + d[i] * j / (missing[i] + 1)
    return t, pos


def _interp_gapped(t_query: np.ndarray, t: np.ndarray, y: np.ndarray, max_gap_s: float,
                   cubic: bool = False) -> np.ndarray:
    """Interpolation that bridges gaps up to ``max_gap_s`` between samples (NaN across longer
    gaps and outside the samples); ``cubic``: a cubic spline (an attitude logged slower than the
    frames), else linear."""
    ok = np.isfinite(y)
    t, y = t[ok], y[ok]
    out = np.full(len(t_query), np.nan)
    if len(t) == 0:
        return out
    if cubic and len(t) >= 4:
        from scipy.interpolate import CubicSpline

        out = CubicSpline(t, y, extrapolate=False)(t_query)
    elif len(t) >= 2:
        out = np.interp(t_query, t, y)
    i = np.clip(native.searchsorted(t, t_query), 1, max(len(t) - 1, 1))  # np.searchsorted, compiled
    lo, hi = t[i - 1], t[np.minimum(i, len(t) - 1)]
    exact = np.minimum(np.abs(t_query - lo), np.abs(t_query - hi)) <= 1e-9
    inside = (t_query >= t[0]) & (t_query <= t[-1]) & (hi - lo <= max_gap_s)
    out = np.where(exact, np.where(np.abs(t_query - lo) <= np.abs(t_query - hi), y[i - 1],
                                   y[np.minimum(i, len(t) - 1)]), out)
    out[~(inside | exact)] = np.nan
    return out


def gyro_spline(t_query: np.ndarray, t: np.ndarray, y: np.ndarray, max_gap_s: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """(integral, value) at ``t_query`` of the local piecewise cubic (Catmull-Rom: cubic Hermite
    with each sample's slope from its neighbours, ``np.gradient``, second order on uneven times)
    through the samples (t, y), per run of samples no further apart than ``max_gap_s`` (the
    integral from the run's first sample; NaN outside the runs).

    Why: the rotation the flow sees is the exact integral of the body rate. A gyro put on the flow's
    frame grid by linear interpolation and integrated by the trapezoid attenuates what it samples
    at high frequency (by (wT)^2/12 and by the interpolation's own averaging: about 1 % at 3 Hz
    and 50 Hz), which reads as a rotation gain, a flow scale or a lever arm of 1-2 % in a flight
    that oscillates. A cubic through the samples at their own times keeps a smooth rate's integral
    at its size: on even samples this one's integral over a step is h/24 (-y0 + 13 y1 + 13 y2 - y3),
    the cubic through four samples, whose gain is 1 - O((wT)^4): within 0.03 % at 3 Hz and 0.1 %
    at 4 Hz at 50 Hz (the trapezoid: 1.2 %, 2 %).

    Why not PCHIP (what it was): its slopes are harmonic means, set to zero at every sample that
    is an extremum, so it flattens each peak of an oscillating rate. On a noise-free generator
    flight whose loop oscillates under a 36 ms flow delay (simvehicle.engines.flightgen, seed 95),
    against the simulator's own integral of the body rate above 3 Hz, PCHIP's integral was 0.85 %
    small (rms error 1.8e-4 rad), this cubic's 0.4 % large (1.3e-4 rad; above 1 Hz -0.16 % and
    +0.05 %), and through PCHIP the finder named a flow scale of 0.988 and a lever arm of -2.4 cm
    beside the delay (tests/test_diagnose_rotation.py). Why not the C2 spline:
    it couples every sample, so a gyro's rounding to whole mrad/s in a hover rings through it (it
    overshot the hover's rotation by 6-7 % in windows under a count, seed 143); this cubic is local
    (a sample moves the four steps around it only)."""
    from scipy.interpolate import CubicHermiteSpline

    ok = np.isfinite(y)
    t, y = t[ok], y[ok]
    ang = np.full(len(t_query), np.nan)
    val = np.full(len(t_query), np.nan)
    if len(t) < 4:
        return ang, val
    cuts = np.flatnonzero(np.diff(t) > max_gap_s) + 1
    for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(t)]]), strict=True):
        if b - a < 4:
            continue
        sp = CubicHermiteSpline(t[a:b], y[a:b], np.gradient(y[a:b], t[a:b]))
        lo, hi = np.searchsorted(t_query, t[a]), np.searchsorted(t_query, t[b - 1], side="right")
        tq = t_query[lo:hi]
        ang[lo:hi] = sp.antiderivative()(tq)
        val[lo:hi] = sp(tq)
    return ang, val


def _recorded(t_query: np.ndarray, t: np.ndarray, tol_s: float) -> np.ndarray:
    return _nearest(t_query, t, tol_s) >= 0


def extract(rec: Recording, cfg: Config, profile: str | None = None) -> FlightData:
    """Aligned per-frame arrays of a closed-loop recording (see the module docstring).

    Lost telemetry and signals logged at other rates than the flow are bridged up to
    ``MAX_BRIDGE_S`` (each signal's ``*_rec`` flag says where it was really recorded); boot
    sessions (a log across reboots) are all used, one after the other. Raises RecordingError
    naming the messages that are missing, or when no stretch of at least ``MIN_SEGMENT_S`` of
    valid, commanded frames exists.
    """
    name = Path(rec.path).name
    if profile is None:
        profile, reason = detect_profile(rec)
    else:
        reason = "given with --profile"
    prof = Profile(profile)
    if "OPTICAL_FLOW" not in rec and "OPTICAL_FLOW_RAD" not in rec:
        raise RecordingError(f"{name}: no OPTICAL_FLOW (or OPTICAL_FLOW_RAD) messages: the flow is required")
    missing = missing_channels(rec, profile)
    if not has_commands(rec):
        missing.append("SET_ATTITUDE_TARGET (or ATTITUDE_TARGET)")
    if missing:
        raise RecordingError(f"{name}: missing {', '.join(missing)} (needed to diagnose a closed-loop flight)")
    flow_name = FLOW_MESSAGE[prof]
    sysid = vehicle_id(rec, prof)
    sessions = _sessions(rec, flow_name, sysid, prof, cfg.flow_sensor.q_rad_per_count)
    parts = []
    for sess in sessions:
        try:
            parts.append(_extract_session(sess, rec.t0_s, cfg, prof, reason, sysid))
        except RecordingError:
            if len(sessions) == 1:
                raise
    if not parts:
        raise RecordingError(f"{name}: no boot session with enough {flow_name} frames")
    data = _concat(parts) if len(parts) > 1 else parts[0]
    if len(sessions) > 1:
        data.notes.append(f"{len(sessions)} boot sessions (the flow time starts again), {len(parts)} used, "
                          f"one after the other")
    n_all = data.n
    good = (np.isfinite(data.dphi_x_rad) & np.isfinite(data.dphi_y_rad) & np.isfinite(data.gyro_x_rad_s)
            & np.isfinite(data.gyro_y_rad_s) & np.isfinite(data.range_m) & (data.range_m > 0)
            & np.isfinite(data.roll_rad) & np.isfinite(data.pitch_rad) & np.isfinite(data.roll_cmd_rad)
            & np.isfinite(data.pitch_cmd_rad))
    _bridge_notes(data, good)
    n_bad = int(np.count_nonzero(~good))
    if n_bad:
        data.notes.append(f"{n_bad} of {n_all} flow frames unusable (no command, invalid flow, range, gyro or "
                          f"attitude at or near the frame)")
    data = data.take(good)
    # keep segments long enough to fit over
    keep = np.zeros(data.n, dtype=bool)
    for a, b in data.segments():
        if data.t_s[b - 1] - data.t_s[a] >= MIN_SEGMENT_S:
            keep[a:b] = True
    if not np.any(keep):
        raise RecordingError(f"{name}: no stretch of {MIN_SEGMENT_S:.0f} s with flow, gyro, range, attitude and "
                             f"a commanded attitude all valid (gaps up to {MAX_BRIDGE_S:g} s bridged)")
    if not np.all(keep):
        data.notes.append(f"{int(np.count_nonzero(~keep))} frames in stretches shorter than {MIN_SEGMENT_S:.0f} s "
                          f"left out")
        data = data.take(keep)
    # the first frame of each segment has no previous frame: its increment is not trusted
    first = np.ones(data.n, dtype=bool)
    first[1:] = np.diff(data.seg) != 0
    data.dphi_x_rad[first] = 0.0
    data.dphi_y_rad[first] = 0.0
    data.dt_s[first] = cfg.flow_sensor.frame_period_s
    return data


def _bridge_notes(data: FlightData, good: np.ndarray) -> None:
    """Say how much of each signal was bridged rather than recorded, over the usable frames."""
    n = int(np.count_nonzero(good))
    if n == 0:
        return
    parts = []
    for flag, what in (("flow_rec", "flow"), ("att_rec", "attitude"), ("gyro_rec", "gyro"),
                       ("cmd_rec", "command")):
        miss = int(np.count_nonzero(~getattr(data, flag)[good]))
        if miss:
            parts.append(f"{what} {100.0 * miss / n:.1f} %")
    if parts:
        data.notes.append("bridged from neighbouring samples (lost telemetry or slower logging), share of frames: "
                          + ", ".join(parts))


def _concat(parts: list[FlightData]) -> FlightData:
    """Sessions one after the other: segment ids kept apart, times shifted where a session's
    times overlap the previous one's (concatenated logs), with a note."""
    kw: dict[str, np.ndarray] = {}
    shift = 0.0
    end = -np.inf
    seg0 = 0
    notes: list[str] = []
    shifted = False
    optional = [k for k in _OPTIONAL if all(getattr(p, k) is not None for p in parts)]
    pieces: dict[str, list[np.ndarray]] = {k: [] for k in (*_ARRAYS, *_FLAGS, *optional)}
    for p in parts:
        if p.n == 0:
            continue
        shift = 0.0
        if p.t_s[0] <= end:
            shift = end + 1.0 - float(p.t_s[0])
            shifted = True
        for k in pieces:
            v = getattr(p, k)
            if k == "t_s":
                v = v + shift
            elif k == "seg":
                v = v - v.min() + seg0
            pieces[k].append(v)
        seg0 = int(pieces["seg"][-1].max()) + 1
        end = float(pieces["t_s"][-1][-1])
        notes.extend(x for x in p.notes if x not in notes)
    for k, v in pieces.items():
        kw[k] = np.concatenate(v)
    if shifted:
        notes.append("a session's log times overlap the previous one's: it is placed after it (report times "
                     "past the first session are shifted)")
    p0 = parts[0]
    steps = {k: max(p.stamp_step_s.get(k, 0.0) for p in parts) for p in parts for k in p.stamp_step_s}
    return FlightData(p0.path, p0.profile, p0.profile_reason, p0.frame_s, p0.command_source, notes=notes,
                      gyro_resolution_rad_s=p0.gyro_resolution_rad_s, flow_resolution_rad=p0.flow_resolution_rad,
                      stamp_step_s=steps, **kw)


def stamp_step_s(t: np.ndarray) -> float:
    """The resolution of a stream's own time stamps, s: 1 ms when every stamp is a whole
    millisecond (a ``time_boot_ms``, or a microsecond field that carries milliseconds, as
    ArduPilot's OPTICAL_FLOW does), else 1 us; 0 for no stamps. Two streams stamped to 1 ms have a
    relative timing known to +-1 ms at worst (each stamp rounded or truncated by its own phase
    against the clock's ticks): what a delay or lag between them can be known to
    (``groups.timing_sigma_s``)."""
    t = np.asarray(t, float)
    t = t[np.isfinite(t)]
    if len(t) == 0:
        return 0.0
    ms = t * 1e3
    return 1e-3 if bool(np.all(np.abs(ms - np.round(ms)) < 1e-4)) else 1e-6


def _extract_session(rec: Recording, t0: float, cfg: Config, prof: Profile, reason: str, sysid: int) -> FlightData:
    """One boot session on its regular frame grid, every frame kept (``extract`` filters)."""
    name = Path(rec.path).name
    flow_name = FLOW_MESSAGE[prof]
    notes: list[str] = []
    T = cfg.flow_sensor.frame_period_s
    bridge = MAX_BRIDGE_S

    # flow frames
    of = vehicle_table(rec, flow_name, sysid)
    if of is None:
        raise RecordingError(f"{name}: no {flow_name} frames from the vehicle")
    fc = flow_columns(of, prof, cfg.flow_sensor.q_rad_per_count)
    bx_all = np.broadcast_to(np.asarray(fc.body_x_rad_s, float), np.shape(fc.time_s))
    by_all = np.broadcast_to(np.asarray(fc.body_y_rad_s, float), np.shape(fc.time_s))
    tr, sx, sy, qual, integ, tlog, bxr, byr = _sorted_unique(
        np.asarray(fc.time_s, float), np.asarray(fc.scene_x, float), np.asarray(fc.scene_y, float),
        np.asarray(fc.quality, float), np.asarray(fc.integration_s, float), of.t_s, bx_all, by_all)
    if len(tr) < 10:
        raise RecordingError(f"{name}: only {len(tr)} {flow_name} frames")
    offset = float(np.median(tlog - tr))
    # each recorded frame's scene-angle increment over its own period: a frame after lost ones
    # covers only its own period (counts) or gives a rate (ArduPilot) held over its own period
    d = np.diff(tr)
    own = np.full(len(tr), T)
    own[1:] = np.where((d > 0) & (d <= 1.5 * T), d, T)
    if fc.increment:
        ix, iy = sx, sy
        ok_int = np.isfinite(integ) & (integ > 0)
        if np.any(ok_int):  # a px4 frame's increment covers its own integration time: rescale
            ix = np.where(ok_int, sx * own / np.where(ok_int, integ, 1.0), sx)
            iy = np.where(ok_int, sy * own / np.where(ok_int, integ, 1.0), sy)
    else:
        ix, iy = sx * own, sy * own
    valid_rec = (qual > 0) & np.isfinite(ix) & np.isfinite(iy)

    tb, pos = _grid(tr, T)
    n = len(tb)
    flow_rec = np.zeros(n, dtype=bool)
    flow_rec[pos] = valid_rec
    dt = np.full(n, T)
    dt[1:] = np.diff(tb)
    dt[1:][np.diff(tb) > bridge + 0.5 * T] = T
    body_x = body_y = None
    if np.count_nonzero(np.isfinite(bxr) & np.isfinite(byr)) >= 0.9 * len(tr):
        ok_b = np.isfinite(bxr) & np.isfinite(byr)
        body_x = _interp_gapped(tb, tr[ok_b], bxr[ok_b], bridge)
        body_y = _interp_gapped(tb, tr[ok_b], byr[ok_b], bridge)

    # attitude estimate (a cubic through slower or gapped samples)
    at = vehicle_attitude(rec, sysid)
    if at is None:
        e = np.zeros(0)
        att_t = roll = pitch = yaw = e
    else:
        att_t, roll, pitch, yaw = _sorted_unique(at.time_s, at.roll, at.pitch, np.unwrap(at.yaw))
    roll_k = _interp_gapped(tb, att_t, roll, bridge, cubic=CUBIC)
    pitch_k = _interp_gapped(tb, att_t, pitch, bridge, cubic=CUBIC)
    yaw_k = _interp_gapped(tb, att_t, yaw, bridge)
    att_rec = _recorded(tb, att_t, 0.5 * T)

    # flow increments on the grid: recorded frames as they are; a lost frame's increment is the
    # rotation the attitude shows over it plus the translational rate interpolated from the
    # recorded neighbours (translation is smooth; rotation is not, and the attitude has it)
    dphi = []
    for inc, s_ax, ang in ((ix, -1.0, pitch_k), (iy, 1.0, roll_k)):
        g = np.full(n, np.nan)
        g[pos] = np.where(valid_rec, inc, np.nan)
        rot = np.zeros(n)
        rot[1:] = s_ax * np.diff(ang)
        rot[~np.isfinite(rot)] = 0.0
        trans_rate = (g - rot) / dt
        have = np.isfinite(trans_rate)
        if np.any(~have) and np.count_nonzero(have) >= 2:
            fill = _interp_gapped(tb, tb[have], trans_rate[have], bridge)
            g = np.where(have, g, fill * dt + rot)
        dphi.append(g)
    dphi_x, dphi_y = dphi
    # a gap too long to bridge: the frame after it starts a new segment
    brk = np.ones(n, dtype=bool)
    brk[1:] = np.diff(tb) > bridge + 0.5 * T

    # gyro
    gyro = gyro_sensor(rec, sysid)
    scale = GYRO_MESSAGES[gyro.names[0]] if gyro.names else 1.0
    gt, gx, gy = _sorted_unique(gyro.time_s, gyro.x_rad_s, gyro.y_rad_s)
    # a clipped sample is unknown (NaN): not bridged over, a frame whose nearest sample it is is not trusted
    near = _nearest(tb, gt, bridge)
    unknown = (near >= 0) & ~(np.isfinite(gx) & np.isfinite(gy))[np.maximum(near, 0)]
    gyro_x = np.where(unknown, np.nan, _interp_gapped(tb, gt, gx, bridge))
    gyro_y = np.where(unknown, np.nan, _interp_gapped(tb, gt, gy, bridge))
    gyro_rec = _recorded(tb, gt, 0.5 * T)
    gang_x, gfine_x = (np.where(unknown, np.nan, v) for v in gyro_spline(tb, gt, gx, bridge))
    gang_y, gfine_y = (np.where(unknown, np.nan, v) for v in gyro_spline(tb, gt, gy, bridge))
    accel = gyro.accel_m_s2
    acc_x = acc_y = acc_z = None
    if accel is not None:
        acc_t, acc_xs, acc_ys, acc_zs = _sorted_unique(gyro.time_s, accel[:, 0], accel[:, 1], accel[:, 2])
        acc_x = _interp_gapped(tb, acc_t, acc_xs, bridge)
        acc_y = _interp_gapped(tb, acc_t, acc_ys, bridge)
        acc_z = _interp_gapped(tb, acc_t, acc_zs, bridge)

    # range (downward only; outside the sensor's own limits is invalid)
    ds = downward_range(rec, sysid)
    if ds is None:
        raise RecordingError(f"{name}: no DISTANCE_SENSOR facing down (orientation 25)")
    rt, rr = _sorted_unique(ds.time_s, ds.range_m)
    range_m = _interp_gapped(tb, rt[np.isfinite(rr)], rr[np.isfinite(rr)], bridge)
    # a frame whose nearest reading is an invalid one is not trusted either
    near = _nearest(tb, rt, bridge)
    range_m[(near < 0) | ~np.isfinite(rr[np.maximum(near, 0)])] = np.nan

    # command active over [t_k, t_k+1]
    sat = companion_commands(rec)
    if sat is not None:
        ct, cr, cp = _sorted_unique(sat.time_s, sat.roll, sat.pitch)
        # the command computed from frame k carries frame k's time and acts from frame k+1
        j = _nearest(tb, ct, 0.4 * T)
        rec_k = j >= 0
        ck_r = np.where(rec_k, cr[np.maximum(j, 0)], np.nan)
        ck_p = np.where(rec_k, cp[np.maximum(j, 0)], np.nan)
        if np.count_nonzero(rec_k) >= 2:  # a lost command: between its neighbours
            ck_r = np.where(rec_k, ck_r, _interp_gapped(tb, tb[rec_k], ck_r[rec_k], bridge))
            ck_p = np.where(rec_k, ck_p, _interp_gapped(tb, tb[rec_k], ck_p[rec_k], bridge))
        roll_u = np.full(n, np.nan)
        pitch_u = np.full(n, np.nan)
        roll_u[1:], pitch_u[1:] = ck_r[:-1], ck_p[:-1]
        cmd_rec = np.zeros(n, dtype=bool)
        cmd_rec[1:] = rec_k[:-1]
        source = "SET_ATTITUDE_TARGET (companion), active from the next frame"
    else:
        atg = vehicle_targets(rec, sysid)
        if atg is None:
            ct = cr = cp = np.zeros(0)
        else:
            ct, cr, cp = _sorted_unique(atg.time_s, atg.roll, atg.pitch)
        roll_u = _interp_gapped(tb, ct, cr, bridge)
        pitch_u = _interp_gapped(tb, ct, cp, bridge)
        cmd_rec = _recorded(tb, ct, 0.6 * T)
        source = "ATTITUDE_TARGET (vehicle)"

    # velocity setpoint (informative)
    vx_set = np.full(n, np.nan)
    vy_set = np.full(n, np.nan)
    pt = companion_table(rec, "POSITION_TARGET_LOCAL_NED")  # the companion's: the setpoint it tracked
    if pt is not None:
        ptt, pvx, pvy = _sorted_unique(message_time_s(pt), np.asarray(pt["vx"], float), np.asarray(pt["vy"], float))
        j = _nearest(tb, ptt, 0.6 * T)
        vx_set = np.where(j >= 0, pvx[np.maximum(j, 0)], np.nan)
        vy_set = np.where(j >= 0, pvy[np.maximum(j, 0)], np.nan)

    # truth, for plots only
    tvx = np.full(n, np.nan)
    tvy = np.full(n, np.nan)
    lp = vehicle_table(rec, "LOCAL_POSITION_NED", sysid)
    if lp is not None:
        if len(lp) > 1:
            lt, lvx, lvy = _sorted_unique(message_time_s(lp), np.asarray(lp["vx"], float), np.asarray(lp["vy"], float))
            vn = _interp(tb, lt, lvx, 0.2)
            ve = _interp(tb, lt, lvy, 0.2)
            c, s = np.cos(yaw_k), np.sin(yaw_k)
            tvx, tvy = c * vn + s * ve, -s * vn + c * ve

    t_report = tb + offset - t0
    # a frame the sensor itself marked invalid (quality 0) is not bridged: it splits the segment
    invalid = np.zeros(n, dtype=bool)
    invalid[pos] = ~valid_rec
    dphi_x[invalid] = np.nan
    dphi_y[invalid] = np.nan
    seg = np.cumsum(brk) - 1
    return FlightData(
        path=str(rec.path), profile=prof.value, profile_reason=reason, frame_s=T, command_source=source,
        t_s=t_report, dt_s=dt, seg=seg, dphi_x_rad=dphi_x, dphi_y_rad=dphi_y, gyro_x_rad_s=gyro_x,
        gyro_y_rad_s=gyro_y, range_m=range_m, roll_rad=roll_k, pitch_rad=pitch_k, yaw_rad=yaw_k,
        roll_cmd_rad=roll_u, pitch_cmd_rad=pitch_u, vx_set_m_s=vx_set, vy_set_m_s=vy_set,
        truth_vx_m_s=tvx, truth_vy_m_s=tvy, notes=notes,
        gyro_resolution_rad_s=(1e-3 if scale == 1e-3 else 0.0) / np.sqrt(12.0),
        flow_resolution_rad=(cfg.flow_sensor.q_rad_per_count if prof is Profile.PAPER else 0.0) / np.sqrt(12.0),
        flow_rec=flow_rec, att_rec=att_rec, gyro_rec=gyro_rec, cmd_rec=cmd_rec,
        stamp_step_s={"flow": stamp_step_s(tr), "attitude": stamp_step_s(att_t), "gyro": stamp_step_s(gt)},
        flow_body_x_rad_s=body_x, flow_body_y_rad_s=body_y, gyro_angle_x_rad=gang_x, gyro_angle_y_rad=gang_y,
        gyro_fine_x_rad_s=gfine_x, gyro_fine_y_rad_s=gfine_y, accel_x_m_s2=acc_x, accel_y_m_s2=acc_y,
        accel_z_m_s2=acc_z)
