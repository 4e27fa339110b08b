"""flowhold's benchmarks, all measured in one run, printed as one table (``make bench``).

    .venv/bin/python benchmarks/run.py [--quick] [--skip SECTION ...] [--json OUT] [--workdir DIR]

Sections (each against a baseline measured in the same run):

- ``sim``: simulator speed in simulated seconds per wall second: the fine-step reference
  (RK4 at 1 ms closed by ``CompanionCore``; also ``scenarios.fly`` through MAVLink), the fast
  engine on one 150 s flight, and a batch of 1000 flights of 150 s (``bench_sim``).
  Targets: one flight >= 1000 x real time; the batch in under 60 s.
- ``latency``: the companion's step on UDP loopback, from a flow frame leaving the fake vehicle
  to its SET_ATTITUDE_TARGET arriving, p50 / p99 over 2000 frames at 50 Hz, under the default
  scheduler and under SCHED_FIFO (``bench_latency``). Target: p99 < 2 ms.
- ``reader``: the fair baseline of issue 17 (``bench_fair``): on each recording (the SITL tlogs,
  a generated 60 min closed-loop flight, the synthetic 60 min recording, the SITL DataFlash log,
  a ULog), pymavlink's plain ``recv_match`` loop (DFReader for the .BIN, pyulog for the ULog)
  against ``load_recording`` in process and the whole ``replay`` (CSV, Parquet) and ``info``
  commands, and where the commands' time goes. Targets: read >= 150 x, commands >= 50 x on 60 min.
- ``replay``: ``companion.tools.replay.replay`` (columns) against ``replay_live`` (pymavlink message by
  message through the live core) on a closed-loop recording.
- ``diagnose``: ``companion.diagnose.closed_loop.command`` on closed-loop recordings of 150 s, 10 min and 60 min,
  and the exponent of its cost against the length. Target: no worse than linear.
- ``growth``: pymavlink's loop, read, and the whole replay, info and diagnose commands on
  generated flights of 1 min to 2 h (``bench_fair.growth``).
- ``history``: the earlier baseline (8-12 k msg/s) re-run with its own commit's code here.

Every number goes to ``--json`` (default ``out/bench/results.json``) with the machine, its
versions and its load average sampled every 5 s; ``benchmarks/render_performance.py`` renders
``docs/performance.md`` and its plot from that file alone.

The closed-loop recordings are written once by ``bench_sim.write_flight_tlog`` into
``--workdir`` (default ``out/bench``) and reused. A section whose code is not in the tree (yet)
prints "not available". ``--quick`` shortens everything (a smoke run, not the numbers to quote).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
for p in (str(ROOT), str(HERE)):
    if p not in sys.path:
        sys.path.insert(0, p)

SECTIONS = ("sim", "latency", "reader", "replay", "diagnose", "growth", "history")
RECORDING_VERSION = 1  # bump when write_flight_tlog changes what it writes


@dataclass
class Table:
    """Rows of (section, measurement, result, versus baseline, target/verdict)."""

    rows: list[tuple[str, str, str, str, str]] = field(default_factory=list)
    numbers: dict[str, Any] = field(default_factory=dict)

    def add(self, section: str, what: str, result: str, versus: str = "", target: str = "") -> None:
        self.rows.append((section, what, result, versus, target))
        print(f"  {what}: {result} {versus} {target}".rstrip(), file=sys.stderr, flush=True)

    def render(self) -> str:
        head = ("section", "measurement", "result", "vs baseline", "target")
        widths = [max(len(r[i]) for r in [head, *self.rows]) for i in range(5)]
        line = "  ".join("-" * w for w in widths)
        out = ["  ".join(h.ljust(w) for h, w in zip(head, widths, strict=True)), line]
        last = None
        for r in self.rows:
            cells = list(r)
            if r[0] == last:
                cells[0] = ""
            last = r[0]
            out.append("  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip())
        return "\n".join(out)


def _verdict(ok: bool) -> str:
    return "met" if ok else "NOT MET"


def _fmt_speed(x: float) -> str:
    return f"{x:,.0f} sim-s/s" if x >= 100 else f"{x:,.2f} sim-s/s"


# ---------------------------------------------------------------------------------------------


def section_sim(t: Table, quick: bool) -> None:
    import bench_sim

    dur = 30.0 if quick else 150.0
    n_batch = 100 if quick else 1000
    workers = os.cpu_count() or 1
    ref = bench_sim.measure_reference(10.0 if quick else 30.0)
    t.numbers["sim_reference"] = ref
    t.add("simulator", "reference: RK4 1 ms + CompanionCore (baseline)", _fmt_speed(ref["speed"]), "1 x",
          f"{ref['speed']:.1f} x real time")
    fly = bench_sim.measure_fly(5.0 if quick else 15.0)
    t.numbers["sim_fly"] = fly
    t.add("simulator", "scenarios.fly: the reference through MAVLink", _fmt_speed(fly["speed"]),
          f"{fly['speed'] / ref['speed']:.2f} x")
    single = bench_sim.measure_fast_single(dur)
    t.numbers["sim_fast_single"] = single
    t.add("simulator", f"fast engine, one {dur:g} s flight (array schedules)", _fmt_speed(single["speed"]),
          f"{single['speed'] / ref['speed']:,.0f} x",
          f">= 1000 x real time: {_verdict(single['speed'] >= 1000)} ({single['speed']:,.0f} x, "
          f"{single['wall_s'] * 1e3:.0f} ms)")
    funcs = bench_sim.measure_fast_single(dur, repeats=3, functions=True)
    t.numbers["sim_fast_single_functions"] = funcs
    t.add("simulator", f"fast engine, one {dur:g} s flight (schedules as Python functions)",
          _fmt_speed(funcs["speed"]), f"{funcs['speed'] / ref['speed']:,.0f} x",
          f"{funcs['wall_s'] * 1e3:.0f} ms; the functions run at 7 points per frame")
    interp = bench_sim.measure_fast_interpreted(2.0 if quick else 4.0)
    t.numbers["sim_fast_interpreted"] = interp
    t.add("simulator", "fast engine, frame loop interpreted (no numba)", _fmt_speed(interp["speed"]),
          f"{interp['speed'] / ref['speed']:,.1f} x", f"numba: {single['speed'] / interp['speed']:,.0f} x faster")
    for w in sorted({1, workers}):
        b = bench_sim.measure_fast_batch(n_batch, dur, w)
        t.numbers[f"sim_fast_batch_{w}"] = b
        t.add("simulator", f"fast engine, batch {n_batch} x {dur:g} s, {w} process{'es' if w > 1 else ''}",
              _fmt_speed(b["speed"]), f"{b['speed'] / ref['speed']:,.0f} x",
              f"1000 x 150 s < 60 s: {_verdict(b['wall_s'] * (1000 * 150) / (n_batch * dur) < 60)} "
              f"({b['wall_s']:.1f} s)")
    c = bench_sim.measure_compile()
    t.numbers["sim_first_use"] = c
    t.add("simulator", "fast engine, first use in a fresh process", f"{c['first_flight_s']:.1f} s",
          "", f"import {c['import_s']:.1f} s; compiles once (~30 s) after fastsim.py changes")


def section_latency(t: Table, quick: bool) -> None:
    import bench_latency

    frames = 500 if quick else 2000
    modes = (False, True) if bench_latency.realtime_available() else (False,)
    for target in ("live", "harness"):
        if target == "live" and not _has_module("companion.mavlink.live"):
            t.add("latency", "python -m companion run", "not available")
            continue
        for rt in modes:
            r = bench_latency.measure_latency(target, frames, 50.0, realtime=rt)
            t.numbers[f"latency_{target}_{'fifo' if rt else 'default'}"] = r
            label = ("python -m companion run" if target == "live" else "harness: MessageRouter + outbound")
            t.add("latency", f"{label}, {'SCHED_FIFO' if rt else 'default scheduler'}",
                  f"p50 {r['p50_ms']:.2f} ms, p99 {r['p99_ms']:.2f} ms", f"max {r['max_ms']:.2f} ms",
                  f"p99 < 2 ms: {_verdict(r['p99_ms'] < 2.0)} ({frames} frames, {r['lost']} lost, "
                  f"load avg {r['load_avg_1min']:.1f})")
    p = bench_latency.profile_step(1000 if quick else 3000)
    t.numbers["latency_in_process"] = {k: v for k, v in p.items() if k != "profile"}
    t.add("latency", "in-process cost per frame (4 messages in, 3 out)",
          f"decode {p['parse_us']:.0f} us, step {p['step_us']:.0f} us, encode {p['encode_us']:.0f} us")


def _x(v: float | None) -> str:
    return "-" if v is None else f"{v:,.1f} x" if v < 100 else f"{v:,.0f} x"


def section_reader(t: Table, quick: bool, workdir: Path) -> None:
    """The fair baseline (issue 17): pymavlink's plain loop / pyulog against the reader and the
    whole replay and info commands, on each recording of ``bench_fair.recordings``."""
    import bench_fair

    results = []
    kernels = bench_fair.kernel_build()
    t.numbers["kernels"] = kernels
    t.add("reader", "compiled kernels (companion/native/kernels.c)",
          f"{'loaded' if kernels['available'] else 'NOT AVAILABLE: numpy path'}",
          f"{kernels['compiler_version'] or kernels['compiler']}",
          f"one build {kernels['build_s']:.2f} s" if kernels["build_s"] is not None else "build failed")
    for rec in bench_fair.recordings(workdir, quick):
        is_long = rec.commands and rec.label.startswith("generated")
        r = bench_fair.measure_recording(rec, workdir / "outputs", repeat=1 if quick else 3 if is_long else 2,
                                         paths=is_long)
        results.append(r)
        b, rd, q = r["baseline"], r["read"], r["ratios"]
        base = f"{b['reader']} {b['loop_s']:.2f} s ({b['messages']:,} msgs"
        base += f", {b['msgs_per_s'] / 1e3:,.1f} k/s)" if b.get("msgs_per_s") else ")"
        t.add("reader", f"{rec.label}: baseline", base, "1 x", f"+ {b['open_s']:.2f} s to open (not counted)")
        t.add("reader", f"{rec.label}: read in process", f"{rd['warm_s']:.3f} s warm, {rd['cold_s']:.3f} s first",
              _x(q["read_warm"]), f">= 150 x: {_verdict(q['read_warm'] >= 150)}" if is_long else "")
        if "read_numpy" in r:
            rn = r["read_numpy"]
            t.add("reader", f"{rec.label}: read in process, numpy path (FLOWHOLD_NATIVE=0)",
                  f"{rn['warm_s']:.3f} s warm, {rn['cold_s']:.3f} s first", _x(q["read_numpy_warm"]))
        for key, what in (("replay_csv", "replay --csv, whole command"),
                          ("replay_parquet", "replay --parquet, whole command"), ("info", "info, whole command"),
                          ("replay_csv_one_core", "replay --csv, whole command on one core (taskset)"),
                          ("info_one_core", "info, whole command on one core (taskset)"),
                          ("replay_csv_numpy", "replay --csv, numpy path (FLOWHOLD_NATIVE=0)"),
                          ("info_numpy", "info, numpy path (FLOWHOLD_NATIVE=0)"),
                          ("replay_csv_first_build", "replay --csv, first run (kernels built)")):
            if key in r:
                c = r[key]
                target = f">= 50 x: {_verdict((q[key] or 0) >= 50)}" if is_long and key in ("replay_csv", "info") \
                    else ""
                result = f"{c['wall_s']:.2f} s" if c.get("wall_s") else f"failed: {c.get('error')}"
                if c.get("cpu_s"):
                    result += f" (CPU {c['cpu_s']:.2f} s)"
                if c.get("wall_s") and len(c.get("walls_s", [])) >= 3:
                    result += f", median of {len(c['walls_s'])} {c['median_wall_s']:.2f} s"
                t.add("reader", f"{rec.label}: {what}", result, _x(q.get(key)), target)
    t.numbers["recordings"] = results
    long = next((r for r in bench_fair.recordings(workdir, quick) if r.commands and "generated" in r.label), None)
    if long is not None:
        ph = bench_fair.phases(long.path, workdir / "outputs")
        t.numbers["phases"] = {"label": long.label, **ph}
        t.add("reader", f"{long.label}: where the commands' time goes",
              ", ".join(f"{k.removesuffix('_s')} {v:.2f} s" for k, v in ph.items() if k.endswith("_s")
                        and not k.startswith("load")))


def section_growth(t: Table, quick: bool, workdir: Path, timeout_s: float) -> None:
    """Cost against recording length, 1 min to 2 h (``bench_fair.growth``)."""
    import bench_fair
    import numpy as np

    minutes = (1.0, 5.0) if quick else bench_fair.GROWTH_MINUTES
    rows = bench_fair.growth(workdir, minutes, diagnose_timeout_s=timeout_s)
    t.numbers["growth"] = rows
    for key in ("baseline", "read", "replay_csv", "info", "diagnose"):
        pts = [(r["minutes"], r[key]["loop_s"] if key == "baseline" else r[key]["warm_s"] if key == "read"
                else r[key]["wall_s"]) for r in rows]
        pts = [(m, v) for m, v in pts if v]
        if len(pts) < 2:
            continue
        k = float(np.polyfit(np.log([m for m, _ in pts]), np.log([v for _, v in pts]), 1)[0])
        t.numbers[f"growth_exponent_{key}"] = k
        t.add("growth", f"{key}: {pts[0][0]:g} min -> {pts[-1][0]:g} min", f"{pts[0][1]:.2f} s -> {pts[-1][1]:.2f} s",
              f"cost ~ length^{k:.2f}")


def section_history(t: Table, workdir: Path, quick: bool) -> None:
    """The earlier baseline (8-12 k msg/s), re-run with its own code on this machine."""
    import bench_fair

    h = bench_fair.history(workdir, minutes=10.0 if quick else 60.0)
    t.numbers["history"] = h
    if "error" in h:
        t.add("history", f"commit {bench_fair.HISTORY_COMMIT} re-run", "failed", "", h["error"])
        return
    then = h["then"]
    for key, what, unit in (("pymavlink_msgs_per_s", "pymavlink probe", "msg/s"),
                            ("reader_msgs_per_s", "read_tlog", "msg/s"),
                            ("reference_sim_s_per_s", "RK4 reference (pure Python)", "sim-s/s")):
        t.add("history", f"commit {h['commit']}'s {what}, today", f"{h[key]:,.1f} {unit}",
              f"then {then[key]:,.1f} {unit}", f"{h[key] / then[key]:.1f} x faster today")


def _flight(workdir: Path, duration_s: float) -> Path:
    import bench_sim

    path = workdir / f"flight_{duration_s:g}s_v{RECORDING_VERSION}.tlog"
    if not path.exists():
        tmp = path.with_suffix(".partial")
        r = bench_sim.write_flight_tlog(tmp, duration_s, seed=3)
        tmp.rename(path)
        print(f"  wrote {path} ({r['messages']:,} messages) in {r['build_s']:.0f} s", file=sys.stderr)
    return path


def section_replay(t: Table, quick: bool, workdir: Path) -> None:
    if not _has_module("companion.tools.replay"):
        t.add("replay", "replay vs pymavlink", "not available")
        return
    from companion.config import load_config
    from companion.recordings.load import load_recording
    from companion.step.profiles import Profile
    from companion.tools.replay import replay, replay_live

    cfg = load_config()
    dur = 60.0 if quick else 600.0
    path = _flight(workdir, dur)
    t0 = time.perf_counter()
    res = replay(load_recording(path), cfg, Profile.PAPER)
    t_cols = time.perf_counter() - t0
    t0 = time.perf_counter()
    live = replay_live(path, cfg, Profile.PAPER)
    t_live = time.perf_counter() - t0
    frames = len(live)
    t.numbers["replay"] = {"duration_s": dur, "frames": frames, "replay_s": t_cols, "replay_live_s": t_live}
    del res
    t.add("replay", f"companion replay, {dur / 60:g} min closed-loop flight ({frames:,} frames)",
          f"{t_cols:.2f} s", f"{t_live / t_cols:.0f} x replay_live",
          f"replay_live (pymavlink, message by message) {t_live:.1f} s")


def section_diagnose(t: Table, quick: bool, workdir: Path, timeout_s: float) -> None:
    if not _has_module("companion.diagnose.closed_loop.command"):
        t.add("diagnose", "diagnose vs recording length", "not available")
        return
    lengths = (150.0, 600.0) if quick else (150.0, 600.0, 3600.0)
    probe = ("import json, sys, time\nt0 = time.perf_counter()\n"
             "from companion.diagnose.closed_loop.command import diagnose_recording\nt1 = time.perf_counter()\n"
             "d = diagnose_recording(sys.argv[1])\nt2 = time.perf_counter()\n"
             "print(json.dumps({'import_s': t1 - t0, 'diagnose_s': t2 - t1}))\n")
    times = []
    for length in lengths:
        path = _flight(workdir, length)
        t0 = time.perf_counter()
        try:
            out = subprocess.run([sys.executable, "-c", probe, str(path)], capture_output=True, text=True, cwd=ROOT,
                                 timeout=timeout_s)
        except subprocess.TimeoutExpired:
            t.add("diagnose", f"{length / 60:g} min recording", f"timeout after {timeout_s:.0f} s")
            continue
        wall = time.perf_counter() - t0
        if out.returncode != 0:
            t.add("diagnose", f"{length / 60:g} min recording", "failed", "",
                  (out.stderr.strip().splitlines() or ["?"])[-1][:100])
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        times.append((length, r["diagnose_s"]))
        t.numbers[f"diagnose_{length:g}s"] = {**r, "wall_s": wall}
        t.add("diagnose", f"{length / 60:g} min closed-loop recording", f"{r['diagnose_s']:.1f} s",
              f"{r['diagnose_s'] / (length / 60):.2f} s per recorded min", f"wall {wall:.1f} s with start-up")
    if not quick:
        # issue 12's budget holds whatever the recording: an hour with 8 % of its messages lost
        import bench_diagnose

        path = bench_diagnose.build_lossy(workdir / "lossy_60min.tlog", 3600.0)
        t0 = time.perf_counter()
        out = subprocess.run([sys.executable, "-c", probe, str(path)], capture_output=True, text=True, cwd=ROOT,
                             timeout=timeout_s, check=False)
        wall = time.perf_counter() - t0
        if out.returncode == 0:
            r = json.loads(out.stdout.strip().splitlines()[-1])
            n_msgs, loop_s, _w = bench_diagnose.time_pymavlink(path)
            t.numbers["diagnose_lossy_3600s"] = {**r, "wall_s": wall, "loop_s": loop_s, "messages": n_msgs}
            t.add("diagnose", "60 min, 8 % of messages lost (matrix flight 164)", f"{wall:.1f} s",
                  f"{wall / loop_s:.2f} x pymavlink's loop ({loop_s:.1f} s)",
                  f"< 0.25: {_verdict(wall / loop_s < 0.25)}")
        else:
            t.add("diagnose", "60 min, 8 % of messages lost", "failed", "",
                  (out.stderr.strip().splitlines() or ["?"])[-1][:100])
    if len(times) >= 2:
        import numpy as np

        x = np.log([a for a, _ in times])
        y = np.log([b for _, b in times])
        slope = float(np.polyfit(x, y, 1)[0])
        t.numbers["diagnose_exponent"] = slope
        t.add("diagnose", "cost ~ length^k, k fitted over the lengths", f"k = {slope:.2f}",
              f"{times[-1][1] / times[0][1]:.1f} x time for {times[-1][0] / times[0][0]:.0f} x length",
              f"no worse than linear (k <= 1.1): {_verdict(slope <= 1.1)}")


def _has_module(name: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:
        return False


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="short runs (a smoke test, not the numbers to quote)")
    ap.add_argument("--skip", nargs="*", default=[], choices=SECTIONS, metavar="SECTION",
                    help=f"sections to leave out: {', '.join(SECTIONS)}")
    ap.add_argument("--only", nargs="*", default=None, choices=SECTIONS, metavar="SECTION",
                    help="run only these sections")
    ap.add_argument("--json", default=str(ROOT / "out" / "bench" / "results.json"),
                    help="write every number measured here (default out/bench/results.json); "
                         "benchmarks/render_performance.py turns it into docs/performance.md")
    ap.add_argument("--workdir", default=str(ROOT / "out" / "bench"), help="where the recordings are cached")
    ap.add_argument("--diagnose-timeout", type=float, default=3600.0, help="seconds allowed per diagnose run")
    args = ap.parse_args(argv)
    todo = [s for s in (args.only or SECTIONS) if s not in args.skip]
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    import bench_fair

    bytecode = bench_fair.use_bytecode_cache(workdir / "pycache")
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)  # every section's processes, not only bench_fair's
    os.environ["PYTHONPYCACHEPREFIX"] = bench_fair.CHILD_ENV["PYTHONPYCACHEPREFIX"]
    subprocess.run([sys.executable, "-m", "companion", "info", str(bench_fair.SITL_DIR / "flight_a.tlog.gz")],
                   capture_output=True, cwd=ROOT, env=bench_fair.CHILD_ENV)  # fills the bytecode cache
    table = Table()
    load0 = os.getloadavg()[0]
    started = time.perf_counter()
    started_utc = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    loads: list[tuple[float, float]] = []
    stop = threading.Event()

    def sample_load() -> None:  # the machine is shared: its load is part of every number
        while not stop.is_set():
            loads.append((time.perf_counter() - started, os.getloadavg()[0]))
            stop.wait(5.0)

    threading.Thread(target=sample_load, daemon=True).start()
    runners: dict[str, Callable[[], None]] = {
        "sim": lambda: section_sim(table, args.quick),
        "latency": lambda: section_latency(table, args.quick),
        "reader": lambda: section_reader(table, args.quick, workdir),
        "replay": lambda: section_replay(table, args.quick, workdir),
        "diagnose": lambda: section_diagnose(table, args.quick, workdir, args.diagnose_timeout),
        "growth": lambda: section_growth(table, args.quick, workdir, args.diagnose_timeout),
        "history": lambda: section_history(table, workdir, args.quick),
    }
    for name in todo:
        print(f"[{name}]", file=sys.stderr, flush=True)
        try:
            runners[name]()
        except Exception as exc:  # noqa: BLE001 - one broken section must not lose the others' numbers
            table.add(name, "error", f"{type(exc).__name__}: {exc}"[:120])
    import numpy

    from simvehicle.engines import fastsim

    numba_version = fastsim._numba.__version__ if fastsim.NUMBA else "not used"  # type: ignore[union-attr]
    header = (f"flowhold benchmarks: {os.cpu_count()} cores, load average {load0:.1f} at start and "
              f"{os.getloadavg()[0]:.1f} at end, Python {platform.python_version()}, numpy {numpy.__version__}, "
              f"numba {numba_version}; {time.perf_counter() - started:.0f} s"
              + (" (--quick: not the numbers to quote)" if args.quick else ""))
    stop.set()
    print(header)
    print(table.render())
    if args.json:
        table.numbers["machine"] = _machine(started_utc, time.perf_counter() - started, load0, loads, args.quick, todo)
        table.numbers["machine"]["bytecode"] = bytecode
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"header": header, "rows": table.rows, "numbers": table.numbers},
                                              indent=2, default=float))
    return 0


def _machine(started_utc: str, wall_s: float, load0: float, loads: list[tuple[float, float]], quick: bool,
             sections: list[str]) -> dict[str, Any]:
    """Where and when the run was made: cores, CPU, versions, commit, and the load average
    sampled every 5 s through the run (the machine is shared)."""
    import importlib.metadata as md

    def version(name: str) -> str | None:
        try:
            return md.version(name)
        except md.PackageNotFoundError:
            return None

    cpu = None
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), None)
    except OSError:
        pass
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    values = [v for _, v in loads] or [load0]
    return {"started_utc": started_utc, "wall_s": wall_s, "cores": os.cpu_count(), "cpu": cpu,
            "python": platform.python_version(), "commit": commit, "quick": quick, "sections": sections,
            "versions": {n: version(n) for n in ("numpy", "numba", "pymavlink", "fastcrc", "pyulog", "pyarrow")},
            "load_start": load0, "load_end": os.getloadavg()[0], "load_min": min(values), "load_max": max(values),
            "load_mean": sum(values) / len(values), "load_samples": loads}


if __name__ == "__main__":
    sys.exit(main())
