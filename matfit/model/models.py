"""A trained model in use: the decoder and the encoders of one model directory (`Model`, `load_model`), and the
networks applied to inputs (`apply`, `apply_in_batches`, `encoder_input`).

The layers are `layers.py`, the networks and their architecture records `architectures.py`, one network's
weights file `weight_files.py`. Every caller that decodes or encodes (training's validation, evaluation,
fitting, the bench) goes through `apply` here, so one compiled program serves them all.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from matfit import images, params, programs
from matfit.errors import WeightsError
from matfit.model.architectures import DECODER, ENCODER_NAMES, ENCODER_RESOLUTION, ENCODERS
from matfit.model.weight_files import Network, load, non_finite_leaf, weights_path

if TYPE_CHECKING:
    from jaxtyping import Float, PyTree


def as_float32(variables: PyTree) -> PyTree:
    """Returns the weights as float32 (float32 weights are left as they are): an encoder loaded alone (`load`) keeps
    its stored float16 weights, which a compiled program then converts where XLA runs."""
    return jax.tree_util.tree_map(lambda leaf: jnp.asarray(leaf).astype(jnp.float32), variables)


@programs.jit(static_argnames=("module",))
def apply(module: nn.Module, variables: dict, x: jax.Array) -> jax.Array:
    """Returns `module` applied to a batch in inference mode; compiled once per module and shape."""
    return module.apply(as_float32(variables), x)  # type: ignore[return-value]  # a tuple only with `mutable`


def apply_in_batches(
    module: nn.Module, variables: dict, inputs: Float[np.ndarray, "n ..."], batch: int = 256
) -> Float[np.ndarray, "n ..."]:
    """Returns `module` applied to every input, float32, in batches of one size (one compilation per size)."""
    batch = max(1, min(batch, len(inputs)))
    outputs = []
    for start in range(0, len(inputs), batch):
        chunk = np.asarray(inputs[start : start + batch], np.float32)
        if len(chunk) < batch:
            chunk = np.concatenate([chunk, np.zeros((batch - len(chunk), *chunk.shape[1:]), np.float32)])
        outputs.append(np.asarray(apply(module, variables, chunk))[: min(batch, len(inputs) - start)])
    return np.concatenate(outputs)


def encoder_input(linear: Float[np.ndarray, "*batch R R 3"]) -> Float[np.ndarray, "*batch 32 32 3"]:
    """Returns what every encoder sees of linear images (..., R, R, 3): clipped to [0, 1], box-filtered
    to ENCODER_RESOLUTION, then sRGB-encoded, float32. R must be a multiple of ENCODER_RESOLUTION.

    Clipping comes first because a target to fit is a picture, already clipped: a training render's
    HDR highlight averaged before clipping would show the encoder up to 0.12 brighter pixels than
    the same render saved as a picture. Training, evaluation and fitting all call this function.
    """
    clipped = np.clip(np.asarray(linear, np.float32), 0.0, 1.0)
    return images.srgb_encode(images.box_downsample(clipped, ENCODER_RESOLUTION))


@dataclass(frozen=True)
class Model:
    """The decoder and the encoders of one model directory."""

    path: str
    decoder: Network
    encoders: dict[int, Network]

    @property
    def resolution(self) -> int:
        """Returns the decoder's image side."""
        return self.decoder.resolution

    def identity(self) -> str:
        """Returns the SHA-256 of all the model's weights: the same model wherever its directory lies."""
        digest = hashlib.sha256(self.decoder.identity().encode())
        for arch, network in sorted(self.encoders.items()):
            digest.update(f"{arch}:{network.identity()}".encode())
        return digest.hexdigest()

    def decode(self, unit: Float[np.ndarray, "n 19"]) -> Float[np.ndarray, "n R R 3"]:
        """Returns phi(x) of unit-cube parameters (N, 19): sRGB images (N, R, R, 3), float32, decoded in batches."""
        return apply_in_batches(
            self.decoder.module, self.decoder.variables, np.asarray(unit, np.float32).reshape(-1, params.COUNT)
        )


class Loader(Protocol):
    """What loads a model when it is first asked for (`matfit.Fitter`): its folder, and the model."""

    model_path: str

    @property
    def model(self) -> Model: ...


def load_model(directory: str) -> Model:
    """Returns the decoder and every encoder found in a model directory (at least one encoder)."""
    if not os.path.isdir(directory):
        found = "is not a folder" if os.path.lexists(directory) else "does not exist"
        raise WeightsError(
            f"model directory {directory} {found}: train one with `matfit train`, "
            "or leave out --model to use the shipped one"
        )
    decoder = load(weights_path(directory, DECODER), name=DECODER)
    encoders = {}
    for arch, name in zip(ENCODERS, ENCODER_NAMES, strict=True):
        path = weights_path(directory, name)
        if os.path.exists(path):
            encoders[arch] = load(path, resolution=decoder.resolution, name=name, check_finite=False)
    if not encoders:
        raise WeightsError(
            f"{directory} has a decoder but no encoders: train them with `matfit train --arch 1..9 --out {directory}`"
        )
    # The encoders' weights (float16 as stored, 90% of the model's) become float32 on the device, all in one compiled
    # program, faster than NumPy's conversion, which also checks them finite; left float16, every fit's best-of-n
    # would convert them again.
    converted, finite = encoders_float32(tuple(network.variables for network in encoders.values()))
    for network, intact in zip(encoders.values(), np.asarray(finite), strict=True):
        if not intact:
            raise WeightsError(
                f"{weights_path(directory, network.name)}: weights {non_finite_leaf(network.variables)} hold NaN or "
                "infinity: train it again (or copy an intact file there)"
            )
    encoders = {
        arch: dataclasses.replace(network, variables=variables)
        for (arch, network), variables in zip(encoders.items(), converted, strict=True)
    }
    return Model(directory, decoder, encoders)


@programs.jit
def encoders_float32(variables: tuple) -> tuple:
    """Returns (every encoder's weights as float32, a tuple of variable trees; for each encoder whether all its weights
    are finite), converted and checked in one compiled program."""
    finite = [
        jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree_util.tree_leaves(tree)]))
        for tree in variables
    ]
    return as_float32(variables), jnp.stack(finite)
