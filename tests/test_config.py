"""Parameter loading: Table VI values, strictness, every shipped config."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from companion.config import CONFIG_DIR, REMOVED_KEYS, config_from_dict, load_config
from companion.errors import ConfigError

CONFIG_FILES = sorted(p for p in CONFIG_DIR.glob("*.toml"))


def _paper_dict() -> dict:
    with (CONFIG_DIR / "paper.toml").open("rb") as fh:
        return tomllib.load(fh)


def test_paper_toml_is_table_vi(paper_cfg):
    c = paper_cfg
    assert (c.airframe.mass_kg, c.airframe.gravity_m_s2) == (2.3, 9.81)
    assert (c.airframe.omega_p_rad_s, c.airframe.zeta) == (5.4, 0.71)
    assert (c.controller.kp_rad_per_m_s, c.controller.ki_rad_per_m) == (0.2, 0.062)
    assert c.controller.tilt_limit_rad == pytest.approx(20 / 57.3, rel=1e-3)
    assert c.flow_sensor.frame_rate_hz == 50.0
    assert c.flow_sensor.q_rad_per_count == pytest.approx(0.09 / 57.3, rel=1e-12)
    assert c.world.altitude_m == 1.0
    assert c.effects.active() == []


@pytest.mark.parametrize("path", CONFIG_FILES, ids=lambda p: p.name)
def test_every_shipped_config_loads(path: Path):
    cfg = load_config(path)
    assert math.isfinite(cfg.flow_sensor.q_rad_per_count)


def test_unknown_key_is_rejected():
    d = _paper_dict()
    d["controller"]["kd_rad_s_per_m"] = 0.1
    with pytest.raises(ConfigError, match="unknown key.*kd_rad_s_per_m"):
        config_from_dict(d)


@pytest.mark.parametrize("section,key", sorted(REMOVED_KEYS))
def test_a_removed_key_is_rejected_with_its_reason(section, key):
    """Issue 13: airframe.drag_b_n_s_per_m and companion.gyro_timeout_s were required and read by
    nothing; a parameter set that still has one is told so in one line."""
    d = _paper_dict()
    assert key not in d[section]
    d[section][key] = 0.1
    with pytest.raises(ConfigError, match=f"\\[{section}\\]: {key} is no longer a key: .*; delete the line"):
        config_from_dict(d)


def test_missing_key_is_rejected():
    d = _paper_dict()
    del d["airframe"]["zeta"]
    with pytest.raises(ConfigError, match="missing key.*zeta"):
        config_from_dict(d)


def test_misspelt_effect_and_effect_parameters_are_rejected():
    d = _paper_dict()
    d["effects"] = {"linear_drgа": {"enabled": True, "b": 0.2}}
    with pytest.raises(ConfigError, match="unknown effect"):
        config_from_dict(d)
    d["effects"] = {"linear_drag": {"enabled": True, "bb": 0.2}}
    with pytest.raises(ConfigError, match="unknown key"):
        config_from_dict(d)


def test_effects_switch_on_only_when_enabled():
    d = _paper_dict()
    d["effects"] = {"linear_drag": {"enabled": True, "b": 0.3},
                    "gyro_bias": {"enabled": False, "bias_x": 0.01, "bias_y": 0.0}}
    cfg = config_from_dict(d)
    assert cfg.effects.active() == ["linear_drag"]
    assert cfg.effects.linear_drag.b == 0.3


def test_wrong_types_and_bad_values_are_rejected():
    d = _paper_dict()
    d["airframe"]["mass_kg"] = "heavy"
    with pytest.raises(ConfigError, match="expected a number"):
        config_from_dict(d)
    d = _paper_dict()
    d["airframe"]["mass_kg"] = -1.0
    with pytest.raises(ConfigError, match="mass_kg must be > 0"):
        config_from_dict(d)


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[airframe\nmass_kg = 1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
