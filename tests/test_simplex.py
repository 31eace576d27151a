import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

from matfit.fitting import simplex

N = 19


def shifted_rosenbrock(x, centre):
    z = 4.0 * (x - centre) + 1.0  # minimum at x = centre
    return jnp.sum(100.0 * (z[1:] - z[:-1] ** 2) ** 2 + (1.0 - z[:-1]) ** 2)


def quadratic(x, args):
    centre, weights = args
    return jnp.sum(weights * (x - centre) ** 2)


def problem(seed):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.1, 0.9, N), rng.uniform(0.5, 5.0, N)


def scipy_iterates(fn, x0, initial, adaptive, maxfev):
    """Returns [(evaluations so far, best x)] after every scipy Nelder-Mead iteration."""
    calls = [0]

    def counted(x):
        calls[0] += 1
        return fn(x)

    trace = []

    def callback(intermediate_result):  # scipy passes the result object to a parameter of this name
        trace.append((calls[0], np.array(intermediate_result.x)))

    scipy.optimize.minimize(
        counted,
        x0,
        method="Nelder-Mead",
        callback=callback,
        options={"initial_simplex": initial, "adaptive": adaptive, "xatol": 0, "fatol": 0, "maxfev": maxfev},
    )
    return trace


def stepped(fn, y0, args, evaluations, solver):
    """Returns [(evaluations so far, best point)] after every step of `solver` within `evaluations`.

    The solver's own `init` and `step`, as `optx.minimise` runs them, with the step compiled once: a `minimise` per
    budget would compile a loop per budget (optimistix takes `max_steps` as a Python int).
    """

    def wrapped(y, args):
        return fn(y, args), None

    state = jax.jit(lambda y0: solver.init(wrapped, y0, args, {}, jax.eval_shape(fn, y0, args), None, frozenset()))(y0)

    @jax.jit
    def step(y, state):
        y, state, _ = solver.step(wrapped, y, args, {}, state, frozenset())
        return y, state, state.evaluations

    y, trace = y0, []
    for _ in range(simplex.steps_for_budget(evaluations, y0.shape[0])):
        y, state, spent = step(y, state)
        trace.append((int(spent), np.asarray(y)))
    return trace


@pytest.mark.parametrize("adaptive", [True, False])
def test_follows_scipy_step_for_step(adaptive):
    with jax.enable_x64(True):
        centre = jnp.asarray(problem(0)[0])
        x0 = jnp.full(N, 0.5)
        initial = np.asarray(simplex.initial_simplex(x0, 0.1, 0.0, 1.0))
        solver = simplex.NelderMead(adaptive=adaptive)

        def fn(x, args):
            return shifted_rosenbrock(x, args)

        trace = scipy_iterates(lambda x: float(fn(jnp.asarray(x), centre)), np.asarray(x0), initial, adaptive, 700)
        checkpoints = [(evaluations, x) for evaluations, x in trace[:: max(1, len(trace) // 8)] if evaluations >= N + 2]
        ours = dict(stepped(fn, x0, centre, checkpoints[-1][0], solver))
        for evaluations, expected in checkpoints:
            np.testing.assert_allclose(ours[evaluations], expected, rtol=0, atol=1e-9)
        assert len(checkpoints) >= 5
        # `minimise` with the last budget runs those same steps: exactly that many evaluations, the same point.
        evaluations, expected = checkpoints[-1]
        solution = simplex.minimise(fn, x0, centre, evaluations, solver)
        assert int(solution.stats["evaluations"]) == evaluations
        np.testing.assert_allclose(solution.value, expected, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(solution.value, ours[evaluations])


@pytest.mark.parametrize("seed", [1, 2])
def test_finds_an_off_centre_minimum_as_scipy_does(seed):
    with jax.enable_x64(True):
        centre, weights = (jnp.asarray(a) for a in problem(seed))
        x0 = jnp.full(N, 0.5)
        ours = simplex.minimise(quadratic, x0, (centre, weights), 6000, simplex.NelderMead(atol=1e-10))
        theirs = scipy.optimize.minimize(
            lambda x: float(quadratic(jnp.asarray(x), (centre, weights))),
            np.asarray(x0),
            method="Nelder-Mead",
            options={"adaptive": True, "maxfev": 6000, "xatol": 1e-10, "fatol": 1e-10},
        )
        assert np.max(np.abs(theirs.x - centre)) < 1e-4
        assert np.max(np.abs(ours.value - centre)) < 1e-4
        assert int(ours.stats["evaluations"]) <= 6000


def test_budget_is_counted_exactly_and_compiles_once():
    calls = []

    def fn(x, args):
        calls.append(1)  # counts traces, not evaluations
        return quadratic(x, args)

    solve = jax.jit(lambda y0, args: simplex.minimise(fn, y0, args, 50))
    for seed in (3, 4, 5):
        centre, weights = (jnp.asarray(a, jnp.float32) for a in problem(seed))
        solution = solve(jnp.full(N, 0.5, jnp.float32), (centre, weights))
        assert int(solution.stats["evaluations"]) == 50
        assert int(solution.stats["num_steps"]) == 50 - (N + 1)
    assert len(calls) <= 3  # traced while compiling the first call only


def test_vmapped_fits_match_single_fits():
    problems = [problem(seed) for seed in (6, 7, 8)]
    centres = jnp.asarray(np.stack([p[0] for p in problems]), jnp.float32)
    weights = jnp.asarray(np.stack([p[1] for p in problems]), jnp.float32)
    y0 = jnp.full((3, N), 0.5, jnp.float32)
    batched = jax.jit(jax.vmap(lambda y, c, w: simplex.minimise(quadratic, y, (c, w), 300).value))(y0, centres, weights)
    for i in range(3):
        single = simplex.minimise(quadratic, y0[i], (centres[i], weights[i]), 300).value
        np.testing.assert_allclose(batched[i], single, atol=1e-6)


def test_best_so_far_never_gets_worse():
    centre, weights = (jnp.asarray(a, jnp.float32) for a in problem(9))
    values = [
        float(simplex.minimise(quadratic, jnp.full(N, 0.5), (centre, weights), budget).stats["value"])
        for budget in (21, 40, 80, 160)
    ]
    assert all(b <= a for a, b in itertools.pairwise(values))
    assert values[-1] < 0.5 * values[0]


def test_initial_simplex_stays_in_the_box():
    y0 = jnp.array([0.0, 0.95, 1.0, 0.5, -0.2])
    vertices = simplex.initial_simplex(y0, 0.1, 0.0, 1.0)
    assert vertices.shape == (6, 5)
    assert float(vertices.min()) >= 0.0 and float(vertices.max()) <= 1.0
    np.testing.assert_allclose(vertices[2], [0.0, 0.85, 1.0, 0.5, 0.0])


def test_too_small_a_budget_is_refused():
    with pytest.raises(ValueError, match="use at least 21"):
        simplex.steps_for_budget(20, N)
