"""Errors the engine raises for bad user input.

Every message names the file (or object) at fault and the problem, so the Blender side can
show it verbatim with ``self.report({'ERROR'}, str(err))``.
"""
from __future__ import annotations

from pathlib import Path


class CaptureError(ValueError):
    """A capture folder, one of its files, or a record inside it is unusable."""

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class RunError(ValueError):
    """A run directory (checkpoints, exports) is missing or unusable."""

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")
