"""``python -m companion info RECORDING``: what a recording holds, at a glance.

Duration, every message type with its count, rate and senders, the largest gaps in each
stream, the sensors the companion and the analysis tools need (CONVENTIONS.md, "Recordings"),
what the reader had to skip, which sensor profile fits, and whose clock stamped the records
(``recording_clock``: the wall clock of a link, or a simulator's clock). ``--json OUT`` writes the
same summary as JSON. Times are seconds from the first record of the recording.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from companion.errors import FlowholdError, RecordingError, check_output, writing
from companion.mavlink_ids import DOWNWARD
from companion.recordings.load import MessageTable, Recording, load_recording
from companion.recordings.tlog_writer import SIM_CLOCK_TEXT
from companion.step import profiles

#: an interval longer than this many times the stream's median interval is a gap
GAP_FACTOR = 3.0
#: gaps listed per message type (the largest first)
MAX_GAPS_LISTED = 5
#: the rate is taken from intervals across this many messages (robust to bursty delivery)
RATE_SPAN = 10
#: a message type sent at least this often on average (Hz, per sender) is a stream: its gaps
#: are listed (1 Hz heartbeats are streams; occasional STATUSTEXT or PARAM_VALUE are not)
STREAM_MIN_HZ = 0.5

#: the vehicle's time fields ``recording_clock`` compares record times with: (message, field, to s)
CLOCK_FIELDS = (("ATTITUDE", "time_boot_ms", 1e-3), ("RAW_IMU", "time_usec", 1e-6),
                ("LOCAL_POSITION_NED", "time_boot_ms", 1e-3), ("DISTANCE_SENSOR", "time_boot_ms", 1e-3),
                ("SCALED_IMU", "time_boot_ms", 1e-3), ("HIGHRES_IMU", "time_usec", 1e-6))
#: record and field intervals that agree to this (s) were stamped from the field's clock
#: (headers carry whole microseconds); a link's arrivals jitter by far more
CLOCK_TOL_S = 1e-5
#: the share of intervals that must agree so for a simulator's clock (a reboot breaks one)
CLOCK_AGREE = 0.95
#: a vehicle time that runs this much faster than the record times: a lockstep or sped-up
#: simulation recorded with wall-clock stamps
CLOCK_FAST = 1.5

#: sensor role -> the messages that fill it (CONVENTIONS.md)
SENSORS: dict[str, tuple[str, ...]] = {
    "flow": ("OPTICAL_FLOW", "OPTICAL_FLOW_RAD"),
    "gyro": ("RAW_IMU", "SCALED_IMU", "HIGHRES_IMU"),
    "range": ("DISTANCE_SENSOR",),
    "attitude": ("ATTITUDE",),
    "commands": ("SET_ATTITUDE_TARGET", "ATTITUDE_TARGET"),
    "truth": ("LOCAL_POSITION_NED",),
}
#: roles a recording needs for diagnosis (truth is optional)
REQUIRED_FOR_DIAGNOSIS = ("flow", "gyro", "range", "attitude", "commands")


def stream_timing(t_s: np.ndarray, t0_s: float) -> dict[str, Any]:
    """Rate and gaps of one stream of message times ``t_s`` (s, file order).

    ``median_interval_s``: the median over the stream of the mean interval across ``RATE_SPAN``
    consecutive messages (one message to the next when there are fewer), so that a link that
    delivers in bursts still gives the sender's rate while gaps barely move it; ``rate_hz`` is
    its inverse (None with fewer than two messages or no time between them). ``gaps``: the
    intervals longer than ``GAP_FACTOR`` x the median interval, largest first, each
    ``{"start_s": time of the message before it, from t0_s, "duration_s"}``.
    """
    n = len(t_s)
    t = np.asarray(t_s, dtype=np.float64)
    if n < 2:
        return {"rate_hz": None, "median_interval_s": None, "gaps": []}
    k = min(RATE_SPAN, n - 1)
    typical = _median(t[k:] - t[:-k]) / k
    if not typical > 0:
        return {"rate_hz": None, "median_interval_s": typical, "gaps": []}
    step = np.diff(t)
    big = np.flatnonzero(step > GAP_FACTOR * typical)
    big = big[np.argsort(-step[big], kind="stable")]
    gaps = [{"start_s": float(t[i] - t0_s), "duration_s": float(step[i])} for i in big]
    return {"rate_hz": 1.0 / typical, "median_interval_s": typical, "gaps": gaps}


def _median(x: np.ndarray) -> float:
    """``np.median`` of a float64 vector, by one partition (np.median's own way, less its
    overheads: a third of the time on the streams of an hour-long recording)."""
    n = len(x)
    if n == 0 or np.isnan(x).any():
        return float(np.median(x))
    h = n // 2
    if n % 2:
        return float(np.partition(x, h)[h])
    part = np.partition(x, (h - 1, h))
    return float((part[h - 1] + part[h]) / 2)


def _senders(tab: MessageTable) -> list[tuple[int, int]]:
    """The (sysid, compid) pairs that sent ``tab``'s rows, sorted. Counted over a dense 16-bit
    key (``np.bincount``): a sort of a million rows, as ``np.unique(..., axis=0)`` does, costs
    a second on an hour-long recording."""
    sysid, compid = tab.sysid.astype(np.int64), tab.compid.astype(np.int64)
    if len(sysid) and (min(sysid.min(), compid.min()) < 0 or max(sysid.max(), compid.max()) > 255):
        pairs = np.unique(np.stack([sysid, compid], axis=1), axis=0)  # not MAVLink ids: the general way
        return [(int(a), int(b)) for a, b in pairs]
    present = np.flatnonzero(np.bincount((sysid << 8) | compid, minlength=1 << 16))
    return [(int(k >> 8), int(k & 0xFF)) for k in present.tolist()]


def _from_sender(tab: MessageTable, sysid: int, compid: int) -> np.ndarray:
    """Which rows of ``tab`` (sysid, compid) sent: a mask, where ``tab.from_sender`` would copy
    every field (a whole table of an hour-long recording, for one column)."""
    return (tab.sysid == sysid) & (tab.compid == compid)


def message_summary(tab: MessageTable, t0_s: float, duration_s: float) -> dict[str, Any]:
    """Count, rate (Hz, summed over senders), mean rate over the recording's ``duration_s``,
    senders and gaps (found per sender) of one message type. ``streamed``: sent at
    ``STREAM_MIN_HZ`` or more on average, so its gaps mean something."""
    senders = []
    gaps = []
    pairs = _senders(tab)
    for sysid, compid in pairs:
        t_s = tab.t_s if len(pairs) == 1 else tab.t_s[_from_sender(tab, sysid, compid)]
        timing = stream_timing(t_s, t0_s)
        senders.append({"sysid": sysid, "compid": compid, "count": len(t_s), "rate_hz": timing["rate_hz"]})
        gaps += [{**g, "sysid": sysid, "compid": compid} for g in timing["gaps"]]
    gaps.sort(key=lambda g: -g["duration_s"])
    rates = [s["rate_hz"] for s in senders if s["rate_hz"] is not None]
    mean_hz = len(tab) / duration_s if duration_s > 0 else None
    return {
        "name": tab.name,
        "count": len(tab),
        "rate_hz": float(sum(rates)) if rates else None,
        "mean_rate_hz": mean_hz,
        "streamed": bool(mean_hz is not None and mean_hz >= STREAM_MIN_HZ * len(senders)),
        "senders": senders,
        "n_gaps": len(gaps),
        "gaps": gaps[:MAX_GAPS_LISTED],
    }


def sensors_found(rec: Recording, duration_s: float, summaries: dict[str, dict[str, Any]] | None = None
                  ) -> dict[str, Any]:
    """Per sensor role, the messages present (count, rate); DISTANCE_SENSOR counts only the
    downward-facing rows (orientation 25) and lists the orientations seen. ``summaries``: the
    ``message_summary`` of whole tables already made, by name (not made again)."""
    t0 = rec.t0_s
    summaries = summaries or {}
    found: dict[str, Any] = {}
    for role, names in SENSORS.items():
        items = []
        for name in names:
            if name not in rec:
                continue
            tab = rec.tables[name]
            entry: dict[str, Any] = {"message": name}
            if name == "DISTANCE_SENSOR" and "orientation" in tab.fields:
                orient = np.asarray(tab["orientation"]).astype(np.int64)
                entry["orientations"] = sorted(int(o) for o in np.unique(orient))
                down = orient == DOWNWARD
                if not down.all():
                    tab = tab.select(down)
                if len(tab) == 0:
                    continue
            entry["count"] = len(tab)
            done = summaries.get(name)
            entry["rate_hz"] = (done if done is not None and done["count"] == len(tab)
                                else message_summary(tab, t0, duration_s))["rate_hz"]
            items.append(entry)
        found[role] = items
    return found


def recording_clock(rec: Recording) -> dict[str, Any]:
    """Whose clock stamped the records: ``{"simulated": True|False|None, "reason": one line}``.

    1. A STATUSTEXT saying "simulated clock" (the simulated vehicle sends it to each peer in
       lockstep and speed-up, and the recordings of both keep it): simulated.
    2. Otherwise the record times against the vehicle's own time field (``CLOCK_FIELDS``, its
       most frequent sender): when ``CLOCK_AGREE`` of the intervals between records equal those
       of the field to ``CLOCK_TOL_S``, the stamps are the vehicle's clock (a simulator's log:
       the scenarios', the simulated vehicle's); a link's arrivals jitter. When the field runs
       ``CLOCK_FAST`` times faster than the stamps, a simulation ran faster than real time and
       was stamped with the wall clock: durations and rates here are wall-clock.
    3. No time field: None.
    """
    if "STATUSTEXT" in rec:
        for text in rec.tables["STATUSTEXT"]["text"]:
            if SIM_CLOCK_TEXT in str(text):
                return {"simulated": True, "reason": f"the recording says so: {str(text)!r}"}
    for name, field_name, scale in CLOCK_FIELDS:
        if name not in rec or field_name not in rec.tables[name].fields:
            continue
        tab = rec.tables[name]
        senders = _senders(tab)
        masks: list[np.ndarray | slice] = ([_from_sender(tab, *sc) for sc in senders] if len(senders) > 1
                                           else [slice(None)])
        rows = max(masks, key=lambda m: len(tab.t_s[m]))  # the most frequent sender (the first of equals)
        t_s, field_values = tab.t_s[rows], tab[field_name][rows]
        if len(t_s) < 20:
            continue
        d_log = np.diff(np.asarray(t_s, dtype=np.float64))
        d_field = np.diff(np.asarray(field_values, dtype=np.float64) * scale)
        agree = float(np.mean(np.abs(d_log - d_field) <= CLOCK_TOL_S))
        where = f"{name} {field_name}"
        if agree >= CLOCK_AGREE:
            return {"simulated": True, "reason": f"record times advance exactly as {where} ({100 * agree:.0f} % of "
                                                 f"{len(d_log)} intervals): stamped with the vehicle's own clock"}
        ahead = d_field > 0  # the field's advance over its forward steps (a reboot steps back)
        log_s = float(np.sum(d_log[ahead]))
        ratio = float(np.sum(d_field[ahead])) / log_s if log_s > 0 else math.inf
        if ratio > CLOCK_FAST:
            return {"simulated": False, "reason": f"but {where} ran {ratio:.1f}x faster than the record times: a "
                                                  "lockstep or sped-up simulation stamped with the wall clock; "
                                                  "durations and rates below are wall-clock"}
        return {"simulated": False, "reason": f"record times jitter against {where}, as a link's arrivals do"}
    return {"simulated": None, "reason": "no time field of the vehicle's to tell"}


def _profile(rec: Recording) -> dict[str, Any]:
    try:
        name, reason = profiles.detect_profile(rec)
    except FlowholdError as exc:
        return {"name": None, "reason": str(exc)}
    return {"name": str(name), "reason": str(reason)}


def summarise(rec: Recording) -> dict[str, Any]:
    """The summary of a recording as a JSON-ready dict.

    Keys: ``file``, ``format``, ``t0_s`` (log time of the first record), ``duration_s`` (first
    to last record), ``n_messages``, ``skipped_bytes``, ``skipped_packets``, ``notes``,
    ``messages`` (per type, most frequent first: ``count``, ``rate_hz`` (1 / median interval),
    ``mean_rate_hz`` (count / duration), ``streamed``, ``senders``, ``n_gaps``, ``gaps``),
    ``sensors`` (see ``sensors_found``), ``missing_for_diagnosis`` (roles with no message)
    ``profile`` (``name``, ``reason``) and ``clock`` (``simulated``, ``reason``: ``recording_clock``).
    Raises RecordingError if the recording holds no messages.
    """
    if rec.n_messages == 0:
        raise RecordingError(f"{Path(rec.path).name}: the recording holds no messages")
    t0 = rec.t0_s
    duration = max(float(np.max(t.t_s)) for t in rec if len(t)) - t0
    messages = [message_summary(t, t0, duration) for t in rec if len(t)]
    messages.sort(key=lambda m: (-m["count"], m["name"]))
    sensors = sensors_found(rec, duration, {m["name"]: m for m in messages})
    return {
        "file": str(rec.path),
        "format": rec.source_format,
        "t0_s": t0,
        "duration_s": duration,
        "n_messages": rec.n_messages,
        "skipped_bytes": int(rec.skipped_bytes),
        "skipped_packets": int(rec.skipped_packets),
        "notes": list(rec.notes),
        "messages": messages,
        "sensors": sensors,
        "missing_for_diagnosis": [r for r in REQUIRED_FOR_DIAGNOSIS if not sensors[r]],
        "profile": _profile(rec),
        "clock": recording_clock(rec),
    }


def _hz(rate: float | None) -> str:
    if rate is None:
        return "-"
    return f"{rate:.1f}" if rate >= 0.95 else f"{rate:.3f}"


def _clock(c: dict[str, Any]) -> str:
    kind = {True: "simulated", False: "wall", None: "unknown"}[c["simulated"]]
    return f"clock     {kind} ({c['reason']})"


def _start(t0_s: float, fmt: str) -> str:
    if fmt == "tlog" and 1e9 < t0_s < 4e9:  # a UNIX time
        return dt.datetime.fromtimestamp(t0_s, tz=dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    return f"log time {t0_s:.3f} s"


def format_summary(s: dict[str, Any]) -> str:
    """``summarise``'s dict as the readable report ``info`` prints."""
    lines = [
        f"file      {s['file']}",
        f"format    {s['format']}",
        f"duration  {s['duration_s']:.1f} s, {s['n_messages']} messages, starting {_start(s['t0_s'], s['format'])}",
        _clock(s["clock"]),
        f"skipped   {s['skipped_bytes']} bytes, {s['skipped_packets']} packets",
    ]
    lines += [f"note      {n}" for n in s["notes"]]
    p = s["profile"]
    lines.append(f"profile: {p['name'] or 'none'} ({p['reason']})")
    lines.append("")
    width = max([len(m["name"]) for m in s["messages"]] + [7])
    lines.append(f"{'message':<{width}}  {'count':>8}  {'rate Hz':>8}  {'mean Hz':>8}  {'gaps':>4}  "
                 "senders (sysid/compid)")
    for m in s["messages"]:
        senders = ", ".join(
            f"{x['sysid']}/{x['compid']}" + (f" {x['count']} @ {_hz(x['rate_hz'])} Hz" if len(m["senders"]) > 1 else "")
            for x in m["senders"])
        n_gaps = str(m["n_gaps"]) if m["streamed"] else "-"
        lines.append(f"{m['name']:<{width}}  {m['count']:>8}  {_hz(m['rate_hz']):>8}  "
                     f"{_hz(m['mean_rate_hz']):>8}  {n_gaps:>4}  {senders}")
    lines.append(f"(rate: 1 / median interval; mean: count / duration; gaps: intervals > {GAP_FACTOR:g}x the "
                 f"median, counted for streams of {STREAM_MIN_HZ:g} Hz or more)")
    gaps = [(g["duration_s"], m["name"], g) for m in s["messages"] if m["streamed"] for g in m["gaps"]]
    gaps.sort(key=lambda x: -x[0])
    lines.append("")
    if gaps:
        lines.append("largest gaps in the streams (s from the first record):")
        for dur, name, g in gaps[:10]:
            lines.append(f"  {name} from {g['sysid']}/{g['compid']}: {dur:.3f} s at {g['start_s']:.3f} s")
    else:
        lines.append("no gaps in the streams")
    lines.append("")
    lines.append("sensors:")
    for role, items in s["sensors"].items():
        if not items:
            text = "none"
        else:
            parts = []
            for it in items:
                extra = ""
                if it["message"] == "DISTANCE_SENSOR":
                    extra = f" facing down (orientations seen: {', '.join(map(str, it['orientations']))})"
                parts.append(f"{it['message']}{extra}: {it['count']} @ {_hz(it['rate_hz'])} Hz")
            text = "; ".join(parts)
        lines.append(f"  {role:<9} {text}")
    missing = s["missing_for_diagnosis"]
    lines.append(f"missing for diagnosis: {', '.join(missing) if missing else 'nothing'}")
    return "\n".join(lines)


def _json_ready(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _json_ready(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_ready(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def run_cli(args: argparse.Namespace) -> int:
    """``info``: print the summary of ``args.recording``; ``args.json``: also write it there."""
    if getattr(args, "json", None):
        check_output(args.json, "--json")
    rec = load_recording(args.recording, sensor_config=getattr(args, "sensor_config", None),
                         progress=sys.stderr.isatty())
    summary = summarise(rec)
    print(format_summary(summary))
    if getattr(args, "json", None):
        with writing("--json", args.json):
            Path(args.json).write_text(json.dumps(_json_ready(summary), indent=2) + "\n")
    return 0
