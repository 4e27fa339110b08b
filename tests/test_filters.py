"""companion.diagnose.filters equals scipy.signal, function by function and option by option,
with the compiled recursion and without it (FLOWHOLD_NATIVE=0: scipy's own lfilter)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from companion import native
from companion.diagnose import filters

# a few ulps: the recursion is scipy's, term for term, but its compiler may contract or reorder
RTOL = 1e-12


@pytest.fixture(params=["native", "numpy"])
def path(request, monkeypatch):
    if request.param == "numpy":
        monkeypatch.setenv("FLOWHOLD_NATIVE", "0")
    elif native.kernels() is None:
        pytest.skip("no C compiler: the kernels are not built")
    return request.param


@pytest.mark.parametrize("wn", [1e-4, 0.004, 0.04, 0.3, 0.5, 0.9, 0.999])
def test_butterworth_is_scipys(wn):
    b, a = filters.butter2_lowpass(wn)
    bs, as_ = signal.butter(2, wn)
    np.testing.assert_allclose(b, bs, rtol=1e-10, atol=1e-300)
    np.testing.assert_allclose(a, as_, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("wn", [0.0, 1.0, -0.2, 1.5])
def test_butterworth_outside_zero_to_nyquist_is_refused(wn):
    with pytest.raises(ValueError, match="between 0 and 1"):
        filters.butter2_lowpass(wn)


def _filters():
    # the two the diagnosis uses (a Butterworth low-pass, a discretised attitude loop), a
    # first-order one, and an un-normalised a[0]
    return [signal.butter(2, 0.04), (np.array([0.02, 0.03, 0.0]), np.array([1.0, -1.7, 0.75])),
            (np.array([0.5, 0.5]), np.array([1.0, -0.3])), (np.array([1.0, 2.0, 1.0]), np.array([4.0, -2.0, 0.5]))]


@pytest.mark.parametrize("k", range(4))
def test_lfiltic_is_scipys(k):
    b, a = _filters()[k]
    rng = np.random.default_rng(k)
    for y, x in ((rng.normal(size=2), rng.normal(size=2)), (rng.normal(size=2), None), (rng.normal(size=1), [0.3])):
        zs = signal.lfiltic(b, a, y, x)
        zi = filters.lfiltic(b, a, y, x)
        np.testing.assert_allclose(zi[:len(zs)], zs, rtol=RTOL, atol=1e-15)
        assert not np.any(zi[len(zs):])


@pytest.mark.parametrize("k", range(4))
@pytest.mark.parametrize("n", [0, 1, 2, 7, 5000])
def test_lfilter_is_scipys(path, k, n):
    b, a = _filters()[k]
    rng = np.random.default_rng(n)
    x = rng.normal(size=n)
    zi = rng.normal(size=2)
    order = max(len(a), len(b)) - 1
    y, z = filters.lfilter(b, a, x, zi if order == 2 else np.r_[zi[:1], 0.0])
    if n == 0:  # nothing filtered: the state is the initial one (scipy's is uninitialised memory)
        assert len(y) == 0 and z[:order] == pytest.approx(zi[:order])
        return
    ys, zs = signal.lfilter(b, a, x, zi=zi[:order])
    np.testing.assert_allclose(y, ys, rtol=RTOL, atol=1e-13)
    np.testing.assert_allclose(z[:order], zs, rtol=RTOL, atol=1e-13)


@pytest.mark.parametrize("k", range(4))
def test_lfilter_zi_is_scipys(k):
    b, a = _filters()[k]
    zs = signal.lfilter_zi(b, a)
    np.testing.assert_allclose(filters.lfilter_zi(b, a)[:len(zs)], zs, rtol=1e-10)


@pytest.mark.parametrize("shape, axis", [((10,), -1), ((500,), 0), ((2, 3000), 1), ((2, 3000), -1), ((40, 3), 0)])
def test_filtfilt_is_scipys(path, shape, axis):
    rng = np.random.default_rng(sum(shape))
    x = np.cumsum(rng.normal(size=shape), axis=axis)  # a random walk: the ends' extension matters
    for b, a in (signal.butter(2, 0.004), signal.butter(2, 0.3)):
        np.testing.assert_allclose(filters.filtfilt(b, a, x, axis=axis), signal.filtfilt(b, a, x, axis=axis),
                                   rtol=1e-9, atol=1e-9 * np.abs(x).max())


def test_filtfilt_refuses_a_signal_as_short_as_its_padding():
    b, a = signal.butter(2, 0.1)
    with pytest.raises(ValueError):
        signal.filtfilt(b, a, np.ones(9))
    with pytest.raises(ValueError, match="longer than 9"):
        filters.filtfilt(b, a, np.ones(9))
    assert filters.filtfilt(b, a, np.ones(10)) == pytest.approx(np.ones(10))


def test_the_filters_do_not_load_scipy_signal():
    import subprocess
    import sys

    code = ("import sys; from companion.diagnose import filters; import numpy as np; "
            "b, a = filters.butter2_lowpass(0.1); filters.filtfilt(b, a, np.arange(50.0)); "
            "from companion import native; assert native.kernels() is None or 'scipy.signal' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("k", range(4))
def test_lfiltic_rows_is_lfiltic_row_by_row(k):
    """The attitude simulation's initial states for all its segments at once: the same numbers
    as ``lfiltic`` one segment at a time, to the bit."""
    b, a = _filters()[k]
    rng = np.random.default_rng(k)
    y, x = rng.normal(size=(50, 2)), rng.normal(size=(50, 2))
    rows = filters.lfiltic_rows(b, a, y, x)
    for s in range(50):
        np.testing.assert_array_equal(rows[s], filters.lfiltic(b, a, y[s], x[s]))


def _stretches(rng, n, min_len):
    cuts = np.sort(rng.choice(np.arange(1, n), n // 40, replace=False))
    bounds = [(int(s0), int(s1)) for s0, s1 in zip(np.r_[0, cuts], np.r_[cuts, n], strict=True) if s1 - s0 >= min_len]
    keep = rng.random(len(bounds)) < 0.8  # gaps between stretches as well
    return np.array([b for b, k in zip(bounds, keep, strict=True) if k], dtype=np.int64)


@pytest.mark.parametrize("k", range(4))
def test_lfilter_segments_is_lfilter_per_stretch(path, k):
    """Thousands of stretches (an hour of attitude restarted after every lost command) in one
    call: each equals ``lfilter`` on the stretch alone with its own initial state, to the bit, and
    the frames between stretches keep the fill."""
    b, a = _filters()[k]
    rng = np.random.default_rng(k)
    n = 20000
    x = rng.normal(size=n)
    bounds = _stretches(rng, n, 1)
    zi = rng.normal(size=(len(bounds), 2))
    y = filters.lfilter_segments(b, a, x, bounds[:, 0], bounds[:, 1], zi, fill=-7.0)
    inside = np.zeros(n, dtype=bool)
    for (s0, s1), z in zip(bounds, zi, strict=True):
        inside[s0:s1] = True
        np.testing.assert_array_equal(y[s0:s1], filters.lfilter(b, a, x[s0:s1], z)[0])
    assert np.all(y[~inside] == -7.0) and len(bounds) > 300


@pytest.mark.parametrize("k", range(4))
def test_filtfilt_segments_is_filtfilt_per_stretch(path, k):
    """The loop-form check's zero-phase split over every segment at once: each stretch equals
    ``filtfilt`` on it alone, to the bit, 0 between stretches; a stretch too short is refused as
    ``filtfilt`` refuses it."""
    b, a = _filters()[k]
    rng = np.random.default_rng(10 + k)
    n = 20000
    x = rng.normal(size=n)
    pad = 3 * max(len(a), len(b))
    bounds = _stretches(rng, n, pad + 1)
    y = filters.filtfilt_segments(b, a, x, bounds[:, 0], bounds[:, 1])
    inside = np.zeros(n, dtype=bool)
    for s0, s1 in bounds:
        inside[s0:s1] = True
        np.testing.assert_array_equal(y[s0:s1], filters.filtfilt(b, a, x[s0:s1]))
    assert np.all(y[~inside] == 0.0) and len(bounds) > 100
    plan = filters.filtfilt_plan(bounds[:, 0], bounds[:, 1], pad)  # made once, for signal after signal
    for x2 in (x, rng.normal(size=n)):
        np.testing.assert_array_equal(filters.filtfilt_segments(b, a, x2, bounds[:, 0], bounds[:, 1], plan),
                                      filters.filtfilt_segments(b, a, x2, bounds[:, 0], bounds[:, 1]))
    with pytest.raises(ValueError, match="longer than"):
        filters.filtfilt_segments(b, a, x, np.array([0]), np.array([pad]))


def test_running_count_counts_the_true_values_of_any_span():
    """c[b] - c[a] is the number of True in mask[a:b], checked against a direct count over every
    span of a random mask (and the empty mask's single zero)."""
    rng = np.random.default_rng(3)
    mask = rng.random(40) < 0.3
    c = filters.running_count(mask)
    assert c.shape == (41,) and c.dtype == np.int64
    for a in range(41):
        for b in range(a, 41):
            assert c[b] - c[a] == int(np.count_nonzero(mask[a:b]))
    assert filters.running_count(np.zeros(0, dtype=bool)).tolist() == [0]
