"""The paper's figures for a scenario run (matplotlib, Agg backend: files only, no screen)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from simvehicle.scenarios import Run  # noqa: E402


def plot_run(run: Run, path: str | Path) -> Path:
    """Fig. 16-19 layout for closed-loop runs (velocity, attitude, flow counts, gyro, truth against
    estimate, x solid and y dashed); Fig. 5/9 layout (counts per sample) for the rail runs."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    c = run.columns
    if run.name in ("rail", "triangle"):
        keys = [k for k in c if k.startswith("counts_")]
        fig, axes = plt.subplots(len(keys), 1, figsize=(9, 2.2 * len(keys)), squeeze=False)
        for ax, k in zip(axes[:, 0], keys, strict=True):
            tag = k.removeprefix("counts_")
            ax.step(c[f"t_s_{tag}"], c[k], where="post", lw=0.8)
            unit = "m/s" if run.name == "rail" else "m altitude"
            ax.set_title(f"{run.name}: {tag} {unit}", fontsize=9)
            ax.set_ylabel("counts/sample")
        axes[-1, 0].set_xlabel("time (s)")
    else:
        t = c["t_s"]
        fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True, squeeze=False)
        ax = axes[0, 0]
        ax.plot(t, c["vx_set_m_s"], "k:", label="setpoint")
        ax.plot(t, c["vx_m_s"], "C0", label="true vx")
        ax.plot(t, c["est_vx_m_s"], "C1", lw=0.7, label="estimate vx (eq. 15)")
        ax.plot(t, c["vy_m_s"], "C0--", lw=0.8, label="true vy")
        ax.set_ylabel("velocity (m/s)")
        ax.legend(fontsize=7, loc="best")
        ax = axes[1, 0]
        ax.plot(t, np.degrees(c["pitch_rad"]), "C0", label="pitch")
        ax.plot(t, np.degrees(c["pitch_cmd_rad"]), "C3", lw=0.7, label="pitch command")
        ax.plot(t, np.degrees(c["roll_rad"]), "C0--", lw=0.8, label="roll")
        ax.set_ylabel("angle (deg)")
        ax.legend(fontsize=7, loc="best")
        ax = axes[2, 0]
        ax.step(t, c["flow_x_counts"], where="post", lw=0.8, label="dX")
        ax.step(t, c["flow_y_counts"], where="post", lw=0.8, ls="--", label="dY")
        ax.set_ylabel("flow (counts/frame)")
        ax.legend(fontsize=7, loc="best")
        ax = axes[3, 0]
        ax.plot(t, c["gyro_y_rad_s"], lw=0.8, label="pitch rate (gyro)")
        ax.plot(t, c["gyro_x_rad_s"], lw=0.8, ls="--", label="roll rate (gyro)")
        ax.set_ylabel("rate (rad/s)")
        ax.set_xlabel("time (s)")
        ax.legend(fontsize=7, loc="best")
        axes[0, 0].set_title(f"scenario {run.name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
