"""Exception types of bag writing; every message names the bad path or topic."""

from __future__ import annotations

from formation_msgs_py.errors import FormationError


class BagError(FormationError):
    """Base class of the errors the bag packages raise on purpose."""


class BagExistsError(BagError, FileExistsError):
    """An output path exists already; we never overwrite."""

    def __init__(self, path: object, what: str = "output") -> None:
        self.path = path
        super().__init__(f"{what} {path} exists already, not overwriting (choose another path or remove it)")


class BagWriterError(BagError, RuntimeError):
    """Writing a bag failed (closed writer, unknown type, storage error)."""
