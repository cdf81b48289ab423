"""glTF accessors read as glTF 2.0 means them: strides, sparse entries and normalized integers
(KHR_mesh_quantization) applied, which trimesh reads raw; and TEXCOORD_0's KHR_texture_transform
(its rules: `pbrfit.scene.mesh`'s docstring)."""

from __future__ import annotations

import numpy as np
from jaxtyping import Float

__all__ = ["read_view", "read_accessor", "texture_transform", "apply_texture_transform", "NORMALIZED",
           "COMPONENT_DTYPES", "TYPE_WIDTHS", "DRACO"]

#: Normalized integer component types (glTF componentType): (dtype, divisor, signed).
NORMALIZED = {5120: (np.int8, 127.0, True), 5121: (np.uint8, 255.0, False),
               5122: (np.int16, 32767.0, True), 5123: (np.uint16, 65535.0, False)}
COMPONENT_DTYPES = {**{k: v[0] for k, v in NORMALIZED.items()}, 5125: np.uint32, 5126: np.float32}
TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
#: The textures whose KHR_texture_transform is TEXCOORD_0's, in order of preference.
_TRANSFORM_TEXTURES = (("pbrMetallicRoughness", "baseColorTexture"),
                       ("pbrMetallicRoughness", "metallicRoughnessTexture"),
                       (None, "normalTexture"), (None, "occlusionTexture"), (None, "emissiveTexture"))
DRACO = "KHR_draco_mesh_compression"


def read_view(tree: dict, buffer, view_index: int, offset: int, component: int, count: int, width: int):
    """(count, width) components of glTF type ``component`` from a buffer view, ``offset`` bytes
    in, following its byteStride; ``buffer(i)`` gives buffer i's bytes."""
    view = tree["bufferViews"][view_index]
    dtype = np.dtype(COMPONENT_DTYPES[component]).newbyteorder("<")
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


def read_accessor(tree: dict, buffer, index: int) -> np.ndarray:
    """An accessor's values as float64 (count, width): sparse entries applied, normalized
    integers divided out (`NORMALIZED`)."""
    acc = tree["accessors"][index]
    component, count, width = acc["componentType"], int(acc["count"]), TYPE_WIDTHS[acc["type"]]
    if "bufferView" in acc:
        values = read_view(tree, buffer, acc["bufferView"], acc.get("byteOffset", 0), component, count, width)
    else:
        values = np.zeros((count, width), COMPONENT_DTYPES[component])
    sparse = acc.get("sparse")
    if sparse:
        values = values.copy()
        ind, val, n = sparse["indices"], sparse["values"], int(sparse["count"])
        rows = read_view(tree, buffer, ind["bufferView"], ind.get("byteOffset", 0), ind["componentType"], n, 1)
        values[rows[:, 0]] = read_view(tree, buffer, val["bufferView"], val.get("byteOffset", 0), component, n,
                                        width)
    values = values.astype(np.float64)
    if acc.get("normalized") and component in NORMALIZED:
        _, divisor, signed = NORMALIZED[component]
        values = values / divisor
        if signed:
            values = np.maximum(values, -1.0)
    return values


def texture_transform(tree: dict, primitive: dict):
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
    counter-clockwise there: `pbrfit.scene.mesh`'s docstring has the README's GLSL erratum)."""
    su, sv = uv[:, 0] * scale[0], uv[:, 1] * scale[1]
    c, s = np.cos(rotation), np.sin(rotation)
    return np.column_stack([offset[0] + c * su + s * sv, offset[1] - s * su + c * sv])
