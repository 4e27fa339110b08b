"""The human report of a diagnosis: ``DIR/report.md`` with PNG plots beside it (matplotlib Agg).

Plots: the residual of every channel against time, nominal and with the chosen effects, with the
nominal model's mismatch windows shaded and each finding's windows marked; the nominal and the
extended model against the recording on the attitude loop, the flow's rotation content and the
force balance (the velocity change the model cannot explain); then a table of every effect tried
with its evidence, the unexplained mismatches and the notes.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from companion.diagnose.closed_loop.diagnosis import Diagnosis, GroupResult
from companion.diagnose.closed_loop.flowmodel import IDX
from companion.diagnose.report import Finding
from companion.errors import FlowholdError

MAX_POINTS = 20000
COLORS = {"nominal": "0.6", "extended": "tab:blue", "recorded": "k"}
FINDING_COLORS = ["tab:red", "tab:green", "tab:purple", "tab:orange", "tab:brown", "tab:pink", "tab:olive",
                  "tab:cyan"]


def _dec(*arrays: np.ndarray) -> list[np.ndarray]:
    n = len(arrays[0])
    step = max(1, math.ceil(n / MAX_POINTS))
    return [a[::step] for a in arrays]


def _broken(t: np.ndarray, *ys: np.ndarray) -> list[np.ndarray]:
    """(t, *ys) with a NaN row inserted in every gap over 2 s and over five times the median step
    (lost telemetry, the part of a long flight held back from the fit): a line is not drawn across
    what was not fitted."""
    if len(t) < 3:
        return [t, *ys]
    dt = np.diff(t)
    cut = np.flatnonzero(dt > max(2.0, 5.0 * float(np.median(dt)))) + 1
    return [np.insert(np.asarray(a, dtype=float), cut, np.nan) for a in (t, *ys)]


def _plt() -> Any:  # matplotlib's pyplot module
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _finding_colors(findings: list[Finding]) -> dict[str, str]:
    return {f.effect: FINDING_COLORS[i % len(FINDING_COLORS)] for i, f in enumerate(findings)}


def plot_residuals(diag: Diagnosis, path: Path) -> Path:
    plt = _plt()
    rows = [(res, c) for res in diag.groups.values() for c in range(len(res.group.channels))]
    fig, axes = plt.subplots(len(rows), 1, figsize=(11, 1.7 * len(rows)), sharex=True)
    sig = diag.report.significant()
    colors = _finding_colors(sig)
    for ax, (res, c) in zip(np.atleast_1d(axes), rows, strict=True):
        g = res.group
        ch = g.channels[c]
        t = g.row_times[c]
        order = np.argsort(t, kind="stable")
        tt, rn, rf = _broken(*_dec(t[order], res.r_nominal[c][order], res.r_final[c][order]))
        ax.plot(tt, rn, color=COLORS["nominal"], lw=0.6, label="nominal model")
        ax.plot(tt, rf, color=COLORS["extended"], lw=0.6, label="with the effects found")
        for iv in res.mismatch_windows.get(ch, []):
            ax.axvspan(iv.start_s, iv.end_s, color="tab:red", alpha=0.08, lw=0)
        y_top = ax.get_ylim()[1]
        for f in sig:
            for w in f.where:
                if w.channel == ch:
                    ax.plot([w.start_s, w.end_s], [y_top, y_top], color=colors[f.effect], lw=4, solid_capstyle="butt")
        ax.set_ylabel(f"{ch}\n[{g.units[c]}]", fontsize=8)
        ax.tick_params(labelsize=7)
    axes_list = np.atleast_1d(axes)
    axes_list[0].legend(loc="upper right", fontsize=7, ncol=2)
    handles = [plt.Line2D([], [], color=colors[f.effect], lw=4, label=f.effect) for f in sig]
    if handles:
        axes_list[1].legend(handles=handles, loc="upper right", fontsize=7, ncol=min(4, len(handles)))
    axes_list[-1].set_xlabel("time from the first record (s)")
    fig.suptitle("Residual of each channel (shaded: where the nominal model departs from the noise; "
                 "bars: where each finding acts)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _zoom(t: np.ndarray, r: np.ndarray, width_s: float) -> tuple[float, float]:
    """The window of ``width_s`` where |r| is largest on average."""
    if len(t) == 0:
        return 0.0, width_s
    if t[-1] - t[0] <= width_s:
        return float(t[0]), float(t[-1])
    cs = np.concatenate([[0.0], np.cumsum(r ** 2)])
    j = np.searchsorted(t, t + width_s)
    score = cs[np.minimum(j, len(t))] - cs[: len(t)]
    score[t + width_s > t[-1]] = -1
    i = int(np.argmax(score))
    return float(t[i]), float(t[i] + width_s)


def plot_models(diag: Diagnosis, path: Path) -> Path:
    """Nominal and extended model against the recording on three channels."""
    plt = _plt()
    d = diag.data
    att = diag.groups["attitude"]
    flow = diag.groups["flow"]
    ap = diag.attitude
    g0 = att.group.nominal
    p = att.final.p
    y_nom = ap.simulate(float(g0[0]), float(g0[1]), float(g0[2]))
    y_ext = ap.simulate(float(p[0]), float(p[1]), float(p[2]))
    fig, axes = plt.subplots(3, 2, figsize=(12, 9))
    for i, (name, ang) in enumerate((("pitch", d.pitch_rad), ("roll", d.roll_rad))):
        ax = axes[0, i]
        k = 1 if name == "pitch" else 0
        a, b = _zoom(att.group.row_times[k], att.r_nominal[k], 10.0)
        m = (d.t_s >= a) & (d.t_s <= b)
        ax.step(d.t_s[m], np.degrees(d.pitch_cmd_rad if name == "pitch" else d.roll_cmd_rad)[m], where="post",
                color="tab:orange", lw=0.8, label="command (active)")
        ax.plot(d.t_s[m], np.degrees(ang[m]), color=COLORS["recorded"], lw=1.2, label="recorded")
        ax.plot(d.t_s[m], np.degrees(y_nom[k][m] - np.mean(y_nom[k] - ang)), color=COLORS["nominal"], lw=1,
                ls="--", label="nominal model")
        ax.plot(d.t_s[m], np.degrees(y_ext[k][m] - np.mean(y_ext[k] - ang)), color=COLORS["extended"], lw=1,
                label="with the effects found")
        ax.set_title(f"attitude loop, {name} (deg)", fontsize=9)
        ax.legend(fontsize=7)
    # flow rotation content: the recorded scene-angle rate against the model's, nominal and extended
    fp = diag.flow
    pf = flow.final.p
    for i, axis in enumerate(("x", "y")):
        ax = axes[1, i]
        res_nom = flow.r_nominal[i]
        tf = flow.group.row_times[i]
        a, b = _zoom(tf, res_nom, 4.0)
        m = (d.t_s >= a) & (d.t_s <= b)
        rate_meas = np.gradient(fp.Phi[i], d.t_s)
        ax.plot(d.t_s[m], rate_meas[m], color=COLORS["recorded"], lw=1, label="recorded flow rate")
        rot_nom = fp.Rdot[i]
        rot_ext = pf[IDX["gain"]] * np.interp(d.t_s - pf[IDX["delay"]], d.t_s, fp.Rdot[i]) / \
            pf[IDX["scale_x" if i == 0 else "scale_y"]]
        ax.plot(d.t_s[m], rot_nom[m], color=COLORS["nominal"], ls="--", lw=1, label="rotation, nominal")
        ax.plot(d.t_s[m], rot_ext[m], color=COLORS["extended"], lw=1, label="rotation, with the effects")
        ax.set_title(f"flow {axis}: scene-angle rate and its rotation part (rad/s)", fontsize=9)
        ax.legend(fontsize=7)
    # force balance: the velocity change the model cannot explain (integrated force residual / m)
    m_kg = diag.cfg.airframe.mass_kg
    for i, axis in enumerate(("x", "y")):
        ax = axes[2, i]
        tw = flow.group.row_times[2 + i]
        span = fp.force.t_end_s - fp.force.t_start_s
        for r, style, label in ((flow.r_nominal[2 + i], dict(color=COLORS["nominal"], ls="--"), "nominal model"),
                                (flow.r_final[2 + i], dict(color=COLORS["extended"]), "with the effects found")):
            ax.plot(tw, np.cumsum(r * span / m_kg), lw=1, label=label, **style)
        ax.axhline(0, color="k", lw=0.5)
        st = flow.final.state
        if "wind_force" in flow.chosen and st:
            ax.axvspan(st["start_s"], st["end_s"], color="tab:red", alpha=0.1, label="wind window")
        ax.set_title(f"force balance {axis}: velocity the model cannot explain (m/s)", fontsize=9)
        ax.set_xlabel("time (s)", fontsize=8)
        ax.legend(fontsize=7)
    for ax in axes.ravel():
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_velocity(diag: Diagnosis, path: Path) -> Path | None:
    """Flow-derived velocity under the nominal and the fitted sensor geometry; the recording's
    LOCAL_POSITION_NED (when present) drawn for comparison only."""
    plt = _plt()
    d = diag.data
    fp = diag.flow
    fig, axes = plt.subplots(2, 1, figsize=(11, 5), sharex=True)
    for p, style, label in ((diag.groups["flow"].group.nominal, dict(color=COLORS["nominal"], ls="--"), "nominal"),
                            (diag.groups["flow"].final.p, dict(color=COLORS["extended"]), "with the effects")):
        X, _ = fp.flow_velocity(p)
        for i in (0, 1):
            v = np.zeros(d.n)
            for a, b in d.segments():
                if b - a > 5:
                    k = 5
                    v[a + k:b - k] = (X[i, a + 2 * k:b] - X[i, a:b - 2 * k]) / (d.t_s[a + 2 * k:b] - d.t_s[a:b - 2 * k])
            tt, vv = _dec(d.t_s, v)
            axes[i].plot(tt, vv, lw=0.7, label=f"from the flow, {label} (0.2 s mean)", **style)
    for i, tv in enumerate((d.truth_vx_m_s, d.truth_vy_m_s)):
        if np.any(np.isfinite(tv)):
            tt, vv = _dec(d.t_s, tv)
            axes[i].plot(tt, vv, color="k", lw=0.6, alpha=0.7, label="LOCAL_POSITION_NED (plot only)")
        axes[i].set_ylabel(f"v{'xy'[i]} (m/s)", fontsize=8)
        axes[i].legend(fontsize=7, loc="upper right")
    axes[1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fmt_params(f: Finding) -> str:
    parts = []
    for k, v in f.parameters.items():
        u = f.uncertainty.get(k, math.nan)
        parts.append(f"{k} = {v:.4g} ± {u:.2g}" if math.isfinite(u) else f"{k} = {v:.4g}")
    return ", ".join(parts)


def _group_lines(res: GroupResult) -> list[str]:
    g = res.group
    out = []
    for c, ch in enumerate(g.channels):
        rn = float(np.sqrt(np.mean(res.r_nominal[c] ** 2))) if len(res.r_nominal[c]) else math.nan
        rf = float(np.sqrt(np.mean(res.r_final[c] ** 2))) if len(res.r_final[c]) else math.nan
        out.append(f"| {ch} | {g.units[c]} | {rn:.4g} | {rf:.4g} | {res.selector.sigma[c]:.3g} |")
    return out


def write_report(diag: Diagnosis, out_dir: str | Path) -> Path:
    """Write ``out_dir/report.md`` and its PNGs; returns the report's path."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FlowholdError(f"cannot create the report folder {out}: {exc.strerror}") from None
    rep = diag.report
    plot_residuals(diag, out / "residuals.png")
    plot_models(diag, out / "models.png")
    plot_velocity(diag, out / "velocity.png")
    d = diag.data
    lines = [f"# Mismatch report: {rep.recording}", ""]
    lines += [f"- {n}" for n in rep.notes]
    lines += ["", f"Nominal model: `{diag.cfg.source}`. Times are seconds from the first record. Method: "
              "docs/diagnose.md.", ""]
    sig = rep.significant()
    lines += ["## What the model leaves out", ""]
    if not sig:
        lines += ["No candidate effect earns its parameters: within its noise the recording follows the nominal "
                  "model.", ""]
    for f in sig:
        fit = f.fit
        ev = f.evidence
        lines += [f"### {f.effect}: {_fmt_params(f)}", "", f.explanation, ""]
        if fit is not None:
            lines.append(f"- held-out residual of `{ev.get('channel')}`: {fit.heldout_rms_before:.4g} → "
                         f"{fit.heldout_rms_after:.4g} {ev.get('unit', '')} ({fit.improvement_pct:.1f} % lower)")
        lines.append(f"- evidence: Wald z = {ev.get('wald_z', math.nan):.1f}, paired held-out t = "
                     f"{ev.get('cv_t', math.nan):.1f}, ΔBIC = {ev.get('delta_bic', math.nan):+.0f}"
                     + (" (at the fastest the frames resolve: judged by its held-out z, the Wald z has no "
                        "meaning at that bound)" if ev.get("at_resolution_bound") else "")
                     + (f"; the accelerometer, which the fit does not use, z = {ev['accelerometer_z']:.1f} over "
                        f"{ev.get('accelerometer_rows', 0)} windows" if "accelerometer_z" in ev else ""))
        if f.where:
            lines.append("- where it acts: " + "; ".join(f"{w.channel} {w.start_s:.1f}–{w.end_s:.1f} s"
                                                         for w in f.where))
        cond = ev.get("conditions")
        if cond:
            edges = cond["edges"]
            rms = cond["rms"]
            j = int(np.argmax(rms))
            lines.append(f"- it shows most at {cond['condition']} {edges[j]:.3g}–{edges[j + 1]:.3g} {cond['unit']} "
                         f"(its contribution's RMS per quartile: " + ", ".join(f"{x:.3g}" for x in rms) + ")")
        lines.append("")
    lines += ["![residuals](residuals.png)", "", "![models](models.png)", "", "![velocity](velocity.png)", ""]
    lines += ["## Every effect tried", "",
              "| effect | significant | parameters (± 1 sigma) | channel | held-out RMS before → after | Wald z | "
              "held-out t | ΔBIC | why not |",
              "|---|---|---|---|---|---|---|---|---|"]
    for f in rep.findings:
        ev = f.evidence
        fit = f.fit
        ho = (f"{fit.heldout_rms_before:.4g} → {fit.heldout_rms_after:.4g} ({fit.improvement_pct:+.1f} %)"
              if fit else "")
        why = "; ".join(ev.get("why_not", []))
        z, tt, db = ev.get("wald_z", math.nan), ev.get("cv_t", math.nan), ev.get("delta_bic", math.nan)
        lines.append(f"| {f.effect} | {'**yes**' if f.significant else 'no'} | {_fmt_params(f)} | "
                     f"{ev.get('channel', '')} | {ho} | {z:.1f} | {tt:.1f} | {db:+.0f} | {why} |")
    lines += ["", "## Unexplained", ""]
    if not rep.unexplained:
        lines += ["Nothing: what the chosen model leaves is noise (no sliding window above twice the noise, no "
                  "candidate term that predicts held-out residual).", ""]
    else:
        lines += ["| channel | from (s) | to (s) | RMS | best-fitting candidate term |", "|---|---|---|---|---|"]
        for u in rep.unexplained:
            lines.append(f"| {u.channel} | {u.start_s:.1f} | {u.end_s:.1f} | {u.rms:.4g} | {u.best_term or ''} |")
        lines.append("")
    lines += ["## Channels", "", "| channel | unit | RMS nominal | RMS with the effects | noise scale |",
              "|---|---|---|---|---|"]
    for res in diag.groups.values():
        lines += _group_lines(res)
    lines += ["", f"{d.n} flow frames, {d.duration_s:.1f} s; run time: "
              + ", ".join(f"{k} {v:.2f} s" for k, v in diag.timings.items()), ""]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
