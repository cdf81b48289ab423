"""Tiny capture fixtures written into tmp folders (no binary files in the repository).

The quad: vertices (0,0,0) (1,0,0) (1,1,0) (0,1,0) in the z = 0 plane, seen from +z. Its
texture coordinates, in glTF orientation (v = 0 at the top row of the image), put the image
upright on the quad, with the top edge at v = 0.25 so that a v flip is visible:
vertex 0 (bottom left) -> (0, 1), vertex 2 (top right) -> (1, 0.25).
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np

from pbrfit.io.images import write_image

QUAD_POSITIONS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
QUAD_UV_GLTF = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.25], [0.0, 0.25]], np.float32)
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def glb_bytes(nodes=None, uv=True, material=True, positions=QUAD_POSITIONS, uvs=QUAD_UV_GLTF) -> bytes:
    """A minimal GLB of the quad, written by hand (not by trimesh) so the test does not
    depend on trimesh's own conventions. ``nodes``: list of translations, one node each."""
    blob = positions.tobytes() + (uvs.tobytes() if uv else b"") + QUAD_FACES.tobytes()
    n_pos, n_uv = positions.nbytes, (uvs.nbytes if uv else 0)
    attributes = {"POSITION": 0}
    views = [{"buffer": 0, "byteOffset": 0, "byteLength": n_pos}]
    accessors = [{"bufferView": 0, "componentType": 5126, "count": len(positions), "type": "VEC3",
                  "min": positions.min(0).tolist(), "max": positions.max(0).tolist()}]
    if uv:
        attributes["TEXCOORD_0"] = 1
        views.append({"buffer": 0, "byteOffset": n_pos, "byteLength": n_uv})
        accessors.append({"bufferView": 1, "componentType": 5126, "count": len(uvs), "type": "VEC2"})
    views.append({"buffer": 0, "byteOffset": n_pos + n_uv, "byteLength": QUAD_FACES.nbytes})
    accessors.append({"bufferView": len(views) - 1, "componentType": 5125, "count": QUAD_FACES.size, "type": "SCALAR"})
    prim = {"attributes": attributes, "indices": len(accessors) - 1}
    tree = {"asset": {"version": "2.0"}, "meshes": [{"primitives": [prim]}],
            "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors}
    if material:
        prim["material"] = 0
        tree["materials"] = [{"pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1]}}]
    if nodes is None:
        nodes = [[0.0, 0.0, 0.0]]
    tree["nodes"] = [{"mesh": 0, "translation": list(map(float, t))} for t in nodes]
    tree["scenes"] = [{"nodes": list(range(len(nodes)))}]
    tree["scene"] = 0
    js = json.dumps(tree).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(blob), 0x004E4942) + blob)


def write_quad_glb(path: Path, **kwargs) -> Path:
    path.write_bytes(glb_bytes(**kwargs))
    return path


def write_quad_obj(path: Path, uv: bool = True) -> Path:
    """The same quad as OBJ: ``vt`` stores v with 0 at the bottom, i.e. 1 - v_gltf."""
    lines = [f"v {p[0]:g} {p[1]:g} {p[2]:g}" for p in QUAD_POSITIONS]
    if uv:
        lines += [f"vt {t[0]:g} {1.0 - t[1]:g}" for t in QUAD_UV_GLTF]
        lines += ["f 1/1 2/2 3/3", "f 1/1 3/3 4/4"]
    else:
        lines += ["f 1 2 3", "f 1 3 4"]
    path.write_text("\n".join(lines) + "\n")
    return path


def read_glb(path: Path) -> tuple[dict, bytes]:
    data = Path(path).read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    tree = json.loads(data[20:20 + json_len])
    bin_len = struct.unpack_from("<I", data, 20 + json_len)[0]
    blob = data[28 + json_len:28 + json_len + bin_len]
    return tree, blob


def glb_accessor(tree: dict, blob: bytes, index: int) -> np.ndarray:
    acc = tree["accessors"][index]
    view = tree["bufferViews"][acc["bufferView"]]
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.frombuffer(blob, dtype, acc["count"] * width, start).reshape(acc["count"], width)


def _quaternion_matrix(q) -> np.ndarray:
    """3 x 3 rotation of the unit quaternion ``q`` = (x, y, z, w), glTF's order."""
    x, y, z, w = (float(c) for c in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def glb_mesh_transforms(tree: dict) -> list[tuple[int, np.ndarray]]:
    """(mesh index, 4 x 4 node-to-scene matrix) for each node of the default scene that holds a
    mesh: the nodes' transforms composed from the scene's roots down, each a ``matrix``
    (column-major) or T * R * S (glTF 2.0, "Transformations")."""

    def local(node: dict) -> np.ndarray:
        if "matrix" in node:
            return np.asarray(node["matrix"], np.float64).reshape(4, 4).T
        m = np.eye(4)
        m[:3, :3] = _quaternion_matrix(node.get("rotation", (0, 0, 0, 1))) * np.asarray(node.get("scale", (1, 1, 1)))
        m[:3, 3] = node.get("translation", (0, 0, 0))
        return m

    found = []

    def visit(index: int, parent: np.ndarray) -> None:
        node = tree["nodes"][index]
        world = parent @ local(node)
        if "mesh" in node:
            found.append((node["mesh"], world))
        for child in node.get("children", []):
            visit(child, world)

    for root in tree["scenes"][tree.get("scene", 0)]["nodes"]:
        visit(root, np.eye(4))
    return found


def glb_image(tree: dict, blob: bytes, texture_index: int) -> np.ndarray:
    from io import BytesIO

    from PIL import Image

    image = tree["images"][tree["textures"][texture_index]["source"]]
    view = tree["bufferViews"][image["bufferView"]]
    start = view.get("byteOffset", 0)
    return np.asarray(Image.open(BytesIO(blob[start:start + view["byteLength"]])))


# --- a complete small capture ------------------------------------------------------------------
W, H = 8, 6
ANGLE_X = 0.8


def c2w_looking_at_quad(z: float = 3.0) -> list[list[float]]:
    return [[1, 0, 0, 0.5], [0, 1, 0, 0.5], [0, 0, 1, z], [0, 0, 0, 1]]


def base_capture_dict() -> dict:
    return {
        "format": "pbrfit-capture/1",
        "mesh": "mesh.obj",
        "world_up": "+z",
        "camera_angle_x": ANGLE_X,
        "frames": [
            {"file_path": "images/000.exr", "transform_matrix": c2w_looking_at_quad(3.0),
             "mask_path": "masks/000.png", "exposure": 1.0},
            {"file_path": "images/001", "transform_matrix": c2w_looking_at_quad(2.0),
             "fl_x": 10.0, "cx": 4.5,
             "lights": [{"type": "point", "position": [0, 0, 2], "intensity": 3.0}]},
        ],
        "lights": [
            {"type": "point", "position": [0, 3, 2], "color": [1, 1, 1], "intensity": 40.0, "range": 0},
            {"type": "directional", "direction": [0, -1, -1], "color": [1, 1, 1], "intensity": 2.0},
            {"type": "spot", "position": [0, 3, 0], "direction": [0, -1, 0], "color": [1, 1, 1],
             "intensity": 40.0, "range": 0, "inner_cone_angle": 0.3, "outer_cone_angle": 0.6},
        ],
        "flash": {"color": [1, 0.9, 0.8], "intensity": 5.0, "offset": [0.1, 0, 0]},
        "environment": {"file": "env.exr", "intensity": 0.5, "rotation_deg": 30.0},
        "images": {"color_space": "linear", "tonemap": "none", "exposure": 0.5},
    }


def base_images(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    img0 = rng.uniform(0, 2, (H, W, 3)).astype(np.float32)
    img1 = rng.uniform(0, 2, (H, W, 4)).astype(np.float32)
    img1[..., 3] = 1.0
    img1[0, :, 3] = 0.0  # top row transparent
    mask0 = np.ones((H, W), np.float32)
    mask0[:, 0] = 0.0  # left column masked out
    return {"images/000.exr": img0, "images/001.exr": img1, "masks/000.png": mask0}


def write_capture(root: Path, data: dict | None = None, images: dict | None = None, mesh: str = "obj") -> Path:
    """Write a capture folder; ``data`` defaults to `base_capture_dict`. Returns the folder."""
    root.mkdir(parents=True, exist_ok=True)
    data = base_capture_dict() if data is None else data
    images = base_images() if images is None else images
    for rel, pixels in images.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        write_image(root / rel, pixels, "float" if rel.endswith((".exr", ".hdr")) else "uint8")
    if mesh == "obj":
        write_quad_obj(root / "mesh.obj")
    elif mesh == "glb":
        write_quad_glb(root / "mesh.glb")
    write_image(root / "env.exr", np.ones((4, 8, 3), np.float32))
    (root / "capture.json").write_text(json.dumps(data))
    return root


def fov_focal(width: int, angle: float) -> float:
    return 0.5 * width / math.tan(0.5 * angle)
