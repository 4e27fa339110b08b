"""The live loop's scalar flow path equals the column path used by replay, for every profile."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.estimator import scene_rate, scene_rate_scalar
from companion.profiles import FieldView, Profile, flow_columns, flow_scalar

ENC = mav.MAVLink(None, 1, 1)


def _same(a: float, b: float) -> bool:
    return (a == b) or (math.isnan(a) and math.isnan(b))


def _messages(rng: np.random.Generator, profile: Profile):
    for _ in range(300):
        if profile is Profile.PX4:
            integ = int(rng.choice([0, 10000, 20000, int(rng.integers(1, 100000))]))
            yield ENC.optical_flow_rad_encode(int(rng.integers(0, 2**40)), 0, integ, *rng.normal(0, 0.1, 5).tolist(),
                                              0, int(rng.integers(0, 256)), 0, float(rng.uniform(0, 5)))
        else:
            yield ENC.optical_flow_encode(int(rng.integers(0, 2**40)), 0, int(rng.integers(-300, 300)),
                                          int(rng.integers(-300, 300)), *rng.normal(0, 1, 2).tolist(),
                                          int(rng.integers(0, 256)), float(rng.uniform(-1, 5)),
                                          *rng.normal(0, 2, 2).tolist())


@pytest.mark.parametrize("profile", list(Profile))
def test_scalar_flow_equals_columns_bit_for_bit(profile):
    rng = np.random.default_rng(7)
    q = 0.09 / 57.3
    for msg in _messages(rng, profile):
        msg = mav.MAVLink(None).decode(bytearray(msg.pack(ENC)))  # float32 on the wire, as live
        s = flow_scalar(msg, profile, q)
        c = flow_columns(FieldView(msg), profile, q)
        for name in ("time_s", "scene_x", "scene_y", "integration_s", "quality", "counts_x", "counts_y",
                     "body_x_rad_s", "body_y_rad_s"):
            with np.errstate(all="ignore"):
                assert _same(float(getattr(s, name)), float(getattr(c, name))), (profile, name)
        assert s.increment == c.increment
        for dt in (0.02, 0.013):
            assert _same(scene_rate_scalar(s.scene_x, s.increment, s.integration_s, dt),
                         float(scene_rate(c.scene_x, c.increment, c.integration_s, dt)))
