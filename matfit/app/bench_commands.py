"""The benchmark commands, `matfit bench` and `matfit bench-*`: each parses its options, calls its `bench/` module and
prints what it measured. `register` puts them on the command line's app (`cli`), after its other commands."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer

import matfit
from matfit.app import options

log = functools.partial(typer.echo, err=True)  # progress goes to standard error, the table to standard output


def bench_render(
    count: Annotated[int, typer.Option(min=5, max=100_000, help="Images timed per configuration.")] = 100,
    variant: options.Variant = None,
) -> None:
    """Measure images per second of `Renderer` against a bare `mi.render` loop on the same scene."""
    from matfit.app.bench import speed

    typer.echo(speed.render_speed(count, variant))


def bench_model(
    model_path: options.Model = options.DEFAULT_MODEL,
    repeats: Annotated[int, typer.Option(min=10, max=1_000_000, help="Timed decoder calls.")] = 500,
) -> None:
    """Time loading a model (all networks, weights ready in memory) and the decoder's forward pass at batch 1."""
    from matfit.app.bench import speed

    typer.echo(speed.model_speed(str(model_path), repeats))


def bench_speed(
    model_path: options.Model = options.DEFAULT_MODEL,
    repeats: Annotated[int, typer.Option(min=1, max=100, help="Timed runs of each figure (their median shown).")] = 5,
    cold: Annotated[bool, typer.Option(help="Also time whole `matfit fit` processes (the slow part).")] = True,
) -> None:
    """Time a default fit of each shipped example: cold whole process, and a warm process's fit stage by stage."""
    from matfit.app.bench import speed

    typer.echo(speed.fit_speed(str(model_path), repeats, cold=cold))


def bench_scene(
    out: Annotated[Path, options.out("Folder for results.jsonl (resumable), the scenes and scenes.md.")] = Path(
        "bench-scene"
    ),
    quick: Annotated[bool, typer.Option("--quick", help="One opaque fit only (a smoke run).")] = False,
    steps: Annotated[int, typer.Option(min=1, max=10_000, help="Each fit's descent steps.")] = 48,
) -> None:
    """Fit materials in scenes that are not the test scene (meshes, lightings, truths, an edit) and judge them."""
    from matfit import files
    from matfit.app.bench import scenes

    text = scenes.table(scenes.run(str(out), quick=quick, steps=steps, log=log))
    files.write_text(str(out / "scenes.md"), text + "\n")
    typer.echo(text)


def bench_fit(
    model_path: options.Model = options.DEFAULT_MODEL,
    count: options.TargetCount = 20,
    evaluations: options.Evaluations = 1500,
) -> None:
    """Compare the fitting methods on reachable targets: neural and Mitsuba RMSE, warm fit time."""
    from matfit.app.bench import fits

    typer.echo(fits.fit_comparison(matfit.load_model(model_path), count, evaluations, log=log))


def bench_ranges(
    model_path: options.Model = options.DEFAULT_MODEL,
    count: Annotated[int, typer.Option(min=1, max=10_000, help="Reachable targets to calibrate on.")] = 100,
    judged: Annotated[
        int, typer.Option(min=0, max=10_000, help="Of them, how many also judge the clean answer at 1024 spp.")
    ] = 20,
    examples: Annotated[bool, typer.Option(help="Also judge the clean answer on the shipped example edits.")] = True,
    results: Annotated[Path | None, typer.Option(help="JSON of every finished case, written as each one ends.")] = None,
) -> None:
    """Calibrate what the picture decides: true values inside the ranges, Mitsuba at their ends, the clean answer."""
    from matfit import images, shipped
    from matfit.app.bench import ranges
    from matfit.fitting import search

    model = matfit.load_model(model_path)
    pictures = []
    if examples:
        for path in sorted(shipped.EXAMPLES.glob("*.png")):
            pictures.append((path.stem, search.prepare_target(images.load(str(path)).pixels, model.resolution, "")[0]))
    typer.echo(ranges.table(ranges.run(model, count, judged, pictures, log=log, results=options.text(results))))


def bench_sequence(
    model_path: options.Model = options.DEFAULT_MODEL,
    frames: Annotated[int, typer.Option(min=2, max=100_000, help="Frames of the built-in black-level sequence.")] = 120,
    frames_out: options.FramesOut = None,
) -> None:
    """Reinitialisation against per-frame fitting on a built-in sequence (a rising black level), as in the paper."""
    from matfit.app.bench import sequence

    typer.echo(sequence.sequence_benchmark(matfit.load_model(model_path), frames, options.text(frames_out)))


def bench(
    out: Annotated[Path, options.out("Output folder: report.md, report.json, cases/*.png.")] = Path("data/bench"),
    model_path: options.Model = options.DEFAULT_MODEL,
    full: options.Full = False,
) -> None:
    """Reproduce the paper's evaluation tables on the built-in edit suite (quick version by default)."""
    from matfit.app.bench import suite_report
    from matfit.fitting import document

    model = matfit.load_model(model_path)
    label = document.display_path(str(model_path))
    typer.echo(suite_report.run_suite(model, label, str(out), full, log=log))


def bench_serve(model_path: options.Model = options.DEFAULT_MODEL, fits: options.Fits = 100) -> None:
    """Time the page: a saved file to its result, a slider to its preview; memory after 10 fits and after --fits."""
    from matfit.app.bench import page
    from matfit.fitting import document

    model = matfit.load_model(model_path)
    typer.echo(page.serve_speed(model, document.display_path(str(model_path)), fits, log=log))


def register(command: Callable[..., Any]) -> None:
    """Registers every benchmark command with the command line's `command` (`console.command` on its app), in the
    order `matfit --help` lists them."""
    command(bench_render)
    command(bench_model)
    command(bench_speed)
    command(name="bench-scene", interrupted="each finished case is kept: run the same command to go on")(bench_scene)
    command(bench_fit)
    command(bench_ranges)
    command(bench_sequence)
    command(bench)
    command(bench_serve)
