"""Environment visibility in the integrators: direction cells, the occluded per-pixel integrals
against the occluded Monte Carlo reference, and the split sum's occlusion factors."""

import jax.numpy as jnp
import numpy as np

from data_synth import environments, meshes
from pbrfit.lighting.environment import Environment
from pbrfit.lighting.ibl import IBLSettings, build_ibl, shade_ibl
from pbrfit.lighting.montecarlo import monte_carlo_radiance
from pbrfit.lighting.pixel_ibl import PixelIBLSettings, pixel_ibl, shade_pixel_ibl
from pbrfit.lighting.visibility import OcclusionSettings, direction_cells, split_sum_factors
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
