"""The paper's optimiser comparison: scipy's optimisers, ours and basin-hopping from a random and from the
best-of-9 start (table 2 of `matfit bench`)."""

from __future__ import annotations

import time

import numpy as np

from matfit import params
from matfit.fitting import search
from matfit.model import models


def optimiser_table(model: models.Model, cases, evaluations: int = 1500, basin_seconds: float = 5.0) -> list[dict]:
    """Returns the paper's optimiser comparison: each optimiser from a random and from the best-of-9 start.

    Nelder-Mead is ours (`evaluations` evaluations); L-BFGS-B, SLSQP and conjugate gradient are
    scipy's with exact gradients of the decoder (the budget below);
    basin-hopping (scipy, L-BFGS-B local steps with exact gradients) stops after `basin_seconds`.
    """
    return [
        {"case": name, **compare_optimisers(model, target, evaluations, basin_seconds)} for name, _, target in cases
    ]


BOX = [(0.0, 1.0)] * params.COUNT  # the unit cube, as scipy's bounds


def compare_optimisers(model: models.Model, target: np.ndarray, evaluations: int, basin_seconds: float) -> dict:
    """Returns RMSE, seconds and evaluations spent of every optimiser from both starts on one target.

    Every budget counts objective evaluations, a value-and-gradient as `search.GRADIENT_COST` of them:
    scipy's L-BFGS-B stops at `evaluations / GRADIENT_COST` calls (`maxfun`), SLSQP and CG at as
    many iterations (they may call more often; the table says how many they spent). "L-BFGS-B
    (ours)" is matfit's gradient stage (`gradient.py`, one value-and-gradient per step) with the
    same budget.
    """
    args = objective_args(model, target)
    bounded, penalised = value_and_gradients(args)
    calls = max(1, int(evaluations // search.GRADIENT_COST))
    solvers = scipy_solvers(bounded, penalised, calls)
    best = search.neural_search(model, target, settings=search.Settings(method=search.Method.nn))
    starts = {
        "random": np.random.default_rng(0).uniform(0.0, 1.0, params.COUNT).astype(np.float32),
        "best-of-9": best.start,
    }
    row: dict[str, float] = {}
    for start_name, x0 in starts.items():
        for solver_name, solve in solvers.items():
            solve(np.asarray(x0, np.float64))  # compile outside the timing
            started = time.perf_counter()
            solution = solve(np.asarray(x0, np.float64))
            seconds = time.perf_counter() - started
            row |= figures(
                f"{solver_name} ({start_name})", solution.x, seconds, solution.nfev * search.GRADIENT_COST, args
            )
        row |= ours(f"L-BFGS-B, ours ({start_name})", x0, args, calls)
        method = search.Method.hybrid if start_name == "best-of-9" else search.Method.optimize
        row |= nelder_mead(f"Nelder-Mead ({start_name})", model, target, method, evaluations, args)
        row |= basin_hopping(f"basin-hopping ({start_name})", bounded, x0, basin_seconds, args)
    return row


def objective_args(model: models.Model, target: np.ndarray) -> tuple:
    """Returns the objective's `args` for one target: the decoder, its weights, the target, uniform pixel weights."""
    import jax.numpy as jnp

    weights = jnp.ones(target.shape[:2], jnp.float32)
    return (model.decoder.module, model.decoder.variables, jnp.asarray(target), weights)


def value_and_gradients(args: tuple):
    """Returns scipy's objectives as host functions of float64 vectors, (value, gradient): the RMSE of the decoded
    point clipped into the box (for the bounded solvers), and the clip-penalised objective (for CG, which has none)."""
    import jax
    import jax.numpy as jnp

    bounded_grad = jax.jit(jax.value_and_grad(lambda x: search.decoded_rmse(x, args)))
    penalised_grad = jax.jit(jax.value_and_grad(lambda x: search.objective(x, (*args, search.Box.clip))))

    def host(function):
        def evaluate(x):
            value, grad = function(jnp.asarray(x, jnp.float32))
            return float(value), np.asarray(grad, np.float64)

        return evaluate

    return host(bounded_grad), host(penalised_grad)


def scipy_solvers(bounded, penalised, calls: int) -> dict:
    """Returns scipy's L-BFGS-B, SLSQP and CG as functions of a start, each held to `calls` calls or iterations."""
    import scipy.optimize

    return {
        "L-BFGS-B": lambda x0: scipy.optimize.minimize(
            bounded, x0, jac=True, method="L-BFGS-B", bounds=BOX, options={"maxfun": calls, "maxiter": calls}
        ),
        "SLSQP": lambda x0: scipy.optimize.minimize(
            bounded, x0, jac=True, method="SLSQP", bounds=BOX, options={"maxiter": calls}
        ),
        "CG": lambda x0: scipy.optimize.minimize(penalised, x0, jac=True, method="CG", options={"maxiter": calls}),
    }


def figures(name: str, x: np.ndarray, seconds: float, spent: float, args: tuple) -> dict:
    """Returns one optimiser's row entries: the RMSE of its answer (clipped into the box), seconds, evaluations."""
    import jax.numpy as jnp

    return {
        name: float(search.decoded_rmse(jnp.asarray(np.clip(x, 0.0, 1.0), jnp.float32), args)),
        f"{name} seconds": seconds,
        f"{name} evaluations": int(spent),
    }


def ours(name: str, x0: np.ndarray, args: tuple, calls: int) -> dict:
    """Returns the figures of matfit's gradient stage from `x0`, `calls` value-and-gradients (compiled untimed)."""
    import jax.numpy as jnp

    from matfit.fitting import gradient

    def minimise(start):
        ends, _, steps = gradient.minimise(search.gradient_objective(args[0]), start[None], args[1:], calls)
        return ends[0], steps

    minimise(jnp.asarray(x0))  # compile outside the timing
    started = time.perf_counter()
    end, count = minimise(jnp.asarray(x0))
    return figures(name, np.asarray(end), time.perf_counter() - started, count * search.GRADIENT_COST, args)


def nelder_mead(
    name: str, model: models.Model, target: np.ndarray, method: search.Method, evaluations: int, args: tuple
) -> dict:
    """Returns the figures of matfit's Nelder-Mead (`method`: from a random start, or the hybrid's best-of-9)."""
    started = time.perf_counter()
    result = search.neural_search(model, target, settings=search.Settings(method=method, evaluations=evaluations))
    return figures(name, result.unit, time.perf_counter() - started, result.evaluations, args)


def basin_hopping(name: str, bounded, x0: np.ndarray, seconds: float, args: tuple) -> dict:
    """Returns the figures of scipy's basin-hopping (L-BFGS-B local steps) from `x0`, stopped after `seconds`."""
    import scipy.optimize

    deadline = time.perf_counter() + seconds
    started = time.perf_counter()
    hopped = scipy.optimize.basinhopping(
        bounded,
        np.asarray(x0, np.float64),
        niter=100_000,
        stepsize=0.1,
        seed=0,
        minimizer_kwargs={"method": "L-BFGS-B", "jac": True, "bounds": BOX},
        callback=lambda x, f, accept: time.perf_counter() > deadline,
    )
    return figures(name, hopped.x, time.perf_counter() - started, hopped.nfev * search.GRADIENT_COST, args)
