"""Sample generators on the hemisphere and their densities: the low-discrepancy Hammersley set,
a tangent frame about a normal, GGX normals and visible normals (Heitz, "Sampling the GGX
Distribution of Visible Normals", JCGT 2018) and cosine-weighted directions. The split sum's LUT
(`brdf_lut`), the per-pixel lobe integrals and the Monte Carlo reference (`montecarlo`) draw from
them.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..physics import brdf

__all__ = ["hammersley", "tangent_frame", "sample_ggx_ndf", "sample_ggx_vndf", "ggx_vndf_pdf", "sample_cosine"]

#: Squared length below which a vector is treated as zero (the VNDF basis at normal incidence; a
#: density's floor in `montecarlo`).
TINY = 1e-12


def hammersley(n: int) -> np.ndarray:
    """(n, 2) Hammersley points in [0, 1)^2: (i / n, radical inverse base 2 of i)."""
    i = np.arange(n, dtype=np.uint64)
    bits = np.zeros(n, dtype=np.float64)
    scale, k = 0.5, i.copy()
    for _ in range(32):
        bits += (k & 1).astype(np.float64) * scale
        k >>= np.uint64(1)
        scale *= 0.5
    return np.stack([(np.arange(n) + 0.5) / n, bits], axis=-1)


def tangent_frame(n: Float[Array, "*b 3"]) -> tuple:
    """(t, b) with (t, b, n) right-handed orthonormal; branchless (Duff et al., JCGT 2017)."""
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = jnp.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    c = x * y * a
    t = jnp.stack([1.0 + sign * x * x * a, sign * c, -sign * x], axis=-1)
    b = jnp.stack([c, sign + y * y * a, -y], axis=-1)
    return t, b


@jax.jit
def sample_ggx_ndf(u: Float[Array, "*b 2"], alpha) -> Float[Array, "*b 3"]:
    """Local half vector with density D(h) (n·h) (Walter et al. 2007, eq. 35-36): the prefilter's sampler.

    cos^2 theta_h = (1 - u1) / (1 + (alpha^2 - 1) u1), phi = 2 pi u2.
    """
    a2 = jnp.square(jnp.maximum(alpha, brdf.MIN_ALPHA))
    c2 = (1.0 - u[..., 0]) / (1.0 + (a2 - 1.0) * u[..., 0])
    s = jnp.sqrt(jnp.clip(1.0 - c2, 0.0, 1.0))
    phi = 2 * math.pi * u[..., 1]
    return jnp.stack([s * jnp.cos(phi), s * jnp.sin(phi), jnp.sqrt(c2)], axis=-1)


@jax.jit
def sample_ggx_vndf(v_local: Float[Array, "*b 3"], alpha, u: Float[Array, "*b 2"]) -> Float[Array, "*b 3"]:
    """Local half vector distributed as GGX's visible normals for view ``v_local`` (Heitz 2018, listing 1).

    Density of h: G1(v) max(0, v·h) D(h) / (n·v); of l = reflect(v, h): see `ggx_vndf_pdf`.
    """
    a = jnp.maximum(alpha, brdf.MIN_ALPHA)[..., None]
    vh = brdf.safe_normalize(jnp.concatenate([a * v_local[..., :2], v_local[..., 2:]], axis=-1))
    lensq = vh[..., 0] ** 2 + vh[..., 1] ** 2
    ok = lensq > TINY
    inv = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, lensq, 1.0)), 0.0)
    t1 = jnp.where(ok[..., None], jnp.stack([-vh[..., 1] * inv, vh[..., 0] * inv, jnp.zeros_like(inv)], -1),
                   jnp.array([1.0, 0.0, 0.0], vh.dtype))
    t2 = jnp.cross(vh, t1)
    r = jnp.sqrt(u[..., 0])
    phi = 2 * math.pi * u[..., 1]
    p1, p2 = r * jnp.cos(phi), r * jnp.sin(phi)
    s = 0.5 * (1.0 + vh[..., 2])
    p2 = (1.0 - s) * jnp.sqrt(jnp.clip(1.0 - p1 * p1, 0.0, 1.0)) + s * p2
    p3 = jnp.sqrt(jnp.clip(1.0 - p1 * p1 - p2 * p2, 0.0, 1.0))
    nh = p1[..., None] * t1 + p2[..., None] * t2 + p3[..., None] * vh
    return brdf.safe_normalize(jnp.concatenate([a * nh[..., :2], jnp.maximum(nh[..., 2:], 0.0)], axis=-1))


@jax.jit
def ggx_vndf_pdf(n_dot_v, n_dot_h, alpha):
    """Solid-angle density of l = reflect(v, h), h ~ VNDF: G1(v) D(h) / (4 n·v) (Heitz 2018, eq. 17)."""
    nv = jnp.clip(n_dot_v, brdf.COS_MIN, 1.0)
    return brdf.g1_smith_ggx(nv, alpha) * brdf.d_ggx(n_dot_h, alpha) / (4.0 * nv)


def sample_cosine(u: Float[Array, "*b 2"]) -> Float[Array, "*b 3"]:
    """Local direction with density cos(theta) / pi (Malley's method)."""
    r = jnp.sqrt(u[..., 0])
    phi = 2 * math.pi * u[..., 1]
    return jnp.stack([r * jnp.cos(phi), r * jnp.sin(phi), jnp.sqrt(jnp.clip(1.0 - u[..., 0], 0.0, 1.0))], -1)
