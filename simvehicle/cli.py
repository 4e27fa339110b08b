"""Command line of the simulated vehicle: ``python -m simvehicle {scenario,serve,sweep,refly}``."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence

from companion.config import load_config
from companion.errors import check_output, run_command, writing
from companion.step.profiles import Profile
from simvehicle.engines.scenarios import SCENARIOS, figures, run_named


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m simvehicle",
                                     description="The paper's simulated vehicle: scenarios, a MAVLink/UDP "
                                                 "vehicle, parameter sweeps.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="{scenario,serve,sweep,refly}")
    sc = sub.add_parser("scenario", help="run one of the paper's scenarios in simulation time")
    sc.add_argument("name", choices=["step", "gust", "slow", "rail", "triangle"],
                    help="step (0 -> 2 m/s at 5 s, Fig. 16), gust (4 N headwind from 5 s, Fig. 17), slow "
                         "(0 -> 1 cm/s at 2 s, Fig. 18-19): closed loop; rail (Table V) and triangle (Fig. 9): "
                         "the flow sensor moved open loop")
    sc.add_argument("--config", help="parameter set (TOML); default configs/paper.toml")
    sc.add_argument("--profile", choices=["paper", "ardupilot", "px4"], default="paper",
                    help="sensor message convention of the recording (default paper)")
    sc.add_argument("--seed", type=int, default=0, help="seed of the noise generator (default 0)")
    sc.add_argument("--tlog", help="write the run as a MAVLink recording")
    sc.add_argument("--plot", help="write the paper's figure for the run (PNG)")
    sc.add_argument("--json", help="write the measured figures of merit (JSON); '-' for stdout")

    sv = sub.add_parser("serve", help="a simulated vehicle speaking MAVLink on one UDP port")
    sv.add_argument("--listen", default="127.0.0.1:14550", help="HOST:PORT to bind (default 127.0.0.1:14550)")
    sv.add_argument("--config", help="parameter set (TOML)")
    sv.add_argument("--profile", choices=["paper", "ardupilot", "px4"], default="paper",
                    help="sensor message convention the vehicle speaks (CONVENTIONS.md): paper = OPTICAL_FLOW "
                         "counts, ardupilot = OPTICAL_FLOW rates with time_usec in ms, px4 = OPTICAL_FLOW_RAD "
                         "(default paper)")
    mode = sv.add_mutually_exclusive_group()
    mode.add_argument("--speedup", type=float, default=1.0,
                      help="run X times faster than real time (default 1: real time)")
    mode.add_argument("--lockstep", action="store_true",
                      help="advance one frame per companion setpoint (deterministic, as fast as the CPU)")
    sv.add_argument("--max-speedup", type=float,
                    help="with --lockstep: never run more than X times faster than real time (a ground "
                         "station or a test reading the streams keeps up; default: no cap)")
    sv.add_argument("--tlog", help="record everything sent and received")
    sv.add_argument("--seed", type=int, default=0,
                    help="seed of the noise generator (gyro noise, turbulence; default 0)")
    sv.add_argument("--signing-key", help="MAVLink 2 signing: a passphrase or a file holding the key")
    sv.add_argument("--sysid", type=int, default=1, help="the vehicle's MAVLink system id (default 1)")
    sv.add_argument("--duration", type=float, help="stop after this many simulated seconds")
    sv.add_argument("--scenario", choices=["step", "gust", "slow"],
                    help="fly a paper scenario's schedule: its external force, and its velocity setpoints "
                         "sent to the companion as a ground station would; --duration defaults to its length")

    sw = sub.add_parser("sweep", help="figures of merit across a parameter grid (on Dask: all cores or a cluster)")
    sw.add_argument("sweep_config", help="sweep definition (TOML), e.g. configs/sweeps/altitude_q.toml")
    sw.add_argument("--out", default="out/sweep", help="folder for the table (CSV) and the plot (default out/sweep)")
    sw.add_argument("--workers", type=int, help="worker processes of the Dask LocalCluster (default: all cores)")
    sw.add_argument("--scheduler", help="address of a running Dask scheduler, e.g. tcp://host:8786 "
                                        "(default: a LocalCluster on this machine)")
    sw.add_argument("--in-process", action="store_true",
                    help="no Dask: one batch after another in this process (the mode without the cluster extra)")
    sw.add_argument("--batch", type=int, help="flights per task (default: about four tasks per worker, at most 256)")
    rf = sub.add_parser("refly", help="fly a recorded flight again in the simulator, nominal and fitted model, "
                                      "and compare both with the recording (docs/refly.md)")
    rf.add_argument("recording", help="the flight: .tlog, DataFlash .bin, PX4 .ulg (each also .gz)")
    rf.add_argument("--config", help="the fitted model (diagnose --model-out); the nominal is the same without its "
                                     "[effects.*]; default configs/paper.toml")
    rf.add_argument("--profile", choices=["paper", "ardupilot", "px4"],
                    help="sensor message convention (default: detected from the recording)")
    rf.add_argument("--also", action="append", metavar="REC2",
                    help="another recording of the same vehicle, compared on every frame (repeatable)")
    rf.add_argument("--report", metavar="DIR", help="write refly.md, its plots and report.html into this folder "
                                                     "(a diagnose report there gets the comparison first)")
    rf.add_argument("--json", help='write {"channels": [{"channel", "unit", "rms_nominal", "rms_fitted"}, ...]} here')
    return parser


def _scenario(args: argparse.Namespace) -> int:
    for flag, path in (("--tlog", args.tlog), ("--plot", args.plot), ("--json", args.json)):
        if path and path != "-":
            check_output(path, flag)
    cfg = load_config(args.config)
    with writing("--tlog", args.tlog or ""):
        run = run_named(args.name, cfg, profile=Profile(args.profile), seed=args.seed, tlog=args.tlog)
    fig = figures(run, cfg)
    text = json.dumps(fig, indent=2)
    if args.json == "-":
        print(text)
    elif args.json:
        with writing("--json", args.json), open(args.json, "w") as fh:
            fh.write(text + "\n")
    if args.plot:
        from simvehicle.tools.plots import plot_run

        scenario = SCENARIOS.get(args.name)
        with writing("--plot", args.plot):
            plot_run(run, args.plot, force=scenario.force if scenario is not None else None)
    if args.json != "-":
        print(_summary(fig))
        for label, p in (("recording", args.tlog), ("plot", args.plot), ("figures", args.json)):
            if p:
                print(f"{label}: {p}")
    return 0


def _summary(fig: dict) -> str:
    lines = [f"scenario {fig['scenario']}"]
    if "rows" in fig:
        for r in fig["rows"]:
            lines.append("  " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                          for k, v in r.items()))
        return "\n".join(lines)
    for axis in ("x", "y"):
        lines.append(f"  {axis}: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                               for k, v in fig[axis].items()))
    return "\n".join(lines)


def _dispatch(args: argparse.Namespace) -> int:
    if args.command == "scenario":
        return _scenario(args)
    if args.command == "serve":
        from simvehicle.server.server import run_cli

        return int(run_cli(args))
    if args.command == "refly":
        from simvehicle.tools.refly import run_cli as refly_cli

        return int(refly_cli(args))
    from simvehicle.tools.sweep import run_cli as sweep_cli

    return int(sweep_cli(args))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_command(lambda: _dispatch(args))
