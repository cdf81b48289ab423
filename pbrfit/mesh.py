"""Meshes: loading a capture's triangle mesh (glTF/GLB, OBJ, PLY) with its uv in glTF orientation.

Rules pinned here (tests in ``tests/test_scene.py`` and ``tests/test_mesh.py``):

* Loaded with trimesh without processing (vertex order kept); a scene's meshes are
  concatenated with their node transforms applied. ``mesh.visual.uv`` holds texture
  coordinates in glTF orientation (v = 0 at the top row of the texture image) for every mesh
  format: trimesh's loaders return v = 0 at the bottom for both OBJ (as stored) and glTF
  (TEXCOORD_0 flipped on load), so `load_mesh` flips v back. A glTF primitive without a
  material still keeps its TEXCOORD_0 (trimesh would drop it).
* A glTF attribute stored as normalized integers (KHR_mesh_quantization, as gltfpack writes
  them) is read as the values it stands for (trimesh would read the raw integers): component c
  of an unsigned byte or short is c / 255 or c / 65535, of a signed one max(c / 127, -1) or
  max(c / 32767, -1) (the extension's README, "Encoding quantized data").
* A texture transform (KHR_texture_transform) on a primitive's material applies to its
  TEXCOORD_0: the maps are read at uv' = T R S uv, with the extension's offset o, rotation r
  and scale s: u' = o_u + s_u u cos r + s_v v sin r, v' = o_v - s_u u sin r + s_v v cos r.
  R is counter-clockwise in glTF's uv space (v down), as the extension's text says and
  three.js, Babylon.js, Blender's importer, CesiumGltf and the TextureTransformTest sample
  model apply it; the GLSL listing in the extension's README has its transpose, a known
  erratum (KhronosGroup/glTF#1563). The README's own example agrees: offset (0, 1), rotation
  π/2 and scale 0.5 show the lower left quadrant. A Draco-compressed primitive (its data
  decoded later, by trimesh) with a transform is refused.
  It is taken from the first of the material's textures that reads TEXCOORD_0, in the order
  baseColorTexture, metallicRoughnessTexture, normalTexture, occlusionTexture, emissiveTexture:
  base colour and metallic-roughness are the maps pbrfit fits, and a quantizing writer gives
  every texture of a material the same transform. The uv `load_mesh` returns (and material.glb
  holds) are the transformed ones.
* Other glTF that trimesh alone misreads is read as glTF 2.0 means it (`_prepare_tree`,
  `_gltf_rewrite_primitives`): triangle fans, morph targets under their weights, sparse
  indices, meshes on or under camera nodes, GPU instancing, skinned meshes (drawn at rest); a
  file requiring an extension that changes the geometry and that pbrfit cannot read (Draco
  without DracoPy, meshopt, any unknown one) is refused.
* OBJ text is read as the format means it (`_obj_text`): fields separated by any whitespace,
  comments after an element's fields, ``vt u`` with v = 0; a face index 0 is refused.
"""

from __future__ import annotations

import base64
import contextlib
import io as _io
import json
import re
import struct
import urllib.parse
from pathlib import Path

import numpy as np
from jaxtyping import Float

from .errors import CaptureError

__all__ = ["gltf_file_uris", "load_mesh"]

_GLB_MAGIC = 0x46546C67
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942


def _gltf_default_material(tree: dict) -> bool:
    """Give every primitive with TEXCOORD_0 but no material a default one; True if changed.

    trimesh's glTF loader keeps TEXCOORD_0 only for primitives that name a material.
    """
    missing = [
        prim
        for mesh in tree.get("meshes", [])
        for prim in mesh.get("primitives", [])
        if "material" not in prim and "TEXCOORD_0" in prim.get("attributes", {})
    ]
    if not missing:
        return False
    materials = tree.setdefault("materials", [])
    materials.append({"name": "pbrfit-default"})
    for prim in missing:
        prim["material"] = len(materials) - 1
    return True


def gltf_file_uris(tree: dict):
    """The buffers and images of a parsed glTF that live in files: (kind, index, entry, relative
    file name) for each, its URI percent-decoded (glTF URIs are RFC 3986 references, relative to
    the .gltf); embedded ones (``data:``) are left out."""
    for kind in ("buffers", "images"):
        for i, entry in enumerate(tree.get(kind) or []):
            uri = entry.get("uri") if isinstance(entry, dict) else None
            if isinstance(uri, str) and not uri.startswith("data:"):
                yield kind, i, entry, urllib.parse.unquote(uri)


# --- glTF attributes trimesh reads raw: normalized integers, texture transforms ------------------
#: Normalized integer component types (glTF componentType): (dtype, divisor, signed).
_NORMALIZED = {5120: (np.int8, 127.0, True), 5121: (np.uint8, 255.0, False),
               5122: (np.int16, 32767.0, True), 5123: (np.uint16, 65535.0, False)}
_COMPONENT_DTYPES = {**{k: v[0] for k, v in _NORMALIZED.items()}, 5125: np.uint32, 5126: np.float32}
_TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
#: The textures whose KHR_texture_transform is TEXCOORD_0's, in order of preference.
_TRANSFORM_TEXTURES = (("pbrMetallicRoughness", "baseColorTexture"),
                       ("pbrMetallicRoughness", "metallicRoughnessTexture"),
                       (None, "normalTexture"), (None, "occlusionTexture"), (None, "emissiveTexture"))
_FLOAT = 5126
_UINT32 = 5125
_TRIANGLE_FAN = 6
_INSTANCING = "EXT_mesh_gpu_instancing"
_DRACO = "KHR_draco_mesh_compression"
#: A normal shorter than this has no direction (a skin that flattens the mesh along it): the
#: file's own normal stands in.
NORMAL_FLOOR = 1e-12
#: The file's normals at one position agree where no component differs by more than this
#: (float32 writes of the same vector); else the position is a hard edge (`_file_normals`).
NORMALS_AGREE = 1e-6


def _read_view(tree: dict, buffer, view_index: int, offset: int, component: int, count: int, width: int):
    """(count, width) components of glTF type ``component`` from a buffer view, ``offset`` bytes
    in, following its byteStride; ``buffer(i)`` gives buffer i's bytes."""
    view = tree["bufferViews"][view_index]
    dtype = np.dtype(_COMPONENT_DTYPES[component]).newbyteorder("<")
    size = dtype.itemsize * width
    stride = int(view.get("byteStride") or size)
    start = int(view.get("byteOffset", 0)) + int(offset)
    need = (count - 1) * stride + size if count else 0
    data = buffer(view["buffer"])
    if int(offset) + need > int(view["byteLength"]) or start + need > len(data):
        raise ValueError(f"bufferView {view_index} is shorter than an accessor reads from it")
    raw = np.frombuffer(data, np.uint8, count=need, offset=start)
    rows = np.lib.stride_tricks.as_strided(raw, (count, size), (stride, 1))
    return np.ascontiguousarray(rows).view(dtype).reshape(count, width)


def _read_accessor(tree: dict, buffer, index: int) -> np.ndarray:
    """An accessor's values as float64 (count, width): sparse entries applied, normalized
    integers divided out (`_NORMALIZED`)."""
    acc = tree["accessors"][index]
    component, count, width = acc["componentType"], int(acc["count"]), _TYPE_WIDTHS[acc["type"]]
    if "bufferView" in acc:
        values = _read_view(tree, buffer, acc["bufferView"], acc.get("byteOffset", 0), component, count, width)
    else:
        values = np.zeros((count, width), _COMPONENT_DTYPES[component])
    sparse = acc.get("sparse")
    if sparse:
        values = values.copy()
        ind, val, n = sparse["indices"], sparse["values"], int(sparse["count"])
        rows = _read_view(tree, buffer, ind["bufferView"], ind.get("byteOffset", 0), ind["componentType"], n, 1)
        values[rows[:, 0]] = _read_view(tree, buffer, val["bufferView"], val.get("byteOffset", 0), component, n,
                                        width)
    values = values.astype(np.float64)
    if acc.get("normalized") and component in _NORMALIZED:
        _, divisor, signed = _NORMALIZED[component]
        values = values / divisor
        if signed:
            values = np.maximum(values, -1.0)
    return values


def _texture_transform(tree: dict, primitive: dict):
    """(offset, rotation, scale) of the KHR_texture_transform that maps the primitive's
    TEXCOORD_0 (`_TRANSFORM_TEXTURES`), or None."""
    materials = tree.get("materials") or []
    index = primitive.get("material")
    if not isinstance(index, int) or not 0 <= index < len(materials):
        return None
    material = materials[index]
    for group, key in _TRANSFORM_TEXTURES:
        info = (material.get(group) or {}).get(key) if group else material.get(key)
        if not isinstance(info, dict):
            continue
        transform = (info.get("extensions") or {}).get("KHR_texture_transform")
        if (transform or {}).get("texCoord", info.get("texCoord", 0)) != 0:
            continue
        if transform is None:
            return None
        return (tuple(float(x) for x in transform.get("offset", (0.0, 0.0))), float(transform.get("rotation", 0.0)),
                tuple(float(x) for x in transform.get("scale", (1.0, 1.0))))
    return None


def apply_texture_transform(uv: Float[np.ndarray, "n 2"], offset, rotation: float, scale) -> Float[np.ndarray, "n 2"]:
    """KHR_texture_transform: uv' = T R S uv, u' = o_u + s_u u cos r + s_v v sin r,
    v' = o_v - s_u u sin r + s_v v cos r (glTF orientation, v = 0 at the image's top row; R
    counter-clockwise there, see the module docstring on the README's GLSL erratum)."""
    su, sv = uv[:, 0] * scale[0], uv[:, 1] * scale[1]
    c, s = np.cos(rotation), np.sin(rotation)
    return np.column_stack([offset[0] + c * su + s * sv, offset[1] - s * su + c * sv])


def _scene_nodes(tree: dict) -> list:
    """The nodes of the scene a viewer shows (``scene``, else the first), with their descendants."""
    nodes, scenes = tree.get("nodes") or [], tree.get("scenes") or []
    scene = tree.get("scene", 0)
    roots = scenes[scene].get("nodes", []) if isinstance(scene, int) and 0 <= scene < len(scenes) else []
    seen, stack = set(), list(roots)
    while stack:
        index = stack.pop()
        if isinstance(index, int) and 0 <= index < len(nodes) and index not in seen and isinstance(nodes[index], dict):
            seen.add(index)
            stack.extend(nodes[index].get("children") or [])
    return [nodes[i] for i in sorted(seen)]


def _morph_weights(tree: dict, mesh_index: int, shown: list) -> list:
    """The morph target weights mesh ``mesh_index`` is drawn with by the ``shown`` nodes: their
    ``weights``, else its own, else 0 (glTF 2.0 §3.7.2.2, "Morph Targets"). A ValueError when
    they draw it with different weights: pbrfit reads one shape per mesh."""
    mesh = tree["meshes"][mesh_index]
    default = [float(w) for w in mesh.get("weights") or []]
    drawn = {tuple(float(w) for w in node.get("weights", default)) for node in shown if node.get("mesh") == mesh_index}
    if len(drawn) > 1:
        raise ValueError(f"mesh {mesh_index} is drawn by nodes with different morph target weights "
                         "(pbrfit reads one shape per mesh)")
    return list(drawn.pop()) if drawn else default


def _expand_instances(tree: dict, buffer) -> None:
    """EXT_mesh_gpu_instancing: a node drawing its mesh once per instance, at the node's transform
    times the instance's T R S (its TRANSLATION, ROTATION and SCALE accessors; each defaults to
    the identity), becomes a node with one child per instance holding the mesh."""
    nodes = tree.get("nodes") or []
    for node in list(nodes):
        attributes = (((node.get("extensions") or {}).get(_INSTANCING) or {}).get("attributes") or {}
                      if isinstance(node, dict) else {})
        if not attributes or not isinstance(node.get("mesh"), int):
            continue
        if "skin" in node:
            raise ValueError(f"a skinned node with {_INSTANCING} instances is not supported")
        values = {name: _read_accessor(tree, buffer, index) for name, index in attributes.items()
                  if name in ("TRANSLATION", "ROTATION", "SCALE")}
        counts = {int(tree["accessors"][index]["count"]) for index in attributes.values()}  # custom ones too
        if len(counts) != 1:
            raise ValueError(f"{_INSTANCING}: the instance attributes of a node differ in count")
        children = node.setdefault("children", [])
        for k in range(counts.pop()):
            child = {"mesh": node["mesh"]}
            for name, key in (("TRANSLATION", "translation"), ("ROTATION", "rotation"), ("SCALE", "scale")):
                if name in values:
                    child[key] = values[name][k].tolist()
            if "weights" in node:
                child["weights"] = node["weights"]
            children.append(len(nodes))
            nodes.append(child)
        del node["mesh"]
        node["extensions"].pop(_INSTANCING)


def _local_matrix(node: dict) -> np.ndarray:
    """A glTF node's local transform: its ``matrix`` (column-major), else T R S (rotation a unit
    quaternion x, y, z, w)."""
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T
    x, y, z, w = (float(c) for c in node.get("rotation", (0.0, 0.0, 0.0, 1.0)))
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = rotation * np.asarray(node.get("scale", (1.0, 1.0, 1.0)), np.float64)
    m[:3, 3] = node.get("translation", (0.0, 0.0, 0.0))
    return m


def _global_matrices(tree: dict):
    """global(i): node i's transform in the world, its ancestors' local transforms composed."""
    nodes = tree.get("nodes") or []
    parent = {c: i for i, n in enumerate(nodes) if isinstance(n, dict) for c in n.get("children") or []}
    cache = {}

    def global_matrix(i: int) -> np.ndarray:
        if i not in cache:
            chain = [i]
            while chain[-1] in parent and len(chain) <= len(nodes):  # (a cycle ends at that length)
                chain.append(parent[chain[-1]])
            m = np.eye(4)
            for j in reversed(chain):
                m = m @ _local_matrix(nodes[j])
            cache[i] = m
        return cache[i]

    return global_matrix


def _skin_in_rest_pose(tree: dict, read, store, shown: list) -> None:
    """Skinned meshes as glTF draws them at rest (glTF 2.0 §3.7.3): each vertex at
    Σₖ wₖ Gⱼₖ Bⱼₖ p, with Gⱼ the joint node's global transform, Bⱼ its inverse bind matrix and
    (jₖ, wₖ) the vertex's JOINTS_n / WEIGHTS_n; the transform of the node holding the mesh is
    ignored. Normals go through the inverse transpose of the same blend. The node's mesh moves to
    a new root node of the shown scene, holding a copy whose POSITION and NORMAL are the skinned
    ones (trimesh applies the node's transform and no skin)."""
    nodes, scene = tree.get("nodes") or [], tree.get("scene", 0)
    global_matrix = _global_matrices(tree)
    for node in shown:
        if not (isinstance(node.get("skin"), int) and isinstance(node.get("mesh"), int)):
            continue
        skin = tree["skins"][node["skin"]]
        joints = list(skin.get("joints") or [])
        if "inverseBindMatrices" in skin:
            inverse_bind = read(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
        else:
            inverse_bind = np.tile(np.eye(4), (len(joints), 1, 1))
        matrices = np.stack([global_matrix(j) @ inverse_bind[k] for k, j in enumerate(joints)])
        mesh = dict(tree["meshes"][node["mesh"]])
        mesh["primitives"] = [dict(p, attributes=dict(p.get("attributes") or {})) for p in mesh.get("primitives") or []]
        for primitive in mesh["primitives"]:
            attributes = primitive["attributes"]
            sets = [(attributes[f"JOINTS_{n}"], attributes[f"WEIGHTS_{n}"]) for n in range(8)
                    if f"JOINTS_{n}" in attributes and f"WEIGHTS_{n}" in attributes]
            if not sets or "POSITION" not in attributes:
                continue
            if _DRACO in (primitive.get("extensions") or {}):  # its data is decoded later, by trimesh
                raise ValueError("a skinned Draco-compressed primitive is not supported")
            blend = sum(np.einsum("vk,vkij->vij", read(w), matrices[read(j).astype(np.int64)]) for j, w in sets)
            position = read(attributes["POSITION"])
            attributes["POSITION"] = store(np.einsum("vij,vj->vi", blend[:, :3, :3], position) + blend[:, :3, 3],
                                           "<f4", "VEC3", _FLOAT)
            if "NORMAL" in attributes:
                # n' ∝ A⁻ᵀ n = cof(A) n / det A, cof(A)'s columns the cross products of A's: defined
                # where a joint flattens the mesh too (a zero scale hides a part)
                a = blend[:, :3, :3]
                columns = (np.cross(a[:, :, 1], a[:, :, 2]), np.cross(a[:, :, 2], a[:, :, 0]),
                           np.cross(a[:, :, 0], a[:, :, 1]))
                given = read(attributes["NORMAL"])
                normal = sum(c * given[:, k:k + 1] for k, c in enumerate(columns))
                normal *= np.where(np.linalg.det(a) < 0, -1.0, 1.0)[:, None]
                length = np.linalg.norm(normal, axis=1, keepdims=True)
                normal = np.where(length > NORMAL_FLOOR, normal / np.maximum(length, NORMAL_FLOOR), given)
                attributes["NORMAL"] = store(normal, "<f4", "VEC3", _FLOAT)
        tree["meshes"].append(mesh)
        nodes.append({"mesh": len(tree["meshes"]) - 1})
        tree["scenes"][scene].setdefault("nodes", []).append(len(nodes) - 1)
        del node["mesh"], node["skin"]


def _gltf_rewrite_primitives(tree: dict, buffer, target: int, start: int) -> bytes:
    """Rewrite what trimesh would misread in the primitives as new accessors, their data in
    buffer ``target`` from byte ``start`` on: returns that data (b"" when nothing needs it; the
    caller stores it).

    - POSITION, NORMAL and TEXCOORD_0 stored as normalized integers or sparse accessors, mapped
      by a texture transform, or moved by morph targets under non-zero weights (the attribute
      plus Σ wᵢ targetᵢ, glTF 2.0 §3.7.2.2; trimesh draws the base shape), as float32;
    - sparse indices (applied), as uint32;
    - a TRIANGLE_FAN primitive (mode 6, which trimesh drops) as TRIANGLES with triangles
      (v_{i+1}, v_{i+2}, v_0) (glTF 2.0 §3.7.2.1);
    - GPU instances as nodes (`_expand_instances`), skinned meshes at rest
      (`_skin_in_rest_pose`)."""
    blob = bytearray()
    made, stored = {}, {}
    skinned = bool(tree.get("skins"))  # only skinning reads back what is stored here

    def store(values, dtype, kind: str, component: int) -> int:
        data = np.ascontiguousarray(values, dtype=dtype)
        if skinned:
            stored[len(tree["accessors"])] = np.asarray(values, np.float64).reshape(len(data), -1)
        blob.extend(b"\0" * (-(start + len(blob)) % 4))
        tree.setdefault("bufferViews", []).append({"buffer": target, "byteOffset": start + len(blob),
                                                   "byteLength": data.nbytes})
        blob.extend(data.tobytes())
        entry = {"bufferView": len(tree["bufferViews"]) - 1, "componentType": component,
                 "count": int(len(data)), "type": kind}
        if len(data) and kind != "SCALAR":
            entry.update(min=data.min(axis=0).tolist(), max=data.max(axis=0).tolist())
        tree["accessors"].append(entry)
        return len(tree["accessors"]) - 1

    _expand_instances(tree, buffer)
    shown = _scene_nodes(tree)
    for mesh_index, mesh in enumerate(tree.get("meshes") or []):
        weights = _morph_weights(tree, mesh_index, shown)
        for primitive in mesh.get("primitives") or []:
            attributes = primitive.get("attributes") or {}
            if _DRACO in (primitive.get("extensions") or {}):  # decoded later, by trimesh (with DracoPy)
                if _texture_transform(tree, primitive) is not None:
                    raise ValueError("a KHR_texture_transform on a Draco-compressed primitive is not supported")
                if any(w != 0.0 for w in weights[:len(primitive.get("targets") or [])]):
                    raise ValueError("morph targets on a Draco-compressed primitive are not supported")
                continue
            targets = primitive.get("targets") or []
            for name in ("POSITION", "NORMAL", "TEXCOORD_0"):
                index = attributes.get(name)
                if not isinstance(index, int):
                    continue
                acc = tree["accessors"][index]
                transform = _texture_transform(tree, primitive) if name == "TEXCOORD_0" else None
                morph = tuple((w, t[name]) for w, t in zip(weights, targets)
                              if w != 0.0 and isinstance(t, dict) and isinstance(t.get(name), int))
                normalized = bool(acc.get("normalized")) and acc.get("componentType") in _NORMALIZED
                if not (normalized or morph) and transform is None and "sparse" not in acc:  # (trimesh ignores sparse)
                    continue
                key = (index, transform, morph)
                if key not in made:
                    values = _read_accessor(tree, buffer, index)
                    for w, t in morph:
                        values = values + w * _read_accessor(tree, buffer, t)[:, : values.shape[1]]
                    if transform is not None:
                        values = apply_texture_transform(values[:, :2], *transform)
                    made[key] = store(values, "<f4", acc["type"] if transform is None else "VEC2", _FLOAT)
                attributes[name] = made[key]
            primitive.pop("targets", None)
            indices = primitive.get("indices")
            fan = primitive.get("mode") == _TRIANGLE_FAN
            if isinstance(indices, int) and ("sparse" in tree["accessors"][indices] or fan):
                order = _read_accessor(tree, buffer, indices)[:, 0].astype(np.int64)
                if not fan:
                    primitive["indices"] = store(order, "<u4", "SCALAR", _UINT32)
            if fan:
                if not isinstance(indices, int):
                    order = np.arange(int(tree["accessors"][attributes["POSITION"]]["count"]))
                first = np.full(max(len(order) - 2, 0), order[0] if len(order) else 0)
                triangles = np.stack([order[1:-1], order[2:], first], 1)  # (v_{i+1}, v_{i+2}, v_0)
                primitive["indices"] = store(triangles.reshape(-1), "<u4", "SCALAR", _UINT32)
                primitive["mode"] = 4
        mesh.pop("weights", None)
    for node in tree.get("nodes") or []:
        if isinstance(node, dict):
            node.pop("weights", None)
    if skinned:
        _skin_in_rest_pose(tree, lambda i: stored[i] if i in stored else _read_accessor(tree, buffer, i), store, shown)
    return bytes(blob)


def _buffer_reader(tree: dict, folder: Path, binary=None):
    """buffer(i): glTF buffer i's bytes (a GLB's BIN chunk for a buffer 0 without a uri, else
    its uri: base64 data or a file name relative to ``folder``, already percent-decoded by
    `_file_resolver`), each read once."""
    cache = {}

    def buffer(i: int) -> bytes:
        if i not in cache:
            entry = tree["buffers"][i]
            uri = entry.get("uri")
            if uri is None:
                if i != 0 or binary is None:
                    raise ValueError(f"buffer {i} has neither a uri nor a GLB BIN chunk")
                cache[i] = binary
            elif uri.startswith("data:"):
                head, _, payload = uri.partition(",")
                if not head.endswith(";base64"):
                    raise ValueError(f"buffer {i}: a data: uri that is not base64")
                cache[i] = base64.b64decode(payload)
            else:
                cache[i] = (folder / uri).read_bytes()
        return cache[i]

    return buffer


def _glb_chunks(data: bytes):
    """(version, JSON tree, BIN chunk or None) of a GLB file."""
    magic, version, _ = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC:
        raise ValueError("not a GLB file (bad magic)")
    json_len, chunk_type = struct.unpack_from("<II", data, 12)
    if chunk_type != _CHUNK_JSON:
        raise ValueError("first GLB chunk is not JSON")
    tree = json.loads(data[20 : 20 + json_len])
    at, binary = 20 + json_len, None
    while binary is None and at + 8 <= len(data):  # the first BIN chunk (other kinds are skipped)
        length, kind = struct.unpack_from("<II", data, at)
        if kind == _CHUNK_BIN:
            binary = data[at + 8 : at + 8 + length]
        at += 8 + length
    return version, tree, binary


def _glb_from_chunks(version: int, tree: dict, binary) -> bytes:
    js = json.dumps(tree).encode()
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<II", len(js), _CHUNK_JSON) + js
    if binary is not None:
        binary = bytes(binary) + b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(binary), _CHUNK_BIN) + binary
    return struct.pack("<III", _GLB_MAGIC, version, 12 + len(chunks)) + chunks


def _store_rewritten_primitives(tree: dict, folder: Path, binary):
    """`_gltf_rewrite_primitives` with its data stored: appended to a GLB's BIN chunk (buffer 0),
    else as a new base64 buffer. Returns the (possibly longer) BIN chunk."""
    buffers = tree.setdefault("buffers", [])
    read = _buffer_reader(tree, folder, binary)
    if binary is not None and buffers and "uri" not in buffers[0]:
        blob = _gltf_rewrite_primitives(tree, read, 0, len(binary))
        if blob:
            binary = bytes(binary) + blob
            buffers[0]["byteLength"] = len(binary)
        return binary
    blob = _gltf_rewrite_primitives(tree, read, len(buffers), 0)
    if blob:
        buffers.append({"byteLength": len(blob),
                        "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()})
    return binary


def _file_resolver(tree: dict, folder: Path):
    """A trimesh resolver for the tree's file URIs, which it rewrites to plain file names (glTF
    URIs are percent-encoded and relative to the file, and may lead out of its folder); a
    missing buffer file is named."""
    import trimesh

    for kind, i, entry, name in gltf_file_uris(tree):
        if kind == "buffers" and not (folder / name).is_file():
            raise ValueError(f"buffer {i}: file {name!r} not found (relative to the glTF file)")
        entry["uri"] = name
    try:
        return trimesh.resolvers.FilePathResolver(str(folder), allow_anywhere=True)
    except TypeError:  # an older trimesh: no such option, and no such restriction
        return trimesh.resolvers.FilePathResolver(str(folder))


#: Required glTF extensions (``extensionsRequired``) that leave the geometry as the core spec reads
#: it, or that pbrfit reads itself: materials, textures, lights and metadata are not read (the
#: material is what a fit finds), quantized attributes and TEXCOORD_0's transform are.
_EXTENSIONS_READ = ("KHR_mesh_quantization", "KHR_texture_transform", "KHR_lights_punctual", "KHR_xmp_json_ld",
                    "EXT_mesh_gpu_instancing")
_EXTENSION_PREFIXES_NOT_READ = ("KHR_materials_", "KHR_texture_", "EXT_texture_")


def _prepare_tree(tree: dict) -> None:
    """Check a glTF's required extensions and give trimesh what it reads right.

    A ValueError names the required extensions pbrfit cannot honour (a loader must refuse a file
    that requires one it does not support: compressed geometry would come out empty or zero). Camera nodes lose their camera: trimesh leaves a node
    with a camera and a mesh, and the meshes under it, out of the scene, which glTF viewers
    draw. Primitives with TEXCOORD_0 and no material get a default one (`_gltf_default_material`)."""
    import importlib.util

    read = _EXTENSIONS_READ
    if importlib.util.find_spec("DracoPy") is not None:  # trimesh decodes Draco with it
        read += (_DRACO,)
    required = [name for name in tree.get("extensionsRequired") or []
                if name not in read and not str(name).startswith(_EXTENSION_PREFIXES_NOT_READ)]
    if required:
        hint = (" (write it without compression)" if any("compression" in str(n) for n in required) else "")
        if _DRACO in required:
            hint = " (install DracoPy, with which trimesh decodes Draco, or write it without compression)"
        raise ValueError(f"it requires the glTF extension{'s' if len(required) > 1 else ''} "
                         f"{', '.join(map(str, required))}, which pbrfit does not read{hint}")
    for node in tree.get("nodes") or []:
        if isinstance(node, dict):
            node.pop("camera", None)
    _gltf_default_material(tree)


def _load_gltf_keeping_uv(path: Path):
    import trimesh

    data = path.read_bytes()
    if path.suffix.lower() == ".glb":
        version, tree, binary = _glb_chunks(data)
        resolver = _file_resolver(tree, path.parent)
        _prepare_tree(tree)
        binary = _store_rewritten_primitives(tree, path.parent, binary)
        data = _glb_from_chunks(version, tree, binary)
        return trimesh.load_scene(_io.BytesIO(data), file_type="glb", resolver=resolver, process=False)
    tree = json.loads(data)
    resolver = _file_resolver(tree, path.parent)
    _prepare_tree(tree)
    _store_rewritten_primitives(tree, path.parent, None)
    return trimesh.load_scene(
        _io.BytesIO(json.dumps(tree).encode()), file_type="gltf", resolver=resolver, process=False
    )


#: A node transform whose smallest scale is at most this fraction of its largest is singular (a
#: zero scale, as glTF files hide nodes): float64 rounding of a product of rotations and
#: non-zero scales stays far above it, so a tiny uniform scale (1e-11) is kept.
SINGULAR_SCALE_REL = 1e-12


def _flatten(scene, where: str, path: Path) -> list:
    """The scene's triangle meshes in world space, keeping the file's vertex normals.

    Each geometry node's transform is applied to positions, and its inverse transpose to the
    normals the file holds (trimesh's ``Scene.dump`` would recompute them from the faces, which
    smooths across hard edges and seams). A mesh the file gives no normals gets trimesh's: at
    each vertex the angle-weighted mean of its faces' normals, smooth across shared vertices (as
    Mitsuba computes them; glTF 2.0 §3.7.2.1 would have flat ones). A mirroring transform also
    reverses the winding, and a node whose transform is singular (a zero scale, which hides a
    node in glTF viewers; `SINGULAR_SCALE_REL`) adds nothing. Face indices outside the vertices
    and non-finite transforms raise `CaptureError` (``where``, ``path`` name the file);
    `load_mesh` checks the positions.
    """
    import trimesh

    parts = []
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry.get(name)
        if not isinstance(geom, trimesh.Trimesh) or not len(geom.faces):
            continue
        label = f" (mesh {name!r})" if len(scene.geometry) > 1 else ""
        faces = np.asarray(geom.faces, np.int64)
        if faces.min() < 0 or faces.max() >= len(geom.vertices):
            raise CaptureError(f"{where}: mesh {path}{label}: face indices run from {faces.min()} to {faces.max()}, "
                               f"outside its {len(geom.vertices)} vertices")
        t = np.asarray(transform, np.float64)
        if not np.all(np.isfinite(t)):
            raise CaptureError(f"{where}: mesh {path}{label}: its node's transform holds NaN or inf")
        scales = np.linalg.svd(t[:3, :3], compute_uv=False)
        if scales[0] == 0.0 or scales[-1] <= SINGULAR_SCALE_REL * scales[0]:  # a zero scale: viewers draw nothing
            continue
        normals = _file_normals(geom) @ np.linalg.inv(t[:3, :3])  # (M^-T n) as rows
        normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
        faces = np.asarray(geom.faces, np.int64)
        if np.linalg.det(t[:3, :3]) < 0:
            faces = faces[:, ::-1]
        part = trimesh.Trimesh(
            vertices=trimesh.transform_points(np.asarray(geom.vertices, np.float64), t),
            faces=faces, visual=geom.visual, process=False,
        )
        part.metadata.update(geom.metadata)
        part.metadata["pbrfit_normals"] = normals
        parts.append(part)
    return parts


#: The largest |coordinate| a mesh's world-space vertices may have: the renderer squares distances
#: in float32 (1e18² = 1e36, below float32's 3.4e38).
MAX_COORDINATE = 1e18

#: The triangle-mesh formats read (through trimesh).
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".off", ".stl")


#: Below this total uv area (in units of the texture square) a mesh's texture coordinates lay out
#: nothing: every texel would be seen through no triangle or through all of them.
UV_AREA_MIN = 1e-10


def _uv_area(uv: np.ndarray, faces: np.ndarray) -> float:
    """Σ over triangles of the uv triangle's area, ½ |(uv1 - uv0) × (uv2 - uv0)|."""
    a, b, c = (uv[faces[:, k]] for k in range(3))
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    return float(0.5 * np.sum(np.abs(cross)))


@contextlib.contextmanager
def _quiet_trimesh():
    """No numpy floating-point warnings and no trimesh log records while a mesh loads: what is
    wrong with a file is said once, by `load_mesh`."""
    import logging
    import warnings

    logger = logging.getLogger("trimesh")
    level = logger.level
    logger.setLevel(logging.CRITICAL + 1)
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            yield
    finally:
        logger.setLevel(level)


#: OBJ element lines: their fields are numbers, and a ``#`` ends them.
_OBJ_ELEMENTS = (b"v", b"vt", b"vn", b"vp", b"f", b"l", b"p")
_OBJ_INDENT = re.compile(rb"(?m)^ +")
#: A one-component texture coordinate line, ``vt u`` (after a line break).
_OBJ_ONE_UV = re.compile(rb"(\nvt +[^ \r\n]+) *(?=\r?\n|\Z)")
#: A 0 among an OBJ line's numbers (``f 0 1 2``, ``f 1/0 ...``; `_obj_text` keeps those on face lines).
_OBJ_ZERO = re.compile(rb"[ /][-+]?0+(?=[ /\r\n]|\Z)")


def _line_at(text: bytes, at: int) -> tuple[int, int]:
    """(start, end) of the line of ``text`` holding byte ``at``, without its line break."""
    start = text.rfind(b"\n", 0, at) + 1
    end = text.find(b"\n", at)
    end = len(text) if end < 0 else end
    return start, end - (text[end - 1:end] == b"\r")


def _obj_text(path: Path, where: str) -> bytes:
    """An OBJ file's text as trimesh's parser reads it as the format means it: fields separated by
    tabs as by spaces, indented lines, a comment after an element's fields and a one-component
    texture coordinate ``vt u`` (v = 0) are valid OBJ, which trimesh misreads (drops the line,
    fails, or shifts every texture coordinate after it). `CaptureError` when a face names index 0,
    as files written counting from 0 do: OBJ counts from 1 (negative: back from the last), and
    trimesh reads 0 as the last vertex, shifting every face. Each rewrite runs only where its
    cause is in the file (a pass over every line in Python took a third of a 1M-face OBJ's load)."""
    text = path.read_bytes()
    if b"\t" in text:
        text = text.replace(b"\t", b" ")
    if text.startswith(b" ") or b"\n " in text:
        text = _OBJ_INDENT.sub(b"", text)
    if b"#" in text:  # cut comments that follow an element's fields
        kept, last = [], 0
        for at in (m.start() for m in re.finditer(rb"#", text)):
            start, end = _line_at(text, at)
            if at < last or text[start:at].split(b" ", 1)[0] not in _OBJ_ELEMENTS:
                continue
            kept.append(text[last:at].rstrip(b" "))
            last = end
        text = b"".join(kept) + text[last:]
    if text.startswith(b"vt ") or _OBJ_ONE_UV.search(text):
        text = _OBJ_ONE_UV.sub(rb"\1 0", b"\n" + text)[1:]
    for match in _OBJ_ZERO.finditer(text):
        start, end = _line_at(text, match.start())
        if text[start:start + 2] == b"f ":
            line = text[start:end].decode("utf-8", "replace").strip()
            raise CaptureError(f"{where}: mesh {path}: face {line!r} has index 0; OBJ indices count from 1 "
                               "(was the file written counting from 0?)")
    return text


def _check_ply(scene, where: str, path: Path) -> None:
    """`CaptureError` when a PLY holds fewer vertices or faces than its header declares (a
    truncated ASCII file, which trimesh loads as far as it goes) or a face index outside its
    vertices (trimesh reads -1 as the last one where the file has texture coordinates)."""
    for geometry in scene.geometry.values():
        raw = geometry.metadata.get("_ply_raw") or {}
        for element, info in raw.items():
            data = info.get("data")
            rows = [len(v) for v in data.values() if hasattr(v, "__len__")] if isinstance(data, dict) else []
            if rows and min(rows) < int(info.get("length", 0)):
                raise CaptureError(f"{where}: mesh {path}: the header declares {info['length']} {element} "
                                   f"elements, the file holds {min(rows)} (is it truncated?)")
        count = int((raw.get("vertex") or {}).get("length", 0))
        for key in ("vertex_indices", "vertex_index"):
            lists = _ply_property(raw, "face", key)
            if lists is not None and len(lists):
                if lists.dtype.names:  # a binary file's fixed-length lists: (count, indices)
                    lists = lists[lists.dtype.names[-1]]
                index = np.concatenate(list(lists)) if lists.dtype == object else lists.reshape(-1)
                if len(index) and (index.min() < 0 or index.max() >= count):
                    raise CaptureError(f"{where}: mesh {path}: face indices run from {index.min()} to "
                                       f"{index.max()}, outside its {count} vertices")


def _ply_property(raw: dict, element: str, name: str):
    """Property ``name`` of PLY element ``element`` as trimesh keeps the file's data (a dict of
    arrays, or a structured array for binary files), or None."""
    data = (raw.get(element) or {}).get("data")
    if isinstance(data, dict):
        return None if data.get(name) is None else np.asarray(data[name])
    if isinstance(data, np.ndarray) and data.dtype.names and name in data.dtype.names:
        return data[name]
    return None


def _file_normals(geom) -> np.ndarray:
    """The vertex normals of a loaded geometry: the file's where it gives them, else trimesh's.

    trimesh gives a PLY vertex a copy for each texture coordinate its faces give it (per-face
    ``texcoord`` lists, as MeshLab writes them) and then drops the file's ``nx, ny, nz``, which
    no longer match its vertices: each copy takes them back from the file's vertices at its
    position where those agree. Where they do not (a hard edge: one vertex per face at a corner)
    the copy keeps trimesh's normal, the mean of the faces it belongs to."""
    computed = np.asarray(geom.vertex_normals, np.float64)
    raw = geom.metadata.get("_ply_raw") or {}
    columns = {k: _ply_property(raw, "vertex", k) for k in ("x", "y", "z", "nx", "ny", "nz")}
    if any(c is None for c in columns.values()) or len(columns["x"]) == len(geom.vertices):
        return computed
    positions = np.column_stack([columns[k] for k in ("x", "y", "z")]).astype(np.float64)
    normals = np.column_stack([columns[k] for k in ("nx", "ny", "nz")]).astype(np.float64)
    keys, group = np.unique(positions, axis=0, return_inverse=True)
    group = group.reshape(-1)
    first = np.full(len(keys), -1)
    first[group[::-1]] = np.arange(len(group))[::-1]  # the first file vertex at each position
    spread = np.zeros(len(keys))
    np.maximum.at(spread, group, np.max(np.abs(normals - normals[first[group]]), axis=1))
    vertices = np.asarray(geom.vertices, np.float64)
    where = np.searchsorted(np.ascontiguousarray(keys).view([("", keys.dtype)] * 3).reshape(-1),
                            np.ascontiguousarray(vertices).view([("", vertices.dtype)] * 3).reshape(-1))
    where = np.minimum(where, len(keys) - 1)
    found = np.all(keys[where] == vertices, axis=1) & (spread[where] <= NORMALS_AGREE)
    return np.where(found[:, None], normals[first[where]], computed)


def load_mesh(path: str | Path, where: str = "mesh", require_uv: bool = True):
    """Load a triangle mesh as one `trimesh.Trimesh` with uv in glTF orientation.

    Scenes are flattened (node transforms applied, meshes concatenated in the order trimesh
    lists the scene's geometry nodes, fixed for a given file). Raises
    `CaptureError` when the file is missing, unreadable or not one of `MESH_SUFFIXES`, has no
    triangles or non-finite positions or texture coordinates, or (with ``require_uv``) lacks
    texture coordinates on any of its meshes or has texture coordinates that span no area.
    """
    import trimesh
    from trimesh.visual.texture import TextureVisuals

    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{where}: mesh file not found: {path}")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise CaptureError(f"{where}: {path}: unsupported mesh format {path.suffix or '(no suffix)'!r}; "
                           f"pbrfit reads {', '.join(MESH_SUFFIXES)}")
    obj = _obj_text(path, where) if path.suffix.lower() == ".obj" else None
    with _quiet_trimesh():  # bad files are reported below, one line
        try:
            if path.suffix.lower() in (".glb", ".gltf"):
                scene = _load_gltf_keeping_uv(path)
            elif obj is not None:
                resolver = trimesh.resolvers.FilePathResolver(str(path.parent))  # its .mtl
                scene = trimesh.load_scene(_io.BytesIO(obj), file_type="obj", resolver=resolver, process=False)
            else:
                scene = trimesh.load_scene(str(path), process=False)
            _check_ply(scene, where, path)
            parts = _flatten(scene, where, path)
        except CaptureError:
            raise
        except Exception as err:  # trimesh raises many types for bad files
            msg = str(err).splitlines()[0] if str(err) else ""
            if isinstance(err, (AssertionError, AttributeError, IndexError, KeyError, TypeError)) or not msg:
                # the parser tripped over the file's structure: say so, and what it tripped on
                msg = f"malformed {path.suffix.lstrip('.').upper()} file ({type(err).__name__}{': ' + msg if msg else ''})"
            raise CaptureError(f"{where}: cannot load mesh {path}: {msg}") from None
    if not parts:
        raise CaptureError(f"{where}: mesh file {path} holds no triangles")
    uvs = []
    for part in parts:
        uv = getattr(part.visual, "uv", None)
        if uv is None or len(uv) != len(part.vertices):
            if require_uv:
                name = part.metadata.get("name", "")
                label = f" (mesh {name!r})" if name and len(parts) > 1 else ""
                if obj is not None and (obj.startswith(b"vt ") or b"\nvt " in obj):  # given, but not usable
                    raise CaptureError(
                        f"{where}: mesh {path}{label}: its vt texture coordinates do not reach every face corner "
                        "(a face without vt, or a vt index past the last vt line); texture maps need them all"
                    )
                raise CaptureError(
                    f"{where}: mesh {path}{label} has no texture coordinates "
                    "(glTF TEXCOORD_0 / OBJ vt); texture maps need them"
                )
            uvs = None
            break
        uvs.append(np.asarray(uv, dtype=np.float64)[:, :2])
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    vertices = np.concatenate([np.asarray(p.vertices, np.float64) for p in parts])
    faces = np.concatenate([np.asarray(p.faces, np.int64) + off for p, off in zip(parts, offsets)])
    normals = np.concatenate([p.metadata["pbrfit_normals"] for p in parts])
    visual = None
    if uvs is not None:
        uv = np.concatenate(uvs)
        # trimesh's convention (v = 0 at the image bottom) -> glTF's (v = 0 at the top row)
        uv_gltf = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
        visual = TextureVisuals(uv=uv_gltf)
    for label, values in (("vertex positions", vertices), ("texture coordinates", None if uvs is None else uv)):
        if values is not None and not np.all(np.isfinite(values)):
            count = int(np.sum(~np.all(np.isfinite(values), axis=1)))
            raise CaptureError(f"{where}: mesh {path}: {count} {label} hold NaN or inf values")
    extent = float(np.max(np.abs(vertices)))
    if extent > MAX_COORDINATE:
        raise CaptureError(f"{where}: mesh {path}: vertex positions reach {extent:.3g}; pbrfit takes up to "
                           f"{MAX_COORDINATE:g} world units (the solve squares distances in float32)")
    mesh = trimesh.Trimesh(
        vertices=vertices, faces=faces, vertex_normals=normals, visual=visual, process=False
    )
    mesh.metadata["uv_orientation"] = "gltf"
    mesh.metadata["file"] = str(path)
    if require_uv:
        check_uv_layout(mesh, where)
    return mesh


def check_uv_layout(mesh, where: str = "mesh") -> None:
    """Raise `CaptureError` unless a loaded mesh's texture coordinates lay out an area texture
    maps can be read through (total uv area above `UV_AREA_MIN`)."""
    path = mesh.metadata.get("file", "")
    uv = getattr(mesh.visual, "uv", None)
    if uv is None:
        raise CaptureError(f"{where}: mesh {path} has no texture coordinates (glTF TEXCOORD_0 / OBJ vt); "
                           "texture maps need them")
    if _uv_area(np.asarray(uv, np.float64), np.asarray(mesh.faces)) <= UV_AREA_MIN:
        raise CaptureError(f"{where}: mesh {path}: texture coordinates span no area (every triangle's uv area "
                           "is 0, e.g. all equal); texture maps need a uv layout")
