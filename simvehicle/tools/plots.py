"""The paper's figures for a scenario run (matplotlib figures drawn to files, no screen: the
``Figure`` API, which needs no backend and changes no global matplotlib state)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from simvehicle.engines.scenarios import Pair, Run


def force_steps(force: Callable[[float], Pair], t_s: np.ndarray) -> list[tuple[float, float, float]]:
    """``(t_s, fx_n, fy_n)`` at each frame time where the external force ``force(t)`` (body axes, N)
    takes a new value, the first frame included when it is not zero: where a gust starts or stops."""
    steps: list[tuple[float, float, float]] = []
    last = (0.0, 0.0)
    for t in t_s:
        f = tuple(float(v) for v in force(float(t)))
        if f != last:
            steps.append((float(t), f[0], f[1]))
            last = f  # type: ignore[assignment]
    return steps


def _force_label(fx: float, fy: float) -> str:
    if fx == 0 and fy == 0:
        return "external force off"
    parts = [f"{name} {v:+g} N" for name, v in (("Fx", fx), ("Fy", fy)) if v != 0]
    return "gust: external force " + ", ".join(parts)


def run_figure(run: Run, *, force: Callable[[float], Pair] | None = None,
               title: str | None = None) -> Figure:
    """The figure ``plot_run`` saves. ``force`` is the external force the run was flown with (the
    scenario's own, body axes, N): each change is drawn as a vertical line on every panel and
    labelled with its size on the velocity panel."""
    c = run.columns
    if run.name in ("rail", "triangle"):
        keys = [k for k in c if k.startswith("counts_")]
        fig = Figure(figsize=(9, 2.2 * len(keys)))
        axes = fig.subplots(len(keys), 1, squeeze=False)
        for ax, k in zip(axes[:, 0], keys, strict=True):
            tag = k.removeprefix("counts_")
            ax.step(c[f"t_s_{tag}"], c[k], where="post", lw=0.8)
            unit = "m/s" if run.name == "rail" else "m altitude"
            ax.set_title(f"{run.name}: {tag} {unit}", fontsize=9)
            ax.set_ylabel("counts/sample")
        axes[-1, 0].set_xlabel("time (s)")
    else:
        t = c["t_s"]
        fig = Figure(figsize=(9, 10))
        axes = fig.subplots(4, 1, sharex=True, squeeze=False)
        ax = axes[0, 0]
        ax.plot(t, c["vx_set_m_s"], "k:", lw=1.2, label="setpoint vx")
        ax.plot(t, c["vy_set_m_s"], color="0.45", ls="-.", lw=1.0, label="setpoint vy")
        ax.plot(t, c["vx_m_s"], "C0", label="true vx")
        ax.plot(t, c["est_vx_m_s"], "C1", lw=0.7, label="estimate vx (eq. 15)")
        ax.plot(t, c["vy_m_s"], "C0--", lw=0.8, label="true vy")
        ax.plot(t, c["est_vy_m_s"], "C1--", lw=0.6, label="estimate vy (eq. 15)")
        ax.set_ylabel("velocity (m/s)")
        ax.legend(fontsize=7, loc="best", ncol=2)
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
        axes[0, 0].set_title(title or f"scenario {run.name}")
        for t0, fx, fy in force_steps(force, t) if force is not None else []:
            for ax in axes[:, 0]:
                ax.axvline(t0, color="tab:red", ls="--", lw=0.9, alpha=0.8)
            axes[0, 0].annotate(f"{_force_label(fx, fy)} from {t0:g} s", (t0, 1.0), xycoords=("data", "axes fraction"),
                                xytext=(3, -3), textcoords="offset points", ha="left", va="top", fontsize=7,
                                color="tab:red", bbox={"fc": "white", "ec": "none", "alpha": 0.85, "pad": 1})
    fig.tight_layout()
    return fig


def plot_run(run: Run, path: str | Path, *, force: Callable[[float], Pair] | None = None,
             title: str | None = None) -> Path:
    """Fig. 16-19 layout for closed-loop runs (velocity with both setpoints, attitude, flow counts,
    gyro, truth against estimate, x solid and y dashed; the external force's changes marked when
    ``force`` is given); Fig. 5/9 layout (counts per sample) for the rail runs."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = run_figure(run, force=force, title=title)
    fig.savefig(path, dpi=110)
    return path
