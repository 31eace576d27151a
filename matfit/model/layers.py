"""The layers the networks are built from: pure functions of arrays, with the maths in their docstrings.

Nearest-neighbour upsampling + 3x3 convolutions (measured faster than transposed convolutions
on this CPU; the upsampling folded into the convolution, `upsampled_conv`), a max-pool and a
depth-to-space shuffle written for fast gradients, sRGB encoding, and the physical inputs of
the refracting decoder: the clear-glass basis read at a material (`interpolate_glass`) and the
interior medium's optical thickness, transmittance and features (`medium_physical`, `absorbed`,
`medium_features`, `medium_weights`). The modules that use them are `architectures.py`.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from matfit import params
from matfit.rendering import scene


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
    n, h, w = inputs.shape[:3]
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
    physical = unit * (params.HIGH - params.LOW).astype(np.float32)[None] + params.LOW.astype(np.float32)[None]
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
