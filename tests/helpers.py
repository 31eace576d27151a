"""Shared test helpers: a random model small enough to fit with in milliseconds."""

import jax
import numpy as np

from matfit import models, params

R = 32


def random_model(seed: int = 0) -> models.Model:
    """A random 32 px decoder and two random encoders: enough to test the machinery, not quality."""
    decoder = models.Decoder(resolution=R, hidden=64, base_channels=32, stage_channels=(32,))
    variables = models.initialise(decoder, jax.random.key(seed), (19,))
    networks = {}
    for arch in (3, 8):
        module = models.encoder(arch)
        networks[arch] = models.Network(
            f"encoder-{arch}",
            models.architecture(f"encoder-{arch}", 64),
            module,
            models.initialise(module, jax.random.key(arch), (32, 32, 3)),
            {},
        )
    return models.Model(
        "memory",
        models.Network("decoder", models.architecture("decoder", R, decoder), decoder, variables, {}),
        networks,
    )


def decode(model, unit):
    return model.decode(unit)[0]


def true_point(seed):
    return np.random.default_rng(seed).uniform(0.15, 0.85, params.COUNT).astype(np.float32)
