"""Shared fixtures: one tiny renderer for the whole session (loading a scene compiles kernels); strict JAX promotion."""

from __future__ import annotations

import os

# The suite's time is XLA compiling, not running: LLVM's optimisation of the many small programs the
# tests build (the tiny decoders' initialisation took 34 s at XLA's default level, 2.5 s at 0, with
# the same numbers). Set before JAX's backend starts; processes the tests start inherit it.
# Under `pytest -n` with several workers, each worker's XLA runs its matrix products on one thread: the
# workers already fill the cores, and their thread pools competing for them cost a third more CPU time
# (docs/decisions.md). xdist sets PYTEST_XDIST_WORKER_COUNT before this file is read.
XLA_TEST_FLAGS = "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    XLA_TEST_FLAGS += " --xla_cpu_multi_thread_eigen=false"
if XLA_TEST_FLAGS not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {XLA_TEST_FLAGS}".strip()
# As optimistix's tests do: a silent broadcast or dtype promotion in matfit's JAX code is an error. Set in the
# environment, which JAX reads at import, so that the `matfit` processes the tests start check it too, and share
# the program store with the tests (its key holds these settings).
os.environ["JAX_NUMPY_RANK_PROMOTION"] = "raise"
os.environ["JAX_NUMPY_DTYPE_PROMOTION"] = "strict"

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from matfit.rendering.engine import Renderer  # noqa: E402

TEST_RESOLUTION = 16
TEST_SPP = 16

assert jax.config.jax_numpy_rank_promotion == "raise" and jax.config.jax_numpy_dtype_promotion == "strict"


@pytest.fixture(scope="session", autouse=True)
def session_cache(tmp_path_factory):
    """Returns the one $XDG_CACHE_HOME of the session (of every worker of `pytest -n`), set for this process and
    every process it starts.

    So the suite neither reads nor fills the user's ~/.cache/matfit, and a program that one test compiled (an
    in-process `matfit fit`, say) is read back from matfit's program store (`matfit/programs.py`) by a later test or
    `matfit` process that needs it, instead of being traced and compiled again.
    """
    with pytest.MonkeyPatch.context() as patch:
        if os.environ.get("PYTEST_XDIST_WORKER"):  # `pytest -n`: one store for every worker of the run
            path = tmp_path_factory.getbasetemp().parent / "cache"
            path.mkdir(exist_ok=True)
        else:
            path = tmp_path_factory.mktemp("cache")
        patch.setenv("XDG_CACHE_HOME", str(path))
        yield path


@pytest.fixture(scope="session")
def renderer() -> Renderer:
    """Returns a 16 x 16, 16-spp renderer of the test scene, shared by every test."""
    return Renderer(TEST_RESOLUTION, TEST_SPP)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory, renderer) -> str:
    """Returns the path of a finished 32 px, 4-spp, 48-sample dataset (encoders need 32 px)."""
    from matfit.model import dataset, dataset_writing
    from matfit.rendering import scene

    path = str(tmp_path_factory.mktemp("tiny") / "data")
    data = dataset_writing.prepare(
        path, dataset.Settings(32, 4, 5, renderer.variant), 48, {"mitsuba": "test", "drjit": "test"}
    )
    dataset_writing.render_missing(data, 0)
    # The default decoder's clear-glass basis, as `Dataset.glass_basis` keeps it, rendered at 4 spp
    # instead of 1024 so that tests training the default decoder do not spend minutes on it.
    cheap = Renderer(32, 4, renderer.variant)
    basis = np.stack([[cheap.render(material) for material in row] for row in scene.glass_basis_materials()])
    np.save(os.path.join(path, dataset.GLASS_FILE.format(specular=basis.shape[0], roughness=basis.shape[1])), basis)
    return path


@pytest.fixture(scope="session")
def knot(tmp_path_factory):
    """Returns the bench's torus knot under the studio light as a read scene file, its camera 32x24 (tests of a scene
    of the user's own; tests/test_scene_file.py has a `knot` of its own, the file's path)."""
    from matfit.rendering import scene_file, scene_library

    path = scene_library.write(str(tmp_path_factory.mktemp("scenes")), "knot", "studio", width=32, height=24)
    return scene_file.read(path, "object")


@pytest.fixture
def tiny_scene_fits(monkeypatch):
    """Scene fits at a tiny configuration, their logic and not their figures (`matfit bench-scene` measures those):
    renders 32 pixels on the longer side, a judge of 32 samples a pixel, probes of 8."""
    from matfit.fitting import scene_fit, scene_judge, scene_ranges

    monkeypatch.setattr(scene_fit, "FIT_SIZE", 32)
    monkeypatch.setattr(scene_judge, "JUDGE_SPP", 32)
    monkeypatch.setattr(scene_ranges, "PROBE_SPP", 8)


@pytest.fixture(scope="session")
def red_picture(knot) -> np.ndarray:
    """Returns the knot in red plastic, linear (48, 64, 3): the picture a user renders and edits."""
    from matfit.rendering import presets, scene_file

    return scene_file.Renderer(knot, knot.size(64)).render(presets.preset("red-plastic"), seed=11, spp=64)


@pytest.fixture(scope="session")
def red_knot_fit(knot, red_picture):
    """Returns (the knot's judging renderer for an opaque material at 64x48, the red picture as a fit's sRGB target, the
    region's weights): what the tests of a fit's stages build their judge and problem on."""
    from matfit import images
    from matfit.fitting import scene_fit
    from matfit.rendering import scene_file

    renderer = scene_file.Renderer(knot, knot.size(64), integrator=scene_file.OPAQUE_INTEGRATOR)
    target = np.clip(images.srgb_encode(red_picture), 0.0, 1.0).astype(np.float32)
    return renderer, target, scene_fit.region(renderer)[0].astype(np.float32)
