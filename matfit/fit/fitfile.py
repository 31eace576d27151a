"""Fitting an image file end to end: read the target and mask, fit, verify in Mitsuba, write every output together.

This is what `matfit fit` does, as a library function: `run(request, model)` (a `request.Request`)
reads and checks the inputs, fits (`search.neural_search`), lets Mitsuba choose among the fit's final
candidates (`verify.verify_candidates`, or `verify.correct_then_verify` after rounds of correction; on
by default), and writes params.json, the report, the render and the exports under temporary names,
renaming them into place only once all of them were written. `fit_neural(request, model)` runs the
neural search alone for a request that asks for nothing after it (each frame of `sequence`).
"""

from __future__ import annotations

import functools
import os
import time
from dataclasses import dataclass, field

import numpy as np

from matfit import documents, files, images, params, programs, shipped
from matfit.errors import FitError
from matfit.fit import clean, ranges, refine, search, verify
from matfit.fit.request import Outputs, Request
from matfit.model import models
from matfit.render import engine as render
from matfit.render.process import Background, Pool, Process

# The folder holding the package: the clone, or site-packages when installed (the shipped model reads
# matfit/data/model either way; a user's own paths lie outside it and stay as given).
PROJECT = str(shipped.PACKAGE.parent)
MAX_RENDER_SIZE = 4096


def display_path(path: str) -> str:
    """Returns a path as people should read it in reports: relative to the project when inside it, else as given."""
    absolute = os.path.abspath(path)
    if os.path.commonpath([absolute, PROJECT]) == PROJECT:
        return os.path.relpath(absolute, PROJECT)
    return path


@dataclass
class Outcome:
    """A finished fit of an image file: the answer, how it was found, the target as fitted, the params.json document."""

    result: search.Result
    target: np.ndarray  # sRGB (R, R, 3) at the model's resolution
    unit: np.ndarray  # the answer (unit cube): the fit's best, or what Mitsuba verification preferred
    image: np.ndarray  # phi(answer), sRGB
    neural_rmse: float
    verified: verify.Verified | None = None
    refined: refine.Refined | None = None
    rendered: np.ndarray | None = None  # sRGB Mitsuba render of the answer at the model's resolution
    variant: str | None = None  # the Mitsuba variant that verified, refined or rendered the answer; None: no Mitsuba
    ranges: ranges.Ranges | None = None  # what the picture decides about the fit's answer
    cleaned: clean.Cleaned | None = None  # the clean answer and how it was chosen (`answer="clean"`)
    document: dict = field(default_factory=dict)
    notices: list[str] = field(default_factory=list)

    @property
    def values(self) -> np.ndarray:
        """Returns the answer's physical parameters (19,)."""
        return params.from_unit(self.unit)

    def summary(self, output: str) -> str:
        """Returns one line on what was found and how well."""
        result, document = self.result, self.document
        mitsuba = ""
        if "mitsuba_rmse" in document:  # the answer's one figure, params.json's: that of the stage that chose it
            mitsuba = f", Mitsuba RMSE {document['mitsuba_rmse']:.2f}"
        if self.verified is not None:
            mitsuba += f" (verification kept {self.verified.chosen}; start {self.verified.start_rmse:.2f})"
        if self.refined is not None:
            refined = self.refined
            kept = "kept" if refined.accepted else "not kept"
            mitsuba += (
                f"; refined {refined.steps} steps, {kept} (its acceptance renders: {refined.rmse_before:.2f} -> "
                f"{refined.rmse_after:.2f})"
            )
        if self.cleaned is not None and self.cleaned.dropped:
            cleaned = self.cleaned
            mitsuba += f"; clean answer without {', '.join(cleaned.dropped)}"
            if cleaned.figures:
                mitsuba += (
                    f": Mitsuba {cleaned.figures['clean']:.2f} against {cleaned.figures['best']:.2f} "
                    f"(noise {cleaned.noise:.2f}), {cleaned.chosen} kept"
                )
        line = (
            f"{output}: {document['method']}, {result.evaluations} evaluations, neural RMSE {self.neural_rmse:.2f} "
            f"(start {result.chosen} {result.start_rmse:.2f}){mitsuba}, {document['wall_time_s']:.1f} s"
        )
        if self.ranges is not None:
            line += f"; {self.ranges.summary()}"
        return line


def load_model(path: str) -> models.Model:
    """Returns the model of a directory, with JAX's compilation cache on (a second fit loads its compiled programs)."""
    programs.enable_compilation_cache()
    return models.load_model(path)


def read_target(
    path: str, resolution: int, *, mask: str | None = None
) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """Returns (sRGB target at the model's resolution, mask weights or None, notices) from image files."""
    loaded = images.load(path)
    weights = None if mask is None else read_mask(mask, loaded.pixels.shape[:2], resolution)
    target, notices = search.prepare_target(loaded.pixels, resolution, path)
    return target, weights, [*loaded.notices, *notices]


def run(request: Request, model: models.Model | str, *, renderer: Process | Pool | None = None) -> Outcome:
    """Fits the picture of `request` with a model (or a model directory) and writes its outputs; returns what was found.

    `renderer`: a `process.Pool` (or `Process`) to verify with, started early by the caller (`fit_file`), or None. Every
    input is read and every output path checked before the fit (`Request.check`); the outputs are written
    together at the end (`files.together`), so a failure leaves none of them.
    """
    started = time.perf_counter()
    outputs = request.outputs
    if outputs is None:
        raise ValueError("run writes the request's outputs: name them (Outputs), or call fit_file")
    request.check(model if isinstance(model, str) else model.path)
    outcome, used = _fit_checked(request, model, renderer)
    with files.together() as batch:
        write_outputs(outcome, outputs, batch, renderer=used)
        outcome.document["wall_time_s"] = round(time.perf_counter() - started, 3)
        files.write_text(batch.path(outputs.params), params_text(outcome))
    return outcome


def fit_file(
    request: Request, model: models.Model | str, *, renderer: render.Renderer | Process | Pool | None = None
) -> tuple[Outcome, render.Renderer | Process | Pool | None]:
    """Returns (what a fit of the picture of `request` found, with its params.json document; the renderer used).

    Writes nothing: `run` writes the CLI's files, `serve` offers the same ones for download.
    `renderer`: a loaded `engine.Renderer` at the model's resolution to reuse, a `process.Pool` or `process.Process`
    (started early by the caller; it loads the scene here, and cannot refine), or None (a
    `process.Background` with the request's variant is made when verification, refinement or a render
    output needs one). Refinement differentiates with the renderer's variant.
    """
    request.check(model if isinstance(model, str) else model.path)
    return _fit_checked(request, model, renderer)


def _fit_checked(
    request: Request, model: models.Model | str, renderer: render.Renderer | Process | Pool | None
) -> tuple[Outcome, render.Renderer | Process | Pool | None]:
    """Returns `fit_file`'s answer to a checked request: the search, then Mitsuba's stages, then the document."""
    extra = request.extra_candidates()
    model_path = model if isinstance(model, str) else model.path
    model = load_model(model) if isinstance(model, str) else model
    target, weights, notices = request_target(request, model.resolution)
    background, renderer = start_renderer(request, model.resolution, renderer)
    result = search_stage(request, model, target, weights, extra, background)
    outcome = Outcome(result, target, result.unit, result.image, result.rmse, notices=notices)
    if background is not None:
        renderer = background.renderer()
        notices.extend([renderer.notice] if renderer.notice else [])
    if renderer is not None:
        outcome.variant = renderer.variant
    mitsuba_stages(outcome, request, model, weights, verifier=background or renderer, renderer=renderer)
    decide(outcome, model, model_path, weights, (background or renderer) if request.verified else None, request.answer)
    refinement_stage(outcome, request, model, model_path, weights, renderer)
    outcome.document = document(outcome, request, model_path)
    return outcome, renderer


def start_renderer(
    request: Request, resolution: int, renderer: render.Renderer | Process | Pool | None
) -> tuple[Process | Pool | Background | None, render.Renderer | None]:
    """Returns (a renderer that loads while the fit runs, or None; the loaded renderer given, or None).

    A `process.Pool` or `process.Process` given is loaded here and returned first; with none given, a
    `process.Background` is made when verification, refinement or a render output needs one.
    """
    if isinstance(renderer, (Process, Pool)):
        if request.refine_steps:
            raise ValueError("refinement renders through Mitsuba in this process: give a Renderer, or none")
        renderer.load(resolution, verify.SPP)
        return renderer, None
    if renderer is None and (request.verified or request.refine_steps or request.needs_render):
        return Background(resolution, verify.SPP, request.variant), None
    return None, renderer


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
    return neural_stage(request, model, target, weights=weights, extra=extra)


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


def neural_stage(request: Request, model, target, *, weights, extra, on_start=None) -> search.Result:
    """Returns `search.neural_search`'s result with the request's settings and seed, from `extra` candidates
    (`Request.extra_candidates`) besides the encoders' guesses."""
    return search.neural_search(
        model, target, settings=request.settings, weights=weights, extra=extra, seed=request.seed, on_start=on_start
    )


def search_stage(request: Request, model, target, weights, extra, background) -> search.Result:
    """Returns the search's result (best-of-n, then the request's method); verification's renders of its start
    begin on `background` meanwhile. Raises FitError for a model whose decoded images are not finite."""
    on_start = None
    if background is not None and request.verified:
        on_start = functools.partial(verify.prefetch_start, background, corrections=request.rounds)
    result = neural_stage(request, model, target, weights=weights, extra=extra, on_start=on_start)
    if not np.isfinite(result.rmse):  # the decoder's images hold NaN: no figure and no answer can be trusted
        raise FitError(
            f"the model {model.path} decodes images that are not finite (neural RMSE {result.rmse}): "
            "its weights are damaged; train it again or use another --model"
        )
    return result


def mitsuba_stages(outcome: Outcome, request: Request, model, weights, *, verifier, renderer) -> None:
    """Sets the answer of `outcome` after verification (after the rounds of correction); without verification or
    refinement, the render of the fit's answer when a renderer was made."""
    result, target = outcome.result, outcome.target
    if request.verified:
        outcome.verified = verification_stage(request, model, result, target, weights, verifier)
        outcome.unit, outcome.rendered = outcome.verified.unit, outcome.verified.rendered
        answer_image(outcome, model, weights)
    elif renderer is not None and not request.refine_steps:
        outcome.rendered = images.srgb_encode(renderer.render(result.values, seed=verify.SEED))


def refinement_stage(outcome: Outcome, request: Request, model, model_path: str, weights, renderer) -> None:
    """Refines the answer (verification's, or the clean one) through Mitsuba's differentiable renderer, when asked:
    the last stage, so the answer returned is the one refinement kept, with its own ranges."""
    if not request.refine_steps:
        return
    outcome.refined = refine.refine(
        outcome.unit, outcome.target, steps=request.refine_steps, weights=weights, renderer=renderer
    )
    moved = not np.array_equal(outcome.unit, outcome.refined.unit)
    outcome.unit, outcome.rendered = outcome.refined.unit, outcome.refined.rendered
    answer_image(outcome, model, weights)
    if moved:
        measure_ranges(outcome, model, model_path, weights)


def answer_image(outcome: Outcome, model, weights) -> None:
    """Sets the decoded image and neural RMSE of the answer: one the fit (or verification's rounds) decoded, else
    decoded now."""
    decoded = outcome.result.decoded(outcome.unit)
    verified = outcome.verified
    if decoded is None and verified is not None and np.array_equal(outcome.unit, verified.unit):
        decoded = verified.decoded.get(verified.chosen)
    outcome.image = model.decode(outcome.unit)[0] if decoded is None else decoded
    outcome.neural_rmse = float(images.rmse(outcome.image, outcome.target, weights))


def verification_stage(request: Request, model, result, target, weights, renderer) -> verify.Verified:
    """Returns the candidate Mitsuba keeps: among the fit's, or after the request's rounds of correction."""
    if request.rounds:
        return verify.correct_then_verify(
            renderer, result, target, model=model, corrections=request.rounds, weights=weights
        )
    return verify.verify_candidates(renderer, result, target, weights=weights)


def decide(outcome: Outcome, model: models.Model, model_path: str, weights, renderer, answer: str) -> None:
    """Sets `outcome.ranges` (what the picture decides about the answer, `ranges.py`) and, with `answer="clean"`,
    replaces the answer by the clean one (`clean.py`; judged against it in Mitsuba by `renderer`, if given), whose
    ranges are then measured: the ranges written are always the answer's own."""
    found = measure_ranges(outcome, model, model_path, weights)
    if answer != "clean":
        return
    decoding = ranges.Decoding(model.decoder.module)
    rendered = outcome.verified.renders if outcome.verified is not None else ()  # the answer's batches
    cleaned = clean.clean(
        decoding,
        model.decoder.variables,
        outcome.unit,
        outcome.target,
        weights,
        found,
        renderer,
        rendered=rendered,
    )
    outcome.cleaned = cleaned
    if cleaned.chosen == "clean" and cleaned.dropped:
        outcome.unit = cleaned.unit
        outcome.image = model.decode(cleaned.unit)[0]
        outcome.neural_rmse = float(images.rmse(outcome.image, outcome.target, weights))
        if cleaned.rendered is not None:
            outcome.rendered = cleaned.rendered
        measure_ranges(outcome, model, model_path, weights)  # the re-fitted others may lie outside the best's ranges


def measure_ranges(outcome: Outcome, model: models.Model, model_path: str, weights) -> ranges.Ranges:
    """Sets and returns `outcome.ranges`: what the picture decides about the outcome's answer as it is now."""
    tau, source = ranges.threshold(model_path, outcome.unit)
    decoding = ranges.Decoding(model.decoder.module)
    outcome.ranges = ranges.measure(decoding, model.decoder.variables, outcome.unit, weights, tau, source)
    return outcome.ranges


def params_text(outcome: Outcome) -> str:
    """Returns the params.json of a fit, as written."""
    return documents.dumps(outcome.document)


def answer_section(cleaned: clean.Cleaned) -> dict:
    """Returns params.json's `answer` section: the clean answer, the candidates judged and the fit's own answer."""
    return {
        "kind": "clean",
        "kept": cleaned.chosen,
        "features_off": list(cleaned.dropped),
        "mitsuba_rmse": {name: round(value, 3) for name, value in cleaned.figures.items()},
        "render_noise": round(cleaned.noise, 3) if cleaned.figures else None,  # null: nothing was rendered
        "candidates": {  # nested, the simplest last; margin: standard errors behind the best (null: decided)
            name: {
                "features_off": candidate["off"],
                "decoded_distance": round(candidate["distance"], 3),
                **({"mitsuba_rmse": round(candidate["mitsuba"], 3)} if "mitsuba" in candidate else {}),
                **(
                    {"margin": round(candidate["margin"], 2) if np.isfinite(candidate["margin"]) else None}
                    if "margin" in candidate
                    else {}
                ),
            }
            for name, candidate in cleaned.candidates.items()
        },
        "free_not_neutral": {"best": cleaned.free_before, "answer": cleaned.free_after},
        "best": params.to_mapping(params.from_unit(cleaned.best)),
        "seconds": round(cleaned.seconds, 3),
    }


def document(outcome: Outcome, request: Request, model_path: str) -> dict:
    """Returns the params.json document of a fit: the 19 values with units, and how they were found."""
    result, checked = outcome.result, outcome.verified
    mitsuba = {}
    if checked is not None:
        mitsuba = {
            "mitsuba_rmse": round(checked.rmse, 3),
            "verification": {
                "kept": checked.chosen,
                "mitsuba_rmse": {name: round(value, 3) for name, value in checked.figures.items()},
                "margins": {  # standard errors behind the kept one; null: renders alike in every batch
                    name: round(value, 2) if np.isfinite(value) else None for name, value in checked.margins.items()
                },
                "batches": checked.batches,
                "corrections": checked.corrections,
                "spp": verify.SPP,
                "seconds": round(checked.seconds, 3),
            },
        }
    elif outcome.rendered is not None:
        mitsuba = {"mitsuba_rmse": round(float(images.rmse(outcome.rendered, outcome.target)), 3)}
    if outcome.cleaned is not None:
        cleaned = outcome.cleaned
        if cleaned.figures:
            mitsuba["mitsuba_rmse"] = round(cleaned.figures[cleaned.chosen], 3)
        mitsuba["answer"] = answer_section(cleaned)
    if outcome.refined is not None:
        refined = outcome.refined
        if refined.accepted or "mitsuba_rmse" not in mitsuba:  # else the answer is still the one an earlier stage chose
            mitsuba["mitsuba_rmse"] = round(refined.rmse, 3)  # the kept point's acceptance render
        mitsuba["refinement"] = {
            "steps": refined.steps,
            "kept": refined.accepted,
            "mitsuba_rmse_before": round(refined.rmse_before, 3),
            "mitsuba_rmse_after": round(refined.rmse_after, 3),
            "seconds": round(refined.seconds, 3),
        }
    if outcome.ranges is not None:
        mitsuba["ranges"] = outcome.ranges.document()
    return params.params_document(
        outcome.values,
        method=request.settings.method.value,
        evaluations=result.evaluations,
        neural_rmse=round(outcome.neural_rmse, 3),
        start=result.chosen,
        start_rmse=round(result.start_rmse, 3),
        **mitsuba,
        box=request.settings.box.value,
        polish_steps=request.settings.polish_steps,
        model=display_path(model_path),
        target=request.target,
        target_sha256=request.target_sha256 or files.sha256(request.target),
        mask=request.mask,
        init=request.init,
        mitsuba_variant=outcome.variant,
        fit_seconds=round(result.seconds, 3),
        wall_time_s=0.0,
    )


def report_picture(outcome: Outcome) -> np.ndarray:
    """Returns the report: target | best-of-n start | fit (neural) | fit (Mitsuba render) | difference, as sRGB."""
    from matfit.fit import report

    result = outcome.result
    assert outcome.rendered is not None, "fit_file renders the answer when a report is asked for (needs_render)"
    panels = [
        (outcome.target, "target"),
        (result.start_image, f"best-of-n {result.start_rmse:.2f}"),
        (outcome.image, f"fit (neural) {outcome.neural_rmse:.2f}"),
        (outcome.rendered, f"fit (Mitsuba) {outcome.document['mitsuba_rmse']:.2f}"),
        (report.difference(outcome.rendered, outcome.target), "|Mitsuba - target| x4"),
    ]
    if outcome.ranges is not None:
        found = outcome.ranges
        panel = report.ranges_panel(params.NAMES, outcome.unit, found.low, found.high, found.verdicts)
        panels.append((panel, f"ranges within {found.threshold:.2f}"))
    return report.compose(panels)


def write_outputs(
    outcome: Outcome, outputs: Outputs, batch: files.Batch, *, renderer: render.Renderer | Process | Pool | None = None
) -> None:
    """Writes the report, the large render and the exports of a fit into `batch` (params.json is the caller's)."""
    values = outcome.values
    if outputs.report is not None:
        images.write(batch.path(outputs.report), images.srgb_decode(report_picture(outcome)))
    if outputs.render is not None:
        from matfit.render.engine import Renderer

        large = Renderer(outputs.render_size, outputs.render_spp, renderer.variant if renderer else None)
        images.write(batch.path(outputs.render), large.render(values))
    if outputs.mitsuba_xml is not None or outputs.blender is not None:
        from matfit.render import export

        if outputs.mitsuba_xml is not None:
            files.write_text(batch.path(outputs.mitsuba_xml), export.mitsuba_xml(values))
        if outputs.blender is not None:
            files.write_text(batch.path(outputs.blender), export.blender_script(values))
