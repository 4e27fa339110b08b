"""Estimator 3, the rotation band: the flow counts against the gyro's rotation (and the
accelerometer's in-band translation) between ``band_low_hz`` and ``band_high_hz``, for the delay,
the rotation gain, and the axis turn, with block-bootstrap uncertainty and blocked k-fold
held-out residuals."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from companion.diagnose.sensor.numerics import window_integral, window_integrals
from companion.diagnose.sensor.series import SensorSeries
from companion.diagnose.sensor.settings import GRAVITY_M_S2, QUANT_RMS_COUNTS, SensorDiagnosisSettings


def inband_velocity(series: SensorSeries, settings: SensorDiagnosisSettings,
                    fs_hz: float = 500.0) -> tuple[np.ndarray, np.ndarray] | None:
    """In-band horizontal velocity over range, ``V_x / A`` and ``V_y / A`` (1/s), on a uniform
    grid, from the accelerometer: ``a_x = f_x - g theta``, ``a_y = f_y + g phi`` with the tilt
    from the integrated gyro, integrated and band-passed. None without an accelerometer."""
    if series.accel_m_s2 is None or series.accel_t_s is None:
        return None
    t0, t1 = float(series.gyro_t_s[0]), float(series.gyro_t_s[-1])
    if t1 - t0 < 3.0 / settings.band_low_hz:
        return None
    tg = np.arange(t0, t1, 1.0 / fs_hz)
    sos = signal.butter(2, [settings.band_low_hz, settings.band_high_hz], btype="band", fs=fs_hz, output="sos")
    w = series.gyro_at(tg)
    f = np.column_stack([np.interp(tg, series.accel_t_s, series.accel_m_s2[:, i]) for i in range(2)])
    tilt_pitch = np.cumsum(w[:, 1]) / fs_hz
    tilt_roll = np.cumsum(w[:, 0]) / fs_hz
    ax = signal.sosfiltfilt(sos, f[:, 0]) - GRAVITY_M_S2 * signal.sosfiltfilt(sos, tilt_pitch)
    ay = signal.sosfiltfilt(sos, f[:, 1]) + GRAVITY_M_S2 * signal.sosfiltfilt(sos, tilt_roll)
    vx = signal.sosfiltfilt(sos, np.cumsum(ax) / fs_hz)
    vy = signal.sosfiltfilt(sos, np.cumsum(ay) / fs_hz)
    a = np.maximum(series.range_at(tg), settings.flow_min_range_m)
    return tg, np.column_stack([vx / a, vy / a])


@dataclass
class RotationBandFit:
    """Band-limited fit of the flow counts to the gyro's rotation (and the accelerometer's
    in-band translation), per axis: ``y = g_rot R(d) + g_tr Tr(d)``, both sides band-passed.

    ``R`` = predicted rotation counts at the nominal Q (x: ``-int omega_y / Q``, y:
    ``+int omega_x / Q``), ``Tr`` = predicted translation counts (``-int V / A / Q``). With the
    paper's model and the true scale s, ``g_rot = 1/s``. Fitted values end in ``_``.
    """

    settings: SensorDiagnosisSettings
    rng: np.random.Generator
    delays_: np.ndarray = field(default_factory=lambda: np.zeros(0))
    delay_: float = float("nan")
    delay_sigma_: float = float("nan")
    gain_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))  # (2,) g_rot x, y
    gain_sigma_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    tr_gain_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    yaw_: float = float("nan")
    yaw_sigma_: float = float("nan")
    r2_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    rotation_rms_counts_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    gyro_band_rms_rad_s_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    expected_rel_sigma_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    reason_: str = ""
    subband_hz_: tuple[tuple[float, float], ...] = ()
    subband_gain_: np.ndarray = field(default_factory=lambda: np.full((2, 2), np.nan))  # (band, axis)
    subband_gain_sigma_: np.ndarray = field(default_factory=lambda: np.full((2, 2), np.nan))
    heldout_: dict[str, float] = field(default_factory=dict)
    baseline_rms_: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    n_rows_: int = 0
    has_translation_: bool = False
    # kept for plots and residual windows
    t_: np.ndarray = field(default_factory=lambda: np.zeros(0))
    y_: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    pred_nominal_: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    pred_fitted_: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    use_: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def fit(self, series: SensorSeries, rows: np.ndarray, bias: np.ndarray) -> RotationBandFit:
        """``rows``: flow rows to use (new readings, in order); ``bias``: (2,) rad/s (0 if unknown)."""
        st = self.settings
        t = series.t_s[rows]
        y = np.column_stack([series.counts_x[rows], series.counts_y[rows]])
        if len(t) < 50 or t[-1] - t[0] < 3.0 / st.band_low_hz:
            self.reason_ = f"too short for the {st.band_low_hz:g} Hz band edge ({len(t)} readings)"
            return self
        q = series.q_rad_per_count
        T = series.read_period_s
        fs_rows = 1.0 / float(np.median(np.diff(t)))
        hi = min(st.band_high_hz, 0.45 * fs_rows)
        sos = signal.butter(2, [st.band_low_hz, hi], btype="band", fs=fs_rows, output="sos")
        # rotation content: in-band gyro and the counts it predicts per reading
        w_rows = series.gyro_at(t)[:, :2] - np.where(np.isfinite(bias), bias, 0.0)
        w_band = signal.sosfiltfilt(sos, w_rows, axis=0)
        self.gyro_band_rms_rad_s_ = np.sqrt(np.mean(w_band**2, axis=0))
        self.rotation_rms_counts_ = self.gyro_band_rms_rad_s_[::-1] * T / q  # x counts <- pitch, y <- roll
        n_eff = 2.0 * (hi - st.band_low_hz) * float(t[-1] - t[0])
        with np.errstate(divide="ignore"):
            self.expected_rel_sigma_ = QUANT_RMS_COUNTS / (self.rotation_rms_counts_ * math.sqrt(n_eff))
        a_med = float(np.median(series.range_at(t)))
        rng_ok = series.range_at(t) >= st.flow_min_range_m
        if not np.any(rng_ok):
            self.reason_ = (f"the range (median {100 * a_med:.1f} cm) is below the flow sensor's "
                            f"{100 * st.flow_min_range_m:.0f} cm working range throughout")
            return self
        edge = int(round(1.0 * fs_rows / st.band_low_hz))  # filter start-up at the ends
        use = rng_ok.copy()
        use[:edge] = False
        use[-edge:] = False
        # rows near excluded stretches carry filter transients from them
        bad = ~rng_ok
        if np.any(bad):
            near = np.convolve(bad.astype(float), np.ones(2 * edge + 1), mode="same") > 0
            use &= ~near
        if np.sum(use) < 50:
            self.reason_ = (f"only {int(np.sum(use))} readings with the range inside the flow sensor's working range, "
                            "away from the band filter's start-up")
            return self
        self.n_rows_ = int(np.sum(use))
        yb = signal.sosfiltfilt(sos, y, axis=0)
        wx = series.gyro_rad_s[:, 0] - (bias[0] if np.isfinite(bias[0]) else 0.0)
        wy = series.gyro_rad_s[:, 1] - (bias[1] if np.isfinite(bias[1]) else 0.0)
        vel = inband_velocity(series, st)
        self.has_translation_ = vel is not None
        delays = np.arange(st.delay_min_s, st.delay_max_s + 1e-12, st.delay_step_s)
        self.delays_ = delays
        R = np.zeros((len(delays), len(t), 2))
        Tr = np.zeros((len(delays), len(t), 2))
        R[:, :, 0] = -window_integrals(t, series.gyro_t_s, wy, delays, T) / q
        R[:, :, 1] = window_integrals(t, series.gyro_t_s, wx, delays, T) / q
        R = signal.sosfiltfilt(sos, R, axis=1)
        if vel is not None:
            tg, v = vel
            Tr[:, :, 0] = -window_integrals(t, tg, v[:, 0], delays, T) / q
            Tr[:, :, 1] = -window_integrals(t, tg, v[:, 1], delays, T) / q
            Tr = signal.sosfiltfilt(sos, Tr, axis=1)
        i0 = int(np.argmin(np.abs(delays)))
        # blocks for the bootstrap and folds for the held-out check
        tu = t[use]
        Yu, Ru, Tu = yb[use], R[:, use], Tr[:, use]
        blocks = np.floor((tu - tu[0]) / st.bootstrap_block_s).astype(int)
        nb = int(blocks.max()) + 1
        S = _block_sums(Yu, Ru, Tu, blocks, nb, self.has_translation_)  # per block cross-products
        tot = {k: v.sum(axis=-1) for k, v in S.items()}
        sse, coef = _sse_all(tot, self.has_translation_)
        k = int(np.argmin(sse.sum(axis=-1)))
        self.delay_ = float(delays[k])
        self.gain_ = coef[k, :, 0].copy()
        self.tr_gain_ = coef[k, :, 1].copy() if self.has_translation_ else np.full(2, np.nan)
        self.r2_ = 1.0 - sse[k] / tot["yy"][k]
        # moving-block bootstrap of delay and gains
        W = self.rng.multinomial(nb, np.full(nb, 1.0 / nb), size=st.n_bootstrap).astype(float)  # (B, nb)
        boot = {kk: np.einsum("bn,...n->b...", W, v) for kk, v in S.items()}
        bsse, bcoef = _sse_all(boot, self.has_translation_)
        kb = np.argmin(bsse.sum(axis=-1), axis=1)
        self.delay_sigma_ = float(np.std(delays[kb]))
        gb = bcoef[np.arange(st.n_bootstrap), kb, :, 0]
        self.gain_sigma_ = np.std(gb, axis=0)
        # yaw: shared cross term u (X gets +u R_y, Y gets -u R_x), at the fitted delay
        yaw, ub = _yaw_fit(Yu, Ru[k], Tu[k], blocks, nb, W, self.has_translation_)
        g_mean = float(np.mean(self.gain_))
        self.yaw_ = float(yaw / g_mean) if g_mean > 0 else float("nan")
        self.yaw_sigma_ = float(np.std(ub) / abs(g_mean)) if g_mean != 0 else float("nan")
        # held-out: contiguous folds; each model refitted on the other folds
        self.heldout_ = _heldout(Yu, Ru, Tu, tu, st.n_folds, i0, self.has_translation_)
        # nominal model: gains 1, delay 0 (translation included when estimated)
        nominal = Ru[i0] + (Tu[i0] if self.has_translation_ else 0.0)
        self.baseline_rms_ = np.sqrt(np.mean((Yu - nominal) ** 2, axis=0))
        fitted = Ru[k] * self.gain_ + (Tu[k] * self.tr_gain_ if self.has_translation_ else 0.0)
        self.t_, self.y_, self.use_ = t, yb, use
        self.pred_nominal_ = np.full_like(yb, np.nan)
        self.pred_fitted_ = np.full_like(yb, np.nan)
        self.pred_nominal_[use] = nominal
        self.pred_fitted_[use] = fitted
        # model check: one rotation gain across the band? (lower and upper half, geometric split)
        split = math.sqrt(st.band_low_hz * hi)
        self.subband_hz_ = ((st.band_low_hz, split), (split, hi))
        raw_r = np.stack([-window_integral(t, series.gyro_t_s, wy, self.delay_, T) / q,
                          window_integral(t, series.gyro_t_s, wx, self.delay_, T) / q], axis=1)
        raw_t = None
        if vel is not None:
            tg, v = vel
            raw_t = np.stack([-window_integral(t, tg, v[:, a], self.delay_, T) / q for a in range(2)], axis=1)
        for j, band_j in enumerate(self.subband_hz_):
            sos_j = signal.butter(2, list(band_j), btype="band", fs=fs_rows, output="sos")
            yj = signal.sosfiltfilt(sos_j, y, axis=0)[use]
            rj = signal.sosfiltfilt(sos_j, raw_r, axis=0)[use][None]
            tj = signal.sosfiltfilt(sos_j, raw_t, axis=0)[use][None] if raw_t is not None else np.zeros_like(rj)
            Sj = _block_sums(yj, rj, tj, blocks, nb, self.has_translation_)
            _, cj = _sse_all({kk: v.sum(axis=-1) for kk, v in Sj.items()}, self.has_translation_)
            _, cb = _sse_all({kk: np.einsum("bn,...n->b...", W, v) for kk, v in Sj.items()}, self.has_translation_)
            self.subband_gain_[j] = cj[0, :, 0]
            self.subband_gain_sigma_[j] = np.std(cb[:, 0, :, 0], axis=0)
        return self

    def rotation_scale_identifiable(self) -> np.ndarray:
        """Per axis: the rotation-only scale is precise (1-sigma below ``max_rel_uncertainty``)
        and the same in both halves of the band (within 2 sigma)."""
        if not self.fitted:
            return np.zeros(2, dtype=bool)
        sr, ssr = self.scale_from_rotation()
        with np.errstate(divide="ignore", invalid="ignore"):
            s_sub = 1.0 / self.subband_gain_
            ss_sub = self.subband_gain_sigma_ / self.subband_gain_**2
            same = np.abs(s_sub[0] - s_sub[1]) <= 2.0 * np.hypot(ss_sub[0], ss_sub[1])
            precise = (sr > 0) & (ssr / sr <= self.settings.max_rel_uncertainty)
        return np.asarray(precise & same, dtype=bool)

    @property
    def fitted(self) -> bool:
        return self.n_rows_ > 0 and np.isfinite(self.delay_)

    def scale_from_rotation(self) -> tuple[np.ndarray, np.ndarray]:
        """Scale relative to Q from the rotation gain alone (1/g) and its 1-sigma."""
        g, sg = self.gain_, self.gain_sigma_
        with np.errstate(divide="ignore", invalid="ignore"):
            return 1.0 / g, sg / g**2


def _block_sums(Y: np.ndarray, R: np.ndarray, Tr: np.ndarray, blocks: np.ndarray, nb: int,
                with_tr: bool) -> dict[str, np.ndarray]:
    """Per-block cross-products, shape (n_delay, 2 axes, nb)."""
    def bsum(x: np.ndarray) -> np.ndarray:  # x: (nd, n, 2) -> (nd, 2, nb)
        out = np.zeros(x.shape[:1] + (2, nb))
        for a in range(2):
            for j in range(x.shape[0]):
                out[j, a] = np.bincount(blocks, weights=x[j, :, a], minlength=nb)
        return out
    nd = R.shape[0]
    Yr = np.broadcast_to(Y, (nd,) + Y.shape)
    S = {"yy": bsum(Yr * Yr), "rr": bsum(R * R), "ry": bsum(R * Yr)}
    if with_tr:
        S.update({"tt": bsum(Tr * Tr), "rt": bsum(R * Tr), "ty": bsum(Tr * Yr)})
    return S


def _sse_all(S: dict[str, np.ndarray], with_tr: bool) -> tuple[np.ndarray, np.ndarray]:
    """Least squares per (..., delay, axis) from summed cross-products: SSE and coefficients
    (..., 2) = (g_rot, g_tr)."""
    rr, ry, yy = S["rr"], S["ry"], S["yy"]
    if not with_tr:
        g = np.where(rr > 0, ry / np.where(rr > 0, rr, 1.0), 0.0)
        return yy - g * ry, np.stack([g, np.zeros_like(g)], axis=-1)
    tt, rt, ty = S["tt"], S["rt"], S["ty"]
    det = rr * tt - rt**2
    ok = det > 1e-12 * np.maximum(rr * tt, 1e-300)
    det = np.where(ok, det, 1.0)
    g1 = np.where(ok, (tt * ry - rt * ty) / det, ry / np.where(rr > 0, rr, 1.0))
    g2 = np.where(ok, (rr * ty - rt * ry) / det, 0.0)
    return yy - g1 * ry - g2 * ty, np.stack([g1, g2], axis=-1)


def _yaw_fit(Y: np.ndarray, R: np.ndarray, Tr: np.ndarray, blocks: np.ndarray, nb: int, W: np.ndarray,
             with_tr: bool) -> tuple[float, np.ndarray]:
    """Joint least squares over both axes with a shared antisymmetric cross term ``u``:
    ``X = g_x R_x + u R_y (+ n_x Tr_x)``, ``Y = g_y R_y - u R_x (+ n_y Tr_y)``. Returns u and
    its bootstrap replicates (``W``: block weights)."""
    n = len(Y)
    cols = [np.r_[R[:, 0], np.zeros(n)], np.r_[np.zeros(n), R[:, 1]], np.r_[R[:, 1], -R[:, 0]]]
    if with_tr:
        cols += [np.r_[Tr[:, 0], np.zeros(n)], np.r_[np.zeros(n), Tr[:, 1]]]
    A = np.column_stack(cols)
    b = np.r_[Y[:, 0], Y[:, 1]]
    bl = np.r_[blocks, blocks]
    AtA = np.zeros((nb, A.shape[1], A.shape[1]))
    Atb = np.zeros((nb, A.shape[1]))
    for j in range(nb):
        m = bl == j
        AtA[j] = A[m].T @ A[m]
        Atb[j] = A[m].T @ b[m]
    u = float(np.linalg.lstsq(AtA.sum(0), Atb.sum(0), rcond=None)[0][2])
    M = np.einsum("bn,nij->bij", W, AtA)
    v = np.einsum("bn,ni->bi", W, Atb)
    ub = np.array([np.linalg.lstsq(M[i], v[i], rcond=None)[0][2] for i in range(len(W))])
    return u, ub


def _heldout(Y: np.ndarray, R: np.ndarray, Tr: np.ndarray, t: np.ndarray, n_folds: int, i0: int,
             with_tr: bool) -> dict[str, float]:
    """Blocked k-fold held-out RMS (counts, both axes pooled) of: the nominal model (gains 1,
    no delay), gains fitted without delay, gains and delay fitted, and with the yaw term."""
    folds = np.array_split(np.arange(len(t)), n_folds)
    err: dict[str, list[np.ndarray]] = {"nominal": [], "no_delay": [], "delay": [], "yaw": []}
    Yb = np.broadcast_to(Y, R.shape)
    P = {"rr": R * R, "ry": R * Yb, "yy": Yb * Yb}
    if with_tr:
        P.update({"tt": Tr * Tr, "rt": R * Tr, "ty": Tr * Yb})
    total = {key: v.sum(axis=1) for key, v in P.items()}
    for f in folds:
        train = np.ones(len(t), dtype=bool)
        train[f] = False
        S = {key: total[key] - P[key][:, f].sum(axis=1) for key in P}
        sse, coef = _sse_all(S, with_tr)
        k = int(np.argmin(sse.sum(axis=-1)))

        nominal = R[i0][f] + (Tr[i0][f] if with_tr else 0.0)
        err["nominal"].append(Y[f] - nominal)
        for key, j in (("no_delay", i0), ("delay", k)):
            pred = R[j][f] * coef[j, :, 0] + (Tr[j][f] * coef[j, :, 1] if with_tr else 0.0)
            err[key].append(Y[f] - pred)
        # yaw model at the training delay
        n = int(np.sum(train))
        Rt, Tt, Yt = R[k][train], Tr[k][train], Y[train]
        cols = [np.r_[Rt[:, 0], np.zeros(n)], np.r_[np.zeros(n), Rt[:, 1]], np.r_[Rt[:, 1], -Rt[:, 0]]]
        if with_tr:
            cols += [np.r_[Tt[:, 0], np.zeros(n)], np.r_[np.zeros(n), Tt[:, 1]]]
        c = np.linalg.lstsq(np.column_stack(cols), np.r_[Yt[:, 0], Yt[:, 1]], rcond=None)[0]
        Rf, Tf = R[k][f], Tr[k][f]
        px = c[0] * Rf[:, 0] + c[2] * Rf[:, 1] + (c[3] * Tf[:, 0] if with_tr else 0.0)
        py = c[1] * Rf[:, 1] - c[2] * Rf[:, 0] + (c[4] * Tf[:, 1] if with_tr else 0.0)
        err["yaw"].append(Y[f] - np.column_stack([px, py]))
    return {key: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for key, v in err.items()}


def rotation_content(band: RotationBandFit) -> str:
    """The rotation content in words: in-band gyro, counts per reading, expected precision."""
    if not np.all(np.isfinite(band.gyro_band_rms_rad_s_)):
        return "no rotation content could be measured"
    return (f"in-band rotation {band.gyro_band_rms_rad_s_[1]:.2g} (pitch) / {band.gyro_band_rms_rad_s_[0]:.2g} "
            f"(roll) rad/s, i.e. {band.rotation_rms_counts_[0]:.2g} / {band.rotation_rms_counts_[1]:.2g} counts per "
            f"reading against {QUANT_RMS_COUNTS:.2f} counts of quantization noise, which alone would limit a "
            f"rotation-only scale to +-{100 * np.nanmin(band.expected_rel_sigma_):.0f} % at best")
