"""Mesh files read as their formats mean them: glTF primitives trimesh alone misreads (triangle
fans, morph targets, skins, GPU instances, sparse indices, camera nodes, required extensions)
and OBJ text it trips over (tabs, indentation, comments after fields, one-component texture
coordinates)."""

import importlib.util
import re

import numpy as np
import pytest
from _capture_fixtures import QUAD_POSITIONS, QUAD_UV_GLTF

from pbrfit.errors import CaptureError
from pbrfit.scene.gltf_read import glb_chunks, glb_from_chunks
from pbrfit.scene.mesh import load_mesh

_COMPONENTS = {np.float32: 5126, np.uint32: 5125, np.uint16: 5123, np.uint8: 5121}


def _glb(path, arrays, **tree):
    """A GLB whose accessor i holds ``arrays[i]`` (float32 VECn or integer SCALAR), completed by
    ``tree`` (meshes, nodes, and scenes unless given)."""
    blob, views, accessors = b"", [], []
    for a in arrays:
        a = np.ascontiguousarray(a)
        blob += b"\0" * (-len(blob) % 4)
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": a.nbytes})
        entry = {"bufferView": len(views) - 1, "componentType": _COMPONENTS[a.dtype.type], "count": len(a),
                 "type": "SCALAR" if a.ndim == 1 else "MAT4" if a.shape[1] == 16 else f"VEC{a.shape[1]}"}
        if a.ndim == 2 and a.shape[1] == 3:
            entry.update(min=a.min(0).tolist(), max=a.max(0).tolist())
        accessors.append(entry)
        blob += a.tobytes()
    tree = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], **tree,
            "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors}
    path.write_bytes(glb_from_chunks(2, tree, blob))
    return path


def _triangles(mesh):
    """The mesh's triangles as sets of (x, y, z) corners, independent of vertex order."""
    return sorted(tuple(sorted(map(tuple, np.round(mesh.vertices[f], 6)))) for f in mesh.faces)


def test_triangle_fans_are_triangles(tmp_path):
    """glTF mode 6 (TRIANGLE_FAN): triangles (v_{i+1}, v_{i+2}, v_0), indexed or not. trimesh
    dropped them: a fan-only file held "no triangles", a fan beside triangles vanished."""
    lifted = QUAD_POSITIONS + np.float32([0, 0, 1])
    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array([0, 1, 2, 3], np.uint16), lifted,
              np.array([[0, 1, 2], [0, 2, 3]], np.uint32).reshape(-1)]
    meshes = [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "mode": 6},
                              {"attributes": {"POSITION": 3, "TEXCOORD_0": 1}, "mode": 6},
                              {"attributes": {"POSITION": 3, "TEXCOORD_0": 1}, "indices": 4}]}]
    mesh = load_mesh(_glb(tmp_path / "fan.glb", arrays, meshes=meshes, nodes=[{"mesh": 0}]))
    assert len(mesh.faces) == 6
    quad = [[0, 1, 2], [0, 2, 3]]
    expected = [tuple(sorted(map(tuple, p[f]))) for p in (QUAD_POSITIONS, lifted, lifted) for f in quad]
    assert _triangles(mesh) == sorted(tuple(sorted(tuple(float(x) for x in c) for c in t)) for t in expected)
    # the fan's first triangle is (v1, v2, v0): winding kept, so its normal faces +z
    np.testing.assert_allclose(mesh.face_normals[:2], [[0, 0, 1]] * 2, atol=1e-6)


def test_morph_targets_move_the_mesh_by_their_weights(tmp_path):
    """POSITION + Σ wᵢ targetᵢ, the weights a node gives, else the mesh's (glTF §3.7.2.2);
    trimesh drew the base shape."""
    up = np.tile(np.float32([0, 0, 2]), (4, 1))
    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array([0, 1, 2, 0, 2, 3], np.uint16), up]
    prim = {"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "targets": [{"POSITION": 3}]}

    def z(**nodes_and_mesh):
        mesh = {"primitives": [prim], **nodes_and_mesh.pop("mesh", {})}
        return load_mesh(_glb(tmp_path / "m.glb", arrays, meshes=[mesh], **nodes_and_mesh)).vertices[:, 2]

    np.testing.assert_allclose(z(nodes=[{"mesh": 0}]), 0.0)  # no weights: 0
    np.testing.assert_allclose(z(mesh={"weights": [0.5]}, nodes=[{"mesh": 0}]), 1.0)
    np.testing.assert_allclose(z(mesh={"weights": [0.5]}, nodes=[{"mesh": 0, "weights": [1.0]}]), 2.0)
    with pytest.raises(CaptureError, match="m.glb: mesh 0 is drawn by nodes with different morph target weights"):
        z(mesh={"weights": [0.5]}, nodes=[{"children": [1, 2]}, {"mesh": 0}, {"mesh": 0, "weights": [1.0]}])
    # nodes the shown scene does not hold draw nothing: a node in no scene, or in another one
    np.testing.assert_allclose(z(mesh={"weights": [0.5]}, nodes=[{"mesh": 0}, {"mesh": 0, "weights": [1.0]}]), 1.0)
    np.testing.assert_allclose(z(mesh={"weights": [0.5]}, nodes=[{"mesh": 0}, {"mesh": 0, "weights": [1.0]}],
                                 scenes=[{"nodes": [0]}, {"nodes": [1]}], scene=1), 2.0)


@pytest.mark.parametrize("mode, stored, expected", [
    (4, [0, 1, 2, 0, 0, 0], [[0, 1, 2], [0, 2, 3]]),  # entries 4, 5 replaced by 2, 3
    (6, [0, 1, 0, 0], [[1, 2, 0], [2, 3, 0]]),  # a fan: entries 2, 3 replaced by 2, 3
])
def test_sparse_indices_are_applied(tmp_path, mode, stored, expected):
    at = [4, 5] if mode == 4 else [2, 3]
    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array(stored, np.uint16), np.array(at, np.uint8),
              np.array([2, 3], np.uint16)]
    primitive = {"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "mode": mode}
    path = _glb(tmp_path / "s.glb", arrays, meshes=[{"primitives": [primitive]}], nodes=[{"mesh": 0}])
    version, tree, blob = glb_chunks(path.read_bytes())
    tree["accessors"][2]["sparse"] = {"count": 2, "indices": {"bufferView": 3, "componentType": 5121},
                                      "values": {"bufferView": 4}}
    path.write_bytes(glb_from_chunks(version, tree, blob))
    np.testing.assert_array_equal(load_mesh(path).faces, expected)


def test_gpu_instances_are_drawn_at_their_transforms(tmp_path):
    """EXT_mesh_gpu_instancing: the mesh once per instance, at node transform × instance T R S
    (trimesh drew it once, at the node's transform)."""
    translation = np.float32([[0, 0, 1], [0, 0, 2], [5, 0, 0]])
    rotation = np.float32([[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, np.sqrt(0.5), np.sqrt(0.5)]])  # last: 90° about z
    scale = np.float32([[1, 1, 1], [2, 2, 2], [1, 1, 1]])
    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array([0, 1, 2, 0, 2, 3], np.uint16), translation, rotation, scale]
    meshes = [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2}]}]
    instancing = {"EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": 3, "ROTATION": 4, "SCALE": 5}}}
    nodes = [{"mesh": 0, "translation": [0, 10, 0], "extensions": instancing}]
    mesh = load_mesh(_glb(tmp_path / "i.glb", arrays, meshes=meshes, nodes=nodes,
                          extensionsUsed=["EXT_mesh_gpu_instancing"], extensionsRequired=["EXT_mesh_gpu_instancing"]))
    expected = np.concatenate([QUAD_POSITIONS + [0, 10, 1], 2 * QUAD_POSITIONS + [0, 10, 2],
                               QUAD_POSITIONS[:, [1, 0, 2]] * [-1, 1, 1] + [5, 10, 0]])
    assert _triangles(mesh) == sorted(
        tuple(sorted(tuple(float(x) for x in c) for c in expected[f + 4 * k]))
        for k in range(3) for f in np.array([[0, 1, 2], [0, 2, 3]]))


def test_skinned_meshes_are_drawn_at_rest(tmp_path):
    """glTF §3.7.3: a vertex at Σ wₖ Gⱼ Bⱼ p, the skinned mesh node's own transform ignored
    (trimesh applied it, and no skin). Here every vertex weighs two joints at z = 2 and z = 4
    (inverse bind matrices the identity, and a rotated parent) equally."""
    joints = np.tile(np.array([[0, 1, 0, 0]], np.uint8), (4, 1))
    weights = np.tile(np.float32([[0.5, 0.5, 0, 0]]), (4, 1))
    inverse_bind = np.tile(np.eye(4, dtype=np.float32).reshape(1, 16), (2, 1))
    normals = np.tile(np.float32([[0, 0, 1]]), (4, 1))
    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array([0, 1, 2, 0, 2, 3], np.uint16), joints, weights, inverse_bind,
              normals]
    attributes = {"POSITION": 0, "TEXCOORD_0": 1, "JOINTS_0": 3, "WEIGHTS_0": 4, "NORMAL": 6}
    quarter = [0, 0, float(np.sin(np.pi / 4)), float(np.cos(np.pi / 4))]  # 90° about z
    nodes = [{"mesh": 0, "skin": 0, "translation": [100, 0, 0]}, {"rotation": quarter, "children": [2, 3]},
             {"translation": [0, 0, 2]}, {"translation": [0, 0, 4]}]
    mesh = load_mesh(_glb(tmp_path / "s.glb", arrays, meshes=[{"primitives": [{"attributes": attributes, "indices": 2}]}],
                          nodes=nodes, skins=[{"joints": [2, 3], "inverseBindMatrices": 5}],
                          scenes=[{"nodes": [0, 1]}]))
    turned = QUAD_POSITIONS[:, [1, 0, 2]] * [-1, 1, 1]  # the parent's quarter turn
    np.testing.assert_allclose(np.sort(mesh.vertices, axis=0), np.sort(turned + [0, 0, 3], axis=0), atol=1e-6)
    np.testing.assert_allclose(mesh.vertex_normals, np.tile([0, 0, 1], (4, 1)), atol=1e-6)


def _translate(x, y, z):
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def test_skinning_against_the_spec_formula(tmp_path):
    """Two joint sets, a column-major inverse bind matrix with a translation (read transposed, it
    moves nothing), a parent turned about x (its order against the children's translations
    matters) and a joint turned and scaled unevenly (T R S, and normals by the blend's inverse
    transpose, not the blend), against Σ wₖ G B p and (Σ wₖ G B)⁻ᵀ n worked out here."""
    turn_x = np.eye(4)
    turn_x[1:3, 1:3] = [[0, -1], [1, 0]]  # 90° about x: quaternion (sin 45°, 0, 0, cos 45°)
    turn_z = np.eye(4)
    turn_z[:2, :2] = [[0, -1], [1, 0]]  # 90° about z: quaternion (0, 0, sin 45°, cos 45°)
    scale = np.diag([1.0, 2.0, 1.0, 1.0])
    g0, g1 = turn_x @ _translate(0, 0, 2) @ turn_z @ scale, turn_x @ _translate(1, 0, 0)
    b0 = _translate(0, 0, -1)
    blend = 0.3 * g0 @ b0 + 0.7 * g1
    tilted = np.float32([0.0, 0.6, 0.8])
    expected_p = (blend @ np.c_[QUAD_POSITIONS, np.ones(4)].T).T[:, :3]
    expected_n = np.linalg.inv(blend[:3, :3]).T @ tilted
    expected_n /= np.linalg.norm(expected_n)

    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array([0, 1, 2, 0, 2, 3], np.uint16),
              np.tile(np.array([[0, 1, 0, 0]], np.uint16), (4, 1)), np.tile(np.float32([[0.3, 0.2, 0, 0]]), (4, 1)),
              np.tile(np.array([[1, 0, 0, 0]], np.uint16), (4, 1)), np.tile(np.float32([[0.5, 0, 0, 0]]), (4, 1)),
              np.stack([b0.T.reshape(16), np.eye(4).reshape(16)]).astype(np.float32), np.tile(tilted, (4, 1))]
    attributes = {"POSITION": 0, "TEXCOORD_0": 1, "JOINTS_0": 3, "WEIGHTS_0": 4, "JOINTS_1": 5, "WEIGHTS_1": 6,
                  "NORMAL": 8}
    half = float(np.sqrt(0.5))
    nodes = [{"mesh": 0, "skin": 0, "scale": [3, 3, 3]}, {"rotation": [half, 0, 0, half], "children": [2, 3]},
             {"translation": [0, 0, 2], "rotation": [0, 0, half, half], "scale": [1, 2, 1]},
             {"translation": [1, 0, 0]}]
    mesh = load_mesh(_glb(tmp_path / "s.glb", arrays, nodes=nodes, scenes=[{"nodes": [0, 1]}],
                          meshes=[{"primitives": [{"attributes": attributes, "indices": 2}]}],
                          skins=[{"joints": [2, 3], "inverseBindMatrices": 7}]))
    np.testing.assert_allclose(mesh.vertices, expected_p, atol=1e-5)
    np.testing.assert_allclose(mesh.vertex_normals, np.tile(expected_n, (4, 1)), atol=1e-5)


def test_a_skin_that_flattens_the_mesh_still_loads(tmp_path):
    """A joint scaled to 0 along an axis (as parts are hidden) has no inverse: the normal goes
    through the blend's cofactor matrix. A plane flattened along its own normal keeps it."""
    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array([0, 1, 2, 0, 2, 3], np.uint16),
              np.tile(np.array([[0, 0, 0, 0]], np.uint8), (4, 1)), np.tile(np.float32([[1, 0, 0, 0]]), (4, 1)),
              np.tile(np.float32([[0, 0, 1]]), (4, 1))]
    attributes = {"POSITION": 0, "TEXCOORD_0": 1, "JOINTS_0": 3, "WEIGHTS_0": 4, "NORMAL": 5}
    mesh = load_mesh(_glb(tmp_path / "f.glb", arrays, nodes=[{"mesh": 0, "skin": 0}, {"scale": [2, 1, 0]}],
                          scenes=[{"nodes": [0, 1]}], skins=[{"joints": [1]}],
                          meshes=[{"primitives": [{"attributes": attributes, "indices": 2}]}]))
    np.testing.assert_allclose(mesh.vertices, QUAD_POSITIONS * [2, 1, 0])
    np.testing.assert_allclose(mesh.vertex_normals, np.tile([0, 0, 1], (4, 1)), atol=1e-6)


def test_gpu_instances_without_a_transform_are_drawn_where_the_node_is(tmp_path):
    """Every instance attribute is optional (custom ones, "_ID", count the instances too)."""
    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array([0, 1, 2, 0, 2, 3], np.uint16), np.float32([7, 8])]
    instancing = {"EXT_mesh_gpu_instancing": {"attributes": {"_ID": 3}}}
    mesh = load_mesh(_glb(tmp_path / "i.glb", arrays, nodes=[{"mesh": 0, "extensions": instancing}],
                          meshes=[{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2}]}]))
    assert len(mesh.faces) == 4
    np.testing.assert_allclose(mesh.vertices[:4], QUAD_POSITIONS)


def test_a_mesh_on_or_under_a_camera_node_is_drawn(tmp_path):
    """trimesh left a node holding a camera and a mesh, and the meshes under it, out of the scene
    (the child raised "No path from world->1!")."""
    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array([0, 1, 2, 0, 2, 3], np.uint16)]
    meshes = [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2}]}]
    nodes = [{"camera": 0, "mesh": 0, "children": [1]}, {"mesh": 0, "translation": [0, 0, 3]}]
    cameras = [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.1}}]
    mesh = load_mesh(_glb(tmp_path / "c.glb", arrays, meshes=meshes, nodes=nodes, cameras=cameras))
    assert sorted(set(np.round(mesh.vertices[:, 2], 6))) == [0.0, 3.0] and len(mesh.faces) == 4


def test_required_extensions_pbrfit_cannot_read_are_refused(tmp_path):
    """A loader must refuse a file requiring an extension it does not support: a Draco or meshopt
    file came out as zeros or "malformed". Material, texture and quantization extensions leave
    what pbrfit reads as it is."""
    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array([0, 1, 2, 0, 2, 3], np.uint16)]
    tree = dict(meshes=[{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2}]}],
                nodes=[{"mesh": 0}])
    ok = ["KHR_materials_clearcoat", "KHR_texture_basisu", "KHR_mesh_quantization", "KHR_texture_transform"]
    assert len(load_mesh(_glb(tmp_path / "ok.glb", arrays, extensionsRequired=ok, **tree)).faces) == 2
    for required, message in (
            (["EXT_meshopt_compression"], "the glTF extension EXT_meshopt_compression, which pbrfit does "
                                          r"not read \(write it without compression\)"),
            (["EXT_meshopt_compression", "KHR_materials_ior", "EXT_foo"],
             "the glTF extensions EXT_meshopt_compression, EXT_foo, which pbrfit does not read "
             r"\(write it without compression\)$")):
        with pytest.raises(CaptureError, match=r"cannot load mesh .*x.glb: it requires " + message):
            load_mesh(_glb(tmp_path / "x.glb", arrays, extensionsRequired=required, **tree))
    # Draco: trimesh decodes it with DracoPy, where that is installed
    draco = _glb(tmp_path / "d.glb", arrays, extensionsRequired=["KHR_draco_mesh_compression"], **tree)
    if importlib.util.find_spec("DracoPy") is None:
        with pytest.raises(CaptureError, match=r"KHR_draco_mesh_compression, which pbrfit does not read \(install "
                                               "DracoPy, with which trimesh decodes Draco, or write it without"):
            load_mesh(draco)
    else:
        assert len(load_mesh(draco).faces) == 2


def test_broken_gltf_files_are_named_in_words(tmp_path):
    """An empty or cut GLB and a .gltf that is not JSON were refused with the parser's words
    ("unpack_from requires a buffer of at least 12 bytes", "Expecting value: line 1 column 741")."""
    arrays = [QUAD_POSITIONS, QUAD_UV_GLTF, np.array([0, 1, 2, 0, 2, 3], np.uint16)]
    tree = dict(meshes=[{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2}]}],
                nodes=[{"mesh": 0}])
    whole = _glb(tmp_path / "whole.glb", arrays, **tree).read_bytes()
    for name, data, message in (
            ("empty.glb", b"", "not a GLB file: 0 bytes, shorter than its headers"),
            ("cut.glb", whole[:40], "truncated GLB file: its JSON chunk needs"),
            ("list.glb", glb_from_chunks(2, [], None), "GLB file's JSON chunk is a list, not an object")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(CaptureError, match=f"cannot load mesh .*{name}: {message}"):
            load_mesh(tmp_path / name)
    for name, text, message in (("cut.gltf", '{"asset": {"version": "2.0"}, "nodes": [', "its JSON is not valid"),
                                ("list.gltf", "[1, 2]", "its JSON is a list, not an object")):
        (tmp_path / name).write_text(text)
        with pytest.raises(CaptureError, match=f"cannot load mesh .*{name}: not a glTF file: {message}"):
            load_mesh(tmp_path / name)


@pytest.mark.parametrize("text", [
    "v\t0 0 0\nv\t1 0 0\nv\t1 1 0\nv\t0 1 0\nvt\t0 0\nvt\t1 0\nvt\t1 0.75\nvt\t0 0.75\nf\t1/1 2/2 3/3\nf\t1/1 3/3 4/4\n",
    "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 0.75\nvt 0 0.75\n"
    "  f 1/1 2/2 3/3  # first\r\nf 1/1 3/3 4/4 # second\n",
])
def test_obj_fields_separated_by_any_whitespace_and_comments_after_them(tmp_path, text):
    """Tab-separated or indented lines were dropped by trimesh (a file "held no triangles", or a
    face was lost), and a comment after a face's fields failed to parse."""
    (tmp_path / "q.obj").write_text(text)
    mesh = load_mesh(tmp_path / "q.obj")
    np.testing.assert_allclose(mesh.vertices, QUAD_POSITIONS)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_allclose(mesh.visual.uv, QUAD_UV_GLTF)  # OBJ's v up, read as glTF's v down


def test_obj_in_another_encoding_loads_and_binary_data_is_named(tmp_path):
    """A comment or a name in Latin-1 (not UTF-8) was refused as "No module named
    'charset_normalizer'" (trimesh's guess at the encoding, which pbrfit does not require); a
    UTF-8 byte-order mark cost the first line, and UTF-16 was refused as binary."""
    quad = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 0.75\nvt 0 0.75\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
    (tmp_path / "latin.obj").write_bytes("# exported by Café 3D\no plaque_été\n".encode("latin-1") + quad.encode())
    mesh = load_mesh(tmp_path / "latin.obj")
    np.testing.assert_allclose(mesh.vertices, QUAD_POSITIONS)
    np.testing.assert_allclose(mesh.visual.uv, QUAD_UV_GLTF)
    for name, data in (("bom8.obj", b"\xef\xbb\xbf" + quad.encode()),  # the first vertex was dropped
                       ("bom16.obj", quad.encode("utf-16"))):  # refused as binary
        (tmp_path / name).write_bytes(data)
        mesh = load_mesh(tmp_path / name)
        np.testing.assert_allclose(mesh.vertices, QUAD_POSITIONS, err_msg=name)
        np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])
    (tmp_path / "binary.obj").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(CaptureError, match=r"binary.obj: not a text OBJ file \(it holds binary data\)"):
        load_mesh(tmp_path / "binary.obj")


def test_obj_one_component_texture_coordinate_has_v_0(tmp_path):
    """``vt u`` is valid OBJ (v defaults to 0); it raised an IndexError, and mixed with ``vt u v``
    lines trimesh shifted every texture coordinate after it."""
    (tmp_path / "mixed.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nvt 0.5\nvt 1 0.5\nvt 0 1\nf 1/1 2/2 3/3\n")
    np.testing.assert_allclose(load_mesh(tmp_path / "mixed.obj").visual.uv, [[0.5, 1], [1, 0.5], [0, 0]])
    (tmp_path / "u.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nvt 0\nvt 1\nvt 0.5\nf 1/1 2/2 3/3\n")
    mesh = load_mesh(tmp_path / "u.obj", require_uv=False)
    np.testing.assert_allclose(mesh.visual.uv, [[0, 1], [1, 1], [0.5, 1]])
    with pytest.raises(CaptureError, match="texture coordinates span no area"):
        load_mesh(tmp_path / "u.obj")


def _ply(path, vertices, faces, vertex_props=("x", "y", "z"), face_texcoord=None):
    head = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}"]
    head += [f"property float {p}" for p in vertex_props]
    head += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    head += ["property list uchar float texcoord"] if face_texcoord is not None else []
    rows = [" ".join(map(repr, map(float, v))) for v in vertices]
    for k, face in enumerate(faces):
        row = f"{len(face)} " + " ".join(map(str, face))
        if face_texcoord is not None:
            row += f" {2 * len(face)} " + " ".join(map(repr, map(float, np.ravel(face_texcoord[k]))))
        rows.append(row)
    path.write_text("\n".join(head + ["end_header"] + rows) + "\n")
    return path


def test_ply_normals_are_kept_where_per_face_texture_coordinates_split_vertices(tmp_path):
    """MeshLab writes a PLY's texture coordinates per face corner (``texcoord`` lists): trimesh
    gives a vertex a copy for each, and dropped the file's normals, which no longer matched; the
    copies shaded with normals of their own were creased at every uv seam."""
    tilted = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])
    vertices = [[*p, *tilted] for p in QUAD_POSITIONS]
    seam = [[[0, 0], [1, 0], [1, 1]], [[0.5, 0], [1, 1], [0, 1]]]  # vertex 0 and 2 get two uv each
    path = _ply(tmp_path / "n.ply", vertices, [[0, 1, 2], [0, 2, 3]], ("x", "y", "z", "nx", "ny", "nz"), seam)
    mesh = load_mesh(path)
    assert len(mesh.vertices) > 4  # the seam's copies
    np.testing.assert_allclose(mesh.vertex_normals, np.tile(tilted, (len(mesh.vertices), 1)), atol=1e-6)


def test_ply_hard_edges_keep_each_face_its_normal(tmp_path):
    """Where the file has one vertex per face at a corner (a hard edge, each with its face's
    normal), a split copy cannot be told by its position: it keeps trimesh's normal, here its
    face's (found by position alone, two of three corners took the wrong face's normal)."""
    # a corner of a cube: three squares meeting at the origin, each with its own four vertices
    vertices, faces, texcoord = [], [], []
    for axis in range(3):
        u, v = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
        n = np.eye(3)[axis]
        base = len(vertices)
        vertices += [[*(a * u + b * v), *n] for a, b in ((0, 0), (1, 0), (1, 1), (0, 1))]
        faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
        # a uv seam along each square's diagonal (its first corner's uv differs in its two triangles)
        texcoord += [[[axis / 3, 0], [(axis + 1) / 3, 0], [(axis + 1) / 3, 1]],
                     [[axis / 3 + 0.01, 0], [(axis + 1) / 3, 1], [axis / 3, 1]]]
    path = _ply(tmp_path / "c.ply", vertices, faces, ("x", "y", "z", "nx", "ny", "nz"), texcoord)
    mesh = load_mesh(path)
    assert len(mesh.vertices) > 12  # split at the seams
    corner_normals = mesh.vertex_normals[mesh.faces]  # (faces, 3, 3)
    np.testing.assert_allclose(corner_normals, np.repeat(mesh.face_normals[:, None], 3, axis=1), atol=1e-6)


def test_ply_face_index_outside_its_vertices_is_refused_with_texture_coordinates_too(tmp_path):
    """With texture coordinates trimesh read index -1 as the last vertex."""
    vertices = [[0, 0, 0, 0, 0], [1, 0, 0, 1, 0], [0, 1, 0, 0, 1]]
    path = _ply(tmp_path / "neg.ply", vertices, [[0, 1, -1]], ("x", "y", "z", "s", "t"))
    with pytest.raises(CaptureError, match="neg.ply: face indices run from -1 to 1, outside its 3 vertices"):
        load_mesh(path)


@pytest.mark.parametrize("faces", ["f 1/1 2/2 3/3\nf 1 3 4\n", "f 1/1 2/2 3/9\n"])
def test_obj_texture_coordinates_that_miss_a_corner_are_named(tmp_path, faces):
    """A face without vt, or a vt index past the last one: trimesh drops the file's uv, and the
    error said the mesh had none."""
    (tmp_path / "p.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\n" + faces)
    with pytest.raises(CaptureError, match=r"p.obj: its vt texture coordinates do not reach every face corner"):
        load_mesh(tmp_path / "p.obj")
    assert len(load_mesh(tmp_path / "p.obj", require_uv=False).faces) >= 1  # a uniform fit needs none


_TWO_QUADS = """mtllib m.mtl
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 2 0 0
v 3 0 0
v 3 1 0
v 2 1 0
{vt}
usemtl red
f 1/1 2/2 3/3
f 1/1 3/3 4/4
usemtl {second}
f 5/{a} 6/{b} 7/{c}
f 5/{a} 7/{c} 8/{d}
"""


@pytest.mark.parametrize("vt, second, corners, warned", [
    ("vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1", "blue", (1, 2, 3, 4), True),  # each over the whole square
    ("vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvt 2 0\nvt 3 0\nvt 3 1\nvt 2 1", "blue", (5, 6, 7, 8), True),  # repeated
    ("vt 0 0\nvt .5 0\nvt .5 1\nvt 0 1\nvt .5 0\nvt 1 0\nvt 1 1\nvt .5 1", "blue", (5, 6, 7, 8), False),  # halves
    ("vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1", "red", (1, 2, 3, 4), False),  # one material, its uv shared by two parts
])
def test_materials_sharing_texture_space_are_warned_of(tmp_path, vt, second, corners, warned):
    """A file whose materials each lay out the whole uv square (their own textures, in the file)
    would have both fitted into pbrfit's one set of maps: the load says so; a material's texture
    coordinates repeated a square over (the maps repeat) count as the same space; materials in
    their own halves, or one material over two parts, load quietly."""
    import warnings

    (tmp_path / "m.mtl").write_text("newmtl red\nKd 1 0 0\nnewmtl blue\nKd 0 0 1\n")
    a, b, c, d = corners
    (tmp_path / "q.obj").write_text(_TWO_QUADS.format(vt=vt, second=second, a=a, b=b, c=c, d=d))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = load_mesh(tmp_path / "q.obj")
    said = [str(w.message) for w in caught]
    assert len(mesh.faces) == 4
    if warned:
        assert len(said) == 1 and "materials 'blue' and 'red' use the same texture space (100% of 'blue'" in said[0], said
    else:
        assert not said, said
    with warnings.catch_warnings(record=True) as caught:  # a uniform fit reads no maps: nothing to say
        warnings.simplefilter("always")
        load_mesh(tmp_path / "q.obj", require_uv=False)
    assert not caught


@pytest.mark.parametrize("names, told", [((None, None), ("material 0", "material 1")),
                                          (("Material", "Material"), ("Material", "Material (material 1)"))])
def test_gltf_materials_are_told_apart_whatever_their_names(tmp_path, names, told):
    """glTF materials need no name, nor different ones: each is known by its index where its
    name does not tell it apart, so two of them over the same uv square are warned of too."""
    import trimesh
    from trimesh.visual.material import PBRMaterial
    from trimesh.visual.texture import TextureVisuals

    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    scene = trimesh.Scene()
    for k, (name, color) in enumerate(zip(names, ([255, 0, 0, 255], [0, 0, 255, 255]))):
        visual = TextureVisuals(uv=uv, material=PBRMaterial(name=name, baseColorFactor=color))
        scene.add_geometry(trimesh.Trimesh(QUAD_POSITIONS + [2.0 * k, 0, 0], faces, visual=visual, process=False),
                           geom_name=f"quad{k}")
    scene.export(tmp_path / "two.glb")
    assert [m.get("name") for m in glb_chunks((tmp_path / "two.glb").read_bytes())[1]["materials"]] == list(names)
    (said,) = _load_warnings(tmp_path / "two.glb")
    pair = re.search(r"materials '([^']+)' and '([^']+)' use the same texture space \(100%", said)
    assert pair and sorted(pair.groups()) == sorted(told), said


def _quads_obj(path, quads):
    """An OBJ (and its MTL) of one flat quad per (material, u0, u1, v0, v1), side by side in
    space, each over its uv rectangle."""
    names = sorted({q[0] for q in quads})
    (path.parent / "q.mtl").write_text("".join(f"newmtl {n}\nKd 1 1 1\n" for n in names))
    lines, groups = ["mtllib q.mtl"], {n: [] for n in names}
    for k, (name, u0, u1, v0, v1) in enumerate(quads):
        lines += [f"v {2 * k + x} {y} 0" for x, y in ((0, 0), (1, 0), (1, 1), (0, 1))]
        lines += [f"vt {u} {v}" for u, v in ((u0, v0), (u1, v0), (u1, v1), (u0, v1))]
        i = 4 * k + 1
        groups[name] += [f"f {i}/{i} {i + 1}/{i + 1} {i + 2}/{i + 2}", f"f {i}/{i} {i + 2}/{i + 2} {i + 3}/{i + 3}"]
    for name in names:
        lines += [f"usemtl {name}"] + groups[name]
    path.write_text("\n".join(lines) + "\n")


def _load_warnings(path):
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_mesh(path)
    return [str(w.message) for w in caught]


def test_materials_that_only_meet_share_no_texture_space(tmp_path):
    """Materials meeting along seams cover the grid cells the seams cross alike: that is no
    shared space, however narrow the regions (a strip 0.05 wide, a 16 × 16 checker)."""
    _quads_obj(tmp_path / "strip.obj", [("red", 0, 0.5, 0, 1), ("blue", 0.5, 0.55, 0, 1)])
    assert _load_warnings(tmp_path / "strip.obj") == []
    tiles = [("red" if (i + j) % 2 else "blue", i / 16, (i + 1) / 16, j / 16, (j + 1) / 16)
             for i in range(16) for j in range(16)]
    _quads_obj(tmp_path / "checker.obj", tiles)
    assert _load_warnings(tmp_path / "checker.obj") == []


def test_texture_space_repeats_across_the_squares_border(tmp_path):
    """The maps repeat: a quad over u in [0.8, 1.2] reads the texels of u in [0, 0.2] as well,
    so a material over u in [0, 0.15] shares them."""
    _quads_obj(tmp_path / "wrap.obj", [("red", 0.8, 1.2, 0, 1), ("blue", 0, 0.15, 0, 1)])
    (said,) = _load_warnings(tmp_path / "wrap.obj")
    assert re.search(r"materials 'blue' and 'red' use the same texture space \((9\d|100)% of 'blue'", said), said
    _quads_obj(tmp_path / "apart.obj", [("red", 0.8, 1.2, 0, 1), ("blue", 0.3, 0.6, 0, 1)])
    assert _load_warnings(tmp_path / "apart.obj") == []
