"""Editing a :class:`dhptam.Config`: the Rust configuration has no setters, so a value is
replaced in its TOML text and the result parsed (and checked) again."""

from __future__ import annotations

import json
import re

from . import _core
from .errors import InputError


def with_setting(
    config: _core.Config, section: str, key: str, value: str | float | bool | list[float]
) -> _core.Config:
    """``config`` with ``[section] key`` set to ``value`` (a key the configuration has)."""
    text = config.to_toml()
    start = text.find(f"[{section}]\n")
    while start > 0 and text[start - 1] != "\n":
        start = text.find(f"[{section}]\n", start + 1)
    if start < 0:
        raise InputError(f"the configuration has no [{section}] section", field=section)
    end = text.find("\n[", start)
    end = len(text) if end < 0 else end
    if isinstance(value, bool):
        literal = "true" if value else "false"
    elif isinstance(value, str):
        literal = json.dumps(value)  # a TOML basic string: quotes and backslashes escaped
    else:
        literal = repr(value)
    line = re.compile(rf"(?m)^{re.escape(key)} = .*$")
    block, found = line.subn(lambda _: f"{key} = {literal}", text[start:end], count=1)
    if not found:
        raise InputError(f"the configuration has no {section}.{key}", field=f"{section}.{key}")
    return _core.Config.from_toml(text[:start] + block + text[end:], "<dhptam>")
