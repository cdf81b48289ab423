"""data_synth: procedural maps, environments, meshes, rigs, noise, and written captures."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from data_synth import environments, meshes, noise, rigs, textures


# --- textures ----------------------------------------------------------------------------------
def test_texel_uv_is_gltf_texel_centres():
    uv = textures.texel_uv((2, 4))
    assert uv.shape == (2, 4, 2)
    np.testing.assert_allclose(uv[0, 0], [0.125, 0.25])
    np.testing.assert_allclose(uv[1, 3], [0.875, 0.75])


def test_noise_is_periodic_bounded_and_seeded():
    a = textures.value_noise(32, 4, np.random.default_rng(3))
    b = textures.value_noise(32, 4, np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    assert 0.0 <= a.min() and a.max() <= 1.0
    # periodic: the step across the wrap is as small as a step inside the map
    inner = np.abs(np.diff(a, axis=1)).max()
    assert np.abs(a[:, 0] - a[:, -1]).max() <= inner * 1.01
    f = textures.fbm(32, np.random.default_rng(0))
    assert f.min() == 0.0 and f.max() == pytest.approx(1.0)


def test_binary_mask_coverage_and_scratches():
    m = textures.binary_mask(64, np.random.default_rng(1), coverage=0.3)
    assert m.dtype == bool and abs(m.mean() - 0.3) < 0.02
    s = textures.scratches(64, np.random.default_rng(1), count=5)
    assert 0.0 <= s.min() and s.max() <= 1.0 and 0.0 < s.mean() < 0.2


def test_textured_maps_ranges_and_gold_metal():
    m = textures.textured_maps(32, np.random.default_rng(0), metal="binary")
    assert m.base_color.shape == (32, 32, 3) and m.metallic.shape == m.roughness.shape == (32, 32, 1)
    assert m.base_color.dtype == np.float32
    assert set(np.unique(m.metallic)) == {0.0, 1.0}
    metal = m.metallic[..., 0] == 1
    np.testing.assert_allclose(m.base_color[metal], np.broadcast_to(textures.GOLD, (metal.sum(), 3)), atol=1e-6)
    assert m.roughness.min() >= textures.MIN_TRUTH_ROUGHNESS and m.roughness.max() <= 1
    again = textures.textured_maps(32, np.random.default_rng(0), metal="binary")
    np.testing.assert_array_equal(m.roughness, again.roughness)


def test_chart_maps_layout():
    c = textures.chart_maps([0.0, 1.0], [0.2, 0.5, 0.9], tile=4)
    assert c.shape == (8, 12)
    assert c.metallic[5, 1, 0] == 1.0 and c.metallic[2, 11, 0] == 0.0
    assert c.roughness[0, 5, 0] == pytest.approx(0.5) and c.roughness[7, 9, 0] == pytest.approx(0.9)


# --- environments ------------------------------------------------------------------------------
def test_equirect_orientation_matches_capture_spec():
    d = environments.equirect_directions(8, 4)
    assert d[0, :, 1].min() > 0.5  # top row looks up
    row = environments.equirect_directions(4, 1)[0]  # azimuths -135, -45, 45, 135 degrees
    np.testing.assert_allclose(row[1:3, 2], [-np.sqrt(0.5)] * 2, atol=1e-12)
    np.testing.assert_allclose(row[1:3, 0], [-np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(environments.direction_to_uv([0, 0, -1.0]), [0.5, 0.5])
    np.testing.assert_allclose(environments.direction_to_uv([1.0, 0, 0]), [0.75, 0.5])
    uv = environments.direction_to_uv(environments.equirect_directions(16, 8))
    np.testing.assert_allclose(uv, textures.texel_uv((8, 16)), atol=1e-6)


def test_world_up_z_maps_to_top_row():
    assert np.allclose(environments.world_to_env([0, 0, 1.0], "+z"), [0, 1, 0])
    p = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_allclose(environments.env_to_world(environments.world_to_env(p, "+z"), "+z"), p)


def test_sky_sun_where_asked():
    s = environments.sky(64, 32, sun_elevation_deg=30, sun_azimuth_deg=90)
    i, j = np.unravel_index(s.sum(-1).argmax(), s.shape[:2])
    assert abs((j + 0.5) / 64 - 0.75) < 1.5 / 64 and abs((i + 0.5) / 32 - 60 / 180) < 1.5 / 32
    assert s.dtype == np.float32 and s.min() > 0
    assert s[-1].mean() < s[0].mean()  # ground darker than the zenith


def test_studio_boxes_bright_walls_dark():
    st = environments.studio(64, 32)
    key = environments.DEFAULT_SOFTBOXES[0]
    u, v = environments.direction_to_uv(environments.direction_from_angles(key.elevation_deg, key.azimuth_deg))
    np.testing.assert_allclose(st[int(v * 32), int(u * 64)], key.radiance, rtol=1e-5)
    assert np.median(st) < 0.2


# --- meshes ------------------------------------------------------------------------------------
ALL_MESHES = {
    "plane": lambda up: meshes.plane(segments=2, world_up=up),
    "sphere": lambda up: meshes.uv_sphere(segments=12, rings=6, world_up=up),
    "torus": lambda up: meshes.torus(segments=12, rings=6, world_up=up),
    "box": lambda up: meshes.rounded_box(segments=2, flat_segments=1, world_up=up),
}


@pytest.mark.parametrize("name", sorted(ALL_MESHES))
@pytest.mark.parametrize("up", ["+y", "+z"])
def test_mesh_winding_follows_normals(name, up):
    m = ALL_MESHES[name](up)
    t = m.vertices[m.faces].astype(np.float64)
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    assert (np.einsum("ij,ij->i", fn, m.normals[m.faces].mean(1)) > 0).all()
    assert 0 <= m.uv.min() and m.uv.max() <= 1
    np.testing.assert_allclose(np.linalg.norm(m.normals, axis=-1), 1, atol=1e-6)


def test_plane_uv_orientation():
    m = meshes.plane(size=2.0, world_up="+y")
    np.testing.assert_allclose(m.uv[np.argmin(m.vertices[:, 2] + m.vertices[:, 0])], [0, 0])  # (-1, 0, -1)
    mz = meshes.plane(size=2.0, world_up="+z")
    assert np.allclose(mz.normals, [0, 0, 1])
    np.testing.assert_allclose(mz.uv[np.argmax(mz.vertices[:, 1] - mz.vertices[:, 0])], [0, 0])  # (-1, 1, 0)


def test_sphere_uv_analytic():
    m = meshes.uv_sphere(segments=16, rings=8)
    p = m.vertices.astype(np.float64)
    inner = (m.uv[:, 1] > 0) & (m.uv[:, 1] < 1) & (m.uv[:, 0] > 0) & (m.uv[:, 0] < 1)
    np.testing.assert_allclose(m.uv[inner, 1], np.arccos(np.clip(p[inner, 1], -1, 1)) / np.pi, atol=1e-6)
    np.testing.assert_allclose(m.uv[inner, 0], 0.5 + np.arctan2(p[inner, 0], p[inner, 2]) / (2 * np.pi), atol=1e-6)


def _glb_texcoords(data: bytes) -> np.ndarray:
    """TEXCOORD_0 of the first primitive of a GLB, read from the raw bytes."""
    (json_len,) = struct.unpack_from("<I", data, 12)
    doc = json.loads(data[20 : 20 + json_len])
    binary = data[20 + json_len + 8 :]
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]]
    view = doc["bufferViews"][acc["bufferView"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.frombuffer(binary, np.float32, acc["count"] * 2, start).reshape(-1, 2)


def test_glb_carries_gltf_uv_and_reads_back(tmp_path):
    m = meshes.rounded_box(segments=2, flat_segments=1)
    data = m.to_trimesh().export(file_type="glb", include_normals=True)
    np.testing.assert_array_equal(_glb_texcoords(data), m.uv)
    path = tmp_path / "m.glb"
    path.write_bytes(data)
    back = meshes.load_mesh(path)
    np.testing.assert_allclose(back.uv, m.uv, atol=1e-7)
    np.testing.assert_array_equal(back.vertices, m.vertices)
    np.testing.assert_allclose(back.normals, m.normals, atol=1e-6)


def test_combine_atlas_tiles():
    a, b = meshes.plane(), meshes.uv_sphere(segments=8, rings=4)
    c = meshes.combine([a, b], [(0, 0, 0.5, 1), (0.5, 0, 1, 0.5)])
    assert len(c.vertices) == len(a.vertices) + len(b.vertices)
    assert c.uv[: len(a.vertices), 0].max() <= 0.5 and c.uv[len(a.vertices) :, 1].max() <= 0.5
    assert c.faces.max() == len(c.vertices) - 1


# --- rigs --------------------------------------------------------------------------------------
@pytest.mark.parametrize("up", ["+y", "+z"])
def test_rigs_look_at_target_with_world_up_up(up):
    rng = np.random.default_rng(0)
    target = np.array([0.1, 0.2, -0.1])
    for cams in (
        rigs.orbit(5, 3.0, 30.0, target=target, world_up=up),
        rigs.hemisphere(6, 2.9, target=target, world_up=up),
        rigs.handheld(4, rng, world_up=up, aim_jitter=0.0, roll_deg=0.0, target=target),
    ):
        r = cams[:, :3, :3]
        np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(r), 1.0)
        to_target = target - cams[:, :3, 3]
        to_target /= np.linalg.norm(to_target, axis=-1, keepdims=True)
        np.testing.assert_allclose(-cams[:, :3, 2], to_target, atol=1e-12)  # looks down -Z
        assert (cams[:, :3, 1] @ rigs.up_vector(up) > 0).all()  # world up is up in the image
        assert ((cams[:, :3, 3] - target) @ rigs.up_vector(up) > 0).all()  # above the target


def test_orbit_azimuth_zero_faces_front():
    c = rigs.orbit(1, 3.0, 0.0)[0]
    np.testing.assert_allclose(c[:3, 3], [0, 0, 3], atol=1e-12)
    np.testing.assert_allclose(c[:3, :3], np.eye(3), atol=1e-12)


# --- noise -------------------------------------------------------------------------------------
def test_box_downsample_and_quantize():
    img = np.arange(16, dtype=np.float32).reshape(4, 4, 1)
    np.testing.assert_allclose(noise.box_downsample(img, 2)[..., 0], [[2.5, 4.5], [10.5, 12.5]])
    q = noise.quantize(np.array([-0.1, 0.3, 1.2], np.float32), 8)
    np.testing.assert_allclose(q, [0.0, round(0.3 * 255) / 255, 1.0])
    np.testing.assert_array_equal(noise.quantize(q, 8), q)
    assert noise.quantize(np.float32([0.3]), 0)[0] == np.float32(0.3)


def test_noise_statistics():
    x = np.full((200, 200, 3), 0.25, np.float32)
    g = noise.add_noise(x, 0.01, np.random.default_rng(0))
    assert abs(g.std() - 0.01) < 5e-4 and abs(g.mean() - 0.25) < 5e-4
    pg = noise.add_noise(x, 0.02, np.random.default_rng(0), model="poisson_gaussian")
    # variance x / q + read^2 with q = 1 / sigma^2, read = sigma / 4
    expected = np.sqrt(0.25 * 0.02**2 + (0.02 / 4) ** 2)
    assert abs(pg.std() / expected - 1) < 0.05
    np.testing.assert_array_equal(g, noise.add_noise(x, 0.01, np.random.default_rng(0)))
