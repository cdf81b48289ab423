"""glTF files read as glTF 2.0 means them, then handed to trimesh: GLB chunks and buffers
(embedded, in the GLB, or in files with percent-encoded URIs), required extensions checked
(`prepare_tree`), primitives rewritten (`pbrfit.scene.gltf_geometry`) and stored as a new buffer
(`load_gltf_scene`)."""

from __future__ import annotations

import base64
import importlib.util
import io as _io
import json
import struct
import urllib.parse
from pathlib import Path

import trimesh

from .gltf_accessors import DRACO
from .gltf_geometry import rewrite_primitives

__all__ = ["gltf_file_uris", "glb_chunks", "glb_from_chunks", "prepare_tree", "load_gltf_scene"]

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
    materials.append({"name": "(no material)"})
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


def _json_object(data: bytes, what: str) -> dict:
    """The JSON object in ``data``; ValueError naming ``what`` where it is not valid JSON or not an object."""
    try:
        tree = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{what} is not valid JSON ({str(err).splitlines()[0]})") from None
    if not isinstance(tree, dict):
        raise ValueError(f"{what} is a {type(tree).__name__}, not an object")
    return tree


def glb_chunks(data: bytes):
    """(version, JSON tree, BIN chunk or None) of a GLB file; ValueError, in words, where the file
    is too short for its header, is not a GLB, or its JSON chunk is cut short or not JSON."""
    if len(data) < 20:
        raise ValueError(f"not a GLB file: {len(data)} bytes, shorter than its headers (20 bytes)")
    magic, version, _ = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC:
        raise ValueError("not a GLB file (bad magic)")
    json_len, chunk_type = struct.unpack_from("<II", data, 12)
    if chunk_type != _CHUNK_JSON:
        raise ValueError("first GLB chunk is not JSON")
    if 20 + json_len > len(data):
        raise ValueError(f"truncated GLB file: its JSON chunk needs {json_len} bytes, {len(data) - 20} are left")
    tree = _json_object(data[20 : 20 + json_len], "GLB file's JSON chunk")
    at, binary = 20 + json_len, None
    while binary is None and at + 8 <= len(data):  # the first BIN chunk (other kinds are skipped)
        length, kind = struct.unpack_from("<II", data, at)
        if kind == _CHUNK_BIN:
            binary = data[at + 8 : at + 8 + length]
        at += 8 + length
    return version, tree, binary


def glb_from_chunks(version: int, tree: dict, binary) -> bytes:
    js = json.dumps(tree).encode()
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<II", len(js), _CHUNK_JSON) + js
    if binary is not None:
        binary = bytes(binary) + b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(binary), _CHUNK_BIN) + binary
    return struct.pack("<III", _GLB_MAGIC, version, 12 + len(chunks)) + chunks


def _store_rewritten_primitives(tree: dict, folder: Path, binary):
    """`rewrite_primitives` with its data stored: appended to a GLB's BIN chunk (buffer 0),
    else as a new base64 buffer. Returns the (possibly longer) BIN chunk."""
    buffers = tree.setdefault("buffers", [])
    read = _buffer_reader(tree, folder, binary)
    if binary is not None and buffers and "uri" not in buffers[0]:
        blob = rewrite_primitives(tree, read, 0, len(binary))
        if blob:
            binary = bytes(binary) + blob
            buffers[0]["byteLength"] = len(binary)
        return binary
    blob = rewrite_primitives(tree, read, len(buffers), 0)
    if blob:
        buffers.append({"byteLength": len(blob),
                        "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()})
    return binary


def _file_resolver(tree: dict, folder: Path):
    """A trimesh resolver for the tree's file URIs, which it rewrites to plain file names (glTF
    URIs are percent-encoded and relative to the file, and may lead out of its folder); a
    missing buffer file is named."""
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


def prepare_tree(tree: dict) -> None:
    """Check a glTF's required extensions and give trimesh what it reads right.

    A ValueError names the required extensions pbrfit cannot honour (a loader must refuse a file
    that requires one it does not support: compressed geometry would come out empty or zero). Camera nodes lose their camera: trimesh leaves a node
    with a camera and a mesh, and the meshes under it, out of the scene, which glTF viewers
    draw. Primitives with TEXCOORD_0 and no material get a default one (`_gltf_default_material`).
    Every material gets a name of its own, so that they can be told apart once trimesh has loaded
    them: an unnamed one its index ("material 3"), a repeated name its index after it."""
    read = _EXTENSIONS_READ
    if importlib.util.find_spec("DracoPy") is not None:  # trimesh decodes Draco with it
        read += (DRACO,)
    required = [name for name in tree.get("extensionsRequired") or []
                if name not in read and not str(name).startswith(_EXTENSION_PREFIXES_NOT_READ)]
    if required:
        hint = (" (write it without compression)" if any("compression" in str(n) for n in required) else "")
        if DRACO in required:
            hint = " (install DracoPy, with which trimesh decodes Draco, or write it without compression)"
        raise ValueError(f"it requires the glTF extension{'s' if len(required) > 1 else ''} "
                         f"{', '.join(map(str, required))}, which pbrfit does not read{hint}")
    for node in tree.get("nodes") or []:
        if isinstance(node, dict):
            node.pop("camera", None)
    _gltf_default_material(tree)
    names = set()  # materials are told apart by name once loaded (`pbrfit.scene.uv_layout`): one each
    for index, material in enumerate(tree.get("materials") or []):
        if isinstance(material, dict):
            name = str(material.get("name") or f"material {index}")
            material["name"] = name if name not in names else f"{name} (material {index})"
            names.add(material["name"])


def load_gltf_scene(path: Path):
    data = path.read_bytes()
    if path.suffix.lower() == ".glb":
        version, tree, binary = glb_chunks(data)
        resolver = _file_resolver(tree, path.parent)
        prepare_tree(tree)
        binary = _store_rewritten_primitives(tree, path.parent, binary)
        data = glb_from_chunks(version, tree, binary)
        return trimesh.load_scene(_io.BytesIO(data), file_type="glb", resolver=resolver, process=False)
    tree = _json_object(data, "not a glTF file: its JSON")
    resolver = _file_resolver(tree, path.parent)
    prepare_tree(tree)
    _store_rewritten_primitives(tree, path.parent, None)
    return trimesh.load_scene(
        _io.BytesIO(json.dumps(tree).encode()), file_type="gltf", resolver=resolver, process=False
    )
