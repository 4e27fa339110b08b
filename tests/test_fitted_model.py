"""The fitted model as a parameter set (issue 16): ``diagnose REC --model-out fitted.toml``."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.config import CONFIG_DIR, EFFECT_TYPES, load_config
from companion.diagnose.fitted_model import (
    MIN_SPLIT_S,
    NOT_SIMULATED,
    config_toml,
    fitted_findings,
    heldout_split_s,
    model_toml,
)
from companion.diagnose.report import Finding, Report
from companion.errors import ConfigError
from simvehicle.engines.scenarios import SCENARIOS, fly

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("name", sorted(p.name for p in CONFIG_DIR.glob("*.toml")))
def test_every_shipped_config_is_written_back_as_it_loads(tmp_path, name):
    cfg = load_config(CONFIG_DIR / name)
    out = tmp_path / "c.toml"
    out.write_text(config_toml(cfg))
    back = load_config(out)
    assert dataclasses.replace(back, source=cfg.source, effects=cfg.effects) == cfg


def _f(effect: str, p: dict[str, float], sd: dict[str, float], significant: bool = True) -> Finding:
    return Finding(effect, significant, p, sd, "")


def test_the_model_loads_with_each_fitted_effect_and_the_rest_as_comments(tmp_path, paper_cfg):
    drag = _f("linear_drag", {"b": 0.31}, {"b": 0.02})
    scale = _f("flow_scale", {"scale_x": 1.1, "scale_y": 1.08}, {"scale_x": 0.004, "scale_y": 0.005})
    yaw = _f("flow_yaw_misalignment", {"yaw": math.radians(6.0)}, {"yaw": 0.002})
    lag = _f("gyro_lag", {"tau": 0.01}, {"tau": 1e-4})
    wind_half = _f("wind_force", {"fx": 9.0, "fy": 9.0, "start_s": 1.0, "end_s": 2.0}, {})
    wind = _f("wind_force", {"fx": 1.5, "fy": -0.5, "start_s": 40.0, "end_s": 70.0},
              {"fx": 0.05, "fy": 0.05, "start_s": 0.3, "end_s": 0.3})
    not_sig = _f("range_offset", {"offset": 0.3}, {"offset": 0.5}, significant=False)
    found = fitted_findings(Report("r", findings=[drag, scale, yaw, lag, wind_half, not_sig]),
                            Report("r", findings=[wind, drag]))
    assert [f.effect for f in found] == ["linear_drag", "flow_scale", "flow_yaw_misalignment", "gyro_lag",
                                         "wind_force"]
    text = model_toml(paper_cfg, found, recording="r.tlog", fit_window_s=(0.0, 75.0), span_s=(0.0, 150.0))
    out = tmp_path / "fitted.toml"
    out.write_text(text)
    cfg = load_config(out)
    e = cfg.effects
    assert e.linear_drag.b == 0.31 and (e.flow_scale.scale_x, e.flow_scale.scale_y) == (1.1, 1.08)
    assert e.flow_yaw_misalignment.yaw == pytest.approx(math.radians(6.0))
    # the wind of the whole flight, in recording time, not the first half's
    assert (e.wind_force.fx, e.wind_force.fy, e.wind_force.start_s, e.wind_force.end_s) == (1.5, -0.5, 40.0, 70.0)
    assert e.range_offset is None
    assert "# gyro_lag (tau = 0.01 +- 0.0001 s): not set: the simulator's gyro is not filtered." in text
    assert "b = 0.31   # +- 0.02 N s/m" in text
    # every section as the nominal has it
    assert dataclasses.replace(cfg, effects=paper_cfg.effects, source=paper_cfg.source) == paper_cfg


def test_an_unknown_key_inside_an_effect_table_is_rejected(tmp_path, paper_cfg):
    text = config_toml(paper_cfg) + "\n[effects.linear_drag]\nenabled = true\nb = 0.3\nc = 1.0\n"
    out = tmp_path / "bad.toml"
    out.write_text(text)
    with pytest.raises(ConfigError, match=r"unknown key\(s\) c"):
        load_config(out)


def test_every_effect_the_finder_names_is_a_table_or_says_why_not():
    from simvehicle.engines.flightgen import EFFECT_NAMES  # CONVENTIONS.md's effect table, written independently

    assert not set(EFFECT_TYPES) & set(NOT_SIMULATED)
    assert set(EFFECT_TYPES) | set(NOT_SIMULATED) == set(EFFECT_NAMES)


def test_a_flight_is_split_at_the_middle_of_its_usable_frames_when_long_enough():
    assert heldout_split_s(np.arange(0.0, 150.0, 0.02) + 10.0) == pytest.approx(10.0 + 149.98 / 2)
    assert heldout_split_s(np.arange(0.0, MIN_SPLIT_S - 1.0, 0.02)) is None


def _diagnose(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "companion", "diagnose", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=300)


def test_model_out_of_the_gust_scenario_replays_its_wind(tmp_path, paper_cfg):
    """gust: -4 N on both axes from 5 s to the end of a 25 s flight (scenarios.py): too short to split,
    fitted whole; its model carries the wind in recording time."""
    tlog = tmp_path / "gust.tlog"
    fly(paper_cfg, SCENARIOS["gust"], tlog=tlog)
    out = tmp_path / "fitted.toml"
    r = _diagnose(str(tlog), "--model-out", str(out))
    assert r.returncode == 0, r.stderr
    assert f"model: {out}" in r.stdout
    cfg = load_config(out)
    w = cfg.effects.wind_force
    assert (w.fx, w.fy) == (pytest.approx(-4.0, rel=0.05), pytest.approx(-4.0, rel=0.05))
    assert w.start_s == pytest.approx(5.0, abs=0.5)  # the scenario's clock starts with the recording
    assert "fitted whole, nothing held out" in out.read_text()


def test_model_out_refuses_a_sensor_only_recording_in_one_line(tmp_path):
    out = tmp_path / "m.toml"
    r = _diagnose(str(REPO / "data" / "real" / "stampfly" / "static_final.csv.gz"), "--sensor-config",
                  str(REPO / "configs" / "sensors" / "stampfly.toml"), "--model-out", str(out))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "--model-out" in r.stderr
    assert not out.exists()
