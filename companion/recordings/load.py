"""Any recording into the columnar form: ``load_recording`` picks a reader by file type.

Readers: ``companion.recordings.tlog_reader.read_tlog`` (.tlog), ``companion.recordings.importers`` (DataFlash .bin,
PX4 .ulg, CSV with a column map). Every reader also takes the file gzip-compressed
(``.tlog.gz``, ``.bin.gz``, ``.ulg.gz``, ``.csv.gz``): it is decompressed in memory
(``read_recording_bytes``).

The form itself, a ``Recording`` of one ``MessageTable`` per MAVLink message type, and the file
helpers live in ``companion.recordings.columnar``, below the readers (so no reader imports this module,
which imports them); they are re-exported here, where the tools import them from.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from pathlib import Path

from companion.errors import RecordingError
from companion.progress import Stages
from companion.recordings.columnar import (
    GZIP_SUFFIX,
    MessageTable,
    Recording,
    gunzip,
    is_gzip_path,
    open_recording,
    read_recording_bytes,
    recording_name,
    recording_stem,
    recording_suffix,
)

__all__ = ["GZIP_SUFFIX", "MessageTable", "Recording", "gunzip", "is_gzip_path", "load_recording", "open_recording",
           "read_recording_bytes", "recording_name", "recording_stem", "recording_suffix"]


def load_recording(path: str | Path, *, sensor_config: str | Path | None = None,
                   progress: bool = False, fields: Mapping[str, Collection[str]] | None = None) -> Recording:
    """Read any supported recording into columns: .tlog, DataFlash .bin, PX4 .ulg, or a CSV
    described by a sensor column map (``sensor_config``), each also gzip-compressed (``.gz``).
    The format comes from the suffix (any case) under a trailing ``.gz``; anything else is read
    as a .tlog. ``progress``: a progress bar on stderr while a long recording is read (a .tlog:
    the reader's own, for files over ``tlog_reader.PROGRESS_MIN_BYTES``; the importers: by stage,
    once the import has lasted ``companion.progress.DELAY_S``). ``fields``: for a .tlog, the
    fields of each message the caller will read, decoded first (``tlog_reader.read_tlog``); the
    values are the same either way."""
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"recording not found: {p}")
    if p.is_dir():
        raise RecordingError(f"recording path is a directory: {p}")
    suffix = recording_suffix(p)
    if sensor_config is not None or suffix == ".csv":
        if sensor_config is None:
            raise RecordingError(f"{p.name}: a CSV needs --sensor-config (a column map in configs/sensors/)")
        from companion.recordings.importers.csv_columns import STAGES as CSV_STAGES
        from companion.recordings.importers.csv_columns import read_csv

        with Stages(progress, f"importing {p.name}", len(CSV_STAGES)) as done:
            return read_csv(p, sensor_config, progress=done)
    if suffix == ".bin":
        from companion.recordings.importers.dataflash import STAGES as BIN_STAGES
        from companion.recordings.importers.dataflash import read_dataflash

        with Stages(progress, f"importing {p.name}", len(BIN_STAGES)) as done:
            return read_dataflash(p, progress=done)
    if suffix == ".ulg":
        from companion.recordings.importers.ulog import STAGES as ULOG_STAGES
        from companion.recordings.importers.ulog import read_ulog

        with Stages(progress, f"importing {p.name}", len(ULOG_STAGES)) as done:
            return read_ulog(p, progress=done)
    from companion.recordings.tlog_reader import read_tlog

    return read_tlog(p, progress=progress, fields=fields)
