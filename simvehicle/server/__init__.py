"""The MAVLink/UDP front end of the simulated vehicle: the server, its telemetry, the parameter flights."""
