"""The compiled kernels (companion/native/kernels.c) equal the numpy formulations they copy
(issue 17): the reader's CRC against pymavlink's x25crc on every message type and every packet
kind, the reader's scan and decoding against the numpy path on clean, damaged and odd files, and
the CSV writer against Python's ``%`` operator.

Each comparison runs the same call twice, with the kernels and with ``FLOWHOLD_NATIVE=0`` (the
numpy path). Skipped only where the kernels cannot be built (no C compiler).
"""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil
from test_tlog_reader import FLIGHT_A, PROJECT_MESSAGES, Built, _write, build_all_types

from companion import native
from companion.recordings.load import Recording
from companion.recordings.tlog_reader import crc16_mcrf4xx, layout_of, read_tlog

lib = native.kernels()
pytestmark = pytest.mark.skipif(lib is None, reason="no C compiler: the numpy path is the only one")


def _damaged_flight_a(path: Path, *, seed: int, n: int, every: int, xor: int) -> Path:
    """flight_a with ``n`` bytes damaged at random (seeded): a start-of-packet byte (0xFD) where
    the position is not a multiple of ``every``, the byte XOR ``xor`` where it is."""
    rng = np.random.default_rng(seed)
    data = bytearray(gzip.decompress(FLIGHT_A.read_bytes()))
    for pos in rng.choice(len(data), size=n, replace=False):
        data[pos] = 0xFD if pos % every else data[pos] ^ xor
    path.write_bytes(bytes(data))
    return path


def test_the_library_is_built_from_this_source():
    assert native.library_path().is_file()
    assert native.library_path().parent == native.cache_dir()
    assert lib.fh_version() == native.VERSION


def test_disabled_by_the_environment(monkeypatch):
    monkeypatch.setenv("FLOWHOLD_NATIVE", "0")
    assert native.kernels() is None
    monkeypatch.delenv("FLOWHOLD_NATIVE")
    assert native.kernels() is lib


def test_no_compiler_means_the_numpy_path(monkeypatch, tmp_path):
    """A failed build leaves ``kernels()`` None (the callers' numpy path), no error."""
    monkeypatch.setenv("FLOWHOLD_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    monkeypatch.setattr(native.tempfile, "gettempdir", lambda: str(tmp_path / "tmp"))
    native._kernels.cache_clear()
    try:
        assert native.kernels() is None
    finally:
        native._kernels.cache_clear()
    monkeypatch.undo()
    assert native.kernels() is not None


# ---------------------------------------------------------------------------------------------
# CRC


@pytest.fixture(scope="module")
def all_types(tmp_path_factory: pytest.TempPathFactory) -> Built:
    return build_all_types(tmp_path_factory.mktemp("native") / "all.tlog", np.random.default_rng(11), per_type=8)


def test_crc_of_every_packet_equals_pymavlink_x25(all_types):
    """Every packet of every project message type, MAVLink 1 and 2, signed or not: the kernel's
    CRC (16-byte blocks with leading zeros) is pymavlink's x25crc with the message's crc_extra."""
    kinds = set()
    for pkt in all_types.packets:
        buf = np.frombuffer(b"\x00" * 32 + pkt, dtype=np.uint8)
        v2 = pkt[0] == 0xFD
        hdr = 10 if v2 else 6
        msgid = int.from_bytes(pkt[7:10], "little") if v2 else pkt[5]
        covered = hdr - 1 + pkt[1]
        extra = layout_of(msgid).crc_extra
        want = mavutil.mavlink.x25crc(pkt[1:1 + covered])
        want.accumulate(bytes([extra]))
        assert want.crc == int.from_bytes(pkt[1 + covered:3 + covered], "little")
        for base in (0, 31):  # with and without room before the packet for the leading zeros
            got = lib.fh_crc_packet(buf.ctypes.data + base, buf.ctypes.data + 33, covered, extra)
            assert got == want.crc
        kinds.add((v2, bool(v2 and pkt[2] & 1), layout_of(msgid).name))
    assert {k[2] for k in kinds} == set(PROJECT_MESSAGES)
    assert {(v2, signed) for v2, signed, _ in kinds} == {(False, False), (True, False), (True, True)}


@pytest.mark.parametrize("length", list(range(0, 40)) + [63, 64, 65, 254, 255, 264, 300, 400])
def test_crc_any_length_and_corrupted_bytes(length):
    """Any length (one block, several, over the block table's reach), any offset, and every
    single-bit corruption of a packet: the kernel and the scalar reference agree, and a
    corrupted packet's CRC differs from the stored one (CRC-16 catches every one-bit error)."""
    rng = np.random.default_rng(length)
    data = rng.integers(0, 256, size=length + 64, dtype=np.uint8)
    for off in (0, 1, 7, 16, 20):
        extra = int(rng.integers(0, 256))
        ref = crc16_mcrf4xx(data[off:off + length].tobytes() + bytes([extra]))
        assert lib.fh_crc_packet(data.ctypes.data, data.ctypes.data + off, length, extra) == ref
        assert lib.fh_crc16(data.ctypes.data + off, length) == crc16_mcrf4xx(data[off:off + length].tobytes())
    if 0 < length <= 64:
        base = lib.fh_crc_packet(data.ctypes.data, data.ctypes.data + 20, length, 50)
        for bit in range(8 * length):
            bad = data.copy()
            bad[20 + bit // 8] ^= 1 << (bit % 8)
            got = lib.fh_crc_packet(bad.ctypes.data, bad.ctypes.data + 20, length, 50)
            assert got == crc16_mcrf4xx(bad[20:20 + length].tobytes() + bytes([50]))
            assert got != base


# ---------------------------------------------------------------------------------------------
# The reader


def _both(path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Recording, Recording]:
    fast = read_tlog(path)
    monkeypatch.setenv("FLOWHOLD_NATIVE", "0")
    slow = read_tlog(path)
    monkeypatch.delenv("FLOWHOLD_NATIVE")
    return fast, slow


def _same_column(a: np.ndarray, b: np.ndarray) -> bool:
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype == object:
        return a.tolist() == b.tolist()
    return a.tobytes() == b.tobytes()  # bit for bit: NaN payloads, signed zeros


def assert_same_recording(fast: Recording, slow: Recording) -> None:
    assert list(fast.tables) == list(slow.tables)  # the same types, in order of first appearance
    for name, tab in fast.tables.items():
        other = slow.tables[name]
        for attr in ("t_s", "sysid", "compid", "record"):
            assert _same_column(getattr(tab, attr), getattr(other, attr)), (name, attr)
        assert list(tab.fields) == list(other.fields), name
        for f, col in tab.fields.items():
            assert _same_column(col, other.fields[f]), (name, f)
    assert (fast.skipped_bytes, fast.skipped_packets, fast.notes) == (slow.skipped_bytes, slow.skipped_packets,
                                                                      slow.notes)


def test_reader_equals_numpy_path_on_every_packet_kind(all_types, monkeypatch):
    assert_same_recording(*_both(all_types.path, monkeypatch))


def test_reader_equals_numpy_path_on_flight_a(tmp_path, monkeypatch):
    plain = tmp_path / "flight_a.tlog"
    plain.write_bytes(gzip.decompress(FLIGHT_A.read_bytes()))
    fast, slow = _both(plain, monkeypatch)
    assert fast.n_messages > 80_000
    assert_same_recording(fast, slow)


def _edits(data: bytes, rng: np.random.Generator, n: int) -> bytes:
    """``n`` random edits: bit flips, garbage inserted (with STX bytes), bytes deleted, a run
    overwritten with copies of a packet's start (candidates that almost chain)."""
    out = bytearray(data)
    for _ in range(n):
        pos = int(rng.integers(0, len(out)))
        kind = int(rng.integers(0, 4))
        if kind == 0:
            out[pos] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:
            junk = rng.integers(0, 256, size=int(rng.integers(1, 80)), dtype=np.uint8)
            junk[rng.random(len(junk)) < 0.2] = 0xFD
            out[pos:pos] = junk.tobytes()
        elif kind == 2:
            del out[pos:pos + int(rng.integers(1, 60))]
        else:
            src = int(rng.integers(0, len(out) - 40))
            out[pos:pos + 20] = out[src:src + 20]
    return bytes(out)


@pytest.mark.parametrize("seed", range(12))
def test_reader_equals_numpy_path_on_damaged_files(all_types, tmp_path, monkeypatch, seed):
    """Bit flips, insertions, deletions, overwrites, a truncated end, garbage at the start: the
    same packets, the same damage counts and notes (passes 2 and 3 see the same candidates)."""
    rng = np.random.default_rng(seed)
    data = all_types.path.read_bytes()
    damaged = _edits(data, rng, n=[1, 5, 40][seed % 3])
    if seed % 4 == 1:
        damaged = damaged[:-int(rng.integers(1, 30))]
    if seed % 4 == 2:
        damaged = rng.integers(0, 256, size=50, dtype=np.uint8).tobytes() + damaged
    path = tmp_path / f"damaged_{seed}.tlog"
    path.write_bytes(damaged)
    fast, slow = _both(path, monkeypatch)
    assert_same_recording(fast, slow)


def test_reader_equals_numpy_path_on_unknown_ids_and_tiny_files(tmp_path, monkeypatch):
    """Packets of ids the dialect does not know, a one-packet file, a packet right at the start."""
    built = build_all_types(tmp_path / "few.tlog", np.random.default_rng(5), per_type=1)
    unknown = bytearray(built.packets[0])
    if unknown[0] == 0xFD:
        unknown[7:10] = (12345).to_bytes(3, "little")
    else:
        unknown[5] = 0xFF if layout_of(255) is None else unknown[5]
    packets = [built.packets[1], bytes(unknown), built.packets[2], built.packets[3]]
    cases = {"unknown": _write(tmp_path / "unknown.tlog", packets, built.t_us[:4]).path,
             "one": _write(tmp_path / "one.tlog", packets[:1], built.t_us[:1]).path}
    for path in cases.values():
        assert_same_recording(*_both(path, monkeypatch))


def test_reader_equals_numpy_path_over_scan_chunks(tmp_path, monkeypatch):
    """Over the scan's 8 MiB chunks (the kernel's resume point) and the file mapping: flight_a
    twice over, 10.7 MB, with a few flipped bits in each chunk."""
    data = bytearray(gzip.decompress(FLIGHT_A.read_bytes()) * 2)
    assert len(data) > 1 << 23
    rng = np.random.default_rng(8)
    for pos in rng.choice(len(data), size=30, replace=False):
        data[pos] ^= 1 << int(rng.integers(0, 8))
    path = tmp_path / "twice.tlog"
    path.write_bytes(bytes(data))
    fast, slow = _both(path, monkeypatch)
    assert fast.skipped_packets > 0
    assert_same_recording(fast, slow)


def test_scan_without_sse2_equals_the_sse2_scan(tmp_path):
    """The portable scan for candidate bytes (64-bit words, for machines without SSE2) finds
    what the SSE2 one finds: the same pass 1 on flight_a with bit flips and inserted 0xFD bytes."""
    import ctypes
    import subprocess

    from companion.recordings import tlog_reader as tr

    so = tmp_path / "portable.so"
    subprocess.run([*native._compiler(), *native._FLAGS, "-DFH_NO_SSE2", "-o", str(so), str(native.SOURCE), "-lm"],
                   check=True, capture_output=True)
    portable = ctypes.CDLL(str(so))
    native._declare(portable)
    portable.fh_init()
    path = _damaged_flight_a(tmp_path / "edited.tlog", seed=21, n=200, every=3, xor=0x40)
    buf, n = tr._load(path)
    runs = [tr._pass1_native(k, buf, n, tr._Progress(False, "")) for k in (lib, portable)]
    (good_a, other_a), (good_b, other_b) = runs
    for f in tr._Packets._FIELDS:
        np.testing.assert_array_equal(np.concatenate([getattr(p, f) for p in good_a]),
                                      np.concatenate([getattr(p, f) for p in good_b]))
    np.testing.assert_array_equal(np.concatenate(other_a), np.concatenate(other_b))
    assert sum(len(p.s) for p in good_a) > 80_000 and sum(len(o) for o in other_a) > 100


@pytest.mark.parametrize("n_threads", [1, 2, 3])
def test_reader_in_threads_equals_numpy_path(tmp_path, monkeypatch, n_threads):
    """The scan in 64 KiB pieces and the decoding in packet ranges, on 1-3 threads (each piece
    and range by the same kernel call as in one thread), on flight_a with damage in many pieces:
    the numpy path's recording."""
    from companion.recordings import tlog_reader as tr

    path = _damaged_flight_a(tmp_path / "damaged.tlog", seed=13, n=60, every=2, xor=0x10)
    monkeypatch.setattr(tr, "_SCAN_CHUNK", 1 << 16)
    monkeypatch.setattr(tr, "_PARALLEL_MIN_PACKETS", 0)
    monkeypatch.setattr(tr, "_PARALLEL_MIN_BYTES", 0)
    monkeypatch.setattr(native, "threads", lambda: n_threads)
    fast, slow = _both(path, monkeypatch)
    assert fast.skipped_packets > 0 and path.stat().st_size > 40 * (1 << 16)
    assert_same_recording(fast, slow)


def test_chain_count_is_the_scans_count_on_a_whole_file(tmp_path, monkeypatch):
    """``fh_count`` (the record chain followed, no CRC) gives each range the number of good
    packets ``fh_scan`` finds in it on a file whose records are whole, at any cut: the threads of
    the scan then write straight into their rows of one set of arrays (no copy), and the reader
    still equals the numpy path. On a damaged file the count is only a hint: the reader joins the
    ranges by a copy and equals the numpy path too (test_reader_in_threads_equals_numpy_path)."""
    from companion.recordings import tlog_reader as tr

    path = tmp_path / "flight_a.tlog"
    path.write_bytes(gzip.decompress(FLIGHT_A.read_bytes()))
    buf, n = tr._load(path)
    known = tr._crc_extra_lookup()[0].view(np.uint8)
    good, _ = tr._pass1_native(lib, buf, n, tr._Progress(False, ""))
    total = sum(len(p.s) for p in good)
    assert total > 80_000
    starts = np.concatenate([p.s for p in good])
    rng = np.random.default_rng(3)
    for cuts in ([8, n], [8, *sorted(rng.integers(9, n, size=4).tolist()), n]):
        counts = [lib.fh_count(buf.ctypes.data, n, a, b, known.ctypes.data, len(known))
                  for a, b in zip(cuts, cuts[1:], strict=False)]
        # the packets whose first byte lies in each range
        assert counts == np.diff(np.searchsorted(starts, cuts)).tolist()
    concatenated = []
    concatenate = np.concatenate
    monkeypatch.setattr(np, "concatenate", lambda *a, **k: concatenated.append(1) or concatenate(*a, **k))
    monkeypatch.setattr(tr, "_PARALLEL_MIN_BYTES", 0)
    monkeypatch.setattr(native, "threads", lambda: 3)
    good3, _ = tr._pass1_native(lib, buf, n, tr._Progress(False, ""))
    monkeypatch.undo()
    assert len(good3) == 1 and not concatenated  # one set of arrays, none copied
    for f in tr._Packets._FIELDS:
        np.testing.assert_array_equal(getattr(good3[0], f), np.concatenate([getattr(p, f) for p in good]))


def test_run_all_keeps_the_order_and_raises_the_first_error():
    import threading
    import time

    seen = set()

    def task(i: int) -> int:
        seen.add(threading.get_ident())
        time.sleep(0.001 * (i % 3))  # finished out of order
        return i * i

    tasks = [lambda i=i: task(i) for i in range(20)]
    assert native.run_all(tasks, 3) == [i * i for i in range(20)]
    assert len(seen) > 1
    assert native.run_all(tasks, 1) == [i * i for i in range(20)]

    def bad() -> int:
        raise ValueError("task 5")

    with pytest.raises(ValueError, match="task 5"):
        native.run_all([*tasks[:5], bad, *tasks[6:]], 2)


def test_threads_follow_the_cpus_allowed(monkeypatch):
    import os

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    assert native.threads() == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(64)))
    assert native.threads() == native.MAX_THREADS


@pytest.mark.parametrize("dtype", [np.int64, np.float64])
@pytest.mark.parametrize("side", ["left", "right"])
def test_searchsorted_equals_numpy(dtype, side):
    """The compiled search on sorted arrays: sorted queries (the galloping merge), unsorted ones,
    duplicates, values outside the array, floats with NaN and infinities (numpy's order: NaN
    last), empty arrays."""
    rng = np.random.default_rng(9)
    for n, m in ((0, 2000), (1, 2000), (5000, 3000), (3000, 20000), (20000, 1500)):
        a = np.sort(rng.integers(-50, 50, n) if dtype is np.int64 else
                    np.concatenate([rng.normal(size=n - n // 10), rng.integers(-3, 3, n // 10).astype(float)]))
        if dtype is np.float64 and n > 10:
            a = np.sort(np.concatenate([a[:-5], [np.nan, np.nan, np.inf, -np.inf, -0.0]]))
        a = a.astype(dtype)
        v = (rng.integers(-60, 60, m) if dtype is np.int64 else rng.normal(size=m) * 1.2).astype(dtype)
        if dtype is np.float64:
            v[::97] = np.nan
            v[::89] = a[0] if n else 0.0
        for q in (np.sort(v), v, np.sort(v)[::-1], np.repeat(np.sort(v)[:m // 3], 3)):
            got = native.searchsorted(a, q, side)
            assert got.dtype == np.int64
            np.testing.assert_array_equal(got, np.searchsorted(a, q, side=side))
    assert native.searchsorted(np.arange(3), np.array([1]), side).tolist() == np.searchsorted(
        np.arange(3), [1], side=side).tolist()  # short: numpy's own call


def test_wind_scan_equals_numpy(monkeypatch):
    """The wind search's compiled scan against ``_scan_gains`` and numpy's argmax, replicate by
    replicate: random residuals and weights (windows of no weight, windows too short), ties
    (a residual of zeros: every allowed gain 0, the first one wins), no window allowed at all (gain
    -1 at index 0), and one pooled window."""
    from companion.diagnose.closed_loop import wind

    rng = np.random.default_rng(4)
    cases = []
    for m in (1, 2, 7, 40, 161):
        t = np.cumsum(rng.uniform(0.5, 1.5, m + 1))
        b0, b1 = t[:-1], t[1:]
        for wp in (np.ones(m), rng.integers(0, 3, m).astype(float), np.zeros(m)):
            for min_s in (0.0, 4.0, 1e9):
                ep = rng.normal(size=(5, 2, m)) * rng.uniform(0.1, 3.0)
                ep[0] = 0.0
                cases.append((wind._cumulative(ep), wp, b0, b1, min_s))
    for ce, wp, b0, b1, min_s in cases:
        got = wind._best_windows(ce, wp, b0, b1, min_s)
        monkeypatch.setenv("FLOWHOLD_NATIVE", "0")
        want = wind._best_windows(ce, wp, b0, b1, min_s)
        monkeypatch.delenv("FLOWHOLD_NATIVE")
        np.testing.assert_array_equal(got[1], want[1])
        np.testing.assert_array_equal(got[0], want[0])
        grid = wind._ScanGrid(wp, b0, b1, min_s)
        for r in range(len(ce)):  # the numpy path is _scan_gains's maximum and numpy's argmax
            g = wind._scan_gains(ce[r], grid)
            assert want[1][r] == np.argmax(g) and want[0][r] == g.max()
    gains = [wind._best_windows(*c)[0] for c in cases]
    assert any(np.all(g == -1.0) for g in gains) and any(g[0] == 0.0 and np.all(g[1:] > 0) for g in gains)


@pytest.mark.parametrize("delay_s", [0.0, 0.013, -0.021, 0.02, 0.3, -0.5])
def test_shift_and_odometry_changes_equal_numpy(monkeypatch, delay_s):
    """The flow model's whole-flight Hermite shift (``fh_hermite_shift``) and the force channel's
    odometry pieces (``fh_odometry_changes``) against numpy's ``_shifted`` and
    ``_odometry_changes``, to the bit: a flight of several segments with jittered frame times,
    delays between frames, of a whole frame, and past a segment's ends (held there); the pieces
    of the shifted scene angle and of the four rotation rows."""
    from companion.diagnose.closed_loop.channels import FlightData
    from companion.diagnose.closed_loop.flowmodel import FlowProblem

    rng = np.random.default_rng(11)
    n = 1500
    t = np.cumsum(rng.uniform(0.019, 0.021, n))
    seg = np.repeat([0, 1, 2], [400, 700, 400])
    z = np.zeros(n)
    cols = dict(t_s=t, dt_s=np.r_[0.02, np.diff(t)], seg=seg, dphi_x_rad=rng.normal(0, 1e-3, n),
                dphi_y_rad=rng.normal(0, 1e-3, n), gyro_x_rad_s=z, gyro_y_rad_s=z,
                range_m=1.2 + 0.3 * np.sin(t), roll_rad=0.05 * np.sin(2 * t), pitch_rad=0.04 * np.cos(3 * t),
                yaw_rad=z, roll_cmd_rad=z, pitch_cmd_rad=z, vx_set_m_s=z * np.nan, vy_set_m_s=z * np.nan,
                truth_vx_m_s=z * np.nan, truth_vy_m_s=z * np.nan)
    data = FlightData(path="synthetic", profile="paper", profile_reason="test", frame_s=0.02,
                      command_source="test", **cols)
    fp = FlowProblem(data, mass_kg=1.0, gravity_m_s2=9.81)
    assert len(fp.force.idx) > 20
    rows = np.concatenate([fp.R, fp.RA])

    def run():
        shifted = fp._shifted(fp.Phi, fp._dPhi, -delay_s)
        return shifted, fp._odometry_changes(shifted), fp._odometry_changes(rows)

    got = run()
    monkeypatch.setenv("FLOWHOLD_NATIVE", "0")
    want = run()
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
        assert np.all(np.isfinite(w)) and np.abs(w).max() > 0
    if delay_s:  # the shift moves the scene angle (a test that compared the unshifted twice would pass too)
        assert np.abs(want[0] - fp.Phi).max() > 1e-6


@pytest.mark.parametrize("omega_p, zeta", [(5.4, 0.71), (2.0, 1.6), (30.0, 0.3)])
def test_free_rate_equals_numpy(monkeypatch, omega_p, zeta):
    """The attitude segments' start-rate fit (``fh_free_rate``) against numpy's bincounts in
    ``AttitudeProblem._free_rate``, to the bit: hundreds of segments after lost commands, a long
    one cut at the free response's length and short ones, NaN in the residual, with and without a
    fit mask (one that leaves a segment only its first frame: no start rate fitted)."""
    from companion.diagnose.closed_loop.attitude import AttitudeProblem
    from companion.diagnose.closed_loop.channels import FlightData

    rng = np.random.default_rng(3)
    n = 6000
    t = np.arange(n) * 0.02
    z = np.zeros(n)
    cmd_rec = rng.random(n) > 0.08
    cmd_rec[:3000] = True  # one long segment
    u = np.repeat(rng.uniform(-0.1, 0.1, n // 20), 20)
    y = 0.8 * u + rng.normal(0, 1e-3, n)
    data = FlightData(path="synthetic", profile="paper", profile_reason="test", frame_s=0.02, command_source="test",
                      t_s=t, dt_s=np.r_[0.02, np.diff(t)], seg=np.zeros(n, dtype=int), dphi_x_rad=z, dphi_y_rad=z,
                      gyro_x_rad_s=rng.normal(0, 0.05, n), gyro_y_rad_s=rng.normal(0, 0.05, n), range_m=np.ones(n),
                      roll_rad=y, pitch_rad=-y, yaw_rad=z, roll_cmd_rad=u, pitch_cmd_rad=-u, vx_set_m_s=z * np.nan,
                      vy_set_m_s=z * np.nan, truth_vx_m_s=z * np.nan, truth_vy_m_s=z * np.nan, cmd_rec=cmd_rec)
    ap = AttitudeProblem(data)
    assert len(ap.segments) > 200
    e = ap.y - ap.simulate(omega_p, zeta, 0.01)
    e[0, rng.choice(n, 50, replace=False)] = np.nan
    mask = rng.random(n) > 0.1
    a1, b1 = ap.segments[5]
    mask[a1 + 1:b1] = False  # this segment's fitted frames: its first only
    for fit_mask in (None, mask):
        got = ap._free_rate(e, omega_p, zeta, fit_mask)
        monkeypatch.setenv("FLOWHOLD_NATIVE", "0")
        want = ap._free_rate(e, omega_p, zeta, fit_mask)
        monkeypatch.delenv("FLOWHOLD_NATIVE")
        np.testing.assert_array_equal(got, want)
        assert np.nanmax(np.abs(want - e)) > 1e-6  # start rates were fitted out


def test_form_drag_regressor_equals_numpy(monkeypatch):
    """The force channel's form-drag regressor (``fh_form_drag``) against numpy's
    ``_FormDrag._form_drag_regressor``, to the bit: segments long and too short for the rate's
    span (rate 0 there), jittered frame times, an odometry of several geometries."""
    from companion.diagnose.closed_loop.channels import FlightData
    from companion.diagnose.closed_loop.flowmodel import IDX, NOMINAL, FlowProblem, _FormDrag

    rng = np.random.default_rng(13)
    n = 2000
    t = np.cumsum(rng.uniform(0.019, 0.021, n))
    seg = np.repeat([0, 1, 2, 3], [700, 9, 891, 400])  # the second too short for +-h frames
    z = np.zeros(n)
    data = FlightData(path="synthetic", profile="paper", profile_reason="test", frame_s=0.02, command_source="test",
                      t_s=t, dt_s=np.r_[0.02, np.diff(t)], seg=seg, dphi_x_rad=rng.normal(0, 2e-3, n),
                      dphi_y_rad=rng.normal(0, 2e-3, n), gyro_x_rad_s=z, gyro_y_rad_s=z,
                      range_m=1.2 + 0.3 * np.sin(t), roll_rad=0.05 * np.sin(2 * t), pitch_rad=0.04 * np.cos(3 * t),
                      yaw_rad=z, roll_cmd_rad=z, pitch_cmd_rad=z, vx_set_m_s=z * np.nan, vy_set_m_s=z * np.nan,
                      truth_vx_m_s=z * np.nan, truth_vy_m_s=z * np.nan)
    fp = FlowProblem(data, mass_kg=1.0, gravity_m_s2=9.81)
    for scale, delay in ((1.0, 0.0), (1.3, 0.017)):
        p = NOMINAL.copy()
        p[IDX["scale_x"]], p[IDX["delay"]] = scale, delay
        X = fp.flow_velocity(p)[0]
        got = _FormDrag(fp, X).dq()
        monkeypatch.setenv("FLOWHOLD_NATIVE", "0")
        want = _FormDrag(fp, X).dq()
        monkeypatch.delenv("FLOWHOLD_NATIVE")
        np.testing.assert_array_equal(got, want)
        assert np.all(np.isfinite(want)) and np.abs(want).max() > 0
