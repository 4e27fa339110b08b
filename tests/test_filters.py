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
