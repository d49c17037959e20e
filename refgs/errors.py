"""Errors raised on bad input: one line naming the file or flag and what was expected.

All derive from ``ValueError`` (house rule: bad input raises ``ValueError`` or a subclass), so a
caller can catch :class:`RefgsError` to turn any of them into a one-line CLI message.
"""
from __future__ import annotations


class RefgsError(ValueError):
    """Base class of refgs' input errors."""


class SceneError(RefgsError):
    """A scene on disk is missing, unreadable or unsupported; the message names the file."""


class ConfigError(RefgsError):
    """A configuration value or command-line flag is invalid; the message names the flag."""


__all__ = ["RefgsError", "SceneError", "ConfigError"]
