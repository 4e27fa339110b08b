"""Downward rangefinder: the height above ground, plus optional offset and Gaussian noise,
quantized to its resolution (1 cm as DISTANCE_SENSOR carries it).

It reads the vertical height, as the paper's altimeter does (Alt_meas = Alt_true). A reading
outside [min, max] is returned as is; DISTANCE_SENSOR consumers treat it as invalid.
"""

from __future__ import annotations

import numpy as np


def range_reading(height_m: float, rng: np.random.Generator | None, *, offset_m: float, noise_std_m: float,
                  resolution_m: float) -> float:
    """One range reading in metres."""
    r = height_m + offset_m
    if noise_std_m > 0.0 and rng is not None:
        r += float(rng.normal(0.0, noise_std_m))
    if resolution_m > 0.0:
        r = round(r / resolution_m) * resolution_m
    return r
