"""The error a user's input raises: one sentence naming the field, the value and what is accepted."""

from __future__ import annotations


class ConfigError(Exception):
    """A user's config (or the file holding it) is wrong; the message says what and how to fix it."""
