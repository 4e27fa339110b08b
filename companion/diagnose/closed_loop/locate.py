"""Where and under what conditions a residual departs from the noise: sliding windows and bins.

``excess_windows`` marks sliding windows whose residual RMS is above a multiple of the channel's
noise (its robust scale, or what the residual's own row-to-row changes give over the flight and
in the window: ``white_part``) and merges them into intervals; ``effect_windows`` does the same
for the part of the residual an effect explains (its contribution). ``conditions`` bins a
residual by operating condition (speed, tilt, rate, altitude) so a report can say *when* the
model fails.
"""

from __future__ import annotations

from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from companion.diagnose.closed_loop.select import robust_std


@dataclass(frozen=True)
class Interval:
    start_s: float
    end_s: float
    rms: float
    #: the noise its rms was judged against (of its window that stands highest above its noise)
    noise: float = 0.0


def _sliding_ms(t: np.ndarray, x: np.ndarray, starts: np.ndarray, width_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean square of ``x`` (rows sorted by ``t``) over [start, start + width) per start, and the
    row count (mean square 0 where there is no row)."""
    x2 = np.concatenate([[0.0], np.cumsum(np.nan_to_num(x) ** 2)])
    i0 = np.searchsorted(t, starts, side="left")
    i1 = np.searchsorted(t, starts + width_s, side="left")
    n = i1 - i0
    return (x2[i1] - x2[i0]) / np.maximum(n, 1), n


def window_rms(t_s: np.ndarray, r: np.ndarray, width_s: float, step_s: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """RMS of ``r`` over sliding windows of ``width_s`` every ``step_s`` (rows sorted by time or
    not). Returns (start_s, end_s, rms, count) per window; windows with no rows are dropped."""
    if len(t_s) == 0:
        z = np.zeros(0)
        return z, z, z, z
    order = np.argsort(t_s, kind="stable")
    t = t_s[order]
    starts = np.arange(t[0], max(t[-1] - width_s, t[0]) + step_s / 2, step_s)
    ms, n = _sliding_ms(t, r[order], starts, width_s)
    ok = n > 0
    return starts[ok], np.minimum(starts[ok] + width_s, t[-1]), np.sqrt(ms[ok]), n[ok].astype(float)


#: ``white_part`` differences rows this many apart: a residual that is a difference of its rows'
#: noise (a rate from two attitudes, a flow count carried into the next frame) is negatively
#: correlated from one row to the next, and two rows apart its differences give its variance
#: exactly (white noise: any lag does)
WHITE_LAG_ROWS = 2


def white_part(t_s: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The part of a residual that changes from row to row: (r[i + 2] - r[i]) / sqrt(2), at the
    two rows' mean time, for rows two apart with no gap between them (at most 2.5 x the median
    row interval). Its mean square is the variance of a white noise of any distribution (sparse
    count errors, a rate's kinks between samples, as well as Gaussian noise), while a misfit
    that is smooth over a few rows (a scale error, a delay, a force) stays out of it; a residual
    whose rows are not sorted is sorted first."""
    order = np.argsort(t_s, kind="stable")
    t, x = t_s[order], r[order]
    k = WHITE_LAG_ROWS
    if len(t) <= k + 1:
        return np.zeros(0), np.zeros(0)
    span = t[k:] - t[:-k]
    d = (x[k:] - x[:-k]) / np.sqrt(2.0)
    ok = (span <= (k + 0.5) * float(np.median(np.diff(t)))) & np.isfinite(d)
    return 0.5 * (t[k:] + t[:-k])[ok], d[ok]


def white_noise(t_s: np.ndarray, r: np.ndarray) -> float:
    """The rms of ``white_part`` over the whole residual (0 when it has too few rows)."""
    return _rms(white_part(t_s, r)[1])


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else 0.0


def merge(starts: np.ndarray, ends: np.ndarray, rms: np.ndarray, flag: np.ndarray, gap_s: float,
          noise: np.ndarray | None = None) -> list[Interval]:
    """Merge flagged windows that overlap or lie within ``gap_s`` of each other. An interval keeps
    the rms (and ``noise``, per window) of its window that stands highest above its noise; without
    ``noise``, the largest rms."""
    out: list[Interval] = []
    nz = np.zeros(len(rms)) if noise is None else noise

    def above(v: float, n: float) -> float:
        return v / n if n > 0 else v

    for s, e, v, n in zip(starts[flag], ends[flag], rms[flag], nz[flag], strict=True):
        if out and s <= out[-1].end_s + gap_s:
            last = out[-1]
            v_, n_ = (float(v), float(n)) if above(v, n) > above(last.rms, last.noise) else (last.rms, last.noise)
            out[-1] = Interval(last.start_s, max(last.end_s, float(e)), v_, n_)
        else:
            out.append(Interval(float(s), float(e), float(v), float(n)))
    return out


def typical_window_rms(t_s: np.ndarray, r: np.ndarray, width_s: float = 5.0, step_s: float = 2.5,
                       min_rows: int = 10) -> float:
    """The median over the flight of the residual's sliding-window rms (windows of ``min_rows``
    rows or more; 0 when there is none): what a window of a noise correlated over a good part of
    the window typically reads, where a robust scale or the white part reads far less. A misfit in
    fewer than half the windows leaves it at the noise."""
    _s, _e, v, n = window_rms(t_s, r, width_s, step_s)
    v = v[n >= min_rows]
    return float(np.median(v)) if len(v) else 0.0


#: a window whose residual stands this many times its noise is listed (``excess_windows``)
STRETCH_TIMES_NOISE = 2.0

#: the chance (per channel and flight) that a coloured noise's highest window stands above
#: ``coloured_factor``'s threshold (``excess_windows`` lists it as a local disturbance)
COLOURED_ALPHA = 0.01


def coloured_factor(t_s: np.ndarray, r: np.ndarray, width_s: float = 5.0, step_s: float = 2.5,
                    min_rows: int = 10, alpha: float = COLOURED_ALPHA) -> float:
    """How far above its typical window (``typical_window_rms``) a window of ``r``, a noise
    correlated over a good part of the window (an estimator's attitude), stands by chance only
    with probability ``alpha`` over the flight's M windows: exp(z x s), with s the spread of the
    windows' log rms (1.4826 x its median absolute deviation, robust to the few windows a misfit
    holds) and z the normal quantile at 1 - alpha / M. A window of such a noise holds a few
    independent values only (0.9 s correlation: four in 7.5 s), and its rms scatters by a third;
    the highest of 80 such windows over a 200 s flight stood 2.0-2.7 x the typical one on four
    clean flights of the generalisation matrix, listed as local disturbances; simulated (Gauss-
    Markov, tau 0.9 s, 200 s), 23 % of flights had one over 2 x. 1 where fewer than three
    windows hold ``min_rows``."""
    _s, _e, v, n = window_rms(t_s, r, width_s, step_s)
    v = v[(n >= min_rows) & (v > 0)]
    if len(v) < 3:
        return 1.0
    return float(np.exp(NormalDist().inv_cdf(1.0 - alpha / len(v)) * robust_std(np.log(v))))


def excess_windows(t_s: np.ndarray, r: np.ndarray, sigma: float, *, factor: float = STRETCH_TIMES_NOISE,
                   width_s: float = 5.0, step_s: float = 2.5, min_rows: int = 10) -> list[Interval]:
    """Intervals where the residual's sliding-window RMS exceeds ``factor`` x its noise there: the
    largest of ``sigma`` (the channel's robust scale), the rms of the residual's ``white_part``
    over the whole residual, and the same in the window (with ``min_rows`` of it).

    Why the white part: a robust scale (the MAD) is the rms of Gaussian noise only. Noise with
    heavy tails has an rms several times its MAD, and its every window stood above it: on noise-
    free generator flights a rate that kinks between the gyro's samples (gen_0098, 0017, 0061,
    0259) and flow count errors on 2-4 % of frames (gen_0098, 0260, 0276) made 14 of the matrix's
    53 clean flights say "the model does not fit ... 3-15 x its noise". Against the noise taken
    this way their gyro windows stand at most 1.9 x, their flow windows 1.5 x, while a 5 % gyro
    scale error put on three of them stands 2.1-3.7 x (a 2 % one 1.5-2.3 x: what a misfit changes
    from row to row is counted as noise, so a small misfit hidden in the noise is not said). In the
    window too, because the noise of a rate's reconstruction grows with the manoeuvre."""
    s, e, v, n = window_rms(t_s, r, width_s, step_s)
    td, d = white_part(t_s, r)
    noise = np.full(len(v), max(float(sigma), _rms(d)))
    if len(d):
        dms, dn = _sliding_ms(td, d, s, width_s)
        noise = np.where(dn >= min_rows, np.maximum(noise, np.sqrt(dms)), noise)
    return merge(s, e, v, (v > factor * noise) & (n >= min_rows), gap_s=step_s, noise=noise)


def effect_windows(t_s: np.ndarray, contribution: np.ndarray, sigma: float, *, width_s: float = 5.0,
                   step_s: float = 2.5, max_intervals: int = 8) -> list[Interval]:
    """Where an effect's contribution to a residual is larger than the noise (``sigma``); when it
    never is, the single window where it is largest. At most ``max_intervals``, the largest."""
    s, e, v, _n = window_rms(t_s, contribution, width_s, step_s)
    if len(v) == 0:
        return []
    flag = v > sigma
    if not np.any(flag):
        flag = v == v.max()
    out = merge(s, e, v, flag, gap_s=width_s)
    if len(out) > max_intervals:
        out = sorted(sorted(out, key=lambda i: -i.rms)[:max_intervals], key=lambda i: i.start_s)
    return out


#: operating conditions a residual is binned by: name -> (unit, description)
CONDITIONS = {
    "speed_m_s": ("m/s", "horizontal speed"),
    "tilt_rad": ("rad", "tilt"),
    "rate_rad_s": ("rad/s", "body rate"),
    "altitude_m": ("m", "height"),
}


def conditions(values: dict[str, np.ndarray], contribution: np.ndarray, n_bins: int = 4) -> dict[str, object]:
    """Bin ``contribution`` (rows) by each condition (same rows) in quantile bins; return the
    condition under which it varies most, its bin edges and RMS per bin."""
    best: dict[str, object] = {}
    best_ratio = 0.0
    for name, x in values.items():
        ok = np.isfinite(x) & np.isfinite(contribution)
        if np.count_nonzero(ok) < 4 * n_bins:
            continue
        edges = np.unique(np.quantile(x[ok], np.linspace(0, 1, n_bins + 1)))
        if len(edges) < 3:
            continue
        idx = np.clip(np.searchsorted(edges, x[ok], side="right") - 1, 0, len(edges) - 2)
        rms = np.array([np.sqrt(np.mean(contribution[ok][idx == b] ** 2)) if np.any(idx == b) else 0.0
                        for b in range(len(edges) - 1)])
        lo = max(float(rms.min()), 1e-300)
        ratio = float(rms.max()) / lo
        if ratio > best_ratio:
            best_ratio = ratio
            best = {"condition": name, "unit": CONDITIONS.get(name, ("", ""))[0], "edges": edges.tolist(),
                    "rms": rms.tolist(), "max_over_min": ratio}
    return best
