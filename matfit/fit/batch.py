"""Fitting several pictures in one process: the model loaded once, one render pool, one params.json per picture.

`matfit fit a.png b.png c.png -o fits/` is `plan` (every output named and checked before any work) then
`fit_all` (each picture fitted by `fitfile.run` with the same model and renderer, so only the first pays for
loading them). A picture whose fit fails is reported and the others go on.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from dataclasses import replace

from matfit import files
from matfit.errors import MatfitError, OutputError
from matfit.fit import fitfile, stages
from matfit.fit.request import Outputs, Request
from matfit.model import models

PARAMS_SUFFIX = ".params.json"  # a picture's params.json in the output folder: <stem>.params.json


def outputs_of(target: str, folder: str, outputs: Outputs) -> Outputs:
    """Returns the outputs of one picture of several: every file in `folder`, named after the picture's stem, the
    optional ones after the name given (`--report report.png` -> `<folder>/<stem>.report.png`)."""
    stem = os.path.splitext(os.path.basename(target))[0]

    def named(path: str | None) -> str | None:
        return None if path is None else os.path.join(folder, f"{stem}.{os.path.basename(path)}")

    return replace(
        outputs,
        params=os.path.join(folder, stem + PARAMS_SUFFIX),
        report=named(outputs.report),
        render=named(outputs.render),
        mitsuba_xml=named(outputs.mitsuba_xml),
        blender=named(outputs.blender),
    )


def plan(targets: list[str], folder: str, request: Request) -> list[Request]:
    """Returns one request a picture of `targets`, each like `request` but for its picture and its outputs (named by
    `outputs_of` in `folder`); raises the one-line OutputError of a plan that cannot run, before any work: a folder
    that is a file or names a .json file, two pictures of one name, a picture given twice, and any request's own
    check (`Request.check`)."""
    if len(targets) < 2:
        raise ValueError("plan fits several pictures: fit one with fitfile.run")
    if not os.path.isdir(folder) and (os.path.exists(folder) or folder.lower().endswith(".json")):
        kind = "is a file" if os.path.exists(folder) else "names one file"
        raise OutputError(
            f"output {folder} {kind}, but {len(targets)} pictures each write a params.json: give -o a folder "
            f"(for example -o {os.path.splitext(folder)[0] if kind == 'names one file' else 'fits'}/)",
            field="output",
        )
    seen: dict[str, str] = {}
    for target in targets:
        stem = os.path.splitext(os.path.basename(target))[0]
        if stem in seen:
            same = (
                f"picture {target} is given twice"
                if os.path.abspath(seen[stem]) == os.path.abspath(target)
                else f"pictures {seen[stem]} and {target} have one name"
            )
            raise OutputError(
                f"{same}: both would write {os.path.join(folder, stem + PARAMS_SUFFIX)}; "
                "fit each picture once, renaming one of two that share a name",
                field="target",
            )
        seen[stem] = target
    if request.outputs is None:
        raise ValueError("plan names the outputs of each picture: give the request Outputs")
    requests = [
        replace(request, target=target, outputs=outputs_of(target, folder, request.outputs)) for target in targets
    ]
    files.check_folder(folder, field="output")
    made = _make_folder(folder)
    try:
        for each in requests:
            each.check()
    except BaseException:
        for path in made:  # the folders made for the check, innermost first: a refused plan leaves nothing
            with contextlib.suppress(OSError):
                os.rmdir(path)
        raise
    return requests


def _make_folder(folder: str) -> list[str]:
    """Creates `folder` and the folders missing on the way; returns those made, innermost first."""
    made, path = [], os.path.abspath(folder)
    while not os.path.exists(path):
        made.append(path)
        path = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    return made


def fit_all(
    requests: list[Request],
    model: models.Model | str,
    *,
    renderer=None,
    done: Callable[[Request, stages.Outcome | MatfitError], None] | None = None,
) -> int:
    """Fits every request in turn with one model and `renderer` (a `process.Pool` or `Process`, or None) and writes
    its outputs (`fitfile.run`); returns how many failed. `done(request, outcome or error)` hears of each picture as
    it ends: a MatfitError of one picture (a picture that cannot be read, a mask of another size) is handed to it and
    the others go on; a failure of the system (OSError, a render process that ended) stops them all."""
    model = fitfile.load_model(model) if isinstance(model, str) else model
    failed = 0
    for request in requests:
        try:
            outcome: stages.Outcome | MatfitError = fitfile.run(request, model, renderer=renderer)
        except MatfitError as error:
            outcome = error
            failed += 1
        if done is not None:
            done(request, outcome)
    return failed
