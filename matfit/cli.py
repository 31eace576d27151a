"""The `matfit` command line: parse, call one function, print. Nothing else lives here."""

from __future__ import annotations

import functools
import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from matfit import dataset, files, images, params, presets
from matfit.dataset import DatasetError
from matfit.fit import FitError
from matfit.models import WeightsError
from matfit.params import ParameterError
from matfit.render import RenderError
from matfit.sequence import SequenceError
from matfit.train import TrainingError

app = typer.Typer(
    help="Turn an edited picture of a material into photorealistic principled-BSDF parameters.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)

EXPECTED_ERRORS = (ParameterError, RenderError, files.OutputError, DatasetError, TrainingError, WeightsError, FitError, SequenceError)
MAX_RENDER_SIZE = 4096
DEFAULT_MODEL = Path(__file__).resolve().parent.parent / "data" / "models" / "default"  # shipped in the repository


def fail(message: str, code: int = 2) -> None:
    """Prints a one-line error to standard error and exits with `code`."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def command(function=None, *, name: str | None = None):
    """Registers a command whose expected errors become a one-line message and exit code 2."""
    if function is None:
        return functools.partial(command, name=name)

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        signal.signal(signal.SIGTERM, signal.default_int_handler)  # `kill` stops as cleanly as Ctrl-C
        try:
            return function(*args, **kwargs)
        except EXPECTED_ERRORS as error:
            fail(str(error))

    return app.command(name=name)(wrapper)


def echo_notice(notice: str | None) -> None:
    """Prints a renderer notice (such as the scalar fallback) to standard error."""
    if notice:
        typer.echo(notice, err=True)


def check_range(name: str, value: int, low: int, high: int) -> None:
    """Raises ParameterError unless low <= value <= high."""
    if not low <= value <= high:
        raise ParameterError(f"{name} {value} is out of range: use {low} to {high}")


def read_params_file(path: Path) -> np.ndarray:
    """Returns the physical parameter vector of a params.json file."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise ParameterError(f"cannot read {path}: {getattr(error, 'strerror', None) or error}") from None
    return params.parse_params_json(text, str(path))


@command
def render(
    params_file: Annotated[Path | None, typer.Argument(help="params.json with named values; names left out take defaults.")] = None,
    output: Annotated[
        Path, typer.Option("--output", "-o", help="Image to write: .png/.jpg/.tif (sRGB 8-bit) or .exr (linear float).")
    ] = Path("render.png"),
    size: Annotated[int, typer.Option(help="Width and height in pixels.")] = 512,
    spp: Annotated[int, typer.Option(help="Samples per pixel.")] = 256,
    preset: Annotated[str | None, typer.Option(help=f"A named material instead of a file: {', '.join(presets.PRESETS)}.")] = None,
    random: Annotated[bool, typer.Option("--random", help="A random material from the training distribution (see --seed).")] = False,
    seed: Annotated[int, typer.Option(help="Seed of the random material and of the render's noise.")] = 0,
    variant: Annotated[str | None, typer.Option(help="Force a Mitsuba variant: llvm_ad_rgb or scalar_rgb.")] = None,
) -> None:
    """Render one material in the test scene with Mitsuba: the artist's starting image."""
    sources = [params_file is not None, preset is not None, random]
    if sum(sources) != 1:
        raise ParameterError("give exactly one material: a params.json file, --preset NAME or --random")
    check_range("--size", size, dataset.MIN_RESOLUTION, MAX_RENDER_SIZE)
    check_range("--spp", spp, 1, dataset.MAX_SPP)
    images.check_extension(str(output))
    files.check_writable(str(output))
    if params_file is not None:
        values = read_params_file(params_file)
    elif preset is not None:
        values = presets.preset(preset)
    else:
        check_range("--seed", seed, 0, 2**32 - 1)
        values = params.from_unit(params.sample_unit(np.random.default_rng(seed)))
        typer.echo(json.dumps(params.params_document(values, source=f"--random --seed {seed}"), indent=2))

    from matfit.render import Renderer

    started = time.perf_counter()
    renderer = Renderer(size, spp, variant)
    echo_notice(renderer.notice)
    image = renderer.render(values, seed=seed)
    images.write(str(output), image)
    typer.echo(f"wrote {output} ({size}x{size}, {spp} spp, {renderer.variant}, {time.perf_counter() - started:.1f} s)", err=True)


@command(name="presets")
def presets_sheet(
    output: Annotated[Path, typer.Option("--output", "-o", help="Contact sheet to write (.png, .jpg or .exr).")] = Path("presets.png"),
    size: Annotated[int, typer.Option(help="Side of each tile in pixels.")] = 128,
    spp: Annotated[int, typer.Option(help="Samples per pixel.")] = 256,
    variant: Annotated[str | None, typer.Option(help="Force a Mitsuba variant: llvm_ad_rgb or scalar_rgb.")] = None,
) -> None:
    """Render every preset side by side, labelled, into one picture."""
    check_range("--size", size, 32, 1024)
    check_range("--spp", spp, 1, dataset.MAX_SPP)
    images.check_extension(str(output))
    files.check_writable(str(output))
    from matfit.render import Renderer

    renderer = Renderer(size, spp, variant)
    echo_notice(renderer.notice)
    tiles = [images.label(images.srgb_encode(renderer.render(presets.preset(name))), name) for name in presets.PRESETS]
    images.write(str(output), images.srgb_decode(np.concatenate(tiles, axis=1)))
    typer.echo(f"wrote {output} ({len(tiles)} presets)", err=True)


@command(name="params")
def parameters() -> None:
    """List the 19 shader parameters: name, range, default, unit and meaning."""
    for p in params.PARAMETERS:
        typer.echo(f"{p.name:16} [{p.low:g}, {p.high:g}]  default {p.default:g}  {p.unit:14} {p.meaning}")


class Progress:
    """A progress display: a rich bar on a terminal, a line every 10% otherwise."""

    def __init__(self, label: str):
        self.label = label
        self.bar = None
        self.next_report = 0.0
        if sys.stderr.isatty():
            from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn
            from rich.progress import Progress as RichProgress

            self.bar = RichProgress(
                TextColumn(label),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[rate]}"),
                TimeRemainingColumn(),
                transient=False,
            )
            self.task = None

    def __call__(self, done: int, total: int, rate: float) -> None:
        rate_text = f"{rate:.1f} img/s" if rate > 0 else ""
        if self.bar is not None:
            if self.task is None:
                self.bar.start()
                self.task = self.bar.add_task(self.label, total=total, completed=done, rate=rate_text)
            self.bar.update(self.task, completed=done, rate=rate_text)
        elif done / total >= self.next_report or done == total:
            eta = f", {(total - done) / rate:.0f} s left" if rate > 0 else ""
            typer.echo(f"{self.label}: {done}/{total} ({100 * done / total:.0f}%) {rate_text}{eta}", err=True)
            self.next_report = min(1.0, done / total + 0.1)

    def close(self) -> None:
        """Stops the bar, leaving its last state on screen."""
        if self.bar is not None and self.task is not None:
            self.bar.stop()


@command
def render_dataset(
    out: Annotated[Path, typer.Argument(help="Dataset directory (created, resumed or grown).")],
    count: Annotated[int, typer.Option(help="Total number of samples the dataset should hold.")] = 20000,
    resolution: Annotated[int, typer.Option(help="Image side in pixels.")] = 64,
    spp: Annotated[int, typer.Option(help="Samples per pixel.")] = 16,
    seed: Annotated[int, typer.Option(help="Seed of the parameter sampling and of the renders' noise.")] = 0,
    workers: Annotated[int, typer.Option(help="Rendering processes, one thread each (default: one per core).")] = os.cpu_count() or 1,
    variant: Annotated[str | None, typer.Option(help="Force a Mitsuba variant: llvm_ad_rgb or scalar_rgb.")] = None,
) -> None:
    """Render a training set of sampled materials; run it again to resume or to grow it."""
    check_range("--workers", workers, 1, 64)
    from matfit import render as render_module

    chosen, notice = render_module.choose_variant(variant)
    settings = dataset.Settings(resolution, spp, seed, chosen)
    settings.check()
    dataset.check_count(count, "--count")
    echo_notice(notice)
    render_module.mitsuba(chosen)
    data = dataset.prepare(str(out), settings, count, render_module.versions())
    progress = Progress(f"rendering {out}")
    try:
        rendered = dataset.render_missing(data, workers, progress)
    except KeyboardInterrupt:
        progress.close()
        typer.echo(f"interrupted: {data.finished}/{count} samples are saved; run the same command to resume", err=True)
        raise typer.Exit(130) from None
    progress.close()
    typer.echo(f"{out}: {count}/{count} samples ({rendered} rendered now, {resolution} px, {spp} spp, {chosen})", err=True)


@command
def bench_render(
    count: Annotated[int, typer.Option(help="Images timed per configuration.")] = 100,
    variant: Annotated[str | None, typer.Option(help="Force a Mitsuba variant: llvm_ad_rgb or scalar_rgb.")] = None,
) -> None:
    """Measure images per second of `Renderer` against a bare `mi.render` loop on the same scene."""
    check_range("--count", count, 5, 100000)
    from matfit.render import Renderer

    typer.echo("| resolution | spp | matfit img/s | bare mi.render img/s | matfit / bare |")
    typer.echo("|---|---|---|---|---|")
    for resolution, spp in ((64, 16), (128, 32)):
        renderer = Renderer(resolution, spp, variant)
        echo_notice(renderer.notice)
        materials = [params.from_unit(params.sample_index(1, i)) for i in range(count)]
        for values in materials[:3]:  # compile every kernel before timing
            renderer.render(values)
        started = time.perf_counter()
        for i, values in enumerate(materials):
            renderer.render(values, seed=i)
        ours = count / (time.perf_counter() - started)
        # The bare loop renders the same materials, with only mi.render inside the timer.
        bare_seconds = 0.0
        for i, values in enumerate(materials):
            renderer.set_material(values)
            started = time.perf_counter()
            np.array(renderer.mi.render(renderer.scene, seed=i))
            bare_seconds += time.perf_counter() - started
        bare = count / bare_seconds
        typer.echo(f"| {resolution} | {spp} | {ours:.1f} | {bare:.1f} | {ours / bare:.2f} |")


@command(name="fit")
def fit_command(
    target: Annotated[Path, typer.Argument(help="The edited picture: PNG, JPEG, TIFF (8/16-bit) or EXR (linear).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="params.json to write (feeds `matfit render`).")] = Path("params.json"),
    model_path: Annotated[Path, typer.Option("--model", help="Model directory (default: the shipped model).")] = DEFAULT_MODEL,
    method: Annotated[
        str, typer.Option(help="hybrid (best-of-n, then Nelder-Mead), nn (best-of-n only) or optimize (Nelder-Mead from a random start).")
    ] = "hybrid",
    evals: Annotated[int, typer.Option("--evals", help="Nelder-Mead budget in objective evaluations (the paper: 50, 300, 1500).")] = 1500,
    seed: Annotated[int, typer.Option(help="Seed of the random start of --method optimize.")] = 0,
    mask: Annotated[
        Path | None, typer.Option(help="Per-pixel weights, same size as the target: white = match here, black = ignore.")
    ] = None,
    box: Annotated[str, typer.Option(help="Keeping inside the parameter box: clip (clip + penalty) or barrier (the paper's).")] = "clip",
    polish: Annotated[int, typer.Option(help="Projected-Adam steps through the decoder after Nelder-Mead (0: none).")] = 0,
    report: Annotated[
        Path | None, typer.Option(help="Write a comparison picture: target | guess | fit | Mitsuba render | difference.")
    ] = None,
    render_path: Annotated[Path | None, typer.Option("--render", help="Render the fitted material with Mitsuba to this image.")] = None,
    size: Annotated[int, typer.Option(help="Size of the --render image in pixels.")] = 512,
    spp: Annotated[int, typer.Option(help="Samples per pixel of the --render image.")] = 256,
    mitsuba_xml: Annotated[Path | None, typer.Option("--mitsuba-xml", help="Write the BSDF and medium as Mitsuba 3 XML.")] = None,
    blender: Annotated[Path | None, typer.Option(help="Write a Blender 4.x script that builds the material.")] = None,
) -> None:
    """Find the shader parameters whose render looks most like the edited picture."""
    import hashlib

    from matfit import fit as fit_module
    from matfit import models

    settings = fit_module.Settings(method=method, evaluations=evals, box=box, polish_steps=polish, seed=seed)
    settings.check()
    check_range("--seed", seed, 0, 2**31 - 1)
    check_range("--size", size, dataset.MIN_RESOLUTION, MAX_RENDER_SIZE)
    check_range("--spp", spp, 1, dataset.MAX_SPP)
    if output.suffix.lower() != ".json":
        raise ParameterError(f"--output {output} must end in .json")
    for path in (report, render_path):
        if path is not None:
            images.check_extension(str(path))
    for path, suffix in ((mitsuba_xml, ".xml"), (blender, ".py")):
        if path is not None and path.suffix.lower() != suffix:
            raise ParameterError(f"{path} must end in {suffix}")
    for path in (output, report, render_path, mitsuba_xml, blender):
        if path is not None:
            files.check_writable(str(path))
    started = time.perf_counter()
    loaded = images.load(str(target))
    mask_image = images.load(str(mask)) if mask is not None else None
    models.enable_compilation_cache()
    model = models.load_model(str(model_path))
    for notice in loaded.notices:
        typer.echo(notice, err=True)
    target_srgb, notices = fit_module.prepare_target(loaded.pixels, model.resolution, str(target))
    for notice in notices:
        typer.echo(notice, err=True)
    weights = None
    if mask_image is not None:
        weights = fit_module.prepare_mask(mask_image.pixels, loaded.pixels.shape[:2], model.resolution, str(mask))
    result = fit_module.fit(model, target_srgb, settings, weights)

    extra = {}
    rendered = None
    if report is not None or render_path is not None:
        from matfit.render import Renderer

        renderer = Renderer(model.resolution, 256)
        echo_notice(renderer.notice)
        rendered = images.srgb_encode(renderer.render(result.values))
        extra["mitsuba_rmse"] = round(images.rmse(rendered, target_srgb), 3)
        if render_path is not None:
            big = Renderer(size, spp, renderer.variant)
            images.write(str(render_path), big.render(result.values))
    document = params.params_document(
        result.values,
        method=method,
        evaluations=result.evaluations,
        neural_rmse=round(result.rmse, 3),
        start=result.chosen,
        start_rmse=round(result.start_rmse, 3),
        **extra,
        box=box,
        polish_steps=polish,
        model=os.path.abspath(model_path),
        target=str(target),
        target_sha256=hashlib.sha256(target.read_bytes()).hexdigest(),
        mask=str(mask) if mask is not None else None,
        fit_seconds=round(result.seconds, 3),
        wall_time_s=round(time.perf_counter() - started, 3),
    )
    if report is not None:
        from matfit import report as report_module

        panels = [
            (target_srgb, "target"),
            (result.start_image, f"best-of-n {result.start_rmse:.2f}"),
            (result.image, f"fit (neural) {result.rmse:.2f}"),
            (rendered, f"fit (Mitsuba) {extra['mitsuba_rmse']:.2f}"),
            (report_module.difference(rendered, target_srgb), "|Mitsuba - target| x4"),
        ]
        images.write(str(report), images.srgb_decode(report_module.compose(panels)))
    if mitsuba_xml is not None or blender is not None:
        from matfit import export

        if mitsuba_xml is not None:
            files.write_text(str(mitsuba_xml), export.mitsuba_xml(result.values))
        if blender is not None:
            files.write_text(str(blender), export.blender_script(result.values))
    files.write_text(str(output), json.dumps(document, indent=2) + "\n")
    typer.echo(
        f"{output}: {method}, {result.evaluations} evaluations, neural RMSE {result.rmse:.2f} (start {result.chosen} {result.start_rmse:.2f})"
        + (f", Mitsuba RMSE {extra['mitsuba_rmse']:.2f}" if extra else "")
        + f", {time.perf_counter() - started:.1f} s",
        err=True,
    )


@command
def sequence(
    frames_path: Annotated[
        Path, typer.Argument(help="Folder of frames (PNG, JPEG, TIFF, EXR), fitted in natural order: frame_2 before frame_10.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder: one JSON per frame, summary.md, preview.png.")] = Path(
        "sequence"
    ),
    model_path: Annotated[Path, typer.Option("--model", help="Model directory (default: the shipped model).")] = DEFAULT_MODEL,
    evals: Annotated[int, typer.Option("--evals", help="Nelder-Mead evaluations per frame.")] = 100,
    method: Annotated[str, typer.Option(help="hybrid, nn or optimize, as in `matfit fit`.")] = "hybrid",
    reinit: Annotated[bool, typer.Option("--reinit/--no-reinit", help="Add the previous frame's optimum to the best-of-n pool.")] = True,
    render_frames: Annotated[
        bool, typer.Option("--render", help="Also render every fitted frame with Mitsuba (<frame>-render.png).")
    ] = False,
    size: Annotated[int, typer.Option(help="Size of the --render images.")] = 256,
    spp: Annotated[int, typer.Option(help="Samples per pixel of the --render images.")] = 64,
) -> None:
    """Fit every frame of an edited sequence, reusing each optimum for the next frame; resumable."""
    from matfit import fit as fit_module
    from matfit import models
    from matfit import sequence as sequence_module

    settings = fit_module.Settings(method=method, evaluations=evals)
    settings.check()
    check_range("--size", size, dataset.MIN_RESOLUTION, MAX_RENDER_SIZE)
    check_range("--spp", spp, 1, dataset.MAX_SPP)
    frames = sequence_module.list_frames(str(frames_path))
    if out.exists() and not out.is_dir():
        raise files.OutputError(f"--out {out} is a file: give a folder for the results")
    out.mkdir(parents=True, exist_ok=True)
    files.check_writable(str(out / "summary.md"))
    models.enable_compilation_cache()
    model = models.load_model(str(model_path))
    progress = Progress(f"fitting {len(frames)} frames")
    started = time.perf_counter()
    try:
        results = sequence_module.fit_sequence(
            model,
            frames,
            str(out),
            settings,
            reinit,
            progress=lambda done, total, frame: progress(done, total, done / (time.perf_counter() - started)),
        )
        if render_frames:
            from matfit.render import Renderer

            renderer = Renderer(size, spp)
            echo_notice(renderer.notice)
            for frame in results:
                path = out / (Path(frame.path).stem + "-render.png")
                if not path.exists():
                    images.write(str(path), renderer.render(params.from_unit(frame.unit)))
    except KeyboardInterrupt:
        progress.close()
        typer.echo(f"interrupted: finished frames are saved in {out}; run the same command to resume", err=True)
        raise typer.Exit(130) from None
    progress.close()
    table = sequence_module.summary_table(results)
    files.write_text(str(out / "summary.md"), table)
    images.write(str(out / "preview.png"), images.srgb_decode(sequence_module.preview(model, results)))
    typer.echo(table)
    typer.echo(
        f"{out}: {len(results)} frames, RMSE sum {sum(f.rmse for f in results):.2f}, {time.perf_counter() - started:.1f} s", err=True
    )


@command
def bench_model(
    model_path: Annotated[Path, typer.Option("--model", help="Model directory to time.")] = DEFAULT_MODEL,
    repeats: Annotated[int, typer.Option(help="Timed decoder calls.")] = 500,
) -> None:
    """Time loading a model (all networks, weights ready in memory) and the decoder's forward pass at batch 1."""
    check_range("--repeats", repeats, 10, 1_000_000)
    from matfit import models

    started = time.perf_counter()
    model = models.load_model(str(model_path))
    loaded = time.perf_counter() - started
    decoder = model.decoder
    x = np.full((1, params.COUNT), 0.5, np.float32)
    models.apply(decoder.module, decoder.variables, x).block_until_ready()  # compile
    started = time.perf_counter()
    for _ in range(repeats):
        models.apply(decoder.module, decoder.variables, x).block_until_ready()
    forward = (time.perf_counter() - started) / repeats
    typer.echo(
        f"| networks | load (s) | decoder forward, batch 1 (ms) |\n|---|---|---|\n| {1 + len(model.encoders)} | {loaded:.3f} | {1e3 * forward:.2f} |"
    )


@command
def bench_fit(
    model_path: Annotated[Path, typer.Option("--model", help="Model directory.")] = DEFAULT_MODEL,
    count: Annotated[int, typer.Option(help="Reachable targets (256-spp renders of held-out parameters).")] = 20,
    evals: Annotated[int, typer.Option("--evals", help="Nelder-Mead budget of the main configurations.")] = 1500,
) -> None:
    """Compare the fitting methods on reachable targets: neural and Mitsuba RMSE, warm fit time."""
    check_range("--count", count, 1, 10000)
    check_range("--evals", evals, params.COUNT + 2, 1_000_000)
    from matfit import bench, models
    from matfit.render import Renderer

    models.enable_compilation_cache()
    model = models.load_model(str(model_path))
    renderer = Renderer(model.resolution, 256)
    echo_notice(renderer.notice)
    typer.echo(f"rendering {count} reachable targets at {model.resolution} px, 256 spp", err=True)
    targets = bench.reachable_targets(renderer, count)
    configurations = bench.default_configurations(evals)
    table = bench.compare(model, targets, configurations, progress=lambda label, done, total: None)
    reference = f"hybrid {evals}"
    mitsuba = {label: bench.mitsuba_rmse(renderer, table[label]["results"], targets) for label in ("nn (best-of-n)", reference)}
    typer.echo(bench.markdown(table, reference, mitsuba))


@command
def bench_sequence(
    model_path: Annotated[Path, typer.Option("--model", help="Model directory.")] = DEFAULT_MODEL,
    frames: Annotated[int, typer.Option(help="Frames of the built-in black-level sequence.")] = 120,
    frames_out: Annotated[Path | None, typer.Option("--write-frames", help="Also write the sequence's frames to this folder.")] = None,
) -> None:
    """Reinitialisation against per-frame fitting on a built-in sequence (a rising black level), as in the paper."""
    check_range("--frames", frames, 2, 100000)
    from matfit import bench, models
    from matfit.render import Renderer

    models.enable_compilation_cache()
    model = models.load_model(str(model_path))
    renderer = Renderer(model.resolution, 256)
    echo_notice(renderer.notice)
    _, sequence_frames = bench.black_level_sequence(renderer, frames)
    if frames_out is not None:
        frames_out.mkdir(parents=True, exist_ok=True)
        for k, frame in enumerate(sequence_frames):
            images.write(str(frames_out / f"frame_{k}.png"), images.srgb_decode(frame))
    started = time.perf_counter()
    typer.echo(bench.sequence_table(model, sequence_frames))
    typer.echo(f"{6 * frames} fits in {time.perf_counter() - started:.1f} s", err=True)


@command
def bench(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder: report.md, report.json, cases/*.png.")] = Path("data/bench"),
    model_path: Annotated[Path, typer.Option("--model", help="Model directory.")] = DEFAULT_MODEL,
    full: Annotated[
        bool, typer.Option("--full", help="Everything: 10 seeds, 60 s basin-hopping, 120 frames (the quick version: 5, 5 s, 40).")
    ] = False,
) -> None:
    """Reproduce the paper's evaluation tables on the built-in edit suite (quick version by default)."""
    from matfit import bench as bench_module
    from matfit import models
    from matfit.render import Renderer

    seeds, basin_seconds, frames = (10, 60.0, 120) if full else (5, 5.0, 40)
    (out / "cases").mkdir(parents=True, exist_ok=True)
    files.check_writable(str(out / "report.md"))
    models.enable_compilation_cache()
    model = models.load_model(str(model_path))
    renderer = Renderer(model.resolution, 256)
    echo_notice(renderer.notice)
    started = time.perf_counter()
    cases = bench_module.suite_targets(renderer)
    typer.echo(
        f"main table: {len(cases)} cases x (best-of-9, optimiser over {seeds} seeds, hybrid) at {bench_module.BUDGETS} evaluations",
        err=True,
    )
    main = bench_module.main_table(model, cases, seeds=seeds)
    for (name, _, target), row in zip(cases, main, strict=True):
        picture = bench_module.case_picture(model, renderer, target, row, bench_module.BUDGETS[-1])
        images.write(str(out / "cases" / f"{bench_module.slug(name)}.png"), images.srgb_decode(picture))
    typer.echo(f"optimiser table: L-BFGS-B, SLSQP, CG, Nelder-Mead, basin-hopping ({basin_seconds:g} s) from two starts", err=True)
    optimisers = bench_module.optimiser_table(model, cases, basin_seconds=basin_seconds)
    typer.echo(f"sequence table: {frames} frames", err=True)
    _, sequence_frames = bench_module.black_level_sequence(renderer, frames)
    sequence_text = bench_module.sequence_table(model, sequence_frames, every=max(1, frames // 12))
    settings = (
        f"{'Full' if full else 'Quick'} version (`matfit bench{' --full' if full else ''}`), model {model_path}, targets at "
        f"{model.resolution} px rendered at 256 spp; {seeds} seeds; basin-hopping time-boxed to {basin_seconds:g} s per run; "
        f"{frames} sequence frames. Total {time.perf_counter() - started:.0f} s on this machine."
    )
    images.write(str(out / "rmse-vs-evaluations.png"), images.srgb_decode(bench_module.budget_plot(main)))
    report_text = bench_module.suite_report(main, optimisers, sequence_text, seeds=seeds, settings=settings)
    files.write_text(str(out / "report.md"), report_text)
    files.write_text(
        str(out / "report.json"),
        json.dumps({"main": main, "optimisers": optimisers, "sequence": sequence_text, "settings": settings}, indent=1) + "\n",
    )
    typer.echo(report_text)


class TrainingProgress:
    """Shows training: a bar per epoch with loss and throughput on a terminal, a line per epoch otherwise."""

    def __init__(self):
        self.bar = None
        self.task = None
        self.label = ""
        if sys.stderr.isatty():
            from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn
            from rich.progress import Progress as RichProgress

            self.bar = RichProgress(
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[stats]}"),
                TimeRemainingColumn(),
            )
            self.bar.start()

    def start(self, name: str, epoch: int, epochs: int, steps: int) -> None:
        self.label = f"{name} epoch {epoch}/{epochs}"
        if self.bar is not None:
            self.task = self.bar.add_task(self.label, total=steps, stats="")

    def step(self, step: int, loss: float, samples_per_second: float) -> None:
        if self.bar is not None:
            self.bar.update(self.task, completed=step, stats=f"loss {loss:.5f}  {samples_per_second:.0f} samples/s")

    def end_epoch(self, record: dict) -> None:
        figures = {key: value for key, value in record.items() if key not in ("epoch", "seconds")}
        text = "  ".join(f"{key} {value:.5g}" for key, value in figures.items())
        line = f"{self.label}: {text}  ({record['seconds']:.1f} s)"
        if self.bar is not None:
            self.bar.update(self.task, description=line, stats="")
        else:
            typer.echo(line, err=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


@command
def train(
    arch: Annotated[
        str, typer.Option(help="What to train: decoder, 1 to 9 (one encoder), 1..9 (all nine), all (decoder and nine), or a comma list.")
    ],
    dataset_path: Annotated[Path, typer.Option("--dataset", help="A finished `matfit render-dataset` directory.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Model directory: weights, metrics, and checkpoints/ for resuming.")] = Path(
        "runs/model"
    ),
    epochs: Annotated[
        int | None, typer.Option(help="Epochs per network (default: decoder 20, encoders 10; 4 and 5: 8, 7: 5, 9: 20).")
    ] = None,
    batch_size: Annotated[int, typer.Option(help="Samples per training step.")] = 64,
    learning_rate: Annotated[float, typer.Option(help="Peak Adam learning rate (warm-up, then cosine decay).")] = 1e-3,
    seed: Annotated[int, typer.Option(help="Seed of initialisation, shuffling and dropout.")] = 0,
) -> None:
    """Train the decoder and/or the encoders; run the same command again to resume after an interruption."""
    from matfit import train as train_module

    names = train_module.parse_arch(arch)
    if not 0.0 < learning_rate <= 1.0:
        raise TrainingError(f"--learning-rate {learning_rate} is out of range: use a value in (0, 1]")
    check_range("--seed", seed, 0, 2**31 - 1)
    data = dataset.open_dataset(str(dataset_path))
    train_module.check_finished(data)
    if out.exists() and not out.is_dir():
        raise files.OutputError(f"--out {out} is a file: give a directory for the model")
    out.mkdir(parents=True, exist_ok=True)
    progress = TrainingProgress()
    try:
        for name in names:
            config = train_module.Config(epochs or train_module.DEFAULT_EPOCHS[name], batch_size, learning_rate, seed=seed)
            metrics = train_module.train_network(name, data, str(out), config, progress)
            if "validation_rmse" in metrics:
                figure = f"validation image RMSE {metrics['validation_rmse']:.2f} (0-255 sRGB)"
            else:
                figure = f"validation parameter RMSE {metrics['validation_parameter_rmse']:.4f} (unit cube)"
            typer.echo(f"{name}: {metrics['epochs']} epochs, {figure}, {metrics['wall_time_s']:.0f} s -> {out}", err=True)
    except KeyboardInterrupt:
        progress.close()
        typer.echo(f"interrupted: finished epochs are saved in {out / 'checkpoints'}; run the same command to resume", err=True)
        raise typer.Exit(130) from None
    progress.close()


@command
def evaluate(
    model_path: Annotated[Path, typer.Option("--model", help="Model directory (decoder.msgpack, encoder-N.msgpack).")] = DEFAULT_MODEL,
    references: Annotated[
        Path, typer.Option(help="Held-out reference dataset, e.g. `matfit render-dataset ref --spp 256 --seed 1`.")
    ] = Path("datasets/reference"),
    card: Annotated[
        bool, typer.Option("--card/--no-card", help="Also write evaluation.json and MODEL.md into the model directory.")
    ] = False,
) -> None:
    """Measure a model against clean references: decoder RMSE, each encoder's errors, best-of-n."""
    from matfit import evaluate as evaluate_module
    from matfit import models

    model = models.load_model(str(model_path))
    evaluation = evaluate_module.evaluate(model, dataset.open_dataset(str(references)))
    if card:
        for path in evaluate_module.write_report(model, evaluation):
            typer.echo(f"wrote {path}", err=True)
    typer.echo(evaluate_module.card(model, evaluation))


def main() -> None:
    """Console-script entry point."""
    app()
