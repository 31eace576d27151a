"""Fitting an image file end to end: read the target and mask, fit, verify in Mitsuba, write every output together.

This is what `matfit fit` does, as a library function: `run(request, model)` (a `request.Request`)
reads and checks the inputs, runs the stages (`stages.fit_stages`: the search, Mitsuba's verification after
rounds of correction, the ranges, the clean answer), makes params.json (`document.py`), and writes it, the
report, the render and the exports under temporary names, renaming them into place only once all of them
were written. `fit_file` does the same and writes nothing; `fit_neural(request, model)` runs the neural
search alone for a request that asks for nothing after it (each frame of `sequence`).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from matfit import files, images, programs
from matfit.fitting import document, search, stages
from matfit.fitting.outcome import Outcome
from matfit.fitting.request import Outputs, Request
from matfit.model import models
from matfit.rendering import engine as render
from matfit.rendering.process import Pool, Process


def load_model(path: str) -> models.Model:
    """Returns the model of a directory, with JAX's compilation cache on (a second fit loads its compiled programs)."""
    programs.enable_compilation_cache()
    return models.load_model(path)


def model_path(model: models.Model | str | models.Loader) -> str:
    """Returns the folder of a model, a model directory or a `models.Loader` (nothing is loaded)."""
    if isinstance(model, str):
        return model
    return model.path if isinstance(model, models.Model) else model.model_path


def loaded(model: models.Model | str | models.Loader) -> models.Model:
    """Returns the model itself: a directory's loaded (`load_model`), a loader's asked for."""
    if isinstance(model, str):
        return load_model(model)
    return model if isinstance(model, models.Model) else model.model


def read_target(
    path: str, resolution: int, *, mask: str | None = None
) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """Returns (sRGB target at the model's resolution, mask weights or None, notices) from image files."""
    loaded = images.load(path)
    weights = None if mask is None else read_mask(mask, loaded.pixels.shape[:2], resolution)
    target, notices = search.prepare_target(loaded.pixels, resolution, path)
    return target, weights, [*loaded.notices, *notices]


def run(
    request: Request,
    model: models.Model | str | models.Loader,
    *,
    renderer: Process | Pool | None = None,
    started: float | None = None,
    on_answer: Callable[[Outcome], None] | None = None,
) -> Outcome:
    """Fits the picture of `request` with a model (a model directory, or a `models.Loader`: loaded once the request
    was checked) and writes its outputs; returns what was found.

    `renderer`: a `process.Pool` (or `Process`) to verify with, started early by the caller (`fit_file`), or None. Every
    input is read and every output path checked before the fit (`Request.check`); the outputs are written
    together at the end (`files.together`), so a failure leaves none of them. `started`: the `time.perf_counter()`
    params.json's wall time counts from (None: now). `on_answer`: `stages.fit_stages`'s, each stage's answer as it
    lands (the last one's before any output is written, so that what it raises leaves none).
    """
    started = time.perf_counter() if started is None else started
    outputs = request.outputs
    if outputs is None:
        raise ValueError("run writes the request's outputs: name them (Outputs), or call fit_file")
    request.check(model_path(model))
    outcome, used = _fit_checked(request, model, renderer, on_answer)
    with files.together() as batch:
        write_outputs(outcome, outputs, batch, renderer=used)
        outcome.document["wall_time_s"] = round(time.perf_counter() - started, 3)
        files.write_text(batch.path(outputs.params), document.params_text(outcome))
    return outcome


def fit_file(
    request: Request,
    model: models.Model | str | models.Loader,
    *,
    renderer: render.Renderer | Process | Pool | None = None,
    on_answer: Callable[[Outcome], None] | None = None,
) -> tuple[Outcome, render.Renderer | Process | Pool | None]:
    """Returns (what a fit of the picture of `request` found, with its params.json document; the renderer used).

    Writes nothing: `run` writes the CLI's files, `serve` offers the same ones for download.
    `renderer`: a loaded `engine.Renderer` at the model's resolution to reuse, a `process.Pool` or `process.Process`
    (started early by the caller; it loads the scene here, and cannot refine), or None (a
    `process.Background` with the request's variant is made when verification, refinement or a render
    output needs one). Refinement differentiates with the renderer's variant. `on_answer`: `stages.fit_stages`'s, each
    stage's answer as it lands.
    """
    request.check(model_path(model))
    return _fit_checked(request, model, renderer, on_answer)


def _fit_checked(
    request: Request,
    model: models.Model | str | models.Loader,
    renderer: render.Renderer | Process | Pool | None,
    on_answer: Callable[[Outcome], None] | None = None,
) -> tuple[Outcome, render.Renderer | Process | Pool | None]:
    """Returns `fit_file`'s answer to a checked request: its inputs read, then the stages (`stages.fit_stages`)."""
    folder, model = model_path(model), loaded(model)
    target, weights, notices = request_target(request, model.resolution)
    return stages.fit_stages(request, model, folder, target, weights, notices, renderer, on_answer)


def fit_neural(request: Request, model: models.Model) -> search.Result:
    """Returns the neural search's result for a request that asks for nothing after it (a sequence's frame).

    The request must say so: no verification, refinement or outputs, and `answer="best"` (ValueError
    otherwise: call `fit_file`). Its picture is `request.pixels` when given, else read from its file.
    Unlike `fit_file`, a result whose RMSE is not finite is returned as it is: the caller records it.
    """
    asked = {
        "verification": request.verified,
        "refinement": bool(request.refine_steps),
        "outputs": request.outputs is not None,
        "the clean answer": request.answer == "clean",
    }
    if any(asked.values()):
        named = ", ".join(name for name, on in asked.items() if on)
        raise ValueError(f"fit_neural runs the neural search alone, not {named}: call fit_file for those")
    request.check()
    extra = request.extra_candidates()
    target, weights, _ = request_target(request, model.resolution)
    return stages.neural_stage(request, model, target, weights=weights, extra=extra)


def request_target(request: Request, resolution: int) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """Returns `read_target`'s (target, mask weights or None, notices) for a request: its `pixels` when the picture
    was read already (the mask sized by the picture file's header), else read from its file; its `weights` when the
    mask was read already."""
    mask = request.mask if request.weights is None else None  # weights given: the mask was read already
    if request.pixels is None:
        target, weights, notices = read_target(request.target, resolution, mask=mask)
    else:
        target, weights, notices = np.asarray(request.pixels), None, []
        if mask is not None:
            width, height = images.header(request.target)[:2]
            weights = read_mask(mask, (height, width), resolution)
    return target, (weights if request.weights is None else np.asarray(request.weights)), notices


def read_mask(path: str, shape: tuple[int, int], resolution: int) -> np.ndarray:
    """Returns the mask file's weights at the model's resolution for a picture of `shape` (height, width)."""
    return search.prepare_mask(images.load(path).pixels, shape, resolution, path)


def write_outputs(
    outcome: Outcome, outputs: Outputs, batch: files.Batch, *, renderer: render.Renderer | Process | Pool | None = None
) -> None:
    """Writes the report, the large render and the exports of a fit into `batch` (params.json is the caller's)."""
    values = outcome.values
    if outputs.report is not None:
        images.write(batch.path(outputs.report), images.srgb_decode(document.report_picture(outcome)))
    if outputs.render is not None:
        from matfit.rendering.engine import Renderer

        large = Renderer(outputs.render_size, outputs.render_spp, renderer.variant if renderer else None)
        images.write(batch.path(outputs.render), large.render(values))
    if outputs.mitsuba_xml is not None or outputs.blender is not None:
        from matfit.rendering import export

        if outputs.mitsuba_xml is not None:
            files.write_text(batch.path(outputs.mitsuba_xml), export.mitsuba_xml(values))
        if outputs.blender is not None:
            files.write_text(batch.path(outputs.blender), export.blender_script(values))
