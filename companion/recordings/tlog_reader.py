"""Read a .tlog into per-message-type numpy columns, fast, and survive damaged bytes.

A .tlog is a sequence of records: an 8-byte big-endian UNIX time in microseconds, then one
raw MAVLink 1 (STX 0xFE) or MAVLink 2 (STX 0xFD) packet. pymavlink reads one Python object per
message (tens of µs each); this reader finds, checks and decodes all packets with numpy:

1. every 0xFE / 0xFD byte is a candidate packet start; its header gives its length;
2. candidates from which the record chain goes on for two more records (each next STX 8 bytes
   after the packet its length says, or the end of the file) have their CRC-16/MCRF4XX (with
   the dialect's ``crc_extra``) checked, vectorised; those that pass, without overlapping
   bodies, are the records;
3. between the packets found (where there was damage) every other candidate is checked;
   what is still left is accounted for by following the record chain through it (damaged
   packets, unrecognisable bytes, a truncated last record);
4. each message type is decoded at once with a structured dtype built from the dialect's
   wire layout (zero-padding MAVLink 2 payloads whose trailing zeros were truncated; the
   13-byte signature of signed packets is skipped, not checked, like pymavlink without a key).
   A record's time is the 8 bytes right before its STX.

Field names and values are pymavlink's (``pymavlink.dialects.v20.ardupilotmega``): raw MAVLink
units, the wire dtype of each field (``float32``, ``int16``, ...), char arrays as ``str``
decoded as pymavlink does, array fields as (n, k) columns. A message type the fast path cannot
lay out is decoded packet by packet with pymavlink. Packets of message ids the dialect does not
know cannot be CRC-checked; they are kept as ``UNKNOWN_<id>`` (field ``data``: the packet bytes,
as pymavlink's ``MAVLink_unknown``) only where they fit the record chain exactly.

On a file without damage the records, their order and their values equal what
``pymavlink.mavutil.mavlink_connection(path, dialect="ardupilotmega")`` yields with
MAVLink 2 decoding (environment ``MAVLINK20=1``, or a file whose first packet is MAVLink 2),
less its BAD_DATA. One known difference: pymavlink 2.4.50's file reader reads 12 bytes for a
MAVLink 1 packet shorter than that (payload under 4 bytes) that follows a MAVLink 2 one, and
misframes the records after it; this reader keeps them.
"""

from __future__ import annotations

import ctypes
import functools
import importlib
import importlib.util
import itertools
import marshal
import os
import re
import sys
import threading
import zlib
from collections.abc import Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion import native
from companion.errors import RecordingError
from companion.recordings.columnar import LazyColumns, MessageTable, Recording, is_gzip_path, read_recording_bytes

STX_V1 = 0xFE
STX_V2 = 0xFD
TIME_HEADER_LEN = 8  # bytes of big-endian UNIX time (µs) before each packet
SIGNATURE_LEN = 13  # MAVLink 2 signature block (link id, 48-bit timestamp, 48-bit signature)
HEADER_LEN_V1 = 6  # STX, len, seq, sysid, compid, msgid
HEADER_LEN_V2 = 10  # STX, len, incompat, compat, seq, sysid, compid, msgid (3 bytes)
CRC_LEN = 2
_MAX_PACKET_LEN = HEADER_LEN_V2 + 255 + CRC_LEN + SIGNATURE_LEN
#: padding after the file's bytes so fixed-width windows never run off the end
_PAD = 512
#: a progress bar is worth showing above this file size (bytes)
PROGRESS_MIN_BYTES = 20_000_000
#: an interior record time further than this (s) from its neighbours, which agree, is damage
TIME_SPIKE_TOL_S = 1.0
#: the same for the first and last two records, which have neighbours on one side only
TIME_SPIKE_TOL_END_S = 86400.0
#: bytes per CRC work block (bounds the temporary arrays of the vectorised CRC)
_CRC_BLOCK_BYTES = 1 << 22
#: bytes of the file scanned for packet starts at a time
_SCAN_CHUNK = 1 << 23
#: packets from which the compiled decoding is shared among threads (below, starting them costs more)
_PARALLEL_MIN_PACKETS = 200_000
#: file bytes from which the compiled scan is shared among threads
_PARALLEL_MIN_BYTES = 1 << 23
#: bytes of payload rows decoded per block
_DECODE_BLOCK_BYTES = 1 << 20
#: the CRC is computed on rows whose width is a multiple of this many bytes (8: see _KEEP_FROM)
_CRC_WIDTH_STEP = 8
#: a little-endian 8-byte word with its first k bytes cleared, for k = 0..7
_KEEP_FROM = np.array([(2**64 - 1) << (8 * k) & (2**64 - 1) for k in range(8)], dtype=np.uint64)
#: rows per block of the CRC's transposed table look-ups (kept within the CPU caches)
_CRC_ROWS_PER_BLOCK = 16384

_NUMPY_CODES = {"b": "i1", "B": "u1", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4",
                "q": "<i8", "Q": "<u8", "f": "<f4", "d": "<f8"}


# ---------------------------------------------------------------------------------------------
# Message layouts from the dialect


@dataclass(frozen=True)
class MessageLayout:
    """How to decode one message type, taken from the dialect's generated class.

    ``size``: wire payload length in bytes (the unpacker's size). ``dtype``: structured numpy
    dtype of the payload in wire order (fields sorted by type size, extensions last), or None
    when the fast path cannot lay it out (decoded with pymavlink instead). ``fieldnames``:
    pymavlink's field order. ``char_fields``: fields of MAVLink type char[N].
    ``char_as_str``: pymavlink turns char[N] into ``str`` (cut at the first NUL, ASCII with
    replacement) rather than ``bytes``. ``cls``: the dialect's class (the dialect loaded then).
    """

    msgid: int
    name: str
    crc_extra: int
    size: int
    dtype: np.dtype | None
    fieldnames: tuple[str, ...]
    char_fields: frozenset[str]
    char_as_str: bool

    @property
    def cls(self) -> type:
        return _dialect().mavlink_map[self.msgid]


#: the dialect the reader decodes with (its classes give each message's wire layout)
DIALECT = "pymavlink.dialects.v20.ardupilotmega"
#: the version of the wire-layout table's cache file (``_wire_table``)
_WIRE_TABLE_VERSION = 1


@functools.cache
def _dialect() -> Any:
    """The ardupilotmega dialect module, loaded when first needed: a file whose layouts are in
    the cache (``_wire_table``) is read without it (about 25 ms of every command's start-up)."""
    return importlib.import_module(DIALECT)


def _payload_dtype(fmt: str, names: Sequence[str], size: int) -> tuple[np.dtype | None, frozenset[str]]:
    """Structured dtype of a wire payload from its unpacker's ``fmt`` (struct format) and the
    ``names`` in wire order (``ordered_fieldnames``); None if a code has no numpy equivalent or
    the sizes disagree with ``size`` (the unpacker's)."""
    if not fmt.startswith("<"):
        return None, frozenset()
    tokens = re.findall(r"(\d*)([a-zA-Z?])", fmt[1:])
    if "".join(k + c for k, c in tokens) != fmt[1:] or len(tokens) != len(names):
        return None, frozenset()
    formats: list[Any] = []
    chars = set()
    for (count_s, code), name in zip(tokens, names, strict=True):
        count = int(count_s) if count_s else 1
        if code == "s":
            formats.append(f"S{count}")
            chars.add(name)
        elif code in _NUMPY_CODES:
            formats.append(_NUMPY_CODES[code] if count == 1 else (_NUMPY_CODES[code], (count,)))
        else:
            return None, frozenset()
    dtype = np.dtype({"names": list(names), "formats": formats})
    if dtype.itemsize != size:
        return None, frozenset()
    return dtype, frozenset(chars)


def _char_as_str(cls: type, dtype: np.dtype, char_fields: frozenset[str]) -> bool | None:
    """Whether pymavlink's constructor turns char[N] bytes into ``str`` (True) or keeps the
    NUL-stripped bytes (False); None if the probe fails. Probed once per message class with a
    value holding a non-ASCII byte and an embedded NUL."""
    args: list[Any] = []
    for name in cls.fieldnames:  # type: ignore[attr-defined]
        shape = dtype.fields[name][0].shape  # type: ignore[index]
        if name in char_fields:
            args.append(b"A\xffB\x00C")
        elif shape:
            args.append([0] * int(np.prod(shape)))
        else:
            args.append(0)
    try:
        msg = cls(*args)
    except Exception:  # noqa: BLE001 - any failure means: decode this type with pymavlink
        return None
    values = [getattr(msg, name) for name in char_fields]
    if all(v == b"A\xffB\x00C".split(b"\x00", 1)[0].decode("ascii", errors="replace") for v in values):
        return True
    if all(v == b"A\xffB\x00C" for v in values):
        return False
    return None


def _wire_entry(cls: type) -> tuple[Any, ...]:
    """What the reader takes from one dialect class: (name, crc_extra, size, unpacker format,
    ordered_fieldnames, fieldnames, fast, char_as_str), ``fast`` False when the numpy layout
    cannot be made (a code without a numpy equivalent, or pymavlink's char handling unclear)."""
    fmt, size = cls.unpacker.format, int(cls.unpacker.size)  # type: ignore[attr-defined]
    ordered = tuple(cls.ordered_fieldnames)  # type: ignore[attr-defined]
    dtype, chars = _payload_dtype(fmt, ordered, size)
    as_str: bool | None = True
    if dtype is not None and chars:
        as_str = _char_as_str(cls, dtype, chars)
    return (cls.msgname, int(cls.crc_extra), size, fmt, ordered, tuple(cls.fieldnames),  # type: ignore[attr-defined]
            dtype is not None and as_str is not None, bool(as_str))


def _dialect_table() -> dict[int, tuple[Any, ...]]:
    """``_wire_entry`` of every message the dialect defines, by id (loads the dialect)."""
    return {int(mid): _wire_entry(cls) for mid, cls in _dialect().mavlink_map.items()}


def _wire_table_file() -> Path | None:
    """The cache file of the wire-layout table for the installed dialect: named by the dialect
    source's size and modification time and the table's version; None if it cannot be found."""
    try:
        spec = importlib.util.find_spec(DIALECT)  # its parent packages only, not the dialect
        origin = spec.origin if spec is not None else None
        st = os.stat(origin) if origin else None
    except (ImportError, OSError, ValueError):
        return None
    if st is None:
        return None
    key = f"{zlib.crc32(str(origin).encode()):08x}_{st.st_size:x}_{st.st_mtime_ns:x}_v{_WIRE_TABLE_VERSION}"
    return native.cache_dir() / f"mavlink_layouts_{key}.marshal"


@functools.cache
def _wire_table() -> dict[int, tuple[Any, ...]]:
    """``_dialect_table()``, kept in a cache file (``_wire_table_file``, beside the compiled
    kernels) after it is first made: reading it (a few ms) spares loading the dialect. A file
    that cannot be read or written is no error: the table is made from the dialect."""
    path = _wire_table_file()
    if path is not None:
        try:
            table = marshal.loads(path.read_bytes())
            if isinstance(table, dict) and table:
                return table
        except (OSError, ValueError, EOFError, TypeError):
            pass
    table = _dialect_table()
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
            tmp.write_bytes(marshal.dumps(table))
            os.replace(tmp, path)
        except OSError:
            pass
    return table


def _make_layout(msgid: int, entry: tuple[Any, ...]) -> MessageLayout:
    name, crc_extra, size, fmt, ordered, fieldnames, fast, as_str = entry
    dtype, chars = _payload_dtype(fmt, ordered, size)
    return MessageLayout(msgid=msgid, name=name, crc_extra=crc_extra, size=size, dtype=dtype if fast else None,
                         fieldnames=tuple(fieldnames), char_fields=chars, char_as_str=as_str if fast else True)


@functools.cache
def layout_of(msgid: int) -> MessageLayout | None:
    """Decoding layout of message ``msgid`` (None if the ardupilotmega dialect does not
    define it), built on first use."""
    entry = _wire_table().get(msgid)
    return None if entry is None else _make_layout(msgid, entry)


def layouts() -> dict[int, MessageLayout]:
    """Decoding layout of every message the dialect defines, by message id."""
    return {mid: lay for mid in _wire_table() if (lay := layout_of(int(mid))) is not None}


@functools.cache
def _crc_extra_lookup() -> tuple[np.ndarray, np.ndarray]:
    """(known, crc_extra): arrays indexed by message id (size max id + 2; the last slot is
    where out-of-range ids are clipped to, and is unknown)."""
    table = _wire_table()
    size = max(table) + 2
    known = np.zeros(size, dtype=bool)
    extra = np.zeros(size, dtype=np.uint8)
    for mid, entry in table.items():
        known[mid] = True
        extra[mid] = entry[1]
    return known, extra


def _view_as(buf: np.ndarray, dtype: str) -> np.ndarray:
    """``buf`` (uint8) as overlapping items of ``dtype``, one starting at every byte: item
    ``i`` is the value stored in ``buf[i:i + itemsize]``."""
    dt = np.dtype(dtype)
    return np.ndarray(shape=(len(buf) - dt.itemsize + 1,), dtype=dt, buffer=buf, strides=(1,))


def gather_rows(buf: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """The bytes ``buf[a:a + width]`` for each ``a`` in ``starts``: (n, width) uint8, a copy.

    ``buf`` (uint8, C-contiguous) must extend ``width`` bytes past every start. Gathers
    whole rows as ``width``-byte items of an overlapping view (stride 1 byte), one copy per row
    rather than per byte.
    """
    items = np.ndarray(shape=(len(buf) - width + 1,), dtype=np.dtype((np.void, width)),
                       buffer=buf, strides=(1,))
    return items[starts].view(np.uint8).reshape(len(starts), width)


# ---------------------------------------------------------------------------------------------
# CRC-16/MCRF4XX (X.25), vectorised


@functools.cache
def _crc_tables() -> tuple[np.ndarray, np.ndarray]:
    """Tables for a position-wise, vectorised CRC-16/MCRF4XX.

    The CRC is affine over GF(2): ``crc(b_1..b_L) = Z^L(0xFFFF) ^ XOR_j Z^(L-j)(T[b_j])``, with
    ``T`` the byte table and ``Z(c) = (c >> 8) ^ T[c & 0xFF]`` one step with a zero byte.
    Returns ``pos[k, b] = Z^k(T[b])`` (shape (K, 256), uint16) and ``init[k] = Z^k(0xFFFF)``.
    """
    n = _MAX_PACKET_LEN + 2
    x = np.arange(256, dtype=np.uint16)
    tmp = (x ^ (x << 4)) & 0xFF
    t0 = ((tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)).astype(np.uint16)
    pos = np.empty((n, 256), dtype=np.uint16)
    pos[0] = t0
    for k in range(1, n):
        prev = pos[k - 1]
        pos[k] = (prev >> 8) ^ t0[prev & 0xFF]
    init = np.empty(n, dtype=np.uint16)
    c = 0xFFFF
    for k in range(n):
        init[k] = c
        c = (c >> 8) ^ int(t0[c & 0xFF])
    return pos, init


def crc16_mcrf4xx(data: bytes) -> int:
    """CRC-16/MCRF4XX of ``data`` (the MAVLink checksum without crc_extra), scalar reference."""
    crc = 0xFFFF
    for b in data:
        tmp = (b ^ (crc & 0xFF)) & 0xFF
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc


@functools.cache
def _pair_table(d: int) -> np.ndarray:
    """Contribution of a little-endian byte pair ``x = b_0 | b_1 << 8`` whose second byte is
    ``d`` steps from the end of the CRC'd sequence: (65536,) uint16."""
    pos, _ = _crc_tables()
    return np.bitwise_xor.outer(pos[d], pos[d + 1]).reshape(-1)  # index: b_1 * 256 + b_0


def _crc_linear(rows: np.ndarray) -> np.ndarray:
    """The data-dependent part of the CRC of rows of bytes followed by one more byte:
    ``XOR_c Z^(M-c)(T[rows[:, c]])``. ``rows``: (n, M) uint8, C-contiguous, M even.
    Works on blocks of rows, two bytes per table look-up. Returns (n,) uint16."""
    n, width = rows.shape
    pairs = rows.view("<u2")
    tables = [_pair_table(width - c - 1) for c in range(0, width, 2)]
    out = np.zeros(n, dtype=np.uint16)
    block = _CRC_ROWS_PER_BLOCK
    for a in range(0, n, block):
        cols = np.ascontiguousarray(pairs[a:a + block].T)
        acc = out[a:a + block]
        for tab, col in zip(tables, cols, strict=True):
            acc ^= tab.take(col)
    return out


def crc_of_rows(rows: np.ndarray, extra: np.ndarray | int) -> np.ndarray:
    """MAVLink CRCs of equal-length byte rows.

    ``rows``: (n, L) uint8, the bytes after STX up to the end of the payload; ``extra``:
    crc_extra of each row's message ((n,) uint8 or one int). Returns (n,) uint16.
    """
    pos, init = _crc_tables()
    n, length = rows.shape
    if length % 2:  # a leading zero byte leaves the data-dependent part unchanged
        rows = np.concatenate((np.zeros((n, 1), dtype=np.uint8), rows), axis=1)
    crc = _crc_linear(np.ascontiguousarray(rows, dtype=np.uint8))
    crc ^= init[length + 1]
    crc ^= pos[0][np.asarray(extra, dtype=np.uint8)]
    return crc


def _check_crc(buf: np.ndarray, s: np.ndarray, covered: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """Which candidate packets carry a good CRC. ``s``: STX positions; ``covered``: bytes
    after STX up to the end of the payload (header - 1 + payload length); ``extra``: the
    message's crc_extra. Candidates must lie inside ``buf`` (padding included) and ``s >= 7``.
    Returns (n,) bool.

    Packets are checked in a few width classes (multiples of ``_CRC_WIDTH_STEP`` bytes): each
    row is the ``width`` bytes that end with the payload, its bytes before STX + 1 zeroed;
    leading zeros leave the data-dependent part of the CRC unchanged.
    """
    pos, init = _crc_tables()
    good = np.zeros(len(s), dtype=bool)
    if len(s) == 0:
        return good
    crc_at = s + 1 + covered
    stored = _view_as(buf, "<u2")[crc_at]
    expected_const = init[covered + 1] ^ pos[0][extra]
    key = ((covered + (_CRC_WIDTH_STEP - 1)) & -_CRC_WIDTH_STEP).astype(np.uint16)  # width class
    start = crc_at - key  # >= 0: STX is at 8 or later, and the row reaches back at most 7 before STX + 1
    order = np.argsort(key, kind="stable")  # radix sort on 16-bit keys
    bounds = np.flatnonzero(np.diff(key[order])) + 1
    for group in np.split(order, bounds):
        w = int(key[group[0]])
        step = max(1, _CRC_BLOCK_BYTES // w)
        for a in range(0, len(group), step):
            idx = group[a:a + step]
            rows = gather_rows(buf, start[idx], w)
            lead = w - covered[idx]  # 0-7 bytes before STX + 1, in the row's first 8: zero them
            rows.view("<u8")[:, 0] &= _KEEP_FROM[lead]
            good[idx] = (_crc_linear(rows) ^ expected_const[idx]) == stored[idx]
    return good


# ---------------------------------------------------------------------------------------------
# Finding packets


@dataclass
class _Packets:
    """Packets (or candidates) as parallel arrays of length n, sorted by position.

    ``s``: offset of STX in the file (int64); ``hdr``: header length, 6 or 10 (uint8);
    ``plen``: payload length as sent (int16); ``total``: packet length with CRC and signature
    (int16); ``msgid``: message id (int32); ``sysid``, ``compid``: sender (uint8);
    ``t_us``: the 8 bytes before STX as a big-endian time, µs (uint64).
    """

    s: np.ndarray
    hdr: np.ndarray
    plen: np.ndarray
    total: np.ndarray
    msgid: np.ndarray
    sysid: np.ndarray
    compid: np.ndarray
    t_us: np.ndarray

    _FIELDS = ("s", "hdr", "plen", "total", "msgid", "sysid", "compid", "t_us")

    @functools.cached_property
    def end(self) -> np.ndarray:
        """Offset just past each packet (int64)."""
        return self.s + self.total

    def subset(self, idx: np.ndarray) -> _Packets:
        return _Packets(*(getattr(self, f)[idx] for f in self._FIELDS))

    def where(self, mask: np.ndarray) -> _Packets:
        """The packets where ``mask`` is True (self when it is True everywhere)."""
        return self if mask.all() else self.subset(np.flatnonzero(mask))

    @staticmethod
    def concat(parts: list[_Packets]) -> _Packets:
        """All of ``parts`` in one; empties ``parts`` as it goes (memory)."""
        if not parts:
            return _parse_headers(np.zeros(_PAD, dtype=np.uint8), np.zeros(0, dtype=np.int64))[0]
        if len(parts) == 1:
            return parts.pop()
        columns = []
        for f in _Packets._FIELDS:
            columns.append(np.concatenate([getattr(p, f) for p in parts]))
            for p in parts:
                setattr(p, f, None)
        return _Packets(*columns)


def _is_stx(b: np.ndarray) -> np.ndarray:
    """Which bytes are 0xFE or 0xFD."""
    return (b - np.uint8(STX_V2)) < 2


def _claimed_end(buf: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Where packets starting at ``s`` end, by their STX, length and signed flag (int64)."""
    head = _view_as(buf, "<u4")[s]  # STX, length, flags (v2) in one gather (``buf`` is padded past the end)
    v2 = (head & 0xFF) == STX_V2
    length = (head >> 8) & 0xFF
    signed = (head >> 16) & v2  # bit 0: MAVLink 2's "signed" flag
    return s + np.where(v2, HEADER_LEN_V2 + CRC_LEN, HEADER_LEN_V1 + CRC_LEN) + length.astype(np.int64) + \
        SIGNATURE_LEN * (signed & 1).astype(np.int64)


def _find_stx(buf: np.ndarray, n_bytes: int, chunk: int = _SCAN_CHUNK) -> Iterator[np.ndarray]:
    """Positions (int64) of 0xFE / 0xFD bytes at or after offset 8, chunk by chunk."""
    for a in range(TIME_HEADER_LEN, n_bytes, chunk):
        part = buf[a:min(a + chunk, n_bytes)]
        hits = np.flatnonzero(part >= STX_V2)  # 0xFD, 0xFE and 0xFF: one pass over the bytes
        yield hits[part[hits] != 0xFF] + a


def _parse_headers(buf: np.ndarray, s: np.ndarray) -> tuple[_Packets, np.ndarray]:
    """What the time headers and packet headers of the candidates at ``s`` (all >= 8) say
    (``buf`` padded past the file end), and whether each is decodable: a message id the
    dialect defines and MAVLink 2 incompatibility flags pymavlink accepts (only "signed")."""
    head = gather_rows(buf, s - TIME_HEADER_LEN, TIME_HEADER_LEN + HEADER_LEN_V2)
    t_us = np.ascontiguousarray(head[:, :TIME_HEADER_LEN]).view(">u8").reshape(-1).astype(np.uint64)
    head = head[:, TIME_HEADER_LEN:]
    v2 = head[:, 0] == STX_V2
    plen = head[:, 1].astype(np.int16)
    flags = head[:, 2] * v2
    hdr = np.where(v2, HEADER_LEN_V2, HEADER_LEN_V1).astype(np.uint8)
    total = hdr + plen + CRC_LEN + SIGNATURE_LEN * (flags & 1)
    id_v2 = (head[:, 7].astype(np.int32) | (head[:, 8].astype(np.int32) << 8)
             | (head[:, 9].astype(np.int32) << 16))
    msgid = np.where(v2, id_v2, head[:, 5].astype(np.int32))
    sysid = np.where(v2, head[:, 5], head[:, 3])
    compid = np.where(v2, head[:, 6], head[:, 4])
    known_tab, _ = _crc_extra_lookup()
    ok = known_tab[np.minimum(msgid, len(known_tab) - 1)] & ((flags & 0xFE) == 0)
    return _Packets(s, hdr, plen, total.astype(np.int16), msgid, sysid, compid, t_us), ok


def _non_overlapping(s: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Mask of a largest set of packets whose bodies ``[s, end)`` do not overlap (``s``
    sorted). Isolated packets are kept; in each cluster of overlapping ones, the earliest
    finishing are taken first (optimal interval scheduling)."""
    n = len(s)
    keep = np.ones(n, dtype=bool)
    if n <= 1 or bool(np.all(s[1:] >= end[:-1])):  # each starts after the one before ends: none overlap
        return keep
    reach = np.maximum.accumulate(end)
    starts_cluster = np.ones(n, dtype=bool)
    starts_cluster[1:] = s[1:] >= reach[:-1]
    if starts_cluster.all():
        return keep
    cluster = np.cumsum(starts_cluster) - 1
    sizes = np.bincount(cluster)
    crowded = np.flatnonzero(sizes[cluster] > 1)
    keep[crowded] = False
    for members in np.split(crowded, np.flatnonzero(np.diff(cluster[crowded])) + 1):
        last_end = -1
        for i in members[np.argsort(end[members], kind="stable")]:
            if s[i] >= last_end:
                keep[i] = True
                last_end = int(end[i])
    return keep


def _between(pk: _Packets) -> np.ndarray:
    """Bytes from the end of each packet to the start of the next: ``s[1:] - end[:-1]`` (n - 1,),
    without making ``end`` for every packet."""
    out = np.subtract(pk.s[1:], pk.s[:-1])
    out -= pk.total[:-1]
    return out


def _gaps(pk: _Packets, n_bytes: int, *, header: int = TIME_HEADER_LEN, between: np.ndarray | None = None
          ) -> tuple[np.ndarray, np.ndarray]:
    """Byte ranges ``[a, b)`` not covered by any record (``header`` time bytes + packet) of
    the packets ``pk`` (sorted, bodies disjoint). ``header=0``: the ranges between packet
    bodies, longer than a time header (where another packet could be). ``between``:
    ``_between(pk)`` if already at hand."""
    s = pk.s
    if len(s) == 0:
        return np.array([0]), np.array([n_bytes])
    least = 0 if header else TIME_HEADER_LEN
    inner = np.flatnonzero((_between(pk) if between is None else between) > header + least)
    last_end = int(s[-1]) + int(pk.total[-1])
    a: list[Any] = [[0]] if s[0] - header > least else []
    a += [s[inner] + pk.total[inner]]
    b: list[Any] = [[s[0] - header]] if s[0] - header > least else []
    b += [s[inner + 1] - header]
    if n_bytes > last_end + least:
        a.append([last_end])
        b.append([n_bytes])
    return np.concatenate(a).astype(np.int64), np.concatenate(b).astype(np.int64)


@dataclass
class _Damage:
    """What was skipped, for ``Recording.skipped_*`` and the notes."""

    damaged_packets: int = 0
    damaged_bytes: int = 0
    garbage_bytes: int = 0
    garbage_places: int = 0
    first_garbage_at: int = -1
    truncated_bytes: int = 0
    unknown_packets: int = 0


def _header_at(buf: np.ndarray, p: int) -> tuple[int, int, bool]:
    """(packet length, message id, incompatibility flags valid) of the packet whose STX is at
    ``p`` (scalar version of ``_parse_headers``)."""
    if buf[p] == STX_V2:
        flags = int(buf[p + 2])
        sig = SIGNATURE_LEN if flags & 1 else 0
        msgid = int(buf[p + 7]) | (int(buf[p + 8]) << 8) | (int(buf[p + 9]) << 16)
        return HEADER_LEN_V2 + int(buf[p + 1]) + CRC_LEN + sig, msgid, (flags & 0xFE) == 0
    return HEADER_LEN_V1 + int(buf[p + 1]) + CRC_LEN, int(buf[p + 5]), True


@dataclass
class _GapWalk:
    """The record chain followed through one damaged byte range ``[a, b)``.

    ``records``: (stx, end, msgid, flags valid) of each complete packet the chain reaches;
    ``spanned``: bytes from ``a`` to the end of the last of them (at most ``b``);
    ``truncated``: bytes of a last record the file ends inside (0 if none);
    ``garbage``: the rest of the range.
    """

    records: list[tuple[int, int, int, bool]]
    spanned: int
    truncated: int
    garbage: int


def _walk_gap(buf: np.ndarray, a: int, b: int, n_bytes: int) -> _GapWalk:
    """Follow the record chain through the damaged range ``[a, b)``, expecting a record (8
    time bytes, then STX) at ``a`` and after each packet, as a sequential reader would."""
    records: list[tuple[int, int, int, bool]] = []
    rec_start = a
    spanned_to = a
    truncated = 0
    while True:
        p = rec_start + TIME_HEADER_LEN
        if b == n_bytes and rec_start < b <= p:  # the file ends inside a time header
            truncated = b - rec_start
            break
        if p >= b or buf[p] not in (STX_V1, STX_V2):
            break
        head_len = HEADER_LEN_V2 if buf[p] == STX_V2 else HEADER_LEN_V1
        total, msgid, flags_ok = _header_at(buf, p) if p + head_len <= n_bytes else (n_bytes, -1, False)
        e = p + total
        if e > n_bytes:  # the file ends inside this packet
            truncated = b - rec_start if b == n_bytes else 0
            if not truncated:
                spanned_to = b
                records.append((p, e, msgid, flags_ok))
            break
        records.append((p, e, msgid, flags_ok))
        spanned_to = min(e, b)
        if e >= b:
            break
        rec_start = e
    garbage = b - spanned_to - truncated
    return _GapWalk(records, spanned_to - a, truncated, garbage)


# ---------------------------------------------------------------------------------------------
# Record times


def _spikes(t: np.ndarray, tol_s: float) -> np.ndarray:
    """Which of ``t[2:-2]`` lie further than ``tol_s`` from the median of their four nearest
    neighbours, beyond the spread of the middle two of them. (n - 4,) bool."""
    a, b, c, d = t[:-4], t[1:-3], t[3:-1], t[4:]
    lo = np.maximum(np.minimum(a, b), np.minimum(c, d))  # the middle two of four values
    hi = np.minimum(np.maximum(a, b), np.maximum(c, d))
    return np.abs(t[2:-2] - 0.5 * (lo + hi)) > tol_s + np.abs(hi - lo)


def _repair_times(t_us: np.ndarray, untrusted: np.ndarray) -> tuple[np.ndarray, int]:
    """Record times in s, with those that cannot be right replaced by the previous trusted
    record's time; and how many were replaced.

    A time is damage when its header overlapped the packet before (``untrusted``) or when it
    is a spike: further than ``TIME_SPIKE_TOL_S`` from the median of its four nearest
    neighbours, beyond the spread of their middle two, so steps, gaps and backward jumps of
    the clock stay as they are. The first and last two records, with neighbours on one side
    only, use ``TIME_SPIKE_TOL_END_S``.
    """
    t = t_us / 1e6
    n = len(t)
    bad = untrusted.copy()
    block = 1 << 18
    # times that never go back have no spike: the middle two of a record's four neighbours are
    # the ones either side of it, so it lies within their spread (tests/test_speed_twins.py)
    if n >= 5 and not bool(np.all(t[1:] >= t[:-1])):
        for a in range(0, n - 4, block):
            hi = min(a + block, n - 4)
            bad[a + 2:hi + 2] |= _spikes(t[a:hi + 4], TIME_SPIKE_TOL_S)
    for i in sorted({i for i in (0, 1, n - 2, n - 1) if 0 <= i < n}):
        neigh = sorted(float(t[j]) for j in range(max(0, i - 2), min(n, i + 3)) if j != i)
        if neigh:
            m1, m2 = neigh[(len(neigh) - 1) // 2], neigh[len(neigh) // 2]
            bad[i] |= abs(float(t[i]) - 0.5 * (m1 + m2)) > TIME_SPIKE_TOL_END_S + abs(m2 - m1)
    n_bad = int(bad.sum())
    if n_bad:
        good_idx = np.where(bad, -1, np.arange(n))
        last_good = np.maximum.accumulate(good_idx)
        first_good = np.flatnonzero(~bad)
        last_good[last_good < 0] = first_good[0] if len(first_good) else 0
        t = t[last_good]
    return t, n_bad


# ---------------------------------------------------------------------------------------------
# Decoding


def _decode_chars(col: np.ndarray, as_str: bool) -> np.ndarray:
    """char[N] column (numpy ``S`` dtype, trailing NULs already gone) as pymavlink gives it."""
    uniq, inverse = np.unique(col, return_inverse=True)
    if as_str:
        values = [u.split(b"\x00", 1)[0].decode("ascii", errors="replace") for u in uniq.tolist()]
    else:
        values = list(uniq.tolist())
    out = np.empty(len(values), dtype=object)
    out[:] = values
    return out[inverse.reshape(-1)]


def _decode_fast(buf: np.ndarray, lay: MessageLayout, payload_at: np.ndarray,
                 plen: np.ndarray) -> dict[str, np.ndarray]:
    """Columns of ``lay``'s messages whose payloads start at ``payload_at`` with lengths
    ``plen`` (shorter than the wire size: truncated trailing zeros; longer: cut, as pymavlink
    does). Arrays (n,) or (n, k) in the wire dtypes; char[N] as object arrays. Works in
    blocks of rows so each block's bytes stay in the CPU caches while its fields are copied."""
    assert lay.dtype is not None
    size = lay.size
    n = len(payload_at)
    numeric = [name for name in lay.fieldnames if name not in lay.char_fields]
    out: dict[str, np.ndarray] = {}
    for name in numeric:
        sub = lay.dtype.fields[name][0]  # type: ignore[index]
        out[name] = np.empty((n, *sub.shape), dtype=sub.base.newbyteorder("="))
    chars: dict[str, list[np.ndarray]] = {name: [] for name in lay.char_fields}
    block = max(1, _DECODE_BLOCK_BYTES // size)
    cut = np.arange(size, dtype=np.int16)
    for a in range(0, n, block):
        rows = gather_rows(buf, payload_at[a:a + block], size)
        length = plen[a:a + block]
        if (length < size).any():
            rows *= cut < length[:, None]
        rec = rows.view(lay.dtype).reshape(-1)
        for name in numeric:
            out[name][a:a + block] = rec[name]
        for name, parts in chars.items():
            parts.append(rec[name].copy())
    for name, parts in chars.items():
        out[name] = _decode_chars(np.concatenate(parts), lay.char_as_str)
    return {name: out[name] for name in lay.fieldnames}


_MAVLINK_TYPES = {"int8_t": "i1", "uint8_t": "u1", "int16_t": "i2", "uint16_t": "u2", "int32_t": "i4",
                  "uint32_t": "u4", "int64_t": "i8", "uint64_t": "u8", "float": "f4", "double": "f8"}


def _decode_pymavlink(buf: np.ndarray, lay: MessageLayout, s: np.ndarray,
                      end: np.ndarray) -> dict[str, np.ndarray]:
    """Columns of ``lay``'s packets ``[s, end)`` decoded one by one with pymavlink, in the
    dtypes the message definition gives (``fieldtypes``); char[N] as object arrays."""
    mav = _dialect().MAVLink(None)
    values: dict[str, list[Any]] = {name: [] for name in lay.fieldnames}
    for a, e in zip(s.tolist(), end.tolist(), strict=True):
        msg = mav.decode(bytearray(buf[a:e].tobytes()))
        for name in lay.fieldnames:
            values[name].append(getattr(msg, name))
    types = dict(zip(lay.cls.fieldnames, lay.cls.fieldtypes, strict=True))  # type: ignore[attr-defined]
    fields = {}
    for name, vals in values.items():
        code = _MAVLINK_TYPES.get(types[name].removesuffix("_mavlink_version"))
        if code is None:  # char[N] and anything else: as pymavlink gives it
            col = np.empty(len(vals), dtype=object)
            col[:] = vals
            fields[name] = col
        else:
            fields[name] = np.array(vals, dtype=code)
    return fields


def _unknown_fields(buf: np.ndarray, s: np.ndarray, end: np.ndarray) -> dict[str, np.ndarray]:
    data = np.empty(len(s), dtype=object)
    data[:] = [buf[a:e].tobytes() for a, e in zip(s.tolist(), end.tolist(), strict=True)]
    return {"data": data}


# ---------------------------------------------------------------------------------------------
# The reader


#: files at least this large are mapped into memory rather than copied (``_map_file``)
MAP_MIN_BYTES = 1 << 20


class _Mapping:
    """A read-only private mapping of a file followed by zero pages (Linux, through libc's
    ``mmap``): ``length`` bytes at ``address``, unmapped when this object is collected."""

    def __init__(self, address: int, length: int, munmap: Any) -> None:
        self.address, self.length, self._munmap = address, length, munmap
        self.__array_interface__ = {"shape": (length,), "typestr": "|u1", "data": (address, True), "version": 3}

    def __del__(self) -> None:
        self._munmap(self.address, self.length)


def _map_file(path: Path, n_bytes: int) -> np.ndarray | None:
    """The file's bytes followed by at least ``_PAD`` zero bytes, as a read-only uint8 array
    mapped from the page cache (no copy, and no page faults one 4 KiB page at a time: an hour-long
    recording's 86 MB cost 0.1-0.2 s to copy in a fresh process). An anonymous zero mapping of
    the whole length is made first and the file mapped over its start (MAP_FIXED); the kernel
    zero-fills the file's last page past its end. None where this is not available (not Linux,
    no libc): the caller copies the file instead."""
    import ctypes
    import ctypes.util
    import mmap

    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.mmap.restype = ctypes.c_void_p
        libc.mmap.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                              ctypes.c_long)
        libc.munmap.argtypes = (ctypes.c_void_p, ctypes.c_size_t)
        page = mmap.PAGESIZE
        length = -(-(n_bytes + _PAD) // page) * page
        failed = ctypes.c_void_p(-1).value
        anon = getattr(mmap, "MAP_ANONYMOUS", 0x20)
        base = libc.mmap(None, length, mmap.PROT_READ, mmap.MAP_PRIVATE | anon, -1, 0)
        if base in (None, failed):
            return None
        with open(path, "rb") as f:
            at = libc.mmap(base, n_bytes, mmap.PROT_READ,
                           mmap.MAP_PRIVATE | 0x10 | getattr(mmap, "MAP_POPULATE", 0), f.fileno(), 0)  # 0x10: MAP_FIXED
        if at != base:
            libc.munmap(base, length)
            return None
    except (OSError, AttributeError, TypeError, ValueError):
        return None
    return np.asarray(_Mapping(base, length, libc.munmap))


def _load(path: Path) -> tuple[np.ndarray, int]:
    """The file's bytes in a zero-padded uint8 array, and the file length (a ``.gz`` file:
    decompressed in memory, and the decompressed length)."""
    if is_gzip_path(path):
        data = read_recording_bytes(path)
        n_bytes = len(data)
        buf = np.empty(n_bytes + _PAD, dtype=np.uint8)
        buf[:n_bytes] = np.frombuffer(data, dtype=np.uint8)
        buf[n_bytes:] = 0
        return buf, n_bytes
    n_bytes = path.stat().st_size
    if n_bytes >= MAP_MIN_BYTES:
        mapped = _map_file(path, n_bytes)
        if mapped is not None:
            return mapped, n_bytes
    buf = np.empty(n_bytes + _PAD, dtype=np.uint8)
    buf[n_bytes:] = 0
    with open(path, "rb") as f:
        got = f.readinto(buf.data[:n_bytes])
    if got != n_bytes:
        raise RecordingError(f"{path.name}: could not read the whole file ({got} of {n_bytes} bytes)")
    return buf, n_bytes


class _Progress:
    """A tqdm bar on stderr in percent of the work (scan 60, repairs 10, decoding 30), or
    nothing when disabled."""

    def __init__(self, enabled: bool, desc: str) -> None:
        self.bar = None
        self.done = 0.0
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=100, desc=desc, unit="%", file=sys.stderr, leave=False,
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]")

    def advance(self, percent: float) -> None:
        if self.bar is not None:
            step = min(percent, 100.0 - self.done)
            self.done += step
            self.bar.update(step)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _pass1_native(lib: Any, buf: np.ndarray, n_bytes: int, progress: _Progress
                  ) -> tuple[list[_Packets], list[np.ndarray]]:
    """Pass 1 of ``_find_packets`` by the compiled kernel (``fh_scan`` in companion/native/kernels.c,
    the numpy pass candidate by candidate): the good packets, and the candidates that fit but are
    not chained. Each candidate is judged on its own, so the file is scanned in as many ranges as
    ``native.threads()`` (files from ``_PARALLEL_MIN_BYTES``), one per thread, and the ranges'
    findings put in file order: the same as one scan from start to end.

    Each range's packets are first counted along the record chain (``fh_count``: no CRC), so
    that every thread writes its packets straight into its own rows of one set of arrays; in a
    fresh process every new page costs its zeroing, and copying the later ranges' packets in
    after the first's cost a second set of pages. Where a range's scan finds another number of
    packets than its count (damage, unknown ids, a CRC error), the ranges' findings are joined
    by a copy instead: the same packets either way."""
    n_threads = native.threads() if n_bytes >= _PARALLEL_MIN_BYTES else 1
    cuts = [TIME_HEADER_LEN + (n_bytes - TIME_HEADER_LEN) * k // n_threads for k in range(n_threads + 1)]
    lock = threading.Lock()
    nf = len(_Packets._FIELDS)
    if n_threads == 1:
        one = _scan_range(lib, buf, n_bytes, cuts[0], cuts[1], n_bytes, progress, lock)
        good = _append_into_first([(arrays[:nf], n) for arrays, n, _ in one])
        other = _append_into_first([(arrays[nf:], n) for arrays, _, n in one])
        return [_Packets(*arrays) for arrays in good], [arrays[0] for arrays in other]

    known_u8 = _crc_extra_lookup()[0].view(np.uint8)

    def count(k: int) -> int:
        return int(lib.fh_count(buf.ctypes.data, n_bytes, cuts[k], cuts[k + 1], known_u8.ctypes.data,
                                len(known_u8)))

    counts = native.run_all([functools.partial(count, k) for k in range(n_threads)], n_threads)
    rows = [0, *itertools.accumulate(counts)]
    shared = [np.empty(rows[-1], dt) for dt in _SCAN_DTYPES[:nf]]

    def scan(k: int) -> list[tuple[list[np.ndarray], int, int]]:
        into = [a[rows[k]:rows[k + 1]] for a in shared]
        return _scan_range(lib, buf, n_bytes, cuts[k], cuts[k + 1], cuts[k + 1], progress, lock, into)

    found = native.run_all([functools.partial(scan, k) for k in range(n_threads)], n_threads)
    other = _append_into_first([(arrays[nf:], n) for parts in found for arrays, _, n in parts])
    # every range filled exactly its rows (a range's scan goes on in new arrays past its rows,
    # finding no more good packets there when the count was right)
    if all(parts[0][1] == n and not any(g for _, g, _ in parts[1:]) for parts, n in zip(found, counts, strict=True)):
        good = [shared]
    else:
        good = [[np.concatenate([arrays[f][:n] for parts in found for arrays, n, _ in parts]) for f in range(nf)]]
    return [_Packets(*arrays) for arrays in good], [arrays[0] for arrays in other]


#: the arrays ``_scan_range`` fills: the ``_Packets`` fields, then the other candidates' positions
_SCAN_DTYPES = (np.int64, np.uint8, np.int16, np.int16, np.int32, np.uint8, np.uint8, np.uint64, np.int64)


def _scan_range(lib: Any, buf: np.ndarray, n_bytes: int, pos: int, stop: int, sized_for: int, progress: _Progress,
                lock: threading.Lock, into: list[np.ndarray] | None = None) -> list[tuple[list[np.ndarray], int, int]]:
    """``fh_scan`` over the candidates in [pos, stop), in ``_SCAN_CHUNK`` steps (for the progress
    bar), into arrays sized for a record every 16 bytes of [pos, sized_for) (the shortest record:
    more is possible only with overlapping candidates, and then the scan goes on in new arrays);
    pages never written are never touched. ``into``: arrays (views) for the first good packets,
    of the length the caller expects; the scan goes on in new arrays when they are full.
    Returns each set of arrays used (the ``_Packets`` fields, then the other candidates) with its
    counts of good packets and other candidates."""
    known_tab, extra_tab = _crc_extra_lookup()
    known_u8 = known_tab.view(np.uint8)
    n_good = ctypes.c_int64()
    n_other = ctypes.c_int64()
    out: list[tuple[list[np.ndarray], int, int]] = []
    nf = len(_Packets._FIELDS)
    while pos < stop:
        cap = (sized_for - pos) // 16 + 64
        if into is not None:
            arrays = [*into, np.empty(cap, _SCAN_DTYPES[nf])]
            into = None
        else:
            arrays = [np.empty(cap, dt) for dt in _SCAN_DTYPES]
        cap_good, cap_other = len(arrays[0]), len(arrays[-1])
        done_good = done_other = 0
        while pos < stop and done_good < cap_good and done_other < cap_other:
            step = min(pos + _SCAN_CHUNK, stop)
            reached = lib.fh_scan(buf.ctypes.data, n_bytes, pos, step, known_u8.ctypes.data, extra_tab.ctypes.data,
                                  len(known_tab), cap_good - done_good,
                                  *(a[done_good:].ctypes.data for a in arrays[:-1]), ctypes.byref(n_good),
                                  cap_other - done_other, arrays[-1][done_other:].ctypes.data, ctypes.byref(n_other))
            done_good += n_good.value
            done_other += n_other.value
            with lock:
                progress.advance(60.0 * (reached - pos) / max(1, n_bytes - TIME_HEADER_LEN))
            pos = reached
        out.append((arrays, done_good, done_other))
    return out


def _append_into_first(parts: list[tuple[list[np.ndarray], int]]) -> list[list[np.ndarray]]:
    """The rows of ``parts`` (each: arrays of a common capacity, the first ``n`` rows used) in
    order, as few sets of arrays as may be: the later parts' rows are copied in after the first's
    as long as its arrays have room."""
    if not parts:
        return []
    first, used = parts[0]
    rest: list[list[np.ndarray]] = []
    for arrays, n in parts[1:]:
        if not rest and used + n <= len(first[0]):
            for dst, src in zip(first, arrays, strict=True):
                dst[used:used + n] = src[:n]
            used += n
        else:
            rest.append([a[:n] for a in arrays])
    return [[a[:used] for a in first], *rest]


def _find_packets(buf: np.ndarray, n_bytes: int, progress: _Progress
                  ) -> tuple[_Packets, np.ndarray, np.ndarray, _Damage]:
    """The good packets of the file, sorted by position; whether each one's time header
    overlaps the packet before (its time is then unreliable); the bytes between each packet
    and the next (``_between``); and the damage found."""
    known_tab, extra_tab = _crc_extra_lookup()

    def check(c: _Packets) -> _Packets:
        covered = c.hdr.astype(np.int16) - 1 + c.plen
        return c.where(_check_crc(buf, c.s, covered, extra_tab[c.msgid]))

    # pass 1: candidates that sit in an unbroken record chain, chunk by chunk
    lib = native.kernels()
    if lib is not None:
        good_parts, other_parts = _pass1_native(lib, buf, n_bytes, progress)
    else:
        good_parts, other_parts = [], []
        n_chunks = max(1, -(-(n_bytes - TIME_HEADER_LEN) // _SCAN_CHUNK))
        for s in _find_stx(buf, n_bytes):
            progress.advance(60.0 / n_chunks)
            # a first, cheap look: does the record chain go on for two more records from here?
            end = _claimed_end(buf, s)
            fits = end <= n_bytes
            nxt = np.minimum(end + TIME_HEADER_LEN, n_bytes)  # the padding after n_bytes is zero
            end2 = _claimed_end(buf, nxt)
            chained = (end == n_bytes) | (
                _is_stx(buf[nxt]) & ((end2 == n_bytes) | _is_stx(buf[np.minimum(end2 + TIME_HEADER_LEN, n_bytes)])))
            cand, ok = _parse_headers(buf, s[chained & fits])
            good_parts.append(check(cand.where(ok)))
            other_parts.append(s[~chained & fits])
    good = _Packets.concat(good_parts)
    del good_parts
    between = _between(good)  # kept while the packets are, for the gaps and the overlaps
    if not bool(np.all(between >= 0)):
        good = good.where(_non_overlapping(good.s, good.end))
        between = _between(good)

    # pass 2: every other candidate whose body lies between the bodies of the packets found
    # (its time header may overlap the packet before; the next one's may overlap it)
    gap_a, gap_b = _gaps(good, n_bytes, header=0, between=between)
    if len(gap_a):
        rest_s = np.concatenate(other_parts) if other_parts else np.zeros(0, dtype=np.int64)
        gi = np.searchsorted(gap_a, rest_s, side="right") - 1
        rest, ok = _parse_headers(buf, rest_s[gi >= 0])
        gi = gi[gi >= 0]
        rest = check(rest.where(ok & (rest.end <= gap_b[gi])))
        rest = rest.where(_non_overlapping(rest.s, rest.end))
        order = np.argsort(np.concatenate((good.s, rest.s)), kind="stable")
        good = _Packets.concat([good, rest]).subset(order)
        between = _between(good)
    del other_parts, gap_a, gap_b
    progress.advance(5.0)

    # what is left between the records: follow the expected record chain through each gap
    damage = _Damage()
    unknown: list[int] = []
    gap_a, gap_b = _gaps(good, n_bytes, between=between)
    for a, b in zip(gap_a.tolist(), gap_b.tolist(), strict=True):
        walk = _walk_gap(buf, a, b, n_bytes)
        # packets of ids the dialect does not define: kept where they fill the gap exactly
        if (walk.records and not walk.truncated and walk.records[-1][1] == b
                and all(ok and not known_tab[min(mid, len(known_tab) - 1)] for _, _, mid, ok in walk.records)):
            unknown.extend(p for p, _, _, _ in walk.records)
            continue
        damage.damaged_packets += len(walk.records)
        damage.damaged_bytes += walk.spanned
        damage.truncated_bytes += walk.truncated
        if walk.garbage:
            damage.garbage_bytes += walk.garbage
            damage.garbage_places += 1
            if damage.first_garbage_at < 0:
                damage.first_garbage_at = a + walk.spanned
    if unknown:
        damage.unknown_packets = len(unknown)
        extra, _ = _parse_headers(buf, np.array(unknown, dtype=np.int64))
        order = np.argsort(np.concatenate((good.s, extra.s)), kind="stable")
        good = _Packets.concat([good, extra]).subset(order)
        between = _between(good)
    progress.advance(5.0)

    overlapped = np.zeros(len(good.s), dtype=bool)
    overlapped[1:] = between < TIME_HEADER_LEN
    return good, overlapped, between, damage


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" + ("" if n == 1 else "s")


def _notes(damage: _Damage, backwards: int, back_max_s: float, repaired_times: int) -> list[str]:
    """One line per kind of damage found while reading."""
    notes = []
    if damage.damaged_packets:
        notes.append(f"skipped {damage.damaged_bytes} bytes: {_plural(damage.damaged_packets, 'damaged packet')} "
                     "(bad CRC or header)")
    if damage.garbage_bytes:
        notes.append(f"skipped {damage.garbage_bytes} bytes of unrecognisable data in "
                     f"{_plural(damage.garbage_places, 'place')} (the first at byte {damage.first_garbage_at})")
    if damage.truncated_bytes:
        notes.append(f"skipped {damage.truncated_bytes} bytes: truncated last record")
    if damage.unknown_packets:
        notes.append(f"kept {_plural(damage.unknown_packets, 'packet')} of message ids the ardupilotmega "
                     "dialect does not define as UNKNOWN_<id> (CRC not checkable)")
    if repaired_times:
        notes.append(f"{_plural(repaired_times, 'record')} had a damaged timestamp: given the previous "
                     "record's time")
    if backwards:
        notes.append(f"{_plural(backwards, 'record')} timestamped earlier than the record before "
                     f"(by up to {back_max_s:.3f} s): kept in file order")
    return notes


def _tables(buf: np.ndarray, pk: _Packets, t_s: np.ndarray, progress: _Progress,
            fields: Mapping[str, Collection[str]] | None = None) -> dict[str, MessageTable]:
    """One MessageTable per message type, in order of first appearance (``fields``: as
    ``read_tlog``'s)."""
    lib = native.kernels() if sys.byteorder == "little" else None
    if lib is not None and len(pk.s):
        return _tables_native(lib, buf, pk, t_s, progress, fields)
    return _tables_numpy(buf, pk, t_s, progress)


def _tables_numpy(buf: np.ndarray, pk: _Packets, t_s: np.ndarray, progress: _Progress
                  ) -> dict[str, MessageTable]:
    """``_tables``: the types grouped by a stable sort, each decoded at once (``_decode_fast``)."""
    # group by message id (a dense 16-bit code, so the stable sort is a radix sort)
    ids = np.array(sorted(_wire_table()), dtype=np.int64)
    code_tab = np.full(int(ids[-1]) + 2, len(ids), dtype=np.uint16)
    code_tab[ids] = np.arange(len(ids), dtype=np.uint16)
    code = code_tab[np.minimum(pk.msgid, len(code_tab) - 1)]
    order = np.argsort(code, kind="stable")
    groups = np.split(order, np.flatnonzero(np.diff(code[order])) + 1)
    del order, code
    if int(pk.msgid[groups[-1][0]]) not in _wire_table():  # unknown ids, one by one
        unknown = groups.pop()
        for mid in np.unique(pk.msgid[unknown]).tolist():
            groups.append(unknown[pk.msgid[unknown] == mid])
    groups.sort(key=lambda g: int(g[0]))
    tables: dict[str, MessageTable] = {}
    for idx in groups:
        mid = int(pk.msgid[idx[0]])
        s = pk.s[idx]
        lay = layout_of(mid)
        if lay is None:
            name = f"UNKNOWN_{mid}"
            fields = _unknown_fields(buf, s, s + pk.total[idx])
        elif lay.dtype is None:
            name = lay.name
            fields = _decode_pymavlink(buf, lay, s, s + pk.total[idx])
        else:
            name = lay.name
            fields = _decode_fast(buf, lay, s + pk.hdr[idx], pk.plen[idx])
        progress.advance(30.0 * len(idx) / len(pk.s))
        tables[name] = MessageTable(name=name, t_s=t_s[idx], sysid=pk.sysid[idx], compid=pk.compid[idx],
                                    record=idx.astype(np.int64, copy=False), fields=fields)
    return tables


def _tables_native(lib: Any, buf: np.ndarray, pk: _Packets, t_s: np.ndarray, progress: _Progress,
                   fields: Mapping[str, Collection[str]] | None = None) -> dict[str, MessageTable]:
    """``_tables_numpy`` with the types the fast path lays out made by the compiled kernel
    ``fh_tables``: one pass over the packets in file order (shared among threads in ranges of
    packets), each packet's time, sender, record and fields copied straight into its table's
    columns; the other types (no numpy layout, unknown ids) by ``_tables_numpy``.

    ``fields``: message name -> the fields to decode in that pass; every other field of the
    type is decoded when first asked for (``columnar.LazyColumns``, by ``fh_fields`` from the
    packets the rows point at: ``buf`` and the packets' positions are kept for that while the
    table lives). None: every field in the pass."""
    n = len(pk.s)
    top = int(pk.msgid.max()) + 1
    counts = np.bincount(pk.msgid, minlength=top)
    fast = [int(m) for m in np.flatnonzero(counts)
            if (lay := layout_of(int(m))) is not None and lay.dtype is not None]
    group_of = np.full(top, -1, dtype=np.int32)
    group_of[fast] = np.arange(len(fast), dtype=np.int32)
    group = group_of[pk.msgid]
    # every column is carved out of one allocation: large enough for the kernel's transparent huge
    # pages (numpy asks for them from 4 MB on), where many separate columns would each fault in
    # their own 4 KiB pages: a third of the decoding time in a fresh process
    shapes: list[tuple[int, str, np.dtype, int, int]] = []  # (group, field, dtype, wire offset, rows)
    eager: list[tuple[str, ...]] = []
    for g, mid in enumerate(fast):
        lay = layout_of(mid)
        assert lay is not None and lay.dtype is not None
        k = int(counts[mid])
        wanted = lay.fieldnames if fields is None else tuple(f for f in lay.fieldnames
                                                             if f in fields.get(lay.name, ()))
        eager.append(wanted)
        for name in wanted:
            sub, off = lay.dtype.fields[name][:2]  # type: ignore[index]
            shapes.append((g, name, sub, off, k))
        for name, dt in (("\0t", np.dtype(np.float64)), ("\0sysid", np.dtype(np.uint8)),
                         ("\0compid", np.dtype(np.uint8)), ("\0record", np.dtype(np.int64))):
            shapes.append((g, name, dt, -1, k))
    align = 64
    spans = [-(-(k * dt.itemsize) // align) * align for _, _, dt, _, k in shapes]
    pool = np.empty(sum(spans) + align, dtype=np.uint8)
    at = -pool.ctypes.data % align
    sizes, first_field, offsets, widths, outs = [], [0], [], [], []
    columns: list[dict[str, np.ndarray]] = [{} for _ in fast]
    for (g, name, dt, off, k), span in zip(shapes, spans, strict=True):
        col = pool[at:at + k * dt.itemsize].view(dt.base.newbyteorder("=")).reshape(k, *dt.shape)
        at += span
        columns[g][name] = col
        if off >= 0:
            offsets.append(off)
            widths.append(dt.itemsize)
            outs.append(col.ctypes.data)
    for mid, wanted in zip(fast, eager, strict=True):
        lay = layout_of(mid)
        assert lay is not None
        sizes.append(lay.size)
        first_field.append(first_field[-1] + len(wanted))
    metas = [tuple(cols.pop(k) for k in ("\0t", "\0sysid", "\0compid", "\0record")) for cols in columns]

    def ints(values: list[int]) -> np.ndarray:
        return np.array(values or [0], dtype=np.int64)

    def ptrs(values: list[int]) -> Any:
        return (ctypes.c_void_p * max(1, len(values)))(*values)

    size_a, first_a, off_a, wid_a = ints(sizes), ints(first_field), ints(offsets), ints(widths)
    s = np.ascontiguousarray(pk.s, dtype=np.int64)
    hdr, plen = pk.hdr, pk.plen
    t = np.ascontiguousarray(t_s, dtype=np.float64)
    outs_p, metas_p = ptrs(outs), [ptrs([m[j].ctypes.data for m in metas]) for j in range(4)]
    # the packets in ranges, one per thread, each range's rows of a type starting after the rows
    # the ranges before it have of that type
    n_threads = native.threads() if n >= _PARALLEL_MIN_PACKETS else 1
    cuts = [n * k // n_threads for k in range(n_threads + 1)]
    rows = np.zeros((n_threads, max(1, len(fast))), dtype=np.int64)
    for k in range(1, n_threads):
        rows[k, :len(fast)] = rows[k - 1, :len(fast)] + np.bincount(group[cuts[k - 1]:cuts[k]] + 1,
                                                                      minlength=len(fast) + 1)[1:]

    def decode(k: int) -> int:
        return int(lib.fh_tables(buf.ctypes.data, cuts[k], cuts[k + 1], s.ctypes.data, hdr.ctypes.data,
                                 plen.ctypes.data, group.ctypes.data, t.ctypes.data, pk.sysid.ctypes.data,
                                 pk.compid.ctypes.data, len(fast), size_a.ctypes.data, first_a.ctypes.data,
                                 off_a.ctypes.data, wid_a.ctypes.data, outs_p, *metas_p, rows[k].ctypes.data))

    if any(native.run_all([functools.partial(decode, k) for k in range(n_threads)], n_threads)):
        raise RecordingError("internal error: a message layout is longer than a MAVLink payload")
    tables = []
    for mid, cols, wanted, (tt, sy, co, rec) in zip(fast, columns, eager, metas, strict=True):
        lay = layout_of(mid)
        assert lay is not None
        for name in lay.char_fields & set(wanted):
            cols[name] = _decode_chars(cols[name], lay.char_as_str)
        if len(wanted) == len(lay.fieldnames):
            table_fields: Mapping[str, np.ndarray] = {name: cols[name] for name in lay.fieldnames}
        else:
            table_fields = LazyColumns(lay.fieldnames, functools.partial(_fields_native, lib, buf, s, hdr, plen, lay,
                                                                         rec), done=cols)
        tables.append(MessageTable(name=lay.name, t_s=tt, sysid=sy, compid=co, record=rec, fields=table_fields))
    rest = np.flatnonzero(group < 0)
    progress.advance(30.0 * (n - len(rest)) / n)
    if len(rest):
        sub = _Packets(**{f: getattr(pk, f)[rest] for f in _Packets._FIELDS if f != "t_us"},
                       t_us=np.zeros(0, np.uint64))
        for tab in _tables_numpy(buf, sub, t_s[rest], _Progress(False, "")).values():
            tab.record = rest[tab.record]
            tables.append(tab)
        progress.advance(30.0 * len(rest) / n)
    tables.sort(key=lambda tab: int(tab.record[0]))  # in order of first appearance
    return {tab.name: tab for tab in tables}


def _fields_native(lib: Any, buf: np.ndarray, s: np.ndarray, hdr: np.ndarray, plen: np.ndarray,
                   lay: MessageLayout, record: np.ndarray, names: list[str]) -> list[np.ndarray]:
    """The columns ``names`` of ``lay``'s messages, the packets ``record`` (indices into ``s``,
    ``hdr``, ``plen``), by ``fh_fields``: what ``_decode_fast`` makes of them."""
    assert lay.dtype is not None
    n = len(record)
    cols, offsets, widths = [], [], []
    for name in names:
        sub, off = lay.dtype.fields[name][:2]  # type: ignore[index]
        cols.append(np.empty((n, *sub.shape), dtype=sub.base.newbyteorder("=")))
        offsets.append(off)
        widths.append(sub.itemsize)
    outs = (ctypes.c_void_p * len(cols))(*(c.ctypes.data for c in cols))
    rec = np.ascontiguousarray(record, dtype=np.int64)
    off_a, wid_a = np.array(offsets, dtype=np.int64), np.array(widths, dtype=np.int64)  # alive for the call
    code = lib.fh_fields(buf.ctypes.data, n, rec.ctypes.data, s.ctypes.data, hdr.ctypes.data, plen.ctypes.data,
                         lay.size, len(cols), off_a.ctypes.data, wid_a.ctypes.data, outs)
    if code != 0:
        raise RecordingError("internal error: a message layout is longer than a MAVLink payload")
    return [_decode_chars(c, lay.char_as_str) if name in lay.char_fields else c
            for name, c in zip(names, cols, strict=True)]


def read_tlog(path: str | Path, *, progress: bool = False, fields: Mapping[str, Collection[str]] | None = None
              ) -> Recording:
    """Read a .tlog into a ``Recording`` (``source_format`` "tlog") of per-message columns; a
    ``.tlog.gz`` is decompressed in memory first (byte counts are of the decompressed file).

    ``t_s``: the record header's UNIX time, s (µs / 1e6); ``record``: index of the packet
    among the file's good packets (0..N-1, file order); ``sysid``/``compid``: from the packet
    header. Damaged bytes are skipped: ``skipped_bytes`` counts every byte not in a good
    record; ``skipped_packets`` the packets lost (CRC or header check failed where the record
    chain expected a packet, or the last record truncated); ``notes`` has one line per kind of
    damage. A record whose time header is damaged keeps its packet and takes the previous
    record's time (noted). ``progress``: a tqdm bar on stderr for files over
    ``PROGRESS_MIN_BYTES``. ``fields``: message name -> the fields a tool will read (replay's
    ``REPLAY_FIELDS``), decoded with the rows; the others are decoded when first read (a
    ``LazyColumns``: the same values, later; with the compiled kernels only). Default: every
    field with the rows. Raises RecordingError when the file holds no good MAVLink packet.
    """
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"recording not found: {p}")
    buf, n_bytes = _load(p)
    bar = _Progress(progress and n_bytes > PROGRESS_MIN_BYTES, f"reading {p.name}")
    try:
        pk, overlapped, between, damage = _find_packets(buf, n_bytes, bar)
        if len(pk.s) == 0:
            raise RecordingError(f"no MAVLink packets found in {p}")
        t_s, repaired = _repair_times(pk.t_us, overlapped)
        pk.t_us = np.zeros(0, dtype=np.uint64)  # no longer needed: free it before decoding
        steps = np.diff(t_s)
        backwards = int(np.count_nonzero(steps < 0))
        back_max = float(-steps.min()) if backwards else 0.0
        del steps
        tables = _tables(buf, pk, t_s, bar, fields)
    finally:
        bar.close()
    # a record starts 8 bytes before its STX, or where the packet before ends if that is later
    np.minimum(between, TIME_HEADER_LEN, out=between)
    in_records = int(np.sum(pk.total, dtype=np.int64)) + min(TIME_HEADER_LEN, int(pk.s[0])) + int(np.sum(between))
    skipped_bytes = n_bytes - in_records
    return Recording(
        path=str(p), tables=tables, source_format="tlog",
        skipped_bytes=skipped_bytes,
        skipped_packets=damage.damaged_packets + (1 if damage.truncated_bytes else 0),
        notes=_notes(damage, backwards, back_max, repaired),
        profile_hint=None)
