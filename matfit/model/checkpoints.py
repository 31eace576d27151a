"""A training run's resumable state (`Checkpoint`) and its file, `<out>/checkpoints/<name>.ckpt`.

After every epoch the whole state (weights, optimiser, history) is written atomically, float32
and exact, with what defines the run: the network and its architecture, the settings, the
datasets' identity and the hash of the weights it started from. A checkpoint is only resumed by
the very run that wrote it; any other is refused with the setting that differs and the fix.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field

import jax
import jax.numpy as jnp
from flax import serialization

from matfit import files, params
from matfit.errors import TrainingError
from matfit.model import weight_files
from matfit.model.train_config import Config

CHECKPOINT_FORMAT = "matfit-checkpoint"


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


def save_checkpoint(
    path: str,
    name: str,
    description: dict,
    config: Config,
    identity: dict | list,
    state: Checkpoint,
    start: str | None = None,
) -> None:
    """Writes the whole training state atomically (float32, exact)."""
    document = {
        "format": CHECKPOINT_FORMAT,
        "version": weight_files.WEIGHTS_VERSION,
        "name": name,
        "architecture": description,
        "parameter_table": params.table_fingerprint(),
        "config": asdict(config),
        "dataset": identity,
        "start_sha256": start,
        "epoch": state.epoch,
        "seconds": state.seconds,
        "history": json.dumps(state.history),
        "weights": serialization.to_state_dict(jax.device_get(state.weights)),
        "opt_state": serialization.to_state_dict(jax.device_get(state.opt_state)),
    }
    files.write_bytes(path, serialization.msgpack_serialize(document))


def load_checkpoint(
    path: str,
    name: str,
    description: dict,
    config: Config,
    identity: dict | list,
    template: Checkpoint,
    start: str | None = None,
) -> Checkpoint:
    """Returns the checkpoint at `path` if it belongs to this very run; refuses any other."""
    document = weight_files.restore_document(path, CHECKPOINT_FORMAT, "checkpoint")
    fix = f"delete {path} to start afresh, or pass the settings it was made with"
    if document.get("name") != name or document.get("architecture") != description:
        raise TrainingError(f"{path} is a checkpoint of another network or architecture: {fix}")
    if document.get("config") != asdict(config):
        stored = document.get("config") or {}
        different = ", ".join(
            f"{key} {stored.get(key)} (now {value})"
            for key, value in asdict(config).items()
            if stored.get(key) != value
        )
        raise TrainingError(f"{path} was made with other settings ({different}): {fix}")
    if document.get("dataset") != identity:
        stored = document.get("dataset") or {}
        if isinstance(stored, dict) and isinstance(identity, dict):
            different = ", ".join(
                f"{key} {stored.get(key)!r}" for key, value in identity.items() if stored.get(key) != value
            )
        else:
            different = "another list of datasets, or another content"
        raise TrainingError(f"{path} was trained on other datasets ({different}): {fix}")
    if document.get("start_sha256") != start:
        raise TrainingError(
            f"{path} started from other weights than "
            f"{weight_files.weights_path(str(config.start_from), name)} holds now: {fix}"
        )
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
