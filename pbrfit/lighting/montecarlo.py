"""Monte Carlo: the reference environment integrator (its sample generators are `sampling`).

`monte_carlo_radiance` estimates the outgoing radiance

    L_o(v) = ∫_{H^2} f(v, l) L_env(l) (n·l) dω_l

with `pbrfit.physics.brdf.evaluate` as f·(n·l), so it integrates exactly the model the punctual lights
use. Two strategies are combined by multiple importance sampling with the balance heuristic
(Veach 1997; Pharr, Jakob & Humphreys, PBR 4th ed., section 2.2.3), one sample of each per step:

- the BRDF: GGX visible normals (Heitz, "Sampling the GGX Distribution of Visible Normals",
  JCGT 2018) for the specular lobe, mixed with cosine-weighted sampling for the diffuse lobe;
- the environment: texels chosen with probability proportional to luminance × solid angle,
  uniform in solid angle inside the texel (a piecewise-constant density on the sphere).

Each estimate f L / (p_brdf + p_env) is unbiased as long as the densities cover the integrand;
the environment density covers every texel the bilinear lookup can reach (3×3 max filter).

Occlusion: with a `pbrfit.lighting.visibility.Visibility` the integrand is f L V (n·l), V(p, l)
the point's visibility of direction l (its direction cell's shadow ray and its own horizon), the
same V the per-pixel integrals read. A shadow ray per sample, cast outside JAX, would take
2 × samples rays per point (2,048 at 1,024 samples: hundreds of millions for a capture), beyond
the numpy ray caster and slow even with embree; the cells take one ray per point and cell.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..physics import brdf
from .environment import (Environment, direction_to_uv, dot3, environment_lookup, from_environment_frame,
                          texel_solid_angles, to_environment_frame)
from ..physics.model import Model
from .brdf_lut import brdf_lut, lookup_brdf_lut
from .sampling import TINY, ggx_vndf_pdf, sample_cosine, sample_ggx_vndf, tangent_frame
from .visibility import Visibility, visible

__all__ = [
    "luminance",
    "EnvironmentSampler",
    "environment_sampler",
    "sample_environment",
    "environment_pdf",
    "monte_carlo_radiance",
    "default_lut", "hash32", "counter_uniforms", "sample_batch"]

#: Rec. 709 / sRGB luminance weights (linear RGB).
LUMINANCE = (0.2126, 0.7152, 0.0722)
#: Fraction of the mean luminance added to every texel's sampling weight, so that no direction
#: has zero density (black texels next to bright ones are still reached by the bilinear filter).
ENV_PDF_FLOOR = 1e-3
#: Smallest probability of either BRDF lobe when both are on: a lobe estimated to be dim is still
#: sampled now and then, so a bright environment feature in it is not left to chance alone.
LOBE_PROB_MIN = 0.1


def luminance(rgb: Float[Array, "*b 3"]) -> Float[Array, "*b"]:
    """Rec. 709 luminance of linear RGB."""
    return jnp.sum(rgb * jnp.asarray(LUMINANCE, rgb.dtype), axis=-1)


# --- environment sampling ----------------------------------------------------------------------

class EnvironmentSampler(NamedTuple):
    """A texel distribution over an equirect map (see `environment_sampler`)."""

    cdf: Float[Array, "HW"]             # cumulative texel probabilities, row-major
    texel_pdf: Float[Array, "H W"]      # solid-angle density inside each texel: P_ij / Ω_i
    cos_edges: Float[Array, "H1"]       # cos(theta) at the row edges, top to bottom


@jax.jit
def environment_sampler(radiance: Float[Array, "H W 3"]) -> EnvironmentSampler:
    """Luminance × solid-angle texel distribution of an equirect map (no gradient flows through it).

    Weight of texel (i, j) = (max of luminance over its 3×3 neighbourhood + floor) × Ω_i, where
    Ω_i is the texel's exact solid angle; inside a texel the density is uniform in solid angle,
    so the density of a direction is P_ij / Ω_i with no sin(theta) singularity at the poles.
    """
    radiance = jax.lax.stop_gradient(radiance)
    h, w, _ = radiance.shape
    lum = luminance(radiance)
    pad = jnp.pad(lum, ((1, 1), (0, 0)), mode="edge")
    pad = jnp.concatenate([pad[:, -1:], pad, pad[:, :1]], axis=1)
    m = jnp.max(jnp.stack([pad[1 + di:1 + di + h, 1 + dj:1 + dj + w]
                           for di in (-1, 0, 1) for dj in (-1, 0, 1)]), axis=0)
    m = m + ENV_PDF_FLOOR * jnp.mean(lum) + TINY
    omega = jnp.asarray(texel_solid_angles(h, w), radiance.dtype)
    p = m * omega
    p = p / jnp.sum(p)
    cdf = jnp.cumsum(p.reshape(-1))
    edges = jnp.asarray(np.cos(np.linspace(0.0, np.pi, h + 1)), radiance.dtype)
    return EnvironmentSampler(cdf, p / omega, edges)


@jax.jit
def sample_environment(sampler: EnvironmentSampler, u: Float[Array, "*b 3"]) -> tuple:
    """Environment-frame directions and their densities from three uniforms per sample."""
    cdf, pdf, edges = sampler
    h, w = pdf.shape
    idx = jnp.clip(jnp.searchsorted(cdf, u[..., 0] * cdf[-1], side="right"), 0, h * w - 1)
    i, j = idx // w, idx % w
    cos_t = edges[i] + u[..., 1] * (edges[i + 1] - edges[i])
    phi = ((j + u[..., 2]) / w - 0.5) * (2 * math.pi)
    sin_t = jnp.sqrt(jnp.clip(1.0 - cos_t * cos_t, 0.0, 1.0))
    d = jnp.stack([sin_t * jnp.sin(phi), cos_t, -sin_t * jnp.cos(phi)], axis=-1)
    return d, pdf[i, j]


@jax.jit
def environment_pdf(sampler: EnvironmentSampler, d_env: Float[Array, "*b 3"]) -> Float[Array, "*b"]:
    """Solid-angle density with which `sample_environment` draws environment-frame direction ``d_env``."""
    _, pdf, _ = sampler
    h, w = pdf.shape
    uv = direction_to_uv(d_env)
    i = jnp.clip(jnp.floor(uv[..., 1] * h).astype(jnp.int32), 0, h - 1)
    j = jnp.clip(jnp.floor(uv[..., 0] * w).astype(jnp.int32), 0, w - 1)
    return pdf[i, j]


# --- the reference integrator ------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def default_lut(model: Model = Model()) -> np.ndarray:
    """The (scale, bias) LUT multiple-scattering compensation uses by default: 64², 512 samples,
    of `model`'s own specular lobe (so the compensation restores that lobe's lost energy)."""
    return np.asarray(brdf_lut(64, 512, model.replace(ibl=None)))


def _as_column(x, like):
    x = jnp.asarray(x, like.dtype)
    return x[..., None] if x.ndim == like.ndim - 1 else x


#: Pixel-samples evaluated together in one step of the sample loop (bounds memory; amortises the
#: per-step overhead when there are few points).
MC_BATCH_ELEMENTS = 1 << 16


def hash32(x):
    """lowbias32 integer hash (C. Wellons, "Hash function prospector", 2018): uint32 -> uint32."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x7FEB352D)
    x = x ^ (x >> 15)
    x = x * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def counter_uniforms(seed, sample, dims: int, dtype):
    """(len(sample), *seed.shape, dims) uniforms in [0, 1): a counter-based hash of (seed, sample, dim).

    Cheaper to compile than threefry inside the sample loop (seconds less per model), and
    independent across points, samples and dimensions for Monte Carlo purposes.
    """
    c = sample.reshape((-1,) + (1,) * seed.ndim + (1,)) * jnp.uint32(dims) + jnp.arange(dims, dtype=jnp.uint32)
    x = hash32(seed[None, ..., None] ^ hash32(c))
    return (x >> 8).astype(dtype) * (1.0 / (1 << 24))


def sample_batch(samples: int, points: int) -> int:
    """Largest power-of-two divisor of ``samples`` with batch × points <= MC_BATCH_ELEMENTS (>= 1)."""
    b = 1
    while samples % (2 * b) == 0 and 2 * b * max(points, 1) <= MC_BATCH_ELEMENTS:
        b *= 2
    return b


@functools.partial(jax.jit, static_argnames=("model", "samples", "batch"))
def _mc(env, n, v, base_color, metallic, roughness, dfg, model, samples, batch, key, vis=None):
    sampler = environment_sampler(env.radiance)
    t, b = tangent_frame(n)
    nv = dot3(n, v)
    v_loc = jnp.stack([dot3(v, t), dot3(v, b), nv], -1)
    alpha = brdf.alpha_from_roughness(jnp.clip(roughness[..., 0], 0.0, 1.0))
    if not model.specular:
        p_spec = jnp.zeros_like(nv)
    elif model.diffuse == "none":
        p_spec = jnp.ones_like(nv)
    else:
        f0 = brdf.specular_f0(base_color, metallic, model)
        ws = luminance(brdf.f_schlick(jnp.clip(nv, 0.0, 1.0)[..., None], f0))
        wd = luminance(brdf.diffuse_color(base_color, metallic, model)) * (1.0 - ws)
        p_spec = LOBE_PROB_MIN + (1 - 2 * LOBE_PROB_MIN) * ws / jnp.maximum(ws + wd, TINY)
    to_world = lambda d: d[..., 0:1] * t + d[..., 1:2] * b + d[..., 2:3] * n
    up, rot = env.world_up, env.rotation_deg
    sg = jax.lax.stop_gradient

    def brdf_pdf(l):
        nl = dot3(n, l)
        nh, _ = brdf.half_vector_cosines(nv, nl, None, brdf.v_plus_l_sq(v, l))
        spec = ggx_vndf_pdf(nv, nh, alpha) if model.specular else 0.0
        return jnp.where(nl > 0, p_spec * spec + (1 - p_spec) * nl / math.pi, 0.0)

    def estimate(l, pdf_sum):
        nl = dot3(n, l)
        nh, vh = brdf.half_vector_cosines(nv, nl, None, brdf.v_plus_l_sq(v, l))
        f = brdf.evaluate_cosines(nv, nl, nh, vh, base_color, metallic, roughness, model, dfg)
        ok = pdf_sum > 0
        radiance = environment_lookup(env, l)
        if vis is not None:
            radiance = radiance * visible(vis, l, to_environment_frame(l, up, rot))[..., None]
        return jnp.where(ok[..., None], f * radiance / jnp.where(ok, pdf_sum, 1.0)[..., None], 0.0)

    kd = jax.random.key_data(key).reshape(-1).astype(jnp.uint32)
    points = jnp.arange(int(np.prod(n.shape[:-1])), dtype=jnp.uint32).reshape(n.shape[:-1])
    seed = hash32(kd[0] ^ hash32(kd[-1] ^ hash32(points)))

    def step(acc, k):
        u = counter_uniforms(seed, k * batch + jnp.arange(batch, dtype=jnp.uint32), 6, n.dtype)
        h = to_world(sample_ggx_vndf(v_loc, alpha, u[..., 1:3]))
        l_spec = 2 * dot3(v, h)[..., None] * h - v
        l_diff = to_world(sample_cosine(u[..., 1:3]))
        l_b = sg(brdf.safe_normalize(jnp.where((u[..., 0] < p_spec)[..., None], l_spec, l_diff)))
        pe_b = environment_pdf(sampler, to_environment_frame(l_b, up, rot))
        d_e, pe_e = sample_environment(sampler, u[..., 3:6])
        l_e = sg(from_environment_frame(d_e, up, rot))
        l = jnp.concatenate([l_b, l_e])
        est = estimate(l, sg(brdf_pdf(l) + jnp.concatenate([pe_b, pe_e])))
        return acc + jnp.sum(est, axis=0), None

    acc, _ = jax.lax.scan(step, jnp.zeros(n.shape[:-1] + (3,), n.dtype), jnp.arange(samples // batch, dtype=jnp.uint32))
    return acc / samples


def monte_carlo_radiance(env: Environment, n: Float[Array, "P 3"], v: Float[Array, "P 3"],
                         base_color: Float[Array, "P 3"], metallic: Float[Array, "P 1"],
                         roughness: Float[Array, "P 1"], model: Model = Model(), samples: int = 256,
                         key=None, dfg: Float[Array, "P 2"] | None = None,
                         visibility: Visibility | None = None) -> Float[Array, "P 3"]:
    """Unbiased estimate of the environment's reflected radiance, ∫ f L_env (n·l) dω_l, per point.

    ``samples`` steps, each one BRDF sample and one environment sample (2 × samples evaluations of
    `brdf.evaluate`), combined by the balance heuristic. metallic and roughness may be (P, 1) or
    (P,). With ``model.multiscatter`` the compensation uses ``dfg`` (split-sum scale and bias at
    (n·v, roughness)), by default `default_lut(model)`. Zero where n·v <= 0, like
    `brdf.evaluate`. Differentiable w.r.t. the material and the environment's pixels (the sampled
    directions and densities are held fixed, which keeps the gradient estimate unbiased).
    ``visibility``: the points' `pbrfit.lighting.visibility.Visibility` (one row per point, n of
    shape (P, 3)), or None: no occlusion (module docstring). Jitted; ``key`` defaults to
    ``PRNGKey(0)``.
    """
    key = jax.random.PRNGKey(0) if key is None else key
    n = jnp.asarray(n)
    base_color = jnp.asarray(base_color, n.dtype)
    metallic = _as_column(metallic, base_color)
    roughness = _as_column(roughness, base_color)
    if model.multiscatter and dfg is None:
        nv = jnp.clip(dot3(n, v), 0.0, 1.0)
        dfg = lookup_brdf_lut(jnp.asarray(default_lut(model), n.dtype), nv, roughness[..., 0])
    if visibility is not None and (n.ndim != 2 or visibility.num_points != n.shape[0]):
        raise ValueError(f"visibility: {visibility.num_points} rows for points of shape {n.shape}; expected one "
                         "row per point of (P, 3) normals")
    samples = int(samples)
    batch = sample_batch(samples, int(np.prod(n.shape[:-1])))
    return _mc(env, n, jnp.asarray(v, n.dtype), base_color, metallic, roughness, dfg, model, samples, batch, key,
               visibility)
