"""Shared fixtures: one tiny renderer for the whole session (loading a scene compiles kernels)."""

from __future__ import annotations

import pytest

from matfit.render import Renderer

TEST_RESOLUTION = 16
TEST_SPP = 16


@pytest.fixture(scope="session")
def renderer() -> Renderer:
    """Returns a 16 x 16, 16-spp renderer of the test scene, shared by every test."""
    return Renderer(TEST_RESOLUTION, TEST_SPP)
