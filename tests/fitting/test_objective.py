"""The fit's objective (`pbrfit.fitting.objective`): what a pixel shades with at texel values x."""

import jax
import jax.numpy as jnp
import numpy as np

from pbrfit.physics.material import Material
from pbrfit.fitting.objective import linearize, pixel_residuals, sample_material, sample_texels
from pbrfit.fitting.parameters import LOWER, UPPER

from test_fit import _stack, _texel_problem


def test_texels_on_the_boxs_bounds_keep_their_derivative_on_every_pixel():
    """Texels the fit holds on a bound (roughness on its floor, metallic 1 over a black channel):
    their float32 bilinear mix leaves the box by a rounding on some pixels (0.044999998 under a
    floor of 0.045), where the BRDF's floor is flat. The shaded values are projected onto the box
    with derivative 1, so every pixel keeps the derivative it has from just inside."""
    rng = np.random.default_rng(0)
    base = rng.uniform(0.2, 0.8, (8, 8, 3)).astype(np.float32)
    base[..., 2] = 0.0
    truth = Material(jnp.asarray(base), jnp.ones((8, 8, 1)), jnp.full((8, 8, 1), LOWER[4], jnp.float32))
    problem = _texel_problem(truth)
    x = _stack(truth)
    mixed = np.asarray(sample_texels(x, problem))
    assert np.any(mixed[:, 4] < LOWER[4]) or np.any(mixed[:, 3] > UPPER[3])  # the rounding the test is about
    m = np.asarray(sample_material(x, problem))
    assert np.all(m >= LOWER) and np.all(m <= UPPER)
    np.testing.assert_allclose(m, mixed, atol=1e-6)
    # the Jacobian at the bound against the one a few ulps inside (roughness up, metallic down)
    inside = x.at[:, 4].set(x[:, 4] * (1 + 1e-6)).at[:, 3].set(1 - 1e-6)
    # jitted, as the fit runs them (and one compile each, not one per operation)
    lin = jax.jit(linearize)
    _, jac, _ = lin(x, problem)
    _, jac_in, _ = lin(inside, problem)
    for c in (3, 4):
        np.testing.assert_allclose(np.asarray(jac[:, :, c]), np.asarray(jac_in[:, :, c]), rtol=2e-3, atol=1e-6)
    # and through autodiff of the residuals (the optimistix solvers' path): derivative 1 past the projection
    along = jax.jit(lambda v, p: jax.jvp(lambda u: pixel_residuals(u, p), (v,), (jnp.zeros_like(v).at[:, 4].set(1.0),))[1])
    d, d_in = along(x, problem), along(inside, problem)
    np.testing.assert_allclose(np.asarray(d), np.asarray(d_in), rtol=2e-3, atol=1e-6)
