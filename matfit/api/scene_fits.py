"""A picture of a scene of the user's own fitted through the public API: `matfit.fit(..., scene=)`,
`Fitter.fit(..., scene=)` and each of `Fitter.fit_all(..., scene=)` (`fit_scene`), its `Fit` made of what
`scenes.fit_in_scene` found."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from matfit.api import scenes
from matfit.api.arguments import Picture, path_text, shown
from matfit.api.choices import check_choices
from matfit.api.material import Material
from matfit.api.results import Fit, Outputs
from matfit.api.scenes import Scene
from matfit.errors import OutputError

if TYPE_CHECKING:
    from matfit.fitting.request import Outputs as RequestOutputs
    from matfit.fitting.scene_fit import SceneOutcome
    from matfit.model.models import Loader


def fit_scene(
    picture: Picture,
    scene: Scene,
    mask: Picture | None,
    init: str | os.PathLike[str] | Material | None,
    linear: bool,
    steps: int,
    outputs: Outputs | RequestOutputs | None,
    variant: str | None,
    progress: Callable[[str, int, int, float], None] | None,
    model: Loader | None = None,
) -> Fit:
    """Returns the fit of the material of a shape in a scene of the user's own (`scenes.fit_in_scene`); `model`
    guesses the start where neither `init` nor the scene gives one (loaded then only). `outputs`: the caller's
    `Outputs`, or those a plan of several pictures named already (`Fitter.fit_all`: a request's)."""
    from matfit.fitting import request, scene_fit

    check_choices(None, init)
    if outputs is not None and not isinstance(outputs, Outputs | request.Outputs):
        raise OutputError(
            f"outputs {shown(outputs)} is no matfit.Outputs: give Outputs(params, ...) or None", field="output"
        )
    named = None if init is None or isinstance(init, Material) else path_text(init)
    start = None if init is None else (init if isinstance(init, Material) else Material.read(init)).array()
    outcome, document = scenes.fit_in_scene(
        picture,
        scene,
        init=start,
        init_name="Material" if isinstance(init, Material) else named,
        mask=mask,
        linear=linear,
        steps=steps or scene_fit.STEPS,
        variant=variant,
        outputs=outputs._request() if isinstance(outputs, Outputs) else outputs,
        progress=progress,
        model=model,
    )
    return fit_of(outcome, document, str(outputs.params) if outputs else document["target"])


def fit_of(outcome: SceneOutcome, document: dict[str, Any], name: str) -> Fit:
    """Returns the `Fit` of a finished scene fit (`scenes.fit_in_scene`'s outcome and params.json document), its
    summary line naming it `name` (its params.json, or its picture)."""
    summary = (
        f"{name}: scene {document['scene']['object']!r}, Mitsuba RMSE {outcome.rmse:.2f} "
        f"(start {outcome.start_rmse:.2f}), {outcome.seconds:.1f} s"
    )
    return scene_fit_result(
        outcome.values,
        rmse=outcome.rmse,
        ranges=dict(outcome.ranges),
        notices=tuple(document["notices"]),
        summary=summary,
        target=outcome.target,
        rendered=outcome.rendered,
        document=document,
        start="given",
        start_rmse=outcome.start_rmse,
        evaluations=len(outcome.losses),
        start_image=outcome.start_rendered,
    )


def scene_fit_result(
    values: np.ndarray,
    *,
    rmse: float,
    ranges: dict[str, Any],
    notices: tuple[str, ...],
    summary: str,
    target: np.ndarray,
    rendered: np.ndarray,
    document: dict[str, Any],
    start: str,
    start_rmse: float,
    evaluations: int,
    start_image: np.ndarray | None = None,
) -> Fit:
    """Returns the `Fit` of a scene fit's answer (physical `values`): no neural RMSE, verification or clean answer;
    its picture of the material is the judge's render, `rendered` (sRGB at the fit's size), as is Mitsuba's. Made
    of a fit just run (`fit_of`) or of one a scene sequence kept from an earlier run (`scene_sequences`)."""
    return Fit(
        Material.from_array(values),
        float("nan"),
        float(rmse),
        {},
        ranges,
        {},
        notices,
        summary,
        target,
        rendered,
        rendered,
        document,
        start,
        float(start_rmse),
        int(evaluations),
        start_image,
    )
