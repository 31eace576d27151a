"""`matfit bench-sequence`: reinitialisation against per-frame fitting on a rising black level (the paper's
sequence table)."""

from __future__ import annotations

import os

import numpy as np

from matfit import files, images, params
from matfit.app.bench.reachable import TARGET_OFFSET, TARGET_SEED
from matfit.fitting import search
from matfit.model import models


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
                result = search.neural_search(model, frame, settings=settings, extra=previous if reinit else None)
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


def sequence_benchmark(model: models.Model, frames: int, frames_out: str | None = None) -> str:
    """Returns the reinitialisation table on the built-in black-level sequence; writes the frames to `frames_out`."""
    from matfit.rendering.engine import Renderer

    if frames_out is not None:
        files.check_folder(frames_out, field="frames_out")
    renderer = Renderer(model.resolution, 256)
    _, sequence_frames = black_level_sequence(renderer, frames)
    if frames_out is not None:
        os.makedirs(frames_out, exist_ok=True)
        for k, frame in enumerate(sequence_frames):
            images.write(os.path.join(frames_out, f"frame_{k}.png"), images.srgb_decode(frame))
    return sequence_table(model, sequence_frames)
