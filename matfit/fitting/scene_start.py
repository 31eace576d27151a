"""A scene fit's start when nothing gives one: the test scene's best-of-n of the shape's pixels (docs/scenes.md).

A scene fit starts from `--init`, else from the shape's own material in the scene file. Where the file gives none
that matfit reads (a textured or non-principled BSDF), the networks guess one: the picture's pixels of the shape's
own surface (`scene_fit.silhouette`) are cut out, scaled onto the test scene's sphere (`composite`), and the test
scene's best-of-n (the nine encoders' guesses, the one whose decoded image is closest over those pixels)
guesses the material. The networks know the test scene's lights, not the user's, so the guess is a start, not an
answer. Measured on the bench's twelve truths (three scenes, four materials), the guess's noise-free error from the
truth was under matfit's default material's on eleven (7.9-31.5 against 21.3-68.0 of 255) and over it on the glass
box under the sky (23.8 against 21.8); fits from it came closer than from the default on three of four cases and
alike on the fourth: docs/scenes.md#the-start.
"""

from __future__ import annotations

import numpy as np

from matfit import images, params
from matfit.fitting import search
from matfit.fitting.methods import Method, Settings
from matfit.model import models
from matfit.rendering import scene

SPHERE_MARGIN = -1.0  # pixels: the sphere's silhouette shrunk by one, so that no weighed pixel is the floor's


def composite(target: np.ndarray, shape: np.ndarray, background: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (the test scene's picture with the shape's pixels on its sphere, the weights of those pixels).

    `target`: sRGB (h, w, 3); `shape`: its boolean (h, w) silhouette; `background`: the test scene in sRGB (R, R, 3).
    The shape's bounding box is scaled onto the sphere's; pixels of the box that are not the shape keep the
    background and weigh 0.
    """
    resolution = background.shape[0]
    ys, xs = np.nonzero(shape)
    box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
    disk = scene.sphere_mask(resolution, margin=SPHERE_MARGIN)
    dy, dx = np.nonzero(disk)
    onto = (slice(dy.min(), dy.max() + 1), slice(dx.min(), dx.max() + 1))
    height, width = dy.max() - dy.min() + 1, dx.max() - dx.min() + 1
    scaled = images.srgb_encode(images.resample(images.srgb_decode(target[box]), height, width))
    covered = images.resample(shape[box][..., None].astype(np.float32), height, width)[..., 0] > 0.5
    picture = np.asarray(background, np.float32).copy()
    picture[onto] = np.where(covered[..., None], np.clip(scaled, 0.0, 1.0), picture[onto])
    weights = np.zeros((resolution, resolution), np.float32)
    weights[onto] = covered & disk[onto]
    return picture, weights


def guess(model: models.Model, target: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, str]:
    """Returns (physical values, the winning candidate's name): the test scene's best-of-n of the shape's pixels of
    the sRGB `target` (h, w, 3), `shape` its silhouette (h, w)."""
    background = model.decode(params.to_unit(params.DEFAULTS)[None])[0]
    picture, weights = composite(target, shape, background)
    found = search.neural_search(model, picture, settings=Settings(method=Method.nn), weights=weights)
    return np.asarray(found.values, np.float64), found.chosen
