"""Benchmark: the fleet diagnosis and the sweep on Dask, against the same work in one process.

    .venv/bin/python benchmarks/bench_fleet.py [--recordings 200] [--duration 150] [--flights 10000]
                                               [--workers 1 2] [--workdir out/bench_fleet] [--json OUT]

Fleet: ``--recordings`` closed-loop recordings of ``--duration`` s (``bench_sim.write_flight_tlog``:
varied flights with sensor noise and a linear drag to find; written once into ``--workdir`` and
reused) diagnosed by ``companion.fleet.run.run_fleet``:

- in-process (the baseline: one file after another, no scheduler);
- on a Dask ``LocalCluster`` of each ``--workers`` count, each run into a fresh output folder.

Sweep: ``--flights`` flights (the step and the gust over an altitude x Q grid; seeds make up the
count) flown by ``simvehicle.tools.sweep.run_sweep`` in-process and on the same clusters, with the
default batches (about four tasks per worker) and with batches of ``--small-batch`` flights.

Per run: wall time (cluster start included), the cluster's start-up alone (workers started and
warmed: the diagnosis imported, the simulator's kernel compiled), the time inside the tasks
(summed), and the scheduling overhead per task: (wall - start-up - task time / workers) / tasks
per worker, i.e. what each task cost beyond its own work. A no-op map over 1000 tasks gives
the bare per-task overhead of the scheduler. Every ratio is against the in-process run of the
same benchmark, measured in the same invocation. The machine's load average is printed with the
table: on a shared machine the 2-worker speed-up is bounded by the cores actually free.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
for p in (str(ROOT), str(HERE)):
    if p not in sys.path:
        sys.path.insert(0, p)

from companion.fleet.engine import Engine  # noqa: E402
from companion.fleet.run import run_fleet  # noqa: E402
from companion.fleet.work import warm_up as fleet_warm_up  # noqa: E402
from simvehicle.engines import fastsim  # noqa: E402
from simvehicle.tools import sweep  # noqa: E402

RECORDING_VERSION = 1  # bump when the recordings change


def recordings(workdir: Path, n: int, duration_s: float) -> list[Path]:
    """``n`` recordings of ``duration_s`` in ``workdir/recordings`` (made once, seeds 0..n-1)."""
    import bench_sim

    folder = workdir / f"recordings_{int(duration_s)}s_v{RECORDING_VERSION}"
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    t0 = time.perf_counter()
    for seed in range(n):
        p = folder / f"vehicle{seed % 10:02d}" / f"flight_{seed:04d}.tlog"
        if not p.is_file():
            p.parent.mkdir(exist_ok=True)
            bench_sim.write_flight_tlog(p, duration_s, seed=seed)
        out.append(p)
    print(f"recordings: {n} x {duration_s:g} s in {folder} ({time.perf_counter() - t0:.0f} s to make the missing)",
          file=sys.stderr, flush=True)
    return out


def startup_s(workers: int, warm: Callable[[], None]) -> tuple[float, float]:
    """(seconds to start a LocalCluster of ``workers`` and run ``warm`` on each, the bare
    scheduling overhead per task in s from a no-op map of 1000 tasks)."""
    t0 = time.perf_counter()
    with Engine(workers=workers, progress=False) as e:
        e.on_every_worker(warm)
        started = time.perf_counter() - t0
        n = 1000
        t1 = time.perf_counter()
        for _ in e.map(abs, [-1.0] * n):
            pass
        per_task = (time.perf_counter() - t1) / n
    return started, per_task


def fleet_runs(recs: list[Path], workers: list[int], workdir: Path) -> list[dict[str, Any]]:
    rows = []
    inputs = [str(p) for p in recs]
    for w in [0, *workers]:
        out = Path(tempfile.mkdtemp(prefix=f"fleet_w{w}_", dir=workdir))
        start, bare = startup_s(w, fleet_warm_up) if w else (0.0, 0.0)
        t0 = time.perf_counter()
        run = run_fleet(inputs, out, in_process=(w == 0), workers=w or None, progress=False, summary=False)
        wall = time.perf_counter() - t0
        tasks = sum(run.task_s)
        n = len(run.task_s)
        per_worker = max(w, 1)
        overhead = (run.wall_s - start - tasks / per_worker) / max(n / per_worker, 1)
        rows.append({"mode": "in-process" if w == 0 else f"LocalCluster {w} worker(s)", "workers": w,
                     "tasks": n, "failed": run.failed, "wall_s": wall, "engine_wall_s": run.wall_s,
                     "startup_s": start, "task_s_sum": tasks, "task_s_mean": tasks / max(n, 1),
                     "overhead_per_task_s": overhead, "bare_overhead_per_task_s": bare})
        print(f"fleet {rows[-1]['mode']}: {wall:.1f} s for {n} files", file=sys.stderr, flush=True)
        shutil.rmtree(out, ignore_errors=True)
    return rows


def sweep_spec(workdir: Path, flights: int) -> sweep.SweepSpec:
    """The step and the gust over a 10 x 10 altitude x Q grid, seeds making up ``flights``."""
    seeds = max(1, math.ceil(flights / (2 * 100)))
    alts = [round(0.5 + 0.25 * i, 3) for i in range(10)]
    qs = [round(0.0005 + 0.0005 * i, 6) for i in range(10)]
    path = workdir / "bench_sweep.toml"
    path.write_text(f'title = "benchmark"\nbase_config = "{ROOT / "configs" / "paper.toml"}"\n'
                    f'scenarios = ["step", "gust"]\nseeds = {list(range(seeds))}\n[grid]\n'
                    f'"world.altitude_m" = {alts}\n"flow_sensor.q_rad_per_count" = {qs}\n')
    return sweep.load_sweep(path)


def sweep_runs(spec: sweep.SweepSpec, workers: list[int], small_batch: int) -> list[dict[str, Any]]:
    rows = []
    n_flights = len(sweep.grid_configs(spec)) * len(spec.seeds) * len(spec.scenarios)
    for w, batch in [(0, None), *((w, b) for w in workers for b in (None, small_batch))]:
        start = startup_s(w, fastsim.warm_up)[0] if w else 0.0
        timings: list[float] = []
        t0 = time.perf_counter()
        with Engine(workers=w or None, in_process=(w == 0), progress=False) as e:
            sweep.run_sweep(spec, engine=e, batch_flights=batch, timings=timings)
        wall = time.perf_counter() - t0
        n = len(timings)
        per_worker = max(w, 1)
        tasks = sum(timings)
        overhead = (wall - start - tasks / per_worker) / max(n / per_worker, 1)
        rows.append({"mode": "in-process" if w == 0 else f"LocalCluster {w} worker(s)", "workers": w,
                     "batch": batch or math.ceil(n_flights / max(n, 1)), "tasks": n, "flights": n_flights,
                     "wall_s": wall, "startup_s": start, "task_s_sum": tasks, "overhead_per_task_s": overhead})
        print(f"sweep {rows[-1]['mode']}, {rows[-1]['batch']} flights/task: {wall:.1f} s", file=sys.stderr,
              flush=True)
    return rows


def table(fleet: list[dict[str, Any]], sweeps: list[dict[str, Any]], meta: dict[str, Any]) -> str:
    lines = [f"machine: {meta['cpus']} cores, load average {meta['load_before']} before, {meta['load_after']} after; "
             f"Python {meta['python']}", ""]
    if fleet:
        lines += _fleet_table(fleet, meta)
    if sweeps:
        lines += _sweep_table(sweeps)
    return "\n".join(lines)


def _fleet_table(fleet: list[dict[str, Any]], meta: dict[str, Any]) -> list[str]:
    lines = []
    base = fleet[0]["wall_s"]
    lines.append(f"fleet: {fleet[0]['tasks']} recordings of {meta['duration_s']:g} s "
                 f"(mean {fleet[0]['task_s_mean']:.2f} s of diagnosis each, in-process)")
    lines.append("| mode | wall (s) | files/s | speed-up vs in-process | mean task (s) | "
                 "cluster start and warm-up (s) | overhead per task (ms) | bare scheduler per task (ms) |")
    lines.append("|---|---|---|---|---|---|---|---|")
    for r in fleet:
        lines.append(f"| {r['mode']} | {r['wall_s']:.1f} | {r['tasks'] / r['wall_s']:.2f} | "
                     f"{base / r['wall_s']:.2f}x | {r['task_s_mean']:.2f} | {r['startup_s']:.1f} | "
                     f"{1e3 * r['overhead_per_task_s']:.0f} | {1e3 * r['bare_overhead_per_task_s']:.1f} |")
    one = next((r for r in fleet if r["workers"] == 1), None)
    for r in fleet:
        if one and r["workers"] > 1:
            cores = r["workers"] * one["task_s_mean"] / r["task_s_mean"]
            lines.append(f"{r['workers']} workers against 1: {one['wall_s'] / r['wall_s']:.2f}x; each task took "
                         f"{r['task_s_mean'] / one['task_s_mean']:.2f}x as long as on 1 worker, i.e. the workers had "
                         f"about {cores:.1f} free core(s) between them")
    lines.append("")
    return lines


def _sweep_table(sweeps: list[dict[str, Any]]) -> list[str]:
    lines = []
    sbase = sweeps[0]["wall_s"]
    lines.append(f"sweep: {sweeps[0]['flights']} flights (step and gust, 15 s and 25 s)")
    lines.append("| mode | flights per task | tasks | wall (s) | flights/s | speed-up vs in-process | "
                 "cluster start and warm-up (s) | overhead per task (ms) | overhead share |")
    lines.append("|---|---|---|---|---|---|---|---|---|")
    for r in sweeps:
        share = r["overhead_per_task_s"] * r["tasks"] / max(r["workers"], 1) / r["wall_s"]
        lines.append(f"| {r['mode']} | {r['batch']} | {r['tasks']} | {r['wall_s']:.1f} | "
                     f"{r['flights'] / r['wall_s']:.0f} | {sbase / r['wall_s']:.2f}x | {r['startup_s']:.1f} | "
                     f"{1e3 * r['overhead_per_task_s']:.1f} | {100 * share:.0f} % |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recordings", type=int, default=200, help="recordings in the fleet (default 200)")
    ap.add_argument("--duration", type=float, default=150.0, help="seconds per recording (default 150)")
    ap.add_argument("--flights", type=int, default=10_000, help="sweep flights (default 10000)")
    ap.add_argument("--small-batch", type=int, default=10, help="flights per task of the small-batch sweep run")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="LocalCluster sizes (default 1 2)")
    ap.add_argument("--workdir", default=str(ROOT / "out" / "bench_fleet"))
    ap.add_argument("--skip", choices=("fleet", "sweep"), nargs="*", default=[])
    ap.add_argument("--json", help="also write the numbers here")
    ap.add_argument("--table-from", help="print the table of a --json file written before, and stop")
    args = ap.parse_args(argv)
    if args.table_from:
        saved = json.loads(Path(args.table_from).read_text())
        print(table(saved["fleet"], saved["sweep"], saved["meta"]))
        return 0
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    meta: dict[str, Any] = {"cpus": os.cpu_count(), "python": platform.python_version(),
                            "load_before": " ".join(f"{x:.2f}" for x in os.getloadavg()),
                            "duration_s": args.duration, "recordings": args.recordings, "flights": args.flights}
    fleet = fleet_runs(recordings(workdir, args.recordings, args.duration), args.workers, workdir) \
        if "fleet" not in args.skip else []
    sweeps = sweep_runs(sweep_spec(workdir, args.flights), args.workers, args.small_batch) \
        if "sweep" not in args.skip else []
    meta["load_after"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(table(fleet, sweeps, meta))
    if args.json:
        Path(args.json).write_text(json.dumps({"meta": meta, "fleet": fleet, "sweep": sweeps}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
