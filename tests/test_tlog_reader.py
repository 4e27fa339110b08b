"""The columnar .tlog reader against pymavlink: every field of every message type the project
uses, MAVLink 1 and 2, truncated and signed packets, damaged files, the real SITL flight."""

from __future__ import annotations

import dataclasses
import functools
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

import companion.recordings.tlog_reader as tr
from companion.errors import RecordingError
from companion.recordings.load import Recording, load_recording
from companion.recordings.tlog_reader import crc16_mcrf4xx, crc_of_rows, read_tlog
from companion.recordings.tlog_writer import TlogWriter, mav_encoder

#: in the repository, gzip-compressed (read directly; pymavlink gets the ``flight_a_plain`` copy)
FLIGHT_A = Path(__file__).resolve().parents[1] / "data" / "sitl" / "ardupilot" / "flight_a.tlog.gz"

#: every message type the project reads or writes
PROJECT_MESSAGES = (
    "HEARTBEAT", "SYS_STATUS", "OPTICAL_FLOW", "OPTICAL_FLOW_RAD", "RAW_IMU", "SCALED_IMU",
    "HIGHRES_IMU", "DISTANCE_SENSOR", "ATTITUDE", "ATTITUDE_TARGET", "SET_ATTITUDE_TARGET",
    "LOCAL_POSITION_NED", "POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_LOCAL_NED",
    "VISION_SPEED_ESTIMATE", "MANUAL_CONTROL", "SIM_STATE", "SIMSTATE", "AHRS", "COMMAND_LONG",
    "COMMAND_ACK", "STATUSTEXT", "PARAM_VALUE", "PARAM_SET",
)
T0_US = 1_750_000_000_000_000

_INT_RANGES = {"int8_t": (-(2**7), 2**7), "uint8_t": (0, 2**8), "int16_t": (-(2**15), 2**15),
               "uint16_t": (0, 2**16), "int32_t": (-(2**31), 2**31), "uint32_t": (0, 2**32),
               "int64_t": (-(2**63), 2**63), "uint64_t": (0, 2**64)}


def _class(module: Any, name: str) -> type:
    return next(c for c in module.mavlink_map.values() if c.msgname == name)


def _random_value(ftype: str, length: int, rng: np.random.Generator) -> Any:
    """A random value of MAVLink type ``ftype`` (array of ``length`` if > 0): zero a third of
    the time (so MAVLink 2 truncates trailing zeros), float32 from random bit patterns (NaN,
    inf, subnormals included), chars with non-ASCII bytes and embedded NULs now and then."""
    ftype = ftype.split("_mavlink_version")[0]
    if ftype == "char":
        if rng.random() < 0.25:
            return b""
        n = int(rng.integers(1, length + 1))
        raw = rng.integers(32, 127, size=n).astype(np.uint8)
        if rng.random() < 0.3:
            raw[rng.integers(0, n)] = rng.integers(128, 256)
        if rng.random() < 0.2:
            raw[rng.integers(0, n)] = 0
        return raw.tobytes()
    if length:
        return [_random_value(ftype, 0, rng) for _ in range(length)]
    if rng.random() < 0.33:
        return 0
    if ftype == "float":
        return float(np.uint32(rng.integers(0, 2**32)).view(np.float32))
    if ftype == "double":
        return float(rng.standard_normal() * 1e3)
    lo, hi = _INT_RANGES[ftype]
    return int(rng.integers(lo, hi, dtype=np.int64 if ftype != "uint64_t" else np.uint64))


def _random_message(module: Any, name: str, rng: np.random.Generator) -> Any:
    cls = _class(module, name)
    args = []
    for fname, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True):
        length = cls.array_lengths[cls.ordered_fieldnames.index(fname)]
        args.append(_random_value(ftype, length, rng))
    return cls(*args)


def _encoder(sysid: int, compid: int, *, v1: bool = False, signed: bool = False) -> Any:
    enc = mavlink1.MAVLink(None, sysid, compid) if v1 else mav_encoder(sysid, compid)
    if signed:
        enc.signing.secret_key = bytes(range(32))
        enc.signing.sign_outgoing = True
        enc.signing.link_id = 7
        enc.signing.timestamp = 123_456_789
    return enc


@dataclasses.dataclass
class Built:
    """A recording written by the tests: its records' byte ranges and what they hold."""

    path: Path
    starts: list[int]  # offset of each record (its time header)
    packets: list[bytes]
    t_us: list[int]

    @functools.cached_property
    def stx(self) -> list[int]:
        return [s + 8 for s in self.starts]


def _write(path: Path, packets: list[bytes], t_us: list[int]) -> Built:
    starts, offset = [], 0
    with open(path, "wb") as f:
        for pkt, t in zip(packets, t_us, strict=True):
            starts.append(offset)
            f.write(t.to_bytes(8, "big") + pkt)
            offset += 8 + len(pkt)
    return Built(path, starts, packets, t_us)


def build_all_types(path: Path, rng: np.random.Generator, per_type: int = 12, *,
                    short_v1: bool = True) -> Built:
    """Every project message type from three senders, as MAVLink 2 (trailing zeros
    truncated), MAVLink 2 signed, MAVLink 1 with extensions (force_mavlink1) and MAVLink 1
    from the v1.0 dialect (no extension fields), shuffled, with 0-40 ms between records.
    ``short_v1=False`` sends MAVLink 1 packets under 12 bytes as MAVLink 2 instead (pymavlink's
    file reader misframes the record after one of those when it follows a MAVLink 2 packet:
    see ``test_short_mavlink1_packet_after_mavlink2``)."""
    senders = [(1, 1), (1, 191), (255, 190)]
    encoders = {
        "v2": [_encoder(*s) for s in senders],
        "signed": [_encoder(*s, signed=True) for s in senders],
        "v1": [_encoder(*s) for s in senders],
        "v10": [_encoder(*s, v1=True) for s in senders],
    }
    jobs = [(name, kind) for name in PROJECT_MESSAGES for kind in ("v2", "v2", "signed", "v1", "v10")
            for _ in range(per_type // 4 + 1)]
    packets = []
    for k in rng.permutation(len(jobs)):
        name, kind = jobs[k]
        enc = encoders[kind][int(rng.integers(0, len(senders)))]
        msg = _random_message(mavlink1 if kind == "v10" else mavlink2, name, rng)
        packet = bytes(msg.pack(enc, force_mavlink1=(kind == "v1")))
        if not short_v1 and packet[0] == 0xFE and len(packet) < 12:
            enc = encoders["v2"][0]
            packet = bytes(_random_message(mavlink2, name, rng).pack(enc))
        packets.append(packet)
        enc.seq = (enc.seq + 1) % 256
    t_us = (T0_US + np.cumsum(rng.integers(0, 40_000, size=len(packets)))).tolist()
    return _write(path, packets, t_us)


def pymavlink_messages(path: Path, monkeypatch: pytest.MonkeyPatch, limit: int | None = None) -> list[Any]:
    """What pymavlink's mavlink_connection + recv_match loop yields (MAVLink 2 decoding).
    With ``limit``, the first messages of the plain sequential log reader that loop runs on
    (``mavlink_connection`` would first index the whole file in Python)."""
    monkeypatch.setenv("MAVLINK20", "1")
    if limit is None:
        conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    else:
        mavutil.set_dialect("ardupilotmega")
        conn = mavutil.mavlogfile(str(path))
    out = []
    try:
        while limit is None or len(out) < limit:
            m = conn.recv_match()
            if m is None:
                break
            out.append(m)
    finally:
        conn.close()
    return out


def decoded_by_pymavlink(packets: list[bytes]) -> list[Any]:
    """Each packet decoded on its own by pymavlink's MAVLink 2 parser."""
    out = []
    for pkt in packets:
        msgs = mavlink2.MAVLink(None).parse_buffer(pkt)
        assert msgs is not None and len(msgs) == 1
        out.append(msgs[0])
    return out


def in_file_order(rec: Recording) -> list[tuple[str, int]]:
    """(message name, row in its table) of every record, by ``record``."""
    rows = [(int(r), name, i) for name, tab in rec.tables.items() for i, r in enumerate(tab.record)]
    rows.sort()
    assert [r for r, _, _ in rows] == list(range(len(rows)))
    return [(name, i) for _, name, i in rows]


def same_value(ours: Any, theirs: Any) -> bool:
    """Exact equality of a column entry and a pymavlink attribute, NaN equal to NaN."""
    if isinstance(theirs, str | bytes):
        return type(ours) is type(theirs) and ours == theirs
    return same_column(np.asarray(ours)[None], [theirs])


def same_column(ours: np.ndarray, theirs: list[Any]) -> bool:
    """Exact equality of a whole column and pymavlink's values of that field, NaN-aware;
    integers must stay integers and floats compare in float64 (float32 widens exactly)."""
    if ours.dtype == object:
        return len(ours) == len(theirs) and all(type(a) is type(b) and a == b
                                                for a, b in zip(ours, theirs, strict=True))
    if ours.dtype.kind == "f":
        want = np.array(theirs, dtype=np.float64)
        return want.shape == ours.shape and bool(np.array_equal(ours.astype(np.float64), want, equal_nan=True))
    if ours.dtype.kind not in "iu" or any(isinstance(v, float) for v in np.ravel(np.array(theirs, dtype=object))):
        return False
    want = np.array(theirs, dtype=ours.dtype)  # raises OverflowError if a value does not fit
    return want.shape == ours.shape and bool(np.array_equal(ours, want))


def assert_matches_pymavlink(rec: Recording, msgs: list[Any], t_us: list[int] | None = None) -> None:
    """``rec`` holds exactly ``msgs`` (pymavlink's messages, in file order): types, order,
    senders, times (pymavlink's, to its 1 µs rounding; ``t_us``: exactly) and every field."""
    msgs = [m for m in msgs if m.get_type() != "BAD_DATA"]
    names = np.empty(rec.n_messages, dtype=object)
    for name, tab in rec.tables.items():
        names[tab.record] = name
    assert names.tolist() == [m.get_type() for m in msgs]
    index = np.arange(len(msgs))
    for name, tab in rec.tables.items():
        mine = [m for m, n in zip(msgs, names, strict=True) if n == name]
        assert same_column(tab.sysid, [m.get_srcSystem() for m in mine]), name
        assert same_column(tab.compid, [m.get_srcComponent() for m in mine]), name
        if hasattr(mine[0], "_timestamp"):
            np.testing.assert_allclose(tab.t_s, [m._timestamp for m in mine], rtol=0, atol=1e-6)
        if t_us is not None:
            assert tab.t_s.tolist() == [t_us[k] / 1e6 for k in index[names == name]]
        for f in mine[0].get_fieldnames():
            assert same_column(tab[f], [getattr(m, f) for m in mine]), (name, f)


# ---------------------------------------------------------------------------------------------
# CRC


def test_crc_matches_pymavlink_x25():
    rng = np.random.default_rng(1)
    for length in [0, 1, 2, 3, 9, 40, 41, 263, 264]:
        data = rng.integers(0, 256, size=length, dtype=np.uint8).tobytes()
        assert crc16_mcrf4xx(data) == mavlink2.x25crc(data).crc


@pytest.mark.parametrize("length", [1, 2, 9, 10, 37, 38, 264])
def test_vectorised_crc_equals_scalar(length):
    rng = np.random.default_rng(length)
    rows = rng.integers(0, 256, size=(50, length), dtype=np.uint8)
    extra = rng.integers(0, 256, size=50, dtype=np.uint8)
    got = crc_of_rows(rows, extra)
    want = [crc16_mcrf4xx(r.tobytes() + bytes([e])) for r, e in zip(rows, extra, strict=True)]
    assert got.tolist() == want


# ---------------------------------------------------------------------------------------------
# Decoding equals pymavlink


@pytest.fixture(scope="module")
def all_types(tmp_path_factory: pytest.TempPathFactory) -> Built:
    return build_all_types(tmp_path_factory.mktemp("reader") / "all.tlog", np.random.default_rng(7))


def test_test_recording_exercises_every_packet_kind(all_types):
    """The recording really holds v1, v2, truncated v2 and signed v2 packets of every type."""
    kinds = Counter()
    for pkt in all_types.packets:
        if pkt[0] == 0xFE:
            kinds["v1"] += 1
            continue
        cls = mavlink2.mavlink_map[pkt[7] | pkt[8] << 8 | pkt[9] << 16]
        kinds["signed" if pkt[2] & 1 else "v2"] += 1
        kinds["truncated"] += pkt[1] < cls.unpacker.size
    assert min(kinds.values()) > 50, kinds
    names = {mavlink2.mavlink_map[p[5] if p[0] == 0xFE else p[7]].msgname for p in all_types.packets}
    assert names == set(PROJECT_MESSAGES)


def test_every_field_of_every_project_message_equals_pymavlink(all_types):
    rec = read_tlog(all_types.path)
    assert rec.source_format == "tlog" and rec.profile_hint is None
    assert (rec.skipped_bytes, rec.skipped_packets, rec.notes) == (0, 0, [])
    assert set(rec.tables) == set(PROJECT_MESSAGES)
    assert_matches_pymavlink(rec, decoded_by_pymavlink(all_types.packets), all_types.t_us)


def test_records_equal_pymavlink_file_loop(tmp_path, monkeypatch):
    """Order, count, senders, times and values equal mavlink_connection + recv_match."""
    built = build_all_types(tmp_path / "loop.tlog", np.random.default_rng(8), short_v1=False)
    rec = read_tlog(built.path)
    msgs = pymavlink_messages(built.path, monkeypatch)
    assert [m.get_type() for m in msgs].count("BAD_DATA") == 0
    assert_matches_pymavlink(rec, msgs, built.t_us)


def test_short_mavlink1_packet_after_mavlink2(tmp_path):
    """A MAVLink 1 packet under 12 bytes (a 3-byte COMMAND_ACK) right after a MAVLink 2 one:
    this reader keeps all three records, decoded as pymavlink decodes each packet. (pymavlink
    2.4.50's file loop reads 12 bytes for the short packet, one into the next record's time
    header, and misframes what follows as BAD_DATA / UNKNOWN_* messages.)"""
    v2, v1 = mav_encoder(1, 1), _encoder(1, 1, v1=True)
    packets = [bytes(v2.heartbeat_encode(2, 3, 0, 0, 4).pack(v2)),
               bytes(mavlink1.MAVLink_command_ack_message(400, 0).pack(v1)),
               bytes(v2.heartbeat_encode(2, 3, 0, 0, 4).pack(v2))]
    assert len(packets[1]) == 11
    built = _write(tmp_path / "short.tlog", packets, [T0_US, T0_US + 1000, T0_US + 2000])
    rec = read_tlog(built.path)
    assert [n for n, _ in in_file_order(rec)] == ["HEARTBEAT", "COMMAND_ACK", "HEARTBEAT"]
    assert rec.tables["COMMAND_ACK"]["command"][0] == 400 and rec.skipped_bytes == 0
    assert_matches_pymavlink(rec, decoded_by_pymavlink(packets), built.t_us)


def test_column_types_and_shapes(all_types):
    rec = read_tlog(all_types.path)
    att = rec.tables["ATTITUDE_TARGET"]
    n = len(att)
    assert att["q"].shape == (n, 4) and att["q"].dtype == np.float32
    assert att.t_s.dtype == np.float64 and att.record.dtype == np.int64
    assert att.sysid.dtype == np.uint8 and att.compid.dtype == np.uint8
    assert rec.tables["RAW_IMU"]["time_usec"].dtype == np.uint64
    assert rec.tables["VISION_SPEED_ESTIMATE"]["covariance"].shape == (len(rec.tables["VISION_SPEED_ESTIMATE"]), 9)
    text = rec.tables["STATUSTEXT"]["text"]
    assert text.dtype == object and all(isinstance(t, str) for t in text)
    for tab in rec:
        assert np.all(np.diff(tab.record) > 0)
        for col in tab.fields.values():
            assert len(col) == len(tab) and (col.dtype == object or col.flags.c_contiguous)


def test_pymavlink_fallback_decodes_the_same(all_types, monkeypatch):
    """A type the fast path cannot lay out is decoded packet by packet with pymavlink."""
    fast = read_tlog(all_types.path)
    slow_layouts = {mid: dataclasses.replace(lay, dtype=None) for mid, lay in tr.layouts().items()}
    monkeypatch.setattr(tr, "layout_of", slow_layouts.get)
    slow = read_tlog(all_types.path)
    assert set(slow.tables) == set(fast.tables)
    for name, tab in fast.tables.items():
        other = slow.tables[name]
        np.testing.assert_array_equal(tab.record, other.record)
        for f, col in tab.fields.items():
            assert same_column(col, other[f].tolist()), (name, f)


def test_unknown_message_ids_are_kept_like_pymavlink(tmp_path, monkeypatch):
    """Message ids the dialect does not define: no CRC to check, kept as UNKNOWN_<id> where
    they fit the record chain, as pymavlink's MAVLink_unknown."""
    assert 12345 not in mavlink2.mavlink_map
    enc = mav_encoder(1, 1)
    hb = bytes(enc.heartbeat_encode(2, 3, 0, 0, 4).pack(enc))
    odd = bytes([0xFD, 4, 0, 0, 9, 1, 1, 12345 & 0xFF, (12345 >> 8) & 0xFF, 0, 1, 2, 3, 4, 0xAA, 0xBB])
    built = _write(tmp_path / "unknown.tlog", [hb, odd, odd, hb], [T0_US + k for k in range(4)])
    rec = read_tlog(built.path)
    assert [name for name, _ in in_file_order(rec)] == ["HEARTBEAT", "UNKNOWN_12345", "UNKNOWN_12345", "HEARTBEAT"]
    assert rec.tables["UNKNOWN_12345"]["data"].tolist() == [odd, odd]
    assert rec.skipped_bytes == 0 and any("UNKNOWN" in n for n in rec.notes)
    msgs = pymavlink_messages(built.path, monkeypatch)
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "UNKNOWN_12345", "UNKNOWN_12345", "HEARTBEAT"]


def test_writer_round_trip(tmp_path, monkeypatch):
    path = tmp_path / "w.tlog"
    enc = mav_encoder(1, 191)
    with TlogWriter(path) as log:
        log.write(enc.heartbeat_encode(18, 8, 0, 0, 4), 1_700_000_000.25, encoder=enc)
        msg = enc.optical_flow_encode(1_000_000, 0, 5, -3, 0.0, 0.0, 200, -1.0)
        msg.pack(enc)
        log.write(msg, 1_700_000_000.5)
        log.write_bytes(bytes(enc.attitude_encode(10, 0.1, -0.2, 0.3, 0, 0, 0).pack(enc)), 1_700_000_001.0)
        assert log.n_records == 3
    rec = read_tlog(path)
    assert [n for n, _ in in_file_order(rec)] == ["HEARTBEAT", "OPTICAL_FLOW", "ATTITUDE"]
    assert rec.tables["OPTICAL_FLOW"].t_s[0] == 1_700_000_000.5
    assert rec.tables["OPTICAL_FLOW"]["flow_y"][0] == -3 and rec.tables["HEARTBEAT"].compid[0] == 191
    assert_matches_pymavlink(rec, pymavlink_messages(path, monkeypatch))


def test_load_recording_dispatches_tlog(all_types):
    rec = load_recording(all_types.path)
    assert rec.source_format == "tlog" and rec.n_messages == len(all_types.packets)


def test_progress_bar_on_stderr(all_types, monkeypatch, capsys):
    monkeypatch.setattr(tr, "PROGRESS_MIN_BYTES", 0)
    read_tlog(all_types.path, progress=True)
    assert "reading all.tlog" in capsys.readouterr().err
    read_tlog(all_types.path, progress=False)
    assert capsys.readouterr().err == ""


# ---------------------------------------------------------------------------------------------
# Damaged recordings


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> tuple[Built, Recording]:
    built = build_all_types(tmp_path_factory.mktemp("clean") / "clean.tlog", np.random.default_rng(11), per_type=16)
    return built, read_tlog(built.path)


def _row(rec: Recording, name: str, i: int) -> tuple:
    tab = rec.tables[name]
    values = []
    for f in tab.fields.values():
        v = f[i]
        values.append(v if isinstance(v, str | bytes) else np.asarray(v).tobytes())
    return (name, int(tab.sysid[i]), int(tab.compid[i]), *values)


def _rows(rec: Recording) -> list[tuple]:
    return [_row(rec, name, i) for name, i in in_file_order(rec)]


def _times(rec: Recording) -> list[float]:
    return [float(rec.tables[name].t_s[i]) for name, i in in_file_order(rec)]


def _damaged(path: Path, data: bytes | bytearray) -> Recording:
    path.write_bytes(bytes(data))
    return read_tlog(path)


def test_one_flipped_payload_bit_loses_exactly_that_packet(clean, tmp_path):
    built, rec = clean
    k = 100
    data = bytearray(built.path.read_bytes())
    data[built.stx[k] + 12] ^= 0x10  # a payload (or CRC) byte of record k
    got = _damaged(tmp_path / "flip.tlog", data)
    want = _rows(rec)
    assert _rows(got) == want[:k] + want[k + 1:]
    assert got.skipped_bytes == 8 + len(built.packets[k])
    assert got.skipped_packets == 1
    assert got.notes == [f"skipped {8 + len(built.packets[k])} bytes: 1 damaged packet (bad CRC or header)"]


def _signature_len(packet: bytes) -> int:
    return 13 if packet[0] == 0xFD and packet[2] & 1 else 0


@pytest.mark.parametrize("seed, n_flips", [(3, 40), (4, 150)])
def test_random_bit_flips_keep_every_untouched_packet(clean, tmp_path, seed, n_flips):
    """Bits flipped anywhere: every packet whose checked bytes (STX to CRC; the signature is
    not checked, as in pymavlink without a key) were not hit comes back, with its values, in
    order, and nothing else but UNKNOWN_<id> packets made by a flipped message id."""
    built, rec = clean
    rng = np.random.default_rng(seed)
    data = bytearray(built.path.read_bytes())
    flips = rng.choice(len(data), size=n_flips, replace=False)
    for pos in flips:
        data[pos] ^= 1 << int(rng.integers(0, 8))
    got = _damaged(tmp_path / "flips.tlog", data)
    ends = [s + 8 + len(p) for s, p in zip(built.starts, built.packets, strict=True)]
    record_of = np.searchsorted(built.starts, flips, side="right") - 1  # the record each flip is in
    touched = {int(k) for k, f in zip(record_of, flips, strict=True)
               if built.stx[k] <= f < ends[k] - _signature_len(built.packets[k])}
    # a flip in a message id can make it one the dialect does not define: such a packet has
    # no CRC to check and comes back as UNKNOWN_<id>, as in pymavlink
    unknown = [bytes(d) for name, tab in got.tables.items() if name.startswith("UNKNOWN_") for d in tab["data"]]
    as_unknown = {k for k in touched if bytes(data[built.stx[k]:ends[k]]) in unknown}
    assert len(as_unknown) == len(unknown)
    want = [r for k, r in enumerate(_rows(rec)) if k not in touched]
    assert [r for r in _rows(got) if not r[0].startswith("UNKNOWN_")] == want  # every untouched packet, in order
    lost = touched - as_unknown
    assert got.skipped_bytes == sum(8 + len(built.packets[k]) for k in lost)
    # packets are counted by following the record chain through the damage; a flip in a
    # header's STX, length or flags byte can hide that packet and the lost ones right after it
    framing = {int(k) for k, f in zip(record_of, flips, strict=True) if 0 <= f - built.stx[k] < 3}
    hidden = set()
    for k in framing:
        while k + 1 in lost:
            k += 1
            hidden.add(k)
    assert len(lost - framing - hidden) <= got.skipped_packets <= len(lost) + len(framing)
    # records whose time header was untouched keep their time exactly
    times = [t for t, r in zip(_times(got), _rows(got), strict=True) if not r[0].startswith("UNKNOWN_")]
    kept = [k for k in range(len(built.packets)) if k not in touched]
    time_hit = {int(k) for k, f in zip(record_of, flips, strict=True) if f < built.stx[k]}
    for j, k in enumerate(kept):
        if k not in time_hit:
            assert times[j] == built.t_us[k] / 1e6


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_random_insertions_deletions_and_overwrites(clean, tmp_path, seed):
    """Garbage inserted, bytes deleted, bytes overwritten at random places: the packets the
    edits did not reach all come back in order (a packet whose signature block lost or gained
    bytes counts as reached; one whose signature was only overwritten does not)."""
    built, rec = clean
    orig = built.path.read_bytes()
    ends = [s + 8 + len(p) for s, p in zip(built.starts, built.packets, strict=True)]
    rng = np.random.default_rng(seed)
    out, prev, reached = bytearray(), 0, set()
    for pos in np.sort(rng.choice(len(orig), size=8, replace=False)).tolist():
        if pos < prev:
            continue
        out += orig[prev:pos]
        kind = int(rng.integers(0, 3))
        k = int(np.searchsorted(built.starts, pos, side="right") - 1)
        if kind == 0:  # insert garbage before byte pos
            out += rng.integers(0, 256, size=int(rng.integers(1, 300)), dtype=np.uint8).tobytes()
            prev = pos
            reached |= {k} if built.stx[k] < pos < ends[k] else set()
            continue
        stop = min(len(orig), pos + int(rng.integers(1, 200)))
        if kind == 2:  # overwrite in place
            out += rng.integers(0, 256, size=stop - pos, dtype=np.uint8).tobytes()
        prev = stop
        for j in range(k, len(built.starts)):
            tail = ends[j] - (_signature_len(built.packets[j]) if kind == 2 else 0)
            if built.starts[j] < stop and max(pos, built.stx[j]) < min(stop, tail):
                reached.add(j)
    out += orig[prev:]
    got = _damaged(tmp_path / "edits.tlog", out)
    have = iter(r for r in _rows(got) if not r[0].startswith("UNKNOWN_"))
    want = [r for k, r in enumerate(_rows(rec)) if k not in reached]
    assert all(any(h == w for h in have) for w in want)  # want is a subsequence of what came back
    assert got.skipped_bytes > 0


def test_truncated_last_packet(clean, tmp_path):
    built, rec = clean
    data = built.path.read_bytes()
    cut = built.stx[-1] + 7  # inside the last packet's header
    got = _damaged(tmp_path / "cut.tlog", data[:cut])
    assert _rows(got) == _rows(rec)[:-1]
    assert (got.skipped_bytes, got.skipped_packets) == (cut - built.starts[-1], 1)
    assert got.notes == [f"skipped {cut - built.starts[-1]} bytes: truncated last record"]


def test_truncated_inside_the_last_time_header(clean, tmp_path):
    built, rec = clean
    cut = built.starts[-1] + 5
    got = _damaged(tmp_path / "cut.tlog", built.path.read_bytes()[:cut])
    assert _rows(got) == _rows(rec)[:-1]
    assert (got.skipped_bytes, got.skipped_packets) == (5, 1)


def test_bytes_cut_out_of_the_middle(clean, tmp_path):
    """A chunk lost from the middle (records k..k+2 partly gone): the rest all come back."""
    built, rec = clean
    data = built.path.read_bytes()
    a, b = built.stx[50] + 5, built.stx[52] + 3
    got = _damaged(tmp_path / "hole.tlog", data[:a] + data[b:])
    want = _rows(rec)
    assert _rows(got) == want[:50] + want[53:]
    lost = sum(8 + len(built.packets[k]) for k in (50, 51, 52)) - (b - a)
    assert got.skipped_bytes == lost


def test_garbage_before_the_first_packet(clean, tmp_path):
    built, rec = clean
    rng = np.random.default_rng(5)
    garbage = rng.integers(0, 256, size=3000, dtype=np.uint8).tobytes()
    got = _damaged(tmp_path / "garbage.tlog", garbage + built.path.read_bytes())
    assert _rows(got) == _rows(rec)
    assert _times(got) == _times(rec)
    assert got.skipped_bytes == len(garbage)
    assert any("unrecognisable" in n for n in got.notes)


def test_garbage_without_stx_bytes_is_not_counted_as_packets(clean, tmp_path):
    built, rec = clean
    garbage = bytes(range(0, 250)) * 4
    got = _damaged(tmp_path / "garbage.tlog", garbage + built.path.read_bytes())
    assert (got.skipped_bytes, got.skipped_packets) == (len(garbage), 0)
    assert got.notes == [f"skipped {len(garbage)} bytes of unrecognisable data in 1 place (the first at byte 0)"]


def test_garbage_inside_a_time_header(clean, tmp_path):
    """Bytes inserted inside record k's time header: its packet survives; its time, now
    partly garbage, is replaced by the previous record's."""
    built, rec = clean
    k = 77
    data = built.path.read_bytes()
    garbage = bytes([0x55, 0xFD, 0x13, 0xFE, 0x99, 0x01, 0x37])
    at = built.starts[k] + 3
    got = _damaged(tmp_path / "in_header.tlog", data[:at] + garbage + data[at:])
    assert _rows(got) == _rows(rec)
    assert got.skipped_bytes == len(garbage)
    times = _times(got)
    assert times[k] == times[k - 1]
    assert times[:k] + times[k + 1:] == [t / 1e6 for j, t in enumerate(built.t_us) if j != k]
    assert any("damaged timestamp" in n for n in got.notes)


@pytest.mark.parametrize("where", ["first", "middle", "last"])
def test_flipped_high_time_bit_is_repaired(clean, tmp_path, where):
    """A record whose time jumped by years keeps its packet and takes the time of the record
    before it (the first record: of the one after it)."""
    built, rec = clean
    k = {"first": 0, "middle": 200, "last": len(built.starts) - 1}[where]
    data = bytearray(built.path.read_bytes())
    data[built.starts[k] + 2] ^= 0x40  # ~2^46 µs = 2.2 years
    got = _damaged(tmp_path / "time.tlog", data)
    assert _rows(got) == _rows(rec)
    times = _times(got)
    assert times[k] == built.t_us[k - 1 if k else 1] / 1e6
    assert times[:k] + times[k + 1:] == [t / 1e6 for j, t in enumerate(built.t_us) if j != k]
    assert got.skipped_bytes == 0
    assert got.notes == ["1 record had a damaged timestamp: given the previous record's time"]


def test_duplicated_records_are_kept(clean, tmp_path):
    built, rec = clean
    data = built.path.read_bytes()
    k = 30
    record = data[built.starts[k]:built.starts[k + 1]]
    got = _damaged(tmp_path / "dup.tlog", data[:built.starts[k + 1]] + record + data[built.starts[k + 1]:])
    want = _rows(rec)
    assert _rows(got) == want[:k + 1] + [want[k]] + want[k + 1:]
    assert (got.skipped_bytes, got.skipped_packets, got.notes) == (0, 0, [])


def test_backward_timestamps_stay_in_file_order(tmp_path):
    enc = mav_encoder(1, 1)
    packets = [bytes(enc.attitude_encode(i, 0.1 * i, 0, 0, 0, 0, 0).pack(enc)) for i in range(40)]
    t_us = [T0_US + 20_000 * i for i in range(40)]
    t_us[20:] = [t - 5_000_000 for t in t_us[20:]]  # the clock steps back 5 s
    rec = read_tlog(_write(tmp_path / "back.tlog", packets, t_us).path)
    att = rec.tables["ATTITUDE"]
    assert att["time_boot_ms"].tolist() == list(range(40))
    assert att.t_s.tolist() == [t / 1e6 for t in t_us]
    assert rec.notes == ["1 record timestamped earlier than the record before (by up to 4.980 s): kept in file order"]


@pytest.mark.parametrize("content", [b"", b"\x00" * 100, bytes(range(256)) * 10])
def test_no_packets_is_an_error(tmp_path, content):
    path = tmp_path / "empty.tlog"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match="no MAVLink packets found in"):
        read_tlog(path)


def test_missing_file_is_an_error(tmp_path):
    with pytest.raises(RecordingError, match="not found"):
        read_tlog(tmp_path / "nope.tlog")


# ---------------------------------------------------------------------------------------------
# The real third-party recording


@pytest.fixture(scope="module")
def flight_a() -> Recording:
    return read_tlog(FLIGHT_A)


def test_flight_a_reads_clean(flight_a):
    assert flight_a.n_messages == 90161
    assert (flight_a.skipped_bytes, flight_a.skipped_packets, flight_a.notes) == (0, 0, [])


def test_flight_a_prefix_equals_pymavlink(flight_a, flight_a_plain, monkeypatch):
    """The first 10 000 messages (the set-up and 25 s of streaming): order, senders, times and
    every field equal pymavlink's (the whole file: the slow test below)."""
    msgs = pymavlink_messages(flight_a_plain, monkeypatch, limit=10_000)
    sub = Recording(flight_a.path, {}, "tlog")
    for name, tab in flight_a.tables.items():
        if (tab.record < len(msgs)).any():
            sub.tables[name] = tab.select(tab.record < len(msgs))
    assert sub.n_messages == len(msgs) == 10_000
    assert_matches_pymavlink(sub, msgs)


@pytest.mark.slow
def test_flight_a_whole_file_equals_pymavlink(flight_a, flight_a_plain, monkeypatch):
    msgs = pymavlink_messages(flight_a_plain, monkeypatch)
    assert Counter(m.get_type() for m in msgs) == {n: len(t) for n, t in flight_a.tables.items()}
    assert_matches_pymavlink(flight_a, msgs)


def test_the_wire_layout_cache_is_the_dialects_table(tmp_path, monkeypatch):
    """The reader's wire layouts come from a cache file (so the dialect, 25 ms of start-up, is
    not loaded): made from the dialect when missing or unreadable, and equal to it."""
    from companion import native

    monkeypatch.setenv("FLOWHOLD_CACHE_DIR", str(tmp_path))
    tr._wire_table.cache_clear()
    try:
        fresh = tr._dialect_table()
        assert tr._wire_table() == fresh  # made and written
        path = tr._wire_table_file()
        assert path is not None and path.parent == native.cache_dir() and path.is_file()
        tr._wire_table.cache_clear()
        assert tr._wire_table() == fresh  # read back
        path.write_bytes(b"\x00garbage")
        tr._wire_table.cache_clear()
        assert tr._wire_table() == fresh  # unreadable: made again
        assert len(fresh) == len(mavlink2.mavlink_map) and fresh[24][0] == "GPS_RAW_INT"
        assert all(tr.layout_of(mid).cls is mavlink2.mavlink_map[mid] for mid in (0, 100, 106))
    finally:
        tr._wire_table.cache_clear()
