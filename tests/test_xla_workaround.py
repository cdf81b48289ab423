"""The jaxlib CPU fusion workaround set by `import pbrfit` keeps jit equal to eager."""

import jax
import jax.numpy as jnp
import numpy as np

import pbrfit  # noqa: F401


def test_fused_reduce_broadcast_matches_eager_past_2_15_elements():
    v = jnp.tile(jnp.array([[0.8, 0.1, 0.5]]), (64, 1))

    def f(u):
        h = jnp.stack([2 * u[..., 0], u[..., 1], u[..., 0]], -1)
        return jnp.sum(v * h, -1, keepdims=True) * h

    u = jax.random.uniform(jax.random.PRNGKey(1), (171, 64, 2))
    with jax.disable_jit():
        ref = np.asarray(f(u))
    np.testing.assert_allclose(np.asarray(jax.jit(f)(u)), ref, rtol=1e-5, atol=1e-5)
