"""Benchmark: the project's readers and commands against a plain pymavlink / pyulog read, on the
same files, in the same run (issue 17).

    .venv/bin/python benchmarks/bench_fair.py [--workdir out/bench] [--json OUT] [--quick]

The baseline is what a user would write: ``mavutil.mavlink_connection(path, dialect="ardupilotmega")``
and a ``recv_match()`` loop to the end (a .tlog: pymavlink's ``mavmmaplog``; a DataFlash .BIN:
``DFReader_binary``), and for a ULog ``pyulog.ULog(path)``. Each baseline runs in a fresh
interpreter; its loop time (``loop_s``, opening excluded: the stricter ratio) and its opening
(``open_s``: mavmmaplog indexes the file first) are kept apart.

Against it, each in a fresh interpreter too:

- ``read``: ``companion.recordings.load.load_recording`` (``read_tlog`` for a .tlog), the first read
  (``cold_s``) and the best of three more (``warm_s``), with the imports timed apart;
- ``replay``: the whole command ``python -m companion replay REC --csv OUT`` (start-up, reading,
  the steps, the CSV) and with ``--parquet OUT`` instead, best of ``repeat`` wall times;
- ``info``: the whole command ``python -m companion info REC``;
- ``diagnose``: the whole command ``python -m companion diagnose REC --json OUT`` (growth only).

``recordings(workdir)`` lists the files (the SITL flights from data/, generated closed-loop
flights written by ``bench_sim.write_flight_tlog``, the synthetic recording of
``bench_reader.build_recording``, the SITL DataFlash log, a long ULog built by the importer test
fixtures' writer); ``measure_recording`` measures one; ``growth`` times read, replay, info and
diagnose over generated flights from 1 minute to 2 hours; ``history`` re-runs the code and probe of
the README's earlier benchmark (commit ``HISTORY_COMMIT``) on today's machine, to tell a change of
method from a change of machine. Each result carries the load average before and after it.
"""

from __future__ import annotations

import argparse
import dataclasses
import gzip
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
for _p in (str(ROOT), str(HERE)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

SITL_DIR = ROOT / "data" / "sitl" / "ardupilot"
FIXTURES = ROOT / "tests" / "data" / "importers"
#: the commit whose README table quoted pymavlink at 11.9 k msg/s (benchmarks/run.py, idle machine)
HISTORY_COMMIT = "aaaf2e6"
#: lengths (min) of the cost-growth curve
GROWTH_MINUTES = (1.0, 5.0, 15.0, 30.0, 60.0, 120.0)
FLIGHT_VERSION = 1  # as run.py's RECORDING_VERSION: the cached flights' names carry it


@dataclasses.dataclass(frozen=True)
class Recording:
    """One benchmark file: ``kind`` "tlog", "dataflash" or "ulog"; ``commands``: whether the
    whole replay/info commands are timed on it."""

    label: str
    path: Path
    kind: str
    commands: bool = True


def load_avg() -> float:
    return os.getloadavg()[0]


#: the environment of every process the benchmark starts (``use_bytecode_cache``)
CHILD_ENV: dict[str, str] = dict(os.environ)


def use_bytecode_cache(folder: Path) -> dict[str, Any]:
    """Time the child processes with Python's bytecode cache in use, as a user's second run of a
    command has it: the cache kept in ``folder`` (``PYTHONPYCACHEPREFIX``, nothing written into
    the checkout), and ``PYTHONDONTWRITEBYTECODE`` left out should the environment set it (then
    every run would compile the project's sources again). Returns what was changed."""
    had = CHILD_ENV.pop("PYTHONDONTWRITEBYTECODE", None)
    CHILD_ENV["PYTHONPYCACHEPREFIX"] = str(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return {"pycache_prefix": str(folder), "environment_had_dont_write_bytecode": had is not None}


def _env(extra: dict[str, str] | None) -> dict[str, str]:
    env = {**CHILD_ENV, **(extra or {})}
    return {k: v for k, v in env.items() if v is not None}


def _run_json(code: str, *args: str, timeout_s: float = 3600.0, env: dict[str, str] | None = None) -> dict[str, Any]:
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=ROOT,
                         timeout=timeout_s, env=_env(env))
    if out.returncode != 0:
        raise RuntimeError((out.stderr.strip().splitlines() or ["?"])[-1][:200])
    return json.loads(out.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------------------------------------
# The baselines

_PYMAVLINK = """
import json, sys, time
t0 = time.perf_counter()
from pymavlink import mavutil
t1 = time.perf_counter()
conn = mavutil.mavlink_connection(sys.argv[1], dialect="ardupilotmega")
t2 = time.perf_counter()
c2 = time.process_time()
n = 0
while True:
    m = conn.recv_match()
    if m is None:
        break
    n += 1
t3 = time.perf_counter()
c3 = time.process_time()
print(json.dumps({"import_s": t1 - t0, "open_s": t2 - t1, "loop_s": t3 - t2, "loop_cpu_s": c3 - c2, "messages": n,
                  "reader": type(conn).__name__}))
"""

_PYULOG = """
import json, sys, time
t0 = time.perf_counter()
from pyulog import ULog
t1 = time.perf_counter()
c1 = time.process_time()
u = ULog(sys.argv[1])
t2 = time.perf_counter()
c2 = time.process_time()
n = sum(len(d.data["timestamp"]) for d in u.data_list)
print(json.dumps({"import_s": t1 - t0, "open_s": 0.0, "loop_s": t2 - t1, "loop_cpu_s": c2 - c1, "messages": n,
                  "reader": "pyulog.ULog"}))
"""


def baseline(rec: Recording, variant: str = "plain", repeat: int = 1) -> dict[str, Any]:
    """The plain third-party read of ``rec``: pymavlink's loop (tlog, DataFlash) or pyulog, the
    best of ``repeat`` fresh interpreters (as the commands it is compared with).
    ``variant`` (pymavlink only): "mavlink20" sets MAVLINK20=1 first; "no-fastcrc" hides the
    fastcrc package, so pymavlink checks CRCs in Python (as without that dependency)."""
    runs = [_baseline_once(rec, variant) for _ in range(max(1, repeat))]
    best = min(runs, key=lambda r: r["loop_s"])
    best["loops_s"] = [r["loop_s"] for r in runs]
    best["load_before"], best["load_after"] = runs[0]["load_before"], runs[-1]["load_after"]
    return best


def _baseline_once(rec: Recording, variant: str) -> dict[str, Any]:
    la = load_avg()
    code = _PYULOG if rec.kind == "ulog" else _PYMAVLINK
    if variant == "mavlink20":
        code = "import os\nos.environ['MAVLINK20'] = '1'\n" + code
    elif variant == "no-fastcrc":
        code = "import sys\nsys.modules['fastcrc'] = None\n" + code
    r = _run_json(code, str(rec.path))
    r["total_s"] = r["open_s"] + r["loop_s"]
    r["msgs_per_s"] = r["messages"] / r["loop_s"] if r["loop_s"] > 0 else None
    r["load_before"], r["load_after"] = la, load_avg()
    return r


# ---------------------------------------------------------------------------------------------
# Ours

_READ = """
import json, sys, time
t0 = time.perf_counter()
from companion.recordings.load import load_recording
import companion.recordings.tlog_reader
t1 = time.perf_counter()
runs, cpus = [], []
for _ in range(int(sys.argv[2])):
    t = time.perf_counter()
    c = time.process_time()
    rec = load_recording(sys.argv[1])
    runs.append(time.perf_counter() - t)
    cpus.append(time.process_time() - c)
    n, skipped = rec.n_messages, rec.skipped_bytes
    del rec
print(json.dumps({"import_s": t1 - t0, "cold_s": runs[0], "warm_s": min(runs[1:] or runs), "cold_cpu_s": cpus[0],
                  "warm_cpu_s": min(cpus[1:] or cpus), "messages": n, "skipped_bytes": skipped}))
"""


def read(rec: Recording, repeat: int = 4, env: dict[str, str] | None = None) -> dict[str, Any]:
    """``load_recording`` in a fresh interpreter: the first read and the best of the others
    (wall and CPU time). ``env``: extra environment (``FLOWHOLD_NATIVE=0``: the numpy path)."""
    la = load_avg()
    r = _run_json(_READ, str(rec.path), str(repeat), env=env)
    r["load_before"], r["load_after"] = la, load_avg()
    return r


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def one_cpu() -> set[int]:
    """The first CPU this process may run on, as a set (for ``command``'s ``cpus``)."""
    return {min(os.sched_getaffinity(0))}


def command(args: list[str], repeat: int = 2, timeout_s: float = 3600.0, env: dict[str, str] | None = None,
            cpus: set[int] | None = None) -> dict[str, Any]:
    """Wall time of ``python -m companion ARGS`` as a user runs it (best of ``repeat``; also the
    median), the CPU time (user + system) of the best run, and the exit code (a failure is kept
    with its last line of stderr). ``env``: extra environment for the command; ``cpus``: the CPUs
    it may run on (``taskset``; default: this process's)."""
    la = load_avg()
    walls, cpus_s = [], []
    pin = None if cpus is None else (lambda: os.sched_setaffinity(0, cpus))
    for _ in range(repeat):
        t = time.perf_counter()
        c = _children_cpu_s()
        out = subprocess.run([sys.executable, "-m", "companion", *args], capture_output=True, text=True, cwd=ROOT,
                             timeout=timeout_s, env=_env(env), preexec_fn=pin)
        walls.append(time.perf_counter() - t)
        cpus_s.append(_children_cpu_s() - c)
        if out.returncode != 0:
            return {"wall_s": None, "exit_code": out.returncode,
                    "error": (out.stderr.strip().splitlines() or ["?"])[-1][:200], "load_before": la,
                    "load_after": load_avg()}
    best = min(range(len(walls)), key=walls.__getitem__)
    return {"wall_s": walls[best], "cpu_s": cpus_s[best], "median_wall_s": statistics.median(walls),
            "walls_s": walls, "cpus_s": cpus_s, "exit_code": 0, "cpus": sorted(cpus) if cpus else None,
            "load_before": la, "load_after": load_avg()}


_PHASES = """
import json, os, resource, sys, time
from companion.cli import _batch_process
_batch_process()  # as the replay and info commands set up their process (one BLAS thread, memory kept)
t0 = time.perf_counter()
import numpy
t1 = time.perf_counter()
from companion import native
from companion.config import load_config
from companion.tools.csv_format import iter_rows
from companion.tools.info import format_summary, summarise
from companion.step.profiles import Profile, detect_profile
from companion.recordings.load import load_recording
from companion.tools.replay import REPLAY_FIELDS, _csv_formats, replay, write_csv, write_parquet
t2 = time.perf_counter()
cfg = load_config()
rec = load_recording(sys.argv[1], fields=REPLAY_FIELDS)  # as replay's run_cli reads it
t3 = time.perf_counter()
rss_read = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
profile = Profile(detect_profile(rec)[0])
res = replay(rec, cfg, profile)
t4 = time.perf_counter()
write_csv(res, sys.argv[2])
t5 = time.perf_counter()
rss_csv = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
names, fmts = _csv_formats(res)
cols = [res.columns[c] for c in names]
t5a = time.perf_counter()
with open(sys.argv[2], "wb") as fh:  # the same text, formatted and written by this thread alone
    fh.write((",".join(names) + "\\n").encode())
    for part in iter_rows(cols, fmts, 16_384, threads=1):
        fh.write(part)
t5b = time.perf_counter()
write_parquet(res, sys.argv[3])
t6 = time.perf_counter()
text = format_summary(summarise(rec))
t7 = time.perf_counter()
from companion.tools.csv_format import format_rows, format_rows_reference
t8 = time.perf_counter()
fast = format_rows(cols, fmts)
t9 = time.perf_counter()
os.environ["FLOWHOLD_NATIVE"] = "0"
vectorised = format_rows(cols, fmts)
del os.environ["FLOWHOLD_NATIVE"]
t10 = time.perf_counter()
ref = format_rows_reference(cols, fmts)
t11 = time.perf_counter()
assert fast == ref == vectorised
print(json.dumps({"numpy_import_s": t1 - t0, "other_imports_s": t2 - t1, "read_s": t3 - t2, "replay_s": t4 - t3,
                  "csv_s": t5 - t4, "csv_one_thread_s": t5b - t5a, "parquet_s": t6 - t5b, "info_summary_s": t7 - t6,
                  "frames": len(res), "csv_values": len(res) * len(names), "csv_bytes": len(ref),
                  "format_native_s": t9 - t8, "format_numpy_s": t10 - t9, "format_python_s": t11 - t10,
                  "native": native.kernels() is not None, "threads": native.threads(),
                  "max_rss_after_read_mb": rss_read, "max_rss_after_csv_mb": rss_csv}))
"""


def phases(path: Path, out_dir: Path) -> dict[str, Any]:
    """Where the whole replay and info commands spend their time on ``path``, phase by phase, in
    one fresh interpreter (the interpreter's own start-up is ``python_startup_s``)."""
    la = load_avg()
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", "pass"], check=True, env=_env(None))
    startup = time.perf_counter() - t
    r = _run_json(_PHASES, str(path), str(out_dir / "phases.csv"), str(out_dir / "phases.parquet"))
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import numba"], check=True, env=_env(None))
    numba_s = time.perf_counter() - t - startup
    r.update({"python_startup_s": startup, "numba_import_only_s": numba_s, **numba_first_call(),
              "load_before": la, "load_after": load_avg()})
    return r


_NUMBA_PROBE = """
import json, sys, time
sys.path.insert(0, sys.argv[1])
t0 = time.perf_counter()
import numpy as np
t1 = time.perf_counter()
import numba
t2 = time.perf_counter()
import flowhold_numba_probe as probe
probe.total(np.arange(10.0))
t3 = time.perf_counter()
print(json.dumps({"numpy_s": t1 - t0, "numba_s": t2 - t1, "first_cached_call_s": t3 - t2}))
"""


def numba_first_call() -> dict[str, Any]:
    """What numba costs a fresh process before it computes anything: ``import numba`` after
    numpy, and the first call of a function already compiled into numba's on-disk cache
    (``cache=True``; compiled by a first run here, then timed in a second)."""
    tmp = Path(tempfile.mkdtemp(prefix="flowhold-numba-"))
    try:
        (tmp / "flowhold_numba_probe.py").write_text(
            "import numba\n\n\n@numba.njit(cache=True)\ndef total(a):\n    s = 0.0\n"
            "    for x in a:\n        s += x\n    return s\n")
        _run_json(_NUMBA_PROBE, str(tmp))  # compiles into the cache
        r = _run_json(_NUMBA_PROBE, str(tmp))
        return {"numba_import_after_numpy_s": r["numba_s"], "numba_first_cached_call_s": r["first_cached_call_s"]}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def kernel_build() -> dict[str, Any]:
    """The compiled kernels: whether they load here, the compiler, and the time one build takes
    (what the first command after installing or changing kernels.c pays once)."""
    from companion import native

    cc = native._compiler()
    try:
        version = subprocess.run([*cc, "--version"], capture_output=True, text=True, timeout=30).stdout
        version = version.splitlines()[0] if version else None
    except (OSError, subprocess.SubprocessError):
        version = None
    tmp = Path(tempfile.mkdtemp(prefix="flowhold-kernels-"))
    try:
        t = time.perf_counter()
        native._build(tmp / "k.so")
        build_s = time.perf_counter() - t
    except (OSError, subprocess.SubprocessError):
        build_s = None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"available": native.kernels() is not None, "compiler": " ".join(cc), "compiler_version": version,
            "build_s": build_s}


NUMPY_PATH = {"FLOWHOLD_NATIVE": "0"}


def measure_recording(rec: Recording, out_dir: Path, repeat: int = 2, paths: bool = False) -> dict[str, Any]:
    """Baseline, read, and (``rec.commands``) the whole replay (CSV, Parquet) and info commands.
    ``paths``: also the numpy path (``FLOWHOLD_NATIVE=0``: read, replay, info) and the first
    replay after a fresh install (an empty kernel cache: the build included)."""
    res: dict[str, Any] = {"label": rec.label, "file": rec.path.name, "kind": rec.kind,
                           "bytes": rec.path.stat().st_size}
    res["baseline"] = baseline(rec, repeat=repeat)
    res["read"] = read(rec)
    if paths:
        res["read_numpy"] = read(rec, env=NUMPY_PATH)
    if rec.commands:
        csv = out_dir / f"{rec.path.stem}.csv"
        res["replay_csv"] = command(["replay", str(rec.path), "--csv", str(csv)], repeat)
        res["replay_csv"]["csv_bytes"] = csv.stat().st_size if csv.exists() else None
        parquet = out_dir / f"{rec.path.stem}.parquet"
        res["replay_parquet"] = command(["replay", str(rec.path), "--parquet", str(parquet)], repeat)
        res["info"] = command(["info", str(rec.path)], repeat)
        if paths:
            one = one_cpu()
            res["replay_csv_one_core"] = command(["replay", str(rec.path), "--csv", str(csv)], repeat, cpus=one)
            res["info_one_core"] = command(["info", str(rec.path)], repeat, cpus=one)
            csv_np = out_dir / f"{rec.path.stem}.numpy.csv"
            res["replay_csv_numpy"] = command(["replay", str(rec.path), "--csv", str(csv_np)], repeat, env=NUMPY_PATH)
            res["replay_csv_numpy"]["same_bytes"] = csv.read_bytes() == csv_np.read_bytes()
            res["info_numpy"] = command(["info", str(rec.path)], repeat, env=NUMPY_PATH)
            # every source compiled again in each run, as with PYTHONDONTWRITEBYTECODE=1 (this machine's default)
            res["replay_csv_no_bytecode_cache"] = command(["replay", str(rec.path), "--csv", str(csv)], repeat,
                                                          env={"PYTHONDONTWRITEBYTECODE": "1",
                                                               "PYTHONPYCACHEPREFIX": str(out_dir / "no-such-cache")})
            cache = Path(tempfile.mkdtemp(prefix="flowhold-cache-"))
            try:
                res["replay_csv_first_build"] = command(["replay", str(rec.path), "--csv", str(csv)], 1,
                                                        env={"FLOWHOLD_CACHE_DIR": str(cache)})
            finally:
                shutil.rmtree(cache, ignore_errors=True)
    base = res["baseline"]["loop_s"]
    res["ratios"] = {k: (base / v["wall_s"] if v.get("wall_s") else None)
                     for k, v in res.items() if isinstance(v, dict) and "wall_s" in v}
    # medians: pymavlink's median loop against each command's median run
    base_median = statistics.median(res["baseline"]["loops_s"])
    res["ratios_median"] = {k: base_median / v["median_wall_s"] for k, v in res.items()
                            if isinstance(v, dict) and v.get("median_wall_s")}
    res["ratios"]["read_warm"] = base / res["read"]["warm_s"]
    res["ratios"]["read_cold"] = base / res["read"]["cold_s"]
    if "read_numpy" in res:
        res["ratios"]["read_numpy_warm"] = base / res["read_numpy"]["warm_s"]
        res["ratios"]["read_numpy_cold"] = base / res["read_numpy"]["cold_s"]
    # the same ratios in CPU time (user + system): what the load of other jobs on the machine leaves out
    base_cpu = res["baseline"].get("loop_cpu_s")
    if base_cpu:
        res["ratios_cpu"] = {k: (base_cpu / v["cpu_s"] if v.get("cpu_s") else None)
                             for k, v in res.items() if isinstance(v, dict) and "cpu_s" in v}
        res["ratios_cpu"]["read_warm"] = base_cpu / res["read"]["warm_cpu_s"]
        res["ratios_cpu"]["read_cold"] = base_cpu / res["read"]["cold_cpu_s"]
    return res


# ---------------------------------------------------------------------------------------------
# The files


def _gunzip(src: Path, dst: Path) -> Path:
    if not dst.exists():
        tmp = dst.with_suffix(dst.suffix + ".partial")
        tmp.write_bytes(gzip.decompress(src.read_bytes()))
        tmp.rename(dst)
    return dst


def flight(workdir: Path, duration_s: float) -> Path:
    """The generated closed-loop flight of ``duration_s`` (``bench_sim.write_flight_tlog``,
    seed 3; cached under the name run.py uses)."""
    import bench_sim

    path = workdir / f"flight_{duration_s:g}s_v{FLIGHT_VERSION}.tlog"
    if not path.exists():
        tmp = path.with_suffix(".partial")
        bench_sim.write_flight_tlog(tmp, duration_s, seed=3)
        tmp.rename(path)
    return path


def long_ulog(workdir: Path, minutes: float) -> Path:
    """A PX4-like ULog of ``minutes`` (the importer fixtures' writer, tests/data/importers,
    with its planted motion held to the end)."""
    path = workdir / f"px4_flow_{minutes:g}min.ulg"
    if path.exists():
        return path
    sys.path.insert(0, str(FIXTURES))
    import make_fixtures as mf

    t = mf.ULOG_TRUTH
    n = int(minutes * 60 * 1e6 / t.frame_us)
    end = t.t0_us + (n + 50) * t.frame_us
    segs = tuple(dataclasses.replace(s, t_end_us=end) if i == len(t.segments) - 1 else s
                 for i, s in enumerate(t.segments))
    tmp = path.with_suffix(".partial")
    tmp.write_bytes(mf.ulog_bytes(dataclasses.replace(t, n_frames=n, segments=segs)))
    tmp.rename(path)
    return path


def recordings(workdir: Path, quick: bool = False) -> list[Recording]:
    """The benchmark's files (decompressed or generated into ``workdir`` once)."""
    import bench_reader

    workdir.mkdir(parents=True, exist_ok=True)
    def sitl(name: str) -> Path:
        return _gunzip(SITL_DIR / f"{name}.gz", workdir / name)

    recs = [Recording("ArduCopter SITL flight_a (2.9 min)", sitl("flight_a.tlog"), "tlog"),
            Recording("ArduCopter SITL flight_c0, companion link", sitl("flight_c0_companion.tlog"), "tlog")]
    minutes = 10.0 if quick else 60.0
    recs.append(Recording(f"generated closed-loop flight, {minutes:g} min", flight(workdir, minutes * 60), "tlog"))
    syn = workdir / f"synthetic_{minutes:g}min.tlog"
    if not syn.exists():
        bench_reader.build_recording(syn, minutes)
    recs.append(Recording(f"synthetic streams, {minutes:g} min (the earlier reader benchmark's)", syn, "tlog",
                          commands=False))
    recs.append(Recording("ArduCopter SITL flight_c0 DataFlash .BIN", sitl("flight_c0.BIN"), "dataflash"))
    recs.append(Recording(f"PX4-like ULog, {2 if quick else 10} min", long_ulog(workdir, 2 if quick else 10), "ulog"))
    return recs


# ---------------------------------------------------------------------------------------------
# Cost growth


def growth(workdir: Path, minutes: tuple[float, ...] = GROWTH_MINUTES, diagnose_timeout_s: float = 1800.0
           ) -> list[dict[str, Any]]:
    """Time against recording length: pymavlink's loop, read (in process), and the whole replay,
    info and diagnose commands, on generated closed-loop flights."""
    out = []
    for m in minutes:
        path = flight(workdir, m * 60)
        rec = Recording(f"{m:g} min", path, "tlog")
        row: dict[str, Any] = {"minutes": m, "bytes": path.stat().st_size}
        row["baseline"] = baseline(rec)
        row["read"] = read(rec, repeat=3)
        row["replay_csv"] = command(["replay", str(path), "--csv", str(workdir / "growth.csv")], repeat=1)
        row["info"] = command(["info", str(path)], repeat=1)  # each once, as the baseline beside them
        row["diagnose"] = command(["diagnose", str(path), "--json", str(workdir / "growth_diagnose.json")], repeat=1,
                                  timeout_s=diagnose_timeout_s)
        print(f"  growth {m:g} min: pymavlink {row['baseline']['loop_s']:.1f} s, read {row['read']['warm_s']:.2f} s, "
              f"replay {row['replay_csv']['wall_s']}, info {row['info']['wall_s']}, "
              f"diagnose {row['diagnose']['wall_s']}", file=sys.stderr, flush=True)
        out.append(row)
    return out


# ---------------------------------------------------------------------------------------------
# The earlier baseline, re-run


def _quoted_then() -> dict[str, Any]:
    """What the README of ``HISTORY_COMMIT`` printed (its benchmark table, read from git):
    the reader's and pymavlink's msg/s on the synthetic 60 min, and the RK4 reference's speed."""
    import re

    text = subprocess.run(["git", "show", f"{HISTORY_COMMIT}:README.md"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout
    num = r"([\d,]+(?:\.\d+)?)"
    reader = re.search(r"^reader .*?" + num + r" msg/s .*?pymavlink " + num + " msg/s", text, re.M)
    ref = re.search(r"^simulator +reference: RK4.*? " + num + " sim-s/s", text, re.M)
    load = re.search(r"load average ([\d.]+) at start and ([\d.]+) at end", text)
    if not (reader and ref):
        return {}

    def f(m: re.Match[str], i: int) -> float:
        return float(m.group(i).replace(",", ""))

    return {"reader_msgs_per_s": f(reader, 1), "pymavlink_msgs_per_s": f(reader, 2),
            "speedup": f(reader, 1) / f(reader, 2), "reference_sim_s_per_s": f(ref, 1),
            "load": [float(load.group(1)), float(load.group(2))] if load else None}


def history(workdir: Path, minutes: float = 60.0) -> dict[str, Any]:
    """The README's earlier reader benchmark (commit ``HISTORY_COMMIT``: its reader, its pymavlink
    probe, its synthetic recording, its RK4 reference) run again here, beside today's numbers it
    quoted. Tells a change of method from a change of machine."""
    import bench_reader

    syn = workdir / f"synthetic_{minutes:g}min.tlog"
    if not syn.exists():
        bench_reader.build_recording(syn, minutes)
    tmp = Path(tempfile.mkdtemp(prefix="flowhold-history-"))
    try:
        arch = tmp / "old.tar"
        with open(arch, "wb") as fh:
            subprocess.run(["git", "archive", HISTORY_COMMIT, "companion", "benchmarks", "simvehicle", "configs"],
                           cwd=ROOT, stdout=fh, check=True)
        with tarfile.open(arch) as tf:
            tf.extractall(tmp / "old", filter="data")
        code = ("import json, sys; sys.path[:0] = ['benchmarks', '.']\n"
                "import bench_reader, bench_sim\n"
                "m = bench_reader.measure_reader(sys.argv[1], pymavlink_sample=0)\n"
                "r = bench_sim.measure_reference(10.0)\n"
                "print(json.dumps({'reader_msgs_per_s': m['reader_msgs_per_s'], "
                "'pymavlink_msgs_per_s': m['pymavlink_msgs_per_s'], 'speedup': m['speedup'], "
                "'messages': m['messages'], 'reference_sim_s_per_s': r['speed']}))\n")
        la = load_avg()
        out = subprocess.run([sys.executable, "-c", code, str(syn)], capture_output=True, text=True, cwd=tmp / "old",
                             timeout=1800)
        if out.returncode != 0:
            return {"error": (out.stderr.strip().splitlines() or ["?"])[-1][:200]}
        r = json.loads(out.stdout.strip().splitlines()[-1])
        r.update({"commit": HISTORY_COMMIT, "minutes": minutes, "load_before": la, "load_after": load_avg(),
                  "then": _quoted_then()})
        # what else could make pymavlink slower: MAVLINK20, or pymavlink without fastcrc (pure-Python CRC)
        sitl = Recording("flight_a", _gunzip(SITL_DIR / "flight_a.tlog.gz", workdir / "flight_a.tlog"), "tlog")
        r["variants"] = {v: baseline(sitl, v) for v in ("plain", "mavlink20", "no-fastcrc")}
        return r
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workdir", default=str(ROOT / "out" / "bench"))
    ap.add_argument("--json", help="write every number here")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    workdir = Path(args.workdir)
    out_dir = workdir / "outputs"
    out_dir.mkdir(parents=True, exist_ok=True)
    use_bytecode_cache(workdir / "pycache")
    results = [measure_recording(r, out_dir) for r in recordings(workdir, args.quick)]
    for r in results:
        print(r["label"], {k: round(v, 1) for k, v in r["ratios"].items() if v})
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
