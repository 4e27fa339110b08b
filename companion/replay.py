"""Old path of ``companion.tools.replay``, kept for scripts outside the repository: remove in the next release."""
from companion.tools.replay import *  # noqa: F401,F403
