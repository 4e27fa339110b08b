"""The vectorised CSV writer is Python's ``%`` formatting, byte for byte (issue 17).

``companion.tools.csv_format.format_rows`` exists only for speed, compiled (companion/native/kernels.c)
or in numpy; ``format_rows_reference`` (the ``%`` operator, value by value) is the rule. Each test
runs on both. Held equal over random values of every magnitude, the edge cases of ``%g`` (ties,
powers of ten and the values around them, the switch to exponents, zeros of both signs, NaN,
infinities, subnormals, the largest doubles), integers, names, and whole replays.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.tools.csv_format import format_rows, format_rows_reference

ROOT = Path(__file__).resolve().parents[1]

EDGES = [0.0, -0.0, np.inf, -np.inf, np.nan, -np.nan, 5e-324, 1e-320, 2.2250738585072014e-308, 1e-300, 1e300,
         1.7976931348623157e308, -1.7976931348623157e308, 1e22, 1e23, 1e-22, 1e-23, 0.5, 1.5, 2.5,
         123456789.5, 1234567895.0, 12345678950.0, 999999999.5, 999.99999995, 9.9999999995, 99999.99999,
         1e-5, 1e-4, 0.0001, 0.00009999999995, 0.000099999999949, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13,
         123456789012.0, 123456789012.5, 999999999999.5, 0.1, 0.2, 0.3, 1 / 3, 2 / 3, -1 / 7, 3.14159265358979,
         0.020000000000000018, 0.019999999999999574, 1.0000000005, 1.0000000015, 10.0, 100.0, 1000.0]


@pytest.fixture(autouse=True, params=["compiled", "numpy"])
def writer(request, monkeypatch):
    """Every test twice: the compiled kernel (``fh_csv_rows``, companion/native) and the numpy
    formulation (``FLOWHOLD_NATIVE=0``)."""
    from companion import native

    if request.param == "numpy":
        monkeypatch.setenv("FLOWHOLD_NATIVE", "0")
    elif native.kernels() is None:
        pytest.skip("no C compiler: the numpy path is the only one")
    return request.param


def _check(columns: list[np.ndarray], formats: list[str]) -> None:
    assert format_rows(columns, formats) == format_rows_reference(columns, formats)


@pytest.mark.parametrize("fmt", ["%.9g", "%.12g", "%.6g", "%.1g", "%.15g"])
def test_edge_values(fmt):
    x = np.array(EDGES + [-v for v in EDGES], dtype=np.float64)
    _check([x], [fmt])
    _check([x[::-1], x], [fmt, "%.9g"])


@pytest.mark.parametrize("fmt", ["%.9g", "%.12g"])
def test_every_magnitude(fmt):
    rng = np.random.default_rng(17)
    n = 60_000
    mant = rng.uniform(-10, 10, n)
    x = mant * 10.0 ** rng.integers(-30, 30, n)
    decimals = np.round(rng.standard_normal(n) * 10.0 ** rng.integers(0, 13, n)) / 10.0 ** rng.integers(0, 13, n)
    halves = (rng.integers(0, 10**10, n) + 0.5) / 10.0 ** rng.integers(0, 8, n)  # near rounding ties
    _check([x, decimals, halves, x.astype(np.float32)], [fmt] * 4)


@pytest.mark.parametrize("fmt", ["%.9g", "%.12g", "%.1g", "%.15g"])
def test_around_powers_of_ten(fmt):
    """A few ulps either side of every power of ten from 1e-35 to 1e45 (where the exponent of
    the digits is in doubt), and a rounding step either side (where the digits carry over)."""
    p = int(fmt[2:-1])
    values = []
    for k in range(-35, 46):
        x = float(f"1e{k}")
        for _ in range(4):
            values += [x, -x]
            x = np.nextafter(x, np.inf)
        x = float(f"1e{k}")
        for _ in range(4):
            x = np.nextafter(x, 0.0)
            values += [x, -x]
        for r in (0.5, 0.49999999999, 0.50000000001, 0.6, 0.4):
            values += [float(f"1e{k}") * (1 - r * 10.0 ** -p), float(f"1e{k}") * (1 + r * 10.0 ** -p)]
    _check([np.array(values, dtype=np.float64)], [fmt])


def test_integers_and_names():
    rng = np.random.default_rng(3)
    n = 5000
    ints = [rng.integers(-10**18, 10**18, n), rng.integers(-3, 3, n).astype(np.int8), rng.integers(0, 255, n).astype(
        np.uint8), np.array([np.iinfo(np.int64).min, np.iinfo(np.int64).max, 0, -1, 1] * (n // 5)),
        rng.integers(0, 2, n).astype(bool)]
    names = np.array(["", "RANGE_INVALID", "DISENGAGED", "é"], dtype=object)[rng.integers(0, 4, n)]
    _check([*ints, names], ["%d"] * len(ints) + ["%s"])
    mixed = np.empty(6, dtype=object)
    mixed[:] = [1, 1.0, True, None, [1, 2], "x"]
    _check([mixed[:3], mixed[3:]], ["%s", "%s"])
    _check([mixed], ["%s"])
    _check([ints[0], ints[1]], ["%.9g", "%.12g"])  # integers through %g as Python does


def test_blocks_and_empty():
    x = np.linspace(-3, 3, 40_000)
    _check([x, np.arange(40_000)], ["%.9g", "%d"])
    _check([np.zeros(0), np.zeros(0, dtype=np.int64)], ["%.9g", "%d"])


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=1, max_size=50),
       st.sampled_from(["%.9g", "%.12g"]))
def test_any_float(values, fmt):
    _check([np.array(values, dtype=np.float64)], [fmt])


def test_replay_csv_is_the_reference_text(tmp_path, flight_a_plain):
    """The whole replay of the SITL flight: the file written equals the ``%`` text of its columns."""
    from companion.config import load_config
    from companion.recordings.tlog_reader import read_tlog
    from companion.step.profiles import Profile
    from companion.tools.replay import _csv_formats, replay, write_csv

    res = replay(read_tlog(flight_a_plain), load_config(), Profile.ARDUPILOT)
    out = tmp_path / "r.csv"
    names = write_csv(res, out)
    _, fmts = _csv_formats(res)
    expected = (",".join(names) + "\n").encode() + format_rows_reference([res.columns[c] for c in names], fmts)
    assert out.read_bytes() == expected


def test_parquet_has_the_csv_columns(tmp_path, flight_a_plain):
    pq = pytest.importorskip("pyarrow.parquet")
    from companion.config import load_config
    from companion.recordings.tlog_reader import read_tlog
    from companion.step.profiles import Profile
    from companion.tools.replay import replay, write_parquet

    res = replay(read_tlog(flight_a_plain), load_config(), Profile.ARDUPILOT)
    names = write_parquet(res, tmp_path / "r.parquet")
    table = pq.read_table(tmp_path / "r.parquet")
    assert table.column_names == names
    for c in names:
        got = table.column(c).to_numpy(zero_copy_only=False)
        want = res.columns[c]
        if want.dtype == object:
            assert got.tolist() == want.tolist()
        else:
            np.testing.assert_array_equal(got, want)


def test_parquet_without_pyarrow_is_one_line(flight_a_plain, tmp_path):
    """``--parquet`` where pyarrow is not installed: one line saying how to install it, the usage
    exit code, and no file."""
    from companion.errors import ExitCode

    probe = ("import sys; sys.modules['pyarrow'] = None; sys.modules['pyarrow.parquet'] = None\n"
             "from companion.cli import main\nsys.exit(main(sys.argv[1:]))")
    out = subprocess.run([sys.executable, "-c", probe, "replay", str(flight_a_plain), "--parquet",
                          str(tmp_path / "r.parquet")], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == int(ExitCode.USAGE)
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "pyarrow" in lines[0] and "pip install" in lines[0] and "Traceback" not in out.stderr
    assert not (tmp_path / "r.parquet").exists()
    # said before the recording is read (a missing one would be another error)
    missing = subprocess.run([sys.executable, "-c", probe, "replay", str(tmp_path / "none.tlog"), "--parquet",
                              str(tmp_path / "r.parquet")], capture_output=True, text=True, cwd=ROOT)
    assert missing.returncode == int(ExitCode.USAGE) and "pyarrow" in missing.stderr


def test_replay_without_an_output_is_one_line(flight_a_plain):
    out = subprocess.run([sys.executable, "-m", "companion", "replay", str(flight_a_plain)], capture_output=True,
                         text=True, cwd=ROOT)
    assert out.returncode == 2
    assert out.stderr.strip().count("\n") == 0 and "--csv" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize("threads", [2, 3])
def test_pieces_formatted_in_threads(threads):
    """The pieces formatted ahead by worker threads (the compiled writer; the numpy path has one
    thread) are the reference text, in order; closing early stops the workers."""
    import threading

    from companion.tools.csv_format import iter_rows

    rng = np.random.default_rng(17)
    n = 5000
    cols = [rng.normal(size=n) * 10.0 ** rng.integers(-8, 9, size=n), np.arange(n) - 2500,
            np.array(["", "DISENGAGED", "NO_GYRO"], dtype=object)[rng.integers(0, 3, size=n)]]
    fmts = ["%.9g", "%d", "%s"]
    pieces = [bytes(p) for p in iter_rows(cols, fmts, block_rows=97, threads=threads)]
    assert len(pieces) == -(-n // 97)
    assert b"".join(pieces) == format_rows_reference(cols, fmts)
    it = iter_rows(cols, fmts, block_rows=97, threads=threads)
    assert bytes(next(it)) == format_rows_reference([c[:97] for c in cols], fmts)
    it.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("csv-format")]
