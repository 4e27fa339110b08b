"""The oracle detectability of a generated recording's true effects (simvehicle/engines/oracle.py).

On one short generated flight with a flow rotation gain (the flow group's residuals are exactly
linear in the gain): the chi-square drop of a linear parameter is the closed-form quadratic in its
size; the evidence is nothing for an effect of zero size and negative for one the recording does
not hold; it is large for a large effect and grows with the effect's size. The pieces (the
chi-square tail -> z conversion, the Newey-West variance) against closed forms.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from simvehicle.engines import flightgen as fg
from simvehicle.engines import oracle as orc

GAIN = "flow_rotation_gain"


def gain_flight(folder: Path, gain: float, stem: str) -> fg.Generated:
    """30 s of sines and a step with a height change, moderate noise and turbulence, no loss; the
    same seed (so the same noise draws) whatever the gain."""
    spec = fg.draw_spec(5, ardupilot_share=0.0)
    segs = (fg.SetpointSegment(0.0, 12.0, "sine", (0.0, 0.0), (0.0, 0.0), (0.8, 0.6), 3.0, 0.0),
            fg.SetpointSegment(12.0, 22.0, "step", (0.0, 0.0), (0.8, -0.6)),
            fg.SetpointSegment(22.0, 1e4, "sine", (0.0, 0.0), (0.0, 0.0), (0.5, 0.8), 2.0, 1.0))
    flight = fg.FlightProfile(segs, (0.0, 10.0, 14.0, 1e4), (1.0, 1.0, 1.6, 1.6), 1.5)
    noise = fg.Noise(att_white_rad=math.radians(0.1), gyro_white_rad_s=0.003, turbulence_n=0.1, turbulence_tau_s=0.5,
                     range_noise_m=0.005)
    spec = dataclasses.replace(spec, duration_s=30.0, warmup_s=2.0, flight=flight, noise=noise, loss=fg.Loss(),
                               effects={GAIN: {"gain": gain}}, wind_from_start=False, wind_to_end=False)
    return fg.write_flight(spec, fg.simulate(spec), folder, stem)


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> dict[float, fg.Generated]:
    folder = tmp_path_factory.mktemp("oracle")
    return {g: gain_flight(folder, g, f"gain_{g:g}") for g in (1.0, 1.06, 1.12)}


def test_the_drop_of_a_linear_parameter_is_its_closed_form_quadratic(flights: dict[float, fg.Generated]) -> None:
    """With the residual r(theta) = r(0) - theta u (linear), drop(theta) = 2 theta u.r(0) - theta^2 |u|^2
    and signal(theta) = theta^2 |u|^2: signal(2 theta) = 4 signal(theta) and
    drop(2 theta) - 2 drop(theta) = -2 signal(theta), on one recording and one noise scale."""
    g = flights[1.12]
    og = orc.build(g.tlog, g.config, g.truth)
    grp, sel = og.groups["flow"], og.selectors["flow"]
    i = grp.params.index("gain")
    out = {}
    for theta in (0.05, 0.10):
        p = grp.nominal.copy()
        p[i] += theta
        out[theta] = orc.effect_evidence(sel, p, grp.nominal, 1)
    (d1, s1, *_), (d2, s2, *_) = out[0.05], out[0.10]
    assert s1 > 0
    assert s2 == pytest.approx(4.0 * s1, rel=1e-9)
    assert d2 - 2.0 * d1 == pytest.approx(-2.0 * s1, rel=1e-6)


def test_an_effect_of_zero_size_or_absent_has_no_evidence(flights: dict[float, fg.Generated]) -> None:
    g = flights[1.0]
    ev = orc.oracle(g.tlog, g.config, g.truth)[GAIN]  # the effect at zero size: it changes nothing
    assert ev.signal == 0.0 and ev.z == 0.0
    # the truth claimed to hold the gain of the other flight, on the flight without it: the residual at
    # the claim is the noise plus the claimed effect, so the drop is -signal up to the noise's
    # projection, whose standard deviation is 2 sqrt(V) = 2 sqrt(inflation x signal) (3 sd here)
    claim = {**g.truth, "effects": {GAIN: {"gain": 1.12}}}
    ev = orc.oracle(g.tlog, g.config, claim)[GAIN]
    assert ev.signal > 100.0
    assert ev.drop < 0.0 and ev.z == 0.0
    assert abs(ev.drop + ev.signal) <= 6.0 * math.sqrt(ev.inflation * ev.signal)


def test_the_evidence_is_large_for_a_large_effect_and_grows_with_its_size(
        flights: dict[float, fg.Generated]) -> None:
    big = {g: orc.oracle(flights[g].tlog, flights[g].config, flights[g].truth)[GAIN] for g in (1.06, 1.12)}
    for ev in big.values():
        # the drop's expectation is +signal, the same noise term as above (3 sd)
        assert abs(ev.drop - ev.signal) <= 6.0 * math.sqrt(ev.inflation * ev.signal)
        assert ev.k == 1 and ev.z == pytest.approx(math.sqrt(ev.drop / ev.inflation), rel=1e-9)
        # z of a one-parameter effect is sqrt(signal / inflation), (size) |u| / sqrt(V / signal), plus
        # noise of unit variance (3 sd)
        assert abs(ev.z - math.sqrt(ev.signal / ev.inflation)) <= 3.0
    assert big[1.12].z >= 10.0
    # twice the size: more evidence by more than the noise of both (3 sd of the difference). Not
    # twice the z: the two flights fly differently (the gain is in the loop), so |u| and the noise's
    # autocovariance differ between them (inflation 0.85 and 1.39; 1.28 and 0.91 under the flow
    # windows' start-velocity term tried in session 45, which this test's old "twice the z" failed)
    assert big[1.12].z - big[1.06].z >= 3.0 * math.sqrt(2.0)


def test_z_of_chi2_is_the_finders_conversion_and_goes_past_its_cap() -> None:
    # one degree of freedom: chi-square is a squared normal, so the two-sided z is sqrt(w)
    for w in (0.5, 9.0, 100.0, 1369.0, 1600.0, 1e5):
        assert orc.z_of_chi2(w, 1) == pytest.approx(math.sqrt(w), rel=1e-6)
    # two: the tail is exp(-w / 2); z = isf(exp(-w/2) / 2); z_min = 3 needs w = 11.83
    assert orc.z_of_chi2(11.829, 2) == pytest.approx(3.0, abs=1e-3)
    assert orc.z_of_chi2(-1.0, 1) == 0.0 and orc.z_of_chi2(0.0, 2) == 0.0


def test_the_newey_west_variance_against_closed_forms() -> None:
    rng = np.random.default_rng(1)
    n = 20000
    d = rng.normal(size=n)
    r = 1.7 * rng.normal(size=n)
    # no lags: gamma(0) |d|^2 exactly
    assert orc.hac_variance(d, r, 0) == pytest.approx(float(np.mean(r * r)) * float(d @ d), rel=1e-9)
    # differenced white noise (e_t - e_{t-1}: gamma(1) = -gamma(0) / 2) against a constant: the sum
    # telescopes, its long-run variance is 0; with Bartlett weights the estimate is gamma(0) / (L + 1)
    # per unit of |d|^2, against gamma(0) for white noise
    e = rng.normal(size=n + 1)
    md = np.diff(e)
    one = np.ones(n)
    lags = 50
    ratio = orc.hac_variance(one, md, lags) / (float(np.mean(md * md)) * n)
    assert ratio == pytest.approx(1.0 / (lags + 1), rel=0.2)
    # AR(1) with coefficient a: long-run variance / variance = (1 + a) / (1 - a) (= 3 for a = 0.5)
    a = 0.5
    x = np.zeros(n)
    w = rng.normal(size=n)
    for t in range(1, n):
        x[t] = a * x[t - 1] + w[t]
    ratio = orc.hac_variance(one, x, 50) / (float(np.mean(x * x)) * n)
    assert ratio == pytest.approx((1 + a) / (1 - a), rel=0.15)


def test_the_matrix_report_counts_hits_and_misses_by_oracle_band() -> None:
    path = Path(__file__).resolve().parents[1] / "scripts" / "generalisation_matrix.py"
    spec = importlib.util.spec_from_file_location("generalisation_matrix", path)
    assert spec is not None and spec.loader is not None
    gm = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gm)

    def rec(effect: str, outcome: str, reason: str, z: float, z_rival: float, rival: str = "") -> dict:
        return {"status": "ok", "truth_effects": {effect: {}},
                "score": {"effects": {effect: {"outcome": outcome, "reason": reason}},
                          "misses": [effect] if outcome == "miss" else [], "false": []},
                "oracle": {effect: {"z": z, "z_rival": z_rival, "rival": rival, "note": ""}}}

    results = [rec("range_offset", "miss", "not reported", 0.4, 0.4),
               rec("range_offset", "miss", "not reported", 12.0, 1.0, "flow_scale"),
               rec("range_offset", "hit", "", 7.0, 6.0, "flow_scale"),
               rec("flow_scale", "miss", "out of tolerance", 4.0, 4.0),
               {"status": "timeout", "truth_effects": {"flow_scale": {}}}]
    text = "\n".join(gm.oracle_section(results))
    # hits / true effects per band: < 3, 3-5, 5-10, >= 10, not computed
    assert "| range_offset | 0 / 1 | - | 1 / 1 | 0 / 1 | - |" in text
    # misses (not reported) per band, then those at z >= 5 with a rival z < 3
    assert "| range_offset | 2 | 1 (1) | - | - | 1 (1) | - | 1 |" in text
    assert "| flow_scale | 1 | - | 1 (0) | - | - | - | - |" in text
    assert "Of 3 misses, 1 have an oracle z < 3, 1 3-5, 0 5-10, 1 >= 10" in text
    assert gm.oracle_line(results).endswith("z < 3: 1, z 3-5: 1, z 5-10: 0, z >= 10: 1; "
                                            "at z >= 5 with a rival z < 3: 1")
    assert gm._oracle_cell(results[1]) == "range_offset 12.0 (1.0 vs flow_scale)"
    assert gm.oracle_section([{"status": "ok", "truth_effects": {}}]) == []  # no oracle, no section
    # right with the misses a recording cannot show excused: the z 0.4 miss and the hit (and the
    # z 4 miss when z < 5 is excused); a false finding is never excused, a timeout is not scored
    assert gm.right_if_excused(results, 3.0) == (2, 4)
    assert gm.right_if_excused(results, 5.0) == (3, 4)
    false_too = rec("range_offset", "miss", "not reported", 0.4, 0.4)
    false_too["score"]["false"] = ["flow_scale"]
    assert gm.right_if_excused([false_too], 3.0) == (0, 1)
    assert "2 / 4 recordings would be right (3 / 4 with z < 5)" in text
