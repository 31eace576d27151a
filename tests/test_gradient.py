import jax
import jax.numpy as jnp
import numpy as np

from matfit import gradient


def quadratic(y, args):
    centre, scales = args
    return jnp.sum(scales * (y - centre) ** 2)


def test_finds_the_argmin_of_off_centre_quadratics_inside_and_on_the_faces():
    rng = np.random.default_rng(0)
    centre = rng.uniform(-0.4, 1.4, 19).astype(np.float32)  # about a third of the coordinates outside [0, 1]
    scales = rng.uniform(0.5, 20.0, 19).astype(np.float32)  # badly conditioned
    starts = jnp.asarray(rng.uniform(0.0, 1.0, (3, 19)), jnp.float32)
    ends, values, counts = gradient.minimise(
        quadratic, starts, (jnp.asarray(centre), jnp.asarray(scales)), iterations=200
    )
    expected = np.clip(centre, 0.0, 1.0)  # the box's argmin: the centre projected onto the faces
    assert np.sum((centre < 0) | (centre > 1)) >= 4
    np.testing.assert_allclose(np.asarray(ends), np.broadcast_to(expected, (3, 19)), atol=2e-3)
    best = float(np.sum(scales * (expected - centre) ** 2))
    np.testing.assert_allclose(np.asarray(values), best, rtol=1e-3)
    assert np.all(np.asarray(counts) > 1) and np.all(np.asarray(counts) < 200)


def test_each_start_in_a_batch_ends_where_it_would_alone():
    centre = jnp.asarray(np.linspace(0.1, 0.9, 19), jnp.float32)
    args = (centre, jnp.ones(19, jnp.float32))
    starts = jnp.asarray(np.random.default_rng(1).uniform(size=(4, 19)), jnp.float32)
    batch, _, _ = gradient.minimise(quadratic, starts, args, iterations=50)
    alone, _, _ = gradient.minimise(quadratic, starts[2:3], args, iterations=50)
    np.testing.assert_allclose(np.asarray(batch[2]), np.asarray(alone[0]), atol=1e-5)


def test_one_compilation_for_every_set_of_data():
    minimise = jax.jit(gradient.minimise, static_argnums=(0, 3))
    starts = jnp.full((2, 19), 0.5, jnp.float32)
    minimise(quadratic, starts, (jnp.zeros(19, jnp.float32), jnp.ones(19, jnp.float32)), 20)
    before = minimise._cache_size()
    for k in range(3):
        minimise(quadratic, starts, (jnp.full(19, 0.1 * k, jnp.float32), jnp.ones(19, jnp.float32)), 20)
    assert minimise._cache_size() == before
