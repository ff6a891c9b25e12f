"""The configuration's error and the finiteness check its validators share."""

from __future__ import annotations

__all__ = ["ConfigError", "finite"]


class ConfigError(ValueError):
    """A bad configuration value or key (the message names the key)."""


def finite(x: float) -> bool:
    """Neither NaN nor infinite."""
    return x == x and abs(x) != float("inf")
