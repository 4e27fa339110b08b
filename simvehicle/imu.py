"""Gyro model: true body rates plus optional constant bias and white noise, saturating at its range.

White noise of density N (rad/s/sqrt(Hz)) sampled at f_s has a per-sample standard deviation
of N sqrt(f_s) (the continuous-to-discrete convention of Kalibr and most IMU simulators).
The default density is the VN-100's 0.0035 deg/s/sqrt(Hz) (Table II), off unless enabled.
"""

from __future__ import annotations

import math

import numpy as np


def gyro_sample(rate_x_rad_s: float, rate_y_rad_s: float, rate_z_rad_s: float, rng: np.random.Generator | None,
                *, bias_x_rad_s: float, bias_y_rad_s: float, noise_density_rad_s_sqrt_hz: float,
                rate_hz: float, range_rad_s: float) -> tuple[float, float, float]:
    """One gyro sample (roll, pitch, yaw rate) in rad/s, body FRD."""
    gx = rate_x_rad_s + bias_x_rad_s
    gy = rate_y_rad_s + bias_y_rad_s
    gz = rate_z_rad_s
    if noise_density_rad_s_sqrt_hz > 0.0 and rng is not None:
        sigma = noise_density_rad_s_sqrt_hz * math.sqrt(rate_hz)
        n = rng.normal(0.0, sigma, 3)
        gx, gy, gz = gx + float(n[0]), gy + float(n[1]), gz + float(n[2])
    lim = range_rad_s
    return (min(max(gx, -lim), lim), min(max(gy, -lim), lim), min(max(gz, -lim), lim))
