"""One sentence of physics per effect, from its fitted parameters (CONVENTIONS.md names)."""

from __future__ import annotations

import math

from companion.config import Config
from companion.diagnose.closed_loop.attitude import OMEGA_P_MAX_RAD_S


def explain(effect: str, p: dict[str, float], cfg: Config, significant: bool, sd: dict[str, float]) -> str:
    """The finding's explanation: what the physics is and what the numbers say."""
    if not significant:
        return tried(effect, p, sd)
    a = cfg.airframe
    if effect == "linear_drag":
        b = p["b"]
        return (f"The air resists horizontal motion with a force of {b:.2f} N per m/s that eq. 28 leaves out, so "
                f"holding a speed takes more tilt than the model predicts (at 1 m/s "
                f"{math.degrees(math.atan(b / (a.mass_kg * a.gravity_m_s2))):.1f} deg more); the PI integrator hides "
                f"it in the velocity but not in the force balance.")
    if effect == "gyro_bias":
        return (f"The roll- and pitch-rate gyros read {1e3 * p['bias_x']:+.1f} and {1e3 * p['bias_y']:+.1f} mrad/s "
                f"more than the rate at which the attitude turns, a constant bias that eq. 15 turns into a velocity "
                f"error of bias x height (the closed loop then flies at that error).")
    if effect == "flow_scale":
        return (f"One flow count is {p['scale_x']:.3f} (x) and {p['scale_y']:.3f} (y) times the nominal Q, so the "
                f"sensor sees both rotation and motion scaled by 1/scale (lens focus, surface texture) and the "
                f"flow velocity is off by that factor.")
    if effect == "flow_delay":
        d = 1e3 * p["delay"]
        if d < 0:
            return (f"The flow frames lead the attitude by {-d:.1f} ms (the model expects them in step), as when a "
                    f"flow rate is sampled at the end of its frame rather than averaged over it, so the rotation is "
                    f"subtracted early and leaks into the velocity as height x delay x angular acceleration.")
        return (f"The flow frames lag the attitude by {d:.0f} ms more than the model assumes, so the rotation is "
                f"subtracted at the wrong moment and leaks into the velocity as height x delay x angular "
                f"acceleration.")
    if effect == "flow_yaw_misalignment":
        return (f"The flow sensor's axes are turned {math.degrees(p['yaw']):+.1f} deg about z from the body axes, so "
                f"each flow axis picks up the other axis' rotation and motion.")
    if effect == "flow_rotation_gain":
        return (f"The flow sees {p['gain']:.3f} times the rotation the attitude shows while its translation is "
                f"not scaled (a sensor that rotates on its mount, or flow rates sampled at instants rather than "
                f"averaged over the frame), so rotation leaks into the flow velocity.")
    if effect == "attitude_dynamics":
        w, z = p["omega_p"], p["zeta"]
        if w >= OMEGA_P_MAX_RAD_S * (1.0 - 1e-6):
            return (f"The attitude follows the recorded command within about a frame: Omega_p at least "
                    f"{OMEGA_P_MAX_RAD_S:g} rad/s, the fastest these frames resolve (zeta {z:.2f}), against "
                    f"the model's {a.omega_p_rad_s:g} rad/s. Eq. 26 describes the loop from a companion's command; "
                    f"a command followed this fast is more likely the autopilot's own attitude target after its "
                    f"input shaping (ArduPilot's ATTITUDE_TARGET, PX4's attitude setpoint), whose shaping the "
                    f"recording does not show.")
        speed = "faster" if w > a.omega_p_rad_s else "slower"
        damp = "better damped" if z > a.zeta else "less damped"
        return (f"The attitude loop answers a command like a second-order system with Omega_p = {w:.2f} rad/s and "
                f"zeta = {z:.2f} instead of {a.omega_p_rad_s:g} and {a.zeta:g}: {speed} and {damp} than "
                f"eq. 26 assumes.")
    if effect == "attitude_delay":
        d = p["delay"]
        when = "later" if d > 0 else "earlier"
        return (f"The attitude starts to follow a command {abs(1e3 * d):.0f} ms {when} than the model's one-frame "
                f"latency (transport or scheduling delay in the attitude loop).")
    if effect == "range_offset":
        return (f"The rangefinder reads {100 * p['offset']:+.1f} cm more than the height the flow sensor sees, so "
                f"the flow velocity (flow rate x range) is scaled by (h + offset) / h, most at low height.")
    if effect == "quadratic_drag":
        c = p["c"]
        return (f"The air resists horizontal motion with a form drag of {c:.2f} N per (m/s)^2 that eq. 28 leaves "
                f"out (at 1 m/s {c:.2f} N, at 2 m/s {4 * c:.2f} N), growing with the square of the speed; the "
                f"PI integrator hides it in the velocity but not in the force balance.")
    if effect == "flow_lever_arm":
        rz = p["rz"]
        return (f"The flow sensor sits {abs(rz) * 100:.1f} cm {'below' if rz > 0 else 'above'} the centre of "
                f"gravity: it moves with the body rate times that arm, which the flow reads as rotation scaled "
                f"by (1 + rz / height), most at low height (rx, ry only show with yaw rate and are not fitted).")
    if effect == "gyro_lag":
        tau = p["tau"]
        return (f"The gyro the companion reads is low-pass filtered with a time constant of {tau * 1000:.1f} ms "
                f"(the autopilot's gyro filter): eq. 15 subtracts a late body rate, which leaks into the velocity "
                f"as height x {tau * 1000:.0f} ms x angular acceleration.")
    if effect == "wind_force":
        fx, fy = p["fx"], p["fy"]
        return (f"An external horizontal force of {math.hypot(fx, fy):.2f} N (fx {fx:+.2f}, fy {fy:+.2f} N, body "
                f"axes) acted from {p['start_s']:.1f} s to {p['end_s']:.1f} s; the vehicle held its velocity by "
                f"tilting against it, so only the force balance shows it.")
    return f"{effect}: " + ", ".join(f"{k} = {v:.4g}" for k, v in p.items())


_WHAT = {
    "linear_drag": "a horizontal drag -b v",
    "gyro_bias": "a constant gyro bias",
    "flow_scale": "a flow scale error",
    "flow_delay": "a flow delay",
    "flow_yaw_misalignment": "a turn of the flow sensor about z",
    "flow_rotation_gain": "a rotation-only gain of the flow",
    "attitude_dynamics": "a different attitude-loop Omega_p and zeta",
    "attitude_delay": "an attitude-loop delay",
    "range_offset": "a rangefinder offset",
    "wind_force": "an external force over a time window",
}


def tried(effect: str, p: dict[str, float], sd: dict[str, float]) -> str:
    """Sentence for an effect that was tried and not found."""
    vals = ", ".join(f"{k} = {v:.4g} +- {sd.get(k, float('nan')):.2g}" for k, v in p.items())
    return f"Tried {_WHAT.get(effect, effect)}: fitted {vals}, which does not earn its parameters on held-out data."
