"""Recordings read gzip-compressed (issue 14): ``.tlog.gz``, ``.bin.gz``/``.BIN.gz``, ``.ulg.gz``
and ``.csv.gz`` give exactly what the plain file gives (every table, every column, the notes and
the skip counts), through ``load_recording``, the readers, ``convert``, ``replay_live`` and the
command line; a truncated or corrupt gzip file is one line and exit code 4, never a traceback.

The plain files compared against are decompressed here with ``gzip`` (the in-repo recordings,
``data/``) or are the test fixtures (``tests/data/importers``) compressed here.
"""

from __future__ import annotations

import gzip
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.config import load_config
from companion.errors import ExitCode, RecordingError
from companion.recordings.importers.csv_columns import read_csv
from companion.recordings.importers.dataflash import read_dataflash
from companion.recordings.importers.ulog import read_ulog
from companion.recordings.load import (
    Recording,
    load_recording,
    read_recording_bytes,
    recording_name,
    recording_stem,
    recording_suffix,
)
from companion.recordings.tlog_reader import read_tlog
from companion.recordings.tlog_writer import TlogWriter
from companion.step.profiles import Profile
from companion.tools.convert import _records, convert_tlog
from companion.tools.replay import replay, replay_live

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "data"
FLIGHT_A = DATA / "sitl" / "ardupilot" / "flight_a.tlog.gz"
FLIGHT_C0_BIN = DATA / "sitl" / "ardupilot" / "flight_c0.BIN.gz"
STAMPFLY = DATA / "real" / "stampfly"
STAMPFLY_MAP = REPO / "configs" / "sensors" / "stampfly.toml"
FIXTURES = Path(__file__).parent / "data" / "importers"
#: every recording in data/ (the StampFly CSVs, flight A, and flights C0 and E1 as published)
STAMPFLY_FILES = ("flow_test_x_axis_01.csv", "flow_test_square_01_final.csv", "square01_13s.csv", "square_30cm.csv",
                  "square_30cm_air.csv", "static_final.csv", "test_400hz_result.csv")


def assert_same_recording(got: Recording, want: Recording) -> None:
    """Every table (in order), every column (dtype and values, NaN equal to NaN), the skip
    counts, notes, format and profile hint equal; only the path may differ."""
    assert (got.source_format, got.profile_hint) == (want.source_format, want.profile_hint)
    assert (got.skipped_bytes, got.skipped_packets, got.notes) == (want.skipped_bytes, want.skipped_packets,
                                                                  want.notes)
    assert list(got.tables) == list(want.tables)
    for name, w in want.tables.items():
        g = got.tables[name]
        assert g.name == w.name
        for attr in ("t_s", "sysid", "compid", "record"):
            a, b = getattr(g, attr), getattr(w, attr)
            assert a.dtype == b.dtype, (name, attr)
            np.testing.assert_array_equal(a, b, err_msg=f"{name}.{attr}")
        assert list(g.fields) == list(w.fields), name
        for field, b in w.fields.items():
            a = g.fields[field]
            assert a.dtype == b.dtype and a.shape == b.shape, (name, field)
            np.testing.assert_array_equal(a, b, err_msg=f"{name}.{field}")
    assert got.n_messages == want.n_messages > 0


def _gzip_copy(src: Path, dst: Path) -> Path:
    dst.write_bytes(gzip.compress(src.read_bytes(), mtime=0))
    return dst


def _gunzip_copy(src: Path, dst: Path) -> Path:
    dst.write_bytes(gzip.decompress(src.read_bytes()))
    return dst


def _truncated(src: Path, dst: Path) -> Path:
    """``src`` (gzip) cut in the middle of its compressed data."""
    data = src.read_bytes()
    dst.write_bytes(data[: len(data) // 2])
    return dst


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=180, check=False)


@pytest.fixture(scope="module")
def flight_a_gz() -> Recording:
    return read_tlog(FLIGHT_A)


@pytest.fixture(scope="module")
def flight_a_slice(tmp_path_factory, flight_a_plain) -> tuple[Path, Path]:
    """49-56 s of flight A (the take-over at 51.16 s) as a small plain .tlog and its .tlog.gz."""
    out = tmp_path_factory.mktemp("slice")
    plain = out / "slice.tlog"
    t0 = None
    with TlogWriter(plain) as w:
        for t_us, packet in _records(flight_a_plain.read_bytes(), "flight_a.tlog"):
            t0 = t_us if t0 is None else t0
            if 49e6 <= t_us - t0 <= 56e6:
                w.write_bytes(packet, t_us * 1e-6)
    return plain, _gzip_copy(plain, out / "slice.tlog.gz")


# --- names --------------------------------------------------------------------------------------


@pytest.mark.parametrize("path, name, suffix, stem", [
    ("a/flight_a.tlog.gz", "flight_a.tlog", ".tlog", "flight_a"),
    ("flight_c0.BIN.gz", "flight_c0.BIN", ".bin", "flight_c0"),
    ("LOG.ULG.GZ", "LOG.ULG", ".ulg", "LOG"),
    ("x.csv.Gz", "x.csv", ".csv", "x"),
    ("x.csv", "x.csv", ".csv", "x"),
    ("flight.tlog", "flight.tlog", ".tlog", "flight"),
    ("noext.gz", "noext", "", "noext"),
])
def test_names_look_through_a_trailing_gz(path, name, suffix, stem):
    assert (recording_name(path), recording_suffix(path), recording_stem(path)) == (name, suffix, stem)


# --- every format, compressed and plain ------------------------------------------------------------


def test_tlog_gz_reads_equal_to_the_plain_tlog(flight_a_gz, flight_a_plain):
    """flight A as shipped (.tlog.gz) against the same bytes decompressed: every table, every field."""
    plain = read_tlog(flight_a_plain)
    assert_same_recording(flight_a_gz, plain)
    assert flight_a_gz.n_messages == 90161 and len(flight_a_gz.tables) == len(plain.tables) > 20
    assert flight_a_gz.path == str(FLIGHT_A)
    assert_same_recording(load_recording(FLIGHT_A), plain)


def test_damaged_tlog_gz_reads_equal_to_the_damaged_plain_tlog(tmp_path, flight_a_slice):
    """Damage inside the compressed file's content is handled as in a plain file (same skips, notes)."""
    plain, _ = flight_a_slice
    data = bytearray(plain.read_bytes())
    for at in (1000, 5000, 5001, 20_000):
        data[at] ^= 0x5A
    data = data[:-7]  # a truncated last record too
    damaged = tmp_path / "damaged.tlog"
    damaged.write_bytes(bytes(data))
    want = read_tlog(damaged)
    assert want.skipped_packets > 0 and want.notes
    assert_same_recording(read_tlog(_gzip_copy(damaged, tmp_path / "damaged.tlog.gz")), want)


@pytest.mark.parametrize("name", STAMPFLY_FILES)
def test_csv_gz_reads_equal_to_the_plain_csv(tmp_path, name):
    plain = _gunzip_copy(STAMPFLY / f"{name}.gz", tmp_path / name)
    want = read_csv(plain, STAMPFLY_MAP)
    assert_same_recording(read_csv(STAMPFLY / f"{name}.gz", STAMPFLY_MAP), want)
    assert_same_recording(load_recording(STAMPFLY / f"{name}.gz", sensor_config=STAMPFLY_MAP), want)


def test_csv_gz_with_a_byte_order_mark_and_crlf_reads_equal_to_the_plain_csv(tmp_path):
    text = gzip.decompress((STAMPFLY / "static_final.csv.gz").read_bytes()).decode()
    lines = text.splitlines()[:200]
    plain = tmp_path / "bom.csv"
    plain.write_bytes(b"\xef\xbb\xbf" + "\r\n".join(lines).encode() + b"\r\n")
    want = read_csv(plain, STAMPFLY_MAP)
    assert len(want.tables["OPTICAL_FLOW"]) == 199
    assert_same_recording(read_csv(_gzip_copy(plain, tmp_path / "bom.CSV.GZ"), STAMPFLY_MAP), want)


def test_dataflash_gz_reads_equal_to_the_plain_bin(tmp_path):
    want = read_dataflash(FIXTURES / "copter_flow.bin")
    gz = _gzip_copy(FIXTURES / "copter_flow.bin", tmp_path / "copter_flow.BIN.GZ")
    assert_same_recording(read_dataflash(gz), want)
    assert_same_recording(load_recording(gz), want)


def test_flight_c0_dataflash_as_shipped_reads_equal_to_the_plain_bin(tmp_path):
    """ArduCopter's own 15 MB DataFlash log of flight C0, kept as published (.BIN.gz)."""
    want = read_dataflash(_gunzip_copy(FLIGHT_C0_BIN, tmp_path / "flight_c0.BIN"))
    got = load_recording(FLIGHT_C0_BIN)
    assert_same_recording(got, want)
    assert got.source_format == "dataflash" and len(got.tables["OPTICAL_FLOW"]) > 5000


def test_ulog_gz_reads_equal_to_the_plain_ulg(tmp_path):
    want = read_ulog(FIXTURES / "px4_flow.ulg")
    gz = _gzip_copy(FIXTURES / "px4_flow.ulg", tmp_path / "px4_flow.ulg.gz")
    assert_same_recording(read_ulog(gz), want)
    assert_same_recording(load_recording(gz), want)


def test_every_recording_in_data_reads(tmp_path):
    """Each compressed recording the repository ships is read straight from its .gz."""
    tlogs = sorted((DATA / "sitl" / "ardupilot").glob("*.tlog.gz"))
    assert [p.name for p in tlogs] == ["flight_a.tlog.gz", "flight_c0_companion.tlog.gz", "flight_c0_gcs.tlog.gz",
                                       "flight_e1_companion.tlog.gz", "flight_e1_gcs.tlog.gz"]
    for p in tlogs[1:]:  # flight A: above
        rec = load_recording(p)
        assert rec.source_format == "tlog" and rec.n_messages > 50_000 and rec.skipped_packets == 0, p.name
        assert "OPTICAL_FLOW" in rec, p.name


# --- the tools on .gz -----------------------------------------------------------------------------


def test_convert_of_a_tlog_gz_equals_the_plain_conversion(tmp_path, flight_a_slice):
    plain, gz = flight_a_slice
    cfg = load_config()
    n_plain = convert_tlog(plain, tmp_path / "from_plain.tlog", src=Profile.ARDUPILOT, dst=Profile.PAPER, cfg=cfg)
    n_gz = convert_tlog(gz, tmp_path / "from_gz.tlog", src=Profile.ARDUPILOT, dst=Profile.PAPER, cfg=cfg)
    assert n_plain == n_gz > 300
    assert (tmp_path / "from_gz.tlog").read_bytes() == (tmp_path / "from_plain.tlog").read_bytes()


def test_replay_live_of_a_tlog_gz_equals_the_plain_one(flight_a_slice, paper_cfg):
    plain, gz = flight_a_slice
    want = replay_live(plain, paper_cfg, Profile.ARDUPILOT)
    got = replay_live(gz, paper_cfg, Profile.ARDUPILOT)
    assert len(got) == len(want) > 300
    for col in ("vx_m_s", "vy_m_s", "roll_cmd_rad", "pitch_cmd_rad", "dt_s"):
        np.testing.assert_array_equal([getattr(o, col) for o in got], [getattr(o, col) for o in want], err_msg=col)
    res = replay(load_recording(gz), paper_cfg, Profile.ARDUPILOT)  # and the column replay agrees with it
    np.testing.assert_array_equal(res["vx_m_s"], [o.vx_m_s for o in got])


def test_cli_replay_of_a_tlog_gz_writes_the_same_csv_as_the_plain_one(tmp_path, flight_a_slice):
    plain, gz = flight_a_slice
    for src, out in ((plain, "plain.csv"), (gz, "gz.csv")):
        r = _cli("replay", str(src), "--profile", "ardupilot", "--csv", str(tmp_path / out))
        assert r.returncode == 0, r.stderr
    text = (tmp_path / "gz.csv").read_text()
    assert text == (tmp_path / "plain.csv").read_text() and text.count("\n") > 300


def test_cli_info_reads_every_compressed_format(tmp_path):
    ulg = _gzip_copy(FIXTURES / "px4_flow.ulg", tmp_path / "px4_flow.ulg.gz")
    for args, fmt in (((str(FLIGHT_A),), "tlog"), ((str(FLIGHT_C0_BIN),), "dataflash"), ((str(ulg),), "ulog"),
                      ((str(STAMPFLY / "static_final.csv.gz"), "--sensor-config", str(STAMPFLY_MAP)), "csv")):
        r = _cli("info", *args)
        assert r.returncode == 0, r.stderr
        assert f"format    {fmt}" in r.stdout, r.stdout


# --- damaged gzip files -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def compressed(tmp_path_factory, flight_a_slice) -> dict[str, Path]:
    """One small gzip file per format (name -> path)."""
    out = tmp_path_factory.mktemp("gz")
    return {
        "tlog": flight_a_slice[1],
        "bin": _gzip_copy(FIXTURES / "copter_flow.bin", out / "copter_flow.bin.gz"),
        "ulg": _gzip_copy(FIXTURES / "px4_flow.ulg", out / "px4_flow.ulg.gz"),
        "csv": shutil.copy(STAMPFLY / "static_final.csv.gz", out / "static_final.csv.gz"),
    }


def _load(path: Path) -> Recording:
    return load_recording(path, sensor_config=STAMPFLY_MAP if recording_suffix(path) == ".csv" else None)


@pytest.mark.parametrize("fmt", ["tlog", "bin", "ulg", "csv"])
def test_truncated_gz_is_a_clear_error(tmp_path, compressed, fmt):
    src = compressed[fmt]
    bad = _truncated(src, tmp_path / src.name)
    with pytest.raises(RecordingError, match=rf"^{bad.name}: truncated gzip file \(the compressed data end "
                                             r"early\): cannot decompress it$"):
        _load(bad)
    args = ["info", str(bad)] + (["--sensor-config", str(STAMPFLY_MAP)] if fmt == "csv" else [])
    r = _cli(*args)
    assert r.returncode == ExitCode.BAD_INPUT
    assert r.stderr == f"error: {bad.name}: truncated gzip file (the compressed data end early): cannot decompress it\n"
    assert r.stdout == ""


@pytest.mark.parametrize("fmt", ["tlog", "bin", "ulg", "csv"])
def test_corrupt_gz_is_a_clear_error(tmp_path, compressed, fmt):
    """A flipped byte in the compressed data (the CRC or the deflate stream catches it)."""
    src = compressed[fmt]
    data = bytearray(src.read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad = tmp_path / src.name
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match=rf"^{bad.name}: corrupt gzip file \(.+\): cannot decompress it$"):
        _load(bad)


def test_a_gz_name_on_a_file_that_is_not_gzip_is_a_clear_error(tmp_path):
    bad = tmp_path / "renamed.tlog.gz"
    shutil.copy(FIXTURES / "copter_flow.bin", bad)
    with pytest.raises(RecordingError, match=r"^renamed.tlog.gz: corrupt gzip file \(Not a gzipped file .*\): "):
        load_recording(bad)
    r = _cli("replay", str(bad), "--csv", str(tmp_path / "x.csv"))
    assert r.returncode == ExitCode.BAD_INPUT and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert not (tmp_path / "x.csv").exists()


def test_missing_gz_is_not_found(tmp_path):
    for name in ("gone.tlog.gz", "gone.bin.gz", "gone.ulg.gz"):
        with pytest.raises(RecordingError, match="^recording not found: "):
            load_recording(tmp_path / name)
    with pytest.raises(RecordingError, match="^recording not found: "):
        read_recording_bytes(tmp_path / "gone.csv.gz")
    with pytest.raises(RecordingError, match="^recording not found: "):
        read_csv(tmp_path / "gone.csv.gz", STAMPFLY_MAP)


def test_empty_gz_content_is_the_format_s_own_error(tmp_path):
    """A valid gzip of nothing: each reader says its file is empty, as for an empty plain file."""
    for name, match in (("e.tlog.gz", "no MAVLink packets found in"), ("e.bin.gz", "empty file, not a DataFlash log"),
                        ("e.ulg.gz", "not a PX4 ULog file"), ("e.csv.gz", "empty CSV file")):
        p = tmp_path / name
        p.write_bytes(gzip.compress(b""))
        with pytest.raises(RecordingError, match=match):
            _load(p)
