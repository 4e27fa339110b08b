"""The columnar recording: what every reader and importer produces, and every tool consumes.

A ``Recording`` is one ``MessageTable`` per MAVLink message type. A table holds one numpy
array per message field (MAVLink field names and MAVLink units, e.g. RAW_IMU ``xgyro`` in
mrad/s), plus the log time of each message, the sender's system/component ids and the
message's position in the file (``record``), so the original interleaving of message types can
be rebuilt by sorting on ``record``. Opening a recording file, plain or gzip-compressed
(``read_recording_bytes``, ``open_recording``), is here too.

This module sits below the readers (``companion.recordings.tlog_reader``, ``companion.recordings.importers``), which
build these tables; ``companion.recordings.load.load_recording`` picks a reader by file type, above
them, and re-exports these names (issue 13: the readers no longer import the module that
imports them).
"""

from __future__ import annotations

import gzip
import io
import zlib
from collections.abc import Callable, ItemsView, Iterator, Mapping, Sequence, ValuesView
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from companion.errors import RecordingError


class LazyColumns(Mapping[str, np.ndarray]):
    """A table's fields (name -> column, in ``names`` order), each column made the first time it
    is asked for and then kept: ``make(names)`` returns the columns of those names, for every
    row of the table as read. A reader whose tables are read for a few fields (replay, info)
    decodes only those (issue 17: in a fresh process the pages of every column decoded cost
    their zeroing). ``rows``: this mapping stands for those rows of ``make``'s columns (a
    selection, kept lazy by ``select``). Pickled as a plain dict of every column."""

    def __init__(self, names: Sequence[str], make: Callable[[list[str]], list[np.ndarray]],
                 rows: np.ndarray | None = None, done: dict[str, np.ndarray] | None = None) -> None:
        self._names = tuple(names)
        self._known = frozenset(self._names)
        self._make = make
        self._rows = rows
        self._done: dict[str, np.ndarray] = dict(done or {})

    def __getitem__(self, key: str) -> np.ndarray:
        col = self._done.get(key)
        if col is None:
            if key not in self._known:
                raise KeyError(key)
            self._fill([key])
            col = self._done[key]
        return col

    def __contains__(self, key: object) -> bool:
        return key in self._known

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def _fill(self, keys: list[str]) -> None:
        cols = self._make(keys)
        if self._rows is not None:
            cols = [c[self._rows] for c in cols]
        self._done.update(zip(keys, cols, strict=True))

    def _all(self) -> None:
        missing = [k for k in self._names if k not in self._done]
        if missing:
            self._fill(missing)

    def items(self) -> ItemsView[str, np.ndarray]:
        self._all()  # in one go
        return super().items()

    def values(self) -> ValuesView[np.ndarray]:
        self._all()
        return super().values()

    def select(self, mask: np.ndarray) -> LazyColumns:
        """The rows ``mask`` (boolean or index array) selects, still lazy."""
        picked = np.flatnonzero(mask) if np.asarray(mask).dtype == bool else np.asarray(mask)
        rows = picked if self._rows is None else self._rows[picked]
        return LazyColumns(self._names, self._make, rows, {k: v[mask] for k, v in self._done.items()})

    def __reduce__(self) -> tuple[Any, ...]:
        return dict, (dict(self.items()),)


@dataclass
class MessageTable:
    """All messages of one type, as columns of equal length ``n``.

    ``t_s``: log time of each message, s (UNIX time for a .tlog; the importer's time base
    otherwise), float64. ``sysid``, ``compid``: sender ids (uint8). ``record``: index of the
    message in the file (int64, increasing). ``fields``: field name -> array of shape (n,) or
    (n, k) for array fields (e.g. ATTITUDE_TARGET ``q``: (n, 4)). Char arrays are ``str``
    object arrays.
    """

    name: str
    t_s: np.ndarray
    sysid: np.ndarray
    compid: np.ndarray
    record: np.ndarray
    fields: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def __getitem__(self, key: str) -> np.ndarray:
        try:
            return self.fields[key]
        except KeyError:
            raise RecordingError(f"{self.name} has no field {key!r}") from None

    def select(self, mask: np.ndarray) -> MessageTable:
        """The rows where ``mask`` (boolean or index array) selects."""
        return MessageTable(
            self.name,
            self.t_s[mask],
            self.sysid[mask],
            self.compid[mask],
            self.record[mask],
            self.fields.select(mask) if isinstance(self.fields, LazyColumns)
            else {k: v[mask] for k, v in self.fields.items()},
        )

    def from_sender(self, sysid: int | None = None, compid: int | None = None) -> MessageTable:
        mask = np.ones(len(self), dtype=bool)
        if sysid is not None:
            mask &= self.sysid == sysid
        if compid is not None:
            mask &= self.compid == compid
        return self.select(mask)


@dataclass
class Recording:
    """A whole recording as per-message-type columns, with what was skipped while reading."""

    path: str
    tables: dict[str, MessageTable]
    source_format: str  # "tlog", "dataflash", "ulog" or "csv"
    skipped_bytes: int = 0
    skipped_packets: int = 0
    #: one line each: what was skipped, repaired or degraded while reading
    notes: list[str] = field(default_factory=list)
    #: the sensor profile an importer produced its tables in (None: decide from the content)
    profile_hint: str | None = None

    def __contains__(self, name: str) -> bool:
        return name in self.tables and len(self.tables[name]) > 0

    def __iter__(self) -> Iterator[MessageTable]:
        return iter(self.tables.values())

    def table(self, name: str) -> MessageTable:
        """The table of ``name``; a RecordingError that names the message if there is none."""
        if name not in self:
            raise RecordingError(f"{Path(self.path).name}: no {name} messages in the recording")
        return self.tables[name]

    def first_of(self, *names: str) -> MessageTable:
        """The first of ``names`` present (e.g. a gyro: RAW_IMU, SCALED_IMU, HIGHRES_IMU)."""
        for name in names:
            if name in self:
                return self.tables[name]
        raise RecordingError(f"{Path(self.path).name}: none of {', '.join(names)} in the recording")

    @property
    def t0_s(self) -> float:
        """Log time of the first record: reports give times in seconds from here."""
        starts = [float(t.t_s[0]) for t in self.tables.values() if len(t)]
        if not starts:
            raise RecordingError(f"{Path(self.path).name}: the recording holds no messages")
        return min(starts)

    @property
    def n_messages(self) -> int:
        return sum(len(t) for t in self.tables.values())


def vehicle_sysid(flow: MessageTable) -> int:
    """The vehicle of a recording, the one rule replay, diagnose and the sensor-only diagnosis
    share (issue 13): the system that sent the most of the flow messages ``flow`` (the profile's
    flow table); on a tie, the one whose first flow message came first (the live loop, which
    can only know the first, takes the first vehicle it hears). A stray message from another
    system at the start of a log does not make that system the vehicle."""
    if len(flow) == 0:
        raise RecordingError(f"no {flow.name} messages: no vehicle to take the others from")
    ids, first, counts = np.unique(np.asarray(flow.sysid), return_index=True, return_counts=True)
    best = np.flatnonzero(counts == counts.max())
    return int(ids[best[np.argmin(first[best])]])


#: the suffix of a gzip-compressed recording (any case): ``flight.tlog.gz``, ``log.BIN.gz``
GZIP_SUFFIX = ".gz"


def is_gzip_path(path: str | Path) -> bool:
    """Whether ``path`` names a gzip-compressed recording (a trailing ``.gz``, any case)."""
    return Path(path).suffix.lower() == GZIP_SUFFIX


def recording_name(path: str | Path) -> str:
    """The recording's file name without a trailing ``.gz``: ``flight_a.tlog.gz`` -> ``flight_a.tlog``."""
    name = Path(path).name
    return name[: -len(GZIP_SUFFIX)] if is_gzip_path(name) else name


def recording_suffix(path: str | Path) -> str:
    """The format suffix in lower case, looking through a trailing ``.gz``: ``.tlog``, ``.bin``,
    ``.ulg``, ``.csv`` (``""`` when there is none)."""
    return Path(recording_name(path)).suffix.lower()


def recording_stem(path: str | Path) -> str:
    """The file name without its format suffix and a trailing ``.gz``: ``x.csv.gz`` -> ``x``."""
    return Path(recording_name(path)).stem


def gunzip(data: bytes, name: str) -> bytes:
    """``data`` (the bytes of the gzip file ``name``) decompressed; a one-line RecordingError
    for a truncated or corrupt file."""
    try:
        return gzip.decompress(data)
    except EOFError:
        raise RecordingError(f"{name}: truncated gzip file (the compressed data end early): "
                             "cannot decompress it") from None
    except (OSError, zlib.error) as exc:  # gzip.BadGzipFile is an OSError
        raise RecordingError(f"{name}: corrupt gzip file ({exc}): cannot decompress it") from None


def read_recording_bytes(path: str | Path) -> bytes:
    """The bytes of the recording ``path``, decompressed in memory when it ends in ``.gz``.
    RecordingError (one line) when it is missing, unreadable or a corrupt gzip file."""
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"recording not found: {p}")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise RecordingError(f"{p.name}: cannot read the file ({exc.strerror or exc})") from None
    return gunzip(data, p.name) if is_gzip_path(p) else data


def open_recording(path: str | Path) -> BinaryIO:
    """The recording ``path`` opened for binary reading: the file itself, or for a ``.gz`` its
    decompressed bytes in memory. RecordingError as ``read_recording_bytes``."""
    p = Path(path)
    if is_gzip_path(p):
        return io.BytesIO(read_recording_bytes(p))
    if not p.is_file():
        raise RecordingError(f"recording not found: {p}")
    try:
        return p.open("rb")
    except OSError as exc:
        raise RecordingError(f"{p.name}: cannot read the file ({exc.strerror or exc})") from None
