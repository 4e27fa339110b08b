"""docs/performance.md is generated, never typed (issue 17): it must be exactly what
benchmarks/render_performance.py makes of the committed results of one benchmark run. So must
the README's headline figures (issue 14): the block between its performance markers."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "performance_results.json"
DOC = ROOT / "docs" / "performance.md"
README = ROOT / "README.md"


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


@pytest.mark.skipif(not RESULTS.exists(), reason="no committed benchmark results")
def test_readme_figures_are_the_render_of_the_same_run():
    renderer = _renderer()
    results = json.loads(RESULTS.read_text())
    text = README.read_text()
    assert text.count(renderer.README_BEGIN) == 1 and text.count(renderer.README_END) == 1
    assert text == renderer.update_readme(text, results)
    block = text.split(renderer.README_BEGIN, 1)[1].split(renderer.README_END, 1)[0]
    assert results["numbers"]["machine"]["commit"] in block  # the run it quotes, named
    assert "docs/performance.md" in block


@pytest.mark.skipif(not RESULTS.exists(), reason="no committed benchmark results")
def test_update_readme_rewrites_only_between_the_markers():
    renderer = _renderer()
    results = json.loads(RESULTS.read_text())
    text = f"head\n{renderer.README_BEGIN}\nstale 97x and 130x\n{renderer.README_END}\ntail\n"
    out = renderer.update_readme(text, results)
    assert out.startswith(f"head\n{renderer.README_BEGIN}") and out.endswith(f"{renderer.README_END}\ntail\n")
    assert "stale" not in out and renderer.readme_block(results) in out
    with pytest.raises(ValueError):
        renderer.update_readme("no markers here", results)
