"""Oracle detectability: how much evidence a generated recording holds for each of its true effects.

The generalisation matrix (``scripts/generalisation_matrix.py``) counts a true effect the finder
does not report as a miss. Some of those effects cannot be seen in the recording at all (a range
offset on a flight that hardly moves, a lever arm on a flight with little rotation, under noise
and turbulence). This module measures, for each true effect of a recording, the evidence an
*oracle* has against the nominal model: one who knows the effect and its true parameters and
judges them with the finder's own residuals.

Definition (``effect_evidence``). The recording goes through the finder's extraction and its
three residual groups (``companion.diagnose.closed_loop.groups``), each with the noise scale per
channel the selection uses (``Selector.sigma``). For a true effect E of group G, with every other
true effect of G at its true value in both:

    r1 = the weighted residuals with E at its true parameters (the truth),
    r0 = the same with E's parameters at the nominal model,  d = r0 - r1,
    drop   = |r0|^2 - |r1|^2 = |d|^2 + 2 d.r1   (the noise-weighted chi-square drop, exact),
    signal = |d|^2                               (what E adds to the residual: its noncentrality).

Under white noise at the assumed scale, d.r1 has variance |d|^2, so ``drop`` is a chi-square
statistic whose mean is ``signal``. Turbulence, coloured attitude noise and a noise scale that is
not the residual's make that variance larger (or smaller), and the naive chi-square overstates (or
understates) the evidence. The finder's answer (``Selector._cov``) is a Newey-West correction: the
noise is taken as correlated over at most ``cluster_s`` (10 s). The same here, for the variance of
the noise's projection on E's signature,

    V = sum over channels of  gamma(0) D(0) + 2 sum_{l=1..L} (1 - l / (L + 1)) gamma(l) D(l),

gamma(l) the autocovariance of the channel's residual at the truth r1 (over the whole recording),
D(l) = sum_t d_t d_{t+l}, L the rows in ``cluster_s`` (``hac_variance``: the Bartlett-kernel form of
Newey-West). Why not the finder's own time clusters: on a 30 s flight they are three, and for an
effect that acts in one or two of them (a wind, one manoeuvre) the cluster estimate of V is the
realised d.r1 squared, one degree of freedom. On the 48 true effects of 40 matrix recordings (seed
0) the cluster form's V / signal ranged over 0.001-1800, this form's over 0.002-15; on the 12 the
finder found with a Wald z under its cap of 37, both were about as near the finder's z (median
ratio oracle / finder 1.5 clusters, 1.7 this form; the oracle, which fits nothing, should not be
below it), but the cluster form fell far below the finder's own z on two (a flow delay the finder
put at z >= 37: 8.5; a flow scale at 20: 2.2), which an upper bound cannot. Channels are taken as
uncorrelated with one another.

The drop is expressed on the finder's scale by W = drop * signal / V (for a linear one-parameter
effect W is, up to the noise in the fit, the Wald statistic (theta / sd)^2 = signal^2 / V the
finder computes with its robust covariance when its estimate lands on the truth). The oracle z is
the normal z with the same tail probability as W under chi-square with k degrees of freedom, k =
the effect's parameter count in the group: the conversion ``Selector.compare`` applies to its Wald
statistic, so the oracle z is on the scale of the finder's ``z_min`` = 3 (for k = 1 it is sqrt(W);
beyond the finder's cap of 37 it goes on growing). ``z_naive`` is the same from the drop without
the correction; ``inflation`` = V / signal says by how much the correction divided the evidence.

What it is, and what it is not:
- an upper bound on what the finder can know from the recording about E alone: the oracle does not
  fit E (it knows its values), does not search (the wind's window is the true one), does not
  choose among candidates, and holds every other true effect at its truth. A low oracle z means
  the recording cannot show the effect, whatever the finder did; a high one means the evidence
  was there.
- it does not see that another candidate can explain the same residual (a scale and a range
  offset at one height, a lever arm and a rotation gain, an attitude delay and the attitude
  dynamics). ``z_rival`` does: the same z with one other candidate effect of the group fitted
  (least squares from the truth, ``fit_free``) in both r1 and r0, the least over the group's other
  candidates one at a time (``rival`` names it; z itself when none lowers it). A high z with a low
  ``z_rival`` is a recording that shows the residual but not which of the two effects made it: the
  finder can only say so (its report's alternatives, which the matrix's scoring counts as a hit).
- the groups are built as the diagnosis builds them, with what the oracle knows: the flow group's
  rotation undone of the true gyro lag (the diagnosis uses the lag it found), and its effects'
  regressors anchored at the true geometry (the diagnosis anchors at the nominal, then again at its
  chosen model: ``FlowProblem.anchor``; at the truth the residual at the truth is exact).
- ``wind_force`` is evaluated with its window at the true start and end (the finder searches for
  it and judges it by a null calibrated on the recording, not by its Wald z); its k is 2 (fx, fy).
- ``flow_lever_arm``: only rz is in the model (rx, ry are not scored either); on a flight whose
  heights hardly vary the finder does not try it (``lever_arm_observable``), which ``note`` says.
- the truth's parameters are read by the names the group gives them, the names the diagnosis
  reports them under and ``flightgen.score`` matches with the truth (CONVENTIONS.md names).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import optimize, stats

from companion.config import load_config
from companion.diagnose.closed_loop.channels import extract
from companion.diagnose.closed_loop.flowmodel import IDX, NOMINAL
from companion.diagnose.closed_loop.groups import (
    GEOMETRY,
    FlowGroupState,
    attitude_group,
    flow_group,
    gyro_group,
    lever_arm_observable,
)
from companion.diagnose.closed_loop.select import Group, Selector, Settings
from companion.diagnose.closed_loop.wind import WindWindow
from companion.errors import RecordingError
from companion.recordings.load import load_recording

#: the oracle z bands of the matrix report (lower edges; the last is open)
Z_BANDS = (3.0, 5.0, 10.0)


@dataclass(frozen=True)
class Evidence:
    """One true effect's oracle evidence (see the module docstring)."""

    effect: str
    group: str
    #: the true parameters the effect frees, in the group's names
    params: dict[str, float]
    k: int
    drop: float
    signal: float
    #: V / signal: the cluster-robust variance of the noise's projection over its white-noise value
    inflation: float
    z: float
    z_naive: float
    #: the least of the same z with one other candidate effect of the group fitted in both (each in
    #: turn, from the truth): the evidence for this effect rather than for the one other effect that
    #: stands in for it best; z itself when none takes any evidence away
    z_rival: float = math.nan
    #: that other effect ("" when none takes any evidence away)
    rival: str = ""
    note: str = ""


def z_of_chi2(w: float, k: int) -> float:
    """The normal z with the tail probability of ``w`` under chi-square with ``k`` degrees of
    freedom (two-sided, as ``Selector.compare`` converts its Wald statistic); 0 for w <= 0."""
    if not w > 0.0:
        return 0.0
    if not math.isfinite(w):
        return math.inf
    log_p = float(stats.chi2.logsf(w, k))
    if not math.isfinite(log_p):  # underflow: the tail's leading term, x^(a-1) e^-x / Gamma(a) at x = w / 2
        log_p = (0.5 * k - 1.0) * math.log(0.5 * w) - 0.5 * w - math.lgamma(0.5 * k)
    if log_p > -600.0:
        p = math.exp(log_p)
        return float(stats.norm.isf(p / 2.0)) if p < 1.0 else 0.0
    # far in the tail (the finder's conversion stops at p = 1e-300, z = 37): solve on the log scale,
    # log sf(z) = log(p / 2), whose root lies below sqrt(-2 log(p / 2)) (log sf(z) < -z^2 / 2 there)
    target = log_p - math.log(2.0)
    return float(optimize.brentq(lambda z: float(stats.norm.logsf(z)) - target, 0.0, math.sqrt(-2.0 * target)))


def hac_variance(d: np.ndarray, r: np.ndarray, lags: int) -> float:
    """Var(d . n) for a stationary noise n whose autocovariance is the sample autocovariance of
    ``r`` up to ``lags`` rows, with Bartlett weights 1 - l / (lags + 1) (Newey-West: a positive
    semi-definite estimate): gamma(0) D(0) + 2 sum_l w_l gamma(l) D(l), D(l) = sum_t d_t d_{t+l}.
    For white noise of unit variance it is |d|^2."""
    n = len(d)
    if n == 0:
        return 0.0
    lags = max(0, min(int(lags), n - 1))
    nfft = 1 << int(math.ceil(math.log2(2 * n)))
    gam = np.fft.irfft(np.abs(np.fft.rfft(r, nfft)) ** 2, nfft)[:lags + 1] / n
    dd = np.fft.irfft(np.abs(np.fft.rfft(d, nfft)) ** 2, nfft)[:lags + 1]
    w = 1.0 - np.arange(lags + 1) / (lags + 1)
    return float(gam[0] * dd[0] + 2.0 * np.sum(w[1:] * gam[1:] * dd[1:]))


def effect_evidence(sel: Selector, p_with: np.ndarray, p_without: np.ndarray, k: int
                    ) -> tuple[float, float, float, float, float]:
    """(drop, signal, inflation, z, z_naive) of the group's residuals at ``p_with`` against
    ``p_without`` (the module docstring), weighted by the selector's noise scales; the noise's
    autocovariance per channel from the residual at ``p_with``, over lags up to the selector's
    ``cluster_s``."""
    r1 = sel.weighted(p_with)
    r0 = sel.weighted(p_without)
    drop = signal = v = 0.0
    for c in range(len(r1)):
        if len(r1[c]) == 0:
            continue
        d = r0[c] - r1[c]
        drop += float(r0[c] @ r0[c] - r1[c] @ r1[c])
        signal += float(d @ d)
        t = sel.g.row_times[c]
        step = float(np.median(np.diff(t))) if len(t) > 1 else math.inf
        lags = int(round(sel.s.cluster_s / step)) if step > 0 and math.isfinite(step) else 0
        v += hac_variance(d, r1[c], lags)
    if not signal > 0.0:
        return drop, 0.0, math.nan, 0.0, 0.0
    inflation = v / signal
    w = drop / inflation if inflation > 0.0 else (math.inf if drop > 0.0 else 0.0)
    return drop, signal, inflation, z_of_chi2(w, k), z_of_chi2(drop, k)


def fit_free(sel: Selector, p0: np.ndarray, free: list[int], iterations: int = 12) -> np.ndarray:
    """Least squares of the selector's weighted residual over the parameters ``free`` from ``p0``
    (Levenberg-Marquardt, forward-difference Jacobian with the group's steps, within its bounds)."""
    p = p0.copy()
    if not free:
        return p
    g = sel.g
    lo, hi = g.lower[free], g.upper[free]

    sse_of = sel.weighted_sse
    sse = sse_of(p)
    lam = 1e-3
    for _ in range(iterations):
        J = np.vstack(sel.jacobian(p, free))
        r = np.concatenate(sel.weighted(p))
        A, grad = J.T @ J, J.T @ r
        accepted = False
        for _try in range(8):
            step = -np.linalg.lstsq(A + lam * np.diag(np.diag(A) + 1e-12), grad, rcond=None)[0]
            q = p.copy()
            q[free] = np.clip(p[free] + step, lo, hi)
            new = sse_of(q)
            if new < sse:
                gain = (sse - new) / max(sse, 1e-300)
                p, sse = q, new
                lam = max(lam / 3.0, 1e-9)
                accepted = gain > 1e-9
                break
            lam *= 4.0
        if not accepted:
            break
    return p


def _effect_params(groups: dict[str, Group], effect: str, truth_params: dict[str, Any]) -> tuple[str, tuple[str, ...],
                                                                                             str]:
    """(group name, the effect's parameter names in that group, note). The effect's candidate
    names them; an effect the finder does not try on this flight (a lever arm at one height) takes
    the group's parameters that carry the truth's names."""
    for name, g in groups.items():
        for cand in g.candidates:
            if cand.effect == effect:
                return name, cand.params, ""
    for name, g in groups.items():
        ps = tuple(p for p in g.params if p in truth_params)
        if ps:
            return name, ps, "not tried by the finder on this flight"
    raise ValueError(f"no residual group has the parameters of {effect} ({', '.join(truth_params)})")


def _values(effect: str, names: tuple[str, ...], truth_params: dict[str, Any]) -> np.ndarray:
    missing = [n for n in names if truth_params.get(n) is None]
    if missing:
        raise ValueError(f"the truth of {effect} has no {', '.join(missing)}")
    return np.array([float(truth_params[n]) for n in names])


@dataclass
class OracleGroups:
    """A recording's residual groups built for the oracle (``build``): for each group holding a
    true effect, its ``Selector`` (the noise scales and time clusters the selection uses) and the
    parameter vector at the truth."""

    groups: dict[str, Group]
    selectors: dict[str, Selector]
    p_true: dict[str, np.ndarray]
    #: effect -> (group name, its parameter names there, note)
    where: dict[str, tuple[str, tuple[str, ...], str]]
    truth_effects: dict[str, dict[str, Any]]


def build(rec_path: str | Path, config_path: str | Path, truth: dict[str, Any], *, profile: str | None = None,
          settings: Settings | None = None) -> OracleGroups:
    """The finder's residual groups on the recording (read with its nominal config as the diagnosis
    reads them), as the oracle uses them for the true effects of ``truth`` (a ``NAME.truth.json``)."""
    settings = settings or Settings()
    cfg = load_config(config_path)
    data = extract(load_recording(rec_path), cfg, profile)
    t0 = float(data.t_s[0])
    t_eff: dict[str, dict[str, Any]] = dict(truth.get("effects", {}) or {})
    # the flow group as the diagnosis builds it, with what the oracle knows: the true gyro lag, and
    # the regressors anchored at the true geometry
    ga, _ = attitude_group(data, cfg)
    gg, _ = gyro_group(data)
    elsewhere = {c.effect for g in (ga, gg) for c in g.candidates}
    lag = float(t_eff["gyro_lag"]["tau"]) if "gyro_lag" in t_eff else 0.0
    p_flow = NOMINAL.copy()
    for effect, tp in t_eff.items():
        if effect not in elsewhere:
            for k in GEOMETRY:
                if tp.get(k) is not None:
                    p_flow[IDX[k]] = float(tp[k])
    gf, _, fstate = flow_group(data, cfg, gyro_lag_s=lag, p_anchor=p_flow)
    _true_window(fstate, t_eff.get("wind_force"))
    groups = {g.name: g for g in (ga, gg, gf)}
    where = {e: _effect_params(groups, e, tp) for e, tp in t_eff.items()}
    if "flow_lever_arm" in where and not where["flow_lever_arm"][2] and not lever_arm_observable(data):
        where["flow_lever_arm"] = (*where["flow_lever_arm"][:2], "not tried by the finder on this flight")
    selectors: dict[str, Selector] = {}
    p_true: dict[str, np.ndarray] = {}
    for gname, g in groups.items():
        mine = [e for e, (gn, _, _) in where.items() if gn == gname]
        if not mine:
            continue
        selectors[gname] = Selector(g, settings, t0)
        if gname == "flow":  # the selector's search moved the window: the truth's again
            _true_window(fstate, t_eff.get("wind_force"))
        p = g.nominal.copy()
        for e in mine:
            names = where[e][1]
            p[g.index(names)] = _values(e, names, t_eff[e])
        p_true[gname] = p
    return OracleGroups(groups, selectors, p_true, where, t_eff)


def evidence_of(og: OracleGroups, effect: str) -> Evidence:
    """The oracle evidence of one true effect (the module docstring)."""
    gname, names, note = og.where[effect]
    g, sel, p_true = og.groups[gname], og.selectors[gname], og.p_true[gname]
    idx = g.index(names)
    p_without = p_true.copy()
    p_without[idx] = g.nominal[idx]
    drop, signal, infl, z, zn = effect_evidence(sel, p_true, p_without, len(names))
    # rivals: each other candidate of the group fitted in both, the one that stands in best (a wind
    # only when it is true: its window is the truth's, there is none to search for otherwise)
    z_rival, rival = math.nan, ""
    for c in g.candidates:
        if c.effect == effect or (c.effect == g.searched_effect and c.effect not in og.truth_effects):
            continue
        free = [i for i in g.index(c.params) if i not in idx]
        *_, zr, _ = effect_evidence(sel, fit_free(sel, p_true, free), fit_free(sel, p_without, free), len(names))
        if not zr >= z_rival:
            z_rival, rival = zr, c.effect
    if not z_rival < z:  # a rival takes evidence away, never adds it (beyond a fit's noise); none took any
        z_rival, rival = z, ""
    return Evidence(effect, gname, {n: float(p_true[i]) for n, i in zip(names, idx, strict=True)}, len(names),
                    drop, signal, infl, z, zn, z_rival, rival, note)


def oracle(rec_path: str | Path, config_path: str | Path, truth: dict[str, Any], *, profile: str | None = None,
           settings: Settings | None = None) -> dict[str, Evidence]:
    """The oracle evidence of every true effect of ``truth`` (a ``NAME.truth.json`` of
    ``flightgen``) on the recording, read with its nominal config as the diagnosis reads them."""
    if not truth.get("effects"):
        return {}
    og = build(rec_path, config_path, truth, profile=profile, settings=settings)
    return {e: evidence_of(og, e) for e in og.where}


def _true_window(state: FlowGroupState, wind: dict[str, Any] | None) -> None:
    """Put the true wind window into the flow group's state (the residuals read it), or none."""
    if not wind:
        state.window = None
        return
    s, e = wind.get("start_s"), wind.get("end_s")
    if s is None or e is None or not e > s:
        raise ValueError("the truth of wind_force has no window (start_s, end_s)")
    state.window = WindWindow(float(s), float(e), float(wind["fx"]), float(wind["fy"]), math.nan)


def oracle_files(folder: str | Path, stem: str) -> dict[str, Evidence]:
    """``oracle`` for ``folder/stem.tlog`` with ``stem.toml`` and ``stem.truth.json`` (a matrix
    recording, ``OUT/recordings``). Raises RecordingError when a file is missing."""
    folder = Path(folder)
    paths = [folder / f"{stem}{ext}" for ext in (".tlog", ".toml", ".truth.json")]
    missing = [p.name for p in paths if not p.exists()]
    if missing:
        raise RecordingError(f"{folder}: missing {', '.join(missing)}")
    truth = json.loads(paths[2].read_text())
    return oracle(paths[0], paths[1], truth, profile=None)


def as_json(ev: dict[str, Evidence]) -> dict[str, dict[str, Any]]:
    """The evidence as JSON-ready dicts, by effect."""
    return {e: asdict(x) for e, x in ev.items()}


def band(z: float) -> str:
    """The oracle z band of ``Z_BANDS``: "< 3", "3-5", "5-10", ">= 10"."""
    lo = Z_BANDS
    if not z >= lo[0]:
        return f"< {lo[0]:g}"
    for a, b in zip(lo[:-1], lo[1:], strict=True):
        if z < b:
            return f"{a:g}-{b:g}"
    return f">= {lo[-1]:g}"


#: the band labels, in order
BANDS = (band(0.0), *(band(x) for x in Z_BANDS))
