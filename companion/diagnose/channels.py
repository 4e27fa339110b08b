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
(``companion.profiles``): ``dphi_x``, ``dphi_y`` (rad) over the frame that ends at t_k.
LOCAL_POSITION_NED is read for plots only (``truth_vx_m_s``), never for fitting.

Frames are grouped into segments of contiguous valid frames (no gap longer than 1.5 frames, every
channel valid, a command present). Times are seconds from the first record of the recording.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion.config import Config
from companion.errors import RecordingError
from companion.estimator import frame_spacing_array
from companion.profiles import FLOW_MESSAGE, GYRO_MESSAGES, Profile, detect_profile, flow_columns
from companion.recording import MessageTable, Recording

COMPANION_COMPONENT = 191
DOWNWARD = 25
#: a segment shorter than this is not used (s)
MIN_SEGMENT_S = 5.0


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
        return FlightData(self.path, self.profile, self.profile_reason, self.frame_s, self.command_source,
                          notes=list(self.notes), gyro_resolution_rad_s=self.gyro_resolution_rad_s,
                          flow_resolution_rad=self.flow_resolution_rad, **kw)


# ---------------------------------------------------------------------------------------------
# helpers


def quaternion_to_euler(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(roll, pitch, yaw) rad from quaternions [w, x, y, z] of shape (n, 4) (ZYX, as
    ``companion.outbound.quaternion_to_euler``, vectorised)."""
    q = np.asarray(q, dtype=float).reshape(-1, 4)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


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
    i = np.clip(np.searchsorted(t, t_query), 1, max(len(t) - 1, 1))
    near = np.minimum(np.abs(t_query - t[i - 1]), np.abs(t[np.minimum(i, len(t) - 1)] - t_query))
    out[near > max_gap_s] = np.nan
    return out


def _nearest(t_query: np.ndarray, t: np.ndarray, tol_s: float) -> np.ndarray:
    """Index of the sample of ``t`` nearest each query time, -1 when none is within ``tol_s``."""
    if len(t) == 0:
        return np.full(len(t_query), -1)
    i = np.clip(np.searchsorted(t, t_query), 1, max(len(t) - 1, 1))
    left = i - 1
    right = np.minimum(i, len(t) - 1)
    pick = np.where(np.abs(t[left] - t_query) <= np.abs(t[right] - t_query), left, right)
    pick = np.where(np.abs(t[pick] - t_query) <= tol_s, pick, -1)
    return pick


def _vehicle_sysid(rec: Recording, flow_name: str) -> int:
    tab = rec.tables[flow_name]
    ids, counts = np.unique(tab.sysid, return_counts=True)
    return int(ids[np.argmax(counts)])


def _from_vehicle(tab: MessageTable, sysid: int) -> MessageTable:
    return tab.select((tab.sysid == sysid) & (tab.compid != COMPANION_COMPONENT))


def _boot_offset(tab: MessageTable, boot_s: np.ndarray) -> float:
    """log time - boot time (s), median over the table: maps sensor times to log times."""
    return float(np.median(tab.t_s - boot_s))


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
    if "SET_ATTITUDE_TARGET" in rec and np.any(rec.tables["SET_ATTITUDE_TARGET"].compid == COMPANION_COMPONENT):
        return True
    return "ATTITUDE_TARGET" in rec


# ---------------------------------------------------------------------------------------------
# extraction


def extract(rec: Recording, cfg: Config, profile: str | None = None) -> FlightData:
    """Aligned per-frame arrays of a closed-loop recording (see the module docstring).

    Raises RecordingError naming the messages that are missing, or when no stretch of at least
    ``MIN_SEGMENT_S`` of valid, commanded frames exists.
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
    t0 = rec.t0_s
    flow_name = FLOW_MESSAGE[prof]
    sysid = _vehicle_sysid(rec, flow_name)
    notes: list[str] = []
    T = cfg.flow_sensor.frame_period_s

    # flow frames
    of = _from_vehicle(rec.tables[flow_name], sysid)
    fc = flow_columns(of, prof, cfg.flow_sensor.q_rad_per_count)
    tb, sx, sy, qual, integ, tlog = _sorted_unique(np.asarray(fc.time_s, float), np.asarray(fc.scene_x, float),
                                                   np.asarray(fc.scene_y, float), np.asarray(fc.quality, float),
                                                   np.asarray(fc.integration_s, float), of.t_s)
    if len(tb) < 10:
        raise RecordingError(f"{name}: only {len(tb)} {flow_name} frames")
    offset = float(np.median(tlog - tb))
    dt = frame_spacing_array(tb, T)
    if fc.increment:
        dphi_x, dphi_y = sx, sy
        # a px4 frame's increment covers its own integration time: rescale to the frame spacing
        ok = np.isfinite(integ) & (integ > 0)
        if np.any(ok):
            dphi_x = np.where(ok, sx * dt / np.where(ok, integ, 1.0), sx)
            dphi_y = np.where(ok, sy * dt / np.where(ok, integ, 1.0), sy)
    else:
        dphi_x, dphi_y = sx * dt, sy * dt
    valid = (qual > 0) & np.isfinite(dphi_x) & np.isfinite(dphi_y)

    # gyro
    gname = next(g for g in GYRO_MESSAGES if g in rec)
    g = _from_vehicle(rec.tables[gname], sysid)
    scale = GYRO_MESSAGES[gname]
    gt, gx, gy = _sorted_unique(np.asarray(g["time_usec"], float) * 1e-6, np.asarray(g["xgyro"], float) * scale,
                                np.asarray(g["ygyro"], float) * scale)
    gyro_x = _interp(tb, gt, gx, 1.5 * T)
    gyro_y = _interp(tb, gt, gy, 1.5 * T)

    # range (downward only; outside the sensor's own limits is invalid)
    ds = _from_vehicle(rec.tables["DISTANCE_SENSOR"], sysid)
    ds = ds.select(np.asarray(ds["orientation"]) == DOWNWARD)
    if len(ds) == 0:
        raise RecordingError(f"{name}: no DISTANCE_SENSOR facing down (orientation 25)")
    cur = np.asarray(ds["current_distance"], float)
    ok = (cur >= np.asarray(ds["min_distance"], float)) & (cur <= np.asarray(ds["max_distance"], float))
    rt, rr = _sorted_unique(np.asarray(ds["time_boot_ms"], float) * 1e-3, np.where(ok, cur * 0.01, np.nan))
    range_m = _interp(tb, rt[np.isfinite(rr)], rr[np.isfinite(rr)], 0.25)
    # a reading next to an invalid one is not trusted either
    near = _nearest(tb, rt, 0.25)
    range_m[(near < 0) | ~np.isfinite(rr[np.maximum(near, 0)])] = np.nan

    # attitude estimate
    at = _from_vehicle(rec.tables["ATTITUDE"], sysid)
    att_t, roll, pitch, yaw = _sorted_unique(np.asarray(at["time_boot_ms"], float) * 1e-3,
                                             np.asarray(at["roll"], float), np.asarray(at["pitch"], float),
                                             np.unwrap(np.asarray(at["yaw"], float)))
    roll_k = _interp(tb, att_t, roll, 1.5 * T)
    pitch_k = _interp(tb, att_t, pitch, 1.5 * T)
    yaw_k = _interp(tb, att_t, yaw, 1.5 * T)

    # command active over [t_k, t_k+1]
    roll_u = np.full(len(tb), np.nan)
    pitch_u = np.full(len(tb), np.nan)
    sat = rec.tables.get("SET_ATTITUDE_TARGET")
    if sat is not None and len(sat) and np.any(sat.compid == COMPANION_COMPONENT):
        sat = sat.select(sat.compid == COMPANION_COMPONENT)
        ct, q = _sorted_unique(np.asarray(sat["time_boot_ms"], float) * 1e-3, np.asarray(sat["q"], float))
        cr, cp, _ = quaternion_to_euler(q)
        j = _nearest(tb, ct, 0.4 * T)  # the command computed from frame k carries frame k's time
        has = j >= 0
        # it acts from frame k+1: frame k's active command is the one computed at frame k-1
        roll_u[1:] = np.where(has[:-1], cr[np.maximum(j[:-1], 0)], np.nan)
        pitch_u[1:] = np.where(has[:-1], cp[np.maximum(j[:-1], 0)], np.nan)
        source = "SET_ATTITUDE_TARGET (companion), active from the next frame"
    else:
        atg = _from_vehicle(rec.tables["ATTITUDE_TARGET"], sysid)
        ct, q = _sorted_unique(np.asarray(atg["time_boot_ms"], float) * 1e-3, np.asarray(atg["q"], float))
        cr, cp, _ = quaternion_to_euler(q)
        j = _nearest(tb, ct, 0.6 * T)
        roll_u = np.where(j >= 0, cr[np.maximum(j, 0)], np.nan)
        pitch_u = np.where(j >= 0, cp[np.maximum(j, 0)], np.nan)
        source = "ATTITUDE_TARGET (vehicle)"

    # velocity setpoint (informative)
    vx_set = np.full(len(tb), np.nan)
    vy_set = np.full(len(tb), np.nan)
    pt = rec.tables.get("POSITION_TARGET_LOCAL_NED")
    if pt is not None and len(pt):
        pt = pt.select(pt.compid == COMPANION_COMPONENT) if np.any(pt.compid == COMPANION_COMPONENT) else pt
        if len(pt):
            ptt, pvx, pvy = _sorted_unique(np.asarray(pt["time_boot_ms"], float) * 1e-3,
                                           np.asarray(pt["vx"], float), np.asarray(pt["vy"], float))
            j = _nearest(tb, ptt, 0.6 * T)
            vx_set = np.where(j >= 0, pvx[np.maximum(j, 0)], np.nan)
            vy_set = np.where(j >= 0, pvy[np.maximum(j, 0)], np.nan)

    # truth, for plots only
    tvx = np.full(len(tb), np.nan)
    tvy = np.full(len(tb), np.nan)
    lp = rec.tables.get("LOCAL_POSITION_NED")
    if lp is not None and len(lp):
        lp = _from_vehicle(lp, sysid)
        if len(lp) > 1:
            lt, lvx, lvy = _sorted_unique(np.asarray(lp["time_boot_ms"], float) * 1e-3,
                                          np.asarray(lp["vx"], float), np.asarray(lp["vy"], float))
            vn = _interp(tb, lt, lvx, 0.2)
            ve = _interp(tb, lt, lvy, 0.2)
            c, s = np.cos(yaw_k), np.sin(yaw_k)
            tvx, tvy = c * vn + s * ve, -s * vn + c * ve

    t_report = tb + offset - t0
    good = valid & np.isfinite(gyro_x) & np.isfinite(gyro_y) & np.isfinite(range_m) & (range_m > 0) \
        & np.isfinite(roll_k) & np.isfinite(pitch_k) & np.isfinite(roll_u) & np.isfinite(pitch_u)
    n_bad = int(np.count_nonzero(~good))
    if n_bad:
        notes.append(f"{n_bad} of {len(tb)} flow frames unusable (no command, invalid flow, range, gyro or "
                     f"attitude at the frame)")
    brk = np.ones(len(tb), dtype=bool)
    brk[1:] = np.diff(tb) > 1.5 * T
    seg_all = np.cumsum(brk | ~np.concatenate([[False], good[:-1]]))
    data = FlightData(
        path=str(rec.path), profile=prof.value, profile_reason=reason, frame_s=T, command_source=source,
        t_s=t_report, dt_s=dt, seg=seg_all, dphi_x_rad=dphi_x, dphi_y_rad=dphi_y, gyro_x_rad_s=gyro_x,
        gyro_y_rad_s=gyro_y, range_m=range_m, roll_rad=roll_k, pitch_rad=pitch_k, yaw_rad=yaw_k,
        roll_cmd_rad=roll_u, pitch_cmd_rad=pitch_u, vx_set_m_s=vx_set, vy_set_m_s=vy_set,
        truth_vx_m_s=tvx, truth_vy_m_s=tvy, notes=notes,
        gyro_resolution_rad_s=(1e-3 if scale == 1e-3 else 0.0) / np.sqrt(12.0),
        flow_resolution_rad=(cfg.flow_sensor.q_rad_per_count if prof is Profile.PAPER else 0.0) / np.sqrt(12.0))
    data = data.take(good)
    # keep segments long enough to fit over
    keep = np.zeros(data.n, dtype=bool)
    for a, b in data.segments():
        if data.t_s[b - 1] - data.t_s[a] >= MIN_SEGMENT_S:
            keep[a:b] = True
    if not np.any(keep):
        raise RecordingError(f"{name}: no stretch of {MIN_SEGMENT_S:.0f} s with flow, gyro, range, attitude and "
                             f"a commanded attitude all valid")
    if not np.all(keep):
        data.notes.append(f"{int(np.count_nonzero(~keep))} frames in stretches shorter than {MIN_SEGMENT_S:.0f} s "
                          f"left out")
        data = data.take(keep)
    # the first frame of each segment has no previous frame: its increment is not trusted
    first = np.ones(data.n, dtype=bool)
    first[1:] = np.diff(data.seg) != 0
    data.dphi_x_rad[first] = 0.0
    data.dphi_y_rad[first] = 0.0
    data.dt_s[first] = T
    return data
