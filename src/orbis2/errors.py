"""The one exception family for problems a user can fix (bad input, missing files, bad params).

Stages catch it, print its message (which names the file and the fix) and exit
with status 2 instead of a stack trace; anything else is a bug and keeps its trace.
"""


class OrbisError(ValueError):
    """A user-fixable problem; the message names the file or key and the fix."""


class ConfigError(OrbisError):
    """A params.yaml value (or a model size) is missing, unknown, mistyped or impossible."""
