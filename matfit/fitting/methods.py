"""The fitting methods and their settings: plain data without JAX, so the command line offers them at start-up.

`Settings` holds what is compiled into a fit (the method, the budget, the box handling); what
varies per call (the target, the mask, the random start's seed) is passed to `search.neural_search` as data,
so one compilation serves every target and seed.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from enum import StrEnum

from matfit import params
from matfit.errors import FitError, flag, number, shown

ANSWERS = ("clean", "best")  # what a fit returns: the clean answer or the fit's own (docs/fitting.md)
CORRECTIONS = 2  # rounds of correction (`correct.py`) a verified fit runs by default: docs/fitting.md#correction


class Method(StrEnum):
    """How a fit searches: the paper's three methods and the gradient methods built on the exact decoder gradient."""

    hybrid = "hybrid"  # best-of-n, then Nelder-Mead from the winner (the paper's)
    nn = "nn"  # best-of-n only (the paper's)
    optimize = "optimize"  # Nelder-Mead from a random start (the paper's baseline)
    lbfgsb = "lbfgsb"  # best-of-n, then L-BFGS-B from the best `starts` candidates at once
    hybrid_lbfgsb = "hybrid-lbfgsb"  # best-of-n, Nelder-Mead, then L-BFGS-B from its result and the best candidates

    @property
    def uses_simplex(self) -> bool:
        """Returns whether the method runs Nelder-Mead."""
        return self in (Method.hybrid, Method.optimize, Method.hybrid_lbfgsb)

    @property
    def uses_gradient(self) -> bool:
        """Returns whether the method ends with L-BFGS-B."""
        return self in (Method.lbfgsb, Method.hybrid_lbfgsb)


class Box(StrEnum):
    """How Nelder-Mead is kept inside the parameter box."""

    clip = "clip"  # evaluate at the clipped point, plus a penalty growing with the distance outside
    barrier = "barrier"  # the paper's: a large constant outside


MAX_EVALUATIONS = 1_000_000
MIN_EVALUATIONS = params.COUNT + 2  # Nelder-Mead's initial simplex in 19 dimensions, plus one step
MAX_POLISH = 100_000
MAX_STARTS = 64
MAX_ITERATIONS = 100_000
MAX_STEP = 1.0  # Nelder-Mead's initial step and the polish's learning rate: the unit cube's side at most
MAX_CORRECTIONS = 100  # rounds of correction (`matfit fit --corrections`)
MAX_REFINE = 10_000  # steps of refinement (`matfit fit --refine`)
# Each whole-number setting's range, as `check` holds it (evaluations': the methods that run Nelder-Mead).
COUNTS = {
    "evaluations": (MIN_EVALUATIONS, MAX_EVALUATIONS),
    "polish_steps": (0, MAX_POLISH),
    "starts": (1, MAX_STARTS),
    "iterations": (1, MAX_ITERATIONS),
    "narrow_after": (1, MAX_ITERATIONS),
}


@dataclass(frozen=True)
class Settings:
    """How to fit: method, budget in objective evaluations, box handling, gradient polish steps.

    Checked when made: a value of the wrong kind or out of its range raises the one-line FitError naming it.
    """

    method: Method = Method.lbfgsb  # judged against the paper's hybrid 1500: docs/fitting.md#measured
    evaluations: int = 1500
    box: Box = Box.clip
    adaptive: bool = True
    initial_step: float = 0.1
    polish_steps: int = 0
    polish_rate: float = 3e-3
    starts: int = 4  # L-BFGS-B starts: the best candidates of best-of-n (and Nelder-Mead's result)
    iterations: int = 60  # L-BFGS-B steps of the best start, one value-and-gradient each (`gradient.py`)
    narrow_after: int = 35  # every start's L-BFGS-B steps; then the best alone (docs/fitting.md#the-gradient-stage)

    def __post_init__(self) -> None:
        try:  # accept the plain strings too ("hybrid"), as the library's callers write them
            object.__setattr__(self, "method", Method(self.method))
        except ValueError:
            raise FitError(
                f"method {self.method!r} is unknown: use one of {', '.join(m.value for m in Method)}", field="method"
            ) from None
        try:
            object.__setattr__(self, "box", Box(self.box))
        except ValueError:
            raise FitError(f"box {self.box!r} is unknown: use clip or barrier", field="box") from None
        for name, (low, high) in COUNTS.items():  # their kind here (60.5 would fail deep in the search), ranges below
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):  # NumPy's integers are Integral
                raise FitError(f"{name} {shown(value)} is not a whole number: use {low} to {high}", field=name)
            object.__setattr__(self, name, int(value))  # a NumPy integer as the int that params.json can hold
        object.__setattr__(self, "adaptive", flag("adaptive", self.adaptive, FitError))
        for name in ("initial_step", "polish_rate"):
            object.__setattr__(self, name, number(name, getattr(self, name), 0, MAX_STEP, FitError, above_low=True))
        self.check()

    def check(self) -> None:
        """Raises FitError for a value out of its range (run when made, once the values' kinds are checked)."""
        if self.method.uses_simplex and not MIN_EVALUATIONS <= self.evaluations <= MAX_EVALUATIONS:
            raise FitError(
                f"evaluations {self.evaluations} is out of range: Nelder-Mead in 19 dimensions needs {MIN_EVALUATIONS} "
                f"to {MAX_EVALUATIONS}",
                field="evaluations",
            )
        if not 0 <= self.polish_steps <= MAX_POLISH:
            raise FitError(
                f"polish steps {self.polish_steps} is out of range: use 0 to {MAX_POLISH}", field="polish_steps"
            )
        if not 1 <= self.starts <= MAX_STARTS:
            raise FitError(f"starts {self.starts} is out of range: use 1 to {MAX_STARTS}", field="starts")
        if not 1 <= self.iterations <= MAX_ITERATIONS:
            raise FitError(
                f"iterations {self.iterations} is out of range: use 1 to {MAX_ITERATIONS}", field="iterations"
            )
        if not 1 <= self.narrow_after <= MAX_ITERATIONS:
            raise FitError(
                f"narrow after {self.narrow_after} is out of range: use 1 to {MAX_ITERATIONS} (at least --iterations "
                "keeps every start to the end)",
                field="narrow_after",
            )


def check_corrections(corrections: int) -> None:
    """Raises FitError unless `corrections` (rounds of correction) is a count."""
    if corrections < 0:
        raise FitError(f"corrections {corrections} must be >= 0: use 0 to skip correction", field="corrections")
