"""Tools over the simulator: sweeps, re-flying a recording, plots."""
