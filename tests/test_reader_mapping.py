"""The reader maps large files instead of copying them (issue 17): the same recording either way,
on whole, cut and damaged files whose padding ends inside the last page or crosses into the zero
pages after it."""

from __future__ import annotations

import mmap

import numpy as np
import pytest

from companion.recordings import tlog_reader
from companion.recordings.tlog_reader import _PAD, read_tlog


def _same(a, b) -> None:
    assert (a.skipped_bytes, a.skipped_packets, a.notes) == (b.skipped_bytes, b.skipped_packets, b.notes)
    assert list(a.tables) == list(b.tables)
    for name, ta in a.tables.items():
        tb = b.tables[name]
        for col in ("t_s", "sysid", "compid", "record"):
            np.testing.assert_array_equal(getattr(ta, col), getattr(tb, col))
        assert list(ta.fields) == list(tb.fields)
        for f, va in ta.fields.items():
            if va.dtype == object:
                assert va.tolist() == tb.fields[f].tolist()
            else:
                np.testing.assert_array_equal(va, tb.fields[f])


def _both(path, monkeypatch):
    monkeypatch.setattr(tlog_reader, "MAP_MIN_BYTES", 1)
    mapped = read_tlog(path)
    monkeypatch.setattr(tlog_reader, "MAP_MIN_BYTES", 1 << 62)
    copied = read_tlog(path)
    return mapped, copied


def test_the_mapping_is_the_file_and_zero_padding(flight_a_plain):
    n = flight_a_plain.stat().st_size
    buf = tlog_reader._map_file(flight_a_plain, n)
    if buf is None:
        pytest.skip("no mmap through libc here")
    assert not buf.flags.writeable
    assert len(buf) >= n + _PAD
    assert buf[:n].tobytes() == flight_a_plain.read_bytes()
    assert not buf[n:].any()


@pytest.mark.parametrize("cut", [0, 1, 7, 100, None])
def test_mapped_and_copied_reads_agree(flight_a_plain, tmp_path, monkeypatch, cut):
    data = bytearray(flight_a_plain.read_bytes())
    page = mmap.PAGESIZE
    if cut is None:  # the padding crosses from the file's last page into the zero pages after it
        size = (len(data) // page) * page - 5
    else:
        size = len(data) - cut
    data = data[:size]
    rng = np.random.default_rng(cut or 0)
    for at in rng.integers(100, size - 100, 40):  # damage: flipped bytes and a run of garbage
        data[int(at)] ^= 0x5A
    data[size // 2:size // 2 + 300] = bytes(rng.integers(0, 256, 300, dtype=np.uint8))
    path = tmp_path / "cut.tlog"
    path.write_bytes(bytes(data))
    mapped, copied = _both(path, monkeypatch)
    assert mapped.skipped_bytes > 0
    _same(mapped, copied)


def test_whole_sitl_flight_mapped_equals_copied(flight_a_plain, monkeypatch):
    mapped, copied = _both(flight_a_plain, monkeypatch)
    assert mapped.skipped_bytes == 0 and mapped.n_messages == 90161
    _same(mapped, copied)
