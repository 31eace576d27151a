"""The choices every fit checks before any work: its options (`check_options`) and the kinds of its settings, init
and outputs (`check_choices`)."""

from __future__ import annotations

import os

from matfit import params
from matfit.api.arguments import flag, shown, whole
from matfit.api.material import Material
from matfit.api.results import Outputs
from matfit.errors import FitError, ImageError, OutputError, ParameterError
from matfit.fitting.methods import ANSWERS, MAX_CORRECTIONS, MAX_REFINE, Settings


def check_options(
    linear: object, verify: object, corrections: object, answer: object, refine: object, seed: object
) -> tuple[bool, bool, int | None, int, int]:
    """Returns (linear, verify, corrections, refine, seed) of a fit, checked with `answer`: the FitError (the
    ImageError of `linear`) of a value of the wrong kind or out of its range, before any work."""
    if not isinstance(answer, str) or answer not in ANSWERS:
        raise FitError(
            f"answer {shown(answer)} is not one of {', '.join(ANSWERS)}: give answer='clean' or answer='best'",
            field="answer",
        )
    return (
        flag("linear", linear, ImageError),
        flag("verify", verify, FitError),
        None if corrections is None else whole("corrections", corrections, 0, MAX_CORRECTIONS, FitError),
        whole("refine", refine, 0, MAX_REFINE, FitError),
        whole("seed", seed, 0, params.MAX_SEED, FitError),
    )


def check_choices(settings: object, init: object, outputs: object = None) -> None:
    """Raises the MatfitError of `settings` that is no `Settings`, `init` that is no path or `Material`, or `outputs`
    that are no `Outputs`."""
    if outputs is not None and not isinstance(outputs, Outputs):
        raise OutputError(
            f"outputs {shown(outputs)} is no matfit.Outputs: give Outputs(params, ...) or None", field="output"
        )
    if settings is not None and not isinstance(settings, Settings):
        raise FitError(
            f"settings {shown(settings)} is no matfit.Settings: give Settings(...) or None", field="settings"
        )
    if init is not None and not isinstance(init, str | os.PathLike | Material):
        raise ParameterError(
            f"init {shown(init)} is no params.json path or matfit.Material: give one, or "
            "Material.from_array(values) of the 19 values in `matfit params` order",
            field="init",
        )
