"""glTF primitives rewritten where trimesh would misread them: morph targets under their weights,
sparse indices, triangle fans, GPU instances (EXT_mesh_gpu_instancing) and skinned meshes at
rest, with normalized, sparse or texture-transformed attributes as plain float32
(`rewrite_primitives`; `pbrfit.scene.gltf_read` stores what it writes)."""

from __future__ import annotations

import numpy as np

from .gltf_accessors import DRACO, NORMALIZED, apply_texture_transform, read_accessor, texture_transform

__all__ = ["rewrite_primitives", "NORMAL_FLOOR"]

_FLOAT = 5126
_UINT32 = 5125
_TRIANGLE_FAN = 6
_INSTANCING = "EXT_mesh_gpu_instancing"
#: A normal shorter than this has no direction (a skin that flattens the mesh along it): the
#: file's own normal stands in.
NORMAL_FLOOR = 1e-12


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
        values = {name: read_accessor(tree, buffer, index) for name, index in attributes.items()
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
            if DRACO in (primitive.get("extensions") or {}):  # its data is decoded later, by trimesh
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


def rewrite_primitives(tree: dict, buffer, target: int, start: int) -> bytes:
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
            if DRACO in (primitive.get("extensions") or {}):  # decoded later, by trimesh (with DracoPy)
                if texture_transform(tree, primitive) is not None:
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
                transform = texture_transform(tree, primitive) if name == "TEXCOORD_0" else None
                morph = tuple((w, t[name]) for w, t in zip(weights, targets)
                              if w != 0.0 and isinstance(t, dict) and isinstance(t.get(name), int))
                normalized = bool(acc.get("normalized")) and acc.get("componentType") in NORMALIZED
                if not (normalized or morph) and transform is None and "sparse" not in acc:  # (trimesh ignores sparse)
                    continue
                key = (index, transform, morph)
                if key not in made:
                    values = read_accessor(tree, buffer, index)
                    for w, t in morph:
                        values = values + w * read_accessor(tree, buffer, t)[:, : values.shape[1]]
                    if transform is not None:
                        values = apply_texture_transform(values[:, :2], *transform)
                    made[key] = store(values, "<f4", acc["type"] if transform is None else "VEC2", _FLOAT)
                attributes[name] = made[key]
            primitive.pop("targets", None)
            indices = primitive.get("indices")
            fan = primitive.get("mode") == _TRIANGLE_FAN
            if isinstance(indices, int) and ("sparse" in tree["accessors"][indices] or fan):
                order = read_accessor(tree, buffer, indices)[:, 0].astype(np.int64)
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
        _skin_in_rest_pose(tree, lambda i: stored[i] if i in stored else read_accessor(tree, buffer, i), store, shown)
    return bytes(blob)
