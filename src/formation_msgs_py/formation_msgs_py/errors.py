"""Exception types of the formation packages."""

from __future__ import annotations

from typing import Any


class FormationError(Exception):
    """Base class of every error this project raises on purpose."""


class FormationSpecError(FormationError, ValueError):
    """A formation file is invalid; ``path`` names the field (``edges[2].distance``)."""

    def __init__(self, path: str, message: str, value: Any = None) -> None:
        self.path = path
        self.value = value
        super().__init__(f"{path}: {message}" if path else message)


class RotationError(FormationError, ValueError):
    """A matrix that should be a rotation is not one (or has the wrong shape)."""
