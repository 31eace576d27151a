"""Training the decoder and the encoders on a rendered dataset, resumably.

`train_network` trains one network ("decoder" or "encoder-N") on a finished `matfit render-dataset`
directory, in the Flax examples' steps: `create_run` (module, data split, optimiser),
`create_train_state` (fresh or resumed), `train_epoch`, `finish`. What a run is asked for is
`train_config`, what it minimises and how it is judged `losses`, its resumable state `checkpoints`:

- the last `validation_fraction` of the samples are held out and never trained on;
- the decoder learns parameters -> sRGB image, or the encoding of the mean linear render
  (`losses`); an encoder learns `models.encoder_input(image)` -> parameters;
- Adam with a warm-up + cosine schedule over the whole run, so a run is defined by its settings;
- after every epoch the whole training state is written atomically (`checkpoints`). Shuffling
  and dropout depend only on (seed, network, epoch, step), so a run that is interrupted and
  resumed ends with the same weights as one that was not;
- at the end the weights are rounded to float16 (what ships), validated, and written to
  `<out>/<name>.msgpack` with their metrics, plus a readable `<out>/<name>.json`;
- `Config.start_from` names a model directory whose weights of the same network start the run
  instead of fresh ones (more epochs at a lower rate: docs/training.md#training); its file's
  hash is part of the run, so a resume from a changed file is refused. The run's decoder may have a
  `GROWABLE` layer the start lacks (`grafted`): it starts fresh, near the identity, the rest as trained.
"""

from __future__ import annotations

import functools
import hashlib
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
import optax

from matfit import documents, files, images
from matfit.errors import TrainingError
from matfit.model import architectures, dataset, models, pipeline, weight_files
from matfit.model.architectures import NETWORKS
from matfit.model.checkpoints import Checkpoint, checkpoint_path, load_checkpoint, save_checkpoint
from matfit.model.dataset import Dataset
from matfit.model.losses import image_loss, validation_metrics
from matfit.model.train_config import Config, validation_count

if TYPE_CHECKING:
    import flax.linen as nn

# Decoder fields that add a layer, so that `Config.start_from` may add it to trained weights: it starts fresh
# (with `path_start` 0 the decoder then draws what it drew; other starts change the picture at once).
GROWABLE = ("coarse_absorption", "path_start")


def as_datasets(data: Dataset | Sequence[Dataset]) -> list[Dataset]:
    """Returns one dataset or several as a non-empty list, checking that their images are of one size."""
    datasets = [data] if isinstance(data, Dataset) else list(data)
    if not datasets:
        raise TrainingError("no dataset to train on: give at least one --dataset", field="dataset")
    for other in datasets[1:]:
        if other.resolution != datasets[0].resolution:
            raise TrainingError(
                f"{other.path} holds {other.resolution} px images, {datasets[0].path} {datasets[0].resolution} px: "
                "train on datasets of one resolution",
                field="dataset",
            )
    return datasets


def split(
    name: str, datasets: list[Dataset], fraction: float, linear: bool = False
) -> tuple[np.ndarray, np.ndarray, int]:
    """Returns (inputs, targets, training samples) of network `name` over several datasets.

    The last `fraction` of each dataset is held out, and the held-out samples are placed after every
    training sample: `inputs[:training]` is what trains, the rest what validates. For one dataset
    this is its own order, as before several were allowed. `linear`: the decoder's targets are the
    linear renders (`pipeline.training_arrays`).
    """
    parts = [pipeline.training_arrays(name, data, linear) for data in datasets]
    kept = [data.count - validation_count(data.count, fraction) for data in datasets]
    order = [(x[:n], y[:n]) for (x, y), n in zip(parts, kept, strict=True)]
    order += [(x[n:], y[n:]) for (x, y), n in zip(parts, kept, strict=True)]
    inputs = np.concatenate([x for x, _ in order]) if len(parts) > 1 else parts[0][0]
    targets = np.concatenate([y for _, y in order]) if len(parts) > 1 else parts[0][1]
    return inputs, targets, sum(kept)


def dataset_identity(data: Dataset) -> dict:
    """Returns what identifies a dataset's content wherever it lies: its settings and a hash of its parameters."""
    digest = hashlib.sha256(np.ascontiguousarray(data.params).tobytes()).hexdigest()
    meta = data.meta
    return {
        "count": data.count,
        "resolution": data.resolution,
        "spp": int(meta["spp"]),
        "seed": int(meta["seed"]),
        "variant": meta.get("variant"),
        "sampler": dataset.sampler_of(meta),
        "params_sha256": digest,
    }


def optimiser(config: Config, steps_per_epoch: int) -> optax.GradientTransformation:
    """Returns Adam with a linear warm-up and a cosine decay over the whole run.

    One object per learning rate and run length in a process, so that runs of the same network and settings (a run
    resumed, or trained again) find their compiled train step (`make_train_step`) instead of compiling it again.
    """
    assert config.epochs is not None, "Config.check refused None"
    return _adam(config.learning_rate, config.epochs * steps_per_epoch)


@functools.cache
def _adam(learning_rate: float, total: int) -> optax.GradientTransformation:
    schedule = optax.warmup_cosine_decay_schedule(
        init_value=0.0,
        peak_value=learning_rate,
        warmup_steps=min(500, max(1, total // 10)),
        decay_steps=total,
        end_value=learning_rate * 0.01,
    )
    return optax.adam(schedule)


@functools.cache
def make_train_step(module, tx: optax.GradientTransformation, is_encoder: bool, loss: str = "srgb"):
    """Returns the jitted train_step(state, constants, x, y, key) -> (state, loss) of a module.

    One per module, optimiser, kind and loss in a process: the modules are frozen dataclasses that compare by their
    settings, so a second run of the same network with the same settings reuses the compiled step.

    state = (weights, optimiser state); constants: the module's untrained variables (the refracting
    decoder's bases), passed in rather than captured so that they are not compiled in. With `loss`
    "linear" (the decoder only) y is the linear render and the loss is the mean squared
    `linear_residual`, whose gradient pulls each pixel towards the encoding of the mean render.
    """

    def loss_fn(weights, constants, x, y, key):
        if is_encoder:
            prediction = module.apply({"params": weights}, x, train=True, rngs={"dropout": key})
        else:
            prediction = module.apply({"params": weights, **constants}, x)
        return image_loss(prediction, y, "srgb" if is_encoder else loss)

    @jax.jit
    def train_step(state, constants, x, y, key):
        # Batches arrive as stored (float16 images): casting here, on the accelerator, is exact
        # and far cheaper for the host than NumPy's cast (docs/training.md#gpu).
        x, y = x.astype(jnp.float32), y.astype(jnp.float32)
        weights, opt_state = state
        loss, grads = jax.value_and_grad(loss_fn)(weights, constants, x, y, key)
        with jax.numpy_dtype_promotion("standard"):  # optax mixes Python floats with its int32 step count
            updates, opt_state = tx.update(grads, opt_state, weights)
        return (optax.apply_updates(weights, updates), opt_state), loss

    return train_step


class Reporter:
    """Receives progress (`progress.TrainingProgress` shows it); the default ignores it."""

    def start_epoch(self, name: str, epoch: int, epochs: int, steps: int) -> None:
        """Called before each epoch."""

    def step(self, step: int, loss: float, samples_per_second: float) -> None:
        """Called after training steps."""

    def end_epoch(self, record: dict) -> None:
        """Called after each epoch, once its checkpoint is written, with its history record."""

    def rendering(self, done: int, total: int) -> None:
        """Called after each render of a refracting decoder's clear-glass or scattering basis."""


@dataclass(frozen=True)
class Run:
    """What stays fixed while one network trains: the module, the data split, the optimiser, the files."""

    name: str
    description: dict
    module: nn.Module
    inputs: np.ndarray
    targets: np.ndarray
    training_samples: int
    steps: int
    tx: optax.GradientTransformation
    root: jax.Array  # the network's PRNG key; epochs and steps fold into it
    config: Config
    identity: dict | list  # the dataset's identity, or a list of them
    checkpoint_file: str
    weights_file: str
    constants: dict  # untrained variables: the refracting decoder's clear-glass and scattering bases, else none
    start: weight_files.Network | None = None  # the trained network the run starts from (Config.start_from), else none

    def variables(self, weights: dict) -> dict:
        """Returns the module's whole variables for trained `weights`."""
        return {"params": weights, **self.constants}

    @property
    def linear(self) -> bool:
        """Whether the targets are linear renders (`linear_targets`), not encoded ones."""
        return linear_targets(self.name, self.config)

    @property
    def network_index(self) -> int:
        """Returns the network's place in NETWORKS, which separates its random streams from the others'."""
        return NETWORKS.index(self.name)


def create_run(
    name: str,
    data: Dataset | Sequence[Dataset],
    out: str,
    config: Config,
    decoder: architectures.Decoder | None = None,
    reporter: Reporter | None = None,
) -> Run:
    """Returns the run of network `name` on finished datasets; `decoder` replaces the decoder (a tiny one in tests).

    A refracting decoder's bases are rendered into the first dataset if they are not there.
    """
    datasets = as_datasets(data)
    description, start = check_run(name, datasets, out, config, decoder)
    weights_file = weight_files.weights_path(out, name)
    checkpoint_file = checkpoint_path(out, name)
    os.makedirs(os.path.dirname(checkpoint_file), exist_ok=True)
    files.check_writable(weights_file)
    linear = linear_targets(name, config)
    inputs, targets, training_samples = split(name, datasets, config.validation_fraction, linear)
    steps = training_samples // config.batch_size
    root = jax.random.fold_in(jax.random.key(config.seed), NETWORKS.index(name))
    module = architectures.build(description)
    constants = {}
    if isinstance(module, architectures.Decoder) and module.glass_grid:
        progress = reporter.rendering if reporter else None
        glass = datasets[0].glass_basis(tuple(module.glass_grid), progress)
        medium = datasets[0].medium_basis(tuple(module.medium_grid), progress) if module.medium_grid else None
        constants = architectures.with_bases(module, {}, glass, medium)
    return Run(
        name,
        description,
        module,
        inputs,
        targets,
        training_samples,
        steps,
        optimiser(config, steps),
        root,
        config,
        dataset_identity(datasets[0]) if len(datasets) == 1 else [dataset_identity(each) for each in datasets],
        checkpoint_file,
        weights_file,
        constants,
        start,
    )


def check_run(
    name: str, datasets: list[Dataset], out: str, config: Config, decoder: architectures.Decoder | None = None
) -> tuple[dict, weight_files.Network | None]:
    """Returns (the architecture record, the starting network or None) of a run, having checked everything that
    can refuse it (datasets, settings, the start's weights) without writing anything."""
    if name not in NETWORKS:
        raise TrainingError(f"unknown network {name!r}: use decoder or 1 to 9", field="arch")
    for each in datasets:
        pipeline.check_finished(each)
        if name != architectures.DECODER:
            pipeline.check_encoder_resolution(each)
    config.check(sum(each.count for each in datasets))
    description = architectures.architecture(name, datasets[0].resolution, decoder)
    if architectures.architecture_problem(description) is not None:
        raise TrainingError(
            f"{datasets[0].path} holds {datasets[0].resolution} px images; networks are trained on "
            f"{', '.join(map(str, architectures.RESOLUTIONS))} px: render a dataset of one of these resolutions",
            field="dataset",
        )
    return description, starting_network(name, config, out, description)


def linear_targets(name: str, config: Config) -> bool:
    """Whether network `name` trains on linear renders: the decoder with `Config.loss` "linear"."""
    return name == architectures.DECODER and config.loss == "linear"


def start_path(name: str, config: Config, out: str) -> str | None:
    """Returns the weights file that starts network `name` (None: fresh weights); refuses one that cannot."""
    if config.start_from is None:
        return None
    if os.path.abspath(config.start_from) == os.path.abspath(out):
        raise TrainingError(
            f"start from {config.start_from} is the model directory being trained: train into another --out",
            field="start_from",
        )
    path = weight_files.weights_path(config.start_from, name)
    if not os.path.exists(path):
        raise TrainingError(
            f"start from {config.start_from} has no {os.path.basename(path)}: train the {name} there first, "
            "or give the model directory that holds it",
            field="start_from",
        )
    return path


def starting_network(name: str, config: Config, out: str, description: dict) -> weight_files.Network | None:
    """Returns network `name` of the model directory `config.start_from`, checked to be of this run's architecture."""
    path = start_path(name, config, out)
    if path is None:
        return None
    network = weight_files.load(path, name=name)
    # Described again from its module: a file written before a field of the architecture existed
    # (the shipped decoder predates `absorption`) holds that field's default implicitly.
    described = architectures.architecture(
        name, network.resolution, network.module if isinstance(network.module, architectures.Decoder) else None
    )
    # A layer that starts as (nearly) the identity may be added to trained weights: it starts fresh.
    grown = {field: description[field] for field in GROWABLE if description.get(field) and not described.get(field)}
    if {**described, **grown} != description:
        raise TrainingError(
            f"{path} is a {name} of another architecture or resolution than this run's: "
            "start from a network trained with the same architecture on images of the same size",
            field="start_from",
        )
    return network


def grafted(fresh: dict, trained: dict) -> dict:
    """Returns `fresh` weights with every trained leaf in its place (as float32); the layers only `fresh`
    has (a `GROWABLE` one) keep their initial values."""
    out = dict(fresh)
    for key, value in trained.items():
        out[key] = grafted(fresh[key], value) if isinstance(value, dict) else jnp.asarray(value, jnp.float32)
    return out


def start_identity(run: Run) -> str | None:
    """Returns the SHA-256 of the weights file the run starts from (None: fresh weights)."""
    return None if run.start is None else run.start.identity()


def create_train_state(run: Run) -> Checkpoint:
    """Returns the state to continue from: the run's checkpoint if there is one, else the starting network's
    weights (`Config.start_from`) or fresh ones, with a fresh optimiser."""
    weights = architectures.initialise(run.module, run.root, architectures.input_shape(run.description))["params"]
    if run.start is not None:
        weights = grafted(weights, run.start.variables["params"])
    state = Checkpoint(0, weights, run.tx.init(weights))
    if os.path.exists(run.checkpoint_file):
        state = load_checkpoint(
            run.checkpoint_file, run.name, run.description, run.config, run.identity, state, start_identity(run)
        )
    return state


def train_epoch(run: Run, train_step, state: Checkpoint, reporter: Reporter) -> Checkpoint:
    """Returns the state after one more epoch, its validation figures appended to the history.

    Shuffling and dropout depend only on (seed, network, epoch, step), so an epoch gives the same
    weights whether or not the run was interrupted before it.
    """
    assert run.config.epochs is not None, "Config.check refused None"
    epoch = state.epoch + 1
    batch_size = run.config.batch_size
    reporter.start_epoch(run.name, epoch, run.config.epochs, run.steps)
    started = time.perf_counter()
    order = np.random.default_rng([run.config.seed, run.network_index, epoch]).permutation(run.training_samples)
    epoch_key = jax.random.fold_in(run.root, epoch)
    training, losses = (state.weights, state.opt_state), []
    for step in range(run.steps):
        batch = order[step * batch_size : (step + 1) * batch_size]
        x, y = run.inputs[batch], run.targets[batch]
        training, loss = train_step(training, run.constants, x, y, jax.random.fold_in(epoch_key, step))
        losses.append(loss)
        if step % 10 == 9 or step == run.steps - 1:
            reporter.step(step + 1, float(loss), (step + 1) * batch_size / (time.perf_counter() - started))
    figures = validate(run, training[0])
    record = {
        "epoch": epoch,
        "train_loss": float(np.mean(jax.device_get(losses))),
        **{key: value for key, value in figures.items() if not key.endswith("_by_name")},
        "seconds": time.perf_counter() - started,
    }
    return Checkpoint(epoch, training[0], training[1], [*state.history, record], state.seconds + record["seconds"])


def validate(run: Run, weights: dict) -> dict:
    """Returns the validation figures of `weights` on the held-out samples."""
    predictions = models.apply_in_batches(run.module, run.variables(weights), run.inputs[run.training_samples :])
    held_out = slice(run.training_samples, None)
    targets = run.targets[held_out]
    if run.linear:  # judged as ever: against the encoded renders
        targets = images.srgb_encode(targets)
    return validation_metrics(run.name, predictions, targets, run.inputs[held_out])


def finish(run: Run, state: Checkpoint) -> dict:
    """Rounds the weights to float16 (what ships), validates them and saves them; returns the metrics.

    Writes `<name>.msgpack` (the network, with its metrics) and `<name>.json` (the metrics alone).
    """
    shipped = jax.tree_util.tree_map(lambda leaf: jnp.asarray(leaf, jnp.float16).astype(jnp.float32), state.weights)
    metrics = {
        "network": run.name,
        "epochs": run.config.epochs,
        "training_samples": run.training_samples,
        "validation_samples": len(run.inputs) - run.training_samples,
        "wall_time_s": round(state.seconds, 1),
        "dataset": run.identity,
        "config": asdict(run.config),
        "start_sha256": start_identity(run),
        "weights_dtype": "float16",
        "parameter_count": architectures.parameter_count({"params": shipped}),
        **validate(run, shipped),
        "history": state.history,
    }
    network = weight_files.Network(run.name, run.description, run.module, run.variables(shipped), {"metrics": metrics})
    weight_files.save(run.weights_file, network)
    files.write_text(os.path.splitext(run.weights_file)[0] + ".json", documents.dumps(metrics))
    return metrics


def train_network(
    name: str,
    data: Dataset | Sequence[Dataset],
    out: str,
    config: Config,
    reporter: Reporter | None = None,
    decoder: architectures.Decoder | None = None,
) -> dict:
    """Trains (or resumes, or finds finished) network `name` and returns its final metrics.

    After every epoch the whole state is checkpointed; an interruption (Ctrl-C, kill -9, an
    exception from the reporter) loses at most the epoch under way.
    """
    reporter = reporter or Reporter()
    run = create_run(name, data, out, config, decoder, reporter)
    assert config.epochs is not None, "Config.check (in create_run) refused None"
    state = create_train_state(run)
    if state.epoch == config.epochs and os.path.exists(run.weights_file):
        return weight_files.load(run.weights_file).info["metrics"]
    train_step = make_train_step(run.module, run.tx, name != architectures.DECODER, config.loss)
    while state.epoch < config.epochs:
        state = train_epoch(run, train_step, state, reporter)
        save_checkpoint(run.checkpoint_file, name, run.description, config, run.identity, state, start_identity(run))
        reporter.end_epoch(state.history[-1])
    return finish(run, state)


def train_networks(
    names: list[str],
    data: Dataset | Sequence[Dataset],
    out: str,
    config: Config,
    reporter: Reporter | None = None,
    coarse_absorption: bool = False,
):
    """Trains the named networks one after another into model directory `out`; yields (name, metrics) for each.

    With `coarse_absorption` the decoder has the coarse absorption layer (`architectures.trained_decoder`).
    """
    if os.path.exists(out) and not os.path.isdir(out):
        raise files.OutputError(f"model directory {out} is a file: give a directory for the model", field="out")
    files.check_folder(out)  # read-only, or under a file: refused with the fix, as `fit` does
    datasets = as_datasets(data)
    decoder = architectures.trained_decoder(datasets[0].resolution, coarse_absorption)
    for name in names:  # everything checked before the model directory is made: a refusal leaves no folder
        check_run(name, datasets, out, config.for_network(name), decoder)
    os.makedirs(out, exist_ok=True)
    for name in names:
        yield name, train_network(name, data, out, config.for_network(name), reporter, decoder)


def summary(name: str, metrics: dict) -> str:
    """Returns one line on a trained network: epochs, validation figure, time."""
    if "validation_rmse" in metrics:
        figure = f"validation image RMSE {metrics['validation_rmse']:.2f} (0-255 sRGB)"
    else:
        figure = f"validation parameter RMSE {metrics['validation_parameter_rmse']:.4f} (unit cube)"
    return f"{name}: {metrics['epochs']} epochs, {figure}, {metrics['wall_time_s']:.0f} s"
