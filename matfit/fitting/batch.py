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
run again fits only the pictures that failed (or changed). A kept picture's params.json must be matfit's of that very
picture (`written_params`: its SHA-256 the one recorded, its settings the command's), not any file of that name.

Nothing is lost (docs/fitting.md#several-pictures): `plan` refuses an output that is any picture of the command, the
mask or init, or another picture's output, and one that is in the folder already but that matfit did not write
(`check_replaceable`: a params.json holding matfit's fields for a picture of that name, and the outputs beside it).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import stat
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
# What every params.json matfit writes holds (`document.build`, and a scene fit's `api.scenes.fit_in_scene`, which
# names no model): a file in the output folder under a picture's params.json name is replaced only if it holds these
# (`written_params`, `check_replaceable`).
PARAMS_KEYS = ("params", "units", "method", "target", "target_sha256")
SCENE_KEYS = ("path", "object", "sha256")  # of a scene fit's params.json `scene`: the scene file and its shape


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
    that is a file or names a .json file, two pictures of one name, a picture given twice, a journal's path that is
    no file (`check_journal`), any request's own check (`Request.check`), an output of one picture that is another
    picture's output or input (`files.check_apart`), and an output in the folder already that matfit did not write
    (`check_replaceable`). `then()` runs after the checks (the model's load): whatever any of them raises, the
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
    check_journal(folder)
    made = _make_folder(folder)
    try:
        for each in requests:
            each.check()
        files.check_apart(
            [pair for each in requests for pair in _outputs(each)],
            [(name, getattr(each, name)) for each in requests for name in ("target", "mask", "init")],
            folder_field="output",
        )
        for each in requests:
            check_replaceable(each)
        if then is not None:
            then()
    except BaseException:
        for path in made:  # the folders made for the check, innermost first: a refused plan leaves nothing
            with contextlib.suppress(OSError):
                os.rmdir(path)
        raise
    return requests


def _outputs(request: Request) -> list[tuple[str, str]]:
    """Returns (what the file is, its path) of each file a request of a plan writes, its params.json first."""
    outputs = request.outputs
    assert outputs is not None, "a plan's requests name their outputs"
    named = {
        "params.json": outputs.params,
        "report": outputs.report,
        "render": outputs.render,
        "mitsuba_xml": outputs.mitsuba_xml,
        "blender": outputs.blender,
    }
    return files.named_paths(named)


def check_journal(folder: str) -> None:
    """Raises OutputError when the journal's path in `folder` holds something that is no file (a folder, a FIFO): its
    record of each picture fitted would fail after the picture was fitted and written."""
    path = os.path.join(folder, JOURNAL)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:  # none yet, or a dangling link, which the first record replaces
        return
    except OSError as error:
        raise OutputError(
            f"cannot use {path}, the journal of the pictures fitted: {error.strerror}; remove it or choose another "
            "output folder",
            field="output",
        ) from None
    if not stat.S_ISREG(mode):
        raise OutputError(
            f"{path} is {files.kind(mode)}, where matfit keeps the journal of the pictures fitted: remove it or choose "
            "another output folder",
            field="output",
        )


def written_params(path: str) -> dict | None:
    """Returns the document of the params.json at `path` if matfit wrote it (a JSON object holding each of
    PARAMS_KEYS, its parameters and units as objects, its target and the target's SHA-256 as text), else None."""
    try:
        document = documents.read(path, "it is no params.json of matfit's")
    except MatfitError:  # missing, no regular file, not JSON
        return None
    if not isinstance(document, dict) or not all(key in document for key in PARAMS_KEYS):
        return None
    kinds = {"params": dict, "units": dict, "target": str, "target_sha256": str}
    return document if all(isinstance(document[key], kind) for key, kind in kinds.items()) else None


def _stem(path: str) -> str:
    return os.path.splitext(os.path.basename(path))[0]


def check_replaceable(request: Request) -> None:
    """Raises OutputError for an output of a plan's request that is in its folder already and that matfit did not
    write: a params.json is matfit's when `written_params` says so and it names a picture of this one's name; the
    picture's other outputs are matfit's when its params.json is (they are written together, `files.together`)."""
    outputs = _outputs(request)
    there = [(label, path) for label, path in outputs if os.path.lexists(path)]
    if not there:
        return
    params_json, stem = outputs[0][1], _stem(request.target)
    document = written_params(params_json)
    if document is not None and _stem(document["target"]) == stem:
        return
    label, path = there[0]  # the params.json when it is there
    if label == "params.json":
        why = f"it is no params.json that matfit wrote for a picture named {stem}"
    else:
        why = f"matfit writes a picture's {files.words(label)} with its params.json, and {params_json} is not there"
    raise OutputError(
        f"{path} is in the output folder already and matfit did not write it ({why}): fitting {request.target} would "
        "replace it; move it away or choose another output folder",
        field="output",
    )


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
    scene: dict[str, object] | None = None,
) -> int:
    """Fits every request in turn with `fit_one(request, written)`, which fits one, writes its outputs and calls
    `written(the SHA-256 of the picture as it was fitted)` at once (`matfit.Fitter`'s: one model and render pool for
    all), and returns its fit; returns how many failed. `done(request, fit or error or None)` hears of each picture as
    it ends: None for one an earlier run of the same requests fitted already (`Journal`), kept as it is; a MatfitError
    of one picture (a picture that cannot be read, a mask of another size) is handed to it and the others go on; a
    failure of the system (OSError, a render process that ended) stops them all. `model_path`: the model folder, whose
    files key the journal. `scene`: where the pictures are fitted in a scene of the user's own, what identifies it
    (`api.scenes.identity`), which keys the journal too."""
    folder = os.path.dirname(requests[0].outputs.params) if requests and requests[0].outputs else "."
    journal = Journal(folder, journal_key(requests, model_path, scene), model_path, scene)
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


def journal_key(requests: list[Request], model_path: str, scene: dict[str, object] | None = None) -> str:
    """Returns the SHA-256 of everything but the pictures that decides the fits of `requests`: their settings and
    options, the contents of their mask and init files, the model folder's files, the scene they are fitted in
    (`api.scenes.identity`: its file's and its meshes' and images' contents, the shape), matfit's version."""
    from importlib import metadata

    first = requests[0]
    parts: dict[str, object] = {
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
    if scene is not None:  # a test-scene journal's key as it was
        parts["scene"] = scene
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

    def __init__(self, folder: str, key: str, model_path: str, scene: dict[str, object] | None = None) -> None:
        self.path, self.key, self.model_path, self.scene = os.path.join(folder, JOURNAL), key, model_path, scene
        self.pictures: dict[str, str] = {}  # absolute path of a picture fitted -> its SHA-256 then
        with contextlib.suppress(OSError, ValueError, MatfitError):  # none, unreadable or another command's: start
            document = documents.read(self.path, "it is rewritten")
            if isinstance(document, dict) and document.get("key") == key and isinstance(document.get("pictures"), dict):
                self.pictures = {str(k): str(v) for k, v in document["pictures"].items()}

    def fitted(self, request: Request) -> bool:
        """Returns whether an earlier run fitted the request's picture as it is now, its outputs all still there and
        its params.json matfit's of that picture: of its SHA-256 (the one recorded), its path, method, box, polish
        steps, mask, init and model, or in a scene its path, mask, scene file and shape (what else decides the fit is
        the journal's key)."""
        from matfit.fitting.document import display_path

        recorded = self.pictures.get(os.path.abspath(request.target))
        if recorded is None or request.outputs is None:
            return False
        if not all(os.path.isfile(path) for _, path in _outputs(request)):
            return False
        document = written_params(request.outputs.params)
        expected: dict[str, object] = {"target_sha256": recorded, "target": request.target, "mask": request.mask}
        if self.scene is None:
            settings = request.settings
            expected.update(
                method=settings.method.value,
                box=settings.box.value,
                polish_steps=settings.polish_steps,
                init=request.init,
                model=display_path(self.model_path),
            )
        else:
            expected["method"] = "scene"
        if document is None or any(document.get(name) != value for name, value in expected.items()):
            return False
        if self.scene is not None:  # fitted in this scene file's shape
            shape = document.get("scene")
            if not isinstance(shape, dict) or any(shape.get(name) != self.scene[name] for name in SCENE_KEYS):
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
