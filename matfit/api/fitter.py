"""Fitting pictures: `Fitter` (the model and the render processes loaded once, for many fits), `fit` (one picture
with a fitter of its own) and `load_model`."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Literal

import numpy as np

from matfit import params, shipped
from matfit.api import requests, scene_fits, scenes
from matfit.api.arguments import (
    Image,
    Picture,
    callback,
    flag,
    path_of,
    path_text,
    picture_paths,
    shown,
    whole,
)
from matfit.api.choices import check_choices, check_options
from matfit.api.material import Material
from matfit.api.results import Fit, Outputs, fit_of, landed
from matfit.api.scenes import Scene
from matfit.errors import FitError, ImageError, MatfitError, OutputError, ParameterError, RenderError, WeightsError
from matfit.fitting.methods import Settings

if TYPE_CHECKING:
    from matfit.fitting.request import Request
    from matfit.model.models import Model
    from matfit.rendering.process import Pool


def load_model(path: str | os.PathLike[str] | None = None) -> Model:
    """Returns the decoder and encoders of a model folder (None: the shipped model), for `Fitter` or `fit`."""
    from matfit.fitting import fitfile

    if path is not None and not isinstance(path, str | os.PathLike):
        raise WeightsError(
            f"model {shown(path)} is no model folder: give a folder's path, load_model()'s model, or None for the "
            "shipped one",
            field="model",
        )
    return fitfile.load_model(str(shipped.MODEL) if path is None else os.fspath(path))


class Fitter:
    """The model and the render processes loaded once, for many fits (the warm path); a context manager.

    `model`: a model folder (None: the shipped model) or a loaded `load_model()`. A folder's model loads at the first
    fit, once that fit's inputs and outputs were checked (a bad picture is refused without loading anything), or at
    the first use of `fitter.model`. `verify`: whether fits let Mitsuba choose among their candidates by default; the
    render processes (one a core) start here when it does, so that Mitsuba loads in them while the model loads here.
    A fit that fails keeps them while every one runs (the picture was at fault); one that lost a render process (it
    ended, or gave no reply in the time its render may take: `process.reply_seconds`) or was interrupted while it
    talked to one (a KeyboardInterrupt) ends them, and the next fit starts new ones. `close()` (or leaving the `with`
    block) ends them.

    A fitter may be shared between threads: its fits, renders and `close` take one lock, so they queue and run one at
    a time (the render processes answer one fit's requests in order; the model is loaded once). Fits side by side
    need a fitter each.
    """

    def __init__(
        self, model: str | os.PathLike[str] | Model | None = None, *, verify: bool = True, variant: str | None = None
    ) -> None:
        from matfit.rendering import engine

        engine.check_request(variant)
        verify = flag("verify", verify, FitError)
        if model is not None and not isinstance(model, str | os.PathLike):
            from matfit.model import models  # a loaded model's module is imported already

            if not isinstance(model, models.Model):
                raise WeightsError(
                    f"model {shown(model)} is no model folder: give a folder's path, load_model()'s model, or None "
                    "for the shipped one",
                    field="model",
                )
        self.variant = variant
        self.verify = verify
        self._lock = threading.RLock()  # held by each fit, render and close: they queue
        self._pool: Pool | None = None
        self._model: Model | None = None
        if model is None:
            self.model_path = str(shipped.MODEL)
        elif isinstance(model, str | os.PathLike):
            self.model_path = os.fspath(model)
        else:
            self._model, self.model_path = model, model.path
        if verify:
            self._renderer()  # Mitsuba starts in the children while JAX and the model load here

    @property
    def model(self) -> Model:
        """The model the fits use (`load_model(model_path)`, loaded at the first use)."""
        with self._lock:
            if self._model is None:
                self._model = load_model(self.model_path)
            return self._model

    def _renderer(self) -> Pool:
        with self._lock:
            if self._pool is None:
                from matfit.rendering.process import Pool

                self._pool = Pool(self.variant)
            return self._pool

    @contextlib.contextmanager
    def _turn(self) -> Iterator[None]:
        """Holds the fitter's lock for one fit or render; one that ends with a render process lost, stuck or left
        part-way through a message (an interrupt) ends the render processes, and the next starts new ones."""
        with self._lock:
            try:
                yield
            except BaseException:
                if self._pool is not None and not self._pool.healthy():
                    self.close()
                raise

    def close(self) -> None:
        """Ends the render processes; a later verified fit starts new ones."""
        with self._lock:
            if self._pool is not None:
                self._pool.close()
                self._pool = None

    def __enter__(self) -> Fitter:
        return self

    def __exit__(self, *exception: object) -> None:
        self.close()

    def render(self, material: Material, *, seed: int = 0, spp: int = 64) -> Image:
        """Returns the linear float32 (R, R, 3) render of a material at the model's resolution R on this fitter's
        render processes (those that verify its fits: started here if not yet), bit-identical whatever their count."""
        from matfit.fitting import verify
        from matfit.model import dataset

        if not isinstance(material, Material):
            raise ParameterError(f"material {shown(material)} is no matfit.Material: give one", field="material")
        seed = whole("seed", seed, 0, params.MAX_SEED, RenderError)
        spp = whole("spp", spp, 1, dataset.MAX_SPP, RenderError)
        with self._turn():
            pool = self._renderer()
            pool.load(self.model.resolution, verify.SPP)
            return np.asarray(pool.render(material.array(), seed=seed, spp=spp), np.float32)

    def fit(
        self,
        picture: Picture,
        *,
        mask: Picture | None = None,
        init: str | os.PathLike[str] | Material | None = None,
        settings: Settings | None = None,
        linear: bool = False,
        verify: bool | None = None,
        corrections: int | None = None,
        answer: Literal["clean", "best"] = "clean",
        refine: int = 0,
        seed: int = 0,
        outputs: Outputs | None = None,
        scene: Scene | None = None,
        progress: Callable[[str, int, int, float], None] | None = None,
        answers: Callable[[Fit], None] | None = None,
    ) -> Fit:
        """Returns the fit of one picture with this fitter's model: `matfit.fit`, warm. `outputs`: the files to write
        (checked before any work, written together at the end: what `matfit fit` writes), or None to write nothing.
        `scene`: fit the material of a shape in a scene of your own instead (`matfit.fit`'s). `answers`: hears each
        stage's answer as soon as it exists (`matfit.fit`'s)."""
        callback("answers", answers, FitError)
        if scene is not None:
            verified = self.verify if verify is None else verify  # not used: checked as the other fits check it
            linear, _, _, refine, _ = check_options(linear, verified, corrections, answer, refine, seed)
            callback("progress", progress, FitError)
            if answers is not None:
                raise FitError(
                    "answers hears the stages of a fit in the test scene; a scene fit reports its steps to progress: "
                    "leave answers out",
                    field="answers",
                )
            return scene_fits.fit_scene(
                picture, scene, mask, init, linear, refine, outputs, self.variant, progress, self
            )
        from matfit.fitting import fitfile  # noqa: F401  # JAX imported before the fit's wall time starts

        started = time.perf_counter()
        verified = self.verify if verify is None else verify
        request, notices = requests.request_of(
            self,
            self.variant,
            picture,
            mask,
            init,
            settings,
            linear,
            verified,
            corrections,
            answer,
            refine,
            seed,
            outputs,
        )
        return self._fit_request(request, notices, started, answers=answers)

    def fit_all(
        self,
        pictures: Iterable[str | os.PathLike[str]],
        folder: str | os.PathLike[str],
        *,
        mask: str | os.PathLike[str] | None = None,
        init: str | os.PathLike[str] | Material | None = None,
        settings: Settings | None = None,
        verify: bool | None = None,
        corrections: int | None = None,
        answer: Literal["clean", "best"] = "clean",
        refine: int = 0,
        seed: int = 0,
        outputs: Outputs | None = None,
        scene: Scene | None = None,
        progress: Callable[[str, int, int, float], None] | None = None,
        done: Callable[[str, str, Fit | MatfitError | None], None] | None = None,
    ) -> int:
        """Fits picture files into `folder`, resumably: `matfit fit a.png b.png -o folder/`. Returns how many failed.

        Each picture writes `<folder>/<stem>.params.json` and the other files `outputs` names (`Outputs`), every
        path checked before the first fit (two pictures of one name are refused). A picture that cannot be fitted
        (a MatfitError: unreadable, a mask of another size) is handed to `done` and the others go on. Stopped part
        way (Ctrl-C, kill -9), the same call again keeps the pictures fitted already (unchanged, their files there,
        the same settings and model) and fits the rest; once all are fitted, the folder's journal of them is
        removed. `done(picture, its params.json, the Fit, its MatfitError, or None for one kept)` hears of each.
        `scene`: each picture is a render of that scene of your own, its shape's material fitted there (`fit`'s),
        `progress` hearing of each fit's steps; a changed scene file, mesh or image fits every picture again.
        """
        from matfit.fitting import batch

        callback("done", done, FitError)
        callback("progress", progress, FitError)
        read = None if scene is None else scenes.check_scene(scene).read()  # a scene that fails, before any fit
        targets = [path_text(picture) for picture in picture_paths(pictures)]
        into = path_of("output", folder, OutputError, "give the folder to write into", name="folder")
        if not targets:
            raise FitError("fit_all was given no pictures: give a list of picture files", field="target")
        if mask is not None:
            path_of("mask", mask, ImageError, "give a picture file's path or None")
        check_choices(settings, init, outputs)  # outputs before they are read
        verified = self.verify if verify is None else verify
        template = dataclasses.replace(outputs or Outputs(), params=os.path.join(into, "params.json"))
        request, _ = requests.request_of(
            self,
            self.variant,
            targets[0],
            mask,
            init,
            settings,
            False,
            verified,
            corrections,
            answer,
            refine,
            seed,
            template,
        )

        def then() -> None:  # after the checks (a folder that is no model is said before any fit, and leaves no folder)
            if read is None:
                self.model  # noqa: B018  # loaded: a fit in the test scene needs it
            else:  # a scene fit loads the model only for a shape whose material it cannot read (`scene_fits.fit_scene`)
                scenes.check_several(read, targets, into, request)

        planned = batch.plan(targets, into, request, then=then)

        def fit_one(request: Request, written: Callable[[str], None]) -> Fit:
            if scene is None:
                return self._fit_request(request, [], time.perf_counter(), written)
            fitted = scene_fits.fit_scene(
                request.target,
                scene,
                mask,
                init,
                False,
                request.refine_steps,
                request.outputs,
                self.variant,
                progress,
                self,
            )
            written(fitted.document["target_sha256"])
            return fitted

        def heard(request: Request, result: Fit | MatfitError | None) -> None:
            if done is not None:
                done(request.target, request.outputs.params if request.outputs else into, result)

        identity = None if read is None else scenes.identity(read)
        return batch.fit_all(planned, self.model_path, fit_one, done=heard, scene=identity)

    def _fit_request(
        self,
        request: Request,
        notices: list[str],
        started: float,
        written: Callable[[str], None] | None = None,
        answers: Callable[[Fit], None] | None = None,
    ) -> Fit:
        """Returns the fit of a request made by `_request`: checked before the model loads, its outputs written, then
        `written(the SHA-256 of the picture fitted)` called (`fit_all`'s journal). `answers(fit)` hears each stage's
        answer as it lands, its params.json's wall time the seconds since `started` then."""
        from matfit.fitting import fitfile

        name = request.outputs.params if request.outputs else request.target
        on_answer = None if answers is None else lambda outcome: answers(landed(outcome, name, notices, started))
        with self._turn():  # fitfile checks the request, then asks for the model (a folder's loads at the first fit)
            renderer = self._renderer() if request.verified and not request.refine_steps else None  # refinement: here
            if request.outputs is None:
                outcome, _ = fitfile.fit_file(request, self, renderer=renderer, on_answer=on_answer)
                outcome.document["wall_time_s"] = round(time.perf_counter() - started, 3)
            else:
                outcome = fitfile.run(request, self, renderer=renderer, started=started, on_answer=on_answer)
                if written is not None:
                    written(str(outcome.document["target_sha256"]))
        outcome = dataclasses.replace(outcome, notices=(*notices, *outcome.notices))
        return fit_of(outcome, name)


def fit(
    picture: Picture,
    *,
    mask: Picture | None = None,
    init: str | os.PathLike[str] | Material | None = None,
    model: str | os.PathLike[str] | Model | None = None,
    settings: Settings | None = None,
    linear: bool = False,
    verify: bool = True,
    corrections: int | None = None,
    answer: Literal["clean", "best"] = "clean",
    refine: int = 0,
    seed: int = 0,
    variant: str | None = None,
    outputs: Outputs | None = None,
    scene: Scene | None = None,
    progress: Callable[[str, int, int, float], None] | None = None,
    answers: Callable[[Fit], None] | None = None,
) -> Fit:
    """Returns the fit of the material whose render looks most like `picture`: what `matfit fit` finds.

    `picture`: a file's path (PNG, JPEG, TIFF, EXR) or its pixels, an (H, W, 3) array (or (H, W, 4), alpha
    dropped): float sRGB in 0-1, uint8 0-255 or uint16, or linear float with `linear=True`. `mask`: the same
    kinds, white where the fit looks. `init`: a params.json or a `Material` that joins the candidates.
    `model`: a model folder or `load_model()`'s (None: the shipped one). `settings`, `verify`, `corrections`,
    `answer`, `refine`, `seed`, `variant`: `matfit fit`'s options of those names, with its defaults. A picture
    file gives the parameters of `matfit fit PICTURE -o params.json` bit for bit. `outputs`: the files to write
    (`Outputs`: checked before any work, written together once the fit is done), or None to write nothing. For many
    pictures, a `Fitter` loads the model once.

    `answers(fit)` hears each stage's answer as soon as it exists, a `Fit` whose `stage` names it: the neural search's
    ("neural": no Mitsuba render yet, `rendered` and `mitsuba_rmse` None), Mitsuba's after verification
    ("verified", without `ranges`: they are measured on the answer known), then the clean one ("clean") and the
    refined one ("refined") where the fit runs those stages; the last is the answer returned, heard before any
    output is written. Its params.json (`document`) is the fit's as if it ended there, its `wall_time_s` the
    seconds since the call. What `answers` raises ends the fit: nothing is written and no render process is left
    (a `Fitter` keeps its own for the next fit).

    `scene`: a `Scene` of your own (a Mitsuba XML file and a shape's id): the picture is a render of that scene,
    edited, and the shape's material is fitted there by Mitsuba's differentiable renderer (docs/scenes.md); `init`
    is the material to start from (None: the shape's own where matfit reads it, else the test scene's guess of the
    shape's pixels), `mask` where to look (None: the pixels the shape changes), `progress(stage, step, steps, loss)`
    hears of each step, `refine` sets its steps (0: its default); `settings`, `verify`, `corrections`, `answer` and
    `seed` are the test scene's and are not used. `Fit.neural_rmse` is NaN.
    """
    _, verify, _, refine, _ = check_options(linear, verify, corrections, answer, refine, seed)  # before any start
    with Fitter(model, verify=verify and not refine and scene is None, variant=variant) as fitter:
        return fitter.fit(
            picture,
            mask=mask,
            init=init,
            settings=settings,
            linear=linear,
            verify=verify,
            corrections=corrections,
            answer=answer,
            refine=refine,
            seed=seed,
            outputs=outputs,
            scene=scene,
            progress=progress,
            answers=answers,
        )
