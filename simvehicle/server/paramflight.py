"""A flight of the simulated vehicle with parameters set by PARAM_SET while it flies (issue 16).

The vehicle is ``simvehicle.server.server.Vehicle``, the logic ``python -m simvehicle serve`` runs, in
process and in lockstep (no sockets, no clock); the companion is ``companion.mavlink.inbound.MessageRouter``
and ``companion.step.core.CompanionCore``, as ``simvehicle.engines.scenarios.fly`` runs it; a ground station
(system 255, component 190) sends the scenario's velocity setpoints every frame and, at the given
times, PARAM_SET messages, as a test engineer would over MAVLink: ``SIM_DRAG_B``,
``SIM_FLOW_SCALE_X``, ``SIM_WIND_FX`` ..., and the autopilot's own ``FLOW_FXSCALER``,
``FLOW_ORIENT_YAW`` ... Everything each side sends (the vehicle's PARAM_VALUE answers too) is
recorded in a .tlog, stamped with the vehicle's clock from ``TLOG_EPOCH_S``, so report time and
simulation time agree. The vehicle is armed in GUIDED_NOGPS from the first frame, as the scenarios
are.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.config import Config
from companion.mavlink import outbound
from companion.mavlink.inbound import MessageRouter
from companion.recordings.tlog_writer import TlogWriter
from companion.step.core import CompanionCore
from companion.step.profiles import Profile
from simvehicle.engines.scenarios import TLOG_EPOCH_S, Scenario
from simvehicle.model.telemetry import GUIDED_NOGPS
from simvehicle.server.server import StreamSchedule, Vehicle

GCS = (255, 190)


@dataclass(frozen=True, order=True)
class ParamChange:
    """A PARAM_SET the ground station sends at simulation time ``t_s``."""

    t_s: float
    name: str
    value: float


def fly_with_params(cfg: Config, scenario: Scenario, changes: Sequence[ParamChange], tlog: str | Path, *,
                    profile: Profile = Profile.PAPER, seed: int = 0) -> dict[str, float]:
    """Fly ``scenario`` with ``changes`` sent as PARAM_SET at their times; record ``tlog``.
    Returns the vehicle's parameter values at the end."""
    v = Vehicle(cfg, profile=profile, seed=seed, scenario=scenario, lockstep=True)
    v.armed, v.custom_mode = True, GUIDED_NOGPS
    core = CompanionCore(cfg, profile)
    router = MessageRouter(core, profile, vehicle_sysid=v.sysid)
    comp = mav.MAVLink(None, srcSystem=v.sysid, srcComponent=outbound.COMPANION_COMPONENT)
    gcs = mav.MAVLink(None, srcSystem=GCS[0], srcComponent=GCS[1])
    parser = mav.MAVLink(None)
    streams = StreamSchedule(v.T)
    pending = sorted(changes)
    n_frames = int(round(scenario.duration_s / v.T))
    per_s = int(round(1.0 / v.T))
    Path(tlog).parent.mkdir(parents=True, exist_ok=True)
    writer = TlogWriter(tlog)

    def emit(msg: Any, enc: Any, stamp: float) -> Any:
        buf = msg.pack(enc)
        writer.write_bytes(buf, stamp)
        return parser.decode(bytearray(buf))

    try:
        for k in range(n_frames + 1):
            t = v.sim.t_s
            stamp = TLOG_EPOCH_S + t
            while pending and pending[0].t_s <= t + 1e-9:
                ch = pending.pop(0)
                msg = emit(gcs.param_set_encode(v.sysid, 1, ch.name.encode(), ch.value, mav.MAV_PARAM_TYPE_REAL32),
                           gcs, stamp)
                for reply in v.handle(msg, streams):
                    emit(reply.msg, v.enc, stamp)
            if k % per_s == 0:
                emit(v.heartbeat(), v.enc, stamp)
            out = v.frame()
            if out.scenario_setpoint is not None:
                router.handle(emit(out.scenario_setpoint, v.gcs_enc, stamp), t)
            step = None
            for _stream, m in out.messages:
                got = router.handle(emit(m, v.enc, stamp), t)
                step = got if got is not None else step
            if step is not None:
                ms = out.time_boot_ms
                cmd = emit(outbound.set_attitude_target(comp, ms, v.sysid, step.roll_cmd_rad, step.pitch_cmd_rad, 0.0),
                           comp, stamp)
                v.handle(cmd, streams)
                emit(outbound.position_target(comp, ms, step.vx_set_m_s, step.vy_set_m_s), comp, stamp)
                if not step.holding:
                    emit(outbound.vision_speed(comp, int(round(t * 1e6)), step.vx_m_s, step.vy_m_s), comp, stamp)
            if k < n_frames:
                v.advance()
    finally:
        writer.close()
    return dict(v.values)
