"""`Material`: the glTF metallic-roughness maps as a pytree, sampled at uv, and normal mapping.

Maps are stored as glTF textures are (row 0 is v = 0), all linear in memory: base color is
decoded from sRGB when read from ``base_color.png``; ``emissive.exr`` holds linear radiance;
metallic, roughness, occlusion and normal are linear data. Roughness is perceptual.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .brdf import safe_normalize
from .textures import sample_bilinear

__all__ = ["Material", "MaterialSample", "material_at", "apply_normal_map", "NORMAL_CONVENTIONS"]

#: Tangent-space normal map conventions: OpenGL (+Y, glTF's) or DirectX (-Y, green flipped).
NORMAL_CONVENTIONS = ("opengl", "directx")


class Material(eqx.Module):
    """glTF metallic-roughness material maps (linear values, glTF texture orientation).

    Attributes:
        base_color: (H, W, 3) linear RGB in [0, 1].
        metallic: (H, W, 1) in [0, 1].
        roughness: (H, W, 1) perceptual roughness in [0, 1].
        normal: optional (H', W', 3) unit tangent-space normals (+Y / OpenGL convention).
        occlusion: optional (H', W', 1) ambient occlusion in [0, 1], applied to indirect light only.
        emissive: optional (H', W', 3) linear emitted radiance.
    """

    base_color: Float[Array, "H W 3"]
    metallic: Float[Array, "H W 1"]
    roughness: Float[Array, "H W 1"]
    normal: Optional[Float[Array, "Hn Wn 3"]] = None
    occlusion: Optional[Float[Array, "Ho Wo 1"]] = None
    emissive: Optional[Float[Array, "He We 3"]] = None

    def __check_init__(self):
        for name, channels in (("base_color", 3), ("metallic", 1), ("roughness", 1), ("normal", 3),
                               ("occlusion", 1), ("emissive", 3)):
            value = getattr(self, name)
            if value is None or not hasattr(value, "shape"):
                continue
            if value.ndim != 3 or value.shape[-1] != channels or min(value.shape[:2]) < 1:
                raise ValueError(f"Material.{name} must have shape (H, W, {channels}) with H, W >= 1, "
                                 f"got {tuple(value.shape)}")

    @classmethod
    def uniform(cls, base_color, metallic, roughness, size: int = 1) -> "Material":
        """A material with the same values in every texel of size x size maps; ``base_color`` is
        R, G, B or one grey value."""
        base = jnp.asarray(base_color, jnp.float32)
        if base.size not in (1, 3):
            raise ValueError(f"Material.uniform: base_color must be R, G, B or one value, got shape {base.shape}")
        if not (isinstance(size, (int, np.integer)) and size >= 1):
            raise ValueError(f"Material.uniform: size must be an integer >= 1, got {size!r}")
        base = jnp.broadcast_to(base.reshape(1, 1, -1), (size, size, 3))
        metal = jnp.full((size, size, 1), metallic, jnp.float32)
        rough = jnp.full((size, size, 1), roughness, jnp.float32)
        return cls(base, metal, rough)

    @property
    def resolution(self) -> tuple[int, int]:
        """(H, W) of the base color map."""
        return tuple(self.base_color.shape[:2])


class MaterialSample(eqx.Module):
    """Material values at a batch of points (what shading reads)."""

    base_color: Float[Array, "*batch 3"]
    metallic: Float[Array, "*batch 1"]
    roughness: Float[Array, "*batch 1"]
    normal: Optional[Float[Array, "*batch 3"]] = None
    occlusion: Optional[Float[Array, "*batch 1"]] = None
    emissive: Optional[Float[Array, "*batch 3"]] = None


def material_at(material: Material, uv: Float[ArrayLike, "*batch 2"], wrap: str = "repeat") -> MaterialSample:
    """Bilinearly sample every map of `material` at uv (glTF orientation)."""

    def sample(t):
        return None if t is None else sample_bilinear(t, uv, wrap)

    return MaterialSample(
        base_color=sample(material.base_color),
        metallic=sample(material.metallic),
        roughness=sample(material.roughness),
        normal=sample(material.normal),
        occlusion=sample(material.occlusion),
        emissive=sample(material.emissive),
    )


def apply_normal_map(
    normal: Float[ArrayLike, "*batch 3"],
    tangent: Float[ArrayLike, "*batch 4"],
    normal_ts: Float[ArrayLike, "*batch 3"],
    convention: str = "opengl",
) -> Float[Array, "*batch 3"]:
    """Perturb shading normals by a tangent-space normal map (glTF 2.0, normalTexture).

    n' = normalize(x T + y B + z N), with B = cross(N, T) * tangent.w (design convention) and
    y negated for DirectX-convention maps. A flat map (0, 0, 1) returns N unchanged.
    """
    if convention not in NORMAL_CONVENTIONS:
        raise ValueError(f"unknown normal map convention {convention!r}; expected one of {NORMAL_CONVENTIONS}")
    n = jnp.asarray(normal)
    t = jnp.asarray(tangent)
    m = jnp.asarray(normal_ts)
    t_xyz = t[..., :3]
    b = jnp.cross(n, t_xyz) * t[..., 3:4]
    y = -m[..., 1:2] if convention == "directx" else m[..., 1:2]
    return safe_normalize(m[..., 0:1] * t_xyz + y * b + m[..., 2:3] * n)
