"""The application's one error type for mistakes a user can fix.

Public names: UserError.
"""

from __future__ import annotations

__all__ = ["UserError"]


class UserError(ValueError):
    """An error the user can fix (a bad option, an output folder in the way); the command line
    prints it as one line and exits with status 2, like every ``ValueError`` of bad input."""
