"""Fitting an image file end to end: read the target and mask, fit, render the result, write every output together.

This is what `matfit fit` does, as a library function: `run(target, model, settings, outputs)`
reads and checks the inputs, fits (`fit.fit`), renders the result with Mitsuba where an output
needs it, and writes params.json, the report, the render and the exports under temporary names,
renaming them into place only once all of them were written.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from matfit import files, fit, images, models, params
from matfit.errors import ImageError, OutputError

PROJECT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_MODEL = os.path.join(PROJECT, "data", "models", "default")  # shipped in the repository
VERIFY_SPP = 256  # the Mitsuba render of the result at the model's resolution, for its RMSE and the report
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

    def check(self) -> None:
        """Raises OutputError for a path of the wrong kind or one that cannot be written, before any work is done."""
        if not self.params.lower().endswith(".json"):
            raise OutputError(f"output {self.params} must end in .json", field="output")
        for path in (self.report, self.render):
            if path is not None:
                images.check_extension(path)
        for path, suffix, name in ((self.mitsuba_xml, ".xml", "mitsuba_xml"), (self.blender, ".py", "blender")):
            if path is not None and not path.lower().endswith(suffix):
                raise OutputError(f"{name.replace('_', ' ')} {path} must end in {suffix}", field=name)
        for path in (self.params, self.report, self.render, self.mitsuba_xml, self.blender):
            if path is not None:
                files.check_writable(path)

    @property
    def needs_render(self) -> bool:
        """Returns whether an output shows the Mitsuba render of the result."""
        return self.report is not None or self.render is not None


@dataclass
class Outcome:
    """A finished fit of an image file: the result, the target as fitted, the params.json document, notices."""

    result: fit.Result
    target: np.ndarray  # sRGB (R, R, 3) at the model's resolution
    document: dict
    rendered: np.ndarray | None = None  # sRGB Mitsuba render of the result at the model's resolution
    notices: list[str] = field(default_factory=list)

    def summary(self, output: str) -> str:
        """Returns one line on what was found and how well."""
        result, document = self.result, self.document
        mitsuba = f", Mitsuba RMSE {document['mitsuba_rmse']:.2f}" if "mitsuba_rmse" in document else ""
        return (
            f"{output}: {document['method']}, {result.evaluations} evaluations, neural RMSE {result.rmse:.2f} "
            f"(start {result.chosen} {result.start_rmse:.2f}){mitsuba}, {document['wall_time_s']:.1f} s"
        )


def load_model(path: str) -> models.Model:
    """Returns the model of a directory, with JAX's compilation cache on (a second fit loads its compiled programs)."""
    models.enable_compilation_cache()
    return models.load_model(path)


def read_target(path: str, resolution: int, mask: str | None = None) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """Returns (sRGB target at the model's resolution, mask weights or None, notices) from image files."""
    loaded = images.load(path)
    weights = None
    if mask is not None:
        weights = fit.prepare_mask(images.load(mask).pixels, loaded.pixels.shape[:2], resolution, mask)
    target, notices = fit.prepare_target(loaded.pixels, resolution, path)
    return target, weights, [*loaded.notices, *notices]


def sha256(path: str) -> str:
    """Returns the SHA-256 of a file's bytes (what params.json records of its target)."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def run(
    target: str,
    model: models.Model | str,
    settings: fit.Settings,
    outputs: Outputs,
    mask: str | None = None,
    seed: int = 0,
) -> Outcome:
    """Fits the image file `target` with a model (or a model directory) and writes `outputs`; returns what was found.

    Every input is read and every output path checked before the fit; the outputs are written
    together at the end (`files.together`), so a failure leaves none of them.
    """
    started = time.perf_counter()
    settings.check()
    outputs.check()
    for path, name in ((target, "target"), (mask, "mask")):
        if path is not None and not os.path.isfile(path):
            raise ImageError(f"{name} {path} is not a file: give the picture's path", field=name)
    model_path = model if isinstance(model, str) else model.path
    model = load_model(model) if isinstance(model, str) else model
    target_srgb, weights, notices = read_target(target, model.resolution, mask)
    result = fit.fit(model, target_srgb, settings, weights, seed=seed)
    outcome = Outcome(result, target_srgb, {}, notices=notices)
    renderer = None
    extra = {}
    if outputs.needs_render:
        from matfit.render import Renderer

        renderer = Renderer(model.resolution, VERIFY_SPP)
        if renderer.notice:
            notices.append(renderer.notice)
        outcome.rendered = images.srgb_encode(renderer.render(result.values))
        extra["mitsuba_rmse"] = round(float(images.rmse(outcome.rendered, target_srgb)), 3)
    outcome.document = params.params_document(
        result.values,
        method=settings.method.value,
        evaluations=result.evaluations,
        neural_rmse=round(result.rmse, 3),
        start=result.chosen,
        start_rmse=round(result.start_rmse, 3),
        **extra,
        box=settings.box.value,
        polish_steps=settings.polish_steps,
        model=display_path(model_path),
        target=target,
        target_sha256=sha256(target),
        mask=mask,
        fit_seconds=round(result.seconds, 3),
        wall_time_s=0.0,
    )
    with files.together() as batch:
        write_outputs(outcome, outputs, batch, renderer)
        outcome.document["wall_time_s"] = round(time.perf_counter() - started, 3)
        files.write_text(batch.path(outputs.params), json.dumps(outcome.document, indent=2) + "\n")
    return outcome


def report_picture(outcome: Outcome) -> np.ndarray:
    """Returns the report: target | best-of-n start | fit (neural) | fit (Mitsuba render) | difference, as sRGB."""
    from matfit import report

    result = outcome.result
    panels = [
        (outcome.target, "target"),
        (result.start_image, f"best-of-n {result.start_rmse:.2f}"),
        (result.image, f"fit (neural) {result.rmse:.2f}"),
        (outcome.rendered, f"fit (Mitsuba) {outcome.document['mitsuba_rmse']:.2f}"),
        (report.difference(outcome.rendered, outcome.target), "|Mitsuba - target| x4"),
    ]
    return report.compose(panels)


def write_outputs(outcome: Outcome, outputs: Outputs, batch: files.Batch, renderer=None) -> None:
    """Writes the report, the large render and the exports of a fit into `batch` (params.json is the caller's)."""
    values = outcome.result.values
    if outputs.report is not None:
        images.write(batch.path(outputs.report), images.srgb_decode(report_picture(outcome)))
    if outputs.render is not None:
        from matfit.render import Renderer

        large = Renderer(outputs.render_size, outputs.render_spp, renderer.variant if renderer else None)
        images.write(batch.path(outputs.render), large.render(values))
    if outputs.mitsuba_xml is not None or outputs.blender is not None:
        from matfit import export

        if outputs.mitsuba_xml is not None:
            files.write_text(batch.path(outputs.mitsuba_xml), export.mitsuba_xml(values))
        if outputs.blender is not None:
            files.write_text(batch.path(outputs.blender), export.blender_script(values))
