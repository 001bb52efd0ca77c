"""Exception types of the formation packages."""

from __future__ import annotations

from typing import Any

#: At most this many errors of one formation file are shown (all are counted).
MAX_ERRORS_SHOWN = 20


class FormationError(Exception):
    """Base class of every error this project raises on purpose."""


class FormationSpecError(FormationError, ValueError):
    """A formation file is invalid; ``path`` names the field (``edges[2].distance``).

    ``location`` is ``FILE:LINE:COL`` of the offending YAML node once the loader knows it.
    ``elements``: when the value was set under ``defaults`` (``path`` names it there), each agent or
    edge that breaks the check with it, as [label, path, location] (``edges[0] (1, 2)``,
    ``edges[0]``, its ``FILE:LINE:COL`` once the loader knows it).
    """

    def __init__(self, path: str, message: str, value: Any = None) -> None:
        self.path = path
        self.message = message
        self.value = value
        self.location = ""
        self.elements: list[list[str]] = []
        super().__init__(path, message)

    def __str__(self) -> str:
        text = f"{self.path}: {self.message}" if self.path else self.message
        if self.elements:
            text += "; broken by " + ", ".join(
                f"{label} at {where}" if where else label for label, _, where in self.elements
            )
        return f"{self.location}: {text}" if self.location else text


class CollectedFormationSpecError(FormationSpecError):
    """Every error found in one formation file (``errors``, in file order); behaves as the first."""

    def __init__(self, errors: list[FormationSpecError]) -> None:
        flat = [x for e in errors for x in each_error(e)]
        self.errors: list[FormationSpecError] = flat
        first = flat[0]
        super().__init__(first.path, first.message, first.value)

    @property
    def location(self) -> str:
        return self.errors[0].location

    @location.setter
    def location(self, value: str) -> None:
        pass  # each error carries its own

    def __str__(self) -> str:
        lines = [str(e) for e in self.errors[:MAX_ERRORS_SHOWN]]
        if len(self.errors) > MAX_ERRORS_SHOWN:
            lines.append(f"… and {len(self.errors) - MAX_ERRORS_SHOWN} more errors")
        return "\n".join(lines)


def each_error(error: FormationSpecError) -> list[FormationSpecError]:
    """The errors ``error`` stands for: its ``errors`` if it collects several, else itself."""
    return error.errors if isinstance(error, CollectedFormationSpecError) else [error]


def one_error(errors: list[FormationSpecError]) -> FormationSpecError:
    """``errors`` (at least one) as one exception: the error itself, or a CollectedFormationSpecError."""
    return errors[0] if len(errors) == 1 else CollectedFormationSpecError(errors)


class RotationError(FormationError, ValueError):
    """A matrix that should be a rotation is not one (or has the wrong shape)."""


class CalibrationError(FormationError, ValueError):
    """A host's capacity calibration (formation-check --calibrate) that cannot be read or used."""


# --- bags: writing and reading (formation_bag), analysing (formation_sim.offline) ---


class BagError(FormationError):
    """Base class of the errors the bag packages raise on purpose."""


class BagExistsError(BagError, FileExistsError):
    """An output path exists already; we never overwrite."""

    def __init__(self, path: object, what: str = "output") -> None:
        self.path = path
        super().__init__(f"{what} {path} exists already, not overwriting (choose another path or remove it)")


class BagWriterError(BagError, RuntimeError):
    """Writing a bag failed (closed writer, unknown type, storage error)."""


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
