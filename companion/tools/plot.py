"""The replay figure: setpoint, estimate, truth, commands and flow against time (a matplotlib
``Figure`` drawn to a file: no backend chosen, no global matplotlib state changed).

It plots any result with the replay's columns (``PlottedReplay``, which ``replay.ReplayResult``
is), so this module does not import ``companion.tools.replay``, whose ``--plot`` imports it (issue 13:
no import cycle); it is imported only when a plot is asked for (matplotlib's start-up).
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np
from matplotlib.figure import Figure

from companion.step.core import GyroSource
from companion.step.profiles import Profile


class PlottedReplay(Protocol):
    """What the figure reads of a replay (``companion.tools.replay.ReplayResult``)."""

    recording: str
    profile: Profile
    gyro_source: GyroSource
    columns: dict[str, np.ndarray]


def plot_replay(result: PlottedReplay, path: str | Path) -> Path:
    """Four panels against ``t_s`` (s from the first record), x solid and y dashed: velocity
    (setpoint, estimate, truth when the recording has LOCAL_POSITION_NED), attitude commands
    (replayed, and recorded when present, deg), flow (counts per frame for the paper profile,
    else the scene-angle rate, rad/s), and the gyro and range used. Held frames are shaded."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    c = result.columns
    t = c["t_s"]
    fig = Figure(figsize=(11, 10))
    axes = fig.subplots(4, 1, sharex=True)
    ax = axes[0]
    for axis, style in (("x", "-"), ("y", "--")):
        ax.plot(t, c[f"v{axis}_set_m_s"], style, color="k", lw=1.0, label=f"setpoint {axis}")
        ax.plot(t, c[f"v{axis}_m_s"], style, color="C0" if axis == "x" else "C1", lw=0.7,
                label=f"estimate {axis}")
        if f"truth_v{axis}_m_s" in c:
            ax.plot(t, c[f"truth_v{axis}_m_s"], style, color="C2" if axis == "x" else "C3", lw=0.9,
                    label=f"truth {axis} (LOCAL_POSITION_NED)")
    ax.set_ylabel("velocity, m/s (body)")
    ax.legend(fontsize=7, ncol=3, loc="upper right")
    ax.set_title(f"replay of {Path(result.recording).name}: profile {result.profile.value}, "
                 f"gyro {result.gyro_source.value} (grey: frames held or not engaged)", fontsize=10)
    ax = axes[1]
    if "rec_pitch_cmd_rad" in c:  # underneath, so the replayed commands stay visible
        ax.plot(t, np.degrees(c["rec_pitch_cmd_rad"]), color="0.55", lw=1.6, label="recorded pitch", zorder=1)
        ax.plot(t, np.degrees(c["rec_roll_cmd_rad"]), color="0.8", lw=1.6, label="recorded roll", zorder=1)
    ax.plot(t, np.degrees(c["pitch_cmd_rad"]), color="C0", lw=0.7, label="pitch command", zorder=2)
    ax.plot(t, np.degrees(c["roll_cmd_rad"]), "--", color="C1", lw=0.7, label="roll command", zorder=2)
    ax.set_ylabel("command, deg")
    ax.legend(fontsize=7, ncol=4, loc="upper right")
    ax = axes[2]
    if np.isfinite(c["flow_x_counts"]).any():
        ax.step(t, c["flow_x_counts"], where="post", color="C0", lw=0.6, label="flow x")
        ax.step(t, c["flow_y_counts"], "--", where="post", color="C1", lw=0.6, label="flow y")
        ax.set_ylabel("flow, counts/frame")
    else:
        ax.plot(t, c["scene_rate_x_rad_s"], color="C0", lw=0.6, label="scene rate x")
        ax.plot(t, c["scene_rate_y_rad_s"], "--", color="C1", lw=0.6, label="scene rate y")
        ax.set_ylabel("flow, rad/s")
    ax.legend(fontsize=7, loc="upper right")
    ax = axes[3]
    ax.plot(t, c["gyro_x_rad_s"], color="C0", lw=0.6, label="gyro x (roll rate)")
    ax.plot(t, c["gyro_y_rad_s"], "--", color="C1", lw=0.6, label="gyro y (pitch rate)")
    ax.set_ylabel("rad/s")
    ax2 = ax.twinx()
    ax2.plot(t, c["range_m"], color="C2", lw=0.8, label="range")
    ax2.set_ylabel("range, m")
    ax.legend(fontsize=7, loc="upper left")
    ax2.legend(fontsize=7, loc="upper right")
    ax.set_xlabel("t, s from the first record")
    held = c["hold_cause"] != ""
    if held.any():
        for a in axes:
            a.fill_between(t, 0, 1, where=held, transform=a.get_xaxis_transform(), color="0.85", lw=0,
                           step="post", zorder=0)
    for a in axes:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path
