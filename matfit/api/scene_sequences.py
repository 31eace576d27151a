"""Edited frames of a scene of the user's own, its shape's material fitted in each, from the previous frame's answer:
`matfit.fit_sequence(..., scene=)` and `matfit sequence FRAMES --scene room.xml --object vase` (`fit_scene_sequence`).
docs/scenes.md#a-sequence-of-frames."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from matfit import documents, files, images, params
from matfit.api import scene_fits, scenes
from matfit.api.arguments import Picture, path_text, whole
from matfit.api.material import Material
from matfit.api.results import Fit
from matfit.api.scenes import Scene
from matfit.errors import ImageError, SceneError

if TYPE_CHECKING:
    from matfit.fitting.scene_fit import SceneOutcome
    from matfit.fitting.sequence import Frame
    from matfit.model.models import Loader
    from matfit.rendering.scene_file import SceneFile

PREVIEW_SIZE = 128  # pixels on the longer side of each frame's picture in preview.png
PREVIEW_FRAMES = 12  # the frames preview.png shows, spread over the sequence


@dataclass(frozen=True)
class _Chain:
    """What every frame of one scene sequence shares: the scene (`read`: its file read), the first frame's start
    (`start`, `named` as params.json names it; None: the shape's own material, else `model`'s guess), whether each
    next frame starts from the previous answer (`reinit`), the fits' steps, variant and step progress, and the mask
    every frame is fitted through (None: the region each fit finds)."""

    scene: Scene
    read: SceneFile
    start: Material | None
    named: str | None
    reinit: bool
    steps: int
    variant: str | None
    model: Loader
    step_progress: Callable[[str, int, int, float], None] | None
    mask: Picture | None = None

    def fit(
        self, picture: Picture, previous: np.ndarray | None, chained: bool, linear: bool
    ) -> tuple[SceneOutcome, dict[str, Any], str]:
        """Returns (the scene fit of a frame, its params.json document, the start's label for the summary): from
        `previous` (physical; None: the shape's own material or the guess), which is the previous frame's answer
        where `chained`."""
        from matfit.fitting import sequence

        outcome, document = scenes.fit_in_scene(
            picture,
            self.scene,
            init=previous,
            init_name=sequence.PREVIOUS if chained else self.named,
            mask=self.mask,
            linear=linear,
            steps=self.steps,
            variant=self.variant,
            outputs=None,
            progress=self.step_progress,
            model=self.model,
        )
        if chained:
            return outcome, document, sequence.PREVIOUS
        return outcome, document, sequence.INIT if self.start is not None else document["start"]["material"]


def fit_scene_sequence(
    frames: object,
    scene: Scene,
    *,
    init: str | os.PathLike[str] | Material | None,
    reinit: bool,
    linear: bool,
    out: str | None,
    render: tuple[int, int] | None,
    refine: int,
    variant: str | None,
    model: Loader,
    model_path: str,
    progress: Callable[[int, int, float], None] | None,
    step_progress: Callable[[str, int, int, float], None] | None,
    mask: Picture | None = None,
) -> list[Fit]:
    """Returns the fits of a scene's frames in order (`fit_sequence(..., scene=)`'s): each frame's shape fitted in
    the scene (`scenes.fit_in_scene`, `refine` steps, 0: the default), the first from `init` (None: the shape's own
    material, else `model`'s guess), each next one from the previous frame's answer with `reinit` (without it, from
    the first's start), through `mask` (of the frames' size) where given. `frames`: pictures, or with `out` the folder
    of the frames, each frame's params.json written at once to `out/<frame>.json` and the same call again resuming
    (`_written`); `render` = (size, spp) checked."""
    from matfit.fitting import scene_fit

    read = scenes.check_scene(scene).read()  # a scene that fails, before anything
    steps = whole("refine", refine or scene_fit.STEPS, 1, scenes.MAX_STEPS, SceneError)
    start = None if init is None else init if isinstance(init, Material) else Material.read(init)
    named = "Material" if isinstance(init, Material) else None if init is None else path_text(init)
    chain = _Chain(scene, read, start, named, reinit, steps, variant, model, step_progress, mask)
    if out is not None:
        return _written(frames, chain, out, render, model_path, progress)
    fits: list[Fit] = []
    for frame in cast(Iterable[Picture], frames):  # a list: `sequences.check_written`
        chained = reinit and bool(fits)
        values = fits[-1].material.array() if chained else None if start is None else start.array()
        outcome, document, label = chain.fit(frame, values, chained, linear)
        fits.append(dataclasses.replace(scene_fits.fit_of(outcome, document, document["target"]), start=label))
    return fits


def _written(
    frames: object,
    chain: _Chain,
    out: str,
    render: tuple[int, int] | None,
    model_path: str,
    progress: Callable[[int, int, float], None] | None,
) -> list[Fit]:
    """Returns the fits of the frames of a folder, written into `out` as `matfit sequence --scene` writes them: every
    frame's aspect and every output checked before the first fit (none may be a frame, the init, the scene's file or
    one it names, or the model's), each frame's params.json (the scene fit's, with its `sequence` record) written
    at once, a frame whose file is there, fitted from the same start with the same steps and scene, kept; then the
    renders, summary.md and preview.png."""
    from matfit.fitting import scene_fit, sequence

    paths = sequence.list_frames(path_text(cast(str, frames)))  # a folder: `sequences.check_written`
    sequence.check_outputs(
        paths,
        out,
        rendered=render is not None,
        init=chain.named if chain.named != "Material" else None,
        model=model_path,
        inputs=[*scenes.scene_inputs(chain.read), ("mask", _mask_path(chain.mask))],
    )
    mask_size = None if chain.mask is None else _mask_size(chain.mask)
    for path in paths:
        width, height = images.header(path)[:2]
        scene_fit.check_aspect(chain.read, height, width, f"the frame {path}")
        if mask_size is not None and mask_size != (width, height):
            raise ImageError(
                f"the mask is {mask_size[0]}x{mask_size[1]}, the frame {path} {width}x{height}: give a mask of the "
                "frames' size",
                field="mask",
            )
    created = not os.path.isdir(out)
    os.makedirs(out, exist_ok=True)
    try:
        results, fits = _frames(paths, chain, out, progress)
    except BaseException:
        if created and not os.listdir(out):  # nothing finished: leave no empty folder behind
            os.rmdir(out)
        raise
    if render is not None:
        size, spp = render

        def draw(unit: np.ndarray) -> np.ndarray:
            values = params.from_unit(unit)
            return scenes.render_values(values, chain.scene, size=size, spp=spp, seed=0, variant=chain.variant)

        sequence.render_frames(results, out, size, spp, draw)
    files.write_text(os.path.join(out, sequence.SUMMARY_FILE), sequence.summary_table(results, "steps", "Mitsuba RMSE"))
    images.write(os.path.join(out, sequence.PREVIEW_FILE), images.srgb_decode(preview(fits)))
    return fits


def _frames(
    paths: list[str], chain: _Chain, out: str, progress: Callable[[int, int, float], None] | None
) -> tuple[list[Frame], list[Fit]]:
    """Returns each frame's record and fit, fitting (and writing at once) those not fitted already from the same
    start with the same steps in the same scene (`sequence.stale`: the frame changed, or the answer it starts from;
    or the scene file or a file it names changed, `scenes.identity`)."""
    from matfit.fitting import sequence

    began = time.perf_counter()
    settings = {"method": "scene", "steps": chain.steps, "reinit": chain.reinit}
    identity = scenes.identity(chain.read)
    mask_sha256 = None if chain.mask is None else _mask_sha256(chain.mask)
    first = None if chain.start is None else [float(u) for u in params.to_unit(chain.start.array())]
    results: list[Frame] = []
    fits: list[Fit] = []
    for index, path in enumerate(paths):
        json_path = sequence.frame_json_path(out, path)
        finished = sequence.read_finished(json_path, settings)
        chained = chain.reinit and index > 0
        previous = [float(u) for u in results[-1].unit] if chained else first
        computed_from = {"frame_sha256": files.sha256(path), "previous": previous}
        note = sequence.stale(finished, computed_from, first=not chained)
        kept = None
        if finished is not None and note is None:
            document = finished[2]
            if document["sequence"].get("scene") != identity:
                note = (
                    "the scene file, or a file it names, is not the one its result on disk was fitted in: fitted again"
                )
            elif document["sequence"].get("mask_sha256") != mask_sha256:
                note = "the mask is not the one its result on disk was fitted through: fitted again"
            else:
                kept = finished[0], _kept(path, finished[0], document, chain)
        if kept is not None:
            frame, fit = kept
        else:
            # from the unit-cube start the frame's record holds, so that a resumed run starts each frame as a run
            # that was not stopped does (a kept frame's answer is read back from that record)
            values = None if previous is None else params.from_unit(np.asarray(previous, np.float64))
            outcome, document, label = chain.fit(path, values, chained, False)
            unit = params.to_unit(outcome.values)
            frame = sequence.Frame(
                path, unit, outcome.rmse, label, outcome.start_rmse, len(outcome.losses), outcome.seconds, note=note
            )
            document["sequence"] = {
                "frame": path,
                "index": index,
                "rmse": outcome.rmse,
                "start": label,
                "start_rmse": outcome.start_rmse,
                "evaluations": len(outcome.losses),
                "seconds": outcome.seconds,
                "settings": settings,
                "scene": identity,
                "mask_sha256": mask_sha256,
                **computed_from,
                "unit": [float(u) for u in unit],
            }
            files.write_text(json_path, documents.dumps(document))
            fit = scene_fits.fit_of(outcome, document, json_path)
            fit = dataclasses.replace(fit, start=label, notices=(*fit.notices, *((note,) if note else ())))
        results.append(frame)
        fits.append(fit)
        if progress is not None:
            progress(index + 1, len(paths), (index + 1) / max(time.perf_counter() - began, 1e-9))
    return results, fits


def _kept(path: str, frame: Frame, document: dict[str, Any], chain: _Chain) -> Fit:
    """Returns the `Fit` of the frame `path` an earlier run fitted: its picture at the fit's size and its answer
    rendered there as the fit's judge renders it (the file holds no picture)."""
    from matfit.fitting import scene_fit, scene_judge

    read, values = chain.read, params.from_unit(np.asarray(frame.unit, np.float64))
    size = read.size(scene_fit.FIT_SIZE)
    target = np.clip(images.srgb_encode(images.resample(images.load(path).pixels, *size)), 0.0, 1.0)
    linear = scenes.render_values(
        values,
        chain.scene,
        size=scene_fit.FIT_SIZE,
        spp=scene_judge.JUDGE_SPP,
        seed=scene_judge.JUDGE_SEED,
        variant=chain.variant,
    )
    image = np.clip(images.srgb_encode(linear), 0.0, 1.0).astype(np.float32)
    summary = (
        f"{path}: kept, fitted by an earlier run of this command (scene {read.object!r}, Mitsuba RMSE "
        f"{frame.rmse:.2f}, start {frame.start_rmse:.2f})"
    )
    return scene_fits.scene_fit_result(
        values,
        rmse=frame.rmse,
        ranges=dict(document.get("ranges") or {}),
        notices=(),
        summary=summary,
        target=target.astype(np.float32),
        rendered=image,
        document=document,
        start=frame.start,
        start_rmse=frame.start_rmse,
        evaluations=frame.evaluations,
    )


def preview(fits: list[Fit]) -> np.ndarray:
    """Returns preview.png's picture, sRGB: up to `PREVIEW_FRAMES` frames spread over the sequence, each frame's
    picture above its answer's render in the scene (both at the fit's size, shown `PREVIEW_SIZE` on the longer side)."""
    chosen = np.unique(np.linspace(0, len(fits) - 1, min(PREVIEW_FRAMES, len(fits))).round().astype(int))
    height, width = np.asarray(fits[0].target).shape[:2]
    scale = PREVIEW_SIZE / max(height, width)
    shown_size = (max(1, round(width * scale)), max(1, round(height * scale)))

    def tile(image: object, text: str) -> np.ndarray:
        linear = images.resample(images.srgb_decode(np.asarray(image, np.float32)), *shown_size)
        return images.label(np.clip(images.srgb_encode(linear), 0.0, 1.0), text, 12)

    top = [tile(fits[k].target, os.path.basename(str(fits[k].document.get("target", k)))) for k in chosen]
    bottom = [tile(fits[k].rendered, f"RMSE {fits[k].mitsuba_rmse:.2f}") for k in chosen]
    return np.concatenate([np.concatenate(top, axis=1), np.concatenate(bottom, axis=1)], axis=0)


def _mask_path(mask: Picture | None) -> str | None:
    """Returns the mask's file (an input no output may replace), None for an array or no mask."""
    return path_text(mask) if isinstance(mask, str | os.PathLike) else None


def _mask_size(mask: Picture) -> tuple[int, int]:
    """Returns the mask's (width, height), a file's from its header; the one-line ImageError of one that is none."""
    if isinstance(mask, str | os.PathLike):
        return images.header(scenes.mask_file(mask))[:2]
    shape = np.shape(mask)
    if len(shape) not in (2, 3):
        raise ImageError(f"mask of shape {shape} is no picture: give an (H, W) or (H, W, C) array", field="mask")
    return int(shape[1]), int(shape[0])


def _mask_sha256(mask: Picture) -> str:
    """Returns the SHA-256 of the mask's file or array bytes: a frame fitted through another is fitted again."""
    if isinstance(mask, str | os.PathLike):
        return files.sha256(path_text(mask))
    return hashlib.sha256(np.ascontiguousarray(np.asarray(mask)).tobytes()).hexdigest()
