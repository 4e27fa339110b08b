"""Sparse regression (SINDy-style) of what the chosen model still leaves in a residual.

For a residual y (one channel, after the chosen effects) and a library of candidate terms built
from the recorded signals (``Term``: e.g. velocity, velocity |velocity|, angular acceleration,
the other axis' rotation), sequentially thresholded least squares (STLSQ, Brunton et al. 2016)
picks a few terms on standardised columns; the threshold is chosen by the same blocked
cross-validation as the effects. What it finds is reported as an *unexplained* mismatch with its
best-fitting term in words, never forced into a named effect.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

THRESHOLDS = (0.02, 0.05, 0.1, 0.2, 0.35)


@dataclass(frozen=True)
class Term:
    """A candidate term: ``values`` per residual row; ``words`` what it stands for physically;
    ``unit`` its unit."""

    name: str
    words: str
    unit: str
    values: np.ndarray


@dataclass
class SparseFit:
    """The thresholded regression of a residual on a term library."""

    terms: list[Term]
    coef: np.ndarray  # per term, residual units per term unit (0 = dropped)
    r2_heldout: float  # fraction of the residual's sum of squares predicted on held-out folds
    threshold: float
    best: Term | None
    best_coef: float
    best_r2_heldout: float  # the best term alone, held out

    def predict(self, n_rows: int) -> np.ndarray:
        """The sparse model's part of the residual, per row of the residual it was fitted to (a
        term's non-finite rows count 0; all 0 without terms)."""
        out = np.zeros(n_rows)
        for k, t in zip(self.coef, self.terms, strict=True):
            if k:
                out += k * np.nan_to_num(t.values)
        return out

    def describe(self, residual_unit: str) -> str | None:
        if self.best is None:
            return None
        return (f"{self.best_coef:+.3g} {residual_unit} per {self.best.unit} of {self.best.name} "
                f"({self.best.words}; alone it predicts {100 * self.best_r2_heldout:.0f} % of the held-out "
                f"residual, the sparse model {100 * self.r2_heldout:.0f} %)")


def stlsq(X: np.ndarray, y: np.ndarray, threshold: float, ridge: float = 1e-6, iterations: int = 10) -> np.ndarray:
    """Sequentially thresholded least squares on standardised X (columns of unit RMS)."""
    return stlsq_gram(X.T @ X, X.T @ y, len(y), threshold, ridge, iterations)


def stlsq_gram(G: np.ndarray, b: np.ndarray, n: int, threshold: float, ridge: float = 1e-6,
               iterations: int = 10) -> np.ndarray:
    """STLSQ from the normal equations (G = X'X, b = X'y over n rows): linear-time in the data
    once G and b are summed, so cross-validation over thresholds and folds costs nothing more."""
    p = len(b)
    active = np.ones(p, dtype=bool)
    coef = np.zeros(p)
    for _ in range(iterations):
        if not np.any(active):
            break
        idx = np.flatnonzero(active)
        A = G[np.ix_(idx, idx)] + ridge * n * np.eye(len(idx))
        coef = np.zeros(p)
        coef[idx] = np.linalg.solve(A, b[idx])
        small = np.abs(coef) < threshold
        if not np.any(small & active):
            break
        active &= ~small
    return coef


def sparse_fit(y: np.ndarray, terms: list[Term], folds: np.ndarray, K: int) -> SparseFit:
    """STLSQ of ``y`` on ``terms`` with the threshold chosen by held-out error over ``folds``."""
    ok = np.isfinite(y)
    if not np.any(ok):  # a channel with no finite row (nothing to explain): no term, no warning
        return SparseFit([], np.zeros(0), 0.0, 0.0, None, 0.0, 0.0)
    cols = [t for t in terms if np.all(np.isfinite(t.values[ok])) and np.std(t.values[ok]) > 0]
    ys = np.sqrt(np.mean(y[ok] ** 2)) if np.any(ok) else 0.0
    if not cols or ys <= 0:
        return SparseFit(cols, np.zeros(len(cols)), 0.0, 0.0, None, 0.0, 0.0)
    scale = np.array([np.sqrt(np.mean(t.values[ok] ** 2)) for t in cols])
    X = np.stack([t.values[ok] for t in cols], axis=1) / scale
    yy = y[ok] / ys
    f = folds[ok]
    Gk = np.stack([X[f == k].T @ X[f == k] for k in range(K)])
    bk = np.stack([X[f == k].T @ yy[f == k] for k in range(K)])
    ssk = np.array([float(yy[f == k] @ yy[f == k]) for k in range(K)])
    nk = np.array([np.count_nonzero(f == k) for k in range(K)])
    G, b, n = Gk.sum(axis=0), bk.sum(axis=0), int(nk.sum())
    # the folds that can be held out (rows in them and in the others); the held-out share is of
    # their rows only: a channel whose rows all sit in one fold (one flow window left after the
    # quiet ones) has nothing held out, not a term that "predicts 100 % of the held-out residual"
    held = [k for k in range(K) if 0 < nk[k] < n]
    total = float(ssk[held].sum())

    def cv(threshold: float, which: np.ndarray | None = None) -> float:
        sel = np.arange(len(cols)) if which is None else which
        sse = 0.0
        for k in held:
            Gt = (G - Gk[k])[np.ix_(sel, sel)]
            c = stlsq_gram(Gt, (b - bk[k])[sel], n - int(nk[k]), threshold)
            sse += ssk[k] - 2 * float(c @ bk[k][sel]) + float(c @ Gk[k][np.ix_(sel, sel)] @ c)
        return sse

    scores = [cv(th) for th in THRESHOLDS]
    i = int(np.argmin(scores))
    th = THRESHOLDS[i]
    r2 = 1.0 - scores[i] / total if total > 0 else 0.0
    c = stlsq_gram(G, b, n, th)
    coef = c * ys / scale
    best = None
    best_coef = 0.0
    best_r2 = 0.0
    for j in np.flatnonzero(c):
        r2j = 1.0 - cv(0.0, np.array([j])) / total if total > 0 else 0.0
        if best is None or r2j > best_r2:
            best, best_coef, best_r2 = cols[j], float(b[j] / G[j, j] * ys / scale[j]), r2j
    return SparseFit(cols, coef, float(r2), th, best, best_coef, float(best_r2))
