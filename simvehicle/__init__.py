"""Simulated vehicle: the paper's plant (eq. 26-28), flow-sensor truth model (eq. 9-11), IMU,
rangefinder and optional effects, with scenarios and a MAVLink/UDP front end."""
