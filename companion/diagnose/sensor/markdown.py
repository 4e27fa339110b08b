"""The sensor-only diagnosis's human report: ``report.md`` with the figure beside it, and the
same as one self-contained page (``report.html``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from companion.diagnose.report import Finding
from companion.diagnose.report_html import write_html_report
from companion.diagnose.sensor.diagnosis import SensorDiagnosis
from companion.diagnose.sensor.motions import leg_reference
from companion.diagnose.sensor.plots import plot_diagnosis
from companion.recordings.load import recording_stem


def _fmt_g(v: float, s: float) -> str:
    if not np.isfinite(v):
        return "n/a"
    return f"{v:.4g} +- {s:.2g}" if np.isfinite(s) else f"{v:.4g}"


def _fmt_param(f: Finding, key: str, v: float) -> str:
    """``key value +- sigma unit`` of one parameter, ``n/a`` when not identifiable."""
    text = f"{key} {_fmt_g(v, f.uncertainty.get(key, float('nan')))}"
    return text + (f" {f.unit(key)}" if f.unit(key) and np.isfinite(v) else "")


def write_report_dir(d: SensorDiagnosis, report_dir: Path) -> Path:
    """Write ``<stem>_sensor.png``, ``report.md`` and ``report.html`` (the same, one page with the
    plot embedded) into ``report_dir``; returns the .md path."""
    report_dir.mkdir(parents=True, exist_ok=True)
    stem = recording_stem(d.series.name)
    png = report_dir / f"{stem}_sensor.png"
    plot_diagnosis(d, png)
    md = report_dir / "report.md"
    md.write_text(markdown_report(d, png.name))
    write_html_report(d.report, md, q_rad_per_count=d.series.q_rad_per_count)
    return md


def markdown_report(d: SensorDiagnosis, png_name: str) -> str:
    rep = d.report
    lines = [f"# Sensor diagnosis: {rep.recording}", "",
             f"![paper model vs extended model]({png_name})", "", "## Findings", "",
             "| effect | significant | parameters | held-out RMS before -> after | explanation |",
             "|---|---|---|---|---|"]
    for f in rep.findings:
        params = ", ".join(_fmt_param(f, k, v) for k, v in f.parameters.items())
        if f.fit is not None:
            fit = f"{f.fit.heldout_rms_before:.4g} -> {f.fit.heldout_rms_after:.4g}"
        else:
            fit = "(counted, not fitted)" if f.evidence.get("constraint") == "log timing" else "n/a"
        lines.append(f"| {f.effect} | {'yes' if f.significant else 'no'} | {params} | {fit} | {f.explanation} |")
    if d.legs and d.motion is not None:
        lines += ["", f"## Legs ({leg_reference(d.motion)}; {d.motion.source})", "",
                  "Each leg's length along its axis with the paper's Q and with the fitted scale, the part of it "
                  "that is rotation removed with the gyro, and how far it went sideways (across its axis, at the "
                  "paper's Q, between the pauses around it, or between its own ends where it turns a corner).", "",
                  "| leg | time (s) | paper Q (cm) | fitted scale (cm) | rotation part (cm) | sideways (cm) |",
                  "|---|---|---|---|---|---|"]
        for lg in d.legs:
            lines.append(f"| {lg.name} | {lg.start_s:.1f}-{lg.end_s:.1f} | {100 * lg.length(1, 1):.1f} | "
                         f"{100 * lg.length(d.scale[0], d.scale[1]):.1f} | {100 * lg.direction * lg.d_rotation:+.1f} | "
                         f"{100 * lg.cross_m:+.1f} |")
    if rep.unexplained:
        lines += ["", "## Unexplained", "", "| channel | start s | end s | RMS |", "|---|---|---|---|"]
        lines += [f"| {u.channel} | {u.start_s:.2f} | {u.end_s:.2f} | {u.rms:.3g} |" for u in rep.unexplained]
    lines += ["", "## Notes", ""] + [f"- {n}" for n in rep.notes] + [""]
    return "\n".join(lines)
