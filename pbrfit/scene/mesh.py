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
* Other glTF that trimesh alone misreads is read as glTF 2.0 means it (`pbrfit.scene.gltf_read`,
  `pbrfit.scene.gltf_geometry`): triangle fans, morph targets under their weights, sparse
  indices, meshes on or under camera nodes, GPU instancing, skinned meshes (drawn at rest); a
  file requiring an extension that changes the geometry and that pbrfit cannot read (Draco
  without DracoPy, meshopt, any unknown one) is refused.
* OBJ text is read as the format means it (`_obj_text`): fields separated by any whitespace,
  comments after an element's fields, ``vt u`` with v = 0; a face index 0 is refused.
"""

from __future__ import annotations

import codecs
import contextlib
import io as _io
import logging
import re
import warnings
from pathlib import Path

import numpy as np
import trimesh
from trimesh.visual.texture import TextureVisuals

from ..errors import CaptureError
from .gltf_read import load_gltf_scene
from .uv_layout import check_uv_layout, shared_uv_space

__all__ = ["load_mesh", "MESH_SUFFIXES"]

#: The file's normals at one position agree where no component differs by more than this
#: (float32 writes of the same vector); else the position is a hard edge (`_file_normals`).
NORMALS_AGREE = 1e-6


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


@contextlib.contextmanager
def _quiet_trimesh():
    """No numpy floating-point warnings and no trimesh log records while a mesh loads: what is
    wrong with a file is said once, by `load_mesh`."""
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


def _as_utf8(text: bytes, what: str) -> bytes:
    """An OBJ's bytes as UTF-8, as trimesh's parser reads them: a byte-order mark read
    (UTF-8's, which trimesh took as part of the first line; UTF-16 text), a file that is not
    UTF-8 read as Latin-1 (a comment or a name in another 8-bit encoding: trimesh would guess
    with charset_normalizer, which pbrfit does not require). NUL bytes: `CaptureError`, not text."""
    if text.startswith(codecs.BOM_UTF8):
        return text[len(codecs.BOM_UTF8):]
    if text.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        try:
            return text.decode("utf-16").encode("utf-8")
        except UnicodeDecodeError:
            raise CaptureError(f"{what}: not a text OBJ file (a UTF-16 mark, then no UTF-16 text)") from None
    try:
        text.decode("utf-8")
    except UnicodeDecodeError:
        if b"\0" in text:
            raise CaptureError(f"{what}: not a text OBJ file (it holds binary data)") from None
        return text.decode("latin-1").encode("utf-8")
    return text


def _obj_text(path: Path, where: str) -> bytes:
    """An OBJ file's text as trimesh's parser reads it as the format means it: fields separated by
    tabs as by spaces, indented lines, a comment after an element's fields and a one-component
    texture coordinate ``vt u`` (v = 0) are valid OBJ, which trimesh misreads (drops the line,
    fails, or shifts every texture coordinate after it). `CaptureError` when a face names index 0,
    as files written counting from 0 do: OBJ counts from 1 (negative: back from the last), and
    trimesh reads 0 as the last vertex, shifting every face. Its encoding: `_as_utf8`. Each
    rewrite runs only where its cause is in the file (a pass over every line in Python took a
    third of a 1M-face OBJ's load)."""
    text = _as_utf8(path.read_bytes(), f"{where}: mesh {path}")
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
                scene = load_gltf_scene(path)
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
        _warn_shared_uv_space(parts, uvs, where, path)
    return mesh


def _warn_shared_uv_space(parts, uvs, where: str, path: Path) -> None:
    """A warning where two of the file's materials lay their texture coordinates over the same
    texture space (`pbrfit.scene.uv_layout.shared_uv_space`): the fit's one set of maps would mix them."""
    named = [(str(name), uv, np.asarray(part.faces)) for part, uv in zip(parts, uvs)
             if (name := getattr(getattr(part.visual, "material", None), "name", None))]
    if len({name for name, _, _ in named}) < 2:
        return
    shared = shared_uv_space(named)
    if shared is not None:
        a, b, share = shared
        warnings.warn(f"{where}: mesh {path}: materials {a!r} and {b!r} use the same texture space ({share:.0%} of "
                      f"{a!r}'s): pbrfit fits one set of maps for the whole mesh, so there each texel is fitted to "
                      "both materials' pixels; give each material its own part of the uv square", stacklevel=3)
