"""The paper's optimiser comparison: scipy's optimisers, ours and basin-hopping from a random and from the
best-of-9 start (table 2 of `matfit bench`)."""

from __future__ import annotations

import time

import numpy as np

from matfit import params
from matfit.fit import search
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


def compare_optimisers(model: models.Model, target: np.ndarray, evaluations: int, basin_seconds: float) -> dict:
    """Returns RMSE, seconds and evaluations spent of every optimiser from both starts on one target.

    Every budget counts objective evaluations, a value-and-gradient as `search.GRADIENT_COST` of them:
    scipy's L-BFGS-B stops at `evaluations / GRADIENT_COST` calls (`maxfun`), SLSQP and CG at as
    many iterations (they may call more often; the table says how many they spent). "L-BFGS-B
    (ours)" is matfit's gradient stage (`gradient.py`, one value-and-gradient per step) with the
    same budget.
    """
    import jax
    import jax.numpy as jnp
    import scipy.optimize

    from matfit.fit import gradient

    decoder, variables = model.decoder.module, model.decoder.variables
    weights = jnp.ones(target.shape[:2], jnp.float32)
    target_j = jnp.asarray(target)
    args = (decoder, variables, target_j, weights)
    bounded_grad = jax.jit(jax.value_and_grad(lambda x: search.decoded_rmse(x, args)))
    penalised_grad = jax.jit(jax.value_and_grad(lambda x: search.objective(x, (*args, search.Box.clip))))

    def host(function):
        def evaluate(x):
            value, grad = function(jnp.asarray(x, jnp.float32))
            return float(value), np.asarray(grad, np.float64)

        return evaluate

    calls = max(1, int(evaluations // search.GRADIENT_COST))
    box = [(0.0, 1.0)] * params.COUNT

    def ours(x0):
        ends, _, steps = gradient.minimise(search.gradient_objective(decoder), x0[None], args[1:], calls)
        return ends[0], steps

    solvers = {
        "L-BFGS-B": lambda x0: scipy.optimize.minimize(
            host(bounded_grad), x0, jac=True, method="L-BFGS-B", bounds=box, options={"maxfun": calls, "maxiter": calls}
        ),
        "SLSQP": lambda x0: scipy.optimize.minimize(
            host(bounded_grad), x0, jac=True, method="SLSQP", bounds=box, options={"maxiter": calls}
        ),
        "CG": lambda x0: scipy.optimize.minimize(
            host(penalised_grad), x0, jac=True, method="CG", options={"maxiter": calls}
        ),
    }
    best = search.fit(model, target, search.Settings(method=search.Method.nn))
    starts = {
        "random": np.random.default_rng(0).uniform(0.0, 1.0, params.COUNT).astype(np.float32),
        "best-of-9": best.start,
    }
    row = {}

    def record(name: str, x: np.ndarray, seconds: float, spent: float) -> None:
        row[name] = float(search.decoded_rmse(jnp.asarray(np.clip(x, 0.0, 1.0), jnp.float32), args))
        row[f"{name} seconds"] = seconds
        row[f"{name} evaluations"] = int(spent)

    for start_name, x0 in starts.items():
        for solver_name, solve in solvers.items():
            solve(np.asarray(x0, np.float64))  # compile outside the timing
            started = time.perf_counter()
            solution = solve(np.asarray(x0, np.float64))
            record(
                f"{solver_name} ({start_name})",
                solution.x,
                time.perf_counter() - started,
                solution.nfev * search.GRADIENT_COST,
            )
        ours(jnp.asarray(x0))
        started = time.perf_counter()
        end, count = ours(jnp.asarray(x0))
        record(
            f"L-BFGS-B, ours ({start_name})",
            np.asarray(end),
            time.perf_counter() - started,
            count * search.GRADIENT_COST,
        )
        started = time.perf_counter()
        method = search.Method.hybrid if start_name == "best-of-9" else search.Method.optimize
        result = search.fit(model, target, search.Settings(method=method, evaluations=evaluations))
        record(f"Nelder-Mead ({start_name})", result.unit, time.perf_counter() - started, result.evaluations)
        deadline = time.perf_counter() + basin_seconds
        started = time.perf_counter()
        hopped = scipy.optimize.basinhopping(
            host(bounded_grad),
            np.asarray(x0, np.float64),
            niter=100_000,
            stepsize=0.1,
            seed=0,
            minimizer_kwargs={"method": "L-BFGS-B", "jac": True, "bounds": box},
            callback=lambda x, f, accept, deadline=deadline: time.perf_counter() > deadline,
        )
        record(
            f"basin-hopping ({start_name})", hopped.x, time.perf_counter() - started, hopped.nfev * search.GRADIENT_COST
        )
    return row
