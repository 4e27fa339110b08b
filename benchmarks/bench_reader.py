"""Benchmark: the project's .tlog reader against pymavlink's message loop.

    .venv/bin/python benchmarks/bench_reader.py [--minutes 60] [--path FILE] [--pymavlink-sample N]

Builds a recording like a closed-loop flight (the vehicle's flow, IMU, range, attitude and
truth streams, the companion's commands and estimates, heartbeats) and prints, in one run:
pymavlink's ``recv_match`` loop and ``companion.recordings.tlog_reader.read_tlog`` in messages per second,
their ratio, and the reader's peak memory against the file size. pymavlink is timed on the
first ``--pymavlink-sample`` messages (default 200 000) and extrapolated, as the table says;
``--pymavlink-sample 0`` times the whole file. Each measurement runs in a fresh subprocess so
its peak resident memory (``ru_maxrss``) is its own.

``build_recording(path, minutes)`` and ``measure_reader(path)`` are importable (benchmarks/run.py).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from companion.recordings.tlog_reader import layouts  # noqa: E402

VEHICLE = (1, 1)
COMPANION = (1, 191)
T0_UNIX_S = 1_750_000_000.0


@dataclass(frozen=True)
class Stream:
    """One periodic message stream of the synthetic flight."""

    message: str
    sender: tuple[int, int]
    rate_hz: float


#: a closed-loop flight: about 363 messages per second, 1.31 M in 60 minutes
FLIGHT_STREAMS = (
    Stream("OPTICAL_FLOW", VEHICLE, 50.0),
    Stream("RAW_IMU", VEHICLE, 50.0),
    Stream("DISTANCE_SENSOR", VEHICLE, 50.0),
    Stream("ATTITUDE", VEHICLE, 50.0),
    Stream("LOCAL_POSITION_NED", VEHICLE, 25.0),
    Stream("ATTITUDE_TARGET", VEHICLE, 25.0),
    Stream("SET_ATTITUDE_TARGET", COMPANION, 50.0),
    Stream("VISION_SPEED_ESTIMATE", COMPANION, 50.0),
    Stream("POSITION_TARGET_LOCAL_NED", COMPANION, 10.0),
    Stream("HEARTBEAT", VEHICLE, 1.0),
    Stream("HEARTBEAT", COMPANION, 1.0),
    Stream("SYS_STATUS", VEHICLE, 1.0),
)

#: fields set to fixed values, as the vehicle and the companion send them (others: signals)
_FIXED: dict[str, dict[str, float]] = {
    "OPTICAL_FLOW": {"quality": 200, "ground_distance": -1.0, "sensor_id": 0,
                     "flow_rate_x": 0.0, "flow_rate_y": 0.0},
    "DISTANCE_SENSOR": {"min_distance": 20, "max_distance": 1000, "type": 0, "id": 0, "orientation": 25,
                        "covariance": 0, "horizontal_fov": 0.0, "vertical_fov": 0.0, "quaternion": 0.0,
                        "signal_quality": 0},
    "RAW_IMU": {"id": 0, "temperature": 0},
    "SET_ATTITUDE_TARGET": {"target_system": 1, "target_component": 1, "type_mask": 7, "thrust": 0.5},
    "ATTITUDE_TARGET": {"type_mask": 7},
    "POSITION_TARGET_LOCAL_NED": {"type_mask": 0b110111000111, "coordinate_frame": 12},
    "HEARTBEAT": {"custom_mode": 20, "type": 2, "autopilot": 3, "base_mode": 209, "system_status": 4,
                  "mavlink_version": 3},
    "SYS_STATUS": {"onboard_control_sensors_present_extended": 0, "onboard_control_sensors_enabled_extended": 0,
                   "onboard_control_sensors_health_extended": 0},
}


def _crc16_rows(rows: np.ndarray, extra: int) -> np.ndarray:
    """CRC-16/MCRF4XX of each row (bytes after STX up to the payload end) and ``extra``,
    the plain bytewise algorithm (independent of the reader's table method)."""
    crc = np.full(rows.shape[0], 0xFFFF, dtype=np.uint32)
    for col in [*np.ascontiguousarray(rows.T), np.full(rows.shape[0], extra, dtype=np.uint8)]:
        tmp = (col.astype(np.uint32) ^ (crc & 0xFF)) & 0xFF
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc.astype(np.uint16)


def _payloads(message: str, t_s: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, int, int]:
    """Wire payloads (n, size) uint8 of ``message`` at scenario times ``t_s`` (s), with
    smooth or random field values; and the message id and crc_extra."""
    lay = next(lay for lay in layouts().values() if lay.name == message)
    assert lay.dtype is not None
    rec = np.zeros(len(t_s), dtype=lay.dtype)
    fixed = _FIXED.get(message, {})
    for k, name in enumerate(lay.dtype.names or ()):
        base = lay.dtype.fields[name][0]  # type: ignore[index]
        shape = (len(t_s), *base.shape)
        kind = base.base.kind
        if name in fixed:
            rec[name] = fixed[name]
        elif name in ("time_usec", "usec"):
            rec[name] = np.round(t_s * 1e6).astype(np.uint64)
        elif name == "time_boot_ms":
            rec[name] = np.round(t_s * 1e3).astype(np.uint32)
        elif kind == "f":
            phase = rng.uniform(0, 2 * np.pi)
            signal = 0.3 * np.sin(2 * np.pi * 0.2 * t_s + phase) + 0.01 * rng.standard_normal(len(t_s))
            rec[name] = (signal[:, None] + np.zeros(shape)) if base.shape else signal
        elif kind in "iu":
            lo = 0 if kind == "u" else -200
            rec[name] = rng.integers(lo, 200 + k, size=shape)
    return rec.view(np.uint8).reshape(len(t_s), lay.size), lay.msgid, lay.crc_extra


def build_recording(path: str | Path, minutes: float, *, seed: int = 0,
                    streams: tuple[Stream, ...] = FLIGHT_STREAMS) -> dict[str, Any]:
    """Write a .tlog of ``minutes`` of flight to ``path``, MAVLink 2 packets with trailing
    zeros truncated as pymavlink sends them. Packed with numpy (a few seconds for an hour).
    Returns {"path", "messages", "bytes", "build_s"}."""
    started = time.perf_counter()
    rng = np.random.default_rng(seed)
    duration = minutes * 60.0
    parts = []
    for k, st in enumerate(streams):
        n = int(duration * st.rate_hz)
        t = (np.arange(n) + 0.1 * k / len(streams)) / st.rate_hz
        rows, msgid, extra = _payloads(st.message, t, rng)
        nonzero = rows != 0
        plen = np.where(nonzero.any(axis=1), rows.shape[1] - np.argmax(nonzero[:, ::-1], axis=1), 1)
        # the host's clock: boot time plus a little delivery jitter, never before the sample
        host_us = np.round((T0_UNIX_S + t + rng.uniform(0, 0.002, n)) * 1e6).astype(np.uint64)
        parts.append((st, rows, plen, msgid, extra, host_us))
    host = np.concatenate([p[5] for p in parts])
    order = np.argsort(host, kind="stable")
    position = np.empty_like(order)
    position[order] = np.arange(len(order))
    sizes = np.concatenate([8 + 10 + p[2] + 2 for p in parts])[order]
    offsets = np.concatenate(([0], np.cumsum(sizes)[:-1]))
    out = np.zeros(int(sizes.sum()), dtype=np.uint8)
    stream_of = np.concatenate([np.full(len(p[2]), k) for k, p in enumerate(parts)])[order]
    # sequence numbers count per sender, in file order
    seq = np.zeros(len(order), dtype=np.uint8)
    for sender in {st.sender for st in streams}:
        mine = np.isin(stream_of, [k for k, st in enumerate(streams) if st.sender == sender])
        seq[mine] = np.arange(int(mine.sum())) % 256
    first = 0
    for st, rows, plen, msgid, extra, host_us in parts:
        pos = position[first:first + len(plen)]
        first += len(plen)
        for length in np.unique(plen):
            sel = np.flatnonzero(plen == length)
            m = len(sel)
            rec = np.empty((m, 8 + 10 + int(length) + 2), dtype=np.uint8)
            rec[:, :8] = host_us[sel].astype(">u8").view(np.uint8).reshape(m, 8)
            rec[:, 8] = 0xFD
            rec[:, 9] = length
            rec[:, 10:12] = 0
            rec[:, 12] = seq[pos[sel]]
            rec[:, 13], rec[:, 14] = st.sender
            rec[:, 15:18] = np.array([msgid & 0xFF, (msgid >> 8) & 0xFF, msgid >> 16], dtype=np.uint8)
            rec[:, 18:18 + length] = rows[sel, :length]
            crc = _crc16_rows(rec[:, 9:18 + length], extra)
            rec[:, -2] = crc & 0xFF
            rec[:, -1] = crc >> 8
            sliding_window_view(out, rec.shape[1], writeable=True)[offsets[pos[sel]]] = rec
    Path(path).write_bytes(out.tobytes())
    _spot_check(Path(path), offsets, rng)
    return {"path": str(path), "messages": int(len(order)), "bytes": int(len(out)),
            "build_s": time.perf_counter() - started}


def _spot_check(path: Path, offsets: np.ndarray, rng: np.random.Generator, n: int = 2000) -> None:
    """pymavlink must accept a random sample of the built packets (CRC, length, decoding)."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    data = path.read_bytes()
    ends = np.append(offsets[1:], len(data))
    mav = mavlink2.MAVLink(None)
    for i in rng.choice(len(offsets), size=min(n, len(offsets)), replace=False):
        mav.decode(bytearray(data[int(offsets[i]) + 8:int(ends[i])]))  # raises on any error


# ---------------------------------------------------------------------------------------------
# Measurements (each in a fresh interpreter)

_READER_PROBE = """
import json, resource, sys, time
sys.path.insert(0, {root!r})
import numpy, pymavlink.dialects.v20.ardupilotmega
from companion.recordings.tlog_reader import read_tlog


def peak_kib():
    # the peak resident set since the last reset (VmHWM); ru_maxrss where /proc has none
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmHWM"))
    except (OSError, StopIteration):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


try:  # a child inherits its parent's peak at fork: reset it (Linux >= 4.0)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
except OSError:
    pass
base = peak_kib()
runs = []
for _ in range({repeat}):
    t, c = time.perf_counter(), time.process_time()
    rec = read_tlog({path!r})
    runs.append((time.perf_counter() - t, time.process_time() - c))
    n, skipped = rec.n_messages, rec.skipped_bytes
    del rec
peak = peak_kib()
print(json.dumps({{"runs": runs, "messages": n, "rss_base_kib": base, "rss_peak_kib": peak,
                  "skipped_bytes": skipped}}))
"""

_PYMAVLINK_PROBE = """
import json, os, sys, time
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
t = time.perf_counter()
conn = mavutil.mavlink_connection({path!r}, dialect="ardupilotmega")  # a .tlog: mavmmaplog, indexes the file
open_s = time.perf_counter() - t
limit = {limit}
n = 0
t, c = time.perf_counter(), time.process_time()
while limit <= 0 or n < limit:
    m = conn.recv_match()
    if m is None:
        break
    n += 1
print(json.dumps({{"seconds": time.perf_counter() - t, "cpu_s": time.process_time() - c, "messages": n,
                  "open_s": open_s}}))
"""


def _run_probe(code: str) -> dict[str, Any]:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def measure_pymavlink(path: str | Path, *, sample: int = 200_000) -> dict[str, Any]:
    """pymavlink's ``recv_match`` loop over the first ``sample`` messages (0: all), timed
    after ``mavlink_connection`` has opened (and indexed) the file, which is timed apart.
    Returns {"messages", "seconds", "cpu_s", "msgs_per_s", "cpu_msgs_per_s", "sampled", "open_s"}."""
    r = _run_probe(_PYMAVLINK_PROBE.format(path=str(path), limit=int(sample)))
    return {"messages": r["messages"], "seconds": r["seconds"], "cpu_s": r["cpu_s"], "open_s": r["open_s"],
            "msgs_per_s": r["messages"] / r["seconds"], "cpu_msgs_per_s": r["messages"] / r["cpu_s"],
            "sampled": sample > 0}


def measure_reader(path: str | Path, *, pymavlink_sample: int | None = 200_000, repeat: int = 3) -> dict[str, Any]:
    """Time ``read_tlog`` on ``path`` ``repeat`` times in a fresh interpreter, with its peak
    memory; and, unless ``pymavlink_sample`` is None, pymavlink's loop (0: the whole file).

    Returns {"file_bytes", "messages", "reader_s" (best wall time), "reader_cold_s" (the
    first read, which also builds the decoding tables), "reader_cpu_s" (best CPU time),
    "reader_msgs_per_s", "peak_rss_bytes" (growth of the peak resident set while reading, over
    the interpreter with numpy and pymavlink imported), "peak_ratio" (that / file size)}, plus
    "pymavlink_msgs_per_s", "pymavlink_full_s_est", "speedup" (wall-time ratio) and
    "speedup_cpu" (CPU-time ratio: steadier on a shared machine)."""
    size = Path(path).stat().st_size
    r = _run_probe(_READER_PROBE.format(root=str(ROOT), path=str(path), repeat=max(1, int(repeat))))
    peak = (r["rss_peak_kib"] - r["rss_base_kib"]) * 1024
    wall = min(w for w, _ in r["runs"])
    cpu = min(c for _, c in r["runs"])
    result: dict[str, Any] = {
        "file_bytes": size, "messages": r["messages"], "reader_s": wall, "reader_cold_s": r["runs"][0][0],
        "reader_cpu_s": cpu, "reader_runs": len(r["runs"]),
        "reader_msgs_per_s": r["messages"] / wall, "peak_rss_bytes": peak,
        "peak_ratio": peak / size, "skipped_bytes": r["skipped_bytes"]}
    if pymavlink_sample is not None:
        pm = measure_pymavlink(path, sample=pymavlink_sample)
        result.update({
            "pymavlink_messages_timed": pm["messages"], "pymavlink_s": pm["seconds"],
            "pymavlink_open_s": pm["open_s"],
            "pymavlink_msgs_per_s": pm["msgs_per_s"],
            "pymavlink_full_s_est": r["messages"] / pm["msgs_per_s"],
            "speedup": result["reader_msgs_per_s"] / pm["msgs_per_s"],
            "speedup_cpu": (r["messages"] / cpu) / pm["cpu_msgs_per_s"]})
    return result


def format_table(built: dict[str, Any], m: dict[str, Any]) -> str:
    """The benchmark's report as a fixed-width text table."""
    mb = m["file_bytes"] / 1e6
    rows = [
        ("recording", f"{m['messages']:,} messages, {mb:.1f} MB"
                      + (f", built in {built['build_s']:.1f} s" if built else "")),
        ("pymavlink recv_match", f"{m['pymavlink_msgs_per_s']:>12,.0f} msg/s   "
                                 f"(timed on {m['pymavlink_messages_timed']:,} messages in "
                                 f"{m['pymavlink_s']:.1f} s; whole file ~{m['pymavlink_full_s_est']:.0f} s, "
                                 f"plus {m['pymavlink_open_s']:.1f} s to open it)"),
        ("flowhold read_tlog", f"{m['reader_msgs_per_s']:>12,.0f} msg/s   "
                               f"(whole file in {m['reader_s']:.2f} s, best of {m['reader_runs']}; "
                               f"first read {m['reader_cold_s']:.2f} s; CPU {m['reader_cpu_s']:.2f} s)"),
        ("speed ratio", f"{m['speedup']:>12.1f} x   wall time ({m['speedup_cpu']:.0f} x in CPU time; "
                        "target >= 50 x; pymavlink's opening not counted)"),
        ("reader peak memory", f"{m['peak_rss_bytes'] / 1e6:>12.1f} MB    "
                               f"= {m['peak_ratio']:.2f} x file size (target < 4 x)"),
    ]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="length of the built recording")
    ap.add_argument("--path", help="use (or build, if missing) this .tlog instead of a temporary one")
    ap.add_argument("--pymavlink-sample", type=int, default=200_000,
                    help="time pymavlink on this many messages and extrapolate (0: the whole file)")
    ap.add_argument("--json", help="also write the numbers here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(args.path) if args.path else Path(tmp) / "bench.tlog"
        built: dict[str, Any] = {}
        if not path.exists():
            built = build_recording(path, args.minutes)
        m = measure_reader(path, pymavlink_sample=args.pymavlink_sample)
        print(format_table(built, m))
        if args.json:
            Path(args.json).write_text(json.dumps({"build": built, **m}, indent=2))
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    raise SystemExit(main())
