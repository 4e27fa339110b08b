"""The velocity-setpoint rule the live loop and replay share: a ground station's or stick
setpoint is held for ``companion.setpoint_timeout_s`` after its last refresh, then ramped
linearly back to the base setpoint (``--setpoint``, or zero) over another timeout.

Its own module, below ``companion.mavlink.live`` and ``companion.tools.replay`` (issue 13: replay imported it
from the live loop, sockets and all).
"""

from __future__ import annotations


def decayed_setpoint(setpoint_m_s: tuple[float, float], base_m_s: tuple[float, float], age_s: float,
                     timeout_s: float) -> tuple[float, float]:
    """A GCS/stick setpoint ``age_s`` after its last refresh: held for ``timeout_s``, then a
    linear ramp to ``base_m_s`` that arrives ``2 timeout_s`` after the refresh."""
    if age_s <= timeout_s:
        return setpoint_m_s
    f = max(0.0, 1.0 - (age_s - timeout_s) / timeout_s)
    return (base_m_s[0] + f * (setpoint_m_s[0] - base_m_s[0]), base_m_s[1] + f * (setpoint_m_s[1] - base_m_s[1]))
