"""The one exception type for mistakes a user can make.

Library code raises `UserError` with a one-line message naming the problem and the valid
choices; the CLI turns it into that line on stderr and exit status 2, with no traceback.
"""


class UserError(Exception):
    """A problem with the user's input (arguments, files, data), not a bug."""


class TrainingError(Exception):
    """Training cannot go on (e.g. a non-finite loss); the last good checkpoint is kept."""
