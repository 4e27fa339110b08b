"""A fake MAVLink connection for the live companion (``LiveCompanion``), driven by a fake clock.

The reference simulator (``simvehicle.model.sim.Simulator``) is the vehicle. Each ``select`` is where time
passes: one frame period, in which the vehicle flies the last command and sends its frame. Messages
are read by ``recv_msg``, so a message arrives when it is read. What the companion writes is kept
in ``written`` as (clock, message) pairs.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

from companion.config import Config
from companion.mavlink import link, outbound
from companion.mavlink.live import LiveCompanion
from companion.step.profiles import Profile
from simvehicle.model import telemetry
from simvehicle.model.sim import Simulator

mav = link.mav


class FakeLink:
    """The vehicle behind a fake connection. ``quality``: every flow frame's quality, when set;
    ``external_force``: the simulator's force (N) as a function of time. ``stall(s)`` stops the
    companion for ``s`` seconds while the vehicle flies on level and queues its frames."""

    def __init__(self, cfg: Config, quality: int | None = None,
                 external_force: Callable[[float], tuple[float, float]] | None = None) -> None:
        self.cfg = cfg
        self.frame_s = cfg.flow_sensor.frame_period_s
        self.clock = 100.0
        self.mav = mav.MAVLink(None, srcSystem=1, srcComponent=outbound.COMPANION_COMPONENT)
        self.veh = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        self.sim = Simulator(cfg) if external_force is None else Simulator(cfg, external_force=external_force)
        self.inbox: deque[Any] = deque()
        self.written: list[tuple[float, Any]] = []  # (clock, message) the companion sent
        self.cmd = (0.0, 0.0)
        self.live: LiveCompanion | None = None
        self.frames_left = 0
        self.quality = quality
        self._parser = mav.MAVLink(None)

    def _decode(self, msg: Any) -> Any:
        return mav.MAVLink(None).decode(bytearray(msg.pack(self.veh)))

    def send_frame(self) -> None:
        rf = self.cfg.rangefinder
        msgs = telemetry.frame_messages(self.veh, self.sim.current, Profile.PAPER, self.cfg.flow_sensor.q_rad_per_count,
                                        self.frame_s, rf.min_m, rf.max_m)
        if self.quality is not None:
            msgs[2].quality = self.quality  # (gyro, range, then the flow)
        if self.sim.frame % 25 == 0:
            msgs.insert(0, telemetry.heartbeat(self.veh, armed=True))
        self.inbox.extend(self._decode(m) for m in msgs)

    def advance(self, cmd: tuple[float, float]) -> None:
        self.sim.advance(*cmd)
        self.clock += self.frame_s
        self.send_frame()

    # what LiveCompanion uses of a connection
    def recv_msg(self) -> Any | None:
        return self.inbox.popleft() if self.inbox else None

    def write(self, buf: bytes) -> None:
        for m in self._parser.parse_buffer(buf) or []:
            self.written.append((self.clock, m))
            if m.get_type() == "SET_ATTITUDE_TARGET":
                self.cmd = outbound.quaternion_to_euler(m.q)[:2]

    def select(self, _timeout: float) -> None:
        """Nothing waiting: the next frame period passes (the vehicle flies the last command)."""
        assert self.live is not None
        if self.frames_left <= 0:
            self.live.stop_requested = True
            return
        self.frames_left -= 1
        self.advance(self.cmd)

    def close(self) -> None:
        pass

    def fly(self, n: int) -> None:
        assert self.live is not None
        self.frames_left = n
        self.live.stop_requested = False
        self.live.run()

    def stall(self, seconds: float) -> None:
        """The companion stops; the vehicle sends a frame each period and flies level."""
        for _ in range(int(round(seconds / self.frame_s))):
            self.advance((0.0, 0.0))

    def messages(self, kind: str, since: int = 0) -> list[tuple[float, Any]]:
        """(clock, message) of the companion's messages of one type, from the ``since``-th written."""
        return [(t, m) for t, m in self.written[since:] if m.get_type() == kind]

    def commands(self, since: int = 0) -> list[tuple[float, Any]]:
        return self.messages("SET_ATTITUDE_TARGET", since)

    def texts(self, since: int = 0) -> list[tuple[str, int]]:
        return [(m.text, m.severity) for _t, m in self.messages("STATUSTEXT", since)]
