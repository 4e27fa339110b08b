"""Old path of ``companion.recordings.load``, kept for scripts outside the repository: remove in the next release."""
from companion.recordings.load import *  # noqa: F401,F403
