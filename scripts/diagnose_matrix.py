"""The diagnose test matrix (issue #5): fly every case, diagnose its recording, score, write the table.

    .venv/bin/python scripts/diagnose_matrix.py [--out out/diagnose_matrix] [--cases NAME ...]
                                                [--workers 2] [--doc docs/diagnose_matrix.md]

Each case of ``simvehicle.engines.flights.MATRIX`` (an effect at three sizes, pairs, clean flights) is flown
closed loop by the reference simulator and recorded (cached in ``OUT/recordings``, re-flown only
when the case or the noise settings change). The diagnosis runs as a user runs it,
``python -m companion diagnose REC --json OUT.json``, in a subprocess that sees only the recording.
``simvehicle.engines.flights.score`` compares the report with the truth under the issue's tolerances.
The table goes to ``--doc`` (docs/diagnose.md and the README point there) and a summary line to stdout.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from simvehicle.engines.flights import MATRIX, TOLERANCES, CaseScore, MatrixCase, score  # noqa: E402

#: a diagnosis that takes longer than this has failed (s)
DIAGNOSE_TIMEOUT_S = 300.0


def recording_for(case: MatrixCase, folder: Path) -> Path:
    """Fly ``case`` into ``folder`` unless a recording of exactly this case is already there."""
    from companion.config import load_config
    from simvehicle.engines.flights import fly_case

    folder.mkdir(parents=True, exist_ok=True)
    tlog = folder / f"{case.name}.tlog"
    key = folder / f"{case.name}.key"
    if tlog.exists() and key.exists() and key.read_text() == case.key():
        return tlog
    partial = tlog.with_suffix(".tlog.part")
    fly_case(case, load_config(), partial)
    partial.replace(tlog)
    key.write_text(case.key())
    return tlog


def diagnose(tlog: Path, json_out: Path) -> tuple[dict[str, Any], float]:
    """``python -m companion diagnose`` on the recording; returns (report, wall time s)."""
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "companion", "diagnose", str(tlog), "--json", str(json_out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=DIAGNOSE_TIMEOUT_S, check=False)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise RuntimeError(f"diagnose failed on {tlog.name}: {proc.stderr.strip()}")
    return json.loads(json_out.read_text()), wall


def run_case(case: MatrixCase, out: Path) -> dict[str, Any]:
    tlog = recording_for(case, out / "recordings")
    report, wall = diagnose(tlog, out / "reports" / f"{case.name}.json")
    s = score(case, report)
    return {"case": case.name, "score": s, "report": report, "wall_s": wall}


def _worker(args: tuple[MatrixCase, Path]) -> dict[str, Any]:
    case, out = args
    (out / "reports").mkdir(parents=True, exist_ok=True)
    return run_case(case, out)


def run_matrix(cases: list[MatrixCase], out: Path, workers: int = 2) -> list[dict[str, Any]]:
    """Fly and diagnose ``cases`` with ``workers`` processes; results in case order."""
    (out / "reports").mkdir(parents=True, exist_ok=True)
    if workers <= 1:
        return [_worker((c, out)) for c in cases]
    with ProcessPoolExecutor(max_workers=workers) as ex:
        return list(ex.map(_worker, [(c, out) for c in cases]))


# ---------------------------------------------------------------------------------------------
# the table


def _fmt_truth(case: MatrixCase) -> str:
    if not case.effects:
        return "none"
    parts = []
    for name, eff in case.effects.items():
        vals = ", ".join(f"{k} {_fmt(name, k, v)}" for k, v in vars(eff).items())
        parts.append(f"{name} ({vals})")
    return "; ".join(parts)


def _fmt(effect: str, key: str, v: float) -> str:
    if effect == "flow_yaw_misalignment" and key == "yaw":
        return f"{math.degrees(v):.2f} deg"
    if effect in ("flow_delay", "attitude_delay") and key == "delay":
        return f"{1e3 * v:.1f} ms"
    return f"{v:.4g}"


def _fmt_found(report: dict[str, Any]) -> str:
    sig = [f for f in report["findings"] if f["significant"]]
    if not sig:
        return "none"
    out = []
    for f in sig:
        vals = ", ".join(f"{k} {_fmt(f['effect'], k, v)}" for k, v in f["parameters"].items() if v is not None)
        out.append(f"{f['effect']} ({vals})")
    return "; ".join(out)


def _fmt_errors(s: CaseScore) -> str:
    if not s.param_errors:
        return ""
    return "; ".join(", ".join(f"{k} {v:.2f}" for k, v in errs.items()) for errs in s.param_errors.values())


def _fmt_heldout(report: dict[str, Any]) -> str:
    out = []
    for f in report["findings"]:
        if f["significant"] and f["fit"]["improvement_pct"] is not None:
            out.append(f"{f['fit']['improvement_pct']:.0f} %")
    return ", ".join(out)


def table(results: list[dict[str, Any]]) -> str:
    """The Markdown table of the matrix, with a summary line."""
    n_truth = sum(len(r["score"].truth) for r in results)
    hits = sum(len(r["score"].hits) for r in results)
    misses = sum(len(r["score"].misses) for r in results)
    false = sum(len(r["score"].false) for r in results)
    improved = sum(v for r in results for v in r["score"].heldout_improved.values())
    named = sum(len(r["score"].heldout_improved) for r in results)
    clean = [r for r in results if not r["score"].truth]
    clean_unexp = sum(len(r["report"]["unexplained"]) for r in clean)
    walls = [r["wall_s"] for r in results]
    lines = [
        f"**{hits} hits / {n_truth} effects, {misses} misses, {false} false findings** over {len(results)} "
        f"recordings ({len(clean)} clean); held-out residual lower with the named effect in {improved} of {named} "
        f"findings; {clean_unexp} unexplained entries on the clean recordings; diagnosis {min(walls):.1f}-"
        f"{max(walls):.1f} s per 150 s recording (subprocess, including reading).",
        "",
        "Tolerances (issue #5): " + "; ".join(
            f"{e} " + ", ".join(f"{k} {'±' if kind == 'abs' else ''}{_tol(e, k, kind, x)}"
                                for k, (kind, x) in t.items()) for e, t in TOLERANCES.items()) + ".",
        "A parameter error is given as |error| / tolerance (a hit needs every one <= 1).",
        "",
        "| case | truth | found (significant) | result | error / tolerance | held-out improvement | time (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        s: CaseScore = r["score"]
        res = []
        if s.hits:
            res.append("hit: " + ", ".join(s.hits))
        if s.misses:
            res.append("**miss**: " + ", ".join(s.misses))
        if s.false:
            res.append("**false**: " + ", ".join(s.false))
        if not res:
            res.append("clean: nothing reported")
        lines.append(f"| {s.case} | {_fmt_truth_by_name(s.case)} | {_fmt_found(r['report'])} | {'; '.join(res)} | "
                     f"{_fmt_errors(s)} | {_fmt_heldout(r['report'])} | {r['wall_s']:.1f} |")
    return "\n".join(lines) + "\n"


def summary_table(results: list[dict[str, Any]]) -> str:
    """One row per effect (its three sizes and the pairs it is in), one for the clean flights."""
    from simvehicle.engines.flights import EFFECT_TYPES

    rows = ["| effect | cases | hits | misses | false findings | worst parameter error / tolerance |",
            "|---|---|---|---|---|---|"]
    for effect in EFFECT_TYPES:
        rs = [r for r in results if effect in r["score"].truth]
        if not rs:
            continue
        hits = sum(effect in r["score"].hits for r in rs)
        false = sum(len(r["score"].false) for r in rs)
        worst = max((max(r["score"].param_errors[effect].values()) for r in rs if effect in r["score"].param_errors),
                    default=math.nan)
        rows.append(f"| {effect} | {len(rs)} | {hits} | {len(rs) - hits} | {false} | {worst:.2f} |")
    clean = [r for r in results if not r["score"].truth]
    rows.append(f"| none (clean flights) | {len(clean)} | - | - | {sum(len(r['score'].false) for r in clean)} | - |")
    return "\n".join(rows) + "\n"


README_BEGIN = "<!-- diagnose-matrix:begin (scripts/diagnose_matrix.py) -->"
README_END = "<!-- diagnose-matrix:end -->"


def update_readme(path: Path, results: list[dict[str, Any]]) -> bool:
    """Replace the README's text between the matrix markers; False when the markers are absent."""
    text = path.read_text()
    if README_BEGIN not in text or README_END not in text:
        return False
    head, rest = text.split(README_BEGIN, 1)
    _old, tail = rest.split(README_END, 1)
    link = "docs/diagnose_matrix.md"
    body = (f"\n{table(results).splitlines()[0]}\n\n{summary_table(results)}\n"
            f"Per case (truth, findings, errors, held-out improvement): [{link}]({link}).\n")
    path.write_text(head + README_BEGIN + body + README_END + tail)
    return True


def _tol(effect: str, key: str, kind: str, x: float) -> str:
    if kind == "rel":
        return f"{100 * x:.0f} %"
    if kind == "vec":
        return f"{100 * x:.0f} % of |F|"
    return _fmt(effect, key, x)


def _fmt_truth_by_name(name: str) -> str:
    return _fmt_truth(next(c for c in MATRIX if c.name == name))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/diagnose_matrix", help="cache of recordings and reports")
    ap.add_argument("--cases", nargs="*", help="case names (default: all)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--doc", default="docs/diagnose_matrix.md", help="where the table goes ('' for nowhere)")
    ap.add_argument("--readme", default="",
                    help="a README whose diagnose-matrix section (between its markers) is also rewritten "
                         "(default: none; the project's README links docs/diagnose_matrix.md instead)")
    args = ap.parse_args(argv)
    cases = list(MATRIX) if not args.cases else [c for c in MATRIX if c.name in set(args.cases)]
    unknown = set(args.cases or []) - {c.name for c in cases}
    if unknown:
        print(f"error: unknown case(s) {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    t = time.perf_counter()
    results = run_matrix(cases, Path(args.out), args.workers)
    text = table(results)
    if args.doc:
        doc = Path(args.doc)
        doc.parent.mkdir(parents=True, exist_ok=True)
        header = ("# The diagnose test matrix\n\nRegenerated by `scripts/diagnose_matrix.py` "
                  "(flights: `simvehicle/engines/flights.py`; method: docs/diagnose.md). Each recording is ~150 s of "
                  "closed-loop flight with steps, slow creeps, sinusoids on both axes, altitude changes between "
                  "0.7 and 2.5 m, turbulence, gyro and range noise; the diagnosis sees only the .tlog.\n\n")
        doc.write_text(header + text.splitlines()[0] + "\n\n" + summary_table(results) + "\n"
                       + "\n".join(text.splitlines()[1:]) + "\n")
    if args.readme and not args.cases:
        readme = Path(args.readme)
        if readme.exists() and not update_readme(readme, results):
            print(f"note: {readme} has no diagnose-matrix markers; table only in {args.doc}")
    print(text.splitlines()[0])
    print(f"{len(results)} cases in {time.perf_counter() - t:.0f} s" + (f"; table: {args.doc}" if args.doc else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
