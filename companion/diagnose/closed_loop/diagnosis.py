"""The closed-loop diagnosis: recording -> channels -> effects chosen per group -> Report.

``diagnose(rec, cfg)`` runs the three groups (``groups``), fills the mismatch report of
CONVENTIONS.md (``companion.diagnose.report.Report``) and keeps everything the human report plots
(``Diagnosis``). Nothing here sees a simulator's settings: only the recording and the nominal
parameter set.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config
from companion.diagnose.advice import actions, recorded_parameters
from companion.diagnose.closed_loop.attitude import AttitudeProblem
from companion.diagnose.closed_loop.channels import FlightData, extract
from companion.diagnose.closed_loop.excitation import LOOP_EFFECTS, LoopForm, loop_form
from companion.diagnose.closed_loop.explain import explain
from companion.diagnose.closed_loop.flowmodel import AXIS_SIGN, IDX, FlowProblem
from companion.diagnose.closed_loop.groups import (
    GEOMETRY_EFFECTS,
    IV_GAP_FRAMES,
    IV_MIN_F,
    FlowGroupState,
    GyroProblem,
    attitude_group,
    flow_group,
    gyro_group,
    lag_by_instruments,
    lever_arm_observable,
)
from companion.diagnose.closed_loop.locate import (
    STRETCH_TIMES_NOISE,
    Interval,
    coloured_factor,
    conditions,
    effect_windows,
    excess_windows,
    typical_window_rms,
    white_noise,
)
from companion.diagnose.closed_loop.select import Comparison, Group, ModelScore, Selector, Settings
from companion.diagnose.closed_loop.sizes import misfit_floor
from companion.diagnose.closed_loop.sparse import SparseFit, Term, sparse_fit
from companion.diagnose.report import Finding, Fit, Report, Unexplained, Window
from companion.errors import RecordingError
from companion.recordings.load import Recording

#: an unexplained residual this many times its channel's noise means the model does not fit
MISFIT_TIMES_NOISE = 3.0
#: effects that can stand in for one another where a flight does not separate them (the flow's
#: scale and its rotation gain when the translation is weak; a range offset and a scale at one
#: height; a lever arm and a rotation gain at one height; linear and form drag at one speed; a
#: drag and a wind over a stretch flown at one speed, where the drag is a constant force)
ALIKE = {
    "flow_scale": ("flow_rotation_gain", "range_offset", "flow_lever_arm"),
    "flow_rotation_gain": ("flow_scale", "flow_lever_arm"),
    "flow_lever_arm": ("flow_rotation_gain", "flow_scale"),
    "range_offset": ("flow_scale",),
    "linear_drag": ("quadratic_drag", "wind_force"),
    "quadratic_drag": ("linear_drag", "wind_force"),
    "wind_force": ("linear_drag", "quadratic_drag"),
    # below the loop's bandwidth a second-order loop lags its command by 2 zeta / Omega_p: a
    # command delay d and a loop slower by that much answer slow commands alike
    "attitude_dynamics": ("attitude_delay",),
    "attitude_delay": ("attitude_dynamics",),
}
#: a recording with more than 1.5 x this much usable flight (s) is fitted on ``FIT_BLOCK_S`` blocks
#: spread evenly over its flown time (``flown_time_s``) that add up to this much, and the rest is
#: held back to check the fitted model (``fit_blocks``, ``_check_held_back``). Why: issue 12's
#: budget, under a quarter of pymavlink's bare read time for an hour whatever the recording, which
#: every frame of a lossy hour missed by half (10.4 s against 22.5 s: thousands of attitude
#: segments, the flow group twice); fitted on 15 of its 60 minutes, the same three effects are
#: found, their sigmas about twice as large (docs/diagnose.md section 6). Fifteen minutes of flight
#: pin every parameter far inside the effects' size thresholds (``sizes``); what acts only in the
#: held-back part is still said, as an unexplained stretch. ``diagnose(fit_span_s=None)``
#: (``--fit-all``) fits every frame.
FIT_SPAN_S = 900.0
#: the length of one fitted block (s): long against the attitude loop, the flow and force windows
#: (1 s) and the cross-validation's time blocks, so that the blocks' ends cost little
FIT_BLOCK_S = 60.0
#: a sparse model must predict at least this fraction of a residual's held-out sum of squares, and
#: what it predicts must be larger than the channel's resolution, to be reported as unexplained
SPARSE_MIN_R2 = 0.2


@dataclass
class GroupResult:
    """One group's fit: chosen effects, their evidence, and the residuals before and after."""

    group: Group
    selector: Selector
    chosen: list[str]
    final: ModelScore
    evidence: dict[str, Comparison]
    r_nominal: list[np.ndarray]
    r_final: list[np.ndarray]
    sparse: dict[str, SparseFit] = field(default_factory=dict)
    unexplained_windows: dict[str, list[Interval]] = field(default_factory=dict)
    mismatch_windows: dict[str, list[Interval]] = field(default_factory=dict)
    #: the attitude group: the chosen loop refitted on the commands' slow and fast parts (``excitation``)
    loop_form: LoopForm | None = None


@dataclass
class Diagnosis:
    """Everything a diagnosis found, for the JSON report and the human report."""

    data: FlightData
    cfg: Config
    report: Report
    groups: dict[str, GroupResult]
    attitude: AttitudeProblem
    gyro: GyroProblem
    flow: FlowProblem
    flow_state: FlowGroupState
    timings: dict[str, float]


def _params(effect: str, g: Group, score: ModelScore, evidence_state: dict[str, float]) -> tuple[
        dict[str, float], dict[str, float]]:
    cand = next(c for c in g.candidates if c.effect == effect)
    idx = g.index(cand.params)
    p = {n: float(score.p[i]) for n, i in zip(cand.params, idx, strict=True)}
    sd = {n: float(math.sqrt(max(score.cov[i, i], 0.0))) for n, i in zip(cand.params, idx, strict=True)}
    if effect == "flow_lever_arm":
        # CONVENTIONS.md names rx, ry, rz; only rz shows without yaw rate: rx, ry stay at the
        # centre of gravity, not fitted (no uncertainty)
        p = {"rx": 0.0, "ry": 0.0, **p}
        sd = {"rx": math.nan, "ry": math.nan, **sd}
    if effect == "wind_force":
        st = score.state or evidence_state
        p["start_s"] = float(st.get("start_s", math.nan))
        p["end_s"] = float(st.get("end_s", math.nan))
        # the ends' uncertainty from the profile of the fit over each end (``wind.locate``); the
        # per-fold windows are not used: a fold whose held-out block touches an end cannot place it
        sd["start_s"] = float(st.get("start_sd", math.nan))
        sd["end_s"] = float(st.get("end_sd", math.nan))
    return p, sd


def _cond_values(data: FlightData, fp: FlowProblem, p_flow: np.ndarray) -> dict[str, np.ndarray]:
    """Per-frame operating conditions: speed from the flow under the final geometry, tilt, body
    rate from the attitude, height from the rangefinder."""
    X, _ = fp.flow_velocity(p_flow)
    v = np.zeros_like(X)
    for a, b in data.segments():
        if b - a > 1:
            v[:, a:b] = np.gradient(X[:, a:b], data.t_s[a:b], axis=1)
    rate = np.zeros(data.n)
    for a, b in data.segments():
        if b - a > 1:
            rr = np.gradient(data.roll_rad[a:b], data.t_s[a:b])
            pr = np.gradient(data.pitch_rad[a:b], data.t_s[a:b])
            rate[a:b] = np.hypot(rr, pr)
    return {"speed_m_s": np.hypot(v[0], v[1]), "tilt_rad": np.hypot(data.roll_rad, data.pitch_rad),
            "rate_rad_s": rate, "altitude_m": data.range_m}


def _terms(name: str, data: FlightData, ap: AttitudeProblem, gp: GyroProblem, fp: FlowProblem,
           res: GroupResult, c: int, fstate: FlowGroupState, loop: np.ndarray | None) -> list[Term]:
    """Candidate-term library for channel c of a group (rows aligned with its residual). ``loop``:
    the fitted attitude loop's attitude for the recorded commands (``_loop_attitude``), simulated
    once for every channel."""
    t = data.t_s
    segs = data.segments()

    def grad(y: np.ndarray) -> np.ndarray:
        out = np.zeros_like(y)
        for a, b in segs:
            if b - a > 1:
                out[..., a:b] = np.gradient(y[..., a:b], t[a:b], axis=-1)
        return out

    if name == "attitude":
        p = res.final.p
        y = ap.simulate(float(p[0]), float(p[1]), float(p[2]))
        u = ap.delayed_command(float(p[2]))
        yd = grad(y)
        ydd = grad(yd)
        ud = grad(u)
        o = 1 - c
        rows = ap.rows
        y, u, yd, ydd, ud = y[:, rows], u[:, rows], yd[:, rows], ydd[:, rows], ud[:, rows]
        return [Term("tracking error", "command minus attitude: a gain error of the loop", "rad", u[c] - y[c]),
                Term("attitude rate", "damping different from zeta", "rad/s", yd[c]),
                Term("angular acceleration", "inertia or a lag in the loop", "rad/s^2", ydd[c]),
                Term("command", "a command scale (DC gain) error", "rad", u[c]),
                Term("command rate", "feed-forward or input shaping", "rad/s", ud[c]),
                Term("cubic tracking error", "a saturating or rate-limited loop", "rad^3", (u[c] - y[c]) ** 3),
                Term("rate |rate|", "a rate-dependent (aerodynamic) damping", "rad^2/s^2", yd[c] * np.abs(yd[c])),
                Term("other-axis attitude", "roll-pitch coupling", "rad", y[o]),
                Term("other-axis rate", "gyroscopic or mixer coupling", "rad/s", yd[o])]
    if name == "gyro":
        # regressors from the attitude the fitted loop gives for the recorded commands, not from the
        # recorded attitude: differentiated, the recorded attitude's own noise would sit in both the
        # residual and the regressor and read as a gyro scale error (errors in variables)
        # (rows the simulation does not reach, e.g. between the attitude fit's segments after lost
        # commands, take the gyro's own mean rate: its noise is not the attitude's either)
        r = gp.gyro.copy()
        if loop is not None:
            sim = (loop[:, gp.k] - loop[:, gp.k_prev]) / (t[gp.k] - t[gp.k_prev])
            ok = np.isfinite(sim)
            r[ok] = sim[ok]
        rd = np.gradient(r, gp.t_s, axis=1) if r.shape[1] > 1 else np.zeros_like(r)
        o = 1 - c
        w = gp.whiten[c]  # through the filter the channel's residual went through (``gyro_whitener``)
        return [Term("attitude rate", "a gyro scale-factor error", "rad/s", w(r[c])),
                Term("angular acceleration", "the gyro lags the attitude (a low-pass filter or a delay)",
                     "rad/s^2", w(rd[c])),
                Term("other-axis rate", "gyro axes not aligned with the attitude axes", "rad/s", w(r[o])),
                Term("attitude", "a g-sensitive or attitude-dependent gyro error", "rad", w(gp.angle[c])),
                Term("rate cubed", "a non-linear gyro scale", "rad^3/s^3", w(r[c] ** 3))]
    if name == "flow":
        W = fp.flow.idx
        if c >= 2:
            return _force_terms(data, fp, res, c - 2, loop)
        i, o = c, 1 - c
        R, Rd = _flow_term_rotation(data, fp, fstate, loop, grad)
        Rdd = grad(Rd)
        # translation from the plant (never from the recorded flow, which holds the residual's noise)
        off = float(res.final.p[IDX["offset"]])
        dl = float(res.final.p[IDX["delay"]])
        Y = fp.model_translation(off, dl)
        YA = fp.model_translation(off, dl, power=2)
        raw = [("rotation", "a rotation scale error of the flow", "rad", R[i][W]),
               ("rotation rate", "a timing error between flow and attitude", "rad/s", Rd[i][W]),
               ("rotation acceleration", "a filter in the flow or attitude path", "rad/s^2", Rdd[i][W]),
               ("other-axis rotation", "cross-talk between the flow axes", "rad", R[o][W]),
               ("other-axis rotation rate", "cross-talk with a timing error", "rad/s", Rd[o][W]),
               ("translation", "a translation scale error (range or lens)", "rad", Y[i]),
               ("translation / height", "a range error that grows at low height", "rad/m", YA[i]),
               ("other-axis translation", "the flow axes turned with respect to the motion", "rad", Y[o]),
               ("rotation squared", "a non-linear flow response", "rad^2", R[i][W] ** 2)]
        return [Term(n, w, u, fstate.whiten[i](fp.project_windows(v)).ravel()) for n, w, u, v in raw]
    return []


def _flow_term_rotation(data: FlightData, fp: FlowProblem, fstate: FlowGroupState, loop: np.ndarray | None,
                        grad: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The rotation (2, n frames, the flow's axes) and its rate that the flow channels' terms are
    regressed on: the effects' regressors' (``fp.R``, the gyro's) when the residual's rotation is
    the attitude estimate's; else the fitted loop's attitude (``loop``, ``_loop_attitude``; the
    recorded attitude where it does not reach, or without a loop). Why: a residual whose rotation
    is the gyro's, or the flow message's own body rate (the autopilot's gyro over each frame),
    holds the gyro's noise, and regressed on a rotation from that same gyro the noise read as a
    filter in the flow path: +2.4e-4 to 3.3e-4 rad per rad/s^2 of rotation acceleration on 8
    ArduPilot-profile recordings of the generalisation matrix (two of them clean hovers, whose
    residual was at its noise: errors in variables). The loop's attitude follows the rotation as the
    gyro does (rate correlation 0.995 on gen_0186) without its noise. The cost: what the shared
    noise added to a real term is gone too (gen_0186's missed 10 ms flow delay, once listed as
    -0.0093 rad per rad/s of rotation rate, is listed no more)."""
    if fstate.source == "attitude":
        return fp.R, fp.Rdot
    ang = _loop_or_recorded(data, loop)
    R = np.zeros((2, data.n))
    for a, b in data.segments():
        for i in (0, 1):
            R[i, a:b] = AXIS_SIGN[i] * (ang[i][a:b] - ang[i][a])
    return R, grad(R)


def _loop_or_recorded(data: FlightData, loop: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(pitch, roll): the fitted loop's attitude (``loop``, [roll, pitch], ``_loop_attitude``), the
    recorded attitude where its simulation does not reach or without a loop."""
    rec = (data.pitch_rad, data.roll_rad)
    if loop is None:
        return rec
    return (np.where(np.isfinite(loop[1]), loop[1], rec[0]), np.where(np.isfinite(loop[0]), loop[0], rec[1]))


def _loop_attitude(ap: AttitudeProblem) -> np.ndarray | None:
    """The attitude (2, n frames) [roll, pitch] that the fitted attitude loop gives for the
    recorded commands (NaN where its simulation does not reach), or None before a loop is fitted:
    the unexplained terms' attitude regressors, where the recorded attitude's own noise would sit
    in both the residual and the regressor and read as an effect (errors in variables)."""
    if ap.final_p is None:
        return None
    return ap.simulate(*(float(x) for x in ap.final_p))


def _force_terms(data: FlightData, fp: FlowProblem, res: GroupResult, i: int,
                 loop: np.ndarray | None = None) -> list[Term]:
    """Window means, per force window, of the candidate force terms of axis i. The tilt term is
    the attitude of the fitted loop (``loop``, ``_loop_attitude``; the recorded attitude where it
    does not reach): the force residual holds the recorded tilt's noise (g tan(tilt), integrated),
    and regressed on that same recorded tilt the noise read as a tilt scale error (it cleared 2 of
    the 18 clean flights of the generalisation matrix that listed an unexplained entry; on
    ``--seed 1`` 2 of 22, and one other came up). What the loop's attitude does not remove is
    the turbulence: the commands follow the velocity the turbulence moves, so the loop tilts
    against it and the tilt still predicts its force; the loop's terms are therefore their
    setpoint-driven part (``_setpoint_driven``; docs/diagnose.md, section 8)."""
    t = data.t_s
    X, _ = fp.flow_velocity(res.final.p)
    k0, k1 = fp.force.idx[:, 0], fp.force.idx[:, 1]
    span = t[k1] - t[k0]

    def wmean(y: np.ndarray) -> np.ndarray:
        cs = np.zeros_like(y)
        cs[1:] = np.cumsum(0.5 * (y[1:] + y[:-1]) * np.diff(t))
        return (cs[k1] - cs[k0]) / span

    v = np.zeros_like(X)
    for a, b in data.segments():
        if b - a > 1:
            v[:, a:b] = np.gradient(X[:, a:b], t[a:b], axis=1)
    o = 1 - i
    tilt = _loop_or_recorded(data, loop)[i]
    climb = np.zeros(data.n)
    for a, b in data.segments():
        if b - a > 1:
            climb[a:b] = np.gradient(data.range_m[a:b], t[a:b])
    raw = [("velocity", "a drag proportional to speed", "m/s", v[i]),
           ("velocity |velocity|", "a quadratic (form) drag", "m^2/s^2", v[i] * np.abs(v[i])),
           ("sign(velocity)", "a constant-magnitude friction-like force", "1", np.tanh(v[i] / 0.05)),
           ("constant", "a steady force (wind, or a tilt-estimate offset)", "1", np.ones(data.n)),
           ("tilt", "a thrust or tilt-estimate scale error, or a flow scale error on this axis", "rad", tilt),
           ("height", "ground effect", "m", data.range_m),
           ("climb rate", "thrust changes while climbing", "m/s", climb),
           ("other-axis velocity", "coupling between the axes", "m/s", v[o])]
    return _setpoint_driven([Term(n, w, u, wmean(y)) for n, w, u, y in raw], _setpoint_instruments(data, wmean))


#: the force terms the horizontal loop answers a disturbance with (its velocity and tilt), and so
#: correlated with the disturbance's force whatever the physics; the height, the climb rate and the
#: constant are the vertical loop's or nobody's, and stay as they are
LOOP_ANSWERED = ("velocity", "velocity |velocity|", "sign(velocity)", "tilt", "other-axis velocity")


#: the setpoint lags (s) whose window means are the force terms' instruments
#: (``_setpoint_instruments``), in the order they are taken when the windows carry only some
SETPOINT_LAGS_S = (0.0, 1.0, 0.5, 2.0)
#: force windows per instrument column at least (both axes' setpoints at each lag, and a constant)
WINDOWS_PER_INSTRUMENT = 4


def _setpoint_driven(terms: list[Term], Z: np.ndarray | None) -> list[Term]:
    """``terms`` with each of the horizontal loop's (``LOOP_ANSWERED``) replaced by its part the
    instruments ``Z`` (``_setpoint_instruments``, per row) predict: the first stage of two-stage
    least squares. A disturbance moves the velocity and the loop tilts against it, so those terms
    regressed on the force residual (the disturbance itself) read the turbulence as a drag or a
    tilt scale; their setpoint-driven part is uncorrelated with it, and a real law (a drag on the
    velocity the setpoints ask for) is still read, without the loop's attenuation. A hold's
    (instruments that are the constant alone) are a constant and left out; without instruments
    (None) the terms are as they are."""
    if Z is None:
        return terms
    Zp = np.linalg.pinv(Z)
    out = []
    for t in terms:
        if t.name in LOOP_ANSWERED and np.all(np.isfinite(t.values)):
            t = replace(t, values=Z @ (Zp @ t.values))
            if np.ptp(t.values) <= 1e-12 * max(1.0, float(np.max(np.abs(t.values)))):
                continue  # a hold's: a constant, which says nothing the constant term does not
        out.append(t)
    return out


def _setpoint_instruments(data: FlightData, wmean: Callable[[np.ndarray], np.ndarray]) -> np.ndarray | None:
    """Per force window, the window means of both axes' velocity setpoints at ``SETPOINT_LAGS_S``
    (as many lags as ``WINDOWS_PER_INSTRUMENT`` allows) and a constant: what drives the flight that
    no disturbance reaches (the reference signal of closed-loop identification). A hold (setpoints
    that never change) gives the constant alone: all the loop's velocity and tilt do there is
    answer disturbances. None where the recording has no setpoint or too few windows."""
    sx, sy = data.vx_set_m_s, data.vy_set_m_s
    if not (np.any(np.isfinite(sx)) and np.any(np.isfinite(sy))):
        return None
    t = data.t_s
    n_windows = len(wmean(t))
    bases = []
    for sp in (sx, sy):
        ok = np.isfinite(sp)
        bases.append(np.interp(t, t[ok], sp[ok]))
    if max(float(np.ptp(b)) for b in bases) <= 1e-9:  # a hold
        return np.ones((n_windows, 1)) if n_windows >= WINDOWS_PER_INSTRUMENT else None
    # as many lags as the windows carry: a first stage with nearly as many columns as rows
    # predicts the disturbance too (a 28 s flight has 25 one-second windows)
    n_lags = min(len(SETPOINT_LAGS_S), (n_windows // WINDOWS_PER_INSTRUMENT - 1) // 2)
    if n_lags < 1:
        return None
    cols = [wmean(np.interp(t - lag, t, base)) for base in bases for lag in SETPOINT_LAGS_S[:n_lags]]
    Z = np.column_stack([np.ones(n_windows), *cols])
    return Z if np.all(np.isfinite(Z)) else None


def _fit_group(g: Group, settings: Settings, t0: float) -> GroupResult:
    sel = Selector(g, settings, t0)
    chosen, final, evidence = sel.select()
    r_nom = g.residuals(g.nominal)
    r_fin = g.residuals(final.p)
    return GroupResult(g, sel, chosen, final, evidence, r_nom, r_fin)


#: the Durbin-Wu-Hausman z under which the gyro lag's least-squares value is kept over the
#: instruments' (``_lag_from_instruments``)
LAG_DWH_Z = 2.0


def _lag_from_instruments(res: GroupResult, gp: GyroProblem, data: FlightData) -> str:
    """Put the chosen gyro lag's instrumental-variables estimate (``groups.lag_by_instruments``)
    in the gyro group's final model, in place of least squares' (which chose it), where the two
    differ by more than ``LAG_DWH_Z`` x the instruments' extra noise (Durbin-Wu-Hausman: without
    errors in the regressor both are consistent and least squares has the smaller sigma); the
    residuals the rest of the diagnosis reads stay the least-squares fit's. Returns the note that
    says which.

    Why the test: least squares on the whitened rows (``groups.gyro_whitener``) is far less
    shortened by the gyro's noise than on the raw rows, and its sigma is a fraction of the
    instruments'. On the generalisation matrix's gen_0052 (no gyro noise, a 14.9 ms lag) it read
    15.6 +- 0.81 ms and the instruments 19.4 +- 3.0; the flow, undone of 19.4 ms, then asked for a
    3.6 ms flow delay that is not there. A hover whose gyro is noisy still reads short by least
    squares (gen_0278: 10.7 +- 0.79 ms for 47.8, the instruments 58.8 +- 6.5), and there the
    instruments are kept."""
    k = res.group.params.index("tau")
    timing = res.group.timing[1] if res.group.timing else 0.0
    iv = lag_by_instruments(gp, data, res.selector.block_s, timing)
    ols, ols_sd = float(res.final.p[k]), math.sqrt(max(float(res.final.cov[k, k]), 0.0))
    if iv is None or not (math.isfinite(iv.tau_s) and math.isfinite(iv.sd_s)):
        return (f"gyro lag {1e3 * ols:.1f} +- {1e3 * ols_sd:.2f} ms by least squares: no instruments strong enough to "
                f"correct it for the gyro's own noise (first-stage F under {IV_MIN_F:g}, or too few rows), "
                f"so it may read short where the gyro's change over a frame is mostly noise (a hover)")
    # Durbin-Wu-Hausman: both consistent without errors in the regressor, least squares the
    # efficient one; the instruments are used only where they disagree with it beyond their noise
    spread = math.sqrt(max(iv.sd_s ** 2 - ols_sd ** 2, 0.0))
    dwh = abs(iv.tau_s - ols) / spread if spread > 0 else math.inf
    if dwh < LAG_DWH_Z:
        return (f"gyro lag {1e3 * ols:.1f} +- {1e3 * ols_sd:.2f} ms by least squares, which chose it: the "
                f"instrumental-variables estimate (the gyro's change {IV_GAP_FRAMES} frames either side of each "
                f"interval; first-stage F {iv.first_stage_f:.0f}), {1e3 * iv.tau_s:.1f} +- {1e3 * iv.sd_s:.2f} ms, "
                f"agrees with it (Durbin-Wu-Hausman z {dwh:.1f} < {LAG_DWH_Z:g}): the gyro's own noise does not "
                f"shorten it")
    lo, hi = float(res.group.lower[k]), float(res.group.upper[k])
    res.final.p[k] = min(max(iv.tau_s, lo), hi)
    res.final.cov[k, :] = 0.0
    res.final.cov[:, k] = 0.0
    res.final.cov[k, k] = iv.sd_s ** 2
    short = ols < iv.tau_s - 2.0 * iv.sd_s
    return (f"gyro lag by instrumental variables (the gyro's change {IV_GAP_FRAMES} frames either side of each "
            f"interval; first-stage F {iv.first_stage_f:.0f}): {1e3 * iv.tau_s:.1f} +- {1e3 * iv.sd_s:.2f} ms; least "
            f"squares, which chose it, read {1e3 * ols:.1f} +- {1e3 * ols_sd:.2f} ms"
            + (", attenuated by the gyro's own noise" if short else ""))


def flown_time_s(data: FlightData) -> np.ndarray:
    """Each usable frame's time from the first, counting only time within segments: the gaps
    between them (unusable stretches, lost telemetry, reboots) take no time."""
    dt = np.zeros(data.n)
    if data.n > 1:
        dt[1:] = np.where(np.diff(data.seg) == 0, np.diff(data.t_s), 0.0)
    return np.cumsum(dt)


def fit_blocks(t_s: np.ndarray, span_s: float, block_s: float = FIT_BLOCK_S) -> np.ndarray | None:
    """The frames (bool mask over ``t_s``, a flight's time axis: ``flown_time_s``, so that a block
    never falls where nothing was flown) of max(2, ceil(span / block)) blocks of ``block_s``, the
    first at the first frame, the last ending at the last, the others evenly between; None when the
    frames span no more than 1.5 x ``span_s`` (then every frame is fitted: what would be held back
    is then under a third of the flight, and fitting it too costs little)."""
    if len(t_s) < 2 or not span_s > 0:
        return None
    t = t_s - t_s[0]
    total = float(t[-1])
    if total <= 1.5 * span_s:
        return None
    n = max(2, math.ceil(span_s / block_s))
    starts = np.linspace(0.0, total - block_s, n)
    k = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, n - 1)
    return ((t >= starts[k]) & (t < starts[k] + block_s)) | (t >= total - block_s)


def _check_held_back(held: FlightData, cfg: Config, results: dict[str, GroupResult], fstate: FlowGroupState,
                     report: Report) -> None:
    """The fitted model on the frames it was not fitted on (``fit_blocks``): each channel's rms
    there beside the fitted part's, in a note, and every stretch where the model does not fit there
    (its residual over ``MISFIT_TIMES_NOISE`` x the fitted part's noise: a wind, a transient that
    acts only in the held-back part) as unexplained, which the headline then says. Not at twice the
    noise, as on the fitted part: there the force channel's few rows per stretch leave it out, here
    they are kept (ten rows a window), and at twice its noise turbulence alone made a stretch of an
    hour's held-back force residual (the bench's 2 h flight)."""
    ga, _ap = attitude_group(held, cfg)
    gg, _gp = gyro_group(held)
    gf, _fp, st = flow_group(held, cfg, gyro_lag_s=fstate.lag_s, p_anchor=results["flow"].final.p,
                             source=fstate.source, refine_lag=False,
                             accelerometer=fstate.accelerometer)  # the fit's rotation source, lag and translation
    st.window = fstate.window  # the wind where the fit put it
    said = []
    for g in (ga, gg, gf):
        res = results[g.name]
        r = g.residuals(res.final.p)
        for c, ch in enumerate(g.channels):
            ok = np.isfinite(r[c])
            x, tt = r[c][ok], g.row_times[c][ok]
            fitted = res.r_final[c][np.isfinite(res.r_final[c])]
            if not len(x) or not len(fitted):
                continue
            sigma = _stretch_noise(res, c)  # the fitted part's
            said.append(f"{ch} {float(np.sqrt(np.mean(x ** 2))):.3g} ({float(np.sqrt(np.mean(fitted ** 2))):.3g})")
            # windows of at least ten rows (the force channel has one a second)
            width = max(5.0, 10.0 * float(np.ptp(tt)) / max(len(tt) - 1, 1))
            for iv in excess_windows(tt, x, sigma, factor=MISFIT_TIMES_NOISE, width_s=width, step_s=0.5 * width):
                report.unexplained.append(Unexplained(ch, iv.start_s, iv.end_s, iv.rms,
                                                      "no candidate term fits (a local disturbance, in the part "
                                                      "held back from the fit)", iv.noise))
    report.notes.append(f"the held-back {held.duration_s / 60.0:.1f} min, not fitted: the fitted model's residual "
                        f"rms there (on the fitted part) {', '.join(said)}")


#: the stages ``diagnose`` reports to its ``progress`` callback, in order
STAGES = ("signals", "attitude loop", "gyro", "flow and force", "report")


def diagnose(rec: Recording, cfg: Config, *, profile: str | None = None,
             settings: Settings | None = None, progress: Callable[[str], None] | None = None,
             window_s: tuple[float, float] | None = None, fit_span_s: float | None = FIT_SPAN_S) -> Diagnosis:
    """Diagnose a closed-loop recording against the nominal model ``cfg`` (see the package docs).
    ``progress(stage)`` is called as each of ``STAGES`` is done (a progress bar). ``window_s``:
    use only the frames in [start, end) (report time, s), e.g. the half of a flight a fitted model
    is made from (``--model-out``). ``fit_span_s``: a longer flight is fitted on evenly spread
    blocks that add up to this and checked on the rest (``fit_blocks``; None: every frame)."""
    settings = settings or Settings()
    step = progress or (lambda _stage: None)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    data = extract(rec, cfg, profile)
    if window_s is not None:
        data = data.take((data.t_s >= window_s[0]) & (data.t_s < window_s[1]))
        if data.n == 0:
            raise RecordingError(f"{Path(rec.path).name}: no usable frame in {window_s[0]:.1f}-{window_s[1]:.1f} s")
        data.notes.append(f"fitted on {window_s[0]:.1f}-{window_s[1]:.1f} s only")
    whole = (data.n, data.duration_s, len(data.segments()))
    held: FlightData | None = None
    keep = fit_blocks(flown_time_s(data), fit_span_s) if fit_span_s else None
    if keep is not None:
        held = data.take(~keep)
        data = data.take(keep)
        data.notes.append(f"a long recording: the effects fitted on {data.duration_s / 60.0:.1f} of "
                          f"{whole[1] / 60.0:.1f} min ({FIT_BLOCK_S:g} s blocks spread evenly over the flight), "
                          f"the rest held back to check the fitted model (--fit-all fits every frame)")
    timings["extract_s"] = time.perf_counter() - t
    step(STAGES[0])
    t0 = float(data.t_s[0])
    ga, ap = attitude_group(data, cfg)
    gg, gp = gyro_group(data)
    results: dict[str, GroupResult] = {}
    for g, stage in ((ga, STAGES[1]), (gg, STAGES[2])):
        t = time.perf_counter()
        results[g.name] = _fit_group(g, settings, t0)
        if g is ga:  # is the chosen loop the vehicle's, or the fit of what this flight flew?
            res = results[g.name]
            res.loop_form = loop_form(g, ap, res.chosen, res.final.p, t0, settings, res.selector.notes)
        timings[f"{g.name}_s"] = time.perf_counter() - t
        step(stage)
    if "gyro_lag" in results["gyro"].chosen:
        data.notes.append(_lag_from_instruments(results["gyro"], gp, data))
    # the flow is compared with the rotation of the gyro above 1 Hz, undone of the lag found
    lag = float(results["gyro"].final.p[2]) if "gyro_lag" in results["gyro"].chosen else 0.0
    t = time.perf_counter()
    notes = list(data.notes)
    gf, fp, fstate = flow_group(data, cfg, gyro_lag_s=lag)
    results["flow"] = _fit_group(gf, settings, t0)
    if any(e in GEOMETRY_EFFECTS for e in results["flow"].chosen):
        # the effects' regressors are exact to first order about their anchor (the nominal model):
        # with a large geometry effect chosen (a 12 deg yaw, a 20 % scale), its second-order share
        # would be fitted as another effect, so the group is built again about the chosen model and
        # the selection rerun from there (``FlowProblem.anchor``)
        data.notes[:] = notes + [n for n in (fstate.source_note, fstate.lag_note, fstate.accel_note) if n]
        gf, fp, fstate = flow_group(data, cfg, gyro_lag_s=fstate.lag_s, refine_lag=False,
                                    p_anchor=results["flow"].final.p,
                                    source=fstate.source, accelerometer=fstate.accelerometer)
        results["flow"] = _fit_group(gf, settings, t0)
    timings["flow_s"] = time.perf_counter() - t
    step(STAGES[3])
    ap.final_p = results["attitude"].final.p
    if "wind_force" in results["flow"].chosen:
        results["flow"].selector._search(results["flow"].final.p, None)
    t = time.perf_counter()
    report = Report(recording=Path(rec.path).name)
    report.notes.extend(rec.notes)
    report.notes.extend(data.notes)
    report.notes.append(f"profile {data.profile} ({data.profile_reason}); command: {data.command_source}; "
                        f"{whole[0]} frames over {whole[1]:.1f} s in {whole[2]} segment(s)")
    cond = _cond_values(data, fp, results["flow"].final.p)
    loop = _loop_attitude(ap)  # the unexplained terms' attitude, for every channel
    for name, res in results.items():
        g = res.group
        for c, ch in enumerate(g.channels):
            x = res.r_nominal[c]  # a channel can hold no rows (every flow window of an axis quiet)
            report.baseline_rms[ch] = float(np.sqrt(np.mean(x ** 2))) if len(x) else math.nan
        for e, comp in res.evidence.items():
            f = _finding(e, comp, res, data, cfg, cond)
            if res.loop_form is not None and e in res.chosen and e in LOOP_EFFECTS:
                _with_loop_form(f, res.loop_form)
            if comp.significant and e in ALIKE:
                f.alternatives = _alternatives(e, res)
                if e == "flow_rotation_gain" and not lever_arm_observable(data):
                    # at one height a lever arm rz adds rz / h times the rotation: a gain of 1 + rz / h
                    h = float(np.nanmean(data.range_m))
                    f.alternatives.append({"effect": "flow_lever_arm",
                                           "parameters": {"rz": (f.parameters["gain"] - 1.0) * h},
                                           "cv_t": float(comp.cv_t)})
                if f.alternatives:
                    others = " or ".join(f"{a['effect']} ({_fmt(a['parameters'])})" for a in f.alternatives)
                    f.explanation += (f" This flight cannot tell it from {others}: fitted in its place, each "
                                      f"explains what it explains; a flight with more manoeuvring (speed and "
                                      f"height changes) would tell them apart.")
            report.findings.append(f)
        _unexplained(name, res, data, ap, gp, fp, fstate, settings, report, loop)
        report.notes.extend(res.selector.notes)
    if held is not None and held.n:
        try:
            _check_held_back(held, cfg, results, fstate, report)
        except (RecordingError, ValueError) as exc:  # the fit stands; what could not be checked is said
            report.notes.append(f"the held-back {held.duration_s / 60.0:.1f} min could not be checked: {exc}")
    report.findings.sort(key=lambda f: (not f.significant, -(f.fit.improvement_pct if f.fit else 0.0)))
    report.headline = headline(report)
    report.actions = actions(report, profile=data.profile, q_rad_per_count=cfg.flow_sensor.q_rad_per_count,
                             current=recorded_parameters(rec))
    step(STAGES[4])
    timings["report_s"] = time.perf_counter() - t
    return Diagnosis(data, cfg, report, results, ap, gp, fp, fstate, timings)


def _with_loop_form(f: Finding, lf: LoopForm) -> None:
    """A chosen attitude effect with the loop-form check (``excitation``): its evidence always;
    when the form depends on what is flown, the explanation says so and each parameter's
    uncertainty includes half the spread between the slow and the fast part's fits."""
    f.evidence["excitation"] = lf.to_json()
    if lf.depends:
        f.uncertainty = {k: lf.widened(k, v) for k, v in f.uncertainty.items()}
        f.explanation += lf.describe({k: f.unit(k) for k in lf.params})


def _fmt(p: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.3g}" for k, v in p.items())


def _alternatives(effect: str, res: GroupResult) -> list[dict[str, Any]]:
    """The effects of ``ALIKE[effect]`` that explain the flight as well as ``effect`` (see
    ``Selector.rivals``), as ``Finding.alternatives``."""
    out = []
    for a, score, t in res.selector.rivals(res.chosen, res.final, effect, ALIKE[effect]):
        out.append({"effect": a, "parameters": _params(a, res.group, score, {})[0], "cv_t": float(t)})
    return out


def _finding(effect: str, comp: Comparison, res: GroupResult, data: FlightData, cfg: Config,
             cond: dict[str, np.ndarray]) -> Finding:
    g = res.group
    state = res.final.state if effect == "wind_force" else {}
    p, sd = _params(effect, g, comp.with_, state)
    c = comp.primary
    ch = g.channels[c]
    fit = Fit(float(comp.heldout_rms_before[c]), float(comp.heldout_rms_after[c]))
    where: list[Window] = []
    evidence: dict[str, Any] = {
        "group": g.name,
        "channel": ch,
        "unit": g.units[c],
        "wald_z": comp.wald_z,
        "cv_t": comp.cv_t,
        "delta_bic": comp.dbic,
        "heldout_by_channel": {g.channels[i]: {"before": float(comp.heldout_rms_before[i]),
                                               "after": float(comp.heldout_rms_after[i])}
                               for i in range(len(g.channels))},
        "method": "exact refit" if effect in res.chosen or "exact" in " ".join(comp.reasons)
        else "linearised at the chosen model",
    }
    if comp.check_rows:  # the accelerometer's independent verdict (``groups.accelerometer_z``)
        evidence["accelerometer_z"] = comp.check_z
        evidence["accelerometer_rows"] = comp.check_rows
    if comp.at_resolution_bound:  # judged by its held-out z in place of the Wald z (``Candidate.resolution_upper``)
        evidence["at_resolution_bound"] = True
    if comp.reasons:
        evidence["why_not"] = comp.reasons
    if comp.significant:
        # where the effect's own term changes the final residual by more than the noise
        cand = next(x for x in g.candidates if x.effect == effect)
        p_off = comp.with_.p.copy()
        idx = g.index(cand.params)
        p_off[idx] = g.nominal[idx]
        r_with = g.residuals(comp.with_.p)
        r_without = g.residuals(p_off)
        sigma = res.selector.sigma
        best: dict[str, object] = {}
        for i, chn in enumerate(g.channels):
            contrib = r_without[i] - r_with[i]
            if not np.any(np.abs(contrib) > 0):
                continue
            if np.sqrt(np.mean(contrib ** 2)) < 0.1 * sigma[i]:
                continue
            if effect == "wind_force":
                continue
            for iv in effect_windows(g.row_times[i], contrib, float(sigma[i])):
                where.append(Window(chn, iv.start_s, iv.end_s))
            if i == c:
                vals = {k: np.interp(g.row_times[i], data.t_s, v) for k, v in cond.items()}
                best = conditions(vals, contrib)
        if effect == "wind_force":
            for chn, key in (("force_x", "fx"), ("force_y", "fy")):
                if abs(p[key]) >= 0.25 * math.hypot(p["fx"], p["fy"]):
                    where.append(Window(chn, p["start_s"], p["end_s"]))
        if best:
            evidence["conditions"] = best
    return Finding(effect=effect, significant=comp.significant, parameters=p, uncertainty=sd,
                   explanation=explain(effect, p, cfg, comp.significant, sd), where=where, fit=fit,
                   evidence=evidence)


def _structured(sp: SparseFit | None, r: np.ndarray, floor: float) -> bool:
    """Whether the sparse fit explains the residual ``r``: a term, a held-out share of at least
    ``SPARSE_MIN_R2``, and more than the channel's resolution (``floor``)."""
    rms = float(np.sqrt(np.mean(r ** 2))) if len(r) else 0.0
    return (sp is not None and sp.best is not None and sp.r2_heldout >= SPARSE_MIN_R2
            and math.sqrt(sp.r2_heldout) * rms > floor)


def _stretch_noise(res: GroupResult, c: int) -> float:
    """Channel c's noise over the whole fit, for the stretch test (``locate.excess_windows``, which
    takes the window's own white part beside it): the selector's robust scale, or the final
    residual's white part where larger (noise with heavy tails), or, for a channel whose noise is
    coloured (``Group.coloured``), its typical window where larger still: the typical window of
    what the sparse fit (``res.sparse``, run first) leaves, when it explains the residual.

    Why what the sparse fit leaves: a misfit in every window is the typical window. A lossy
    ground-station copy of the ArduCopter SITL flight C0, whose attitude residual is 0.98 x the
    tracking error over the whole flight (the attitude model lost with its commands), said "does
    not fit attitude_roll from 58.2 to 212.6 s: 101 x its noise" against the robust scale, against
    its typical window only 4 x over 23 s of it, and against what the sparse fit leaves 16 x from
    140.7 to 203.2 s, with four more stretches over 63-206 s."""
    g = res.group
    t, r = g.row_times[c], res.r_final[c]
    sigma = max(float(res.selector.sigma[c]), white_noise(t, r))
    if g.coloured and g.coloured[c]:
        sigma = max(sigma, typical_window_rms(t, _sparse_left(res, c)))
    return sigma


def _sparse_left(res: GroupResult, c: int) -> np.ndarray:
    """Channel c's final residual less what its sparse fit (``res.sparse``) predicts, when that
    fit explains it (``_structured``); the residual itself otherwise."""
    g = res.group
    r = res.r_final[c]
    sp = res.sparse.get(g.channels[c])
    return r - sp.predict(len(r)) if sp is not None and _structured(sp, r, g.floors[c]) else r


def _stretch_factor(res: GroupResult, c: int) -> float:
    """How many times its noise (``_stretch_noise``) channel c's window must stand to be listed:
    ``STRETCH_TIMES_NOISE``, or, for a coloured channel, what its own windows' scatter leaves
    to chance (``locate.coloured_factor``, on what the sparse fit leaves) where that is higher."""
    g = res.group
    if not (g.coloured and g.coloured[c]):
        return STRETCH_TIMES_NOISE
    return max(STRETCH_TIMES_NOISE, coloured_factor(g.row_times[c], _sparse_left(res, c)))


def _unexplained(name: str, res: GroupResult, data: FlightData, ap: AttitudeProblem, gp: GyroProblem,
                 fp: FlowProblem, fstate: FlowGroupState, settings: Settings, report: Report,
                 loop: np.ndarray | None) -> None:
    g = res.group
    sel = res.selector
    for c, ch in enumerate(g.channels):
        r = res.r_final[c]
        tt = g.row_times[c]
        if len(r) == 0:
            continue
        terms = _terms(name, data, ap, gp, fp, res, c, fstate, loop)
        sp = sparse_fit(r, terms, sel.folds[c], sel.K) if terms else None
        if sp is not None:
            res.sparse[ch] = sp
        structured = _structured(sp, r, g.floors[c])
        sigma = _stretch_noise(res, c)
        factor = _stretch_factor(res, c)
        res.mismatch_windows[ch] = excess_windows(tt, res.r_nominal[c], sigma, factor=factor)
        windows = excess_windows(tt, r, sigma, factor=factor)
        res.unexplained_windows[ch] = windows
        rms = float(np.sqrt(np.mean(r ** 2)))
        best_text = sp.describe(g.units[c]) if (sp is not None and structured) else None
        if structured and not windows:
            report.unexplained.append(Unexplained(ch, float(tt.min()), float(tt.max()), rms, best_text, sigma))
        for iv in windows:
            report.unexplained.append(Unexplained(ch, iv.start_s, iv.end_s, iv.rms,
                                                  best_text or "no candidate term fits (a local disturbance)",
                                                  iv.noise))


def headline(report: Report) -> str:
    """The first line of a report, in plain words: what differs, or that the model does not fit
    where no named effect explains a residual far above its channel's noise, or that it fits."""
    found = report.significant()
    over = [u for u in report.unexplained if u.times_noise >= MISFIT_TIMES_NOISE]
    misfit = sorted((u for u in over if u.rms >= misfit_floor(u.channel)[0]), key=lambda u: -u.times_noise)
    small = sorted((u for u in over if u.rms < misfit_floor(u.channel)[0]), key=lambda u: -u.times_noise)
    parts = []
    if found:
        names = [f.effect + (f" (or {' or '.join(a['effect'] for a in f.alternatives)}: this flight cannot tell "
                             "them apart)" if f.alternatives else "") for f in found]
        # the attitude loop's form outside the model (``excitation``), said once, at its first finding
        loop = [i for i, f in enumerate(found) if f.evidence.get("excitation", {}).get("depends_on_commands")]
        if loop:
            names[loop[0]] += " (not the model's second-order loop: its fit depends on what is flown)"
        parts.append(f"the model leaves out {', '.join(names)}")
    if misfit:
        u = misfit[0]
        more = f" (and {len(misfit) - 1} more stretch(es))" if len(misfit) > 1 else ""
        parts.append(f"{'it still' if found else 'the model'} does not fit {u.channel} from {u.start_s:.1f} to "
                     f"{u.end_s:.1f} s: residual {u.times_noise:.0f} x its noise, which no named effect "
                     f"explains{more}")
    if not parts and small:
        u = small[0]
        floor, unit = misfit_floor(u.channel)
        return (f"the recording fits the nominal model to within what matters: no effect it leaves out earns its "
                f"parameters; {u.channel} from {u.start_s:.1f} to {u.end_s:.1f} s stands {u.times_noise:.0f} x its "
                f"noise, but at {u.rms:.2g} {unit} rms, under the {floor:g} {unit} a misfit must reach to matter")
    if not parts:
        return "the recording fits the nominal model within its noise: no effect it leaves out earns its parameters"
    text = "; ".join(parts)
    return text[0].upper() + text[1:]

