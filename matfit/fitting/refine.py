"""Physical refinement: a few gradient steps on the material through Mitsuba's differentiable renderer.

The fit minimises the decoder's error; refinement then minimises the physical render's error
directly. The 19 unit-cube coordinates are one Dr.Jit array with gradients; they are mapped onto
the physical ranges (`physical`, the same affine map as `params.from_unit`) and onto the scene's
values exactly as `engine.Renderer.set_material` writes them (`scene.medium_textures` for the
medium), the test scene is rendered with `prbvolpath` (path replay with media: the backward pass
costs about what the forward pass does and stores no path), and the loss is `images.rmse` written
in Dr.Jit (sRGB encode after clipping, 0-255, optionally mask-weighted). A projected Adam step in
the unit cube follows; each step renders with its own seed (`seed + step`). sRGB encoding and
clipping are concave, so a noisy image's pixel reads darker than its mean: at 16 samples the steps
brightened jade (more sheen, scattering) until its render was 14 RMSE away instead of 5. So the
image whose residual drives the gradient takes `PRIMAL` times the gradient's samples (Mitsuba
decorrelates the primal and adjoint passes itself, `seed_grad`); and where a `Problem` asks
(`linear`: a scene fit of a transmissive material, or of an opaque one whose images darken so,
`scene_fit.DARKENING`) the residual is the image's difference from the linear target times the
chord of the sRGB curve between the target and the mean of the earlier steps' images (`secant`; the
first step's, its own image), linear in this step's image, so in expectation the residual of its
mean render: encoded at 64 samples and 64 px the bench's jade knot read 0.7 of 255 darker over its
region than its mean (glass 0.4, gold under a sun 0.5, a red plastic 0.03). The point returned is
the visited point of lowest step loss (the start included), since late steps drift; `path` returns
every visited point, for a caller that chooses among them otherwise (`fitting/scene_fit`).
Where a `Problem` asks (`robust`: an opaque scene fit's) the steps that hold parameters (`held`) take
Huber's loss instead of the squares: a residual past a corner, `robust` times the step's residuals' robust
spread (`huber_corner`), pulls by the corner, not by itself, so that a few wild pixels (a noisy picture's
fireflies, what no material makes of an edit) do not steer the search while it is far; the steps after
take the squares, which use every pixel as it is.

What moves: all 19 parameters; none is held fixed by choice. Mitsuba 3.9 marks every scene value
they set as differentiable (principled `specular` too: it sets eta; `roughness`, `specular` and the
phase function's `g` are flagged discontinuous, which matters for geometry, not here), and none of
them recompiles the kernel when it changes: every value written comes out of the one optimised
array (no Python literal), and the medium's `scale` (a plain float, which would recompile) stays at
`scene.MEDIUM_SCALE`. Where the derivative is zero a parameter stays where it is (measured):
`sheen` and `clearcoat` at exactly 0 (Mitsuba evaluates those lobes only where their weight is
above 0), and with them `sheen_tint` and `clearcoat_gloss`; the medium's colour, scattering and
`phase_g` while `density` is 0 or `spec_trans` is 0 (no light reaches a medium). The extinction's
floor (`params.MINIMUM_EXTINCTION`) passes the unfloored gradient, so `density` itself can leave 0:
a clear glass can become a tinted one. `prbvolpath` samples directions detached, so for a
near-mirror lobe (roughness near 0) the gradient of `specular` (eta) is valid only in expectation
and very noisy; it is left free because the acceptance render guards it. What does not move is the
scene: camera, lights, geometry.

What is kept: the refined point is rendered with the scene's own integrator (`volpathmis`,
`engine.Renderer`) at ACCEPT_SPP next to the start, both with one
common seed that no refinement step used, and it is kept only if its render is closer to the
target. The answer is never physically worse than the input, as that render sees it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from matfit import images, params
from matfit.errors import FitError, RenderError
from matfit.rendering import engine, scene

if TYPE_CHECKING:
    from types import ModuleType

    import mitsuba as mi

SPP = 16  # samples per pixel of a refinement step's gradient: noisy, but Adam averages them over steps
PRIMAL = 4  # the step's image (the residual) takes PRIMAL x SPP samples: see the module docstring
# prbvolpath's path length during the steps: the acceptance render's (`scene.MAX_DEPTH`), so that a step's image is
# in expectation the picture it is compared with. At 16 a dense medium's render read darker (sphere mean, 0-255 sRGB,
# 512 spp: milk -15.6, jade -2.8, amber glass -0.9) and the steps brightened it to match (30 steps 0.08 off the truth:
# noise-free error milk 2.63, jade 3.97 at 16 against 0.97 and 1.95 at 64); a step costs milk 0.45 -> 0.69 s, jade
# 0.45 -> 0.51 s, an opaque material the same (64 px, 16 spp)
MAX_DEPTH = scene.MAX_DEPTH
RATE = 0.02  # Adam's step in the unit cube
SEED = 3_000_017  # step k renders with SEED + k: neither verify.SEED nor ACCEPT_SEED, nor a training image's seed
ACCEPT_SEED = 2_000_029  # the common seed of the two acceptance renders
ACCEPT_SPP = 128  # enough to rank two materials with common random numbers (verification's 64 and more)
BETAS = (0.9, 0.999)
EPSILON = 1e-8
# a step that renders by channel gives each channel's render its samples over this (`step_image`): at the bench's jade
# box a step took 0.64 s against 0.45-0.51 s in one render (0.73-0.86 s with a share of 2)
CHANNEL_SHARE = 4
CHANNEL_TOLERANCE = 1e-3  # a medium's extinction differs by channel where its largest is over its smallest by more
MEAN_DECAY = 0.5  # the running mean of the steps' images that sets each step's residual slope (`secant`)


@dataclass(frozen=True)
class Refined:
    """What refinement did: the point kept, its render, both Mitsuba RMSEs, whether the refined point was kept."""

    unit: np.ndarray  # the point kept (unit cube): the refined point if accepted, else the input
    rendered: np.ndarray  # the kept point's acceptance render, sRGB (R, R, 3)
    rmse_before: float  # Mitsuba RMSE of the input (acceptance render)
    rmse_after: float  # Mitsuba RMSE of the refined point (acceptance render), kept or not
    accepted: bool
    steps: int
    seconds: float  # in all: steps and acceptance renders
    descent_seconds: float  # the steps alone (the first one of a process also compiles)
    losses: list[float] = field(default_factory=list)  # each step's loss (its own seed, SPP samples)

    @property
    def rmse(self) -> float:
        """Returns the Mitsuba RMSE of the point kept."""
        return self.rmse_after if self.accepted else self.rmse_before


def physical(unit: mi.Float) -> list[mi.Float]:
    """Returns the 19 physical values (Dr.Jit Floats) of a Dr.Jit Float of 19 unit-cube coordinates.

    The map is `params.from_unit`'s, low + u (high - low), with the bounds read from `params`.
    """
    import drjit as dr
    import mitsuba as mi

    return [
        low + dr.gather(mi.Float, unit, i) * (high - low)
        for i, (low, high) in enumerate(zip(params.LOW.tolist(), params.HIGH.tolist(), strict=True))
    ]


def medium_textures(values: list[mi.Float]) -> tuple[mi.Color3f, mi.Color3f]:
    """Returns (sigma_t / MEDIUM_SCALE, albedo) as Color3f for physical Dr.Jit values: `scene.medium_textures`."""
    import drjit as dr
    import mitsuba as mi

    index = params.INDEX
    colour = values[index["medium_color_r"] : index["medium_color_b"] + 1]
    density = values[index["density"]]
    extinction = [density * -dr.log(c) for c in colour]
    # The value is scene.medium_textures' (floored at MINIMUM_EXTINCTION); the gradient is the unfloored one's, so
    # that a clear material (density 0, all of it at the floor) can still be given a medium.
    sigma_t = [(e + dr.detach(dr.maximum(e, params.MINIMUM_EXTINCTION) - e)) / scene.MEDIUM_SCALE for e in extinction]
    scattering = values[index["scattering"]]
    return mi.Color3f(*sigma_t), mi.Color3f(scattering, scattering, scattering)


def set_material(
    scene_parameters: mi.SceneParameters, values: list[mi.Float], keys: engine.Keys, channel: int | None = None
) -> None:
    """Writes physical Dr.Jit values into a loaded scene at `keys`, as `engine.set_material` writes NumPy ones;
    `channel`: the medium's extinction that colour channel's in all three (`step_image`)."""
    import mitsuba as mi

    index = params.INDEX
    scene_parameters[keys.base_color] = mi.Color3f(*values[index["base_color_r"] : index["base_color_b"] + 1])
    for name in engine.SCALAR_BSDF_PARAMETERS:
        scene_parameters[keys.scalar(name)] = values[index[name]]
    sigma_t, albedo = medium_textures(values)
    if channel is not None:
        sigma_t = mi.Color3f(sigma_t[channel], sigma_t[channel], sigma_t[channel])
    scene_parameters[keys.sigma_t] = sigma_t
    scene_parameters[keys.albedo] = albedo
    scene_parameters[keys.phase_g] = values[index["phase_g"]]
    scene_parameters.update()


def huber_corner(residuals: np.ndarray, weights: np.ndarray, spreads: float) -> float:
    """Returns `spreads` robust spreads (1.4826 x the median absolute residual, over the channels of the pixels of
    positive weight) of a step's residuals (H, W, 3): where Huber's loss turns from squares to absolute values."""
    seen = np.abs(np.asarray(residuals, np.float64)[np.asarray(weights) > 0])
    return float(spreads * 1.4826 * np.median(seen)) if seen.size else 0.0


def srgb_rmse(
    linear: mi.TensorXf, target: mi.TensorXf, weights: mi.TensorXf, corner: mi.Float | None = None
) -> mi.TensorXf:
    """Returns `images.rmse` of a linear Dr.Jit image (H, W, 3) against an sRGB `target`, as a Dr.Jit Float.

    `weights` (H, W, 3) sum to 1 (`normalised_weights`). sRGB encoding after clipping to [0, 1]; the
    power branch reads max(x, 0.0031308) so that its derivative stays finite where the linear branch
    is the one taken.
    """
    import drjit as dr

    x = dr.clip(linear, 0.0, 1.0)
    # Dr.Jit's stubs type `dr.power` of an array as `object` (it returns the array's type)
    encoded = dr.select(
        x <= 0.0031308,
        12.92 * x,
        1.055 * dr.power(dr.maximum(x, 0.0031308), 1.0 / 2.4) - 0.055,  # type: ignore[operator]
    )
    return 255.0 * dr.sqrt(dr.sum(weights * _squares(encoded - target, corner), axis=None))


def _squares(residual: mi.TensorXf, corner: mi.Float | None) -> mi.TensorXf:
    """Returns the residuals squared, or past `corner` Huber's 2 corner |r| - corner^2 (their square below it)."""
    import drjit as dr

    if corner is None:
        return dr.square(residual)
    size = dr.abs(residual)
    # Dr.Jit's stubs do not type a tensor against a Float (the Float of one value broadcasts)
    return dr.select(size <= corner, dr.square(residual), 2.0 * corner * size - dr.square(corner))  # type: ignore[operator]


def secant(mean: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Returns the slope of sRGB encoding from linear `target` to linear `mean` (both clipped to [0, 1]), element by
    element: (encode(mean) - encode(target)) / (mean - target), the derivative at their midpoint where they meet.

    A step's residual is this slope times (its render - the target): linear in the render, so its expectation is the
    residual of the render's mean however noisy the render (`path`), where encode(render) - encode(target) reads a
    noisy pixel darker than its mean."""
    a = np.clip(np.asarray(mean, np.float64), 0.0, 1.0)
    b = np.clip(np.asarray(target, np.float64), 0.0, 1.0)
    gap = a - b
    close = np.abs(gap) < 1e-4
    chord = (images.srgb_encode(a).astype(np.float64) - images.srgb_encode(b)) / np.where(close, 1.0, gap)
    return np.where(close, images.srgb_slope(0.5 * (a + b)), chord).astype(np.float32)


def step_rmse(
    linear: mi.TensorXf,
    target: mi.TensorXf,
    slope: mi.TensorXf,
    weights: mi.TensorXf,
    corner: mi.Float | None = None,
) -> mi.TensorXf:
    """Returns a step's loss, 0-255, as a Dr.Jit Float: the weighted RMS of `slope` (H, W, 3, `secant`) times the
    linear image (H, W, 3, clipped to [0, 1]) less the linear `target`. Where `slope` is the secant to the image
    itself this is `images.rmse` of the two encoded; `weights` (H, W, 3) sum to 1 (`normalised_weights`)."""
    import drjit as dr

    residual = slope * (dr.clip(linear, 0.0, 1.0) - target)
    return 255.0 * dr.sqrt(dr.sum(weights * _squares(residual, corner), axis=None))


def normalised_weights(weights: np.ndarray) -> np.ndarray:
    """Returns per-pixel weights (H, W) as (H, W, 3) weights that sum to 1: `images.rmse`'s normalisation."""
    weights = np.asarray(weights, np.float64)
    return np.repeat(weights[..., None] / (3.0 * weights.sum()), 3, axis=-1).astype(np.float32)


@lru_cache(maxsize=2)
def _differentiable_scene(
    resolution: int, requested: str | None = None
) -> tuple[ModuleType, mi.Scene, mi.SceneParameters]:
    """Returns (mi, scene, traversed parameters) of the test scene under `prbvolpath`, loaded once per resolution.

    `requested`: the variant of the renderer that the fit verifies with (None: `engine.choose_variant`'s); a
    differentiable one, cuda_ad_rgb or llvm_ad_rgb.
    """
    variant, _ = engine.choose_variant(requested)
    if variant == engine.SCALAR_VARIANT:
        raise RenderError(
            f"refinement differentiates with {engine.LLVM_VARIANT}, which needs libLLVM >= {engine.MINIMUM_LLVM}: "
            "install Debian's libllvm19 or set DRJIT_LIBLLVM_PATH, or leave refinement off"
        )
    mi = engine.mitsuba(variant)
    description = scene.scene(resolution, SPP)
    description["integrator"] = {"type": "prbvolpath", "max_depth": MAX_DEPTH}
    loaded = mi.load_dict(engine.to_mitsuba(mi, description))
    return mi, loaded, mi.traverse(loaded)


def check(
    unit: np.ndarray,
    target: np.ndarray,
    steps: int,
    weights: np.ndarray | None,
    spp: int,
    renderer: engine.Renderer | None,
) -> None:
    """Raises FitError naming the value and the fix if refinement cannot run on these inputs."""
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer) or steps < 0:
        raise FitError(f"refinement steps {steps!r} must be a whole number >= 0: use 0 to skip refinement", "steps")
    if isinstance(spp, bool) or not isinstance(spp, int | np.integer) or spp < 1:
        raise FitError(f"refinement spp {spp!r} must be a whole number >= 1: use {SPP}", "spp")
    unit = np.asarray(unit)
    if unit.shape != (params.COUNT,) or not np.all(np.isfinite(unit)) or unit.min() < 0 or unit.max() > 1:
        raise FitError(f"the start must be {params.COUNT} unit-cube values in [0, 1], got shape {unit.shape}")
    target = np.asarray(target)
    if target.ndim != 3 or target.shape[0] != target.shape[1] or target.shape[2] != 3:
        raise FitError(f"the target must be a square sRGB image (R, R, 3), got shape {target.shape}")
    if weights is not None and np.asarray(weights).shape != target.shape[:2]:
        raise FitError(f"the mask must be {target.shape[:2]} like the target, got {np.asarray(weights).shape}")
    if renderer is not None and renderer.resolution != target.shape[0]:
        raise FitError(
            f"the renderer renders {renderer.resolution} px, the target is {target.shape[0]} px: use one size"
        )


def refine(
    unit: np.ndarray,
    target: np.ndarray,
    *,
    steps: int,
    weights: np.ndarray | None = None,
    renderer: engine.Renderer | None = None,
    spp: int = SPP,
    seed: int = SEED,
    rate: float = RATE,
) -> Refined:
    """Returns the material after `steps` projected Adam steps on its Mitsuba RMSE, kept only if its render improves.

    `unit`: the start (19 unit-cube values); `target`: the sRGB image (R, R, 3) to match; `weights`:
    per-pixel weights (R, R), as the fit's mask; `renderer`: an `engine.Renderer` at R px for the two
    acceptance renders (one is made if None), whose variant the steps differentiate with (cuda_ad_rgb or
    llvm_ad_rgb). Step k renders with seed `seed + k` and `spp` samples.
    """
    check(unit, target, steps, weights, spp, renderer)
    started = time.perf_counter()
    start = np.asarray(unit, np.float64)
    resolution = int(np.asarray(target).shape[0])
    weights = np.ones((resolution, resolution), np.float32) if weights is None else np.asarray(weights, np.float32)
    variant = renderer.variant if renderer is not None else None  # the steps render with the renderer's variant
    refined, losses = _descend(start, np.asarray(target, np.float32), weights, steps, spp, seed, rate, variant)
    descended = time.perf_counter() - started
    renderer = renderer or engine.Renderer(resolution, ACCEPT_SPP, variant)
    renders = {"before": images.srgb_encode(renderer.render(params.from_unit(start), seed=ACCEPT_SEED, spp=ACCEPT_SPP))}
    # Where the steps found nothing better than the start, its render is reused: two renders of one material differ
    # in the last bits (the threads' order of summation), and that must not count as an improvement.
    unchanged = np.array_equal(refined, start)
    renders["after"] = (
        renders["before"]
        if unchanged
        else images.srgb_encode(renderer.render(params.from_unit(refined), seed=ACCEPT_SEED, spp=ACCEPT_SPP))
    )
    before, after = (float(images.rmse(renders[name], target, weights)) for name in ("before", "after"))
    accepted = after < before
    return Refined(
        refined if accepted else start,
        renders["after" if accepted else "before"],
        before,
        after,
        accepted,
        steps,
        time.perf_counter() - started,
        descended,
        losses,
    )


@dataclass(frozen=True)
class Problem:
    """A scene loaded for differentiable rendering, where the fitted material lives in it, and the picture its renders
    are compared with: what `descend` needs, for the test scene (`refine`) and a scene file (`fitting/scene_fit`)."""

    mitsuba: ModuleType
    scene: mi.Scene
    parameters: mi.SceneParameters
    keys: engine.Keys
    target: mi.TensorXf  # sRGB (H, W, 3)
    weights: mi.TensorXf  # (H, W, 3), summing to 1 (`normalised_weights`)
    linear: bool = False  # each step's residual linear in its image (`secant`), not its image encoded (`srgb_rmse`)
    robust: float | None = None  # Huber's corner in robust spreads of the residuals (`huber_corner`); None: squares
    # the scene loaded once for each colour channel (the first `scene` itself), where a step renders a medium whose
    # extinction differs by channel one channel at a time (`step_image`); empty: in one render
    channels: tuple[tuple[mi.Scene, mi.SceneParameters], ...] = ()


def coloured(unit: np.ndarray) -> bool:
    """Returns whether the material at `unit` (unit cube) has a medium that shows whose extinction differs by colour
    channel: one that `prbvolpath` renders with heavy-tailed noise in one render (`step_image`)."""
    values = params.from_unit(np.asarray(unit, np.float64))
    sigma_t = np.asarray(params.medium_coefficients(values)[0], np.float64)
    return bool(params.shows_medium(values) and sigma_t.max() > (1.0 + CHANNEL_TOLERANCE) * sigma_t.min())


def step_image(problem: Problem, unit: mi.Float, x: np.ndarray, seed: int, spp: int) -> mi.TensorXf:
    """Returns a step's linear image (H, W, 3) of the material at `unit` (its Dr.Jit coordinates, `x` their
    values): `PRIMAL` x `spp` samples for the image, `spp` for the gradient.

    `prbvolpath` samples a path's distances in a medium by one colour channel's extinction, chosen at random, and
    weighs the others by the ratio of their transmittance to its (no spectral MIS, unlike `volpathmis`: Mitsuba's
    issue 1846). Where the extinction differs by channel the ratio grows without bound along a path: at the bench's
    jade box under the sky the truth's renders at 64 samples read pixels up to 13.3 (`volpathmis`'s 0.78), and a
    step's gradients at the truth spread 5-10 times as wide as by channel
    (docs/scenes.md#a-mediums-colours-a-render-each).
    So where the `problem` has `channels` and the material is `coloured`, each channel renders in its own scene with
    that channel's extinction in all three, which `prbvolpath` renders without ratios, with `spp` / `CHANNEL_SHARE`
    samples, and the image takes channel c of render c (the three at the step's seed: their noise correlated, as
    one render's channels are)."""
    mi = problem.mitsuba
    values = physical(unit)
    if not problem.channels or not coloured(x):
        set_material(problem.parameters, values, problem.keys)
        return mi.render(problem.scene, problem.parameters, seed=seed & 0xFFFFFFFF, spp=PRIMAL * spp, spp_grad=spp)
    share = max(1, spp // CHANNEL_SHARE)
    parts = []
    for channel, (loaded, scene_parameters) in enumerate(problem.channels):
        set_material(scene_parameters, values, problem.keys, channel)
        rendered = mi.render(loaded, scene_parameters, seed=seed & 0xFFFFFFFF, spp=PRIMAL * share, spp_grad=share)
        picked = np.zeros(tuple(rendered.shape), np.float32)
        picked[..., channel] = 1.0
        parts.append(rendered * mi.TensorXf(picked))
    return parts[0] + parts[1] + parts[2]


def channel_noise(problem: Problem, unit: np.ndarray, spp: int, seeds: tuple[int, int]) -> tuple[float, float]:
    """Returns (a step image's noise variance in one render, rendering by channel; `step_image`'s, `PRIMAL` x `spp`
    samples) at `unit`, each from two renders at `seeds`: half the weighted mean square of their difference, the image
    clipped to [0, 1] as a step's loss clips it. Which is lower depends on the light: at the jade box under the sky a
    render by channel is far less noisy, at the jade knot under the studio light its quarter of the samples make it
    noisier (docs/scenes.md#a-mediums-colours-a-render-each)."""
    mi = problem.mitsuba
    weights = np.asarray(problem.weights, np.float64)
    found = []
    for p in (replace(problem, channels=()), problem):
        a, b = (
            np.clip(np.array(step_image(p, mi.Float(unit), unit, seed, spp), np.float64), 0.0, 1.0) for seed in seeds
        )
        found.append(float(0.5 * (weights * np.square(a - b)).sum() / max(weights.sum(), 1e-12)))
    return found[0], found[1]


def _descend(
    start: np.ndarray,
    target: np.ndarray,
    weights: np.ndarray,
    steps: int,
    spp: int,
    seed: int,
    rate: float,
    variant: str | None = None,
) -> tuple[np.ndarray, list[float]]:
    """Returns `descend` on the test scene (loaded once per resolution)."""
    if steps == 0:
        return start, []
    mi, loaded, scene_parameters = _differentiable_scene(target.shape[0], variant)
    problem = Problem(
        mi, loaded, scene_parameters, engine.Keys(), mi.TensorXf(target), mi.TensorXf(normalised_weights(weights))
    )
    return descend(problem, start, steps, spp=spp, seed=seed, rate=rate)


def descend(
    problem: Problem,
    start: np.ndarray,
    steps: int,
    *,
    spp: int = SPP,
    seed: int = SEED,
    rate: float = RATE,
    progress: Callable[[int, float], None] | None = None,
    hold: tuple[int, ...] = (),
    held: int = 0,
) -> tuple[np.ndarray, list[float]]:
    """Returns the point of lowest loss among those that `steps` projected Adam steps from `start` visited, and the
    losses (step k's loss is that of the point before its update, so the start is a candidate too): `path`'s.
    """
    points, losses = path(problem, start, steps, spp=spp, seed=seed, rate=rate, progress=progress, hold=hold, held=held)
    if steps == 0:
        return start, []
    return points[int(np.argmin(losses))], losses


def path(
    problem: Problem,
    start: np.ndarray,
    steps: int,
    *,
    spp: int = SPP,
    seed: int = SEED,
    rate: float = RATE,
    progress: Callable[[int, float], None] | None = None,
    hold: tuple[int, ...] = (),
    held: int = 0,
) -> tuple[list[np.ndarray], list[float]]:
    """Returns the points that `steps` projected Adam steps from `start` visit (the start first, the point after
    the last update last: `steps` + 1 of them) and the losses (step k's loss is that of point k, before its update).

    Step k renders with seed `seed + k`: its image takes PRIMAL x `spp` samples, its gradient `spp`. The first
    `held` steps leave the parameters `hold` where they are and, where the problem is `robust`, take Huber's loss
    (their losses are Huber's too). `progress(step, loss)` hears of each step.
    """
    if steps == 0:
        return [start], []
    import drjit as dr

    mi = problem.mitsuba
    weights = np.asarray(problem.weights)
    if problem.linear:
        target = images.srgb_decode(np.asarray(problem.target))
        linear_target = mi.TensorXf(target)
    else:
        target = np.asarray(problem.target, np.float64)
    x, moment, second = start.copy(), np.zeros(params.COUNT), np.zeros(params.COUNT)
    losses, points, mean = [], [], None
    for step in range(steps):
        points.append(x)
        unit = mi.Float(x)
        dr.enable_grad(unit)
        image = step_image(problem, unit, x, seed + step, spp)
        corner = None
        spreads = problem.robust if step < held else None  # Huber's while the search holds, then the squares
        if problem.linear or spreads is not None:
            seen = np.array(dr.detach(image), np.float64)
        if problem.linear:
            # the slope from the earlier steps' images (the first step's own): independent of this step's noise, so
            # that the residual is in expectation that of the image's mean
            slope = secant(seen if mean is None else mean, target)
            if spreads is not None:
                residual = slope * (np.clip(seen, 0.0, 1.0) - target)
                corner = dr.opaque(mi.Float, huber_corner(residual, weights, spreads))
            loss = step_rmse(image, linear_target, mi.TensorXf(slope), problem.weights, corner)
            mean = seen if mean is None else MEAN_DECAY * mean + (1.0 - MEAN_DECAY) * seen
        else:
            if spreads is not None:
                residual = images.srgb_encode(seen) - target  # encoding clips to [0, 1], as the loss does
                corner = dr.opaque(mi.Float, huber_corner(residual, weights, spreads))
            loss = srgb_rmse(image, problem.target, problem.weights, corner)
        dr.backward(loss)
        gradient = np.array(dr.grad(unit), np.float64)
        if step < held:
            gradient[list(hold)] = 0.0
        losses.append(float(loss.array[0]))
        if progress is not None:
            progress(step, losses[-1])
        moment = BETAS[0] * moment + (1 - BETAS[0]) * gradient
        second = BETAS[1] * second + (1 - BETAS[1]) * gradient**2
        corrected = moment / (1 - BETAS[0] ** (step + 1)), second / (1 - BETAS[1] ** (step + 1))
        x = np.clip(x - rate * corrected[0] / (np.sqrt(corrected[1]) + EPSILON), 0.0, 1.0)
    points.append(x)
    return points, losses
