"""Mitsuba in the loop: the fit's final candidates rendered with Mitsuba, and the one closest to the target kept.

The optimiser minimises the decoder's error, and where the decoder is wrong (refraction, media)
it can walk to parameters whose physical render is worse than where it started. Verification
renders a few candidates at the model's resolution: the best-of-n start, and the fit's end points
best neural RMSE first (with `corrections`: the start, the best end and the last round of
correction, `correct.py`). The start is always among them.

The rule. Each candidate is rendered in batches of BATCH_SPP samples; batch j of every candidate uses
the seed BATCH_SEED + j (common random numbers: the candidates' noise is alike, so their
difference is mostly the material's). From m batches R_1..R_m of a candidate, the mean over pairs
i != j of the weighted mean of (R_i - t)(R_j - t) estimates, without bias, the squared error of
its noise-free render against the target t: a render's own noise, which a single render's RMSE
counts and which favours the less noisy material, cancels between independent batches. The
candidate with the lowest estimate leads (the start first, so a tie keeps the start). For every
other candidate, the paired difference of its estimate and the leader's, over their common
batches, has a standard error from the jackknife over batches. While a candidate is within LEAD
standard errors of the leader, that candidate and the leader get one more batch each, up to
MAX_BATCHES; then the leader is kept. So an answer other than the start is kept only when its
estimate beats the start's, and a lead within the noise is measured again before it decides;
at the cap, a lead too small to resolve is a difference too small to matter at that precision.

Its noise: the standard error of each decision is recorded (`margins`: each other candidate's
deficit behind the kept one, in standard errors). Its cost: BATCHES renders per candidate at
least (the start's are asked for while the fit runs, `prefetch_start`), more only for undecided
pairs.

With `corrections`, the rounds start from the start or the best end (`where_rounds_start`);
round k takes its residual from a render of its starting point with the seed SEED + k - 1, a seed
no batch uses, so that no round carries another's noise and no batch judges the noise a round
was corrected on.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from matfit import images, params
from matfit.fitting import correct, search
from matfit.fitting.methods import check_corrections
from matfit.model import models

if TYPE_CHECKING:
    from collections.abc import Sequence

    from jaxtyping import Float

    from matfit.rendering.engine import Renders

CANDIDATES = 5  # without correction: the start and up to four end points, every end of the default 4-start fit
# With correction the start and the best end choose where the rounds start, and the last round joins them.
CORRECTED_CANDIDATES = 2
SPP = 64  # samples of a round's residual render, and of a render process's renders unless asked otherwise
BATCH_SPP = 64  # samples of one batch
SEED = 1_000_003  # round k's residual render: SEED + k - 1; not a seed of the training set's images
BATCH_SEED = 1_000_033  # batch j of every candidate: BATCH_SEED + j; neither a residual's nor a training image's seed
BATCHES = 3  # batches of every candidate: the fewest with which the jackknife says how far to trust a difference
MAX_BATCHES = 8  # the most batches of a candidate whose difference from the leader stays within LEAD standard errors
LEAD = 2.0  # standard errors by which a difference is decided without more batches


@dataclass(frozen=True)
class Verified:
    """Which candidate Mitsuba preferred, and the figures of the decision."""

    unit: Float[np.ndarray, " 19"]  # the chosen candidate (unit cube)
    rendered: Float[np.ndarray, "R R 3"]  # its Mitsuba render, sRGB (R, R, 3): the mean of its batches
    rmse: float  # its estimated noise-free Mitsuba RMSE against the target
    chosen: str  # "start", "end-1", "end-2", ... (end-1: the best neural RMSE), or "corrected-1", ...
    figures: dict[str, float]  # every candidate's estimated noise-free Mitsuba RMSE
    seconds: float
    start_rmse: float  # the start's estimated noise-free Mitsuba RMSE
    batches: dict[str, int] = dataclasses.field(default_factory=dict)  # batches rendered of each candidate
    margins: dict[str, float] = dataclasses.field(default_factory=dict)  # each other's deficit, in standard errors
    decoded: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # phi of each correction round's point
    points: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # every candidate rendered (unit cube)
    corrections: int = 0  # rounds of correction run
    renders: list[np.ndarray] = dataclasses.field(default_factory=list)  # the chosen one's batches (sRGB), in order


def candidates(result: search.Result, *, count: int = CANDIDATES) -> dict[str, Float[np.ndarray, " 19"]]:
    """Returns the candidates to render, by name: the start, then the fit's distinct end points, best neural first."""
    chosen = {"start": np.asarray(result.start, np.float64)}
    ends = result.ends if result.ends is not None else result.unit[None]
    for k, end in enumerate(ends):
        if len(chosen) == count:
            break
        if all(np.max(np.abs(end - other)) > 1e-6 for other in chosen.values()):
            chosen[f"end-{k + 1}"] = np.asarray(end, np.float64)
    return chosen


def verify_candidates(
    renderer: Renders,
    result: search.Result,
    target: Float[np.ndarray, "R R 3"],
    *,
    weights: Float[np.ndarray, "R R"] | None = None,
    count: int = CANDIDATES,
    spp: int = BATCH_SPP,
) -> Verified:
    """Returns the candidate whose noise-free Mitsuba render is estimated closest to the sRGB `target` (weighted like
    the fit, if a mask is given), by the rule of the module docstring: the verification stage without correction.

    `renderer` renders at the target's resolution; every batch has `spp` samples.
    `count`: how many of the fit's candidates (`candidates`) to render.
    """
    started = time.perf_counter()
    pool = candidates(result, count=count)
    return judge(renderer, pool, list(pool), {}, target, as_weights(target, weights), spp=spp, started=started)


def correct_then_verify(
    renderer: Renders,
    result: search.Result,
    target: np.ndarray,
    *,
    model: models.Model,
    corrections: int,
    weights: np.ndarray | None = None,
    count: int = CORRECTED_CANDIDATES,
    spp: int = BATCH_SPP,
    residual_spp: int = SPP,
) -> Verified:
    """Returns, as `verify_candidates`, the candidate kept among the fit's `count` candidates and the last of
    `corrections` rounds of `correct.correction_round` ("corrected-1", ...) from the better of them
    (`where_rounds_start`): the correction stage, then the verification stage.

    `model`: the fit's, whose decoder the rounds fit with. `residual_spp`: samples of the rounds' residual renders.
    """
    check_corrections(corrections)
    if not corrections:
        raise ValueError("correct_then_verify runs at least one round of correction: use verify_candidates for none")
    started = time.perf_counter()
    weights = as_weights(target, weights)
    pool = candidates(result, count=count)
    contenders = list(pool)
    batches: dict[str, list[np.ndarray]] = {}
    last, corrected = correction_rounds(
        renderer,
        model,
        result,
        pool,
        batches,
        target,
        weights,
        corrections=corrections,
        spp=spp,
        residual_spp=residual_spp,
    )
    verified = judge(renderer, pool, [*contenders, last], batches, target, weights, spp=spp, started=started)
    return dataclasses.replace(verified, decoded=corrected, corrections=corrections)


def as_weights(target: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    """Returns the fit's per-pixel weights as float32 (R, R): ones where no mask is given."""
    return np.ones(target.shape[:2], np.float32) if weights is None else np.asarray(weights, np.float32)


def render_candidate(renderer: Renders, unit: np.ndarray, *, seed: int, spp: int) -> np.ndarray:
    """Returns Mitsuba's sRGB render of a candidate (unit cube) with `seed` and `spp` samples."""
    return images.srgb_encode(renderer.render(params.from_unit(unit), seed=seed, spp=spp))


def render_batches(
    renderer: Renders,
    pool: dict[str, Float[np.ndarray, " 19"]],
    batches: dict[str, list[np.ndarray]],
    names: Sequence[str],
    *,
    count: int,
    spp: int,
) -> None:
    """Adds to `batches` the batches (batch j with BATCH_SEED + j) that the candidates `names` of `pool` lack of
    `count` each."""
    for name in names:  # every request first, so that a render process works through them while this one waits
        for j in range(len(batches.get(name, ())), count):
            renderer.prefetch(params.from_unit(pool[name]), BATCH_SEED + j, spp)
    for name in names:
        done = batches.setdefault(name, [])
        done.extend(
            render_candidate(renderer, pool[name], seed=BATCH_SEED + j, spp=spp) for j in range(len(done), count)
        )


def correction_rounds(
    renderer: Renders,
    model: models.Model,
    result: search.Result,
    pool: dict[str, Float[np.ndarray, " 19"]],
    batches: dict[str, list[np.ndarray]],
    target: Float[np.ndarray, "R R 3"],
    weights: Float[np.ndarray, "R R"],
    *,
    corrections: int,
    spp: int,
    residual_spp: int | None = None,
) -> tuple[str, dict[str, np.ndarray]]:
    """Returns (the name of the last round's point, phi of each round's point by name) after adding each round's
    point to `pool`: `corrections` rounds of `correct.correction_round`, each from the last one's point
    (`correct.py`); the residual renders have `residual_spp` samples (None: `spp`).

    The rounds wait for one render at a time, and the judge after them renders the best end's BATCHES batches
    whatever the rounds do: each of those is asked for beside a render the rounds wait for (`Spare`), so that a
    second render child makes it meanwhile. The images are the same whoever makes them, and when."""
    residual_spp = residual_spp or spp
    spare = Spare(renderer, pool, ["end-1"] if "end-1" in pool else [], spp=spp)
    name, image = where_rounds_start(
        renderer, pool, batches, target, weights, spp=spp, residual_spp=residual_spp, spare=spare
    )
    unit = pool[name]
    decoded = result.decoded(unit)
    decoded = model.decode(unit)[0] if decoded is None else decoded
    corrected = {}
    for k in range(corrections):
        unit, decoded = correct.correction_round(model, target, weights, unit, image, decoded)
        name = f"corrected-{k + 1}"
        pool[name], corrected[name] = unit, decoded
        if k + 1 < corrections:  # the next round's residual, from a render with this round's own seed
            image = spare.beside(unit, seed=SEED + k + 1, spp=residual_spp)
    return name, corrected


class Spare:
    """Batches the judge will render whatever happens (BATCHES of each of `names` in `pool`), asked for one at a time
    beside a render the caller waits for (`beside`): on a `process.Pool` the two go to two children, and the spare
    one is ready when the judge asks for it. On one renderer it is made after the awaited one, in the time the
    caller then computes."""

    def __init__(self, renderer: Renders, pool: dict[str, np.ndarray], names: list[str], *, spp: int) -> None:
        self.renderer, self.spp = renderer, spp
        self.waiting = [(pool[name], BATCH_SEED + j) for name in names for j in range(BATCHES)]

    def beside(self, unit: np.ndarray, *, seed: int, spp: int) -> np.ndarray:
        """Returns `render_candidate`'s render of `unit`, asked for first, then the next spare batch."""
        values = params.from_unit(unit)
        self.renderer.prefetch(values, seed, spp)
        if self.waiting:
            spare, spare_seed = self.waiting.pop(0)
            self.renderer.prefetch(params.from_unit(spare), spare_seed, self.spp)
        return render_candidate(self.renderer, unit, seed=seed, spp=spp)


def judge(
    renderer: Renders,
    pool: dict[str, Float[np.ndarray, " 19"]],
    contenders: list[str],
    batches: dict[str, list[np.ndarray]],
    target: Float[np.ndarray, "R R 3"],
    weights: Float[np.ndarray, "R R"],
    *,
    spp: int,
    started: float,
) -> Verified:
    """Returns the contender kept by the noise-aware rule of the module docstring: BATCHES batches of each, then one
    more of the leader and of every contender within LEAD standard errors of it, up to MAX_BATCHES.

    `batches`: what was rendered already, by name (added to); `started`: when verification began (for `seconds`).
    """
    render_batches(renderer, pool, batches, contenders, count=BATCHES, spp=spp)
    while True:
        chosen, estimates, margins = decide({name: batches[name] for name in contenders}, target, weights)
        undecided = [name for name, margin in margins.items() if margin < LEAD]
        if not undecided or len(batches[chosen]) >= MAX_BATCHES:
            break
        render_batches(renderer, pool, batches, [chosen, *undecided], count=len(batches[chosen]) + 1, spp=spp)
    figures = {name: 255.0 * float(np.sqrt(max(value, 0.0))) for name, value in estimates.items()}
    return Verified(
        pool[chosen],
        np.mean(batches[chosen], axis=0, dtype=np.float32),  # type: ignore[arg-type]  # an image, not a scalar
        figures[chosen],
        chosen,
        figures,
        time.perf_counter() - started,
        figures["start"],
        {name: len(batches[name]) for name in contenders},
        margins,
        points=pool,
        renders=list(batches[chosen]),
    )


def where_rounds_start(
    renderer: Renders,
    pool: dict[str, Float[np.ndarray, " 19"]],
    batches: dict[str, list[np.ndarray]],
    target: Float[np.ndarray, "R R 3"],
    weights: Float[np.ndarray, "R R"],
    *,
    spp: int = BATCH_SPP,
    residual_spp: int | None = None,
    spare: Spare | None = None,
) -> tuple[str, np.ndarray]:
    """Returns (where the rounds of correction start: the start or the best end, its render with SEED for the first
    round's residual).

    No answer is decided here (the start, the best end and the last round are all judged after the rounds), so one
    render of each does: the best end's with SEED (the residual's, if it starts there) against the start's first
    batch; with `residual_spp` other than `spp` (a batch noisier or less noisy than a residual render) the start's
    SEED render at `residual_spp` instead of its batch, both asked for at once. Choosing by the estimate instead
    started from the truly better point, yet the rounds from it ended worse
    on some targets (jade among them, `scripts/verification_judged.py`): how well the rounds go depends on more than
    where they start. `spare`: batches to ask for beside each render waited for (`Spare`), or None.
    """
    residual_spp = residual_spp or spp
    spare = spare or Spare(renderer, pool, [], spp=spp)
    if residual_spp != spp and "end-1" in pool:  # a batch is not as noisy as the residual: both with SEED, at once
        values = {name: params.from_unit(pool[name]) for name in ("end-1", "start")}
        for value in values.values():
            renderer.prefetch(value, SEED, residual_spp)
        rendered = {name: render_candidate(renderer, pool[name], seed=SEED, spp=residual_spp) for name in values}
        errors = {name: float(images.rmse(image, target, weights)) for name, image in rendered.items()}
        name = "end-1" if errors["end-1"] < errors["start"] else "start"
        return name, rendered[name]
    start = batches.setdefault("start", [])
    start[:1] = start[:1] or [render_candidate(renderer, pool["start"], seed=BATCH_SEED, spp=spp)]
    figure = float(images.rmse(start[0], target, weights))
    if "end-1" in pool:
        image = spare.beside(pool["end-1"], seed=SEED, spp=residual_spp)
        if float(images.rmse(image, target, weights)) < figure:
            return "end-1", image
    return "start", spare.beside(pool["start"], seed=SEED, spp=residual_spp)


def squared_error(
    renders: list[Float[np.ndarray, "R R 3"]], target: Float[np.ndarray, "R R 3"], weights: Float[np.ndarray, "R R"]
) -> tuple[float, Float[np.ndarray, " m"]]:
    """Returns (the unbiased estimate of the weighted mean squared error of the noise-free render,
    `images.noise_free_mse`, and its jackknife leave-one-out estimates (m,)) from m >= 3 independent sRGB renders
    (m, R, R, 3) of one material."""
    m = len(renders)
    if m < 3:
        raise ValueError(f"{m} renders: the estimate's jackknife needs at least 3")
    gram = images.residual_products(np.asarray(renders), target, weights)
    diagonal, rows = np.diag(gram), gram.sum(axis=1)
    pairs = gram.sum() - diagonal.sum()  # every ordered pair i != j
    estimate = pairs / (m * (m - 1))  # `images.noise_free_mse`
    leave_one_out = (pairs - 2.0 * (rows - diagonal)) / ((m - 1) * (m - 2))
    return float(estimate), leave_one_out


def decide(
    batches: dict[str, list[Float[np.ndarray, "R R 3"]]],
    target: Float[np.ndarray, "R R 3"],
    weights: Float[np.ndarray, "R R"],
    *,
    count: int | None = None,
) -> tuple[str, dict[str, float], dict[str, float]]:
    """Returns (the leader: the lowest estimate of `squared_error`, the start first so that a tie keeps it; every
    candidate's estimate; every other candidate's margin behind the leader in standard errors).

    `batches`: each candidate's renders, batch j of every one with the same seed. A margin compares the two over
    their common batches (the first `count` of each, if given): the paired difference of their estimates, with
    the jackknife's standard error over those batches (no spread at all, as of identical renders: infinitely many).
    """
    used = {name: renders[:count] for name, renders in batches.items()}
    estimates = {name: squared_error(renders, target, weights)[0] for name, renders in used.items()}
    leader = min(estimates, key=estimates.__getitem__)
    margins = {}
    for name, renders in used.items():
        if name == leader:
            continue
        common = min(len(renders), len(used[leader]))
        mine, mine_out = squared_error(renders[:common], target, weights)
        theirs, theirs_out = squared_error(used[leader][:common], target, weights)
        out = mine_out - theirs_out
        error = float(np.sqrt((common - 1) / common * np.sum((out - out.mean()) ** 2)))
        difference = mine - theirs
        margins[name] = difference / error if error > 0 else np.inf  # no spread: the same renders, decided
    return leader, estimates, margins


def prefetch_start(
    renderer: Renders, start: Float[np.ndarray, " 19"], *, corrections: int = 0, spp: int = BATCH_SPP
) -> None:
    """Starts, on a `process.Background` or `process.Process`, the renders verification will make of the fit's start
    (unit cube): its first BATCHES batches (`corrections` changes nothing: the start is judged by the same batches)."""
    values = params.from_unit(np.asarray(start, np.float64))  # as `candidates` and `render_candidate` make them
    for j in range(BATCHES):
        renderer.prefetch(values, BATCH_SEED + j, spp)
