"""Fuzzing (hypothesis): the recording reader and the tools behind ``replay`` and ``info``, the
companion's message handling, and the simulated vehicle's; plus property tests of the control
step with any gains and tilt limit.

What must hold whatever arrives:
- ``read_tlog`` on a mutated recording returns a ``Recording`` or raises ``RecordingError``
  (nothing else, and never hangs); ``replay`` and ``info`` on what it read do the same, and
  every replayed command is finite and inside the tilt limit;
- the live companion (``LiveCompanion._on_message``, the path every received message takes)
  never raises, and every SET_ATTITUDE_TARGET it sends has a finite unit quaternion, a roll and
  pitch inside the tilt limit and thrust 0.5;
- the simulated vehicle's model (``Vehicle.handle``) never raises, every reply packs, and its
  physics stays finite.

The default run is short (a few seconds); ``make test-slow`` runs the same properties with
many more examples (``@pytest.mark.slow``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.config import Config, load_config
from companion.errors import RecordingError
from companion.mavlink import link, outbound
from companion.mavlink.live import LiveCompanion
from companion.recordings.tlog_reader import read_tlog
from companion.step.core import CompanionCore, Plausibility, PlausibilityParams
from companion.step.profiles import FlowColumns, Profile
from companion.tools.info import summarise
from companion.tools.replay import replay
from simvehicle.engines.scenarios import Scenario, fly
from simvehicle.model import telemetry
from simvehicle.model.sim import Simulator
from simvehicle.server.server import StreamSchedule, Vehicle

mav = link.mav
CFG = load_config()
LIMIT = CFG.controller.tilt_limit_rad
FAST = settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
SLOW = settings(max_examples=1500, deadline=None, suppress_health_check=list(HealthCheck))
#: a read of a ~25 kB recording must not take longer than this (s): no pathological resync
READ_TIME_LIMIT_S = 5.0


def _both(test: Any, strategy: Any) -> tuple[Any, Any]:
    """The same property as a short default test and a long ``slow`` one."""
    fast = FAST(given(strategy)(test))
    slow = pytest.mark.slow(SLOW(given(strategy)(test)))
    return fast, slow


# ---------------------------------------------------------------------------------------------
# 1. The recording reader and the tools on what it reads


@pytest.fixture(scope="module")
def small_tlog(tmp_path_factory) -> bytes:
    """1 s of closed-loop flight at 0.5 m/s (51 frames, about 460 records)."""
    path = tmp_path_factory.mktemp("fuzz") / "small.tlog"
    fly(CFG, Scenario("fuzz", 1.0, lambda t: (0.5, -0.3)), tlog=path)
    return path.read_bytes()


mutation = st.one_of(
    st.tuples(st.just("flip"), st.floats(0, 1), st.integers(0, 7)),
    st.tuples(st.just("set"), st.floats(0, 1), st.integers(0, 255)),
    st.tuples(st.just("insert"), st.floats(0, 1), st.binary(min_size=1, max_size=300)),
    st.tuples(st.just("delete"), st.floats(0, 1), st.integers(1, 300)),
    st.tuples(st.just("duplicate"), st.floats(0, 1), st.integers(1, 2000)),
    st.tuples(st.just("truncate"), st.floats(0, 1), st.just(0)),
    st.tuples(st.just("stx"), st.floats(0, 1), st.sampled_from([0xFD, 0xFE])),
)


def mutate(buf: bytes, ops: list[tuple[str, float, Any]]) -> bytes:
    b = bytearray(buf)
    for op, where, arg in ops:
        i = min(int(where * len(b)), max(len(b) - 1, 0))
        if op == "flip" and b:
            b[i] ^= 1 << arg
        elif op in ("set", "stx") and b:
            b[i] = arg
        elif op == "insert":
            b[i:i] = arg
        elif op == "delete":
            del b[i:i + arg]
        elif op == "duplicate":
            b[i:i] = b[i:i + arg]
        elif op == "truncate":
            del b[i:]
    return bytes(b)


def _read_and_use(data: bytes, tmp: Path) -> None:
    path = tmp / "fuzzed.tlog"
    path.write_bytes(data)
    t0 = time.monotonic()
    try:
        rec = read_tlog(path)
    except RecordingError:
        return
    assert time.monotonic() - t0 < READ_TIME_LIMIT_S
    assert rec.skipped_bytes >= 0 and rec.n_messages > 0
    try:
        s = summarise(rec)
        assert s["n_messages"] == rec.n_messages
    except RecordingError:
        pass
    try:
        res = replay(rec, CFG, Profile.PAPER)
    except RecordingError:
        return
    for col in ("roll_cmd_rad", "pitch_cmd_rad"):
        c = np.asarray(res[col], float)
        assert np.all(np.isfinite(c)) and np.all(np.abs(c) <= LIMIT)


def _reader_property(small_tlog: bytes, tmp_path_factory: Any, ops: list) -> None:
    _read_and_use(mutate(small_tlog, ops), tmp_path_factory.mktemp("f", numbered=True))


_ops = st.lists(mutation, min_size=1, max_size=12)


@FAST
@given(ops=_ops)
def test_reader_replay_and_info_survive_mutations(small_tlog, tmp_path_factory, ops):
    _reader_property(small_tlog, tmp_path_factory, ops)


@pytest.mark.slow
@SLOW
@given(ops=_ops)
def test_reader_replay_and_info_survive_mutations_long(small_tlog, tmp_path_factory, ops):
    _reader_property(small_tlog, tmp_path_factory, ops)


@FAST
@given(data=st.binary(max_size=3000))
def test_reader_survives_random_bytes(tmp_path_factory, data):
    _read_and_use(data, tmp_path_factory.mktemp("r", numbered=True))


# ---------------------------------------------------------------------------------------------
# 2. Message strategies from the dialect's own field types

_INT_RANGES = {"int8_t": (-2**7, 2**7 - 1), "uint8_t": (0, 2**8 - 1), "int16_t": (-2**15, 2**15 - 1),
               "uint16_t": (0, 2**16 - 1), "int32_t": (-2**31, 2**31 - 1), "uint32_t": (0, 2**32 - 1),
               "int64_t": (-2**63, 2**63 - 1), "uint64_t": (0, 2**64 - 1)}
#: floats over the whole float32 line, with the special values drawn often
any_float = st.one_of(st.sampled_from([math.nan, math.inf, -math.inf, 0.0, 1.0, -1.0, 20.0, 1e30]),
                      st.floats(allow_nan=True, allow_infinity=True, width=32))


#: values of integer fields that reach deep into the handlers (a random uint16 is almost never a
#: command either side supports), drawn three times in four
_INTERESTING = {
    "command": [mav.MAV_CMD_DO_SET_MODE, mav.MAV_CMD_COMPONENT_ARM_DISARM, mav.MAV_CMD_SET_MESSAGE_INTERVAL,
                mav.MAV_CMD_GET_MESSAGE_INTERVAL, mav.MAV_CMD_REQUEST_MESSAGE,
                mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES],
    "target_system": [0, 1], "target": [0, 1], "target_component": [0, 1, outbound.COMPANION_COMPONENT],
    "coordinate_frame": [1, 8, 9, 12], "orientation": [25], "type_mask": [outbound.VELOCITY_TYPE_MASK, 7],
    "quality": [0, 255], "custom_mode": [0, 2, 4, 20], "base_mode": [1, 129], "type": [2, 6, 18],
    "autopilot": [3, 8], "req_stream_id": [0, 1, 2, 6, 10, 12], "start_stop": [0, 1], "result": [0, 2, 3, 4, 5],
}


def _field(name: str, ftype: str, length: int) -> st.SearchStrategy:
    if ftype == "char":
        return st.binary(min_size=0 if length else 1, max_size=length or 1)
    if ftype in ("float", "double"):
        one = any_float if ftype == "float" else st.floats(allow_nan=True, allow_infinity=True)
    else:
        lo, hi = _INT_RANGES[ftype]
        one = st.one_of(st.integers(lo, hi), st.sampled_from([lo, hi, 0, 1]))
        fits = [v for v in _INTERESTING.get(name, ()) if lo <= v <= hi]
        if fits:  # three times in four
            one = st.one_of(st.sampled_from(fits), st.sampled_from(fits), st.sampled_from(fits), one)
    return st.lists(one, min_size=length, max_size=length) if length else one


def message(cls: type) -> st.SearchStrategy:
    """Any instance of a pymavlink message class: every field over its whole wire range."""
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))  # type: ignore[attr-defined]
    fields = [_field(n, t, lengths[n])
              for n, t in zip(cls.fieldnames, cls.fieldtypes, strict=True)]  # type: ignore[attr-defined]
    return st.tuples(*fields).map(lambda vals: cls(*vals))


def _cls(name: str) -> type:
    return mav.mavlink_map[getattr(mav, f"MAVLINK_MSG_ID_{name}")]


COMPANION_INPUTS = ["OPTICAL_FLOW", "OPTICAL_FLOW_RAD", "RAW_IMU", "SCALED_IMU", "HIGHRES_IMU", "DISTANCE_SENSOR",
                    "ATTITUDE", "HEARTBEAT", "COMMAND_ACK", "COMMAND_LONG", "COMMAND_INT",
                    "SET_POSITION_TARGET_LOCAL_NED", "MANUAL_CONTROL", "STATUSTEXT", "PARAM_VALUE"]
sender = st.one_of(st.just((1, 1)), st.tuples(st.integers(0, 255), st.integers(0, 255)))
fuzz_message = st.tuples(st.one_of(*[message(_cls(n)) for n in COMPANION_INPUTS]), sender)


# ---------------------------------------------------------------------------------------------
# 3. The live companion's message handling


class _Conn:
    """What ``LiveCompanion`` needs of a pymavlink connection: an encoder and ``write``."""

    def __init__(self) -> None:
        self.mav = mav.MAVLink(None, srcSystem=1, srcComponent=outbound.COMPANION_COMPONENT)
        self.written: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.written.append(bytes(buf))

    def close(self) -> None:
        pass


def _pack(msg: Any, sysid: int, compid: int) -> Any:
    enc = mav.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    return mav.MAVLink(None).decode(bytearray(msg.pack(enc)))


def _check_commands(conn: _Conn) -> int:
    parser = mav.MAVLink(None)
    n = 0
    for buf in conn.written:
        for m in parser.parse_buffer(buf) or []:
            assert m.get_type() != "BAD_DATA"
            if m.get_type() == "SET_ATTITUDE_TARGET":
                q = np.array(m.q, float)
                assert np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < 1e-6
                roll, pitch, _ = outbound.quaternion_to_euler(q)
                assert abs(roll) <= LIMIT + 1e-6 and abs(pitch) <= LIMIT + 1e-6
                assert m.thrust == 0.5 and m.type_mask == outbound.ATTITUDE_TYPE_MASK
                n += 1
    return n


event = st.one_of(
    st.tuples(st.just("frames"), st.integers(1, 15)),  # good frames from the simulator
    st.tuples(st.just("message"), fuzz_message),
    st.tuples(st.just("bytes"), st.binary(max_size=400)),
    st.tuples(st.just("wait"), st.floats(0.0, 2.0)),  # wall time passes (watchdog)
)


def _companion_property(events: list) -> None:
    conn = _Conn()
    clock = [100.0]
    live = LiveCompanion(CFG, Profile.PAPER, conn, clock=lambda: clock[0], wall=lambda: 1.7e9 + clock[0],
                         out=lambda _s: None, setpoint_m_s=(0.5, -0.3))
    live.router.vehicle_sysid, live.vehicle_compid = 1, 1
    veh = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    sim = Simulator(CFG)
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    rf = CFG.rangefinder

    def feed(msg: Any) -> None:
        live._on_message(msg, clock[0])

    feed(_pack(telemetry.heartbeat(veh, armed=True), 1, 1))
    for kind, arg in events:
        if kind == "frames":
            for _ in range(arg):
                for m in telemetry.frame_messages(veh, sim.current, Profile.PAPER, CFG.flow_sensor.q_rad_per_count,
                                                  sim.T, rf.min_m, rf.max_m):
                    feed(_pack(m, 1, 1))
                roll, pitch = live.last_cmd_rad
                sim.advance(roll, pitch)
                clock[0] += sim.T
                live._watchdog(clock[0])
        elif kind == "message":
            msg, (sysid, compid) = arg
            feed(_pack(msg, sysid, compid))
        elif kind == "bytes":
            msgs = parser.parse_buffer(arg) or []
            link.discard_partial(parser)
            for m in msgs:
                if m.get_type() != "BAD_DATA":
                    feed(m)
        else:
            clock[0] += arg
            live._watchdog(clock[0])
        assert all(math.isfinite(a) and abs(a) <= LIMIT for a in live.last_cmd_rad)
    _check_commands(conn)


_events = st.lists(event, min_size=1, max_size=40)


@FAST
@given(events=_events)
def test_companion_message_handling_never_raises_and_never_sends_a_bad_command(events):
    _companion_property(events)


@pytest.mark.slow
@SLOW
@given(events=_events)
def test_companion_message_handling_never_raises_and_never_sends_a_bad_command_long(events):
    _companion_property(events)


def test_the_companion_fuzz_harness_flies():
    """The harness itself: good frames alone give one finite command per frame, and a lean."""
    _companion_property([("frames", 60)])  # no exception
    conn = _Conn()
    live = LiveCompanion(CFG, Profile.PAPER, conn, clock=lambda: 0.0, out=lambda _s: None, setpoint_m_s=(0.5, 0.0))
    live.router.vehicle_sysid, live.vehicle_compid = 1, 1
    veh = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    live._on_message(_pack(telemetry.heartbeat(veh, armed=True), 1, 1), 0.0)
    sim = Simulator(CFG)
    for _ in range(30):
        for m in telemetry.frame_messages(veh, sim.current, Profile.PAPER, CFG.flow_sensor.q_rad_per_count, sim.T,
                                          CFG.rangefinder.min_m, CFG.rangefinder.max_m):
            live._on_message(_pack(m, 1, 1), 0.0)
        sim.advance(*live.last_cmd_rad)
    assert _check_commands(conn) == 30  # one per frame
    assert live.last_cmd_rad[1] < 0  # nose down to accelerate forward (CONVENTIONS.md)


# ---------------------------------------------------------------------------------------------
# 4. The simulated vehicle's message handling

VEHICLE_INPUTS = ["SET_ATTITUDE_TARGET", "COMMAND_LONG", "COMMAND_INT", "SET_MODE", "PARAM_REQUEST_LIST",
                  "PARAM_REQUEST_READ", "PARAM_SET", "REQUEST_DATA_STREAM", "HEARTBEAT", "MANUAL_CONTROL"]
_param_names = [p for p in ("GUID_TIMEOUT", "ANGLE_MAX", "SIM_WIND_FX", "SIM_DRAG_B", "SIM_FLOW_SCALE_X",
                            "SIM_FLOW_DELAY", "SIM_ATT_OMEGA", "SIM_ATT_ZETA", "SIM_FLOW_FAULT", "SIM_GYRO_FAULT",
                            "SIM_RNG_FAULT", "SIM_RNG_JUMP", "SIM_REBOOT", "SIM_FLOW_SPIKE")]
param_set = st.tuples(st.sampled_from(_param_names), st.floats(allow_nan=True, allow_infinity=True, width=32)).map(
    lambda nv: mav.MAVLink_param_set_message(1, 1, nv[0].encode(), nv[1], 9))
vehicle_event = st.one_of(
    st.tuples(st.one_of(*[message(_cls(n)) for n in VEHICLE_INPUTS], param_set), sender),
    st.tuples(st.just(None), st.integers(1, 10)),  # frames pass
)


def _vehicle_property(events: list) -> None:
    v = Vehicle(CFG)
    streams = StreamSchedule(v.T)
    v.custom_mode, v.armed = link.GUIDED_NOGPS, True
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    for what, arg in events:
        if what is None:
            for _ in range(arg):
                v.advance()
                for _name, m in v.frame().messages:
                    m.pack(enc)
            continue
        msg = _pack(what, *arg)
        if v.for_me(msg):
            for r in v.handle(msg, streams):
                r.msg.pack(enc)
    s = v.sim.current
    for f in dataclasses.fields(s):
        val = getattr(s, f.name)
        if isinstance(val, float) and f.name != "range_m":
            assert math.isfinite(val), (f.name, val)


_vevents = st.lists(vehicle_event, min_size=1, max_size=30)


@FAST
@given(events=_vevents)
def test_vehicle_message_handling_never_raises(events):
    _vehicle_property(events)


@pytest.mark.slow
@SLOW
@given(events=_vevents)
def test_vehicle_message_handling_never_raises_long(events):
    _vehicle_property(events)


# ---------------------------------------------------------------------------------------------
# 5. The control step with any gains and tilt limit (tests/test_properties.py: Table VI's)


def _with_controller(cfg: Config, kp: float, ki: float, limit_deg: float) -> Config:
    return dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, kp_rad_per_m_s=kp, ki_rad_per_m=ki,
                                                                   tilt_limit_deg=limit_deg))


anything = st.floats(allow_nan=True, allow_infinity=True)
step_event = st.one_of(
    st.tuples(st.just("gyro"), anything, anything, anything),
    st.tuples(st.just("range"), anything, anything),
    st.tuples(st.just("setpoint"), anything, anything),
    st.tuples(st.just("flow"), anything, anything, anything, st.integers(-10, 300), st.booleans(), anything),
)


@FAST
@given(kp=st.floats(0.0, 50.0), ki=st.floats(0.0, 50.0), limit_deg=st.floats(0.5, 60.0),
       events=st.lists(step_event, min_size=1, max_size=60))
def test_any_gains_and_limit_keep_the_command_inside_the_limit(kp, ki, limit_deg, events):
    cfg = _with_controller(CFG, kp, ki, limit_deg)
    core = CompanionCore(cfg)
    plaus = Plausibility(PlausibilityParams.from_config(cfg))
    lim = math.radians(limit_deg)
    for e in events:
        if e[0] == "gyro":
            core.on_gyro(e[1], e[2], e[3])
        elif e[0] == "range":
            core.on_range(e[1], e[2])
        elif e[0] == "setpoint":
            core.set_setpoint(e[1], e[2])
        else:
            _, t, sx, sy, quality, increment, integ = e
            out = core.on_flow(FlowColumns(t, sx, sy, increment, integ, quality, math.nan, math.nan))
            assert math.isfinite(out.roll_cmd_rad) and math.isfinite(out.pitch_cmd_rad)
            assert abs(out.roll_cmd_rad) <= lim and abs(out.pitch_cmd_rad) <= lim
            if not out.holding:  # the live loop's cross-frame checks take anything the core used
                plaus.check(out.time_s, (sx, sy), (out.gyro_x_rad_s, out.gyro_y_rad_s),
                            (out.vx_raw_m_s, out.vy_raw_m_s), out.range_m, None)
