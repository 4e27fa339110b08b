"""The sensor-only diagnosis as a mismatch report (``companion.diagnose.report.Report``, ``mode =
"sensor"``): one finding per effect, each saying which constraint its numbers come from, a
parameter the data cannot pin down reported as NaN with the reason."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config
from companion.diagnose.advice import actions, recorded_parameters
from companion.diagnose.report import Finding, Fit, Report, Unexplained, Window
from companion.diagnose.sensor.band import RotationBandFit, rotation_content
from companion.diagnose.sensor.diagnosis import SensorDiagnosis
from companion.diagnose.sensor.legs import pattern_match
from companion.diagnose.sensor.numerics import runs
from companion.diagnose.sensor.settings import QUANT_RMS_COUNTS, SensorDiagnosisSettings
from companion.diagnose.sensor.timing import range_finding, timing_findings
from companion.recordings.load import Recording


def build_report(rec: Recording, cfg: Config, d: SensorDiagnosis, st: SensorDiagnosisSettings) -> Report:
    s, band = d.series, d.band
    rep = Report(recording=Path(rec.path).name, mode="sensor")
    q = cfg.flow_sensor.q_rad_per_count
    rep.notes.append(f"sensor-only diagnosis against the paper's flow model (eq. 9-15), Q = {q:.6g} rad/count "
                     f"from {Path(cfg.source).name}; flow rows read every {1e3 * s.read_period_s:g} ms; "
                     f"profile {s.profile}")
    rep.notes.extend(f"recording: {n}" for n in rec.notes)
    rep.findings.extend(timing_findings(s, d.timing))
    rep.findings.append(range_finding(s, st))
    rep.findings.append(_scale_finding(d, st, q))
    rep.findings.append(_bias_finding(d, st))
    rep.findings.append(_delay_finding(d, st))
    rep.findings.append(_yaw_finding(d, st))
    rep.notes.append(_rotation_note(band, st))
    if band.fitted:
        rep.baseline_rms["flow_x_band_counts"] = float(band.baseline_rms_[0])
        rep.baseline_rms["flow_y_band_counts"] = float(band.baseline_rms_[1])
        rep.unexplained.extend(_band_unexplained(band))
    for f in rep.findings:
        if not f.significant and f.effect in ("flow_scale", "gyro_bias", "flow_delay", "flow_yaw_misalignment") \
                and not any(np.isfinite(v) for v in f.parameters.values()):
            rep.notes.append(f"{f.effect}: {f.explanation}")
    if d.scale_fit is not None and d.legs:
        errs = [lg.length(1.0, 1.0) - d.motion.leg_m for lg in d.legs] if d.motion else []
        rep.baseline_rms["leg_length_m"] = float(np.sqrt(np.mean(np.square(errs)))) if errs else float("nan")
        for lg in d.legs:
            e = lg.length(d.scale[0], d.scale[1]) - (d.motion.leg_m if d.motion else 0.0)
            if abs(e) > 2 * st.leg_tolerance_rel * (d.motion.leg_m if d.motion else 0.0):
                rep.unexplained.append(Unexplained("leg_length_m", lg.start_s, lg.end_s, abs(e),
                                                   best_term="leg length off the documented one by more than 2 sigma "
                                                             "of the hand tolerance"))
    if np.isfinite(d.bias.before):
        rep.baseline_rms["still_scene_angle_rad"] = d.bias.before
    rep.actions = actions(rep, profile=s.profile, q_rad_per_count=q, current=recorded_parameters(rec))
    return rep


def _rotation_note(band: RotationBandFit, st: SensorDiagnosisSettings) -> str:
    head = f"rotation band {st.band_low_hz:g}-{st.band_high_hz:g} Hz: {rotation_content(band)}"
    if not band.fitted:
        return f"{head}; not fitted: {band.reason_}"
    sr, ssr = band.scale_from_rotation()
    ok = band.rotation_scale_identifiable()
    words = [f"{'xy'[a]} {sr[a]:.2f} +- {ssr[a]:.2f}" + ("" if ok[a] else " (not identifiable)") for a in range(2)]
    return (f"{head}; delay {1e3 * band.delay_:.0f} +- {1e3 * band.delay_sigma_:.0f} ms; rotation-only scale "
            f"{', '.join(words)} (R^2 {band.r2_[0]:.2f} / {band.r2_[1]:.2f}; identifiable only if within "
            f"{100 * st.max_rel_uncertainty:.0f} % and equal in both halves of the band)")


def _fmt_pm(v: float, s: float, nd: int = 2) -> str:
    if not np.isfinite(v):
        return "n/a"
    return f"{v:.{nd}f} +- {s:.{nd}f}" if np.isfinite(s) else f"{v:.{nd}f}"


def _scale_finding(d: SensorDiagnosis, st: SensorDiagnosisSettings, q: float) -> Finding:
    band = d.band
    sr, ssr = band.scale_from_rotation()
    rot_ok = [bool(v) for v in band.rotation_scale_identifiable()]
    with np.errstate(divide="ignore", invalid="ignore"):
        s_sub, ss_sub = 1.0 / band.subband_gain_, band.subband_gain_sigma_ / band.subband_gain_**2
    ev: dict[str, Any] = {
        "constraint": "displacement: legs of documented length (Fig. 6 style)",
        "q_nominal_rad_per_count": q,
        "rotation_band_scale": {"x": sr[0], "y": sr[1], "sigma_x": ssr[0], "sigma_y": ssr[1],
                                "identifiable_x": rot_ok[0], "identifiable_y": rot_ok[1],
                                "r2_x": band.r2_[0], "r2_y": band.r2_[1],
                                "subbands_hz": [list(b) for b in band.subband_hz_],
                                "subband_x": list(s_sub[:, 0]), "subband_sigma_x": list(ss_sub[:, 0]),
                                "subband_y": list(s_sub[:, 1]), "subband_sigma_y": list(ss_sub[:, 1]),
                                "note": "rotation-only scale: identifiable only if precise and equal in both "
                                        "halves of the band; never used for the parameters"},
    }
    if d.motion is None or d.scale_fit is None:
        if band.fitted:
            rot = (f"the rotation band alone gives x {_fmt_pm(sr[0], ssr[0])}, y {_fmt_pm(sr[1], ssr[1])}, "
                   f"{'consistent' if all(rot_ok) else 'not consistent'} across the band")
        else:
            rot = f"the rotation band is unusable: {band.reason_}; {rotation_content(band)}"
        return Finding(
            effect="flow_scale", significant=False, parameters={"scale_x": float("nan"), "scale_y": float("nan")},
            uncertainty={"scale_x": float("nan"), "scale_y": float("nan")},
            explanation=(f"Not identifiable: there is no documented motion to measure the counts against, and {rot}."),
            fit=None, evidence=ev)
    f = d.scale_fit
    m = d.motion
    pm, seq = pattern_match(d.legs, m)
    ev.update({
        "reference": ("documented" if m.documented else "assumed") + f": {m.source}",
        "leg_m": m.leg_m, "leg_tolerance_rel": st.leg_tolerance_rel, "range_scale_rel": st.range_scale_rel,
        "legs_detected": seq, "pattern_match": pm, "chi2_reduced": f.chi2_red_,
        "scale_rad_per_count": {"x": f.scale_[0] * q, "y": f.scale_[1] * q},
        "legs": [{"leg": lg.name, "start_s": lg.start_s, "end_s": lg.end_s,
                  "nominal_m": lg.length(1.0, 1.0), "fitted_m": lg.length(d.scale[0], d.scale[1]),
                  "rotation_part_m": lg.direction * lg.d_rotation, "cross_m": lg.cross_m} for lg in d.legs],
    })
    params = {"scale_x": float(f.scale_[0]) if f.identifiable_[0] else float("nan"),
              "scale_y": float(f.scale_[1]) if f.identifiable_[1] else float("nan")}
    unc = {"scale_x": float(f.sigma_[0]) if f.identifiable_[0] else float("nan"),
           "scale_y": float(f.sigma_[1]) if f.identifiable_[1] else float("nan")}
    fit = Fit(f.heldout_before_, f.heldout_after_) if np.isfinite(f.heldout_after_) else None
    away = any(f.identifiable_[a] and abs(f.scale_[a] - 1.0) > 2 * f.sigma_[a] for a in range(2))
    earned = bool(fit is not None and fit.improvement_pct >= st.min_improvement_pct)
    sig = earned and away
    parts = [f"{'xy'[a]} {f.scale_[a]:.2f} +- {f.sigma_[a]:.2f}" for a in range(2) if f.identifiable_[a]]
    bigger = all(f.scale_[a] > 1.0 for a in range(2) if f.identifiable_[a])
    expl = (f"Each count is a {'larger' if bigger else 'different'} angle than the paper's Q (true rad per count = "
            f"scale x Q: {', '.join(parts) or 'none identifiable'}), measured by making the rotation-compensated "
            f"running sum of flow times range span the {100 * m.leg_m:.0f} cm legs ({len(d.legs)} found)")
    if f.reasons_:
        expl += "; " + "; ".join(f.reasons_)
    if fit is not None and earned and not away:
        expl += (f"; the held-out leg error drops ({100 * fit.heldout_rms_before:.1f} -> "
                 f"{100 * fit.heldout_rms_after:.1f} cm) but the scale is within 2 sigma of the paper's Q")
    expl += "."
    where = [Window("flow_x" if lg.axis == 0 else "flow_y", lg.start_s, lg.end_s) for lg in d.legs]
    return Finding(effect="flow_scale", significant=sig, parameters=params, uncertainty=unc, explanation=expl,
                   where=where, fit=fit, evidence=ev)


def _bias_finding(d: SensorDiagnosis, st: SensorDiagnosisSettings) -> Finding:
    b = d.bias
    ev: dict[str, Any] = {"constraint": "still segments: gyro mean minus the rotation the flow sees",
                          "still_s": b.still_s, "quietest_gyro_std_rad_s": b.quietest_gyro_std,
                          "bias_z_rad_s": d.bias_z}
    if not np.all(np.isfinite(b.bias)):
        return Finding(effect="gyro_bias", significant=False,
                       parameters={"bias_x": float("nan"), "bias_y": float("nan")},
                       uncertainty={"bias_x": float("nan"), "bias_y": float("nan")},
                       explanation=f"Not identifiable: {b.reason}.", fit=None, evidence=ev)
    fit = Fit(b.before, b.after)
    away = bool(np.any(np.abs(b.bias) > 2 * np.nan_to_num(b.sigma, nan=np.inf)))
    sig = bool(fit.improvement_pct >= st.min_improvement_pct and away)
    return Finding(
        effect="gyro_bias", significant=sig,
        parameters={"bias_x": float(b.bias[0]), "bias_y": float(b.bias[1])},
        uncertainty={"bias_x": float(b.sigma[0]), "bias_y": float(b.sigma[1])},
        explanation=(f"At rest the gyro reads {1e3 * b.bias[0]:+.1f} (roll) and {1e3 * b.bias[1]:+.1f} (pitch) mrad/s "
                     f"that the flow does not see, so the model without this offset drifts by that rate in scene "
                     f"angle ({b.still_s:.1f} s of still data)."),
        where=[Window("gyro", a, e) for a, e in b.windows], fit=fit, evidence=ev)


def _delay_finding(d: SensorDiagnosis, st: SensorDiagnosisSettings) -> Finding:
    band = d.band
    T = d.series.read_period_s
    if not band.fitted:
        return Finding(effect="flow_delay", significant=False, parameters={"delay": float("nan")},
                       uncertainty={"delay": float("nan")},
                       explanation=f"Not identifiable: {band.reason_}; {rotation_content(band)}.", fit=None,
                       evidence={"constraint": "rotation band"})
    ho = band.heldout_
    ev = {"constraint": f"rotation band {st.band_low_hz:g}-{st.band_high_hz:g} Hz, blocked {st.n_folds}-fold",
          "nominal_window": f"each row's counts cover the {1e3 * T:g} ms before its timestamp",
          "gyro_band_rms_rad_s": {"x": band.gyro_band_rms_rad_s_[0], "y": band.gyro_band_rms_rad_s_[1]},
          "rotation_rms_counts": {"x": band.rotation_rms_counts_[0], "y": band.rotation_rms_counts_[1]},
          "quantization_rms_counts": QUANT_RMS_COUNTS, "heldout_rms_counts": ho,
          "rows": band.n_rows_, "translation_from_accelerometer": band.has_translation_}
    ident = band.delay_sigma_ <= max(0.005, 0.25 * abs(band.delay_))
    if not ident:
        return Finding(effect="flow_delay", significant=False, parameters={"delay": float("nan")},
                       uncertainty={"delay": float("nan")},
                       explanation=(f"Not identifiable: {rotation_content(band)}, and the delay scatters by "
                                    f"{1e3 * band.delay_sigma_:.0f} ms under resampling."),
                       fit=Fit(ho["no_delay"], ho["delay"]), evidence=ev)
    fit = Fit(ho["no_delay"], ho["delay"])
    sig = bool(fit.improvement_pct >= st.min_improvement_pct and abs(band.delay_) > 2 * band.delay_sigma_)
    return Finding(
        effect="flow_delay", significant=sig, parameters={"delay": band.delay_},
        uncertainty={"delay": band.delay_sigma_}, where=_band_windows(band),
        explanation=(f"The flow counts follow the gyro's rotation {1e3 * band.delay_:.0f} ms later than a reading of "
                     f"the {1e3 * T:g} ms before its row would (the logged reading is up to one read old, and the "
                     f"sensor reports a frame after it images it)."),
        fit=fit, evidence=ev)


def _yaw_finding(d: SensorDiagnosis, st: SensorDiagnosisSettings) -> Finding:
    band = d.band
    if not band.fitted or not np.isfinite(band.yaw_):
        return Finding(effect="flow_yaw_misalignment", significant=False, parameters={"yaw": float("nan")},
                       uncertainty={"yaw": float("nan")},
                       explanation=f"Not identifiable: {band.reason_ or 'the rotation band could not be fitted'}.",
                       fit=None, evidence={"constraint": "rotation band"})
    ho = band.heldout_
    fit = Fit(ho["delay"], ho["yaw"])
    ev = {"constraint": "rotation band: cross-axis response of the flow to roll and pitch",
          "convention": "sensor x axis turned by +yaw towards body y (simvehicle.model.flow_sensor.sensor_axes)"}
    if band.yaw_sigma_ > math.radians(10):
        return Finding(effect="flow_yaw_misalignment", significant=False, parameters={"yaw": float("nan")},
                       uncertainty={"yaw": float("nan")},
                       explanation=(f"Not identifiable: the cross-axis response scatters by "
                                    f"{math.degrees(band.yaw_sigma_):.0f} deg under resampling."), fit=fit, evidence=ev)
    sig = bool(fit.improvement_pct >= st.min_improvement_pct and abs(band.yaw_) > 2 * band.yaw_sigma_)
    return Finding(
        effect="flow_yaw_misalignment", significant=sig, parameters={"yaw": band.yaw_},
        uncertainty={"yaw": band.yaw_sigma_}, where=_band_windows(band),
        explanation=(f"Roll and pitch leak into the other flow axis as a turn of the sensor by "
                     f"{math.degrees(band.yaw_):+.1f} +- {math.degrees(band.yaw_sigma_):.1f} deg about z"
                     + ("." if sig else ", which does not improve the held-out fit enough to count.")),
        fit=fit, evidence=ev)


def _band_windows(band: RotationBandFit) -> list[Window]:
    """The stretches the rotation band was fitted on."""
    return [Window("flow_band", float(band.t_[a]), float(band.t_[b - 1])) for a, b in runs(band.use_)]


def _band_unexplained(band: RotationBandFit, window_s: float = 1.0, factor: float = 2.5) -> list[Unexplained]:
    """1-s windows where the extended model's in-band residual RMS exceeds ``factor`` x the median."""
    out: list[Unexplained] = []
    t = band.t_[band.use_]
    if len(t) == 0:
        return out
    res = (band.y_ - band.pred_fitted_)[band.use_]
    idx = np.floor((t - t[0]) / window_s).astype(int)
    for a, ch in enumerate(("flow_x_band_counts", "flow_y_band_counts")):
        rms = np.array([np.sqrt(np.mean(res[idx == k, a] ** 2)) if np.any(idx == k) else np.nan
                        for k in range(idx.max() + 1)])
        med = float(np.nanmedian(rms))
        for k in np.flatnonzero(rms > factor * med):
            sel = t[idx == k]
            out.append(Unexplained(ch, float(sel[0]), float(sel[-1]), float(rms[k])))
    return out
