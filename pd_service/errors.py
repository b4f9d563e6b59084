"""Errors shared by every executable."""

from __future__ import annotations


class ConfigError(ValueError):
    """Settings or a configuration file that cannot be used; the message names the field and
    where it came from. Executables exit with status 2 on it."""
