"""When a fitted effect is large enough to matter: one threshold per effect, stated in physics.

A statistically certain effect can still be too small to change anything a user sees or sets:
a 0.03 N wind, a 1 ms delay, a 0.5 % scale. The finder reports an effect only when its size
passes the threshold here as well as the statistical tests (``select``). The thresholds are
about a tenth of what moves a velocity estimate or a held position by a visible amount on a
small multicopter (e.g. 0.1 N tilts a 1 kg vehicle by 0.6 deg; a 1 % flow scale is 1 cm/s at
1 m/s), and they sit below the smallest size a user would correct on a vehicle.

| effect | parameters | too small to matter when |
|---|---|---|
| ``linear_drag`` | ``b`` | b < 0.05 N s/m (0.1 N at 2 m/s) |
| ``quadratic_drag`` | ``c`` | c < 0.025 N s^2/m^2 (0.1 N at 2 m/s) |
| ``wind_force`` | ``fx``, ``fy`` | the force < 0.1 N |
| ``gyro_bias`` | ``bias_x``, ``bias_y`` | both < 0.002 rad/s (0.11 deg/s) |
| ``flow_scale`` | ``scale_x``, ``scale_y`` | both within 1 % of 1 |
| ``flow_delay`` | ``delay`` | under 2 ms |
| ``flow_yaw_misalignment`` | ``yaw`` | under 1 deg |
| ``attitude_dynamics`` | ``omega_p``, ``zeta`` | omega_p within 5 % of the nominal and zeta within 0.05 |
| ``attitude_delay`` | ``delay`` | under 2 ms |
| ``range_offset`` | ``offset`` | under 1 cm |
| ``flow_rotation_gain`` | ``gain`` | within 2 % of 1 |
| ``gyro_lag`` | ``tau`` | under 2 ms |
| ``flow_lever_arm`` | ``rz`` | under 2 cm |

A residual the named effects leave is held to a size too (``misfit_floor``): the headline says
"the model does not fit" only where a stretch's rms is over 3 x its channel's noise *and* over the
channel's floor below. Under the floors a misfit changes nothing a user sees: 1 mrad (0.06 deg) is
under any attitude estimate's own accuracy, 2 mrad/s is the gyro bias threshold above, 0.5 mrad of
flow scene angle is a third of a PMW3901 count, 0.1 N is the wind threshold above. A noise-free
recording has a noise far under any of them, and there the finder's own rebuilding of the rotation
between lost samples stood 6 x over it (0.55 mrad on attitude_roll, seed 15 of the generator with
15 % of its messages lost and no effect).

| channel | too small to say "does not fit" when the stretch's rms is |
|---|---|
| ``attitude_roll``, ``attitude_pitch`` | under 1 mrad |
| ``gyro_x``, ``gyro_y`` | under 2 mrad/s |
| ``flow_x``, ``flow_y`` | under 0.5 mrad |
| ``force_x``, ``force_y`` | under 0.1 N |
"""

from __future__ import annotations

import math
from collections.abc import Callable

Check = Callable[[dict[str, float]], str | None]


def _below(what: str, value: float, limit: float, unit: str) -> str | None:
    if abs(value) < limit:
        return f"too small to matter ({what} {value:.3g} {unit}, under {limit:g} {unit})"
    return None


def threshold(effect: str, nominal: dict[str, float] | None = None) -> Check | None:
    """The size check of ``effect`` (None: no threshold); ``nominal`` holds the nominal values of
    parameters whose threshold is relative (attitude_dynamics: omega_p, zeta)."""
    nom = nominal or {}
    if effect == "linear_drag":
        return lambda p: _below("b", p["b"], 0.05, "N s/m")
    if effect == "quadratic_drag":
        return lambda p: _below("c", p["c"], 0.025, "N s^2/m^2")
    if effect == "wind_force":
        return lambda p: _below("force", math.hypot(p["fx"], p["fy"]), 0.1, "N")
    if effect == "gyro_bias":
        return lambda p: _below("bias", max(abs(p["bias_x"]), abs(p["bias_y"])), 0.002, "rad/s")
    if effect == "flow_scale":
        return lambda p: _below("scale - 1", max(abs(p["scale_x"] - 1), abs(p["scale_y"] - 1)), 0.01, "")
    if effect in ("flow_delay", "attitude_delay"):
        return lambda p: _below("delay", p["delay"], 0.002, "s")
    if effect == "flow_yaw_misalignment":
        return lambda p: _below("yaw", math.degrees(p["yaw"]), 1.0, "deg")
    if effect == "range_offset":
        return lambda p: _below("offset", p["offset"], 0.01, "m")
    if effect == "flow_rotation_gain":
        return lambda p: _below("gain - 1", p["gain"] - 1.0, 0.02, "")
    if effect == "gyro_lag":
        return lambda p: _below("tau", p["tau"], 0.002, "s")
    if effect == "flow_lever_arm":
        return lambda p: _below("rz", p["rz"], 0.02, "m")
    if effect == "attitude_dynamics":
        w0, z0 = nom.get("omega_p", math.nan), nom.get("zeta", math.nan)

        def dyn(p: dict[str, float]) -> str | None:
            rel = abs(p["omega_p"] / w0 - 1.0) if w0 > 0 else math.inf
            if rel < 0.05 and abs(p["zeta"] - z0) < 0.05:
                return (f"too small to matter (omega_p {p['omega_p']:.3g} within 5 % of {w0:g} rad/s, "
                        f"zeta {p['zeta']:.3g} within 0.05 of {z0:g})")
            return None

        return dyn
    return None


#: a channel's misfit floor by the prefix of its name (value, unit)
MISFIT_FLOORS = {"attitude_": (1e-3, "rad"), "gyro_": (2e-3, "rad/s"), "flow_": (5e-4, "rad"), "force_": (0.1, "N")}


def misfit_floor(channel: str) -> tuple[float, str]:
    """The smallest rms of a stretch of ``channel``'s residual that the headline calls a misfit, and
    its unit ((0, "") for a channel not in ``MISFIT_FLOORS``: its noise alone decides)."""
    for prefix, floor in MISFIT_FLOORS.items():
        if channel.startswith(prefix):
            return floor
    return 0.0, ""
