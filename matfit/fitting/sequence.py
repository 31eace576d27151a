"""Fitting image sequences with reinitialisation (the paper's Section 5 extension).

For frames t_0..t_k (say, a slider dragged in an editor), frame i's best-of-n pool is the
encoders' guesses plus, from the second frame on, the previous frame's optimum; Nelder-Mead
refines the winner within the budget. `reinit=False` fits every frame alone, for comparison.
Each frame is one `request.Request` (the frame as read, that optimum as a unit-cube candidate, no
Mitsuba stage) fitted by `fitfile.fit_neural`.

Each finished frame is written at once to `<out>/<frame stem>.json` (params.json format, plus how
it was found), so an interrupted run resumes after the last finished frame, reading that frame's
optimum back as the next frame's candidate: a resumed run gives the same results as a whole one.
Each result records what it was computed from: the settings, the model's identity (the hash of
its weights, wherever the model lies), the frame's SHA-256 and, with reinitialisation, the
previous frame's optimum. A result whose frame changed since (an edit made again, another folder
with the same names) is fitted again, and so is every frame after it whose previous optimum thereby
changed; each such frame says why (`Frame.note`). With `--render`, each frame's result records the
render made from it (`sequence.render`: the image's SHA-256, size and samples): a render that is
not the one recorded in its frame's current result (the frame was fitted again since, the render
settings changed, the image was replaced) is made again.

Every file a run writes is checked before the first fit (`check_outputs`): two frames whose
results would share a name (`a.png` and `a.jpg`, both `a.json`) are refused, and so is an output
folder that is read-only, where a result would overwrite a frame, or that is the frames' folder
itself (its preview.png and renders would be frames of the next run, which resumes).
"""

from __future__ import annotations

import functools
import os
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from matfit import documents, files, images, params
from matfit.errors import OutputError, SequenceError
from matfit.fitting import fitfile, search
from matfit.fitting.request import Request
from matfit.model import models

if TYPE_CHECKING:
    from matfit.rendering.engine import Renderer

FRAME_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".hdr")
PREVIOUS = "previous frame"
INIT = "--init"
RENDER_SUFFIX = "-render.png"
SUMMARY_FILE = "summary.md"
PREVIEW_FILE = "preview.png"


def natural_key(name: str) -> list:
    """Returns a sort key that puts frame_2 before frame_10."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def list_frames(directory: str) -> list[str]:
    """Returns the image files of a folder in natural order; refuses a missing or empty folder."""
    if not os.path.isdir(directory):
        raise SequenceError(f"{directory} is not a folder: give the folder that holds the frames")
    names = [
        name
        for name in os.listdir(directory)
        if os.path.splitext(name)[1].lower() in FRAME_EXTENSIONS and not name.startswith(".")
    ]
    if not names:
        raise SequenceError(
            f"{directory} holds no frames ({', '.join(FRAME_EXTENSIONS)}): export the frames there first"
        )
    return [os.path.join(directory, name) for name in sorted(names, key=natural_key)]


@dataclass
class Frame:
    """One fitted frame, as written to its JSON file."""

    path: str
    unit: np.ndarray
    rmse: float
    start: str
    start_rmse: float
    evaluations: int
    seconds: float
    image: np.ndarray | None = None  # phi(x), only for frames fitted in this run
    target: np.ndarray | None = None
    note: str | None = None  # why a frame with a result on disk was fitted again


def frame_json_path(out: str, frame: str) -> str:
    """Returns where a frame's result is written."""
    return os.path.join(out, os.path.splitext(os.path.basename(frame))[0] + ".json")


def render_path(out: str, frame: str) -> str:
    """Returns where a frame's Mitsuba render is written (`--render`)."""
    return os.path.join(out, os.path.splitext(os.path.basename(frame))[0] + RENDER_SUFFIX)


def check_frame_names(frames: list[str]) -> None:
    """Raises SequenceError when two frames would write the same result file (`a.png` and `a.jpg`: `a.json`)."""
    seen: dict[str, str] = {}
    for path in frames:
        name = os.path.basename(frame_json_path("", path))
        if name in seen:
            raise SequenceError(
                f"frames {seen[name]} and {path} would both write their result to {name}: "
                "rename one of them (a frame's result is named after the frame without its extension)"
            )
        seen[name] = path


def check_outputs(
    frames: list[str],
    out: str,
    *,
    rendered: bool,
    init: str | None = None,
    model: str | None = None,
    inputs: Sequence[tuple[str, str | None]] = (),
) -> None:
    """Raises SequenceError or OutputError, before any fit, unless every file of a run into `out` can be written.

    No two frames may share a result name, the folder must take files, and no output (a result, a
    render, summary.md, preview.png) may be a frame, the `init` file, one of `inputs` (what else is read: a
    scene's files) or a file of the model folder `model` (or of the shipped model); nor may `out` lie in a folder
    that does not exist, or be the frames' folder: preview.png and the renders are pictures that the next run,
    resuming, would list as frames.
    """
    parent = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(parent) and not os.path.exists(parent):
        raise SequenceError(
            f"output folder {out} cannot be created: {parent} does not exist (create it first)", field="out"
        )
    check_frame_names(frames)
    outputs = [("result", frame_json_path(out, frame)) for frame in frames]
    outputs += [("render", render_path(out, frame)) for frame in frames] if rendered else []
    outputs += [("summary", os.path.join(out, SUMMARY_FILE)), ("preview", os.path.join(out, PREVIEW_FILE))]
    files.check_folder(out, outputs, [("frame", frame) for frame in frames] + [("init", init), *inputs], model=model)
    folder = os.path.dirname(frames[0]) or "."
    if os.path.isdir(out) and os.path.samefile(out, folder):
        raise OutputError(
            f"out {out} is the folder of the frames: its {PREVIEW_FILE} (and renders) would be frames of the next "
            f"run, which resumes; choose another out folder, such as {os.path.join(out, 'fits')}",
            field="out",
        )


def run_settings(settings: search.Settings, reinit: bool, model: models.Model) -> dict:
    """Returns what a resumed run must share with the run that wrote the finished frames."""
    return {
        "method": settings.method,
        "evaluations": settings.evaluations,
        "box": settings.box,
        "starts": settings.starts,
        "iterations": settings.iterations,
        "narrow_after": settings.narrow_after,
        "reinit": reinit,
        "model": model.identity(),
    }


def read_finished(path: str, expected: dict) -> tuple[Frame, dict, dict] | None:
    """Returns a finished frame's result, what it was computed from and its whole document (params.json with its
    `sequence` record), if its file exists with the same settings."""
    if not os.path.exists(path):
        return None
    try:
        document = documents.read(path, "delete it to fit that frame again", SequenceError)
        stored = document["sequence"]
        unit = np.asarray(stored["unit"], np.float64)  # exact, unlike the rounded physical values
        if unit.shape != (params.COUNT,):
            raise ValueError("unit vector of the wrong length")
        frame = Frame(
            stored["frame"],
            unit,
            stored["rmse"],
            stored["start"],
            stored["start_rmse"],
            stored["evaluations"],
            stored["seconds"],
        )
    except SequenceError:
        raise
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise SequenceError(f"{path} is damaged ({type(error).__name__}): delete it to fit that frame again") from None
    if stored.get("settings") != expected:
        raise SequenceError(
            f"{path} was made with other settings or another model ({stored.get('settings')}): "
            "use another --out folder or delete it"
        )
    return frame, {"frame_sha256": stored.get("frame_sha256"), "previous": stored.get("previous")}, document


def stale(finished: tuple[Frame, dict, dict] | None, computed_from: dict, *, first: bool = False) -> str | None:
    """Returns why a finished frame's result must be fitted again (None: it can be reused)."""
    if finished is None:
        return None
    recorded = finished[1]
    if recorded["frame_sha256"] != computed_from["frame_sha256"]:
        return "the picture is not the one its result on disk was fitted to: fitted again"
    if recorded["previous"] != computed_from["previous"]:
        return (
            "the --init material changed: fitted again"
            if first
            else "the previous frame's result changed: fitted again"
        )
    return None


def check_sizes(frames: list[str]) -> None:
    """Raises SequenceError unless every frame has the first frame's size (headers only)."""
    first = images.header(frames[0])[:2]
    for path in frames[1:]:
        size = images.header(path)[:2]
        if size != first:
            raise SequenceError(
                f"{path} is {size[0]}x{size[1]}, the first frame is {first[0]}x{first[1]}: "
                "give every frame the same size"
            )


def load_frame(path: str, resolution: int) -> np.ndarray:
    """Returns a frame as the model's sRGB target (sizes were checked from the headers by `check_sizes`)."""
    target, _ = search.prepare_target(images.load(path).pixels, resolution, path)
    return target


def fit_sequence(
    model: models.Model,
    frames: list[str],
    *,
    out: str,
    settings: search.Settings,
    reinit: bool = True,
    progress: Callable[[int, int, Frame], None] | None = None,
    init: np.ndarray | None = None,
) -> list[Frame]:
    """Fits every frame in order, writing each result at once; returns all frames' results.

    `init` (unit cube, (19,)): the source material's parameters, a candidate of the first frame.
    """
    settings.check()
    check_frame_names(frames)
    check_sizes(frames)
    created = not os.path.isdir(out)
    os.makedirs(out, exist_ok=True)
    try:
        return _fit_frames(model, frames, out, settings, reinit, progress, init)
    except BaseException:
        if created and not os.listdir(out):  # nothing finished: leave no empty folder behind
            os.rmdir(out)
        raise


def _fit_frames(
    model: models.Model,
    frames: list[str],
    out: str,
    settings: search.Settings,
    reinit: bool,
    progress: Callable[[int, int, Frame], None] | None,
    init: np.ndarray | None,
) -> list[Frame]:
    expected = run_settings(settings, reinit, model)
    results: list[Frame] = []
    for index, path in enumerate(frames):
        json_path = frame_json_path(out, path)
        finished = read_finished(json_path, expected)
        previous = [float(u) for u in results[-1].unit] if reinit and results else None
        if not results and init is not None:  # the source material joins the first frame's candidates
            previous = [float(u) for u in np.asarray(init, np.float32)]
        computed_from = {"frame_sha256": files.sha256(path), "previous": previous}
        note = stale(finished, computed_from, first=not results)
        target = load_frame(path, model.resolution)
        if finished is not None and note is None:
            frame = finished[0]
            frame.target = target
            results.append(frame)
        else:
            candidates = np.asarray(previous, np.float32)[None] if previous is not None else None
            request = Request(
                path, settings=settings, verified=False, answer="best", pixels=target, candidates=candidates
            )
            result = fitfile.fit_neural(request, model)
            start = (INIT if index == 0 else PREVIOUS) if result.chosen == "extra-1" else result.chosen
            frame = Frame(
                path,
                result.unit,
                result.rmse,
                start,
                result.start_rmse,
                result.evaluations,
                result.seconds,
                result.image,
                target,
                note,
            )
            document = params.params_document(
                result.values,
                sequence={
                    "frame": path,
                    "index": index,
                    "rmse": result.rmse,
                    "start": start,
                    "start_rmse": result.start_rmse,
                    "evaluations": result.evaluations,
                    "seconds": result.seconds,
                    "settings": expected,
                    **computed_from,
                    "unit": [float(u) for u in result.unit],
                },
            )
            files.write_text(json_path, documents.dumps(document))
            results.append(frame)
        if progress is not None:
            progress(index + 1, len(frames), results[-1])
    return results


def summary_table(results: list[Frame], count: str = "evaluations", figure: str = "RMSE") -> str:
    """Returns the per-frame table (frame, start chosen, RMSE, evaluations, time) in Markdown; `count` and `figure`
    name what `Frame.evaluations` and `Frame.rmse` hold (a scene's frames: "steps", "Mitsuba RMSE")."""
    lines = [f"| frame | start | start {figure} | {figure} | {count} | time (s) |", "|---|---|---|---|---|---|"]
    for frame in results:
        lines.append(
            f"| {os.path.basename(frame.path)} | {frame.start} | {frame.start_rmse:.2f} | {frame.rmse:.2f} | "
            f"{frame.evaluations} | {frame.seconds:.3f} |"
        )
    lines.append(
        f"| sum | | | {sum(frame.rmse for frame in results):.2f} | {sum(f.evaluations for f in results)} | "
        f"{sum(f.seconds for f in results):.2f} |"
    )
    return "\n".join(lines) + "\n"


def preview(model: models.Model, results: list[Frame], *, columns: int = 12, tile: int = 96) -> np.ndarray:
    """Returns an sRGB strip: targets on top, fitted (neural) images below, for up to `columns` frames."""
    from matfit.fitting import report

    chosen = np.unique(np.linspace(0, len(results) - 1, min(columns, len(results))).round().astype(int))
    decoded = model.decode(np.stack([results[k].unit for k in chosen]))
    top = report.compose(
        [(results[k].target, os.path.basename(results[k].path)) for k in chosen], size=tile, caption=12
    )
    bottom = report.compose(
        [(image, f"RMSE {results[k].rmse:.2f}") for image, k in zip(decoded, chosen, strict=True)],
        size=tile,
        caption=12,
    )
    return np.concatenate([top, bottom], axis=0)


def run(
    model: models.Model | str | models.Loader,
    frames_path: str,
    *,
    out: str,
    settings: search.Settings,
    reinit: bool = True,
    render: tuple[int, int] | None = None,
    progress: Callable[[int, int, float], None] | None = None,
    init: str | None = None,
    init_values: np.ndarray | None = None,
) -> list[Frame]:
    """Fits a folder of frames into `out`: a JSON per frame, summary.md and preview.png; returns the frames' results.

    `model`: a model, a model directory, or a `models.Loader` of one (`matfit.Fitter`); a directory's model is
    loaded, and a loader's asked for, once every input and output was checked.

    `render` = (size, spp) also renders every fitted frame with Mitsuba (`<frame>-render.png`).
    `progress(done, total, frames per second)` follows the fits; `init` is a params.json of the
    source material, a candidate of the first frame (`init_values`: its 19 physical values, read already).
    Finished frames are read back, so running it again after an interruption resumes.
    """
    frames = list_frames(frames_path)
    values = init_values if init_values is not None else params.read_file(init) if init is not None else None
    start = params.to_unit(values) if values is not None else None
    check_outputs(frames, out, rendered=render is not None, init=init, model=fitfile.model_path(model))
    model = fitfile.loaded(model)
    started = time.perf_counter()

    def report(done: int, total: int, frame: Frame) -> None:
        if progress is not None:
            progress(done, total, done / max(time.perf_counter() - started, 1e-9))

    results = fit_sequence(model, frames, out=out, settings=settings, reinit=reinit, progress=report, init=start)
    if render is not None:
        render_frames(results, out, *render)
    files.write_text(os.path.join(out, SUMMARY_FILE), summary_table(results))
    images.write(os.path.join(out, PREVIEW_FILE), images.srgb_decode(preview(model, results)))
    return results


def render_frames(
    results: list[Frame], out: str, size: int, spp: int, draw: Callable[[np.ndarray], np.ndarray] | None = None
) -> None:
    """Renders each frame's result with Mitsuba to `<frame>-render.png`, unless its result records that very render.

    After writing a render, the frame's result records it (the image's SHA-256, size, samples), so
    a result fitted again since (whose new file has no record), other render settings, or a
    replaced image all make it again, whether or not this run fitted the frame. `draw(unit)`: the linear render
    of a frame's answer (None: the test scene's, `size` pixels a side at `spp`).
    """
    for frame in results:
        path, json_path = render_path(out, frame.path), frame_json_path(out, frame.path)
        document = documents.read(json_path, "delete it to fit that frame again", SequenceError)
        settings = {"size": size, "spp": spp}
        recorded = document["sequence"].get("render")
        if os.path.exists(path) and recorded == {**settings, "sha256": files.sha256(path)}:
            continue
        if draw is None:
            from matfit.rendering.engine import Renderer

            draw = functools.partial(_test_scene, Renderer(size, spp))
        images.write(path, draw(frame.unit))
        document["sequence"]["render"] = {**settings, "sha256": files.sha256(path)}
        files.write_text(json_path, documents.dumps(document))


def _test_scene(renderer: Renderer, unit: np.ndarray) -> np.ndarray:
    return renderer.render(params.from_unit(unit))
