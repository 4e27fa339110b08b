"""CSV logs into the columnar ``Recording``, driven by a column map (TOML in configs/sensors/).

A column map names the columns that hold time, gyro rates, accelerations (optional), flow counts,
flow quality and range, their units, and how their axes and signs become the project's
conventions (CONVENTIONS.md): body FRD rates, and the paper's flow counts ``dX``, ``dY`` (eq. 11,
``dphi_x = dX Q``). ``configs/sensors/stampfly.toml`` is the worked example. Signed columns are
written ``"+name"`` or ``"-name"``; every key is required and unknown keys are errors. The map
never sets the quantization step Q (that is the parameter set's ``[flow_sensor]``).

The tables come out as if the vehicle had streamed MAVLink (paper profile):

* ``OPTICAL_FLOW``: ``time_usec`` (us), ``flow_x``/``flow_y`` = paper-convention counts (float),
  ``quality`` (0-255), ``ground_distance`` = -1 (the flow sensor has no range of its own),
  ``flow_rate_*`` and ``flow_comp_m_*`` = NaN, ``sensor_id`` 0, and ``integration_time_us`` =
  the map's read period: the time one row's counts cover (a row holds the latest reading, which
  is not the row spacing when the logger and the sensor run at different rates).
* ``RAW_IMU``: ``time_usec``, ``x/y/zgyro`` mrad/s (float), ``x/y/zacc`` milli-g (NaN without an
  ``[accel]`` section), ``id`` 0.
* ``DISTANCE_SENSOR``: ``time_boot_ms``, ``current_distance`` cm (float, keeps mm resolution),
  ``min_distance``/``max_distance`` cm from the map, ``orientation`` 25 (PITCH_270, facing down),
  ``type`` 0 (laser), ``id`` 0, ``covariance`` 255 (unknown), ``signal_quality`` 0 (unknown).

``t_s`` of every table is the device time in seconds. ``record`` is row-ordered and unique:
``3 * row + {0: RAW_IMU, 1: DISTANCE_SENSOR, 2: OPTICAL_FLOW}`` (``row`` counts data lines from
0), so ``record // 3`` is the CSV row of any message. sysid 1, compid 1. A ``.csv.gz`` is read
the same way, decompressed in memory.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import bind, read_toml
from companion.errors import ConfigError, RecordingError
from companion.mavlink_ids import DOWNWARD, MAV_DISTANCE_SENSOR_LASER
from companion.progress import StageCallback
from companion.recordings.columnar import MessageTable, Recording, open_recording
from companion.recordings.importers.common import GRAVITY_M_S2, Columns, find_read_grid

TIME_UNITS_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
GYRO_UNITS_RAD_S = {"rad/s": 1.0, "deg/s": math.pi / 180.0, "mrad/s": 1e-3}
ACCEL_UNITS_M_S2 = {"m/s^2": 1.0, "g": GRAVITY_M_S2, "mg": GRAVITY_M_S2 * 1e-3}
RANGE_UNITS_M = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
REPEATED_READINGS = ("keep", "drop")
HELD_VALUES = ("keep", "drop")

#: record = 3 * row + offset
RECORD_OFFSET = {"RAW_IMU": 0, "DISTANCE_SENSOR": 1, "OPTICAL_FLOW": 2}


# ---------------------------------------------------------------------------------------------
# The column map


@dataclass(frozen=True)
class SensorSection:
    name: str


@dataclass(frozen=True)
class TimeSection:
    column: str
    unit: str


@dataclass(frozen=True)
class AxesSection:
    """Three signed columns giving body FRD x, y, z, and their unit."""

    unit: str
    body_x: str
    body_y: str
    body_z: str


@dataclass(frozen=True)
class FlowSection:
    paper_x: str
    paper_y: str
    quality_column: str
    read_period_ms: float
    repeated_readings: str


@dataclass(frozen=True)
class RangeSection:
    column: str
    unit: str
    min_m: float
    max_m: float
    held_values: str


@dataclass(frozen=True)
class SignedColumn:
    """A column name and the sign (+1 or -1) that maps it to the project's convention."""

    name: str
    sign: float
    role: str  # the map key it came from, e.g. "gyro.body_x", for error messages


@dataclass(frozen=True)
class ColumnMap:
    sensor: SensorSection
    time: TimeSection
    gyro: AxesSection
    accel: AxesSection | None
    flow: FlowSection
    range: RangeSection
    source: str

    def gyro_columns(self) -> tuple[SignedColumn, SignedColumn, SignedColumn]:
        return _axes_columns(self.gyro, "gyro")

    def accel_columns(self) -> tuple[SignedColumn, SignedColumn, SignedColumn] | None:
        return None if self.accel is None else _axes_columns(self.accel, "accel")

    def flow_columns(self) -> tuple[SignedColumn, SignedColumn]:
        return (parse_signed(self.flow.paper_x, "flow.paper_x", self.source),
                parse_signed(self.flow.paper_y, "flow.paper_y", self.source))


_SECTIONS: dict[str, type] = {"sensor": SensorSection, "time": TimeSection, "gyro": AxesSection,
                              "accel": AxesSection, "flow": FlowSection, "range": RangeSection}
_OPTIONAL = {"accel"}


def parse_signed(text: str, role: str, source: str) -> SignedColumn:
    """``"+name"`` or ``"-name"`` -> SignedColumn; anything else is a ConfigError."""
    if len(text) < 2 or text[0] not in "+-" or not text[1:].strip():
        raise ConfigError(f"{source} [{role.split('.')[0]}] {role.split('.')[1]}: expected a signed column "
                          f"like \"+raw_gyro_x\" or \"-raw_flow_dx\", got {text!r}")
    return SignedColumn(text[1:].strip(), 1.0 if text[0] == "+" else -1.0, role)


def _axes_columns(sec: AxesSection, name: str) -> tuple[SignedColumn, SignedColumn, SignedColumn]:
    return (parse_signed(sec.body_x, f"{name}.body_x", ""), parse_signed(sec.body_y, f"{name}.body_y", ""),
            parse_signed(sec.body_z, f"{name}.body_z", ""))


def column_map_from_dict(data: dict[str, Any], source: str = "<dict>") -> ColumnMap:
    """Bind a parsed column-map TOML: every key required, no unknown sections or keys."""
    unknown = sorted(set(data) - set(_SECTIONS))
    if unknown:
        raise ConfigError(f"{source}: unknown section(s) {', '.join(unknown)} (allowed: {', '.join(_SECTIONS)})")
    missing = [s for s in _SECTIONS if s not in data and s not in _OPTIONAL]
    if missing:
        raise ConfigError(f"{source}: missing section(s) {', '.join(missing)}")
    bound: dict[str, Any] = {name: bind(cls, data[name], f"{source} [{name}]") for name, cls in _SECTIONS.items()
                             if name in data}
    cmap = ColumnMap(sensor=bound["sensor"], time=bound["time"], gyro=bound["gyro"], accel=bound.get("accel"),
                     flow=bound["flow"], range=bound["range"], source=source)
    _validate(cmap)
    return cmap


def _choice(value: str, allowed: Any, where: str) -> None:
    if value not in allowed:
        raise ConfigError(f"{where}: {value!r} is not one of {', '.join(allowed)}")


def _validate(m: ColumnMap) -> None:
    s = m.source
    _choice(m.time.unit, TIME_UNITS_S, f"{s} [time] unit")
    _choice(m.gyro.unit, GYRO_UNITS_RAD_S, f"{s} [gyro] unit")
    if m.accel is not None:
        _choice(m.accel.unit, ACCEL_UNITS_M_S2, f"{s} [accel] unit")
    _choice(m.range.unit, RANGE_UNITS_M, f"{s} [range] unit")
    _choice(m.flow.repeated_readings, REPEATED_READINGS, f"{s} [flow] repeated_readings")
    _choice(m.range.held_values, HELD_VALUES, f"{s} [range] held_values")
    if not m.flow.read_period_ms > 0:
        raise ConfigError(f"{s} [flow] read_period_ms must be > 0")
    if not 0 <= m.range.min_m < m.range.max_m:
        raise ConfigError(f"{s} [range] needs 0 <= min_m < max_m")
    for sec, keys in (("gyro", ("body_x", "body_y", "body_z")), ("accel", ("body_x", "body_y", "body_z")),
                      ("flow", ("paper_x", "paper_y"))):
        table = getattr(m, sec)
        if table is None:
            continue
        cols = [parse_signed(getattr(table, k), f"{sec}.{k}", s).name for k in keys]
        if len(set(cols)) != len(cols):
            raise ConfigError(f"{s} [{sec}]: the same column is used for two axes ({', '.join(cols)})")


def load_column_map(path: str | Path) -> ColumnMap:
    """Read and check a column map (TOML). Raises ConfigError with one clear line."""
    p = Path(path)
    return column_map_from_dict(read_toml(p, "sensor config"), source=str(p))


# ---------------------------------------------------------------------------------------------
# The CSV


#: the stages ``read_csv`` reports to its ``progress`` callback, in order
STAGES = ("read", "columns", "tables")


def read_csv(path: str | Path, sensor_config_path: str | Path, *, progress: StageCallback = None) -> Recording:
    """Read a CSV log described by a column map into MAVLink-named tables (module docstring).

    Raises ``ConfigError`` for a bad column map and ``RecordingError`` (one line, naming the
    column and line) for a missing column, a non-numeric or non-finite value, a ragged line, or
    time that runs backwards. ``progress`` is called with each of ``STAGES`` as it ends
    (``companion.progress.Stages``).
    """
    done = progress or (lambda _stage: None)
    cmap = load_column_map(sensor_config_path)
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"recording not found: {p}")
    header, rows, linenos, notes = _read_rows(p)
    done(STAGES[0])

    gyro = cmap.gyro_columns()
    accel = cmap.accel_columns()
    flow = cmap.flow_columns()
    wanted: list[tuple[str, str]] = [(cmap.time.column, "time.column")]
    wanted += [(c.name, c.role) for c in gyro]
    wanted += [(c.name, c.role) for c in (accel or ())]
    wanted += [(c.name, c.role) for c in flow]
    wanted += [(cmap.flow.quality_column, "flow.quality_column"), (cmap.range.column, "range.column")]
    index = {name: i for i, name in enumerate(header)}
    for name, role in wanted:
        if name not in index:
            raise RecordingError(f"{p.name}: column {name!r} ({role} in {Path(cmap.source).name}) is not in the "
                                 f"CSV header")
    cols = {name: _numeric(p, rows, linenos, index[name], name) for name, _ in wanted}
    n = len(rows)
    done(STAGES[1])

    t_s = cols[cmap.time.column] * TIME_UNITS_S[cmap.time.unit]
    steps = np.diff(t_s)
    if np.any(steps < 0):
        k = int(np.argmax(steps < 0)) + 1
        raise RecordingError(f"{p.name}: time ({cmap.time.column}) goes backwards at line {linenos[k]} "
                             f"(a reboot?): split the file there")
    n_same_t = int(np.sum(steps == 0))
    if n_same_t:
        notes.append(f"{n_same_t} rows repeat the previous row's timestamp (kept)")
    time_usec = np.round(t_s * 1e6).astype(np.int64)

    g = GYRO_UNITS_RAD_S[cmap.gyro.unit]
    gyro_mrad_s = [c.sign * cols[c.name] * g * 1e3 for c in gyro]
    if accel is not None:
        assert cmap.accel is not None
        a = ACCEL_UNITS_M_S2[cmap.accel.unit]
        acc_mg = [c.sign * cols[c.name] * a / GRAVITY_M_S2 * 1e3 for c in accel]
    else:
        acc_mg = [np.full(n, np.nan)] * 3
        notes.append("no [accel] section in the column map: RAW_IMU accelerations are NaN")
    raw_imu: Columns = {"time_usec": time_usec, "xgyro": gyro_mrad_s[0], "ygyro": gyro_mrad_s[1],
                        "zgyro": gyro_mrad_s[2], "xacc": acc_mg[0], "yacc": acc_mg[1], "zacc": acc_mg[2],
                        "id": np.zeros(n, np.uint8)}

    range_m = cols[cmap.range.column] * RANGE_UNITS_M[cmap.range.unit]
    dist: Columns = {"time_boot_ms": t_s * 1e3, "min_distance": np.full(n, cmap.range.min_m * 100.0),
            "max_distance": np.full(n, cmap.range.max_m * 100.0), "current_distance": range_m * 100.0,
            "type": np.full(n, MAV_DISTANCE_SENSOR_LASER, np.uint8), "id": np.zeros(n, np.uint8),
            "orientation": np.full(n, DOWNWARD, np.uint8),
            "covariance": np.full(n, 255, np.uint8), "signal_quality": np.zeros(n, np.uint8)}
    n_invalid = int(np.sum((range_m < cmap.range.min_m) | (range_m > cmap.range.max_m)))
    if n_invalid:
        notes.append(f"{n_invalid} range values outside [{cmap.range.min_m}, {cmap.range.max_m}] m (kept; "
                     f"readers treat them as invalid)")

    fx = flow[0].sign * cols[flow[0].name]
    fy = flow[1].sign * cols[flow[1].name]
    quality = cols[cmap.flow.quality_column]
    if np.any((quality < 0) | (quality > 255)):
        notes.append("flow quality outside 0-255: clipped")
    period_s = cmap.flow.read_period_ms * 1e-3
    of: Columns = {"time_usec": time_usec, "sensor_id": np.zeros(n, np.uint8), "flow_x": fx, "flow_y": fy,
          "flow_comp_m_x": np.full(n, np.nan), "flow_comp_m_y": np.full(n, np.nan),
          "quality": np.clip(np.round(quality), 0, 255).astype(np.uint8), "ground_distance": np.full(n, -1.0),
          "flow_rate_x": np.full(n, np.nan), "flow_rate_y": np.full(n, np.nan),
          "integration_time_us": np.full(n, period_s * 1e6)}
    notes.append(f"flow: paper dX = {cmap.flow.paper_x}, dY = {cmap.flow.paper_y}; each row's counts cover one "
                 f"{cmap.flow.read_period_ms:g} ms read (OPTICAL_FLOW.integration_time_us), not the row spacing "
                 f"(median {1e3 * float(np.median(steps)) if len(steps) else float('nan'):.1f} ms)")
    if len(steps) and float(np.median(steps)) < 0.9 * period_s and cmap.flow.repeated_readings == "keep":
        notes.append(f"rows come faster than reads (median {1e3 * float(np.median(steps)):.1f} ms against "
                     f"{cmap.flow.read_period_ms:g} ms): most rows repeat a reading; kept as logged "
                     f"(repeated_readings = keep); the sensor diagnosis drops them, replay wants "
                     f"repeated_readings = drop")
    if len(steps) and float(np.median(steps)) > 1.05 * period_s:
        expected = float(np.sum(np.maximum(steps / period_s - 1.0, 0.0)))
        notes.append(f"rows come slower than reads: about {expected:.0f} of {expected + n:.0f} readings "
                     f"({100 * expected / (expected + n):.1f} %) never reached the log")

    row = np.arange(n, dtype=np.int64)
    tables = {
        "RAW_IMU": _table("RAW_IMU", t_s, raw_imu, row),
        "DISTANCE_SENSOR": _table("DISTANCE_SENSOR", t_s, dist, row),
        "OPTICAL_FLOW": _table("OPTICAL_FLOW", t_s, of, row),
    }
    if cmap.flow.repeated_readings == "drop":
        grid = find_read_grid(t_s, np.column_stack([fx, fy, quality]), period_s)
        if grid.slot is None:
            notes.append(f"repeated_readings = drop: nothing dropped ({grid.method})")
        else:
            first = np.ones(n, dtype=bool)
            first[1:] = grid.slot[1:] != grid.slot[:-1]
            tables["OPTICAL_FLOW"] = tables["OPTICAL_FLOW"].select(first)
            notes.append(f"repeated_readings = drop: {int(np.sum(~first))} of {n} rows repeat a "
                         f"{cmap.flow.read_period_ms:g} ms read slot and were left out of OPTICAL_FLOW ({grid.method})")
    if cmap.range.held_values == "drop":
        new = np.ones(n, dtype=bool)
        new[1:] = range_m[1:] != range_m[:-1]
        tables["DISTANCE_SENSOR"] = tables["DISTANCE_SENSOR"].select(new)
        notes.append(f"held_values = drop: {int(np.sum(~new))} of {n} rows repeat the previous range value and "
                     f"were left out of DISTANCE_SENSOR")
    unused = [h for h in header if h not in cols]
    if unused:
        notes.append(f"{len(unused)} columns not in the map were ignored ({', '.join(unused[:4])}"
                     f"{', ...' if len(unused) > 4 else ''})")
    done(STAGES[2])
    return Recording(path=str(p), tables=tables, source_format="csv", notes=notes, profile_hint="paper")


def _table(name: str, t_s: np.ndarray, fields: dict[str, np.ndarray], row: np.ndarray) -> MessageTable:
    n = len(t_s)
    return MessageTable(name=name, t_s=np.asarray(t_s, dtype=np.float64), sysid=np.ones(n, np.uint8),
                        compid=np.ones(n, np.uint8), record=3 * row + RECORD_OFFSET[name], fields=fields)


def _read_rows(p: Path) -> tuple[list[str], list[list[str]], list[int], list[str]]:
    """Header (stripped names), data rows and their line numbers in the file; blank lines are
    skipped, a short last line (logging cut off) is dropped with a note, any other ragged line
    is an error."""
    notes: list[str] = []
    try:
        with open_recording(p) as raw, io.TextIOWrapper(raw, encoding="utf-8-sig", newline="") as fh:
            lines = [r for r in csv.reader(fh)]  # a .csv.gz: decompressed in memory
    except UnicodeDecodeError:
        raise RecordingError(f"{p.name}: not a text CSV file (not UTF-8)") from None
    except csv.Error as exc:
        raise RecordingError(f"{p.name}: not a readable CSV file ({exc})") from None
    numbered = [(i + 1, r) for i, r in enumerate(lines) if r and any(c.strip() for c in r)]
    if not numbered:
        raise RecordingError(f"{p.name}: empty CSV file")
    header = [c.strip() for c in numbered[0][1]]
    body = numbered[1:]
    if not body:
        raise RecordingError(f"{p.name}: the CSV has a header but no data rows")
    if len(body[-1][1]) < len(header):
        notes.append(f"last line {body[-1][0]} is cut short ({len(body[-1][1])} of {len(header)} fields): dropped")
        body = body[:-1]
        if not body:
            raise RecordingError(f"{p.name}: the CSV has no complete data rows")
    for lineno, r in body:
        if len(r) != len(header):
            raise RecordingError(f"{p.name}: line {lineno} has {len(r)} fields, the header has {len(header)}")
    return header, [r for _, r in body], [i for i, _ in body], notes


def _numeric(p: Path, rows: list[list[str]], linenos: list[int], j: int, name: str) -> np.ndarray:
    """Column ``j`` as float64; a RecordingError naming the column and line for a bad value."""
    text = [r[j] for r in rows]
    try:
        values = np.array(text, dtype=np.float64)
    except ValueError:
        values = None
    if values is not None and bool(np.all(np.isfinite(values))):
        return values
    for i, s in enumerate(text):
        try:
            v = float(s)
        except ValueError:
            raise RecordingError(f"{p.name}: column {name!r}, line {linenos[i]}: {s.strip()!r} is not a "
                                 f"number") from None
        if not math.isfinite(v):
            raise RecordingError(f"{p.name}: column {name!r}, line {linenos[i]}: {s.strip()!r} is not a finite number")
    raise RecordingError(f"{p.name}: column {name!r} could not be read as numbers")  # pragma: no cover
