"""The control step's rules, each written once for one frame and for whole columns alike (issue 13).

Every function here takes Python floats, numpy scalars or equal-length arrays and uses only
operators (``+ - * <= & | ==``), ``abs`` and numpy ufuncs that take scalars, so one definition
serves the live loop's per-frame step (``companion.step.core.CompanionCore``, the scenarios),
replay's column form (``core.gate_frames``, ``core.repeat_mask``, ``core.plausibility_columns``,
...) and, compiled by numba, the fast simulator's kernel (``simvehicle.engines.fastsim``). On arrays the
caller holds the ``np.errstate``. Where a rule has state across frames (the PI integral, the
tilt filter, the cross-frame checks) the state lives in ``core``; the rule it applies at each
frame is here.

Booleans: comparisons give ``bool`` on floats and boolean arrays on arrays; they are combined
with ``&`` and ``|`` and negated with ``== False`` (``not`` and ``~`` differ between the two
shapes); each function says what NaN gives.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: a flow time this much (s) before the last frame's means the vehicle rebooted (a new frame)
FRAME_REBOOT_S = 1.0
#: a frame spacing beyond this many nominal frames is a gap: the nominal period is used instead
MAX_SPACING_FRAMES = 5.0


def select(condition: Any, if_true: Any, if_false: Any) -> Any:
    """``np.where`` over columns; on one frame (a bool condition) the value chosen, without the
    few microseconds ``np.where`` takes on scalars."""
    if isinstance(condition, (bool, np.bool_)):
        return if_true if condition else if_false
    return np.where(condition, if_true, if_false)


# -- per-frame gates (core.GATE_CAUSES: the order in which they are checked) ---------------------


def flow_invalid(time_s: Any, scene_x: Any, scene_y: Any) -> Any:
    """The flow or its time is not a finite number (``HoldCause.FLOW_INVALID``)."""
    return (np.isfinite(scene_x) & np.isfinite(scene_y) & np.isfinite(time_s)) == False  # noqa: E712 (arrays too)


def quality_zero(quality: Any) -> Any:
    """Quality 0 (``int(quality) == 0``), or not a number (``HoldCause.FLOW_QUALITY``)."""
    return (abs(quality) >= 1.0) == False  # noqa: E712


def gyro_invalid(gyro_x_rad_s: Any, gyro_y_rad_s: Any, limit_rad_s: float) -> Any:
    """A gyro rate not finite or at the sensor's limit (saturated) (``HoldCause.GYRO_INVALID``)."""
    ok = np.isfinite(gyro_x_rad_s) & np.isfinite(gyro_y_rad_s)
    return (ok == False) | (abs(gyro_x_rad_s) >= limit_rad_s) | (abs(gyro_y_rad_s) >= limit_rad_s)  # noqa: E712


def range_invalid(range_m: Any, min_m: float, max_m: float) -> Any:
    """A range not finite or outside the sensor's limits (``HoldCause.RANGE_INVALID``)."""
    return (np.isfinite(range_m) & (range_m >= min_m) & (range_m <= max_m)) == False  # noqa: E712


def range_stale(time_s: Any, range_time_s: Any, timeout_s: float) -> Any:
    """The latest range reading is older than the timeout at the frame (NaN: not stale)."""
    return time_s - range_time_s > timeout_s


def scene_spike(rate_x_rad_s: Any, rate_y_rad_s: Any, max_rate_rad_s: float) -> Any:
    """More scene rate in one frame than the sensor can see (``HoldCause.FLOW_SPIKE``; NaN: no)."""
    return np.maximum(abs(rate_x_rad_s), abs(rate_y_rad_s)) > max_rate_rad_s


# -- eq. 15's inputs ------------------------------------------------------------------------------


def spacing(dt_s: Any, nominal_s: float) -> Any:
    """The time a frame's flow covers from the time since the previous frame ``dt_s``: itself
    when plausible (0 < dt <= ``MAX_SPACING_FRAMES`` frames), else the nominal period (NaN: nominal)."""
    return select((dt_s > 0.0) & (dt_s <= MAX_SPACING_FRAMES * nominal_s), dt_s, nominal_s)


def covered_span(integration_s: Any, frame_dt_s: Any) -> Any:
    """The time a frame's flow covers (s): the integration time its message states (finite and
    > 0), else the frame spacing ``frame_dt_s``."""
    return select(np.isfinite(integration_s) & (integration_s > 0.0), integration_s, frame_dt_s)


def clip_speed(v_m_s: Any, max_m_s: float) -> Any:
    """A velocity setpoint clipped to +-``max_m_s`` on its axis."""
    return np.minimum(np.maximum(v_m_s, -max_m_s), max_m_s)


# -- repeated and out-of-order frames -------------------------------------------------------------


def same_value(a: Any, b: Any) -> Any:
    """Equal, NaN equal to NaN (a payload field of a repeated sample)."""
    return (a == b) | ((a != a) & (b != b))


def duplicate_time(dt_s: Any, reboot_jump_s: float = FRAME_REBOOT_S) -> Any:
    """A frame ``dt_s`` after the last one is not after it, by at most ``reboot_jump_s`` (more
    is a reboot: a new frame); NaN: no."""
    return (dt_s <= 0.0) & (dt_s >= -reboot_jump_s)


def repeat_window(integration_s: Any, nominal_window_s: float, frames: float) -> Any:
    """The window within which the same payload again is the same sample: ``frames`` of the
    reading's own span when the message states one (finite, > 0), else the nominal window."""
    own = np.isfinite(integration_s) & (integration_s > 0.0)
    return select(own, frames * integration_s, nominal_window_s)


def is_repeat(dt_s: Any, same_payload: Any, window_s: Any) -> Any:
    """A flow message ``dt_s`` after the last frame stepped is not a new frame: the same payload
    within the repeat window (``0 <= dt < window``), or a time not after the last frame's."""
    return (same_payload & (dt_s >= 0.0) & (dt_s < window_s)) | duplicate_time(dt_s)


# -- the gyro sample aligned with a frame ---------------------------------------------------------


def gyro_scan(sample_time_s: Any, frame_time_s: Any, best_skew_s: Any, max_skew_s: float) -> tuple[Any, Any, Any]:
    """One step of the scan from the newest gyro sample back: (skew s, take, stop). A sample is
    taken when it is at least as near the frame as the best so far (so ties go to the older one);
    the scan stops at the first sample not taken that is older than the frame by more than
    ``max_skew_s``. NaN times: neither."""
    skew = abs(sample_time_s - frame_time_s)
    take = skew <= best_skew_s
    stop = (skew > best_skew_s) & (sample_time_s < frame_time_s - max_skew_s)
    return skew, take, stop


# -- across frames (core.Plausibility) -------------------------------------------------------------


def jump_allowance(max_accel_m_s2: float, noise_rad_s: float, dt_s: Any, range_m: Any, anchor_range_m: Any) -> Any:
    """How far eq. 15's estimate may move from the anchor's in ``dt_s``: what the vehicle can
    accelerate plus the flow noise at the lower of the two ranges (m/s)."""
    return max_accel_m_s2 * dt_s + noise_rad_s * np.minimum(range_m, anchor_range_m)


def velocity_jump(dvx_m_s: Any, dvy_m_s: Any, allowed_m_s: Any) -> Any:
    """The estimate moved further than allowed on either axis (NaN: no)."""
    return np.maximum(abs(dvx_m_s), abs(dvy_m_s)) > allowed_m_s


def flow_rotation(gyro_x_rad_s: Any, gyro_y_rad_s: Any) -> tuple[Any, Any]:
    """The rotation part of eq. 15 on each axis (x: ``-omega_y``, y: ``+omega_x``), rad/s."""
    return -gyro_y_rad_s, gyro_x_rad_s


def rotating(span_x_rad_s: Any, span_y_rad_s: Any, threshold_rad_s: float) -> Any:
    """A rate spanning more than the threshold on either axis across the window: the vehicle
    turned enough that a working sensor would have changed (NaN: no)."""
    return np.maximum(span_x_rad_s, span_y_rad_s) > threshold_rad_s


# -- the sequential part (core.control_step, core.run_control) ------------------------------------


def control_action(usable: Any, engaged: Any) -> tuple[Any, Any]:
    """What a frame does to the PI integrals and the tilt filter: (step, reset). Usable and
    engaged: step them. Not engaged: reset them (control restarts afresh at the next take-over).
    Engaged but held: neither, the integrals frozen (and the filter restarts at the next usable
    frame)."""
    return usable & engaged, engaged == False  # noqa: E712


def disengaged(usable: Any, engaged: Any) -> Any:
    """A frame the step would have used while the vehicle is not in the companion's mode: it is
    labelled DISENGAGED (no other cause held it)."""
    return usable & (engaged == False)  # noqa: E712
