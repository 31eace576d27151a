"""Bounded L-BFGS-B from many starts at once: jaxopt's native `LBFGSB`, vmapped, with exact gradients.

The objective is a pure `fn(y, args)` on the unit cube [0, 1]^n; the starts run as one batch, so
each step of the batch costs one batched call of `fn` (for matfit: one batched decoder call),
whatever the number of starts. Under `vmap` the loop runs until the slowest start stops, at most
`iterations` steps; each start counts its own value-and-gradient evaluations.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

with (
    warnings.catch_warnings()
):  # jaxopt says on import that it is no longer maintained; its native LBFGSB is what we need
    warnings.simplefilter("ignore", DeprecationWarning)
    import jaxopt

TOLERANCE = 1e-4  # projected-gradient norm at which a start stops (RMSE units per unit of the cube)


def minimise(
    fn: Callable[[jax.Array, Any], jax.Array], starts: jax.Array, args: Any, iterations: int
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Returns (end points (k, n), fn at them (k,), value-and-gradient evaluations (k,)) of L-BFGS-B from k starts in the box."""
    solver = jaxopt.LBFGSB(fun=fn, maxiter=iterations, tol=TOLERANCE)
    n = starts.shape[-1]
    bounds = (jnp.zeros(n, starts.dtype), jnp.ones(n, starts.dtype))

    def run(y0: jax.Array) -> tuple[jax.Array, jax.Array]:
        solution = solver.run(y0, bounds, args)
        return jnp.clip(solution.params, 0.0, 1.0), solution.state.num_fun_eval

    ends, counts = jax.vmap(run)(starts)
    return ends, jax.vmap(lambda y: fn(y, args))(ends), counts
