"""Read a .tlog into per-message-type numpy columns, fast, and survive damaged bytes.

A .tlog is a sequence of records: an 8-byte big-endian UNIX time in microseconds, then one
raw MAVLink 1 (STX 0xFE) or MAVLink 2 (STX 0xFD) packet. pymavlink reads one Python object per
message (~10 µs each); this reader finds, checks and decodes all packets with numpy:

1. every 0xFE / 0xFD byte is a candidate packet start; its header gives its length;
2. candidates whose successor record starts where their length says (or that end the file)
   have their CRC-16/MCRF4XX (with the dialect's ``crc_extra``) checked, vectorised; the
   packets that pass, without overlapping bodies, are the records;
3. the bytes between records (damage) are searched again for any packet that passes its CRC;
4. each message type is decoded at once with a structured dtype built from the dialect's
   wire layout (zero-padding MAVLink 2 payloads whose trailing zeros were truncated; the
   13-byte signature of signed packets is skipped, not checked, like pymavlink without a key).

Field names and values are pymavlink's (``pymavlink.dialects.v20.ardupilotmega``): raw MAVLink
units, the wire dtype of each field (``float32``, ``int16``, ...), char arrays as ``str``
decoded as pymavlink does, array fields as (n, k) columns. A message type the fast path cannot
lay out is decoded packet by packet with pymavlink. Packets of message ids the dialect does not
know cannot be CRC-checked; they are kept as ``UNKNOWN_<id>`` (field ``data``: the packet bytes,
as pymavlink's ``MAVLink_unknown``) only where they fit the record chain exactly.

On a file without damage the records, their order and their values equal what
``pymavlink.mavutil.mavlink_connection(path, dialect="ardupilotmega")`` yields with
MAVLink 2 decoding (environment ``MAVLINK20=1``, or a file whose first packet is MAVLink 2).
"""

from __future__ import annotations

import functools
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from companion.errors import RecordingError
from companion.recording import MessageTable, Recording

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
    replacement) rather than ``bytes``.
    """

    msgid: int
    name: str
    cls: type
    crc_extra: int
    size: int
    dtype: np.dtype | None
    fieldnames: tuple[str, ...]
    char_fields: frozenset[str]
    char_as_str: bool


def _payload_dtype(cls: type) -> tuple[np.dtype | None, frozenset[str]]:
    """Structured dtype of ``cls``'s wire payload from its ``unpacker`` format and
    ``ordered_fieldnames``; None if a code has no numpy equivalent or the sizes disagree."""
    fmt: str = cls.unpacker.format  # type: ignore[attr-defined]
    names: list[str] = list(cls.ordered_fieldnames)  # type: ignore[attr-defined]
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
    dtype = np.dtype({"names": names, "formats": formats})
    if dtype.itemsize != cls.unpacker.size:  # type: ignore[attr-defined]
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


def _make_layout(msgid: int, cls: type) -> MessageLayout:
    dtype, chars = _payload_dtype(cls)
    as_str = True
    if dtype is not None and chars:
        probed = _char_as_str(cls, dtype, chars)
        if probed is None:
            dtype = None
        else:
            as_str = probed
    return MessageLayout(
        msgid=msgid, name=cls.msgname, cls=cls,  # type: ignore[attr-defined]
        crc_extra=int(cls.crc_extra), size=int(cls.unpacker.size),  # type: ignore[attr-defined]
        dtype=dtype, fieldnames=tuple(cls.fieldnames),  # type: ignore[attr-defined]
        char_fields=chars, char_as_str=as_str)


@functools.cache
def layouts() -> dict[int, MessageLayout]:
    """Decoding layout of every message the ardupilotmega dialect defines, by message id."""
    return {int(mid): _make_layout(int(mid), cls) for mid, cls in mavlink2.mavlink_map.items()}


@functools.cache
def _crc_extra_lookup() -> tuple[np.ndarray, np.ndarray]:
    """(known, crc_extra): arrays indexed by message id (size max id + 2; the last slot is
    where out-of-range ids are clipped to, and is unknown)."""
    table = layouts()
    size = max(table) + 2
    known = np.zeros(size, dtype=bool)
    extra = np.zeros(size, dtype=np.uint8)
    for mid, lay in table.items():
        known[mid] = True
        extra[mid] = lay.crc_extra
    return known, extra


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


def crc_of_rows(rows: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """MAVLink CRCs of equal-length byte rows.

    ``rows``: (n, L) uint8, the bytes after STX up to the end of the payload; ``extra``: (n,)
    uint8 crc_extra of each row's message. Returns (n,) uint16.
    """
    pos, init = _crc_tables()
    n, length = rows.shape
    crc = np.full(n, init[length + 1], dtype=np.uint16)
    crc ^= pos[0][extra]
    cols = np.ascontiguousarray(rows.T)
    for j in range(length):
        crc ^= pos[length - j][cols[j]]
    return crc


def _check_crc(buf: np.ndarray, s: np.ndarray, hdr: np.ndarray, plen: np.ndarray,
               extra: np.ndarray) -> np.ndarray:
    """Which candidate packets (STX at ``s``, header and payload lengths) carry a good CRC.
    Candidates must lie inside ``buf`` (padding included). Returns (n,) bool."""
    good = np.zeros(len(s), dtype=bool)
    if len(s) == 0:
        return good
    covered = hdr - 1 + plen  # bytes after STX up to the end of the payload
    crc_at = s + hdr + plen
    stored = buf[crc_at].astype(np.uint16) | (buf[crc_at + 1].astype(np.uint16) << 8)
    order = np.argsort(covered, kind="stable")
    sorted_len = covered[order]
    bounds = np.flatnonzero(np.diff(sorted_len)) + 1
    for group in np.split(order, bounds):
        length = int(covered[group[0]])
        windows = sliding_window_view(buf, length)
        step = max(1, _CRC_BLOCK_BYTES // max(length, 1))
        for a in range(0, len(group), step):
            idx = group[a:a + step]
            good[idx] = crc_of_rows(windows[s[idx] + 1], extra[idx]) == stored[idx]
    return good


# ---------------------------------------------------------------------------------------------
# Finding packets


@dataclass
class _Candidates:
    """Candidate packet starts and what their headers claim (all arrays (n,), int64 unless
    noted). ``total``: packet length including signature; ``ok_header``: known message id and
    valid MAVLink 2 incompatibility flags; ``known``: the dialect defines the message id."""

    s: np.ndarray
    hdr: np.ndarray
    plen: np.ndarray
    total: np.ndarray
    msgid: np.ndarray
    known: np.ndarray
    flags_ok: np.ndarray

    @property
    def end(self) -> np.ndarray:
        return self.s + self.total

    def subset(self, idx: np.ndarray) -> _Candidates:
        return _Candidates(self.s[idx], self.hdr[idx], self.plen[idx], self.total[idx],
                           self.msgid[idx], self.known[idx], self.flags_ok[idx])


def _find_stx(buf: np.ndarray, n_bytes: int, chunk: int = 1 << 23) -> Iterator[np.ndarray]:
    """Positions (int64) of 0xFE / 0xFD bytes at or after offset 8, chunk by chunk."""
    lo = np.uint8(STX_V2)
    for a in range(TIME_HEADER_LEN, n_bytes, chunk):
        part = buf[a:min(a + chunk, n_bytes)]
        yield np.flatnonzero((part - lo) < 2) + a


def _parse_headers(buf: np.ndarray, s: np.ndarray) -> _Candidates:
    """Header fields of the candidates at ``s`` (buf must be padded past the file end)."""
    v2 = buf[s] == STX_V2
    plen = buf[s + 1].astype(np.int64)
    flags = np.where(v2, buf[s + 2], 0)
    hdr = np.where(v2, HEADER_LEN_V2, HEADER_LEN_V1)
    sig = np.where(v2 & ((flags & 1) == 1), SIGNATURE_LEN, 0)
    total = hdr + plen + CRC_LEN + sig
    msgid = np.where(
        v2,
        buf[s + 7].astype(np.int64) | (buf[s + 8].astype(np.int64) << 8) | (buf[s + 9].astype(np.int64) << 16),
        buf[s + 5].astype(np.int64))
    known_tab, _ = _crc_extra_lookup()
    known = known_tab[np.minimum(msgid, len(known_tab) - 1)]
    flags_ok = (flags & 0xFE) == 0
    return _Candidates(s, hdr, plen, total, msgid, known, flags_ok)


def _non_overlapping(s: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Mask of a largest set of packets whose bodies ``[s, end)`` do not overlap (``s``
    sorted). Isolated packets are kept; in each cluster of overlapping ones, the earliest
    finishing are taken first (optimal interval scheduling)."""
    n = len(s)
    keep = np.ones(n, dtype=bool)
    if n <= 1:
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


def _gaps(s: np.ndarray, end: np.ndarray, n_bytes: int) -> tuple[np.ndarray, np.ndarray]:
    """Byte ranges ``[a, b)`` not covered by any record (time header + packet) of the
    accepted packets (``s`` sorted, bodies disjoint)."""
    prev_end = np.concatenate(([0], end))
    rec_start = np.concatenate((s - TIME_HEADER_LEN, [n_bytes]))
    a = prev_end
    b = np.maximum(rec_start, prev_end)
    has = b > a
    return a[has], b[has]


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


def _repair_times(t_us: np.ndarray, untrusted: np.ndarray) -> tuple[np.ndarray, int]:
    """Replace record times that cannot be right by the previous trusted record's time.

    A time is damage when its header overlapped the packet before (``untrusted``) or when it
    is a spike: further than ``TIME_SPIKE_TOL_S`` (ends: ``TIME_SPIKE_TOL_END_S``) from the
    median of its four nearest neighbours, beyond the spread of their middle two (so steps,
    gaps and backward jumps of the clock are left alone). Returns (times in s, number replaced).
    """
    t = t_us.astype(np.float64) / 1e6
    n = len(t)
    bad = untrusted.copy()
    if n >= 3:
        padded = np.concatenate((np.full(2, np.nan), t, np.full(2, np.nan)))
        neigh = np.stack([padded[0:n], padded[1:n + 1], padded[3:n + 3], padded[4:n + 4]], axis=1)
        neigh = np.sort(neigh, axis=1)  # NaN last
        count = np.sum(~np.isnan(neigh), axis=1)
        lo_i = (count - 1) // 2
        hi_i = count // 2
        rows = np.arange(n)
        m1 = neigh[rows, lo_i]
        m2 = neigh[rows, hi_i]
        med = 0.5 * (m1 + m2)
        tol = np.full(n, TIME_SPIKE_TOL_S)
        tol[:2] = TIME_SPIKE_TOL_END_S
        tol[-2:] = TIME_SPIKE_TOL_END_S
        bad |= np.abs(t - med) > tol + np.abs(m2 - m1)
    n_bad = int(bad.sum())
    if n_bad:
        good_idx = np.where(bad, -1, np.arange(n))
        last_good = np.maximum.accumulate(good_idx)
        if (last_good < 0).any():  # leading bad records take the first good time
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
    """Columns of ``lay``'s messages whose payloads start at ``payload_at`` (lengths
    ``plen``; shorter than the wire size means truncated trailing zeros, longer is cut)."""
    assert lay.dtype is not None
    size = lay.size
    rows = sliding_window_view(buf, size)[payload_at]  # (n, size) copy
    short = np.flatnonzero(plen < size)
    if len(short):
        keep = np.arange(size) < plen[short, None]
        rows[short] = np.where(keep, rows[short], 0)
    rec = rows.view(lay.dtype).reshape(-1)
    fields: dict[str, np.ndarray] = {}
    for name in lay.fieldnames:
        if name in lay.char_fields:
            fields[name] = _decode_chars(rec[name], lay.char_as_str)
        else:
            fields[name] = np.ascontiguousarray(rec[name])
    return fields


def _decode_pymavlink(buf: np.ndarray, lay: MessageLayout, s: np.ndarray,
                      end: np.ndarray) -> dict[str, np.ndarray]:
    """Columns of ``lay``'s packets ``[s, end)`` decoded one by one with pymavlink."""
    mav = mavlink2.MAVLink(None)
    values: dict[str, list[Any]] = {name: [] for name in lay.fieldnames}
    for a, e in zip(s.tolist(), end.tolist(), strict=True):
        msg = mav.decode(bytearray(buf[a:e].tobytes()))
        for name in lay.fieldnames:
            values[name].append(getattr(msg, name))
    fields = {}
    for name, vals in values.items():
        if vals and isinstance(vals[0], str | bytes):
            col = np.empty(len(vals), dtype=object)
            col[:] = vals
            fields[name] = col
        else:
            fields[name] = np.asarray(vals)
    return fields


def _unknown_fields(buf: np.ndarray, s: np.ndarray, end: np.ndarray) -> dict[str, np.ndarray]:
    data = np.empty(len(s), dtype=object)
    data[:] = [buf[a:e].tobytes() for a, e in zip(s.tolist(), end.tolist(), strict=True)]
    return {"data": data}


# ---------------------------------------------------------------------------------------------
# The reader


def _load(path: Path) -> tuple[np.ndarray, int]:
    """The file's bytes in a zero-padded uint8 array, and the file length."""
    n_bytes = path.stat().st_size
    buf = np.zeros(n_bytes + _PAD, dtype=np.uint8)
    with open(path, "rb") as f:
        got = f.readinto(memoryview(buf)[:n_bytes])
    if got != n_bytes:
        raise RecordingError(f"{path.name}: could not read the whole file ({got} of {n_bytes} bytes)")
    return buf, n_bytes


class _Progress:
    """A tqdm bar on stderr over the reader's stages, or nothing."""

    def __init__(self, enabled: bool, total: int, desc: str) -> None:
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="step", file=sys.stderr, leave=False)

    def update(self, n: int = 1) -> None:
        if self.bar is not None:
            self.bar.update(n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _find_packets(buf: np.ndarray, n_bytes: int, progress: _Progress
                  ) -> tuple[_Candidates, np.ndarray, _Damage]:
    """The good packets of the file, sorted by position, whether each one's time header
    overlaps the packet before, and the damage found."""
    _, extra_tab = _crc_extra_lookup()
    table = layouts()
    checkable_parts = []
    checked_parts = []
    for s in _find_stx(buf, n_bytes):
        cand = _parse_headers(buf, s)
        end = cand.end
        nxt = end + TIME_HEADER_LEN
        follows = (buf[np.minimum(nxt, n_bytes)] - np.uint8(STX_V2)) < 2
        chained = (end == n_bytes) | ((nxt < n_bytes) & follows)
        ok = cand.known & cand.flags_ok & (end <= n_bytes)
        checked_parts.append(cand.subset(np.flatnonzero(ok & chained)))
        checkable_parts.append(cand.subset(np.flatnonzero(ok & ~chained)))
    progress.update()

    def cat(parts: list[_Candidates]) -> _Candidates:
        return _Candidates(*(np.concatenate([getattr(p, f) for p in parts]) if parts
                             else np.zeros(0, dtype=np.int64)
                             for f in ("s", "hdr", "plen", "total", "msgid", "known", "flags_ok")))

    # pass 1: candidates that sit in an unbroken record chain
    first = cat(checked_parts)
    del checked_parts
    good = _check_crc(buf, first.s, first.hdr, first.plen, extra_tab[first.msgid])
    first = first.subset(np.flatnonzero(good))
    first = first.subset(np.flatnonzero(_non_overlapping(first.s, first.end)))
    progress.update()

    # pass 2: every other checkable candidate whose body lies in a gap between records
    gap_a, gap_b = _gaps(first.s, first.end, n_bytes)
    if len(gap_a):
        rest = cat(checkable_parts)
        gi = np.searchsorted(gap_a, rest.s, side="right") - 1
        inside = (gi >= 0) & (rest.end <= gap_b[np.maximum(gi, 0)])
        rest = rest.subset(np.flatnonzero(inside))
        good = _check_crc(buf, rest.s, rest.hdr, rest.plen, extra_tab[rest.msgid])
        rest = rest.subset(np.flatnonzero(good))
        rest = rest.subset(np.flatnonzero(_non_overlapping(rest.s, rest.end)))
        order = np.argsort(np.concatenate((first.s, rest.s)), kind="stable")
        first = cat([first, rest]).subset(order)
    del checkable_parts

    # what is left between the records: walk the expected record chain through each gap
    damage = _Damage()
    unknown: list[int] = []
    gap_a, gap_b = _gaps(first.s, first.end, n_bytes)
    for a, b in zip(gap_a.tolist(), gap_b.tolist(), strict=True):
        walk = _walk_gap(buf, a, b, n_bytes)
        # packets of ids the dialect does not define: kept where they fill the gap exactly
        if (walk.records and not walk.truncated and walk.records[-1][1] == b
                and all(ok and table.get(mid) is None for _, _, mid, ok in walk.records)):
            unknown.extend(p for p, _, _, _ in walk.records)
            continue
        damage.damaged_packets += len(walk.records)
        damage.damaged_bytes += walk.spanned
        if walk.truncated:
            damage.truncated_bytes += walk.truncated
        if walk.garbage:
            damage.garbage_bytes += walk.garbage
            damage.garbage_places += 1
            if damage.first_garbage_at < 0:
                damage.first_garbage_at = a + walk.spanned
    if unknown:
        damage.unknown_packets = len(unknown)
        extra = _parse_headers(buf, np.array(unknown, dtype=np.int64))
        order = np.argsort(np.concatenate((first.s, extra.s)), kind="stable")
        first = cat([first, extra]).subset(order)
    progress.update()

    overlapped = np.zeros(len(first.s), dtype=bool)
    overlapped[1:] = first.s[1:] - TIME_HEADER_LEN < first.end[:-1]
    return first, overlapped, damage


def _notes(damage: _Damage, backwards: int, back_max_s: float,
           repaired_times: int) -> list[str]:
    notes = []
    if damage.damaged_packets:
        notes.append(f"skipped {damage.damaged_bytes} bytes: {damage.damaged_packets} damaged packets "
                     "(bad CRC or header)")
    if damage.garbage_bytes:
        notes.append(f"skipped {damage.garbage_bytes} bytes of unrecognisable data in "
                     f"{damage.garbage_places} places (the first at byte {damage.first_garbage_at})")
    if damage.truncated_bytes:
        notes.append(f"skipped {damage.truncated_bytes} bytes: truncated last record")
    if damage.unknown_packets:
        notes.append(f"kept {damage.unknown_packets} packets of message ids the ardupilotmega dialect "
                     "does not define as UNKNOWN_<id> (CRC not checkable)")
    if repaired_times:
        notes.append(f"{repaired_times} records had a damaged timestamp: given the previous record's time")
    if backwards:
        notes.append(f"{backwards} records are timestamped earlier than the record before them "
                     f"(by up to {back_max_s:.3f} s); kept in file order")
    return notes


def read_tlog(path: str | Path, *, progress: bool = False) -> Recording:
    """Read a .tlog into a ``Recording`` (``source_format`` "tlog") of per-message columns.

    ``t_s``: the record header's UNIX time, s (µs / 1e6); ``record``: index of the packet
    among the file's good packets (0..N-1, file order); ``sysid``/``compid``: from the packet
    header. Damaged bytes are skipped: ``skipped_bytes`` counts every byte not in a good
    record, ``skipped_packets`` the packets lost (CRC or header check failed at a record
    position, or the last record truncated); ``notes`` has one line per kind of damage.
    ``progress``: show a tqdm bar on stderr for files over ``PROGRESS_MIN_BYTES``.
    Raises RecordingError when the file holds no good MAVLink packet.
    """
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"recording not found: {p}")
    buf, n_bytes = _load(p)
    table = layouts()
    bar = _Progress(progress and n_bytes > PROGRESS_MIN_BYTES, 4, f"reading {p.name}")
    try:
        pk, overlapped, damage = _find_packets(buf, n_bytes, bar)
        n = len(pk.s)
        if n == 0:
            raise RecordingError(f"no MAVLink packets found in {p}")
        t_us = sliding_window_view(buf, TIME_HEADER_LEN)[pk.s - TIME_HEADER_LEN].copy().view(">u8").reshape(-1)
        t_s, repaired = _repair_times(t_us, overlapped)
        del t_us
        steps = np.diff(t_s)
        backwards = int(np.count_nonzero(steps < 0))
        back_max = float(-steps.min()) if backwards else 0.0
        del steps
        v2 = buf[pk.s] == STX_V2
        sysid = np.where(v2, buf[pk.s + 5], buf[pk.s + 3])
        compid = np.where(v2, buf[pk.s + 6], buf[pk.s + 4])
        del v2

        # group by message id, keeping file order inside each group
        order = np.argsort(pk.msgid, kind="stable")
        ids = pk.msgid[order]
        bounds = np.flatnonzero(np.diff(ids)) + 1
        groups = np.split(order, bounds)
        groups.sort(key=lambda g: int(g[0]))  # tables in order of first appearance
        tables: dict[str, MessageTable] = {}
        for idx in groups:
            mid = int(pk.msgid[idx[0]])
            s = pk.s[idx]
            lay = table.get(mid)
            if lay is None:
                name = f"UNKNOWN_{mid}"
                fields = _unknown_fields(buf, s, s + pk.total[idx])
            elif lay.dtype is None:
                name = lay.name
                fields = _decode_pymavlink(buf, lay, s, s + pk.total[idx])
            else:
                name = lay.name
                fields = _decode_fast(buf, lay, s + pk.hdr[idx], pk.plen[idx])
            tables[name] = MessageTable(name=name, t_s=t_s[idx], sysid=sysid[idx], compid=compid[idx],
                                        record=idx.astype(np.int64), fields=fields)
        bar.update()
    finally:
        bar.close()

    skipped_bytes = n_bytes - int(np.sum(pk.end - np.maximum(pk.s - TIME_HEADER_LEN,
                                                             np.concatenate(([0], pk.end[:-1])))))
    return Recording(
        path=str(p), tables=tables, source_format="tlog",
        skipped_bytes=skipped_bytes,
        skipped_packets=damage.damaged_packets + (1 if damage.truncated_bytes else 0),
        notes=_notes(damage, backwards, back_max, repaired),
        profile_hint=None)
