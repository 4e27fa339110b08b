"""Benchmark: simulator speed, the fine-step reference against the fast engine.

    .venv/bin/python benchmarks/bench_sim.py [--batch 1000] [--duration 150] [--workers N]

All flights fly ``fastsim.demanding_flight`` (velocity steps of up to 4 m/s that saturate the
tilt limit, 4 N gusts), the companion's estimator and PI closing the loop. Speeds are simulated
seconds per wall-clock second:

- reference: ``simvehicle.model.sim.Simulator`` (RK4, 20 steps per 20 ms frame) driven by
  ``CompanionCore`` (``fastsim.reference_run``), the baseline;
- ``scenarios.fly``: the same, every message through MAVLink encoding and decoding;
- fast engine, one flight: schedules as arrays, and as Python functions (evaluated at every
  quadrature node: the user's functions then dominate);
- fast engine, the frame loop interpreted (what runs without numba);
- fast engine, a batch of N flights with per-flight seeds (gyro noise and turbulence on, so
  every flight differs), in one process and over all cores.

``write_flight_tlog(path, duration_s, seed)`` writes a long closed-loop recording as
``scenarios.fly`` would (same messages, same numbers) in a fraction of its time; run.py uses it
for the replay and diagnose benchmarks.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from companion.config import Config, load_config, replace_section  # noqa: E402
from simvehicle.engines import fastsim  # noqa: E402


def _speed(sim_s: float, wall_s: float, **extra: Any) -> dict[str, Any]:
    return {"sim_s": sim_s, "wall_s": wall_s, "speed": sim_s / wall_s, **extra}


def measure_reference(duration_s: float = 30.0, cfg: Config | None = None) -> dict[str, Any]:
    """The fine-step reference closed by ``CompanionCore`` (no MAVLink)."""
    cfg = cfg or load_config()
    sched = fastsim.demanding_flight(duration_s)
    t0 = time.perf_counter()
    fastsim.reference_run(cfg, duration_s=duration_s, setpoint=sched["setpoints"], force=sched["forces"])
    return _speed(duration_s, time.perf_counter() - t0)


def _scenario(duration_s: float) -> Any:
    from simvehicle.engines.scenarios import Scenario

    sched = fastsim.demanding_flight(duration_s)
    sp, fo, T = sched["setpoints"], sched["forces"], 0.02
    n = len(fo)
    return Scenario("demanding", duration_s, lambda t: tuple(sp[min(int(round(t / T)), n)]),
                    force=lambda t: tuple(fo[min(int(t / T), n - 1)]))


def measure_fly(duration_s: float = 15.0, cfg: Config | None = None) -> dict[str, Any]:
    """``scenarios.fly``: the reference with every message through MAVLink."""
    from simvehicle.engines.scenarios import fly

    cfg = cfg or load_config()
    sc = _scenario(duration_s)
    t0 = time.perf_counter()
    fly(cfg, sc)
    return _speed(duration_s, time.perf_counter() - t0)


def measure_fast_single(duration_s: float = 150.0, repeats: int = 5, cfg: Config | None = None,
                        functions: bool = False) -> dict[str, Any]:
    """One flight on the fast engine, all columns kept; median of ``repeats`` (after a warm-up)."""
    cfg = cfg or load_config()
    fastsim.warm_up()
    if functions:
        sc = _scenario(duration_s)
        kwargs: dict[str, Any] = {"setpoints": sc.setpoint, "forces": sc.force}
    else:
        kwargs = fastsim.demanding_flight(duration_s)
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fastsim.simulate_batch(cfg, 1, duration_s=duration_s, **kwargs)
        walls.append(time.perf_counter() - t0)
    return _speed(duration_s, statistics.median(walls), repeats=repeats)


def measure_fast_interpreted(duration_s: float = 4.0, cfg: Config | None = None) -> dict[str, Any]:
    """The fast engine's frame loop run as plain Python (numba's contribution)."""
    cfg = cfg or load_config()
    compiled = fastsim._frames
    fastsim._frames = getattr(compiled, "py_func", compiled)
    try:
        t0 = time.perf_counter()
        fastsim.simulate_batch(cfg, 1, duration_s=duration_s, **fastsim.demanding_flight(duration_s))
        wall = time.perf_counter() - t0
    finally:
        fastsim._frames = compiled
    return _speed(duration_s, wall)


def batch_config() -> Config:
    """Table VI with the gyro's white noise on (each seed then flies a different flight)."""
    return replace_section(load_config(), "imu", gyro_noise=True)


def measure_fast_batch(n: int = 1000, duration_s: float = 150.0, workers: int = 1) -> dict[str, Any]:
    """``n`` flights of ``duration_s`` in one ``simulate_batch`` call, positions kept."""
    fastsim.warm_up()
    sched = fastsim.demanding_flight(duration_s)
    t0 = time.perf_counter()
    res = fastsim.simulate_batch(batch_config(), n, duration_s=duration_s, seeds=np.arange(n),
                                 turbulence_sigma_n=0.5, turbulence_tau_s=1.0, columns=("x_m", "y_m"),
                                 workers=workers, **sched)
    wall = time.perf_counter() - t0
    final = res["x_m"][:, -1]
    assert len(res) == n and np.all(np.isfinite(final)) and len(np.unique(final)) == n
    return _speed(n * duration_s, wall, flights=n, duration_s=duration_s, workers=workers)


def measure_compile() -> dict[str, Any]:
    """First use of the kernel in a fresh process: numba import and load from its cache (or
    compile, the first time after a change of fastsim.py)."""
    import subprocess

    code = ("import time; t0 = time.perf_counter(); from simvehicle.engines import fastsim; t1 = time.perf_counter(); "
            "fastsim.warm_up(); t2 = time.perf_counter(); print(t1 - t0, t2 - t1)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=600,
                         check=True)
    imp, warm = (float(x) for x in out.stdout.split())
    return {"import_s": imp, "first_flight_s": warm}


# ---------------------------------------------------------------------------------------------
# Long recordings for replay and diagnose


def write_flight_tlog(path: str | Path, duration_s: float, seed: int = 0) -> dict[str, Any]:
    """A closed-loop recording of a varied flight (``simvehicle.engines.flights``: steps, slow creeps,
    sinusoids, altitude changes, turbulence; sensor noise; linear drag b = 0.3 N s/m as a model
    mismatch to find), with the messages ``scenarios.fly`` writes, each frame's numbers from the
    fast engine through MAVLink quantization (what ``fly`` would record). Returns
    {"path", "frames", "messages", "bytes", "build_s"}."""
    from companion.config import LinearDrag, with_effects
    from companion.mavlink import outbound
    from companion.recordings.tlog_writer import TlogWriter, mav_encoder
    from companion.step.profiles import Profile
    from simvehicle.engines.scenarios import TLOG_EPOCH_S, VEHICLE_SYSID
    from simvehicle.model import telemetry
    from simvehicle.model.sim import FrameSample

    started = time.perf_counter()
    cfg = with_effects(load_config(), linear_drag=LinearDrag(0.3))
    try:
        from simvehicle.engines.flights import flight_plan, with_sensor_noise

        cfg = with_sensor_noise(cfg)
        sc = flight_plan(seed, duration_s).scenario()
    except ImportError:  # pragma: no cover - the flights module belongs to another part of the tree
        sc = _scenario(duration_s)
    run = fastsim.fly_fast(cfg, dataclasses.replace(sc, duration_s=duration_s), seed=seed)
    c = run.columns
    n = len(c["t_s"])
    roll_active = np.concatenate(([0.0], c["roll_cmd_rad"][:-1]))
    pitch_active = np.concatenate(([0.0], c["pitch_cmd_rad"][:-1]))
    names = [f.name for f in dataclasses.fields(FrameSample)]
    veh = mav_encoder(VEHICLE_SYSID, 1)
    comp = mav_encoder(VEHICLE_SYSID, outbound.COMPANION_COMPONENT)
    q, T, rf = cfg.flow_sensor.q_rad_per_count, cfg.flow_sensor.frame_period_s, cfg.rangefinder
    messages = 0
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with TlogWriter(path) as log:
        for k in range(n):
            t = float(c["t_s"][k])
            stamp = TLOG_EPOCH_S + t
            values = {"frame": k, "t_s": t, "flow_x_counts": int(c["flow_x_counts"][k]),
                      "flow_y_counts": int(c["flow_y_counts"][k]), "flow_quality": 255, "gyro_z_rad_s": 0.0,
                      "force_x_n": 0.0, "force_y_n": 0.0, "roll_cmd_active_rad": float(roll_active[k]),
                      "pitch_cmd_active_rad": float(pitch_active[k]),
                      # the fast engine models no accelerometer: RAW_IMU holds the (0, 0, -1000) mg placeholder
                      "accel_x_m_s2": math.nan, "accel_y_m_s2": math.nan, "accel_z_m_s2": math.nan}
            s = FrameSample(**{name: values[name] if name in values else float(c[name][k]) for name in names})
            if k % int(round(1.0 / T)) == 0:
                log.write(telemetry.heartbeat(veh, armed=True), stamp, encoder=veh)
                messages += 1
            for m in telemetry.frame_messages(veh, s, Profile.PAPER, q, T, rf.min_m, rf.max_m):
                log.write(m, stamp, encoder=veh)
                messages += 1
            ms = int(round(t * 1e3))
            log.write(outbound.set_attitude_target(comp, ms, VEHICLE_SYSID, float(c["roll_cmd_rad"][k]),
                                                   float(c["pitch_cmd_rad"][k]), 0.0), stamp, encoder=comp)
            log.write(outbound.position_target(comp, ms, float(c["vx_set_m_s"][k]), float(c["vy_set_m_s"][k])),
                      stamp, encoder=comp)
            messages += 2
            if not c["hold"][k]:
                log.write(outbound.vision_speed(comp, int(round(t * 1e6)), float(c["est_vx_m_s"][k]),
                                                float(c["est_vy_m_s"][k])), stamp, encoder=comp)
                messages += 1
            log.write(telemetry.attitude_target(veh, t, float(roll_active[k]), float(pitch_active[k])), stamp,
                      encoder=veh)
            messages += 1
    return {"path": str(path), "frames": n, "messages": messages, "bytes": Path(path).stat().st_size,
            "build_s": time.perf_counter() - started}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, default=1000, help="flights in the batch")
    ap.add_argument("--duration", type=float, default=150.0, help="seconds per flight")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = ap.parse_args(argv)
    ref = measure_reference()
    rows = [("reference (RK4 1 ms + CompanionCore)", ref),
            ("scenarios.fly (+ MAVLink)", measure_fly()),
            ("fast, one flight (arrays)", measure_fast_single(args.duration)),
            ("fast, one flight (functions)", measure_fast_single(args.duration, repeats=3, functions=True)),
            ("fast, interpreted kernel", measure_fast_interpreted()),
            (f"fast, batch {args.batch} x {args.duration:g} s, 1 process",
             measure_fast_batch(args.batch, args.duration, 1)),
            (f"fast, batch {args.batch} x {args.duration:g} s, {args.workers} processes",
             measure_fast_batch(args.batch, args.duration, args.workers))]
    for name, r in rows:
        print(f"{name:<48} {r['speed']:>12,.1f} sim-s/s  {r['speed'] / ref['speed']:>10,.0f} x ref  "
              f"(wall {r['wall_s']:.3f} s)")
    print(f"{'first use in a fresh process':<48} {measure_compile()}")
    return 0 if math.isfinite(ref["speed"]) else 1


if __name__ == "__main__":
    sys.exit(main())
