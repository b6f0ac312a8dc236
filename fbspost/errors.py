"""The error every reader raises on bad input: one line naming the file and the line."""
from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """Bad input: ``str()`` is ``FILE:LINE: message`` (``FILE: message`` for the whole file)."""

    def __init__(self, path: str | Path, line: int | None, message: str):
        super().__init__(f"{path}:{line}: {message}" if line is not None else f"{path}: {message}")
        self._parts = (path, line, message)

    def __reduce__(self):  # (pickled from the compensation's process: offload.py)
        return type(self), self._parts
