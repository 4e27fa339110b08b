"""`make demo`: the closed loop over MAVLink, as a user runs it, then its plots.

Starts two processes on loopback, as in docs/loop.md:

    python -m simvehicle serve --lockstep --listen 127.0.0.1:PORT --tlog OUT/vehicle.tlog
    python -m companion run --connect udpout:127.0.0.1:PORT --arm --tlog OUT/companion.tlog

PORT is a free port (``--port`` picks one); the demo prints it with the command that watches the
flight live from a ground station while it runs (MAVProxy ``--master=udpout:127.0.0.1:PORT``).

and acts as the ground station itself (a third MAVLink peer): it flies a 30 s profile on the
vehicle's clock - hover, a step to 1.5 m/s forward and 0.5 m/s left at 2 s, hold (zero) from
12 s, and a 4 N headwind injected by PARAM_SET SIM_WIND_FX = -4 at 18 s (Fig. 17's gust) - then
stops both, reads the vehicle's recording (companion.recordings.load.load_recording, via
simvehicle.server.server.recording_run) and plots truth, estimate, setpoint, commands and flow counts.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from pymavlink import mavutil  # noqa: E402

import companion.mavlink.link  # noqa: E402 - MAVLink 2 for every connection opened below
from companion.mavlink.outbound import VELOCITY_TYPE_MASK  # noqa: E402

mav = companion.mavlink.link.mav
DURATION_S = 30.0
#: (from vehicle time s, setpoint vx, vy m/s): the profile the ground station flies
PROFILE = ((0.0, 0.0, 0.0), (2.0, 1.5, -0.5), (12.0, 0.0, 0.0))
GUST_AT_S, GUST_N = 18.0, -4.0
WALL_LIMIT_S = 110.0


def _start(args: list[str], log: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, *args], cwd=REPO, env=env, stdout=log.open("w"),
                            stderr=subprocess.STDOUT)


def _wait_port(proc: subprocess.Popen, log: Path, timeout_s: float = 60.0) -> int:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = re.search(r"listening on udp 127\.0\.0\.1:(\d+)", log.read_text())
        if m:
            return int(m.group(1))
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    raise RuntimeError(f"the vehicle did not start:\n{log.read_text()[-2000:]}")


def watch_lines(port: int) -> list[str]:
    """How to watch this run live: the vehicle's true address (it serves any peer that sends to it)."""
    return [f"watch it live while it flies: mavproxy.py --master=udpout:127.0.0.1:{port}",
            f"  (QGroundControl: a UDP comm link with server 127.0.0.1:{port}; lockstep runs faster than "
            "real time: docs/loop.md, \"Watching with MAVProxy or QGroundControl\")"]


def gust_force(t_s: float) -> tuple[float, float]:
    """The external force the ground station switches on at GUST_AT_S (SIM_WIND_FX, body x, N),
    as a function of time: what loop.png marks."""
    return (GUST_N, 0.0) if t_s >= GUST_AT_S else (0.0, 0.0)


def _setpoint_at(t_s: float) -> tuple[float, float]:
    vx = vy = 0.0
    for t0, sx, sy in PROFILE:
        if t_s >= t0:
            vx, vy = sx, sy
    return vx, vy


def _fly_ground_station(port: int, vehicle: subprocess.Popen) -> None:
    """Send the setpoint profile and the gust on the vehicle's clock until it stops."""
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190,
                                     dialect="ardupilotmega")
    try:
        gcs.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE)
        for name in ("RAW_IMU", "DISTANCE_SENSOR", "OPTICAL_FLOW", "ATTITUDE", "ATTITUDE_TARGET", "SYS_STATUS"):
            msg_id = getattr(mav, f"MAVLINK_MSG_ID_{name}")
            gcs.mav.send(companion.mavlink.link.set_message_interval(gcs.mav, 1, msg_id, -1))
        gcs.mav.send(companion.mavlink.link.set_message_interval(gcs.mav, 1, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                                                                 0.1))
        gust_sent = False
        last = None
        deadline = time.monotonic() + WALL_LIMIT_S
        next_hb = 0.0
        while vehicle.poll() is None and time.monotonic() < deadline:
            if time.monotonic() > next_hb:
                gcs.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE)
                next_hb = time.monotonic() + 1.0
            msg = gcs.recv_match(blocking=True, timeout=0.2)
            if msg is None:
                continue
            if msg.get_type() == "STATUSTEXT":
                print(f"  [{msg.get_srcComponent()}] {msg.text}")
            if msg.get_type() != "LOCAL_POSITION_NED" or msg.get_srcComponent() != 1:
                continue
            t = msg.time_boot_ms * 1e-3
            sp = _setpoint_at(t)
            if sp != last:
                print(f"  t = {t:5.2f} s: velocity setpoint {sp[0]:+.1f}, {sp[1]:+.1f} m/s (body frame)")
                last = sp
            gcs.mav.set_position_target_local_ned_send(0, 1, 191, mav.MAV_FRAME_BODY_FRD, VELOCITY_TYPE_MASK,
                                                       0, 0, 0, sp[0], sp[1], 0, 0, 0, 0, 0, 0)
            if t >= GUST_AT_S and not gust_sent:
                gcs.mav.param_set_send(1, 1, b"SIM_WIND_FX", GUST_N, mav.MAV_PARAM_TYPE_REAL32)
                print(f"  t = {t:5.2f} s: PARAM_SET SIM_WIND_FX = {GUST_N:g} N (a gust from ahead)")
                gust_sent = True
    finally:
        gcs.close()


def _stop(proc: subprocess.Popen, sig: int = signal.SIGINT) -> None:
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=15)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/demo", help="folder for the recordings and the plot (default out/demo)")
    ap.add_argument("--port", type=int, default=0,
                    help="UDP port of the vehicle on 127.0.0.1, for a ground station to watch (default: a free one)")
    args = ap.parse_args()
    sys.stdout.reconfigure(line_buffering=True)  # each line as it happens, also into a pipe or a log
    if not 0 <= args.port <= 65535:
        ap.error(f"--port must be in 0..65535, got {args.port}")
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    vtlog, ctlog, png = out / "vehicle.tlog", out / "companion.tlog", out / "loop.png"
    vlog, clog = out / "vehicle.log", out / "companion.log"
    t0 = time.monotonic()
    vehicle = _start(["-m", "simvehicle", "serve", "--lockstep", "--listen", f"127.0.0.1:{args.port}", "--duration",
                      str(DURATION_S), "--tlog", str(vtlog)], vlog)
    comp = None
    try:
        port = _wait_port(vehicle, vlog)
        print(f"vehicle: python -m simvehicle serve --lockstep on udp 127.0.0.1:{port}")
        comp = _start(["-m", "companion", "run", "--connect", f"udpout:127.0.0.1:{port}", "--arm", "--quiet",
                       "--tlog", str(ctlog)], clog)
        print(f"companion: python -m companion run --connect udpout:127.0.0.1:{port} --arm")
        for line in watch_lines(port):
            print(line, flush=True)
        _fly_ground_station(port, vehicle)
        vehicle.wait(timeout=30)
    finally:
        _stop(vehicle)
        if comp is not None:
            _stop(comp)
    if vehicle.returncode != 0 or comp is None or comp.returncode != 0:
        print(f"the loop failed; see {vlog} and {clog}", file=sys.stderr)
        return 1

    import numpy as np

    from simvehicle.server.server import recording_run
    from simvehicle.tools.plots import plot_run

    run = recording_run(vtlog, name="MAVLink loop (lockstep)")
    plot_run(run, png, force=gust_force, title="make demo: the companion and the simulated vehicle over MAVLink "
                                               "(lockstep)")
    t, x = run["t_s"], run["x_m"]
    cruise_end = PROFILE[2][0]
    cruise = (t >= cruise_end - 3.0) & (t < cruise_end)  # the last 3 s before the setpoint returns to 0
    sp = _setpoint_at(cruise_end - 3.0)
    i_gust = int(np.searchsorted(t, GUST_AT_S))
    print(f"flew {t[-1]:.1f} s of simulated time in {time.monotonic() - t0:.1f} s: "
          f"cruise {np.mean(run['vx_m_s'][cruise]):.3f}, {np.mean(run['vy_m_s'][cruise]):.3f} m/s "
          f"(setpoint {sp[0]:g}, {sp[1]:g}); the gust pushed it back {x[i_gust] - x[-1]:.2f} m and it holds at "
          f"{abs(run['vx_m_s'][-1]):.3f} m/s")
    print(f"plot: {png}")
    print(f"recordings: {vtlog} (vehicle), {ctlog} (companion); logs: {vlog}, {clog}")
    print("to watch a flight in real time: python -m simvehicle serve (UDP 127.0.0.1:14550), the companion "
          "with --connect udpout:127.0.0.1:14550, and mavproxy.py --master=udpout:127.0.0.1:14550 (docs/loop.md)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
