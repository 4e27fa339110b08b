"""Columns of numbers as CSV text, vectorised, byte for byte what Python's ``%`` formatting gives.

``format_rows(columns, formats)`` returns the bytes of ``",".join(fmt % v ...) + "\\n"`` for
every row, where each format is ``"%.<P>g"`` (floats), ``"%d"`` (integers) or ``"%s"`` (object
columns such as names). ``format_rows_reference`` is that rule written out with Python's own
``%`` operator, one value at a time: it is the definition, and the tests hold the two equal
(tests/test_csv_format.py, over random values, edge cases and whole replays).

How the floats are done without Python per value. For a finite non-zero ``x`` and ``P``
significant digits, ``e = floor(log10(|x|))`` and ``m = |x| * 10**(P - 1 - e)`` (one correctly
rounded multiplication or division by an exactly representable power of ten, so ``m`` is within
``m * 2**-53`` of the exact product); the digits are ``D = rint(m)``. Python rounds the exact
binary value half to even; ``rint`` of the rounded product agrees whenever ``m`` is not within
the rounding error of a half-integer. Every value where that, or the exponent, is in doubt (``m``
within ``10**P * 1e-15`` of a half, ``D`` outside ``[10**(P-1), 10**P)``, a power of ten beyond
1e22, subnormals) is formatted by Python itself. Each value's text is then laid out from its
digits by a per-shape template (sign, exponent, number of significant digits), gathered in one
``take_along_axis``; rows are joined by dropping the padding of a fixed-width byte matrix.
"""

from __future__ import annotations

import ctypes
import functools
import queue
import re
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from companion import native

#: rows formatted per block (keeps the byte matrices within the CPU caches)
BLOCK_ROWS = 16384
_PAD = 0  # padding byte of the fixed-width matrices (never in the text)
_FLOAT_FMT = re.compile(r"%\.(\d+)g")
#: powers of ten exactly representable in float64
_EXACT_POW10 = 22


def format_rows_reference(columns: Sequence[np.ndarray], formats: Sequence[str]) -> bytes:
    """The CSV rows of ``columns`` (equal lengths) with Python's ``%`` operator, value by value:
    the rule ``format_rows`` reproduces. UTF-8 text, one ``\\n`` per row."""
    row = ",".join(formats)
    values = [np.asarray(c).tolist() for c in columns]
    return "".join(row % r + "\n" for r in zip(*values, strict=True)).encode()


def format_rows(columns: Sequence[np.ndarray], formats: Sequence[str]) -> bytes:
    """``format_rows_reference(columns, formats)``, vectorised (see the module docstring).

    ``formats``: per column ``"%.<P>g"`` (1 <= P <= 15; the column is read as float64),
    ``"%d"`` (an integer column) or ``"%s"`` (any column: ``str`` of each value). Other formats
    or dtypes are handed to the reference. With the compiled kernels (``companion.native``)
    the rows are written by ``fh_csv_rows``, a C copy of the same rule; otherwise with numpy."""
    return b"".join(bytes(part) for part in iter_rows(columns, formats))


def iter_rows(columns: Sequence[np.ndarray], formats: Sequence[str], block_rows: int = 65_536,
              threads: int | None = None) -> Iterator[bytes | memoryview]:
    """``format_rows(columns, formats)`` in pieces of up to ``block_rows`` rows, for writing
    to a file as they come (a piece may be a view of a buffer the next one reuses: write it
    before asking for the next). With the compiled kernel, the pieces are formatted by up to
    ``threads`` threads (default ``native.threads()``) while the caller writes the ones before:
    each piece is the same text whichever thread formats it."""
    cols = [np.asarray(c) for c in columns]
    if not cols:
        return
    n = len(cols[0])
    if any(len(c) != n for c in cols):
        raise ValueError("columns of different lengths")
    kinds = [_kind(c, f) for c, f in zip(cols, formats, strict=True)]
    if any(k is None for k in kinds):
        for a in range(0, n, block_rows):
            yield format_rows_reference([c[a:a + block_rows] for c in cols], formats)
        return
    lib = native.kernels()
    if lib is not None:
        yield from _rows_native(lib, cols, kinds, n, block_rows,  # type: ignore[arg-type]
                                native.threads() if threads is None else threads)
        return
    for a in range(0, n, block_rows):
        part = []
        for b in range(a, min(a + block_rows, n), BLOCK_ROWS):
            stop = min(b + BLOCK_ROWS, a + block_rows, n)
            fields = [_field(c[b:stop], k) for c, k in zip(cols, kinds, strict=True)]  # type: ignore[arg-type]
            part.append(_join_rows(fields))
        yield b"".join(part)


#: column kinds of ``fh_csv_rows`` (kernels.c)
_NATIVE_FLOAT, _NATIVE_INT, _NATIVE_TEXT = 0, 1, 2


def _rows_native(lib: Any, cols: list[np.ndarray], kinds: list[tuple[str, int]], n: int, block_rows: int,
                 threads: int = 1) -> Iterator[memoryview]:
    """``iter_rows`` by the compiled kernel: floats as float64, integers as int64, ``%s``
    columns as codes into their distinct texts (as ``_strings``). ``threads`` > 1: the pieces
    are formatted in that many threads (``_in_threads``; ctypes lets go of the GIL in the
    kernel), each piece by the same call as in one thread."""
    kind_c, data, digits, blobs, offsets, width = [], [], [], [], [], 0
    keep: list[np.ndarray] = []  # the arrays the kernel reads, alive until the end
    for col, (k, p) in zip(cols, kinds, strict=True):
        blob = off = np.zeros(1, dtype=np.int64)
        if k == "g":
            arr = np.ascontiguousarray(col, dtype=np.float64)
            kind_c.append(_NATIVE_FLOAT)
            width += p + 8  # sign, digits, point, e-308 (or "0." and three zeros)
        elif k == "d":
            arr = np.ascontiguousarray(col, dtype=np.int64)
            kind_c.append(_NATIVE_INT)
            width += 20
        else:
            codes, texts = _string_codes(col)
            arr = codes.astype(np.int32)
            blob = np.frombuffer(b"".join(texts) or b"\0", dtype=np.uint8)
            off = np.concatenate(([0], np.cumsum([len(t) for t in texts]))).astype(np.int64)
            kind_c.append(_NATIVE_TEXT)
            width += max((len(t) for t in texts), default=0)
        keep += [arr, blob, off]
        data.append(arr.ctypes.data)
        digits.append(p)
        blobs.append(blob.ctypes.data)
        offsets.append(off.ctypes.data)
    ncols = len(cols)
    row_bound = width + ncols
    pointers = ctypes.c_void_p * ncols
    kind_a = np.array(kind_c, dtype=np.int32)
    digit_a = np.array(digits, dtype=np.int32)
    blob_p, off_p = pointers(*blobs), pointers(*offsets)
    size = min(block_rows, max(n, 1)) * row_bound + 64  # + room for the kernel's whole-slot copies

    def fill(a: int, out: np.ndarray) -> int:
        """Rows [a, a + block_rows) into ``out``; the bytes written."""
        m = min(block_rows, n - a)
        shifted = pointers(*(d + a * (8 if kc != _NATIVE_TEXT else 4) for d, kc in zip(data, kind_c, strict=True)))
        written = lib.fh_csv_rows(m, ncols, kind_a.ctypes.data, shifted, digit_a.ctypes.data, blob_p, off_p,
                                  out.ctypes.data, len(out), row_bound)
        if written < 0:
            raise RuntimeError("internal error: CSV row longer than its bound")
        return int(written)

    starts = range(0, n, block_rows)
    if threads > 1 and len(starts) > 1:
        yield from _in_threads(fill, starts, size, min(threads, len(starts)))
    else:
        out = np.empty(size, dtype=np.uint8)
        view = memoryview(out)  # type: ignore[arg-type]
        for a in starts:
            yield view[:fill(a, out)]
    del keep


def _in_threads(fill: Callable[[int, np.ndarray], int], starts: range, size: int, threads: int
                ) -> Iterator[memoryview]:
    """``fill``'s pieces at ``starts``, in order, formatted ahead by ``threads`` threads: thread
    w formats pieces w, w + threads, ... into its two buffers in turn, a buffer taken again only
    once the caller has asked for the piece after the one it held (so the caller's write of a
    piece overlaps the formatting of the next ones)."""
    free = [threading.Semaphore(2) for _ in range(threads)]
    done: list[queue.SimpleQueue[tuple[memoryview | None, BaseException | None]]] = [
        queue.SimpleQueue() for _ in range(threads)]
    stop = threading.Event()

    def work(w: int) -> None:
        bufs = [np.empty(size, dtype=np.uint8) for _ in range(2)]
        for j, a in enumerate(starts[w::threads]):
            free[w].acquire()
            if stop.is_set():
                return
            out = bufs[j % 2]
            try:
                piece = memoryview(out)[:fill(a, out)]  # type: ignore[arg-type]
            except BaseException as exc:  # handed to the caller's thread
                done[w].put((None, exc))
                return
            done[w].put((piece, None))

    pool = [threading.Thread(target=work, args=(w,), daemon=True, name=f"csv-format-{w}") for w in range(threads)]
    for t in pool:
        t.start()
    try:
        for k in range(len(starts)):
            piece, exc = done[k % threads].get()
            if exc is not None:
                raise exc
            yield piece  # type: ignore[misc]
            free[k % threads].release()  # the caller is done with the piece
    finally:
        stop.set()
        for sem in free:
            sem.release()
        for t in pool:
            t.join()


def _kind(col: np.ndarray, fmt: str) -> tuple[str, int] | None:
    if fmt == "%s":
        return ("s", 0)
    if fmt == "%d" and col.dtype.kind in "iub" and col.ndim == 1:
        if col.dtype.kind == "u" and col.dtype.itemsize == 8:
            return None
        return ("d", 0)
    m = _FLOAT_FMT.fullmatch(fmt)
    if m and 1 <= int(m.group(1)) <= 15 and col.dtype.kind in "fiub" and col.ndim == 1:
        return ("g", int(m.group(1)))
    return None


def _field(col: np.ndarray, kind: tuple[str, int]) -> np.ndarray:
    """The text of each value of ``col`` as a (n, W) uint8 matrix padded with ``_PAD``."""
    if kind[0] == "s":
        return _strings(col)
    if kind[0] == "d":
        return _integers(col)
    return _floats(col, kind[1])


def _string_codes(col: np.ndarray) -> tuple[np.ndarray, list[bytes]]:
    """``"%s" % v`` of each value as codes (int64) into the distinct texts (UTF-8)."""
    values = col.tolist()
    try:
        distinct = dict.fromkeys(values)  # in order of first appearance
    except TypeError:  # unhashable values: one by one
        return np.arange(len(values), dtype=np.int64), [str(v).encode() for v in values]
    if all(type(v) is str for v in distinct):  # names (no str equals a value of another type)
        lookup = {v: i for i, v in enumerate(distinct)}
        return (np.fromiter(map(lookup.__getitem__, values), dtype=np.int64, count=len(values)),
                [v.encode() for v in distinct])
    uniq: dict[tuple[type, object], int] = {}  # keyed by type too: 1, 1.0 and True print differently
    try:
        codes = np.fromiter((uniq.setdefault((type(v), v), len(uniq)) for v in values), dtype=np.int64,
                            count=len(values))
    except TypeError:  # unhashable values: one by one
        return np.arange(len(values), dtype=np.int64), [str(v).encode() for v in values]
    return codes, [str(v).encode() for _, v in uniq]


def _strings(col: np.ndarray) -> np.ndarray:
    """``"%s" % v`` of each value, through the distinct values."""
    codes, texts = _string_codes(col)
    return _rows_of(texts)[codes] if texts else np.zeros((0, 1), dtype=np.uint8)


def _rows_of(texts: list[bytes]) -> np.ndarray:
    """The byte strings as a (k, W) padded matrix."""
    width = max(1, *(len(t) for t in texts))
    out = np.zeros((len(texts), width), dtype=np.uint8)
    for i, t in enumerate(texts):
        out[i, :len(t)] = np.frombuffer(t, dtype=np.uint8)
    return out


def _python(values: np.ndarray, fmt: str) -> np.ndarray:
    return _rows_of([(fmt % v).encode() for v in values.tolist()])


def _place(out: np.ndarray, idx: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``out`` with ``rows`` (text of the values at ``idx``) written in, widened if needed."""
    if rows.shape[1] > out.shape[1]:
        out = np.concatenate((out, np.zeros((len(out), rows.shape[1] - out.shape[1]), np.uint8)), axis=1)
    out[idx] = _PAD
    out[idx, :rows.shape[1]] = rows  # one row broadcasts to all of idx
    return out


@functools.cache
def _chunk_tables() -> tuple[np.ndarray, np.ndarray]:
    """For 0..99999: the five ASCII digits (as 5-byte items) and the number of trailing zeros
    of the five-digit string (5 for 0)."""
    v = np.arange(100_000)
    chars = np.empty((len(v), 5), dtype=np.uint8)
    rest = v.copy()
    for j in range(4, -1, -1):
        rest, r = np.divmod(rest, 10)
        chars[:, j] = ord("0") + r
    tz = np.zeros(len(v), dtype=np.int64)
    for k in range(1, 6):
        tz += v % 10**k == 0
    return chars.view("V5").reshape(-1), tz


def _digits(a: np.ndarray, places: int) -> tuple[np.ndarray, np.ndarray]:
    """The last ``places`` (<= 20) decimal digits of each non-negative int64 in ``a`` as ASCII,
    most significant first, (n, places) uint8; and the number of trailing zeros among them."""
    chars5, tz5 = _chunk_tables()
    k = -(-places // 5)
    out = np.empty((len(a), 5 * k), dtype=np.uint8)
    items = out.view("V5")
    rest = a
    tz = np.zeros(len(a), dtype=np.int64)
    running = np.ones(len(a), dtype=bool)  # all chunks so far (from the right) were zero
    for j in range(k - 1, -1, -1):
        rest, r = np.divmod(rest, 100_000)
        items[:, j] = chars5[r]
        tz += tz5[r] * running
        running &= r == 0
    return out[:, 5 * k - places:], np.minimum(tz, places)


def _mask(cond: np.ndarray, char: int | np.ndarray) -> np.ndarray:
    """``char`` where ``cond``, padding elsewhere (padding is 0: a product)."""
    return np.multiply(cond, char, dtype=np.uint8, casting="unsafe")


def _integers(col: np.ndarray) -> np.ndarray:
    """``"%d" % v`` of each integer: a sign slot, then the digits right-aligned, leading zeros
    as padding."""
    v = col.astype(np.int64)
    extreme = v == np.iinfo(np.int64).min
    a = np.abs(np.where(extreme, 0, v))
    places = max(1, len(str(int(a.max())))) if len(a) else 1
    out = np.empty((len(a), 1 + places), dtype=np.uint8)
    out[:, 0] = _mask(v < 0, ord("-"))
    digits, _ = _digits(a, places)
    ndig = np.ones(len(a), dtype=np.int64)
    for k in range(1, places):
        ndig += a >= 10**k
    out[:, 1:] = _mask(np.arange(places) >= places - ndig[:, None], digits)
    if extreme.any():
        idx = np.flatnonzero(extreme)
        out = _place(out, idx, _python(col[idx], "%d"))
    return out


@functools.cache
def _pow10(digits: int) -> np.ndarray:
    """10.0**k for k = -22..22 - as the factor ``_floats`` multiplies (k >= 0) or divides by."""
    return np.array([10.0 ** abs(k) for k in range(-_EXACT_POW10, _EXACT_POW10 + 1)])


def _floats(col: np.ndarray, digits: int) -> np.ndarray:
    """``"%.<digits>g" % v`` of each value (as float64), in slots: sign (1), ``0.`` and the
    zeros of a fixed-notation value under 1 (5, when there is one), the digits with a slot for
    the point (digits + 1), the exponent (5, when there is one); unused slots hold padding."""
    fmt = f"%.{digits}g"
    x = col.astype(np.float64)
    n = len(x)
    ax = np.abs(x)
    finite = np.isfinite(x)
    special = ~finite | (ax == 0)
    normal = ~special & (ax >= 1e-300) & (ax < 1e300)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        e = np.floor(np.log10(np.where(normal, ax, 1.0))).astype(np.int64)
        k = digits - 1 - e  # scale by 10**k
        ok = normal & (np.abs(k) <= _EXACT_POW10)
        kk = np.where(ok, k, 0)
        scale = _pow10(digits)[kk + _EXACT_POW10]
        m = np.where(kk >= 0, ax * scale, ax / scale)
        d = np.rint(m)
        frac = m - np.floor(m)
    lo, hi = 10 ** (digits - 1), 10**digits
    ok &= (np.abs(frac - 0.5) > hi * 1e-15) & (d >= lo) & (d < hi)
    dig, tz = _digits(np.where(ok, d, lo).astype(np.int64), digits)
    ndig = digits - tz  # trailing zeros are dropped (%g)
    e = np.where(ok, e, 0)
    fixed = (e >= -4) & (e < digits)
    under_one = fixed & (e < 0)
    sci = ~fixed
    any_under, any_sci = bool(under_one.any()), bool(sci.any())
    width = 1 + 5 * any_under + digits + 1 + 5 * any_sci
    out = np.empty((n, width), dtype=np.uint8)
    out[:, 0] = _mask(x < 0, ord("-"))
    c = 1
    if any_under:  # "0." and the zeros after the point of 0.000ddd
        out[:, 1] = _mask(under_one, ord("0"))
        out[:, 2] = _mask(under_one, ord("."))
        for j in range(3):
            out[:, 3 + j] = _mask(under_one & (j < -e - 1), ord("0"))
        c = 6
    # the digits shown (trailing zeros of the fraction are not), then a point slot after the
    # digit ``at`` (digits: no point) by moving the digits after it one slot on
    i = np.arange(digits + 1)
    whole = np.where(fixed & (e >= 0), e + 1, 0)
    body = _mask(i[None, :digits] < np.maximum(ndig, whole)[:, None], dig)
    at = np.where(fixed, np.where(e >= 0, e, digits), 0)
    at = np.where(ndig > at + 1, at, digits)
    slot = out[:, c:c + digits + 1]
    slot[:, :digits] = body
    slot[:, digits] = 0
    moved = i[None, 1:] > at[:, None] + 1
    np.copyto(slot[:, 1:], body, where=moved)
    np.copyto(slot[:, 1:], np.uint8(ord(".")), where=i[None, 1:] == at[:, None] + 1)
    if any_sci:
        ae = np.abs(e)
        tail = out[:, c + digits + 1:]
        tail[:, 0] = _mask(sci, ord("e"))
        tail[:, 1] = _mask(sci, np.where(e < 0, ord("-"), ord("+")))
        tail[:, 2] = _mask(sci & (ae >= 100), ord("0") + ae // 100 % 10)
        tail[:, 3] = _mask(sci, ord("0") + ae // 10 % 10)
        tail[:, 4] = _mask(sci, ord("0") + ae % 10)
    rest = ~ok
    if special.any():  # zeros, NaN and infinities: as Python spells them
        zero = ax == 0
        for mask, text in ((zero & ~np.signbit(x), b"0"), (zero & np.signbit(x), b"-0"), (np.isnan(x), b"nan"),
                           (x == np.inf, b"inf"), (x == -np.inf, b"-inf")):
            if mask.any():
                idx = np.flatnonzero(mask)
                out = _place(out, idx, np.frombuffer(text, dtype=np.uint8)[None, :])
                rest[idx] = False
    if rest.any():
        idx = np.flatnonzero(rest)
        out = _place(out, idx, _python(x[idx], fmt))
    return out


def _join_rows(fields: list[np.ndarray]) -> bytes:
    """The rows of the fields' texts joined by commas, each ended by a newline."""
    n = len(fields[0])
    sep = np.full((n, 1), ord(","), dtype=np.uint8)
    parts: list[np.ndarray] = []
    for f in fields:
        parts += [f, sep]
    parts[-1] = np.full((n, 1), ord("\n"), dtype=np.uint8)
    mat = np.concatenate(parts, axis=1)
    return mat[mat != _PAD].tobytes()
