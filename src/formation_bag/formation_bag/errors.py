"""Exception types of reading and analysing bags; every message names the bad path, topic or field.

Writing's (``BagError``, ``BagExistsError``, ``BagWriterError``) are :mod:`formation_msgs_py.bag.errors`.
"""

from __future__ import annotations

from formation_msgs_py.bag.errors import BagError


class BagNotFoundError(BagError, FileNotFoundError):
    """A bag path does not exist or holds no readable storage file."""


class BagFormatError(BagError, ValueError):
    """A bag, a segment file or its metadata.yaml is malformed."""


class BagTopicError(BagError, KeyError):
    """A topic the command needs is missing from the bag, or a topic option is malformed."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class OverrideError(BagError, ValueError):
    """An override file for the controller re-run is invalid; ``path`` names the field."""

    def __init__(self, path: str, message: str) -> None:
        self.path = path
        super().__init__(f"{path}: {message}" if path else message)
