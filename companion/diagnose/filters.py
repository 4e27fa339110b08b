"""The few linear filters the diagnosis uses, without importing ``scipy.signal``.

``scipy.signal`` (with ``scipy.stats``, which it loads) takes about 0.3 s to import, a twentieth
of the whole ``diagnose`` command on an hour-long recording and more than its own work on a short
one. The diagnosis needs only a second-order Butterworth low-pass, ``lfilter``/``lfiltic`` of
second-order sections and ``filtfilt``: they are written here with ``scipy.signal``'s rules and
defaults, and ``tests/test_filters.py`` holds each equal to ``scipy.signal``'s, option by option.
``running_count``, a running sum over a mask, is here too: every window test of "no lost frame
in it" uses it.

The recursion of ``lfilter`` (a loop over samples) runs in the compiled kernels
(``companion.native``, ``fh_lfilter2``: scipy's direct form II transposed, term for term); without
them (no C compiler, ``FLOWHOLD_NATIVE=0``) ``scipy.signal.lfilter`` itself runs, imported then.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion import native


def running_count(mask: np.ndarray) -> np.ndarray:
    """c (len(mask) + 1,) with c[k] the number of True among mask[:k]: c[b] - c[a] counts them in
    mask[a:b], for any number of spans at once (``c[b] - c[a] == 0``: none of a window's frames
    is lost, invalid, a break). A running sum, the simplest of filters."""
    return np.concatenate([[0], np.cumsum(mask, dtype=np.int64)])


def butter2_lowpass(wn: float) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.signal.butter(2, wn)``: the digital second-order Butterworth low-pass with cut-off
    ``wn`` (a fraction of the Nyquist frequency, 0 < wn < 1), by the bilinear transform with
    prewarping: K = tan(pi wn / 2), b = K^2 (1, 2, 1) / D, a = (1, 2 (K^2 - 1) / D,
    (1 - sqrt2 K + K^2) / D), D = 1 + sqrt2 K + K^2."""
    if not 0.0 < wn < 1.0:
        raise ValueError(f"a digital filter's cut-off must lie between 0 and 1 (Nyquist), not {wn}")
    k = math.tan(math.pi * wn / 2.0)
    d = 1.0 + math.sqrt(2.0) * k + k * k
    b = np.array([k * k, 2.0 * k * k, k * k]) / d
    a = np.array([1.0, 2.0 * (k * k - 1.0) / d, (1.0 - math.sqrt(2.0) * k + k * k) / d])
    return b, a


def _second_order(b: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """b and a as three coefficients each, normalised by a[0] (as scipy's lfilter does)."""
    b = np.asarray(b, dtype=float)
    a = np.asarray(a, dtype=float)
    if b.ndim != 1 or a.ndim != 1 or not 1 <= len(b) <= 3 or not 1 <= len(a) <= 3 or a[0] == 0:
        raise ValueError("only filters of order up to 2 with a[0] != 0")
    b3 = np.zeros(3)
    a3 = np.zeros(3)
    b3[:len(b)] = b
    a3[:len(a)] = a
    return b3 / a3[0], a3 / a3[0]


def lfiltic(b: np.ndarray, a: np.ndarray, y: np.ndarray | Sequence[float],
            x: np.ndarray | Sequence[float] | None = None) -> np.ndarray:
    """``scipy.signal.lfiltic(b, a, y, x)`` for a filter of order 2: the state (2,) of
    ``lfilter`` that continues from the past outputs y = [y[-1], y[-2]] and inputs
    x = [x[-1], x[-2]] (zeros where not given)."""
    b3, a3 = _second_order(b, a)
    yy = np.zeros(2)
    xx = np.zeros(2)
    ya = np.asarray(y, dtype=float)
    yy[:min(len(ya), 2)] = ya[:2]
    if x is not None:
        xa = np.asarray(x, dtype=float)
        xx[:min(len(xa), 2)] = xa[:2]
    # scipy: zi[m] = sum(b[m + 1:] * x[:M - m]) - sum(a[m + 1:] * y[:N - m]) (b, a as given, a[0] = 1 here)
    zi = np.array([b3[1] * xx[0] + b3[2] * xx[1], b3[2] * xx[0]])
    zi -= np.array([a3[1] * yy[0] + a3[2] * yy[1], a3[2] * yy[0]])
    return zi


def lfilter(b: np.ndarray, a: np.ndarray, x: np.ndarray, zi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.signal.lfilter(b, a, x, zi=zi)`` for a filter of order 2 and a 1-D x: the output
    and the final state."""
    b3, a3 = _second_order(b, a)
    x = np.ascontiguousarray(x, dtype=float)
    z = np.array(zi, dtype=float).reshape(2)
    if x.ndim == 1 and len(x) == 0:  # (scipy leaves the final state uninitialised here)
        return x.copy(), z
    lib = native.kernels()
    if lib is None or x.ndim != 1:
        from scipy import signal  # the definition, where the kernels are not loaded

        y, zf = signal.lfilter(b3, a3, x, zi=z)
        return np.asarray(y), np.asarray(zf)
    y = np.empty_like(x)
    lib.fh_lfilter2(b3.ctypes.data, a3.ctypes.data, x.ctypes.data, len(x), z.ctypes.data, y.ctypes.data)
    return y, z


def lfiltic_rows(b: np.ndarray, a: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``lfiltic(b, a, y[s], x[s])`` for every row s of y and x (each (nseg, 2): the past two
    outputs and inputs, latest first) at once: (nseg, 2), the same arithmetic term for term."""
    b3, a3 = _second_order(b, a)
    y = np.asarray(y, dtype=float)
    x = np.asarray(x, dtype=float)
    zi = np.empty((len(y), 2))
    zi[:, 0] = (b3[1] * x[:, 0] + b3[2] * x[:, 1]) - (a3[1] * y[:, 0] + a3[2] * y[:, 1])
    zi[:, 1] = b3[2] * x[:, 0] - a3[2] * y[:, 0]
    return zi


def lfilter_segments(b: np.ndarray, a: np.ndarray, x: np.ndarray, starts: np.ndarray, stops: np.ndarray,
                     zi: np.ndarray, fill: float = math.nan) -> np.ndarray:
    """``lfilter(b, a, x[start:stop], zi[s])`` for each stretch s of the 1-D x, into one array
    (``fill`` outside every stretch): the compiled kernel ``fh_lfilter2_segments`` in one call
    when loaded (an hour's attitude restarted after every lost command is thousands of
    stretches), else ``lfilter`` stretch by stretch; tests/test_native.py holds the two equal."""
    b3, a3 = _second_order(b, a)
    x = np.ascontiguousarray(x, dtype=float)
    starts = np.ascontiguousarray(starts, dtype=np.int64)
    stops = np.ascontiguousarray(stops, dtype=np.int64)
    zi = np.ascontiguousarray(zi, dtype=float).reshape(len(starts), 2)
    y = np.full_like(x, fill)
    lib = native.kernels()
    if lib is not None and x.ndim == 1:
        lib.fh_lfilter2_segments(b3.ctypes.data, a3.ctypes.data, x.ctypes.data, starts.ctypes.data,
                                 stops.ctypes.data, len(starts), zi.ctypes.data, y.ctypes.data)
        return y
    for s0, s1, z in zip(starts, stops, zi, strict=True):
        if s1 > s0:
            y[s0:s1], _ = lfilter(b3, a3, x[s0:s1], z)
    return y


def lfilter_zi(b: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``scipy.signal.lfilter_zi(b, a)`` for order 2: the state of the step response's steady
    state, solving (I - companion(a)^T) zi = b[1:] - a[1:] b[0]."""
    b3, a3 = _second_order(b, a)
    companion_t = np.array([[-a3[1], 1.0], [-a3[2], 0.0]])
    return np.linalg.solve(np.eye(2) - companion_t, b3[1:] - a3[1:] * b3[0])


def filtfilt(b: np.ndarray, a: np.ndarray, x: np.ndarray, axis: int = -1) -> np.ndarray:
    """``scipy.signal.filtfilt(b, a, x, axis=axis)`` with its defaults (odd extension of
    3 max(len(a), len(b)) samples at each end, each pass started in the steady state of the first
    sample) for a filter of order 2."""
    x = np.asarray(x, dtype=float)
    padlen = 3 * max(len(a), len(b))
    xm = np.moveaxis(x, axis, -1)
    if xm.shape[-1] <= padlen:
        raise ValueError(f"filtfilt: the signal must be longer than {padlen} samples")
    zi = lfilter_zi(b, a)
    out = np.empty_like(xm)
    for idx in np.ndindex(*xm.shape[:-1]):
        row = xm[idx]
        ext = np.concatenate((2 * row[0] - row[padlen:0:-1], row, 2 * row[-1] - row[-2:-(padlen + 2):-1]))
        y, _ = lfilter(b, a, ext, zi * ext[0])
        y, _ = lfilter(b, a, y[::-1], zi * y[-1])
        out[idx] = y[::-1][padlen:-padlen]
    return np.moveaxis(out, -1, axis)


@dataclass(frozen=True)
class FiltfiltPlan:
    """Where ``filtfilt_segments`` takes each sample of the stretches' odd extensions from: it
    depends on the stretches only, so a signal filtered again and again over the same stretches
    (a fit's residuals) builds it once (``filtfilt_plan``)."""

    pad: int
    ext_start: np.ndarray  # each stretch's extension in the extended signal
    ext_stop: np.ndarray
    src: np.ndarray  # the x sample each extended sample is taken from (mirrored in the pads)
    left: np.ndarray  # extended samples before each stretch (odd: 2 x[first] - mirrored), its first
    left_end: np.ndarray
    right: np.ndarray  # after each stretch, its last
    right_end: np.ndarray
    rev: np.ndarray  # each stretch's extension reversed in place
    mid: np.ndarray  # the stretches' own samples, and their x indices
    mid_src: np.ndarray


def filtfilt_plan(starts: np.ndarray, stops: np.ndarray, pad: int) -> FiltfiltPlan:
    """``filtfilt_segments``'s indices for the stretches [starts, stops), each longer than ``pad``."""
    starts = np.asarray(starts, dtype=np.int64)
    stops = np.asarray(stops, dtype=np.int64)
    lens = stops - starts
    if np.any(lens <= pad):
        raise ValueError(f"filtfilt: the signal must be longer than {pad} samples")
    ext_len = lens + 2 * pad
    ext_start = np.concatenate([[0], np.cumsum(ext_len)[:-1]]).astype(np.int64)
    seg = np.repeat(np.arange(len(starts)), ext_len)
    pos = np.arange(int(ext_len.sum())) - ext_start[seg]
    left = pos < pad
    right = pos >= pad + lens[seg]
    mid = ~left & ~right
    src = starts[seg] + pos - pad  # the stretch itself
    src[left] = starts[seg[left]] + pad - pos[left]  # row[pad:0:-1]
    src[right] = stops[seg[right]] - 2 - (pos[right] - pad - lens[seg[right]])  # row[-2:-(pad + 2):-1]
    rev = ext_start[seg] + ext_len[seg] - 1 - pos  # each stretch reversed in place
    return FiltfiltPlan(pad, ext_start, ext_start + ext_len, src, left, starts[seg[left]], right, stops[seg[right]] - 1,
                        rev, mid, src[mid])


def filtfilt_segments(b: np.ndarray, a: np.ndarray, x: np.ndarray, starts: np.ndarray, stops: np.ndarray,
                      plan: FiltfiltPlan | None = None) -> np.ndarray:
    """``filtfilt(b, a, x[start:stop])`` for each stretch of the 1-D x (each longer than
    3 max(len(a), len(b)) samples), into one array (0 outside every stretch): every stretch's odd
    extension built at once and both passes run by ``lfilter_segments``, the same arithmetic as
    ``filtfilt`` stretch by stretch (tests/test_filters.py). ``plan``: ``filtfilt_plan`` of the
    same stretches, when one signal after another is filtered over them."""
    x = np.asarray(x, dtype=float)
    out = np.zeros_like(x)
    if len(starts) == 0:
        return out
    pad = 3 * max(len(a), len(b))
    lib = native.kernels()
    if lib is not None and x.ndim == 1:
        # the compiled copy (``fh_filtfilt2_segments``, tests/test_filters.py holds the two equal)
        starts = np.ascontiguousarray(starts, dtype=np.int64)
        stops = np.ascontiguousarray(stops, dtype=np.int64)
        lens = stops - starts
        if np.any(lens <= pad):
            raise ValueError(f"filtfilt: the signal must be longer than {pad} samples")
        b3, a3 = _second_order(b, a)
        zi = np.ascontiguousarray(lfilter_zi(b, a), dtype=float)
        x = np.ascontiguousarray(x)
        scratch = np.empty(3 * (int(lens.max()) + 2 * pad))
        lib.fh_filtfilt2_segments(b3.ctypes.data, a3.ctypes.data, zi.ctypes.data, x.ctypes.data, starts.ctypes.data,
                                  stops.ctypes.data, len(starts), pad, scratch.ctypes.data, out.ctypes.data)
        return out
    if plan is None:
        plan = filtfilt_plan(starts, stops, pad)
    elif plan.pad != pad or len(plan.ext_start) != len(starts):
        raise ValueError("filtfilt_segments: the plan is for other stretches or another filter order")
    ext = x[plan.src]
    ext[plan.left] = 2 * x[plan.left_end] - ext[plan.left]
    ext[plan.right] = 2 * x[plan.right_end] - ext[plan.right]
    zi = lfilter_zi(b, a)
    y = lfilter_segments(b, a, ext, plan.ext_start, plan.ext_stop, zi[None, :] * ext[plan.ext_start][:, None],
                         fill=0.0)
    yr = y[plan.rev]
    y2 = lfilter_segments(b, a, yr, plan.ext_start, plan.ext_stop, zi[None, :] * yr[plan.ext_start][:, None],
                          fill=0.0)
    out[plan.mid_src] = y2[plan.rev][plan.mid]
    return out
