"""The stages of a fit, in order: the neural search, Mitsuba's verification (after rounds of correction), the
ranges, the clean answer, refinement; then the params.json document (`document.py`).

`fit_stages` runs them for a request whose inputs were read (`fitfile`): each stage takes what it needs and
sets the answer of an `Outcome`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from matfit import images, params
from matfit.errors import FitError
from matfit.fit import clean, document, ranges, refine, search, verify
from matfit.fit.request import Request
from matfit.model import models
from matfit.render import engine as render
from matfit.render.process import Background, Pool, Process


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


def fit_stages(
    request: Request,
    model: models.Model,
    model_path: str,
    target: np.ndarray,
    weights: np.ndarray | None,
    notices: list[str],
    renderer: render.Renderer | Process | Pool | None,
) -> tuple[Outcome, render.Renderer | Process | Pool | None]:
    """Returns (what the stages found for a checked request's target and mask weights, with its params.json
    document; the renderer used): the search, then Mitsuba's stages, then the document."""
    extra = request.extra_candidates()
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
    outcome.document = document.build(outcome, request, model_path)
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
