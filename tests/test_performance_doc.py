"""docs/performance.md is generated, never typed (issue 17): it must be exactly what
benchmarks/render_performance.py makes of the committed results of one benchmark run."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "performance_results.json"
DOC = ROOT / "docs" / "performance.md"


def _renderer():
    spec = importlib.util.spec_from_file_location("render_performance", ROOT / "benchmarks" / "render_performance.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.skipif(not RESULTS.exists(), reason="no committed benchmark results")
def test_performance_page_is_the_render_of_one_run():
    results = json.loads(RESULTS.read_text())
    assert "machine" in results["numbers"] and results["numbers"]["machine"]["load_samples"]
    assert DOC.read_text() == _renderer().render(results)
