"""``python -m companion diagnose``: find where a flight and the paper's model differ, and why.

    python -m companion diagnose RECORDING [--config FILE] [--profile P] [--json OUT] [--report DIR]

The recording is compared with the nominal model (``--config``, default ``configs/paper.toml``)
on channels where each effect shows despite the closed loop (``groups``): the attitude loop, the
gyro against the attitude, the flow against the rotation and the plant, and the force balance.
Candidate effects (CONVENTIONS.md) are fitted, kept only when they earn their parameters on
held-out data (``select``), located in time and by operating condition (``locate``); what they do
not explain goes through sparse regression (``sparse``). Output: the JSON report of
CONVENTIONS.md (``--json``), a Markdown report with plots and the same as one self-contained
HTML page (``--report``: ``report.md``, ``report.html``), a summary on stdout.
Method: docs/diagnose.md.

Recordings without a commanded attitude (or given ``--sensor-config``) go to the sensor-only
diagnosis (``companion.diagnose.sensor.api``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from companion.config import Config, load_config
from companion.diagnose.closed_loop.channels import has_commands
from companion.diagnose.closed_loop.diagnosis import FIT_SPAN_S, STAGES, Diagnosis, diagnose
from companion.diagnose.closed_loop.markdown import write_report
from companion.diagnose.fitted_model import fitted_findings, heldout_split_s, model_toml, write_model
from companion.diagnose.report import Report
from companion.diagnose.report_html import write_html_report
from companion.errors import UsageError, check_output, writing
from companion.recordings.load import Recording, load_recording

__all__ = ["run_cli", "diagnose_recording", "summary"]


def diagnose_recording(path: str | Path, *, config: str | Path | None = None, profile: str | None = None,
                       report_dir: str | Path | None = None) -> Diagnosis:
    """Load, diagnose, optionally write the Markdown and HTML reports; returns the ``Diagnosis``."""
    cfg = load_config(config)
    rec = load_recording(path)
    diag = diagnose(rec, cfg, profile=profile)
    if report_dir is not None:
        _write_html(diag, write_report(diag, report_dir))
    return diag


def _write_html(diag: Diagnosis, markdown_path: Path) -> Path:
    """``report.html`` beside the Markdown report: the same content, plots embedded, the first line
    in plain words."""
    return write_html_report(diag.report, markdown_path, q_rad_per_count=diag.cfg.flow_sensor.q_rad_per_count)


def _sensor_mode(args: argparse.Namespace) -> int:
    from companion.diagnose.sensor import api as sensor_diagnose  # (scipy.signal: only for this mode)

    return int(sensor_diagnose.run_sensor_cli(args))


def run_cli(args: argparse.Namespace) -> int:
    """Entry point of ``python -m companion diagnose`` (arguments declared in companion/cli.py)."""
    model_out = getattr(args, "model_out", None)
    if model_out:
        check_output(model_out, "--model-out")
    if getattr(args, "sensor_config", None):
        if model_out:
            raise UsageError("--model-out needs a closed-loop flight (with commands), not a sensor-only recording")
        return _sensor_mode(args)
    t_start = time.perf_counter()
    cfg = load_config(args.config)
    rec = load_recording(args.recording, progress=sys.stderr.isatty())  # a bar on a terminal only
    if not has_commands(rec) and ("OPTICAL_FLOW" in rec or "OPTICAL_FLOW_RAD" in rec):
        if model_out:
            raise UsageError(f"{Path(args.recording).name}: --model-out needs a closed-loop flight; this recording has "
                             "no commanded attitude")
        return _sensor_mode(args)
    bar = None
    if sys.stderr.isatty():  # a progress bar on a terminal only; quiet in pipes, logs and CI
        from tqdm import tqdm

        bar = tqdm(total=len(STAGES), desc="diagnose", unit="stage", leave=False, file=sys.stderr)

    def progress(stage: str) -> None:
        if bar is not None:
            bar.set_postfix_str(stage)
            bar.update(1)

    try:
        diag = diagnose(rec, cfg, profile=args.profile, progress=progress,
                        fit_span_s=None if args.fit_all else FIT_SPAN_S)
    finally:
        if bar is not None:
            bar.close()
    report = diag.report
    report.notes.append(f"diagnosed in {time.perf_counter() - t_start:.1f} s")
    if args.json:
        report.write_json(args.json)
    if args.report:
        out = write_report(diag, args.report)
        html_out = _write_html(diag, out)
    if model_out:
        with writing("--model-out", model_out):
            write_model_out(rec, cfg, diag, model_out, profile=args.profile)
    print(summary(report))
    if args.json:
        print(f"json: {args.json}")
    if model_out:
        print(f"model: {model_out} (load it with --config; python -m simvehicle refly {args.recording} --config "
              f"{model_out})")
    if args.report:
        print(f"report: {out}")
        print(f"report: {html_out} (one page, plots embedded)")
    return 0


def write_model_out(rec: Recording, cfg: Config, whole: Diagnosis, path: str | Path, *,
                    profile: str | None = None) -> Path:
    """``--model-out``: the fitted model of ``companion.diagnose.fitted_model``. The vehicle's properties are
    fitted on the first half of the flight's usable frames (a second diagnosis of that half), the
    wind windows come from ``whole``; a flight too short to split is fitted whole."""
    t = whole.data.t_s
    split = heldout_split_s(t)
    span = (float(t[0]), float(t[-1]))
    if split is None:
        fit, window = whole.report, None
    else:
        window = (span[0], split)
        fit = diagnose(rec, cfg, profile=profile, window_s=window).report
    text = model_toml(cfg, fitted_findings(fit, whole.report), recording=Path(rec.path).name, fit_window_s=window,
                      span_s=span)
    return write_model(path, text)


def summary(report: Report) -> str:
    """A short human summary of a report."""
    head = next((n for n in report.notes if n.startswith("profile ")), "")
    lines = [f"{report.recording}: {report.headline}" if report.headline else f"{report.recording}:", head]
    # what the reader skipped or repaired and the frames left out: a damaged recording says so
    lines += [f"note: {n}" for n in report.notes if n != head and not n.startswith("diagnosed in")]
    found = report.significant()
    if found:
        lines.append(f"found {len(found)} effect(s) the model leaves out:")
        for f in found:
            ps = ", ".join(f"{k} = {v:.4g} +- {f.uncertainty.get(k, math.nan):.2g}" for k, v in f.parameters.items())
            fit = f.fit
            ch = f.evidence.get("channel", "")
            unit = f.evidence.get("unit", "")
            imp = (f"held-out {ch} rms {fit.heldout_rms_before:.3g} -> {fit.heldout_rms_after:.3g} {unit} "
                   f"({fit.improvement_pct:.0f} % lower)") if fit else ""
            lines.append(f"  {f.effect}: {ps}; {imp}")
            lines.append(f"    {f.explanation}")
    elif not report.headline:
        lines.append("no effect the model leaves out earns its parameters: the recording fits the nominal model")
    not_found = [f.effect for f in report.findings if not f.significant]
    if not_found:
        lines.append("tried, not found: " + ", ".join(not_found))
    for u in report.unexplained:
        lines.append(f"unexplained: {u.channel} {u.start_s:.1f}-{u.end_s:.1f} s rms {u.rms:.3g}"
                     + (f"; best term: {u.best_term}" if u.best_term else ""))
    return "\n".join(lines)
