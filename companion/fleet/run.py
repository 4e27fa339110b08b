"""``python -m companion fleet``: diagnose every recording of a fleet, one task per file, on Dask.

    python -m companion fleet DIR_OR_GLOB... --out OUT [--scheduler tcp://host:8786] [--workers N]
                              [--config F] [--profile P] [--sensor-config MAP] [--in-process]

Recordings: every .tlog, DataFlash .bin, PX4 .ulg and CSV (with ``--sensor-config``) under each
folder, or matched by each glob, each also gzip-compressed (``.gz``); a file named on the command
line is taken whatever its suffix (read as a .tlog). Each is diagnosed as ``python -m companion
diagnose`` does (closed loop, or sensor-only without commands) against one nominal model
(``--config``). Where: a Dask ``LocalCluster`` of ``--workers`` processes (default: all cores), the
cluster at ``--scheduler``, or this process (``--in-process``, and the mode when Dask is not
installed: ``pip install 'flowhold[cluster]'``). The output is the same in every mode:

- ``OUT/reports/<path>.json``: each file's mismatch report (CONVENTIONS.md) with a ``fleet``
  block (vehicle system id, start time, duration, frames used, or the error of a failed file);
- ``OUT/fleet.csv`` and ``OUT/fleet.parquet``: one row per recording and effect (``table``);
- ``OUT/summary.html``: the fleet summary, plots embedded (``summary``).

Resumable: a file whose report is newer than it, made with the same model, profile and column map,
is not diagnosed again. A bad file is one failed row; a worker that dies loses only its task, which
Dask runs once more. The vehicle of a recording is the folder holding it (``--vehicle-from
folder``, a fleet kept as ``logs/<vehicle>/...``) or its MAVLink system id (``sysid``).
"""

from __future__ import annotations

import argparse
import glob
import hashlib
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion.config import load_config
from companion.errors import UsageError, check_output, writing
from companion.fleet.engine import INSTALL_HINT, Engine, TaskLost
from companion.fleet.summary import write_summary
from companion.fleet.table import flag_outliers, have_pyarrow, rows_of, write_csv, write_parquet
from companion.fleet.work import FileResult, Job, diagnose_file, warm_up
from companion.recordings.load import recording_suffix

__all__ = ["FleetRun", "find_recordings", "run_fleet", "run_cli"]

#: the formats the fleet picks up in a folder (looking through a trailing .gz)
SUFFIXES = (".tlog", ".bin", ".ulg", ".csv")
_GLOB_CHARS = set("*?[")


@dataclass
class FleetRun:
    """What a fleet run did: the table rows, and how the work went."""

    rows: list[dict[str, Any]]
    recordings: list[Path]
    diagnosed: int
    skipped: int
    failed: int
    wall_s: float
    engine: str
    dashboard: str | None
    #: seconds each diagnosed file took inside its task (the per-task cost)
    task_s: list[float] = field(default_factory=list)
    outputs: dict[str, Path] = field(default_factory=dict)
    note: str = ""


def find_recordings(inputs: list[str]) -> list[Path]:
    """Every recording under the folders / matched by the globs / named in ``inputs``, sorted,
    without duplicates. UsageError (one line) for an input that names or matches nothing."""
    found: set[Path] = set()
    for item in inputs:
        if any(c in _GLOB_CHARS for c in item):
            matches = [Path(m) for m in glob.glob(item, recursive=True)]
            hits = [m for m in matches if m.is_file() and recording_suffix(m) in SUFFIXES]
            for d in (m for m in matches if m.is_dir()):
                hits += _in_folder(d)
            if not hits:
                raise UsageError(f"{item}: matches no recording ({', '.join(SUFFIXES)}, each also .gz)")
            found.update(hits)
        elif Path(item).is_dir():
            hits = _in_folder(Path(item))
            if not hits:
                raise UsageError(f"{item}: holds no recording ({', '.join(SUFFIXES)}, each also .gz)")
            found.update(hits)
        elif Path(item).exists():
            found.add(Path(item))
        else:
            raise UsageError(f"{item}: no such file or folder")
    return sorted(found)


def _in_folder(d: Path) -> list[Path]:
    return [p for p in d.rglob("*") if p.is_file() and recording_suffix(p) in SUFFIXES]


def _settings_key(job: Job) -> str:
    """What a report depends on besides the file: the bound model, the profile, the column map."""
    h = hashlib.sha256(repr(job.config).encode())
    h.update(repr(job.profile).encode())
    if job.sensor_config:
        h.update(Path(job.sensor_config).read_bytes())
    return h.hexdigest()[:16]


def _report_path(out: Path, rec: Path, root: Path) -> Path:
    try:
        rel = rec.resolve().relative_to(root)
    except ValueError:
        rel = Path(rec.name)
    return out / "reports" / rel.parent / f"{rel.name}.json"


def _fresh(report: Path, rec: Path, key: str) -> bool:
    """Whether ``report`` is newer than ``rec`` and made with the same settings."""
    try:
        if report.stat().st_mtime <= rec.stat().st_mtime:
            return False
        return json.loads(report.read_text()).get("fleet", {}).get("settings") == key
    except (OSError, ValueError):
        return False


def _num(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _report_json(res: FileResult, key: str, rec: Path) -> dict[str, Any]:
    meta = {"path": str(rec), "settings": key, "sysid": res.sysid, "start_unix_s": _num(res.start_unix_s),
            "duration_s": _num(res.duration_s), "frames_used": res.frames_used, "error": res.error,
            "elapsed_s": round(res.elapsed_s, 3)}
    if res.report is None:
        return {"recording": rec.name, "mode": "", "headline": "", "findings": [], "unexplained": [],
                "notes": [], "fleet": meta}
    return {**res.report, "fleet": meta}


def _vehicle(rec: Path, report: dict[str, Any], vehicle_from: str) -> str:
    if vehicle_from == "sysid":
        sysid = report.get("fleet", {}).get("sysid", -1)
        return f"sysid {sysid}" if sysid >= 0 else "unknown"
    return rec.resolve().parent.name


def run_fleet(inputs: list[str], out: str | Path, *, config: str | Path | None = None, profile: str | None = None,
              sensor_config: str | None = None, scheduler: str | None = None, workers: int | None = None,
              in_process: bool = False, vehicle_from: str = "folder", progress: bool | None = None,
              summary: bool = True, say: Callable[[str], None] = lambda _line: None) -> FleetRun:
    """Diagnose the fleet (see the module's docs) and write its outputs into ``out``. ``say``
    gets the lines a user should see while it runs (the dashboard's address)."""
    if vehicle_from not in ("folder", "sysid"):
        raise UsageError(f"--vehicle-from must be folder or sysid, got {vehicle_from!r}")
    recs = find_recordings(inputs)
    engine = Engine(scheduler=scheduler, workers=workers, in_process=in_process, progress=progress)
    outdir = check_output(out, "--out", folder=True)
    cfg = load_config(config)
    if sensor_config is not None and not Path(sensor_config).is_file():
        raise UsageError(f"--sensor-config: not found: {sensor_config}")
    inside = outdir.resolve()
    recs = [p for p in recs if inside not in p.resolve().parents]  # never our own fleet.csv
    if not recs:
        raise UsageError(f"no recording outside --out {outdir}")
    root = Path(os.path.commonpath([str(p.resolve().parent) for p in recs]))
    # absolute paths: a worker on another machine shares the storage, not our working directory
    column_map = str(Path(sensor_config).resolve()) if sensor_config else None
    jobs = [Job(str(p.resolve()), cfg, profile, column_map) for p in recs]
    key = _settings_key(jobs[0])
    reports = [_report_path(outdir, p, root) for p in recs]
    todo = [i for i, (p, r) in enumerate(zip(recs, reports, strict=True)) if not _fresh(r, p, key)]
    t0 = time.perf_counter()
    task_s: list[float] = []
    run = FleetRun([], recs, 0, len(recs) - len(todo), 0, 0.0, "nothing to do", None, note=engine.note)
    if todo:
        with engine:
            run.engine, run.dashboard = engine.description, engine.dashboard
            if engine.dashboard:
                say(f"dashboard: {engine.dashboard}")
            elif engine.dask:
                say(f"dashboard: none ({engine.dashboard_note})")
            engine.on_every_worker(warm_up)
            for k, res in engine.map(diagnose_file, [jobs[i] for i in todo], desc="fleet", unit="file",
                                     names=[f"diagnose-{recs[i].name}" for i in todo]):
                i = todo[k]
                if isinstance(res, TaskLost):
                    res = FileResult(path=str(recs[i]), report=None, error=f"not diagnosed: {res}")
                else:
                    task_s.append(res.elapsed_s)
                reports[i].parent.mkdir(parents=True, exist_ok=True)
                with writing("--out", reports[i]):
                    reports[i].write_text(json.dumps(_report_json(res, key, recs[i]), indent=2, allow_nan=False)
                                          + "\n")
                run.diagnosed += 1
    run.wall_s = time.perf_counter() - t0
    run.task_s = task_s
    rows: list[dict[str, Any]] = []
    for p, r in zip(recs, reports, strict=True):
        rep = json.loads(r.read_text())
        rows += rows_of(rep, recording=str(p), vehicle=_vehicle(p, rep, vehicle_from),
                        report_path=str(r.relative_to(outdir)))
    flag_outliers(rows)
    run.rows = rows
    run.failed = len({r["recording"] for r in rows if r["status"] != "ok"})
    run.outputs["csv"] = outdir / "fleet.csv"
    with writing("--out", run.outputs["csv"]):
        write_csv(rows, run.outputs["csv"])
    if have_pyarrow():
        run.outputs["parquet"] = outdir / "fleet.parquet"
        with writing("--out", run.outputs["parquet"]):
            write_parquet(rows, run.outputs["parquet"])
    else:
        run.note = (run.note + "; " if run.note else "") + f"fleet.parquet not written: pyarrow is not installed " \
                                                           f"({INSTALL_HINT})"
    if summary:
        run.outputs["summary"] = outdir / "summary.html"
        note = (f"{run.diagnosed} diagnosed ({run.engine}) in {run.wall_s:.1f} s, {run.skipped} skipped "
                f"(reports newer than their files); model {config or 'configs/paper.toml'}, "
                f"profile {profile or 'detected per recording'}.")
        with writing("--out", run.outputs["summary"]):
            write_summary(rows, run.outputs["summary"], title=f"Fleet summary: {len(recs)} recordings", run_note=note)
    return run


def run_cli(args: argparse.Namespace) -> int:
    """Entry point of ``python -m companion fleet`` (arguments declared in companion/cli.py)."""
    run = run_fleet(args.inputs, args.out, config=args.config, profile=args.profile,
                    sensor_config=args.sensor_config, scheduler=args.scheduler, workers=args.workers,
                    in_process=args.in_process, vehicle_from=args.vehicle_from,
                    say=lambda line: print(line, flush=True))
    if run.note:
        print(f"note: {run.note}")
    n_rec = len(run.recordings)
    print(f"fleet: {n_rec} recording(s): {run.diagnosed} diagnosed, {run.skipped} skipped (reports newer than "
          f"their files), {run.failed} failed; {run.engine}, {run.wall_s:.1f} s")
    flagged = [r for r in run.rows if r["outlier"]]
    for r in flagged:
        print(f"outlier: {r['vehicle']} {Path(r['recording']).name} {r['effect']}: {r['outlier_note']}")
    for label, p in run.outputs.items():
        print(f"{label}: {p}")
    return 0
