"""Fitting an image file end to end: read the target and mask, fit, verify in Mitsuba, write every output together.

This is what `matfit fit` does, as a library function: `run(target, model, settings, outputs)`
reads and checks the inputs, fits (`search.fit`), lets Mitsuba choose among the fit's final
candidates (`verify.verify`, on by default), and writes params.json, the report, the render and
the exports under temporary names, renaming them into place only once all of them were written.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

from matfit import documents, files, images, params, programs, shipped
from matfit.errors import FitError, ImageError, OutputError
from matfit.fit import refine, search, verify
from matfit.fit.methods import CORRECTIONS
from matfit.model import models
from matfit.render import engine as render
from matfit.render.process import Background, Process

# The folder holding the package: the clone, or site-packages when installed (the shipped model reads
# matfit/data/model either way; a user's own paths lie outside it and stay as given).
PROJECT = str(shipped.PACKAGE.parent)
MAX_RENDER_SIZE = 4096


def display_path(path: str) -> str:
    """Returns a path as people should read it in reports: relative to the project when inside it, else as given."""
    absolute = os.path.abspath(path)
    if os.path.commonpath([absolute, PROJECT]) == PROJECT:
        return os.path.relpath(absolute, PROJECT)
    return path


@dataclass(frozen=True)
class Outputs:
    """The files a fit writes: params.json always, the others when named."""

    params: str
    report: str | None = None
    render: str | None = None
    render_size: int = 512
    render_spp: int = 256
    mitsuba_xml: str | None = None
    blender: str | None = None

    def check(self, inputs: dict[str, str | None] | None = None) -> None:
        """Raises OutputError, before any work is done, for a path of the wrong kind, one that cannot be written,
        one named twice, or one that is an input (`inputs`: {"target": path, ...}) that writing would overwrite."""
        if not self.params.lower().endswith(".json"):
            raise OutputError(f"output {self.params} must end in .json", field="output")
        for path in (self.report, self.render):
            if path is not None:
                images.check_extension(path)
        for path, suffix, name in ((self.mitsuba_xml, ".xml", "mitsuba_xml"), (self.blender, ".py", "blender")):
            if path is not None and not path.lower().endswith(suffix):
                raise OutputError(f"{name.replace('_', ' ')} {path} must end in {suffix}", field=name)
        named = {
            "output": self.params,
            "report": self.report,
            "render": self.render,
            "mitsuba_xml": self.mitsuba_xml,
            "blender": self.blender,
        }
        files.check_outputs(named, inputs)

    @property
    def needs_render(self) -> bool:
        """Returns whether an output shows the Mitsuba render of the result."""
        return self.report is not None or self.render is not None


@dataclass
class Outcome:
    """A finished fit of an image file: the answer, how it was found, the target as fitted, the params.json document."""

    result: search.Result
    target: np.ndarray  # sRGB (R, R, 3) at the model's resolution
    unit: np.ndarray  # the answer (unit cube): the fit's best, or what Mitsuba verification preferred
    image: np.ndarray  # phi(answer), sRGB
    neural_rmse: float
    verified: verify.Verified | None = None
    refined: refine.Refined | None = None
    rendered: np.ndarray | None = None  # sRGB Mitsuba render of the answer at the model's resolution
    variant: str | None = None  # the Mitsuba variant that verified, refined or rendered the answer; None: no Mitsuba
    document: dict = field(default_factory=dict)
    notices: list[str] = field(default_factory=list)

    @property
    def values(self) -> np.ndarray:
        """Returns the answer's physical parameters (19,)."""
        return params.from_unit(self.unit)

    def summary(self, output: str) -> str:
        """Returns one line on what was found and how well."""
        result, document = self.result, self.document
        mitsuba = ""
        if self.verified is not None:
            verified = self.verified
            mitsuba = f", Mitsuba RMSE {verified.rmse:.2f} (start {verified.start_rmse:.2f}; kept {verified.chosen})"
        elif "mitsuba_rmse" in document:
            mitsuba = f", Mitsuba RMSE {document['mitsuba_rmse']:.2f}"
        if self.refined is not None:
            refined = self.refined
            kept = "kept" if refined.accepted else "not kept"
            mitsuba += (
                f"; refined {refined.steps} steps: {refined.rmse_before:.2f} -> {refined.rmse_after:.2f} ({kept})"
            )
        return (
            f"{output}: {document['method']}, {result.evaluations} evaluations, neural RMSE {self.neural_rmse:.2f} "
            f"(start {result.chosen} {result.start_rmse:.2f}){mitsuba}, {document['wall_time_s']:.1f} s"
        )


def load_model(path: str) -> models.Model:
    """Returns the model of a directory, with JAX's compilation cache on (a second fit loads its compiled programs)."""
    programs.enable_compilation_cache()
    return models.load_model(path)


def read_target(path: str, resolution: int, mask: str | None = None) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """Returns (sRGB target at the model's resolution, mask weights or None, notices) from image files."""
    loaded = images.load(path)
    weights = None
    if mask is not None:
        weights = search.prepare_mask(images.load(mask).pixels, loaded.pixels.shape[:2], resolution, mask)
    target, notices = search.prepare_target(loaded.pixels, resolution, path)
    return target, weights, [*loaded.notices, *notices]


def run(
    target: str,
    model: models.Model | str,
    settings: search.Settings,
    outputs: Outputs,
    mask: str | None = None,
    seed: int = 0,
    init: str | None = None,
    verified: bool = True,
    refine_steps: int = 0,
    corrections: int | None = None,
    renderer: Process | None = None,
    variant: str | None = None,
) -> Outcome:
    """Fits the image file `target` with a model (or a model directory) and writes `outputs`; returns what was found.

    `init`: a params.json of the source material, whose parameters join best-of-n's candidates;
    `renderer`: a `process.Process` to verify with (`fit_file`), or None; `variant`: the Mitsuba variant of the
    renderer made when none is given (None: `engine.choose_variant`'s).
    `verified`: let Mitsuba choose among the fit's final candidates (`verify.verify`), after
    `corrections` rounds of correction (`correct.py`; None: `methods.CORRECTIONS` when verified,
    else none) from the best of them; `refine_steps`:
    then that many steps through Mitsuba's differentiable renderer (`refine.refine`). Every input
    is read and every output path checked before the fit; the outputs are written together at the
    end (`files.together`), so a failure leaves none of them.
    """
    started = time.perf_counter()
    outputs.check({"target": target, "mask": mask, "init": init})
    init_values = params.read_file(init) if init is not None else None
    outcome, used = fit_file(
        target,
        model,
        settings,
        mask,
        seed,
        init_values,
        verified,
        refine_steps,
        outputs.needs_render,
        renderer,
        source=init,
        corrections=corrections,
        variant=variant,
    )
    with files.together() as batch:
        write_outputs(outcome, outputs, batch, used)
        outcome.document["wall_time_s"] = round(time.perf_counter() - started, 3)
        files.write_text(batch.path(outputs.params), params_text(outcome))
    return outcome


def fit_file(
    target: str,
    model: models.Model | str,
    settings: search.Settings,
    mask: str | None = None,
    seed: int = 0,
    init_values: np.ndarray | None = None,
    verified: bool = True,
    refine_steps: int = 0,
    needs_render: bool = False,
    renderer=None,
    source: str | None = None,
    corrections: int | None = None,
    variant: str | None = None,
) -> tuple[Outcome, render.Renderer | Process | None]:
    """Returns (what a fit of the image file `target` found, with its params.json document; the renderer used).

    Writes nothing: `run` writes the CLI's files, `serve` offers the same ones for download.
    `init_values`: the source material's physical parameters (joining best-of-n's candidates), read
    from the file `source` (recorded in the document); `renderer`: a loaded `engine.Renderer` at the
    model's resolution to reuse, a `process.Process` (started early by the caller; it loads the scene
    here, and cannot refine), or None (a `process.Background` with `variant` is made when verification,
    refinement or a render output needs one). Refinement differentiates with the renderer's variant.
    """
    settings.check()
    if refine_steps < 0:
        raise FitError(f"refine steps {refine_steps} must be >= 0: use 0 to skip refinement", field="refine")
    if refine_steps and variant == render.SCALAR_VARIANT:
        raise FitError(
            f"refinement differentiates with {render.CUDA_VARIANT} or {render.LLVM_VARIANT}, not "
            f"{render.SCALAR_VARIANT}: leave --variant out or leave refinement off",
            field="variant",
        )
    corrections = (CORRECTIONS if verified else 0) if corrections is None else corrections
    verify.check_corrections(corrections)  # before the fit: no work for a bad count
    if corrections and not verified:
        raise FitError(
            f"{corrections} correction rounds need verification's renders: drop --no-verify or add --corrections 0",
            field="corrections",
        )
    for path, name in ((target, "target"), (mask, "mask")):
        if path is not None and not os.path.isfile(path):
            raise ImageError(f"{name} {path} is not a file: give the picture's path", field=name)
    extra = params.to_unit(init_values)[None] if init_values is not None else None
    model_path = model if isinstance(model, str) else model.path
    model = load_model(model) if isinstance(model, str) else model
    target_srgb, weights, notices = read_target(target, model.resolution, mask)
    background: Process | Background | None
    background = on_start = None
    if isinstance(renderer, Process):
        if refine_steps:
            raise ValueError("refinement renders through Mitsuba in this process: give a Renderer, or none")
        background, renderer = renderer, None
        background.load(model.resolution, verify.SPP)
    elif renderer is None and (verified or refine_steps or needs_render):
        background = Background(model.resolution, verify.SPP, variant)  # loads while the fit runs
    if background is not None and verified:

        def on_start(start: np.ndarray) -> None:
            verify.prefetch_start(background, start, corrections)

    result = search.fit(model, target_srgb, settings, weights, extra=extra, seed=seed, on_start=on_start)
    if not np.isfinite(result.rmse):  # the decoder's images hold NaN: no figure and no answer can be trusted
        raise FitError(
            f"the model {model_path} decodes images that are not finite (neural RMSE {result.rmse}): "
            "its weights are damaged; train it again or use another --model"
        )
    outcome = Outcome(result, target_srgb, result.unit, result.image, result.rmse, notices=notices)
    if background is not None:
        renderer = background.renderer()
        notices.extend([renderer.notice] if renderer.notice else [])
    if renderer is not None:
        outcome.variant = renderer.variant
    if verified:
        outcome.verified = verify.verify(
            background or renderer, result, target_srgb, weights, corrections=corrections, model=model
        )
        outcome.unit, outcome.rendered = outcome.verified.unit, outcome.verified.rendered
    elif renderer is not None and not refine_steps:
        outcome.rendered = images.srgb_encode(renderer.render(result.values, seed=verify.SEED))
    if refine_steps:
        outcome.refined = refine.refine(outcome.unit, target_srgb, refine_steps, weights, renderer)
        outcome.unit, outcome.rendered = outcome.refined.unit, outcome.refined.rendered
    if verified or refine_steps:
        decoded = result.decoded(outcome.unit)  # verification keeps a point the fit decoded (or a round decoded)
        if decoded is None and outcome.verified is not None:
            decoded = outcome.verified.decoded.get(outcome.verified.chosen)
        outcome.image = model.decode(outcome.unit)[0] if decoded is None else decoded
        outcome.neural_rmse = float(images.rmse(outcome.image, target_srgb, weights))
    outcome.document = document(outcome, settings, model_path, target, mask, source)
    return outcome, renderer


def params_text(outcome: Outcome) -> str:
    """Returns the params.json of a fit, as written."""
    return documents.dumps(outcome.document)


def document(
    outcome: Outcome, settings: search.Settings, model_path: str, target: str, mask: str | None, init: str | None
) -> dict:
    """Returns the params.json document of a fit: the 19 values with units, and how they were found."""
    result, checked = outcome.result, outcome.verified
    mitsuba = {}
    if checked is not None:
        mitsuba = {
            "mitsuba_rmse": round(checked.rmse, 3),
            "verification": {
                "kept": checked.chosen,
                "mitsuba_rmse": {name: round(value, 3) for name, value in checked.figures.items()},
                "margins": {  # standard errors behind the kept one; null: renders alike in every batch
                    name: round(value, 2) if np.isfinite(value) else None for name, value in checked.margins.items()
                },
                "batches": checked.batches,
                "corrections": checked.corrections,
                "spp": verify.SPP,
                "seconds": round(checked.seconds, 3),
            },
        }
    elif outcome.rendered is not None:
        mitsuba = {"mitsuba_rmse": round(float(images.rmse(outcome.rendered, outcome.target)), 3)}
    if outcome.refined is not None:
        refined = outcome.refined
        mitsuba["mitsuba_rmse"] = round(refined.rmse, 3)  # the kept point's acceptance render
        mitsuba["refinement"] = {
            "steps": refined.steps,
            "kept": refined.accepted,
            "mitsuba_rmse_before": round(refined.rmse_before, 3),
            "mitsuba_rmse_after": round(refined.rmse_after, 3),
            "seconds": round(refined.seconds, 3),
        }
    return params.params_document(
        outcome.values,
        method=settings.method.value,
        evaluations=result.evaluations,
        neural_rmse=round(outcome.neural_rmse, 3),
        start=result.chosen,
        start_rmse=round(result.start_rmse, 3),
        **mitsuba,
        box=settings.box.value,
        polish_steps=settings.polish_steps,
        model=display_path(model_path),
        target=target,
        target_sha256=files.sha256(target),
        mask=mask,
        init=init,
        mitsuba_variant=outcome.variant,
        fit_seconds=round(result.seconds, 3),
        wall_time_s=0.0,
    )


def report_picture(outcome: Outcome) -> np.ndarray:
    """Returns the report: target | best-of-n start | fit (neural) | fit (Mitsuba render) | difference, as sRGB."""
    from matfit.fit import report

    result = outcome.result
    assert outcome.rendered is not None, "fit_file renders the answer when a report is asked for (needs_render)"
    panels = [
        (outcome.target, "target"),
        (result.start_image, f"best-of-n {result.start_rmse:.2f}"),
        (outcome.image, f"fit (neural) {outcome.neural_rmse:.2f}"),
        (outcome.rendered, f"fit (Mitsuba) {outcome.document['mitsuba_rmse']:.2f}"),
        (report.difference(outcome.rendered, outcome.target), "|Mitsuba - target| x4"),
    ]
    return report.compose(panels)


def write_outputs(
    outcome: Outcome, outputs: Outputs, batch: files.Batch, renderer: render.Renderer | Process | None = None
) -> None:
    """Writes the report, the large render and the exports of a fit into `batch` (params.json is the caller's)."""
    values = outcome.values
    if outputs.report is not None:
        images.write(batch.path(outputs.report), images.srgb_decode(report_picture(outcome)))
    if outputs.render is not None:
        from matfit.render.engine import Renderer

        large = Renderer(outputs.render_size, outputs.render_spp, renderer.variant if renderer else None)
        images.write(batch.path(outputs.render), large.render(values))
    if outputs.mitsuba_xml is not None or outputs.blender is not None:
        from matfit.render import export

        if outputs.mitsuba_xml is not None:
            files.write_text(batch.path(outputs.mitsuba_xml), export.mitsuba_xml(values))
        if outputs.blender is not None:
            files.write_text(batch.path(outputs.blender), export.blender_script(values))
