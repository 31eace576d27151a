import jax.numpy as jnp
import numpy as np
import pytest

from matfit.fitting import gradient


def quadratic(y, args):
    centre, scales = args
    return jnp.sum(scales * (y - centre) ** 2)


def rosenbrock(y, args):
    z = 4.0 * y - 2.0  # the unit cube maps to [-2, 2]^n; the minimum (z = 1) lies at y = 0.75
    return jnp.sum(100.0 * (z[1:] - z[:-1] ** 2) ** 2 + (1.0 - z[:-1]) ** 2)


def test_finds_the_argmin_of_off_centre_quadratics_inside_and_on_the_faces():
    rng = np.random.default_rng(0)
    centre = rng.uniform(-0.4, 1.4, 19).astype(np.float32)  # about a third of the coordinates outside [0, 1]
    scales = rng.uniform(0.5, 20.0, 19).astype(np.float32)  # badly conditioned
    starts = jnp.asarray(rng.uniform(0.0, 1.0, (3, 19)), jnp.float32)
    ends, values, steps = gradient.minimise(quadratic, starts, (jnp.asarray(centre), jnp.asarray(scales)), 200)
    expected = np.clip(centre, 0.0, 1.0)  # the box's argmin: the centre projected onto the faces
    assert np.sum((centre < 0) | (centre > 1)) >= 4
    np.testing.assert_allclose(np.asarray(ends), np.broadcast_to(expected, (3, 19)), atol=1e-4)
    best = float(np.sum(scales * (expected - centre) ** 2))
    np.testing.assert_allclose(np.asarray(values), best, rtol=1e-5)
    assert steps < 3 * 50  # converged, and stopped early: a quadratic takes a few dozen L-BFGS steps, not 200


def test_spends_at_most_its_budget_and_only_improves():
    starts = jnp.asarray(np.random.default_rng(2).uniform(size=(2, 19)), jnp.float32)
    first = np.asarray([rosenbrock(s, None) for s in starts])
    values = []
    for steps in (1, 7, 30):
        _, value, spent = gradient.minimise(rosenbrock, starts, None, steps)
        assert spent == 2 * steps  # Rosenbrock is far from converged in 30 steps: the whole budget is spent
        values.append(np.asarray(value))
    np.testing.assert_allclose(values[0], first, rtol=1e-6)  # one step evaluates the starts only
    assert np.all(values[1] < first) and np.all(values[2] <= values[1])


def test_reaches_the_rosenbrock_valley_floor_from_most_starts():
    starts = jnp.asarray(np.random.default_rng(3).uniform(size=(4, 19)), jnp.float32)
    ends, values, _ = gradient.minimise(rosenbrock, starts, None, 600)
    solved = np.asarray(values) < 1e-6
    assert solved.sum() >= 2  # 19-D Rosenbrock also has a local minimum near 3.99; the others end there
    np.testing.assert_allclose(np.asarray(ends)[solved], 0.75, atol=1e-3)
    assert np.all((np.asarray(values) < 1e-6) | (np.abs(np.asarray(values) - 3.99) < 0.05))


def test_each_start_in_a_batch_ends_where_it_would_alone():
    centre = jnp.asarray(np.linspace(0.1, 0.9, 19), jnp.float32)
    args = (centre, jnp.ones(19, jnp.float32))
    starts = jnp.asarray(np.random.default_rng(1).uniform(size=(4, 19)), jnp.float32)
    batch, _, _ = gradient.minimise(quadratic, starts, args, 50)
    alone, _, _ = gradient.minimise(quadratic, starts[2:3], args, 50)
    np.testing.assert_allclose(np.asarray(batch[2]), np.asarray(alone[0]), atol=1e-6)


def test_one_compilation_for_every_set_of_data():
    starts = jnp.full((2, 19), 0.5, jnp.float32)
    gradient.minimise(quadratic, starts, (jnp.zeros(19, jnp.float32), jnp.ones(19, jnp.float32)), 5)
    before = gradient.step._cache_size()
    for k in range(3):
        data = (jnp.full(19, 0.1 * k, jnp.float32), jnp.ones(19, jnp.float32))
        gradient.minimise(quadratic, starts + 0.1 * k, data, 5)
    assert gradient.step._cache_size() == before


def test_narrowing_lets_the_best_start_go_on_alone_as_it_would_have_in_the_batch():
    starts = jnp.asarray(np.random.default_rng(4).uniform(size=(4, 19)), jnp.float32)
    early, early_values, _ = gradient.minimise(rosenbrock, starts, None, 20)
    narrowed, values, spent = gradient.minimise(rosenbrock, starts, None, 60, narrow_after=20)
    together, together_values, _ = gradient.minimise(rosenbrock, starts, None, 60)
    best = int(np.argmin(np.asarray(early_values)))
    others = np.arange(4) != best
    assert spent == 4 * 20 + 40  # far from converged: every step of the budget, the batch's and the best's
    np.testing.assert_array_equal(np.asarray(narrowed)[others], np.asarray(early)[others])  # they end at step 20
    np.testing.assert_array_equal(np.asarray(values)[others], np.asarray(early_values)[others])
    np.testing.assert_allclose(np.asarray(narrowed)[best], np.asarray(together)[best], atol=1e-5)
    assert float(values[best]) == pytest.approx(float(together_values[best]), rel=1e-4)
    assert float(values[best]) < float(early_values[best])


def test_narrowing_rejects_a_count_below_one():
    with pytest.raises(ValueError, match="narrow_after 0"):
        gradient.minimise(rosenbrock, jnp.zeros((2, 19), jnp.float32), None, 5, narrow_after=0)


def test_starts_shared_among_threads_end_where_one_batch_ends_them_for_the_same_budget():
    starts = jnp.asarray(np.random.default_rng(5).uniform(size=(5, 19)), jnp.float32)  # shares of 3 and 2
    runs = [gradient.minimise(rosenbrock, starts, None, 40, narrow_after=15, workers=w) for w in (1, 2, 3)]
    for ends, values, spent in runs:
        assert spent == 5 * 15 + 25
        np.testing.assert_allclose(ends, runs[0][0], atol=1e-4)
        np.testing.assert_allclose(values, runs[0][1], rtol=1e-4)
    with pytest.raises(ValueError, match="workers 0"):
        gradient.minimise(rosenbrock, starts, None, 5, workers=0)
