"""Shared fixtures: one tiny renderer for the whole session (loading a scene compiles kernels); strict JAX promotion."""

from __future__ import annotations

import jax
import pytest

from matfit.render import Renderer

TEST_RESOLUTION = 16
TEST_SPP = 16

# As optimistix's tests do: a silent broadcast or dtype promotion in matfit's JAX code is an error.
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture(scope="session")
def renderer() -> Renderer:
    """Returns a 16 x 16, 16-spp renderer of the test scene, shared by every test."""
    return Renderer(TEST_RESOLUTION, TEST_SPP)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory, renderer) -> str:
    """Returns the path of a finished 32 px, 4-spp, 48-sample dataset (encoders need 32 px)."""
    from matfit import dataset

    path = str(tmp_path_factory.mktemp("tiny") / "data")
    data = dataset.prepare(path, dataset.Settings(32, 4, 5, renderer.variant), 48, {"mitsuba": "test", "drjit": "test"})
    dataset.render_missing(data, 0)
    return path
