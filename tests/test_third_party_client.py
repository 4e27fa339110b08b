"""A third-party MAVLink client sees the simulated vehicle: MAVProxy (from PyPI) connects,
detects an ArduCopter-like quadrotor in STABILIZE, downloads its parameters, arms it, and
records a telemetry log that pymavlink reads back with the vehicle's attitude in it.

MAVProxy is an optional test dependency (``pip install MAVProxy``); without it the test is
skipped and says so. MAVProxy is told not to try MAVFTP for the parameters (the vehicle does
not speak it; MAVProxy would fall back to PARAM_REQUEST_LIST after its timeouts). Run time:
about 10 s.
"""

from __future__ import annotations

import re
import time

import pytest
from loop_helpers import Procs

pytest.importorskip("MAVProxy", reason="MAVProxy is not installed (pip install MAVProxy) - the third-party "
                    "client test needs it")

from pymavlink import mavutil  # noqa: E402

from simvehicle.server.server import param_specs  # noqa: E402


def test_mavproxy_connects_sees_and_arms_the_vehicle(tmp_path, paper_cfg):
    n_params = len(param_specs(paper_cfg))
    with Procs(tmp_path) as procs:
        veh, port = procs.vehicle()
        mp = procs.start("-m", "MAVProxy.mavproxy", f"--master=udpout:127.0.0.1:{port}", "--non-interactive",
                         "--cmd=set param_ftp 0; param fetch; arm throttle", f"--state-basedir={tmp_path}",
                         name="mavproxy", cwd=tmp_path)
        mp.wait_for(rf"Received {n_params} parameters", timeout_s=90)
        mp.wait_for("ARMED", timeout_s=30)
        veh.wait_for("armed STABILIZE", timeout_s=30)
        time.sleep(1.0)
        mp.stop()
    out = mp.text()
    assert "Detected vehicle 1:1" in out
    assert re.search(r"Mode STABILIZE", out)  # ArduCopter's custom_mode 0, decoded by MAVProxy
    assert "AP: Arming motors" in out  # the vehicle's STATUSTEXT
    logs = list(tmp_path.rglob("mav.tlog"))
    assert logs, out
    log = mavutil.mavlink_connection(str(logs[0]))
    try:
        att = log.recv_match(type="ATTITUDE", condition="ATTITUDE.get_srcSystem() == 1")
    finally:
        log.close()  # an unclosed file is a ResourceWarning, an error for whichever test is running at GC
    assert att is not None and abs(att.roll) < 1e-6  # disarmed, level
