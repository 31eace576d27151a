"""Fitting several pictures in one process: the model loaded once, one render pool, one params.json per picture.

`matfit fit a.png b.png c.png -o fits/` is `plan` (every output named and checked before any work) then
`fit_all` (each picture fitted and written by `matfit.Fitter.fit_all`'s one fitter, the same model and render pool,
so only the first pays for loading them). A picture whose fit fails is reported and the others go on.

Stopped part way (Ctrl-C, kill -9, a machine that went down), the same command goes on where it stopped: the
output folder holds a journal (`Journal`, JOURNAL) of the pictures fitted so far, each with its SHA-256, under a
key of everything else that decides a fit (the settings, the mask and init files' contents, the model's files,
matfit's version). A rerun with the same key keeps a picture whose journal entry matches the picture as it is now
and whose outputs are all there; anything changed fits again. The journal is removed once every picture is fitted,
so a finished command run again fits every picture again; after a picture failed it stays, and the same command
run again fits only the pictures that failed (or changed).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
from collections.abc import Callable
from dataclasses import replace
from typing import TypeVar

import numpy as np

from matfit import documents, files
from matfit.errors import MatfitError, OutputError
from matfit.fitting.request import Outputs, Request

Fitted = TypeVar("Fitted")  # what fitting one picture returns (`matfit.Fit`)

PARAMS_SUFFIX = ".params.json"  # a picture's params.json in the output folder: <stem>.params.json
JOURNAL = ".matfit-fit-journal.json"  # in the output folder while a command of several pictures has some left


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


def plan(
    targets: list[str], folder: str, request: Request, *, then: Callable[[], object] | None = None
) -> list[Request]:
    """Returns one request a picture of `targets`, each like `request` but for its picture and its outputs (named by
    `outputs_of` in `folder`); raises the one-line OutputError of a plan that cannot run, before any work: a folder
    that is a file or names a .json file, two pictures of one name, a picture given twice, and any request's own
    check (`Request.check`). `then()` runs after the checks (the model's load): whatever any of them raises, the
    folders made for the plan are removed again."""
    if not targets:
        raise ValueError("plan fits pictures: give at least one")
    if not os.path.isdir(folder) and (os.path.exists(folder) or folder.lower().endswith(".json")):
        kind = "is a file" if os.path.exists(folder) else "names one file"
        raise OutputError(
            f"output {folder} {kind}, but {_pictures(len(targets))} each write a params.json: give -o a folder "
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
        if then is not None:
            then()
    except BaseException:
        for path in made:  # the folders made for the check, innermost first: a refused plan leaves nothing
            with contextlib.suppress(OSError):
                os.rmdir(path)
        raise
    return requests


def _pictures(count: int) -> str:
    """Returns "1 picture" or "3 pictures"."""
    return f"{count} picture" + ("" if count == 1 else "s")


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
    model_path: str,
    fit_one: Callable[[Request, Callable[[str], None]], Fitted],
    *,
    done: Callable[[Request, Fitted | MatfitError | None], None] | None = None,
) -> int:
    """Fits every request in turn with `fit_one(request, written)`, which fits one, writes its outputs and calls
    `written(the SHA-256 of the picture as it was fitted)` at once (`matfit.Fitter`'s: one model and render pool for
    all), and returns its fit; returns how many failed. `done(request, fit or error or None)` hears of each picture as
    it ends: None for one an earlier run of the same requests fitted already (`Journal`), kept as it is; a MatfitError
    of one picture (a picture that cannot be read, a mask of another size) is handed to it and the others go on; a
    failure of the system (OSError, a render process that ended) stops them all. `model_path`: the model folder, whose
    files key the journal."""
    folder = os.path.dirname(requests[0].outputs.params) if requests and requests[0].outputs else "."
    journal = Journal(folder, journal_key(requests, model_path))
    failed = 0
    for request in requests:
        if journal.fitted(request):
            if done is not None:
                done(request, None)
            continue
        try:
            outcome: Fitted | MatfitError = fit_one(request, functools.partial(journal.record, request))
        except MatfitError as error:
            outcome = error
            failed += 1
        if done is not None:
            done(request, outcome)
    if not failed:  # else the journal stays: the same command, run again, fits only the pictures that failed
        journal.finish()
    return failed


def journal_key(requests: list[Request], model_path: str) -> str:
    """Returns the SHA-256 of everything but the pictures that decides the fits of `requests`: their settings and
    options, the contents of their mask and init files, the model folder's files, matfit's version."""
    from importlib import metadata

    first = requests[0]
    parts = {
        "settings": repr(first.settings),
        "options": [first.seed, first.verified, first.corrections, first.refine_steps, first.variant, first.answer],
        "outputs": None
        if first.outputs is None
        else [
            [getattr(first.outputs, name) is not None for name in ("report", "render", "mitsuba_xml", "blender")],
            first.outputs.render_size,
            first.outputs.render_spp,
        ],
        "mask": files.sha256(first.mask) if first.mask else None,
        "init": init_key(first),
        "model": {
            name: files.sha256(os.path.join(model_path, name))
            for name in sorted(os.listdir(model_path))
            if os.path.isfile(os.path.join(model_path, name))
        },
        "pictures": [os.path.abspath(request.target) for request in requests],
        "matfit": metadata.version("matfit"),
    }
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def init_key(request: Request) -> str | None:
    """Returns the SHA-256 of a request's source material: its values where they were given (`matfit.Material`, no
    file to read: `init` only names them), else its params.json's, else None."""
    if request.init_values is not None:
        return hashlib.sha256(np.ascontiguousarray(request.init_values, np.float64).tobytes()).hexdigest()
    return files.sha256(request.init) if request.init else None


class Journal:
    """The pictures of one command fitted so far (module docstring): `fitted` says whether a picture can be kept,
    `record` adds one once its outputs are written, `finish` removes the journal when the command is done."""

    def __init__(self, folder: str, key: str) -> None:
        self.path, self.key = os.path.join(folder, JOURNAL), key
        self.pictures: dict[str, str] = {}  # absolute path of a picture fitted -> its SHA-256 then
        with contextlib.suppress(OSError, ValueError, MatfitError):  # none, unreadable or another command's: start
            document = documents.read(self.path, "it is rewritten")
            if isinstance(document, dict) and document.get("key") == key and isinstance(document.get("pictures"), dict):
                self.pictures = {str(k): str(v) for k, v in document["pictures"].items()}

    def fitted(self, request: Request) -> bool:
        """Returns whether an earlier run fitted the request's picture as it is now, its outputs all still there."""
        recorded = self.pictures.get(os.path.abspath(request.target))
        if recorded is None or request.outputs is None:
            return False
        written = [path for path in vars(request.outputs).values() if isinstance(path, str)]
        if not all(os.path.isfile(path) for path in written):
            return False
        with contextlib.suppress(OSError):
            return files.sha256(request.target) == recorded
        return False

    def record(self, request: Request, picture: str) -> None:
        """Adds a picture fitted (its SHA-256 when it was read) and writes the journal whole (`files.write_text`)."""
        self.pictures[os.path.abspath(request.target)] = picture
        files.write_text(self.path, documents.dumps({"key": self.key, "pictures": self.pictures}))

    def finish(self) -> None:
        """Removes the journal: every picture was fitted, so nothing is left to go on with."""
        with contextlib.suppress(FileNotFoundError):
            os.remove(self.path)
