"""Numpy copies that exist only for speed, held equal to the definitions they copy (issue 17)."""

from __future__ import annotations

import numpy as np
import pytest

from companion.step.core import _trailing_span, _trailing_span_direct
from companion.tools.info import _median


@pytest.mark.parametrize("m", [1, 2, 3, 7, 25, 60, 101, 150])
@pytest.mark.parametrize("n", [0, 1, 2, 24, 25, 26, 49, 50, 51, 1000, 4099])
def test_trailing_span_equals_the_window_view(n, m):
    """The O(n) sliding extremes equal the window view's max - min, NaN and infinities included
    (a window holding a NaN is NaN; +inf - +inf is NaN in both)."""
    rng = np.random.default_rng(1000 * n + m)
    x = np.round(rng.standard_normal(n), 2)  # ties between equal values
    for value, share in ((np.nan, 0.01), (np.inf, 0.005), (-np.inf, 0.005), (0.0, 0.05), (-0.0, 0.05)):
        x[rng.random(n) < share] = value
    with np.errstate(invalid="ignore"):
        got, want = _trailing_span(x, m), _trailing_span_direct(x, m)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 50, 51, 1000, 1001, 20_000])
def test_info_median_equals_numpy(n):
    """``info._median`` (one partition) is ``np.median`` exactly: odd and even lengths, ties,
    every magnitude, and NaN (then NaN)."""
    rng = np.random.default_rng(n)
    for scale in (1e-6, 1.0, 1e6):
        x = rng.standard_normal(n) * scale
        assert _median(x) == float(np.median(x))
        r = np.round(x / scale, 1) * scale  # many equal values
        assert _median(r) == float(np.median(r))
    x[n // 2] = np.nan
    assert np.isnan(_median(x))


@pytest.mark.parametrize("seed", range(5))
def test_times_that_never_go_back_have_no_spike(seed):
    """``tlog_reader._repair_times`` skips the spike scan when the record times never go back:
    the scan finds none there (steps of any size, repeats, clock jumps of hours, times near
    2^64 us where the doubles are coarse)."""
    from companion.recordings.tlog_reader import TIME_SPIKE_TOL_S, _spikes

    rng = np.random.default_rng(seed)
    n = 20_000
    steps = rng.choice([0.0, 1e-6, 0.02, 0.9, 1.5, 3600.0, 1e6], size=n, p=[0.1, 0.1, 0.6, 0.05, 0.05, 0.05, 0.05])
    for t0 in (0.0, 1.75e9, 1.8e13):
        t = t0 + np.cumsum(steps)
        assert np.all(np.diff(t) >= 0)
        assert not _spikes(t, TIME_SPIKE_TOL_S).any()


def test_stable_order_equals_a_stable_argsort():
    """``replay._stable_order`` skips the sort of keys already in order: the same order as
    ``np.argsort(kind="stable")`` for sorted keys, ties, one swap, NaN, empty and one key."""
    from companion.tools.replay import _stable_order

    rng = np.random.default_rng(4)
    sorted_keys = np.sort(rng.integers(0, 50, 1000)).astype(float)
    swapped = sorted_keys.copy()
    swapped[[10, 500]] = swapped[[500, 10]]
    with_nan = sorted_keys.copy()
    with_nan[300] = np.nan
    for keys in (sorted_keys, swapped, with_nan, sorted_keys[::-1], np.zeros(0), np.ones(1), sorted_keys.astype(int)):
        np.testing.assert_array_equal(_stable_order(keys), np.argsort(keys, kind="stable"))
