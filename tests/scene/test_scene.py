import json
import math
import re
import shutil
import struct

import numpy as np
import pytest

from _capture_fixtures import (
    ANGLE_X,
    H,
    QUAD_POSITIONS,
    QUAD_UV_GLTF,
    W,
    base_capture_dict,
    base_images,
    c2w_looking_at_quad,
    fov_focal,
    write_capture,
    write_quad_glb,
    write_quad_obj,
)
from pbrfit.physics.color import srgb_to_linear
from pbrfit.errors import CaptureError
from pbrfit.io.images import write_image
from pbrfit.scene.mesh import load_mesh
from pbrfit.scene.capture import load_capture


# --- a well-formed capture ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    return write_capture(tmp_path_factory.mktemp("cap") / "capture")


@pytest.fixture(scope="module")
def capture(capture_dir):
    return load_capture(capture_dir)


def test_cameras_from_both_intrinsics_forms(capture):
    c0, c1 = capture.frames[0].camera, capture.frames[1].camera
    f = fov_focal(W, ANGLE_X)
    assert (c0.fx, c0.fy, c0.cx, c0.cy, c0.width, c0.height) == pytest.approx((f, f, W / 2, H / 2, W, H))
    # frame 1 carries its own fl_x and cx; fl_y defaults to fl_x, cy to H/2
    assert (c1.fx, c1.fy, c1.cx, c1.cy) == pytest.approx((10.0, 10.0, 4.5, H / 2))
    np.testing.assert_array_equal(c0.c2w, c2w_looking_at_quad(3.0))


def test_a_crops_principal_point_may_lie_outside_its_image(capture_dir, tmp_path):
    """The spec gives cx, cy no range: the right half of a wider image's frame has its principal
    point left of its own first column, and its rays are those of that half."""
    root = tmp_path / "crop"
    shutil.copytree(capture_dir, root)
    doc = json.loads((root / "capture.json").read_text())
    _frame0(doc).update(fl_x=10.0, cx=-3.0, cy=H + 2.5)
    (root / "capture.json").write_text(json.dumps(doc))
    cam = load_capture(root).frames[0].camera
    assert (cam.cx, cam.cy) == (-3.0, H + 2.5)
    _, d = cam.rays()
    # pixel (row 0, column 0)'s centre sits 3.5 px right of and H + 2 px above the principal point
    expect = cam.c2w[:3, :3] @ np.array([3.5 / 10.0, (H + 2.0) / 10.0, -1.0])
    np.testing.assert_allclose(d[0, 0], expect / np.linalg.norm(expect), atol=1e-12)


def test_images_masks_exposure(capture):
    imgs = base_images()
    f0, f1 = capture.frames
    np.testing.assert_array_equal(f0.image, imgs["images/000.exr"])
    np.testing.assert_array_equal(f1.image, imgs["images/001.exr"][..., :3])
    assert f1.file_path.name == "001.exr"  # extension-less path resolved
    assert f0.mask.dtype == bool and f0.mask.shape == (H, W)
    assert not f0.mask[:, 0].any() and f0.mask[:, 1:].all()  # from mask_path
    assert not f1.mask[0].any() and f1.mask[1:].all()  # from the alpha channel
    assert not f0.saturated.any()  # float files never saturate
    assert f0.exposure == 1.5 and f1.exposure == 0.5  # images.exposure + frames[].exposure
    assert capture.color_space == "linear" and f0.color_space == "linear"
    assert capture.tonemap == "none" and capture.world_up == "+z"


def test_lights_global_frame_and_flash(capture):
    f0, f1 = capture.frames
    assert [l.kind for l in f0.lights] == ["point", "directional", "spot", "point"]
    assert [l.kind for l in f1.lights] == ["point", "directional", "spot", "point", "point"]
    assert len(capture.lights) == 3
    np.testing.assert_allclose(f1.lights[3].position, [0, 0, 2])
    # flash: camera centre + c2w[:3,:3] @ offset
    np.testing.assert_allclose(f0.lights[-1].position, [0.6, 0.5, 3.0], atol=1e-6)
    np.testing.assert_allclose(f1.lights[-1].position, [0.6, 0.5, 2.0], atol=1e-6)
    np.testing.assert_allclose(f0.lights[-1].color, [1, 0.9, 0.8], atol=1e-7)
    assert float(f0.lights[-1].intensity) == 5.0


def test_environment_mesh_and_bookkeeping(capture, capture_dir):
    env = capture.environment
    assert env.file == capture_dir / "env.exr" and env.intensity == 0.5 and env.rotation_deg == 30.0
    assert capture.mesh_path == capture_dir / "mesh.obj" and capture.root == capture_dir
    np.testing.assert_allclose(capture.uv, QUAD_UV_GLTF)
    np.testing.assert_allclose(capture.mesh.vertices, QUAD_POSITIONS)
    assert capture.truth_dir is None and capture.raw["format"] == "pbrfit-capture/1"
    # the same capture through its capture.json path
    again = load_capture(capture_dir / "capture.json")
    assert again.frames[1].camera == capture.frames[1].camera


def test_a_cut_environment_file_is_named_by_its_key(capture_dir, tmp_path):
    """The header reads (the capture loads), the pixels do not: the error names the key that
    gave the file, capture.json's or render's --environment."""
    from pbrfit.render.views import apply_overrides, capture_environment

    root = tmp_path / "c"
    shutil.copytree(capture_dir, root)
    env = root / "env.exr"
    env.write_bytes(env.read_bytes()[:-8])  # the last scanline chunk cut short
    cap = load_capture(root)
    with pytest.raises(CaptureError, match=rf"^{re.escape(str(root / 'capture.json'))}: environment\.file: .*{env.name}"):
        capture_environment(cap)
    with pytest.raises(CaptureError, match=rf"^--environment: .*{env.name}"):
        capture_environment(apply_overrides(cap, env))


def test_truth_dir_and_glb_mesh(tmp_path):
    data = base_capture_dict()
    data["mesh"] = "mesh.glb"
    root = write_capture(tmp_path / "c", data, mesh="glb")
    (root / "truth").mkdir()
    cap = load_capture(root)
    assert cap.truth_dir == root / "truth"
    np.testing.assert_allclose(cap.uv, QUAD_UV_GLTF)


# --- uv orientation: OBJ and glTF agree, in glTF orientation --------------------------------------
def test_obj_and_glb_give_the_same_gltf_uv(tmp_path):
    # trimesh returns v = 0 at the image bottom for both loaders (OBJ vt as stored, glTF
    # TEXCOORD_0 flipped on load); load_mesh returns glTF's orientation for both.
    obj = load_mesh(write_quad_obj(tmp_path / "q.obj"))
    glb = load_mesh(write_quad_glb(tmp_path / "q.glb"))
    glb_nomat = load_mesh(write_quad_glb(tmp_path / "n.glb", material=False))
    for mesh in (obj, glb, glb_nomat):
        np.testing.assert_allclose(mesh.vertices, QUAD_POSITIONS)
        np.testing.assert_allclose(mesh.visual.uv, QUAD_UV_GLTF)  # TEXCOORD_0 as stored in the GLB
        np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])
        assert mesh.metadata["uv_orientation"] == "gltf"
    # vertex 3, top-left corner in 3-D (y = 1), sits at the top of the texture: smallest v
    assert np.argmin(obj.visual.uv[:, 1]) in (2, 3)


@pytest.mark.parametrize("kind", ["obj", "glb"])
def test_gbuffer_sees_texture_top_at_image_top(tmp_path, kind):
    # End to end through gbuffer: the quad's top edge (y = 1, v = 0.25) is at the top of the
    # view, its bottom edge (y = 0, v = 1) at the bottom, for both mesh formats.
    from pbrfit.scene.gbuffer import compute_gbuffer

    data = base_capture_dict()
    data["mesh"] = f"mesh.{kind}"
    cap = load_capture(write_capture(tmp_path / "c", data, mesh=kind))
    g = compute_gbuffer(cap.mesh, cap.frames[0].camera, (), backend="numpy")
    column = g.uv[:, W // 2, 1][g.hit[:, W // 2]]
    assert len(column) >= 3 and np.all(np.diff(column) > 0)  # v grows down the image
    assert 0.25 <= column.min() < 0.4 and 0.85 < column.max() <= 1.0


def test_scene_nodes_are_concatenated_with_transforms(tmp_path):
    mesh = load_mesh(write_quad_glb(tmp_path / "two.glb", nodes=[[0, 0, 0], [2, 0, 0]]))
    assert len(mesh.vertices) == 8 and len(mesh.faces) == 4
    blocks = sorted([mesh.vertices[:4], mesh.vertices[4:]], key=lambda b: b[0, 0])  # node order is trimesh's
    np.testing.assert_allclose(blocks[0], QUAD_POSITIONS)
    np.testing.assert_allclose(blocks[1], QUAD_POSITIONS + [2, 0, 0])
    np.testing.assert_allclose(mesh.visual.uv, np.concatenate([QUAD_UV_GLTF] * 2))
    np.testing.assert_array_equal(mesh.faces[2:], [[4, 5, 6], [4, 6, 7]])


# --- glTF attributes stored as integers, and texture transforms -----------------------------------
def _quantized_quad(path, uv_values, uv_component, uv_stride=None, positions_short=False, transform=None,
                    external=False, sparse_uv=None):
    """The quad written by hand with TEXCOORD_0 stored as normalized integers of glTF type
    ``uv_component`` (5121 unsigned byte, 5123 unsigned short) with an optional byteStride,
    positions optionally as normalized signed shorts, an optional KHR_texture_transform on the
    base colour texture, as .glb or (``external``) .gltf with a .bin file."""
    divisor = {5121: 255, 5123: 65535}[uv_component]
    dtype = {5121: np.uint8, 5123: np.uint16}[uv_component]
    uv_q = np.round(np.asarray(uv_values) * divisor).astype(dtype)
    if uv_stride:  # pad each element to the stride
        padded = np.zeros((len(uv_q), uv_stride), np.uint8)
        padded[:, :uv_q.itemsize * 2] = uv_q.view(np.uint8).reshape(len(uv_q), -1)
        uv_bytes = padded.tobytes()
    else:
        uv_bytes = uv_q.tobytes()
    if positions_short:
        pos_bytes = np.round(QUAD_POSITIONS * 32767).astype(np.int16)
        pos_bytes = np.concatenate([pos_bytes, np.zeros((4, 1), np.int16)], axis=1).tobytes()  # 8-byte stride
        pos_acc = {"componentType": 5122, "normalized": True}
    else:
        pos_bytes, pos_acc = QUAD_POSITIONS.tobytes(), {"componentType": 5126}
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.uint32).tobytes()
    blob = pos_bytes + uv_bytes + faces
    views = [{"buffer": 0, "byteOffset": 0, "byteLength": len(pos_bytes)},
             {"buffer": 0, "byteOffset": len(pos_bytes), "byteLength": len(uv_bytes)},
             {"buffer": 0, "byteOffset": len(pos_bytes) + len(uv_bytes), "byteLength": len(faces)}]
    if positions_short:
        views[0]["byteStride"] = 8
    if uv_stride:
        views[1]["byteStride"] = uv_stride
    uv_acc = {"bufferView": 1, "componentType": uv_component, "normalized": True, "count": 4, "type": "VEC2"}
    if sparse_uv is not None:  # vertex sparse_uv[0] gets uv sparse_uv[1]
        idx = np.array([sparse_uv[0]], np.uint32).tobytes()
        val = np.round(np.asarray(sparse_uv[1]) * divisor).astype(dtype).tobytes()
        val += b"\0" * (-len(val) % 4)
        views += [{"buffer": 0, "byteOffset": len(blob), "byteLength": 4},
                  {"buffer": 0, "byteOffset": len(blob) + 4, "byteLength": len(val)}]
        blob += idx + val
        uv_acc["sparse"] = {"count": 1, "indices": {"bufferView": 3, "componentType": 5125},
                            "values": {"bufferView": 4}}
    accessors = [{"bufferView": 0, "count": 4, "type": "VEC3", **pos_acc}, uv_acc,
                 {"bufferView": 2, "componentType": 5125, "count": 6, "type": "SCALAR"}]
    texture_info = {"index": 0}
    if transform is not None:
        texture_info["extensions"] = {"KHR_texture_transform": transform}
    tree = {"asset": {"version": "2.0"}, "extensionsUsed": ["KHR_mesh_quantization", "KHR_texture_transform"],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2,
                                        "material": 0}]}],
            "materials": [{"pbrMetallicRoughness": {"baseColorTexture": texture_info}}],
            "textures": [{}], "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0,
            "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors}
    if external:
        (path.parent / "quad data.bin").write_bytes(blob)
        tree["buffers"][0]["uri"] = "quad%20data.bin"
        path.write_text(json.dumps(tree))
        return path
    js = json.dumps(tree).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, 28 + len(js) + len(blob))
                     + struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(blob), 0x004E4942) + blob)
    return path


@pytest.mark.parametrize("component, stride, suffix, positions_short", [
    (5123, None, "glb", False), (5121, 4, "glb", True), (5123, None, "gltf", True)])
def test_normalized_integer_attributes_read_as_their_values(tmp_path, component, stride, suffix, positions_short):
    # KHR_mesh_quantization: trimesh alone reads the integers (uv 65535, positions 32767).
    path = _quantized_quad(tmp_path / f"q.{suffix}", QUAD_UV_GLTF, component, stride, positions_short,
                           external=suffix == "gltf")
    mesh = load_mesh(path)
    step = 1.0 / {5121: 255, 5123: 65535}[component]
    np.testing.assert_allclose(mesh.visual.uv, QUAD_UV_GLTF, atol=step)
    np.testing.assert_allclose(mesh.vertices, QUAD_POSITIONS, atol=1.0 / 32767)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])


def test_sparse_normalized_texture_coordinates(tmp_path):
    # vertex 3's stored uv (0, 0.25) is replaced by the sparse entry (0.5, 0.5)
    mesh = load_mesh(_quantized_quad(tmp_path / "s.glb", QUAD_UV_GLTF, 5123, sparse_uv=(3, [0.5, 0.5])))
    expected = QUAD_UV_GLTF.copy()
    expected[3] = [0.5, 0.5]
    np.testing.assert_allclose(mesh.visual.uv, expected, atol=1e-4)


def test_texture_transform_maps_texture_coordinates(tmp_path):
    # KHR_texture_transform: uv' = T R S uv, R counter-clockwise in glTF's v-down uv space (the
    # text, and the viewers; the README's GLSL listing has the transpose, glTF issue #1563).
    # The README's example: offset (0, 1), rotation pi/2, scale 0.5 show the lower left quadrant.
    transform = {"offset": [0.0, 1.0], "rotation": math.pi / 2, "scale": [0.5, 0.5]}
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], np.float32)
    mesh = load_mesh(_quantized_quad(tmp_path / "t.glb", corners, 5123, transform=transform))
    np.testing.assert_allclose(mesh.visual.uv, [[0, 1], [0, 0.5], [0.5, 0.5], [0.5, 1]], atol=1e-4)
    # CesiumGltf's case: uv (1, 1), offset (5, 12), rotation pi/2, scale (2, 0.5) -> (5.5, 10)
    transform = {"offset": [5.0, 12.0], "rotation": math.pi / 2, "scale": [2.0, 0.5]}
    mesh = load_mesh(_quantized_quad(tmp_path / "c.glb", corners, 5123, transform=transform))
    np.testing.assert_allclose(mesh.visual.uv[2], [5.5, 10.0], atol=1e-4)  # the corner at uv (1, 1)
    u, v = QUAD_UV_GLTF[:, 0], QUAD_UV_GLTF[:, 1]
    # offset and scale alone (the dequantization transform a quantizing writer stores)
    transform = {"offset": [-0.25, 0.5], "scale": [2.0, 0.5]}
    mesh = load_mesh(_quantized_quad(tmp_path / "o.glb", QUAD_UV_GLTF, 5123, transform=transform))
    np.testing.assert_allclose(mesh.visual.uv, np.column_stack([-0.25 + 2 * u, 0.5 + 0.5 * v]), atol=1e-4)
    # a transform for another texture coordinate set leaves TEXCOORD_0 alone
    transform = {"offset": [0.5, 0.5], "texCoord": 1}
    mesh = load_mesh(_quantized_quad(tmp_path / "n.glb", QUAD_UV_GLTF, 5123, transform=transform))
    np.testing.assert_allclose(mesh.visual.uv, QUAD_UV_GLTF, atol=1e-4)


def test_mesh_whose_texture_coordinates_span_no_area_is_refused_for_maps(tmp_path):
    obj = write_quad_obj(tmp_path / "q.obj").read_text()
    lines = obj.splitlines()
    for name, uv in (("same", lambda i: "vt 0.5 0.5"), ("line", lambda i: f"vt {0.25 * i:g} 0.5")):
        vts = iter(range(4))
        text = "\n".join(uv(next(vts)) if line.startswith("vt ") else line for line in lines) + "\n"
        (tmp_path / f"{name}.obj").write_text(text)
        with pytest.raises(CaptureError, match=f"{name}.obj: texture coordinates span no area"):
            load_mesh(tmp_path / f"{name}.obj")
        assert len(load_mesh(tmp_path / f"{name}.obj", require_uv=False).faces) == 2  # a uniform fit needs none
    assert len(load_mesh(tmp_path / "q.obj").faces) == 2


def test_mesh_without_uv_allowed_for_uniform_fits(tmp_path):
    mesh = load_mesh(write_quad_obj(tmp_path / "q.obj", uv=False), require_uv=False)
    assert getattr(mesh.visual, "uv", None) is None


# --- LDR images, color spaces, NaN ---------------------------------------------------------------
def _single_frame(tmp_path, file_path, pixels, dtype, images=None, **frame):
    data = base_capture_dict()
    data.pop("environment")
    data["images"] = images or {}
    data["frames"] = [{"file_path": file_path, "transform_matrix": c2w_looking_at_quad(), **frame}]
    root = write_capture(tmp_path / "c", data, images={})
    rel = file_path if "." in file_path.rsplit("/", 1)[-1] else file_path + ".png"
    (root / rel).parent.mkdir(parents=True, exist_ok=True)
    write_image(root / rel, pixels, dtype)
    return root


@pytest.mark.parametrize("dtype, code_max", [("uint8", 255), ("uint16", 65535)])
def test_png_is_srgb_decoded_and_saturation_marked(tmp_path, dtype, code_max):
    codes = np.random.default_rng(0).integers(0, code_max, size=(H, W, 3))
    codes[2, 3, 1] = code_max
    root = _single_frame(tmp_path, "img.png", codes / code_max, dtype)
    frame = load_capture(root).frames[0]
    assert frame.color_space == "srgb"
    np.testing.assert_allclose(frame.image, srgb_to_linear(codes / code_max), rtol=1e-5, atol=1e-7)
    assert frame.saturated.sum() == 1 and frame.saturated[2, 3]
    assert frame.mask.all()


def test_color_space_override_and_gray_images(tmp_path):
    gray = np.random.default_rng(1).uniform(0, 1, (H, W))
    root = _single_frame(tmp_path, "img.png", gray, "uint8", images={"color_space": "linear"})
    cap = load_capture(root)
    frame = cap.frames[0]
    assert cap.color_space == "linear" and frame.image.shape == (H, W, 3)
    np.testing.assert_allclose(frame.image[..., 2], np.round(gray * 255) / 255, atol=1e-7)


def test_nerf_transforms_json_with_mesh(tmp_path):
    # NeRF-synthetic style: no "format", extension-less RGBA PNG paths, camera_angle_x, extra keys
    root = tmp_path / "nerf"
    (root / "train").mkdir(parents=True)
    write_quad_obj(root / "mesh.obj")
    rgba = np.random.default_rng(2).uniform(0, 1, (H, W, 4))
    rgba[..., 3] = 1.0
    rgba[:2, :, 3] = 0.0
    write_image(root / "train" / "r_0.png", rgba, "uint8")
    data = {"camera_angle_x": ANGLE_X, "mesh": "mesh.obj", "aabb_scale": 4,
            # instant-ngp-style keys besides (none of them changes the cameras)
            "up": [0, 0, 1], "aabb": [[-1, -1, -1], [1, 1, 1]], "render_aabb": [[-1, -1, -1], [1, 1, 1]],
            "n_extra_learnable_dims": 0, "white_transparent": True, "black_transparent": False,
            "orientation_override": 0, "fisheye_crop_radius": 0,
            "frames": [{"file_path": "./train/r_0", "rotation": 0.012,
                        "transform_matrix": c2w_looking_at_quad()}]}  # fmt: skip
    (root / "transforms_train.json").write_text(json.dumps(data))
    cap = load_capture(root / "transforms_train.json")
    frame = cap.frames[0]
    assert frame.file_path == root / "train" / "r_0.png"
    assert cap.color_space == "srgb" and cap.world_up == "+y"
    assert not frame.mask[:2].any() and frame.mask[2:].all()
    assert frame.camera.fx == pytest.approx(fov_focal(W, ANGLE_X))
    # a folder holding only transforms.json loads too
    shutil.copy(root / "transforms_train.json", root / "transforms.json")
    assert load_capture(root).frames[0].file_path == frame.file_path


def test_global_fl_and_camera_angle_y(tmp_path):
    data = base_capture_dict()
    data.pop("camera_angle_x")
    data.update({"fl_x": 7.0, "fl_y": 8.0, "cx": 3.0, "cy": 2.5, "w": W, "h": H})
    root = write_capture(tmp_path / "a", data)
    c0, c1 = (f.camera for f in load_capture(root).frames)
    assert (c0.fx, c0.fy, c0.cx, c0.cy) == (7.0, 8.0, 3.0, 2.5)
    assert (c1.fx, c1.fy, c1.cx, c1.cy) == (10.0, 8.0, 4.5, 2.5)  # frame overrides per key
    data = base_capture_dict()
    data["camera_angle_y"] = 0.6
    c0 = load_capture(write_capture(tmp_path / "b", data)).frames[0].camera
    assert c0.fy == pytest.approx(0.5 * H / math.tan(0.3))
    # both forms, as instant-ngp writes them: accepted when they agree
    data = base_capture_dict()
    data["fl_x"] = fov_focal(W, data["camera_angle_x"]) * 1.001
    c0 = load_capture(write_capture(tmp_path / "c", data)).frames[0].camera
    assert c0.fx == pytest.approx(data["fl_x"])


def test_nan_pixels_on_the_mesh_are_an_error_off_it_harmless(tmp_path):
    from pbrfit.fitting.observations import observations_from_capture
    from pbrfit.render.views import capture_gbuffers

    pixels = np.ones((H, W, 4), np.float32)
    root = _single_frame(tmp_path / "a", "img.exr", pixels, "float")
    hit = np.asarray(capture_gbuffers(load_capture(root), None)[0].hit, bool)
    assert hit.any() and (~hit).any()
    (r_on, c_on), (r_off, c_off) = np.argwhere(hit)[0], np.argwhere(~hit)[0]
    pixels[r_off, c_off, 0] = np.nan  # off the mesh: loads, and fits
    pixels[1, 1, 3] = 0.0  # masked out (alpha 0): never read whatever it holds
    pixels[1, 1, 1] = np.inf
    cap = load_capture(_single_frame(tmp_path / "b", "img.exr", pixels, "float"))
    frame = cap.frames[0]
    assert np.all(np.isfinite(frame.image)) and frame.nonfinite[r_off, c_off] and not frame.nonfinite[1, 1]
    assert observations_from_capture(cap).num_pixels > 0
    pixels[r_on, c_on, 2] = -np.inf  # on the mesh: refused, naming the file and the pixel
    cap = load_capture(_single_frame(tmp_path / "c", "img.exr", pixels, "float"))
    with pytest.raises(CaptureError) as err:
        observations_from_capture(cap)
    message = str(err.value)
    assert "\n" not in message and "frames[0].file_path: 1 pixel(s) on the mesh with NaN or inf values in" in message
    assert f"img.exr (first at row {r_on}, column {c_on})" in message




# --- malformed captures: every one a CaptureError with one line naming the key or file ---------------
def _frame0(d):
    return d["frames"][0]


def _write_text(root, rel, text):
    (root / rel).write_text(text)


MALFORMED = {
    "missing capture.json": (lambda d, r: (r / "capture.json").unlink(), "no capture.json (or transforms.json) in this folder"),
    "bad JSON": (lambda d, r: _write_text(r, "capture.json", '{"format": "pbrfit-capture/1",\n "mesh": }'), "invalid JSON at line 2 column"),
    "top level not an object": (lambda d, r: _write_text(r, "capture.json", "[1, 2]"), "expected a JSON object at the top level"),
    "wrong format": (lambda d, r: d.update(format="pbrfit-capture/2"), "capture.json: format: expected 'pbrfit-capture/1', got 'pbrfit-capture/2'"),
    "missing format": (lambda d, r: d.pop("format"), "capture.json: missing key 'format'"),
    "missing mesh key": (lambda d, r: d.pop("mesh"), "capture.json: missing key 'mesh'"),
    "missing mesh file": (lambda d, r: (r / "mesh.obj").unlink(), "capture.json: mesh: mesh file not found:"),
    "mesh without uv": (lambda d, r: write_quad_obj(r / "mesh.obj", uv=False), "has no texture coordinates (glTF TEXCOORD_0 / OBJ vt)"),
    "unreadable mesh": (lambda d, r: (d.update(mesh="mesh.glb"), _write_text(r, "mesh.glb", "garbage")), "capture.json: mesh: cannot load mesh"),
    "no frames": (lambda d, r: d.update(frames=[]), "capture.json: frames: no frames"),
    "missing frames": (lambda d, r: d.pop("frames"), "capture.json: missing key 'frames'"),
    "missing image": (lambda d, r: (r / "images" / "000.exr").unlink(), "capture.json: frames[0].file_path: image file not found:"),
    "missing extension-less image": (lambda d, r: (r / "images" / "001.exr").unlink(), "capture.json: frames[1].file_path: image file not found: "),
    "unreadable image": (lambda d, r: _write_text(r, "images/000.exr", "not an exr"), "capture.json: frames[0].file_path: cannot read image"),
    "matrix 3x4": (lambda d, r: _frame0(d).update(transform_matrix=c2w_looking_at_quad()[:3]), "capture.json: frames[0].transform_matrix: expected shape 4x4, got 3x4"),
    "matrix ragged": (lambda d, r: _frame0(d).update(transform_matrix=[[1, 0], [0, 1, 0, 0]]), "capture.json: frames[0].transform_matrix: expected a 4x4 array of numbers"),
    "matrix NaN": (lambda d, r: _frame0(d)["transform_matrix"][0].__setitem__(1, float("nan")), "capture.json: frames[0].transform_matrix: non-finite values"),
    "matrix last row": (lambda d, r: _frame0(d)["transform_matrix"].__setitem__(3, [0, 0, 1, 1]), "capture.json: frames[0].transform_matrix: last row must be [0, 0, 0, 1]"),
    "missing transform": (lambda d, r: _frame0(d).pop("transform_matrix"), "capture.json: frames[0]: missing key 'transform_matrix'"),
    "missing file_path": (lambda d, r: _frame0(d).pop("file_path"), "capture.json: frames[0]: missing key 'file_path'"),
    "no intrinsics": (lambda d, r: d.pop("camera_angle_x"), "capture.json: frames[0]: no intrinsics: give camera_angle_x, or fl_x"),
    "bad fov": (lambda d, r: d.update(camera_angle_x=3.5), "capture.json: camera_angle_x: must be in (0, pi) radians"),
    "intrinsics disagree": (lambda d, r: d.update(fl_x=100.0), "capture.json: frames[0]: fl_x 100 disagrees with camera_angle_x"),
    "w disagrees with image": (lambda d, r: d.update(w=16), "capture.json: w: says 16 but image"),
    "negative focal": (lambda d, r: _frame0(d).update(fl_x=-3), "capture.json: frames[0].fl_x: must be > 0"),
    "unknown light type": (lambda d, r: d["lights"][1].update(type="area"), "capture.json: lights[1].type: unknown light type 'area'"),
    "negative intensity": (lambda d, r: d["lights"][0].update(intensity=-1.0), "capture.json: lights[0].intensity: negative intensity"),
    "frame light unknown key": (lambda d, r: d["frames"][1]["lights"][0].update(watts=3), "capture.json: frames[1].lights[0]: unknown key 'watts'"),
    "negative flash intensity": (lambda d, r: d["flash"].update(intensity=-5), "capture.json: flash.intensity: negative intensity"),
    "unknown tonemap": (lambda d, r: d["images"].update(tonemap="filmic"), "capture.json: images.tonemap: unknown tone map 'filmic'"),
    "unknown color space": (lambda d, r: d["images"].update(color_space="rec2020"), "capture.json: images.color_space: unknown color space 'rec2020'"),
    "unknown world_up": (lambda d, r: d.update(world_up="-y"), "capture.json: world_up: unknown value '-y'"),
    "mask size mismatch": (lambda d, r: write_image(r / "masks" / "000.png", np.ones((3, 3)), "uint8"), "capture.json: frames[0].mask_path: mask"),
    "missing mask": (lambda d, r: _frame0(d).update(mask_path="masks/none.png"), "capture.json: frames[0].mask_path: image file not found"),
    "unknown top-level key": (lambda d, r: d.update(meshes="mesh.obj"), "capture.json: unknown key 'meshes' in the top level"),
    "unknown images key": (lambda d, r: d["images"].update(gamma=2.2), "capture.json: images: unknown key 'gamma' in images"),
    "unknown flash key": (lambda d, r: d["flash"].update(power=1), "capture.json: flash: unknown key 'power' in flash"),
    "unknown environment key": (lambda d, r: d["environment"].update(exposure=1), "capture.json: environment: unknown key 'exposure' in environment"),
    "unknown frame key": (lambda d, r: _frame0(d).update(filepath="x"), "capture.json: frames[0]: unknown key 'filepath' in a frame"),
    "missing environment file": (lambda d, r: d["environment"].update(file="sky.hdr"), "capture.json: environment.file: image file not found"),
    "lens distortion": (lambda d, r: d.update(k1=0.1), "capture.json: k1: lens distortion is not supported"),
    "fisheye": (lambda d, r: d.update(is_fisheye=True), "capture.json: is_fisheye: fisheye cameras are not supported"),
    "lights not a list": (lambda d, r: d.update(lights={"type": "point"}), "capture.json: lights: expected a list of lights"),
    "integer beyond float": (lambda d, r: _frame0(d).update(exposure=10 ** 400), "capture.json: frames[0].exposure: expected a finite number, got 1000000"),
    "beyond float32": (lambda d, r: d["lights"][0].update(intensity=1e40), "capture.json: lights[0].intensity: 1e+40 is beyond float32's range"),
    "position beyond float32": (lambda d, r: d["lights"][0].update(position=[1e39, 0, 3]), "capture.json: lights[0].position: 1e+39 is beyond float32's range"),
    "exposure overflows": (lambda d, r: _frame0(d).update(exposure=200), "capture.json: frames[0].exposure: exposure 200.5 EV (with images.exposure) is beyond ±64 EV"),
    "matrix beyond float32": (lambda d, r: _frame0(d)["transform_matrix"][0].__setitem__(3, 1e39), "capture.json: frames[0].transform_matrix: values beyond float32's range"),
    "matrix string": (lambda d, r: _frame0(d)["transform_matrix"][0].__setitem__(0, "1.0"), "capture.json: frames[0].transform_matrix: expected a 4x4 array of numbers, got '1.0' in it"),
    "matrix shear": (lambda d, r: _frame0(d)["transform_matrix"][0].__setitem__(1, _frame0(d)["transform_matrix"][0][1] + 0.5), "capture.json: frames[0].transform_matrix: the camera's axes (rotation columns) are not perpendicular"),
    "matrix mirrored": (lambda d, r: [row.__setitem__(0, -row[0]) for row in _frame0(d)["transform_matrix"][:3]], "capture.json: frames[0].transform_matrix: the camera's axes are mirrored"),
    "JSON nested too deeply": (lambda d, r: _write_text(r, "capture.json", "[" * 100000 + "]" * 100000), "capture.json: invalid JSON: nested too deeply"),
    "binary capture.json": (lambda d, r: (r / "capture.json").write_bytes(b"glTF\x02\x00\x00\x00\xf0\x9f\xff"), "capture.json: not a capture.json: not UTF-8 text"),
    "is_fisheye a string": (lambda d, r: d.update(is_fisheye="false"), "capture.json: is_fisheye: expected true or false, got 'false'"),
    "field of view of 1e-30": (lambda d, r: d.update(camera_angle_x=1e-30), "frames[0]: focal length 8e+30 pixels: above 8.39e+06, every pixel's ray is the same"),
    "key twice": (lambda d, r: _write_text(r, "capture.json", json.dumps(d)[:-1] + ', "mesh": "other.obj"}'), "capture.json: invalid JSON: key 'mesh' twice in one object"),
    "key twice in a frame": (lambda d, r: _write_text(r, "capture.json", json.dumps(d).replace('"file_path"', '"file_path": "x.png", "file_path"', 1)), "capture.json: invalid JSON: key 'file_path' twice in one object"),
    "integer of 5000 digits": (lambda d, r: _write_text(r, "capture.json", json.dumps(d)[:-1] + ', "camera_angle_y": ' + "9" * 5000 + "}"), "capture.json: invalid JSON: an integer of more than 4300 digits"),
    # 550 levels: json.loads takes them from the stack depth a test runs at (under xdist too), the
    # null-stripping walk (two frames a level) does not
    "JSON nested deeper than Python walks": (lambda d, r: _write_text(r, "capture.json", json.dumps(d)[:-1] + ', "deep": ' + "[" * 550 + "]" * 550 + "}"), "json: invalid capture: JSON nested too deeply"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_capture(tmp_path, case):
    mutate, fragment = MALFORMED[case]
    data = base_capture_dict()
    root = write_capture(tmp_path / "cap", data)
    before = (root / "capture.json").read_bytes()
    mutate(data, root)
    if (root / "capture.json").exists() and (root / "capture.json").read_bytes() == before:
        (root / "capture.json").write_text(json.dumps(data))
    with pytest.raises(CaptureError) as info:
        load_capture(root)
    message = str(info.value)
    assert fragment in message, message
    assert "\n" not in message


def test_a_scaled_camera_frame_is_the_same_camera(tmp_path):
    """A scale on the camera's axes (a scaled camera object in Blender) changes no ray."""
    data = base_capture_dict()
    plain = load_capture(write_capture(tmp_path / "a", data))
    m = np.array(_frame0(data)["transform_matrix"], float)
    m[:3, :3] *= np.array([2.0, 0.5, 3.0])
    _frame0(data)["transform_matrix"] = m.tolist()
    scaled = load_capture(write_capture(tmp_path / "b", data))
    np.testing.assert_allclose(scaled.frames[0].camera.c2w, plain.frames[0].camera.c2w, atol=1e-12)


def test_capture_path_not_found(tmp_path):
    with pytest.raises(CaptureError, match="capture not found"):
        load_capture(tmp_path / "nope" / "capture.json")


def test_malformed_cases_are_many_and_distinct():
    assert len(MALFORMED) >= 14
    assert len({fragment for _, fragment in MALFORMED.values()}) == len(MALFORMED)


@pytest.mark.parametrize("case", ["missing format", "matrix 3x4", "unknown light type", "mask size mismatch", "no frames"])
def test_cli_exits_2_with_one_line_and_writes_nothing(tmp_path, capsys, case):
    from pbrfit.cli.main import main

    mutate, fragment = MALFORMED[case]
    data = base_capture_dict()
    root = write_capture(tmp_path / "cap", data)
    mutate(data, root)
    (root / "capture.json").write_text(json.dumps(data))
    out = tmp_path / "out"
    status = main(["render", str(root), "--material", str(tmp_path / "material"), "--out", str(out), "--no-cache"])
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("pbrfit: error: ") and err.count("\n") == 1 and fragment in err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["cap"]


def test_premultiplied_exr_edge_pixels_are_unpremultiplied(tmp_path):
    rgb = np.full((H, W, 3), 0.6, np.float32)
    alpha = np.ones((H, W, 1), np.float32)
    alpha[0] = 0.0
    alpha[1, :4] = 0.25  # partly covered: stored premultiplied, 0.6 * 0.25
    alpha[2, :2] = 0.002  # barely covered, still "nonzero = use the pixel"
    root = _single_frame(tmp_path, "img.exr", np.concatenate([rgb * alpha, alpha], -1), "float")
    frame = load_capture(root).frames[0]
    np.testing.assert_allclose(frame.image[1:], 0.6, rtol=1e-6)
    assert not frame.mask[0].any() and frame.mask[1:].all()
    # a PNG's alpha is unassociated: its color is taken as stored
    codes = np.concatenate([np.full((H, W, 3), 0.6), alpha], -1)
    frame = load_capture(_single_frame(tmp_path / "png", "img.png", codes, "uint16")).frames[0]
    np.testing.assert_allclose(frame.image[1], srgb_to_linear(np.float32(round(0.6 * 65535) / 65535)), rtol=1e-5)


def test_frames_of_mixed_file_types_keep_their_own_color_spaces(tmp_path):
    # the spec's default color space is by file type, frame by frame: EXR linear, PNG sRGB
    data = base_capture_dict()
    data["images"].pop("color_space")
    data["frames"][1]["file_path"] = "images/001.png"
    root = write_capture(tmp_path / "cap", data)
    codes = np.random.default_rng(1).integers(0, 255, size=(H, W, 3)) / 255.0
    write_image(root / "images" / "001.png", codes, "uint8")
    cap = load_capture(root)
    assert [f.color_space for f in cap.frames] == ["linear", "srgb"]
    assert cap.color_space == "linear"  # residuals in linear: the PNG frame is compared decoded
    np.testing.assert_allclose(cap.frames[1].image, srgb_to_linear(codes.astype(np.float32)), rtol=1e-5, atol=1e-7)


def test_rgba_mask_uses_its_alpha_too(tmp_path):
    mask = np.ones((H, W, 4), np.float32)
    mask[:2, :, 3] = 0.0  # white RGB, alpha holds the mask
    mask[:, :1, :3] = 0.0  # black RGB, opaque
    root = _single_frame(tmp_path, "img.exr", np.full((H, W, 3), 0.5, np.float32), "float", mask_path="m.png")
    write_image(root / "m.png", mask, "uint8")
    used = load_capture(root).frames[0].mask
    assert not used[:2].any() and not used[:, 0].any() and used[2:, 1:].all()


def test_frames_without_mask_or_alpha_leave_out_the_silhouette(tmp_path):
    from pbrfit.scene.gbuffer import silhouette
    from pbrfit.render.views import capture_gbuffers, capture_views

    rgb = np.ones((H, W, 3), np.float32)
    cap = load_capture(_single_frame(tmp_path / "a", "img.exr", rgb, "float"))
    assert cap.frames[0].mask_source == "none"
    hit = np.asarray(capture_gbuffers(cap, None)[0].hit, bool)
    ring = silhouette(hit)
    assert ring.any() and (hit & ~ring).any()
    used = np.asarray(capture_views(cap, capture_gbuffers(cap, None))[0].pixel)
    np.testing.assert_array_equal(np.sort(used), np.flatnonzero((hit & ~ring).reshape(-1)))
    # with an alpha channel (or a mask file) the mask says which pixels hold the surface: all kept
    cap = load_capture(_single_frame(tmp_path / "b", "img.exr", np.concatenate([rgb, rgb[..., :1]], -1), "float"))
    assert cap.frames[0].mask_source == "alpha"
    used = np.asarray(capture_views(cap, capture_gbuffers(cap, None))[0].pixel)
    assert used.size == hit.sum()


def test_fl_y_with_camera_angle_x(tmp_path):
    """A given fl_y is the vertical focal length with `camera_angle_x` too (it was dropped)."""
    data = base_capture_dict()
    data["fl_y"] = 7.0
    data["frames"][1].pop("fl_x")
    data["frames"][1]["fl_y"] = 9.0
    c0, c1 = (f.camera for f in load_capture(write_capture(tmp_path / "a", data)).frames)
    f = fov_focal(W, ANGLE_X)
    assert (c0.fx, c0.fy) == pytest.approx((f, 7.0)) and (c1.fx, c1.fy) == pytest.approx((f, 9.0))


def test_null_keys_count_as_absent(tmp_path):
    data = base_capture_dict()
    data.update(images=None, lights=None, world_up=None)
    data["frames"][0].update(mask_path=None, lights=None, exposure=None)
    data["frames"][1].update(cx=None)
    data["environment"]["rotation_deg"] = None
    data["extras"] = {"note": None}  # left as written
    cap = load_capture(write_capture(tmp_path / "a", data))
    assert cap.lights == () and cap.color_space == "linear" and cap.world_up == "+y"
    assert cap.frames[0].mask_source == "none" and cap.frames[0].exposure == 0.0 and cap.frames[1].camera.cx == W / 2
    assert cap.environment.rotation_deg == 0.0
    data = base_capture_dict()
    data["mesh"] = None  # a required key: missing
    with pytest.raises(CaptureError, match="missing key 'mesh'"):
        load_capture(write_capture(tmp_path / "b", data))


def test_mask_values_other_than_zero_use_the_pixel(tmp_path):
    mask = np.full((H, W, 1), -1.0, np.float32)  # nonzero: used
    mask[:, :2] = 0.0
    mask[0, 5] = np.nan  # not a value: not used
    root = _single_frame(tmp_path, "img.exr", np.full((H, W, 3), 0.5, np.float32), "float", mask_path="m.exr")
    write_image(root / "m.exr", mask, "float")
    used = load_capture(root).frames[0].mask
    assert not used[:, :2].any() and not used[0, 5] and used[1:, 2:].all()


def test_premultiplied_tiff_colour_is_used_under_any_nonzero_alpha(tmp_path):
    """A 16-bit TIFF (premultiplied unless it says otherwise) with alpha under 1/256 on its first
    row: those pixels are used, as the spec's "nonzero = use the pixel" says, and their colour is
    divided by alpha (98 codes of colour under alpha 0.003: 0.5 to within half a code's ratio)."""
    import OpenImageIO as oiio

    rgba = np.ones((H, W, 4), np.float32)
    rgba[..., :3] = 0.5
    rgba[0, :, 3] = 0.003
    rgba[0, :, :3] = 0.003 * 0.5
    rgba[1, :, 3] = 0.0
    root = _single_frame(tmp_path, "img.exr", np.zeros((H, W, 3), np.float32), "float")
    doc = json.loads((root / "capture.json").read_text())
    doc["frames"][0]["file_path"] = "img.tif"
    (root / "capture.json").write_text(json.dumps(doc))
    out = oiio.ImageOutput.create(str(root / "img.tif"))
    assert out.open(str(root / "img.tif"), oiio.ImageSpec(W, H, 4, "uint16")) and out.write_image(rgba)
    out.close()
    frame = load_capture(root).frames[0]
    assert frame.color_space == "linear"
    assert frame.mask[0].all() and not frame.mask[1].any() and frame.mask[2:].all()
    np.testing.assert_allclose(frame.image[0], 0.5, rtol=0.01)
    np.testing.assert_allclose(frame.image[2:], 0.5, atol=1e-4)


def test_premultiplied_float_colour_is_used_under_any_nonzero_alpha(tmp_path):
    """Float colour is divided by any nonzero alpha (the spec: nonzero = use the pixel)."""
    rgba = np.full((H, W, 4), 1.0, np.float32)
    rgba[0, :, 3] = 1e-3
    rgba[0, :, :3] = 1e-3 * 0.5
    rgba[1, :, 3] = 0.5  # partly covered: the colour is divided by alpha
    rgba[1, :, :3] = 0.25
    rgba[2, :, 3] = 0.0
    rgba[3, :2, 3], rgba[3, :2, :3] = 1e-38, 5.0  # too bright for float32 once divided: not used
    frame = load_capture(_single_frame(tmp_path, "img.exr", rgba, "float")).frames[0]
    assert frame.mask[:2].all() and not frame.mask[2].any() and frame.mask[4:].all()
    assert not frame.mask[3, :2].any() and frame.mask[3, 2:].all() and np.all(np.isfinite(frame.image))
    np.testing.assert_allclose(frame.image[:2], 0.5, rtol=1e-6)


def _write_cropped_exr(path, crop, origin, display):
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(crop.shape[1], crop.shape[0], crop.shape[2], "float")
    spec.x, spec.y = origin
    spec.full_x, spec.full_y, spec.full_width, spec.full_height = display
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(crop)
    out.close()


def test_exr_data_window_is_placed_in_the_display_window(tmp_path):
    """A cropped OpenEXR (data window inside the display window, as compositors write): the camera
    is the display window's, and pixels outside the data window leave the objective, whatever
    the mask's source; the silhouette rule for images without a mask still applies."""
    from pbrfit.io.images import read_image, read_image_info

    root = _single_frame(tmp_path, "img.exr", np.zeros((H, W, 3), np.float32), "float")
    crop = np.arange(3 * 4 * 3, dtype=np.float32).reshape(3, 4, 3) + 1.0
    _write_cropped_exr(root / "img.exr", crop, (2, 1), (0, 0, W, H))
    pixels, info = read_image(root / "img.exr")
    assert pixels.shape == (H, W, 3) and (info.width, info.height, info.data_window) == (W, H, (2, 1, 6, 4))
    assert read_image_info(root / "img.exr") == info
    np.testing.assert_array_equal(pixels[1:4, 2:6], crop)
    assert pixels.sum() == crop.sum()
    frame = load_capture(root).frames[0]
    assert (frame.camera.width, frame.camera.height) == (W, H) and frame.camera.cx == W / 2
    expected = np.zeros((H, W), bool)
    expected[1:4, 2:6] = True
    np.testing.assert_array_equal(frame.mask, expected)
    assert frame.mask_source == "none"
    # with a mask file the data window still bounds what is observed
    data = json.loads((root / "capture.json").read_text())
    data["frames"][0]["mask_path"] = "m.png"
    (root / "capture.json").write_text(json.dumps(data))
    write_image(root / "m.png", np.ones((H, W, 1), np.float32), "uint8")
    np.testing.assert_array_equal(load_capture(root).frames[0].mask, expected)
    # overscan: a data window larger than the display window is cut to it
    big = np.random.default_rng(0).uniform(size=(H + 4, W + 2, 3)).astype(np.float32)
    _write_cropped_exr(root / "img.exr", big, (-1, -2), (0, 0, W, H))
    pixels, info = read_image(root / "img.exr")
    np.testing.assert_array_equal(pixels, big[2 : 2 + H, 1 : 1 + W])
    assert info.data_window == (0, 0, W, H)


def test_png_offsets_do_not_move_the_image(tmp_path):
    """PNG's oFFs (ImageMagick keeps a crop's offset there) places an image on a page; it is not
    a crop of the camera's frame, so the pixels are read as stored."""
    import struct
    import zlib

    import OpenImageIO as oiio

    from pbrfit.io.images import read_image

    pixels = np.random.default_rng(1).integers(0, 255, size=(H, W, 3)) / 255.0
    write_image(tmp_path / "plain.png", pixels, "uint8")
    data = (tmp_path / "plain.png").read_bytes()
    body = struct.pack(">iiB", 3, 2, 0)  # x, y offset in pixels
    chunk = struct.pack(">I", len(body)) + b"oFFs" + body + struct.pack(">I", zlib.crc32(b"oFFs" + body))
    (tmp_path / "o.png").write_bytes(data[:33] + chunk + data[33:])  # after the signature and IHDR
    inp = oiio.ImageInput.open(str(tmp_path / "o.png"))
    offset = (inp.spec().x, inp.spec().y)
    inp.close()
    assert offset == (3, 2)  # OpenImageIO reports the offset as the data window's origin
    read, info = read_image(tmp_path / "o.png")
    np.testing.assert_allclose(read, pixels, atol=1e-6)
    assert info.data_window is None and (info.width, info.height) == (W, H)


def test_cropped_material_exr_is_refused(tmp_path):
    from pbrfit.io.material_files import read_map

    _write_cropped_exr(tmp_path / "roughness.exr", np.ones((2, 2, 1), np.float32), (1, 1), (0, 0, 4, 4))
    with pytest.raises(CaptureError, match="cropped OpenEXR"):
        read_map(tmp_path, "roughness")


def test_occlusion_and_emissive_maps_are_checked_like_the_others(tmp_path):
    from pbrfit.io.images import write_image
    from pbrfit.io.material_files import read_material, write_material
    from pbrfit.physics.material import Material

    m = Material.uniform([0.5, 0.5, 0.5], 0.0, 0.5, size=2)
    write_material(tmp_path, m)
    for name, pixels, message in (
            ("occlusion.exr", np.full((2, 2, 1), np.nan, np.float32), "occlusion.exr: 4 texels of occlusion hold NaN or inf"),
            ("occlusion.exr", np.full((2, 2, 1), 1.5, np.float32), r"occlusion.exr: occlusion must lie in \[0, 1\]"),
            ("emissive.exr", np.full((2, 2, 3), -0.1, np.float32), r"emissive.exr: emissive must lie in \[0, inf\)"),
            ("emissive.exr", np.full((2, 2, 2), 1.0, np.float32), "emissive.exr: expected 3 channels, found 2")):
        write_image(tmp_path / name, pixels, "float")
        with pytest.raises(CaptureError, match=message):
            read_material(tmp_path)
        (tmp_path / name).unlink()
    _write_cropped_exr(tmp_path / "occlusion.exr", np.ones((1, 1, 1), np.float32), (1, 1), (0, 0, 2, 2))
    with pytest.raises(CaptureError, match="occlusion.exr: the data window .* cropped OpenEXR"):
        read_material(tmp_path)
    write_image(tmp_path / "occlusion.exr", np.full((2, 2, 1), 0.25, np.float32), "float")
    write_image(tmp_path / "emissive.exr", np.full((2, 2, 3), 4.0, np.float32), "float")  # HDR emission is fine
    got = read_material(tmp_path)
    assert float(got.occlusion.max()) == 0.25 and float(got.emissive.min()) == 4.0


def test_mesh_with_non_finite_values_or_an_unknown_format_is_refused(tmp_path):
    obj = write_quad_obj(tmp_path / "q.obj").read_text()
    (tmp_path / "uv.obj").write_text(obj.replace("vt 0 0\n", "vt nan nan\n", 1))
    with pytest.raises(CaptureError, match="1 texture coordinates hold NaN or inf"):
        load_mesh(tmp_path / "uv.obj")
    (tmp_path / "v.obj").write_text(obj.replace("v 0 0 0\n", "v 0 0 nan\n", 1))
    with pytest.raises(CaptureError, match="1 vertex positions hold NaN or inf"):
        load_mesh(tmp_path / "v.obj")
    (tmp_path / "m.xyz").write_text("0 0 0\n")
    with pytest.raises(CaptureError, match="unsupported mesh format '.xyz'; pbrfit reads .glb, .gltf, .obj"):
        load_mesh(tmp_path / "m.xyz")


@pytest.mark.parametrize("suffix", [".glb", ".obj", ".ply"])
def test_mesh_normals_from_the_file_or_else_trimeshs(tmp_path, suffix):
    """Normals the file gives are kept; without them, trimesh's (the spec's loader): the
    angle-weighted mean of the faces' normals at each shared vertex, as Mitsuba computes them,
    not glTF 2.0's flat ones (docs/conventions.md, where the spec is silent)."""
    import trimesh

    # a ridge along z: two slopes, the crest's vertices shared by both (a right angle of each)
    v = np.array([[-1, 0, -1], [0, 0.5, -1], [1, 0, -1], [-1, 0, 1], [0, 0.5, 1], [1, 0, 1]], float)
    f = np.array([[0, 3, 1], [1, 3, 4], [1, 4, 2], [2, 4, 5]])
    uv = np.c_[(v[:, 0] + 1) / 2, (v[:, 2] + 1) / 2]
    ridge = trimesh.Trimesh(v, f, visual=trimesh.visual.TextureVisuals(uv=uv), process=False)
    ply = suffix == ".ply"
    ridge.export(tmp_path / f"bare{suffix}", **(dict(vertex_normal=False) if ply else dict(include_normals=False)))
    bare = load_mesh(tmp_path / f"bare{suffix}")
    assert len(bare.vertices) == 6
    crest = np.abs(bare.vertices[:, 0]) < 1e-9
    np.testing.assert_allclose(bare.vertex_normals[crest], [[0, 1, 0]] * 2, atol=1e-6)
    given = np.tile(np.array([[0.6, 0.8, 0.0]]), (6, 1))
    ridge.vertex_normals = given
    ridge.export(tmp_path / f"given{suffix}", **(dict(vertex_normal=True) if ply else {}))
    np.testing.assert_allclose(load_mesh(tmp_path / f"given{suffix}").vertex_normals, given, atol=1e-6)


def _quad_glb(path, edit=None):
    """The fixture quad as a GLB (normals written), its JSON chunk passed through ``edit``."""
    import trimesh

    from pbrfit.scene.gltf_read import glb_chunks, glb_from_chunks

    quad = trimesh.Trimesh(QUAD_POSITIONS, [[0, 1, 2], [0, 2, 3]], process=False)
    quad.vertex_normals  # computed: the export writes them
    version, tree, binary = glb_chunks(quad.export(file_type="glb"))
    if edit is not None:
        edit(tree)
    path.write_bytes(glb_from_chunks(version, tree, binary))
    return path


def test_broken_mesh_structure_is_one_clear_error(tmp_path):
    """Singular or non-finite node transforms, face indices outside the vertices, positions
    beyond what float32 distances hold, a truncated GLB: a CaptureError naming the file."""
    node = lambda **kw: (lambda tree: tree["nodes"][0].update(kw))  # noqa: E731
    # a zero scale hides a node, as in glTF viewers: here the only one, so nothing is left
    with pytest.raises(CaptureError, match="holds no triangles"):
        load_mesh(_quad_glb(tmp_path / "zero.glb", node(scale=[1, 1, 0])), require_uv=False)
    tiny = load_mesh(_quad_glb(tmp_path / "tiny.glb", node(scale=[1e-11] * 3)), require_uv=False)
    np.testing.assert_allclose(tiny.vertices, QUAD_POSITIONS * 1e-11, rtol=1e-6)  # small, not hidden
    with pytest.raises(CaptureError, match="transform holds NaN or inf"):
        load_mesh(_quad_glb(tmp_path / "nan.glb", node(matrix=[float("nan")] * 16)), require_uv=False)
    with pytest.raises(CaptureError, match="vertex positions reach 1e\\+30; pbrfit takes up to 1e\\+18"):
        load_mesh(_quad_glb(tmp_path / "far.glb", node(scale=[1e30] * 3)), require_uv=False)
    short = _quad_glb(tmp_path / "short.glb", lambda tree: tree["accessors"][1].update(count=3))
    with pytest.raises(CaptureError, match=r"short.glb: face indices run from 0 to 3, outside its 3 vertices"):
        load_mesh(short, require_uv=False)
    data = _quad_glb(tmp_path / "whole.glb").read_bytes()
    (tmp_path / "cut.glb").write_bytes(data[: len(data) * 9 // 10])
    with pytest.raises(CaptureError, match=r"cannot load mesh .*cut.glb: malformed GLB file"):
        load_mesh(tmp_path / "cut.glb", require_uv=False)
    ply = ["ply", "format ascii 1.0", "element vertex 4", "property float x", "property float y", "property float z",
           "element face 2", "property list uchar int vertex_indices", "end_header",
           "0 0 0", "1 0 0", "1 1 0", "0 1 0", "3 0 1 2", "3 0 2 {}"]
    for last, low, high in ((9, 0, 9), (-1, -1, 2)):
        (tmp_path / "bad.ply").write_text("\n".join(ply).format(last) + "\n")
        with pytest.raises(CaptureError, match=f"bad.ply: face indices run from {low} to {high}, outside its 4"):
            load_mesh(tmp_path / "bad.ply", require_uv=False)
    # a truncated ASCII PLY: trimesh loads what is there; fewer rows than the header declares
    for rows, element, held in ((ply[:-1], "face", 1), (ply[:-3], "vertex", 3)):
        (tmp_path / "cut.ply").write_text("\n".join(rows).format(3) + "\n")
        with pytest.raises(CaptureError, match=f"cut.ply: the header declares . {element} elements, the file "
                                               f"holds {held}"):
            load_mesh(tmp_path / "cut.ply", require_uv=False)
    # an OBJ written counting from 0: trimesh would read 0 as the last vertex and shift every face
    obj = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
    for faces in ("f 0/0 1/1 2/2\nf 0/0 2/2 3/3\n", "f 1/0 2/1 3/2\n"):
        (tmp_path / "zero.obj").write_text(obj + faces)
        with pytest.raises(CaptureError, match=r"zero.obj: face 'f [0-9/ ]+' has index 0; OBJ indices count from 1"):
            load_mesh(tmp_path / "zero.obj")
    (tmp_path / "one.obj").write_text(obj + "# f 0/0 1/1 2/2\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")  # a comment is no face
    assert len(load_mesh(tmp_path / "one.obj").faces) == 2


def test_gltf_whose_buffer_file_is_missing_names_it(tmp_path):
    path = _quantized_quad(tmp_path / "m.gltf", QUAD_UV_GLTF, 5123, external=True)
    (tmp_path / "quad data.bin").unlink()
    with pytest.raises(CaptureError, match=r"cannot load mesh .*m.gltf: buffer 0: file 'quad data.bin' not found"):
        load_mesh(path)


# --- layered OpenEXR frames: read through their colour layer --------------------------------------
def _write_layered_exr(path, layers: dict) -> None:
    """An OpenEXR whose channels are ``{name: (H, W) values}``, stored in that order."""
    import OpenImageIO as oiio

    names = list(layers)
    spec = oiio.ImageSpec(W, H, len(names), "float")
    spec.channelnames = names
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(np.stack([layers[n] for n in names], axis=-1).astype(np.float32))
    out.close()


def test_layered_exr_frame_is_read_through_its_combined_layer(tmp_path):
    # Blender's multilayer OpenEXR: "ViewLayer.AO.*" sorts before "ViewLayer.Combined.*", and
    # OpenImageIO lists it first; the frame is the Combined pass, its alpha the Combined alpha.
    root = write_capture(tmp_path / "c")
    rgba = base_images()["images/001.exr"]
    layers = {f"ViewLayer.AO.{c}": np.full((H, W), 7.0) for c in "RGB"}
    layers.update({f"ViewLayer.Combined.{c}": rgba[..., k] for k, c in enumerate("RGBA")})
    layers["ViewLayer.Depth.Z"] = np.full((H, W), 3.0)
    _write_layered_exr(root / "images/001.exr", layers)
    frame = load_capture(root).frames[1]
    np.testing.assert_allclose(frame.image[1:], rgba[1:, :, :3], rtol=1e-6)
    assert not frame.mask[0].any() and frame.mask[1:].all()
    # two colour layers, neither plain R, G, B nor a Combined one: which is meant is not guessed
    del layers["ViewLayer.Combined.A"]
    layers = {k.replace("Combined", "Beauty"): v for k, v in layers.items()}
    _write_layered_exr(root / "images/001.exr", layers)
    with pytest.raises(CaptureError, match=r"frames\[1\]\.file_path: image .*001.exr holds several colour layers "
                                           r"\(ViewLayer.AO, ViewLayer.Beauty\)"):
        load_capture(root)
    # one layer and a plain A: that alpha; a grey Y beside a layer: Y
    layers = {"A": rgba[..., 3], **{f"beauty.{c}": rgba[..., k] for k, c in enumerate("RGB")}}
    _write_layered_exr(root / "images/001.exr", layers)
    frame = load_capture(root).frames[1]
    assert not frame.mask[0].any() and frame.mask[1:].all()
    layers = {"Y": rgba[..., 0], **{f"AO.{c}": np.full((H, W), 7.0) for c in "RGB"}}
    _write_layered_exr(root / "images/001.exr", layers)
    np.testing.assert_allclose(load_capture(root).frames[1].image, np.repeat(rgba[..., :1], 3, -1), rtol=1e-6)
    # plain R, G, B beside other layers: those
    layers = {c: rgba[..., k] for k, c in enumerate("RGBA")}
    layers.update({f"AO.{c}": np.full((H, W), 7.0) for c in "RGB"})
    _write_layered_exr(root / "images/001.exr", layers)
    np.testing.assert_allclose(load_capture(root).frames[1].image[1:], rgba[1:, :, :3], rtol=1e-6)
