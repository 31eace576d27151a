"""The fit in a scene of the user's own: the shape's material whose Mitsuba render of that scene looks most like
the edited picture, found by differentiable rendering (docs/scenes.md).

The test scene's networks know one scene only, so here Mitsuba's differentiable renderer is the whole optimiser:
`refine.descend`, the test scene's refinement loop (projected Adam in the unit cube, a new seed each step, the
residual's image at `refine.PRIMAL` times the gradient's samples, the best visited point; for a transmissive
start the residual linear in the image, `refine.Problem.linear`), on the scene file's own camera, lights and
shapes. In order:

1. The picture, resampled to the fit's size (`FIT_SIZE` pixels on the longer side, the camera's aspect), must
   have the camera's aspect.
2. Where the fit looks (`region`): the pixels the shape changes, found by rendering the scene with the shape
   white, with it black, and without it: its silhouette, its shadow, its reflections and what shows through
   it. A mask given instead decides alone. Each pixel's weight is scaled by how little its render is noise
   (`precision`, from the start's two judged renders): caustics' pixels are noisy at any affordable sample count.
   Outside the region the picture must look like the scene's render (else it is not a picture of this scene),
   and inside it like something other than the scene without the shape.
3. Starts: the material given (or the shape's own, or matfit's default) and four that keep its colour over metallic x
   roughness (a start with spec_trans < 0.5) or, for a transmissive one, two over roughness, one with all of it
   transmitted and one as clear glass without coat or sheen (the bench's jade box and glass box under a sky); a start
   that repeats another's values is one start. One start can stick: a glossy plastic fitted to a rough gold stays at
   roughness 0.001 (measured in the prototype). Each runs a quarter of the steps (at most `SHORT_STEPS`). An opaque
   fit's start of lowest noise-free error (`Judge.squared`) then goes on for `steps` more, its residual linear in the
   image too where a step's image there encodes darker than its mean by more than `DARKENING` (`Judge.darkening`); a
   transmissive fit's starts all go on, with spec_trans held where it started for the short run and the descent's
   first half (`refine.path`'s `hold`): the descent could otherwise trade the transmission for a diffuse lobe before
   the medium is fitted and stay in that valley (the jade box: 8.0 in every run, the short runs' ranking no guide to
   where a descent ends). Every fit holds the lobes it can do without (`OPTIONAL`) where they started for the short
   runs and the first half of the descent (`holding`): the base colour, roughness and specular settle first. Free
   from the start, the descent from a sharp highlight to a broader one reached for anisotropy, and of the valley it
   found there no later step or stage took it out (the bench's red knot under the sun: 0.66-1.25 over five runs,
   three over 1.0 by the stricter judge; held, 0.67-0.69 over six: [measured](docs/scenes.md#the-lobes-held)). While
   an opaque fit holds them its steps take Huber's loss (`ROBUST`), the squares after. Of a descent's visited point
   of lowest step loss, its last point and the mean of its last quarter's points, the one of lowest noise-free error
   is its answer (`scene_descent.closest`): a step's loss is one seed's, and where the loss lies flat at its noise
   its lowest point is partly luck; of the starts' answers, the one of lowest noise-free error goes on. A
   transmissive fit's chosen start then descends `scene_descent.AGAIN` more times from its short run's point with
   other step seeds (`AGAIN_BY_CHANNEL` where its steps render a channel a render, `refine.step_image`, and scatter
   less), and of the answers and their mean the one of lowest noise-free error goes on
   (`scene_descent.again`): where the loss lies flat at its noise, one start's descents end where their seeds take
   them (the bench's jade knot: 1.0-4.5 apart). From there on an opaque fit's judge looks past the target's
   outlying pixels where the renders of where its descent ends have heavy-tailed noise (`Judge.robust`: a glossy
   metal's fireflies under a small light).
4. Off the bounds: at some bounds the gradient is zero (sheen and clearcoat at 0 are not evaluated) or wrong
   (roughness at 0, a near-mirror lobe's: `refine`'s docstring), so the descent cannot leave them
   (`scene_descent.TRAPS`). Each such parameter the descent left there is moved inward by `scene_descent.INWARD`
   and judged; if one is closer, `short` more steps go on from it, and the point of the three of lowest noise-free
   error is the answer (`scene_descent.off_bounds`; the bench's box under a sky: roughness stuck at 0 against a
   truth of 0.3, 1.77 -> 0.69).
5. Plain lobes (`scene_plain`): the lobes a material can do without (`OPTIONAL`: clearcoat, sheen, anisotropy)
   that the answer holds are turned off, all together and else each alone, the others re-descended for `short`
   steps with them held at 0; a try is kept unless the answer is closer by `PLAIN_LEAD` standard errors
   (`Judge.behind`). The descent puts on a lobe to follow the target's noise as readily as the picture's light, and
   a lobe whose gradient is 0 at 0 cannot be taken off by it (`plain`).
   Then a roughness, or a shown medium's density, within `NEAR_ZERO` of 0 is tried at 0 by the same rule, without
   steps (`at_zero`): smooth and clear are plainer, and roughness 0 a bound the descent cannot reach
   (`scene_descent.TRAPS`).
6. The answer is judged against the start, and kept only if its noise-free error is lower: never worse than the
   start, as the two renders see it.
7. What one view decides (`scene_ranges`): each parameter moved by `PROBE` in the unit cube both ways from the
   answer, the two renders (one common seed) compared over the region: a change under `UNDECIDED_RMSE` is not
   decided by this picture (`ranges` in params.json).

A start whose medium shows (some transmission, some density) differentiates with `prbvolpath` and is judged with
`volpathmis`; any other differentiates with `prb` (the measured faster integrator; the medium then has no effect
and is reported undecided) and is judged with `path`, which renders it alike in a third of the time.

Every choice between materials is the judge's (`scene_judge.Judge`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, cast

import numpy as np

from matfit import images, params
from matfit.errors import SceneError
from matfit.fitting import refine, scene_descent, scene_plain, scene_ranges
from matfit.fitting.scene_judge import JUDGE_SEED, SECOND_SEED, Judge, root
from matfit.rendering import engine, scene_file
from matfit.rendering import scene as scene_model

FIT_SIZE = 64  # pixels on the longer side of the fit's renders: the prototype's measured recovery size
SHORT_STEPS = 12  # each start's steps before the best goes on (at most; a quarter of `steps` where that is less)
STEPS = 48  # the best start's further steps (`steps=`)
STEP_SPP = refine.SPP  # a step's gradient samples (its image takes refine.PRIMAL times as many)
REGION_SPP = 64  # the renders that find the region
REGION_THRESHOLD = 6.0 / 255.0  # sRGB change (3x3 mean) that counts as the shape's doing
SILHOUETTE_CHANGE = 0.15  # sRGB change between the shape white and black: its own surface, not its shadow
NOT_THIS_SCENE_RMSE = 20.0  # 0-255 outside the region: a picture further than this from the scene is another's
# 0-255 over the region: a picture this close to the scene without the shape has nothing of the shape in it (the
# region's pixels are those the shape changes by 6 or more; two renders' noise alone stays under it)
NOTHING_RMSE = 4.0
NOISE_RADIUS = 2  # the noise variance of a pixel is averaged over its 5x5 neighbours (`precision`)
# The share of a fit's descent that holds the optional lobes (and a transmissive start's spec_trans) where they
# started (`holding`)
LOBES_HELD = 0.5
# An opaque fit's step loss: Huber's, its corner this many robust spreads of the step's residuals (`refine.Problem`);
# a transmissive fit's stays the squares: its caustics are the picture, not its noise (docs/scenes.md#hubers-loss)
ROBUST = 3.0
# An opaque fit's steps from its descent on take the residual linear in their image (`refine.Problem.linear`, as a
# transmissive fit's do throughout) where a step's image, encoded, reads darker than its mean by more than this
# (0-255 over the weights, `Judge.darkening` at the descent's first point): the bench's gold knot under the sun
# 0.67-0.72, whose answers' green then read 0.707-0.729 against the truth's 0.71 (0.728-0.756 encoded); its red
# knot under the sun 0.26, its other opaque cases and edits 0.01-0.05 (docs/scenes.md#the-steps-darkening)
DARKENING = 0.5
ASPECT_TOLERANCE = 0.02


@dataclass(frozen=True)
class SceneOutcome:
    """What a fit in a scene found: the answer, the start, their judged renders, how it went."""

    values: np.ndarray  # physical (19,): the answer kept
    start_values: np.ndarray  # the material the fit started from
    rmse: float  # the answer's judged RMSE over the region, 0-255 sRGB
    start_rmse: float
    accepted: bool  # whether the descent's point was kept (else the start is the answer)
    target: np.ndarray  # sRGB (h, w, 3) at the fit's size
    weights: np.ndarray  # (h, w) the region (or the mask), as used
    rendered: np.ndarray  # sRGB judged render of the answer
    start_rendered: np.ndarray
    guessed: str | None  # how `guess` found the start (None: the start was given, the shape's own or the default)
    starts: list[dict[str, object]]  # each start: name, judged RMSE after its short run
    bounds: dict[str, object]  # the off-the-bounds stage: what it tried, what it moved, the judged RMSEs
    plain: dict[str, object]  # the optional lobes' stage: which were on, each try's lead, which were turned off
    losses: list[float]  # the chosen start's step losses, short run and continuation
    ranges: dict[str, dict[str, object]]  # per parameter: change over the region when probed, decided or not
    integrator: str
    seconds: float
    notices: list[str] = field(default_factory=list)
    # an opaque fit's judge after the descent: the kurtosis of its renders' noise where the descent ended, whether it
    # looked past the target's outlying pixels (`Judge.robust`), the share of the weight it kept
    judge: dict[str, object] = field(default_factory=dict)
    # the descent's step residual: the darkening of a step's image where the descent began (`Judge.darkening`, an
    # opaque fit's), whether the residual was linear in the image (`DARKENING`; a transmissive fit's always); where a
    # transmissive start's medium is coloured, whether its steps rendered by channel (`refine.step_image`) and the two
    # ways' noise variances at the start (x 1e6, `refine.channel_noise`)
    residual: dict[str, object] = field(default_factory=dict)
    # a transmissive fit's chosen start descending again (`scene_descent.again`): the start, each answer's judged
    # RMSE, which was kept
    again: dict[str, object] = field(default_factory=dict)


def check_aspect(scene: scene_file.SceneFile, height: int, width: int, name: str) -> None:
    """Raises SceneError unless a picture of (height, width) has the scene camera's aspect."""
    if abs(width / height - scene.aspect) > ASPECT_TOLERANCE * scene.aspect:
        raise SceneError(
            f"{name} is {width}x{height} (aspect {width / height:.3f}), the scene's camera "
            f"{scene.width}x{scene.height} (aspect {scene.aspect:.3f}): give a picture of the camera's aspect, as "
            "`matfit render --scene` renders it",
            "target",
        )


# (the picture at the fit's size, sRGB (h, w, 3); the shape's own pixels (h, w)) -> (physical values, how found)
Guess = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, str]]


def _renderer(
    scene: scene_file.SceneFile, size: tuple[int, int], variant: str | None, first: np.ndarray
) -> scene_file.Renderer:
    """Returns the judging renderer of a fit from `first`: `volpathmis` where its medium shows, else `path`."""
    judging = None if params.shows_medium(first) else scene_file.OPAQUE_INTEGRATOR
    renderer = scene_file.Renderer(scene, size, variant, judging)
    if renderer.variant == engine.SCALAR_VARIANT:
        raise SceneError(
            f"a fit in a scene differentiates with {engine.LLVM_VARIANT}, which needs libLLVM >= "
            f"{engine.MINIMUM_LLVM}: install Debian's libllvm19 or set DRJIT_LIBLLVM_PATH",
            "variant",
        )
    return renderer


def _blurred(image: np.ndarray, radius: int = 1) -> np.ndarray:
    """Returns the mean over each pixel's (2 radius + 1)^2 neighbours of an (h, w, ...) image, edges repeated."""
    padded = np.pad(image, ((radius, radius), (radius, radius)) + ((0, 0),) * (image.ndim - 2), mode="edge")
    h, w, side = image.shape[0], image.shape[1], 2 * radius + 1
    return np.mean([padded[i : i + h, j : j + w] for i in range(side) for j in range(side)], axis=0)


def precision(renders: tuple[np.ndarray, np.ndarray], weights: np.ndarray) -> np.ndarray:
    """Returns `weights` (h, w) scaled by how little the pixel's render is noise: v0 / (v + v0), where v is the noise
    variance of the two independent sRGB `renders` (half their squared difference, its `NOISE_RADIUS` mean) and v0
    its median over the weighted pixels (a pixel without noise keeps its weight, one as noisy as the median half).

    A least-squares fit weighted by its residuals' precision is the one whose answer varies least with the noise.
    Where the light reaches the region by caustics (a sun through glass or jade onto the floor) a tenth of the
    pixels held 0.71-0.90 of the render's variance on the bench, and a fit there chases the picture's noise."""
    variance = _blurred((np.square(renders[0] - renders[1]) / 2.0).mean(axis=2), NOISE_RADIUS)
    typical = float(np.median(variance[weights > 0])) if np.any(weights > 0) else 0.0
    if typical <= 0:  # renders without noise: every pixel as sure as another
        return weights
    return (weights * typical / (variance + typical)).astype(np.float32)


def _dilated(mask: np.ndarray, pixels: int) -> np.ndarray:
    grown = mask.copy()
    for _ in range(pixels):
        padded = np.pad(grown, 1)
        grown = grown | padded[:-2, 1:-1] | padded[2:, 1:-1] | padded[1:-1, :-2] | padded[1:-1, 2:]
    return grown


def _probe(values: np.ndarray, **changes: float) -> np.ndarray:
    probed = np.asarray(values, np.float64).copy()
    for name, value in changes.items():
        probed[params.INDEX[name]] = value
    return probed


def shape_values(white: bool) -> np.ndarray:
    """Returns the material of the shape's two renders that tell its surface and what it changes: white or black
    (no metal, transmission, medium; the black one without specular, sheen or coat either)."""
    changes = {"metallic": 0.0, "spec_trans": 0.0, "density": 0.0}
    if not white:
        changes |= {"specular": 0.0, "sheen": 0.0, "clearcoat": 0.0}
    grey = 1.0 if white else 0.0
    return _probe(params.DEFAULTS, base_color_r=grey, base_color_g=grey, base_color_b=grey, **changes)


def shape_renders(renderer: scene_file.Renderer) -> tuple[np.ndarray, np.ndarray]:
    """Returns the sRGB renders of the scene with the shape white and black (`shape_values`): what `region` and
    `silhouette` read."""
    white, black = (
        images.srgb_encode(renderer.render(shape_values(w), seed=JUDGE_SEED, spp=REGION_SPP)) for w in (True, False)
    )
    return white, black


def silhouette(renderer: scene_file.Renderer, renders: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Returns the boolean (h, w) mask of the shape's own surface: where its render white and black (`renders`, else
    rendered) differ by more than SILHOUETTE_CHANGE (its shadow and reflections change less)."""
    white, black = renders if renders is not None else shape_renders(renderer)
    return np.abs(white - black).max(axis=2) > SILHOUETTE_CHANGE


def region(
    renderer: scene_file.Renderer, renders: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Returns (the pixels the shape changes as a boolean (h, w) mask, the sRGB render without the shape); `renders`:
    the shape white and black (`shape_renders`), else rendered."""
    renders = renders if renders is not None else shape_renders(renderer)
    without = images.srgb_encode(renderer.render_without(seed=JUDGE_SEED, spp=REGION_SPP))
    changed = np.zeros(without.shape[:2], bool)
    for a, b in ((renders[0], renders[1]), (renders[0], without), (renders[1], without)):
        changed |= _blurred(np.abs(a - b)).max(axis=2) > REGION_THRESHOLD
    return _dilated(changed, 1), without


def problem_of(
    renderer: scene_file.Renderer,
    target: np.ndarray,
    weights: np.ndarray,
    integrator: str,
    linear: bool = False,
    by_channel: bool = False,
) -> refine.Problem:
    """Returns the scene of `renderer` loaded for `refine.descend` with `integrator` ("prb" or "prbvolpath") at the
    path length `renderer` judges with, its renders compared with the sRGB `target` over `weights` (h, w), each
    step's residual linear in its image where `linear` (`refine.Problem.linear`, a transmissive fit's), else its loss
    Huber's (`ROBUST`); under `prbvolpath` where `by_channel` (a transmissive fit whose start's medium is coloured,
    `refine.coloured`), the scene loaded for each colour channel too, so that a step can render a medium whose
    extinction differs by channel one channel at a time (`refine.step_image`)."""
    mi, scene, size = renderer.mi, renderer.scene_file, renderer.size
    start_values = scene.own if scene.own is not None else scene_model.all_lobes_values()
    # the judge's path length, so that a step's image is in expectation the judged one (at 12 against the judge's
    # 64 the bench's jade read 2.5 darker over the region, glass 0.9: `refine.MAX_DEPTH`)
    depth = cast(int, renderer.integrator.get("max_depth", scene_model.MAX_DEPTH))
    description = scene_file.xml(scene, start_values, size, integrator={"type": integrator, "max_depth": depth})
    loaded = scene_file.load(mi, scene, description)
    parameters = mi.traverse(loaded)
    channels: tuple[tuple[Any, Any], ...] = ()
    if integrator == "prbvolpath" and by_channel:
        copies = [scene_file.load(mi, scene, description) for _ in range(2)]
        channels = ((loaded, parameters), *((copy, mi.traverse(copy)) for copy in copies))
    return refine.Problem(
        mi,
        loaded,
        parameters,
        engine.Keys(scene.object),
        mi.TensorXf(target),
        mi.TensorXf(refine.normalised_weights(weights)),
        linear,
        None if linear else ROBUST,
        channels,
    )


def transmissive(values: np.ndarray) -> bool:
    """Returns whether a material (physical) is fitted as a transmissive one: spec_trans 0.5 or more."""
    return bool(values[params.INDEX["spec_trans"]] >= 0.5)


def starts(start: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Returns the named starts of a fit from the material `start` (physical): it, and others that keep its colour."""
    found = [("given", start)]
    if transmissive(start):
        found += [(f"roughness {r}", _probe(start, roughness=r)) for r in (0.02, 0.35)]
        # all of it transmitted: from a partly diffuse start the descent can match a dense medium's glow with the
        # diffuse lobe and stay there (the bench's jade box under the sky)
        found.append(("all transmitted", _probe(start, spec_trans=1.0)))
        # clear glass with no coat or sheen: against a smooth environment a coated, half-transmissive material
        # can look alike to the gradient, and the descent stays there (the bench's box under the sky)
        found.append(("clear glass", _probe(start, spec_trans=1.0, roughness=0.02, clearcoat=0.0, sheen=0.0)))
    else:
        found += [
            (f"metallic {m} roughness {r}", _probe(start, metallic=m, roughness=r))
            for m in (0.0, 1.0)
            for r in (0.15, 0.55)
        ]
    # a start that is another's values (the given roughness is 0.35, or all of it is transmitted) is one descent
    return [
        (name, values)
        for k, (name, values) in enumerate(found)
        if not any(np.array_equal(values, v) for _, v in found[:k])
    ]


def holding(first: np.ndarray, steps: int) -> tuple[tuple[int, ...], int]:
    """Returns (the indices of the parameters that a fit from physical `first` holds where they start through its
    starts' short runs, for how many of its descent's `steps`): the optional lobes (`scene_plain.OPTIONAL`), and a
    transmissive start's spec_trans, for `LOBES_HELD` of the steps. The base lobe (and the medium) settle before
    the descent can reach for a lobe, or trade the transmission for a diffuse lobe."""
    lobes = tuple(params.INDEX[name] for name in scene_plain.OPTIONAL)
    return ((params.INDEX["spec_trans"], *lobes) if transmissive(first) else lobes), int(LOBES_HELD * steps)


def fit(
    scene: scene_file.SceneFile,
    picture: np.ndarray,
    *,
    start: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    steps: int = STEPS,
    variant: str | None = None,
    progress: Callable[[str, int, int, float], None] | None = None,
    guess: Guess | None = None,
) -> SceneOutcome:
    """Returns the fit of the shape's material to `picture` (linear RGB (H, W, 3), the camera's aspect).

    `start`: the material to start from (19 physical values; None: the shape's own, else `guess`'s, else matfit's
    default). `mask`: weights (H, W) in [0, 1] where the fit looks, instead of the region the shape changes.
    `progress(stage, step, steps, loss)` hears of each step ("starts", then "descent") and of the judging ("judge").
    `guess(target, silhouette)`: (physical values, how they were found) of the picture at the fit's size (sRGB) and
    the shape's pixels in it (`scene_start.guess` with a model).
    """
    started = time.perf_counter()
    check_aspect(scene, picture.shape[0], picture.shape[1], "the picture")
    size = scene.size(FIT_SIZE)
    target = np.clip(images.srgb_encode(images.resample(picture, *size)), 0.0, 1.0).astype(np.float32)
    first = start if start is not None else scene.own
    guessing = first is None and guess is not None
    first = np.clip(np.asarray(params.DEFAULTS if first is None else first, np.float64), params.LOW, params.HIGH)
    renderer = _renderer(scene, size, variant, first)
    notices = []
    white_black = shape_renders(renderer)
    shape_region, without = region(renderer, white_black)
    outside = ~shape_region
    if shape_region.mean() < 0.002:
        raise SceneError(
            f"the shape {scene.object!r} is not seen by the scene's camera (it changes no pixel of its render): give "
            "the id of a shape in view",
            "object",
        )
    if outside.any():
        away = float(images.rmse(target, without, outside.astype(np.float32)))
        if away > NOT_THIS_SCENE_RMSE:
            raise SceneError(
                f"the picture is not a render of {scene.path}: away from the shape it differs from the scene by RMSE "
                f"{away:.1f} (0-255): give a picture `matfit render --scene` made of this scene, edited on the shape",
                "target",
            )
    nothing = float(images.rmse(target, without, shape_region.astype(np.float32)))
    if nothing < NOTHING_RMSE:
        raise SceneError(
            f"the picture shows the scene without the shape {scene.object!r} (RMSE {nothing:.1f} from its render "
            "without it): give a picture with the shape in it",
            "target",
        )
    source = None
    if guessing and guess is not None:
        shape = silhouette(
            renderer, white_black
        )  # a shape lit too dimly to differ by SILHOUETTE_CHANGE: the region instead
        guessed, source = guess(target, shape if shape.any() else shape_region)
        first = np.clip(np.asarray(guessed, np.float64), params.LOW, params.HIGH)
        if params.shows_medium(first) != (renderer.integrator != scene_file.OPAQUE_INTEGRATOR):  # judged another way
            renderer = _renderer(scene, size, variant, first)
    integrator = "prbvolpath" if params.shows_medium(first) else "prb"
    if mask is not None:
        weights = np.asarray(images.resample(mask[..., None].astype(np.float32), *size)[..., 0], np.float32)
        if weights.sum() <= 0:
            raise SceneError("the mask is black where the picture is fitted: paint the shape white", "mask")
    else:
        weights = shape_region.astype(np.float32)
    # each pixel weighted by its precision, from the start's two judged renders (which the acceptance reuses)
    judge = Judge(renderer, target, weights)
    weights = precision((judge.render(first, JUDGE_SEED), judge.render(first, SECOND_SEED)), weights)
    judge = judge.weighted(weights)
    # a transmissive material's renders are noisy enough that encoding them reads them darker than their mean (the
    # bench's jade knot 0.7 of 255 at a step's 64 samples, a red plastic 0.03): its steps' residual is linear in the
    # image ([measured](docs/scenes.md#a-steps-residual)); an opaque one's keeps the encoded residual, whose noise
    # the curve compresses (linear throughout, the edits ended further: desaturated 4.01 and 3.92 against 1.41),
    # unless its descent begins where a step's image reads darker than `DARKENING` (below)
    every = transmissive(first)  # every start descends, spec_trans held at first; else the closest start alone
    unit = params.to_unit(first)
    coloured = every and refine.coloured(unit)  # a medium of more than one extinction shows
    problem = problem_of(renderer, target, weights, integrator, linear=every, by_channel=coloured)
    residual: dict[str, object] = {"linear": every}
    if problem.channels:  # one render a step or one a channel: the quieter at the start (a grey medium: one render)
        one, by_channel = refine.channel_noise(problem, unit, STEP_SPP, (JUDGE_SEED, SECOND_SEED))
        residual.update({"by_channel": by_channel < one, "noise": [round(1e6 * one, 2), round(1e6 * by_channel, 2)]})
        if by_channel >= one:
            problem = replace(problem, channels=())
    again = scene_descent.AGAIN_BY_CHANNEL if problem.channels else scene_descent.AGAIN
    candidates = starts(first)
    short = min(SHORT_STEPS, max(1, steps // 4))
    total = (
        short * len(candidates)
        + steps * (len(candidates) + again if every else 1)
        + short
        + short * (1 + len(scene_plain.OPTIONAL))
    )
    hold, held = holding(first, steps)
    done = 0

    def heard(stage: str) -> Callable[[int, float], None]:
        def step(k: int, loss: float) -> None:
            nonlocal done
            done += 1
            if progress is not None:
                progress(stage, done, total, loss)

        return step

    tried: list[dict[str, Any]] = []
    for name, values in candidates:
        point, losses = refine.descend(
            problem,
            params.to_unit(values),
            short,
            spp=STEP_SPP,
            seed=refine.SEED,
            progress=heard("starts"),
            hold=hold,
            held=short,
        )
        judged = judge.squared(params.from_unit(point))
        tried.append({"name": name, "squared": judged, "point": point, "losses": losses})
    descended = tried if every else [min(tried, key=lambda t: t["squared"])]
    if not every:  # an opaque fit's steps encode their image, unless that reads it much darker than its mean: a glossy
        # metal's fireflies under a small light (the gold knot under the sun, whose answers' green read 0.73-0.76
        # against the truth's 0.71 with the encoded residual)
        darker = judge.darkening(params.from_unit(descended[0]["point"]), refine.PRIMAL * STEP_SPP)
        residual = {"darkening": round(darker, 3), "linear": darker > DARKENING}
        if darker > DARKENING:
            problem = replace(problem, linear=True)
    for t in descended:
        t["points"], t["more"] = refine.path(
            problem,
            np.asarray(t["point"]),
            steps,
            spp=STEP_SPP,
            seed=refine.SEED + short,
            progress=heard("descent"),
            hold=hold,
            held=held,
        )
    looked: dict[str, object] = {}
    if not every:  # from here on an opaque fit's judge looks past a heavy-tailed target's outlying pixels, as seen
        # from where its descent ends (`Judge.robust`); a transmissive fit's caustics are its picture, not its noise
        reference = params.from_unit(scene_descent.ending(descended[0]["points"]))
        robust = judge.robust(reference)
        weight = float(robust.weights.sum() / max(float(judge.weights.sum()), 1e-12))
        looked = {
            "kurtosis": round(judge.tails(reference), 2),
            "robust": robust is not judge,
            "weight": round(weight, 3),
        }
        judge = robust
    for t in descended:
        t["answer"], t["answer_squared"] = scene_descent.closest(judge, t["points"], t["more"])
    best = min((t for t in tried if "answer" in t), key=lambda t: t["answer_squared"])
    point, more = best["answer"], best["more"]
    descents: dict[str, object] = {}
    if every:
        point, more, descents = scene_descent.again(
            judge,
            problem,
            best,
            steps,
            seed=refine.SEED + short,
            hold=hold,
            held=held,
            progress=heard("again"),
            times=again,
        )
    point, bounds, inward = scene_descent.off_bounds(
        judge, problem, point, short, seed=short + steps, progress=heard("bounds")
    )
    point, plainer, simpler = scene_plain.plain(
        judge, problem, point, short, seed=2 * short + steps, progress=heard("plain")
    )
    point, bounds["at_zero"] = scene_plain.at_zero(judge, point)
    answer = params.from_unit(point)
    start_squared, answer_squared = judge.squared(first), judge.squared(answer)
    start_rmse, rmse = root(start_squared), root(answer_squared)
    start_rendered, rendered = judge.render(first), judge.render(answer)
    accepted = answer_squared < start_squared
    if not accepted:
        notices.append(
            f"the descent found nothing closer than the start (noise-free error {rmse:.2f} >= {start_rmse:.2f}): kept"
        )
        answer, rmse, rendered = first, start_rmse, start_rendered
    if progress is not None:
        progress("judge", total, total, rmse)
    return SceneOutcome(
        answer,
        first,
        rmse,
        start_rmse,
        accepted,
        target,
        weights,
        rendered,
        start_rendered,
        source,
        [
            {"name": t["name"], "error": round(root(t["squared"]), 3)}
            | ({"descended": round(root(t["answer_squared"]), 3)} if "answer" in t else {})
            for t in tried
        ],
        bounds,
        plainer,
        [*list(best["losses"]), *more, *inward, *simpler],
        scene_ranges.decided(renderer, answer, weights, integrator),
        integrator,
        time.perf_counter() - started,
        notices,
        looked,
        residual,
        descents,
    )
