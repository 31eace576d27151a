"""Bounded L-BFGS from many starts at once, one value-and-gradient evaluation per step, with an exact budget.

`minimise(fn, starts, args, steps)` minimises a pure `fn(y, args)` over the unit cube [0, 1]^n
from k starts as one batch: every step evaluates `fn` and its gradient once per start, in one
batched call (for matfit: one batched decoder forward and backward pass), so a step costs k
value-and-gradient evaluations whatever happens inside, and `steps` steps bound the budget.

The algorithm is projected L-BFGS (the "two-metric" projection of Bertsekas, with an L-BFGS
metric on the free variables). Like `simplex.py` it is a state machine whose step evaluates the
trial point the previous step chose:

    trial accepted (Armijo: f_t <= f + c1 g.(x_t - x), and f_t <= f):
        store the pair (x_t - x, g_t - g) if its curvature is positive; x, f, g <- trial;
        variables on a face of the box whose gradient points outwards are held (the active set);
        d = -H g on the free variables (two-loop recursion over the last `memory` pairs,
        H0 = s.y / y.y; before any pair: a step of at most `initial_step` per coordinate);
        a direction that is not downhill is replaced by the scaled steepest descent;
        next trial: clip(x + d)
    trial rejected: backtrack along the same d to the minimiser of the quadratic through f,
        g.d and f_t, kept within [0.1, 0.5] of the last step; next trial: clip(x + a d)

Why not jaxopt's `LBFGSB`: its zoom line search evaluates a varying number of times per
iteration inside `lax.while_loop`s; under `vmap` every start waits for the slowest, the budget is
not known in advance, and compiling it is slow.

Why the loop runs on the host (a Python loop over the compiled `step`) and not in `lax.fori_loop`:
on XLA's CPU backend the decoder's backward pass inside a loop body runs many times slower than
the same compiled call outside one (unrolled or not; the forward pass alone is not affected, which
is why the Nelder-Mead loop stays compiled), and a call costs far less dispatch than a step
computes. See docs/fitting.md#the-gradient-stage.

The starts are split among `workers` threads (WORKERS, at most one per processor), each running
the loop over its share as a smaller batch: XLA's CPU backend runs the decoder's small
convolutions on one thread, so one batch of 4 leaves the second core idle
(docs/fitting.md#the-gradient-stage). Each start's path is its own (the batch only shares the
calls), so the split changes nothing but the rounding of the batched convolutions.

A start whose projected gradient falls below `tolerance` stops moving (its steps still evaluate,
as the batch does). The accepted points only ever improve, so a start's `x` is its best point.
With `narrow_after`, the batch runs that many steps, then the best start goes on alone (a batch
of one: the step's second compiled shape); the others end where they are.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from matfit import programs

TOLERANCE = 1e-4  # projected-gradient max-norm at which a start stops (RMSE units per unit of the cube)
MEMORY = 8  # L-BFGS pairs kept
INITIAL_STEP = 0.05  # the first step moves no coordinate further than this (a twentieth of the cube)
ARMIJO = 1e-4
CURVATURE_FLOOR = 1e-10  # pairs with s.y at or below this (relative to y.y) are not stored
CHECK_EVERY = 5  # steps between the host's checks for convergence of every start
WORKERS = 2  # threads sharing the starts (at most one per processor): see the module's docstring


def _two_loop(
    g: jax.Array, s: jax.Array, y: jax.Array, rho: jax.Array, newest: jax.Array, gamma: jax.Array
) -> jax.Array:
    """Returns H g for the L-BFGS inverse-Hessian H of the stored pairs (rho 0 marks an empty slot)."""
    memory = s.shape[0]
    order = (newest - jnp.arange(memory)) % memory  # newest first

    def backward(q: jax.Array, k: jax.Array) -> tuple[jax.Array, jax.Array]:
        i = order[k]
        a = rho[i] * jnp.dot(s[i], q)
        return q - a * y[i], a

    q, alphas = jax.lax.scan(backward, g, jnp.arange(memory))

    def forward(r: jax.Array, k: jax.Array) -> tuple[jax.Array, None]:
        i = order[memory - 1 - k]
        b = rho[i] * jnp.dot(y[i], r)
        return r + s[i] * (alphas[memory - 1 - k] - b), None

    r, _ = jax.lax.scan(forward, gamma * q, jnp.arange(memory))
    return r


def _free_gradient(x: jax.Array, g: jax.Array) -> jax.Array:
    """Returns g with the held variables zeroed: those on a face of the box whose gradient points outwards."""
    return jnp.where(((x <= 0.0) & (g > 0.0)) | ((x >= 1.0) & (g < 0.0)), 0.0, g)


def _first_scale(x: jax.Array, g: jax.Array) -> jax.Array:
    """Returns the steepest-descent scale whose step moves no free coordinate further than INITIAL_STEP."""
    return INITIAL_STEP / jnp.maximum(jnp.max(jnp.abs(_free_gradient(x, g))), 1e-12)


def _direction(
    x: jax.Array, g: jax.Array, s: jax.Array, y: jax.Array, rho: jax.Array, newest: jax.Array, gamma: jax.Array
) -> jax.Array:
    """Returns the search direction at x: -H g on the free variables, zero on the held ones."""
    masked = _free_gradient(x, g)
    free = masked != 0.0
    d = -jnp.where(free, _two_loop(masked, s, y, rho, newest, gamma), 0.0)
    downhill = jnp.dot(d, masked) < 0.0
    return jnp.where(downhill, d, -gamma * masked)


def init(starts: np.ndarray, memory: int = MEMORY) -> dict[str, np.ndarray]:
    """Returns the state of k starts (k, n) before their first evaluation (at the starts, clipped into the box).

    Host (NumPy) arrays: every JAX operation outside a compiled program is a small program of its
    own, traced and compiled (or read from the cache) on its first use in a process.
    """
    starts = np.asarray(starts)
    k, n = starts.shape
    dtype = starts.dtype
    x0 = np.clip(starts, 0.0, 1.0)
    return {
        "x": x0,
        "f": np.full(k, np.inf, dtype),
        "g": np.zeros((k, n), dtype),
        "d": np.zeros((k, n), dtype),
        "step": np.ones(k, dtype),
        "trial": x0,
        "s": np.zeros((k, memory, n), dtype),
        "y": np.zeros((k, memory, n), dtype),
        "rho": np.zeros((k, memory), dtype),
        "newest": np.zeros(k, np.int32),
        "gamma": np.ones(k, dtype),
        "converged": np.zeros(k, bool),
    }


def _update(state: dict, f_t: jax.Array, g_t: jax.Array, tolerance: float) -> dict:
    """Returns one start's state after the evaluation (f_t, g_t) of its trial point."""
    memory = state["s"].shape[0]
    x, f, g, d, trial = state["x"], state["f"], state["g"], state["d"], state["trial"]
    first = jnp.isinf(f)
    moved = trial - x
    slope = jnp.dot(g, moved)
    accept = first | ((f_t <= f + ARMIJO * jnp.minimum(slope, 0.0)) & (f_t <= f))
    accept = accept & jnp.isfinite(f_t)
    # On acceptance: the new pair, the new point, the new direction.
    dy = g_t - g
    sy, yy = jnp.dot(moved, dy), jnp.dot(dy, dy)
    store = accept & ~first & (sy > CURVATURE_FLOOR * jnp.maximum(yy, 1e-30))
    slot = (state["newest"] + 1) % memory
    s = jnp.where(store, state["s"].at[slot].set(moved), state["s"])
    y = jnp.where(store, state["y"].at[slot].set(dy), state["y"])
    rho = jnp.where(store, state["rho"].at[slot].set(1.0 / jnp.where(store, sy, 1.0)), state["rho"])
    newest = jnp.where(store, slot, state["newest"])
    gamma = jnp.where(store, sy / jnp.maximum(yy, 1e-30), jnp.where(first, _first_scale(trial, g_t), state["gamma"]))
    new_x = jnp.where(accept, trial, x)
    new_f = jnp.where(accept, f_t, f)
    new_g = jnp.where(accept, g_t, g)
    new_d = _direction(trial, g_t, s, y, rho, newest, gamma)
    # On rejection: backtrack to the minimiser of the quadratic through f, slope and f_t.
    curvature = f_t - f - slope
    shrink = jnp.where(curvature > 0, -0.5 * slope / jnp.where(curvature > 0, curvature, 1.0), 0.5)
    shrink = jnp.clip(jnp.where(jnp.isfinite(shrink), shrink, 0.5), 0.1, 0.5)
    step = jnp.where(accept, 1.0, state["step"] * shrink)
    d = jnp.where(accept, new_d, d)
    descent = jnp.clip(new_x - new_g, 0.0, 1.0) - new_x  # the projected steepest descent at the best point
    converged = jnp.max(jnp.abs(descent)) < tolerance
    # Backtracked to nothing (the L-BFGS metric went bad): forget it, restart from steepest descent.
    lost = ~converged & (step * jnp.max(jnp.abs(d)) < 1e-7)
    restart = _first_scale(new_x, new_g)
    d = jnp.where(lost, -restart * _free_gradient(new_x, new_g), d)
    step = jnp.where(lost, 1.0, step)
    rho = jnp.where(lost, 0.0, rho)
    gamma = jnp.where(lost, restart, gamma)
    return {
        "x": new_x,
        "f": new_f,
        "g": new_g,
        "d": d,
        "step": step,
        "trial": jnp.where(converged, new_x, jnp.clip(new_x + step * d, 0.0, 1.0)),  # converged starts stay
        "s": s,
        "y": y,
        "rho": rho,
        "newest": newest,
        "gamma": gamma,
        "converged": converged,
    }


@programs.jit(static_argnames=("fn", "tolerance"))
def step(fn: Callable[[jax.Array, Any], jax.Array], state: dict, args: Any, tolerance: float = TOLERANCE) -> dict:
    """Returns the state after one step: every start's trial point evaluated (one batched call), then updated."""
    f_t, g_t = jax.vmap(jax.value_and_grad(fn), in_axes=(0, None))(state["trial"], args)
    return jax.vmap(partial(_update, tolerance=tolerance))(state, f_t, g_t)


def _run(
    fn: Callable[[jax.Array, Any], jax.Array], state: dict, args: Any, steps: int, tolerance: float
) -> tuple[dict[str, np.ndarray], int]:
    """Returns (the state after at most `steps` steps, on the host; the steps taken) from a host state: it stops early
    once every start converged.

    The state goes to the device committed, as the step's outputs are: otherwise the first step
    and the others would be two compilations of one program.
    """
    state = jax.device_put(state, jax.devices()[0])
    done = 0
    for done in range(1, steps + 1):
        state = step(fn, state, args, tolerance)
        if done % CHECK_EVERY == 0 and np.all(jax.device_get(state["converged"])):
            break
    return jax.device_get(state), done


def processors() -> int:
    """Returns how many processors this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@functools.cache
def _pool(threads: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(threads, thread_name_prefix="matfit-gradient")


def _run_shared(
    fn: Callable[[jax.Array, Any], jax.Array],
    starts: np.ndarray,
    args: Any,
    steps: int,
    tolerance: float,
    memory: int,
    workers: int,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Returns (the state of every start, the steps each one took) after `_run` over the starts split among `workers`
    threads (the caller's thread runs the first share)."""
    shares = [share for share in np.array_split(starts, min(workers, len(starts))) if len(share)]
    others = [
        _pool(len(shares) - 1).submit(_run, fn, init(share, memory), args, steps, tolerance) for share in shares[1:]
    ]
    runs = [_run(fn, init(shares[0], memory), args, steps, tolerance), *(job.result() for job in others)]
    state = {name: np.concatenate([run[0][name] for run in runs]) for name in runs[0][0]}
    done = np.concatenate([np.full(len(share), run[1]) for share, run in zip(shares, runs, strict=True)])
    return state, done


def minimise(
    fn: Callable[[jax.Array, Any], jax.Array],
    starts: np.ndarray,
    args: Any,
    steps: int,
    tolerance: float = TOLERANCE,
    memory: int = MEMORY,
    narrow_after: int | None = None,
    workers: int | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Returns (best points (k, n), fn at them (k,), value-and-gradient evaluations spent by all starts) from k starts.

    At most `steps` steps (the first evaluates the starts); with `narrow_after`, every start takes
    that many steps, then only the best one so far goes on, alone, to `steps` (the others end
    where they are). The best start's later steps lower the decoded RMSE most; the others' ends,
    less refined, stay candidates for Mitsuba's verification: a short shared budget then the best
    alone reaches a lower decoded RMSE than every start running as long, and as good a verified
    answer, in less time (docs/fitting.md#the-gradient-stage). The loop ends early once every start
    still moving has converged (checked every CHECK_EVERY steps). `fn` must be the same object
    from call to call, or an equal one (it is a static argument of the compiled step). Host work
    in between is NumPy, not JAX (see `init`).
    `workers`: threads sharing the starts (None: WORKERS, at most one per processor).
    """
    if steps < 1:
        raise ValueError(f"steps {steps} must be at least 1")
    if narrow_after is not None and narrow_after < 1:
        raise ValueError(f"narrow_after {narrow_after} must be at least 1")
    if workers is not None and workers < 1:
        raise ValueError(f"workers {workers} must be at least 1")
    workers = min(WORKERS, processors()) if workers is None else workers
    starts = np.asarray(starts)
    together = steps if narrow_after is None else min(narrow_after, steps)
    state, done = _run_shared(fn, starts, args, together, tolerance, memory, workers)
    x, f, spent = state["x"].copy(), state["f"].copy(), int(done.sum())
    best = int(np.argmin(f))
    if done[best] == together < steps and not state["converged"][best]:  # the best goes on alone
        alone = {name: leaf[best : best + 1] for name, leaf in state.items()}
        alone, more = _run(fn, alone, args, steps - together, tolerance)
        x[best], f[best], spent = alone["x"][0], alone["f"][0], spent + more
    return x, f, spent
