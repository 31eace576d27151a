"""The clean answer: among the materials that decode within the threshold of the fit's answer, the simplest.

Simplest means: the shader's optional features (`params.FEATURES`: anisotropy, sheen, clearcoat,
the interior medium, transmission) turned off unless the picture decides them. Greedily, in that
order, each feature whose leading parameter the picture does not decide (`ranges.Ranges.verdicts`)
and that is not already off is set to its neutral values; the other parameters that are still
free to move are re-fitted to the target by Gauss-Newton steps with the answer's Jacobian (the
chord method, `STEPS` decodes); the feature stays off when the result decodes within the
threshold tau of the answer's picture, or no further from the target than the answer
(docs/fitting.md#what-the-picture-decides).

Like every answer it is then judged in Mitsuba (`judge`), against the answer it would replace,
by verification's estimates (`verify.decide`, common random numbers, the jackknife): the clean
answer is kept unless the other one is better by more than LEAD standard errors (`judge`), so it
is never measurably worse. (Allowing the noise of the kept render as well kept every clean answer
and made them worse on average by an independent judge: docs/fitting.md#what-the-picture-decides.)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from matfit import images, params, programs
from matfit.fit import ranges, verify

STEPS = 2  # Gauss-Newton steps (one decode each) re-fitting the other parameters after a feature is turned off
NEUTRAL_TOLERANCE = 0.01  # of a parameter's range: a value this close to its neutral one counts as neutral


@dataclass
class Cleaned:
    """The clean answer and how it was chosen."""

    unit: np.ndarray  # the answer returned (unit cube): the clean one, or the fit's when Mitsuba preferred it
    simplest: np.ndarray  # the simplest material within the threshold (unit cube)
    best: np.ndarray  # the fit's own answer it started from (unit cube)
    dropped: tuple[str, ...]  # the features turned off
    chosen: str  # "clean" or "best"
    figures: dict[str, float] = field(default_factory=dict)  # each one's estimated noise-free Mitsuba RMSE
    margins: dict[str, float] = field(default_factory=dict)  # the other one's deficit, in standard errors
    noise: float = 0.0  # the render noise (RMSE) of the best's mean render, the tolerance of the judgement
    batches: dict[str, int] = field(default_factory=dict)
    rendered: np.ndarray | None = None  # the chosen one's Mitsuba render (sRGB), None when nothing was rendered
    free_before: int = 0  # parameters the picture leaves free, away from their neutral values, in the fit's answer
    free_after: int = 0  # the same in the clean answer
    seconds: float = 0.0


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


@programs.jit(static_argnames=("decode", "features"))
def _simplest(decode, features, variables, answer, target, weights, threshold, allowed):
    """Returns (the simplest point, which of `features` were turned off (bool)); `features`: a tuple of
    (index tuple, neutral unit values tuple) in the order tried, `allowed` (bool, one per feature): which to try."""
    count = answer.shape[0]
    picture = decode(answer[None], variables)[0]
    jacobian = jax.jacfwd(lambda x: decode(x[None], variables)[0])(answer)
    scale = 255.0**2 / (3.0 * jnp.sum(weights))
    hessian = scale * jnp.einsum("hwcj,hwck->jk", jacobian * weights[:, :, None, None], jacobian)
    answer_error = images.rmse(picture, target, weights)
    x, held, dropped = answer, jnp.zeros(count, bool), []
    for k, (indices, values) in enumerate(features):
        idx = jnp.array(indices)
        trial = x.at[idx].set(jnp.array(values, x.dtype))
        trial_held = held.at[idx].set(True)
        for _ in range(STEPS):
            residual = (decode(trial[None], variables)[0] - target) * weights[:, :, None]
            gradient = scale * jnp.einsum("hwc,hwcj->j", residual, jacobian)
            step = ranges.box_quadratic(hessian, gradient, jnp.zeros_like(x), -trial, 1.0 - trial, trial_held)
            trial = jnp.clip(trial + step, 0.0, 1.0)
        image = decode(trial[None], variables)[0]
        within = (images.rmse(image, picture, weights) <= threshold) | (
            images.rmse(image, target, weights) <= answer_error
        )
        accepted = allowed[k] & within
        x = jnp.where(accepted, trial, x)
        held = jnp.where(accepted, trial_held, held)
        dropped.append(accepted)
    return x, jnp.stack(dropped)


def simplest(
    decode, variables, answer: np.ndarray, target: np.ndarray, weights: np.ndarray | None, found: ranges.Ranges
) -> tuple[np.ndarray, tuple[str, ...]]:
    """Returns (the simplest material within `found.threshold` of `answer` (unit cube), the features turned off),
    by the module docstring. `decode` as for `ranges.measure`; `found`: the answer's ranges."""
    answer = np.clip(np.asarray(answer, np.float32), 0.0, 1.0)
    neutral = neutral_values()
    features, allowed = [], []
    for feature in params.FEATURES.values():
        indices = tuple(params.INDEX[p] for p in feature)
        features.append((indices, tuple(float(neutral[i]) for i in indices)))
        decided = found.verdicts[indices[0]] == "decided"
        allowed.append(not decided and any(abs(answer[i] - neutral[i]) > 1e-6 for i in indices))
    if not any(allowed):
        return np.asarray(answer, np.float64), ()
    weights = np.ones(target.shape[:2], np.float32) if weights is None else np.asarray(weights, np.float32)
    unit, dropped = jax.device_get(
        _simplest(
            decode,
            tuple(features),
            variables,
            answer,
            np.asarray(target, np.float32),
            weights,
            np.float32(found.threshold),
            np.array(allowed),
        )
    )
    off = tuple(name for name, turned_off in zip(params.FEATURES, dropped, strict=True) if turned_off)
    return (np.asarray(unit, np.float64) if off else np.asarray(answer, np.float64)), off


def render_noise(renders: list[np.ndarray], target: np.ndarray, weights: np.ndarray) -> float:
    """Returns the RMSE (0-255) of the noise in the mean of `renders` (m batches of one material): each batch's
    mean squared error against `target` less the noise-free estimate (`verify.squared_error`), over m."""
    estimate, _ = verify.squared_error(renders, target, weights)
    single = float(np.mean([float(images.rmse(render, target, weights)) ** 2 for render in renders])) / 255.0**2
    return 255.0 * float(np.sqrt(max(single - estimate, 0.0) / len(renders)))


def judge(renderer, best: np.ndarray, clean: np.ndarray, target: np.ndarray, weights: np.ndarray | None) -> dict:
    """Returns {"chosen": "clean" or "best", "figures", "noise", "margins", "batches", "rendered"}: the two rendered
    in batches with verification's seeds and compared by its estimates (`verify.decide`, more batches while the
    difference is within LEAD standard errors, up to MAX_BATCHES). The clean one is kept unless the other is
    better by more than LEAD standard errors: verification's own rule, the clean one in the start's place.
    `noise`: the render noise of the best's mean render (`render_noise`), recorded beside the figures."""
    weights = verify.as_weights(target, weights)
    pool = {"clean": clean, "best": best}
    batches: dict[str, list[np.ndarray]] = {name: [] for name in pool}
    verify.render_batches(renderer, pool, batches, list(pool), count=verify.BATCHES, spp=verify.SPP)
    while True:
        leader, estimates, margins = verify.decide(batches, target, weights)
        if leader == "clean" or margins["clean"] >= verify.LEAD or len(batches["best"]) >= verify.MAX_BATCHES:
            break
        verify.render_batches(renderer, pool, batches, list(pool), count=len(batches["best"]) + 1, spp=verify.SPP)
    figures = {name: 255.0 * float(np.sqrt(max(value, 0.0))) for name, value in estimates.items()}
    noise = render_noise(batches["best"], target, weights)
    chosen = "best" if leader == "best" and margins["clean"] >= verify.LEAD else "clean"
    return {
        "chosen": chosen,
        "figures": figures,
        "noise": noise,
        "margins": margins,
        "batches": {name: len(renders) for name, renders in batches.items()},
        "rendered": np.mean(batches[chosen], axis=0, dtype=np.float32),
    }


def clean(
    decode,
    variables,
    answer: np.ndarray,
    target: np.ndarray,
    weights: np.ndarray | None,
    found: ranges.Ranges,
    renderer=None,
) -> Cleaned:
    """Returns the clean answer of `answer` (unit cube), judged in Mitsuba against it with `renderer` (an
    `engine.Renderer`, `Background` or `Process` at the target's resolution; None: not judged, the clean answer
    returned)."""
    started = time.perf_counter()
    answer = np.asarray(answer, np.float64)
    simple, dropped = simplest(decode, variables, answer, target, weights, found)
    out = Cleaned(
        unit=simple,
        simplest=simple,
        best=answer,
        dropped=dropped,
        chosen="clean",
        free_before=free_away_from_neutral(answer, found.verdicts),
        free_after=free_away_from_neutral(simple, found.verdicts),
    )
    if dropped and renderer is not None:
        judged = judge(renderer, answer, simple, target, weights)
        out.chosen, out.figures, out.margins = judged["chosen"], judged["figures"], judged["margins"]
        out.noise = judged["noise"]
        out.batches, out.rendered = judged["batches"], judged["rendered"]
        if out.chosen == "best":
            out.unit, out.free_after = answer, out.free_before
    elif not dropped:
        out.unit = answer
    out.seconds = time.perf_counter() - started
    return out
