"""The fitted model as a parameter set: ``diagnose REC --model-out fitted.toml`` (issue 16).

The file is the nominal config (every section, every key, as ``companion.config`` binds it) plus
one ``[effects.<name>]`` table per significant finding the simulator models, with the fitted
values and their 1-sigma uncertainties as comments. An effect the simulator cannot model (a
gyro filter, form drag, ...) is written as a comment saying so. It loads wherever ``--config``
is taken (``load_config``), and ``python -m simvehicle refly REC --config fitted.toml`` flies it.

Which part of the flight the model comes from (``heldout_split_s``): a flight of at least
``MIN_SPLIT_S`` of usable frames is split at the middle of their time span; the vehicle's
properties are fitted on the first half only, so that ``refly`` can judge the model on the second
half, which the fit never saw. A wind window is a circumstance of the flight, not a property of
the vehicle: it comes from the diagnosis of the whole flight and is replayed where it was found
(in recording time, s from its first record), so on the second half it is in-sample. A shorter
flight is fitted whole, and the file says so.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import EFFECT_TYPES, Config
from companion.diagnose.report import PARAMETER_UNITS, Finding, Report

#: the config's sections, in its order (every field of ``Config`` but the effects and the source)
SECTIONS = tuple(f.name for f in dataclasses.fields(Config) if f.name not in ("effects", "source"))

#: a flight with fewer seconds of usable frames than this is fitted whole (no held-out half)
MIN_SPLIT_S = 60.0

#: what the simulator does not model, per effect the finder names (CONVENTIONS.md's table)
NOT_SIMULATED = {
    "quadratic_drag": "the simulator's plant has linear drag only",
    "attitude_delay": "the simulator's attitude loop has no delay beyond the one-frame latency",
    "flow_rotation_gain": "the simulator's flow sees the whole rotation",
    "flow_lever_arm": "the simulator's flow sensor sits at the centre of gravity",
    "gyro_lag": "the simulator's gyro is not filtered",
}


def heldout_split_s(t_s: np.ndarray) -> float | None:
    """The time (report s) that splits a flight's usable frames ``t_s`` into the half a model is
    fitted on and the half it is judged on; None when the flight is too short to split."""
    if t_s.size < 2 or float(t_s[-1] - t_s[0]) < MIN_SPLIT_S:
        return None
    return float(0.5 * (t_s[0] + t_s[-1]))


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)
    return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'


def config_toml(cfg: Config) -> str:
    """Every section of ``cfg`` (not its effects) as TOML that ``load_config`` reads back equal."""
    out = []
    for name in SECTIONS:
        out.append(f"[{name}]")
        section = getattr(cfg, name)
        out += [f"{f.name} = {_value(getattr(section, f.name))}" for f in dataclasses.fields(section)]
        out.append("")
    return "\n".join(out)


def _pm(f: Finding, key: str) -> str:
    sd = f.uncertainty.get(key, math.nan)
    unit = PARAMETER_UNITS.get(key, "")
    unit = "" if unit in ("1", "") else f" {unit}"
    return f"+- {sd:.2g}{unit}" if sd is not None and math.isfinite(sd) else f"(no uncertainty){unit}"


def effect_table(f: Finding) -> list[str]:
    """The ``[effects.<name>]`` table of one finding, or comment lines when the simulator cannot
    model it (or its parameters are not all finite)."""
    p = f.parameters
    if f.effect not in EFFECT_TYPES:
        why = NOT_SIMULATED.get(f.effect, "the simulator has no model of it")
        vals = ", ".join(f"{k} = {v:.4g} {_pm(f, k)}" for k, v in p.items())
        return [f"# {f.effect} ({vals}): not set: {why}."]
    names = [fl.name for fl in dataclasses.fields(EFFECT_TYPES[f.effect])]
    if not all(k in p and p[k] is not None and math.isfinite(p[k]) for k in names):
        return [f"# {f.effect}: not set: its fit gave no finite {', '.join(names)}."]
    lines = [f"[effects.{f.effect}]", "enabled = true"]
    lines += [f"{k} = {_value(float(p[k]))}   # {_pm(f, k)}" for k in names]
    if f.alternatives:
        alts = " or ".join(a["effect"] for a in f.alternatives)
        lines.append(f"# this flight cannot tell it from {alts}")
    return lines


def fitted_findings(fit: Report, whole: Report) -> list[Finding]:
    """The findings a fitted model is made of: the vehicle's properties from ``fit`` (the first
    half), a wind window from ``whole`` (the whole flight); significant ones only."""
    props = [f for f in fit.significant() if f.effect != "wind_force"]
    wind = [f for f in whole.significant() if f.effect == "wind_force"]
    return props + wind


def model_toml(cfg: Config, findings: list[Finding], *, recording: str, fit_window_s: tuple[float, float] | None,
               span_s: tuple[float, float]) -> str:
    """The whole fitted-model file (see the module docstring)."""
    head = [f"# Fitted model of {recording} (python -m companion diagnose --model-out), from the nominal",
            f"# {Path(cfg.source).name}: its sections as they are, plus one [effects.<name>] table per",
            "# significant finding the simulator models (values fitted, 1 sigma in the comments).",
            "# Load it with --config wherever a config is taken; fly it against the recording with",
            "# python -m simvehicle refly RECORDING --config THIS_FILE."]
    if fit_window_s is not None:
        a, b = fit_window_s
        head += [f"# The vehicle's properties are fitted on {a:.2f}-{b:.2f} s (report time) only;",
                 f"# {b:.2f}-{span_s[1]:.2f} s is held out (refly judges the model there). A wind window comes",
                 "# from the whole flight: a circumstance of it, replayed where it was found."]
    else:
        head += [f"# The flight ({span_s[0]:.2f}-{span_s[1]:.2f} s usable) is shorter than {MIN_SPLIT_S:g} s:",
                 "# fitted whole, nothing held out."]
    body = [config_toml(cfg)]
    if not findings:
        body.append("# no effect the nominal model leaves out earned its parameters: nothing to add.")
    for f in findings:
        body += effect_table(f)
        body.append("")
    return "\n".join(head) + "\n\n" + "\n".join(body).rstrip() + "\n"


def write_model(path: str | Path, text: str) -> Path:
    out = Path(path)
    out.write_text(text)
    return out
