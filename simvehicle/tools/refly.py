"""``python -m simvehicle refly REC [--config fitted.toml]``: fly the recorded flight again in the
simulator, with the nominal model and with the fitted one, and put both beside the recording.

The simulated vehicle flies in closed loop with the companion's control step (the fast engine,
``simvehicle.engines.fastsim``: eq. 15 and the PI of ``companion.step.controller``, compiled), driven by the
recording's own velocity setpoints over each stretch the companion was in control (a segment of
frames with commands, ``companion.diagnose.closed_loop.channels``), at the recording's height (its
rangefinder), from rest. The two models are the config given (``fitted``: its ``[effects.*]``, as
``diagnose --model-out`` writes them) and the same config without its effects (``nominal``). A
wind window of the fitted model is in recording time and is replayed at that time; it is a
circumstance of that flight and is never carried to another recording (``--also``).

Channels compared with the recording, frame by frame (the command computed from frame k is the
recording's SET_ATTITUDE_TARGET k, CONVENTIONS.md): ``pitch_cmd``, ``roll_cmd`` (rad), the
attitude ``pitch``, ``roll`` (rad), the flow's scene rate ``flow_x``, ``flow_y`` (rad/s, the
paper's convention), the companion's velocity estimate ``vx_est``, ``vy_est`` (its
VISION_SPEED_ESTIMATE) and the recording's own velocity ``vx``, ``vy`` (LOCAL_POSITION_NED in body
axes, where it has one). The closed loop hides drag and wind in the velocity (the integrator flies
the setpoint anyway): they show in the tilt the loop needs, which is why the commanded tilt is the
channel that judges a model.

The RMS of simulation minus recording is taken on the held-out half of the flight
(``companion.diagnose.fitted_model.heldout_split_s``, the half the fit never saw) and on every frame of an
``--also`` recording. Turbulence is not reproducible: ``unreproducible`` estimates the random force
the recording saw from its own force balance and flies the fitted model with a random force of
that size (and other sensor-noise seeds) to say how much of the remaining error it explains:
that spread is the recording's noise width, the error an exact model would still have.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config, Effects, WindForce, load_config
from companion.diagnose.closed_loop.channels import FlightData, extract
from companion.diagnose.fitted_model import heldout_split_s
from companion.diagnose.report_html import write_refly_html
from companion.errors import RecordingError, check_output, writing
from companion.mavlink_ids import COMPANION_COMPONENT
from companion.recordings.load import Recording, load_recording
from companion.step.core import EstimatorOptions, GyroSource, VelocityEstimator
from companion.step.profiles import Profile
from simvehicle.engines.fastsim import simulate_batch

#: (channel, unit) in the order reports list them; pitch_cmd and roll_cmd judge a model
CHANNELS = (("pitch_cmd", "rad"), ("roll_cmd", "rad"), ("pitch", "rad"), ("roll", "rad"), ("flow_x", "rad/s"),
            ("flow_y", "rad/s"), ("vx_est", "m/s"), ("vy_est", "m/s"), ("vx", "m/s"), ("vy", "m/s"))
#: the commanded tilt averaged over MEAN_S blocks (``scores``)
MEAN_S = 1.0
MEAN_SUFFIX = "_1s"
MEAN_CHANNELS = (("pitch_cmd_1s", "rad"), ("roll_cmd_1s", "rad"))
UNITS = dict((*CHANNELS, *MEAN_CHANNELS))
#: the simulator's column for each channel
_SIM_COLUMN = {"pitch_cmd": "pitch_cmd_rad", "roll_cmd": "roll_cmd_rad", "pitch": "pitch_rad", "roll": "roll_rad",
               "vx_est": "est_vx_m_s", "vy_est": "est_vy_m_s", "vx": "vx_m_s", "vy": "vy_m_s"}
#: a segment shorter than this is not flown (s)
MIN_SEGMENT_S = 5.0
#: turbulence: the force balance's window (s), its boundary means (frames), the flights flown
TURB_WINDOW_S = 1.0
TURB_EDGE_FRAMES = 10
TURB_SEEDS = 8
#: the correlation time assumed for the random force (s): the simulator's turbulence default
TURB_TAU_S = 1.0


def nominal_of(cfg: Config) -> Config:
    """The nominal model: ``cfg`` without its effects."""
    return dataclasses.replace(cfg, effects=Effects())


@dataclass
class Track:
    """One recording flown again: per-frame arrays on the recording's usable frames.

    ``recorded``/``nominal``/``fitted``: channel -> array (n,) (NaN where a channel has no value);
    ``score``: frames the RMS is taken on (the held-out half, or all of an ``--also`` recording)."""

    recording: str
    t_s: np.ndarray
    seg: np.ndarray
    recorded: dict[str, np.ndarray]
    nominal: dict[str, np.ndarray]
    fitted: dict[str, np.ndarray]
    score: np.ndarray
    #: "held-out half from X s", "the whole flight (another recording)", or "in-sample: ..."
    scored_on: str
    data: FlightData
    #: whether the fitted model's wind window was flown (only on the recording it was found in)
    carried_wind: bool = True
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class ChannelScore:
    channel: str
    unit: str
    rms_nominal: float
    rms_fitted: float
    frames: int

    def to_json(self) -> dict[str, Any]:
        return {"channel": self.channel, "unit": self.unit, "rms_nominal": _num(self.rms_nominal),
                "rms_fitted": _num(self.rms_fitted)}


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


# ---------------------------------------------------------------------------------------------
# the recording's channels


def _nearest(t_query: np.ndarray, t: np.ndarray, tol_s: float) -> np.ndarray:
    """Index of the nearest ``t`` to each query within ``tol_s``; -1 where none."""
    if t.size == 0:
        return np.full(t_query.shape, -1)
    order = np.argsort(t)
    ts = t[order]
    j = np.clip(np.searchsorted(ts, t_query), 1, max(ts.size - 1, 1))
    lo = np.clip(j - 1, 0, ts.size - 1)
    hi = np.clip(j, 0, ts.size - 1)
    pick = np.where(np.abs(ts[hi] - t_query) < np.abs(ts[lo] - t_query), hi, lo)
    ok = np.abs(ts[pick] - t_query) <= tol_s
    return np.where(ok, order[pick], -1)


def _estimate(rec: Recording, data: FlightData) -> tuple[np.ndarray, np.ndarray] | None:
    """The companion's velocity estimate at each frame: its VISION_SPEED_ESTIMATE (sent right after
    the frame's flow arrived), by log time; None when the recording has none."""
    vse = rec.tables.get("VISION_SPEED_ESTIMATE")
    if vse is None or len(vse) == 0:
        return None
    if np.any(vse.compid == COMPANION_COMPONENT):
        vse = vse.select(vse.compid == COMPANION_COMPONENT)
    t = np.asarray(vse.t_s, float) - rec.t0_s
    j = _nearest(data.t_s, t, 0.4 * data.frame_s)
    x = np.where(j >= 0, np.asarray(vse["x"], float)[np.maximum(j, 0)], np.nan)
    y = np.where(j >= 0, np.asarray(vse["y"], float)[np.maximum(j, 0)], np.nan)
    return x, y


def recorded_channels(rec: Recording, data: FlightData) -> dict[str, np.ndarray]:
    """The recording's channels on its usable frames (see the module docstring)."""
    n = data.n
    nxt = np.full(n, False)
    nxt[:-1] = data.seg[1:] == data.seg[:-1]
    out: dict[str, np.ndarray] = {}
    for name, col in (("pitch_cmd", data.pitch_cmd_rad), ("roll_cmd", data.roll_cmd_rad)):
        # the command computed from frame k is the one active from frame k+1
        c = np.full(n, np.nan)
        c[:-1] = np.where(nxt[:-1], col[1:], np.nan)
        out[name] = c
    out["pitch"], out["roll"] = data.pitch_rad.copy(), data.roll_rad.copy()
    out["flow_x"], out["flow_y"] = data.dphi_x_rad / data.dt_s, data.dphi_y_rad / data.dt_s
    est = _estimate(rec, data)
    nan = np.full(n, np.nan)
    out["vx_est"], out["vy_est"] = est if est is not None else (nan, nan)
    out["vx"], out["vy"] = data.truth_vx_m_s.copy(), data.truth_vy_m_s.copy()
    return out


# ---------------------------------------------------------------------------------------------
# flying it


def _segments(data: FlightData) -> list[tuple[int, int]]:
    return [(a, b) for a, b in data.segments() if (b - a - 1) * data.frame_s >= MIN_SEGMENT_S]


def _fill(y: np.ndarray, fallback: float) -> np.ndarray:
    ok = np.isfinite(y)
    if not np.any(ok):
        return np.full(y.shape, fallback)
    idx = np.arange(y.size)
    return np.interp(idx, idx[ok], y[ok])


class _Profile:
    """A per-frame profile as a function of simulation time (linear between frames)."""

    def __init__(self, t_s: np.ndarray, y: np.ndarray) -> None:
        self.t, self.y = t_s, y

    def __call__(self, t: float) -> float:
        return float(np.interp(t, self.t, self.y))


def _shift_wind(cfg: Config, t0_s: float) -> Config:
    """``cfg`` with its wind window moved from recording time to simulation time (t0 -> 0)."""
    w = cfg.effects.wind_force
    if w is None:
        return cfg
    return dataclasses.replace(cfg, effects=dataclasses.replace(
        cfg.effects, wind_force=WindForce(w.fx, w.fy, w.start_s - t0_s, w.end_s - t0_s)))


def fly_segments(data: FlightData, configs: list[Config], *, turbulence_sigma_n: float = 0.0,
                 seeds: list[int] | None = None) -> list[dict[str, np.ndarray]]:
    """Fly each config over every segment of ``data``, driven by its setpoints at its height;
    returns per config the simulated channels on ``data``'s frames (NaN outside flown segments)."""
    n, T = data.n, data.frame_s
    seeds = seeds if seeds is not None else [0] * len(configs)
    out = [{c: np.full(n, np.nan) for c, _ in CHANNELS} for _ in configs]
    for a, b in _segments(data):
        m = b - a
        t_rel = data.t_s[a:b] - data.t_s[a]
        sp = np.stack([_fill(data.vx_set_m_s[a:b], 0.0), _fill(data.vy_set_m_s[a:b], 0.0)], axis=1)
        height = _fill(data.range_m[a:b], configs[0].world.altitude_m)
        offsets = [cfg.effects.range_offset.offset if cfg.effects.range_offset is not None else 0.0
                   for cfg in configs]
        profiles = {off: _Profile(t_rel, np.maximum(height - off, 0.05)) for off in set(offsets)}
        alts: Any = profiles[offsets[0]] if len(profiles) == 1 else [profiles[off] for off in offsets]
        cfgs = [_shift_wind(cfg, float(data.t_s[a])) for cfg in configs]
        res = simulate_batch(cfgs, duration_s=(m - 1) * T, setpoints=sp, altitude=alts, seeds=seeds,
                             turbulence_sigma_n=turbulence_sigma_n, turbulence_tau_s=TURB_TAU_S,
                             mavlink_quantization=True, name="refly")
        for i, cfg in enumerate(configs):
            for ch, col in _SIM_COLUMN.items():
                out[i][ch][a:b] = res[col][i, :m]
            q = cfg.flow_sensor.q_rad_per_count  # what the companion reads: counts x its Q
            out[i]["flow_x"][a:b] = res["flow_x_counts"][i, :m] * q / T
            out[i]["flow_y"][a:b] = res["flow_y_counts"][i, :m] * q / T
    return out


def engine_differences(cfg: Config, profile: str) -> list[str]:
    """What the companion this config selects for ``profile`` does that the fast engine (eq. 15 on
    the IMU gyro) does not: the simulated estimate and command differ from the recording's frame by
    frame by that, whatever the model (a note each; the 1 s means of the commanded tilt, where drag
    and wind show, are affected least)."""
    opts = EstimatorOptions.from_config(cfg)
    prof = Profile(profile)
    out = []
    est = opts.resolved_estimator(prof)
    if est is not VelocityEstimator.EQ15:
        out.append(f"the companion this config selects for the {profile} profile flies velocity_estimator = "
                   f"{est.value} ({cfg.companion.velocity_estimator!r} in the config); the fast engine flies eq. 15: "
                   "its estimate and command are eq. 15's, noisier frame by frame than the recording's")
    gyro = opts.resolved_gyro(prof)
    if gyro is not GyroSource.IMU:
        out.append(f"the companion this config selects for the {profile} profile takes the gyro from the flow "
                   "message (gyro_source); the fast engine uses the IMU's")
    return out


def refly_recording(path: str | Path, cfg: Config, *, profile: str | None = None, held_out: bool = True,
                    carry_wind: bool = True) -> Track:
    """Fly ``path`` again with ``nominal_of(cfg)`` and ``cfg``. ``held_out``: score the half of the
    flight a ``--model-out`` fit never saw (else every frame: another recording of the vehicle);
    ``carry_wind``: keep ``cfg``'s wind window (only for the recording it was found in)."""
    rec = load_recording(path)
    data = extract(rec, nominal_of(cfg), profile)
    if not _segments(data):
        raise RecordingError(f"{Path(path).name}: no stretch of {MIN_SEGMENT_S:g} s or more with commands to fly")
    fitted = cfg if carry_wind else dataclasses.replace(cfg, effects=dataclasses.replace(cfg.effects,
                                                                                          wind_force=None))
    notes = []
    if cfg.effects.wind_force is not None and not carry_wind:
        notes.append("the fitted model's wind window belongs to the flight it was found in: not flown here")
    nom, fit = fly_segments(data, [nominal_of(cfg), fitted])
    flown = np.isfinite(nom["pitch_cmd"])
    if held_out:
        split = heldout_split_s(data.t_s)
        if split is None:
            score, scored_on = flown, "every frame: in-sample (a flight under 60 s is fitted whole)"
        else:
            score, scored_on = flown & (data.t_s >= split), f"the held-out half, from {split:.1f} s"
    else:
        score, scored_on = flown, "every frame (another recording of the vehicle)"
    if not cfg.effects.active():
        notes.append("the config has no [effects.*]: the fitted model is the nominal one")
    notes += engine_differences(cfg, data.profile)
    return Track(Path(path).name, data.t_s, data.seg, recorded_channels(rec, data), nom, fit, score, scored_on,
                 data, carry_wind, notes)


# ---------------------------------------------------------------------------------------------
# scores


def _rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else math.nan


def _mask(track: Track, ch: str, *others: dict[str, np.ndarray]) -> np.ndarray:
    base = ch.removesuffix(MEAN_SUFFIX)
    ok = track.score & np.isfinite(track.recorded[base])
    for o in (track.nominal, track.fitted, *others):
        ok &= np.isfinite(o[base])
    return ok


def block_means(y: np.ndarray, ok: np.ndarray, seg: np.ndarray, frames: int) -> np.ndarray:
    """Means of ``y`` over consecutive blocks of ``frames`` frames within runs of ``ok`` frames of
    one segment (a shorter remainder is dropped)."""
    out = []
    start = 0
    n = y.size
    while start < n:
        if not ok[start]:
            start += 1
            continue
        end = start
        while end < n and ok[end] and seg[end] == seg[start]:
            end += 1
        for k in range(start, end - frames + 1, frames):
            out.append(float(np.mean(y[k:k + frames])))
        start = end
    return np.asarray(out)


def _values(track: Track, ch: str, source: dict[str, np.ndarray], ok: np.ndarray) -> np.ndarray:
    """A channel's values on the scored frames: per frame, or 1 s means for ``*_1s``."""
    base = ch.removesuffix(MEAN_SUFFIX)
    if ch == base:
        return source[base][ok]
    return block_means(source[base], ok, track.seg, _frames_per_s(track))


def _frames_per_s(track: Track) -> int:
    return max(int(round(MEAN_S / track.data.frame_s)), 1)


def scores(track: Track) -> list[ChannelScore]:
    """RMS of simulation minus recording per channel, nominal and fitted, on the scored frames;
    channels the recording does not have are left out. Besides the per-frame channels, the
    commanded tilt averaged over MEAN_S blocks (``pitch_cmd_1s``, ``roll_cmd_1s``): the tilt the loop
    needs, where drag and wind show, without the frame-rate noise of the estimate."""
    out = []
    for ch, unit in (*CHANNELS, *MEAN_CHANNELS):
        ok = _mask(track, ch)
        if np.count_nonzero(ok) < 10:
            continue
        r = _values(track, ch, track.recorded, ok)
        if r.size < 3:
            continue
        out.append(ChannelScore(ch, unit, _rms(_values(track, ch, track.nominal, ok) - r),
                                _rms(_values(track, ch, track.fitted, ok) - r), int(np.count_nonzero(ok))))
    return out


# ---------------------------------------------------------------------------------------------
# turbulence: how much of the remaining error it explains


@dataclass(frozen=True)
class Unreproducible:
    """What no simulation from the setpoints can reproduce: the random force the recording saw
    (``force_residual``) and the sensors' noise. ``floor``: per channel, the RMS by which flights of
    the fitted model itself differ when flown with a random force of that size and other noise
    seeds, on the scored frames: the error an exact model would still have (the recording's noise
    width). ``share``: floor^2 / rms_fitted^2 per channel, the part of the fitted model's remaining
    mean-square error it explains (at most 1)."""

    force_sd_n: tuple[float, float]
    floor: dict[str, float]
    share: dict[str, float]


def _velocity(track: Track, axis: str) -> np.ndarray:
    """The recording's own velocity (LOCAL_POSITION_NED: an EKF's, or a simulator's truth) where it
    has it on most frames, else the companion's estimate (which a flow scale or yaw distorts)."""
    own = track.recorded[axis]
    if np.count_nonzero(np.isfinite(own)) >= 0.9 * own.size:
        return own
    return track.recorded[f"{axis}_est"]


def window_kernel(frames: int, edge: int) -> np.ndarray:
    """Weights ``c`` (frames - 1,) such that mean(v[-edge:]) - mean(v[:edge]) = sum_i c_i (v[i+1] - v[i])
    for a window of ``frames`` frames: the share of the end samples after the step minus that of the
    start samples (0 to 1 over the first block, 1 in the middle, 1 to 0 over the last)."""
    i = np.arange(1, frames)
    after_end = np.clip(i - (frames - edge), 0, edge)  # end samples at index < i
    after_start = np.clip(i, 0, edge)  # start samples at index < i
    return (edge - after_end) / edge - (edge - after_start) / edge


def _window_residuals(track: Track, cfg: Config, frames: int) -> tuple[list[float], list[float]]:
    """Per axis, the unexplained velocity change (m/s) over consecutive windows of ``frames`` frames:
    the change of the recording's velocity (``_velocity``) between boundary means over
    TURB_EDGE_FRAMES frames, minus what the fitted model explains (s g tan(tilt) - b v / m + wind / m,
    the trapezoid between frames, weighted by ``window_kernel``)."""
    m, g = cfg.airframe.mass_kg, cfg.airframe.gravity_m_s2
    b = cfg.effects.linear_drag.b if cfg.effects.linear_drag is not None else 0.0
    w = cfg.effects.wind_force
    e = TURB_EDGE_FRAMES
    c = window_kernel(frames, e)
    out: list[list[float]] = [[], []]
    for wi, (v_name, ang_name, s) in enumerate((("vx", "pitch", -1.0), ("vy", "roll", 1.0))):
        v, ang = _velocity(track, v_name), track.recorded[ang_name]
        acc = s * g * np.tan(ang) - b * v / m
        if w is not None:
            acc = acc + (w.fx, w.fy)[wi] / m * ((track.t_s >= w.start_s) & (track.t_s < w.end_s))
        for segid in np.unique(track.seg):
            idx = np.flatnonzero(track.seg == segid)
            for k in range(0, idx.size - frames + 1, frames):
                j = idx[k:k + frames]
                if not (np.all(np.isfinite(v[j])) and np.all(np.isfinite(acc[j]))):
                    continue
                dv = float(np.mean(v[j[-e:]]) - np.mean(v[j[:e]]))
                step = 0.5 * (acc[j[1:]] + acc[j[:-1]]) * np.diff(track.t_s[j])
                out[wi].append(dv - float(np.dot(c, step)))
    return out[0], out[1]


def force_residual(track: Track, cfg: Config) -> tuple[float, float]:
    """The random horizontal force the recording saw under the fitted model (N, standard deviation
    per axis, averaged over TURB_WINDOW_S windows).

    The unexplained velocity change over 1 s windows holds the force's and the estimate's noise;
    over windows of two boundary means only (2 x TURB_EDGE_FRAMES frames, 0.2 s at 50 Hz) it holds
    the same estimate noise and a force effect (0.2 s / 1 s)^2 = 4 % as large in variance: their
    difference in variance is the force's."""
    m = cfg.airframe.mass_kg
    T = float(np.median(np.diff(track.t_s))) if track.t_s.size > 1 else 0.02
    L = int(round(TURB_WINDOW_S / T))
    e = TURB_EDGE_FRAMES
    long_, short = _window_residuals(track, cfg, L), _window_residuals(track, cfg, 2 * e)
    out = []
    for lo, sh in zip(long_, short, strict=True):
        if len(lo) < 5 or len(sh) < 5:
            out.append(math.nan)
            continue
        var = float(np.var(lo)) - float(np.var(sh))
        out.append(m * math.sqrt(max(var, 0.0)) / ((L - e) * T))
    return out[0], out[1]


def unreproducible(track: Track, cfg: Config, fitted_scores: list[ChannelScore]) -> Unreproducible:
    """Fly the fitted model with a random force of the recording's size (``force_residual``, both
    axes at the larger of the two, correlation time TURB_TAU_S) and other noise seeds, TURB_SEEDS
    times, against the same model flown calm (``track.fitted``: seed 0, no random force)."""
    fx, fy = force_residual(track, cfg)
    sigma = max([v for v in (fx, fy) if math.isfinite(v)] + [0.0])
    fitted = cfg if track.carried_wind else dataclasses.replace(
        cfg, effects=dataclasses.replace(cfg.effects, wind_force=None))
    runs = fly_segments(track.data, [fitted] * TURB_SEEDS, turbulence_sigma_n=sigma,
                        seeds=list(range(1, TURB_SEEDS + 1)))
    floor, share = {}, {}
    for sc in fitted_scores:
        ch = sc.channel
        ok = _mask(track, ch, *runs)
        calm = _values(track, ch, track.fitted, ok)
        floor[ch] = _rms(np.concatenate([_values(track, ch, r, ok) - calm for r in runs]))
        share[ch] = min(floor[ch] ** 2 / sc.rms_fitted ** 2, 1.0) if sc.rms_fitted > 0 else math.nan
    return Unreproducible((fx, fy), floor, share)


# ---------------------------------------------------------------------------------------------
# output: table, JSON, plot, report


@dataclass
class Result:
    """One recording's comparison: the flights, the scores, what is not reproducible."""

    track: Track
    scores: list[ChannelScore]
    unrepro: Unreproducible

    def to_json(self) -> dict[str, Any]:
        u = self.unrepro
        return {"recording": self.track.recording, "scored_on": self.track.scored_on,
                "channels": [s.to_json() for s in self.scores],
                "noise": {ch: _num(v) for ch, v in u.floor.items()},
                "turbulence": {"force_sd_n": [_num(u.force_sd_n[0]), _num(u.force_sd_n[1])],
                               "share_of_fitted_ms": {ch: _num(v) for ch, v in u.share.items()}},
                "notes": list(self.track.notes)}


def compare(path: str | Path, cfg: Config, *, profile: str | None = None, held_out: bool = True,
            carry_wind: bool = True) -> Result:
    """Fly ``path`` again with the nominal and the fitted model and score both (the whole refly)."""
    track = refly_recording(path, cfg, profile=profile, held_out=held_out, carry_wind=carry_wind)
    sc = scores(track)
    return Result(track, sc, unreproducible(track, cfg, sc))


def table(res: Result) -> list[str]:
    """The comparison as text lines (RMS of simulation minus recording, and in noise widths)."""
    u = res.unrepro
    lines = [f"{res.track.recording}: scored on {res.track.scored_on} ({res.scores[0].frames if res.scores else 0} "
             "frames)", f"  {'channel':12s} {'unit':6s} {'nominal':>9s} {'fitted':>9s} {'noise':>9s}   "
             "in noise widths: nominal, fitted"]
    for s in res.scores:
        fl = u.floor.get(s.channel, math.nan)
        lines.append(f"  {s.channel:12s} {s.unit:6s} {s.rms_nominal:9.4g} {s.rms_fitted:9.4g} {fl:9.3g}   "
                     f"{_widths(s.rms_nominal, fl):>5s}, {_widths(s.rms_fitted, fl):>5s}")
    lines.append("  " + turbulence_line(res))
    lines += [f"  note: {n}" for n in res.track.notes]
    return lines


def _widths(rms: float, noise: float) -> str:
    """``rms`` in noise widths, or "-" when the noise width is zero or unknown (a recording with no
    random force the fitted model's sensors have no noise: nothing to measure it against)."""
    return f"{rms / noise:.1f}" if noise > 0 and math.isfinite(noise) else "-"


def turbulence_line(res: Result) -> str:
    """How much of the fitted model's remaining error turbulence (and the sensors' noise) explains."""
    u = res.unrepro
    sh = [u.share.get(c, math.nan) for c in ("pitch_cmd", "roll_cmd")]
    return (f"Turbulence: a random force of {u.force_sd_n[0]:.2g} / {u.force_sd_n[1]:.2g} N (x / y, over "
            f"{TURB_WINDOW_S:g} s, from the recording's force balance) with the sensors' noise explains "
            f"{100 * sh[0]:.0f} % / {100 * sh[1]:.0f} % of the fitted model's remaining mean-square error in "
            "pitch_cmd / roll_cmd.")


#: the channels the plot draws, top to bottom
PLOTTED = ("pitch_cmd", "roll_cmd", "pitch", "flow_x", "vx_est")


def plot(res: Result, path: str | Path, *, title: str) -> Path:
    """Recording, nominal and fitted simulation on one time axis per channel; the scored frames
    shaded."""
    from matplotlib.figure import Figure

    tr = res.track
    chans = [c for c in PLOTTED if np.any(np.isfinite(tr.recorded[c]))]
    fig = Figure(figsize=(11, 2.1 * len(chans) + 0.6))
    axes = fig.subplots(len(chans), 1, sharex=True, squeeze=False)[:, 0]
    byname = {s.channel: s for s in res.scores}
    scored = tr.t_s[tr.score]
    for ax, ch in zip(axes, chans, strict=True):
        ax.plot(tr.t_s, tr.nominal[ch], color="tab:red", lw=0.8, alpha=0.85, label="simulation, nominal model")
        ax.plot(tr.t_s, tr.fitted[ch], color="tab:blue", lw=0.8, alpha=0.85, label="simulation, fitted model")
        ax.plot(tr.t_s, tr.recorded[ch], color="black", lw=0.5, label="your flight (the recording)")
        if scored.size:
            ax.axvspan(float(scored[0]), float(scored[-1]), color="0.92", zorder=0)
        s = byname.get(ch)
        extra = (f": RMS nominal {s.rms_nominal:.3g}, fitted {s.rms_fitted:.3g} (noise "
                 f"{res.unrepro.floor.get(ch, math.nan):.2g})") if s else ""
        ax.set_ylabel(f"{ch} ({UNITS[ch]})", fontsize=8)
        ax.set_title(f"{ch}{extra}", fontsize=9, loc="left")
    axes[0].legend(loc="upper right", fontsize=7, ncol=3)
    axes[-1].set_xlabel(f"time (s from the recording's first record); shaded: scored ({tr.scored_on})")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return Path(path)


def markdown(results: list[Result], cfg: Config, images: list[str]) -> str:
    """The report section "your simulation vs your flight, before and after"."""
    eff = ", ".join(cfg.effects.active()) or "none"
    md = ["## Your simulation vs your flight, before and after", "",
          f"The recorded flight flown again in the simulator from its own setpoints, with the nominal model and "
          f"with the fitted one (`{Path(cfg.source).name}`, effects: {eff}). RMS of simulation minus recording; "
          "*noise* is the error an exact model would still have (the fitted model flown again with the random "
          "force the recording saw and other sensor-noise seeds). The closed loop hides drag and wind in the "
          "velocity: they show in the tilt the loop needs (`pitch_cmd`, `roll_cmd`).", ""]
    for res, img in zip(results, images, strict=True):
        md += [f"### {res.track.recording}: {res.track.scored_on}", "",
               "| channel | unit | nominal | fitted | noise | nominal / noise | fitted / noise |",
               "|---|---|---|---|---|---|---|"]
        for s in res.scores:
            fl = res.unrepro.floor.get(s.channel, math.nan)
            md.append(f"| `{s.channel}` | {s.unit} | {s.rms_nominal:.4g} | {s.rms_fitted:.4g} | {fl:.3g} | "
                      f"{_widths(s.rms_nominal, fl)} | {_widths(s.rms_fitted, fl)} |")
        md += ["", turbulence_line(res), "", f"![{res.track.recording}]({img})", ""]
    return "\n".join(md)


def run_cli(args: Any) -> int:
    """``python -m simvehicle refly`` (arguments in ``simvehicle/cli.py``)."""
    import json

    if args.json:
        check_output(args.json, "--json")
    if args.report:
        check_output(args.report, "--report", folder=True)
    cfg = load_config(args.config)
    results = [compare(args.recording, cfg, profile=args.profile)]
    for other in args.also or []:
        results.append(compare(other, cfg, profile=args.profile, held_out=False, carry_wind=False))
    eff = ", ".join(cfg.effects.active()) or "none: the fitted model is the nominal one"
    print(f"refly with {cfg.source} (effects: {eff}) against the same config without effects")
    for res in results:
        print("\n".join(table(res)))
    if args.json:
        out = {"config": str(cfg.source), "effects": cfg.effects.active(), **results[0].to_json(),
               "also": [r.to_json() for r in results[1:]]}
        with writing("--json", args.json):
            Path(args.json).write_text(json.dumps(out, indent=2, allow_nan=False) + "\n")
        print(f"json: {args.json}")
    if args.report:
        folder = Path(args.report)
        with writing("--report", folder):
            folder.mkdir(parents=True, exist_ok=True)
            images = []
            for i, res in enumerate(results):
                name = "refly.png" if i == 0 else f"refly_also_{i}.png"
                plot(res, folder / name, title=f"{res.track.recording}: your simulation vs your flight")
                images.append(name)
            md = folder / "refly.md"
            md.write_text(markdown(results, cfg, images) + "\n")
            html_out = write_refly_html(md)
        print(f"report: {md}")
        print(f"report: {html_out} (one page, plots embedded; with diagnose's report when it is in the same folder)")
    return 0
