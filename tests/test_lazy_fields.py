"""The .tlog reader decodes the fields a tool reads with the rows and every other field when it
is first read (issue 17: replay on an hour-long recording reads about half of the decoded bytes,
and in a fresh process every page of a decoded column costs its zeroing). The values are the
same either way: ``columnar.LazyColumns`` against plain dicts, the reader with and without a
``fields`` hint against each other, and ``replay.REPLAY_FIELDS`` complete (replay on recordings
of the three profiles, every estimator and gyro choice, decodes nothing late and gives what it
gives on a recording decoded whole)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from test_native import assert_same_recording
from test_replay import SHORT_STEP
from test_tlog_reader import build_all_types

from companion import native
from companion.recordings import tlog_reader as tr
from companion.recordings.columnar import LazyColumns, MessageTable
from companion.recordings.load import load_recording
from companion.step.core import EstimatorOptions, GyroSource, VelocityEstimator
from companion.step.profiles import Profile
from companion.tools.replay import REPLAY_FIELDS, replay
from simvehicle.engines.scenarios import fly

pytestmark = pytest.mark.skipif(native.kernels() is None, reason="lazy fields come with the compiled kernels")


def _columns() -> tuple[dict[str, np.ndarray], list[list[str]], LazyColumns]:
    full = {"a": np.arange(6.0), "b": np.arange(6) * 10, "q": np.arange(24.0).reshape(6, 4)}
    calls: list[list[str]] = []

    def make(names: list[str]) -> list[np.ndarray]:
        calls.append(list(names))
        return [full[k].copy() for k in names]

    return full, calls, LazyColumns(("a", "b", "q"), make)


def test_lazy_columns_are_the_columns_made_once_on_first_use():
    full, calls, lazy = _columns()
    assert list(lazy) == ["a", "b", "q"] and len(lazy) == 3 and "b" in lazy and "z" not in lazy
    assert calls == []
    np.testing.assert_array_equal(lazy["b"], full["b"])
    assert lazy["b"] is lazy["b"] and calls == [["b"]]
    with pytest.raises(KeyError):
        lazy["z"]
    assert [k for k, _ in lazy.items()] == ["a", "b", "q"]
    assert calls == [["b"], ["a", "q"]]  # the rest in one go
    table = MessageTable("X", np.arange(6.0), np.ones(6, np.uint8), np.ones(6, np.uint8), np.arange(6), lazy)
    with pytest.raises(Exception, match="X has no field 'z'"):
        table["z"]


@pytest.mark.parametrize("decoded_first", [False, True])
def test_a_selection_stays_lazy_and_equals_the_eager_selection(decoded_first):
    full, calls, lazy = _columns()
    if decoded_first:
        lazy["a"]
    table = MessageTable("X", np.arange(6.0), np.ones(6, np.uint8), np.ones(6, np.uint8), np.arange(6), lazy)
    eager = MessageTable("X", table.t_s, table.sysid, table.compid, table.record, dict(full))
    mask = np.array([True, False, True, True, False, True])
    sel, sel_eager = table.select(mask), eager.select(mask)
    assert isinstance(sel.fields, LazyColumns)
    again, again_eager = sel.select(np.array([3, 0])), sel_eager.select(np.array([3, 0]))  # indices, twice
    for a, b in ((sel, sel_eager), (again, again_eager)):
        for k in full:
            np.testing.assert_array_equal(a[k], b[k])
    assert calls[-1] in (["q"], ["a", "q"], ["b"])  # made for the whole table, then selected


def test_lazy_columns_pickle_as_a_dict():
    full, _, lazy = _columns()
    back = pickle.loads(pickle.dumps(lazy))
    assert type(back) is dict and list(back) == list(full)
    for k in full:
        np.testing.assert_array_equal(back[k], full[k])


@pytest.mark.parametrize("hint", ["none", "some", "replay"])
def test_the_reader_with_a_fields_hint_equals_the_reader_without(tmp_path, hint):
    """Every message type and packet kind (signed, MAVLink 1, truncated payloads, char arrays,
    array fields), read with no field, some fields or replay's fields decoded with the rows:
    every column equal to the whole decoding's, bit for bit."""
    built = build_all_types(tmp_path / "all.tlog", np.random.default_rng(4))
    fields = {"none": {}, "some": {"OPTICAL_FLOW": ("flow_x", "quality"), "PARAM_VALUE": ("param_id",),
                                    "ATTITUDE_TARGET": ("q",)}, "replay": REPLAY_FIELDS}[hint]
    whole = tr.read_tlog(built.path)
    hinted = tr.read_tlog(built.path, fields=fields)
    assert any(isinstance(t.fields, LazyColumns) for t in hinted.tables.values())
    assert not any(isinstance(t.fields, LazyColumns) for t in whole.tables.values())
    assert_same_recording(hinted, whole)


@pytest.fixture(scope="module")
def three_profiles(tmp_path_factory, paper_cfg, flight_a_plain):
    d = tmp_path_factory.mktemp("lazy")
    paths = {}
    for prof in Profile:
        paths[prof] = d / f"step_{prof.value}.tlog"
        fly(paper_cfg, SHORT_STEP, profile=prof, tlog=paths[prof])
    return [(p, prof) for prof, p in paths.items()] + [(flight_a_plain, Profile.ARDUPILOT)]


OPTIONS = [EstimatorOptions(), EstimatorOptions(GyroSource.IMU), EstimatorOptions(GyroSource.FLOW),
           EstimatorOptions(estimator=VelocityEstimator.EQ15), EstimatorOptions(estimator=VelocityEstimator.KF),
           EstimatorOptions(GyroSource.IMU, estimator=VelocityEstimator.KF)]


def test_replay_fields_are_every_field_replay_reads(three_profiles, paper_cfg, monkeypatch):
    late: list[tuple[str, list[str]]] = []
    decode = tr._fields_native

    def spy(lib, buf, s, hdr, plen, lay, record, names):
        late.append((lay.name, names))
        return decode(lib, buf, s, hdr, plen, lay, record, names)

    monkeypatch.setattr(tr, "_fields_native", spy)
    for path, prof in three_profiles:
        whole = load_recording(path)
        for options in OPTIONS:
            rec = load_recording(path, fields=REPLAY_FIELDS)
            fast = replay(rec, paper_cfg, prof, options)
            assert late == [], (path.name, options, late)
            ref = replay(whole, paper_cfg, prof, options)
            assert list(fast.columns) == list(ref.columns) and fast.notes == ref.notes
            for k, col in ref.columns.items():
                assert fast.columns[k].tobytes() == col.tobytes() if col.dtype != object else \
                    fast.columns[k].tolist() == col.tolist(), (path.name, k)
