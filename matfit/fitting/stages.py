"""The stages of a fit, in order, each a function of what it needs that returns a frozen value: the neural search
(`search.Result`), Mitsuba's verification after rounds of correction (`verify.Verified`), the ranges
(`ranges.Ranges`), the clean answer (`clean.Cleaned`), refinement (`refine.Refined`); each stage that may change
the answer returns the next `Answer`. `fit_stages` runs them for a request whose inputs were read (`fitfile`) and
returns the `Outcome`, with its params.json document (`document.py`); `on_answer` hears each stage's answer as soon
as it exists (`NEURAL`, `VERIFIED`, `CLEAN`, `REFINED`: those the request runs, in that order).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Iterable

import numpy as np

from matfit import images
from matfit.errors import FitError
from matfit.fitting import clean, document, ranges, refine, search, verify
from matfit.fitting.outcome import Answer, Outcome
from matfit.fitting.request import Request
from matfit.model import models
from matfit.rendering import engine as render
from matfit.rendering.engine import Renders
from matfit.rendering.process import Background, Pool, Process

Weights = np.ndarray | None  # the mask's per-pixel weights (R, R) at the model's resolution, or None: every pixel
# The stages whose answers `fit_stages` reports (`Outcome.stage`), in the order they land.
NEURAL, VERIFIED, CLEAN, REFINED = "neural", "verified", "clean", "refined"


def fit_stages(
    request: Request,
    model: models.Model,
    model_path: str,
    target: np.ndarray,
    weights: Weights,
    notices: list[str],
    renderer: render.Renderer | Process | Pool | None,
    on_answer: Callable[[Outcome], None] | None = None,
) -> tuple[Outcome, render.Renderer | Process | Pool | None]:
    """Returns (what the stages found for a checked request's target and mask weights, with its params.json
    document; the renderer used): the search, then Mitsuba's stages, the ranges, the clean answer, refinement.

    `on_answer(outcome)` hears each stage's answer as soon as it exists, with its params.json document as if the fit
    ended there (`Outcome.stage` names the stage): an earlier stage's without the ranges, which are measured only
    once the answer is known (after verification); the last stage's is the outcome returned, heard before it is
    returned (before any output is written). What it raises ends the fit. Nothing is rendered or decoded for it.
    """
    extra = request.extra_candidates()
    last = last_stage(request)

    def landed(outcome: Outcome) -> None:  # an earlier stage's answer: the last one's is heard below, with its ranges
        if on_answer is not None and outcome.stage != last:
            on_answer(dataclasses.replace(outcome, document=document.build(outcome, request, model_path)))

    background, renderer = start_renderer(request, model.resolution, renderer)
    result = search_stage(request, model, target, weights, extra, background)
    notices = list(notices)
    landed(Outcome(result, target, Answer(result.unit, result.image, result.rmse), notices=tuple(notices)))
    if background is not None:
        renderer = background.renderer()
        notices.extend([renderer.notice] if renderer.notice else [])
    variant = renderer.variant if renderer is not None else None
    verifier: Renders | None = background or renderer
    verified = None
    if request.verified:
        assert verifier is not None, "start_renderer gives verification a renderer"
        verified = verification_stage(request, model, result, target, weights, verifier)
    answer = verified_answer(result, verified, model, target, weights)
    if verified is None and renderer is not None and not request.refine_steps:
        answer = dataclasses.replace(
            answer, rendered=images.srgb_encode(renderer.render(result.values, seed=verify.SEED))
        )
    if verified is not None:
        landed(Outcome(result, target, answer, verified, variant=variant, notices=tuple(notices), stage=VERIFIED))
    answer = dataclasses.replace(answer, ranges=ranges_stage(model, model_path, answer.unit, weights))
    cleaned = None
    if request.answer == "clean":
        cleaned = clean_stage(model, answer, target, weights, verifier if request.verified else None, verified)
        answer = clean_answer(answer, cleaned, model, model_path, target, weights)
        landed(Outcome(result, target, answer, verified, cleaned, None, variant, tuple(notices), stage=CLEAN))
    refined = None
    if request.refine_steps:
        assert isinstance(renderer, render.Renderer), "start_renderer gives refinement a Renderer"
        refined = refine.refine(answer.unit, target, steps=request.refine_steps, weights=weights, renderer=renderer)
        answer = refined_answer(answer, refined, result, verified, model, model_path, target, weights)
    outcome = Outcome(result, target, answer, verified, cleaned, refined, variant, tuple(notices), stage=last)
    outcome = dataclasses.replace(outcome, document=document.build(outcome, request, model_path))
    if on_answer is not None:
        on_answer(outcome)
    return outcome, renderer


def last_stage(request: Request) -> str:
    """Returns the last stage a request runs, whose answer is the fit's: refinement, the clean answer, verification
    or the neural search."""
    if request.refine_steps:
        return REFINED
    if request.answer == "clean":
        return CLEAN
    return VERIFIED if request.verified else NEURAL


def neural_outcome(
    request: Request, result: search.Result, target: np.ndarray, model_path: str, notices: Iterable[str] = ()
) -> Outcome:
    """Returns the `Outcome`, with its document, of a request that ran the neural search alone (`fitfile.fit_neural`:
    a sequence's frame)."""
    outcome = Outcome(result, target, Answer(result.unit, result.image, result.rmse), notices=tuple(notices))
    return dataclasses.replace(outcome, document=document.build(outcome, request, model_path))


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


def neural_stage(
    request: Request,
    model: models.Model,
    target: np.ndarray,
    *,
    weights: Weights,
    extra: np.ndarray | None,
    on_start: Callable[[np.ndarray], None] | None = None,
) -> search.Result:
    """Returns `search.neural_search`'s result with the request's settings and seed, from `extra` candidates
    (`Request.extra_candidates`) besides the encoders' guesses."""
    return search.neural_search(
        model, target, settings=request.settings, weights=weights, extra=extra, seed=request.seed, on_start=on_start
    )


def search_stage(
    request: Request,
    model: models.Model,
    target: np.ndarray,
    weights: Weights,
    extra: np.ndarray | None,
    background: Renders | None,
) -> search.Result:
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


def verification_stage(
    request: Request,
    model: models.Model,
    result: search.Result,
    target: np.ndarray,
    weights: Weights,
    renderer: Renders,
) -> verify.Verified:
    """Returns the candidate Mitsuba keeps: among the fit's, or after the request's rounds of correction."""
    if request.rounds:
        return verify.correct_then_verify(
            renderer, result, target, model=model, corrections=request.rounds, weights=weights
        )
    return verify.verify_candidates(renderer, result, target, weights=weights)


def verified_answer(
    result: search.Result, verified: verify.Verified | None, model: models.Model, target: np.ndarray, weights: Weights
) -> Answer:
    """Returns the answer after the search and verification: the candidate verification kept, with its mean render,
    or the search's best without verification (unrendered)."""
    if verified is None:
        return Answer(result.unit, result.image, result.rmse)
    image, error = decoded_answer(verified.unit, result, verified, model, target, weights)
    return Answer(verified.unit, image, error, verified.rendered)


def decoded_answer(
    unit: np.ndarray,
    result: search.Result,
    verified: verify.Verified | None,
    model: models.Model,
    target: np.ndarray,
    weights: Weights,
) -> tuple[np.ndarray, float]:
    """Returns (phi(unit), its neural RMSE against the target): a picture the fit (or verification's rounds) decoded,
    else decoded now."""
    decoded = result.decoded(unit)
    if decoded is None and verified is not None and np.array_equal(unit, verified.unit):
        decoded = verified.decoded.get(verified.chosen)
    image = model.decode(unit)[0] if decoded is None else decoded
    return image, float(images.rmse(image, target, weights))


def ranges_stage(model: models.Model, model_path: str, unit: np.ndarray, weights: Weights) -> ranges.Ranges:
    """Returns what the picture decides about the answer `unit` (`ranges.measure`, with the model's threshold)."""
    tau, source = ranges.threshold(model_path, unit)
    decoding = ranges.Decoding(model.decoder.module)
    return ranges.measure(decoding, model.decoder.variables, unit, weights, tau, source)


def clean_stage(
    model: models.Model,
    answer: Answer,
    target: np.ndarray,
    weights: Weights,
    renderer: Renders | None,
    verified: verify.Verified | None,
) -> clean.Cleaned:
    """Returns the clean answer of `answer` (`clean.py`), judged against it in Mitsuba by `renderer` (None: not
    judged), verification's batches of it reused."""
    assert answer.ranges is not None, "the clean answer starts from the answer's ranges"
    rendered = verified.renders if verified is not None else ()  # the answer's batches
    decoding = ranges.Decoding(model.decoder.module)
    return clean.clean(
        decoding, model.decoder.variables, answer.unit, target, weights, answer.ranges, renderer, rendered=rendered
    )


def clean_answer(
    answer: Answer, cleaned: clean.Cleaned, model: models.Model, model_path: str, target: np.ndarray, weights: Weights
) -> Answer:
    """Returns the answer after the clean answer's judgement: the clean one, if kept, with its own picture, render and
    ranges (the re-fitted others may lie outside the best's ranges); else `answer`."""
    if cleaned.chosen != "clean" or not cleaned.dropped:
        return answer
    image = model.decode(cleaned.unit)[0]
    rendered = cleaned.rendered if cleaned.rendered is not None else answer.rendered
    return Answer(
        cleaned.unit,
        image,
        float(images.rmse(image, target, weights)),
        rendered,
        ranges_stage(model, model_path, cleaned.unit, weights),
    )


def refined_answer(
    answer: Answer,
    refined: refine.Refined,
    result: search.Result,
    verified: verify.Verified | None,
    model: models.Model,
    model_path: str,
    target: np.ndarray,
    weights: Weights,
) -> Answer:
    """Returns the answer after refinement (the last stage): the point it kept, with that point's acceptance render,
    picture and (when it moved) its own ranges."""
    image, error = decoded_answer(refined.unit, result, verified, model, target, weights)
    moved = not np.array_equal(answer.unit, refined.unit)
    found = ranges_stage(model, model_path, refined.unit, weights) if moved else answer.ranges
    return Answer(refined.unit, image, error, refined.rendered, found)
