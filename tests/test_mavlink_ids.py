"""``companion.mavlink_ids`` holds the MAVLink numbers once (issue 13): every value equals
pymavlink's dialect, and no other module defines them again."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion import mavlink_ids as ids

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted(p for pkg in ("companion", "simvehicle") for p in (ROOT / pkg).rglob("*.py")
                 if p.name != "mavlink_ids.py")
NAMES = sorted(n for n in vars(ids) if n.isupper())


@pytest.mark.parametrize("name", [n for n in NAMES if n.startswith("MAV_")])
def test_dialect_named_values_equal_pymavlinks(name):
    assert getattr(ids, name) == getattr(mav, name)


def test_project_named_values_equal_the_dialects():
    assert ids.COMPANION_COMPONENT == mav.MAV_COMP_ID_ONBOARD_COMPUTER == 191
    assert ids.GUIDED_NOGPS == mav.COPTER_MODE_GUIDED_NOGPS == 20
    assert ids.DOWNWARD == mav.MAV_SENSOR_ROTATION_PITCH_270 == 25
    assert ids.BODY_FRAMES == (mav.MAV_FRAME_BODY_NED, mav.MAV_FRAME_BODY_OFFSET_NED, mav.MAV_FRAME_BODY_FRD)
    assert ids.NOT_VEHICLE_TYPES == (mav.MAV_TYPE_GCS, mav.MAV_TYPE_ONBOARD_CONTROLLER)


def _module_constants(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = set()
    for node in tree.body:
        if isinstance(node, ast.Assign):
            out |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            out.add(node.target.id)
    return out


def test_no_module_defines_an_id_again():
    again = {f"{p.relative_to(ROOT)}: {n}" for p in SOURCES for n in _module_constants(p) & set(NAMES)}
    assert not again


def test_the_companion_component_is_never_a_bare_191():
    bare = [f"{p.relative_to(ROOT)}:{node.lineno}" for p in SOURCES
            for node in ast.walk(ast.parse(p.read_text(encoding="utf-8")))
            if isinstance(node, ast.Constant) and type(node.value) is int and node.value == ids.COMPANION_COMPONENT]
    assert not bare
