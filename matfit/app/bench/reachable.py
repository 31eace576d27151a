"""Reachable targets, and the independent render that judges answers to them (every benchmark's ground truth).

A reachable target is a Mitsuba render (default 256 spp) of parameters sampled from the
training distribution with a seed the training set did not use, so some parameters reproduce
it exactly, up to render noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from matfit import images, params

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
    rendered = [
        images.srgb_encode(renderer.render(params.from_unit(u), seed=TARGET_OFFSET + i, spp=spp))
        for i, u in enumerate(unit)
    ]
    return Targets(unit, np.stack(rendered))


def rendered_rmse(renderer, unit: np.ndarray, target: np.ndarray, seed: int, spp: int) -> float:
    """Returns the RMSE of a Mitsuba render of unit-cube parameters against an sRGB target."""
    return float(images.rmse(images.srgb_encode(renderer.render(params.from_unit(unit), seed, spp)), target))


JUDGE_SPP = 1024  # the independent render that judges what verification kept
JUDGE_SEED = 977
# Two renders of the same material with the same seed differ by up to ~5e-6 per pixel (Mitsuba's LLVM backend sums
# across threads in no fixed order), so their RMSE differ in the sixth decimal: an answer that is its start, judged
# again, must count as no worse. Comparisons of RMSE against the start allow this much.
RENDER_JITTER = 1e-4


def no_worse(errors, start_errors) -> np.ndarray:
    """Returns where RMSE `errors` are no worse than `start_errors`, within the renderer's run-to-run jitter."""
    return np.asarray(errors) <= np.asarray(start_errors) + RENDER_JITTER
