"""Long recordings (issue 12's time budget): a flight over 1.5 x ``FIT_SPAN_S`` is fitted on evenly
spread blocks that add up to it, and the fitted model is checked on the rest, so that what acts
only in the held-back part is still said (``diagnosis.fit_blocks``, ``_check_held_back``)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.config import load_config
from companion.diagnose.closed_loop.diagnosis import FIT_BLOCK_S, FIT_SPAN_S, diagnose, fit_blocks, flown_time_s
from companion.recordings.load import load_recording

ROOT = Path(__file__).resolve().parent.parent


def _starts(mask: np.ndarray) -> np.ndarray:
    return np.flatnonzero(np.diff(np.r_[False, mask].astype(int)) == 1)


def test_the_fitted_blocks_are_spread_evenly_from_the_first_frame_to_the_last():
    t = 1000.0 + np.arange(0, 3600.0, 0.02)  # an hour at 50 Hz, report time from 1000 s
    keep = fit_blocks(t, FIT_SPAN_S)
    assert keep is not None and keep[0] and keep[-1]
    starts = _starts(keep)
    n = int(np.ceil(FIT_SPAN_S / FIT_BLOCK_S))
    assert len(starts) == n
    # each block FIT_BLOCK_S long (the last also holds the last frame), together FIT_SPAN_S
    assert abs(keep.sum() * 0.02 - n * FIT_BLOCK_S) <= 2 * 0.02
    step = (3600.0 - 0.02 - FIT_BLOCK_S) / (n - 1)
    np.testing.assert_allclose(np.diff(t[starts]), step, atol=0.02)


def test_no_block_falls_where_nothing_was_flown():
    """Two 20 min flights an hour apart in one log (the companion engaged twice): the blocks are
    spread over the 40 min flown, not over the 100 min the log spans."""
    from companion.diagnose.closed_loop.channels import FlightData

    t = np.r_[np.arange(0.0, 1200.0, 0.02), 4800.0 + np.arange(0.0, 1200.0, 0.02)]
    n = len(t)
    z = np.zeros(n)
    seg = (t > 3000.0).astype(int)
    data = FlightData(path="synthetic", profile="paper", profile_reason="test", frame_s=0.02, command_source="test",
                      t_s=t, dt_s=np.r_[0.02, np.diff(t)], seg=seg, dphi_x_rad=z, dphi_y_rad=z, gyro_x_rad_s=z,
                      gyro_y_rad_s=z, range_m=z + 1.0, roll_rad=z, pitch_rad=z, yaw_rad=z, roll_cmd_rad=z,
                      pitch_cmd_rad=z, vx_set_m_s=z, vy_set_m_s=z, truth_vx_m_s=z, truth_vy_m_s=z)
    flown = flown_time_s(data)
    assert flown[-1] == pytest.approx(2400.0 - 2 * 0.02)
    keep = fit_blocks(flown, FIT_SPAN_S)
    assert keep is not None
    assert abs(keep.sum() * 0.02 - FIT_SPAN_S) <= 2 * 0.02
    # the blocks in each flight as its share of the flown time (half each, within a block)
    assert abs(keep[seg == 0].sum() - keep[seg == 1].sum()) * 0.02 <= FIT_BLOCK_S


@pytest.mark.parametrize("minutes", [0.5, 20.0, 22.4])
def test_a_flight_up_to_one_and_a_half_fit_spans_is_fitted_whole(minutes):
    assert fit_blocks(np.arange(0.0, minutes * 60.0, 0.02), FIT_SPAN_S) is None


def test_a_gust_in_the_held_back_part_is_said_where_it_acts(tmp_path):
    """A 150 s flight (the matrix's generator, noise but no loss) with a 1.5 N gust over 20 s,
    fitted as if 40 s were the span: the two 60 s blocks at its ends are fitted, the gust's
    middle is held back. The fit cannot name the gust, but the headline says the model does not
    fit force_x where it blows, by about its 1.5 N; fitted whole, the gust is found."""
    from simvehicle.engines import flightgen as fg

    spec = fg.draw_spec(95)
    prof = fg.draw_profile(np.random.default_rng([95, 13]), spec.warmup_s + 150.0, 1.5, False, 1.5)
    spec = dataclasses.replace(spec, duration_s=150.0, flight=prof, loss=fg.Loss(),
                               noise=fg.Noise(gyro_white_rad_s=0.002, att_white_rad=0.001),
                               effects={"wind_force": {"fx": -1.5, "fy": 0.0, "start_s": 65.0, "end_s": 85.0}})
    g = fg.write_flight(spec, fg.simulate(spec), tmp_path, "gust")
    truth = g.truth["effects"]["wind_force"]
    rec, cfg = load_recording(g.tlog), load_config(g.config)

    rep = diagnose(rec, cfg, fit_span_s=40.0).report
    assert rep.significant() == []
    assert rep.headline.startswith("The model does not fit force_x from")
    [u] = [u for u in rep.unexplained if u.channel == "force_x"]
    assert u.start_s < truth["end_s"] and u.end_s > truth["start_s"]
    assert u.start_s > 60.0 - 5.0 and u.end_s < 90.0 + 5.0  # the held-back part, to a window
    assert abs(u.rms - 1.5) < 0.5
    assert any(n.startswith("a long recording: the effects fitted on 2.0 of 2.5 min") for n in rep.notes)
    assert any(n.startswith("the held-back 0.5 min, not fitted") for n in rep.notes)

    whole = diagnose(rec, cfg, fit_span_s=None).report
    [w] = [f for f in whole.significant() if f.effect == "wind_force"]
    assert abs(w.parameters["fx"] + 1.5) < 0.15
    assert abs(w.parameters["start_s"] - truth["start_s"]) < 1.5


def test_fit_all_on_the_command_line(tmp_path):
    out = subprocess.run([sys.executable, "-m", "companion", "diagnose", "--help"], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout
    assert "--fit-all" in out


def _rows_by_definition(data, delay_frames):
    """``groups.attitude_rows`` as its rule reads, one run of lost commands at a time."""
    from companion.diagnose.closed_loop.groups import AFTER_COMMAND_GAP_S, COMMAND_SETTLE_FRAMES, _runs

    rows = data.att_rec.copy()
    t = data.t_s
    lost = np.flatnonzero(~data.cmd_rec)
    for k in range(COMMAND_SETTLE_FRAMES + max(delay_frames, 0)):
        rows[np.minimum(lost + k, data.n - 1)] = False
    for a, b in _runs(~data.cmd_rec, 2):
        rows &= ~((t >= t[a]) & (t <= t[b - 1] + AFTER_COMMAND_GAP_S + max(delay_frames, 0) * data.frame_s))
    return rows


@pytest.mark.parametrize("shuffle", [False, True])
def test_the_attitude_rows_after_lost_commands_are_those_of_the_rule(shuffle):
    """The frames left out after runs of lost commands, marked for all runs at once (a lossy hour
    has thousands), are those of the rule applied run by run: 20 % of commands lost at random and
    in bursts, time stamps jittered, and (``shuffle``) frames out of time order."""
    from companion.diagnose.closed_loop.channels import FlightData
    from companion.diagnose.closed_loop.groups import attitude_rows

    rng = np.random.default_rng(3)
    n = 6000
    t = np.arange(n) * 0.02 + rng.uniform(-0.004, 0.004, n)
    if shuffle:  # the rule holds on any times: some frames swap theirs with a frame 2 s away
        k = rng.choice(np.arange(0, n - 100, 200), 20, replace=False)
        t[k], t[k + 100] = t[k + 100].copy(), t[k].copy()
    cmd = rng.random(n) > 0.2
    for a in rng.choice(n - 40, 30, replace=False):
        cmd[a:a + 25] = False
    att = rng.random(n) > 0.05
    z = np.zeros(n)
    data = FlightData(path="synthetic", profile="paper", profile_reason="test", frame_s=0.02, command_source="test",
                      t_s=t, dt_s=np.r_[0.02, np.diff(t)], seg=np.zeros(n, dtype=int), dphi_x_rad=z, dphi_y_rad=z,
                      gyro_x_rad_s=z, gyro_y_rad_s=z, range_m=z + 1.0, roll_rad=z, pitch_rad=z, yaw_rad=z,
                      roll_cmd_rad=z, pitch_cmd_rad=z, vx_set_m_s=z, vy_set_m_s=z, truth_vx_m_s=z, truth_vy_m_s=z,
                      att_rec=att, cmd_rec=cmd)
    for delay in (0, 3):
        got = attitude_rows(data, delay)
        want = _rows_by_definition(data, delay)
        assert 0 < got.sum() < n
        np.testing.assert_array_equal(got, want)
