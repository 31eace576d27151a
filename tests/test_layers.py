"""The layers the networks are built of (matfit/model/layers.py), each against its definition computed independently."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from matfit import params
from matfit.model import layers
from matfit.rendering import presets, scene


def test_upsample_pool_and_shuffle_match_their_definitions():
    x = jax.random.normal(jax.random.key(0), (2, 4, 6, 8))
    np.testing.assert_array_equal(layers.upsample(x), np.repeat(np.repeat(x, 2, axis=1), 2, axis=2))
    np.testing.assert_array_equal(
        layers.max_pool(x), jax.lax.reduce_window(x, -np.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1), "VALID")
    )
    shuffled = layers.depth_to_space(x)
    assert shuffled.shape == (2, 8, 12, 2)
    # output pixel (2i + a, 2j + b) channel c comes from input (i, j) channel (2a + b) * 2 + c
    np.testing.assert_array_equal(shuffled[:, 3, 5, 1], x[:, 1, 2, (2 * 1 + 1) * 2 + 1])


def _conv_of_upsampled(x, kernel):
    return jax.lax.conv_general_dilated(
        layers.upsample(x), kernel, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
    )


def test_the_upsampling_folded_into_a_convolution_is_the_convolution_of_the_upsampled_map():
    x = jax.random.normal(jax.random.key(0), (2, 3, 5, 4))  # not square: rows and columns are not mixed up
    kernel = jax.random.normal(jax.random.key(1), (3, 3, 4, 6))
    folded = layers.upsampled_conv(x, kernel)
    assert folded.shape == (2, 6, 10, 6)
    np.testing.assert_allclose(folded, _conv_of_upsampled(x, kernel), rtol=1e-5, atol=1e-5)
    # and so are its gradients, with respect to the map and to the kernel
    probe = jax.random.normal(jax.random.key(2), folded.shape)
    grads = [
        jax.grad(lambda x, k, f=f: jnp.sum(f(x, k) * probe), argnums=(0, 1))(x, kernel)
        for f in (layers.upsampled_conv, _conv_of_upsampled)
    ]
    for ours, theirs in zip(*grads, strict=True):
        np.testing.assert_allclose(ours, theirs, rtol=1e-4, atol=1e-4)


def test_coordinate_channels_are_pixel_centres_in_the_unit_square():
    out = layers.coordinate_channels(jnp.zeros((1, 2, 4, 1)))
    assert out.shape == (1, 2, 4, 3)
    np.testing.assert_allclose(out[0, 0, :, 1], [-0.75, -0.25, 0.25, 0.75])  # x along a row
    np.testing.assert_allclose(out[0, :, 0, 2], [-0.5, 0.5])  # y down a column


def test_glass_interpolation_hits_grid_points_and_blends_between_them():
    shape = (5, 3)
    basis = jnp.asarray(np.random.default_rng(0).uniform(size=(*shape, 4, 4, 3)).astype(np.float32))
    specular, roughness = scene.glass_grid_values(shape)  # roughness 0, 0.25, 1
    at = layers.interpolate_glass(basis, jnp.asarray([specular[2], specular[4]]), jnp.asarray([roughness[1], 1.0]))
    np.testing.assert_allclose(at[0], basis[2, 1], atol=1e-5)
    np.testing.assert_allclose(at[1], basis[4, 2], atol=1e-5)
    # halfway in specular, and halfway in the square root of roughness (0.5 ** 2)
    between = layers.interpolate_glass(basis, jnp.asarray([0.125]), jnp.asarray([0.25]))
    np.testing.assert_allclose(between[0], 0.5 * (basis[0, 1] + basis[1, 1]), atol=1e-5)
    between = layers.interpolate_glass(basis, jnp.asarray([0.0]), jnp.asarray([0.75**2]))  # root halfway 0.5 to 1
    np.testing.assert_allclose(between[0], 0.5 * (basis[0, 1] + basis[0, 2]), atol=1e-5)

    def brightness(s, r):
        return jnp.sum(layers.interpolate_glass(basis, s, r))

    grad_s, grad_r = jax.grad(brightness, argnums=(0, 1))(jnp.asarray([0.3]), jnp.asarray([0.4]))
    # specular 0.3 lies between grid points 1 and 2 (spacing 1/4); roughness 0.4 between 1 and 2 in its root
    wr = np.sqrt(0.4) * 2 - 1
    step = (basis[2, 1] - basis[1, 1]) * (1 - wr) + (basis[2, 2] - basis[1, 2]) * wr
    assert float(grad_s[0]) == pytest.approx(4 * float(jnp.sum(step)), rel=1e-3)
    assert np.isfinite(float(grad_r[0])) and float(grad_r[0]) != 0.0


def test_medium_weights_read_each_channel_at_its_own_thickness():
    shape = (4, 3)
    thickness, albedo = scene.medium_grid_values(shape)
    material = presets.preset("milk")
    index = params.INDEX
    material[index["density"]] = 4.0  # the largest: colour 0.01 gives the largest thickness
    # channel r on grid point 1, g on grid point 3, b halfway between 0 and 1 in log2(1 + 8 tau)
    halfway = (2.0 ** (0.5 * np.log2(1.0 + 8.0 * thickness[1])) - 1.0) / 8.0
    for channel, tau in zip(("r", "g", "b"), (thickness[1], thickness[3], halfway), strict=True):
        material[index[f"medium_color_{channel}"]] = np.exp(-tau / 4.0)
    material[index["scattering"]] = albedo[1]
    weights = np.asarray(layers.medium_weights(jnp.asarray(params.to_unit(material)[None], jnp.float32), shape))
    assert weights.shape == (1, 3, 12)
    grid = weights[0].reshape(3, 4, 3)
    np.testing.assert_allclose(weights.sum(-1), 1.0, atol=1e-5)
    assert grid[0, 1, 1] == pytest.approx(1.0, abs=1e-4) and grid[1, 3, 1] == pytest.approx(1.0, abs=1e-4)
    np.testing.assert_allclose(grid[2, :2, 1], [0.5, 0.5], atol=1e-4)

    def light(unit):
        return jnp.sum(layers.medium_weights(unit, shape) * jnp.arange(12, dtype=jnp.float32)[None, None])

    gradient = jax.grad(light)(jnp.asarray(params.to_unit(material)[None], jnp.float32))
    assert np.all(np.isfinite(gradient)) and float(gradient[0, index["density"]]) != 0.0


def test_absorption_is_beer_lambert_per_colour_along_the_predicted_path():
    amber = presets.preset("amber-glass")
    unit = jnp.asarray(params.to_unit(np.stack([amber, presets.preset("glass")])), jnp.float32)
    path = jnp.broadcast_to(jnp.asarray([2.0, 0.5])[:, None, None, None], (2, 4, 4, 1))
    transmittance = np.asarray(layers.absorbed(unit, path))
    assert transmittance.shape == (2, 4, 4, 3)
    colour = amber[params.INDEX["medium_color_r"] : params.INDEX["medium_color_b"] + 1]
    # a diameter of amber (density 1): each colour's own exp(-2 tau) = colour^2; clear glass keeps everything
    np.testing.assert_allclose(transmittance[0], np.broadcast_to(colour**2, (4, 4, 3)), rtol=1e-4)
    np.testing.assert_allclose(transmittance[1], 1.0, atol=1e-3)


def test_medium_features_follow_the_physics_of_the_presets():
    names = ("milk", "glass", "amber-glass")
    unit = jnp.asarray(params.to_unit(np.stack([presets.preset(name) for name in names])), jnp.float32)
    opacity, transmittance, scattered, reflectance = np.split(np.asarray(layers.medium_features(unit)), [3, 6, 9], 1)
    milk, glass, amber = range(3)
    # milk: opaque, nothing absorbed, everything scattered, a white half-space (albedo 1)
    np.testing.assert_allclose(np.stack([opacity[milk], transmittance[milk], scattered[milk]]), 1.0, atol=1e-3)
    assert reflectance[milk, 0] == pytest.approx(1.0, abs=0.01)
    # clear glass: no medium at all
    np.testing.assert_allclose(np.concatenate([opacity[glass], scattered[glass], reflectance[glass]]), 0.0, atol=1e-6)
    np.testing.assert_allclose(transmittance[glass], 1.0)
    # amber: absorbs blue most, scatters nothing
    colour = presets.preset("amber-glass")[params.INDEX["medium_color_r"] : params.INDEX["medium_color_b"] + 1]
    density = presets.preset("amber-glass")[params.INDEX["density"]]
    np.testing.assert_allclose(transmittance[amber], colour ** (2 * density), rtol=1e-4)
    assert transmittance[amber, 2] < transmittance[amber, 0] and reflectance[amber, 0] == 0.0
