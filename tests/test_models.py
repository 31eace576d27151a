import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from matfit import params
from matfit.errors import WeightsError
from matfit.model import architectures, layers, models, weight_files
from matfit.rendering import presets, scene

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
    model = architectures.encoder(arch)
    assert [b.filters for b in model.blocks for _ in range(b.repeat)] == filters
    assert (model.dense.repeat, model.dense.neurons, model.dense.dropout) == (2, neurons, dropout)
    variables = architectures.initialise(model, jax.random.key(0), (architectures.ENCODER_RESOLUTION,) * 2 + (3,))
    assert architectures.parameter_count(variables) == expected_encoder_weights(
        filters, neurons, architectures.ENCODER_RESOLUTION
    )
    out = model.apply(variables, jnp.full((2, 32, 32, 3), 0.5))
    assert out.shape == (2, 19)
    assert float(out.min()) > 0.0 and float(out.max()) < 1.0


def test_dropout_is_active_only_in_training():
    model = architectures.encoder(3)
    variables = architectures.initialise(model, jax.random.key(0), (32, 32, 3))
    image = jax.random.uniform(jax.random.key(1), (4, 32, 32, 3))
    np.testing.assert_array_equal(model.apply(variables, image), model.apply(variables, image))
    trained = model.apply(variables, image, train=True, rngs={"dropout": jax.random.key(2)})
    assert not np.allclose(trained, model.apply(variables, image))


def test_unknown_architectures_are_refused():
    for arch in (0, 10):
        with pytest.raises(ValueError, match="use 1 to 9"):
            architectures.encoder(arch)


@pytest.mark.parametrize("resolution", [16, 64, 128])
def test_decoder_outputs_images_in_the_unit_range(resolution):
    model = architectures.Decoder(resolution=resolution, hidden=32, base_channels=16, stage_channels=(8,))
    variables = architectures.initialise(model, jax.random.key(0), (19,))
    out = models.apply(model, variables, jax.random.uniform(jax.random.key(1), (3, 19)))
    assert out.shape == (3, resolution, resolution, 3)
    assert float(out.min()) > 0.0 and float(out.max()) < 1.0


def test_decoder_weights_do_not_grow_with_the_image_beyond_one_stage():
    sizes = {}
    for resolution in (64, 128, 256):
        model = architectures.Decoder(resolution=resolution)
        shapes = jax.eval_shape(lambda model=model: architectures.initialise(model, jax.random.key(0), (19,)))
        sizes[resolution] = architectures.parameter_count(shapes)
    # one more upsampling stage of 32 channels (one 3x3 convolution 32 -> 32) and a larger background image
    stage = 3 * 3 * 32 * 32 + 32
    assert sizes[128] - sizes[64] == stage + (128**2 - 64**2) * 3
    assert sizes[256] - sizes[128] == stage + (256**2 - 128**2) * 3


def test_decoder_rejects_resolutions_it_cannot_reach():
    with pytest.raises(ValueError, match="4 times a power of two"):
        architectures.initialise(architectures.Decoder(resolution=48), jax.random.key(0), (19,))


def test_the_decoder_folds_its_upsampling_without_changing_its_weights_or_what_it_draws():
    decoder = architectures.Decoder(
        resolution=32, hidden=32, base_channels=16, stage_channels=(8, 6), convs_per_stage=2
    )
    variables = architectures.initialise(decoder, jax.random.key(0), (19,))
    names = sorted(variables["params"])
    assert names == ["Conv_0", "Conv_1", "Conv_2", "Conv_3", "Conv_4", "Dense_0", "Dense_1", "Dense_2", "background"]
    assert variables["params"]["Conv_0"]["kernel"].shape == (3, 3, 16, 8)  # a plain 3x3 kernel on the source
    # the same network written out with explicit upsampling and plain convolutions (compiled as one program)
    y = jax.random.uniform(jax.random.key(1), (3, 19))

    @jax.jit
    def written_out(p, y):
        x = y
        for k in range(3):
            x = jax.nn.gelu(x @ p[f"Dense_{k}"]["kernel"] + p[f"Dense_{k}"]["bias"][None])
        x = x.reshape(-1, 4, 4, 16)

        def conv(x, name):
            return (
                jax.lax.conv_general_dilated(
                    x, p[name]["kernel"], (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
                )
                + p[name]["bias"][None, None, None]
            )

        for stage in range(2):
            x = jax.nn.gelu(conv(layers.upsample(x), f"Conv_{2 * stage}"))
            x = jax.nn.gelu(conv(x, f"Conv_{2 * stage + 1}"))
        return jax.nn.sigmoid(layers.depth_to_space(conv(x, "Conv_4")) + p["background"][None])

    expected = written_out(variables["params"], y)
    np.testing.assert_allclose(models.apply(decoder, variables, y), expected, atol=1e-5)


def test_a_weights_file_of_another_network_is_refused(tmp_path):
    decoder = architectures.Decoder(resolution=32, hidden=64, base_channels=32, stage_channels=(32,))
    network = weight_files.Network(
        "decoder",
        architectures.architecture("decoder", 32, decoder),
        decoder,
        architectures.initialise(decoder, jax.random.key(0), (19,)),
        {},
    )
    encoder = architectures.encoder(8)
    variables = architectures.initialise(encoder, jax.random.key(1), (32, 32, 3))
    weight_files.save(
        str(tmp_path / "decoder.msgpack"),
        weight_files.Network("encoder-8", architectures.architecture("encoder-8", 32), encoder, variables, {}),
    )
    with pytest.raises(
        WeightsError, match="holds the weights of the encoder-8, not of the decoder: copy the right file"
    ):
        models.load_model(str(tmp_path))
    weight_files.save(str(tmp_path / "decoder.msgpack"), network)
    weight_files.save(str(tmp_path / "encoder-3.msgpack"), network)
    with pytest.raises(
        WeightsError, match=r"encoder-3\.msgpack holds the weights of the decoder, not of the encoder-3"
    ):
        models.load_model(str(tmp_path))
    moved = tmp_path / "moved"
    moved.mkdir()
    weight_files.save(str(moved / "decoder.msgpack"), network)
    weight_files.save(
        str(moved / "encoder-8.msgpack"),
        weight_files.Network("encoder-8", architectures.architecture("encoder-8", 32), encoder, variables, {}),
    )
    first = models.load_model(str(moved))
    stored = weight_files.load(str(moved / "encoder-8.msgpack")).variables  # one network alone: its weights as stored
    loaded = first.encoders[8].variables  # the model's: converted on the device, the same numbers
    for kept, converted in zip(jax.tree_util.tree_leaves(stored), jax.tree_util.tree_leaves(loaded), strict=True):
        assert kept.dtype == np.float16 and converted.dtype == np.float32
        np.testing.assert_array_equal(np.asarray(kept, np.float32), np.asarray(converted))
    assert {leaf.dtype for leaf in jax.tree_util.tree_leaves(first.decoder.variables)} == {np.dtype(np.float32)}
    os.rename(moved, tmp_path / "elsewhere")
    assert models.load_model(str(tmp_path / "elsewhere")).identity() == first.identity()  # the weights, not the place


def test_glass_basis_materials_are_clear_glass_on_the_grid():
    materials = scene.glass_basis_materials((3, 2))
    assert materials.shape == (3, 2, params.COUNT)
    unit = params.to_unit(materials)
    index = params.INDEX
    np.testing.assert_allclose(materials[:, 0, index["specular"]], [0.0, 0.5, 1.0])
    np.testing.assert_allclose(materials[0, :, index["roughness"]], [0.0, 1.0])
    assert np.all(materials[..., index["spec_trans"]] == 1.0) and np.all(materials[..., index["density"]] == 0.0)
    assert np.all(materials[..., index["metallic"]] == 0.0) and np.all(unit >= 0) and np.all(unit <= 1)


def saved_and_loaded(tmp_path, model: architectures.Decoder, variables: dict) -> weight_files.Network:
    """Returns a decoder's weights saved with its description and loaded back (the same module rebuilt)."""
    path = str(tmp_path / "decoder.msgpack")
    description = architectures.architecture("decoder", model.resolution, model)
    weight_files.save(path, weight_files.Network("decoder", description, model, variables, {}))
    loaded = weight_files.load(path)
    assert loaded.module == model
    return loaded


def tiny_refracting_decoder():
    return architectures.Decoder(resolution=16, hidden=16, base_channels=8, stage_channels=(8,), glass_grid=(3, 2))


def test_refracting_decoder_adds_the_glass_basis_and_round_trips_with_it(tmp_path):
    model = tiny_refracting_decoder()
    basis = np.random.default_rng(2).uniform(0.0, 0.5, size=(3, 2, 16, 16, 3)).astype(np.float32)
    variables = architectures.with_bases(model, dict(architectures.initialise(model, jax.random.key(0), (19,))), basis)
    np.testing.assert_array_equal(variables["constants"]["glass"], basis)
    x = jax.random.uniform(jax.random.key(1), (2, 19))
    out = models.apply(model, variables, x)
    assert out.shape == (2, 16, 16, 3) and float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    darker = models.apply(model, architectures.with_bases(model, variables, basis * 0.0), x)
    assert float(jnp.mean(out - darker)) > 0.002  # the glass layer adds light
    with pytest.raises(ValueError, match="glass basis"):
        architectures.with_bases(model, variables, basis[:2])
    assert architectures.architecture("decoder", 16, model)["glass_grid"] == [3, 2]
    loaded = saved_and_loaded(tmp_path, model, variables)
    np.testing.assert_allclose(loaded.variables["constants"]["glass"], basis, atol=1e-3)
    np.testing.assert_allclose(models.apply(loaded.module, loaded.variables, x), out, atol=1e-2)


def test_medium_basis_materials_are_grey_media_of_the_grid_thickness_and_albedo():
    materials = scene.medium_basis_materials((4, 3))
    assert materials.shape == (4, 3, params.COUNT)
    thickness, albedo = scene.medium_grid_values((4, 3))
    np.testing.assert_allclose(albedo, [1.0, 0.75, 0.0])  # uniform in sqrt(1 - albedo)
    assert thickness[0] == 0.0 and thickness[-1] == pytest.approx(scene.MEDIUM_SCALE)
    for i, j in np.ndindex(4, 3):
        sigma_t, scattering = params.medium_coefficients(materials[i, j])
        np.testing.assert_allclose(sigma_t, max(thickness[i], params.MINIMUM_EXTINCTION), rtol=1e-6)
        np.testing.assert_allclose(scattering, albedo[j])
    index = params.INDEX
    assert np.all(materials[..., index["spec_trans"]] == 1.0) and np.all(materials[..., index["metallic"]] == 0.0)
    assert np.all(materials[..., index["roughness"]] == scene.MEDIUM_ROUGHNESS)
    unit = params.to_unit(materials)
    assert np.all(unit >= 0) and np.all(unit <= 1)


def test_scattering_decoder_adds_the_basis_by_the_transmitted_share(tmp_path):
    model = architectures.Decoder(
        resolution=16, hidden=16, base_channels=8, stage_channels=(8,), glass_grid=(3, 2), medium_grid=(4, 3)
    )
    rng = np.random.default_rng(3)
    glass = rng.uniform(0.0, 0.3, size=(3, 2, 16, 16, 3)).astype(np.float32)
    medium = rng.uniform(0.0, 0.3, size=(4, 3, 16, 16, 3)).astype(np.float32)
    variables = architectures.with_bases(
        model, dict(architectures.initialise(model, jax.random.key(0), (19,))), glass, medium
    )
    milk = params.to_unit(presets.preset("milk"))
    opaque = milk.copy()
    opaque[params.INDEX["spec_trans"]] = 0.0
    x = jnp.asarray(np.stack([milk, opaque]), jnp.float32)
    out = models.apply(model, variables, x)
    without = models.apply(model, architectures.with_bases(model, variables, glass, medium * 0.0), x)
    assert float(jnp.mean(out[0] - without[0])) > 0.01  # milk: the scattered light is added
    np.testing.assert_allclose(out[1], without[1], atol=1e-6)  # nothing transmitted, nothing scattered
    with pytest.raises(ValueError, match="scattering basis"):
        architectures.with_bases(model, variables, glass)
    with pytest.raises(ValueError, match="scattering basis"):
        architectures.with_bases(model, variables, glass, medium[:2])
    assert architectures.architecture("decoder", 16, model)["medium_grid"] == [4, 3]
    loaded = saved_and_loaded(tmp_path, model, variables)
    np.testing.assert_allclose(loaded.variables["constants"]["medium"], medium, atol=1e-3)
    np.testing.assert_allclose(models.apply(loaded.module, loaded.variables, x), out, atol=1e-2)


def test_an_absorbing_decoder_tints_the_glass_layer_by_the_medium_and_round_trips(tmp_path):
    model = architectures.Decoder(
        resolution=16, hidden=16, base_channels=8, stage_channels=(8,), glass_grid=(3, 2), absorption=True
    )
    basis = np.random.default_rng(4).uniform(0.0, 0.5, size=(3, 2, 16, 16, 3)).astype(np.float32)
    variables = architectures.with_bases(model, dict(architectures.initialise(model, jax.random.key(0), (19,))), basis)
    amber = params.to_unit(presets.preset("amber-glass"))
    clear = amber.copy()
    clear[params.INDEX["density"]] = 0.0
    x = jnp.asarray(np.stack([amber, clear]), jnp.float32)
    glass_layer = models.apply(model, variables, x) - models.apply(
        model, architectures.with_bases(model, variables, basis * 0.0), x
    )
    # the layer starts at path length 1: amber keeps more red than blue, clear glass keeps every colour
    red, blue = (float(jnp.mean(glass_layer[0, ..., k])) for k in (0, 2))
    assert red > 4 * blue > 0.0
    np.testing.assert_allclose(jnp.mean(glass_layer[1], axis=(0, 1)), jnp.mean(glass_layer[1]), rtol=0.2)
    gradient = jax.grad(lambda y: jnp.sum(models.apply(model, variables, y)))(x)
    assert np.all(np.isfinite(np.asarray(gradient))) and float(gradient[0, params.INDEX["medium_color_b"]]) > 0.0
    assert architectures.architecture("decoder", 16, model)["absorption"] is True
    loaded = saved_and_loaded(tmp_path, model, variables)
    np.testing.assert_allclose(
        models.apply(loaded.module, loaded.variables, x), models.apply(model, variables, x), atol=1e-2
    )


def test_a_coarse_absorption_layer_grows_on_a_decoder_without_changing_it_and_absorbs_by_extinction(tmp_path):
    plain = architectures.Decoder(resolution=16, hidden=16, base_channels=8, stage_channels=(8,), glass_grid=(3, 2))
    coarse = plain.clone(coarse_absorption=True)
    basis = np.random.default_rng(4).uniform(0.0, 0.5, size=(3, 2, 16, 16, 3)).astype(np.float32)
    trained = architectures.with_bases(plain, dict(architectures.initialise(plain, jax.random.key(0), (19,))), basis)
    fresh = architectures.initialise(coarse, jax.random.key(1), (19,))["params"]
    assert set(fresh) - set(trained["params"]) == {"path"}  # one layer more, the others named as before
    grown = {**trained, "params": {**trained["params"], "path": fresh["path"]}}
    amber = params.to_unit(presets.preset("amber-glass"))
    clear = amber.copy()
    clear[params.INDEX["density"]] = 0.0
    x = jnp.asarray(np.stack([amber, clear]), jnp.float32)
    np.testing.assert_array_equal(models.apply(coarse, grown, x), models.apply(plain, trained, x))  # E = 0

    # A longer path dims each colour by its own extinction (amber per radius: red 0.16, green 0.80, blue
    # 2.53): blue most, red least; clear glass not at all.
    def glass_layer(path_bias):
        weights = {**grown["params"], "path": {**grown["params"]["path"], "bias": jnp.full((1,), path_bias)}}
        return layers.srgb_decode(models.apply(coarse, {**grown, "params": weights}, x)) - layers.srgb_decode(
            models.apply(plain, architectures.with_bases(plain, trained, basis * 0.0), x)
        )

    longer = architectures.initialise(coarse.clone(path_start=2.0), jax.random.key(1), (19,))["params"]["path"]
    assert float(longer["bias"][0]) == 2.0 and not np.any(np.asarray(longer["kernel"]))
    kept = jnp.sum(glass_layer(2.0), axis=(1, 2)) / jnp.sum(glass_layer(0.0), axis=(1, 2))
    assert 0.0 < float(kept[0, 2]) < float(kept[0, 1]) < float(kept[0, 0]) < 1.0
    np.testing.assert_allclose(kept[1], 1.0, rtol=1e-5)
    assert float(jnp.max(glass_layer(-50.0))) <= 1.5 * float(basis.max()) + 1e-5  # bounded whatever E
    assert architectures.architecture("decoder", 16, coarse)["coarse_absorption"] is True
    loaded = saved_and_loaded(tmp_path, coarse, grown)
    np.testing.assert_allclose(
        models.apply(loaded.module, loaded.variables, x), models.apply(coarse, grown, x), atol=1e-2
    )


def test_decoder_descriptions_without_refraction_fields_still_build():
    description = architectures.architecture("decoder", 64)
    for key in (
        "coordinates",
        "glass_grid",
        "medium_inputs",
        "medium_grid",
        "absorption",
        "coarse_absorption",
        "path_start",
    ):
        description.pop(key)
    assert architectures.build(description) == architectures.Decoder()


def test_a_decoder_with_medium_inputs_has_finite_gradients_everywhere_in_the_box():
    model = architectures.Decoder(resolution=16, hidden=16, base_channels=8, stage_channels=(8,), medium_inputs=True)
    variables = architectures.initialise(model, jax.random.key(0), (19,))
    corners = jnp.asarray(np.stack([np.zeros(19), np.ones(19), np.full(19, 0.5)]), jnp.float32)
    gradient = jax.grad(lambda x: jnp.sum(models.apply(model, variables, x)))(corners)
    assert np.all(np.isfinite(np.asarray(gradient)))


@pytest.fixture(scope="module")
def tiny_networks():
    """A small decoder and encoder 8, initialised once: (decoder module, its variables, encoder, its variables)."""
    decoder = architectures.Decoder(resolution=32, hidden=64, base_channels=32, stage_channels=(32,))
    encoder = architectures.encoder(8)
    return (
        decoder,
        architectures.initialise(decoder, jax.random.key(0), (19,)),
        encoder,
        architectures.initialise(encoder, jax.random.key(1), (32, 32, 3)),
    )


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"resolution": "abc"}, "field 'resolution' is \"abc\", not one of 8, 16, 32, 64, 128, 256, 512, 1024"),
        ({"resolution": 10**6}, "field 'resolution' is 1000000, not one of 8"),
        ({"resolution": 2**20}, "field 'resolution' is 1048576, not one of 8"),  # a power of two: it allocated
        ({"resolution": 32.0}, "field 'resolution' is 32.0, not one of 8"),
        ({"hidden": -1}, "field 'hidden' is -1, not a whole number from 1 to 8192"),
        ({"stage_channels": [32, "x"]}, "field 'stage_channels' is [32, \"x\"], not 1 to 8 whole numbers"),
        ({"stage_channels": []}, "field 'stage_channels' is [], not 1 to 8 whole numbers"),
        ({"glass_grid": [17]}, "field 'glass_grid' is [17], not [] or two whole numbers from 2 to 64"),
        ({"coordinates": "yes"}, "field 'coordinates' is \"yes\", not true or false"),
        ({"path_start": float("nan")}, "field 'path_start' is NaN, not a number from -100 to 100"),
        ({"kind": "vae"}, "field 'kind' is \"vae\", not decoder or encoder"),
        ({"depth": 3}, "field 'depth' is not part of a decoder"),
    ],
)
def test_a_damaged_architecture_record_is_refused_in_one_line(tmp_path, change, message):
    path = tmp_path / "decoder.msgpack"
    description = {**architectures.architecture("decoder", 32), **change}
    # The record is refused before any weight is looked at: any will do.
    weight_files.save(str(path), weight_files.Network("decoder", description, None, {"params": {"x": np.zeros(1)}}, {}))
    with pytest.raises(WeightsError) as caught:
        weight_files.load(str(path))
    assert str(caught.value).startswith(f"{path}: architecture {message}")
    assert str(caught.value).endswith(": train it again (or copy an intact file there)")


def test_an_encoder_architecture_record_is_checked_too(tmp_path):
    description = {**architectures.architecture("encoder-8", 32), "arch": "8"}
    weight_files.save(
        str(tmp_path / "encoder-8.msgpack"),
        weight_files.Network("encoder-8", description, None, {"params": {"x": np.zeros(1)}}, {}),
    )
    with pytest.raises(WeightsError, match="field 'arch' is \"8\", not a whole number from 1 to 9"):
        weight_files.load(str(tmp_path / "encoder-8.msgpack"))


@pytest.mark.parametrize(("network", "value"), [("decoder", np.nan), ("encoder-8", np.inf)])
def test_weights_with_nan_or_infinity_are_refused_when_a_model_loads(tmp_path, tiny_networks, network, value):
    """A broken network is refused at load, so that no fit can write NaN into params.json."""
    decoder, decoder_variables, encoder, encoder_variables = tiny_networks
    variables = {"decoder": decoder_variables, "encoder-8": encoder_variables}
    variables[network] = jax.tree_util.tree_map(lambda leaf: np.array(leaf), variables[network])
    variables[network]["params"]["Dense_1"]["kernel"][3, 2] = value
    weight_files.save(
        str(tmp_path / "decoder.msgpack"),
        weight_files.Network(
            "decoder", architectures.architecture("decoder", 32, decoder), decoder, variables["decoder"], {}
        ),
    )
    weight_files.save(
        str(tmp_path / "encoder-8.msgpack"),
        weight_files.Network(
            "encoder-8", architectures.architecture("encoder-8", 32), encoder, variables["encoder-8"], {}
        ),
    )
    expected = (
        f"{tmp_path / (network + '.msgpack')}: weights params/Dense_1/kernel hold NaN or infinity: "
        "train it again (or copy an intact file there)"
    )
    with pytest.raises(WeightsError) as caught:
        models.load_model(str(tmp_path))
    assert str(caught.value) == expected
    with pytest.raises(WeightsError) as caught:
        weight_files.load(str(tmp_path / f"{network}.msgpack"))
    assert str(caught.value) == expected
