"""Environment visibility of the fixed mesh: parallel shadow rays against the per-ray caster, a
convex mesh casts nothing, a point under a sphere on a floor is shadowed, the cache is read, the
blocked rays' closest hits and the light read there."""

import jax.numpy as jnp
import numpy as np
import pytest

from data_synth import environments, meshes
from pbrfit.lighting.environment import Environment
from pbrfit.lighting.visibility import blocked_cells, direction_cells
from pbrfit.scene import occlusion
from pbrfit.scene.occlusion import (cast_visibility, environment_visibility, occluded_share, occluding_faces,
                                    probe_share)
from pbrfit.scene.raycast import any_hit_along, cast, make_first_hit

SKY = Environment(jnp.asarray(environments.sky(64, 32, sun_elevation_deg=40.0, sun_azimuth_deg=30.0)))


def _sphere_on_floor():
    floor = meshes.plane(3.0, segments=2)
    sphere = meshes.uv_sphere(0.5, 24, 12, center=(0.0, 0.5, 0.0))
    return meshes.combine([floor, sphere], [(0, 0, 0.5, 1), (0.5, 0, 1, 1)]).to_trimesh()


def test_parallel_rays_agree_with_the_per_ray_caster():
    mesh = _sphere_on_floor()
    tri = np.asarray(mesh.triangles, np.float64)
    rng = np.random.default_rng(0)
    origins = np.c_[rng.uniform(-1.4, 1.4, 400), np.full(400, 1e-4), rng.uniform(-1.4, 1.4, 400)]
    first_hit = make_first_hit(mesh, "numpy")
    for d in ([0.3, 0.8, 0.2], [1.0, 0.05, 0.0], [0.0, 1.0, 0.0], [-0.2, 0.4, -0.9]):
        d = np.asarray(d) / np.linalg.norm(d)
        face, _, _, _ = cast(first_hit, tri, origins, np.tile(d, (len(origins), 1)))
        hit = any_hit_along(tri, origins, d)
        assert hit.any() and not hit.all()
        np.testing.assert_array_equal(hit, face >= 0)


def test_a_convex_mesh_blocks_nothing():
    sphere = meshes.uv_sphere(1.0, 48, 24).to_trimesh()
    assert not occluding_faces(sphere).any()  # what occlusion="auto" stops at: no ray is cast
    rng = np.random.default_rng(1)
    n = rng.normal(size=(64, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cells = direction_cells(SKY)
    bits = environment_visibility(sphere, n, n, cells.directions)
    assert np.all(np.unpackbits(bits, axis=1, count=cells.count, bitorder="little") == 1)
    assert probe_share(sphere, SKY, n, n) == 0.0


def test_a_point_under_the_sphere_is_shadowed():
    mesh = _sphere_on_floor()
    assert occluding_faces(mesh).any()
    points = np.array([[0.15, 0.0, 0.1], [1.4, 0.0, -1.4]])  # under the sphere; a far corner of the floor
    up = np.tile([0.0, 1.0, 0.0], (2, 1))
    vis, cells = cast_visibility(mesh, SKY, points, up)
    open_ = np.unpackbits(np.asarray(vis.bits), axis=1, count=cells.count, bitorder="little")
    zenith = int(np.argmax(cells.directions @ [0.0, 1.0, 0.0]))
    assert open_[0, zenith] == 0 and open_[1, zenith] == 1
    under = occluded_share(np.asarray(vis.bits)[:1], up[:1], cells.directions, cells.power)
    corner = occluded_share(np.asarray(vis.bits)[1:], up[1:], cells.directions, cells.power)
    assert under > 0.5 and corner < 0.05


def test_the_rays_are_cached(tmp_path, monkeypatch):
    mesh = _sphere_on_floor()
    points = np.array([[0.15, 0.0, 0.1], [0.9, 0.0, 0.3]])
    up = np.tile([0.0, 1.0, 0.0], (2, 1))
    cells = direction_cells(SKY)
    first = environment_visibility(mesh, points, up, cells.directions, tmp_path)
    assert len(list(tmp_path.glob("visibility-*.npy"))) == 1

    def refuse(*args):
        raise AssertionError("cast again although cached")

    monkeypatch.setattr(occlusion, "any_hit_along", refuse)
    np.testing.assert_array_equal(environment_visibility(mesh, points, up, cells.directions, tmp_path), first)
    with pytest.raises(AssertionError, match="cast again"):  # other points are not in the cache
        environment_visibility(mesh, points + [0.01, 0.0, 0.0], up, cells.directions, tmp_path)


def test_blocked_rays_land_on_what_blocks_them(tmp_path, monkeypatch):
    """Points on the floor under and beside the sphere: each blocked ray's closest hit is on the
    sphere, where the per-ray caster puts it, with the sphere's outward normal (the side the ray
    sees); read back from the cache."""
    mesh = _sphere_on_floor()
    points = np.array([[0.15, 0.0, 0.1], [0.6, 0.0, 0.0], [0.0, 0.0, -0.7]])
    up = np.tile([0.0, 1.0, 0.0], (3, 1))
    vis, cells = cast_visibility(mesh, SKY, points, up)
    bits = np.asarray(vis.bits)
    at, normal = occlusion.blocked_hits(mesh, points, up, cells.directions, bits, tmp_path)
    rows, blocked = blocked_cells(bits, cells.count)
    assert at.shape == normal.shape == (len(rows), 3) and len(set(rows.tolist())) == 3
    hit = np.all(np.isfinite(at), -1)
    assert hit.mean() > 0.95
    centre = np.array([0.0, 0.5, 0.0])
    np.testing.assert_allclose(np.linalg.norm(at[hit] - centre, axis=1), 0.5, atol=0.01)  # on the sphere (24 x 12 facets)
    assert np.all(np.sum(normal[hit] * (at[hit] - centre), -1) > 0.45)  # its outside, facing the floor below
    some = np.flatnonzero(hit)[:: max(1, hit.sum() // 20)]
    tri = np.asarray(mesh.triangles, np.float64)
    start = points[rows[some]] + up[rows[some]] * occlusion.shadow_offset(mesh)
    _, t, _, _ = cast(make_first_hit(mesh, "numpy"), tri, start, cells.directions[blocked[some]])
    np.testing.assert_allclose(at[some], start + t[:, None] * cells.directions[blocked[some]], atol=1e-5)

    monkeypatch.setattr(occlusion, "make_first_hit", lambda *a: (_ for _ in ()).throw(AssertionError("cast again")))
    again = occlusion.blocked_hits(mesh, points, up, cells.directions, bits, tmp_path)
    np.testing.assert_array_equal(again[0], at)
    np.testing.assert_array_equal(again[1], normal)


def test_observed_radiance_is_read_from_the_same_surface_without_glints():
    """The light leaving a hit point: the median of the nearest seen points on the same surface
    (normals within 60°), so a glint one camera saw does not spread, nor does a brighter surface
    close by; the nearest seen point where none faces the same way; 0 for a ray that hit nothing."""
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-1, 1, 400), np.zeros(400), rng.uniform(-1, 1, 400)]
    wall = np.c_[rng.uniform(-1, 1, 400), rng.uniform(0.001, 1, 400), np.full(400, 0.02)]  # a wall standing close
    seen = np.r_[floor, wall]
    seen_normals = np.r_[np.tile([0.0, 1.0, 0.0], (400, 1)), np.tile([0.0, 0.0, -1.0], (400, 1))]
    radiance = np.r_[np.tile([0.2, 0.3, 0.4], (400, 1)), np.tile([5.0, 5.0, 5.0], (400, 1))]
    radiance[np.argmin(np.linalg.norm(floor - [0.3, 0.0, -0.3], axis=1))] = 50.0  # a glint
    at = np.array([[0.3, 0.0, -0.3], [0.0, 0.0, 0.0], [0.5, 0.5, 0.02], [np.nan] * 3, [3.0, 0.0, 0.0]])
    at_normals = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    got, unseen = occlusion.observed_radiance_at(seen, seen_normals, radiance, at, at_normals)
    np.testing.assert_allclose(got[:2], [[0.2, 0.3, 0.4]] * 2, rtol=1e-6)
    np.testing.assert_allclose(got[2], 5.0)
    np.testing.assert_array_equal(got[3], 0.0)
    # a point far off the floor no camera saw: read from the floor's nearest seen points, and counted
    np.testing.assert_allclose(got[4], [0.2, 0.3, 0.4], rtol=1e-6)
    assert unseen.tolist() == [False, False, False, False, True]
    sideways, _ = occlusion.observed_radiance_at(seen, seen_normals, radiance, at[1:2], np.array([[1.0, 0.0, 0.0]]))
    nearest = np.argmin(np.linalg.norm(seen - at[1], axis=1))
    np.testing.assert_allclose(sideways[0], radiance[nearest])
