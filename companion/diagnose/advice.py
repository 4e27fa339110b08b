"""What a mismatch report means for the config, in plain words: what differs, how sure, what to change.

A report (``companion.diagnose.report.Report``, either diagnose mode) names the effects the nominal model
leaves out with their fitted parameters. This module turns them into

- ``config_changes``: the TOML keys to set, with the fitted values as suggestions (keys and
  sections exactly as ``companion.config`` binds them, so the snippet loads);
- ``how_sure``: one clause per finding, from its 1-sigma uncertainty and its held-out fit;
- ``lead``: the first line of a human report, the three together;
- ``actions``: every value to set, in the user's terms (``diagnose --json``'s ``actions``): the
  companion's config keys, and for an ArduPilot or PX4 recording the autopilot's own parameters
  in that autopilot's units, each with its 1-sigma uncertainty propagated from the fit.

Pure functions of the report; nothing here fits or decides anything (that is the finder's job).

How each autopilot parameter acts, read in the autopilot's own source (the mappings below are
the inverse of these):

- ArduPilot ``FLOW_FXSCALER``/``FLOW_FYSCALER`` (parts per thousand): every flow backend multiplies
  the sensor's X (Y) flow rate by ``1 + 0.001 FLOW_FxSCALER`` before anything uses it
  (libraries/AP_OpticalFlow/AP_OpticalFlow_Pixart.cpp and AP_OpticalFlow_MAV.cpp, ``update()``:
  ``flowScaleFactorX = 1.0f + 0.001f * flowScaler.x``), and OPTICAL_FLOW carries the scaled rate.
  MAVLink's X flow rate is the rotation about the X axis, so it carries the *sideways* motion: it
  is the paper's y axis (CONVENTIONS.md, profile ``ardupilot``: ``dphi_y = +flow_rate_x dt``), and
  ``FLOW_FXSCALER`` corrects ``scale_y``, ``FLOW_FYSCALER`` corrects ``scale_x``.
- ArduPilot ``FLOW_ORIENT_YAW`` (centidegrees; "a sensor with its X-axis pointing to the right of
  the vehicle X axis has a positive yaw angle", libraries/AP_OpticalFlow/AP_OpticalFlow.cpp): the
  backend turns the sensor-axes rate into body axes with ``Vector2f::rotate(+yaw)``
  (AP_OpticalFlow_Backend.cpp ``_applyYaw``). The finder's ``yaw`` is the same angle (sensor axes
  turned by +yaw about body z, towards the right), so ``FLOW_ORIENT_YAW = 100 degrees(yaw)``.
- ArduPilot ``EK3_FLOW_DELAY`` and PX4 ``EKF2_OF_DELAY`` (ms): the flow measurement's delay behind
  the IMU that the EKF assumes; the finder's ``delay`` is how much later the flow is than the gyro.
- ArduPilot ``FLOW_POS_X/Y/Z`` and PX4 ``EKF2_OF_POS_X/Y/Z`` (m, body FRD): where the flow sensor's
  focal point is; the EKF removes the lever arm's velocity ``omega x r``. The finder's
  ``flow_lever_arm`` is that position (only ``rz`` is observable without yaw rate).
- ArduPilot ``RNGFND1_OFFSET``: a PWM rangefinder's distance is ``reading + RNGFND1_OFFSET`` in cm
  (libraries/AP_RangeFinder/AP_RangeFinder_PWM.cpp, ``state.distance_cm += params.offset``); for an
  analog one it is volts at zero distance (distance = (V - OFFSET) SCALING), for other drivers there
  is no offset parameter. The action is the PWM one; the note says so.
- PX4 ``SENS_FLOW_SCALE``: ``VehicleOpticalFlow`` multiplies the integrated flow of both axes by it
  (src/modules/sensors/vehicle_optical_flow/VehicleOpticalFlow.cpp: ``pixel_flow *
  _param_sens_flow_scale.get()``): one factor for both axes.
- PX4 ``SENS_FLOW_ROT``: a ``Rotation`` enum, yaw in steps of 45 deg (0 none, 1 yaw 45, ... 7 yaw
  315), applied with ``rotate_3f`` (``ROTATION_YAW_45``: x' = (x - y)/sqrt 2, y' = (x + y)/sqrt 2, the
  same +yaw turn as ArduPilot's): it can undo a misalignment only to the nearest 45 deg.

Values are relative to what the vehicle flew with: ``current`` gives the autopilot parameters the
recording holds (PARAM_VALUE), otherwise each autopilot's default is assumed (0, or 1 for
``SENS_FLOW_SCALE``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import EFFECT_TYPES
from companion.diagnose.report import Action, Finding, Report
from companion.recordings.load import Recording

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


# ---------------------------------------------------------------------------------------------
# Actions: the values to set, in the user's terms (see the module docstring for the sources)

#: each autopilot's default for the parameters the actions set (what a recording without
#: PARAM_VALUE is assumed to have flown with)
AUTOPILOT_DEFAULTS = {"FLOW_FXSCALER": 0.0, "FLOW_FYSCALER": 0.0, "FLOW_ORIENT_YAW": 0.0, "EK3_FLOW_DELAY": 0.0,
                      "RNGFND1_OFFSET": 0.0, "SENS_FLOW_SCALE": 1.0, "SENS_FLOW_ROT": 0.0, "EKF2_OF_DELAY": 0.0}

#: companion config keys of the effects the config models: (section, key) per finding parameter
_COMPANION_KEYS = {"attitude_dynamics": {"omega_p": ("airframe", "omega_p_rad_s"), "zeta": ("airframe", "zeta")}}


def _sd(f: Finding, key: str) -> float:
    v = f.uncertainty.get(key, math.nan)
    return float(v) if v is not None else math.nan


def _ok(v: float) -> bool:
    return v is not None and math.isfinite(v)


def flow_scaler_permille(scale: float, current_permille: float = 0.0) -> float:
    """ArduPilot's FLOW_FxSCALER (parts per thousand) that undoes a flow read ``1/scale`` of the
    truth, given the one flown with: the new factor ``1 + 0.001 F`` is the old one times ``scale``."""
    return ((1.0 + 0.001 * current_permille) * scale - 1.0) * 1000.0


def orient_yaw_cd(yaw_rad: float, current_cd: float = 0.0) -> float:
    """ArduPilot's FLOW_ORIENT_YAW (centidegrees, in (-18000, 18000]) for a sensor turned a further
    ``yaw_rad`` (towards the right) from where the current value says it is."""
    cd = current_cd + math.degrees(yaw_rad) * 100.0
    cd = (cd + 18000.0) % 36000.0 - 18000.0
    return 18000.0 if cd == -18000.0 else cd


def px4_flow_rot(yaw_rad: float, current_rot: float = 0.0) -> int:
    """PX4's SENS_FLOW_ROT (0..7, yaw in 45 deg steps) nearest to the current one plus ``yaw_rad``."""
    return int(round(current_rot + math.degrees(yaw_rad) / 45.0)) % 8


def _companion_actions(f: Finding, profile: str, q_rad_per_count: float) -> list[Action]:
    p = f.parameters
    if f.effect == "flow_scale":
        if profile != "paper":
            return []  # flow in rad: the autopilot scales it (its own actions below)
        keys = [k for k in ("scale_x", "scale_y") if _ok(p.get(k, math.nan))]
        if not keys:
            return []
        mean = sum(p[k] for k in keys) / len(keys)
        sd = math.sqrt(sum(_sd(f, k) ** 2 for k in keys)) / len(keys)
        return [Action("companion", "flow_sensor.q_rad_per_count", q_rad_per_count * mean, q_rad_per_count * sd,
                       f.effect, "rad/count", "the config holds one Q: the mean of the axes"
                       if len(keys) == 2 else "")]
    if f.effect in _COMPANION_KEYS:
        return [Action("companion", f"{sec}.{key}", p[name], _sd(f, name), f.effect)
                for name, (sec, key) in _COMPANION_KEYS[f.effect].items() if _ok(p.get(name, math.nan))]
    if f.effect in CIRCUMSTANCES or f.effect in LOG_TIMING or f.effect not in EFFECT_TYPES:
        return []
    return [Action("companion", f"effects.{f.effect}.{k}", v, _sd(f, k), f.effect, f.unit(k),
                   "the simulator's model of this vehicle") for k, v in p.items() if _ok(v)]


def _ardupilot_actions(f: Finding, cur: dict[str, float]) -> list[Action]:
    p = f.parameters
    out: list[Action] = []
    if f.effect == "flow_scale":
        # MAVLink's X flow rate carries the paper's y axis: FLOW_FXSCALER corrects scale_y
        for name, key in (("FLOW_FXSCALER", "scale_y"), ("FLOW_FYSCALER", "scale_x")):
            s = p.get(key, math.nan)
            if _ok(s):
                c = cur[name]
                out.append(Action("ardupilot", name, round(flow_scaler_permille(s, c)),
                                  (1000.0 + c) * _sd(f, key), f.effect, "per mille",
                                  f"from {c:g}: the flow's factor 1 + 0.001 {name} times {s:.4g}"))
    elif f.effect == "flow_yaw_misalignment" and _ok(p.get("yaw", math.nan)):
        c = cur["FLOW_ORIENT_YAW"]
        out.append(Action("ardupilot", "FLOW_ORIENT_YAW", round(orient_yaw_cd(p["yaw"], c)),
                          math.degrees(_sd(f, "yaw")) * 100.0, f.effect, "cdeg", f"from {c:g}"))
    elif f.effect == "flow_delay" and _ok(p.get("delay", math.nan)):
        c = cur["EK3_FLOW_DELAY"]
        out.append(Action("ardupilot", "EK3_FLOW_DELAY", round(c + 1000.0 * p["delay"]), 1000.0 * _sd(f, "delay"),
                          f.effect, "ms", "the delay EKF3 assumes when it fuses the flow (EK3_SRCn_VELXY 5)"))
    elif f.effect == "flow_lever_arm":
        for axis in ("x", "y", "z"):
            v, sd = p.get(f"r{axis}", math.nan), _sd(f, f"r{axis}")
            if _ok(v) and _ok(sd):  # rx, ry are not fitted without yaw rate (no uncertainty)
                out.append(Action("ardupilot", f"FLOW_POS_{axis.upper()}", v, sd, f.effect, "m",
                                  "where the sensor is, body FRD: the EKF removes its lever arm"))
    elif f.effect == "range_offset" and _ok(p.get("offset", math.nan)):
        c = cur["RNGFND1_OFFSET"]
        out.append(Action("ardupilot", "RNGFND1_OFFSET", round(c - 100.0 * p["offset"]), 100.0 * _sd(f, "offset"),
                          f.effect, "cm", "a PWM rangefinder's (added to its distance in cm); an analog one's "
                          "is volts: lower it by offset / RNGFND1_SCALING; other drivers have none"))
    return out


def _px4_actions(f: Finding, cur: dict[str, float]) -> list[Action]:
    p = f.parameters
    out: list[Action] = []
    if f.effect == "flow_scale":
        keys = [k for k in ("scale_x", "scale_y") if _ok(p.get(k, math.nan))]
        if keys:
            c = cur["SENS_FLOW_SCALE"]
            mean = sum(p[k] for k in keys) / len(keys)
            sd = math.sqrt(sum(_sd(f, k) ** 2 for k in keys)) / len(keys)
            out.append(Action("px4", "SENS_FLOW_SCALE", c * mean, c * sd, f.effect, "",
                              "one factor for both axes: the mean"))
    elif f.effect == "flow_yaw_misalignment" and _ok(p.get("yaw", math.nan)):
        c = cur["SENS_FLOW_ROT"]
        rot = px4_flow_rot(p["yaw"], c)
        if rot != int(c) % 8:  # otherwise no 45 deg step undoes it: the sensor must be turned
            out.append(Action("px4", "SENS_FLOW_ROT", float(rot), math.degrees(_sd(f, "yaw")) / 45.0, f.effect,
                              "x 45 deg", "to the nearest 45 deg step"))
    elif f.effect == "flow_delay" and _ok(p.get("delay", math.nan)):
        c = cur["EKF2_OF_DELAY"]
        out.append(Action("px4", "EKF2_OF_DELAY", c + 1000.0 * p["delay"], 1000.0 * _sd(f, "delay"), f.effect,
                          "ms"))
    elif f.effect == "flow_lever_arm":
        for axis in ("x", "y", "z"):
            v, sd = p.get(f"r{axis}", math.nan), _sd(f, f"r{axis}")
            if _ok(v) and _ok(sd):
                out.append(Action("px4", f"EKF2_OF_POS_{axis.upper()}", v, sd, f.effect, "m"))
    return out


def recorded_parameters(rec: Recording) -> dict[str, float]:
    """The autopilot's parameters the recording holds (PARAM_VALUE from component 1 of any system,
    the last value of each name): what the vehicle flew with, for ``companion.diagnose.advice.actions``."""
    pv = rec.tables.get("PARAM_VALUE")
    if pv is None or len(pv) == 0 or "param_id" not in pv.fields:
        return {}
    out: dict[str, float] = {}
    order = np.argsort(pv.record, kind="stable")
    for i in order:
        if int(pv.compid[i]) != 1:
            continue
        v = float(pv["param_value"][i])
        if np.isfinite(v):
            out[str(pv["param_id"][i])] = v
    return out


def actions(report: Report, *, profile: str, q_rad_per_count: float,
            current: dict[str, float] | None = None) -> list[Action]:
    """What to set for each significant finding of ``report``: the companion's config keys, and for
    a recording in the ``ardupilot`` (``px4``) profile ArduPilot's (PX4's) parameters.

    ``profile`` is the recording's sensor profile; ``q_rad_per_count`` the nominal Q the
    report's ``flow_scale`` is relative to; ``current`` the autopilot parameters the vehicle flew
    with (from the recording's PARAM_VALUE; missing ones are the autopilot's defaults)."""
    cur = {**AUTOPILOT_DEFAULTS, **{k: float(v) for k, v in (current or {}).items() if k in AUTOPILOT_DEFAULTS}}
    out: list[Action] = []
    for f in report.significant():
        out += _companion_actions(f, profile, q_rad_per_count)
        if profile == "ardupilot":
            out += _ardupilot_actions(f, cur)
        elif profile == "px4":
            out += _px4_actions(f, cur)
    return out
