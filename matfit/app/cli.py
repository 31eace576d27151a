"""The `matfit` command line: each command parses its options, calls one library function and prints.

Errors a user can fix (`errors.MatfitError`, and Typer's own usage errors) become one `error:` line
and exit code 2; Ctrl-C or `kill` becomes one `interrupted:` line and exit code 130. JAX, Mitsuba
and the networks are imported inside the commands that need them, so `matfit params` starts fast.
Options that several commands take are declared once, in `options`.
"""

from __future__ import annotations

import functools
import os
import sys
from importlib import metadata
from pathlib import Path
from typing import Annotated, Any

import typer

import matfit
from matfit import documents, interrupt, params
from matfit.app import bench_commands, console, fit_lines, options
from matfit.app import progress as progress_module
from matfit.fitting.methods import Box, Method, Settings
from matfit.model import dataset, dataset_workers, dataset_writing
from matfit.rendering import presets

app = typer.Typer(
    cls=console.OneLineErrors,
    help="Turn an edited picture of a material into photorealistic principled-BSDF parameters.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)
command = functools.partial(console.command, app)
echo_lines = console.echo_lines
log = functools.partial(typer.echo, err=True)  # progress, notices and what was written go to standard error


def print_version(asked: bool) -> None:
    """Prints the installed matfit's version (pyproject.toml's, as pip recorded it) and ends the process."""
    if not asked:
        return
    try:
        typer.echo(metadata.version("matfit"))
    except metadata.PackageNotFoundError:
        message = "matfit is not installed, so it has no version: run `make install` or `pip install .`"
        raise typer.BadParameter(message) from None
    raise typer.Exit()


@app.callback()
def root(
    version: Annotated[
        bool, typer.Option("--version", callback=print_version, is_eager=True, help="Print the version and exit.")
    ] = False,
) -> None:
    """Turn an edited picture of a material into photorealistic principled-BSDF parameters."""


@command
def render(
    params_file: Annotated[Path | None, typer.Argument(help="params.json (names left out take defaults).")] = None,
    output: Annotated[Path, options.output("Image: .png/.jpg/.tif (8-bit sRGB) or .exr (linear).")] = Path(
        "render.png"
    ),
    size: options.Size = 512,
    spp: options.Spp = 256,
    preset: Annotated[str | None, typer.Option(help=f"A named material: {', '.join(presets.PRESETS)}.")] = None,
    random: Annotated[
        bool, typer.Option("--random", help="A random material from the training distribution (see --seed).")
    ] = False,
    seed: Annotated[int, options.seed("Seed of the random material and of the render's noise.")] = 0,
    variant: options.Variant = None,
    scene: options.SceneFile = None,
    object: options.SceneObject = None,
) -> None:
    """Render one material in the test scene with Mitsuba: the artist's starting image (--scene: in a scene of your
    own, on its shape --object, --size pixels on the longer side)."""
    from matfit.rendering import engine as render_module

    values = presets.material(options.text(params_file), preset, seed if random else None)
    if random:
        typer.echo(documents.dumps(params.params_document(values, source=f"--random --seed {seed}")), nl=False)
    if scene is not None or object is not None:
        from matfit.api import scenes

        written = scenes.render_file(
            values, options.scene(scene, object), str(output), size=size, spp=spp, seed=seed, variant=variant
        )
        log(f"wrote {output} ({written[0]}x{written[1]}, {spp} spp, shape {object!r} of {scene})")
        return
    inputs = {"params_file": options.text(params_file)}
    done = render_module.render_file(values, str(output), size, spp, seed, variant, inputs)
    echo_lines(done.notices)
    log(f"wrote {output} ({size}x{size}, {spp} spp, {done.variant}, {done.seconds:.1f} s)")


@command(name="presets")
def presets_sheet(
    output: Annotated[Path, options.output("Contact sheet to write (.png, .jpg or .exr).")] = Path("presets.png"),
    size: Annotated[int, typer.Option(min=32, max=1024, help="Side of each tile in pixels.")] = 128,
    spp: options.Spp = 256,
    variant: options.Variant = None,
) -> None:
    """Render every preset side by side, labelled, into one picture."""
    from matfit import images

    images.check_output(str(output))
    images.write(str(output), presets.sheet(size, spp, variant))
    log(f"wrote {output} ({len(presets.PRESETS)} presets)")


@command(name="blender-check")
def blender_check(
    out: Annotated[Path, options.out("Folder for blender-check.md and blender-check.png.")] = Path("blender-check"),
    preset: Annotated[list[str] | None, typer.Option(help="A preset to compare (repeat it; default: all).")] = None,
    params_file: options.ParamsFiles = None,
    size: Annotated[int, typer.Option(min=16, max=512, help="Image side in pixels.")] = 64,
    spp: Annotated[int, typer.Option(min=1, max=dataset.MAX_SPP, help="Samples per pixel, in both renderers.")] = 256,
    blender: options.BlenderPython = None,
    variant: options.Variant = None,
) -> None:
    """Render materials through the exported Blender script in Cycles and with Mitsuba, and compare them."""
    from matfit.rendering import blender as round_trip

    setup = round_trip.Setup(size, spp, blender, variant)
    comparison = round_trip.check(str(out), preset or None, [str(path) for path in params_file or []], setup, log)
    typer.echo(round_trip.table(comparison), nl=False)
    log(f"wrote {out / round_trip.TABLE_FILE} and {out / round_trip.PICTURE_FILE}")


@command(name="params")
def parameters() -> None:
    """List the 19 shader parameters: name, range, default, unit and meaning."""
    for p in params.PARAMETERS:
        typer.echo(f"{p.name:16} [{p.low:g}, {p.high:g}]  default {p.default:g}  {p.unit:14} {p.meaning}")


@command(interrupted="the server stopped; nothing was written")
def serve(
    model: options.Model = options.DEFAULT_MODEL,
    host: options.Host = "127.0.0.1",
    port: options.Port = 8765,
    watch: options.Watch = None,
    variant: options.Variant = None,
) -> None:
    """Serve a local page that fits edited pictures as you save them (--watch), with sliders and a Mitsuba render."""
    from matfit.app.serve import server

    server.serve(
        str(model),
        host,
        port,
        options.text(watch),
        ready=lambda url: log(f"open {url} (Ctrl-C stops)"),
        variant=variant,
    )


@command(interrupted="finished samples are saved; run the same command to resume")
def render_dataset(
    out: Annotated[Path, typer.Argument(help="Dataset directory (created, resumed or grown).")],
    count: Annotated[int, typer.Option(help="Total number of samples the dataset should hold.")] = 20000,
    resolution: Annotated[int, typer.Option(help="Image side in pixels.")] = 64,
    spp: Annotated[int, typer.Option(help="Samples per pixel.")] = 16,
    seed: Annotated[int, options.seed("Seed of the parameter sampling and of the renders' noise.")] = 0,
    workers: Annotated[
        int | None,
        typer.Option(
            help=f"Rendering processes, one thread each (default: one per core; {dataset_workers.GPU_WORKERS} on a "
            "GPU).",
            show_default=False,
        ),
    ] = None,
    variant: options.Variant = None,
    ray: Annotated[
        str | None,
        typer.Option(help="Render on Ray (.[cluster]): 'local' (--workers CPUs, for this run), 'auto' or HOST:PORT."),
    ] = None,
    sampler: options.Sampler = "uniform",
) -> None:
    """Render a training set of sampled materials; run it again to resume or to grow it."""
    from matfit.app.progress import Progress

    with Progress(f"rendering {out}") as progress:
        counter = progress.counter()
        data, rendered, notices = dataset_writing.render_dataset(
            str(out), count, resolution, spp, seed, workers, variant, counter, ray_address=ray, sampler=sampler
        )
    echo_lines(notices)
    log(f"{out}: {count}/{count} samples ({rendered} rendered now, {resolution} px, {spp} spp, {data.meta['variant']})")


@command(name="fit", interrupted="nothing was written")
def fit_command(
    targets: Annotated[
        list[Path],
        typer.Argument(
            help="The edited picture: PNG, JPEG, TIFF (8/16-bit) or EXR (linear). Several are fitted in one process, "
            "each written to OUTPUT/<name>.params.json (and --report report.png to OUTPUT/<name>.report.png).",
            show_default=False,
        ),
    ],
    output: Annotated[
        Path | None,
        options.output(
            "params.json to write (feeds `matfit render`); with several pictures, the folder to write into."
        ),
    ] = None,
    model_path: options.Model = options.DEFAULT_MODEL,
    method: options.Fitting = Method.lbfgsb,
    evaluations: options.Evaluations = 1500,
    seed: Annotated[int, options.seed("Seed of the random start of --method optimize.")] = 0,
    mask: options.Mask = None,
    box: options.BoxOption = Box.clip,
    polish_steps: options.Polish = 0,
    report: options.Report = None,
    render: options.RenderOutput = None,
    size: options.Size = 512,
    spp: options.Spp = 256,
    mitsuba_xml: options.MitsubaXml = None,
    blender: options.BlenderScript = None,
    init: options.Init = None,
    starts: options.Starts = Settings.starts,
    iterations: options.Iterations = Settings.iterations,
    narrow_after: options.NarrowAfter = Settings.narrow_after,
    verify: options.Verify = True,
    refine: options.Refine = 0,
    corrections: options.Corrections = None,
    variant: options.Variant = None,
    answer: options.Answer = "clean",
    scene: options.SceneFile = None,
    object: options.SceneObject = None,
) -> None:
    """Find the shader parameters whose render looks most like the edited picture (--scene: a render of a scene of
    your own, the material of its shape --object fitted there)."""
    from matfit.app import worker

    text = options.text
    several = len(targets) > 1
    written = str(output or ("." if several else "params.json"))
    outputs = matfit.Outputs(written, text(report), text(render), size, spp, text(mitsuba_xml), text(blender))
    if scene is not None or object is not None:
        chosen_scene = options.scene(scene, object)
        # the model guesses the start of a shape whose material matfit cannot read (in `matfit worker`, its warm one);
        # no render pool is started for it: the fit renders the scene itself
        chosen_options: dict[str, Any] = {"mask": text(mask), "init": text(init), "refine": refine, "outputs": outputs}
        with (
            progress_module.Progress(f"fitting {object!r} in {scene}") as shown,
            worker.fitter(str(model_path), variant, verify=False) as fitter,
        ):
            if several:
                fit_lines.fit_several(
                    fitter, targets, written, scene=chosen_scene, progress=shown.steps(), **chosen_options
                )
                return
            fitted = fitter.fit(str(targets[0]), scene=chosen_scene, progress=shown.steps(), **chosen_options)
        echo_lines(fitted.notices)
        log(fitted.summary)
        return
    settings = Settings(
        method,
        evaluations,
        box,
        polish_steps=polish_steps,
        starts=starts,
        iterations=iterations,
        narrow_after=narrow_after,
    )
    chosen = {
        "mask": text(mask),
        "init": text(init),
        "settings": settings,
        "verify": verify,
        "corrections": corrections,
        "answer": answer,
        "refine": refine,
        "seed": seed,
        "outputs": outputs,
    }
    # Verification's Mitsuba starts in child processes now, on the other cores, while this one imports JAX
    # (in `matfit worker`, the fitter is its warm one: the model loaded, the render pool running).
    with worker.fitter(str(model_path), variant, verify=verify and not refine) as fitter:
        if several:
            fit_lines.fit_several(fitter, targets, written, **chosen)
            return
        fitted = fitter.fit(str(targets[0]), **chosen, answers=worker.answers(fit_lines.report_answer))
    echo_lines(fitted.notices)
    log(fitted.summary)


@command(name="worker", interrupted="the worker stopped; the fit in hand wrote nothing")
def worker_command() -> None:
    """Run `matfit fit` for each JSON request line on standard input, its model and Mitsuba kept warm between fits.

    A request is {"id": 1, "arguments": ["fit", "edited.png", "-o", "params.json", ...]}; each answer is one JSON
    line on standard output, {"id": 1, "exit": 0, "output": "..."}. A request with "stages": true hears each stage's
    answer first, as it lands: {"id": 1, "stage": "neural", "document": its params.json}. Ends when standard input
    ends. The Blender extension's (docs/blender.md).
    """
    from matfit.app import worker

    # Replies go to the standard output this process was given; anything else written there (a library's own
    # message, a render child's) goes to standard error instead.
    sys.stdout.flush()
    replies = os.fdopen(os.dup(sys.stdout.fileno()), "w", encoding="utf-8")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    worker.serve(app, sys.stdin.buffer, replies, on_close=interrupt.exit_now)


@command(interrupted="finished frames are saved; run the same command to resume")
def sequence(
    frames: Annotated[
        Path,
        typer.Argument(help="Folder of frames (PNG, JPEG, TIFF, EXR) in natural order: frame_2 before frame_10."),
    ],
    out: Annotated[Path, options.out("Folder: one JSON per frame, summary.md, preview.png.")] = Path("sequence"),
    model_path: options.Model = options.DEFAULT_MODEL,
    evaluations: options.Evaluations = 100,
    method: options.Fitting = Method.hybrid,
    reinit: Annotated[
        bool, typer.Option(help="Add the previous frame's optimum to the best-of-n pool (--scene: start from it).")
    ] = True,
    render: Annotated[
        bool, typer.Option("--render", help="Also render each fit with Mitsuba (<frame>-render.png).")
    ] = False,
    size: options.Size = 256,
    spp: options.Spp = 64,
    init: options.Init = None,
    scene: options.SceneFile = None,
    object: options.SceneObject = None,
    refine: Annotated[
        int, typer.Option(min=0, max=options.MAX_REFINE, help="With --scene: each frame's fit's steps (0: 48).")
    ] = 0,
    variant: options.Variant = None,
    mask: options.Mask = None,
) -> None:
    """Fit every frame of an edited sequence, reusing each optimum for the next frame; resumable (--scene: frames of
    a scene of your own, the material of its shape --object fitted there, --refine its steps)."""
    from matfit.app.progress import Progress

    if scene is not None or object is not None:
        with Progress(f"fitting {object!r} in {scene}") as shown:

            def frame_done(done: int, total: int, rate: float) -> None:
                shown.note(f"frame {done} of {total} fitted")

            fits = matfit.fit_sequence(
                frames,
                model=model_path,
                reinit=reinit,
                init=init,
                out=out,
                render=(size, spp) if render else None,
                progress=frame_done,
                scene=options.scene(scene, object),
                refine=refine,
                variant=variant,
                step_progress=shown.steps(),
                mask=options.text(mask),
            )
        figure = f"in {scene}, Mitsuba RMSE sum {sum(fit.mitsuba_rmse or 0.0 for fit in fits):.2f}"
    else:
        with Progress("fitting frames") as progress:
            fits = matfit.fit_sequence(
                frames,
                model=model_path,
                settings=Settings(method=method, evaluations=evaluations),
                reinit=reinit,
                init=init,
                out=out,
                render=(size, spp) if render else None,
                progress=progress.counter("frames/s"),
                refine=refine,
                variant=variant,
                mask=options.text(mask),
            )
        figure = f"RMSE sum {sum(fit.neural_rmse for fit in fits):.2f}"
    echo_lines(f"{os.path.basename(fit.document['sequence']['frame'])}: {note}" for fit in fits for note in fit.notices)
    typer.echo((out / "summary.md").read_text())  # the table the command wrote there
    log(f"{out}: {len(fits)} frames, {figure}")


@command(interrupted="finished epochs are saved in the model's checkpoints/; run the same command to resume")
def train(
    arch: Annotated[
        str,
        typer.Option(help="decoder, 1 to 9 (one encoder), 1..9 (all nine), all (decoder and nine), or a comma list."),
    ],
    dataset_paths: Annotated[
        list[Path],
        typer.Option("--dataset", help="A finished `matfit render-dataset` directory; repeat it to train on several."),
    ],
    out: Annotated[Path, options.out("Model directory: weights, metrics, and checkpoints/ for resuming.")] = Path(
        "runs/model"
    ),
    epochs: Annotated[
        int | None, typer.Option(help="Epochs per network (default: decoder 20, encoders 10; 4, 5: 8; 7: 5; 9: 20).")
    ] = None,
    batch_size: Annotated[int, typer.Option(help="Samples per training step.")] = 64,
    learning_rate: Annotated[float, typer.Option(help="Peak Adam learning rate (warm-up, then cosine decay).")] = 1e-3,
    seed: Annotated[int, options.seed("Seed of initialisation, shuffling and dropout.")] = 0,
    start_from: Annotated[
        Path | None,
        typer.Option(
            help="A model directory whose weights of each network start the run instead of fresh ones "
            "(e.g. more epochs at a lower --learning-rate)."
        ),
    ] = None,
    loss: Annotated[
        str,
        typer.Option(
            help="The decoder's loss: srgb (L2 on the encoded renders, the paper's) or linear (learns the "
            "encoding of the mean render, unbiased by render noise)."
        ),
    ] = "srgb",
    coarse_absorption: Annotated[
        bool,
        typer.Option(
            help="The decoder also predicts a path length per 2 x 2 pixels that dims each colour by its medium's "
            "extinction (Beer-Lambert), as the shipped one does; with --start-from a decoder without it, the layer "
            "is added. --no-coarse-absorption trains the plain decoder."
        ),
    ] = True,
) -> None:
    """Train the decoder and/or the encoders; run the same command again to resume after an interruption."""
    from matfit.app.progress import TrainingProgress
    from matfit.model import train as train_module
    from matfit.model import train_config

    names = train_config.parse_arch(arch)
    config = train_config.Config(
        epochs, batch_size, learning_rate, seed=seed, start_from=options.text(start_from), loss=loss
    )
    data = [dataset.open_dataset(str(path)) for path in dataset_paths]
    with TrainingProgress() as progress:
        # TrainingProgress is a train.Reporter by its methods, not by its class (app/progress imports no JAX).
        for name, metrics in train_module.train_networks(names, data, str(out), config, progress, coarse_absorption):  # type: ignore[arg-type]
            progress.note(f"{train_module.summary(name, metrics)} -> {out}")


@command
def evaluate(
    model_path: options.Model = options.DEFAULT_MODEL,
    references: Annotated[
        Path, typer.Option(help="Held-out references, e.g. `matfit render-dataset ref --spp 256 --seed 1`.")
    ] = Path("datasets/reference"),
    card: Annotated[
        bool, typer.Option(help="Also write evaluation.json and MODEL.md into the model directory.")
    ] = False,
    preset_spp: Annotated[
        int,
        typer.Option(
            min=1,
            max=65536,
            help="Samples per pixel of the presets' clean renders (made once, kept beside the references).",
        ),
    ] = 4096,
) -> None:
    """Measure a model against clean references: the decoder's RMSE, each encoder's errors, best-of-n.

    The decoder's RMSE over all references, each third (transmissive, scattering, opaque) and each preset.
    """
    from matfit.model import evaluate as evaluate_module
    from matfit.model import models

    data = dataset.open_dataset(str(references))  # the cheaper check first
    model = models.load_model(str(model_path))
    evaluation = evaluate_module.evaluate(model, data, preset_spp)
    if card:
        echo_lines(f"wrote {path}" for path in evaluate_module.write_report(model, evaluation))
    typer.echo(evaluate_module.card(model, evaluation))


bench_commands.register(command)  # `matfit bench` and `bench-*`, listed after the others
