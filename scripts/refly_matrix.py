"""Issue 16's evidence: from a finding to a simulator that matches the vehicle, and to the settings
that undo the effect. Writes docs/refly_matrix.md (``--out`` to write elsewhere).

Part 1, simulated flights with known effects. Each case is a varied 150 s flight
(``simvehicle.engines.flights.flight_plan``: steps, creeps, sinusoids, height changes, turbulence) flown by
the in-process simulated vehicle with the companion, in the ``ardupilot`` profile, the effects set
by PARAM_SET while it flies (``simvehicle.server.paramflight``: 1 s after take-off; a wind switched on and
off). Then, as a user would:

1. ``diagnose`` the recording with ``--model-out`` (the properties fitted on the first half);
2. compare the written parameters with the truth (the finder's tolerances, ``flights.TOLERANCES``);
3. ``refly`` it with the fitted model: RMS of the commanded tilt on the held-out half, nominal and
   fitted, in noise widths; and, for reference, with the true model;
4. apply the suggested autopilot values (``actions``: FLOW_FXSCALER, FLOW_FYSCALER, FLOW_ORIENT_YAW)
   by PARAM_SET before the effects come on, fly the same flight again and diagnose it: what is left.

Part 2, ArduCopter SITL: the model fitted on one flight of the vehicle (data/sitl/ardupilot) flown
against the others (``refly --also``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from companion.config import (  # noqa: E402
    FlowScale,
    FlowYawMisalignment,
    LinearDrag,
    WindForce,
    load_config,
    replace_section,
    with_effects,
)
from companion.diagnose.closed_loop.command import write_model_out  # noqa: E402
from companion.diagnose.closed_loop.diagnosis import diagnose  # noqa: E402
from companion.recordings.load import load_recording  # noqa: E402
from companion.step.profiles import Profile  # noqa: E402
from simvehicle.engines.flights import flight_plan, param_error_ratios, with_sensor_noise  # noqa: E402
from simvehicle.server.paramflight import ParamChange, fly_with_params  # noqa: E402
from simvehicle.tools.refly import compare  # noqa: E402

ON_S = 1.0  # the effects come on 1 s into the flight
FIX_S = 0.5  # the suggested autopilot values are set before that
WIND = (50.0, 100.0)  # the wind window (s)
YAW = math.radians(8.0)

#: name -> (PARAM_SET changes, the truth as config effects); plan seeds differ per case
CASES = {
    "drag": ([ParamChange(ON_S, "SIM_DRAG_B", 0.5)], {"linear_drag": LinearDrag(0.5)}),
    "flow scale": ([ParamChange(ON_S, "SIM_FLOW_SCALE_X", 1.15), ParamChange(ON_S, "SIM_FLOW_SCALE_Y", 1.10)],
                   {"flow_scale": FlowScale(1.15, 1.10)}),
    "wind window": ([ParamChange(WIND[0], "SIM_WIND_FX", 2.0), ParamChange(WIND[0], "SIM_WIND_FY", -1.0),
                     ParamChange(WIND[1], "SIM_WIND_FX", 0.0), ParamChange(WIND[1], "SIM_WIND_FY", 0.0)],
                    {"wind_force": WindForce(2.0, -1.0, *WIND)}),
    "yaw": ([ParamChange(ON_S, "SIM_FLOW_YAW", YAW)], {"flow_yaw_misalignment": FlowYawMisalignment(YAW)}),
}
CASES["combined"] = ([c for k in CASES for c in CASES[k][0]],
                     {e: v for k in CASES for e, v in CASES[k][1].items()})
SEEDS = {"drag": 31, "flow scale": 32, "wind window": 33, "yaw": 34, "combined": 35}
AUTOPILOT_FIXES = ("FLOW_FXSCALER", "FLOW_FYSCALER", "FLOW_ORIENT_YAW")

SITL = REPO / "data" / "sitl" / "ardupilot"
SITL_FLIGHTS = ("flight_a.tlog.gz", "flight_c0_companion.tlog.gz", "flight_e1_companion.tlog.gz")


def _cmd(res, ch: str) -> tuple[float, float, float]:
    s = next(x for x in res.scores if x.channel == ch)
    return s.rms_nominal, s.rms_fitted, res.unrepro.floor[ch]


def simulated_case(name: str, folder: Path) -> dict:
    changes, truth = CASES[name]
    seed = SEEDS[name]
    # flown on eq. 15, the estimator of the fast engine refly uses (the ardupilot profile's default,
    # the Kalman filter, differs from it frame by frame whatever the model)
    base = replace_section(with_sensor_noise(load_config()), "companion", velocity_estimator="eq15")
    plan = flight_plan(seed)
    tlog = folder / f"{name.replace(' ', '_')}.tlog"
    t = time.perf_counter()
    fly_with_params(base, plan.scenario(), changes, tlog, profile=Profile.ARDUPILOT, seed=seed)
    rec = load_recording(tlog)
    diag = diagnose(rec, base)
    model = folder / f"{tlog.stem}.toml"
    write_model_out(rec, base, diag, model)
    fitted = load_config(model)
    found = {f.effect: f.parameters for f in diag.report.significant()}
    errors = {e: param_error_ratios(e, {k: float(x) for k, x in vars(v).items()}, found[e])
              for e, v in truth.items() if e in found}
    model_params = {e: vars(getattr(fitted.effects, e)) for e in fitted.effects.active()}
    model_errors = {e: param_error_ratios(e, {k: float(x) for k, x in vars(v).items()}, model_params[e])
                    for e, v in truth.items() if e in model_params}
    res = compare(tlog, fitted)
    true_cfg = with_effects(base, **truth)
    res_true = compare(tlog, true_cfg)
    actions = [a for a in diag.report.actions if a.system == "ardupilot" and a.parameter in AUTOPILOT_FIXES]
    fixed_found: dict[str, dict[str, float]] | None = None
    if actions:
        fixes = [ParamChange(FIX_S, a.parameter, float(a.value)) for a in actions]
        tlog2 = folder / f"{tlog.stem}_fixed.tlog"
        fly_with_params(base, plan.scenario(), fixes + list(changes), tlog2, profile=Profile.ARDUPILOT, seed=seed)
        fixed_found = {f.effect: f.parameters for f in diagnose(load_recording(tlog2), base).report.significant()}
    return {"case": name, "truth": {e: vars(v) for e, v in truth.items()}, "found": sorted(found),
            "errors": errors, "model_effects": fitted.effects.active(), "model_errors": model_errors,
            "pitch": _cmd(res, "pitch_cmd"), "roll": _cmd(res, "roll_cmd"),
            "pitch_true": _cmd(res_true, "pitch_cmd")[1], "roll_true": _cmd(res_true, "roll_cmd")[1],
            "pitch_1s": _cmd(res, "pitch_cmd_1s"), "roll_1s": _cmd(res, "roll_cmd_1s"),
            "turb_n": res.unrepro.force_sd_n, "turbulence_sigma_n": plan.turbulence_sigma_n,
            "share": (res.unrepro.share["pitch_cmd"], res.unrepro.share["roll_cmd"]),
            "actions": [(a.parameter, a.value, a.sigma) for a in diag.report.actions if a.system == "ardupilot"],
            "fixed_found": fixed_found, "seconds": time.perf_counter() - t}


def sitl_rows(folder: Path) -> list[dict]:
    cfg = load_config(REPO / "configs" / "ardupilot_sitl.toml")
    rows = []
    for fit_on in SITL_FLIGHTS[:2]:
        rec = load_recording(SITL / fit_on)
        diag = diagnose(rec, cfg, profile="ardupilot")
        model = folder / (fit_on.split(".")[0] + ".toml")
        write_model_out(rec, cfg, diag, model, profile="ardupilot")
        fitted = load_config(model)
        for other in SITL_FLIGHTS:
            same = other == fit_on
            res = compare(SITL / other, fitted, profile="ardupilot", held_out=same, carry_wind=same)
            row = {"fit_on": fit_on, "flown": other, "scored_on": res.track.scored_on,
                   "effects": fitted.effects.active()}
            for s in res.scores:
                row[s.channel] = (s.rms_nominal, s.rms_fitted, res.unrepro.floor.get(s.channel, math.nan))
            rows.append(row)
    return rows


def _widths(v: tuple[float, float, float]) -> str:
    return f"{v[0] / v[2]:.1f}, {v[1] / v[2]:.2f}"


def _r(e: dict) -> str:
    return ", ".join(f"{k} {v:.2f}" for k, v in e.items())


def render(cases: list[dict], sitl: list[dict]) -> str:
    md = ["# refly matrix (issue 16)", "",
          "Generated by `scripts/refly_matrix.py` (do not edit). Method: [refly.md](refly.md).", "",
          "## Simulated flights with effects set by PARAM_SET while flying", "",
          "Each case: a varied 150 s flight (`flight_plan(seed)`, sensor noise on, turbulence as drawn), "
          "`ardupilot` profile, the effects set by PARAM_SET 1 s after the start (the wind from 50 s to "
          "100 s). *param / tol*: the largest |error| / tolerance of the written parameters (the finder's "
          "tolerances, `simvehicle/engines/flights.py`; <= 1 passes), for the whole-flight report and for the model "
          "file (first half). Commanded tilt: RMS of simulation minus recording on the held-out half, rad; "
          "*noise*: the noise width (refly.md); *true*: the simulation with the true effects.", "",
          "| case | truth | found | param / tol (report; model) | pitch_cmd nominal / fitted / true / noise | "
          "roll_cmd nominal / fitted / true / noise | in noise widths (pitch; roll): nominal, fitted | "
          "1 s means, in noise widths (pitch; roll): nominal, fitted | "
          "turbulence: measured (true sigma) N; share of fitted error | suggested ArduPilot values | "
          "after applying them, found |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        truth = "; ".join(f"{e} ({_r(p)})" for e, p in c["truth"].items())
        err_r = max((r for e in c["errors"].values() for r in e.values()), default=math.nan)
        err_m = max((r for e in c["model_errors"].values() for r in e.values()), default=math.nan)
        pn, pf, pfl = c["pitch"]
        rn, rf, rfl = c["roll"]
        acts = ", ".join(f"{p} {v:.0f} ± {s:.0f}" for p, v, s in c["actions"]) or "-"
        fixed = "-" if c["fixed_found"] is None else (
            "; ".join(f"{e} ({_r(p)})" for e, p in c["fixed_found"].items()) or "nothing")
        md.append(f"| {c['case']} | {truth} | {', '.join(c['found'])} | {err_r:.2f}; {err_m:.2f} | "
                  f"{pn:.4f} / {pf:.4f} / {c['pitch_true']:.4f} / {pfl:.4f} | "
                  f"{rn:.4f} / {rf:.4f} / {c['roll_true']:.4f} / {rfl:.4f} | "
                  f"{pn / pfl:.1f}, {pf / pfl:.2f}; {rn / rfl:.1f}, {rf / rfl:.2f} | "
                  f"{_widths(c['pitch_1s'])}; {_widths(c['roll_1s'])} | "
                  f"{c['turb_n'][0]:.3f}, {c['turb_n'][1]:.3f} ({c['turbulence_sigma_n']:.3f}); "
                  f"{100 * c['share'][0]:.0f} %, {100 * c['share'][1]:.0f} % | {acts} | {fixed} |")
    md += ["", "## ArduCopter SITL: a model fitted on one flight, flown against the others", "",
           "The model is written by `diagnose --model-out` from the flight in the first column "
           "(`configs/ardupilot_sitl.toml`, `--profile ardupilot`; its properties from that flight's first "
           "half); the row's flight is flown with it and without its effects. On the flight it was fitted "
           "on, the held-out half is scored; on the others, every frame. RMS of simulation minus recording "
           "(nominal -> fitted), and the noise width.", "",
           "| fitted on | effects | flown | scored on | pitch_cmd (rad) | roll_cmd (rad) | pitch_cmd_1s (rad) | "
           "roll_cmd_1s (rad) | pitch (rad) | roll (rad) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in sitl:
        cells = []
        for ch in ("pitch_cmd", "roll_cmd", "pitch_cmd_1s", "roll_cmd_1s", "pitch", "roll"):
            v = r.get(ch)
            cells.append(f"{v[0]:.4f} -> {v[1]:.4f} ({v[2]:.4f})" if v else "-")
        md.append(f"| {r['fit_on']} | {', '.join(r['effects'])} | {r['flown']} | {r['scored_on']} | "
                  + " | ".join(cells) + " |")
    return "\n".join(md) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(REPO / "docs" / "refly_matrix.md"))
    ap.add_argument("--json", help="also write the raw results here")
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--no-sitl", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cases = []
        for name in args.cases:
            c = simulated_case(name, folder)
            print(f"{name}: found {c['found']}, pitch_cmd_1s {c['pitch_1s']}, fixed -> {c['fixed_found']} "
                  f"({c['seconds']:.0f} s)", flush=True)
            cases.append(c)
        sitl = [] if args.no_sitl else sitl_rows(folder)
    Path(args.out).write_text(render(cases, sitl))
    if args.json:
        Path(args.json).write_text(json.dumps({"cases": cases, "sitl": sitl}, indent=1, default=str))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
