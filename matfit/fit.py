"""Fitting the 19 shader parameters to a target image: the paper's Algorithm 1, jit-compiled.

- best-of-n: every encoder guesses x from the target; the guesses (plus any extra candidates,
  such as the previous frame's optimum in a sequence) are decoded in one batch and the one whose
  image is closest to the target wins;
- Nelder-Mead (`simplex.py`) minimises the image RMSE E(x) = RMSE(phi(x), t) (0-255 sRGB,
  optionally weighted per pixel by a mask) inside the unit cube, within a budget of evaluations;
- `hybrid` starts Nelder-Mead from the best-of-n guess, `optimize` from a random point (the
  paper's baseline), `nn` stops after best-of-n.

The box: `clip` (default) evaluates phi at the point clipped into the box and adds
PENALTY x (distance outside); `barrier` is the paper's finite barrier (E + BARRIER outside).
Both keep the result inside the box, which is clipped at the end in any case.

Everything per call (weights, target, mask, candidates, random start) travels as arguments of
one jitted function, compiled once per model and settings and reused for every target.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optax

from matfit import images, models, params, simplex
from matfit.errors import FitError
from matfit.methods import Box, Method, Settings

__all__ = ["Box", "FitError", "Method", "Result", "Settings", "fit", "objective", "prepare_mask", "prepare_target"]

PENALTY = 100.0
BARRIER = 1e4
ASPECT_TOLERANCE = 0.01


def distance_outside(x: jax.Array) -> jax.Array:
    """Returns the Euclidean distance from x to the unit cube, with a zero (not NaN) gradient inside it."""
    squared = jnp.sum((x - jnp.clip(x, 0.0, 1.0)) ** 2)
    positive = squared > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)


def objective(x: jax.Array, args: tuple) -> jax.Array:
    """Returns E(x) plus the box term; args = (decoder module, decoder variables, target, weights, box)."""
    decoder, variables, target, weights, box = args
    error = images.rmse(decoder.apply(variables, jnp.clip(x, 0.0, 1.0)), target, weights)
    outside = distance_outside(x)
    if box == Box.barrier:
        return jnp.where(outside > 0, error + BARRIER, error)
    return error + PENALTY * outside


def polish(decoder, variables, target, weights, x: jax.Array, steps: int, rate: float) -> jax.Array:
    """Returns the best point of `steps` projected Adam steps on E from x (x itself if none is better)."""
    tx = optax.adam(rate)
    loss = jax.value_and_grad(lambda y: images.rmse(decoder.apply(variables, y), target, weights))

    def body(_, carry):
        y, state, best, best_value = carry
        value, grad = loss(y)
        better = value < best_value
        best, best_value = jnp.where(better, y, best), jnp.where(better, value, best_value)
        updates, state = tx.update(grad, state, y)
        return jnp.clip(optax.apply_updates(y, updates), 0.0, 1.0), state, best, best_value

    y, _, best, best_value = jax.lax.fori_loop(0, steps, body, (x, tx.init(x), x, jnp.inf))
    last = images.rmse(decoder.apply(variables, y), target, weights)
    return jnp.where(last < best_value, y, best)


@partial(jax.jit, static_argnames=("decoder", "encoders", "settings"))
def _fit(decoder, encoders, settings: Settings, decoder_variables, encoder_variables, target, encoder_target, weights, extra, start):
    guesses = [encoder.apply(variables, encoder_target[None])[0] for encoder, variables in zip(encoders, encoder_variables, strict=True)]
    candidates = jnp.concatenate([jnp.stack(guesses), extra]) if guesses else extra
    candidate_images = decoder.apply(decoder_variables, candidates)
    candidate_errors = images.rmse(candidate_images, target, weights)
    chosen = jnp.argmin(candidate_errors)
    x = candidates[chosen]
    evaluations = jnp.array(0)
    if settings.method != Method.nn:
        y0 = x if settings.method == Method.hybrid else start
        solver = simplex.NelderMead(adaptive=settings.adaptive, initial_step=settings.initial_step)

        def fn(y, args):  # the module and box mode are structure; the data travels in args
            return objective(y, (decoder, *args, settings.box))

        solution = simplex.minimise(fn, y0, (decoder_variables, target, weights), settings.evaluations, solver)
        x = jnp.clip(solution.value, 0.0, 1.0)
        evaluations = solution.stats["evaluations"]
    if settings.polish_steps:
        x = polish(decoder, decoder_variables, target, weights, x, settings.polish_steps, settings.polish_rate)
    image = decoder.apply(decoder_variables, x)
    return {
        "unit": x,
        "image": image,
        "rmse": images.rmse(image, target, weights),
        "candidates": candidates,
        "start_image": candidate_images[chosen],
        "candidate_rmse": candidate_errors,
        "chosen": chosen,
        "evaluations": evaluations,
    }


@dataclass
class Result:
    """What a fit found and how."""

    values: np.ndarray  # physical parameters (19,)
    unit: np.ndarray  # the same on the unit cube
    image: np.ndarray  # phi(x), sRGB (R, R, 3)
    rmse: float  # neural RMSE against the target, 0-255
    start_rmse: float  # RMSE of the best-of-n start
    start: np.ndarray  # unit-cube start chosen by best-of-n
    start_image: np.ndarray  # phi(start), sRGB (R, R, 3)
    chosen: str  # which candidate won best-of-n ("encoder-4", "extra-1", ...)
    candidate_rmse: dict = field(default_factory=dict)
    evaluations: int = 0
    seconds: float = 0.0


def candidate_names(model: models.Model, extra_count: int) -> list[str]:
    """Returns the names of the best-of-n candidates in order: encoders, then extra candidates."""
    return [f"encoder-{arch}" for arch in model.encoders] + [f"extra-{k + 1}" for k in range(extra_count)]


def fit(
    model: models.Model,
    target: np.ndarray,
    settings: Settings | None = None,
    weights: np.ndarray | None = None,
    extra: np.ndarray | None = None,
    seed: int = 0,
) -> Result:
    """Returns the parameters whose decoded image best matches `target`.

    target: sRGB (R, R, 3) in [0, 1] at the model's resolution (`prepare_target`); weights: (R, R)
    per-pixel weights (a mask) or None; extra: unit-cube candidates (k, 19) joining best-of-n;
    seed: draws the random start of `optimize` (data, not a setting: no recompilation).
    """
    settings = settings or Settings()
    settings.check()
    side = model.resolution
    target = np.asarray(target, np.float32)
    if target.shape != (side, side, 3):
        raise FitError(f"the target is {target.shape}, the model needs ({side}, {side}, 3): resample it with prepare_target")
    weights = np.ones((side, side), np.float32) if weights is None else np.asarray(weights, np.float32)
    if weights.shape != (side, side) or not np.all(np.isfinite(weights)) or weights.min() < 0 or weights.sum() <= 0:
        raise FitError("the mask must be (R, R) finite non-negative weights, not all zero: paint some of it white")
    extra = np.zeros((0, params.COUNT), np.float32) if extra is None else np.asarray(extra, np.float32).reshape(-1, params.COUNT)
    if not model.encoders and not len(extra) and settings.method != Method.optimize:
        raise FitError("best-of-n needs at least one encoder or extra candidate: use a model with encoders")
    start = np.random.default_rng(seed).uniform(0.0, 1.0, params.COUNT).astype(np.float32)
    encoder_target = models.encoder_input(images.srgb_decode(target))
    started = time.perf_counter()
    out = _fit(
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
    out = jax.device_get(out)
    seconds = time.perf_counter() - started
    names = candidate_names(model, len(extra))
    unit = np.asarray(out["unit"], np.float64)
    chosen = int(out["chosen"])
    return Result(
        values=params.from_unit(unit),
        unit=unit,
        image=np.asarray(out["image"]),
        rmse=float(out["rmse"]),
        start_rmse=float(out["candidate_rmse"][chosen]),
        start=np.asarray(out["candidates"][chosen]),
        start_image=np.asarray(out["start_image"]),
        chosen=names[chosen],
        candidate_rmse=dict(zip(names, map(float, out["candidate_rmse"]), strict=True)),
        evaluations=int(out["evaluations"]),
        seconds=seconds,
    )


def prepare_target(linear: np.ndarray, resolution: int, source: str) -> tuple[np.ndarray, list[str]]:
    """Returns a linear image resampled to the model's square resolution and sRGB-encoded, with warnings."""
    height, width = linear.shape[:2]
    notices = []
    if abs(width / height - 1.0) > ASPECT_TOLERANCE:
        notices.append(
            f"warning: {source} is {width}x{height} (aspect {width / height:.3f}) but the scene is square (1.000): "
            f"it is stretched to {resolution}x{resolution}; crop it to a square for a faithful fit"
        )
    return images.srgb_encode(images.resample(linear, resolution, resolution)), notices


def prepare_mask(linear: np.ndarray, target_shape: tuple[int, int], resolution: int, source: str) -> np.ndarray:
    """Returns per-pixel weights (R, R) from a mask image: white = 1 (fit here), black = 0 (ignore)."""
    if linear.shape[:2] != target_shape:
        raise FitError(
            f"the mask {source} is {linear.shape[1]}x{linear.shape[0]}, the target is {target_shape[1]}x{target_shape[0]}: "
            "make the mask the same size as the target"
        )
    weights = images.srgb_encode(images.resample(linear, resolution, resolution)).mean(axis=2)
    if weights.sum() <= 0:
        raise FitError(f"the mask {source} is black everywhere: paint white where the fit should look")
    return weights
