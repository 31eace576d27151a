"""What a fit gives back: the files it writes (`Outputs`) and what it found (`Fit`, made of a finished fit's outcome
by `fit_of`)."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from matfit import documents
from matfit.api.arguments import MAX_SIZE, Image, path_of, path_text, whole
from matfit.api.material import Material
from matfit.errors import FitError, OutputError

if TYPE_CHECKING:
    from matfit.fitting.outcome import Outcome
    from matfit.fitting.request import Outputs as RequestOutputs


@dataclass(frozen=True)
class Outputs:
    """The files a fit writes (`Fitter.fit(..., outputs=...)`): params.json always, the others where named.

    Every path is checked before any work (a folder that cannot be written, a wrong extension, a path named twice,
    an input it would overwrite, a file of the model) and all are written together once the fit is done, so a
    failed or interrupted fit leaves none of them. `report`: the report picture (target, start, fit, Mitsuba's render,
    difference, ranges); `render`: Mitsuba's render of the answer, `render_size` pixels a side at `render_spp`
    samples a pixel; `mitsuba_xml` and `blender`: the exports (`Material.to_mitsuba_xml`, `to_blender_script`).
    In `Fitter.fit_all`, each picture's files go into the folder given, named after the picture:
    `<stem>.params.json`, and `<stem>.<name>` for each other file named here (`params` is not used there).
    """

    params: str | os.PathLike[str] = "params.json"
    report: str | os.PathLike[str] | None = None
    render: str | os.PathLike[str] | None = None
    render_size: int = 512
    render_spp: int = 256
    mitsuba_xml: str | os.PathLike[str] | None = None
    blender: str | os.PathLike[str] | None = None

    def _request(self) -> RequestOutputs:
        """Returns the outputs as the fit's request holds them (paths as `matfit fit` passes them on)."""
        from matfit.fitting.request import Outputs as RequestOutputs
        from matfit.model import dataset

        named = {}
        for name in ("params", "report", "render", "mitsuba_xml", "blender"):
            value = getattr(self, name)
            named[name] = (
                None if value is None else path_text(path_of(name, value, OutputError, "give a file's path or None"))
            )
        size = whole("render_size", self.render_size, dataset.MIN_RESOLUTION, MAX_SIZE, OutputError)
        spp = whole("render_spp", self.render_spp, 1, dataset.MAX_SPP, OutputError)
        return RequestOutputs(
            str(named["params"]),
            named["report"],
            named["render"],
            size,
            spp,
            named["mitsuba_xml"],
            named["blender"],
        )


@dataclass(frozen=True, eq=False)
class Fit:
    """What a fit of a picture found: the material, how well it matches, and its params.json.

    `mitsuba_rmse` is None and `verification` empty for a fit without verification; `ranges` is what the
    picture decides about each parameter and `answer` how the clean answer was chosen (docs/fitting.md),
    both as params.json holds them. RMSE on 0-255 sRGB values. The pictures are sRGB, (R, R, 3) at the
    model's resolution: `target` as fitted, `image` the decoder's picture of the material, `rendered`
    Mitsuba's (None where nothing was rendered), `start_image` the decoder's picture of the best-of-n start
    (`start`, among the encoders' guesses and the init's material) the search began from. `stage`: the stage
    whose answer this is, "neural" (the search's), "verified" (Mitsuba's, after rounds of correction), "clean" or
    "refined": the last the fit ran for the `Fit` a fit returns, an earlier one for those `answers=` hears first
    (`Fitter.fit`); "" for a scene fit.
    """

    material: Material
    neural_rmse: float
    mitsuba_rmse: float | None
    verification: dict[str, Any]
    ranges: dict[str, Any]
    answer: dict[str, Any]
    notices: tuple[str, ...]
    summary: str
    target: Image = field(repr=False)
    image: Image = field(repr=False)
    rendered: Image | None = field(repr=False)
    document: dict[str, Any] = field(repr=False)
    start: str = ""  # which guess best-of-n started from ("encoder-4", "extra-1": the init's material, ...)
    start_rmse: float = float("nan")  # its neural RMSE
    evaluations: int = 0  # the search's objective evaluations
    start_image: Image | None = field(default=None, repr=False)
    stage: str = ""
    _outcome: Outcome | None = field(default=None, repr=False)

    def to_json(self) -> str:
        """Returns the fit's params.json text: for a picture file, what `matfit fit` writes, but for the timings."""
        return documents.dumps(self.document)

    def report(self) -> Image:
        """Returns `matfit fit --report`'s picture, sRGB (target | start | fit (neural) | fit (Mitsuba) | difference |
        ranges): for a fit with Mitsuba's render (verified, the default), else MatfitError."""
        from matfit.fitting import document

        if self._outcome is None or self._outcome.rendered is None:
            raise FitError("a fit without Mitsuba's render has no report: fit with verify=True", field="report")
        return np.asarray(document.report_picture(self._outcome), np.float32)


def landed(outcome: Outcome, name: str, notices: Sequence[str], started: float) -> Fit:
    """Returns the `Fit` of one stage's answer as it lands (`Fitter.fit(answers=)`): `notices` (of the pixels read
    before the fit) first, its params.json's wall time the seconds since `started` (a `time.perf_counter()`)."""
    timed = {**outcome.document, "wall_time_s": round(time.perf_counter() - started, 3)}
    return fit_of(dataclasses.replace(outcome, notices=(*notices, *outcome.notices), document=timed), name)


def fit_of(outcome: Outcome, name: str) -> Fit:
    """Returns the `Fit` of a finished fit (its document's timings set), or of one stage's answer."""
    document = outcome.document
    rendered = None if outcome.rendered is None else np.asarray(outcome.rendered, np.float32)
    return Fit(
        Material.from_array(outcome.values),
        float(outcome.neural_rmse),
        document.get("mitsuba_rmse"),
        dict(document.get("verification") or {}),
        dict(document.get("ranges") or {}),
        dict(document.get("answer") or {}),
        tuple(outcome.notices),
        outcome.summary(name),
        np.asarray(outcome.target, np.float32),
        np.asarray(outcome.image, np.float32),
        rendered,
        document,
        outcome.result.chosen,
        float(outcome.result.start_rmse),
        int(outcome.result.evaluations),
        np.asarray(outcome.result.start_image, np.float32),
        outcome.stage,
        outcome,
    )
