"""The simulated vehicle's models: plant (eq. 26-28), flow sensor (eq. 9-11), IMU, rangefinder, and the
simulator that steps them."""
