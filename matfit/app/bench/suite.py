"""The edit suite and the paper's main table on it (`matfit bench`): the edits, their targets, the fits."""

from __future__ import annotations

import time

import numpy as np

from matfit import edits, images, params
from matfit.app.bench.reachable import TARGET_OFFSET, TARGET_SEED
from matfit.fitting import search, verify
from matfit.fitting.methods import CORRECTIONS
from matfit.model import models
from matfit.rendering import presets

BUDGETS = (50, 300, 1500)  # the paper's Nelder-Mead budgets, in evaluations
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
    search.neural_search(model, target, settings=settings)  # compile outside the timing
    started = time.perf_counter()
    result = search.neural_search(model, target, settings=settings)
    checked = verify.correct_then_verify(renderer, result, target, model=model, corrections=CORRECTIONS)
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
        row["best_of_n"] = search.neural_search(model, target, settings=search.Settings(method=search.Method.nn)).rmse
        if renderer is not None:
            row.update(default_fit(model, renderer, target))
        for budget in budgets:
            for method in (search.Method.optimize, search.Method.hybrid):  # compile outside the timing
                search.neural_search(model, target, settings=search.Settings(method=method, evaluations=budget))
            settings = search.Settings(method=search.Method.optimize, evaluations=budget)
            optimised = [search.neural_search(model, target, settings=settings, seed=seed) for seed in range(seeds)]
            started = time.perf_counter()
            hybrid = search.neural_search(
                model, target, settings=search.Settings(method=search.Method.hybrid, evaluations=budget)
            )
            row[f"optimize_{budget}"] = float(np.mean([r.rmse for r in optimised]))
            row[f"optimize_{budget}_seconds"] = float(np.mean([r.seconds for r in optimised]))
            row[f"hybrid_{budget}"] = hybrid.rmse
            row[f"hybrid_{budget}_seconds"] = time.perf_counter() - started
            row[f"hybrid_{budget}_values"] = hybrid.values.tolist()
            row[f"optimize_{budget}_values"] = optimised[0].values.tolist()
        rows.append(row)
    return rows
