"""The live companion: ``python -m companion run --connect URL [--arm] [--setpoint VX,VY]``.

The socket, the clock and the I/O around one ``companion.mavlink.session.Session``, which holds what the
companion decides (engagement and take-over, setpoints and their decay, one control step per new
flow frame through ``CompanionCore``, staleness and the hold causes, what is said): this module
reads the link, hands each message to the session with its time, runs the session's watchdog
each pass of its loop, and sends what the session returns. The session's messages are the same
``companion.mavlink.outbound`` messages the in-process scenarios send, so a lockstep run over UDP
reproduces them frame for frame. What is the loop's own:

- the sensor profile: ``--profile``, or detected from the vehicle's first messages before
  taking control (``profiles.LiveProfileDetector``: the OPTICAL_FLOW ``time_usec`` unit against
  the vehicle's other clocks, OPTICAL_FLOW_RAD, the flow content), printed with the reason;
- the link: wait for the vehicle's HEARTBEAT, ask for the streams with SET_MESSAGE_INTERVAL,
  send our HEARTBEAT (component 191) at 1 Hz, and with ``--arm`` switch to GUIDED_NOGPS and arm
  (without it, wait for the pilot; the session takes control only while armed in GUIDED_NOGPS);
- reading: what waits on the link is read before it is handled, each message stamped with its
  arrival (the kernel's stamp on UDP) and shown to the session's clock mapping in that order, so
  that a frame of a backlog is aged against the newer samples behind it; when the loop itself
  stood still for more than ``flow_timeout_s`` (the process stopped or starved) the session is
  told (``Session.on_stall``: the hold is "companion stalled") and only the newest flow frame
  waiting is flown, every other one handed in as ``behind`` (dropped);
- sending: each control step as POSITION_TARGET_LOCAL_NED, VISION_SPEED_ESTIMATE (not while
  holding) and SET_ATTITUDE_TARGET (thrust 0.5) last, in one datagram, stamped with the flow
  frame's time; the announcements as STATUSTEXT from component 191, rate limited
  (``TextLimiter``) so a flapping cause cannot flood the link, and on the console; the
  ``--tlog`` recording (``RecordStamps``);
- a message that cannot be handled is counted and dropped, never fatal; on UDP each datagram is
  parsed on its own; commands to the companion are refused with a COMMAND_ACK; what is refused is
  counted in the status line (``rejected N``) and the exit summary.

The failsafes and announcements themselves are described in ``companion.mavlink.session``.
"""

from __future__ import annotations

import math
import signal
import sys
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.config import Config, load_config
from companion.errors import LinkError, UsageError, check_output, output_error
from companion.mavlink import link, outbound
from companion.mavlink.session import AGE_SLACK_S as AGE_SLACK_S
from companion.mavlink.session import BACKLOG_SAY_FRAMES as BACKLOG_SAY_FRAMES
from companion.mavlink.session import HEARTBEAT_TIMEOUT_S as HEARTBEAT_TIMEOUT_S
from companion.mavlink.session import LONG_HOLD_S as LONG_HOLD_S
from companion.mavlink.session import MAX_FRAME_AGE_FRAMES as MAX_FRAME_AGE_FRAMES
from companion.mavlink.session import REBOOT_JUMP_S as REBOOT_JUMP_S
from companion.mavlink.session import Command, Estimate, HoldMonitor, Out, Say, Session, vehicle_time_s
from companion.mavlink.session import safe_attitude as safe_attitude
from companion.mavlink_ids import GUIDED_NOGPS
from companion.recordings.tlog_writer import SIM_CLOCK_TEXT, SIM_EPOCH_S, TlogWriter
from companion.step.core import FrameOrder as FrameOrder  # (re-exported: companion.mavlink.live.FrameOrder)
from companion.step.core import HoldCause, StepOutput
from companion.step.core import classify_frame as classify_frame
from companion.step.profiles import FLOW_MESSAGE, LiveProfileDetector, Profile
from companion.step.setpoint import decayed_setpoint as decayed_setpoint

mav = link.mav

#: seconds to wait for the vehicle's first HEARTBEAT before giving up
CONNECT_TIMEOUT_S = 30.0
COMMAND_RETRY_S = 1.0
#: wall-clock seconds after the vehicle is heard before "profile still unknown" is said
PROFILE_WARN_S = 5.0
#: STATUSTEXTs to the ground station (wall clock): the same text at most once per TEXT_REPEAT_S, and
#: all texts at most TEXT_BURST at once and TEXT_RATE_HZ sustained (``TextLimiter``)
TEXT_REPEAT_S = 1.0
TEXT_BURST = 20
TEXT_RATE_HZ = 5.0
#: the characters a STATUSTEXT carries
STATUSTEXT_LEN = 50
#: the most messages read from the link in one go: what is waiting is read before any of it is
#: handled, so that a frame is aged against the newer samples already behind it
READ_AHEAD_MAX = 2000
#: the attribute a message read from the link carries: its arrival on the companion's clock (s)
ARRIVAL_ATTR = "flowhold_arrival_s"
COMMAND_TRIES = 5
STATUS_PERIOD_TTY_S = 0.25
STATUS_PERIOD_LOG_S = 5.0
#: counters of input that was refused or dropped (shown as "rejected" in the status line)
REJECTION_COUNTERS = frozenset({"bad packets", "packets rejected: unsigned or badly signed", "unreadable input",
                                "oversized datagrams dropped",
                                "sensor data from another system", "commands refused (unsupported)"})


# ---------------------------------------------------------------------------------------------
# Pure pieces


def parse_setpoint(text: str) -> tuple[float, float]:
    """``"VX,VY"`` (m/s, body frame) -> (vx, vy); UsageError when malformed or not finite."""
    parts = str(text).split(",")
    try:
        vx, vy = (float(p) for p in parts)
    except ValueError:
        raise UsageError(f"--setpoint: expected VX,VY in m/s (e.g. 1.5,0), got {text!r}") from None
    if not (math.isfinite(vx) and math.isfinite(vy)):
        raise UsageError(f"--setpoint: values must be finite, got {text!r}")
    return vx, vy


class RecordStamps:
    """The companion's ``--tlog`` with the stamps a log of this link should carry.

    A real vehicle (and the simulated one in real time): the wall clock, as MAVProxy stamps. A
    simulated vehicle whose clock is not the wall clock says so in a STATUSTEXT ("simvehicle:
    simulated clock (lockstep)") before any sensor data: then, as a SITL's log, ``SIM_EPOCH_S`` + the
    vehicle's time (its messages' time fields, carried on across a reboot), so the companion's and
    the vehicle's recordings share their time axis. Should the vehicle's clock stand still for
    ``FREEZE_S`` of wall time (the vehicle stopped or gone), stamps run on at the wall clock's rate
    from there. Stamps never go back.

    Records written before the clock is known (the first HEARTBEATs) wait in memory: until a
    sensor message arrives without the STATUSTEXT before it (the wall clock), or the STATUSTEXT
    and then a time field, or ``PENDING_MAX_S`` of wall time.
    """

    FREEZE_S = 0.5
    PENDING_MAX_S = 2.0

    def __init__(self, writer: TlogWriter, wall: Callable[[], float], clock: Callable[[], float]) -> None:
        self.writer = writer
        self.wall = wall
        self.clock = clock
        #: None until known; then whether stamps are simulated time
        self.simulated: bool | None = None
        self.note = ""
        self._vt: float | None = None  # the vehicle's time (s), made monotonic across reboots
        self._last_raw: float | None = None
        self._offset = 0.0
        self._vt_clock = 0.0  # monotonic clock when the vehicle's time last advanced
        self._last_stamp = -math.inf
        self._pending: list[tuple[bytes, float]] = []
        self._first_clock: float | None = None

    def observe(self, msg: Any) -> None:
        """A message from the vehicle, before it is recorded: the clock notice and its time."""
        if msg.get_type() == "STATUSTEXT" and SIM_CLOCK_TEXT in str(msg.text):
            if self.simulated is None:
                self.simulated = True
                self.note = str(msg.text)
            return
        t = vehicle_time_s(msg)
        if t is None or not math.isfinite(t):
            return
        if self.simulated is None:
            self.simulated = False  # sensor data came first: not a simulated clock
        if self._last_raw is not None and t < self._last_raw - 1.0:  # a reboot: carry the time on
            self._offset += self._last_raw - t
        if self._vt is None or t + self._offset > self._vt:
            self._vt = t + self._offset
            self._vt_clock = self.clock()
        self._last_raw = t

    def _stamp(self) -> float:
        if not self.simulated:
            return self.wall()
        assert self._vt is not None
        stalled = max(0.0, self.clock() - self._vt_clock - self.FREEZE_S)
        stamp = max(SIM_EPOCH_S + self._vt + stalled, self._last_stamp)
        self._last_stamp = stamp
        return stamp

    def write(self, packet: bytes) -> None:
        now = self.clock()
        if self.simulated is None or (self.simulated and self._vt is None):
            if self._first_clock is None:
                self._first_clock = now
            if now - self._first_clock <= self.PENDING_MAX_S:
                self._pending.append((packet, self.wall()))
                return
            self._settle()
        self._flush()
        self.writer.write_bytes(packet, self._stamp())

    def _settle(self) -> None:
        """No time to stamp with: what waits is stamped with the wall clock, as is what follows
        until the vehicle's time is known."""
        if self.simulated is None or self._vt is None:
            self.simulated = False

    def _flush(self) -> None:
        if not self._pending:
            return
        pending, self._pending = self._pending, []
        for packet, wall in pending:
            self.writer.write_bytes(packet, self._stamp() if self.simulated else wall)

    def close(self) -> None:
        self._settle()
        self._flush()
        self.writer.close()


class TextLimiter:
    """Rate limit for the STATUSTEXTs the companion sends (times passed in, s), so that a flapping
    cause (a hold that comes and goes every frame) cannot flood the link, while every new cause is
    still said at once.

    A text goes out at once unless the same text went out less than ``repeat_s`` ago (the flapping
    case), or the token bucket (``burst`` texts, refilled at ``rate_hz``: a cap on many causes at
    once) is empty. Otherwise it is held back: only the latest held-back text is kept, and it goes
    out (``offer`` of a new text, or ``poll``) once allowed, with the number of texts that never went
    out (`` (+N held back)``), so the ground station always ends with the current state."""

    def __init__(self, repeat_s: float = TEXT_REPEAT_S, burst: int = TEXT_BURST,
                 rate_hz: float = TEXT_RATE_HZ) -> None:
        self.repeat_s = repeat_s
        self.burst = burst
        self.rate_hz = rate_hz
        self.tokens = float(burst)
        self._t: float | None = None
        self._sent_at: dict[str, float] = {}
        self.held: tuple[str, int] | None = None
        self.n_held = 0
        #: texts that never went out
        self.dropped = 0

    def _refill(self, now_s: float) -> None:
        if self._t is not None:
            self.tokens = min(float(self.burst), self.tokens + max(0.0, now_s - self._t) * self.rate_hz)
        self._t = now_s

    def _allowed(self, now_s: float, text: str) -> bool:
        return self.tokens >= 1.0 and now_s - self._sent_at.get(text, -math.inf) >= self.repeat_s

    def _send(self, now_s: float, text: str, severity: int) -> tuple[str, int]:
        self.tokens -= 1.0
        self._sent_at[text] = now_s
        n, self.n_held, self.held = self.n_held, 0, None
        if n:
            suffix = f" (+{n} held back)"
            text = text[:STATUSTEXT_LEN - len(suffix)] + suffix
        return text, severity

    def offer(self, now_s: float, text: str, severity: int) -> tuple[str, int] | None:
        """(text, severity) to send now, or None when it is held back."""
        self._refill(now_s)
        if self.held is not None:  # the state moved on: what was held back will never go out
            self.n_held += 1
            self.dropped += 1
            self.held = None
        if self._allowed(now_s, text):
            return self._send(now_s, text, severity)
        self.held = (text, severity)
        return None

    def poll(self, now_s: float) -> tuple[str, int] | None:
        """The held-back text, once it is allowed (None otherwise)."""
        self._refill(now_s)
        if self.held is None or not self._allowed(now_s, self.held[0]):
            return None
        return self._send(now_s, *self.held)


@dataclass
class PendingCommand:
    what: str
    command: int
    params: tuple[float, ...]
    required: bool
    tries: int = 0
    next_send_s: float = 0.0


class Commander:
    """COMMAND_LONGs sent one at a time, resent until COMMAND_ACK (times passed in)."""

    def __init__(self) -> None:
        self.queue: deque[PendingCommand] = deque()
        self.warnings: list[str] = []

    def add(self, what: str, command: int, *params: float, required: bool = True) -> None:
        self.queue.append(PendingCommand(what, command, params, required))

    @property
    def idle(self) -> bool:
        return not self.queue

    def poll(self, now_s: float, send: Callable[[PendingCommand], None]) -> None:
        if not self.queue:
            return
        head = self.queue[0]
        if now_s < head.next_send_s:
            return
        if head.tries >= COMMAND_TRIES:
            self.queue.popleft()
            if head.required:
                raise LinkError(f"the vehicle never acknowledged: {head.what}")
            self.warnings.append(f"no answer to {head.what}")
            return
        send(head)
        head.tries += 1
        head.next_send_s = now_s + COMMAND_RETRY_S

    def on_ack(self, command: int, result: int) -> PendingCommand | None:
        """The pending command this ACK answers (popped), or None. Raises LinkError when a
        required command is refused."""
        if not self.queue or self.queue[0].command != command:
            return None
        if result == mav.MAV_RESULT_IN_PROGRESS:
            return None
        head = self.queue.popleft()
        if result != mav.MAV_RESULT_ACCEPTED:
            name = mav.enums["MAV_RESULT"][result].name if result in mav.enums["MAV_RESULT"] else str(result)
            if head.required:
                raise LinkError(f"the vehicle refused: {head.what} ({name})")
            self.warnings.append(f"{head.what}: {name}")
        return head


# ---------------------------------------------------------------------------------------------
# The loop

class LiveCompanion:
    """The companion's live loop over one pymavlink connection (see the module docstring): the
    socket, the clock and the I/O around one ``session.Session``, which decides what is sent."""

    def __init__(self, cfg: Config, profile: Profile | None, conn: Any, *, url: str = "", arm: bool = False,
                 setpoint_m_s: tuple[float, float] | None = None, tlog: str | None = None,
                 vehicle_sysid: int | None = None, quiet: bool = False,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time,
                 out: Callable[[str], None] | None = None) -> None:
        self.cfg = cfg
        #: None: detect it from the vehicle's messages (``LiveProfileDetector``) before taking
        #: control; until then the core runs on a provisional profile and steps no flow frame
        self.detector = LiveProfileDetector() if profile is None else None
        self.session = Session(cfg, profile, vehicle_sysid=vehicle_sysid, setpoint_m_s=setpoint_m_s)
        self.core = self.session.core
        self.router = self.session.router
        #: what was counted, the session's and the link's (one Counter, shared)
        self.counters = self.session.counters
        self.conn = conn
        self.url = url
        self.arm = arm
        self.clock = clock
        self.wall = wall
        self.quiet = quiet
        self.out = out or (lambda text: print(text, flush=True))
        self.want_sysid = vehicle_sysid
        self.vehicle_compid = 1
        self.T = cfg.flow_sensor.frame_period_s
        self.commander = Commander()
        self.texts = TextLimiter()
        self.tlog = RecordStamps(TlogWriter(tlog), wall, clock) if tlog else None
        self.tlog_path = tlog
        self._next_heartbeat = -math.inf
        self._next_status = -math.inf
        self._loop_wall: float | None = None  # when the main loop last ran (its gaps are stalls)
        #: while handling a stall's backlog: the one flow frame to resume from (the newest waiting)
        self._catching_up = False
        self._resume_frame: Any | None = None
        self._vehicle_heard_wall: float | None = None
        self._profile_warned = False
        self._requested_flow: set[str] = set()
        self._tty = sys.stdout.isatty()
        #: UDP: read whole datagrams (an unfinished packet at a datagram's end is dropped, not
        #: joined to the next datagram); their messages wait here
        self._datagrams = link.is_datagram_link(conn)
        self._pending: deque[Any] = deque()
        #: set by a signal handler (Ctrl-C, SIGTERM): the loop ends between two messages
        self.stop_requested = False

    # -- the session's state, as the loop and its callers read it --------------------------

    @property
    def profile(self) -> Profile:
        return self.session.profile

    @property
    def profile_known(self) -> bool:
        return self.session.profile_known

    @property
    def in_control(self) -> bool:
        return self.session.in_control

    @property
    def armed(self) -> bool:
        return self.session.armed

    @property
    def mode(self) -> int:
        return self.session.mode

    @property
    def control_start(self) -> float | None:
        return self.session.control_start

    @property
    def last_step(self) -> StepOutput | None:
        return self.session.last_step

    @property
    def last_cmd_rad(self) -> tuple[float, float]:
        return self.session.last_cmd_rad

    @property
    def monitor(self) -> HoldMonitor:
        return self.session.monitor

    # -- sending -------------------------------------------------------------------------

    def _send(self, *msgs: Any, taken_up_s: float | None = None) -> None:
        """Pack ``msgs`` in order and write them in one go (one datagram on UDP). ``taken_up_s``: a
        step's messages, whose frame was taken up then; they are not written when the process
        stopped for longer than ``flow_timeout_s`` since (a SIGSTOP or a swap that fell inside the
        step: they would fly a frame that old), and the sequence numbers they took are given back.
        Checked last, after packing, just before the write: a stop can fall anywhere in the step,
        and building and packing them is a few hundred microseconds of it."""
        enc = self.conn.mav
        before = (enc.seq, enc.total_packets_sent, enc.total_bytes_sent)
        bufs = []
        for msg in msgs:
            buf = bytes(msg.pack(enc))
            enc.seq = (enc.seq + 1) % 256
            enc.total_packets_sent += 1
            enc.total_bytes_sent += len(buf)
            bufs.append(buf)
        if taken_up_s is not None and self.clock() - taken_up_s > self.cfg.companion.flow_timeout_s:
            enc.seq, enc.total_packets_sent, enc.total_bytes_sent = before
            self.counters["commands not sent (stalled inside the step)"] += 1
            return
        try:
            self.conn.write(b"".join(bufs))
        except Exception:  # noqa: BLE001 - a full buffer or a gone serial port must not stop the loop
            self.counters["send errors"] += 1
            return
        if self.tlog is not None:
            for buf in bufs:
                self.tlog.write(buf)

    def _emit(self, outs: list[Out], taken_up_s: float | None = None) -> None:
        """Send what the session asked for, in its order; ``taken_up_s``: the clock when the message
        these answer was taken up (``_send_step``)."""
        for o in outs:
            if isinstance(o, Command):
                self._send_step(o, taken_up_s)
            elif isinstance(o, Estimate):
                self._send(outbound.vision_speed(self.conn.mav, int(round(o.time_s * 1e6)), o.vx_m_s, o.vy_m_s,
                                                 o.vx_var_m2_s2, o.vy_var_m2_s2))
            elif isinstance(o, Say):
                self._statustext(o.text, o.severity, console=o.console)
            else:
                self.out(o.text)

    def _send_step(self, c: Command, taken_up_s: float | None = None) -> None:
        """POSITION_TARGET_LOCAL_NED, VISION_SPEED_ESTIMATE (with an estimate), then SET_ATTITUDE_TARGET,
        in one datagram, in MAVLink's units. A step's command (``taken_up_s``: the clock when its
        frame was taken up) is not sent when the process stopped between then and its write for
        longer than ``flow_timeout_s`` (``_send``); the main loop then sees the stall and resumes
        from the newest frame (``_on_stall``). The watchdog's level commands are always sent."""
        ms = int(round(c.time_s * 1e3)) if math.isfinite(c.time_s) else 0
        enc = self.conn.mav
        msgs = [outbound.position_target(enc, ms, c.vx_set_m_s, c.vy_set_m_s)]
        if c.estimate is not None:
            msgs.append(outbound.vision_speed(enc, int(round(c.time_s * 1e6)), *c.estimate))
        msgs.append(outbound.set_attitude_target(enc, ms, self.router.vehicle_sysid or 1, c.roll_rad, c.pitch_rad,
                                                 c.yaw_rad, self.vehicle_compid))
        self._send(*msgs, taken_up_s=taken_up_s)

    def _statustext(self, text: str, severity: int, console: str | None = None) -> None:
        """Say ``text`` to the ground station (STATUSTEXT from component 191, rate limited by
        ``TextLimiter``) and on the console (``console`` if given: it may say more than 50 characters)."""
        self.out(console or text)
        said = self.texts.offer(self.clock(), text, severity)
        if self.texts.dropped:
            self.counters["status texts dropped (rate limit)"] = self.texts.dropped
        if said is not None:
            self._send(link.statustext(self.conn.mav, *said))

    def _poll_texts(self, now: float) -> None:
        said = self.texts.poll(now)
        if said is not None:
            self._send(link.statustext(self.conn.mav, *said))

    def _send_command(self, p: PendingCommand) -> None:
        self._send(link.command_long(self.conn.mav, self.router.vehicle_sysid or 1, self.vehicle_compid,
                                     p.command, *p.params))

    # -- connection ----------------------------------------------------------------------

    def connect(self, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
        """Send our HEARTBEAT until a vehicle's arrives (LinkError after ``timeout_s``)."""
        self.out(f"flowhold: waiting for a vehicle on {self.url} ...")
        deadline = self.clock() + timeout_s
        while self.router.vehicle_sysid is None and not self.stop_requested:
            now = self.clock()
            if now > deadline:
                raise LinkError(f"no HEARTBEAT from a vehicle on {self.url} within {timeout_s:g} s")
            self._check_open()
            self._heartbeat(now)
            msg = self._recv()
            if msg is None:
                if not self._pending:
                    self.conn.select(0.05)
                continue
            if link.is_vehicle_heartbeat(msg) and self.want_sysid in (None, msg.get_srcSystem()):
                self.router.vehicle_sysid = msg.get_srcSystem()
                self.vehicle_compid = msg.get_srcComponent()
                self.conn.mav.srcSystem = msg.get_srcSystem()  # a companion shares its vehicle's system id
                self._on_message(msg, now)
                self.out(f"flowhold: vehicle {msg.get_srcSystem()} heard ({link.mode_name(msg.custom_mode)}, "
                         f"{'armed' if link.heartbeat_armed(msg) else 'disarmed'})")
        if self.stop_requested:
            return
        self._vehicle_heard_wall = self.clock()
        flow = FLOW_MESSAGE[self.profile]
        if self.detector is None:
            self.out(f"flowhold: sensor profile {self.profile.value} (given)")
        elif self.detector.result is None:
            self.out("flowhold: sensor profile: detecting it from the vehicle's messages (or give --profile)")
            # until the flow tells: the flow message of the vehicle's kind (PX4 sends OPTICAL_FLOW_RAD)
            flow = "OPTICAL_FLOW_RAD" if self.detector.autopilot == mav.MAV_AUTOPILOT_PX4 else "OPTICAL_FLOW"
        for name in (flow, "RAW_IMU", "DISTANCE_SENSOR", "ATTITUDE"):
            self._request_stream(name)
        if self.arm:
            if self.mode != GUIDED_NOGPS:
                self.commander.add("switch to GUIDED_NOGPS", mav.MAV_CMD_DO_SET_MODE,
                                   mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED_NOGPS)
            if not self.armed:
                self.commander.add("arm", mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        else:
            self.out("flowhold: waiting for the pilot to arm in GUIDED_NOGPS")

    def _request_stream(self, name: str) -> None:
        if name in FLOW_MESSAGE.values():
            self._requested_flow.add(name)
        mid = getattr(mav, f"MAVLINK_MSG_ID_{name}")
        self.commander.add(f"stream {name} at {1 / self.T:g} Hz", mav.MAV_CMD_SET_MESSAGE_INTERVAL, mid,
                           round(self.T * 1e6), required=False)

    def _detect(self, msg: Any) -> None:
        """Feed the profile detector a vehicle message; bind the profile once it can tell."""
        assert self.detector is not None
        found = self.detector.observe(msg)
        if found is None:
            return
        profile, why = found
        self.session.set_profile(profile)
        self.out(f"flowhold: sensor profile {profile.value} (detected: {why})")
        if FLOW_MESSAGE[profile] not in self._requested_flow:
            self._request_stream(FLOW_MESSAGE[profile])

    def _check_open(self) -> None:
        """LinkError when a stream link (TCP) has been closed by the other end."""
        why = link.closed_reason(self.conn)
        if why is not None:
            raise LinkError(f"the connection {self.url} was {why}")

    def _read_ahead(self) -> None:
        """Read what is waiting on the link (up to ``READ_AHEAD_MAX`` messages) into ``_pending``.

        Each message carries its arrival on our clock (``ARRIVAL_ATTR``): the kernel's stamp on
        UDP (how long it waited in the socket), the time of reading otherwise; the vehicle's
        samples are shown to the clock mapping in arrival order, before any is handled, so that a
        frame of a backlog is aged against the newest sample behind it."""
        n = 0
        while n < READ_AHEAD_MAX:
            if self._datagrams:
                d = link.read_datagram(self.conn)
                if d is None:
                    return
                if d.oversized:
                    self.counters["oversized datagrams dropped"] += 1
                if d.partial_bytes:
                    self.counters["bad packets"] += 1  # an unfinished packet at the end of a datagram
                now = self.clock()  # read now, with the stamp: the process may be stopped anywhere
                arrival = now if d.arrival_unix_s is None else now - max(0.0, self.wall() - d.arrival_unix_s)
                batch = d.messages
            else:
                m = self.conn.recv_msg()
                if m is None:
                    return
                arrival, batch = self.clock(), [m]
            for m in batch:
                if m.get_type() != "BAD_DATA":
                    setattr(m, ARRIVAL_ATTR, arrival)
                    self._observe(m, arrival)
                self._pending.append(m)
            n += max(1, len(batch))

    def _observe(self, msg: Any, arrival_s: float) -> None:
        """Show the session's clock mapping a message as it arrives (``Session.observe``)."""
        try:
            vehicle = self._from_vehicle(msg)
        except Exception:  # noqa: BLE001 - a message without a sender is no evidence (the handler will say)
            return
        self.session.observe(msg, arrival_s, vehicle=vehicle)

    def _recv(self) -> Any | None:
        try:
            if not self._pending:
                self._read_ahead()
            msg = self._pending.popleft() if self._pending else None
        except Exception:  # noqa: BLE001 - garbage on the wire: drop it, go on
            self.counters["unreadable input"] += 1
            return None
        if msg is None:
            return None
        if msg.get_type() == "BAD_DATA":
            self.counters[link.bad_data_kind(msg)] += 1
            return None
        if self.tlog is not None:
            if self._from_vehicle(msg):
                self.tlog.observe(msg)
            self.tlog.write(bytes(msg.get_msgbuf()))
        return msg

    # -- incoming ------------------------------------------------------------------------

    def _from_vehicle(self, msg: Any) -> bool:
        return msg.get_srcSystem() == self.router.vehicle_sysid and msg.get_srcComponent() == self.vehicle_compid

    def _on_message(self, msg: Any, now: float) -> None:
        """One message from the link: the profile detector and the commands are the loop's, the
        rest the session's (``Session.on_message``), whose answer is sent."""
        mtype = msg.get_type()
        vehicle = self._from_vehicle(msg)
        arrival = getattr(msg, ARRIVAL_ATTR, None)
        if arrival is None:  # handed in directly, not read by ``_read_ahead``: it arrives now
            arrival = now
            self._observe(msg, now)
        if vehicle and not self.profile_known:
            self._detect(msg)
        if mtype == "COMMAND_ACK":
            if vehicle and msg.target_component in (0, outbound.COMPANION_COMPONENT):
                done = self.commander.on_ack(msg.command, msg.result)
                if done is not None and msg.result == mav.MAV_RESULT_ACCEPTED:
                    if done.command == mav.MAV_CMD_DO_SET_MODE:
                        self._emit(self.session.on_vehicle_state(now, mode=GUIDED_NOGPS))
                    elif done.command == mav.MAV_CMD_COMPONENT_ARM_DISARM:
                        self._emit(self.session.on_vehicle_state(now, armed=True))
        elif mtype in ("COMMAND_LONG", "COMMAND_INT"):
            self._on_command(msg)
        behind = self._catching_up and msg is not self._resume_frame  # a stall's backlog: only the newest flies
        self._emit(self.session.on_message(msg, now, vehicle=vehicle, arrival_s=arrival, behind=behind), now)

    def _on_command(self, msg: Any) -> None:
        """A command addressed to the companion: none is supported, so it is refused with a
        COMMAND_ACK (MAV_RESULT_UNSUPPORTED), as MAVLink asks, and counted."""
        if msg.target_component != outbound.COMPANION_COMPONENT or \
                msg.target_system not in (0, self.conn.mav.srcSystem):
            return
        self.counters["commands refused (unsupported)"] += 1
        self._send(self.conn.mav.command_ack_encode(msg.command, mav.MAV_RESULT_UNSUPPORTED, 0, 0,
                                                    msg.get_srcSystem(), msg.get_srcComponent()))

    # -- periodic ------------------------------------------------------------------------

    def _heartbeat(self, now: float) -> None:
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + 1.0
            self._send(outbound.heartbeat(self.conn.mav))

    def _watchdog(self, now: float) -> None:
        """The profile still unknown after ``PROFILE_WARN_S``; then the session's watchdog
        (``Session.tick``: link lost, the GCS's setpoints stopping, no flow frame for flow_timeout_s)."""
        if not self.profile_known and not self._profile_warned and self._vehicle_heard_wall is not None \
                and now - self._vehicle_heard_wall > PROFILE_WARN_S:
            self._profile_warned = True
            assert self.detector is not None
            self.out(f"flowhold: warning: sensor profile still unknown after {PROFILE_WARN_S:g} s "
                     f"({self.detector.n_flow} OPTICAL_FLOW, none telling); not taking control: give --profile")
        self._emit(self.session.tick(now))

    def status_line(self, now: float) -> str:
        ses = self.session
        s = ses.last_step
        sp = ses.setpoint(now)
        rate = ses.flow_rate_hz()
        hb = now - ses.last_heartbeat_s
        est = f"{s.vx_m_s:+.2f} {s.vy_m_s:+.2f}" if s is not None and not ses.last_held else "  --    -- "
        t = f"{s.time_s:7.2f}" if s is not None else "    --"
        state = "CONTROL" if self.in_control else ("standby" if self.profile_known else "standby (profile?)")
        hold = f" HOLD: {self.monitor.cause.value}" if self.monitor.cause is not HoldCause.NONE else ""
        roll, pitch = (math.degrees(a) for a in self.last_cmd_rad)
        n_rejected = sum(self.rejected().values())
        rejected = f"  rejected {n_rejected}" if n_rejected else ""
        return (f"flowhold t {t} s  set {sp[0]:+.2f} {sp[1]:+.2f}  est {est} m/s  cmd roll {roll:+5.1f} "
                f"pitch {pitch:+5.1f} deg  {state}  link {'LOST' if hb > HEARTBEAT_TIMEOUT_S else 'ok'} "
                f"(hb {min(hb, 99.9):.1f} s, flow {rate:.0f} Hz){hold}{rejected}")

    def _status(self, now: float) -> None:
        if self.quiet or now < self._next_status:
            return
        self._next_status = now + (STATUS_PERIOD_TTY_S if self._tty else STATUS_PERIOD_LOG_S)
        line = self.status_line(now)
        if self._tty:
            sys.stdout.write("\r" + line[:150].ljust(150))
            sys.stdout.flush()
        else:
            self.out(line)

    # -- main loop -----------------------------------------------------------------------

    def run(self, duration_s: float | None = None) -> None:
        """Run until ``duration_s`` seconds of control (wall clock) or ``stop_requested``."""
        while not self.stop_requested:
            now = self.clock()
            if self._loop_wall is not None and now - self._loop_wall > self.cfg.companion.flow_timeout_s:
                self._on_stall(now - self._loop_wall, now)
                now = self.clock()
            self._loop_wall = now
            self._heartbeat(now)
            self._poll_texts(now)
            self.commander.poll(now, self._send_command)
            while self.commander.warnings:
                self.out(f"flowhold: warning: {self.commander.warnings.pop(0)}")
            self._watchdog(now)
            self._status(now)
            if duration_s is not None and self.control_start is not None and now - self.control_start >= duration_s:
                return
            msg = self._recv()
            if msg is None:
                if not self._pending:  # (a bad packet read ahead: the next one is already here)
                    self._check_open()
                    self.conn.select(min(self.T / 2, 0.01))
                continue
            self._handle(msg)

    def _handle(self, msg: Any) -> None:
        try:
            self._on_message(msg, self.clock())
        except Exception as exc:  # noqa: BLE001 - one bad message must not stop the loop
            key = f"unhandled {msg.get_type()}: {type(exc).__name__}"
            if self.counters[key] == 0:
                print(f"flowhold: dropped a message ({key}: {exc})", file=sys.stderr, flush=True)
            self.counters[key] += 1

    def _on_stall(self, gap_s: float, now: float) -> None:
        """The loop did not run for ``gap_s`` (> ``flow_timeout_s``): the process was stopped,
        starved or swapped out. The session names the hold (``Session.on_stall``); then everything
        that waited is handled at once, before the watchdog would act: every flow frame but the
        newest is dropped (as is the newest if it is too old), so control resumes from the newest
        frame with the integrator as it was before the stall."""
        self._emit(self.session.on_stall(gap_s, now))
        self._read_ahead()
        flow = FLOW_MESSAGE[self.profile]
        frames = [m for m in self._pending if m.get_type() == flow and self._from_vehicle(m)]
        self._resume_frame = frames[-1] if frames else None
        self._catching_up = True
        try:
            for _ in range(len(self._pending)):
                msg = self._recv()
                if msg is not None:
                    self._handle(msg)
        finally:
            self._catching_up = False
            self._resume_frame = None

    def close(self) -> None:
        if self._tty and not self.quiet:
            sys.stdout.write("\n")
        if self.tlog is not None:
            self.tlog.close()
        try:
            self.conn.close()
        except Exception:  # noqa: BLE001 - closing a dead link is not an error
            pass

    def rejected(self) -> Counter[str]:
        """What was refused or dropped, by reason: bad or unsigned packets, sensor data from
        another system, setpoints that are not finite or in an unsupported frame, ..."""
        c = Counter({k: v for k, v in self.counters.items() if k in REJECTION_COUNTERS or k.startswith("unhandled")})
        c.update({f"ignored: {k}": v for k, v in self.router.ignored.items()})
        return c

    def summary(self) -> str:
        c = self.counters + Counter({f"ignored: {k}": v for k, v in self.router.ignored.items()})
        parts = [f"{c['steps']} steps", f"{c['commands']} commands", f"{self.monitor.episodes} hold episode(s)"]
        parts += [f"{k}: {v}" for k, v in sorted(c.items()) if k not in ("steps", "commands")]
        return "flowhold: " + ", ".join(parts)

def run_cli(args: Any) -> int:
    """``python -m companion run``: 0 after ``--duration`` of control or a clean Ctrl-C / SIGTERM."""
    setpoint = parse_setpoint(args.setpoint) if args.setpoint else None
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise UsageError(f"--duration must be a positive number of seconds, got {args.duration}")
    if args.vehicle_sysid is not None and not 1 <= args.vehicle_sysid <= 255:
        raise UsageError(f"--vehicle-sysid must be in 1..255, got {args.vehicle_sysid}")
    if args.tlog:
        check_output(args.tlog, "--tlog")
    cfg = load_config(args.config)
    profile = Profile(args.profile) if args.profile else None
    key = link.signing_key(args.signing_key) if args.signing_key else None
    link.check_url(args.connect)
    conn = link.open_connection(args.connect, source_system=args.vehicle_sysid or 1,
                                source_component=outbound.COMPANION_COMPONENT)
    if key is not None:
        link.setup_signing(conn.mav, key)
    try:
        live = LiveCompanion(cfg, profile, conn, url=args.connect, arm=args.arm, setpoint_m_s=setpoint,
                             tlog=args.tlog, vehicle_sysid=args.vehicle_sysid, quiet=args.quiet)
    except OSError as exc:
        conn.close()
        raise output_error("--tlog", args.tlog, exc) from None

    def request_stop(_signum: int, _frame: Any) -> None:
        live.stop_requested = True

    old = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        live.connect()
        live.run(args.duration)
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        live.close()
    if live.router.vehicle_sysid is not None:
        print(live.summary(), flush=True)
    print(f"flowhold: {'stopped' if live.stop_requested else 'done'}"
          + (f"; recording {args.tlog}" if args.tlog else ""), flush=True)
    return 0
