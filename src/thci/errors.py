"""User-facing errors.

Every mistake a user can make (unknown environment id, bad hyperparameter, corrupt checkpoint,
...) raises :class:`ThciError` with a one-line message that says what is wrong and how to fix
it. The CLI prints that line and exits with status 2 instead of showing a traceback.
"""


class ThciError(Exception):
    """A problem caused by the user's input, with a one-line explanation and fix."""
