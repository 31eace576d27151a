"""The public API's checks of its arguments: pixels given as an array, paths, whole numbers, and how an error names
a value. Each raises the one-line `MatfitError` that names the value and the fix (docs/api.md)."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from matfit.errors import FitError, ImageError, MatfitError, check_range

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


def shown(value: object) -> str:
    """Returns how an error message names a value: its repr if that is short and one line, else its type."""
    text = repr(value)
    return text if len(text) <= 40 and "\n" not in text else f"of type {type(value).__name__}"


def whole(field: str, value: object, low: int, high: int, error: type[MatfitError]) -> int:
    """Returns `value` as an int: a whole number in [low, high], else `error` naming it and the range."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise error(f"{field} {shown(value)} is not a whole number: use {low} to {high}", field=field)
    check_range(field, int(value), low, high, error)
    return int(value)


def picture_paths(pictures: object) -> list[str | os.PathLike[str]]:
    """Returns the picture paths of `fit_all`'s `pictures` (FitError for anything but an iterable of paths)."""
    if isinstance(pictures, str | os.PathLike) or not isinstance(pictures, Iterable):
        raise FitError(f"pictures {shown(pictures)} is no list of paths: give a list of picture files", field="target")
    listed = list(pictures)
    for picture in listed:
        if not isinstance(picture, str | os.PathLike):
            raise FitError(f"picture {shown(picture)} is no path: fit_all fits picture files", field="target")
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
