"""The flow group's rotation and its anchor (issue 12): the gyro's integral is exact enough not to
read as a rotation gain, a gyro lag is undone exactly, and the regressors' anchor reproduces the
best source's residual at the anchor, whatever the geometry there."""

from __future__ import annotations

import numpy as np
import pytest

from companion.diagnose.closed_loop.channels import FlightData, gyro_spline
from companion.diagnose.closed_loop.flowmodel import IDX, NOMINAL, FlowProblem
from companion.diagnose.closed_loop.groups import regressor_scene_angle, rotation_angles


def _rotation_gain_error(angle: np.ndarray, truth: np.ndarray) -> float:
    """Least-squares gain of ``angle`` against ``truth`` (both zero-mean over the span), minus 1."""
    a, b = angle - angle.mean(), truth - truth.mean()
    return float(a @ b / (b @ b)) - 1.0


def test_the_gyro_integral_keeps_a_fast_rotation_at_its_size():
    """A 3 Hz body rate sampled at 50 Hz, 3.3 ms before each flow frame: the angle over the frames
    from the spline through the samples at their own times is within 0.05 % of the truth; the
    trapezoid of the rate linearly interpolated onto the frames (what the finder did before) is
    1 % small, the size of a rotation-gain or flow-scale finding."""
    w = 2 * np.pi * 3.0
    t_frames = np.arange(500) * 0.02
    t_gyro = t_frames - 0.0033
    rate = np.cos(w * t_gyro)
    truth = np.sin(w * t_frames) / w
    ang, val = gyro_spline(t_frames[5:-5], t_gyro, rate, 0.6)
    assert abs(_rotation_gain_error(ang, truth[5:-5])) < 5e-4
    np.testing.assert_allclose(val, np.cos(w * t_frames[5:-5]), atol=2e-3)
    g = np.interp(t_frames, t_gyro, rate)
    trapz = np.concatenate([[0.0], np.cumsum(0.5 * (g[1:] + g[:-1]) * 0.02)])
    assert _rotation_gain_error(trapz[5:-5], truth[5:-5]) < -0.008


def test_a_gyro_run_across_a_long_gap_is_not_bridged():
    t = np.r_[np.arange(100) * 0.02, 3.0 + np.arange(100) * 0.02]
    ang, val = gyro_spline(np.array([1.0, 2.5, 3.5]), t, np.ones_like(t), 0.6)
    assert np.isfinite(ang[[0, 2]]).all() and np.isnan(ang[1]) and np.isnan(val[1])


def _flight(t: np.ndarray, pitch: np.ndarray, roll: np.ndarray, gyro_y: np.ndarray, gyro_x: np.ndarray,
            **extra: np.ndarray) -> FlightData:
    n = len(t)
    z = np.zeros(n)
    return FlightData(path="synthetic", profile="paper", profile_reason="test", frame_s=0.02, command_source="test",
                      t_s=t, dt_s=np.r_[0.02, np.diff(t)], seg=np.zeros(n, dtype=int), dphi_x_rad=z, dphi_y_rad=z,
                      gyro_x_rad_s=gyro_x, gyro_y_rad_s=gyro_y, range_m=np.ones(n), roll_rad=roll, pitch_rad=pitch,
                      yaw_rad=z, roll_cmd_rad=z, pitch_cmd_rad=z, vx_set_m_s=z * np.nan, vy_set_m_s=z * np.nan,
                      truth_vx_m_s=z * np.nan, truth_vy_m_s=z * np.nan, **extra)


def test_a_lagging_gyro_is_undone_exactly():
    """A first-order low-pass gyro (tau 45 ms) of a rotation with 2-4 Hz content: the fused angle
    with the lag undone (integral of g plus tau (g - g0)) follows the attitude above the crossover
    to 0.1 % in gain."""
    tau, T = 0.045, 0.02
    t_fine = np.arange(0, 20, 1e-4)
    q = 0.3 * np.sin(2 * np.pi * 2.0 * t_fine) + 0.2 * np.sin(2 * np.pi * 3.7 * t_fine + 1.0)
    theta = np.concatenate([[0.0], np.cumsum(0.5 * (q[1:] + q[:-1]) * 1e-4)])
    g = np.zeros_like(q)  # tau g' = q - g
    for k in range(1, len(q)):
        g[k] = g[k - 1] + 1e-4 * (0.5 * (q[k] + q[k - 1]) - g[k - 1]) / tau
    k = np.arange(0, len(t_fine), int(round(T / 1e-4)))
    t = t_fine[k]
    ang, val = gyro_spline(t, t, g[k], 0.6)
    data = _flight(t, theta[k], theta[k], g[k], g[k], gyro_angle_x_rad=ang, gyro_angle_y_rad=ang,
                   gyro_fine_x_rad_s=val, gyro_fine_y_rad_s=val)
    pitch, _roll = rotation_angles(data, gyro_lag_s=tau, crossover_hz=0.1)  # the gyro above 0.1 Hz
    sl = slice(200, -200)
    assert abs(_rotation_gain_error(pitch[sl], theta[k][sl])) < 1e-3
    assert np.sqrt(np.mean((pitch[sl] - theta[k][sl]) ** 2)) < 2e-4


@pytest.mark.parametrize("anchor", [{}, {"yaw": 0.2, "scale_x": 1.2, "scale_y": 0.9, "delay": 0.01, "offset": 0.05}])
def test_the_anchor_holds_the_best_sources_residual_at_the_anchor(anchor):
    """r(p) = r_best(p_a) + [r_reg(p) - r_reg(p_a)]: at p = p_a the anchored problem's residuals are
    the best source's, for the nominal geometry and for a far one."""
    rng = np.random.default_rng(5)
    n = 3000
    t = np.arange(n) * 0.02
    pitch = 0.05 * np.sin(2 * np.pi * 0.4 * t) + 0.002 * rng.standard_normal(n)
    roll = 0.04 * np.sin(2 * np.pi * 0.3 * t + 1.0) + 0.002 * rng.standard_normal(n)
    dphi = 1e-3 * rng.standard_normal((2, n))
    data = _flight(t, pitch, roll, np.gradient(pitch, t), np.gradient(roll, t))
    data.dphi_x_rad, data.dphi_y_rad = dphi[0], dphi[1]
    kw = dict(mass_kg=1.5, gravity_m_s2=9.81)
    best = FlowProblem(data, **kw)
    rot = (np.convolve(pitch, np.ones(5) / 5, "same"), np.convolve(roll, np.ones(5) / 5, "same"))
    p_a = NOMINAL.copy()
    for key, v in anchor.items():
        p_a[IDX[key]] = v
    reg = FlowProblem(data, rotation_angles=rot, scene_angle=regressor_scene_angle(best, rot, p_a), **kw)
    reg.anchor(best, p_a)
    np.testing.assert_allclose(reg.flow_residual(p_a), best.flow_residual(p_a), atol=1e-12)
    np.testing.assert_allclose(reg.force_residual(p_a), best.force_residual(p_a), atol=1e-9)
    # away from the anchor the residual moves with the regressors' source
    q = p_a.copy()
    q[IDX["scale_x"]] *= 1.05
    assert not np.allclose(reg.flow_residual(q), best.flow_residual(p_a))


# ---------------------------------------------------------------------------------------------
# the held-out test (Selector.heldout_z)

#: (start s, amplitude) of six 2 s manoeuvres of uneven size in a 100 s flight, hovering between
BURSTS = ((6.0, 6.0), (21.0, 1.0), (36.0, 4.0), (51.0, 1.0), (66.0, 5.0), (81.0, 2.0))


def _burst_selector(seed: int, k_true: float):
    """One channel, one linear effect whose regressor is non-zero only in the manoeuvres (what a
    scale or a lever arm looks like between hovers), unit white noise."""
    from companion.diagnose.closed_loop.select import Candidate, Group, Selector, Settings

    rng = np.random.default_rng(seed)
    t = np.arange(5000) * 0.02
    x = np.zeros_like(t)
    for t0, a in BURSTS:
        on = (t >= t0) & (t < t0 + 2.0)
        x[on] = a * np.sin(2 * np.pi * 1.5 * (t[on] - t0))
    y = k_true * x + rng.standard_normal(len(t))
    g = Group(name="burst", params=("k",), nominal=np.zeros(1), steps=np.array([1e-3]), lower=np.array([-10.0]),
              upper=np.array([10.0]), channels=("c",), units=("1",), floors=(1e-3,),
              residuals=lambda p: [y - p[0] * x], row_times=[t], candidates=[Candidate("effect", ("k",))],
              linear=("k",))
    return Selector(g, Settings(two_starts=False), 0.0)


def _held_out(seed: int, k_true: float) -> tuple[float, float]:
    """(paired t of the block gains, held-out z) of the effect against none."""
    sel = _burst_selector(seed, k_true)
    with_, without = sel.score_exact(["effect"]), sel.score_exact([])
    per, have = sel._block_gain(with_, without)
    diff = per[have]
    return float(diff.mean() / (diff.std(ddof=1) / np.sqrt(len(diff)))), sel.heldout_z(with_, without)[0]


def test_an_effect_seen_only_in_a_few_manoeuvres_passes_the_held_out_test():
    """Its held-out gain sits in 6 of 20 blocks, unevenly: the paired t of the block gains counts
    that spread as noise and never reaches 2; the held-out z against the noise's own variance does
    in most flights."""
    runs = [_held_out(seed, 0.15) for seed in range(10)]
    assert max(t for t, _z in runs) < 2.0, runs
    assert sum(z >= 2.0 for _t, z in runs) >= 6, runs


def test_noise_alone_does_not_pass_the_held_out_test():
    zs = [_held_out(1000 + seed, 0.0)[1] for seed in range(40)]
    assert max(zs) < 2.0, zs
