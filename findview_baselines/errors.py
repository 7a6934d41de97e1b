"""The baselines' own exception types for the tools' exit statuses, defined in the bottom layer so that
every layer (``rl``, ``agents``, ``evaluation``, ``training``) can raise them without importing the tools'
layer (``cli``). ``cli.USER_ERRORS`` lists every type printed as one line with exit status 2."""

from __future__ import annotations

__all__ = ["UserError", "Interrupted"]


class UserError(Exception):
    """A problem the user caused and can fix (bad value, missing file, unwritable folder, ...): the tools
    print the message as one line and exit with status 2. The message names the file or value and the
    way out."""


class Interrupted(Exception):
    """A run stopped cleanly on a signal (its resume state written); ``signum`` decides the exit status."""

    def __init__(self, signum: int, message: str) -> None:
        super().__init__(message)
        self.signum = int(signum)
