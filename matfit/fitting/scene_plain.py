"""Plainer materials than a scene fit's descent reached, each kept unless the judge finds the descent's answer closer
by `PLAIN_LEAD` standard errors (`Judge.behind`): its optional lobes turned off and the others re-descended
(`plain`), and a roughness or a shown medium's density near 0 set to 0 (`at_zero`). The descent puts on a lobe to
follow the target's noise as readily as the picture's light, and a lobe whose gradient is 0 at 0 cannot be taken off
by it; roughness 0 is a bound the descent cannot reach (`scene_descent.TRAPS`). Stage 5 of `scene_fit` and
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


def silent(values: np.ndarray) -> tuple[str, ...]:
    """Returns the `OPTIONAL` lobes that cannot show in physical `values`: sheen, part of Mitsuba's diffuse lobe
    (weighted by 1 - metallic, absent once spec_trans is 1), on a full metal or through full transmission. Its
    gradient there is 0, so the descent leaves it where it started (the bench's gold knots: sheen 0.2 in every
    answer), and a try turning it off changes nothing the judge can see."""
    diffuse = (1.0 - values[params.INDEX["metallic"]]) * (1.0 - values[params.INDEX["spec_trans"]])
    return ("sheen",) if diffuse <= 0.0 else ()


# (k, the names of the parameters a try changes) -> (the try's point, unit cube; the losses of its steps)
Make = Callable[[int, tuple[str, ...]], tuple[np.ndarray, list[float]]]


def plainer(
    judge: Judge, point: np.ndarray, names: list[str], make: Make, key: str
) -> tuple[tuple[np.ndarray, tuple[str, ...], list[float]] | None, list[dict[str, object]]]:
    """Returns (the try kept: its point, the names it changed, its steps' losses; None where the judge kept none, the
    record of each try, its names under `key`) of `names` changed from `point` (unit cube) by `make`: all of them
    together, then (if the judge refused that and there is more than one) each alone. A try is kept unless `point`
    is closer by `PLAIN_LEAD` of the difference's standard errors (`Judge.behind`); of those each alone the closest;
    all together, once kept, ends the tries."""
    values = params.from_unit(point)
    tries = ([tuple(names)] if names else []) + ([(name,) for name in names] if len(names) > 1 else [])
    kept: tuple[float, np.ndarray, tuple[str, ...], list[float]] | None = None
    tried: list[dict[str, object]] = []
    for k, changed in enumerate(tries):
        candidate, losses = make(k, changed)
        behind, error = judge.behind(params.from_unit(candidate), values)
        keep = behind < PLAIN_LEAD * error
        tried.append({key: list(changed), "behind": round(behind, 3), "standard_error": round(error, 3), "kept": keep})
        if keep and (kept is None or behind < kept[0]):
            kept = (behind, candidate, changed, losses)
        if keep and k == 0:
            break
    return (None if kept is None else kept[1:]), tried


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
    `point` (unit cube) holds turned off (`plainer`): each try sets them to 0 and runs `steps` steps with them held
    there (seeds from refine.SEED + `seed`). A lobe stays only where the picture measurably asks for it. A lobe that
    cannot show (`silent`) is turned off first, without a try: such a try read the same as the answer, give or take
    its steps' noise, and as the closest of the tries each alone it was the one kept over a lobe that shows (the
    gold knot under the sun: sheen off -0.64 kept, anisotropy off 0.34 +- 1.45 left on)."""
    point = np.asarray(point, np.float64).copy()
    mute = [name for name in silent(params.from_unit(point)) if point[params.INDEX[name]] > OFF]
    point[[params.INDEX[name] for name in mute]] = 0.0
    on = [name for name in OPTIONAL if point[params.INDEX[name]] > OFF]

    def off(k: int, names: tuple[str, ...]) -> tuple[np.ndarray, list[float]]:
        held = tuple(params.INDEX[name] for name in names)
        start = point.copy()
        start[list(held)] = 0.0
        seed_k = refine.SEED + seed + k * steps
        return refine.descend(
            problem, start, steps, spp=refine.SPP, seed=seed_k, progress=progress, hold=held, held=steps
        )

    kept, tried = plainer(judge, point, on, off, "off")
    done: dict[str, object] = {"on": on, "silent": mute, "tried": tried, "off": [] if kept is None else list(kept[1])}
    return (point, done, []) if kept is None else (kept[0], done, kept[2])


def at_zero(judge: Judge, point: np.ndarray) -> tuple[np.ndarray, dict[str, object]]:
    """Returns (the point, what the stage did) after trying the `PLAIN_ZERO` parameters that `point` (unit cube) holds
    within `NEAR_ZERO` of 0 (density only where the medium shows) set to 0 (`plainer`). No steps follow: the judge
    alone decides."""
    point = np.asarray(point, np.float64)
    shows = params.shows_medium(params.from_unit(point))
    near = [n for n in PLAIN_ZERO if 0.0 < point[params.INDEX[n]] <= NEAR_ZERO and (n != "density" or shows)]

    def zero(k: int, names: tuple[str, ...]) -> tuple[np.ndarray, list[float]]:
        moved = point.copy()
        moved[[params.INDEX[name] for name in names]] = 0.0
        return moved, []

    kept, tried = plainer(judge, point, near, zero, "zero")
    done: dict[str, object] = {"near": near, "tried": tried, "zero": [] if kept is None else list(kept[1])}
    return (point if kept is None else kept[0]), done
