"""The Gauss-Newton matrix by stencil (`pbrfit.fitting.stencil`) against the product through the
pixels (`pbrfit.fitting.normal_matrix.gn_product`), and the structured solver with either.

The problems are `test_sharding`'s (a plane under two lights, random uv), on small maps of both
wrap modes, some narrower than the stencil, with the smoothness prior on, at pixel centres and
with 2 × 2 samples a pixel whose uv spread over 0.6 of a texel."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import Mesh

from pbrfit.fitting.initialisation import grid_initialise
from pbrfit.fitting.normal_matrix import gauss_newton_factors, gn_product
from pbrfit.fitting.objective import linearize, texel_grid
from pbrfit.fitting.observations import PIXEL_FIELDS, neighbour_pairs, texel_layout
from pbrfit.fitting.sharding import shard_problem, take_pixels
from pbrfit.fitting.solvers.structured import LMCarry, StructuredLM, solve
from pbrfit.fitting.stages.selection import profile_hessian, uniform_direction
from pbrfit.fitting.stencil import cell_side, cells_fit, stencil_blocks, stencil_product, with_stencil
from test_sharding import _problem, _start


def _sampled(obs, spread: float):
    """`obs` with 2 × 2 samples a pixel, their uv `spread` apart around the pixel's."""
    jitter = 0.5 * spread * np.tile([[-1, -1], [1, -1], [-1, 1], [1, 1]], (obs.num_pixels, 1))
    rows = {name: np.repeat(np.asarray(getattr(obs, name)), 4, axis=0) for name in PIXEL_FIELDS}
    rows["uv"] = rows["uv"] + jitter.astype(np.float32)
    return dataclasses.replace(obs, samples=4, **{k: jnp.asarray(v) for k, v in rows.items()})


def _on_map(problem, shape, wrap, samples=1, texels=None):
    """`problem` on a map of `shape` (`wrap`), its texels padded to `texels` (a coarser level of a
    fit), with `samples` per pixel and the prior on the map's neighbour pairs."""
    h, w = shape
    obs = problem.obs if samples == 1 else _sampled(problem.obs, 0.6 / max(h, w))
    layout = texel_layout(obs, shape, wrap)
    t = texels or h * w
    pairs = neighbour_pairs(shape)
    return with_stencil(dataclasses.replace(
        problem, obs=obs, index=layout.index, weight=layout.weight, free=jnp.ones((t, 5), jnp.float32),
        pairs=jnp.asarray(pairs), pair_weight=jnp.asarray(np.random.default_rng(1).uniform(0.5, 1.5, len(pairs)),
                                                          jnp.float32),
        smooth=jnp.asarray(0.3, jnp.float32), grid=texel_grid(shape, t))), layout


@jax.jit
def _products(x, v, problem):
    """By stencil and through the pixels, and the stencil's blocks and neighbours."""
    _, jac, _ = linearize(x, problem)
    st = problem.stencil
    blocks = stencil_blocks(jac, problem, st)
    product = gn_product(gauss_newton_factors(jac, problem), v, problem)
    return stencil_product(blocks, st.neighbours, v), product, blocks, st.neighbours


@pytest.mark.parametrize("samples, shape, wrap, texels", [
    (1, (4, 4), "repeat", None), (1, (5, 3), "clamp", None), (1, (2, 1), "repeat", 4), (4, (5, 6), "repeat", None),
    (4, (4, 3), "clamp", None), (4, (2, 3), "repeat", 16)])
def test_the_stencil_product_is_the_product_through_the_pixels(samples, shape, wrap, texels):
    """(JᵀJ + smooth L) v by stencil against the matrix-free product, for a random v and x."""
    problem, _ = _problem(pixels=300, tonemap="aces_hill", color_space="srgb", loss="huber", render=False)
    problem, layout = _on_map(problem, shape, wrap, samples, texels)
    assert cells_fit(layout.index, samples, shape)
    rng = np.random.default_rng(2)
    t = problem.num_texels
    x = jnp.asarray(rng.uniform(0.1, 0.9, (t, 5)), jnp.float32)
    v = jnp.asarray(rng.normal(size=(t, 5)), jnp.float32)
    got, want, blocks, neighbours = (np.asarray(a) for a in _products(x, v, problem))
    got, want = got.astype(np.float64), want.astype(np.float64)
    scale = np.abs(want).max()
    assert scale > 0
    np.testing.assert_allclose(got, want, atol=2e-6 * scale)
    # every offset's blocks count where the map is wide enough to reach them (taps at pixel
    # centres are up to one texel apart, with samples two)
    reach = cell_side(samples) - 1
    needed = [max(abs(di), abs(dj)) <= reach and abs(di) < shape[0] and abs(dj) < shape[1]
              for di in range(-reach, reach + 1) for dj in range(-reach, reach + 1)]
    if min(shape) > 2 * reach:
        assert all(needed)
    part = np.einsum("tnij,tnj->tni", blocks, np.asarray(v)[neighbours])  # each offset's share of the product
    for k in np.flatnonzero(needed):
        assert np.abs(part[:, k]).max() > 5e-6 * scale, k  # (rounding: 1e-6)


def test_cells_fit_only_footprints_narrower_than_a_cell():
    """... and only such a problem gets a stencil (`with_stencil`); one without a grid gets none."""
    problem, _ = _problem(pixels=300, render=False)
    assert cell_side(1) == 2 and cell_side(4) == 3
    assert with_stencil(problem).stencil is None
    for spread, fits in ((0.2, True), (2.5, False)):  # in texels of an 8 x 8 map
        obs = _sampled(problem.obs, spread / 8)
        layout = texel_layout(obs, (8, 8))
        assert cells_fit(layout.index, 4, (8, 8)) == fits
        on_map = dataclasses.replace(problem, obs=obs, index=layout.index, weight=layout.weight,
                                     free=jnp.ones((64, 5), jnp.float32), grid=texel_grid((8, 8), 64))
        assert (with_stencil(on_map).stencil is not None) == fits


@pytest.mark.parametrize("samples", [1, 4])
def test_the_stencil_follows_the_pixels_a_problem_keeps(samples):
    """A problem over some of its pixels, padded with inert ones (`take_pixels`), and one split
    over the devices (`shard_problem`, padded to their count) get stencils of their own pixels:
    their products by stencil are still those through their pixels (a stencil kept from the whole
    problem would sum the wrong pixels into each cell)."""
    problem, _ = _problem(pixels=300, tonemap="aces_hill", color_space="srgb", render=False)
    problem, _ = _on_map(problem, (5, 6), "repeat", samples)
    pixels = np.arange(1, problem.num_pixels, 3)
    mesh = Mesh(np.asarray(jax.devices()), ("pixels",))
    rng = np.random.default_rng(5)
    t = problem.num_texels
    x = jnp.asarray(rng.uniform(0.1, 0.9, (t, 5)), jnp.float32)
    v = jnp.asarray(rng.normal(size=(t, 5)), jnp.float32)
    for part in (take_pixels(problem, pixels, len(pixels) + 7), shard_problem(take_pixels(problem, pixels, len(pixels)), mesh)):
        assert part.stencil is not None and part.stencil.cell.shape[0] == part.num_pixels
        got, want, _, _ = (np.asarray(a, np.float64) for a in _products(x, v, part))
        np.testing.assert_allclose(got, want, atol=2e-6 * np.abs(want).max())


def test_the_solver_by_stencil_takes_the_steps_through_the_pixels():
    """StructuredLM on one problem (the prior on) with and without its grid, in float64: the same
    steps, accepted steps and CG iterations, and E after each step to 1e-8 (the observations are
    float32). (In float32 the solutions agree to its rounding, but at E's float32 floor whether a
    step lowers E is rounding too: with rtol 1e-7, 10 steps against 5.)"""
    problem, _ = _problem(smooth=1e-3)
    on_grid = with_stencil(dataclasses.replace(problem, grid=texel_grid((4, 4), problem.num_texels)))
    x0 = grid_initialise(_start(problem), problem)
    with jax.enable_x64(True):
        x64 = x0.astype(jnp.float64)
        solver = StructuredLM(rtol=1e-12, atol=1e-12, noise_rtol=0.0)
        runs = [solve(x64, p, solver, 8, LMCarry.start(jnp.float64)) for p in (problem, on_grid)]
    counts = [(int(s.steps), int(s.accepted), int(s.cg_iterations)) for _, s, *_ in runs]
    assert counts[0] == counts[1] and counts[0][0] >= 5, counts
    history = [np.asarray(s.history)[: counts[0][0] + 1] for _, s, *_ in runs]
    np.testing.assert_allclose(history[1], history[0], rtol=1e-8)
    np.testing.assert_allclose(np.asarray(runs[1][0]), np.asarray(runs[0][0]), atol=1e-7)


def test_the_uniform_checks_profile_curvature_is_the_same_by_stencil():
    """`profile_hessian` by stencil and through the pixels (the prior on, in both products): the
    same curvature and slope along a common metallic and roughness."""
    problem, _ = _problem(pixels=300, render=False)
    problem, _ = _on_map(problem, (5, 6), "repeat")
    rng = np.random.default_rng(3)
    t = problem.num_texels
    x = jnp.asarray(rng.uniform(0.1, 0.9, (t, 5)), jnp.float32)
    r, jac, _ = jax.jit(linearize)(x, problem)
    free = np.ones((t, 5), np.float32)
    free[:, 3:] = 0.0  # the common values' channels are held; base colour re-fitted
    held = dataclasses.replace(problem, free=jnp.asarray(free))
    directions = jnp.asarray(np.stack([uniform_direction(np.ones(t, bool), c, 5) for c in (3, 4)]))
    got = [np.asarray(a, np.float64) for a in profile_hessian(r, jac, x, held, directions)]
    want = [np.asarray(a, np.float64) for a in profile_hessian(r, jac, x, dataclasses.replace(held, stencil=None),
                                                               directions)]
    assert np.all(np.linalg.eigvalsh(want[0]) > 0)
    for a, b in zip(got, want):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6 * np.abs(b).max())
