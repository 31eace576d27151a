"""The errors a user can fix: one base class, one subclass per kind, each message naming the value and the fix.

Library messages speak of values by the names the library uses (`evaluations 5 is out of range`).
An error that concerns one argument carries its library name in `field`; the command line turns
that name into the option the user typed (`--evals 5 is out of range`). Nothing here imports JAX,
Mitsuba or OpenImageIO, so every module, and the command line's start-up, can import it.
"""

from __future__ import annotations

import os


class MatfitError(ValueError):
    """A failure the user can fix; the command line prints it as one `error:` line and exits with 2."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.field = field


class ParameterError(MatfitError):
    """A parameter name or value that the shader cannot take."""


class RenderError(MatfitError):
    """Rendering cannot proceed (variant, libLLVM, material vector)."""


class OutputError(MatfitError):
    """An output path cannot be written."""


class ImageError(OutputError):
    """An image cannot be read or written."""


class DatasetError(MatfitError):
    """A dataset cannot be created, extended or read."""


class TrainingError(MatfitError):
    """Training cannot start or resume."""


class WeightsError(MatfitError):
    """A weights or checkpoint file that cannot be used."""


class FitError(MatfitError):
    """Fit settings or inputs that cannot work."""


class SequenceError(MatfitError):
    """A frames folder or sequence output that cannot be used."""


class SceneError(MatfitError):
    """A scene file of the user's own, or the shape named in it, that cannot be used."""


def check_range(
    field: str, value: int | float, low: int | float, high: int | float, error: type[MatfitError] = MatfitError
) -> None:
    """Raises `error` (naming `field`) unless low <= value <= high."""
    if not low <= value <= high:
        raise error(f"{field} {value} is out of range: use {low} to {high}", field=field)


def printable(path: object) -> str:
    """Returns a path as text that can always be printed: bytes of a name that are not UTF-8 become \\x escapes."""
    return os.fsencode(path).decode("utf-8", "backslashreplace") if isinstance(path, str | bytes) else str(path)
