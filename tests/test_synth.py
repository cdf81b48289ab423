"""data_synth: procedural maps, environments, meshes, rigs, noise, and written captures."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import trimesh

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
    m = meshes.rounded_box(segments=2, flat_segments=1).translated((0.5, 0.0, 0.0))
    data = m.to_trimesh().export(file_type="glb", include_normals=True)
    np.testing.assert_array_equal(_glb_texcoords(data), m.uv)
    path = tmp_path / "m.glb"
    path.write_bytes(data)
    back = meshes.load_mesh(path)
    np.testing.assert_allclose(back.uv, m.uv, atol=1e-7)
    np.testing.assert_array_equal(back.vertices, m.vertices)


def test_file_normals_survive_loading(tmp_path):
    m = meshes.uv_sphere(segments=16, rings=8)
    meshes.write_glb(tmp_path / "s.glb", m)
    np.testing.assert_allclose(meshes.load_mesh(tmp_path / "s.glb").normals, m.normals, atol=1e-6)


def test_user_obj_mesh_keeps_gltf_uv(tmp_path):
    from scipy.spatial import cKDTree

    m = meshes.torus(segments=12, rings=6)
    path = tmp_path / "t.obj"
    path.write_text(m.to_trimesh().export(file_type="obj", include_texture=True))
    back = meshes.load_mesh(path)
    key = lambda d: np.concatenate([d.vertices, d.uv], axis=-1).astype(np.float64)
    dist, _ = cKDTree(key(m)).query(key(back))
    assert dist.max() < 1e-5  # every loaded (position, uv) pair is one of the torus's
    scene = presets.make_scene("mesh-env", mesh=str(path), views=2, size=8)
    assert np.linalg.norm(scene.mesh.vertices, axis=-1).max() == pytest.approx(1.0, rel=1e-5)


def test_user_mesh_without_area_is_refused(tmp_path):
    from pbrfit.errors import CaptureError

    path = tmp_path / "flat.obj"  # two triangles, each with its corners on one line
    path.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
                    "f 1/1 2/2 3/3\nf 2/2 3/3 4/4\n")
    with pytest.raises(CaptureError, match="flat.obj: every triangle has zero area"):
        meshes.load_mesh(path, normalize=True)


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
    y = np.concatenate([x, 4 * x], axis=-1)  # values 0.25 and 1.0
    rel = noise.add_noise(y, 0.01, np.random.default_rng(0), model="relative")
    for c, value in ((0, 0.25), (3, 1.0)):
        assert abs(rel[..., c].std() / (0.01 * value) - 1) < 0.05 and abs(rel[..., c].mean() / value - 1) < 1e-3
    np.testing.assert_array_equal(g, noise.add_noise(x, 0.01, np.random.default_rng(0)))


# --- presets -----------------------------------------------------------------------------------
from data_synth import presets, writer  # noqa: E402


def test_peer_plane_matches_the_fitting_issue_layout():
    s = presets.make_scene("peer-plane", seed=1)
    assert s.world_up == "+z" and s.num_views == 6 and (s.width, s.height) == (128, 128)
    assert s.camera_angle_x == pytest.approx(np.deg2rad(45.0))
    np.testing.assert_allclose(np.linalg.norm(s.cameras[:, :3, 3], axis=-1), 2.9)
    assert len(s.lights) == 4
    for light in s.lights:
        assert light.kind == "point" and float(light.intensity) == pytest.approx(6.0)
        assert np.linalg.norm(np.asarray(light.position)) == pytest.approx(2.6, rel=1e-6)
        assert float(np.asarray(light.position)[2]) > 0  # above the Z-up plane
    assert s.truth.shape == (64, 64) and s.truth.metallic.max() == 0.0
    np.testing.assert_allclose(s.mesh.normals, np.broadcast_to([0, 0, 1], s.mesh.normals.shape))
    np.testing.assert_allclose(np.ptp(s.mesh.vertices, axis=0), [2, 2, 0])
    assert s.environment is None and s.noise == 0 and s.image_format == "exr"


def test_plane_flash_matches_the_flash_capture():
    s = presets.make_scene("plane-flash", seed=0)
    assert s.num_views == 12 and s.flash is not None and len(s.lights) == 2
    assert s.image_format == "png16" and s.color_space == "srgb"
    assert s.supersample == 2 and s.noise == pytest.approx(0.01)
    metal = s.truth.metallic[..., 0]
    assert set(np.unique(metal)) == {0.0, 1.0}
    np.testing.assert_allclose(s.truth.base_color[metal == 1][0], textures.GOLD, atol=1e-6)


@pytest.mark.parametrize("name", presets.preset_names())
def test_presets_are_seeded(name):
    a = presets.make_scene(name, seed=3, views=3, size=8)
    b = presets.make_scene(name, seed=3, views=3, size=8)
    np.testing.assert_array_equal(a.cameras, b.cameras)
    np.testing.assert_array_equal(a.truth.base_color, b.truth.base_color)
    assert a.num_views == 3 and a.width == 8
    if name != "spheres-grid":  # the chart is the same for every seed
        c = presets.make_scene(name, seed=4, views=3, size=8)
        assert not np.array_equal(a.truth.base_color, c.truth.base_color)


@pytest.mark.parametrize("name", ["sphere-floor", "torus-floor", "demo", "mesh-env"])
def test_presets_whose_mesh_is_not_convex_render_light_between_surfaces(name):
    """As ``--max-depth`` says: a preset's Mitsuba depth is 2 for a convex mesh, else
    `presets.INTERREFLECTION_DEPTH` (an object on a floor lights the floor, and the floor the object)."""
    assert presets.make_scene(name, seed=0, views=1, size=8).max_depth == presets.INTERREFLECTION_DEPTH
    assert presets.make_scene("sphere-env", seed=0, views=1, size=8).max_depth == presets.MIN_DEPTH


def test_unknown_preset_or_parameter_is_a_capture_error():
    from pbrfit.errors import CaptureError

    with pytest.raises(CaptureError, match="unknown preset"):
        presets.make_scene("nope")
    with pytest.raises(CaptureError, match="shape"):
        presets.make_scene("demo", shape="torus")


# --- writing captures --------------------------------------------------------------------------
def _tiny(name, **kw):
    base = dict(size=16, views=2, texture_size=8)
    base.update(kw)
    return presets.make_scene(name, seed=0, **base)


@pytest.fixture(scope="module")
def peer_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "peer"
    return writer.synthesize(_tiny("peer-plane"), out)


@pytest.fixture(scope="module")
def flash_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "flash"
    return writer.synthesize(_tiny("plane-flash"), out)


def _same_light(a, b):
    from pbrfit.io.lights import light_to_json

    assert light_to_json(a) == light_to_json(b)


def test_capture_round_trip_linear(peer_capture):
    from pbrfit.io.material_files import read_material
    from pbrfit.scene.capture import load_capture

    cap = load_capture(peer_capture.path)
    scene = peer_capture.scene
    assert cap.world_up == "+z" and cap.color_space == "linear" and cap.environment is None
    assert len(cap.frames) == scene.num_views
    for frame, c2w, img, mask in zip(cap.frames, scene.cameras, peer_capture.images, peer_capture.masks):
        assert frame.camera == writer.frame_camera(scene, c2w)
        np.testing.assert_array_equal(frame.image, img)
        np.testing.assert_array_equal(frame.mask, mask)
        assert len(frame.lights) == len(scene.lights)
        for a, b in zip(frame.lights, scene.lights):
            _same_light(a, b)
    truth = read_material(cap.truth_dir)
    np.testing.assert_array_equal(np.asarray(truth.base_color), scene.truth.base_color)
    np.testing.assert_array_equal(np.asarray(truth.roughness), scene.truth.roughness)
    np.testing.assert_array_equal(np.asarray(truth.metallic), scene.truth.metallic)
    np.testing.assert_allclose(cap.mesh.visual.uv, scene.mesh.uv, atol=1e-7)
    np.testing.assert_allclose(cap.mesh.vertices, scene.mesh.vertices)
    assert (peer_capture.path / "contact_sheet.png").is_file()
    synth = json.loads((peer_capture.path / "truth" / "synth.json").read_text())
    assert synth["preset"] == "peer-plane" and synth["seed"] == 0
    # the truth GLB carries the mesh's uv as TEXCOORD_0 (glTF orientation)
    np.testing.assert_array_equal(_glb_texcoords((peer_capture.path / "truth" / "material.glb").read_bytes()),
                                  scene.mesh.uv)


def test_capture_round_trip_srgb_png_flash(flash_capture):
    from pbrfit.physics.color import srgb_to_linear
    from pbrfit.physics.lights import flash_light
    from pbrfit.scene.capture import load_capture

    cap = load_capture(flash_capture.path)
    scene = flash_capture.scene
    assert cap.color_space == "srgb" and cap.frames[0].info.bits == 16
    for frame, c2w, img in zip(cap.frames, scene.cameras, flash_capture.images):
        np.testing.assert_allclose(frame.image, np.asarray(srgb_to_linear(img)), atol=1e-6)
        assert len(frame.lights) == 3
        f = scene.flash
        _same_light(frame.lights[-1], flash_light(c2w, f.color, f.intensity, f.offset))
        assert frame.camera == writer.frame_camera(scene, c2w)
    # noise then 16-bit quantisation: within a few sigma of the clean render, on the code grid
    img, clean = flash_capture.images[0], flash_capture.clean[0]
    np.testing.assert_array_equal(np.round(img * 65535) / 65535, img)
    ok = (clean > 0.05) & (clean < 0.95)
    assert 0.005 < np.std((img - clean)[ok]) < 0.015


def test_rerender_with_truth_reproduces_images(peer_capture):
    from pbrfit.io.material_files import read_material
    from pbrfit.scene.capture import load_capture
    from pbrfit.render.views import render_capture

    cap = load_capture(peer_capture.path)
    renders = render_capture(cap, read_material(cap.truth_dir))
    for (image, alpha), clean, mask in zip(renders, peer_capture.clean, peer_capture.masks):
        assert mask.any()
        np.testing.assert_allclose(image[mask], clean[mask], rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(alpha > 0, mask)


def test_monte_carlo_environment_matches_the_per_pixel_integrals(tmp_path):
    """A scene rendered with ``ibl="monte_carlo"`` agrees with the fit's per-pixel integrals of the
    true maps: two exact integrators, so within their noise and without bias."""
    from pbrfit.io.material_files import read_material
    from pbrfit.physics.material import material_at
    from pbrfit.fitting.observations import observations_from_capture
    from pbrfit.lighting.pixel_ibl import PixelIBLSettings, pixel_ibl
    from pbrfit.render.shade import shade
    from pbrfit.scene.capture import load_capture
    from pbrfit.render.views import capture_environment

    scene = presets.make_scene("sphere-env", 1, size=24, views=2, texture_size=8)
    scene = scene.replace(model=scene.model.replace(ibl="monte_carlo"), mc_samples=512)
    writer.synthesize(scene, tmp_path / "cap")
    cap = load_capture(tmp_path / "cap")
    obs = observations_from_capture(cap, cache_dir=tmp_path / "cache")
    model = scene.model.replace(ibl="per_pixel")
    ibl = pixel_ibl(capture_environment(cap), np.asarray(obs.normal), np.asarray(obs.view), model,
                    PixelIBLSettings(samples=256))
    s = material_at(read_material(cap.truth_dir), obs.uv, "repeat")
    rad = np.asarray(shade(obs.normal, obs.view, obs.light_l, obs.light_radiance, s.base_color, s.metallic,
                           s.roughness, model, ibl))
    target = np.asarray(obs.target)
    rel = np.abs(rad - target).sum(1) / np.maximum(target.sum(1), 1e-3)  # (pixels facing away: both 0)
    assert np.median(rel) < 0.03 and abs(np.sum(rad - target)) < 0.01 * np.sum(target), (np.median(rel), np.sum(rad - target) / np.sum(target))


def test_monte_carlo_reference_casts_the_mesh_shadows_of_the_environment(tmp_path, monkeypatch):
    """The Monte Carlo reference renders a sphere on a floor with the sphere's shadow: darker
    than the same render with every direction open, on the floor about the sphere alone; a
    convex mesh casts nothing (`writer._reference_visibility`)."""
    from pbrfit.io.images import read_image
    import pbrfit.scene.occlusion as occlusion

    scene = presets.make_scene("sphere-floor", 0, size=16, views=2, texture_size=8, noise=0.0)
    scene = scene.replace(model=scene.model.replace(ibl="monte_carlo"), mc_samples=64)
    writer.synthesize(scene, tmp_path / "shadowed")
    monkeypatch.setattr(occlusion, "occluding_faces", lambda mesh: np.zeros(1, bool))  # nothing above any face
    writer.synthesize(scene, tmp_path / "open")
    shadowed, open_ = (np.asarray(read_image(tmp_path / name / "images" / "000.exr")[0])[..., :3] for name in
                       ("shadowed", "open"))
    darker = shadowed.sum(-1) < 0.95 * open_.sum(-1)
    assert 0.05 < darker.mean() < 0.6 and np.all(shadowed.sum(-1) <= open_.sum(-1) * 1.0001 + 1e-6)
    monkeypatch.undo()
    assert writer._reference_visibility(trimesh.creation.icosphere(), None, []) is None


def test_mitsuba_masks_hold_only_pixels_wholly_on_the_mesh(tmp_path):
    """A Mitsuba pixel is the mean over its area: its mask holds the pixels wholly on the mesh, not
    those whose centre alone does (a sky-mixed silhouette pixel), and 16 samples per side find no
    masked pixel even partly off the mesh."""
    from pbrfit.scene.gbuffer import compute_gbuffer
    from pbrfit.scene.mesh import load_mesh

    scene = presets.make_scene("sphere-env", 0, size=8, views=1, texture_size=4).replace(renderer="mitsuba")
    meshes.write_glb(tmp_path / "m.glb", scene.mesh)
    mesh = load_mesh(tmp_path / "m.glb")
    (mask,) = writer.mitsuba_masks(scene, mesh)
    centre = np.asarray(compute_gbuffer(mesh, writer.frame_camera(scene, scene.cameras[0])).hit, bool)
    fine = noise.box_downsample(np.asarray(compute_gbuffer(mesh, writer.frame_camera(scene, scene.cameras[0], 16)).hit,
                                           np.float32)[..., None], 16)[..., 0]
    assert mask.any() and not np.any(mask & ~centre) and np.sum(centre & ~mask) >= 4
    assert np.all(fine[mask] == 1.0) and np.any((fine < 1) & centre)


def test_whole_pixel_masks_leave_out_slivers_between_the_samples():
    """A straight edge that cuts a pixel between its 4 x 4 samples (within 1/8 of its side of its
    border) leaves it out of the mask, and a pixel wholly on the mesh stays in: checked against the
    exact coverage of a half-plane at 64 samples per side."""
    k, n = writer.MITSUBA_MASK_SAMPLES, 12

    def hits(per_pixel):  # the half-plane y < 0.37 x + 5.06 (in pixels), sampled at sub-pixel centres
        t = (np.arange(n * per_pixel) + 0.5) / per_pixel
        return t[:, None] < 0.37 * t[None, :] + 5.06

    exact = noise.box_downsample(hits(64).astype(np.float32)[..., None], 64)[..., 0]
    mask, samples_alone = writer._whole_pixels(hits(k), k), writer._mask(hits(k), k)
    assert np.all(exact[mask] == 1.0) and np.any(samples_alone & (exact < 1))
    inner = exact == 1.0
    assert np.sum(inner & ~mask) <= n  # what it gives up: pixels within 1/(2k) of the edge, about one per column


def test_texture_top_row_is_the_far_edge_seen_from_above(tmp_path):
    """End to end: texel row 0 (v = 0) lies at z = -1 of the +y plane, at the top of a camera
    looking straight down with -Z up in its image."""
    from pbrfit.physics.lights import directional_light

    maps = textures.uniform_maps(8, (0.1, 0.1, 0.8), 0.0, 0.8)
    bc = maps.base_color.copy()
    bc[:4] = (0.8, 0.1, 0.1)  # top half of the texture image red
    maps = textures.TruthMaps(bc, maps.metallic, maps.roughness)
    cam = rigs.look_at([0, 3, 0], [0, 0, 0], [0, 1, 0])[None]
    scene = presets.Scene(
        name="orientation", seed=0, mesh=meshes.plane(2.0), truth=maps, cameras=cam,
        camera_angle_x=np.deg2rad(30.0), width=16, height=16,
        lights=(directional_light((0, -1, 0), (1, 1, 1), 3.0),),
    )  # fmt: skip
    res = writer.synthesize(scene, tmp_path / "o")
    img = res.images[0]
    assert res.masks[0].all()
    assert img[:6, :, 0].min() > img[:6, :, 2].max()  # top: red
    assert img[-6:, :, 2].min() > img[-6:, :, 0].max()  # bottom: blue


def test_cli_synth_writes_and_refuses_bad_input(tmp_path, capsys):
    from pbrfit.cli.main import main

    out = tmp_path / "c"
    args = ["synth", "peer-plane", "--out", str(out), "--size", "16", "--views", "2", "--texture-size", "8"]
    assert main(args + ["--quiet"]) == 0
    assert (out / "capture.json").is_file() and capsys.readouterr().out == ""
    # --seed reaches the preset: the truth maps are those of make_scene with that seed, not seed 0's
    from data_synth import presets
    from pbrfit.io.material_files import read_material

    seeded = tmp_path / "seed3"
    assert main(["synth", "peer-plane", "--out", str(seeded), "--size", "16", "--views", "2", "--texture-size", "8",
                 "--seed", "3", "--quiet"]) == 0
    assert json.loads((seeded / "truth" / "synth.json").read_text())["seed"] == 3
    want = presets.make_scene("peer-plane", seed=3, size=16, views=2, texture_size=8).truth.base_color
    got = np.asarray(read_material(seeded / "truth").base_color)
    np.testing.assert_array_equal(got, want)
    assert not np.array_equal(got, np.asarray(read_material(out / "truth").base_color))
    assert main(args + ["--noise", "-1"]) == 2
    assert "--noise" in capsys.readouterr().err
    for extra, message in ((["--seed", "-1"], "--seed: must be at least 0"),
                           (["--size", "200000"], "--size: must be at most 8192"),
                           (["--texture-size", "200000"], "--texture-size: must be at most 8192"),
                           (["--views", "100000000"], "--views: must be at most 1024"),
                           (["--supersample", "100000"], "--supersample: must be at most 16"),
                           (["--noise", "inf"], "--noise: must be a finite number >= 0, got inf"),
                           (["--noise", "1e30"], "--noise: must be at most 100"),
                           (["--ibl-samples", "64"], "--ibl-samples: only --ibl monte_carlo uses it"),
                           (["--ibl", "monte_carlo"], "--ibl monte_carlo: preset peer-plane has no environment"),
                           (["--out", str(tmp_path / "c" / "capture.json" / "x")], "capture.json is not a folder")):
        assert main(["synth", "peer-plane", "--out", str(tmp_path / "x"), *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0] and not (tmp_path / "x").exists()
    # a kill (SIGTERM) midway removes what was half written, as Ctrl-C does
    import os
    import signal

    import pbrfit.io.images

    real = pbrfit.io.images.write_image

    def killed(*a, **k):
        os.kill(os.getpid(), signal.SIGTERM)
        return real(*a, **k)

    pbrfit.io.images.write_image = killed
    try:
        assert main(["synth", "peer-plane", "--out", str(tmp_path / "k"), "--size", "16", "--views", "2"]) == 143
    finally:
        pbrfit.io.images.write_image = real
    assert capsys.readouterr().err.strip() == "pbrfit: terminated"
    assert not any(p.name.startswith((".k.", "k")) for p in tmp_path.iterdir())
    assert signal.getsignal(signal.SIGTERM) is not None
    other = tmp_path / "mine"
    other.mkdir()
    (other / "precious.txt").write_text("keep")
    assert main(["synth", "demo", "--out", str(other)]) == 2
    assert (other / "precious.txt").read_text() == "keep" and len(list(other.iterdir())) == 1
    assert main(["synth", "mesh-env", "--out", str(tmp_path / "m"), "--mesh", str(tmp_path / "none.obj")]) == 2
    assert not (tmp_path / "m").exists()
    capsys.readouterr()
    assert main(["synth", "mesh-env", "--out", str(tmp_path / "m"), "--mesh", "a.obj", "--shape", "box"]) == 2
    assert "--shape: --mesh gives the mesh already" in capsys.readouterr().err and not (tmp_path / "m").exists()

