"""The fast simulation engine: many closed-loop flights at once, each frame integrated exactly.

Between two flow frames the attitude command is constant, the attitude loop (eq. 26) is linear
and the sensors only look at the state at frame times. So one frame of one axis,

    omega_dot = Omega_p^2 (u - angle) - 2 zeta Omega_p omega,   angle_dot = omega
    v_dot     = s g tan(angle) + F(t) / m - c v                   (c = b / m, 0 unless linear_drag)
    pos_dot   = v,   phi_dot = s omega - v / A(t)

is integrated in closed form where the equations allow and by high-order quadrature where they
do not (``T`` the frame period, ``tau`` the time into the frame):

- ``(omega, angle - u)(tau) = expm(A tau) (omega, angle - u)(0)``: a 2x2 matrix exponential,
  in closed form, precomputed once per flight at the quadrature nodes, at ``T`` and at the
  flow-delay point;
- the forcing ``f = s g tan(angle) + F / m`` is evaluated at ``n`` Gauss-Legendre nodes and
  replaced by its interpolating polynomial; the exact exponential integrator of the linear
  ``v`` equation and the double integral that gives ``pos`` are then fixed weights
  (``v(T) = e^{-cT} v0 + sum_j Wv_j f_j``, ``pos(T) = pos0 + phi1(c,T) v0 + sum_j Wp_j f_j``);
- ``phi(T) = phi0 + s (angle(T) - angle0) - integral(v / A)``: with a constant altitude the
  last term is ``(pos(T) - pos0) / A`` exactly; with an altitude profile, quadrature of
  ``v / A`` at the nodes;
- a ``wind_force`` window that opens or closes inside a frame is integrated exactly (piecewise
  constant force), so windows on the reference's 1 ms grid agree with it.

What is modelled, exactly. The vehicle: everything the reference simulator
(``simvehicle.model.sim.Simulator``, RK4 at 1 ms) does per frame: the effects ``MODELLED_EFFECTS``
(every effect the config has today), turbulence, gyro and range noise drawn from each flight's
own seeded Generator in the reference's order. The companion: ``companion.step.core.CompanionCore``'s
step for the ``paper`` profile flying eq. 15 unfiltered on the IMU gyro (``gyro_source`` ``imu``
or ``auto``, ``velocity_estimator`` ``eq15`` or ``auto``), always engaged, from the companion's
own source compiled: the setpoint clip (``companion.step.rules.clip_speed``, ``max_speed_m_s``); of
the per-frame gates (``core.GATE_CAUSES``) the two a simulated frame can fail, the gyro saturated
or not finite (``rules.gyro_invalid``) and the range outside the sensor's limits
(``rules.range_invalid``), then the spike gate (``rules.scene_spike``, ``max_flow_rate_rad_s``);
eq. 15 (``companion.step.estimator.velocity_from_flow``) over the frame spacing
(``estimator.frame_spacing_array``); the PI law (``companion.step.controller._axis``, anti-windup
included), its integrator frozen on a held frame. A held frame is ``hold`` 1 (the cause is not
kept). The other gates cannot fail here: every flow frame is finite, of quality 255, new and in
order (no repeats, no reboot), and finds a gyro sample at its own time and a range of its own
frame (so a ``max_gyro_skew_s`` or ``range_timeout_s`` >= 0 never holds one). With
``mavlink_quantization=True`` the companion sees what ``simvehicle.engines.scenarios.fly`` feeds it
through MAVLink (gyro in integer mrad/s, range in integer cm, times in integer µs), so the two
agree frame for frame: estimates, commands and holds, for each option value the engine flies and
with the gates firing (tests/test_fastsim.py).

Not modelled, and refused (``check_modelled``: a ConfigError naming the key, which ``simvehicle
sweep`` prints as one line) rather than ignored: ``velocity_estimator = "tilt"`` or ``"kf"``,
``gyro_source = "flow"`` (the flow message's own body rate), a negative ``max_gyro_skew_s`` or
``range_timeout_s``, an effect outside ``MODELLED_EFFECTS``, and any key the engine does not read
(``FIELDS_READ``; a new estimator option, say) set to anything but ``configs/paper.toml``'s
value. Not modelled and not a config option: the cross-frame checks (``companion.step.core.
Plausibility``: velocity jump, frozen flow, frozen gyro). They hold a frame only on a sensor
fault (a glitch, a stream that stops changing), which none of the modelled effects produces; the
frame-for-frame agreement with ``scenarios.fly`` shows they did not fire there. A flight where
they would fire diverges from the companion from that frame on. Fly such configs with
``python -m simvehicle scenario`` or ``serve``, which run the companion's own step.

The frame loop runs in a numba-compiled kernel (one pass over flights and axes per frame,
no temporaries). Without numba the same kernel runs as plain Python, correct but about 200
times slower. Measured numbers: ``docs/performance.md``.

Public API: ``simulate_batch`` (N flights, one call), ``fly_fast`` (one of the paper's
scenarios, like ``scenarios.fly``), ``reference_run`` (the fine-step baseline, driven directly),
``pi_step_batch`` (the PI law over arrays).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.config import Config, load_config
from companion.errors import ConfigError
from companion.step import rules
from companion.step.controller import _axis as _pi_axis_py
from companion.step.core import CompanionCore
from companion.step.estimator import frame_spacing_array
from companion.step.estimator import velocity_from_flow as _velocity_from_flow_py
from companion.step.profiles import FlowColumns
from simvehicle.engines.scenarios import Run, Scenario
from simvehicle.model.sim import Simulator, Turbulence

try:  # numba turns the frame loop into machine code; without it the same loop runs in Python
    import numba as _numba
except ImportError:  # pragma: no cover - numba is a dependency; this keeps imports working without it
    _numba = None  # type: ignore[assignment]

NUMBA = _numba is not None and not os.environ.get("FLOWHOLD_NO_NUMBA")


def _jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    if not NUMBA:
        return fn
    return _numba.njit(cache=True, nogil=True)(fn)


#: the companion's own eq. 15, per-axis PI step and step rules (``companion.step.rules``), compiled:
#: the same source as the live loop's and replay's
_velocity_from_flow = _jit(_velocity_from_flow_py)
_pi_axis = _jit(_pi_axis_py)
_clip_speed = _jit(rules.clip_speed)
_gyro_invalid = _jit(rules.gyro_invalid)
_range_invalid = _jit(rules.range_invalid)
_scene_spike = _jit(rules.scene_spike)

#: Gauss-Legendre nodes per frame. From 4 nodes on, the frame-time scene angle of a 150 s
#: demanding flight stops changing and sits within 1.5e-10 rad of the 1 ms RK4 reference (whose
#: own error that is); 6 leave a margin for faster attitude loops (docs/performance.md)
DEFAULT_NODES = 6

#: frames per kernel call when noise is drawn (bounds the memory of the pre-drawn normals)
_BLOCK_FRAMES = 512

# -- per-flight parameter columns (P[i, ...]) ---------------------------------------------------
(P_G, P_MASS, P_C, P_ALT, P_QX, P_QY, P_YAW_C, P_YAW_S, P_BIAS_X, P_BIAS_Y, P_GYRO_SIGMA, P_GYRO_RANGE,
 P_RANGE_OFFSET, P_RANGE_STD, P_RANGE_RES, P_WIND_ON, P_WIND_FX, P_WIND_FY, P_WIND_START, P_WIND_END,
 P_TURB_A, P_TURB_W, P_LAG, P_TAU_D, P_Q_NOM, P_KP, P_KI, P_LIMIT, P_VMAX, P_MAX_RATE, P_GYRO_LIMIT,
 P_RANGE_MIN, P_RANGE_MAX, P_RANGE_MIN_CM, P_RANGE_MAX_CM) = range(35)
_NP = 35

# -- output columns, in the order of ``COLUMNS`` -------------------------------------------------
COLUMNS = ("t_s", "vx_m_s", "vy_m_s", "x_m", "y_m", "roll_rad", "pitch_rad", "roll_rate_rad_s",
           "pitch_rate_rad_s", "flow_x_counts", "flow_y_counts", "gyro_x_rad_s", "gyro_y_rad_s", "range_m",
           "est_vx_m_s", "est_vy_m_s", "vx_set_m_s", "vy_set_m_s", "roll_cmd_rad", "pitch_cmd_rad", "hold",
           "phi_x_rad", "phi_y_rad", "altitude_m")
"""Per-frame columns of a flight: those of ``simvehicle.engines.scenarios.Run`` plus the true scene
angles and altitude. ``gyro_*`` and ``range_m`` are the sensors' outputs before MAVLink
encoding, as ``fly`` records them; ``*_cmd_rad`` the command computed at the frame (or the
imposed one, see ``commands``); ``est_*`` NaN on frames the companion held."""
(C_T, C_VX, C_VY, C_X, C_Y, C_ROLL, C_PITCH, C_ROLL_RATE, C_PITCH_RATE, C_FLOW_X, C_FLOW_Y, C_GYRO_X,
 C_GYRO_Y, C_RANGE, C_EST_VX, C_EST_VY, C_VX_SET, C_VY_SET, C_ROLL_CMD, C_PITCH_CMD, C_HOLD, C_PHI_X,
 C_PHI_Y, C_ALT) = range(len(COLUMNS))


# =============================================================================================
# The kernel (compiled by numba when available). Scalars only: one flight, one axis at a time.


@_jit
def _round_half_even(x: float) -> float:
    """Python's ``round(x)`` (ties to even) on a finite float, as a float."""
    fl = float(math.floor(x))
    d = x - fl
    if d > 0.5:
        return fl + 1.0
    if d < 0.5:
        return fl
    return fl if fl % 2.0 == 0.0 else fl + 1.0


@_jit
def _phi1(c: float, x: float) -> float:
    """integral_0^x exp(-c s) ds = (1 - exp(-c x)) / c (x when c = 0). s, with c in 1/s."""
    z = c * x
    if z == 0.0:
        return x
    return -math.expm1(-z) / c


@_jit
def _phi2(c: float, x: float) -> float:
    """integral_0^x phi1(c, s) ds = x^2 (z - 1 + exp(-z)) / z^2 with z = c x (x^2 / 2 when c = 0)."""
    z = c * x
    if z < 1e-2:
        g2 = 0.5 - z / 6.0 + z * z / 24.0 - z * z * z / 120.0 + z * z * z * z / 720.0
    else:
        g2 = (z + math.expm1(-z)) / (z * z)
    return x * x * g2


@_jit
def _frames(f0, f1, T, tt, dtc, P, Mn, MT, Md, WvT, WpT, WpD, eT, ePT, Pd0, wq, tau, Wn, en, Sd,  # type: ignore[no-untyped-def]
            alt_varies, alt_frame, alt_nodes, has_fnodes, f_nodes, has_fframe, f_frame, sp_sched, use_cmd,
            cmd_sched, mavlink, z, xs, uact, upend, cprev, integ, sp, turb, hist, slots, out):  # noqa: ANN001
    """Frames f0 <= f < f1 of every flight: advance to t_f (f > 0), sample, run the companion.

    Shapes: P (N, _NP); Mn (N, n, 4) = expm entries (m11, m12, m21, m22) at the nodes, MT and
    Md (N, 4) at T and at the delay point; WvT, WpT, WpD (N, n); Wn (N, n, n); en (N, n);
    Sd (N, n); schedules with a leading dimension of 1 (shared) or N; z (N, f1 - f0, 6) standard
    normals [turb x, turb y, gyro x, y, z, range] in the reference's draw order; state xs
    (N, 2, 5) per axis (x = pitch, y = roll) (omega, angle, v, pos, phi); out (n_slots, N, n_t).
    """
    n_sims = xs.shape[0]
    n_nodes = tau.shape[0]
    f_v = np.empty(n_nodes)
    h_v = np.empty(n_nodes)
    n_cols = slots.shape[0]
    rec = np.empty(n_cols)
    L = hist.shape[1]
    for f in range(f0, f1):
        zf = f - f0
        for i in range(n_sims):
            p = P[i]
            # ---- advance [t_(f-1), t_f] with the active command, then activate the pending one
            if f > 0:
                k = f - 1
                t0 = tt[k]
                if p[P_TURB_W] > 0.0:
                    turb[i, 0] = p[P_TURB_A] * turb[i, 0] + p[P_TURB_W] * z[i, zf, 0]
                    turb[i, 1] = p[P_TURB_A] * turb[i, 1] + p[P_TURB_W] * z[i, zf, 1]
                g = p[P_G]
                m = p[P_MASS]
                c = p[P_C]
                lag = int(p[P_LAG])
                tau_d = p[P_TAU_D]
                ia = i if alt_frame.shape[0] > 1 else 0
                iff = i if f_frame.shape[0] > 1 else 0
                # wind window, relative to the frame start, clipped to the frame
                wa = 0.0
                wb = 0.0
                if p[P_WIND_ON] > 0.0:
                    wa = max(p[P_WIND_START] - t0, 0.0)
                    wb = min(p[P_WIND_END] - t0, T)
                for a in range(2):
                    s = -1.0 if a == 0 else 1.0
                    om0 = xs[i, a, 0]
                    th0 = xs[i, a, 1]
                    v0 = xs[i, a, 2]
                    p0 = xs[i, a, 3]
                    phi0 = xs[i, a, 4]
                    u = uact[i, a]
                    e0 = th0 - u
                    fconst = turb[i, a]
                    if has_fframe:
                        fconst += f_frame[iff, k, a]
                    vT = eT[i] * v0
                    dp = ePT[i] * v0
                    dpd = Pd0[i] * v0
                    for j in range(n_nodes):
                        th_j = u + Mn[i, j, 2] * om0 + Mn[i, j, 3] * e0
                        force = fconst
                        if has_fnodes:
                            force += f_nodes[i if f_nodes.shape[0] > 1 else 0, k, j, a]
                        fj = s * g * math.tan(th_j) + force / m
                        f_v[j] = fj
                        vT += WvT[i, j] * fj
                        dp += WpT[i, j] * fj
                        dpd += WpD[i, j] * fj
                    fw = 0.0
                    if wb > wa:
                        fw = (p[P_WIND_FX] if a == 0 else p[P_WIND_FY]) / m
                        vT += fw * (_phi1(c, T - wa) - _phi1(c, T - wb))
                        dp += fw * (_phi2(c, T - wa) - _phi2(c, T - wb))
                        if lag > 0 and tau_d > wa:
                            dpd += fw * (_phi2(c, tau_d - wa) - _phi2(c, tau_d - min(wb, tau_d)))
                    omT = MT[i, 0] * om0 + MT[i, 1] * e0
                    thT = u + MT[i, 2] * om0 + MT[i, 3] * e0
                    if alt_varies:
                        it = 0.0
                        idl = 0.0
                        for j in range(n_nodes):
                            vj = en[i, j] * v0
                            for q in range(n_nodes):
                                vj += Wn[i, j, q] * f_v[q]
                            if wb > wa and tau[j] > wa:
                                vj += fw * (_phi1(c, tau[j] - wa) - _phi1(c, tau[j] - min(wb, tau[j])))
                            h_v[j] = vj / alt_nodes[ia, k, j]
                            it += wq[j] * h_v[j]
                            idl += Sd[i, j] * h_v[j]
                    else:
                        it = dp / p[P_ALT]
                        idl = dpd / p[P_ALT]
                    xs[i, a, 0] = omT
                    xs[i, a, 1] = thT
                    xs[i, a, 2] = vT
                    xs[i, a, 3] = p0 + dp
                    xs[i, a, 4] = phi0 + s * (thT - th0) - it
                    if lag > 0:
                        th_d = u + Md[i, 2] * om0 + Md[i, 3] * e0
                        hist[i, k % L, a] = phi0 + s * (th_d - th0) - idl
                uact[i, 0] = upend[i, 0]
                uact[i, 1] = upend[i, 1]
            # ---- sample the sensors at t_f
            ia = i if alt_frame.shape[0] > 1 else 0
            alt = alt_frame[ia, f] if alt_varies else p[P_ALT]
            lag = int(p[P_LAG])
            if lag > 0:
                jd = f - lag
                phx = hist[i, jd % L, 0] if jd >= 0 else 0.0
                phy = hist[i, jd % L, 1] if jd >= 0 else 0.0
            else:
                phx = xs[i, 0, 4]
                phy = xs[i, 1, 4]
            sx = p[P_YAW_C] * phx + p[P_YAW_S] * phy
            sy = -p[P_YAW_S] * phx + p[P_YAW_C] * phy
            cx = float(math.floor(sx / p[P_QX]))
            cy = float(math.floor(sy / p[P_QY]))
            dcx = cx - cprev[i, 0] if f > 0 else 0.0
            dcy = cy - cprev[i, 1] if f > 0 else 0.0
            cprev[i, 0] = cx
            cprev[i, 1] = cy
            gx = xs[i, 1, 0] + p[P_BIAS_X]  # roll rate
            gy = xs[i, 0, 0] + p[P_BIAS_Y]  # pitch rate
            if p[P_GYRO_SIGMA] > 0.0:
                gx += p[P_GYRO_SIGMA] * z[i, zf, 2]
                gy += p[P_GYRO_SIGMA] * z[i, zf, 3]
            lim = p[P_GYRO_RANGE]
            gx = min(max(gx, -lim), lim)
            gy = min(max(gy, -lim), lim)
            rng_m = alt + p[P_RANGE_OFFSET]
            if p[P_RANGE_STD] > 0.0:
                rng_m += p[P_RANGE_STD] * z[i, zf, 5]
            if p[P_RANGE_RES] > 0.0:
                rng_m = _round_half_even(rng_m / p[P_RANGE_RES]) * p[P_RANGE_RES]
            # ---- what the companion receives (through MAVLink: integer mrad/s, integer cm)
            cgx = gx
            cgy = gy
            crng = rng_m
            if mavlink:
                if math.isfinite(gx):
                    cgx = min(max(_round_half_even(gx * 1e3), -32768.0), 32767.0) * 1e-3
                if math.isfinite(gy):
                    cgy = min(max(_round_half_even(gy * 1e3), -32768.0), 32767.0) * 1e-3
                cm = rng_m * 100.0
                cur = 0.0 if not math.isfinite(cm) else min(max(_round_half_even(cm), 0.0), 65535.0)
                crng = cur * 0.01
                if not (p[P_RANGE_MIN_CM] <= cur <= p[P_RANGE_MAX_CM]):
                    crng = math.nan
            # ---- the companion's step (companion.step.core.CompanionCore.on_flow)
            isp = i if sp_sched.shape[0] > 1 else 0
            spx = sp_sched[isp, f, 0]
            spy = sp_sched[isp, f, 1]
            if math.isfinite(spx) and math.isfinite(spy):
                sp[i, 0] = _clip_speed(spx, p[P_VMAX])
                sp[i, 1] = _clip_speed(spy, p[P_VMAX])
            # the gates that can fail here (the flow, its quality, the gyro's and range's presence
            # and the range's age cannot): GYRO_INVALID, RANGE_INVALID
            ok = not (_gyro_invalid(cgx, cgy, p[P_GYRO_LIMIT]) or _range_invalid(crng, p[P_RANGE_MIN], p[P_RANGE_MAX]))
            dt = dtc[f]
            evx = math.nan
            evy = math.nan
            roll = 0.0
            pitch = 0.0
            if ok:
                rx = dcx * p[P_Q_NOM] / dt
                ry = dcy * p[P_Q_NOM] / dt
                evx, evy = _velocity_from_flow(rx, ry, cgx, cgy, crng)
                if _scene_spike(rx, ry, p[P_MAX_RATE]):
                    ok = False
                    evx = math.nan
                    evy = math.nan
            if ok:
                ix, effx = _pi_axis(integ[i, 0], sp[i, 0] - evx, dt, p[P_KP], p[P_KI], p[P_LIMIT])
                iy, effy = _pi_axis(integ[i, 1], sp[i, 1] - evy, dt, p[P_KP], p[P_KI], p[P_LIMIT])
                integ[i, 0] = ix
                integ[i, 1] = iy
                roll = effy
                pitch = -effx
            if use_cmd:
                ic = i if cmd_sched.shape[0] > 1 else 0
                roll = cmd_sched[ic, f, 0]
                pitch = cmd_sched[ic, f, 1]
            upend[i, 0] = pitch  # x axis is driven by pitch
            upend[i, 1] = roll
            # ---- record
            rec[C_T] = tt[f]
            rec[C_VX] = xs[i, 0, 2]
            rec[C_VY] = xs[i, 1, 2]
            rec[C_X] = xs[i, 0, 3]
            rec[C_Y] = xs[i, 1, 3]
            rec[C_ROLL] = xs[i, 1, 1]
            rec[C_PITCH] = xs[i, 0, 1]
            rec[C_ROLL_RATE] = xs[i, 1, 0]
            rec[C_PITCH_RATE] = xs[i, 0, 0]
            rec[C_FLOW_X] = dcx
            rec[C_FLOW_Y] = dcy
            rec[C_GYRO_X] = gx
            rec[C_GYRO_Y] = gy
            rec[C_RANGE] = rng_m
            rec[C_EST_VX] = evx
            rec[C_EST_VY] = evy
            rec[C_VX_SET] = sp[i, 0]
            rec[C_VY_SET] = sp[i, 1]
            rec[C_ROLL_CMD] = roll
            rec[C_PITCH_CMD] = pitch
            rec[C_HOLD] = 0.0 if ok else 1.0
            rec[C_PHI_X] = xs[i, 0, 4]
            rec[C_PHI_Y] = xs[i, 1, 4]
            rec[C_ALT] = alt
            for col in range(n_cols):
                slot = slots[col]
                if slot >= 0:
                    out[slot, i, f] = rec[col]


@_jit
def _pi_batch_kernel(integral, err, dt, kp, ki, limit, out_integral, out_effort):  # type: ignore[no-untyped-def]  # noqa: ANN001
    for i in range(integral.shape[0]):
        out_integral[i], out_effort[i] = _pi_axis(integral[i], err[i], dt[i], kp[i], ki[i], limit[i])


def pi_step_batch(integral_x_m: Any, integral_y_m: Any, err_x_m_s: Any, err_y_m_s: Any, dt_s: Any, *,
                  kp_rad_per_m_s: Any, ki_rad_per_m: Any, limit_rad: Any
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``companion.step.controller.pi_step`` over arrays of flights (the kernel's own compiled step).

    All arguments broadcast to one shape (N,); gains may differ per flight. Returns
    ``(integral_x_m, integral_y_m, roll_cmd_rad, pitch_cmd_rad)``, each (N,).
    """
    ix, iy, ex, ey, dt, kp, ki, lim = (np.ascontiguousarray(a, dtype=float).ravel() for a in np.broadcast_arrays(
        integral_x_m, integral_y_m, err_x_m_s, err_y_m_s, dt_s, kp_rad_per_m_s, ki_rad_per_m, limit_rad))
    if not (np.all(np.isfinite(ex)) and np.all(np.isfinite(ey)) and np.all(np.isfinite(dt))):
        raise ConfigError("PI step needs finite errors and time steps")
    nix, nex, niy, ney = (np.empty_like(ix) for _ in range(4))
    _pi_batch_kernel(ix, ex, dt, kp, ki, lim, nix, nex)
    _pi_batch_kernel(iy, ey, dt, kp, ki, lim, niy, ney)
    return nix, niy, ney, -nex


# =============================================================================================
# Precomputation (numpy, vectorised over flights)


def attitude_expm(omega_p_rad_s: Any, zeta: Any, tau_s: Any) -> np.ndarray:
    """``expm(A tau)`` of the attitude loop ``A = [[-2 zeta Op, -Op^2], [1, 0]]`` acting on
    ``(omega, angle - u)``, in closed form for any damping. Arguments broadcast together;
    returns ``(..., 4)`` = (m11, m12, m21, m22)."""
    wp, zt, tau = np.broadcast_arrays(np.asarray(omega_p_rad_s, float), np.asarray(zeta, float),
                                      np.asarray(tau_s, float))
    s = -zt * wp  # half the trace
    q2 = wp * wp * (zt - 1.0) * (zt + 1.0)  # (trace/2)^2 - det, without cancellation near zeta = 1
    qz = np.sqrt(q2.astype(complex)) * tau  # real (overdamped) or imaginary (underdamped)
    small = np.abs(qz) < 1e-8
    safe = np.where(small, 1.0, qz)
    cosh = np.where(small, 1.0 + qz * qz / 2.0, np.cosh(safe)).real
    sinhc = tau * np.where(small, 1.0 + qz * qz / 6.0, np.sinh(safe) / safe).real  # sinh(q tau) / q
    e = np.exp(s * tau)
    return np.stack([e * (cosh + s * sinhc), -e * wp * wp * sinhc, e * sinhc, e * (cosh - s * sinhc)], axis=-1)


def _phi1_np(c: np.ndarray, x: float | np.ndarray) -> np.ndarray:
    c, x = np.broadcast_arrays(np.asarray(c, float), np.asarray(x, float))
    z = c * x
    return np.where(z == 0.0, x, -np.expm1(-z) / np.where(c == 0.0, 1.0, c))


@functools.lru_cache(maxsize=32)
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on [-1, 1] (numpy's leggauss is slow: computed once)."""
    x, w = np.polynomial.legendre.leggauss(n)
    x.flags.writeable = False
    w.flags.writeable = False
    return x, w


def _lagrange(nodes: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Lagrange basis polynomials of ``nodes`` at points ``x``: shape x.shape + (n,)."""
    n = len(nodes)
    out = np.ones((*x.shape, n))
    for j in range(n):
        for q in range(n):
            if q != j:
                out[..., j] *= (x - nodes[q]) / (nodes[j] - nodes[q])
    return out


@dataclass(frozen=True)
class _Weights:
    """Per-flight frame propagators (see the module docstring). Shapes in ``_frames``."""

    tau: np.ndarray
    wq: np.ndarray
    Mn: np.ndarray
    MT: np.ndarray
    Md: np.ndarray
    WvT: np.ndarray
    WpT: np.ndarray
    WpD: np.ndarray
    eT: np.ndarray
    ePT: np.ndarray
    Pd0: np.ndarray
    Wn: np.ndarray
    en: np.ndarray
    Sd: np.ndarray


def _weights(T: float, n_nodes: int, wp: np.ndarray, zeta: np.ndarray, c: np.ndarray, tau_d: np.ndarray,
             alt_varies: bool) -> _Weights:
    x, w = _gauss_legendre(n_nodes)
    tau = (x + 1.0) * T / 2.0
    wq = w * T / 2.0
    xf, wf = _gauss_legendre(24)  # fine rule for the weights themselves (exact here)
    c1 = c[:, None]

    def rule(upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (xf + 1.0) * upper[..., None] / 2.0, wf * upper[..., None] / 2.0

    sT, wT = rule(np.array(T))
    LT = _lagrange(tau, sT)  # (24, n)
    WvT = np.einsum("q,iq,qj->ij", wT, np.exp(-c1 * (T - sT)), LT)
    WpT = np.einsum("q,iq,qj->ij", wT, _phi1_np(c1, T - sT), LT)
    sD, wD = rule(tau_d)  # (N, 24)
    LD = _lagrange(tau, sD)  # (N, 24, n)
    WpD = np.einsum("iq,iq,iqj->ij", wD, _phi1_np(c1, tau_d[:, None] - sD), LD)
    Sd = np.einsum("iq,iqj->ij", wD, LD)
    if alt_varies:
        sN, wN = rule(tau)  # (n, 24)
        LN = _lagrange(tau, sN)  # (n, 24, m)
        Wn = np.einsum("kq,ikq,kqj->ikj", wN, np.exp(-c[:, None, None] * (tau[None, :, None] - sN[None])), LN)
        en = np.exp(-c1 * tau[None, :])
    else:
        Wn = np.zeros((len(c), 1, 1))
        en = np.zeros((len(c), 1))
    return _Weights(
        tau=tau, wq=wq,
        Mn=np.ascontiguousarray(attitude_expm(wp[:, None], zeta[:, None], tau[None, :])),
        MT=attitude_expm(wp, zeta, T), Md=attitude_expm(wp, zeta, tau_d),
        WvT=WvT, WpT=WpT, WpD=WpD, eT=np.exp(-c * T), ePT=_phi1_np(c, T), Pd0=_phi1_np(c, tau_d),
        Wn=np.ascontiguousarray(Wn), en=en, Sd=Sd)


def _weights_for(T: float, n_nodes: int, wp: np.ndarray, zeta: np.ndarray, c: np.ndarray, tau_d: np.ndarray,
                 alt_varies: bool) -> _Weights:
    """``_weights`` computed once per distinct (Omega_p, zeta, c, delay point) and spread to the
    flights; batches of few distinct rows (single flights, Monte Carlo) hit a cache."""
    keys = np.stack([wp, zeta, c, tau_d], axis=1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    if len(uniq) <= 8:
        w = _weights_cached(T, n_nodes, tuple(map(tuple, uniq.tolist())), alt_varies)
    else:
        w = _weights(T, n_nodes, uniq[:, 0], uniq[:, 1], uniq[:, 2], uniq[:, 3], alt_varies)
    per_sim = {f.name: np.ascontiguousarray(getattr(w, f.name)[inv]) for f in dataclasses.fields(w)
               if f.name not in ("tau", "wq")}
    return _Weights(tau=w.tau, wq=w.wq, **per_sim)


@functools.lru_cache(maxsize=64)
def _weights_cached(T: float, n_nodes: int, rows: tuple[tuple[float, ...], ...], alt_varies: bool) -> _Weights:
    a = np.array(rows, dtype=float)
    return _weights(T, n_nodes, a[:, 0], a[:, 1], a[:, 2], a[:, 3], alt_varies)


#: the config's effects the engine flies (``_params``); any other active effect is refused
MODELLED_EFFECTS = frozenset({"linear_drag", "gyro_bias", "flow_scale", "flow_delay", "flow_yaw_misalignment",
                              "attitude_dynamics", "range_offset", "wind_force"})
#: ``[companion]`` keys the engine reads or that cannot matter to it: what it does with the key,
#: and the values for which that is what the companion's step does
COMPANION_MODELLED: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "max_speed_m_s": ("it clips the setpoint to it", lambda v: True),
    "max_flow_rate_rad_s": ("it holds a frame whose scene rate is over it", lambda v: True),
    "setpoint_timeout_s": ("the live loop's: a simulated flight has no link", lambda v: True),
    "flow_timeout_s": ("the live loop's: a simulated flight has no link", lambda v: True),
    "range_timeout_s": ("it samples the range at every frame: never stale for a timeout >= 0", lambda v: v >= 0),
    "max_gyro_skew_s": ("it samples the gyro at the frame's own time: aligned for a skew >= 0", lambda v: v >= 0),
    "gyro_source": ("it flies the IMU gyro, as 'imu' (and 'auto' for the paper profile)",
                    lambda v: v in ("auto", "imu")),
    "velocity_estimator": ("it flies eq. 15 unfiltered, as 'eq15' (and 'auto' for the paper profile)",
                           lambda v: v in ("auto", "eq15")),
    "flow_sample_age_s": ("only the Kalman filter reads it, which it does not fly", lambda v: True),
}
#: the fields of each config section the engine reads (``_params``; ``sim.substeps_per_frame`` is
#: the reference's step count: the engine integrates each frame exactly); any other field, in any
#: section, must keep configs/paper.toml's value
FIELDS_READ: dict[str, frozenset[str]] = {
    "airframe": frozenset({"mass_kg", "gravity_m_s2", "omega_p_rad_s", "zeta"}),
    "controller": frozenset({"kp_rad_per_m_s", "ki_rad_per_m", "tilt_limit_deg"}),
    "flow_sensor": frozenset({"frame_rate_hz", "q_rad_per_count"}),
    "imu": frozenset({"rate_hz", "gyro_noise", "gyro_noise_density_deg_s_sqrt_hz", "gyro_range_deg_s"}),
    "rangefinder": frozenset({"resolution_m", "min_m", "max_m", "noise_std_m"}),
    "world": frozenset({"altitude_m"}),
    "sim": frozenset({"substeps_per_frame"}),
    "companion": frozenset(COMPANION_MODELLED),
}
_WHERE_INSTEAD = "fly it with 'python -m simvehicle scenario' or 'serve', which run the companion's own step"


@functools.lru_cache(maxsize=1)
def _shipped_default() -> Config:
    return load_config()


def check_modelled(cfg: Config) -> None:
    """A ConfigError (one line, naming the key) when ``cfg`` asks for something the engine does
    not model (see the module docstring), instead of flying without it."""
    where = f"{cfg.source}: the fast engine does not model"
    for name in cfg.effects.active():
        if name not in MODELLED_EFFECTS:
            raise ConfigError(f"{where} the effect {name} (it models {', '.join(sorted(MODELLED_EFFECTS))}); "
                              f"{_WHERE_INSTEAD}")
    for key, (does, ok) in COMPANION_MODELLED.items():
        value = getattr(cfg.companion, key)
        if not ok(value):
            raise ConfigError(f"{where} companion.{key} = {value!r} ({does}); {_WHERE_INSTEAD}")
    default = _shipped_default()
    for section in (f.name for f in dataclasses.fields(cfg) if f.name not in ("source", "effects")):
        table, ref = getattr(cfg, section), getattr(default, section)
        read = FIELDS_READ.get(section, frozenset())
        pairs = ([(f"{section}.{f.name}", getattr(table, f.name), getattr(ref, f.name))
                  for f in dataclasses.fields(table) if f.name not in read]
                 if dataclasses.is_dataclass(table) else [(section, table, ref)])
        for key, value, shipped in pairs:
            if value != shipped:
                raise ConfigError(f"{where} {key} = {value!r} (it reads no such key and flies configs/paper.toml's "
                                  f"{shipped!r}); {_WHERE_INSTEAD}")


def _params(cfg: Config, T: float, turb_sigma_n: float, turb_tau_s: float) -> tuple[list[float], float, float,
                                                                                       float]:
    """One flight's parameter row, computed with the reference's own scalar expressions."""
    a, e, fs, imu, rf, cc = cfg.airframe, cfg.effects, cfg.flow_sensor, cfg.imu, cfg.rangefinder, cfg.companion
    wp, zeta = (e.attitude_dynamics.omega_p, e.attitude_dynamics.zeta) if e.attitude_dynamics \
        else (a.omega_p_rad_s, a.zeta)
    if not (wp > 0 and zeta > 0):
        raise ConfigError(f"{cfg.source}: attitude_dynamics needs omega_p > 0 and zeta > 0")
    b = e.linear_drag.b if e.linear_drag else 0.0
    if b < 0:
        raise ConfigError(f"{cfg.source}: linear_drag.b must be >= 0")
    q = fs.q_rad_per_count
    sx, sy = (e.flow_scale.scale_x, e.flow_scale.scale_y) if e.flow_scale else (1.0, 1.0)
    if not (sx > 0 and sy > 0):
        raise ConfigError(f"{cfg.source}: flow_scale factors must be > 0")
    yaw = e.flow_yaw_misalignment.yaw if e.flow_yaw_misalignment else 0.0
    delay = e.flow_delay.delay if e.flow_delay else 0.0
    if delay < 0:
        raise ConfigError(f"{cfg.source}: flow_delay.delay must be >= 0 s")
    lag = math.ceil(delay / T) if delay > 0 else 0
    tau_d = lag * T - delay if lag > 0 else 0.0
    density = math.radians(imu.gyro_noise_density_deg_s_sqrt_hz) if imu.gyro_noise else 0.0
    gyro_sigma = density * math.sqrt(imu.rate_hz) if density > 0 else 0.0
    w = e.wind_force
    if turb_sigma_n < 0 or (turb_sigma_n > 0 and not turb_tau_s > 0):
        raise ConfigError("turbulence needs sigma >= 0 N and tau > 0 s")
    ta = math.exp(-T / turb_tau_s) if turb_sigma_n > 0 else 0.0
    tw = turb_sigma_n * math.sqrt(1.0 - ta * ta) if turb_sigma_n > 0 else 0.0
    row = [0.0] * _NP
    row[P_G], row[P_MASS], row[P_C], row[P_ALT] = a.gravity_m_s2, a.mass_kg, b / a.mass_kg, cfg.world.altitude_m
    row[P_QX], row[P_QY] = q * sx, q * sy
    row[P_YAW_C], row[P_YAW_S] = (math.cos(yaw), math.sin(yaw)) if yaw != 0.0 else (1.0, 0.0)
    row[P_BIAS_X], row[P_BIAS_Y] = (e.gyro_bias.bias_x, e.gyro_bias.bias_y) if e.gyro_bias else (0.0, 0.0)
    row[P_GYRO_SIGMA], row[P_GYRO_RANGE] = gyro_sigma, math.radians(imu.gyro_range_deg_s)
    row[P_RANGE_OFFSET] = e.range_offset.offset if e.range_offset else 0.0
    row[P_RANGE_STD], row[P_RANGE_RES] = rf.noise_std_m, rf.resolution_m
    if w is not None:
        row[P_WIND_ON], row[P_WIND_FX], row[P_WIND_FY] = 1.0, w.fx, w.fy
        row[P_WIND_START], row[P_WIND_END] = w.start_s, w.end_s
    row[P_TURB_A], row[P_TURB_W] = ta, tw
    row[P_LAG], row[P_TAU_D] = float(lag), tau_d
    row[P_Q_NOM], row[P_KP], row[P_KI] = q, cfg.controller.kp_rad_per_m_s, cfg.controller.ki_rad_per_m
    row[P_LIMIT], row[P_VMAX] = cfg.controller.tilt_limit_rad, cc.max_speed_m_s
    row[P_MAX_RATE] = cc.max_flow_rate_rad_s
    row[P_GYRO_LIMIT] = math.radians(imu.gyro_range_deg_s) * 0.999
    row[P_RANGE_MIN], row[P_RANGE_MAX] = rf.min_m, rf.max_m
    row[P_RANGE_MIN_CM], row[P_RANGE_MAX_CM] = float(round(rf.min_m * 100)), float(round(rf.max_m * 100))
    return row, wp, zeta, tau_d


# =============================================================================================
# Inputs: schedules given as callables or arrays, normalised to arrays with a leading 1 or N

#: a per-frame input: a function of time (s) -> (x, y), one such function per flight, or an array
Schedule = Callable[[float], tuple[float, float]] | Sequence[Callable[[float], tuple[float, float]]] | np.ndarray


def _functions(spec: Any) -> bool:
    """A function of time, or a list of them (one per flight)."""
    return callable(spec) or (isinstance(spec, Sequence) and not isinstance(spec, str) and len(spec) > 0
                              and all(callable(f) for f in spec))


def _eval_pairs(fn: Callable[[float], Any], times: np.ndarray, what: str) -> np.ndarray:
    try:
        vals = np.array([fn(float(t)) for t in times.ravel()], dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{what}: the schedule must return a pair of numbers ({exc})") from None
    if vals.shape != (times.size, 2):
        raise ConfigError(f"{what}: the schedule must return a pair of numbers, got shape {vals.shape[1:]}")
    return vals.reshape(*times.shape, 2)


def _pairs(spec: Any, n_sims: int, times: np.ndarray, what: str, *, finite: bool) -> np.ndarray | None:
    """A schedule of (x, y) pairs at ``times`` (any shape): (1 or N, *times.shape, 2), or None."""
    if spec is None:
        return None
    if callable(spec):
        out = _eval_pairs(spec, times, what)[None]
    elif _functions(spec):
        if len(spec) != n_sims:
            raise ConfigError(f"{what}: {len(spec)} schedules for {n_sims} flights")
        out = np.stack([_eval_pairs(fn, times, what) for fn in spec])
    else:
        arr = np.asarray(spec, dtype=float)
        shape = (*times.shape[:1], 2)
        if arr.shape == shape:
            arr = arr[None]
        if arr.shape[1:] != shape or arr.shape[0] not in (1, n_sims):
            raise ConfigError(f"{what}: expected an array of shape {shape} or {(n_sims, *shape)}, "
                              f"got {np.shape(spec)}")
        out = arr
    if finite and not np.all(np.isfinite(out)):
        raise ConfigError(f"{what}: values must be finite")
    return np.ascontiguousarray(out)


def _altitudes(spec: Any, n_sims: int, times: np.ndarray) -> np.ndarray | None:
    """Altitude profile(s) at ``times``: (1 or N, *times.shape) in m, or None (config altitude)."""
    if spec is None:
        return None
    fns = [spec] if callable(spec) else list(spec)
    if not all(callable(fn) for fn in fns) or len(fns) not in (1, n_sims):
        raise ConfigError("altitude: give a function of time (s) -> m, or one per flight")
    out = np.stack([np.array([fn(float(t)) for t in times.ravel()], float).reshape(times.shape) for fn in fns])
    if not (np.all(np.isfinite(out)) and np.all(out > 0)):
        raise ConfigError("altitude: the profile must stay finite and > 0 m")
    return np.ascontiguousarray(out)


def _per_sim(value: Any, n_sims: int, what: str) -> np.ndarray:
    arr = np.broadcast_to(np.asarray(value, dtype=float), (n_sims,)) if np.ndim(value) == 0 \
        else np.asarray(value, dtype=float)
    if arr.shape != (n_sims,) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{what}: expected a finite number or {n_sims} of them")
    return arr


@dataclass
class _Problem:
    """Everything the kernel needs for a batch, as arrays (picklable, sliceable by flight)."""

    configs: tuple[Config, ...]
    seeds: np.ndarray
    T: float
    n_frames: int
    nodes: int
    mavlink: bool
    turb_sigma: np.ndarray
    turb_tau: np.ndarray
    setpoints: np.ndarray  # (1|N, n_t, 2)
    f_nodes: np.ndarray | None  # (1|N, n_frames, n, 2)
    f_frame: np.ndarray | None  # (1|N, n_frames, 2)
    alt_frame: np.ndarray | None  # (1|N, n_t)
    alt_nodes: np.ndarray | None  # (1|N, n_frames, n)
    commands: np.ndarray | None  # (1|N, n_t, 2)
    columns: tuple[str, ...]
    name: str
    meta: dict[str, Any] = field(default_factory=dict)

    def take(self, lo: int, hi: int) -> _Problem:
        def sl(a: np.ndarray | None) -> np.ndarray | None:
            return a if a is None or a.shape[0] == 1 else np.ascontiguousarray(a[lo:hi])

        return _Problem(self.configs[lo:hi], self.seeds[lo:hi], self.T, self.n_frames, self.nodes, self.mavlink,
                        self.turb_sigma[lo:hi], self.turb_tau[lo:hi], sl(self.setpoints), sl(self.f_nodes),  # type: ignore[arg-type]
                        sl(self.f_frame), sl(self.alt_frame), sl(self.alt_nodes), sl(self.commands), self.columns,
                        self.name, self.meta)


@dataclass
class BatchResult:
    """N finished flights: per-frame columns, each an array (N, n_t) (``COLUMNS``)."""

    name: str
    columns: dict[str, np.ndarray]
    configs: tuple[Config, ...]
    seeds: tuple[int, ...]
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.configs)

    def __getitem__(self, key: str) -> np.ndarray:
        return self.columns[key]

    def run(self, i: int) -> Run:
        """Flight ``i`` as a ``simvehicle.engines.scenarios.Run`` (``figures`` and ``plots`` take it)."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"flight {i} of a batch of {len(self)}")
        return Run(self.name, {k: np.asarray(v[i]) for k, v in self.columns.items()},
                   meta={**self.meta, "seed": self.seeds[i], "engine": "fastsim"})


def simulate_batch(cfg: Config | Sequence[Config], n: int | None = None, *, duration_s: float,
                   setpoints: Schedule | None = None, forces: Schedule | None = None, altitude: Any = None,
                   commands: np.ndarray | None = None,
                   seeds: int | Sequence[int] | None = None, turbulence_sigma_n: Any = 0.0,
                   turbulence_tau_s: Any = 1.0, mavlink_quantization: bool = False,
                   columns: Sequence[str] | None = None, nodes: int = DEFAULT_NODES, name: str = "batch",
                   workers: int = 1) -> BatchResult:
    """Fly N closed-loop flights of ``duration_s`` at once (frames 0..round(duration / T)).

    ``cfg``: one Config flown ``n`` times, or one Config per flight (all with the same frame
    rate). Per-flight inputs take either one value for all flights or one per flight:

    - ``setpoints``: body-frame velocity setpoint (vx, vy) m/s at frame times: a function of
      time ``t_s -> (vx, vy)``, a list of N such functions, or an array (n_t, 2) / (N, n_t, 2);
      a non-finite setpoint is ignored, as the companion does. Default 0.
    - ``forces``: external horizontal force (fx, fy) N on the body axes: a function of time
      (evaluated at the quadrature nodes: steps belong on frame times, as in the reference's
      1 ms grid), a list of N functions, or an array (n_frames, 2) / (N, n_frames, 2) held over
      each frame. The config's ``wind_force`` and the turbulence add to it.
    - ``altitude``: a function of time (s) -> m, or one per flight. Default: ``world.altitude_m``.
    - ``commands``: impose the (roll, pitch) command of every frame, rad, (n_t, 2) or
      (N, n_t, 2), instead of the PI's (open loop; the companion still estimates).
    - ``seeds``: the seed of each flight's ``numpy.random.default_rng`` (noise, turbulence);
      an int is used for every flight. Default 0, as ``scenarios.fly``.
    - ``turbulence_sigma_n``, ``turbulence_tau_s``: ``simvehicle.model.sim.Turbulence`` per flight.

    ``mavlink_quantization``: the companion sees the gyro in integer mrad/s, the range in integer
    cm and times in integer µs, as through ``scenarios.fly``'s MAVLink path. ``columns``: keep
    only these (default all of ``COLUMNS``). ``workers`` > 1 splits the batch over processes.
    """
    if isinstance(cfg, Config):
        configs: tuple[Config, ...] = (cfg,) * (1 if n is None else int(n))
    else:
        configs = tuple(cfg)
        if n is not None and n != len(configs):
            raise ConfigError(f"n = {n} but {len(configs)} configs were given")
    n_sims = len(configs)
    if n_sims < 1:
        raise ConfigError("a batch needs at least one flight")
    for c in {id(c): c for c in configs}.values():
        check_modelled(c)
    T = configs[0].flow_sensor.frame_period_s
    if any(c.flow_sensor.frame_period_s != T for c in configs):
        raise ConfigError("all flights of a batch must share flow_sensor.frame_rate_hz (group them by rate)")
    if not (isinstance(duration_s, (int, float)) and math.isfinite(duration_s) and duration_s > 0):
        raise ConfigError(f"duration_s must be a positive number of seconds, got {duration_s!r}")
    if not (isinstance(nodes, int) and 2 <= nodes <= 16):
        raise ConfigError(f"nodes must be an integer in [2, 16], got {nodes!r}")
    cols = tuple(COLUMNS if columns is None else columns)
    unknown = sorted(set(cols) - set(COLUMNS))
    if unknown:
        raise ConfigError(f"unknown column(s) {', '.join(unknown)} (known: {', '.join(COLUMNS)})")
    if seeds is None or isinstance(seeds, (int, np.integer)):
        seed_arr = np.full(n_sims, 0 if seeds is None else int(seeds), dtype=np.int64)
    else:
        seed_arr = np.asarray(list(seeds), dtype=np.int64)
        if seed_arr.shape != (n_sims,):
            raise ConfigError(f"{len(seed_arr)} seeds for {n_sims} flights")
    n_frames = int(round(duration_s / T))
    if n_frames < 1:
        raise ConfigError(f"duration_s = {duration_s} is shorter than one frame ({T} s)")
    tt = np.arange(n_frames + 1, dtype=float) * T
    x, _ = _gauss_legendre(nodes)
    t_nodes = tt[:-1, None] + (x + 1.0)[None, :] * T / 2.0
    sp = _pairs(setpoints, n_sims, tt, "setpoints", finite=False)
    alt_f = _altitudes(altitude, n_sims, tt)
    problem = _Problem(
        configs=configs, seeds=seed_arr, T=T, n_frames=n_frames, nodes=nodes, mavlink=bool(mavlink_quantization),
        turb_sigma=_per_sim(turbulence_sigma_n, n_sims, "turbulence_sigma_n"),
        turb_tau=_per_sim(turbulence_tau_s, n_sims, "turbulence_tau_s"),
        setpoints=sp if sp is not None else np.zeros((1, n_frames + 1, 2)),
        # functions of time are evaluated at the quadrature nodes, arrays hold over each frame
        f_nodes=_pairs(forces, n_sims, t_nodes, "forces", finite=True) if _functions(forces) else None,
        f_frame=_pairs(forces, n_sims, tt[:-1], "forces", finite=True) if not _functions(forces) else None,
        alt_frame=alt_f, alt_nodes=_altitudes(altitude, n_sims, t_nodes),
        commands=_pairs(commands, n_sims, tt, "commands", finite=True),
        columns=cols, name=name, meta={"mavlink_quantization": bool(mavlink_quantization), "nodes": nodes})
    if workers is None or workers <= 1 or n_sims == 1:
        return _simulate(problem)
    return _simulate_parallel(problem, int(workers))


def _simulate_parallel(problem: _Problem, workers: int) -> BatchResult:
    n_sims = len(problem.configs)
    n_chunks = min(n_sims, workers * 4)
    bounds = np.linspace(0, n_sims, n_chunks + 1).round().astype(int)
    warm_up()  # compile (or load) the kernel once here, so forked workers inherit it
    with ProcessPoolExecutor(max_workers=workers) as pool:
        parts = list(pool.map(_simulate, [problem.take(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:],
                                                                                   strict=True)]))
    return _concat(parts)


def _concat(parts: list[BatchResult]) -> BatchResult:
    first = parts[0]
    return BatchResult(first.name, {k: np.concatenate([p.columns[k] for p in parts]) for k in first.columns},
                       tuple(c for p in parts for c in p.configs), tuple(s for p in parts for s in p.seeds),
                       first.meta)


def _simulate(pb: _Problem) -> BatchResult:
    n_sims = len(pb.configs)
    T, n_t = pb.T, pb.n_frames + 1
    rows, wps, zetas, tau_ds = [], [], [], []
    for cfg, ts, tt_ in zip(pb.configs, pb.turb_sigma, pb.turb_tau, strict=True):
        row, wp, zeta, tau_d = _params(cfg, T, float(ts), float(tt_))
        rows.append(row)
        wps.append(wp)
        zetas.append(zeta)
        tau_ds.append(tau_d)
    P = np.array(rows, dtype=float)
    alt_varies = pb.alt_frame is not None
    W = _weights_for(T, pb.nodes, np.array(wps), np.array(zetas), P[:, P_C], np.array(tau_ds), alt_varies)
    tt = np.arange(n_t, dtype=float) * T
    tc = np.round(tt * 1e6) * 1e-6 if pb.mavlink else tt
    dtc = frame_spacing_array(tc, T)
    slots = np.full(len(COLUMNS), -1, dtype=np.int64)
    kept = [c for c in pb.columns if c != "t_s"]
    for s, name in enumerate(kept):
        slots[COLUMNS.index(name)] = s
    out = np.full((len(kept), n_sims, n_t), np.nan)
    xs = np.zeros((n_sims, 2, 5))
    uact, upend, cprev, integ, sp, turb = (np.zeros((n_sims, 2)) for _ in range(6))
    lag_max = int(P[:, P_LAG].max())
    hist = np.zeros((n_sims, lag_max + 1, 2))
    noisy = (P[:, P_TURB_W] > 0) | (P[:, P_GYRO_SIGMA] > 0) | (P[:, P_RANGE_STD] > 0)
    gens = [np.random.default_rng(int(s)) if on else None for s, on in zip(pb.seeds, noisy, strict=True)]
    dummy2 = np.zeros((1, 1))
    alt_frame = pb.alt_frame if alt_varies else dummy2
    alt_nodes = pb.alt_nodes if alt_varies else np.zeros((1, 1, 1))
    f_nodes = pb.f_nodes if pb.f_nodes is not None else np.zeros((1, 1, 1, 2))
    f_frame = pb.f_frame if pb.f_frame is not None else np.zeros((1, 1, 2))
    cmds = pb.commands if pb.commands is not None else np.zeros((1, 1, 2))
    block = _BLOCK_FRAMES if noisy.any() else n_t
    z = np.zeros((n_sims, 1, 6))
    for f0 in range(0, n_t, block):
        f1 = min(f0 + block, n_t)
        if noisy.any():
            z = _normals(P, gens, f0, f1)
        _frames(f0, f1, T, tt, dtc, P, W.Mn, W.MT, W.Md, W.WvT, W.WpT, W.WpD, W.eT, W.ePT, W.Pd0, W.wq, W.tau,
                W.Wn, W.en, W.Sd, alt_varies, alt_frame, alt_nodes, pb.f_nodes is not None, f_nodes,
                pb.f_frame is not None, f_frame, pb.setpoints, pb.commands is not None, cmds, pb.mavlink, z,
                xs, uact, upend, cprev, integ, sp, turb, hist, slots, out)
    result = {name: out[s] for s, name in enumerate(kept)}
    if "t_s" in pb.columns:
        result = {"t_s": np.broadcast_to(tt, (n_sims, n_t)), **result}
    return BatchResult(pb.name, result, pb.configs, tuple(int(s) for s in pb.seeds), dict(pb.meta))


def _normals(P: np.ndarray, gens: list[np.random.Generator | None], f0: int, f1: int) -> np.ndarray:
    """Standard normals for frames f0..f1-1, laid out [turb x, turb y, gyro x, y, z, range] per
    frame, drawn from each flight's Generator in the reference simulator's order (frame 0 has no
    turbulence draw: ``Simulator`` samples frame 0 before any ``advance``)."""
    z = np.zeros((P.shape[0], f1 - f0, 6))
    for i, gen in enumerate(gens):
        if gen is None:
            continue
        cols = ([0, 1] if P[i, P_TURB_W] > 0 else []) + ([2, 3, 4] if P[i, P_GYRO_SIGMA] > 0 else []) \
            + ([5] if P[i, P_RANGE_STD] > 0 else [])
        zi = z[i]
        start = f0
        if f0 == 0:
            cols0 = [c for c in cols if c > 1]
            zi[0, cols0] = gen.standard_normal(len(cols0))
            start = 1
        rows = f1 - start
        if rows > 0:
            zi[start - f0:, cols] = gen.standard_normal(rows * len(cols)).reshape(rows, len(cols))
    return z


def demanding_flight(duration_s: float, *, frame_period_s: float = 0.02, seed: int = 1) -> dict[str, np.ndarray]:
    """Schedules of a hard closed-loop flight, the standard workload of the accuracy tests and the
    benchmarks: on each axis a velocity setpoint stepping every 2.5 s among -2..2 m/s (steps of
    up to 4 m/s saturate the 20 deg tilt limit) and an external force stepping every 7 s among
    -4..4 N (the paper's gust), drawn once from a seeded Generator.
    Returns ``{"setpoints": (n_t, 2) m/s, "forces": (n_frames, 2) N}`` for ``simulate_batch``."""
    n_frames = int(round(duration_s / frame_period_s))
    t = np.arange(n_frames + 1) * frame_period_s
    rng = np.random.default_rng(seed)
    levels = rng.choice([-2.0, -1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0], size=(int(duration_s / 2.5) + 2, 2))
    gusts = rng.choice([-4.0, -2.0, 0.0, 2.0, 4.0], size=(int(duration_s / 7.0) + 2, 2))
    setpoints = levels[(t // 2.5).astype(int)]
    forces = gusts[(t[:-1] // 7.0).astype(int)]
    return {"setpoints": setpoints, "forces": forces}


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel with a two-frame flight."""
    simulate_batch(load_config(), 1, duration_s=0.04, columns=("vx_m_s",))


def fly_fast(cfg: Config, scenario: Scenario, *, seed: int = 0, mavlink_quantization: bool = True,
             nodes: int = DEFAULT_NODES) -> Run:
    """``scenarios.fly`` (paper profile) on the fast engine, without the recording: the same
    columns, frame for frame (``mavlink_quantization`` as ``fly``'s MAVLink path), plus the
    scene angles and altitude."""
    res = simulate_batch(cfg, 1, duration_s=scenario.duration_s, setpoints=scenario.setpoint,
                         forces=scenario.force, altitude=scenario.altitude, seeds=seed,
                         turbulence_sigma_n=scenario.turbulence_sigma_n, turbulence_tau_s=scenario.turbulence_tau_s,
                         mavlink_quantization=mavlink_quantization, nodes=nodes, name=scenario.name)
    return res.run(0)


# =============================================================================================
# The fine-step reference, driven directly (no MAVLink encoding): the baseline of the benchmarks


def reference_run(cfg: Config, *, duration_s: float, setpoint: Any = None, force: Any = None,
                  altitude: Callable[[float], float] | None = None, commands: np.ndarray | None = None,
                  turbulence_sigma_n: float = 0.0, turbulence_tau_s: float = 1.0, seed: int = 0,
                  name: str = "reference") -> Run:
    """One flight of ``simvehicle.model.sim.Simulator`` (RK4, ``sim.substeps_per_frame`` per frame)
    closed by ``companion.step.core.CompanionCore``, fed the sensor samples directly (no MAVLink
    quantization). Inputs as in ``simulate_batch`` for one flight; same columns."""
    T = cfg.flow_sensor.frame_period_s
    n_frames = int(round(duration_s / T))
    tt = np.arange(n_frames + 1, dtype=float) * T
    sp_arr = _pairs(setpoint, 1, tt, "setpoint", finite=False)
    if force is None or callable(force):
        force_fn = force if force is not None else (lambda _t: (0.0, 0.0))
    else:
        f_arr = _pairs(force, 1, tt[:-1], "force", finite=True)[0]  # type: ignore[index]

        def force_fn(t: float) -> tuple[float, float]:
            k = min(int(t / T), n_frames - 1)
            return float(f_arr[k, 0]), float(f_arr[k, 1])
    cmd_arr = _pairs(commands, 1, tt, "commands", finite=True)
    rng = np.random.default_rng(seed)
    turb = Turbulence(turbulence_sigma_n, turbulence_tau_s) if turbulence_sigma_n > 0 else None
    sim = Simulator(cfg, rng=rng, external_force=force_fn, altitude=altitude, turbulence=turb)
    core = CompanionCore(cfg)
    q = cfg.flow_sensor.q_rad_per_count
    cols: dict[str, list[float]] = {c: [] for c in COLUMNS}
    s = sim.current
    for k in range(n_frames + 1):
        t = s.t_s
        core.on_gyro(t, s.gyro_x_rad_s, s.gyro_y_rad_s)
        core.on_range(t, s.range_m)
        if sp_arr is not None:
            core.set_setpoint(float(sp_arr[0, k, 0]), float(sp_arr[0, k, 1]))
        out = core.on_flow(FlowColumns(time_s=t, scene_x=s.flow_x_counts * q, scene_y=s.flow_y_counts * q,
                                       increment=True, integration_s=math.nan, quality=s.flow_quality,
                                       counts_x=float(s.flow_x_counts), counts_y=float(s.flow_y_counts)))
        roll, pitch = out.roll_cmd_rad, out.pitch_cmd_rad
        if cmd_arr is not None:
            roll, pitch = float(cmd_arr[0, k, 0]), float(cmd_arr[0, k, 1])
        for c, value in zip(COLUMNS, (t, s.vx_m_s, s.vy_m_s, s.x_m, s.y_m, s.roll_rad, s.pitch_rad,
                                      s.roll_rate_rad_s, s.pitch_rate_rad_s, s.flow_x_counts, s.flow_y_counts,
                                      s.gyro_x_rad_s, s.gyro_y_rad_s, s.range_m, out.vx_m_s, out.vy_m_s,
                                      out.vx_set_m_s, out.vy_set_m_s, roll, pitch, float(out.holding),
                                      s.phi_x_rad, s.phi_y_rad, s.altitude_m), strict=True):
            cols[c].append(value)
        if k < n_frames:
            s = sim.advance(roll, pitch)
    return Run(name, {k: np.asarray(v, dtype=float) for k, v in cols.items()}, meta={"seed": seed,
                                                                                    "engine": "reference"})
