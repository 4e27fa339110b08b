"""Benchmark: the companion's control-step latency on UDP loopback.

    .venv/bin/python benchmarks/bench_latency.py [--frames 2000] [--rate 50] [--target live|harness|both]

A fake vehicle (this process) binds a UDP port on 127.0.0.1 and plays a recorded closed-loop
flight (the fast engine's demanding flight, through MAVLink quantization) at the frame rate:
HEARTBEAT (armed, GUIDED_NOGPS) once a second and per frame RAW_IMU, DISTANCE_SENSOR, ATTITUDE
and OPTICAL_FLOW, one datagram each, as an autopilot sends them. It acknowledges the companion's
COMMAND_LONGs. The companion under test runs in its own process:

- ``live``: ``python -m companion run --connect udpout:127.0.0.1:PORT --quiet`` (the product);
- ``harness``: a minimal loop (``_serve_harness``): socket -> pymavlink parse ->
  ``MessageRouter`` -> ``outbound`` -> socket, the same core without the live loop's extras.

Latency of a frame: from just before its OPTICAL_FLOW datagram is sent to the arrival of the
SET_ATTITUDE_TARGET stamped with that frame's time (``time_boot_ms``), both on this process's
``perf_counter``: the companion's wake-up, parse, control step and encoding, and two loopback
hops (this side only slices the reply's header). Every reply is then decoded and checked (finite,
inside the tilt limit, thrust 0.5). ``profile_step`` times the step in-process and names where
its time goes (cProfile).

``measure_latency(target, frames, rate_hz)`` and ``profile_step()`` are importable (benchmarks/run.py).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import math
import os
import pstats
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

SET_ATTITUDE_TARGET_ID = 82
COMMAND_LONG_ID = 76
VEHICLE = (1, 1)
#: vehicle boot time of the first frame (s): nonzero, like a vehicle that has been up a while
T0_S = 10.0
#: SCHED_FIFO priority of both processes with ``realtime`` (ArduPilot's own threads use 10-60)
RT_PRIORITY = 40


def flight_frames(n_frames: int, frame_s: float = 0.02) -> list[list[bytes]]:
    """Per frame, the vehicle's datagrams [RAW_IMU, DISTANCE_SENSOR, ATTITUDE, OPTICAL_FLOW],
    packed from a fast-engine flight so the companion sees realistic, changing data."""
    from companion.config import load_config
    from simvehicle.engines import fastsim

    cfg = load_config()
    duration = n_frames * frame_s
    res = fastsim.simulate_batch(cfg, 1, duration_s=duration, mavlink_quantization=True,
                                 **fastsim.demanding_flight(duration)).run(0)
    enc = mav.MAVLink(None, srcSystem=VEHICLE[0], srcComponent=VEHICLE[1])
    out = []
    c = res.columns
    for k in range(n_frames):
        t = T0_S + k * frame_s
        us, ms = int(round(t * 1e6)), int(round(t * 1e3))
        gx, gy = (int(round(c[n][k] * 1e3)) for n in ("gyro_x_rad_s", "gyro_y_rad_s"))
        msgs = [
            enc.raw_imu_encode(us, 0, 0, -1000, gx, gy, 0, 0, 0, 0),
            enc.distance_sensor_encode(ms, 2, 400, int(round(c["range_m"][k] * 100)), mav.MAV_DISTANCE_SENSOR_LASER,
                                       0, 25, 255),
            enc.attitude_encode(ms, c["roll_rad"][k], c["pitch_rad"][k], 0.0, c["roll_rate_rad_s"][k],
                                c["pitch_rate_rad_s"][k], 0.0),
            enc.optical_flow_encode(us, 0, int(c["flow_x_counts"][k]), int(c["flow_y_counts"][k]), 0.0, 0.0, 255,
                                    -1.0, 0.0, 0.0),
        ]
        frame = []
        for m in msgs:
            frame.append(bytes(m.pack(enc)))
            enc.seq = (enc.seq + 1) % 256
        out.append(frame)
    return out


def _packets(buf: bytes) -> list[tuple[int, int, bytes]]:
    """(msgid, offset, packet) of each MAVLink 1/2 packet in a datagram (header slicing only)."""
    out = []
    o, n = 0, len(buf)
    while o < n:
        if buf[o] == 0xFD and o + 10 <= n:
            plen, incompat = buf[o + 1], buf[o + 2]
            size = 12 + plen + (13 if incompat & 1 else 0)
            out.append((buf[o + 7] | buf[o + 8] << 8 | buf[o + 9] << 16, o, buf[o:o + size]))
            o += size
        elif buf[o] == 0xFE and o + 6 <= n:
            size = 8 + buf[o + 1]
            out.append((buf[o + 5], o, buf[o:o + size]))
            o += size
        else:
            o += 1
    return out


def _time_boot_ms(packet: bytes) -> int:
    """time_boot_ms (the first payload field) of a SET_ATTITUDE_TARGET packet; MAVLink 2
    truncates trailing zero bytes of the payload."""
    payload = packet[10:10 + packet[1]] if packet[0] == 0xFD else packet[6:6 + packet[1]]
    return struct.unpack("<I", (payload + b"\0\0\0\0")[:4])[0]


def _command(target: str, port: int, cfg_path: str | None) -> list[str]:
    url = f"udpout:127.0.0.1:{port}"
    if target == "live":
        cmd = [sys.executable, "-m", "companion", "run", "--connect", url, "--quiet"]
        return cmd + (["--config", cfg_path] if cfg_path else [])
    return [sys.executable, str(Path(__file__).resolve()), "--serve-harness", url]


def realtime_available() -> bool:
    """Whether this process may use SCHED_FIFO (root, or CAP_SYS_NICE)."""
    try:
        old = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RT_PRIORITY))
        os.sched_setscheduler(0, old[0], old[1])
        return True
    except (AttributeError, PermissionError, OSError):
        return False


def measure_latency(target: str = "live", frames: int = 2000, rate_hz: float = 50.0, warmup: int = 100,
                    timeout_s: float = 60.0, realtime: bool = False) -> dict[str, Any]:
    """Run the companion (``live`` or ``harness``) against the fake vehicle for ``warmup +
    frames`` frames. Returns latency percentiles (ms) over the last ``frames``, the frames lost
    (no command within 0.5 s) and the number of commands checked.

    ``realtime``: run both processes under SCHED_FIFO (priority ``RT_PRIORITY``), as a flight
    computer runs its control loop, so other work on the machine does not delay the step."""
    if target not in ("live", "harness"):
        raise ValueError(f"target must be live or harness, got {target!r}")
    old_sched = os.sched_getscheduler(0), os.sched_getparam(0)
    n = warmup + frames
    data = flight_frames(n)
    enc = mav.MAVLink(None, srcSystem=VEHICLE[0], srcComponent=VEHICLE[1])
    parser = mav.MAVLink(None)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    log = tempfile.TemporaryFile()
    proc = subprocess.Popen(_command(target, port, None), stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
    latencies = np.full(n, np.nan)
    replies: list[bytes] = []
    try:
        if realtime:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RT_PRIORITY))
            os.sched_setscheduler(proc.pid, os.SCHED_FIFO, os.sched_param(RT_PRIORITY))
        sock.settimeout(timeout_s)
        try:
            _, peer = sock.recvfrom(65536)  # the companion's first HEARTBEAT
        except TimeoutError:
            log.seek(0)
            raise RuntimeError(f"the {target} companion never called: {log.read().decode()[-500:]}") from None

        def send_msg(m: Any) -> None:
            sock.sendto(bytes(m.pack(enc)), peer)
            enc.seq = (enc.seq + 1) % 256

        def heartbeat() -> None:
            send_msg(enc.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                          mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_SAFETY_ARMED, 20,
                                          mav.MAV_STATE_ACTIVE))

        def handle(buf: bytes) -> list[bytes]:
            found = []
            for mid, _, pkt in _packets(buf):
                if mid == SET_ATTITUDE_TARGET_ID:
                    found.append(pkt)
                elif mid == COMMAND_LONG_ID:
                    for m in parser.parse_buffer(pkt) or []:
                        send_msg(enc.command_ack_encode(m.command, mav.MAV_RESULT_ACCEPTED, 0, 0,
                                                        m.get_srcSystem(), m.get_srcComponent()))
            return found

        heartbeat()
        period = 1.0 / rate_hz
        start = time.perf_counter() + 0.5
        for k in range(n):
            wait = start + k * period - time.perf_counter()
            if wait > 0:
                time.sleep(wait)  # never spin: under SCHED_FIFO a spin would starve the machine
            if k % int(rate_hz) == 0:
                heartbeat()
            imu, rng, att, flow = data[k]
            sock.sendto(imu, peer)
            sock.sendto(rng, peer)
            sock.sendto(att, peer)
            want = int(round((T0_S + k * 0.02) * 1e3))  # the frame's own time, whatever the pace
            t_send = time.perf_counter()
            sock.sendto(flow, peer)
            deadline = t_send + 0.5
            while True:
                left = deadline - time.perf_counter()
                if left <= 0:
                    break
                sock.settimeout(left)
                try:
                    buf = sock.recv(65536)
                except TimeoutError:
                    break
                t_recv = time.perf_counter()
                hit = [p for p in handle(buf) if _time_boot_ms(p) == want]
                if hit:
                    latencies[k] = t_recv - t_send
                    replies.append(hit[0])
                    break
    finally:
        os.sched_setscheduler(0, old_sched[0], old_sched[1])
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        sock.close()
        log.close()
    checked = _check_replies(replies)
    lat = latencies[warmup:]
    got = lat[np.isfinite(lat)] * 1e3
    if len(got) == 0:
        raise RuntimeError(f"the {target} companion sent no SET_ATTITUDE_TARGET")
    return {"target": target, "realtime": realtime, "frames": frames, "rate_hz": rate_hz,
            "lost": int(np.isnan(lat).sum()), "load_avg_1min": os.getloadavg()[0],
            "p50_ms": float(np.percentile(got, 50)), "p99_ms": float(np.percentile(got, 99)),
            "max_ms": float(got.max()), "mean_ms": float(got.mean()), "commands_checked": checked}


def _check_replies(replies: list[bytes]) -> int:
    """Decode every SET_ATTITUDE_TARGET received: finite, within 20 deg, thrust 0.5."""
    from companion.mavlink.outbound import quaternion_to_euler

    parser = mav.MAVLink(None)
    n = 0
    for pkt in replies:
        for m in parser.parse_buffer(pkt) or []:
            roll, pitch, _ = quaternion_to_euler(m.q)
            if not (math.isfinite(roll) and math.isfinite(pitch) and abs(roll) <= math.radians(20.0) + 1e-6
                    and abs(pitch) <= math.radians(20.0) + 1e-6 and m.thrust == 0.5):
                raise RuntimeError(f"bad command from the companion: {m}")
            n += 1
    return n


# ---------------------------------------------------------------------------------------------
# The minimal harness (runs in its own process)


def _serve_harness(url: str) -> int:
    """socket -> pymavlink -> MessageRouter -> outbound -> socket, until killed."""
    from companion.config import load_config
    from companion.mavlink import outbound
    from companion.mavlink.inbound import MessageRouter
    from companion.step.core import CompanionCore
    from companion.step.profiles import Profile

    host, port = url.split(":", 1)[1].rsplit(":", 1)
    cfg = load_config()
    core = CompanionCore(cfg, Profile.PAPER)
    router = MessageRouter(core, Profile.PAPER, vehicle_sysid=VEHICLE[0])
    enc = mav.MAVLink(None, srcSystem=VEHICLE[0], srcComponent=outbound.COMPANION_COMPONENT)
    parser = mav.MAVLink(None)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer = (host, int(port))
    sock.sendto(bytes(outbound.heartbeat(enc).pack(enc)), peer)
    while True:
        buf = sock.recv(65536)
        for msg in parser.parse_buffer(buf) or []:
            out = router.handle(msg)
            if out is None:
                continue
            ms = int(round(out.time_s * 1e3))
            packets = [outbound.position_target(enc, ms, out.vx_set_m_s, out.vy_set_m_s)]
            if not out.holding:
                packets.append(outbound.vision_speed(enc, int(round(out.time_s * 1e6)), out.vx_m_s, out.vy_m_s))
            packets.append(outbound.set_attitude_target(enc, ms, VEHICLE[0], out.roll_cmd_rad, out.pitch_cmd_rad, 0.0))
            sock.sendto(b"".join(bytes(p.pack(enc)) for p in packets), peer)


# ---------------------------------------------------------------------------------------------
# In-process profile of one step


def profile_step(frames: int = 3000, top: int = 8) -> dict[str, Any]:
    """The step without sockets: decode a frame's messages, ``MessageRouter.handle`` them, encode
    the replies. Returns per-frame times (µs) of each part and cProfile's top functions by
    cumulative time of the control step."""
    from companion.config import load_config
    from companion.mavlink import outbound
    from companion.mavlink.inbound import MessageRouter
    from companion.step.core import CompanionCore
    from companion.step.profiles import Profile

    data = flight_frames(frames)
    core = CompanionCore(load_config(), Profile.PAPER)
    router = MessageRouter(core, Profile.PAPER, vehicle_sysid=VEHICLE[0])
    parser = mav.MAVLink(None)
    enc = mav.MAVLink(None, srcSystem=VEHICLE[0], srcComponent=outbound.COMPANION_COMPONENT)
    decoded = [[parser.parse_buffer(d)[0] for d in frame] for frame in data]
    t0 = time.perf_counter()
    for frame in data:
        for d in frame:
            parser.parse_buffer(d)
    t_parse = (time.perf_counter() - t0) / frames
    outs = []
    t0 = time.perf_counter()
    for frame in decoded:
        for m in frame:
            o = router.handle(m)
            if o is not None:
                outs.append(o)
    t_step = (time.perf_counter() - t0) / frames
    t0 = time.perf_counter()
    for o in outs:
        ms = int(round(o.time_s * 1e3))
        for p in (outbound.position_target(enc, ms, o.vx_set_m_s, o.vy_set_m_s),
                  outbound.vision_speed(enc, int(round(o.time_s * 1e6)), o.vx_m_s, o.vy_m_s),
                  outbound.set_attitude_target(enc, ms, 1, o.roll_cmd_rad, o.pitch_cmd_rad, 0.0)):
            p.pack(enc)
    t_encode = (time.perf_counter() - t0) / frames
    core2 = CompanionCore(load_config(), Profile.PAPER)
    router2 = MessageRouter(core2, Profile.PAPER, vehicle_sysid=VEHICLE[0])
    prof = cProfile.Profile()
    prof.enable()
    for frame in decoded:
        for m in frame:
            router2.handle(m)
    prof.disable()
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("cumulative").print_stats(top + 6)
    return {"parse_us": t_parse * 1e6, "step_us": t_step * 1e6, "encode_us": t_encode * 1e6,
            "profile": s.getvalue()}


def format_result(r: dict[str, Any]) -> str:
    sched = "SCHED_FIFO" if r["realtime"] else "default scheduler"
    return (f"{r['target']:>7} ({sched}): p50 {r['p50_ms']:.3f} ms, p99 {r['p99_ms']:.3f} ms, max "
            f"{r['max_ms']:.2f} ms over {r['frames']} frames at {r['rate_hz']:g} Hz ({r['lost']} lost, "
            f"{r['commands_checked']} commands checked, load average {r['load_avg_1min']:.1f})")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=2000, help="frames measured (after 100 of warm-up)")
    ap.add_argument("--rate", type=float, default=50.0, help="frame rate of the fake vehicle, Hz")
    ap.add_argument("--target", choices=["live", "harness", "both"], default="both")
    ap.add_argument("--realtime", choices=["no", "yes", "both"], default="both",
                    help="run the processes under SCHED_FIFO (needs root or CAP_SYS_NICE); both: measure each")
    ap.add_argument("--profile", action="store_true", help="also profile the step in-process")
    ap.add_argument("--serve-harness", metavar="URL", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.serve_harness:
        return _serve_harness(args.serve_harness)
    modes = {"no": (False,), "yes": (True,), "both": (False, True)}[args.realtime]
    if True in modes and not realtime_available():
        print("SCHED_FIFO not permitted here (needs root or CAP_SYS_NICE): default scheduler only")
        modes = (False,)
    for target in (("live", "harness") if args.target == "both" else (args.target,)):
        for rt in modes:
            print(format_result(measure_latency(target, args.frames, args.rate, realtime=rt)), flush=True)
    if args.profile:
        p = profile_step()
        print(f"in-process per frame: parse {p['parse_us']:.0f} us, step {p['step_us']:.0f} us, "
              f"encode {p['encode_us']:.0f} us")
        print(p["profile"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
