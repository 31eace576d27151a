"""The input pipeline: a rendered dataset's arrays as the networks see them (data only, no training).

`python -m matfit.model.pipeline` measures how fast training's host side gathers batches (`measure_loader`).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from matfit import images
from matfit.errors import DatasetError
from matfit.model import architectures, models
from matfit.model.dataset import Dataset

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


def check_encoder_resolution(data: Dataset) -> None:
    """Raises DatasetError unless the encoders can read the dataset's images (a side that is a multiple of theirs)."""
    side = architectures.ENCODER_RESOLUTION
    if data.resolution % side:
        raise DatasetError(
            f"encoders need images whose side is a multiple of {side} px; {data.path} has {data.resolution}: "
            "render one at 64 px"
        )


def encoder_inputs(data: Dataset) -> np.ndarray:
    """Returns every image as the encoders see it (`models.encoder_input`), float16 (count, 32, 32, 3)."""
    check_encoder_resolution(data)
    return convert(data, models.encoder_input, architectures.ENCODER_RESOLUTION)


def training_arrays(name: str, data: Dataset, linear: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Returns (inputs, targets) of network `name` for every sample: (x, image) for the decoder, else (image, x).

    The decoder's images are sRGB-encoded, or with `linear` linear (`losses.linear_residual`).
    """
    unit = data.unit_params()
    if name == architectures.DECODER:
        return unit, linear_targets(data) if linear else srgb_targets(data)
    return encoder_inputs(data), unit


def measure_loader(
    resolution: int, batch_size: int, host_cast: bool = False, samples: int = 22000, seconds: float = 2.0
) -> dict:
    """Returns samples/s of training's data loading: gather a shuffled batch (`host_cast`: cast to float32 in NumPy).

    The same operations as a training step's host side, on in-memory arrays of the shapes and
    types training holds: the decoder's sRGB targets (float16, resolution^2 x 3) with their
    parameters, and an encoder's 32 x 32 inputs. Training sends the float16 batch as it is and
    casts it inside the compiled step; `host_cast` measures the NumPy cast it replaced. A GPU is
    fed as long as this is well above its training rate in samples/s.
    """
    rng = np.random.default_rng(0)
    arrays: dict[str, tuple[np.ndarray, np.ndarray]] = {
        "decoder": (
            rng.random((samples, 19), np.float32),
            rng.random((samples, resolution, resolution, 3), np.float32).astype(np.float16),
        ),
        "encoder": (
            rng.random((samples, 32, 32, 3), np.float32).astype(np.float16),
            rng.random((samples, 19), np.float32),
        ),
    }
    rates = {}
    for name, (inputs, targets) in arrays.items():
        order, steps, started = rng.permutation(samples), 0, time.perf_counter()
        while time.perf_counter() - started < seconds:
            start = steps * batch_size % (samples - batch_size)
            batch = order[start : start + batch_size]
            x, y = inputs[batch], targets[batch]
            if host_cast:
                np.asarray(x, np.float32), np.asarray(y, np.float32)
            steps += 1
        rates[name] = steps * batch_size / (time.perf_counter() - started)
    return {
        "resolution": resolution,
        "batch_size": batch_size,
        **{f"{name}_samples_per_s": rate for name, rate in rates.items()},
    }


if __name__ == "__main__":
    for side in (64, 128):
        for host_cast in (False, True):
            figures = measure_loader(side, 64, host_cast)
            print(
                f"loader, {side} px, batch 64{', float32 cast in NumPy' if host_cast else ''}: decoder "
                f"{figures['decoder_samples_per_s']:.0f} samples/s, encoder {figures['encoder_samples_per_s']:.0f} "
                "samples/s"
            )
