"""The mismatch report of CONVENTIONS.md (``diagnose --json``), as typed objects.

Both diagnose modes (closed-loop flights and sensor-only recordings) fill a ``Report`` and
write it with ``Report.write_json``; the JSON layout is the contract read by outside checks.
Times are seconds from the first record of the recording.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: units of CONVENTIONS.md's parameter keys (SI; scales relative to the nominal Q), for labels and reports
PARAMETER_UNITS = {"b": "N s/m", "bias_x": "rad/s", "bias_y": "rad/s", "scale_x": "x nominal Q",
                   "scale_y": "x nominal Q", "delay": "s", "yaw": "rad", "omega_p": "rad/s", "zeta": "1",
                   "offset": "m", "fx": "N", "fy": "N", "start_s": "s", "end_s": "s", "gain": "1",
                   "c": "N s^2/m^2", "rx": "m", "ry": "m", "rz": "m", "tau": "s"}


@dataclass
class Window:
    channel: str
    start_s: float
    end_s: float

    def to_json(self) -> dict[str, Any]:
        return {"channel": self.channel, "start_s": _num(self.start_s), "end_s": _num(self.end_s)}


@dataclass
class Fit:
    heldout_rms_before: float
    heldout_rms_after: float

    @property
    def improvement_pct(self) -> float:
        if self.heldout_rms_before <= 0:
            return 0.0
        return 100.0 * (self.heldout_rms_before - self.heldout_rms_after) / self.heldout_rms_before

    def to_json(self) -> dict[str, Any]:
        return {
            "heldout_rms_before": _num(self.heldout_rms_before),
            "heldout_rms_after": _num(self.heldout_rms_after),
            "improvement_pct": _num(self.improvement_pct),
        }


@dataclass
class Finding:
    """One effect tried. ``significant`` says whether it earned its parameters."""

    effect: str
    significant: bool
    parameters: dict[str, float]
    uncertainty: dict[str, float]
    explanation: str
    where: list[Window] = field(default_factory=list)
    fit: Fit | None = None
    #: extra evidence for the human report (information criteria, notes); also written to JSON
    evidence: dict[str, Any] = field(default_factory=dict)
    #: other effects that explain the recording as well (this flight cannot tell them apart):
    #: ``{"effect", "parameters", "cv_t"}`` each, cv_t the held-out advantage of this one (< 2)
    alternatives: list[dict[str, Any]] = field(default_factory=list)

    def unit(self, key: str) -> str:
        """The unit of parameter ``key``: the finding's own (``evidence["units"]``, for parameters
        outside CONVENTIONS.md such as a count of readings), else CONVENTIONS.md's; "" for a
        dimensionless one or one whose name carries its unit (``longest_gap_s``)."""
        own = self.evidence.get("units", {})
        if key in own:
            return str(own[key])
        unit = PARAMETER_UNITS.get(key, "")
        return "" if unit == "1" else unit

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "effect": self.effect,
            "significant": bool(self.significant),
            "parameters": {k: _num(v) for k, v in self.parameters.items()},
            "uncertainty": {k: _num(v) for k, v in self.uncertainty.items()},
            "explanation": self.explanation,
            "where": [w.to_json() for w in self.where],
            "fit": self.fit.to_json() if self.fit else
            {"heldout_rms_before": None, "heldout_rms_after": None, "improvement_pct": None},
        }
        if self.alternatives:
            out["alternatives"] = _clean(self.alternatives)
        if self.evidence:
            out["evidence"] = _clean(self.evidence)
        return out


@dataclass
class Unexplained:
    channel: str
    start_s: float
    end_s: float
    rms: float
    #: best-fitting candidate term from sparse regression, in words (optional)
    best_term: str | None = None
    #: the channel's noise scale (same unit as ``rms``), when known
    noise: float | None = None

    @property
    def times_noise(self) -> float:
        return self.rms / self.noise if self.noise else float("nan")

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"channel": self.channel, "start_s": _num(self.start_s),
                               "end_s": _num(self.end_s), "rms": _num(self.rms)}
        if self.best_term is not None:
            out["best_term"] = self.best_term
        if self.noise is not None:
            out["noise"] = _num(self.noise)
        return out


@dataclass(frozen=True)
class Action:
    """One thing to set, in the user's terms (``diagnose --json``'s ``actions``).

    ``system``: ``"companion"`` (a key of the companion's TOML config, ``section.key``),
    ``"ardupilot"`` or ``"px4"`` (an autopilot parameter, in that autopilot's own unit);
    ``value`` the value to set, computed from the fit; ``sigma`` its 1-sigma uncertainty
    propagated from the fit's (NaN when the fit gives none); ``because`` the effect it undoes.
    ``unit`` and ``note`` are for human reports only (not in the JSON)."""

    system: str
    parameter: str
    value: float
    sigma: float
    because: str
    unit: str = ""
    note: str = ""

    def to_json(self) -> dict[str, Any]:
        return {"system": self.system, "parameter": self.parameter, "value": _num(self.value),
                "sigma": _num(self.sigma), "because": self.because}


@dataclass
class Report:
    recording: str
    baseline_rms: dict[str, float] = field(default_factory=dict)
    findings: list[Finding] = field(default_factory=list)
    unexplained: list[Unexplained] = field(default_factory=list)
    #: what was skipped or could not be judged, one line each
    notes: list[str] = field(default_factory=list)
    mode: str = "flight"  # "flight" (closed loop) or "sensor" (sensor-only)
    #: the first line a reader needs, in plain words (``diagnose`` writes it)
    headline: str = ""
    #: what to set, per finding (``companion.diagnose.advice.actions``)
    actions: list[Action] = field(default_factory=list)

    def significant(self) -> list[Finding]:
        return [f for f in self.findings if f.significant]

    def to_json(self) -> dict[str, Any]:
        return {
            "recording": self.recording,
            "mode": self.mode,
            "headline": self.headline,
            "baseline": {"channels": {k: {"rms": _num(v)} for k, v in self.baseline_rms.items()}},
            "findings": [f.to_json() for f in self.findings],
            "unexplained": [u.to_json() for u in self.unexplained],
            "notes": list(self.notes),
            "actions": [a.to_json() for a in self.actions],
        }

    def write_json(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=2, allow_nan=False) + "\n")


def _num(x: Any) -> float | None:
    """JSON has no NaN: a value that could not be computed is written as null."""
    if x is None:
        return None
    xf = float(x)
    return xf if math.isfinite(xf) else None


def _clean(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, (int, float)) or hasattr(obj, "__float__"):
        return _num(obj)
    return str(obj)
