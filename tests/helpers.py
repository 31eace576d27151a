"""Shared test helpers: a random model small enough to fit with in milliseconds."""

import functools

import jax
import numpy as np
import pytest

from matfit import images, params
from matfit.model import architectures, models, weight_files

R = 32


def random_model(seed: int = 0) -> models.Model:
    """A random 32 px decoder and two random encoders: enough to test the machinery, not quality.

    Built once per seed for the whole session (initialising the three networks compiles them: seconds each time)
    and shared by every test file: a `Model` is frozen and its weights are immutable JAX arrays.
    """
    return _random_model(seed)


@functools.cache
def _random_model(seed: int) -> models.Model:
    decoder = architectures.Decoder(resolution=R, hidden=64, base_channels=32, stage_channels=(32,))
    variables = architectures.initialise(decoder, jax.random.key(seed), (19,))
    networks = {}
    for arch in (3, 8):
        module = architectures.encoder(arch)
        networks[arch] = weight_files.Network(
            f"encoder-{arch}",
            architectures.architecture(f"encoder-{arch}", 64),
            module,
            architectures.initialise(module, jax.random.key(arch), (32, 32, 3)),
            {},
        )
    return models.Model(
        "memory",
        weight_files.Network("decoder", architectures.architecture("decoder", R, decoder), decoder, variables, {}),
        networks,
    )


def decode(model, unit):
    return model.decode(unit)[0]


def true_point(seed):
    return np.random.default_rng(seed).uniform(0.15, 0.85, params.COUNT).astype(np.float32)


class Noisy:
    """A renderer whose picture of a material is the target, plus the material's offset, plus noise drawn from the
    seed alone (common random numbers: every material's batch j has the same noise pattern, scaled by its own
    spread). Any other material (a round of correction's point) is 0.3 off, without noise. Records every render as
    (material's name or None, seed)."""

    def __init__(self, target, materials):
        self.target, self.materials, self.asked = target, materials, []

    def prefetch(self, values, seed=0, spp=None):
        pass

    def render(self, values, seed=0, spp=None):
        name = next((n for n, (v, _, _) in self.materials.items() if np.allclose(v, values)), None)
        self.asked.append((name, seed))
        _, offset, spread = self.materials[name] if name is not None else (None, 0.3, 0.0)
        noise = np.random.default_rng(seed).normal(0, 1, self.target.shape)
        return images.srgb_decode(np.clip(self.target + offset + spread * noise, 0, 1).astype(np.float32))


# The export cannot carry the medium's colour and density apart: Blender holds their product, the extinction
# density x -ln(colour) (blender_mapping's docstring), which is compared instead.
MEDIUM_PRODUCT = ("medium_color_r", "medium_color_g", "medium_color_b", "density")


def assert_round_trip(values, back, missing):
    """Every parameter the export carries comes back within 1e-3; the medium as its extinction."""
    for name, expected, got in zip(params.NAMES, values, back, strict=True):
        if name not in missing and name not in MEDIUM_PRODUCT:
            assert got == pytest.approx(expected, abs=1e-3), name
    if "density" not in missing:
        np.testing.assert_allclose(
            params.medium_coefficients(back)[0], params.medium_coefficients(values)[0], atol=1e-3
        )
