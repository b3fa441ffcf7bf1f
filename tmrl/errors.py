"""Exceptions for user mistakes.

Every user mistake (a config key, a password, a port, a missing plugin, mismatched spaces) raises a
:class:`UserError` whose message is one line naming the cause and the fix. The CLI prints that line
and exits with code 2; any other exception is a bug and keeps its traceback.
"""

from __future__ import annotations


class UserError(Exception):
    """A mistake the user can fix; ``str(err)`` is one line saying what to change."""

    exit_code = 2
