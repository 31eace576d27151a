"""What one view of a scene decides of a fitted material: each parameter moved both ways from the answer, the two
renders compared over the fit's region (`decided`); a parameter that changes the picture too little is reported
as not decided by this view (`ranges` in a scene fit's params.json, docs/scenes.md)."""

from __future__ import annotations

import numpy as np

from matfit import images, params
from matfit.fitting.scene_judge import JUDGE_SEED
from matfit.rendering import scene_file

PROBE = 0.15  # unit-cube step of the per-parameter check of what the view decides
PROBE_SPP = 32
UNDECIDED_RMSE = 0.75  # 0-255 over the region: a parameter that changes the picture less is not decided by it


def decided(
    renderer: scene_file.Renderer, values: np.ndarray, weights: np.ndarray, integrator: str
) -> dict[str, dict[str, object]]:
    """Returns, per parameter, how much the picture changes over `weights` when it moves by PROBE both ways from
    `values` (RMSE of the two renders, one common seed), and whether the picture decides it."""
    unit = params.to_unit(values)
    found: dict[str, dict[str, object]] = {}
    for name in params.NAMES:
        i = params.INDEX[name]
        low, high = unit.copy(), unit.copy()
        low[i], high[i] = max(0.0, unit[i] - PROBE), min(1.0, unit[i] + PROBE)
        a, b = (
            images.srgb_encode(renderer.render(params.from_unit(u), seed=JUDGE_SEED, spp=PROBE_SPP))
            for u in (low, high)
        )
        change = float(images.rmse(a, b, weights))
        medium = name.startswith("medium_") or name in ("density", "scattering", "phase_g")
        verdict = "decided" if change >= UNDECIDED_RMSE else "not decided by this view"
        if medium and integrator == "prb":
            verdict += " (the fit's integrator shows no medium)"
        found[name] = {"change": round(change, 3), "verdict": verdict}
    return found
