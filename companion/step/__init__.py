"""The control step: estimator (eq. 15), controller (PI), the rules of the step, its scalar and column
forms, the profiles of the flow message; imports nothing first-party above the base modules."""
