"""The neural renderer (decoder) and the nine inversion networks (encoders), in Flax Linen.

Linen keeps the weights out of the modules: `model.apply(variables, x)` is a pure function, so
the weights travel as an argument and one compiled function serves every set of weights and
targets. Only the modules live here; training is `train.py`'s job.

Decoder phi: 19 unit-cube parameters -> (H, W, 3) sRGB-encoded image in [0, 1]. Fully connected
layers to a 4 x 4 feature map, then stages of nearest-neighbour upsampling + 3x3 convolutions
(measured faster than transposed convolutions on this CPU; the upsampling folded into the
convolution, `upsampled_conv`). No layer grows with the image: a larger output only adds
upsampling stages.

Encoders phi^-1_(1..9): image -> 19 unit-cube parameters, exactly the paper's Appendix A:
Conv2D(filters, 3, 1) + MaxPool(2, 2) blocks, FC(neurons, dropout) layers, an FC(19) output
squashed into the unit cube by a sigmoid. The table `ENCODERS` reads line by line against the
paper. Their input is the target resized to `ENCODER_RESOLUTION` (32 px) to keep the weights
small: the first FC layer's size is (32 / 2^blocks)^2 x filters x neurons.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from matfit import files, images, params, programs
from matfit.errors import OutputError, WeightsError
from matfit.render import scene

ENCODER_RESOLUTION = 32
WEIGHTS_FORMAT = "matfit-weights"
WEIGHTS_VERSION = 1
WEIGHTS_SUFFIX = ".msgpack"
DECODER = "decoder"


def upsample(x: jax.Array) -> jax.Array:
    """Returns (N, H, W, C) feature maps repeated to (N, 2H, 2W, C): nearest-neighbour upsampling.

    Written as a broadcast, whose gradient is a sum; `jax.image.resize` differentiates through a
    gather and made a training step several times slower on this CPU.
    """
    n, h, w, c = x.shape
    return jnp.broadcast_to(x[:, :, None, :, None, :], (n, h, 2, w, 2, c)).reshape(n, 2 * h, 2 * w, c)


def _phases(kernel: jax.Array, axis: int) -> jax.Array:
    """Returns a 3-tap kernel's two 2-tap kernels along `axis` (a new axis before it: phase 0, then 1) that act on
    the nearest-upsampled signal's source: output 2i sees source rows (i - 1, i), output 2i + 1 rows (i, i + 1)."""
    before, centre, after = (jnp.take(kernel, k, axis=axis) for k in range(3))
    even = jnp.stack([before, centre + after], axis=axis)
    odd = jnp.stack([before + centre, after], axis=axis)
    return jnp.stack([even, odd], axis=axis)


def upsampled_conv(inputs: jax.Array, kernel: jax.Array, window_strides=(1, 1), padding="SAME", **_) -> jax.Array:
    """Returns the SAME 3x3 convolution of `upsample(inputs)` (N, 2H, 2W, O), computed on the H x W source.

    Each output pixel of a 3x3 convolution of a nearest-upsampled map sees only 2 x 2 source
    pixels, which ones depending on its position in its 2 x 2 block (its phase). So the four
    phases are one 2x2 convolution of the source padded by one pixel, with four 2x2 kernels summed
    from the 3x3 one (4 O outputs), each phase read at its offset and the four interleaved:
    16 multiply-adds per source pixel and filter instead of 36, the same function up to rounding.
    It is called as `lax.conv_general_dilated`, so `nn.Conv(..., conv_general_dilated=upsampled_conv)`
    keeps the plain convolution's weights (a 3x3 kernel, the same names); the other arguments are
    those of a stride-1 SAME convolution in NHWC / HWIO (the layouts are not read).
    """
    if tuple(window_strides) != (1, 1) or padding != "SAME" or kernel.shape[:2] != (3, 3):
        raise ValueError(f"upsampled_conv is a 3x3 SAME convolution of stride 1, not {kernel.shape[:2]} {padding}")
    n, h, w, _ = inputs.shape
    out = kernel.shape[-1]
    phases = _phases(_phases(kernel, 0), 2)  # (row phase, row tap, column phase, column tap, I, O)
    combined = phases.transpose(1, 3, 4, 0, 2, 5).reshape(2, 2, kernel.shape[2], 4 * out)
    padded = jnp.pad(inputs, ((0, 0), (1, 1), (1, 1), (0, 0)))
    y = jax.lax.conv_general_dilated(padded, combined, (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    y = y.reshape(n, h + 1, w + 1, 2, 2, out)
    rows = [jnp.stack([y[:, a : a + h, b : b + w, a, b] for b in (0, 1)], axis=3) for a in (0, 1)]
    return jnp.stack(rows, axis=2).reshape(n, 2 * h, 2 * w, out)


def max_pool(x: jax.Array) -> jax.Array:
    """Returns MaxPool(2, 2) of (N, H, W, C) feature maps (odd edges dropped, as with VALID padding).

    A reshape and a max, whose gradient is a mask; XLA's select-and-scatter gradient of
    `nn.max_pool` is slow on CPU.
    """
    n, h, w, c = x.shape
    x = x[:, : h - h % 2, : w - w % 2]
    return x.reshape(n, h // 2, 2, w // 2, 2, c).max(axis=(2, 4))


def depth_to_space(x: jax.Array) -> jax.Array:
    """Returns (N, H, W, 4C) feature maps rearranged to (N, 2H, 2W, C) (a sub-pixel convolution's shuffle)."""
    n, h, w, c = x.shape
    return x.reshape(n, h, w, 2, 2, c // 4).transpose(0, 1, 3, 2, 4, 5).reshape(n, 2 * h, 2 * w, c // 4)


def coordinate_channels(x: jax.Array) -> jax.Array:
    """Returns (N, H, W, C) feature maps with two more channels: each pixel's x and y in [-1, 1]."""
    n, h, w, _ = x.shape
    ys = (jnp.arange(h, dtype=x.dtype) + 0.5) / h * 2.0 - 1.0
    xs = (jnp.arange(w, dtype=x.dtype) + 0.5) / w * 2.0 - 1.0
    grid = jnp.stack(jnp.meshgrid(xs, ys, indexing="xy"), axis=-1)
    return jnp.concatenate([x, jnp.broadcast_to(grid, (n, h, w, 2))], axis=-1)


def srgb_encode(linear: jax.Array) -> jax.Array:
    """Returns sRGB-encoded values of linear ones, clipped to [0, 1], with finite gradients everywhere."""
    x = jnp.clip(linear, 0.0, 1.0)
    return jnp.where(x <= 0.0031308, 12.92 * x, 1.055 * jnp.maximum(x, 0.0031308) ** (1.0 / 2.4) - 0.055)


def srgb_slope(linear: jax.Array) -> jax.Array:
    """Returns the slope of `srgb_encode`'s curve at linear values in [0, 1], ignoring its clip (1.055/2.4 at 1)."""
    return jnp.where(linear <= 0.0031308, 12.92, (1.055 / 2.4) * jnp.maximum(linear, 0.0031308) ** (1 / 2.4 - 1))


def srgb_decode(encoded: jax.Array) -> jax.Array:
    """Returns linear values of sRGB-encoded ones in [0, 1]."""
    return jnp.where(encoded <= 0.04045, encoded / 12.92, ((jnp.maximum(encoded, 0.04045) + 0.055) / 1.055) ** 2.4)


def interpolate_glass(basis: jax.Array, specular: jax.Array, roughness: jax.Array) -> jax.Array:
    """Returns the clear-glass basis (S, G, H, W, C) interpolated bilinearly at unit-cube specular and roughness (N,).

    The grid is `scene.glass_grid_values`: uniform in specular, uniform in the square root of
    roughness. The result (N, H, W, C) is differentiable in both. One row gather per corner from the
    basis laid out as (S G, H W C): on CPU, XLA gathers whole rows far faster than single values.
    """
    specular_count, roughness_count = basis.shape[:2]
    table = basis.reshape(specular_count * roughness_count, -1)
    s = jnp.clip(specular, 0.0, 1.0) * (specular_count - 1)
    r = jnp.sqrt(jnp.clip(roughness, 1e-6, 1.0)) * (roughness_count - 1)
    s0 = jnp.clip(jnp.floor(s), 0, specular_count - 2)
    r0 = jnp.clip(jnp.floor(r), 0, roughness_count - 2)
    ws, wr = (s - s0)[:, None], (r - r0)[:, None]
    i, j = s0.astype(jnp.int32), r0.astype(jnp.int32)

    def at(i, j):
        return jnp.take(table, i * roughness_count + j, axis=0)  # (N, H W C)

    low = at(i, j) * (1 - wr) + at(i, j + 1) * wr
    high = at(i + 1, j) * (1 - wr) + at(i + 1, j + 1) * wr
    return (low * (1 - ws) + high * ws).reshape(-1, *basis.shape[2:])


def medium_physical(unit: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Returns the interior medium's optical thickness of a radius per colour, tau = density x -ln(colour) (N, 3),
    and its albedo (N, 1), from unit-cube parameters (N, 19)."""
    physical = params.LOW.astype(np.float32)[None] + unit * (params.HIGH - params.LOW).astype(np.float32)[None]
    colour = physical[:, params.INDEX["medium_color_r"] : params.INDEX["medium_color_b"] + 1]
    tau = physical[:, params.INDEX["density"], None] * -jnp.log(jnp.clip(colour, 1e-3, 1.0))
    return tau, physical[:, params.INDEX["scattering"], None]


def medium_weights(unit: jax.Array, shape: Sequence[int]) -> jax.Array:
    """Returns the bilinear weights (N, 3, T A) of the scattering basis grid `shape` (T, A) per colour channel.

    Channel k reads the grid at its own optical thickness tau_k = density x -ln(colour_k) per radius
    (in `scene.medium_grid_values`' coordinate log2(1 + 8 tau)) and at sqrt(1 - albedo); each
    channel's weights sum to 1 and are differentiable in every medium parameter. Hat functions
    rather than gathers: the basis is small, so the weighted sum is one dense contraction.
    """
    thickness_count, albedo_count = shape
    tau, albedo = medium_physical(unit)
    t = jnp.log2(1.0 + scene.THICKNESS_SCALE * tau) / scene.LARGEST_COORDINATE * (thickness_count - 1)
    a = jnp.sqrt(jnp.clip(1.0 - albedo, 1e-6, 1.0)) * (albedo_count - 1)  # (N, 1)
    t_grid = jnp.arange(thickness_count, dtype=tau.dtype)[None, None, :]
    a_grid = jnp.arange(albedo_count, dtype=tau.dtype)[None, None, :]
    hat_t = jax.nn.relu(1.0 - jnp.abs(jnp.clip(t, 0.0, thickness_count - 1)[..., None] - t_grid))  # (N, 3, T)
    hat_a = jax.nn.relu(1.0 - jnp.abs(a[..., None] - a_grid))  # (N, 1, A)
    return (hat_t[..., :, None] * hat_a[..., None, :]).reshape(*tau.shape, thickness_count * albedo_count)


def absorbed(unit: jax.Array, path: jax.Array) -> jax.Array:
    """Returns the transmittance exp(-L tau) (N, R, R, 3) of light crossing the medium along paths L (N, R, R, 1).

    tau is each colour's extinction per radius (`medium_physical`: density x -ln(colour), known
    exactly from the unit-cube parameters (N, 19)), L in radii, one length for all three colours:
    the colour of what is seen through a tinted sphere follows from Beer-Lambert, and a network
    that predicts L only learns how far the light travels inside it.
    """
    tau, _ = medium_physical(unit)
    return jnp.exp(-path * tau[:, None, None, :])


def medium_features(unit: jax.Array) -> jax.Array:
    """Returns 10 physical features of the interior medium (N, 10) from unit-cube parameters (N, 19).

    What a medium looks like depends on its parameters through steep functions that a few dense
    layers learn poorly from samples: a dense white medium (milk) turns grey as the scattering
    albedo drops from 1 to 0.9. Per colour channel, with the optical thickness tau = density x
    -ln(colour) per radius and albedo a: the opacity of a diameter 1 - exp(-2 tau), its
    absorption-only transmittance exp(-2 tau (1 - a)) and its scattered share 1 - exp(-2 tau a);
    and the diffuse reflectance of a half-space of albedo a (van de Hulst's similarity relation,
    s = sqrt(1 - a): (1 - s)(1 - 0.139 s) / (1 + 1.17 s)).
    """
    radius, albedo = medium_physical(unit)
    tau = 2.0 * radius  # through a diameter
    s = jnp.sqrt(jnp.clip(1.0 - albedo, 1e-6, 1.0))
    reflectance = (1.0 - s) * (1.0 - 0.139 * s) / (1.0 + 1.17 * s)
    return jnp.concatenate(
        [1.0 - jnp.exp(-tau), jnp.exp(-tau * (1.0 - albedo)), 1.0 - jnp.exp(-tau * albedo), reflectance], axis=-1
    )


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
    def __call__(self, x: jax.Array) -> jax.Array:
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
    def __call__(self, image: jax.Array, train: bool = False) -> jax.Array:
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
    return jax.jit(model.init)(key, jnp.zeros((1, *input_shape), jnp.float32))  # compiled: faster than op by op


def as_float32(variables: dict) -> dict:
    """Returns the weights as float32 (float32 weights are left as they are): an encoder loaded alone (`load`) keeps
    its stored float16 weights, which a compiled program then converts where XLA runs."""
    return jax.tree_util.tree_map(lambda leaf: jnp.asarray(leaf).astype(jnp.float32), variables)


@programs.jit(static_argnames=("module",))
def apply(module: nn.Module, variables: dict, x: jax.Array) -> jax.Array:
    """Returns `module` applied to a batch in inference mode; compiled once per module and shape."""
    return module.apply(as_float32(variables), x)


def apply_in_batches(module: nn.Module, variables: dict, inputs: np.ndarray, batch: int = 256) -> np.ndarray:
    """Returns `module` applied to every input, float32, in batches of one size (one compilation per size)."""
    batch = max(1, min(batch, len(inputs)))
    outputs = []
    for start in range(0, len(inputs), batch):
        chunk = np.asarray(inputs[start : start + batch], np.float32)
        if len(chunk) < batch:
            chunk = np.concatenate([chunk, np.zeros((batch - len(chunk), *chunk.shape[1:]), np.float32)])
        outputs.append(np.asarray(apply(module, variables, chunk))[: min(batch, len(inputs) - start)])
    return np.concatenate(outputs)


def encoder_input(linear: np.ndarray) -> np.ndarray:
    """Returns what every encoder sees of linear images (..., R, R, 3): clipped to [0, 1], box-filtered
    to ENCODER_RESOLUTION, then sRGB-encoded, float32. R must be a multiple of ENCODER_RESOLUTION.

    Clipping comes first because a target to fit is a picture, already clipped: a training render's
    HDR highlight averaged before clipping would show the encoder up to 0.12 brighter pixels than
    the same render saved as a picture. Training, evaluation and fitting all call this function.
    """
    clipped = np.clip(np.asarray(linear, np.float32), 0.0, 1.0)
    return images.srgb_encode(images.box_downsample(clipped, ENCODER_RESOLUTION))


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


def save(path: str, network: Network, dtype: np.dtype = np.float16) -> None:
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
        with open(path, "rb") as file:
            data = file.read()
        document = serialization.msgpack_restore(data)
    except FileNotFoundError:
        raise WeightsError(f"{path} does not exist: train it with `matfit train` or check the path") from None
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
    path: str, description: dict, stored: dict, dtype: type | None = np.float32
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


def describe_network(description: dict) -> str:
    """Returns which network an architecture description is of: "decoder" or "encoder-N"."""
    if description.get("kind") == DECODER:
        return DECODER
    return f"encoder-{description.get('arch')}"


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

    def decode(self, unit: np.ndarray) -> np.ndarray:
        """Returns phi(x) of unit-cube parameters (N, 19): sRGB images (N, R, R, 3), float32, decoded in batches."""
        return apply_in_batches(
            self.decoder.module, self.decoder.variables, np.asarray(unit, np.float32).reshape(-1, params.COUNT)
        )


def weights_path(directory: str, name: str) -> str:
    """Returns where network `name` lives in a model directory."""
    return os.path.join(directory, name + WEIGHTS_SUFFIX)


def load_model(directory: str) -> Model:
    """Returns the decoder and every encoder found in a model directory (at least one encoder)."""
    if not os.path.isdir(directory):
        raise WeightsError(
            f"model directory {directory} does not exist: train one with `matfit train`, "
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


# The most the program store may hold: the shipped model's default fit stores ~2.4 MB of executables (its four compiled
# stages and the encoders' conversion); every new matfit, JAX or model writes new entries beside the old, which only
# pruning removes.
CACHE_BYTES = {"programs": 64 * 2**20}


def enable_compilation_cache() -> None:
    """Turns on matfit's store of compiled programs (`programs.py`) under $XDG_CACHE_HOME/matfit or ~/.cache/matfit.

    A second `matfit fit` then loads its compiled stages instead of tracing and compiling them again. The store
    does not grow without bound: each process first prunes it to `CACHE_BYTES` (least recently used first).
    JAX's own persistent compilation cache is not turned on: the store keeps the executables themselves, and an
    executable that JAX read from its cache does not survive being stored again (it fails at its next load with
    "Function ... not found"). What earlier matfit versions kept there (`matfit/jax`) is removed. A store that
    another user could have written (see `programs`) is not used, with a one-line notice on standard error.
    """
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    stored = os.path.join(root, "matfit", "programs")
    try:
        programs.enable(stored)
    except OSError:
        return  # no writable cache: trace and compile every time
    except OutputError as error:  # a store others could have written to is never read: said once, then compiled
        print(f"notice: compiled programs are not stored or read: {error}", file=sys.stderr)
        return
    programs.prune(os.path.join(root, "matfit", "jax"), 0)
    programs.prune(stored, CACHE_BYTES["programs"])
