"""What a fit found: the answer as each stage leaves it (`Answer`) and the finished fit (`Outcome`), frozen values that
the stages (`stages.py`) make and the document (`document.py`), the page and the API read."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from matfit import params
from matfit.fitting import clean, ranges, refine, search, verify


@dataclass(frozen=True)
class Answer:
    """The answer as a stage leaves it: the material, its decoded picture and figure, its Mitsuba render and ranges."""

    unit: np.ndarray  # the material (unit cube, (19,))
    image: np.ndarray  # phi(unit), sRGB (R, R, 3)
    neural_rmse: float  # of `image` against the target (weighted by the mask, if any)
    rendered: np.ndarray | None = None  # its Mitsuba render, sRGB (R, R, 3), or None: not rendered
    ranges: ranges.Ranges | None = None  # what the picture decides about it, or None: not measured yet


@dataclass(frozen=True)
class Outcome:
    """A finished fit of an image file (or one stage's answer, `stage`, as `stages.fit_stages` reports it): the answer,
    what each stage returned, the target as fitted, the document."""

    result: search.Result
    target: np.ndarray  # sRGB (R, R, 3) at the model's resolution
    answer: Answer
    verified: verify.Verified | None = None
    cleaned: clean.Cleaned | None = None  # the clean answer and how it was chosen (`answer="clean"`)
    refined: refine.Refined | None = None
    variant: str | None = None  # the Mitsuba variant that verified, refined or rendered the answer; None: no Mitsuba
    notices: tuple[str, ...] = ()
    document: dict[str, Any] = field(default_factory=dict)  # params.json (`document.build`)
    stage: str = "neural"  # the stage whose answer this is (`stages.NEURAL`, ...): the last one's, for a finished fit

    @property
    def unit(self) -> np.ndarray:
        """The answer (unit cube): the fit's best, what Mitsuba verification preferred, the clean or refined one."""
        return self.answer.unit

    @property
    def image(self) -> np.ndarray:
        """phi(answer), sRGB."""
        return self.answer.image

    @property
    def neural_rmse(self) -> float:
        """The answer's neural RMSE against the target."""
        return self.answer.neural_rmse

    @property
    def rendered(self) -> np.ndarray | None:
        """The answer's Mitsuba render at the model's resolution (sRGB), or None."""
        return self.answer.rendered

    @property
    def ranges(self) -> ranges.Ranges | None:
        """What the picture decides about the answer."""
        return self.answer.ranges

    @property
    def values(self) -> np.ndarray:
        """Returns the answer's physical parameters (19,)."""
        return params.from_unit(self.unit)

    def summary(self, output: str) -> str:
        """Returns one line on what was found and how well."""
        result, document = self.result, self.document
        mitsuba = ""
        if "mitsuba_rmse" in document:  # the answer's one figure, params.json's: that of the stage that chose it
            mitsuba = f", Mitsuba RMSE {document['mitsuba_rmse']:.2f}"
        if self.verified is not None:
            mitsuba += f" (verification kept {self.verified.chosen}; start {self.verified.start_rmse:.2f})"
        if self.refined is not None:
            refined = self.refined
            kept = "kept" if refined.accepted else "not kept"
            mitsuba += (
                f"; refined {refined.steps} steps, {kept} (its acceptance renders: {refined.rmse_before:.2f} -> "
                f"{refined.rmse_after:.2f})"
            )
        if self.cleaned is not None and self.cleaned.dropped:
            cleaned = self.cleaned
            mitsuba += f"; clean answer without {', '.join(cleaned.dropped)}"
            if cleaned.figures:
                mitsuba += (
                    f": Mitsuba {cleaned.figures['clean']:.2f} against {cleaned.figures['best']:.2f} "
                    f"(noise {cleaned.noise:.2f}), {cleaned.chosen} kept"
                )
        line = (
            f"{output}: {document['method']}, {result.evaluations} evaluations, neural RMSE {self.neural_rmse:.2f} "
            f"(start {result.chosen} {result.start_rmse:.2f}){mitsuba}, {document['wall_time_s']:.1f} s"
        )
        if self.ranges is not None:
            line += f"; {self.ranges.summary()}"
        return line
