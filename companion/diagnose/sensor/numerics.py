"""Small numerical pieces the estimators share: moving means, runs of a mask, and the exact
integral of a piecewise-linear signal over a window ending at each query time."""

from __future__ import annotations

import numpy as np


def moving_mean(x: np.ndarray, n: int) -> np.ndarray:
    n = max(1, int(n))
    k = np.ones(n) / n
    return np.convolve(np.pad(x, (n // 2, n - 1 - n // 2), mode="edge"), k, mode="valid")


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index pairs of the True runs of ``mask``."""
    m = np.r_[False, np.asarray(mask, dtype=bool), False]
    d = np.diff(m.astype(np.int8))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True))


def window_integral(t_query: np.ndarray, t_sig: np.ndarray, sig: np.ndarray, delay_s: float,
                    width_s: np.ndarray | float) -> np.ndarray:
    """Integral of the piecewise-linear ``sig(t)`` over ``[t - delay - width, t - delay]`` for each
    query time (trapezoid on the signal's own samples, exact for piecewise-linear signals)."""
    c = np.concatenate([[0.0], np.cumsum(0.5 * (sig[1:] + sig[:-1]) * np.diff(t_sig))])
    hi = t_query - delay_s
    return _cum_at(hi, t_sig, sig, c) - _cum_at(hi - width_s, t_sig, sig, c)


def window_integrals(t_query: np.ndarray, t_sig: np.ndarray, sig: np.ndarray, delays_s: np.ndarray,
                     width_s: float) -> np.ndarray:
    """``window_integral`` for many delays at once: shape (len(delays_s), len(t_query))."""
    c = np.concatenate([[0.0], np.cumsum(0.5 * (sig[1:] + sig[:-1]) * np.diff(t_sig))])
    hi = t_query[None, :] - np.asarray(delays_s, dtype=float)[:, None]
    return _cum_at(hi, t_sig, sig, c) - _cum_at(hi - width_s, t_sig, sig, c)


def _cum_at(tq: np.ndarray, t: np.ndarray, s: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The cumulative integral of the piecewise-linear signal at ``tq`` (held flat outside)."""
    tq = np.clip(tq, t[0], t[-1])
    i = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)
    h = tq - t[i]
    dt = t[i + 1] - t[i]
    slope = np.where(dt > 0, (s[i + 1] - s[i]) / np.where(dt > 0, dt, 1.0), 0.0)
    return c[i] + s[i] * h + 0.5 * slope * h**2
