"""Environment visibility of the fixed mesh: parallel shadow rays against the per-ray caster, a
convex mesh casts nothing, a point under a sphere on a floor is shadowed, the cache is read."""

import jax.numpy as jnp
import numpy as np
import pytest

from data_synth import environments, meshes
from pbrfit.lighting.environment import Environment
from pbrfit.lighting.visibility import direction_cells
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
