"""Cycles against Mitsuba: the exported Blender script rendered in Blender's copy of the test scene.

Blender runs in a subprocess with its own Python (`matfit.rendering.blender_scene`): bpy 4.5 requires
numpy < 2, matfit numpy >= 2.4, so the two cannot share an environment (`make blender` builds
`.venv-blender` from the `blender` dependency group of pyproject.toml). Which Python: the
`--blender` argument, else $MATFIT_BLENDER_PYTHON, else `.venv-blender/bin/python` beside the
matfit package. A Blender executable works too (it is run as `blender -b -P ... -- job.json`).

How the two renders are compared: both are linear images of the same scene at the same
resolution. Blender's lights and environment are given in Mitsuba's radiance units, but one
exposure factor is still matched, for the whole run, not per material (so that a material that
is too bright or too dark in Cycles stays so): the ratio of the mean linear values of Mitsuba's
and Cycles' images over the pixels outside the sphere's silhouette (floor, backdrop), over every
material of the run. Then the RMSE (0-255 sRGB, as everywhere in matfit) over the whole image and
over the sphere's silhouette alone.
"""

from __future__ import annotations

import collections
import json
import os
import subprocess
import tempfile
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from matfit import files, images, shipped
from matfit.errors import RenderError
from matfit.rendering import export, presets, scene
from matfit.rendering.engine import Renderer, check_request

ENVIRONMENT_VARIABLE = "MATFIT_BLENDER_PYTHON"
# `make blender` makes it beside the package in a clone; an installed matfit has none.
DEFAULT_PYTHON = str(shipped.PACKAGE.parent / ".venv-blender" / "bin" / "python")
TABLE_FILE, PICTURE_FILE = "blender-check.md", "blender-check.png"
OPAQUE_PRESETS = ("gold", "silver", "copper", "red-plastic", "blue-rubber", "velvet")
OPAQUE_TARGET = 8.0  # RMSE the opaque presets must stay under (issue 15)
PROGRESS_PREFIX = "matfit-blender:"  # the line blender_scene prints after each image


class BlenderError(RenderError):
    """Blender cannot be found or failed; the message says what to install or change."""


def find_blender(explicit: str | None = None) -> str:
    """Returns the Python with bpy (or the Blender executable) to run, or raises BlenderError."""
    candidate = explicit or os.environ.get(ENVIRONMENT_VARIABLE) or DEFAULT_PYTHON
    if not (os.path.isfile(candidate) and os.access(candidate, os.X_OK)):
        raise BlenderError(
            f"no Blender at {candidate}: point --blender or ${ENVIRONMENT_VARIABLE} at a Python with bpy 4.5 "
            "(`pip install bpy==4.5.15` in a Python 3.11 venv) or a Blender 4.5 executable; "
            "in a clone, `make blender` makes .venv-blender",
            field="blender",
        )
    return candidate


def _command(blender: str, job: str) -> list[str]:
    worker = str(shipped.PACKAGE / "rendering" / "blender_scene.py")
    if "python" in os.path.basename(blender):
        return [blender, worker, job]
    return [blender, "--background", "--factory-startup", "--python", worker, "--", job]


def render_scripts(
    scripts: list[str],
    resolution: int = 64,
    spp: int = 64,
    seed: int = 0,
    blender: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> np.ndarray:
    """Returns Cycles renders (N, H, W, 3), linear float32, of the test scene with each material script applied.

    `progress` receives Blender's one line per finished image; Ctrl-C stops Blender too.
    """
    executable = find_blender(blender)
    with tempfile.TemporaryDirectory(prefix="matfit-blender-") as folder:
        paths = []
        for index, script in enumerate(scripts):
            paths.append(os.path.join(folder, f"material-{index}.py"))
            with open(paths[-1], "w") as file:
                file.write(script)
        job = os.path.join(folder, "job.json")
        with open(job, "w") as file:
            json.dump({"resolution": resolution, "spp": spp, "seed": seed, "scripts": paths, "out": folder}, file)
        tail: collections.deque[str] = collections.deque(maxlen=20)
        try:
            with subprocess.Popen(
                _command(executable, job),
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                env={**os.environ, "PYTHONNOUSERSITE": "1"},
            ) as process:
                assert process.stdout is not None  # stdout=PIPE
                for line in process.stdout:
                    tail.append(line.rstrip())
                    if progress is not None and line.startswith(PROGRESS_PREFIX):
                        progress(line.rstrip())
        except OSError as error:
            raise BlenderError(f"cannot run Blender ({executable}): {error.strerror or error}") from None
        if process.returncode != 0:
            errors = [line for line in tail if "Error" in line] or list(tail) or [f"exit code {process.returncode}"]
            raise BlenderError(f"Blender ({executable}) failed: {errors[-1].strip()}")
        return np.stack([np.load(os.path.join(folder, f"{index}.npy")) for index in range(len(scripts))])


@dataclass
class Comparison:
    """Mitsuba and Cycles renders of the same materials, and how far apart they are."""

    names: list[str]
    mitsuba: np.ndarray  # (N, H, W, 3) linear
    cycles: np.ndarray  # (N, H, W, 3) linear, exposure-matched
    exposure: float  # the factor Cycles' images were multiplied by
    rmse: list[float]  # whole image, 0-255 sRGB
    rmse_sphere: list[float]  # sphere's silhouette only
    noise: list[float]  # Mitsuba against Mitsuba with another seed, whole image: the noise floor
    resolution: int
    spp: int


@dataclass(frozen=True)
class Setup:
    """How both renderers render a comparison: image side, samples per pixel, which Blender, which Mitsuba variant."""

    resolution: int = 64
    spp: int = 256
    blender: str | None = None  # see find_blender
    variant: str | None = None  # None: engine.py chooses


def compare(
    names: list[str], materials: list[np.ndarray], setup: Setup = Setup(), progress: Callable[[str], None] | None = None
) -> Comparison:
    """Returns the Comparison of Mitsuba and Cycles renders of `materials` (physical vectors (19,))."""
    resolution, spp = setup.resolution, setup.spp
    scripts = [export.blender_script(values) for values in materials]
    cycles = render_scripts(scripts, resolution, spp, blender=setup.blender, progress=progress)
    renderer = Renderer(resolution, spp, setup.variant)
    first, second = [], []
    for index, values in enumerate(materials):
        first.append(renderer.render(values, seed=0))
        second.append(renderer.render(values, seed=1))
        if progress is not None:
            progress(f"matfit-mitsuba: rendered {index + 1}/{len(materials)} (twice, seeds 0 and 1)")
    mitsuba, again = np.stack(first), np.stack(second)
    mask = scene.sphere_mask(resolution)
    exposure = float(mitsuba[:, ~mask].mean() / max(cycles[:, ~mask].mean(), 1e-12))
    cycles = cycles * exposure
    encoded_m, encoded_c = images.srgb_encode(mitsuba), images.srgb_encode(cycles)
    rmse = [float(x) for x in images.rmse(encoded_c, encoded_m)]
    rmse_sphere = [float(x) for x in images.rmse(encoded_c, encoded_m, mask.astype(np.float64))]
    noise = [float(x) for x in images.rmse(images.srgb_encode(again), encoded_m)]
    return Comparison(list(names), mitsuba, cycles, exposure, rmse, rmse_sphere, noise, resolution, spp)


def table(comparison: Comparison, targets: dict[str, float] | None = None) -> str:
    """Returns the comparison as a Markdown table."""
    targets = {name: OPAQUE_TARGET for name in OPAQUE_PRESETS} if targets is None else targets
    lines = [
        f"Cycles (Blender {comparison.resolution} px, {comparison.spp} spp) against Mitsuba ({comparison.spp} spp), "
        f"exposure factor {comparison.exposure:.4f} for every material (matched on the floor and backdrop).",
        "",
        "| material | RMSE, whole image | RMSE, sphere only | noise floor (Mitsuba, two seeds) | target |",
        "|---|---|---|---|---|",
    ]
    for name, whole, sphere, noise in zip(
        comparison.names, comparison.rmse, comparison.rmse_sphere, comparison.noise, strict=True
    ):
        target = targets.get(name)
        verdict = "" if target is None else f"<= {target:g} ({'met' if whole <= target else 'missed'})"
        lines.append(f"| {name} | {whole:.2f} | {sphere:.2f} | {noise:.2f} | {verdict} |")
    return "\n".join(lines) + "\n"


def picture(comparison: Comparison, scale: int = 2) -> np.ndarray:
    """Returns a linear image: one row per material, Mitsuba | Cycles | difference x4, labelled."""
    rows = []
    for name, m, c, whole in zip(comparison.names, comparison.mitsuba, comparison.cycles, comparison.rmse, strict=True):
        tiles = [images.srgb_encode(m), images.srgb_encode(c)]
        tiles.append(np.clip(4.0 * np.abs(tiles[0] - tiles[1]), 0.0, 1.0))
        tiles = [np.repeat(np.repeat(tile, scale, axis=0), scale, axis=1) for tile in tiles]
        captions = [f"{name}: Mitsuba", "Cycles", f"diff x4, RMSE {whole:.1f}"]
        rows.append(
            np.concatenate([images.label(tile, caption) for tile, caption in zip(tiles, captions, strict=True)], axis=1)
        )
    return images.srgb_decode(np.concatenate(rows, axis=0))


def check(
    out: str,
    names: list[str] | None = None,
    params_files: list[str] | None = None,
    setup: Setup = Setup(),
    progress: Callable[[str], None] | None = None,
) -> Comparison:
    """Compares presets and params.json files in Cycles and Mitsuba; writes out/blender-check.md and .png.

    `names` None: every preset. Both files are written only at the end.
    """
    params_files = list(params_files or [])
    names = list(presets.PRESETS) if names is None else list(names)
    materials = [presets.preset(name) for name in names]
    for path in params_files:
        materials.append(presets.material(params_file=path))
        names.append(os.path.splitext(os.path.basename(path))[0])
    if not materials:
        raise BlenderError("nothing to compare: give a preset or a params.json file", field="preset")
    outputs = {"table": os.path.join(out, TABLE_FILE), "picture": os.path.join(out, PICTURE_FILE)}
    files.check_folder(out, outputs, [("params_file", path) for path in params_files])
    check_request(setup.variant)
    find_blender(setup.blender)
    comparison = compare(names, materials, setup, progress)
    os.makedirs(out, exist_ok=True)
    images.write(os.path.join(out, PICTURE_FILE), picture(comparison))
    files.write_text(os.path.join(out, TABLE_FILE), table(comparison))
    return comparison
