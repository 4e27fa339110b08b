"""Sensor-only diagnosis of a recording with no commands; the parts are one module each, and
``companion.diagnose.sensor.api`` re-exports their public names."""
