"""``python -m companion diagnose``: the closed-loop diagnosis; the command is
``companion.diagnose.closed_loop.command``."""
