"""The visual report of a fit: target | best-of-n guess | fitted (neural) | fitted (Mitsuba) | difference | ranges."""

from __future__ import annotations

from collections.abc import Sequence

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


VERDICT_COLOURS = {"decided": (0.3, 0.8, 0.3), "partly": (0.9, 0.7, 0.2), "free": (0.45, 0.45, 0.45)}


def ranges_panel(
    names: Sequence[str],
    unit: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    verdicts: Sequence[str],
    size: int = TILE,
) -> np.ndarray:
    """Returns an sRGB size x size panel with one row per parameter: its name, then a bar over its whole range
    with the range the picture allows coloured by verdict (green decided, amber partly, grey free) and the
    answer as a white tick (docs/fitting.md#what-the-picture-decides)."""
    rows = len(names)
    height = size // rows
    bar_start, bar_width = size // 2, size // 2 - 4
    panel = []
    for name, x, lo, hi, verdict in zip(names, unit, low, high, verdicts, strict=True):
        row = images.label(np.zeros((0, size, 3), np.float32), name, height)
        row[1:-1, bar_start : bar_start + bar_width] = 0.15
        a = bar_start + round(float(lo) * (bar_width - 1))
        b = bar_start + round(float(hi) * (bar_width - 1))
        row[1:-1, a : b + 1] = VERDICT_COLOURS[verdict]
        tick = bar_start + round(float(x) * (bar_width - 1))
        row[:, tick] = 1.0
        panel.append(row)
    out = np.zeros((size, size, 3), np.float32)
    out[: rows * height] = np.concatenate(panel, axis=0)
    return out
