"""The input pipeline: a rendered dataset's arrays as the networks see them (data only, no training)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from matfit import images, models
from matfit.dataset import Dataset
from matfit.errors import DatasetError

CHUNK = 1024  # images converted at a time: float32 copies of the whole set would not fit in memory at 128 px


def check_finished(data: Dataset) -> None:
    """Raises DatasetError unless every sample of the dataset has been rendered."""
    if data.finished < data.count:
        raise DatasetError(
            f"{data.path} has {data.finished}/{data.count} samples rendered: finish it with "
            f"`matfit render-dataset {data.path} --count {data.count}` (same settings) first"
        )


def convert(data: Dataset, function: Callable[[np.ndarray], np.ndarray], side: int) -> np.ndarray:
    """Returns function(linear images) for every image of the dataset, float16 (count, side, side, 3), in chunks."""
    out = np.empty((data.count, side, side, 3), np.float16)
    for start in range(0, data.count, CHUNK):
        out[start : start + CHUNK] = function(np.asarray(data.images[start : start + CHUNK], np.float32))
    return out


def srgb_targets(data: Dataset) -> np.ndarray:
    """Returns every image sRGB-encoded (what the decoder learns to draw), float16 (count, R, R, 3)."""
    return convert(data, images.srgb_encode, data.resolution)


def linear_targets(data: Dataset) -> np.ndarray:
    """Returns every image linear, negative values set to 0, float16 (count, R, R, 3): the decoder's linear loss."""
    return convert(data, lambda linear: np.maximum(linear, 0.0), data.resolution)


def encoder_inputs(data: Dataset) -> np.ndarray:
    """Returns every image as the encoders see it (`models.encoder_input`), float16 (count, 32, 32, 3)."""
    side = models.ENCODER_RESOLUTION
    if data.resolution % side:
        raise DatasetError(
            f"encoders need images whose side is a multiple of {side} px; {data.path} has {data.resolution}: "
            "render one at 64 px"
        )
    return convert(data, models.encoder_input, side)


def training_arrays(name: str, data: Dataset, linear: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Returns (inputs, targets) of network `name` for every sample: (x, image) for the decoder, else (image, x).

    The decoder's images are sRGB-encoded, or with `linear` linear (`train.linear_residual`).
    """
    unit = data.unit_params()
    if name == models.DECODER:
        return unit, linear_targets(data) if linear else srgb_targets(data)
    return encoder_inputs(data), unit
