"""Repeated flights of one vehicle: do the finder's parameters agree within their uncertainties?

One airframe, one sensor set and one noise model (drawn once), the same effects, and ``--n``
flights of different profiles and noise draws (``simvehicle.engines.flightgen``); each is diagnosed as a
user would (``companion.diagnose.closed_loop.command``), and for every parameter found in at least two flights the
table gives the values, their stated 1-sigma uncertainties, the weighted mean and chi^2 per degree
of freedom of the spread about it (about 1 when the uncertainties are honest; 4 means they are
half what they should be).

    python scripts/repeat_flights.py --n 8 --out out/repeat
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
    args = ap.parse_args(argv)
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


if __name__ == "__main__":
    raise SystemExit(main())
