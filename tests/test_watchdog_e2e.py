"""Issue 18 (c) end to end: a killed companion (SIGKILL) beside the simulated vehicle with the
watchdog applet's behaviour on (``FHW_ENABLE`` 1), in real time over UDP, in a 2 N wind on each axis.

From the vehicle's recording (stamped with its own clock, so the load of the machine does not move
the figures): while the companion commands, the vehicle stays in GUIDED_NOGPS and the watchdog says
nothing; after the companion's last SET_ATTITUDE_TARGET, the vehicle levels at GUID_TIMEOUT (0.5 s)
and, at FHW_TIMEOUT (1 s), says ``flowhold watchdog: companion lost 1.0 s: LAND`` (CRITICAL) and
switches to LAND (HEARTBEAT custom_mode 9). Each to within the frame the vehicle checks on.

Run time (2 shared cores): about 15 s.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from loop_helpers import Gcs, Procs

from companion.mavlink.outbound import quaternion_to_euler
from companion.recordings.load import load_recording

WIND_N = 2.0
LEAN_RAD = math.atan(WIND_N / (2.3 * 9.81))
T_S = 0.02
GUID_TIMEOUT_S, FHW_TIMEOUT_S = 0.5, 1.0
STAMP_TOL_S = 2e-6
LAND = 9


def _wait_leaning(gcs: Gcs, timeout_s: float = 90.0) -> None:
    deadline = time.monotonic() + timeout_s
    run = 0
    while run < 25:
        at = gcs.recv("ATTITUDE_TARGET", cond=lambda m: m.get_srcComponent() == 1, timeout_s=timeout_s)
        roll, pitch, _ = quaternion_to_euler(at.q)
        run = run + 1 if abs(pitch + LEAN_RAD) < 0.2 * LEAN_RAD and abs(roll + LEAN_RAD) < 0.2 * LEAN_RAD else 0
        assert time.monotonic() < deadline, "never settled on the lean into the wind"


@pytest.fixture(scope="module")
def killed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("watchdog")
    vtlog = tmp / "vehicle.tlog"
    with Procs(tmp) as procs:
        veh, port = procs.vehicle("--tlog", str(vtlog))
        comp = procs.companion(port, "--arm", "--quiet")
        gcs = Gcs(port)
        try:
            gcs.wait_vehicle()
            gcs.quiet({"ATTITUDE_TARGET": 50.0})
            assert gcs.set_param("FHW_ENABLE", 1).param_value == 1
            assert gcs.set_param("SIM_WIND_FX", -WIND_N).param_value == -WIND_N
            assert gcs.set_param("SIM_WIND_FY", WIND_N).param_value == WIND_N
            comp.wait_for("in control")
            _wait_leaning(gcs)
            gcs.wait_time(gcs.vehicle_time_s + 2.0)  # the companion healthy for a while: no action
            comp.kill()  # SIGKILL: nothing is said, nothing more is sent
            gcs.wait_text("flowhold watchdog:")
            gcs.wait_time(gcs.vehicle_time_s + 0.5)
        finally:
            gcs.close()
        assert veh.stop() == 0
    return load_recording(vtlog), veh.text()


def test_a_killed_companion_levels_then_lands(killed):
    rec, console = killed
    att = rec.table("ATTITUDE").from_sender(sysid=1, compid=1)
    epoch = float(att.t_s[0] - att["time_boot_ms"][0] * 1e-3)  # the recording: epoch + the vehicle's clock
    clock = lambda table: table.t_s - epoch  # noqa: E731

    sat = rec.table("SET_ATTITUDE_TARGET").from_sender(sysid=1, compid=191)
    t_last = float(clock(sat).max())
    t_first = float(clock(sat).min())
    assert t_last - t_first > 3.0  # it commanded for seconds before it was killed

    target = rec.table("ATTITUDE_TARGET").from_sender(sysid=1, compid=1)
    ang = np.array([quaternion_to_euler(q)[:2] for q in target["q"]])
    t_target = clock(target)
    level = np.all(ang == 0.0, axis=1)
    after = t_target > t_last
    t_level = float(t_target[after & level].min())
    assert np.all(~level[after & (t_target < t_level)])  # leaning until then
    # STAMP_TOL_S: a difference of two .tlog stamps, each rounded to the microsecond and held as
    # float64 seconds near the simulated epoch (0.24 us apart there): 2 x (0.5 + 0.24) us < 2 us
    assert GUID_TIMEOUT_S < t_level - t_last <= GUID_TIMEOUT_S + 2 * T_S + STAMP_TOL_S, t_level - t_last

    st = rec.table("STATUSTEXT").from_sender(sysid=1, compid=1)
    said = [(float(t), str(x), int(s)) for t, x, s in zip(clock(st), st["text"], st["severity"], strict=True)
            if "flowhold watchdog" in str(x)]
    assert [(x, s) for _t, x, s in said] == [("flowhold watchdog: companion lost 1.0 s: LAND", 2)], said
    assert FHW_TIMEOUT_S < said[0][0] - t_last <= FHW_TIMEOUT_S + T_S + STAMP_TOL_S, said[0][0] - t_last

    hb = rec.table("HEARTBEAT").from_sender(sysid=1, compid=1)
    modes = np.asarray(hb["custom_mode"])
    t_hb = clock(hb)
    t_land = float(t_hb[modes == LAND].min())
    assert t_land == pytest.approx(said[0][0], abs=1e-6)  # the mode change goes out with the text
    assert np.all(modes[(t_hb >= t_first) & (t_hb < t_land)] == 20)  # GUIDED_NOGPS until then
    assert "armed LAND" in console and "(flowhold watchdog)" in console
