"""PX4 ULog files (.ulg, or .ulg.gz: decompressed in memory) into the columnar ``Recording``,
in MAVLink names and units.

The tables come out as if PX4 had streamed them over MAVLink, so the ``px4`` profile of
CONVENTIONS.md applies unchanged (``profile_hint = "px4"``). PX4's uORB flow convention (RH
rotation about a body axis gives a positive ``pixel_flow``) is the MAVLink OPTICAL_FLOW_RAD
convention: PX4's MAVLink receiver copies ``integrated_x/y`` into ``pixel_flow[0]/[1]`` without a
sign change, so the inverse mapping is the identity (docs/importers.md has the references).

Mapping (topic.field, unit -> table.field):

* vehicle_optical_flow.pixel_flow[0], [1] (rad over the interval) -> OPTICAL_FLOW_RAD
  integrated_x, integrated_y; delta_angle[0..2] (rad) -> integrated_x/y/zgyro;
  integration_timespan_us -> integration_time_us; timestamp_sample -> time_usec (us);
  quality -> quality; distance_m (m, NaN) -> distance (-1 = unknown). The older optical_flow
  topic (pixel_flow_x/y_integral, gyro_x/y/z_rate_integral, integration_timespan,
  ground_distance_m) maps the same way; sensor_optical_flow is the last resort (sensor frame).
* sensor_combined.gyro_rad[3] (rad/s), accelerometer_m_s2[3] (m/s^2) -> RAW_IMU x/y/zgyro
  (mrad/s), x/y/zacc (milli-g); vehicle_angular_velocity.xyz[3] if there is no sensor_combined.
* distance_sensor.current/min/max_distance (m), orientation -> DISTANCE_SENSOR (cm), orientation
  (25 = ROTATION_DOWNWARD_FACING = MAV_SENSOR_ROTATION_PITCH_270).
* vehicle_attitude.q[4] ([w, x, y, z]) -> ATTITUDE roll, pitch, yaw (ZYX, rad); rollspeed..
  from the nearest vehicle_angular_velocity (else sensor_combined) sample.
* vehicle_attitude_setpoint.q_d[4] -> ATTITUDE_TARGET q; thrust = |thrust_body|; body rates
  from the nearest vehicle_rates_setpoint (as PX4's own ATTITUDE_TARGET stream).

Every table's ``t_s`` is the topic's ``timestamp`` in seconds (boot time); ``record`` orders
all rows by time; sysid 1, compid 1. Instance 0 (``multi_id`` 0) of each topic is used,
except distance_sensor, whose instances all go into DISTANCE_SENSOR with ``id`` = multi_id.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path
from typing import BinaryIO

import numpy as np

from companion.errors import RecordingError
from companion.mavlink_ids import MAV_DISTANCE_SENSOR_UNKNOWN
from companion.progress import StageCallback
from companion.recordings.columnar import MessageTable, Recording, open_recording
from companion.recordings.importers.common import GRAVITY_M_S2, Columns, assign_records, build_table, nearest_index
from companion.rotation import quaternions_to_euler

ULOG_MAGIC = b"ULog\x01\x12\x35"
#: flow topics in order of preference
FLOW_TOPICS = ("vehicle_optical_flow", "optical_flow", "sensor_optical_flow")
TOPICS = FLOW_TOPICS + ("sensor_combined", "vehicle_angular_velocity", "distance_sensor", "vehicle_attitude",
                        "vehicle_attitude_setpoint", "vehicle_rates_setpoint")

#: message types that end the definitions section: add-logged 'A', logging 'L', tagged 'C'
_DATA_SECTION_TYPES = frozenset(b"ALC")
#: pyulog treats a definitions message above this size as corruption
_MAX_DEFINITION_SIZE = 10000

#: fields a topic must carry for this importer to use it
_REQUIRED: dict[str, tuple[str, ...]] = {
    "vehicle_optical_flow": ("pixel_flow[0]", "pixel_flow[1]", "integration_timespan_us", "quality"),
    "sensor_optical_flow": ("pixel_flow[0]", "pixel_flow[1]", "integration_timespan_us", "quality"),
    "optical_flow": ("pixel_flow_x_integral", "pixel_flow_y_integral", "integration_timespan", "quality"),
    "sensor_combined": ("gyro_rad[0]", "gyro_rad[1]", "gyro_rad[2]"),
    "vehicle_angular_velocity": ("xyz[0]", "xyz[1]", "xyz[2]"),
    "distance_sensor": ("current_distance", "min_distance", "max_distance", "orientation"),
    "vehicle_attitude": ("q[0]", "q[1]", "q[2]", "q[3]"),
    "vehicle_attitude_setpoint": ("q_d[0]", "q_d[1]", "q_d[2]", "q_d[3]"),
    "vehicle_rates_setpoint": ("roll", "pitch", "yaw"),
}


#: the stages ``read_ulog`` reports to its ``progress`` callback, in order
STAGES = ("read", "parsed", "tables")


def read_ulog(path: str | Path, *, progress: StageCallback = None) -> Recording:
    """Read a PX4 ULog into MAVLink-named tables (see the module table).

    Raises ``RecordingError`` (one line) when the file is missing, is not a ULog, or holds no
    optical-flow topic. Missing gyro, range or attitude topics are skipped with a note.
    ``progress`` is called with each of ``STAGES`` as it ends (``companion.progress.Stages``).
    """
    done = progress or (lambda _stage: None)
    p = Path(path)
    with open_recording(p) as fh:  # a .ulg.gz: decompressed in memory
        head = fh.read(16)
        if len(head) < 16 or head[:7] != ULOG_MAGIC:
            raise RecordingError(f"{p.name}: not a PX4 ULog file (no 'ULog' header)")
        problem = _definitions_problem(fh)
        if problem:
            raise RecordingError(f"{p.name}: damaged ULog definitions section ({problem})")
        fh.seek(0)
        done(STAGES[0])
        topics, notes = _load(p, fh)
        done(STAGES[1])
    with np.errstate(invalid="ignore", over="ignore"):  # damaged floats (NaN, sNaN, inf) pass through
        rec = _tables(p, topics, notes)
    done(STAGES[2])
    return rec


def _tables(p: Path, topics: dict[tuple[str, int], Columns], notes: list[str]) -> Recording:
    """``read_ulog`` after parsing: map the topics to tables."""

    flow_name = next((t for t in FLOW_TOPICS if (t, 0) in topics), None)
    if flow_name is None:
        why = "".join(f"; {n}" for n in notes if n.startswith(FLOW_TOPICS))
        raise RecordingError(f"{p.name}: no optical flow in the ULog (none of {', '.join(FLOW_TOPICS)}){why}")
    tables: dict[str, MessageTable] = {}

    def add(table: MessageTable) -> None:
        tables[table.name] = table

    add(_flow(flow_name, topics[(flow_name, 0)], notes))

    gyro = _raw_imu(topics.get(("sensor_combined", 0)), topics.get(("vehicle_angular_velocity", 0)), notes)
    if gyro is not None:
        add(gyro)

    ranges = sorted((mid, d) for (name, mid), d in topics.items() if name == "distance_sensor")
    if ranges:
        add(_distance_sensor(ranges))
    else:
        notes.append("no distance_sensor topic: range missing")

    rate_src = _rate_source(topics)
    att = topics.get(("vehicle_attitude", 0))
    if att is None:
        notes.append("no vehicle_attitude topic: attitude missing")
    else:
        add(_attitude(att, rate_src, notes))
    sp = topics.get(("vehicle_attitude_setpoint", 0))
    if sp is None:
        notes.append("no vehicle_attitude_setpoint topic: attitude target missing")
    else:
        add(_attitude_target(sp, topics.get(("vehicle_rates_setpoint", 0))))

    assign_records(tables, {n: np.zeros(len(t)) for n, t in tables.items()}, notes)
    return Recording(path=str(p), tables=tables, source_format="ulog", notes=notes, profile_hint="px4")


def _definitions_problem(fh: BinaryIO) -> str | None:
    """Walk the definitions section (after the 16-byte header) up to the first add-logged or
    logging message; describe the first damage found, or None.

    pyulog resynchronises inside a damaged definitions section by stepping one byte at a time,
    and near the end of the file that step can go backwards forever; a damaged section is
    refused here instead (the topic formats it holds could not be trusted anyway).
    """
    pos = 16
    while True:
        header = fh.read(3)
        if len(header) < 3:
            return f"no logged data after byte {pos}"
        size, kind = int.from_bytes(header[:2], "little"), header[2]
        if kind in _DATA_SECTION_TYPES:
            return None
        if kind == 0 or size == 0 or size > _MAX_DEFINITION_SIZE or len(fh.read(size)) < size:
            return f"bad message header at byte {pos}"
        pos += 3 + size


def _load(p: Path, fh: BinaryIO) -> tuple[dict[tuple[str, int], Columns], list[str]]:
    """Parse the open file ``fh`` (of ``p``) with pyulog (only the topics used); ``{(topic,
    multi_id): columns}`` and notes."""
    from pyulog import ULog

    sink = io.StringIO()
    try:
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            ulog = ULog(fh, message_name_filter_list=list(TOPICS), disable_str_exceptions=True)
    except Exception as exc:  # pyulog raises ULogException, struct.error, ValueError, ...
        raise RecordingError(f"{p.name}: ULog could not be parsed ({exc})") from None
    notes: list[str] = []
    if ulog.file_corruption:
        notes.append("ULog: corrupt stretches were skipped by the parser")
    if ulog.dropouts:
        total_ms = sum(int(d.duration) for d in ulog.dropouts)
        notes.append(f"ULog: {len(ulog.dropouts)} logger dropouts, {total_ms} ms in total")
    topics: dict[tuple[str, int], Columns] = {}
    for d in ulog.data_list:
        if not len(d.data.get("timestamp", ())):
            continue
        missing = [f for f in _REQUIRED.get(d.name, ()) if f not in d.data]
        if missing:
            notes.append(f"{d.name} lacks {', '.join(missing)} (unsupported message version): skipped")
            continue
        topics[(d.name, int(d.multi_id))] = dict(d.data)
    rot = ulog.initial_parameters.get("SENS_FLOW_ROT")
    if rot not in (None, 0):
        notes.append(f"SENS_FLOW_ROT = {rot}: vehicle_optical_flow is already rotated to the body frame")
    return topics, notes


def _array(c: Columns, name: str, n: int) -> list[np.ndarray]:
    """The flattened array field ``name[0..n-1]`` as float64 columns."""
    return [c[f"{name}[{i}]"].astype(np.float64) for i in range(n)]


def _flow(topic: str, c: Columns, notes: list[str]) -> MessageTable:
    """A flow topic -> OPTICAL_FLOW_RAD (identity mapping of the signs, see the module doc)."""
    ts = c["timestamp"].astype(np.int64)
    n = len(ts)
    if topic == "optical_flow":
        ix, iy = c["pixel_flow_x_integral"], c["pixel_flow_y_integral"]
        gyro = [c.get(f"gyro_{a}_rate_integral", np.full(n, np.nan)) for a in "xyz"]
        span = c["integration_timespan"]
        dist = c.get("ground_distance_m", np.full(n, np.nan))
        t_sample = ts
        sensor_id = c.get("sensor_id", np.zeros(n)).astype(np.uint8)
        dt_dist = c.get("time_since_last_sonar_update", np.zeros(n))
    else:
        ix, iy = _array(c, "pixel_flow", 2)
        gyro = _array(c, "delta_angle", 3) if "delta_angle[0]" in c else [np.full(n, np.nan)] * 3
        span = c["integration_timespan_us"]
        dist = c.get("distance_m", np.full(n, np.nan))
        t_sample = c["timestamp_sample"].astype(np.int64) if "timestamp_sample" in c else ts
        sensor_id = np.zeros(n, np.uint8)
        dt_dist = np.zeros(n)
        if topic == "sensor_optical_flow":
            notes.append("flow from sensor_optical_flow (sensor frame: SENS_FLOW_ROT not applied)")
    dist = np.asarray(dist, dtype=np.float64)
    fields: Columns = {
        "time_usec": t_sample,
        "sensor_id": sensor_id,
        "integration_time_us": np.asarray(span).astype(np.int64),
        "integrated_x": np.asarray(ix, dtype=np.float64),
        "integrated_y": np.asarray(iy, dtype=np.float64),
        "integrated_xgyro": np.asarray(gyro[0], dtype=np.float64),
        "integrated_ygyro": np.asarray(gyro[1], dtype=np.float64),
        "integrated_zgyro": np.asarray(gyro[2], dtype=np.float64),
        "temperature": np.zeros(n, np.int16),
        "quality": c["quality"].astype(np.uint8),
        "time_delta_distance_us": np.asarray(dt_dist).astype(np.int64),
        "distance": np.where(np.isfinite(dist) & (dist >= 0), dist, -1.0),
    }
    return build_table("OPTICAL_FLOW_RAD", ts * 1e-6, fields)


def _raw_imu(sc: Columns | None, av: Columns | None, notes: list[str]) -> MessageTable | None:
    """sensor_combined (preferred) or vehicle_angular_velocity -> RAW_IMU (mrad/s, milli-g)."""
    if sc is not None:
        ts = sc["timestamp"].astype(np.int64)
        acc = (_array(sc, "accelerometer_m_s2", 3) if "accelerometer_m_s2[0]" in sc
               else [np.full(len(ts), np.nan)] * 3)
        gyro = _array(sc, "gyro_rad", 3)
    elif av is not None:
        ts = av["timestamp"].astype(np.int64)
        acc = [np.full(len(ts), np.nan)] * 3
        gyro = _array(av, "xyz", 3)
        notes.append("no sensor_combined topic: RAW_IMU from vehicle_angular_velocity, accelerations NaN")
    else:
        notes.append("no sensor_combined or vehicle_angular_velocity topic: gyro missing")
        return None
    src = sc if sc is not None else av
    assert src is not None
    t_sample = src["timestamp_sample"].astype(np.int64) if "timestamp_sample" in src else ts
    fields: Columns = {"time_usec": t_sample}
    for ax, a in zip("xyz", acc, strict=True):
        fields[f"{ax}acc"] = a / GRAVITY_M_S2 * 1000.0
    for ax, g in zip("xyz", gyro, strict=True):
        fields[f"{ax}gyro"] = g * 1000.0
    fields["id"] = np.zeros(len(ts), np.uint8)
    return build_table("RAW_IMU", ts * 1e-6, fields)


def _distance_sensor(instances: list[tuple[int, Columns]]) -> MessageTable:
    """All distance_sensor instances -> DISTANCE_SENSOR (cm), ``id`` = multi_id."""
    parts: list[Columns] = []
    for mid, c in instances:
        n = len(c["timestamp"])
        sq = c["signal_quality"].astype(np.int64) if "signal_quality" in c else np.full(n, -1)
        var = c["variance"].astype(np.float64) if "variance" in c else np.zeros(n)
        parts.append({
            "t": c["timestamp"].astype(np.int64),
            "min_distance": c["min_distance"].astype(np.float64) * 100.0,
            "max_distance": c["max_distance"].astype(np.float64) * 100.0,
            "current_distance": c["current_distance"].astype(np.float64) * 100.0,
            "type": (c["type"].astype(np.uint8) if "type" in c
                     else np.full(n, MAV_DISTANCE_SENSOR_UNKNOWN, np.uint8)),
            "id": np.full(n, mid, np.uint8),
            "orientation": c["orientation"].astype(np.uint8),
            # MAVLink: cm^2, 255 = unknown
            "covariance": np.where(var > 0, np.clip(np.round(var * 1e4), 0, 254), 255).astype(np.uint8),
            # PX4: -1 unknown, 0 invalid, 1-100 %; MAVLink: 0 unknown, 1 invalid, 100 best
            "signal_quality": np.where(sq < 0, 0, np.clip(sq, 1, 100)).astype(np.uint8),
        })
    cols = {k: np.concatenate([part[k] for part in parts]) for k in parts[0]}
    t = cols.pop("t")
    order = np.argsort(t, kind="stable")
    fields = {"time_boot_ms": t[order] / 1000.0, **{k: v[order] for k, v in cols.items()}}
    return build_table("DISTANCE_SENSOR", t[order] * 1e-6, fields)


def _rate_source(topics: dict[tuple[str, int], Columns]) -> tuple[np.ndarray, list[np.ndarray]] | None:
    """Body rates for ATTITUDE: vehicle_angular_velocity (what PX4 streams), else sensor_combined."""
    av = topics.get(("vehicle_angular_velocity", 0))
    if av is not None and "xyz[0]" in av:
        return av["timestamp"].astype(np.int64) * 1e-6, _array(av, "xyz", 3)
    sc = topics.get(("sensor_combined", 0))
    if sc is not None and "gyro_rad[0]" in sc:
        return sc["timestamp"].astype(np.int64) * 1e-6, _array(sc, "gyro_rad", 3)
    return None


def _spacing(t: np.ndarray) -> float:
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 0.02


def _attitude(c: Columns, rates: tuple[np.ndarray, list[np.ndarray]] | None,
              notes: list[str]) -> MessageTable:
    """vehicle_attitude.q -> ATTITUDE (ZYX Euler, rad) + the nearest body-rate sample (rad/s)."""
    ts = c["timestamp"].astype(np.int64)
    roll, pitch, yaw = quaternions_to_euler(np.stack(_array(c, "q", 4), axis=-1))
    n = len(ts)
    speeds = [np.full(n, np.nan) for _ in range(3)]
    if rates is None:
        notes.append("no body-rate topic: ATTITUDE rates are NaN")
    else:
        t_rate, xyz = rates
        idx = nearest_index(t_rate, ts * 1e-6, _spacing(t_rate))
        hit = idx >= 0
        for s, r in zip(speeds, xyz, strict=True):
            s[hit] = r[idx[hit]]
        if not hit.all():
            notes.append(f"vehicle_attitude: {int((~hit).sum())} of {n} rows have no body-rate sample "
                         "within one rate period: their rates are NaN")
    fields = {"time_boot_ms": ts / 1000.0, "roll": roll, "pitch": pitch, "yaw": yaw,
              "rollspeed": speeds[0], "pitchspeed": speeds[1], "yawspeed": speeds[2]}
    return build_table("ATTITUDE", ts * 1e-6, fields)


def _attitude_target(c: Columns, rsp: Columns | None) -> MessageTable:
    """vehicle_attitude_setpoint (+ nearest vehicle_rates_setpoint) -> ATTITUDE_TARGET, as PX4's
    own ATTITUDE_TARGET stream fills it (q = q_d, thrust = |thrust_body|)."""
    ts = c["timestamp"].astype(np.int64)
    n = len(ts)
    thrust = (np.linalg.norm(np.stack(_array(c, "thrust_body", 3), axis=-1), axis=-1)
              if "thrust_body[0]" in c else np.full(n, np.nan))
    body = [np.full(n, np.nan) for _ in range(3)]
    if rsp is not None and all(k in rsp for k in ("roll", "pitch", "yaw")):
        t_r = rsp["timestamp"].astype(np.int64) * 1e-6
        idx = nearest_index(t_r, ts * 1e-6, _spacing(t_r))
        hit = idx >= 0
        for b, k in zip(body, ("roll", "pitch", "yaw"), strict=True):
            b[hit] = rsp[k].astype(np.float64)[idx[hit]]
    have = np.isfinite(body[0]) & np.isfinite(body[1]) & np.isfinite(body[2])
    fields = {
        "time_boot_ms": ts / 1000.0,
        "type_mask": np.where(have, 0, 7).astype(np.uint8),
        "q": np.stack(_array(c, "q_d", 4), axis=-1),
        "body_roll_rate": body[0],
        "body_pitch_rate": body[1],
        "body_yaw_rate": body[2],
        "thrust": thrust,
    }
    return build_table("ATTITUDE_TARGET", ts * 1e-6, fields)
