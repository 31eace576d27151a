"""The params.json a fit job wrote in its own folder, read and checked in Blender's Python (no numpy, no matfit).

The extension never runs a script: it builds the material from these values through
blender_mapping.to_blender, the table the export writes with. A file that is missing, not a regular
file, larger than a params.json can be, not JSON, or holding a value that is not one of matfit's
parameters in its range is one line (`FitError`), and the material is left as it was; a stage's answer
from the worker (its params.json document) is checked the same way (`values`).
"""

import errno
import json
import math
import os
import stat

LIMIT = 1 << 20  # bytes: a params.json is a few KB
FIX = "set the matfit command to matfit's own executable in Edit > Preferences > Add-ons > matfit"


class FitError(Exception):
    """The fit's params.json cannot be used; the message is one line for Blender's report."""


def _refuse_constant(name):
    raise ValueError(f"{name} is not a number JSON allows")


def _read_bytes(path, command):
    """Returns the bytes of the regular file `path`, opened without following a link or blocking on a FIFO."""
    try:
        descriptor = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise FitError(
            f"matfit ({command}) ended without writing the fit's params.json: the material is unchanged; {FIX}"
        ) from None
    except OSError as error:
        if error.errno == errno.ELOOP:
            raise FitError(f"matfit ({command}) wrote a link as the fit's params.json: {FIX}") from None
        raise FitError(f"matfit: cannot read the fit's params.json ({error.strerror or error}): {FIX}") from None
    with os.fdopen(descriptor, "rb") as file:
        if not stat.S_ISREG(os.fstat(file.fileno()).st_mode):
            raise FitError(f"matfit ({command}) wrote something other than a file as the fit's params.json: {FIX}")
        data = file.read(LIMIT + 1)
    if len(data) > LIMIT:
        raise FitError(f"matfit ({command}) wrote a params.json of more than {LIMIT // 1024} KB: {FIX}")
    return data


def _refuse(problem):
    return FitError(f"matfit: the fit's params.json {problem}: the material is unchanged; {FIX}")


def read(path, table, command):
    """Returns (named values, document, its bytes) of the params.json at `path`, which the job of `command` wrote.

    `table` is params.table() (parameters.json in the zip): names, bounds and defaults. Names left
    out take their defaults, as in matfit.
    """
    data = _read_bytes(path, command)
    try:
        document = json.loads(data, parse_constant=_refuse_constant)
    except (ValueError, RecursionError) as error:  # not JSON, not UTF-8, NaN, nested too deeply
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise _refuse(f"is not valid JSON ({reason})") from None
    return values(document, table), document, data


def values(document, table):
    """Returns the named values of a params.json document (read from the file, or a stage's answer from the worker),
    or raises FitError: `table` as `read`'s, names left out at their defaults."""
    if not isinstance(document, dict) or not isinstance(document.get("params"), dict):
        raise _refuse('holds no "params" object')
    parameters = {entry["name"]: entry for entry in table}
    named = {name: entry["default"] for name, entry in parameters.items()}
    for name, value in document["params"].items():
        if name not in parameters:
            raise _refuse(f"names {name!r}, which is not one of matfit's parameters")
        low, high = parameters[name]["low"], parameters[name]["high"]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise _refuse(f"gives {name} = {value!r}, not a number")
        if not low <= value <= high:
            raise _refuse(f"gives {name} = {value!r}, outside [{low:g}, {high:g}]")
        named[name] = float(value)
    return named


def medium_coefficients(values, minimum_extinction):
    """Returns (sigma_t, albedo) of the medium as matfit's params.medium_coefficients does, in plain Python."""
    colours = [values[f"medium_color_{channel}"] for channel in "rgb"]
    sigma_t = [max(values["density"] * -math.log(c), minimum_extinction) for c in colours]  # c >= 0.01: in range
    return sigma_t, [values["scattering"]] * 3


def figure(document, name):
    """Returns the figure `name` of the document as a number, or None (absent with --no-verify, or not a number)."""
    value = document.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)
