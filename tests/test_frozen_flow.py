"""Issue 18 (a): in the ``ardupilot`` profile a flow payload identical to the last one is a repeat
whatever its time (ArduPilot re-sends its last sample ~0.5 s after the sensor stops), so the
live core and replay's column rule both stop stepping it; the paper profile keeps its window."""

import math

import numpy as np

from companion.step.core import REPEAT_WINDOW_FRAMES, repeat_mask, repeat_window
from companion.step.profiles import Profile


def _frozen(n_new: int, n_frozen: int, t_frame_s: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n_new + n_frozen) * t_frame_s
    payload = np.zeros((len(t), 2))
    payload[:n_new, 0] = np.arange(1, n_new + 1) * 0.01  # new rates every frame
    payload[n_new:] = payload[n_new - 1]  # then the same floats re-sent, a frame apart
    return t, payload


def test_ardupilot_frozen_payload_is_a_repeat_whatever_its_time():
    t, payload = _frozen(10, 25, 0.02)
    win = repeat_window(np.full(len(t), np.nan), REPEAT_WINDOW_FRAMES * 0.02, Profile.ARDUPILOT)
    assert np.all(np.isinf(win))
    rep = repeat_mask(t, payload, win)
    assert rep.tolist() == [False] * 10 + [True] * 25


def test_paper_profile_keeps_the_frame_window():
    # integer counts: a still sensor really reads the same counts a frame later: a new sample
    t, payload = _frozen(10, 25, 0.02)
    win = repeat_window(np.full(len(t), np.nan), REPEAT_WINDOW_FRAMES * 0.02, Profile.PAPER)
    assert np.allclose(win, 0.75 * 0.02)
    assert not repeat_mask(t, payload, win).any()
    assert math.isclose(REPEAT_WINDOW_FRAMES, 0.75)


def test_live_core_and_replay_rule_agree_on_a_frozen_ardupilot_flow(paper_cfg):
    """The live core (``CompanionCore._is_repeat``) flags the same messages as the column rule."""
    from companion.step.core import CompanionCore
    from companion.step.profiles import FlowColumns

    t, rates = _frozen(10, 25, 0.02)
    core = CompanionCore(paper_cfg, Profile.ARDUPILOT)
    flags = []
    for ti, (sx, sy) in zip(t, rates, strict=True):
        f = FlowColumns(time_s=float(ti), scene_x=float(sx), scene_y=float(sy), increment=False, quality=255.0,
                        counts_x=math.nan, counts_y=math.nan,
                        integration_s=math.nan, body_x_rad_s=0.001, body_y_rad_s=0.0)
        flags.append(core.on_flow(f).repeat)
    payload = np.column_stack([rates, np.full((len(t), 2), [255.0, np.nan]),
                               np.full((len(t), 2), [0.001, 0.0])])
    win = repeat_window(np.full(len(t), np.nan), REPEAT_WINDOW_FRAMES * 0.02, Profile.ARDUPILOT, payload)
    assert flags == repeat_mask(t, payload, win).tolist() == [False] * 10 + [True] * 25
