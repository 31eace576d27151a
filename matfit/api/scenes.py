"""A scene of the user's own (`Scene`): a Mitsuba 3 XML file and the shape whose material is fitted or rendered
there; its render (`render_values`) and its fit written as `matfit fit --scene` writes it (`fit_in_scene`).
docs/scenes.md."""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from matfit import documents, files, images, params
from matfit.api.arguments import MAX_SIZE, Picture, linear_pixels, path_text, shown, whole
from matfit.errors import ImageError, RenderError, SceneError

if TYPE_CHECKING:
    from matfit.fitting.request import Outputs as RequestOutputs
    from matfit.fitting.request import Request
    from matfit.fitting.scene_fit import Guess, SceneOutcome
    from matfit.model.models import Loader
    from matfit.rendering.scene_file import SceneFile

MAX_STEPS = 10_000  # the descent's steps a fit may ask for (`matfit fit --refine`'s most)


@dataclass(frozen=True)
class Scene:
    """A Mitsuba 3 scene file of your own (`path`, its meshes and images beside it) and the id of the shape whose
    material is fitted or rendered (`object`). Camera, lights and the other shapes stay as the file has them.
    """

    path: str | os.PathLike[str]
    object: str

    def read(self) -> SceneFile:
        """Returns the scene file read and checked (`MatfitError` naming what is wrong and the fix)."""
        from matfit.rendering import scene_file

        if not isinstance(self.path, str | os.PathLike):
            raise SceneError(f"scene {shown(self.path)} is no path: give a Mitsuba 3 XML file's path", "scene")
        if not isinstance(self.object, str):
            raise SceneError(f"object {shown(self.object)} is no shape id: give the shape's id attribute", "object")
        return scene_file.read(os.fspath(self.path), self.object)


def check_scene(scene: object) -> Scene:
    """Returns `scene` if it is a `Scene`, else the one-line SceneError."""
    if not isinstance(scene, Scene):
        raise SceneError(f"scene {shown(scene)} is no matfit.Scene: give Scene(path, object) or None", "scene")
    return scene


_renderers: dict[tuple[str, str, tuple[int, int], str | None], Any] = {}


def render_values(
    values: np.ndarray, scene: Scene, *, size: int, spp: int, seed: int, variant: str | None
) -> np.ndarray:
    """Returns the linear float32 (H, W, 3) render of the scene with its shape's material `values`, `size` pixels
    on the longer side (the camera's aspect kept)."""
    from matfit.rendering import scene_file

    read = check_scene(scene).read()
    size = whole("size", size, 8, MAX_SIZE, RenderError)
    spp = whole("spp", spp, 1, 1 << 16, RenderError)
    seed = whole("seed", seed, 0, params.MAX_SEED, RenderError)
    key = (read.path, read.sha256 + read.object, read.size(size), variant)
    if key not in _renderers:
        _renderers.clear()  # one scene kept: a scene file's meshes can be large
        _renderers[key] = scene_file.Renderer(read, read.size(size), variant)
    return np.asarray(_renderers[key].render(values, seed=seed, spp=spp), np.float32)


def scene_inputs(read: SceneFile) -> list[tuple[str, str]]:
    """Returns the scene file and every file it names, as inputs no output may replace (`files.check_outputs`)."""
    return [("scene", read.path), *(("scene's file", path) for path in read.files)]


def identity(read: SceneFile) -> dict[str, object]:
    """Returns what identifies a scene fit's scene for the journal of several pictures (`batch.Journal`): its file's
    path and SHA-256, the shape's id, and the SHA-256 of every file it names (a mesh or image changed fits again)."""
    named = {path: files.sha256(path) for path in read.files}
    return {"path": read.path, "object": read.object, "sha256": read.sha256, "files": named}


def check_several(read: SceneFile, targets: list[str], folder: str, request: Request) -> None:
    """Raises the one-line error, before the first fit of several pictures in the scene `read` into `folder`
    (`Fitter.fit_all`), of steps out of range or of an output of a picture that is the scene's file or one it names;
    `request` is the template of the plan's (`batch.plan`)."""
    from matfit.fitting import batch

    whole("steps", request.refine_steps, 0, MAX_STEPS, SceneError)
    assert request.outputs is not None, "the template names the outputs"
    for target in targets:
        files.check_outputs(output_paths(batch.outputs_of(target, folder, request.outputs)), scene_inputs(read))


def output_paths(outputs: RequestOutputs) -> dict[str, str | None]:
    """Returns the files a scene fit writes, by the option that names each (`files.check_outputs`)."""
    return {
        "output": outputs.params,
        "report": outputs.report,
        "render": outputs.render,
        "mitsuba_xml": outputs.mitsuba_xml,
        "blender": outputs.blender,
    }


def render_file(
    values: np.ndarray, scene: Scene, output: str, *, size: int, spp: int, seed: int, variant: str | None
) -> tuple[int, int]:
    """Renders the scene with its shape's material `values` into the image file `output` (`matfit render --scene`)
    and returns its (width, height); the output is checked before any work and is not the scene's own file."""
    read = check_scene(scene).read()
    images.check_output(output)
    files.check_outputs({"output": output}, scene_inputs(read))
    pixels = render_values(values, scene, size=size, spp=spp, seed=seed, variant=variant)
    with files.together() as batch:
        images.write(batch.path(output), pixels)
    return pixels.shape[1], pixels.shape[0]


def _picture(picture: Picture, linear: bool) -> tuple[np.ndarray, str, str, list[str]]:
    """Returns (linear pixels, the target's name for params.json, its SHA-256, notices) of a file or an array."""
    if isinstance(picture, str | os.PathLike):
        path = path_text(picture)
        if not os.path.isfile(path):
            raise ImageError(f"target {path} is not a file: give the picture's path", field="target")
        loaded = images.load(path)
        return np.asarray(loaded.pixels, np.float32), path, files.sha256(path), list(loaded.notices)
    pixels, notices = linear_pixels(picture, "picture", linear=linear)
    digest = hashlib.sha256(np.ascontiguousarray(np.asarray(picture)).tobytes()).hexdigest()
    return pixels, "array", digest, notices


def mask_file(mask: str | os.PathLike[str]) -> str:
    """Returns the path of a mask given as a file; the one-line ImageError of one that is no file."""
    path = path_text(mask)
    if not os.path.isfile(path):
        raise ImageError(f"mask {path} is not a file: give the mask's path", field="mask")
    return path


def _mask(mask: Picture | None, shape: tuple[int, int]) -> tuple[np.ndarray | None, str | None]:
    if mask is None:
        return None, None
    if isinstance(mask, str | os.PathLike):
        path = mask_file(mask)
        pixels, name = np.asarray(images.load(path).pixels, np.float32), path
    else:
        pixels, name = linear_pixels(mask, "mask", linear=False)[0], "array"
    if pixels.shape[:2] != shape:
        raise ImageError(
            f"the mask is {pixels.shape[1]}x{pixels.shape[0]}, the picture {shape[1]}x{shape[0]}: give a mask of the "
            "picture's size",
            field="mask",
        )
    return np.clip(pixels.mean(axis=2), 0.0, 1.0), name


def fit_in_scene(
    picture: Picture,
    scene: Scene,
    *,
    init: np.ndarray | None,
    init_name: str | None,
    mask: Picture | None,
    linear: bool,
    steps: int,
    variant: str | None,
    outputs: RequestOutputs | None,
    progress: Callable[[str, int, int, float], None] | None,
    model: Loader | None = None,
) -> tuple[SceneOutcome, dict[str, Any]]:
    """Returns (the fit of the scene's shape to `picture`, its params.json document), its outputs written together
    once it is done (every path checked first). `init`: physical values to start from (None: the shape's own
    material, else the test scene's best-of-n of the shape's pixels with `model`'s networks, else matfit's
    default)."""
    from matfit.fitting import scene_fit

    started = time.perf_counter()
    read = check_scene(scene).read()
    steps = whole("steps", steps, 1, MAX_STEPS, SceneError)
    if outputs is not None:
        inputs = {
            "target": path_text(picture) if isinstance(picture, str | os.PathLike) else None,
            "mask": path_text(mask) if isinstance(mask, str | os.PathLike) else None,
            "init": init_name,
            "scene": read.path,
        }
        outputs.check(inputs)
        files.check_outputs(output_paths(outputs), scene_inputs(read))
    pixels, target_name, digest, notices = _picture(picture, linear)
    scene_fit.check_aspect(read, pixels.shape[0], pixels.shape[1], f"the picture {target_name}")
    weights, mask_name = _mask(mask, (pixels.shape[0], pixels.shape[1]))
    guess = None if model is None else _guess(model)
    outcome = scene_fit.fit(
        read, pixels, start=init, mask=weights, steps=steps, variant=variant, progress=progress, guess=guess
    )
    if init_name is not None:
        source = init_name
    elif outcome.guessed is not None:
        source = outcome.guessed
    else:
        source = "the shape's own material" if read.own is not None and init is None else "matfit's default"
    document = params.params_document(
        outcome.values,
        method="scene",
        target=target_name,
        target_sha256=digest,
        mask=mask_name,
        scene={
            "path": read.path,
            "object": read.object,
            "sha256": read.sha256,
            "camera": [read.width, read.height],
            "fit_size": [int(outcome.target.shape[1]), int(outcome.target.shape[0])],
            "own_material": read.own_note,
        },
        mitsuba_rmse=round(outcome.rmse, 4),
        start={
            "material": source,
            "rmse": round(outcome.start_rmse, 4),
            "params": params.to_mapping(outcome.start_values),
        },
        accepted=outcome.accepted,
        starts=outcome.starts,
        bounds=outcome.bounds,
        plain=outcome.plain,
        judge=outcome.judge,
        residual=outcome.residual,
        again=outcome.again,
        steps={"short": min(scene_fit.SHORT_STEPS, max(1, steps // 4)), "descent": steps, "spp": scene_fit.STEP_SPP},
        integrator=outcome.integrator,
        region_fraction=round(float(outcome.weights.mean()), 4),
        ranges=outcome.ranges,
        notices=[*notices, *outcome.notices],
        fit_seconds=round(outcome.seconds, 3),
    )
    if outputs is not None:
        with files.together() as batch:
            write_outputs(outcome, read, outputs, batch, variant)
            document["wall_time_s"] = round(time.perf_counter() - started, 3)
            files.write_text(batch.path(outputs.params), documents.dumps(document))
    else:
        document["wall_time_s"] = round(time.perf_counter() - started, 3)
    return outcome, document


def _guess(model: Loader) -> Guess:
    """Returns the start's guess by the test scene's best-of-n with `model`'s networks (`scene_start.guess`)."""

    def guess(target: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, str]:
        from matfit.fitting import fitfile, scene_start

        values, chosen = scene_start.guess(fitfile.loaded(model), target, shape)
        return values, f"the test scene's best-of-n of the shape's pixels ({chosen})"

    return guess


def report_picture(outcome: SceneOutcome) -> np.ndarray:
    """Returns the report of a scene fit, sRGB: target | start | fit | difference x4 | where the fit looked."""
    difference = np.clip(np.abs(outcome.rendered - outcome.target) * 4.0, 0.0, 1.0)
    region = np.repeat(outcome.weights[..., None], 3, axis=2) * 0.8 + 0.2 * outcome.target
    panels = [
        (outcome.target, "target"),
        (outcome.start_rendered, f"start {outcome.start_rmse:.2f}"),
        (outcome.rendered, f"fit {outcome.rmse:.2f}"),
        (difference, "difference x4"),
        (region, "region"),
    ]
    return np.concatenate([images.label(np.asarray(p, np.float32), text, 10) for p, text in panels], axis=1)


def write_outputs(
    outcome: SceneOutcome, read: SceneFile, outputs: RequestOutputs, batch: files.Batch, variant: str | None
) -> None:
    """Writes a scene fit's report, render and exports into `batch` (params.json is the caller's)."""
    from matfit.rendering import export, scene_file

    if outputs.report is not None:
        images.write(batch.path(outputs.report), images.srgb_decode(report_picture(outcome)))
    if outputs.render is not None:
        large = scene_file.Renderer(read, read.size(outputs.render_size), variant)
        images.write(batch.path(outputs.render), large.render(outcome.values, spp=outputs.render_spp))
    if outputs.mitsuba_xml is not None:
        files.write_text(batch.path(outputs.mitsuba_xml), export.mitsuba_xml(outcome.values))
    if outputs.blender is not None:
        files.write_text(batch.path(outputs.blender), export.blender_script(outcome.values))
