"""One signal path: a recording's messages -> the vehicle's signals in SI units (issue 13).

Replay, the closed-loop diagnosis (``diagnose.channels``), the sensor-only diagnosis
(``sensor_diagnose.series``) and the simulated vehicle's recording run take their signals from
here, so that each rule below is written once. What each tool then does with the samples
(the live core's alignment, interpolation onto the frame grid, matching by time) stays its own.

**Which sender.** The vehicle is the system that sent the most of the profile's flow messages
(``columnar.vehicle_sysid``; on a tie the first); its signals are the messages of that system
(``vehicle_table``), as the live ``MessageRouter`` takes them. The companion's are those of
component 191 (``COMPANION_COMPONENT``; ``companion_table``), whichever system it uses.

**Which time field.** Each message's own (``profiles.TIME_FIELDS``, the live loop's too;
CONVENTIONS.md): RAW_IMU and HIGHRES_IMU ``time_usec`` (us), SCALED_IMU ``time_boot_ms``,
DISTANCE_SENSOR, ATTITUDE, ATTITUDE_TARGET, SET_ATTITUDE_TARGET, LOCAL_POSITION_NED and
POSITION_TARGET_LOCAL_NED ``time_boot_ms`` (ms), VISION_SPEED_ESTIMATE ``usec``; the flow
message's by the sensor profile (``profiles.flow_columns``: ArduPilot fills OPTICAL_FLOW
``time_usec`` with milliseconds). ``time_s`` gives seconds (a gyro's through whole
microseconds: one instant, one time, whichever gyro message told it), ``time_ms`` the whole
milliseconds the messages are matched on.

**Which unit conversion.** Gyro: RAW_IMU and SCALED_IMU mrad/s, HIGHRES_IMU rad/s
(``profiles.GYRO_MESSAGES``) -> rad/s; an int16 mrad/s field at its limit
(``profiles.INT16_CLIP``) has clipped and the rate is unknown: NaN (the live loop's rule,
``inbound.MessageRouter``). Accelerometer: milli-g, HIGHRES_IMU m/s^2 -> m/s^2. DISTANCE_SENSOR:
cm -> m, only orientation 25 (facing down) is altitude, a reading outside the sensor's own
[min, max] is invalid. Attitude quaternions -> roll, pitch (``rotation.quaternions_to_euler``).

**Which gyro message.** Every gyro message of the contract: RAW_IMU, SCALED_IMU, HIGHRES_IMU
(``profiles.GYRO_MESSAGES``, in order of preference), and the flow message's own body rates
(``profiles.FlowColumns.body_*``: ArduPilot ``flow_rate - flow_comp_m``, PX4 ``integrated_*gyro``).
The companion takes every gyro message of the vehicle as it arrives (``gyro_as_received``: what
replay feeds the live core's history); the analyses take the vehicle's gyro as one sensor, the
first of the three messages in that order the vehicle sent (``gyro_sensor``), whose samples keep
one resolution and rate.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cached_property

import numpy as np

from companion.mavlink_ids import COMPANION_COMPONENT, DOWNWARD
from companion.recordings.columnar import MessageTable, Recording, vehicle_sysid
from companion.rotation import quaternions_to_euler
from companion.step.profiles import (
    FLOW_MESSAGE,
    GYRO_MESSAGES,
    INT16_CLIP,
    TIME_FIELDS,
    FlowColumns,
    Profile,
    accel_m_s2,
    flow_columns,
)


def stable_order(keys: np.ndarray) -> np.ndarray:
    """``np.argsort(keys, kind="stable")``, without the sort when the keys are already in
    order (a recording's times and sequence numbers nearly always are)."""
    if len(keys) < 2 or bool(np.all(keys[1:] >= keys[:-1])):  # False with a NaN: then sorted
        return np.arange(len(keys))
    return np.argsort(keys, kind="stable")


# ---------------------------------------------------------------------------------------------
# Senders and time fields


def vehicle_id(rec: Recording, profile: Profile) -> int:
    """The vehicle's system id: the most frequent sender of the profile's flow message
    (``columnar.vehicle_sysid``). RecordingError when the recording has none."""
    return vehicle_sysid(rec.table(FLOW_MESSAGE[profile]))


def vehicle_table(rec: Recording, name: str, sysid: int) -> MessageTable | None:
    """The messages ``name`` the vehicle (system ``sysid``) sent, or None when it sent none.
    The recording's own table when every row is the vehicle's (no copy)."""
    if name not in rec:
        return None
    t = rec.tables[name]
    if not np.all(t.sysid == sysid):
        t = t.from_sender(sysid=sysid)
    return t if len(t) else None


def companion_table(rec: Recording, name: str, fields: Sequence[str] | None = None) -> MessageTable | None:
    """The messages ``name`` the companion (component 191, any system) sent, or None when it
    sent none. The recording's own table when every row is the companion's; else a copy of
    ``fields`` only (default: every field)."""
    if name not in rec:
        return None
    t = rec.tables[name]
    mask = t.compid == COMPANION_COMPONENT
    if not mask.all():
        keep = t.fields if fields is None else fields
        t = MessageTable(t.name, t.t_s[mask], t.sysid[mask], t.compid[mask], t.record[mask],
                         {k: t[k][mask] for k in keep})
    return t if len(t) else None


def time_s(table: MessageTable) -> np.ndarray:
    """Each message's own time (``TIME_FIELDS``), s (float64). Not for the flow message, whose
    time field depends on the profile (``profiles.flow_columns``)."""
    name, factor, scale = TIME_FIELDS[table.name]
    value = np.asarray(table[name], dtype=float)
    return (value if factor == 1 else value * factor) * scale


def time_ms(table: MessageTable) -> np.ndarray:
    """Each message's own time as whole milliseconds (int64), the key messages are matched on:
    a ``time_boot_ms`` as it is, a microsecond field rounded to the millisecond."""
    name = TIME_FIELDS[table.name][0]
    if name == "time_boot_ms":
        return np.asarray(table[name], dtype=np.int64)
    return np.round(np.asarray(table[name], dtype=float) * 1e-3).astype(np.int64)


# ---------------------------------------------------------------------------------------------
# The flow


class Flow:
    """The vehicle's flow messages in the paper's convention (``profiles.FlowColumns``: the
    profile's own time rule, scene-angle increments or rates, the message's own body rates).
    ``n_other``: flow messages from other systems, left out."""

    def __init__(self, sysid: int, table: MessageTable, columns: FlowColumns, n_other: int) -> None:
        self.sysid = sysid
        self.table = table
        self.columns = columns
        self.n_other = n_other


def vehicle_flow(rec: Recording, profile: Profile, q_rad_per_count: float) -> Flow:
    """The vehicle's flow (the vehicle: ``vehicle_id``). RecordingError when the recording has
    no flow message of the profile."""
    every = rec.table(FLOW_MESSAGE[profile])
    sysid = vehicle_sysid(every)
    table = every if np.all(every.sysid == sysid) else every.from_sender(sysid=sysid)
    return Flow(sysid, table, flow_columns(table, profile, q_rad_per_count), len(every) - len(table))


# ---------------------------------------------------------------------------------------------
# The gyro (and the accelerometer of the same messages)


class GyroSamples:
    """Gyro samples of the vehicle, in arrival order (``record``), from one or more gyro
    messages (``names``). Arrays of shape (n,): ``record`` (int64), ``time_s`` (each message's
    own time field, s), ``x_rad_s``, ``y_rad_s``, ``z_rad_s`` (body FRD roll, pitch, yaw rate;
    NaN where an int16 field clipped: x and y both where either did, as the live loop has it, z
    where it did itself). ``accel_m_s2``: (n, 3) body FRD specific force (``profiles.accel_m_s2``:
    NaN where an int16 field clipped), or None when a message has no accelerometer fields.
    Columns are computed on first use."""

    def __init__(self, parts: Sequence[MessageTable]) -> None:
        self.parts = tuple(parts)
        self.names = tuple(p.name for p in self.parts)
        if self.parts:
            rec = np.concatenate([p.record for p in self.parts])
            self._order = stable_order(rec)
            self.record = rec[self._order]
        else:
            self._order = np.zeros(0, np.int64)
            self.record = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return len(self.record)

    def _column(self, per_part: Sequence[np.ndarray]) -> np.ndarray:
        if not self.parts:
            return np.zeros(0)
        return np.concatenate([np.asarray(c, float) for c in per_part])[self._order]

    @cached_property
    def _clipped(self) -> list[np.ndarray | None]:
        out: list[np.ndarray | None] = []
        for p in self.parts:
            if p.name == "HIGHRES_IMU":  # float rad/s: nothing clips
                out.append(None)
            else:
                out.append(np.maximum(np.abs(p["xgyro"].astype(np.int64)), np.abs(p["ygyro"].astype(np.int64)))
                           >= INT16_CLIP)
        return out

    def _rate(self, key: str) -> np.ndarray:
        cols = []
        for p, clipped in zip(self.parts, self._clipped, strict=True):
            g = p[key] * GYRO_MESSAGES[p.name]
            if clipped is not None:
                if key == "zgyro":
                    clipped = clipped | (np.abs(p["zgyro"].astype(np.int64)) >= INT16_CLIP)
                g = np.where(clipped, np.nan, g)
            cols.append(g)
        return self._column(cols)

    @cached_property
    def time_s(self) -> np.ndarray:
        return self._column([time_s(p) for p in self.parts])

    @cached_property
    def time_ms(self) -> np.ndarray:
        """Each sample's own time as whole milliseconds (``time_ms``), int64."""
        if not self.parts:
            return np.zeros(0, np.int64)
        return np.concatenate([time_ms(p) for p in self.parts])[self._order]

    @cached_property
    def x_rad_s(self) -> np.ndarray:
        return self._rate("xgyro")

    @cached_property
    def y_rad_s(self) -> np.ndarray:
        return self._rate("ygyro")

    @cached_property
    def z_rad_s(self) -> np.ndarray:
        return self._rate("zgyro")

    @cached_property
    def accel_m_s2(self) -> np.ndarray | None:
        keys = ("xacc", "yacc", "zacc")
        if not self.parts or not all(k in p.fields for p in self.parts for k in keys):
            return None
        per_part = [accel_m_s2(p.name, p["xacc"], p["yacc"], p["zacc"]) for p in self.parts]
        return np.column_stack([self._column([a[i] for a in per_part]) for i in range(3)])


def gyro_as_received(rec: Recording, sysid: int) -> GyroSamples:
    """Every gyro message (RAW_IMU, SCALED_IMU, HIGHRES_IMU) the vehicle sent, merged in
    arrival order: what the live companion's gyro history receives."""
    return GyroSamples([t for name in GYRO_MESSAGES if (t := vehicle_table(rec, name, sysid)) is not None])


def gyro_sensor(rec: Recording, sysid: int) -> GyroSamples:
    """The vehicle's gyro as one sensor: the first of RAW_IMU, SCALED_IMU, HIGHRES_IMU the
    vehicle sent (empty when it sent none)."""
    for name in GYRO_MESSAGES:
        t = vehicle_table(rec, name, sysid)
        if t is not None:
            return GyroSamples([t])
    return GyroSamples([])


# ---------------------------------------------------------------------------------------------
# Range, attitude, commands


class _OneMessage:
    """One message type's rows in arrival order: ``record``, ``time_s`` and ``time_ms`` (the
    message's own time field, ``time_s`` / ``time_ms``), ``len``; the subclasses add its fields."""

    def __init__(self, table: MessageTable) -> None:
        self.table = table

    @property
    def record(self) -> np.ndarray:
        return self.table.record

    @cached_property
    def time_s(self) -> np.ndarray:
        return time_s(self.table)

    @cached_property
    def time_ms(self) -> np.ndarray:
        return time_ms(self.table)

    def __len__(self) -> int:
        return len(self.table)


class RangeReadings(_OneMessage):
    """The vehicle's downward DISTANCE_SENSOR readings (orientation 25), in arrival order, shape
    (n,): ``record``, ``time_s``, ``reading_m`` the distance as sent (cm -> m), ``valid`` within
    the sensor's own [min_distance, max_distance]; ``range_m`` is ``reading_m`` where valid, else NaN."""

    @cached_property
    def reading_m(self) -> np.ndarray:
        return self.table["current_distance"] * 0.01

    @cached_property
    def valid(self) -> np.ndarray:
        cur = self.table["current_distance"]
        return (self.table["min_distance"] <= cur) & (cur <= self.table["max_distance"])

    @cached_property
    def range_m(self) -> np.ndarray:
        return np.where(self.valid, self.reading_m, np.nan)


def downward_range(rec: Recording, sysid: int) -> RangeReadings | None:
    """The vehicle's downward range readings, or None when it sent none."""
    ds = vehicle_table(rec, "DISTANCE_SENSOR", sysid)
    if ds is None:
        return None
    down = ds["orientation"] == DOWNWARD
    if not down.all():  # (select copies every field)
        ds = ds.select(down)
    return RangeReadings(ds) if len(ds) else None


class Attitude(_OneMessage):
    """ATTITUDE (the vehicle's estimate) in arrival order, shape (n,): ``time_s``, and ``roll``,
    ``pitch``, ``yaw`` (rad), ``rollspeed``, ``pitchspeed`` (rad/s) as float64."""

    @cached_property
    def roll(self) -> np.ndarray:
        return np.asarray(self.table["roll"], dtype=float)

    @cached_property
    def pitch(self) -> np.ndarray:
        return np.asarray(self.table["pitch"], dtype=float)

    @cached_property
    def yaw(self) -> np.ndarray:
        return np.asarray(self.table["yaw"], dtype=float)

    @cached_property
    def rollspeed(self) -> np.ndarray:
        return np.asarray(self.table["rollspeed"], dtype=float)

    @cached_property
    def pitchspeed(self) -> np.ndarray:
        return np.asarray(self.table["pitchspeed"], dtype=float)


def vehicle_attitude(rec: Recording, sysid: int) -> Attitude | None:
    """The vehicle's ATTITUDE, or None when it sent none."""
    at = vehicle_table(rec, "ATTITUDE", sysid)
    return None if at is None else Attitude(at)


class AttitudeCommand(_OneMessage):
    """Commanded attitudes (the companion's SET_ATTITUDE_TARGET or the vehicle's ATTITUDE_TARGET)
    in arrival order, shape (n,): ``time_s``, ``time_ms``, ``q`` (n, 4) [w, x, y, z] float64,
    ``roll``, ``pitch`` rad (ZYX, ``rotation.quaternions_to_euler``)."""

    @cached_property
    def q(self) -> np.ndarray:
        return np.reshape(np.asarray(self.table["q"], dtype=float), (-1, 4))

    @cached_property
    def _euler(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return quaternions_to_euler(self.q)

    @property
    def roll(self) -> np.ndarray:
        return self._euler[0]

    @property
    def pitch(self) -> np.ndarray:
        return self._euler[1]


def companion_commands(rec: Recording) -> AttitudeCommand | None:
    """The companion's SET_ATTITUDE_TARGET (component 191), or None when it sent none."""
    t = companion_table(rec, "SET_ATTITUDE_TARGET", ("time_boot_ms", "q"))
    return None if t is None else AttitudeCommand(t)


def vehicle_targets(rec: Recording, sysid: int) -> AttitudeCommand | None:
    """The vehicle's ATTITUDE_TARGET (the target it is tracking), or None when it sent none."""
    t = vehicle_table(rec, "ATTITUDE_TARGET", sysid)
    return None if t is None else AttitudeCommand(t)
