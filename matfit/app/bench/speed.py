"""`matfit bench-render` and `matfit bench-model`: the renderer's and the model's speed."""

from __future__ import annotations

import time

import numpy as np

from matfit import params
from matfit.model import models


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
