import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from matfit import models

# The paper's Appendix A as (conv filters in order, FC neurons, dropout), written out independently.
APPENDIX_A = {
    1: ([32, 32, 64, 128, 128], 1000, 0.1),
    2: ([32, 32], 1000, 0.1),
    3: ([32, 32], 1000, 0.5),
    4: ([32, 32, 64, 128, 128], 3000, 0.5),
    5: ([32, 32, 64, 128, 128], 3000, 0.0),
    6: ([32, 32], 1000, 0.0),
    7: ([32, 32], 1000, 0.0),
    8: ([32, 32], 100, 0.0),
    9: ([32, 32], 1000, 0.0),
}


def expected_encoder_weights(filters, neurons, resolution):
    count, channels, side = 0, 3, resolution
    for f in filters:
        count += 3 * 3 * channels * f + f
        channels, side = f, side // 2
    flat = side * side * channels
    return count + flat * neurons + neurons + neurons * neurons + neurons + neurons * 19 + 19


@pytest.mark.parametrize("arch", range(1, 10))
def test_encoders_match_appendix_a(arch):
    filters, neurons, dropout = APPENDIX_A[arch]
    model = models.encoder(arch)
    assert [b.filters for b in model.blocks for _ in range(b.repeat)] == filters
    assert (model.dense.repeat, model.dense.neurons, model.dense.dropout) == (2, neurons, dropout)
    variables = models.initialise(model, jax.random.key(0), (models.ENCODER_RESOLUTION,) * 2 + (3,))
    assert models.parameter_count(variables) == expected_encoder_weights(filters, neurons, models.ENCODER_RESOLUTION)
    out = model.apply(variables, jnp.full((2, 32, 32, 3), 0.5))
    assert out.shape == (2, 19)
    assert float(out.min()) > 0.0 and float(out.max()) < 1.0


def test_dropout_is_active_only_in_training():
    model = models.encoder(3)
    variables = models.initialise(model, jax.random.key(0), (32, 32, 3))
    image = jax.random.uniform(jax.random.key(1), (4, 32, 32, 3))
    np.testing.assert_array_equal(model.apply(variables, image), model.apply(variables, image))
    trained = model.apply(variables, image, train=True, rngs={"dropout": jax.random.key(2)})
    assert not np.allclose(trained, model.apply(variables, image))


def test_unknown_architectures_are_refused():
    for arch in (0, 10):
        with pytest.raises(ValueError, match="use 1 to 9"):
            models.encoder(arch)


@pytest.mark.parametrize("resolution", [16, 64, 128])
def test_decoder_outputs_images_in_the_unit_range(resolution):
    model = models.Decoder(resolution=resolution, hidden=32, base_channels=16, stage_channels=(8,))
    variables = models.initialise(model, jax.random.key(0), (19,))
    out = models.apply(model, variables, jax.random.uniform(jax.random.key(1), (3, 19)))
    assert out.shape == (3, resolution, resolution, 3)
    assert float(out.min()) > 0.0 and float(out.max()) < 1.0


def test_decoder_weights_do_not_grow_with_the_image_beyond_one_stage():
    sizes = {}
    for resolution in (64, 128, 256):
        model = models.Decoder(resolution=resolution)
        shapes = jax.eval_shape(lambda model=model: models.initialise(model, jax.random.key(0), (19,)))
        sizes[resolution] = models.parameter_count(shapes)
    # one more upsampling stage of 32 channels (one 3x3 convolution 32 -> 32) and a larger background image
    stage = 3 * 3 * 32 * 32 + 32
    assert sizes[128] - sizes[64] == stage + (128**2 - 64**2) * 3
    assert sizes[256] - sizes[128] == stage + (256**2 - 128**2) * 3


def test_decoder_rejects_resolutions_it_cannot_reach():
    with pytest.raises(ValueError, match="4 times a power of two"):
        models.initialise(models.Decoder(resolution=48), jax.random.key(0), (19,))


def test_upsample_pool_and_shuffle_match_their_definitions():
    x = jax.random.normal(jax.random.key(0), (2, 4, 6, 8))
    np.testing.assert_array_equal(models.upsample(x), np.repeat(np.repeat(x, 2, axis=1), 2, axis=2))
    np.testing.assert_array_equal(
        models.max_pool(x), jax.lax.reduce_window(x, -np.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1), "VALID")
    )
    shuffled = models.depth_to_space(x)
    assert shuffled.shape == (2, 8, 12, 2)
    # output pixel (2i + a, 2j + b) channel c comes from input (i, j) channel (2a + b) * 2 + c
    np.testing.assert_array_equal(shuffled[:, 3, 5, 1], x[:, 1, 2, (2 * 1 + 1) * 2 + 1])


def test_a_weights_file_of_another_network_is_refused(tmp_path):
    decoder = models.Decoder(resolution=32, hidden=64, base_channels=32, stage_channels=(32,))
    network = models.Network(
        "decoder",
        models.architecture("decoder", 32, decoder),
        decoder,
        models.initialise(decoder, jax.random.key(0), (19,)),
        {},
    )
    encoder = models.encoder(8)
    variables = models.initialise(encoder, jax.random.key(1), (32, 32, 3))
    models.save(
        str(tmp_path / "decoder.msgpack"),
        models.Network("encoder-8", models.architecture("encoder-8", 32), encoder, variables, {}),
    )
    with pytest.raises(
        models.WeightsError, match="holds the weights of the encoder-8, not of the decoder: copy the right file"
    ):
        models.load_model(str(tmp_path))
    models.save(str(tmp_path / "decoder.msgpack"), network)
    models.save(str(tmp_path / "encoder-3.msgpack"), network)
    with pytest.raises(
        models.WeightsError, match=r"encoder-3\.msgpack holds the weights of the decoder, not of the encoder-3"
    ):
        models.load_model(str(tmp_path))
    moved = tmp_path / "moved"
    moved.mkdir()
    models.save(str(moved / "decoder.msgpack"), network)
    models.save(
        str(moved / "encoder-8.msgpack"),
        models.Network("encoder-8", models.architecture("encoder-8", 32), encoder, variables, {}),
    )
    first = models.load_model(str(moved))
    os.rename(moved, tmp_path / "elsewhere")
    assert models.load_model(str(tmp_path / "elsewhere")).identity() == first.identity()  # the weights, not the place


def test_bilinear_upsampling_matches_jax_image_resize():
    x = jax.random.normal(jax.random.key(0), (2, 4, 6, 3))
    expected = jax.image.resize(x, (2, 8, 12, 3), "linear")
    np.testing.assert_allclose(models.upsample_bilinear(x), expected, atol=1e-6)


def test_coordinate_channels_are_pixel_centres_in_the_unit_square():
    out = models.coordinate_channels(jnp.zeros((1, 2, 4, 1)))
    assert out.shape == (1, 2, 4, 3)
    np.testing.assert_allclose(out[0, 0, :, 1], [-0.75, -0.25, 0.25, 0.75])  # x along a row
    np.testing.assert_allclose(out[0, :, 0, 2], [-0.5, 0.5])  # y down a column


def reference_bilinear(image, x, y):
    """Bilinear lookup of one (H, W, C) image at one (x, y), clamped, written independently."""
    height, width = image.shape[:2]
    x, y = min(max(x, 0.0), width - 1.0), min(max(y, 0.0), height - 1.0)
    x0, y0 = min(int(np.floor(x)), width - 2), min(int(np.floor(y)), height - 2)
    fx, fy = x - x0, y - y0
    return (
        image[y0, x0] * (1 - fx) * (1 - fy)
        + image[y0, x0 + 1] * fx * (1 - fy)
        + image[y0 + 1, x0] * (1 - fx) * fy
        + image[y0 + 1, x0 + 1] * fx * fy
    )


def test_bilinear_sampling_matches_a_reference_and_clamps_at_the_border():
    rng = np.random.default_rng(0)
    levels = rng.uniform(size=(2, 5, 7, 3)).astype(np.float32)
    position = rng.uniform(-2.0, 8.0, size=(3, 4, 4, 2)).astype(np.float32)
    out = np.asarray(models.bilinear(jnp.asarray(levels), jnp.asarray(position)))
    assert out.shape == (3, 4, 4, 2, 3)
    for n, i, j, level in [(0, 0, 0, 0), (1, 2, 3, 1), (2, 3, 1, 0), (2, 1, 2, 1)]:
        x, y = position[n, i, j]
        np.testing.assert_allclose(
            out[n, i, j, level], reference_bilinear(levels[level], float(x), float(y)), rtol=1e-5, atol=1e-6
        )


def test_bilinear_sampling_is_differentiable_in_the_position():
    image = jnp.asarray(np.random.default_rng(1).uniform(size=(1, 6, 6, 3)).astype(np.float32))
    position = jnp.array([[[[2.3, 3.6]]]])
    gradient = jax.grad(lambda p: models.bilinear(image, p).sum())(position)
    step = 1e-2
    for axis in range(2):
        shift = jnp.zeros((1, 1, 1, 2)).at[..., axis].set(step)
        finite = (models.bilinear(image, position + shift).sum() - models.bilinear(image, position - shift).sum()) / (
            2 * step
        )
        np.testing.assert_allclose(gradient[0, 0, 0, axis], finite, rtol=1e-3)


def test_blur_pyramid_keeps_level_zero_and_the_mean_of_a_delta():
    image = np.zeros((21, 21, 1), np.float32)
    image[10, 10] = 1.0
    pyramid = models.blur_pyramid(image, (0.0, 1.0, 2.0))
    assert pyramid.shape == (3, 21, 21, 1)
    np.testing.assert_array_equal(pyramid[0], image)
    np.testing.assert_allclose(pyramid.sum(axis=(1, 2, 3)), [1.0, 1.0, 1.0], rtol=1e-5)
    taps = np.exp(-0.5 * (np.arange(-3, 4) / 1.0) ** 2)
    np.testing.assert_allclose(pyramid[1, 10, 7:14, 0], taps * taps[3] / taps.sum() ** 2, rtol=1e-5)


def tiny_refracting_decoder():
    return models.Decoder(
        resolution=16, hidden=16, base_channels=8, stage_channels=(8,), coordinates=True, blur_levels=(0.0, 2.0)
    )


def test_refracting_decoder_shows_the_scene_through_and_round_trips_with_it(tmp_path):
    model = tiny_refracting_decoder()
    scene = np.random.default_rng(2).uniform(0.0, 0.5, size=(16, 16, 3)).astype(np.float32)
    variables = models.with_scene(model, dict(models.initialise(model, jax.random.key(0), (19,))), scene)
    np.testing.assert_allclose(variables["constants"]["scene"], models.blur_pyramid(scene, (0.0, 2.0)))
    x = jax.random.uniform(jax.random.key(1), (2, 19))
    out = models.apply(model, variables, x)
    assert out.shape == (2, 16, 16, 3) and float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    darker = models.apply(model, models.with_scene(model, variables, scene * 0.0), x)
    assert float(jnp.mean(out - darker)) > 0.01  # the scene behind adds light
    description = models.architecture("decoder", 16, model)
    path = str(tmp_path / "decoder.msgpack")
    models.save(path, models.Network("decoder", description, model, variables, {}))
    loaded = models.load(path)
    assert loaded.module == model
    np.testing.assert_allclose(loaded.variables["constants"]["scene"], variables["constants"]["scene"], atol=1e-3)
    np.testing.assert_allclose(models.apply(loaded.module, loaded.variables, x), out, atol=1e-2)


def test_decoder_descriptions_without_refraction_fields_still_build():
    description = models.architecture("decoder", 64)
    for key in ("coordinates", "blur_levels", "max_offset"):
        description.pop(key)
    assert models.build(description) == models.Decoder()
