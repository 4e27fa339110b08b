"""Helpers the importers share (DataFlash, ULog, CSV): building the columnar tables, ordering
their rows into one record sequence, matching samples by time, and finding the read grid of a
log whose rows come faster than its sensor is read (also used by the sensor-only diagnosis).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from companion.recordings.columnar import MessageTable

#: standard gravity used by ArduPilot (GRAVITY_MSS) and PX4 for RAW_IMU milli-g
GRAVITY_M_S2 = 9.80665

#: a table's fields: name -> array (n,) or (n, k)
Columns = dict[str, np.ndarray]


def build_table(name: str, t_s: np.ndarray, fields: Columns, *, sysid: int = 1,
                compid: int = 1) -> MessageTable:
    """A MessageTable with ``t_s`` (s), sender ids and a placeholder ``record`` (set by
    ``assign_records``)."""
    n = len(t_s)
    return MessageTable(
        name=name,
        t_s=np.asarray(t_s, dtype=np.float64),
        sysid=np.full(n, sysid, np.uint8),
        compid=np.full(n, compid, np.uint8),
        record=np.arange(n, dtype=np.int64),
        fields=fields,
    )


def assign_records(tables: dict[str, MessageTable], keys: Mapping[str, np.ndarray], notes: list[str]) -> None:
    """Sort each table by (``t_s``, key) and number all rows of all tables in that order.

    ``keys[name]``: a tie-break per row (e.g. the file offset), equal length to the table.
    Rewrites ``tables`` in place; a table that was out of time order gets a note.
    """
    names = list(tables)
    for name in names:
        tab, key = tables[name], np.asarray(keys[name])
        order = np.lexsort((key, tab.t_s))
        moved = int(np.sum(order != np.arange(len(order))))
        if moved:
            notes.append(f"{name}: {moved} rows out of time order, sorted by time")
            tables[name] = tab.select(order)
            keys = {**keys, name: key[order]}
    if not names:
        return
    t_all = np.concatenate([tables[n].t_s for n in names])
    k_all = np.concatenate([np.asarray(keys[n], dtype=np.float64) for n in names])
    which = np.concatenate([np.full(len(tables[n]), i) for i, n in enumerate(names)])
    order = np.lexsort((which, k_all, t_all))
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    start = 0
    for n in names:
        stop = start + len(tables[n])
        tables[n].record = rank[start:stop]
        start = stop


def nearest_index(t_ref: np.ndarray, t_query: np.ndarray, tol: float) -> np.ndarray:
    """Index of the ``t_ref`` sample nearest to each ``t_query`` (both in the same unit,
    ``t_ref`` sorted), or -1 where the nearest is farther than ``tol``."""
    t_ref = np.asarray(t_ref, dtype=np.float64)
    t_query = np.asarray(t_query, dtype=np.float64)
    if len(t_ref) == 0:
        return np.full(len(t_query), -1, np.int64)
    hi = np.clip(np.searchsorted(t_ref, t_query), 0, len(t_ref) - 1)
    lo = np.clip(hi - 1, 0, len(t_ref) - 1)
    pick = np.where(np.abs(t_ref[lo] - t_query) <= np.abs(t_ref[hi] - t_query), lo, hi)
    return np.where(np.abs(t_ref[pick] - t_query) <= tol, pick, -1).astype(np.int64)


@dataclass(frozen=True)
class ReadGrid:
    """How logged rows map onto the flow sensor's reads at ``phase_s + k * period_s``.

    ``slot``: the read each row holds (int64), or None when the rows alone cannot tell (rows
    never closer than one read period: every row is then a distinct reading). ``agreement``:
    fraction of value changes that fall on a slot change (NaN without a phase).
    """

    period_s: float
    phase_s: float | None
    slot: np.ndarray | None
    agreement: float
    method: str


def find_read_grid(time_s: np.ndarray, readings: np.ndarray, period_s: float, *,
                   min_agreement: float = 0.95) -> ReadGrid:
    """Find the read grid from rows that sample faster than the sensor is read.

    ``readings``: (n, k) values that identify a reading (counts and quality). A new reading can
    only appear when a row crosses a read time, so the phase is the one that puts the most value
    changes on slot changes and the fewest slot changes without a value change. Used only when
    at least 20 % of row steps are shorter than 0.9 read periods.
    """
    t = np.asarray(time_s, dtype=float)
    n = len(t)
    steps = np.diff(t)
    if n < 3 or np.mean(steps < 0.9 * period_s) < 0.2:
        return ReadGrid(period_s, None, None, float("nan"),
                        "rows are never closer than one read period, so each row is a distinct reading")
    vals = np.asarray(readings, dtype=float).reshape(n, -1)
    change = np.any(vals[1:] != vals[:-1], axis=1)
    phases = np.linspace(0.0, period_s, 200, endpoint=False)
    scores = np.empty(len(phases))
    for i, p in enumerate(phases):
        slot = np.floor((t - t[0] - p) / period_s)
        cross = slot[1:] != slot[:-1]
        scores[i] = np.sum(change == cross)
    best = np.flatnonzero(scores == scores.max())
    p = float(phases[best[len(best) // 2]])
    slot = np.floor((t - t[0] - p) / period_s).astype(np.int64)
    cross = slot[1:] != slot[:-1]
    agreement = float(np.sum(change & cross) / max(1, np.sum(change)))
    if agreement < min_agreement:
        return ReadGrid(period_s, None, None, agreement,
                        f"no read phase explains the value changes (best {100 * agreement:.0f} %); "
                        "rows treated as distinct readings")
    return ReadGrid(period_s, (t[0] + p) % period_s, slot, agreement,
                    f"read grid of {1e3 * period_s:g} ms found from the rows: {100 * agreement:.1f} % of value "
                    f"changes fall on a new read slot")
