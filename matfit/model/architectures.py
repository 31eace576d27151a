"""The neural renderer (decoder) and the nine inversion networks (encoders), in Flax Linen, and the plain-data
architecture records that rebuild them.

Linen keeps the weights out of the modules: `model.apply(variables, x)` is a pure function, so
the weights travel as an argument and one compiled function serves every set of weights and
targets. Only the modules live here; training is `train.py`'s job, weights files `weight_files.py`'s.

Decoder phi: 19 unit-cube parameters -> (H, W, 3) sRGB-encoded image in [0, 1]. Fully connected
layers to a 4 x 4 feature map, then stages of nearest-neighbour upsampling + 3x3 convolutions
(`layers.py`). No layer grows with the image: a larger output only adds upsampling stages.

Encoders phi^-1_(1..9): image -> 19 unit-cube parameters, exactly the paper's Appendix A:
Conv2D(filters, 3, 1) + MaxPool(2, 2) blocks, FC(neurons, dropout) layers, an FC(19) output
squashed into the unit cube by a sigmoid. The table `ENCODERS` reads line by line against the
paper. Their input is the target resized to `ENCODER_RESOLUTION` (32 px) to keep the weights
small: the first FC layer's size is (32 / 2^blocks)^2 x filters x neurons.

An architecture record (`architecture`) is what a weights file stores to rebuild its network
(`build`); `architecture_problem` checks one field by field before anything is built.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING, Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from matfit import params
from matfit.errors import WeightsError
from matfit.model.layers import (
    absorbed,
    coordinate_channels,
    depth_to_space,
    interpolate_glass,
    max_pool,
    medium_features,
    medium_physical,
    medium_weights,
    srgb_decode,
    srgb_encode,
    upsample,
    upsampled_conv,
)

if TYPE_CHECKING:
    from jaxtyping import Float
from matfit.rendering import scene

ENCODER_RESOLUTION = 32


DECODER = "decoder"


class Decoder(nn.Module):
    """Maps unit-cube parameters (..., 19) to sRGB images (..., resolution, resolution, 3).

    Two dense layers to a 4 x 4 x `base_channels` map; then one stage per doubling up to half
    the resolution: nearest upsampling and `convs_per_stage` 3x3 convolutions with
    `stage_channels[k]` filters (the last entry repeats for larger images; with `coordinates`,
    each convolution also sees every pixel's x and y; without, the upsampling is computed inside
    the stage's first convolution, `upsampled_conv`, at less than half the cost); then a 3x3
    convolution shuffled into full-resolution channels (sub-pixel convolution: no convolution
    runs at full resolution, where it would cost the most), plus a learned per-pixel `background` logit image before the
    sigmoid: the scene around the object hardly changes with the material, so the convolutions
    only learn what does.

    With `glass_grid` (S, G), the decoder draws refraction: the scene is fixed, so what a clear
    glass sphere shows (the checkers bent and turned upside down, blurred by roughness, the caustic
    in its shadow) depends only on its index of refraction and roughness. A basis of Mitsuba
    renders of clear glass on an S x G grid of specular and roughness (`scene.glass_basis_materials`;
    a constant, set with `with_bases`) is interpolated at the material's values and multiplied per
    pixel by a predicted full-resolution transmittance (spec_trans, absorption tint, light lost to
    scattering), then added in linear light to the direct layer (reflection, diffuse, scattering):
    image = sRGB(direct + transmittance x glass(specular, roughness)).

    With `medium_grid` (T, A) (an option, not the shipped decoder's: docs/decisions.md, "A scattering
    basis"), it also draws the light a medium scatters: a basis of Mitsuba renders
    of grey media on a grid of optical thickness x albedo, less their absorbing-only renders
    (`scene.medium_basis_materials`; a constant, set with `with_bases`), read per colour channel at
    that channel's thickness (`medium_weights`), weighted by the transmitted share (1 - metallic) x
    spec_trans and by a second predicted full-resolution map (starting at 1) and added in linear light.

    With `medium_inputs`, the dense layers also see `medium_features` of the parameters.

    With `coarse_absorption`, each colour's transmittance logit is also lowered by E tau, tau that
    colour's extinction per radius (known from the parameters) and E a path length in radii, of
    either sign, predicted once per 2 x 2 pixels (`path_length`: one more 3x3 convolution of the
    half-resolution features). Where little light is left, 1.5 sigmoid(z - E tau) ~ 1.5 sigmoid(z)
    exp(-E tau): Beer-Lambert couples the three colours through the medium's own extinction (a
    saturated amber keeps red and loses blue along the same path), and the transmittance stays
    bounded whatever E. E starts at `path_start` (0: a zero kernel and bias), so the layer can be grown
    on a trained decoder (`train.GROWABLE`) without changing what it draws (grown so it stays near 0:
    docs/decisions.md#the-decoder-and-its-training-data).
    """

    resolution: int = 64
    hidden: int = 256
    base_channels: int = 128
    stage_channels: Sequence[int] = (64, 48, 32)
    convs_per_stage: int = 1
    coordinates: bool = False
    glass_grid: Sequence[int] = ()
    medium_inputs: bool = False
    medium_grid: Sequence[int] = ()
    absorption: bool = False
    coarse_absorption: bool = False
    path_start: float = 0.0  # the coarse absorption layer's path length at initialisation, in radii

    @nn.compact
    def __call__(self, x: Float[jax.Array, "*batch 19"]) -> Float[jax.Array, "*batch R R 3"]:
        stages = self.resolution.bit_length() - 1 - 3  # from 4 x 4 up to resolution / 2
        if self.resolution < 8 or 8 * 2**stages != self.resolution:
            raise ValueError(
                f"decoder resolution must be 4 times a power of two (8, 16, ..., 256), got {self.resolution}"
            )
        batch_shape = x.shape[:-1]
        inputs = x = x.reshape(-1, x.shape[-1])
        if self.medium_inputs:
            x = jnp.concatenate([x, medium_features(x)], axis=-1)
        x = nn.gelu(nn.Dense(self.hidden)(x))
        x = nn.gelu(nn.Dense(self.hidden)(x))
        x = nn.gelu(nn.Dense(4 * 4 * self.base_channels)(x)).reshape(-1, 4, 4, self.base_channels)
        channels = list(self.stage_channels) + [self.stage_channels[-1]] * max(0, stages - len(self.stage_channels))
        for stage in range(stages):
            # Without coordinates, the upsampling is folded into the stage's first convolution (the same
            # weights and function, less than half the work: `upsampled_conv`).
            if self.coordinates or not self.convs_per_stage:
                x = upsample(x)
            for conv in range(self.convs_per_stage):
                folded = upsampled_conv if conv == 0 and not self.coordinates else None
                features = coordinate_channels(x) if self.coordinates else x
                x = nn.gelu(nn.Conv(channels[stage], (3, 3), conv_general_dilated=folded)(features))
        features = coordinate_channels(x) if self.coordinates else x
        background = self.param("background", nn.initializers.zeros, (self.resolution, self.resolution, 3))
        direct = nn.sigmoid(depth_to_space(nn.Conv(4 * 3, (3, 3))(features)) + background[None])
        if self.glass_grid:
            shape = (*self.glass_grid, self.resolution, self.resolution, 3)
            basis = self.variable("constants", "glass", jnp.zeros, shape).value
            glass = interpolate_glass(basis, inputs[:, params.INDEX["specular"]], inputs[:, params.INDEX["roughness"]])
            # Starts near 0 (sigmoid(-3) = 0.05): the direct layer first learns the opaque scene.
            # With `absorption`, a fourth channel per pixel is the path length (softplus(start) = 1).
            per_pixel = 4 if self.absorption else 3
            start = np.full((4, per_pixel), -3.0, np.float32)
            start[:, 3:] = np.log(np.expm1(1.0))
            logit = nn.Conv(
                4 * per_pixel,
                (3, 3),
                kernel_init=nn.initializers.zeros,
                bias_init=nn.initializers.constant(start.reshape(-1)),
            )
            out = depth_to_space(logit(features))
            colour_logits = out[..., :3]
            if self.coarse_absorption:
                colour_logits = (
                    colour_logits - self.path_length(features) * medium_physical(inputs)[0][:, None, None, :]
                )
            transmittance = 1.5 * nn.sigmoid(colour_logits)
            if self.absorption:
                transmittance = transmittance * absorbed(inputs, nn.softplus(out[..., 3:]))
            linear = srgb_decode(direct) + transmittance * glass
            if self.medium_grid:
                linear = linear + self.scattered(inputs, features)
            direct = srgb_encode(linear)
        return direct.reshape(*batch_shape, self.resolution, self.resolution, 3)

    def path_length(self, features: jax.Array) -> jax.Array:
        """Returns the path length E (N, R, R, 1) in radii, of either sign, one per 2 x 2 pixels: a 3x3
        convolution of the half-resolution features (N, R/2, R/2, C), upsampled; `path_start` at initialisation."""
        start = nn.initializers.constant(self.path_start)
        return upsample(nn.Conv(1, (3, 3), kernel_init=nn.initializers.zeros, bias_init=start, name="path")(features))

    def scattered(self, inputs: jax.Array, features: jax.Array) -> jax.Array:
        """Returns the medium's scattered light (N, R, R, 3), linear: the scattering basis read at its values."""
        thickness_count, albedo_count = self.medium_grid
        shape = (thickness_count, albedo_count, self.resolution, self.resolution, 3)
        basis = self.variable("constants", "medium", jnp.zeros, shape).value
        table = basis.reshape(thickness_count * albedo_count, self.resolution * self.resolution, 3)
        weights = medium_weights(inputs, self.medium_grid)
        # One (N, T A) x (T A, R R) product per colour: faster at batch 1 than one einsum over all three.
        light = jnp.stack([weights[:, k, :] @ table[:, :, k] for k in range(3)], axis=-1)
        share = (1.0 - inputs[:, params.INDEX["metallic"]]) * inputs[:, params.INDEX["spec_trans"]]
        # Starts at 1 (1.5 sigmoid(ln 2)): the basis is right for clear glass of the default specular.
        start = nn.initializers.constant(np.log(2.0))
        logit = nn.Conv(4 * 3, (3, 3), kernel_init=nn.initializers.zeros, bias_init=start)
        weight = 1.5 * nn.sigmoid(depth_to_space(logit(features)))
        return weight * share[:, None, None, None] * light.reshape(-1, self.resolution, self.resolution, 3)


def with_bases(decoder: Decoder, variables: dict, glass: np.ndarray, medium: np.ndarray | None = None) -> dict:
    """Returns decoder variables holding its constants: the clear-glass basis (linear (S, G, R, R, 3)) and, if
    the decoder has a `medium_grid`, the scattering basis (linear (T, A, R, R, 3)); unchanged without a glass grid."""
    if not decoder.glass_grid:
        return variables
    constants = {"glass": _basis(glass, (*decoder.glass_grid, decoder.resolution, decoder.resolution, 3), "glass")}
    if decoder.medium_grid:
        if medium is None:
            raise ValueError("this decoder draws scattering media: give it the scattering basis too")
        expected = (*decoder.medium_grid, decoder.resolution, decoder.resolution, 3)
        constants["medium"] = _basis(medium, expected, "scattering")
    return {**variables, "constants": constants}


def _basis(basis: np.ndarray, expected: tuple[int, ...], what: str) -> jax.Array:
    if tuple(basis.shape) != expected:
        raise ValueError(f"Shape mismatch: the {what} basis is {tuple(basis.shape)}, the decoder needs {expected}.")
    return jnp.asarray(basis, jnp.float32)


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
    def __call__(self, image: Float[jax.Array, "*batch 32 32 3"], train: bool = False) -> Float[jax.Array, "*batch 19"]:
        batch_shape = image.shape[:-3]
        x = image.reshape(-1, *image.shape[-3:])
        for block in self.blocks:
            for _ in range(block.repeat):
                x = nn.relu(nn.Conv(block.filters, (3, 3), strides=(1, 1))(x))
                x = max_pool(x)
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


ENCODER_NAMES = tuple(f"encoder-{arch}" for arch in ENCODERS)


NETWORKS = (DECODER, *ENCODER_NAMES)  # the ten networks of a model directory, in training order


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
    return _initialise(model, key, jnp.zeros((1, *input_shape), jnp.float32))


@partial(jax.jit, static_argnames=("model",))
def _initialise(model: nn.Module, key: jax.Array, x: jax.Array) -> Any:  # flax types init as a FrozenDict or dict
    # Compiled, which is faster than op by op, and once per architecture and input shape in a process: modules are
    # frozen dataclasses that compare by their settings, so every model of one architecture shares the program.
    return model.init(key, x)


# The coarse absorption layer's path length at initialisation when trained from scratch, in radii:
# Beer-Lambert from the first step (grown on a trained decoder the layer starts at 0: docs/decisions.md).
COARSE_PATH_START = 1.0


def trained_decoder(resolution: int, coarse_absorption: bool = False) -> Decoder:
    """Returns the decoder `matfit train` trains on images of `resolution` pixels (`--coarse-absorption`: with the
    coarse absorption layer, its path length starting at COARSE_PATH_START)."""
    path_start = COARSE_PATH_START if coarse_absorption else 0.0
    return Decoder(
        resolution=resolution,
        glass_grid=scene.GLASS_GRID,
        medium_inputs=True,
        coarse_absorption=coarse_absorption,
        path_start=path_start,
    )


def architecture(name: str, resolution: int, decoder: Decoder | None = None) -> dict:
    """Returns the plain-data description that rebuilds network `name` ("decoder" or "encoder-N").

    `resolution` is the image side the network was trained on (the decoder's output); encoders
    always read ENCODER_RESOLUTION pixels.
    """
    if name == DECODER:
        decoder = decoder or trained_decoder(resolution)
        fields = {
            field.name: getattr(decoder, field.name)
            for field in dataclasses.fields(Decoder)
            if field.name not in ("parent", "name")
        }
        fields["stage_channels"] = list(fields["stage_channels"])
        fields["glass_grid"] = list(fields["glass_grid"])
        fields["medium_grid"] = list(fields["medium_grid"])
        return {"kind": DECODER, **fields}
    if name not in ENCODER_NAMES:
        raise WeightsError(f"unknown network {name!r}: use decoder or encoder-1 to encoder-9")
    return {"kind": "encoder", "arch": int(name.split("-")[1]), "resolution": resolution}


def build(description: dict) -> nn.Module:
    """Returns the module described by `architecture(...)`."""
    fields = dict(description)
    kind = fields.pop("kind")
    if kind == DECODER:
        fields["stage_channels"] = tuple(fields["stage_channels"])
        fields["glass_grid"] = tuple(fields.get("glass_grid", ()))
        fields["medium_grid"] = tuple(fields.get("medium_grid", ()))
        return Decoder(**fields)
    return encoder(fields["arch"])


def input_shape(description: dict) -> tuple[int, ...]:
    """Returns the shape of one input of the network described by `description`."""
    if description["kind"] == DECODER:
        return (params.COUNT,)
    return (ENCODER_RESOLUTION, ENCODER_RESOLUTION, 3)


# What an architecture record may hold, field by field: (type, low, high) for numbers, the length for grids. Checked
# before anything is built, so a damaged record is refused in one line instead of failing inside Flax or allocating
# a decoder for a million-pixel image. Resolutions: those of datasets (`dataset.MAX_RESOLUTION`) that a decoder draws.
RESOLUTIONS = tuple(8 * 2**stage for stage in range(8))  # 8 to 1024


WHOLE_FIELDS = {"hidden": (1, 8192), "base_channels": (1, 4096), "convs_per_stage": (0, 16)}


FLAG_FIELDS = ("coordinates", "medium_inputs", "absorption", "coarse_absorption")


GRID_FIELDS = ("glass_grid", "medium_grid")


MAX_GRID = 64


MAX_CHANNELS = 4096


MAX_STAGES = len(RESOLUTIONS)


MAX_PATH_START = 100.0


def _is_whole(value: object, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def architecture_problem(description: dict) -> str | None:
    """Returns what is wrong with an architecture record (`architecture(...)`), as "field 'x' is ...", or None."""

    def field(name: str, expected: str) -> str:
        return f"field {name!r} is {json.dumps(description.get(name), default=repr)[:40]}, not {expected}"

    kind = description.get("kind")
    if kind not in (DECODER, "encoder"):
        return field("kind", "decoder or encoder")
    if "resolution" not in description:
        return "field 'resolution' is missing"
    if not _is_whole(description["resolution"], RESOLUTIONS[0], RESOLUTIONS[-1]) or (
        description["resolution"] not in RESOLUTIONS
    ):
        return field("resolution", f"one of {', '.join(map(str, RESOLUTIONS))}")
    if kind == "encoder":
        if not _is_whole(description.get("arch"), 1, len(ENCODERS)):
            return field("arch", f"a whole number from 1 to {len(ENCODERS)}")
        unknown = sorted(set(description) - {"kind", "arch", "resolution"})
        return f"field {unknown[0]!r} is not part of an encoder" if unknown else None
    known = {entry.name for entry in dataclasses.fields(Decoder)} - {"parent", "name"}
    unknown = sorted(set(description) - known - {"kind"})
    if unknown:
        return f"field {unknown[0]!r} is not part of a decoder"
    for name, (low, high) in WHOLE_FIELDS.items():
        if name in description and not _is_whole(description[name], low, high):
            return field(name, f"a whole number from {low} to {high}")
    channels = description.get("stage_channels", list(Decoder.stage_channels))
    if (
        not isinstance(channels, list)
        or not 1 <= len(channels) <= MAX_STAGES
        or not all(_is_whole(value, 1, MAX_CHANNELS) for value in channels)
    ):
        return field("stage_channels", f"1 to {MAX_STAGES} whole numbers from 1 to {MAX_CHANNELS}")
    for name in FLAG_FIELDS:
        if name in description and not isinstance(description[name], bool):
            return field(name, "true or false")
    for name in GRID_FIELDS:
        grid = description.get(name, [])
        if grid != [] and not (
            isinstance(grid, list) and len(grid) == 2 and all(_is_whole(value, 2, MAX_GRID) for value in grid)
        ):
            return field(name, f"[] or two whole numbers from 2 to {MAX_GRID}")
    start = description.get("path_start", 0.0)
    if isinstance(start, bool) or not isinstance(start, int | float) or not abs(start) <= MAX_PATH_START:
        return field("path_start", f"a number from {-MAX_PATH_START:g} to {MAX_PATH_START:g}")
    return None


def describe_network(description: dict) -> str:
    """Returns which network an architecture description is of: "decoder" or "encoder-N"."""
    if description.get("kind") == DECODER:
        return DECODER
    return f"encoder-{description.get('arch')}"
