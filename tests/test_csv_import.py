"""CSV importer driven by a column map (companion/recordings/importers/csv_columns.py).

The imported tables are checked against an independent read of the same CSV with the ``csv``
module and the unit/sign mapping written out here from the StampFly README (gyro rad/s ->
mrad/s, accel m/s^2 -> milli-g, ToF m -> cm, flow ``dX_paper = -raw_flow_dx``,
``dY_paper = -raw_flow_dy``). Bad column maps and bad CSVs must give one-line errors.
"""

from __future__ import annotations

import csv
import gzip
import shutil
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from companion.diagnose.sensor.api import find_read_grid
from companion.errors import ConfigError, RecordingError
from companion.recordings.importers.csv_columns import load_column_map, read_csv
from companion.recordings.load import load_recording
from companion.step.estimator import velocity_from_flow

REPO = Path(__file__).resolve().parent.parent
STAMPFLY = REPO / "data" / "real" / "stampfly"
XTEST = STAMPFLY / "flow_test_x_axis_01.csv.gz"
MAP = REPO / "configs" / "sensors" / "stampfly.toml"
G = 9.80665
Q_PAPER = 0.09 / 57.3


def _rows(path: Path) -> list[dict[str, str]]:
    """The rows of a .csv.gz, read independently with gzip and the ``csv`` module."""
    with gzip.open(path, "rt", newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def xtest():
    return read_csv(XTEST, MAP), _rows(XTEST)


@pytest.mark.parametrize("i", [0, 1, 2, 917, 1833])
def test_row_values_follow_the_map(xtest, i):
    rec, rows = xtest
    r = rows[i]
    ms = float(r["timestamp_ms"])
    of, imu, ds = rec.tables["OPTICAL_FLOW"], rec.tables["RAW_IMU"], rec.tables["DISTANCE_SENSOR"]
    for tab in (of, imu, ds):
        assert tab.t_s[i] == pytest.approx(ms / 1e3)
        assert tab.sysid[i] == 1 and tab.compid[i] == 1
    assert of["time_usec"][i] == round(ms * 1000) and imu["time_usec"][i] == round(ms * 1000)
    assert ds["time_boot_ms"][i] == pytest.approx(ms)
    assert of["flow_x"][i] == -float(r["raw_flow_dx"])
    assert of["flow_y"][i] == -float(r["raw_flow_dy"])
    assert of["quality"][i] == int(r["raw_flow_squal"])
    assert of["ground_distance"][i] == -1.0 and of["sensor_id"][i] == 0
    assert np.isnan(of["flow_rate_x"][i]) and np.isnan(of["flow_comp_m_y"][i])
    assert of["integration_time_us"][i] == pytest.approx(10_000.0)  # README: read every 10 ms
    for ax in "xyz":
        assert imu[f"{ax}gyro"][i] == pytest.approx(float(r[f"raw_gyro_{ax}"]) * 1000.0)
        assert imu[f"{ax}acc"][i] == pytest.approx(float(r[f"raw_accel_{ax}"]) / G * 1000.0)
    assert ds["current_distance"][i] == pytest.approx(float(r["raw_tof"]) * 100.0)
    assert ds["orientation"][i] == 25
    assert ds["min_distance"][i] == pytest.approx(1.0) and ds["max_distance"][i] == pytest.approx(300.0)


def test_recording_shape(xtest):
    rec, rows = xtest
    assert rec.source_format == "csv" and rec.profile_hint == "paper"
    assert {len(t) for t in rec.tables.values()} == {len(rows)} == {1834}  # README: 1834 rows
    rec_all = np.concatenate([t.record for t in rec.tables.values()])
    assert len(np.unique(rec_all)) == len(rec_all)  # unique, row-ordered
    assert_array_equal(rec.tables["OPTICAL_FLOW"].record // 3, np.arange(len(rows)))
    assert rec.t0_s == pytest.approx(float(rows[0]["timestamp_ms"]) / 1e3)
    assert any("never reached the log" in n for n in rec.notes)


def test_translation_sign_on_the_data(xtest):
    """README: the X test gives about +406 raw counts out and -405 back (its exact counting rule
    is not stated; plain sums over its time windows are within 10 %); through the paper's eq. 15
    with the mapped counts, forward motion must come out as positive body velocity."""
    rec, rows = xtest
    t = np.array([float(r["timestamp_ms"]) for r in rows]) / 1e3
    t -= t[0]
    raw_dx = np.array([float(r["raw_flow_dx"]) for r in rows])
    out = (t > 3.0) & (t < 9.0)
    back = (t > 9.0) & (t < 13.0)
    assert raw_dx[out].sum() == pytest.approx(406, rel=0.1)
    assert raw_dx[back].sum() == pytest.approx(-405, rel=0.1)
    of = rec.tables["OPTICAL_FLOW"]
    tof = rec.tables["DISTANCE_SENSOR"]["current_distance"] / 100.0
    vx, _ = velocity_from_flow(of["flow_x"] * Q_PAPER / 0.010, of["flow_y"] * Q_PAPER / 0.010, 0.0, 0.0, tof)
    assert np.sum(vx[out]) > 0 > np.sum(vx[back])


def test_load_recording_dispatches_csv_and_files_without_mag():
    rec = load_recording(STAMPFLY / "square_30cm.csv.gz", sensor_config=MAP)  # 37 columns, no raw_mag_*
    assert len(rec.tables["OPTICAL_FLOW"]) == 1833
    with pytest.raises(RecordingError, match="needs --sensor-config"):
        load_recording(XTEST)


# --- synthetic CSVs -----------------------------------------------------------------------------

HEADER = ["timestamp_ms", "gx", "gy", "gz", "tof_mm", "dx", "dy", "squal"]
SMALL_MAP = """
[sensor]
name = "test"
[time]
column = "timestamp_ms"
unit = "ms"
[gyro]
unit = "deg/s"
body_x = "-gy"
body_y = "+gx"
body_z = "+gz"
[flow]
paper_x = "+dy"
paper_y = "-dx"
quality_column = "squal"
read_period_ms = 10.0
repeated_readings = "keep"
[range]
column = "tof_mm"
unit = "mm"
min_m = 0.05
max_m = 4.0
held_values = "keep"
"""


def _write(tmp: Path, rows: list[list[object]], header: list[str] = HEADER, name: str = "log.csv") -> Path:
    p = tmp / name
    with p.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return p


def _map(tmp: Path, text: str = SMALL_MAP, name: str = "map.toml") -> Path:
    p = tmp / name
    p.write_text(text)
    return p


def test_axis_permutation_units_and_no_accel(tmp_path):
    p = _write(tmp_path, [[1000, 10.0, 20.0, 30.0, 250, 2, -3, 100], [1011, -5.0, 0.0, 1.0, 30, 0, 1, 90]])
    rec = read_csv(p, _map(tmp_path))
    imu, of, ds = rec.tables["RAW_IMU"], rec.tables["OPTICAL_FLOW"], rec.tables["DISTANCE_SENSOR"]
    d2r = np.pi / 180.0
    assert_allclose(imu["xgyro"], [-20.0 * d2r * 1e3, -0.0])
    assert_allclose(imu["ygyro"], [10.0 * d2r * 1e3, -5.0 * d2r * 1e3])
    assert_allclose(of["flow_x"], [-3, 1])
    assert_allclose(of["flow_y"], [-2, 0])
    assert_allclose(ds["current_distance"], [25.0, 3.0])
    assert np.all(np.isnan(imu["xacc"]))
    assert any("no [accel] section" in n for n in rec.notes)
    assert any("outside [0.05, 4.0] m" in n for n in rec.notes)  # 30 mm < min


def _one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and msg
    return msg


@pytest.mark.parametrize("edit, match", [
    (lambda s: s.replace('unit = "deg/s"', 'unit = "deg/s"\nscale = 2'), "unknown key"),
    (lambda s: s.replace('body_z = "+gz"\n', ""), "missing key.*body_z"),
    (lambda s: s.replace('"-gy"', '"gy"'), "signed column"),
    (lambda s: s.replace('unit = "deg/s"', 'unit = "rpm"'), "not one of"),
    (lambda s: s.replace("[sensor]", "[sensors]"), "unknown section"),
    (lambda s: s.replace('[range]\ncolumn = "tof_mm"\nunit = "mm"\nmin_m = 0.05\nmax_m = 4.0\nheld_values = "keep"\n',
                         ""), "missing section.*range"),
    (lambda s: s.replace('"+gz"', '"+gx"'), "same column"),
    (lambda s: s.replace("read_period_ms = 10.0", "read_period_ms = 0.0"), "read_period_ms"),
    (lambda s: s.replace("read_period_ms = 10.0", 'read_period_ms = "10"'), "expected a number"),
    (lambda s: s.replace('repeated_readings = "keep"', 'repeated_readings = "merge"'), "not one of"),
    (lambda s: s + "\n[[oops", "not valid TOML"),
])
def test_bad_column_map_is_one_config_error(tmp_path, edit, match):
    p = _write(tmp_path, [[1000, 0, 0, 0, 250, 0, 0, 100]])
    with pytest.raises(ConfigError, match=match) as exc:
        read_csv(p, _map(tmp_path, edit(SMALL_MAP)))
    _one_line(exc)


def test_missing_map_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_column_map(tmp_path / "nope.toml")


@pytest.mark.parametrize("rows, header, match", [
    ([[1000, 0, 0, 0, 250, 0, 0]], HEADER[:-1], r"column 'squal' \(flow.quality_column"),
    ([[1000, 0, 0, 0, 250, 0, 0, 100], [1011, 0, "abc", 0, 250, 0, 0, 100]], HEADER, "column 'gy', line 3: 'abc'"),
    ([[1000, 0, 0, 0, "nan", 0, 0, 100]], HEADER, "column 'tof_mm', line 2: 'nan' is not a finite"),
    ([[1000, 0, 0, 0, 250, 0, 0, 100, 7], [1011, 0, 0, 0, 250, 0, 0, 100]], HEADER, "line 2 has 9 fields"),
    ([[1000, 0, 0, 0, 250, 0, 0, 100], [990, 0, 0, 0, 250, 0, 0, 100]], HEADER, "goes backwards at line 3"),
    ([], HEADER, "no data rows"),
])
def test_bad_csv_is_one_recording_error(tmp_path, rows, header, match):
    p = _write(tmp_path, rows, header)
    with pytest.raises(RecordingError, match=match) as exc:
        read_csv(p, _map(tmp_path))
    _one_line(exc)


def test_empty_and_truncated_files(tmp_path):
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(RecordingError, match="empty CSV"):
        read_csv(empty, _map(tmp_path))
    p = _write(tmp_path, [[1000, 0, 0, 0, 250, 0, 0, 100], [1011, 0, 0, 0, 250, 0, 0, 100]])
    with p.open("a") as fh:
        fh.write("1022,0,0")  # logging cut off mid-line
    rec = read_csv(p, _map(tmp_path))
    assert len(rec.tables["OPTICAL_FLOW"]) == 2
    assert any("cut short" in n for n in rec.notes)


def _fast_rows(n_reads: int, phase_ms: float, rng: np.random.Generator) -> tuple[list[list[object]], int, int]:
    """Rows every 2-3 ms holding the latest of reads every 10 ms (read k at phase + 10 k):
    returns the rows, the number of rows that repeat a read, and the number of range changes."""
    t, rows, reads = 5000, [], []
    for _ in range(n_reads):
        reads.append((int(rng.integers(-3, 4)), int(rng.integers(-3, 4)), int(rng.integers(40, 200))))
    repeats = 0
    prev = None
    tof, changes, last_tof = 250, 0, None
    while True:
        k = int(np.floor((t - 5000 - phase_ms) / 10.0))
        if k >= n_reads:
            break
        if k >= 0:
            if t % 33 < 3:
                tof += 1
            dx, dy, q = reads[k]
            rows.append([t, 0.0, 0.0, 0.0, tof, dx, dy, q])
            repeats += int(prev == k)
            changes += int(last_tof is not None and tof != last_tof)
            prev, last_tof = k, tof
        t += int(rng.integers(2, 4))
    return rows, repeats, changes


def test_repeated_readings_found_and_dropped(tmp_path):
    rows, repeats, changes = _fast_rows(300, 6.0, np.random.default_rng(7))
    p = _write(tmp_path, rows)
    t = np.array([r[0] for r in rows], dtype=float) * 1e-3
    vals = np.array([r[5:8] for r in rows], dtype=float)
    grid = find_read_grid(t, vals, 0.010)
    assert grid.slot is not None and grid.agreement > 0.99
    assert grid.phase_s * 1e3 % 10 == pytest.approx(6.0, abs=1.0)  # reads at 5006, 5016, ...
    assert int(np.sum(np.diff(grid.slot) == 0)) == repeats
    keep = read_csv(p, _map(tmp_path))
    assert len(keep.tables["OPTICAL_FLOW"]) == len(rows)
    drop_map = SMALL_MAP.replace('repeated_readings = "keep"', 'repeated_readings = "drop"').replace(
        'held_values = "keep"', 'held_values = "drop"')
    drop = read_csv(p, _map(tmp_path, drop_map, "drop.toml"))
    assert len(drop.tables["OPTICAL_FLOW"]) == len(rows) - repeats == 300
    assert len(drop.tables["DISTANCE_SENSOR"]) == changes + 1
    assert len(drop.tables["RAW_IMU"]) == len(rows)
    assert any(f"{repeats} of {len(rows)} rows repeat" in n for n in drop.notes)


def test_slow_rows_are_distinct_readings():
    t = np.arange(0, 2000, 11) * 1e-3
    grid = find_read_grid(t, np.zeros((len(t), 3)), 0.010)
    assert grid.slot is None and "never closer" in grid.method


def test_shipped_map_loads_and_names_every_key():
    cmap = load_column_map(MAP)
    assert cmap.flow.read_period_ms == 10.0
    assert cmap.flow.paper_x == "-raw_flow_dx" and cmap.flow.paper_y == "-raw_flow_dy"
    assert cmap.accel is not None and cmap.range.unit == "m"


def test_a_copy_of_the_map_elsewhere_still_works(tmp_path):
    """The map holds no paths: a copy in another folder reads the same CSV."""
    shutil.copy(MAP, tmp_path / "copy.toml")
    rec = read_csv(XTEST, tmp_path / "copy.toml")
    assert len(rec.tables["RAW_IMU"]) == 1834



def test_replay_of_a_csv_uses_each_readings_own_10ms_span_and_keeps_every_row(tmp_path):
    """Rows are ~11 ms apart but each holds one 10 ms PMW3901 reading (data README): eq. 15 divides
    the counts by 10 ms, and identical consecutive readings 11 ms apart are distinct readings."""
    import subprocess
    import sys
    from pathlib import Path

    import numpy as np

    repo = Path(__file__).resolve().parent.parent
    src = repo / "data/real/stampfly/flow_test_x_axis_01.csv.gz"
    out = tmp_path / "x.csv"
    r = subprocess.run([sys.executable, "-m", "companion", "replay", str(src), "--sensor-config",
                        str(repo / "configs/sensors/stampfly.toml"), "--csv", str(out)],
                       capture_output=True, text=True, timeout=120, cwd=repo)
    assert r.returncode == 0, r.stderr
    d = np.genfromtxt(out, delimiter=",", names=True, dtype=None, encoding=None)
    with gzip.open(src, "rt") as fh:
        assert len(d) == sum(1 for _ in fh) - 1  # one output row per CSV row
    q = 0.09 / 57.3
    ok = np.isfinite(d["scene_rate_x_rad_s"])
    assert ok.sum() > 1000
    expected = d["flow_x_counts"][ok] * q / 0.010
    np.testing.assert_allclose(d["scene_rate_x_rad_s"][ok], expected, rtol=1e-8, atol=1e-12)  # the CSV keeps 9 digits
