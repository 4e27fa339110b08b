"""Regenerate the small DataFlash and ULog recordings the importer tests read.

    .venv/bin/python tests/data/importers/make_fixtures.py

writes ``copter_flow.bin``, ``px4_flow.ulg`` and ``truth.json`` next to this file. Output is
deterministic (no randomness, no clock): ``tests/test_importers.py`` checks that a fresh run
reproduces the committed bytes.

The planted truth is a vehicle over flat ground with piecewise-constant body velocity
(``vx``, ``vy`` m/s, FRD), body rates (``wx``, ``wy``, ``wz`` rad/s) and height ``A`` (m); the
segments change at one flow frame. The sensors are synthesised in each autopilot's own
convention, taken from its estimator (docs/importers.md):

* ArduPilot OF (NavEKF3 predicts ``-flowRate + bodyRate = (vy/A, -vx/A)``):
  ``flowX = wx - vy/A``, ``flowY = wy + vx/A``, ``bodyX = wx``, ``bodyY = wy`` (rad/s).
* PX4 vehicle_optical_flow (EKF2 negates ``pixel_flow`` into its LOS convention):
  ``pixel_flow[0] = (wx - vy/A) dt``, ``pixel_flow[1] = (wy + vx/A) dt``, ``delta_angle = w dt``.

The tests map them back through the importers and the ``ardupilot`` / ``px4`` profiles and
compare with the paper's ``dphi_x = (-wy - vx/A) dt``, ``dphi_y = (+wx - vy/A) dt``.

The writers are minimal but follow the formats: DataFlash (FMT 0x80 records, 0xA3 0x95 heads,
ArduPilot format characters, read by pymavlink's DFReader) and ULog v1 (header, flag bits,
formats, info, parameters, add-logged and data messages, read by pyulog).
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import asdict, dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
GRAVITY_M_S2 = 9.80665

# --------------------------------------------------------------------------- DataFlash writer

#: ArduPilot format character -> (struct code, scale applied before packing)
_DF_PACK = {
    "a": ("32h", None), "b": ("b", None), "B": ("B", None), "h": ("h", None), "H": ("H", None),
    "i": ("i", None), "I": ("I", None), "f": ("f", None), "d": ("d", None), "n": ("4s", None),
    "N": ("16s", None), "Z": ("64s", None), "c": ("h", 100.0), "C": ("H", 100.0), "e": ("i", 100.0),
    "E": ("I", 100.0), "L": ("i", 1.0e7), "M": ("B", None), "q": ("q", None), "Q": ("Q", None),
}


class DataFlashWriter:
    """Builds a DataFlash log in memory: ``fmt`` declares a message, ``msg`` appends one."""

    HEAD = b"\xa3\x95"

    def __init__(self) -> None:
        self.buf = bytearray()
        self._defs: dict[str, tuple[int, str, list[str]]] = {}
        self.fmt(0x80, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")

    def fmt(self, type_id: int, name: str, fmt: str, columns: str) -> None:
        length = 3 + struct.calcsize("<" + "".join(_DF_PACK[c][0] for c in fmt))
        self._defs[name] = (type_id, fmt, columns.split(","))
        self.buf += self.HEAD + bytes([0x80]) + struct.pack(
            "<BB4s16s64s", type_id, length, name.encode(), fmt.encode(), columns.encode())

    def msg(self, name: str, **values: float | int | str) -> None:
        type_id, fmt, cols = self._defs[name]
        packed = []
        for ch, col in zip(fmt, cols, strict=True):
            code, scale = _DF_PACK[ch]
            v = values.get(col, 0)
            if ch in "nNZ":
                packed.append(str(v).encode())
            elif scale is not None:
                packed.append(int(round(float(v) * scale)))
            elif code in ("f", "d"):
                packed.append(float(v))
            else:
                packed.append(int(v))
        self.buf += self.HEAD + bytes([type_id]) + struct.pack(
            "<" + "".join(_DF_PACK[c][0] for c in fmt), *packed)


# --------------------------------------------------------------------------- ULog writer

_ULOG_TYPES = {"int8_t": "b", "uint8_t": "B", "int16_t": "h", "uint16_t": "H", "int32_t": "i",
               "uint32_t": "I", "int64_t": "q", "uint64_t": "Q", "float": "f", "double": "d",
               "bool": "?", "char": "c"}


class ULogWriter:
    """Builds a ULog v1 file in memory. Call ``format``, ``info``, ``param`` first (definitions
    section), then ``add_logged`` and ``data``."""

    def __init__(self, start_us: int) -> None:
        self.buf = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", start_us))
        self._msg(b"B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
        self._formats: dict[str, list[tuple[str, int, str]]] = {}
        self._ids: dict[tuple[str, int], int] = {}

    def _msg(self, kind: bytes, payload: bytes) -> None:
        self.buf += struct.pack("<H", len(payload)) + kind + payload

    def format(self, name: str, fields: list[tuple[str, str]]) -> None:
        """``fields``: (type, name) with type like ``float`` or ``float[3]``; ``timestamp`` first."""
        parsed = []
        for typ, fname in fields:
            base, _, rest = typ.partition("[")
            parsed.append((base, int(rest[:-1]) if rest else 0, fname))
        self._formats[name] = parsed
        self._msg(b"F", f"{name}:{''.join(f'{t} {n};' for t, n in fields)}".encode())

    def info(self, key: str, value: str) -> None:
        key_b = f"char[{len(value)}] {key}".encode()
        self._msg(b"I", bytes([len(key_b)]) + key_b + value.encode())

    def param(self, name: str, value: float | int) -> None:
        if isinstance(value, int):
            key_b, val_b = f"int32_t {name}".encode(), struct.pack("<i", value)
        else:
            key_b, val_b = f"float {name}".encode(), struct.pack("<f", value)
        self._msg(b"P", bytes([len(key_b)]) + key_b + val_b)

    def add_logged(self, name: str, multi_id: int = 0) -> None:
        msg_id = len(self._ids)
        self._ids[(name, multi_id)] = msg_id
        self._msg(b"A", struct.pack("<BH", multi_id, msg_id) + name.encode())

    def data(self, name: str, multi_id: int = 0, **values: float | int | list[float]) -> None:
        codes, packed = "<", []
        fields = list(self._formats[name])
        while fields and fields[-1][2].startswith("_padding"):
            fields.pop()  # PX4's logger writes o_size_no_padding: no trailing padding
        for base, count, fname in fields:
            code = _ULOG_TYPES[base]
            v = values.get(fname, 0)
            items = list(v) if isinstance(v, list | tuple) else [v] * max(count, 1)
            for item in items:
                codes += code
                packed.append(float(item) if code in "fd" else bool(item) if code == "?" else int(item))
        self._msg(b"D", struct.pack("<H", self._ids[(name, multi_id)]) + struct.pack(codes, *packed))


# --------------------------------------------------------------------------- planted truth


@dataclass(frozen=True)
class Segment:
    """Constant motion from the previous segment's end (or the start) to ``t_end_us``."""

    t_end_us: int
    vx: float
    vy: float
    wx: float
    wy: float
    wz: float
    A: float


@dataclass(frozen=True)
class Truth:
    t0_us: int            # first sample, us since boot
    frame_us: int         # nominal flow frame period
    n_frames: int         # flow frames after the first
    jitter_us: tuple[int, ...]  # frame k is late by jitter_us[k % len]
    segments: tuple[Segment, ...]
    roll0: float          # attitude at t0, rad
    pitch0: float
    yaw0: float

    def frame_times_us(self) -> list[int]:
        return [self.t0_us + k * self.frame_us + self.jitter_us[k % len(self.jitter_us)]
                for k in range(self.n_frames + 1)]

    def at(self, t_us: float) -> Segment:
        """Segment in force at ``t_us`` (intervals closed on the right)."""
        for seg in self.segments:
            if t_us <= seg.t_end_us:
                return seg
        return self.segments[-1]

    def attitude(self, t_us: float) -> tuple[float, float, float]:
        """(roll, pitch, yaw) rad: the body rates integrated as Euler rates (small angles)."""
        r, p, y, start = self.roll0, self.pitch0, self.yaw0, self.t0_us
        for seg in self.segments:
            stop = min(t_us, seg.t_end_us)
            if stop > start:
                dt = (stop - start) * 1e-6
                r, p, y = r + seg.wx * dt, p + seg.wy * dt, y + seg.wz * dt
            start = max(start, seg.t_end_us)
        return r, p, y


def _truth(t0_us: int, segs: list[tuple[float, ...]], step_frame: int,
           att0: tuple[float, float, float]) -> Truth:
    base = Truth(t0_us, 20_000, 100, (0, 150, -100, 40), (), *att0)
    t_step = base.frame_times_us()[step_frame]
    end = base.frame_times_us()[-1] + 1_000_000
    segments = (Segment(t_step, *segs[0]), Segment(end, *segs[1]))
    return Truth(base.t0_us, base.frame_us, base.n_frames, base.jitter_us, segments, *att0)


#            vx     vy    wx     wy     wz    A
DF_TRUTH = _truth(5_000_000, [(0.5, -0.2, 0.1, -0.05, 0.02, 1.0),
                              (-0.3, 0.25, -0.06, 0.08, -0.01, 1.6)], 50,
                  (math.radians(2.0), math.radians(-3.0), math.radians(359.0)))
ULOG_TRUTH = _truth(3_000_000, [(-0.4, 0.3, -0.08, 0.06, -0.03, 2.0),
                                (0.2, -0.1, 0.04, 0.02, 0.0, 1.2)], 60,
                    (math.radians(-1.0), math.radians(4.0), math.radians(-179.5)))

#: planted details the tests check
DF_IMU1_GYRO_OFFSET = 0.01        # rad/s added on IMU instance 1 (must not be used)
DF_IMU_TEMP_C = 45.5
DF_QUALITY_ZERO_FRAMES = (10, 11)  # OF frames logged with Qual 0
DF_RFND_NODATA_ROWS = (3,)         # RFND instance 0 rows with Stat 1 (NoData)
DF_RFND2_DIST_M = 3.2              # forward rangefinder (instance 1, Orient 0)
DF_PARAMS = {"RNGFND1_MIN": 0.2, "RNGFND1_MAX": 7.0, "RNGFND2_MIN": 0.1, "RNGFND2_MAX": 12.0,
             "FLOW_TYPE": 1.0}
DF_DES_OFFSET_DEG = (1.0, -0.5, 0.0)    # DesRoll - Roll, DesPitch - Pitch, DesYaw - Yaw
DF_RATE_DES_OFFSET_DEG_S = (2.0, -1.0, 0.5)
DF_RATE_DELAY_US = 30                   # RATE is logged this long after ATT
UL_FLOW_PUBLISH_DELAY_US = 800          # timestamp - timestamp_sample
UL_SETPOINT_OFFSET_DEG = (1.0, -0.5, 0.0)
UL_THRUST_BODY = (0.0, 0.0, -0.55)
UL_RATES_SP = (0.3, -0.2, 0.1)          # vehicle_rates_setpoint roll, pitch, yaw rad/s
UL_RANGE_LIMITS_M = (0.08, 12.0)


def _quality(k: int) -> int:
    return 0 if k in DF_QUALITY_ZERO_FRAMES else 100 + (k * 7) % 150


def _wrap360(deg: float) -> float:
    return deg % 360.0


def _euler_to_q(roll: float, pitch: float, yaw: float) -> list[float]:
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return [cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy]


def _samples(t0_us: int, t1_us: int, period_us: int, offset_us: int = 0) -> list[int]:
    return list(range(t0_us + offset_us, t1_us + 1, period_us))


# --------------------------------------------------------------------------- DataFlash fixture


def dataflash_bytes(truth: Truth = DF_TRUTH) -> bytes:
    """A 2 s ArduCopter-like log: OF 50 Hz, IMU x2 400 Hz, RFND x2, ATT + RATE 100 Hz, PARM."""
    w = DataFlashWriter()
    w.fmt(0x81, "PARM", "QNff", "TimeUS,Name,Value,Default")
    w.fmt(0x82, "MSG", "QZ", "TimeUS,Message")
    w.fmt(0x83, "OF", "QBffff", "TimeUS,Qual,flowX,flowY,bodyX,bodyY")
    w.fmt(0x84, "IMU", "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz")
    w.fmt(0x85, "RFND", "QBCBB", "TimeUS,Instance,Dist,Stat,Orient")
    w.fmt(0x86, "ATT", "QffffffB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,AEKF")
    w.fmt(0x87, "RATE", "Qfffffffffffff", "TimeUS,RDes,R,ROut,PDes,P,POut,YDes,Y,YOut,ADes,A,AOut,AOutSlew")
    frames = truth.frame_times_us()
    t_start, t_end = frames[0], frames[-1]
    w.msg("MSG", TimeUS=t_start - 2000, Message="ArduCopter V4.6.0 (flowhold test fixture)")
    for i, (name, value) in enumerate(DF_PARAMS.items()):
        w.msg("PARM", TimeUS=t_start - 1000 + i, Name=name, Value=value, Default=0.0)

    events: list[tuple[int, int, str, dict[str, float | int]]] = []  # (time, order, name, values)
    for k, t in enumerate(frames):
        s = truth.at(t)
        events.append((t, 0, "OF", {"Qual": _quality(k), "flowX": s.wx - s.vy / s.A,
                                    "flowY": s.wy + s.vx / s.A, "bodyX": s.wx, "bodyY": s.wy}))
    for t in _samples(t_start, t_end, 2500, 700):
        s = truth.at(t)
        for inst, off in ((0, 0.0), (1, DF_IMU1_GYRO_OFFSET)):
            events.append((t, 1 + inst, "IMU", {
                "I": inst, "GyrX": s.wx + off, "GyrY": s.wy + off, "GyrZ": s.wz + off,
                "AccX": 0.0, "AccY": 0.0, "AccZ": -GRAVITY_M_S2, "T": DF_IMU_TEMP_C, "GH": 1, "AH": 1,
                "GHz": 400, "AHz": 400}))
    for j, t in enumerate(_samples(t_start, t_end, 50_000, 1300)):
        stat = 1 if j in DF_RFND_NODATA_ROWS else 4
        events.append((t, 3, "RFND", {"Instance": 0, "Dist": truth.at(t).A, "Stat": stat, "Orient": 25}))
        if j % 2 == 0:
            events.append((t + 100, 3, "RFND",
                           {"Instance": 1, "Dist": DF_RFND2_DIST_M, "Stat": 4, "Orient": 0}))
    for t in _samples(t_start, t_end, 10_000, 5000):
        s = truth.at(t)
        r, p, y = (math.degrees(a) for a in truth.attitude(t))
        dr, dp, dy = DF_DES_OFFSET_DEG
        events.append((t, 4, "ATT", {"Roll": r, "Pitch": p, "Yaw": _wrap360(y), "DesRoll": r + dr,
                                     "DesPitch": p + dp, "DesYaw": _wrap360(y + dy), "AEKF": 3}))
        rr, pr, yr = (math.degrees(v) for v in (s.wx, s.wy, s.wz))
        o = DF_RATE_DES_OFFSET_DEG_S
        events.append((t + DF_RATE_DELAY_US, 5, "RATE", {
            "RDes": rr + o[0], "R": rr, "ROut": 0.01, "PDes": pr + o[1], "P": pr, "POut": -0.02,
            "YDes": yr + o[2], "Y": yr, "YOut": 0.0, "ADes": 0.0, "A": 0.0, "AOut": 0.5}))
    for t, _, name, values in sorted(events, key=lambda e: (e[0], e[1])):
        w.msg(name, TimeUS=t, **values)
    return bytes(w.buf)


# --------------------------------------------------------------------------- ULog fixture

_VEHICLE_OPTICAL_FLOW = [
    ("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"),
    ("float[2]", "pixel_flow"), ("float[3]", "delta_angle"), ("float", "distance_m"),
    ("uint32_t", "integration_timespan_us"), ("float", "max_flow_rate"),
    ("float", "min_ground_distance"), ("float", "max_ground_distance"), ("uint8_t", "quality"),
    ("uint8_t[3]", "_padding0")]
_OPTICAL_FLOW_LEGACY = [
    ("uint64_t", "timestamp"), ("float", "pixel_flow_x_integral"), ("float", "pixel_flow_y_integral"),
    ("float", "gyro_x_rate_integral"), ("float", "gyro_y_rate_integral"), ("float", "gyro_z_rate_integral"),
    ("float", "ground_distance_m"), ("uint32_t", "integration_timespan"),
    ("uint32_t", "time_since_last_sonar_update"), ("uint16_t", "frame_count_since_last_readout"),
    ("int16_t", "gyro_temperature"), ("uint8_t", "sensor_id"), ("uint8_t", "quality")]
_SENSOR_COMBINED = [
    ("uint64_t", "timestamp"), ("float[3]", "gyro_rad"), ("uint32_t", "gyro_integral_dt"),
    ("int32_t", "accelerometer_timestamp_relative"), ("float[3]", "accelerometer_m_s2"),
    ("uint32_t", "accelerometer_integral_dt"), ("uint8_t", "accelerometer_clipping"),
    ("uint8_t", "gyro_clipping"), ("uint8_t", "accel_calibration_count"),
    ("uint8_t", "gyro_calibration_count")]
_ANGULAR_VELOCITY = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float[3]", "xyz"),
                     ("float[3]", "xyz_derivative")]
_DISTANCE_SENSOR = [
    ("uint64_t", "timestamp"), ("uint32_t", "device_id"), ("float", "min_distance"),
    ("float", "max_distance"),
    ("float", "current_distance"), ("float", "variance"), ("float", "h_fov"), ("float", "v_fov"),
    ("float[4]", "q"), ("int8_t", "signal_quality"), ("uint8_t", "type"), ("uint8_t", "orientation"),
    ("uint8_t", "mode")]
_ATTITUDE = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float[4]", "q"),
             ("float[4]", "delta_q_reset"), ("uint8_t", "quat_reset_counter"), ("uint8_t[7]", "_padding0")]
_ATTITUDE_SETPOINT = [("uint64_t", "timestamp"), ("float", "yaw_sp_move_rate"), ("float[4]", "q_d"),
                      ("float[3]", "thrust_body"), ("bool", "reset_integral"),
                      ("bool", "fw_control_yaw_wheel"), ("uint8_t[6]", "_padding0")]
_RATES_SETPOINT = [("uint64_t", "timestamp"), ("float", "roll"), ("float", "pitch"), ("float", "yaw"),
                   ("float[3]", "thrust_body"), ("bool", "reset_integral"), ("uint8_t[3]", "_padding0")]


def _flow_increments(s: Segment, dt_s: float) -> tuple[float, float]:
    """PX4 / MAVLink OPTICAL_FLOW_RAD convention: RH rotation gives +, +Y motion gives -x flow."""
    return (s.wx - s.vy / s.A) * dt_s, (s.wy + s.vx / s.A) * dt_s


def ulog_bytes(truth: Truth = ULOG_TRUTH, *, legacy_flow: bool = False) -> bytes:
    """A 2 s PX4-like log. ``legacy_flow``: the flow as the pre-1.13 ``optical_flow`` topic
    and no vehicle_angular_velocity / vehicle_rates_setpoint."""
    frames = truth.frame_times_us()
    t_start, t_end = frames[0], frames[-1]
    w = ULogWriter(t_start - 500_000)
    flow_topic = "optical_flow" if legacy_flow else "vehicle_optical_flow"
    topics = {flow_topic: _OPTICAL_FLOW_LEGACY if legacy_flow else _VEHICLE_OPTICAL_FLOW,
              "sensor_combined": _SENSOR_COMBINED, "distance_sensor": _DISTANCE_SENSOR,
              "vehicle_attitude": _ATTITUDE, "vehicle_attitude_setpoint": _ATTITUDE_SETPOINT}
    if not legacy_flow:
        topics["vehicle_angular_velocity"] = _ANGULAR_VELOCITY
        topics["vehicle_rates_setpoint"] = _RATES_SETPOINT
    for name, fields in topics.items():
        w.format(name, fields)
    w.info("sys_name", "PX4")
    w.info("ver_sw", "flowhold-test-fixture")
    w.param("SENS_FLOW_ROT", 0)
    w.param("SENS_FLOW_MAXHGT", 5.0)
    for name in topics:
        w.add_logged(name)
    w.add_logged("distance_sensor", 1)

    events: list[tuple[int, int, str, int, dict]] = []
    for k, t in enumerate(frames):
        s = truth.at(t)
        dt_us = frames[k] - frames[k - 1] if k else truth.frame_us
        fx, fy = _flow_increments(s, dt_us * 1e-6)
        da = [s.wx * dt_us * 1e-6, s.wy * dt_us * 1e-6, s.wz * dt_us * 1e-6]
        if legacy_flow:
            values = {"timestamp": t, "pixel_flow_x_integral": fx, "pixel_flow_y_integral": fy,
                      "gyro_x_rate_integral": da[0], "gyro_y_rate_integral": da[1],
                      "gyro_z_rate_integral": da[2], "ground_distance_m": s.A,
                      "integration_timespan": dt_us, "quality": _quality(k), "sensor_id": 3}
            events.append((t, 0, flow_topic, 0, values))
        else:
            values = {"timestamp": t + UL_FLOW_PUBLISH_DELAY_US, "timestamp_sample": t, "device_id": 0x4C0001,
                      "pixel_flow": [fx, fy], "delta_angle": da, "distance_m": float("nan"),
                      "integration_timespan_us": dt_us, "quality": _quality(k), "max_flow_rate": 7.4,
                      "min_ground_distance": 0.1, "max_ground_distance": 5.0}
            events.append((t + UL_FLOW_PUBLISH_DELAY_US, 0, flow_topic, 0, values))
    for t in _samples(t_start, t_end, 5000, 300):
        s = truth.at(t)
        events.append((t, 1, "sensor_combined", 0, {
            "timestamp": t, "gyro_rad": [s.wx, s.wy, s.wz], "gyro_integral_dt": 5000,
            "accelerometer_m_s2": [0.0, 0.0, -GRAVITY_M_S2], "accelerometer_integral_dt": 5000}))
    if not legacy_flow:
        for t in _samples(t_start, t_end, 10_000, 2100):
            s = truth.at(t - 200)
            events.append((t, 2, "vehicle_angular_velocity", 0, {
                "timestamp": t, "timestamp_sample": t - 200, "xyz": [s.wx, s.wy, s.wz]}))
    lo, hi = UL_RANGE_LIMITS_M
    for j, t in enumerate(_samples(t_start, t_end, 50_000, 1700)):
        events.append((t, 3, "distance_sensor", 0, {
            "timestamp": t, "device_id": 0x2A0001, "min_distance": lo, "max_distance": hi,
            "current_distance": truth.at(t).A, "variance": 0.0004, "signal_quality": -1 if j == 2 else 100,
            "type": 0, "orientation": 25}))
        if j % 2 == 0:
            events.append((t + 50, 3, "distance_sensor", 1, {
                "timestamp": t + 50, "device_id": 0x2A0002, "min_distance": 0.2, "max_distance": 40.0,
                "current_distance": 7.5, "signal_quality": 100, "type": 0, "orientation": 0}))
    for t in _samples(t_start, t_end, 10_000, 4000):
        events.append((t, 4, "vehicle_attitude", 0, {
            "timestamp": t, "timestamp_sample": t - 100, "q": _euler_to_q(*truth.attitude(t))}))
    for t in _samples(t_start, t_end, 20_000, 6000):
        r, p, y = truth.attitude(t)
        o = [math.radians(v) for v in UL_SETPOINT_OFFSET_DEG]
        events.append((t, 5, "vehicle_attitude_setpoint", 0, {
            "timestamp": t, "q_d": _euler_to_q(r + o[0], p + o[1], y + o[2]),
            "thrust_body": list(UL_THRUST_BODY)}))
        if not legacy_flow:
            events.append((t + 10, 6, "vehicle_rates_setpoint", 0, {
                "timestamp": t + 10, "roll": UL_RATES_SP[0], "pitch": UL_RATES_SP[1], "yaw": UL_RATES_SP[2],
                "thrust_body": list(UL_THRUST_BODY)}))
    for _, _, name, multi_id, values in sorted(events, key=lambda e: (e[0], e[1], e[3])):
        w.data(name, multi_id, **values)
    return bytes(w.buf)


def truth_json() -> str:
    """The planted truth of both fixtures, for the tests (and for humans)."""
    def one(tr: Truth) -> dict:
        d = asdict(tr)
        d["frame_times_us"] = tr.frame_times_us()
        return d
    return json.dumps({"dataflash": one(DF_TRUTH), "ulog": one(ULOG_TRUTH)}, indent=1, sort_keys=True) + "\n"


def write_all(outdir: Path = HERE) -> dict[str, Path]:
    """Write the committed fixtures into ``outdir``; returns name -> path."""
    out = {"copter_flow.bin": dataflash_bytes(), "px4_flow.ulg": ulog_bytes(),
           "truth.json": truth_json().encode()}
    paths = {}
    for name, blob in out.items():
        paths[name] = outdir / name
        paths[name].write_bytes(blob)
    return paths


if __name__ == "__main__":
    for name, path in write_all().items():
        print(f"{name}: {path.stat().st_size} bytes")
