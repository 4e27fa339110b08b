"""Benchmark: ``python -m companion diagnose`` against the time pymavlink needs merely to read.

    .venv/bin/python benchmarks/bench_diagnose.py [--minutes 60] [--out out/bench_diagnose]

Flies (once; cached in ``--out``) a 150 s and a ``--minutes`` closed-loop varied flight
(``simvehicle.engines.flights``: steps, creeps, sinusoids, altitude changes, turbulence, sensor noise,
a gyro bias and a linear drag so there is something to find), then times, each in a fresh
subprocess as a user runs them:

* ``python -m companion diagnose REC --json OUT`` on both recordings (issue 12: under 10 s for
  150 s; under a quarter of pymavlink's read time for the long one);
* pymavlink's ``mavutil.mavlink_connection(path)`` + ``recv_match()`` loop over every message of
  the long recording (nothing else done with them);
* the same two on a flight of the generalisation matrix's generator as long, with 8 % of its
  messages lost at random (``build_lossy``: thousands of attitude segments).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

PYMAVLINK_READ = """
import os, sys, time
os.environ["MAVLINK20"] = "1"  # as benchmarks/bench_reader.py times it
from pymavlink import mavutil
t = time.perf_counter()
m = mavutil.mavlink_connection(sys.argv[1], dialect="ardupilotmega")
n = 0
while m.recv_match() is not None:
    n += 1
print(n, time.perf_counter() - t)
"""


def build(path: Path, duration_s: float, seed: int) -> Path:
    from companion.config import GyroBias, LinearDrag, load_config, with_effects
    from simvehicle.engines.flights import flight_plan, with_sensor_noise
    from simvehicle.engines.scenarios import fly

    if path.exists():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    cfg = with_effects(with_sensor_noise(load_config()), gyro_bias=GyroBias(0.01, -0.006), linear_drag=LinearDrag(0.3))
    part = path.with_suffix(".part")
    fly(cfg, flight_plan(seed, duration_s=duration_s).scenario(), seed=seed, tlog=part)
    part.replace(path)
    return path


def build_lossy(path: Path, duration_s: float, seed: int = 164, lost: float = 0.0833) -> Path:
    """A flight of the generalisation matrix's generator (``simvehicle.engines.flightgen``, seed
    164: an attitude delay and dynamics, turbulence, attitude and gyro noise) stretched to
    ``duration_s`` with ``lost`` of its messages lost at random: every lost command restarts the
    attitude simulation, thousands of segments an hour."""
    import dataclasses

    import numpy as np

    from simvehicle.engines import flightgen as fg

    if path.exists():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    spec = fg.draw_spec(seed)
    prof = fg.draw_profile(np.random.default_rng([seed, 13]), spec.warmup_s + duration_s, 2.0, False, 1.5)
    spec = dataclasses.replace(spec, duration_s=duration_s, flight=prof,
                               loss=dataclasses.replace(spec.loss, random_frac=lost))
    fg.write_flight(spec, fg.simulate(spec), path.parent, path.stem)
    return path


def time_diagnose(path: Path, out: Path) -> tuple[float, dict]:
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "companion", "diagnose", str(path), "--json", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=3600, check=False)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"diagnose failed: {proc.stderr.strip()}")
    return wall, json.loads(out.read_text())


def time_pymavlink(path: Path) -> tuple[int, float, float]:
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", PYMAVLINK_READ, str(path)], capture_output=True, text=True,
                          timeout=7200, check=True)
    wall = time.perf_counter() - t
    n, loop_s = proc.stdout.split()
    return int(n), float(loop_s), wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--out", default="out/bench_diagnose")
    args = ap.parse_args(argv)
    out = Path(args.out)
    short = build(out / "flight_150s.tlog", 150.0, 101)
    long = build(out / f"flight_{args.minutes:g}min.tlog", 60.0 * args.minutes, 102)
    w_short, rep_short = time_diagnose(short, out / "short.json")
    w_long, rep_long = time_diagnose(long, out / "long.json")
    n, loop_s, w_read = time_pymavlink(long)
    lossy = build_lossy(out / f"lossy_{args.minutes:g}min.tlog", 60.0 * args.minutes)
    w_lossy, _rep = time_diagnose(lossy, out / "lossy.json")
    n_lossy, loop_lossy, _w = time_pymavlink(lossy)
    found = [f["effect"] for f in rep_long["findings"] if f["significant"]]
    print(f"diagnose, 150 s recording ({short.stat().st_size / 1e6:.1f} MB): {w_short:.1f} s (issue 12: < 10 s)")
    size_mb = long.stat().st_size / 1e6
    print(f"diagnose, {args.minutes:g} min recording ({size_mb:.0f} MB): {w_long:.1f} s; found {found}")
    print(f"pymavlink reading the same {n} messages: {loop_s:.1f} s in its loop ({w_read:.1f} s with start-up)")
    print(f"ratio diagnose / pymavlink read: {w_long / loop_s:.2f} (issue 12: < 0.25)")
    print(f"diagnose, {args.minutes:g} min with 8 % of messages lost ({lossy.stat().st_size / 1e6:.0f} MB): "
          f"{w_lossy:.1f} s; pymavlink {loop_lossy:.1f} s over its {n_lossy} messages: ratio "
          f"{w_lossy / loop_lossy:.2f} (issue 12: < 0.25, whatever the recording)")
    print(f"load average while measuring: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
