"""The one error hierarchy of keyshape.

Every error a user can cause (bad file, bad array, bad option) is a
:class:`KeyshapeError`. The command line prints its message without a
traceback and exits with status 2.
"""
from __future__ import annotations

from pathlib import Path


class KeyshapeError(Exception):
    """Base class of every error keyshape raises on bad input."""


class InputError(KeyshapeError, ValueError):
    """Bad content: a malformed file, an array of the wrong shape, NaNs, bad option.

    Parameters
    ----------
    message : str
        What was expected and what was found.
    path : str or Path, optional
        The file concerned; prefixed to the message.
    line : int, optional
        One-based line number within ``path``.
    """

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.path = None if path is None else Path(path)
        self.line = line
        where = "" if path is None else f"{path}" + ("" if line is None else f", line {line}") + ": "
        super().__init__(where + message)


class MissingFileError(KeyshapeError, FileNotFoundError):
    """A file or folder the user named does not exist."""

    def __init__(self, path: str | Path, what: str = "file"):
        self.path = Path(path)
        super().__init__(f"{path}: {what} not found")


def require_file(path: str | Path, what: str = "file") -> Path:
    """Return ``Path(path)`` or raise :class:`MissingFileError` naming it."""
    p = Path(path)
    if not p.is_file():
        if p.is_dir():
            raise InputError(f"is a folder; a {what} was expected", p)
        raise MissingFileError(p, what)
    return p


def require_dir(path: str | Path, what: str = "folder") -> Path:
    """Return ``Path(path)`` or raise :class:`MissingFileError` naming it."""
    p = Path(path)
    if not p.is_dir():
        if p.exists():
            raise InputError(f"is a file; a {what} was expected", p)
        raise MissingFileError(p, what)
    return p


class NotFittedError(KeyshapeError, ValueError):
    """An estimator was used before ``fit`` (the one "not fitted" error of every estimator)."""
