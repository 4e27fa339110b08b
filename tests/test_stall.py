"""Issue 18 (b, d) in process: the link's clock mapping, a stalled companion's backlog dropped (not
replayed), a backlog on the link dropped by age, and what the pilot is told: the long-hold cue,
the GCS's setpoints stopping. Times are passed in (a fake clock), so every number is exact;
``tests/test_stall_e2e.py`` does the same with real processes, SIGSTOP and UDP.

The harness is the live loop itself (``LiveCompanion.run``) on a fake link that hands it the
reference simulator's frames, one per frame period of the fake clock, and advances the simulator
with the companion's last command, as the vehicle would.
"""

from __future__ import annotations

import math

import pytest
from fake_link import FakeLink

from companion.config import load_config
from companion.mavlink import link, outbound
from companion.mavlink.link import ClockMapping
from companion.mavlink.live import BACKLOG_SAY_FRAMES, LONG_HOLD_S, MAX_FRAME_AGE_FRAMES, HoldMonitor, LiveCompanion
from companion.mavlink.session import Command
from companion.step.controller import pi_step
from companion.step.core import HoldCause
from companion.step.profiles import Profile

mav = link.mav
CFG = load_config()
T_S = CFG.flow_sensor.frame_period_s
WIND_N = 2.0

# ---------------------------------------------------------------------------------------------
# The clock mapping alone


def test_age_is_the_time_behind_the_newest_sample_plus_the_time_since_it_arrived():
    m = ClockMapping()
    assert m.age_s(5.0, 100.0) == 0.0  # nothing heard: nothing is known to be old
    for k in range(50):  # a vehicle on the wall clock, heard 5 ms after each frame
        m.observe(5.0 + k * T_S, 100.0 + k * T_S + 0.005)
    last = 5.0 + 49 * T_S
    arrived = 100.0 + 49 * T_S + 0.005
    assert m.age_s(last, arrived) == 0.0
    assert m.age_s(last, arrived + 0.012) == pytest.approx(0.012)
    assert m.age_s(last - 2.0, arrived) == pytest.approx(2.0)  # a frame of a 2 s backlog
    # the newest sample itself waited 2 s (a stalled reader whose socket lost the newer ones)
    assert m.age_s(last, arrived + 2.0) == pytest.approx(2.0)


@pytest.mark.parametrize("text,rate", [
    ("simvehicle: simulated clock (lockstep)", 0.0),
    ("simvehicle: simulated clock (speedup x4)", 4.0),
    ("simvehicle: simulated clock (speedup x0.5)", 0.5),
    ("simvehicle: simulated clock (speedup xnan)", 1.0),
])
def test_the_rate_comes_from_the_simulators_clock_notice(text, rate):
    m = ClockMapping()
    assert m.set_clock_text(text)
    assert m.rate == rate
    m.observe(3.0, 50.0)
    # a lockstep vehicle's clock stands while it waits for the companion: the newest frame is not
    # old however long ago it came; at speed-up X its clock ran X times the local time
    assert m.age_s(3.0, 50.5) == pytest.approx(0.5 * rate)
    assert not ClockMapping().set_clock_text("PreArm: RC not calibrated")


def test_one_bogus_time_cannot_make_every_frame_old_but_a_reboot_is_taken():
    m = ClockMapping(jump_s=1.0)
    m.observe(10.0, 100.0)
    m.observe(9.2e12, 100.001)  # OPTICAL_FLOW time_usec 2**63: a jump no clock can make
    m.observe(10.02, 100.02)
    assert m.newest_s == 10.02 and m.age_s(10.02, 100.02) == 0.0
    m.observe(0.0, 100.03)  # a reboot: every time field restarts at 0 ...
    assert m.newest_s == 10.02
    m.observe(0.0, 100.031)  # ... and the next sample agrees
    assert m.newest_s == 0.0 and m.age_s(0.0, 100.031) == 0.0
    m.observe(math.nan, 100.04)
    assert m.newest_s == 0.0


def test_a_hold_episode_is_said_again_once_after_a_second():
    mon = HoldMonitor()
    assert mon.update(HoldCause.FLOW_STALE, 10.0)[0] == "flowhold: HOLD flow stale"
    assert not mon.long_hold(10.0 + LONG_HOLD_S, LONG_HOLD_S)  # not *over* a second yet
    mon.update(HoldCause.LINK, 10.5)  # the cause changes: the same episode
    assert mon.long_hold(10.0 + LONG_HOLD_S + 0.01, LONG_HOLD_S)
    assert not mon.long_hold(13.0, LONG_HOLD_S)  # once
    mon.update(HoldCause.NONE, 13.1)
    assert not mon.long_hold(20.0, LONG_HOLD_S)
    mon.update(HoldCause.FLOW_QUALITY, 20.0)
    assert mon.long_hold(21.5, LONG_HOLD_S)  # a new episode, said again
    assert mon.episodes == 2


# ---------------------------------------------------------------------------------------------
# The live loop on a fake link (tests/fake_link.py): the vehicle in a 2 N wind on each axis


def _wind(_t_s: float) -> tuple[float, float]:
    return (-WIND_N, WIND_N)


@pytest.fixture
def flying():
    """A companion in control for 3 s of the fake link, leaning into the wind."""
    fl = FakeLink(CFG, external_force=_wind)
    console: list[str] = []
    live = LiveCompanion(CFG, Profile.PAPER, fl, clock=lambda: fl.clock, wall=lambda: 1.7e9 + fl.clock,
                         out=console.append, quiet=True)
    live.router.vehicle_sysid, live.vehicle_compid = 1, 1
    fl.live = live
    fl.send_frame()
    fl.fly(150)
    assert live.in_control and live.counters["steps"] >= 140
    return fl, live, console


def test_a_stall_is_not_replayed(flying):
    fl, live, console = flying
    pi_before = live.core.pi.state
    n_sent, n_steps, n_said = len(fl.written), live.counters["steps"], len(console)
    fl.stall(2.0)  # 100 frames wait
    newest_ms = round(fl.sim.t_s * 1e3)
    fl.fly(0)  # the companion runs again: one loop pass over what waited
    resumed = fl.commands(n_sent)
    # one command, from the newest frame; 99 frames dropped, none stepped
    assert [m.time_boot_ms for _t, m in resumed] == [newest_ms]
    assert live.counters["steps"] == n_steps + 1
    assert live.counters["flow frames dropped (too old)"] == 99
    # the integrator took that one step (Table VI's PI, here at its limit: conditional integration)
    # and nothing of the stall
    out = live.last_step
    assert out is not None and not out.holding and out.dt_s == T_S
    e_x, e_y = out.vx_set_m_s - out.vx_m_s, out.vy_set_m_s - out.vy_m_s
    c = CFG.controller
    expected, roll, pitch = pi_step(pi_before, e_x, e_y, T_S, kp_rad_per_m_s=c.kp_rad_per_m_s,
                                    ki_rad_per_m=c.ki_rad_per_m, limit_rad=c.tilt_limit_rad)
    assert live.core.pi.state == expected and (out.roll_cmd_rad, out.pitch_cmd_rad) == (roll, pitch)
    assert abs(e_x) > 1.0  # the vehicle did drift during the stall: integrating it would have counted
    texts = fl.texts(n_sent)
    assert texts == [("flowhold: HOLD companion stalled", mav.MAV_SEVERITY_WARNING),
                     ("flowhold: backlog dropped: 99 frames (2.0 s)", mav.MAV_SEVERITY_WARNING),
                     ("flowhold: resumed", mav.MAV_SEVERITY_NOTICE)]
    said = console[n_said:]
    assert said[0] == "flowhold: HOLD companion stalled"
    assert said[1].startswith("flowhold: companion stalled for 2.00 s (this process did not run): dropped 99 "
                              "backlog frames"), said
    assert not [c for c in said if "link lost" in c]
    # and it flies on, one command per frame
    fl.fly(10)
    assert len(fl.commands(n_sent)) == 11


def _no_command_from_the_stalled_step(fl, live, n_sent: int) -> None:
    """Every command sent since ``n_sent`` flies a frame under ``flow_timeout_s`` old (by the
    simulator's clock), and the stalled step's command was the one not sent."""
    sent = fl.commands(n_sent)
    ages = [t - m.time_boot_ms * 1e-3 - (fl.clock - fl.sim.t_s) for t, m in sent]
    assert sent and max(ages) < CFG.companion.flow_timeout_s, ages
    assert live.counters["commands not sent (stalled inside the step)"] == 1


def test_a_stall_inside_a_step_does_not_send_its_old_command(flying):
    """The process stops after a frame is taken up and before its command is written (a SIGSTOP
    that falls inside the step: ``tests/test_stall_e2e.py`` met it once in a CI run, a command
    flown from a frame 2.02 s old). That command is not sent; the next pass of the loop sees the
    stall and resumes from the newest frame, so no command leaves from a frame older than
    ``flow_timeout_s``."""
    fl, live, _console = flying
    n_sent = len(fl.written)
    emit = live._emit
    stalled = []

    def stall_inside(outs, taken_up_s=None):
        if taken_up_s is not None and not stalled and any(isinstance(o, Command) for o in outs):
            stalled.append(True)
            fl.stall(2.0)  # stopped here: the clock runs, the vehicle queues 100 frames
        emit(outs, taken_up_s)

    live._emit = stall_inside
    fl.fly(5)
    assert stalled
    _no_command_from_the_stalled_step(fl, live, n_sent)
    assert live.counters["companion stalls"] == 1


def test_a_stall_while_a_step_is_written_does_not_send_its_old_command(flying, monkeypatch):
    """The process stops after the step's age was checked and before its messages are written:
    while they are built and packed (``tests/test_stall_e2e.py`` met it in a bare-clone run after
    the check above was in place: the first command after the stall computed from a frame 2.02 s
    old; building and packing three messages is a few hundred microseconds of each 20 ms step).
    The age is checked last, after packing, so that command is not sent either, and the sequence
    numbers it took are given back (the vehicle sees no packet lost)."""
    fl, live, _console = flying
    n_sent = len(fl.written)
    build = outbound.set_attitude_target
    stalled = []

    def stall_while_building(*args, **kwargs):
        if not stalled:
            stalled.append(True)
            fl.stall(2.0)  # stopped here: the clock runs, the vehicle queues 100 frames
        return build(*args, **kwargs)

    monkeypatch.setattr(outbound, "set_attitude_target", stall_while_building)
    fl.fly(5)
    assert stalled
    _no_command_from_the_stalled_step(fl, live, n_sent)
    seqs = [m.get_seq() for _t, m in fl.written[n_sent - 1:]]
    assert all((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:], strict=False)), seqs


def test_a_backlog_on_the_link_is_dropped_by_age(flying):
    """Ten frames held upstream (a router that stalled) come at once: the companion was never
    stopped, so no stall is named; the frames more than two frame periods behind the newest are
    dropped (7), the rest flown, and the drop is said."""
    fl, live, console = flying
    n_sent = len(fl.written)
    held = []
    for _ in range(10):
        fl.advance(fl.cmd)
        held.extend(fl.inbox)
        fl.inbox.clear()
        fl.clock -= T_S  # (the companion's clock does not run meanwhile: no stall of its own)
    fl.inbox.extend(held)
    newest_ms = round(fl.sim.t_s * 1e3)
    fl.fly(0)
    flown = [m.time_boot_ms for _t, m in fl.commands(n_sent)]
    n_ok = int(MAX_FRAME_AGE_FRAMES) + 1  # ages 0, T, 2T
    assert flown == [newest_ms - round(1e3 * T_S * k) for k in reversed(range(n_ok))]
    assert live.counters["flow frames dropped (too old)"] == 10 - n_ok
    assert 10 - n_ok >= BACKLOG_SAY_FRAMES
    assert fl.texts(n_sent) == [("flowhold: backlog dropped: 7 frames (0.2 s)", mav.MAV_SEVERITY_WARNING)]
    assert any("dropped 7 flow frames older than 40 ms (a backlog on the link" in c for c in console)
    assert live.counters["companion stalls"] == 0


def test_a_hold_over_a_second_is_the_pilots_cue():
    fl = FakeLink(CFG, external_force=_wind)
    console: list[str] = []
    live = LiveCompanion(CFG, Profile.PAPER, fl, clock=lambda: fl.clock, wall=lambda: 1.7e9 + fl.clock,
                         out=console.append, quiet=True)
    live.router.vehicle_sysid, live.vehicle_compid = 1, 1
    fl.live = live
    fl.send_frame()
    fl.fly(50)
    fl.quality = 0  # the flow sensor says its frames are invalid
    t0 = fl.clock
    n_sent = len(fl.written)
    fl.fly(int(3.0 / T_S))
    said = [(t, m.text, m.severity) for t, m in fl.written[n_sent:] if m.get_type() == "STATUSTEXT"]
    assert [(s, v) for _t, s, v in said] == [
        ("flowhold: HOLD flow quality 0", mav.MAV_SEVERITY_WARNING),
        ("flowhold: HOLD for 1 s, drifting: switch mode", mav.MAV_SEVERITY_CRITICAL)]
    assert LONG_HOLD_S <= said[1][0] - said[0][0] <= LONG_HOLD_S + T_S + 1e-9  # the first frame past 1 s
    assert said[0][0] == pytest.approx(t0 + T_S)
    assert "flowhold: holding level for 1.0 s (flow quality 0): level is not hover" in "\n".join(console)


def test_the_gcs_setpoints_stopping_is_said_when_the_ramp_begins():
    """Issue 18 "say it": a GCS setpoint not refreshed for ``setpoint_timeout_s`` (1 s) is held, then
    ramps to the constant setpoint; the ramp's start is said once (WARNING) and on the console."""
    fl = FakeLink(CFG, external_force=_wind)
    console: list[str] = []
    live = LiveCompanion(CFG, Profile.PAPER, fl, clock=lambda: fl.clock, wall=lambda: 1.7e9 + fl.clock,
                         out=console.append, quiet=True)
    live.router.vehicle_sysid, live.vehicle_compid = 1, 1
    fl.live = live
    fl.send_frame()
    fl.fly(50)
    gcs = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    sp = gcs.set_position_target_local_ned_encode(0, 1, outbound.COMPANION_COMPONENT, 12, outbound.VELOCITY_TYPE_MASK,
                                                  0, 0, 0, 0.4, 0.0, 0, 0, 0, 0, 0, 0)
    fl.inbox.append(mav.MAVLink(None).decode(bytearray(sp.pack(gcs))))
    t_sp = fl.clock
    n_sent = len(fl.written)
    fl.fly(int(2.5 / T_S))
    said = [(t, m.text, m.severity) for t, m in fl.written[n_sent:] if m.get_type() == "STATUSTEXT"]
    ramp = "flowhold: GCS setpoints stopped, ramp to hold"
    assert [(s, v) for _t, s, v in said] == [(ramp, mav.MAV_SEVERITY_WARNING)]
    timeout = CFG.companion.setpoint_timeout_s
    assert timeout < said[0][0] - t_sp <= timeout + T_S + 1e-9
    assert any(c.startswith(f"flowhold: GCS setpoints stopped for {timeout:g} s: ramping to +0.00 +0.00 m/s")
               for c in console), console
