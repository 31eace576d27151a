"""Nelder-Mead inside a box, one function evaluation per step, as an optimistix minimiser.

`NelderMead` plugs into `optx.minimise(fn, NelderMead(...), y0, args, max_steps=...)`. Each
solver step evaluates `fn` exactly once, so a budget of B evaluations is `max_steps = B - (n + 1)`
after the n + 1 evaluations of the initial simplex (see `steps_for_budget`). The algorithm is a
state machine whose phase says which point the next evaluation is for:

    reflect:  sort the simplex; c = centroid of all but the worst x_n; x_r = c + a (c - x_n)
              f_0 <= f_r < f_{n-1}: accept x_r | f_r < f_0: expand | f_r < f_n: contract outside
              | otherwise: contract inside
    expand:   x_e = c + b (x_r - c); keep the better of x_e and x_r
    outside:  x_oc = c + g (x_r - c); accept if f_oc <= f_r, else shrink
    inside:   x_ic = c + g (x_n - c); accept if f_ic < f_n, else shrink
    shrink k: x_k = x_0 + d (x_k - x_0) for k = 1..n, one vertex per step

which is scipy's `minimize(method="Nelder-Mead")` step for step (tests check the iterates). With
`adaptive=True` the coefficients follow Gao and Han (2012) for dimension n: a = 1,
b = 1 + 2/n, g = 0.75 - 1/(2n), d = 1 - 1/n; otherwise 1, 2, 1/2, 1/2.

Why a state machine: under `jax.vmap` (many fits at once) a `lax.cond` around the objective runs
every branch, so a classic iteration would pay for reflection, expansion, contraction and n shrink
evaluations every time. Here each step computes the candidate points (cheap vector arithmetic),
selects one by phase, and evaluates the objective once, batched across the vmapped fits.

The vertices only ever get replaced by better points (shrink keeps the best), so the best vertex
is the best point seen: it is the `y` every step returns. The box [lower, upper] only places the
initial simplex: vertex k is y0 + h e_k, or y0 - h e_k where that would leave the box. Keeping the
search inside the box is the objective's business (a barrier or a clip-plus-penalty, `search.py`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeAlias

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, PyTree, Scalar

if TYPE_CHECKING:
    # The objective as optimistix hands it to a solver: fn(y, args) returns (value, aux)
    SolverFn: TypeAlias = Callable[[Array, PyTree], tuple[Scalar, Any]]

REFLECT, EXPAND, OUTSIDE, INSIDE, SHRINK = range(5)


def steps_for_budget(evaluations: int, dimension: int) -> int:
    """Returns the `max_steps` that spends exactly `evaluations` function evaluations."""
    if evaluations < dimension + 2:
        raise ValueError(
            f"a budget of {evaluations} evaluations is too small for {dimension} dimensions: "
            f"use at least {dimension + 2}"
        )
    return evaluations - (dimension + 1)


def coefficients(dimension: int, adaptive: bool) -> tuple[float, float, float, float]:
    """Returns (reflection, expansion, contraction, shrink) coefficients."""
    if adaptive:
        return 1.0, 1.0 + 2.0 / dimension, 0.75 - 0.5 / dimension, 1.0 - 1.0 / dimension
    return 1.0, 2.0, 0.5, 0.5


def initial_simplex(y0: Array, step: float, lower: float | Array, upper: float | Array) -> Array:
    """Returns the (n + 1, n) simplex y0, y0 +- step e_k, each vertex inside [lower, upper]."""
    n = y0.shape[0]
    inside = jnp.clip(y0, lower, upper)
    offsets = jnp.where(inside + step <= upper, step, -step)[None, :] * jnp.eye(n, dtype=y0.dtype)
    return jnp.concatenate([inside[None], inside[None] + offsets])


class _State(eqx.Module):
    simplex: Array
    values: Array
    phase: Array
    shrink_index: Array
    centroid: Array
    reflected: Array
    reflected_value: Array
    evaluations: Array
    converged: Array


def best_so_far(state: _State) -> tuple[Array, Array]:
    """Returns the best point evaluated so far and its value.

    That is the best vertex, except while an expansion is pending: the reflected point that
    triggered it beat every vertex but is not in the simplex yet.
    """
    best = jnp.argmin(state.values)
    pending = (state.phase == EXPAND) & (state.reflected_value < state.values[best])
    return jnp.where(pending, state.reflected, state.simplex[best]), jnp.where(
        pending, state.reflected_value, state.values[best]
    )


def trial_point(state: _State, coefficient: tuple[float, float, float, float]) -> tuple[Array, ...]:
    """Returns (simplex, values, centroid, reflected point, the point this step evaluates) of a state's phase.

    A new reflection starts from the sorted simplex; the other phases keep the order. Every phase's
    point is an affine combination of the centroid and the worst vertex (x_r - c = a (c - x_n)), or
    for a shrink of the best vertex and vertex `shrink_index`.
    """
    a, b, g, d = coefficient
    n = state.simplex.shape[0] - 1
    reflecting = state.phase == REFLECT
    order = jnp.where(reflecting, jnp.argsort(state.values, stable=True), jnp.arange(n + 1))
    simplex, values = state.simplex[order], state.values[order]
    best, worst = simplex[0], simplex[n]
    centroid = jnp.where(reflecting, jnp.sum(simplex[:n], axis=0) / n, state.centroid)
    reflected = jnp.where(reflecting, (1 + a) * centroid - a * worst, state.reflected)
    candidates = jnp.stack(
        [
            reflected,
            (1 + a * b) * centroid - a * b * worst,
            (1 + g * a) * centroid - g * a * worst,
            (1 - g) * centroid + g * worst,
            best + d * (simplex[state.shrink_index] - best),
        ]
    )
    return simplex, values, centroid, reflected, candidates[state.phase]


def take_point(
    state: _State, simplex: Array, values: Array, reflected: Array, point: Array, value: Array
) -> tuple[Array, Array, Array, Array]:
    """Returns (simplex, values, the reflected point's value, the next phase) once `point` is evaluated: what
    replaces the worst vertex (or, in a shrink, vertex `shrink_index`), if anything, and which phase follows."""
    n = simplex.shape[0] - 1
    k = state.shrink_index
    reflecting, shrinking = state.phase == REFLECT, state.phase == SHRINK
    f0, f_second, f_worst = values[0], values[n - 1], values[n]
    fr = jnp.where(reflecting, value, state.reflected_value)
    after_reflect = jnp.select([value < f0, value < f_second, value < f_worst], [EXPAND, REFLECT, OUTSIDE], INSIDE)
    accept_point = jnp.select(
        [state.phase == REFLECT, state.phase == EXPAND, state.phase == OUTSIDE, state.phase == INSIDE],
        [(value >= f0) & (value < f_second), jnp.array(True), value <= fr, value < f_worst],
        jnp.array(False),
    )
    expand_keeps_reflection = (state.phase == EXPAND) & (value >= fr)
    new_point = jnp.where(expand_keeps_reflection, reflected, point)
    new_value = jnp.where(expand_keeps_reflection, fr, value)
    replaced = jnp.where(accept_point, n, -1)
    index = jnp.where(shrinking, k, replaced)
    slot = jnp.arange(n + 1) == index
    simplex = jnp.where(slot[:, None], new_point[None], simplex)
    values = jnp.where(slot, new_value, values)
    next_phase = jnp.select(
        [reflecting, state.phase == EXPAND, (state.phase == OUTSIDE) | (state.phase == INSIDE), shrinking],
        [after_reflect, REFLECT, jnp.where(accept_point, REFLECT, SHRINK), jnp.where(k >= n, REFLECT, SHRINK)],
    )
    return simplex, values, fr, next_phase


class NelderMead(optx.AbstractMinimiser):
    """Nelder-Mead with one evaluation per step; y must be a 1-D array.

    rtol, atol: stop when every vertex is within atol + rtol |x_0| of the best x_0 and every value
    within atol + rtol |f_0| of f_0 (checked when a new reflection starts). 0 runs the whole budget.
    """

    rtol: float = 0.0
    atol: float = 0.0
    norm: Callable[[PyTree], Scalar] = optx.max_norm
    adaptive: bool = True
    initial_step: float = 0.1
    lower: float = 0.0
    upper: float = 1.0

    def init(
        self,
        fn: SolverFn,
        y: Array,
        args: PyTree,
        options: dict[str, Any],
        f_struct: jax.ShapeDtypeStruct,
        aux_struct: PyTree[jax.ShapeDtypeStruct],
        tags: frozenset[object],
    ) -> _State:
        if y.ndim != 1:
            raise ValueError(f"NelderMead needs a 1-D y, got shape {y.shape}")
        simplex = initial_simplex(y, self.initial_step, self.lower, self.upper)
        values = jax.vmap(lambda vertex: fn(vertex, args)[0])(simplex).astype(f_struct.dtype)
        zero = jnp.zeros_like(y)
        return _State(
            simplex=simplex,
            values=values,
            phase=jnp.array(REFLECT),
            shrink_index=jnp.array(1),
            centroid=zero,
            reflected=zero,
            reflected_value=jnp.array(jnp.inf, values.dtype),
            evaluations=jnp.array(simplex.shape[0]),
            converged=jnp.array(False),
        )

    def step(
        self, fn: SolverFn, y: Array, args: PyTree, options: dict[str, Any], state: _State, tags: frozenset[object]
    ) -> tuple[Array, _State, Any]:
        n = y.shape[0]
        coefficient = coefficients(n, self.adaptive)
        simplex, values, centroid, reflected, point = trial_point(state, coefficient)
        value, aux = fn(point, args)
        value = value.astype(values.dtype)
        simplex, values, reflected_value, next_phase = take_point(state, simplex, values, reflected, point, value)
        k = state.shrink_index
        next_shrink = jnp.where((state.phase == SHRINK) & (k < n), k + 1, 1)
        converged = self._converged(simplex, values) & (next_phase == REFLECT)
        new_state = _State(
            simplex=simplex,
            values=values,
            phase=next_phase,
            shrink_index=next_shrink,
            centroid=centroid,
            reflected=reflected,
            reflected_value=reflected_value,
            evaluations=state.evaluations + 1,
            converged=converged,
        )
        return best_so_far(new_state)[0], new_state, aux

    def _converged(self, simplex: Array, values: Array) -> Array:
        if self.rtol == 0 and self.atol == 0:
            return jnp.array(False)
        best = jnp.argmin(values)
        x_scale = self.atol + self.rtol * jnp.abs(simplex[best])[None, :]
        f_scale = self.atol + self.rtol * jnp.abs(values[best])
        return jnp.all(jnp.abs(simplex - simplex[best][None, :]) <= x_scale) & jnp.all(
            jnp.abs(values - values[best]) <= f_scale
        )

    def terminate(
        self, fn: SolverFn, y: Array, args: PyTree, options: dict[str, Any], state: _State, tags: frozenset[object]
    ) -> tuple[Array, optx.RESULTS]:
        # an item of RESULTS; mypy reads the members of an enumeration that extends lineax's as their messages (str)
        return state.converged, optx.RESULTS.successful  # type: ignore[return-value]

    def postprocess(
        self,
        fn: SolverFn,
        y: Array,
        aux: Any,
        args: PyTree,
        options: dict[str, Any],
        state: _State,
        tags: frozenset[object],
        result: optx.RESULTS,
    ) -> tuple[Array, Any, dict[str, Array]]:
        point, value = best_so_far(state)
        return point, aux, {"evaluations": state.evaluations, "value": value}


def minimise(
    fn: Callable[[Array, Any], Scalar],
    y0: Array,
    args: Any,
    evaluations: int,
    solver: NelderMead | None = None,
) -> optx.Solution:
    """Returns optimistix's Solution of minimising fn(y, args) from y0 within `evaluations`.

    Reaching the budget is a normal outcome (`result` says `nonlinear_max_steps_reached`);
    `stats["evaluations"]` counts the evaluations spent and `stats["value"]` is the best value.
    """
    solver = solver or NelderMead()
    return optx.minimise(fn, solver, y0, args, max_steps=steps_for_budget(evaluations, y0.shape[-1]), throw=False)
