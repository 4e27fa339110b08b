"""ArduPilot DataFlash logs (.bin, or .bin.gz: decompressed in memory) into the columnar
``Recording``, in MAVLink names and units.

The tables come out as if ArduPilot had streamed them over MAVLink, so the ``ardupilot`` profile
of CONVENTIONS.md applies unchanged (``profile_hint = "ardupilot"``). Mapping (docs/importers.md
has the references):

| DataFlash | unit, sign | table.field |
|---|---|---|
| OF.TimeUS | us | OPTICAL_FLOW.time_usec = TimeUS / 1000 (**ms**, as ArduPilot's MAVLink stream) |
| OF.flowX, flowY | rad/s, RH rotation of the sensor gives + | flow_rate_x, flow_rate_y (as is) |
| OF.bodyX, bodyY | rad/s, body gyro | flow_comp_m_x/y = flowX - bodyX, flowY - bodyY (as ArduPilot) |
| OF.Qual | 0-255 | quality; flow_x = flow_y = 0; ground_distance = -1 (unknown) |
| IMU (I = 0) or GYR | rad/s, m/s^2, FRD | RAW_IMU x/y/zgyro mrad/s, x/y/zacc milli-g, time_usec us |
| RFND.Dist, Orient | m, Rotation enum | DISTANCE_SENSOR current_distance cm, orientation (25 = down) |
| PARM RNGFNDn_MIN/MAX | m (or *_CM in cm) | DISTANCE_SENSOR min_distance, max_distance cm |
| ATT.Roll, Pitch, Yaw | deg (Yaw 0-360) | ATTITUDE roll, pitch, yaw rad (yaw wrapped to [-pi, pi)) |
| RATE.R, P, Y | deg/s | ATTITUDE rollspeed.. rad/s (nearest RATE row) and table RATE (rad/s) |
| ATT.DesRoll, DesPitch, DesYaw | deg | ATTITUDE_TARGET q = [w, x, y, z] (ZYX Euler) |
| RATE.RDes, PDes, YDes | deg/s | ATTITUDE_TARGET body_roll_rate.. rad/s |

Every table's ``t_s`` is the log's ``TimeUS`` in seconds (boot time); ``record`` orders all rows
of all tables by time (ties: file position); sysid 1, compid 1. pymavlink's ``DFReader``
indexes the file (formats and message offsets, robust to corrupt stretches); the columns are
then decoded with numpy in one pass per message type.

The helpers the importers share (``build_table``, ``assign_records``, ``nearest_index``) are in
``companion.recordings.importers.common``, the attitude conversions in ``companion.rotation``.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from companion.errors import RecordingError
from companion.mavlink_ids import MAV_DISTANCE_SENSOR_UNKNOWN
from companion.progress import StageCallback
from companion.recordings.columnar import MessageTable, Recording, read_recording_bytes
from companion.recordings.importers.common import GRAVITY_M_S2, Columns, assign_records, build_table, nearest_index
from companion.rotation import euler_to_quaternions

#: ArduPilot RangeFinder::Status::Good
RFND_STATUS_GOOD = 4

_HEAD = b"\xa3\x95"
_FMT_ID = 0x80

#: DataFlash format character -> (numpy dtype, multiplier DFReader applies). Matches
#: pymavlink.DFReader.FORMAT_TO_STRUCT ('a' is int16[32]).
_DF_TYPES: dict[str, tuple[str | tuple[str, tuple[int]], float | None]] = {
    "a": (("<i2", (32,)), None),
    "b": ("i1", None),
    "B": ("u1", None),
    "g": ("<f2", None),
    "h": ("<i2", None),
    "H": ("<u2", None),
    "i": ("<i4", None),
    "I": ("<u4", None),
    "f": ("<f4", None),
    "d": ("<f8", None),
    "n": ("S4", None),
    "N": ("S16", None),
    "Z": ("S64", None),
    "c": ("<i2", 0.01),
    "C": ("<u2", 0.01),
    "e": ("<i4", 0.01),
    "E": ("<u4", 0.01),
    "L": ("<i4", 1.0e-7),
    "M": ("i1", None),
    "q": ("<i8", None),
    "Q": ("<u8", None),
}


#: the stages ``read_dataflash`` reports to its ``progress`` callback, in order
STAGES = ("read", "indexed", "decoded", "tables")


def read_dataflash(path: str | Path, *, progress: StageCallback = None) -> Recording:
    """Read an ArduPilot DataFlash log into MAVLink-named tables (see the module table).

    Raises ``RecordingError`` (one line) when the file is missing, is not a DataFlash log, or
    holds no usable optical flow (OF). Missing gyro, range or attitude are skipped with a note.
    ``progress`` is called with each of ``STAGES`` as it ends (``companion.progress.Stages``).
    """
    done = progress or (lambda _stage: None)
    p = Path(path)
    raw = read_recording_bytes(p)  # a .bin.gz: decompressed in memory
    done(STAGES[0])
    data = np.frombuffer(raw, dtype=np.uint8)
    if data.size == 0:
        raise RecordingError(f"{p.name}: empty file, not a DataFlash log")
    if bytes(data[:3]) != _HEAD + bytes([_FMT_ID]):
        raise RecordingError(
            f"{p.name}: not an ArduPilot DataFlash log (no 0xA3 0x95 FMT header at the start)")
    try:
        with np.errstate(invalid="ignore", over="ignore"):  # damaged floats (NaN, sNaN, inf) pass through
            return _read(p, raw, data, done)
    except RecordingError as exc:
        if str(exc).startswith(p.name):
            raise
        raise RecordingError(f"{p.name}: {exc}") from None


def _read(p: Path, raw: bytes, data: np.ndarray, done: Callable[[str], None]) -> Recording:
    """``read_dataflash`` after the file checks (``data``: ``raw`` as uint8)."""
    messages, skipped, notes = _index(p, raw, data, done)
    done(STAGES[2])

    def take(name: str) -> tuple[Columns, np.ndarray] | None:
        """The decoded messages ``name``, or None (with a note) when their layout lacks a field
        this importer needs."""
        got = messages.get(name)
        if got is None or len(got[1]) == 0:
            return None
        layouts = _REQUIRED.get(name, ((),))
        if any(all(f in got[0] for f in layout) for layout in layouts):
            return got
        missing = [f for f in layouts[0] if f not in got[0]]
        problem = f"{name} messages lack {', '.join(missing)} (unsupported log layout)"
        if name == "OF":
            raise RecordingError(f"{p.name}: {problem}")
        notes.append(f"{problem}: skipped")
        return None

    of = take("OF")
    if of is None:
        raise RecordingError(f"{p.name}: no OF (optical flow) messages in the DataFlash log")
    tables: dict[str, MessageTable] = {}
    order_keys: dict[str, np.ndarray] = {}

    def add(table: MessageTable, key: np.ndarray) -> None:
        tables[table.name] = table
        order_keys[table.name] = key

    add(*_optical_flow(*of))

    gyro = _raw_imu(take("IMU"), take("GYR"), notes)
    if gyro is not None:
        add(*gyro)

    params = _params(take("PARM"))
    rfnd = take("RFND")
    if rfnd is None:
        notes.append("no RFND messages: range missing")
    else:
        add(*_distance_sensor(*rfnd, params, notes))

    att = take("ATT")
    rate = take("RATE")
    if att is None:
        notes.append("no ATT messages: attitude and attitude target missing")
    else:
        for table, key in _attitude(*att, rate, notes):
            add(table, key)
    if rate is None:
        notes.append("no RATE messages: ATTITUDE rates and ATTITUDE_TARGET body rates are NaN")
    else:
        add(*_rate_table(*rate))

    assign_records(tables, order_keys, notes)
    done(STAGES[3])
    return Recording(
        path=str(p),
        tables=tables,
        source_format="dataflash",
        skipped_bytes=int(skipped),
        notes=notes,
        profile_hint="ardupilot",
    )


# --------------------------------------------------------------------------- file decoding


def _index(p: Path, raw: bytes, data: np.ndarray, done: Callable[[str], None]
           ) -> tuple[dict[str, tuple[Columns, np.ndarray]], int, list[str]]:
    """Index the log's bytes ``raw`` with pymavlink's DFReader and decode the messages this
    importer uses (``data``: ``raw`` as uint8).

    Returns ``{name: (columns, file_offsets)}``, the number of bytes that lie outside complete
    messages (corruption, truncation) and notes on message types that could not be decoded.
    """
    from pymavlink import DFReader

    class IndexOnly(DFReader.DFReader_binary):
        """DFReader's indexer over bytes in memory (so a decompressed .bin.gz needs no file),
        without its clock set-up: ``init_clock`` parses every message of a log without GPS
        (~50 us each) and this importer reads TimeUS directly.

        ``DFReader_binary.__init__`` opens and maps a file; this is the same set-up with the
        bytes as the map (its indexers only slice ``data_map`` or take a memoryview of it)."""

        def __init__(self, buffer: bytes) -> None:
            DFReader.DFReader.__init__(self)
            self.filehandle = None
            self.data_map = buffer
            self.data_len = len(buffer)
            self.HEAD1, self.HEAD2 = _HEAD[0], _HEAD[1]
            self.unpackers: dict[Any, Any] = {}
            self.formats = {_FMT_ID: DFReader.DFFormat(_FMT_ID, "FMT", 89, "BBnNZ", "Type,Length,Name,Format,Columns")}
            self._zero_time_base = True
            self.prev_type = None
            fast = getattr(DFReader, "dfindexer", None)
            if getattr(fast, "available", False) and os.getenv("PYMAVLINK_FAST_INDEX", "1") == "1":
                self.init_arrays_fast()
            else:
                self.init_arrays()
            self.init_clock()
            self.prev_type = None
            self._rewind(keep_messages=True)

        def init_clock(self) -> None:
            self._rewind(keep_messages=True)
            self.clock = DFReader.DFReaderClock_usec()

        def close(self) -> None:
            """Nothing to close: the bytes belong to the caller."""

    wanted = ("OF", "IMU", "GYR", "RFND", "ATT", "RATE", "PARM")
    try:
        with _quiet():
            reader = IndexOnly(raw)
    except Exception as exc:  # DFReader raises bare Exceptions on malformed FMT records
        raise RecordingError(f"{p.name}: DataFlash log could not be indexed ({exc})") from None
    done(STAGES[1])
    formats = dict(reader.formats)
    offsets = [np.asarray(o, dtype=np.int64) for o in reader.offsets]
    used = 0
    out: dict[str, tuple[Columns, np.ndarray]] = {}
    notes: list[str] = []
    for type_id, fmt in formats.items():
        ofs = offsets[type_id] if type_id < len(offsets) else np.zeros(0, np.int64)
        ofs = ofs[ofs + fmt.len <= data.size]
        used += len(ofs) * fmt.len
        if fmt.name in wanted and len(ofs):
            try:
                out[fmt.name] = (decode_messages(data, ofs, fmt.format, list(fmt.columns), fmt.len), ofs)
            except RecordingError as exc:
                if fmt.name == "OF":
                    raise RecordingError(f"{p.name}: OF: {exc}") from None
                notes.append(f"{fmt.name}: {exc}: skipped")
    skipped = max(0, int(data.size) - used)
    if skipped:
        notes.insert(0, f"DataFlash: {skipped} bytes outside complete messages skipped "
                        "(corrupt or truncated log)")
    return out, skipped, notes


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Silence stdout and stderr, at the file-descriptor level too: pymavlink's C indexer
    prints a line per skipped byte of a damaged log (the count is in ``skipped_bytes``)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved: list[tuple[int, int]] = []
    try:
        with open(os.devnull, "wb") as null:
            for fd in (1, 2):
                try:
                    saved.append((fd, os.dup(fd)))
                    os.dup2(null.fileno(), fd)
                except OSError:  # no such descriptor (embedded interpreter): nothing to silence
                    continue
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                yield
    finally:
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)


def decode_messages(data: np.ndarray, offsets: np.ndarray, fmt: str, columns: list[str],
                    length: int) -> Columns:
    """Decode all messages of one DataFlash type at ``offsets`` (bytes from the file start,
    each at its 3-byte header) into columns, applying DFReader's multipliers (c/C/e/E x0.01,
    L x1e-7) and decoding strings. ``length``: FMT.Length, header included."""
    if len(fmt) != len(columns):
        raise RecordingError(f"DataFlash FMT mismatch: {len(fmt)} types for {len(columns)} columns")
    names = [_unique(c, i, columns) for i, c in enumerate(columns)]
    try:
        dtype = np.dtype([(n, _DF_TYPES[ch][0]) for n, ch in zip(names, fmt, strict=True)])
    except KeyError as exc:
        raise RecordingError(f"DataFlash format character {exc} is not supported") from None
    if dtype.itemsize != length - 3:
        raise RecordingError(f"DataFlash FMT length {length} does not match format {fmt!r}")
    if len(offsets) == 0:
        return {c: np.zeros(0) for c in columns}
    window = np.lib.stride_tricks.sliding_window_view(data, dtype.itemsize)
    rows = np.ascontiguousarray(window[offsets + 3]).view(dtype).reshape(-1)
    cols: Columns = {}
    for col, name, ch in zip(columns, names, fmt, strict=True):
        v = rows[name]
        mult = _DF_TYPES[ch][1]
        if mult is not None:
            v = v.astype(np.float64) * mult
        elif ch in "nNZ":
            v = np.array([s.split(b"\0", 1)[0].decode("ascii", "replace") for s in v], dtype=object)
        cols[col] = np.array(v)
    return cols


def _unique(col: str, i: int, columns: list[str]) -> str:
    return col if columns.index(col) == i else f"{col}__{i}"


#: fields each message must carry (any one of the layouts) for this importer to use it
_REQUIRED: dict[str, tuple[tuple[str, ...], ...]] = {
    "OF": (("TimeUS", "Qual", "flowX", "flowY", "bodyX", "bodyY"),),
    "IMU": (("TimeUS", "GyrX", "GyrY", "GyrZ"),),
    "GYR": (("TimeUS", "GyrX", "GyrY", "GyrZ"),),
    "RFND": (("TimeUS", "Dist", "Orient"), ("TimeUS", "Dist1", "Orient1")),
    "ATT": (("TimeUS", "DesRoll", "Roll", "DesPitch", "Pitch", "DesYaw", "Yaw"),),
    "RATE": (("TimeUS", "RDes", "R", "PDes", "P", "YDes", "Y"),),
    "PARM": (("Name", "Value"),),
}


# --------------------------------------------------------------------------- message mapping


def _optical_flow(c: Columns, ofs: np.ndarray) -> tuple[MessageTable, np.ndarray]:
    """OF -> OPTICAL_FLOW in the ardupilot profile's MAVLink semantics."""
    t_us = c["TimeUS"].astype(np.int64)
    fx = c["flowX"].astype(np.float64)
    fy = c["flowY"].astype(np.float64)
    n = len(t_us)
    fields: Columns = {
        "time_usec": t_us / 1000.0,  # milliseconds, as ArduPilot's OPTICAL_FLOW stream
        "sensor_id": np.zeros(n, np.uint8),
        "flow_x": np.zeros(n, np.int16),
        "flow_y": np.zeros(n, np.int16),
        "flow_comp_m_x": fx - c["bodyX"].astype(np.float64),
        "flow_comp_m_y": fy - c["bodyY"].astype(np.float64),
        "quality": c["Qual"].astype(np.uint8),
        "ground_distance": np.full(n, -1.0),
        "flow_rate_x": fx,
        "flow_rate_y": fy,
    }
    return build_table("OPTICAL_FLOW", t_us * 1e-6, fields), ofs


def _first_instance(c: Columns, ofs: np.ndarray, name: str, notes: list[str]) -> tuple[Columns, np.ndarray]:
    """Rows of instance 0 when the message carries an instance field ``I``."""
    if "I" not in c:
        return c, ofs
    inst = c["I"]
    present = np.unique(inst)
    if len(present) > 1:
        notes.append(f"{name}: instances {present.tolist()} present, using I=0")
    mask = inst == 0
    if not mask.any():
        mask = inst == present[0]
        notes.append(f"{name}: no instance 0, using I={int(present[0])}")
    return {k: v[mask] for k, v in c.items()}, ofs[mask]


def _raw_imu(imu: tuple[Columns, np.ndarray] | None, gyr: tuple[Columns, np.ndarray] | None,
             notes: list[str]) -> tuple[MessageTable, np.ndarray] | None:
    """IMU (preferred) or GYR -> RAW_IMU: gyro mrad/s, accel milli-g, time_usec us."""
    if imu is not None:
        c, ofs = _first_instance(*imu, "IMU", notes)
        t_us = c["TimeUS"].astype(np.int64)
        fields: Columns = {"time_usec": t_us}
        for ax in "XYZ":
            acc = c.get(f"Acc{ax}")
            fields[f"{ax.lower()}acc"] = (acc.astype(np.float64) / GRAVITY_M_S2 * 1000.0 if acc is not None
                                          else np.full(len(t_us), np.nan))
        for ax in "XYZ":
            fields[f"{ax.lower()}gyro"] = c[f"Gyr{ax}"].astype(np.float64) * 1000.0
        fields["id"] = np.zeros(len(t_us), np.uint8)
        if "T" in c:
            fields["temperature"] = c["T"].astype(np.float64) * 100.0
        return build_table("RAW_IMU", t_us * 1e-6, fields), ofs
    if gyr is not None:
        c, ofs = _first_instance(*gyr, "GYR", notes)
        t_us = c["TimeUS"].astype(np.int64)
        sample_us = c["SampleUS"].astype(np.int64) if "SampleUS" in c else t_us
        n = len(t_us)
        fields = {"time_usec": sample_us}
        for ax in "xyz":
            fields[f"{ax}acc"] = np.full(n, np.nan)
        for ax in "XYZ":
            fields[f"{ax.lower()}gyro"] = c[f"Gyr{ax}"].astype(np.float64) * 1000.0
        fields["id"] = np.zeros(n, np.uint8)
        notes.append("no IMU messages: RAW_IMU from GYR (raw gyro samples), accelerations NaN")
        return build_table("RAW_IMU", t_us * 1e-6, fields), ofs
    notes.append("no IMU or GYR messages: gyro missing")
    return None


def _params(parm: tuple[Columns, np.ndarray] | None) -> dict[str, float]:
    """PARM rows -> {name: last logged value}."""
    if parm is None:
        return {}
    return {str(n): float(v) for n, v in zip(parm[0]["Name"], parm[0]["Value"], strict=True)}


def _range_limits_cm(params: Mapping[str, float], instance: int) -> tuple[float, float] | None:
    """(min, max) in cm from RNGFNDn_MIN/_MAX (m, ArduPilot 4.6+) or RNGFNDn_MIN_CM/_MAX_CM
    (cm, older; the first sensor was RNGFND_* before multi-rangefinder support)."""
    prefixes = [f"RNGFND{instance + 1}"] + (["RNGFND"] if instance == 0 else [])
    for pre in prefixes:
        # PARM values are float32: round away the representation noise (0.2 m -> 20.0000003 cm)
        if f"{pre}_MIN" in params and f"{pre}_MAX" in params:
            return round(params[f"{pre}_MIN"] * 100.0, 3), round(params[f"{pre}_MAX"] * 100.0, 3)
        if f"{pre}_MIN_CM" in params and f"{pre}_MAX_CM" in params:
            return round(params[f"{pre}_MIN_CM"], 3), round(params[f"{pre}_MAX_CM"], 3)
    return None


def _distance_sensor(c: Columns, ofs: np.ndarray, params: Mapping[str, float],
                     notes: list[str]) -> tuple[MessageTable, np.ndarray]:
    """RFND -> DISTANCE_SENSOR (cm). Handles the current layout (Instance, Dist, Stat, Orient)
    and the pre-4.0 two-sensor layout (Dist1, Orient1, Dist2, Orient2)."""
    if "Dist" in c:
        t_us = c["TimeUS"].astype(np.int64)
        inst = c["Instance"].astype(np.int64) if "Instance" in c else np.zeros(len(t_us), np.int64)
        dist_m = c["Dist"].astype(np.float64)
        orient = c["Orient"].astype(np.int64)
        status = c["Stat"].astype(np.int64) if "Stat" in c else None
        quality = c["Quality"].astype(np.int64) if "Quality" in c else None
    else:  # pre-4.0 layout
        t1 = c["TimeUS"].astype(np.int64)
        parts = [(t1, np.zeros_like(t1), c["Dist1"], c["Orient1"], ofs)]
        if "Dist2" in c and np.any(c["Dist2"] > 0):
            parts.append((t1, np.ones_like(t1), c["Dist2"], c["Orient2"], ofs))
        t_us, inst, dist_m, orient, ofs = (np.concatenate([p[i] for p in parts]) for i in range(5))
        dist_m = dist_m.astype(np.float64)
        orient = orient.astype(np.int64)
        status = quality = None
    n = len(t_us)
    min_cm = np.zeros(n)
    max_cm = np.zeros(n)
    for i in np.unique(inst):
        sel = inst == i
        limits = _range_limits_cm(params, int(i))
        if limits is None:
            finite = dist_m[sel][np.isfinite(dist_m[sel])]
            limits = (0.0, float(np.ceil(finite.max() * 100.0)) if len(finite) else 0.0)
            notes.append(f"RFND instance {int(i)}: no RNGFND{int(i) + 1}_MIN/_MAX parameters, "
                         f"range limits taken from the data (0-{limits[1]:.0f} cm)")
        min_cm[sel], max_cm[sel] = limits
    if status is None:
        signal_quality = np.zeros(n, np.uint8)
    else:
        good_q = np.clip(quality, 0, 100) if quality is not None else np.zeros(n, np.int64)
        signal_quality = np.where(status == RFND_STATUS_GOOD, good_q, 1).astype(np.uint8)
    fields: Columns = {
        "time_boot_ms": t_us / 1000.0,
        "min_distance": min_cm,
        "max_distance": max_cm,
        "current_distance": dist_m * 100.0,
        "type": np.full(n, MAV_DISTANCE_SENSOR_UNKNOWN, np.uint8),
        "id": inst.astype(np.uint8),
        "orientation": orient.astype(np.uint8),
        "covariance": np.full(n, 255, np.uint8),
        "signal_quality": signal_quality,
    }
    order = np.argsort(t_us, kind="stable")
    return build_table("DISTANCE_SENSOR", t_us * 1e-6, fields).select(order), ofs[order]


def _attitude(c: Columns, ofs: np.ndarray, rate: tuple[Columns, np.ndarray] | None,
              notes: list[str]) -> list[tuple[MessageTable, np.ndarray]]:
    """ATT (+ the nearest RATE row) -> ATTITUDE and ATTITUDE_TARGET."""
    t_us = c["TimeUS"].astype(np.int64)
    t_s = t_us * 1e-6
    n = len(t_us)
    deg = np.deg2rad
    rates = {k: np.full(n, np.nan) for k in ("R", "P", "Y", "RDes", "PDes", "YDes")}
    if rate is not None:
        rc = rate[0]
        rt = rc["TimeUS"].astype(np.int64) * 1e-6
        idx = nearest_index(rt, t_s, _median_spacing(t_s, cap_s=0.02) / 2.0)
        hit = idx >= 0
        for k in rates:
            rates[k][hit] = deg(rc[k].astype(np.float64)[idx[hit]])
        if not hit.all():
            notes.append(f"ATT: {int((~hit).sum())} of {n} rows have no RATE row within half an ATT "
                         "period: their rates are NaN")
    attitude: Columns = {
        "time_boot_ms": t_us / 1000.0,
        "roll": deg(c["Roll"].astype(np.float64)),
        "pitch": deg(c["Pitch"].astype(np.float64)),
        "yaw": wrap_pi(deg(c["Yaw"].astype(np.float64))),
        "rollspeed": rates["R"],
        "pitchspeed": rates["P"],
        "yawspeed": rates["Y"],
    }
    have_rates = np.isfinite(rates["RDes"]) & np.isfinite(rates["PDes"]) & np.isfinite(rates["YDes"])
    target: Columns = {
        "time_boot_ms": t_us / 1000.0,
        "type_mask": np.where(have_rates, 0, 7).astype(np.uint8),
        "q": euler_to_quaternions(deg(c["DesRoll"].astype(np.float64)), deg(c["DesPitch"].astype(np.float64)),
                                 wrap_pi(deg(c["DesYaw"].astype(np.float64)))),
        "body_roll_rate": rates["RDes"],
        "body_pitch_rate": rates["PDes"],
        "body_yaw_rate": rates["YDes"],
        "thrust": np.full(n, np.nan),
    }
    return [(build_table("ATTITUDE", t_s, attitude), ofs),
            (build_table("ATTITUDE_TARGET", t_s, target), ofs)]


def _rate_table(c: Columns, ofs: np.ndarray) -> tuple[MessageTable, np.ndarray]:
    """RATE -> table RATE (not a MAVLink message): desired and achieved body rates, rad/s."""
    t_us = c["TimeUS"].astype(np.int64)
    fields: Columns = {"time_usec": t_us}
    for axis, short in (("roll", "R"), ("pitch", "P"), ("yaw", "Y")):
        fields[f"{axis}_rate_des_rad_s"] = np.deg2rad(c[f"{short}Des"].astype(np.float64))
        fields[f"{axis}_rate_rad_s"] = np.deg2rad(c[short].astype(np.float64))
    return build_table("RATE", t_us * 1e-6, fields), ofs


def _median_spacing(t: np.ndarray, cap_s: float) -> float:
    d = np.diff(np.asarray(t, dtype=np.float64))
    d = d[d > 0]
    return float(min(np.median(d), cap_s)) if len(d) else cap_s


def wrap_pi(a: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi
