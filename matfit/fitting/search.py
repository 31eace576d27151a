"""Fitting the 19 shader parameters to a target image: the paper's Algorithm 1, jit-compiled.

- best-of-n: every encoder guesses x from the target; the guesses (plus any extra candidates,
  such as the previous frame's optimum in a sequence, and for the gradient methods the fixed
  grid of `media_candidates`) are decoded in one batch and the one whose image is closest to the
  target wins;
- Nelder-Mead (`simplex.py`) minimises the image RMSE E(x) = RMSE(phi(x), t) (0-255 sRGB,
  optionally weighted per pixel by a mask) inside the unit cube, within a budget of evaluations;
- `hybrid` starts Nelder-Mead from the best-of-n guess, `optimize` from a random point (the
  paper's baseline), `nn` stops after best-of-n;
- `lbfgsb` runs bounded L-BFGS-B (`gradient.py`, exact decoder gradients) from the best `starts`
  candidates of best-of-n at once, `narrow_after` steps, then the best of them alone up to
  `iterations` steps; `hybrid-lbfgsb` runs Nelder-Mead first and adds its result to
  those starts. A value-and-gradient counts as GRADIENT_COST evaluations in the budget reported.

Every method returns its end points sorted by neural RMSE (`Result.ends`): `verify.py` lets
Mitsuba choose among them and the best-of-n start.

The box: `clip` (default) evaluates phi at the point clipped into the box and adds
PENALTY x (distance outside); `barrier` is the paper's finite barrier (E + BARRIER outside).
Both keep the result inside the box, which is clipped at the end in any case.

Everything per call (weights, target, mask, candidates, random start) travels as arguments of
compiled functions, compiled once per model and settings and reused for every target: `_best_of_n`
(best-of-n, Nelder-Mead), the gradient stage's step (a host loop, see `gradient.py` for why) and
`_polish_and_sort` (the optional neural polish, the end points sorted).
"""

from __future__ import annotations

import functools
import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from matfit import images, params, programs
from matfit.errors import FitError
from matfit.fitting import gradient
from matfit.fitting.methods import Box, Method, Settings
from matfit.model import models

if TYPE_CHECKING:
    # flax types `nn.Module.apply` as returning the output or (output, variables), a tuple only with `mutable`: where
    # a decoder's output is used as the array it is, mypy is told to ignore that (`type: ignore`)
    import flax.linen as nn
    from jaxtyping import Float

__all__ = [
    "Box",
    "FitError",
    "Method",
    "Result",
    "Settings",
    "neural_search",
    "objective",
    "prepare_mask",
    "prepare_target",
]

PENALTY = 100.0
BARRIER = 1e4
# What one value-and-gradient of the objective costs, in objective evaluations (forward passes), so that budgets in
# evaluations are comparable across methods: the ratio of the two calls' times on the shipped decoder at the gradient
# stage's batch sizes; remeasure it when the decoder changes (docs/fitting.md#the-gradient-stage).
GRADIENT_COST = 2.5
ASPECT_TOLERANCE = 0.01
# The grid of `media_candidates`: white dielectric spheres filled with a grey medium. The encoders, trained on
# uniform draws where a dense white medium is rare, guess milk as an opaque white material and the fit stays
# there (docs/fitting.md#best-of-n).
MEDIA_GRID = {
    "density": (0.5, 1.0, 2.0, 4.0),
    "medium_color": (0.05, 0.2, 0.5),
    "scattering": (0.7, 1.0),
    "roughness": (0.05, 0.3),
}


def distance_outside(x: jax.Array) -> jax.Array:
    """Returns the Euclidean distance from x to the unit cube, with a zero (not NaN) gradient inside it."""
    squared = jnp.sum((x - jnp.clip(x, 0.0, 1.0)) ** 2)
    positive = squared > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)


@functools.cache
def media_candidates() -> Float[np.ndarray, "k 19"]:
    """Returns the unit-cube grid (k, 19) of transmissive candidates the gradient methods add to best-of-n.

    Each is the default material made a white dielectric (base colour 1, spec_trans 1) holding a grey
    medium, for every combination of `MEDIA_GRID`; the gradient stage tints and tunes the winner.
    """
    points = []
    for density, grey, albedo, roughness in itertools.product(*MEDIA_GRID.values()):
        x = params.DEFAULTS.copy()
        for name in ("base_color_r", "base_color_g", "base_color_b", "spec_trans"):
            x[params.INDEX[name]] = 1.0
        for name in ("medium_color_r", "medium_color_g", "medium_color_b"):
            x[params.INDEX[name]] = grey
        x[params.INDEX["density"]], x[params.INDEX["scattering"]] = density, albedo
        x[params.INDEX["roughness"]] = roughness
        points.append(params.to_unit(x))
    return np.asarray(points, np.float32)


def objective(x: Float[jax.Array, " 19"], args: tuple) -> Float[jax.Array, ""]:
    """Returns E(x) plus the box term; args = (decoder module, decoder variables, target, weights, box)."""
    decoder, variables, target, weights, box = args
    error = images.rmse(decoder.apply(variables, jnp.clip(x, 0.0, 1.0)), target, weights)
    outside = distance_outside(x)
    if box == Box.barrier:
        return jnp.where(outside > 0, error + BARRIER, error)
    return error + PENALTY * outside


def neural_polish(
    decoder: nn.Module,
    variables: dict,
    target: jax.Array,
    weights: jax.Array,
    x: jax.Array,
    steps: int,
    rate: float,
) -> jax.Array:
    """Returns the best point of `steps` projected Adam steps on E from x (x itself if none is better)."""
    import optax  # only for the opt-in polish: every cold start would pay for its import

    tx = optax.adam(rate)
    loss = jax.value_and_grad(lambda y: images.rmse(decoder.apply(variables, y), target, weights))  # type: ignore[arg-type]

    def body(
        _: jax.Array, carry: tuple[jax.Array, optax.OptState, jax.Array, jax.Array]
    ) -> tuple[jax.Array, optax.OptState, jax.Array, jax.Array]:
        y, state, best, best_value = carry
        value, grad = loss(y)
        better = value < best_value
        best, best_value = jnp.where(better, y, best), jnp.where(better, value, best_value)
        updates, state = tx.update(grad, state, y)
        return jnp.clip(optax.apply_updates(y, updates), 0.0, 1.0), state, best, best_value

    y, _, best, best_value = jax.lax.fori_loop(0, steps, body, (x, tx.init(x), x, jnp.inf))
    last = images.rmse(decoder.apply(variables, y), target, weights)  # type: ignore[arg-type]
    return jnp.where(last < best_value, y, best)


def decoded_rmse(y: Float[jax.Array, " 19"], args: tuple) -> Float[jax.Array, ""]:
    """Returns E(y) = RMSE(phi(y), t) for y inside the box, the gradient stage's objective.

    args = (decoder module, variables, target, weights). No clip: the gradient stage only evaluates
    points inside the box, and a clip would halve the gradient of a coordinate lying on a face.
    """
    decoder, variables, target, weights = args
    return images.rmse(decoder.apply(variables, y), target, weights)


@programs.jit(static_argnames=("decoder", "encoders", "settings"))
def _best_of_n(
    decoder: nn.Module,
    encoders: tuple[nn.Module, ...],
    settings: Settings,
    decoder_variables: dict,
    encoder_variables: tuple[dict, ...],
    target: jax.Array,
    encoder_target: jax.Array,
    weights: jax.Array,
    extra: jax.Array,
    start: jax.Array,
) -> dict[str, jax.Array]:
    guesses = [
        encoder.apply(variables, encoder_target[None])[0]
        for encoder, variables in zip(encoders, encoder_variables, strict=True)
    ]
    candidates = jnp.concatenate([jnp.stack(guesses), extra]) if guesses else extra
    candidate_images: jax.Array = decoder.apply(decoder_variables, candidates)  # type: ignore[assignment]
    candidate_errors = images.rmse(candidate_images, target, weights)
    chosen = jnp.argmin(candidate_errors)
    # The fit's end points (sorted by `_polish_and_sort`): what Mitsuba verification chooses among.
    ends = candidates[chosen][None]
    evaluations = jnp.array(0, jnp.float32)
    if settings.method.uses_simplex:
        from matfit.fitting import (
            simplex,  # optimistix and equinox: imported only for Nelder-Mead (a cold start's time)
        )

        y0 = start if settings.method == Method.optimize else candidates[chosen]
        solver = simplex.NelderMead(adaptive=settings.adaptive, initial_step=settings.initial_step)

        def fn(
            y: jax.Array, args: tuple[dict, jax.Array, jax.Array]
        ) -> jax.Array:  # the module and box mode are structure; the data travels in args
            return objective(y, (decoder, *args, settings.box))

        solution = simplex.minimise(fn, y0, (decoder_variables, target, weights), settings.evaluations, solver)
        x = jnp.clip(solution.value, 0.0, 1.0)
        ends = x[None]
        evaluations = solution.stats["evaluations"].astype(jnp.float32)
    if settings.method.uses_gradient:  # the gradient stage's starts; it runs on the host (`gradient.py`)
        best_candidates = jnp.argsort(candidate_errors)[: min(settings.starts, candidates.shape[0])]
        starts = candidates[best_candidates]
        ends = jnp.concatenate([ends, starts]) if settings.method.uses_simplex else starts
    return {
        "ends": ends,
        "candidates": candidates,
        "start_image": candidate_images[chosen],
        "candidate_rmse": candidate_errors,
        "chosen": chosen,
        "evaluations": evaluations,
    }


@dataclass(frozen=True)
class DecodedObjective:
    """E(y) for one decoder module as a function of (y, (variables, target, weights)): the gradient stage's objective.

    A frozen dataclass rather than a closure: equal for equal modules (the compiled step is reused)
    and with a repr that names the module, so its traced step can be stored (`programs.py`).
    """

    decoder: nn.Module

    def __call__(self, y: jax.Array, args: tuple) -> jax.Array:
        return decoded_rmse(y, (self.decoder, *args))


def gradient_objective(decoder: nn.Module) -> DecodedObjective:
    """Returns E(y) for `decoder` as a function of (y, (variables, target, weights))."""
    return DecodedObjective(decoder)


@programs.jit(static_argnames=("decoder", "settings"))
def _polish_and_sort(
    decoder: nn.Module,
    settings: Settings,
    decoder_variables: dict,
    target: jax.Array,
    weights: jax.Array,
    ends: jax.Array,
) -> dict[str, jax.Array]:
    """Returns the end points sorted by neural RMSE (after the optional polish), and their images."""
    end_images: jax.Array = decoder.apply(decoder_variables, ends)  # type: ignore[assignment]
    end_errors = images.rmse(end_images, target, weights)
    if settings.polish_steps:
        polished = neural_polish(
            decoder,
            decoder_variables,
            target,
            weights,
            ends[jnp.argmin(end_errors)],
            settings.polish_steps,
            settings.polish_rate,
        )
        ends = jnp.concatenate([polished[None], ends])
        end_images = decoder.apply(decoder_variables, ends)  # type: ignore[assignment]
        end_errors = images.rmse(end_images, target, weights)
    order = jnp.argsort(end_errors)
    ends, end_errors, end_images = ends[order], end_errors[order], end_images[order]
    return {
        "unit": ends[0],
        "image": end_images[0],
        "rmse": end_errors[0],
        "ends": ends,
        "end_rmse": end_errors,
        "end_images": end_images,
    }


@dataclass(frozen=True)
class Result:
    """What a fit found and how."""

    values: Float[np.ndarray, " 19"]  # physical parameters (19,)
    unit: Float[np.ndarray, " 19"]  # the same on the unit cube
    image: Float[np.ndarray, "R R 3"]  # phi(x), sRGB (R, R, 3)
    rmse: float  # neural RMSE against the target, 0-255
    start_rmse: float  # RMSE of the best-of-n start
    start: Float[np.ndarray, " 19"]  # unit-cube start chosen by best-of-n
    start_image: Float[np.ndarray, "R R 3"]  # phi(start), sRGB (R, R, 3)
    chosen: str  # which candidate won best-of-n ("encoder-4", "extra-1", ...), or "random" (`optimize`)
    candidate_rmse: dict = field(default_factory=dict)
    evaluations: int = 0  # objective evaluations, a value-and-gradient counted as GRADIENT_COST of them
    seconds: float = 0.0
    ends: Float[np.ndarray, "k 19"] | None = None  # the fit's end points (unit cube, (k, 19)), best neural RMSE first
    end_rmse: Float[np.ndarray, " k"] | None = None  # their neural RMSE
    end_images: Float[np.ndarray, "k R R 3"] | None = None  # their decoded images, sRGB (k, R, R, 3)

    def decoded(self, unit: Float[np.ndarray, " 19"]) -> Float[np.ndarray, "R R 3"] | None:
        """Returns phi(unit) if `unit` is the start or an end point (already decoded by the fit), else None."""
        unit = np.asarray(unit, np.float64)
        if np.array_equal(unit, np.asarray(self.start, np.float64)):
            return self.start_image
        if self.ends is not None and self.end_images is not None:
            for end, image in zip(self.ends, self.end_images, strict=True):
                if np.array_equal(unit, np.asarray(end, np.float64)):
                    return image
        return None


def candidate_names(model: models.Model, extra_count: int, *, media_count: int = 0) -> list[str]:
    """Returns the names of the best-of-n candidates in order: encoders, extra candidates, then the media grid."""
    return (
        [f"encoder-{arch}" for arch in model.encoders]
        + [f"extra-{k + 1}" for k in range(extra_count)]
        + [f"media-{k + 1}" for k in range(media_count)]
    )


def neural_search(
    model: models.Model,
    target: Float[np.ndarray, "R R 3"],
    *,
    settings: Settings | None = None,
    weights: Float[np.ndarray, "R R"] | None = None,
    extra: Float[np.ndarray, "k 19"] | None = None,
    seed: int = 0,
    on_start: Callable[[Float[np.ndarray, " 19"]], None] | None = None,
) -> Result:
    """Returns the parameters whose decoded image best matches `target`: best-of-n, then the method's optimiser.

    target: sRGB (R, R, 3) in [0, 1] at the model's resolution (`prepare_target`); weights: (R, R)
    per-pixel weights (a mask) or None; extra: unit-cube candidates (k, 19) joining best-of-n (the
    gradient methods add `media_candidates` after them); seed: draws the random start of `optimize`
    (data, not a setting: no recompilation); on_start: called with best-of-n's winner (unit cube)
    as soon as it is chosen, before the gradient stage (verification renders it meanwhile).
    """
    settings = settings or Settings()
    settings.check()
    target, weights, extra, media = checked_inputs(model, settings, target, weights, extra)
    start = np.random.default_rng(seed).uniform(0.0, 1.0, params.COUNT).astype(np.float32)
    encoder_target = models.encoder_input(images.srgb_decode(target))
    started = time.perf_counter()
    out = best_of_n_stage(model, settings, target, encoder_target, weights, np.concatenate([extra, media]), start)
    ends = out["ends"]
    if on_start is not None and settings.method != Method.optimize:  # optimize starts at random
        on_start(np.asarray(out["candidates"][int(out["chosen"])]))
    if settings.method.uses_gradient:
        ends, spent = gradient_stage(model, settings, target, weights, ends)
        out["evaluations"] = out["evaluations"] + GRADIENT_COST * spent
    decoder, variables = model.decoder.module, model.decoder.variables
    out |= jax.device_get(_polish_and_sort(decoder, settings, variables, target, weights, ends))
    seconds = time.perf_counter() - started
    names = candidate_names(model, len(extra), media_count=len(media))
    return search_result(model, settings, out, names, start, target, weights, seconds)


def checked_inputs(
    model: models.Model,
    settings: Settings,
    target: Float[np.ndarray, "R R 3"],
    weights: Float[np.ndarray, "R R"] | None,
    extra: Float[np.ndarray, "k 19"] | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns (target, weights, extra candidates, the media grid or none) as float32 arrays, or raises FitError
    naming what is wrong with them."""
    side = model.resolution
    target = np.asarray(target, np.float32)
    if target.shape != (side, side, 3):
        raise FitError(
            f"the target is {target.shape}, the model needs ({side}, {side}, 3): resample it with prepare_target"
        )
    weights = np.ones((side, side), np.float32) if weights is None else np.asarray(weights, np.float32)
    if weights.shape != (side, side) or not np.all(np.isfinite(weights)) or weights.min() < 0 or weights.sum() <= 0:
        raise FitError("the mask must be (R, R) finite non-negative weights, not all zero: paint some of it white")
    extra = (
        np.zeros((0, params.COUNT), np.float32)
        if extra is None
        else np.asarray(extra, np.float32).reshape(-1, params.COUNT)
    )
    media = media_candidates() if settings.method.uses_gradient else np.zeros((0, params.COUNT), np.float32)
    if not model.encoders and not len(extra) + len(media) and settings.method != Method.optimize:
        raise FitError("best-of-n needs at least one encoder or extra candidate: use a model with encoders")
    return target, weights, extra, media


def best_of_n_stage(
    model: models.Model,
    settings: Settings,
    target: Float[np.ndarray, "R R 3"],
    encoder_target: Float[np.ndarray, "32 32 3"],
    weights: Float[np.ndarray, "R R"],
    extra: Float[np.ndarray, "k 19"],
    start: Float[np.ndarray, " 19"],
) -> dict:
    """Returns the compiled first stage's outputs as host arrays (`_best_of_n`): best-of-n over the encoders' guesses
    and `extra`, then Nelder-Mead for the simplex methods, and the gradient stage's starts."""
    out = _best_of_n(
        model.decoder.module,
        tuple(network.module for network in model.encoders.values()),
        settings,
        model.decoder.variables,
        tuple(network.variables for network in model.encoders.values()),
        target,
        encoder_target,
        weights,
        extra,
        start,
    )
    return jax.device_get(out)  # host arrays between the compiled stages: no JAX operation outside them


def gradient_stage(
    model: models.Model,
    settings: Settings,
    target: Float[np.ndarray, "R R 3"],
    weights: Float[np.ndarray, "R R"],
    starts: Float[np.ndarray, "k 19"],
) -> tuple[np.ndarray, float]:
    """Returns (the end points of projected L-BFGS from `starts` (`gradient.minimise`), the value-and-gradients
    spent)."""
    data = (model.decoder.variables, target, weights)
    ends, _, spent = gradient.minimise(
        gradient_objective(model.decoder.module), starts, data, settings.iterations, narrow_after=settings.narrow_after
    )
    return ends, spent


def search_result(
    model: models.Model,
    settings: Settings,
    out: dict,
    names: list[str],
    start: Float[np.ndarray, " 19"],
    target: Float[np.ndarray, "R R 3"],
    weights: Float[np.ndarray, "R R"],
    seconds: float,
) -> Result:
    """Returns the `Result` of the compiled stages' outputs `out`; for `optimize`, its start is the random `start`."""
    unit = np.asarray(out["unit"], np.float64)
    chosen = int(out["chosen"])
    start_rmse, start_point, start_image, chosen_name = (
        float(out["candidate_rmse"][chosen]),
        np.asarray(out["candidates"][chosen]),
        np.asarray(out["start_image"]),
        names[chosen],
    )
    if settings.method == Method.optimize:  # it started from the random point, not from best-of-n's winner
        start_image = np.asarray(models.apply(model.decoder.module, model.decoder.variables, start[None]))[0]
        start_point, chosen_name = start, "random"
        start_rmse = float(images.rmse(start_image, target, weights))
    return Result(
        values=params.from_unit(unit),
        unit=unit,
        image=np.asarray(out["image"]),
        rmse=float(out["rmse"]),
        start_rmse=start_rmse,
        start=start_point,
        start_image=start_image,
        chosen=chosen_name,
        candidate_rmse=dict(zip(names, map(float, out["candidate_rmse"]), strict=True)),
        evaluations=round(float(out["evaluations"])),
        seconds=seconds,
        ends=np.asarray(out["ends"], np.float64),
        end_rmse=np.asarray(out["end_rmse"], np.float64),
        end_images=np.asarray(out["end_images"]),
    )


def prepare_target(
    linear: Float[np.ndarray, "H W 3"], resolution: int, source: str
) -> tuple[Float[np.ndarray, "resolution resolution 3"], list[str]]:
    """Returns a linear image resampled to the model's square resolution and sRGB-encoded, with warnings."""
    height, width = linear.shape[:2]
    notices = []
    if abs(width / height - 1.0) > ASPECT_TOLERANCE:
        notices.append(
            f"warning: {source} is {width}x{height} (aspect {width / height:.3f}) but the scene is square (1.000): "
            f"it is stretched to {resolution}x{resolution}; crop it to a square for a faithful fit"
        )
    return images.srgb_encode(images.resample(linear, resolution, resolution)), notices


def prepare_mask(
    linear: Float[np.ndarray, "H W C"], target_shape: tuple[int, int], resolution: int, source: str
) -> Float[np.ndarray, "resolution resolution"]:
    """Returns per-pixel weights (R, R) from a mask image: white = 1 (fit here), black = 0 (ignore)."""
    if linear.shape[:2] != target_shape:
        raise FitError(
            f"the mask {source} is {linear.shape[1]}x{linear.shape[0]}, the target is "
            f"{target_shape[1]}x{target_shape[0]}: make the mask the same size as the target"
        )
    weights = images.srgb_encode(images.resample(linear, resolution, resolution)).mean(axis=2)
    if weights.sum() <= 0:
        raise FitError(f"the mask {source} is black everywhere: paint white where the fit should look")
    return weights
