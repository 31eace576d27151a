"""A job (one fit or render asked for by one page) and the page's view of its result: the figures, the pictures
as PNG, the files the CLI writes for the same fit."""

from __future__ import annotations

import base64
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from matfit import documents, images, params
from matfit.api.results import Fit

FILES = {
    "params.json": "application/json",
    "material.xml": "application/xml",
    "material.py": "text/x-python",
    "report.png": "image/png",
}


@dataclass
class Job:
    """One fit or render asked for by one page: its progress, and its result or error."""

    id: str
    kind: str  # "fit" or "render"
    state: str = "queued"  # queued, running, done, error, cancelled, superseded
    stage: str = "queued"
    progress: float = 0.0
    error: str | None = None
    status: int = 200  # the HTTP status of the job's answer: 4xx for the user's errors
    result: dict | None = None  # a fit's while it runs: its latest stage's answer (`fit_result`), until its own lands
    outcome: Fit | None = None  # the fit of a fit job, once done
    cancelled: threading.Event = field(default_factory=threading.Event)
    created: float = field(default_factory=time.perf_counter)
    finished: float | None = None

    def answer(self) -> dict:
        """Returns what the page is told about the job (strict JSON: a figure that is not finite is null)."""
        answer: dict[str, Any] = {"job": self.id, "kind": self.kind, "state": self.state, "stage": self.stage}
        answer["progress"] = round(self.progress, 3)
        if self.error is not None:
            answer["error"] = self.error
        if self.result is not None:
            answer["result"] = self.result
        return documents.finite(answer)


def png_data_url(srgb: np.ndarray) -> str:
    """Returns an sRGB image in [0, 1] as a PNG data URL for the page."""
    return "data:image/png;base64," + base64.b64encode(png_bytes(srgb)).decode()


def png_bytes(srgb: np.ndarray) -> bytes:
    """Returns an sRGB image in [0, 1] as PNG bytes (8-bit), encoded by the CLI's own writer."""
    return images.encode(images.srgb_decode(np.clip(np.asarray(srgb, np.float32), 0.0, 1.0)), ".png")


def fit_result(fitted: Fit) -> dict:
    """Returns the page's view of a fit, or of one stage's answer as it lands (`Fit.stage`): figures, the five pictures
    of the report, the 19 parameters. An answer not yet checked in Mitsuba (the neural search's: `mitsuba_checked`
    false) has no Mitsuba figure, render or difference (None), nor ranges."""
    from matfit.fitting import report

    document, rendered = fitted.document, fitted.rendered
    assert fitted.start_image is not None, "a fit of a picture keeps the search's start"
    return {
        "stage": fitted.stage,
        "mitsuba_checked": rendered is not None,
        "neural_rmse": round(fitted.neural_rmse, 3),
        "mitsuba_rmse": document.get("mitsuba_rmse"),
        "start": fitted.start,
        "start_rmse": round(fitted.start_rmse, 3),
        "kept": fitted.verification.get("kept"),
        "evaluations": fitted.evaluations,
        "seconds": document["wall_time_s"],
        "values": [round(float(v), 6) for v in fitted.material.array()],
        "pictures": {
            "target": png_data_url(fitted.target),
            "start": png_data_url(fitted.start_image),
            "neural": png_data_url(fitted.image),
            "mitsuba": None if rendered is None else png_data_url(rendered),
            "difference": None if rendered is None else png_data_url(report.difference(rendered, fitted.target)),
        },
        "notices": list(fitted.notices),
        "mask": document.get("mask"),
        "ranges": page_ranges(document.get("ranges")),
    }


def page_ranges(section: dict | None) -> dict | None:
    """Returns params.json's `ranges` section (`ranges.Ranges.document`) as the sliders take it: per parameter, in
    params.py's order and the sliders' physical units, its range and verdict; the look-alikes as 19 values each with
    which end they are ("roughness high"). The page's figures are the file's (docs/fitting.md#what-the-picture-decides).
    """
    if section is None:
        return None
    return {
        "threshold_rmse": section["threshold_rmse"],
        "parameters": [
            {key: section["parameters"][name][key] for key in ("low", "high", "verdict")} for name in params.NAMES
        ],
        "look_alikes": [
            {"label": alike["move"], "rmse": alike["rmse"], "values": params.from_mapping(alike["params"]).tolist()}
            for alike in section["look_alikes"]
        ],
    }


def fit_files(fitted: Fit) -> dict[str, bytes]:
    """Returns the files the CLI writes for the same fit (`fit -o params.json --report --mitsuba-xml --blender`)."""
    return {
        "params.json": fitted.to_json().encode(),
        "material.xml": fitted.material.to_mitsuba_xml().encode(),
        "material.py": fitted.material.to_blender_script().encode(),
        "report.png": png_bytes(fitted.report()),
    }
