"""Fitting a sequence of frames with the neural search alone, each from the previous frame's answer:
`fit_sequence` (`matfit sequence`)."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, cast

import numpy as np

from matfit import documents, params
from matfit.api import requests, scenes
from matfit.api.arguments import MAX_SIZE, Picture, callback, flag, path_of, path_text, shown, whole
from matfit.api.choices import check_choices
from matfit.api.fitter import Fitter
from matfit.api.material import Material
from matfit.api.results import Fit, fit_of
from matfit.api.scenes import Scene
from matfit.errors import FitError, ImageError, OutputError, RenderError
from matfit.fitting.methods import Method, Settings

if TYPE_CHECKING:
    from matfit.fitting import search
    from matfit.model.models import Model


def fit_sequence(
    frames: Iterable[Picture] | str | os.PathLike[str],
    *,
    model: str | os.PathLike[str] | Model | None = None,
    settings: Settings | None = None,
    reinit: bool = True,
    init: str | os.PathLike[str] | Material | None = None,
    linear: bool = False,
    out: str | os.PathLike[str] | None = None,
    render: tuple[int, int] | None = None,
    progress: Callable[[int, int, float], None] | None = None,
    scene: Scene | None = None,
    refine: int = 0,
    variant: str | None = None,
    step_progress: Callable[[str, int, int, float], None] | None = None,
    mask: Picture | None = None,
) -> list[Fit]:
    """Returns the fits of a sequence of frames in order: `matfit sequence`'s.

    Each frame is fitted by the neural search alone (no Mitsuba stage), from the encoders' guesses plus, with
    `reinit`, the previous frame's answer (the first frame: `init`'s). `settings` None: `matfit sequence`'s
    (hybrid, 100 evaluations). `frames`: pictures (paths or arrays), written nowhere; or, with `out`, the folder
    of the frames (in natural order: frame_2 before frame_10), which `matfit sequence FRAMES -o OUT` fits: each
    frame's result written at once to `OUT/<frame>.json` (its `Fit.to_json()`), then summary.md and preview.png,
    and with `render=(size, spp)` each frame's Mitsuba render `OUT/<frame>-render.png`. Every output is checked
    before the first fit, and the same call again resumes: frames whose results are there, for the same frames,
    settings and model, are read back, not fitted again. `progress(frames done, frames in all, frames a second)`
    hears of each frame (with `out`).

    `scene`: the frames are renders of that scene of your own, edited, and each frame's shape is fitted there
    (`fit(..., scene=)`'s fit, `refine` steps, 0: its default), from the previous frame's answer with `reinit`;
    `step_progress(stage, step, steps, RMSE)` hears of each fit's steps; `mask` (of the frames' size) weights every
    frame's fit; with `out`, each frame's params.json is the scene fit's, and `render` renders the scene
    (docs/scenes.md#a-sequence-of-frames). `settings` are the test scene's search, and `refine`, `variant`,
    `step_progress` and `mask` a scene's fit: each only where it applies.
    """
    reinit, linear = flag("reinit", reinit, FitError), flag("linear", linear, ImageError)
    progress = callback("progress", progress, FitError)
    step_progress = callback("step_progress", step_progress, FitError)
    check_choices(settings, init)
    if scene is not None:
        return scene_sequence(
            frames,
            scene,
            settings,
            model,
            reinit,
            init,
            linear,
            out,
            render,
            progress,
            refine,
            variant,
            step_progress,
            mask,
        )
    for name, value, given in (
        ("refine", refine, refine != 0),
        ("variant", variant, variant is not None),
        ("step_progress", step_progress, step_progress is not None),
        ("mask", mask, mask is not None),
    ):
        if given:
            raise FitError(
                f"{name} {shown(value)} is for the frames of a scene of your own: give the scene too, or leave it out",
                field=name,
            )
    settings = settings or Settings(Method.hybrid, 100)
    check_written(frames, out, render, progress, linear)
    if out is not None:
        return written_sequence(frames, model, settings, reinit, init, out, render, progress)
    from matfit.fitting import fitfile, stages

    fitter = Fitter(model, verify=False)
    start = None if init is None else (init if isinstance(init, Material) else Material.read(init)).unit()
    previous = None if start is None else np.asarray(start, np.float32)
    fits: list[Fit] = []
    for frame in cast(Iterable[Picture], frames):  # a list: `check_written`
        request, notices = requests.request_of(
            fitter, fitter.variant, frame, None, None, settings, linear, False, None, "best", 0, 0
        )
        if request.pixels is None:  # a file: read as `matfit sequence` reads a frame
            pixels, _, _ = fitfile.request_target(request, fitter.model.resolution)
            request = dataclasses.replace(request, pixels=pixels)
        candidates = None if previous is None else previous[None]
        request = dataclasses.replace(request, candidates=candidates)
        result: search.Result = fitfile.fit_neural(request, fitter.model)
        outcome = stages.neural_outcome(request, result, np.asarray(request.pixels), fitter.model.path, notices)
        fits.append(fit_of(outcome, request.target))
        previous = np.asarray(result.unit, np.float32) if reinit else None
    return fits


def scene_sequence(
    frames: object,
    scene: Scene,
    settings: Settings | None,
    model: str | os.PathLike[str] | Model | None,
    reinit: bool,
    init: str | os.PathLike[str] | Material | None,
    linear: bool,
    out: str | os.PathLike[str] | None,
    render: tuple[int, int] | None,
    progress: Callable[[int, int, float], None] | None,
    refine: int,
    variant: str | None,
    step_progress: Callable[[str, int, int, float], None] | None,
    mask: Picture | None,
) -> list[Fit]:
    """Returns `fit_sequence`'s fits of a scene's frames (`scene_sequences.fit_scene_sequence`), its arguments
    checked as for the test scene's."""
    from matfit.api import scene_sequences

    scene = scenes.check_scene(scene)
    if settings is not None:
        raise FitError(
            "settings= are the test scene's search; a scene's frames are fitted by Mitsuba's descent: leave settings "
            "out (refine= sets its steps)",
            field="settings",
        )
    check_written(frames, out, render, progress, linear)
    written = None if out is None else path_of("out", out, OutputError, "give the folder to write into")
    fitter = Fitter(model, verify=False, variant=variant)
    return scene_sequences.fit_scene_sequence(
        frames,
        scene,
        init=init,
        reinit=reinit,
        linear=linear,
        out=written,
        render=None if render is None else render_settings(render),
        refine=refine,
        variant=fitter.variant,
        model=fitter,
        model_path=fitter.model_path,
        progress=progress,
        step_progress=step_progress,
        mask=mask,
    )


def check_written(
    frames: object,
    out: str | os.PathLike[str] | None,
    render: tuple[int, int] | None,
    progress: Callable[[int, int, float], None] | None,
    linear: bool,
) -> None:
    """Raises the one-line error of `fit_sequence`'s arguments that a sequence written to a folder (`out`) needs or a
    list of frames does not take (the frames: a list without `out`, a folder with it), the test scene's and a
    scene's alike."""
    if out is None and (isinstance(frames, str | os.PathLike) or render is not None or progress is not None):
        raise FitError(
            "a folder of frames, render= and progress= are for a sequence written to a folder: give out= too, or "
            "give the frames as a list",
            field="out",
        )
    if out is None and not isinstance(frames, Iterable):
        raise FitError(
            f"frames {shown(frames)} is no list of pictures: give the frames' paths or arrays, or their folder with "
            "out=",
            field="frames",
        )
    if out is not None and not isinstance(frames, str | os.PathLike):
        raise FitError(
            f"frames {shown(frames)} is no folder: with out=, give the folder that holds the frames", field="frames"
        )
    if out is not None and linear:
        raise ImageError(
            "linear=True describes arrays; frame files say how they are encoded: leave it out", field="linear"
        )


def render_settings(render: object) -> tuple[int, int]:
    """Returns `render=` (size, spp) checked: a pair of whole numbers in range."""
    from matfit.model import dataset

    if not isinstance(render, tuple) or len(render) != 2:
        raise RenderError(f"render {shown(render)} is not (size, spp): give render=(256, 64)", field="render")
    return (
        whole("size", render[0], dataset.MIN_RESOLUTION, MAX_SIZE, RenderError),
        whole("spp", render[1], 1, dataset.MAX_SPP, RenderError),
    )


def written_sequence(
    frames: object,
    model: str | os.PathLike[str] | Model | None,
    settings: Settings,
    reinit: bool,
    init: str | os.PathLike[str] | Material | None,
    out: str | os.PathLike[str],
    render: tuple[int, int] | None,
    progress: Callable[[int, int, float], None] | None,
) -> list[Fit]:
    """Returns `fit_sequence`'s fits of a folder of frames written into `out` (`fitting/sequence.run`)."""
    from matfit.fitting import sequence

    written = path_of("out", out, OutputError, "give the folder to write into")
    rendered = None if render is None else render_settings(render)
    fitter = Fitter(model, verify=False)
    frames_found = sequence.run(
        fitter,
        os.fspath(cast(str, frames)),  # a folder: `check_written`
        out=written,
        settings=settings,
        reinit=reinit,
        render=rendered,
        progress=progress,
        init=path_text(init) if isinstance(init, str | os.PathLike) else None,
        init_values=init.array() if isinstance(init, Material) else None,
    )
    fits = []
    for frame in frames_found:
        path = sequence.frame_json_path(written, frame.path)
        document = documents.read(path, "delete it to fit that frame again", FitError)
        image = frame.image if frame.image is not None else fitter.model.decode(np.asarray(frame.unit)[None])[0]
        summary = (
            f"{path}: {settings.method.value}, {frame.evaluations} evaluations, neural RMSE {frame.rmse:.2f} "
            f"(start {frame.start} {frame.start_rmse:.2f}), {frame.seconds:.1f} s"
        )
        fits.append(
            Fit(
                Material.from_array(params.from_unit(np.asarray(frame.unit, np.float64))),
                float(frame.rmse),
                None,
                {},
                {},
                {},
                (frame.note,) if frame.note else (),
                summary,
                np.asarray(frame.target, np.float32),
                np.asarray(image, np.float32),
                None,
                document,
                frame.start,
                float(frame.start_rmse),
                int(frame.evaluations),
                stage="neural",  # a frame's answer is the neural search's
            )
        )
    return fits
