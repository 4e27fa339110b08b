"""Issue 18 (c): the watchdog that outlives the companion, in process.

- The ArduCopter applet (``companion/ardupilot/flowhold_watchdog.lua``), as
  ``python -m companion ardupilot-script`` writes it, run under mocked ArduPilot bindings by a stock
  Lua 5.4 (``tests/lua/watchdog_spec.lua``): a mode switch only armed in GUIDED_NOGPS, only after
  ``FHW_TIMEOUT`` without the companion's SET_ATTITUDE_TARGET, once, with its STATUSTEXT; nothing while
  the companion commands.
- The simulated vehicle's copy of it (``FHW_*`` parameters), frame by frame in simulated time, beside
  its GUID_TIMEOUT levelling.

``tests/test_watchdog_e2e.py`` kills a real companion beside the simulated vehicle.
"""

from __future__ import annotations

import math
import shutil
import subprocess
from pathlib import Path

import pytest

from companion.ardupilot_script import SCRIPT_NAME, script_text
from companion.cli import main
from companion.mavlink import link, outbound

mav = link.mav
LUA = shutil.which("lua5.4")
SPEC = Path(__file__).resolve().parent / "lua" / "watchdog_spec.lua"


def test_ardupilot_script_prints_or_writes_the_applet(tmp_path, capsys):
    assert main(["ardupilot-script"]) == 0
    printed = capsys.readouterr().out
    assert printed == script_text() and "FHW_TIMEOUT" in printed and printed.rstrip().endswith(
        "return protected_update, UPDATE_MS")
    out = tmp_path / "scripts"  # created
    assert main(["ardupilot-script", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert (out / SCRIPT_NAME).read_text() == printed
    assert str(out / SCRIPT_NAME) in said and "SCR_ENABLE 1" in said
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["ardupilot-script", "--out", str(blocker / "x")]) == 2  # a usage error, one line
    assert capsys.readouterr().err.startswith("error: --out: cannot write")


@pytest.mark.skipif(LUA is None, reason="needs a stock Lua 5.4 interpreter (Debian: apt install lua5.4)")
def test_the_applet_under_mocked_ardupilot_bindings(tmp_path):
    assert main(["ardupilot-script", "--out", str(tmp_path)]) == 0  # what a user installs
    run = subprocess.run([LUA, str(SPEC), str(tmp_path / SCRIPT_NAME)], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "11 scenarios passed" in run.stdout, run.stdout


# ---------------------------------------------------------------------------------------------
# The simulated vehicle's copy


def _from(enc, msg):
    return mav.MAVLink(None).decode(bytearray(msg.pack(enc)))


def _texts(msgs) -> list[tuple[str, int]]:
    return [(m.text, m.severity) for m in msgs if m.get_type() == "STATUSTEXT"]


def _fly(paper_cfg, *, fhw: dict[str, float], commands_until_s: float, heartbeats_until_s: float,
         until_s: float = 4.0):
    """A vehicle armed in GUIDED_NOGPS, its companion sending a lean command each frame and a
    HEARTBEAT each second until the given times. Returns (vehicle, [(t, messages the watchdog sent)],
    [(t, active roll, pitch)])."""
    from simvehicle.server.server import StreamSchedule, Vehicle

    v = Vehicle(paper_cfg)
    for name, value in fhw.items():
        v.set_param(name, value)
    gcs = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    comp = mav.MAVLink(None, srcSystem=1, srcComponent=outbound.COMPANION_COMPONENT)
    streams = StreamSchedule(v.T)
    v.handle(_from(gcs, link.command_long(gcs, 1, 1, mav.MAV_CMD_DO_SET_MODE, 1, link.GUIDED_NOGPS)), streams)
    v.handle(_from(gcs, link.command_long(gcs, 1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)), streams)
    assert v.armed and v.guided
    said, active = [], []
    while v.sim.t_s < until_s:
        t = v.sim.t_s
        out = v.frame()
        extra = [m for name, m in out.messages if name is None]
        if extra:
            said.append((t, extra))
        if t <= commands_until_s + 1e-9:
            v.handle(_from(comp, outbound.set_attitude_target(comp, int(round(t * 1e3)), 1, 0.05, -0.05, 0.0)),
                     streams)
        if t <= heartbeats_until_s + 1e-9 and round(t / v.T) % 50 == 0:
            v.handle(_from(comp, outbound.heartbeat(comp)), streams)
        v.advance()
        active.append((v.sim.t_s, *v.sim.u_active))
    return v, said, active


def test_the_simulated_vehicle_levels_then_lands_when_the_commands_stop(paper_cfg):
    """Commands until 2.00 s: the vehicle levels at GUID_TIMEOUT (0.5 s) and the watchdog switches
    to LAND at the first frame more than FHW_TIMEOUT (1 s) after the last command, once."""
    v, said, active = _fly(paper_cfg, fhw={"FHW_ENABLE": 1}, commands_until_s=2.0, heartbeats_until_s=2.0)
    assert [t for t, _ in said] == [pytest.approx(3.02)]
    msgs = said[0][1]
    assert _texts(msgs) == [("flowhold watchdog: companion lost 1.0 s: LAND", mav.MAV_SEVERITY_CRITICAL)]
    assert [m.custom_mode for m in msgs if m.get_type() == "HEARTBEAT"] == [9]
    assert v.custom_mode == 9 and v.armed
    level = [t for t, r, p in active if (r, p) == (0.0, 0.0)]
    leaning = [t for t, r, p in active if (r, p) != (0.0, 0.0)]
    assert min(level) == pytest.approx(2.0 + 0.5 + 2 * v.T)  # activated from the frame after 2.52 s
    assert max(leaning) < min(level)


def test_the_simulated_watchdog_waits_while_the_companion_commands_and_says_a_silent_loop(paper_cfg):
    v, said, _ = _fly(paper_cfg, fhw={"FHW_ENABLE": 1}, commands_until_s=9.0, heartbeats_until_s=9.0, until_s=8.0)
    assert said == [] and v.guided
    # the companion's process alive (HEARTBEAT) but its commands stopped
    v, said, _ = _fly(paper_cfg, fhw={"FHW_ENABLE": 1, "FHW_TIMEOUT": 2.0}, commands_until_s=1.0,
                      heartbeats_until_s=9.0)
    assert [(t, _texts(m)) for t, m in said] == [
        (pytest.approx(3.02), [("flowhold watchdog: no commands 2.0 s: LAND", mav.MAV_SEVERITY_CRITICAL)])]
    # not installed (the default, as a stock ArduCopter): levels, and nothing more
    v, said, active = _fly(paper_cfg, fhw={}, commands_until_s=1.0, heartbeats_until_s=1.0)
    assert said == [] and v.guided and active[-1][1:] == (0.0, 0.0)


def test_a_mode_the_simulated_vehicle_refuses_gives_land(paper_cfg):
    v, said, _ = _fly(paper_cfg, fhw={"FHW_ENABLE": 1, "FHW_MODE": 17}, commands_until_s=1.0,
                      heartbeats_until_s=1.0)
    assert _texts(said[0][1]) == [("flowhold watchdog: companion lost 1.0 s: BRAKE", mav.MAV_SEVERITY_CRITICAL),
                                  ("flowhold watchdog: BRAKE refused", mav.MAV_SEVERITY_CRITICAL),
                                  ("flowhold watchdog: LAND instead", mav.MAV_SEVERITY_CRITICAL)]
    assert v.custom_mode == 9 and len(said) == 1
    assert math.isclose(said[0][0], 2.02)
