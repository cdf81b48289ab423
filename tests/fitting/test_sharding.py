"""Sharding the fit over devices (`pbrfit.fitting.sharding`).

The multi-device check needs several JAX devices, and on the CPU their number is fixed by
``XLA_FLAGS=--xla_force_host_platform_device_count`` before JAX starts, so it runs this file as
a script in a fresh interpreter (`_multi_device_report`) and checks what it prints. The padding
checks run here, on one device.

The problems are synthetic and tiny: a plane (normal +z) seen along random directions under two
lights, a 4 × 4 map read bilinearly at random uv, targets rendered from a random material.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import PartitionSpec

from pbrfit.physics.color import COLOR_SPACES, TONEMAPS, encode
from pbrfit.lighting.ibl import IBLTables
from pbrfit.physics.model import Model
from pbrfit.fitting.observations import PIXEL_FIELDS, Observations, coverage_counts, neighbour_pairs, texel_layout
from pbrfit.render.shade import shade
from pbrfit.fitting.sharding import (PAD_LIGHT, PAD_NORMAL, PAD_VIEW, PIXEL_AXIS, pad_layout, pad_observations, pad_pixel_rows,
                             padded_size, pixel_mesh, shard_problem, take_pixels)
from pbrfit.fitting.objective import Problem, linearize, objective, pixel_residuals, rounding_floor
from pbrfit.fitting.normal_matrix import gradient, normal_blocks, spd_block_inverse

DEVICES = 4
PIXELS = 1001          # not a multiple of DEVICES: the sharded problem is padded to 1004
MAP = (4, 4)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _hemisphere(rng, n, max_deg=70.0):
    """n unit directions around +z, at most `max_deg` from it."""
    theta = np.radians(max_deg) * np.sqrt(rng.random(n))
    phi = 2 * np.pi * rng.random(n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def _problem(pixels=PIXELS, tonemap="none", color_space="linear", loss="l2", model=Model(), ibl=None, smooth=1e-3,
             render=True, seed=0) -> tuple[Problem, np.ndarray]:
    """A small fitting problem and its true (T, 5) texel values; targets rendered from them
    (plus noise) when `render`, else random."""
    rng = np.random.default_rng(seed)
    views = 3
    lights = _unit(np.array([[0.6, 0.2, 1.0], [-0.5, -0.4, 0.8]]))
    obs = Observations(
        normal=jnp.asarray(np.tile([[0.0, 0.0, 1.0]], (pixels, 1)), jnp.float32),
        tangent=jnp.asarray(np.tile([[1.0, 0.0, 0.0, 1.0]], (pixels, 1)), jnp.float32),
        view=jnp.asarray(_hemisphere(rng, pixels), jnp.float32),
        light_l=jnp.asarray(np.broadcast_to(lights, (pixels, 2, 3)), jnp.float32),
        light_radiance=jnp.asarray(np.broadcast_to([[3.0, 3.0, 3.0], [2.0, 2.5, 3.0]], (pixels, 2, 3)), jnp.float32),
        uv=jnp.asarray(rng.random((pixels, 2)), jnp.float32),
        exposure=jnp.asarray(rng.choice([-0.5, 0.0, 0.5], pixels), jnp.float32),
        target=jnp.asarray(rng.random((pixels, 3)), jnp.float32),
        residual_weight=jnp.ones((pixels, 3), jnp.float32),
        view_index=jnp.asarray(np.arange(pixels) % views, jnp.int32),
        pixel=jnp.asarray(np.arange(pixels) // views, jnp.int32),
        shapes=((1, -(-pixels // views)),) * views,
        tonemap=tonemap,
        color_space=color_space,
    )
    layout = texel_layout(obs, MAP)
    t = MAP[0] * MAP[1]
    pairs = neighbour_pairs(MAP)
    free = np.ones((t, 5), np.float32)
    free[:, 3] = 0.0  # dielectric: metallic held at 0
    truth = np.concatenate([rng.uniform(0.2, 0.8, (t, 3)), np.zeros((t, 1)), rng.uniform(0.3, 0.7, (t, 1))], 1)
    truth = truth.astype(np.float32)
    problem = Problem(obs, layout.index, layout.weight, jnp.asarray(free), jnp.asarray(pairs),
                      jnp.ones(len(pairs), jnp.float32), jnp.asarray(smooth, jnp.float32),
                      jnp.asarray(0.05, jnp.float32), ibl, model, loss)
    if render:
        blank = dataclasses.replace(problem, obs=dataclasses.replace(obs, target=jnp.zeros_like(obs.target)), loss="l2")
        clean = jax.jit(pixel_residuals)(jnp.asarray(truth), blank)  # target 0: the rendered values
        noisy = clean + 0.01 * jnp.asarray(rng.standard_normal(clean.shape), jnp.float32)
        problem = dataclasses.replace(problem, obs=dataclasses.replace(obs, target=noisy))
    return problem, truth


def _start(problem: Problem) -> jnp.ndarray:
    return jnp.asarray(np.tile([[0.5, 0.5, 0.5, 0.0, 0.5]], (problem.num_texels, 1)), jnp.float32)


def _constant_ibl() -> IBLTables:
    """Split-sum tables of a grey environment, built by hand (no table building to compile)."""
    sh = np.zeros((9, 3), np.float32)
    sh[0] = 2.0
    return IBLTables(jnp.asarray(sh), jnp.full((2, 4, 8, 3), 1.5, jnp.float32), jnp.full((4, 4, 2), 0.5, jnp.float32),
                     jnp.full((4, 4, 3), 0.8, jnp.float32), jnp.full((4, 4, 1), 0.3, jnp.float32), "sh9",
                     ((4, 8), (4, 8)))


# --- one device: padding ---------------------------------------------------------------------


def test_padded_size():
    assert [padded_size(n, 4) for n in (0, 1, 4, 5, 1001)] == [0, 4, 4, 8, 1004]
    with pytest.raises(ValueError):
        padded_size(3, 0)


def test_encode_sends_zero_radiance_to_zero():
    zero = jnp.zeros((2, 3), jnp.float32)
    for tonemap in TONEMAPS:
        for space in COLOR_SPACES:
            for ev in (0.0, -3.0, 2.5):
                assert np.all(np.asarray(encode(zero, ev, tonemap, space)) == 0.0), (tonemap, space, ev)


def test_shade_and_its_tangents_vanish_at_padded_geometry():
    """n·v < 0 zeroes every lobe, punctual and environment, and the forward-mode derivative."""
    model = Model(distribution="beckmann", geometry="schlick_ggx_direct", fresnel="dielectric", diffuse="burley",
                  multiscatter=True, ibl="split_sum")
    ibl = _constant_ibl()
    n = 3
    geometry = (jnp.tile(jnp.asarray([PAD_NORMAL]), (n, 1)), jnp.tile(jnp.asarray([PAD_VIEW]), (n, 1)),
                jnp.tile(jnp.asarray([[PAD_LIGHT]]), (n, 1, 1)), jnp.ones((n, 1, 3)))  # lit, to be sure
    front = (geometry[0], -geometry[1], geometry[0][:, None, :], geometry[3])

    @jax.jit
    def check(m):
        f = lambda v, g: shade(*g, v[:, 0:3], v[:, 3:4], v[:, 4:5], model, ibl)  # noqa: E731
        return f(m, geometry), jax.jacfwd(f)(m, geometry), f(m, front)

    value, jac, lit = check(jnp.asarray([[0.7, 0.4, 0.2, 0.5, 0.3]] * n, jnp.float32))
    assert np.all(np.asarray(value) == 0.0) and np.all(np.asarray(jac) == 0.0)
    assert np.all(np.asarray(lit) > 0.0)  # seen from the front it is lit: the zeros are the n·v gate's


def test_padded_pixels_have_zero_residual_and_jacobian():
    """With a tone map, sRGB, a robust loss and an environment (linear, no tone map and l2 are
    `test_padded_layout_and_problem_change_nothing_texel_side`)."""
    tonemap, color_space, loss = "aces_hill", "srgb", "huber"
    model = Model(ibl="split_sum", multiscatter=True)
    problem, truth = _problem(pixels=37, tonemap=tonemap, color_space=color_space, loss=loss, model=model,
                              ibl=_constant_ibl(), render=False)
    obs, real = pad_observations(problem.obs, 8)
    assert (real, obs.num_pixels) == (37, 40)
    assert obs.shapes == problem.obs.shapes and (obs.tonemap, obs.color_space) == (tonemap, color_space)
    np.testing.assert_array_equal(np.asarray(obs.view_index[real:]), -1)
    np.testing.assert_array_equal(np.asarray(obs.pixel[real:]), -1)
    np.testing.assert_array_equal(np.asarray(obs.target[:real]), np.asarray(problem.obs.target))
    # Give the padded pixels real texels with full weight: their rows must vanish by themselves.
    index = jnp.concatenate([problem.index, problem.index[:3]])
    weight = jnp.concatenate([problem.weight, problem.weight[:3]])
    padded = dataclasses.replace(problem, obs=obs, index=index, weight=weight)
    r, jac, _ = jax.jit(linearize)(jnp.asarray(truth), padded)
    assert np.all(np.asarray(r[real:]) == 0.0) and np.all(np.asarray(jac[real:]) == 0.0)
    assert np.all(np.isfinite(np.asarray(jac))) and np.all(np.any(np.asarray(r[:real]) != 0.0, axis=1))


def test_padded_layout_and_problem_change_nothing_texel_side():
    problem, truth = _problem(pixels=37, render=False)
    obs, real = pad_observations(problem.obs, 4)
    layout = pad_layout(texel_layout(problem.obs, MAP), 4)
    assert layout.index.shape == (40, 4) and layout.shape == MAP
    assert np.all(np.asarray(layout.weight[real:]) == 0.0) and np.all(np.asarray(layout.index[real:]) == 0)
    np.testing.assert_array_equal(coverage_counts(layout), coverage_counts(texel_layout(problem.obs, MAP)))
    index, weight = pad_pixel_rows(problem.index, problem.weight, 4)
    np.testing.assert_array_equal(np.asarray(index), np.asarray(layout.index))
    padded = dataclasses.replace(problem, obs=obs, index=index, weight=weight)

    @jax.jit
    def texel_side(x, p):
        r, jac, energy = linearize(x, p)
        return (normal_blocks(jac, p), gradient(r, jac, x, p), energy, objective(x, p)), (r, jac)

    x = jnp.asarray(truth)
    got_all, (r, jac) = texel_side(x, padded)
    assert np.all(np.asarray(r[real:]) == 0.0) and np.all(np.asarray(jac[real:]) == 0.0)
    for got, want in zip(got_all, texel_side(x, problem)[0]):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-6, atol=1e-6)


def test_shard_problem_on_one_device():
    problem, _ = _problem(pixels=37, render=False)
    sharded = shard_problem(problem, pixel_mesh(jax.devices()[:1]))
    assert pixel_mesh().axis_names == (PIXEL_AXIS,)
    assert sharded.obs.num_pixels == 37 and sharded.obs.target.sharding.spec == PartitionSpec(PIXEL_AXIS)
    assert (sharded.model, sharded.loss, sharded.obs.shapes) == (problem.model, problem.loss, problem.obs.shapes)
    np.testing.assert_array_equal(np.asarray(sharded.index), np.asarray(problem.index))


def test_take_pixels_keeps_the_objective_change_of_the_texels_its_pixels_read():
    """A problem of the pixels that read texel 5, padded with inert pixels: its rows are theirs,
    and moving texel 5 changes its objective as it changes the whole problem's (the prior too)."""
    problem, truth = _problem(pixels=37, render=False)
    index, weight = np.asarray(problem.index), np.asarray(problem.weight)
    pixels = np.flatnonzero(np.any((index == 5) & (weight > 0), axis=1))
    assert 0 < len(pixels) < 30
    sub = take_pixels(problem, pixels, 32)
    assert sub.num_pixels == 32 and sub.obs.num_pixels == 32 and sub.obs.shapes == problem.obs.shapes
    for name in PIXEL_FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(sub.obs, name))[: len(pixels)],
                                      np.asarray(getattr(problem.obs, name))[pixels])
    np.testing.assert_array_equal(np.asarray(sub.index)[: len(pixels)], index[pixels])
    assert np.all(np.asarray(sub.weight)[len(pixels):] == 0.0)
    assert np.all(np.asarray(sub.obs.residual_weight)[len(pixels):] == 0.0)
    moved = truth.copy()
    moved[5] = [0.9, 0.1, 0.3, 0.0, 0.8]
    energy = jax.jit(objective)
    change = lambda p: float(energy(jnp.asarray(moved), p)) - float(energy(jnp.asarray(truth), p))
    assert abs(change(problem)) > 1e-2
    assert change(sub) == pytest.approx(change(problem), rel=1e-5)
    with pytest.raises(ValueError, match="cannot hold"):
        take_pixels(problem, pixels, len(pixels) - 1)


def test_take_pixels_with_residuals_keeps_the_pixels_it_leaves_out_as_a_term():
    """With the problem's residuals where it stands, the pixels left out stay a term
    (`LeftOut`): the objective, E of the linearisation, the pixel count and the rounding floor
    are the whole problem's, at that point and wherever the texels the kept pixels read move."""
    problem, truth = _problem(pixels=37, render=False)
    index, weight = np.asarray(problem.index), np.asarray(problem.weight)
    pixels = np.flatnonzero(np.any((index == 5) & (weight > 0), axis=1))
    start = np.asarray(truth, np.float32)  # the targets are random: every pixel misfits
    r = jax.jit(pixel_residuals)(jnp.asarray(start), problem)
    sub = take_pixels(problem, pixels, 32, residuals=r)
    assert take_pixels(problem, pixels, 32).left_out is None
    assert sub.num_pixels + float(sub.left_out.pixels) == problem.num_pixels
    energy = jax.jit(objective)
    moved = start.copy()
    moved[5] = [0.9, 0.1, 0.3, 0.0, 0.8]
    for x in (start, moved):
        whole = pytest.approx(float(energy(jnp.asarray(x), problem)), rel=1e-5)
        assert float(energy(jnp.asarray(x), sub)) == whole
        assert float(jax.jit(linearize)(jnp.asarray(x), sub)[2]) == whole
    assert float(sub.left_out.energy) > 0.1 * float(energy(jnp.asarray(start), problem))
    assert float(rounding_floor(sub)) == pytest.approx(float(rounding_floor(problem)), rel=1e-5)


def test_spd_block_inverse_matches_lapack_in_float64():
    """The preconditioner's block inverses (plain XLA, no LAPACK: see the four-device test) on
    SPD blocks whose channels differ in scale by 1e6, as colour and roughness do, and the identity
    blocks of inactive channels: within float32 rounding of float64's inverse."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(64, 5, 8)) * np.array([1e3, 1e3, 1e3, 1.0, 1e-3])[None, :, None]
    m = np.einsum("tik,tjk->tij", a, a) + 1e-6 * np.eye(5)
    m[0] = np.eye(5)
    got = np.asarray(jax.jit(spd_block_inverse)(jnp.asarray(m, jnp.float32)), np.float64)
    want = np.linalg.inv(m)
    scale = np.sqrt(np.einsum("tii->ti", want))  # compare on the unit-diagonal scaling
    rel = np.abs(got - want) / (scale[:, :, None] * scale[:, None, :])
    assert rel.max() < 1e-4, rel.max()
    np.testing.assert_array_equal(got[0], np.eye(5))


# --- several devices (in a subprocess) ---------------------------------------------------------


def _multi_device_report() -> dict:
    """Solve the same problem unsharded and sharded over all devices; what the test checks."""
    from pbrfit.fitting.api import fit_observations
    from pbrfit.fitting.initialisation import coordinate_search, grid_initialise, parity_classes
    from pbrfit.fitting.solvers.structured import StructuredLM, solve

    from pbrfit.cli.fit import fit_devices

    out = dict(devices=len(jax.devices()), auto_devices=fit_devices("auto"))
    problem, _ = _problem()
    mesh = pixel_mesh()
    sharded = shard_problem(problem, mesh)
    real = problem.obs.num_pixels
    target = sharded.obs.target
    out.update(
        pixels=sharded.obs.num_pixels,
        spec=str(target.sharding.spec), want_spec=str(PartitionSpec(PIXEL_AXIS)),
        shard_rows=sorted(int(s.data.shape[0]) for s in target.addressable_shards),
        shard_devices=len({s.device for s in target.addressable_shards}),
        index_shards=len({s.device for s in sharded.index.addressable_shards}),
        light_shard_rows=sorted(int(s.data.shape[0]) for s in sharded.obs.light_radiance.addressable_shards),
        texels_replicated=bool(sharded.free.sharding.is_fully_replicated and sharded.pairs.sharding.is_fully_replicated
                               and sharded.smooth.sharding.is_fully_replicated),
    )

    x0 = grid_initialise(_start(problem), problem)
    x0_sh = grid_initialise(_start(problem), sharded)
    out["init_diff"] = float(jnp.max(jnp.abs(x0 - x0_sh)))

    # As `pbrfit.fitting.runner.Runner` does: ahead-of-time compile, then run.
    solver = StructuredLM(rtol=1e-7, atol=1e-6)
    args = (x0, problem, solver, jnp.asarray(30, jnp.int32))
    x, stats, r, jac = solve.lower(*args).compile()(*args)
    args_sh = (x0, sharded, solver, jnp.asarray(30, jnp.int32))
    x_sh, stats_sh, r_sh, jac_sh = solve.lower(*args_sh).compile()(*args_sh)
    energy = jax.jit(objective)
    out.update(
        x_diff=float(jnp.max(jnp.abs(x - x_sh))),
        steps=[int(stats.steps), int(stats_sh.steps)],
        loss=[float(stats.loss), float(stats_sh.loss)],
        objective=[float(energy(x, problem)), float(energy(x_sh, problem))],
        residual_spec=str(r_sh.sharding.spec), residual_rows=int(r_sh.shape[0]),
        residual_diff=float(jnp.max(jnp.abs(r[:real] - r_sh[:real]))),
        padded_residual=float(jnp.max(jnp.abs(r_sh[real:]))), padded_jacobian=float(jnp.max(jnp.abs(jac_sh[real:]))),
    )
    # residual weights (`pbrfit.fitting.noise`) go with their pixels; padded pixels' are 0
    w = jnp.asarray(np.random.default_rng(7).uniform(0.2, 5.0, (real, 3)), jnp.float32)
    weighted = dataclasses.replace(problem, obs=dataclasses.replace(problem.obs, residual_weight=w))
    lin = jax.jit(linearize)
    r_w, jac_w, _ = lin(x, weighted)
    r_w_sh, jac_w_sh, _ = lin(x, shard_problem(weighted, mesh))
    out.update(
        weighted_residual_diff=float(jnp.max(jnp.abs(r_w - r_w_sh[:real]))),
        weighted_jacobian_diff=float(jnp.max(jnp.abs(jac_w - jac_w_sh[:real]))),
        weighted_scale_diff=float(jnp.max(jnp.abs(r_w - w * r))),
        weighted_padded=float(jnp.max(jnp.abs(r_w_sh[real:]))),
    )
    blocks = jax.jit(normal_blocks)(jac, problem)
    blocks_sh = jax.jit(normal_blocks)(jac_sh, sharded)
    out["blocks_rel_diff"] = float(jnp.max(jnp.abs(blocks - blocks_sh)) / jnp.max(jnp.abs(blocks)))

    classes = jnp.asarray(parity_classes(MAP))
    out["search_diff"] = float(jnp.max(jnp.abs(coordinate_search(x0, problem, classes)
                                               - coordinate_search(x0, sharded, classes))))
    # The whole fit, as `pbrfit fit --devices 4` runs it.
    one = fit_observations(problem.obs, resolution=MAP, max_steps=20)
    many = fit_observations(problem.obs, resolution=MAP, max_steps=20, devices=jax.devices())
    out.update(
        fit_devices=len(many.report["devices"]),
        fit_map_diff=max(float(np.max(np.abs(np.asarray(getattr(one.material, n)) - np.asarray(getattr(many.material, n)))))
                         for n in ("base_color", "metallic", "roughness")),
        fit_sigma_diff=float(np.max(np.abs(one.uncertainty - many.uncertainty))),
        fit_render_diff=max(float(np.max(np.abs(a - b))) for a, b in zip(one.images, many.images)),
    )
    # Four samples per pixel (whole pixels per device: rows padded to 4 x 4 x 251), each row with
    # its per-pixel IBL integrals: both travel with their pixels, and the fit is the same.
    from pbrfit.lighting.environment import procedural_sky
    from pbrfit.lighting.pixel_ibl import PixelIBLSettings, pixel_ibl

    base = problem.obs
    jitter = np.tile([[-0.01, -0.01], [0.01, -0.01], [-0.01, 0.01], [0.01, 0.01]], (base.num_pixels, 1))
    rows = {name: np.repeat(np.asarray(getattr(base, name)), 4, axis=0) for name in PIXEL_FIELDS}
    rows["uv"] = rows["uv"] + jitter.astype(np.float32)
    sampled = dataclasses.replace(base, samples=4, **{k: jnp.asarray(v) for k, v in rows.items()})
    layout = texel_layout(sampled, MAP)
    sp = dataclasses.replace(problem, obs=sampled, index=layout.index, weight=layout.weight)
    sp_sh = shard_problem(sp, mesh)
    model = Model(ibl="per_pixel")
    table = pixel_ibl(procedural_sky(16), np.asarray(sampled.normal), np.asarray(sampled.view), model,
                      PixelIBLSettings(levels=3, samples=8))
    table_sh = shard_problem(dataclasses.replace(sp, ibl=table, model=model), mesh).ibl.table
    lean = dict(resolution=MAP, search=False, continuation=None, uniform_check=False, repair=False)  # the solve alone
    one = fit_observations(sampled, model=model, ibl=table, max_steps=20, **lean)
    many = fit_observations(sampled, model=model, ibl=table, max_steps=20, devices=jax.devices(), **lean)
    blocks_of = jax.jit(lambda x, p: normal_blocks(linearize(x, p)[1], p))
    out.update(
        samples_shard_rows=sorted(int(s.data.shape[0]) for s in sp_sh.obs.target.addressable_shards),
        samples_blocks_rel_diff=float(jnp.max(jnp.abs(blocks_of(x, sp) - blocks_of(x, sp_sh)))
                                      / jnp.max(jnp.abs(blocks_of(x, sp)))),
        table_shard_rows=sorted(int(s.data.shape[0]) for s in table_sh.addressable_shards),
        table_padding=float(jnp.max(jnp.abs(table_sh[4 * real:]))),
        samples_map_diff=max(float(np.max(np.abs(np.asarray(getattr(one.material, n))
                                                 - np.asarray(getattr(many.material, n)))))
                             for n in ("base_color", "metallic", "roughness")),
        samples_loss=[one.report["final_loss"], many.report["final_loss"]],
        samples_render_diff=max(float(np.max(np.abs(a - b))) for a, b in zip(one.images, many.images)),
    )
    # some of those pixels alone (a repair's search): whole pixels per device, integrals with them
    with_table = dataclasses.replace(sp, ibl=table, model=model)
    reads = np.any((np.asarray(sp.index) == 5) & (np.asarray(sp.weight) > 0), axis=1)
    pixels = np.flatnonzero(reads.reshape(-1, 4).any(axis=1))
    sub = take_pixels(shard_problem(with_table, mesh), pixels, padded_size(len(pixels) + 1, DEVICES))
    moved = x.at[5].set(jnp.asarray([0.9, 0.1, 0.3, 0.0, 0.8], jnp.float32))
    change = lambda p: float(energy(moved, p)) - float(energy(x, p))
    out.update(
        taken_pixels=len(pixels), taken_shard_rows=sorted(int(s.data.shape[0]) for s in sub.obs.target.addressable_shards),
        taken_table_rows=sorted(int(s.data.shape[0]) for s in sub.ibl.table.addressable_shards),
        taken_change=[change(with_table), change(sub)],
    )
    # a re-fit of two texels over their pixels (`Runner.refit`, made to take them): the same on the mesh
    from pbrfit.fitting import runner as fit_runner

    fit_runner.REFIT_COMPILE_ROW_STEPS = 0
    moving = np.zeros(problem.num_texels, bool)
    moving[[5, 6]] = True

    def refit(p):
        region = dataclasses.replace(p, free=jax.device_put(np.asarray(p.free) * moving[:, None], p.free.sharding))
        compiler = fit_runner.Compiler(dict(compile=0.0, solve=0.0), background=False)
        run = fit_runner.Runner(StructuredLM(), None, compiler)
        start = jax.jit(linearize)(moved, p)[:2]
        y, info = run.refit(moved, region, moving, 5, int(np.sum(np.asarray(region.free))), start)
        return np.asarray(y), info["steps"], np.asarray(run.linearization[0])[:real]

    one_refit, many_refit = refit(problem), refit(sharded)
    out.update(refit_steps=[one_refit[1], many_refit[1]],
               refit_diff=float(np.max(np.abs(one_refit[0] - many_refit[0]))),
               refit_moved=float(np.max(np.abs(one_refit[0] - np.asarray(moved)))),
               refit_residual_diff=float(np.max(np.abs(one_refit[2] - many_refit[2]))))
    # The whole `pbrfit fit --devices 4` on the peer layout (32² images of 16² maps here). With 64² it
    # hung at the solver's first step: the block-Jacobi inverses went through LAPACK
    # (``jnp.linalg.inv``), whose batched kernel waits on the CPU thread pool that the other
    # devices' kernels held (`pbrfit.fitting.normal_matrix.spd_block_inverse` replaced it).
    import tempfile
    from pathlib import Path

    from pbrfit.cli.main import main

    with tempfile.TemporaryDirectory() as tmp:
        cap, fitted = Path(tmp) / "cap", Path(tmp) / "out"
        assert main(["synth", "peer-plane", "--out", str(cap), "--size", "32", "--texture-size", "16",
                     "--quiet"]) == 0
        assert main(["fit", str(cap), "--out", str(fitted), "--resolution", "16", "--devices", str(DEVICES), "--quiet",
                     "--no-search", "--no-repair", "--no-uniform-check"]) == 0
        report = json.loads((fitted / "report.json").read_text())
    out.update(command_devices=len(report["devices"]), command_truth_rmse=report["truth_rmse"])
    return out


def test_structured_lm_sharded_over_four_cpu_devices():
    """One interpreter with four host devices: the solver, the stages' kernels and the whole fit
    sharded and not, samples and per-pixel IBL rows with their pixels (in a problem of some of
    them too, `take_pixels`, and a re-fit over some, `Runner.refit`), and the whole
    `pbrfit fit --devices 4` command (it once hung), under one time limit."""
    proc = subprocess.run([sys.executable, __file__], env=_four_device_env(), capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0, proc.stderr[-4000:]
    rep = json.loads(proc.stdout.strip().splitlines()[-1])
    assert rep["devices"] == DEVICES
    assert rep["auto_devices"] is None  # --devices auto: one device on the CPU, however many host devices
    assert rep["pixels"] == padded_size(PIXELS, DEVICES) == 1004
    assert rep["spec"] == rep["want_spec"]
    assert rep["shard_rows"] == [251] * DEVICES and rep["light_shard_rows"] == [251] * DEVICES
    assert rep["shard_devices"] == DEVICES and rep["index_shards"] == DEVICES
    assert rep["texels_replicated"]
    assert rep["init_diff"] <= 1e-5, rep
    assert rep["steps"][0] > 2 and rep["steps"][1] > 2, rep
    # 30 LM steps whose sums run in another order on four devices: float32 rounding, grown by the
    # steps (1.1e-5 from today's grid start, under 1e-5 from the per-texel one)
    assert rep["x_diff"] <= 3e-5, rep
    np.testing.assert_allclose(rep["loss"][1], rep["loss"][0], rtol=1e-5)
    np.testing.assert_allclose(rep["objective"], rep["loss"][0], rtol=1e-5)
    assert rep["residual_spec"] == rep["want_spec"] and rep["residual_rows"] == 1004, rep
    assert rep["residual_diff"] <= 1e-5 and rep["padded_residual"] == 0.0 and rep["padded_jacobian"] == 0.0, rep
    assert rep["weighted_residual_diff"] <= 1e-5 and rep["weighted_jacobian_diff"] <= 1e-4, rep
    assert rep["weighted_scale_diff"] <= 1e-5 and rep["weighted_padded"] == 0.0, rep
    assert rep["blocks_rel_diff"] <= 3e-5, rep  # each at its own run's final x (x_diff apart)
    assert rep["search_diff"] <= 1e-5, rep
    assert rep["fit_devices"] == DEVICES, rep
    assert rep["samples_shard_rows"] == [4 * 251] * DEVICES, rep
    assert rep["samples_blocks_rel_diff"] <= 1e-5, rep
    assert rep["table_shard_rows"] == [4 * 251] * DEVICES and rep["table_padding"] == 0.0, rep
    # twenty steps from the start: the sums' order moves the maps by float32 rounding grown over
    # the steps (2.4e-4 on one host, under 1e-4 on another, with the same code)
    assert rep["samples_map_diff"] <= 1e-3 and rep["samples_render_diff"] <= 1e-3, rep
    np.testing.assert_allclose(rep["samples_loss"][1], rep["samples_loss"][0], rtol=1e-4)
    assert rep["fit_map_diff"] <= 1e-4 and rep["fit_render_diff"] <= 1e-4 and rep["fit_sigma_diff"] <= 1e-4, rep
    rows = 4 * padded_size(rep["taken_pixels"] + 1, DEVICES) // DEVICES
    assert rep["taken_shard_rows"] == [rows] * DEVICES and rep["taken_table_rows"] == [rows] * DEVICES, rep
    assert abs(rep["taken_change"][0]) > 1e-3, rep
    np.testing.assert_allclose(rep["taken_change"][1], rep["taken_change"][0], rtol=1e-4)
    assert rep["refit_steps"][0] > 1 and rep["refit_steps"][0] == rep["refit_steps"][1], rep
    assert rep["refit_moved"] > 1e-3, rep
    assert rep["refit_diff"] <= 1e-5 and rep["refit_residual_diff"] <= 1e-5, rep
    assert rep["command_devices"] == DEVICES, rep
    assert max(rep["command_truth_rmse"].values()) < 1e-4, rep


def _four_device_env() -> dict:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    flags = [f for f in env.get("XLA_FLAGS", "").split() if not f.startswith("--xla_force_host_platform_device_count")]
    env["XLA_FLAGS"] = " ".join(flags + [f"--xla_force_host_platform_device_count={DEVICES}"])
    return env


if __name__ == "__main__":
    print(json.dumps(_multi_device_report()))
