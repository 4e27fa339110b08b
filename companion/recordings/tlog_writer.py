"""Write MAVLink packets to a .tlog (the MAVProxy / Mission Planner layout).

Each record is an 8-byte big-endian unsigned UNIX time in microseconds followed by the raw
packet, exactly what ``companion.recordings.tlog_reader.read_tlog`` and pymavlink's
``mavutil.mavlink_connection(path)`` read back.

    with TlogWriter("flight.tlog") as log:
        enc = mav_encoder(sysid=1, compid=1)
        log.write(enc.heartbeat_encode(2, 3, 0, 0, 0), t_s=1.7e9)
"""

from __future__ import annotations

import struct
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

_TIME_HEADER = struct.Struct(">Q")

#: UNIX time of simulated time 0 in a recording stamped with a simulator's clock
#: (2026-01-01T00:00:00Z): the scenarios' recordings, and the vehicle's and the companion's in
#: lockstep or speed-up (header = SIM_EPOCH_S + simulated seconds)
SIM_EPOCH_S = 1_767_225_600.0
#: in the STATUSTEXT a simulated vehicle sends each peer when its clock is not the wall clock
#: ("simvehicle: simulated clock (lockstep)"); a recording that holds it is stamped with simulated time
SIM_CLOCK_TEXT = "simulated clock"


def mav_encoder(sysid: int, compid: int) -> mavlink2.MAVLink:
    """A pymavlink encoder (ardupilotmega dialect, MAVLink 2, no file) for one sender.

    ``msg = enc.optical_flow_encode(...)``, then ``msg.pack(enc)`` (or ``TlogWriter.write``)
    gives the packet. Packing advances the encoder's sequence number only through
    ``TlogWriter.write`` / ``enc.send``; callers packing by hand may bump ``enc.seq``.
    """
    return mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)


def _time_header(t_s: float) -> bytes:
    """The 8-byte record header for UNIX time ``t_s`` (s), rounded to the microsecond."""
    t_us = round(t_s * 1e6)
    if t_us < 0:
        raise ValueError(f"a .tlog time must not be negative: {t_s} s")
    return _TIME_HEADER.pack(t_us)


class TlogWriter:
    """A .tlog open for writing (truncates), as a context manager.

    ``write(msg, t_s)`` packs a pymavlink message with the encoder it was made for (or the
    one passed) and appends it; ``write_bytes(packet, t_s)`` appends a packet as is.
    ``t_s`` is the UNIX time (s) put in the record header.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._f: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - closed by close()/__exit__
        self.n_records = 0

    def write(self, msg: mavlink2.MAVLink_message, t_s: float, *,
              encoder: mavlink2.MAVLink | None = None) -> bytes:
        """Append ``msg`` at time ``t_s`` (s). Packs it with ``encoder`` when given (its
        sender ids and sequence number, which then advances); otherwise the message must
        already be packed (``msg.get_msgbuf()``). Returns the packet bytes."""
        if encoder is not None:
            packet = msg.pack(encoder)
            encoder.seq = (encoder.seq + 1) % 256
        else:
            packet = bytes(msg.get_msgbuf())
            if not packet:
                raise ValueError(f"{msg.get_type()} is not packed: pass encoder= or pack it first")
        self.write_bytes(packet, t_s)
        return packet

    def write_bytes(self, packet: bytes, t_s: float) -> None:
        """Append one raw MAVLink packet at time ``t_s`` (s)."""
        self._f.write(_time_header(t_s))
        self._f.write(packet)
        self.n_records += 1

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
