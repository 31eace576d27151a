import numpy as np
import pytest

from matfit import edits
from matfit.app.bench import suite


@pytest.fixture
def image():
    return np.random.default_rng(0).uniform(0.05, 0.95, (16, 16, 3))


def test_saturate_and_greyscale(image):
    grey = edits.saturate(image, 1.0)
    np.testing.assert_allclose(grey[..., 0], grey[..., 2])
    np.testing.assert_allclose(grey[..., 0], np.clip(image @ edits.LUMA, 0, 1))
    stronger = edits.saturate(image, -0.5)
    assert np.std(stronger - (stronger @ edits.LUMA)[..., None]) > np.std(image - (image @ edits.LUMA)[..., None])


def test_hue_rotation_keeps_greys_and_turns_full_circle():
    greys = np.full((2, 2, 3), 0.4)
    np.testing.assert_allclose(edits.hue_rotate(greys, 77.0), greys, atol=1e-12)
    colour = np.array([[[0.6, 0.3, 0.2]]])
    np.testing.assert_allclose(edits.hue_rotate(edits.hue_rotate(colour, 120.0), 240.0), colour, atol=1e-12)
    np.testing.assert_allclose(edits.hue_rotate(colour, 120.0), [[[0.2, 0.6, 0.3]]], atol=1e-12)


def test_tint_mix_and_stitch(image):
    np.testing.assert_allclose(edits.tint(image, (1.0, 0.5, 0.0), 1.0), image * [1.0, 0.5, 0.0])
    other = np.zeros_like(image)
    np.testing.assert_allclose(edits.mix(image, other, 0.25), 0.75 * image)
    stitched = edits.stitch(image, other, (0.0, 0.0, 0.5, 1.0))
    assert np.all(stitched[:, :8] == 0) and np.array_equal(stitched[:, 8:], image[:, 8:])


def test_blur_keeps_dark_pixels_and_softens_the_highlight():
    image = np.full((32, 32, 3), 0.2)
    image[14:18, 14:18] = 1.0
    blurred = edits.blur_highlight(image, 0.55, 2.0)
    np.testing.assert_allclose(blurred[:5, :5], 0.2)
    assert blurred[15, 15, 0] < 0.9 and blurred[12, 15, 0] > 0.25
    np.testing.assert_allclose(edits.gaussian_blur(np.full((8, 8, 3), 0.3), 1.5), 0.3)


def test_the_suite_has_eight_cases_with_a_control():
    assert [case[0] for case in suite.SUITE] == [
        "control",
        "saturation+",
        "greyscale",
        "hue shift",
        "tint",
        "stitch",
        "highlight blur",
        "mix",
    ]
    assert suite.SUITE[0][0] == "control"
    image = np.full((8, 8, 3), 0.5)
    for name, _, sources, edit in suite.SUITE:
        out = edit(*[image] * len(sources))
        assert out.shape == image.shape and np.all((out >= 0) & (out <= 1)), name
