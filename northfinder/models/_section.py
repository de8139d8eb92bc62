"""Reading a bench.toml section the same way whether it is a config dataclass or a plain dict."""

from __future__ import annotations

from typing import Any


def value(section: Any, key: str, default: Any) -> Any:
    """`section.key` (or `section[key]`), `default` when absent."""
    if isinstance(section, dict):
        return section.get(key, default)
    return getattr(section, key, default)
