"""Repeated flights of one vehicle: do the finder's parameters agree within their uncertainties?

One airframe, one sensor set and one noise model (drawn once), the same effects, and ``--n``
flights of different profiles and noise draws (``simvehicle.engines.flightgen``); each is diagnosed as a
user would (``companion.diagnose.closed_loop.command``), and for every parameter found in at least two flights the
table gives the values, their stated 1-sigma uncertainties, the weighted mean and chi^2 per degree
of freedom of the spread about it (about 1 when the uncertainties are honest; 4 means they are
half what they should be).

    python scripts/repeat_flights.py --n 8 --out out/repeat

``--reflight I,J,...``: the generalisation matrix's recordings I, J, ... (``--matrix-seed``, as
``scripts/generalisation_matrix.py --seed``) flown again ``--reps`` times each, everything the
same but the noise and random-loss draws, and the truth's effects refitted exactly in each
(``Selector.score_exact`` on the truth's effects of each group, whatever the selection chose):
the pulls (fit - truth) / stated sigma, per parameter and split by the flight's turbulence. Were
the stated sigma true, 68 % of pulls would lie within 1 and 95 % within 2 (median |pull| 0.67).

    python scripts/repeat_flights.py --reflight 52,267 --reps 10 --out out/reflight
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.config import load_config  # noqa: E402
from companion.diagnose.closed_loop.diagnosis import diagnose  # noqa: E402
from companion.recordings.load import load_recording  # noqa: E402
from simvehicle.engines import flightgen as fg  # noqa: E402

DEFAULT_EFFECTS = {"linear_drag": {"b": 0.4}, "gyro_bias": {"bias_x": 0.02, "bias_y": -0.015},
                   "flow_scale": {"scale_x": 1.1, "scale_y": 0.93}}
NOISE = fg.Noise(att_white_rad=math.radians(0.1), att_gm_rad=math.radians(0.1), att_gm_tau_s=0.5,
                 flow_count_error_frac=0.01, gyro_white_rad_s=0.002, range_noise_m=0.005, record_jitter_s=0.002,
                 turbulence_n=0.15, turbulence_tau_s=0.5)


def fly_and_diagnose(n: int, effects: dict[str, dict[str, float]], duration_s: float, out: Path,
                     vehicle_seed: int = 1000, progress: bool = True
                     ) -> dict[tuple[str, str], list[tuple[int, float, float]]]:
    """``n`` flights of the vehicle drawn from ``vehicle_seed`` with ``effects`` (different
    profiles and noise draws), each diagnosed as a user would: per (effect, parameter) found
    significant, the (flight, value, stated 1-sigma) of every flight that found it."""
    out.mkdir(parents=True, exist_ok=True)
    base = fg.draw_spec(vehicle_seed)
    found: dict[tuple[str, str], list[tuple[int, float, float]]] = {}
    for s in range(n):
        seed = 5000 + s
        sp = fg.draw_spec(seed)
        prof = fg.draw_profile(np.random.default_rng([seed, 13]), sp.warmup_s + duration_s, 1.5, False, 1.5)
        sp = dataclasses.replace(sp, vehicle=base.vehicle, sensors=base.sensors, noise=NOISE, flight=prof,
                                 effects=json.loads(json.dumps(effects)), duration_s=duration_s)
        g = fg.write_flight(sp, fg.simulate(sp), out, f"flight_{s}")
        rep = diagnose(load_recording(g.tlog), load_config(g.config)).report
        for f in rep.significant():
            for k, v in f.parameters.items():
                found.setdefault((f.effect, k), []).append((s, v, f.uncertainty.get(k, math.nan)))
        if progress:
            print(f"flight {s}: {', '.join(f.effect for f in rep.significant()) or 'nothing'}", flush=True)
    return found


#: re-flight r of matrix recording seed s uses noise seed REFLIGHT_SEED0 + 1000 s + r
REFLIGHT_SEED0 = 50_000_000
#: the turbulence (N) that splits the re-flights' pulls (docs/diagnose.md section 8: above it the
#: flow geometry is biased)
TURBULENT_N = 0.2


def reflight_pulls(spec: fg.FlightSpec, reps: int, out: Path, progress: bool = True) -> list[dict[str, float | str]]:
    """``spec`` flown ``reps`` times with new noise draws (its seed replaced), each diagnosed, and in
    each group the truth's effects refitted exactly at the group's fit: one row per (re-flight,
    effect, parameter) with the truth, the fit, its stated sigma and the pull. A wind's window
    (searched), parameters a group does not fit (a lever arm's rx, ry) and the gyro lag (its
    reported value is the instrumental variables', not this least squares: docs/diagnose.md 3b)
    are left out."""
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, float | str]] = []
    for r in range(reps):
        sp = dataclasses.replace(spec, seed=REFLIGHT_SEED0 + 1000 * spec.seed + r)
        g = fg.write_flight(sp, fg.simulate(sp), out, f"reflight_{spec.seed}_{r}")
        diag = diagnose(load_recording(g.tlog), load_config(g.config))
        for res in diag.groups.values():
            cands = {c.effect: c for c in res.group.candidates}
            effects = [e for e in spec.effects if e in cands and e != "gyro_lag"]
            if not effects:
                continue
            ms = res.selector.score_exact(effects, res.final.p)
            for e in effects:
                for k in cands[e].params:
                    if k not in spec.effects[e]:
                        continue
                    i = res.group.params.index(k)
                    sd = math.sqrt(max(float(ms.cov[i, i]), 0.0))
                    truth, value = float(spec.effects[e][k]), float(ms.p[i])
                    rows.append({"seed": spec.seed, "reflight": r, "effect": e, "param": k, "truth": truth,
                                 "value": value, "sigma": sd, "pull": (value - truth) / sd if sd > 0 else math.inf,
                                 "turbulence_n": spec.noise.turbulence_n})
        if progress:
            chosen = [e for res in diag.groups.values() for e in res.chosen]
            print(f"seed {spec.seed} re-flight {r}: chose {', '.join(chosen) or 'nothing'}", flush=True)
    return rows


def pull_summary(pulls: list[float]) -> tuple[int, float, float, float]:
    """(count, share within 1, share within 2, median |pull|) of finite pulls."""
    a = np.abs(np.array([p for p in pulls if math.isfinite(p)]))
    if len(a) == 0:
        return 0, math.nan, math.nan, math.nan
    return len(a), float(np.mean(a < 1)), float(np.mean(a < 2)), float(np.median(a))


def spread(vals: list[tuple[int, float, float]]) -> tuple[float, float] | None:
    """(weighted mean, chi^2 per degree of freedom of the values about it, each weighted by its
    stated sigma): about 1 when the stated sigmas are true. None for fewer than two values or a
    sigma that is not a positive number."""
    v = np.array([x[1] for x in vals])
    sd = np.array([x[2] for x in vals])
    if len(v) < 2 or not np.all(np.isfinite(sd) & (sd > 0)):
        return None
    w = 1.0 / sd ** 2
    m = float(np.sum(w * v) / np.sum(w))
    return m, float(np.sum(((v - m) / sd) ** 2) / (len(v) - 1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=8, help="flights (default 8)")
    ap.add_argument("--vehicle-seed", type=int, default=1000, help="seed the airframe and sensors are drawn from")
    ap.add_argument("--effects", default=json.dumps(DEFAULT_EFFECTS), help="true effects (JSON, CONVENTIONS.md names)")
    ap.add_argument("--duration", type=float, default=90.0, help="seconds per flight (default 90)")
    ap.add_argument("--out", default="out/repeat", help="folder for the recordings (default out/repeat)")
    ap.add_argument("--reflight", default="", help="matrix recordings to fly again (indices, comma-separated)")
    ap.add_argument("--matrix-seed", type=int, default=0, help="the matrix's base seed (recording i: seed*1000003 + i)")
    ap.add_argument("--reps", type=int, default=10, help="re-flights per recording (default 10)")
    args = ap.parse_args(argv)
    if args.reflight:
        try:
            idx = [int(x) for x in args.reflight.split(",") if x.strip()]
        except ValueError:
            print(f"error: --reflight takes recording indices (e.g. 52,267), not {args.reflight!r}", file=sys.stderr)
            return 2
        return _reflight_main(idx, args.matrix_seed, args.reps, Path(args.out))
    try:
        effects = json.loads(args.effects)
    except json.JSONDecodeError as exc:
        print(f"error: --effects is not JSON: {exc}", file=sys.stderr)
        return 2
    found = fly_and_diagnose(args.n, effects, args.duration, Path(args.out), args.vehicle_seed)
    print(f"\ntrue effects: {json.dumps(effects)}\n")
    print("| parameter | flights | values | stated sigma (median) | weighted mean | spread (sd) | chi2/dof |")
    print("|---|---|---|---|---|---|---|")
    for (e, k), vals in sorted(found.items()):
        v = np.array([x[1] for x in vals])
        sd = np.array([x[2] for x in vals])
        got = spread(vals)
        if got is None:
            print(f"| {e}.{k} | {len(v)} | {' '.join(f'{x:.4g}' for x in v)} | - | - | - | - |")
            continue
        m, chi2 = got
        print(f"| {e}.{k} | {len(v)} | {' '.join(f'{x:.4g}' for x in v)} | {np.median(sd):.3g} | {m:.4g} | "
              f"{np.std(v, ddof=1):.3g} | {chi2:.2f} |")
    return 0


def _reflight_main(idx: list[int], matrix_seed: int, reps: int, out: Path) -> int:
    rows: list[dict[str, float | str]] = []
    for i in idx:
        rows += reflight_pulls(fg.draw_spec(matrix_seed * 1_000_003 + i), reps, out)
    (out / "reflight.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    print("\n| seed | turbulence (N) | parameter | truth | mean fit | spread (sd) | stated sigma (rms) | "
          "within 1 sigma | within 2 sigma |")
    print("|---|---|---|---|---|---|---|---|---|")
    keys = sorted({(r["seed"], r["effect"], r["param"]) for r in rows})
    for seed, e, k in keys:
        sel = [r for r in rows if (r["seed"], r["effect"], r["param"]) == (seed, e, k)]
        v = np.array([float(r["value"]) for r in sel])
        sd = np.array([float(r["sigma"]) for r in sel])
        _n, w1, w2, _med = pull_summary([float(r["pull"]) for r in sel])
        print(f"| {seed} | {float(sel[0]['turbulence_n']):.2f} | {e}.{k} | {float(sel[0]['truth']):.4g} | "
              f"{v.mean():.4g} | {np.std(v, ddof=1) if len(v) > 1 else math.nan:.3g} | "
              f"{math.sqrt(float(np.mean(sd ** 2))):.3g} | {100 * w1:.0f} % | {100 * w2:.0f} % |")
    print("\n| flights | pulls | within 1 sigma | within 2 sigma | median abs pull |")
    print("|---|---|---|---|---|")
    for name, keep in ((f"turbulence under {TURBULENT_N:g} N", lambda r: float(r["turbulence_n"]) < TURBULENT_N),
                       (f"turbulence {TURBULENT_N:g} N or more", lambda r: float(r["turbulence_n"]) >= TURBULENT_N),
                       ("all", lambda r: True)):
        n, w1, w2, med = pull_summary([float(r["pull"]) for r in rows if keep(r)])
        if n:
            print(f"| {name} | {n} | {100 * w1:.0f} % | {100 * w2:.0f} % | {med:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
