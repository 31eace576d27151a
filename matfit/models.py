"""The neural renderer (decoder) and the nine inversion networks (encoders), in Flax Linen.

Linen keeps the weights out of the modules: `model.apply(variables, x)` is a pure function, so
the weights travel as an argument and one compiled function serves every set of weights and
targets. Only the modules live here; training is `train.py`'s job.

Decoder phi: 19 unit-cube parameters -> (H, W, 3) sRGB-encoded image in [0, 1]. Fully connected
layers to a 4 x 4 feature map, then stages of nearest-neighbour upsampling + 3x3 convolutions
(measured faster than transposed convolutions on this CPU). No layer grows with the image: a
larger output only adds upsampling stages.

Encoders phi^-1_(1..9): image -> 19 unit-cube parameters, exactly the paper's Appendix A:
Conv2D(filters, 3, 1) + MaxPool(2, 2) blocks, FC(neurons, dropout) layers, an FC(19) output
squashed into the unit cube by a sigmoid. The table `ENCODERS` reads line by line against the
paper. Their input is the target resized to `ENCODER_RESOLUTION` (32 px) to keep the weights
small: the first FC layer's size is (32 / 2^blocks)^2 x filters x neurons.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import flax.linen as nn
import jax
import jax.numpy as jnp

from matfit import params

ENCODER_RESOLUTION = 32


class Decoder(nn.Module):
    """Maps unit-cube parameters (..., 19) to sRGB images (..., resolution, resolution, 3)."""

    resolution: int = 64
    hidden: int = 512
    base_channels: int = 256
    stage_channels: Sequence[int] = (192, 128, 96, 64)

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        stages = self.resolution.bit_length() - 1 - 2  # from 4 x 4 up to resolution
        if 4 * 2**stages != self.resolution:
            raise ValueError(f"decoder resolution must be 4 times a power of two, got {self.resolution}")
        batch_shape = x.shape[:-1]
        x = x.reshape(-1, x.shape[-1])
        x = nn.gelu(nn.Dense(self.hidden)(x))
        x = nn.gelu(nn.Dense(self.hidden)(x))
        x = nn.Dense(4 * 4 * self.base_channels)(x).reshape(-1, 4, 4, self.base_channels)
        channels = list(self.stage_channels) + [self.stage_channels[-1]] * max(0, stages - len(self.stage_channels))
        for stage in range(stages):
            n, h, w, c = x.shape
            x = jax.image.resize(x, (n, 2 * h, 2 * w, c), method="nearest")
            x = nn.gelu(nn.Conv(channels[stage], (3, 3))(x))
            x = nn.gelu(nn.Conv(channels[stage], (3, 3))(x))
        x = nn.sigmoid(nn.Conv(3, (3, 3))(x))
        return x.reshape(*batch_shape, self.resolution, self.resolution, 3)


@dataclass(frozen=True)
class Block:
    """`repeat` x {Conv2D(filters, 3, 1), MaxPool(2, 2)}."""

    repeat: int
    filters: int


@dataclass(frozen=True)
class Dense:
    """`repeat` x {FC(neurons), dropout}."""

    repeat: int
    neurons: int
    dropout: float


class Encoder(nn.Module):
    """Maps images (..., ENCODER_RESOLUTION, ENCODER_RESOLUTION, 3) to unit-cube parameters (..., 19)."""

    blocks: Sequence[Block]
    dense: Dense

    @nn.compact
    def __call__(self, image: jax.Array, train: bool = False) -> jax.Array:
        batch_shape = image.shape[:-3]
        x = image.reshape(-1, *image.shape[-3:])
        for block in self.blocks:
            for _ in range(block.repeat):
                x = nn.relu(nn.Conv(block.filters, (3, 3), strides=(1, 1))(x))
                x = nn.max_pool(x, (2, 2), strides=(2, 2))
        x = x.reshape(x.shape[0], -1)
        for _ in range(self.dense.repeat):
            x = nn.relu(nn.Dense(self.dense.neurons)(x))
            x = nn.Dropout(self.dense.dropout, deterministic=not train)(x)
        x = nn.sigmoid(nn.Dense(params.COUNT)(x))
        return x.reshape(*batch_shape, params.COUNT)


# The paper's Appendix A, one line per network.
ENCODERS: dict[int, partial] = {
    1: partial(Encoder, blocks=(Block(2, 32), Block(1, 64), Block(2, 128)), dense=Dense(2, 1000, 0.1)),
    2: partial(Encoder, blocks=(Block(2, 32),), dense=Dense(2, 1000, 0.1)),
    3: partial(Encoder, blocks=(Block(2, 32),), dense=Dense(2, 1000, 0.5)),
    4: partial(Encoder, blocks=(Block(2, 32), Block(1, 64), Block(2, 128)), dense=Dense(2, 3000, 0.5)),
    5: partial(Encoder, blocks=(Block(2, 32), Block(1, 64), Block(2, 128)), dense=Dense(2, 3000, 0.0)),
    6: partial(Encoder, blocks=(Block(2, 32),), dense=Dense(2, 1000, 0.0)),
    7: partial(Encoder, blocks=(Block(2, 32),), dense=Dense(2, 1000, 0.0)),  # as 6, trained for other epochs
    8: partial(Encoder, blocks=(Block(2, 32),), dense=Dense(2, 100, 0.0)),
    9: partial(Encoder, blocks=(Block(2, 32),), dense=Dense(2, 1000, 0.0)),  # as 6, trained for other epochs
}


def encoder(arch: int) -> Encoder:
    """Returns encoder number `arch` (1..9) of the paper's Appendix A."""
    if arch not in ENCODERS:
        raise ValueError(f"encoder architecture {arch} does not exist: use 1 to 9")
    return ENCODERS[arch]()


def parameter_count(variables: dict) -> int:
    """Returns the number of trainable weights in a Flax variables tree."""
    return sum(int(leaf.size) for leaf in jax.tree_util.tree_leaves(variables["params"]))


def initialise(model: nn.Module, key: jax.Array, input_shape: tuple[int, ...]) -> dict:
    """Returns freshly initialised variables of `model` for one input of `input_shape`."""
    return model.init(key, jnp.zeros((1, *input_shape), jnp.float32))
