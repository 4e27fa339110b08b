"""Whether the fitted attitude loop is the vehicle's or the flight's: the chosen attitude model
fitted again on the commands' slow and on their fast part.

A loop that is what the model says (eq. 26, with the fitted Omega_p, zeta and delay) answers every
part of the command's spectrum with the same parameters, so a fit that sees only the residual
below the loop's own natural frequency and one that sees only the residual above it agree within
their uncertainties. A loop outside the model does not: ArduCopter shapes each attitude command
(``ATC_INPUT_TC``, a first-order approach whose rate is slewed at most at ``ATC_ACCEL_R_MAX``)
before a much faster controller, and a second-order fit then takes whatever (Omega_p, zeta) best
matches the commands that were flown. Two flights of one vehicle then give different values, each
with a small uncertainty that is true only *given* the model (data/sitl/ardupilot: flight A, whose
commands jump by 2.4 deg from frame to frame and keep the shaper at its acceleration limit,
Omega_p 13.7 +- 0.5; flights C0 and E1, smooth commands, 16.6 +- 0.8).

The split: the residual of the chosen model is divided by a zero-phase low-pass (Butterworth,
second order, run forwards and backwards over each simulation segment) at the fitted loop's natural
frequency Omega_p / 2 pi into a slow part and the fast remainder (the two add up to the residual);
the chosen effects' parameters are refitted on each part alone (``Selector``: Levenberg-Marquardt
on the exact residual from the whole flight's fit, covariance cluster-robust and floored by the
fold jackknife, as for every fit). Their difference against the sum of the two covariances is a
chi-square with as many degrees of freedom as parameters, turned into the normal z of the same
tail probability; at ``z_min`` (the z an effect's parameters need to differ from the nominal
model) or more, and with a difference that matters by the effects' own size rules (``sizes``:
Omega_p 5 %, zeta 0.05, a delay 2 ms), the loop's form depends on what is flown. The report then
says so, with both fits, and each parameter's stated uncertainty includes half the difference of
the two (sqrt(sigma^2 + (d / 2)^2)): the spread between what the slow and the fast part of one
flight's commands give is the least another flight's commands can move the fit by. A correct
model is left as it is (its parts agree within their noise, z < z_min, or differ by a size that
does not matter).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.diagnose import filters
from companion.diagnose.closed_loop.attitude import AttitudeProblem
from companion.diagnose.closed_loop.select import Group, Selector, Settings, z_of_chi2
from companion.diagnose.closed_loop.sizes import threshold

#: the attitude effects whose parameters are refitted on each part
LOOP_EFFECTS = ("attitude_dynamics", "attitude_delay")
#: the split is kept below this fraction of the frame rate (the Nyquist frequency is 0.5)
MAX_SPLIT_FRACTION = 0.4
#: split residuals kept for reuse (the two parts' fits evaluate the same points at first)
MEMO_SIZE = 8
#: residual evaluations the two parts' fits take together, about (for the time budget; 58 on a
#: 241 s generated flight with random telemetry loss and 752 simulation segments)
EVALUATIONS = 60


@dataclass
class LoopForm:
    """The chosen attitude model fitted on the slow and on the fast part of the residual."""

    split_hz: float
    params: tuple[str, ...]
    whole: np.ndarray
    slow: np.ndarray
    slow_sd: np.ndarray
    fast: np.ndarray
    fast_sd: np.ndarray
    chi2: float
    z: float
    #: the z at which the form depends on what is flown (the selection's ``z_min``)
    z_min: float
    #: a part's fit ran to the edge of the allowed range (the spread is then at least what is shown)
    at_bound: bool
    #: the two parts differ by a size that matters (``sizes``: the threshold of the effect whose
    #: parameters they are, the fast part's values against the slow part's)
    matters: bool = True

    @property
    def depends(self) -> bool:
        return self.z >= self.z_min and self.matters

    def spread(self) -> dict[str, float]:
        """Half the difference between the two parts' fits, per parameter."""
        return {n: 0.5 * abs(float(a - b)) for n, a, b in zip(self.params, self.slow, self.fast, strict=True)}

    def widened(self, name: str, sd: float) -> float:
        """The uncertainty of parameter ``name`` with the spread included, when the form depends on
        what is flown (else ``sd`` as it is)."""
        if not self.depends or name not in self.params:
            return sd
        return math.hypot(sd, self.spread()[name])

    def to_json(self) -> dict[str, object]:
        return {"split_hz": self.split_hz, "chi2": self.chi2, "z": self.z, "depends_on_commands": self.depends,
                "at_bound": self.at_bound, "matters": self.matters,
                "slow": {n: float(v) for n, v in zip(self.params, self.slow, strict=True)},
                "slow_sd": {n: float(v) for n, v in zip(self.params, self.slow_sd, strict=True)},
                "fast": {n: float(v) for n, v in zip(self.params, self.fast, strict=True)},
                "fast_sd": {n: float(v) for n, v in zip(self.params, self.fast_sd, strict=True)}}

    def describe(self, units: dict[str, str]) -> str:
        """One sentence for a finding's explanation (only when the form depends on the commands)."""

        def vals(p: np.ndarray, sd: np.ndarray) -> str:
            return ", ".join(f"{n} {_num(v, n, 3)} +- {_num(s, n, 2)}{_unit(units, n)}"
                             for n, v, s in zip(self.params, p, sd, strict=True))

        edge = " (a fit at the edge of its allowed range: the spread is at least this)" if self.at_bound else ""
        return (f" Its fit depends on what is flown: on the commands' slow part (below {self.split_hz:.2g} Hz, "
                f"the loop's own frequency) {vals(self.slow, self.slow_sd)}; on their fast part "
                f"{vals(self.fast, self.fast_sd)}{edge}, {self.z:.1f} sigma apart. The loop is not the model's "
                f"second-order one (e.g. an autopilot's input shaping or acceleration limit ahead of its "
                f"controller), so these values describe this flight's commands, and their uncertainty includes "
                f"half that spread.")


def _num(v: float, name: str, digits: int) -> str:
    return f"{1000 * v:.{digits}g}" if name == "delay" else f"{v:.{digits}g}"


def _unit(units: dict[str, str], name: str) -> str:
    if name == "delay":
        return " ms"
    u = units.get(name, "")
    return f" {u}" if u and u != "1" else ""


def split_filter(frame_s: float, omega_p: float) -> tuple[float, np.ndarray, np.ndarray]:
    """The split frequency (Hz) and the low-pass (b, a) at the loop's natural frequency: a
    second-order Butterworth, run forwards and backwards (zero phase, a fourth-order slope)."""
    fs = 1.0 / frame_s
    f = min(max(omega_p, 1e-3) / (2.0 * math.pi), MAX_SPLIT_FRACTION * fs)
    b, a = filters.butter2_lowpass(f / (0.5 * fs))
    return f, b, a


class Splitter:
    """The slow (zero-phase low-passed, per segment) and fast (the rest) parts of (2, n)
    residuals over fixed segments: ``split(e)``. A segment too short to filter gives both parts
    zero there (it carries no split information). The segments' filtering plan is made once (a
    lossy hour has thousands of segments, and a fit splits dozens of residuals)."""

    def __init__(self, segments: Sequence[tuple[int, int]], b: np.ndarray, a: np.ndarray, n: int) -> None:
        self.b, self.a = b, a
        pad = 3 * max(len(a), len(b))
        seg = np.array(segments, dtype=np.int64).reshape(-1, 2)
        self.bounds = seg[seg[:, 1] - seg[:, 0] > pad]
        # frames inside a kept segment: +1 at its start, -1 at its stop, summed
        d = np.zeros(n + 1, dtype=np.int64)
        np.add.at(d, self.bounds[:, 0], 1)
        np.add.at(d, self.bounds[:, 1], -1)
        self.inside = np.cumsum(d[:n]) > 0
        self.plan = filters.filtfilt_plan(self.bounds[:, 0], self.bounds[:, 1], pad) if len(self.bounds) else None

    def split(self, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        slow = np.zeros_like(e)
        fast = np.zeros_like(e)
        if self.plan is None:
            return slow, fast
        x = np.nan_to_num(e)
        for i in range(e.shape[0]):
            slow[i] = filters.filtfilt_segments(self.b, self.a, x[i], self.bounds[:, 0], self.bounds[:, 1], self.plan)
            fast[i] = np.where(self.inside, x[i] - slow[i], 0.0)
        return slow, fast


def loop_form(g: Group, ap: AttitudeProblem, chosen: Sequence[str], p_whole: np.ndarray, t0_s: float,
              settings: Settings, notes: list[str] | None = None) -> LoopForm | None:
    """The chosen attitude model (``chosen`` effects of the attitude group ``g``, fitted ``p_whole``)
    refitted on the slow and on the fast part of its residual (see the module docstring). None
    when no attitude effect is chosen (the nominal model has nothing to refit), or when the two
    refits would take longer than the selection's time budget (``notes`` then says so)."""
    effects = [e for e in chosen if e in LOOP_EFFECTS]
    if not effects:
        return None
    free = sorted({i for c in g.candidates if c.effect in effects for i in g.index(c.params)})
    split_hz, b, a = split_filter(ap.T, float(p_whole[0]))
    rows = ap.rows
    splitter = Splitter(ap.segments, b, a, ap.y.shape[1])
    # both parts' fits start at the whole flight's fit and take their first derivatives there: the
    # split residuals of the last few parameter vectors are kept, computed once for both parts
    memo: dict[tuple[float, ...], tuple[np.ndarray, np.ndarray]] = {}

    def split_at(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = tuple(float(x) for x in p)
        if key not in memo:
            if len(memo) >= MEMO_SIZE:
                memo.pop(next(iter(memo)))
            e = ap.residual(float(p[0]), float(p[1]), float(p[2]), fit_mask=rows)
            memo[key] = splitter.split(e)
        return memo[key]

    t = time.perf_counter()
    split_at(p_whole)
    cost_s = EVALUATIONS * (time.perf_counter() - t)
    if cost_s > settings.time_budget_s:
        if notes is not None:
            notes.append(f"attitude: the loop's form was not checked on the commands' slow and fast parts "
                         f"(about {cost_s:.0f} s, over the time budget of {settings.time_budget_s:g} s)")
        return None
    fits = []
    for part in (0, 1):
        def residuals(p: np.ndarray, part: int = part) -> list[np.ndarray]:
            x = split_at(p)[part]
            return [x[0][rows], x[1][rows]]

        # the part's group: its residual, the chosen effects only, anchored at the whole flight's
        # fit (the selector's largest model is then the part's fit, started where it is)
        part_group = dataclasses.replace(g, residuals=residuals, nominal=p_whole.copy(),
                                         candidates=[c for c in g.candidates if c.effect in effects])
        sel = Selector(part_group, settings, t0_s)
        score = sel.score_exact(effects, sel.p_full)
        fits.append((score.p[free], score.cov[np.ix_(free, free)]))
    (ps, cs), (pf, cf) = fits
    d = ps - pf
    cov = cs + cf
    # chi-square over the directions the two fits determine (a parameter neither part moves, e.g.
    # pinned at a bound with no uncertainty, is no evidence either way), with as many degrees of
    # freedom, turned into the normal z of the same tail probability (as ``Selector.compare`` does)
    z = 0.0
    chi2 = 0.0
    if np.all(np.isfinite(d)) and np.all(np.isfinite(cov)):
        rank = int(np.linalg.matrix_rank(cov))
        if rank > 0:
            chi2 = float(d @ np.linalg.pinv(cov) @ d)
            z = z_of_chi2(chi2, rank)
    # the difference must matter by the size rules of the effects (``sizes``): a 0.2 % change of
    # zeta is certain on a noise-free record yet describes the same loop
    names = [g.params[i] for i in free]
    slow_p = dict(zip(names, (float(x) for x in ps), strict=True))
    fast_p = dict(zip(names, (float(x) for x in pf), strict=True))
    matters = False
    for e in effects:
        cand = next(c for c in g.candidates if c.effect == e)
        if e == "attitude_delay":
            check = threshold(e)
            fast_e = {"delay": fast_p["delay"] - slow_p["delay"]}
        else:
            check = threshold(e, {n: slow_p[n] for n in cand.params})
            fast_e = {n: fast_p[n] for n in cand.params}
        matters |= check is None or check(fast_e) is None
    span = g.upper[free] - g.lower[free]
    at_bound = bool(any(np.any((np.abs(x - g.lower[free]) <= 1e-6 * span) | (np.abs(x - g.upper[free]) <= 1e-6 * span))
                        for x in (ps, pf)))
    return LoopForm(split_hz, tuple(g.params[i] for i in free), p_whole[free].copy(), ps,
                    np.sqrt(np.maximum(np.diag(cs), 0.0)), pf, np.sqrt(np.maximum(np.diag(cf), 0.0)),
                    chi2, z, settings.z_min, at_bound, matters)
