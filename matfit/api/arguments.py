"""The public API's checks of its arguments, each run before any work: pixels given as an array, a material's values,
paths, callables, and (from `matfit.errors`, which `Settings` shares) whole numbers, finite numbers, True or False,
and how an error names a value. Each raises the one-line `MatfitError` that names the value and the fix
(docs/api.md)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from matfit import params
from matfit.errors import FitError, ImageError, MatfitError, ParameterError
from matfit.errors import flag as flag  # the checks `Settings` shares, which the API's modules take from here
from matfit.errors import number as number
from matfit.errors import shown as shown
from matfit.errors import whole as whole

Picture = str | os.PathLike[str] | npt.NDArray[Any]  # a picture file's path, or its pixels (`fit`)
Image = npt.NDArray[np.float32]
ARRAY = "array"  # params.json's `target` (and `mask`) of pixels given as an array
MAX_SIZE = 4096  # pixels a side of a render (`render`, `Outputs.render_size`): `matfit render --size`'s


def linear_pixels(picture: npt.ArrayLike, name: str, *, linear: bool) -> tuple[Image, list[str]]:
    """Returns (linear RGB float32 (H, W, 3), notices) of pixels given as an array, as `images.load` reads a file."""
    try:
        array = np.asarray(picture)
    except (ValueError, TypeError) as error:
        raise ImageError(
            f"the {name} array cannot be read ({error}): give an (H, W, 3) NumPy array", field=name
        ) from None
    shapes = "(H, W, 3) RGB, (H, W, 4) with alpha, or (H, W) grey"
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] not in (1, 2, 3, 4)) or 0 in array.shape:
        raise ImageError(f"the {name} array has shape {array.shape}: give {shapes}", field=name)
    kinds = "float sRGB in 0-1, uint8 0-255, uint16 0-65535, or linear float with linear=True"
    if array.dtype.kind == "u" and array.dtype.itemsize in (1, 2) and not linear:
        scaled = array.astype(np.float32) / np.float32(np.iinfo(array.dtype).max)
    elif array.dtype.kind == "f":
        scaled = array.astype(np.float32)
    else:
        raise ImageError(f"the {name} array holds {array.dtype} values: give {kinds}", field=name)
    from matfit import images

    if array.shape[0] * array.shape[1] > images.MAX_PIXELS:
        raise ImageError(
            f"the {name} array is {array.shape[1]}x{array.shape[0]}, more than {images.MAX_PIXELS / 1e6:.0f} Mpixel: "
            "scale it down first",
            field=name,
        )
    if not np.all(np.isfinite(scaled)):
        raise ImageError(f"the {name} array contains NaN or infinite values: fix or clamp them first", field=name)
    if not linear and (scaled.min() < 0 or scaled.max() > 1):
        raise ImageError(
            f"the {name} array's values run from {scaled.min():g} to {scaled.max():g}, outside sRGB's 0-1: divide "
            "0-255 values by 255, or pass linear=True for linear (HDR) values",
            field=name,
        )
    notices = []
    channels = 1 if array.ndim == 2 else array.shape[2]
    if channels in (1, 2):
        notices.append(f"the {name} array is grey: replicated to RGB")
        scaled = np.repeat(scaled.reshape(*array.shape[:2], -1)[:, :, :1], 3, axis=2)
    elif channels == 4:
        notices.append(f"the {name} array's alpha dropped (the colour is used as it is, not composited)")
    pixels = scaled[:, :, :3]
    return np.ascontiguousarray(pixels if linear else images.srgb_decode(pixels), np.float32), notices


def path_text(path: str | os.PathLike[str]) -> str:
    """Returns a path as the command line passes it on: `str(Path(...))`, so that params.json names it alike."""
    return str(Path(path))


Called = TypeVar("Called", bound=Callable[..., object])


def callback(field: str, value: Called | None, error: type[MatfitError]) -> Called | None:
    """Returns `value`: a function (anything callable) or None, else `error` naming it."""
    if value is not None and not callable(value):
        raise error(f"{field} {shown(value)} is not callable: give a function or None", field=field)
    return value


def path_of(field: str, value: object, error: type[MatfitError], fix: str, *, name: str | None = None) -> str:
    """Returns `value` as a path's text (`os.fspath`): a str or os.PathLike, else `error` naming it (as `name`, if
    given: the argument's name where `field` is the command line's) and the fix."""
    if not isinstance(value, str | os.PathLike) or not isinstance(os.fspath(value), str):
        raise error(f"{name or field} {shown(value)} is no path: {fix}", field=field)
    return os.fspath(value)


MATERIAL_ORDER = "one value a parameter, in the order `matfit params` lists them"


def material_values(field: str, values: object) -> npt.NDArray[np.float64]:
    """Returns a material's 19 values as float64 (19,): real numbers (ints or floats, NumPy's too), else the
    ParameterError naming them (text, None, complex, a ragged list, objects: nothing converted silently)."""
    try:
        array = np.asarray(values)
    except (ValueError, TypeError):  # a ragged list
        raise ParameterError(
            f"{field} {shown(values)} is no list of numbers: give {params.COUNT} numbers, {MATERIAL_ORDER}", field=field
        ) from None
    if array.dtype.kind not in "iuf":
        raise ParameterError(
            f"{field} {shown(values)} holds {array.dtype} values: give {params.COUNT} real numbers, {MATERIAL_ORDER}",
            field=field,
        )
    if array.shape != (params.COUNT,):
        raise ParameterError(
            f"a material is {params.COUNT} values, got shape {array.shape}: give {MATERIAL_ORDER}", field=field
        )
    return array.astype(np.float64)


def picture_paths(pictures: object) -> list[str | os.PathLike[str]]:
    """Returns the picture paths of `fit_all`'s `pictures` (FitError for anything but an iterable of paths)."""
    if isinstance(pictures, str | os.PathLike) or not isinstance(pictures, Iterable):
        raise FitError(f"pictures {shown(pictures)} is no list of paths: give a list of picture files", field="target")
    listed = list(pictures)
    for picture in listed:
        path_of("target", picture, FitError, "fit_all fits picture files", name="picture")
    return listed


def read_pixels(path: str, name: str) -> Image:
    """Returns a picture file's linear pixels (the one-line ImageError of a missing or unreadable one)."""
    from matfit import images

    if not os.path.isfile(path):
        raise ImageError(f"{name} {path} is not a file: give the picture's path", field=name)
    return np.asarray(images.load(path).pixels, np.float32)


def picture_size(path: str) -> tuple[int, int]:
    """Returns (height, width) of a picture file (the one-line ImageError of a missing or unreadable one)."""
    from matfit import images

    if not os.path.isfile(path):
        raise ImageError(f"target {path} is not a file: give the picture's path", field="target")
    width, height = images.header(path)[:2]
    return height, width
