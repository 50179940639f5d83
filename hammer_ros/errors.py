"""Exceptions that carry a one-line, user-facing reason.

The CLI turns these into exit code 2 and a single line on stderr; the node turns them into
a diagnostics message. Anything else that escapes is a bug in hammer_ros.
"""


class HammerRosError(ValueError):
    """Base class: the message names the offending file, field, topic or option."""


class UsageError(HammerRosError):
    """A bad command-line option, file, column or configuration."""


class IdentificationError(HammerRosError):
    """The data cannot identify the requested model (e.g. an empty partition interval,
    an input that is not persistently exciting)."""
