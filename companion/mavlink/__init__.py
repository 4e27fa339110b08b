"""The MAVLink side: inbound and outbound messages, the link, the pure session (engagement, take-over,
setpoint decay, staleness) and the live loop (socket and clock)."""
