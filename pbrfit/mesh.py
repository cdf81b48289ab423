"""Meshes: loading a capture's triangle mesh (glTF/GLB, OBJ, PLY) with its uv in glTF orientation.

Rules pinned here (tests in ``tests/test_scene.py``):

* Loaded with trimesh without processing (vertex order kept); a scene's meshes are
  concatenated with their node transforms applied. ``mesh.visual.uv`` holds texture
  coordinates in glTF orientation (v = 0 at the top row of the texture image) for every mesh
  format: trimesh's loaders return v = 0 at the bottom for both OBJ (as stored) and glTF
  (TEXCOORD_0 flipped on load), so `load_mesh` flips v back. A glTF primitive without a
  material still keeps its TEXCOORD_0 (trimesh would drop it).
"""

from __future__ import annotations

import io as _io
import json
import struct
import urllib.parse
from pathlib import Path

import numpy as np

from .errors import CaptureError

__all__ = ["gltf_file_uris", "load_mesh"]

_GLB_MAGIC = 0x46546C67
_CHUNK_JSON = 0x4E4F534A


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


def _load_gltf_keeping_uv(path: Path):
    import trimesh

    data = path.read_bytes()
    if path.suffix.lower() == ".glb":
        magic, version, _ = struct.unpack_from("<III", data, 0)
        if magic != _GLB_MAGIC:
            raise ValueError("not a GLB file (bad magic)")
        json_len, chunk_type = struct.unpack_from("<II", data, 12)
        if chunk_type != _CHUNK_JSON:
            raise ValueError("first GLB chunk is not JSON")
        tree = json.loads(data[20 : 20 + json_len])
        if _gltf_default_material(tree):
            js = json.dumps(tree).encode()
            js += b" " * (-len(js) % 4)
            rest = data[20 + json_len :]
            header = struct.pack("<III", magic, version, 12 + 8 + len(js) + len(rest))
            data = header + struct.pack("<II", len(js), _CHUNK_JSON) + js + rest
        return trimesh.load_scene(_io.BytesIO(data), file_type="glb", process=False)
    tree = json.loads(data)
    _gltf_default_material(tree)
    for _, _, entry, name in gltf_file_uris(tree):  # the resolver takes file names
        entry["uri"] = name
    # the URIs are relative to the file and may lead out of its folder ("../buffers/a.bin")
    try:
        resolver = trimesh.resolvers.FilePathResolver(str(path.parent), allow_anywhere=True)
    except TypeError:  # an older trimesh: no such option, and no such restriction
        resolver = trimesh.resolvers.FilePathResolver(str(path.parent))
    return trimesh.load_scene(
        _io.BytesIO(json.dumps(tree).encode()), file_type="gltf", resolver=resolver, process=False
    )


def _flatten(scene) -> list:
    """The scene's triangle meshes in world space, keeping the file's vertex normals.

    Each geometry node's transform is applied to positions, and its inverse transpose to the
    normals the file holds (trimesh's ``Scene.dump`` would recompute them from the faces, which
    smooths across hard edges and seams). A mirroring transform also reverses the winding.
    """
    import trimesh

    parts = []
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry.get(name)
        if not isinstance(geom, trimesh.Trimesh) or not len(geom.faces):
            continue
        t = np.asarray(transform, np.float64)
        normals = np.asarray(geom.vertex_normals, np.float64) @ np.linalg.inv(t[:3, :3])  # (M^-T n) as rows
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
    try:
        if path.suffix.lower() in (".glb", ".gltf"):
            scene = _load_gltf_keeping_uv(path)
        else:
            scene = trimesh.load_scene(str(path), process=False)
    except Exception as err:  # trimesh raises many types for bad files
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise CaptureError(f"{where}: cannot load mesh {path}: {msg}") from None
    parts = _flatten(scene)
    if not parts:
        raise CaptureError(f"{where}: mesh file {path} holds no triangles")
    uvs = []
    for part in parts:
        uv = getattr(part.visual, "uv", None)
        if uv is None or len(uv) != len(part.vertices):
            if require_uv:
                name = part.metadata.get("name", "")
                label = f" (mesh {name!r})" if name and len(parts) > 1 else ""
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
