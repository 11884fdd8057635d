"""The one exception type for mistakes a user can make.

Library code raises `UserError` with a one-line message naming the problem and the valid
choices; the CLI turns it into that line on stderr and exit status 2, with no traceback.
"""


class UserError(Exception):
    """A problem with the user's input (arguments, files, data), not a bug."""


class TrainingError(Exception):
    """Training cannot go on (e.g. a non-finite loss); the last good checkpoint is kept. Exit 1."""

    exit_code = 1


class PeerStopped(TrainingError):
    """Another process of a run on several processes stopped first (failed or was interrupted).
    Exit 3, so a launcher can tell this consequence from the cause: the other process's status."""

    exit_code = 3
