"""Sensor profiles: how each autopilot's flow message maps to the paper's scene angle.

CONVENTIONS.md, "Sensor profiles". Everything downstream of this module works in the paper's
convention: the scene-angle rate over one flow frame, ``Omega_x = dphi_x / T`` and
``Omega_y = dphi_y / T`` (rad/s), with ``phi_x = integral(-omega_y - V_x / A)`` and
``phi_y = integral(+omega_x - V_y / A)``.

- paper: OPTICAL_FLOW counts ``flow_x``, ``flow_y`` per frame: dphi_x = flow_x Q, dphi_y = flow_y Q
- ardupilot: OPTICAL_FLOW ``flow_rate_x/y`` rad/s, ``time_usec`` holds ms:
  Omega_x = -flow_rate_y, Omega_y = +flow_rate_x
- px4: OPTICAL_FLOW_RAD ``integrated_x/y`` rad over ``integration_time_us``:
  dphi_x = -integrated_y, dphi_y = +integrated_x

The functions take scalars or numpy arrays alike, so the live loop (one message) and replay
(whole columns) run the same arithmetic.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.errors import RecordingError
from companion.recordings.importers.common import GRAVITY_M_S2
from companion.recordings.load import Recording


class Profile(enum.StrEnum):
    PAPER = "paper"
    ARDUPILOT = "ardupilot"
    PX4 = "px4"


#: the MAVLink message that carries the flow in each profile
FLOW_MESSAGE = {
    Profile.PAPER: "OPTICAL_FLOW",
    Profile.ARDUPILOT: "OPTICAL_FLOW",
    Profile.PX4: "OPTICAL_FLOW_RAD",
}

#: gyro messages accepted, in order of preference, and their scale to rad/s
GYRO_MESSAGES = {"RAW_IMU": 1e-3, "SCALED_IMU": 1e-3, "HIGHRES_IMU": 1.0}
#: RAW_IMU / SCALED_IMU gyro fields (int16, mrad/s) at this magnitude have clipped: the rate is unknown
INT16_CLIP = 32767
#: the same messages' accelerometer fields (body FRD specific force) -> m/s^2: milli-g of standard
#: gravity (ArduPilot's and PX4's RAW_IMU, SCALED_IMU; int16, clipping at ``INT16_CLIP`` like the
#: gyro's), HIGHRES_IMU m/s^2 (float)
ACCEL_M_S2 = {"RAW_IMU": GRAVITY_M_S2 * 1e-3, "SCALED_IMU": GRAVITY_M_S2 * 1e-3, "HIGHRES_IMU": 1.0}


def accel_m_s2(name: str, x: Any, y: Any, z: Any) -> tuple[Any, Any, Any]:
    """A gyro message's accelerometer fields (scalars or arrays) in m/s^2, body FRD; NaN on all
    three where an int16 field has clipped (the specific force is unknown) or a value is not
    finite. The one conversion of the live loop (``inbound.MessageRouter``) and of recordings
    (``companion.recordings.signals``). Whether a vehicle has an accelerometer at all is the estimator's
    rule (``estimator.VelocityKalman.on_accel``: the (0, 0, -1 g) placeholder)."""
    k = ACCEL_M_S2[name]
    fx, fy, fz = (np.asarray(v, dtype=float) for v in (x, y, z))
    with np.errstate(invalid="ignore"):
        bad = ~(np.isfinite(fx) & np.isfinite(fy) & np.isfinite(fz))
        if name != "HIGHRES_IMU":
            bad = bad | (np.maximum(np.maximum(np.abs(fx), np.abs(fy)), np.abs(fz)) >= INT16_CLIP)
    out = tuple(np.where(bad, np.nan, v * k) for v in (fx, fy, fz))
    if out[0].ndim == 0:
        return float(out[0]), float(out[1]), float(out[2])
    return out[0], out[1], out[2]
#: each message's own time field (CONVENTIONS.md), the one time-field rule of the live loop
#: (``inbound``) and of recordings (``companion.recordings.signals``): (field, factor, scale), the time in s
#: is ``value * factor * scale``. A gyro's time goes through whole microseconds (SCALED_IMU's
#: ``time_boot_ms`` x 1000), so that one instant has one time whichever gyro message told it
#: (``ms * 1e-3`` and ``us * 1e-6`` differ in the last bit for 2 in 5 instants). The flow
#: message's depends on the profile (``flow_columns``: ArduPilot fills OPTICAL_FLOW ``time_usec`` with ms).
TIME_FIELDS: dict[str, tuple[str, int, float]] = {
    "RAW_IMU": ("time_usec", 1, 1e-6),
    "HIGHRES_IMU": ("time_usec", 1, 1e-6),
    "SCALED_IMU": ("time_boot_ms", 1000, 1e-6),
    "DISTANCE_SENSOR": ("time_boot_ms", 1, 1e-3),
    "ATTITUDE": ("time_boot_ms", 1, 1e-3),
    "ATTITUDE_TARGET": ("time_boot_ms", 1, 1e-3),
    "SET_ATTITUDE_TARGET": ("time_boot_ms", 1, 1e-3),
    "LOCAL_POSITION_NED": ("time_boot_ms", 1, 1e-3),
    "POSITION_TARGET_LOCAL_NED": ("time_boot_ms", 1, 1e-3),
    "VISION_SPEED_ESTIMATE": ("usec", 1, 1e-6),
}


@dataclass(frozen=True)
class FlowColumns:
    """Flow frames in the paper's convention (scalars or equal-length arrays).

    ``time_s``: the frame's sensor (boot) time, s. ``increment``: True when ``scene_x/y`` are
    angle increments over the frame (rad) and False when they are rates (rad/s).
    ``integration_s``: the integration time the message states (px4), else NaN: the frame
    spacing is used. ``quality``: 0 = invalid. ``counts_x/y``: the raw counts (paper profile;
    NaN otherwise), for plots and spike checks. ``body_x/y_rad_s``: the body rates (roll rate
    omega_x, pitch rate omega_y, rad/s) the message carries for its own flow sample, NaN when
    the profile has none: ardupilot ``flow_rate - flow_comp_m`` (ArduPilot's ``bodyRate``, the
    gyro it uses to compensate that sample), px4 ``integrated_x/ygyro`` over the integration
    time. The companion uses them only with ``--gyro flow`` (``core.GyroSource``).
    """

    time_s: Any
    scene_x: Any
    scene_y: Any
    increment: bool
    integration_s: Any
    quality: Any
    counts_x: Any
    counts_y: Any
    body_x_rad_s: Any = np.nan
    body_y_rad_s: Any = np.nan


def flow_columns(fields: Any, profile: Profile, q_rad_per_count: float) -> FlowColumns:
    """Map the flow message's fields (a MessageTable, a dict, or a pymavlink message via
    ``FieldView``) to the paper's convention. Works elementwise on arrays."""
    f = fields
    nan = np.nan
    if profile is Profile.PAPER:
        cx = np.asarray(f["flow_x"], dtype=float)
        cy = np.asarray(f["flow_y"], dtype=float)
        return FlowColumns(
            time_s=np.asarray(f["time_usec"], dtype=float) * 1e-6,
            scene_x=cx * q_rad_per_count,
            scene_y=cy * q_rad_per_count,
            increment=True,
            integration_s=_optional_integration_s(f, cx),
            quality=np.asarray(f["quality"]),
            counts_x=cx,
            counts_y=cy,
        )
    if profile is Profile.ARDUPILOT:
        rx = np.asarray(f["flow_rate_x"], dtype=float)
        ry = np.asarray(f["flow_rate_y"], dtype=float)
        return FlowColumns(
            time_s=np.asarray(f["time_usec"], dtype=float) * 1e-3,  # ArduPilot puts ms here
            scene_x=-ry,
            scene_y=+rx,
            increment=False,
            integration_s=np.full_like(rx, nan),
            quality=np.asarray(f["quality"]),
            counts_x=np.full_like(rx, nan),
            counts_y=np.full_like(rx, nan),
            # flow_comp_m = flowRate - bodyRate (rad/s despite the name): the sample's own body rate
            body_x_rad_s=rx - np.asarray(f["flow_comp_m_x"], dtype=float),
            body_y_rad_s=ry - np.asarray(f["flow_comp_m_y"], dtype=float),
        )
    ix = np.asarray(f["integrated_x"], dtype=float)
    iy = np.asarray(f["integrated_y"], dtype=float)
    integration_s = np.asarray(f["integration_time_us"], dtype=float) * 1e-6
    with np.errstate(all="ignore"):  # an integration time of 0 gives no body rate (inf/NaN: gated)
        body_x = np.asarray(f["integrated_xgyro"], dtype=float) / integration_s
        body_y = np.asarray(f["integrated_ygyro"], dtype=float) / integration_s
    return FlowColumns(
        time_s=np.asarray(f["time_usec"], dtype=float) * 1e-6,
        scene_x=-iy,
        scene_y=+ix,
        increment=True,
        integration_s=integration_s,
        quality=np.asarray(f["quality"]),
        counts_x=np.full_like(ix, nan),
        counts_y=np.full_like(ix, nan),
        body_x_rad_s=body_x,
        body_y_rad_s=body_y,
    )


def flow_scalar(msg: Any, profile: Profile, q_rad_per_count: float) -> FlowColumns:
    """``flow_columns`` for one pymavlink message (the live loop), its values as Python floats
    (the quality as an int): the same mapping, so one rule."""
    with np.errstate(all="ignore"):
        c = flow_columns(FieldView(msg), profile, q_rad_per_count)
    return FlowColumns(float(c.time_s), float(c.scene_x), float(c.scene_y), c.increment, float(c.integration_s),
                       int(c.quality), float(c.counts_x), float(c.counts_y), float(c.body_x_rad_s),
                       float(c.body_y_rad_s))


def _optional_integration_s(f: Any, like: np.ndarray) -> np.ndarray:
    """``integration_time_us`` in s where the source states it (MAVLink OPTICAL_FLOW has no such
    field; importers such as the CSV one add it when a reading covers less than the row spacing),
    else NaN: the frame spacing is used."""
    try:
        us = f["integration_time_us"]
    except (KeyError, AttributeError, RecordingError):  # the field is absent (dict, message, table)
        return np.full_like(like, np.nan)
    return np.broadcast_to(np.asarray(us, dtype=float) * 1e-6, np.shape(like)).copy()


class FieldView:
    """Dict-like access to a pymavlink message's fields (``view['flow_x']``)."""

    __slots__ = ("_msg",)

    def __init__(self, msg: Any) -> None:
        self._msg = msg

    def __getitem__(self, key: str) -> Any:
        return getattr(self._msg, key)


def detect_profile(rec: Recording) -> tuple[str, str]:
    """Which profile fits a recording, and why (one line).

    An importer's ``profile_hint`` wins. OPTICAL_FLOW_RAD without OPTICAL_FLOW is px4.
    OPTICAL_FLOW whose ``time_usec`` advances by about a thousandth of the log time (ms, not
    µs) or whose integer counts are all zero while ``flow_rate_*`` move is ardupilot.
    Otherwise paper.
    """
    if rec.profile_hint:
        return rec.profile_hint, f"set by the {rec.source_format} importer"
    has_flow = "OPTICAL_FLOW" in rec
    if not has_flow and "OPTICAL_FLOW_RAD" in rec:
        return Profile.PX4.value, "flow arrives as OPTICAL_FLOW_RAD (integrated radians)"
    if not has_flow:
        return Profile.PAPER.value, "no flow messages: defaulting to paper"
    of = rec.tables["OPTICAL_FLOW"]
    reasons = []
    if len(of) >= 3:
        dt_log = float(of.t_s[-1] - of.t_s[0])
        dt_field = float(of["time_usec"][-1]) - float(of["time_usec"][0])
        if dt_log > 0.5 and dt_field > 0:
            ratio = dt_field / dt_log
            if 300 < ratio < 3000:
                reasons.append(f"time_usec advances {ratio:.0f} per second (milliseconds)")
    counts = np.abs(np.asarray(of["flow_x"], float)) + np.abs(np.asarray(of["flow_y"], float))
    rates = np.abs(np.asarray(of["flow_rate_x"], float)) + np.abs(np.asarray(of["flow_rate_y"], float))
    rates = rates[np.isfinite(rates)]
    if len(rates) and np.mean(rates > 0) > 0.5 and np.mean(counts > 0) < 0.5 * np.mean(rates > 0):
        reasons.append("flow_rate_x/y carry the flow while flow_x/y are mostly zero")
    if reasons:
        return Profile.ARDUPILOT.value, "; ".join(reasons)
    return Profile.PAPER.value, "OPTICAL_FLOW counts in flow_x/y with time_usec in microseconds"


#: messages whose time field gives a live vehicle's clock, and the field's scale to microseconds
_CLOCK_FIELDS = {m: (TIME_FIELDS[m][0], 1e3 if TIME_FIELDS[m][0] == "time_boot_ms" else 1.0)
                 for m in ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU", "ATTITUDE", "DISTANCE_SENSOR")}
#: OPTICAL_FLOW time_usec / the vehicle's clock in µs: microseconds in [lo, hi], milliseconds in [lo, hi] / 1000
_SAME_UNIT = (0.5, 2.0)
#: the vehicle's clock (µs) must be past this for the ratio to mean anything (20 ms = one frame)
_MIN_CLOCK_US = 10_000.0
#: flow messages after which the content alone decides, when no clock has told the unit
CONTENT_FRAMES = 25


def autopilot_name(autopilot: int | None) -> str:
    """MAV_AUTOPILOT's short name (``ArduPilot``, ``PX4``, ``GENERIC``, ...)."""
    if autopilot is None:
        return "unknown"
    if autopilot == 3:  # MAV_AUTOPILOT_ARDUPILOTMEGA
        return "ArduPilot"
    if autopilot == 12:  # MAV_AUTOPILOT_PX4
        return "PX4"
    from pymavlink.dialects.v20 import ardupilotmega as mav

    entry = mav.enums["MAV_AUTOPILOT"].get(int(autopilot))
    return entry.name.removeprefix("MAV_AUTOPILOT_") if entry is not None else str(autopilot)


class LiveProfileDetector:
    """Which profile a live vehicle speaks, from its messages: ``detect_profile``'s rules for a link.

    ``observe(msg)`` with each message from the vehicle; it returns ``(profile, reason)`` once it
    can tell (and ``result`` keeps it), None before.

    - OPTICAL_FLOW_RAD before any OPTICAL_FLOW: px4.
    - OPTICAL_FLOW: its ``time_usec`` against the vehicle's own clock in the same stream (the latest
      RAW_IMU / HIGHRES_IMU ``time_usec``, or SCALED_IMU / ATTITUDE / DISTANCE_SENSOR
      ``time_boot_ms``): the same number of microseconds is paper; a thousandth of it is
      ardupilot (ArduPilot fills ``time_usec`` with milliseconds). One frame past boot time
      0.01 s is enough.
    - When the times cannot tell (boot time 0, or no clock): ``ground_distance`` -1 is paper (the
      flow sensor has no range of its own; ArduPilot sends its height above ground, 0 without one).
    - Without a clock to compare, after ``CONTENT_FRAMES`` flow messages: ``flow_rate_x/y`` moving
      while the integer ``flow_x/y`` stay zero is ardupilot (ArduPilot's truncated rad/s); counts that
      move are paper.
    - The HEARTBEAT's autopilot (MAV_AUTOPILOT_ARDUPILOTMEGA, PX4, ...) is named in the reason but
      decides nothing alone: the project's simulated vehicle presents itself as ArduPilot in
      every profile.
    """

    def __init__(self) -> None:
        self.autopilot: int | None = None
        self.clock_us: float | None = None
        self.clock_from = ""
        self.n_flow = 0
        self.n_rates_only = 0
        self.n_counts = 0
        self.result: tuple[Profile, str] | None = None

    def _decide(self, profile: Profile, why: str) -> tuple[Profile, str]:
        self.result = (profile, f"{why}; HEARTBEAT autopilot {autopilot_name(self.autopilot)}")
        return self.result

    def observe(self, msg: Any) -> tuple[Profile, str] | None:
        if self.result is not None:
            return self.result
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            self.autopilot = int(msg.autopilot)
        elif mtype in _CLOCK_FIELDS:
            name, scale = _CLOCK_FIELDS[mtype]
            self.clock_us = float(getattr(msg, name)) * scale
            self.clock_from = f"{mtype} {name}"
        elif mtype == "OPTICAL_FLOW_RAD" and self.n_flow == 0:
            return self._decide(Profile.PX4, "flow arrives as OPTICAL_FLOW_RAD (integrated radians)")
        elif mtype == "OPTICAL_FLOW":
            return self._on_flow(msg)
        return None

    def _on_flow(self, msg: Any) -> tuple[Profile, str] | None:
        self.n_flow += 1
        t = float(msg.time_usec)
        if self.clock_us is not None and self.clock_us >= _MIN_CLOCK_US and t > 0:
            ratio = t / self.clock_us
            lo, hi = _SAME_UNIT
            clock = f"{self.clock_from} {self.clock_us:.0f} us"
            if lo <= ratio <= hi:
                return self._decide(Profile.PAPER, f"OPTICAL_FLOW time_usec {t:.0f} against {clock}: microseconds")
            if lo * 1e-3 <= ratio <= hi * 1e-3:
                return self._decide(Profile.ARDUPILOT, f"OPTICAL_FLOW time_usec {t:.0f} against {clock}: "
                                                       "milliseconds (ArduPilot's convention)")
        if float(msg.ground_distance) == -1.0:
            return self._decide(Profile.PAPER, "OPTICAL_FLOW ground_distance -1 (no range of its own: the paper's "
                                               "convention; ArduPilot sends its height)")
        counts = abs(float(msg.flow_x)) + abs(float(msg.flow_y))
        rates = abs(float(msg.flow_rate_x)) + abs(float(msg.flow_rate_y))
        if counts > 0:
            self.n_counts += 1
        elif math.isfinite(rates) and rates > 0:
            self.n_rates_only += 1
        if self.n_flow >= CONTENT_FRAMES:
            if self.n_rates_only > self.n_flow // 2 and self.n_counts < self.n_rates_only // 2:
                return self._decide(Profile.ARDUPILOT, "flow_rate_x/y carry the flow while flow_x/y are mostly zero")
            if self.n_counts > self.n_flow // 4 and self.n_rates_only == 0:
                return self._decide(Profile.PAPER, "OPTICAL_FLOW counts move in flow_x/y")
        return None
