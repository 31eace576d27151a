import dataclasses
import hashlib
import json
import os
import pathlib
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from matfit import images, params
from matfit.errors import DatasetError, TrainingError, WeightsError
from matfit.model import (
    architectures,
    checkpoints,
    dataset,
    dataset_writing,
    losses,
    models,
    pipeline,
    train,
    train_config,
    weight_files,
)
from matfit.model.train_config import Config

TINY_DECODER = architectures.Decoder(resolution=32, hidden=32, base_channels=16, stage_channels=(16, 8, 8))


@pytest.fixture(scope="module")
def data(tiny_dataset):
    return dataset.open_dataset(tiny_dataset)


class StopAfterOneEpoch(train.Reporter):
    """Interrupts a run as Ctrl-C would, once the first epoch's checkpoint is written."""

    def end_epoch(self, record: dict) -> None:
        raise KeyboardInterrupt


def weights_equal(a, b):
    return all(
        np.array_equal(x, y) for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True)
    )


def test_split_holds_out_the_last_samples():
    assert train_config.validation_count(48, 0.05) == 2
    assert train_config.validation_count(10, 0.05) == 1
    assert train_config.validation_count(22000, 0.05) == 1100


def test_several_datasets_train_together_and_each_holds_out_its_own_last_samples(tmp_path, data):
    second = tmp_path / "second"
    shutil.copytree(data.path, second)
    other = dataset.open_dataset(str(second))
    inputs, targets, training = train.split("decoder", [data, other], 0.05)
    unit = data.unit_params()
    assert training == 92 and len(inputs) == 96
    np.testing.assert_array_equal(inputs[:46], unit[:46])
    np.testing.assert_array_equal(inputs[46:92], unit[:46])
    np.testing.assert_array_equal(inputs[92:], np.concatenate([unit[46:], unit[46:]]))
    np.testing.assert_array_equal(targets[92:94], pipeline.srgb_targets(data)[46:])
    alone = train.split("decoder", [data], 0.05)
    assert alone[2] == 46 and np.array_equal(alone[0], unit)
    metrics = train.train_network(
        "decoder", [data, other], str(tmp_path / "m"), Config(epochs=1, batch_size=8), decoder=TINY_DECODER
    )
    assert metrics["training_samples"] == 92 and metrics["validation_samples"] == 4
    assert [each["count"] for each in metrics["dataset"]] == [48, 48]


def test_datasets_of_two_resolutions_are_refused(tmp_path, data, renderer):
    small = dataset_writing.prepare(str(tmp_path / "small"), dataset.Settings(16, 1, 5, renderer.variant), 4, {})
    dataset_writing.render_missing(small, 0)
    with pytest.raises(TrainingError, match=r"16 px images, .* 32 px: train on datasets of one resolution"):
        train.create_run("decoder", [data, dataset.open_dataset(str(tmp_path / "small"))], str(tmp_path), Config(1))
    with pytest.raises(TrainingError, match="no dataset to train on: give at least one --dataset"):
        train.create_run("decoder", [], str(tmp_path), Config(1))


@pytest.mark.parametrize("name", ["decoder", "encoder-8"])
def test_training_reduces_the_loss(tmp_path, data, name):
    metrics = train.train_network(
        name, data, str(tmp_path), Config(epochs=8, batch_size=8, learning_rate=3e-3), decoder=TINY_DECODER
    )
    losses = [record["train_loss"] for record in metrics["history"]]
    assert len(losses) == 8
    # the decoder learns the scene at once; an encoder on 46 samples first learns the mean (1/12 per parameter)
    assert losses[-1] < (0.7 if name == "decoder" else 0.95) * losses[0]
    assert metrics["training_samples"] == 46 and metrics["validation_samples"] == 2
    stored = json.loads((tmp_path / f"{name}.json").read_text())
    assert stored["epochs"] == 8 and stored["dataset"]["count"] == 48
    network = weight_files.load(weight_files.weights_path(str(tmp_path), name), resolution=32)
    assert network.info["metrics"]["validation_loss"] == pytest.approx(metrics["validation_loss"])


class Renders(train.Reporter):
    def __init__(self):
        self.calls = []

    def rendering(self, done: int, total: int) -> None:
        self.calls.append((done, total))


def test_refracting_decoder_renders_its_bases_once_and_ships_them(tmp_path, data, monkeypatch):
    monkeypatch.setattr(dataset, "BASIS_SPP", 64)  # the bases' logic, not their noise: 16 times cheaper
    copy = tmp_path / "data"
    shutil.copytree(data.path, copy)
    copied = dataset.open_dataset(str(copy))
    decoder = architectures.Decoder(
        resolution=32, hidden=32, base_channels=16, stage_channels=(16, 8, 8), glass_grid=(2, 2), medium_grid=(2, 2)
    )
    reporter = Renders()
    metrics = train.train_network(
        "decoder",
        copied,
        str(tmp_path / "model"),
        Config(epochs=4, batch_size=8, learning_rate=3e-3),
        reporter,
        decoder,
    )
    assert reporter.calls == [(1, 4), (2, 4), (3, 4), (4, 4), (1, 2), (2, 2)]  # glass 2 x 2, then media 1 x 2
    losses = [record["train_loss"] for record in metrics["history"]]
    assert losses[-1] < 0.85 * losses[0]  # 4 epochs on 46 samples: the loss falls
    assert "validation_rmse_transmissive" in metrics
    basis = np.load(copy / dataset.GLASS_FILE.format(specular=2, roughness=2))
    assert basis.shape == (2, 2, 32, 32, 3) and not (copy / "glass-2x2.parts").exists()
    # specular 0 is glass of index 1: the sphere vanishes, the floor and backdrop show through unbent
    np.testing.assert_allclose(basis[0, 0].mean(), copied.scene_image().mean(), rtol=0.1)
    assert np.abs(basis[1, 0] - basis[0, 0]).mean() > 0.01  # index 1.79 bends the checkers
    network = weight_files.load(weight_files.weights_path(str(tmp_path / "model"), "decoder"), resolution=32)
    np.testing.assert_allclose(network.variables["constants"]["glass"], basis, atol=2e-3)
    assert copied.glass_basis((2, 2)) is not None and len(reporter.calls) == 6  # kept: not rendered again
    medium = copied.medium_basis((2, 2))
    assert medium.shape == (2, 2, 32, 32, 3) and not (copy / "medium-2x2.parts").exists()
    # only scattered light: none at thickness 0 or albedo 0; a thick lossless medium scatters plenty
    assert np.all(medium[0] == 0.0) and np.all(medium[:, 1] == 0.0) and medium[1, 0].mean() > 0.02
    np.testing.assert_allclose(network.variables["constants"]["medium"], medium, atol=2e-3)


def test_an_interrupted_glass_basis_keeps_its_renders(tmp_path, data):
    copy = tmp_path / "data"
    shutil.copytree(data.path, copy)
    copied = dataset.open_dataset(str(copy))

    def stop_after_two(done, total):
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        copied.glass_basis((2, 2), stop_after_two)
    assert sorted(os.listdir(copy / "glass-2x2.parts")) == ["0-0.npy", "0-1.npy"]
    first = np.load(copy / "glass-2x2.parts" / "0-0.npy")
    basis = copied.glass_basis((2, 2))
    np.testing.assert_array_equal(basis[0, 0], first)


@pytest.mark.parametrize("arch", [1, 3])
def test_encoder_steps_fit_a_batch(data, arch):
    module = architectures.encoder(arch)
    tx = train.optimiser(Config(epochs=1, learning_rate=1e-3), steps_per_epoch=40)
    variables = architectures.initialise(module, jax.random.key(0), (32, 32, 3))
    train_step = train.make_train_step(module, tx, is_encoder=True)
    x, y = (np.asarray(a[:8], np.float32) for a in pipeline.training_arrays(f"encoder-{arch}", data))
    state = (variables["params"], tx.init(variables["params"]))
    losses = []
    for step in range(40):
        state, loss = train_step(state, {}, x, y, jax.random.key(step))
        losses.append(float(loss))
    assert losses[-1] < 0.6 * losses[0]  # below the 1/12 of predicting the mean: it fits


def test_interrupted_run_resumes_to_the_same_weights(tmp_path, data):
    config = Config(epochs=3, batch_size=8)
    whole = tmp_path / "whole"
    train.train_network("encoder-3", data, str(whole), config)
    parts = tmp_path / "parts"
    with pytest.raises(KeyboardInterrupt):
        train.train_network("encoder-3", data, str(parts), config, StopAfterOneEpoch())
    assert not os.path.exists(weight_files.weights_path(str(parts), "encoder-3"))
    resumed = train.train_network("encoder-3", data, str(parts), config)
    assert [r["epoch"] for r in resumed["history"]] == [1, 2, 3]
    a = weight_files.load(weight_files.weights_path(str(whole), "encoder-3"))
    b = weight_files.load(weight_files.weights_path(str(parts), "encoder-3"))
    assert weights_equal(a.variables, b.variables)
    # a finished run is found, not trained again
    again = train.train_network("encoder-3", data, str(parts), config)
    assert again["wall_time_s"] == resumed["wall_time_s"]


def test_save_load_round_trip_is_exact(tmp_path):
    module = architectures.encoder(8)
    variables = architectures.initialise(module, jax.random.key(3), (32, 32, 3))
    network = weight_files.Network(
        "encoder-8", architectures.architecture("encoder-8", 64), module, variables, {"note": "x"}
    )
    path = str(tmp_path / "e.msgpack")
    weight_files.save(path, network, dtype=np.float32)
    loaded = weight_files.load(path, resolution=64)
    assert weights_equal(loaded.variables, variables)
    assert loaded.info == {"note": "x"} and loaded.name == "encoder-8"
    weight_files.save(path, network)  # float16 storage: exactly the rounded weights come back
    rounded = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float16).astype(np.float32), variables)
    assert weights_equal(weight_files.load(path).variables, rounded)


def test_other_resolution_or_table_is_refused(tmp_path, monkeypatch):
    module = architectures.Decoder(resolution=16, hidden=8, base_channels=4, stage_channels=(4,))
    variables = architectures.initialise(module, jax.random.key(0), (19,))
    path = str(tmp_path / "decoder.msgpack")
    weight_files.save(
        path, weight_files.Network("decoder", architectures.architecture("decoder", 16, module), module, variables, {})
    )
    with pytest.raises(WeightsError, match="trained on 16 px images, not 64 px"):
        weight_files.load(path, resolution=64)
    changed = params.table_fingerprint()
    changed["parameters"][4] = {**changed["parameters"][4], "high": 2.0}
    monkeypatch.setattr(params, "table_fingerprint", lambda: changed)
    with pytest.raises(WeightsError, match=r"another parameter table .*'roughness'"):
        weight_files.load(path)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda b: b[: len(b) // 2], "not a readable weights file"),
        (lambda b: b"\x00" * 100, "not a readable weights file|not a matfit weights file"),
        (lambda b: b"", "not a readable weights file|not a matfit weights file"),
    ],
)
def test_corrupt_weights_are_refused(tmp_path, damage, message):
    module = architectures.encoder(8)
    variables = architectures.initialise(module, jax.random.key(0), (32, 32, 3))
    path = tmp_path / "encoder-8.msgpack"
    weight_files.save(
        str(path), weight_files.Network("encoder-8", architectures.architecture("encoder-8", 64), module, variables, {})
    )
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(WeightsError, match=message):
        weight_files.load(str(path))


def test_weights_that_are_not_a_regular_file_are_refused_at_once(tmp_path):
    # A FIFO planted in a model folder blocked the fit that loaded it, for ever.
    os.mkfifo(tmp_path / "decoder.msgpack")
    with pytest.raises(WeightsError, match=r"decoder\.msgpack: it is a FIFO \(named pipe\), not a regular file: del"):
        weight_files.load(str(tmp_path / "decoder.msgpack"))


def test_checkpoint_of_other_settings_or_damaged_is_refused(tmp_path, data):
    out = str(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        train.train_network("encoder-8", data, out, Config(epochs=2, batch_size=8), StopAfterOneEpoch())
    with pytest.raises(TrainingError, match=r"other settings \(batch_size 8 \(now 16\)\)"):
        train.train_network("encoder-8", data, out, Config(epochs=2, batch_size=16))
    checkpoint = checkpoints.checkpoint_path(out, "encoder-8")
    with open(checkpoint, "r+b") as file:
        file.truncate(200)
    with pytest.raises(WeightsError, match="not a readable checkpoint"):
        train.train_network("encoder-8", data, out, Config(epochs=2, batch_size=8))


def test_bad_settings_are_refused(tmp_path, data):
    with pytest.raises(TrainingError, match="epochs 0 is out of range"):
        train.train_network("encoder-8", data, str(tmp_path), Config(epochs=0))
    with pytest.raises(TrainingError, match=r"learning rate 2\.0 is out of range"):
        train.train_network("encoder-8", data, str(tmp_path), Config(epochs=1, learning_rate=2.0))
    with pytest.raises(TrainingError, match="batch size 64 does not fit 46"):
        train.train_network("encoder-8", data, str(tmp_path), Config(epochs=1, batch_size=64))


def test_unfinished_dataset_is_refused(tmp_path, renderer):
    path = str(tmp_path / "partial")
    dataset_writing.prepare(path, dataset.Settings(32, 1, 0, renderer.variant), 4, {})
    with pytest.raises(DatasetError, match="0/4 samples rendered"):
        train.train_network("decoder", dataset.open_dataset(path), str(tmp_path), Config(epochs=1, batch_size=1))


def test_arch_parsing():
    assert train_config.parse_arch("decoder") == ["decoder"]
    assert train_config.parse_arch("4") == ["encoder-4"]
    assert train_config.parse_arch("1..9") == [f"encoder-{i}" for i in range(1, 10)]
    assert train_config.parse_arch("all")[0] == "decoder" and len(train_config.parse_arch("all")) == 10
    for bad, message in (
        ("0", "arch 0 does not exist"),
        ("10", "arch 10 does not exist"),
        ("x", "not an architecture"),
    ):
        with pytest.raises(TrainingError, match=message):
            train_config.parse_arch(bad)


def test_encoder_input_box_filters_then_encodes():
    linear = np.zeros((64, 64, 3), np.float32)
    linear[:2, :2] = [1.0, 0.5, 0.0]
    out = models.encoder_input(linear)
    assert out.shape == (32, 32, 3)
    np.testing.assert_allclose(out[0, 0], [1.0, 0.7353569, 0.0], rtol=1e-6)
    assert out[0, 1].max() == 0.0


def test_encoder_input_clips_before_averaging_as_a_saved_picture_does():
    linear = np.zeros((64, 64, 3), np.float32)
    linear[:2, :2, 0] = [[4.0, 0.0], [0.0, 0.0]]  # an HDR highlight in one of four pixels
    rendered = models.encoder_input(linear)
    saved = models.encoder_input(images.srgb_decode(images.srgb_encode(linear)))
    np.testing.assert_allclose(rendered, saved, atol=1e-6)
    np.testing.assert_allclose(rendered[0, 0, 0], images.srgb_encode(np.float32(0.25)), rtol=1e-6)


def test_a_run_started_from_trained_weights_continues_from_them_and_resumes_exactly(tmp_path, data):
    base = str(tmp_path / "base")
    train.train_network("decoder", data, base, Config(epochs=8, batch_size=8, learning_rate=3e-3), decoder=TINY_DECODER)
    # written before a field of the architecture existed (the shipped decoder predates `absorption`): still this run's
    older = weight_files.load(weight_files.weights_path(base, "decoder"))
    description = {key: value for key, value in older.description.items() if key != "absorption"}
    weight_files.save(weight_files.weights_path(base, "decoder"), dataclasses.replace(older, description=description))
    started = weight_files.load(weight_files.weights_path(base, "decoder"))
    assert "absorption" not in started.description
    config = Config(epochs=2, batch_size=8, learning_rate=1e-3, start_from=base)
    run = train.create_run("decoder", data, str(tmp_path / "next"), config, TINY_DECODER)
    state = train.create_train_state(run)
    assert state.epoch == 0 and weights_equal(state.weights, started.variables["params"])
    whole = train.train_network("decoder", data, str(tmp_path / "whole"), config, decoder=TINY_DECODER)
    assert whole["start_sha256"] == started.identity() and whole["config"]["start_from"] == base
    assert whole["validation_loss"] < started.info["metrics"]["validation_loss"]
    parts = str(tmp_path / "parts")
    with pytest.raises(KeyboardInterrupt):
        train.train_network("decoder", data, parts, config, StopAfterOneEpoch(), TINY_DECODER)
    resumed = train.train_network("decoder", data, parts, config, decoder=TINY_DECODER)
    assert [r["epoch"] for r in resumed["history"]] == [1, 2]
    assert weights_equal(
        weight_files.load(weight_files.weights_path(parts, "decoder")).variables,
        weight_files.load(weight_files.weights_path(str(tmp_path / "whole"), "decoder")).variables,
    )
    # the start changed under an unfinished run: its checkpoint is refused, not silently mixed
    with pytest.raises(KeyboardInterrupt):
        train.train_network("decoder", data, str(tmp_path / "changed"), config, StopAfterOneEpoch(), TINY_DECODER)
    other = str(tmp_path / "other")
    train.train_network("decoder", data, other, Config(epochs=1, batch_size=8), decoder=TINY_DECODER)
    shutil.copy(weight_files.weights_path(other, "decoder"), weight_files.weights_path(base, "decoder"))
    with pytest.raises(TrainingError, match=r"started from other weights than .*base/decoder\.msgpack holds now"):
        train.train_network("decoder", data, str(tmp_path / "changed"), config, decoder=TINY_DECODER)


def test_a_start_that_cannot_start_the_run_is_refused(tmp_path, data):
    base = str(tmp_path / "base")
    train.train_network("encoder-8", data, base, Config(epochs=1, batch_size=8))
    with pytest.raises(TrainingError, match=r"start from .*base has no decoder\.msgpack: train the decoder there"):
        list(train.train_networks(["encoder-8", "decoder"], data, str(tmp_path / "m"), Config(1, 8, start_from=base)))
    assert not os.path.exists(tmp_path / "m")  # refused before anything was made or trained
    with pytest.raises(TrainingError, match="is the model directory being trained: train into another --out"):
        train.train_network("encoder-8", data, base, Config(1, 8, start_from=base))
    train.train_network("decoder", data, base, Config(epochs=1, batch_size=8), decoder=TINY_DECODER)
    other = architectures.Decoder(resolution=32, hidden=16, base_channels=16, stage_channels=(16, 8, 8))
    with pytest.raises(TrainingError, match=r"decoder\.msgpack is a decoder of another architecture"):
        train.train_network("decoder", data, str(tmp_path / "m"), Config(1, 8, start_from=base), decoder=other)


def test_a_run_may_grow_a_coarse_absorption_layer_on_trained_weights_but_not_drop_one(tmp_path, data, monkeypatch):
    monkeypatch.setattr(dataset, "BASIS_SPP", 16)  # the graft's logic, not the basis's noise
    copy = tmp_path / "data"
    shutil.copytree(data.path, copy)
    copied = dataset.open_dataset(str(copy))
    plain = architectures.Decoder(
        resolution=32, hidden=16, base_channels=8, stage_channels=(8, 8, 8), glass_grid=(2, 2)
    )
    coarse = plain.clone(coarse_absorption=True)
    base = str(tmp_path / "base")
    train.train_network("decoder", copied, base, Config(epochs=1, batch_size=8), decoder=plain)
    started = weight_files.load(weight_files.weights_path(base, "decoder"))
    run = train.create_run("decoder", copied, str(tmp_path / "grown"), Config(1, 8, start_from=base), coarse)
    state = train.create_train_state(run)
    grown = dict(state.weights)
    path = grown.pop("path")  # the new layer starts fresh (a zero kernel); every trained weight is the start's
    assert weights_equal(grown, started.variables["params"]) and not np.any(np.asarray(path["kernel"]))
    metrics = train.train_network(
        "decoder", copied, str(tmp_path / "grown"), Config(1, 8, start_from=base), decoder=coarse
    )
    assert metrics["start_sha256"] == started.identity()
    with pytest.raises(TrainingError, match=r"decoder\.msgpack is a decoder of another architecture"):
        train.create_run(
            "decoder", copied, str(tmp_path / "dropped"), Config(1, 8, start_from=str(tmp_path / "grown")), plain
        )


def test_the_linear_loss_learns_the_encoding_of_the_mean_render_where_the_srgb_loss_learns_a_darker_one():
    # One pixel of mean 0.6, rendered with noise (gamma-distributed, 15% of the values above 1):
    # the sRGB loss's optimum, the mean of the encodings, lies 18.4 of 255 below the encoding of
    # the mean; the linear loss's lies at it, but for the 0.2 that clipping the residual costs.
    linear = np.random.default_rng(0).gamma(2.0, 0.3, 200_000).astype(np.float32)
    truth = float(images.srgb_encode(linear.mean()))

    def optimum(loss: str) -> float:
        target = jnp.asarray(linear if loss == "linear" else images.srgb_encode(linear))
        slope = jax.grad(lambda p: losses.image_loss(jnp.full(target.shape, p), target, loss))
        low, high = 0.0, 1.0
        for _ in range(30):  # the loss is convex in p: bisect on the sign of its slope
            low, high = ((low + high) / 2, high) if slope((low + high) / 2) < 0 else (low, (low + high) / 2)
        return low

    assert optimum("srgb") == pytest.approx(float(images.srgb_encode(linear).mean()), abs=1e-6)
    assert (truth - optimum("srgb")) * 255 == pytest.approx(18.38, abs=0.01)
    assert (truth - optimum("linear")) * 255 == pytest.approx(0.22, abs=0.01)


def test_the_linear_residual_is_clipped_to_one_full_scale():
    prediction = jnp.array([0.5, 0.5, 0.0, 1.0])
    residual = losses.linear_residual(prediction, jnp.array([8.0, 0.0, 0.5, 1.0]))
    # 0.5 encodes 0.2140 linear, where the curve rises 1.0804 per linear unit: -0.2140 x 1.0804
    np.testing.assert_allclose(residual, [1.0, -0.2312, 1.0, 0.0], atol=2e-4)


def test_a_decoder_trained_with_the_linear_loss_is_judged_against_the_encoded_renders(tmp_path, data):
    inputs, targets, _ = train.split("decoder", [data], 0.05, linear=True)
    np.testing.assert_array_equal(targets, np.maximum(np.asarray(data.images), 0).astype(np.float16))
    metrics = train.train_network(
        "decoder",
        data,
        str(tmp_path),
        Config(epochs=8, batch_size=8, learning_rate=3e-3, loss="linear"),
        decoder=TINY_DECODER,
    )
    assert metrics["config"]["loss"] == "linear"
    # Its loss holds the 4-spp targets' noise in linear light: the picture's error tells more.
    judged = [record["validation_rmse"] for record in metrics["history"]]
    assert judged[-1] < 0.85 * judged[0]
    network = weight_files.load(str(tmp_path / "decoder.msgpack"))
    predictions = models.apply(network.module, network.variables, inputs[46:])
    expected = images.rmse(np.asarray(predictions, np.float64), pipeline.srgb_targets(data)[46:].astype(np.float64))
    assert metrics["validation_rmse"] == pytest.approx(float(expected.mean()), abs=0.05)
    with pytest.raises(TrainingError, match=r"other settings \(loss linear \(now srgb\)\)"):
        train.train_network(
            "decoder", data, str(tmp_path), Config(epochs=8, batch_size=8, learning_rate=3e-3), decoder=TINY_DECODER
        )
    with pytest.raises(TrainingError, match="loss 'l1' is unknown: use srgb or linear"):
        train.train_network("decoder", data, str(tmp_path / "other"), Config(epochs=1, loss="l1"))


ROOT = pathlib.Path(__file__).resolve().parent.parent  # the repository


def makefile_model_commands(makefile: str) -> list[list[str]]:
    """Returns the `make model` recipe's matfit commands, each split into words (after `$(BIN)/matfit`), with
    `$(DECODER_DATA)` replaced by its definition's words."""
    decoder_data = makefile.split("\nDECODER_DATA = ", 1)[1].split("\n", 1)[0].split()
    recipe = makefile.split("\nmodel:", 1)[1].split("\n\n", 1)[0]
    commands = [line.split()[1:] for line in recipe.splitlines()[1:] if line.strip().startswith("$(BIN)/matfit")]
    return [[part for w in words for part in (decoder_data if w == "$(DECODER_DATA)" else [w])] for words in commands]


def options_of(words: list[str]) -> dict[str, list[str]]:
    """Returns every `--name value` of a command (repeated options in order; a flag's value is "")."""
    found: dict[str, list[str]] = {}
    for k, word in enumerate(words):
        if word.startswith("--"):
            value = words[k + 1] if k + 1 < len(words) and not words[k + 1].startswith("--") else ""
            found.setdefault(word, []).append(value)
    return found


def test_make_model_trains_what_ships():
    """The shipped decoder's and encoders' datasets (down to their parameters' hashes), its schedule and its
    architecture are what the Makefile's `model` recipe renders and trains."""
    commands = makefile_model_commands((ROOT / "Makefile").read_text())
    rendered = {}
    for words in (w for w in commands if w[0] == "render-dataset"):
        found = options_of(words)
        sampler = found.get("--sampler", ["uniform"])[0]
        count, seed = int(found["--count"][0]), int(found["--seed"][0])
        units = [params.sample_index(seed, i, sampler) for i in range(count)]
        values = np.stack([params.from_unit(unit) for unit in units]).astype(np.float32)
        rendered[words[1]] = {
            "count": count,
            "resolution": int(found["--resolution"][0]),
            "spp": int(found["--spp"][0]),
            "seed": seed,
            "sampler": sampler,
            "params_sha256": hashlib.sha256(values.tobytes()).hexdigest(),
        }
    trains = [options_of(words) for words in commands if words[0] == "train"]
    shipped = ROOT / "matfit" / "data" / "model"
    for network, found in (("decoder", trains[1]), ("encoder-1", trains[2])):
        metrics = json.loads((shipped / f"{network}.json").read_text())
        identities = metrics["dataset"] if isinstance(metrics["dataset"], list) else [metrics["dataset"]]
        trained_on = [{**each, "sampler": each.get("sampler", "uniform")} for each in identities]
        expected = [rendered[path] for path in found["--dataset"]]
        assert [{key: each[key] for key in expected[0]} for each in trained_on] == expected, network
    decoder = json.loads((shipped / "decoder.json").read_text())["config"]
    last = trains[1]
    assert decoder["epochs"] == int(last["--epochs"][0]) and decoder["loss"] == last["--loss"][0]
    assert decoder["learning_rate"] == float(last["--learning-rate"][0])
    assert decoder["start_from"] == last["--start-from"][0] == trains[0]["--out"][0]
    architecture = weight_files.load(str(shipped / "decoder.msgpack")).description
    assert architecture == architectures.architecture(
        "decoder", 64, architectures.trained_decoder(64, "--coarse-absorption" in last)
    )
    assert ("--coarse-absorption" in trains[0]) == ("--coarse-absorption" in last)


def test_a_refused_train_leaves_no_folder(tmp_path, data, renderer):
    """Backward ranges, an unfinished dataset, a start of another architecture, encoders on 16 px images (--arch 9
    left out/checkpoints/, --arch all,1 trained the decoder before refusing the encoders): one error line, exit 2,
    no out/, before any work."""
    from typer.testing import CliRunner

    from matfit.app.cli import app

    partial = str(tmp_path / "partial")
    dataset_writing.prepare(partial, dataset.Settings(32, 1, 0, renderer.variant), 4, {})
    base = tmp_path / "base"  # an encoder 8 trained on 64 px images: it cannot start a run on 32 px ones
    base.mkdir()
    encoder = architectures.encoder(8)
    variables = architectures.initialise(encoder, jax.random.key(1), (32, 32, 3))
    network = weight_files.Network("encoder-8", architectures.architecture("encoder-8", 64), encoder, variables, {})
    weight_files.save(weight_files.weights_path(str(base), "encoder-8"), network)
    small = str(tmp_path / "small")  # 16 px: the decoder trains on it, the encoders cannot
    dataset_writing.render_missing(
        dataset_writing.prepare(small, dataset.Settings(16, 1, 0, renderer.variant), 4, {}), 0
    )
    cases = [
        (["--arch", "9", "--dataset", small, "--batch-size", "1"], "encoders need images whose side is a multiple"),
        (["--arch", "all,1", "--dataset", small, "--batch-size", "1"], f"{small} has 16: render one at 64 px"),
        (["--arch", "9..1", "--dataset", data.path], "error: --arch 9..1 is an empty range: give it from low to high"),
        (["--arch", "3..2,8", "--dataset", data.path], "error: --arch 3..2 is an empty range"),
        (["--arch", "8", "--dataset", partial, "--batch-size", "1"], "0/4 samples rendered"),
        (["--arch", "8", "--dataset", data.path, "--batch-size", "8", "--start-from", base], "of another architecture"),
    ]
    for arguments, message in cases:
        out = tmp_path / "out"
        result = CliRunner().invoke(app, ["train", *map(str, arguments), "--epochs", "1", "--out", str(out)])
        assert result.exit_code == 2, result.output
        assert len(result.output.splitlines()) == 1 and message in result.output, result.output
        assert not out.exists(), f"{arguments}: the refused run left {sorted(os.listdir(out))} in out/"
