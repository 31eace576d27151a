"""A scene fit's start guessed by the test scene's best-of-n (`fitting/scene_start`): real renders, the shipped
model."""

import numpy as np
import pytest

import matfit
from matfit import images, params
from matfit.fitting import scene_fit, scene_start
from matfit.rendering import presets, scene, scene_file


@pytest.fixture(scope="module")
def renderer(knot) -> scene_file.Renderer:
    return scene_file.Renderer(knot, knot.size(64), integrator=scene_file.OPAQUE_INTEGRATOR)


def test_the_silhouette_is_the_shapes_surface_within_the_region_it_changes(renderer):
    shape = scene_fit.silhouette(renderer)
    region, _ = scene_fit.region(renderer)
    assert shape.shape == (48, 64) and shape[24, 32]  # the knot sits in the middle
    assert 0.05 < shape.mean() < region.mean()  # its shadow and reflections are in the region, not the silhouette
    assert not (shape & ~region).any()


def test_the_composite_puts_the_shapes_pixels_on_the_sphere_and_weighs_only_them():
    target = np.zeros((48, 64, 3), np.float32)
    shape = np.zeros((48, 64), bool)
    shape[10:30, 20:50] = True
    target[shape] = [0.8, 0.1, 0.1]
    background = np.full((64, 64, 3), 0.5, np.float32)
    picture, weights = scene_start.composite(target, shape, background)
    disk = scene.sphere_mask(64, margin=scene_start.SPHERE_MARGIN)
    assert weights.sum() == pytest.approx(disk.sum(), rel=0.02)  # a full box: the whole sphere is the shape's
    assert not (weights.astype(bool) & ~disk).any()
    np.testing.assert_allclose(picture[weights > 0].mean(axis=0), [0.8, 0.1, 0.1], atol=0.01)
    np.testing.assert_array_equal(picture[0, 0], [0.5, 0.5, 0.5])  # the background stays where no shape is


def test_the_guess_of_a_red_knot_is_red_and_closer_than_the_default(renderer):
    truth = presets.preset("red-plastic")
    target = np.clip(images.srgb_encode(renderer.render(truth, seed=3, spp=64)), 0.0, 1.0)
    guessed, chosen = scene_start.guess(matfit.load_model(), target, scene_fit.silhouette(renderer))
    colour = guessed[params.INDEX["base_color_r"] : params.INDEX["base_color_b"] + 1]
    assert colour[0] > 2 * max(colour[1], colour[2])  # red
    assert chosen.startswith(("encoder-", "media-"))
    weights = scene_fit.region(renderer)[0].astype(np.float32)

    def error(values: np.ndarray) -> float:
        return float(images.rmse(images.srgb_encode(renderer.render(values, seed=4, spp=64)), target, weights))

    assert error(guessed) < 0.7 * error(params.DEFAULTS)
