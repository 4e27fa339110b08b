"""The sensor-only diagnosis as a call (``diagnose_sensor``, ``run_sensor_diagnosis``) and as
the command (``run_sensor_cli``: ``python -m companion diagnose`` on a recording without
commands, or with ``--sensor-config``)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config, load_config
from companion.diagnose.report import Report
from companion.diagnose.sensor.diagnosis import SensorDiagnosis, analyse
from companion.diagnose.sensor.findings import build_report
from companion.diagnose.sensor.markdown import write_report_dir
from companion.diagnose.sensor.settings import SensorDiagnosisSettings
from companion.recordings.load import Recording, load_recording


def diagnose_sensor(rec: Recording, cfg: Config, *, report_dir: Path | None = None, profile: str | None = None,
                    settings: SensorDiagnosisSettings | None = None,
                    rng: np.random.Generator | None = None) -> Report:
    """Sensor-only diagnosis of ``rec`` against the paper's flow-sensor model with ``cfg``'s Q.

    Returns the mismatch report (``mode = "sensor"``); with ``report_dir``, also writes one PNG
    and ``report.md`` there. ``rng`` drives the bootstrap (default: seeded with 0, so reports
    are reproducible).
    """
    return run_sensor_diagnosis(rec, cfg, report_dir=report_dir, profile=profile, settings=settings,
                                rng=rng).report


def run_sensor_diagnosis(rec: Recording, cfg: Config, *, report_dir: Path | None = None,
                         profile: str | None = None, settings: SensorDiagnosisSettings | None = None,
                         rng: np.random.Generator | None = None) -> SensorDiagnosis:
    """``diagnose_sensor`` keeping the intermediate results (``SensorDiagnosis``)."""
    st = settings or SensorDiagnosisSettings()
    rng = rng if rng is not None else np.random.default_rng(0)
    d = analyse(rec, cfg, st, rng, profile=profile)
    d.report = build_report(rec, cfg, d, st)
    if report_dir is not None:
        write_report_dir(d, Path(report_dir))
    return d


def summary_lines(rep: Report) -> list[str]:
    """One line per finding for the console."""
    out = [f"{rep.recording}: sensor-only diagnosis"]
    for f in rep.findings:
        params = ", ".join(
            (f"{k}={v:.4g}" + (f"+-{f.uncertainty[k]:.2g}" if np.isfinite(f.uncertainty.get(k, np.nan)) else "")
             + (f" {f.unit(k)}" if f.unit(k) else ""))
            if np.isfinite(v) else f"{k}=n/a" for k, v in f.parameters.items())
        mark = "*" if f.significant else " "
        out.append(f" {mark} {f.effect:<24} {params}")
    return out


def run_sensor_cli(args: Any) -> int:
    """``python -m companion diagnose RECORDING [--sensor-config MAP] [--config] [--profile]
    [--json OUT] [--report DIR]`` for a recording without commands: the whole command."""
    rec = load_recording(args.recording, sensor_config=getattr(args, "sensor_config", None),
                         progress=sys.stderr.isatty())
    cfg = load_config(getattr(args, "config", None))
    report_dir = getattr(args, "report", None)
    rep = diagnose_sensor(rec, cfg, report_dir=Path(report_dir) if report_dir else None,
                          profile=getattr(args, "profile", None))
    if getattr(args, "json", None):
        rep.write_json(args.json)
    for line in summary_lines(rep):
        print(line)
    if getattr(args, "json", None):
        print(f"json: {args.json}")
    if report_dir:
        print(f"report: {Path(report_dir) / 'report.md'}")
        print(f"report: {Path(report_dir) / 'report.html'} (one page, plot embedded)")
    return 0
