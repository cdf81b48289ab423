"""glTF export: a mesh with a fitted material as a binary glTF (GLB) that glTF viewers and Blender
open (`write_gltf`): the maps as textures in glTF's packing, or a uniform material as exact
factors, upright in glTF's +Y-up frame whatever the capture's ``world_up``, and clean under the
Khronos glTF-Validator (bufferView targets, an explicit sampler)."""

from __future__ import annotations

import json
import math
import os
import struct
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image
from trimesh.visual.material import PBRMaterial
from trimesh.visual.texture import TextureVisuals

from .atomic import atomic_open
from .images import srgb_encoded
from .material_files import encode_normal, map_array, pack_orm

__all__ = ["write_gltf", "needs_texture_coordinates", "WORLD_TO_GLTF_ROTATION"]

#: The rotation, as a unit quaternion (x, y, z, w), that turns a capture's world (``world_up``,
#: the capture spec's values) into glTF's frame, +Y up (glTF 2.0, "Coordinate System and
#: Units"): none for +y; for +z, -90 degrees about +X, (x, y, z) -> (x, z, -y), the Blender to
#: glTF axis change `pbrfit.lighting.environment.to_environment_frame` applies to a +z world.
WORLD_TO_GLTF_ROTATION = {"+y": None, "+z": (-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5))}

# glTF 2.0 enums (the WebGL values of bufferView.target, sampler.magFilter / minFilter / wrapS / wrapT).
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_LINEAR, _LINEAR_MIPMAP_LINEAR, _REPEAT = 9729, 9987, 10497


def _pil_image(pixels: np.ndarray):
    """8-bit PIL image from [0, 1] floats, row 0 at the top (glTF: row 0 is v = 0)."""
    codes = np.round(np.clip(np.asarray(pixels, np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)
    if codes.shape[-1] == 1:
        return Image.fromarray(codes[..., 0], mode="L")
    return Image.fromarray(np.ascontiguousarray(codes[..., :3]), mode="RGB")


def _is_uniform(material) -> bool:
    """Whether glTF's factors hold ``material`` whole: it reads no texture coordinates
    (`needs_texture_coordinates`) and has no occlusion map, for which glTF has no factor."""
    return not needs_texture_coordinates(material) and getattr(material, "occlusion", None) is None


def needs_texture_coordinates(material) -> bool:
    """Whether rendering ``material`` reads texture coordinates: any map larger than 1 x 1
    (occlusion and emissive included), or a normal map."""
    maps = [map_array(getattr(material, name, None)) for name in ("base_color", "metallic", "roughness", "occlusion",
                                                            "emissive")]
    return getattr(material, "normal", None) is not None or any(m is not None and m.shape[:2] != (1, 1) for m in maps)


def _glb_with_json(data: bytes, edit) -> bytes:
    """A GLB whose JSON chunk is ``edit(json)``: header, JSON chunk (space-padded to 4 bytes),
    then the other chunks unchanged (glTF 2.0, "GLB File Format Specification")."""
    magic, version, _ = struct.unpack_from("<4sII", data, 0)
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    if magic != b"glTF" or json_type != b"JSON":
        raise ValueError("not a GLB with a leading JSON chunk")
    tree = edit(json.loads(data[20 : 20 + json_len]))
    text = json.dumps(tree, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    rest = data[20 + json_len :]
    chunk = struct.pack("<I4s", len(text), b"JSON") + text
    return struct.pack("<4sII", magic, version, 12 + len(chunk) + len(rest)) + chunk + rest


def _set_buffer_view_targets(tree: dict) -> dict:
    """Set each bufferView's ``target`` from its use (glTF 2.0, "Buffers and Buffer Views": it
    SHOULD be defined for vertex and index data): ARRAY_BUFFER for a view a primitive's
    attributes read, ELEMENT_ARRAY_BUFFER for its indices. Views of images keep none."""
    accessors, views = tree.get("accessors", []), tree.get("bufferViews", [])

    def mark(accessor: int, target: int) -> None:
        view = accessors[accessor].get("bufferView")
        if view is not None:
            views[view]["target"] = target

    for mesh in tree.get("meshes", []):
        for prim in mesh.get("primitives", []):
            for accessor in prim.get("attributes", {}).values():
                mark(accessor, _ARRAY_BUFFER)
            if "indices" in prim:
                mark(prim["indices"], _ELEMENT_ARRAY_BUFFER)
    return tree


def _set_sampler(tree: dict) -> dict:
    """Give every texture one sampler: REPEAT in u and v, as pbrfit samples (the capture spec),
    magnification LINEAR (pbrfit's bilinear lookup), minification LINEAR_MIPMAP_LINEAR.

    The maps are fitted at the size whose texels cover at least a pixel in the views
    (`pbrfit.fitting.resolution.default_resolution`), where a viewer magnifies and LINEAR is
    pbrfit's own lookup. Zoomed out, LINEAR alone aliases; trilinear mipmaps give the average
    the pixel sees, and are what glTF-Sample-Viewer (``gltfSampler``) and three.js
    (``GLTFLoader``) use for a texture without a sampler, whose filtering glTF 2.0 leaves to
    the viewer (``texture.sampler``): the file states the filtering viewers already pick.
    No sampler when there is no texture (it would go unused)."""
    if tree.get("textures"):
        tree["samplers"] = [dict(magFilter=_LINEAR, minFilter=_LINEAR_MIPMAP_LINEAR, wrapS=_REPEAT, wrapT=_REPEAT)]
        for texture in tree["textures"]:
            texture["sampler"] = 0
    return tree


def _set_up_axis(tree: dict, world_up: str) -> dict:
    """Put the scene under one root node that turns ``world_up`` into glTF's +Y up
    (`WORLD_TO_GLTF_ROTATION`); for +y the tree is unchanged.

    A node rotation rather than rotated vertices: the vertex data (POSITION, NORMAL) stay the
    capture mesh's, in the capture's world, so the file holds the geometry the material was
    fitted on, and the change of frame is one quaternion a reader sees (and drops to get the
    world back); nothing else (normals, a tangent frame) needs turning with it. Every glTF
    reader applies node transforms (glTF 2.0, "Transformations"); Blender's importer then
    turns glTF's +Y up into its own +Z, so a +z capture opens in Blender in its own frame."""
    rotation = WORLD_TO_GLTF_ROTATION[world_up]
    if rotation is None:
        return tree
    nodes = tree.setdefault("nodes", [])
    scenes = tree.get("scenes") or [{"nodes": []}]
    for scene in scenes:
        nodes.append({"name": f"world_{world_up[1]}_up", "rotation": [float(c) for c in rotation],
                      "children": list(scene.get("nodes", []))})
        scene["nodes"] = [len(nodes) - 1]
    tree["scenes"] = scenes
    return tree


def _export_glb(path, mesh, visual, world_up: str, edit=None) -> Path:
    """``mesh``'s vertices, faces and vertex normals with ``visual``, as a GLB at ``path``
    (atomically), upright in glTF's frame (`_set_up_axis`), with bufferView targets and a
    sampler; ``edit`` may rewrite the glTF JSON first (`_glb_with_json`)."""
    out_mesh = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices),
        faces=np.asarray(mesh.faces),
        vertex_normals=np.asarray(mesh.vertex_normals),
        visual=visual,
        process=False,
    )
    data = out_mesh.export(file_type="glb", include_normals=True)

    def conventions(tree: dict) -> dict:
        tree = edit(tree) if edit is not None else tree
        return _set_up_axis(_set_sampler(_set_buffer_view_targets(tree)), world_up)

    data = _glb_with_json(data, conventions)
    path = Path(path)
    with atomic_open(path) as f:
        f.write(data)
    return path


def _write_uniform_gltf(path: Path, mesh, material, world_up: str) -> Path:
    base = [float(v) for v in np.clip(map_array(material.base_color).reshape(-1)[:3], 0.0, 1.0)] + [1.0]
    metallic = float(np.clip(map_array(material.metallic).reshape(-1)[0], 0.0, 1.0))
    roughness = float(np.clip(map_array(material.roughness).reshape(-1)[0], 0.0, 1.0))
    emissive = map_array(getattr(material, "emissive", None))

    def exact_factors(tree):  # trimesh stores baseColorFactor as 8-bit; write the floats
        for m in tree.get("materials", []):
            m["pbrMetallicRoughness"] = dict(baseColorFactor=base, metallicFactor=metallic, roughnessFactor=roughness)
            if emissive is not None:  # clipped to [0, 1], as the emissive texture is
                m["emissiveFactor"] = [float(v) for v in np.clip(emissive.reshape(-1)[:3], 0.0, 1.0)]
        return tree

    visual = TextureVisuals(material=PBRMaterial(name="pbrfit", doubleSided=True))
    return _export_glb(path, mesh, visual, world_up, exact_factors)


def write_gltf(path: str | os.PathLike, mesh, material, world_up: str = "+y") -> Path:
    """Write ``mesh`` with ``material`` as a binary glTF (GLB) at ``path``, atomically.

    ``mesh`` is in the capture's world, whose up axis is ``world_up`` (``"+y"`` or ``"+z"``,
    the capture spec's ``world_up``); the file is +Y up as glTF requires, by a rotation of a
    root node (`_set_up_axis`), so every viewer shows it upright.

    ``mesh`` is a `trimesh.Trimesh` whose ``visual.uv`` is in glTF orientation (v = 0 at the
    top row of the texture), as `pbrfit.scene.capture.load_capture` gives it. trimesh's exporter
    expects its own convention (v = 0 at the bottom) and writes TEXCOORD_0 = (u, 1 - v), so the
    uv is flipped before export and TEXCOORD_0 ends up equal to ``mesh.visual.uv``. Textures are
    stored with row 0 at the top of the image, so texel row 0 is v = 0 as glTF requires. baseColorTexture is sRGB 8-bit,
    metallicRoughnessTexture linear (R = occlusion or 1, G = roughness, B = metallic) with
    factors 1; normalTexture, occlusionTexture (the same image's R, or an image of its own when its
    size differs from metallic and roughness) and emissiveTexture
    (factor 1, clipped to [0, 1]) when the material has them. Vertex normals are written
    (NORMAL), so shading matches the mesh the material was fitted on. Every bufferView of
    vertex or index data names its target and every texture the one sampler (`_set_sampler`).

    A uniform material (1 x 1 maps, emissive included; no normal or occlusion map) is written as
    glTF factors instead, exactly (baseColorFactor is linear, as the fit's base color): no
    textures, and no texture coordinates needed. A material of 1 x 1 maps with a 1 x 1 occlusion
    map, which only a texture can hold, is written with textures and TEXCOORD_0 = (0, 0) on a
    mesh without texture coordinates: a 1 x 1 texture reads the same everywhere.
    """
    if world_up not in WORLD_TO_GLTF_ROTATION:
        raise ValueError(f"write_gltf: world_up must be one of {', '.join(WORLD_TO_GLTF_ROTATION)}, got {world_up!r}")
    if _is_uniform(material):
        return _write_uniform_gltf(Path(path), mesh, material, world_up)
    uv = getattr(getattr(mesh, "visual", None), "uv", None)
    if uv is None or len(uv) != len(mesh.vertices):
        if needs_texture_coordinates(material):
            raise ValueError("write_gltf needs a mesh with one texture coordinate per vertex (mesh.visual.uv)")
        uv = np.zeros((len(mesh.vertices), 2))
    base = map_array(material.base_color)
    orm = pack_orm(material)
    orm_image = _pil_image(orm)
    kwargs = dict(
        baseColorTexture=_pil_image(srgb_encoded(base)),
        metallicRoughnessTexture=orm_image,
        metallicFactor=1.0,
        roughnessFactor=1.0,
        baseColorFactor=[255, 255, 255, 255],
        name="pbrfit",
        doubleSided=True,  # pbrfit shades both sides of a face (`pbrfit.scene.gbuffer`)
    )
    normal = map_array(getattr(material, "normal", None))
    if normal is not None:
        kwargs["normalTexture"] = _pil_image(encode_normal(normal))
    occlusion = map_array(getattr(material, "occlusion", None))
    if occlusion is not None:
        if occlusion.shape[:2] == orm.shape[:2]:
            kwargs["occlusionTexture"] = orm_image  # its R channel, as glTF reads occlusion
        else:  # a size of its own: its own image (R, repeated so viewers show grey)
            kwargs["occlusionTexture"] = _pil_image(np.repeat(occlusion[..., :1], 3, axis=-1))
    emissive = map_array(getattr(material, "emissive", None))
    if emissive is not None:
        kwargs["emissiveTexture"] = _pil_image(srgb_encoded(emissive))
        kwargs["emissiveFactor"] = [1.0, 1.0, 1.0]
    uv = np.asarray(uv, dtype=np.float64)[:, :2]
    uv_trimesh = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])  # undone by trimesh's exporter
    return _export_glb(path, mesh, TextureVisuals(uv=uv_trimesh, material=PBRMaterial(**kwargs)), world_up)
