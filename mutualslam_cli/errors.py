"""Exception hierarchy: every error a user can cause is an :class:`MslamError`.

The CLI turns an ``MslamError`` into one red line and exit code 1; anything else is a bug
and keeps its traceback.
"""

from __future__ import annotations


class MslamError(Exception):
    """Base class of all errors caused by input or configuration."""


class DatasetError(MslamError):
    """A sequence on disk is missing, malformed or inconsistent.

    The message names the file, the line (when there is one) and the expected format.
    """


class ConfigError(MslamError):
    """A configuration file or ``--set`` override is invalid."""


class TrackingLost(MslamError):
    """The VO front end lost track; the pipeline re-initialises and records a gap."""


class ShapeError(MslamError, ValueError):
    """An array or tensor does not have the documented shape."""
