"""Logging set-up shared by the library and the CLI.

Records from the Rust core arrive in Python's :mod:`logging` under the logger
``dhptam_core`` (and its children, named after the Rust modules); records from the Python
side use ``dhptam``. :func:`configure` sets both from, in order of precedence, the
``DHPTAM_LOG`` environment variable, an explicit level, or the ``[log]`` section of a
:class:`dhptam.Config`.
"""

from __future__ import annotations

import logging
import os

from . import _core
from .errors import ConfigError

LEVELS = {
    "error": logging.ERROR,
    "warn": logging.WARNING,
    "warning": logging.WARNING,
    "info": logging.INFO,
    "debug": logging.DEBUG,
    # Python has no TRACE level; NOTSET-adjacent 5 keeps trace records distinct from debug.
    "trace": 5,
}
ENV_VAR = "DHPTAM_LOG"
LOGGER_NAMES = ("dhptam", "dhptam_core")


def resolve_level(level: str | None = None, config: _core.Config | None = None) -> int:
    """The numeric level: ``$DHPTAM_LOG`` if set, else ``level``, else the config's, else info."""
    name = os.environ.get(ENV_VAR) or level
    origin = f"environment variable {ENV_VAR}" if os.environ.get(ENV_VAR) else "level"
    if name is None and config is not None:
        name = config.to_dict()["log"]["level"]
        origin = "config [log] level"
    if name is None:
        return logging.INFO
    try:
        return LEVELS[name.strip().lower()]
    except KeyError:
        raise ConfigError(
            f"{origin}: expected one of {', '.join(sorted(LEVELS))}, got {name!r}", field=origin
        ) from None


def configure(
    level: str | None = None,
    config: _core.Config | None = None,
    *,
    handler: logging.Handler | None = None,
) -> int:
    """Set the level of the dhptam loggers (Python and Rust) and return it.

    A handler writing to stderr is attached to the ``dhptam`` and ``dhptam_core`` loggers
    unless one was attached before or ``handler`` is given.
    """
    numeric = resolve_level(level, config)
    for name in LOGGER_NAMES:
        logger = logging.getLogger(name)
        logger.setLevel(numeric)
        if handler is not None:
            logger.addHandler(handler)
        elif not any(getattr(h, "_dhptam", False) for h in logger.handlers):
            stream = logging.StreamHandler()
            stream.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
            stream._dhptam = True  # type: ignore[attr-defined]
            logger.addHandler(stream)
    # The Rust side caches logger levels; make it read them again.
    _core._reset_log_cache()
    return numeric
