"""What a mismatch report means for the config, in plain words: what differs, how sure, what to change.

A report (``companion.report.Report``, either diagnose mode) names the effects the nominal model
leaves out with their fitted parameters. This module turns them into

- ``config_changes``: the TOML keys to set, with the fitted values as suggestions (keys and
  sections exactly as ``companion.config`` binds them, so the snippet loads);
- ``how_sure``: one clause per finding, from its 1-sigma uncertainty and its held-out fit;
- ``lead``: the first line of a human report, the three together.

Pure functions of the report; nothing here fits or decides anything (that is the finder's job).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.config import EFFECT_TYPES
from companion.report import Finding, Report

#: effects that describe the flight, not the vehicle: nothing to change in a vehicle's config
CIRCUMSTANCES = {"wind_force": "a wind during this flight, not a property of the vehicle"}

#: findings of the sensor-only mode that describe the log's timing, not the sensor model
LOG_TIMING = {"missing_flow_readings", "repeated_flow_readings", "held_range"}


@dataclass(frozen=True)
class ConfigChange:
    """Keys to set in one TOML table (``section`` as written between the brackets)."""

    section: str
    values: dict[str, float | bool]
    why: str

    def toml(self) -> str:
        """The table as TOML text (values in the config's units)."""
        return "\n".join([f"[{self.section}]", *(f"{k} = {_toml_value(v)}" for k, v in self.values.items())])

    def inline(self) -> str:
        """One line: ``[section] key = value, key = value``."""
        return f"[{self.section}] " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in self.values.items())


def _toml_value(v: float | bool) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return f"{v:.4g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.4e}"


def _finite(f: Finding) -> bool:
    return bool(f.parameters) and all(math.isfinite(v) for v in f.parameters.values())


def change_for(f: Finding, *, q_rad_per_count: float) -> ConfigChange | None:
    """The config keys one finding suggests, with its fitted values; None when the config has no
    key for it (an effect it does not model, a circumstance such as a wind, the log's timing)."""
    p = f.parameters
    if f.effect == "attitude_dynamics":
        if not _finite(f):
            return None
        return ConfigChange("airframe", {"omega_p_rad_s": p["omega_p"], "zeta": p["zeta"]},
                            "the nominal model of this vehicle's attitude loop")
    if f.effect == "flow_scale":
        scales = [v for k, v in p.items() if k in ("scale_x", "scale_y") and math.isfinite(v)]
        if not scales:
            return None
        why = "rad per count of this sensor (counts in the `paper` profile and in CSVs; flow in rad is scaled " \
              "on the autopilot)"
        sd = [f.uncertainty.get(k, 0.0) for k in ("scale_x", "scale_y")]
        if len(scales) == 2 and abs(scales[0] - scales[1]) > 2 * math.hypot(*(x if math.isfinite(x) else 0.0
                                                                               for x in sd)):
            why += "; x and y differ and the config holds one Q: the mean of the two"
        return ConfigChange("flow_sensor", {"q_rad_per_count": q_rad_per_count * sum(scales) / len(scales)}, why)
    if f.effect in CIRCUMSTANCES or f.effect in LOG_TIMING or f.effect not in EFFECT_TYPES or not _finite(f):
        return None
    return ConfigChange(f"effects.{f.effect}", {"enabled": True, **p}, "for the simulator to fly like this vehicle")


def config_changes(report: Report, *, q_rad_per_count: float) -> list[ConfigChange]:
    """The config keys the report's significant findings suggest, with the fitted values.

    ``q_rad_per_count`` is the nominal Q the report's ``flow_scale`` is relative to.
    """
    changes = (change_for(f, q_rad_per_count=q_rad_per_count) for f in report.significant())
    return [c for c in changes if c is not None]


def _pm(key: str, v: float, sd: float, unit: str) -> str:
    unit = f" {unit}" if unit else ""
    return f"{key} {v:.4g} ± {sd:.2g}{unit}" if math.isfinite(sd) else f"{key} {v:.4g}{unit}"


def how_sure(f: Finding) -> str:
    """How sure the report is of one finding, in words: its size with 1 sigma and its held-out gain."""
    sizes = ", ".join(_pm(k, v, f.uncertainty.get(k, math.nan), f.unit(k)) for k, v in f.parameters.items()
                      if math.isfinite(v))
    head = f"{f.effect} ({sizes})" if sizes else f.effect
    if f.effect in LOG_TIMING:
        return f"{head}, counted in the log, not fitted"
    if f.fit is not None and f.fit.heldout_rms_before > 0:
        return f"{head}, with {f.fit.improvement_pct:.0f} % less error on data the fit never saw"
    return head


def what_differs(report: Report) -> str:
    """The report's own headline, or for a report without one (sensor-only) its significant effects."""
    if report.headline:
        text = report.headline.rstrip(".")
        return text[0].upper() + text[1:]
    found = [f.effect for f in report.significant()]
    if not found:
        return "The recording fits the nominal model within its noise: no effect it leaves out earns its parameters"
    return "The recording differs from the nominal model: " + ", ".join(found)


def lead(report: Report, *, q_rad_per_count: float) -> str:
    """The first line of a human report: what differs, how sure, what to change in the config."""
    sentences = [what_differs(report) + "."]
    sig = report.significant()
    if sig:
        sentences.append("How sure: " + "; ".join(how_sure(f) for f in sig) + ".")
    pairs = [(f, change_for(f, q_rad_per_count=q_rad_per_count)) for f in sig]
    set_ = [c.inline() for _f, c in pairs if c is not None]
    keep = [_no_change(f) for f, c in pairs if c is None]
    if set_:
        sentences.append("In the config, set " + "; ".join(set_) + ".")
    if keep:
        sentences.append(("Nothing else to change" if set_ else "Nothing to change in the config") + ": "
                         + "; ".join(keep) + ".")
    if not sig:
        sentences.append("Nothing to change in the config.")
    return " ".join(sentences)


def _no_change(f: Finding) -> str:
    if f.effect in CIRCUMSTANCES:
        return f"{f.effect} is {CIRCUMSTANCES[f.effect]}"
    if f.effect in LOG_TIMING:
        return f"{f.effect} is the log's timing, not the sensor"
    return f"no config key models {f.effect} (docs/diagnose.md)"
