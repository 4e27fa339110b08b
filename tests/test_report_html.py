"""The HTML diagnose report and its plain-words first line (issue 14): one self-contained page
(plots embedded, nothing loaded from elsewhere) that opens with what differs, how sure, and what
to change in the config with the fitted values, keys the config loader accepts."""

from __future__ import annotations

import base64
import html
import re
import tomllib
from pathlib import Path

import pytest

from companion.config import config_from_dict
from companion.diagnose.advice import change_for, config_changes, how_sure, lead
from companion.diagnose.report import Finding, Fit, Report
from companion.diagnose.report_html import markdown_to_html, render, write_html_report

REPO = Path(__file__).resolve().parent.parent
PAPER = REPO / "configs" / "paper.toml"
Q = 0.09 / 57.3
#: the smallest valid PNG (1 x 1 pixel)
PNG = base64.b64decode("iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mNk+M9QDwADhgGAWjR9aw"
                       "AAAABJRU5ErkJggg==")


def _finding(effect: str, params: dict[str, float], sd: dict[str, float], *, significant: bool = True,
             before: float = 2.0, after: float = 1.0) -> Finding:
    return Finding(effect, significant, params, sd, "physics", fit=Fit(before, after))


def external_references(page: str) -> list[str]:
    """Every src/href/url() of ``page`` that would load or point somewhere outside it."""
    refs = re.findall(r"""(?:src|href)\s*=\s*["']?([^"'\s>]+)""", page, flags=re.I)
    refs += re.findall(r"url\(\s*['\"]?([^)'\"]+)", page, flags=re.I)
    refs += re.findall(r"@import", page)
    return [r for r in refs if not r.startswith("data:image/png;base64,")]


def _apply(changes) -> dict:  # noqa: ANN001
    """paper.toml with the suggested keys set, as a user would edit a copy of it."""
    data = tomllib.loads(PAPER.read_text())
    for c in changes:
        table = data
        for part in c.section.split("."):
            table = table.setdefault(part, {})
        table.update(c.values)
    return data


# --- what to change in the config ------------------------------------------------------------


def test_each_config_change_names_keys_the_loader_accepts_with_the_fitted_values():
    rep = Report("f.tlog", headline="The model leaves out ...", findings=[
        _finding("attitude_dynamics", {"omega_p": 13.7, "zeta": 1.14}, {"omega_p": 0.5, "zeta": 0.03}),
        _finding("linear_drag", {"b": 0.62}, {"b": 0.013}),
        _finding("gyro_bias", {"bias_x": 0.01, "bias_y": -0.008}, {"bias_x": 1e-4, "bias_y": 1e-4}),
        _finding("flow_scale", {"scale_x": 1.4, "scale_y": 1.6}, {"scale_x": 0.01, "scale_y": 0.01}),
        _finding("range_offset", {"offset": 0.05}, {"offset": 0.003}, significant=False)])
    changes = config_changes(rep, q_rad_per_count=Q)
    cfg = config_from_dict(_apply(changes), "paper.toml with the suggestions")
    assert (cfg.airframe.omega_p_rad_s, cfg.airframe.zeta) == (13.7, 1.14)
    assert cfg.effects.linear_drag is not None and cfg.effects.linear_drag.b == 0.62
    assert cfg.effects.gyro_bias is not None and cfg.effects.gyro_bias.bias_y == -0.008
    assert cfg.flow_sensor.q_rad_per_count == pytest.approx(1.5 * Q)  # one Q: the mean of x and y
    assert cfg.effects.range_offset is None  # not significant: nothing suggested
    flow = next(c for c in changes if c.section == "flow_sensor")
    assert "x and y differ" in flow.why
    # the TOML text of each change parses to the same values (to 4 significant digits)
    for c in changes:
        parsed = tomllib.loads(c.toml())
        table = parsed
        for part in c.section.split("."):
            table = table[part]
        assert table == pytest.approx(c.values, rel=1e-3)


@pytest.mark.parametrize("effect, params", [
    ("wind_force", {"fx": -4.0, "fy": 0.0, "start_s": 18.0, "end_s": 30.0}),  # the flight, not the vehicle
    ("gyro_lag", {"tau": 0.01}),  # no key in the config
    ("missing_flow_readings", {"count": 197.5, "fraction": 0.097}),  # the log's timing
    ("flow_scale", {"scale_x": float("nan"), "scale_y": float("nan")}),  # nothing identifiable
])
def test_findings_with_nothing_to_change_suggest_nothing_and_say_why(effect, params):
    f = _finding(effect, params, {k: 0.01 for k in params})
    assert change_for(f, q_rad_per_count=Q) is None
    text = lead(Report("f.tlog", findings=[f]), q_rad_per_count=Q)
    assert "Nothing to change in the config" in text and effect in text


def test_the_lead_says_what_differs_how_sure_and_what_to_set():
    rep = Report("f.tlog", headline="The model leaves out linear_drag, wind_force", findings=[
        _finding("linear_drag", {"b": 0.62}, {"b": 0.013}, before=4.0, after=1.0),
        _finding("wind_force", {"fx": -4.0, "fy": 0.5, "start_s": 18.0, "end_s": 30.0},
                 {"fx": 0.004, "fy": 0.002, "start_s": 0.02, "end_s": 0.8})])
    text = lead(rep, q_rad_per_count=Q)
    assert text.startswith("The model leaves out linear_drag, wind_force.")
    assert "b 0.62 ± 0.013 N s/m" in text and "75 % less error on data the fit never saw" in text
    assert "In the config, set [effects.linear_drag] enabled = true, b = 0.62." in text
    assert "wind_force is a wind during this flight" in text
    assert how_sure(rep.findings[1]).startswith("wind_force (fx -4 ± 0.004 N, fy 0.5 ± 0.002 N, start_s 18 ± 0.02 s")
    clean = lead(Report("f.tlog", headline="the recording fits the nominal model within its noise"),
                 q_rad_per_count=Q)
    assert clean == "The recording fits the nominal model within its noise. Nothing to change in the config."


# --- the page --------------------------------------------------------------------------------


def test_markdown_becomes_html_with_the_images_embedded_and_no_link_out(tmp_path):
    (tmp_path / "a.png").write_bytes(PNG)
    md = ("# Title\n\n- one `code`\n- two **bold**\n  continued\n\nSee [the method](docs/diagnose.md) & more.\n\n"
          "![a plot](a.png)\n\n| x | y |\n|---|---|\n| 1 < 2 | 3 |\n\n![gone](missing.png)\n")
    out = markdown_to_html(md, tmp_path)
    assert "<h1>Title</h1>" in out
    assert "<ul><li>one <code>code</code></li><li>two <strong>bold</strong> continued</li></ul>" in out
    assert "<p>See the method (docs/diagnose.md) &amp; more.</p>" in out
    assert f'src="data:image/png;base64,{base64.b64encode(PNG).decode()}"' in out
    assert "<table><tr><th>x</th><th>y</th></tr><tr><td>1 &lt; 2</td><td>3</td></tr></table>" in out
    assert "plot not found: missing.png" in out
    assert external_references(out) == []


def test_the_page_opens_with_the_lead_then_the_changes_then_the_evidence(tmp_path):
    (tmp_path / "p.png").write_bytes(PNG)
    (tmp_path / "report.md").write_text("# Mismatch report: f.tlog\n\n- a note\n\n![residuals](p.png)\n")
    rep = Report("f.tlog", headline="The model leaves out attitude_dynamics", findings=[
        _finding("attitude_dynamics", {"omega_p": 13.7, "zeta": 1.14}, {"omega_p": 0.5, "zeta": 0.03})])
    path = write_html_report(rep, tmp_path / "report.md", q_rad_per_count=Q)
    page = path.read_text()
    assert path == tmp_path / "report.html" and page == render(rep, (tmp_path / "report.md").read_text(),
                                                              tmp_path, q_rad_per_count=Q)
    body = page.split("<body>", 1)[1]
    first = re.search(r'<p class="lead" id="headline">(.*?)</p>', body).group(1)
    assert body.index("<h1>") < body.index('class="lead"') < body.index("<pre>") < body.index("The evidence")
    assert html.unescape(first) == lead(rep, q_rad_per_count=Q)
    assert "[airframe]\nomega_p_rad_s = 13.7\nzeta = 1.14" in html.unescape(page)
    assert page.count("data:image/png;base64,") == 1 and external_references(page) == []


def test_a_report_without_a_headline_names_its_significant_effects():
    rep = Report("s.csv", mode="sensor", findings=[_finding("flow_delay", {"delay": 0.02}, {"delay": 0.0015}),
                                                   _finding("gyro_bias", {"bias_x": 0.0, "bias_y": 0.0},
                                                            {"bias_x": 1.0, "bias_y": 1.0}, significant=False)])
    assert lead(rep, q_rad_per_count=Q).startswith("The recording differs from the nominal model: flow_delay. "
                                                   "How sure: flow_delay (delay 0.02 ± 0.0015 s), with 50 % less")
