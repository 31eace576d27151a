"""Plainer materials than a scene fit's descent reached, each kept unless the judge finds the descent's answer closer
by `PLAIN_LEAD` standard errors (`Judge.behind`): its optional lobes turned off and the others re-descended
(`plain`), and a roughness or a shown medium's density near 0 set to 0 (`at_zero`). The descent puts on a lobe to
follow the target's noise as readily as the picture's light, and a lobe whose gradient is 0 at 0 cannot be taken off
by it; roughness 0 is a bound the descent cannot reach (`scene_fit.TRAPS`). Stage 5 of `scene_fit` and
docs/scenes.md#smooth-and-clear.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from matfit import params
from matfit.fitting import refine
from matfit.fitting.scene_judge import Judge

# The lobes a material can do without: an answer's are turned off, the others re-descended, unless the judge finds
# the plainer material behind by `PLAIN_LEAD` standard errors or more (`plain`). The descent puts them on to follow
# the target's noise: the bench's gold knot under the sun (no coat in truth) ended with clearcoat 0.78 at 1.38,
# and with the three off and re-descended came to 0.72 (median over five runs 0.86, against 1.7 without). The red
# knot's coat (0.5 in truth) stays under the studio light; under the sun, whose target is noisier, it went in two
# runs of five with the lobes free from the start, in none of six held (docs/scenes.md#the-lobes-held).
OPTIONAL = ("clearcoat", "sheen", "anisotropic")
PLAIN_LEAD = 2.0  # standard errors, as the test scene's verification decides (`verify.LEAD`)
PLAIN_ZERO = ("roughness", "density")  # a plainer material's bounds (smooth, clear), tried near them (`at_zero`)
NEAR_ZERO = 0.25  # unit cube
OFF = 0.001  # unit cube: a parameter at or under this is at its lower bound (a trap, a lobe that is off)


def plain(
    judge: Judge,
    problem: refine.Problem,
    point: np.ndarray,
    steps: int,
    *,
    seed: int,
    progress: Callable[[int, float], None] | None = None,
) -> tuple[np.ndarray, dict[str, object], list[float]]:
    """Returns (the point, what the stage did, the losses of the steps kept) after trying the `OPTIONAL` lobes that
    `point` (unit cube) holds turned off: all of them together, then (if the judge refused that and more than one
    was on) each alone. Each try sets them to 0 and runs `steps` steps with them held there (seeds from
    refine.SEED + `seed`), and is kept unless `point` is closer by `PLAIN_LEAD` of the difference's standard errors
    (`Judge.behind`): a lobe stays only where the picture measurably asks for it. Of the tries each alone that the
    judge keeps, the closest; all together, once kept, ends the stage."""
    point = np.asarray(point, np.float64)
    on = [name for name in OPTIONAL if point[params.INDEX[name]] > OFF]
    tries = ([tuple(on)] if on else []) + ([(name,) for name in on] if len(on) > 1 else [])
    kept: tuple[float, np.ndarray, tuple[str, ...], list[float]] | None = None
    tried: list[dict[str, object]] = []
    for k, names in enumerate(tries):
        held = tuple(params.INDEX[name] for name in names)
        off = point.copy()
        off[list(held)] = 0.0
        further, losses = refine.descend(
            problem,
            off,
            steps,
            spp=refine.SPP,
            seed=refine.SEED + seed + k * steps,
            progress=progress,
            hold=held,
            held=steps,
        )
        behind, error = judge.behind(params.from_unit(further), params.from_unit(point))
        keep = behind < PLAIN_LEAD * error
        tried.append({"off": list(names), "behind": round(behind, 3), "standard_error": round(error, 3), "kept": keep})
        if keep and (kept is None or behind < kept[0]):
            kept = (behind, further, names, losses)
        if keep and k == 0:
            break
    done: dict[str, object] = {"on": on, "tried": tried, "off": [] if kept is None else list(kept[2])}
    return (point, done, []) if kept is None else (kept[1], done, kept[3])


def at_zero(judge: Judge, point: np.ndarray) -> tuple[np.ndarray, dict[str, object]]:
    """Returns (the point, what the stage did) after trying the `PLAIN_ZERO` parameters that `point` (unit cube) holds
    within `NEAR_ZERO` of 0 (density only where the medium shows) set to 0: all together, then (if refused and more
    than one) each alone; a try is kept unless `point` is closer by `PLAIN_LEAD` standard errors (`Judge.behind`), of
    those each alone the closest. No steps follow: the judge alone decides."""
    point = np.asarray(point, np.float64)
    values = params.from_unit(point)
    shows = params.shows_medium(values)
    near = [n for n in PLAIN_ZERO if 0.0 < point[params.INDEX[n]] <= NEAR_ZERO and (n != "density" or shows)]
    tries = ([tuple(near)] if near else []) + ([(name,) for name in near] if len(near) > 1 else [])
    kept: tuple[float, np.ndarray, tuple[str, ...]] | None = None
    tried: list[dict[str, object]] = []
    for k, names in enumerate(tries):
        zero = point.copy()
        zero[[params.INDEX[name] for name in names]] = 0.0
        behind, error = judge.behind(params.from_unit(zero), values)
        keep = behind < PLAIN_LEAD * error
        tried.append({"zero": list(names), "behind": round(behind, 3), "standard_error": round(error, 3), "kept": keep})
        if keep and (kept is None or behind < kept[0]):
            kept = (behind, zero, names)
        if keep and k == 0:
            break
    done: dict[str, object] = {"near": near, "tried": tried, "zero": [] if kept is None else list(kept[2])}
    return (point if kept is None else kept[1]), done
