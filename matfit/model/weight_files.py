"""Weights files: one trained network (`Network`) saved to and loaded from a Flax msgpack file.

A file holds its format and version, the network's name and architecture record
(`architectures.architecture`), the parameter table it was trained for, what it was trained on
(`info`) and its weights. Loading checks all of them and the weights' shapes and values before
anything is used, and refuses a damaged file in one line that says how to mend it.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass

import flax.linen as nn
import jax
import numpy as np
from flax import serialization

from matfit import files, params, programs
from matfit.errors import WeightsError
from matfit.model.architectures import DECODER, architecture_problem, build, describe_network, initialise, input_shape

WEIGHTS_FORMAT = "matfit-weights"


WEIGHTS_VERSION = 1


WEIGHTS_SUFFIX = ".msgpack"


@dataclass(frozen=True)
class Network:
    """A trained network: its name, architecture, module and weights, and what it was trained on."""

    name: str
    description: dict
    module: nn.Module
    variables: dict
    info: dict
    digest: str | None = None  # SHA-256 of the weights file it was loaded from

    @property
    def resolution(self) -> int:
        """Returns the image side of the training data (the decoder's output size)."""
        return int(self.description["resolution"])

    def identity(self) -> str:
        """Returns the SHA-256 of the weights: of the file it was loaded from, else of the weights themselves."""
        if self.digest is not None:
            return self.digest
        digest = hashlib.sha256()
        for leaf in jax.tree_util.tree_leaves(self.variables):
            digest.update(np.asarray(leaf).tobytes())
        return digest.hexdigest()


def save(path: str, network: Network, dtype: type = np.float16) -> None:
    """Writes a network's weights (as `dtype`) and description to a Flax msgpack file, atomically."""
    weights = jax.tree_util.tree_map(
        lambda leaf: np.asarray(leaf, dtype=dtype), serialization.to_state_dict(network.variables)
    )
    document = {
        "format": WEIGHTS_FORMAT,
        "version": WEIGHTS_VERSION,
        "name": network.name,
        "architecture": network.description,
        "parameter_table": params.table_fingerprint(),
        "info": network.info,
        "variables": weights,
    }
    files.write_bytes(path, serialization.msgpack_serialize(document))


def restore_document(path: str, expected_format: str, what: str) -> dict:
    """Returns a msgpack document of `expected_format`, checking its parameter table; "sha256" holds the file's hash."""
    try:
        data = files.read_input(path)  # a regular file only: a FIFO in the model folder would block the fit
        document = serialization.msgpack_restore(data)
    except FileNotFoundError:
        raise WeightsError(f"{path} does not exist: train it with `matfit train` or check the path") from None
    except files.NotRegularError as error:
        raise WeightsError(f"cannot read {path}: {error.strerror}: delete it and train again") from None
    except Exception as error:  # msgpack raises many types on damaged bytes
        raise WeightsError(
            f"{path} is not a readable {what} ({type(error).__name__}): delete it and train again"
        ) from None
    if not isinstance(document, dict) or document.get("format") != expected_format:
        raise WeightsError(f"{path} is not a matfit {what}: delete it and train again")
    if document.get("version") != WEIGHTS_VERSION:
        raise WeightsError(
            f"{path} is {what} version {document.get('version')}, this matfit reads {WEIGHTS_VERSION}: train again"
        )
    difference = params.describe_table_difference(document.get("parameter_table", {}))
    if difference is not None:
        raise WeightsError(
            f"{path} was trained for another parameter table ({difference}): train again on a new dataset"
        )
    return {**document, "sha256": hashlib.sha256(data).hexdigest()}


def restore_variables(
    path: str, description: dict, stored: dict | None, dtype: type | None = np.float32
) -> tuple[nn.Module, dict]:
    """Returns the module of `description` and `stored` weights checked against its shapes, as `dtype` (None: as
    stored)."""
    try:
        module = build(description)
    except (KeyError, TypeError, ValueError) as error:
        raise WeightsError(
            f"{path} describes an architecture this matfit cannot build ({error}): train again"
        ) from None
    # The shapes its architecture builds, traced once per architecture and matfit (`programs.remembered`): tracing
    # the ten networks' initialisation would cost every cold start (docs/fitting.md#measured).
    shapes = programs.remembered(
        "shapes",
        description,
        lambda: jax.tree_util.tree_map(
            lambda leaf: list(leaf.shape),
            jax.eval_shape(lambda: initialise(module, jax.random.key(0), input_shape(description))),
        ),
    )
    try:
        stored_shapes = jax.tree_util.tree_map(lambda leaf: list(np.shape(leaf)), stored)
    except (TypeError, ValueError) as error:
        raise WeightsError(f"{path} does not hold the weights of its architecture ({error}): train again") from None
    if stored_shapes != shapes:
        raise WeightsError(f"{path} holds weights of other shapes than its architecture: train again")
    # One transfer of the whole tree: one device_put of float32 NumPy arrays is several times faster than converting
    # leaf by leaf with jnp.asarray.
    return module, jax.device_put(jax.tree_util.tree_map(lambda leaf: np.asarray(leaf, dtype), stored))


def non_finite_leaf(variables: dict) -> str | None:
    """Returns the name of the first weight array holding NaN or infinity ("params/Dense_0/kernel"), or None."""
    for keys, leaf in jax.tree_util.tree_flatten_with_path(variables)[0]:
        if not np.isfinite(np.asarray(leaf)).all():
            return "/".join(str(getattr(key, "key", key)) for key in keys)
    return None


def load(path: str, resolution: int | None = None, name: str | None = None, *, check_finite: bool = True) -> Network:
    """Returns the network saved at `path`, checking the parameter table and, if given, the resolution and the name.

    Its architecture record is checked field by field, and with `check_finite` its weights too (NaN or infinity
    is refused: a broken network would otherwise put NaN into every result). `load_model` checks its encoders'
    weights on the device instead, where they are converted anyway.
    """
    document = restore_document(path, WEIGHTS_FORMAT, "weights file")
    description = document.get("architecture")
    if not isinstance(description, dict):
        raise WeightsError(f"{path} has no architecture description: train again")
    problem = architecture_problem(description)
    if problem is not None:
        raise WeightsError(f"{path}: architecture {problem}: train it again (or copy an intact file there)")
    stored_name = describe_network(description)
    if name is not None and stored_name != name:
        raise WeightsError(
            f"{path} holds the weights of the {stored_name}, not of the {name}: "
            "copy the right file there or train it again"
        )
    if resolution is not None and int(description["resolution"]) != resolution:
        raise WeightsError(
            f"{path} was trained on {description['resolution']} px images, not {resolution} px: "
            "use a model of that resolution"
        )
    # The decoder's weights become float32 here; an encoder's stay as stored (float16 in the shipped model) for
    # `load_model` to convert all of them in one program on the device, the same numbers.
    dtype = np.float32 if stored_name == DECODER else None
    module, variables = restore_variables(path, description, document.get("variables"), dtype)
    broken = non_finite_leaf(document["variables"]) if check_finite else None
    if broken is not None:
        raise WeightsError(
            f"{path}: weights {broken} hold NaN or infinity: train it again (or copy an intact file there)"
        )
    return Network(
        str(document.get("name")), description, module, variables, document.get("info") or {}, document["sha256"]
    )


def weights_path(directory: str, name: str) -> str:
    """Returns where network `name` lives in a model directory."""
    return os.path.join(directory, name + WEIGHTS_SUFFIX)
