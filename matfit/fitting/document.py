"""What a fit writes about itself: the params.json document (`build`) and the report picture (`report_picture`)."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import numpy as np

from matfit import documents, files, images, params, shipped
from matfit.fitting import clean, verify
from matfit.fitting.request import Request

if TYPE_CHECKING:
    from matfit.fitting.outcome import Outcome

# The folder holding the package: the clone, or site-packages when installed (the shipped model reads
# matfit/data/model either way; a user's own paths lie outside it and stay as given).
PROJECT = str(shipped.PACKAGE.parent)


def display_path(path: str) -> str:
    """Returns a path as people should read it in reports: relative to the project when inside it, else as given."""
    absolute = os.path.abspath(path)
    if os.path.commonpath([absolute, PROJECT]) == PROJECT:
        return os.path.relpath(absolute, PROJECT)
    return path


def params_text(outcome: Outcome) -> str:
    """Returns the params.json of a fit, as written."""
    return documents.dumps(outcome.document)


def answer_section(cleaned: clean.Cleaned) -> dict:
    """Returns params.json's `answer` section: the clean answer, the candidates judged and the fit's own answer."""
    return {
        "kind": "clean",
        "kept": cleaned.chosen,
        "features_off": list(cleaned.dropped),
        "mitsuba_rmse": {name: round(value, 3) for name, value in cleaned.figures.items()},
        "render_noise": round(cleaned.noise, 3) if cleaned.figures else None,  # null: nothing was rendered
        "candidates": {  # nested, the simplest last; margin: standard errors behind the best (null: decided)
            name: {
                "features_off": candidate["off"],
                "decoded_distance": round(candidate["distance"], 3),
                **({"mitsuba_rmse": round(candidate["mitsuba"], 3)} if "mitsuba" in candidate else {}),
                **(
                    {"margin": round(candidate["margin"], 2) if np.isfinite(candidate["margin"]) else None}
                    if "margin" in candidate
                    else {}
                ),
            }
            for name, candidate in cleaned.candidates.items()
        },
        "free_not_neutral": {"best": cleaned.free_before, "answer": cleaned.free_after},
        "best": params.to_mapping(params.from_unit(cleaned.best)),
        "seconds": round(cleaned.seconds, 3),
    }


def build(outcome: Outcome, request: Request, model_path: str) -> dict:
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
                "spp": verify.BATCH_SPP,
                "seconds": round(checked.seconds, 3),
            },
        }
    elif outcome.rendered is not None:
        mitsuba = {"mitsuba_rmse": round(float(images.rmse(outcome.rendered, outcome.target)), 3)}
    if outcome.cleaned is not None:
        cleaned = outcome.cleaned
        if cleaned.figures:
            mitsuba["mitsuba_rmse"] = round(cleaned.figures[cleaned.chosen], 3)
        mitsuba["answer"] = answer_section(cleaned)
    if outcome.refined is not None:
        refined = outcome.refined
        if refined.accepted or "mitsuba_rmse" not in mitsuba:  # else the answer is still the one an earlier stage chose
            mitsuba["mitsuba_rmse"] = round(refined.rmse, 3)  # the kept point's acceptance render
        mitsuba["refinement"] = {
            "steps": refined.steps,
            "kept": refined.accepted,
            "mitsuba_rmse_before": round(refined.rmse_before, 3),
            "mitsuba_rmse_after": round(refined.rmse_after, 3),
            "seconds": round(refined.seconds, 3),
        }
    if outcome.ranges is not None:
        mitsuba["ranges"] = outcome.ranges.document()
    return params.params_document(
        outcome.values,
        method=request.settings.method.value,
        evaluations=result.evaluations,
        neural_rmse=round(outcome.neural_rmse, 3),
        start=result.chosen,
        start_rmse=round(result.start_rmse, 3),
        **mitsuba,
        box=request.settings.box.value,
        polish_steps=request.settings.polish_steps,
        model=display_path(model_path),
        target=request.target,
        target_sha256=request.target_sha256 or files.sha256(request.target),
        mask=request.mask,
        init=request.init,
        mitsuba_variant=outcome.variant,
        fit_seconds=round(result.seconds, 3),
        wall_time_s=0.0,
    )


def report_picture(outcome: Outcome) -> np.ndarray:
    """Returns the report: target | best-of-n start | fit (neural) | fit (Mitsuba render) | difference, as sRGB."""
    from matfit.fitting import report

    result = outcome.result
    assert outcome.rendered is not None, "fit_file renders the answer when a report is asked for (needs_render)"
    panels = [
        (outcome.target, "target"),
        (result.start_image, f"best-of-n {result.start_rmse:.2f}"),
        (outcome.image, f"fit (neural) {outcome.neural_rmse:.2f}"),
        (outcome.rendered, f"fit (Mitsuba) {outcome.document['mitsuba_rmse']:.2f}"),
        (report.difference(outcome.rendered, outcome.target), "|Mitsuba - target| x4"),
    ]
    if outcome.ranges is not None:
        found = outcome.ranges
        panel = report.ranges_panel(params.NAMES, outcome.unit, found.low, found.high, found.verdicts)
        panels.append((panel, f"ranges within {found.threshold:.2f}"))
    return report.compose(panels)
