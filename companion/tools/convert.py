"""Rewrite a .tlog's flow messages from one sensor profile's convention to another's.

    python -m companion.tools.convert IN.tlog OUT.tlog --to ardupilot [--from paper] [--config FILE]

(``IN`` may be a .tlog.gz; ``OUT`` is written uncompressed.)

Every record other than the vehicle's flow messages is copied byte for byte (record times too);
each flow message is decoded in the source convention (``profiles.flow_columns``) and encoded
again in the target one (CONVENTIONS.md, "Sensor profiles"), with the sender's ids and sequence
number kept:

- to ``paper``: OPTICAL_FLOW, ``flow_x/y`` = round(dphi / Q) (int16), ``time_usec`` in µs,
  ``flow_rate_x/y`` the MAVLink-rule rates (informative), ``flow_comp_m`` 0, ``ground_distance`` -1;
- to ``ardupilot``: OPTICAL_FLOW, ``flow_rate_x`` = +dphi_y / dt, ``flow_rate_y`` = -dphi_x / dt
  (rad/s), ``time_usec`` in ms, ``flow_x/y`` the rates truncated, ``flow_comp_m`` = rate - body rate;
- to ``px4``: OPTICAL_FLOW_RAD, ``integrated_x`` = +dphi_y, ``integrated_y`` = -dphi_x over
  ``integration_time_us`` = dt, ``integrated_x/ygyro`` = body rate x dt.

``dt`` is the time the frame covers: the message's integration time when it states one (px4),
else the spacing from the previous flow frame (``estimator.frame_spacing``). The body rate is the
source message's own when it carries one (ardupilot, px4), else the gyro sample nearest the frame
among the last ones received (RAW_IMU, SCALED_IMU or HIGHRES_IMU, each by its own time field;
within ``max_gyro_skew_s``, the companion's rule ``rules.gyro_scan``; 0 if none). Converting to
``paper`` quantizes the scene angle to Q (``--config``; the velocity then differs by at most
Q / (2 dt) times the range); the other conversions are exact up to the float32 message fields.
This is what makes the profile-equivalence test possible: the same flight in two conventions.
"""

from __future__ import annotations

import argparse
import math
import struct
import sys
from collections import deque
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from companion.config import Config, load_config
from companion.errors import ExitCode, FlowholdError, RecordingError
from companion.mavlink.inbound import gyro_time_s
from companion.recordings.load import load_recording, read_recording_bytes
from companion.recordings.tlog_writer import TlogWriter, mav_encoder
from companion.step.estimator import frame_spacing
from companion.step.profiles import FLOW_MESSAGE, GYRO_MESSAGES, FieldView, Profile, detect_profile, flow_columns
from companion.step.rules import covered_span, gyro_scan

_HEADER = struct.Struct(">Q")


def _records(data: bytes, name: str) -> Iterator[tuple[int, bytes]]:
    """(UNIX time µs, packet bytes) of each record of an undamaged .tlog."""
    i, n = 0, len(data)
    while i < n:
        if i + 8 + 3 > n:
            raise RecordingError(f"{name}: truncated record at byte {i}")
        t_us = _HEADER.unpack_from(data, i)[0]
        p = i + 8
        stx = data[p]
        if stx == 0xFD:
            length = 10 + data[p + 1] + 2 + (13 if data[p + 2] & 1 else 0)
        elif stx == 0xFE:
            length = 6 + data[p + 1] + 2
        else:
            raise RecordingError(f"{name}: no MAVLink packet at byte {p} (convert needs an undamaged .tlog)")
        if p + length > n:
            raise RecordingError(f"{name}: truncated packet at byte {p}")
        yield t_us, data[p:p + length]
        i = p + length


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, x)))


class _Converter:
    def __init__(self, cfg: Config, src: Profile, dst: Profile) -> None:
        self.q = cfg.flow_sensor.q_rad_per_count
        self.nominal_s = cfg.flow_sensor.frame_period_s
        self.max_skew_s = cfg.companion.max_gyro_skew_s
        self.src, self.dst = src, dst
        self.prev_time_s: float | None = None
        self.gyro: deque[tuple[float, float, float]] = deque(maxlen=32)
        self.encoders: dict[tuple[int, int], Any] = {}

    def on_gyro(self, msg: Any) -> None:
        scale = GYRO_MESSAGES[msg.get_type()]
        self.gyro.append((gyro_time_s(msg), msg.xgyro * scale, msg.ygyro * scale))

    def _body_rate(self, c: Any, time_s: float) -> tuple[float, float]:
        bx, by = float(c.body_x_rad_s), float(c.body_y_rad_s)
        if math.isfinite(bx) and math.isfinite(by):
            return bx, by
        best, best_skew = (0.0, 0.0), self.max_skew_s
        for t, gx, gy in reversed(self.gyro):  # the companion's rule: the nearest within the skew
            skew, take, stop = gyro_scan(t, time_s, best_skew, self.max_skew_s)
            if take:
                best, best_skew = (gx, gy), skew
            elif stop:
                break
        return best

    def flow(self, msg: Any) -> Any:
        """The flow message ``msg`` (source convention) in the target convention."""
        c = flow_columns(FieldView(msg), self.src, self.q)
        t = float(c.time_s)
        dt = frame_spacing(self.prev_time_s, t, self.nominal_s)
        self.prev_time_s = t if math.isfinite(t) else self.prev_time_s
        if c.increment:
            span = float(covered_span(float(c.integration_s), dt))
            dphi_x, dphi_y = float(c.scene_x), float(c.scene_y)
        else:
            span = dt
            dphi_x, dphi_y = float(c.scene_x) * dt, float(c.scene_y) * dt
        rate_x, rate_y = dphi_y / span, -dphi_x / span  # MAVLink flow_rate: x-flow carries y-motion
        bx, by = self._body_rate(c, t)
        quality = int(c.quality)
        rng = float(getattr(msg, "ground_distance", getattr(msg, "distance", -1.0)))
        if self.dst is Profile.PAPER:
            return mavlink2.MAVLink_optical_flow_message(
                int(round(t * 1e6)), 0, _i16(round(dphi_x / self.q)), _i16(round(dphi_y / self.q)), 0.0, 0.0,
                quality, -1.0, rate_x, rate_y)
        if self.dst is Profile.ARDUPILOT:
            return mavlink2.MAVLink_optical_flow_message(
                int(round(t * 1e3)), 0, _i16(math.trunc(rate_x)), _i16(math.trunc(rate_y)), rate_x - bx,
                rate_y - by, quality, rng, rate_x, rate_y)
        return mavlink2.MAVLink_optical_flow_rad_message(
            int(round(t * 1e6)), 0, int(round(span * 1e6)), dphi_y, -dphi_x, bx * span, by * span, 0.0, 0,
            quality, 0, rng)

    def pack(self, msg: Any, sysid: int, compid: int, seq: int) -> bytes:
        enc = self.encoders.get((sysid, compid))
        if enc is None:
            enc = self.encoders[(sysid, compid)] = mav_encoder(sysid, compid)
        enc.seq = seq
        return bytes(msg.pack(enc))


def convert_tlog(src_path: str | Path, dst_path: str | Path, *, src: Profile, dst: Profile,
                 cfg: Config | None = None) -> int:
    """Write ``dst_path``: ``src_path`` (a .tlog, or a .tlog.gz) with the flow messages in
    profile ``dst``. Returns the number of flow messages converted. Raises RecordingError for a
    damaged or flow-less file."""
    cfg = cfg if cfg is not None else load_config()
    src_path, dst_path = Path(src_path), Path(dst_path)
    data = read_recording_bytes(src_path)  # a .tlog.gz: decompressed in memory
    conv = _Converter(cfg, src, dst)
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    flow_name = FLOW_MESSAGE[src]
    vehicle: int | None = None
    n = 0
    wanted = {mavlink2.MAVLINK_MSG_ID_OPTICAL_FLOW, mavlink2.MAVLINK_MSG_ID_OPTICAL_FLOW_RAD,
              mavlink2.MAVLINK_MSG_ID_RAW_IMU, mavlink2.MAVLINK_MSG_ID_SCALED_IMU, mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU}
    with TlogWriter(dst_path) as out:
        for t_us, packet in _records(data, src_path.name):
            msgid = packet[7] | (packet[8] << 8) | (packet[9] << 16) if packet[0] == 0xFD else packet[5]
            if msgid not in wanted:  # copied as is, not decoded
                out.write_bytes(packet, t_us * 1e-6)
                continue
            try:
                msg = parser.decode(bytearray(packet))
            except mavlink2.MAVError:
                out.write_bytes(packet, t_us * 1e-6)
                continue
            mtype = msg.get_type()
            if mtype in GYRO_MESSAGES and (vehicle is None or msg.get_srcSystem() == vehicle):
                conv.on_gyro(msg)
            if mtype == flow_name:
                if vehicle is None:
                    vehicle = msg.get_srcSystem()
                if msg.get_srcSystem() == vehicle:
                    new = conv.flow(msg)
                    packet = conv.pack(new, msg.get_srcSystem(), msg.get_srcComponent(), msg.get_seq())
                    n += 1
            out.write_bytes(packet, t_us * 1e-6)
    if n == 0:
        dst_path.unlink(missing_ok=True)
        raise RecordingError(f"{src_path.name}: no {flow_name} messages to convert from the {src.value} profile")
    return n


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m companion.tools.convert", description=__doc__.splitlines()[0])
    ap.add_argument("recording", help="input .tlog (or .tlog.gz)")
    ap.add_argument("out", help="output .tlog")
    ap.add_argument("--from", dest="src", choices=[p.value for p in Profile],
                    help="the input's profile (default: detected)")
    ap.add_argument("--to", dest="dst", required=True, choices=[p.value for p in Profile])
    ap.add_argument("--config", help="parameter set (TOML) for Q and the frame period; default configs/paper.toml")
    args = ap.parse_args(argv)
    try:
        cfg = load_config(args.config)
        if args.src is None:
            src = Profile(detect_profile(load_recording(args.recording))[0])
        else:
            src = Profile(args.src)
        n = convert_tlog(args.recording, args.out, src=src, dst=Profile(args.dst), cfg=cfg)
    except FlowholdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return int(exc.exit_code)
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return int(ExitCode.BAD_INPUT)
    print(f"converted {n} flow messages from {src.value} to {args.dst} -> {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

__all__ = ["convert_tlog", "main"]
