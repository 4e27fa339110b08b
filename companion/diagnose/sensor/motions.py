"""What the makers of known recordings say was done with the sensor: the documented motions,
by file name (data/real/stampfly/README.md). Data, not method: a recording named here has its
legs measured against ``leg_m`` (``legs.LegScaleFit``); any other has no scale constraint."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DocumentedMotion:
    """What a recording's maker says was done: straight legs of ``leg_m`` in the body
    directions of ``pattern`` (repeated when ``cyclic``), yaw held."""

    leg_m: float
    pattern: tuple[str, ...]
    cyclic: bool
    documented: bool
    source: str


#: Documented motions of known recordings, by file name, also gzip-compressed (data/real/stampfly/README.md).
DOCUMENTED_MOTIONS: dict[str, DocumentedMotion] = {
    "flow_test_x_axis_01.csv": DocumentedMotion(
        0.20, ("+x", "-x"), False, True,
        "maker's plan: single-axis X test, forward 20 cm, pause, back 20 cm"),
    "flow_test_square_01_final.csv": DocumentedMotion(
        0.20, ("+y", "-x", "-y", "+x"), True, True,
        "maker's plan: clockwise square, 20 cm sides, yaw held, from the front-left corner"),
    "square01_13s.csv": DocumentedMotion(
        0.20, ("+y", "-x", "-y", "+x"), True, False,
        "undocumented: one clockwise loop in the data; 20 cm sides assumed from the plan"),
    "square_30cm.csv": DocumentedMotion(
        0.20, ("+y", "-x", "-y", "+x"), True, False,
        "undocumented: about three clockwise loops; 20 cm sides assumed (maker's notes: 20 cm square at 30 cm)"),
    "square_30cm_air.csv": DocumentedMotion(
        0.20, ("+y", "-x", "-y", "+x"), True, False,
        "undocumented: about three clockwise loops; 20 cm sides assumed (maker's notes: 20 cm square at 30 cm)"),
}


def leg_reference(m: DocumentedMotion) -> str:
    """``documented 20 cm`` where the maker documents the legs, ``assumed 20 cm`` where they are assumed."""
    return f"{'documented' if m.documented else 'assumed'} {100 * m.leg_m:.0f} cm"
