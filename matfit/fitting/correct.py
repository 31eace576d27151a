"""Correction: the fit run again on the target less what the decoder gets wrong at its answer, as Mitsuba shows it.

The fit finds x where the decoder's picture phi(x) matches the target t. Where the decoder is
wrong, its error e(x) = R(x) - phi(x) (R: Mitsuba's render, sRGB) is carried into the answer: the
physical render is off by about e. That error changes slowly with the material (a refraction drawn
too blurred, a medium drawn too grey), so one render at the answer measures it, and the fit run
again from there on the corrected target t - e(x) moves the answer to where phi(y) + e(x) = t:
the decoder supplies the direction (its exact gradient), Mitsuba the residual. This is defect
correction, as in iterative refinement of a linear solve with an inexact factorisation: each
round costs one render and a short gradient fit, and a fixed point x* has R(x*) as close to t as
the decoder's derivatives can tell. Verification runs the rounds and keeps the last one's point
only if its estimated Mitsuba error is the lowest of the start's, the best end's and its own (`verify.py`).

Each round takes the answer closer to the target than verification alone, judged by independent
renders (`matfit bench-fit`); why two is the default: docs/fitting.md#correction.
"""

from __future__ import annotations

import numpy as np

from matfit.fitting import gradient, search
from matfit.model import models

# Gradient steps of a round's fit (it starts next to the answer of the corrected target): the fewest whose rounds judge
# as well as twice as many, at half the cost (docs/fitting.md#correction; the measurement: docs/decisions.md).
ITERATIONS = 15


def corrected_target(target: np.ndarray, rendered: np.ndarray, decoded: np.ndarray) -> np.ndarray:
    """Returns t - (R(x) - phi(x)): the target less the decoder's error at x, as Mitsuba's render `rendered` shows it.

    All three are sRGB (R, R, 3) in [0, 1]; the result may leave [0, 1] where the decoder is far off.
    """
    if not target.shape == rendered.shape == decoded.shape:
        raise ValueError(f"Shape mismatch: got {target.shape}, {rendered.shape} and {decoded.shape}.")
    error = np.asarray(rendered, np.float32) - np.asarray(decoded, np.float32)
    return np.asarray(target, np.float32) - error


def correction_round(
    model: models.Model,
    target: np.ndarray,
    weights: np.ndarray,
    unit: np.ndarray,
    rendered: np.ndarray,
    decoded: np.ndarray,
    *,
    iterations: int = ITERATIONS,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns one round of correction from `unit`: (the new point (19,), phi of it (R, R, 3)).

    `rendered`: Mitsuba's sRGB render of `unit`; `decoded`: phi(unit); `weights`: the fit's (R, R)
    mask weights. The gradient stage (`gradient.minimise`, the fit's objective and compiled step,
    one start) minimises RMSE(phi(y), t - (R(x) - phi(x))) from x.
    """
    data = (model.decoder.variables, corrected_target(target, rendered, decoded), np.asarray(weights, np.float32))
    ends, _, _ = gradient.minimise(
        search.gradient_objective(model.decoder.module), np.asarray(unit, np.float32)[None], data, iterations
    )
    point = np.clip(np.asarray(ends[0], np.float64), 0.0, 1.0)
    decoded = models.apply(model.decoder.module, model.decoder.variables, point[None].astype(np.float32))
    return point, np.asarray(decoded, np.float32)[0]  # indexed in NumPy: a JAX index is a program of its own
