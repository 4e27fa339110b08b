"""The compiled kernels of ``companion/native/kernels.c``, loaded through ctypes (issue 17).

The reader's record scan with its CRC check and the CSV writer's number formatting run at the
speed of reading the bytes only when compiled. numba would compile them, but loading numba and
its cache costs about 0.45 s in a fresh process, the whole budget of a ``replay`` command on an
hour-long recording; a small C library loads in a millisecond. So the C file is compiled once
with the system's C compiler (``$CC``, else ``cc``) into a cache folder, keyed by a hash of the
source (CRC-32 and length), the compiler and the platform, and loaded from there afterwards.

Every kernel is a copy, for speed only, of a numpy formulation that stays the definition: the
callers use the numpy path when ``kernels()`` is None (no compiler, a failed build, not a
POSIX system, or ``FLOWHOLD_NATIVE=0`` in the environment), and tests/test_native.py holds
the two equal. Cache folder: ``$FLOWHOLD_CACHE_DIR``, else ``$XDG_CACHE_HOME/flowhold``, else
``~/.cache/flowhold`` (a temporary folder if none is writable).
"""

from __future__ import annotations

import ctypes
import functools
import itertools
import os
import sys
import tempfile
import threading
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

SOURCE = Path(__file__).resolve().parent / "native" / "kernels.c"
#: the ABI the Python side expects (``fh_version`` in kernels.c)
VERSION = 14
_FLAGS = ("-O2", "-std=c99", "-ffp-contract=off", "-shared", "-fPIC")
_COMPILE_TIMEOUT_S = 120.0
#: most threads the kernels run in at once (reading and formatting are memory-bound beyond a few)
MAX_THREADS = 4

T = TypeVar("T")


def enabled() -> bool:
    """Whether the compiled kernels may be used (``FLOWHOLD_NATIVE`` is not "0")."""
    return os.environ.get("FLOWHOLD_NATIVE", "1") != "0"


def cache_dir() -> Path:
    """Where the compiled library is kept (created on first use)."""
    env = os.environ.get("FLOWHOLD_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "flowhold"


def _compiler() -> list[str]:
    return (os.environ.get("CC") or "cc").split()


def library_path() -> Path:
    """The compiled library's file for this source, compiler and platform."""
    source = SOURCE.read_bytes()
    how = repr((VERSION, _compiler(), _FLAGS, sys.platform, os.uname().machine if hasattr(os, "uname") else ""))
    key = f"{zlib.crc32(source):08x}{zlib.crc32(how.encode()):08x}{len(source) & 0xFFFF:04x}"  # (hashlib: 6 ms)
    return cache_dir() / f"flowhold_kernels_{key}.so"


def _build(target: Path) -> None:
    """Compile the source into ``target`` (atomically: other processes may build it too)."""
    import subprocess  # only to build: 5 ms of every command's start-up otherwise

    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=target.stem + ".", suffix=".tmp.so", dir=target.parent)
    os.close(fd)
    try:
        subprocess.run([*_compiler(), *_FLAGS, "-o", tmp, str(SOURCE), "-lm"], check=True, capture_output=True,
                       timeout=_COMPILE_TIMEOUT_S)
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int32
    lib.fh_version.restype = i32
    lib.fh_version.argtypes = ()
    lib.fh_init.restype = None
    lib.fh_init.argtypes = ()
    lib.fh_crc16.restype = ctypes.c_uint16
    lib.fh_crc16.argtypes = (p, i64)
    lib.fh_crc_packet.restype = ctypes.c_uint16
    lib.fh_crc_packet.argtypes = (p, p, i64, ctypes.c_uint8)
    lib.fh_scan.restype = i64
    lib.fh_scan.argtypes = (p, i64, i64, i64, p, p, i64, i64, p, p, p, p, p, p, p, p, p, i64, p, p)
    lib.fh_count.restype = i64
    lib.fh_count.argtypes = (p, i64, i64, i64, p, i64)
    lib.fh_tables.restype = i32
    lib.fh_tables.argtypes = (p, i64, i64, p, p, p, p, p, p, p, i32, p, p, p, p, p, p, p, p, p, p)
    lib.fh_fields.restype = i32
    lib.fh_fields.argtypes = (p, i64, p, p, p, p, i64, i32, p, p, p)
    for name in ("fh_searchsorted_f64", "fh_searchsorted_i64"):
        getattr(lib, name).restype = None
        getattr(lib, name).argtypes = (p, i64, p, i64, i32, p)
    lib.fh_lfilter2.restype = None
    lib.fh_lfilter2.argtypes = (p, p, p, i64, p, p)
    lib.fh_lfilter2_segments.restype = None
    lib.fh_lfilter2_segments.argtypes = (p, p, p, p, p, i64, p, p)
    lib.fh_wind_scan.restype = None
    lib.fh_wind_scan.argtypes = (p, i64, i64, p, p, p, ctypes.c_double, p, p)
    lib.fh_hermite_shift.restype = None
    lib.fh_hermite_shift.argtypes = (p, i64, p, p, p, p, i64, ctypes.c_double, p)
    lib.fh_odometry_changes.restype = None
    lib.fh_odometry_changes.argtypes = (p, i64, i64, p, p, p, p, p, p, p, i64, i64, p, p)
    lib.fh_free_rate.restype = None
    lib.fh_free_rate.argtypes = (p, i64, p, i64, p, p, i64, p, ctypes.c_double, p)
    lib.fh_filtfilt2_segments.restype = None
    lib.fh_filtfilt2_segments.argtypes = (p, p, p, p, p, p, i64, i64, p, p)
    lib.fh_form_drag.restype = None
    lib.fh_form_drag.argtypes = (p, i64, p, p, p, p, i64, p, p, p, p, i64, i64, p, p)
    lib.fh_csv_rows.restype = i64
    lib.fh_csv_rows.argtypes = (i64, i32, p, p, p, p, p, p, i64, i64)


def _load(path: Path) -> ctypes.CDLL | None:
    try:
        lib = ctypes.CDLL(str(path))
        _declare(lib)
        if lib.fh_version() != VERSION:
            return None
    except (OSError, AttributeError):
        return None
    lib.fh_init()
    return lib


@functools.cache
def _kernels() -> ctypes.CDLL | None:
    if os.name != "posix" or not SOURCE.is_file():
        return None
    candidates = [library_path()]
    fallback = Path(tempfile.gettempdir()) / f"flowhold-{os.getuid()}" / candidates[0].name
    candidates.append(fallback)
    for path in candidates:
        if path.is_file():
            lib = _load(path)
            if lib is not None:
                return lib
    import subprocess  # only to build

    for path in candidates:
        try:
            _build(path)
        except (OSError, subprocess.SubprocessError):
            continue
        return _load(path)
    return None


def kernels() -> ctypes.CDLL | None:
    """The loaded library (compiled first if needed), or None: then use the numpy path."""
    return _kernels() if enabled() else None


def ptr(a: object) -> int | None:
    """The data address of a numpy array, for a ``c_void_p`` argument."""
    return a.ctypes.data  # type: ignore[attr-defined]


def threads() -> int:
    """How many threads the kernels' callers run them in: the CPUs this process may run on
    (``os.sched_getaffinity``: ``taskset -c 0`` gives one), at most ``MAX_THREADS``. The kernels
    are called through ctypes, which lets go of the GIL for the call, so they run in parallel."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    return max(1, min(MAX_THREADS, cpus))


def run_all(tasks: Sequence[Callable[[], T]], n_threads: int) -> list[T]:
    """Each task's result, in the tasks' order. The tasks run on ``n_threads`` threads, this one
    among them, each taking the next task not yet taken; one thread: in order, here. The first
    exception a task raises is raised here once every thread has stopped (no task is started
    after it)."""
    results: list[T | None] = [None] * len(tasks)
    errors: list[BaseException] = []
    taken = itertools.count()  # next() of a count is atomic under the GIL

    def work() -> None:
        while not errors:
            i = next(taken)
            if i >= len(tasks):
                return
            try:
                results[i] = tasks[i]()
            except BaseException as exc:  # raised again in the caller's thread
                errors.append(exc)
                return

    pool = [threading.Thread(target=work, daemon=True, name=f"flowhold-kernel-{k}")
            for k in range(min(n_threads, len(tasks)) - 1)]
    for t in pool:
        t.start()
    try:
        work()
    finally:
        for t in pool:
            t.join()
    if errors:
        raise errors[0]
    return results  # type: ignore[return-value]


#: queries from which ``searchsorted`` calls the kernel (below, numpy's call costs less)
SEARCHSORTED_MIN = 1024


def searchsorted(a: Any, v: Any, side: str = "left") -> Any:
    """``numpy.searchsorted(a, v, side)`` for a sorted 1-d ``a``: by the compiled kernel
    (``fh_searchsorted_*``: galloping on from the previous answer, linear for sorted queries, as
    record numbers and times are) for int64 or float64 arrays of the same dtype, else by numpy.
    The same int64 indices either way (tests/test_native.py)."""
    a_arr, v_arr = np.asarray(a), np.asarray(v)
    lib = kernels()
    if (lib is None or a_arr.ndim != 1 or v_arr.ndim != 1 or len(v_arr) < SEARCHSORTED_MIN
            or a_arr.dtype != v_arr.dtype or a_arr.dtype not in (np.int64, np.float64)):
        return np.searchsorted(a_arr, v_arr, side=side)  # type: ignore[call-overload]
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', not {side!r}")
    a_c, v_c = np.ascontiguousarray(a_arr), np.ascontiguousarray(v_arr)
    out = np.empty(len(v_c), dtype=np.int64)
    fn = lib.fh_searchsorted_f64 if a_c.dtype == np.float64 else lib.fh_searchsorted_i64
    fn(a_c.ctypes.data, len(a_c), v_c.ctypes.data, len(v_c), int(side == "right"), out.ctypes.data)
    return out
