"""Replay: the companion's estimator and controller over a recording, one row per flow frame.

    python -m companion replay RECORDING --csv OUT.csv [--config FILE] [--profile P] [--plot OUT.png]
                                         [--gyro {auto,imu,flow}] [--estimator {auto,eq15,tilt,kf}]

The live code path over the recorded messages, fast: the recording is read into columns
(``companion.recordings.load.load_recording``), the vehicle's signals taken from them by
``companion.recordings.signals`` (which sender, which time field, which units, every gyro message as
received), the live core's alignment rules are applied to whole
columns (``core.align_gyro_columns``, ``core.latest_before``, ``core.repeat_mask``: only the
gyro, range, attitude and heartbeat messages received *before* each flow message count, as in
the live loop), gating and eq. 15 run on whole columns (``core.gate_frames``,
``core.estimate_frames``) and the sequential part (``core.run_control``: optional filter and PI)
runs over the frames in order. ``replay_live`` feeds the same recording message by message to the
live ``MessageRouter`` and ``CompanionCore``; the tests hold the two equal.

Per frame, from the recording:
- the velocity setpoint: the companion's POSITION_TARGET_LOCAL_NED (component 191) whose
  ``time_boot_ms`` is the frame's time (the companion sends it after the command of the same
  step, so it is matched by time, not order); else the GCS's latest SET_POSITION_TARGET_LOCAL_NED
  received before the frame, held for ``companion.setpoint_timeout_s`` and then ramped to 0 as
  the live loop does (MANUAL_CONTROL sticks are not replayed: the companion's own
  POSITION_TARGET_LOCAL_NED records what they gave); else 0;
- whether the companion was engaged: the vehicle's latest HEARTBEAT before the frame says
  GUIDED_NOGPS (ArduCopter custom_mode 20) and armed; for a non-ArduPilot autopilot, armed;
  without vehicle heartbeats, always. Control starts afresh (integrator 0) at each engagement;
- truth, when the recording has LOCAL_POSITION_NED: its velocity at the frame's time, rotated
  into body axes by the ATTITUDE yaw;
- the recorded command (SET_ATTITUDE_TARGET from component 191, matched by ``time_boot_ms``,
  as roll and pitch) and estimate (VISION_SPEED_ESTIMATE, matched by ``usec``), when present.

CSV columns (``CSV_COLUMNS``; SI units in the names): ``t_s`` the flow message's log time minus
the recording's first record; ``vx_m_s``, ``vy_m_s`` the estimate the PI used (after the optional
filter; NaN on held frames); ``roll_cmd_rad``, ``pitch_cmd_rad`` the command; ``frame_time_s`` the
flow message's own (boot) time; ``dt_s`` the time the frame covers; ``vx_set_m_s``,
``vy_set_m_s``; ``hold_cause`` a ``core.HoldCause`` name (empty: controlled); ``engaged`` 0/1;
``vx_raw_m_s``, ``vy_raw_m_s`` eq. 15 before the filter; ``scene_rate_x/y_rad_s`` the flow in the
paper's convention; ``flow_x/y_counts`` (paper profile; NaN otherwise); ``quality``;
``gyro_x/y_rad_s`` and ``range_m`` as used; then, when the recording has them, ``truth_vx/vy_m_s``
and the companion's recorded ``rec_roll/pitch_cmd_rad`` and ``rec_vx/vy_m_s``; last
``vx_var_m2_s2``, ``vy_var_m2_s2``, the variance of the estimate when the Kalman filter made it
(``estimator.VelocityKalman``; NaN with the other estimators and on held frames).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion import native
from companion.config import Config, load_config
from companion.errors import RecordingError, UsageError, check_output, writing
from companion.mavlink.inbound import MessageRouter
from companion.mavlink_ids import (
    BODY_FRAMES,
    COMPANION_COMPONENT,
    GUIDED_NOGPS,
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_AUTOPILOT_INVALID,
    MAV_FRAME_LOCAL_NED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    NOT_VEHICLE_TYPES,
)
from companion.recordings.load import (
    MessageTable,
    Recording,
    is_gzip_path,
    load_recording,
    read_recording_bytes,
    recording_name,
)
from companion.recordings.signals import (
    companion_commands,
    companion_table,
    downward_range,
    gyro_as_received,
    time_ms,
    vehicle_attitude,
    vehicle_flow,
    vehicle_table,
)
from companion.recordings.signals import stable_order as _stable_order
from companion.recordings.signals import time_s as message_time_s
from companion.step.core import (
    CAUSE_CODES,
    FILTER_RESET,
    CompanionCore,
    EstimatorOptions,
    GyroSource,
    HoldCause,
    PlausibilityParams,
    StepOutput,
    StepParams,
    TiltFilter,
    VelocityEstimator,
    VelocityKalman,
    align_gyro_columns,
    estimate_frames,
    gate_frames,
    gyro_history_columns,
    gyro_window_mean,
    kalman_columns,
    kalman_measurement,
    kalman_settings,
    latest_before,
    plausibility_columns,
    repeat_mask,
    repeat_window,
    run_control,
)
from companion.step.profiles import FLOW_MESSAGE, FlowColumns, Profile, detect_profile
from companion.step.rules import clip_speed, covered_span, disengaged
from companion.step.setpoint import decayed_setpoint
from companion.tools.csv_format import iter_rows

#: truth is interpolated only between LOCAL_POSITION_NED samples at most this far apart (s)
TRUTH_MAX_GAP_S = 0.25
#: a progress bar for writing the CSV above this many rows
PROGRESS_MIN_FRAMES = 100_000
#: rows of the CSV formatted at a time (each formatting thread has two buffers of this many rows:
#: about 1 MB each, reused, where every fresh page costs its zeroing)
CSV_BLOCK_ROWS = 4096

#: the fields replay reads of each message: the .tlog reader decodes these with the rows, any
#: other when it is first read (``tlog_reader.read_tlog``'s ``fields``), so this is for speed
#: only (tests/test_lazy_fields.py holds it complete on recordings of the three profiles)
_GYRO_FIELDS = ("xgyro", "ygyro", "zgyro", "xacc", "yacc", "zacc")
REPLAY_FIELDS: dict[str, tuple[str, ...]] = {
    "HEARTBEAT": ("type", "autopilot", "base_mode", "custom_mode"),
    "OPTICAL_FLOW": ("time_usec", "flow_x", "flow_y", "flow_comp_m_x", "flow_comp_m_y", "quality", "flow_rate_x",
                     "flow_rate_y"),
    "OPTICAL_FLOW_RAD": ("time_usec", "integration_time_us", "integrated_x", "integrated_y", "integrated_xgyro",
                         "integrated_ygyro", "quality"),
    "RAW_IMU": ("time_usec", *_GYRO_FIELDS),
    "SCALED_IMU": ("time_boot_ms", *_GYRO_FIELDS),
    "HIGHRES_IMU": ("time_usec", *_GYRO_FIELDS),
    "DISTANCE_SENSOR": ("time_boot_ms", "current_distance", "min_distance", "max_distance", "orientation"),
    "ATTITUDE": ("time_boot_ms", "roll", "pitch", "yaw", "rollspeed", "pitchspeed"),
    "LOCAL_POSITION_NED": ("time_boot_ms", "vx", "vy"),
    "SET_ATTITUDE_TARGET": ("time_boot_ms", "q"),
    "POSITION_TARGET_LOCAL_NED": ("time_boot_ms", "vx", "vy"),
    "VISION_SPEED_ESTIMATE": ("usec", "x", "y"),
    "SET_POSITION_TARGET_LOCAL_NED": ("target_component", "coordinate_frame", "vx", "vy"),
}

#: the CSV's columns, in order (truth and recorded columns only when the recording has them)
CSV_COLUMNS = (
    "t_s", "vx_m_s", "vy_m_s", "roll_cmd_rad", "pitch_cmd_rad", "frame_time_s", "dt_s", "vx_set_m_s",
    "vy_set_m_s", "hold_cause", "engaged", "vx_raw_m_s", "vy_raw_m_s", "scene_rate_x_rad_s",
    "scene_rate_y_rad_s", "flow_x_counts", "flow_y_counts", "quality", "gyro_x_rad_s", "gyro_y_rad_s",
    "range_m", "truth_vx_m_s", "truth_vy_m_s", "rec_roll_cmd_rad", "rec_pitch_cmd_rad", "rec_vx_m_s",
    "rec_vy_m_s", "vx_var_m2_s2", "vy_var_m2_s2")
_OPTIONAL = ("truth_vx_m_s", "truth_vy_m_s", "rec_roll_cmd_rad", "rec_pitch_cmd_rad", "rec_vx_m_s", "rec_vy_m_s")
_TIME_COLUMNS = ("t_s", "frame_time_s")


@dataclass
class ReplayResult:
    """Per-frame columns (``CSV_COLUMNS``; ``hold_cause`` holds ``HoldCause`` names, "" = none)
    and what the replay had to say about the recording (one line each)."""

    recording: str
    profile: Profile
    gyro_source: GyroSource
    columns: dict[str, np.ndarray]
    notes: list[str] = field(default_factory=list)
    n_repeats: int = 0

    def __getitem__(self, key: str) -> np.ndarray:
        return self.columns[key]

    def __len__(self) -> int:
        return len(self.columns["t_s"])


# ---------------------------------------------------------------------------------------------
# Selecting the vehicle's messages


def vehicle_engaged(autopilot: Any, base_mode: Any, custom_mode: Any) -> Any:
    """Whether a vehicle HEARTBEAT says the companion is in control: armed and, on ArduPilot,
    in GUIDED_NOGPS (custom_mode 20). Elementwise."""
    armed = (np.asarray(base_mode).astype(np.int64) & MAV_MODE_FLAG_SAFETY_ARMED) != 0
    ardupilot = np.asarray(autopilot) == MAV_AUTOPILOT_ARDUPILOTMEGA
    return armed & (~ardupilot | (np.asarray(custom_mode) == GUIDED_NOGPS))


def _vehicle_heartbeats(rec: Recording, sysid: int) -> MessageTable | None:
    hb = vehicle_table(rec, "HEARTBEAT", sysid)
    if hb is None:
        return None
    own = (hb["autopilot"] != MAV_AUTOPILOT_INVALID) & ~np.isin(hb["type"], NOT_VEHICLE_TYPES)
    hb = hb.select(own)
    return hb if len(hb) else None


def _ms_key(time_s: np.ndarray) -> np.ndarray:
    """A frame time (s) as the whole milliseconds the companion puts in ``time_boot_ms``."""
    with np.errstate(invalid="ignore"):
        k = np.round(np.asarray(time_s, float) * 1e3)
    return np.where(np.isfinite(k), k, -1).astype(np.int64)


def _match_last(keys: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Index of the last message whose key equals each query key, -1 if none."""
    if len(keys) == 0:
        return np.full(len(query), -1, dtype=np.int64)
    order = _stable_order(keys)
    sk = keys[order]
    pos = native.searchsorted(sk, query, side="right") - 1
    ok = (pos >= 0) & (sk[np.maximum(pos, 0)] == query)
    return np.where(ok, order[np.maximum(pos, 0)], -1)


def frame_setpoints(rec: Recording, cfg: Config, sysid: int, flow_record: np.ndarray, flow_log_s: np.ndarray,
                    frame_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """The velocity setpoint (vx, vy m/s, body axes) of each flow message, and where it came from.

    Companion POSITION_TARGET_LOCAL_NED matched by ``time_boot_ms``, else the GCS's latest
    SET_POSITION_TARGET_LOCAL_NED (target component 0 or 191; body frames 8, 9, 12, or
    LOCAL_NED rotated by the vehicle's yaw when it arrived) no older than the setpoint timeout,
    else 0. Non-finite values keep the previous setpoint (as ``CompanionCore.set_setpoint``)."""
    n = len(flow_record)
    sx = np.zeros(n)
    sy = np.zeros(n)
    src = []
    if "SET_POSITION_TARGET_LOCAL_NED" in rec:
        g = rec.tables["SET_POSITION_TARGET_LOCAL_NED"]
        g = g.select(np.isin(g["target_component"], (0, COMPANION_COMPONENT)))
        frame = g["coordinate_frame"]
        gvx = np.asarray(g["vx"], float)
        gvy = np.asarray(g["vy"], float)
        local = frame == MAV_FRAME_LOCAL_NED
        if local.any():  # rotated by the yaw the vehicle reported last before the setpoint arrived
            att = vehicle_attitude(rec, sysid)
            yaw = np.zeros(len(g))
            if att is not None:
                j = latest_before(att.record, g.record)
                yaw_att = att.yaw
                yaw = np.where(j >= 0, yaw_att[np.maximum(j, 0)], 0.0)
                yaw = np.where(np.isfinite(yaw), yaw, 0.0)
            c, s = np.cos(yaw), np.sin(yaw)
            gvx, gvy = np.where(local, c * gvx + s * gvy, gvx), np.where(local, -s * gvx + c * gvy, gvy)
        usable = np.isin(frame, BODY_FRAMES) | local
        g_rec, g_t = g.record[usable], g.t_s[usable]
        gvx, gvy = gvx[usable], gvy[usable]
        if len(g_rec):
            j = latest_before(g_rec, flow_record)
            age = flow_log_s - g_t[np.maximum(j, 0)]
            timeout = cfg.companion.setpoint_timeout_s
            for i in np.flatnonzero(j >= 0).tolist():  # the live loop's hold-then-ramp to 0
                sx[i], sy[i] = decayed_setpoint((float(gvx[j[i]]), float(gvy[j[i]])), (0.0, 0.0), float(age[i]),
                                                timeout)
            src.append("the GCS's SET_POSITION_TARGET_LOCAL_NED")
    pt = companion_table(rec, "POSITION_TARGET_LOCAL_NED", ("time_boot_ms", "vx", "vy"))
    if pt is not None:
        j = _match_last(time_ms(pt), frame_ms)
        hit = j >= 0
        sx = np.where(hit, np.asarray(pt["vx"], float)[np.maximum(j, 0)], sx)
        sy = np.where(hit, np.asarray(pt["vy"], float)[np.maximum(j, 0)], sy)
        src.insert(0, f"the companion's POSITION_TARGET_LOCAL_NED ({int(hit.sum())} frames)")
    # a non-finite setpoint is ignored: the previous one stays (CompanionCore.set_setpoint)
    bad = ~(np.isfinite(sx) & np.isfinite(sy))
    if bad.any():
        idx = np.maximum.accumulate(np.where(~bad, np.arange(n), -1))
        sx = np.where(idx >= 0, sx[np.maximum(idx, 0)], 0.0)
        sy = np.where(idx >= 0, sy[np.maximum(idx, 0)], 0.0)
    vmax = cfg.companion.max_speed_m_s
    sx, sy = clip_speed(sx, vmax), clip_speed(sy, vmax)
    return sx, sy, " then ".join(src) if src else "none in the recording (0)"


# ---------------------------------------------------------------------------------------------
# The replay


@dataclass
class _Frames:
    """Everything the steps need, per flow message of the vehicle (before repeat removal)."""

    fc: FlowColumns
    record: np.ndarray
    log_s: np.ndarray
    setpoint_x: np.ndarray
    setpoint_y: np.ndarray
    engaged: np.ndarray
    notes: list[str]


def _prepare(rec: Recording, cfg: Config, profile: Profile) -> tuple[_Frames, int]:
    name = FLOW_MESSAGE[profile]
    if name not in rec:
        other = [m for m in ("OPTICAL_FLOW", "OPTICAL_FLOW_RAD") if m != name and m in rec]
        hint = f" (it has {other[0]}: try --profile {'px4' if other[0] == 'OPTICAL_FLOW_RAD' else 'ardupilot'})" \
            if other else ""
        raise RecordingError(f"{Path(rec.path).name}: no {name} messages in the recording, nothing to replay"
                             f" with the {profile.value} profile{hint}")
    vf = vehicle_flow(rec, profile, cfg.flow_sensor.q_rad_per_count)
    sysid, flow, fc = vf.sysid, vf.table, vf.columns
    notes = []
    if vf.n_other:
        notes.append(f"ignored {vf.n_other} {name} messages from systems other than {sysid}")
    frame_ms = _ms_key(fc.time_s)
    sx, sy, src = frame_setpoints(rec, cfg, sysid, flow.record, flow.t_s, frame_ms)
    notes.append(f"setpoint from {src}")
    hb = _vehicle_heartbeats(rec, sysid)
    if hb is None:
        engaged = np.ones(len(flow), dtype=bool)
    else:
        j = latest_before(hb.record, flow.record)
        eng_hb = vehicle_engaged(hb["autopilot"], hb["base_mode"], hb["custom_mode"])
        engaged = (j >= 0) & eng_hb[np.maximum(j, 0)]
        notes.append(f"engaged (vehicle armed in GUIDED_NOGPS) for {int(engaged.sum())} of {len(engaged)} "
                     "flow messages")
    return _Frames(fc, flow.record, flow.t_s, sx, sy, engaged, notes), sysid


def _payload(fc: FlowColumns) -> np.ndarray:
    """Column form of ``CompanionCore.payload``."""
    n = len(fc.time_s)

    def col(x: Any) -> np.ndarray:
        return np.broadcast_to(np.asarray(x, dtype=float), (n,))

    return np.stack([col(fc.scene_x), col(fc.scene_y), col(fc.quality), col(fc.integration_s),
                     col(fc.body_x_rad_s), col(fc.body_y_rad_s)], axis=1)


def _take(x: Any, idx: np.ndarray, n: int) -> np.ndarray:
    return np.broadcast_to(np.asarray(x, dtype=float), (n,))[idx]


def replay(rec: Recording, cfg: Config, profile: Profile, options: EstimatorOptions | None = None) -> ReplayResult:
    """Run the companion over ``rec`` (parameters ``cfg``, sensor ``profile``, estimator
    ``options``; default: ``EstimatorOptions()``): one output row per flow frame, repeated and
    out-of-order flow messages dropped as the live core drops them. Raises RecordingError when
    the recording has no flow message of the profile."""
    options = options if options is not None else EstimatorOptions.from_config(cfg)
    gyro_source = options.resolved_gyro(profile)
    p = StepParams.from_config(cfg)
    fr, sysid = _prepare(rec, cfg, profile)
    notes = list(fr.notes)
    fc = fr.fc
    n_msg = len(fr.record)
    t_all = np.asarray(fc.time_s, float)

    # repeated samples: the same payload again within the repeat window is not a new frame
    pl = _payload(fc)
    rep = repeat_mask(t_all, pl, repeat_window(fc.integration_s, p.repeat_window_s, profile, pl))
    keep = np.flatnonzero(~rep)
    n = len(keep)
    if rep.any():
        notes.append(f"{int(rep.sum())} flow messages repeated the last sample (sent faster than the sensor "
                     "updates) or came out of order: not stepped again")
    time_s = t_all[keep]
    record = fr.record[keep]
    scene_x, scene_y = _take(fc.scene_x, keep, n_msg), _take(fc.scene_y, keep, n_msg)
    quality = _take(fc.quality, keep, n_msg)
    integration_s = _take(fc.integration_s, keep, n_msg)

    # the gyro sample aligned with each frame
    gyro_hist = None  # (times, gx, gy, first, last): the live core's gyro history at each frame
    if gyro_source is GyroSource.FLOW:
        gx, gy = _take(fc.body_x_rad_s, keep, n_msg), _take(fc.body_y_rad_s, keep, n_msg)
        gyro_found = ~(np.isnan(gx) | np.isnan(gy))
        if not gyro_found.any():
            notes.append(f"the {profile.value} flow message carries no body rate: every frame holds "
                         "(use --gyro imu)")
    else:
        gyro = gyro_as_received(rec, sysid)
        g_rec, g_t, g_x, g_y = gyro.record, gyro.time_s, gyro.x_rad_s, gyro.y_rad_s
        if len(g_rec) == 0:
            notes.append("no gyro (RAW_IMU, SCALED_IMU or HIGHRES_IMU) from the vehicle: every frame holds")
        else:
            notes.append(f"gyro from {', '.join(gyro.names)}")
        j = align_gyro_columns(g_rec, g_t, record, time_s, p.max_gyro_skew_s)
        if fc.increment:  # the flow covers a window: its rotation is the gyro's mean over it (core.kalman_measurement)
            gyro_hist = (g_t, g_x, g_y, *gyro_history_columns(g_rec, g_t, record))
        gyro_found = j >= 0
        gx = np.where(gyro_found, g_x[np.maximum(j, 0)] if len(g_x) else np.nan, np.nan)
        gy = np.where(gyro_found, g_y[np.maximum(j, 0)] if len(g_y) else np.nan, np.nan)

    # the latest downward range reading received before each frame
    ds = downward_range(rec, sysid)
    if ds is None:
        notes.append("no downward DISTANCE_SENSOR (orientation 25) from the vehicle: every frame holds")
        range_found = np.zeros(n, dtype=bool)
        range_t = range_m = np.full(n, np.nan)
    else:
        j = latest_before(ds.record, record)
        range_found = j >= 0
        range_t = np.where(range_found, ds.time_s[np.maximum(j, 0)], np.nan)
        range_m = np.where(range_found, ds.range_m[np.maximum(j, 0)], np.nan)

    # the attitude for the optional tilt filter
    roll_a = pitch_a = np.full(n, np.nan)
    tilt: TiltFilter | None = options.resolved_tilt(profile)
    estimator = options.resolved_estimator(profile)
    if tilt is not None:
        att = vehicle_attitude(rec, sysid)
        if att is None:
            notes.append("no ATTITUDE from the vehicle: the tilt filter passes eq. 15 through")
        else:
            j = latest_before(att.record, record)
            t_a = np.where(j >= 0, att.time_s[np.maximum(j, 0)], np.nan)
            with np.errstate(invalid="ignore"):
                fresh = (j >= 0) & ((time_s - t_a) <= tilt.max_attitude_age_s)
            roll_a = np.where(fresh, att.roll[np.maximum(j, 0)], np.nan)
            pitch_a = np.where(fresh, att.pitch[np.maximum(j, 0)], np.nan)

    # gating and eq. 15 over all frames at once
    finite_t = np.where(np.isfinite(time_s), time_s, np.nan)
    idx = np.where(np.isfinite(time_s), np.arange(n), -1)
    last_finite = np.maximum.accumulate(idx) if n else idx
    prev_time = np.full(n, np.nan)
    if n > 1:
        prev_time[1:] = np.where(last_finite[:-1] >= 0, finite_t[np.maximum(last_finite[:-1], 0)], np.nan)
    codes = gate_frames(time_s, scene_x, scene_y, quality, gyro_found, gx, gy, range_found, range_t, range_m, p=p)
    codes, vx, vy, dt, rate_x, rate_y = estimate_frames(codes, time_s, prev_time, scene_x, scene_y,
                                                        fc.increment, integration_s, gx, gy, range_m, p=p)
    vx_raw, vy_raw = vx.copy(), vy.copy()
    codes = _cross_frame_checks(rec, sysid, cfg, record, codes, time_s, scene_x, scene_y, gx, gy, vx, vy, range_m)
    vx, vy = np.where(codes == 0, vx, np.nan), np.where(codes == 0, vy, np.nan)
    engaged = fr.engaged[keep]
    sx, sy = fr.setpoint_x[keep], fr.setpoint_y[keep]
    var_x = var_y = np.full(n, np.nan)
    if estimator is VelocityEstimator.KF:
        vx, vy, var_x, var_y = _kalman(rec, sysid, cfg, profile, options, gyro_hist, codes == 0, record, time_s,
                                       integration_s, dt, vx, vy, gx, gy, range_m, notes, p.max_gyro_skew_s)

    # the sequential part: the live loop's run_control over all frames
    _, _, vx_used, vy_used, roll_cmd, pitch_cmd = run_control((0.0, 0.0), FILTER_RESET, codes == 0, engaged, vx, vy,
                                                              roll_a, pitch_a, sx, sy, dt, p=p, tilt=tilt)
    cause = codes.astype(np.int64)
    cause = np.where(disengaged(cause == 0, engaged), CAUSE_CODES.index(HoldCause.DISENGAGED), cause)
    names = np.array([c.name if c is not HoldCause.NONE else "" for c in CAUSE_CODES], dtype=object)
    held = np.bincount(cause, minlength=len(CAUSE_CODES))
    summary = ", ".join(f"{CAUSE_CODES[i].name.lower()} {int(k)}" for i, k in enumerate(held) if i and k)
    if summary:
        notes.append(f"held frames by cause: {summary}")

    cols: dict[str, np.ndarray] = {
        "t_s": fr.log_s[keep] - rec.t0_s,
        "vx_m_s": vx_used, "vy_m_s": vy_used, "roll_cmd_rad": roll_cmd, "pitch_cmd_rad": pitch_cmd,
        "frame_time_s": time_s, "dt_s": dt, "vx_set_m_s": sx, "vy_set_m_s": sy,
        "hold_cause": names[cause], "engaged": engaged.astype(np.int8),
        "vx_raw_m_s": vx_raw, "vy_raw_m_s": vy_raw, "scene_rate_x_rad_s": rate_x, "scene_rate_y_rad_s": rate_y,
        "flow_x_counts": _take(fc.counts_x, keep, n_msg), "flow_y_counts": _take(fc.counts_y, keep, n_msg),
        "quality": quality, "gyro_x_rad_s": gx, "gyro_y_rad_s": gy, "range_m": range_m,
        "vx_var_m2_s2": var_x, "vy_var_m2_s2": var_y,
    }
    cols.update(_truth(rec, sysid, time_s))
    cols.update(_recorded(rec, time_s))
    return ReplayResult(rec.path, profile, gyro_source, cols, notes, int(rep.sum()))


def _kalman(rec: Recording, sysid: int, cfg: Config, profile: Profile, options: EstimatorOptions,
            gyro_hist: tuple[np.ndarray, ...] | None, usable: np.ndarray, record: np.ndarray, time_s: np.ndarray,
            integration_s: np.ndarray, dt: np.ndarray, vx: np.ndarray, vy: np.ndarray, gx: np.ndarray,
            gy: np.ndarray, range_m: np.ndarray, notes: list[str], max_skew_s: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The Kalman filter (``core.kalman_columns``) over the usable frames, with the vehicle's
    ATTITUDE as the live core gets it; eq. 15 passes through where no attitude is fresh. With the
    IMU's gyro (``gyro_hist``) its rotation is the mean over the flow sample's own window, from
    the samples the live core holds at that frame (``core.kalman_measurement``)."""
    settings = options.kalman or kalman_settings(cfg, profile)
    zx, zy = vx.copy(), vy.copy()
    span = covered_span(integration_s, dt)
    if gyro_hist is not None:
        g_t, g_x, g_y, first, last = gyro_hist
        rows = list(zip(g_t.tolist(), g_x.tolist(), g_y.tolist(), strict=True))
        age = settings.flow_sample_age_s
        for i in np.flatnonzero(usable).tolist():
            t1 = float(time_s[i]) - age
            mean = gyro_window_mean(rows[first[i]:last[i] + 1], t1 - float(span[i]), t1, max_skew_s)
            zx[i], zy[i] = kalman_measurement(float(vx[i]), float(vy[i]), float(gx[i]), float(gy[i]), mean,
                                              float(range_m[i]))
    att = vehicle_attitude(rec, sysid)
    if att is None:
        notes.append("no ATTITUDE from the vehicle: the Kalman filter passes eq. 15 through")
        e = np.zeros(0)
        cols: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] = (
            np.zeros(0, np.int64), e, e, e, e, e)
    else:
        cols = (att.record, att.time_s, att.roll, att.pitch, att.rollspeed, att.pitchspeed)
    kf = VelocityKalman(settings)
    gyro = gyro_as_received(rec, sysid)  # the accelerometer of the gyro messages, as the live router takes it
    acc = gyro.accel_m_s2
    accel = None if acc is None else (gyro.record, gyro.time_s, acc[:, 0], acc[:, 1])
    return kalman_columns(kf, usable, record, time_s, span, zx, zy, range_m, *cols, accel=accel)


def _cross_frame_checks(rec: Recording, sysid: int, cfg: Config, record: np.ndarray, codes: np.ndarray,
                        time_s: np.ndarray, scene_x: np.ndarray, scene_y: np.ndarray, gx: np.ndarray, gy: np.ndarray,
                        vx: np.ndarray, vy: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """``core.Plausibility`` over the usable frames in order, as ``CompanionCore.on_flow`` runs it:
    with the latest ATTITUDE rates received before each frame (None when absent or not finite).
    Returns the codes with the vetoed frames' causes."""
    att = vehicle_attitude(rec, sysid)
    if att is not None:
        j = latest_before(att.record, record)
        ar_x = np.where(j >= 0, att.rollspeed[np.maximum(j, 0)], np.nan)
        ar_y = np.where(j >= 0, att.pitchspeed[np.maximum(j, 0)], np.nan)
    else:
        ar_x = ar_y = np.full(len(record), np.nan)
    usable = np.flatnonzero(codes == 0)
    every = len(usable) == len(codes)  # the usual flight: the columns as they are, no copies

    def rows(c: np.ndarray) -> np.ndarray:
        return np.asarray(c, float) if every else np.asarray(c, float)[usable]

    vetoes = plausibility_columns(PlausibilityParams.from_config(cfg),
                                  *(rows(c) for c in (time_s, scene_x, scene_y, gx, gy, vx, vy, range_m, ar_x, ar_y)))
    out = codes.copy()
    for k, cause in vetoes:
        out[usable[k]] = CAUSE_CODES.index(cause)
    return out


def _truth(rec: Recording, sysid: int, time_s: np.ndarray) -> dict[str, np.ndarray]:
    """LOCAL_POSITION_NED velocity at each frame time, in body axes by the ATTITUDE yaw."""
    lp = vehicle_table(rec, "LOCAL_POSITION_NED", sysid)
    if lp is None:
        return {}
    t = message_time_s(lp)
    order = _stable_order(t)
    t = t[order]
    vn = np.asarray(lp["vx"], float)[order]
    ve = np.asarray(lp["vy"], float)[order]
    # valid between two samples at most TRUTH_MAX_GAP_S apart (or on a sample)
    hi = np.clip(native.searchsorted(t, time_s, side="left"), 0, len(t) - 1)
    lo = np.clip(native.searchsorted(t, time_s, side="right") - 1, 0, len(t) - 1)
    with np.errstate(invalid="ignore"):
        ok = (time_s >= t[0]) & (time_s <= t[-1]) & (t[hi] - t[lo] <= TRUTH_MAX_GAP_S)
    vn_f = np.where(ok, np.interp(time_s, t, vn), np.nan)
    ve_f = np.where(ok, np.interp(time_s, t, ve), np.nan)
    att = vehicle_attitude(rec, sysid)
    yaw = np.zeros(len(time_s))
    if att is not None:
        ta = att.time_s
        o = _stable_order(ta)
        yaw = np.interp(time_s, ta[o], np.unwrap(att.yaw[o]))
    c, s = np.cos(yaw), np.sin(yaw)
    return {"truth_vx_m_s": c * vn_f + s * ve_f, "truth_vy_m_s": -s * vn_f + c * ve_f}


def _recorded(rec: Recording, time_s: np.ndarray) -> dict[str, np.ndarray]:
    """The companion's own recorded command and estimate for each frame (NaN where none)."""
    out: dict[str, np.ndarray] = {}
    ms = _ms_key(time_s)
    sat = companion_commands(rec)
    if sat is not None:
        j = _match_last(sat.time_ms, ms)
        out["rec_roll_cmd_rad"] = np.where(j >= 0, sat.roll[np.maximum(j, 0)], np.nan)
        out["rec_pitch_cmd_rad"] = np.where(j >= 0, sat.pitch[np.maximum(j, 0)], np.nan)
    vse = companion_table(rec, "VISION_SPEED_ESTIMATE", ("usec", "x", "y"))
    if vse is not None:
        j = _match_last(time_ms(vse), ms)
        out["rec_vx_m_s"] = np.where(j >= 0, np.asarray(vse["x"], float)[np.maximum(j, 0)], np.nan)
        out["rec_vy_m_s"] = np.where(j >= 0, np.asarray(vse["y"], float)[np.maximum(j, 0)], np.nan)
    return out


# ---------------------------------------------------------------------------------------------
# The reference: the live path, message by message


def replay_live(path: str | Path, cfg: Config, profile: Profile, options: EstimatorOptions | None = None
                ) -> list[StepOutput]:
    """Feed a .tlog message by message (pymavlink) to the live ``MessageRouter`` and
    ``CompanionCore``, with the setpoint and engagement of each flow message taken from the
    recording as ``replay`` takes them. Returns the step output of every new frame (repeats
    dropped). Slow (pymavlink); it is the yardstick ``replay`` is tested against. A .tlog.gz is
    given to pymavlink decompressed into a temporary file."""
    rec = load_recording(path)
    if is_gzip_path(path):
        with tempfile.TemporaryDirectory(prefix="flowhold-replay-") as tmp:
            plain = Path(tmp) / recording_name(path)
            plain.write_bytes(read_recording_bytes(path))
            return _replay_live(rec, plain, cfg, profile, options)
    return _replay_live(rec, Path(path), cfg, profile, options)


def _replay_live(rec: Recording, path: Path, cfg: Config, profile: Profile, options: EstimatorOptions | None
                 ) -> list[StepOutput]:
    """``replay_live`` with the recording read (``rec``) and ``path`` a plain .tlog of it."""
    from pymavlink import mavutil

    fr, sysid = _prepare(rec, cfg, profile)
    core = CompanionCore(cfg, profile, options)
    core.set_engaged(_vehicle_heartbeats(rec, sysid) is None)  # with heartbeats: not before the first says so
    router = MessageRouter(core, profile, vehicle_sysid=sysid)
    flow_name = FLOW_MESSAGE[profile]
    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    outputs: list[StepOutput] = []
    k = 0
    try:
        for msg in _messages(conn):
            mtype = msg.get_type()
            src = msg.get_srcSystem()
            if mtype == "HEARTBEAT" and src == sysid and msg.autopilot != MAV_AUTOPILOT_INVALID \
                    and msg.type not in NOT_VEHICLE_TYPES:
                core.set_engaged(bool(vehicle_engaged(msg.autopilot, msg.base_mode, msg.custom_mode)))
                continue
            if mtype in ("SET_POSITION_TARGET_LOCAL_NED", "MANUAL_CONTROL"):
                continue  # the per-frame setpoint below stands for them
            if mtype == flow_name and src == sysid:
                if k >= len(fr.setpoint_x):
                    raise RecordingError("pymavlink and the column reader disagree on the flow messages")
                core.set_setpoint(float(fr.setpoint_x[k]), float(fr.setpoint_y[k]))
                k += 1
            out = router.handle(msg)
            if out is not None and not out.repeat:
                outputs.append(out)
    finally:
        conn.close()
    return outputs


def _messages(conn: Any) -> Iterator[Any]:
    while True:
        msg = conn.recv_match(blocking=False)
        if msg is None:
            return
        if msg.get_type() != "BAD_DATA":
            yield msg


# ---------------------------------------------------------------------------------------------
# Output


def _csv_formats(result: ReplayResult) -> tuple[list[str], list[str]]:
    """The CSV's column names (``CSV_COLUMNS`` present in the result, then any others) and the
    ``%`` format of each: ``%s`` names, ``%d`` integers, ``%.12g`` times, ``%.9g`` the rest."""
    names = [c for c in CSV_COLUMNS if c in result.columns]
    names += [c for c in result.columns if c not in names]
    fmts = []
    for c in names:
        col = result.columns[c]
        if col.dtype == object:
            fmts.append("%s")
        elif np.issubdtype(col.dtype, np.integer):
            fmts.append("%d")
        else:
            fmts.append("%.12g" if c in _TIME_COLUMNS else "%.9g")
    return names, fmts


def write_csv(result: ReplayResult, path: str | Path, *, progress: bool = False) -> list[str]:
    """Write the per-frame CSV (``CSV_COLUMNS`` present in the result; 9 significant digits, 12
    for times; NaN as ``nan``): the text of Python's ``%`` formatting, produced compiled or
    vectorised (``companion.tools.csv_format.iter_rows``) and written piece by piece. ``progress``: a
    bar on stderr for long results.
    Returns the columns written."""
    names, fmts = _csv_formats(result)
    values = [result.columns[c] for c in names]
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    bar = None
    if progress and len(result) > PROGRESS_MIN_FRAMES:
        from tqdm import tqdm

        bar = tqdm(total=len(result), desc=f"writing {p.name}", unit="row", file=sys.stderr, leave=False)
    try:
        with open(p, "wb") as fh:
            fh.write((",".join(names) + "\n").encode())
            chunk = CSV_BLOCK_ROWS
            for a, part in zip(range(0, len(result), chunk), iter_rows(values, fmts, chunk), strict=True):
                fh.write(part)  # before the next piece: it may reuse this one's buffer
                if bar is not None:
                    bar.update(min(chunk, len(result) - a))
    finally:
        if bar is not None:
            bar.close()
    return names


def _pyarrow() -> tuple[Any, Any]:
    """pyarrow and pyarrow.parquet, or a one-line ``UsageError`` saying how to install them."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise UsageError("--parquet needs pyarrow: pip install 'flowhold[parquet]' (or pip install pyarrow)") from None
    return pa, pq


def write_parquet(result: ReplayResult, path: str | Path) -> list[str]:
    """Write the per-frame columns (the CSV's, same names and order) as a Parquet file: float64
    and integer columns as they are, ``hold_cause`` as strings. Needs pyarrow (the ``parquet``
    extra: ``pip install 'flowhold[parquet]'``); without it a one-line ``UsageError``.
    Returns the columns written."""
    pa, pq = _pyarrow()
    names, _ = _csv_formats(result)
    arrays = []
    for c in names:
        col = result.columns[c]
        arrays.append(pa.array(col.tolist(), type=pa.string()) if col.dtype == object else pa.array(col))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.table(arrays, names=names), p)
    return names


def _options(args: argparse.Namespace, cfg: Config) -> EstimatorOptions:
    """The config's ``[companion]`` choices, overridden by ``--gyro`` / ``--estimator`` when given
    (``--filter`` none/tilt: the older spelling of ``--estimator`` eq15/tilt)."""
    gyro = GyroSource(getattr(args, "gyro", None) or cfg.companion.gyro_source)
    older = {"none": "eq15", "tilt": "tilt", None: None}[getattr(args, "filter", None)]
    est = VelocityEstimator(getattr(args, "estimator", None) or older or cfg.companion.velocity_estimator)
    return EstimatorOptions(gyro, TiltFilter() if est is VelocityEstimator.TILT else None, est)


def run_cli(args: argparse.Namespace) -> int:
    """``python -m companion replay``: CSV (and plot) of the companion over a recording."""
    parquet = getattr(args, "parquet", None)
    if not args.csv and not parquet:
        raise UsageError("replay needs an output: --csv OUT.csv and/or --parquet OUT.parquet")
    if args.csv:
        check_output(args.csv, "--csv")
    if parquet:
        check_output(parquet, "--parquet")
        _pyarrow()  # before the recording is read
    if args.plot:
        check_output(args.plot, "--plot")
    cfg = load_config(args.config)
    rec = load_recording(args.recording, sensor_config=getattr(args, "sensor_config", None),
                         progress=sys.stderr.isatty(), fields=REPLAY_FIELDS)
    if args.profile:
        profile = Profile(args.profile)
        why = "given"
    else:
        detected, why = detect_profile(rec)
        profile = Profile(detected)
    result = replay(rec, cfg, profile, _options(args, cfg))
    outputs = []
    if args.csv:
        with writing("--csv", args.csv):
            names = write_csv(result, args.csv, progress=sys.stderr.isatty())
        outputs.append(args.csv)
    if parquet:
        with writing("--parquet", parquet):
            names = write_parquet(result, parquet)
        outputs.append(parquet)
    err = sys.stderr
    estimator = _options(args, cfg).resolved_estimator(profile)
    print(f"profile {profile.value} ({why}); gyro {result.gyro_source.value}; estimator {estimator.value}", file=err)
    for line in rec.notes + result.notes:
        print(line, file=err)
    print(f"{len(result)} frames -> {' and '.join(outputs)} ({len(names)} columns)", file=err)
    if "truth_vx_m_s" in result.columns:
        e = _rms_vs_truth(result)
        if e is not None:
            print(f"estimate - LOCAL_POSITION_NED (body axes), RMS over the engaged frames: "
                  f"x {e[0]:.4f} m/s, y {e[1]:.4f} m/s", file=err)
    if args.plot:
        from companion.tools.plot import plot_replay

        with writing("--plot", args.plot):
            plot_replay(result, args.plot)
        print(f"plot -> {args.plot}", file=err)
    return 0


def _rms_vs_truth(result: ReplayResult) -> tuple[float, float] | None:
    c = result.columns
    ok = (c["engaged"] == 1) & np.isfinite(c["vx_m_s"]) & np.isfinite(c["truth_vx_m_s"])
    if not ok.any():
        return None
    return (float(np.sqrt(np.mean((c["vx_m_s"][ok] - c["truth_vx_m_s"][ok]) ** 2))),
            float(np.sqrt(np.mean((c["vy_m_s"][ok] - c["truth_vy_m_s"][ok]) ** 2))))

