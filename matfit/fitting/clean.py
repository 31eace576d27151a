"""The clean answer: the simplest material that Mitsuba cannot tell apart from the fit's answer, or the answer.

Simplest means: the shader's optional features (`params.FEATURES`: anisotropy, sheen, clearcoat,
the interior medium, transmission) turned off unless the picture decides them
(docs/fitting.md#what-the-picture-decides).

Candidates (`candidates`). A feature is tried when its leading parameter is not decided
(`ranges.Ranges.verdicts`) and it is not already off. Turned off alone (its parameters at their
neutral values), the other parameters are re-fitted by STEPS Gauss-Newton steps, each linearised
afresh at the current point (a Jacobian and a decode), the box respected, each step the best of
a full, a half and a quarter step (a step that does not lower the error is not taken). They are
re-fitted to the answer's own decoded picture, not to the target: the answer is Mitsuba's choice,
corrected for the decoder's error (`correct.py`), and a re-fit to the target would undo that
correction; the distance to the answer's picture (D, RMSE on 0-255 sRGB) is what the decoder
predicts of the Mitsuba difference between the two. The features whose re-fit keeps D within
CLOSE (and within the ranges' tau) are then turned off together in order of their D, smallest
first, re-fitting after each; every prefix that still decodes within CLOSE is a candidate, so the
candidates are nested, the last the simplest. Without transmission (spec_trans at 0) no light
reaches the medium inside the object and the renderer does not show it: the medium is then turned
off first, without a re-fit, and the answer's picture is decoded without it.

Judgement (`judge`), like every answer: the answer and the candidates are rendered with
verification's seeds and samples (common random numbers) and compared by its estimates
(`verify.decide` of each candidate against the answer), over verify.BATCHES batches each, the
simplest first. A candidate that the answer does not beat is returned: verification's rule, so
the clean answer is never measurably worse. A candidate the answer beats by verify.LEAD standard
errors or more is refused, and the next less simple one is rendered only then. A candidate behind
the answer, though not by LEAD standard errors, is undecided: the judgement ends there with the
answer itself, and no less simple candidate is rendered.

Why one look, and why undecided keeps the answer. The candidates re-fit the answer's own decoded
picture within CLOSE, so the difference Mitsuba sees between them and the answer is small: an
undecided candidate used to get batches up to verify.MAX_BATCHES, and the renders of
desaturated.png's judgement were two thirds of its fit, to tell differences of a few hundredths
of RMSE. Ending with the answer costs no quality: it is verification's choice, and on the judged
sets the answers that changed were judged no worse (docs/fitting.md#the-judged-sets-and-the-samples-a-fit-renders); the
less simple candidates lie between the undecided one and the answer, so they would be less
decidable still. The answer's batches are verification's own, not rendered again: at most
len(FEATURES) * verify.BATCHES renders, verify.BATCHES where the simplest is plainly kept.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from matfit import images, params, programs
from matfit.fitting import ranges, verify

if TYPE_CHECKING:
    from jaxtyping import PyTree

    from matfit.fitting.ranges import Decode
    from matfit.rendering.engine import Renders

STEPS = 3  # re-linearised Gauss-Newton steps (a Jacobian and one batched decode each) re-fitting the others
CLOSE = 0.5  # RMSE (0-255 sRGB): how far a candidate may decode from the answer's picture (docs/fitting.md)
SHARES = (1.0, 0.5, 0.25)  # of the Gauss-Newton step, tried at once; the best taken if it lowers the error
ALIKE = 1e-5  # relative difference of two estimates that is rounding (two renders of one material), no deficit
NEUTRAL_TOLERANCE = 0.01  # of a parameter's range: a value this close to its neutral one counts as neutral


@dataclass(frozen=True)
class Cleaned:
    """The clean answer and how it was chosen."""

    unit: np.ndarray  # the answer returned (unit cube): the clean one, or the fit's when Mitsuba preferred it
    simplest: np.ndarray  # the simplest candidate (unit cube)
    best: np.ndarray  # the fit's own answer it started from (unit cube)
    dropped: tuple[str, ...]  # the features off in the clean answer returned (in the simplest, if none was kept)
    chosen: str  # "clean" or "best"
    figures: dict[str, float] = field(default_factory=dict)  # estimated noise-free Mitsuba RMSE: "clean", "best"
    margins: dict[str, float] = field(default_factory=dict)  # each candidate's deficit behind "best", in std errors
    noise: float = 0.0  # the render noise (RMSE) of the best's mean render, the tolerance of the judgement
    batches: dict[str, int] = field(default_factory=dict)
    rendered: np.ndarray | None = None  # the chosen one's Mitsuba render (sRGB), None when nothing was rendered
    free_before: int = 0  # parameters the picture leaves free, away from their neutral values, in the fit's answer
    free_after: int = 0  # the same in the answer returned
    seconds: float = 0.0
    candidates: dict[str, dict] = field(default_factory=dict)  # by name: "off" (features), "distance" (D), "mitsuba"


def neutral_values() -> dict[int, float]:
    """Returns {parameter index: its neutral value (unit cube)} for every parameter of `params.FEATURES`."""
    out = {}
    for feature in params.FEATURES.values():
        for name, value in feature.items():
            i = params.INDEX[name]
            out[i] = (value - params.LOW[i]) / (params.HIGH[i] - params.LOW[i])
    return out


def free_away_from_neutral(unit: np.ndarray, verdicts: tuple[str, ...]) -> int:
    """Returns how many parameters are free (`verdicts`) yet not at their neutral value in `unit`."""
    return sum(
        int(verdicts[i] == "free" and abs(unit[i] - value) > NEUTRAL_TOLERANCE) for i, value in neutral_values().items()
    )


def _refit(
    decode: Decode, variables: PyTree, start: np.ndarray, held: np.ndarray, picture: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray | jax.Array, jax.Array | None]:
    """Returns (the point after STEPS re-linearised Gauss-Newton steps from `start` toward `picture`, the parameters
    where `held` (bool (19,)) is true held, its decoded RMSE to `picture`).

    A host loop over one compiled step: a decoder inside a compiled loop body runs slowly on XLA's CPU backend, and
    the steps unrolled into one program cost STEPS times the tracing and compiling (docs/decisions.md)."""
    x, error = start, None
    for _ in range(STEPS):
        x, error = _refit_step(decode, variables, x, held, picture, weights)
    return x, error


@programs.jit(static_argnames=("decode",))
def _refit_step(
    decode: Decode, variables: PyTree, x: jax.Array, held: jax.Array, picture: jax.Array, weights: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Returns (the point after one Gauss-Newton step from `x`, linearised there, toward `picture` with the
    parameters where `held` is true held: the best of SHARES of the step, or `x` where none lowers the error; its
    decoded RMSE to `picture`)."""
    scale = 255.0**2 / (3.0 * jnp.sum(weights))
    shares = jnp.array(SHARES, x.dtype)[:, None]
    image, tangent = jax.linearize(lambda y: decode(y[None], variables)[0], x)
    error = images.rmse(image, picture, weights)
    jacobian = jax.vmap(tangent, out_axes=-1)(jnp.eye(x.shape[0], dtype=x.dtype))  # (R, R, 3, 19)
    hessian = scale * jnp.einsum("hwcj,hwck->jk", jacobian * weights[:, :, None, None], jacobian)
    gradient = scale * jnp.einsum("hwc,hwcj->j", (image - picture) * weights[:, :, None], jacobian)
    step = ranges.box_quadratic(hessian, gradient, jnp.zeros_like(x), -x, 1.0 - x, held)
    trials = jnp.clip(x[None] + shares * step[None], 0.0, 1.0)
    errors = images.rmse(decode(trials, variables), picture[None], weights)
    k = jnp.argmin(errors)
    better = errors[k] < error
    return jnp.where(better, trials[k], x), jnp.where(better, errors[k], error)


def unseen_medium(unit: np.ndarray) -> bool:
    """Returns whether the material (unit cube) has no transmission, so that no light reaches the medium inside it
    and the renderer does not show the medium (the decoder may: its own error)."""
    return bool(abs(unit[params.INDEX["spec_trans"]] - neutral_values()[params.INDEX["spec_trans"]]) <= 1e-6)


def candidates(
    decode: Decode, variables: PyTree, answer: np.ndarray, weights: np.ndarray | None, found: ranges.Ranges
) -> list[tuple[tuple[str, ...], np.ndarray, float]]:
    """Returns the nested candidates of the module docstring, the simplest last: [(features off, the material (unit
    cube), D: its decoded RMSE to the answer's picture)]. `decode` as for `ranges.measure`; `found`: the answer's
    ranges."""
    answer = np.clip(np.asarray(answer, np.float32), 0.0, 1.0)
    neutral = neutral_values()
    tried = {}
    for name, feature in params.FEATURES.items():
        indices = [params.INDEX[p] for p in feature]
        if found.verdicts[indices[0]] != "decided" and any(abs(answer[i] - neutral[i]) > 1e-6 for i in indices):
            tried[name] = indices
    if not tried:
        return []
    base, held = answer.copy(), np.zeros(params.COUNT, bool)
    names: tuple[str, ...] = ()
    out: list[tuple[tuple[str, ...], np.ndarray, float]] = []
    if "medium" in tried and unseen_medium(answer):
        for i in tried.pop("medium"):
            base[i], held[i] = neutral[i], True
        names = ("medium",)
        out.append((names, np.asarray(base, np.float64), 0.0))
    picture = np.asarray(ranges.decoded(decode, base[None].astype(np.float32), variables))[0]  # as rendered
    weights = np.ones(picture.shape[:2], np.float32) if weights is None else np.asarray(weights, np.float32)
    limit = min(CLOSE, found.threshold)

    def off(start: np.ndarray, held: np.ndarray, indices: list[int]) -> tuple[np.ndarray, np.ndarray, float]:
        start, held = start.copy(), held.copy()
        for i in indices:
            start[i], held[i] = neutral[i], True
        point, distance = jax.device_get(_refit(decode, variables, start, held, picture, weights))
        return np.asarray(point, np.float32), held, float(distance)

    alone = {name: off(base, held, indices)[2] for name, indices in tried.items()}
    order = sorted((name for name in tried if alone[name] <= limit), key=alone.__getitem__)
    point = base
    for name in order:
        trial, trial_held, distance = off(point, held, tried[name])
        if distance <= limit:
            point, held, names = trial, trial_held, (*names, name)
            out.append((names, np.asarray(point, np.float64), distance))
    return out


def render_noise(renders: list[np.ndarray], target: np.ndarray, weights: np.ndarray) -> float:
    """Returns the RMSE (0-255) of the noise in the mean of `renders` (m batches of one material): each batch's
    mean squared error against `target` less the noise-free estimate (`verify.squared_error`), over m."""
    estimate, _ = verify.squared_error(renders, target, weights)
    single = float(np.mean([float(images.rmse(render, target, weights)) ** 2 for render in renders])) / 255.0**2
    return 255.0 * float(np.sqrt(max(single - estimate, 0.0) / len(renders)))


def judge(
    renderer: Renders,
    best: np.ndarray,
    pool: dict[str, np.ndarray],
    target: np.ndarray,
    weights: np.ndarray | None,
    *,
    rendered: list[np.ndarray] | tuple = (),
    spp: int = verify.BATCH_SPP,
) -> dict[str, Any]:
    """Returns {"chosen": the name kept ("best" or one of `pool`), "figures", "noise", "margins", "batches",
    "rendered"}: `best` and the candidates of `pool` (by name, simplest last) rendered in batches with verification's
    seeds and compared by its estimates, by the rule of the module docstring. `margins`: each judged candidate's
    deficit behind the best over their common batches, in standard errors (negative: ahead of it); those after the
    one kept or undecided are not rendered, so neither in `margins` nor in `figures`; `noise`: the render noise
    of the best's mean render (`render_noise`), recorded beside the figures. `rendered`: the batches of `best` that
    verification rendered already (`verify.Verified.renders`), which are not rendered again; `spp`: samples of a
    batch, as verification's."""
    weights = verify.as_weights(target, weights)
    everyone = {"best": best, **pool}
    batches: dict[str, list[np.ndarray]] = {"best": list(rendered)}
    margins: dict[str, float] = {}
    chosen = "best"
    for name in reversed(pool):  # the simplest first; a less simple one is rendered only when it is refused
        verify.render_batches(renderer, everyone, batches, ["best", name], count=verify.BATCHES, spp=spp)
        margins[name] = deficit(batches["best"], batches[name], target, weights)
        if margins[name] <= 0:
            chosen = name
            break
        if margins[name] < verify.LEAD:  # undecided: the answer stays, and so would a less simple candidate
            break
    estimates = {name: verify.squared_error(renders, target, weights)[0] for name, renders in batches.items()}
    return {
        "chosen": chosen,
        "figures": {name: 255.0 * float(np.sqrt(max(value, 0.0))) for name, value in estimates.items()},
        "noise": render_noise(batches["best"], target, weights),
        "margins": margins,
        "batches": {name: len(renders) for name, renders in batches.items()},
        "rendered": np.mean(batches[chosen], axis=0, dtype=np.float32),
    }


def deficit(best: list[np.ndarray], other: list[np.ndarray], target: np.ndarray, weights: np.ndarray) -> float:
    """Returns how far `other`'s estimate trails `best`'s over their common batches, in standard errors (negative:
    ahead; `verify.decide` of the two, the best first so that a tie favours it)."""
    leader, estimates, margins = verify.decide({"best": best, "other": other}, target, weights)
    if abs(estimates["other"] - estimates["best"]) <= ALIKE * estimates["best"]:  # renders alike to their last bits
        return 0.0
    return float(margins["other"]) if leader == "best" else -float(margins["best"])


def clean(
    decode: Decode,
    variables: PyTree,
    answer: np.ndarray,
    target: np.ndarray,
    weights: np.ndarray | None,
    found: ranges.Ranges,
    renderer: Renders | None = None,
    *,
    rendered: list[np.ndarray] | tuple = (),
    spp: int = verify.BATCH_SPP,
) -> Cleaned:
    """Returns the clean answer of `answer` (unit cube), judged in Mitsuba against it with `renderer` (an
    `engine.Renderer`, `Background` or `Process` at the target's resolution; None: not judged, the simplest
    candidate returned). `rendered`, `spp`: verification's batches of `answer` and their samples, as for `judge`."""
    started = time.perf_counter()
    answer = np.asarray(answer, np.float64)
    found_candidates = candidates(decode, variables, answer, weights, found)
    pool = {f"clean-{k + 1}": unit for k, (_, unit, _) in enumerate(found_candidates)}
    described = {
        f"clean-{k + 1}": {"off": list(names), "distance": distance}
        for k, (names, _, distance) in enumerate(found_candidates)
    }
    chosen = "clean-" + str(len(pool)) if pool else "best"
    judged: dict = {}
    figures: dict[str, float] = {}
    if pool and renderer is not None:
        judged = judge(renderer, answer, pool, target, weights, rendered=rendered, spp=spp)
        chosen = judged["chosen"]
        shown = chosen if chosen != "best" else f"clean-{len(pool)}"
        figures = {"clean": judged["figures"][shown], "best": judged["figures"]["best"]}
        for name in judged["margins"]:  # the candidates judged: the simplest, and less simple ones while refused
            described[name]["mitsuba"] = judged["figures"][name]
            described[name]["margin"] = judged["margins"][name]
    unit = pool[chosen] if chosen != "best" else answer
    dropped = found_candidates[-1][0] if found_candidates else ()
    if chosen != "best":
        dropped = found_candidates[int(chosen.split("-")[1]) - 1][0]
    return Cleaned(
        unit=unit,
        simplest=found_candidates[-1][1] if found_candidates else answer,
        best=answer,
        dropped=dropped,
        chosen="best" if chosen == "best" else "clean",
        figures=figures,
        margins=judged.get("margins", {}),
        noise=judged.get("noise", 0.0),
        batches=judged.get("batches", {}),
        rendered=judged.get("rendered"),
        free_before=free_away_from_neutral(answer, found.verdicts),
        free_after=free_away_from_neutral(unit, found.verdicts),
        seconds=time.perf_counter() - started,
        candidates=described,
    )
