"""`matfit bench-render`, `bench-model` and `bench-speed`: the renderer's, the model's and a whole fit's speed."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from matfit import params
from matfit.model import models


def render_speed(count: int, variant: str | None = None) -> str:
    """Returns a Markdown table: images per second of `Renderer` against a bare `mi.render` loop, same materials."""
    from matfit.rendering.engine import Renderer

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


def cpu_seconds(pids: list[int]) -> float:
    """Returns the CPU seconds (user + system) that the processes `pids` have used so far (Linux's /proc)."""
    ticks = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for pid in pids:
        with open(f"/proc/{pid}/stat") as file:
            fields = file.read().rsplit(")", 1)[1].split()
        total += (int(fields[11]) + int(fields[12])) / ticks
    return total


def whole_process(arguments: list[str], repeats: int) -> list[float]:
    """Returns the wall seconds of `repeats` runs of `python -m matfit ARGUMENTS` after one run not timed (Dr.Jit's and
    the program store's caches filled, as on a user's second fit)."""
    times = []
    for k in range(repeats + 1):
        started = time.perf_counter()
        subprocess.run([sys.executable, "-m", "matfit", *arguments], check=True, capture_output=True)
        if k:
            times.append(time.perf_counter() - started)
    return times


def figures(times: list[float]) -> str:
    """Returns 'median (min-max)' of seconds."""
    return f"{np.median(times):.2f} ({min(times):.2f}-{max(times):.2f})"


def fit_speed(model_path: str, repeats: int, *, cold: bool = True, pictures: list[str] | None = None) -> str:
    """Returns Markdown tables of a default fit's speed on `pictures` (default: the shipped examples): the cold whole
    process (`matfit fit`, median of `repeats` after one run not timed), and a warm process's fit of the same picture
    again and again (one `matfit.Fitter`'s, its model and render pool kept, as the page and `matfit fit a b c` do):
    when the first answer (the neural search's, `answers=`) landed, seconds per stage, renders made, samples
    rendered and the cores' use (CPU seconds of this process and its render children over the wall seconds)."""
    import matfit
    from matfit import shipped

    pictures = pictures or sorted(str(path) for path in shipped.EXAMPLES.glob("*.png"))
    lines = []
    with tempfile.TemporaryDirectory(prefix="matfit-bench-speed-") as folder:
        if cold:
            lines += ["| picture | cold `matfit fit`, s |", "|---|---|"]
            for picture in pictures:
                output = os.path.join(folder, "cold.json")
                times = whole_process(["fit", picture, "-o", output, "--model", model_path], repeats)
                lines.append(f"| {os.path.basename(picture)} | {figures(times)} |")
            times = whole_process(["fit", *pictures, "-o", os.path.join(folder, "all"), "--model", model_path], repeats)
            lines += [f"| all {len(pictures)} in one command | {figures(times)} |", ""]
        lines += [
            "| picture (warm) | first answer, s | fit, s | search | verification + correction | "
            "ranges, document, outputs | clean answer | renders | samples (M) | cores busy |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        with matfit.Fitter(model_path) as fitter:
            pool = fitter._renderer()
            resolution = fitter.model.resolution
            pids = [os.getpid(), *(child._child.pid for child in pool._children)]
            for picture in pictures:
                outputs = matfit.Outputs(os.path.join(folder, "warm.json"))
                fitter.fit(picture, outputs=outputs)  # compiles, loads and fills what a warm process holds
                rows: dict[str, list[float]] = {}
                for _ in range(repeats):
                    renders, samples = pool.renders, pool.samples
                    landed: list[float] = []  # when each stage's answer landed (`answers=`), from the call

                    def heard(
                        _: matfit.Fit, landed: list[float] = landed, started: float = time.perf_counter()
                    ) -> None:
                        landed.append(time.perf_counter() - started)

                    started, cpu = time.perf_counter(), cpu_seconds(pids)
                    fitted = fitter.fit(picture, outputs=outputs, answers=heard)
                    wall = time.perf_counter() - started
                    stages = {
                        "first": landed[0],
                        "fit": wall,
                        "search": float(fitted.document["fit_seconds"]),
                        "verification": float(fitted.verification.get("seconds", 0.0)),
                        "clean": float(fitted.answer.get("seconds", 0.0)),
                        "renders": pool.renders - renders,
                        "samples": (pool.samples - samples) * resolution**2 / 1e6,
                        "cores": (cpu_seconds(pids) - cpu) / wall,
                    }
                    stages["rest"] = wall - stages["search"] - stages["verification"] - stages["clean"]
                    for name, value in stages.items():
                        rows.setdefault(name, []).append(value)
                m = {name: float(np.median(values)) for name, values in rows.items()}
                lines.append(
                    f"| {os.path.basename(picture)} | {figures(rows['first'])} | {figures(rows['fit'])} | "
                    f"{m['search']:.2f} | "
                    f"{m['verification']:.2f} | {m['rest']:.2f} | {m['clean']:.2f} | {m['renders']:.0f} | "
                    f"{m['samples']:.2f} | {m['cores']:.2f} |"
                )
    return "\n".join(lines)
