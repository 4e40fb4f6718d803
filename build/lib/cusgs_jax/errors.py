"""Errors a user can fix: each message names the file or option at fault and says what to do.

The command-line tools turn every :class:`UserError` into one line on stderr and
exit code 2 (:func:`cusgs_jax.app.errors.exit_on_user_error`); anything else is
a bug and keeps its traceback.
"""

from __future__ import annotations

__all__ = ["UserError", "ConfigError", "CheckpointError"]


class UserError(ValueError):
    """A problem with the user's input or settings; the message says how to fix it."""


class ConfigError(UserError):
    """A setting that cannot mean anything useful (named as ``group.option`` in the message)."""


class CheckpointError(UserError):
    """A checkpoint that cannot be written or restored (folder named in the message)."""
