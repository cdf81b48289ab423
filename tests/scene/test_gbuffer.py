"""G-buffer: camera rays, hits, interpolated attributes, tangent frames, shadows, cache."""

import dataclasses

import numpy as np
import pytest
import trimesh

from pbrfit.scene import gbuffer as gb
from pbrfit.errors import CaptureError
from pbrfit.scene.camera import Camera
from pbrfit.scene.gbuffer import compute_gbuffer


@dataclasses.dataclass(frozen=True)
class _Light:
    """Stand-in with the attributes compute_gbuffer reads from pbrfit.physics.lights.Light."""

    kind: str
    position: tuple = (0.0, 0.0, 0.0)
    direction: tuple = (0.0, 0.0, -1.0)


def look_at(eye, target, up=(0.0, 1.0, 0.0)):
    """OpenGL camera-to-world: -Z looks from eye to target."""
    eye, target, up = (np.asarray(a, float) for a in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, eye
    return c2w


def grid_plane(n=4, z=0.0, half=1.0, mirror_u=False, mirror_v=False):
    """Square [-half, half]^2 at height z, normal +Z, glTF uv: u along +x, v = 0 at +y edge."""
    s = np.linspace(-half, half, n + 1)
    x, y = np.meshgrid(s, s)
    verts = np.c_[x.ravel(), y.ravel(), np.full(x.size, z)]
    u = (x.ravel() + half) / (2 * half)
    v = (half - y.ravel()) / (2 * half)
    uv = np.c_[1 - u if mirror_u else u, 1 - v if mirror_v else v]
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, c, d = i.ravel(), i.ravel() + 1, i.ravel() + n + 2, i.ravel() + n + 1
    faces = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    return verts, faces, uv


def textured(verts, faces, uv, normals=None):
    mesh = trimesh.Trimesh(verts, faces, vertex_normals=normals, process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv)
    return mesh


def uv_sphere(n_lat=24, n_lon=48, radius=1.0):
    """Sphere with analytic glTF uv: u = 0.5 + atan2(x, z) / 2pi, v = theta / pi (v = 0 at +Y).

    The seam column is duplicated so u runs 0..1 without wrapping inside a triangle.
    """
    theta = np.linspace(0, np.pi, n_lat + 1)
    phi = np.linspace(-np.pi, np.pi, n_lon + 1)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(th) * np.sin(ph), np.cos(th), np.sin(th) * np.cos(ph)], -1).reshape(-1, 3)
    uv = np.c_[0.5 + ph.ravel() / (2 * np.pi), th.ravel() / np.pi]
    i = np.arange(n_lat)[:, None] * (n_lon + 1) + np.arange(n_lon)[None, :]
    a, b, c, d = i.ravel(), i.ravel() + n_lon + 1, i.ravel() + n_lon + 2, i.ravel() + 1
    faces = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    # drop the degenerate triangles at the poles
    tri = dirs[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1)
    faces = faces[area > 1e-12]
    mesh = textured(radius * dirs, faces, uv, normals=dirs)
    assert np.all(np.sum(mesh.face_normals * mesh.triangles_center, -1) > 0), "outward winding"
    return mesh


def test_rays_known_camera():
    cam = Camera.from_fov(np.eye(4), 2 * np.arctan(0.5), 4, 2)  # fx = fy = 4
    np.testing.assert_allclose((cam.fx, cam.fy, cam.cx, cam.cy), (4, 4, 2, 1), rtol=1e-15)
    o, d = cam.rays()
    assert o.shape == d.shape == (2, 4, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-15)
    # pixel (0, 0): x = 0.5, y = 0.5 -> camera ray (-1.5/4, +0.5/4, -1): up and left
    expect = np.array([-1.5 / 4, 0.5 / 4, -1.0])
    np.testing.assert_allclose(d[0, 0], expect / np.linalg.norm(expect), atol=1e-15)
    expect = np.array([1.5 / 4, -0.5 / 4, -1.0])
    np.testing.assert_allclose(d[1, 3], expect / np.linalg.norm(expect), atol=1e-15)
    np.testing.assert_array_equal(o, 0.0)


def test_rays_posed_camera_and_projection_round_trip():
    c2w = look_at((1.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    cam = Camera(c2w, fx=30.0, fy=25.0, cx=10.5, cy=7.5, width=21, height=15)
    o, d = cam.rays()
    np.testing.assert_allclose(o[0, 0], (1, 2, 3))
    np.testing.assert_allclose(cam.center, (1, 2, 3))
    # the principal point sits on pixel (7, 10)'s centre: that ray looks along -Z of c2w
    np.testing.assert_allclose(d[7, 10], -c2w[:3, 2], atol=1e-14)
    # row 0 is up (+Y of the camera), column 0 is left (-X)
    assert np.dot(d[0, 10], c2w[:3, 1]) > 0 and np.dot(d[7, 0], c2w[:3, 0]) < 0
    pts = o + 2.7 * d
    jj, ii = np.meshgrid(np.arange(21) + 0.5, np.arange(15) + 0.5)
    np.testing.assert_allclose(cam.project(pts), np.stack([jj, ii], -1), atol=1e-10)
    assert np.all(np.isnan(cam.project(np.array([[2.0, 4.0, 6.0]]))))  # behind the camera


def test_camera_validation_and_equality():
    with pytest.raises(CaptureError, match="4x4"):
        Camera(np.eye(3), 1, 1, 0, 0, 2, 2)
    with pytest.raises(CaptureError, match="fx"):
        Camera(np.eye(4), 0, 1, 0, 0, 2, 2)
    with pytest.raises(CaptureError, match="width"):
        Camera(np.eye(4), 1, 1, 0, 0, 0, 2)
    a = Camera.from_fov(np.eye(4), 0.7, 8, 6)
    b = Camera.from_fov(np.eye(4).tolist(), 0.7, 8, 6)
    assert a == b and hash(a) == hash(b) and a != Camera.from_fov(np.eye(4), 0.8, 8, 6)
    # as the capture loader reads transform_matrix: scaled axes are made unit (the same rays),
    # zero, sheared or mirrored ones are refused
    scaled = Camera.from_fov(np.diag([2.0, 0.5, 3.0, 1.0]), 0.7, 8, 6)
    assert scaled == a and np.allclose(scaled.rays()[1], a.rays()[1])
    for c2w, match in ((np.diag([1.0, 1.0, -1.0, 1.0]), "mirrored"), (np.diag([1.0, 0.0, 1.0, 1.0]), "is zero"),
                       ([[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "not perpendicular")):
        with pytest.raises(CaptureError, match=f"camera: transform: .*{match}"):
            Camera.from_fov(c2w, 0.7, 8, 6)


PLANE_CAM = Camera.from_fov(look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0)), 0.5, 24, 20)


def test_plane_positions_uv_normals_tangents():
    mesh = textured(*grid_plane())
    g = compute_gbuffer(mesh, PLANE_CAM, ())
    assert g.hit.all() and g.visibility.shape == (20, 24, 0)
    p = g.position
    np.testing.assert_allclose(p[..., 2], 0.0, atol=1e-14)
    o, d = PLANE_CAM.rays()
    np.testing.assert_allclose(p, o + d * (3.0 / -d[..., 2:3]), atol=1e-12)  # analytic z = 0 hit
    np.testing.assert_allclose(g.uv[..., 0], (p[..., 0] + 1) / 2, atol=1e-6)
    np.testing.assert_allclose(g.uv[..., 1], (1 - p[..., 1]) / 2, atol=1e-6)
    # top image row sees the top of the texture (small v), as an upright photo of it would
    assert g.uv[0, :, 1].mean() < g.uv[-1, :, 1].mean()
    np.testing.assert_allclose(g.normal, np.broadcast_to([0, 0, 1], p.shape), atol=1e-6)
    np.testing.assert_allclose(g.geometric_normal, np.broadcast_to([0, 0, 1], p.shape), atol=1e-6)
    np.testing.assert_allclose(g.tangent, np.broadcast_to([1, 0, 0, 1], g.tangent.shape), atol=1e-6)
    view = (PLANE_CAM.center - p) / np.linalg.norm(PLANE_CAM.center - p, axis=-1, keepdims=True)
    np.testing.assert_allclose(g.view, view, atol=1e-6)
    assert g.face.min() >= 0


def _bitangent(g):
    return np.cross(g.normal, g.tangent[..., :3]) * g.tangent[..., 3:]


@pytest.mark.parametrize("mirror_u", [False, True])
@pytest.mark.parametrize("mirror_v", [False, True])
def test_tangent_frame_handedness(mirror_u, mirror_v):
    mesh = textured(*grid_plane(mirror_u=mirror_u, mirror_v=mirror_v))
    g = compute_gbuffer(mesh, PLANE_CAM, ())
    t, n, w = g.tangent[..., :3], g.normal, g.tangent[..., 3]
    np.testing.assert_allclose(np.linalg.norm(t, axis=-1), 1, atol=1e-6)
    np.testing.assert_allclose(np.sum(t * n, -1), 0, atol=1e-6)
    assert set(np.unique(w)) == {-1.0 if mirror_u != mirror_v else 1.0}
    dpdu = np.array([-1.0 if mirror_u else 1.0, 0, 0])  # u grows along +x unless mirrored
    dpdv = np.array([0, 1.0 if mirror_v else -1.0, 0])  # v grows down the image: -y
    np.testing.assert_allclose(t, np.broadcast_to(dpdu, t.shape), atol=1e-6)
    np.testing.assert_allclose(_bitangent(g), np.broadcast_to(-dpdv, t.shape), atol=1e-6)


def test_back_face_mirrors_the_whole_frame():
    mesh = textured(*grid_plane())
    below = Camera.from_fov(look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0)), 0.5, 16, 16)
    g = compute_gbuffer(mesh, below, ())
    assert g.hit.all()
    np.testing.assert_allclose(g.geometric_normal, np.broadcast_to([0, 0, -1], g.normal.shape), atol=1e-6)
    np.testing.assert_allclose(g.normal, np.broadcast_to([0, 0, -1], g.normal.shape), atol=1e-6)
    np.testing.assert_allclose(g.tangent, np.broadcast_to([-1, 0, 0, -1], g.tangent.shape), atol=1e-6)
    np.testing.assert_allclose(_bitangent(g), np.broadcast_to([0, -1, 0], g.normal.shape), atol=1e-6)


def test_tangent_attribute_is_used_when_present():
    mesh = textured(*grid_plane())
    tan = np.tile([0.0, 1.0, 0.0, -1.0], (len(mesh.vertices), 1))
    mesh.vertex_attributes["tangent"] = tan
    g = compute_gbuffer(mesh, PLANE_CAM, ())
    np.testing.assert_allclose(g.tangent, np.broadcast_to([0, 1, 0, -1], g.tangent.shape), atol=1e-6)


def test_trimesh_uv_convention_matches_gltf_after_flip():
    v, f, uv = grid_plane(mirror_u=True)
    ref = compute_gbuffer(textured(v, f, uv), PLANE_CAM, ())
    flipped = textured(v, f, np.c_[uv[:, 0], 1 - uv[:, 1]])  # as trimesh's loaders store it
    g = compute_gbuffer(flipped, PLANE_CAM, (), uv_convention="trimesh")
    np.testing.assert_array_equal(g.uv, ref.uv)
    np.testing.assert_array_equal(g.tangent, ref.tangent)
    with pytest.raises(ValueError, match="uv_convention"):
        compute_gbuffer(flipped, PLANE_CAM, (), uv_convention="obj")


def test_gltf_file_round_trip_through_trimesh(tmp_path):
    """trimesh's glTF loader stores v as 1 - v: uv_convention="trimesh" undoes it."""
    v, f, uv = grid_plane()
    mesh = textured(v, f, np.c_[uv[:, 0], 1 - uv[:, 1]])
    mesh.export(tmp_path / "plane.glb")
    loaded = trimesh.load(tmp_path / "plane.glb", force="mesh", process=False)
    g = compute_gbuffer(loaded, PLANE_CAM, (), uv_convention="trimesh")
    np.testing.assert_allclose(g.uv[..., 1], (1 - g.position[..., 1]) / 2, atol=1e-6)


def test_no_uv_gives_zero_uv_and_a_perpendicular_tangent():
    v, f, _ = grid_plane()
    g = compute_gbuffer(trimesh.Trimesh(v, f, process=False), PLANE_CAM, ())
    np.testing.assert_array_equal(g.uv, 0)
    np.testing.assert_allclose(np.sum(g.tangent[..., :3] * g.normal, -1), 0, atol=1e-6)
    np.testing.assert_array_equal(g.tangent[..., 3], 1)


SPHERE = uv_sphere()
SPHERE_CAM = Camera.from_fov(look_at((0.5, 1.0, 3.0), (0.0, 0.0, 0.0)), 0.9, 40, 40)


def test_sphere_uv_normals_and_positions():
    g = compute_gbuffer(SPHERE, SPHERE_CAM, ())
    h = g.hit
    assert 0.2 < h.mean() < 0.9 and not h[0, 0]
    p = g.position[h]
    r = np.linalg.norm(p, axis=-1)
    # triangles of a 24 x 48 tessellation sit at most 1 - cos(pi/24)^2 inside the sphere
    assert r.max() <= 1 + 1e-12 and r.min() > np.cos(np.pi / 24) ** 2
    # hits lie on the reported triangle's plane to float64 rounding
    tri = SPHERE.triangles[g.face[h]]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    np.testing.assert_allclose(np.sum((p - tri[:, 0]) * nrm, -1) / np.linalg.norm(nrm, axis=-1), 0, atol=1e-12)
    # and project to their pixel centres
    jj, ii = np.meshgrid(np.arange(40) + 0.5, np.arange(40) + 0.5)
    np.testing.assert_allclose(SPHERE_CAM.project(p), np.stack([jj, ii], -1)[h], atol=1e-9)
    radial = p / r[:, None]
    # radial vertex normals, interpolated and normalised, are radial at the hit point
    np.testing.assert_allclose(g.normal[h], radial, atol=1e-6)
    assert np.all(np.sum(g.geometric_normal[h] * g.view[h], -1) >= 0)
    # analytic uv of the radial direction, away from the poles and the seam; linear interpolation
    # over a 1/48 x 1/24 uv cell departs from it by < 1e-3
    u = 0.5 + np.arctan2(radial[:, 0], radial[:, 2]) / (2 * np.pi)
    v = np.arccos(np.clip(radial[:, 1], -1, 1)) / np.pi
    ok = (np.abs(radial[:, 1]) < 0.9) & (np.abs(u - 0.5) < 0.45)
    np.testing.assert_allclose(g.uv[h][ok, 0], u[ok], atol=1e-3)
    np.testing.assert_allclose(g.uv[h][ok, 1], v[ok], atol=1e-3)
    # tangent along +u (east, d/dphi), bitangent towards the north pole (-dP/dv)
    east = np.stack([np.cos(2 * np.pi * (u - 0.5)), np.zeros_like(u), -np.sin(2 * np.pi * (u - 0.5))], -1)
    t = g.tangent[h][:, :3]
    assert np.all(np.sum(t[ok] * east[ok], -1) > 0.99)
    assert np.all(g.tangent[h][:, 3] == 1)
    b = np.cross(g.normal[h], t) * g.tangent[h][:, 3:]
    north = np.array([0, 1.0, 0]) - radial * radial[:, 1:2]
    assert np.all(np.sum(b[ok] * north[ok], -1) > 0)


def _occluded_scene():
    """Ground plane at z = 0 (2 x 2) and a 0.4 x 0.4 square occluder at z = 0.5."""
    gv, gf, guv = grid_plane(n=2)
    ov, of, ouv = grid_plane(n=1, z=0.5, half=0.2)
    mesh = textured(np.r_[gv, ov], np.r_[gf, of + len(gv)], np.r_[guv, ouv])
    return mesh, len(gf)


def _analytic_shadow(p, light):
    """Whether the segment/ray from ground points p towards the light crosses the occluder."""
    if light.kind == "directional":
        to_light = -np.asarray(light.direction, float)
        s = p + to_light * (0.5 - p[:, 2:3]) / to_light[2]
    else:
        lp = np.asarray(light.position, float)
        frac = (0.5 - p[:, 2:3]) / (lp[2] - p[:, 2:3])
        s = np.where(frac <= 1, p + (lp - p) * frac, np.inf)
    return np.all(np.abs(s[:, :2]) < 0.2, axis=-1), np.min(np.abs(np.abs(s[:, :2]) - 0.2), axis=-1)


SHADOW_LIGHTS = (
    _Light("directional", direction=(1.0, 0.0, -1.0)),
    _Light("point", position=(-0.3, 0.2, 1.5)),
    _Light("spot", position=(0.1, -0.1, 0.3), direction=(0.0, 0.0, -1.0)),  # under the occluder
    _Light("point", position=(0.0, 0.0, -1.0)),  # below the ground: lights its back only
)
SHADOW_CAM = Camera.from_fov(look_at((0.0, -0.01, 4.0), (0.0, 0.0, 0.0)), 0.6, 48, 48)


@pytest.mark.parametrize("backend", ["embree", "numpy"])
def test_shadows_where_geometry_says(backend):
    if backend == "embree" and not gb.has_embree:
        pytest.skip("embreex not installed")
    mesh, n_ground = _occluded_scene()
    g = compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS, backend=backend)
    ground = g.hit & (g.face < n_ground)
    assert ground.sum() > 1000
    p = g.position[ground]
    for k, light in enumerate(SHADOW_LIGHTS[:3]):
        shadow, margin = _analytic_shadow(p, light)
        clear = margin > 1e-6
        vis = g.visibility[ground][:, k]
        np.testing.assert_array_equal(vis[clear], (~shadow[clear]).astype(np.float32))
        if k < 2:
            assert shadow.sum() > 20  # the shadow is in view
        else:
            assert not shadow.any() and np.all(vis == 1)  # occluder beyond the light: no shadow
    assert np.all(g.visibility[ground][:, 3] == 0)
    occ = g.hit & (g.face >= n_ground)
    assert np.all(g.visibility[occ][:, :2] == 1) and np.all(g.visibility[occ][:, 2] == 0)
    assert np.all(g.visibility[~g.hit] == 0)


@pytest.mark.skipif(not gb.has_embree, reason="embreex not installed")
def test_embree_matches_numpy_intersector():
    cam = Camera.from_fov(look_at((0.3, 0.8, 2.5), (0.0, 0.0, 0.0)), 1.0, 32, 32)
    lights = (_Light("point", position=(2.0, 2.0, 2.0)), _Light("directional", direction=(0.0, -1.0, 0.2)))
    a = compute_gbuffer(SPHERE, cam, lights, backend="embree")
    b = compute_gbuffer(SPHERE, cam, lights, backend="numpy")
    # float32 traversal may pick the neighbour across an edge or miss a silhouette graze
    assert np.mean(a.hit != b.hit) < 0.005
    both = a.hit & b.hit
    assert np.mean(a.face[both] == b.face[both]) > 0.99
    np.testing.assert_allclose(a.position[both], b.position[both], atol=1e-6)
    np.testing.assert_allclose(a.normal[both], b.normal[both], atol=1e-5)
    np.testing.assert_allclose(a.uv[both], b.uv[both], atol=1e-5)
    assert np.mean(a.visibility[both] != b.visibility[both]) < 0.005


def test_cache_round_trip_and_invalidation(tmp_path, monkeypatch):
    monkeypatch.setattr(gb, "_memo", type(gb._memo)())  # the files alone (the process's memo: the
    monkeypatch.setattr(gb, "MEMO_BYTES", 0)  # test below)
    mesh, _ = _occluded_scene()
    g1 = compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS, cache_dir=tmp_path)
    files = sorted(tmp_path.iterdir())
    assert len(files) == 1 and files[0].suffix == ".npz"

    def boom(*args, **kwargs):
        raise AssertionError("ray cast despite a cached result")

    with monkeypatch.context() as m:
        m.setattr(gb, "make_first_hit", boom)
        g2 = compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS, cache_dir=tmp_path)
    for name, a in g1._arrays().items():
        b = getattr(g2, name)
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b, err_msg=name)

    moved = Camera.from_fov(look_at((0.0, -0.01, 4.1), (0.0, 0.0, 0.0)), 0.6, 48, 48)
    g3 = compute_gbuffer(mesh, moved, SHADOW_LIGHTS, cache_dir=tmp_path)
    assert len(list(tmp_path.iterdir())) == 2
    assert not np.array_equal(g3.position, g1.position)
    compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS[:1], cache_dir=tmp_path)  # other lights
    assert len(list(tmp_path.iterdir())) == 3
    # the mesh's vertices, texture coordinates and normals are in the key too
    verts = np.array(mesh.vertices)
    verts[-4:, 2] += 0.1  # the occluder moved up
    uv = np.array(mesh.visual.uv)
    normals = np.array(mesh.vertex_normals)
    normals[:4] = [0.0, 0.6, 0.8]
    for edited, what in ((textured(verts, mesh.faces, uv), "position"), (textured(mesh.vertices, mesh.faces, uv[:, ::-1]), "uv"),
                         (textured(mesh.vertices, mesh.faces, uv, normals), "normal")):
        before = len(list(tmp_path.iterdir()))
        g = compute_gbuffer(edited, SHADOW_CAM, SHADOW_LIGHTS, cache_dir=tmp_path)
        assert len(list(tmp_path.iterdir())) == before + 1, what
        assert not np.array_equal(getattr(g, what), getattr(g1, what)), what
    files[0].write_bytes(b"not an npz")  # a damaged entry is recomputed and replaced
    g4 = compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS, cache_dir=tmp_path)
    np.testing.assert_array_equal(g4.position, g1.position)
    np.testing.assert_array_equal(np.load(files[0])["position"], g1.position)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_the_process_remembers_the_latest_gbuffers(tmp_path, monkeypatch):
    monkeypatch.setattr(gb, "_memo", type(gb._memo)())
    mesh, _ = _occluded_scene()
    g1 = compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS)
    size = sum(a.nbytes for a in g1._arrays().values())
    with monkeypatch.context() as m:
        m.setattr(gb, "make_first_hit", lambda *a, **k: pytest.fail("ray cast despite a remembered result"))
        assert compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS) is g1
        # a cache folder named later still gets its file, written from the memo
        assert compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS, cache_dir=tmp_path) is g1
    np.testing.assert_array_equal(np.load(next(tmp_path.iterdir()))["position"], g1.position)
    with pytest.raises(ValueError):  # shared: read-only
        g1.position[0, 0, 0] = 1.0
    if gb.has_embree:  # each intersector's own: the other one casts
        other = "numpy" if compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS, backend="embree") is g1 else "embree"
        assert compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS, backend=other) is not g1
        gb._memo.clear()
        g1 = compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS)
    # room for one: the next view's G-buffer takes its place, and the first is cast again
    monkeypatch.setattr(gb, "MEMO_BYTES", size)
    moved = Camera.from_fov(look_at((0.0, -0.01, 4.1), (0.0, 0.0, 0.0)), 0.6, 48, 48)
    g2 = compute_gbuffer(mesh, moved, SHADOW_LIGHTS)
    assert list(gb._memo.values()) == [g2]
    g3 = compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS)
    assert g3 is not g1
    np.testing.assert_array_equal(g3.position, g1.position)
    monkeypatch.setattr(gb, "MEMO_BYTES", size - 1)  # one larger than the bound is not kept
    gb._memo.clear()
    compute_gbuffer(mesh, moved, SHADOW_LIGHTS)
    assert not gb._memo


def test_real_light_objects_when_available():
    lights = pytest.importorskip("pbrfit.physics.lights")
    mesh, n_ground = _occluded_scene()
    light = lights.directional_light(np.array([1.0, 0.0, -1.0]), np.ones(3), 1.0)
    g = compute_gbuffer(mesh, SHADOW_CAM, (light,))
    ref = compute_gbuffer(mesh, SHADOW_CAM, SHADOW_LIGHTS[:1])
    np.testing.assert_array_equal(g.visibility, ref.visibility)


def test_silhouette_marks_hit_pixels_beside_a_miss():
    from pbrfit.scene.gbuffer import silhouette

    hit = np.zeros((5, 6), bool)
    hit[1:4, 1:6] = True  # touches the right border: the border is not a miss
    ring = silhouette(hit)
    expected = hit.copy()
    expected[2, 2:6] = False  # interior: every neighbour hits
    np.testing.assert_array_equal(ring, expected)


def test_a_captures_frames_are_cast_in_threads_in_frame_order(monkeypatch):
    """`capture_gbuffers` casts the frames in a thread per core: each frame's G-buffer is the
    one cast alone, in the frames' order, and a frame that cannot be cast raises its error."""
    from types import SimpleNamespace

    from pbrfit.render.views import capture_gbuffers

    monkeypatch.setattr(gb, "_memo", type(gb._memo)())
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    mesh, _ = _occluded_scene()
    cams = [Camera.from_fov(look_at((0.3 * k, -0.01, 4.0 + 0.1 * k), (0.0, 0.0, 0.0)), 0.6, 32, 32) for k in range(5)]
    frames = [SimpleNamespace(camera=c, lights=SHADOW_LIGHTS[: 1 + k % 3]) for k, c in enumerate(cams)]
    got = capture_gbuffers(SimpleNamespace(mesh=mesh, frames=frames))
    gb._memo.clear()
    for g, f in zip(got, frames, strict=True):
        alone = compute_gbuffer(mesh, f.camera, f.lights)
        for name, a in alone._arrays().items():
            np.testing.assert_array_equal(getattr(g, name), a, err_msg=name)
    import pbrfit.render.views as views

    def cast(mesh, camera, lights, cache_dir):
        if camera is cams[3]:
            raise CaptureError("frame 3: broken")
        return compute_gbuffer(mesh, camera, lights, cache_dir)

    monkeypatch.setattr(views, "compute_gbuffer", cast)
    with pytest.raises(CaptureError, match="frame 3: broken"):
        capture_gbuffers(SimpleNamespace(mesh=mesh, frames=frames))
