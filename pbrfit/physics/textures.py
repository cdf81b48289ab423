"""Differentiable texture sampling in glTF orientation, and mip building.

glTF convention: texel row 0 is v = 0, and texel (i, j) of an (H, W) texture has its centre at
uv = ((j + 0.5) / W, (i + 0.5) / H). Bilinear filtering interpolates between the four texel
centres around a uv; ``wrap`` says what lies beyond the edge: ``"repeat"`` (glTF's default
sampler) or ``"clamp"`` (clamp-to-edge).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

__all__ = ["WRAPS", "bilinear_weights", "sample_bilinear", "downsample2x", "build_mips", "resample_map"]

WRAPS = ("repeat", "clamp")


def _wrap_index(k, n: int, wrap: str):
    if wrap == "repeat":
        return jnp.mod(k, n)
    return jnp.clip(k, 0, n - 1)


@functools.partial(jax.jit, static_argnames=("shape", "wrap"))  # eagerly: one compile per map size
def bilinear_weights(
    uv: Float[ArrayLike, "*batch 2"], shape: tuple[int, int], wrap: str = "repeat"
) -> tuple[Int[Array, "*batch 4"], Float[Array, "*batch 4"]]:
    """Flat texel indices (i * W + j) and bilinear weights of the four texels a uv reads.

    x = u W - 1/2, y = v H - 1/2 are continuous texel coordinates (texel centres at integers);
    the texels are (floor y + {0, 1}, floor x + {0, 1}) with weights (1 - fy, fy) x (1 - fx, fx).
    The weights sum to one and are differentiable in uv; the indices are not.
    """
    if wrap not in WRAPS:
        raise ValueError(f"unknown wrap {wrap!r}; expected one of {', '.join(WRAPS)}")
    height, width = shape
    uv = jnp.asarray(uv)
    x = uv[..., 0] * width - 0.5
    y = uv[..., 1] * height - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx = x - x0
    fy = y - y0
    j0 = x0.astype(jnp.int32)
    i0 = y0.astype(jnp.int32)
    j = jnp.stack([j0, j0 + 1, j0, j0 + 1], axis=-1)
    i = jnp.stack([i0, i0, i0 + 1, i0 + 1], axis=-1)
    j = _wrap_index(j, width, wrap)
    i = _wrap_index(i, height, wrap)
    weights = jnp.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=-1)
    return i * width + j, weights


def sample_bilinear(
    texture: Float[ArrayLike, "H W C"], uv: Float[ArrayLike, "*batch 2"], wrap: str = "repeat"
) -> Float[Array, "*batch C"]:
    """Bilinearly filtered texture values at uv (glTF orientation); differentiable in both."""
    texture = jnp.asarray(texture)
    height, width, channels = texture.shape
    idx, w = bilinear_weights(uv, (height, width), wrap)
    texels = texture.reshape(height * width, channels)[idx]  # (*batch, 4, C)
    return jnp.sum(texels * w[..., None].astype(texture.dtype), axis=-2)


def downsample2x(texture: Float[ArrayLike, "H W C"]) -> Float[Array, "h w C"]:
    """Box-filter a texture to half size (ceil for odd sizes; the edge texel is repeated)."""
    t = jnp.asarray(texture)
    h, w = t.shape[0], t.shape[1]
    t = jnp.pad(t, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    return 0.25 * (t[0::2, 0::2] + t[1::2, 0::2] + t[0::2, 1::2] + t[1::2, 1::2])


def build_mips(texture: Float[ArrayLike, "H W C"]) -> list[Float[Array, "h w C"]]:
    """The mip chain [level 0 = texture, ..., 1x1] by repeated 2x box filtering."""
    levels = [jnp.asarray(texture)]
    while levels[-1].shape[0] > 1 or levels[-1].shape[1] > 1:
        levels.append(downsample2x(levels[-1]))
    return levels


def resample_map(values, shape: tuple[int, int]):
    """An (H, W, C) map at another (h, w), as a host array: where H and W are whole multiples of
    h and w, each texel is the mean of its block of the map (a mip level's box filter: a map
    upsampled by repeating texels comes back exactly); otherwise ``jax.image.resize``, linear,
    antialiased (a widened triangle filter) when it shrinks."""
    v = np.asarray(values, np.float32)
    (h0, w0), (h, w) = v.shape[:2], tuple(shape)
    if (h0, w0) == (h, w):
        return v
    if h0 % h == 0 and w0 % w == 0:
        return v.reshape(h, h0 // h, w, w0 // w, *v.shape[2:]).mean(axis=(1, 3))
    return np.asarray(jax.image.resize(v, (h, w) + v.shape[2:], "linear"))
