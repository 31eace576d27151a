"""The visual report of a fit: target | best-of-n guess | fitted (neural) | fitted (Mitsuba) | difference."""

from __future__ import annotations

import numpy as np

from matfit import images

TILE = 192
DIFFERENCE_GAIN = 4.0


def tile(image_srgb: np.ndarray, size: int = TILE) -> np.ndarray:
    """Returns an sRGB image resampled (in linear light) to a size x size tile."""
    return images.srgb_encode(images.resample(images.srgb_decode(image_srgb), size, size))


def difference(a_srgb: np.ndarray, b_srgb: np.ndarray) -> np.ndarray:
    """Returns |a - b| on sRGB values, amplified DIFFERENCE_GAIN times, as an sRGB image."""
    return np.clip(DIFFERENCE_GAIN * np.abs(np.asarray(a_srgb, np.float32) - np.asarray(b_srgb, np.float32)), 0.0, 1.0)


def compose(panels: list[tuple[np.ndarray, str]], size: int = TILE, caption: int = 16) -> np.ndarray:
    """Returns the panels (sRGB images with captions) side by side, as one sRGB image."""
    return np.concatenate([images.label(tile(image, size), text, caption) for image, text in panels], axis=1)
