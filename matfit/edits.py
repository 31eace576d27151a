"""Image edits, as an artist makes them in a 2D editor: pure functions of sRGB images in [0, 1].

Global: `saturate` (amount < 0 increases saturation, 1 is greyscale), `hue_rotate`, `tint`.
Local: `stitch` (a region taken from another material's image), `blur_highlight` (a selective
blur of the bright specular highlight), `paint_highlight`. Between two images: `mix`.
"""

from __future__ import annotations

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709


def saturate(srgb: np.ndarray, amount: float) -> np.ndarray:
    """Returns colours moved `amount` of the way to their grey: 1 is greyscale, -0.6 is 60% more saturated."""
    grey = srgb @ LUMA
    return np.clip(srgb + amount * (grey[..., None] - srgb), 0.0, 1.0)


def hue_rotate(srgb: np.ndarray, degrees: float) -> np.ndarray:
    """Returns colours rotated about the grey axis by `degrees` (greys stay grey)."""
    angle = np.radians(degrees)
    axis = np.ones(3) / np.sqrt(3.0)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.cos(angle) * np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * np.outer(axis, axis)
    return np.clip(srgb @ rotation.T, 0.0, 1.0)


def tint(srgb: np.ndarray, colour: tuple[float, float, float], amount: float) -> np.ndarray:
    """Returns the image multiplied by a colour, `amount` of the way (a photo filter)."""
    return np.clip(srgb * (1.0 - amount + amount * np.asarray(colour)), 0.0, 1.0)


def mix(a: np.ndarray, b: np.ndarray, weight: float) -> np.ndarray:
    """Returns (1 - weight) a + weight b: two pictures blended."""
    return (1.0 - weight) * a + weight * b


def stitch(a: np.ndarray, b: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """Returns `a` with the box (left, top, right, bottom, fractions of the size) taken from `b`."""
    height, width = a.shape[:2]
    left, top, right, bottom = (round(f * n) for f, n in zip(box, (width, height, width, height), strict=True))
    out = a.copy()
    out[top:bottom, left:right] = b[top:bottom, left:right]
    return out


def gaussian_blur(srgb: np.ndarray, sigma: float) -> np.ndarray:
    """Returns the image blurred by a separable Gaussian of `sigma` pixels (edges repeated)."""
    radius = max(1, int(3 * sigma))
    x = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (x / sigma) ** 2)
    kernel /= kernel.sum()
    padded = np.pad(srgb, ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    rows = sum(kernel[k] * padded[:, k : k + srgb.shape[1]] for k in range(len(kernel)))
    return sum(kernel[k] * rows[k : k + srgb.shape[0]] for k in range(len(kernel)))


def blur_highlight(srgb: np.ndarray, threshold: float, sigma: float) -> np.ndarray:
    """Returns the image with its brightest parts (luma above `threshold`, softened) blurred."""
    luma = srgb @ LUMA
    weight = gaussian_blur(np.clip((luma - threshold) / (1.0 - threshold), 0.0, 1.0)[..., None] * np.ones(3), sigma)
    weight = np.clip(3.0 * weight, 0.0, 1.0)
    return np.clip(srgb * (1.0 - weight) + gaussian_blur(srgb, sigma) * weight, 0.0, 1.0)


def paint_highlight(srgb: np.ndarray, centre: tuple[float, float], radius: float, strength: float) -> np.ndarray:
    """Returns the image with a soft white spot painted at `centre` (fractions of width, height)."""
    height, width = srgb.shape[:2]
    y, x = np.mgrid[0:height, 0:width]
    distance = np.hypot(x - centre[0] * width, y - centre[1] * height) / (radius * width)
    alpha = strength * np.exp(-(distance**2))[..., None]
    return srgb * (1 - alpha) + alpha
