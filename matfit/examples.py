"""The example edits shipped in data/examples: a preset rendered, then changed as in a 2D editor.

- recoloured.png: red plastic with its hue turned by 120 degrees (green plastic);
- desaturated.png: copper with 85% of its saturation taken out (a grey metal);
- painted-highlight.png: red plastic with a sharp white highlight painted on (a local edit that
  asks for a glossier coat).

Run `make examples` (python -m matfit.examples data/examples) to make them again.
"""

from __future__ import annotations

import os
import sys

import numpy as np

from matfit import images, presets

SIZE = 256
SPP = 256


def hue_rotate(srgb: np.ndarray, degrees: float) -> np.ndarray:
    """Returns sRGB colours rotated about the grey axis by `degrees` (greys stay grey)."""
    angle = np.radians(degrees)
    axis = np.ones(3) / np.sqrt(3.0)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.cos(angle) * np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * np.outer(axis, axis)
    return np.clip(srgb @ rotation.T, 0.0, 1.0)


def desaturate(srgb: np.ndarray, amount: float) -> np.ndarray:
    """Returns sRGB colours moved `amount` of the way to their grey (Rec. 709 luma)."""
    grey = srgb @ np.array([0.2126, 0.7152, 0.0722])
    return np.clip(srgb + amount * (grey[..., None] - srgb), 0.0, 1.0)


def paint_highlight(srgb: np.ndarray, centre: tuple[float, float], radius: float, strength: float) -> np.ndarray:
    """Returns the image with a soft white spot painted at `centre` (fractions of width, height)."""
    height, width = srgb.shape[:2]
    y, x = np.mgrid[0:height, 0:width]
    distance = np.hypot(x - centre[0] * width, y - centre[1] * height) / (radius * width)
    alpha = strength * np.exp(-(distance**2))[..., None]
    return srgb * (1 - alpha) + alpha


EXAMPLES = {
    "recoloured.png": ("red-plastic", lambda image: hue_rotate(image, 120.0)),
    "desaturated.png": ("copper", lambda image: desaturate(image, 0.85)),
    "painted-highlight.png": ("red-plastic", lambda image: paint_highlight(image, (0.38, 0.38), 0.035, 0.95)),
}


def make(directory: str, size: int = SIZE, spp: int = SPP) -> list[str]:
    """Renders the presets and writes the edited examples into `directory`; returns their paths."""
    from matfit.render import Renderer

    renderer = Renderer(size, spp)
    written = []
    for name, (preset, edit) in EXAMPLES.items():
        original = images.srgb_encode(renderer.render(presets.preset(preset)))
        path = os.path.join(directory, name)
        images.write(path, images.srgb_decode(edit(original)))
        written.append(path)
    return written


if __name__ == "__main__":
    for written_path in make(sys.argv[1] if len(sys.argv) > 1 else "data/examples"):
        print(f"wrote {written_path}")
