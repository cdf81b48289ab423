"""Monte Carlo integration of `pbrfit.lighting.pixel_ibl`'s lobe integrals I_k(r), per pixel, on a roughness grid.

Per pixel and sample step: one direction from the environment's luminance
distribution, one cosine-weighted direction, and one GGX visible-normal direction per roughness
level; specular lobes combine (visible normals, environment) and diffuse lobes (cosine,
environment) by the balance heuristic (Veach 1997). The steps are the points of the R_7
quasi-random sequence (Roberts 2018), shifted per pixel by a hashed offset (Cranley-Patterson
rotation): unbiased, and at 256 samples 1.3% off a 4,096-sample reference where independent
uniforms were 4% off.
Every level reuses the same points, so the integrals are smooth in roughness, and Lambert's
lobes, which do not depend on it, are the same number at every level.

With a `pbrfit.lighting.visibility.Visibility` the environment radiance of every sample direction
is multiplied by the point's visibility V(p, l) of that direction (its direction cell's shadow
ray and its own horizon), so the integrals are those of an occluded environment; where the
visibility carries a bounce, a blocked direction brings the radiance of the surface it hits
(`pbrfit.lighting.visibility.incoming`). The cosine and visible-normal techniques cover every
direction a lobe reaches, so the estimate stays unbiased where the environment technique never
samples that light.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..physics import brdf
from .environment import direction_to_uv, dot3, from_environment_frame, sample_equirect, to_environment_frame
from ..physics.model import Model
from .montecarlo import counter_uniforms, environment_pdf, environment_sampler, hash32, sample_environment
from .sampling import ggx_vndf_pdf, sample_cosine, sample_ggx_vndf, tangent_frame
from .brdf_lut import lookup_brdf_lut
from .visibility import incoming

__all__ = ["SPECULAR_LOBES", "DIFFUSE_LOBES", "integrate_lobes"]

#: The lobes that depend on roughness through D V, and Lambert's, which do not (`pbrfit.lighting.pixel_ibl.LOBES`).
SPECULAR_LOBES = ("dv", "dv_s", "dv_fd")
DIFFUSE_LOBES = ("lambert", "lambert_s", "lambert_fd")


def _dv(model: Model, nv, nl, nh, rough):
    """D V (n·l) of the model's specular lobe (zero unless n·v > 0 and n·l > 0)."""
    nvc, nlc = jnp.clip(nv, 0.0, 1.0), jnp.clip(nl, 0.0, 1.0)
    return jnp.where((nv > 0) & (nl > 0), brdf.specular_dv(model, nvc, nlc, nh, rough) * nlc, 0.0)


@functools.partial(jax.jit, static_argnames=("model", "lobes", "levels", "samples", "batch"))
def integrate_lobes(env, lut, n, v, first, seed, vis=None, *, model, lobes, levels, samples, batch):
    """(P, levels, len(lobes), C) lobe integrals I_k(r_j) of `pbrfit.lighting.pixel_ibl` for points with unit normals n and
    view directions v (P, 3): ``samples`` sample steps, ``batch`` at a time; pixel i's sequence is shifted by
    hashing ``first`` + i with ``seed``. ``lut`` is the split-sum LUT (read only for the dfg lobes); ``vis``
    the points' `pbrfit.lighting.visibility.Visibility` (P rows), or None: no occlusion. C = 3 (RGB), or 6 where
    ``vis`` carries a bounce: the environment's light that arrives, then the bounce's
    (`pbrfit.lighting.visibility.incoming`; the dfg lobes repeated in both)."""
    radiance = env.radiance
    sampler = environment_sampler(radiance)
    dtype = n.dtype
    t, b = tangent_frame(n)
    nv = dot3(n, v)                                                   # (P,)
    v_loc = jnp.stack([dot3(v, t), dot3(v, b), nv], -1)
    rough = jnp.linspace(0.0, 1.0, levels, dtype=dtype)               # (R,)
    alpha = brdf.alpha_from_roughness(rough)
    to_world = lambda d: d[..., 0:1] * t + d[..., 1:2] * b + d[..., 2:3] * n  # noqa: E731
    spec = [k for k in lobes if k in SPECULAR_LOBES]
    diff = [k for k in lobes if k in DIFFUSE_LOBES]
    burley = "burley" in lobes

    def arriving(rad, l, d):
        """Radiance ``rad`` of world directions l (environment frame: d) that reaches the points."""
        return rad if vis is None else incoming(vis, rad, l, d)

    def light(l):
        """Radiance arriving along world directions l and the environment technique's density there."""
        d = to_environment_frame(l, env.world_up, env.rotation_deg)
        return arriving(sample_equirect(radiance, direction_to_uv(d)), l, d), environment_pdf(sampler, d)

    def cosines(l):
        """(n·l, n·h, v·h) for directions l of shape (B, P, [R,] 3)."""
        extra = l.ndim - 2
        nv_ = nv.reshape(nv.shape + (1,) * (extra - 1))
        nl = dot3(n.reshape(n.shape[:1] + (1,) * (extra - 1) + (3,)), l)
        vl_sq = brdf.v_plus_l_sq(v.reshape(v.shape[:1] + (1,) * (extra - 1) + (3,)), l)
        nh, vh = brdf.half_vector_cosines(nv_, nl, None, vl_sq)
        return nl, nh, vh

    def spec_values(nl, nh, vh):
        """(B, P, R, Ks) specular lobe values at every level from the cosines of directions,
        (B, P, R) or (B, P, 1) (one direction for all levels)."""
        dv = _dv(model, nv[:, None], nl, nh, rough)
        s = brdf.f_schlick(vh, 0.0)
        out = {"dv": dv, "dv_s": dv * s}
        if "dv_fd" in spec:
            out["dv_fd"] = dv * brdf.f_dielectric(vh, model.ior)
        return jnp.stack([out[k] for k in spec], -1)

    def diff_values(l):
        """(B, P, Kd) r-independent diffuse lobe values and (B, P, R) Burley's, at directions l (B, P, 3)."""
        nl, _, vh = cosines(l)
        lit = (nv > 0) & (nl > 0)
        cos = jnp.where(lit, jnp.clip(nl, 0.0, 1.0), 0.0) / math.pi
        s = brdf.f_schlick(vh, 0.0)
        vals = {"lambert": cos, "lambert_s": cos * (1.0 - s)}
        if "lambert_fd" in diff:
            vals["lambert_fd"] = cos * (1.0 - brdf.f_dielectric(vh, model.ior))
        lam = jnp.stack([vals[k] for k in diff], -1) if diff else None
        bur = None
        if burley:
            fd = brdf.diffuse_burley(jnp.clip(nv, 0.0, 1.0)[:, None], jnp.clip(nl, 0.0, 1.0)[..., None],
                                     vh[..., None], rough)
            bur = fd * (math.pi * cos)[..., None]
        return lam, bur

    pixels = first + jnp.arange(n.shape[0], dtype=jnp.uint32)
    shift = counter_uniforms(hash32(seed ^ hash32(pixels)), jnp.zeros((1,), jnp.uint32), 7, jnp.float32)[0]  # (P, 7)
    safe = lambda x: jnp.where(x > 0, x, 1.0)  # noqa: E731
    channels = 6 if vis is not None and vis.bounce is not None else 3
    zeros_r = jnp.zeros(n.shape[:1] + (levels, channels), dtype)

    def step(acc, k):
        spec_acc, diff_acc, bur_acc = acc
        u = _lattice(shift, k * batch + jnp.arange(batch, dtype=jnp.uint32), dtype)   # (B, P, 7)
        d_e, pe_e = sample_environment(sampler, u[..., 0:3])
        l_e = from_environment_frame(d_e, env.world_up, env.rotation_deg)                # (B, P, 3)
        L_e = arriving(sample_equirect(radiance, direction_to_uv(d_e)), l_e, d_e)
        l_c = to_world(sample_cosine(u[..., 3:5]))
        L_c, pe_c = light(l_c)
        nl_e, nh_e, vh_e = cosines(l_e)
        nl_c, _, _ = cosines(l_c)
        pc = lambda nl: jnp.clip(nl, 0.0, 1.0) / math.pi  # noqa: E731
        if spec:
            v_lr = jnp.broadcast_to(v_loc[:, None, :], (n.shape[0], levels, 3))
            h = sample_ggx_vndf(v_lr, jnp.broadcast_to(alpha, v_lr.shape[:2]), u[..., None, 5:7])
            h = h[..., 0:1] * t[:, None] + h[..., 1:2] * b[:, None] + h[..., 2:3] * n[:, None]  # (B, P, R, 3)
            l_s = brdf.safe_normalize(2 * dot3(v[:, None, :], h)[..., None] * h - v[:, None, :])
            L_s, pe_s = light(l_s)
            nl_s, nh_s, vh_s = cosines(l_s)
            pv = lambda nl, nh: jnp.where(nl > 0, ggx_vndf_pdf(nv[:, None], nh, alpha), 0.0)  # noqa: E731
            w_s = L_s / safe(pv(nl_s, nh_s) + pe_s)[..., None]                              # (B, P, R, 3)
            e1 = (nl_e[..., None], nh_e[..., None], vh_e[..., None])                          # (B, P, 1)
            w_e = L_e[:, :, None, :] / safe(pv(*e1[:2]) + pe_e[..., None])[..., None]
            est = (spec_values(nl_s, nh_s, vh_s)[..., None] * w_s[..., None, :]
                   + spec_values(*e1)[..., None] * w_e[..., None, :])                          # (B, P, R, Ks, 3)
            spec_acc = spec_acc + jnp.sum(est, axis=0)
        if diff or burley:
            w_c = L_c / safe(pc(nl_c) + pe_c)[..., None]                                     # (B, P, 3)
            w_e2 = L_e / safe(pc(nl_e) + pe_e)[..., None]
            lam_c, bur_c = diff_values(l_c)
            lam_e, bur_e = diff_values(l_e)
            if diff:
                diff_acc = diff_acc + jnp.sum(lam_c[..., None] * w_c[..., None, :] + lam_e[..., None] * w_e2[..., None, :], 0)
            if burley:
                bur_acc = bur_acc + jnp.sum(bur_c[..., None] * w_c[:, :, None, :] + bur_e[..., None] * w_e2[:, :, None, :], 0)
        return (spec_acc, diff_acc, bur_acc), None

    acc0 = (jnp.zeros(n.shape[:1] + (levels, len(spec), channels), dtype),
            jnp.zeros(n.shape[:1] + (len(diff), channels), dtype),
            zeros_r)
    (spec_acc, diff_acc, bur_acc), _ = jax.lax.scan(step, acc0, jnp.arange(samples // batch, dtype=jnp.uint32))
    inv = 1.0 / (samples // batch * batch)
    parts = {}
    for i, name in enumerate(spec):
        parts[name] = spec_acc[:, :, i] * inv
    for i, name in enumerate(diff):
        parts[name] = jnp.broadcast_to(diff_acc[:, None, i] * inv, zeros_r.shape)
    if burley:
        parts["burley"] = bur_acc * inv
    if "dfg_scale" in lobes:
        dfg = lookup_brdf_lut(lut, jnp.clip(nv, 0.0, 1.0)[:, None], jnp.broadcast_to(rough, nv.shape + (levels,)))
        parts["dfg_scale"] = jnp.broadcast_to(dfg[..., 0:1], zeros_r.shape)
        parts["dfg_bias"] = jnp.broadcast_to(dfg[..., 1:2], zeros_r.shape)
    return jnp.stack([parts[name] for name in lobes], axis=2)


def _golden(d: int) -> np.ndarray:
    """The additive recurrence α_i = φ_d^-(i+1), i < d, φ_d the root of x^(d+1) = x + 1 (Roberts 2018, "R_d")."""
    phi = 2.0
    for _ in range(64):
        phi = (1.0 + phi) ** (1.0 / (d + 1))
    return np.mod(phi ** -np.arange(1, d + 1, dtype=np.float64), 1.0)


_ALPHA7 = _golden(7)


def _lattice(shift, sample, dtype):
    """(len(sample), P, 7) quasi-random points: the R_7 sequence, shifted per pixel by ``shift``
    (P, 7), uniform random (Cranley-Patterson rotation), so each pixel's estimate is unbiased and
    its samples are spread evenly (error falling faster than 1/sqrt(samples) on smooth integrands)."""
    # k α mod 1 in exact integer arithmetic (24-bit fixed point), then shifted
    step = jnp.asarray(np.round(_ALPHA7 * (1 << 24)).astype(np.uint32))
    frac = ((sample[:, None] * step[None, :]) & jnp.uint32((1 << 24) - 1)).astype(jnp.float32) * (1.0 / (1 << 24))
    u = frac[:, None, :] + shift[None]
    return (u - jnp.floor(u)).astype(dtype)
