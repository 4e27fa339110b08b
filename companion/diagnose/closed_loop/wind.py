"""Locating an external force over a time window: a two-change-point search on the force residual.

With drag and the sensor geometry accounted for, the force channel (``flowmodel``) is, window by
window, the mean force the model leaves unexplained: turbulence around zero, plus F over the
windows a wind acts in. The best single window [start, end) is the one whose mean shift explains
most of the residual (least-squares piecewise-constant fit with two change points, both axes
together): an exhaustive search over window boundaries with cumulative sums, then a refinement of
each end at frame resolution with the exact averaging kernel of the channel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion import native
from companion.diagnose.closed_loop.flowmodel import ramp_integral

#: a window shorter than this is turbulence, not wind (s)
MIN_WIND_S = 4.0
#: the coarse search works on at most this many boundaries (longer recordings are pooled)
MAX_COARSE = 800
#: the null calibration's scan works on at most this many pooled windows
MAX_NULL = 160
#: sign-flip blocks of the null calibration (s): longer than the force residual's correlation
NULL_BLOCK_S = 3.0
#: bootstrap replicates of the null calibration
NULL_REPS = 99


@dataclass(frozen=True)
class WindWindow:
    start_s: float
    end_s: float
    fx_n: float
    fy_n: float
    gain: float  # residual sum of squares explained (N^2)
    #: 1-sigma of the ends from the profile of the fit over each end (the other held), s
    start_sd: float = math.nan
    end_sd: float = math.nan


def kernel_regressor(t_s: np.ndarray, k0: np.ndarray, k1: np.ndarray, h: int, start_s: float | np.ndarray,
                     end_s: float | np.ndarray) -> np.ndarray:
    """The fraction of each force window [k0, k1] during which a unit force acts, as the force
    channel averages it (boundary means over +-h frames); shape (n_windows,), or broadcast against
    ``start_s``, ``end_s`` given as columns (G, 1) of candidate windows: (G, n_windows)."""
    # the ends of both boundary means of every window, the ramp's integral at all four at once (a
    # wind's search evaluates this for hundreds of candidate windows)
    ends = np.stack([t_s[k1 + h], t_s[k1 - h], t_s[k0 + h], t_s[k0 - h]])
    columns = np.ndim(start_s) > 0 or np.ndim(end_s) > 0
    ramp = ramp_integral(ends[:, None, :] if columns else ends, start_s, end_s)
    b1 = (ramp[0] - ramp[1]) / (ends[0] - ends[1])
    b0 = (ramp[2] - ramp[3]) / (ends[2] - ends[3])
    return (b1 - b0) / (t_s[k1] - t_s[k0])


def locate(e: np.ndarray, t_s: np.ndarray, k0: np.ndarray, k1: np.ndarray, h: int,
           mask: np.ndarray | None = None, min_s: float = MIN_WIND_S) -> WindWindow | None:
    """Best force window for residual ``e`` (2, n_windows) in N; ``mask`` (n_windows,) selects the
    windows to fit on. Windows must be in time order. None when nothing can be fitted."""
    nw = e.shape[1]
    if nw < 4:
        return None
    w = np.ones(nw) if mask is None else mask.astype(float)
    e = np.where(np.isfinite(e), e, 0.0) * w
    tm0, tm1 = t_s[k0], t_s[k1]
    # coarse: pool neighbouring windows when there are many, then every window at once
    ep, wp, b0, b1, pool = _pool(e, w, tm0, tm1, MAX_COARSE)
    _gain, j1, j2 = _scan(ep, wp, b0, b1, min_s)
    start, end = float(b0[j1]), float(b1[j2 - 1])

    lo_sup = t_s[k0 - h]  # each window's kernel support
    hi_sup = t_s[k1 + h]

    def fit(s: np.ndarray, en: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Explained sum of squares and forces (G, 2) for candidate windows (G,) that differ in
        one end only: the regressor is computed for the windows whose kernel meets the range of
        that end, the rest (0 or 1 for every candidate) summed once."""
        moving = s if np.ptp(s) > 0 else en
        vary = (hi_sup >= moving.min()) & (lo_sup <= moving.max())
        x_ref = kernel_regressor(t_s, k0[~vary], k1[~vary], h, float(s[0]), float(en[0])) * w[~vary]
        ex0 = e[:, ~vary] @ x_ref
        xx0 = float(x_ref @ x_ref)
        x = kernel_regressor(t_s, k0[vary], k1[vary], h, s[:, None], en[:, None]) * w[vary]
        xx = xx0 + np.einsum("gj,gj->g", x, x)
        ex = ex0[None, :] + x @ e[:, vary].T
        f = ex / np.where(xx > 0, xx, 1.0)[:, None]
        return np.where(xx > 0, (ex ** 2).sum(axis=1) / np.where(xx > 0, xx, 1.0), -1.0), f

    # refine each end at twice the frame resolution, twice around
    step = max(2 * float(np.median(np.diff(t_s))), 1e-3)
    span = 1.5 * float(np.median(tm1 - tm0)) * pool

    def around(x: float, dt: float = step) -> np.ndarray:
        """Candidate times for an end now at x: within ``span``, and as far as the start of the
        window before x and the end of the window after it, so that an end next to a gap in the
        windows (a burst of lost telemetry) can move to the far side of the gap, where the
        windows after it show the force still on."""
        before, after = tm0[tm0 < x], tm1[tm1 > x]
        lo = min(x - span, float(before.max()) if len(before) else x)
        hi = max(x + span, float(after.min()) if len(after) else x)
        return x + np.arange(lo - x, hi - x + dt / 2, dt)

    for _ in range(2):
        grid = around(start)
        grid = grid[grid <= end - min_s]
        if len(grid):
            start = float(grid[int(np.argmax(fit(grid, np.full(len(grid), end))[0]))])
        grid = around(end)
        grid = grid[grid >= start + min_s]
        if len(grid):
            end = float(grid[int(np.argmax(fit(np.full(len(grid), start), grid)[0]))])
    if mask is not None and np.any(w > 0):
        # no evidence past the rows fitted on: a force that lasts to the last of them (or from
        # the first) is taken to go on over the rows held out there, not to stop where they begin
        used = w > 0
        if end >= float(tm1[used].max()) - step:
            end = max(end, float(hi_sup[-1]))
        if start <= float(tm0[used].min()) + step:
            start = min(start, float(lo_sup[0]))
    gains, f = fit(np.array([start]), np.array([end]))
    # profile of each end: where the explained sum of squares drops by one noise variance (the
    # residual's, inflated by its lag-one correlation, as turbulence makes neighbouring windows alike)
    x = kernel_regressor(t_s, k0, k1, h, start, end) * w
    r = (e - f[0][:, None] * x)[:, w > 0]
    var = float(np.mean(r ** 2))
    # a residual row that is constant (a vehicle at rest) has no correlation to speak of
    rhos = [np.corrcoef(ri[1:], ri[:-1])[0, 1] for ri in r if r.shape[1] > 3 and np.std(ri[1:]) > 0
            and np.std(ri[:-1]) > 0]
    rho = float(np.mean(rhos)) if rhos else 0.0
    var *= 1.0 + 2.0 * max(rho, 0.0) / max(1.0 - max(rho, 0.0), 0.1)
    fine = max(float(np.median(np.diff(t_s))), 1e-3)

    def sd(grid: np.ndarray, gains_: np.ndarray) -> float:
        ok = grid[gains_ >= gains_.max() - var]
        return max(0.5 * float(ok.max() - ok.min()), fine) if len(ok) else math.nan

    gs = around(start, step / 2)
    gs = gs[gs <= end - min_s]
    ge = around(end, step / 2)
    ge = ge[ge >= start + min_s]
    start_sd = sd(gs, fit(gs, np.full(len(gs), end))[0]) if len(gs) else math.nan
    end_sd = sd(ge, fit(np.full(len(ge), start), ge)[0]) if len(ge) else math.nan
    return WindWindow(start, end, float(f[0, 0]), float(f[0, 1]), float(gains[0]), start_sd, end_sd)


def _pool(e: np.ndarray, w: np.ndarray, tm0: np.ndarray, tm1: np.ndarray, max_m: int
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Neighbouring force windows summed in groups so that at most ``max_m`` remain: the pooled
    residual sums (2, m), weights (m,), start and end times (m,), and the group size."""
    pool = max(1, math.ceil(e.shape[1] / max_m))
    m = e.shape[1] // pool
    return (e[:, : m * pool].reshape(2, m, pool).sum(axis=2), w[: m * pool].reshape(m, pool).sum(axis=1),
            tm0[: m * pool: pool], tm1[pool - 1: m * pool: pool], pool)


def _scan(ep: np.ndarray, wp: np.ndarray, b0: np.ndarray, b1: np.ndarray, min_s: float) -> tuple[float, int, int]:
    """Largest explained sum of squares of one mean shift over pooled windows j1..j2-1 lasting at
    least ``min_s``: (gain, j1, j2). ``ep`` (2, m) pooled residual sums, ``wp`` (m,) weights."""
    gain, flat = _best_windows(_cumulative(ep)[None], wp, b0, b1, min_s)
    a, b = divmod(int(flat[0]), ep.shape[1])
    return float(gain[0]), a, b + 1


class _ScanGrid:
    """What the scan's gain depends on besides the residual: for each pair (j1, j2) whether the
    window is allowed (long enough, with weight) and its pooled weight."""

    def __init__(self, wp: np.ndarray, b0: np.ndarray, b1: np.ndarray, min_s: float) -> None:
        m = len(wp)
        cw = np.concatenate([[0.0], np.cumsum(wp)])
        j1 = np.arange(m)[:, None]
        j2 = np.arange(1, m + 1)[None, :]
        dur = b1[np.minimum(j2, m) - 1] - b0[j1]
        nwt = cw[j2] - cw[j1]
        self.ok = (j2 > j1) & (dur >= min_s) & (nwt > 0)
        self.nwt = np.where(nwt > 0, nwt, 1.0)


def _cumulative(ep: np.ndarray) -> np.ndarray:
    """Cumulative sums from 0 along the last axis: (..., m) -> (..., m + 1)."""
    out = np.zeros(ep.shape[:-1] + (ep.shape[-1] + 1,))
    np.cumsum(ep, axis=-1, out=out[..., 1:])
    return out


def _scan_gains(ce: np.ndarray, grid: _ScanGrid) -> np.ndarray:
    """The explained sum of squares of every allowed window (-1 elsewhere) for the pooled
    residual's cumulative sums ``ce`` (2, m + 1): shape (m, m), [j1, j2 - 1]."""
    num = ((ce[:, None, 1:] - ce[:, :-1, None]) ** 2).sum(axis=0)
    return np.where(grid.ok, num / grid.nwt, -1.0)


def _best_windows(ce: np.ndarray, wp: np.ndarray, b0: np.ndarray, b1: np.ndarray, min_s: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """For R pooled residuals given by their cumulative sums ``ce`` (R, 2, m + 1): each one's
    largest gain over the allowed windows and its flat index in ``_scan_gains``'s array (numpy's
    argmax: the first maximum; -1 at 0 when no window is allowed). The compiled kernel
    ``fh_wind_scan`` when loaded (tests/test_native.py holds the two equal), else ``_scan_gains``
    one residual at a time (its (m, m) arrays stay in the cache)."""
    R, m = ce.shape[0], ce.shape[-1] - 1
    gain = np.empty(R)
    flat = np.zeros(R, dtype=np.int64)
    lib = native.kernels()
    if lib is not None and m > 0:
        ce = np.ascontiguousarray(ce, dtype=float)
        cw = np.ascontiguousarray(_cumulative(np.asarray(wp, dtype=float)))
        b0 = np.ascontiguousarray(b0, dtype=float)
        b1 = np.ascontiguousarray(b1, dtype=float)
        lib.fh_wind_scan(ce.ctypes.data, R, m, cw.ctypes.data, b0.ctypes.data, b1.ctypes.data, float(min_s),
                         gain.ctypes.data, flat.ctypes.data)
        return gain, flat
    grid = _ScanGrid(wp, b0, b1, min_s)
    for r in range(R):
        g = _scan_gains(ce[r], grid)
        flat[r] = int(np.argmax(g)) if g.size else 0
        gain[r] = float(g.flat[flat[r]]) if g.size else -1.0
    return gain, flat


def null_pvalue(e: np.ndarray, t_s: np.ndarray, k0: np.ndarray, k1: np.ndarray, mask: np.ndarray | None = None,
                min_s: float = MIN_WIND_S, reps: int = NULL_REPS, seed: int = 0) -> float:
    """Tail probability of the window search's statistic (the largest sum of squares one force
    window explains) under the null of no force, calibrated on the recording itself.

    ``e`` (2, n_windows) is the force residual without the force. The null is zero-mean noise with
    the residual's own long-run variance per axis (the residual with the best window's shift
    removed; a Newey-West estimate over ``NULL_BLOCK_S`` and at least three of its correlation
    times, so slow turbulence, a force that lasts seconds, counts at its full weight), and the same
    search runs on each replicate: a penalised likelihood-ratio test whose penalty, the scan over
    every window, is measured rather than assumed."""
    nw = e.shape[1]
    if nw < 4:
        return 1.0
    w = np.ones(nw) if mask is None else mask.astype(float)
    e = np.where(np.isfinite(e), e, 0.0) * w
    tm0, tm1 = t_s[k0], t_s[k1]
    ep, wp, b0, b1, _pool_n = _pool(e, w, tm0, tm1, MAX_NULL)
    if ep.shape[1] < 4:
        return 1.0
    observed, j1, j2 = _scan(ep, wp, b0, b1, min_s)
    if observed <= 0:
        return 1.0
    # the null residual per unit weight: the best window's shift removed
    use = wp > 0
    x = np.zeros_like(ep)
    x[:, use] = ep[:, use] / wp[use]
    shift = ep[:, j1:j2].sum(axis=1) / max(float(wp[j1:j2].sum()), 1e-12)
    x[:, j1:j2] -= shift[:, None]
    x = x[:, use]
    span = float(np.median(b1 - b0))
    lag_s = NULL_BLOCK_S
    rho = float(np.mean([np.corrcoef(xi[1:], xi[:-1])[0, 1] for xi in x
                         if np.std(xi[1:]) > 0 and np.std(xi[:-1]) > 0] or [0.0]))
    if 0.0 < rho < 1.0:
        lag_s = max(lag_s, -3.0 * span / math.log(rho))
    L = min(max(1, int(round(lag_s / max(span, 1e-6)))), x.shape[1] - 1)
    lr_var = np.zeros(2)
    for i in range(2):
        xi = x[i] - x[i].mean()
        n = len(xi)
        v = float(xi @ xi) / n
        for k in range(1, L + 1):
            v += 2.0 * (1.0 - k / (L + 1)) * float(xi[k:] @ xi[:-k]) / n
        lr_var[i] = max(v, float(xi @ xi) / n, 1e-300)
    rng = np.random.default_rng(seed)
    sd = np.sqrt(lr_var)[:, None] * np.sqrt(wp)[None, :]  # a pooled sum of wp windows
    null, _flat = _best_windows(_cumulative(rng.standard_normal((reps,) + ep.shape) * sd), wp, b0, b1, min_s)
    exceed = int(np.count_nonzero(null >= observed))
    return (1 + exceed) / (reps + 1)
