"""Mitsuba in the loop: the fit's final candidates rendered with Mitsuba, and the one closest to the target kept.

The optimiser minimises the decoder's error, and where the decoder is wrong (refraction, media)
it can walk to parameters whose physical render is worse than where it started. Verification
renders a few candidates at the model's resolution: the best-of-n start, and the fit's end points
best neural RMSE first. Every candidate is rendered with the same seed (common random numbers),
so their difference is mostly the material's, and the start is always among them. An end point
that beats the start must beat it again in a second render of both with another seed
(`CONFIRM_SEED`): with one render, a lead within the render's noise keeps answers that an
independent judge finds worse than the start (docs/fitting.md#verification).

With `corrections`, the candidates are the start and the best end (CORRECTED_CANDIDATES), and the
better of their renders starts rounds of correction (`correct.py`: the fit run again on the target
less the decoder's error at the point, as its render shows it), each from the last round's point. A
round's residual comes from a render with its own seed (`SEED` + round), so that it does not carry
the last one's noise. The last round's point is the answer if it beats the start in renders of both
with CONFIRM_SEED (which no round used); otherwise the best end, if its lead over the start holds in
a render of it with CONFIRM_SEED too, or else the start. The start is rendered with CONFIRM_SEED
only, unless the rounds start from it (they need its residual): its guard render also decides where
the rounds start, against the ends' renders with SEED: one render fewer. That choice is made
across two seeds, and judges as the start's SEED render would. The rounds' points do not join the
candidates: a candidate's render noise is part of its RMSE, and the 64-spp renders would prefer
worse points. The rules and their measurements: docs/fitting.md#verification and
docs/fitting.md#correction.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from matfit import correct, fit, images, models, params
from matfit.errors import FitError

CANDIDATES = 5  # without correction: the start and up to four end points, every end of the default 4-start fit
# With correction the ends' renders only choose where the rounds start, and the start with the best end alone judges as
# well as all five for three renders fewer (docs/fitting.md#verification).
CORRECTED_CANDIDATES = 2
# 64 spp: the cheapest count whose choices match 128 spp within the judge's noise (`bench.verification_table`; see
# docs/fitting.md#verification).
SPP = 64
SEED = 1_000_003  # not a seed of the training set's images
CONFIRM_SEED = 1_000_033  # the second opinion on an end point's lead; neither SEED nor a training image's seed


@dataclass
class Verified:
    """Which candidate Mitsuba preferred, and the renders' figures."""

    unit: np.ndarray  # the chosen candidate (unit cube)
    rendered: np.ndarray  # its Mitsuba render, sRGB (R, R, 3)
    rmse: float  # its Mitsuba RMSE against the target
    chosen: str  # "start", "end-1", "end-2", ... (end-1: the best neural RMSE), or "corrected-1", ...
    figures: dict[str, float]  # Mitsuba RMSE of the fit's candidates (seed SEED) and of the rounds but the last
    seconds: float
    start_rmse: float  # the start's Mitsuba RMSE in the same render as `rmse` (seed SEED, or CONFIRM_SEED)
    confirmation: dict[str, float] = dataclasses.field(default_factory=dict)  # renders with CONFIRM_SEED
    decoded: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # phi of each correction round's point
    points: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # every candidate rendered (unit cube)
    corrections: int = 0  # rounds of correction run


def candidates(result: fit.Result, count: int = CANDIDATES) -> dict[str, np.ndarray]:
    """Returns the candidates to render, by name: the start, then the fit's distinct end points, best neural first."""
    chosen = {"start": np.asarray(result.start, np.float64)}
    ends = result.ends if result.ends is not None else result.unit[None]
    for k, end in enumerate(ends):
        if len(chosen) == count:
            break
        if all(np.max(np.abs(end - other)) > 1e-6 for other in chosen.values()):
            chosen[f"end-{k + 1}"] = np.asarray(end, np.float64)
    return chosen


def verify(
    renderer,
    result: fit.Result,
    target: np.ndarray,
    weights: np.ndarray | None = None,
    count: int | None = None,
    spp: int = SPP,
    corrections: int = 0,
    model: models.Model | None = None,
) -> Verified:
    """Returns the candidate whose Mitsuba render is closest to the sRGB `target` (weighted like the fit, if a mask is
    given).

    `renderer` renders at the target's resolution; every candidate uses the same seed and `spp` samples.
    `count`: how many candidates (`candidates`) to render; by default CANDIDATES, or CORRECTED_CANDIDATES with
    `corrections`.
    `corrections`: rounds of `correct.step` from the best of the fit's candidates ("corrected-1",
    ...; they need the fit's `model`); the last one's point is kept if it beats the start in renders
    with CONFIRM_SEED (`confirmation`), else the rule of the module docstring chooses. `figures` then
    holds the start only if the rounds started from it.
    """
    check_corrections(corrections)
    if corrections and model is None:
        raise ValueError("correction needs the fit's model")
    started = time.perf_counter()
    weights = np.ones(target.shape[:2], np.float32) if weights is None else np.asarray(weights, np.float32)
    count = (CORRECTED_CANDIDATES if corrections else CANDIDATES) if count is None else count
    pool = candidates(result, count)

    def rendered(name: str, seed: int) -> np.ndarray:
        return images.srgb_encode(renderer.render(params.from_unit(pool[name]), seed=seed, spp=spp))

    confirmation, corrected = {}, {}

    def figure(image: np.ndarray) -> float:
        return float(images.rmse(image, target, weights))

    def confirm(names) -> dict[str, np.ndarray]:
        second = {name: rendered(name, CONFIRM_SEED) for name in names if name not in confirmation}
        confirmation.update({name: figure(image) for name, image in second.items()})
        return second

    def answer(name: str, image: np.ndarray, rmse: float, start_rmse: float) -> Verified:
        seconds = time.perf_counter() - started
        return Verified(
            pool[name], image, rmse, name, figures, seconds, start_rmse, confirmation, corrected, pool, corrections
        )

    if not corrections:
        renders = {name: rendered(name, SEED) for name in pool}
        figures = {name: figure(image) for name, image in renders.items()}
        best = min(figures, key=figures.get)  # the start comes first, so a tie keeps the start
        if best != "start":
            confirm(("start", best))
        chosen = keep(figures, confirmation)
        return answer(chosen, renders[chosen], figures[chosen], figures["start"])
    # The start is rendered with CONFIRM_SEED only: that render guards the rounds' answer, and it also tells whether
    # they start from the best end (its render with SEED is better) or from the start (then rendered with SEED too,
    # for its residual).
    renders = {name: rendered(name, SEED) for name in pool if name != "start"}
    figures = {name: figure(image) for name, image in renders.items()}
    start_image = confirm(("start",))["start"]
    name = min(figures, key=figures.get, default="start")
    if name == "start" or figures[name] >= confirmation["start"]:
        name = "start"
        renders[name] = rendered(name, SEED)
        figures[name] = figure(renders[name])
    # The fit's candidates as verification's rule compares them: the start by its SEED render if the rounds needed one.
    fits = {"start": figures.get("start", confirmation["start"]), **{n: f for n, f in figures.items() if n != "start"}}
    unit, image = pool[name], renders[name]
    decoded = result.decoded(unit)
    decoded = model.decode(unit)[0] if decoded is None else decoded
    for k in range(corrections):  # each round from the last one's point: `correct.py`
        unit, decoded = correct.step(model, target, weights, unit, image, decoded)
        name = f"corrected-{k + 1}"
        pool[name], corrected[name] = unit, decoded
        if k + 1 < corrections:  # the next round's residual, from a render with this round's own seed
            image = renders[name] = rendered(name, SEED + k + 1)
            figures[name] = figure(image)
    second = confirm((name,))
    if confirmation[name] < confirmation["start"]:
        return answer(name, second[name], confirmation[name], confirmation["start"])
    # The rounds lost: verification's rule, every figure of `answer` from CONFIRM_SEED's renders.
    best = min(fits, key=fits.get)  # the start comes first, so a tie keeps the start
    second = confirm((best,)) if best != "start" else {}
    chosen = keep(fits, confirmation)
    image = start_image if chosen == "start" else second[chosen]
    return answer(chosen, image, confirmation[chosen], confirmation["start"])


def prefetch_start(renderer, start: np.ndarray, corrections: int = 0, spp: int = SPP) -> None:
    """Starts, on a `render.Background` or `render.Process`, the render `verify` will make of the fit's start (unit
    cube): with SEED, or with CONFIRM_SEED when rounds of correction will be guarded against it."""
    values = params.from_unit(np.asarray(start, np.float64))  # as `candidates` and `rendered` make them
    renderer.prefetch(values, CONFIRM_SEED if corrections else SEED, spp)


def check_corrections(corrections: int) -> None:
    """Raises FitError unless `corrections` (rounds of correction) is a count."""
    if corrections < 0:
        raise FitError(f"corrections {corrections} must be >= 0: use 0 to skip correction", field="corrections")


def keep(figures: dict[str, float], confirmation: dict[str, float]) -> str:
    """Returns the candidate to keep: the best of `figures` if it is the start or its lead over the start holds in
    `confirmation` (both renders again with another seed), else the start."""
    best = min(figures, key=figures.get)
    if best == "start" or confirmation.get(best, np.inf) < confirmation.get("start", -np.inf):
        return best
    return "start"
