"""The diagnose test matrix of issue #5, as tests.

Each case is flown closed loop by the reference simulator (``simvehicle.engines.flights``: ~150 s of steps,
slow creeps, sinusoids on both axes, altitude changes, turbulence, gyro and range noise) and its
recording diagnosed by ``python -m companion diagnose`` in a subprocess that sees only the .tlog.
The issue's tolerances (``simvehicle.engines.flights.TOLERANCES``) are asserted per case: every planted
effect named with its parameters within tolerance, nothing else named, and the held-out residual
lower with each named effect than without.

Default run: a representative subset (a clean flight, a drag, a flow delay, a wind), two processes:
about 40-70 s on a loaded 2-core machine. The whole matrix (33 recordings) is ``@pytest.mark.slow``
(about 5 min with two processes); ``scripts/diagnose_matrix.py`` writes its table.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from typing import Any

import pytest

from simvehicle.engines.flights import MATRIX, MatrixCase

REPO = Path(__file__).resolve().parent.parent
SUBSET = ("clean-s2", "linear_drag-a", "flow_delay-a", "wind_force-b")


def _script() -> Any:
    spec = importlib.util.spec_from_file_location("diagnose_matrix", REPO / "scripts" / "diagnose_matrix.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["diagnose_matrix"] = module
    spec.loader.exec_module(module)
    return module


def _run(cases: list[MatrixCase], out: Path) -> dict[str, dict[str, Any]]:
    return {r["case"]: r for r in _script().run_matrix(cases, out, workers=2)}


def _check(result: dict[str, Any]) -> None:
    s = result["score"]
    assert not s.false, f"{s.case}: named effects that are not there: {s.false} ({result['report']['findings']})"
    assert not s.misses, f"{s.case}: missed {s.misses}; found {s.found}; error/tolerance {s.param_errors}"
    assert set(s.hits) == set(s.truth)
    for effect, ratios in s.param_errors.items():
        assert all(r <= 1.0 for r in ratios.values()), (s.case, effect, ratios)
    assert all(s.heldout_improved.values()), (s.case, s.heldout_improved)


@pytest.fixture(scope="module")
def subset(tmp_path_factory) -> dict[str, dict[str, Any]]:
    cases = [c for c in MATRIX if c.name in SUBSET]
    assert len(cases) == len(SUBSET)
    return _run(cases, tmp_path_factory.mktemp("matrix"))


@pytest.mark.parametrize("name", SUBSET)
def test_subset_case(subset, name):
    r = subset[name]
    print(f"\n{name}: diagnosed in {r['wall_s']:.1f} s (150 s recording, subprocess including start-up)")
    _check(r)


@pytest.mark.slow
def test_full_matrix(tmp_path_factory):
    results = _run(list(MATRIX), tmp_path_factory.mktemp("matrix_full"))
    print("\n" + _script().table(list(results.values())).splitlines()[0])
    failures = []
    for r in results.values():
        try:
            _check(r)
        except AssertionError as exc:
            failures.append(str(exc))
    assert not failures, "\n".join(failures)
    clean = [r for r in results.values() if not r["score"].truth]
    assert len(clean) >= 3
    assert all(not [f for f in r["report"]["findings"] if f["significant"]] for r in clean)
