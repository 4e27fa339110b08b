"""Command line of the companion: ``python -m companion {run,replay,info,diagnose,fleet}``.

Each subcommand's work lives in its own module (``live``, ``replay``, ``info``, ``diagnose``, ``fleet``);
this file only declares the arguments and turns errors into one clear line and an exit code.
Set FLOWHOLD_DEBUG=1 to see the traceback of an unexpected error.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence

from companion.errors import run_command

PROFILES = ("paper", "ardupilot", "px4")


def _add_common(p: argparse.ArgumentParser, *, detected_from: str = "the recording") -> None:
    p.add_argument("--config", help="parameter set (TOML); default configs/paper.toml (Table VI)")
    p.add_argument("--profile", choices=PROFILES,
                   help=f"sensor message convention (CONVENTIONS.md); default: detected from {detected_from}")


def _add_recording(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", help=".tlog, DataFlash .bin, PX4 .ulg, or CSV (with --sensor-config); "
                                     "each also gzip-compressed (.gz)")
    p.add_argument("--sensor-config", help="column map (TOML in configs/sensors/) for a CSV recording")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m companion",
        description="Optical-flow velocity hold beside an autopilot: live loop, replay, info, diagnose, fleet, "
                    "the autopilot's watchdog applet.")
    sub = parser.add_subparsers(dest="command", required=True,
                                metavar="{run,replay,info,diagnose,fleet,ardupilot-script}")

    run = sub.add_parser("run", help="run the velocity-hold loop against a vehicle over MAVLink")
    run.add_argument("--connect", required=True,
                     help="pymavlink URL: udpout:127.0.0.1:14550, udpin:0.0.0.0:14550, tcp:HOST:PORT, "
                          "/dev/ttyUSB0,921600")
    _add_common(run, detected_from="the vehicle's messages before taking control")
    run.add_argument("--arm", action="store_true", help="switch to GUIDED_NOGPS and arm (simulators only)")
    run.add_argument("--setpoint", help="constant body-frame velocity setpoint VX,VY in m/s")
    run.add_argument("--tlog", help="record everything sent and received to this .tlog")
    run.add_argument("--vehicle-sysid", type=int, help="accept sensor data only from this system id "
                     "(default: the first autopilot heard)")
    run.add_argument("--signing-key", help="MAVLink 2 signing: a passphrase or a file holding the key")
    run.add_argument("--duration", type=float, help="stop after this many seconds of control")
    run.add_argument("--quiet", action="store_true", help="no console status line")

    replay = sub.add_parser("replay", help="run the estimator and controller over a recording")
    _add_recording(replay)
    _add_common(replay)
    replay.add_argument("--csv", help="output CSV, one row per flow frame (this and/or --parquet)")
    replay.add_argument("--parquet", help="the same columns as a Parquet file (needs pyarrow: flowhold[parquet])")
    replay.add_argument("--plot", help="PNG of setpoint, estimate, truth, commands and flow counts")
    replay.add_argument("--gyro", choices=("auto", "imu", "flow"), default=None,
                        help="body rate for eq. 15: imu = RAW_IMU/SCALED_IMU/HIGHRES_IMU nearest the frame; "
                             "flow = the flow message's own body rate; auto = flow for ardupilot, imu otherwise "
                             "(docs/ardupilot.md); default: the config's companion.gyro_source (auto in "
                             "configs/paper.toml)")
    replay.add_argument("--estimator", choices=("auto", "eq15", "tilt", "kf"), default=None,
                        help="the velocity the PI flies on: eq15 (the paper's), tilt (attitude-predicted two-state "
                             "observer, companion.step.core.TiltFilter), kf (Kalman filter, flow sample's age "
                             "compensated: "
                             "docs/estimator.md), auto (kf for ardupilot and px4, eq15 for paper); default: the "
                             "config's companion.velocity_estimator (auto in configs/paper.toml)")
    replay.add_argument("--filter", choices=("none", "tilt"), default=None,
                        help="the older spelling of --estimator: none = eq15, tilt = tilt")

    info = sub.add_parser("info", help="summarise a recording")
    _add_recording(info)
    info.add_argument("--json", help="also write the summary as JSON here")

    diag = sub.add_parser("diagnose", help="find where the model and a recording differ, and why")
    _add_recording(diag)
    _add_common(diag)
    diag.add_argument("--json", help="write the mismatch report (CONVENTIONS.md) here")
    diag.add_argument("--report", metavar="DIR",
                      help="write the report into this folder: report.md with its PNG plots, and report.html, "
                           "the same as one page with the plots embedded (opens offline), led by what differs, "
                           "how sure, and what to change in the config")
    diag.add_argument("--fit-all", action="store_true",
                      help="fit every frame of a long recording (by default a flight over 22.5 min is fitted on "
                           "15 min of 60 s blocks spread evenly over it and checked on the rest: the time budget)")
    diag.add_argument("--model-out", metavar="TOML",
                      help="write the fitted model: the nominal config plus an [effects.<name>] table per "
                           "significant finding (uncertainties as comments), loadable with --config; the vehicle's "
                           "properties are fitted on the first half of the flight, so that 'python -m simvehicle "
                           "refly' can judge the model on the second (docs/refly.md)")

    fleet = sub.add_parser("fleet", help="diagnose every recording of a fleet on Dask (one task per file): "
                                         "a table, the reports and an HTML summary")
    fleet.add_argument("inputs", nargs="+", metavar="DIR_OR_GLOB",
                       help="folders (searched for .tlog, .bin, .ulg, .csv, each also .gz), globs or files")
    fleet.add_argument("--out", required=True, help="folder for fleet.csv, fleet.parquet, summary.html, reports/")
    _add_common(fleet, detected_from="each recording")
    fleet.add_argument("--sensor-config", help="column map (TOML in configs/sensors/) for the CSV recordings")
    fleet.add_argument("--scheduler", help="address of a running Dask scheduler, e.g. tcp://host:8786 "
                                           "(default: a LocalCluster on this machine)")
    fleet.add_argument("--workers", type=int, help="worker processes of the LocalCluster (default: all cores)")
    fleet.add_argument("--in-process", action="store_true",
                       help="no Dask: one file after another in this process (the mode without the cluster extra)")
    fleet.add_argument("--vehicle-from", choices=("folder", "sysid"), default="folder",
                       help="a recording's vehicle: the folder holding it, or its MAVLink system id (default folder)")

    script = sub.add_parser("ardupilot-script", help="the ArduCopter Lua applet that switches to LAND when the "
                                                     "companion's commands stop (docs/ardupilot.md)")
    script.add_argument("--out", help="folder to write flowhold_watchdog.lua into, created if missing "
                                      "(default: print the script)")
    return parser


#: glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: set by the commands whose process may end without the interpreter's clean-up (``finish``)
_exit_directly = False


def _batch_process(*, exit_directly: bool = True) -> None:
    """``replay`` and ``info`` read a recording, work on it and exit: set this process up for
    that (docs/performance.md). ``diagnose`` too, except the direct exit (``exit_directly``).

    - One OpenBLAS thread, unless the user chose otherwise: they do no large linear algebra, and
      OpenBLAS's idle threads, started when numpy loads, spin for about 0.1 s of CPU each before
      they sleep, taking the core the compiled reader's and CSV writer's second thread would run
      on. Only before numpy is loaded (after, it has no effect). The diagnosis' products are
      small (13 parameters by the frames): a second BLAS thread cost it more in synchronising
      than it gave (an hour-long recording: 5.5 s of CPU with one thread, 10.4 s with two, and
      a longer wall time).
    - With glibc, memory freed is kept for the next allocation rather than given back to the
      system (allocations under 64 MB from the heap, no trimming): numpy's temporaries of a long
      recording's columns were otherwise mapped and unmapped again and again, and every fresh
      page costs a fault and its zeroing. The memory goes back at exit.
    - Run as ``python -m companion``, the process ends without the interpreter's clean-up
      (``finish``): their files are written and closed by then, and freeing every object and
      array one by one took some 30 ms after an hour-long replay."""
    global _exit_directly
    _exit_directly = exit_directly
    if "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            libc = ctypes.CDLL(None)
            mallopt = libc.mallopt
        except (OSError, AttributeError):  # not glibc (musl has no mallopt)
            return
        mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
        mallopt(_M_MMAP_THRESHOLD, 64 << 20)
        mallopt(_M_TRIM_THRESHOLD, 1 << 30)


def _dispatch(command: str) -> Callable[[argparse.Namespace], int]:
    if command == "run":
        from companion.mavlink.live import run_cli
    elif command == "replay":
        _batch_process()
        from companion.tools.replay import run_cli
    elif command == "info":
        _batch_process()
        from companion.tools.info import run_cli
    elif command == "fleet":
        from companion.fleet.run import run_cli
    elif command == "ardupilot-script":
        from companion.ardupilot_script import run_cli
    else:
        _batch_process(exit_directly=False)
        from companion.diagnose.closed_loop.command import run_cli
    return run_cli


def finish(code: int) -> None:
    """End ``python -m companion`` with ``code``: for the commands that asked for it
    (``_batch_process``), the standard streams flushed and the process ended at once
    (``os._exit``: no atexit handlers, no object clean-up; every output file is closed by then);
    otherwise ``sys.exit``."""
    if _exit_directly:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed pipe: main has already said what it had to
                pass
        os._exit(code)
    sys.exit(code)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_command(lambda: _dispatch(args.command)(args))
