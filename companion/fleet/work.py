"""One fleet task: diagnose one recording, on a Dask worker or in this process.

``diagnose_file(job)`` never raises for a bad recording: an unreadable, damaged beyond use or
empty file comes back as ``FileResult.error`` (one line), so the fleet table gets one failed row
for it. The report is returned to the caller (who writes it), so workers need read access to the
recordings only.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion.config import Config
from companion.diagnose.closed_loop.channels import has_commands
from companion.diagnose.closed_loop.diagnosis import diagnose
from companion.diagnose.sensor.api import run_sensor_diagnosis
from companion.errors import FlowholdError, RecordingError
from companion.recordings.columnar import vehicle_sysid
from companion.recordings.load import Recording, load_recording, recording_suffix

#: log times above this (2000-01-01) are UNIX times; below it a reader's boot time
UNIX_2000_S = 946_684_800.0
_FLOW = ("OPTICAL_FLOW", "OPTICAL_FLOW_RAD")


@dataclass(frozen=True)
class Job:
    """What a worker needs: the recording's path (readable from the worker), the nominal model
    (shipped as an object: no config file needed on the worker), the profile and the column map
    of the CSV recordings (other formats ignore it)."""

    path: str
    config: Config
    profile: str | None = None
    sensor_config: str | None = None


@dataclass
class FileResult:
    """A diagnosed (or failed) recording: the mismatch report as JSON (``None`` if it failed),
    what the table needs beyond it, and the one-line error of a failure."""

    path: str
    report: dict[str, Any] | None
    error: str | None = None
    sysid: int = -1
    start_unix_s: float = math.nan
    duration_s: float = math.nan
    frames_used: int = 0
    elapsed_s: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)


def warm_up() -> None:
    """Nothing to do: importing this module (which a worker does to run it) loads the diagnosis."""


def _sysid(rec: Recording) -> int:
    """The vehicle's system id (``columnar.vehicle_sysid``, replay's and diagnose's rule); -1 without flow."""
    for name in _FLOW:
        if name in rec:
            return vehicle_sysid(rec.tables[name])
    return -1


def _diagnose(rec: Recording, job: Job, sensor_only: bool) -> tuple[dict[str, Any], int, float]:
    """The report (JSON), the frames used and the duration (s) of a loaded recording (a CSV read
    through a column map is ``sensor_only``, as ``diagnose --sensor-config`` takes it)."""
    if not sensor_only and has_commands(rec):
        diag = diagnose(rec, job.config, profile=job.profile)
        return diag.report.to_json(), int(diag.data.n), float(diag.data.duration_s)
    if not any(n in rec for n in _FLOW):
        raise RecordingError(f"{Path(rec.path).name}: neither a commanded attitude (SET_ATTITUDE_TARGET or "
                             "ATTITUDE_TARGET) nor optical flow: nothing to diagnose")
    sd = run_sensor_diagnosis(rec, job.config, profile=job.profile)
    t = sd.series.t_s
    return sd.report.to_json(), int(len(sd.rows)), float(t[-1] - t[0]) if len(t) > 1 else 0.0


def diagnose_file(job: Job) -> FileResult:
    """Diagnose ``job.path``; a bad file is a ``FileResult`` with ``error`` set, never an exception.
    Warnings raised inside the diagnosis become notes of the report (the same in every mode)."""
    t0 = time.perf_counter()
    out = FileResult(path=job.path, report=None)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            column_map = job.sensor_config if recording_suffix(job.path) == ".csv" else None
            rec = load_recording(job.path, sensor_config=column_map)
            out.sysid = _sysid(rec)
            start = rec.t0_s
            out.start_unix_s = start if start > UNIX_2000_S else math.nan
            report, out.frames_used, out.duration_s = _diagnose(rec, job, column_map is not None)
        seen: list[str] = []
        for w in caught:
            line = f"warning during the diagnosis: {w.category.__name__}: {w.message}"
            if line not in seen:
                seen.append(line)
        report.setdefault("notes", []).extend(seen)
        out.report = report
    except FlowholdError as exc:
        out.error = str(exc)
    except MemoryError:
        out.error = "out of memory while diagnosing it"
    except Exception as exc:  # noqa: BLE001 - a finder bug on one file is that file's failed row
        out.error = f"{type(exc).__name__}: {exc}".splitlines()[0]
    out.elapsed_s = time.perf_counter() - t0
    return out
