"""Environment visibility in the integrators: direction cells, the occluded per-pixel integrals
against the occluded Monte Carlo reference, and the split sum's occlusion factors."""

import jax.numpy as jnp
import numpy as np

from data_synth import environments, meshes
from pbrfit.lighting.environment import Environment, to_environment_frame
from pbrfit.lighting.ibl import IBLSettings, build_ibl, shade_ibl
from pbrfit.lighting.montecarlo import monte_carlo_radiance
from pbrfit.lighting.pixel_ibl import PixelIBLSettings, pixel_ibl, pixel_ibl_parts, shade_pixel_ibl
from pbrfit.lighting.visibility import (Bounce, OcclusionSettings, blocked_cells, direction_cells, incoming,
                                       split_sum_factors, visibility_rows)
from pbrfit.physics.model import Model
from pbrfit.scene.occlusion import cast_visibility

SKY = Environment(jnp.asarray(environments.sky(64, 32, sun_elevation_deg=40.0, sun_azimuth_deg=30.0)))


def test_cells_split_where_the_light_is():
    flat = Environment(jnp.ones((32, 64, 3), jnp.float32))
    cells = direction_cells(flat, OcclusionSettings(rows=8, power_share=1.0))
    assert cells.count == 8 * 16 and sorted(np.unique(cells.labels)) == list(range(cells.count))
    sky = direction_cells(SKY, OcclusionSettings(rows=8))
    assert sky.count > 8 * 16
    sun = np.argmax(np.asarray(SKY.radiance).sum(-1))
    assert np.sum(sky.labels == sky.labels.reshape(-1)[sun]) == 1  # the sun's texels are cells of their own
    np.testing.assert_allclose(np.linalg.norm(sky.directions, axis=1), 1.0, rtol=1e-12)


def _scene_points():
    """Points on a floor around a sphere and on the sphere, seen from one camera (n·v > 0.15)."""
    floor = meshes.plane(3.0, segments=2)
    sphere = meshes.uv_sphere(0.5, 24, 12, center=(0.0, 0.5, 0.0))
    mesh = meshes.combine([floor, sphere], [(0, 0, 0.5, 1), (0.5, 0, 1, 1)]).to_trimesh()
    rng = np.random.default_rng(1)
    angle, radius = rng.uniform(0, 2 * np.pi, 12), rng.uniform(0.3, 1.2, 12)
    floor_p = np.c_[radius * np.cos(angle), np.zeros(12), radius * np.sin(angle)]
    theta, phi = rng.uniform(0.3, 2.6, 12), rng.uniform(0, 2 * np.pi, 12)
    sphere_n = np.c_[np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)]
    points = np.r_[floor_p, 0.5 * sphere_n + [0.0, 0.5, 0.0]]
    normals = np.r_[np.tile([0.0, 1.0, 0.0], (12, 1)), sphere_n]
    v = np.array([2.0, 2.5, 2.0]) - points
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    keep = np.sum(v * normals, 1) > 0.15
    return mesh, points[keep], normals[keep], v[keep]


def _material(count, seed=2):
    rng = np.random.default_rng(seed)
    return (jnp.asarray(rng.uniform(0.2, 0.9, (count, 3)), jnp.float32),
            jnp.asarray((rng.uniform(size=(count, 1)) > 0.5).astype(np.float32)),
            jnp.asarray(rng.uniform(0.25, 0.9, (count, 1)), jnp.float32))


def test_occluded_integrals_match_the_occluded_reference():
    """Σ c_k I_k with V in the integrals equals ∫ f L V cos by Monte Carlo with the same V, within
    the noise, where the occlusion takes a fifth of the light or more at several points."""
    mesh, points, normals, v = _scene_points()
    vis, _ = cast_visibility(mesh, SKY, points, normals)
    n, v = jnp.asarray(normals, jnp.float32), jnp.asarray(v, jnp.float32)
    model = Model(ibl="per_pixel")
    base, metal, rough = _material(len(points))
    table = pixel_ibl(SKY, n, v, model, PixelIBLSettings(levels=9, samples=256), visibility=vis)
    ours = np.asarray(shade_pixel_ibl(table, base, metal, rough, model))
    reference = np.asarray(monte_carlo_radiance(SKY, n, v, base, metal, rough, Model(), samples=2048,
                                                visibility=vis))
    open_ = np.asarray(monte_carlo_radiance(SKY, n, v, base, metal, rough, Model(), samples=2048))
    assert np.sum(reference.mean(1) < 0.8 * open_.mean(1)) >= 3
    error = np.abs(ours - reference).mean(1) / reference.mean(1)
    assert error.mean() < 0.02 and error.max() < 0.08


def test_split_sum_factors_come_closer_to_the_occluded_integrals():
    mesh, points, normals, v = _scene_points()
    vis, cells = cast_visibility(mesh, SKY, points, normals)
    n, v = jnp.asarray(normals, jnp.float32), jnp.asarray(v, jnp.float32)
    base, metal, rough = _material(len(points), seed=3)
    truth = shade_pixel_ibl(pixel_ibl(SKY, n, v, Model(ibl="per_pixel"), PixelIBLSettings(levels=9, samples=256),
                                      visibility=vis), base, metal, rough, Model(ibl="per_pixel"))
    tables = build_ibl(SKY, IBLSettings(), Model())
    factors = jnp.asarray(split_sum_factors(vis, cells, n, v))
    assert np.all((np.asarray(factors) >= 0) & (np.asarray(factors) <= 1))
    plain = shade_ibl(tables, n, v, base, metal, rough, Model())
    occluded = shade_ibl(tables, n, v, base, metal, rough, Model(), factors=factors)
    err = lambda x: float(np.mean(np.abs(np.asarray(x) - np.asarray(truth)) / np.asarray(truth).mean(1, keepdims=True)))  # noqa: E731
    assert err(occluded) < 0.5 * err(plain)


def test_a_bounce_as_bright_as_the_light_it_hides_gives_the_open_integrals():
    """Under an even sky, blocked directions that bring the sky's own radiance make the occluded
    integrals those of no occlusion at all (the same samples: equal to rounding); a dark bounce
    makes them those of occlusion alone; `incoming` picks the bounce only on blocked cells above
    the point's face."""
    mesh, points, normals, v = _scene_points()
    even = Environment(jnp.full((32, 64, 3), 0.7, jnp.float32))
    vis, cells = cast_visibility(mesh, even, points, normals)
    rows, blocked = blocked_cells(np.asarray(vis.bits), cells.count)
    assert len(rows) > 50
    offsets = np.searchsorted(rows, np.arange(len(points) + 1))
    n, v = jnp.asarray(normals, jnp.float32), jnp.asarray(v, jnp.float32)
    model, settings = Model(ibl="per_pixel"), PixelIBLSettings(levels=5, samples=64)
    table = lambda **kw: np.asarray(pixel_ibl(even, n, v, model, settings, **kw).table)  # noqa: E731
    sky = Bounce(np.full((len(rows), 3), 0.7, np.float32), offsets)
    dark = Bounce(np.zeros((len(rows), 3), np.float32), offsets)
    np.testing.assert_allclose(table(visibility=vis, bounce=sky), table(), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(table(visibility=vis, bounce=dark), table(visibility=vis), rtol=1e-5, atol=1e-7)
    direct, bounced = pixel_ibl_parts(even, n, v, model, settings, visibility=vis, bounce=sky)
    np.testing.assert_allclose(np.asarray(direct.table), table(visibility=vis), rtol=1e-5, atol=1e-7)
    assert np.asarray(bounced.table).max() > 0.05  # the light the sphere hides, brought back by the bounce
    assert np.mean(table(visibility=vis)) < 0.95 * np.mean(table())

    colour = Bounce(np.tile(np.float32([[0.1, 0.2, 0.3]]), (len(rows), 1)) * (1 + np.arange(len(rows)))[:, None], offsets)
    full = np.zeros((len(points), cells.count, 3), np.float32)
    full[rows, blocked] = colour.radiance
    middle = (len(points) // 3, 2 * len(points) // 3)  # rows from the middle, padded by two
    some = visibility_rows(vis, *middle, 2, colour)
    assert some.bounce.shape == (middle[1] - middle[0] + 2, cells.count, 3) and offsets[middle[0]] > 0
    np.testing.assert_array_equal(np.asarray(some.bounce[:-2]), full[middle[0]:middle[1]])
    assert not np.any(np.asarray(some.bounce[-2:]))
    p = int(rows[0])
    k_blocked = int(blocked[0])
    k_open = int(np.flatnonzero(np.unpackbits(np.asarray(vis.bits)[p], count=cells.count, bitorder="little")
                                & (cells.directions @ normals[p] > 0.3))[0])
    below = -np.asarray(normals[p])
    l = jnp.asarray(np.stack([cells.directions[k_blocked], cells.directions[k_open], below])[:, None], jnp.float32)
    d = to_environment_frame(l, even.world_up, even.rotation_deg)
    rad = jnp.full(l.shape, 0.7, jnp.float32)
    got = np.asarray(incoming(visibility_rows(vis, p, p + 1, 0, colour), rad, l, d))[:, 0]
    assert got.shape == (3, 6)  # [the environment's light, the bounce's]
    np.testing.assert_allclose(got[0], np.r_[np.zeros(3), colour.radiance[offsets[p]]], rtol=1e-6)
    np.testing.assert_allclose(got[1], np.r_[np.full(3, 0.7), np.zeros(3)], rtol=1e-6)
    np.testing.assert_array_equal(got[2], 0.0)
