"""Every benchmark: rendering and model speed, the fitting methods on reachable targets, the paper's tables.

A reachable target is a Mitsuba render (default 256 spp) of parameters sampled from the
training distribution with a seed the training set did not use, so some parameters reproduce
it exactly, up to render noise. Each configuration fits every target; the table reports the
neural RMSE (phi(x) against the target) and, for chosen configurations, the RMSE of a fresh
Mitsuba render of the result against the target: the honest figure.
"""

from __future__ import annotations

import io
import json
import os
import time
from dataclasses import dataclass

import numpy as np

from matfit import documents, edits, files, images, params
from matfit.fit import search, verify
from matfit.fit.methods import CORRECTIONS
from matfit.model import models
from matfit.render import presets

TARGET_SEED = 1
TARGET_OFFSET = 100_000  # sample indices far from the reference set's 0..N
BUDGETS = (50, 300, 1500)  # the paper's Nelder-Mead budgets, in evaluations


@dataclass
class Targets:
    """Reachable targets: their unit-cube parameters and sRGB images at the model's resolution."""

    unit: np.ndarray
    images: np.ndarray


def reachable_targets(renderer, count: int, spp: int = 256) -> Targets:
    """Returns `count` renders of held-out sampled parameters (seed TARGET_SEED)."""
    unit = np.stack([params.sample_index(TARGET_SEED, TARGET_OFFSET + i) for i in range(count)]).astype(np.float32)
    rendered = [
        images.srgb_encode(renderer.render(params.from_unit(u), seed=TARGET_OFFSET + i, spp=spp))
        for i, u in enumerate(unit)
    ]
    return Targets(unit, np.stack(rendered))


_DEFAULT = search.Settings()
DEFAULT_LABEL = (
    f"lbfgsb, {_DEFAULT.starts} starts x {_DEFAULT.narrow_after}, the best to {_DEFAULT.iterations} (default)"
)


def default_configurations(evaluations: int) -> dict[str, search.Settings]:
    """Returns the compared configurations: the paper's three methods and our variations."""
    return {
        "nn (best-of-n)": search.Settings(method=search.Method.nn),
        f"optimize {evaluations} (random start)": search.Settings(method="optimize", evaluations=evaluations),
        "hybrid 50": search.Settings(method=search.Method.hybrid, evaluations=50),
        "hybrid 300": search.Settings(method=search.Method.hybrid, evaluations=300),
        f"hybrid {evaluations}": search.Settings(method=search.Method.hybrid, evaluations=evaluations),
        f"hybrid {evaluations}, paper's barrier": search.Settings(
            method=search.Method.hybrid, evaluations=evaluations, box="barrier"
        ),
        f"hybrid {evaluations}, fixed coefficients": search.Settings(
            method=search.Method.hybrid, evaluations=evaluations, adaptive=False
        ),
        f"hybrid {evaluations} + polish 200": search.Settings(
            method=search.Method.hybrid, evaluations=evaluations, polish_steps=200
        ),
        "lbfgsb, 1 start": search.Settings(method=search.Method.lbfgsb, starts=1),
        "lbfgsb, 4 starts x 50": search.Settings(iterations=50, narrow_after=50),
        DEFAULT_LABEL: search.Settings(),
        "hybrid-lbfgsb 300, 4 starts": search.Settings(method=search.Method.hybrid_lbfgsb, evaluations=300, starts=4),
    }


def compare(
    model: models.Model, targets: Targets, configurations: dict[str, search.Settings], progress=None
) -> dict[str, dict]:
    """Fits every target with every configuration; returns per configuration the results' figures."""
    table = {}
    for label, settings in configurations.items():
        search.fit(model, targets.images[0], settings)  # compile outside the timing
        errors, seconds, results = [], [], []
        for k, target in enumerate(targets.images):
            started = time.perf_counter()
            result = search.fit(model, target, settings)
            seconds.append(time.perf_counter() - started)
            errors.append(result.rmse)
            results.append(result)
            if progress is not None:
                progress(label, k + 1, len(targets.images))
        table[label] = {"rmse": np.array(errors), "seconds": np.array(seconds), "results": results}
    return table


def mitsuba_rmse(renderer, results: list[search.Result], targets: Targets, spp: int = 256) -> np.ndarray:
    """Returns the RMSE of a fresh Mitsuba render of each result against its target."""
    errors = []
    for k, (result, target) in enumerate(zip(results, targets.images, strict=True)):
        rendered = images.srgb_encode(renderer.render(result.values, seed=7 + k, spp=spp))
        errors.append(float(images.rmse(rendered, target)))
    return np.array(errors)


def rendered_rmse(renderer, unit: np.ndarray, target: np.ndarray, seed: int, spp: int) -> float:
    """Returns the RMSE of a Mitsuba render of unit-cube parameters against an sRGB target."""
    return float(images.rmse(images.srgb_encode(renderer.render(params.from_unit(unit), seed, spp)), target))


VERIFICATION_SPP = (16, 32, 64, 128)  # verification's spp compared by `verification_table` (verify.SPP among them)
JUDGE_SPP = 1024  # the independent render that judges what verification kept
JUDGE_SEED = 977
# Two renders of the same material with the same seed differ by up to ~5e-6 per pixel (Mitsuba's LLVM backend sums
# across threads in no fixed order), so their RMSE differ in the sixth decimal: an answer that is its start, judged
# again, must count as no worse. Comparisons of RMSE against the start allow this much.
RENDER_JITTER = 1e-4


def no_worse(errors, start_errors) -> np.ndarray:
    """Returns where RMSE `errors` are no worse than `start_errors`, within the renderer's run-to-run jitter."""
    return np.asarray(errors) <= np.asarray(start_errors) + RENDER_JITTER


def verification_table(renderer, results: list[search.Result], targets: Targets, spps=VERIFICATION_SPP) -> str:
    """Returns how verification's spp decides (Markdown): per spp, its renders' seconds, the Mitsuba RMSE of the
    candidate it keeps as an independent JUDGE_SPP render sees it, and how often it keeps what the highest spp keeps.
    """
    judged, kept, seconds = [], {spp: [] for spp in spps}, {spp: [] for spp in spps}
    for k, (result, target) in enumerate(zip(results, targets.images, strict=True)):
        judge = {
            name: rendered_rmse(renderer, unit, target, JUDGE_SEED + k, JUDGE_SPP)
            for name, unit in verify.candidates(result).items()
        }
        judged.append(judge)
        for spp in spps:
            checked = verify.verify(renderer, result, target, spp=spp)
            kept[spp].append(checked.chosen)
            seconds[spp].append(checked.seconds)
    lines = [
        f"| verification spp | seconds (median) | kept candidate: mean Mitsuba RMSE at {JUDGE_SPP} spp "
        f"| same choice as {spps[-1]} spp |",
        "|---|---|---|---|",
    ]
    for spp in spps:
        mean = np.mean([judge[name] for judge, name in zip(judged, kept[spp], strict=True)])
        same = sum(a == b for a, b in zip(kept[spp], kept[spps[-1]], strict=True))
        lines.append(f"| {spp} | {np.median(seconds[spp]):.2f} | {mean:.3f} | {same}/{len(judged)} |")
    oracle, start = np.mean([min(judge.values()) for judge in judged]), np.mean([judge["start"] for judge in judged])
    lines += [f"| the best candidate (oracle) | | {oracle:.3f} | |", f"| the best-of-n start | | {start:.3f} | |"]
    return "\n".join(lines)


def judged_table(renderer, answers: dict[str, list[np.ndarray]], targets: Targets, start: str) -> str:
    """Returns the answers' physical quality (Markdown): per label, the mean Mitsuba RMSE of its unit-cube answers
    as independent JUDGE_SPP renders see them (one seed per target for every answer), the share of that above the
    judge's noise floor (the target's true parameters so rendered), and on how many targets it is no worse than the
    answers labelled `start`.
    """
    floor_label = "the true parameters (the judge's noise floor)"
    judged = {
        label: np.array(
            [
                rendered_rmse(renderer, unit, target, JUDGE_SEED + k, JUDGE_SPP)
                for k, (unit, target) in enumerate(zip(units, targets.images, strict=True))
            ]
        )
        for label, units in {floor_label: list(targets.unit), **answers}.items()
    }
    floor = judged.pop(floor_label)
    lines = [
        f"| answer | mean Mitsuba RMSE ({JUDGE_SPP} spp judge) | above the noise floor | no worse than the {start} |",
        "|---|---|---|---|",
        f"| {floor_label} | {np.mean(floor):.3f} | | |",
    ]
    for label, errors in judged.items():
        held = int(np.sum(no_worse(errors, judged[start])))
        lines.append(f"| {label} | {errors.mean():.3f} | {errors.mean() - np.mean(floor):.3f} | {held}/{len(errors)} |")
    return "\n".join(lines)


def markdown(table: dict[str, dict], reference: str, mitsuba: dict[str, np.ndarray]) -> str:
    """Returns the comparison as a Markdown table; `reference` is the configuration others are compared to."""
    lines = [
        f"| configuration | neural RMSE mean | median | targets where {reference} is lower or equal | Mitsuba RMSE "
        "mean | fit time, warm (s) |",
        "|---|---|---|---|---|---|",
    ]
    base = table[reference]["rmse"]
    for label, row in table.items():
        wins = "" if label == reference else f"{int(np.sum(base <= row['rmse'] + 1e-9))}/{len(base)}"
        render = f"{mitsuba[label].mean():.2f}" if label in mitsuba else ""
        lines.append(
            f"| {label} | {row['rmse'].mean():.2f} | {np.median(row['rmse']):.2f} | {wins} | {render} | "
            f"{np.median(row['seconds']):.3f} |"
        )
    return "\n".join(lines)


def black_level(srgb: np.ndarray, level: float) -> np.ndarray:
    """Returns an sRGB image with its black point raised to `level`: (v - level) / (1 - level), clipped."""
    return np.clip((srgb - level) / (1.0 - level), 0.0, 1.0)


def black_level_sequence(
    renderer, count: int = 120, highest: float = 0.3, spp: int = 256
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Returns (the base material's unit parameters, `count` frames with a black level rising from 0 to `highest`).

    The base is a reachable material (a held-out sample) rendered at `spp`, as in the paper's sequence.
    """
    unit = params.sample_index(TARGET_SEED, TARGET_OFFSET - 1).astype(np.float32)
    base = images.srgb_encode(renderer.render(params.from_unit(unit), seed=1, spp=spp))
    return unit, [black_level(base, highest * k / max(1, count - 1)) for k in range(count)]


def sequence_table(
    model: models.Model, frames: list[np.ndarray], budgets: tuple[int, ...] = (100, 300, 600), every: int = 10
) -> str:
    """Returns the paper's sequence table: per-frame RMSE with and without reinitialisation, for each budget."""
    runs = {}
    for budget in budgets:
        settings = search.Settings(method=search.Method.hybrid, evaluations=budget)
        for reinit in (False, True):
            errors, previous = [], None
            for frame in frames:
                result = search.fit(model, frame, settings, extra=previous if reinit else None)
                errors.append(result.rmse)
                previous = result.unit[None]
            runs[(budget, reinit)] = np.array(errors)
    header = "| frame | " + " | ".join(f"{budget}: per frame | {budget}: reinit" for budget in budgets) + " |"
    lines = [header, "|---|" + "---|---|" * len(budgets)]
    for k in range(0, len(frames), every):
        lines.append(
            f"| {k} | " + " | ".join(f"{runs[(b, False)][k]:.2f} | {runs[(b, True)][k]:.2f}" for b in budgets) + " |"
        )
    lines.append(
        "| sum | " + " | ".join(f"{runs[(b, False)].sum():.1f} | {runs[(b, True)].sum():.1f}" for b in budgets) + " |"
    )
    counts = []
    for b in budgets:
        counts += ["", f"{int(np.sum(runs[(b, True)] <= runs[(b, False)] + 1e-6))}/{len(frames)}"]
    lines.append("| frames where reinit <= per frame | " + " | ".join(counts) + " |")
    return "\n".join(lines)


# The edit suite: (name, what was done, source presets, edit of their sRGB renders).
SUITE = (
    ("control", "unedited render of held-out parameters (reachable)", ("held-out",), lambda a: a),
    ("saturation+", "red plastic, saturation +60%", ("red-plastic",), lambda a: edits.saturate(a, -0.6)),
    ("greyscale", "copper made grey", ("copper",), lambda a: edits.saturate(a, 1.0)),
    ("hue shift", "gold, hue turned by 150 degrees", ("gold",), lambda a: edits.hue_rotate(a, 150.0)),
    ("tint", "silver through a warm photo filter", ("silver",), lambda a: edits.tint(a, (1.0, 0.75, 0.45), 0.6)),
    (
        "stitch",
        "jade with its left half taken from blue rubber",
        ("jade", "blue-rubber"),
        lambda a, b: edits.stitch(a, b, (0.0, 0.0, 0.5, 1.0)),
    ),
    (
        "highlight blur",
        "red plastic, specular highlight blurred",
        ("red-plastic",),
        lambda a: edits.blur_highlight(a, 0.55, 2.0),
    ),
    ("mix", "gold and blue rubber blended 50/50", ("gold", "blue-rubber"), lambda a, b: edits.mix(a, b, 0.5)),
)


def suite_targets(renderer, spp: int = 256) -> list[tuple[str, str, np.ndarray]]:
    """Returns (name, description, sRGB target) for every case of SUITE, rendered at the renderer's size."""
    cache = {}

    def source(name: str) -> np.ndarray:
        if name not in cache:
            values = (
                params.from_unit(params.sample_index(TARGET_SEED, TARGET_OFFSET - 2))
                if name == "held-out"
                else presets.preset(name)
            )
            cache[name] = images.srgb_encode(renderer.render(values, seed=3, spp=spp))
        return cache[name]

    return [
        (name, description, edit(*[source(s) for s in sources]).astype(np.float32))
        for name, description, sources, edit in SUITE
    ]


def random_guess_rmse(model: models.Model, target: np.ndarray, seeds: int) -> float:
    """Returns the mean RMSE of phi at uniformly random parameters (the optimiser's random starts)."""
    starts = np.stack([np.random.default_rng(seed).uniform(0.0, 1.0, params.COUNT) for seed in range(seeds)])
    return float(np.mean(images.rmse(model.decode(starts), target)))


def default_fit(model: models.Model, renderer, target: np.ndarray) -> dict:
    """Returns matfit's default fit of a target (`search.Settings()`, Mitsuba-verified and corrected, as `matfit fit`):
    neural figures, time, values."""
    settings = search.Settings()
    search.fit(model, target, settings)  # compile outside the timing
    started = time.perf_counter()
    result = search.fit(model, target, settings)
    checked = verify.verify(renderer, result, target, corrections=CORRECTIONS, model=model)
    return {
        "default": float(images.rmse(model.decode(checked.unit)[0], target)),
        "default_seconds": time.perf_counter() - started,
        "default_evaluations": result.evaluations,
        "default_kept": checked.chosen,
        "default_values": params.from_unit(checked.unit).tolist(),
        "start_values": params.from_unit(result.start).tolist(),
    }


def main_table(model: models.Model, cases, budgets=BUDGETS, seeds: int = 5, renderer=None) -> list[dict]:
    """Returns the paper's main table: random guess, best-of-9, then optimiser (mean over seeds) vs hybrid per budget,
    and matfit's default (gradient stage and Mitsuba verification, with `renderer`)."""
    rows = []
    for name, description, target in cases:
        row = {"case": name, "description": description, "random": random_guess_rmse(model, target, seeds)}
        row["best_of_n"] = search.fit(model, target, search.Settings(method=search.Method.nn)).rmse
        if renderer is not None:
            row.update(default_fit(model, renderer, target))
        for budget in budgets:
            for method in (search.Method.optimize, search.Method.hybrid):  # compile outside the timing
                search.fit(model, target, search.Settings(method=method, evaluations=budget))
            settings = search.Settings(method=search.Method.optimize, evaluations=budget)
            optimised = [search.fit(model, target, settings, seed=seed) for seed in range(seeds)]
            started = time.perf_counter()
            hybrid = search.fit(model, target, search.Settings(method=search.Method.hybrid, evaluations=budget))
            row[f"optimize_{budget}"] = float(np.mean([r.rmse for r in optimised]))
            row[f"optimize_{budget}_seconds"] = float(np.mean([r.seconds for r in optimised]))
            row[f"hybrid_{budget}"] = hybrid.rmse
            row[f"hybrid_{budget}_seconds"] = time.perf_counter() - started
            row[f"hybrid_{budget}_values"] = hybrid.values.tolist()
            row[f"optimize_{budget}_values"] = optimised[0].values.tolist()
        rows.append(row)
    return rows


def optimiser_table(model: models.Model, cases, evaluations: int = 1500, basin_seconds: float = 5.0) -> list[dict]:
    """Returns the paper's optimiser comparison: each optimiser from a random and from the best-of-9 start.

    Nelder-Mead is ours (`evaluations` evaluations); L-BFGS-B, SLSQP and conjugate gradient are
    scipy's with exact gradients of the decoder (the budget below);
    basin-hopping (scipy, L-BFGS-B local steps with exact gradients) stops after `basin_seconds`.
    """
    return [
        {"case": name, **compare_optimisers(model, target, evaluations, basin_seconds)} for name, _, target in cases
    ]


def compare_optimisers(model: models.Model, target: np.ndarray, evaluations: int, basin_seconds: float) -> dict:
    """Returns RMSE, seconds and evaluations spent of every optimiser from both starts on one target.

    Every budget counts objective evaluations, a value-and-gradient as `search.GRADIENT_COST` of them:
    scipy's L-BFGS-B stops at `evaluations / GRADIENT_COST` calls (`maxfun`), SLSQP and CG at as
    many iterations (they may call more often; the table says how many they spent). "L-BFGS-B
    (ours)" is matfit's gradient stage (`gradient.py`, one value-and-gradient per step) with the
    same budget.
    """
    import jax
    import jax.numpy as jnp
    import scipy.optimize

    from matfit.fit import gradient

    decoder, variables = model.decoder.module, model.decoder.variables
    weights = jnp.ones(target.shape[:2], jnp.float32)
    target_j = jnp.asarray(target)
    args = (decoder, variables, target_j, weights)
    bounded_grad = jax.jit(jax.value_and_grad(lambda x: search.decoded_rmse(x, args)))
    penalised_grad = jax.jit(jax.value_and_grad(lambda x: search.objective(x, (*args, search.Box.clip))))

    def host(function):
        def evaluate(x):
            value, grad = function(jnp.asarray(x, jnp.float32))
            return float(value), np.asarray(grad, np.float64)

        return evaluate

    calls = max(1, int(evaluations // search.GRADIENT_COST))
    box = [(0.0, 1.0)] * params.COUNT

    def ours(x0):
        ends, _, steps = gradient.minimise(search.gradient_objective(decoder), x0[None], args[1:], calls)
        return ends[0], steps

    solvers = {
        "L-BFGS-B": lambda x0: scipy.optimize.minimize(
            host(bounded_grad), x0, jac=True, method="L-BFGS-B", bounds=box, options={"maxfun": calls, "maxiter": calls}
        ),
        "SLSQP": lambda x0: scipy.optimize.minimize(
            host(bounded_grad), x0, jac=True, method="SLSQP", bounds=box, options={"maxiter": calls}
        ),
        "CG": lambda x0: scipy.optimize.minimize(
            host(penalised_grad), x0, jac=True, method="CG", options={"maxiter": calls}
        ),
    }
    best = search.fit(model, target, search.Settings(method=search.Method.nn))
    starts = {
        "random": np.random.default_rng(0).uniform(0.0, 1.0, params.COUNT).astype(np.float32),
        "best-of-9": best.start,
    }
    row = {}

    def record(name: str, x: np.ndarray, seconds: float, spent: float) -> None:
        row[name] = float(search.decoded_rmse(jnp.asarray(np.clip(x, 0.0, 1.0), jnp.float32), args))
        row[f"{name} seconds"] = seconds
        row[f"{name} evaluations"] = int(spent)

    for start_name, x0 in starts.items():
        for solver_name, solve in solvers.items():
            solve(np.asarray(x0, np.float64))  # compile outside the timing
            started = time.perf_counter()
            solution = solve(np.asarray(x0, np.float64))
            record(
                f"{solver_name} ({start_name})",
                solution.x,
                time.perf_counter() - started,
                solution.nfev * search.GRADIENT_COST,
            )
        ours(jnp.asarray(x0))
        started = time.perf_counter()
        end, count = ours(jnp.asarray(x0))
        record(
            f"L-BFGS-B, ours ({start_name})",
            np.asarray(end),
            time.perf_counter() - started,
            count * search.GRADIENT_COST,
        )
        started = time.perf_counter()
        method = search.Method.hybrid if start_name == "best-of-9" else search.Method.optimize
        result = search.fit(model, target, search.Settings(method=method, evaluations=evaluations))
        record(f"Nelder-Mead ({start_name})", result.unit, time.perf_counter() - started, result.evaluations)
        deadline = time.perf_counter() + basin_seconds
        started = time.perf_counter()
        hopped = scipy.optimize.basinhopping(
            host(bounded_grad),
            np.asarray(x0, np.float64),
            niter=100_000,
            stepsize=0.1,
            seed=0,
            minimizer_kwargs={"method": "L-BFGS-B", "jac": True, "bounds": box},
            callback=lambda x, f, accept, deadline=deadline: time.perf_counter() > deadline,
        )
        record(
            f"basin-hopping ({start_name})", hopped.x, time.perf_counter() - started, hopped.nfev * search.GRADIENT_COST
        )
    return row


def case_picture(
    model: models.Model, renderer, target: np.ndarray, row: dict, budget: int, spp: int = 256
) -> np.ndarray:
    """Returns target | best-of-9 | optimiser | hybrid | Mitsuba render of hybrid (| of the default, if `row` has it),
    and stores in `row` the RMSE of Mitsuba renders of the best-of-9, optimiser (seed 0), hybrid and default results."""
    from matfit.fit import report

    best = search.fit(model, target, search.Settings(method=search.Method.nn))

    def decode(values):
        return model.decode(params.to_unit(np.asarray(values)))[0]

    hybrid_values = np.asarray(row[f"hybrid_{budget}_values"])
    rendered = images.srgb_encode(renderer.render(hybrid_values, seed=11, spp=spp))
    rendered_best = images.srgb_encode(renderer.render(best.values, seed=11, spp=spp))
    rendered_optimiser = images.srgb_encode(
        renderer.render(np.asarray(row[f"optimize_{budget}_values"]), seed=11, spp=spp)
    )
    hybrid_render_rmse = float(images.rmse(rendered, target))
    row[f"mitsuba_hybrid_{budget}"] = hybrid_render_rmse
    row["mitsuba_best_of_n"] = float(images.rmse(rendered_best, target))
    row[f"mitsuba_optimize_{budget}"] = float(images.rmse(rendered_optimiser, target))
    extra_panels = []
    renders = {}  # by point: a default that kept its start is the start's very render (two renders of one
    # material differ in the last bits, the threads' order of summation, which must not read as worse)
    for key in ("start", "default"):  # independent of verification's seed: the honest comparison
        if f"{key}_values" in row:
            values = np.asarray(row[f"{key}_values"], np.float64)
            if values.tobytes() not in renders:
                renders[values.tobytes()] = images.srgb_encode(renderer.render(values, seed=11, spp=spp))
            rendered_key = renders[values.tobytes()]
            row[f"mitsuba_{key}"] = float(images.rmse(rendered_key, target))
            if key == "default":
                extra_panels.append((rendered_key, f"default, Mitsuba {row['mitsuba_default']:.2f}"))
    panels = [
        (target, f"{row['case']}"),
        (best.image, f"best-of-9 {best.rmse:.2f}"),
        (decode(row[f"optimize_{budget}_values"]), f"optimiser {row[f'optimize_{budget}']:.2f}"),
        (decode(hybrid_values), f"hybrid {row[f'hybrid_{budget}']:.2f}"),
        (rendered, f"Mitsuba {hybrid_render_rmse:.2f}"),
        *extra_panels,
    ]
    return report.compose(panels, size=128, caption=14)


def suite_report(
    main: list[dict], optimisers: list[dict], sequence: str, budgets=BUDGETS, seeds: int = 5, settings: str = ""
) -> str:
    """Returns the Markdown report of the edit suite: main table with Mitsuba column, optimisers, sequence, timings."""
    lines = [
        "# matfit bench: the paper's tables on the built-in edit suite",
        "",
        settings,
        "",
        "## 1. Main table (RMSE, 0-255 sRGB)",
        "",
    ]
    header = (
        "| case | random guess | best-of-9 | "
        + " | ".join(f"optimiser {b} | hybrid {b}" for b in budgets)
        + " | Mitsuba: best-of-9 | Mitsuba: optimiser | Mitsuba: hybrid |"
    )
    lines += [header, "|---|" + "---|" * (5 + 2 * len(budgets))]
    for row in main:
        cells = [f"{row['random']:.2f}", f"{row['best_of_n']:.2f}"]
        for b in budgets:
            cells += [
                f"{row[f'optimize_{b}']:.2f}",
                f"**{row[f'hybrid_{b}']:.2f}**"
                if row[f"hybrid_{b}"] <= row[f"optimize_{b}"] + 1e-6
                else f"{row[f'hybrid_{b}']:.2f}",
            ]
        cells += [
            f"{row['mitsuba_best_of_n']:.2f}",
            f"{row[f'mitsuba_optimize_{budgets[-1]}']:.2f}",
            f"{row[f'mitsuba_hybrid_{budgets[-1]}']:.2f}",
        ]
        lines.append(f"| {row['case']} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"Optimiser = Nelder-Mead from a uniformly random start, mean over {seeds} seeds (the random-guess column is "
        "the mean RMSE of those starts).",
        "Hybrid = Nelder-Mead from the best-of-9 guess; bold where it is at least as good as the optimiser. The "
        "Mitsuba columns render the result",
        f"(best-of-9, optimiser seed 0 and hybrid at {budgets[-1]}) at 256 spp and compare it with the target: "
        "the neural renderer's own error shows there.",
        "",
        f"## 1b. matfit's default ({search.Settings().method.value}, Mitsuba-verified, {CORRECTIONS} corrections) "
        "against its start and the paper's hybrid",
        "",
        "Mitsuba RMSE of a fresh 256-spp render (seed independent of verification's) against the target.",
        "",
        "| case | neural: default | evaluations | time (s) | kept | Mitsuba: start (best-of-9) | Mitsuba: "
        f"hybrid {budgets[-1]} | Mitsuba: default | default <= start |",
        "|---|---|---|---|---|---|---|---|---|",
        *default_rows(main, budgets[-1]),
        "",
        "## 2. Optimisers from a random and from the best-of-9 start (RMSE; seconds and evaluations spent in brackets)",
        "",
        f"Budget {1500} objective evaluations each, a value-and-gradient counted as {search.GRADIENT_COST:g}; "
        "basin-hopping is time-boxed.",
        "",
    ]
    names = [key for key in optimisers[0] if key != "case" and not key.endswith(("seconds", "evaluations"))]
    lines += ["| case | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for row in optimisers:
        cells = [f"{row[n]:.2f} ({row[n + ' seconds']:.1f} s, {row[n + ' evaluations']})" for n in names]
        lines.append(f"| {row['case']} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## 3. Sequence: rising black level, per-frame fitting against reinitialisation",
        "",
        sequence,
        "",
        "## 4. Timings (seconds per fit, warm, median over cases)",
        "",
    ]
    lines += ["| method | " + " | ".join(str(b) for b in budgets) + " |", "|---|" + "---|" * len(budgets)]
    for method in ("optimize", "hybrid"):
        lines.append(
            f"| {method} | "
            + " | ".join(f"{np.median([row[f'{method}_{b}_seconds'] for row in main]):.3f}" for b in budgets)
            + " |"
        )
    lines += [
        "",
        "## 5. Pictures",
        "",
        "Mean RMSE over the suite against the budget:",
        "",
        "![RMSE against evaluations](rmse-vs-evaluations.png)",
        "",
    ]
    lines += [
        "target | best-of-9 | optimiser | hybrid | Mitsuba renders of the hybrid and of the default result, per case:",
        "",
    ]
    lines += [f"![{row['case']}](cases/{slug(row['case'])}.png)" for row in main]
    return "\n".join(lines) + "\n"


def default_rows(main: list[dict], budget: int) -> list[str]:
    """Returns the rows of table 1b, and a row of means."""
    rows = [row for row in main if "mitsuba_default" in row]
    lines = [
        f"| {row['case']} | {row['default']:.2f} | {row['default_evaluations']} | {row['default_seconds']:.2f} | "
        f"{row['default_kept']} | {row['mitsuba_start']:.2f} | {row[f'mitsuba_hybrid_{budget}']:.2f} | "
        f"**{row['mitsuba_default']:.2f}** | "
        f"{'yes' if no_worse(row['mitsuba_default'], row['mitsuba_start']) else 'NO'} |"
        for row in rows
    ]
    if rows:
        mean = {
            key: np.mean([row[key] for row in rows])
            for key in ("mitsuba_start", f"mitsuba_hybrid_{budget}", "mitsuba_default")
        }
        lines.append(
            f"| mean | | | | | {mean['mitsuba_start']:.2f} | {mean[f'mitsuba_hybrid_{budget}']:.2f} | "
            f"**{mean['mitsuba_default']:.2f}** | "
            f"{sum(bool(no_worse(row['mitsuba_default'], row['mitsuba_start'])) for row in rows)}/{len(rows)} |"
        )
    return lines


def slug(name: str) -> str:
    """Returns a file-name-safe version of a case name."""
    return "".join(c if c.isalnum() else "-" for c in name).strip("-")


def budget_plot(main: list[dict], path: str, budgets=BUDGETS) -> None:
    """Writes the main table as a plot: mean RMSE over the cases against the budget (optimiser, hybrid, best-of-9)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot

    mean = {
        key: [float(np.mean([row[f"{key}_{b}"] for row in main])) for b in budgets] for key in ("optimize", "hybrid")
    }
    best_of_n = float(np.mean([row["best_of_n"] for row in main]))
    figure, axes = pyplot.subplots(figsize=(6.4, 4.0), dpi=100)
    axes.plot(budgets, mean["optimize"], "o-", color="tab:red", label="optimiser (Nelder-Mead from a random start)")
    axes.plot(budgets, mean["hybrid"], "o-", color="tab:blue", label="hybrid (Nelder-Mead from best-of-9)")
    axes.axhline(best_of_n, color="grey", linestyle="--", label="best-of-9 (no optimisation)")
    axes.set_xscale("log")
    axes.set_xticks(list(budgets), [str(b) for b in budgets])
    axes.set_ylim(bottom=0.0)
    axes.set_xlabel("budget (objective evaluations)")
    axes.set_ylabel("mean RMSE over the suite (0-255 sRGB)")
    axes.set_title(f"The edit suite ({len(main)} cases): neural RMSE against budget")
    axes.grid(True, which="major", alpha=0.3)
    axes.legend()
    figure.tight_layout()
    encoded = io.BytesIO()
    figure.savefig(encoded, format="png")
    pyplot.close(figure)
    files.write_bytes(path, encoded.getvalue())


def render_speed(count: int, variant: str | None = None) -> str:
    """Returns a Markdown table: images per second of `Renderer` against a bare `mi.render` loop, same materials."""
    from matfit.render.engine import Renderer

    lines = ["| resolution | spp | matfit img/s | bare mi.render img/s | matfit / bare |", "|---|---|---|---|---|"]
    for resolution, spp in ((64, 16), (128, 32)):
        renderer = Renderer(resolution, spp, variant)
        materials = [params.from_unit(params.sample_index(1, i)) for i in range(count)]
        for values in materials[:3]:  # compile every kernel before timing
            renderer.render(values)
        started = time.perf_counter()
        for i, values in enumerate(materials):
            renderer.render(values, seed=i)
        ours = count / (time.perf_counter() - started)
        bare_seconds = 0.0  # the same materials, with only mi.render inside the timer
        for i, values in enumerate(materials):
            renderer.set_material(values)
            started = time.perf_counter()
            renderer.render_current(seed=i)
            bare_seconds += time.perf_counter() - started
        bare = count / bare_seconds
        lines.append(f"| {resolution} | {spp} | {ours:.3g} | {bare:.3g} | {ours / bare:.2f} |")
    return "\n".join(lines)


def model_speed(model_path: str, repeats: int) -> str:
    """Returns a Markdown table: seconds to load a model's networks, milliseconds per decoder forward at batch 1."""
    started = time.perf_counter()
    model = models.load_model(model_path)
    loaded = time.perf_counter() - started
    x = np.full((1, params.COUNT), 0.5, np.float32)
    decoder = model.decoder
    models.apply(decoder.module, decoder.variables, x).block_until_ready()  # compile
    started = time.perf_counter()
    for _ in range(repeats):
        models.apply(decoder.module, decoder.variables, x).block_until_ready()
    forward = (time.perf_counter() - started) / repeats
    networks = 1 + len(model.encoders)
    return (
        f"| networks | load (s) | decoder forward, batch 1 (ms) |\n|---|---|---|\n"
        f"| {networks} | {loaded:.3f} | {1e3 * forward:.2f} |"
    )


def fit_comparison(model: models.Model, count: int, evaluations: int, log=print) -> str:
    """Returns the methods compared on `count` reachable targets: neural and Mitsuba RMSE, warm fit time (Markdown)."""
    from matfit.render.engine import Renderer

    renderer = Renderer(model.resolution, 256)
    log(f"rendering {count} reachable targets at {model.resolution} px, 256 spp")
    targets = reachable_targets(renderer, count)
    table = compare(model, targets, default_configurations(evaluations))
    reference = f"hybrid {evaluations}"
    shown = ("nn (best-of-n)", reference, "lbfgsb, 4 starts x 50", DEFAULT_LABEL, "hybrid-lbfgsb 300, 4 starts")
    mitsuba = {label: mitsuba_rmse(renderer, table[label]["results"], targets) for label in shown}
    default = table[DEFAULT_LABEL]["results"]
    log("verification at each spp, judged by independent renders")
    verification = verification_table(renderer, default, targets)
    log(f"every answer judged by an independent {JUDGE_SPP}-spp render")
    answers = {
        "best-of-n start": [result.start for result in default],
        reference: [result.unit for result in table[reference]["results"]],
        "default, not verified": [result.unit for result in default],
        "default, verified, not corrected": [
            verify.verify(renderer, result, target).unit for result, target in zip(default, targets.images, strict=True)
        ],
        f"default, verified, {CORRECTIONS} corrections (what `matfit fit` answers)": [
            verify.verify(renderer, result, target, corrections=CORRECTIONS, model=model).unit
            for result, target in zip(default, targets.images, strict=True)
        ],
    }
    judged = judged_table(renderer, answers, targets, "best-of-n start")
    return (
        f"{markdown(table, reference, mitsuba)}\n\nVerification of the default's candidates:\n\n{verification}"
        f"\n\nThe answers as the user keeps them, in Mitsuba:\n\n{judged}"
    )


def sequence_benchmark(model: models.Model, frames: int, frames_out: str | None = None) -> str:
    """Returns the reinitialisation table on the built-in black-level sequence; writes the frames to `frames_out`."""
    from matfit.render.engine import Renderer

    if frames_out is not None:
        files.check_folder(frames_out, field="frames_out")
    renderer = Renderer(model.resolution, 256)
    _, sequence_frames = black_level_sequence(renderer, frames)
    if frames_out is not None:
        os.makedirs(frames_out, exist_ok=True)
        for k, frame in enumerate(sequence_frames):
            images.write(os.path.join(frames_out, f"frame_{k}.png"), images.srgb_decode(frame))
    return sequence_table(model, sequence_frames)


def run_suite(model: models.Model, model_label: str, out: str, full: bool = False, log=print) -> str:
    """Runs the paper's tables on the edit suite; writes report.md, report.json, the plot, a picture per case to `out`.

    Quick: 5 seeds, basin-hopping time-boxed to 5 s, 40 sequence frames; `full`: 10, 60 s, 120.
    Returns the report's Markdown.
    """
    from matfit.render.engine import Renderer

    files.check_folder(out, [(name, os.path.join(out, name)) for name in ("report.md", "report.json")])
    seeds, basin_seconds, frames = (10, 60.0, 120) if full else (5, 5.0, 40)
    os.makedirs(os.path.join(out, "cases"), exist_ok=True)
    renderer = Renderer(model.resolution, 256)
    started = time.perf_counter()
    cases = suite_targets(renderer)
    log(f"main table: {len(cases)} cases x (best-of-9, optimiser over {seeds} seeds, hybrid) at {BUDGETS} evaluations")
    main = main_table(model, cases, seeds=seeds, renderer=renderer)
    for (name, _, target), row in zip(cases, main, strict=True):
        picture = case_picture(model, renderer, target, row, BUDGETS[-1])
        images.write(os.path.join(out, "cases", f"{slug(name)}.png"), images.srgb_decode(picture))
    log(f"optimiser table: L-BFGS-B, SLSQP, CG, Nelder-Mead, basin-hopping ({basin_seconds:g} s) from two starts")
    optimisers = optimiser_table(model, cases, basin_seconds=basin_seconds)
    log(f"sequence table: {frames} frames")
    _, sequence_frames = black_level_sequence(renderer, frames)
    sequence_text = sequence_table(model, sequence_frames, every=max(1, frames // 12))
    settings = (
        f"{'Full' if full else 'Quick'} version (`matfit bench{' --full' if full else ''}`), model {model_label}, "
        f"targets at {model.resolution} px rendered at 256 spp; {seeds} seeds; basin-hopping time-boxed to "
        f"{basin_seconds:g} s per run; {frames} sequence frames. Total {time.perf_counter() - started:.0f} s on this "
        "machine."
    )
    budget_plot(main, os.path.join(out, "rmse-vs-evaluations.png"))
    report_text = suite_report(main, optimisers, sequence_text, seeds=seeds, settings=settings)
    files.write_text(os.path.join(out, "report.md"), report_text)
    document = {"main": main, "optimisers": optimisers, "sequence": sequence_text, "settings": settings}
    files.write_text(os.path.join(out, "report.json"), documents.dumps(document, indent=1))
    return report_text


def serve_speed(
    model: models.Model, model_label: str, fits: int = 100, previews: int = 200, log=print, samples: int = 10
) -> str:
    """Returns the page's figures (Markdown): file saved -> result shown, slider -> preview, memory over many fits.

    Warm fit and latency are medians of `samples` fits; memory is read after `samples` fits and after `fits`.

    The server runs in this process (`serve.running`), the client is this process too, over HTTP on
    the loopback: the latency is measured from the watched file's write to the moment the client,
    told of the job by the page's event stream, reads the finished result, as the page does.
    """
    import tempfile
    import threading
    import urllib.request

    from matfit import shipped
    from matfit.app import serve

    examples = [str(shipped.EXAMPLES / f"{name}.png") for name in ("recoloured", "desaturated", "painted-highlight")]
    contents = []
    for path in examples:
        with open(path, "rb") as file:
            contents.append(file.read())
    studio = serve.Studio(model, model_label)
    studio.worker.submit(studio.warm_up).result()
    folder = tempfile.mkdtemp(prefix="matfit-bench-serve-")
    watched = os.path.join(folder, "edit.png")
    with open(watched, "wb") as file:
        file.write(contents[0])
    warm = []
    for k in range(samples):
        started = time.perf_counter()
        renderer = studio.renderer(model.resolution)
        studio.worker.submit(
            serve.fitfile.fit_file, examples[k % 3], model, studio.settings, renderer=renderer
        ).result()
        warm.append(time.perf_counter() - started)
    events: list[tuple[float, dict]] = []

    def listen(url: str) -> None:
        with urllib.request.urlopen(url + "api/watch", timeout=600) as stream:
            for line in stream:
                if line.startswith(b"data: "):
                    events.append((time.perf_counter(), json.loads(line[6:])))

    def job_done(url: str, job: str) -> dict:
        while True:
            with urllib.request.urlopen(f"{url}api/jobs/{job}", timeout=60) as reply:
                answer = json.loads(reply.read())
            if answer["state"] not in ("queued", "running"):
                return answer
            time.sleep(0.02)

    with serve.running(studio, watched) as url:
        threading.Thread(target=listen, args=(url,), daemon=True).start()
        time.sleep(0.5)
        latency = []
        for k in range(samples):
            seen = len(events)
            started = time.perf_counter()
            with open(watched, "wb") as file:  # as an editor saves: the file rewritten in place
                file.write(contents[(k + 1) % len(contents)])
            while len(events) == seen:
                time.sleep(0.005)
            job_done(url, events[-1][1]["job"])
            latency.append(time.perf_counter() - started)
        rng = np.random.default_rng(0)
        round_trips = []
        for _ in range(previews):
            body = json.dumps({"values": params.from_unit(rng.uniform(size=params.COUNT)).tolist()}).encode()
            started = time.perf_counter()
            request = urllib.request.Request(url + "api/preview", body, {"Content-Type": "application/json"})
            with urllib.request.urlopen(request, timeout=60) as reply:
                reply.read()
            round_trips.append(time.perf_counter() - started)
        log(f"{fits} fits through the page")
        memory = {}
        for k in range(1, fits + 1):
            with open(watched, "wb") as file:
                file.write(contents[k % len(contents)])
            seen = len(events)
            while len(events) == seen:
                time.sleep(0.005)
            job_done(url, events[-1][1]["job"])
            if k in (samples, fits):
                memory[k] = resident_mib()
    studio.close()
    return "\n".join(
        [
            "| figure | value |",
            "|---|---|",
            f"| warm fit through the library, the CLI's path (median of {samples}) | {np.median(warm):.3f} s |",
            f"| watched file saved -> result read by the page's client (median of {samples}) "
            f"| {np.median(latency):.3f} s |",
            f"| slider -> neural preview round trip (median of {previews}) | {1e3 * np.median(round_trips):.1f} ms |",
            f"| resident memory after {samples} fits / after {fits} | {memory[samples]:.0f} / {memory[fits]:.0f} MiB "
            f"({100 * (memory[fits] / memory[samples] - 1):+.1f}%) |",
        ]
    )


def resident_mib() -> float:
    """Returns this process's resident memory in MiB (Linux)."""
    with open("/proc/self/status") as status:
        line = next(line for line in status if line.startswith("VmRSS:"))
    return int(line.split()[1]) / 1024
