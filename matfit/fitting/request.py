"""What one fit of a picture file is asked to do: what to fit, how, and which outputs, as one frozen object.

`matfit fit`, the page's fit job and the bench each build one `Request` and hand it to `fitfile.run`
(which writes its `outputs`) or `fitfile.fit_file` (which writes nothing); `matfit sequence` builds one
per frame (its picture already read, the previous frame's optimum among its candidates) and hands it
to `fitfile.fit_neural` (the neural search alone). `matfit.fit` builds one for a picture file or an
array (its pixels already read). `Request.check` raises the one-line error of a bad
value before any work: no picture is read and no model loaded for a request that cannot run.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from matfit import files, images, params
from matfit.errors import FitError, ImageError, OutputError
from matfit.fitting import ranges
from matfit.fitting.methods import ANSWERS, CORRECTIONS, Settings, check_corrections
from matfit.rendering import engine


@dataclass(frozen=True)
class Outputs:
    """The files a fit writes: params.json always, the others when named."""

    params: str
    report: str | None = None
    render: str | None = None
    render_size: int = 512
    render_spp: int = 256
    mitsuba_xml: str | None = None
    blender: str | None = None

    def check(self, inputs: dict[str, str | None] | None = None, *, model: str | None = None) -> None:
        """Raises OutputError, before any work is done, for a path of the wrong kind, one that cannot be written,
        one named twice, one that is an input (`inputs`: {"target": path, ...}) that writing would overwrite, or
        one in the folder of the model `model` or of the shipped model."""
        if not self.params.lower().endswith(".json"):
            raise OutputError(f"output {self.params} must end in .json", field="output")
        for path in (self.report, self.render):
            if path is not None:
                images.check_extension(path)
        for path, suffix, name in ((self.mitsuba_xml, ".xml", "mitsuba_xml"), (self.blender, ".py", "blender")):
            if path is not None and not path.lower().endswith(suffix):
                raise OutputError(f"{name.replace('_', ' ')} {path} must end in {suffix}", field=name)
        named = {
            "output": self.params,
            "report": self.report,
            "render": self.render,
            "mitsuba_xml": self.mitsuba_xml,
            "blender": self.blender,
        }
        files.check_outputs(named, inputs, model=model)

    @property
    def needs_render(self) -> bool:
        """Returns whether an output shows the Mitsuba render of the result."""
        return self.report is not None or self.render is not None


@dataclass(frozen=True)
class Request:
    """One fit of a picture file: what to fit, how, and which files to write."""

    target: str  # the picture's path
    mask: str | None = None  # a picture's path: white = fit here, black = ignore
    init: str | None = None  # a params.json of the source material; its parameters join best-of-n's candidates
    # The source material's physical parameters (19,) when they were read already (the page's upload); `init` then
    # only names them in params.json.
    init_values: np.ndarray | None = field(default=None, compare=False)
    seed: int = 0  # the random start of `optimize`
    settings: Settings = field(default_factory=Settings)
    verified: bool = True  # let Mitsuba choose among the fit's final candidates (`verify`)
    corrections: int | None = None  # rounds of correction (`correct`); None: CORRECTIONS when verified, else none
    refine_steps: int = 0  # steps through Mitsuba's differentiable renderer after verification (`refine`)
    variant: str | None = None  # the Mitsuba variant of a renderer made for the fit; None: `engine.choose_variant`'s
    outputs: Outputs | None = None  # None: nothing is written (`fitfile.fit_file`)
    answer: str = "clean"  # "clean": the simplest material within the threshold of the fit's (`clean`); "best"
    # The picture as the model's sRGB target (R, R, 3) when it was read already (a sequence's frame); `target` then
    # only names it.
    pixels: np.ndarray | None = field(default=None, compare=False)
    # Unit-cube candidates (k, 19) that join best-of-n after the source material's (a sequence's previous optimum).
    candidates: np.ndarray | None = field(default=None, compare=False)
    # The mask as the model's weights (R, R) when it was read already (an array given to `matfit.fit`); `mask` then
    # only names it.
    weights: np.ndarray | None = field(default=None, compare=False)
    # The picture's SHA-256 for params.json when `target` names no file (an array given to `matfit.fit`); None: the
    # file's.
    target_sha256: str | None = None

    @property
    def rounds(self) -> int:
        """Returns the rounds of correction the fit runs."""
        if self.corrections is None:
            return CORRECTIONS if self.verified else 0
        return self.corrections

    @property
    def needs_render(self) -> bool:
        """Returns whether an output shows the Mitsuba render of the result."""
        return self.outputs is not None and self.outputs.needs_render

    def check(self, model: str | None = None) -> None:
        """Raises the one-line error (OutputError, FitError, ImageError, WeightsError) of the first value that cannot
        run; with the folder of the `model` to fit with, also of an output among its files or of its card
        (`ranges.read_card`)."""
        if self.outputs is not None:
            self.outputs.check({"target": self.target, "mask": self.mask, "init": self.init}, model=model)
        if model is not None:
            ranges.read_card(model)
        self.settings.check()
        if self.answer not in ANSWERS:
            raise FitError(
                f"answer {self.answer!r} is not one of {', '.join(ANSWERS)}: use --answer clean or best", field="answer"
            )
        if self.refine_steps < 0:
            raise FitError(f"refine steps {self.refine_steps} must be >= 0: use 0 to skip refinement", field="refine")
        if self.refine_steps and self.variant == engine.SCALAR_VARIANT:
            raise FitError(
                f"refinement differentiates with {engine.CUDA_VARIANT} or {engine.LLVM_VARIANT}, not "
                f"{engine.SCALAR_VARIANT}: leave --variant out or leave refinement off",
                field="variant",
            )
        check_corrections(self.rounds)
        if self.rounds and not self.verified:
            raise FitError(
                f"{self.rounds} correction rounds need verification's renders: drop --no-verify or add --corrections 0",
                field="corrections",
            )
        read = ((self.target, "target", self.pixels), (self.mask, "mask", self.weights))
        for path, name, given in read:  # a picture or mask given as pixels names no file
            if path is not None and given is None and not os.path.isfile(path):
                raise ImageError(f"{name} {path} is not a file: give the picture's path", field=name)

    def initial_values(self) -> np.ndarray | None:
        """Returns the source material's physical parameters (19,): `init_values`, else read from `init`, else None."""
        if self.init_values is not None:
            return np.asarray(self.init_values)
        return params.read_file(self.init) if self.init is not None else None

    def extra_candidates(self) -> np.ndarray | None:
        """Returns the unit-cube candidates (k, 19) the request adds to best-of-n, or None: the source material's
        (`initial_values`), then `candidates`, each as given (a unit-cube candidate is never converted)."""
        values = self.initial_values()
        parts = [] if values is None else [params.to_unit(values)[None]]
        if self.candidates is not None:
            parts.append(np.asarray(self.candidates).reshape(-1, params.COUNT))
        return np.concatenate(parts) if parts else None
