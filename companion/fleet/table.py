"""The fleet table: one row per recording and effect tried, outliers flagged, written as CSV and
Parquet (pyarrow, with the ``cluster`` extra).

A recording that could not be diagnosed is one row with ``status = "failed"`` and its ``error``;
one diagnosed without any effect tried (nothing to fit) is one row with an empty ``effect``.
Parameters are columns ``param_<key>`` and ``param_<key>_sd`` (one standard deviation), with
CONVENTIONS.md's keys and SI units (``param_b`` N s/m, ``param_scale_x`` ratio, ...), empty where
an effect has no such parameter.

Outliers. A vehicle's property should stay put between flights: for each vehicle, effect and
parameter, recordings in time order, the change from the previous recording in combined standard
deviations ``(p_i - p_prev) / sqrt(sd_i^2 + sd_prev^2)``; a row whose parameter moved by more than
``OUTLIER_SIGMA`` of them is flagged (``outlier``, ``outlier_sigma`` the largest move,
``outlier_note`` what moved) when the effect is significant in one of the two recordings (the
fitted value of an effect neither flight shows is noise about the nominal model). Weather is not
a property of the vehicle: ``wind_force`` is not flagged. docs/diagnose.md finds the force
channel's uncertainties optimistic by about 2x in closed loop, hence 3 and not 2.
"""

from __future__ import annotations

import csv
import math
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

#: a parameter that moved by more than this many combined standard deviations is an outlier
OUTLIER_SIGMA = 3.0
#: effects that describe the day, not the vehicle: never flagged as a drift
NOT_VEHICLE_PROPERTIES = frozenset({"wind_force"})
#: parameters that place an effect in time (not a property of anything)
TIME_PARAMETERS = frozenset({"start_s", "end_s"})

#: (column, type) in order; type one of "str", "int", "float", "bool"
BASE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("recording", "str"), ("vehicle", "str"), ("vehicle_sysid", "int"), ("start_unix_s", "float"),
    ("start_utc", "str"), ("duration_s", "float"), ("frames_used", "int"), ("mode", "str"), ("status", "str"),
    ("error", "str"), ("effect", "str"), ("significant", "bool"), ("heldout_rms_before", "float"),
    ("heldout_rms_after", "float"), ("improvement_pct", "float"), ("headline", "str"), ("report", "str"),
    ("outlier", "bool"), ("outlier_sigma", "float"), ("outlier_note", "str"))


def _f(x: Any) -> float:
    return math.nan if x is None else float(x)


def utc_text(unix_s: float) -> str:
    """``2026-11-24T08:00:00Z`` for a UNIX time; empty when unknown."""
    if not math.isfinite(unix_s):
        return ""
    return datetime.fromtimestamp(unix_s, UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def rows_of(report: dict[str, Any], *, recording: str, vehicle: str, report_path: str) -> list[dict[str, Any]]:
    """The table rows of one per-file JSON (a mismatch report with its ``fleet`` block, or a
    failure: ``fleet.error`` set and no findings)."""
    meta = report.get("fleet", {})
    start = _f(meta.get("start_unix_s"))
    base: dict[str, Any] = {
        "recording": recording, "vehicle": vehicle, "vehicle_sysid": int(meta.get("sysid", -1)),
        "start_unix_s": start, "start_utc": utc_text(start), "duration_s": _f(meta.get("duration_s")),
        "frames_used": int(meta.get("frames_used", 0)), "mode": report.get("mode", ""),
        "status": "failed" if meta.get("error") else "ok", "error": meta.get("error") or "",
        "effect": "", "significant": False, "heldout_rms_before": math.nan, "heldout_rms_after": math.nan,
        "improvement_pct": math.nan, "headline": report.get("headline", ""), "report": report_path,
        "outlier": False, "outlier_sigma": math.nan, "outlier_note": "", "params": {}, "sds": {}}
    findings = report.get("findings") or []
    if meta.get("error") or not findings:
        return [base]
    out = []
    for f in findings:
        fit = f.get("fit") or {}
        row = dict(base, effect=f["effect"], significant=bool(f["significant"]),
                   heldout_rms_before=_f(fit.get("heldout_rms_before")),
                   heldout_rms_after=_f(fit.get("heldout_rms_after")), improvement_pct=_f(fit.get("improvement_pct")),
                   params={k: _f(v) for k, v in (f.get("parameters") or {}).items()},
                   sds={k: _f(v) for k, v in (f.get("uncertainty") or {}).items()})
        out.append(row)
    return out


def _time_key(row: dict[str, Any]) -> tuple[float, str]:
    s = row["start_unix_s"]
    return (s if math.isfinite(s) else math.inf, row["recording"])


def flag_outliers(rows: list[dict[str, Any]], sigma: float = OUTLIER_SIGMA) -> None:
    """Set ``outlier``, ``outlier_sigma`` and ``outlier_note`` in place (see the module's docs)."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        if r["status"] == "ok" and r["effect"] and r["effect"] not in NOT_VEHICLE_PROPERTIES:
            groups.setdefault((r["vehicle"], r["effect"]), []).append(r)
    for members in groups.values():
        members.sort(key=_time_key)
        last: dict[str, tuple[float, float, str, bool]] = {}  # parameter -> (value, sd, recording, significant)
        for r in members:
            worst = math.nan
            notes = []
            for k, p in r["params"].items():
                sd = r["sds"].get(k, math.nan)
                if k in TIME_PARAMETERS or not (math.isfinite(p) and math.isfinite(sd) and sd > 0):
                    continue
                if k in last:
                    p0, sd0, rec0, sig0 = last[k]
                    moved = (p - p0) / math.hypot(sd, sd0)
                    if not math.isfinite(worst) or abs(moved) > worst:
                        worst = abs(moved)
                    if abs(moved) > sigma and (sig0 or r["significant"]):
                        notes.append(f"{k} {p0:.4g} +- {sd0:.2g} -> {p:.4g} +- {sd:.2g} since {Path(rec0).name} "
                                     f"({moved:+.1f} sigma)")
                last[k] = (p, sd, r["recording"], bool(r["significant"]))
            r["outlier_sigma"] = worst
            r["outlier"] = bool(notes)
            r["outlier_note"] = "; ".join(notes)


def _keys(rows: list[dict[str, Any]]) -> list[str]:
    return sorted({k for r in rows for k in r["params"]} | {k for r in rows for k in r["sds"]})


def columns(rows: list[dict[str, Any]]) -> list[tuple[str, str]]:
    """The table's columns: the base ones, then ``param_<key>``, ``param_<key>_sd`` for every
    parameter key that occurs (sorted)."""
    return list(BASE_COLUMNS) + [c for k in _keys(rows) for c in ((f"param_{k}", "float"), (f"param_{k}_sd", "float"))]


def flat(rows: list[dict[str, Any]]) -> tuple[list[tuple[str, str]], list[dict[str, Any]]]:
    """The columns and the rows as flat dicts over them (parameters spread into their columns)."""
    keys = _keys(rows)
    out = []
    for r in rows:
        d = {name: r[name] for name, _ in BASE_COLUMNS}
        for k in keys:
            d[f"param_{k}"] = r["params"].get(k, math.nan)
            d[f"param_{k}_sd"] = r["sds"].get(k, math.nan)
        out.append(d)
    return columns(rows), out


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    """The table as CSV: floats at full precision (``repr``), ``nan`` where there is none."""
    cols, data = flat(rows)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([c for c, _ in cols])
        for d in data:
            w.writerow([repr(d[c]) if t == "float" else d[c] for c, t in cols])


def have_pyarrow() -> bool:
    import importlib.util

    return importlib.util.find_spec("pyarrow") is not None


def write_parquet(rows: list[dict[str, Any]], path: Path) -> None:
    """The table as Parquet (pyarrow; NaN kept as NaN, strings as UTF-8, booleans as bool)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols, data = flat(rows)
    types = {"str": pa.string(), "int": pa.int64(), "float": pa.float64(), "bool": pa.bool_()}
    schema = pa.schema([(c, types[t]) for c, t in cols])
    table = pa.Table.from_pydict({c: [d[c] for d in data] for c, _ in cols}, schema=schema)
    pq.write_table(table, path)


def read_parquet(path: Path) -> list[dict[str, Any]]:
    """A written Parquet table back as flat dicts (for tests and notebooks)."""
    import pyarrow.parquet as pq

    return pq.read_table(path).to_pylist()
