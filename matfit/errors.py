"""The errors a user can fix: one base class, one subclass per kind, each message naming the value and the fix; and
the checks of a value's kind and range that raise them (`whole`, `number`, `flag`, `check_range`).

Library messages speak of values by the names the library uses (`evaluations 5 is out of range`).
An error that concerns one argument carries its library name in `field`; the command line turns
that name into the option the user typed (`--evals 5 is out of range`). Nothing here imports JAX,
Mitsuba or OpenImageIO, so every module, and the command line's start-up, can import it.
"""

from __future__ import annotations

import math
import numbers
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


def shown(value: object) -> str:
    """Returns how an error message names a value: its repr if that is short and one line, else its type."""
    text = repr(value)
    return text if len(text) <= 40 and "\n" not in text else f"of type {type(value).__name__}"


def whole(field: str, value: object, low: int, high: int, error: type[MatfitError]) -> int:
    """Returns `value` as an int: a whole number in [low, high], else `error` naming it and the range."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):  # NumPy's integers are Integral too
        raise error(f"{field} {shown(value)} is not a whole number: use {low} to {high}", field=field)
    check_range(field, int(value), low, high, error)
    return int(value)


def number(
    field: str, value: object, low: float, high: float, error: type[MatfitError], *, above_low: bool = False
) -> float:
    """Returns `value` as a float: a finite number in [low, high] (above `low` with `above_low`), else `error` naming
    it and the range."""
    span = f"above {low:g} up to {high:g}" if above_low else f"{low:g} to {high:g}"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):  # NumPy's floats and integers are Real too
        raise error(f"{field} {shown(value)} is not a number: use {span}", field=field)
    try:
        checked = float(value)
    except OverflowError:  # an int too long for a float
        checked = math.inf
    if not math.isfinite(checked) or not low <= checked <= high or (above_low and checked == low):
        raise error(f"{field} {shown(value)} is out of range: use {span}", field=field)
    return checked


BOOLS = ("bool", "bool_")  # the name of NumPy's bool (2.x, 1.x): checked without importing NumPy here


def flag(field: str, value: object, error: type[MatfitError]) -> bool:
    """Returns `value` as a bool: True or False (NumPy's too), else `error` naming it."""
    if not isinstance(value, bool) and not (type(value).__module__ == "numpy" and type(value).__name__ in BOOLS):
        raise error(f"{field} {shown(value)} is not True or False: give {field}=True or {field}=False", field=field)
    return bool(value)


def printable(path: object) -> str:
    """Returns a path as text that can always be printed: bytes of a name that are not UTF-8 become \\x escapes."""
    return os.fsencode(path).decode("utf-8", "backslashreplace") if isinstance(path, str | bytes) else str(path)
