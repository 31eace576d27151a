"""Training the decoder and the encoders on a rendered dataset, resumably.

One function, `train_network`, trains one network ("decoder" or "encoder-N") on a finished
`matfit render-dataset` directory:

- the last `validation_fraction` of the samples are held out and never trained on;
- the decoder learns parameters -> sRGB image (L2 on sRGB values, as the paper's RMSE);
  an encoder learns `models.encoder_input(image)` -> parameters (L2 on the unit cube);
- Adam with a warm-up + cosine schedule over the whole run, so a run is defined by its settings;
- after every epoch the whole training state (weights, optimiser, history) is written atomically
  to `<out>/checkpoints/<name>.ckpt`. Shuffling and dropout depend only on (seed, network,
  epoch, step), so a run that is interrupted and resumed ends with the same weights as one that
  was not;
- at the end the weights are rounded to float16 (what ships), validated, and written to
  `<out>/<name>.msgpack` with their metrics, plus a readable `<out>/<name>.json`.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization

from matfit import files, images, models, params
from matfit.dataset import Dataset

CHECKPOINT_FORMAT = "matfit-checkpoint"
NETWORKS = (models.DECODER, *models.ENCODER_NAMES)
# The paper trains the isomorphic encoders 6, 7 and 9 for different numbers of epochs.
# Sized so that `make model` trains all ten in about 50 minutes on a 2-core CPU (README).
DEFAULT_EPOCHS = {
    models.DECODER: 20,
    **{name: 10 for name in models.ENCODER_NAMES},
    "encoder-4": 8,
    "encoder-5": 8,
    "encoder-7": 5,
    "encoder-9": 20,
}
CONVERT_CHUNK = 1024


class TrainingError(ValueError):
    """Training cannot start or resume; the message names the file or value and the fix."""


@dataclass(frozen=True)
class Config:
    """What defines a training run: resuming needs the same values."""

    epochs: int
    batch_size: int = 64
    learning_rate: float = 1e-3
    validation_fraction: float = 0.05
    seed: int = 0

    def check(self, samples: int) -> None:
        """Raises TrainingError for values that cannot train on `samples` samples."""
        if not 1 <= self.epochs <= 10000:
            raise TrainingError(f"--epochs {self.epochs} is out of range: use 1 to 10000")
        if not 0.0 < self.validation_fraction < 0.5:
            raise TrainingError(f"validation fraction {self.validation_fraction} is out of range: use a value in (0, 0.5)")
        training = samples - validation_count(samples, self.validation_fraction)
        if not 1 <= self.batch_size <= training:
            raise TrainingError(f"--batch-size {self.batch_size} does not fit {training} training samples: use 1 to {training}")


def validation_count(samples: int, fraction: float) -> int:
    """Returns how many of the last samples are held out for validation (at least one)."""
    return max(1, round(samples * fraction))


def dataset_identity(data: Dataset) -> dict:
    """Returns what identifies a dataset's content: its settings and a hash of its parameters."""
    digest = hashlib.sha256(np.ascontiguousarray(data.params).tobytes()).hexdigest()
    meta = data.meta
    return {
        "path": os.path.abspath(data.path),
        "count": data.count,
        "resolution": data.resolution,
        "spp": int(meta["spp"]),
        "seed": int(meta["seed"]),
        "variant": meta.get("variant"),
        "params_sha256": digest,
    }


def check_finished(data: Dataset) -> None:
    """Raises TrainingError unless every sample of the dataset has been rendered."""
    if data.finished < data.count:
        raise TrainingError(
            f"{data.path} has {data.finished}/{data.count} samples rendered: finish it with "
            f"`matfit render-dataset {data.path} --count {data.count}` (same settings) before training"
        )


def srgb_targets(data: Dataset) -> np.ndarray:
    """Returns every image sRGB-encoded, float16 (count, R, R, 3), converted in chunks."""
    out = np.empty(data.images.shape, np.float16)
    for start in range(0, data.count, CONVERT_CHUNK):
        chunk = np.asarray(data.images[start : start + CONVERT_CHUNK], np.float32)
        out[start : start + CONVERT_CHUNK] = images.srgb_encode(chunk)
    return out


def encoder_inputs(data: Dataset) -> np.ndarray:
    """Returns every image as the encoders see it, float16 (count, 32, 32, 3)."""
    side = models.ENCODER_RESOLUTION
    if data.resolution % side:
        raise TrainingError(
            f"encoders need images whose side is a multiple of {side} px; {data.path} has {data.resolution}: render one at 64 px"
        )
    out = np.empty((data.count, side, side, 3), np.float16)
    for start in range(0, data.count, CONVERT_CHUNK):
        out[start : start + CONVERT_CHUNK] = models.encoder_input(np.asarray(data.images[start : start + CONVERT_CHUNK], np.float32))
    return out


def training_arrays(name: str, data: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Returns (inputs, targets) of network `name` for every sample of the dataset."""
    unit = data.unit_params()
    if name == models.DECODER:
        return unit, srgb_targets(data)
    return encoder_inputs(data), unit


def optimiser(config: Config, steps_per_epoch: int) -> optax.GradientTransformation:
    """Returns Adam with a linear warm-up and a cosine decay over the whole run."""
    total = config.epochs * steps_per_epoch
    schedule = optax.warmup_cosine_decay_schedule(
        init_value=0.0,
        peak_value=config.learning_rate,
        warmup_steps=min(500, max(1, total // 10)),
        decay_steps=total,
        end_value=config.learning_rate * 0.01,
    )
    return optax.adam(schedule)


def make_train_step(module, tx: optax.GradientTransformation, is_encoder: bool):
    """Returns the jitted train_step(state, x, y, key) -> (state, loss) of a module; state = (weights, optimiser state)."""

    def loss_fn(weights, x, y, key):
        if is_encoder:
            prediction = module.apply({"params": weights}, x, train=True, rngs={"dropout": key})
        else:
            prediction = module.apply({"params": weights}, x)
        return jnp.mean((prediction - y) ** 2)

    @jax.jit
    def train_step(state, x, y, key):
        weights, opt_state = state
        loss, grads = jax.value_and_grad(loss_fn)(weights, x, y, key)
        updates, opt_state = tx.update(grads, opt_state, weights)
        return (optax.apply_updates(weights, updates), opt_state), loss

    return train_step


def validation_metrics(name: str, predictions: np.ndarray, targets: np.ndarray) -> dict:
    """Returns the validation figures of a network: image RMSE (0-255 sRGB) or parameter RMSE."""
    targets = np.asarray(targets, np.float64)
    error = predictions.astype(np.float64) - targets
    if name == models.DECODER:
        per_image = 255.0 * np.sqrt(np.mean(error**2, axis=(1, 2, 3)))
        return {"validation_loss": float(np.mean(error**2)), "validation_rmse": float(per_image.mean())}
    per_parameter = np.sqrt(np.mean(error**2, axis=0))
    return {
        "validation_loss": float(np.mean(error**2)),
        "validation_parameter_rmse": float(np.sqrt(np.mean(error**2))),
        "validation_parameter_rmse_by_name": dict(zip(params.NAMES, map(float, per_parameter), strict=True)),
    }


@dataclass
class Checkpoint:
    """The resumable state of a run after `epoch` finished epochs."""

    epoch: int
    weights: dict
    opt_state: object
    history: list = field(default_factory=list)
    seconds: float = 0.0


def checkpoint_path(out: str, name: str) -> str:
    """Returns where run `name` keeps its checkpoint."""
    return os.path.join(out, "checkpoints", name + ".ckpt")


def save_checkpoint(path: str, name: str, description: dict, config: Config, identity: dict, state: Checkpoint) -> None:
    """Writes the whole training state atomically (float32, exact)."""
    document = {
        "format": CHECKPOINT_FORMAT,
        "version": models.WEIGHTS_VERSION,
        "name": name,
        "architecture": description,
        "parameter_table": params.table_fingerprint(),
        "config": asdict(config),
        "dataset": identity,
        "epoch": state.epoch,
        "seconds": state.seconds,
        "history": json.dumps(state.history),
        "weights": serialization.to_state_dict(jax.device_get(state.weights)),
        "opt_state": serialization.to_state_dict(jax.device_get(state.opt_state)),
    }
    files.write_bytes(path, serialization.msgpack_serialize(document))


def load_checkpoint(path: str, name: str, description: dict, config: Config, identity: dict, template: Checkpoint) -> Checkpoint:
    """Returns the checkpoint at `path` if it belongs to this very run; refuses any other."""
    document = models.restore_document(path, CHECKPOINT_FORMAT, "checkpoint")
    fix = f"delete {path} to start afresh, or pass the settings it was made with"
    if document.get("name") != name or document.get("architecture") != description:
        raise TrainingError(f"{path} is a checkpoint of another network or architecture: {fix}")
    if document.get("config") != asdict(config):
        stored = document.get("config") or {}
        different = ", ".join(f"{key} {stored.get(key)} (now {value})" for key, value in asdict(config).items() if stored.get(key) != value)
        raise TrainingError(f"{path} was made with other settings ({different}): {fix}")
    if document.get("dataset") != identity:
        stored = document.get("dataset") or {}
        different = ", ".join(f"{key} {stored.get(key)!r}" for key, value in identity.items() if stored.get(key) != value)
        raise TrainingError(f"{path} was trained on another dataset ({different}): {fix}")
    try:
        weights = serialization.from_state_dict(template.weights, document["weights"])
        opt_state = serialization.from_state_dict(template.opt_state, document["opt_state"])
        history = json.loads(document["history"])
        epoch = int(document["epoch"])
    except (KeyError, ValueError, TypeError) as error:
        raise TrainingError(f"{path} is damaged ({type(error).__name__}: {error}): delete it and train again") from None
    weights = jax.tree_util.tree_map(jnp.asarray, weights)
    opt_state = jax.tree_util.tree_map(jnp.asarray, opt_state)
    return Checkpoint(epoch, weights, opt_state, history, float(document.get("seconds", 0.0)))


class Reporter:
    """Receives progress; the command line shows it, tests ignore it."""

    def start(self, name: str, epoch: int, epochs: int, steps: int) -> None:
        """Called before each epoch."""

    def step(self, step: int, loss: float, samples_per_second: float) -> None:
        """Called after each training step."""

    def end_epoch(self, record: dict) -> None:
        """Called after each epoch with its history record."""


def train_network(
    name: str,
    data: Dataset,
    out: str,
    config: Config,
    reporter: Reporter | None = None,
    decoder: models.Decoder | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> dict:
    """Trains (or resumes, or finds finished) network `name` and returns its final metrics.

    `decoder` overrides the default decoder architecture (tests use tiny ones). `should_stop` is
    polled after each epoch's checkpoint, for tests of interruption.
    """
    if name not in NETWORKS:
        raise TrainingError(f"unknown network {name!r}: use decoder or 1 to 9")
    reporter = reporter or Reporter()
    check_finished(data)
    config.check(data.count)
    description = models.architecture(name, data.resolution, decoder)
    identity = dataset_identity(data)
    weights_file = models.weights_path(out, name)
    ckpt_file = checkpoint_path(out, name)
    os.makedirs(os.path.dirname(ckpt_file), exist_ok=True)
    files.check_writable(weights_file)

    module = models.build(description)
    is_encoder = name != models.DECODER
    inputs, targets = training_arrays(name, data)
    n_validation = validation_count(data.count, config.validation_fraction)
    n_training = data.count - n_validation
    steps = n_training // config.batch_size
    tx = optimiser(config, steps)
    network_index = NETWORKS.index(name)
    root = jax.random.fold_in(jax.random.key(config.seed), network_index)
    variables = models.initialise(module, root, models.input_shape(description))
    state = Checkpoint(0, variables["params"], tx.init(variables["params"]))
    if os.path.exists(ckpt_file):
        state = load_checkpoint(ckpt_file, name, description, config, identity, state)
        if state.epoch == config.epochs and os.path.exists(weights_file):
            return models.load(weights_file).info["metrics"]

    train_step = make_train_step(module, tx, is_encoder)
    training = (state.weights, state.opt_state)
    while state.epoch < config.epochs:
        epoch = state.epoch + 1
        reporter.start(name, epoch, config.epochs, steps)
        started = time.perf_counter()
        order = np.random.default_rng([config.seed, network_index, epoch]).permutation(n_training)
        epoch_key = jax.random.fold_in(root, epoch)
        losses = []
        for step in range(steps):
            batch = order[step * config.batch_size : (step + 1) * config.batch_size]
            x = np.asarray(inputs[batch], np.float32)
            y = np.asarray(targets[batch], np.float32)
            training, loss = train_step(training, x, y, jax.random.fold_in(epoch_key, step))
            losses.append(loss)
            if step % 10 == 9 or step == steps - 1:
                reporter.step(step + 1, float(loss), (step + 1) * config.batch_size / (time.perf_counter() - started))
        predictions = models.apply_in_batches(module, {"params": training[0]}, inputs[n_training:])
        record = {
            "epoch": epoch,
            "train_loss": float(np.mean(jax.device_get(losses))),
            **{
                key: value
                for key, value in validation_metrics(name, predictions, targets[n_training:]).items()
                if not key.endswith("_by_name")
            },
            "seconds": time.perf_counter() - started,
        }
        state = Checkpoint(epoch, training[0], training[1], [*state.history, record], state.seconds + record["seconds"])
        save_checkpoint(ckpt_file, name, description, config, identity, state)
        reporter.end_epoch(record)
        if should_stop is not None and epoch < config.epochs and should_stop():
            raise KeyboardInterrupt

    shipped = jax.tree_util.tree_map(lambda leaf: jnp.asarray(leaf, jnp.float16).astype(jnp.float32), state.weights)
    metrics = {
        "network": name,
        "epochs": config.epochs,
        "training_samples": n_training,
        "validation_samples": n_validation,
        "wall_time_s": round(state.seconds, 1),
        "dataset": identity,
        "config": asdict(config),
        "weights_dtype": "float16",
        "parameter_count": models.parameter_count({"params": shipped}),
        **validation_metrics(name, models.apply_in_batches(module, {"params": shipped}, inputs[n_training:]), targets[n_training:]),
        "history": state.history,
    }
    models.save(weights_file, models.Network(name, description, module, {"params": shipped}, {"metrics": metrics}))
    files.write_text(os.path.join(out, name + ".json"), json.dumps(metrics, indent=2) + "\n")
    return metrics


def parse_arch(text: str) -> list[str]:
    """Returns the networks named by --arch: "decoder", "N" (1..9), "A..B", "all" or a comma list."""
    names: list[str] = []
    for part in text.split(","):
        part = part.strip().lower()
        if part == "decoder":
            names.append(models.DECODER)
        elif part == "all":
            names.extend(NETWORKS)
        elif ".." in part:
            low, _, high = part.partition("..")
            names.extend(f"encoder-{arch}" for arch in range(_arch_number(low), _arch_number(high) + 1))
        else:
            names.append(f"encoder-{_arch_number(part)}")
    return list(dict.fromkeys(names))


def _arch_number(text: str) -> int:
    try:
        arch = int(text)
    except ValueError:
        raise TrainingError(f"--arch {text!r} is not an architecture: use decoder, 1 to 9, 1..9 or all") from None
    if arch not in models.ENCODERS:
        raise TrainingError(f"--arch {arch} does not exist: the paper's encoders are 1 to 9 (or use decoder)")
    return arch
