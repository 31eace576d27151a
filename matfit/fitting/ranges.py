"""What the picture decides: per parameter, how far it can move before the picture changes visibly.

Given a decoder phi (unit-cube parameters -> sRGB images), an answer x0, mask weights w and a
threshold tau (RMSE on 0-255 sRGB, the report's unit), the *range* of parameter i is the set of
values v for which some material with x_i = v, the other parameters free to adjust inside the box,
decodes within tau of the answer's picture:

    D(x) = RMSE_w(phi(x), phi(x0)) <= tau.

Linearised (Gauss-Newton), D(x0 + z)^2 ~ z^T H z with H = 255^2 J^T W J / (3 sum w), J the
decoder's Jacobian at x0. Each end of each range is then a small convex problem: the largest
t >= 0 such that min { z^T H z : z_i = +-t, x0 + z in the box } <= tau^2, found by bisection on t
with the box-constrained quadratic solved by coordinate descent (`box_quadratic`). So a parameter
that the picture does not see reaches both faces of the box, and one that other parameters can
compensate gets the range that compensation allows.

The linear answer is then checked against the decoder itself, from inside: each end point (the
moved parameter and the others as the quadratic left them) is taken START of the way from the
answer (an end the linear answer puts on a face of the box is tried there) and decoded; where D
exceeds tau the move shrinks by 0.9 tau / D (unless the correction at least halved D since the
round before: then the move is tried again), where it stays below it grows by tau / D (each
within [1/4, 2], up to the box and below the smallest move refused), and the others are
re-optimised by a Gauss-Newton step with the answer's Jacobian (the chord method) before the next
decode. An end is reported only where a decode found it within
tau (`CHECKS` rounds): the range is the widest move the decoder confirmed, never the linear guess.
So the ends are confirmed, not maximal: each is a material decoded within tau, a range known to lie
within tau, and the parameter may reach further (the furthest end, the others free, is a
non-convex search this does not settle); params.json says so (`ENDS`).
A round decodes only the ends not yet settled (confirmed at the box's face, or confirmed and
refused moves within SETTLED of each other), in batches of CHUNK ends, so one compiled program.

Verdicts (docs/fitting.md#what-the-picture-decides): *free* when the range reaches both faces of the
box (moving the parameter to either end, others adjusted, stays within tau), *decided* when it
spans at most DECIDED_WIDTH of the parameter's range, *partly* otherwise.

Look-alikes: the confirmed end points that moved the material furthest (unit-cube distance), one
per parameter, parameters the picture leaves free last: materials that decode within tau of the
answer yet differ from it most.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeAlias

import jax
import jax.numpy as jnp
import numpy as np

from matfit import documents, images, params, programs, shipped
from matfit.errors import WeightsError

if TYPE_CHECKING:
    from collections.abc import Callable

    import flax.linen as nn
    from jaxtyping import PyTree

    # phi: unit-cube parameters (n, 19) and the decoder's variables -> sRGB images (n, R, R, 3); `Decoding` for a model
    Decode: TypeAlias = Callable[[jax.Array, PyTree], jax.Array]

DECIDED_WIDTH = 0.25  # a range spanning at most a quarter of the parameter's box is "decided"
FACE = 1e-6  # how close (unit cube) a confirmed end must lie to a face of the box for "free"
BISECTIONS = 14  # halvings of the linear end: 1e-4 of the box (the decoder's check refines it)
SWEEPS = 10  # coordinate-descent sweeps of each box-constrained quadratic
CHECKS = 8  # decodes of every end point, with a correction between them: enough that the ends stop moving
SETTLED = 0.005  # unit cube: an end whose confirmed and refused moves lie this close is not decoded again
CHUNK = 19  # ends decoded together: the first round's 38 in two batches, the later rounds' unsettled ones in one or two
START = 0.5  # the decoder's check starts at this share of each linear end and grows (at most 2x a round) from there
HOLD = 0.5  # an end outside tau keeps its move for the next round while its correction at least halves D
GROWTH = 0.9  # a try outside tau is followed by one aimed at this share of tau, the response taken as linear
LOOK_ALIKES = 4
ENDS = "confirmed: each end decodes within threshold_rmse of the answer; the parameter may reach further"
VERDICTS = ("decided", "partly", "free")


@dataclass(frozen=True)
class Decoding:
    """phi for one decoder module as a function of (unit (n, 19), variables): the static part of `measure`.

    A frozen dataclass rather than a closure, like `search.DecodedObjective`: equal for equal modules, so the
    compiled program is reused, and with a faithful repr, so it can be stored (`programs.py`).
    """

    module: nn.Module

    def __call__(self, unit: jax.Array, variables: PyTree) -> jax.Array:
        return self.module.apply(variables, unit)  # type: ignore[return-value]  # a tuple only with `mutable`


@programs.jit(static_argnames=("decode",))
def decoded(decode: Decode, unit: jax.Array, variables: PyTree) -> jax.Array:
    """Returns `decode(unit, variables)` compiled as one program (an eager call compiles each of its operations)."""
    return decode(unit, variables)


@dataclass(frozen=True)
class Ranges:
    """What the picture decides about each parameter of an answer (see the module docstring)."""

    answer: np.ndarray  # unit cube (19,): the answer measured
    low: np.ndarray  # unit cube (19,): the lowest confirmed value of each parameter
    high: np.ndarray  # unit cube (19,): the highest
    verdicts: tuple[str, ...]  # per parameter: "decided", "partly" or "free"
    threshold: float  # tau, RMSE on 0-255 sRGB
    source: str  # where tau comes from, in words
    ends: np.ndarray  # unit cube (19, 2, 19): the confirmed material at each parameter's low and high end
    end_rmse: np.ndarray  # (19, 2): D at those materials
    linear_low: np.ndarray  # unit cube (19,): the linearised answer's ends, before the decoder's check
    linear_high: np.ndarray
    look_alikes: np.ndarray  # unit cube (k, 19)
    look_alike_rmse: np.ndarray  # (k,): their D
    look_alike_moves: tuple[str, ...]  # which end each is, e.g. "roughness high"

    @property
    def physical_low(self) -> np.ndarray:
        """Returns the low ends in physical units (19,)."""
        return params.from_unit(self.low)

    @property
    def physical_high(self) -> np.ndarray:
        """Returns the high ends in physical units (19,)."""
        return params.from_unit(self.high)

    def named(self, verdict: str) -> list[str]:
        """Returns the names of the parameters with `verdict`."""
        return [name for name, v in zip(params.NAMES, self.verdicts, strict=True) if v == verdict]

    def summary(self) -> str:
        """Returns "decided: a, b; free: c, d" (the parameters the picture fixes and those it leaves free)."""
        parts = [
            f"{verdict}: {', '.join(self.named(verdict))}" for verdict in ("decided", "free") if self.named(verdict)
        ]
        return "; ".join(parts) or "every parameter partly decided"

    def document(self) -> dict:
        """Returns the params.json section: per parameter its range in physical units and verdict, the threshold,
        the look-alikes in physical units."""
        low, high = self.physical_low, self.physical_high
        return {
            "threshold_rmse": round(self.threshold, 3),
            "threshold_source": self.source,
            "ends": ENDS,
            "parameters": {
                p.name: {
                    "low": round(float(low[i]), 6),
                    "high": round(float(high[i]), 6),
                    "unit": p.unit,
                    "verdict": self.verdicts[i],
                }
                for i, p in enumerate(params.PARAMETERS)
            },
            "look_alikes": [
                {"move": move, "rmse": round(float(rmse), 3), "params": params.to_mapping(params.from_unit(unit))}
                for move, rmse, unit in zip(self.look_alike_moves, self.look_alike_rmse, self.look_alikes, strict=True)
            ],
        }


def verdicts_of(low: np.ndarray, high: np.ndarray) -> tuple[str, ...]:
    """Returns each parameter's verdict from its unit-cube range (module docstring)."""
    out = []
    for lo, hi in zip(np.asarray(low), np.asarray(high), strict=True):
        if lo <= FACE and hi >= 1.0 - FACE:
            out.append("free")
        elif hi - lo <= DECIDED_WIDTH:
            out.append("decided")
        else:
            out.append("partly")
    return tuple(out)


def box_quadratic(
    hessian: jax.Array, linear: jax.Array, z: jax.Array, low: jax.Array, high: jax.Array, fixed: jax.Array
) -> jax.Array:
    """Returns z minimising z^T H z + 2 b^T z over low <= z <= high, the coordinates where `fixed` (bool (19,)) is
    true held, by coordinate descent from z.

    A coordinate the quadratic does not see (H_jj = 0) stays where it is.
    """

    def sweep(_: jax.Array, z: jax.Array) -> jax.Array:
        for j in range(z.shape[0]):  # unrolled: one loop iteration per sweep costs far less than one per coordinate
            curvature = hessian[j, j]
            slope = hessian[j] @ z + linear[j]
            moved = jnp.clip(z[j] - slope / jnp.where(curvature > 0, curvature, 1.0), low[j], high[j])
            keep = fixed[j] | (curvature <= 0)
            z = z.at[j].set(jnp.where(keep, z[j], moved))
        return z

    return jax.lax.fori_loop(0, SWEEPS, sweep, z)


def _linear_end(
    hessian: jax.Array, low: jax.Array, high: jax.Array, index: jax.Array, sign: jax.Array, threshold: jax.Array
) -> jax.Array:
    """Returns the point z (relative to the answer) at the linearised end of parameter `index` in direction `sign`."""
    count = low.shape[0]
    bound = jnp.where(sign > 0, high[index], -low[index])
    zero = jnp.zeros(count, hessian.dtype)

    def profile(t: jax.Array, z: jax.Array) -> tuple[jax.Array, jax.Array]:
        z = z.at[index].set(sign * t)
        z = box_quadratic(hessian, zero, z, low, high, jnp.arange(count) == index)
        return z, z @ hessian @ z

    z_full, cost_full = profile(bound, zero)

    def halve(_: jax.Array, carry: tuple[jax.Array, jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array, jax.Array]:
        below, above, z_below = carry
        middle = 0.5 * (below + above)
        z, cost = profile(middle, z_below)
        inside = cost <= threshold**2
        return jnp.where(inside, middle, below), jnp.where(inside, above, middle), jnp.where(inside, z, z_below)

    _, _, z_bisected = jax.lax.fori_loop(0, BISECTIONS, halve, (jnp.zeros((), hessian.dtype), bound, zero))
    return jnp.where(cost_full <= threshold**2, z_full, z_bisected)


def _directions(count: int, dtype: np.dtype) -> tuple[np.ndarray, np.ndarray]:
    """Returns (parameter, sign) of every end: each parameter's low end (-1), then its high end (+1). NumPy, not
    JAX: outside a compiled program a JAX operation is compiled on its own in every new process."""
    return np.repeat(np.arange(count, dtype=np.int32), 2), np.tile(np.array([-1.0, 1.0], dtype), count)


@programs.jit(static_argnames=("decode",))
def _linearise(decode: Decode, variables: PyTree, answer: jax.Array, weights: jax.Array) -> dict[str, jax.Array]:
    """Returns the answer's picture, the decoder's Jacobian there, the Gauss-Newton Hessian and its scale."""
    picture = decode(answer[None], variables)[0]
    jacobian = jax.jacfwd(lambda x: decode(x[None], variables)[0])(answer)  # (R, R, 3, 19)
    scale = 255.0**2 / (3.0 * jnp.sum(weights))
    weighted = jacobian * weights[:, :, None, None]
    hessian = scale * jnp.einsum("hwcj,hwck->jk", weighted, jacobian)
    return {"picture": picture, "jacobian": jacobian, "hessian": hessian, "scale": scale}


@programs.jit
def _linear_ends(hessian: jax.Array, answer: jax.Array, threshold: jax.Array) -> jax.Array:
    """Returns the linearised answer's end points relative to the answer (2 * 19, 19; `_directions`' order).

    A program of its own, apart from the decoder's: it depends on no model, so one compiled program serves them all.
    """
    count = answer.shape[0]
    indices, signs = _directions(count, answer.dtype)
    return jax.vmap(lambda i, s: _linear_end(hessian, -answer, 1.0 - answer, i, s, threshold))(indices, signs)


@programs.jit(static_argnames=("decode",))
def _check(
    decode: Decode,
    variables: PyTree,
    answer: jax.Array,
    linear: dict[str, jax.Array],
    weights: jax.Array,
    threshold: jax.Array,
    ends: jax.Array,
    moves: jax.Array,
    best_move: jax.Array,
    refused: jax.Array,
    indices: jax.Array,
    signs: jax.Array,
    previous: jax.Array,
) -> dict[str, jax.Array]:
    """One round of the decoder's check of the ends given (n of them; `indices`, `signs` say which): decodes them,
    keeps the widest move confirmed within tau (`best_move`) and the narrowest refused, and returns the next tries,
    the others corrected by a Gauss-Newton step with the answer's Jacobian (the chord method).

    An end outside tau whose D is at most HOLD times its D of the round before (`previous`) is held: its move is
    tried again, corrected, rather than refused, since the correction, not the move, is what is still wrong."""
    count = answer.shape[0]
    picture, jacobian, hessian = linear["picture"], linear["jacobian"], linear["hessian"]
    low, high = -answer, 1.0 - answer
    bounds = jnp.where(signs > 0, high[indices], -low[indices])
    decoded = decode(answer[None] + ends, variables)
    rmse = images.rmse(decoded, picture[None], weights)
    inside = rmse <= threshold
    hold = ~inside & (rmse <= HOLD * previous)
    better = inside & (moves >= best_move)
    refused = jnp.where(inside | hold, refused, jnp.minimum(refused, moves))
    best_move = jnp.where(better, moves, best_move)
    # within tau the next try aims at tau itself (the response taken as linear in the move); beyond it, a little inside
    ratio = jnp.clip(jnp.where(inside, 1.0, GROWTH) * threshold / jnp.maximum(rmse, 1e-6), 1.0 / 4.0, 2.0)
    # the next try lies between the widest confirmed move and the narrowest refused one
    new_moves = jnp.clip(moves * ratio, best_move, jnp.minimum(refused, bounds))
    new_moves = jnp.where(new_moves >= refused, 0.5 * (best_move + refused), new_moves)
    new_moves = jnp.where(hold, moves, new_moves)
    residual = (decoded - picture[None]) * weights[None, :, :, None]
    gradients = linear["scale"] * jnp.einsum("nhwc,hwcj->nj", residual, jacobian)

    def correct(z: jax.Array, gradient: jax.Array, index: jax.Array, sign: jax.Array, move: jax.Array) -> jax.Array:
        step = jnp.zeros_like(z).at[index].set(sign * move - z[index])
        linear_term = gradient + hessian @ step  # the chord model of the residual after the parameter's move
        held = jnp.arange(count) == index
        step = step + box_quadratic(hessian, linear_term, jnp.zeros_like(z), low - z - step, high - z - step, held)
        return z + step

    return {
        "rmse": rmse,
        "better": better,
        "best_move": best_move,
        "refused": refused,
        "ends": jax.vmap(correct)(ends, gradients, indices, signs, new_moves),
        "moves": new_moves,
    }


def chunks(active: np.ndarray) -> list[np.ndarray]:
    """Returns `active` (end numbers) in batches of CHUNK, the last padded by repeating its first end: one compiled
    program checks every batch of every round."""
    out = []
    for start in range(0, active.size, CHUNK):
        part = active[start : start + CHUNK]
        out.append(np.concatenate([part, np.full(CHUNK - part.size, part[0])]))
    return out


def _checked(
    decode: Decode,
    variables: PyTree,
    answer: np.ndarray,
    linear: dict[str, np.ndarray],
    weights: np.ndarray,
    threshold: np.float32,
) -> dict[str, np.ndarray]:
    """Returns the decoder's check of the linearised ends (`linear`: `_linearise`'s and `_linear_ends`'): CHECKS
    rounds of `_check` over the ends not yet settled, each end's widest move confirmed within tau, its material and
    D there.

    An end is settled, and no longer decoded, once its move is confirmed at the face of the box or the widest
    confirmed and the narrowest refused move lie within SETTLED of each other: later rounds only try moves
    between those two, so they could change the range by less than SETTLED.
    """
    count = answer.shape[0]
    indices, signs = _directions(count, answer.dtype)
    bounds = np.where(signs > 0, 1.0 - answer[indices], answer[indices]).astype(answer.dtype)
    ends = np.asarray(linear["ends"], answer.dtype)
    at_face = np.abs(ends[np.arange(2 * count), indices]) >= bounds - FACE
    ends = ends * np.where(at_face, 1.0, START)[:, None]  # from inside, where the corrections hold; "free" tried as is
    moves = np.abs(ends[np.arange(2 * count), indices])
    best_move, best_rmse = np.zeros_like(moves), np.zeros_like(moves)
    best_point = np.zeros_like(ends)
    refused = np.full_like(moves, np.inf)
    previous = np.full_like(moves, np.inf)
    active = np.arange(2 * count)
    around = {name: linear[name] for name in ("picture", "jacobian", "hessian", "scale")}  # what `_check` reads
    for _ in range(CHECKS):
        batches = []
        for take in chunks(active):
            state = (
                ends[take],
                moves[take],
                best_move[take],
                refused[take],
                indices[take],
                signs[take],
                previous[take],
            )
            batches.append(jax.device_get(_check(decode, variables, answer, around, weights, threshold, *state)))
        out = {k: np.concatenate([b[k] for b in batches])[: active.size] for k in batches[0]}
        better = out["better"]
        best_point[active[better]] = ends[active[better]]
        best_rmse[active[better]] = out["rmse"][better]
        best_move[active], refused[active] = out["best_move"], out["refused"]
        ends[active], moves[active] = out["ends"], out["moves"]
        previous[active] = out["rmse"]
        settled = (best_move[active] >= bounds[active] - FACE) | (refused[active] - best_move[active] <= SETTLED)
        active = active[~settled]
        if not active.size:
            break
    return {
        "moves": best_move.reshape(count, 2),
        "points": (answer[None] + best_point).reshape(count, 2, count),
        "rmse": best_rmse.reshape(count, 2),
        "linear": np.abs(linear["ends"][np.arange(2 * count), indices]).reshape(count, 2),
    }


def measure(
    decode: Decode,
    variables: PyTree,
    answer: np.ndarray,
    weights: np.ndarray | None,
    threshold: float,
    source: str = "given",
) -> Ranges:
    """Returns what the picture decides about each parameter of `answer` (unit cube (19,)), by the module docstring.

    `decode(unit (n, 19), variables)` returns sRGB images (n, R, R, 3) (`Decoding` for a model's decoder);
    `weights`: the fit's mask (R, R), or None; `threshold`: tau, RMSE on 0-255 sRGB; `source`: where tau comes
    from, recorded with it.
    """
    answer = np.clip(np.asarray(answer, np.float32), 0.0, 1.0)
    if answer.shape != (params.COUNT,):
        raise ValueError(f"Shape mismatch: got {answer.shape}, expected ({params.COUNT},).")
    if not threshold > 0:
        raise ValueError(f"the threshold {threshold} must be > 0")
    if weights is None:
        # the picture's side, decoded by a stored program: an eager decode, or tracing it, costs every new process
        side = np.shape(decoded(decode, answer[None], variables))[1]
        weights = np.ones((side, side), np.float32)
    weights, tau = np.asarray(weights, np.float32), np.float32(threshold)
    linear = _linearise(decode, variables, answer, weights)
    linear = jax.device_get({**linear, "ends": _linear_ends(linear["hessian"], answer, tau)})
    out = _checked(decode, variables, answer, linear, weights, tau)
    moves = np.asarray(out["moves"], np.float64)
    low, high = answer - moves[:, 0], answer + moves[:, 1]
    low, high = np.clip(low, 0.0, 1.0), np.clip(high, 0.0, 1.0)
    low[answer - moves[:, 0] <= FACE] = 0.0
    high[answer + moves[:, 1] >= 1.0 - FACE] = 1.0
    verdicts = verdicts_of(low, high)
    points = np.clip(np.asarray(out["points"], np.float64), 0.0, 1.0)
    linear = np.asarray(out["linear"], np.float64)
    chosen = look_alikes(points, np.asarray(answer, np.float64), verdicts)
    return Ranges(
        answer=np.asarray(answer, np.float64),
        low=low,
        high=high,
        verdicts=verdicts,
        threshold=float(threshold),
        source=source,
        ends=points,
        end_rmse=np.asarray(out["rmse"], np.float64),
        linear_low=np.clip(answer - linear[:, 0], 0.0, 1.0),
        linear_high=np.clip(answer + linear[:, 1], 0.0, 1.0),
        look_alikes=np.array([points[i, side] for i, side in chosen]).reshape(-1, params.COUNT),
        look_alike_rmse=np.array([out["rmse"][i][side] for i, side in chosen], np.float64),
        look_alike_moves=tuple(f"{params.NAMES[i]} {('low', 'high')[side]}" for i, side in chosen),
    )


def look_alikes(
    points: np.ndarray, answer: np.ndarray, verdicts: tuple[str, ...], count: int = LOOK_ALIKES
) -> list[tuple[int, int]]:
    """Returns [(parameter, 0 low / 1 high)] of the `count` end points furthest from the answer (unit cube),
    one per parameter, parameters the picture leaves free after the others."""
    distance = np.linalg.norm(points - answer[None, None], axis=-1)  # (19, 2)
    order = sorted(
        ((i, side) for i in range(len(verdicts)) for side in (0, 1) if distance[i, side] > FACE),
        key=lambda end: (verdicts[end[0]] == "free", -distance[end]),
    )
    chosen, seen = [], set()
    for i, side in order:
        if i not in seen:
            chosen.append((i, side))
            seen.add(i)
        if len(chosen) == count:
            break
    return chosen


EVALUATION = "evaluation.json"  # a model directory's card (`model.evaluate`): the decoder's error against Mitsuba
KINDS = ("transmissive", "scattering", "opaque")  # the card's kinds of material, each with its own figures
STATISTIC = "mean"  # which of the card's figures is tau: the decoder's mean error on the answer's kind of material
STATISTICS = {"mean": "mean", "median": "median", "p95": "95th-percentile"}  # the card's figures, in words


def read_card(model_directory: str) -> tuple[dict, str]:
    """Returns (the card, its path): the model's evaluation.json, or the shipped model's when the model has none.

    WeightsError (one line naming the file and the fix) unless it is a JSON object (`documents.read`: a regular file
    of at most 1 MB) whose "decoder_rmse" and every "decoder_rmse_<kind>" it has hold each statistic as a finite
    positive number: a card that is empty, a list, a string, NaN, 0 or negative would be a threshold that decides
    nothing (a traceback on every fit before).
    """
    path = os.path.join(model_directory, EVALUATION)
    if not os.path.lexists(path):
        path = os.path.join(str(shipped.MODEL), EVALUATION)
    if os.path.dirname(path) == os.path.normpath(model_directory):
        fix = f"write it again with `matfit evaluate --model {model_directory} --card`, or delete it"
    else:
        fix = "install matfit again (the shipped model's card is damaged)"
    card = documents.read(path, fix, WeightsError)
    if not isinstance(card, dict):
        raise WeightsError(f'{path} must hold a JSON object with "decoder_rmse": {fix}')
    for key in ["decoder_rmse", *(f"decoder_rmse_{kind}" for kind in KINDS)]:
        if key != "decoder_rmse" and not card.get(key):  # no references of that kind: `threshold` uses all
            continue
        figures = card.get(key)
        for statistic in STATISTICS:
            value = figures.get(statistic) if isinstance(figures, dict) else None
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < math.inf:
                shown = "missing" if value is None else json.dumps(value)[:40]
                raise WeightsError(f"{path}: {key}.{statistic} is {shown}, not a positive RMSE: {fix}")
    return card, path


def threshold(model_directory: str, unit: np.ndarray, *, statistic: str = STATISTIC) -> tuple[float, str]:
    """Returns (tau, its source in words): the decoder's RMSE against Mitsuba references on the answer's kind of
    material, its `statistic` over those references, from the model's evaluation.json (the shipped model's when the
    model has none).

    The kinds are the card's: transmissive (spec_trans >= 0.5), scattering (transmissive with scattering >= 0.5
    and density >= 1), opaque (the rest). A difference the decoder cannot tell from its own error is not visible to
    the fit (docs/fitting.md#what-the-picture-decides); `bench-ranges` calibrates the ranges with each statistic.
    """
    if statistic not in STATISTICS:
        raise ValueError(f"unknown statistic {statistic!r}: use one of {', '.join(STATISTICS)}")
    values = params.from_unit(np.asarray(unit, np.float64))
    kind = "opaque"
    if values[params.INDEX["spec_trans"]] >= 0.5:
        dense = values[params.INDEX["scattering"]] >= 0.5 and values[params.INDEX["density"]] >= 1.0
        kind = "scattering" if dense else "transmissive"
    card, path = read_card(model_directory)
    if not card.get(f"decoder_rmse_{kind}"):  # a card without such references: every material's error
        kind = "all"
    figure = float(card["decoder_rmse" if kind == "all" else f"decoder_rmse_{kind}"][statistic])
    where = "this model's" if os.path.dirname(path) == os.path.normpath(model_directory) else "the shipped model's"
    return figure, f"{where} {STATISTICS[statistic]} decoder RMSE against Mitsuba on {kind} materials ({EVALUATION})"
