"""Old path of ``simvehicle.model.sim``, kept for scripts outside the repository; to be removed in the next release."""
from simvehicle.model.sim import *  # noqa: F401,F403
