"""Fitting candidate effects and choosing among them: blocked cross-validation, jackknife, BIC.

A *group* is a residual model over some channels with a parameter vector (nominal = the paper's
model) and candidate effects, each freeing some of the parameters (``Candidate``). The
``Selector`` does, for one group:

1. Noise scale per channel: a robust standard deviation (MAD) of the residual of the *largest*
   model (every candidate free), floored at the channel's resolution. Residuals are weighted by it,
   so channels in different units add up as chi-square.
2. Blocked K-fold cross-validation: time is cut into blocks of ``block_s`` and block j belongs to
   fold j mod K (interleaved, so an effect confined to part of the flight is seen by every training
   set, and blocks much longer than the residuals' correlation time keep folds nearly independent).
3. Forward selection on the linearisation at the largest model's fit (every candidate subset and
   fold is a small linear least-squares problem from per-fold sufficient statistics): at each step
   the candidate that lowers the held-out error most is added if it *earns its parameters*:
   - held-out chi-square lower in the paired per-fold comparison (t >= ``cv_t_screen``; the exact
     refit asks ``cv_t_min`` of its held-out z),
   - its parameters further than ``z_screen`` sigma from the nominal (Wald test, jackknife
     covariance over the folds, which holds under correlated residuals, plus what the recording's
     time stamps leave unknown of a delay or lag, ``Group.timing``; the exact refit asks
     ``z_min``: the screen only proposes, the exact refit confirms),
   - the information criterion (BIC) lower with it, and
   - the held-out RMS of its primary channel lower by at least ``min_improvement_pct``.
   A selected effect is dropped again when, refitted with the others, it no longer passes.
4. The chosen model is refitted exactly (Gauss-Newton with the fixed Jacobian, on the exact
   residual), on all data and on each fold's training set; its held-out residual and that of the
   model without each of its effects (and with each rejected effect added) are exact too.

Everything is linear-time in the recording: the residual functions are, and the selection works
on K x P x P statistics.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TypeVar

import numpy as np
from scipy import special


def z_of_chi2(w: float, dof: int) -> float:
    """The two-sided normal z with the tail probability of ``w`` under a chi-square with ``dof``
    degrees of freedom (a Wald statistic turned into z; inf counts as certain, z capped at
    p = 1e-300). scipy.stats' chi2.sf and norm.isf are these special functions; scipy.stats costs
    0.3 s to import."""
    pval = float(special.chdtrc(dof, w)) if math.isfinite(w) else 0.0
    return float(-special.ndtri(max(pval, 1e-300) / 2)) if pval < 1 else 0.0


@dataclass(frozen=True)
class Candidate:
    """An effect of CONVENTIONS.md (or an added one) and the group parameters it frees.

    ``physical``: optional check of fitted values (name -> value); returns why they are not
    physical (e.g. a negative drag), or None."""

    effect: str
    params: tuple[str, ...]
    physical: Callable[[dict[str, float]], str | None] | None = None
    #: optional: why fitted values are too small to matter physically (``companion.diagnose.closed_loop.sizes``),
    #: or None when they matter
    matters: Callable[[dict[str, float]], str | None] | None = None
    #: parameters whose upper bound is the fastest the recording's frames resolve (a loop's natural
    #: frequency): a fit there says "at least this fast", not that something else is at work, and
    #: its Wald z (a quadratic approximation that the bound cuts off, and that measures a fast loop
    #: on a scale, rad/s, where every loop faster than the frames looks the same) gives way to the
    #: exact held-out z, which must then reach ``Settings.z_min`` (``Selector.compare``)
    resolution_upper: tuple[str, ...] = ()


@dataclass(frozen=True)
class Settings:
    """Selection settings (see the module docstring)."""

    folds: int = 8
    block_s: float = 5.0
    #: a short flight uses shorter blocks, so that each fold holds at least two: its length is
    #: duration / (2 folds), between this and ``block_s`` (s)
    min_block_s: float = 2.0
    #: an exact comparison needs held-out data in at least this many time blocks
    min_blocks: int = 8
    #: time clusters of the cluster-robust covariance (longer than the residuals' correlation)
    cluster_s: float = 10.0
    z_min: float = 3.0
    #: the linearised screen's Wald z (lower, as ``cv_t_screen`` is: the linearisation at the
    #: nominal or the largest model understates an effect it is far from, a delay of more than
    #: a frame; every effect the screen chooses must pass ``z_min`` in the exact refit)
    z_screen: float = 2.0
    #: exact fits: the held-out gain over the time blocks at least this many of its noise-only
    #: standard deviations (``Selector.heldout_z``)
    cv_t_min: float = 2.0
    #: the linearised screen's paired t over the folds (a candidate must pass it to be refitted
    #: exactly; lower, because an effect that shows only when the vehicle moves, or only at
    #: height, gains in few folds)
    cv_t_screen: float = 1.0
    min_improvement_pct: float = 2.0
    #: an effect with a physical size threshold (``sizes``) whose parameters are this many sigma
    #: from the nominal needs only some held-out gain: it matters by its size, and a noisy channel
    #: (a gyro bias under a noisy attitude) dilutes its share of the residual
    z_overwhelming: float = 10.0
    chord_iterations: int = 2
    #: choose from two starting linearisations (the largest model's fit and the nominal model) and
    #: keep the choice whose exact model predicts held-out data better
    two_starts: bool = True
    #: flights longer than this use the first start only (the time is linear in the length, and
    #: the candidates' trade-offs that a second start resolves are pinned by that much data) (s)
    two_starts_max_s: float = 1200.0
    #: a searched (localised) effect must beat this tail probability of its statistic under the
    #: no-effect null, calibrated on the recording itself (``Group.null_pvalue``)
    null_p_max: float = 0.01
    #: forward-selection steps at most (each adds one effect or a pair; a set of effects is never
    #: visited twice, so the selection ends even without this cap)
    max_steps: int = 12
    #: ``Group.check``: an effect whose independent check's z is at most this is contradicted by it
    check_veto_z: float = -2.0
    #: ``Group.check``: an effect whose independent check's z is at least this (and whose own
    #: held-out gain is positive) passes the held-out test: a sensor the fit did not use confirms it
    check_confirm_z: float = 3.0
    #: wall-clock budget of one group's selection (s); past it the selection keeps what it has
    #: chosen and says so
    time_budget_s: float = 20.0


@dataclass
class Group:
    """A residual model over some channels.

    ``residuals(p)`` returns one 1-D array per channel (fixed length and row order for every p);
    ``row_times[c]`` the time (s) of each row of channel c (for folds and windows);
    ``floors[c]`` the channel's resolution (a noise scale below it is not believed);
    ``steps`` finite-difference steps per parameter; ``lower``/``upper`` bounds.
    """

    name: str
    params: tuple[str, ...]
    nominal: np.ndarray
    steps: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    channels: tuple[str, ...]
    units: tuple[str, ...]
    floors: tuple[float, ...]
    residuals: Callable[[np.ndarray], list[np.ndarray]]
    row_times: list[np.ndarray]
    candidates: list[Candidate]
    #: parameters the residuals are linear in (their Jacobian column needs one evaluation)
    linear: tuple[str, ...] = ()
    #: optional, for an effect with a searched part (the wind window): ``search(p, train)`` finds
    #: that part on the rows of ``train`` (per-channel masks; all rows when None) from the residual
    #: at p with the effect's own (linear) parameters zeroed, keeps it, and returns the residual's
    #: derivative with respect to those parameters, one (rows, n) array per channel
    search: Callable[[np.ndarray, list[np.ndarray] | None], list[np.ndarray]] | None = None
    #: the searched part as numbers (e.g. start_s, end_s), for the report
    state: Callable[[], dict[str, float]] | None = None
    #: the effect that has a searched part
    searched_effect: str | None = None
    #: for the searched effect: ``null_pvalue(p_with, p_without)`` = the tail probability of the
    #: search statistic under the null of no effect, calibrated on the recording (a localised
    #: effect cannot be judged by folds that hold out data where it is absent), and the rows of each
    #: channel where it acts (inside and around its window) for the held-out improvement
    null_pvalue: Callable[[np.ndarray, np.ndarray], float] | None = None
    active_rows: Callable[[], list[np.ndarray] | None] | None = None
    #: (parameter, sigma_s): a parameter that is a time between two recorded streams (a delay, a
    #: lag) whose time stamps leave their relative timing uncertain by sigma_s (1 ms stamps:
    #: ``groups.timing_sigma_s``). No amount of data pins it closer: the covariance adds sigma_s^2
    #: to it, or, when it is not fitted, what that shift of it moves the fitted ones by
    #: (``Selector._cov``)
    timing: tuple[str, float] | None = None
    #: per channel, whether its noise is coloured (an estimator's output, correlated over a good
    #: part of a second): a window of it stands above the noise's rms by chance far more often than
    #: white noise's, and ``diagnosis`` judges it against the flight's typical window as well
    #: (``locate.typical_window_rms``); none when empty
    coloured: tuple[bool, ...] = ()
    #: optional instruments: ``instrument(p)`` returns, per channel, residuals of the same rows
    #: whose derivative in p is the channel's instrument (None for a channel fitted by plain least
    #: squares): a regressor that carries noise of its own (a rotation from a noisy source) is
    #: fitted by the instrumental-variable normal equations Z'J d = -Z'r, which that noise does not
    #: attenuate as it does J'J, as long as the instrument's noise is independent of both
    instrument: Callable[[np.ndarray], list[np.ndarray | None]] | None = None
    #: optional independent check: ``check(p_with, p_without)`` gives the z of a channel the fit
    #: does not use (the flow group's accelerometer, ``groups.accelerometer_z``) for the change
    #: from p_without to p_with (p_with with the effect's parameters at the nominal: the effect's
    #: own part of the fit), and how many rows it has (NaN, 0 when it cannot tell). An exact
    #: comparison is turned down when it says ``Settings.check_veto_z`` or less (the sensor
    #: contradicts the effect), and passes the held-out test with ``check_confirm_z`` or more
    #: when its own held-out gain is positive (``Selector.compare``)
    check: Callable[[np.ndarray, np.ndarray], tuple[float, int]] | None = None

    def index(self, names: Sequence[str]) -> list[int]:
        return [self.params.index(n) for n in names]


@dataclass
class ModelScore:
    """A model (set of effects) scored by cross-validation and on all data."""

    effects: tuple[str, ...]
    free: list[int]
    p: np.ndarray  # full-data fit
    p_folds: np.ndarray  # (K, P) fits on each fold's training set
    cov: np.ndarray  # (P, P) covariance of p (jackknife, floored by the asymptotic one), zero outside free
    fold_sse: np.ndarray  # (K,) held-out weighted SSE per fold
    heldout_ss: np.ndarray  # (C,) held-out unweighted sum of squares per channel (summed over folds)
    full_sse: float  # weighted SSE on all data
    n_rows: int
    #: the searched part's state on all data and per fold (e.g. the wind window)
    state: dict[str, float] = field(default_factory=dict)
    fold_states: list[dict[str, float]] = field(default_factory=list)
    #: exact scores only: each channel's held-out residual, row by row (the row's fold held out)
    heldout_rows: list[np.ndarray] | None = None

    @property
    def cv_sse(self) -> float:
        return float(np.sum(self.fold_sse))

    def bic(self) -> float:
        n = max(self.n_rows, 1)
        return n * math.log(max(self.full_sse, 1e-300) / n) + len(self.free) * math.log(n)


@dataclass
class Comparison:
    """One effect's evidence: the model with it against the model without it."""

    effect: str
    with_: ModelScore
    without: ModelScore
    z: float  # Wald statistic as an equivalent normal z (at a resolution bound: the held-out z)
    cv_t: float  # paired t of the per-fold held-out improvement
    dbic: float  # BIC(with) - BIC(without)
    heldout_rms_before: np.ndarray  # (C,) per channel
    heldout_rms_after: np.ndarray
    primary: int  # channel index where it improves most (relative)
    significant: bool = False
    reasons: list[str] = field(default_factory=list)
    #: searched effects: tail probability of the search statistic under the calibrated null
    null_p: float = math.nan
    #: the Wald z as computed (``z`` is the held-out z where a parameter sits at a resolution bound,
    #: ``Candidate.resolution_upper``)
    wald_z: float = math.nan
    at_resolution_bound: bool = False
    #: ``Group.check``'s z and rows (NaN, 0: not checked)
    check_z: float = math.nan
    check_rows: int = 0
    #: ``Group.check``'s z against the model refitted without the effect (NaN: not asked; it is
    #: asked only when a confirmation would pass a held-out test that failed)
    check_refit_z: float = math.nan

    @property
    def improvement_pct(self) -> float:
        b, a = self.heldout_rms_before[self.primary], self.heldout_rms_after[self.primary]
        return 100.0 * (b - a) / b if b > 0 else 0.0


#: the sandwich's correlation is used unless it is this much nearer singular than the model's
#: (smallest eigenvalue of the correlation matrix under this share of the model's): ``_correlation``
SINGULAR_SHARE = 0.1


def _correlation(cr: np.ndarray, Hi: np.ndarray) -> tuple[np.ndarray, bool]:
    """The free parameters' correlation matrix: the cluster-robust sandwich's ``cr``, or the model's
    (Gauss-Newton, ``Hi`` = H^-1) where the sandwich is singular beside it; and whether it was.

    Why: the sandwich sums the scores of the time blocks, so it spans no more directions than the
    blocks that carry a score. A wind over 4 s of a 41 s flight has scores in two blocks: its fx
    and fy came out correlated at +1.00000 although they act on different axes (the model says 0),
    and the Wald test along the direction no block spans was infinitely confident (z 29 for
    fx = -0.12 +- 0.07, fy = 0.10 +- 0.07, each under 2 sigma: a false wind on a clean flight;
    gen_0164, gen_0293 likewise, at -0.99999). Only where the sandwich's smallest eigenvalue is
    under ``SINGULAR_SHARE`` of the model's; the caller then floors the variances by the model's
    too (one block's sandwich is zero)."""
    def corr(c: np.ndarray) -> np.ndarray:
        d = np.sqrt(np.clip(np.diag(c), 0.0, None))
        ok = d > 0
        if ok.all():  # (the usual case: every element divided, no index arrays needed)
            return np.clip(c / np.outer(d, d), -1.0, 1.0)
        out = np.eye(len(c))
        out[np.ix_(ok, ok)] = c[np.ix_(ok, ok)] / np.outer(d[ok], d[ok])
        return np.clip(out, -1.0, 1.0)

    c_cr, c_as = corr(cr), corr(Hi)
    if len(cr) == 0 or not (np.all(np.isfinite(c_cr)) and np.all(np.isfinite(c_as))):
        return c_cr, False
    if not np.all(np.diag(cr) > 0.0):  # the sandwich says nothing along some parameter (one block)
        return c_as, True
    if len(cr) == 1:
        return c_cr, False
    e_cr, e_as = np.linalg.eigvalsh(c_cr)[0], np.linalg.eigvalsh(c_as)[0]
    singular = bool(e_cr < SINGULAR_SHARE * e_as)
    return (c_as if singular else c_cr), singular


def block_ids(t_s: np.ndarray, t0_s: float, settings: Settings, block_s: float | None = None) -> np.ndarray:
    """Time block of each time: floor((t - t0) / block_s)."""
    return np.floor((t_s - t0_s) / (block_s or settings.block_s)).astype(int)


def block_length(row_times: Sequence[np.ndarray], t0_s: float, settings: Settings) -> float:
    """The cross-validation block length for rows spanning these times: ``block_s``, shortened
    for a short flight to duration / (2 folds), not below ``min_block_s``."""
    ends = [float(t.max()) for t in row_times if len(t)]
    if not ends:
        return settings.block_s
    span = max(ends) - t0_s
    return float(np.clip(span / (2 * settings.folds), settings.min_block_s, settings.block_s))


def block_meat(scores: np.ndarray) -> np.ndarray:
    """The middle of a cluster-robust sandwich over time blocks: the sum over blocks of s s' of
    each block's score s, plus adjacent blocks' cross terms at half weight (a Newey-West estimate
    with one lag: it holds when residuals are correlated across a block's edge, as turbulence
    makes them). ``scores``: (B, k) per block, or (B,) for one score (then a 0-d array)."""
    if scores.ndim == 1:
        return np.asarray(float(scores @ scores) + (float(scores[1:] @ scores[:-1]) if len(scores) > 1 else 0.0))
    S = scores.T @ scores
    if len(scores) > 1:
        cross = scores[1:].T @ scores[:-1]
        S = S + 0.5 * (cross + cross.T)
    return S


def robust_std(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


#: ``Selector.residuals`` keeps this many parameter vectors' residuals (and ``weighted`` as many
#: weighted ones)
RESIDUAL_MEMO = 6


_Key = TypeVar("_Key")


def _remember(memo: dict[_Key, list[np.ndarray]], key: _Key, value: list[np.ndarray]) -> None:
    """Put ``value`` in ``memo`` as its newest entry, the oldest dropped past ``RESIDUAL_MEMO``."""
    memo[key] = value
    if len(memo) > RESIDUAL_MEMO:
        memo.pop(next(iter(memo)))


#: ``Selector._stats`` forms the rows' outer products a batch of blocks at a time, at most this
#: many values at once (32 MB)
STATS_BATCH_VALUES = 4_000_000

#: a linearisation's statistics per (fold, channel): J'J, J'r, r'r, and the training side's Z'J, Z'r
_Stats = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _block_products(A: np.ndarray, B: np.ndarray, starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Each block's A'B (rows sorted by block, blocks starting at ``starts``): the rows' outer
    products summed per block, a batch of blocks at a time (at most STATS_BATCH_VALUES values of
    outer products at once)."""
    P, Q = A.shape[1], B.shape[1]
    out = np.empty((len(starts), P, Q))
    limit = max(1, STATS_BATCH_VALUES // (P * Q))
    i = 0
    while i < len(starts):
        j = max(i + 1, int(np.searchsorted(stops, starts[i] + limit, side="right")))
        a, b = int(starts[i]), int(stops[j - 1])
        out[i:j] = np.add.reduceat(A[a:b, :, None] * B[a:b, None, :], starts[i:j] - a, axis=0)
        i = j
    return out


class Selector:
    """Fit and choose among a group's candidate effects (see the module docstring)."""

    #: the linearisation (``_linearise``, ``_stats``): per channel the Jacobian (rows, P); per
    #: (fold, channel) J'J, J'r and r'r; per cross-validation block J'J and J'r
    J: list[np.ndarray]
    G: np.ndarray
    gv: np.ndarray
    ss: np.ndarray
    Gb: np.ndarray
    gvb: np.ndarray

    def __init__(self, group: Group, settings: Settings, t0_s: float) -> None:
        self.g = group
        self.s = settings
        self.K = settings.folds
        #: what the selection had to cut short, for the report
        self.notes: list[str] = []
        self._deadline = time.monotonic() + settings.time_budget_s
        self._timed_out = False
        self._null_cache: dict[tuple[tuple[float, ...], tuple[float, ...]], float] = {}
        #: the last residuals and weighted residuals (``residuals``, ``weighted``)
        self._memo_raw: dict[bytes, list[np.ndarray]] = {}
        self._memo_weighted: dict[tuple[bytes, bytes], list[np.ndarray]] = {}
        #: ``_blocks`` by set of free parameters
        self._block_index: dict[tuple[int, ...], tuple[list[int], tuple[np.ndarray, ...], tuple[np.ndarray, ...]]] = {}
        #: the parameters of the last ``_relinearise``, until anything moves the linearisation
        self._linearised_at: bytes | None = None
        self.t0_s = t0_s
        self.block_s = block_length(group.row_times, t0_s, settings)
        self.cvblocks = [np.maximum(block_ids(t, t0_s, settings, self.block_s), 0) for t in group.row_times]
        self.folds = [b % settings.folds for b in self.cvblocks]
        self.per_cluster = max(1, int(round(settings.cluster_s / self.block_s)))
        self.n_blocks = int(max((int(b.max()) for b in self.cvblocks if len(b)), default=0)) // self.per_cluster + 1
        self.n_rows = int(sum(len(t) for t in group.row_times))
        self.P = len(group.params)
        self.sigma = np.ones(len(group.channels))
        self.r_nominal = self.residuals(group.nominal)
        self.sigma = self._noise(self.r_nominal)
        self.widx: list[int] = []
        self.Z: list[np.ndarray | None] | None = None
        self.Gzz = np.zeros((self.P, self.P))  # Z'Z over all rows (``_stats``)
        if group.searched_effect is not None:
            cand = next(c for c in group.candidates if c.effect == group.searched_effect)
            self.widx = group.index(cand.params)
        # the largest model, fitted from the nominal (Levenberg-Marquardt), and linearised there
        self.all_free = sorted({i for c in group.candidates for i in group.index(c.params)})
        self._linearise(group.nominal)
        p_full = self._levenberg(group.nominal.copy(), self.all_free)
        if self.widx:
            self._search(p_full, None)
            p_full = self._levenberg(p_full, self.all_free)
        self.p_full = p_full
        self.sigma = self._noise(self.residuals(p_full))
        self._relinearise(p_full)

    def _relinearise(self, p: np.ndarray) -> None:
        """Linearise at p (the searched effect's own parameters from zero) and, for the searched
        effect, keep per-fold statistics with its part found on each training set alone. Nothing
        to do when the last linearisation was made here at p and nothing has moved since (no
        search, which moves the stored Jacobian): the selection starts where the constructor
        linearised, at the largest model's fit."""
        if p.tobytes() == self._linearised_at:
            return
        base = p.copy()
        base[self.widx] = self.g.nominal[self.widx]
        self._linearise(base)
        self.state_full = self.g.state() if (self.widx and self.g.state) else {}
        self.variants: list[_Stats] = []
        if self.widx:
            J_full = [j.copy() for j in self.J]
            Z_full = None if self.Z is None else [None if z is None else z.copy() for z in self.Z]
            Gb0, gvb0, Gzz0 = self.Gb.copy(), self.gvb.copy(), self.Gzz.copy()
            # only channels the searched effect acts on change between variants
            moving = [c for c in range(len(self.J)) if np.any(self.J[c][:, self.widx])]
            for k in range(self.K):
                self._search(base, [f != k for f in self.folds])
                full = [x.copy() for x in self.stats]
                if self.Z is None:  # Z'J and Z'r are J'J and J'r
                    full[3], full[4] = full[0], full[1]
                part = self._stats(moving)
                for i in range(5 if self.Z is not None else 3):
                    full[i][:, moving] = part[i][:, moving]
                self.variants.append((full[0], full[1], full[2], full[3], full[4]))
            self.J = J_full
            self.Z = Z_full
            self.Gb, self.gvb, self.Gzz = Gb0, gvb0, Gzz0
            self._search(base, None)
        self._linearised_at = p.tobytes()

    def _levenberg(self, p: np.ndarray, free: Sequence[int], iterations: int = 15) -> np.ndarray:
        """Levenberg-Marquardt on the exact residual from p over all rows, the Jacobian started
        from the stored linearisation and kept up to date by Broyden's rank-one updates (no new
        finite differences): robust to large departures from the nominal model, linear-time."""
        free = list(free)
        if not free:
            return p.copy()
        p = p.copy()
        lo, hi = self.g.lower[free], self.g.upper[free]
        J = [j[:, free].copy() for j in self.J]
        r = self.weighted(p)
        sse = float(sum(float(x @ x) for x in r))
        lam = 1e-3
        for _ in range(iterations):
            A = sum(j.T @ j for j in J)
            grad = sum(j.T @ x for j, x in zip(J, r, strict=True))
            accepted = False
            for _try in range(8):
                step = -_solve(A + lam * np.diag(np.diag(A) + 1e-12), grad)
                new = np.clip(p[free] + step, lo, hi)
                actual = new - p[free]
                if not np.any(actual):
                    break
                q = p.copy()
                q[free] = new
                r_new = self.weighted(q)
                sse_new = float(sum(float(x @ x) for x in r_new))
                den = float(actual @ actual)
                for c in range(len(J)):  # Broyden: make J reproduce the step just taken
                    J[c] += np.outer(r_new[c] - r[c] - J[c] @ actual, actual) / den
                if sse_new < sse:
                    gain = (sse - sse_new) / max(sse, 1e-300)
                    p, r, sse = q, r_new, sse_new
                    lam = max(lam / 3.0, 1e-9)
                    accepted = gain > 1e-6  # a relative gain this small: converged
                    break
                lam *= 4.0
                A = sum(j.T @ j for j in J)
                grad = sum(j.T @ x for j, x in zip(J, r, strict=True))
            if not accepted or np.all(np.abs(actual) < 1e-4 * self.g.steps[free]):
                break
        return p

    # -- residuals and linearisation -------------------------------------------------------------

    def _noise(self, res: list[np.ndarray]) -> np.ndarray:
        return np.array([max(robust_std(r), f, 1e-300) for r, f in zip(res, self.g.floors, strict=True)])

    def residuals(self, p: np.ndarray) -> list[np.ndarray]:
        """The group's residuals at p (read-only arrays), kept for the last ``RESIDUAL_MEMO``
        parameter vectors until the searched part moves (``_search``, the one state a group's
        residuals read besides p). Why: a fit evaluates the same parameters again and again (each
        fold's refit starts where the full fit ended, a Jacobian at the last iterate, the largest
        model's noise at its fit): a third of a lossy hour's evaluations were repeats."""
        key = p.tobytes()
        r = self._memo_raw.pop(key, None)
        if r is None:
            r = self.g.residuals(p)
            for x in r:
                x.flags.writeable = False
        _remember(self._memo_raw, key, r)
        return r

    def weighted(self, p: np.ndarray) -> list[np.ndarray]:
        """Residuals divided by each channel's noise scale; a non-finite row counts as 0 (read-only
        arrays, kept as ``residuals`` keeps its own)."""
        key = (p.tobytes(), self.sigma.tobytes())
        w = self._memo_weighted.pop(key, None)
        if w is None:
            w = []
            for r, s in zip(self.residuals(p), self.sigma, strict=True):
                x = r / s
                w.append(np.where(np.isfinite(x), x, 0.0))  # np.nan_to_num's zeros, without its wrapper
            for x in w:
                x.flags.writeable = False
        _remember(self._memo_weighted, key, w)
        return w

    def weighted_sse(self, p: np.ndarray) -> float:
        """The sum of squares of ``weighted(p)`` over every channel."""
        return float(sum(float(r @ r) for r in self.weighted(p)))

    def jacobian(self, p: np.ndarray, cols: Sequence[int]) -> list[np.ndarray]:
        """Weighted Jacobian per channel (rows, len(cols)) by forward differences with the group's
        steps (exact for the parameters the residuals are linear in; it only steers the fits,
        which converge on the exact residual)."""
        out = [np.zeros((len(t), len(cols))) for t in self.g.row_times]
        r0 = self.weighted(p)
        for j, i in enumerate(cols):
            h = self.g.steps[i]
            pp = p.copy()
            pp[i] += h
            rp = self.weighted(pp)
            for c in range(len(out)):
                out[c][:, j] = (rp[c] - r0[c]) / h
        return out

    def _instruments(self, p: np.ndarray, cols: Sequence[int]) -> list[np.ndarray | None] | None:
        """Per channel the instruments (rows, P) at p (``Group.instrument``: its residuals'
        forward differences, weighted as the residuals are; None for a channel without), or None."""
        if self.g.instrument is None:
            return None
        r0 = self.g.instrument(p)
        out: list[np.ndarray | None] = [None if x is None else np.zeros((len(x), self.P)) for x in r0]
        for i in cols:
            pp = p.copy()
            pp[i] += self.g.steps[i]
            rp = self.g.instrument(pp)
            for c, z in enumerate(out):
                rpc, r0c = rp[c], r0[c]
                if z is not None and rpc is not None and r0c is not None:
                    d = (rpc - r0c) / (self.g.steps[i] * self.sigma[c])
                    z[:, i] = np.where(np.isfinite(d), d, 0.0)
        return out

    def _search(self, p: np.ndarray, train: list[np.ndarray] | None) -> None:
        """Run the group's search and put its columns into the stored Jacobian."""
        assert self.g.search is not None
        self._linearised_at = None
        self._memo_raw.clear()  # the residuals move with the searched part
        self._memo_weighted.clear()
        cols = self.g.search(p, train)
        for c in range(len(self.J)):
            self.J[c][:, self.widx] = cols[c] / self.sigma[c]
            z = None if self.Z is None else self.Z[c]
            if z is not None:  # the searched part is its own instrument
                z[:, self.widx] = self.J[c][:, self.widx]

    def _linearise(self, p: np.ndarray) -> None:
        """Jacobian and per (fold, channel) sufficient statistics of the linearisation at p."""
        self._linearised_at = None
        self._linear_scores: dict[tuple[frozenset[str], bool], ModelScore] = {}
        self._sums: dict[tuple[int | None, int | None], tuple[tuple[np.ndarray, np.ndarray],
                                                              tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
        self.p_lin = p.copy()
        others = [i for i in range(self.P) if i not in self.widx]
        Jo = self.jacobian(p, others)
        self.J = [np.zeros((len(t), self.P)) for t in self.g.row_times]
        for c in range(len(self.J)):
            self.J[c][:, others] = Jo[c]
        self.Z = self._instruments(p, others)
        if self.widx:
            self._search(p, None)
        self.r_lin = self.weighted(p)
        self.stats = self._stats()
        self.cnt = np.array([[np.count_nonzero(f == k) for f in self.folds] for k in range(self.K)], dtype=float)

    def _stats(self, channels: Sequence[int] | None = None) -> _Stats:
        """Per (fold, channel): J'J, J'r, r'r of the linearisation, and the training side's Z'J
        and Z'r (the instruments Z, ``Group.instrument``; the same arrays as J'J and J'r when the
        group has none); per time cluster (summed over channels) Z'J and Z'r for the
        cluster-robust covariance (``_cov``), and Z'Z over all rows. One pass: the sums are taken
        per cross-validation block, then added up into folds and clusters."""
        C, K, P = len(self.g.channels), self.K, self.P
        G = np.zeros((K, C, P, P))
        gv = np.zeros((K, C, P))
        ss = np.zeros((K, C))
        iv = self.Z is not None
        Gz, gz = (np.zeros((K, C, P, P)), np.zeros((K, C, P))) if iv else (G, gv)
        self.Gb = np.zeros((self.n_blocks, P, P))
        self.gvb = np.zeros((self.n_blocks, P))
        self.Gzz = np.zeros((P, P))
        for c in range(C) if channels is None else channels:
            J, r, blk = self.J[c], self.r_lin[c], self.cvblocks[c]
            if len(r) == 0:
                continue
            zc = None if self.Z is None else self.Z[c]
            Zc = J if zc is None else zc
            order = np.argsort(blk, kind="stable")
            bs = blk[order]
            starts = np.concatenate([[0], np.flatnonzero(np.diff(bs)) + 1])
            stops = np.concatenate([starts[1:], [len(bs)]])
            Jo, ro, Zo = J[order], r[order], Zc[order]
            gsum = np.add.reduceat(Jo * ro[:, None], starts, axis=0)
            zsum = gsum if Zc is J else np.add.reduceat(Zo * ro[:, None], starts, axis=0)
            rsum = np.add.reduceat(ro * ro, starts)
            Gblk = _block_products(Jo, Jo, starts, stops)
            Zblk = Gblk if Zc is J else _block_products(Zo, Jo, starts, stops)
            self.Gzz += Zc.T @ Zc
            ids = bs[starts]
            fold = ids % K
            np.add.at(G[:, c], fold, Gblk)
            np.add.at(gv[:, c], fold, gsum)
            np.add.at(ss[:, c], fold, rsum)
            if iv:
                np.add.at(Gz[:, c], fold, Zblk)
                np.add.at(gz[:, c], fold, zsum)
            cl = ids // self.per_cluster
            np.add.at(self.Gb, cl, Zblk)
            np.add.at(self.gvb, cl, zsum)
        return G, gv, ss, Gz, gz

    def _gauss_newton(self, p: np.ndarray, free: Sequence[int], train: list[np.ndarray] | None, *,
                      iterations: int, jac: list[np.ndarray] | None = None) -> np.ndarray:
        """Chord iterations on the exact residual: Gauss-Newton steps with the stored Jacobian
        (or ``jac``, per channel the free parameters' columns, without instruments) over the rows
        of ``train`` (per-channel masks; all rows when None). They converge to the exact
        least-squares fit of the free parameters (the Jacobian only steers)."""
        free = list(free)
        if not free:
            return p.copy()
        p = p.copy()
        lo, hi = self.g.lower[free], self.g.upper[free]
        A = np.zeros((len(free), len(free)))
        if jac is not None:
            Js = Zs = jac
            cols: list[int] | slice = slice(None)
        else:
            Js = self.J
            Zs = [J if z is None else z for J, z in zip(self.J, self.Z or [None] * len(self.J), strict=True)]
            cols = free
        for c in range(len(Js)):
            Jc = Js[c][:, cols]
            Zc = Zs[c][:, cols]
            Zm = Zc if train is None else Zc * train[c][:, None]
            A += Zm.T @ Jc
        for _ in range(iterations):
            r = self.weighted(p)
            b = np.zeros(len(free))
            for c in range(len(r)):
                rc = r[c] if train is None else np.where(train[c], r[c], 0.0)
                b += rc @ Zs[c][:, cols]
            new = np.clip(p[free] - _solve(A, b), lo, hi)
            done = np.all(np.abs(new - p[free]) < 1e-3 * self.g.steps[free])
            p[free] = new
            if done:
                break
        return p

    # -- linearised scoring ----------------------------------------------------------------------

    def _fold_sums(self, variant: int | None, k: int | None) -> tuple[tuple[np.ndarray, np.ndarray],
                                                                       tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The sums of the per (fold, channel) statistics a linearised score takes: J'J and J'r over
        the training folds (every fold but k; every fold when k is None) and channels, and J'J, J'r,
        r'r per channel over the held-out folds (fold k; every fold). From the linearisation's
        statistics, or from ``variants[variant]``'s (the searched part found without fold
        ``variant``). Kept until the next linearisation: they depend on it alone, and a selection
        scores hundreds of effect sets from the same few (summing them again for each took half
        of a lossy hour's linearised selection)."""
        key = (variant, k)
        if key not in self._sums:
            G_all, gv_all, ss_all, Gz_all, gz_all = self.stats if variant is None else self.variants[variant]
            train = np.ones(self.K, dtype=bool)
            ks = np.arange(self.K)
            if k is not None:
                train[k] = False
                ks = np.array([k])
            self._sums[key] = ((Gz_all[train].sum(axis=(0, 1)), gz_all[train].sum(axis=(0, 1))),
                               (G_all[ks].sum(axis=0), gv_all[ks].sum(axis=0), ss_all[ks].sum(axis=0)))
        return self._sums[key]

    def _delta(self, free: list[int], trains: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """Parameter changes from p_lin (full vectors, one row per set of training folds) minimising
        the linearised SSE over each set of training folds (``trains``: their J'J and J'r,
        ``_fold_sums``), with the other parameters at their nominal values."""
        d0 = self.g.nominal - self.p_lin
        d = np.tile(d0, (len(trains), 1))
        if free:
            fixed, ff, fx = self._blocks(free)
            b = np.stack([gv[free] + G[fx] @ d0[fixed] for G, gv in trains])
            d[:, free] = -_solve_stack(np.stack([G[ff] for G, _gv in trains]), b)
        return d

    def _blocks(self, free: list[int]) -> tuple[list[int], tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
        """The parameters not in ``free`` and the index arrays of J'J's free-free and free-fixed
        blocks (``np.ix_``): made once per set of free parameters, which ``_delta`` is asked about
        for every fold of every score."""
        key = tuple(free)
        if key not in self._block_index:
            fixed = [i for i in range(self.P) if i not in free]
            self._block_index[key] = (fixed, np.ix_(free, free), np.ix_(free, fixed))
        return self._block_index[key]

    @staticmethod
    def _sse(d: np.ndarray, held: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
        """Linearised weighted SSE per channel over the held-out folds (``held``: their J'J, J'r and
        r'r per channel, ``_fold_sums``) at p_lin + d."""
        G, gv, ss = held
        return np.maximum(ss + 2 * gv @ d + np.einsum("i,cij,j->c", d, G, d), 0.0)

    def score_linear(self, effects: Sequence[str], relocate: bool = False) -> ModelScore:
        """The model scored on the linearisation: a small least-squares problem per fold. With
        ``relocate`` the searched part (wind window) is the one found on each training set alone
        (used when the searched effect itself is judged); otherwise the one found on all data."""
        free = self._free(effects)
        searched = relocate and bool(self.widx) and any(i in free for i in self.widx)
        # a pure function of the linearisation: the same effects are scored again and again (a
        # pair of one step is the single of the next, the backward check rescored), so the
        # scores are kept until the next linearisation; each caller gets its own copy
        key = (frozenset(effects), searched)
        if key not in self._linear_scores:
            self._linear_scores[key] = self._score_linear(effects, free, searched)
        m = self._linear_scores[key]
        return replace(m, effects=tuple(effects), free=list(m.free), p=m.p.copy(), p_folds=m.p_folds.copy(),
                       cov=m.cov.copy(), fold_sse=m.fold_sse.copy(), heldout_ss=m.heldout_ss.copy(),
                       state=dict(m.state))

    def _score_linear(self, effects: Sequence[str], free: list[int], searched: bool) -> ModelScore:
        K = self.K
        p_folds = np.zeros((K, self.P))
        fold_sse = np.zeros(K)
        ho = np.zeros(len(self.g.channels))
        # each fold's training set, then all folds: their solves at once
        sums = [self._fold_sums(k if searched else None, k) for k in range(K)] + [self._fold_sums(None, None)]
        deltas = self._delta(free, [train for train, _held in sums])
        for k in range(K):
            d = deltas[k]
            p_folds[k] = self.p_lin + d
            sk = self._sse(d, sums[k][1])
            fold_sse[k] = sk.sum()
            ho += sk * self.sigma ** 2
        d = deltas[K]
        full = float(self._sse(d, sums[K][1]).sum())
        p = self.p_lin + d
        has_search = bool(self.widx) and any(i in free for i in self.widx)
        return ModelScore(tuple(effects), free, p, p_folds, self._cov(free, p, p_folds, full), fold_sse, ho,
                          full, self.n_rows, state=dict(self.state_full) if has_search else {})

    def _free(self, effects: Sequence[str]) -> list[int]:
        names = [n for c in self.g.candidates if c.effect in effects for n in c.params]
        return sorted(set(self.g.index(names)))

    def _cov(self, free: list[int], p: np.ndarray, p_folds: np.ndarray, full_sse: float,
             jac: list[np.ndarray] | None = None) -> np.ndarray:
        """Covariance of the free parameters: the cluster-robust sandwich H^-1 S H^-1 over the
        time blocks (scores summed per block, adjacent blocks' cross terms at half weight: a
        Newey-West estimate that holds when residuals are correlated in time, as turbulence makes
        them), its variances floored by the jackknife over the K delete-one-fold fits. Where the
        sandwich is singular beside the model's own H^-1 (the residuals are weighted by their noise
        scale: ``_correlation``), that gives the correlation and floors the variances too. ``jac``:
        the free parameters' Jacobian at p, for a fit the linearisation does not describe
        (``_refit_off_linearisation``): the block scores and H from it instead of extrapolated."""
        del full_sse
        P = self.P
        cov = np.zeros((P, P))
        if not free:
            return cov
        K = self.K
        d = p - self.p_lin
        _fixed, ff, _fx = self._blocks(free)
        H_all = self.Gb.sum(axis=0)
        H = H_all[ff]
        sb = self.gvb[:, free] + self.Gb[:, free, :] @ d  # (B, k) block scores at p
        Hi = Hi_lin = np.linalg.pinv(H)
        if jac is not None:  # a fit the linearisation does not describe: the scores from the Jacobian at it
            sb, H = self._exact_scores(p, jac)
            Hi = np.linalg.pinv(H)
        S = block_meat(sb)
        B = max(len(sb), 1)
        cr = Hi @ S @ Hi.T * B / max(B - len(free), 1)
        own = Hi if self.Z is None else Hi @ self.Gzz[ff] @ Hi.T  # the model's own covariance
        dev = p_folds[:, free] - p_folds[:, free].mean(axis=0)
        jk = (K - 1) / K * dev.T @ dev
        dc, dj = np.diag(cr), np.diag(jk)
        var = np.maximum(dc, dj)
        corr, singular = _correlation(cr, own)
        if singular:  # a sandwich over the one or two blocks a short effect acts in (one: zero)
            var = np.maximum(var, np.clip(np.diag(own), 0.0, None))
        sd = np.sqrt(var)
        sub = corr * np.outer(sd, sd)
        sub += self._timing_cov(free, Hi_lin, H_all)
        cov[ff] = sub
        return cov

    def _exact_scores(self, p: np.ndarray, J: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The block scores (per time cluster, summed over channels: J'r over its rows) and J'J of
        the free parameters from ``J``, their Jacobian at p itself, for the sandwich of an exact fit
        the linearisation does not describe (``_refit_off_linearisation``)."""
        r = self.weighted(p)
        k = J[0].shape[1] if J else 0
        sb = np.zeros((self.n_blocks, k))
        H = np.zeros((k, k))
        for c in range(len(J)):
            if len(r[c]) == 0:
                continue
            Jc = np.nan_to_num(J[c])
            rc = np.nan_to_num(r[c])
            cl = self.cvblocks[c] // self.per_cluster
            np.add.at(sb, cl, Jc * rc[:, None])
            H += Jc.T @ Jc
        return sb, H

    def _timing_cov(self, free: list[int], Hi: np.ndarray, H_all: np.ndarray) -> np.ndarray:
        """The systematic share of the free parameters' covariance from the recording's time stamps
        (``Group.timing``): a shift s of the streams' relative timing is a shift s of the timing
        parameter; fitted, it moves by s; not fitted, the fitted ones move by -H_ff^-1 H_ft s
        (the Gauss-Newton normal equations at the linearisation, ``H_all`` summed over the blocks)."""
        out = np.zeros((len(free), len(free)))
        if self.g.timing is None or not self.g.timing[1] > 0.0:
            return out
        name, sigma_s = self.g.timing
        t = self.g.params.index(name)
        if t in free:
            k = free.index(t)
            out[k, k] = sigma_s ** 2
            return out
        h_ft = H_all[free, t]
        sens = -Hi @ h_ft
        return sigma_s ** 2 * np.outer(sens, sens)

    def compare(self, with_: ModelScore, without: ModelScore, effect: str | Sequence[str],
                screen: bool = False) -> Comparison:
        """The evidence for ``effect`` (or several effects together): ``with_`` is ``without``
        plus the effect(s). ``screen``: the selection's linearised screen, which asks less of the
        Wald z (``z_screen``) when the scores are not exact.

        A searched (localised) effect, e.g. a wind over a window, is judged where it acts: by the
        tail probability of its search statistic under a null calibrated on the recording
        (``Group.null_pvalue``) instead of the consistency of its gain over folds (folds whose
        held-out blocks lie outside the window cannot show a gain, whatever the effect's size),
        and by its held-out improvement on the rows inside and around its window."""
        effects = [effect] if isinstance(effect, str) else list(effect)
        cands = [c for c in self.g.candidates if c.effect in effects]
        idx = self.g.index([n for c in cands for n in c.params])
        dp = with_.p[idx] - self.g.nominal[idx]
        cov = with_.cov[np.ix_(idx, idx)]
        try:
            w = float(dp @ np.linalg.solve(cov, dp)) if np.all(np.isfinite(cov)) and np.linalg.det(cov) > 0 \
                else math.inf
        except np.linalg.LinAlgError:
            w = math.inf
        z = z_wald = z_of_chi2(w, len(idx))
        exact = with_.heldout_rows is not None and without.heldout_rows is not None
        localised = self.g.searched_effect in effects and self.g.null_pvalue is not None
        resolved = self._at_resolution_edge(cands, with_.p)
        z_ho, n_ho = 0.0, 0
        if exact:  # per time block: an effect that acts in some blocks only is not diluted by folds
            assert with_.heldout_rows is not None and without.heldout_rows is not None
            # a localised effect: only the blocks inside and around its window
            active = self.g.active_rows() if (localised and self.g.active_rows is not None) else None
            if active is not None and self.g.state is not None:  # consistency: inside the window only
                st = self.g.state()
                s0, s1 = st.get("start_s", -math.inf), st.get("end_s", math.inf)
                active = [a & (t >= s0) & (t <= s1) for a, t in zip(active, self.g.row_times, strict=True)]
            if not localised:
                z_ho, n_ho = self.heldout_z(with_, without)
            per, have = self._block_gain(with_, without, active)
            nb = len(per)
            if active is not None and self.g.state is not None:
                # the blocks that hold the window's ends test where it starts and stops (a fold
                # holding one out cannot place that end), not the force: left out here
                st = self.g.state()
                for key in ("start_s", "end_s"):
                    if math.isfinite(st.get(key, math.nan)):
                        j = int(math.floor((st[key] - self.t0_s) / self.block_s))
                        if 0 <= j < nb:
                            have[j] = False
            diff = per[have]
            if active is not None and len(diff) < 3:
                # too short a window to judge by blocks: its held-out gain must be positive (below)
                # and the calibrated null decides
                diff = np.full(3, 1.0)
        else:
            diff = without.fold_sse - with_.fold_sse
        sd = float(np.std(diff, ddof=1)) if len(diff) > 1 else 0.0
        mean = float(np.mean(diff))
        cv_t = mean / (sd / math.sqrt(len(diff))) if sd > 0 else (math.inf if mean > 0 else 0.0)
        t_need = self.s.cv_t_min if exact else self.s.cv_t_screen
        z_need = self.s.z_screen if screen and not exact else self.s.z_min
        if exact and not localised:
            # the held-out gain against the noise's own variance (``heldout_z``), over the blocks
            cv_t, n_blocks = z_ho, n_ho
            diff = np.zeros(n_blocks)
            if resolved:  # the Wald z has no meaning at the bound (``Candidate.resolution_upper``)
                z = cv_t
        n_per_c = self.cnt.sum(axis=0)
        before = np.sqrt(without.heldout_ss / np.maximum(n_per_c, 1))
        after = np.sqrt(with_.heldout_ss / np.maximum(n_per_c, 1))
        null_p = math.nan
        acts = np.ones(len(before), dtype=bool)
        if localised:
            null_p = self._null_p(with_.p, without.p)
            b_loc, a_loc = self._active_rms(with_, without)
            acts = np.isfinite(b_loc)
            before = np.where(acts, b_loc, before)
            after = np.where(acts, a_loc, after)
            if not np.any(acts):
                acts[:] = True
        rel = np.where(before > 0, (before - after) / np.where(before > 0, before, 1.0), 0.0)
        # the primary channel is one the effect acts on (a localised effect: where its window is)
        primary = int(np.argmax(np.where(acts, rel, -np.inf)))
        comp = Comparison("+".join(effects), with_, without, z, cv_t, with_.bic() - without.bic(), before, after,
                          primary, null_p=null_p, wald_z=z_wald, at_resolution_bound=resolved)
        if exact and not localised and self.g.check is not None:
            # the effect's own part of the fit: its parameters back at the nominal, the rest as fitted
            # with it (``without``'s refit moves the others too, which is not this effect's doing)
            p_off = with_.p.copy()
            p_off[idx] = self.g.nominal[idx]
            comp.check_z, comp.check_rows = self.g.check(with_.p, p_off)
        reasons = []
        if comp.check_z <= self.s.check_veto_z:
            reasons.append(f"the accelerometer contradicts it: over {comp.check_rows} windows it reads the flow's "
                           f"velocity worse with it (z = {comp.check_z:.1f})")
        if localised and not null_p <= self.s.null_p_max:
            reasons.append(f"a window this strong is found in this recording's own noise too "
                           f"(p = {null_p:.2g} > {self.s.null_p_max:g})")
        if localised and not exact:
            pass  # the linearised screen: the calibrated null only; the exact refit checks the blocks
        elif exact and not localised and len(diff) < self.s.min_blocks:
            reasons.append(f"too short to judge on held-out data: {len(diff)} time blocks of "
                           f"{self.block_s:.1f} s (at least {self.s.min_blocks} needed)")
        elif exact and not localised and not cv_t >= t_need:
            if cv_t > 0 and comp.check_z >= self.s.check_confirm_z and self.g.check is not None:
                # a confirmation must also hold against the model refitted without the effect: two
                # effects that cancel each other (a scale and a range offset) each look needed given
                # the other, and refitted without one the other takes its place
                comp.check_refit_z = self.g.check(with_.p, without.p)[0]
            if not (cv_t > 0 and min(comp.check_z, comp.check_refit_z) >= self.s.check_confirm_z):  # else confirmed
                reasons.append(f"held-out improvement within what the residual's own noise gives over the time "
                               f"blocks (z = {cv_t:.1f} < {t_need:g})")
        elif not cv_t >= t_need:
            over = "time blocks where it acts" if exact else "folds"
            reasons.append(f"held-out improvement not consistent over {over} (t = {cv_t:.1f} < {t_need:g})")
        if not z >= z_need:
            if resolved and exact and not localised:
                reasons.append(f"at the fastest the frames resolve, its held-out z ({z:.1f}) is under {z_need:g}")
            else:
                reasons.append(f"parameters within {z_need:g} sigma of the nominal model (z = {z:.1f})")
        if not comp.dbic < 0:
            reasons.append(f"the information criterion does not prefer it (dBIC = {comp.dbic:+.1f})")
        for cand in cands:
            ci = self.g.index(cand.params)
            span = self.g.upper[ci] - self.g.lower[ci]
            open_top = np.array([n in cand.resolution_upper for n in cand.params])
            at_bound = (np.abs(with_.p[ci] - self.g.lower[ci]) <= 1e-6 * span) \
                | ((np.abs(with_.p[ci] - self.g.upper[ci]) <= 1e-6 * span) & ~open_top)
            if np.any(at_bound):
                reasons.append("the fit ran to the edge of the allowed range: the data ask for more than this "
                               "effect can be, so something else is at work")
            vals = {n: float(with_.p[self.g.params.index(n)]) for n in cand.params}
            for check in (cand.physical, cand.matters):
                why = check(vals) if check is not None else None
                if why:
                    reasons.append(why)
        need = self.s.min_improvement_pct
        if not localised and all(c.matters is not None for c in cands) and z >= self.s.z_overwhelming:
            need = 0.0
        if not comp.improvement_pct > need:
            where = " where it acts" if localised else ""
            reasons.append(f"held-out residual{where} lower by only {comp.improvement_pct:.2f} % "
                           f"(needs > {need:g} %)")
        comp.reasons = reasons
        comp.significant = not reasons
        return comp

    def _at_resolution_edge(self, cands: Sequence[Candidate], p: np.ndarray) -> bool:
        """Whether p holds one of ``cands``' ``resolution_upper`` parameters at its upper bound."""
        for cand in cands:
            for name in cand.resolution_upper:
                i = self.g.params.index(name)
                if abs(p[i] - self.g.upper[i]) <= 1e-6 * (self.g.upper[i] - self.g.lower[i]):
                    return True
        return False

    def _block_gain(self, with_: ModelScore, without: ModelScore,
                    active: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Per time block, the held-out weighted SSE of ``without`` minus that of ``with_`` (exact
        scores), over the rows of ``active`` (all rows when None); and which blocks hold any row."""
        assert with_.heldout_rows is not None and without.heldout_rows is not None
        nb = int(max((int(b.max()) for b in self.cvblocks if len(b)), default=0)) + 1
        per = np.zeros(nb)
        have = np.zeros(nb, dtype=bool)
        for c in range(len(self.g.channels)):
            if len(self.cvblocks[c]) == 0:
                continue
            use = np.ones(len(self.cvblocks[c]), dtype=bool) if active is None else active[c]
            if not np.any(use):
                continue
            d = (np.nan_to_num(without.heldout_rows[c]) ** 2 - np.nan_to_num(with_.heldout_rows[c]) ** 2) \
                / self.sigma[c] ** 2
            per += np.bincount(self.cvblocks[c][use], weights=d[use], minlength=nb)
            have |= np.bincount(self.cvblocks[c][use], minlength=nb) > 0
        return per, have

    def heldout_z(self, with_: ModelScore, without: ModelScore) -> tuple[float, int]:
        """The held-out gain of ``with_`` over ``without`` (exact scores) against the noise it
        would have without any effect, as a normal z; and the number of time blocks that hold rows.

        Per time block j, the gain is G_j = sum(r_without^2 - r_with^2) / sigma^2 over its held-out
        rows; with d = r_without - r_with (what the other folds' fit predicts there) that is
        sum(2 d r_with + d^2). Under no effect, r is noise independent of d (held out), so the gain
        has mean -sum(d^2) and variance 4 Var(sum d r): the noise's projection on the prediction,
        S_j = sum(d r_with) / sigma^2 per block, whose variance is taken from the blocks themselves
        (cluster-robust, adjacent blocks' cross terms at half weight as in ``_cov``: a Newey-West
        estimate that holds for the coloured noise within a block and any noise model's misfit).
        z = sum(G) / (2 sqrt(V)). Unlike the paired t of the block gains, it does not count the
        spread of a real effect's gain between blocks as noise: an effect that shows only where the
        vehicle manoeuvres (a scale, a lever arm, a rotation gain) gains a lot in a few blocks and
        nothing elsewhere, which is evidence, not inconsistency. The evidence must not hinge on one
        block either (a transient the model leaves out, fitted once): the z is the smaller of the
        one over every block and the one without the block that gains most."""
        assert with_.heldout_rows is not None and without.heldout_rows is not None
        nb = int(max((int(b.max()) for b in self.cvblocks if len(b)), default=0)) + 1
        gain = np.zeros(nb)
        proj = np.zeros(nb)
        have = np.zeros(nb, dtype=bool)
        for c in range(len(self.g.channels)):
            blk = self.cvblocks[c]
            if len(blk) == 0:
                continue
            r1 = np.nan_to_num(with_.heldout_rows[c])
            d = np.nan_to_num(without.heldout_rows[c]) - r1
            s2 = self.sigma[c] ** 2
            gain += np.bincount(blk, weights=(2.0 * d * r1 + d * d) / s2, minlength=nb)
            proj += np.bincount(blk, weights=d * r1 / s2, minlength=nb)
            have |= np.bincount(blk, minlength=nb) > 0
        n = int(np.count_nonzero(have))

        def z_of(keep: np.ndarray) -> float:
            g, sp = gain[keep], proj[keep]
            v = float(block_meat(sp))
            total = float(np.sum(g))
            if v <= 0.0:
                return math.inf if total > 0 else (-math.inf if total < 0 else 0.0)
            return total / (2.0 * math.sqrt(v))

        if n == 0:
            return 0.0, 0
        z = z_of(have)
        if n > 1:
            top = int(np.flatnonzero(have)[np.argmax(gain[have])])
            keep = have.copy()
            keep[top] = False
            z = min(z, z_of(keep))
        return z, n

    def rivals(self, chosen: Sequence[str], final: ModelScore, effect: str,
               alternatives: Sequence[str]) -> list[tuple[str, ModelScore, float]]:
        """The effects among ``alternatives`` that explain this flight as well as ``effect`` does.

        An alternative is one whose swap (the chosen model with ``effect`` replaced by it, refitted
        exactly) predicts held-out data better than the model without either, and that the flight
        does not tell from ``effect``: either the swap predicts held-out data no worse than
        ``final`` (``heldout_z`` below ``cv_t_min``), or, with both fitted, ``effect`` adds no
        evidence of its own over the alternative by the test that names an effect at all (its Wald
        z below ``z_min`` or its held-out gain below ``cv_t_min``: the nested comparison, which
        the paired swap can pass by chance where the two share most of what they explain). Each as
        (effect, its score, t), t > 0 when ``effect`` predicts better than the swap. A flight that
        does not separate two effects (a flow scale and a rotation gain when the translation is
        too weak to show) must say so, not name one of them as if it knew."""
        names = {c.effect for c in self.g.candidates}
        rest = [x for x in chosen if x != effect]
        out: list[tuple[str, ModelScore, float]] = []
        alts = [a for a in alternatives if a in names and a not in chosen]
        if not alts or self._out_of_time():
            return out
        without = self.score_exact(rest, final.p)
        for a in alts:
            alt = self.score_exact([*rest, a], final.p)
            if not alt.cv_sse < without.cv_sse:
                continue
            t, n = self.heldout_z(final, alt)
            if n < 2:
                continue
            if t < self.s.cv_t_min or not self._separates(rest, effect, a, final, alt):
                out.append((a, alt, t))
        if any(i in final.free for i in self.widx):  # the refits searched the window again: back to final's
            self._search(final.p, None)
        return out

    def _separates(self, rest: list[str], effect: str, alt_effect: str, final: ModelScore,
                   alt: ModelScore) -> bool:
        """Whether ``effect`` shows on its own with ``alt_effect`` fitted too: the model with
        both against the alternative's (``alt``), by ``compare``'s Wald z and held-out gain."""
        both = self.score_exact([*rest, effect, alt_effect], final.p)
        comp = self.compare(both, alt, effect)
        return comp.z >= self.s.z_min and comp.cv_t >= self.s.cv_t_min

    def _null_p(self, p_with: np.ndarray, p_without: np.ndarray) -> float:
        assert self.g.null_pvalue is not None
        key = (tuple(np.round(p_with, 12)), tuple(np.round(p_without, 12)))
        if key not in self._null_cache:
            self._null_cache[key] = float(self.g.null_pvalue(p_with, p_without))
        return self._null_cache[key]

    def _active_rms(self, with_: ModelScore, without: ModelScore) -> tuple[np.ndarray, np.ndarray]:
        """Per channel, the RMS of the residual without and with a searched effect on the rows
        where it acts (NaN for a channel it does not act on): held out when both scores are exact,
        on all-data fits otherwise (the calibrated null guards those against overfitting)."""
        C = len(self.g.channels)
        nan = np.full(C, np.nan)
        rows = self.g.active_rows() if self.g.active_rows is not None else None
        if rows is None:
            return nan, nan.copy()
        if with_.heldout_rows is not None and without.heldout_rows is not None:
            rw, r0 = with_.heldout_rows, without.heldout_rows
        else:
            rw, r0 = self.residuals(with_.p), self.residuals(without.p)
        b, a = nan.copy(), nan.copy()
        for c in range(C):
            m = rows[c]
            if m is None or not np.any(m):
                continue
            x0 = np.nan_to_num(r0[c][m])
            x1 = np.nan_to_num(rw[c][m])
            b[c] = math.sqrt(float(np.mean(x0 * x0)))
            a[c] = math.sqrt(float(np.mean(x1 * x1)))
        return b, a

    # -- selection -------------------------------------------------------------------------------

    def _out_of_time(self) -> bool:
        if time.monotonic() <= self._deadline:
            return False
        if not self._timed_out:
            self._timed_out = True
            self.notes.append(f"{self.g.name}: selection stopped at its time budget of {self.s.time_budget_s:g} s; "
                              f"effects not yet tried in combination may be missing")
        return True

    def select_linear(self, banned: Sequence[str] = ()) -> list[str]:
        """Forward selection with a backward check, on the linearisation (see module docstring).
        Each step tries every single effect and every pair (two effects can be needed together:
        a flow scale and a rangefinder offset that cancel at one height); a pair is taken only
        when it beats the best single effect on held-out data and by the information criterion.

        It always ends: a set of effects once left is never entered again (forward steps that
        would lead back to one are refused, so add A / drop B / add B / drop A cannot cycle), at
        most ``max_steps`` steps are taken, and the time budget is respected."""
        names = [c.effect for c in self.g.candidates if c.effect not in banned]
        chosen: list[str] = []
        visited: set[frozenset[str]] = {frozenset()}
        for _step in range(self.s.max_steps):
            if self._out_of_time():
                break
            base = self.score_linear(chosen)
            rest = [e for e in names if e not in chosen]
            best: Comparison | None = None
            for e in rest:
                if frozenset([*chosen, e]) in visited:
                    continue
                comp = self.compare(self.score_linear([*chosen, e], self._judged(e)), base, e, screen=True)
                if comp.significant and (best is None or comp.with_.cv_sse < best.with_.cv_sse):
                    best = comp
            best_pair: Comparison | None = None
            for i, e1 in enumerate(rest):
                for e2 in rest[i + 1:]:
                    if frozenset([*chosen, e1, e2]) in visited:
                        continue
                    with_ = self.score_linear([*chosen, e1, e2], self._judged(e1, e2))
                    comp = self.compare(with_, base, [e1, e2], screen=True)
                    if not comp.significant:
                        continue
                    if best is not None:  # the pair must earn its extra parameters over the best single
                        vs = self.compare(with_, best.with_, [x for x in (e1, e2) if x not in best.with_.effects],
                                          screen=True)
                        if not ((vs.cv_t >= self.s.cv_t_screen or vs.null_p <= self.s.null_p_max) and vs.dbic < 0):
                            continue
                    if best_pair is None or comp.with_.cv_sse < best_pair.with_.cv_sse:
                        best_pair = comp
            step = best_pair or best
            if step is None:
                break
            chosen.extend(e for e in step.effect.split("+") if e not in chosen)
            visited.add(frozenset(chosen))
            while len(chosen) > 1:  # backward check: every chosen effect must still earn its place
                weak = [e for e in chosen
                        if frozenset(x for x in chosen if x != e) not in visited
                        and not self.compare(self.score_linear(chosen, self._judged(e)),
                                             self.score_linear([x for x in chosen if x != e]), e,
                                             screen=True).significant]
                if not weak:
                    break
                chosen.remove(weak[0])
                visited.add(frozenset(chosen))
        else:
            self.notes.append(f"{self.g.name}: selection stopped after {self.s.max_steps} steps")
        return chosen

    def _judged(self, *effects: str) -> bool:
        """Whether a comparison judges the searched effect (its part is then searched per fold)."""
        return self.g.searched_effect is not None and self.g.searched_effect in effects

    def select(self) -> tuple[list[str], ModelScore, dict[str, Comparison]]:
        """The selection (``select_from``) started from the linearisation at the largest model's
        fit and, with ``two_starts``, again from the nominal model; the choice whose exact model has
        the lower held-out error is kept (on a tie, the one with fewer effects). The largest model
        can sit far along directions where candidates trade off (a scale, a gain and an offset;
        linear and form drag), and the linearisation there can favour the wrong one of them."""
        first = self.select_from(self.p_full)
        ends = [float(t.max() - t.min()) for t in self.g.row_times if len(t)]
        long = max(ends, default=0.0) > self.s.two_starts_max_s  # long flights pin the fit down anyway
        if not self.s.two_starts or long or self._out_of_time():
            return first
        second = self.select_from(self.g.nominal)
        a, b = first[1], second[1]
        if (b.cv_sse, len(b.free)) < (a.cv_sse, len(a.free)):
            return second
        if self.widx:
            self._search(a.p, None)
        return first

    def select_from(self, p_start: np.ndarray) -> tuple[list[str], ModelScore, dict[str, Comparison]]:
        """Linearised selection (from the linearisation at ``p_start``) confirmed by exact refits:
        an effect whose exact drop-one comparison fails is banned and the selection rerun (at most
        once per candidate, so this ends too). Returns the chosen effects, the exact score of the
        chosen model, and the evidence for every candidate (exact for the chosen ones and for those
        the exact refit turned down, linearised add-one for the others)."""
        self._relinearise(p_start)
        banned: dict[str, Comparison] = {}
        evidence: dict[str, Comparison] = {}
        for _round in range(len(self.g.candidates) + 1):
            chosen = self.select_linear(list(banned))
            final = self.score_exact(chosen)
            # linearise again where the chosen model is (the largest model may sit far away along
            # directions the data hardly constrain), and choose again from there
            if not self._out_of_time():
                self._relinearise(final.p)
                again = self.select_linear(list(banned))
                if set(again) != set(chosen):
                    chosen = again
                    final = self.score_exact(chosen)
            evidence = {}
            failing = []
            for e in chosen:
                with_ = self.score_exact(chosen, final.p, relocate=True) if self._judged(e) else final
                comp = self.compare(with_, self.score_exact([x for x in chosen if x != e], final.p), e)
                evidence[e] = comp
                if not comp.significant:
                    failing.append(comp)
            if not failing:
                break
            worst = min(failing, key=lambda c: min(c.z, c.cv_t))
            worst.reasons.append("not confirmed by the exact refit")
            banned[worst.effect] = worst
        base = self.score_linear(chosen)
        for c in self.g.candidates:
            if c.effect in banned:
                evidence[c.effect] = banned[c.effect]
            elif c.effect not in chosen:
                evidence[c.effect] = self.compare(self.score_linear([*chosen, c.effect], self._judged(c.effect)),
                                                  base, c.effect)
        return chosen, final, evidence

    # -- exact refits ----------------------------------------------------------------------------

    def score_exact(self, effects: Sequence[str], start: np.ndarray | None = None,
                    relocate: bool = False) -> ModelScore:
        """The model refitted on the exact residual, on all data and on each fold's training set
        (chord iterations), with exact held-out residuals. With ``relocate`` a searched part is
        searched again on each fold's training rows."""
        free = self._free(effects)
        p0 = self.p_lin.copy() if start is None else start.copy()
        fixed = [i for i in range(self.P) if i not in free]
        p0[fixed] = self.g.nominal[fixed]
        it = self.s.chord_iterations
        searched = bool(self.widx) and any(i in free for i in self.widx)
        if searched:
            self._search(p0, None)
        p = self._gauss_newton(p0, free, None, iterations=it + 1)
        if searched:
            self._search(p, None)
            p = self._gauss_newton(p, free, None, iterations=it)
        full_sse = self.weighted_sse(p)
        jac = None
        if self.Z is None and free and not searched and not self._describes(p, free):
            p, full_sse, jac = self._refit_off_linearisation(p, full_sse, p0, free)
        state_full = self.g.state() if (searched and self.g.state) else {}
        K = self.K
        p_folds = np.zeros((K, self.P))
        fold_sse = np.zeros(K)
        ho = np.zeros(len(self.g.channels))
        fold_states = []
        rows = [np.zeros(len(t)) for t in self.g.row_times]
        for k in range(K):
            train = [f != k for f in self.folds]
            if searched and relocate:
                self._search(p, train)
                if self.g.state:
                    fold_states.append(self.g.state())
            pk = self._gauss_newton(p, free, train, iterations=max(1, it - 1), jac=jac) if free else p
            p_folds[k] = pk
            for c, r in enumerate(self.weighted(pk)):
                held = self.folds[c] == k
                rk = r[held]
                rows[c][held] = rk * self.sigma[c]
                sk = float(rk @ rk)
                fold_sse[k] += sk
                ho[c] += sk * self.sigma[c] ** 2
        if searched:
            self._search(p, None)
        elif self.widx:
            self._search(self.p_lin, None)
        cov = self._cov(free, p, p_folds, full_sse, jac=jac)
        return ModelScore(tuple(effects), free, p, p_folds, cov, fold_sse, ho,
                          full_sse, self.n_rows, state_full, fold_states, heldout_rows=rows)

    def _describes(self, p: np.ndarray, free: list[int]) -> bool:
        """Whether the stored linearisation describes the exact fit ``p`` of the free parameters:
        the gradient it extrapolates to p (nil at a least-squares fit when the residual is linear
        between the linearisation point and p) is within one standard error of nil, g' (J'J)^-1 g
        at most 1."""
        d = p - self.p_lin
        g = (self.gvb[:, free] + self.Gb[:, free, :] @ d).sum(axis=0)
        _fixed, ff, _fx = self._blocks(free)
        return float(g @ np.linalg.pinv(self.Gb.sum(axis=0)[ff]) @ g) <= 1.0

    def _refit_off_linearisation(self, p: np.ndarray, sse: float, p0: np.ndarray, free: list[int]
                                 ) -> tuple[np.ndarray, float, list[np.ndarray]]:
        """``score_exact``'s least-squares fit where the stored linearisation does not describe it
        (``_describes``), and the Jacobian of the free parameters at the fit, which the folds' fits
        and the covariance then take (``_gauss_newton``'s and ``_cov``'s ``jac``).

        The chord iterations steer with the Jacobian of the linearisation, made at the largest
        model's fit; for a parameter the residual is far from linear in (a loop's natural
        frequency, a delay of several frames) and a linearisation far from its value they can run
        away to the parameter's bound (gen_0105 of the matrix: a loop of 4.0 rad/s for a nominal
        5.8 fitted at the bound, its held-out residual three times the model's without it), and
        the block scores and the folds' fits extrapolated from there gave a fit at 4.0 a sigma of
        7.6 rad/s. So: when the chord iterations left the fit worse than where they started (``p0``,
        or ``p0`` with the free parameters at the nominal: the model without the effects),
        Levenberg-Marquardt from the better of those, which only takes steps that lower the SSE;
        then Gauss-Newton steps with the Jacobian at the fit, made afresh, each kept only if it
        lowers the SSE. Not for the instrumental-variable fit, which is not a least-squares
        minimum, nor for a searched part, which moves with every evaluation."""
        q = p0.copy()
        q[free] = self.g.nominal[free]
        best_sse, best = sse, p
        for st in (p0, q):
            s0 = self.weighted_sse(st)
            if s0 < best_sse * (1.0 - 1e-9):
                best_sse, best = s0, st
        if best is not p:
            p = self._levenberg(best.copy(), free)
        sse = self.weighted_sse(p)
        jac = self.jacobian(p, free)
        for _ in range(2):  # Gauss-Newton steps with the Jacobian at the fit, kept while they lower the SSE
            q = self._gauss_newton(p, free, None, iterations=1, jac=jac)
            sq = self.weighted_sse(q)
            if not sq < sse:
                break
            p, sse = q, sq
            jac = self.jacobian(p, free)
        return p, sse, jac


def _solve_stack(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``_solve`` of A[i] x = b[i] for a stack of systems (A (m, k, k), b (m, k)): the same numbers,
    each of numpy's batched LAPACK calls being its single one, in one condition number's and one
    solve's call for all (a selection solves thousands of small systems, the folds' of each score
    together, and numpy's wrappers took longer than the solves)."""
    try:
        good = np.linalg.cond(A) < 1e12
    except np.linalg.LinAlgError:  # one by one, as ``_solve`` takes them
        return np.array([_solve(a, v) for a, v in zip(A, b, strict=True)]).reshape(b.shape)
    out = np.empty_like(b, dtype=float)
    if np.any(good):
        try:
            out[good] = np.linalg.solve(A[good], b[good][..., None])[..., 0]
        except np.linalg.LinAlgError:
            return np.array([_solve(a, v) for a, v in zip(A, b, strict=True)]).reshape(b.shape)
    for i in np.flatnonzero(~good):
        out[i] = np.linalg.lstsq(A[i], b[i], rcond=None)[0]
    return out


def _solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares solve of A x = b robust to (near-)singular A."""
    try:
        if np.linalg.cond(A) < 1e12:
            return np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        pass
    return np.linalg.lstsq(A, b, rcond=None)[0]
