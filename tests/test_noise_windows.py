"""Where a residual stands above its noise (``locate.excess_windows``) when the noise is not
Gaussian: sparse count errors, a noise that grows with the manoeuvre, an estimator's coloured
output (issue 12: nothing listed as unexplained that the recording's own noise explains), and a
misfit that must still be said. The noise sizes are the matrix's (a flow count error on 3.5 % of
frames, ArduPilot's attitude noise correlated over 0.9 s); the expected values are closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import load_config
from companion.diagnose.closed_loop.diagnosis import MISFIT_TIMES_NOISE, diagnose
from companion.diagnose.closed_loop.locate import (
    COLOURED_ALPHA,
    STRETCH_TIMES_NOISE,
    coloured_factor,
    excess_windows,
    typical_window_rms,
    white_noise,
    white_part,
    window_rms,
)
from companion.diagnose.closed_loop.select import robust_std
from companion.recordings.load import load_recording

FRAME_S = 0.02


def _times(duration_s: float) -> np.ndarray:
    return np.arange(int(round(duration_s / FRAME_S))) * FRAME_S


def _count_errors(t: np.ndarray, rng: np.random.Generator, share: float = 0.035) -> np.ndarray:
    """A flow residual in counts as gen_0098's: 0.05 counts of Gaussian noise (the rounding is
    carried to the next frame, not lost) and a +-1 count error on ``share`` of the frames. Its rms,
    sqrt(0.05^2 + share) = 0.19 counts, is nearly four times its MAD."""
    return 0.05 * rng.standard_normal(len(t)) + np.where(rng.random(len(t)) < share,
                                                         rng.choice([-1.0, 1.0], len(t)), 0.0)


def test_the_white_part_of_a_differenced_noise_is_its_rms():
    """A rate taken from two noisy attitudes, (n[i+1] - n[i]) / dt, is negatively correlated from
    one row to the next: its differences one row apart read sqrt(3/2) of its rms, two rows apart
    exactly its rms, sqrt(2) sigma / dt (closed form)."""
    rng = np.random.default_rng(0)
    sigma = 1e-3
    n = sigma * rng.standard_normal(40001)
    t = _times(40000 * FRAME_S)
    r = np.diff(n) / FRAME_S
    assert white_noise(t, r) == pytest.approx(math.sqrt(2.0) * sigma / FRAME_S, rel=0.02)
    # a gap (lost rows) is not differenced across
    keep = (t < 100.0) | (t > 110.0)
    td, d = white_part(t[keep], r[keep])
    assert not np.any((td > 100.0) & (td < 110.0))
    assert len(d) == np.count_nonzero(keep) - 2 - 2


def test_sparse_count_errors_are_noise_not_a_misfit():
    """Count errors on 3.5 % of frames make the rms 3.7 x the MAD: against the MAD alone every
    window stood above twice the noise (gen_0098: "the model does not fit flow_x ... 4 x its
    noise" over the whole flight); against the white part none does, nor at 1.4 x."""
    rng = np.random.default_rng(1)
    t = _times(200.0)
    r = _count_errors(t, rng)
    sigma = robust_std(r)
    assert math.sqrt(np.mean(r ** 2)) > 3.0 * sigma
    assert excess_windows(t, r, sigma, factor=1.4) == []
    # every window stands above twice the MAD
    v = window_rms(t, r, 5.0, 2.5)[2]
    assert np.all(v > 2.0 * sigma)


def test_a_noise_that_grows_with_the_manoeuvre_is_judged_where_it_is():
    """White noise four times larger for 20 s (the reconstruction of a rate that kinks between
    samples grows with the manoeuvre): the window's own white part holds it."""
    rng = np.random.default_rng(2)
    t = _times(120.0)
    loud = (t >= 60.0) & (t < 80.0)
    r = rng.standard_normal(len(t)) * np.where(loud, 4.0, 1.0)
    assert excess_windows(t, r, robust_std(r)) == []
    assert window_rms(t, r, 5.0, 2.5)[2].max() > 3.0 * robust_std(r)  # the robust scale alone: 3 x


def test_a_smooth_misfit_in_count_errors_is_still_said_where_it_acts():
    """A 0.5 Hz misfit of 0.6 counts' amplitude from 40 to 60 s on the same count errors: the
    misfit's rms is 0.42 counts, and over two frames it changes by 0.04 rms, so its windows read
    sqrt(0.19^2 + 0.42^2) = 0.47 against a white part of 0.20 (2.4 x), and nothing else stands at
    twice the noise; the interval says the noise it was judged against."""
    rng = np.random.default_rng(3)
    t = _times(120.0)
    on = (t >= 40.0) & (t < 60.0)
    r = _count_errors(t, rng) + np.where(on, 0.6 * np.sin(2 * np.pi * 0.5 * t), 0.0)
    [iv] = excess_windows(t, r, robust_std(r))
    assert 35.0 <= iv.start_s <= 40.0 and 57.5 <= iv.end_s <= 62.5
    assert iv.noise == pytest.approx(white_noise(t[~on], r[~on]), rel=0.15)
    assert iv.rms / iv.noise == pytest.approx(0.47 / 0.20, rel=0.15)


def test_a_step_in_count_errors_is_said_at_three_times_the_noise():
    """A step of one count from 40 to 60 s (a force that comes and goes, a sensor offset): inside,
    its windows read sqrt(1 + 0.19^2) = 1.02 counts against a white part of 0.19, over 3 x (the
    headline's "does not fit"); it changes over two rows only at its ends."""
    rng = np.random.default_rng(4)
    t = _times(120.0)
    on = (t >= 40.0) & (t < 60.0)
    r = _count_errors(t, rng) + np.where(on, 1.0, 0.0)
    [iv] = excess_windows(t, r, robust_std(r), factor=3.0)
    assert 37.5 <= iv.start_s <= 40.0 and 57.5 <= iv.end_s <= 62.5
    assert iv.rms / iv.noise > 3.0


def _gauss_markov(t: np.ndarray, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """Gauss-Markov noise of unit stationary variance, correlated over ``tau_s``, at the times ``t``
    (a frame apart), started at zero."""
    a = math.exp(-FRAME_S / tau_s)
    w = rng.standard_normal(len(t)) * math.sqrt(1 - a * a)
    r = np.zeros(len(t))
    for i in range(1, len(t)):
        r[i] = a * r[i - 1] + w[i]
    return r


def test_a_coloured_noises_highest_window_is_judged_by_its_own_scatter():
    """Gauss-Markov noise correlated over 0.9 s over 200 s, 40 draws: a 5 s window holds a few
    independent values, and the highest of the flight's 80 windows stands over twice the typical
    one on 23 % of 200 simulated flights, 7 of these 40 (it did on four clean flights of the
    generalisation matrix, each then listing "a local disturbance" at 2.0-2.7 x). Judged against
    the windows' own scatter (``coloured_factor``: chance ``COLOURED_ALPHA`` = 1 % per flight), at most one of the
    40 draws lists a window (binomial, 40 x 1 %: the chance of two or more is 6 %; the robust
    scatter is an estimate, so allow for one). A 6 s stretch at four times the noise's rms stands
    above it on every draw."""
    t = _times(200.0)
    twice, listed, found = 0, 0, 0
    for seed in range(40):
        r = _gauss_markov(t, 0.9, np.random.default_rng([seed, 9]))
        typical = typical_window_rms(t, r)
        twice += bool(excess_windows(t, r, typical, factor=STRETCH_TIMES_NOISE))
        factor = max(STRETCH_TIMES_NOISE, coloured_factor(t, r))
        listed += bool(excess_windows(t, r, typical, factor=factor))
        bump = r + np.where((t >= 100.0) & (t < 106.0), 4.0 * math.sqrt(2.0), 0.0) * np.sin(2 * np.pi * t)
        said = excess_windows(t, bump, typical_window_rms(t, bump),
                              factor=max(STRETCH_TIMES_NOISE, coloured_factor(t, bump)))
        found += any(iv.start_s < 106.0 and iv.end_s > 100.0 for iv in said)
    assert COLOURED_ALPHA == 0.01 and STRETCH_TIMES_NOISE == 2.0
    assert twice >= 5  # 7 here (23 % of 200 simulated flights): the fixed factor lists the noise itself
    assert listed <= 1
    assert found == 40


def test_coloured_noise_is_judged_against_its_typical_window():
    """Gauss-Markov noise correlated over 0.9 s (the matrix's EKF-like attitude noise) over 200 s:
    a 5 s window holds about 5 correlation times, and its rms ranges widely. Its white part is a
    fifth of its rms (it is smooth), so the white part cannot be its noise; its typical window is
    its rms, and no window stands at 3 x that. (On gen_0240, whose attitude residual's rms is
    1.7 x its MAD, that made "the model does not fit attitude_roll ... 4 x its noise": the
    regression test is below.)"""
    t = _times(200.0)
    a = math.exp(-FRAME_S / 0.9)
    r = _gauss_markov(t, 0.9, np.random.default_rng(5))
    sigma = robust_std(r)
    # closed form: two rows apart, a Gauss-Markov noise of unit variance differs by
    # 2 (1 - a^2) in variance
    assert white_noise(t, r) == pytest.approx(math.sqrt(1 - a * a) * math.sqrt(np.mean(r ** 2)), rel=0.1)
    assert white_noise(t, r) < 0.25 * sigma
    v = window_rms(t, r, 5.0, 2.5)[2]
    assert v.max() > 1.5 * v.min()
    typical = typical_window_rms(t, r)
    assert typical == pytest.approx(math.sqrt(np.mean(r ** 2)), rel=0.25)
    assert excess_windows(t, r, max(sigma, typical), factor=3.0) == []


# ---------------------------------------------------------------------------------------------
# the matrix's clean flights, regenerated from their seeds (simvehicle.engines.flightgen)


@pytest.mark.parametrize("seed", [98, 17, 260, 240])
def test_a_clean_flights_own_noise_is_not_called_a_misfit(tmp_path, seed):
    """Four clean flights of the generalisation matrix whose headline said "the model does not fit":
    98 (no noise but ArduPilot's rates and flow count errors on 3.5 % of frames: gyro_x 15 x and
    flow_x 4 x "its noise"), 17 (gyro_x 13 x: a rate that kinks between the gyro's samples), 260
    (flow count errors on 3 % of frames: flow_x 8 x), 240 (attitude noise correlated over 0.9 s:
    attitude_roll 4 x). Each is said to fit, and nothing is listed as unexplained (240 listed six
    attitude windows at 2.0-2.7 x its typical window until those were judged by their own scatter,
    ``locate.coloured_factor``)."""
    from simvehicle.engines import flightgen as fg

    spec = fg.draw_spec(seed)
    assert not spec.effects
    fg.write_flight(spec, fg.simulate(spec), tmp_path, "clean")
    rep = diagnose(load_recording(tmp_path / "clean.tlog"), load_config(tmp_path / "clean.toml")).report
    assert rep.headline.startswith("the recording fits the nominal model"), rep.headline
    assert all(u.times_noise < 3.0 for u in rep.unexplained)
    assert rep.unexplained == []


@pytest.mark.parametrize("seed", [18, 44, 99, 88, 124])
def test_what_the_loop_answers_is_not_listed_as_structure(tmp_path, seed):
    """Three clean flights of the generalisation matrix (104, 41 and 47 s; turbulence of 0.31,
    0.07 and 0.27 N, flow count errors on 2-3 % of frames: both moves the loop answers) whose force
    residual the sparse fit put down to that answer at 7dbdef3: "+0.169 N per sign(velocity)" (a
    friction pushing along the motion), "+21.1 N per rad of tilt", "+0.124 N per sign(velocity)".
    The loop's terms are their setpoint-driven part (``diagnosis._setpoint_driven``), and no force
    channel lists an entry. Two more at d48ae65: 88 (28 s, 25 force windows, too few for all four
    lags, so no instruments at all: "-4.66 N per rad of tilt"; now the two lags its windows carry)
    and 124 (a hold: its one step comes before the recording; "+16.5 N per rad of tilt" and "+3.64
    N per m/s of velocity" under 0.38 N of turbulence; now the loop's terms are the hold's constant,
    and dropped)."""
    from simvehicle.engines import flightgen as fg

    spec = fg.draw_spec(seed)
    assert not spec.effects
    fg.write_flight(spec, fg.simulate(spec), tmp_path, "clean")
    rep = diagnose(load_recording(tmp_path / "clean.tlog"), load_config(tmp_path / "clean.toml")).report
    assert rep.significant() == []
    assert [u for u in rep.unexplained if u.channel.startswith("force")] == []


def test_a_gyro_scale_error_on_a_clean_flight_is_still_said(tmp_path, monkeypatch):
    """The same kind of flight (seed 252, clean) with its gyro read 5 % large, which no effect of
    the vocabulary is: the headline says the gyro does not fit, and the gyro's unexplained entries
    put it down to a gyro scale-factor error of +0.05 (within 0.01)."""
    from companion.diagnose.closed_loop import diagnosis as dmod
    from simvehicle.engines import flightgen as fg

    spec = fg.draw_spec(252)
    assert not spec.effects
    fg.write_flight(spec, fg.simulate(spec), tmp_path, "scaled")
    extract = dmod.extract

    def scaled(rec, cfg, profile=None):  # type: ignore[no-untyped-def]
        data = extract(rec, cfg, profile)
        for name in ("gyro_x_rad_s", "gyro_y_rad_s", "gyro_angle_x_rad", "gyro_angle_y_rad",
                     "gyro_fine_x_rad_s", "gyro_fine_y_rad_s"):
            if getattr(data, name) is not None:
                setattr(data, name, 1.05 * getattr(data, name))
        return data

    monkeypatch.setattr(dmod, "extract", scaled)
    rep = diagnose(load_recording(tmp_path / "scaled.tlog"), load_config(tmp_path / "scaled.toml")).report
    assert "does not fit gyro_" in rep.headline, rep.headline
    named = [float(u.best_term.split()[0]) for u in rep.unexplained
             if u.channel.startswith("gyro_") and u.best_term and "gyro scale-factor error" in u.best_term]
    assert named and all(abs(k - 0.05) <= 0.01 for k in named)


def test_a_misfit_in_every_window_of_a_coloured_channel_is_not_its_noise():
    """An attitude residual that is 0.98 x the tracking error over the whole flight (a lossy
    ground-station log of ArduCopter SITL flight C0, its attitude model lost with its commands)
    plus noise correlated over 0.9 s of a tenth its size. The tracking error is the loop's answer to
    a command step every 2.5 s (rising for 0.15 s, then settling), so the misfit is in every window and the MAD,
    taken mostly between the steps, is far under it. Its typical window is the misfit itself, so
    against it nothing stands out; the sparse fit names the term, and the typical window of what
    it leaves is the noise's (``diagnosis._stretch_noise``), against which the misfit stands
    above 3 x (the headline's "does not fit")."""
    from types import SimpleNamespace

    from companion.diagnose.closed_loop.diagnosis import _stretch_noise
    from companion.diagnose.closed_loop.sparse import Term, sparse_fit

    rng = np.random.default_rng(6)
    t = _times(200.0)
    steps = np.arange(1.0, 200.0, 2.5)
    k = np.searchsorted(steps, t, side="right") - 1
    since = np.where(k >= 0, t - steps[np.maximum(k, 0)], 0.0)
    amp = rng.uniform(-0.1, 0.1, len(steps))[np.maximum(k, 0)]
    error = np.where(k >= 0, amp * (since / 0.15) * np.exp(1.0 - since / 0.15), 0.0)
    a = math.exp(-FRAME_S / 0.9)
    w = rng.standard_normal(len(t)) * math.sqrt(1 - a * a) * 0.1 * math.sqrt(np.mean(error ** 2))
    noise = np.zeros(len(t))
    for i in range(1, len(t)):
        noise[i] = a * noise[i - 1] + w[i]
    r = 0.98 * error + noise
    folds = (t // 5.0).astype(int) % 8
    group = SimpleNamespace(row_times=[t], channels=("attitude_roll",), coloured=(True,), floors=(1e-4,))
    res = SimpleNamespace(group=group, r_final=[r], selector=SimpleNamespace(sigma=np.array([robust_std(r)])),
                          sparse={})
    assert robust_std(r) < 0.5 * typical_window_rms(t, r)
    alone = _stretch_noise(res, 0)  # the typical window of the residual itself
    assert alone == pytest.approx(typical_window_rms(t, r))
    assert all(iv.rms / iv.noise < 3.0 for iv in excess_windows(t, r, alone))
    res.sparse["attitude_roll"] = sparse_fit(r, [Term("tracking error", "", "rad", error)], folds, 8)
    left = _stretch_noise(res, 0)
    assert left == pytest.approx(max(typical_window_rms(t, noise), robust_std(r), white_noise(t, r)), rel=0.2)
    found = excess_windows(t, r, left)
    assert found and max(iv.rms / iv.noise for iv in found) > MISFIT_TIMES_NOISE  # 5.8 here


@pytest.mark.parametrize(("channel", "rms", "noise", "said"), [
    ("attitude_roll", 0.55e-3, 0.1e-3, False),  # seed 15 without noise or effect, 15 % lost: 6 x, 0.55 mrad
    ("attitude_roll", 5e-3, 1e-3, True),
    ("gyro_x", 1.5e-3, 0.2e-3, False),
    ("gyro_x", 20e-3, 2e-3, True),  # a 5 % gyro scale error at 0.4 rad/s
    ("flow_y", 0.3e-3, 0.05e-3, False),
    ("force_x", 0.05, 0.01, False),
    ("force_x", 0.4, 0.1, True),
])
def test_the_headline_says_does_not_fit_only_for_a_misfit_that_matters(channel, rms, noise, said):
    """A stretch over 3 x its noise is called a misfit in the headline only when its rms passes the
    channel's floor (``sizes.misfit_floor``); under it the headline says the recording fits to
    within what matters, and gives the stretch, its size and the floor."""
    from companion.diagnose.closed_loop.diagnosis import headline
    from companion.diagnose.closed_loop.sizes import misfit_floor
    from companion.diagnose.report import Report, Unexplained

    rep = Report("synthetic", unexplained=[Unexplained(channel, 70.0, 77.5, rms, None, noise)])
    text = headline(rep)
    assert (f"does not fit {channel} from 70.0 to 77.5 s" in text) is said, text
    if not said:
        floor, unit = misfit_floor(channel)
        assert text.startswith("the recording fits the nominal model to within what matters"), text
        assert f"{rms:.2g} {unit} rms, under the {floor:g} {unit}" in text, text
    # under 3 x its noise nothing is said, whatever its size
    rep = Report("synthetic", unexplained=[Unexplained(channel, 70.0, 77.5, rms, None, rms / 2.9)])
    assert headline(rep).startswith("the recording fits the nominal model within its noise")
