"""A descent's answer and the stages that descend again from it (stages 3 and 4 of `scene_fit`, docs/scenes.md): of a
descent's visited points, the one the judge finds closest (`closest`, `ending`); a transmissive fit's chosen start
descending again with other step seeds (`again`); and the bounds the gradient cannot leave, tried inward
(`off_bounds`). Every choice is the judge's (`scene_judge.Judge.squared`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from matfit import params
from matfit.fitting import refine, scene_plain
from matfit.fitting.scene_judge import Judge, root

INWARD = (0.1, 0.25)  # unit-cube distances from a bound that the judge tries for a parameter the descent left there
# The bounds the descent cannot leave by its gradient: sheen and clearcoat at 0 (Mitsuba does not evaluate a lobe
# of weight 0, so their derivative there is 0) and roughness at 0 (a near-mirror lobe's gradient, its directions
# sampled detached, is valid only in expectation and very noisy: `refine`'s docstring). Elsewhere at a bound the
# gradient is valid, and a move there that the judge favours is the target's noise (measured: spec_tint moved off 0
# on the glass knot, closer to the picture at two seeds, further from the truth, 1.78 -> 2.32).
TRAPS = ("roughness", "sheen", "clearcoat")
# A transmissive fit's chosen start descends this many more times from its short run's point, each with other step
# seeds (`SEEDS_APART` apart), and the judge picks among the descents' answers and their mean (`again`): one start's
# descents of the jade knot ended 1.0-4.5 apart by the bench (docs/scenes.md#the-chosen-start-descending-again)
AGAIN = 2
# ... and where its steps render a channel a render (`refine.step_image`), whose descents scatter less
AGAIN_BY_CHANNEL = 1
SEEDS_APART = 1000


def closest(judge: Judge, points: list[np.ndarray], losses: list[float]) -> tuple[np.ndarray, float]:
    """Returns (the descent's answer, its `Judge.squared`): of the visited point of lowest step loss, the last point
    and the mean of the last quarter's points (unit cube, `refine.path`'s), the one whose noise-free error at two
    seeds is lowest. A held step's loss is Huber's, lower than the squares, and counts: sought among the squares'
    steps alone, the red knot under the sun lost its coat in three runs of six (docs/scenes.md#the-lowest-step)."""
    if not losses:
        return points[0], judge.squared(params.from_unit(points[0]))
    candidates = [points[int(np.argmin(losses))], points[-1], ending(points)]
    judged = [judge.squared(params.from_unit(p)) for p in candidates]
    kept = int(np.argmin(judged))
    return candidates[kept], judged[kept]


def again(
    judge: Judge,
    problem: refine.Problem,
    chosen: dict[str, Any],
    steps: int,
    *,
    seed: int,
    hold: tuple[int, ...],
    held: int,
    progress: Callable[[int, float], None] | None = None,
    times: int = AGAIN,
) -> tuple[np.ndarray, list[float], dict[str, object]]:
    """Returns (the answer, its descent's step losses, what the stage did) after the `chosen` start (`fit`'s entry:
    its short run's `point`, its descent's `answer`, `answer_squared` and `more` losses) descends `times` more times
    from the same point, `steps` steps with seeds from `seed` + k `SEEDS_APART` and its hold, each answer by `closest`:
    of the descents' answers and their mean (unit cube), the one of lowest noise-free error (`Judge.squared`).

    Where the loss lies flat at its noise, one start's descent ends where its steps' seeds take it: the jade knot's
    three descents from one point ended 1.0-4.5 apart by the bench, their mean often closer than each; where they end
    in other valleys the mean is far off, and the judge keeps the closest answer (docs/scenes.md)."""
    answers = [(np.asarray(chosen["answer"]), float(chosen["answer_squared"]), list(chosen["more"]))]
    for k in range(1, times + 1):
        points, losses = refine.path(
            problem,
            np.asarray(chosen["point"]),
            steps,
            spp=refine.SPP,
            seed=seed + k * SEEDS_APART,
            progress=progress,
            hold=hold,
            held=held,
        )
        point, squared = closest(judge, points, losses)
        answers.append((point, squared, losses))
    mean = np.clip(np.mean([a[0] for a in answers], axis=0), 0.0, 1.0)
    answers.append((mean, judge.squared(params.from_unit(mean)), answers[0][2]))
    kept = int(np.argmin([a[1] for a in answers]))
    names = [*(f"descent {k + 1}" for k in range(times + 1)), "mean"]
    done: dict[str, object] = {
        "start": chosen["name"],
        "errors": {name: round(root(a[1]), 3) for name, a in zip(names, answers, strict=True)},
        "kept": names[kept],
    }
    return answers[kept][0], answers[kept][2], done


def ending(points: list[np.ndarray]) -> np.ndarray:
    """Returns the mean of the last quarter of a descent's points (unit cube): where it ends, its steps' noise
    averaged."""
    return np.mean(points[-max(1, len(points) // 4) :], axis=0)


def off_bounds(
    judge: Judge,
    problem: refine.Problem,
    point: np.ndarray,
    steps: int,
    *,
    seed: int,
    progress: Callable[[int, float], None] | None = None,
) -> tuple[np.ndarray, dict[str, object], list[float]]:
    """Returns (the point, what the stage did, the losses of its steps) after trying each of `TRAPS` that `point`
    (unit cube) leaves at 0 moved inward by `INWARD`: the try of lowest noise-free error (`Judge.squared`), if
    lower than `point`'s, goes on for `steps` steps (seeds from refine.SEED + `seed`), and of the three points the
    one of lowest noise-free error is returned."""
    point = np.asarray(point, np.float64)
    base = judge.squared(params.from_unit(point))
    tries = []
    for name in TRAPS:
        i = params.INDEX[name]
        if point[i] > scene_plain.OFF:
            continue
        for distance in INWARD:
            moved = point.copy()
            moved[i] = distance
            tries.append((judge.squared(params.from_unit(moved)), name, float(moved[i]), moved))
    done: dict[str, object] = {"error": round(root(base), 3), "tried": len(tries), "moved": None}
    if not tries or min(t[0] for t in tries) >= base:
        return point, done, []
    judged, name, value, moved = min(tries, key=lambda t: t[0])
    further, losses = refine.descend(problem, moved, steps, spp=refine.SPP, seed=refine.SEED + seed, progress=progress)
    three = [base, judged, judge.squared(params.from_unit(further))]
    kept = int(np.argmin(three))
    done.update({"moved": name, "to": round(value, 3), "errors": [round(root(e), 3) for e in three]})
    done["kept"] = ("the descent's point", "the moved point", "the steps after it")[kept]
    return (point, moved, further)[kept], done, losses
