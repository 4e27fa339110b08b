"""``python -m companion ardupilot-script [--out DIR]``: the watchdog applet for ArduCopter.

The applet (``companion/ardupilot/flowhold_watchdog.lua``, read through ``importlib.resources``)
runs on the autopilot, so it outlives the companion: while the vehicle is armed in GUIDED_NOGPS
and the companion's SET_ATTITUDE_TARGETs (component 191) stop for ``FHW_TIMEOUT`` seconds, it
says so (STATUSTEXT CRITICAL) and switches to ``FHW_MODE`` (LAND by default). docs/ardupilot.md
says how to install it and what it cannot cover. The simulated vehicle has the same behaviour as
its ``FHW_*`` parameters (``simvehicle.server.server``), so the end-to-end tests can kill the companion.
"""

from __future__ import annotations

import sys
from importlib import resources
from pathlib import Path
from typing import Any

from companion.errors import output_error

SCRIPT_NAME = "flowhold_watchdog.lua"


def script_text() -> str:
    """The applet's Lua source."""
    return resources.files("companion").joinpath("ardupilot", SCRIPT_NAME).read_text(encoding="utf-8")


def run_cli(args: Any) -> int:
    """Print the applet, or write it into ``--out`` (created if missing) and say how to install it."""
    text = script_text()
    if args.out is None:
        sys.stdout.write(text)
        return 0
    path = Path(args.out) / SCRIPT_NAME
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise output_error("--out", args.out, exc) from None
    print(f"flowhold: wrote {path}: copy it into the vehicle's scripts folder (APM/scripts on the SD card), "
          "set SCR_ENABLE 1 and reboot (docs/ardupilot.md, \"The watchdog applet\")")
    return 0
