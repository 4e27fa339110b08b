"""``make demo`` (scripts/demo.py) tells the truth about where to watch it (issue 14)."""

from __future__ import annotations

import re
import subprocess
import time

from loop_helpers import PY, REPO, Gcs, free_udp_port


def test_demo_prints_the_address_a_ground_station_can_watch_it_on(tmp_path):
    """The demo said "watch it live ... UDP 14550" while its lockstep vehicle was on another port. It
    now prints the vehicle's true address while it runs, and a ground station sent there is served
    (the vehicle's HEARTBEAT, then the companion's)."""
    port = free_udp_port()
    log = tmp_path / "demo.log"
    with open(log, "w") as fh:
        p = subprocess.Popen([PY, "scripts/demo.py", "--out", str(tmp_path / "demo"), "--port", str(port)], cwd=REPO,
                             stdout=fh, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while not re.search(r"watch it live while it flies: mavproxy\.py --master=udpout:127\.0\.0\.1:(\d+)",
                            log.read_text()):
            assert p.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        m = re.search(r"--master=udpout:127\.0\.0\.1:(\d+)", log.read_text())
        assert int(m.group(1)) == port
        gcs = Gcs(int(m.group(1)))
        try:
            gcs.wait_vehicle(timeout_s=20)
            gcs.recv("HEARTBEAT", timeout_s=20, cond=lambda msg: msg.get_srcComponent() == 191)
        finally:
            gcs.close()
        assert p.wait(timeout=240) == 0, log.read_text()
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    text = log.read_text()
    assert "UDP 14550" not in text.split("to watch a flight in real time")[0]
    assert re.search(r"vehicle: python -m simvehicle serve --lockstep on udp 127\.0\.0\.1:(\d+)", text).group(1) \
        == str(port)
