"""The fleet summary: one self-contained HTML page (plots embedded as base64 PNG, readable offline).

First what the fleet shows in plain words (how many recordings, which effects where, which
vehicles moved), then the outliers, the failed files, and per effect found somewhere in the fleet
one figure per parameter: its value with one standard deviation across all recordings, and over
time per vehicle, outliers ringed in red.
"""

from __future__ import annotations

import base64
import html
import io
import math
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from companion.diagnose.report import PARAMETER_UNITS as UNITS
from companion.fleet.table import NOT_VEHICLE_PROPERTIES, OUTLIER_SIGMA, TIME_PARAMETERS

_CSS = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;font-size:.85em;margin:.5em 0}td,th{border:1px solid #ddd;padding:3px 6px;
text-align:left;vertical-align:top}th{background:#f4f4f4}.bad{color:#b00}.lead{font-size:1.1em}
img{max-width:100%}"""


def _png(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _table(head: list[str], body: list[list[Any]]) -> str:
    rows = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in body)
    return "<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>" + rows + "</table>"


def _plot(rows: list[dict[str, Any]], effect: str, key: str) -> str:
    """Base64 PNG: ``key`` of ``effect`` across recordings (left) and over time per vehicle (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = [r for r in rows if r["effect"] == effect and math.isfinite(r["params"].get(key, math.nan))]
    pts.sort(key=lambda r: (r["vehicle"], r["start_unix_s"] if math.isfinite(r["start_unix_s"]) else math.inf,
                            r["recording"]))
    unit = UNITS.get(key, "")
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 3.6))
    vehicles = sorted({r["vehicle"] for r in pts})
    colours = {v: plt.get_cmap("tab10")(i % 10) for i, v in enumerate(vehicles)}
    for i, r in enumerate(pts):
        p, sd = r["params"][key], r["sds"].get(key, math.nan)
        c = colours[r["vehicle"]]
        a1.errorbar(i, p, yerr=sd if math.isfinite(sd) else None, fmt="o", color=c, capsize=2,
                    mfc=c if r["significant"] else "white")
        if r["outlier"]:
            a1.plot(i, p, "o", ms=13, mfc="none", mec="red", mew=1.5)
    a1.set_xticks(range(len(pts)), [Path(r["recording"]).name for r in pts], rotation=60, ha="right", fontsize=6)
    a1.set_title(f"{effect}: {key} across recordings (filled: significant; red ring: outlier)", fontsize=9)
    a1.set_ylabel(f"{key} ({unit})" if unit else key)
    a1.grid(True, alpha=0.3)
    dated = all(math.isfinite(r["start_unix_s"]) for r in pts)
    for v in vehicles:
        mine = [r for r in pts if r["vehicle"] == v]
        x: list[Any] = ([datetime.fromtimestamp(r["start_unix_s"], UTC) for r in mine] if dated
                        else list(range(len(mine))))
        y = [r["params"][key] for r in mine]
        e = [r["sds"].get(key, math.nan) for r in mine]
        a2.errorbar(x, y, yerr=[s if math.isfinite(s) else 0.0 for s in e], fmt="o-", color=colours[v], capsize=2,
                    label=v, lw=1)
        for xi, yi, r in zip(x, y, mine, strict=True):
            if r["outlier"]:
                a2.plot(xi, yi, "o", ms=13, mfc="none", mec="red", mew=1.5)
    a2.set_title(f"{key} over time per vehicle" + ("" if dated else " (recording order: no UNIX start time)"),
                 fontsize=9)
    a2.set_xlabel("start of the recording (UTC)" if dated else "recording of the vehicle")
    a2.set_ylabel(f"{key} ({unit})" if unit else key)
    a2.grid(True, alpha=0.3)
    if len(vehicles) <= 12:
        a2.legend(fontsize=7)
    if dated:
        fig.autofmt_xdate()
    fig.tight_layout()
    return _png(fig)


def write_summary(rows: list[dict[str, Any]], path: Path, *, title: str, run_note: str) -> None:
    """Write the HTML fleet summary of the table ``rows`` (``table.rows_of`` dicts, outliers set)."""
    recs: dict[str, dict[str, Any]] = {}
    for r in rows:
        recs.setdefault(r["recording"], r)
    ok = [r for r in recs.values() if r["status"] == "ok"]
    failed = [r for r in recs.values() if r["status"] != "ok"]
    vehicles = sorted({r["vehicle"] for r in recs.values()})
    found: dict[str, set[str]] = {}
    for r in rows:
        if r["significant"]:
            found.setdefault(r["effect"], set()).add(r["recording"])
    outliers = [r for r in rows if r["outlier"]]
    parts = [f"<h1>{html.escape(title)}</h1>"]
    lead = (f"{len(recs)} recording(s) of {len(vehicles)} vehicle(s): {len(ok)} diagnosed, {len(failed)} could not "
            f"be read or diagnosed. ")
    if found:
        lead += "Effects the nominal model leaves out: " + ", ".join(
            f"{e} in {len(s)}" for e, s in sorted(found.items(), key=lambda kv: -len(kv[1]))) + ". "
    else:
        lead += "No recording shows an effect the nominal model leaves out. "
    moved = sorted({(r["vehicle"], r["effect"]) for r in outliers})
    lead += (f"{len(outliers)} finding(s) moved by more than {OUTLIER_SIGMA:g} standard deviations from the "
             f"vehicle's previous recording: " + ", ".join(f"{v} ({e})" for v, e in moved) + "."
             if outliers else "No vehicle's parameters moved by more than their uncertainties allow.")
    parts.append(f"<p class='lead'>{html.escape(lead)}</p><p>{html.escape(run_note)}</p>")
    parts.append("<h2>Outliers</h2><p>A parameter of a vehicle is compared with the same vehicle's previous "
                 f"recording: a change over {OUTLIER_SIGMA:g} combined standard deviations "
                 "(sqrt(sd1^2 + sd2^2)) is flagged when either recording finds the effect. The wind is weather, "
                 "not the vehicle: not flagged. "
                 "docs/diagnose.md finds the force channel's uncertainties optimistic by about 2x.</p>")
    parts.append(_table(["vehicle", "recording", "start (UTC)", "effect", "what moved"],
                        [[r["vehicle"], r["recording"], r["start_utc"], r["effect"], r["outlier_note"]]
                         for r in outliers]) if outliers else "<p>None.</p>")
    parts.append("<h2>Failed files</h2>")
    parts.append(_table(["recording", "error"], [[r["recording"], r["error"]] for r in failed])
                 if failed else "<p>None.</p>")
    plotted = sorted(set(found) | {r["effect"] for r in outliers})
    for effect in plotted:
        parts.append(f"<h2>{html.escape(effect)}</h2>")
        keys = sorted({k for r in rows if r["effect"] == effect for k in r["params"]} - TIME_PARAMETERS)
        note = " (weather: not flagged)" if effect in NOT_VEHICLE_PROPERTIES else ""
        parts.append(f"<p>Significant in {len(found.get(effect, ()))} of {len(ok)} recording(s){note}.</p>")
        for k in keys:
            if any(math.isfinite(r["params"].get(k, math.nan)) for r in rows if r["effect"] == effect):
                parts.append(f"<img alt='{html.escape(effect)} {html.escape(k)}' "
                             f"src='data:image/png;base64,{_plot(rows, effect, k)}'>")
    parts.append("<h2>Recordings</h2>")
    parts.append(_table(["recording", "vehicle", "start (UTC)", "duration (s)", "frames used", "headline"],
                        [[r["recording"], r["vehicle"], r["start_utc"],
                          f"{r['duration_s']:.1f}" if math.isfinite(r["duration_s"]) else "",
                          r["frames_used"], r["headline"] or r["error"]] for r in recs.values()]))
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{_CSS}</style></head><body>{''.join(parts)}</body></html>\n")
    path.write_text(page)
