"""Exceptions raised by dhptam.

Every error dhptam raises on purpose derives from :class:`DhptamError`; each subclass also
derives from the matching built-in exception, so ``except ValueError`` keeps working.
Instances carry the facts a user needs to fix the input:

``field``
    the argument or key that was wrong (``None`` when not applicable),
``path``
    the file concerned,
``line``
    the 1-based line of that file.
"""

from __future__ import annotations


class DhptamError(Exception):
    """Base class of every error dhptam raises on purpose."""

    field: str | None = None
    path: str | None = None
    line: int | None = None

    def __init__(
        self,
        message: str,
        *,
        field: str | None = None,
        path: str | None = None,
        line: int | None = None,
    ) -> None:
        super().__init__(message)
        self.field = field
        self.path = path
        self.line = line


class InputError(DhptamError, ValueError):
    """An argument or a value read from a file does not meet the documented expectation."""


class ParseError(InputError):
    """A text file could not be parsed; ``path`` and ``line`` say where."""


class ConfigError(DhptamError, ValueError):
    """A configuration file or value is invalid (unknown key, wrong type, out of range)."""


class FileError(DhptamError, OSError):
    """A file could not be read or written."""


class NumericalError(DhptamError, ArithmeticError):
    """A numerical procedure failed on valid input (degenerate geometry, no convergence)."""


class MissingDependencyError(DhptamError, ImportError):
    """An optional dependency is not installed; the message says which extra to install."""


class InternalError(DhptamError, RuntimeError):
    """A bug in dhptam: the Rust core panicked. The binding catches the panic at the boundary
    and raises this instead of PyO3's ``PanicException`` (a ``BaseException``)."""


__all__ = [
    "ConfigError",
    "DhptamError",
    "FileError",
    "InputError",
    "InternalError",
    "MissingDependencyError",
    "NumericalError",
    "ParseError",
]
