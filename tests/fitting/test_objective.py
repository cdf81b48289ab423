"""The fit's objective (`pbrfit.fitting.objective`): what a pixel shades with at texel values x."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit.physics.material import Material
from pbrfit.physics.textures import sample_bilinear
from pbrfit.fitting.objective import (texel_grid, linearize, pixel_residuals, sample_material, sample_texels,
                                      scatter_texels)
from pbrfit.fitting.observations import CELL_CORNERS, texel_layout
from pbrfit.fitting.parameters import LOWER, UPPER

from test_fit import _stack, _texel_problem
from test_sharding import _problem


@pytest.mark.parametrize("shape, wrap, texels", [((5, 3), "repeat", None), ((4, 6), "clamp", 30),
                                                 ((1, 4), "clamp", None), ((2, 1), "repeat", None)])
def test_rows_read_and_write_texels_by_cells(shape, wrap, texels):
    """A layout's taps are the corners of their cells, in order (clamped edges: weights summed on
    the corner read), its samples the textures' bilinear ones, and with a grid, `sample_texels`
    and `scatter_texels` by cells are the per-tap gather and scatter-add (texels past the map,
    a coarser level's padding, get nothing)."""
    problem, _ = _problem(pixels=200, render=False)
    obs = dataclasses.replace(problem.obs, uv=problem.obs.uv * 1.4 - 0.2)  # past the edges too
    layout = texel_layout(obs, shape, wrap)
    h, w = shape
    index, first = np.asarray(layout.index), np.asarray(layout.index)[:, 0]
    corners = np.stack([((first // w + di) % h) * w + (first % w + dj) % w for di, dj in CELL_CORNERS], 1)
    np.testing.assert_array_equal(index, corners)
    t = texels or h * w
    plain = dataclasses.replace(problem, obs=obs, index=layout.index, weight=layout.weight, free=jnp.ones((t, 5)))
    cells = dataclasses.replace(plain, grid=texel_grid(shape, t))
    rng = np.random.default_rng(4)
    x = jnp.asarray(rng.uniform(size=(t, 5)), jnp.float32)
    values = jnp.asarray(rng.normal(size=(obs.num_rows, 4, 3)), jnp.float32)
    sample, scatter = jax.jit(sample_texels), jax.jit(scatter_texels)
    want = np.asarray(sample_bilinear(x[: h * w].reshape(h, w, 5), obs.uv, wrap))
    np.testing.assert_allclose(np.asarray(sample(x, plain)), want, atol=1e-6)
    np.testing.assert_allclose(np.asarray(sample(x, cells)), want, atol=1e-6)
    got, want = np.asarray(scatter(values, cells)), np.asarray(scatter(values, plain))
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert np.all(got[h * w:] == 0.0) and np.abs(want).max() > 1.0


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
