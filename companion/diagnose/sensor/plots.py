"""The sensor-only diagnosis's figure (a matplotlib ``Figure`` drawn to a file: no backend
chosen, no global matplotlib state changed; matplotlib is loaded only when a plot is drawn)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from companion.diagnose.sensor.band import rotation_content
from companion.diagnose.sensor.diagnosis import SensorDiagnosis
from companion.diagnose.sensor.motions import leg_reference


def plot_diagnosis(d: SensorDiagnosis, path: Path) -> None:
    """One figure per recording: the running displacement (Fig. 6) on x and y with the paper's
    nominal model (Q, no bias, no delay) and the extended one, the legs and their documented
    length; the band-passed counts against both models; the still-segment drift."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 8.5), layout="constrained")
    axs = fig.subplots(2, 2)
    nom = d.disp_nominal.path(1.0, 1.0)
    ext = d.disp_fitted.path(d.scale[0], d.scale[1])
    t = d.disp_fitted.t_s
    for a, ax in enumerate(axs[0]):
        unit = 1e3 if np.max(np.abs(ext)) < 0.01 else 100.0  # mm for a recording that does not move
        ax.plot(d.disp_nominal.t_s, unit * nom[:, a], "--", color="0.5", lw=1, label="paper model (Q, no bias)")
        ax.plot(t, unit * ext[:, a], color="C0" if a == 0 else "C1", lw=1.5,
                label=f"extended (scale {d.scale[a]:.2f}, bias, delay)")
        for lg in d.legs:
            if lg.axis != a:
                continue
            ax.axvspan(lg.start_s, lg.end_s, color="C2", alpha=0.12)
            base = float(np.mean(ext[(t >= lg.before[0]) & (t <= lg.before[1]), a])) \
                if np.any((t >= lg.before[0]) & (t <= lg.before[1])) else 0.0
            if d.motion is not None:
                ax.hlines(100 * (base + lg.direction * d.motion.leg_m), lg.after[0], lg.after[1], colors="C3", lw=2)
            ax.annotate(f"{100 * lg.length(1.0, 1.0):.1f} / {100 * lg.length(d.scale[0], d.scale[1]):.1f} cm",
                        (0.5 * (lg.start_s + lg.end_s), 100 * base), fontsize=8, ha="center",
                        xytext=(0, -12 if lg.direction > 0 else 12), textcoords="offset points")
        ax.set_title(f"{'xy'[a]} position from the flow (gyro rotation removed, times range), "
                     f"{'mm' if unit > 100 else 'cm'}")
        ax.set_xlabel("time from first row (s)")
        ax.set_ylabel("displacement (mm)" if unit > 100 else "displacement (cm)")
        ax.grid(alpha=0.3)
        if d.motion is not None:
            ax.plot([], [], color="C3", lw=2, label=f"{leg_reference(d.motion)} leg end")
        ax.legend(fontsize=8, loc="best")
    band = d.band
    ax = axs[1, 0]
    if band.fitted:
        u = band.use_
        tb = band.t_
        energy = np.convolve(np.where(u, np.sum(band.pred_fitted_ ** 2, axis=1), 0.0),
                             np.ones(max(1, int(4.0 / np.median(np.diff(tb))))), mode="same")
        c = tb[int(np.argmax(energy))]
        m = u & (tb >= c - 2.0) & (tb <= c + 2.0)
        for a, col in enumerate(("C0", "C1")):
            off = 3.0 * a
            ax.plot(tb[m], band.y_[m, a] + off, color=col, lw=1, label=f"recorded {'xy'[a]} (band-passed)")
            ax.plot(tb[m], band.pred_nominal_[m, a] + off, "--", color="0.4", lw=1,
                    label="paper model" if a == 0 else None)
            ax.plot(tb[m], band.pred_fitted_[m, a] + off, color="k", lw=1, label="extended" if a == 0 else None)
        ax.set_title(f"counts, {d.band.settings.band_low_hz:g}-{d.band.settings.band_high_hz:g} Hz band "
                     f"(y offset +3); delay {1e3 * band.delay_:.0f} ms")
        ax.legend(fontsize=8, loc="upper right")
    else:
        ax.text(0.5, 0.5, textwrap.fill(f"rotation band not fitted: {band.reason_}; {rotation_content(band)}", 60),
                ha="center", va="center", transform=ax.transAxes, fontsize=9)
    ax.set_xlabel("time from first row (s)")
    ax.set_ylabel("counts per reading")
    ax.grid(alpha=0.3)
    ax = axs[1, 1]
    s = d.series
    q = s.q_rad_per_count
    if d.legs and d.motion is not None:
        x = np.arange(len(d.legs))
        ax.bar(x - 0.2, [100 * lg.length(1.0, 1.0) for lg in d.legs], 0.4, color="0.6", label="paper model (Q)")
        ax.bar(x + 0.2, [100 * lg.length(d.scale[0], d.scale[1]) for lg in d.legs], 0.4, color="C0",
               label="extended (fitted scale)")
        ax.axhline(100 * d.motion.leg_m, color="C3", lw=2, label=leg_reference(d.motion))
        ax.axhspan(100 * d.motion.leg_m * (1 - d.band.settings.leg_tolerance_rel),
                   100 * d.motion.leg_m * (1 + d.band.settings.leg_tolerance_rel), color="C3", alpha=0.1)
        ax.set_xticks(x, [f"{lg.name}\n{lg.start_s:.0f}s" for lg in d.legs], fontsize=7)
        ax.set_ylabel("leg length (cm)")
        ax.set_title(f"reconstructed legs against the {'documented' if d.motion.documented else 'assumed'} "
                     f"length (+-{100 * d.band.settings.leg_tolerance_rel:.0f} % shaded), cm")
        ax.legend(fontsize=8, loc="lower right")
    else:
        tt = s.t_s[d.rows]
        g = s.gyro_at(tt)
        cover = np.r_[s.read_period_s, np.minimum(np.diff(tt), 2.0 * s.read_period_s)]
        still = np.zeros(len(tt), dtype=bool)
        for a0, b0 in d.bias.windows:
            still |= (tt >= a0) & (tt <= b0)
        flow_rot = np.column_stack([s.counts_y[d.rows] * q * d.scale[1], -s.counts_x[d.rows] * q * d.scale[0]])
        for a, (lab, col) in enumerate((("roll", "C0"), ("pitch", "C1"))):
            rate = np.where(still, g[:, a] - flow_rot[:, a] / s.read_period_s, 0.0)
            drift = np.cumsum(rate * cover)
            ax.plot(tt, 1e3 * drift, "--", color=col, lw=1, label=f"{lab}: paper model (no bias)")
            if np.isfinite(d.bias.bias[a]):
                ax.plot(tt, 1e3 * (drift - np.cumsum(np.where(still, d.bias.bias[a], 0.0) * cover)), color=col,
                        lw=1.5, label=f"{lab}: bias {1e3 * d.bias.bias[a]:+.1f} mrad/s removed")
        for a0, b0 in d.bias.windows:
            ax.axvspan(a0, b0, color="C2", alpha=0.1)
        ax.set_title("gyro angle minus flow angle over still segments (shaded)")
        ax.set_xlabel("time from first row (s)")
        ax.set_ylabel("angle (mrad)")
        ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.suptitle(f"{s.name}: paper's flow model vs recording (Q = {q:.5f} rad/count)")
    fig.savefig(path, dpi=90)
