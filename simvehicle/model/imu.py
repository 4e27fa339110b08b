"""IMU models. Gyro: true body rates plus optional constant bias and white noise, saturating at its range.
Accelerometer: the body-frame specific force of the plant's motion (``specific_force``), with bias and
white noise the same way (``accel_sample``).

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


def specific_force(roll_rad: float, pitch_rad: float, accel_x_m_s2: float, accel_y_m_s2: float,
                   accel_z_m_s2: float, gravity_m_s2: float) -> tuple[float, float, float]:
    """What an ideal accelerometer reads, body FRD (m/s^2): ``R^T (a - g)``, ``a`` the vehicle's
    acceleration in the local NED frame, ``g = (0, 0, gravity)`` and ``R`` the body-to-NED rotation
    of (roll, pitch, yaw 0) (ZYX, CONVENTIONS.md: positive pitch nose up, positive roll right side
    down). At rest it reads (0, 0, -g), ArduPilot's RAW_IMU -1000 mg on z; a horizontal force F on
    mass m with the body level reads F / m along it."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    dx, dy, dz = accel_x_m_s2, accel_y_m_s2, accel_z_m_s2 - gravity_m_s2
    # R^T = Rx(roll)^T Ry(pitch)^T
    bx = cp * dx - sp * dz
    bz0 = sp * dx + cp * dz
    return bx, cr * dy + sr * bz0, -sr * dy + cr * bz0


def accel_sample(f_x_m_s2: float, f_y_m_s2: float, f_z_m_s2: float, rng: np.random.Generator | None, *,
                 bias_x_m_s2: float, bias_y_m_s2: float, noise_density_m_s2_sqrt_hz: float, rate_hz: float,
                 range_m_s2: float) -> tuple[float, float, float]:
    """One accelerometer sample (body FRD specific force, m/s^2): the truth plus a constant bias on
    x and y and white noise of ``noise_density * sqrt(rate)`` a sample (the gyro's convention),
    saturating at ``range_m_s2``."""
    ax, ay, az = f_x_m_s2 + bias_x_m_s2, f_y_m_s2 + bias_y_m_s2, f_z_m_s2
    if noise_density_m_s2_sqrt_hz > 0.0 and rng is not None:
        n = rng.normal(0.0, noise_density_m_s2_sqrt_hz * math.sqrt(rate_hz), 3)
        ax, ay, az = ax + float(n[0]), ay + float(n[1]), az + float(n[2])
    lim = range_m_s2
    return (min(max(ax, -lim), lim), min(max(ay, -lim), lim), min(max(az, -lim), lim))
