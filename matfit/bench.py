"""Benchmarks of fitting: speed and quality of the methods on reachable targets.

A reachable target is a Mitsuba render (default 256 spp) of parameters sampled from the
training distribution with a seed the training set did not use, so some parameters reproduce
it exactly, up to render noise. Each configuration fits every target; the table reports the
neural RMSE (phi(x) against the target) and, for chosen configurations, the RMSE of a fresh
Mitsuba render of the result against the target: the honest figure.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from matfit import fit, images, models, params

TARGET_SEED = 1
TARGET_OFFSET = 100_000  # sample indices far from the reference set's 0..N


@dataclass
class Targets:
    """Reachable targets: their unit-cube parameters and sRGB images at the model's resolution."""

    unit: np.ndarray
    images: np.ndarray


def reachable_targets(renderer, count: int, spp: int = 256) -> Targets:
    """Returns `count` renders of held-out sampled parameters (seed TARGET_SEED)."""
    unit = np.stack([params.sample_index(TARGET_SEED, TARGET_OFFSET + i) for i in range(count)]).astype(np.float32)
    rendered = [images.srgb_encode(renderer.render(params.from_unit(u), seed=TARGET_OFFSET + i, spp=spp)) for i, u in enumerate(unit)]
    return Targets(unit, np.stack(rendered))


def default_configurations(evaluations: int) -> dict[str, fit.Settings]:
    """Returns the compared configurations: the paper's three methods and our variations."""
    return {
        "nn (best-of-n)": fit.Settings(method="nn"),
        f"optimize {evaluations} (random start)": fit.Settings(method="optimize", evaluations=evaluations),
        "hybrid 50": fit.Settings(evaluations=50),
        "hybrid 300": fit.Settings(evaluations=300),
        f"hybrid {evaluations}": fit.Settings(evaluations=evaluations),
        f"hybrid {evaluations}, paper's barrier": fit.Settings(evaluations=evaluations, box="barrier"),
        f"hybrid {evaluations}, fixed coefficients": fit.Settings(evaluations=evaluations, adaptive=False),
        f"hybrid {evaluations} + polish 200": fit.Settings(evaluations=evaluations, polish_steps=200),
    }


def compare(model: models.Model, targets: Targets, configurations: dict[str, fit.Settings], progress=None) -> dict[str, dict]:
    """Fits every target with every configuration; returns per configuration the results' figures."""
    table = {}
    for label, settings in configurations.items():
        fit.fit(model, targets.images[0], settings)  # compile outside the timing
        errors, seconds, results = [], [], []
        for k, target in enumerate(targets.images):
            started = time.perf_counter()
            result = fit.fit(model, target, settings)
            seconds.append(time.perf_counter() - started)
            errors.append(result.rmse)
            results.append(result)
            if progress is not None:
                progress(label, k + 1, len(targets.images))
        table[label] = {"rmse": np.array(errors), "seconds": np.array(seconds), "results": results}
    return table


def mitsuba_rmse(renderer, results: list[fit.Result], targets: Targets, spp: int = 256) -> np.ndarray:
    """Returns the RMSE of a fresh Mitsuba render of each result against its target."""
    errors = []
    for k, (result, target) in enumerate(zip(results, targets.images, strict=True)):
        rendered = images.srgb_encode(renderer.render(result.values, seed=7 + k, spp=spp))
        errors.append(images.rmse(rendered, target))
    return np.array(errors)


def markdown(table: dict[str, dict], reference: str, mitsuba: dict[str, np.ndarray]) -> str:
    """Returns the comparison as a Markdown table; `reference` is the configuration others are compared to."""
    lines = [
        f"| configuration | neural RMSE mean | median | targets where {reference} is lower or equal | Mitsuba RMSE mean | fit time, warm (s) |",
        "|---|---|---|---|---|---|",
    ]
    base = table[reference]["rmse"]
    for label, row in table.items():
        wins = "" if label == reference else f"{int(np.sum(base <= row['rmse'] + 1e-9))}/{len(base)}"
        render = f"{mitsuba[label].mean():.2f}" if label in mitsuba else ""
        lines.append(
            f"| {label} | {row['rmse'].mean():.2f} | {np.median(row['rmse']):.2f} | {wins} | {render} | {np.median(row['seconds']):.3f} |"
        )
    return "\n".join(lines)


def black_level(srgb: np.ndarray, level: float) -> np.ndarray:
    """Returns an sRGB image with its black point raised to `level`: (v - level) / (1 - level), clipped."""
    return np.clip((srgb - level) / (1.0 - level), 0.0, 1.0)


def black_level_sequence(renderer, count: int = 120, highest: float = 0.3, spp: int = 256) -> tuple[np.ndarray, list[np.ndarray]]:
    """Returns (the base material's unit parameters, `count` frames with a black level rising from 0 to `highest`).

    The base is a reachable material (a held-out sample) rendered at `spp`, as in the paper's sequence.
    """
    unit = params.sample_index(TARGET_SEED, TARGET_OFFSET - 1).astype(np.float32)
    base = images.srgb_encode(renderer.render(params.from_unit(unit), seed=1, spp=spp))
    return unit, [black_level(base, highest * k / max(1, count - 1)) for k in range(count)]


def sequence_table(model: models.Model, frames: list[np.ndarray], budgets: tuple[int, ...] = (100, 300, 600), every: int = 10) -> str:
    """Returns the paper's sequence table: per-frame RMSE with and without reinitialisation, for each budget."""
    runs = {}
    for budget in budgets:
        settings = fit.Settings(evaluations=budget)
        for reinit in (False, True):
            errors, previous = [], None
            for frame in frames:
                result = fit.fit(model, frame, settings, extra=previous if reinit else None)
                errors.append(result.rmse)
                previous = result.unit[None]
            runs[(budget, reinit)] = np.array(errors)
    header = "| frame | " + " | ".join(f"{budget}: per frame | {budget}: reinit" for budget in budgets) + " |"
    lines = [header, "|---|" + "---|---|" * len(budgets)]
    for k in range(0, len(frames), every):
        lines.append(f"| {k} | " + " | ".join(f"{runs[(b, False)][k]:.2f} | {runs[(b, True)][k]:.2f}" for b in budgets) + " |")
    lines.append("| sum | " + " | ".join(f"{runs[(b, False)].sum():.1f} | {runs[(b, True)].sum():.1f}" for b in budgets) + " |")
    counts = []
    for b in budgets:
        counts += ["", f"{int(np.sum(runs[(b, True)] <= runs[(b, False)] + 1e-6))}/{len(frames)}"]
    lines.append("| frames where reinit <= per frame | " + " | ".join(counts) + " |")
    return "\n".join(lines)
